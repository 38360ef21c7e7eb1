"""Jointed rock masses: a region cut into convex blocks by planar joint sets (host side, numpy + scipy).

A joint set is a family of parallel planes given the way rock engineers log them (ISRM 1978): dip
delta (degrees below horizontal) and dip direction alpha (azimuth of the dip, clockwise from north).
With x = east, y = north, z = up the plane's upward unit normal is

    n = (sin delta sin alpha, sin delta cos alpha, cos delta)                    (Priest 1993, eq. 2.2)

and plane k of the set is n . (x - origin) = offset + sum of the first k spacings. In 2D (x east,
y up, blocks extruded along z) a joint is a line: alpha must be 90 (dips toward +x) or 270 (toward -x)
and n = (sin delta sin alpha, cos delta).

Cutting a convex region (a box, a turned box, the hull of points) is exact: a block is the
intersection of the region's half-spaces with one slab of every set (the cell of the plane indices
k_1..k_m). Cells whose parallelepiped (three independent sets) lies inside the region are taken as
they are, in one vectorised pass; cells on the region's boundary get their vertices by enumerating
the intersections of three of their planes that satisfy all of their half-spaces (vectorised over
cells), and scipy's Qhull gives their volume. A closed mesh region (the slope) that is convex is cut
as the hull of its vertices. A non-convex one is cut cell by cell: each cell of its bounding box is
clipped by the mesh (signed columns under its triangles, see _clip_cell_by_mesh); a clipped cell that
is not one convex piece (it straddles a concave edge no joint plane runs through) makes the region
refused, not decomposed: DDA blocks are convex, and a decomposition adds cuts that are not joints.

Blocks whose largest inscribed sphere is narrower than ``min_block_size`` merge into a face neighbour when
the union stays convex (the joint between them is taken not to run through there); a sliver with no
such neighbour is an error. Non-persistent joints (persistence p < 1: the fraction of the joint
plane that is open) are cut through, and their contacts carry Jennings' (1970) equivalent strength
of a joint plane made of open joint and intact rock bridges:

    c = p c_j + (1 - p) c_r,  tan phi = p tan phi_j + (1 - p) tan phi_r,  sigma_t = p sigma_tj + (1 - p) sigma_tr

(Jennings 1970, "A mathematical theory for the calculation of the stability of slopes in open cast
mines"; the same step-path strength Hoek & Bray 1981, sec. 7, use). The DDA contact law takes one
material per block and the weaker value of a pair (rockwave/dda/blocks.py ContactMaterial), so a block
carries, per property, the weakest of the joint sets it has faces on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import combinations

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from rockwave.base.maths import euler_xyz_deg_to_quat, quat_to_matrix
from rockwave.build import sampling
from rockwave.dda import geometry
from rockwave.dda.blocks import BlockSpec, ContactMaterial
from rockwave.scene.format import SceneError

__all__ = ["RockMassError", "JointSet", "Cut", "joint_normal", "plane_positions", "box_halfspaces",
           "hull_halfspaces", "cut_convex", "cut_box", "cut_mesh", "merge_slivers", "jennings_strength",
           "rock_mass_specs", "resize_box_region", "inscribed_diameter", "block_widths"]


class RockMassError(ValueError):
    """A rock mass that cannot be cut. ``key`` names the scene key below the rock_mass entry."""

    def __init__(self, key: str, msg: str):
        super().__init__(msg)
        self.key = key


@dataclass
class JointSet:
    """One joint set. Angles in degrees, lengths in metres; strength of the open joint."""

    dip_deg: float
    dip_direction_deg: float
    spacing_m: float
    offset_m: float = 0.0
    random_offset: bool = False
    spacing_jitter: float = 0.0
    persistence: float = 1.0
    friction_angle_deg: float = 30.0
    cohesion_pa: float = 0.0
    tensile_strength_pa: float = 0.0
    name: str = ""


@dataclass
class Cut:
    """Blocks of a cut rock mass: vertices in CSR form (block i: ``vertices[start[i]:start[i+1]]``),
    volume and centroid, the plane index of each set per block (``cells``; merged blocks keep their
    largest cell's), which sets it has faces on (``on_set``), the planes (n, t) of every set, and the
    inscribed-sphere diameter where the cut knows it without a computation (``width``, else NaN)."""

    vertices: np.ndarray
    start: np.ndarray
    volumes: np.ndarray
    centroids: np.ndarray
    cells: np.ndarray
    on_set: np.ndarray
    normals: np.ndarray
    positions: list = field(default_factory=list)
    merged: int = 0
    width: np.ndarray | None = None  # diameter of the largest inscribed sphere where known (parallelepipeds), else NaN

    def __len__(self) -> int:
        return len(self.volumes)

    def block_vertices(self, i: int) -> np.ndarray:
        return self.vertices[self.start[i]:self.start[i + 1]]


def joint_normal(dip_deg: float, dip_direction_deg: float, dim: int = 3) -> np.ndarray:
    """Upward unit normal of a joint plane (3D: x east, y north, z up; 2D: x east, y up, z = 0)."""
    d, a = math.radians(dip_deg), math.radians(dip_direction_deg)
    if dim == 2:
        s = math.sin(a)
        if abs(abs(s) - 1.0) > 1e-9 and math.sin(d) > 1e-12:
            raise RockMassError("dip_direction_deg", f"= {dip_direction_deg:g}: in a 2D scene a joint dips toward +x (90) "
                                                     f"or -x (270)")
        return np.array([math.sin(d) * round(s), math.cos(d), 0.0])
    return np.array([math.sin(d) * math.sin(a), math.sin(d) * math.cos(a), math.cos(d)])


def plane_positions(lo: float, hi: float, js: JointSet, rng: np.random.Generator) -> np.ndarray:
    """Sorted plane offsets t (n . (x - origin) = t) of one set covering [lo, hi]: the first at or below lo,
    the last at or above hi. Phase: offset_m, or uniform in [0, spacing) with random_offset; each gap
    uniform in spacing (1 +- spacing_jitter)."""
    s = js.spacing_m
    phase = rng.uniform(0.0, s) if js.random_offset else js.offset_m
    t0 = phase + math.floor((lo - phase) / s) * s
    if js.spacing_jitter == 0.0:
        n = int(math.ceil((hi - t0) / s - 1e-9)) + 1
        return t0 + s * np.arange(max(n, 2))
    ts = [t0]
    while ts[-1] < hi:
        ts.append(ts[-1] + s * (1.0 + js.spacing_jitter * rng.uniform(-1.0, 1.0)))
    return np.asarray(ts if len(ts) > 1 else ts + [t0 + s])


def box_halfspaces(lo, hi, rotation=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, b, corners) of a box lo..hi turned by ``rotation`` (3x3) about its centre: A x <= b."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    R = np.eye(3) if rotation is None else np.asarray(rotation, float)
    c = 0.5 * (lo + hi)
    h = 0.5 * (hi - lo)
    A = np.concatenate([R.T, -R.T])  # rows: outward normals R e_k, -R e_k
    b = np.concatenate([A[:3] @ c + h, A[3:] @ c + h])
    signs = np.array([[sx, sy, sz] for sz in (-1, 1) for sy in (-1, 1) for sx in (-1, 1)], float)
    corners = c + (signs * h) @ R.T
    return A, b, corners


def hull_halfspaces(points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, b, vertices) of the convex hull of points: Qhull's facets with coplanar triangles merged."""
    pts = np.asarray(points, float)
    try:
        hull = ConvexHull(pts)
    except (QhullError, ValueError) as e:
        raise RockMassError("region.vertices_m", f"the points span no volume ({str(e).splitlines()[0]})") from None
    eq = hull.equations
    scale = float(np.ptp(pts, axis=0).max())
    _, keep = np.unique(np.round(eq / np.array([1e-9, 1e-9, 1e-9, 1e-9 * scale])), axis=0, return_index=True)
    eq = eq[np.sort(keep)]  # one row per plane (a duplicate split by the rounding costs only time)
    return eq[:, :3].copy(), -eq[:, 3].copy(), pts[hull.vertices]


def _solve_vertices(A: np.ndarray, b: np.ndarray, tol: float) -> list[np.ndarray]:
    """Vertices of the polytopes {x: A_c x <= b_c} for a chunk of cells (A: (C, P, 3), b: (C, P)): every
    intersection of three of the P planes that satisfies all half-spaces within tol (vectorised)."""
    P = A.shape[1]
    tri = np.array(list(combinations(range(P), 3)))
    M = A[:, tri]  # (C, T, 3, 3)
    rhs = b[:, tri]  # (C, T, 3)
    det = np.linalg.det(M)
    ok = np.abs(det) > 1e-10
    M = np.where(ok[..., None, None], M, np.eye(3))
    x = np.linalg.solve(M, rhs[..., None])[..., 0]  # (C, T, 3)
    feas = ok & np.all(np.einsum("cpk,ctk->ctp", A, x) <= b[:, None, :] + tol, axis=2)
    return [x[c][feas[c]] for c in range(len(A))]


def _hull_props(pts: np.ndarray, tol: float):
    """(volume, centroid, hull vertices, facet equations n.x + e = 0) of the convex hull of pts; None when
    they span no volume."""
    if len(pts) < 4:
        return None
    try:
        hull = ConvexHull(pts)
    except QhullError:
        return None
    p0 = pts[hull.vertices].mean(axis=0)
    tet = pts[hull.simplices]  # (F, 3, 3)
    v6 = np.einsum("fi,fi->f", tet[:, 0] - p0, np.cross(tet[:, 1] - p0, tet[:, 2] - p0))
    vol = float(np.sum(np.abs(v6))) / 6.0
    if vol <= 0:
        return None
    cen = np.sum(np.abs(v6)[:, None] * (p0 + tet.sum(axis=1)) / 4.0, axis=0) / (6.0 * vol)
    return vol, cen, pts[hull.vertices], hull.equations


def _faces_on(eq: np.ndarray, normals: np.ndarray, lo_t: np.ndarray, hi_t: np.ndarray, tol: float) -> np.ndarray:
    """Per set: does a hull facet (equations n.x + e = 0, outward n) lie on one of the block's slab planes
    (n = +n_s at t_hi, n = -n_s at t_lo)?"""
    dots = eq[:, :3] @ normals.T  # (F, m)
    off = -eq[:, 3:4]  # (F, 1)
    up = (np.abs(dots - 1) < 1e-9) & (np.abs(off - hi_t[None]) <= tol)
    down = (np.abs(dots + 1) < 1e-9) & (np.abs(off + lo_t[None]) <= tol)
    return np.any(up | down, axis=0)


def _set_planes(normals, origin, lo_pts, sets: list[JointSet], rng) -> list[np.ndarray]:
    d = (np.asarray(lo_pts) - origin) @ np.asarray(normals).T  # (V, m)
    return [plane_positions(float(d[:, s].min()), float(d[:, s].max()), js, rng) + float(normals[s] @ origin)
            for s, js in enumerate(sets)]


def cut_convex(A, b, corners, sets: list[JointSet], normals, origin, seed: int = 0, chunk: int = 4096,
               max_cells: int = 50_000_000) -> Cut:
    """Cut the convex region {A x <= b} (its vertices ``corners``) by the joint sets (unit ``normals``,
    planes through ``origin`` + offsets); vectorised over cells. Cells of zero volume (a joint plane on
    the region's boundary) are dropped."""
    A, b = np.asarray(A, float), np.asarray(b, float)
    normals = np.asarray(normals, float)
    rng = np.random.default_rng(seed)
    pos = _set_planes(normals, np.asarray(origin, float), corners, sets, rng)
    L = float(np.ptp(corners, axis=0).max())
    tol = 1e-9 * L
    counts = [len(p) - 1 for p in pos]
    ncand = int(np.prod(counts, dtype=float))
    if ncand > max_cells:
        raise RockMassError("joint_sets", f"{ncand:.3g} candidate cells (slabs per set {counts}) exceed {max_cells:.3g}; "
                                          f"the spacings are too small for the region")
    idx = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), axis=-1).reshape(-1, len(sets))
    # lower and upper plane offsets of every candidate's slabs: (N, m)
    t_lo = np.stack([pos[s][idx[:, s]] for s in range(len(sets))], axis=1)
    t_hi = np.stack([pos[s][idx[:, s] + 1] for s in range(len(sets))], axis=1)
    verts: list = [None] * len(idx)
    eqs: dict[int, np.ndarray] = {}
    vols = np.zeros(len(idx))
    cens = np.zeros((len(idx), 3))
    done = np.zeros(len(idx), bool)
    if len(sets) == 3 and abs(np.linalg.det(normals)) > 1e-6:
        # parallelepipeds: corner = N^-1 t for t from (t_lo | t_hi) per set
        Ninv = np.linalg.inv(normals)
        pick = np.array([[sx, sy, sz] for sz in (0, 1) for sy in (0, 1) for sx in (0, 1)], bool)
        T = np.where(pick[None], t_hi[:, None, :], t_lo[:, None, :])  # (N, 8, 3)
        P = T @ Ninv.T  # (N, 8, 3)
        inside = np.all(np.einsum("pk,nvk->nvp", A, P) <= b + tol, axis=(1, 2))
        outside = np.any(np.all(np.einsum("pk,nvk->nvp", A, P) >= b - tol, axis=1), axis=1)
        vol_pp = np.prod(t_hi - t_lo, axis=1) / abs(np.linalg.det(normals))
        vols[inside] = vol_pp[inside]
        cens[inside] = P[inside].mean(axis=1)
        done |= inside | outside
        interior_pts = P
    else:
        inside = np.zeros(len(idx), bool)
        interior_pts = None
    rest = np.flatnonzero(~done)
    for c0 in range(0, len(rest), chunk):
        cs = rest[c0:c0 + chunk]
        Ac = np.concatenate([np.broadcast_to(A, (len(cs),) + A.shape), np.broadcast_to(normals, (len(cs),) + normals.shape),
                             np.broadcast_to(-normals, (len(cs),) + normals.shape)], axis=1)
        bc = np.concatenate([np.broadcast_to(b, (len(cs), len(b))), t_hi[cs], -t_lo[cs]], axis=1)
        for c, pts in zip(cs, _solve_vertices(Ac, bc, tol)):
            hp = _hull_props(pts, tol)
            if hp is not None:
                vols[c], cens[c], verts[c], eqs[c] = hp
    keep = vols > 1e-12 * max(float(vols.sum()), 1e-300)  # a plane on the boundary leaves a cell of rounding-error volume
    keep_i = np.flatnonzero(keep)
    nv = np.array([8 if inside[i] else len(verts[i]) for i in keep_i], dtype=np.int64)
    start = np.concatenate([[0], np.cumsum(nv)])
    V = np.empty((int(start[-1]), 3))
    ins = inside[keep_i]
    if ins.any():
        rows = (start[:-1][ins][:, None] + np.arange(8)).ravel()
        V[rows] = interior_pts[keep_i[ins]].reshape(-1, 3)
    for j in np.flatnonzero(~ins):
        V[start[j]:start[j + 1]] = verts[keep_i[j]]
    on_set = np.ones((len(keep_i), len(sets)), bool)
    for j in np.flatnonzero(~ins):
        i = keep_i[j]
        on_set[j] = _faces_on(eqs[i], normals, t_lo[i], t_hi[i], 1e-7 * L)
    # a parallelepiped's largest inscribed sphere: the ball at its centre as wide as its thinnest slab
    width = np.where(ins, np.min(t_hi[keep_i] - t_lo[keep_i], axis=1) * np.ones(len(keep_i)), np.nan)
    return Cut(vertices=V, start=start, volumes=vols[keep_i], centroids=cens[keep_i], cells=idx[keep_i],
               on_set=on_set, normals=normals, positions=pos, width=width)


def cut_box(box_min, box_max, sets: list[JointSet], seed: int = 0, orientation_deg=(0.0, 0.0, 0.0), origin=None,
            min_block_size: float = 0.0, dim: int = 3) -> Cut:
    """A box (turned about its centre by orientation_deg, fixed x, y, z turns) cut by joint sets: the entry point
    for benchmarks (vectorised: ~1e6 blocks of three independent sets in seconds). Planes pass through origin
    (default: the box's first corner, box_min turned) shifted by each set's offset."""

    R = quat_to_matrix(euler_xyz_deg_to_quat(orientation_deg))
    A, b, corners = box_halfspaces(box_min, box_max, R)
    normals = np.array([joint_normal(js.dip_deg, js.dip_direction_deg, dim) for js in sets])
    cut = cut_convex(A, b, corners, sets, normals, corners[0] if origin is None else origin, seed=seed)
    return merge_slivers(cut, min_block_size)


def winding_number(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Generalised winding number of a closed, outward-oriented triangle mesh at points (1 inside, 0 outside):
    the solid angles of the triangles (Van Oosterom & Strackee 1983) summed over 4 pi."""
    w = np.zeros(len(points))
    for c0 in range(0, len(points), 256):
        p = points[c0:c0 + 256]
        a, b, c = (tris[None, :, k] - p[:, None] for k in range(3))  # (k, F, 3)
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        num = np.einsum("kfi,kfi->kf", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("kfi,kfi->kf", a, b) * lc + np.einsum("kfi,kfi->kf", b, c) * la \
            + np.einsum("kfi,kfi->kf", c, a) * lb
        w[c0:c0 + 256] = np.arctan2(num, den).sum(axis=1) / (2 * np.pi)
    return w


def _clip_cell_by_mesh(Ac, bc, cverts, tris, tri_n, tol):
    """Vertices (of the hull) and volume of the cell {Ac x <= bc} (vertices cverts) intersected with a closed
    mesh, or None if empty. The mesh's inside is the signed sum of the columns under its triangles (a vertical
    ray from a point inside crosses the surface above it once more upward-facing than downward-facing), so

        V(cell & mesh) = sum_t sign(n_z,t) V(cell & {(x, y) in proj t, z <= plane of t})

    each term a convex polytope (vertices from every three of its planes, volume by Qhull). The pieces' vertices
    inside or on the mesh hold every vertex of the clipped cell: their hull has its volume iff it is convex.
    Returns (hull vertices, volume of the clipped cell, hull volume, hull centroid, hull equations)."""
    lo, hi = cverts.min(axis=0) - tol, cverts.max(axis=0) + tol
    tmin, tmax = tris.min(axis=1), tris.max(axis=1)
    rel = np.flatnonzero((tmin[:, 0] <= hi[0]) & (tmax[:, 0] >= lo[0]) & (tmin[:, 1] <= hi[1]) & (tmax[:, 1] >= lo[1])
                         & (tmax[:, 2] >= lo[2]) & (np.abs(tri_n[:, 2]) > 1e-12))
    if len(rel) == 0:
        return None
    T = tris[rel]
    sgn = np.sign(tri_n[rel, 2])
    # the column's side planes (inward: orient each projected edge so that the third corner is inside)
    As, bs = [], []
    for k in range(3):
        p, q, r = T[:, k], T[:, (k + 1) % 3], T[:, (k + 2) % 3]
        e = q - p
        nrm = np.stack([e[:, 1], -e[:, 0], np.zeros(len(T))], axis=1)
        flip = np.einsum("ti,ti->t", nrm, r - p) > 0  # r on the positive side: the outward normal is -nrm
        nrm[flip] *= -1
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        As.append(nrm)
        bs.append(np.einsum("ti,ti->t", nrm, p))
    up = tri_n[rel] * sgn[:, None]  # the triangle's normal turned upward: below it is up.x <= up.p
    As.append(up)
    bs.append(np.einsum("ti,ti->t", up, T[:, 0]))
    A = np.concatenate([np.broadcast_to(Ac, (len(T),) + Ac.shape), np.stack(As, axis=1)], axis=1)
    b = np.concatenate([np.broadcast_to(bc, (len(T), len(bc))), np.stack(bs, axis=1)], axis=1)
    vol, moment, cand = 0.0, np.zeros(3), []
    for t, pts in enumerate(_solve_vertices(A, b, tol)):
        hp = _hull_props(pts, tol)
        if hp is None:
            continue
        vol += sgn[t] * hp[0]
        moment += sgn[t] * hp[0] * hp[1]
        on_tri = np.abs(pts @ up[t] - b[t, -1]) <= tol
        cand.append((pts[on_tri], pts[~on_tri]))
    if not cand or vol <= 0:
        return None
    on = np.concatenate([c[0] for c in cand])  # on a triangle and in the cell: on the clipped cell's boundary
    off = np.concatenate([c[1] for c in cand])
    if len(off):
        # the others count when inside the mesh; a point on its surface (a cell corner on a face) is tested a
        # millionth of the way toward the clipped cell's centroid (inside it when the clipped cell is convex)
        off = np.unique(off, axis=0)
        cen = moment / vol
        off = off[winding_number(off + 1e-6 * (cen - off), tris) > 0.5]
    hp = _hull_props(np.concatenate([on, off]), tol)
    if hp is None:
        return None
    return hp[2], vol, hp[0], hp[1], hp[3]


def cut_mesh(mesh, sets: list[JointSet], normals, origin, seed: int = 0, convex_tol: float = 1e-6) -> Cut:
    """Cut a closed, outward-oriented trimesh region by the joint sets. A convex mesh (volume within
    convex_tol of its hull's) is cut exactly as the hull of its vertices (vectorised). A non-convex one is cut
    cell by cell: each cell of its bounding box is clipped by the mesh (_clip_cell_by_mesh); a clipped cell
    that is not one convex piece is a RockMassError naming region.mesh (refused, not decomposed: DDA blocks
    are convex and a decomposition adds cuts that are not joints)."""
    vol = abs(float(mesh.volume))
    hv = float(mesh.convex_hull.volume)
    if hv - vol <= convex_tol * hv:
        A, b, corners = hull_halfspaces(np.asarray(mesh.vertices))
        return cut_convex(A, b, corners, sets, normals, origin, seed=seed)
    normals = np.asarray(normals, float)
    lo, hi = np.asarray(mesh.bounds, float)
    A, b, corners = box_halfspaces(lo, hi)
    box = cut_convex(A, b, corners, sets, normals, origin, seed=seed)
    L = float(np.ptp(corners, axis=0).max())
    tol = 1e-9 * L
    tris = np.asarray(mesh.triangles, float)
    tri_n = np.asarray(mesh.face_normals, float)
    m = len(sets)
    out_v, vols, cens, cells, on = [], [], [], [], []
    for i in range(len(box)):
        k = box.cells[i]
        t_lo = np.array([box.positions[s][k[s]] for s in range(m)])
        t_hi = np.array([box.positions[s][k[s] + 1] for s in range(m)])
        Ac = np.concatenate([A, normals, -normals])
        bc = np.concatenate([b, t_hi, -t_lo])
        res = _clip_cell_by_mesh(Ac, bc, box.block_vertices(i), tris, tri_n, tol)
        if res is None:
            continue
        hverts, v, hvol, hcen, heq = res
        if v <= 1e-12 * vol:
            continue
        if abs(hvol - v) > convex_tol * hvol:
            raise RockMassError("region.mesh", (
                f"the mesh is not convex, and the cell of joint-plane indices {k.tolist()} (near "
                f"{np.round(hcen, 4).tolist()} m) clipped by it is not one convex piece: volume {v:.6g} m^3, its hull "
                f"{hvol:.6g} m^3 ({100 * (1 - v / hvol):.3g}% short). DDA blocks are convex, and the region is refused "
                f"rather than decomposed (a decomposition adds cuts that are not joints): put a joint plane through the "
                f"concave edge (offset_m), or split the mesh there into convex parts, one [[rock_mass]] each"))
        out_v.append(hverts)
        vols.append(hvol)
        cens.append(hcen)
        cells.append(k)
        on.append(_faces_on(heq, normals, t_lo, t_hi, 1e-7 * L))
    return _csr(out_v, vols, cens, cells, on, normals, box.positions, m)


def _csr(out_v, vols, cens, cells, on, normals, pos, m) -> Cut:
    nv = np.array([len(v) for v in out_v], dtype=np.int64)
    start = np.concatenate([[0], np.cumsum(nv)]).astype(np.int64)
    V = np.concatenate(out_v) if out_v else np.zeros((0, 3))
    return Cut(vertices=V, start=start, volumes=np.asarray(vols, float), centroids=np.asarray(cens, float).reshape(-1, 3),
               cells=np.asarray(cells, dtype=np.int64).reshape(-1, m), on_set=np.asarray(on, bool).reshape(-1, m),
               normals=normals, positions=pos)


def inscribed_diameter(eq: np.ndarray) -> float:
    """Diameter of the largest sphere inside the convex polytope {x: n_f.x + e_f <= 0} (unit n_f): the
    Chebyshev centre, max r with n_f.x + r <= -e_f (a linear programme, scipy HiGHS)."""
    from scipy.optimize import linprog

    A = np.concatenate([eq[:, :3], np.ones((len(eq), 1))], axis=1)
    res = linprog(c=[0, 0, 0, -1.0], A_ub=A, b_ub=-eq[:, 3], bounds=[(None, None)] * 3 + [(0, None)], method="highs")
    return 2.0 * float(res.x[3]) if res.status == 0 else 0.0


def block_widths(cut: Cut, min_size: float = math.inf) -> np.ndarray:
    """Inscribed-sphere diameter of every block; where (6 V / pi)^(1/3) (the sphere of the block's volume, an
    upper bound) is already below min_size, that bound stands in (such a block is a sliver either way)."""
    w = np.full(len(cut), np.nan) if cut.width is None else cut.width.copy()
    bound = (6.0 * cut.volumes / math.pi) ** (1.0 / 3.0)
    todo = np.isnan(w) & (bound >= min_size)
    w[np.isnan(w) & ~todo] = bound[np.isnan(w) & ~todo]
    for i in np.flatnonzero(todo):
        w[i] = inscribed_diameter(ConvexHull(cut.block_vertices(i)).equations)
    return w


def merge_slivers(cut: Cut, min_size: float) -> Cut:
    """Merge every block whose largest inscribed sphere is narrower than min_size (a sliver: a thin plate, a
    needle or a small block, the shapes that make the DDA step small) into a face neighbour (one cell index
    apart in one set), or two at once, such that the union is convex (its hull's volume equals the sum within
    1e-9): the largest neighbour first, the thinnest sliver first, and a merged block still too thin goes
    again. A sliver that cannot merge is a RockMassError naming min_block_size_m."""
    n = len(cut)
    if min_size <= 0 or n == 0:
        return cut
    width = block_widths(cut, min_size)
    small = np.flatnonzero(width < min_size)
    if len(small) == 0:
        cut.width = width
        return cut
    L = float(np.ptp(cut.vertices, axis=0).max())
    tol = 1e-9 * L
    group = np.arange(n)
    members: dict[int, list[int]] = {i: [i] for i in range(n)}
    gverts = {i: cut.block_vertices(i) for i in small}
    gvol = cut.volumes.copy()
    gcen = cut.centroids.copy()
    geq: dict[int, np.ndarray] = {}
    by_cell: dict[tuple, list[int]] = {}
    for i, c in enumerate(map(tuple, cut.cells)):
        by_cell.setdefault(c, []).append(i)
    m = cut.cells.shape[1]
    def order_key(i):  # the thinnest first; of equally thin ones the largest (a face sliver before an edge's)
        return (round(width[i] / tol), -gvol[i])

    queue = sorted(small.tolist(), key=order_key)
    merged = 0
    while queue:
        g = queue.pop(0)
        if group[g] != g or width[g] >= min_size:
            continue
        nbrs = set()
        for i in members[g]:
            for s in range(m):
                for d in (-1, 1):
                    c = list(cut.cells[i])
                    c[s] += d
                    for j in by_cell.get(tuple(c), []):
                        if group[j] != g:
                            nbrs.add(int(group[j]))
        best = None
        for h in nbrs:
            if h not in gverts:
                gverts[h] = cut.block_vertices(h)
        # one neighbour, else two at once (a sliver in the corner between two blocks): of the convex unions the
        # one with the widest inscribed sphere (a thin slab joins the block across its thin side), then the largest
        order = sorted(nbrs, key=lambda h: -gvol[h])
        for tries in ([(h,) for h in order], list(combinations(order, 2))):
            found = []
            for hs in tries:
                hp = _hull_props(np.concatenate([gverts[g]] + [gverts[h] for h in hs]), tol)
                if hp is not None and hp[0] <= (gvol[g] + sum(gvol[h] for h in hs)) * (1 + 1e-9):
                    found.append((inscribed_diameter(hp[3]), hp[0], hs, hp))
            if found:
                wbest, _, hs, hp = max(found, key=lambda f: (round(f[0] / tol), f[1]))
                best = (hs, hp, wbest)
                break
        if best is None:
            raise RockMassError("min_block_size_m", (
                f"= {min_size:g} m: block #{g} near {np.round(gcen[g], 4).tolist()} m is a sliver (its largest inscribed "
                f"sphere is {width[g]:.4g} m across, volume {gvol[g]:.4g} m^3) with no face neighbour it can merge with into "
                f"a convex block; lower min_block_size_m, or move the joint planes (offset_m) so that no sliver forms there"))
        hs, (_, _, hv, heq), wbest = best
        parts = (g,) + hs
        vol = sum(gvol[k] for k in parts)  # the exact sum (the hull agrees within 1e-9)
        cen = sum(gvol[k] * gcen[k] for k in parts) / vol
        keep_g = max(parts, key=lambda k: len(members[k]))  # keep the largest group's id
        for other in parts:
            if other != keep_g:
                for i in members[other]:
                    group[i] = keep_g
                members[keep_g] += members.pop(other)
        gvol[keep_g], gcen[keep_g], gverts[keep_g], geq[keep_g] = vol, cen, hv, heq
        width[keep_g] = wbest
        merged += len(hs)
        if width[keep_g] < min_size:
            queue.append(keep_g)
            queue.sort(key=order_key)
    roots = np.flatnonzero(group == np.arange(n))
    out_v, on = [], []
    for r in roots:
        out_v.append(gverts[r] if len(members[r]) > 1 else cut.block_vertices(r))
        on.append(np.any(cut.on_set[members[r]], axis=0) if len(members[r]) == 1 else _merged_on_set(cut, gverts[r], geq[r], members[r]))
    res = _csr(out_v, gvol[roots], gcen[roots], cut.cells[roots], on, cut.normals, cut.positions, m)
    res.merged = merged
    res.width = width[roots]
    return res


def _merged_on_set(cut: Cut, verts: np.ndarray, eq: np.ndarray, members: list[int]) -> np.ndarray:
    """Sets with a face of the merged block: any plane of a member's slabs carrying >= 3 non-collinear vertices."""
    L = float(np.ptp(verts, axis=0).max())
    out = np.zeros(cut.cells.shape[1], bool)
    for i in members:
        lo_t = np.array([cut.positions[s][k] for s, k in enumerate(cut.cells[i])])
        hi_t = np.array([cut.positions[s][k + 1] for s, k in enumerate(cut.cells[i])])
        out |= _faces_on(eq, cut.normals, lo_t, hi_t, 1e-7 * L)
    return out


def jennings_strength(js: JointSet, rock_friction_deg: float, rock_cohesion_pa: float, rock_tension_pa: float):
    """(friction angle deg, cohesion Pa, tensile strength Pa) of a joint plane with persistence p (Jennings 1970)."""
    p = js.persistence
    tphi = p * math.tan(math.radians(js.friction_angle_deg)) + (1 - p) * math.tan(math.radians(rock_friction_deg))
    return (math.degrees(math.atan(tphi)), p * js.cohesion_pa + (1 - p) * rock_cohesion_pa,
            p * js.tensile_strength_pa + (1 - p) * rock_tension_pa)


# --------------------------------------------------------------------------------------------
# scene [[rock_mass]] -> BlockSpecs
# --------------------------------------------------------------------------------------------


def _joint_sets(entry) -> list[JointSet]:
    return [JointSet(dip_deg=js.dip_deg, dip_direction_deg=js.dip_direction_deg, spacing_m=js.spacing_m, offset_m=js.offset_m,
                     random_offset=js.random_offset, spacing_jitter=js.spacing_jitter, persistence=js.persistence,
                     friction_angle_deg=js.friction_angle_deg, cohesion_pa=js.cohesion_pa,
                     tensile_strength_pa=js.tensile_strength_pa, name=js.name) for js in entry.joint_sets]


def cut_entry(entry, dim: int = 3) -> Cut:
    """Cut one validated [[rock_mass]] entry (rockwave/scene/format.py); RockMassError names the key below the entry."""

    sets = _joint_sets(entry)
    normals = []
    for j, js in enumerate(sets):
        try:
            normals.append(joint_normal(js.dip_deg, js.dip_direction_deg, dim))
        except RockMassError as e:
            raise RockMassError(f"joint_sets[{j}].{e.key}", str(e)) from None
    reg = entry.region
    origin = None if entry.origin_m is None else np.asarray(list(entry.origin_m) + [0.0] * (3 - dim), float)
    if reg.mesh is not None:
        try:
            tm = sampling.load_trimesh(reg.mesh, reg.mesh_scale, reg.mesh_offset_m)
        except sampling.MeshInputError as e:
            raise RockMassError("region.mesh", str(e)) from None
        if not tm.is_watertight:
            raise RockMassError("region.mesh", f"{reg.mesh}: the mesh is not closed (watertight); a region needs an inside")
        if tm.volume < 0:
            tm.invert()
        cut = cut_mesh(tm, sets, normals, tm.bounds[0] if origin is None else origin, seed=entry.seed)
    else:
        if reg.vertices_m is not None:
            A, b, corners = hull_halfspaces(reg.vertices_m)
            first = corners.min(axis=0)
        else:
            lo, hi = list(reg.box_min_m), list(reg.box_max_m)
            if dim == 2:
                lo, hi = lo + [-0.5 * reg.depth_m], hi + [0.5 * reg.depth_m]
            R = quat_to_matrix(euler_xyz_deg_to_quat(reg.orientation_deg))
            A, b, corners = box_halfspaces(lo, hi, R)
            first = corners[0]
        cut = cut_convex(A, b, corners, sets, normals, first if origin is None else origin, seed=entry.seed)
    if len(cut) == 0:
        raise RockMassError("joint_sets", "the joint sets cut no block from the region")
    return merge_slivers(cut, entry.min_block_size_m)


def block_materials(entry, cut: Cut):
    """One ContactMaterial per block: per property the weakest of the (Jennings) strengths of the joint sets
    the block has faces on; the intact rock's for a block with none. Stiffness and damping: the entry's."""

    mat = entry.material
    rock = (mat.friction_angle_deg, mat.cohesion_pa, mat.tensile_strength_pa)
    strengths = np.array([jennings_strength(js, *rock) for js in _joint_sets(entry)])  # (m, 3)
    cache: dict[bytes, ContactMaterial] = {}
    out = []
    for on in cut.on_set:
        key = on.tobytes()
        if key not in cache:
            phi, c, t = strengths[on].min(axis=0) if on.any() else rock
            cache[key] = ContactMaterial(friction_angle_deg=float(phi), cohesion_pa=float(c), tensile_strength_pa=float(t),
                                         normal_stiffness=mat.normal_stiffness_n_m, shear_stiffness=mat.shear_stiffness_n_m,
                                         restitution=mat.restitution, damping_ratio=mat.damping_ratio)
        out.append(cache[key])
    return out


def block_geometries(cut: Cut, name: str = "rock") -> tuple[list, np.ndarray]:
    """One ConvexPolyhedron per block (blocks of one shape, such as a regular cut's interior, share one; the
    shapes found with np.unique on the vertices about their mean, quantised to 1e-9 of the cut's size) and
    the blocks' centroid positions (n, 3)."""
    n = len(cut)
    geoms: list = [None] * n
    pos = np.zeros((n, 3))
    counts = np.diff(cut.start)
    quantum = 1e-9 * float(np.ptp(cut.vertices, axis=0).max())  # one length for all: a scaled copy is another shape
    for nv in np.unique(counts):
        ids = np.flatnonzero(counts == nv)
        V = cut.vertices[cut.start[ids][:, None] + np.arange(nv)]  # (k, nv, 3)
        mean = V.mean(axis=1)
        keys = np.round((V - mean[:, None]) / quantum).astype(np.int64).reshape(len(ids), -1)
        _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        inverse = inverse.ravel()
        shapes, delta = [], np.zeros((len(first), 3))
        for u, f in enumerate(first):
            k = int(ids[f])
            try:
                g = geometry.prism(V[f], name=f"{name}_{k}")
            except (geometry.GeometryError, ValueError) as e:
                raise RockMassError("joint_sets", f"block {k} near {np.round(mean[f], 4).tolist()} m: {e}") from None
            shapes.append(g)
            delta[u] = np.asarray(g.origin_offset) - mean[f]  # centroid minus vertex mean, the same for the whole shape
        pos[ids] = mean + delta[inverse]
        for m, u in zip(ids.tolist(), inverse.tolist()):
            geoms[m] = shapes[u]
    return geoms, pos


def rock_mass_specs(scene) -> list:
    """BlockSpecs of every [[rock_mass]] entry of a validated scene (SceneError naming rock_mass[i].<key>).
    Blocks of one shape (a regular cut's interior) share one ConvexPolyhedron."""

    specs = []
    for i, entry in enumerate(scene.rock_mass):
        try:
            cut = cut_entry(entry, scene.dim)
        except RockMassError as e:
            raise SceneError(scene.path, [(f"rock_mass[{i}].{e.key}", str(e))]) from None
        mats = block_materials(entry, cut)
        geoms, positions = block_geometries(cut, entry.name)
        for k, (g, pos) in enumerate(zip(geoms, positions.tolist())):
            specs.append(BlockSpec(geometry=g, position=tuple(pos), density=entry.density_kg_m3, kind=entry.kind,
                                   youngs_modulus=entry.youngs_modulus_pa, poisson_ratio=entry.poisson_ratio,
                                   material=mats[k], name=f"{entry.name}_{k}"))
    return specs


def estimate_block_count(entry, dim: int = 3) -> int:
    """Blocks a [[rock_mass]] entry will give, without cutting: the region's bounding volume over the volume
    of a cell of its first three sets (for memory and run-length estimates)."""
    reg = entry.region
    if reg.box_min_m is not None and reg.box_max_m is not None:
        ext = np.asarray(reg.box_max_m, float) - np.asarray(reg.box_min_m, float)
        vol = float(np.prod(ext)) * (reg.depth_m if dim == 2 else 1.0)
    elif reg.vertices_m is not None:
        vol = float(np.prod(np.ptp(np.asarray(reg.vertices_m, float), axis=0)))
    else:
        return 1
    sp = [js.spacing_m for js in entry.joint_sets][:3]
    cell = float(np.prod(sp)) * (reg.depth_m if dim == 2 and len(sp) < 3 else 1.0)
    if len(sp) < 3 and dim == 3:
        cell *= float(np.cbrt(vol)) ** (3 - len(sp))
    return max(1, int(round(vol / cell)))


def resize_box_region(entry, extents) -> None:
    """Give a [[rock_mass]] box region new edge lengths (before turning), its first corner (box_min_m turned)
    kept where it is, so a slab resting on a slope stays on it (benchmarks grow a scene's rock mass this way)."""

    reg = entry["region"]
    R = quat_to_matrix(euler_xyz_deg_to_quat(reg["orientation_deg"]))
    _, _, corners = box_halfspaces(reg["box_min_m"], reg["box_max_m"], R)
    h = 0.5 * np.asarray(extents, float)
    c = corners[0] + R @ h
    reg["box_min_m"], reg["box_max_m"] = (c - h).tolist(), (c + h).tolist()
