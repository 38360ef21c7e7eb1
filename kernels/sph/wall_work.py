"""The work of the Adami walls' extrapolated pressure, paired in the continuity equation (launched by
rockwave/sph/fluid.py FluidSolver.wall_work, the ``wall_work`` pass between the density and the wall pressure;
continuity density with Adami walls only).

The wall term of the momentum equation (Adami, Hu & Adams 2012) a_i -= m_b (p_i/rho_i^2 + p_b/rho_b^2) grad W_ib has
two parts. The p_i part does work that the continuity equation pays back exactly: d rho_i/dt holds
m_b (v_i - v_b) . grad W_ib, and m_i p_i/rho_i^2 d rho_i/dt is the change of i's internal energy. The p_b part
has no such partner: the wall particle's pressure is extrapolated from the fluid around it,
p_b = sum_f w_bf p_f + (g - a_b) . sum_f rho_f r_bf w_bf (w_bf = W_bf / sum_f W_bf), and its state changes with
nobody's energy. Its power on the water (relative to the wall, whose reaction the block takes) is

    P_b = -c_b p_b R_b,   c_b = m_b' / rho_b^2,   R_b = sum_k m_k (v_k - v_b) . grad_k W_kb,

m_b' the wall's mass in the force term (m_b, or m_b rho_b/rho0 with fluid.wall_volume = 'geometric'). R_b is the
rate of the fluid's summation density at the wall: water that leaves the wall (R_b < 0) is pushed by p_b and gains
kinetic energy. If p_b were a state of the wall's own (its summation density through an EOS, as a fluid particle)
its internal energy m_b e(rho_b) would pay for it. Here the fluid particles that set p_b pay, each by its share of
the extrapolation:

    d rho_f/dt += rho_f^2/m_f sum_b w_bf c_b (p_b/pbar_b) R_b,   pbar_b = sum_f w_bf p_f,

so that sum_f m_f p_f/rho_f^2 d rho_f/dt = sum_b c_b p_b R_b, the power of p_b, its hydrostatic part included. The
particles whose pressure the wall carries decompress as water leaves the wall and are compressed as water arrives,
as the mirror image of the water behind a wall would be. The share p_b/pbar_b is kept within [0, PB_SHARE_MAX]:
where the setters hold almost no pressure (a wall beside the free surface, p_b mostly the extrapolation's
hydrostatic term) they cannot pay for it, and an unbounded share there would compress them without limit; a bound
of 2 pays for the hydrostatic part up to the setters' own pressure (chosen, not fitted: no other value was run).
Without the share (pairing sum_f w_bf p_f only) the hydrostatic part's work stayed unpaired and the standing wave
of tests/test_standing_wave.py decayed 17% per period with 6.5% of its kinetic energy at the particle scale,
against 13% and 2.8% without any pairing and 15% and 3.6% with it (CPU, 16 per depth; docs/notes.md). p_b and
rho_b are the wall's of the last step (state.wall_pressure): extrapolated again here from this step's density
before the pairing, the piston wave maker of tests/test_coupling.py read -19.8% of linear theory (-8.7% with the
last step's, -10% without pairing); why this is so sensitive was not found.

Without the pairing a particle held compressed by something that does no work (water pressed into the floor's wall
layer by a block resting on the floor) raised the wall pressure of its whole neighbourhood, which then pushed the
water beside it away for nothing: the landing under water of issue 37 (docs/notes.md, "Landing under water: the
wall pressure's work paired").
"""

import warp as wp

from rockwave.kernels.sph.fluid import (
    EOS_TAIT,
    CellGrid,
    SPHParams,
    cell_of,
    kernel_grad,
    kernel_w,
    slot_range,
    step_of,
    store_density,
)

wp.set_module_options({"enable_backward": False})

PB_SHARE_MAX = wp.constant(2.0)  # the largest share p_b/pbar_b the setters pay for (module docstring)


@wp.kernel
def wall_density_rate(
    g: CellGrid,
    r_lo: int,
    r_hi: int,
    R: float,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=float),
    xq: wp.array(dtype=wp.vec3),
    q_off: int,
    wall_pressure: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    p: SPHParams,
    wall_rate: wp.array(dtype=float),
):
    """Per boundary particle b (launched over them; the cell-grid query of wall_pressure_adami, radius R centred at
    xq[q_off + t]): wall_rate[t] = c_b (p_b/pbar_b) R_b / sum_f W_bf (module docstring), c_b from the wall's pressure of the last step
    (wall_pressure[t], part of the state: a resumed run is the same; 0 before the first: rho_b = rho0) through the
    inverse EOS. 0 with no fluid within H."""
    t = wp.tid()
    b = t + p.n_fluid
    xb = x[b]
    vb = v[b]
    sw = float(0.0)
    rate = float(0.0)
    spf = float(0.0)
    H2 = p.H * p.H
    xc = xq[q_off + t]
    ix, iy, iz = cell_of(g, xc)
    for r in range(r_lo, r_hi):
        s0, e0 = slot_range(g, xc, R, iy, iz, r)
        for k in range(s0, e0):
            f = g.order[k]
            if f < p.n_fluid:
                d = x[f] - xb
                r2 = wp.length_sq(d)
                if r2 < H2:
                    wf = kernel_w(r2, p)
                    sw += wf
                    spf += wf * pressure[f]
                    # R_b = sum_f m_f (v_f - v_b) . grad_f W(x_f - x_b): the rate of the fluid's summation density at b
                    rate += particle_mass[f] * wp.dot(v[f] - vb, kernel_grad(d, wp.sqrt(r2), p))
    if sw <= 0.0:
        wall_rate[t] = 0.0
        return
    # rho_b/rho0 from the inverse EOS, as wall_pressure_adami: Tait (p/B + 1)^(1/gamma); linear 1 + p/(k rho0)
    pb = wall_pressure[t]
    rr = float(0.0)
    if p.eos == EOS_TAIT:
        rr = wp.pow(wp.max(pb / p.eos_b + 1.0, 1.0e-3), 1.0 / p.eos_gamma)
    else:
        rr = wp.max(1.0 + pb / (p.eos_b * p.rest_density), 1.0e-3)
    mp = particle_mass[b]
    if p.wall_volume != 0:
        mp = mp * rr
    rho_b = rr * p.rest_density
    # the share of the setters' pressure: p_b / pbar_b, pbar_b = sum_f p_f W_bf / sum_f W_bf (this step's), so that the
    # paired work is that of the whole p_b, its hydrostatic part included; at most PB_SHARE_MAX (module docstring)
    c = mp / (rho_b * rho_b)
    pbar = spf / sw
    if pbar > 1.0e-6 * p.eos_b:
        c = c * wp.clamp(pb / pbar, 0.0, PB_SHARE_MAX)
    wall_rate[t] = c * rate / sw


@wp.func
def wall_share(xi: wp.vec3, j: int, x: wp.array(dtype=wp.vec3), wall_rate: wp.array(dtype=float), p: SPHParams):
    # W_ib (wall_rate of wall particle j): 0 for a fluid neighbour or beyond H
    if j < p.n_fluid:
        return 0.0
    r2 = wp.length_sq(xi - x[j])
    if r2 >= p.H * p.H:
        return 0.0
    return kernel_w(r2, p) * wall_rate[j - p.n_fluid]


@wp.kernel
def paired_wall_density(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    g: CellGrid,
    r_lo: int,
    r_hi: int,
    R: float,
    x: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=float),
    wall_rate: wp.array(dtype=float),
    dt: wp.array(dtype=float),
    p: SPHParams,
    drho_dt: wp.array(dtype=float),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
):
    """rho_i += dt rho_i^2/m_i sum_b W_ib wall_rate[b] over the wall neighbours (the list; a cell-grid query of
    radius R where it overflowed), then p_i = EOS(rho_i), pr2_i = p_i/rho_i^2; the rate is added to drho_dt."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    xi = x[i]
    s = float(0.0)
    if c <= nbr.shape[0] // n:
        for k in range(c):
            s += wall_share(xi, nbr[k * n + i], x, wall_rate, p)
    else:
        ix, iy, iz = cell_of(g, xi)
        for r in range(r_lo, r_hi):
            s0, e0 = slot_range(g, xi, R, iy, iz, r)
            for k in range(s0, e0):
                s += wall_share(xi, g.order[k], x, wall_rate, p)
    if s == 0.0:
        return
    ri = rho[i]
    rate = ri * ri / particle_mass[i] * s
    drho_dt[i] = drho_dt[i] + rate
    store_density(i, ri + step_of(dt, i) * rate, p, rho, pressure, pr2)
