"""List-free fluid passes (``fluid.neighbours = 'cells'``, issue 40): each pass gathers its neighbours straight from
the sorted cell grid (kernels/sph/fluid.py CellGrid) instead of reading a stored Verlet list, launched by
rockwave/sph/fluid.py FluidSolver in place of the ``*_list`` kernels of kernels/sph/fluid.py, diffusion.py and
shifting.py.

The grid is the one the list path builds (particles sorted by cell, fluid and boundary particles alike), kept
between rebuilds by the same skin check. A query is centred on the particle's position at the last build
(x_build) with the list radius R = (1 + skin) H, so it visits the candidates the list build visited, in the same
slot order, and keeps those closer than H now: the pair set and the summation order of the list path (the skin
check guarantees that a pair now closer than H was closer than R at the build). Each pair term is the list
kernel's own function (pair_density_rate, pair_acceleration_fluid, ...); pairs at r >= H add an exact zero.
What is saved: the list's 4 B x capacity per particle (216 slots at support 3 with a 5% skin: 864 B) and the
list build's writes; what is paid: every pass visits the candidates of the runs (3.8x the neighbours within H at
support 3 with the default cell_span) and reads their current positions.
"""

from __future__ import annotations

import warp as wp

from rockwave.kernels.sph.diffusion import diffusion_pair
from rockwave.kernels.sph.fluid import (
    DENSITY_CONTINUITY,
    DENSITY_SUMMATION,
    CellGrid,
    SPHParams,
    cell_of,
    continuity_floor,
    equation_of_state,
    kernel_grad,
    kernel_w,
    kgc_blend,
    own_correction,
    pair_acceleration_fluid,
    pair_density_rate,
    slot_range,
    step_of,
)
from rockwave.kernels.sph.shifting import SPLASH_LAMBDA, band_pair, band_start, shift_finish, surface_finish, surface_pair

wp.set_module_options({"enable_backward": False})  # forward kernels only


@wp.func
def candidate(g: CellGrid, k: int, xq: wp.vec3, R: float) -> int:
    """The particle of sorted slot k, or -1 when the grid prefilters (g.prefilter, FluidOptions.gather_prefilter) and
    its position at the build lies R or farther from the query centre xq: the list build's own test
    (kernels/sph/fluid.py build_neighbour_list_cells), read from the slot-ordered positions (contiguous) before the
    particle's current position (a random read)."""
    if g.prefilter != 0:
        if wp.length_sq(xq - g.x_sorted[k]) >= R * R:
            return -1
    return g.order[k]


@wp.kernel
def store_build_positions_all(x: wp.array(dtype=wp.vec3), rebuild: wp.array(dtype=int), x_build: wp.array(dtype=wp.vec3)):
    """At a rebuild of the cell grid: x_build[i] = x[i] for every fluid particle (the list build's x_build, for
    the skin check and the queries of the gather passes). rebuild[0] == 0: nothing to do."""
    i = wp.tid()
    if rebuild[0] != 0:
        x_build[i] = x[i]


@wp.kernel
def neighbour_count_cells(g: CellGrid, r_lo: int, r_hi: int, R: float, x_build: wp.array(dtype=wp.vec3),
                          x: wp.array(dtype=wp.vec3), H: float, count: wp.array(dtype=int)):
    """Neighbours within H of each fluid particle (self excluded, fluid and boundary) by the gather of the passes."""
    i = wp.tid()
    xi = x[i]
    xq = x_build[i]
    ix, iy, iz = cell_of(g, xq)
    c = int(0)
    for r in range(r_lo, r_hi):
        s0, e0 = slot_range(g, xq, R, iy, iz, r)
        for k in range(s0, e0):
            j = candidate(g, k, xq, R)
            if j >= 0 and j != i and wp.length_sq(xi - x[j]) < H * H:
                c += 1
    count[i] = c


@wp.kernel
def neighbour_count_list(count: wp.array(dtype=int), nbr: wp.array(dtype=int), x: wp.array(dtype=wp.vec3), H: float,
                         out: wp.array(dtype=int)):
    """neighbour_count_cells's count from the neighbour lists (their pairs now closer than H; -1 where a list
    overflowed), for comparing the two searches."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    if c > nbr.shape[0] // n:
        out[i] = -1
        return
    xi = x[i]
    k_in = int(0)
    for k in range(c):
        if wp.length_sq(xi - x[nbr[k * n + i]]) < H * H:
            k_in += 1
    out[i] = k_in


@wp.kernel
def gradient_correction_cells(g: CellGrid, r_lo: int, r_hi: int, R: float, x_build: wp.array(dtype=wp.vec3),
                              x: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float),
                              particle_mass: wp.array(dtype=float), p: SPHParams, kgc: wp.array(dtype=wp.mat33)):
    """kernels/sph/fluid.py gradient_correction_matrix over the cell gather: L_i from
    M_i = sum_j V_j grad W_ij (x) (x_j - x_i) (Bonet & Lok 1999), blended by kgc_blend."""
    i = wp.tid()
    xi = x[i]
    xq = x_build[i]
    H2 = p.H * p.H
    m = wp.mat33(0.0)
    ix, iy, iz = cell_of(g, xq)
    for r in range(r_lo, r_hi):
        s0, e0 = slot_range(g, xq, R, iy, iz, r)
        for k in range(s0, e0):
            j = candidate(g, k, xq, R)
            if j >= 0 and j != i:
                rij = xi - x[j]
                r2 = wp.length_sq(rij)
                if r2 < H2:
                    vol = float(0.0)
                    if j < p.n_fluid:
                        vol = p.fluid_mass / rho[j]
                    else:
                        vol = particle_mass[j] / p.rest_density
                    m += vol * wp.outer(kernel_grad(rij, wp.sqrt(r2), p), -rij)
    kgc[i] = kgc_blend(m, p)


@wp.kernel
def particle_density_cells(
    g: CellGrid,
    r_lo: int,
    r_hi: int,
    R: float,
    x_build: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=float),
    dt: wp.array(dtype=float),
    kgc: wp.array(dtype=wp.mat33),
    p: SPHParams,
    mode: int,
    drho_dt: wp.array(dtype=float),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
):
    """The density pass over the cell gather: DENSITY_SUMMATION rho_i = m_i W(0) + sum_j m_j W_ij
    (particle_density_summation_list); DENSITY_CONTINUITY d rho_i/dt = sum_j m_j (v_i - v_j) . G_ij, then
    rho_i += dt d rho_i/dt (particle_density_continuity_list); then p_i = EOS(rho_i), pr2_i = p_i/rho_i^2."""
    i = wp.tid()
    xi = x[i]
    vi = v[i]
    xq = x_build[i]
    s = float(0.0)
    if mode == DENSITY_SUMMATION:
        s = particle_mass[i] * kernel_w(0.0, p)
    H2 = p.H * p.H
    li = own_correction(kgc, i, p)
    ix, iy, iz = cell_of(g, xq)
    for r in range(r_lo, r_hi):
        s0, e0 = slot_range(g, xq, R, iy, iz, r)
        for k in range(s0, e0):
            j = candidate(g, k, xq, R)
            if j >= 0 and j != i:
                r2 = wp.length_sq(xi - x[j])
                if r2 < H2:  # (the candidates beyond H skip the pair term)
                    if mode == DENSITY_CONTINUITY:
                        s += pair_density_rate(xi, vi, j, x, v, particle_mass, li, kgc, p)
                    else:
                        s += particle_mass[j] * kernel_w(r2, p)
    if mode == DENSITY_CONTINUITY:
        drho_dt[i] = s
        s = continuity_floor(rho[i] + step_of(dt, i) * s, p)
    rho[i] = s
    pr = equation_of_state(s, p)
    pressure[i] = pr
    pr2[i] = pr / (s * s)


# the force pass: a module of its own, as kernels/sph/fluid.py FORCE_PASS_MODULE (launched at its own block size)
GATHER_FORCE_MODULE = "rockwave.kernels.sph.gather_force_pass"


@wp.kernel(module=GATHER_FORCE_MODULE)
def particle_acceleration_cells(
    g: CellGrid,
    r_lo: int,
    r_hi: int,
    R: float,
    x_build: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    wall_pr2: wp.array(dtype=wp.vec2),
    wall_v: wp.array(dtype=wp.vec3),
    kgc: wp.array(dtype=wp.mat33),
    p: SPHParams,
    accel: wp.array(dtype=wp.vec3),
    xsph_dv: wp.array(dtype=wp.vec3),
):
    """kernels/sph/fluid.py particle_acceleration_list over the cell gather: a_i = pressure + viscosity + gravity,
    dv_i the XSPH correction (pair_acceleration_fluid per pair; pairs at r >= H add nothing)."""
    i = wp.tid()
    xi = x[i]
    vi = v[i]
    rhoi = rho[i]
    pi = pressure[i]
    pi_r2 = pr2[i]
    xq = x_build[i]
    H2 = p.H * p.H
    a = wp.vec3(0.0)
    dv = wp.vec3(0.0)
    li = own_correction(kgc, i, p)
    ix, iy, iz = cell_of(g, xq)
    for r in range(r_lo, r_hi):
        s0, e0 = slot_range(g, xq, R, iy, iz, r)
        for k in range(s0, e0):
            j = candidate(g, k, xq, R)
            if j >= 0 and j != i and wp.length_sq(xi - x[j]) < H2:  # (the candidates beyond H skip the pair term's call)
                da, ddv = pair_acceleration_fluid(j, xi, vi, rhoi, pi, pi_r2, x, v, rho, pressure, pr2, particle_mass,
                                                  wall_pr2, wall_v, li, kgc, p)
                a += da
                dv += ddv
    accel[i] = a + p.gravity
    xsph_dv[i] = p.xsph * dv


@wp.kernel
def density_diffusion_rate_cells(
    g: CellGrid,
    r_lo: int,
    r_hi: int,
    R: float,
    x_build: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    wall_pr2: wp.array(dtype=wp.vec2),
    walls: int,
    p: SPHParams,
    delta: float,
    pressure_density: int,
    out: wp.array(dtype=float),
):
    """kernels/sph/diffusion.py density_diffusion_rate over the cell gather (diffusion_pair per pair)."""
    i = wp.tid()
    xi = x[i]
    ri = rho[i]
    clip = pressure_density != 0 and p.clamp_negative != 0
    if clip:
        ri = wp.max(ri, p.rest_density)
    xq = x_build[i]
    s = float(0.0)
    ix, iy, iz = cell_of(g, xq)
    for r in range(r_lo, r_hi):
        s0, e0 = slot_range(g, xq, R, iy, iz, r)
        for k in range(s0, e0):
            j = candidate(g, k, xq, R)
            if j >= 0 and j != i:
                s += diffusion_pair(xi, ri, j, x, rho, particle_mass, wall_pr2, walls, clip, p)
    out[i] = delta * 0.5 * p.H * p.sound_speed * s


@wp.kernel
def surface_and_concentration_cells(
    g: CellGrid,
    r_lo: int,
    r_hi: int,
    R: float,
    x_build: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    p: SPHParams,
    w_dx: float,
    lam: wp.array(dtype=float),
    grad_c: wp.array(dtype=wp.vec3),
    grad_s: wp.array(dtype=wp.vec3),
):
    """kernels/sph/shifting.py surface_and_concentration over the cell gather (surface_pair per pair)."""
    i = wp.tid()
    xi = x[i]
    xq = x_build[i]
    m = wp.mat33(0.0)
    gc = wp.vec3(0.0)
    gs = wp.vec3(0.0)
    ix, iy, iz = cell_of(g, xq)
    for r in range(r_lo, r_hi):
        s0, e0 = slot_range(g, xq, R, iy, iz, r)
        for k in range(s0, e0):
            j = candidate(g, k, xq, R)
            if j >= 0 and j != i:
                dm, dc, ds = surface_pair(xi, j, x, rho, particle_mass, p, w_dx)
                m += dm
                gc += dc
                gs += ds
    lam[i] = surface_finish(m, p)
    grad_c[i] = gc
    grad_s[i] = gs


@wp.kernel
def shift_displacement_cells(
    g: CellGrid,
    r_lo: int,
    r_hi: int,
    R: float,
    x_build: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    lam: wp.array(dtype=float),
    grad_c: wp.array(dtype=wp.vec3),
    grad_s: wp.array(dtype=wp.vec3),
    v2max: wp.array(dtype=float),
    ids: wp.array(dtype=int),
    owner: wp.array(dtype=int),
    dt: wp.array(dtype=float),
    p: SPHParams,
    coef: float,
    dx: float,
    dr: wp.array(dtype=wp.vec3),
):
    """kernels/sph/shifting.py shift_displacement over the cell gather (band_start, band_pair, shift_finish)."""
    i = wp.tid()
    if lam[i] < SPLASH_LAMBDA or step_of(dt, i) == 0.0:
        dr[i] = wp.vec3(0.0)
        return
    xi = x[i]
    xq = x_build[i]
    ns, band = band_start(i, lam, grad_c, p)
    ix, iy, iz = cell_of(g, xq)
    for r in range(r_lo, r_hi):
        s0, e0 = slot_range(g, xq, R, iy, iz, r)
        for k in range(s0, e0):
            j = candidate(g, k, xq, R)
            if j >= 0 and j != i:
                dn, hit = band_pair(xi, j, x, lam, grad_c, p)
                ns -= dn
                band = wp.max(band, hit)
    dr[i] = shift_finish(i, ns, band, grad_s, v2max, ids, owner, p, coef, dx)
