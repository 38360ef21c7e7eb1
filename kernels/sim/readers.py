"""Gauge kernels, launched by rockwave/sim/readers.py (Gauges): water-level and pressure probes evaluated on
the device from the current state; one host read returns every gauge's value."""

import warp as wp

from rockwave.kernels.sph.fluid import SPHParams, kernel_w

wp.set_module_options({"enable_backward": False})  # forward kernels only: nothing here is differentiated

# A sample whose open (non-solid) fraction 1 - phi_s is below this is inside a wall: not water.
SOLID_CUTOFF = wp.constant(0.2)


@wp.func
def line_add(xj: wp.vec3, vol: float, origin: wp.vec3, up: int, z0: float, dz: float, p: SPHParams,
             prof: wp.array2d(dtype=float), g: int):
    """Add V_j W(|x(z_k) - x_j|) to prof[g, k] at the samples z_k = z0 + k dz of the vertical line through
    origin that lie within the support H of x_j (nothing when x_j is H or more from the line)."""
    d = xj - origin
    zj = xj[up]
    d[up] = 0.0
    h2 = wp.length_sq(d)
    hh = p.H * p.H
    if h2 >= hh:
        return
    reach = wp.sqrt(hh - h2)
    n = prof.shape[1]
    k0 = wp.max(int(wp.ceil((zj - reach - z0) / dz)), 0)
    k1 = wp.min(int(wp.floor((zj + reach - z0) / dz)), n - 1)
    for k in range(k0, k1 + 1):
        e = z0 + float(k) * dz - zj
        wp.atomic_add(prof, g, k, vol * kernel_w(h2 + e * e, p))


@wp.kernel
def gauge_fluid_profile(
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    gauge_pos: wp.array(dtype=wp.vec3),
    is_height: wp.array(dtype=int),
    up: int,
    z0: float,
    dz: float,
    p: SPHParams,
    prof: wp.array2d(dtype=float),
):
    """The fluid fraction phi_f(z_k) = sum_j V_j W(|x(z_k) - x_j|), V_j = m_j / rho_j, sampled along each
    height gauge's vertical line (launched over fluid particles x gauges; particles H or more from the
    line add nothing)."""
    j, g = wp.tid()
    if is_height[g] == 0:
        return
    line_add(x[j], particle_mass[j] / rho[j], gauge_pos[g], up, z0, dz, p, prof, g)


@wp.kernel
def gauge_solid_profile(
    x: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=float),
    offset: int,
    gauge_pos: wp.array(dtype=wp.vec3),
    is_height: wp.array(dtype=int),
    up: int,
    z0: float,
    dz: float,
    p: SPHParams,
    prof: wp.array2d(dtype=float),
):
    """The solid fraction phi_s(z_k) = sum_b V_b W of the (static) boundary particles, V_b = Psi_b / rho0,
    along each height gauge's line (launched once over boundary particles x gauges; x holds the boundary
    particles, particle_mass the fluid's first: offset = n_fluid)."""
    b, g = wp.tid()
    if is_height[g] == 0:
        return
    line_add(x[b], particle_mass[offset + b] / p.rest_density, gauge_pos[g], up, z0, dz, p, prof, g)


@wp.kernel
def kernel_slabs(p: SPHParams, m: int, out: wp.array(dtype=float)):
    """The kernel's weight in slab i of m across its support, z in [-H + i dz, -H + (i + 1) dz], dz = 2H/m (one
    thread per slab; midpoint rule, m points each way): dz A(z_i), A(z) = 2 pi int_|z|^H W(rho) rho drho over the
    plane at height z (3D; rho^2 = r^2 + z^2), or 2 int_0^sqrt(H^2 - z^2) W(sqrt(r^2 + z^2)) dr over the line (2D).
    Summed from the top, F(d) = int_d^H A(z) dz is the kernel-weighted volume of a half-space whose face lies d
    below the kernel's centre (moving_solid_profile; rockwave/sim/readers.py MovingSolids)."""
    i = wp.tid()
    H = p.H
    dz = 2.0 * H / float(m)
    z = -H + (float(i) + 0.5) * dz
    acc = float(0.0)
    if p.dim == 3:
        dr = (H - wp.abs(z)) / float(m)
        for j in range(m):
            rho = wp.abs(z) + (float(j) + 0.5) * dr
            acc += 2.0 * wp.pi * kernel_w(rho * rho, p) * rho * dr
    else:
        half = wp.sqrt(wp.max(H * H - z * z, 0.0))
        dr = half / float(m)
        for j in range(m):
            r = (float(j) + 0.5) * dr
            acc += 2.0 * kernel_w(r * r + z * z, p) * dr
    out[i] = acc * dz


@wp.func
def half_space_fraction(d: float, table: wp.array(dtype=float), H: float) -> float:
    """F(d): the share of the kernel's weight on the far side of a plane d from its centre (d < 0: the centre is
    behind the plane), linear in the table of F at d_i = -H + i 2H/(n - 1); 1 at d <= -H, 0 at d >= H."""
    n = table.shape[0]
    u = (d + H) / (2.0 * H) * float(n - 1)
    if u <= 0.0:
        return 1.0
    if u >= float(n - 1):
        return 0.0
    i = int(wp.floor(u))
    w = u - float(i)
    return table[i] * (1.0 - w) + table[wp.min(i + 1, n - 1)] * w


@wp.kernel
def moving_solid_profile(
    line_pos: wp.array(dtype=wp.vec3),
    line_z0: wp.array(dtype=float),
    line_dz: wp.array(dtype=float),
    line_n: wp.array(dtype=int),
    solid_first: wp.array(dtype=int),
    solid_count: wp.array(dtype=int),
    solid_list: wp.array(dtype=int),
    solid_block: wp.array(dtype=int),
    solid_radius: wp.array(dtype=float),
    face_first: wp.array(dtype=int),
    face_count: wp.array(dtype=int),
    plane_n: wp.array(dtype=wp.vec3),
    plane_d: wp.array(dtype=float),
    bx: wp.array(dtype=wp.vec3),
    up: int,
    H: float,
    table: wp.array(dtype=float),
    prof: wp.array2d(dtype=float),
):
    """The moving blocks' solid fraction along each vertical line (launched over lines x the most moving blocks of
    a line; line g's are the solids solid_list[solid_first[g] + i], i < solid_count[g], each a block solid_block[s]
    with its bounding radius about the centroid and its world face planes): with dist = max_k (n_k . x - d_k) the
    sample's signed distance to the block (convex: exact inside and over a face, short of the true distance off
    an edge), phi_m = 1 inside (dist < 0: the line is in the block there) and F(dist) within H outside, F the
    kernel's weight beyond a plane at that distance (half_space_fraction): the share a flat face takes of the
    kernel support, as the static walls' particles do in phi_s. Where blocks meet, the largest (atomic max; prof
    zeroed first)."""
    g, i = wp.tid()
    if i >= solid_count[g]:
        return
    s = solid_list[solid_first[g] + i]
    b = solid_block[s]
    o = line_pos[g]
    c = bx[b]
    off = c - o
    off[up] = 0.0
    r = solid_radius[s] + H
    if wp.length_sq(off) >= r * r:
        return  # the line passes farther than H from the block's bounding sphere
    z0 = line_z0[g]
    dz = line_dz[g]
    k0 = wp.max(int(wp.ceil((c[up] - r - z0) / dz)), 0)
    k1 = wp.min(int(wp.floor((c[up] + r - z0) / dz)), line_n[g] - 1)
    fs = face_first[s]
    for k in range(k0, k1 + 1):
        x = wp.vec3(o[0], o[1], o[2])
        x[up] = z0 + float(k) * dz
        dist = float(-1.0e30)
        for f in range(face_count[s]):
            dist = wp.max(dist, wp.dot(plane_n[fs + f], x) - plane_d[fs + f])
        if dist < 0.0:
            wp.atomic_max(prof, g, k, 1.0)  # inside: solid
        elif dist < H:
            wp.atomic_max(prof, g, k, half_space_fraction(dist, table, H))


@wp.func
def water_fraction(fluid: wp.array2d(dtype=float), solid: wp.array2d(dtype=float), moving: wp.array2d(dtype=float),
                   has_moving: int, g: int, k: int) -> float:
    """phi_f / (1 - phi_s - phi_m): the water's share of the space that is not wall or moving block (phi_f where
    there is neither; next to a wall or a block face, which takes part of the kernel support, bulk water still
    reads 1); 0 inside a wall or a block."""
    open_ = 1.0 - solid[g, k]
    if has_moving != 0:
        open_ -= moving[g, k]
    if open_ < SOLID_CUTOFF:
        return 0.0
    return fluid[g, k] / open_


@wp.func
def column_top(fluid: wp.array2d(dtype=float), solid: wp.array2d(dtype=float), moving: wp.array2d(dtype=float),
               has_moving: int, g: int, n: int, z0: float, dz: float, reach: int) -> float:
    """The top of the continuous water column on line g, sampled at z0 + k dz for k < n (gauge_level)."""
    level = float(wp.nan)
    bed = int(-1)
    wet = int(0)
    top = int(-1)  # the sample of the last crossing (-1: none yet)
    prev = float(0.0)
    for k in range(n):
        f = water_fraction(fluid, solid, moving, has_moving, g, k)
        open_ = 1.0 - solid[g, k]
        if has_moving != 0:
            open_ -= moving[g, k]
        inside = open_ < SOLID_CUTOFF
        if inside:
            bed = -1  # inside a wall: the bed is above
            wet = 0
            top = -1  # a wall on top of the column: it may go on above the wall
        elif bed < 0:
            bed = k
        if top >= 0 and k - top > reach:
            return level  # air above the column and no wall: done
        if not inside:
            if wet == 0:
                if f >= 0.5:
                    if bed >= n or k - bed > reach:
                        return level  # water resting on nothing (or overhead, with air between)
                    wet = 1
                    top = -1
            elif f < 0.5:
                level = z0 + (float(k - 1) + (prev - 0.5) / (prev - f)) * dz
                wet = 0
                top = k
                bed = 2 * n  # no new bed in the air: only above a wall
        prev = f
    if wet == 1:
        level = z0 + float(n - 1) * dz
    return level


@wp.kernel
def gauge_level(
    fluid: wp.array2d(dtype=float),
    solid: wp.array2d(dtype=float),
    moving: wp.array2d(dtype=float),
    has_moving: int,
    is_height: wp.array(dtype=int),
    z0: float,
    dz: float,
    reach: int,
    out: wp.array(dtype=float),
):
    """The top of the continuous water column of each height gauge (one thread per gauge). Going up the
    samples from the line's lower end: the bed is the lowest sample not inside a wall; the column starts
    where the water fraction first reaches 0.5, which must be within `reach` samples of the bed (else the
    water on the line rests on nothing: a jet or spray over a dry bed); the reading is the first crossing
    back below 0.5 above it, linearly interpolated between the two samples; water overhead beyond it does
    not count. A wall within `reach` above that crossing (water under a beach, a shelf) starts a new bed:
    the column may go on above it. NaN when dry; the line's upper end when the fraction never drops
    below 0.5 again."""
    g = wp.tid()
    if is_height[g] == 0:
        return
    out[g] = column_top(fluid, solid, moving, has_moving, g, fluid.shape[1], z0, dz, reach)


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
def gauge_pressure_wall_sums(
    x: wp.array(dtype=wp.vec3),
    wall_pressure: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    gauge_pos: wp.array(dtype=wp.vec3),
    p: SPHParams,
    sums: wp.array2d(dtype=float),
):
    """Adami walls (kernels/sph/fluid.py wall_pressure_adami): the wall particles' share of the pressure gauges'
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


@wp.kernel
def surface_pressure(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    wall_pressure: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    adami: int,
    n_all: int,
    points: wp.array(dtype=wp.vec3),
    p: SPHParams,
    wet_min: float,
    out: wp.array(dtype=float),
):
    """Force gauges (rockwave/sim/readers.py ForceGauges): the pressure at points on a block's faces, the
    Shepard interpolation over the fluid and, with Adami walls, the wall particles (whose extrapolated pressure
    continues the fluid's across the face, so the reading is not that of a point half a support inside the
    water), found through a hash grid of all particles. A point whose fluid volume fraction sum V_j W is below
    wet_min (a face pressed on another block or the floor, or above the water) reads 0."""
    k = wp.tid()
    xp = points[k]
    sf = float(0.0)
    vf = float(0.0)
    sw = float(0.0)
    vw = float(0.0)
    q = wp.hash_grid_query(grid, xp, p.H)
    j = int(0)
    while wp.hash_grid_query_next(q, j):
        if j >= n_all:
            continue
        r2 = wp.length_sq(xp - x[j])
        if r2 < p.H * p.H:
            if j < p.n_fluid:
                w = particle_mass[j] / rho[j] * kernel_w(r2, p)
                sf += w * pressure[j]
                vf += w
            elif adami != 0:
                w = particle_mass[j] / p.rest_density * kernel_w(r2, p)
                sw += w * wall_pressure[j - p.n_fluid]
                vw += w
    if vf < wet_min:
        out[k] = 0.0
    else:
        out[k] = (sf + sw) / (vf + vw)


@wp.kernel
def surface_pressure_sums(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    wall: int,
    n: int,
    points: wp.array(dtype=wp.vec3),
    p: SPHParams,
    sums: wp.array2d(dtype=float),
):
    """surface_pressure's four sums over one chunk of particles (rockwave/sim/readers.py HostWater), added to
    sums[k]: fluid (wall = 0) sums[k, 0] += V_j p_j W, sums[k, 1] += V_j W, V_j = m_j / rho_j; Adami walls
    (wall = 1, ``pressure`` their extrapolated pressure) sums[k, 2] += V_b p_b W, sums[k, 3] += V_b W,
    V_b = m_b / rho0; over the chunk's n particles within H of point k (its hash grid)."""
    k = wp.tid()
    xp = points[k]
    s = float(0.0)
    v = float(0.0)
    q = wp.hash_grid_query(grid, xp, p.H)
    j = int(0)
    while wp.hash_grid_query_next(q, j):
        if j >= n:
            continue
        r2 = wp.length_sq(xp - x[j])
        if r2 < p.H * p.H:
            if wall == 0:
                w = particle_mass[j] / rho[j] * kernel_w(r2, p)
            else:
                w = particle_mass[j] / p.rest_density * kernel_w(r2, p)
            s += w * pressure[j]
            v += w
    sums[k, 2 * wall] = sums[k, 2 * wall] + s
    sums[k, 2 * wall + 1] = sums[k, 2 * wall + 1] + v


@wp.kernel
def surface_pressure_finish(sums: wp.array2d(dtype=float), wet_min: float, out: wp.array(dtype=float)):
    """surface_pressure's reading from the summed chunks (surface_pressure_sums): 0 where the fluid's volume
    fraction is below wet_min, else (s_f + s_w) / (v_f + v_w)."""
    k = wp.tid()
    if sums[k, 1] < wet_min:
        out[k] = 0.0
    else:
        out[k] = (sums[k, 0] + sums[k, 2]) / (sums[k, 1] + sums[k, 3])


# ---------------------------------------------------------------------------------------------------
# Hazard summary (rockwave/output/hazard.py): running extremes reduced on the device, one host read at the end.
# ---------------------------------------------------------------------------------------------------

# columns of a wave gauge's row in the hazard statistics
HZ_MAX = wp.constant(0)  # highest eta
HZ_T_MAX = wp.constant(1)
HZ_MIN = wp.constant(2)  # lowest eta
HZ_T_MIN = wp.constant(3)
HZ_ARRIVAL = wp.constant(4)  # first time |eta| > threshold (NaN: not yet)
HZ_PREV_ETA = wp.constant(5)  # the previous sample (NaN: dry)
HZ_PREV_T = wp.constant(6)
HZ_COLUMNS = 7


@wp.func
def wave_sample(g: int, z: float, still: float, thr: float, t: float, stats: wp.array2d(dtype=float)):
    """One sample of wave gauge g (its reading z, NaN when dry) into its row of stats (hazard_wave_update)."""
    if wp.isnan(z):
        stats[g, HZ_PREV_ETA] = wp.nan
        return
    eta = z - still
    if eta > stats[g, HZ_MAX]:
        stats[g, HZ_MAX] = eta
        stats[g, HZ_T_MAX] = t
    if eta < stats[g, HZ_MIN]:
        stats[g, HZ_MIN] = eta
        stats[g, HZ_T_MIN] = t
    a = wp.abs(eta)
    if wp.isnan(stats[g, HZ_ARRIVAL]) and a > thr:
        t_arr = t
        a0 = wp.abs(stats[g, HZ_PREV_ETA])
        if not wp.isnan(a0) and a0 <= thr:
            t_arr = stats[g, HZ_PREV_T] + (thr - a0) / (a - a0) * (t - stats[g, HZ_PREV_T])
        stats[g, HZ_ARRIVAL] = t_arr
    stats[g, HZ_PREV_ETA] = eta
    stats[g, HZ_PREV_T] = t


@wp.kernel
def hazard_wave_update(
    level: wp.array(dtype=float),
    still: wp.array(dtype=float),
    threshold: wp.array(dtype=float),
    t: float,
    stats: wp.array2d(dtype=float),
):
    """One sample of each wave gauge (one thread per gauge; level: its height-gauge reading, NaN when dry).
    eta = level - still. Keeps the highest crest max(eta) and the deepest trough min(eta) with their times,
    and the first arrival: the first time |eta| exceeds the gauge's threshold, linearly interpolated between
    the previous sample and this one (|eta| rising through the threshold). A dry sample (NaN) changes nothing
    but the previous sample."""
    g = wp.tid()
    wave_sample(g, level[g], still[g], threshold[g], t, stats)


@wp.func
def column_sample(c: int, z: float, t: float, stats: wp.array2d(dtype=float)):
    """One sample of run-up column c (hazard_column_update)."""
    if not wp.isnan(z) and z > stats[c, 0]:
        stats[c, 0] = z
        stats[c, 1] = t


@wp.kernel
def hazard_column_update(level: wp.array(dtype=float), offset: int, t: float, stats: wp.array2d(dtype=float)):
    """Run-up columns (one thread per column; level[offset + c]: the top of the continuous water column on the
    column's vertical line, NaN when dry): the highest top so far (stats[c, 0], -inf until wet) and its time."""
    c = wp.tid()
    column_sample(c, level[offset + c], t, stats)


@wp.func
def speed_sample(i: int, s: float, t: float, stats: wp.array2d(dtype=float)):
    """One reading s of watched block i's speed (hazard_block_speed)."""
    if s > stats[i, 0]:
        stats[i, 0] = s
        stats[i, 1] = t


@wp.kernel
def hazard_block_speed(v: wp.array(dtype=wp.vec3), index: wp.array(dtype=int), t: float, stats: wp.array2d(dtype=float)):
    """Peak speed |v| of each watched block (one thread per slide; index: its block) and its time."""
    i = wp.tid()
    speed_sample(i, wp.length(v[index[i]]), t, stats)


@wp.kernel
def hazard_slide_record(
    x: wp.array(dtype=wp.vec3),
    x_lo: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    index: wp.array(dtype=int),
    row: int,
    t: float,
    motion: wp.array2d(dtype=float),
):
    """One sample of each watched block's motion (one thread per slide; index: its block): row row * n + i of
    motion holds t, the centroid x + x_lo [m] and the velocity v [m/s] (n = number of slides)."""
    i = wp.tid()
    r = row * index.shape[0] + i
    b = index[i]
    c = x[b] + x_lo[b]
    motion[r, 0] = t
    for k in range(3):
        motion[r, 1 + k] = c[k]
        motion[r, 4 + k] = v[b][k]


@wp.kernel
def hazard_side_volume(
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    point: wp.array(dtype=wp.vec3),
    normal: wp.array(dtype=wp.vec3),
    vol: wp.array(dtype=float),
):
    """The water volume on the positive side of each crossing line (plane through point, horizontal normal):
    vol[l] += m_j / rho_j for (x_j - point_l).n_l > 0 (launched over fluid particles x lines)."""
    j, l = wp.tid()
    if wp.dot(x[j] - point[l], normal[l]) > 0.0:
        wp.atomic_add(vol, l, particle_mass[j] / rho[j])


@wp.func
def crossing_sample(l: int, vol: float, t: float, stats: wp.array2d(dtype=float)):
    """One sample of crossing line l's volume (hazard_crossing_update)."""
    if wp.isnan(stats[l, 0]):
        stats[l, 0] = vol
    dv = vol - stats[l, 0]
    stats[l, 1] = dv
    if dv > stats[l, 2]:
        stats[l, 2] = dv
        stats[l, 3] = t


@wp.kernel
def hazard_crossing_update(vol: wp.array(dtype=float), t: float, stats: wp.array2d(dtype=float)):
    """Crossing lines (one thread per line): stats[l, 0] the volume at the first sample (V0), then the net
    volume moved across the line V - V0 now (col 1), its largest value (col 2) and that time (col 3)."""
    l = wp.tid()
    crossing_sample(l, vol[l], t, stats)
