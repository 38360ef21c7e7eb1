"""Particle shifting with a free-surface band (the PST of the delta-plus-SPH, Sun et al. 2017), launched by
rockwave/sph/fluid.py (FluidSolver: the ``shifting`` and ``shift`` passes, scene key fluid.particle_shifting; the
`delta_plus` level sets it), so the levels without it launch nothing of it.

Sources (equations written out here; no code copied):

- Lind, Xu, Stansby & Rogers (2012), J. Comput. Phys. 231, 1499-1523: particles are moved down the gradient of the
  particle concentration, delta r_i = -D grad C_i, grad C_i = sum_j V_j grad_i W_ij; at the free surface only
  along it (the normal part of the shift is removed).
- Sun, Colagrossi, Marrone, Antuono & Zhang (2017), Comput. Methods Appl. Mech. Engrg. 315, 25-49 (delta-plus-SPH),
  their eq. (9)-(10):

      delta r_i = -K Ma (2h)^2 sum_j [1 + R (W_ij / W(dx))^n] grad_i W_ij V_j,   R = 0.2, n = 4,  Ma = U_max / c0,

  (the bracket is Monaghan's (2000) anti-clumping term: two particles closer than the lattice push apart harder),
  applied in full inside the water, with its normal component removed, delta r_i <- (I - n n) delta r_i, for the
  particles at the free surface and within one kernel support of it, and not at all for splash. Their K is the
  Courant number; here K = fluid.particle_shifting (0.02 at `delta_plus`), (2h)^2 = H^2 (our H is the support radius 2h).
- Free-surface detection: Marrone, Colagrossi, Le Touze & Graziani (2010), J. Comput. Phys. 229, 3652-3663:
  lambda_i = the smallest eigenvalue of B_i = sum_j V_j grad_i W_ij (x) (x_j - x_i) (the renormalisation matrix
  of Randles & Libersky 1996; 1 in full support, ~0.5 at a flat free surface); lambda_i < FS_LAMBDA marks a
  surface particle (0.75, their interior bound), lambda_i < SPLASH_LAMBDA a splash particle (not shifted); the
  surface normal n_i = -grad C_i / |grad C_i| (the gradient of the kernel sum points into the water).

Walls: Adami wall particles and the wall particles of blocks (rockwave/coupling/walls.py) enter both sums with their
geometric volume V_b = m_b / rho0, as if they were water: a particle next to a wall has a full support (lambda ~ 1,
not surface) and the concentration gradient pushes it away from a wall it comes closer to than the lattice. So the
shift applies next to walls and block faces as inside the water, and never drives a particle into a wall (tested:
tests/test_delta_plus.py). Particles carry their mass, so shifting conserves mass exactly; as in Sun et al. (2017)
the velocity and density are not re-interpolated to the shifted position (the diffusion of the density smooths
what the small shift leaves)."""

from __future__ import annotations

import warp as wp

from rockwave.kernels.sph.fluid import SPHParams, kernel_grad, kernel_w, step_of

wp.set_module_options({"enable_backward": False})  # forward kernels only: nothing here is differentiated

FS_LAMBDA = wp.constant(0.75)  # lambda_i below: a free-surface particle (Marrone et al. 2010's interior bound)
SPLASH_LAMBDA = wp.constant(0.35)  # lambda_i below: splash (a support less than ~a third full): not shifted
ANTICLUMP_R = wp.constant(0.2)  # Sun et al. (2017) / Monaghan (2000): R = 0.2, n = 4
MAX_SHIFT = wp.constant(0.25)  # largest shift of one step, in particle spacings


@wp.kernel
def surface_and_concentration(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    p: SPHParams,
    w_dx: float,
    lam: wp.array(dtype=float),
    grad_c: wp.array(dtype=wp.vec3),
    grad_s: wp.array(dtype=wp.vec3),
):
    """lambda_i (free-surface indicator), grad C_i = sum_j V_j grad_i W_ij (the surface normal's direction) and the
    shifting gradient grad_s_i = sum_j V_j [1 + R (W_ij/W(dx))^4] grad_i W_ij over the neighbour list, fluid
    V_j = m/rho_j, walls V_b = m_b/rho0 (module docstring). A particle whose list overflowed (a compressed crowd:
    never a surface) gets lambda = 1 and no shift."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    if c > nbr.shape[0] // n:
        lam[i] = 1.0
        grad_c[i] = wp.vec3(0.0)
        grad_s[i] = wp.vec3(0.0)
        return
    xi = x[i]
    H2 = p.H * p.H
    m = wp.mat33(0.0)
    gc = wp.vec3(0.0)
    gs = wp.vec3(0.0)
    for k in range(c):
        j = nbr[k * n + i]
        rij = xi - x[j]
        r2 = wp.length_sq(rij)
        if r2 < H2:
            vol = float(0.0)
            if j < p.n_fluid:
                vol = p.fluid_mass / rho[j]
            else:
                vol = particle_mass[j] / p.rest_density
            g = kernel_grad(rij, wp.sqrt(r2), p)
            m += vol * wp.outer(g, -rij)
            gc += vol * g
            q = kernel_w(r2, p) / w_dx
            gs += (vol * (1.0 + ANTICLUMP_R * q * q * q * q)) * g
    if p.dim == 2:
        m[2, 2] = 1.0
    m = 0.5 * (m + wp.transpose(m))
    ev, d = wp.eig3(m)
    lam[i] = wp.min(wp.min(d[0], d[1]), d[2])
    grad_c[i] = gc
    grad_s[i] = gs


@wp.kernel
def speed_max(v: wp.array(dtype=wp.vec3), n: int, stride: int, out: wp.array(dtype=float)):
    """out[0] = max |v_i|^2 over the first n particles (zeroed by the caller; as kernels/sph/fluid.py motion_extrema)."""
    t = wp.tid()
    v2 = float(0.0)
    i = t
    while i < n:
        v2 = wp.max(v2, wp.length_sq(v[i]))
        i += stride
    wp.atomic_max(out, 0, v2)


@wp.kernel
def scenario_speed_max(v: wp.array(dtype=wp.vec3), ids: wp.array(dtype=int), owner: wp.array(dtype=int),
                       out: wp.array(dtype=float)):
    """out[k] = max |v_i|^2 over scenario k's fluid particles (owner: scenario by seeded index; zeroed by the caller)."""
    i = wp.tid()
    wp.atomic_max(out, owner[ids[i]], wp.length_sq(v[i]))


@wp.kernel
def shift_displacement(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
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
    """dr_i = -coef Ma H^2 grad_s_i (Sun et al. 2017, module docstring), Ma = sqrt(v2max[0]) / c0; splash particles
    (lambda_i < SPLASH_LAMBDA) none; a particle that is at the free surface or has a surface particle within H (the
    band of one support under the surface) only along the surface: its normal component removed, n the
    W-weighted mean of the surface normals -grad C / |grad C| of the surface particles around it (itself included).
    At most MAX_SHIFT spacings. A batch of scenarios with their own steps (rockwave/sim/batch.py): Ma from the
    particle's scenario's largest speed (v2max[owner[ids[i]]]; one entry: the solo run's), and no shift while its
    scenario does not step (its dt 0: step_of)."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    li = lam[i]
    if li < SPLASH_LAMBDA or c > nbr.shape[0] // n or step_of(dt, i) == 0.0:
        dr[i] = wp.vec3(0.0)
        return
    xi = x[i]
    H2 = p.H * p.H
    ns = wp.vec3(0.0)
    band = int(0)
    if li < FS_LAMBDA:
        band = 1
        gl = wp.length(grad_c[i])
        if gl > 0.0:
            ns = -kernel_w(0.0, p) / gl * grad_c[i]
    for k in range(c):
        j = nbr[k * n + i]
        if j < p.n_fluid:
            if lam[j] < FS_LAMBDA:
                r2 = wp.length_sq(xi - x[j])
                if r2 < H2:
                    band = 1
                    gl = wp.length(grad_c[j])
                    if gl > 0.0:
                        ns -= kernel_w(r2, p) / gl * grad_c[j]
    k = int(0)
    if v2max.shape[0] > 1:
        k = owner[ids[i]]
    ma = wp.sqrt(v2max[k]) / p.sound_speed
    d = -(coef * ma * p.H * p.H) * grad_s[i]
    if band != 0:
        nl = wp.length(ns)
        if nl > 0.0:
            nn = ns / nl
            d = d - wp.dot(d, nn) * nn
        else:
            d = wp.vec3(0.0)
    dl = wp.length(d)
    if dl > MAX_SHIFT * dx:
        d = (MAX_SHIFT * dx / dl) * d
    if p.dim == 2:
        d = wp.vec3(d[0], d[1], 0.0)
    dr[i] = d


# The pair terms and the finishes of the two list passes above, for the list-free gather (kernels/sph/gather.py
# surface_and_concentration_cells, shift_displacement_cells: the same arithmetic).


@wp.func
def surface_pair(xi: wp.vec3, j: int, x: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float),
                 particle_mass: wp.array(dtype=float), p: SPHParams, w_dx: float):
    """Neighbour j's terms of surface_and_concentration: V_j grad W_ij (x) (x_j - x_i), V_j grad W_ij and
    V_j [1 + R (W_ij/W(dx))^4] grad W_ij (zeros at r >= H)."""
    rij = xi - x[j]
    r2 = wp.length_sq(rij)
    if r2 < p.H * p.H:
        vol = float(0.0)
        if j < p.n_fluid:
            vol = p.fluid_mass / rho[j]
        else:
            vol = particle_mass[j] / p.rest_density
        g = kernel_grad(rij, wp.sqrt(r2), p)
        q = kernel_w(r2, p) / w_dx
        return vol * wp.outer(g, -rij), vol * g, (vol * (1.0 + ANTICLUMP_R * q * q * q * q)) * g
    return wp.mat33(0.0), wp.vec3(0.0), wp.vec3(0.0)


@wp.func
def surface_finish(m_in: wp.mat33, p: SPHParams) -> float:
    """lambda_i, the smallest eigenvalue of the symmetrised moment M_i (2D: its z row the identity's)."""
    m = m_in
    if p.dim == 2:
        m[2, 2] = 1.0
    m = 0.5 * (m + wp.transpose(m))
    ev, d = wp.eig3(m)
    return wp.min(wp.min(d[0], d[1]), d[2])


@wp.func
def band_start(i: int, lam: wp.array(dtype=float), grad_c: wp.array(dtype=wp.vec3), p: SPHParams):
    """shift_displacement's surface normal and band from particle i itself: (-W(0) grad C_i/|grad C_i|, 1) at the
    free surface, else (0, 0)."""
    ns = wp.vec3(0.0)
    band = int(0)
    if lam[i] < FS_LAMBDA:
        band = 1
        gl = wp.length(grad_c[i])
        if gl > 0.0:
            ns = -kernel_w(0.0, p) / gl * grad_c[i]
    return ns, band


@wp.func
def band_pair(xi: wp.vec3, j: int, x: wp.array(dtype=wp.vec3), lam: wp.array(dtype=float),
              grad_c: wp.array(dtype=wp.vec3), p: SPHParams):
    """Neighbour j's part of the band's normal: (W_ij grad C_j/|grad C_j|, 1) for a fluid surface particle within H
    (the normal sums minus it), else (0, 0)."""
    if j < p.n_fluid:
        if lam[j] < FS_LAMBDA:
            r2 = wp.length_sq(xi - x[j])
            if r2 < p.H * p.H:
                gl = wp.length(grad_c[j])
                if gl > 0.0:
                    return kernel_w(r2, p) / gl * grad_c[j], 1
                return wp.vec3(0.0), 1
    return wp.vec3(0.0), 0


@wp.func
def shift_finish(i: int, ns: wp.vec3, band: int, grad_s: wp.array(dtype=wp.vec3), v2max: wp.array(dtype=float),
                 ids: wp.array(dtype=int), owner: wp.array(dtype=int), p: SPHParams, coef: float, dx: float) -> wp.vec3:
    """shift_displacement's shift from the band's normal ns and flag: -coef Ma H^2 grad_s_i, along the surface in
    the band, at most MAX_SHIFT spacings."""
    k = int(0)
    if v2max.shape[0] > 1:
        k = owner[ids[i]]
    ma = wp.sqrt(v2max[k]) / p.sound_speed
    d = -(coef * ma * p.H * p.H) * grad_s[i]
    if band != 0:
        nl = wp.length(ns)
        if nl > 0.0:
            nn = ns / nl
            d = d - wp.dot(d, nn) * nn
        else:
            d = wp.vec3(0.0)
    dl = wp.length(d)
    if dl > MAX_SHIFT * dx:
        d = (MAX_SHIFT * dx / dl) * d
    if p.dim == 2:
        d = wp.vec3(d[0], d[1], 0.0)
    return d


@wp.kernel
def apply_shift(dr: wp.array(dtype=wp.vec3), x: wp.array(dtype=wp.vec3)):
    """x_i += dr_i (after the step's integration: dr_i was found at the step's start positions)."""
    i = wp.tid()
    x[i] = x[i] + dr[i]
