"""Basic vs Ghost SPH on the same scene: cost per step and the share spent on ghost sampling.

    python benchmarks/ghost_bench.py --device cpu --scene scenes/ghost_dam_break_case1.toml --steps 200
    python benchmarks/ghost_bench.py --device cuda:0 --spacing 0.0025     # GPU, finer

Each method runs ``--repeats`` timed blocks of ``--steps`` steps; the fastest block is reported (wall
time, and on the CPU also the process CPU time, which a busy shared machine disturbs less).
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


def run(scene_path, method, device, steps, spacing, warm=20, repeats=1, attempts=None, rounds=None):
    d = rockwave.load_scene(scene_path).raw
    d["fluid"]["method"] = method
    if spacing:
        d["fluid"]["spacing_m"] = spacing
    for key, value in (("attempts", attempts), ("rounds", rounds)):
        if value:
            d["fluid"].setdefault("ghost", {})[key] = value
    sim = rockwave.Simulation(rockwave.parse_scene(d, str(scene_path), Path(scene_path).parent), device=device)
    for _ in range(warm):
        sim.step()
    wp.synchronize_device(sim.device)
    s = sim.fluid_solver
    wall, cpu, share = float("inf"), float("inf"), 0.0
    # On a GPU the sampling share is timed in an extra block: the profile mode synchronises inside the
    # step, which the timed blocks must not do. On the CPU (synchronous anyway) every block profiles.
    cuda = wp.get_device(sim.device).is_cuda
    for rep in range(repeats + (1 if cuda and method == "ghost" else 0)):
        profiling = method == "ghost" and (not cuda or rep == repeats)
        if method == "ghost":
            s.profile, s.sample_seconds = profiling, 0.0
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(steps):
            sim.step()
        wp.synchronize_device(sim.device)
        w, c = (time.perf_counter() - t0) / steps, (time.process_time() - c0) / steps
        if profiling:
            share = s.sample_seconds / steps / w
        if rep < repeats:
            wall = min(wall, w)
            cpu = min(cpu, c)
    if method == "ghost":
        s.profile = False
    s_sim[0] = sim
    return sim.fluid.n_fluid, wall, share, getattr(s, "n_ghost", 0), cpu, s


s_sim = [None]  # the last simulation run (for --busy)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scene", default=str(ROOT / "scenes" / "ghost_dam_break_case1.toml"))
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--spacing", type=float, default=None)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--attempts", type=int, default=None, help="darts per cell and round (default: the scene's)")
    ap.add_argument("--rounds", type=int, default=None, help="passes over the phases (default: the scene's)")
    ap.add_argument("--busy", action="store_true", help="GPU: time each kernel of the ghost step (CUDA events)")
    ap.add_argument("--darts", choices=["auto", "parallel", "serial"], default="auto",
                    help="dart throwing: parallel screens + light phase launches, or the per-cell serial "
                         "throw_darts (default: parallel on CUDA, serial on the CPU)")
    ap.add_argument("--read-counts", action="store_true",
                    help="parallel darts: read the per-phase active-cell counts back every step (exact launch sizes) "
                         "even where the host bound is small")
    ap.add_argument("--plain-launches", action="store_true",
                    help="ghost step with plain wp.launch calls instead of recorded, replayed launches")
    a = ap.parse_args()
    wp.config.quiet = True
    from rockwave.ghost import GhostFluidSolver

    GhostFluidSolver.parallel_darts = {"auto": None, "parallel": True, "serial": False}[a.darts]
    if a.read_counts:
        GhostFluidSolver.parallel_bound_max = 0
    if a.plain_launches:
        GhostFluidSolver.recorded_launches = False
    nb, tb, _, _, cb, _ = run(a.scene, "basic", a.device, a.steps, a.spacing, repeats=a.repeats)
    ng, tg, share, ghosts, cg, s = run(a.scene, "ghost", a.device, a.steps, a.spacing, repeats=a.repeats,
                                       attempts=a.attempts, rounds=a.rounds)
    print(f"scene {Path(a.scene).name} device {a.device} fluid {nb} ghosts(last step) {ghosts} darts {a.darts}: "
          f"{s.attempts} x {s.rounds} rounds (GPU: {s.n_phases * s.rounds} dart launches per step)")
    print(f"basic {tb * 1e3:.3f} ms/step  ghost {tg * 1e3:.3f} ms/step  ratio {tg / tb:.2f}  sampling share of ghost step {share:.0%}")
    if not wp.get_device(a.device).is_cuda:
        print(f"process CPU time: basic {cb * 1e3:.3f} ms/step  ghost {cg * 1e3:.3f} ms/step  ratio {cg / cb:.2f}")
    elif a.busy:
        # GPU time per kernel of the ghost step (CUDA events) against its wall time
        sim = s_sim[0]
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
