"""Stored Verlet lists against the list-free gather, side by side (issue 40): ``fluid.neighbours = 'lists' | 'cells'``.

The 3D dam break (SPHERIC Test 2's tank, scenes/dam_break_3d.toml) at one spacing and fidelity level, built once
per neighbour search in the same process: advanced ``--flow-s`` simulated seconds (the column collapsing: the lists
or cell grid are rebuilt as it flows), then ``--warmup`` steps and ``--steps`` timed steps of ``step_many`` (on a GPU
the CUDA-graph chunks with the rebuild as a conditional node and the reorder every 10 steps, as a run steps). Each row:
particles, mean neighbours within H (fluid and walls), ms per step, particle-steps/s, pairs/s (particle-steps/s x
mean neighbours), list builds of the timed steps, the device bytes per fluid particle counted by
FluidSolver.device_bytes (lists, solver, state, model, hash grid) and, on a GPU, the memory pool's growth from before
the build to after the steps; and the largest position difference of the second search from the first after the same steps (in spacings:
the two visit the same pairs in the same order).

    python -m benchmarks.neighbour_gather --device cuda:0 --spacing 0.0065 --steps 200          # 2.5 M particles
    python -m benchmarks.neighbour_gather --device cpu --spacing 0.04 --steps 20 --flow-s 0.05  # 10.9 k, CPU
"""

from __future__ import annotations

import argparse
import gc
import time

import numpy as np


def _pool(device: str):
    import warp as wp

    d = wp.get_device(device)
    if not d.is_cuda:
        return None
    try:
        return wp.get_mempool_used_mem_current(d)
    except Exception:  # no memory pool
        return None


def measure(device: str, spacing: float, level: str, neighbours: str, flow_s: float, warmup: int, steps: int,
            cell_span: int = 1) -> tuple:
    """One row: ``neighbours`` "lists", "cells" or "cells_prefilter" (cells with FluidOptions.gather_prefilter)."""
    prefilter = neighbours == "cells_prefilter"
    neighbours = "cells" if prefilter else neighbours
    import warp as wp

    import rockwave
    from benchmarks import harness as H
    from benchmarks.common import ROOT, timed
    from rockwave.sim.simulation import SimulationOptions
    from rockwave.sph.fluid import FluidOptions

    gc.collect()
    pool0 = _pool(device)
    variant = {"fluid.fidelity": level, "fluid.neighbours": neighbours, "output.gauges": []}
    t0 = time.perf_counter()
    scene = rockwave.parse_scene(H.scene_dict("spheric", spacing, variant, strip=H.FORMULATION_KEYS), "spheric.toml",
                                 ROOT / "scenes")
    fo = FluidOptions(cell_span=cell_span, gather_prefilter=prefilter)
    sim = rockwave.Simulation(scene, device=device, options=SimulationOptions(fluid=fo))
    build_s = time.perf_counter() - t0
    if flow_s > 0:
        sim.advance(flow_s)
    sim.step_many(warmup)
    fs = sim.fluid_solver
    builds0 = fs.list_builds
    t = timed(lambda: sim.step_many(steps), device)
    builds = fs.list_builds - builds0
    wp.synchronize_device(device)
    nf = sim.fluid.n_fluid
    with wp.ScopedDevice(sim.device):
        nbrs = float(np.mean(fs.pair_counts(sim.state)))
    b = fs.device_bytes(sim.state)
    pool1 = _pool(device)
    row = dict(level=level, neighbours=neighbours + (" prefilter" if prefilter else ""), cell_span=cell_span, spacing_m=spacing, fluid=nf, boundary=sim.fluid.n_boundary,
               neighbours_within_H=nbrs, list_slots=fs.neighbour_cap, sim_time_s=sim.time, build_s=build_s,
               steps=steps, ms_per_step=1e3 * t / steps, particle_steps_per_s=nf * steps / t,
               pairs_per_s=nf * nbrs * steps / t, list_builds=builds if not wp.get_device(device).is_cuda else None,
               **{f"{k}_b_per_particle": v / nf for k, v in b.items() if k != "per_particle"})
    if pool0 is not None and pool1 is not None:
        row["pool_growth_b_per_particle"] = (pool1 - pool0) / nf  # what the build and the steps left allocated
    x = sim.positions()
    sim = fs = None  # (freed before the next build)
    gc.collect()
    return row, x


COLS = ("lists", "solver", "state", "model", "hash_grid", "total")


def markdown(rows: list, head: str) -> str:
    out = [head, "", "| level | neighbours (cell span) | fluid | boundary | nbrs in H | ms/step | particle-steps/s | pairs/s | "
           + " | ".join(f"{c} B" for c in COLS) + " | pool growth B | max dx / spacing |", "|---" * (10 + len(COLS)) + "|"]
    for r in rows:
        pk = r.get("pool_growth_b_per_particle")
        out.append(f"| {r['level']} | {r['neighbours']} ({r.get('cell_span', 1)}) | {r['fluid']:,} | {r['boundary']:,} | {r['neighbours_within_H']:.1f} | "
                   f"{r['ms_per_step']:.3f} | {r['particle_steps_per_s']:.3g} | {r['pairs_per_s']:.3g} | "
                   + " | ".join(f"{r[c + '_b_per_particle']:.0f}" for c in COLS)
                   + f" | {'-' if pk is None else f'{pk:.0f}'} | {r.get('max_dx_spacings', 0.0):.2g} |")
    out.append("")
    out.append("Bytes per fluid particle (FluidSolver.device_bytes: each Warp array at its capacity, boundary particles "
               "counted in the arrays they own; hash_grid estimated). pairs/s = particle-steps/s x the mean neighbours "
               "within H. max dx: the largest position difference from the first row of the level after the same steps.")
    return "\n".join(out) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.neighbour_gather", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--spacing", type=float, default=0.04)
    ap.add_argument("--levels", nargs="+", default=["standard"])
    ap.add_argument("--neighbours", nargs="+", default=["lists", "cells"], choices=["lists", "cells", "cells_prefilter"],
                    help="fluid.neighbours of the rows; cells_prefilter: cells with FluidOptions.gather_prefilter")
    ap.add_argument("--cell-span", nargs="+", type=int, default=[1],
                    help="FluidOptions.cell_span of the rows (y/z cells R/n wide, (2n+1)^2 columns a query)")
    ap.add_argument("--flow-s", type=float, default=0.2, help="simulated seconds of flow before the timed steps")
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    import warp as wp

    from benchmarks.common import RESULTS, commit, device_name, log, write_record

    wp.config.quiet = True
    rows = []
    for lv in a.levels:
        first = None
        for nb, span in [(nb, span) for span in a.cell_span for nb in a.neighbours]:
            row, x = measure(a.device, a.spacing, lv, nb, a.flow_s, a.warmup, a.steps, span)
            if first is None:
                first = x
            row["max_dx_spacings"] = float(np.abs(x - first).max() / a.spacing)
            rows.append(row)
            log(f"  {lv} {nb} (span {span}): {row['fluid']:,} particles, {row['ms_per_step']:.3f} ms/step, "
                f"{row['particle_steps_per_s']:.3g} particle-steps/s, {row['total_b_per_particle']:.0f} B/particle")
    date = time.strftime("%Y-%m-%d")
    stem = a.out or str(RESULTS / f"{date}-{a.device.replace(':', '')}-neighbour_gather")
    head = (f"# Verlet lists against the cell gather (fluid.neighbours), 3D dam break at {a.spacing:g} m after "
            f"{a.flow_s:g} s of flow, {a.steps} steps (issue 40): {device_name(a.device)}, commit {commit()}, {date}")
    write_record(stem, rows, head, markdown, a.device, a)


if __name__ == "__main__":
    main()
