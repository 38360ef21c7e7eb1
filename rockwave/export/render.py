"""Render-ready outputs of a run, hooked into :meth:`rockwave.Simulation.run` with two calls:
``usd_setup(stage)`` when the stage is made and ``frame(frame, samples)`` once per frame.

What they add:
- USD: root-layer ``customLayerData["rockwave"]`` (dimension, particle spacing, scene path, prim
  paths; ``python -m rockwave preview`` reads it); per-particle ``primvars:density`` and
  ``primvars:pressure`` on ``/World/fluid`` (vertex interpolation, time-sampled); the fluid
  surface ``/World/fluid_surface`` (``output.surface``; see :mod:`rockwave.export.surface`);
- ParaView: the ``.vtu``/``.pvd`` series of ``output.vtk`` (see :mod:`rockwave.export.vtk`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rockwave.export import surface as surf
from rockwave.export import vtk

FLUID_PRIM = "/World/fluid"


class RenderOutputs:
    def __init__(self, sim, out_dir: str | Path):
        self.sim = sim
        scene = sim.scene
        self.dim = scene.dim
        fluid = getattr(sim, "fluid", None)
        self.nf = int(fluid.n_fluid) if fluid is not None else 0
        self.spacing = float(fluid.spacing) if fluid is not None else 0.0
        wanted = bool(scene.output.usd or scene.output.get("vtk"))  # the surface goes nowhere else
        self.surface = surf.extractor_for(scene, fluid, sim.device) if self.nf and wanted else None
        self.vtk = vtk.VtkSeries(Path(out_dir) / scene.output.vtk) if scene.output.get("vtk") else None
        self.last_surface: surf.SurfaceMesh | None = None

    # ---------------------------------------------------------------------------------- USD --
    def usd_setup(self, stage) -> None:
        from pxr import Sdf, UsdGeom

        scene = self.sim.scene
        info = {"dimension": self.dim, "spacing_m": self.spacing, "fluid_prim": FLUID_PRIM if self.nf else "",
                "surface_prim": surf.SURFACE_PRIM if self.surface is not None else "", "blocks_prim": "/World/blocks",
                "scene": str(Path(scene.path).resolve()) if scene.path != "<scene>" else scene.path}
        layer = stage.GetRootLayer()
        data = dict(layer.customLayerData)
        data["rockwave"] = info
        layer.customLayerData = data
        if self.nf:
            api = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath(FLUID_PRIM) or UsdGeom.Points.Define(stage, FLUID_PRIM).GetPrim())
            for name in ("density", "pressure"):
                api.CreatePrimvar(name, Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
        if self.surface is not None:
            surf.usd_setup(self.dim, 0.5 * self.spacing)(stage)

    # -------------------------------------------------------------------------------- frames --
    def frame(self, frame: int, samples: dict) -> None:
        """Add this frame's surface and fluid fields to ``samples`` (the USD time samples) and
        write the ParaView files."""
        sim = self.sim
        x = v = rho = p = None
        if self.nf:
            x = samples.get((FLUID_PRIM, "points", "point3f[]"))
            v = samples.get((FLUID_PRIM, "velocities", "vector3f[]"))
            if x is None:
                x = sim.state.x.numpy()[: self.nf]
            if v is None:
                v = sim.state.v.numpy()[: self.nf]
            rho = sim.state.rho.numpy()[: self.nf]
            p = sim.state.pressure.numpy()[: self.nf]
            samples[(FLUID_PRIM, "primvars:density", "float[]")] = rho
            samples[(FLUID_PRIM, "primvars:pressure", "float[]")] = p
        mesh = None
        if self.surface is not None:
            xs = x[:, :3]
            mesh = self.surface.extract(sim.state.x[: self.nf], sim.state.rho, xs.min(axis=0), xs.max(axis=0))
            samples.update(surf.usd_samples(mesh))
            self.last_surface = mesh
        if self.vtk is not None:
            t = float(sim.time)
            if self.nf:
                self.vtk.write(frame, t, "fluid", vtk.fluid_vtu(x[:, : self.dim], v[:, : self.dim], rho, p))
            blocks = self._blocks()
            if blocks:
                self.vtk.write(frame, t, "blocks", vtk.blocks_vtu(blocks))
            if mesh is not None:
                self.vtk.write(frame, t, "surface", vtk.surface_vtu(mesh))
            self.vtk.flush()

    def _blocks(self) -> list:
        model, state = getattr(self.sim, "blocks", None), getattr(self.sim, "block_state", None)
        if model is None or state is None:
            return []
        verts = state.world_vertices()
        return [(verts[b], [list(f) for f in model.specs[b].geometry.faces]) for b in range(len(verts))]
