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

Big blocks (issue 20): ``contacts_prisms`` rows of 50-vertex prisms (a 25-gon extruded 1 m, radius 0.5 m)
resting on a side face on one fixed 5 degree slope, ms per step with the cooperative narrow phase (one thread
block of 32 lanes per pair, kernels/dda/blocks_coop.py narrow_phase_coop) and with every pair on one thread
(``BlockOptions(coop_min_vertices=10**9)``), same trajectory. On Warp's CPU backend both run one thread per
pair (the cooperative kernel is then the serial loop plus its tile overhead, which is why the solver's default
leaves it off there): the rows only mean something on a GPU.
"""

from __future__ import annotations

import argparse
import json
import math
import time

CONFIG = {
    "quick": dict(contacts_blocks=[1000], contacts_layers=4, contacts_warmup_steps=5, contacts_steps=20,
                  contacts_prisms=[1, 16]),
    "full": dict(contacts_blocks=[10_000, 100_000, 1_000_000], contacts_layers=4, contacts_warmup_steps=20, contacts_steps=200,
                 contacts_prisms=[1, 100, 10_000]),
}


def grid_specs(n: int, layers: int, size: float = 1.0, gap: float = 0.05):
    """The floor, then n cubes in columns of ``layers`` (row by row), each resting on the one below."""
    from rockwave.dda import geometry as G
    from rockwave.dda.blocks import BlockSpec

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


def prism_specs(count: int, alpha_deg: float = 5.0, sides: int = 25, r: float = 0.5, length: float = 1.0):
    """One fixed slope dipping alpha along x, then ``count`` 50-vertex prisms (axis along the strike) resting on
    a side face on it, 1.5 m apart along the strike and in rows of 20 down the slope."""
    import numpy as np

    from rockwave.dda import geometry as G
    from rockwave.dda.blocks import BlockSpec

    th = -0.5 * math.pi + math.pi / sides + 2 * math.pi * np.arange(sides) / sides
    ring = np.stack([r * np.cos(th), np.zeros(sides), r * np.sin(th)], axis=1)
    prism = G.prism(np.concatenate([ring + [0, -length / 2, 0], ring + [0, length / 2, 0]]), name="prism")
    a = math.radians(alpha_deg)
    q = (0.0, math.sin(a / 2), 0.0, math.cos(a / 2))
    n = np.array([math.sin(a), 0.0, math.cos(a)])
    dip = np.array([math.cos(a), 0.0, -math.sin(a)])
    rows = min(count, 20)
    cols = math.ceil(count / rows)
    t = 0.5
    wx, wy = 1.5 * rows + 2.0, 1.5 * length * cols + 2.0
    specs = [BlockSpec(G.box((wx, wy, 2 * t)), kind="fixed", orientation=q, name="slope")]
    for b in range(count):
        j, i = divmod(b, rows)
        p = (t - prism.vertices[:, 2].min()) * n + (1.5 * (i - (rows - 1) / 2)) * dip + np.array([0, 1.5 * length * (j - (cols - 1) / 2), 0])
        specs.append(BlockSpec(prism, position=tuple(p), orientation=q, density=2600.0))
    return specs


def timed_steps(solver, state, device: str, warmup: int, steps: int) -> tuple[float, float]:
    """(wall seconds of ``steps`` block steps after ``warmup`` untimed ones, the step: the stable step at start)."""
    import warp as wp

    from rockwave.base.solver import TimeStep

    dt = solver.stable_dt(state)
    dt_array = wp.array([dt], dtype=float, device=device)
    for _ in range(warmup):
        solver.step(state, TimeStep(dt, state.time, dt_array))
    wp.synchronize_device(device)
    t = time.perf_counter()
    for _ in range(steps):
        solver.step(state, TimeStep(dt, state.time, dt_array))
    wp.synchronize_device(device)
    return time.perf_counter() - t, dt


def measure_prisms(device: str, count: int, warmup: int, steps: int) -> dict:
    import numpy as np

    from rockwave.dda.blocks import BlockModel, BlockOptions, BlockSolver

    out = {"prisms": count, "steps": steps}
    final = {}
    for name, opt in (("coop", BlockOptions(coop_min_vertices=32)), ("serial", BlockOptions(coop_min_vertices=10**9))):
        model = BlockModel(prism_specs(count), device=device, check_overlap=False)
        state = model.state()
        solver = BlockSolver(model, options=opt)
        out[f"{name}_ms_per_step"] = 1e3 * timed_steps(solver, state, device, warmup, steps)[0] / steps
        final[name] = state.positions_numpy()
        out["points_per_prism"] = float(np.mean(state.contact_counts()[1:]))
    out["coop_speedup"] = out["serial_ms_per_step"] / out["coop_ms_per_step"]
    out["same_trajectory"] = bool(np.array_equal(final["coop"], final["serial"]))
    return out


def measure(device: str, n: int, layers: int, warmup: int, steps: int) -> dict:
    import numpy as np

    from rockwave.dda.blocks import BlockModel, BlockSolver

    t0 = time.perf_counter()
    model = BlockModel(grid_specs(n, layers), device=device, check_overlap=False)
    state = model.state()
    solver = BlockSolver(model)
    build_s = time.perf_counter() - t0
    wall, dt = timed_steps(solver, state, device, warmup, steps)
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
    prisms = []
    for n in cfg["contacts_prisms"]:
        r = measure_prisms(device, int(n), int(cfg["contacts_warmup_steps"]), int(cfg["contacts_steps"]))
        log(f"  {n} prisms: {r['coop_ms_per_step']:.3f} ms/step cooperative, {r['serial_ms_per_step']:.3f} serial, "
            f"same trajectory: {r['same_trajectory']}")
        prisms.append(r)
    return {"cases": cases, "prisms": prisms}


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.block_contacts", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--blocks", type=int, nargs="+", default=[1000])
    ap.add_argument("--layers", type=int, default=4)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--prisms", type=int, nargs="*", default=[1])
    a = ap.parse_args()
    import warp as wp

    wp.config.quiet = True
    cfg = dict(contacts_blocks=a.blocks, contacts_layers=a.layers, contacts_warmup_steps=a.warmup, contacts_steps=a.steps,
               contacts_prisms=a.prisms)
    print(json.dumps(run(a.device, cfg), indent=1))


if __name__ == "__main__":
    main()
