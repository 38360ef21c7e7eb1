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

The density of the pressure (fluid.density_diffusion_form = 'pressure'). With negative pressure clipped
(clamp_negative_pressure, every level) a continuity density below rho0 holds no pressure: it is a memory of
expansion (the run-up sheet on a wall, splash), not a state the pressure field sees. Diffused as it is, it drains
the compression of the water next to it: a particle driven into a wall from such a sheet lost the compression that
makes the wall push back (the 2D dam break into a wall: the sheet running up the end wall at 680-980 kg/m^3, its
particles crept 1-16 spacings into the wall with the diffusion, 0.27 without). So the form 'pressure' diffuses
max(rho, rho0), the density whose EOS pressure the water has (the wall particles' rho_b = EOS^-1(p_b >= 0) already
is): a particle below rho0 takes compression from neighbours above it and gives none; the pair terms stay
antisymmetric (sum_i V_i out_i = 0 over the fluid pairs). With the hydrostatic part removed as above.

The renormalised term (fluid.density_diffusion_renormalised; Antuono et al. 2010, 2012). The difference term alone
is a Laplacian only inside a full support: where the support is cut (under the free surface) its sum is a one-sided
difference ~ delta c0 (d rho/dn), an O(1/h) flux of any smooth density gradient (the wave's dynamic pressure). Antuono
et al. take the gradients out of it,

    psi_ij = 2 (rho_j - rho_i) (x_j - x_i)/|x_ij|^2 - (<grad rho>_i^L + <grad rho>_j^L),

<grad rho>_i^L = L_i sum_j (rho_j - rho_i) grad_i W_ij V_j the renormalised gradient (Bonet & Lok 1999: L_i the
inverse of M_i = sum_j V_j grad_i W_ij (x) (x_j - x_i), so it is exact for a linear field in any support that
spans the space), so psi_ij . grad_i W_ij vanishes for every linear field at every particle and the term is left
with the particle-scale (curvature) part of the density. Here the density is the dynamic one (hydrostatic part
removed as above, in both terms); wall particles take part in M_i and in the gradient sum with their rho_b and
V_b = m_b/rho0 and take the gradient of the fluid particle they face (<grad rho>_b := <grad rho>_i). M_i is blended
to the identity by its smallest eigenvalue lambda (L_i = w M_i^-1 + (1 - w) I, w = (lambda - 0.2)/(0.4 - 0.2) in
[0, 1]): a flat free surface (lambda ~ 0.5) keeps the full renormalisation, thin jets and splash (one direction
nearly empty) get the plain sum. The pair terms stay antisymmetric (the gradients enter as G_i + G_j).
"""

from __future__ import annotations

import warp as wp

from rockwave.kernels.sph.fluid import BOUNDARY_ADAMI, SPHParams, kernel_grad, step_of, store_density

wp.set_module_options({"enable_backward": False})  # forward kernels only: nothing here is differentiated


@wp.func
def neighbour_density(j: int, rho: wp.array(dtype=float), particle_mass: wp.array(dtype=float),
                      wall_pr2: wp.array(dtype=wp.vec2), walls: int, clip: bool, p: SPHParams) -> wp.vec2:
    """(rho_j, V_j) of neighbour j in the diffusion's sums: a fluid particle rho_j (max(rho_j, rho0) with ``clip``) and
    m/rho0; with ``walls`` and Adami walls a wall particle rho0 wall_pr2[b][1] and m_b/rho0; otherwise (0, 0)."""
    rj = float(0.0)
    vj = float(0.0)
    if j < p.n_fluid:
        rj = rho[j]
        if clip:
            rj = wp.max(rj, p.rest_density)
        vj = p.fluid_mass / p.rest_density
    elif walls != 0 and p.boundary == BOUNDARY_ADAMI:
        rj = p.rest_density * wall_pr2[j - p.n_fluid][1]
        vj = particle_mass[j] / p.rest_density
    return wp.vec2(rj, vj)


@wp.func
def diffusion_pair(xi: wp.vec3, ri: float, j: int, x: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float),
                   particle_mass: wp.array(dtype=float), wall_pr2: wp.array(dtype=wp.vec2), walls: int, clip: bool,
                   p: SPHParams) -> float:
    """The term of neighbour j in density_diffusion_rate's sum (before the factor delta h c0):
    2 (rho_j - rho_i - rho0 g.x_ji/c0^2) (x_ji . grad_i W_ij)/|x_ij|^2 V_j; 0 at r >= H, for a wall particle
    without ``walls`` (or with Akinci walls)."""
    rv = neighbour_density(j, rho, particle_mass, wall_pr2, walls, clip, p)
    rj = rv[0]
    vj = rv[1]
    if vj > 0.0:
        xji = x[j] - xi
        r2 = wp.length_sq(xji)
        if r2 < p.H * p.H and r2 > 0.0:
            g = kernel_grad(-xji, wp.sqrt(r2), p)
            drho = rj - ri - p.rest_density * wp.dot(p.gravity, xji) / (p.sound_speed * p.sound_speed)
            return 2.0 * drho * wp.dot(xji, g) / r2 * vj
    return 0.0


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
    renormalised: int,
    grad: wp.array(dtype=wp.vec3),
    out: wp.array(dtype=float),
):
    """out_i = delta h c0 sum_j 2 (rho_j - rho_i - rho0 g.(x_j - x_i)/c0^2) ((x_j - x_i) . grad_i W_ij)/|x_ij|^2 V_j
    over the neighbour list (pairs at r >= H skipped; a particle whose list overflowed gets 0): fluid neighbours with
    V_j = m/rho0; with ``walls`` = 1 and Adami walls also the wall particles, rho_b = rho0 wall_pr2[b][1] and
    V_b = m_b/rho0; with ``pressure_density`` = 1 and clipped negative pressure rho_i, rho_j read max(rho, rho0)
    (module docstring); with ``renormalised`` = 1 psi_ij also takes - (grad_i + grad_j) (Antuono et al. 2010; grad
    from density_gradient_renormalised, a wall particle taking grad_i)."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    if c > nbr.shape[0] // n:
        out[i] = 0.0
        return
    xi = x[i]
    ri = rho[i]
    # pressure_density = 1 (fluid.density_diffusion_form = 'pressure', with clipped negative pressure): the density
    # of the pressure, max(rho, rho0), is diffused (module docstring)
    clip = pressure_density != 0 and p.clamp_negative != 0
    if clip:
        ri = wp.max(ri, p.rest_density)
    H2 = p.H * p.H
    c2 = p.sound_speed * p.sound_speed
    s = float(0.0)
    gi = wp.vec3(0.0)
    if renormalised != 0:
        gi = grad[i]
    for k in range(c):
        j = nbr[k * n + i]
        rv = neighbour_density(j, rho, particle_mass, wall_pr2, walls, clip, p)
        rj = rv[0]
        vj = rv[1]
        gj = gi
        if renormalised != 0 and j < p.n_fluid:
            gj = grad[j]
        if vj > 0.0:
            xji = x[j] - xi
            r2 = wp.length_sq(xji)
            if r2 < H2 and r2 > 0.0:
                g = kernel_grad(-xji, wp.sqrt(r2), p)
                drho = rj - ri - p.rest_density * wp.dot(p.gravity, xji) / c2
                s += 2.0 * drho * wp.dot(xji, g) / r2 * vj
                if renormalised != 0:
                    # - (<grad rho>_i^L + <grad rho>_j^L) . grad_i W_ij V_j (Antuono et al. 2010)
                    s -= wp.dot(gi + gj, g) * vj
    out[i] = delta * 0.5 * p.H * p.sound_speed * s


DIFF_LAMBDA_NONE = wp.constant(0.2)  # the renormalised gradient's blend by the smallest eigenvalue of M_i (module docstring)
DIFF_LAMBDA_FULL = wp.constant(0.4)


@wp.kernel
def density_gradient_renormalised(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    wall_pr2: wp.array(dtype=wp.vec2),
    walls: int,
    p: SPHParams,
    pressure_density: int,
    grad: wp.array(dtype=wp.vec3),
):
    """grad_i = L_i sum_j (rho_j - rho_i - rho0 g.(x_j - x_i)/c0^2) grad_i W_ij V_j, L_i the blended inverse of
    M_i = sum_j V_j grad_i W_ij (x) (x_j - x_i) (module docstring), over the fluid neighbours (V_j = m/rho0) and, with
    ``walls`` = 1 and Adami walls, the wall particles (rho_b = rho0 wall_pr2[b][1], V_b = m_b/rho0); the densities
    read max(rho, rho0) as density_diffusion_rate's with ``pressure_density``. A particle whose list overflowed: 0."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    if c > nbr.shape[0] // n:
        grad[i] = wp.vec3(0.0)
        return
    xi = x[i]
    ri = rho[i]
    clip = pressure_density != 0 and p.clamp_negative != 0
    if clip:
        ri = wp.max(ri, p.rest_density)
    H2 = p.H * p.H
    c2 = p.sound_speed * p.sound_speed
    m = wp.mat33(0.0)
    s = wp.vec3(0.0)
    for k in range(c):
        j = nbr[k * n + i]
        rv = neighbour_density(j, rho, particle_mass, wall_pr2, walls, clip, p)
        rj = rv[0]
        vj = rv[1]
        if vj > 0.0:
            xji = x[j] - xi
            r2 = wp.length_sq(xji)
            if r2 < H2 and r2 > 0.0:
                g = kernel_grad(-xji, wp.sqrt(r2), p)
                m += vj * wp.outer(g, xji)
                s += (rj - ri - p.rest_density * wp.dot(p.gravity, xji) / c2) * vj * g
    if p.dim == 2:
        m[2, 2] = 1.0
    m = 0.5 * (m + wp.transpose(m))
    q, d = wp.eig3(m)
    lam = wp.min(wp.min(d[0], d[1]), d[2])
    w = wp.clamp((lam - DIFF_LAMBDA_NONE) / (DIFF_LAMBDA_FULL - DIFF_LAMBDA_NONE), 0.0, 1.0)
    ident = wp.identity(n=3, dtype=float)
    L = ident
    if w > 0.0:
        L = w * wp.inverse(m) + (1.0 - w) * ident
    grad[i] = L * s


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
    r = rho[i] + step_of(dt, i) * rate[i]
    drho_dt[i] = drho_dt[i] + rate[i]
    store_density(i, r, p, rho, pressure, pr2)
