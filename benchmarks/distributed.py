"""Scaling of one scene over MPI ranks, one GPU each (rockwave/sim/distributed.py; docs/mpi.md), against the plain
one-GPU Simulation.

The 3D dam break (scenes/dam_break_3d.toml, gauges off) at the spacing that gives about ``--particles`` fluid
particles in all (strong scaling) or per rank (``--weak``). The ranks advance ``--steps`` times the initial dt
(adaptive steps, as in a run) after ``--warmup`` steps (kernels loaded); the timing ends with a barrier and leaves
out the gather on rank 0. Then rank 0 alone runs the plain one-GPU ``Simulation`` (CUDA graphs, reorders: the
fastest one-GPU path) on the reference size: the same scene (strong) or the per-rank size (weak), same steps.
Efficiency is always against that plain run, never against the distributed code on one rank:

    strong: speedup = rate(N ranks) / rate(plain, same scene);   efficiency = speedup / N
    weak:   efficiency = rate(N ranks) / (N x rate(plain, per-rank size))

Rank 0 prints one JSON line and writes it to benchmarks/results/<date>-<device>-distributed-<mode>-<N>ranks.json
(and a row to the markdown table beside it): particle-steps/s, the halo exchange's seconds per step and share of
the step (rank 0: the per-step halo refresh + the halo densities inside the step), the relayouts (list rebuilds:
migration, new halos, new lists), the transport that ran, and rank 0's device bytes per particle.

    mpiexec -n 2 python -m benchmarks.distributed --particles 16e6 --device cuda            # strong
    mpiexec -n 2 python -m benchmarks.distributed --particles 8e6 --weak --device cuda      # weak
    mpiexec -n 2 python -m benchmarks.distributed --particles 1e6 --device cuda --compare   # 2 GPUs vs 1, 100 steps
    python -m benchmarks.distributed --particles 2e4 --device cpu --steps 20 --no-plain     # a smoke run
    mpiexec -n 2 python -m benchmarks.distributed --particles 2e5 --device cpu --memory --steps 3  # bytes per rank

``--memory``: each rank's peak bytes while it builds the scene and while it steps: the Warp allocations
(wp.ScopedMemoryTracker's peak: the GPU's memory on CUDA, host memory on the CPU) and the process's peak resident
host memory (ru_maxrss), per particle of the whole scene and per particle the rank owns, for the slab build
(default) or every rank building the whole scene (``--whole-build``, the earlier start); run both in separate
launches (a process's peak never goes down). ``--outputs``: with the scene's gauges, rank 0 also reads one frame's
surface and gauges from its host copy of the water (HostWater, on its device a chunk at a time), inside the peak;
rank 0's record then has the count of device arrays as long as the scene's water outside its own step arrays
(``whole_scene_device_arrays``: 0 once the scene is larger than a chunk, 2^21 particles) and the chunk buffers' bytes.
"""

from __future__ import annotations

import argparse
import gc
import json
import sys
import time
from datetime import date
from pathlib import Path

from benchmarks.common import RESULTS, ROOT, commit, device_name, write_json


def _scene(particles: float, name: str = "dam_break_3d", gauges: bool = False):
    """The shipped scene ``name`` with the spacing that gives about ``particles`` in its fluid boxes (never coarser
    than its own), the hazard summary off and its gauges off unless ``gauges``."""
    import rockwave

    scene = rockwave.load_scene(ROOT / "scenes" / f"{name}.toml")
    if not gauges:
        scene.output["gauges"] = []
    scene.hazard = None
    s0 = float(scene.fluid["spacing_m"])
    volume = sum((hi[0] - lo[0]) * (hi[1] - lo[1]) * (hi[2] - lo[2])
                 for lo, hi in ((r["box_min_m"], r["box_max_m"]) for r in scene.fluid["regions"]))
    scene.fluid["spacing_m"] = min(s0, (volume / particles) ** (1.0 / 3.0))
    return scene


def _plain_rate(particles: float, device: str, steps: int, warmup: int, name: str = "dam_break_3d") -> dict:
    """The plain one-GPU Simulation on the scene of ``particles``: particle-steps/s over ``steps`` steps."""
    import warp as wp

    from rockwave.sim.simulation import Simulation

    sim = Simulation(_scene(particles, name), device=device)
    dt = sim.dt
    sim.advance(warmup * dt)
    wp.synchronize_device(sim.device)
    s0, t0 = sim.steps, time.perf_counter()
    sim.advance(steps * dt)
    wp.synchronize_device(sim.device)
    t = time.perf_counter() - t0
    n = sim.fluid.n_fluid
    out = {"particles": n, "steps": sim.steps - s0, "seconds": t, "particle_steps_per_s": n * (sim.steps - s0) / t}
    del sim
    gc.collect()
    return out


def _compare(sim, a, comm) -> int:
    """Rank 0 of --compare: positions, velocities, densities of the ranks against the plain one-GPU Simulation after
    the same simulated time (the same adaptive steps: dt from the extrema reduced over ranks), and the yardstick:
    the plain run against itself with every initial fluid coordinate moved by one float32 ulp; total momentum
    (equal masses: sum of v) and particle count (mass) of both."""
    import numpy as np

    from rockwave.sim.simulation import Simulation

    duration = a.steps * sim.dt
    t0 = time.perf_counter()
    sim.advance(duration)
    t_ranks = time.perf_counter() - t0
    two = dict(x=sim.positions(), v=sim.velocities(), rho=sim.densities(), steps=sim.steps)
    report = sim.run_report()
    sim.close()
    del sim
    gc.collect()
    comm.Barrier()

    def plain(ulp: bool) -> dict:
        p = Simulation(_scene(a.particles * (comm.Get_size() if a.weak else 1), a.scene), device=a.device)
        if ulp:
            nf = p.fluid.n_fluid
            x = p.state.x.numpy().copy()
            sign = np.random.default_rng(1).choice([-1.0, 1.0], size=(nf, 3)).astype(np.float32)
            x[:nf] = np.nextafter(x[:nf], x[:nf] + sign)
            p.state.x.assign(x)
            p.fluid_solver.invalidate_lists()
        p.advance(duration)
        out = dict(x=p.positions(), v=p.velocities(), rho=p.densities(), steps=p.steps)
        del p
        gc.collect()
        return out

    one, ulp = plain(False), plain(True)
    diff = {k: float(np.abs(two[k] - one[k]).max()) for k in ("x", "v", "rho")}
    yard = {k: float(np.abs(ulp[k] - one[k]).max()) for k in ("x", "v", "rho")}
    p1, p2 = one["v"].astype(np.float64).sum(axis=0), two["v"].astype(np.float64).sum(axis=0)
    res = {"benchmark": "distributed-compare", "scene": a.scene, "ranks": comm.Get_size(), "device": a.device,
           "device_name": device_name(a.device), "date": date.today().isoformat(), "commit": commit(),
           "particles": len(one["x"]), "steps_ranks": int(two["steps"]), "steps_plain": int(one["steps"]),
           "simulated_s": duration, "ranks_wall_s": t_ranks, "max_diff_ranks_vs_plain": diff,
           "max_diff_plain_vs_one_ulp": yard, "bound": "2 x the one-ulp pair's difference",
           "within_round_off": all(diff[k] <= 2.0 * yard[k] for k in diff),
           "momentum_plain": p1.tolist(), "momentum_ranks": p2.tolist(),
           "momentum_rel_diff": float(np.abs(p1 - p2).max() / max(np.abs(p1).max(), 1e-30)),
           "particles_equal": len(one["x"]) == len(two["x"]), "ranks_record": report}
    print(json.dumps(res))
    dev = a.device.replace(":", "")
    out = a.out or RESULTS / f"{res['date']}-{dev}-distributed-compare-{a.scene}-{res['ranks']}ranks.json"
    write_json(res, out)
    return 0


def _peak_bytes(report: str) -> dict:
    """Peak bytes per device from a wp.ScopedMemoryTracker report ("Peak usage:" lines: device, value, unit)."""
    units = {"B": 1, "KB": 1024, "MB": 1024**2, "GB": 1024**3, "TB": 1024**4}
    out, on = {}, False
    for line in report.splitlines():
        if line.strip().startswith("Peak usage"):
            on = True
            continue
        if on:
            parts = line.split()
            if len(parts) != 3 or parts[2] not in units:
                break
            out[parts[0]] = float(parts[1]) * units[parts[2]]
    return out


def _memory(a, comm) -> int:
    """--memory: each rank's peak Warp bytes and resident host bytes at build and over --steps steps; rank 0: one
    gather's seconds and its peak numpy bytes (tracemalloc)."""
    import resource
    import tracemalloc

    import warp as wp

    from rockwave.sim.distributed import DistributedSimulation

    size = comm.Get_size()
    reports: list[str] = []
    with wp.ScopedMemoryTracker("build", print=False, report_func=reports.append) as tracker:
        t0 = time.perf_counter()
        sim = DistributedSimulation(_scene(a.particles * (size if a.weak else 1), a.scene, gauges=a.outputs),
                                    device=a.device,
                                    comm=comm, transport=a.transport, balance_by=a.balance_by,
                                    slab_build=not a.whole_build)
        build_s = time.perf_counter() - t0
        tracker.report()
        build = _peak_bytes(reports[-1])
        rss_build = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
        df = sim.dfluid
        n, own = df.n_global, df.n_own
        gather = {}
        if sim.rank == 0:
            dt = sim.dt
            sim.advance(a.steps * dt, gather=False)
            tracemalloc.start()  # numpy's host arrays of one gather (rank 0: Gatherv rows, sorted, into its state)
            t0 = time.perf_counter()
            sim.gather()
            gather = {"gather_s": time.perf_counter() - t0, "gather_host_peak_bytes": tracemalloc.get_traced_memory()[1]}
            tracemalloc.stop()
            if a.outputs:  # one frame's device-evaluated outputs from rank 0's water: the surface and the gauges
                from rockwave.output import recorders as rec
                from rockwave.output import surface as surf

                t0 = time.perf_counter()
                frame = rec.Frame(sim, 0, surf.extractor_for(sim.scene, sim.fluid, sim.device))
                mesh, readings = frame.surface, frame.gauges
                gather.update(outputs_s=time.perf_counter() - t0, surface_points=len(mesh.points) if mesh else 0,
                              gauges=readings)
            sim.close()
        else:
            sim.serve()
        tracker.report()
        run = _peak_bytes(reports[-1])
        rss_run = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    dev = sim.device if sim.device in build else next(iter(build), sim.device)
    mine = {"rank": sim.rank, "owned": own, "seeded": sim.built["seeded"], "held_points": sim.built["held_points"],
            "layout_window_points": sim.built["layout_window_points"], "build_s": build_s,
            "warp_peak_build_bytes": build.get(dev, 0.0), "warp_peak_run_bytes": run.get(dev, 0.0),
            "host_rss_peak_build_bytes": rss_build, "host_rss_peak_run_bytes": rss_run,
            "rank_bytes_per_owned_particle": round(df.bytes_per_particle(), 1), **gather}
    if sim.rank == 0:
        from rockwave.sim.distributed import whole_scene_device_arrays
        from rockwave.sim.readers import HostWater

        mine.update(whole_scene_device_arrays=whole_scene_device_arrays(sim),
                    output_device_bytes=sim.state.device_bytes() if isinstance(sim.state, HostWater) else None)
    for k in ("warp_peak_build_bytes", "warp_peak_run_bytes", "host_rss_peak_build_bytes", "host_rss_peak_run_bytes",
              "gather_host_peak_bytes"):
        if k not in mine:
            continue
        mine[k.replace("_bytes", "_per_particle")] = round(mine[k] / n, 1)
    ranks = comm.gather(mine, root=0)
    if sim.rank != 0:
        return 0
    res = {"benchmark": "distributed-memory", "scene": a.scene, "ranks": size, "device": a.device,
           "device_name": device_name(a.device), "date": date.today().isoformat(), "commit": commit(),
           "build": "whole scene on every rank" if a.whole_build else "slab per rank", "particles": n,
           "steps": a.steps, "per_rank": ranks}
    print(json.dumps(res))
    tag = "whole" if a.whole_build else "slab"
    out = a.out or RESULTS / f"{res['date']}-{a.device.replace(':', '')}-distributed-memory-{tag}-{size}ranks.json"
    write_json(res, out)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.distributed")
    ap.add_argument("--particles", type=float, required=True, help="fluid particles in all (or per rank with --weak)")
    ap.add_argument("--weak", action="store_true", help="--particles per rank")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--scene", default="dam_break_3d", help="a shipped scene with box fluid regions (default "
                    "dam_break_3d; slide_3d: water and blocks, the blocks replicated on every rank)")
    ap.add_argument("--transport", default="auto", help="auto, nccl, cuda-mpi or host (rockwave/sim/transport.py)")
    ap.add_argument("--balance-by", default="time", choices=("time", "count"))
    ap.add_argument("--no-plain", action="store_true", help="leave out the plain one-GPU reference run")
    ap.add_argument("--out", default=None, help="result JSON (default under benchmarks/results/)")
    ap.add_argument("--compare", action="store_true", help="correctness instead of speed: the ranks and the plain "
                    "Simulation advance the same --steps x the initial dt from the start; their particles are "
                    "compared, with two plain runs one float32 ulp apart as the round-off yardstick")
    ap.add_argument("--memory", action="store_true", help="peak bytes per rank at build and over --steps steps "
                    "(Warp allocations and resident host memory) instead of speed")
    ap.add_argument("--outputs", action="store_true", help="with --memory: the scene's gauges kept, and rank 0 reads "
                    "one frame's water surface and gauges (on its device, from its host copy of the water, a chunk "
                    "at a time)")
    ap.add_argument("--whole-build", action="store_true", help="every rank builds the whole scene, rank 0 scatters "
                    "it (the earlier start; default: each rank seeds its slab)")
    a = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    from rockwave.sim.distributed import DistributedSimulation, require_mpi

    comm = require_mpi().COMM_WORLD
    size = comm.Get_size()
    if a.memory:
        return _memory(a, comm)
    target = a.particles * (size if a.weak else 1)
    sim = DistributedSimulation(_scene(target, a.scene), device=a.device, comm=comm, transport=a.transport,
                                balance_by=a.balance_by, slab_build=not a.whole_build)
    if sim.rank != 0:
        sim.serve()
        del sim
        gc.collect()
        comm.Barrier()  # rank 0's plain run uses its GPU alone
        return 0
    if a.compare:
        return _compare(sim, a, comm)
    dt = sim.dt
    for _ in range(a.warmup):
        sim.step(dt)
    sim.gather()  # a collective: every rank is between steps here
    sim.timings.clear()
    df = sim.dfluid
    s0, r0 = sim.steps, df.relayouts
    t0 = time.perf_counter()
    sim.advance(a.steps * dt, gather=False)  # adaptive steps (dt may shrink as the water speeds up)
    t = time.perf_counter() - t0
    n, steps = sim.fluid.n_fluid, sim.steps - s0
    tm = {k: v / steps for k, v in sim.timings.items()}
    step_s = t / steps
    res = {"benchmark": "distributed", "scene": a.scene, "mode": "weak" if a.weak else "strong", "ranks": size,
           "device": sim.device, "device_name": device_name(sim.device), "date": date.today().isoformat(),
           "commit": commit(), "transport": sim.transport, "balance_by": a.balance_by,
           "particles": n, "spacing_m": sim.scene.fluid["spacing_m"], "steps": steps, "seconds": t,
           "particle_steps_per_s": n * steps / t, "relayouts": df.relayouts - r0,
           "rank0_owned": df.n_own, "rank0_halo": df.n_halo, "rank0_bytes_per_particle": round(df.bytes_per_particle(), 1),
           "rank0_seconds_per_step": {k: round(v, 6) for k, v in tm.items()},
           "halo_exchange_s_per_step": tm.get("halo", 0.0), "halo_share_of_step": tm.get("halo", 0.0) / step_s,
           "faces": [float(f) for f in df.dec.faces[1:-1]], "rebalances": df.rebalances}
    sim.close()
    del sim, df
    gc.collect()
    comm.Barrier()
    if not a.no_plain:
        ref = _plain_rate(a.particles, a.device, a.steps, a.warmup, a.scene)
        res["plain"] = ref
        if a.weak:
            res["efficiency"] = res["particle_steps_per_s"] / (size * ref["particle_steps_per_s"])
        else:
            res["speedup"] = res["particle_steps_per_s"] / ref["particle_steps_per_s"]
            res["efficiency"] = res["speedup"] / size
    print(json.dumps(res))
    dev = res["device"].replace(":", "")
    out = a.out or RESULTS / f"{res['date']}-{dev}-distributed-{a.scene}-{res['mode']}-{size}ranks.json"
    write_json(res, out)
    md = Path(out).parent / "distributed.md"
    if not md.exists():
        md.write_text("| date | commit | device | scene, mode | ranks | particles | transport | particle-steps/s | plain 1 GPU | "
                      "efficiency | halo s/step (share) | relayouts/steps | B/particle (rank 0) |\n"
                      "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    with open(md, "a") as f:
        p = res.get("plain", {}).get("particle_steps_per_s")
        f.write(f"| {res['date']} | {res['commit']} | {res['device_name']} | {a.scene}, {res['mode']} | {size} | {n:,} | "
                f"{res['transport']} | {res['particle_steps_per_s']:.3g} | {p:.3g} | " if p else
                f"| {res['date']} | {res['commit']} | {res['device_name']} | {a.scene}, {res['mode']} | {size} | {n:,} | "
                f"{res['transport']} | {res['particle_steps_per_s']:.3g} | - | ")
        f.write(f"{res.get('efficiency', float('nan')):.2f} | {res['halo_exchange_s_per_step']:.2e} "
                f"({100 * res['halo_share_of_step']:.1f}%) | {res['relayouts']}/{steps} | "
                f"{res['rank0_bytes_per_particle']:.0f} |\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
