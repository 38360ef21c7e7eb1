"""Density diffusion (delta-SPH) for continuity density, launched by rockwave/sph/fluid.py
(FluidSolver._density_diffusion): an opt-in pass after the density pass of FluidSolver.step (scene key
fluid.density_diffusion; the `delta_plus` level sets it), so the levels without it launch nothing of it.

Molteni & Colagrossi (2009) and Antuono et al. (2010, 2012) add to the continuity equation

    d rho_i/dt += delta h c0 sum_j psi_ij . grad_i W_ij V_j,   psi_ij = 2 (rho_j - rho_i) (x_j - x_i)/|x_ij|^2,

V_j = m_j/rho0 (not m_j/rho_j: a splash particle's continuity density falls far below rho0, 300 kg/m^3 in
SPHERIC Test 2, and with m_j/rho_j its neighbours' diffusion then grew without bound and drove densities
negative), h = H/2: a Laplacian of the density that damps the particle-scale density (pressure) noise of
continuity-density WCSPH and leaves the smooth field alone (its size is delta h c0, delta ~ 0.1; Antuono et al.
2010). In a column of water at rest this diffuses the hydrostatic density gradient (truncated kernels at the free
surface and walls turn it into a net flux); so, as Fourtakas et al. (2019, the 'dynamic density' form of
DualSPHysics), the hydrostatic part is taken out of the difference: rho_j - rho_i - (rho_j^H - rho_i^H),
rho_j^H - rho_i^H = rho0 g . (x_j - x_i)/c0^2 (the linearised EOS; g the gravity vector).

Walls (Adami et al. 2012) take part with the density of their extrapolated pressure, rho_b = EOS^-1(p_b)
(wall_pr2[b][1] = rho_b/rho0, from this step's wall_pressure_adami, which the solver runs before this pass when
the diffusion includes walls) and their geometric volume V_b = m_b/rho0. Why (docs/notes.md 'delta-plus'): with
fluid neighbours only, the sum over a support cut by a wall is not a Laplacian but a one-sided difference,
~ delta c0 (d rho/dn) (an O(1/h) flux through the wall). At rest the Fourtakas term removes it; at an impact
the density (pressure) is largest against the wall, and the diffusion drained it from the wall's water every
step: the Adami wall pressure extrapolated from that water fell, and water crossed the wall (a 2D dam break into
a wall on the CPU: 6 particles through the end wall at the run-up, densities to -300 kg/m^3 after; SPHERIC
Test 2 on the H100 blew up the same way after its impact). The wall's extrapolated density continues the fluid's
field through the wall (its gradient is the fluid's hydrostatic and wall-acceleration part, which the Fourtakas
term removes), so the boundary flux vanishes and the water pressed against the wall keeps its pressure. Akinci
walls carry no density: there the sum stays the fluid's (only `draft` uses Akinci walls, without diffusion).
"""

from __future__ import annotations

import warp as wp

from rockwave.kernels.sph.fluid import BOUNDARY_ADAMI, CellGrid, SPHParams, cell_of, kernel_grad, kernel_w, slot_range, store_density

wp.set_module_options({"enable_backward": False})  # forward kernels only: nothing here is differentiated


@wp.kernel
def density_diffusion_rate(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
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
    """out_i = delta h c0 sum_j 2 (rho_j - rho_i - rho0 g.(x_j - x_i)/c0^2) ((x_j - x_i) . grad_i W_ij)/|x_ij|^2 V_j
    over the neighbour list (pairs at r >= H skipped; a particle whose list overflowed gets 0): fluid neighbours with
    V_j = m/rho0; with ``walls`` = 1 and Adami walls also the wall particles, rho_b = rho0 wall_pr2[b][1] and
    V_b = m_b/rho0 (module docstring)."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    if c > nbr.shape[0] // n:
        out[i] = 0.0
        return
    xi = x[i]
    ri = rho[i]
    # pressure_density = 1 (fluid.density_diffusion_form = 'pressure', with clipped negative pressure): the density
    # of the pressure, max(rho, rho0), is what is diffused (module docstring)
    clip = pressure_density != 0 and p.clamp_negative != 0
    if clip:
        ri = wp.max(ri, p.rest_density)
    H2 = p.H * p.H
    c2 = p.sound_speed * p.sound_speed
    with_walls = walls != 0 and p.boundary == BOUNDARY_ADAMI
    s = float(0.0)
    for k in range(c):
        j = nbr[k * n + i]
        rj = float(0.0)
        vj = float(0.0)
        if j < p.n_fluid:
            rj = rho[j]
            if clip:
                rj = wp.max(rj, p.rest_density)
            vj = p.fluid_mass / p.rest_density
        elif with_walls:
            rj = p.rest_density * wall_pr2[j - p.n_fluid][1]
            vj = particle_mass[j] / p.rest_density
        if vj > 0.0:
            xji = x[j] - xi
            r2 = wp.length_sq(xji)
            if r2 < H2 and r2 > 0.0:
                g = kernel_grad(-xji, wp.sqrt(r2), p)
                drho = rj - ri - p.rest_density * wp.dot(p.gravity, xji) / c2
                s += 2.0 * drho * wp.dot(xji, g) / r2 * vj
    out[i] = delta * 0.5 * p.H * p.sound_speed * s


@wp.kernel
def apply_density_diffusion(
    rate: wp.array(dtype=float),
    dt: wp.array(dtype=float),
    p: SPHParams,
    drho_dt: wp.array(dtype=float),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
):
    """rho_i += dt rate_i, then p_i = EOS(rho_i) and pr2_i = p_i/rho_i^2 (drho_dt gains the rate)."""
    i = wp.tid()
    r = rho[i] + dt[0] * rate[i]
    drho_dt[i] = drho_dt[i] + rate[i]
    store_density(i, r, p, rho, pressure, pr2)


# The renormalised gradient's weight w ramps from 0 to 1 as the smallest eigenvalue lambda of B_i (fluid neighbours
# only) rises from RENORM_LAMBDA_NONE to RENORM_LAMBDA_FULL. On the lattice at 3 spacings lambda is 1 inside, 0.5 in
# the first row at a wall or a flat free surface (w = 1 there), 0.85 in the second, 0.25 at a corner (w ~ 0.25); a
# jet one or two particles thick and splash fall below (w = 0: there the inverse of a nearly singular B amplified
# the gradient's error, and the diffusion drove densities negative in a 2D dam break into a wall, docs/notes.md)
RENORM_LAMBDA_NONE = wp.constant(0.2)
RENORM_LAMBDA_FULL = wp.constant(0.4)


@wp.func
def dynamic_difference(rj: float, ri: float, xji: wp.vec3, p: SPHParams) -> float:
    """(rho_j - rho_i) less its hydrostatic part rho0 g.(x_j - x_i)/c0^2 (Fourtakas et al. 2019; the linearised EOS)."""
    return rj - ri - p.rest_density * wp.dot(p.gravity, xji) / (p.sound_speed * p.sound_speed)


@wp.kernel
def renormalised_gradients(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    p: SPHParams,
    lmat: wp.array(dtype=wp.mat33),
    grad_rho: wp.array(dtype=wp.vec3),
    grad_v: wp.array(dtype=wp.mat33),
):
    """The renormalised (first-order consistent) gradients over the FLUID neighbours (Randles & Libersky 1996;
    Antuono et al. 2010), V_j = m/rho0:

        B_i = sum_j V_j grad_i W_ij (x) (x_j - x_i),  L_i = w_i B_i^-1,
        grad_rho_i = L_i sum_j (rho_j - rho_i - rho0 g.x_ji/c0^2) grad_i W_ij V_j   (the dynamic density's gradient),
        grad_v_i: the same for each velocity component (rows: components, grad_v[i][a] = d v_a / dx),

    exact for a linear field whatever part of the support is filled where w_i = 1 (the weight of the module
    constants RENORM_LAMBDA_*; 0 for splash and thin jets). A particle whose list overflowed gets none."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    if c > nbr.shape[0] // n:
        lmat[i] = wp.mat33(0.0)
        grad_rho[i] = wp.vec3(0.0)
        grad_v[i] = wp.mat33(0.0)
        return
    xi = x[i]
    vi = v[i]
    ri = rho[i]
    H2 = p.H * p.H
    vol = p.fluid_mass / p.rest_density
    b = wp.mat33(0.0)
    gr = wp.vec3(0.0)
    gv = wp.mat33(0.0)
    for k in range(c):
        j = nbr[k * n + i]
        if j < p.n_fluid:
            xji = x[j] - xi
            r2 = wp.length_sq(xji)
            if r2 < H2 and r2 > 0.0:
                g = vol * kernel_grad(-xji, wp.sqrt(r2), p)
                b += wp.outer(g, xji)
                gr += dynamic_difference(rho[j], ri, xji, p) * g
                gv += wp.outer(v[j] - vi, g)
    if p.dim == 2:
        b[2, 2] = 1.0
    # (B is symmetric up to round-off: grad_i W_ij lies along x_ji; the eigenvalues are those of its symmetric part)
    q, d = wp.eig3(0.5 * (b + wp.transpose(b)))
    lam = wp.min(wp.min(d[0], d[1]), d[2])
    w = wp.clamp((lam - RENORM_LAMBDA_NONE) / (RENORM_LAMBDA_FULL - RENORM_LAMBDA_NONE), 0.0, 1.0)
    if w > 0.0:
        L = w * wp.inverse(b)
        if p.dim == 2:
            L[2, 2] = 0.0
        lmat[i] = L
        grad_rho[i] = L * gr  # sum_j (G.x_ji) grad W_ij V_j = B G
        grad_v[i] = gv * wp.transpose(L)  # sum_j (v_j - v_i) (x) grad W_ij V_j = G_v B^T
    else:
        lmat[i] = wp.mat33(0.0)
        grad_rho[i] = wp.vec3(0.0)
        grad_v[i] = wp.mat33(0.0)


@wp.kernel
def density_diffusion_rate_renormalised(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    grad_rho: wp.array(dtype=wp.vec3),
    p: SPHParams,
    delta: float,
    out: wp.array(dtype=float),
):
    """Antuono et al. (2010) eq. (5)-(6), the delta-SPH diffusion with the renormalised correction, written for the
    dynamic density rho - rho^H (rho^H the hydrostatic density, as Fourtakas et al. 2019):

        out_i = delta h c0 sum_j psi_ij . grad_i W_ij V_j,   x_ji = x_j - x_i,  h = H/2,  V_j = m/rho0,
        psi_ij = 2 (rho_j - rho_i - rho0 g.x_ji/c0^2) x_ji/|x_ji|^2 - (<grad rho>_i^L + <grad rho>_j^L),

    over the FLUID neighbours. For a linear dynamic field the two parts of psi_ij . grad_i W_ij cancel pair by pair
    (grad_i W_ij = c x_ji: 2 (G.x_ji)(x_ji.gW)/r^2 = 2 G.gW) wherever the weights are 1, whatever part of the
    support is filled: the term diffuses the second-order part and the particle-scale noise of the density, and
    no flux leaves through a wall or the free surface (the one-sided difference ~ delta c0 d rho/dn of the plain
    form is gone), so the wall particles stay out of the sum. Where the weight is below 1 (corners, thin jets,
    splash) the hydrostatic part is still exact. psi_ij = psi_ji and grad_j W_ji = -grad_i W_ij: with equal volumes
    sum_i V_i out_i = 0."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    if c > nbr.shape[0] // n:
        out[i] = 0.0
        return
    xi = x[i]
    ri = rho[i]
    gi = grad_rho[i]
    H2 = p.H * p.H
    vol = p.fluid_mass / p.rest_density
    s = float(0.0)
    for k in range(c):
        j = nbr[k * n + i]
        if j < p.n_fluid:
            xji = x[j] - xi
            r2 = wp.length_sq(xji)
            if r2 < H2 and r2 > 0.0:
                g = kernel_grad(-xji, wp.sqrt(r2), p)
                s += (2.0 * dynamic_difference(rho[j], ri, xji, p) * wp.dot(xji, g) / r2 - wp.dot(gi + grad_rho[j], g)) * vol
    out[i] = delta * 0.5 * p.H * p.sound_speed * s


@wp.kernel
def wall_density_extrapolated(
    g: CellGrid,
    r_lo: int,
    r_hi: int,
    R: float,
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    grad_rho: wp.array(dtype=wp.vec3),
    xq: wp.array(dtype=wp.vec3),
    q_off: int,
    p: SPHParams,
    wall_rho: wp.array(dtype=wp.vec2),
):
    """The density of each boundary particle b for the diffusion (fluid.density_diffusion_form = 'extrapolated'),
    the fluid's field continued linearly to x_b (a first-order Taylor expansion about each fluid particle f within
    H, Shepard-weighted):

        rho_b = sum_f [rho_f + (<grad rho>_f^L + rho0 g/c0^2) . (x_b - x_f)] W_bf / sum_f W_bf,

    <grad rho>_f^L the renormalised gradient of the dynamic density (renormalised_gradients) and rho0 g/c0^2 the
    hydrostatic one. The Adami density (wall_pressure_adami: the Shepard average of the fluid's pressure plus the
    hydrostatic part) is lower than the water pressed against the wall whenever the density rises towards the wall
    (an impact, a run-up): with it in the sum the diffusion drained that water's compression (docs/notes.md
    'delta-plus'); continued linearly, a density field linear across the wall gives no flux through it. wall_rho[b]
    = (0, rho_b / rho0) (the layout density_diffusion_rate reads); rho0 where no fluid is within H. The cell query
    as wall_pressure_adami's (R the list radius, centred at xq[q_off + t])."""
    t = wp.tid()
    b = t + p.n_fluid
    xb = x[b]
    gh = p.rest_density / (p.sound_speed * p.sound_speed) * p.gravity
    sw = float(0.0)
    sr = float(0.0)
    H2 = p.H * p.H
    xc = xq[q_off + t]
    ix, iy, iz = cell_of(g, xc)
    for r in range(r_lo, r_hi):
        s0, e0 = slot_range(g, xc, R, iy, iz, r)
        for k in range(s0, e0):
            f = g.order[k]
            if f < p.n_fluid:
                d = xb - x[f]
                r2 = wp.length_sq(d)
                if r2 < H2:
                    w = kernel_w(r2, p)
                    sw += w
                    sr += w * (rho[f] + wp.dot(grad_rho[f] + gh, d))
    rb = p.rest_density
    if sw > 0.0:
        rb = wp.max(sr / sw, 1.0e-3 * p.rest_density)
    wall_rho[t] = wp.vec2(0.0, rb / p.rest_density)
