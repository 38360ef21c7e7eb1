"""Hashes of every shipped scene's state after a few CPU steps: the restructuring's no-physics-change
check (tests/test_identical_trajectories.py). Regenerate only after a deliberate physics change:

    python tests/golden/trajectories.py --write

(``--add``: keep the recorded sets and add this machine's where it differs: for scenes whose set-up depends on the
host's numerical libraries, tests/test_identical_trajectories.py.)
"""

from __future__ import annotations

import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
FILE = Path(__file__).with_name("trajectories.json")
STEPS = 12  # adaptive steps (crosses a dt update, a list rebuild and, with ghosts, a resampling)


def scene_hashes(path: Path) -> dict:
    import rockwave

    sim = rockwave.Simulation(rockwave.load_scene(path), device="cpu")
    sim.advance(STEPS * sim.dt)
    sim.step_many(STEPS)  # chunks of steps after a reorder by cell, then the original order back
    h = {}
    arrays = {"x": sim.positions(), "v": sim.velocities()}
    if sim.fluid is not None:
        arrays["rho"] = sim.densities()
    if sim.blocks is not None:
        arrays["block_x"] = sim.block_positions()
        arrays["block_v"] = sim.block_velocities()
        arrays["block_q"] = sim.block_state.orientations_numpy()
    for k, a in arrays.items():
        h[k] = hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]
    h["steps"] = sim.steps
    h["time"] = repr(float(sim.time))
    return h


def main() -> None:
    import warp as wp

    wp.config.quiet = True
    only = [a for a in sys.argv[1:] if not a.startswith("--")]
    out = json.loads(FILE.read_text()) if FILE.exists() else {}
    for p in sorted((ROOT / "scenes").glob("*.toml")):
        if only and p.stem not in only:
            continue
        t = time.perf_counter()
        h = scene_hashes(p)
        print(f"{p.stem}: {h} ({time.perf_counter() - t:.1f} s)", flush=True)
        known = out.get(p.stem)
        known = known if isinstance(known, list) else [known]
        if "--write" in sys.argv:
            out[p.stem] = h
        elif "--add" in sys.argv and h not in known:  # another machine's exact trajectory of the same code
            out[p.stem] = [k for k in known if k] + [h]
        elif h not in known:
            print(f"  DIFFERS from {out.get(p.stem)}")
    if "--write" in sys.argv or "--add" in sys.argv:
        FILE.write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")


if __name__ == "__main__":
    main()
