"""Part ``ghost_accuracy``: accuracy of basic SPH and Ghost SPH (both ghost samplers) on the report's
scenes (scenes/ghost_dam_break_case1..3.toml; the full suite at their 0.01 m, the quick one at the tests'
0.03 m). For each method (``basic``, ``tile``, ``darts``) and the same scene settings otherwise:

- case 1 (column against the left wall): surge front Z = (max x + dx/2) / a against Martin & Moyce
  (1952, n^2 = 1) at their times up to T = t sqrt(g/a) = 1.62 (before the far wall): mean and largest
  relative error;
- case 2 (column in the middle): at t = 0.2 s the centroid's offset from the tank centre, the
  difference between the two fronts' distances from their walls (both / dx), and the mean distance
  from each particle's mirror image to the nearest particle / dx;
- case 3 (case 1 with an obstacle), to the scene's end: energy per mass E = g y + v^2/2 + e(rho) (Tait
  elastic energy, as in tests/test_ghost.py) sampled every 0.1 s, as max E/E(0) and the largest rise
  between samples / E(0); particles thrown over the open top of the 3.5 m tank (seen above it at a check
  every 0.02 s: the run-up jet at 0.01 m, basic SPH too) and their highest point; of the others the
  deepest past a tank face or into the obstacle / dx (a wall leak).

``ghost_repeats`` runs each case and method several times (on a GPU runs differ: atomics order);
``ghost_set``: (dotted key, value) scene changes (for ghost runs only where the key is under fluid.ghost).
Wall time per case is recorded (the runs go through Simulation.advance, so it includes the host reads of
the checks).
"""

from __future__ import annotations

import time

import numpy as np

from benchmarks.common import ROOT, log
from benchmarks.harness import martin_moyce

CONFIG = {
    "quick": dict(ghost_spacing=0.03, ghost_methods=["basic", "tile", "darts"], ghost_accuracy_cases=[1, 2, 3],
                  ghost_repeats_accuracy=1, ghost_set=[]),
    "full": dict(ghost_spacing=None, ghost_methods=["basic", "tile", "darts"], ghost_accuracy_cases=[1, 2, 3],
                 ghost_repeats_accuracy=3, ghost_set=[]),
}
TANK_LO, TANK_HI = np.array([0.0, 0.0]), np.array([1.6, 3.5])
OBSTACLE_LO, OBSTACLE_HI = np.array([1.0, 0.0]), np.array([1.12, 0.12])


def simulation(case: int, method: str, spacing: float | None, device: str, changes=()):
    """Scene ghost_dam_break_case<case>.toml with fluid.method basic, or ghost with the given sampler;
    ``changes``: (dotted key, value) pairs applied to the scene (ghost runs only for fluid.ghost keys)."""
    import rockwave

    path = ROOT / "scenes" / f"ghost_dam_break_case{case}.toml"
    d = rockwave.load_scene(path).raw
    for key, value in changes:
        if method == "basic" and key.startswith("fluid.ghost."):
            continue
        node = d
        *parents, last = key.split(".")
        for k in parents:
            node = node.setdefault(k, {})
        node[last] = value
    if spacing:
        d["fluid"]["spacing_m"] = spacing
    if method == "basic":
        d["fluid"]["method"] = "basic"
        d["fluid"].pop("ghost", None)  # ghost settings with the basic method are a SceneError
    else:
        d["fluid"]["method"] = "ghost"
        d["fluid"].setdefault("ghost", {})["sampler"] = method
    d["output"]["usd"] = ""
    return rockwave.Simulation(rockwave.parse_scene(d, str(path), path.parent), device=device)


def elastic_energy(params, rho: np.ndarray) -> np.ndarray:
    """Specific elastic energy [J/kg] of the Tait EOS as the solver applies it: e(rho) = integral from rho0
    to rho of p/rho'^2 drho', p = B((rho/rho0)^gamma - 1), clipped at 0 below rho0 when
    clamp_negative_pressure is set (the default; then no energy is stored in tension). Used by
    tests/test_ghost.py too."""
    B, g, rho0 = float(params.eos_b), float(params.eos_gamma), float(params.rest_density)
    assert params.eos == 0, "Tait EOS expected"
    if params.clamp_negative:
        rho = np.maximum(rho, rho0)
    return B * ((rho ** (g - 1) - rho0 ** (g - 1)) / ((g - 1) * rho0**g) + 1.0 / rho - 1.0 / rho0)


def case1_front(sim, a: float = 0.6) -> dict:
    dx = sim.fluid.spacing
    errors = []
    for T, Z in martin_moyce("front_n2_1"):
        if T > 1.62:
            break
        sim.advance(T / np.sqrt(9.81 / a) - sim.time)
        z = (sim.positions()[:, 0].max() + 0.5 * dx) / a
        errors.append(z / Z - 1.0)
    e = np.array(errors)
    return {"front_error_mean": float(e.mean()), "front_error_max": float(e[np.argmax(np.abs(e))]), "samples": len(e)}


def case2_symmetry(sim, t: float = 0.2) -> dict:
    from scipy.spatial import cKDTree

    dx = sim.fluid.spacing
    sim.advance(t)
    x = sim.positions()
    mirror = x.copy()
    mirror[:, 0] = 1.6 - mirror[:, 0]
    return {"centroid_dx": float((x[:, 0].mean() - 0.8) / dx),
            "front_difference_dx": float((x[:, 0].min() - (1.6 - x[:, 0].max())) / dx),
            "mirror_distance_dx": float(cKDTree(x).query(mirror)[0].mean() / dx)}


def case3_energy(sim) -> dict:
    dx = sim.fluid.spacing
    n = sim.fluid.n_fluid
    w = sim.fluid.particle_mass.numpy()[:n].astype(np.float64)
    w /= w.sum()

    def energy():
        x, v = sim.positions()[:, :2], sim.velocities()[:, :2]
        e = 9.81 * x[:, 1] + 0.5 * (v**2).sum(axis=1) + elastic_energy(sim.fluid.params, sim.densities())
        return float(np.sum(w * e))

    e = [energy()]
    over_top = np.zeros(n, dtype=bool)
    depth = np.zeros(n)
    highest = 0.0
    end = sim.scene.simulation.duration_s
    k = 0
    while sim.time < end - 1e-9:
        sim.advance(min(0.02, end - sim.time))
        k += 1
        x = sim.positions()[:, :2]
        if not np.isfinite(x).all():
            return {"finite": False}
        over_top |= x[:, 1] > TANK_HI[1]
        highest = max(highest, float(x[:, 1].max()))
        past = np.maximum(np.max(TANK_LO - x, axis=1), np.max(x - TANK_HI, axis=1))
        inside = np.min(np.minimum(x - OBSTACLE_LO, OBSTACLE_HI - x), axis=1)
        depth = np.maximum(depth, np.maximum(past, inside))
        if k % 5 == 0 or sim.time >= end - 1e-9:
            e.append(energy())
    e = np.array(e)
    leak = depth[~over_top]
    return {"finite": True, "E0": float(e[0]), "max_E_over_E0": float(e.max() / e[0]),
            "largest_rise_over_E0": float(np.diff(e).max() / e[0]), "over_top": int(over_top.sum()),
            "highest_m": highest, "deepest_past_wall_dx": float(leak.max() if len(leak) else 0.0) / dx,
            "passed_obstacle": bool(sim.positions()[:, 0].max() > OBSTACLE_HI[0])}


def run(dev: str, cfg: dict) -> dict:
    rows = []
    changes = [tuple(kv) for kv in cfg["ghost_set"]]
    for case in cfg["ghost_accuracy_cases"]:
        for method in [m for m in cfg["ghost_methods"] for _ in range(cfg["ghost_repeats_accuracy"])]:
            sim = simulation(case, method, cfg["ghost_spacing"], dev, changes)
            t0 = time.perf_counter()
            res = {1: case1_front, 2: case2_symmetry, 3: case3_energy}[case](sim)
            res.update(case=case, method=method, spacing=sim.fluid.spacing, n_fluid=sim.n_fluid,
                       wall_s=time.perf_counter() - t0, device=str(sim.device))
            rows.append(res)
            shown = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in res.items()
                     if k not in ("case", "method", "device", "spacing")}
            log(f"  case {case} {method:6s} {shown}")
    return {"rows": rows}
