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


def kernel_values(sim, r2: np.ndarray) -> np.ndarray:
    """W(r) of the scene's kernel (kernels/sph/fluid.py kernel_w, through sph.lattice_moments) at squared distances r2."""
    import warp as wp

    from rockwave.kernels.sph import fluid as sph

    pts = np.zeros((len(r2) + 1, 3), np.float32)
    pts[1:, 0] = np.sqrt(np.asarray(r2, np.float64))
    dev = sim.fluid.device
    w = wp.zeros(len(pts), dtype=float, device=dev)
    gx = wp.zeros(len(pts), dtype=float, device=dev)
    wp.launch(sph.lattice_moments, dim=len(pts), inputs=[wp.array(pts, dtype=wp.vec3, device=dev), sim.fluid.params],
              outputs=[w, gx], device=dev)
    return w.numpy()[1:].astype(np.float64)


def gauge_level_reference(sim, name: str) -> float:
    """A height gauge from its definition (rockwave/sim/readers.py Gauges), in numpy: the water fraction
    phi_f / (1 - phi_s) (0 where 1 - phi_s < 0.2) on the gauge's samples, the bed where it first reaches 0.5
    going up, the reading where it next drops below 0.5 (linear between samples); NaN when dry."""
    g, m = sim.readers._gauges, sim.fluid
    up, H, nf = sim.scene.dim - 1, m.support_radius, m.n_fluid
    gg = sim.scene.output.gauges[g.names.index(name)]
    pos = np.array(list(gg.position_m) + [0.0] * (3 - len(gg.position_m)))
    z = g.z0 + g.dz * np.arange(g.n_samples)
    x = sim.state.x.numpy().astype(np.float64)
    mass = m.particle_mass.numpy().astype(np.float64)
    vol = np.concatenate([mass[:nf] / sim.state.rho.numpy().astype(np.float64), mass[nf:] / m.params.rest_density])

    def fraction(sel):
        d = x[sel] - pos
        h2 = (np.delete(d, up, axis=1) ** 2).sum(1)
        near = h2 < H * H
        zj, h2, v = x[sel][near, up], h2[near], vol[sel][near]
        r2 = h2[None, :] + (z[:, None] - zj[None, :]) ** 2
        w = np.zeros_like(r2)
        inside = r2 < H * H
        w[inside] = kernel_values(sim, r2[inside])
        return (w * v[None, :]).sum(1)

    phi_f = fraction(np.arange(nf))
    phi_s = fraction(np.arange(nf, len(x))) if len(x) > nf else np.zeros_like(z)
    open_ = 1.0 - phi_s
    phi = np.where(open_ < 0.2, 0.0, phi_f / np.where(open_ < 0.2, 1.0, open_))
    wet = np.flatnonzero(phi >= 0.5)
    if not len(wet):
        return float("nan")
    above = np.flatnonzero(phi[wet[0]:] < 0.5)
    if not len(above):
        return float(z[-1])
    k = wet[0] + above[0]
    return float(z[k - 1] + (phi[k - 1] - 0.5) / (phi[k - 1] - phi[k]) * g.dz)
