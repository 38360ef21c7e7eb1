"""Weakly compressible SPH kernels (Warp; same code on CPU and CUDA), launched by rockwave/sph/fluid.py
(FluidSolver: neighbour search, density, forces, integration, particle order; the lattice calibration
and boundary volumes of build_fluid_model), by rockwave/sph/ghost.py (GhostFluidSolver reuses the list
passes) and by rockwave/sim/simulation.py (the gauges). The force pass, particle_acceleration_list, is
compiled in a Warp module of its own (FORCE_PASS_MODULE, below).

Conventions: particle arrays hold the fluid particles first (indices < n_fluid) and the static
boundary particles after them. ``particle_mass[j]`` is the mass of a fluid particle, and for a
boundary particle its Akinci et al. (2012) mass-equivalent ``Psi_b = rho0 * V_b`` with
``V_b = 1 / sum_k W_bk`` over boundary neighbours. 2D scenes keep z = 0 and use 2D
normalisations. ``H`` is the kernel support radius; the cubic spline's smoothing length is H/2.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})  # forward kernels only: nothing here is differentiated

KERNEL_MULLER = wp.constant(0)
KERNEL_CUBIC = wp.constant(1)
KERNEL_WENDLAND = wp.constant(2)
EOS_TAIT = wp.constant(0)
EOS_LINEAR = wp.constant(1)
FORCE_MOMENTUM = wp.constant(0)
FORCE_MULLER = wp.constant(1)
BOUNDARY_AKINCI = wp.constant(0)  # boundary particles push with -Psi_b p_i/rho_i^2 grad W (Akinci et al. 2012)
BOUNDARY_ADAMI = wp.constant(1)  # boundary particles carry the fluid's extrapolated pressure (Adami et al. 2012)

PI = wp.constant(3.14159265358979)


@wp.struct
class SPHParams:
    dim: int
    kernel: int  # KERNEL_MULLER, KERNEL_CUBIC or KERNEL_WENDLAND
    H: float  # support radius
    rest_density: float
    eos: int
    eos_b: float  # Tait B (Pa) or linear k (m^2/s^2)
    eos_gamma: float
    clamp_negative: int
    density_floor: int  # continuity density kept >= rho0 (fluid.density_floor; continuity_floor below)
    pressure_form: int
    sound_speed: float
    mu: float  # Mueller Laplacian viscosity (Pa s)
    alpha: float  # Monaghan artificial viscosity
    xsph: float  # XSPH epsilon
    gravity: wp.vec3
    n_fluid: int
    grad_scale: float  # lattice gradient correction (see rockwave.sph.fluid.calibrate_lattice)
    fluid_mass: float  # mass of every fluid particle (boundary masses vary: particle_mass array)
    boundary: int  # BOUNDARY_AKINCI or BOUNDARY_ADAMI
    no_slip: int  # Adami walls: 1 = no-slip (viscous terms with the extrapolated wall velocity), 0 = free slip
    gradient_correction: int  # 1: corrected kernel gradients in the continuity and pressure terms (corrected_grad)
    wall_volume: int  # Adami walls: 0 = the wall's mass m_b in the force, 1 = its geometric volume (m_b rho_b/rho0)
    # Mueller kernel constants for H and dim (rockwave.sph.fluid.set_kernel_constants; pow() per
    # neighbour was a large share of the neighbour loops on a GPU)
    w_coef: float  # poly6: 315/(64 pi H^9) (3D), 4/(pi H^8) (2D)
    grad_coef: float  # spiky gradient: 45/(pi H^6) (3D), 30/(pi H^5) (2D)
    lap_coef: float  # viscosity Laplacian: 45/(pi H^6) (3D), 40/(pi H^5) (2D)


# ------------------------------------------------------------------ smoothing kernels ------


@wp.func
def spiky_grad(rij: wp.vec3, r: float, H: float, dim: int) -> wp.vec3:
    # Mueller 2003: grad W = -45/(pi H^6) (H - r)^2 r_hat (3D);  -30/(pi H^5) (H - r)^2 r_hat (2D)
    if r >= H or r < 1.0e-9 * H:
        return wp.vec3(0.0)
    d = H - r
    c = 45.0 / (PI * wp.pow(H, 6.0))
    if dim == 2:
        c = 30.0 / (PI * wp.pow(H, 5.0))
    return (-c * d * d / r) * rij


@wp.func
def cubic_sigma(h: float, dim: int) -> float:
    # Monaghan 1992 cubic spline normalisation: 1/(pi h^3) (3D), 10/(7 pi h^2) (2D)
    if dim == 3:
        return 1.0 / (PI * h * h * h)
    return 10.0 / (7.0 * PI * h * h)


@wp.func
def cubic_w(r: float, H: float, dim: int) -> float:
    # W = sigma (1 - 1.5 q^2 + 0.75 q^3) for q < 1; sigma/4 (2 - q)^3 for 1 <= q < 2; q = r/h, h = H/2
    h = 0.5 * H
    q = r / h
    s = cubic_sigma(h, dim)
    if q < 1.0:
        return s * (1.0 - 1.5 * q * q + 0.75 * q * q * q)
    if q < 2.0:
        t = 2.0 - q
        return 0.25 * s * t * t * t
    return 0.0


@wp.func
def cubic_grad(rij: wp.vec3, r: float, H: float, dim: int) -> wp.vec3:
    # dW/dr = sigma/h (-3q + 2.25 q^2) for q < 1; -0.75 sigma/h (2 - q)^2 for 1 <= q < 2
    h = 0.5 * H
    q = r / h
    if q >= 2.0 or r < 1.0e-9 * H:
        return wp.vec3(0.0)
    s = cubic_sigma(h, dim) / h
    dw = float(0.0)
    if q < 1.0:
        dw = s * (-3.0 * q + 2.25 * q * q)
    else:
        t = 2.0 - q
        dw = -0.75 * s * t * t
    return (dw / r) * rij


@wp.func
def wendland_w(r: float, H: float, dim: int) -> float:
    # Wendland (1995) C2: W = sigma (1 - q/2)^4 (2q + 1), q = r/h, h = H/2; sigma = 7/(4 pi h^2) (2D), 21/(16 pi h^3) (3D)
    h = 0.5 * H
    q = r / h
    if q >= 2.0:
        return 0.0
    s = 7.0 / (4.0 * PI * h * h)
    if dim == 3:
        s = 21.0 / (16.0 * PI * h * h * h)
    t = 1.0 - 0.5 * q
    return s * t * t * t * t * (2.0 * q + 1.0)


@wp.func
def wendland_grad(rij: wp.vec3, r: float, H: float, dim: int) -> wp.vec3:
    # dW/dr = -5 sigma/h q (1 - q/2)^3
    h = 0.5 * H
    q = r / h
    if q >= 2.0 or r < 1.0e-9 * H:
        return wp.vec3(0.0)
    s = 7.0 / (4.0 * PI * h * h)
    if dim == 3:
        s = 21.0 / (16.0 * PI * h * h * h)
    t = 1.0 - 0.5 * q
    return (-5.0 * s / h * q * t * t * t / r) * rij


@wp.func
def kernel_w(r2: float, p: SPHParams) -> float:
    if p.kernel == KERNEL_MULLER:
        # Mueller 2003 poly6: W = w_coef (H^2 - r^2)^3, w_coef = 315/(64 pi H^9) (3D), 4/(pi H^8) (2D)
        if r2 >= p.H * p.H:
            return 0.0
        d = p.H * p.H - r2
        return p.w_coef * d * d * d
    if p.kernel == KERNEL_WENDLAND:
        return wendland_w(wp.sqrt(r2), p.H, p.dim)
    return cubic_w(wp.sqrt(r2), p.H, p.dim)


@wp.func
def kernel_grad(rij: wp.vec3, r: float, p: SPHParams) -> wp.vec3:
    # scaled so that sum_j V_j (x_j - x_i) (x) grad W_ij = -I holds on the initial lattice
    if p.kernel == KERNEL_MULLER:  # spiky gradient with the precomputed constant
        if r >= p.H or r < 1.0e-9 * p.H:
            return wp.vec3(0.0)
        d = p.H - r
        return (-p.grad_scale * p.grad_coef * d * d / r) * rij
    if p.kernel == KERNEL_WENDLAND:
        return p.grad_scale * wendland_grad(rij, r, p.H, p.dim)
    return p.grad_scale * cubic_grad(rij, r, p.H, p.dim)


@wp.func
def kernel_laplacian(r: float, p: SPHParams) -> float:
    # Mueller 2003 viscosity Laplacian for every kernel choice (positive everywhere: stable viscosity):
    # lap W = lap_coef (H - r), lap_coef = 45/(pi H^6) (3D), 40/(pi H^5) (2D)
    if r >= p.H:
        return 0.0
    return p.lap_coef * (p.H - r)


@wp.func
def equation_of_state(rho: float, p: SPHParams) -> float:
    # Tait: p = B((rho/rho0)^gamma - 1);  linear: p = k (rho - rho0)
    pr = float(0.0)
    if p.eos == EOS_TAIT:
        pr = p.eos_b * (wp.pow(rho / p.rest_density, p.eos_gamma) - 1.0)
    else:
        pr = p.eos_b * (rho - p.rest_density)
    if p.clamp_negative != 0:
        pr = wp.max(pr, 0.0)
    return pr


# ------------------------------------------------------------------ passes ------


@wp.kernel
def boundary_volume(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    p: SPHParams,
    particle_mass: wp.array(dtype=float),
):
    """Akinci 2012: Psi_b = rho0 / sum_k W_bk over boundary particles k (launched over boundary particles)."""
    b = wp.tid() + p.n_fluid
    xb = x[b]
    s = float(0.0)
    q = wp.hash_grid_query(grid, xb, p.H)
    k = int(0)
    while wp.hash_grid_query_next(q, k):
        if k >= p.n_fluid:
            s += kernel_w(wp.length_sq(xb - x[k]), p)
    particle_mass[b] = p.rest_density / s


@wp.kernel
def lattice_moments(
    x: wp.array(dtype=wp.vec3),
    p: SPHParams,
    w: wp.array(dtype=float),
    gx: wp.array(dtype=float),
):
    """Terms of the lattice sums about x[0]: w[j] = W_0j and gx[j] = (x_j - x_0)_x (dW/dx)_0j (unscaled
    gradient of the scene's kernel), summed on the host in float64 for the calibration of particle mass
    and gradient scale (a float atomic sum here made the mass, and so every GPU run, differ in the last
    bit from run to run)."""
    j = wp.tid()
    rij = x[0] - x[j]
    r = wp.length(rij)
    w[j] = kernel_w(r * r, p)
    g = wp.vec3(0.0)
    if p.kernel == KERNEL_MULLER:
        g = spiky_grad(rij, r, p.H, p.dim)
    elif p.kernel == KERNEL_WENDLAND:
        g = wendland_grad(rij, r, p.H, p.dim)
    else:
        g = cubic_grad(rij, r, p.H, p.dim)
    gx[j] = (x[j][0] - x[0][0]) * g[0]


@wp.kernel
def equation_of_state_pass(rho: wp.array(dtype=float), p: SPHParams, pressure: wp.array(dtype=float)):
    i = wp.tid()
    pressure[i] = equation_of_state(rho[i], p)


@wp.func
def corrected_grad(gw: wp.vec3, li: wp.mat33, j: int, kgc: wp.array(dtype=wp.mat33), p: SPHParams) -> wp.vec3:
    """The kernel gradient of the continuity and pressure terms between fluid particles i and j. With
    fluid.gradient_correction, G_ij = (L_i + L_j)/2 grad W_ij, L the renormalisation matrices of
    gradient_correction_matrix (Bonet & Lok 1999; symmetrised as Oger et al. 2007 so that G_ji = -G_ij: momentum is
    kept, and with the same G in both terms the pressure's work equals the internal energy's change); grad W_ij
    itself without it. Pairs with wall particles keep grad W_ib (the callers do not correct them): a wall's
    velocity in the continuity sum is the wall's, not the water's, and L_i would mix the water's sliding velocity
    into the wall-normal rate (measured: water sank through the floor of a 2D dam break)."""
    if p.gradient_correction == 0:
        return gw
    return 0.5 * ((li + kgc[j]) * gw)


@wp.func
def own_correction(kgc: wp.array(dtype=wp.mat33), i: int, p: SPHParams) -> wp.mat33:
    """L_i (the identity without fluid.gradient_correction: kgc is then a one-entry placeholder)."""
    if p.gradient_correction == 0:
        return wp.identity(n=3, dtype=float)
    return kgc[i]


# gradient_correction_matrix: the inverse is blended towards the identity where the kernel support is short of
# fluid neighbours, by the smallest eigenvalue lambda of M_i (Marrone et al. 2010's free-surface indicator: ~1 in
# the bulk, 0.5 on a flat free surface or a wall, 0.84-0.86 one layer below it at 3 spacings; 0.75 is their
# interior bound). The smallest eigenvalue, not det M_i: a thin tongue of water on a floor or a line of splash
# has one short direction that a determinant averages with the full ones.
KGC_LAMBDA_FULL = wp.constant(0.75)
KGC_LAMBDA_NONE = wp.constant(0.6)


@wp.func
def kgc_blend(m_in: wp.mat33, p: SPHParams) -> wp.mat33:
    """L_i from the moment M_i (gradient_correction_matrix): symmetrised, then w M_i^-1 + (1 - w) I with w from
    its smallest eigenvalue lambda, (lambda - KGC_LAMBDA_NONE)/(KGC_LAMBDA_FULL - KGC_LAMBDA_NONE) clipped to [0, 1]."""
    m = m_in
    ident = wp.identity(n=3, dtype=float)
    if p.dim == 2:
        m[2, 2] = 1.0
    m = 0.5 * (m + wp.transpose(m))
    q, d = wp.eig3(m)
    lam = wp.min(wp.min(d[0], d[1]), d[2])
    w = wp.clamp((lam - KGC_LAMBDA_NONE) / (KGC_LAMBDA_FULL - KGC_LAMBDA_NONE), 0.0, 1.0)
    if w > 0.0:
        return w * wp.inverse(m) + (1.0 - w) * ident
    return ident


@wp.kernel
def gradient_correction_matrix(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    p: SPHParams,
    kgc: wp.array(dtype=wp.mat33),
):
    """L_i = M_i^-1, M_i = sum_j V_j grad W_ij (x) (x_j - x_i) over the fluid neighbours (V_j = m/rho_j): the
    matrix that makes the SPH gradient of a linear field over them exact (Bonet & Lok 1999). M_i is
    symmetric (grad W_ij lies along x_ij); in 2D its z row is the identity's. With lambda the smallest eigenvalue of
    M_i, L_i = w M_i^-1 + (1 - w) I, w = (lambda - KGC_LAMBDA_NONE)/(KGC_LAMBDA_FULL - KGC_LAMBDA_NONE) clipped to
    [0, 1]: the full correction inside the water, none at the free surface, next to walls (whose pairs keep the
    plain gradient, corrected_grad) and in splash. A particle whose list overflowed keeps the identity."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    ident = wp.identity(n=3, dtype=float)
    if c > nbr.shape[0] // n:
        kgc[i] = ident
        return
    xi = x[i]
    H2 = p.H * p.H
    m = wp.mat33(0.0)
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
            m += vol * wp.outer(kernel_grad(rij, wp.sqrt(r2), p), -rij)
    kgc[i] = kgc_blend(m, p)


@wp.func
def wall_pair_acceleration(b: int, rij: wp.vec3, r2: float, gw: wp.vec3, vi: wp.vec3, rhoi: float, pi_r2: float,
                           mb: float, wall_pr2: wp.array(dtype=wp.vec2), wall_v: wp.array(dtype=wp.vec3), p: SPHParams):
    """Acceleration of fluid particle i from wall particle b (Adami et al. 2012): the momentum-conserving
    pressure term with the wall's extrapolated pressure, a_i -= m_b (p_i/rho_i^2 + p_b/rho_b^2) grad W_ib;
    with fluid.wall_volume = 'geometric' the wall keeps its volume V_b = m_b/rho0 at every pressure, so its mass
    in the term is rho_b V_b = m_b rho_b/rho0 (wall_pr2[b] = (p_b/rho_b^2, rho_b/rho0), wall_pressure_adami);
    with no-slip walls also the viscous terms against the extrapolated wall velocity v~_b (with m_b)."""
    wb = wall_pr2[b]
    mp = mb
    if p.wall_volume != 0:
        mp = mb * wb[1]
    a = -(mp * (pi_r2 + wb[0])) * gw
    if p.no_slip != 0:
        vij = vi - wall_v[b]
        r = wp.sqrt(r2)
        if p.mu > 0.0:
            a -= (p.mu * mb / (rhoi * p.rest_density) * kernel_laplacian(r, p)) * vij
        if p.alpha > 0.0:
            vr = wp.dot(vij, rij)
            if vr < 0.0:
                h_s = 0.5 * p.H
                mu_ij = h_s * vr / (r2 + 0.01 * h_s * h_s)
                a -= mb * (-p.alpha * p.sound_speed * mu_ij / (0.5 * (rhoi + p.rest_density))) * gw
    return a


@wp.func
def pair_acceleration(
    i: int,
    j: int,
    xi: wp.vec3,
    vi: wp.vec3,
    rhoi: float,
    pi: float,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    wall_pr2: wp.array(dtype=wp.vec2),
    wall_v: wp.array(dtype=wp.vec3),
    li: wp.mat33,
    kgc: wp.array(dtype=wp.mat33),
    p: SPHParams,
):
    """Contributions of neighbour j (0 < r_ij < H) to particle i: (acceleration without gravity, XSPH sum).
    The fluid pairs' pressure terms use the corrected gradient (corrected_grad; li = L_i), the viscous and wall
    terms grad W_ij."""
    rij = xi - x[j]
    r2 = wp.length_sq(rij)
    r = wp.sqrt(r2)
    mj = particle_mass[j]
    gw = kernel_grad(rij, r, p)
    a = wp.vec3(0.0)
    dv = wp.vec3(0.0)
    if j >= p.n_fluid:
        if p.boundary == BOUNDARY_AKINCI:
            # Akinci et al. 2012 boundary pressure: a_i -= Psi_b p_i/rho_i^2 grad W_ib (walls at rest)
            return -(mj * pi / (rhoi * rhoi)) * gw, dv
        return wall_pair_acceleration(j - p.n_fluid, rij, r2, gw, vi, rhoi, pi / (rhoi * rhoi), mj, wall_pr2, wall_v, p), dv
    gc = corrected_grad(gw, li, j, kgc, p)
    rhoj = rho[j]
    pj = pressure[j]
    if p.pressure_form == FORCE_MOMENTUM:
        # a_i -= sum_j m_j (p_i/rho_i^2 + p_j/rho_j^2) grad W_ij  (Monaghan 1992)
        a = -(mj * (pi / (rhoi * rhoi) + pj / (rhoj * rhoj))) * gc
    else:
        # Mueller 2003 symmetric: a_i -= 1/rho_i sum_j m_j (p_i + p_j)/(2 rho_j) grad W_ij
        a = -(mj * (pi + pj) / (2.0 * rhoj * rhoi)) * gc
    vj = v[j]
    vij = vi - vj
    if p.mu > 0.0:
        # Mueller 2003: a_i += mu/rho_i sum_j m_j (v_j - v_i)/rho_j lap W_ij
        a -= (p.mu * mj / (rhoi * rhoj) * kernel_laplacian(r, p)) * vij
    if p.alpha > 0.0:
        # Monaghan 1992: Pi_ij = -alpha c mu_ij / rho_ij, mu_ij = h v_ij.r_ij/(r^2 + 0.01 h^2), only when approaching
        vr = wp.dot(vij, rij)
        if vr < 0.0:
            h_s = 0.5 * p.H  # smoothing length
            mu_ij = h_s * vr / (r2 + 0.01 * h_s * h_s)
            a -= mj * (-p.alpha * p.sound_speed * mu_ij / (0.5 * (rhoi + rhoj))) * gw
    if p.xsph > 0.0:
        dv = -(mj / (0.5 * (rhoi + rhoj)) * kernel_w(r2, p)) * vij
    return a, dv


# ------------------------------------------------------------------ cell grid ------
# The fluid solver's own neighbour search (rockwave.sph.fluid.FluidSolver.build_cells builds it):
# particles sorted by cell key, cells H wide in y and z and H/4 in x, keys x-fastest, so the cells
# of one (y, z) column that lie within H of a particle form one contiguous run of sorted slots.
# A query visits the 9 columns (3 in 2D) around a particle and, in each, only the x-cells within
# sqrt(H^2 - d_yz^2) of it (d_yz: distance to the column): ~115 candidates for ~30 neighbours in 3D
# instead of the ~185 of a 27-cell query. Cell coordinates wrap modulo the grid dimensions (a
# hashed dense grid, like wp.HashGrid), so any domain fits; aliased cells only add candidates.


@wp.struct
class CellGrid:
    lo: wp.vec3  # grid origin
    inv_cx: float  # 1 / x-cell width
    c: float  # y and z cell width (>= H / span)
    span: int  # y/z columns on each side of a particle's own that a query visits (c >= H / span)
    nx: int
    ny: int
    nz: int
    first: wp.array(dtype=int)  # first[k] = first sorted slot whose cell key is >= k (nx*ny*nz + 1 entries)
    order: wp.array(dtype=int)  # sorted slot -> particle index
    x_sorted: wp.array(dtype=wp.vec3)  # positions in slot order (the list build reads candidates contiguously)
    prefilter: int  # the cell gather (kernels/sph/gather.py) first keeps the candidates within R in x_sorted


@wp.func
def wrap(a: int, n: int) -> int:
    return ((a % n) + n) % n


@wp.func
def cell_of(g: CellGrid, x: wp.vec3):
    """Unwrapped integer cell coordinates of a point."""
    d = x - g.lo
    return int(wp.floor(d[0] * g.inv_cx)), int(wp.floor(d[1] / g.c)), int(wp.floor(d[2] / g.c))


@wp.kernel
def cell_keys(g: CellGrid, x: wp.array(dtype=wp.vec3), keys: wp.array(dtype=int), values: wp.array(dtype=int),
              rebuild: wp.array(dtype=int)):
    """Cell key of every point (rebuild[0] == 0: the lists are still valid, nothing to do; the cell grid's
    other kernels and the list build take the same flag, see rockwave.sph.fluid.FluidSolver.neighbour_skin)."""
    i = wp.tid()
    if rebuild[0] == 0:
        return
    ix, iy, iz = cell_of(g, x[i])
    keys[i] = wrap(ix, g.nx) + g.nx * (wrap(iy, g.ny) + g.ny * wrap(iz, g.nz))
    values[i] = i


@wp.func
def lower_bound(keys: wp.array(dtype=int), n: int, c: int) -> int:
    """First index of the n sorted keys whose key is >= c (binary search)."""
    lo = int(0)
    hi = n
    while lo < hi:
        mid = (lo + hi) / 2
        if keys[mid] < c:
            lo = mid + 1
        else:
            hi = mid
    return lo


@wp.kernel
def cell_first(keys: wp.array(dtype=int), n: int, first: wp.array(dtype=int), rebuild: wp.array(dtype=int)):
    """first[c] = lower bound of cell c in the n sorted keys (launched over every cell and one past the
    last: a binary search each; a loop over the empty cells after each key serialised the tail)."""
    c = wp.tid()
    if rebuild[0] == 0:
        return
    first[c] = lower_bound(keys, n, c)


@wp.kernel
def gather_sorted_positions(order: wp.array(dtype=int), x: wp.array(dtype=wp.vec3), x_sorted: wp.array(dtype=wp.vec3),
                            rebuild: wp.array(dtype=int)):
    k = wp.tid()
    if rebuild[0] == 0:
        return
    x_sorted[k] = x[order[k]]


@wp.func
def slot_range(g: CellGrid, xi: wp.vec3, H: float, iy: int, iz: int, r: int):
    """Sorted-slot range [s, e) number r of a query around xi: column col = r / 2 of the (2 span + 1)^2 around the
    particle's (dy = col % (2 span + 1) - span, dz = col / (2 span + 1) - span), part r % 2 (the second part is
    non-empty only when the column's x-run wraps)."""
    col = r / 2
    side = 2 * g.span + 1
    cy = iy + col % side - g.span
    cz = iz + col / side - g.span
    y0 = g.lo[1] + float(cy) * g.c
    z0 = g.lo[2] + float(cz) * g.c
    dy = wp.max(wp.max(y0 - xi[1], xi[1] - (y0 + g.c)), 0.0)
    dz = wp.max(wp.max(z0 - xi[2], xi[2] - (z0 + g.c)), 0.0)
    d2 = dy * dy + dz * dz
    if d2 >= H * H:
        return 0, 0
    w = wp.sqrt(H * H - d2)
    x0 = int(wp.floor((xi[0] - w - g.lo[0]) * g.inv_cx))
    x1 = int(wp.floor((xi[0] + w - g.lo[0]) * g.inv_cx))
    base = g.nx * (wrap(cy, g.ny) + g.ny * wrap(cz, g.nz))
    a = wrap(x0, g.nx)
    b = wrap(x1, g.nx)
    whole = x1 - x0 + 1 >= g.nx  # the run covers the whole (wrapped) row
    if r % 2 == 0:
        if whole:
            return g.first[base], g.first[base + g.nx]
        if a <= b:
            return g.first[base + a], g.first[base + b + 1]
        return g.first[base + a], g.first[base + g.nx]
    if whole or a <= b:
        return 0, 0
    return g.first[base], g.first[base + b + 1]


@wp.kernel
def wall_pressure_adami(
    g: CellGrid,
    r_lo: int,
    r_hi: int,
    R: float,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    xq: wp.array(dtype=wp.vec3),
    q_off: int,
    wall_accel: wp.array(dtype=wp.vec3),
    p: SPHParams,
    wall_pressure: wp.array(dtype=float),
    wall_pr2: wp.array(dtype=wp.vec2),
    wall_v: wp.array(dtype=wp.vec3),
):
    """Generalized wall boundary condition (Adami, Hu & Adams 2012, eqs. 22, 23 and 27), launched over the
    boundary particles b, from the fluid particles f within H on the cell grid:

        p_b = (sum_f p_f W_bf + (g - a_b) . sum_f rho_f (x_b - x_f) W_bf) / sum_f W_bf,
        rho_b = EOS^-1(p_b),   v~_b = 2 v_b - sum_f v_f W_bf / sum_f W_bf

    so that the pressure gradient across the wall balances gravity and the wall's own acceleration a_b: a
    hydrostatic tank has the hydrostatic pressure on its walls and corners. Static walls have v_b = a_b = 0;
    the wall particles of moving blocks (rockwave/coupling/walls.py BlockWalls) carry the block's rigid velocity in
    v and its acceleration in wall_accel. A wall particle with no fluid within H gets p_b = 0, v~_b = 2 v_b.
    wall_pr2[b] = (p_b / rho_b^2, rho_b / rho0) is what the force pass reads (wall_pair_acceleration). R: the radius of the cell-grid query (the
    list radius: the grid may be the one of the last list build, see particle_density_overflow), centred at
    xq[q_off + t], the particle's position at that build (a moving wall particle has moved since)."""
    t = wp.tid()
    b = t + p.n_fluid
    xb = x[b]
    sw = float(0.0)
    sp = float(0.0)
    srx = wp.vec3(0.0)
    sv = wp.vec3(0.0)
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
                    sp += pressure[f] * w
                    srx += (rho[f] * w) * d
                    sv += w * v[f]
    pb = float(0.0)
    vw = v[b]
    vb = 2.0 * vw
    if sw > 0.0:
        pb = (sp + wp.dot(p.gravity - wall_accel[t], srx)) / sw
        vb = 2.0 * vw - sv / sw
    if p.clamp_negative != 0:
        pb = wp.max(pb, 0.0)
    # rho_b from the inverse EOS: Tait rho0 (p/B + 1)^(1/gamma); linear rho0 + p/k
    rb = float(0.0)
    if p.eos == EOS_TAIT:
        rb = p.rest_density * wp.pow(wp.max(pb / p.eos_b + 1.0, 1.0e-3), 1.0 / p.eos_gamma)
    else:
        rb = wp.max(p.rest_density + pb / p.eos_b, 1.0e-3 * p.rest_density)
    wall_pressure[t] = pb
    wall_pr2[t] = wp.vec2(pb / (rb * rb), rb / p.rest_density)
    wall_v[t] = vb


@wp.kernel
def build_neighbour_list_cells(
    g: CellGrid,
    x: wp.array(dtype=wp.vec3),
    H: float,
    r_lo: int,
    r_hi: int,
    rebuild: wp.array(dtype=int),
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    x_build: wp.array(dtype=wp.vec3),
):
    """The neighbours within H (here the list radius: support radius + skin) of each fluid particle on the
    cell grid (slot ranges r_lo..r_hi-1: 0..18 in 3D, 6..12 in 2D); x_build keeps the positions of the
    build for the skin's displacement check. rebuild[0] == 0: the list is still valid, nothing to do."""
    i = wp.tid()
    if rebuild[0] == 0:
        return
    n = count.shape[0]
    cap = nbr.shape[0] // n
    xi = x[i]
    x_build[i] = xi
    ix, iy, iz = cell_of(g, xi)
    c = int(0)
    for r in range(r_lo, r_hi):
        s, e = slot_range(g, xi, H, iy, iz, r)
        for k in range(s, e):
            if wp.length_sq(xi - g.x_sorted[k]) < H * H:
                j = g.order[k]
                if j != i:
                    if c < cap:
                        nbr[c * n + i] = j
                    c += 1
    count[i] = c


@wp.kernel
def list_displacement_check(x: wp.array(dtype=wp.vec3), x_off: int, x_build: wp.array(dtype=wp.vec3), b_off: int,
                            limit2: float, rebuild: wp.array(dtype=int)):
    """Verlet-list check: rebuild[0] = 1 when particle x_off + i has moved limit = skin/2 or more since the
    list was built (x_build[b_off + i]; or its position is not finite). A pair closer than H now was then
    closer than H + skin at the build, so the list (radius H + skin) still holds every neighbour. Launched
    over the fluid (offsets 0) and over the wall particles of moving blocks; static walls never move."""
    i = wp.tid()
    if not (wp.length_sq(x[x_off + i] - x_build[b_off + i]) < limit2):
        rebuild[0] = 1


@wp.struct
class CheckGrid:
    """Dense grid of cells of width c (>= 2 H) over the build positions, for the relative-displacement
    check of the neighbour lists (FluidSolver._list_guard)."""

    lo: wp.vec3
    inv_c: float
    nx: int
    ny: int
    nz: int


@wp.func
def check_cell(g: CheckGrid, x: wp.vec3) -> wp.vec3i:
    # clamped: a point outside the grid joins the edge cell (two points closer than c stay in cells at
    # most one apart along each axis, so the adjacency argument holds there too)
    q = (x - g.lo) * g.inv_c
    return wp.vec3i(wp.clamp(int(wp.floor(q[0])), 0, g.nx - 1), wp.clamp(int(wp.floor(q[1])), 0, g.ny - 1),
                    wp.clamp(int(wp.floor(q[2])), 0, g.nz - 1))


@wp.kernel
def displacement_bounds(
    g: CheckGrid,
    x: wp.array(dtype=wp.vec3),
    x_off: int,
    x_build: wp.array(dtype=wp.vec3),
    b_off: int,
    absolute2: float,
    overflowed: wp.array(dtype=int),
    moved: wp.array(dtype=int),
    d_lo: wp.array(dtype=wp.vec3),
    d_hi: wp.array(dtype=wp.vec3),
    rebuild: wp.array(dtype=int),
):
    """Per check cell (by build position) the box of the particles' displacements d = x - x_build
    (d_lo/d_hi pre-filled with +-BIG). A position that is not finite, or a particle moved sqrt(absolute2)
    while some list overflowed (the overflow passes query the kept cell grid, which holds the build
    positions, out to the list radius only), sets rebuild[0]. moved[0] == 0 (no particle moved
    sqrt(absolute2): then no pair moved twice that relative to each other either): nothing to do.
    Particle x_off + i, build position x_build[b_off + i] (as list_displacement_check)."""
    i = wp.tid()
    if moved[0] == 0:
        return
    xb = x_build[b_off + i]
    d = x[x_off + i] - xb
    r2 = wp.length_sq(d)
    if not (r2 < 1.0e30):
        rebuild[0] = 1
        return
    if overflowed[0] != 0 and r2 >= absolute2:
        rebuild[0] = 1
    c = check_cell(g, xb)
    k = c[0] + g.nx * (c[1] + g.ny * c[2])
    wp.atomic_min(d_lo, k, d)
    wp.atomic_max(d_hi, k, d)


@wp.kernel
def displacement_check_cells(
    g: CheckGrid,
    d_lo: wp.array(dtype=wp.vec3),
    d_hi: wp.array(dtype=wp.vec3),
    wall: wp.array(dtype=int),
    skin2: float,
    reach2: float,
    moved: wp.array(dtype=int),
    rebuild: wp.array(dtype=int),
):
    """The relative-displacement test of the Verlet lists: rebuild[0] = 1 when in some cell a particle
    moved sqrt(reach2) = (c - H)/2 or more, or two particles in the same or adjacent cells may have moved
    sqrt(skin2) = s H or more relative to each other (bound from their cells' displacement boxes).
    Why it suffices: a pair now closer than H that is not in the list (built out to (1 + s) H) has moved
    more than s H relative to each other, and was closer than H + 2 max|d| < c at the build, so it
    sits in the same or adjacent cells. Static wall particles never move: a cell holding some (wall[c] = 1)
    has d = 0 in its box. moved[0] == 0: as in displacement_bounds."""
    t = wp.tid()
    if moved[0] == 0:
        return
    ci = t % g.nx
    cj = (t // g.nx) % g.ny
    ck = t // (g.nx * g.ny)
    lo_a = d_lo[t]
    hi_a = d_hi[t]
    if wall[t] != 0:
        lo_a = wp.min(lo_a, wp.vec3(0.0))
        hi_a = wp.max(hi_a, wp.vec3(0.0))
    if lo_a[0] > hi_a[0]:  # no particle
        return
    far = wp.vec3(wp.max(wp.abs(lo_a[0]), wp.abs(hi_a[0])), wp.max(wp.abs(lo_a[1]), wp.abs(hi_a[1])),
                  wp.max(wp.abs(lo_a[2]), wp.abs(hi_a[2])))
    if wp.length_sq(far) >= reach2:
        rebuild[0] = 1
        return
    for k in range(wp.max(ck - 1, 0), wp.min(ck + 1, g.nz - 1) + 1):
        for j in range(wp.max(cj - 1, 0), wp.min(cj + 1, g.ny - 1) + 1):
            for i in range(wp.max(ci - 1, 0), wp.min(ci + 1, g.nx - 1) + 1):
                b = i + g.nx * (j + g.ny * k)
                if b >= t:  # each pair of cells once (and the cell with itself)
                    lo_b = d_lo[b]
                    hi_b = d_hi[b]
                    if wall[b] != 0:
                        lo_b = wp.min(lo_b, wp.vec3(0.0))
                        hi_b = wp.max(hi_b, wp.vec3(0.0))
                    if lo_b[0] <= hi_b[0]:
                        # max over d_i in box a, d_j in box b of |d_i - d_j|, per axis
                        e = wp.max(hi_a - lo_b, hi_b - lo_a)
                        if wp.length_sq(e) >= skin2:
                            rebuild[0] = 1
                            return


@wp.kernel
def list_overflow_flag(count: wp.array(dtype=int), cap: int, rebuild: wp.array(dtype=int), overflowed: wp.array(dtype=int)):
    """overflowed[0] = 1 when a list of this build holds more neighbours than its capacity (after the build;
    reset by list_overflow_reset before it). rebuild[0] == 0: no build this step."""
    i = wp.tid()
    if rebuild[0] != 0 and count[i] > cap:
        overflowed[0] = 1


@wp.kernel
def list_overflow_reset(rebuild: wp.array(dtype=int), overflowed: wp.array(dtype=int)):
    if rebuild[0] != 0:
        overflowed[0] = 0


# ------------------------------------------------------------------ neighbour lists ------
# One grid query per particle per step collects the neighbours within H into a list laid out
# neighbour-major (nbr[k * n_fluid + i], so that consecutive threads read consecutive words); the
# density and force passes then loop over true neighbours only. A hash-grid query visits ~6x more
# candidates than neighbours in 3D (27 cells of H^3 against a sphere of radius H), and on a GPU the
# lanes of a warp that find a neighbour make the others wait, so a candidate cost as much as a
# neighbour when the forces were summed inside the query loop. Particles with more than `cap`
# neighbours keep count > cap and are summed by a cell-grid query instead (correct, slower).


@wp.kernel
def particle_density_summation_list(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=float),
    p: SPHParams,
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
):
    """rho_i = m_i W(0) + sum_j m_j W_ij over the neighbour list, then p_i = EOS(rho_i) and
    pr2_i = p_i / rho_i^2 (particles whose list overflowed: particle_density_overflow)."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    if c > nbr.shape[0] // n:
        return
    xi = x[i]
    s = particle_mass[i] * kernel_w(0.0, p)
    H2 = p.H * p.H
    for k in range(c):
        j = nbr[k * n + i]
        r2 = wp.length_sq(xi - x[j])
        if r2 < H2:  # a list built with a skin also holds pairs out to H + skin
            s += particle_mass[j] * kernel_w(r2, p)
    rho[i] = s
    pr = equation_of_state(s, p)
    pressure[i] = pr
    pr2[i] = pr / (s * s)


@wp.func
def pair_density_rate(xi: wp.vec3, vi: wp.vec3, j: int, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                      particle_mass: wp.array(dtype=float), li: wp.mat33, kgc: wp.array(dtype=wp.mat33), p: SPHParams):
    # continuity: d rho_i/dt = sum_j m_j (v_i - v_j) . grad W_ij  (wall particles: v_j their wall's velocity,
    # 0 for static walls; between fluid particles the corrected gradient with fluid.gradient_correction)
    rij = xi - x[j]
    r2 = wp.length_sq(rij)
    if r2 >= p.H * p.H:  # a list built with a skin also holds pairs out to H + skin
        return 0.0
    g = kernel_grad(rij, wp.sqrt(r2), p)
    if j < p.n_fluid:
        return p.fluid_mass * wp.dot(vi - v[j], corrected_grad(g, li, j, kgc, p))
    return particle_mass[j] * wp.dot(vi - v[j], g)


@wp.func
def continuity_floor(rr: float, p: SPHParams) -> float:
    """The continuity density with fluid.density_floor: max(rr, rho0). With negative pressure clipped, a
    density below rho0 holds no pressure and no internal energy (int p/rho^2 d rho = 0 there), only a memory of
    expansion: a splash particle whose neighbours left it kept 250-300 kg/m^3 in SPHERIC Test 2 and, landing,
    was compressed back that far before it pushed at all (and crossed walls with density diffusion). Flooring
    it changes no energy; water that separates stays at rho0. Opt-in (docs/notes.md 'Density floor')."""
    if p.density_floor != 0:
        return wp.max(rr, p.rest_density)
    return rr


@wp.func
def step_of(dt: wp.array(dtype=float), i: int):
    """The step [s] of particle i: dt[0] (one step for all, the solo run), or dt[i] where dt holds one step per fluid
    particle (a batch of scenarios with their own steps: rockwave/sim/batch.py)."""
    if dt.shape[0] > 1:
        return dt[i]
    return dt[0]


@wp.func
def store_density(i: int, rr_in: float, p: SPHParams, rho: wp.array(dtype=float), pressure: wp.array(dtype=float),
                  pr2: wp.array(dtype=float)):
    """rho_i = rr (continuity_floor applied), p_i = EOS(rr), pr2_i = p_i / rr^2 (the force pass reads pr2)."""
    rr = continuity_floor(rr_in, p)
    rho[i] = rr
    pr = equation_of_state(rr, p)
    pressure[i] = pr
    pr2[i] = pr / (rr * rr)


@wp.kernel
def particle_density_continuity_list(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=float),
    dt: wp.array(dtype=float),
    kgc: wp.array(dtype=wp.mat33),
    p: SPHParams,
    drho_dt: wp.array(dtype=float),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
):
    """Continuity density rate over the neighbour list, then rho_i += dt d rho_i/dt, p_i = EOS(rho_i),
    pr2_i = p_i / rho_i^2 (overflowed lists: particle_density_overflow). The density is advanced
    before the forces are evaluated (the forces then see the density of the current positions):
    evaluating both from the start-of-step state is forward Euler for the acoustic (rho, v)
    oscillator and gained energy in the 2D hydrostatic tank."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    if c > nbr.shape[0] // n:
        return
    xi = x[i]
    vi = v[i]
    s = float(0.0)
    li = own_correction(kgc, i, p)
    for k in range(c):
        s += pair_density_rate(xi, vi, nbr[k * n + i], x, v, particle_mass, li, kgc, p)
    drho_dt[i] = s
    store_density(i, rho[i] + step_of(dt, i) * s, p, rho, pressure, pr2)


@wp.kernel
def particle_density_overflow(
    g: CellGrid,
    r_lo: int,
    r_hi: int,
    R: float,
    count: wp.array(dtype=int),
    cap: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=float),
    dt: wp.array(dtype=float),
    kgc: wp.array(dtype=wp.mat33),
    p: SPHParams,
    summation: int,
    drho_dt: wp.array(dtype=float),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
):
    """The density passes for the particles whose neighbour list overflowed (count > cap): the same
    sums over a cell-grid query of radius R, the list radius (every other particle returns at once).
    With a skin the grid may be the one of the list build: its points have since moved less than
    skin/2, so a neighbour within H now lies within H + skin/2 < R of x_i in that grid."""
    i = wp.tid()
    if count[i] <= cap:
        return
    xi = x[i]
    vi = v[i]
    s = float(0.0)
    if summation != 0:
        s = particle_mass[i] * kernel_w(0.0, p)
    li = own_correction(kgc, i, p)
    ix, iy, iz = cell_of(g, xi)
    for r in range(r_lo, r_hi):
        s0, e0 = slot_range(g, xi, R, iy, iz, r)
        for k in range(s0, e0):
            j = g.order[k]
            if j != i and wp.length_sq(xi - x[j]) < p.H * p.H:
                if summation != 0:
                    s += particle_mass[j] * kernel_w(wp.length_sq(xi - x[j]), p)
                else:
                    s += pair_density_rate(xi, vi, j, x, v, particle_mass, li, kgc, p)
    if summation == 0:
        drho_dt[i] = s
        s = continuity_floor(rho[i] + step_of(dt, i) * s, p)
    rho[i] = s
    pr = equation_of_state(s, p)
    pressure[i] = pr
    pr2[i] = pr / (s * s)


DENSITY_NONE = wp.constant(0)
DENSITY_CONTINUITY = wp.constant(1)
DENSITY_SUMMATION = wp.constant(2)


@wp.kernel
def neighbour_list_density(
    g: CellGrid,
    r_lo: int,
    r_hi: int,
    R: float,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=float),
    dt: wp.array(dtype=float),
    p: SPHParams,
    mode: int,
    kgc: wp.array(dtype=wp.mat33),
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    drho_dt: wp.array(dtype=float),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
    x_build: wp.array(dtype=wp.vec3),
):
    """build_neighbour_list_cells (list radius R = H + skin) and, in the same query, the density
    over the pairs closer than H: DENSITY_CONTINUITY advances rho_i by dt sum_j m_j (v_i - v_j) . grad W_ij;
    DENSITY_SUMMATION sets rho_i = sum_j m_j W_ij (self included); then p_i = EOS(rho_i) (see
    particle_density_continuity_list for the order). Always a rebuild (the host decides when to launch it)."""
    i = wp.tid()
    n = count.shape[0]
    cap = nbr.shape[0] // n
    xi = x[i]
    x_build[i] = xi
    vi = v[i]
    s = float(0.0)
    if mode == DENSITY_SUMMATION:
        s = particle_mass[i] * kernel_w(0.0, p)
    c = int(0)
    H2 = p.H * p.H
    li = own_correction(kgc, i, p)
    ix, iy, iz = cell_of(g, xi)
    for r in range(r_lo, r_hi):
        s0, e0 = slot_range(g, xi, R, iy, iz, r)
        for k in range(s0, e0):
            j = g.order[k]
            r2 = wp.length_sq(xi - x[j])
            if j != i and r2 < R * R:
                if c < cap:
                    nbr[c * n + i] = j
                c += 1
                if r2 < H2:
                    if mode == DENSITY_CONTINUITY:
                        s += pair_density_rate(xi, vi, j, x, v, particle_mass, li, kgc, p)
                    elif mode == DENSITY_SUMMATION:
                        s += particle_mass[j] * kernel_w(r2, p)
    count[i] = c
    if mode == DENSITY_CONTINUITY:
        drho_dt[i] = s
        s = continuity_floor(rho[i] + step_of(dt, i) * s, p)
    if mode != DENSITY_NONE:
        rho[i] = s
        pr = equation_of_state(s, p)
        pressure[i] = pr
        pr2[i] = pr / (s * s)


@wp.func
def pair_acceleration_fluid(
    j: int,
    xi: wp.vec3,
    vi: wp.vec3,
    rhoi: float,
    pi: float,
    pi_r2: float,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    wall_pr2: wp.array(dtype=wp.vec2),
    wall_v: wp.array(dtype=wp.vec3),
    li: wp.mat33,
    kgc: wp.array(dtype=wp.mat33),
    p: SPHParams,
):
    """pair_acceleration with the fluid mass from p.fluid_mass (no mass read for fluid neighbours) and
    p_j/rho_j^2 from pr2 (momentum form): ~27% less time in the force pass on an H100. Pairs at
    r >= H (a list built with a skin holds them out to H + skin) add nothing."""
    rij = xi - x[j]
    r2 = wp.length_sq(rij)
    dv = wp.vec3(0.0)
    if r2 >= p.H * p.H:
        return dv, dv
    r = wp.sqrt(r2)
    gw = kernel_grad(rij, r, p)
    if j >= p.n_fluid:
        if p.boundary == BOUNDARY_AKINCI:
            # Akinci et al. 2012 boundary pressure: a_i -= Psi_b p_i/rho_i^2 grad W_ib (walls at rest)
            return -(particle_mass[j] * pi_r2) * gw, dv
        return wall_pair_acceleration(j - p.n_fluid, rij, r2, gw, vi, rhoi, pi_r2, particle_mass[j], wall_pr2, wall_v, p), dv
    gc = corrected_grad(gw, li, j, kgc, p)
    mj = p.fluid_mass
    rhoj = rho[j]
    a = wp.vec3(0.0)
    if p.pressure_form == FORCE_MOMENTUM:
        # a_i -= sum_j m_j (p_i/rho_i^2 + p_j/rho_j^2) G_ij  (Monaghan 1992; G_ij: corrected_grad)
        a = -(mj * (pi_r2 + pr2[j])) * gc
    else:
        # Mueller 2003 symmetric: a_i -= 1/rho_i sum_j m_j (p_i + p_j)/(2 rho_j) G_ij
        a = -(mj * (pi + pressure[j]) / (2.0 * rhoj * rhoi)) * gc
    vij = vi - v[j]
    if p.mu > 0.0:
        # Mueller 2003: a_i += mu/rho_i sum_j m_j (v_j - v_i)/rho_j lap W_ij
        a -= (p.mu * mj / (rhoi * rhoj) * kernel_laplacian(r, p)) * vij
    if p.alpha > 0.0:
        # Monaghan 1992: Pi_ij = -alpha c mu_ij / rho_ij, mu_ij = h v_ij.r_ij/(r^2 + 0.01 h^2), only when approaching
        vr = wp.dot(vij, rij)
        if vr < 0.0:
            h_s = 0.5 * p.H
            mu_ij = h_s * vr / (r2 + 0.01 * h_s * h_s)
            a -= mj * (-p.alpha * p.sound_speed * mu_ij / (0.5 * (rhoi + rhoj))) * gw
    if p.xsph > 0.0:
        dv = -(mj / (0.5 * (rhoi + rhoj)) * kernel_w(r2, p)) * vij
    return a, dv


# The force pass is launched with its own block size on CUDA (rockwave.sph.fluid.FluidSolver._block_dim: 128,
# every other launch 256). Warp builds a module once per block size, so in this module it would build
# all of rockwave.kernels.sph.fluid twice (and again after every change of the module); it lives in a module
# of its own, built only at the force pass's block size.
FORCE_PASS_MODULE = "rockwave.kernels.sph.fluid_force_pass"


@wp.kernel(module=FORCE_PASS_MODULE)
def particle_acceleration_list(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
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
    """a_i = pressure + viscosity + gravity and the XSPH correction dv_i = eps sum m_j/rho_ij (v_j - v_i) W_ij over the
    neighbour list (pair_acceleration per neighbour; overflowed lists: particle_acceleration_overflow; kgc: the
    gradient-correction matrices, or a one-entry placeholder without the correction)."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    if c > nbr.shape[0] // n:
        return
    xi = x[i]
    vi = v[i]
    rhoi = rho[i]
    pi = pressure[i]
    pi_r2 = pr2[i]
    a = wp.vec3(0.0)
    dv = wp.vec3(0.0)
    li = own_correction(kgc, i, p)
    for k in range(c):
        da, ddv = pair_acceleration_fluid(nbr[k * n + i], xi, vi, rhoi, pi, pi_r2, x, v, rho, pressure, pr2,
                                          particle_mass, wall_pr2, wall_v, li, kgc, p)
        a += da
        dv += ddv
    accel[i] = a + p.gravity
    xsph_dv[i] = p.xsph * dv


@wp.kernel
def particle_acceleration_overflow(
    g: CellGrid,
    r_lo: int,
    r_hi: int,
    R: float,
    count: wp.array(dtype=int),
    cap: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    wall_pr2: wp.array(dtype=wp.vec2),
    wall_v: wp.array(dtype=wp.vec3),
    kgc: wp.array(dtype=wp.mat33),
    p: SPHParams,
    accel: wp.array(dtype=wp.vec3),
    xsph_dv: wp.array(dtype=wp.vec3),
):
    """particle_acceleration_list for the particles whose neighbour list overflowed, over a cell-grid query of
    radius R (the list radius; see particle_density_overflow)."""
    i = wp.tid()
    if count[i] <= cap:
        return
    xi = x[i]
    vi = v[i]
    rhoi = rho[i]
    pi = pressure[i]
    a = wp.vec3(0.0)
    dv = wp.vec3(0.0)
    li = own_correction(kgc, i, p)
    ix, iy, iz = cell_of(g, xi)
    for r in range(r_lo, r_hi):
        s0, e0 = slot_range(g, xi, R, iy, iz, r)
        for k in range(s0, e0):
            j = g.order[k]
            if j != i and wp.length_sq(xi - x[j]) < p.H * p.H:
                da, ddv = pair_acceleration(i, j, xi, vi, rhoi, pi, x, v, rho, pressure, particle_mass, wall_pr2, wall_v,
                                            li, kgc, p)
                a += da
                dv += ddv
    accel[i] = a + p.gravity
    xsph_dv[i] = p.xsph * dv


@wp.kernel
def integrate_particles(
    accel: wp.array(dtype=wp.vec3),
    xsph_dv: wp.array(dtype=wp.vec3),
    dt: wp.array(dtype=float),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
):
    """Semi-implicit (symplectic) Euler: v += a dt; x += (v + dv_xsph) dt."""
    i = wp.tid()
    h = step_of(dt, i)
    vn = v[i] + h * accel[i]
    v[i] = vn
    x[i] = x[i] + h * (vn + xsph_dv[i])


@wp.kernel
def motion_extrema(
    v: wp.array(dtype=wp.vec3),
    accel: wp.array(dtype=wp.vec3),
    n: int,
    stride: int,
    out: wp.array(dtype=float),
):
    """out[0] = max |v|^2, out[1] = max |a|^2 over the first n particles (for the CFL and force
    time-step limits). Launched over `stride` threads, each reducing every stride-th particle before its
    two atomics (one atomic per particle on two words serialises on a GPU)."""
    t = wp.tid()
    v2 = float(0.0)
    a2 = float(0.0)
    i = t
    while i < n:
        v2 = wp.max(v2, wp.length_sq(v[i]))
        a2 = wp.max(a2, wp.length_sq(accel[i]))
        i += stride
    wp.atomic_max(out, 0, v2)
    wp.atomic_max(out, 1, a2)


@wp.kernel
def neighbour_count(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    H: float,
    count: wp.array(dtype=int),
):
    """Number of neighbours within the support radius (self excluded), fluid and boundary."""
    i = wp.tid()
    xi = x[i]
    c = int(0)
    q = wp.hash_grid_query(grid, xi, H)
    j = int(0)
    while wp.hash_grid_query_next(q, j):
        if j != i and wp.length_sq(xi - x[j]) < H * H:
            c += 1
    count[i] = c


# ------------------------------------------------------------------ particle order ------
# Fluid particles are reordered by hash-grid cell every few steps (rockwave.sph.fluid.FluidSolver.reorder)
# so that neighbour reads are coherent; boundary particles (indices >= n_fluid) never move.


@wp.kernel
def sorted_fluid_flags(order: wp.array(dtype=int), n_fluid: int, flag: wp.array(dtype=int)):
    """flag[k] = 1 when the k-th point in the cell order is a fluid particle."""
    k = wp.tid()
    if order[k] < n_fluid:
        flag[k] = 1
    else:
        flag[k] = 0


@wp.kernel
def sorted_fluid_perm(order: wp.array(dtype=int), n_fluid: int, flag: wp.array(dtype=int), rank: wp.array(dtype=int),
                      perm: wp.array(dtype=int)):
    """perm[d] = index of the d-th fluid particle in cell order (stable compaction of the grid order)."""
    k = wp.tid()
    if flag[k] == 1:
        perm[rank[k]] = order[k]


@wp.kernel
def gather_by(perm: wp.array(dtype=int), src: wp.array(dtype=Any), dst: wp.array(dtype=Any)):
    i = wp.tid()
    dst[i] = src[perm[i]]


@wp.kernel
def scatter_by(ids: wp.array(dtype=int), src: wp.array(dtype=Any), dst: wp.array(dtype=Any)):
    i = wp.tid()
    dst[ids[i]] = src[i]


# The permutations run on vec3, float and int arrays. Their overloads are declared here, with the module:
# an overload made at the first launch of a new dtype changes the module's hash, and Warp then rebuilds
# the whole module (one full build per new dtype, on each device).
for _permute_kernel in (gather_by, scatter_by):
    for _dtype in (wp.vec3, float, int):
        wp.overload(_permute_kernel, [wp.array(dtype=int), wp.array(dtype=_dtype), wp.array(dtype=_dtype)])
del _permute_kernel, _dtype


@wp.kernel
def iota(a: wp.array(dtype=int)):
    i = wp.tid()
    a[i] = i


@wp.kernel
def store_build_positions(x: wp.array(dtype=wp.vec3), x_off: int, rebuild: wp.array(dtype=int),
                          x_build: wp.array(dtype=wp.vec3), b_off: int):
    """x_build[b_off + i] = x[x_off + i] at a list build (rebuild[0] != 0): the build positions of the wall
    particles of moving blocks, for the displacement checks and the wall pressure's cell query."""
    i = wp.tid()
    if rebuild[0] != 0:
        x_build[b_off + i] = x[x_off + i]
