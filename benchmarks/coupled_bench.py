"""Coupled SPH-DDA throughput: particle-steps/s and the share of the step spent in the coupling
(broad phase + penalty forces + impulse), for the paper's scenes at their size and larger.

    python benchmarks/coupled_bench.py --device cpu --steps 20
    python benchmarks/coupled_bench.py --device cuda:0 --steps 200 --scale 1 2

--scale s multiplies the particle count by about s (spacing / s^(1/dim)).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import warp as wp

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import rockwave  # noqa: E402
from rockwave.scene import load_scene  # noqa: E402


def bench(scene_name: str, device: str, steps: int, scale: float) -> dict:
    scene = load_scene(ROOT / "scenes" / scene_name)
    scene.fluid["spacing_m"] = scene.fluid.spacing_m / scale ** (1.0 / scene.dim)
    sim = rockwave.Simulation(scene, device=device)
    c = sim.coupling
    t_coupling = 0.0
    compute, apply = c.compute, c.apply

    def timed_compute(*a):
        nonlocal t_coupling
        wp.synchronize_device(device)
        t = time.perf_counter()
        compute(*a)
        wp.synchronize_device(device)
        t_coupling += time.perf_counter() - t

    def timed_apply(*a):
        nonlocal t_coupling
        wp.synchronize_device(device)
        t = time.perf_counter()
        apply(*a)
        wp.synchronize_device(device)
        t_coupling += time.perf_counter() - t

    for _ in range(3):  # warm-up (kernel loads)
        sim.step()
    c.compute, c.apply = timed_compute, timed_apply
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        sim.step()
    wp.synchronize_device(device)
    wall = time.perf_counter() - t0
    return {"scene": scene_name, "scale": scale, "fluid_particles": sim.n_fluid, "blocks": sim.blocks.num_blocks,
            "active_blocks": c.active_block_count(), "steps": steps, "s_per_step": wall / steps,
            "particle_steps_per_s": sim.n_fluid * steps / wall, "coupling_share": t_coupling / wall,
            "removed_inside_blocks": sim.removed_inside_blocks}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--scale", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--scenes", nargs="+", default=["wave_maker.toml", "sliding_wedge.toml"])
    a = ap.parse_args(argv)
    wp.config.quiet = True
    rows = []
    for sc in a.scenes:
        for s in a.scale:
            r = bench(sc, a.device, a.steps, s)
            rows.append(r)
            print(f"{sc:22s} x{s:<4g} {r['fluid_particles']:>9d} particles {r['blocks']:>4d} blocks "
                  f"({r['active_blocks']} near water)  {r['s_per_step'] * 1e3:9.2f} ms/step  "
                  f"{r['particle_steps_per_s']:.3g} particle-steps/s  coupling {100 * r['coupling_share']:.1f}%", flush=True)
    try:
        from benchmarks.common import save

        print("saved", save("coupled", a.device, {"rows": rows}))
    except Exception:  # the shared helper is optional
        print(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
