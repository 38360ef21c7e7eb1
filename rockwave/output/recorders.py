"""Recorders: the outputs of a run, behind one interface that only reads the simulation.

Each frame the run loop (rockwave/app/run.py) makes one :class:`Frame` (host copies of the state, read
once and shared) and hands it to every recorder:

- :class:`UsdRecorder`: the USD stage (``output.usd``): particles with velocity, density and
  pressure, block meshes moving by their poses, the fluid surface (``output.surface``), chunks joined
  by value clips (rockwave/output/usd.py);
- :class:`CsvRecorder`: gauges.csv (``output.gauges_csv``) and blocks.csv (``output.blocks_csv``);
- :class:`VtkRecorder`: the ParaView ``.vtu``/``.pvd`` series (``output.vtk``).

A recorder has ``frame(frame)``, ``close()`` and, for checkpoints, ``checkpoint_state(tag)`` and
``restore(state)``. Every file is written atomically.
"""

from __future__ import annotations

import csv
import io
import json
import re
from functools import cached_property
from pathlib import Path

import numpy as np

from rockwave.base.files import atomic_write
from rockwave.build.preflight import INSTANCER_MIN_BLOCKS
from rockwave.output import surface as surf
from rockwave.output import usd, vtk
from rockwave.output.usd import UsdFrameWriter, points_setup
from rockwave.sim.checkpoint import csv_restore, csv_state
from rockwave.sim.energy import COLUMNS
from rockwave.sim.readers import HostWater

FLUID_PRIM = "/World/fluid"
BLOCKS_PRIM = "/World/blocks"
INSTANCER_PRIM = "/World/blocks/instances"  # the PointInstancer of many blocks (UsdRecorder._blocks_setup)
# INSTANCER_MIN_BLOCKS (rockwave/build/preflight.py, with the run-length estimate's cost of the USD output): rigid, fixed
# and kinematic blocks from which they are the instances of one PointInstancer, not one mesh prim each
BLOCK_CSV_HEADER = ["time_s", "block", "name", "x_m", "y_m", "z_m", "vx_m_s", "vy_m_s", "vz_m_s",
                    "wx_rad_s", "wy_rad_s", "wz_rad_s", "contacts"]


class Frame:
    """Host copies of a simulation's state at one output frame, read on first use and shared by the
    recorders and the blow-up guard. Reading leaves the simulation untouched (rockwave/sim/readers.py)."""

    def __init__(self, sim, index: int, surface=None):
        self.sim = sim
        self.index = index
        self.time = float(sim.time)
        self._surface = surface

    n_fluid = property(lambda self: self.sim.n_fluid)

    @cached_property
    def x(self) -> np.ndarray:
        return self.sim.readers.view("x").copy() if self.n_fluid else np.zeros((0, 3), np.float32)

    @cached_property
    def v(self) -> np.ndarray:
        return self.sim.readers.view("v").copy() if self.n_fluid else np.zeros((0, 3), np.float32)

    @cached_property
    def rho(self) -> np.ndarray:
        return self.sim.readers.view("rho").copy()

    @cached_property
    def pressure(self) -> np.ndarray:
        return self.sim.readers.view("pressure").copy()

    @cached_property
    def blocks(self) -> dict:
        st = self.sim.block_state
        return {"x": st.positions_numpy(), "q": st.orientations_numpy(), "v": st.velocities_numpy(),
                "w": st.angular_velocities_numpy(), "contacts": st.contact_counts()}

    @cached_property
    def block_vertices(self) -> list:
        return self.sim.block_state.world_vertices()

    @cached_property
    def gauges(self) -> dict:
        return self.sim.gauges()

    @cached_property
    def surface(self):
        """The fluid surface mesh (rockwave/output/surface.py), or None when the scene asks for none."""
        if self._surface is None or not self.n_fluid:
            return None
        st = self.sim.state
        xs = self.x[:, :3]
        if isinstance(st, HostWater):  # rank 0 of several: the water on the host, on the device a chunk at a time
            parts = ((a["x"], a["rho"]) for _, a in st.fluid_chunks(("x", "rho")))
            return self._surface.extract_parts(parts, xs.min(axis=0), xs.max(axis=0))
        return self._surface.extract(st.x[: self.n_fluid], st.rho, xs.min(axis=0), xs.max(axis=0))


def write_csv_atomic(path: Path, header: list[str], rows: list[list]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(header)
    for r in rows:
        w.writerow([f"{c:.6g}" if isinstance(c, float) else c for c in r])
    atomic_write(path, buf.getvalue().encode())


class CsvRecorder:
    """A CSV log with one row (or one row per block) a frame, rewritten atomically each frame."""

    def __init__(self, path: Path, header: list[str], rows_of):
        self.path, self.header, self.rows_of = Path(path), header, rows_of
        self.rows: list[list] = []

    def frame(self, f: Frame) -> None:
        self.rows.extend(self.rows_of(f))
        write_csv_atomic(self.path, self.header, self.rows)

    def close(self) -> None:
        pass

    def checkpoint_state(self, tag: str) -> dict | None:
        return csv_state(self.path, self.rows)

    def restore(self, state: dict | None) -> None:
        self.rows[:] = csv_restore(self.path, state, self.header)


def gauge_csv(path: Path, names: list[str]) -> CsvRecorder:
    return CsvRecorder(path, ["time_s"] + names, lambda f: [[f.time] + [f.gauges[n] for n in names]])


def block_csv(path: Path, names: list[str], skip=()) -> CsvRecorder:
    """blocks.csv: one row per block and frame; the blocks of ``skip`` (indices: the tank's own fixed blocks) left out."""
    keep = [(i, n) for i, n in enumerate(names) if i not in set(skip)]

    def rows(f: Frame):
        b = f.blocks
        return [[f.time, i, n, *map(float, b["x"][i]), *map(float, b["v"][i]), *map(float, b["w"][i]), int(b["contacts"][i])]
                for i, n in keep]

    return CsvRecorder(path, BLOCK_CSV_HEADER, rows)


class EnergyRecorder(CsvRecorder):
    """energy.csv (``output.energy_csv``; rockwave/sim/energy.py COLUMNS): the energy budget each frame, checked by
    the guard (a warning, or a stop with simulation.energy_check = 'error'); run.json's "energy" from ``summary()``.
    Without a file (energy_csv = '') it still measures and checks."""

    def __init__(self, sim, path: Path | None):
        self.sim = sim
        self.write = path is not None
        super().__init__(path if path is not None else Path(), COLUMNS, self._rows)

    def _rows(self, f: Frame) -> list[list]:
        sim = self.sim
        if sim.n_fluid:
            row = sim.energy.measure(f.x, f.v, f.rho)
        else:
            row = sim.energy.measure()
        sim.check_energy(row)
        return [[float(row[k]) for k in COLUMNS]]

    def frame(self, f: Frame) -> None:
        if self.write:
            super().frame(f)
        else:
            self.rows = self._rows(f)[-1:]

    def checkpoint_state(self, tag: str) -> dict | None:
        return super().checkpoint_state(tag) if self.write else None

    def restore(self, state: dict | None) -> None:
        if self.write:
            super().restore(state)
            if self.rows:  # the budget goes on from the run's start and input work, not the resumed frame's
                self.sim.energy.resume([float(c) for c in self.rows[0]], [float(c) for c in self.rows[-1]], COLUMNS)

    def summary(self) -> dict:
        return self.sim.energy.summary()


def block_prim_paths(names: list[str], reserved=()) -> list[str]:
    """Valid, unique USD prim paths /World/blocks/<name> for block names (none of them one of the ``reserved`` names)."""
    out, seen = [], set(reserved)
    for n in names:
        p = re.sub(r"[^A-Za-z0-9_]", "_", n) or "block"
        if p[0].isdigit():
            p = "b_" + p
        base, k = p, 1
        while p in seen:
            p = f"{base}_{k}"
            k += 1
        seen.add(p)
        out.append(f"{BLOCKS_PRIM}/{p}")
    return out


def _prim_names(blocks) -> list[str]:
    """Block names for prims: a compound block's first part stands for the body (its name)."""
    return [n.removesuffix(".part0") if s.compound is not None and s.compound.part == 0 else n
            for n, s in zip(blocks.names, blocks.specs)]


def scene_boxes(scene) -> list:
    """[lo, hi, 'tank' | 'obstacle'] of the scene's box tank and box obstacles (the preview draws them)."""
    out = []
    if scene.fluid is not None and scene.tank is not None and scene.tank.get("box_min_m") is not None:
        out.append([list(scene.tank.box_min_m), list(scene.tank.box_max_m), "tank"])
    for ob in scene.obstacles if scene.fluid is not None else []:
        if ob.get("box_min_m") is not None:
            out.append([list(ob.box_min_m), list(ob.box_max_m), "obstacle"])
    return out


class _MeshFaces:
    """Points and triangle faces of a compound block's original mesh, shaped like a ConvexPolyhedron
    for the USD setup (vertices, faces)."""

    def __init__(self, vertices, triangles):
        self.vertices = vertices
        self.faces = [list(t) for t in triangles]


class UsdRecorder:
    """The run's USD stage: particles, blocks and the fluid surface (rockwave/output/usd.py)."""

    def __init__(self, sim, path: Path, surface=None, progress=None):
        scene = sim.scene
        self.sim = sim
        self.dim = scene.dim
        self.nf = sim.n_fluid
        self.spacing = float(sim.fluid.spacing) if sim.fluid is not None else 0.0
        self.surface = surface
        self.blocks = sim.blocks
        self.deformable = [s.kind == "deformable" for s in sim.blocks.specs] if sim.blocks is not None else []
        # compound (non-convex) blocks: one prim, named after the body, for the first part; the others skipped
        self.skip = [s.compound is not None and s.compound.part != 0 for s in sim.blocks.specs] if sim.blocks is not None else []
        # many blocks: the rigid, fixed and kinematic ones (not compound) are instances of one PointInstancer
        can = [s.kind != "deformable" and s.compound is None for s in sim.blocks.specs] if sim.blocks is not None else []
        many = sum(can) >= INSTANCER_MIN_BLOCKS
        self.instanced = [c and many for c in can]
        self._instanced_index = np.nonzero(self.instanced)[0]
        self.n_instanced = len(self._instanced_index)
        self._orient_attr = usd.instancer_orientation_attr()
        reserved = [INSTANCER_PRIM.rsplit("/", 1)[1]] if self.n_instanced else []
        self.prims = block_prim_paths(_prim_names(sim.blocks), reserved) if sim.blocks is not None else []
        self.progress = progress  # progress(done, total) of the set-up's block prims (the run loop's line)
        self.writer = UsdFrameWriter(path, scene.output.frame_rate_hz, "Z" if self.dim == 3 else "Y", self._setup,
                                     scene.output.chunk_frames)

    def _setup(self, stage) -> None:
        from pxr import Sdf, UsdGeom

        scene = self.sim.scene
        info = {"dimension": self.dim, "spacing_m": self.spacing, "fluid_prim": FLUID_PRIM if self.nf else "",
                "surface_prim": surf.SURFACE_PRIM if self.surface is not None else "", "blocks_prim": BLOCKS_PRIM,
                "block_instancer": INSTANCER_PRIM if self.n_instanced else "", "boxes": json.dumps(scene_boxes(scene)),
                "scene": str(Path(scene.path).resolve()) if scene.path != "<scene>" else scene.path}
        layer = stage.GetRootLayer()
        data = dict(layer.customLayerData)
        data["rockwave"] = info
        layer.customLayerData = data
        if self.sim.fluid is not None:
            points_setup(FLUID_PRIM, self.nf, self.spacing)(stage)
            if self.nf:
                api = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath(FLUID_PRIM))
                for name in ("density", "pressure"):
                    api.CreatePrimvar(name, Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
        if self.surface is not None:
            surf.usd_setup(self.dim, 0.5 * self.spacing)(stage)
        if self.blocks is not None:
            self._blocks_setup(stage)

    def _blocks_setup(self, stage) -> None:
        """Static part of the block meshes: body-frame points and polygon faces; rigid, fixed and
        kinematic blocks move by time-sampled translate + orient ops, deformable ones by their points.
        Authored as Sdf specs in batches (rockwave/output/usd.py define_meshes: the set-up grows linearly with the
        block count). From INSTANCER_MIN_BLOCKS blocks on, the rigid, fixed and kinematic ones (not compound) are
        the instances of one PointInstancer (INSTANCER_PRIM) whose prototypes are their distinct geometries, posed
        by two arrays per frame (positions, orientations) instead of two time samples per block."""
        layer = stage.GetRootLayer()
        meshes, keys = [], {}
        for b, (spec, prim) in enumerate(zip(self.blocks.specs, self.prims)):
            if self.skip[b] or self.instanced[b]:
                continue
            geo = spec.geometry
            if spec.compound is not None:  # a compound block is one prim: its original mesh, posed by its first part
                geo = _MeshFaces(spec.compound.body.mesh_vertices, spec.compound.body.mesh_triangles)
            key = keys.setdefault(id(geo), len(keys))
            deformable = spec.kind == "deformable"  # its points come from the clips (a default would hide them)
            meshes.append((prim.rsplit("/", 1)[1], key, None if deformable else geo.vertices, geo.faces, not deformable))
        total = len(meshes) + (1 if self.n_instanced else 0)
        usd.define_meshes(layer, BLOCKS_PRIM, meshes, progress=self._progress_of(total))
        if self.n_instanced:
            protos, index, by_geo = [], [], {}
            for b, spec in enumerate(self.blocks.specs):
                if self.instanced[b]:
                    k = by_geo.get(id(spec.geometry))
                    if k is None:
                        k = by_geo[id(spec.geometry)] = len(protos)
                        protos.append((spec.geometry.vertices, spec.geometry.faces))
                    index.append(k)
            usd.define_instancer(layer, INSTANCER_PRIM, protos, np.asarray(index), np.nonzero(self.instanced)[0])
            if self.progress is not None:
                self.progress(total, total)

    def _progress_of(self, total: int):
        if self.progress is None:
            return None
        return lambda done, _: self.progress(done, total)

    def frame(self, f: Frame) -> None:
        from pxr import Gf

        samples = {}
        if self.sim.fluid is not None:
            samples[(FLUID_PRIM, "points", "point3f[]")] = f.x
            samples[(FLUID_PRIM, "velocities", "vector3f[]")] = f.v
            if self.nf:
                samples[(FLUID_PRIM, "primvars:density", "float[]")] = f.rho
                samples[(FLUID_PRIM, "primvars:pressure", "float[]")] = f.pressure
        if self.blocks is not None:
            b = f.blocks
            verts = f.block_vertices if any(self.deformable) else None
            if self.n_instanced:
                inst = self._instanced_index
                samples[(INSTANCER_PRIM, "positions", "point3f[]")] = b["x"][inst]
                samples[(INSTANCER_PRIM, *self._orient_attr)] = b["q"][inst]  # (x, y, z, w): Gf.Quatf's memory order
            for i, prim in enumerate(self.prims):
                if self.skip[i] or self.instanced[i]:
                    continue
                if self.deformable[i]:
                    samples[(prim, "points", "point3f[]")] = verts[i]
                else:
                    q = b["q"][i]
                    samples[(prim, "xformOp:translate", "double3")] = b["x"][i]
                    samples[(prim, "xformOp:orient", "quatf")] = Gf.Quatf(float(q[3]), float(q[0]), float(q[1]), float(q[2]))
        if f.surface is not None:
            samples.update(surf.usd_samples(f.surface))
        self.writer.write_frame(f.index, samples)

    def close(self) -> None:
        self.writer.close()

    def checkpoint_state(self, tag: str) -> dict:
        return self.writer.checkpoint_state(tag)

    def restore(self, state: dict | None) -> None:
        if state is not None:
            self.writer.restore_checkpoint_state(state)


class VtkRecorder:
    """The ParaView series: fluid (points with velocity, density, pressure), blocks, surface."""

    def __init__(self, sim, folder: Path):
        self.sim = sim
        self.dim = sim.scene.dim
        self.series = vtk.VtkSeries(folder)

    def frame(self, f: Frame) -> None:
        d = self.dim
        if f.n_fluid:
            self.series.write(f.index, f.time, "fluid", vtk.fluid_vtu(f.x[:, :d], f.v[:, :d], f.rho, f.pressure))
        if self.sim.blocks is not None:
            specs = self.sim.blocks.specs
            parts = [(v, [list(face) for face in specs[b].geometry.faces]) for b, v in enumerate(f.block_vertices)]
            if parts:
                self.series.write(f.index, f.time, "blocks", vtk.blocks_vtu(parts))
        if f.surface is not None:
            self.series.write(f.index, f.time, "surface", vtk.surface_vtu(f.surface))
        self.series.flush()

    def close(self) -> None:
        pass

    def checkpoint_state(self, tag: str) -> list:
        return [list(e) for e in self.series.entries]

    def restore(self, state: list | None) -> None:
        if state is not None:
            self.series.entries = [tuple(e) for e in state]
