"""Block throughput: the jointed rock slope (scenes/rock_slope_10k.toml) at increasing block counts.

    python -m benchmarks.blocks_bench --device cuda:0 --counts 1000 10000 100000 --steps 200

Prints blocks, contacts per block (after settling), steps/s and block-steps/s of complete DDA
steps (broad phase, FCP narrow phase, contact forces, integration), timed after a warm-up."""

from __future__ import annotations

import argparse
import math

import numpy as np
import warp as wp

import rockwave
from benchmarks.common import ROOT, device_name, save, timed


def run(device: str, count: int, steps: int, settle: int = 300) -> dict:
    scene = rockwave.load_scene(ROOT / "scenes" / "rock_slope_10k.toml")
    nz = 10
    ny = max(1, int(round(math.sqrt(count / nz / 1.6))))
    nx = max(1, int(round(count / nz / ny)))
    scene.blocks[1]["array"]["count"] = [float(nx), float(ny), float(nz)]
    # a base large enough for the array
    scene.blocks[0]["size_m"] = [max(40.0, 0.5002 * nx + 25.0), max(16.0, 0.5002 * ny + 4.0), 1.0]
    scene.blocks[1]["position_m"][1] = -0.5002 * ny / 2
    sim = rockwave.Simulation(scene, device=device)
    for _ in range(settle):  # close the 0.2 mm joints so contacts exist
        sim.step()
    contacts = float(np.mean(sim.block_state.contact_counts()[1:]))
    t = timed(lambda: [sim.step() for _ in range(steps)], device)
    n = sim.blocks.num_blocks
    return {"blocks": n, "contacts_per_block": contacts, "steps": steps, "seconds": t, "steps_per_s": steps / t,
            "block_steps_per_s": n * steps / t, "dt_s": sim.dt}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--counts", type=int, nargs="+", default=[100, 400, 1000])
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--settle", type=int, default=300)
    a = ap.parse_args(argv)
    wp.config.quiet = True
    rows = []
    print(f"# block step throughput, jointed rock slope, {device_name(a.device)}")
    print(f"{'blocks':>8} {'contacts/block':>15} {'steps/s':>9} {'block-steps/s':>14}")
    for c in a.counts:
        r = run(a.device, c, a.steps, a.settle)
        rows.append(r)
        print(f"{r['blocks']:8,d} {r['contacts_per_block']:15.2f} {r['steps_per_s']:9.1f} {r['block_steps_per_s']:14.3e}", flush=True)
    print("saved", save("blocks", a.device, {"rows": rows}))


if __name__ == "__main__":
    main()
