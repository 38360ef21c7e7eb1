"""Scaling of one scene over MPI ranks (rockwave/sim/distributed.py; docs/mpi.md).

The 3D dam break (scenes/dam_break_3d.toml, gauges off) at the spacing that gives about ``--particles``
fluid particles in all (strong scaling) or per rank (``--weak``), advanced by ``--steps`` times the initial
dt (adaptive steps, as in a run) after ``--warmup`` steps (kernels loaded); the timing ends after a barrier
ends with a barrier and leaves out the gather on rank 0. Rank 0 prints one JSON line: ranks, particles, seconds, particle-steps/s and the
particle-steps/s per rank (parallel efficiency = that over the one-rank figure of the same size).

    mpiexec -n 4 python -m benchmarks.distributed --particles 8e6 --device cuda
    mpiexec -n 4 python -m benchmarks.distributed --particles 8e6 --weak --device cuda
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from benchmarks.common import ROOT


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.distributed")
    ap.add_argument("--particles", type=float, required=True, help="fluid particles in all (or per rank with --weak)")
    ap.add_argument("--weak", action="store_true", help="--particles per rank")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--device", default="cuda")
    a = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    import rockwave
    from rockwave.sim.distributed import DistributedSimulation, require_mpi

    comm = require_mpi().COMM_WORLD
    size = comm.Get_size()
    scene = rockwave.load_scene(ROOT / "scenes" / "dam_break_3d.toml")
    scene.output["gauges"] = []
    s0 = float(scene.fluid["spacing_m"])
    volume = sum(float((lambda lo, hi: (hi[0] - lo[0]) * (hi[1] - lo[1]) * (hi[2] - lo[2]))(r["box_min_m"], r["box_max_m"]))
                 for r in scene.fluid["regions"])
    target = a.particles * (size if a.weak else 1)
    scene.fluid["spacing_m"] = min(s0, (volume / target) ** (1.0 / 3.0))
    sim = DistributedSimulation(scene, device=a.device, comm=comm)
    if sim.rank != 0:
        sim.serve()
        return 0
    dt = sim.dt
    for _ in range(a.warmup):
        sim.step(dt)
    sim.gather()  # a collective: every rank is between steps here
    sim.timings.clear()
    t0 = time.perf_counter()
    sim.advance(a.steps * dt, gather=False)  # adaptive steps (dt may shrink as the water speeds up)
    t = time.perf_counter() - t0
    n = sim.fluid.n_fluid
    print(json.dumps({"ranks": size, "device": sim.device, "particles": n, "spacing_m": scene.fluid["spacing_m"],
                      "steps": sim.steps - a.warmup, "seconds": t, "particle_steps_per_s": n * (sim.steps - a.warmup) / t,
                      "per_rank": n * (sim.steps - a.warmup) / t / size, "weak": a.weak,
                      "rank0_owned": len(sim.dfluid.rows), "rank0_halo": sim.dfluid.n_halo,
                      "rank0_seconds": {k: round(v, 4) for k, v in sim.timings.items()}}))
    sim.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
