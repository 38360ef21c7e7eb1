"""Device bytes per fluid particle, per fluid level (issue 40: the memory target of 250 B per particle at the default).

The 3D dam break (scenes/dam_break_3d.toml, SPHERIC Test 2's tank) at a given spacing, each ``fluid.fidelity``
level built and stepped a few steps (so that every lazily allocated buffer exists), then every Warp array of the
fluid counted once at its capacity (rockwave/sph/fluid.py FluidSolver.device_bytes): the neighbour lists, the
solver's other buffers, the model (the boundary lattice included), the state, and Warp's HashGrid (estimated).
The count is of allocations, so it is the same on the CPU and on a GPU (a GPU adds its CUDA graphs and the
allocator's rounding, which ``--device cuda:0`` reports beside it as the memory pool's growth).

``--neighbours lists cells`` counts each level with both neighbour searches (``fluid.neighbours``: the Verlet
lists, or the list-free gather from the cell grid, kernels/sph/gather.py), side by side.

    python -m benchmarks.fluid_bytes [--device cpu] [--spacing 0.04] [--levels draft standard high waves delta_plus]
                                     [--neighbours lists cells]
"""

import argparse
import time


def count(device: str, spacing: float, level: str, steps: int = 3, neighbours: str = "lists") -> dict:
    import warp as wp

    from benchmarks import harness as H

    pool0 = _pool_used(device)
    variant = {"fluid.fidelity": level, "fluid.neighbours": neighbours}
    sim = H.build("spheric", H.scene_dict("spheric", spacing, variant, strip=H.FORMULATION_KEYS), device)
    sim.step_many(steps)
    wp.synchronize_device(device)
    b = sim.fluid_solver.device_bytes(sim.state)
    nf = sim.fluid.n_fluid
    row = dict(level=level, neighbours=neighbours, spacing_m=spacing, fluid=nf, boundary=sim.fluid.n_total - nf,
               list_slots_per_particle=sim.fluid_solver.neighbour_cap,
               **{f"{k}_b_per_particle": v / nf for k, v in b.items() if k != "per_particle"})
    pool1 = _pool_used(device)
    if pool0 is not None and pool1 is not None:
        row["pool_growth_b_per_particle"] = (pool1 - pool0) / nf  # everything the run allocated, blocks none here
    del sim
    return row


def _pool_used(device: str):
    import warp as wp

    d = wp.get_device(device)
    if not d.is_cuda:
        return None
    try:
        return wp.get_mempool_used_mem_current(d)
    except Exception:  # an older Warp or no memory pool
        return None


COLS = ("lists", "solver", "state", "model", "hash_grid", "total")


def markdown(rows: list, head: str) -> str:
    out = [head, "", "| level | neighbours | fluid | boundary | list slots | " + " | ".join(f"{c} B" for c in COLS)
           + " | pool growth B |", "|---" * (6 + len(COLS)) + "|"]
    for r in rows:
        pg = r.get("pool_growth_b_per_particle")
        out.append(f"| {r['level']} | {r.get('neighbours', 'lists')} | {r['fluid']:,} | {r['boundary']:,} | "
                   f"{r['list_slots_per_particle']} | "
                   + " | ".join(f"{r[c + '_b_per_particle']:.0f}" for c in COLS) + f" | {'-' if pg is None else f'{pg:.0f}'} |")
    out.append("")
    out.append("Bytes per fluid particle; boundary particles are counted in the model, state and lists they own. "
               "hash_grid is estimated (16 B per reserved point, 8 B per cell).")
    return "\n".join(out) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.fluid_bytes", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--spacing", type=float, default=0.04)
    ap.add_argument("--levels", nargs="+", default=["draft", "standard", "high", "waves", "delta_plus"])
    ap.add_argument("--neighbours", nargs="+", default=["lists"], choices=["lists", "cells"],
                    help="fluid.neighbours of each row (both: side by side)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    import warp as wp

    from benchmarks.common import RESULTS, commit, device_name, write_record

    wp.config.quiet = True
    rows = [count(a.device, a.spacing, lv, neighbours=nb) for lv in a.levels for nb in a.neighbours]
    date = time.strftime("%Y-%m-%d")
    stem = a.out or str(RESULTS / f"{date}-{a.device.replace(':', '')}-fluid_bytes")
    head = (f"# Device bytes per fluid particle by level, 3D dam break at {a.spacing:g} m (issue 40): "
            f"{device_name(a.device)}, commit {commit()}, {date}")
    write_record(stem, rows, head, markdown, a.device, a)


if __name__ == "__main__":
    main()
