"""One slab of the water without the rest: the seeding of a rank of a run on several processes (docs/mpi.md).

The whole scene's seeding (builder.seed_fluid) makes every particle, then filters them. A rank of a distributed
run needs only its slab, but three whole-scene facts: the slab faces (equal-count quantiles of the particles'
coordinates along the decomposition axis), each particle's id (its index in the whole scene's seeding order: the
outputs and checkpoints are in that order), and the water's bounding box and first particle (where the fixed
blocks' wall particles go, the domain of the cell grids). :func:`fluid_layout` finds them by a host pass over the
lattice in windows along x, holding one window at a time: it counts the kept particles of each lattice column
(the lattice points sharing their horizontal indices) of each region. :func:`seed_fluid_slab` then makes the
particles of one range along a horizontal axis, with the same positions, velocities, depths and ids as the whole
scene's seeding (tests/test_slab_seeding.py), and no more than that range's particles plus a margin of two
spacings on each side (the packed start moves particles along their column only; the margin keeps the columns
whole).

The ids: the whole seeding runs region by region, each region's lattice in numpy's "ij" order (x slowest, the
vertical axis fastest), and drops points (tank, obstacles, blocks). A kept point's id is the kept points of the
regions before, plus those of its region's columns before its own (an exclusive prefix sum of the column counts),
plus its rank among the kept points of its column.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from rockwave.base.maths import pad3
from rockwave.build import sampling
from rockwave.build.builder import (
    FluidSeeds,
    Parts,
    block_walls_on,
    boundary_particles,
    fixed_block_walls,
    fluid_keep,
    packed_start,
    seeding_clearance,
)
from rockwave.build.options import boundary_lattice, gravity_norm, sph_params
from rockwave.build.rocks import inside_blocks_message
from rockwave.coupling.penalty import block_signed_distance
from rockwave.scene.format import Scene, SceneError
from rockwave.sph.fluid import hydrostatic_density

WINDOW_POINTS = 2_000_000  # lattice points a window of the layout pass holds at most (about)


@dataclass
class _Region:
    axes: list  # lattice coordinates along each of the scene's dim axes
    mesh: object  # trimesh of a mesh region (None: a box)
    velocity: np.ndarray
    top: float = -math.inf  # highest lattice point inside the region (before the tank and obstacles)
    counts: np.ndarray | None = None  # kept points per column (flat index over the horizontal lattice indices)
    prefix: np.ndarray | None = None  # exclusive prefix sum of counts, plus the regions before
    offset: int = 0  # kept points of the regions before


@dataclass
class FluidLayout:
    """What a slab's seeding needs of the whole scene's water (:func:`fluid_layout`), without its particles."""

    n_fluid: int
    """Particles of the whole scene's water (after the tank, obstacles and blocks)."""

    lo: np.ndarray
    """(3,) lowest coordinates of the seeded water (after the packed start, as builder.seed_fluid leaves it)."""

    hi: np.ndarray
    """(3,) highest coordinates of the seeded water."""

    first: np.ndarray
    """(3,) position of particle 0 (the fixed blocks' wall lattice is anchored on it)."""

    boundary: np.ndarray
    """The static boundary particles (tank, obstacles, the fixed blocks' Adami walls), as the whole seeding's."""

    removed_inside_blocks: int = 0
    """Lattice points dropped inside blocks, whole scene."""

    peak_points: int = 0
    """The most lattice points the pass held at once."""

    regions: list = field(default_factory=list)

    def plane_counts(self, axis: int) -> tuple[np.ndarray, np.ndarray]:
        """(coordinates, particles) of the lattice planes normal to the horizontal ``axis``, sorted by coordinate:
        the exact distribution of the particles' coordinates along it (the packed start moves them vertically
        only)."""
        cs, ns = [], []
        for r in self.regions:
            shape = [len(a) for a in r.axes[:-1]]
            per = r.counts.reshape(shape)
            other = tuple(k for k in range(len(shape)) if k != axis)
            cs.append(r.axes[axis])
            ns.append(per.sum(axis=other) if other else per)
        c, n = np.concatenate(cs), np.concatenate(ns).astype(np.int64)
        order = np.argsort(c, kind="stable")
        return c[order], n[order]


def quantile_from_counts(coords: np.ndarray, counts: np.ndarray, q: float) -> float:
    """np.quantile(c, q) (its default "linear" method) of the sorted coordinates c that hold coords[k] counts[k]
    times, without making c: the two order statistics around q (n - 1) and numpy's interpolation between them."""
    cum = np.cumsum(counts)
    n = int(cum[-1])
    pos = q * (n - 1)
    k = int(math.floor(pos))
    a = coords[int(np.searchsorted(cum, k, side="right"))]
    b = coords[int(np.searchsorted(cum, min(k + 1, n - 1), side="right"))]
    return float(np.quantile(np.array([a, b]), pos - k))


def _regions(scene: Scene, device: str) -> list[_Region]:
    fl, dim = scene.fluid, scene.dim
    out = []
    for r in fl.regions:
        if r.get("box_min_m") is not None:
            axes = [sampling.lattice_axis(a, b, fl.spacing_m) for a, b in zip(r["box_min_m"], r["box_max_m"])]
            mesh = None
        else:
            if dim != 3:
                raise ValueError("slab seeding: mesh regions in 2D")
            try:
                mesh = sampling.load_trimesh(r["mesh"], r["mesh_scale"], r["mesh_offset_m"])
            except sampling.MeshInputError as e:
                raise SceneError(scene.path, [("fluid.regions", str(e))]) from None
            axes = [sampling.lattice_axis(a, b, fl.spacing_m) for a, b in zip(mesh.bounds[0], mesh.bounds[1])]
        vel = pad3(r.velocity_m_s) if r.velocity_m_s is not None else [0.0, 0.0, 0.0]
        out.append(_Region(axes=axes, mesh=mesh, velocity=np.asarray(vel, float)))
    return out


def _region_window(reg: _Region, axis: int, lo: float, hi: float, device, dim: int):
    """The region's lattice points with coordinate ``axis`` in [lo, hi), in the whole lattice's "ij" order:
    positions (n, 3), column index, and the mesh test (inside the region's mesh; all for a box)."""
    ax = reg.axes[axis]
    sel = np.flatnonzero((ax >= lo) & (ax < hi))
    if len(sel) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    axes = [np.arange(len(a)) for a in reg.axes]
    axes[axis] = sel
    idx = np.meshgrid(*axes, indexing="ij")
    pts = np.zeros((idx[0].size, 3))
    for k in range(dim):
        pts[:, k] = reg.axes[k][idx[k].ravel()]
    shape = [len(a) for a in reg.axes[:-1]]
    col = np.ravel_multi_index(tuple(i.ravel() for i in idx[:-1]), shape) if len(shape) > 1 else idx[0].ravel()
    col = np.asarray(col, np.int64)
    if reg.mesh is not None:
        inside = sampling.mesh_signed_distance(reg.mesh, pts, device) < 0.0
        pts, col = pts[inside], col[inside]
    return pts, col


def _window(scene: Scene, device, parts: Parts, options, regions, axis: int, lo: float, hi: float, origin,
            with_ids: bool = False):
    """The water of [lo - margin, hi + margin) along ``axis`` through the whole seeding's steps (tank, obstacles,
    blocks, packed start with the whole water's ``origin``), then cut to [lo, hi): positions, velocities, depths,
    (region, column) of each point, the points held, the points removed inside blocks, and the ids (with_ids)."""
    fl, dim = scene.fluid, scene.dim
    up, s = dim - 1, fl.spacing_m
    margin = 2.0 * s
    xs, vs, ds, rs, cs = [], [], [], [], []
    for k, reg in enumerate(regions):
        p, col = _region_window(reg, axis, lo - margin, hi + margin, device, dim)
        xs.append(p)
        ds.append(reg.top + 0.5 * s - p[:, up])
        vs.append(np.tile(reg.velocity, (len(p), 1)))
        rs.append(np.full(len(p), k, np.int64))
        cs.append(col)
    x, v, depth, reg, col = (np.concatenate(a) for a in (xs, vs, ds, rs, cs))
    held = len(x)
    keep = fluid_keep(scene, device, x)
    removed = 0
    if parts.blocks is not None and len(x):
        dist, _ = block_signed_distance(parts.blocks, parts.block_state, x[keep])
        inb = dist < seeding_clearance(scene, options)  # as the whole scene's seeding (builder.remove_inside_blocks)
        removed_mask = np.zeros(len(x), bool)
        removed_mask[np.flatnonzero(keep)[inb]] = True
        keep &= ~removed_mask
        inner = (x[:, axis] >= lo) & (x[:, axis] < hi)
        removed = int((removed_mask & inner).sum())
    x, v, depth, reg, col = x[keep], v[keep], depth[keep], reg[keep], col[keep]
    if fl.packed_start and len(x) and origin is not None:
        rho0 = fl.rest_density_kg_m3
        params = sph_params(scene, max(len(x), 1))
        g = gravity_norm(scene)
        x = packed_start(x, depth, lambda d: hydrostatic_density(params, g * d) / rho0, s, up, origin=origin)
    inner = (x[:, axis] >= lo) & (x[:, axis] < hi)
    ids = None
    if with_ids:  # the whole seeding's order: region, column, then up the column (module doc)
        key = reg * (1 << 40) + col
        first = np.searchsorted(key, key)  # points of one (region, column) are contiguous, in order
        within = np.arange(len(key)) - first
        base = np.zeros(len(key), np.int64)
        for k, r in enumerate(regions):
            m = reg == k
            base[m] = r.prefix[col[m]]
        ids = base + within
        ids = ids[inner]
    return x[inner], v[inner], depth[inner], reg[inner], col[inner], held, removed, ids


def _windows(regions, n_points: int) -> np.ndarray:
    """Window edges along x over the regions' lattices, about WINDOW_POINTS points each."""
    lo = min(r.axes[0][0] for r in regions)
    hi = max(r.axes[0][-1] for r in regions)
    k = max(1, math.ceil(n_points / WINDOW_POINTS))
    edges = np.linspace(lo, hi, k + 1)
    edges[0], edges[-1] = -math.inf, math.inf
    return edges


def fluid_layout(scene: Scene, device: str, parts: Parts, options=None) -> FluidLayout:
    """The whole scene's water without its particles (module doc): per-column counts of each region, its bounds
    and first particle, its static walls. ``parts``: the blocks already built (their removal counts)."""
    fl, dim = scene.fluid, scene.dim
    if not fl.regions:
        raise ValueError("slab seeding: no fluid regions")
    regions = _regions(scene, device)
    n_points = sum(int(np.prod([len(a) for a in r.axes])) for r in regions)
    edges = _windows(regions, n_points)
    up = dim - 1
    peak = 0
    for reg in regions:  # each region's top: its highest lattice point inside its box or mesh
        if reg.mesh is None:
            reg.top = float(reg.axes[up][-1])
        else:
            for a, b in zip(edges[:-1], edges[1:]):
                p, _ = _region_window(reg, 0, a, b, device, dim)
                peak = max(peak, len(p))
                if len(p):
                    reg.top = max(reg.top, float(p[:, up].max()))
    for reg in regions:
        reg.counts = np.zeros(int(np.prod([len(a) for a in reg.axes[:-1]])), np.int64)
    lo, hi = np.full(3, math.inf), np.full(3, -math.inf)
    removed = 0
    for a, b in zip(edges[:-1], edges[1:]):  # counts per column (no packing: it moves points along columns only)
        x, _, _, reg, col, held, rem, _ = _window(scene, device, parts, options, regions, 0, a, b, None)
        peak, removed = max(peak, held), removed + rem
        for k, r in enumerate(regions):
            r.counts += np.bincount(col[reg == k], minlength=len(r.counts))
        if len(x):
            lo, hi = np.minimum(lo, x.min(axis=0)), np.maximum(hi, x.max(axis=0))
    n = 0
    for r in regions:
        r.offset = n
        r.prefix = n + np.concatenate([[0], np.cumsum(r.counts)[:-1]]).astype(np.int64)
        n += int(r.counts.sum())
    if n == 0:
        raise ValueError("slab seeding: the scene seeds no water")
    if dim == 2:
        lo[2] = hi[2] = 0.0
    first = None
    if fl.packed_start:  # the packed top and particle 0 (the packing moves them): a second pass
        hi[up] = -math.inf
        for a, b in zip(edges[:-1], edges[1:]):
            x, _, _, _, _, held, _, ids = _window(scene, device, parts, options, regions, 0, a, b, lo, with_ids=True)
            peak = max(peak, held)
            if len(x):
                hi[up] = max(hi[up], float(x[:, up].max()))
                if first is None and (ids == 0).any():
                    first = x[int(np.flatnonzero(ids == 0)[0])]
    else:
        for a, b in zip(edges[:-1], edges[1:]):
            x, _, _, _, _, held, _, ids = _window(scene, device, parts, options, regions, 0, a, b, None, with_ids=True)
            if len(x) and (ids == 0).any():
                first = x[int(np.flatnonzero(ids == 0)[0])]
                break
    if removed:
        warnings.warn(inside_blocks_message(removed, n + removed), stacklevel=2)
    parts.removed_inside_blocks = removed
    xb = boundary_particles(scene, device)
    bstep, layers = boundary_lattice(scene)
    bounds = (lo.copy(), hi.copy(), np.asarray(first, float))
    if scene.fluid.boundary == "adami" and parts.blocks is not None:
        xw = fixed_block_walls(scene, parts, bounds, bstep, layers, seeding_clearance(scene, options))
        if len(xw):
            xb = np.concatenate([xb, xw]) if len(xb) else xw
    if parts.blocks is not None and block_walls_on(scene, options):
        raise ValueError("slab seeding: the wall particles of moving blocks are not decomposed")
    return FluidLayout(n_fluid=n, lo=lo, hi=hi, first=bounds[2], boundary=xb, removed_inside_blocks=removed,
                       peak_points=peak, regions=regions)


def seed_fluid_slab(scene: Scene, device: str, parts: Parts, layout: FluidLayout, axis: int, faces: np.ndarray,
                    rank: int, options=None) -> tuple[FluidSeeds, np.ndarray, int]:
    """The particles of slab ``rank`` (float32 coordinate along ``axis`` in [faces[rank], faces[rank + 1]), as the
    distributed run's owner test reads it), as the whole scene's seeding places them: (seeds with the static walls
    of ``layout``, global ids in increasing order, lattice points held at most)."""
    if axis == scene.dim - 1:
        raise ValueError("slab seeding: slabs along the vertical axis would cut the packed columns")
    f_lo, f_hi = float(faces[rank]), float(faces[rank + 1])
    # the window in float64 a little wider than the float32 test, then the test itself
    a = -math.inf if not math.isfinite(f_lo) else f_lo - 1e-6 * max(1.0, abs(f_lo))
    b = math.inf if not math.isfinite(f_hi) else f_hi + 1e-6 * max(1.0, abs(f_hi))
    x, v, depth, _, _, held, _, ids = _window(scene, device, parts, options, layout.regions, axis, a, b,
                                              layout.lo if scene.fluid.packed_start else None, with_ids=True)
    c = x[:, axis].astype(np.float32).astype(np.float64)
    mine = (c >= f_lo) & (c < f_hi)
    x, v, depth, ids = x[mine], v[mine], depth[mine], ids[mine]
    order = np.argsort(ids, kind="stable")
    seeds = FluidSeeds(x[order], v[order], depth[order], layout.boundary)
    return seeds, ids[order], held
