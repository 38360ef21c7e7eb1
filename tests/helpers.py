"""Small scene builders shared by the tests."""

import copy
import json
import math
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "benchmarks" / "data"


def tank_2d(width=0.2, depth=0.2, height=0.3, spacing=0.01, **fluid):
    d = {
        "simulation": {"dimension": 2, "duration_s": 1.0},
        "fluid": {"spacing_m": spacing, "eos": {"speed_of_sound_m_s": 20.0}, "viscosity": {"artificial_alpha": 0.3},
                  "regions": [{"box_min_m": [0.0, 0.0], "box_max_m": [width, depth]}]},
        "tank": {"box_min_m": [0.0, 0.0], "box_max_m": [width, height]},
    }
    for k, v in fluid.items():
        d["fluid"][k] = v
    return d


def martin_moyce(series: str) -> np.ndarray:
    rows = [l.split(",") for l in (DATA / "martin_moyce_1952.csv").read_text().splitlines()
            if l and not l.startswith("#") and not l.startswith("series")]
    return np.array([[float(t), float(v)] for s, t, v in rows if s == series])


def with_changes(d: dict, **paths) -> dict:
    """Copy of a scene dict with dotted-path changes: with_changes(d, **{"fluid.kernel": "muller"})."""
    d = copy.deepcopy(d)
    for path, value in paths.items():
        node = d
        keys = path.split(".")
        for k in keys[:-1]:
            node = node.setdefault(k, {})
        node[keys[-1]] = value
    return d


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def to_toml(d: dict) -> str:
    """A scene dict as TOML text (inline tables; NaN and inf as TOML writes them)."""
    return "".join(f"{json.dumps(k)} = {_toml_value(v)}\n" for k, v in d.items())
