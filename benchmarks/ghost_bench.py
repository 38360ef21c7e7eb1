"""Basic vs Ghost SPH on the same scene: cost per step and the share spent on ghost sampling.

    python benchmarks/ghost_bench.py --device cpu --scene scenes/ghost_dam_break_case1.toml --steps 200
    python benchmarks/ghost_bench.py --device cuda:0 --spacing 0.0025     # GPU, finer

Each method runs ``--repeats`` timed blocks of ``--steps`` steps, basic and ghost alternating; the fastest
block is reported (wall time, and on the CPU also the process CPU time, which a busy shared machine
disturbs less). Both are timed step by step (``Simulation.step``: plain launches); on a GPU the basic
step is also timed as ``Simulation.step_many`` runs it (CUDA graph chunks, which the ghost step,
with its host reads, cannot use).
``--attempts`` / ``--rounds`` override ``[fluid.ghost]`` (darts per cell and round, passes over the
phases: a GPU step launches ``3^dim x rounds`` dependent dart kernels).
"""

import argparse
import time
from pathlib import Path

import numpy as np
import warp as wp

import rockwave

ROOT = Path(__file__).resolve().parent.parent


def make(scene_path, method, device, spacing, warm=20, attempts=None, rounds=None, sampler=None):
    """A Simulation of the scene with ``method``, stepped ``warm`` times."""
    d = rockwave.load_scene(scene_path).raw
    d["fluid"]["method"] = method
    if spacing:
        d["fluid"]["spacing_m"] = spacing
    for key, value in (("attempts", attempts), ("rounds", rounds), ("sampler", sampler)):
        if value:
            d["fluid"].setdefault("ghost", {})[key] = value
    sim = rockwave.Simulation(rockwave.parse_scene(d, str(scene_path), Path(scene_path).parent), device=device)
    for _ in range(warm):
        sim.step()
    wp.synchronize_device(sim.device)
    return sim


def block(sim, steps, profile=False):
    """Wall and process CPU time per step over ``steps`` steps, and (profile) the ghost sampling's share."""
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


def run(scene_path, device, steps, spacing, repeats=1, attempts=None, rounds=None, sampler=None):
    """Basic and ghost on the same scene, timed in alternating blocks (basic, ghost, basic, ...: both at
    the same flow time, and a drift of the machine hits both); fastest block of each. On a GPU the
    sampling share comes from one extra profiled ghost block (profiling synchronises inside the step,
    which the timed blocks must not do); on the CPU (synchronous anyway) every ghost block profiles."""
    basic = make(scene_path, "basic", device, spacing)
    ghost = make(scene_path, "ghost", device, spacing, attempts=attempts, rounds=rounds, sampler=sampler)
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
    if cuda:
        share = block(ghost, steps, profile=True)[2]
    return basic, ghost, tb, cb, tg, cg, share, tgraph


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scene", default=str(ROOT / "scenes" / "ghost_dam_break_case1.toml"))
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--spacing", type=float, default=None)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--attempts", type=int, default=None, help="darts per cell and round (default: the scene's)")
    ap.add_argument("--rounds", type=int, default=None, help="passes over the phases (default: the scene's)")
    ap.add_argument("--sampler", choices=["tile", "darts"], default=None,
                    help="fluid.ghost.sampler (default: the scene's, else tile; darts with persistent ghosts)")
    ap.add_argument("--busy", action="store_true", help="GPU: time each kernel of the ghost step (CUDA events)")
    ap.add_argument("--darts", choices=["auto", "parallel", "serial"], default="auto",
                    help="dart throwing: parallel screens + light phase launches, or the per-cell serial "
                         "throw_darts (default: parallel on CUDA, serial on the CPU)")
    ap.add_argument("--read-counts", action="store_true",
                    help="parallel darts: read the per-phase active-cell counts back every step (exact launch sizes) "
                         "even where the host bound is small")
    ap.add_argument("--plain-launches", action="store_true",
                    help="ghost step with plain wp.launch calls instead of recorded, replayed launches")
    ap.add_argument("--no-graph-darts", action="store_true",
                    help="parallel darts: launch a round's dart kernels one by one instead of replaying them as one CUDA graph")
    ap.add_argument("--conflict-span", type=int, choices=[1, 5], default=None,
                    help="parallel darts: dart_conflicts threads per cell of the 5^d block (1) or per row of 5 cells (5)")
    a = ap.parse_args()
    wp.config.quiet = True
    from rockwave.ghost import GhostFluidSolver

    GhostFluidSolver.parallel_darts = {"auto": None, "parallel": True, "serial": False}[a.darts]
    if a.read_counts:
        GhostFluidSolver.parallel_bound_max = 0
    if a.plain_launches:
        GhostFluidSolver.recorded_launches = False
    if a.no_graph_darts:
        GhostFluidSolver.graph_darts = False
    if a.conflict_span:
        GhostFluidSolver.conflict_span = a.conflict_span
    basic, ghost, tb, cb, tg, cg, share, tgraph = run(a.scene, a.device, a.steps, a.spacing, repeats=a.repeats,
                                                      attempts=a.attempts, rounds=a.rounds, sampler=a.sampler)
    s = ghost.fluid_solver
    nb, ghosts = basic.fluid.n_fluid, s.n_ghost
    if s.sampler == "tile":
        how = f"sampler tile ({s.tile_k}^{s.model.dim} cells, r {s.r / s.model.spacing:.2f} dx)"
    else:
        how = (f"sampler darts {a.darts}: {s.attempts} x {s.rounds} rounds (GPU: {s.n_phases * s.rounds} dart launches "
               f"per step)")
    print(f"scene {Path(a.scene).name} device {a.device} fluid {nb} ghosts(last step) {ghosts} {how}")
    print(f"basic {tb * 1e3:.3f} ms/step  ghost {tg * 1e3:.3f} ms/step  ratio {tg / tb:.2f}  sampling share of ghost step {share:.0%}")
    if not wp.get_device(a.device).is_cuda:
        print(f"process CPU time: basic {cb * 1e3:.3f} ms/step  ghost {cg * 1e3:.3f} ms/step  ratio {cg / cb:.2f}")
    else:
        print(f"basic in CUDA graph chunks (step_many) {tgraph * 1e3:.3f} ms/step  ghost/that {tg / tgraph:.2f}")
    if wp.get_device(a.device).is_cuda and a.busy:
        # GPU time per kernel of the ghost step (CUDA events) against its wall time
        sim = ghost
        wp.synchronize_device(a.device)
        t0 = time.perf_counter()
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        for _ in range(a.steps):
            sim.step()
        res = wp.timing_end()
        wall = (time.perf_counter() - t0) / a.steps
        by = {}
        for r in res:
            by[r.name] = by.get(r.name, 0.0) + r.elapsed / a.steps
        print(f"ghost step wall {wall * 1e3:.3f} ms, GPU busy {sum(by.values()):.3f} ms, {len(res) / a.steps:.1f} launches/step")
        for k, v in sorted(by.items(), key=lambda kv: -kv[1])[:10]:
            print(f"  {v:8.3f} ms  {k}")


if __name__ == "__main__":
    main()
