"""Fluid <-> block coupling kernels (Warp): penalty repulsion between SPH particles and the faces
of convex DDA blocks, after Nezami et al. (SPH-DDA 3D rock-fluid paper, Eq. 22)::

    f_i = (K_s d_i - K_d (v_rel . n)) n ,   d_i = d0 - dist_i > 0

with dist_i the signed distance of particle i to the block (max over the block's face planes:
exact inside a convex block, a slight under-estimate outside near edges and corners), n the
outward normal of the face that attains the max, d0 the contact distance and v_rel the particle
velocity relative to the block surface point. The force is clipped at zero (no suction). The
equal and opposite force, applied at the projection of the particle onto the face (the same line
of action, so angular momentum is conserved too), goes to the block's ext_force / ext_torque.

Squeeze-out (rockwave/coupling/penalty.py): a particle touching a block face and pinched by an opposing
solid face within the gap w_s = 2 d0 + H gets its normal force turned to mag (n + lambda t), t the way
out of the gap (towards the nearest side face of the moving block; none if the other face closes the gap
before it: a wedge's apex), lambda = (w_s - w)/(w_s - 2 d0);
the film drains and a block can settle on a floor or on another block.

Broad phase ("a scene pays only for what it contains"): each block's AABB, grown by max(d0, w_s), is clipped
to the AABB of the fluid particles; blocks outside it are skipped entirely. The cells of a uniform
grid (cell size S) covered by the clipped box are hashed into buckets (counting sort); a particle
reads only the bucket of its own cell. Blocks covering more than ``max_cells`` cells go to a short
"large" list that every particle tests.
"""

import warp as wp

from rockwave.kernels.dda.blocks import BlockBodies, BlockLoads
from rockwave.kernels.sph.fluid import step_of

wp.set_module_options({"enable_backward": False})  # forward kernels only: nothing here is differentiated

KIND_RIGID = wp.constant(0)
KIND_DEFORMABLE = wp.constant(1)
KIND_FIXED = wp.constant(2)
KIND_KINEMATIC = wp.constant(3)
BIG = wp.constant(1.0e30)


@wp.kernel
def fluid_bounds(x: wp.array(dtype=wp.vec3), n: int, stride: int, bounds: wp.array(dtype=float)):
    """bounds[0:3] = min, bounds[3:6] = max of the first n positions (pre-filled with +-BIG). Launched
    over `stride` threads, each reducing every stride-th particle before its six atomics: one atomic
    per particle and axis contended on six words (0.55 ms per step at 1.24 M particles on an H100)."""
    t = wp.tid()
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    i = t
    while i < n:
        p = x[i]
        lo = wp.min(lo, p)
        hi = wp.max(hi, p)
        i += stride
    for k in range(3):
        wp.atomic_min(bounds, k, lo[k])
        wp.atomic_max(bounds, 3 + k, hi[k])


@wp.kernel
def face_planes(
    face_block: wp.array(dtype=int),
    body_normal: wp.array(dtype=wp.vec3),
    body_offset: wp.array(dtype=float),
    bx: wp.array(dtype=wp.vec3),
    bq: wp.array(dtype=wp.quat),
    n_out: wp.array(dtype=wp.vec3),
    d_out: wp.array(dtype=float),
):
    """World face planes n . x = d of the (rigidly moved) blocks."""
    f = wp.tid()
    b = face_block[f]
    n = wp.quat_rotate(bq[b], body_normal[f])
    n_out[f] = n
    d_out[f] = wp.dot(n, bx[b]) + body_offset[f]


@wp.struct
class CouplingParams:
    """The penalty law and broad-phase cell of a Coupling (built once)."""

    k_s: float  # penalty stiffness K_s [N/m per particle; N/m per m of depth in 2D]
    k_d: float  # penalty damping K_d [N s/m]
    d0: float  # contact distance [m]
    inv_s: float  # 1 / broad-phase cell size
    track_walls: int  # 1: sum the forces of fixed/kinematic blocks on the water (diagnostics)
    squeeze_gap: float  # gap w_s between two opposing solid faces below which pinched water is squeezed out (0: off)
    squeeze_speed: float  # closing speed above which a pinch is an impact, not squeezed: sqrt(|g| d0) [m/s]


@wp.struct
class CouplingGrid:
    """Blocks near the water (Coupling's broad phase): each block's cell range, cell count and the
    exclusive scan of the counts (its first entry); the hashed buckets of (block, cell) entries
    (nbuckets, start, count, fill; entry block and cell), the large blocks every particle tests
    (counters[1] of them), the counters ([0] entries, [1] large blocks) and each block's grown,
    clipped box."""

    cell_lo: wp.array(dtype=wp.vec3i)
    cell_hi: wp.array(dtype=wp.vec3i)
    ncell: wp.array(dtype=int)
    cell_offset: wp.array(dtype=int)
    nbuckets: int
    bucket_start: wp.array(dtype=int)
    bucket_count: wp.array(dtype=int)
    bucket_fill: wp.array(dtype=int)
    entry_block: wp.array(dtype=int)
    entry_cell: wp.array(dtype=wp.vec3i)
    large: wp.array(dtype=int)
    counters: wp.array(dtype=int)
    box_lo: wp.array(dtype=wp.vec3)
    box_hi: wp.array(dtype=wp.vec3)


@wp.struct
class BlockFaces:
    """World face planes n . x = d of the blocks (face_planes), each block's range of faces, its kind,
    its z-extent (2D: forces per metre of depth times it; 3D: 1) and whether it is a wall only (the tank)."""

    face_start: wp.array(dtype=int)
    face_count: wp.array(dtype=int)
    plane_n: wp.array(dtype=wp.vec3)
    plane_d: wp.array(dtype=float)
    kinds: wp.array(dtype=int)
    depth_scale: wp.array(dtype=float)
    wall_only: wp.array(dtype=int)  # 1: a block of the [tank] (its boundary particles hold the water): no penalty force,
    # only the opposing face of a squeeze-out pinch


@wp.func
def cell_of(p: wp.vec3, inv_s: float):
    return wp.vec3i(int(wp.floor(p[0] * inv_s)), int(wp.floor(p[1] * inv_s)), int(wp.floor(p[2] * inv_s)))


@wp.func
def bucket_of(c: wp.vec3i, nbuckets: int):
    h = (c[0] * 73856093) ^ (c[1] * 19349663) ^ (c[2] * 83492791)
    return (h & 2147483647) % nbuckets


@wp.kernel
def block_cells(
    wv: wp.array(dtype=wp.vec3),
    vert_start: wp.array(dtype=int),
    vert_count: wp.array(dtype=int),
    bounds: wp.array(dtype=float),
    reach: float,
    inv_s: float,
    max_cells: int,
    grid: CouplingGrid,
):
    """Per block: AABB grown by `reach`, clipped to the fluid AABB (box_lo/hi: every point within reach
    of the block lies inside); cell range and count (0 when the block is away from all water; blocks over
    max_cells cells go to the large list, all of them when max_cells < 0)."""
    ncell = grid.ncell
    counters = grid.counters
    b = wp.tid()
    s = vert_start[b]
    lo = wv[s]
    hi = wv[s]
    for k in range(1, vert_count[b]):
        p = wv[s + k]
        lo = wp.min(lo, p)
        hi = wp.max(hi, p)
    empty = int(0)
    for k in range(3):
        l = wp.max(lo[k] - reach, bounds[k])
        h = wp.min(hi[k] + reach, bounds[3 + k])
        if l > h:
            empty = 1
        lo[k] = l
        hi[k] = h
    ncell[b] = 0
    grid.box_lo[b] = lo
    grid.box_hi[b] = hi
    if empty == 1:
        return
    cl = cell_of(lo, inv_s)
    ch = cell_of(hi, inv_s)
    grid.cell_lo[b] = cl
    grid.cell_hi[b] = ch
    n = (ch[0] - cl[0] + 1) * (ch[1] - cl[1] + 1) * (ch[2] - cl[2] + 1)
    if n > max_cells or n < 0:
        slot = wp.atomic_add(counters, 1, 1)
        grid.large[slot] = b
        return
    ncell[b] = n
    wp.atomic_add(counters, 0, n)


@wp.func
def nth_cell(cl: wp.vec3i, ch: wp.vec3i, e: int) -> wp.vec3i:
    """The e-th cell of the range [cl, ch] (k fastest, as the former nested loops)."""
    nk = ch[2] - cl[2] + 1
    nj = ch[1] - cl[1] + 1
    return wp.vec3i(cl[0] + e / (nj * nk), cl[1] + (e / nk) % nj, cl[2] + e % nk)


@wp.func
def entry_of(t: int, cell_offset: wp.array(dtype=int)):
    """(block b, cell e of its range) of entry t: the last b with cell_offset[b] <= t."""
    lo = int(0)
    hi = cell_offset.shape[0] - 1
    while lo < hi:
        mid = (lo + hi + 1) / 2
        if cell_offset[mid] <= t:
            lo = mid
        else:
            hi = mid - 1
    return lo, t - cell_offset[lo]


@wp.func
def bucket_count_cell(cl: wp.vec3i, ch: wp.vec3i, e: int, nbuckets: int, bucket_count: wp.array(dtype=int)):
    wp.atomic_add(bucket_count, bucket_of(nth_cell(cl, ch, e), nbuckets), 1)


@wp.kernel
def count_buckets(grid: CouplingGrid):
    # one thread per (block, cell) entry, cell_offset = exclusive scan of ncell (a serial loop per
    # block made this phase 1.7 ms of a 6.3 ms coupled step at 1.2 M particles on an H100); launched
    # over the entry capacity, the threads past the device count (counters[0]) stop
    if wp.tid() >= grid.counters[0]:
        return
    b, e = entry_of(wp.tid(), grid.cell_offset)
    bucket_count_cell(grid.cell_lo[b], grid.cell_hi[b], e, grid.nbuckets, grid.bucket_count)


@wp.kernel
def fill_buckets(grid: CouplingGrid):
    if wp.tid() >= grid.counters[0]:
        return
    b, e = entry_of(wp.tid(), grid.cell_offset)  # as count_buckets
    c = nth_cell(grid.cell_lo[b], grid.cell_hi[b], e)
    h = bucket_of(c, grid.nbuckets)
    slot = grid.bucket_start[h] + wp.atomic_add(grid.bucket_fill, h, 1)
    grid.entry_block[slot] = b
    grid.entry_cell[slot] = c


PINCH_COS = wp.constant(0.7071)  # two faces oppose (pinch a gap) when n_a . n_b < -cos 45 deg
SIDE_COS = wp.constant(0.7071)  # exit faces of the moving block: |n_k . n| < cos 45 deg (its sides)
WEDGE_SIN = wp.constant(0.3827)  # a pinch is a wedge, not a film, when its faces open at more than half the pinch
# cone's 45 deg: sin 22.5 deg (a block landing on a floor stays below it; a box's front face over the floor at the toe
# of a 60 deg plane opens at 30 deg)


@wp.func
def in_box(xi: wp.vec3, lo: wp.vec3, hi: wp.vec3):
    return xi[0] >= lo[0] and xi[0] <= hi[0] and xi[1] >= lo[1] and xi[1] <= hi[1] and xi[2] >= lo[2] and xi[2] <= hi[2]


@wp.func
def block_distance(
    b: int,
    xi: wp.vec3,
    face_start: wp.array(dtype=int),
    face_count: wp.array(dtype=int),
    plane_n: wp.array(dtype=wp.vec3),
    plane_d: wp.array(dtype=float),
):
    """Signed distance of xi to the convex block b (max over its face planes) and that face's normal."""
    fs = face_start[b]
    dist = float(-BIG)
    n = wp.vec3(0.0)
    for k in range(face_count[b]):
        e = wp.dot(plane_n[fs + k], xi) - plane_d[fs + k]
        if e > dist:
            dist = e
            n = plane_n[fs + k]
    return dist, n


@wp.func
def exit_direction(
    b: int,
    xi: wp.vec3,
    n: wp.vec3,
    face_start: wp.array(dtype=int),
    face_count: wp.array(dtype=int),
    plane_n: wp.array(dtype=wp.vec3),
    plane_d: wp.array(dtype=float),
):
    """Unit direction, in the plane of block b's face with normal n, towards the nearest side face of
    b (the shortest way out of the gap under that face; zero if b has no such side face), and the distance to
    that side face's plane along the face (0 when the point is beyond it)."""
    fs = face_start[b]
    best = float(-BIG)
    t = wp.vec3(0.0)
    for k in range(face_count[b]):
        nk = plane_n[fs + k]
        c = wp.dot(nk, n)
        if wp.abs(c) < SIDE_COS:
            e = wp.dot(nk, xi) - plane_d[fs + k]
            if e > best:
                best = e
                t = nk - c * n
    edge = float(0.0)
    if wp.length(t) > 0.0:
        edge = wp.max(-best, 0.0) / wp.length(t)  # the side face's plane reached along the face, not along its normal
        t = wp.normalize(t)
    return t, edge


@wp.func
def block_contact(
    b: int,
    xi: wp.vec3,
    vi: wp.vec3,
    p: CouplingParams,
    squeeze: wp.vec3,
    faces: BlockFaces,
    bodies: BlockBodies,
    loads: BlockLoads,
    wall_force: wp.array(dtype=wp.vec3),
    wall_work: wp.array(dtype=float),
    dt: float,
):
    """Penalty force of block b on a particle at xi moving at vi; ``squeeze`` (lambda t, zero outside
    a pinch) turns the force to n + lambda t: the squeeze-out push along the gap (module docstring). A kinematic
    block's work on the particle over the step, dt f . v_surface, is added to wall_work[0] (the energy budget)."""
    dist, n = block_distance(b, xi, faces.face_start, faces.face_count, faces.plane_n, faces.plane_d)
    f = wp.vec3(0.0)
    if dist < p.d0:
        c = bodies.x[b]
        xc = xi - dist * n  # projection onto the face plane (same line of action as f)
        vs = bodies.v[b] + wp.cross(bodies.w[b], xc - c)
        vn = wp.dot(vi - vs, n)
        mag = p.k_s * (p.d0 - dist) - p.k_d * vn
        if mag > 0.0:
            f = mag * (n + squeeze)
            kind = faces.kinds[b]
            if kind != KIND_FIXED and kind != KIND_KINEMATIC:
                fb = -faces.depth_scale[b] * f
                wp.atomic_add(loads.ext_force, b, fb)
                wp.atomic_add(loads.ext_torque, b, wp.cross(xc - c, fb))
            else:
                if p.track_walls != 0:
                    wp.atomic_add(wall_force, 0, f)
                if kind == KIND_KINEMATIC:
                    wp.atomic_add(wall_work, 0, dt * wp.dot(f, vs))
    return f


@wp.func
def surface_velocity(b: int, xi: wp.vec3, kinds: wp.array(dtype=int), bodies: BlockBodies):
    """Velocity of block b's rigid motion at xi (zero for a fixed block)."""
    if kinds[b] == KIND_FIXED:
        return wp.vec3(0.0)
    return bodies.v[b] + wp.cross(bodies.w[b], xi - bodies.x[b])


@wp.func
def pinch_force(dist: float, vn: float, p: CouplingParams):
    """Magnitude of the penalty force of a face at distance dist on a particle approaching it at -vn."""
    return wp.max(p.k_s * (p.d0 - dist) - p.k_d * vn, 0.0)


@wp.kernel
def squeeze_energy(sq_power: wp.array(dtype=wp.vec2), sq_scale: wp.array(dtype=float)):
    """Per block, after a step's forces: the scale of next step's squeeze-out push, the ratio of the power the
    closing gaps took from the block (pinch force x closing speed, summed over its pinched particles) to the power
    the push gave the water along the gaps (push x the particles' speed out), at most 1; then the sums are cleared."""
    b = wp.tid()
    pw = sq_power[b]
    s = float(1.0)
    if pw[1] > 0.0:
        s = wp.min(1.0, pw[0] / pw[1])
    sq_scale[b] = s
    sq_power[b] = wp.vec2(0.0, 0.0)


@wp.kernel
def particle_block_forces(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=float),
    dt: wp.array(dtype=float),
    p: CouplingParams,
    grid: CouplingGrid,
    faces: BlockFaces,
    bodies: BlockBodies,
    loads: BlockLoads,
    wall_force: wp.array(dtype=wp.vec3),
    wall_work: wp.array(dtype=float),
    sq_power: wp.array(dtype=wp.vec2),
    sq_scale: wp.array(dtype=float),
    dv: wp.array(dtype=wp.vec3),
):
    """Penalty force of every nearby block on fluid particle i, stored as the velocity change
    dv_i = dt f_i / m_i (applied after the fluid step); reactions go to the blocks (loads.ext_force,
    loads.ext_torque).

    Three passes over the candidate blocks (the bucket of the particle's cell and the large list):
    the nearest block a; if the particle touches it (dist < d0), the nearest block b whose face
    opposes a's (a pinch: the particle is in a gap of width w = dist_a + dist_b); then the forces."""
    bucket_start = grid.bucket_start
    bucket_count = grid.bucket_count
    entry_block = grid.entry_block
    entry_cell = grid.entry_cell
    large = grid.large
    counters = grid.counters
    box_lo = grid.box_lo
    box_hi = grid.box_hi
    face_start = faces.face_start
    face_count = faces.face_count
    plane_n = faces.plane_n
    plane_d = faces.plane_d
    kinds = faces.kinds
    i = wp.tid()
    step = step_of(dt, i)  # this particle's step (a batch: its scenario's)
    xi = x[i]
    vi = v[i]
    c = cell_of(xi, p.inv_s)
    h = bucket_of(c, grid.nbuckets)
    s = bucket_start[h]
    # pass 1: nearest block
    ba = int(-1)
    da = float(BIG)
    na = wp.vec3(0.0)
    wall_only = faces.wall_only
    for e in range(s, s + bucket_count[h]):
        if entry_cell[e] == c:
            b = entry_block[e]
            if wall_only[b] != 0:
                continue
            d, n = block_distance(b, xi, face_start, face_count, plane_n, plane_d)
            if d < da:
                ba = b
                da = d
                na = n
    for k in range(counters[1]):
        b = large[k]
        if wall_only[b] != 0 or not in_box(xi, box_lo[b], box_hi[b]):  # a tank wall, or farther than reach from b
            continue
        d, n = block_distance(b, xi, face_start, face_count, plane_n, plane_d)
        if d < da:
            ba = b
            da = d
            na = n
    if da >= p.d0:
        dv[i] = wp.vec3(0.0)
        return
    # pass 2: a pinch, the nearest opposing solid within the squeeze gap
    squeeze = wp.vec3(0.0)
    bb = int(-1)
    if p.squeeze_gap > 0.0:
        db = float(p.squeeze_gap - da)
        nb = wp.vec3(0.0)
        for e in range(s, s + bucket_count[h]):
            if entry_cell[e] == c:
                b = entry_block[e]
                if b != ba:
                    d, n = block_distance(b, xi, face_start, face_count, plane_n, plane_d)
                    if d < db and wp.dot(n, na) < -PINCH_COS:
                        bb = b
                        db = d
                        nb = n
        for k in range(counters[1]):
            b = large[k]
            if b != ba and in_box(xi, box_lo[b], box_hi[b]):
                d, n = block_distance(b, xi, face_start, face_count, plane_n, plane_d)
                if d < db and wp.dot(n, na) < -PINCH_COS:
                    bb = b
                    db = d
                    nb = n
        if bb >= 0:
            # the block that moves sets the way out (the nearest edge of its face); two walls: none
            t = wp.vec3(0.0)
            edge = float(0.0)
            bm = int(-1)
            if kinds[ba] != KIND_FIXED:
                t, edge = exit_direction(ba, xi, na, face_start, face_count, plane_n, plane_d)
                bm = ba
            elif kinds[bb] != KIND_FIXED:
                t, edge = exit_direction(bb, xi, nb, face_start, face_count, plane_n, plane_d)
                bm = bb
            # a wedge (its faces open at more than 22.5 deg), not a film: t lies in the moving face's plane; if the
            # way along t runs into the other face (its distance d_o + s t.n_o reaches 0) before it passes the moving
            # face's edge (s = edge), that edge is the wedge's apex, not a way out, and there is no push (a block's
            # front face leaning over the floor it rests on: pushing the water into the apex pressed it through the
            # floor, docs/notes.md 'Why the box slides read +100%'). A film (faces within 22.5 deg of parallel) is
            # squeezed as before.
            n_o = nb
            d_o = db
            if bm == bb:
                n_o = na
                d_o = da
            g = wp.dot(t, n_o)
            if g < -WEDGE_SIN and d_o < -g * edge:
                t = wp.vec3(0.0)
            w = wp.max(da + db, 2.0 * p.d0)
            lam = wp.min(1.0, (p.squeeze_gap - w) / wp.max(p.squeeze_gap - 2.0 * p.d0, 1.0e-12))
            if bm >= 0:
                # energy: the push along the gap may give the water only what the closing gap takes from the block
                # that moves (squeeze_energy: last step's ratio of the two powers, per block)
                va = surface_velocity(ba, xi, kinds, bodies)
                vb = surface_velocity(bb, xi, kinds, bodies)
                mag = pinch_force(da, wp.dot(vi - va, na), p)
                if wall_only[bb] == 0:
                    mag += pinch_force(db, wp.dot(vi - vb, nb), p)
                closing = wp.dot(va - vb, na)  # the gap's closing speed (the faces' normals oppose)
                u = wp.dot(vi - surface_velocity(bm, xi, kinds, bodies), t)  # the particle's speed out of the gap
                # an impact (the gap closing faster than a fall through d0 gives) is left to the water's own pressure
                lam = lam * wp.max(0.0, 1.0 - closing / p.squeeze_speed)
                wp.atomic_add(sq_power, bm, wp.vec2(mag * wp.max(closing, 0.0), lam * mag * wp.max(u, 0.0)))
                lam = lam * sq_scale[bm]
            squeeze = lam * t
    # pass 3: forces
    f = wp.vec3(0.0)
    zero = wp.vec3(0.0)
    for e in range(s, s + bucket_count[h]):
        if entry_cell[e] == c:
            b = entry_block[e]
            if wall_only[b] != 0:
                continue
            sq = zero
            if b == ba or b == bb:  # only the two faces of the pinch push along the gap
                sq = squeeze
            f += block_contact(b, xi, vi, p, sq, faces, bodies, loads, wall_force, wall_work, step)
    for k in range(counters[1]):
        b = large[k]
        if wall_only[b] != 0 or not in_box(xi, box_lo[b], box_hi[b]):
            continue
        sq = zero
        if b == ba or b == bb:
            sq = squeeze
        f += block_contact(b, xi, vi, p, sq, faces, bodies, loads, wall_force, wall_work, step)
    dv[i] = (step / particle_mass[i]) * f


@wp.kernel
def apply_dv(dv: wp.array(dtype=wp.vec3), dt: wp.array(dtype=float), x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3)):
    """Add the coupling impulse after the fluid step: the same update as including f/m in the
    semi-implicit Euler acceleration (v += dt a; x += dt v)."""
    i = wp.tid()
    d = dv[i]
    v[i] = v[i] + d
    x[i] = x[i] + step_of(dt, i) * d


@wp.kernel
def signed_distance_to_blocks(
    x: wp.array(dtype=wp.vec3),
    n_blocks: int,
    face_start: wp.array(dtype=int),
    face_count: wp.array(dtype=int),
    plane_n: wp.array(dtype=wp.vec3),
    plane_d: wp.array(dtype=float),
    out: wp.array(dtype=float),
    which: wp.array(dtype=int),
):
    """Smallest signed distance of each point to any block (brute force: start-up and diagnostics)."""
    i = wp.tid()
    xi = x[i]
    best = float(BIG)
    bb = int(-1)
    for b in range(n_blocks):
        fs = face_start[b]
        dist = float(-BIG)
        for k in range(face_count[b]):
            dist = wp.max(dist, wp.dot(plane_n[fs + k], xi) - plane_d[fs + k])
        if dist < best:
            best = dist
            bb = b
    out[i] = best
    which[i] = bb
