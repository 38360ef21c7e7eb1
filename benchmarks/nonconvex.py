"""Part ``nonconvex``: scanned-rock-like boulders (scenes/scanned_rock_on_slope.toml: a lumpy, notched,
non-convex mesh) falling onto a slope as compound blocks of CoACD convex parts.

Per case (n x n boulders, 1.4 m apart in rows along the slope, 0.2 m above it, on a slope grown to hold them): the decomposition's wall time with
an empty cache (``decompose_s``) and with the cache filled (``cached_load_s``: the scene built a second
time), the parts per boulder and their volume error, then ``steps`` block steps after ``settle`` steps of
warm-up: ``step_ms``, ``body_steps_per_s`` (boulders x steps / s), ``part_steps_per_s`` (convex parts x
steps / s: what the narrow phase sees), contact points per boulder at the end, and how far the boulders
travelled (mean, m). The decomposition runs on the CPU whatever the device.

    python -m benchmarks run --device cuda:0 --suite full --only nonconvex
"""

from __future__ import annotations

import tempfile
import time

import numpy as np

CONFIG = {
    "quick": dict(nonconvex_counts=[1], nonconvex_steps=200, nonconvex_settle=50),
    "full": dict(nonconvex_counts=[1, 10, 32], nonconvex_steps=4000, nonconvex_settle=200),
}
SPACING_M = 1.4  # centre-to-centre distance of the boulders (bounding diameter ~1.1 m)


def _scene(n: int, cache_dir: str):
    import rockwave
    from benchmarks.harness import ROOT

    scene = rockwave.load_scene(ROOT / "scenes" / "scanned_rock_on_slope.toml")
    slope, rock = scene.blocks
    side = SPACING_M * n
    slope["size_m"] = [max(8.0, side / np.cos(np.radians(25.0)) + 6.0), max(3.0, side + 1.0), 0.3]
    # the array along the slope (its axes turn with the rock's orientation): every boulder 0.2 m above the
    # slope's top face (bounding radius ~0.55 m), centred across it, starting near its upper end
    c, si = np.cos(np.radians(25.0)), np.sin(np.radians(25.0))
    rock["orientation_deg"] = [0.0, 25.0, 0.0]
    rock["array"]["count"] = [float(n), float(n), 1.0]
    rock["array"]["spacing_m"] = [SPACING_M, SPACING_M, 0.0]
    s0 = -0.5 * slope["size_m"][0] + 1.5
    rock["position_m"] = [s0 * c + 0.9 * si, -0.5 * SPACING_M * (n - 1), -s0 * si + 0.9 * c]
    rock["decomposition"]["cache_dir"] = cache_dir
    return scene


def measure(device: str, n: int, steps: int, settle: int) -> dict:
    import warp as wp

    import rockwave

    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        sim = rockwave.Simulation(_scene(n, tmp), device=device)
        build_s = time.perf_counter() - t
        t = time.perf_counter()
        rockwave.Simulation(_scene(n, tmp), device=device)
        cached_s = time.perf_counter() - t
    bs = sim.block_state
    specs = sim.blocks.specs
    body = next(s.compound.body for s in specs if s.compound is not None)
    lead = np.nonzero(sim.blocks.lead & sim.blocks.movable)[0]
    x0 = bs.positions_numpy()[lead]
    sim.step_many(settle)
    wp.synchronize_device(sim.device)
    t = time.perf_counter()
    sim.step_many(steps)
    wp.synchronize_device(sim.device)
    wall = time.perf_counter() - t
    parts = int(sum(1 for s in specs if s.compound is not None))
    cc = bs.contact_counts()
    per_body = [int(cc[b: b + body.num_parts].sum()) for b in lead]
    return {"boulders": int(len(lead)), "parts_per_boulder": body.num_parts, "volume_error": body.volume_error,
            "decompose_s": build_s - cached_s, "cached_load_s": cached_s, "steps": steps, "step_ms": 1e3 * wall / steps,
            "body_steps_per_s": len(lead) * steps / wall, "part_steps_per_s": parts * steps / wall,
            "contacts_per_boulder": float(np.mean(per_body)),
            "travel_m": float(np.mean(np.linalg.norm(bs.positions_numpy()[lead] - x0, axis=1))),
            "simulated_s": float(bs.time)}


def run(device: str, cfg: dict) -> dict:
    from benchmarks.common import log

    rows = []
    for n in cfg["nonconvex_counts"]:
        r = measure(device, n, cfg["nonconvex_steps"], cfg["nonconvex_settle"])
        log(f"  nonconvex: {r['boulders']} boulders x {r['parts_per_boulder']} parts (volume error "
            f"{100 * r['volume_error']:+.2f}%), decomposition {r['decompose_s']:.1f} s, cached {r['cached_load_s']:.2f} s, "
            f"{r['step_ms']:.3f} ms/step, {r['body_steps_per_s']:.3g} boulder-steps/s")
        rows.append(r)
    return {"cases": rows}


if __name__ == "__main__":
    import argparse
    import json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--count", type=int, nargs="+", default=[1], help="n: n x n boulders")
    ap.add_argument("--steps", type=int, default=4000)
    a = ap.parse_args()
    import warp as wp

    wp.config.quiet = True
    import rockwave

    dev = rockwave.resolve_device(a.device)
    print(json.dumps([measure(dev, n, a.steps, 200) for n in a.count], indent=1))
