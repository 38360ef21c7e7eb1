"""Water pressure in the joints between blocks (Warp kernels; rockwave/coupling/joint_water.py).

A contact point of two blocks below the water's surface gets the hydrostatic pore pressure of the water around it,

    u = rho0 |g| max(z_s - z_p, 0),

z_p the point's height, z_s the free surface over it: the highest fluid particle in its column (and the two columns
beside it, each way) + s / 2 (a particle stands for the cell around it). The force u a n acts on B at the point and
-u a n on A (n the contact normal from A to B, a the point's share of the contact patch's area): the water in a joint
open to it pushes the two faces apart (Hoek & Bray's uplift U), the penalty spring carries F_n - U at equilibrium and
the Coulomb cap becomes mu (F_n - U) by itself (Terzaghi's effective stress). A column without water (z_s below every
particle: none) gives u = 0, a dry joint.
"""

import warp as wp

from rockwave.kernels.dda.blocks import BlockBodies, BlockLoads, ContactTable, contact_tangent

wp.set_module_options({"enable_backward": False})  # forward kernels only: nothing here is differentiated

NO_WATER = wp.constant(-1.0e30)


@wp.func
def column_of(p: wp.vec3, lo: wp.vec3, inv_s: float, ncol: wp.vec2i, up: int):
    # the (i, j) column of point p in the surface map: the two axes other than ``up``, clamped to the map
    a0 = 0
    a1 = 1
    if up == 0:
        a0 = 1
        a1 = 2
    elif up == 1:
        a1 = 2
    i = wp.clamp(int(wp.floor((p[a0] - lo[a0]) * inv_s)), 0, ncol[0] - 1)
    j = wp.clamp(int(wp.floor((p[a1] - lo[a1]) * inv_s)), 0, ncol[1] - 1)
    return i, j


@wp.kernel
def surface_map(x: wp.array(dtype=wp.vec3), lo: wp.vec3, inv_s: float, ncol: wp.vec2i, up: int,
                height: wp.array(dtype=float)):
    """Highest fluid particle per column (height pre-filled with NO_WATER), atomic max."""
    i = wp.tid()
    p = x[i]
    ci, cj = column_of(p, lo, inv_s, ncol, up)
    wp.atomic_max(height, ci * ncol[1] + cj, p[up])


@wp.kernel
def joint_uplift(
    table: ContactTable,
    nblocks: int,
    kinds: wp.array(dtype=int),
    bodies: BlockBodies,
    lo: wp.vec3,
    inv_s: float,
    ncol: wp.vec2i,
    up: int,
    half_s: float,
    rho_g: float,
    height: wp.array(dtype=float),
    loads: BlockLoads,
):
    """Uplift at the contact points of the block step just taken (BlockState.tables[0]); one thread per pair slot.
    The points are relative to A's centroid x + x_lo (kernels/dda/blocks.py contact_forces), their area shares the
    patch polygon's area over the points, as contact_forces forms them."""
    s = wp.tid()
    key = table.keys[s]
    if key < wp.int64(0):
        return
    nc = table.nc[s]
    if nc == 0:
        return
    A = int(key / wp.int64(nblocks))
    B = int(key - wp.int64(A) * wp.int64(nblocks))
    base = table.pstart[s]
    n = table.normal[s]
    xa = bodies.x[A] + bodies.x_lo[A]
    xB = (bodies.x[B] - bodies.x[A]) + (bodies.x_lo[B] - bodies.x_lo[A])
    t1 = contact_tangent(n)
    t2 = wp.cross(n, t1)
    cen = wp.vec3(0.0, 0.0, 0.0)
    for k in range(nc):
        cen = cen + table.pos[base + k]
    cen = cen / float(nc)
    area = float(0.0)
    if nc >= 3:  # the convex patch through the points in angular order (contact_forces)
        for k in range(nc):
            rk = table.pos[base + k] - cen
            ak = wp.atan2(wp.dot(rk, t2), wp.dot(rk, t1))
            best = float(1.0e9)
            nxt = int(-1)
            for m in range(nc):
                rm = table.pos[base + m] - cen
                am = wp.atan2(wp.dot(rm, t2), wp.dot(rm, t1))
                da = am - ak
                if da <= 0.0:
                    da = da + 6.283185307
                if m != k and da < best:
                    best = da
                    nxt = m
            if nxt >= 0:
                rn = table.pos[base + nxt] - cen
                area = area + 0.5 * wp.dot(wp.cross(rk, rn), n)
    a_share = wp.abs(area) / float(nc)
    if a_share <= 0.0:
        return
    for k in range(nc):
        p = table.pos[base + k]
        pw = xa + p
        ci, cj = column_of(pw, lo, inv_s, ncol, up)
        zs = float(NO_WATER)
        for di in range(-2, 3):
            for dj in range(-2, 3):
                ii = ci + di
                jj = cj + dj
                if ii >= 0 and ii < ncol[0] and jj >= 0 and jj < ncol[1]:
                    zs = wp.max(zs, height[ii * ncol[1] + jj])
        if zs > NO_WATER:
            u = rho_g * (zs + half_s - pw[up])
            if u > 0.0:
                f = (u * a_share) * n  # on B; -f on A
                if kinds[B] < 2:  # rigid or deformable (fixed and kinematic blocks take no load)
                    wp.atomic_add(loads.ext_force, B, f)
                    wp.atomic_add(loads.ext_torque, B, wp.cross(p - xB, f))
                if kinds[A] < 2:
                    wp.atomic_add(loads.ext_force, A, -f)
                    wp.atomic_add(loads.ext_torque, A, wp.cross(p, -f))
