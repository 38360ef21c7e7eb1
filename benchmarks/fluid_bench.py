"""Fluid throughput: the 3D dam break (SPHERIC Test 2 geometry) at increasing particle counts.

    python -m benchmarks.fluid_bench --device cuda:0 --spacings 0.02 0.015 0.01 --steps 200

Prints particles, mean neighbours per particle (fluid and boundary within the support radius),
steps/s and particle-steps/s of complete steps (neighbour grid, density, EOS, forces,
integration), timed after a warm-up that compiles the kernels. Fixed dt = the scene's initial
step; no output is written during the timed steps."""

from __future__ import annotations

import argparse

import numpy as np
import warp as wp

import rockwave
from benchmarks.common import ROOT, device_name, save, timed


def run(device: str, spacing: float, steps: int, warmup: int = 20) -> dict:
    scene = rockwave.load_scene(ROOT / "scenes" / "dam_break_3d.toml")
    scene.fluid["spacing_m"] = spacing
    scene.output["gauges"] = []
    sim = rockwave.Simulation(scene, device=device)
    for _ in range(warmup):
        sim.step()
    nbrs = float(np.mean(sim.fluid_solver.neighbour_counts(sim.state)))
    t = timed(lambda: [sim.step() for _ in range(steps)], device)
    n = sim.fluid.n_fluid
    return {"spacing_m": spacing, "particles": n, "boundary_particles": sim.fluid.n_boundary, "neighbours": nbrs,
            "steps": steps, "seconds": t, "steps_per_s": steps / t, "particle_steps_per_s": n * steps / t}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--spacings", type=float, nargs="+", default=[0.06, 0.04, 0.03])
    ap.add_argument("--steps", type=int, default=50)
    a = ap.parse_args(argv)
    wp.config.quiet = True
    rows = []
    print(f"# fluid step throughput, 3D dam break, {device_name(a.device)}")
    print(f"{'spacing':>8} {'particles':>10} {'nbrs':>6} {'steps/s':>9} {'particle-steps/s':>17}")
    for s in a.spacings:
        r = run(a.device, s, a.steps)
        rows.append(r)
        print(f"{s:8.4f} {r['particles']:10,d} {r['neighbours']:6.1f} {r['steps_per_s']:9.1f} {r['particle_steps_per_s']:17.3e}", flush=True)
    print("saved", save("fluid", a.device, {"rows": rows}))


if __name__ == "__main__":
    main()
