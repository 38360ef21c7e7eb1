"""Part ``energy_budget``: the energy budget of every shipped scene over its first second (issue 37's target: no
growth beyond the bound).

Every scene of the scenes package (rockwave.app.cli.shipped_scenes) runs for ``energy_duration`` simulated seconds
(its own duration where shorter) from its own start, reading the budget (rockwave/sim/energy.py, docs/outputs.md
"The energy budget") every ``energy_read_s``. Recorded per scene:

- ``max_growth_j`` / ``max_growth_fraction``: the largest growth (total - start - input work) and its share of the
  scene's releasable energy ``scale_j``; ``check``: the budget's verdict ("ok" below ENERGY_GROWTH_LIMIT = 1% of
  the scale, "exceeded", or "open: ..." where kinematic blocks touch moving blocks);
- ``max_rise_fraction``: the largest rise of the total less the input work above its lowest value so far, over the
  scale (energy made after earlier dissipation, e.g. at a landing, which the growth from the start can hide);
- ``input_work_j``, ``dissipated_j``, the particle and block counts, the spacing run and ``spacing_note``.

CPU size: a scene whose fluid exceeds ``energy_max_particles[dim - 2]`` particles runs at a coarser spacing,
spacing x (n / cap)^(1/dim) (``spacing_note`` says so; the scene's own spacing otherwise). A scene still running
after ``energy_wall_limit_s`` of wall time stops there: ``t_reached_s`` says how far it got. A scene that cannot
be built at the coarser spacing is run at its own. Errors are recorded per scene.

    python -m benchmarks run --only energy_budget --device cpu --suite quick     # the CPU run of docs/notes.md
    python -m benchmarks run --only energy_budget --device cuda:0 --suite full   # every scene at its own size
    python -m benchmarks run --only energy_budget --set 'energy_scenes=["hydrostatic_tank"]'
"""

from __future__ import annotations

import math
import time
import tomllib
import warnings

CONFIG = {
    # quick: CPU size (2D up to 4,000, 3D up to 5,000 fluid particles), 4 min of wall per scene at most
    "quick": dict(energy_scenes=None, energy_duration=1.0, energy_read_s=0.01, energy_max_particles=[4000, 5000],
                  energy_wall_limit_s=240.0),
    # full: every scene at its own resolution (GPU)
    "full": dict(energy_scenes=None, energy_duration=1.0, energy_read_s=0.01, energy_max_particles=None,
                 energy_wall_limit_s=540.0),
}


def _set(d: dict, path: str, value) -> None:
    node = d
    keys = path.split(".")
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value


def scene_at_size(path, device: str, cap) -> tuple:
    """(Scene, note, fluid particles estimated) at CPU size: coarser where the fluid exceeds cap[dim - 2]."""
    from rockwave.build import preflight
    from rockwave.scene.format import parse_scene

    data = tomllib.loads(path.read_text())
    scene = parse_scene(data, path, path.parent)
    est = preflight.check_scene(scene, device)
    n = est.fluid_particles
    if cap is None or scene.fluid is None or n <= cap[scene.dim - 2]:
        return scene, "own", n
    s = float(scene.fluid.spacing_m)
    s2 = s * (n / cap[scene.dim - 2]) ** (1.0 / scene.dim)
    _set(data, "fluid.spacing_m", s2)
    try:
        coarse = parse_scene(data, path, path.parent)
        est2 = preflight.check_scene(coarse, device)
    except Exception as e:  # e.g. a region thinner than the coarse spacing: run the scene's own
        return scene, f"own (coarsening to {s2:.4g} m failed: {type(e).__name__}: {str(e).splitlines()[0][:120]})", n
    return coarse, f"coarsened from {s:g} m ({n:,} particles) to {s2:.4g} m", est2.fluid_particles


def _size(path, device: str, cap) -> tuple:
    try:
        scene, _, n = scene_at_size(path, device, cap)
        return (0, n * (2 if scene.dim == 3 else 1), path.stem)
    except Exception:
        return (1, 0, path.stem)


def run_scene(path, device: str, cfg: dict) -> dict:
    from rockwave import Simulation

    t0 = time.perf_counter()
    scene, note, n_est = scene_at_size(path, device, cfg["energy_max_particles"])
    row = {"scene": path.stem, "dim": scene.dim, "spacing_m": float(scene.fluid.spacing_m) if scene.fluid else None,
           "spacing_note": note}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sim = Simulation(scene, device=device)
        b = sim.energy
        b.measure()
        row.update(fluid_particles=sim.n_fluid, blocks=int(len(b.rock)), build_s=time.perf_counter() - t0,
                   multirate=bool(sim.multirate))
        t_end = min(float(cfg["energy_duration"]), float(scene.simulation.duration_s))
        dt_read = float(cfg["energy_read_s"])
        low, rise, rise_t, warned = b.start["total_j"], 0.0, 0.0, False  # of total - input work
        t1 = time.perf_counter()
        n = max(1, math.ceil(t_end / dt_read - 1e-9))
        for k in range(n):
            sim.advance(min(dt_read, t_end - sim.time))
            r = b.measure()
            net = r["total_j"] - r["input_work_j"]
            low = min(low, net)
            if net - low > rise:
                rise, rise_t = net - low, r["time_s"]
            warned = warned or b.exceeded(r)
            if time.perf_counter() - t1 > cfg["energy_wall_limit_s"] and k < n - 1:
                row["stopped"] = "wall limit"
                break
    s = b.summary()
    row.update(t_reached_s=float(sim.time), wall_s=time.perf_counter() - t1, steps=int(sim.steps), units=s["units"],
               scale_j=s["scale_j"], limit_j=s["limit_j"], input_work_j=s["input_work_j"], dissipated_j=s["dissipated_j"],
               max_growth_j=s["max_growth_j"], max_growth_time_s=s["max_growth_time_s"],
               max_growth_fraction=s["max_growth_fraction"], max_rise_j=rise, max_rise_time_s=rise_t,
               max_rise_fraction=rise / s["scale_j"], check=s["check"],
               warnings=sorted({str(w.message).splitlines()[0][:160] for w in caught}))
    return row


def run(device: str, cfg: dict, save=None) -> dict:
    from benchmarks.common import log
    from rockwave.app.cli import shipped_scenes

    paths = shipped_scenes()
    if cfg.get("energy_scenes"):
        want = list(cfg["energy_scenes"])
        paths = sorted((p for p in paths if p.stem in want), key=lambda p: want.index(p.stem))
    else:  # the cheapest first (the fluid's particle count at the size run), so a cut-off run keeps the most scenes
        paths = sorted(paths, key=lambda p: _size(p, device, cfg["energy_max_particles"]))
    out = {"scenes": [], "bound": "growth <= 1% of the scene's releasable energy (rockwave/sim/energy.py)"}
    for p in paths:
        log(f"  {p.stem}")
        try:
            r = run_scene(p, device, cfg)
            log(f"    {r['check']}: growth {r['max_growth_fraction']:.3g} of {r['scale_j']:.4g} {r['units']}, "
                f"t {r['t_reached_s']:.3g} s, {r['wall_s']:.0f} s wall ({r['spacing_note']})")
        except Exception as e:  # recorded; the other scenes still run
            r = {"scene": p.stem, "error": f"{type(e).__name__}: {str(e)[:300]}"}
            log(f"    error: {r['error']}")
        out["scenes"].append(r)
        if save is not None:
            save(out)
    return out


def merge(a: dict, b: dict) -> dict:
    """Two records' rows of this part (``python -m benchmarks merge``): b's row of a scene replaces a's."""
    rows = {r["scene"]: r for r in a.get("scenes", [])}
    rows.update({r["scene"]: r for r in b.get("scenes", [])})
    return dict(a, scenes=list(rows.values()))
