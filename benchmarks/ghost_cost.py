"""Part ``ghost_cost``: basic vs Ghost SPH on the same scene: cost per step and the share spent on
ghost sampling.

Each method runs ``repeats`` timed blocks of ``steps`` steps, basic and ghost alternating (both at the
same flow time; a drift of the machine hits both); the fastest block is reported (wall time, and on the
CPU also the process CPU time, which a busy shared machine disturbs less). Both are timed step by step
(``Simulation.step``: plain launches); on a GPU the basic step is also timed as ``Simulation.step_many``
runs it (CUDA graph chunks, which the ghost step, with its host reads, cannot use), and with ``busy`` the
GPU time of each kernel of the ghost step is recorded (CUDA events). A case: scene file, spacing (None:
the scene's), steps; ``sampler``/``attempts``/``rounds`` set ``[fluid.ghost]`` (None: the scene's).
"""

from __future__ import annotations

import time
from pathlib import Path

from benchmarks.common import ROOT, log

_2D = [("ghost_dam_break_case1.toml", None, 100), ("ghost_dam_break_case2.toml", None, 100),
       ("ghost_dam_break_case3.toml", None, 100)]
CONFIG = {
    "quick": dict(ghost_cases=_2D + [("drop_zero_g_3d.toml", None, 10)], ghost_repeats=2, ghost_sampler=None,
                  ghost_busy=False),
    "full": dict(ghost_cases=_2D + [("ghost_dam_break_case1.toml", 0.0025, 50), ("ghost_dam_break_case1.toml", 0.000625, 20),
                                    ("drop_zero_g_3d.toml", None, 50), ("dam_break_3d.toml", 0.02, 30),
                                    ("dam_break_3d.toml", 0.01, 10)],
                 ghost_repeats=5, ghost_sampler=None, ghost_busy=True),
}


def make(scene_path, method, device, spacing, warm=20, attempts=None, rounds=None, sampler=None):
    """A Simulation of the scene with fluid.method ``method``, stepped ``warm`` times."""
    import warp as wp

    import rockwave

    d = rockwave.load_scene(scene_path).raw
    d["fluid"]["method"] = method
    if method == "basic":
        d["fluid"].pop("ghost", None)  # ghost settings with the basic method are a SceneError
    d.setdefault("output", {})["usd"] = ""
    if spacing:
        d["fluid"]["spacing_m"] = spacing
    for key, value in (("attempts", attempts), ("rounds", rounds), ("sampler", sampler)):
        if value and method == "ghost":
            d["fluid"].setdefault("ghost", {})[key] = value
    sim = rockwave.Simulation(rockwave.parse_scene(d, str(scene_path), Path(scene_path).parent), device=device)
    for _ in range(warm):
        sim.step()
    wp.synchronize_device(sim.device)
    return sim


def block(sim, steps, profile=False):
    """Wall and process CPU time per step over ``steps`` steps, and (profile) the ghost sampling's share."""
    import warp as wp

    s = sim.fluid_solver
    ghost = hasattr(s, "sample_seconds")
    if ghost:
        s.profile, s.sample_seconds = profile, 0.0
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(steps):
        sim.step()
    wp.synchronize_device(sim.device)
    w, c = (time.perf_counter() - t0) / steps, (time.process_time() - c0) / steps
    share = s.sample_seconds / steps / w if ghost and profile else 0.0
    if ghost:
        s.profile = False
    return w, c, share


def busy(sim, steps) -> dict:
    """GPU time per step of each kernel of ``sim``'s step (CUDA events) against its wall time per step."""
    import warp as wp

    wp.synchronize_device(sim.device)
    t0 = time.perf_counter()
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    for _ in range(steps):
        sim.step()
    res = wp.timing_end()
    wall = (time.perf_counter() - t0) / steps
    by = {}
    for r in res:
        by[r.name] = by.get(r.name, 0.0) + r.elapsed / steps
    top = dict(sorted(by.items(), key=lambda kv: -kv[1])[:10])
    return {"wall_ms": 1e3 * wall, "gpu_busy_ms": sum(by.values()), "launches_per_step": len(res) / steps, "top_ms": top}


def case(scene: str, device: str, steps: int, spacing=None, repeats=1, sampler=None, attempts=None, rounds=None,
         profile_busy=False) -> dict:
    """One scene, basic against ghost (see the module docstring)."""
    import warp as wp

    path = ROOT / "scenes" / scene
    basic = make(path, "basic", device, spacing)
    ghost = make(path, "ghost", device, spacing, attempts=attempts, rounds=rounds, sampler=sampler)
    cuda = wp.get_device(ghost.device).is_cuda
    tb = cb = tg = cg = tgraph = float("inf")
    share = 0.0
    for _ in range(repeats):
        w, c, _ = block(basic, steps)
        tb, cb = min(tb, w), min(cb, c)
        if cuda:
            t0 = time.perf_counter()
            basic.step_many(steps)
            wp.synchronize_device(basic.device)
            tgraph = min(tgraph, (time.perf_counter() - t0) / steps)
        w, c, sh = block(ghost, steps, profile=not cuda)
        if w < tg:
            share = sh
        tg, cg = min(tg, w), min(cg, c)
    if cuda:  # profiling synchronises inside the step: its own block, after the timed ones
        share = block(ghost, steps, profile=True)[2]
    s = ghost.fluid_solver
    r = {"scene": scene, "spacing_m": ghost.fluid.spacing, "dim": ghost.scene.dim, "fluid": basic.fluid.n_fluid,
         "ghosts": int(s.n_ghost), "sampler": getattr(s, "sampler", None), "steps": steps, "repeats": repeats,
         "basic_ms": 1e3 * tb, "ghost_ms": 1e3 * tg, "ratio": tg / tb, "sampling_share": share}
    if cuda:
        r.update(basic_graph_ms=1e3 * tgraph, ratio_graph=tg / tgraph)
        if profile_busy:
            r["ghost_busy"] = busy(ghost, steps)
    else:
        r.update(basic_cpu_ms=1e3 * cb, ghost_cpu_ms=1e3 * cg, ratio_cpu=cg / cb)
    return r


def run(dev: str, cfg: dict) -> dict:
    rows = []
    for scene, spacing, steps in cfg["ghost_cases"]:
        try:
            r = case(scene, dev, steps, spacing, cfg["ghost_repeats"], cfg["ghost_sampler"], profile_busy=cfg["ghost_busy"])
        except Exception as e:  # recorded; the other scenes still run
            r = {"scene": scene, "spacing_m": spacing, "error": f"{type(e).__name__}: {e}"[:300]}
        rows.append(r)
        if "error" in r:
            log(f"  {scene}: {r['error']}")
        else:
            log(f"  {scene} {r['spacing_m']:g} m: {r['fluid']} fluid, {r['ghosts']} ghosts; basic {r['basic_ms']:.3f} ms, "
                f"ghost {r['ghost_ms']:.3f} ms, ratio {r['ratio']:.2f}, sampling {r['sampling_share']:.0%}")
    return {"cases": rows}
