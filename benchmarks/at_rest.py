"""Part ``at_rest``: water at rest in a tank, per fidelity level (issue 19's first target: wall and floor
pressure, corners included, within 2% of rho0 g d; particle speed RMS below 0.1% of c0; no drift of the surface).

A tank of water at rest (2D: d = 0.3 m deep, 0.6 m wide; 3D: a 0.3 m cube of water), c0 = 20 m/s, the scene's
default time step, started from the hydrostatic density, run for ``t`` seconds. Read at the end:

- pressure gauges (Shepard-interpolated fluid pressure, as scenes place them) at the floor corner, mid-floor and
  mid-depth on a side wall, each over rho0 g (level - z) (``corner``, ``floor_mid``, ``side_mid``; 1 is exact),
  averaged over the last tenth of the run (20 reads: the water's acoustic ringing, rho0 c0 |v| ~ 1% of rho0 g d
  at a speed RMS of 1e-4 c0, is not hydrostatics; a pressure sensor averages too); the last single read in
  ``*_last``;
- with Adami walls, the wall particles of the first layer below one kernel support from the surface: the largest
  |p_b - rho0 g (level - z_b)| / (rho0 g d) of their pressure averaged as the gauges (``wall_error_max``, where
  it is: ``wall_error_at``; the last read: ``wall_error_max_last``);
- ``speed_rms_c0``: the fluid's RMS speed / c0; ``drift_spacings``: the surface level's change in spacings (the
  level: the mean height of the particles within half a spacing of the highest, plus half a spacing).

The same tank in small is tests/test_walls.py's; this part measures it at the issue's size and duration.
"""

from __future__ import annotations

import math
import time

import numpy as np

# cases: [dimension, layers over the depth, simulated seconds]; levels: [fluid.fidelity, Courant number or None
# for the default, optionally {other [fluid] keys}]
# UNIFORM: the standard level's start and walls before they became its defaults (uniform lattice, wall mass)
UNIFORM = {"packed_start": False, "wall_volume": "mass"}
CONFIG = {
    "quick": dict(at_rest_cases=[[2, 20, 0.2], [3, 8, 0.1]], at_rest_levels=[["standard", None]]),
    "full": dict(at_rest_cases=[[2, 100, 2.0], [3, 30, 2.0]],
                 at_rest_levels=[["standard", None], ["standard", None, UNIFORM], ["standard", 0.4], ["waves", None],
                                 ["draft", None]]),
}
READS = 20  # gauge reads over the last tenth of the run
DEPTH, C0, RHO0, G = 0.3, 20.0, 1000.0, 9.81


def tank_scene(dim: int, layers: int, t_end: float, level: str, cfl: float | None = None, keys: dict | None = None) -> dict:
    """The scene of one case: water filling the lower 0.3 m of a tank (2D 0.6 m wide, 3D 0.3 m square)."""
    width = 2 * DEPTH if dim == 2 else DEPTH
    lo, hi = [0.0] * dim, [width] * (dim - 1) + [DEPTH]
    gauges = [{"name": "corner", "kind": "pressure", "position_m": [0.0] * dim},
              {"name": "floor_mid", "kind": "pressure", "position_m": [0.5 * width] * (dim - 1) + [0.0]},
              {"name": "side_mid", "kind": "pressure", "position_m": [0.0] + [0.5 * width] * (dim - 2) + [0.5 * DEPTH]}]
    sim = {"dimension": dim, "duration_s": t_end} | ({"cfl_number": cfl} if cfl else {})
    return {"simulation": sim,
            "fluid": {"spacing_m": DEPTH / layers, "fidelity": level, "rest_density_kg_m3": RHO0,
                      "eos": {"speed_of_sound_m_s": C0}, "regions": [{"box_min_m": lo, "box_max_m": hi}], **(keys or {})},
            "tank": {"box_min_m": lo, "box_max_m": [width] * (dim - 1) + [DEPTH + 0.1]},
            "output": {"gauges": gauges}}


def surface_level(positions: np.ndarray, dim: int, spacing: float) -> float:
    z = positions[:, dim - 1]
    return float(z[z > z.max() - 0.5 * spacing].mean()) + 0.5 * spacing


def measure(device: str, dim: int, layers: int, t_end: float, level: str, cfl: float | None = None,
            keys: dict | None = None) -> dict:
    import warp as wp

    import rockwave

    sim = rockwave.Simulation(rockwave.parse_scene(tank_scene(dim, layers, t_end, level, cfl, keys)), device=device)
    s = sim.fluid.spacing
    level0 = surface_level(sim.positions(), dim, s)
    steps0 = sim.steps
    wp.synchronize_device(sim.device)
    t0 = time.perf_counter()
    sim.advance(0.9 * t_end)
    wall = time.perf_counter() - t0
    names = ("corner", "floor_mid", "side_mid")
    reads, walls = [], []
    from benchmarks.harness import fluid_settings

    settings = fluid_settings(sim)
    adami = settings.get("boundary") == "adami"
    for k in range(READS):  # the last tenth, read READS times (the reads' own time is not counted)
        t1 = time.perf_counter()
        sim.advance((t_end - sim.time) / (READS - k))
        wp.synchronize_device(sim.device)
        wall += time.perf_counter() - t1
        g = sim.gauges()
        reads.append([float(g.get(n, math.nan)) for n in names])
        if adami:
            walls.append(sim.state.wall_pressure.numpy().astype(np.float64).copy())
    x = sim.positions()
    top = surface_level(x, dim, s)
    speed = np.linalg.norm(sim.velocities(), axis=1)
    rec = dict(dim=dim, layers=layers, spacing_m=s, level=level, cfl=cfl, keys=dict(keys or {}), particles=int(sim.n_fluid), simulated_s=float(sim.time),
               steps=int(sim.steps - steps0), wall_s=wall, wall_per_sim_s=wall / max(sim.time, 1e-12),
               finite=bool(np.all(np.isfinite(x))), speed_rms_c0=float(np.sqrt(np.mean(speed ** 2)) / C0),
               drift_spacings=(top - level0) / s, reads=READS, read_window_s=0.1 * t_end)
    mean, last = np.mean(reads, axis=0), reads[-1]
    for i, (name, z) in enumerate(zip(names, (0.0, 0.0, 0.5 * DEPTH))):
        rec[name] = float(mean[i]) / (RHO0 * G * (top - z))
        rec[f"{name}_last"] = float(last[i]) / (RHO0 * G * (top - z))
    rec["gauge_error_max"] = max(abs(rec[n] - 1.0) for n in names)
    rec["gauge_error_max_last"] = max(abs(rec[f"{n}_last"] - 1.0) for n in names)
    rec["fluid"] = settings
    if adami:
        width = 2 * DEPTH if dim == 2 else DEPTH
        nf = sim.fluid.n_fluid
        xb = np.asarray(sim.fluid.initial_positions[nf:])
        pw = np.mean(walls, axis=0)[: len(xb)]
        up = dim - 1
        first = np.all((xb[:, :up] > -s) & (xb[:, :up] < width + s), axis=1) & (xb[:, up] > -s) & (xb[:, up] < top)
        first &= np.any(np.abs(xb[:, :up] + 0.5 * s) < 1e-6, axis=1) | (np.abs(xb[:, up] + 0.5 * s) < 1e-6)
        first &= xb[:, up] < top - sim.fluid.support_radius
        exact = RHO0 * G * (top - xb[first, up])
        err = np.abs(pw[first] - exact) / (RHO0 * G * DEPTH)
        k = int(np.argmax(err))
        rec.update(wall_particles=int(first.sum()), wall_error_max=float(err[k]),
                   wall_error_at=[round(float(v), 4) for v in xb[first][k]],
                   wall_error_max_last=float(np.max(np.abs(walls[-1][: len(xb)][first] - exact)) / (RHO0 * G * DEPTH)))
    return rec


def run(dev: str, cfg: dict) -> dict:
    from benchmarks.common import log

    rows = []
    for level, cfl, *keys in cfg["at_rest_levels"]:
        for dim, layers, t_end in cfg["at_rest_cases"]:
            r = measure(dev, int(dim), int(layers), float(t_end), level, cfl, keys[0] if keys else None)
            log(f"  {level:9s} C {cfl or 'default'} {keys[0] if keys else ''} {dim}D {layers:4d} layers {r['particles']:7d} particles {t_end:g} s: corner {r['corner']:.4f} "
                f"floor {r['floor_mid']:.4f} side {r['side_mid']:.4f} (rho0 g d); walls {r.get('wall_error_max', math.nan):.4f}; "
                f"last read {r['gauge_error_max_last']:.4f}; speed RMS {r['speed_rms_c0']:.2e} c0; drift {r['drift_spacings']:+.3f} spacing; {r['wall_per_sim_s']:.2f} s/s")
            rows.append(r)
    return {"rows": rows}
