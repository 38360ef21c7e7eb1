"""Gauge kernels, launched by rockwave/readers.py (Gauges): free-surface height and pressure probes
evaluated on the device from the current state; one host read returns every gauge's value."""

import warp as wp

from rockwave.kernels.fluid import SPHParams, kernel_w


@wp.kernel
def gauge_height(
    x: wp.array(dtype=wp.vec3),
    gauge_pos: wp.array(dtype=wp.vec3),
    up: int,
    radius: float,
    cell: float,
    m: int,
    top: wp.array2d(dtype=float),
):
    """Column tops for the free-surface gauges (launched over fluid particles x gauges).

    Around each gauge's vertical line the horizontal plane is cut into square columns of width `cell`
    on a (2m)^2 grid centred on the line (2D, up == 1: one row of 2m columns); the columns whose centre
    lies within `radius` of the line are used whole (no slivers: a clipped column would see only part of
    its particles and read low). top[g, c] is the highest up-coordinate of the fluid particles in column c
    (-1e30 where it holds none); gauge_median reduces them to one reading."""
    i, g = wp.tid()
    d = x[i] - gauge_pos[g]
    a0 = int(0)
    a1 = int(2)
    if up == 0:
        a0 = 1
    elif up == 2:
        a1 = 1
    n2 = 2 * m
    ca = int(wp.floor(d[a0] / cell)) + m
    cb = m
    oa = (float(ca - m) + 0.5) * cell
    ob = float(0.0)
    if up != 1:
        cb = int(wp.floor(d[a1] / cell)) + m
        ob = (float(cb - m) + 0.5) * cell
    if ca >= 0 and ca < n2 and cb >= 0 and cb < n2:
        if oa * oa + ob * ob < radius * radius:
            wp.atomic_max(top, g, ca * n2 + cb, x[i][up])


@wp.kernel
def gauge_pressure_sums(
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    gauge_pos: wp.array(dtype=wp.vec3),
    p: SPHParams,
    sums: wp.array2d(dtype=float),
):
    """The Shepard sums of the pressure gauges, launched over fluid particles x gauges (no grid to build):
    sums[g, 0] += V_j p_j W(x_g - x_j), sums[g, 1] += V_j W(x_g - x_j), V_j = m_j / rho_j, for r < H."""
    j, g = wp.tid()
    r2 = wp.length_sq(gauge_pos[g] - x[j])
    if r2 < p.H * p.H:
        w = particle_mass[j] / rho[j] * kernel_w(r2, p)
        wp.atomic_add(sums, g, 0, w * pressure[j])
        wp.atomic_add(sums, g, 1, w)


@wp.kernel
def gauge_pressure(sums: wp.array2d(dtype=float), out: wp.array(dtype=float)):
    """Shepard-normalised SPH interpolation p(x_g) = sum V_j p_j W / sum V_j W (0 where no particle is near)."""
    g = wp.tid()
    if sums[g, 1] > 0.0:
        out[g] = sums[g, 0] / sums[g, 1]
    else:
        out[g] = 0.0


@wp.kernel
def gauge_median(top: wp.array2d(dtype=float), is_height: wp.array(dtype=int), out: wp.array(dtype=float)):
    """Median of the wet column tops of each height gauge (top > -1e29; NaN when none is wet), as
    numpy.median: the mean of the two middle values for an even count. One thread per gauge
    (a few dozen columns: rank counting, no sort)."""
    g = wp.tid()
    if is_height[g] == 0:
        return
    n = top.shape[1]
    k = int(0)
    for c in range(n):
        if top[g, c] > -1.0e29:
            k += 1
    if k == 0:
        out[g] = wp.nan
        return
    lo_rank = (k - 1) / 2
    hi_rank = k / 2
    a = float(0.0)
    b = float(0.0)
    for c in range(n):
        v = top[g, c]
        if v > -1.0e29:
            below = int(0)
            equal = int(0)
            for e in range(n):
                u = top[g, e]
                if u > -1.0e29:
                    if u < v:
                        below += 1
                    elif u == v:
                        equal += 1
            # v holds ranks below .. below + equal - 1
            if lo_rank >= below and lo_rank < below + equal:
                a = v
            if hi_rank >= below and hi_rank < below + equal:
                b = v
    out[g] = (a + b) * 0.5


@wp.kernel
def gauge_pressure_wall_sums(
    x: wp.array(dtype=wp.vec3),
    wall_pressure: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    gauge_pos: wp.array(dtype=wp.vec3),
    p: SPHParams,
    sums: wp.array2d(dtype=float),
):
    """Adami walls (kernels/fluid.py wall_pressure_adami): the wall particles' share of the pressure gauges'
    Shepard sums, launched over boundary particles x gauges, V_b = m_b / rho0. A sensor on a wall then averages
    over both sides of the wall surface, as the wall's own pressure field continues the fluid's (a sum over
    the fluid alone is centred inside the water and reads the pressure of a shallower point)."""
    t, g = wp.tid()
    b = t + p.n_fluid
    r2 = wp.length_sq(gauge_pos[g] - x[b])
    if r2 < p.H * p.H:
        w = particle_mass[b] / p.rest_density * kernel_w(r2, p)
        wp.atomic_add(sums, g, 0, w * wall_pressure[t])
        wp.atomic_add(sums, g, 1, w)
