"""Small scene builders shared by the tests."""

import copy
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
