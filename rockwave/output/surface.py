"""Fluid surface for rendering: a smooth scalar field of the particles on a grid, then an
isosurface (3D: Warp's marching cubes, a triangle mesh) or an isoline (2D: marching squares,
line segments in the z = 0 plane), all on the simulation's device.

The field (``output.surface.field``) is the SPH colour field or the metaball field of the Ghost
SPH report (formulas in ``kernels/output/surface.py``); both are ~1 inside the water and fall to 0 over
the support radius R = radius_ratio x spacing, so the default iso-level 0.5 puts the surface half
a particle spacing outside the outermost particle layer, where the continuum the particles stand
for ends. The grid covers the particles' bounding box plus R and one cell, so the surface is
closed (water against a tank wall is closed just inside the wall).

Grid cell (``output.surface.resolution_m``): by default one particle spacing in 3D and half a spacing
in 2D (:func:`default_cell`). The field is smooth over R = 2 spacings, so a cell of one spacing puts a
flat surface within ~0.06 spacing of where the half-spacing grid puts it (tests/test_outputs.py), while
the 3D grid has ~8x fewer nodes: on the CPU a frame's surface of scenes/wave_maker.toml costs ~1.4 fluid
steps instead of ~7.5 (python -m benchmarks.surface). 2D grids are small either way. The grid and the
particle-cell buffers are kept from frame to frame and only grow (no allocation per frame once the
water's box stops growing).

In the USD stage the surface is ``/World/fluid_surface``: a ``UsdGeom.Mesh`` (3D; points,
faceVertexCounts, faceVertexIndices, normals and extent time-sampled each frame, no subdivision)
or linear ``UsdGeom.BasisCurves`` (2D; one two-point curve per segment).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from rockwave.kernels.output import surface as surface_k
from rockwave.scene.format import SCHEMA

# the defaults of [output.surface], whose one home is the scene schema (rockwave/scene/format.py)
_SURFACE = {k: v.default for k, v in SCHEMA["output"].children["surface"].children.items()}

SURFACE_PRIM = "/World/fluid_surface"


@dataclass
class SurfaceMesh:
    """One frame's surface. 3D: ``points`` (V, 3) and ``triangles`` (T, 3) int, counter-clockwise
    seen from outside the water. 2D: ``points`` (2 S, 3) with z = 0 and ``segments`` (S, 2),
    each running with the water on its left."""

    dim: int
    points: np.ndarray
    triangles: np.ndarray | None = None
    segments: np.ndarray | None = None

    @property
    def empty(self) -> bool:
        return len(self.points) == 0

    def normals(self) -> np.ndarray:
        """Area-weighted vertex normals (3D), pointing out of the water."""
        n = np.zeros_like(self.points, dtype=np.float64)
        if self.triangles is None or len(self.triangles) == 0:
            return n
        p = self.points.astype(np.float64)
        t = self.triangles
        fn = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
        nv = len(p)
        for c in range(3):
            for k in range(3):
                n[:, k] += np.bincount(t[:, c], weights=fn[:, k], minlength=nv)
        ln = np.linalg.norm(n, axis=1, keepdims=True)
        return n / np.where(ln > 0, ln, 1.0)


def default_cell(dim: int, spacing: float) -> float:
    """Grid cell of the surface field when ``output.surface.resolution_m`` is not set: one particle spacing
    in 3D, half a spacing in 2D (module docstring)."""
    return float(spacing) * (1.0 if int(dim) == 3 else 0.5)


def _marching_cubes_class():
    """Warp's marching cubes: wp.geometry.IsoSurfaceMarchingCubes (Warp >= 1.19; a submodule that
    ``import warp`` does not load), else the older wp.MarchingCubes (deprecated, with a printed note, in 1.19)."""
    try:
        import importlib

        cls = getattr(importlib.import_module("warp.geometry"), "IsoSurfaceMarchingCubes", None)
    except ImportError:
        cls = None
    return cls if cls is not None else wp.MarchingCubes


class SurfaceExtractor:
    """Builds the field and extracts the surface for one frame at a time.

    ``dim``: 2 or 3; ``spacing``: particle spacing [m]; ``mass``: fluid particle mass [kg];
    ``resolution_m``: grid cell (default :func:`default_cell`: the spacing in 3D, half of it in 2D);
    ``radius_ratio``: R / spacing;
    ``iso_level``: field value of the surface; ``field``: 'colour' or 'metaball';
    ``max_grid_nodes``: the cell grows when the particles' box would need more nodes.
    """

    def __init__(self, dim: int, spacing: float, mass: float, device, resolution_m: float | None = None,
                 radius_ratio: float = _SURFACE["radius_ratio"], iso_level: float = _SURFACE["iso_level"],
                 field: str = _SURFACE["field"], max_grid_nodes: int = _SURFACE["max_grid_nodes"]):
        if field not in ("colour", "metaball"):
            raise ValueError(f"surface field {field!r}: expected 'colour' or 'metaball'")
        self.dim = int(dim)
        self.spacing = float(spacing)
        self.mass = float(mass)
        self.device = wp.get_device(device)
        self.cell = float(resolution_m) if resolution_m else default_cell(self.dim, self.spacing)
        self.radius = float(radius_ratio) * self.spacing
        self.iso = float(iso_level)
        self.kind = 0 if field == "colour" else 1
        self.max_nodes = int(max_grid_nodes)
        R = self.radius
        v_r = 32.0 * math.pi * R**3 / 105.0 if self.dim == 3 else math.pi * R * R / 3.0
        self.metaball_norm = self.spacing**self.dim / v_r
        self.last_cell = self.cell
        # nodes per thread along x in the field gather (kernels/output/surface.py fluid_field): they share the
        # bookkeeping of the rows of cells they visit; fewer on a GPU, which wants threads
        self.node_run = 4 if self.device.is_cuda else 32
        self._buffers: dict[str, wp.array] = {}  # kept from frame to frame (_buffer)

    def _buffer(self, name: str, n: int, dtype) -> wp.array:
        """A 1D array of at least ``n`` elements kept under ``name`` from call to call (grown by 1.5x when too
        small, so a slowly growing box reallocates rarely); callers use its first n elements."""
        b = self._buffers.get(name)
        if b is None or b.shape[0] < n:
            b = wp.empty(max(int(n), int(1.5 * b.shape[0]) if b is not None else 0), dtype=dtype, device=self.device)
            self._buffers[name] = b
        return b

    def field(self, x: wp.array, rho: wp.array, lo: np.ndarray, hi: np.ndarray, parts=None):
        """The scalar field on the grid covering [lo, hi] padded by R + one cell.
        Returns (field wp.array3d, lower corner (3,), cell size); the field is a view of a buffer the
        extractor reuses, valid until its next call. ``parts``: (x, rho) pairs of device arrays whose fields
        are summed (the chunks of water held on the host: the field is a sum over particles), instead of x, rho."""
        pad = self.radius + self.cell
        lower = np.asarray(lo, np.float64)[:3] - pad
        upper = np.asarray(hi, np.float64)[:3] + pad
        if self.dim == 2:
            lower[2] = upper[2] = 0.0
        cell = self.cell
        while True:
            n = np.maximum(np.ceil((upper - lower) / cell).astype(np.int64) + 1, 2)
            if self.dim == 2:
                n[2] = 1
            if int(np.prod(n)) <= self.max_nodes:
                break
            cell *= 1.25
        self.last_cell = cell
        lower32 = wp.vec3(*lower.astype(np.float32))
        shape = tuple(int(c) for c in n)
        size = int(np.prod(n))
        buf = self._buffer("field", size, float)
        f = buf[:size].reshape(shape)  # a view of the kept buffer
        f.zero_()
        with wp.ScopedDevice(self.device):
            for px, prho in (parts if parts is not None else [(x, rho)]):
                g = self._particle_cells(px, prho, lower, (n - 1) * cell)
                run = self.node_run
                wp.launch(surface_k.fluid_field, dim=((f.shape[0] + run - 1) // run, f.shape[1], f.shape[2]),
                          inputs=[g, lower32, float(cell), self.radius, self.kind, self.dim, float(self.metaball_norm),
                                  run], outputs=[f])
        return f, lower, cell

    def _particle_cells(self, x: wp.array, rho: wp.array, lower: np.ndarray, extent: np.ndarray) -> surface_k.ParticleCells:
        """The particles sorted by cell of a dense grid over the field's box (cells of width R/2, wider when
        the box would need more than max_grid_nodes cells; kernels/output/surface.py), for the gather."""
        n = len(x)
        c = 0.5 * self.radius
        while True:
            nc = np.maximum(np.floor(np.asarray(extent, np.float64) / c).astype(np.int64) + 1, 1)
            if self.dim == 2:
                nc[2] = 1
            if int(np.prod(nc)) <= self.max_nodes:
                break
            c *= 1.25
        g = surface_k.ParticleCells()
        g.lo = wp.vec3(*np.asarray(lower, np.float32)[:3])
        g.c = float(c)
        g.inv_c = float(1.0 / c)
        g.nx, g.ny, g.nz = (int(v) for v in nc)
        # radix_sort_pairs sorts in place and needs 2 n of room
        keys = self._buffer("keys", 2 * n, int)[: 2 * n]
        order = self._buffer("order", 2 * n, int)[: 2 * n]
        wp.launch(surface_k.particle_cell_keys, dim=n, inputs=[g, x], outputs=[keys, order])
        wp.utils.radix_sort_pairs(keys, order, n)
        ncell = int(np.prod(nc)) + 1
        g.first = self._buffer("first", ncell, int)[:ncell]
        wp.launch(surface_k.cell_starts, dim=ncell, inputs=[keys, n], outputs=[g.first])
        g.x_sorted = self._buffer("x_sorted", n, wp.vec3)[:n]
        g.w_sorted = self._buffer("w_sorted", n, float)[:n]
        wp.launch(surface_k.gather_sorted_particles, dim=n, inputs=[order, x, rho, self.mass], outputs=[g.x_sorted, g.w_sorted])
        return g

    def extract(self, x: wp.array, rho: wp.array, lo=None, hi=None) -> SurfaceMesh:
        """Surface of the fluid particles ``x`` (wp.array of vec3, fluid only) with densities
        ``rho``; ``lo``/``hi``: their bounding box (read from ``x`` when not given)."""
        if len(x) == 0:
            return self._empty()
        if lo is None or hi is None:
            xn = x.numpy()
            lo, hi = xn.min(axis=0), xn.max(axis=0)
        f, lower, cell = self.field(x, rho, lo, hi)
        if self.dim == 3:
            return self._cubes(f, lower, cell)
        return self._squares(f, lower, cell)

    def extract_parts(self, parts, lo, hi) -> SurfaceMesh:
        """Surface of the water given as (x, rho) chunks of device arrays (an iterable; the field of each added,
        field()) whose particles lie in the box [lo, hi]."""
        f, lower, cell = self.field(None, None, lo, hi, parts=parts)
        if self.dim == 3:
            return self._cubes(f, lower, cell)
        return self._squares(f, lower, cell)

    def _empty(self) -> SurfaceMesh:
        if self.dim == 3:
            return SurfaceMesh(3, np.zeros((0, 3), np.float32), triangles=np.zeros((0, 3), np.int32))
        return SurfaceMesh(2, np.zeros((0, 3), np.float32), segments=np.zeros((0, 2), np.int32))

    def _cubes(self, f, lower, cell) -> SurfaceMesh:
        n = np.asarray(f.shape)
        upper = lower + (n - 1) * cell
        with wp.ScopedDevice(self.device):
            verts, tris = _marching_cubes_class().extract(f, self.iso, lower=wp.vec3(*lower.astype(np.float32)),
                                                          upper=wp.vec3(*upper.astype(np.float32)))
        pts = verts.numpy().astype(np.float32).reshape(-1, 3)
        t = tris.numpy().astype(np.int32).reshape(-1, 3)
        # Warp's tables wind triangles clockwise seen from the high side of the field (the water);
        # reverse them so that the right-handed normal points out of the water.
        t = np.ascontiguousarray(t[:, ::-1])
        return SurfaceMesh(3, pts, triangles=t)

    def _squares(self, f, lower, cell) -> SurfaceMesh:
        nx, ny = f.shape[0], f.shape[1]
        nc = (nx - 1) * (ny - 1)
        seg = wp.zeros(4 * nc, dtype=wp.vec3, device=self.device)
        cnt = wp.zeros(nc, dtype=int, device=self.device)
        with wp.ScopedDevice(self.device):
            wp.launch(surface_k.marching_squares, dim=(nx - 1, ny - 1), inputs=[f, self.iso, wp.vec3(*lower.astype(np.float32)), float(cell)],
                      outputs=[seg, cnt])
        c = cnt.numpy()
        s = seg.numpy().reshape(nc, 2, 2, 3)
        keep = np.concatenate([s[c >= 1, 0], s[c >= 2, 1]]).reshape(-1, 3).astype(np.float32)
        ns = len(keep) // 2
        return SurfaceMesh(2, keep, segments=np.arange(2 * ns, dtype=np.int32).reshape(ns, 2))


def extractor_for(scene, model, device) -> SurfaceExtractor | None:
    """The extractor a scene's ``[output.surface]`` asks for, or None when disabled."""
    s = scene.output.get("surface")
    if not s or not s.get("enabled", False) or model.n_fluid == 0:
        return None
    return SurfaceExtractor(scene.dim, model.spacing, model.fluid_mass, device, resolution_m=s.get("resolution_m"),
                            **{k: s.get(k, _SURFACE[k]) for k in ("radius_ratio", "iso_level", "field", "max_grid_nodes")})


# ------------------------------------------------------------------------------------------ USD
def usd_setup(dim: int, width: float, prim_path: str = SURFACE_PRIM):
    """Static part of the surface prim (a setup callable for UsdFrameWriter)."""

    def setup(stage):
        from pxr import UsdGeom, Vt

        if dim == 3:
            m = UsdGeom.Mesh.Define(stage, prim_path)
            m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            m.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
            m.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
            m.CreateDoubleSidedAttr(False)
        else:
            c = UsdGeom.BasisCurves.Define(stage, prim_path)
            c.CreateTypeAttr(UsdGeom.Tokens.linear)
            c.CreateWidthsAttr(Vt.FloatArray([float(width)]))
            c.SetWidthsInterpolation(UsdGeom.Tokens.constant)

    return setup


def usd_samples(mesh: SurfaceMesh, prim_path: str = SURFACE_PRIM) -> dict:
    """One frame of time samples for UsdFrameWriter.write_frame."""
    p = mesh.points.astype(np.float32)
    ext = np.array([p.min(axis=0), p.max(axis=0)], np.float32) if len(p) else np.zeros((2, 3), np.float32)
    out = {(prim_path, "points", "point3f[]"): p, (prim_path, "extent", "float3[]"): ext}
    if mesh.dim == 3:
        t = mesh.triangles
        out[(prim_path, "faceVertexCounts", "int[]")] = np.full(len(t), 3, np.int32)
        out[(prim_path, "faceVertexIndices", "int[]")] = t.reshape(-1).astype(np.int32)
        out[(prim_path, "normals", "normal3f[]")] = mesh.normals().astype(np.float32)
    else:
        out[(prim_path, "curveVertexCounts", "int[]")] = np.full(len(mesh.segments), 2, np.int32)
    return out
