"""Wall particles of moving blocks (Warp), launched by rockwave/coupling/walls.py (BlockWalls).

Adami et al. (2012) walls on moving blocks (rockwave/coupling/walls.py BlockWalls): a lattice of wall particles
inside each block's faces, stored in the body frame, placed each step from the block's pose with the block's
rigid velocity and acceleration (for the no-slip and the wall-acceleration terms of Adami's eqs. 23 and 27);
the fluid step extrapolates their pressure (kernels/sph/fluid.py wall_pressure_adami) and the force each fluid
particle feels from them is summed back, equal and opposite, onto the block.
"""

import warp as wp

from rockwave.kernels.coupling.penalty import KIND_DEFORMABLE, KIND_KINEMATIC, KIND_RIGID
from rockwave.kernels.dda.blocks import BlockBodies, BlockLoads
from rockwave.kernels.sph import fluid as sph

wp.set_module_options({"enable_backward": False})  # forward kernels only: nothing here is differentiated


@wp.kernel
def block_wall_motion(
    bodies: BlockBodies,
    dt_prev: wp.array(dtype=float),
    v_prev: wp.array(dtype=wp.vec3),
    w_prev: wp.array(dtype=wp.vec3),
    acc: wp.array(dtype=wp.vec3),
    ang_acc: wp.array(dtype=wp.vec3),
):
    """Per block: its acceleration over the last fluid step from its velocities at the start of that step and
    now, a = (v - v_prev) / dt_prev, alpha = (w - w_prev) / dt_prev (zero before the first step, dt_prev = 0);
    then v_prev = v, w_prev = w for the next step (explicit: the block moves after the water's step)."""
    b = wp.tid()
    h = dt_prev[0]
    v = bodies.v[b]
    w = bodies.w[b]
    a = wp.vec3(0.0)
    al = wp.vec3(0.0)
    if h > 0.0:
        a = (v - v_prev[b]) / h
        al = (w - w_prev[b]) / h
    acc[b] = a
    ang_acc[b] = al
    v_prev[b] = v
    w_prev[b] = w


@wp.kernel
def place_block_walls(
    body_r: wp.array(dtype=wp.vec3),
    wall_block: wp.array(dtype=int),
    bodies: BlockBodies,
    acc: wp.array(dtype=wp.vec3),
    ang_acc: wp.array(dtype=wp.vec3),
    planar: int,
    x_off: int,
    a_off: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    wall_accel: wp.array(dtype=wp.vec3),
):
    """Wall particle t of block b from the block's pose: x = c + R r, v = v_c + w x (R r),
    a = a_c + alpha x (R r) + w x (w x R r) (rigid-body kinematics); particle x_off + t of the fluid arrays,
    acceleration slot a_off + t. planar (2D): the particles stay in the z = 0 plane."""
    t = wp.tid()
    b = wall_block[t]
    r = wp.quat_rotate(bodies.q[b], body_r[t])
    xw = bodies.x[b] + r
    if planar != 0:
        xw = wp.vec3(xw[0], xw[1], 0.0)
    w = bodies.w[b]
    x[x_off + t] = xw
    v[x_off + t] = bodies.v[b] + wp.cross(w, r)
    wall_accel[a_off + t] = acc[b] + wp.cross(ang_acc[b], r) + wp.cross(w, wp.cross(w, r))


@wp.kernel
def block_wall_reactions(
    g: sph.CellGrid,
    r_lo: int,
    r_hi: int,
    R: float,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    wall_pr2: wp.array(dtype=wp.vec2),
    wall_v: wp.array(dtype=wp.vec3),
    xq: wp.array(dtype=wp.vec3),
    b_off: int,
    wall_block: wp.array(dtype=int),
    p: sph.SPHParams,
    bodies: BlockBodies,
    kinds: wp.array(dtype=int),
    depth_scale: wp.array(dtype=float),
    loads: BlockLoads,
    water_force: wp.array(dtype=wp.vec3),
    water_torque: wp.array(dtype=wp.vec3),
):
    """The force of the water on the wall particle b_off + t of a moving block: minus the sum over the fluid
    particles f within H of m_f a_fb, a_fb the acceleration the force pass gave f from that wall particle
    (kernels/sph/fluid.py wall_pair_acceleration, the same terms and values: Adami's momentum-conserving pressure
    term, and the viscous ones with no-slip walls), so the water and the block exchange equal and opposite
    forces. It acts at the wall particle (the pressure pair force lies along x_f - x_b: no spurious torque).
    Summed per block into water_force / water_torque (about the centroid; 2D: times the block's z-extent) and,
    for rigid and deformable blocks, into their loads (ext_force / ext_torque, held over the block sub-steps
    like the penalty's). Cell query of radius R at the particle's position of the last list build (xq), as in
    wall_pressure_adami."""
    t = wp.tid()
    bi = b_off + t
    xb = x[p.n_fluid + bi]
    xc = xq[bi]
    H2 = p.H * p.H
    mb = particle_mass[p.n_fluid + bi]
    f = wp.vec3(0.0)
    ix, iy, iz = sph.cell_of(g, xc)
    for r in range(r_lo, r_hi):
        s0, e0 = sph.slot_range(g, xc, R, iy, iz, r)
        for k in range(s0, e0):
            i = g.order[k]
            if i < p.n_fluid:
                rij = x[i] - xb
                r2 = wp.length_sq(rij)
                if r2 < H2:
                    gw = sph.kernel_grad(rij, wp.sqrt(r2), p)
                    a = sph.wall_pair_acceleration(bi, rij, r2, gw, v[i], rho[i], pr2[i], mb, wall_pr2, wall_v, p)
                    f += p.fluid_mass * a
    if wp.length_sq(f) == 0.0:
        return
    blk = wall_block[t]
    fb = -depth_scale[blk] * f
    tb = wp.cross(xb - bodies.x[blk], fb)
    wp.atomic_add(water_force, blk, fb)
    wp.atomic_add(water_torque, blk, tb)
    kind = kinds[blk]
    if kind == KIND_RIGID or kind == KIND_DEFORMABLE:
        wp.atomic_add(loads.ext_force, blk, fb)
        wp.atomic_add(loads.ext_torque, blk, tb)


@wp.kernel
def kinematic_wall_work(
    kinds: wp.array(dtype=int),
    bodies: BlockBodies,
    water_force: wp.array(dtype=wp.vec3),
    water_torque: wp.array(dtype=wp.vec3),
    depth_scale: wp.array(dtype=float),
    dt: wp.array(dtype=float),
    wall_work: wp.array(dtype=float),
):
    """The work of a kinematic block's wall particles on the water over the step, -dt (F . v + T . w) / depth (F, T:
    the water's force and torque on the block, block_wall_reactions; per metre of depth in 2D), into wall_work[0]."""
    b = wp.tid()
    if kinds[b] != KIND_KINEMATIC:
        return
    p = wp.dot(water_force[b], bodies.v[b]) + wp.dot(water_torque[b], bodies.w[b])
    wp.atomic_add(wall_work, 0, -dt[0] * p / depth_scale[b])
