"""Warp kernels of the explicit 3D DDA block solver (rockwave.kernels.dda.blocks).

Sources: Nezami et al. (2004) "A fast contact detection algorithm for 3-D discrete element method"
(broad-phase cell size S ~ 1.5 D50, Fast Common Plane); the SPH-DDA rock/fluid seed paper §2-5
(half-edges, explicit central difference dt <= 2/w_max); Shi (1993) DDA first-order block
displacement (12 DOF: translation, rotation, 6 constant strains).

Conventions: z up, SI units, float32.  Quaternions are Warp's (x, y, z, w).  A pair (A, B) has
A < B; the common-plane normal n points from A to B; the force on B is +F, on A is -F.
Strain vector s (wp.spatial_vector) = (eps_x, eps_y, eps_z, gamma_yz, gamma_zx, gamma_xy) in the
block's body frame (engineering shear strains).

Kernel arguments come in groups (wp.structs below) built once on the host: BlockTopology,
BlockProps, BlockMaterial, BlockMotion (BlockModel), BlockBodies, BlockLoads, ContactTable
(BlockState), BroadPhaseGrid, PairList (BlockSolver). Kernels copy the fields they use into locals.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # forward kernels only: nothing here is differentiated

KIND_RIGID = wp.constant(0)
KIND_DEFORMABLE = wp.constant(1)
KIND_FIXED = wp.constant(2)
KIND_KINEMATIC = wp.constant(3)

MOTION_SINE = wp.constant(1)
MOTION_TABLE = wp.constant(2)

MAX_CONTACTS = 16  # contact points kept per pair (host side constant)
K_MAX = wp.constant(MAX_CONTACTS)
# a pair's contact points while narrow_phase generates them (thread-local, K_MAX of each), before they
# are given exactly nc entries of the table's point pool
PointCoord = wp.types.vector(length=MAX_CONTACTS, dtype=wp.float32)
PointKey = wp.types.vector(length=MAX_CONTACTS, dtype=wp.int32)
# damping ratio of the shear dashpot of a stuck contact point: overdamped, so a suddenly loaded stuck
# spring settles without overshoot (critical damping overshoots the load by 13%, more than a small
# friction margin); the dashpot only ever takes the Coulomb capacity the spring leaves (narrow_phase)
ZETA_STUCK = wp.constant(4.0)
MAX_VALENCE = wp.constant(64)  # cap on half-edge walks around one vertex
FCP_MAX_ITER = wp.constant(10)  # Nezami et al.: "usually very small" number of iterations
SAT_EDGE_PAIRS = wp.constant(2048)  # overlap check over all edge pairs only below this E_A * E_B

FLAG_ENTRY_OVERFLOW = wp.constant(1)
FLAG_LARGE_OVERFLOW = wp.constant(2)
FLAG_PAIR_OVERFLOW = wp.constant(4)
FLAG_CONTACT_OVERFLOW = wp.constant(8)


# ----------------------------------------------------------------------------------------------
# argument groups: device-array views built once (BlockModel, BlockState, BlockSolver) and passed
# to the kernels whole instead of dozens of separate arrays
# ----------------------------------------------------------------------------------------------


@wp.struct
class BlockTopology:
    """Static geometry of all blocks (BlockModel): per-block ranges into the concatenated vertex and
    face arrays, the half-edge mesh (global indices), each block's bounding diameter [m], and its
    half-edges in walk order (he_walk[he_start[b] ...]: vertex by vertex, each vertex's outgoing ones
    around it, the order in which narrow_phase walks them; narrow_phase_coop's work items)."""

    vert_start: wp.array(dtype=int)
    vert_count: wp.array(dtype=int)
    face_start: wp.array(dtype=int)
    face_count: wp.array(dtype=int)
    face_he: wp.array(dtype=int)
    vertex_out_he: wp.array(dtype=int)
    he_vertex: wp.array(dtype=int)
    he_next: wp.array(dtype=int)
    he_twin: wp.array(dtype=int)
    block_size: wp.array(dtype=float)
    he_start: wp.array(dtype=int)
    he_count: wp.array(dtype=int)
    he_walk: wp.array(dtype=int)


@wp.struct
class BlockProps:
    """Static per-block mass properties (BlockModel): kind, 1/m (0 for fixed and kinematic blocks),
    body-frame inertia and its inverse, deformable blocks' strain-mode inverse mass, stiffness and
    damping rate [1/s]."""

    kinds: wp.array(dtype=int)
    inv_mass: wp.array(dtype=float)
    inertia_body: wp.array(dtype=wp.mat33)
    inv_inertia_body: wp.array(dtype=wp.mat33)
    strain_minv: wp.array(dtype=wp.spatial_matrix)
    strain_k: wp.array(dtype=wp.spatial_matrix)
    strain_damp: wp.array(dtype=float)


@wp.struct
class BlockMaterial:
    """Contact law of each block's surface (BlockModel): k_n, k_s [N/m per point], tan(phi),
    cohesion and tensile strength [Pa], dashpot damping ratio zeta."""

    k_n: wp.array(dtype=float)
    k_s: wp.array(dtype=float)
    tan_phi: wp.array(dtype=float)
    cohesion: wp.array(dtype=float)
    tensile: wp.array(dtype=float)
    zeta: wp.array(dtype=float)


@wp.struct
class BlockMotion:
    """Prescribed motion of kinematic blocks (BlockModel): base position, motion type (MOTION_*),
    sine amplitude/frequency/phase, and the rows of the displacement tables."""

    base_x: wp.array(dtype=wp.vec3)
    motion_type: wp.array(dtype=int)
    motion_amp: wp.array(dtype=wp.vec3)
    motion_freq: wp.array(dtype=float)
    motion_phase: wp.array(dtype=float)
    table_start: wp.array(dtype=int)
    table_count: wp.array(dtype=int)
    table_t: wp.array(dtype=float)
    table_x: wp.array(dtype=wp.vec3)


@wp.struct
class BlockBodies:
    """Pose and velocity of every block (BlockState): centroid x, orientation q, velocity v,
    angular velocity w (world), strain and strain rate (body frame), and x_lo, the part of the centroid
    below float32's resolution at x: the centroid is x + x_lo ("double-float", ~48 bits; integrate_blocks); q_lo likewise
    the part of the orientation below q's resolution (the orientation is q + q_lo, unit to float64's precision;
    every kernel reads the rounded q). v_step: a kinematic block's displacement over its last step / dt (v is its
    prescribed velocity at the step's end; the contact springs integrate v_step, as they integrate a free block's
    v, the velocity that moved it over the last step); unused for other blocks."""

    x: wp.array(dtype=wp.vec3)
    q: wp.array(dtype=wp.quat)
    v: wp.array(dtype=wp.vec3)
    w: wp.array(dtype=wp.vec3)
    strain: wp.array(dtype=wp.spatial_vector)
    strain_rate: wp.array(dtype=wp.spatial_vector)
    x_lo: wp.array(dtype=wp.vec3)
    q_lo: wp.array(dtype=wp.quat)
    v_step: wp.array(dtype=wp.vec3)


# a symmetric 6x6 matrix as its upper triangle, row by row (21 entries: 84 B, not the full matrix's 144)
sym6 = wp.types.vector(length=21, dtype=wp.float32)


@wp.func
def sym6_outer(c: float, j: wp.spatial_vector):
    # c j j^T as sym6 (entries c (j_r j_q), as c * outer(j, j) rounds them)
    s = sym6()
    k = int(0)
    for r in range(6):
        for q in range(r, 6):
            s[k] = c * (j[r] * j[q])
            k += 1
    return s


@wp.func
def sym6_matrix(s: sym6):
    # the full 6x6 of a sym6
    C = wp.spatial_matrix()
    k = int(0)
    for r in range(6):
        for q in range(r, 6):
            C[r, q] = s[k]
            C[q, r] = s[k]
            k += 1
    return C


@wp.struct
class BlockLoads:
    """Force accumulators of every block (BlockState): contact force, torque and generalised strain
    force, external force and torque (added by other modules), contact points of the step, and the
    contact dashpots implicit in the block update: damp_c (6x6 over [v, w], symmetric: its upper
    triangle, sym6) and damp_b (generalised force
    from the other block's velocity; add_damper)."""

    force: wp.array(dtype=wp.vec3)
    torque: wp.array(dtype=wp.vec3)
    strain_force: wp.array(dtype=wp.spatial_vector)
    ext_force: wp.array(dtype=wp.vec3)
    ext_torque: wp.array(dtype=wp.vec3)
    contact_count: wp.array(dtype=int)
    damp_c: wp.array(dtype=sym6)
    damp_b: wp.array(dtype=wp.spatial_vector)


@wp.struct
class ContactTable:
    """Contact history hash table (BlockState, two of them swapped each step): per slot the pair key
    (-1 empty), common-plane normal, gap or its lower bound, contact point count nc and the first of
    its points in the point pool (pstart); per point (pstart + k, k < nc: a pair in contact takes
    exactly nc entries, so the pool is sized from the live contact points, not a capacity per pair) the
    feature key, shear spring force, position (relative to A's centroid x + x_lo), depth, normal force, the closing speed when the point
    first touched [m/s] and the step's Coulomb cap mu F_n + c A [N]. pcount[0]: pool entries
    requested this step (above the pool's length: it overflowed; BlockSolver grows it and redoes)."""

    keys: wp.array(dtype=wp.int64)
    normal: wp.array(dtype=wp.vec3)
    gapb: wp.array(dtype=float)
    nc: wp.array(dtype=int)
    pstart: wp.array(dtype=int)
    pcount: wp.array(dtype=int)
    ckey: wp.array(dtype=wp.vec2i)
    shear: wp.array(dtype=wp.vec3)
    pos: wp.array(dtype=wp.vec3)
    depth: wp.array(dtype=float)
    fn: wp.array(dtype=float)
    vimp: wp.array(dtype=float)
    fcap: wp.array(dtype=float)


@wp.struct
class WorldVerts:
    """World vertices of every block (BlockState) as arms: each vertex relative to its block's float32
    centroid x, x_lo + R (X + E X) (~ the block's size, so float32 keeps its bits there). The float32
    world position is x + arm, formed where it is needed (block_aabbs, pose_motion; not stored: 12 B per
    vertex). The narrow phase reads them in a frame of its pair (pair_vertex), where contact depths keep
    their bits however far the pair is from the world origin. arm_lo: the part of the arm below float32's
    resolution at it (the arm x_lo + R(q + q_lo) (X + E X) is formed in float64, arm + arm_lo its value to
    ~48 bits): column_depth reads it, so that a contact depth of a few um is not rounded to the ~3e-8 m spacing of
    coordinates ~0.5 m (issue 36)."""

    arm: wp.array(dtype=wp.vec3)
    arm_lo: wp.array(dtype=wp.vec3)


@wp.struct
class BroadPhaseGrid:
    """Uniform-grid broad phase (BlockSolver): each block's AABB (lo, hi, grown by the margin), 1 / cell
    size [1/m], the hashed buckets of (block, cell) entries (counting sort: count; start, advanced to each
    bucket's end as bp_fill places the entries), the
    entries, the large blocks (over large_cells cells) tested against every block, and each block's
    body (body[b] = b, or the first part of b's compound block: parts of one body are never paired)."""

    lo: wp.array(dtype=wp.vec3)
    hi: wp.array(dtype=wp.vec3)
    inv_s: float
    large_cells: int
    nbuckets: int
    bucket_count: wp.array(dtype=int)
    bucket_start: wp.array(dtype=int)
    entry_block: wp.array(dtype=int)
    entry_cell: wp.array(dtype=wp.vec3i)
    is_large: wp.array(dtype=int)
    large_list: wp.array(dtype=int)
    body: wp.array(dtype=int)


@wp.struct
class PairList:
    """Candidate pairs of the broad phase (BlockSolver): pairs (A < B), the counters ([0] pairs,
    [1] overflow flags, [2] large blocks, [3] active pairs, [4] active pairs of big blocks), the
    compact list of pairs not certified separated (active) and those of them with more than coop_min
    vertices together (active_big: narrow_phase_coop), each pair's history slots (this step, last
    step: -1 none) and gap [m]."""

    pairs: wp.array(dtype=wp.vec2i)
    counters: wp.array(dtype=int)
    active: wp.array(dtype=int)
    active_big: wp.array(dtype=int)
    slot: wp.array(dtype=int)
    oslot: wp.array(dtype=int)
    gap: wp.array(dtype=float)


# ----------------------------------------------------------------------------------------------
# small helpers
# ----------------------------------------------------------------------------------------------


@wp.func
def two_sum(a: wp.vec3, b: wp.vec3):
    # s = fl(a + b) and its rounding error e, a + b = s + e exactly (Knuth's TwoSum, TAOCP vol. 2
    # §4.2.2; no ordering of |a|, |b| needed). Additions only: FMA contraction cannot change it.
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


@wp.func
def pair_origin(A: int, B: int, x: wp.array(dtype=wp.vec3), block_size: wp.array(dtype=float)):
    # origin of the pair frame of the narrow phase: the centroid of the smaller block rounded down to a
    # power-of-two grid S >= its size. The frame's coordinates near the pair stay within a few S; o is a
    # multiple of S, hence of the float32 spacing at any world coordinate near it, so x_b - o is exact for a
    # centroid near it; and o moves only when the block crosses a grid line, so between such moves a fixed
    # block's vertices have the same pair-frame coordinates, bit for bit, every step
    b = A
    if block_size[B] < block_size[A]:
        b = B
    S = wp.pow(2.0, wp.ceil(wp.log2(wp.max(block_size[b], 1.0e-6))))
    c = x[b]
    return wp.vec3(wp.floor(c[0] / S) * S, wp.floor(c[1] / S) * S, wp.floor(c[2] / S) * S)


@wp.func
def pair_vertex(wv: wp.array(dtype=wp.vec3), dc: wp.vec3, i: int):
    # vertex i in the pair frame: dc + arm_i, dc = x_b - o its block's float32 centroid there (exact for a
    # centroid near o, pair_origin), so the frame's coordinates have float32's relative precision of the
    # pair's size, not of the distance to the origin. In the narrow phase's functions `wv` is the arms
    # array WorldVerts.arm, read with the centroid of the vertex's block (dA, dB, dc)
    return dc + wv[i]


@wp.func
def strain_matrix(s: wp.spatial_vector) -> wp.mat33:
    # symmetric small-strain tensor E from engineering strains (shear gamma = 2 eps_ij)
    return wp.mat33(
        s[0], 0.5 * s[5], 0.5 * s[4],
        0.5 * s[5], s[1], 0.5 * s[3],
        0.5 * s[4], 0.5 * s[3], s[2],
    )


@wp.func
def strain_gen_force(X: wp.vec3, f: wp.vec3) -> wp.spatial_vector:
    # generalised strain force Q_a = f . du/da for u = E X (Shi 1993 first-order displacement)
    return wp.spatial_vector(
        X[0] * f[0],
        X[1] * f[1],
        X[2] * f[2],
        0.5 * (X[2] * f[1] + X[1] * f[2]),
        0.5 * (X[2] * f[0] + X[0] * f[2]),
        0.5 * (X[1] * f[0] + X[0] * f[1]),
    )


@wp.func
def point_velocity(
    b: int,
    p: wp.vec3,
    xb: wp.vec3,
    q: wp.array(dtype=wp.quat),
    v: wp.array(dtype=wp.vec3),
    w: wp.array(dtype=wp.vec3),
    strain_rate: wp.array(dtype=wp.spatial_vector),
    kinds: wp.array(dtype=int),
):
    # v(p) = v + w x r (+ R dE/dt R^T r for deformable blocks), r = p - x_b (p and x_b in one frame)
    r = p - xb
    vel = v[b] + wp.cross(w[b], r)
    if kinds[b] == KIND_DEFORMABLE:
        X = wp.quat_rotate_inv(q[b], r)
        vel = vel + wp.quat_rotate(q[b], strain_matrix(strain_rate[b]) * X)
    return vel


@wp.func
def add_damper(
    A: int,
    B: int,
    p: wp.vec3,
    e: wp.vec3,
    c: float,
    vA: wp.vec3,
    vB: wp.vec3,
    xA: wp.vec3,
    xB: wp.vec3,
    kinds: wp.array(dtype=int),
    loads: BlockLoads,
):
    # dashpot c along unit e at point p between blocks A and B (centroids xA, xB in p's frame), implicit in each block's own velocity:
    # on B, f = -c e e.(v_B(p) - v_A(p)) with v_B(p) = J_B V_B at the end of the step and v_A(p) from the
    # start: the generalised force -C_B V_B + b_B, C_B += c J^T J, b_B += c (e.v_A(p)) J^T, J = [e, r x e]
    if movable(kinds[B]):
        jb = wp.spatial_vector(e, wp.cross(p - xB, e))
        wp.atomic_add(loads.damp_c, B, sym6_outer(c, jb))
        wp.atomic_add(loads.damp_b, B, (c * wp.dot(e, vA)) * jb)
    if movable(kinds[A]):
        ja = wp.spatial_vector(e, wp.cross(p - xA, e))
        wp.atomic_add(loads.damp_c, A, sym6_outer(c, ja))
        wp.atomic_add(loads.damp_b, A, (c * wp.dot(e, vB)) * ja)


@wp.func
def inv_rocking_inertia(b: int, e: wp.vec3, c: wp.vec3, xb: wp.vec3, props: BlockProps, bodies: BlockBodies):
    # 1 / I of block b about the axis e through the point c (parallel axes: e.I_w e + m |e x (x_b - c)|^2,
    # x_b its centroid in c's frame);
    # 0 for a fixed or kinematic block
    if not movable(props.kinds[b]):
        return float(0.0)
    R = wp.quat_to_matrix(bodies.q[b])
    Iw = R * props.inertia_body[b] * wp.transpose(R)
    arm = wp.cross(e, xb - c)
    return 1.0 / (wp.dot(e, Iw * e) + wp.dot(arm, arm) / props.inv_mass[b])


@wp.func
def add_rocking_damper(
    A: int,
    B: int,
    e: wp.vec3,
    c: float,
    wA: wp.vec3,
    wB: wp.vec3,
    kinds: wp.array(dtype=int),
    loads: BlockLoads,
):
    # rotational dashpot c about the axis e between blocks A and B, implicit like add_damper: on B the
    # torque -c e e.(w_B - w_A) with w_B at the end of the step, J = [0, e]
    j = wp.spatial_vector(wp.vec3(0.0, 0.0, 0.0), e)
    if movable(kinds[B]):
        wp.atomic_add(loads.damp_c, B, sym6_outer(c, j))
        wp.atomic_add(loads.damp_b, B, (c * wp.dot(e, wA)) * j)
    if movable(kinds[A]):
        wp.atomic_add(loads.damp_c, A, sym6_outer(c, j))
        wp.atomic_add(loads.damp_b, A, (c * wp.dot(e, wB)) * j)


@wp.func
def solve6(Ain: wp.spatial_matrix, bin: wp.spatial_vector):
    # x = A^-1 b for a symmetric positive definite 6x6 (Gaussian elimination, no pivoting needed)
    A = Ain
    b = bin
    for k in range(6):
        piv = A[k, k]
        for i in range(k + 1, 6):
            f = A[i, k] / piv
            for j in range(k, 6):
                A[i, j] = A[i, j] - f * A[k, j]
            b[i] = b[i] - f * b[k]
    out = wp.spatial_vector()
    for kk in range(6):
        i = 5 - kk
        s = b[i]
        for j in range(i + 1, 6):
            s = s - A[i, j] * out[j]
        out[i] = s / A[i, i]
    return out


@wp.func
def extent_along(n: wp.vec3, start: int, count: int, wv: wp.array(dtype=wp.vec3), dc: wp.vec3):
    # min/max of n.x over a block's vertices (pair frame: x = dc + arm, dc its centroid there) and where
    # they are attained
    lo = float(1.0e30)
    hi = float(-1.0e30)
    ilo = int(start)
    ihi = int(start)
    ndc = wp.dot(n, dc)
    for k in range(count):
        d = wp.dot(n, wv[start + k]) + ndc
        if d < lo:
            lo = d
            ilo = start + k
        if d > hi:
            hi = d
            ihi = start + k
    return lo, ilo, hi, ihi


@wp.func
def signed_gap(n: wp.vec3, sA: int, cA: int, sB: int, cB: int, wv: wp.array(dtype=wp.vec3), dA: wp.vec3, dB: wp.vec3):
    # gap of the plane family with normal +-n: gap(+n) = min_B n.x - max_A n.x; keep the better sign
    loA, ilA, hiA, ihA = extent_along(n, sA, cA, wv, dA)
    loB, ilB, hiB, ihB = extent_along(n, sB, cB, wv, dB)
    gp = loB - hiA
    gm = loA - hiB
    if gm > gp:
        return -n, gm
    return n, gp


@wp.func
def sat_recheck(oslot: int, gap: float, prev_gap: wp.array(dtype=float)):
    """Whether an overlap FCP found (gap < 0) goes through the exhaustive separating-axis check. FCP is a
    local search (Nezami et al. 2004): from a cold start it may stop on a plane that is not the best one, so a
    new contact is checked against every face normal and edge-pair axis. A contact that continues from the
    previous step started from that step's checked plane, and the best plane moves continuously with the
    blocks, so FCP's warm start tracks it; the check is repeated only when the overlap grew by more than
    a tenth in one step (a jump that a stale plane would show). Resting and sliding contacts, the common
    case under water load, skip the O(E_A E_B) walk."""
    if oslot < 0:
        return True
    g0 = prev_gap[oslot]
    if g0 >= 0.0:
        return True
    return gap < 1.1 * g0


@wp.func
def try_plane(
    cand: wp.vec3, best_n: wp.vec3, best_gap: float, sA: int, cA: int, sB: int, cB: int, wv: wp.array(dtype=wp.vec3), dA: wp.vec3, dB: wp.vec3
):
    # keep the candidate plane with the largest gap (smallest overlap), FCP step iii
    ln = wp.length(cand)
    if ln < 1.0e-12:
        return best_n, best_gap
    nn, g = signed_gap(cand / ln, sA, cA, sB, cB, wv, dA, dB)
    if g > best_gap + 1.0e-9:
        return nn, g
    return best_n, best_gap


@wp.func
def he_dest(h: int, he_vertex: wp.array(dtype=int), he_next: wp.array(dtype=int)):
    return he_vertex[he_next[h]]


@wp.func
def face_plane_of_he(
    h: int, wv: wp.array(dtype=wp.vec3), dc: wp.vec3, he_vertex: wp.array(dtype=int), he_next: wp.array(dtype=int)
):
    # outward normal and offset (pair frame; dc: the face's block's centroid there) of the face left of
    # half-edge h (CCW loop: n = (p1-p0) x (p2-p1), from the block's arms)
    h1 = he_next[h]
    p0 = wv[he_vertex[h]]
    p1 = wv[he_vertex[h1]]
    p2 = wv[he_vertex[he_next[h1]]]
    nf = wp.normalize(wp.cross(p1 - p0, p2 - p1))
    return nf, wp.dot(nf, p0) + wp.dot(nf, dc)


@wp.func
def face_normal(h: int, wv: wp.array(dtype=wp.vec3), he_vertex: wp.array(dtype=int), he_next: wp.array(dtype=int)):
    # unit outward normal of the face left of half-edge h (as face_plane_of_he, without the offset)
    h1 = he_next[h]
    p0 = wv[he_vertex[h]]
    p1 = wv[he_vertex[h1]]
    p2 = wv[he_vertex[he_next[h1]]]
    return wp.normalize(wp.cross(p1 - p0, p2 - p1))


@wp.func
def minkowski_edge_face(a: wp.vec3, b: wp.vec3, c: wp.vec3, d: wp.vec3):
    # do the Gauss-map arcs (a, b) of an edge of A and (c, d) of an edge of -B cross? Only then is the
    # edge-pair axis a face normal of the Minkowski difference A - B, i.e. a candidate for the SAT
    # maximum; every other edge-pair axis gives a smaller gap than some face or crossing axis
    # (Gregorius, "The Separating Axis Test between convex polyhedra", GDC 2013). Unit normals.
    bxa = wp.cross(b, a)
    dxc = wp.cross(d, c)
    cba = wp.dot(c, bxa)
    dba = wp.dot(d, bxa)
    adc = wp.dot(a, dxc)
    bdc = wp.dot(b, dxc)
    return cba * dba < 0.0 and adc * bdc < 0.0 and cba * bdc > 0.0


@wp.func
def fcp_candidates(
    a: int,
    b: int,
    best_n: wp.vec3,
    best_gap: float,
    sA: int,
    cA: int,
    sB: int,
    cB: int,
    wv: wp.array(dtype=wp.vec3),
    dA: wp.vec3,
    dB: wp.vec3,
    vertex_out_he: wp.array(dtype=int),
    he_vertex: wp.array(dtype=int),
    he_next: wp.array(dtype=int),
    he_twin: wp.array(dtype=int),
):
    # FCP candidate planes of the vertex pair (A, B): (a) PB of AB, (b) faces at A or B,
    # (c) edge at A x edge at B, (d) one edge at A or B and AB
    xa = pair_vertex(wv, dA, a)
    xb = pair_vertex(wv, dB, b)
    dab = xb - xa
    # (a) perpendicular bisector of AB
    best_n, best_gap = try_plane(dab, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB)
    # walk the half-edges leaving A: h -> twin(prev(h))
    h0 = vertex_out_he[a]
    h = h0
    for ka in range(MAX_VALENCE):
        nf, df = face_plane_of_he(h, wv, dA, he_vertex, he_next)
        best_n, best_gap = try_plane(nf, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB)  # (b)
        ea = wv[he_dest(h, he_vertex, he_next)] - wv[a]
        # (d) plane containing edge ea, as close to the PB as possible: n = AB - (AB.e)e
        le = wp.length(ea)
        if le > 0.0:
            eh = ea / le
            best_n, best_gap = try_plane(dab - wp.dot(dab, eh) * eh, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB)
        # (c) edge at A x edge at B
        g0 = vertex_out_he[b]
        g = g0
        for kb in range(MAX_VALENCE):
            eb = wv[he_dest(g, he_vertex, he_next)] - wv[b]
            c = wp.cross(ea, eb)
            if wp.length(c) > 1.0e-6 * wp.length(ea) * wp.length(eb):
                best_n, best_gap = try_plane(c, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB)
            g = he_next[he_twin[g]]
            if g == g0:
                break
        h = he_next[he_twin[h]]
        if h == h0:
            break
    # faces and edges at B: (b), (d)
    g0 = vertex_out_he[b]
    g = g0
    for kb in range(MAX_VALENCE):
        nf, df = face_plane_of_he(g, wv, dB, he_vertex, he_next)
        best_n, best_gap = try_plane(-nf, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB)
        eb = wv[he_dest(g, he_vertex, he_next)] - wv[b]
        le = wp.length(eb)
        if le > 0.0:
            eh = eb / le
            best_n, best_gap = try_plane(dab - wp.dot(dab, eh) * eh, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB)
        g = he_next[he_twin[g]]
        if g == g0:
            break
    return best_n, best_gap


@wp.func
def column_through(
    p: wp.vec3,
    n: wp.vec3,
    fstart: int,
    fcount: int,
    face_he: wp.array(dtype=int),
    wv: wp.array(dtype=wp.vec3),
    d: wp.vec3,
    he_vertex: wp.array(dtype=int),
    he_next: wp.array(dtype=int),
    tol: float,
):
    # interval [t_lo, t_hi] of the line p + t n inside a convex block (all faces n_f.x <= d_f; pair frame,
    # d: the block's centroid there);
    # hit = False when the line misses it (a lateral face excludes p)
    t_lo = float(-1.0e30)
    t_hi = float(1.0e30)
    hit = int(1)
    for k in range(fcount):
        nf, df = face_plane_of_he(face_he[fstart + k], wv, d, he_vertex, he_next)
        c = wp.dot(nf, n)
        s = df - wp.dot(nf, p)
        if c > 1.0e-4:
            t_hi = wp.min(t_hi, s / c)
        elif c < -1.0e-4:
            t_lo = wp.max(t_lo, s / c)
        else:
            if s < -tol:
                hit = 0
    if t_lo > t_hi + tol:
        hit = 0
    return t_lo, t_hi, hit


@wp.func
def vec64(a: wp.vec3):
    return wp.vec3d(wp.float64(a[0]), wp.float64(a[1]), wp.float64(a[2]))


@wp.func
def column_depth(
    vi: int,
    dv: wp.vec3,
    n: wp.vec3,
    fstart: int,
    fcount: int,
    face_he: wp.array(dtype=int),
    verts: WorldVerts,
    dfc: wp.vec3,
    he_vertex: wp.array(dtype=int),
    he_next: wp.array(dtype=int),
    upper: int,
):
    # the depth of vertex vi (its block's centroid dv in the pair frame) in the convex block of faces fstart ..
    # (centroid dfc) along n: t_hi (upper = 1: a vertex of B in A) or -t_lo (upper = 0: a vertex of A in B) of
    # column_through, formed in float64 from the arms' hi and lo parts (WorldVerts.arm_lo): per face
    # s_f = n_f.(p_f - p), p_f - p = (dfc - dv) + (arm_f - arm_v) + (lo_f - lo_v), the face normal from the
    # arms' differences. column_through's float32 dot products round n_f.p at coordinates ~|p| (3e-8 m at 0.5 m):
    # against a resting corner's depth of ~4e-6 m at the default stiffness, a normal force noise of ~1%, more
    # than the friction margin of a block 0.1 deg above its limit (issue 36, docs/notes.md). The float32 search
    # (which points, hit or not) stays column_through's.
    wv = verts.arm
    wl = verts.arm_lo
    pv = vec64(wv[vi]) + vec64(wl[vi])
    dd = vec64(dfc) - vec64(dv)
    nd = vec64(n)
    t = wp.float64(1.0e30)
    for k in range(fcount):
        h = face_he[fstart + k]
        h1 = he_next[h]
        i0 = he_vertex[h]
        i1 = he_vertex[h1]
        i2 = he_vertex[he_next[h1]]
        p0 = vec64(wv[i0]) + vec64(wl[i0])
        p1 = vec64(wv[i1]) + vec64(wl[i1])
        p2 = vec64(wv[i2]) + vec64(wl[i2])
        nf = wp.normalize(wp.cross(p1 - p0, p2 - p1))
        c = wp.dot(nf, nd)
        sf = wp.dot(nf, dd + (p0 - pv))
        if upper == 1 and c > wp.float64(1.0e-4):
            t = wp.min(t, sf / c)
        elif upper == 0 and c < wp.float64(-1.0e-4):
            t = wp.min(t, -sf / c)
    return wp.float32(t)


@wp.func
def crossing_depth(
    va: int, ua: int, vb: int, ub: int, dA: wp.vec3, dB: wp.vec3, s: float, u: float, n: wp.vec3, verts: WorldVerts
):
    # depth n.(x_a - x_b) of an edge-edge crossing, x_a = p_va + s (p_ua - p_va) on A's edge, x_b likewise on B's,
    # in float64 from the arms' hi and lo parts as column_depth (the float32 difference of two ~0.5 m pair-frame
    # coordinates rounds a depth of ~1e-6 m by ~3e-8)
    wv = verts.arm
    wl = verts.arm_lo
    pa = vec64(wv[va]) + vec64(wl[va])
    qa = vec64(wv[ua]) + vec64(wl[ua])
    pb = vec64(wv[vb]) + vec64(wl[vb])
    qb = vec64(wv[ub]) + vec64(wl[ub])
    sd = wp.float64(s)
    ud = wp.float64(u)
    r = (vec64(dA) - vec64(dB)) + (pa - pb) + sd * (qa - pa) - ud * (qb - pb)
    return wp.float32(wp.dot(vec64(n), r))


@wp.func
def patch_crossing(va: int, ua: int, vb: int, ub: int, dA: wp.vec3, dB: wp.vec3, t1: wp.vec3, t2: wp.vec3, tol: float,
                   verts: WorldVerts):
    # is the crossing of A's edge (va, ua) with B's edge (vb, ub), projected on the common plane (t1, t2), a vertex
    # of the contact patch? Yes when each edge's ends lie on opposite sides of the other edge's line, each farther
    # than tol / 2 from it. The distance is measured across the line, as the vertex test measures its tolerance
    # (column_through: a vertex up to tol outside a face's plane is in): an end within tol / 2 of the other edge's
    # line is that end's vertex, found up to tol outside, so the two tests overlap by tol / 2 at any angle. A window
    # along the edges (the former rule) let two edges collinear to ~1e-6 rad and within a fraction of a um of each
    # other (continuous joints) cross anywhere along them, with the last bits of their 2D determinant: a point at
    # full depth appeared and vanished every few steps (issue 36, docs/notes.md). The distances in float64 from the
    # arms' hi and lo parts, as crossing_depth (in float32 on ~0.5 m pair-frame coordinates an end 0.34 um from the
    # other line was rounded across tol / 2 = 0.43 um in some steps). Returns ok and the crossing's parameters s on
    # A's edge, u on B's, from the ends' signed distances (well conditioned at any angle: s = d(pa) / (d(pa) - d(qa)),
    # Sutherland & Hodgman 1974's intersection of an edge with a clip line).
    wv = verts.arm
    wl = verts.arm_lo
    pa = vec64(wv[va]) + vec64(wl[va])
    qa = vec64(wv[ua]) + vec64(wl[ua])
    pb = vec64(wv[vb]) + vec64(wl[vb])
    qb = vec64(wv[ub]) + vec64(wl[ub])
    e1 = vec64(t1)
    e2 = vec64(t2)
    ea = qa - pa
    eb = qb - pb
    r = (vec64(dA) - vec64(dB)) + (pa - pb)  # pa - pb in the pair frame
    ea0 = wp.dot(ea, e1)
    ea1 = wp.dot(ea, e2)
    eb0 = wp.dot(eb, e1)
    eb1 = wp.dot(eb, e2)
    ra0 = wp.dot(r, e1)
    ra1 = wp.dot(r, e2)
    la = wp.sqrt(ea0 * ea0 + ea1 * ea1)
    lb = wp.sqrt(eb0 * eb0 + eb1 * eb1)
    # |eb| x the signed distances of A's ends from B's line, and |ea| x those of B's ends from A's line
    da0 = eb0 * ra1 - eb1 * ra0
    da1 = da0 + (eb0 * ea1 - eb1 * ea0)
    db0 = ra0 * ea1 - ra1 * ea0  # ea x (pb - pa)
    db1 = db0 + (ea0 * eb1 - ea1 * eb0)
    half = wp.float64(0.5) * wp.float64(tol)
    ha = half * lb
    hb = half * la
    zero = wp.float64(0.0)
    ok = da0 * da1 < zero and db0 * db1 < zero
    ok = ok and wp.abs(da0) > ha and wp.abs(da1) > ha and wp.abs(db0) > hb and wp.abs(db1) > hb
    s = float(0.0)
    u = float(0.0)
    if ok:
        s = wp.float32(da0 / (da0 - da1))
        u = wp.float32(db0 / (db0 - db1))
    return ok, s, u


@wp.func
def fcp_touching(
    n: wp.vec3,
    gap: float,
    tie: float,
    hiA: float,
    loB: float,
    sA: int,
    cA: int,
    sB: int,
    cB: int,
    fsA: int,
    fcA: int,
    fsB: int,
    fcB: int,
    face_he: wp.array(dtype=int),
    wv: wp.array(dtype=wp.vec3),
    dA: wp.vec3,
    dB: wp.vec3,
    he_vertex: wp.array(dtype=int),
    he_next: wp.array(dtype=int),
):
    # certificate that no plane separates better than (n, gap): a closest vertex p of one block whose
    # line along n meets the other block at q = p +- gap n (within tie); any plane's gap is <= |q - p|
    for k in range(cA):
        p = pair_vertex(wv, dA, sA + k)
        if wp.dot(n, p) >= hiA - tie:
            t_lo, t_hi, hit = column_through(p, n, fsB, fcB, face_he, wv, dB, he_vertex, he_next, tie)
            if hit == 1 and t_lo <= gap + tie:
                return int(1)
    for k in range(cB):
        p = pair_vertex(wv, dB, sB + k)
        if wp.dot(n, p) <= loB + tie:
            t_lo, t_hi, hit = column_through(p, n, fsA, fcA, face_he, wv, dA, he_vertex, he_next, tie)
            if hit == 1 and t_hi >= -gap - tie:
                return int(1)
    return int(0)


@wp.func
def fcp_plane(
    n0: wp.vec3,
    tie: float,
    sA: int,
    cA: int,
    sB: int,
    cB: int,
    fsA: int,
    fcA: int,
    fsB: int,
    fcB: int,
    face_he: wp.array(dtype=int),
    wv: wp.array(dtype=wp.vec3),
    dA: wp.vec3,
    dB: wp.vec3,
    vertex_out_he: wp.array(dtype=int),
    he_vertex: wp.array(dtype=int),
    he_next: wp.array(dtype=int),
    he_twin: wp.array(dtype=int),
):
    # Fast Common Plane (Nezami et al. 2004): iterate closest vertices A, B and their candidate planes
    # until the closest pair repeats. Face and edge-edge planes leave a face or edge of each block
    # closest, its vertices tied (float32 rounding picks one), and the candidates of that one vertex
    # miss those at the others (e.g. the edge-edge plane of a face edge not at it): FCP stopped below
    # the optimum. So at a separating fixed point (gap > 0) not certified by fcp_touching, the
    # candidates of every pair of closest vertices (within tie) are tried, and FCP goes on if one is
    # better. gap(n) = min_B n.x - max_A n.x is concave in n, so for separated blocks the final fixed
    # point is the exact gap. Overlaps stop at the first fixed point: narrow_phase's SAT fallback
    # checks them (and resting face contacts would pay |face|^2 pairs every step).
    best_n, best_gap = signed_gap(n0, sA, cA, sB, cB, wv, dA, dB)
    a = int(-1)
    b = int(-1)
    for it in range(FCP_MAX_ITER):
        n = best_n
        gap0 = best_gap
        loA, ilA, hiA, ihA = extent_along(n, sA, cA, wv, dA)
        loB, ilB, hiB, ihB = extent_along(n, sB, cB, wv, dB)
        if ihA != a or ilB != b:
            a = ihA
            b = ilB
            best_n, best_gap = fcp_candidates(
                a, b, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB, vertex_out_he, he_vertex, he_next, he_twin
            )
        else:
            if gap0 <= 0.0:
                break
            touching = fcp_touching(n, gap0, tie, hiA, loB, sA, cA, sB, cB, fsA, fcA, fsB, fcB, face_he, wv, dA, dB,
                                    he_vertex, he_next)
            if touching == 1:
                break
            for ka in range(cA):
                va = sA + ka
                if wp.dot(n, pair_vertex(wv, dA, va)) >= hiA - tie:
                    for kb in range(cB):
                        vb = sB + kb
                        if wp.dot(n, pair_vertex(wv, dB, vb)) <= loB + tie:
                            best_n, best_gap = fcp_candidates(
                                va, vb, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB,
                                vertex_out_he, he_vertex, he_next, he_twin,
                            )
            if best_gap <= gap0:
                break
    return best_n, best_gap


@wp.func
def hash_cell(cx: int, cy: int, cz: int, nbuckets: int):
    h = (wp.uint32(cx) * wp.uint32(73856093)) ^ (wp.uint32(cy) * wp.uint32(19349663)) ^ (wp.uint32(cz) * wp.uint32(83492791))
    return int(h & wp.uint32(nbuckets - 1))


@wp.func
def hash_key(key: wp.int64, cap: int):
    h = wp.uint64(key) * wp.uint64(11400714819323198485)  # Fibonacci hashing
    return int((h >> wp.uint64(33)) % wp.uint64(cap))  # any capacity (the tables are sized from the live pairs)


@wp.func
def table_find(key: wp.int64, keys: wp.array(dtype=wp.int64), cap: int):
    # open addressing, linear probing; -1 = empty slot
    s = hash_key(key, cap)
    for k in range(cap):
        kk = keys[s]
        if kk == key:
            return s
        if kk == wp.int64(-1):
            return -1
        s = s + 1
        if s == cap:
            s = 0
    return -1


@wp.func
def table_insert(key: wp.int64, keys: wp.array(dtype=wp.int64), cap: int):
    s = hash_key(key, cap)
    for k in range(cap):
        old = wp.atomic_cas(keys, s, wp.int64(-1), key)
        if old == wp.int64(-1) or old == key:
            return s
        s = s + 1
        if s == cap:
            s = 0
    return -1


@wp.func
def movable(kind: int):
    return kind == KIND_RIGID or kind == KIND_DEFORMABLE


# ----------------------------------------------------------------------------------------------
# pose -> world vertices, AABBs
# ----------------------------------------------------------------------------------------------


@wp.kernel
def world_vertices(
    body_verts: wp.array(dtype=wp.vec3),
    vert_block: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    q: wp.array(dtype=wp.quat),
    strain: wp.array(dtype=wp.spatial_vector),
    kinds: wp.array(dtype=int),
    out: wp.array(dtype=wp.vec3),
):
    # x_world = x_c + R (X + E X)  (Shi's first-order displacement on top of the rigid motion), float32 from
    # the float32 centroid (the coupling's view; the block solver's own: block_world_vertices)
    v = wp.tid()
    b = vert_block[v]
    X = body_verts[v]
    if kinds[b] == KIND_DEFORMABLE:
        X = X + strain_matrix(strain[b]) * X
    out[v] = x[b] + wp.quat_rotate(q[b], X)


@wp.func
def vertex_arm(x_lo: wp.vec3, qh: wp.quat, ql: wp.quat, X: wp.vec3):
    # a vertex's arm from its block's float32 centroid, x_lo + R(q + q_lo) X, formed in float64 from the compensated
    # orientation and split into its float32 value and the rest (hi, lo). With R from the rounded q alone, every
    # change of q's last bit moved the arm of a 0.5 m vertex by ~6e-8 m (R's rounding, |X| x 2 ulps of q) while the
    # block had turned by ~1e-9 rad: a resting block's corner forces jumped by k_n x 6e-8 (~50 N at the default
    # stiffness of a 1 m block) as its q flickered, and at a small friction margin the jumps drove a limit cycle
    # of twist and rocking that ratcheted the lightly loaded corners' springs down (issue 36, docs/notes.md)
    q = wp.quatd(wp.float64(qh[0]) + wp.float64(ql[0]), wp.float64(qh[1]) + wp.float64(ql[1]),
                 wp.float64(qh[2]) + wp.float64(ql[2]), wp.float64(qh[3]) + wp.float64(ql[3]))
    Xd = wp.vec3d(wp.float64(X[0]), wp.float64(X[1]), wp.float64(X[2]))
    r = wp.quat_rotate(q, Xd) + wp.vec3d(wp.float64(x_lo[0]), wp.float64(x_lo[1]), wp.float64(x_lo[2]))
    hi = wp.vec3(wp.float32(r[0]), wp.float32(r[1]), wp.float32(r[2]))
    lo = wp.vec3(wp.float32(r[0] - wp.float64(hi[0])), wp.float32(r[1] - wp.float64(hi[1])),
                 wp.float32(r[2] - wp.float64(hi[2])))
    return hi, lo


@wp.kernel
def block_world_vertices(
    body_verts: wp.array(dtype=wp.vec3),
    vert_block: wp.array(dtype=int),
    bodies: BlockBodies,
    kinds: wp.array(dtype=int),
    out: WorldVerts,
):
    """The block solver's world vertices x_world = (x + x_lo) + R (X + E X) (WorldVerts): the arm
    x_lo + R (X + E X) from the float32 centroid x, R from the compensated orientation q + q_lo (vertex_arm)."""
    v = wp.tid()
    b = vert_block[v]
    X = body_verts[v]
    if kinds[b] == KIND_DEFORMABLE:
        X = X + strain_matrix(bodies.strain[b]) * X
    hi, lo = vertex_arm(bodies.x_lo[b], bodies.q[b], bodies.q_lo[b], X)
    out.arm[v] = hi
    out.arm_lo[v] = lo


@wp.kernel
def pose_motion(
    body_verts: wp.array(dtype=wp.vec3),
    kinds: wp.array(dtype=int),
    vert_start: wp.array(dtype=int),
    vert_count: wp.array(dtype=int),
    bodies: BlockBodies,
    arm: wp.array(dtype=wp.vec3),
    x_ref: wp.array(dtype=wp.vec3),
    q_ref: wp.array(dtype=wp.quat),
    q_lo_ref: wp.array(dtype=wp.quat),
    x_lo_ref: wp.array(dtype=wp.vec3),
    strain_ref: wp.array(dtype=wp.spatial_vector),
    dx: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
):
    # motion of each block since the last narrow phase (the poses of the history table's planes):
    # every world vertex moved by dx[b] + dev with |dev| <= rho[b] (rotation, strain, and 2 ulps of
    # the coordinates for float32 round-off); then the reference becomes the current pose. The reference
    # vertices are not stored: they are rebuilt from the reference pose (x, q, q_lo, x_lo, strain) by the same
    # operations as block_world_vertices, so they equal the world vertices of that step bit for bit.
    # A zero q_ref (no reference yet: the first step, or a checkpoint from before format 4) takes the
    # reference vertices at the origin, which certifies nothing.
    b = wp.tid()
    s = vert_start[b]
    xb = bodies.x[b]
    xr = x_ref[b]
    d = xb - xr
    qr = q_ref[b]
    have_ref = qr[0] != 0.0 or qr[1] != 0.0 or qr[2] != 0.0 or qr[3] != 0.0
    deformable = kinds[b] == KIND_DEFORMABLE
    lr = x_lo_ref[b]
    r = float(0.0)
    amax = float(0.0)
    for k in range(vert_count[b]):
        p = xb + arm[s + k]  # the float32 world vertex
        pr = wp.vec3(0.0, 0.0, 0.0)
        if have_ref:
            X = body_verts[s + k]
            if deformable:
                X = X + strain_matrix(strain_ref[b]) * X
            ar, alo = vertex_arm(lr, qr, q_lo_ref[b], X)
            pr = xr + ar
        r = wp.max(r, wp.length(p - pr - d))
        amax = wp.max(amax, wp.max(wp.abs(p[0]), wp.max(wp.abs(p[1]), wp.abs(p[2]))))
    dx[b] = d
    rho[b] = r + 2.4e-7 * amax
    x_ref[b] = xb
    q_ref[b] = bodies.q[b]
    q_lo_ref[b] = bodies.q_lo[b]
    x_lo_ref[b] = bodies.x_lo[b]
    if deformable:
        strain_ref[b] = bodies.strain[b]


@wp.kernel
def block_aabbs(
    x: wp.array(dtype=wp.vec3),
    arm: wp.array(dtype=wp.vec3),
    vert_start: wp.array(dtype=int),
    vert_count: wp.array(dtype=int),
    margin: float,
    lo: wp.array(dtype=wp.vec3),
    hi: wp.array(dtype=wp.vec3),
    contact_count: wp.array(dtype=int),
):
    # each block's AABB over its float32 world vertices x + arm, grown by the margin
    b = wp.tid()
    s = vert_start[b]
    xb = x[b]
    l = xb + arm[s]
    h = l
    for k in range(1, vert_count[b]):
        p = xb + arm[s + k]
        l = wp.min(l, p)
        h = wp.max(h, p)
    m = wp.vec3(margin, margin, margin)
    lo[b] = l - m
    hi[b] = h + m
    contact_count[b] = 0


@wp.kernel
def aabbs_left_pair_boxes(
    lo: wp.array(dtype=wp.vec3),
    hi: wp.array(dtype=wp.vec3),
    lo_bp: wp.array(dtype=wp.vec3),
    hi_bp: wp.array(dtype=wp.vec3),
    half_margin: float,
    moved: wp.array(dtype=int),
):
    """moved[0] = 1 when a block's AABB grown by margin/2 (lo, hi: grown by margin) is no longer inside
    the box grown by margin that the last broad phase used (lo_bp, hi_bp): while none is, every pair whose
    AABBs grown by margin/2 overlap is still in the pair list, and the broad phase can be skipped."""
    b = wp.tid()
    l = lo[b] + wp.vec3(half_margin)
    h = hi[b] - wp.vec3(half_margin)
    lb = lo_bp[b]
    hb = hi_bp[b]
    if l[0] < lb[0] or l[1] < lb[1] or l[2] < lb[2] or h[0] > hb[0] or h[1] > hb[1] or h[2] > hb[2]:
        moved[0] = 1


# ----------------------------------------------------------------------------------------------
# broad phase: uniform grid (cell S ~ 1.5 D50), counting sort into hashed buckets
# ----------------------------------------------------------------------------------------------


@wp.func
def cell_range(l: wp.vec3, h: wp.vec3, inv_s: float):
    c0 = wp.vec3i(int(wp.floor(l[0] * inv_s)), int(wp.floor(l[1] * inv_s)), int(wp.floor(l[2] * inv_s)))
    c1 = wp.vec3i(int(wp.floor(h[0] * inv_s)), int(wp.floor(h[1] * inv_s)), int(wp.floor(h[2] * inv_s)))
    return c0, c1


@wp.kernel
def bp_count(grid: BroadPhaseGrid, counters: wp.array(dtype=int)):
    # counters: [0] pairs, [1] overflow flags, [2] large blocks
    large_cells = grid.large_cells
    large_list = grid.large_list
    b = wp.tid()
    c0, c1 = cell_range(grid.lo[b], grid.hi[b], grid.inv_s)
    nx = c1[0] - c0[0] + 1
    ny = c1[1] - c0[1] + 1
    nz = c1[2] - c0[2] + 1
    # blocks spanning many cells (floors, slopes) are tested against all blocks instead
    if nx > large_cells or ny > large_cells or nz > large_cells or nx * ny * nz > large_cells:
        grid.is_large[b] = 1
        k = wp.atomic_add(counters, 2, 1)
        if k < large_list.shape[0]:
            large_list[k] = b
        else:
            wp.atomic_or(counters, 1, FLAG_LARGE_OVERFLOW)
        return
    grid.is_large[b] = 0
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                hb = hash_cell(c0[0] + i, c0[1] + j, c0[2] + k, grid.nbuckets)
                wp.atomic_add(grid.bucket_count, hb, 1)


@wp.kernel
def bp_fill(grid: BroadPhaseGrid, counters: wp.array(dtype=int)):
    entry_block = grid.entry_block
    b = wp.tid()
    if grid.is_large[b] != 0:
        return
    c0, c1 = cell_range(grid.lo[b], grid.hi[b], grid.inv_s)
    for i in range(c1[0] - c0[0] + 1):
        for j in range(c1[1] - c0[1] + 1):
            for k in range(c1[2] - c0[2] + 1):
                c = wp.vec3i(c0[0] + i, c0[1] + j, c0[2] + k)
                hb = hash_cell(c[0], c[1], c[2], grid.nbuckets)
                e = wp.atomic_add(grid.bucket_start, hb, 1)  # start -> end of the bucket once filled
                if e < entry_block.shape[0]:
                    entry_block[e] = b
                    grid.entry_cell[e] = c
                else:
                    wp.atomic_or(counters, 1, FLAG_ENTRY_OVERFLOW)


@wp.func
def aabb_overlap(la: wp.vec3, ha: wp.vec3, lb: wp.vec3, hb: wp.vec3):
    return la[0] <= hb[0] and lb[0] <= ha[0] and la[1] <= hb[1] and lb[1] <= ha[1] and la[2] <= hb[2] and lb[2] <= ha[2]


@wp.func
def emit_pair(i: int, j: int, pairs: wp.array(dtype=wp.vec2i), counters: wp.array(dtype=int)):
    k = wp.atomic_add(counters, 0, 1)
    if k < pairs.shape[0]:
        pairs[k] = wp.vec2i(wp.min(i, j), wp.max(i, j))
    else:
        wp.atomic_or(counters, 1, FLAG_PAIR_OVERFLOW)


@wp.kernel
def bp_pairs(grid: BroadPhaseGrid, kinds: wp.array(dtype=int), pl: PairList):
    # one thread per (block, cell) entry e1, against the later entries of its bucket (a bucket's
    # entries are contiguous after the counting sort); a pair is emitted only from the cell holding
    # the min corner of the AABB overlap, so it appears exactly once however many cells the two
    # blocks share. (One thread per bucket looped over ~n^2/2 entry pairs serially: few, long threads.)
    lo = grid.lo
    hi = grid.hi
    inv_s = grid.inv_s
    nbuckets = grid.nbuckets
    bucket_start = grid.bucket_start
    entry_block = grid.entry_block
    entry_cell = grid.entry_cell
    e1 = wp.tid()
    ntot = bucket_start[nbuckets - 1]  # bp_fill left each bucket's end in bucket_start
    if e1 >= wp.min(ntot, entry_block.shape[0]):
        return
    ci = entry_cell[e1]
    hb = hash_cell(ci[0], ci[1], ci[2], nbuckets)
    end = bucket_start[hb]
    if end > entry_block.shape[0]:
        return
    i = entry_block[e1]
    li = lo[i]
    hi_i = hi[i]
    mov_i = movable(kinds[i])
    body_i = grid.body[i]
    for e2 in range(e1 + 1, end):
        j = entry_block[e2]
        if grid.body[j] == body_i:  # j == i, or two parts of one compound block
            continue
        cj = entry_cell[e2]
        if ci[0] != cj[0] or ci[1] != cj[1] or ci[2] != cj[2]:
            continue
        if not (mov_i or movable(kinds[j])):
            continue
        lj = lo[j]
        if not aabb_overlap(li, hi_i, lj, hi[j]):
            continue
        m = wp.max(li, lj)
        c0, c1 = cell_range(m, m, inv_s)
        if c0[0] == ci[0] and c0[1] == ci[1] and c0[2] == ci[2]:
            emit_pair(i, j, pl.pairs, pl.counters)


@wp.kernel
def bp_large_pairs(grid: BroadPhaseGrid, kinds: wp.array(dtype=int), pl: PairList):
    # large block L (from the list) against every block j by AABB
    lo = grid.lo
    hi = grid.hi
    large_list = grid.large_list
    k, j = wp.tid()
    if k >= wp.min(pl.counters[2], large_list.shape[0]):
        return
    L = large_list[k]
    if grid.body[j] == grid.body[L]:  # j == L, or two parts of one compound block
        return
    if grid.is_large[j] != 0 and j < L:
        return
    if not (movable(kinds[L]) or movable(kinds[j])):
        return
    if aabb_overlap(lo[L], hi[L], lo[j], hi[j]):
        emit_pair(L, j, pl.pairs, pl.counters)


# ----------------------------------------------------------------------------------------------
# narrow phase (FCP) + contact forces, one thread per candidate pair
# ----------------------------------------------------------------------------------------------


@wp.func
def contact_tangent(n: wp.vec3):
    # a unit tangent of the contact plane (t1; t2 = n x t1)
    t1 = wp.vec3(1.0, 0.0, 0.0)
    if wp.abs(n[0]) > 0.6:
        t1 = wp.vec3(0.0, 1.0, 0.0)
    return wp.normalize(t1 - wp.dot(t1, n) * n)


@wp.func
def add_contact(
    nc: int,
    p: wp.vec3,
    depth: float,
    ka: int,
    kb: int,
    dup_tol: float,
    px: PointCoord,
    py: PointCoord,
    pz: PointCoord,
    pd: PointCoord,
    pka: PointKey,
    pkb: PointKey,
):
    # append a contact point to the pair's thread-local list unless one already sits within dup_tol
    # (coincident features)
    for k in range(nc):
        if wp.length(wp.vec3(px[k], py[k], pz[k]) - p) < dup_tol:
            return nc, px, py, pz, pd, pka, pkb
    if nc >= K_MAX:
        return nc, px, py, pz, pd, pka, pkb
    px[nc] = p[0]
    py[nc] = p[1]
    pz[nc] = p[2]
    pd[nc] = depth
    pka[nc] = ka
    pkb[nc] = kb
    return nc + 1, px, py, pz, pd, pka, pkb


@wp.kernel
def narrow_screen(
    pl: PairList,
    nblocks: int,
    screen: int,
    coop_min: int,
    verts: WorldVerts,
    topo: BlockTopology,
    bodies: BlockBodies,
    dx: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    prev: ContactTable,
    cur: ContactTable,
):
    # one thread per candidate pair: history slots, then the separation certificate. The warm-start
    # plane (last step's common plane, else the PB of the centroids) is FCP's step i; if it already
    # separates the world vertices of both blocks (gap > 0) the pair has no contact this step (FCP only
    # increases the gap), so FCP and contact generation are skipped: the pair is stored exactly like a
    # separated pair (plane kept, nc = 0, no shear carried), its gap is a lower bound of FCP's.
    # The other pairs go to the compact list `active` (count in counters[3]) for narrow_phase.
    # screen = 0 (diagnostics, detect()): every pair goes to the list and gets FCP's gap.
    pairs = pl.pairs
    counters = pl.counters
    x = bodies.x
    tid = wp.tid()
    if tid >= wp.min(counters[0], pairs.shape[0]):
        return
    A = pairs[tid][0]
    B = pairs[tid][1]
    o = pair_origin(A, B, x, topo.block_size)  # the pair frame (pair_vertex): the centroids there
    dA = x[A] - o
    dB = x[B] - o
    wv = verts.arm  # each vertex relative to its block's float32 centroid
    key = wp.int64(A) * wp.int64(nblocks) + wp.int64(B)
    slot = table_insert(key, cur.keys, cur.keys.shape[0])
    pl.slot[tid] = slot
    if slot < 0:
        wp.atomic_or(counters, 1, FLAG_CONTACT_OVERFLOW)
        return
    oslot = table_find(key, prev.keys, prev.keys.shape[0])
    pl.oslot[tid] = oslot
    if screen != 0:
        if oslot >= 0:
            # last step's plane had gap G at the reference poses (prev.gapb, exact or a lower bound);
            # with vertices moved by dx + dev (|dev| <= rho) its gap is now >= G + n.(dx_B - dx_A)
            # - rho_A - rho_B: if that is > 0 the pair is still separated, no vertex is read
            nb = prev.normal[oslot]
            gb = prev.gapb[oslot] + wp.dot(nb, dx[B] - dx[A]) - rho[A] - rho[B]
            if gb > 0.0:
                cur.normal[slot] = nb
                cur.gapb[slot] = gb
                pl.gap[tid] = gb
                cur.nc[slot] = 0
                cur.pstart[slot] = 0
                return
        n0 = x[B] - x[A]
        if oslot >= 0:
            n0 = prev.normal[oslot]
        if wp.length(n0) < 1.0e-12:
            n0 = wp.vec3(0.0, 0.0, 1.0)
        n, gap = signed_gap(wp.normalize(n0), topo.vert_start[A], topo.vert_count[A], topo.vert_start[B], topo.vert_count[B], wv, dA, dB)
        if gap > 0.0:
            cur.normal[slot] = n
            cur.gapb[slot] = gap
            pl.gap[tid] = gap
            cur.nc[slot] = 0
            cur.pstart[slot] = 0
            return
    k = wp.atomic_add(counters, 3, 1)
    pl.active[k] = tid
    if topo.vert_count[A] + topo.vert_count[B] > coop_min:
        kb = wp.atomic_add(counters, 4, 1)
        pl.active_big[kb] = tid


@wp.kernel
def narrow_phase(
    pl: PairList,
    coop_min: int,
    verts: WorldVerts,
    topo: BlockTopology,
    bodies: BlockBodies,
    prev: ContactTable,
    cur: ContactTable,
):
    """FCP narrow phase of the pairs of small blocks (vert_count[A] + vert_count[B] <= coop_min; the
    others: narrow_phase_coop, the same algorithm): world vertices wv, previous contact history `prev`
    (read), this step's `cur` (written: plane, gap, contact points); contact_forces then acts on them."""
    # local names for the grouped arrays (the arithmetic below reads them as before)
    vert_start = topo.vert_start
    vert_count = topo.vert_count
    face_start = topo.face_start
    face_count = topo.face_count
    face_he = topo.face_he
    vertex_out_he = topo.vertex_out_he
    he_vertex = topo.he_vertex
    he_next = topo.he_next
    he_twin = topo.he_twin
    block_size = topo.block_size
    x = bodies.x
    new_pos = cur.pos
    new_depth = cur.depth
    new_ckey = cur.ckey
    # one thread per pair of the compact list from narrow_screen (pairs not certified separated)
    li = wp.tid()
    if li >= pl.counters[3]:
        return
    tid = pl.active[li]
    A = pl.pairs[tid][0]
    B = pl.pairs[tid][1]
    o = pair_origin(A, B, x, block_size)  # the pair frame (pair_vertex): the centroids there
    dA = x[A] - o
    dB = x[B] - o
    wv = verts.arm  # each vertex relative to its block's float32 centroid
    slot = pl.slot[tid]
    oslot = pl.oslot[tid]
    sA = vert_start[A]
    cA = vert_count[A]
    sB = vert_start[B]
    cB = vert_count[B]
    if cA + cB > coop_min:
        return  # narrow_phase_coop
    # FCP step i: warm start from last step's plane, else PB of the centroids
    n0 = x[B] - x[A]
    if oslot >= 0:
        n0 = prev.normal[oslot]
    if wp.length(n0) < 1.0e-12:
        n0 = wp.vec3(0.0, 0.0, 1.0)
    # FCP's tie tolerance for closest vertices: float32 rounding of n.x (~1e-7 (|x| + size)) well inside
    tie = 1.0e-6 * (block_size[A] + block_size[B] + wp.length(dA) + wp.length(dB))
    fsA = face_start[A]
    fcA = face_count[A]
    fsB = face_start[B]
    fcB = face_count[B]
    n, gap = fcp_plane(wp.normalize(n0), tie, sA, cA, sB, cB, fsA, fcA, fsB, fcB, face_he, wv, dA, dB,
                       vertex_out_he, he_vertex, he_next, he_twin)
    if gap < 0.0 and sat_recheck(oslot, gap, prev.gapb):
        # FCP is a local search: before accepting an overlap, also try every face normal of both
        # blocks (separating-axis faces); if one separates better, iterate FCP again from it
        n1 = n
        g1 = gap
        for k in range(face_count[A]):
            nf, df = face_plane_of_he(face_he[face_start[A] + k], wv, dA, he_vertex, he_next)
            n1, g1 = try_plane(nf, n1, g1, sA, cA, sB, cB, wv, dA, dB)
        for k in range(face_count[B]):
            nf, df = face_plane_of_he(face_he[face_start[B] + k], wv, dB, he_vertex, he_next)
            n1, g1 = try_plane(nf, n1, g1, sA, cA, sB, cB, wv, dA, dB)
        # and every edge-pair axis (exact SAT) when the blocks are small enough (E_A E_B <= 2048)
        if (cA + face_count[A] - 2) * (cB + face_count[B] - 2) <= SAT_EDGE_PAIRS:
            for ka in range(cA):
                va = sA + ka
                h0 = vertex_out_he[va]
                h = h0
                for ia in range(MAX_VALENCE):
                    ua = he_dest(h, he_vertex, he_next)
                    if va < ua:
                        ea = wv[ua] - wv[va]
                        # normals of the two faces at edge (va, ua): its arc on A's Gauss map
                        fa1 = face_normal(h, wv, he_vertex, he_next)
                        fa2 = face_normal(he_twin[h], wv, he_vertex, he_next)
                        for kb in range(cB):
                            vb = sB + kb
                            g0 = vertex_out_he[vb]
                            gg = g0
                            for ib in range(MAX_VALENCE):
                                ub = he_dest(gg, he_vertex, he_next)
                                if vb < ub:
                                    ax = wp.cross(ea, wv[ub] - wv[vb])
                                    if wp.length(ax) > 1.0e-6 * wp.length(ea) * wp.length(wv[ub] - wv[vb]):
                                        fb1 = face_normal(gg, wv, he_vertex, he_next)
                                        fb2 = face_normal(he_twin[gg], wv, he_vertex, he_next)
                                        if minkowski_edge_face(fa1, fa2, -fb1, -fb2):
                                            n1, g1 = try_plane(ax, n1, g1, sA, cA, sB, cB, wv, dA, dB)
                                gg = he_next[he_twin[gg]]
                                if gg == g0:
                                    break
                    h = he_next[he_twin[h]]
                    if h == h0:
                        break
        if g1 > gap + 1.0e-7:
            n, gap = fcp_plane(n1, tie, sA, cA, sB, cB, fsA, fcA, fsB, fcB, face_he, wv, dA, dB,
                               vertex_out_he, he_vertex, he_next, he_twin)
    cur.normal[slot] = n
    cur.gapb[slot] = gap
    pl.gap[tid] = gap
    cur.nc[slot] = 0
    cur.pstart[slot] = 0
    if gap > 0.0:
        return
    size = wp.min(block_size[A], block_size[B])
    tol = 1.0e-6 * size
    dup_tol = 1.0e-4 * size
    over = -gap  # total overlap along n: max_A n.x - min_B n.x
    loA, ilA, hiA, ihA = extent_along(n, sA, cA, wv, dA)
    loB, ilB, hiB, ihB = extent_along(n, sB, cB, wv, dB)
    nc = int(0)
    px = PointCoord()
    py = PointCoord()
    pz = PointCoord()
    pd = PointCoord()
    pka = PointKey()
    pkb = PointKey()
    # vertices of A that may lie inside B: column through the vertex along n meets B's bottom
    for k in range(cA):
        va = sA + k
        pa = pair_vertex(wv, dA, va)
        if wp.dot(n, pa) >= loB - tol:
            t_lo, t_hi, hit = column_through(pa, n, face_start[B], face_count[B], face_he, wv, dB, he_vertex, he_next, tol)
            d = float(0.0)
            if hit == 1:
                d = wp.min(column_depth(va, dA, n, face_start[B], face_count[B], face_he, verts, dB, he_vertex, he_next, 0),
                           over + tol)
            if hit == 1 and d > 0.0:
                nc, px, py, pz, pd, pka, pkb = add_contact(nc, pa + (0.5 * t_lo) * n, d, va, -1, dup_tol, px, py, pz, pd, pka, pkb)
    # vertices of B that may lie inside A
    for k in range(cB):
        vb = sB + k
        pb = pair_vertex(wv, dB, vb)
        if wp.dot(n, pb) <= hiA + tol:
            t_lo, t_hi, hit = column_through(pb, n, face_start[A], face_count[A], face_he, wv, dA, he_vertex, he_next, tol)
            d = float(0.0)
            if hit == 1:
                d = wp.min(column_depth(vb, dB, n, face_start[A], face_count[A], face_he, verts, dA, he_vertex, he_next, 1),
                           over + tol)
            if hit == 1 and d > 0.0:
                nc, px, py, pz, pd, pka, pkb = add_contact(nc, pb + (0.5 * t_hi) * n, d, -1, vb, dup_tol, px, py, pz, pd, pka, pkb)
    # edge-edge crossings of the two contact patches, projected on the plane
    t1 = contact_tangent(n)
    t2 = wp.cross(n, t1)
    for k in range(cA):
        va = sA + k
        pa = pair_vertex(wv, dA, va)
        if wp.dot(n, pa) < loB - tol:
            continue
        h0 = vertex_out_he[va]
        h = h0
        for ka in range(MAX_VALENCE):
            ua = he_dest(h, he_vertex, he_next)
            qa = pair_vertex(wv, dA, ua)
            if wp.dot(n, qa) < loB - tol or va < ua:
                # edge (va, ua) once: from its lower end if both ends are in the patch
                for kk in range(cB):
                    vb = sB + kk
                    pb = pair_vertex(wv, dB, vb)
                    if wp.dot(n, pb) > hiA + tol:
                        continue
                    g0 = vertex_out_he[vb]
                    g = g0
                    for kb in range(MAX_VALENCE):
                        ub = he_dest(g, he_vertex, he_next)
                        qb = pair_vertex(wv, dB, ub)
                        if wp.dot(n, qb) > hiA + tol or vb < ub:
                            # a vertex of the patch where the projected edges cross (patch_crossing)
                            ok, s, u = patch_crossing(va, ua, vb, ub, dA, dB, t1, t2, tol, verts)
                            if ok:
                                xa_ = pa + s * (qa - pa)
                                xb_ = pb + u * (qb - pb)
                                d = wp.min(crossing_depth(va, ua, vb, ub, dA, dB, s, u, n, verts), over + tol)
                                if d > 0.0:
                                    ha = wp.min(h, he_twin[h])
                                    hb2 = wp.min(g, he_twin[g])
                                    nc, px, py, pz, pd, pka, pkb = add_contact(
                                        nc, 0.5 * (xa_ + xb_), d, ha, hb2, dup_tol, px, py, pz, pd, pka, pkb)
                        g = he_next[he_twin[g]]
                        if g == g0:
                            break
            h = he_next[he_twin[h]]
            if h == h0:
                break
    if nc == 0:
        return
    # exactly nc entries of the point pool; past its end: none (the host grows the pool and redoes the step)
    base = wp.atomic_add(cur.pcount, 0, nc)
    if base + nc > new_pos.shape[0]:
        return
    oA = dA + bodies.x_lo[A]  # A's centroid x + x_lo in the pair frame
    for k in range(nc):
        new_pos[base + k] = wp.vec3(px[k], py[k], pz[k]) - oA  # relative to A's centroid (contact_forces)
        new_depth[base + k] = pd[k]
        new_ckey[base + k] = wp.vec2i(pka[k], pkb[k])
    cur.nc[slot] = nc
    cur.pstart[slot] = base


@wp.kernel
def set_block_clock(clock: wp.array(dtype=float), t_next: float, dt: float):
    """The block step's clock on the device: [end time of the step, step length]."""
    clock[0] = t_next
    clock[1] = dt


@wp.kernel
def advance_block_clock(clock: wp.array(dtype=float)):
    """Next sub-step of equal length (inside a captured CUDA graph of block sub-steps)."""
    clock[0] = clock[0] + clock[1]


@wp.func
def kinematic_last_step(b: int, bodies: BlockBodies, kinds: wp.array(dtype=int)):
    # what the contact springs integrate for block b beyond point_velocity (which reads v): a kinematic block's
    # displacement over its last step / dt (v_step) in place of its prescribed velocity at the step's end (v), so
    # that a stuck spring records exactly the relative displacement (the sum of v_step dt is the motion, the sum of
    # v dt is not); zero for other blocks, whose v is already the velocity that moved them over the last step
    dv = wp.vec3(0.0, 0.0, 0.0)
    if kinds[b] == KIND_KINEMATIC:
        dv = bodies.v_step[b] - bodies.v[b]
    return dv


@wp.func
def clock_of(clock: wp.array(dtype=float), b: int, j: int):
    """Entry j of block b's clock [t_next, dt, friction locked]: clock[j] (one clock for all blocks), or
    clock[3 b + j] where the array holds one clock per block (a batch of scenarios with their own steps:
    rockwave/sim/batch.py; a block whose scenario has finished its sub-steps has dt = 0 and does not move)."""
    if clock.shape[0] > 3:
        return clock[3 * b + j]
    return clock[j]


@wp.func
def kinematic_step_change(b: int, clock: wp.array(dtype=float), motion: BlockMotion, bodies: BlockBodies,
                          kinds: wp.array(dtype=int)):
    # a kinematic block's velocity over the coming step (its prescribed displacement from x + x_lo to
    # base_x + u(t_next), over dt: what integrate_blocks will move it by) minus the one it moved with over the last
    # (v_step); zero for other blocks
    dv = wp.vec3(0.0, 0.0, 0.0)
    dt = clock_of(clock, b, 1)
    if kinds[b] == KIND_KINEMATIC and dt > 0.0:
        u, uv = kinematic_motion(b, clock_of(clock, b, 0), motion)
        xs, xl = two_sum(motion.base_x[b], u)
        dv = ((xs - bodies.x[b]) + (xl - bodies.x_lo[b])) / dt - bodies.v_step[b]
    return dv


@wp.kernel
def contact_forces(
    pl: PairList,
    clock: wp.array(dtype=float),
    g_mag: float,
    props: BlockProps,
    mat: BlockMaterial,
    motion: BlockMotion,
    bodies: BlockBodies,
    prev: ContactTable,
    cur: ContactTable,
    loads: BlockLoads,
    block_size: wp.array(dtype=float),
):
    """Contact forces at the step's contact points (narrow_phase / narrow_phase_coop wrote them into
    `cur`; `prev`: last step's history), into `loads`: one thread per pair of the active list, in its
    order (the forces add up in the same order whichever kernel found the points). clock = [t_next, dt]
    of this step (set_block_clock), read on the device so a CUDA graph can replay the step; clock[2] = 1: friction
    locked (BlockSolver.settle), every point sticks whatever its Coulomb cap (the cap is still recorded)."""
    kinds = props.kinds
    inv_mass = props.inv_mass
    x = bodies.x
    q = bodies.q
    v = bodies.v
    w = bodies.w
    strain_rate = bodies.strain_rate
    new_pos = cur.pos
    new_depth = cur.depth
    new_ckey = cur.ckey
    force = loads.force
    torque = loads.torque
    strain_force = loads.strain_force
    li = wp.tid()
    if li >= pl.counters[3]:
        return
    tid = pl.active[li]
    A = pl.pairs[tid][0]
    B = pl.pairs[tid][1]
    dt = clock_of(clock, A, 1)  # (A and B share a clock: one scenario's blocks)
    locked = clock_of(clock, A, 2) > 0.5  # BlockSolver.settle: friction locked, every point sticks
    slot = pl.slot[tid]
    oslot = pl.oslot[tid]
    nc = cur.nc[slot]
    if nc == 0:
        return
    base = cur.pstart[slot]
    n = cur.normal[slot]
    # the frame of the contact points (cur.pos): A's centroid x + x_lo at its origin, B's at xB; the
    # difference of the nearby float32 centroids is exact, so lever arms keep their bits far from the origin
    xA = wp.vec3(0.0, 0.0, 0.0)
    xB = (x[B] - x[A]) + (bodies.x_lo[B] - bodies.x_lo[A])
    t1 = contact_tangent(n)
    t2 = wp.cross(n, t1)
    # contact patch area (convex polygon through the points, angular order) -> area share
    cen = wp.vec3(0.0, 0.0, 0.0)
    for k in range(nc):
        cen = cen + new_pos[base + k]
    cen = cen / float(nc)
    area = float(0.0)
    if nc >= 3:
        for k in range(nc):
            rk = new_pos[base + k] - cen
            ak = wp.atan2(wp.dot(rk, t2), wp.dot(rk, t1))
            best = float(1.0e9)
            nxt = int(-1)
            for m in range(nc):
                rm = new_pos[base + m] - cen
                am = wp.atan2(wp.dot(rm, t2), wp.dot(rm, t1))
                da = am - ak
                if da <= 0.0:
                    da = da + 6.283185307
                if m != k and da < best:
                    best = da
                    nxt = m
            if nxt >= 0:
                rn = new_pos[base + nxt] - cen
                area = area + 0.5 * wp.dot(wp.cross(rk, rn), n)
    area = wp.abs(area)
    a_share = area / float(nc)
    # material of the pair: the weaker of the two blocks
    kn = wp.min(mat.k_n[A], mat.k_n[B])
    ks = wp.min(mat.k_s[A], mat.k_s[B])
    mu = wp.min(mat.tan_phi[A], mat.tan_phi[B])
    coh = wp.min(mat.cohesion[A], mat.cohesion[B])
    ten = wp.min(mat.tensile[A], mat.tensile[B])
    zt = wp.max(mat.zeta[A], mat.zeta[B])
    im = inv_mass[A] + inv_mass[B]
    m_eff = float(0.0)
    if im > 0.0:
        m_eff = 1.0 / im
    # dashpots per point: c = 2 zeta sqrt(k m_eff / n_points) (n points act in parallel). Normal: zeta
    # from the restitution for a point that closed as an impact, critical (1) for a resting one;
    # shear: overdamped (ZETA_STUCK) while stuck, none while sliding. Between rigid blocks the dashpots are implicit in the block update
    # (damp_c, damp_b; integrate_blocks), so strong damping costs no stability; with a deformable block
    # they stay explicit, bounded by c dt <= m_eff / n_points.
    sq_n = wp.sqrt(kn * m_eff / float(nc))
    implicit = kinds[A] != KIND_DEFORMABLE and kinds[B] != KIND_DEFORMABLE
    # a point is an impact when it closed faster than v_rest = |g| / omega, omega = sqrt(n k_n / m_eff):
    # the speed the penalty spring itself gives a block settling onto it under gravity
    v_rest = float(1.0e30)
    if m_eff > 0.0:
        v_rest = g_mag / wp.sqrt(float(nc) * kn / m_eff)
    onc = int(0)
    obase = int(0)
    if oslot >= 0:
        onc = prev.nc[oslot]
        obase = prev.pstart[oslot]
    if dt <= 0.0 and clock.shape[0] > 3:
        # a batch's scenario that has taken its own sub-steps of this fluid step (per-block clocks,
        # rockwave/sim/batch.py): no force, and each point's history kept as its last real sub-step left it (depth,
        # normal force, shear spring, closing speed, cap), so its next real sub-step reads what it reads alone; a
        # point without history stays without (its key cleared: fresh at the next real sub-step, as alone)
        for k in range(nc):
            c = base + k
            ck = new_ckey[c]
            hist = int(-1)
            for m in range(onc):
                ok = prev.ckey[obase + m]
                if ok[0] == ck[0] and ok[1] == ck[1]:
                    hist = obase + m
            if hist >= 0:
                new_depth[c] = prev.depth[hist]
                cur.fn[c] = prev.fn[hist]
                cur.shear[c] = prev.shear[hist]
                cur.vimp[c] = prev.vimp[hist]
                cur.fcap[c] = prev.fcap[hist]
            else:
                new_ckey[c] = wp.vec2i(-1, -1)
        return
    # pass 1: springs, the Coulomb cap and which points stick (the stuck points share the shear dashpot)
    cs0 = 2.0 * ZETA_STUCK * wp.sqrt(ks * m_eff / float(nc))
    if not implicit and dt > 0.0:
        cs0 = wp.min(cs0, m_eff / (float(nc) * dt))
    stuck_mask = int(0)
    fresh_mask = int(0)  # points without history (their first step in contact)
    n_stuck = int(0)
    # history of each point: last step's point of the same feature key; else (its key changed while the point stayed:
    # on continuous joints the faces' corners coincide, and a relative shift of a fraction of a um across the
    # vertex test's tolerance turns a vertex-in-face point into an edge crossing or into the other block's coincident
    # vertex, at the same place) the nearest unclaimed point of last step within dup_tol in the plane, the distance
    # below which narrow_phase's add_contact takes two points for one. Keyed by feature only, such a point restarted
    # its spring from zero: its share of the shear load went to the other points, the block moved by it (a quarter
    # of a base spring's extension), and the new spring loaded again from there, a ratchet: a jointed mass at 2 deg
    # above its limit crept a few um/s for a minute (issue 36, docs/notes.md)
    hk = PointKey()
    claimed = int(0)
    for k in range(nc):
        hk[k] = -1
        ck = new_ckey[base + k]
        for m in range(onc):
            ok = prev.ckey[obase + m]
            if ok[0] == ck[0] and ok[1] == ck[1]:
                hk[k] = m
        if hk[k] >= 0:
            claimed = claimed | (1 << hk[k])
    dup_tol = 1.0e-4 * wp.min(block_size[A], block_size[B])  # narrow_phase's
    for k in range(nc):
        if hk[k] < 0:
            pk = new_pos[base + k]
            best = dup_tol
            bm = int(-1)
            for m in range(onc):
                if (claimed & (1 << m)) == 0:
                    dpo = pk - prev.pos[obase + m]  # both relative to A's centroid (moved by v dt since)
                    dpl = wp.length(dpo - wp.dot(dpo, n) * n)
                    if dpl < best:
                        best = dpl
                        bm = m
            if bm >= 0:
                hk[k] = bm
                claimed = claimed | (1 << bm)
    for k in range(nc):
        c = base + k
        p = new_pos[c]
        vrel = point_velocity(B, p, xB, q, v, w, strain_rate, kinds) - point_velocity(A, p, xA, q, v, w, strain_rate, kinds)
        vrel = vrel + kinematic_last_step(B, bodies, kinds) - kinematic_last_step(A, bodies, kinds)
        vn = wp.dot(vrel, n)
        vt = vrel - vn * n
        # history of this point (hk): shear spring, closing speed at first touch
        fs = wp.vec3(0.0, 0.0, 0.0)
        vimp = wp.max(-vn, 0.0)
        hist = int(-1)
        if hk[k] >= 0:
            hist = obase + hk[k]
            vimp = prev.vimp[hist]
            # shear spring carried from last step, rotated onto the new plane keeping its magnitude
            fo = prev.shear[hist]
            mag = wp.length(fo)
            fp = fo - wp.dot(fo, n) * n
            lp = wp.length(fp)
            if lp > 1.0e-20:
                fs = fp * (mag / lp)
        cur.vimp[c] = vimp
        if hist < 0:
            fresh_mask = fresh_mask | (1 << k)
        zn = float(1.0)
        if vimp > v_rest:
            zn = zt  # an impact: the restitution's ratio
        # normal: penalty k_n delta + dashpot; tension cut-off (pull only up to the tensile strength)
        cn1 = 2.0 * zn * sq_n
        if not implicit and dt > 0.0:
            cn1 = wp.min(cn1, m_eff / (float(nc) * dt))
        fn = wp.max(kn * new_depth[c] - cn1 * vn, -ten * a_share)
        # the normal force that bounds friction: this estimate plus what the implicit step last applied
        # beyond last step's estimate (k_n delta - c_n v_n with v_n now, the velocity it solved for), so
        # that over the steps friction never exceeds mu times the normal impulse actually delivered
        fnc = fn
        if implicit and hist >= 0:
            fnc = fn + wp.max(kn * prev.depth[hist] - cn1 * vn, -ten * a_share) - prev.fn[hist]
        # shear: incremental spring in the contact plane, df = -k_s v_t dt
        fs = fs - (ks * dt) * vt
        # Coulomb cap mu F_n + c A_share
        fmax = mu * wp.max(fnc, 0.0) + coh * a_share
        cur.fcap[c] = fmax
        # Coulomb: a point sticks while its spring and its dashpot together stay within the cap; beyond it the
        # point slides at the cap, in the direction of that trial force, with no dashpot. Never a force above the
        # trial force: mu F_n applied to a point that a smaller force stops reverses it within the explicit step
        # and makes energy (docs/notes.md 'A locked jointed mass explodes'). With explicit dashpots (deformable
        # blocks, c dt <= m / n) the spring alone is tested: the trial's dashpot share, written into a stuck
        # spring set to its cap, ratchets a block on a shaking base (docs/notes.md 'Deformable Newmark ratchet')
        ftr = fs - cs0 * vt
        lftr = wp.length(ftr)
        ltest = lftr
        if not implicit:
            ltest = wp.length(fs)
        if locked or ltest <= fmax:
            stuck_mask = stuck_mask | (1 << k)
            n_stuck += 1
        elif lftr > 0.0:
            fs = ftr * (fmax / lftr)
        cur.shear[c] = fs
        cur.fn[c] = fn
    # shear dashpot of a stuck point: c_s = 2 zeta_s sqrt(k_s m_eff / n_stuck), zeta_s = ZETA_STUCK (over the
    # points that stick; sliding points carry mu F_n and no dashpot); deformable blocks: at most m_eff / (n dt)
    cs = float(0.0)
    if n_stuck > 0:
        cs = 2.0 * ZETA_STUCK * wp.sqrt(ks * m_eff / float(n_stuck))
        if not implicit and dt > 0.0:
            cs = wp.min(cs, m_eff / (float(n_stuck) * dt))  # explicit dashpot: c dt <= m (stable, no overshoot)
    # pass 2: forces. The implicit dashpots pull a block towards the other's velocity over this step: a kinematic
    # block's is its prescribed displacement over the step / dt (integrate_blocks), not the one it moved with over the
    # last (once per pair: a table motion's lookup scans its rows)
    dvA_step = kinematic_step_change(A, clock, motion, bodies, kinds)
    dvB_step = kinematic_step_change(B, clock, motion, bodies, kinds)
    impact_pts = int(0)
    cn_face = 2.0 * sq_n  # a resting point's normal dashpot
    for k in range(nc):
        c = base + k
        p = new_pos[c]
        d = new_depth[c]
        vA = point_velocity(A, p, xA, q, v, w, strain_rate, kinds) + kinematic_last_step(A, bodies, kinds)
        vB = point_velocity(B, p, xB, q, v, w, strain_rate, kinds) + kinematic_last_step(B, bodies, kinds)
        vrel = vB - vA
        vn = wp.dot(vrel, n)
        vt = vrel - vn * n
        vAd = vA + dvA_step
        vBd = vB + dvB_step
        zn = float(1.0)
        if cur.vimp[c] > v_rest:
            zn = zt
            impact_pts += 1
        cn = 2.0 * zn * sq_n
        if not implicit and dt > 0.0:
            cn = wp.min(cn, m_eff / (float(nc) * dt))
        fn = cur.fn[c]
        fs = cur.shear[c]
        stuck = (stuck_mask & (1 << k)) != 0
        # Coulomb bounds the whole shear force of a stuck point, spring and dashpot together:
        # |f_s - c v_t| <= mu F_n + c A. The dashpot takes only the capacity the spring leaves (largest c
        # with |f_s - c v_t| = f_max), so it damps the elastic shear motion of a stuck point and never adds
        # friction beyond Coulomb's (a point touching down with a tangential velocity slides at mu F_n)
        csk = float(0.0)
        lvt2 = wp.dot(vt, vt)
        # a point's first step in contact (no history) takes no dashpot: the bound below is formed from the
        # start-of-step v_t, and a point touching at rest (v_t = 0: a block placed exactly touching, gravity from
        # t = 0) would otherwise hold the whole step's tangential motion in the implicit solve with next to no
        # normal force behind it (its depth ~0). float32 depths had hidden this by rounding such a touch to no
        # contact; exact depths found it and a block sliding 5 deg past its limit lost 1-2% of its speed in that
        # one step (issue 36, docs/notes.md)
        fresh = (fresh_mask & (1 << k)) != 0
        if stuck and (locked or not fresh):
            csk = cs
            if lvt2 > 0.0 and not locked:
                fcap = cur.fcap[c]
                fv = wp.dot(fs, vt)
                disc = fv * fv - lvt2 * (wp.dot(fs, fs) - fcap * fcap)
                csk = wp.min(cs, wp.max((fv + wp.sqrt(wp.max(disc, 0.0))) / lvt2, 0.0))
        f = fn * n + fs  # force on B
        if implicit:
            # explicit part: springs (or the cut-off force); the dashpots go to damp_c / damp_b
            f = fs
            if kn * d - cn * vn < -ten * a_share:
                f = f + fn * n
            else:
                f = f + (kn * d) * n
                add_damper(A, B, p, n, cn, vAd, vBd, xA, xB, kinds, loads)
            if stuck:
                add_damper(A, B, p, t1, csk, vAd, vBd, xA, xB, kinds, loads)
                add_damper(A, B, p, t2, csk, vAd, vBd, xA, xB, kinds, loads)
        elif stuck:
            f = f - csk * vt
        if movable(kinds[B]):
            wp.atomic_add(force, B, f)
            wp.atomic_add(torque, B, wp.cross(p - xB, f))
            if kinds[B] == KIND_DEFORMABLE:
                Xb = wp.quat_rotate_inv(q[B], p - xB)
                wp.atomic_add(strain_force, B, strain_gen_force(Xb, wp.quat_rotate_inv(q[B], f)))
        if movable(kinds[A]):
            wp.atomic_add(force, A, -f)
            wp.atomic_add(torque, A, wp.cross(p - xA, -f))
            if kinds[A] == KIND_DEFORMABLE:
                Xa = wp.quat_rotate_inv(q[A], p - xA)
                wp.atomic_add(strain_force, A, strain_gen_force(Xa, wp.quat_rotate_inv(q[A], -f)))
    # rocking of a resting face: the point dashpots (critical for the normal translation, c_n per point) give
    # its two rocking modes about the in-plane axes through the patch centre only c_n sum l_k^2 against
    # 2 sqrt(K_e I_e) critical (K_e = k_n sum l_k^2, l_k the points' lever arms, I_e the blocks' inertia about
    # that axis): zeta = sqrt(m / (n I_e / sum l_k^2)), 0.67 for a block of h/w 1.2 on its base. A suddenly
    # loaded face (gravity on a block set down on it) then pitches and overshoots, as a stuck shear spring
    # would without its overdamped dashpot; so the rocking modes get the stuck shear's ratio ZETA_STUCK,
    # the missing part as an implicit rotational dashpot (resting faces of rigid blocks: not at an impact,
    # which keeps the restitution's damping)
    if implicit and nc >= 3 and impact_pts == 0:
        for ax in range(2):
            e = t1
            if ax == 1:
                e = t2
            sl2 = float(0.0)
            for k in range(nc):
                lk = wp.dot(wp.cross(e, new_pos[base + k] - cen), n)
                sl2 += lk * lk
            inv_i = inv_rocking_inertia(A, e, cen, xA, props, bodies) + inv_rocking_inertia(B, e, cen, xB, props, bodies)
            if sl2 > 0.0 and inv_i > 0.0:
                c_rock = 2.0 * ZETA_STUCK * wp.sqrt(kn * sl2 / inv_i) - cn_face * sl2
                if c_rock > 0.0:
                    add_rocking_damper(A, B, e, c_rock, w[A], w[B], kinds, loads)
    wp.atomic_add(loads.contact_count, A, nc)
    wp.atomic_add(loads.contact_count, B, nc)


@wp.kernel
def carry_contacts(
    pl: PairList,
    clock: wp.array(dtype=float),
    kinds: wp.array(dtype=int),
    bodies: BlockBodies,
    prev: ContactTable,
    cur: ContactTable,
):
    """Held contacts (BlockSolver.substeps, hold_contacts): a block sub-step after the first of a fluid step keeps
    the pairs, planes and contact points of that step's narrow phase, moved by the sub-step just taken, instead of
    finding them again. One thread per candidate pair; its slot (the same in both tables while held) is copied
    from prev to cur. Each contact point p moves with the mean motion of the two blocks at p, dp = h (v_A(p) +
    v_B(p)) / 2, in the frame of A's centroid (which moved by h v_A); its depth by the approach along the normal,
    d' = d - h n.(v_B(p) - v_A(p)); the normal turns with the blocks' mean spin. A point whose depth is no longer
    positive is dropped, as the narrow phase would not find it. h = clock[1]: the sub-step over which the
    velocities (after integration) just moved the blocks (semi-implicit Euler, x' = x + h v'). Points that
    appear inside a held step are found at the next fluid step's narrow phase."""
    tid = wp.tid()
    if tid >= wp.min(pl.counters[0], pl.pairs.shape[0]):
        return
    slot = pl.slot[tid]
    if slot < 0:
        return
    pl.oslot[tid] = slot
    cur.keys[slot] = prev.keys[slot]
    cur.gapb[slot] = prev.gapb[slot]
    nc = prev.nc[slot]
    base = prev.pstart[slot]
    cur.pstart[slot] = base
    n = prev.normal[slot]
    if nc == 0:
        cur.normal[slot] = n
        cur.nc[slot] = 0
        return
    A = pl.pairs[tid][0]
    B = pl.pairs[tid][1]
    h = clock_of(clock, A, 1)
    x = bodies.x
    xA = wp.vec3(0.0, 0.0, 0.0)
    xB = (x[B] - x[A]) + (bodies.x_lo[B] - bodies.x_lo[A])
    vcA = bodies.v[A]
    kept = int(0)
    for k in range(nc):
        c = base + k
        p = prev.pos[c]
        vA = point_velocity(A, p, xA, bodies.q, bodies.v, bodies.w, bodies.strain_rate, kinds)
        vB = point_velocity(B, p, xB, bodies.q, bodies.v, bodies.w, bodies.strain_rate, kinds)
        d = prev.depth[c] - h * wp.dot(n, vB - vA)
        if d > 0.0:
            o = base + kept
            cur.pos[o] = p + h * (0.5 * (vA + vB) - vcA)
            cur.depth[o] = d
            cur.ckey[o] = prev.ckey[c]
            kept += 1
    cur.nc[slot] = kept
    spin = 0.5 * (bodies.w[A] + bodies.w[B])
    cur.normal[slot] = wp.normalize(n + h * wp.cross(spin, n))


@wp.func
def block_reach(b: int, v: wp.array(dtype=wp.vec3), w: wp.array(dtype=wp.vec3), block_size: wp.array(dtype=float)):
    # the fastest any point of block b moves: |v| + |w| r, r = block_size / 2 [m/s]
    return wp.length(v[b]) + wp.length(w[b]) * 0.5 * block_size[b]


@wp.kernel
def hold_check_blocks(
    kinds: wp.array(dtype=int),
    block_size: wp.array(dtype=float),
    v: wp.array(dtype=wp.vec3),
    w: wp.array(dtype=wp.vec3),
    reach_dt: float,
    half_margin: float,
    flags: wp.array(dtype=int),
):
    """BlockSolver.hold_checks, per block: flags[0] = 0 when a block that moves reaches beyond margin/2 over the
    step, headroom (|v| + |w| r) dt > margin / 2 (reach_dt = headroom dt; r = block_size / 2): the pair
    list may not be kept."""
    b = wp.tid()
    if kinds[b] == KIND_FIXED:
        return
    if reach_dt * block_reach(b, v, w, block_size) > half_margin:
        flags[0] = 0


@wp.kernel
def settle_speed(
    kinds: wp.array(dtype=int),
    block_size: wp.array(dtype=float),
    v: wp.array(dtype=wp.vec3),
    w: wp.array(dtype=wp.vec3),
    tol: float,
    x: wp.array(dtype=wp.vec3),
    x0: wp.array(dtype=wp.vec3),
    max_move: wp.array(dtype=float),
    flags: wp.array(dtype=int),
    reach: wp.array(dtype=float),
):
    """BlockSolver.settle: reach[b] = the speed of a rigid or deformable block's fastest point |v| + |w| r
    (r = block_size / 2; 0 for the others), and flags[0] = 1 when one is above tol; flags[1] = 1 when a block's
    centroid has moved more than max_move[b] [m] from x0 (where it was placed)."""
    b = wp.tid()
    reach[b] = 0.0
    if not movable(kinds[b]):
        return
    r = block_reach(b, v, w, block_size)
    reach[b] = r
    if r > tol:
        flags[0] = 1
    if wp.length(x[b] - x0[b]) > max_move[b]:
        flags[1] = 1


@wp.kernel
def relax_blocks(
    kinds: wp.array(dtype=int),
    block_size: wp.array(dtype=float),
    v: wp.array(dtype=wp.vec3),
    w: wp.array(dtype=wp.vec3),
    strain_rate: wp.array(dtype=wp.spatial_vector),
    e_prev: wp.array(dtype=float),
    rise: wp.array(dtype=int),
    reach_max: wp.array(dtype=float),
):
    """BlockSolver.settle's friction stage, after each step: kinetic damping (dynamic relaxation; Cundall 1976,
    Topping & Khan 1996): a block's kinetic measure e = |v|^2 + (|w| r)^2 (r = block_size / 2) is followed step by
    step, and when it stops rising (a peak: the block crosses its equilibrium) v, w and the strain rate are zeroed,
    so the block creeps to the nearest statically admissible state without the momentum that would carry it past.
    rise[b]: steps since the last peak (a block whose e rises without end is sliding); reach_max[b]: the largest
    |v| + |w| r since it was last read (relax_check)."""
    b = wp.tid()
    if not movable(kinds[b]):
        return
    r = block_reach(b, v, w, block_size)
    reach_max[b] = wp.max(reach_max[b], r)
    rw = wp.length(w[b]) * 0.5 * block_size[b]
    e = wp.dot(v[b], v[b]) + rw * rw
    if e < e_prev[b]:
        v[b] = wp.vec3(0.0, 0.0, 0.0)
        w[b] = wp.vec3(0.0, 0.0, 0.0)
        strain_rate[b] = wp.spatial_vector(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        e_prev[b] = 0.0
        rise[b] = 0
    elif e > e_prev[b]:
        e_prev[b] = e
        rise[b] = rise[b] + 1
    else:
        rise[b] = 0


@wp.kernel
def relax_check(
    kinds: wp.array(dtype=int),
    reach_max: wp.array(dtype=float),
    tol: float,
    x: wp.array(dtype=wp.vec3),
    x0: wp.array(dtype=wp.vec3),
    max_move: wp.array(dtype=float),
    rise: wp.array(dtype=int),
    max_rise: int,
    flags: wp.array(dtype=int),
    reach: wp.array(dtype=float),
    sliding: wp.array(dtype=int),
):
    """BlockSolver.settle's friction stage, every few steps: reach[b] = the fastest a block moved since the last
    check (reach_max, then reset), flags[0] = 1 when one is above tol; a block that leaves its place (|x - x0| >
    max_move[b]) or whose kinetic measure has risen for more than max_rise steps without a peak (it accelerates:
    friction below what the slope needs) is sliding: sliding[b] = 1, flags[1] = 1."""
    b = wp.tid()
    reach[b] = 0.0
    if not movable(kinds[b]):
        return
    r = reach_max[b]
    reach_max[b] = 0.0
    reach[b] = r
    if r > tol:
        flags[0] = 1
    if wp.length(x[b] - x0[b]) > max_move[b] or rise[b] > max_rise:
        sliding[b] = 1
        flags[1] = 1


@wp.kernel
def hold_check_pairs(
    pl: PairList,
    props: BlockProps,
    mat: BlockMaterial,
    block_size: wp.array(dtype=float),
    bodies: BlockBodies,
    g_mag: float,
    close_dt: float,
    table: ContactTable,
    flags: wp.array(dtype=int),
):
    """BlockSolver.hold_checks, per candidate pair: flags[1] = 0 when contacts may not be carried through a fluid
    step's sub-steps:
    - a pair without contact points at the last narrow phase could close its gap before the next check,
      gap <= close_dt (reach_A + reach_B) (close_dt = headroom dt steps, reach = |v| + |w| r);
    - a pair in contact is not at rest: its points approach or part faster than the resting-contact speed
      v_rest = |g| / sqrt(n k_n / m_eff) that contact_forces uses to tell impacts apart, or the blocks turn
      against each other faster than v_rest over the smaller one's radius. An impact, a bounce or a block
      rocking onto a new corner is found again every sub-step; a resting or sliding contact (its points move
      along the plane) is carried."""
    tid = wp.tid()
    if tid >= wp.min(pl.counters[0], pl.pairs.shape[0]):
        return
    A = pl.pairs[tid][0]
    B = pl.pairs[tid][1]
    x = bodies.x
    v = bodies.v
    w = bodies.w
    slot = pl.slot[tid]
    nc = int(0)
    if slot >= 0:
        nc = table.nc[slot]
    if nc == 0:
        reach = block_reach(A, v, w, block_size) + block_reach(B, v, w, block_size)
        if pl.gap[tid] <= close_dt * reach:
            flags[1] = 0
        return
    im = props.inv_mass[A] + props.inv_mass[B]
    if im <= 0.0:
        return
    kn = wp.min(mat.k_n[A], mat.k_n[B])
    v_rest = g_mag / wp.sqrt(float(nc) * kn * im)
    n = table.normal[slot]
    xA = wp.vec3(0.0, 0.0, 0.0)
    xB = (x[B] - x[A]) + (bodies.x_lo[B] - bodies.x_lo[A])
    base = table.pstart[slot]
    approach = wp.length(w[B] - w[A]) * 0.5 * wp.min(block_size[A], block_size[B])
    vmax = float(0.0)
    for k in range(nc):
        p = table.pos[base + k]
        vr = point_velocity(B, p, xB, bodies.q, v, w, bodies.strain_rate, props.kinds) - point_velocity(
            A, p, xA, bodies.q, v, w, bodies.strain_rate, props.kinds)
        vmax = wp.max(vmax, wp.abs(wp.dot(n, vr)))
    if approach + vmax > v_rest:
        flags[1] = 0


@wp.kernel
def rehash_table(prev: ContactTable, cur: ContactTable):
    # move the contact history into a larger table (capacity growth)
    s = wp.tid()
    key = prev.keys[s]
    if key < wp.int64(0):
        return
    t = table_insert(key, cur.keys, cur.keys.shape[0])
    if t < 0:
        return
    cur.normal[t] = prev.normal[s]
    cur.gapb[t] = prev.gapb[s]
    nc = prev.nc[s]
    i = prev.pstart[s]
    o = int(0)
    if nc > 0:
        o = wp.atomic_add(cur.pcount, 0, nc)
        if o + nc > cur.pos.shape[0]:
            nc = 0  # the host sizes the new pool for every point (BlockState.alloc_tables)
    cur.nc[t] = nc
    cur.pstart[t] = o
    for k in range(nc):
        cur.ckey[o + k] = prev.ckey[i + k]
        cur.shear[o + k] = prev.shear[i + k]
        cur.pos[o + k] = prev.pos[i + k]
        cur.vimp[o + k] = prev.vimp[i + k]
        cur.fcap[o + k] = prev.fcap[i + k]
        cur.fn[o + k] = prev.fn[i + k]
        cur.depth[o + k] = prev.depth[i + k]


# ----------------------------------------------------------------------------------------------
# time integration (semi-implicit Euler = central difference with velocities at half steps)
# ----------------------------------------------------------------------------------------------


@wp.func
def kinematic_motion(b: int, t: float, mo: BlockMotion):
    # displacement and velocity of a prescribed motion at time t:
    # sine: u = A sin(2 pi f t + phase), du/dt = 2 pi f A cos(...); table: piecewise linear in t
    mt = mo.motion_type[b]
    if mt == MOTION_SINE:
        om = 6.283185307179586 * mo.motion_freq[b]
        arg = om * t + mo.motion_phase[b]
        return mo.motion_amp[b] * wp.sin(arg), mo.motion_amp[b] * (om * wp.cos(arg))
    if mt == MOTION_TABLE:
        table_t = mo.table_t
        table_x = mo.table_x
        s = mo.table_start[b]
        n = mo.table_count[b]
        if t <= table_t[s]:
            return table_x[s], wp.vec3(0.0, 0.0, 0.0)
        for k in range(n - 1):
            t0 = table_t[s + k]
            t1 = table_t[s + k + 1]
            if t <= t1:
                slope = (table_x[s + k + 1] - table_x[s + k]) / (t1 - t0)
                return table_x[s + k] + slope * (t - t0), slope
        return table_x[s + n - 1], wp.vec3(0.0, 0.0, 0.0)
    return wp.vec3(0.0, 0.0, 0.0), wp.vec3(0.0, 0.0, 0.0)


@wp.func
def unit_compensated(qh: wp.quat, ql: wp.quat):
    # the compensated orientation q + q_lo made unit (integrate_blocks' rule): its norm's excess
    # e2 = |q + q_lo|^2 - 1 in float64, then q_lo -= (e2 / 2) q (first order); far from unit (> 1e-5): start over
    n2 = wp.float64(0.0)
    for i in range(4):
        ci = wp.float64(qh[i]) + wp.float64(ql[i])
        n2 += ci * ci
    hc = wp.float32(wp.float64(0.5) * (n2 - wp.float64(1.0)))
    rl = ql - hc * qh
    rh = qh
    if wp.abs(hc) > 1.0e-5:  # far from unit (a quaternion set from outside): start the compensation over
        rh = wp.normalize(qh + rl)
        rl = wp.quat(0.0, 0.0, 0.0, 0.0)
    return rh, rl


@wp.kernel
def integrate_blocks(
    props: BlockProps,
    motion: BlockMotion,
    gravity: wp.vec3,
    clock: wp.array(dtype=float),
    bodies: BlockBodies,
    loads: BlockLoads,
):
    """One explicit step of every block: kinematic blocks follow their motion at t_next, rigid and
    deformable ones integrate the contact and external loads (then zeroed) and gravity.
    clock = [t_next, dt] (set_block_clock)."""
    x = bodies.x
    q = bodies.q
    v = bodies.v
    w = bodies.w
    force = loads.force
    torque = loads.torque
    strain_force = loads.strain_force
    ext_force = loads.ext_force
    ext_torque = loads.ext_torque
    b = wp.tid()
    t_next = clock_of(clock, b, 0)
    dt = clock_of(clock, b, 1)
    kind = props.kinds[b]
    if dt <= 0.0:  # a batch's block whose scenario has taken its sub-steps of this fluid step: it stays as it is
        kind = KIND_FIXED
    if kind == KIND_KINEMATIC:
        u, uv = kinematic_motion(b, t_next, motion)
        xs, xl = two_sum(motion.base_x[b], u)
        vs = uv
        if dt > 0.0:  # the displacement over this step / dt (the same float32 parts as x + x_lo): v_step
            vs = ((xs - x[b]) + (xl - bodies.x_lo[b])) / dt
        x[b] = xs
        bodies.x_lo[b] = xl
        v[b] = uv
        bodies.v_step[b] = vs
        w[b] = wp.vec3(0.0, 0.0, 0.0)
    elif kind != KIND_FIXED:
        im = props.inv_mass[b]
        R = wp.quat_to_matrix(q[b])
        Iw = R * props.inertia_body[b] * wp.transpose(R)
        Iwinv = R * props.inv_inertia_body[b] * wp.transpose(R)
        om = w[b]
        ftot = force[b] + ext_force[b]
        tau = torque[b] + ext_torque[b] - wp.cross(om, Iw * om)
        C = sym6_matrix(loads.damp_c[b])
        vn = v[b]
        if C[0, 0] + C[1, 1] + C[2, 2] + C[3, 3] + C[4, 4] + C[5, 5] > 0.0:
            # contact dashpots implicit: (M + dt C) V' = M V + dt (F + M g + b), M = diag(m, I_w)
            # (backward Euler in the damping: stable for any damping ratio)
            m = 1.0 / im
            Mv = wp.spatial_vector(m * vn, Iw * om)
            rhs = Mv + dt * (wp.spatial_vector(ftot + m * gravity, tau) + loads.damp_b[b])
            Amat = dt * C
            for i in range(3):
                Amat[i, i] = Amat[i, i] + m
            for i in range(3):
                for j in range(3):
                    Amat[3 + i, 3 + j] = Amat[3 + i, 3 + j] + Iw[i, j]
            sol = solve6(Amat, rhs)
            vn = wp.spatial_top(sol)
            om = wp.spatial_bottom(sol)
        else:
            # translation: m dv/dt = F_contact + F_ext + m g
            vn = vn + dt * (ftot * im + gravity)
            # rotation (world frame): I_w dw/dt = tau - w x (I_w w),  I_w = R I_b R^T
            om = om + dt * (Iwinv * tau)
        # compensated position update (x + x_lo += dt v): a step moves a block by far less than the
        # float32 spacing of x far from the origin allows (0.2 um per step against 1.2e-7 m at 1 m), so the
        # plain sum would round every step's increment to a few ulps and walk the block off its path
        xs, xl = two_sum(x[b], dt * vn + bodies.x_lo[b])
        x[b] = xs
        bodies.x_lo[b] = xl
        v[b] = vn
        w[b] = om
        # exact rotation by |w| dt about w, q <- dq q with dq = (sin(a/2) e, cos(a/2)), a = |w| dt, compensated like
        # the position: q + q_lo += (dq - 1) q, dq - 1 = (sin(a/2) e, -2 sin^2(a/4)) (no cancellation). A resting
        # block turns by far less than float32's spacing of q per step (|w| dt = 2.4e-8 rad against 6e-8 at
        # q_i ~ 0.9): the plain product rounded every such turn away, and a block whose stuck contact points
        # held its base could roll on them at |w| = v / r, its centroid creeping at v (issue 36, docs/notes.md)
        ang = wp.length(om) * dt
        ql = bodies.q_lo[b]
        qh = q[b]
        if ang > 0.0:
            e = om / wp.length(om)
            sh = wp.sin(0.5 * ang)
            s4 = wp.sin(0.25 * ang)
            dqm = wp.quat(sh * e[0], sh * e[1], sh * e[2], -2.0 * s4 * s4)
            dlt = wp.mul(dqm, qh) + ql
            qs = qh + dlt
            bb = qs - qh
            ql = (qh - (qs - bb)) + (dlt - bb)  # two_sum, componentwise
            qh = qs
        # keep q + q_lo unit (in float64: float32 would round the norm's excess to its own size)
        qh, ql = unit_compensated(qh, ql)
        q[b] = qh
        bodies.q_lo[b] = ql
        if kind == KIND_DEFORMABLE:
            # Shi's strain DOFs: M_e de'/dt = Q - V D e - 2 zeta w_e M_e e'
            s = bodies.strain[b]
            sr = bodies.strain_rate[b]
            acc = props.strain_minv[b] * (strain_force[b] - props.strain_k[b] * s) - props.strain_damp[b] * sr
            sr = sr + dt * acc
            bodies.strain_rate[b] = sr
            bodies.strain[b] = s + dt * sr
    force[b] = wp.vec3(0.0, 0.0, 0.0)
    torque[b] = wp.vec3(0.0, 0.0, 0.0)
    strain_force[b] = wp.spatial_vector(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    ext_force[b] = wp.vec3(0.0, 0.0, 0.0)
    ext_torque[b] = wp.vec3(0.0, 0.0, 0.0)
    loads.damp_c[b] = sym6()
    loads.damp_b[b] = wp.spatial_vector()


@wp.kernel
def compound_loads(start: wp.array(dtype=int), count: wp.array(dtype=int), loads: BlockLoads):
    """Compound (non-convex) blocks, one thread per body: every part carries the body's pose, mass and
    inertia, and its loads are about the body's centroid (the parts' common x), so the body's load is the
    plain sum over its parts (F = sum F_p, tau = sum tau_p; the implicit dashpots C, b likewise, all in
    [v, w] of the same body); each part gets the sum, summed in one order, so all parts integrate the
    same motion bit for bit. Rigid parts only (no strain force)."""
    c = wp.tid()
    s = start[c]
    f = wp.vec3(0.0, 0.0, 0.0)
    t = wp.vec3(0.0, 0.0, 0.0)
    fe = wp.vec3(0.0, 0.0, 0.0)
    te = wp.vec3(0.0, 0.0, 0.0)
    C = sym6()
    bb = wp.spatial_vector()
    for k in range(count[c]):
        f = f + loads.force[s + k]
        t = t + loads.torque[s + k]
        fe = fe + loads.ext_force[s + k]
        te = te + loads.ext_torque[s + k]
        C = C + loads.damp_c[s + k]
        bb = bb + loads.damp_b[s + k]
    for k in range(count[c]):
        loads.force[s + k] = f
        loads.torque[s + k] = t
        loads.ext_force[s + k] = fe
        loads.ext_torque[s + k] = te
        loads.damp_c[s + k] = C
        loads.damp_b[s + k] = bb



@wp.kernel
def planar_blocks(z0: wp.array(dtype=float), kinds: wp.array(dtype=int), bodies: BlockBodies):
    """2D scenes (BlockModel.planar): blocks move in the x-y plane only (z fixed at z0, spin about z
    only); fixed blocks are left as they are. The orientation q + q_lo keeps spin about z only and stays
    unit as a compensated pair (unit_compensated). Normalising the float32 q alone threw away the norm
    correction integrate_blocks had put in q_lo: |q + q_lo| - 1 then flipped sign every step and
    random-walked to ~2e-6 in 0.3 s (1,400 steps), the arms R(q + q_lo) X (vertex_arm) stretched by twice
    that, a prism's corners stepped outside and inside the face of a neighbour of the same depth by
    ~4e-7 m (4 x the vertex test's tolerance) every other step, so the contact points changed key (vertex
    <-> edge crossing) and depth (+-0.3 um) each step and a resting rock at a 0.5 deg margin slid at
    ~1 mm/s (issue 36, docs/notes.md)."""
    b = wp.tid()
    if kinds[b] == KIND_FIXED:
        return
    x = bodies.x
    v = bodies.v
    w = bodies.w
    q = bodies.q
    p = x[b]
    x[b] = wp.vec3(p[0], p[1], z0[b])
    pl = bodies.x_lo[b]
    bodies.x_lo[b] = wp.vec3(pl[0], pl[1], 0.0)
    u = v[b]
    v[b] = wp.vec3(u[0], u[1], 0.0)
    o = w[b]
    w[b] = wp.vec3(0.0, 0.0, o[2])
    r = q[b]
    rl = bodies.q_lo[b]
    qh, ql = unit_compensated(wp.quat(0.0, 0.0, r[2], r[3]), wp.quat(0.0, 0.0, rl[2], rl[3]))
    q[b] = qh
    bodies.q_lo[b] = ql


@wp.kernel
def clear_forces(loads: BlockLoads):
    b = wp.tid()
    loads.force[b] = wp.vec3(0.0, 0.0, 0.0)
    loads.torque[b] = wp.vec3(0.0, 0.0, 0.0)
    loads.strain_force[b] = wp.spatial_vector(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    loads.damp_c[b] = sym6()
    loads.damp_b[b] = wp.spatial_vector()


@wp.kernel
def vertex_walk_count(vertex_out_he: wp.array(dtype=int), he_next: wp.array(dtype=int), he_twin: wp.array(dtype=int),
                      count: wp.array(dtype=int)):
    # half-edges leaving vertex v, walked around it as narrow_phase does (at most MAX_VALENCE)
    v = wp.tid()
    h0 = vertex_out_he[v]
    h = h0
    c = int(0)
    for k in range(MAX_VALENCE):
        c += 1
        h = he_next[he_twin[h]]
        if h == h0:
            break
    count[v] = c


@wp.kernel
def vertex_walk_fill(vertex_out_he: wp.array(dtype=int), he_next: wp.array(dtype=int), he_twin: wp.array(dtype=int),
                     offset: wp.array(dtype=int), he_walk: wp.array(dtype=int)):
    # BlockTopology.he_walk: vertex v's outgoing half-edges in walk order from offset[v]
    v = wp.tid()
    h0 = vertex_out_he[v]
    h = h0
    o = offset[v]
    for k in range(MAX_VALENCE):
        he_walk[o + k] = h
        h = he_next[he_twin[h]]
        if h == h0:
            break
