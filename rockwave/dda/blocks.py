"""Explicit 3D DDA rock-block solver (host side).

What lives where:

* ``BlockSpec`` (with ``ContactMaterial``, ``KinematicMotion``): one block as a scene gives it
  (rockwave/build/rocks.py builds them from ``[[blocks]]``).
* ``BlockModel``: the static description, device arrays that never change during a run: concatenated
  vertices / faces / half-edges with per-block offsets, masses, inertia, kinds, materials, kinematic
  motions, and their kernel argument groups (``topology``, ``props``, ``material``, ``motion``:
  kernels/dda/blocks.py structs). ``planar=True`` (2D scenes): blocks are prisms extruded along z that move
  in their x-y plane only (z fixed, rotation about z only).
* ``BlockState``: everything that changes in time: poses, velocities, strains, load accumulators
  (``ext_force`` / ``ext_torque``, where the coupling adds its reactions), world vertices, the two
  contact-history tables (swapped each step) and ``time``; kernel views ``bodies``, ``loads``,
  ``table_views``. A checkpoint of it is a complete restart point.
* ``BlockOptions``: the solver's knobs (dt safety, broad-phase cell and margin, capacity paths),
  defaults equal to the shipped values (a scene's: rockwave/build/options.py block_options).
* ``BlockSolver(model, options=...)``: the solver contract of rockwave/base/solver.py:
  ``stable_dt(state)`` = options.dt_safety x ``critical_dt()`` (the physical limit 2/omega_max), and
  ``step(state, ts)`` (ts: rockwave.base.solver.TimeStep; refuses ts.dt above ``critical_dt()``) = world
  vertices + AABBs, uniform-grid broad phase, Fast Common Plane narrow phase with multi-point
  contacts, penalty contact forces with per-pair history, explicit integration and, for a planar
  model, the 2D constraint. All as Warp kernels on the model's device (kernels/dda/blocks.py). The solver
  keeps buffers only (capacities, the pair list between broad phases, diagnostics).

Units SI, z up, quaternions (x, y, z, w).  Contact stiffness is *per contact point* (a face resting
on a face gets >= 3 points, each with k_n), so a box resting on its face sinks m g / (n_points k_n).
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from rockwave.base.maths import next_pow2, quat_to_matrix
from rockwave.base.solver import TimeStep
from rockwave.dda.geometry import CompoundBlock, ConvexPolyhedron
from rockwave.kernels.dda import blocks as dda_k
from rockwave.kernels.dda import blocks_coop as coop_k

__all__ = [
    "ContactMaterial",
    "KinematicMotion",
    "BlockSpec",
    "CompoundPart",
    "BlockModel",
    "BlockState",
    "BlockSolver",
    "BlockOptions",
    "BlockOverlapError",
    "check_initial_overlap",
    "KINDS",
]

KINDS = {"rigid": 0, "deformable": 1, "fixed": 2, "kinematic": 3}
DEFAULT_YOUNGS_MODULUS = 10.0e9  # Pa, a medium-strength rock
DEFAULT_RESTITUTION = 0.5
PENALTY_FACTOR = 0.1  # default k_n = PENALTY_FACTOR * E * L  (N/m per contact point)


class BlockOverlapError(ValueError):
    """Two blocks overlap in the initial configuration."""


def restitution_with_cutoff(zeta: float) -> float:
    """Coefficient of restitution of a linear spring-dashpot contact whose force is cut off at zero
    (no pull): x'' + 2 zeta x' + x = 0 from x = 0, x' = 1; the contact force x + 2 zeta x' vanishes at
    w_d t* = pi - atan2(2 zeta w_d, 1 - 2 zeta^2) (w_d = sqrt(1 - zeta^2)); e = -x'(t*).
    (Without the cut-off it would be exp(-zeta pi / w_d); the cut-off ends the contact earlier and
    gives a slightly larger e, e.g. 0.623 instead of 0.6 at zeta = 0.16.)"""
    if zeta <= 0.0:
        return 1.0
    z = min(zeta, 0.999999)
    wd = math.sqrt(1.0 - z * z)
    ts = (math.pi - math.atan2(2.0 * z * wd, 1.0 - 2.0 * z * z)) / wd
    return math.exp(-z * ts) * -(math.cos(wd * ts) - z / wd * math.sin(wd * ts))


@functools.lru_cache(maxsize=256)
def restitution_to_damping_ratio(e: float) -> float:
    """Damping ratio zeta giving restitution e for the cut-off spring-dashpot contact used here
    (bisection on restitution_with_cutoff; e -> 1: zeta -> 0; e below ~0.2 needs zeta -> 1, clamped)."""
    if not 0.0 <= e <= 1.0:
        raise ValueError(f"restitution must be in [0, 1], got {e}")
    if e >= 1.0:
        return 0.0
    lo, hi = 0.0, 0.999999
    if restitution_with_cutoff(hi) >= e:
        return 1.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if restitution_with_cutoff(mid) > e:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@dataclass
class ContactMaterial:
    """Contact law of a block's surface (a pair uses the weaker value of the two blocks; damping the larger).

    friction_angle_deg: Coulomb friction angle phi (mu = tan phi).
    cohesion_pa: cohesion c (Pa), times the contact area share of each point.
    tensile_strength_pa: pull allowed per unit area before the cut-off (0 = no tension).
    normal_stiffness: k_n in N/m per contact point; None -> 0.1 * E * L (E = block modulus or 10 GPa,
        L = V^(1/3)).  0.1 E L keeps the self-weight penetration ~1e-6 L-ish while the critical step
        stays ~1e-3 s for metre-sized blocks (a full E*L would cut dt by ~3x for no gain in accuracy).
    shear_stiffness: k_s in N/m per point; None -> k_n / (2 (1 + nu)) (the G/E ratio of the block).
    restitution: coefficient e of a normal impact; the dashpot ratio zeta is chosen so that the
        spring-dashpot with the tension cut-off rebounds with exactly e (restitution_to_damping_ratio).
        damping_ratio overrides it if given.  Default e = 0.5.
    """

    friction_angle_deg: float = 30.0
    cohesion_pa: float = 0.0
    tensile_strength_pa: float = 0.0
    normal_stiffness: float | None = None
    shear_stiffness: float | None = None
    restitution: float | None = None
    damping_ratio: float | None = None

    def resolved_damping_ratio(self) -> float:
        if self.damping_ratio is not None:
            if self.damping_ratio < 0:
                raise ValueError("damping_ratio must be >= 0")
            return float(self.damping_ratio)
        return restitution_to_damping_ratio(DEFAULT_RESTITUTION if self.restitution is None else self.restitution)


@dataclass
class KinematicMotion:
    """Prescribed motion of a kinematic block, as a displacement added to BlockSpec.position.

    kind "sine": u(t) = amplitude * sin(2 pi frequency_hz t + phase_rad), du/dt exact.
    kind "table": u(t) linear between rows (times, displacements), constant outside; du/dt = slope.
    """

    kind: str = "sine"
    amplitude: tuple = (0.0, 0.0, 0.0)
    frequency_hz: float = 0.0
    phase_rad: float = 0.0
    times: tuple = ()
    displacements: tuple = ()

    @staticmethod
    def sine(amplitude, frequency_hz, phase_rad=0.0) -> "KinematicMotion":
        return KinematicMotion("sine", tuple(float(a) for a in amplitude), float(frequency_hz), float(phase_rad))

    @staticmethod
    def table(times, displacements) -> "KinematicMotion":
        t = np.asarray(times, float)
        d = np.asarray(displacements, float).reshape(-1, 3)
        if len(t) < 1 or len(t) != len(d) or np.any(np.diff(t) <= 0):
            raise ValueError("motion table: times must be strictly increasing and match the displacement rows")
        return KinematicMotion("table", times=tuple(t), displacements=tuple(map(tuple, d)))

    def displacement(self, t: float) -> np.ndarray:
        """Host-side evaluation (reference for tests and exporters)."""
        if self.kind == "sine":
            return np.asarray(self.amplitude) * math.sin(2 * math.pi * self.frequency_hz * t + self.phase_rad)
        tt = np.asarray(self.times)
        d = np.asarray(self.displacements)
        return np.array([np.interp(t, tt, d[:, k]) for k in range(3)])


@dataclass(frozen=True)
class CompoundPart:
    """Marks a BlockSpec as part ``part`` of one rigid compound block (a decomposed non-convex mesh).

    The specs of one compound are consecutive, parts 0 .. body.num_parts - 1, with the same position
    (the body's centroid), orientation, velocities, kind and density; each has geometry =
    body.parts[part] (in the body frame).  In the model every part carries the body's mass and
    inertia (of the original mesh) and the body's pose; a compound stage (kernels/dda/blocks.py
    compound_loads) sums the parts' loads, so every part integrates the same body motion."""

    body: CompoundBlock
    part: int


@dataclass
class BlockSpec:
    """One block as a scene gives it.

    geometry: body-frame convex polyhedron (centroid at origin).  position: centroid (m).
    orientation: quaternion (x, y, z, w).  density kg/m^3.  velocity m/s, angular_velocity rad/s (world).
    kind: "rigid" | "deformable" | "fixed" | "kinematic".  youngs_modulus Pa (None -> 10 GPa),
    poisson_ratio.  motion: KinematicMotion (kinematic only).  strain_damping_ratio: damping of the
    deformable block's strain modes.  compound: CompoundPart when this block is one convex part of a
    rigid compound (non-convex) block, else None. tank: a fixed block built from the scene's [tank] (or a box
    obstacle) so that the tank is solid to blocks (rockwave/build/rocks.py tank_specs); the water already has the
    tank's boundary particles there, so the coupling gives it no penalty faces and it gets no wall particles.
    """

    geometry: ConvexPolyhedron
    position: tuple = (0.0, 0.0, 0.0)
    orientation: object = (0.0, 0.0, 0.0, 1.0)
    density: float = 2600.0
    velocity: tuple = (0.0, 0.0, 0.0)
    angular_velocity: tuple = (0.0, 0.0, 0.0)
    kind: str = "rigid"
    youngs_modulus: float | None = None
    poisson_ratio: float = 0.25
    motion: KinematicMotion | None = None
    material: ContactMaterial = field(default_factory=ContactMaterial)
    name: str = ""
    strain_damping_ratio: float = 0.05
    compound: CompoundPart | None = None
    tank: bool = False


def _compound_ranges(specs: list) -> tuple[np.ndarray, list]:
    """body_of (N,): the index of each block's body (its first part; a convex block is its own body)
    and the (first part, part count) ranges of the compound bodies; checks CompoundPart's contract."""
    n = len(specs)
    body_of = np.arange(n)
    ranges = []
    b = 0
    while b < n:
        c = specs[b].compound
        if c is None:
            b += 1
            continue
        body = c.body
        name = specs[b].name or body.name
        if c.part != 0 or b + body.num_parts > n:
            raise ValueError(f"block '{name}': compound parts must be listed in order, parts 0 .. {body.num_parts - 1}")
        for k in range(body.num_parts):
            s = specs[b + k]
            if s.compound is None or s.compound.body is not body or s.compound.part != k or s.geometry is not body.parts[k]:
                raise ValueError(f"block '{name}': compound parts must be listed in order, parts 0 .. {body.num_parts - 1}")
            if s.kind == "deformable":
                raise ValueError(f"block '{name}': a compound (non-convex) block must be rigid, fixed or kinematic, "
                                 f"not deformable")
            for attr in ("position", "orientation", "velocity", "angular_velocity", "kind", "density"):
                if np.any(np.asarray(getattr(s, attr), dtype=object) != np.asarray(getattr(specs[b], attr), dtype=object)):
                    raise ValueError(f"block '{name}': the parts of a compound block must share its {attr}")
        body_of[b: b + body.num_parts] = b
        ranges.append((b, body.num_parts))
        b += body.num_parts
    return body_of, ranges


def _quat(q) -> np.ndarray:
    a = np.asarray([float(c) for c in q], dtype=float)
    n = np.linalg.norm(a)
    if a.shape != (4,) or n == 0:
        raise ValueError(f"orientation must be a non-zero quaternion (x, y, z, w), got {q}")
    return a / n


def _strain_mass(S: np.ndarray) -> np.ndarray:
    """Generalised mass of the 6 strain DOFs: M_ab = tr(G_a^T G_b S), u = G_a X, S = rho int X X^T."""
    G = np.zeros((6, 3, 3))
    G[0][0, 0] = G[1][1, 1] = G[2][2, 2] = 1.0
    G[3][1, 2] = G[3][2, 1] = 0.5  # gamma_yz
    G[4][0, 2] = G[4][2, 0] = 0.5  # gamma_zx
    G[5][0, 1] = G[5][1, 0] = 0.5  # gamma_xy
    return np.einsum("aji,bjk,ki->ab", G, G, S)


def _elastic_D(E: float, nu: float) -> np.ndarray:
    """3D isotropic elasticity matrix for (eps_x, eps_y, eps_z, gamma_yz, gamma_zx, gamma_xy)."""
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    G = E / (2 * (1 + nu))
    D = np.zeros((6, 6))
    D[:3, :3] = lam
    D[0, 0] = D[1, 1] = D[2, 2] = lam + 2 * G
    D[3, 3] = D[4, 4] = D[5, 5] = G
    return D


def _table_slots(pairs: int) -> int:
    """Contact-history slots for ``pairs`` candidate pairs: 4/3 x (linear probing at load <= 3/4: ~2.5 probes per
    hit, ~8.5 per miss, Knuth's estimates) + 64."""
    return 4 * pairs // 3 + 64


class BlockModel:
    """Static description of all blocks, as device arrays (V vertices, F faces, H half-edges, N blocks, C compound
    bodies). Device arrays are wp.array on ``device``; "int" is int32, "float" float32.

    Attributes:
        device: the Warp device. specs: list[BlockSpec] (N), as given. names: list[str] (N), block names.
        gravity: (3,) tuple of float [m/s^2]. num_blocks: N. num_vertices: V. num_half_edges: H.
        num_compounds: C, the rigid compound (non-convex) bodies.
        np: host copies (numpy, float64 unless said): kinds (N, int32), mass (N) [kg], inertia (N, 3, 3) [kg m^2],
            size (N) bounding diameter [m], radius (N) bounding radius [m], k_n, k_s (N) [N/m per point], zeta (N),
            tan_phi (N), body_verts (V, 3) [m], vert_start, vert_count (N), motion_type (N, int32).
        movable: bool (N): rigid or deformable (fixed and kinematic blocks are not integrated).
        body_of: int64 (N): the first part of each block's body (itself for a convex block). lead: bool (N): the
            blocks that stand for a body (momentum, energy).
        base_position: float64 (N, 3): the specs' centroids [m]. d50: median bounding diameter D50 [m].
        strain_omega: float64 (N): highest strain-mode frequency of a deformable block [rad/s] (0 for the rest).
        strain_mass: float64 (N, 6, 6): generalised strain mass of a deformable block [kg m^2].
        max_vertex_pair: the most vertices of any two blocks.
        planar: 2D scene: blocks keep z = planar_z (the specs' z) and turn about z only.

        Geometry (global indices into the concatenated arrays):
        body_verts: vec3 (V): vertices in the body frame [m]. vert_block: int (V): each vertex's block.
        vert_start, vert_count: int (N). face_start, face_count: int (N). face_he: int (F): a half-edge of each face.
        vertex_out_he: int (V): a half-edge leaving each vertex. he_vertex, he_next, he_twin: int (H) (no he_prev on
            the device: the walk around a vertex is h -> he_next[he_twin[h]]).
        he_start, he_count: int (N), he_walk: int (H): half-edges in walk order (half_edge_walk; one-entry
            placeholders until a solver has pairs of big blocks).
        block_body: int (N): body_of on the device. compound_start, compound_count: int (C): the bodies' parts
            (only with compounds).

        Per block:
        kinds: int (N): 0 rigid, 1 deformable, 2 fixed, 3 kinematic. mass: float (N) [kg]. inv_mass: float (N)
            [1/kg] (0 for fixed and kinematic). inertia_body, inv_inertia_body: mat33 (N) [kg m^2], [1/(kg m^2)],
            body frame. block_size: float (N): bounding diameter [m].
        k_n, k_s: float (N): contact stiffness [N/m per point]. tan_phi: float (N). cohesion, tensile: float (N) [Pa].
            zeta: float (N): contact damping ratio.
        strain_minv, strain_k: spatial_matrix (N, or 1 without deformable blocks): inverse strain mass [1/(kg m^2)]
            and strain stiffness [N m]. strain_damp: float (N): strain damping 2 zeta omega [1/s].
        base_x: vec3 (N): base positions [m] (kinematic motion is added to them). motion_type: int (N): 0 none,
            1 sine, 2 table. motion_amp: vec3 (N) [m]. motion_freq: float (N) [Hz]. motion_phase: float (N) [rad].
        table_start, table_count: int (N): each kinematic block's rows of table_t: float (rows) [s] and table_x: vec3
            (rows) [m].
        planar_z: float (N): the fixed z of each block [m] (planar only; else None).

        Kernel argument groups (kernels/dda/blocks.py structs over the arrays above): topology, props, material,
        motion.
    """

    def __init__(
        self,
        specs: list,
        device=None,
        gravity=(0.0, 0.0, -9.81),
        check_overlap: bool = True,
        overlap_tol: float | None = None,
        planar: bool = False,
    ):
        if not specs:
            raise ValueError("BlockModel needs at least one block")
        self.device = wp.get_device(device)
        self.specs = list(specs)
        self.gravity = tuple(float(g) for g in gravity)
        n = len(specs)
        self.num_blocks = n
        self.names = []
        verts, vblock, vstart, vcount = [], [], [], []
        fstart, fcount, face_he, vout = [], [], [], []
        hv, hn, ht = [], [], []
        kinds = np.zeros(n, np.int32)
        mass = np.zeros(n)
        inertia = np.zeros((n, 3, 3))
        size = np.zeros(n)
        radius = np.zeros(n)
        kn = np.zeros(n)
        ks = np.zeros(n)
        tphi = np.zeros(n)
        coh = np.zeros(n)
        ten = np.zeros(n)
        zeta = np.zeros(n)
        sminv = np.zeros((n, 6, 6))
        sk = np.zeros((n, 6, 6))
        sdamp = np.zeros(n)
        self.strain_omega = np.zeros(n)
        self.strain_mass = np.zeros((n, 6, 6))
        mtype = np.zeros(n, np.int32)
        mamp = np.zeros((n, 3))
        mfreq = np.zeros(n)
        mphase = np.zeros(n)
        tstart = np.zeros(n, np.int32)
        tcount = np.zeros(n, np.int32)
        tab_t, tab_x = [], []
        nv = nf = nh = 0
        body_of, compounds = _compound_ranges(self.specs)
        for b, s in enumerate(specs):
            g = s.geometry
            if not isinstance(g, ConvexPolyhedron):
                raise TypeError(f"block {b}: geometry must be a ConvexPolyhedron")
            name = s.name or g.name or f"block{b}"
            self.names.append(name)
            if s.kind not in KINDS:
                raise ValueError(f"block '{name}': kind must be one of {sorted(KINDS)}, got '{s.kind}'")
            if not s.density > 0:
                raise ValueError(f"block '{name}': density must be > 0")
            kinds[b] = KINDS[s.kind]
            verts.append(g.vertices)
            vblock.append(np.full(g.num_vertices, b))
            vstart.append(nv)
            vcount.append(g.num_vertices)
            fstart.append(nf)
            fcount.append(g.num_faces)
            face_he.append(g.face_he + nh)
            vout.append(g.vertex_out_he + nh)
            hv.append(g.he_vertex + nv)
            hn.append(g.he_next + nh)
            ht.append(g.he_twin + nh)
            nv += g.num_vertices
            nf += g.num_faces
            nh += g.num_half_edges
            mass[b] = g.mass(s.density)
            inertia[b] = g.inertia(s.density)
            size[b] = 2.0 * g.bounding_radius
            radius[b] = g.bounding_radius
            body = s.compound.body if s.compound is not None else None
            if body is not None:  # a part: the body's mass properties (the original mesh's) and extent
                mass[b] = body.mass(s.density)
                inertia[b] = body.inertia(s.density)
                size[b] = 2.0 * body.part_radius[s.compound.part]
                radius[b] = body.bounding_radius
            E = DEFAULT_YOUNGS_MODULUS if s.youngs_modulus is None else float(s.youngs_modulus)
            nu = float(s.poisson_ratio)
            if not (E > 0 and -1.0 < nu < 0.5):
                raise ValueError(f"block '{name}': need youngs_modulus > 0 and -1 < poisson_ratio < 0.5")
            m = s.material
            L = g.size if body is None else body.size
            kn[b] = PENALTY_FACTOR * E * L if m.normal_stiffness is None else float(m.normal_stiffness)
            ks[b] = kn[b] / (2.0 * (1.0 + nu)) if m.shear_stiffness is None else float(m.shear_stiffness)
            if kn[b] <= 0 or ks[b] < 0:
                raise ValueError(f"block '{name}': contact stiffness must be positive")
            tphi[b] = math.tan(math.radians(m.friction_angle_deg))
            coh[b] = m.cohesion_pa
            ten[b] = m.tensile_strength_pa
            zeta[b] = m.resolved_damping_ratio()
            if s.kind == "deformable":
                I = inertia[b]
                S = 0.5 * np.trace(I) * np.eye(3) - I
                M = _strain_mass(S)
                Kst = g.volume * _elastic_D(E, nu)
                # generalised eigenvalues of (V D, M_e): real and positive for SPD matrices
                om2 = np.real(np.linalg.eigvals(np.linalg.solve(M, Kst)))
                self.strain_omega[b] = math.sqrt(max(om2.max(), 0.0))
                self.strain_mass[b] = M
                sminv[b] = np.linalg.inv(M)
                sk[b] = Kst
                sdamp[b] = 2.0 * s.strain_damping_ratio * self.strain_omega[b]
            if s.kind == "kinematic":
                mo = s.motion
                if mo is None:
                    raise ValueError(f"block '{name}': kinematic block needs a motion (KinematicMotion)")
                if mo.kind == "sine":
                    mtype[b] = 1
                    mamp[b] = mo.amplitude
                    mfreq[b] = mo.frequency_hz
                    mphase[b] = mo.phase_rad
                elif mo.kind == "table":
                    mtype[b] = 2
                    tstart[b] = len(tab_t)
                    tcount[b] = len(mo.times)
                    tab_t.extend(mo.times)
                    tab_x.extend(mo.displacements)
                else:
                    raise ValueError(f"block '{name}': motion kind must be 'sine' or 'table'")
        movable = (kinds == 0) | (kinds == 1)
        inv_mass = np.where(movable, 1.0 / mass, 0.0)
        inv_inertia = np.linalg.inv(inertia)
        self.np = dict(
            kinds=kinds, mass=mass, inertia=inertia, size=size, radius=radius, k_n=kn, k_s=ks, zeta=zeta,
            tan_phi=tphi, body_verts=np.concatenate(verts), vert_start=np.asarray(vstart), vert_count=np.asarray(vcount),
            motion_type=mtype,
        )
        self.movable = movable
        # compound blocks (CompoundPart): body_of[b] = first part of b's body (b for a convex block);
        # lead: the blocks that stand for a body (momentum, energy); compound_start/count: the bodies' parts
        self.body_of = body_of
        self.lead = body_of == np.arange(n)
        self.num_compounds = len(compounds)
        d = self.device
        f32 = wp.float32

        def arr(a, dtype):
            return wp.array(np.ascontiguousarray(a), dtype=dtype, device=d)

        self.body_verts = arr(np.concatenate(verts).astype(np.float32), wp.vec3)
        self.vert_block = arr(np.concatenate(vblock).astype(np.int32), int)
        self.vert_start = arr(np.asarray(vstart, np.int32), int)
        self.vert_count = arr(np.asarray(vcount, np.int32), int)
        self.face_start = arr(np.asarray(fstart, np.int32), int)
        self.face_count = arr(np.asarray(fcount, np.int32), int)
        self.face_he = arr(np.concatenate(face_he).astype(np.int32), int)
        self.vertex_out_he = arr(np.concatenate(vout).astype(np.int32), int)
        self.he_vertex = arr(np.concatenate(hv).astype(np.int32), int)
        self.he_next = arr(np.concatenate(hn).astype(np.int32), int)
        self.he_twin = arr(np.concatenate(ht).astype(np.int32), int)
        self.num_vertices = nv
        self.num_half_edges = nh
        self.max_vertex_pair = int(np.sum(np.sort(np.asarray(vcount))[-2:]))  # most vertices of any two blocks
        # half-edges in walk order: built by half_edge_walk() when a solver has pairs of big blocks
        self.he_start = self.he_count = self.he_walk = wp.zeros(1, dtype=int, device=d)
        self.block_body = arr(body_of.astype(np.int32), int)
        if compounds:
            self.compound_start = arr(np.asarray([c[0] for c in compounds], np.int32), int)
            self.compound_count = arr(np.asarray([c[1] for c in compounds], np.int32), int)
        self.kinds = arr(kinds, int)
        self.mass = arr(mass.astype(np.float32), f32)
        self.inv_mass = arr(inv_mass.astype(np.float32), f32)
        self.inertia_body = arr(inertia.astype(np.float32), wp.mat33)
        self.inv_inertia_body = arr(inv_inertia.astype(np.float32), wp.mat33)
        self.block_size = arr(size.astype(np.float32), f32)
        self.k_n = arr(kn.astype(np.float32), f32)
        self.k_s = arr(ks.astype(np.float32), f32)
        self.tan_phi = arr(tphi.astype(np.float32), f32)
        self.cohesion = arr(coh.astype(np.float32), f32)
        self.tensile = arr(ten.astype(np.float32), f32)
        self.zeta = arr(zeta.astype(np.float32), f32)
        # Shi's strain matrices are read for deformable blocks only (integrate_blocks): one entry when there are
        # none (288 bytes per block less in a rigid rock mass)
        if not np.any(kinds == int(dda_k.KIND_DEFORMABLE)):
            sminv, sk = sminv[:1], sk[:1]
        self.strain_minv = arr(sminv.astype(np.float32), wp.spatial_matrix)
        self.strain_k = arr(sk.astype(np.float32), wp.spatial_matrix)
        self.strain_damp = arr(sdamp.astype(np.float32), f32)
        self.motion_type = arr(mtype, int)
        self.motion_amp = arr(mamp.astype(np.float32), wp.vec3)
        self.motion_freq = arr(mfreq.astype(np.float32), f32)
        self.motion_phase = arr(mphase.astype(np.float32), f32)
        self.table_start = arr(tstart, int)
        self.table_count = arr(tcount, int)
        self.table_t = arr(np.asarray(tab_t if tab_t else [0.0], np.float32), f32)
        self.table_x = arr(np.asarray(tab_x if tab_x else [[0.0, 0.0, 0.0]], np.float32).reshape(-1, 3), wp.vec3)
        self.base_position = np.array([np.asarray(s.position, float).reshape(3) for s in specs])
        self.base_x = arr(self.base_position.astype(np.float32), wp.vec3)
        self.d50 = float(np.median(size))
        # 2D scenes: blocks are prisms extruded along z that move in their x-y plane (z fixed at the
        # spec's, rotation about z only); BlockSolver.step applies it after each integration
        self.planar = bool(planar)
        self.planar_z = arr(self.base_position[:, 2].astype(np.float32), f32) if self.planar else None
        # kernel argument groups (kernels/dda/blocks.py), built once
        self.topology = dda_k.BlockTopology()
        for name in ("vert_start", "vert_count", "face_start", "face_count", "face_he", "vertex_out_he", "he_vertex",
                     "he_next", "he_twin", "block_size", "he_start", "he_count", "he_walk"):
            setattr(self.topology, name, getattr(self, name))
        self.props = dda_k.BlockProps()
        for name in ("kinds", "inv_mass", "inertia_body", "inv_inertia_body", "strain_minv", "strain_k", "strain_damp"):
            setattr(self.props, name, getattr(self, name))
        self.material = dda_k.BlockMaterial()
        for name in ("k_n", "k_s", "tan_phi", "cohesion", "tensile", "zeta"):
            setattr(self.material, name, getattr(self, name))
        self.motion = dda_k.BlockMotion()
        for name in ("base_x", "motion_type", "motion_amp", "motion_freq", "motion_phase", "table_start", "table_count",
                     "table_t", "table_x"):
            setattr(self.motion, name, getattr(self, name))
        if check_overlap:
            check_initial_overlap(self, tol=overlap_tol)

    def half_edge_walk(self) -> None:
        """Each block's half-edges in walk order (vertex by vertex, around each vertex as narrow_phase
        walks them; topology.he_walk / he_start / he_count): the work items of narrow_phase_coop
        (kernels/dda/blocks.py). Built once, on the first solver that has pairs of big blocks."""
        if self.he_walk.shape[0] > 1 or self.num_half_edges <= 1:
            return
        d = self.device
        walk_count = wp.zeros(self.num_vertices, dtype=int, device=d)
        wp.launch(dda_k.vertex_walk_count, dim=self.num_vertices, inputs=[self.vertex_out_he, self.he_next, self.he_twin, walk_count],
                  device=d)
        off = np.concatenate([[0], np.cumsum(walk_count.numpy().astype(np.int64))])
        vs = self.np["vert_start"].astype(np.int64)
        ve = vs + self.np["vert_count"].astype(np.int64)
        self.he_start = wp.array(off[vs].astype(np.int32), dtype=int, device=d)
        self.he_count = wp.array((off[ve] - off[vs]).astype(np.int32), dtype=int, device=d)
        self.he_walk = wp.zeros(int(off[-1]), dtype=int, device=d)
        wp.launch(dda_k.vertex_walk_fill, dim=self.num_vertices,
                  inputs=[self.vertex_out_he, self.he_next, self.he_twin, wp.array(off[:-1].astype(np.int32), dtype=int, device=d),
                          self.he_walk], device=d)
        self.topology.he_start, self.topology.he_count, self.topology.he_walk = self.he_start, self.he_count, self.he_walk

    def initial_poses(self):
        """(positions (N,3), quaternions (N,4) xyzw) at t = 0, kinematic motion applied."""
        pos = self.base_position.copy()
        quats = np.array([_quat(s.orientation) for s in self.specs])
        for b, s in enumerate(self.specs):
            if s.kind == "kinematic":
                pos[b] = pos[b] + s.motion.displacement(0.0)
        return pos, quats

    def state(self) -> "BlockState":
        """Allocate a BlockState at the specs' initial conditions."""
        return BlockState(self)


def _table_view(t: dict) -> "dda_k.ContactTable":
    v = dda_k.ContactTable()
    for name, a in t.items():
        setattr(v, name, a)
    return v


class BlockState:
    """Time-varying block data (device arrays on the model's device, N blocks, V vertices; "float" is float32).

    Attributes:
        model: the BlockModel.
        x: vec3 (N): centroids in the world, float32 part [m]; the part below its resolution is in x_lo: vec3 (N) [m]
            (the centroid is x + x_lo, carried by a compensated sum in integrate_blocks; positions_numpy).
        q: quat (N): orientation body -> world (x, y, z, w), float32 part; the part below its resolution is in
            q_lo: quat (N) (the orientation is q + q_lo, integrate_blocks). v: vec3 (N) [m/s]. w: vec3 (N): spin, world frame [rad/s].
            v_step: vec3 (N) [m/s]: a kinematic block's displacement over its last step / dt (its contact springs
            integrate it; v is its prescribed velocity); unused for other blocks.
        strain, strain_rate: spatial_vector (N): eps_x, eps_y, eps_z, gamma_yz, gamma_zx, gamma_xy, body frame [-],
            [1/s] (zero for non-deformable blocks).
        ext_force, ext_torque: vec3 (N): external loads [N], [N m] about the centroid, world frame: other modules
            (the coupling) add here atomically before a step, the solver zeroes them after use.
        force, torque: vec3 (N) [N], [N m], strain_force: spatial_vector (N) [N m]: contact accumulators of a step.
        contact_count: int (N): contact points of the last step.
        damp_c: sym6 (N) (upper triangle), damp_b: spatial_vector (N): the implicit contact dashpots (kernels/dda/blocks.py).
        world_verts_arm: vec3 (V): each vertex relative to its block's float32 centroid x [m] (x_lo + R (X + E X)),
            world_verts_arm_lo: its part below float32's spacing (kernels/dda/blocks.py vertex_arm).
        x_ref, x_lo_ref: vec3 (N) [m], q_ref, q_lo_ref: quat (N) (q_ref 0: none yet), strain_ref: spatial_vector (N, or 1 without
            deformable blocks): the poses of the history table's planes (the last narrow phase).
        motion_dx: vec3 (N) [m], motion_rho: float (N) [m]: the motion since the reference poses: every world vertex
            moved by motion_dx + dev with |dev| <= motion_rho (kernels/dda/blocks.py pose_motion).
        time: simulated time [s].
        tables: two dicts of arrays, the contact-history tables (swapped each step by swap_tables), table_cap pair
            slots and point_cap contact points each.
        Kernel views (kernels/dda/blocks.py structs): bodies (x, q, v, w, strain, strain_rate, x_lo), verts (arm),
        loads (force ... damp_b), table_views (one per table, swapped with them).
    """

    def __init__(self, model: BlockModel):
        self.model = model
        d = model.device
        n = model.num_blocks
        pos, quats = model.initial_poses()
        vel = np.array([np.asarray(s.velocity, float).reshape(3) for s in model.specs])
        ang = np.array([np.asarray(s.angular_velocity, float).reshape(3) for s in model.specs])
        fixed = ~model.movable
        vel[fixed] = 0.0
        ang[fixed] = 0.0
        for b, s in enumerate(model.specs):
            if s.kind == "kinematic":
                mo = s.motion
                if mo.kind == "sine":
                    om = 2 * math.pi * mo.frequency_hz
                    vel[b] = np.asarray(mo.amplitude) * om * math.cos(mo.phase_rad)
                else:
                    vel[b] = 0.0
        self.x = wp.array(pos.astype(np.float32), dtype=wp.vec3, device=d)
        self.q = wp.array(quats.astype(np.float32), dtype=wp.quat, device=d)
        self.v = wp.array(vel.astype(np.float32), dtype=wp.vec3, device=d)
        self.w = wp.array(ang.astype(np.float32), dtype=wp.vec3, device=d)
        # a kinematic block's displacement over its last step / dt (integrate_blocks; the contact springs integrate it):
        # its prescribed velocity until it has moved
        self.v_step = wp.array(vel.astype(np.float32), dtype=wp.vec3, device=d)
        self.strain = wp.zeros(n, dtype=wp.spatial_vector, device=d)
        self.strain_rate = wp.zeros(n, dtype=wp.spatial_vector, device=d)
        # centroid = x + x_lo (kernels/dda/blocks.py two_sum): the specs' float64 poses to ~48 bits, so a scene placed
        # far from the world origin starts with the same contacts as at the origin (kinematic blocks follow
        # their float32 base position: BlockMotion.base_x)
        lo = pos - pos.astype(np.float32)
        lo[np.array([s.kind == "kinematic" for s in model.specs], dtype=bool)] = 0.0
        self.x_lo = wp.array(lo.astype(np.float32), dtype=wp.vec3, device=d)
        # orientation = q + q_lo likewise (integrate_blocks): the specs' float64 quaternions to ~48 bits
        self.q_lo = wp.array((quats - quats.astype(np.float32)).astype(np.float32), dtype=wp.quat, device=d)
        self.force = wp.zeros(n, dtype=wp.vec3, device=d)
        self.torque = wp.zeros(n, dtype=wp.vec3, device=d)
        self.strain_force = wp.zeros(n, dtype=wp.spatial_vector, device=d)
        self.ext_force = wp.zeros(n, dtype=wp.vec3, device=d)
        self.ext_torque = wp.zeros(n, dtype=wp.vec3, device=d)
        self.contact_count = wp.zeros(n, dtype=int, device=d)
        self.damp_c = wp.zeros(n, dtype=dda_k.sym6, device=d)  # implicit contact dashpots (kernels/dda/blocks.py; upper triangle)
        self.damp_b = wp.zeros(n, dtype=wp.spatial_vector, device=d)
        # each vertex relative to its block's float32 centroid x: x_lo + R (X + E X) (the narrow phase's pair frame)
        self.world_verts_arm = wp.zeros(model.num_vertices, dtype=wp.vec3, device=d)
        self.world_verts_arm_lo = wp.zeros(model.num_vertices, dtype=wp.vec3, device=d)  # its part below float32's spacing
        # poses of the history table's planes (last narrow phase: x, q, x_lo and, of deformable blocks, strain;
        # q_ref = 0: none yet) and the motion since (pose_motion)
        self.x_ref = wp.zeros(n, dtype=wp.vec3, device=d)
        self.q_ref = wp.zeros(n, dtype=wp.quat, device=d)
        self.q_lo_ref = wp.zeros(n, dtype=wp.quat, device=d)
        self.x_lo_ref = wp.zeros(n, dtype=wp.vec3, device=d)
        self.strain_ref = wp.zeros(n if np.any(model.np["kinds"] == int(dda_k.KIND_DEFORMABLE)) else 1, dtype=wp.spatial_vector,
                                   device=d)
        self.motion_dx = wp.zeros(n, dtype=wp.vec3, device=d)
        self.motion_rho = wp.zeros(n, dtype=wp.float32, device=d)
        self.time = 0.0
        # kernel argument groups (kernels/dda/blocks.py) over the arrays above, built once (the arrays are
        # only ever assigned in place, e.g. by a checkpoint restore)
        self.bodies = dda_k.BlockBodies()
        for name in ("x", "q", "v", "w", "strain", "strain_rate", "x_lo", "q_lo", "v_step"):
            setattr(self.bodies, name, getattr(self, name))
        self.verts = dda_k.WorldVerts()
        self.verts.arm = self.world_verts_arm
        self.verts.arm_lo = self.world_verts_arm_lo
        self.loads = dda_k.BlockLoads()
        for name in ("force", "torque", "strain_force", "ext_force", "ext_torque", "contact_count", "damp_c", "damp_b"):
            setattr(self.loads, name, getattr(self, name))
        self.tables = [None, None]
        self.table_views = [None, None]  # dda_k.ContactTable over tables[0], tables[1] (swapped with them)
        # small to start with: BlockSolver grows both from the live pairs and contact points
        self.alloc_tables(_table_slots(n), 4 * n + 64)

    def alloc_tables(self, cap: int, point_cap: int | None = None):
        """(Re)allocate both contact-history tables: ``cap`` pair slots (BlockSolver keeps it >= 4/3 x the
        candidate pairs: _table_slots) and ``point_cap`` contact points each (None: as now). tables[0]'s
        history is kept (rehashed). Sized from the live pairs and points, not a capacity per block."""
        d = self.model.device
        if point_cap is None:
            point_cap = self.point_cap
        old = self.tables[0]
        if old is not None:
            point_cap = max(int(point_cap), int(old["pcount"].numpy()[0]))

        # the contact points' positions (each table its own: contact_forces finds a point whose feature key changed
        # by its position in the previous step's table, carry_contacts moves the previous step's points)
        def make():
            return dict(
                keys=wp.full(cap, -1, dtype=wp.int64, device=d),
                normal=wp.zeros(cap, dtype=wp.vec3, device=d),
                gapb=wp.zeros(cap, dtype=wp.float32, device=d),  # gap (or lower bound) along normal
                nc=wp.zeros(cap, dtype=int, device=d),
                pstart=wp.zeros(cap, dtype=int, device=d),  # first point in the pool
                pcount=wp.zeros(1, dtype=int, device=d),  # pool entries taken this step
                ckey=wp.zeros(point_cap, dtype=wp.vec2i, device=d),
                shear=wp.zeros(point_cap, dtype=wp.vec3, device=d),
                pos=wp.zeros(point_cap, dtype=wp.vec3, device=d),
                depth=wp.zeros(point_cap, dtype=wp.float32, device=d),
                fn=wp.zeros(point_cap, dtype=wp.float32, device=d),
                vimp=wp.zeros(point_cap, dtype=wp.float32, device=d),  # closing speed at first touch
                fcap=wp.zeros(point_cap, dtype=wp.float32, device=d),  # Coulomb cap of the step
            )

        self.tables = [make(), make()]
        self.table_views = [_table_view(t) for t in self.tables]
        self.table_cap = cap
        self.point_cap = point_cap
        if old is not None:  # keep the contact history (rehash into the larger table)
            wp.launch(dda_k.rehash_table, dim=old["keys"].shape[0], inputs=[_table_view(old), self.table_views[0]], device=d)

    def swap_tables(self) -> None:
        """tables[0] <-> tables[1] (after a narrow phase: tables[0] holds this step's history)."""
        self.tables = [self.tables[1], self.tables[0]]
        self.table_views = [self.table_views[1], self.table_views[0]]

    # ---- read-back helpers (host sync) ----
    def positions_numpy(self) -> np.ndarray:
        """Centroids x + x_lo [m] (float64: the compensated sum's ~48 bits)."""
        return self.x.numpy().astype(np.float64) + self.x_lo.numpy()

    def orientations_numpy(self) -> np.ndarray:
        return self.q.numpy().astype(np.float64)

    def velocities_numpy(self) -> np.ndarray:
        return self.v.numpy().astype(np.float64)

    def angular_velocities_numpy(self) -> np.ndarray:
        return self.w.numpy().astype(np.float64)

    def strains_numpy(self) -> np.ndarray:
        return self.strain.numpy().astype(np.float64)

    def contact_counts(self) -> np.ndarray:
        """Contact points per block found in the last step."""
        return self.contact_count.numpy().copy()

    def world_vertices(self) -> list:
        """World-space vertices per block (list of (V_b, 3) arrays) at the current pose and strain."""
        m = self.model
        wp.launch(dda_k.block_world_vertices, dim=m.num_vertices,
                  inputs=[m.body_verts, m.vert_block, self.bodies, m.kinds, self.verts], device=m.device)
        wv = self.x.numpy().astype(np.float64)[m.vert_block.numpy()] + self.world_verts_arm.numpy()
        s, c = m.np["vert_start"], m.np["vert_count"]
        return [wv[s[b]: s[b] + c[b]] for b in range(m.num_blocks)]

    def linear_momentum(self) -> np.ndarray:
        """Sum of m v over movable blocks (kg m/s)."""
        m = self.model
        mv = m.np["mass"][:, None] * self.velocities_numpy()
        return mv[m.movable & m.lead].sum(axis=0)

    def kinetic_energy(self) -> float:
        """Translational + rotational (+ strain-rate) kinetic energy of movable blocks (J)."""
        m = self.model
        v = self.velocities_numpy()
        w = self.angular_velocities_numpy()
        q = self.orientations_numpy()
        sr = self.strain_rate.numpy().astype(np.float64)
        e = 0.0
        for b in np.nonzero(m.movable & m.lead)[0]:
            R = quat_to_matrix(q[b])
            Iw = R @ m.np["inertia"][b] @ R.T
            e += 0.5 * m.np["mass"][b] * v[b] @ v[b] + 0.5 * w[b] @ Iw @ w[b]
            if m.np["kinds"][b] == 1:
                e += 0.5 * sr[b] @ m.strain_mass[b] @ sr[b]
        return float(e)


def _sat_overlap(va: np.ndarray, ga: ConvexPolyhedron, Ra, vb: np.ndarray, gb: ConvexPolyhedron, Rb) -> float:
    """Penetration depth of two convex polyhedra by the separating-axis test (<= 0: apart)."""
    axes = [ga.face_normals @ Ra.T, gb.face_normals @ Rb.T]
    ea = ga.edges()
    eb = gb.edges()
    da = va[ea[:, 1]] - va[ea[:, 0]]
    db = vb[eb[:, 1]] - vb[eb[:, 0]]
    cr = np.cross(da[:, None, :], db[None, :, :]).reshape(-1, 3)
    ln = np.linalg.norm(cr, axis=1)
    keep = ln > 1e-9 * max(1.0, ln.max(initial=0.0))
    axes.append(cr[keep] / ln[keep, None])
    ax = np.concatenate(axes)
    pa = va @ ax.T
    pb = vb @ ax.T
    ov = np.minimum(pa.max(0) - pb.min(0), pb.max(0) - pa.min(0))
    return float(ov.min())


def _sweep_pairs(pos: np.ndarray, rad: np.ndarray):
    """Pairs whose bounding spheres overlap (sort and sweep along x)."""
    order = np.argsort(pos[:, 0])
    xs = pos[order, 0]
    rmax = float(rad.max())
    for a, i in enumerate(order):
        end = np.searchsorted(xs, xs[a] + rad[i] + rmax, side="right")
        for j in order[a + 1: end]:
            if np.linalg.norm(pos[i] - pos[j]) <= rad[i] + rad[j]:
                yield (int(min(i, j)), int(max(i, j)))


def check_initial_overlap(model: BlockModel, positions=None, quats=None, tol: float | None = None):
    """Raise BlockOverlapError naming the first pair (with a movable block) that overlaps by more than tol.

    tol defaults to 1e-3 x the smallest block size.  Pairs of two fixed/kinematic blocks are skipped
    (they never interact).  Exact separating-axis test on the host (numpy).
    """
    if positions is None or quats is None:
        positions, quats = model.initial_poses()
    sizes = model.np["size"]
    if tol is None:
        tol = 1e-3 * float(sizes.min())
    rad = model.np["radius"]
    n = model.num_blocks
    if n < 2:
        return
    Rs = [quat_to_matrix(q) for q in quats]
    worst = None
    for i, j in _sweep_pairs(positions, rad):
        if not (model.movable[i] or model.movable[j]) or model.body_of[i] == model.body_of[j]:
            continue
        gi, gj = model.specs[i].geometry, model.specs[j].geometry
        vi = gi.vertices @ Rs[i].T + positions[i]
        vj = gj.vertices @ Rs[j].T + positions[j]
        depth = _sat_overlap(vi, gi, Rs[i], vj, gj, Rs[j])
        if depth > tol and (worst is None or depth > worst[2]):
            worst = (i, j, depth)
    if worst is not None:
        i, j, depth = worst
        raise BlockOverlapError(
            f"blocks '{model.names[i]}' (#{i}) and '{model.names[j]}' (#{j}) overlap by {depth:.6g} m at the start "
            f"(tolerance {tol:.3g} m); move them apart"
        )


def check_initial_overlap_on_device(solver: "BlockSolver", state: "BlockState", tol: float | None = None):
    """The same check as check_initial_overlap for large block sets: the device broad phase and FCP
    narrow phase (validated against the exact separating-axis test in the tests) give each candidate
    pair's gap; a gap below -tol is an overlap. O(n) instead of the host test's per-pair numpy work."""
    model = solver.model
    if tol is None:
        tol = 1e-3 * float(model.np["size"].min())
    solver.detect(state)
    n = solver.pair_count
    if n == 0:
        return
    gaps = solver.pair_gap.numpy()[:n]
    pairs = solver.pairs.numpy()[:n]
    mov = np.asarray(model.movable, dtype=bool)
    bad = (gaps < -tol) & (mov[pairs[:, 0]] | mov[pairs[:, 1]])
    if bad.any():
        k = int(np.argmin(np.where(bad, gaps, np.inf)))
        i, j = (int(c) for c in pairs[k])
        raise BlockOverlapError(
            f"blocks '{model.names[i]}' (#{i}) and '{model.names[j]}' (#{j}) overlap by {-gaps[k]:.6g} m at the start "
            f"(tolerance {tol:.3g} m); move them apart")


@dataclass(frozen=True)
class BlockOptions:
    """Knobs of the DDA block solver: ``BlockSolver(model, options=BlockOptions(...))``. The defaults are
    the shipped values (the scene format takes its defaults from here); rockwave/build/options.py block_options
    reads the ones a scene sets."""

    dt_safety: float = 0.5
    """stable_dt = dt_safety x critical_dt() [-] (scene: ``simulation.block_dt_safety``)."""

    cell_factor: float = 1.5
    """Broad-phase cell size S = cell_factor x median block bounding size D50 [-] (Nezami: 1.5)."""

    cell_size_m: float | None = None
    """Explicit broad-phase cell size S [m]; overrides cell_factor."""

    aabb_margin_m: float | None = None
    """Inflation of each block's AABB in the broad phase [m]; None: 0.05 D50."""

    contact_points_for_dt: int = 8
    """Contact points assumed on one block in the critical-step estimate (critical_dt) [-]."""

    large_block_cells: int = 27
    """A block whose AABB covers more broad-phase cells than this (per axis or in all) is "large": it
    is tested against every block instead of being hashed into cells [cells]."""

    sync_free_max_blocks: int = 64
    """Up to this many blocks the broad phase runs at capacities that cannot overflow and the step
    reads nothing back from the device; above it capacities grow on demand (one counter read per
    step) [blocks]."""

    substep_graphs: bool = True
    """CUDA: multi-rate sub-steps 1..n-1 of a fluid step (kept pair list, sync-free path) replay one captured
    graph per sub-step instead of ~12 launches from Python (each costs ~30-50 us of host time against a few
    us of GPU work for a coupled scene's few blocks). Same kernels, same order; ignored on the CPU."""

    fluid_step_graphs: bool = True
    """CUDA, with substep_graphs: all n sub-steps of a fluid step, the first one's broad and narrow phases
    included, replay one captured graph (sync-free path, the pair list not kept across fluid steps): one
    launch per fluid step. Same kernels, same order; ignored on the CPU."""

    sync_check_interval_steps: int = 200
    """Sync-free path: the overflow flags (a bug if set) are read back every this many steps [steps]."""

    keep_pairs: bool | None = None
    """Keep the pair list while every block's AABB grown by margin/2 stays inside the box of the last
    broad phase (kernels/dda/blocks.py aabbs_left_pair_boxes); None: on for the counter-read path (more than
    sync_free_max_blocks blocks), off for the sync-free one. False: a broad phase every step."""

    coop_min_vertices: int | None = None
    """A candidate pair whose two blocks have more vertices than this together goes to the cooperative
    narrow phase (kernels/dda/blocks_coop.py narrow_phase_coop: one thread block per pair, the work over
    vertices, faces and half-edge pairs spread over its lanes; the same result); smaller pairs: one
    thread each [-]. None: 32 on a GPU (or on the CPU with warp.config.enable_cpu_blocks), 0 (every pair) on
    a GPU for models of at most sync_free_max_blocks blocks, else off (Warp's CPU backend runs one lane per
    block, where the cooperative kernel is the serial loop plus overhead)."""

    hold_contacts: bool = True
    """Multi-rate sub-steps (substeps() with the pair list kept): sub-steps 1..n-1 of a fluid step carry the
    first sub-step's contacts (kernels/dda/blocks.py carry_contacts: points moved with the blocks, depths advanced
    by their approach) instead of running the narrow phase, while holds_contacts() finds every candidate pair
    out of contact farther apart than it can close before the next check (scene: ``simulation.block_contacts =
    "held"``, the default; "found": a narrow phase every sub-step)."""

    narrow_block_dim: int = 32
    """Threads per pair in the cooperative narrow phase (a GPU warp; Warp's CPU backend runs 1 unless
    warp.config.enable_cpu_blocks) [-]."""

    start: str = "settled"
    """How a scene's blocks start (scene: ``simulation.start``): "settled" (the default): BlockSolver.settle() first
    brings the blocks resting on another at t = 0 with no initial velocity to the equilibrium of their contact
    springs under gravity with friction locked, then with friction on under kinetic damping (contact points whose
    locked shear is above their Coulomb cap slip quasi-statically to it; a block that slides is detected and
    starts from the locked state), then releases them, so a stable block or rock mass starts at rest in a
    statically admissible state with its contacts loaded; blocks placed in the air or given a velocity start as placed; a resting block that
    does not stay where it was put with its friction locked (it topples or falls: settle_max_move) is held while
    the others settle and released as placed (settle_attempts); a scene that does not come to rest
    (settle_max_steps) starts plain, with a warning. "plain": every block
    as placed, contacts unloaded, gravity from t = 0 (a stable block slips while its normal springs load: a 10 m
    cube on 2.5e8 N/m per point at a 0.1 deg margin ends 13 mm beyond its elastic deflection). rockwave/build/builder.py runs it; a solver made in
    Python starts as its state is unless settle() is called (docs/physics.md 'The start of a block scene')."""

    settle_speed_ratio: float = 1.0e-3
    """Settled start: the blocks count as at rest when every settling block moves slower than this fraction of
    the resting-contact speed g / omega_max = g dt_crit / 2 (the speed a block reaches settling onto its
    springs): its residual motion is then ~this fraction of its deflection under its weight [-]."""

    settle_max_steps: int = 20000
    """Settled start: block steps allowed before the settling gives up (the scene then starts plain, with a
    warning: e.g. a block that topples even with its friction locked) [steps]."""

    settle_max_move: float = 0.01
    """Settled start: a settling block whose centroid moves more than this fraction of its size, plus twice its
    springs' sag under its own weight on one point (2 m g / k_n), from where it was placed is not at rest there
    even with its friction locked (it topples, or falls off an overhang): the settling stops and the scene starts
    plain, with a warning. A block sinking onto its springs moves m g / (n k_n), ~1e-3 of its size at the default
    stiffness (0.15% for a 10 m cube at 2.5e8 N/m per point), but 3% of a 20 m block's on a 1 MPa/m joint [-]."""

    settle_attempts: int = 4
    """Settled start: stages run at most. A stage in which blocks leave their place (settle_max_move) is undone,
    those blocks are held where they were put and released as placed (a loose block on a stable slope falls
    from where it was put while the rest starts settled), and the others settle again from the start; still
    moving after this many stages, the scene starts plain, with a warning [-]."""

    settle_contact_gap: float = 1.0e-4
    """Settled start: a block rests on another at t = 0 when their gap is below this fraction of the smaller
    one's size [-] (a block placed in the air, e.g. 1 mm above a slope, falls as placed)."""


# the settled start's friction stage (BlockSolver._relax_with_friction) is calm when every block is slower than this
# fraction of the locked stage's bound (settle_speed_ratio x g / omega_max): a block released at speed v creeps on by
# ~ v / omega of its slowest mode (its tilt on soft joints), 0.56 mm after t = 0 for a 20 m block at 1 MPa/m with the
# locked stage's bound, 0.010 mm with 1% of it; kinetic damping reaches it in ~1.8x the steps (docs/notes.md)
SETTLE_RELAX_TOL = 0.01


class BlockSolver:
    """Explicit DDA solver (the rockwave/base/solver.py contract): ``stable_dt(state)`` and
    ``step(state, ts)`` = broad phase, FCP narrow phase, contact forces, integration (and, for a planar
    model, the 2D constraint). Knobs: ``options`` (BlockOptions). It keeps buffer capacities, the
    kept pair list and diagnostics only; everything a step needs from the past is in the BlockState.
    """

    def __init__(self, model: BlockModel, device=None, options: BlockOptions | None = None):
        self.model = model
        self.options = opt = options if options is not None else BlockOptions()
        self.device = wp.get_device(device) if device is not None else model.device
        if self.device != model.device:
            raise ValueError(f"solver device {self.device} differs from model device {model.device}")
        if not 0.0 < opt.dt_safety <= 1.0:
            raise ValueError(f"BlockOptions.dt_safety must be in (0, 1], got {opt.dt_safety}")
        self.cell_size = float(opt.cell_size_m) if opt.cell_size_m else opt.cell_factor * model.d50
        self.margin = 0.05 * model.d50 if opt.aabb_margin_m is None else float(opt.aabb_margin_m)
        self.contact_points_for_dt = int(opt.contact_points_for_dt)
        self.g_mag = float(np.linalg.norm(model.gravity))  # |g| for the resting-contact speed (narrow_phase)
        self.large_cells = int(opt.large_block_cells)
        coop = opt.coop_min_vertices
        if coop is None:
            coop = 32 if (self.device.is_cuda or wp.config.enable_cpu_blocks) else 2**31 - 1
            if self.device.is_cuda and model.num_blocks <= opt.sync_free_max_blocks:
                # few blocks (a coupled scene): the few pairs leave the GPU idle but for their threads, so every
                # pair gets a thread block (measured, H100, submarine_slide_2d: one 14-vertex pair took 400 us
                # in one thread, and the coupled run went from 41 to 25 wall s per simulated s at 20 mm)
                coop = 0
        self.coop_min = int(coop)
        self.narrow_block_dim = int(opt.narrow_block_dim)
        if opt.start not in ("plain", "settled"):
            raise ValueError(f"BlockOptions.start must be 'plain' or 'settled', got {opt.start!r}")
        if self.coop_min < 0 or not 1 <= self.narrow_block_dim <= 1024:
            raise ValueError(f"BlockOptions: coop_min_vertices must be >= 0 (got {self.coop_min}) and narrow_block_dim "
                             f"in 1..1024 (got {self.narrow_block_dim})")
        self.has_big_pairs = model.max_vertex_pair > self.coop_min  # any pair for narrow_phase_coop?
        if self.has_big_pairs:
            model.half_edge_walk()
        self.coop_pairs = 0  # pairs the last narrow phase gave narrow_phase_coop (counter-read path; diagnostics)
        n = model.num_blocks
        d = self.device
        self.lo = wp.zeros(n, dtype=wp.vec3, device=d)
        self.hi = wp.zeros(n, dtype=wp.vec3, device=d)
        self.is_large = wp.zeros(n, dtype=int, device=d)
        self.counters = wp.zeros(5, dtype=int, device=d)
        self.grid = dda_k.BroadPhaseGrid()  # kernel argument groups, refreshed when a capacity grows
        self.grid.lo, self.grid.hi, self.grid.is_large = self.lo, self.hi, self.is_large
        self.grid.inv_s = 1.0 / self.cell_size
        self.grid.body = model.block_body  # parts of one compound block are never paired
        self.grid.large_cells = self.large_cells
        self.pair_list = dda_k.PairList()
        self.pair_list.counters = self.counters
        # Few blocks (the coupled scenes): capacities that cannot overflow (a block in more than
        # large_cells cells is "large"; each pair is emitted at most twice), so a step reads nothing
        # back and the GPU never waits for the host; the overflow flags are still checked every
        # sync_check_interval_steps steps. More blocks: capacities grow on demand (one counter read per step).
        self.sync_free = n <= opt.sync_free_max_blocks
        self.sync_check_interval = int(opt.sync_check_interval_steps)
        # no rigid or deformable block: nothing can collide (fixed and kinematic blocks do not act on each
        # other), so a step only moves the kinematic blocks and clears the coupling's forces
        kinds = model.np["kinds"]
        self.has_free_blocks = bool(np.any((kinds == int(dda_k.KIND_RIGID)) | (kinds == int(dda_k.KIND_DEFORMABLE))))
        if self.sync_free:
            self._alloc_large(n)
            self._alloc_entries(self.large_cells * n + 64)
            self._alloc_pairs(n * n + 64)
        else:
            self._alloc_large(min(n, 16))
            self._alloc_entries(8 * n + 64)
            self._alloc_pairs(8 * n + 64)
        self._pair_count = 0
        self._unchecked_steps = 0
        self._dt_crit = None
        # Many blocks (the counter-read path): the pair list is kept while every block's AABB grown by
        # margin/2 stays inside the box (grown by margin) of the last broad phase (kernels/dda/blocks.py
        # aabbs_left_pair_boxes; one flag read joins the step's counter read). Few blocks: every step.
        self._keep_pairs = (not self.sync_free) if opt.keep_pairs is None else bool(opt.keep_pairs)
        self.lo_bp = wp.zeros(n, dtype=wp.vec3, device=d)
        self.hi_bp = wp.zeros(n, dtype=wp.vec3, device=d)
        self._moved = wp.ones(1, dtype=int, device=d)
        # [t_next, dt, friction locked (settle(): 1)] of the current (sub-)step, read by contact_forces and
        # integrate_blocks on the device. Not the fluid's TimeStep.dt_array: in multi-rate stepping a block sub-step
        # is dt/n and its end time (kinematic blocks' prescribed motion) advances n times inside one fluid step, on the
        # device inside a captured graph
        self.block_clock = wp.zeros(3, dtype=float, device=d)
        # CUDA graphs of one multi-rate sub-step (substeps()), keyed by the contact tables' parity and the
        # addresses the graph baked in; None: not on this device (CPU, or graphs switched off)
        self._substep_graphs: dict | None = {} if (wp.get_device(d).is_cuda and opt.substep_graphs) else None
        self.graph_substeps = 0  # sub-steps replayed from a CUDA graph (diagnostics)
        self._step_graphs_ok = opt.fluid_step_graphs  # whole fluid steps of sub-steps as one graph (_fluid_step_graph)
        self.broad_phases = 0  # broad phases run (diagnostics)
        self.narrow_phases = 0  # narrow phases launched from the host (diagnostics; a graph replay is not counted)
        self.carried_substeps = 0  # sub-steps that carried their contacts (hold_contacts; launched or replayed)
        self.graph_captures = 0  # CUDA graphs captured (diagnostics)
        self.fluid_step_graphs = 0  # fluid steps whose sub-steps replayed one graph (_fluid_step_graph; diagnostics)
        self.point_regrows = 0  # narrow phases redone after the contact-point pool grew (diagnostics)
        self.contact_points = 0  # contact points of the last step (counter-read path; diagnostics)
        # the kernel argument groups of the contact forces and the integration: the model's, but for the settling
        # stage of the equilibrium start (settle()), which swaps in blocks held
        self.props, self.motion = model.props, model.motion
        self.start_report: dict = {"start": "plain"}  # what settle() did (run.json "block_start")
        # the paths, chosen once
        self._grid_pass = self._grid_pass_sync_free if self.sync_free else self._grid_pass_counted
        self._step_broad_phase = self._broad_phase_if_moved if self._keep_pairs else self._broad_phase_always
        self._contact_forces = self._contact_forces_all if self.has_free_blocks else self._no_contacts

    @property
    def keep_pairs(self) -> bool:
        """Whether the pair list is kept between broad phases (options.keep_pairs, resolved at construction)."""
        return self._keep_pairs

    @property
    def pair_count(self) -> int:
        """Candidate pairs of the last broad phase (a host read when the solver runs sync-free)."""
        if self.sync_free:
            return min(int(self.counters.numpy()[0]), self.pair_cap)
        return self._pair_count

    def _check_capacity_flags(self) -> None:
        flags = int(self.counters.numpy()[1])
        if flags:
            raise RuntimeError(f"DDA broad phase overflowed its fixed capacities (flags {flags}) with "
                               f"{self.model.num_blocks} blocks; this is a bug: please report the scene")

    # ---- capacity management ----
    def _alloc_large(self, cap):
        self.large_list = wp.zeros(max(1, cap), dtype=int, device=self.device)
        self.grid.large_list = self.large_list

    def _alloc_entries(self, cap):
        d = self.device
        self.entry_cap = cap
        # buckets >= entries (load <= 1; a shared bucket only costs the cell test in bp_pairs)
        self.nbuckets = next_pow2(cap)
        self.entry_block = wp.zeros(cap, dtype=int, device=d)
        self.entry_cell = wp.zeros(cap, dtype=wp.vec3i, device=d)
        self.bucket_count = wp.zeros(self.nbuckets, dtype=int, device=d)
        self.bucket_start = wp.zeros(self.nbuckets, dtype=int, device=d)
        g = self.grid
        g.nbuckets = self.nbuckets
        g.entry_block, g.entry_cell = self.entry_block, self.entry_cell
        g.bucket_count, g.bucket_start = self.bucket_count, self.bucket_start

    def _alloc_pairs(self, cap):
        d = self.device
        self.pair_cap = cap
        self.pairs = wp.zeros(cap, dtype=wp.vec2i, device=d)
        self.pair_gap = wp.zeros(cap, dtype=wp.float32, device=d)
        self.pair_slot = wp.zeros(cap, dtype=int, device=d)
        self.pair_oslot = wp.zeros(cap, dtype=int, device=d)
        self.active = wp.zeros(cap, dtype=int, device=d)  # pairs not certified separated (narrow_screen)
        self.active_big = wp.zeros(cap if self.has_big_pairs else 1, dtype=int, device=d)  # of them: narrow_phase_coop's
        pl = self.pair_list
        pl.pairs, pl.gap, pl.slot, pl.oslot, pl.active = self.pairs, self.pair_gap, self.pair_slot, self.pair_oslot, self.active
        pl.active_big = self.active_big

    # ---- time step limits ----
    def critical_dt(self) -> float:
        """The physical limit [s]: dt_crit = min over movable blocks of 2/omega (sqrt(1+zeta^2) - zeta),
        omega from translation sqrt(k_n n_c / m), rotation sqrt(k_n n_c r^2 / I_min) (r = bounding
        radius, n_c = options.contact_points_for_dt) and, for deformable blocks, the largest strain-mode
        frequency of M_e^-1 V D (~ 3.5 c / L). step() refuses a dt above it."""
        if self._dt_crit is None:
            self._dt_crit, self._dt_crit_block = self.critical_dt_of(np.nonzero(self.model.movable)[0])
        return self._dt_crit

    def critical_dt_of(self, blocks) -> tuple[float, tuple[int, str] | None]:
        """critical_dt() over the given block indices alone (inf where none is movable) and the block and mode that
        set it (a batch of scenarios: each scenario's own limit, rockwave/sim/batch.py)."""
        m = self.model
        nc = self.contact_points_for_dt
        best, which = math.inf, None
        for b in (int(i) for i in blocks if m.movable[int(i)]):
            kn = m.np["k_n"][b]
            z = m.np["zeta"][b]
            fac = math.sqrt(1.0 + z * z) - z
            mass = m.np["mass"][b]
            imin = float(np.linalg.eigvalsh(m.np["inertia"][b]).min())
            r = m.np["radius"][b]
            om = max(math.sqrt(kn * nc / mass), math.sqrt(kn * nc * r * r / imin))
            if 2.0 / om * fac < best:
                best, which = 2.0 / om * fac, (int(b), "contact")
            if m.np["kinds"][b] == 1:
                zs = m.specs[b].strain_damping_ratio
                ds = 2.0 / m.strain_omega[b] * (math.sqrt(1 + zs * zs) - zs)
                if ds < best:
                    best, which = ds, (int(b), "strain")
        return best, which

    def critical_block(self) -> tuple[int, str] | None:
        """(block index, 'contact' or 'strain'): the block and mode that set critical_dt() (None: no
        movable block)."""
        self.critical_dt()
        return getattr(self, "_dt_crit_block", None)

    def stable_dt(self, state: BlockState) -> float:
        """Largest step the clock should take [s]: options.dt_safety x critical_dt() (the DDA limit
        depends on the model only, not on ``state``)."""
        if isinstance(state, (int, float)):
            raise TypeError("BlockSolver.stable_dt(state) takes the BlockState; the safety factor is "
                            "BlockOptions.dt_safety")
        return self.options.dt_safety * self.critical_dt()

    # ---- pipeline ----
    def _prepare(self, state: BlockState):
        m, d = self.model, self.device
        wp.launch(dda_k.block_world_vertices, dim=m.num_vertices,
                  inputs=[m.body_verts, m.vert_block, state.bodies, m.kinds, state.verts], device=d)
        wp.launch(dda_k.block_aabbs, dim=m.num_blocks,
                  inputs=[state.x, state.world_verts_arm, m.vert_start, m.vert_count, self.margin, self.lo, self.hi,
                          state.contact_count], device=d)

    def _broad_phase(self, force: bool = False):
        """Broad phase of this step: always when ``force``, else as options.keep_pairs chose."""
        if force:
            self._broad_phase_always()
        else:
            self._step_broad_phase()

    def _broad_phase_if_moved(self):
        self._moved.zero_()
        wp.launch(dda_k.aabbs_left_pair_boxes, dim=self.model.num_blocks,
                  inputs=[self.lo, self.hi, self.lo_bp, self.hi_bp, 0.5 * self.margin, self._moved], device=self.device)
        if int(self._moved.numpy()[0]) != 0:
            self._broad_phase_always()

    def _broad_phase_always(self):
        self.broad_phases += 1
        wp.copy(self.lo_bp, self.lo)
        wp.copy(self.hi_bp, self.hi)
        while not self._grid_pass():
            pass

    def _grid_launches(self):
        m, d = self.model, self.device
        self.counters.zero_()
        self.bucket_count.zero_()
        wp.launch(dda_k.bp_count, dim=m.num_blocks, inputs=[self.grid, self.counters], device=d)
        wp.utils.array_scan(self.bucket_count, self.bucket_start, inclusive=False)
        wp.launch(dda_k.bp_fill, dim=m.num_blocks, inputs=[self.grid, self.counters], device=d)
        wp.launch(dda_k.bp_pairs, dim=self.entry_cap, inputs=[self.grid, m.kinds, self.pair_list], device=d)
        wp.launch(dda_k.bp_large_pairs, dim=(self.large_list.shape[0], m.num_blocks),
                  inputs=[self.grid, m.kinds, self.pair_list], device=d)

    def _grid_pass_sync_free(self) -> bool:
        """Launch dims at capacity; the kernels stop at the device counts; nothing is read back."""
        self._grid_launches()
        self._unchecked_steps += 1
        if self._unchecked_steps >= self.sync_check_interval:
            self._unchecked_steps = 0
            self._check_capacity_flags()
        return True

    def _grid_pass_counted(self) -> bool:
        """One counter read (the host sync of the step); False after growing an overflowed capacity."""
        self._grid_launches()
        c = self.counters.numpy()
        flags = int(c[1])
        if flags == 0:
            self._pair_count = int(c[0])
            return True
        if flags & 1:
            self._alloc_entries(2 * int(self.bucket_count.numpy().sum()))
        if flags & 2:
            self._alloc_large(2 * int(c[2]))
        if flags & 4:
            self._alloc_pairs(int(c[0]) + int(c[0]) // 4 + 64)  # the live pairs + 25%
        return False

    def _narrow_phase(self, state: BlockState, dt: float, screen: bool = True):
        """FCP narrow phase + contact forces (at block_clock's dt, set by the caller; ``dt`` is that value). screen: pairs whose warm-start plane already separates
        them (gap > 0; first by the bound from last step's gap and the blocks' motion since, else from
        the world vertices) skip FCP and contact generation (narrow_screen); detect() turns it off so
        that every pair's gap is FCP's."""
        m, d = self.model, self.device
        n = self.pair_cap if self.sync_free else self._pair_count
        # history tables sized from the live pairs (slots >= 4/3 x the pairs: linear probing at load <= 3/4)
        # and contact points; sync-free (few blocks): for every pair at K_MAX points, so nothing is read back
        cap, pcap = state.table_cap, state.point_cap
        if 4 * n > 3 * cap:
            cap = _table_slots(n)
        if self.sync_free:
            pcap = max(pcap, dda_k.MAX_CONTACTS * self.pair_cap)
        if (cap, pcap) != (state.table_cap, state.point_cap):
            state.alloc_tables(cap, pcap)
        wp.launch(dda_k.pose_motion, dim=m.num_blocks,
                  inputs=[m.body_verts, m.kinds, m.vert_start, m.vert_count, state.bodies, state.world_verts_arm, state.x_ref,
                          state.q_ref, state.q_lo_ref, state.x_lo_ref, state.strain_ref, state.motion_dx, state.motion_rho], device=d)
        while True:
            old, new = state.table_views
            new.keys.fill_(-1)
            new.pcount.zero_()
            if n > 0:
                self.counters[3:5].zero_()  # lengths of the active lists
                coop_min = self.coop_min if self.has_big_pairs else m.max_vertex_pair
                wp.launch(dda_k.narrow_screen, dim=n,
                          inputs=[self.pair_list, m.num_blocks, int(screen), coop_min, state.verts, m.topology,
                                  state.bodies, state.motion_dx, state.motion_rho, old, new], device=d)
                wp.launch(dda_k.narrow_phase, dim=n,
                          inputs=[self.pair_list, coop_min, state.verts, m.topology, state.bodies, old, new], device=d)
                if self.has_big_pairs:
                    nb = n
                    if not self.sync_free:  # the counter-read path: launch for the big pairs only
                        nb = self.coop_pairs = int(self.counters.numpy()[4])
                    if nb > 0:
                        wp.launch_tiled(coop_k.narrow_phase_coop, dim=[nb], block_dim=self.narrow_block_dim,
                                        inputs=[self.pair_list, state.verts, m.topology, state.bodies, old, new],
                                        device=d)
                wp.launch(dda_k.contact_forces, dim=n,
                          inputs=[self.pair_list, self.block_clock, self.g_mag, self.props, m.material, self.motion, state.bodies, old, new,
                                  state.loads, m.topology.block_size], device=d)
            if self.sync_free or n == 0:
                break
            used = int(new.pcount.numpy()[0])  # the counter-read path: one read of the points taken
            self.contact_points = used
            if used <= state.point_cap:
                break
            # the pool overflowed: grow it to the live points (+25%) and redo this narrow phase from
            # zeroed contact accumulators (the same launches on the same inputs: the same result)
            state.alloc_tables(state.table_cap, used + used // 4 + 64)
            for a in (state.force, state.torque, state.strain_force, state.damp_c, state.damp_b, state.contact_count):
                a.zero_()
            self.point_regrows += 1
        state.swap_tables()  # tables[0] now holds this step's history
        self.narrow_phases += 1

    def _carry_contacts(self, state: BlockState):
        """A held sub-step's contacts: the last narrow phase's pairs, planes and points carried over the sub-step
        just taken (kernels/dda/blocks.py carry_contacts), then the contact forces on them; the tables swap as
        after a narrow phase."""
        m, d = self.model, self.device
        old, new = state.table_views
        new.keys.fill_(-1)
        wp.copy(new.pcount, old.pcount)
        state.contact_count.zero_()  # (block_aabbs zeroes it on a narrow-phase sub-step)
        self.carried_substeps += 1
        n = self.pair_cap if self.sync_free else self._pair_count
        if n > 0:
            wp.launch(dda_k.carry_contacts, dim=n, inputs=[self.pair_list, self.block_clock, m.kinds, state.bodies, old, new],
                      device=d)
            wp.launch(dda_k.contact_forces, dim=n,
                      inputs=[self.pair_list, self.block_clock, self.g_mag, self.props, m.material, self.motion, state.bodies, old, new,
                              state.loads, m.topology.block_size], device=d)
        state.swap_tables()

    def holds_contacts(self, state: BlockState, dt: float, steps: int, headroom: float = 2.0) -> bool:
        """Whether the sub-steps of the next ``steps`` fluid steps of length dt may carry their contacts
        (options.hold_contacts): every candidate pair without contact points at the last narrow phase is
        farther apart than the two blocks can close over them, gap > headroom (reach_A + reach_B) dt steps,
        reach = |v| + |w| r (so no new contact appears inside a held sub-step), and every pair in contact is at
        rest or sliding: its points approach or part, and the blocks turn against each other, slower than the
        resting-contact speed v_rest = |g| / sqrt(n k_n / m_eff) (kernels/dda/blocks.py hold_check_pairs). A carried
        pair keeps its points and gains none until the next fluid step's narrow phase. A host read (hold_checks)."""
        return self.hold_checks(state, dt, steps, headroom)[1]

    def _contact_forces_all(self, state: BlockState, dt: float):
        self._prepare(state)
        self._broad_phase()
        self._narrow_phase(state, dt)

    def _no_contacts(self, state: BlockState, dt: float):
        pass

    def _set_clock(self, t_next: float, dt: float):
        wp.launch(dda_k.set_block_clock, dim=1, inputs=[self.block_clock, float(t_next), float(dt)], device=self.device)

    def _integrate(self, state: BlockState):
        """Integration over the clock's step (block_clock: [t_next, dt]; and the planar constraint of a 2D
        model)."""
        m, d = self.model, self.device
        if m.num_compounds:  # compound blocks: each part gets its body's summed load
            wp.launch(dda_k.compound_loads, dim=m.num_compounds, inputs=[m.compound_start, m.compound_count, state.loads], device=d)
        wp.launch(dda_k.integrate_blocks, dim=m.num_blocks,
                  inputs=[self.props, self.motion, wp.vec3(*m.gravity), self.block_clock, state.bodies, state.loads],
                  device=d)
        if m.planar:
            wp.launch(dda_k.planar_blocks, dim=m.num_blocks, inputs=[m.planar_z, m.kinds, state.bodies], device=d)

    def detect(self, state: BlockState, screen: bool = False, dt: float = 0.0):
        """Collision detection only (world vertices, broad + narrow phase), forces discarded. ``screen``: as a step
        runs it (pairs whose warm-start plane already separates them by more than they can close in ``dt`` are
        skipped, kernels/dda/blocks.py); False: every candidate pair through the full FCP search."""
        self._set_clock(0.0, dt)
        self._prepare(state)
        self._broad_phase(force=True)
        self._narrow_phase(state, dt, screen=screen)
        wp.launch(dda_k.clear_forces, dim=self.model.num_blocks, inputs=[state.loads], device=self.device)

    def settle(self, state: BlockState) -> dict:
        """Equilibrium start (BlockOptions.start = "settled"; issue 36): the blocks that rest on another at t = 0
        (a gap below settle_contact_gap x the smaller one's size, no initial velocity) are brought to the
        equilibrium of their contact springs under gravity with friction locked (every contact point sticks:
        kernels/dda/blocks.py contact_forces, the block clock's flag), the others held where they are (as fixed blocks; kinematic blocks at their pose of t = 0, at
        rest); once every settling block moves slower than settle_speed_ratio x g / omega_max (twice in a row,
        16 steps apart) their velocities are zeroed and friction is switched on for a second stage under kinetic
        damping (_relax_with_friction: the points whose locked share is above their cap slip quasi-statically to
        it, so the blocks start in a statically admissible state; a block that slides is detected and starts from
        the locked stage's state; run.json's block_start.friction_stage), then released. The contact history keeps the
        loaded springs: a block whose equilibrium needs less than its friction starts at rest, its normal springs
        already carrying it (a plain start loads them while gravity already pulls: a 10 m cube at 2.5e8 N/m per
        point on 35 deg at a 0.1 deg margin slid 24 mm that way); one whose points would slip slides from a
        loaded state. The clock is not advanced (state.time stays 0). A block that leaves its place (settle_max_move:
        it topples or falls even with locked friction) undoes the stage; it is held where it was put while the
        others settle again and is then released as placed (report "released_as_placed"), up to settle_attempts
        stages. Not settled within settle_max_steps, or blocks still leaving their place after the last stage: the
        plain start is restored, with a warning.
        Returns (and keeps in start_report, for run.json) what it did."""
        m, d, opt = self.model, self.device, self.options
        n = m.num_blocks
        kinds = m.np["kinds"]
        movable = (kinds == int(dda_k.KIND_RIGID)) | (kinds == int(dda_k.KIND_DEFORMABLE))
        report = {"start": "settled", "settled_blocks": 0, "steps": 0, "time_s": 0.0, "converged": True,
                  "max_speed_m_s": 0.0, "max_displacement_m": 0.0}
        if not self.has_free_blocks:
            self.start_report = report
            return report
        # who rests on whom at t = 0: FCP's gaps of every candidate pair (detect; not counted in the diagnostics)
        counts = (self.broad_phases, self.narrow_phases)
        self.detect(state)
        self.broad_phases, self.narrow_phases = counts
        npairs = self.pair_count
        pairs = self.pairs.numpy()[:npairs]
        gaps = self.pair_gap.numpy()[:npairs]
        size = m.np["size"]
        touching = np.zeros(n, bool)
        close = gaps <= opt.settle_contact_gap * np.minimum(size[pairs[:, 0]], size[pairs[:, 1]]) if npairs else gaps > 0
        for a, b in pairs[close]:
            touching[a] = touching[b] = True
        at_rest = (np.linalg.norm(state.v.numpy(), axis=1) == 0.0) & (np.linalg.norm(state.w.numpy(), axis=1) == 0.0)
        settling = movable & touching & at_rest
        body = m.body_of
        settling = settling[body]  # the parts of a compound block follow its first part
        report["settled_blocks"] = int(np.count_nonzero(settling & m.lead))
        if not settling.any():
            self._reset_history(state)
            self.start_report = report
            return report
        motion = dda_k.BlockMotion()
        for name in ("motion_freq", "motion_phase", "table_start", "table_count", "table_t", "table_x", "motion_amp"):
            setattr(motion, name, getattr(m, name))
        motion.motion_type = wp.zeros(n, dtype=int, device=d)
        pos0, _ = m.initial_poses()
        motion.base_x = wp.array(pos0.astype(np.float32), dtype=wp.vec3, device=d)
        x0 = state.positions_numpy()
        x0_dev = wp.clone(state.x)
        saved = {k: wp.clone(getattr(state, k)) for k in ("x", "x_lo", "q", "q_lo", "v", "w", "strain", "strain_rate",
                                                           "v_step")}
        dt = self.stable_dt(state)
        tol = opt.settle_speed_ratio * self.g_mag * self.critical_dt() / 2.0
        flags = wp.zeros(2, dtype=int, device=d)
        # float32's floor: a block whose contact force changes by k_n x (the spacing of its vertices' float32
        # coordinates) per step of position more than its friction margin chatters at ~ that force x dt / m and
        # never gets below tol (1 m cube at k_n = 3e9 N/m per point, 0.2 m cube at the default 2e8); it counts as
        # settled once its speed has not halved over stall_checks checks and is below 0.1 g / omega_max
        stall_checks, v_max = 32, self.g_mag * self.critical_dt() / 2.0
        reach = wp.zeros(n, dtype=float, device=d)
        # how far a block may move and still be "where it was placed": settle_max_move of its size, plus twice
        # its springs' deflection under its own weight on one contact point, 2 m g / k_n (soft joints: a 20 m
        # block on 1 MPa/m sinks 0.7 m onto its springs, 3% of its size, and is still at rest there)
        with np.errstate(divide="ignore", invalid="ignore"):
            sag = np.where(m.np["k_n"] > 0.0, 2.0 * m.np["mass"] * self.g_mag / m.np["k_n"], 0.0)
        allow = opt.settle_max_move * size + np.where(np.isfinite(sag), sag, 0.0)
        allow_dev = wp.array(allow.astype(np.float32), dtype=float, device=d)
        released = np.zeros(n, bool)  # blocks that left their place: held during the stage, released as placed
        steps_total = 0
        for attempt in range(opt.settle_attempts):
            # the stage's argument groups: the others held (kind fixed, no inverse mass), kinematic blocks at rest
            # at their pose of t = 0; friction locked by the block clock's flag (kernels/dda/blocks.py contact_forces)
            props = dda_k.BlockProps()
            for name in ("inertia_body", "inv_inertia_body", "strain_minv", "strain_k", "strain_damp"):
                setattr(props, name, getattr(m, name))
            props.kinds = wp.array(np.where(movable & ~settling, int(dda_k.KIND_FIXED), kinds).astype(np.int32), dtype=int, device=d)
            props.inv_mass = wp.array(np.where(settling, m.inv_mass.numpy(), 0.0).astype(np.float32), dtype=float, device=d)
            moved = False
            calm, steps, speed, best, stall = 0, 0, math.inf, math.inf, 0
            self.props, self.motion = props, motion
            self.block_clock.assign(np.array([0.0, dt, 1.0]))  # clock[2] = 1: friction locked (contact_forces)
            try:
                while steps < opt.settle_max_steps:
                    self._set_clock(0.0, dt)
                    self._contact_forces(state, dt)
                    self._integrate(state)
                    steps += 1
                    self.broad_phases, self.narrow_phases = counts
                    if steps % 16 == 0:
                        flags.zero_()
                        wp.launch(dda_k.settle_speed, dim=n,
                                  inputs=[props.kinds, m.block_size, state.v, state.w, float(tol), state.x, x0_dev,
                                          allow_dev, flags, reach], device=d)
                        fl = flags.numpy()
                        if fl[1]:  # a block left its place: not at rest where it was put (it topples or falls)
                            moved = True
                            break
                        calm = calm + 1 if int(fl[0]) == 0 else 0
                        if calm >= 2:
                            break
                        speed = float(reach.numpy().max())  # (a read of N floats every 16 steps)
                        if speed < 0.5 * best:
                            best, stall = speed, 0
                        else:
                            stall += 1
                        if stall >= stall_checks and speed < 0.1 * v_max:
                            calm = 2  # at float32's floor
                            report["float32_floor"] = True
                            break
            finally:
                self.props, self.motion = m.props, m.motion
                self.block_clock.assign(np.array([0.0, dt, 0.0]))
            steps_total += steps
            disp = np.linalg.norm(state.positions_numpy() - x0, axis=1)
            if not moved:
                break
            # the blocks that left their place start as placed, held while the others settle again from the start
            out = settling & (disp > allow)
            out = out[body] | np.isin(body, body[out])  # a compound block whole
            if not out.any():  # (the flag and the host's check disagree only at round-off: take the farthest)
                out = body == body[int(np.argmax(np.where(settling, disp / allow, -1.0)))]
            released |= out
            settling = settling & ~out
            for k, a in saved.items():
                wp.copy(getattr(state, k), a)
            self._reset_history(state)
            if not settling.any():
                break
        v, w = state.v.numpy().astype(np.float64), state.w.numpy().astype(np.float64)
        speed = float(np.max(np.linalg.norm(v, axis=1) + np.linalg.norm(w, axis=1) * 0.5 * size, where=settling, initial=0.0))
        disp = np.linalg.norm(state.positions_numpy() - x0, axis=1)
        report.update(steps=steps_total, time_s=steps_total * dt, converged=calm >= 2 and not moved, max_speed_m_s=speed,
                      max_displacement_m=float(np.max(disp, where=settling, initial=0.0)),
                      settled_blocks=int(np.count_nonzero(settling & m.lead)))
        if released.any():
            names = [m.names[b] for b in np.flatnonzero(released & m.lead)]
            report["released_as_placed"] = names
        if moved or calm < 2:  # not at rest: the blocks as placed, unloaded contacts
            for k, a in saved.items():
                wp.copy(getattr(state, k), a)
            self._reset_history(state)
            report["start"] = "plain"
            report["converged"] = False
            if moved or released.any():
                report["moved"] = True
                warnings.warn(f"settled start: {len(report.get('released_as_placed', []))} blocks left their place with "
                              f"their friction locked (they topple or fall; the bound is BlockOptions.settle_max_move = "
                              f"{opt.settle_max_move:g} of a block's size + 2 m g / k_n), still after "
                              f"{opt.settle_attempts} settling stages of {steps_total} steps in all: the blocks are not at "
                              f"rest where they were placed; the scene starts as placed (simulation.start = 'plain')")
            else:
                worst = int(np.argmax(np.where(settling, np.linalg.norm(v, axis=1), -1.0)))
                warnings.warn(f"settled start: the blocks did not come to rest within {opt.settle_max_steps} block steps "
                              f"({steps * dt:.3g} s; block '{m.names[worst]}' still moves at {speed:.3g} m/s, the bound is "
                              f"{tol:.3g} m/s): the scene starts as placed (simulation.start = 'plain')")
        else:
            for a in (state.v, state.w, state.strain_rate):  # the settled blocks at rest (a thrown block keeps its v)
                arr = a.numpy()
                arr[settling] = 0.0
                a.assign(arr)
            report["friction_stage"] = self._relax_with_friction(state, settling, allow, dt, tol, steps_total)
            for a in (state.v, state.w, state.strain_rate):  # at rest after it too
                arr = a.numpy()
                arr[settling] = 0.0
                a.assign(arr)
            if released.any():
                names = report["released_as_placed"]
                warnings.warn(f"settled start: {len(names)} block(s) left their place with their friction locked (they "
                              f"topple or fall: {', '.join(names[:5])}{' ...' if len(names) > 5 else ''}); they start as "
                              f"placed, the other {report['settled_blocks']} settled (run.json block_start)")
        state.time = 0.0
        self.start_report = report
        return report

    @staticmethod
    def _snapshot(state: BlockState) -> dict:
        """A copy of the state's arrays and contact-history tables (BlockSolver._restore)."""
        arrays = {k: wp.clone(a) for k, a in vars(state).items() if isinstance(a, wp.array)}
        tables = [{k: wp.clone(a) for k, a in t.items()} for t in state.tables]
        return {"arrays": arrays, "tables": tables, "cap": (state.table_cap, state.point_cap)}

    @staticmethod
    def _restore(state: BlockState, snap: dict) -> None:
        for k, a in snap["arrays"].items():  # in place: the argument groups (bodies, loads) hold these arrays
            wp.copy(getattr(state, k), a)
        state.tables = [{k: wp.clone(a) for k, a in t.items()} for t in snap["tables"]]
        state.table_views = [_table_view(t) for t in state.tables]
        state.table_cap, state.point_cap = snap["cap"]

    def _relax_with_friction(self, state: BlockState, settling: np.ndarray, allow: np.ndarray, dt: float, tol: float,
                             locked_steps: int) -> dict:
        """The settled start's second stage (issue 36): after the locked stage, friction is switched on (Coulomb
        caps, the clock's flag 0) and the settling blocks relax under kinetic damping (kernels/dda/blocks.py
        relax_blocks: a block's velocities are zeroed whenever its kinetic energy stops rising), so a contact point
        whose locked share of the shear is above its cap mu F_n (the uphill corners of a tall block on a slope)
        slips quasi-statically to its limit, and the block starts at rest in a statically admissible state
        (the partial-slip state) instead of slipping dynamically, and overshooting, at t = 0. Calm: every block
        slower than SETTLE_RELAX_TOL x tol over two windows of 16 steps in a row (or at float32's floor, as the locked stage). A block
        that slides (friction below what it needs: its kinetic energy rises for more steps than the locked stage
        took to come to rest, or it leaves its place, settle_max_move) is detected, the stage is undone and run
        again with that block held; it starts from its locked-stage state and slides at t = 0. Not calm within
        settle_max_steps: the locked-stage state is kept, with a warning. Returns the stage's report."""
        m, d, opt = self.model, self.device, self.options
        n = m.num_blocks
        kinds = m.np["kinds"]
        movable = (kinds == int(dda_k.KIND_RIGID)) | (kinds == int(dda_k.KIND_DEFORMABLE))
        body = m.body_of
        counts = (self.broad_phases, self.narrow_phases)
        locked = self._snapshot(state)
        x1 = state.positions_numpy()
        x1_dev = wp.clone(state.x)
        allow_dev = wp.array(allow.astype(np.float32), dtype=float, device=d)
        # a block's kinetic energy may rise without a peak at most as long as the locked stage took to ring its
        # springs down (its elastic periods are shorter); longer, it accelerates: it slides
        max_rise = max(int(locked_steps), 64)
        flags = wp.zeros(2, dtype=int, device=d)
        reach = wp.zeros(n, dtype=float, device=d)
        stall_checks, v_max = 32, self.g_mag * self.critical_dt() / 2.0
        held = np.zeros(n, bool)
        rep = {"friction": "on", "damping": "kinetic", "steps": 0, "converged": False, "max_displacement_m": 0.0}
        steps_total, calm = 0, 0
        for attempt in range(opt.settle_attempts):
            active = settling & ~held
            if not active.any():
                break
            props = dda_k.BlockProps()
            for name in ("inertia_body", "inv_inertia_body", "strain_minv", "strain_k", "strain_damp"):
                setattr(props, name, getattr(m, name))
            props.kinds = wp.array(np.where(movable & ~active, int(dda_k.KIND_FIXED), kinds).astype(np.int32), dtype=int, device=d)
            props.inv_mass = wp.array(np.where(active, m.inv_mass.numpy(), 0.0).astype(np.float32), dtype=float, device=d)
            e_prev = wp.zeros(n, dtype=float, device=d)
            rise = wp.zeros(n, dtype=int, device=d)
            reach_max = wp.zeros(n, dtype=float, device=d)
            sliding = wp.zeros(n, dtype=int, device=d)
            slid = False
            calm, steps, best, stall = 0, 0, math.inf, 0
            self.props = props
            self.block_clock.assign(np.array([0.0, dt, 0.0]))  # clock[2] = 0: Coulomb caps on
            try:
                while steps < opt.settle_max_steps:
                    self._set_clock(0.0, dt)
                    self._contact_forces(state, dt)
                    # between the contact forces and the integration: the shear springs have just recorded the
                    # last step's motion (df = -k_s v_t dt with the velocity that moved the block), so zeroing v
                    # here loses no motion from them (zeroed after the integration, the step's v dt would be a slip)
                    wp.launch(dda_k.relax_blocks, dim=n, inputs=[props.kinds, m.block_size, state.v, state.w,
                                                                 state.strain_rate, e_prev, rise, reach_max], device=d)
                    self._integrate(state)
                    steps += 1
                    self.broad_phases, self.narrow_phases = counts
                    if steps % 16 == 0:
                        flags.zero_()
                        wp.launch(dda_k.relax_check, dim=n,
                                  inputs=[props.kinds, reach_max, float(tol * SETTLE_RELAX_TOL), state.x, x1_dev, allow_dev, rise,
                                          int(max_rise), flags, reach, sliding], device=d)
                        fl = flags.numpy()
                        if fl[1]:
                            slid = True
                            break
                        calm = calm + 1 if int(fl[0]) == 0 else 0
                        if calm >= 2:
                            break
                        speed = float(reach.numpy().max())
                        if speed < 0.5 * best:
                            best, stall = speed, 0
                        else:
                            stall += 1
                        if stall >= stall_checks and speed < 0.1 * v_max:
                            calm = 2
                            rep["float32_floor"] = True
                            break
            finally:
                self.props = m.props
            steps_total += steps
            if not slid:
                break
            out = (sliding.numpy() != 0) & active
            out = out[body] | np.isin(body, body[out])
            held |= out
            self._restore(state, locked)
        if held.any():
            rep["sliding"] = [m.names[b] for b in np.flatnonzero(held & m.lead)]
        active = settling & ~held
        rep["steps"] = steps_total
        rep["time_s"] = steps_total * dt
        if active.any() and calm < 2:  # not calm: the locked-stage state, as before this stage
            self._restore(state, locked)
            warnings.warn(f"settled start: the blocks did not come to rest with friction on within {opt.settle_max_steps} "
                          f"block steps: they start from the locked stage's state (contact points above their cap slip at t = 0)")
        else:
            rep["converged"] = True
            disp = np.linalg.norm(state.positions_numpy() - x1, axis=1)
            rep["max_displacement_m"] = float(np.max(disp, where=active, initial=0.0))
        self.block_clock.assign(np.array([0.0, dt, 0.0]))
        return rep

    def _reset_history(self, state: BlockState) -> None:
        """No contact history (as a fresh state: the plain start)."""
        for t in state.tables:
            t["keys"].fill_(-1)
            t["pcount"].zero_()
        state.q_ref.zero_()

    def step(self, state: BlockState, ts: TimeStep):
        """Advance state by ts.dt from ts.time; refuses a dt above critical_dt()."""
        dt, t = ts.dt, ts.time
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        dc = self.critical_dt()
        if dt > dc:
            raise ValueError(f"dt = {dt:.4g} s exceeds the critical DDA time step {dc:.4g} s (2/omega_max); "
                             f"use BlockSolver.stable_dt(state) = {self.stable_dt(state):.4g} s "
                             f"(BlockOptions.dt_safety = {self.options.dt_safety:g} of the critical step)")
        self._set_clock(t + dt, dt)
        self._contact_forces(state, dt)
        self._integrate(state)
        state.time = t + dt

    def substeps(self, state: BlockState, ts: TimeStep, n: int, keep_pairs: bool = False, hold_contacts: bool = False):
        """Multi-rate stepping (rockwave/sim/clock.py): n steps of ts.dt / n from ts.time with the external
        load (ext_force / ext_torque: the water's reaction, written once per fluid step by the coupling)
        held over all of them, so the blocks receive exactly the impulse ts.dt x load. n = 1 is step().
        ``keep_pairs``: the first sub-step's broad phase serves all n (the caller checked with
        pairs_hold() that no block moves margin/2 over ts.dt, so the pair list stays complete). ``hold_contacts``
        (with keep_pairs; the caller checked holds_contacts()): sub-steps 1..n-1 carry the first one's contacts
        (_carry_contacts) instead of running the narrow phase."""
        if n == 1:
            return self.step(state, ts)
        h = ts.dt / n
        dc = self.critical_dt()
        if not 0.0 < h <= dc:
            raise ValueError(f"block sub-step {h:.4g} s must be in (0, {dc:.4g}] s (the critical DDA step)")
        held = getattr(self, "_held_load", None)
        if held is None:
            nb = self.model.num_blocks
            held = self._held_load = (wp.zeros(nb, dtype=wp.vec3, device=self.device), wp.zeros(nb, dtype=wp.vec3, device=self.device))
        wp.copy(held[0], state.ext_force)  # integrate_blocks zeroes the load after each sub-step
        wp.copy(held[1], state.ext_torque)
        contacts_only = keep_pairs and self.has_free_blocks
        hold = contacts_only and hold_contacts
        graphs = self._substep_graphs if (contacts_only and self.sync_free) else None
        if graphs is not None and self._step_graphs_ok and not self._keep_pairs and self.narrow_phases > 0:
            # the whole fluid step's n sub-steps replayed from one CUDA graph (the first one's broad and narrow
            # phases included: the sync-free path reads nothing back), one launch instead of ~25 from Python
            g = self._fluid_step_graph(state, held, h, n, hold)
            if g is not None:
                self._set_clock(ts.time + h, h)
                wp.capture_launch(g)
                if n % 2:
                    state.swap_tables()  # each sub-step wrote the other table
                self.graph_substeps += n
                self.fluid_step_graphs += 1
                if hold:
                    self.carried_substeps += n - 1
                self.broad_phases += 1
                self._unchecked_steps += 1
                if self._unchecked_steps >= self.sync_check_interval:
                    self._unchecked_steps = 0
                    self._check_capacity_flags()
                state.time = ts.time + ts.dt
                return
        for i in range(n):
            if i and graphs is not None:  # sub-steps 1..n-1 replayed from a CUDA graph (the clock advances on the device)
                if i == 1:
                    self._set_clock(ts.time + h + h, h)
                wp.capture_launch(self._substep_graph(state, held, h, hold))
                state.swap_tables()  # the graph's narrow phase wrote the other table
                self.graph_substeps += 1
                continue
            if i:
                wp.copy(state.ext_force, held[0])
                wp.copy(state.ext_torque, held[1])
            self._set_clock(ts.time + i * h + h, h)
            if i and hold:
                self._carry_contacts(state)
            elif i and contacts_only:
                self._prepare(state)
                self._narrow_phase(state, h)
            else:
                self._contact_forces(state, h)
            self._integrate(state)
        state.time = ts.time + ts.dt

    def _fluid_step_body(self, state: BlockState, held, h: float, n: int, hold: bool):
        """The n sub-steps of one fluid step at the device clock (set_block_clock before it; the clock advances
        after each): the captured body of _fluid_step_graph. Sync-free path only (no host read)."""
        wp.copy(held[0], state.ext_force)
        wp.copy(held[1], state.ext_torque)
        for i in range(n):
            if i:
                wp.copy(state.ext_force, held[0])
                wp.copy(state.ext_torque, held[1])
            if i and hold:
                self._carry_contacts(state)
            else:
                self._prepare(state)
                if i == 0:
                    wp.copy(self.lo_bp, self.lo)
                    wp.copy(self.hi_bp, self.hi)
                    self._grid_launches()
                self._narrow_phase(state, h)
            self._integrate(state)
            wp.launch(dda_k.advance_block_clock, dim=1, inputs=[self.block_clock], device=self.device)

    def _fluid_step_graph(self, state: BlockState, held, h: float, n: int, hold: bool):
        """The CUDA graph of one fluid step's n block sub-steps for the tables' current parity, captured on first
        use and keyed by every address it baked in (None, and no more tries, if the capture fails: the
        sub-steps are then launched as before)."""
        t0, t1 = state.tables
        key = ("step", n, hold, id(t0), id(t1), state.table_cap, state.point_cap, self.pair_cap, state.x.ptr,
               state.ext_force.ptr, held[0].ptr, self.pair_list.active.ptr, self.entry_cap, self.large_list.ptr)
        g = self._substep_graphs.get(key)
        if g is None:
            if len(self._substep_graphs) > 8:  # stale keys after reallocations
                self._substep_graphs.clear()
            tables, views = list(state.tables), list(state.table_views)
            counts = (self.narrow_phases, self.carried_substeps)
            try:
                with wp.ScopedCapture(device=self.device, force_module_load=False) as cap:
                    self._fluid_step_body(state, held, h, n, hold)
            except Exception as e:  # e.g. a Warp utility that cannot be captured: launch as before
                self._step_graphs_ok = False
                warnings.warn(f"block sub-steps: one graph per fluid step could not be captured ({e}); launching them")
                return None
            finally:
                state.tables, state.table_views = tables, views  # capture ran no kernel: the parity is unchanged
                self.narrow_phases, self.carried_substeps = counts
            g = self._substep_graphs[key] = cap.graph
            self.graph_captures += 1
        return g

    def _substep_one(self, state: BlockState, held, h: float, hold: bool = False):
        """One kept-pairs sub-step at the device clock, then the clock advances (the captured body)."""
        wp.copy(state.ext_force, held[0])
        wp.copy(state.ext_torque, held[1])
        if hold:
            self._carry_contacts(state)
        else:
            self._prepare(state)
            self._narrow_phase(state, h)
        self._integrate(state)
        wp.launch(dda_k.advance_block_clock, dim=1, inputs=[self.block_clock], device=self.device)

    def _substep_graph(self, state: BlockState, held, h: float, hold: bool = False):
        """The CUDA graph of one kept-pairs sub-step for the tables' current parity, captured on first use
        (sync-free path: no host read, no allocation inside). Its key holds every address it baked in
        (state arrays, both contact tables, the pair list), so a reallocation captures a new one."""
        t0, t1 = state.tables
        key = (id(t0), id(t1), state.table_cap, state.point_cap, self.pair_cap, state.x.ptr, state.ext_force.ptr,
               held[0].ptr, self.pair_list.active.ptr if hasattr(self.pair_list, "active") else 0, hold)
        g = self._substep_graphs.get(key)
        if g is None:
            if len(self._substep_graphs) > 8:  # stale keys after reallocations
                self._substep_graphs.clear()
            tables, views = list(state.tables), list(state.table_views)
            with wp.ScopedCapture(device=self.device, force_module_load=False) as cap:
                self._substep_one(state, held, h, hold)
            state.tables, state.table_views = tables, views  # capture ran no kernel: the parity is unchanged
            g = self._substep_graphs[key] = cap.graph
            self.graph_captures += 1
        return g

    def pairs_hold(self, state: BlockState, dt: float, headroom: float = 2.0) -> bool:
        """Whether one broad phase can serve a whole step dt of sub-steps: max over the blocks that move
        (rigid, deformable, kinematic) of (|v| + |w| r) dt, times ``headroom`` for the speed growing before
        the next check, is within margin/2 (the distance the kept pair list tolerates,
        aabbs_left_pair_boxes). A host read (hold_checks)."""
        return self.hold_checks(state, dt, 1, headroom)[0]

    def hold_checks(self, state: BlockState, dt: float, steps: int, headroom: float = 2.0) -> tuple[bool, bool]:
        """(pairs_hold, holds_contacts) from two small kernels (kernels/dda/blocks.py hold_check_blocks,
        hold_check_pairs) and one read of two ints through a pinned host buffer (array reads of v, w and the pair
        list cost milliseconds on a GPU host). Contacts are held only when the pair list is, and after a
        narrow phase (before it nothing is known)."""
        m, d = self.model, self.device
        flags = getattr(self, "_hold_flags", None)
        if flags is None:
            flags = self._hold_flags = (wp.zeros(2, dtype=int, device=d),
                                        wp.zeros(2, dtype=int, device="cpu", pinned=wp.get_device(d).is_cuda))
        flags[0].fill_(1)
        wp.launch(dda_k.hold_check_blocks, dim=m.num_blocks,
                  inputs=[m.kinds, m.block_size, state.v, state.w, float(headroom * dt), 0.5 * self.margin, flags[0]],
                  device=d)
        check_contacts = bool(self.options.hold_contacts and self.narrow_phases)
        n = self.pair_cap if self.sync_free else self._pair_count
        if check_contacts and n > 0:
            wp.launch(dda_k.hold_check_pairs, dim=n,
                      inputs=[self.pair_list, m.props, m.material, m.block_size, state.bodies, self.g_mag,
                              float(headroom * dt * steps), state.table_views[0], flags[0]], device=d)
        wp.copy(flags[1], flags[0])
        wp.synchronize_device(d)
        f = flags[1].numpy()
        pairs_ok = bool(f[0])
        return pairs_ok, bool(pairs_ok and check_contacts and f[1])

    # ---- diagnostics ----
    def contacts(self, state: BlockState) -> list:
        """Pairs examined in the last step: dicts with blocks (i, j), normal (i -> j), gap (m,
        negative = overlap), points (k, 3, world), depths (k,), normal_forces (k,).  After step(), a pair
        certified separated by its warm-start plane keeps that plane and a positive lower bound of the
        gap; after detect() every gap is FCP's."""
        n = self.pair_count
        if n == 0:
            return []
        pairs = self.pairs.numpy()[:n]
        gaps = self.pair_gap.numpy()[:n]
        slots = self.pair_slot.numpy()[:n]
        t = state.tables[0]
        normal = t["normal"].numpy()
        nc = t["nc"].numpy()
        ps = t["pstart"].numpy()
        pos = t["pos"].numpy()
        dep = t["depth"].numpy()
        fn = t["fn"].numpy()
        # the table keeps points relative to block i's centroid x + x_lo (kernels/dda/blocks.py contact_forces)
        centroid = state.x.numpy().astype(np.float64) + state.x_lo.numpy()
        out = []
        for p in range(n):
            s = slots[p]
            k = nc[s] if s >= 0 else 0
            i = ps[s] if s >= 0 else 0
            a = int(pairs[p][0])
            out.append(dict(blocks=(a, int(pairs[p][1])), normal=normal[s].astype(float),
                            gap=float(gaps[p]), points=pos[i: i + k].astype(float) + centroid[a],
                            depths=dep[i: i + k].astype(float), normal_forces=fn[i: i + k].astype(float)))
        return out

    def device_bytes(self, state: BlockState) -> dict:
        """Device memory of the block solver [bytes]: every Warp array of the model (``model``), the state
        without its history tables (``state``), the two contact-history tables (``history``) and the
        solver's buffers (``solver``: AABBs, broad-phase grid, pair list), each array counted once;
        ``total`` and ``per_block`` (total / blocks)."""
        seen = set()

        def walk(obj):
            tot = 0
            items = obj.items() if isinstance(obj, dict) else vars(obj).items()
            for name, a in items:
                if isinstance(a, wp.array) and a.ptr is not None and id(a) not in seen and name != "model":
                    seen.add(id(a))
                    tot += a.capacity
            return tot

        out = dict(model=walk(self.model), history=sum(walk(t) for t in state.tables))
        out["state"] = walk(state)
        out["solver"] = walk(self)
        out["total"] = out["model"] + out["history"] + out["state"] + out["solver"]
        out["per_block"] = out["total"] / self.model.num_blocks
        return out
