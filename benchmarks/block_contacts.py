"""Part ``block_contacts``: the DDA block solver at scale: block-steps/s, device bytes and contacts per block.

N cubes (1 m, 2600 kg/m3) stand in columns of ``contacts_layers`` on a fixed floor, 5 cm apart side to side,
each resting on the one below from t = 0 (no gap, no pre-set penetration), and settle under gravity at the
solver's stable step. After ``contacts_warmup_steps`` (the pools and tables have grown to the live contacts),
``contacts_steps`` steps are timed (device synchronised): ``block_steps_per_s`` = N x steps / wall time.
``bytes_per_block`` = BlockSolver.device_bytes(): every device array of the model, the state, the two
contact-history tables and the solver's buffers over N (issue 21 target: <= 4 KB, 1 M blocks well under
10 GB); ``points_per_block`` = contact points per block (each point counted for both blocks of its pair),
``pairs_per_block`` = candidate pairs of the broad phase per block. Only the public API is used (BlockModel,
BlockSolver, TimeStep), so ``python -m benchmarks.block_contacts --device cuda:0 --blocks 1000000`` runs it
alone.
"""

from __future__ import annotations

import argparse
import json
import math
import time

CONFIG = {
    "quick": dict(contacts_blocks=[1000], contacts_layers=4, contacts_warmup_steps=5, contacts_steps=20),
    "full": dict(contacts_blocks=[10_000, 100_000, 1_000_000], contacts_layers=4, contacts_warmup_steps=20, contacts_steps=200),
}


def grid_specs(n: int, layers: int, size: float = 1.0, gap: float = 0.05):
    """The floor, then n cubes in columns of ``layers`` (row by row), each resting on the one below."""
    from rockwave import geometry as G
    from rockwave.blocks import BlockSpec

    columns = math.ceil(n / layers)
    nx = math.ceil(math.sqrt(columns))
    ny = math.ceil(columns / nx)
    pitch = size + gap
    cube = G.box((size, size, size))
    floor = G.box((nx * pitch + size, ny * pitch + size, size))
    specs = [BlockSpec(floor, kind="fixed", position=(0.5 * (nx - 1) * pitch, 0.5 * (ny - 1) * pitch, -0.5 * size),
                       name="floor")]
    for b in range(n):
        c, k = divmod(b, layers)
        j, i = divmod(c, nx)
        specs.append(BlockSpec(cube, position=(i * pitch, j * pitch, (k + 0.5) * size), density=2600.0))
    return specs


def measure(device: str, n: int, layers: int, warmup: int, steps: int) -> dict:
    import numpy as np
    import warp as wp

    from rockwave.blocks import BlockModel, BlockSolver
    from rockwave.solver import TimeStep

    t0 = time.perf_counter()
    model = BlockModel(grid_specs(n, layers), device=device, check_overlap=False)
    state = model.state()
    solver = BlockSolver(model)
    build_s = time.perf_counter() - t0
    dt = solver.stable_dt(state)
    dt_array = wp.array([dt], dtype=float, device=device)
    for _ in range(warmup):
        solver.step(state, TimeStep(dt, state.time, dt_array))
    wp.synchronize_device(device)
    t = time.perf_counter()
    for _ in range(steps):
        solver.step(state, TimeStep(dt, state.time, dt_array))
    wp.synchronize_device(device)
    wall = time.perf_counter() - t
    mem = solver.device_bytes(state)
    counts = state.contact_counts()[1:]
    v = np.linalg.norm(state.velocities_numpy()[1:], axis=1)
    return {"blocks": n, "layers": layers, "dt_s": dt, "steps": steps, "build_s": build_s, "wall_s": wall,
            "block_steps_per_s": n * steps / wall, "bytes_per_block": mem["per_block"],
            "bytes": {k: int(mem[k]) for k in ("model", "state", "history", "solver", "total")},
            "points_per_block": float(counts.mean()), "pairs_per_block": solver.pair_count / n,
            "point_regrows": solver.point_regrows, "broad_phases": solver.broad_phases,
            "max_speed_m_s": float(v.max())}


def run(device: str, cfg: dict) -> dict:
    from benchmarks.common import log

    cases = []
    for n in cfg["contacts_blocks"]:
        r = measure(device, int(n), int(cfg["contacts_layers"]), int(cfg["contacts_warmup_steps"]), int(cfg["contacts_steps"]))
        log(f"  {n} blocks: {r['block_steps_per_s']:.4g} block-steps/s, {r['bytes_per_block']:.0f} B/block, "
            f"{r['points_per_block']:.2f} contact points/block (build {r['build_s']:.1f} s)")
        cases.append(r)
    return {"cases": cases}


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.block_contacts", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--blocks", type=int, nargs="+", default=[1000])
    ap.add_argument("--layers", type=int, default=4)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--steps", type=int, default=20)
    a = ap.parse_args()
    import warp as wp

    wp.config.quiet = True
    cfg = dict(contacts_blocks=a.blocks, contacts_layers=a.layers, contacts_warmup_steps=a.warmup, contacts_steps=a.steps)
    print(json.dumps(run(a.device, cfg), indent=1))


if __name__ == "__main__":
    main()
