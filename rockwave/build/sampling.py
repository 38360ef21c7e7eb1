"""Seeding particles: fluid lattices in boxes and meshes, boundary-particle layers for tanks and
obstacles. Host side (numpy), with mesh inside/outside tests in a Warp kernel."""

from __future__ import annotations

import numpy as np
import warp as wp

from rockwave.kernels.build import sampling as sampling_k


class MeshInputError(ValueError):
    """A mesh file that cannot be used, with the file and the reason."""


def lattice_axis(lo: float, hi: float, step: float) -> np.ndarray:
    """Cell-centred coordinates lo + (i + 1/2) step filling [lo, hi] (step adjusted to fit exactly)."""
    n = max(int(round((hi - lo) / step)), 1)
    s = (hi - lo) / n
    return lo + (np.arange(n) + 0.5) * s


def box_lattice(lo, hi, step: float) -> np.ndarray:
    axes = [lattice_axis(a, b, step) for a, b in zip(lo, hi)]
    g = np.meshgrid(*axes, indexing="ij")
    return np.stack([c.ravel() for c in g], axis=1)


def load_trimesh(path: str, scale: float = 1.0, offset=(0.0, 0.0, 0.0)):
    """Load a closed triangle mesh through trimesh, scaled and translated; clear errors for bad files."""
    import trimesh

    try:
        m = trimesh.load(path, force="mesh")
    except Exception as e:  # trimesh raises many types for unreadable files
        raise MeshInputError(f"{path}: cannot read mesh ({type(e).__name__}: {e})") from None
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise MeshInputError(f"{path}: holds no triangles")
    m = m.copy()
    m.apply_scale(scale)
    m.apply_translation(np.asarray(offset, dtype=float))
    if not m.is_watertight:
        raise MeshInputError(f"{path}: mesh is not watertight (closed); inside/outside is undefined")
    if abs(m.volume) < 1e-12:
        raise MeshInputError(f"{path}: mesh has zero volume")
    if m.volume < 0:
        m.invert()
    return m


def mesh_signed_distance(mesh, points: np.ndarray, device) -> np.ndarray:
    """Signed distance (negative inside) from each point to a closed trimesh mesh."""
    if len(points) == 0:
        return np.zeros(0)
    wmesh = wp.Mesh(
        points=wp.array(np.asarray(mesh.vertices, dtype=np.float32), dtype=wp.vec3, device=device),
        indices=wp.array(np.asarray(mesh.faces, dtype=np.int32).ravel(), dtype=int, device=device),
    )
    pts = wp.array(points.astype(np.float32), dtype=wp.vec3, device=device)
    out = wp.zeros(len(points), dtype=float, device=device)
    span = float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]) + np.abs(points).max() + 1.0) * 4.0
    wp.launch(sampling_k.mesh_signed_distance, dim=len(points), inputs=[wmesh.id, pts, span, out], device=device)
    return out.numpy().astype(np.float64)


def _pad(v, dim):
    return np.asarray(list(v) + [0.0] * (3 - dim), dtype=np.float64)


def region_lattice(region, spacing: float, dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lattice :func:`fill_region` seeds a region on: (first point (3,), steps (3,), last point (3,)), its points
    first + k steps, each axis's step fitted to the region's extent (a mesh region: its bounds) as :func:`lattice_axis`
    fits it, the same floats (2D: z = 0, step = spacing)."""
    if region.get("box_min_m") is not None:
        lo, hi = np.asarray(region["box_min_m"], float), np.asarray(region["box_max_m"], float)
    else:
        m = load_trimesh(region["mesh"], region["mesh_scale"], region["mesh_offset_m"])
        lo, hi = np.asarray(m.bounds[0], float), np.asarray(m.bounds[1], float)
    first, last, steps = np.zeros(3), np.zeros(3), np.full(3, float(spacing))
    for i in range(len(lo)):
        a = lattice_axis(lo[i], hi[i], spacing)
        steps[i] = (hi[i] - lo[i]) / len(a)
        first[i], last[i] = a[0], a[-1]
    if dim == 2:
        first[2] = last[2] = 0.0
        steps[2] = float(spacing)
    return first, steps, last


def lattice_steps_and_scale(regions, spacing: float, dim: int) -> tuple[list, float]:
    """Each region's smallest fitted lattice step and the largest coordinate of their lattices (the seeding's
    clearance from block faces, rockwave/coupling/penalty.py seeding_clearance_m, is computed from them)."""
    lat = [region_lattice(r, spacing, dim) for r in regions]
    steps = [float(np.min(st[:dim])) for _, st, _ in lat]
    scale = max([float(np.abs(np.concatenate([a, b])).max()) for a, _, b in lat] + [1.0])
    return steps, scale


def fill_region(region, spacing: float, dim: int, device) -> np.ndarray:
    """Fluid particles on a lattice of the given spacing inside a box or a closed mesh."""
    if region.get("box_min_m") is not None:
        pts = box_lattice(region["box_min_m"], region["box_max_m"], spacing)
    else:
        m = load_trimesh(region["mesh"], region["mesh_scale"], region["mesh_offset_m"])
        pts = box_lattice(m.bounds[0], m.bounds[1], spacing)
        pts = pts[mesh_signed_distance(m, pts, device) < 0.0]
    if dim == 2:
        pts = np.concatenate([pts, np.zeros((len(pts), 1))], axis=1)
    return pts


def box_shell(lo, hi, step: float, layers: int, outside: bool, open_top: bool, up: int) -> np.ndarray:
    """Boundary particles in `layers` lattice layers just outside (tank) or just inside (obstacle)
    the faces of the box [lo, hi]. The lattice is aligned so that the box faces lie half a step
    from the nearest layer (an open tank's walls: the floor's, with the exact step, up to the first whole step at
    or above the top). Built slab by slab along the up axis to bound memory."""
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    d = len(lo)
    n = np.maximum(np.round((hi - lo) / step).astype(int), 1)
    s = (hi - lo) / n
    if outside and open_top:
        # An open tank's walls rise on the water's lattice, which starts at the floor with the exact step: a
        # lattice stretched to end at the top would put the side-wall particles between the water's rows and
        # give each less volume than the wall force assumes (+0.6% pressure at 40 layers, docs/notes.md 'Water
        # at rest on the H200'); the walls end at the first whole step at or above the top instead.
        n[up] = max(int(np.ceil((hi[up] - lo[up]) / step - 1e-9)), 1)
        s[up] = step
    axes = []
    for a in range(d):
        if outside:
            lo_ext = lo[a] - layers * s[a]
            top = 0 if (open_top and a == up) else layers
            cnt = n[a] + layers + top
            axes.append(lo_ext + (np.arange(cnt) + 0.5) * s[a])
        else:
            axes.append(lo[a] + (np.arange(n[a]) + 0.5) * s[a])
    out = []
    other = [a for a in range(d) if a != up]
    grids = np.meshgrid(*[axes[a] for a in other], indexing="ij")
    flat = [g.ravel() for g in grids]
    for zc in axes[up]:
        cols = [None] * d
        for a, f in zip(other, flat):
            cols[a] = f
        cols[up] = np.full_like(flat[0], zc)
        p = np.stack(cols, axis=1)
        if outside:
            inside = np.all((p > lo) & (p < hi), axis=1)
            if open_top:
                inside_top = np.all((p[:, other] > lo[other]) & (p[:, other] < hi[other]), axis=1) & (p[:, up] > lo[up])
                inside = inside | inside_top
            p = p[~inside]
        else:
            depth = np.min(np.minimum(p - lo, hi - p), axis=1)
            p = p[depth < layers * np.min(s)]
        out.append(p)
    pts = np.concatenate(out) if out else np.zeros((0, d))
    if d == 2:
        pts = np.concatenate([pts, np.zeros((len(pts), 1))], axis=1)
    return pts


def mesh_shell(path: str, scale: float, offset, step: float, layers: int, outside: bool, device) -> np.ndarray:
    """Boundary particles on a lattice within `layers * step` outside (tank) or inside (obstacle) a closed mesh."""
    m = load_trimesh(path, scale, offset)
    t = layers * step
    lo = m.bounds[0] - (t if outside else 0.0)
    hi = m.bounds[1] + (t if outside else 0.0)
    pts = box_lattice(lo, hi, step)
    sd = mesh_signed_distance(m, pts, device)
    keep = (sd > 0) & (sd < t) if outside else (sd < 0) & (sd > -t)
    return pts[keep]


def inside_obstacle(points: np.ndarray, obstacle, dim: int, device) -> np.ndarray:
    """Mask of points inside an obstacle (box or closed mesh)."""
    if obstacle.get("box_min_m") is not None:
        lo = _pad(obstacle["box_min_m"], dim)[:dim]
        hi = _pad(obstacle["box_max_m"], dim)[:dim]
        return np.all((points[:, :dim] > lo) & (points[:, :dim] < hi), axis=1)
    m = load_trimesh(obstacle["mesh"], obstacle["mesh_scale"], obstacle["mesh_offset_m"])
    return mesh_signed_distance(m, points, device) < 0.0
