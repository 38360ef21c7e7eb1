"""Part ``surface``: what the fluid surface of one output frame costs, in fluid steps of the same scene.

A scene (default scenes/wave_maker.toml, 3D, ~62,000 particles; ``surface_spacings`` rescales its particle
spacing) steps ``surface_steps`` steps (``Simulation.step_many``) and its frame surface is extracted
``surface_frames`` times (rockwave/output/surface.py ``extractor_for``, the extractor a run uses, on the
particles as a frame passes them), all in one process on one device, after a warm-up of each (kernel loads).
``surface_in_steps`` = surface s / step s is the figure the target is stated in (issue 24: at most a few fluid
steps). Where the extractor has them, the field (``field``) and the isosurface (``mesh``) are timed apart.

Standalone: ``python -m benchmarks.surface --device cpu [--scene PATH] [--spacing S]``.
"""

from __future__ import annotations

import json
import time

# surface_cells: grid cell / particle spacing (None: the default, rockwave/output/surface.py default_cell;
# 0.5: the default before 1aae2a3)
CONFIG = {
    "quick": dict(surface_spacings=[None], surface_cells=[None, 0.5], surface_steps=10, surface_frames=3),
    "full": dict(surface_spacings=[None, 0.05], surface_cells=[None, 0.5], surface_steps=20, surface_frames=5),
}


def _scene_path():
    from benchmarks.common import ROOT

    return ROOT / "scenes" / "wave_maker.toml"


def _sync(device):
    import warp as wp

    wp.synchronize_device(device)


def measure(device: str, spacing: float | None = None, steps: int = 10, frames: int = 3, scene_path=None,
            resolution: float | None = None, resolution_cells: float | None = None) -> dict:
    """One case; ``resolution`` [m] or ``resolution_cells`` (x the spacing) sets output.surface.resolution_m."""
    import numpy as np

    import rockwave
    from rockwave.output import surface as surf

    scene = rockwave.load_scene(scene_path or _scene_path())
    if spacing:
        scene.fluid["spacing_m"] = spacing
    scene.output.setdefault("surface", {})["enabled"] = True
    if resolution_cells:
        resolution = resolution_cells * float(scene.fluid["spacing_m"])
    if resolution:
        scene.output["surface"]["resolution_m"] = resolution
    sim = rockwave.Simulation(scene, device=device)
    nf = sim.n_fluid
    sim.step_many(2)  # warm-up: kernel loads, neighbour lists
    _sync(sim.device)
    t0 = time.perf_counter()
    sim.step_many(steps)
    _sync(sim.device)
    step_s = (time.perf_counter() - t0) / steps

    ex = surf.extractor_for(scene, sim.fluid, sim.device)
    st = sim.state

    def one():
        xs = sim.readers.view("x")[:, :3]  # as a frame (rockwave/output/recorders.py Frame.surface) passes them
        return ex.extract(st.x[:nf], st.rho, xs.min(axis=0), xs.max(axis=0))

    mesh = one()  # warm-up
    _sync(sim.device)
    t0 = time.perf_counter()
    for _ in range(frames):
        mesh = one()
    _sync(sim.device)
    surface_s = (time.perf_counter() - t0) / frames

    split = {}
    if hasattr(ex, "field") and hasattr(ex, "_cubes") and scene.dim == 3:  # field and marching cubes apart
        xs = sim.readers.view("x")[:, :3]
        lo, hi = xs.min(axis=0), xs.max(axis=0)
        tf = tm = 0.0
        for _ in range(frames):
            t0 = time.perf_counter()
            out = ex.field(st.x[:nf], st.rho, lo, hi)
            _sync(sim.device)
            t1 = time.perf_counter()
            ex._cubes(*out)
            _sync(sim.device)
            tf += t1 - t0
            tm += time.perf_counter() - t1
        split = {"field_s": tf / frames, "mesh_s": tm / frames, "field_in_steps": tf / frames / step_s,
                 "mesh_in_steps": tm / frames / step_s}
    f = out[0] if split else None
    return dict(scene=str(getattr(scene, "name", "")) or str(scene_path or _scene_path().name), dim=scene.dim,
                spacing_m=float(sim.fluid.spacing), cell_m=float(getattr(ex, "last_cell", resolution or 0.0)), particles=nf, step_s=step_s, surface_s=surface_s,
                surface_in_steps=surface_s / step_s, triangles=int(len(mesh.triangles) if mesh.triangles is not None else 0),
                vertices=int(len(mesh.points)), grid_nodes=int(np.prod(getattr(f, "shape", (0,)))) if f is not None else None,
                **split)


def run(dev: str, cfg: dict) -> dict:
    from benchmarks.common import log

    cases = []
    for s, c in [(s, c) for s in cfg["surface_spacings"] for c in cfg["surface_cells"]]:
        r = measure(dev, s, cfg["surface_steps"], cfg["surface_frames"], resolution_cells=c)
        log(f"  spacing {r['spacing_m']:g} m, cell {r['cell_m']:g} m, {r['particles']} particles: step {r['step_s'] * 1e3:.1f} ms, surface "
            f"{r['surface_s'] * 1e3:.1f} ms = {r['surface_in_steps']:.2f} steps ({r['triangles']} triangles)")
        cases.append(r)
    return {"cases": cases}


def main(argv=None) -> None:
    import argparse

    import warp as wp

    p = argparse.ArgumentParser(prog="python -m benchmarks.surface", description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--scene", default=None)
    p.add_argument("--spacing", type=float, default=None)
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--frames", type=int, default=3)
    p.add_argument("--resolution", type=float, default=None, help="output.surface.resolution_m")
    a = p.parse_args(argv)
    from rockwave.base.device import quiet_warp

    quiet_warp()
    wp.init()
    from rockwave import resolve_device
    print(json.dumps(measure(resolve_device(a.device), a.spacing, a.steps, a.frames, a.scene, a.resolution), indent=1))


if __name__ == "__main__":
    main()
