"""Warp's own SPH example (warp/examples/core/example_sph.py, installed with warp-lang) at a given
particle count, timed per substep, next to rockwave's 3D dam break at about the same count.

The example fixes its smoothing length in Example.__init__ (0.8 -> 62,500 particles); to set the
count, ``example_at`` runs the example's own constructor and then rebuilds its arrays with
h = (32000 / N)^(1/3) by the example's formulas. Its physics differs from rockwave's (Mueller kernels,
linear EOS, clamped walls, no boundary particles, non-physical units, particles one support radius
apart: about 6 neighbours instead of ~30), so the throughput ratio is a cost per particle-step, not
a like-for-like comparison; the neighbour counts of both are recorded next to it.
"""

from __future__ import annotations

import contextlib
import io
import time

import numpy as np
import warp as wp


def example_at(n_target: int, device: str):
    import warp.examples.core.example_sph as ex

    with wp.ScopedDevice(device), contextlib.redirect_stdout(io.StringIO()):
        e = ex.Example(stage_path=None)
        h = (e.height * (e.width / 4.0) * (e.height / 4.0) / n_target) ** (1.0 / 3.0)
        e.smoothing_length = h
        e.particle_mass = 0.01 * h**3
        e.dt = 0.01 * h
        e.n = int(e.height * (e.width / 4.0) * (e.height / 4.0) / h**3)
        e.sim_step_to_frame_ratio = int(32 / h)
        e.density_normalization = (315.0 * e.particle_mass) / (64.0 * np.pi * h**9)
        e.pressure_normalization = -(45.0 * e.particle_mass) / (np.pi * h**6)
        e.viscous_normalization = (45.0 * e.dynamic_visc * e.particle_mass) / (np.pi * h**6)
        e.x = wp.empty(e.n, dtype=wp.vec3)
        e.v = wp.zeros(e.n, dtype=wp.vec3)
        e.rho = wp.zeros(e.n, dtype=float)
        e.a = wp.zeros(e.n, dtype=wp.vec3)
        wp.launch(ex.initialize_particles, dim=e.n, inputs=[e.x, h, e.width, e.height, e.length])
        g = int(e.height / (4.0 * h))
        e.grid = wp.HashGrid(g, g, g)
    return e


def neighbours(x: np.ndarray, radius: float) -> float:
    from scipy.spatial import cKDTree

    t = cKDTree(x)
    return float(np.mean([len(l) - 1 for l in t.query_ball_point(x, radius)]))


def run(n_target: int, device: str, frames: int = 2) -> dict:
    e = example_at(n_target, device)
    with wp.ScopedDevice(device), contextlib.redirect_stdout(io.StringIO()):
        e.step()  # kernel loads
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        for _ in range(frames):
            e.step()
        wp.synchronize_device(device)
        wall = time.perf_counter() - t0
    steps = frames * e.sim_step_to_frame_ratio
    x = e.x.numpy()
    return {"particles": e.n, "smoothing_length": e.smoothing_length, "steps": steps, "s_per_step": wall / steps,
            "particle_steps_per_s": e.n * steps / wall, "neighbours": neighbours(x, e.smoothing_length)}


def compare(spacing: float, device: str, steps: int = 20) -> dict:
    """rockwave's 3D dam break at ``spacing`` (the scaling part's fluid throughput) and the example at its particle count."""
    from benchmarks import scaling

    r = scaling.fluid(device, spacing, steps, warmup=5)
    w = run(r["particles"], device)
    return {"rockwave": r, "warp_example": w, "throughput_ratio": r["particle_steps_per_s"] / w["particle_steps_per_s"],
            "note": "example: Mueller kernels, linear EOS, clamped walls, ~6 neighbours; rockwave: ~30 neighbours "
                    "plus boundary particles (Akinci), continuity density, Tait EOS"}
