"""Part ``readers``: what reading the state costs while a run steps.

The 3D dam break (scenes/dam_break_3d.toml, its five gauges) at a given spacing steps in blocks of 10
(``Simulation.step_many``: a reorder by cell, then the steps; a CUDA graph on a GPU), alone, and with every
gauge and all positions read after each block. Two ways to read: ``copy`` (``positions()``: a new float64 array, and ``gauges()``)
``view`` (``Simulation.readers.view("x")``: the float32 view of the reader's pinned host buffer, one
device-to-host copy; and ``gauges()``), and ``async`` (``view_async("x")`` and ``gauges_async()`` queued after
each block, their results taken after the next block is launched: the state of every block, one block late). ``*_overhead`` = (read loop - step loop) /
step loop; the target (issue 18) is at most 10% at 1 M particles on a GPU. Reading leaves the particle order, the
neighbour lists and the captured graph untouched (rockwave/sim/readers.py), so the step loop does not slow down.

Only the public API is used (Simulation, step_many, positions, gauges), so the same file measures an
older rockwave too: ``python -m benchmarks.readers --device cuda:0 --spacing 0.0087``.
"""

from __future__ import annotations

import json
import time

CONFIG = {
    "quick": dict(readers_spacings=[0.04], readers_blocks=3),
    "full": dict(readers_spacings=[0.02, 0.0087], readers_blocks=10),
}
BLOCK_STEPS = 10


def measure(device: str, spacing: float, blocks: int) -> dict:
    import warp as wp

    import rockwave

    scene = rockwave.load_scene(_scene_path())
    scene.fluid["spacing_m"] = spacing
    sim = rockwave.Simulation(scene, device=device)
    n = sim.fluid.n_fluid

    # "copy": positions() (a new float64 array) and gauges(); "view": the float32 view of the reader's pinned host
    # buffer (Simulation.readers.view("x"), valid until the next read) and gauges(); older versions: "copy" only
    views = hasattr(sim, "readers")
    reads = {"none": lambda: None, "copy": lambda: (sim.positions(), sim.gauges())}
    pending = []

    def read_async():  # queue this block's reads, take the previous block's (launched steps keep the GPU busy)
        if pending:
            [p.result() for p in pending.pop()]
        pending.append((sim.readers.view_async("x"), sim.readers.gauges_async()))

    if views:
        reads["view"] = lambda: (sim.readers.view("x"), sim.gauges())
        reads["async"] = read_async

    def loop(read) -> float:
        wp.synchronize_device(sim.device)
        t = time.perf_counter()
        for _ in range(blocks):
            sim.step_many(BLOCK_STEPS)
            read()
        while pending:
            [p.result() for p in pending.pop()]
        wp.synchronize_device(sim.device)
        return (time.perf_counter() - t) / (blocks * BLOCK_STEPS)

    for f in reads.values():  # warm: kernels loaded, graphs captured
        loop(f)
    best = {k: float("inf") for k in reads}
    for _ in range(3):  # alternating, fastest of three (a drift of the machine hits all)
        for k, f in reads.items():
            best[k] = min(best[k], loop(f))
    out = {"spacing_m": spacing, "particles": n, "gauges": len(scene.output.gauges), "step_ms": 1e3 * best["none"]}
    for k in reads:
        if k != "none":
            out[f"{k}_ms"] = 1e3 * best[k]
            out[f"{k}_overhead"] = best[k] / best["none"] - 1.0
    return out


def _scene_path():
    from pathlib import Path

    try:
        from importlib.resources import files

        p = files("rockwave.scenes") / "dam_break_3d.toml"
        if p.is_file():
            return Path(str(p))
    except (ModuleNotFoundError, TypeError):
        pass
    return Path(__file__).resolve().parent.parent / "scenes" / "dam_break_3d.toml"


def run(device: str, cfg: dict) -> dict:
    from benchmarks.common import log

    rows = []
    for s in cfg["readers_spacings"]:
        r = measure(device, s, cfg["readers_blocks"])
        log(f"  readers: {r['particles']:,} particles, step {r['step_ms']:.3f} ms, reading copies "
            f"{100 * r['copy_overhead']:+.1f}%, views {100 * r.get('view_overhead', float('nan')):+.1f}%, "
            f"queued {100 * r.get('async_overhead', float('nan')):+.1f}%")
        rows.append(r)
    return {"block_steps": BLOCK_STEPS, "cases": rows}


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--spacing", type=float, nargs="+", default=[0.0087])
    ap.add_argument("--blocks", type=int, default=10)
    a = ap.parse_args()
    import warp as wp

    wp.config.quiet = True
    import rockwave

    dev = rockwave.resolve_device(a.device)
    print(json.dumps([measure(dev, s, a.blocks) for s in a.spacing]))
