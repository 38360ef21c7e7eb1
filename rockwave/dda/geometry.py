"""Convex block geometry for the DDA solver (host side: numpy + trimesh).

A block is a convex polyhedron stored in its *body frame* (centroid at the origin) with

* polygon faces (coplanar hull triangles merged, vertex loops counter-clockwise seen from outside),
* outward unit face normals ``n_f`` and offsets ``d_f`` (points on face f satisfy ``n_f . x = d_f``),
* half-edge arrays (Nezami et al. 2004 / the DDA-FCP paper §4): ``he_vertex`` (origin vertex),
  ``he_next``, ``he_prev``, ``he_twin``, ``he_face``; ``vertex_out_he`` (one outgoing half-edge per
  vertex) and ``face_he`` (one half-edge per face).  Walking the half-edges leaving a vertex ``v``:
  ``h = vertex_out_he[v]; repeat: h = he_twin[he_prev[h]]`` — O(valence), which FCP needs.
* mass properties per unit density (volume, inertia tensor about the centroid), bounding radius.

A non-convex closed mesh becomes a :class:`CompoundBlock`: one rigid body made of convex parts from
CoACD (Wei et al. 2022, "Approximate convex decomposition for 3D meshes with collision-aware concavity
and tree search", SIGGRAPH), cached by mesh hash (:func:`decompose`). Its mass properties come from the
original mesh; each part is a ConvexPolyhedron in the *body's* frame (the body's centroid at the
origin, so a part's own centroid is off the origin). Without a :class:`Decomposition` a non-convex
mesh is refused, saying by how much it falls short of its hull.
"""

from __future__ import annotations

import hashlib
import os
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import trimesh

from rockwave.base.maths import quat_to_matrix

__all__ = [
    "GeometryError",
    "DecompositionError",
    "ConvexPolyhedron",
    "CompoundBlock",
    "Decomposition",
    "decompose",
    "from_trimesh",
    "load_mesh",
    "box",
    "prism",
    "half_edge_invariants",
]

# relative volume shortfall (1 - V_mesh / V_hull) above which a mesh counts as non-convex
CONVEXITY_TOL = 1e-4


class GeometryError(ValueError):
    """A mesh cannot be used as a DDA block; the message names the mesh/file and the reason."""


class NonConvexError(GeometryError):
    """A non-convex mesh given where a convex one is needed (no Decomposition)."""


class DecompositionError(GeometryError):
    """The convex decomposition of a non-convex mesh failed or broke a bound; ``key`` names the
    Decomposition field (scene key ``blocks[i].decomposition.<key>``) that was exceeded, if any."""

    def __init__(self, message: str, key: str = ""):
        super().__init__(message)
        self.key = key


@dataclass
class ConvexPolyhedron:
    """Convex block in its body frame (centroid at the origin). Units: metres.

    Attributes (V vertices, F faces, H half-edges, all int arrays int32):
        name: label used in error messages.
        vertices: (V, 3) float64, body-frame vertex positions.
        faces: list of F int arrays, vertex loops CCW seen from outside.
        face_normals: (F, 3) outward unit normals.  face_offsets: (F,) with n_f . x = d_f on face f (> 0).
        he_vertex, he_next, he_prev, he_twin, he_face: (H,) half-edge arrays.
        vertex_out_he: (V,) one outgoing half-edge per vertex.  face_he: (F,) one half-edge per face.
        volume: m^3.  inertia_unit: (3, 3) inertia tensor about the centroid per unit density (m^5).
        bounding_radius: max |vertex| (m).
        origin_offset: (3,) centroid position in the source mesh's frame (to place the block where
            the file put it).
    """

    name: str
    vertices: np.ndarray
    faces: list
    face_normals: np.ndarray
    face_offsets: np.ndarray
    he_vertex: np.ndarray
    he_next: np.ndarray
    he_prev: np.ndarray
    he_twin: np.ndarray
    he_face: np.ndarray
    vertex_out_he: np.ndarray
    face_he: np.ndarray
    volume: float
    inertia_unit: np.ndarray
    bounding_radius: float
    origin_offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def num_vertices(self) -> int:
        return len(self.vertices)

    @property
    def num_faces(self) -> int:
        return len(self.faces)

    @property
    def num_half_edges(self) -> int:
        return len(self.he_vertex)

    @property
    def centroid(self) -> np.ndarray:
        """Centroid in the body frame (zero by construction)."""
        return np.zeros(3)

    @property
    def size(self) -> float:
        """Equivalent size L = V^(1/3) (m)."""
        return float(self.volume ** (1.0 / 3.0))

    def mass(self, density: float) -> float:
        return float(self.volume * density)

    def inertia(self, density: float) -> np.ndarray:
        """Inertia tensor about the centroid, body frame (kg m^2)."""
        return self.inertia_unit * density

    def edges(self) -> np.ndarray:
        """(E, 2) unique undirected edges (v0 < v1)."""
        a = self.he_vertex
        b = self.he_vertex[self.he_next]
        m = a < b
        return np.stack([a[m], b[m]], axis=1)

    def triangles(self) -> np.ndarray:
        """Fan triangulation of the polygon faces, (T, 3), for rendering/export."""
        tris = []
        for f in self.faces:
            for k in range(1, len(f) - 1):
                tris.append((f[0], f[k], f[k + 1]))
        return np.asarray(tris, dtype=np.int64)

    def to_trimesh(self) -> trimesh.Trimesh:
        return trimesh.Trimesh(self.vertices.copy(), self.triangles(), process=False)

    def transformed_vertices(self, position, quat_xyzw) -> np.ndarray:
        """World-space vertices for a pose (quaternion x, y, z, w)."""
        return self.vertices @ quat_to_matrix(quat_xyzw).T + np.asarray(position, dtype=float)


def _merge_coplanar(points: np.ndarray, tris: np.ndarray, name: str, tol: float):
    """Group hull triangles into polygon faces by (normal, offset); return vertex loops (CCW)."""
    p0, p1, p2 = points[tris[:, 0]], points[tris[:, 1]], points[tris[:, 2]]
    cr = np.cross(p1 - p0, p2 - p0)
    area2 = np.linalg.norm(cr, axis=1)
    if np.any(area2 <= 1e-14 * max(1.0, tol) ** 2):
        keep = area2 > 0
        tris, cr, area2, p0 = tris[keep], cr[keep], area2[keep], p0[keep]
    nrm = cr / area2[:, None]
    off = np.einsum("ij,ij->i", nrm, p0)
    # union-find over triangles sharing an edge with the same plane
    parent = np.arange(len(tris))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    edge_owner = {}
    for t, (a, b, c) in enumerate(tris):
        for u, v in ((a, b), (b, c), (c, a)):
            edge_owner[(int(u), int(v))] = t
    for (u, v), t in edge_owner.items():
        s = edge_owner.get((v, u))
        if s is None:
            raise GeometryError(f"mesh '{name}': hull is not a closed surface (edge {u}-{v} has no twin)")
        if np.dot(nrm[t], nrm[s]) > 1 - 1e-6 and abs(off[t] - off[s]) < tol:
            ra, rb = find(t), find(s)
            if ra != rb:
                parent[ra] = rb
    groups = {}
    for t in range(len(tris)):
        groups.setdefault(find(t), []).append(t)
    loops = []
    for tlist in groups.values():
        directed = set()
        for t in tlist:
            a, b, c = (int(x) for x in tris[t])
            directed.update(((a, b), (b, c), (c, a)))
        boundary = {u: v for (u, v) in directed if (v, u) not in directed}
        start = next(iter(boundary))
        loop = [start]
        cur = boundary[start]
        while cur != start:
            loop.append(cur)
            cur = boundary[cur]
            if len(loop) > len(boundary):
                raise GeometryError(f"mesh '{name}': could not build a simple loop for a face")
        if len(loop) != len(boundary):
            raise GeometryError(f"mesh '{name}': a merged face has a hole or several loops")
        loops.append(np.asarray(loop, dtype=np.int32))
    return loops


def _drop_collinear(points: np.ndarray, loops: list, tol: float) -> list:
    """Remove vertices lying on a straight edge of a polygon loop (keeps faces strictly convex)."""
    out = []
    for loop in loops:
        changed = True
        lp = list(loop)
        while changed and len(lp) > 3:
            changed = False
            for k in range(len(lp)):
                a, b, c = points[lp[k - 1]], points[lp[k]], points[lp[(k + 1) % len(lp)]]
                if np.linalg.norm(np.cross(b - a, c - b)) < tol * np.linalg.norm(c - a):
                    del lp[k]
                    changed = True
                    break
        out.append(np.asarray(lp, dtype=np.int32))
    return out


def _build(points: np.ndarray, name: str, origin_offset=None) -> ConvexPolyhedron:
    """Convex hull of points -> ConvexPolyhedron (centroid-centred, merged faces, half-edges)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise GeometryError(f"mesh '{name}': need at least 4 points in 3D, got shape {points.shape}")
    ext = np.ptp(points, axis=0)
    scale = float(np.max(ext))
    if not np.isfinite(points).all():
        raise GeometryError(f"mesh '{name}': non-finite vertex coordinates")
    if scale <= 0 or np.min(ext) <= 1e-9 * scale:
        raise GeometryError(f"mesh '{name}': degenerate (flat or zero-size) point set, extents {ext}")
    try:
        hull = trimesh.convex.convex_hull(points, qhull_options="QbB Pp Qt")
    except Exception as exc:  # qhull errors on degenerate input
        raise GeometryError(f"mesh '{name}': convex hull failed ({exc})") from exc
    vol = float(hull.volume)
    if not np.isfinite(vol) or vol <= 1e-12 * scale**3:
        raise GeometryError(f"mesh '{name}': zero or negative volume ({vol:g} m^3)")
    props = hull.mass_properties  # density 1
    com = np.asarray(props["center_mass"], dtype=np.float64)
    inertia = np.asarray(props["inertia"], dtype=np.float64)
    # keep only vertices used by the hull faces, re-indexed
    used = np.unique(hull.faces)
    remap = -np.ones(len(hull.vertices), dtype=np.int64)
    remap[used] = np.arange(len(used))
    verts = np.asarray(hull.vertices[used], dtype=np.float64) - com
    tris = remap[np.asarray(hull.faces)]
    tol = 1e-7 * scale
    loops = _merge_coplanar(verts, tris, name, tol)
    loops = _drop_collinear(verts, loops, 1e-9)
    # vertices that vanished (collinear) -> re-index again
    used2 = np.unique(np.concatenate(loops))
    if len(used2) != len(verts):
        remap2 = -np.ones(len(verts), dtype=np.int64)
        remap2[used2] = np.arange(len(used2))
        verts = verts[used2]
        loops = [remap2[lp].astype(np.int32) for lp in loops]
    nV, nF = len(verts), len(loops)
    normals = np.zeros((nF, 3))
    offsets = np.zeros(nF)
    for f, lp in enumerate(loops):
        # Newell's method: robust polygon normal
        p = verts[lp]
        q = np.roll(p, -1, axis=0)
        nn = np.array(
            [
                np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
                np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
                np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])),
            ]
        )
        nn /= np.linalg.norm(nn)
        normals[f] = nn
        offsets[f] = float(np.mean(p @ nn))
    if np.any(offsets <= 0):
        raise GeometryError(f"mesh '{name}': a face plane does not enclose the centroid (inverted hull)")
    # half-edges
    nH = sum(len(lp) for lp in loops)
    he_vertex = np.zeros(nH, np.int32)
    he_next = np.zeros(nH, np.int32)
    he_prev = np.zeros(nH, np.int32)
    he_face = np.zeros(nH, np.int32)
    face_he = np.zeros(nF, np.int32)
    h = 0
    lookup = {}
    for f, lp in enumerate(loops):
        k = len(lp)
        face_he[f] = h
        for i in range(k):
            he_vertex[h + i] = lp[i]
            he_next[h + i] = h + (i + 1) % k
            he_prev[h + i] = h + (i - 1) % k
            he_face[h + i] = f
            lookup[(int(lp[i]), int(lp[(i + 1) % k]))] = h + i
        h += k
    he_twin = np.full(nH, -1, np.int32)
    vertex_out_he = np.full(nV, -1, np.int32)
    for (u, v), e in lookup.items():
        t = lookup.get((v, u))
        if t is None:
            raise GeometryError(f"mesh '{name}': half-edge {u}->{v} has no twin (not closed)")
        he_twin[e] = t
        if vertex_out_he[u] < 0:
            vertex_out_he[u] = e
    return ConvexPolyhedron(
        name=name,
        vertices=verts,
        faces=loops,
        face_normals=normals,
        face_offsets=offsets,
        he_vertex=he_vertex,
        he_next=he_next,
        he_prev=he_prev,
        he_twin=he_twin,
        he_face=he_face,
        vertex_out_he=vertex_out_he,
        face_he=face_he,
        volume=vol,
        inertia_unit=inertia,
        bounding_radius=float(np.max(np.linalg.norm(verts, axis=1))),
        origin_offset=com + (np.zeros(3) if origin_offset is None else np.asarray(origin_offset, float)),
    )


def from_trimesh(mesh: trimesh.Trimesh, name: str = "mesh", decomposition: "Decomposition | None" = None):
    """Validate a closed triangle mesh and convert it to a ConvexPolyhedron (convex mesh) or, given a
    Decomposition, a CompoundBlock (non-convex mesh).

    Raises GeometryError for open (non-watertight) or zero-volume meshes, and for non-convex meshes
    without a Decomposition.  Inverted normals (negative signed volume) are fixed with a warning.
    """
    if not isinstance(mesh, trimesh.Trimesh):
        raise GeometryError(f"mesh '{name}': expected a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) < 4 or len(mesh.vertices) < 4:
        raise GeometryError(f"mesh '{name}': too few faces/vertices to enclose a volume")
    mesh = mesh.copy()
    mesh.merge_vertices()
    if not mesh.is_watertight:
        raise GeometryError(
            f"mesh '{name}': not watertight (open boundary or non-manifold edges); a block must be a closed solid"
        )
    vol = float(mesh.volume)
    scale = float(np.max(mesh.extents)) if len(mesh.vertices) else 0.0
    if not np.isfinite(vol) or abs(vol) <= 1e-12 * max(scale, 1e-30) ** 3:
        raise GeometryError(f"mesh '{name}': zero volume ({vol:g} m^3), degenerate mesh")
    if vol < 0:
        warnings.warn(f"mesh '{name}': faces are inverted (negative volume); flipping normals", stacklevel=2)
        mesh.invert()
        vol = -vol
    hull_vol = float(mesh.convex_hull.volume)
    ratio = vol / hull_vol
    if ratio < 1.0 - CONVEXITY_TOL:
        if decomposition is not None:
            return decompose(mesh, name, decomposition)
        raise NonConvexError(
            f"mesh '{name}': not convex — its volume is {ratio:.4f} of its convex hull "
            f"({100 * (1 - ratio):.2f}% short). DDA blocks must be convex: split the mesh into convex "
            f"parts (e.g. with CoACD or V-HACD) and give each part as its own block, or let the scene "
            f"decompose it (blocks[i].decomposition)."
        )
    return _build(np.asarray(mesh.vertices), name)


def load_mesh(path, decomposition: "Decomposition | None" = None, scale: float = 1.0):
    """Load STL/OBJ/PLY/GLB through trimesh.  One part -> ConvexPolyhedron (or CompoundBlock); several
    -> list.  A non-convex part becomes a CompoundBlock when a Decomposition is given (decomposed at
    ``scale``, so its parts and cache entry are in metres); convex parts are returned unscaled (the
    caller scales them, as before)."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise GeometryError(f"mesh file '{path}': does not exist")
    try:
        loaded = trimesh.load(path, process=False)
    except Exception as exc:
        raise GeometryError(f"mesh file '{path}': trimesh could not read it ({exc})") from exc
    if isinstance(loaded, trimesh.Scene):
        parts = [(f"{path}:{k}", g) for k, g in _scene_parts(loaded)]
    elif isinstance(loaded, trimesh.Trimesh):
        parts = [(path, loaded)]
    else:
        raise GeometryError(f"mesh file '{path}': holds no triangle mesh ({type(loaded).__name__})")
    if not parts:
        raise GeometryError(f"mesh file '{path}': holds no triangle mesh")
    out = []
    for pname, m in parts:
        if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
            raise GeometryError(f"mesh file '{pname}': part is not a triangle mesh")
        m = m.copy()
        m.merge_vertices()
        bodies = m.split(only_watertight=False) if m.body_count > 1 else [m]
        for k, b in enumerate(bodies):
            bname = pname if len(bodies) == 1 else f"{pname}#{k}"
            if decomposition is not None and scale != 1.0:
                try:  # convex: unscaled, the caller scales it (as before)
                    out.append(from_trimesh(b, bname))
                except NonConvexError:
                    b = b.copy()
                    b.apply_scale(scale)
                    out.append(from_trimesh(b, bname, decomposition))
            else:
                out.append(from_trimesh(b, bname, decomposition))
    return out[0] if len(out) == 1 else out


def _scene_parts(mesh_scene: trimesh.Scene):
    for node in mesh_scene.graph.nodes_geometry:
        transform, gname = mesh_scene.graph[node]
        g = mesh_scene.geometry[gname].copy()
        g.apply_transform(transform)
        yield node, g


def box(size_xyz, name: str = "box") -> ConvexPolyhedron:
    """Axis-aligned box centred at the origin with edge lengths (sx, sy, sz) in metres."""
    s = np.asarray(size_xyz, dtype=float).reshape(3)
    if np.any(s <= 0):
        raise GeometryError(f"mesh '{name}': box size must be positive, got {s}")
    c = np.array([[i, j, k] for i in (-0.5, 0.5) for j in (-0.5, 0.5) for k in (-0.5, 0.5)])
    return _build(c * s, name)


def prism(vertices, name: str = "prism") -> ConvexPolyhedron:
    """Convex hull of the given points (e.g. the 6 corners of a wedge)."""
    return _build(np.asarray(vertices, dtype=float), name, origin_offset=None)


def half_edge_invariants(p: ConvexPolyhedron) -> dict:
    """Check half-edge consistency; returns a dict of booleans (all must be True)."""
    H = p.num_half_edges
    idx = np.arange(H)
    res = {}
    res["twin_involution"] = bool(np.all(p.he_twin >= 0) and np.all(p.he_twin[p.he_twin] == idx))
    res["twin_not_self"] = bool(np.all(p.he_twin != idx))
    res["twin_reverses"] = bool(
        np.all(p.he_vertex[p.he_twin] == p.he_vertex[p.he_next]) and np.all(p.he_face[p.he_twin] != p.he_face)
    )
    res["next_prev_inverse"] = bool(np.all(p.he_prev[p.he_next] == idx) and np.all(p.he_next[p.he_prev] == idx))
    loops_ok = True
    for f in range(p.num_faces):
        h0 = p.face_he[f]
        h, n = h0, 0
        while True:
            if p.he_face[h] != f:
                loops_ok = False
                break
            h = p.he_next[h]
            n += 1
            if h == h0 or n > H:
                break
        loops_ok &= h == h0 and n == len(p.faces[f])
    res["face_loops_close"] = bool(loops_ok)
    E = H // 2
    res["euler"] = bool(H % 2 == 0 and p.num_vertices - E + p.num_faces == 2)
    res["vertex_out_he"] = bool(np.all(p.he_vertex[p.vertex_out_he] == np.arange(p.num_vertices)))
    # walking around each vertex visits all its outgoing half-edges
    valence = np.bincount(p.he_vertex, minlength=p.num_vertices)
    ring_ok = True
    for v in range(p.num_vertices):
        h0 = p.vertex_out_he[v]
        h, n = h0, 0
        while True:
            h = p.he_twin[p.he_prev[h]]
            n += 1
            if h == h0 or n > H:
                break
        ring_ok &= n == valence[v]
    res["vertex_rings"] = bool(ring_ok)
    # convexity / outward normals: every vertex on or behind every face plane
    dist = p.vertices @ p.face_normals.T - p.face_offsets[None, :]
    res["convex_outward"] = bool(np.all(dist <= 1e-9 * max(1.0, p.bounding_radius)))
    # CCW loops: Newell normal of the loop agrees with the stored outward normal
    res["ccw"] = bool(
        all(
            np.dot(np.cross(p.vertices[f[1]] - p.vertices[f[0]], p.vertices[f[2]] - p.vertices[f[1]]), p.face_normals[i]) > 0
            for i, f in enumerate(p.faces)
        )
    )
    return res


# ----------------------------------------------------------------------------------------------
# non-convex meshes: compound blocks of convex parts (CoACD), cached by mesh hash
# ----------------------------------------------------------------------------------------------

DECOMPOSITION_CACHE_ENV = "ROCKWAVE_CACHE_DIR"
CACHE_FORMAT = 1  # bump when the cached arrays change meaning


def default_cache_dir() -> Path:
    """$ROCKWAVE_CACHE_DIR/decompositions, else $XDG_CACHE_HOME/rockwave/decompositions, else
    ~/.cache/rockwave/decompositions."""
    root = os.environ.get(DECOMPOSITION_CACHE_ENV)
    if root:
        return Path(root) / "decompositions"
    xdg = os.environ.get("XDG_CACHE_HOME")
    return Path(xdg or Path.home() / ".cache") / "rockwave" / "decompositions"


@dataclass(frozen=True)
class Decomposition:
    """How a non-convex mesh is split into convex parts (scene: ``blocks[i].decomposition``).

    max_parts: the most convex parts allowed; more is a DecompositionError (key "max_parts").
    concavity: CoACD's concavity threshold (its ``threshold``: the largest allowed distance, relative
        to the mesh's bounding-box diagonal, between a part's hull surface and the mesh; smaller ->
        more, tighter parts).
    cache_dir: where decompositions are kept (None: default_cache_dir()).
    seed: CoACD's random seed (its tree search is randomised; a fixed seed makes it repeatable).
    """

    max_parts: int = 32
    concavity: float = 0.05
    cache_dir: str | None = None
    seed: int = 0


@dataclass
class CompoundBlock:
    """One rigid block made of convex parts (a decomposed non-convex mesh), in its body frame: the
    original mesh's centroid at the origin. Units: metres.

    parts: ConvexPolyhedron per part, vertices in the body frame (each part's own centroid is off the
        origin; its origin_offset is the body centroid in the source frame, as for every part).
    part_radius: (P,) each part's bounding radius about its own centroid (m).
    mesh_vertices (V, 3), mesh_triangles (T, 3): the original mesh in the body frame (what outputs show).
    volume (m^3), inertia_unit (3, 3, about the centroid per unit density): the original mesh's.
    bounding_radius: max |vertex| of the parts (m).  origin_offset: the centroid in the source frame.
    parts_volume: sum of the parts' volumes (m^3).  cached: True when the parts came from the cache.
    concavity, max_parts: the Decomposition used.
    """

    name: str
    parts: list
    part_radius: np.ndarray
    mesh_vertices: np.ndarray
    mesh_triangles: np.ndarray
    volume: float
    inertia_unit: np.ndarray
    bounding_radius: float
    origin_offset: np.ndarray
    parts_volume: float
    cached: bool = False
    concavity: float = 0.0
    max_parts: int = 0

    @property
    def num_parts(self) -> int:
        return len(self.parts)

    @property
    def volume_error(self) -> float:
        """Relative volume error of the decomposition: sum of part volumes / mesh volume - 1."""
        return self.parts_volume / self.volume - 1.0

    @property
    def size(self) -> float:
        """Equivalent size L = V^(1/3) of the original mesh (m)."""
        return float(self.volume ** (1.0 / 3.0))

    def mass(self, density: float) -> float:
        return float(self.volume * density)

    def inertia(self, density: float) -> np.ndarray:
        """Inertia tensor of the original mesh about its centroid, body frame (kg m^2)."""
        return self.inertia_unit * density

    def summary(self) -> str:
        return (f"{self.num_parts} convex parts (CoACD concavity {self.concavity:g}, max_parts {self.max_parts}), "
                f"volume error {100 * self.volume_error:+.2f}% (parts {self.parts_volume:.6g} m^3 vs mesh "
                f"{self.volume:.6g} m^3){' [cached]' if self.cached else ''}")


def shifted(p: ConvexPolyhedron, t) -> ConvexPolyhedron:
    """The same polyhedron with its frame origin moved by -t (vertices + t): face offsets
    d' = d + n.t, inertia about the new origin by the parallel-axis theorem I_O = I_c + V (|t|^2 1 - t t^T),
    origin_offset - t (the new origin in the source frame)."""
    t = np.asarray(t, dtype=np.float64).reshape(3)
    v = p.vertices + t
    return replace(p, vertices=v, face_offsets=p.face_offsets + p.face_normals @ t,
                   inertia_unit=p.inertia_unit + p.volume * (float(t @ t) * np.eye(3) - np.outer(t, t)),
                   bounding_radius=float(np.max(np.linalg.norm(v, axis=1))),
                   origin_offset=np.asarray(p.origin_offset, float) - t)


def _cache_key(vertices: np.ndarray, faces: np.ndarray, opt: Decomposition) -> str:
    import coacd

    h = hashlib.sha256()
    h.update(f"rockwave-coacd/{CACHE_FORMAT}/{_coacd_version(coacd)}/{opt.concavity!r}/{opt.seed}".encode())
    h.update(np.ascontiguousarray(vertices, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(faces, dtype="<i8").tobytes())
    return h.hexdigest()


def _coacd_version(coacd) -> str:
    try:
        from importlib.metadata import version

        return version("coacd")
    except Exception:  # noqa: BLE001
        return getattr(coacd, "__version__", "?")


def _run_coacd(vertices: np.ndarray, faces: np.ndarray, opt: Decomposition, name: str) -> list:
    """CoACD on the mesh -> list of (vertices (n, 3), faces (m, 3)) convex parts."""
    try:
        import coacd
    except ImportError as exc:  # a dependency; only a broken install lands here
        raise DecompositionError(f"mesh '{name}': non-convex, and the decomposition library coacd is not "
                                 f"installed ({exc})") from exc
    coacd.set_log_level("error")
    try:
        out = coacd.run_coacd(coacd.Mesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int32)),
                              threshold=float(opt.concavity), seed=int(opt.seed))
    except Exception as exc:  # noqa: BLE001  (CoACD raises plain exceptions)
        raise DecompositionError(f"mesh '{name}': convex decomposition failed ({exc})") from exc
    return [(np.asarray(v, np.float64), np.asarray(f, np.int64)) for v, f in out]


def decompose(mesh: trimesh.Trimesh, name: str, opt: Decomposition) -> CompoundBlock:
    """A closed non-convex mesh (already checked watertight, positive volume) -> CompoundBlock.

    The parts come from CoACD at opt.concavity, or from the cache (keyed by the SHA-256 of the
    normalised vertices, faces, concavity, seed and CoACD version), written atomically after a fresh run.
    Mass properties: the original mesh's (trimesh).  Raises DecompositionError when CoACD fails,
    returns no part, or more than opt.max_parts parts."""
    if not (isinstance(opt.max_parts, int) and opt.max_parts >= 1):
        raise DecompositionError(f"mesh '{name}': max_parts must be a whole number >= 1, got {opt.max_parts}", "max_parts")
    if not opt.concavity > 0:
        raise DecompositionError(f"mesh '{name}': concavity must be > 0, got {opt.concavity}", "concavity")
    verts = np.asarray(mesh.vertices, np.float64)
    faces = np.asarray(mesh.faces, np.int64)
    # CoACD's concavity is relative to the bounding box, so it works on the mesh normalised to a unit
    # diagonal (rounded to 1e-9 so that the same shape at another scale or place hits the same cache entry)
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    centre, diag = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))
    unit = np.round((verts - centre) / diag, 9)
    cache = Path(opt.cache_dir) if opt.cache_dir else default_cache_dir()
    key = _cache_key(unit, faces, opt)
    file = cache / f"{key}.npz"
    cached = False
    parts_raw = None
    if file.exists():
        try:
            with np.load(file) as z:
                pv, pf, nv, nf = z["vertices"], z["faces"], z["nverts"], z["nfaces"]
            iv, jf = np.concatenate([[0], np.cumsum(nv)]), np.concatenate([[0], np.cumsum(nf)])
            parts_raw = [(pv[iv[k]:iv[k + 1]], pf[jf[k]:jf[k + 1]]) for k in range(len(nv))]
            cached = True
        except Exception:  # noqa: BLE001  (a torn or foreign file: decompose again and overwrite it)
            parts_raw = None
    if parts_raw is None:
        parts_raw = _run_coacd(unit, faces, opt, name)
        if parts_raw:
            try:
                cache.mkdir(parents=True, exist_ok=True)
                tmp = cache / f".{key}.{os.getpid()}.tmp.npz"
                np.savez_compressed(tmp, vertices=np.concatenate([v for v, _ in parts_raw]),
                         faces=np.concatenate([f for _, f in parts_raw]),
                         nverts=np.array([len(v) for v, _ in parts_raw]), nfaces=np.array([len(f) for _, f in parts_raw]))
                os.replace(tmp, file)
            except OSError as exc:
                warnings.warn(f"mesh '{name}': could not write the decomposition cache {file} ({exc})", stacklevel=2)
    if not parts_raw:
        raise DecompositionError(f"mesh '{name}': convex decomposition returned no part")
    if len(parts_raw) > opt.max_parts:
        raise DecompositionError(
            f"mesh '{name}': decomposed into {len(parts_raw)} convex parts at concavity {opt.concavity:g}, "
            f"more than max_parts = {opt.max_parts}; raise max_parts or the concavity threshold", "max_parts")
    props = mesh.mass_properties  # density 1: the original mesh's volume, centroid and inertia
    com = np.asarray(props["center_mass"], np.float64)
    inertia = np.asarray(props["inertia"], np.float64)
    parts, radius = [], []
    for k, (v, _) in enumerate(parts_raw):
        p = _build(v * diag + centre, f"{name}[part {k}]")
        radius.append(p.bounding_radius)
        parts.append(shifted(p, np.asarray(p.origin_offset) - com))
    return CompoundBlock(
        name=name, parts=parts, part_radius=np.asarray(radius), mesh_vertices=verts - com,
        mesh_triangles=faces.copy(), volume=float(props["volume"]), inertia_unit=inertia,
        bounding_radius=float(max(p.bounding_radius for p in parts)), origin_offset=com,
        parts_volume=float(sum(p.volume for p in parts)), cached=cached, concavity=float(opt.concavity),
        max_parts=int(opt.max_parts))
