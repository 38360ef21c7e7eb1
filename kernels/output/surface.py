"""Warp kernels of rockwave/output/surface.py (SurfaceExtractor): a smooth scalar field of the fluid on a
regular grid, gathered at each grid node from the particles of the cells around it, and marching
squares for 2D contours (3D isosurfaces use Warp's own marching cubes).

Fields (``kind``), both normalised so that the field is ~1 inside bulk water and ~0.5 at the
free surface of a particle lattice:
- 0, SPH colour field: c(x) = sum_j (m_j / rho_j) W(|x - x_j|, R), Monaghan's cubic spline with
  compact support R (smoothing length R/2; kernels/sph/fluid.py cubic_w, the fluid's own);
- 1, metaball field (Ghost SPH report): f(x) = sum_j s^d / V_R (1 - (d/R)^2)^2 for d < R, where
  s^d / V_R makes the sum over a filled lattice of spacing s equal 1 (V_R = 32 pi R^3 / 105 in
  3D, pi R^2 / 3 in 2D).

The particles are sorted by cell of a dense grid over the field's box (``ParticleCells``: cells of
width R/2, keys x-fastest, so the cells of one (y, z) row form one run of sorted slots), and the field is
a gather: a thread owns a run of nodes along x, visits the rows of cells within R of them and, in each,
only the slots of the x-cells within sqrt(R^2 - d_yz^2) (d_yz: the distance to the row); each particle
there adds its term to the run's nodes within R of it. No atomics, and a node sums its particles in a
fixed order (slot order), so the field is the same from run to run on any device. (The former
wp.HashGrid query per node, 27 cells of width R, wrapped around its 64^3 buckets along a long flume and
visited several times the particles in reach: ~42 s for a frame of scenes/wave_maker.toml on the CPU.)
"""

import warp as wp

from rockwave.kernels.sph.fluid import cubic_w, lower_bound

wp.set_module_options({"enable_backward": False})  # forward kernels only: nothing here is differentiated


@wp.struct
class ParticleCells:
    lo: wp.vec3  # lower corner of the grid (the field grid's)
    inv_c: float  # 1 / cell width
    c: float  # cell width
    nx: int
    ny: int
    nz: int
    first: wp.array(dtype=int)  # first[k] = first sorted slot of cell k (nx * ny * nz + 1 entries)
    x_sorted: wp.array(dtype=wp.vec3)  # positions in slot order
    w_sorted: wp.array(dtype=float)  # m / rho in slot order


@wp.func
def clamped_cell(a: float, lo: float, inv_c: float, n: int) -> int:
    """Cell of coordinate a along one axis, clamped: a particle outside the grid joins its edge cell. The
    nodes lie inside the grid, so such a particle is farther from any node than its edge cell is, and the
    gather's distance bounds (row_gap) still hold for it."""
    return wp.clamp(int(wp.floor((a - lo) * inv_c)), 0, n - 1)


@wp.kernel
def particle_cell_keys(g: ParticleCells, x: wp.array(dtype=wp.vec3), keys: wp.array(dtype=int),
                       values: wp.array(dtype=int)):
    """Cell key (x-fastest) and index of every particle, for the sort."""
    i = wp.tid()
    xi = x[i]
    cx = clamped_cell(xi[0], g.lo[0], g.inv_c, g.nx)
    cy = clamped_cell(xi[1], g.lo[1], g.inv_c, g.ny)
    cz = clamped_cell(xi[2], g.lo[2], g.inv_c, g.nz)
    keys[i] = cx + g.nx * (cy + g.ny * cz)
    values[i] = i


@wp.kernel
def cell_starts(keys: wp.array(dtype=int), n: int, first: wp.array(dtype=int)):
    """first[c] = lower bound of cell c in the n sorted keys (a binary search per cell and one past the last)."""
    c = wp.tid()
    first[c] = lower_bound(keys, n, c)


@wp.kernel
def gather_sorted_particles(order: wp.array(dtype=int), x: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float),
                            mass: float, x_sorted: wp.array(dtype=wp.vec3), w_sorted: wp.array(dtype=float)):
    k = wp.tid()
    i = order[k]
    x_sorted[k] = x[i]
    w_sorted[k] = mass / rho[i]


@wp.func
def row_gap(a: float, c: int, lo: float, width: float) -> float:
    """Distance along one axis from coordinate a to the cells of index c."""
    c0 = lo + float(c) * width
    return wp.max(wp.max(c0 - a, a - (c0 + width)), 0.0)


@wp.kernel
def fluid_field(
    g: ParticleCells,
    lower: wp.vec3,
    cell: float,
    R: float,
    kind: int,
    dim: int,
    metaball_norm: float,
    run: int,
    field: wp.array3d(dtype=float),
):
    """The field at the grid nodes lower + (i, j, k) cell: the sum over the particles within R of each node,
    gathered from the sorted cells around it. A thread owns a run of ``run`` nodes along x (i = run * t ..
    run * t + run - 1; j, k fixed), which share the rows of cells they visit: the row bookkeeping (~25 rows
    of cells in 3D) is done once per run instead of once per node. Each particle of a row adds its term to
    the run's nodes within R of it, in slot order, so a node's sum runs over its particles in the same
    order as a query of its own would. ``field`` comes in zeroed."""
    t, j, k = wp.tid()
    nx = field.shape[0]
    i0 = t * run
    i1 = wp.min(i0 + run, nx) - 1  # last node of the run
    p0 = lower + wp.vec3(float(i0), float(j), float(k)) * cell
    x_last = lower[0] + float(i1) * cell
    R2 = R * R
    y0 = clamped_cell(p0[1] - R, g.lo[1], g.inv_c, g.ny)
    y1 = clamped_cell(p0[1] + R, g.lo[1], g.inv_c, g.ny)
    z0 = clamped_cell(p0[2] - R, g.lo[2], g.inv_c, g.nz)
    z1 = clamped_cell(p0[2] + R, g.lo[2], g.inv_c, g.nz)
    for cz in range(z0, z1 + 1):
        gz = row_gap(p0[2], cz, g.lo[2], g.c)
        for cy in range(y0, y1 + 1):
            gy = row_gap(p0[1], cy, g.lo[1], g.c)
            gap2 = gy * gy + gz * gz
            if gap2 < R2:
                w = wp.sqrt(R2 - gap2)
                x0 = clamped_cell(p0[0] - w, g.lo[0], g.inv_c, g.nx)
                x1 = clamped_cell(x_last + w, g.lo[0], g.inv_c, g.nx)
                base = g.nx * (cy + g.ny * cz)
                for slot in range(g.first[base + x0], g.first[base + x1 + 1]):
                    xs = g.x_sorted[slot]
                    ey = xs[1] - p0[1]
                    ez = xs[2] - p0[2]
                    e2 = ey * ey + ez * ez
                    if e2 < R2:
                        # the run's nodes within R of the particle (one more each side against rounding;
                        # the test d < R below decides)
                        wx = wp.sqrt(R2 - e2)
                        n0 = wp.max(int(wp.floor((xs[0] - wx - lower[0]) / cell)), i0)
                        n1 = wp.min(int(wp.ceil((xs[0] + wx - lower[0]) / cell)), i1)
                        for i in range(n0, n1 + 1):
                            p = lower + wp.vec3(float(i), float(j), float(k)) * cell
                            d = wp.length(xs - p)
                            if d < R:
                                if kind == 0:
                                    field[i, j, k] = field[i, j, k] + g.w_sorted[slot] * cubic_w(d, R, dim)
                                else:
                                    u = 1.0 - (d / R) * (d / R)
                                    field[i, j, k] = field[i, j, k] + metaball_norm * u * u


@wp.func
def _edge_point(fa: float, fb: float, pa: wp.vec3, pb: wp.vec3, iso: float) -> wp.vec3:
    t = float(0.5)
    den = fb - fa
    if wp.abs(den) > 1.0e-12:
        t = wp.clamp((iso - fa) / den, 0.0, 1.0)
    return pa + (pb - pa) * t


@wp.kernel
def marching_squares(
    field: wp.array3d(dtype=float),
    iso: float,
    lower: wp.vec3,
    cell: float,
    seg: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=int),
):
    """One cell (i, j) of the 2D field field[:, :, 0]: up to two segments, written to
    seg[4 c .. 4 c + 3] with count[c] in {0, 1, 2} (c = i * (ny - 1) + j). Segments run with the
    fluid (field > iso) on their left, so a closed contour around water is counter-clockwise."""
    i, j = wp.tid()
    ny = field.shape[1]
    c = i * (ny - 1) + j
    f0 = field[i, j, 0]  # corners counter-clockwise: (i, j), (i+1, j), (i+1, j+1), (i, j+1)
    f1 = field[i + 1, j, 0]
    f2 = field[i + 1, j + 1, 0]
    f3 = field[i, j + 1, 0]
    p0 = lower + wp.vec3(float(i), float(j), 0.0) * cell
    p1 = p0 + wp.vec3(cell, 0.0, 0.0)
    p2 = p0 + wp.vec3(cell, cell, 0.0)
    p3 = p0 + wp.vec3(0.0, cell, 0.0)
    code = int(0)
    if f0 > iso:
        code += 1
    if f1 > iso:
        code += 2
    if f2 > iso:
        code += 4
    if f3 > iso:
        code += 8
    # edge points: e0 bottom (0-1), e1 right (1-2), e2 top (2-3), e3 left (3-0)
    e0 = _edge_point(f0, f1, p0, p1, iso)
    e1 = _edge_point(f1, f2, p1, p2, iso)
    e2 = _edge_point(f2, f3, p2, p3, iso)
    e3 = _edge_point(f3, f0, p3, p0, iso)
    n = int(0)
    b = 4 * c
    if code == 1:
        seg[b] = e0
        seg[b + 1] = e3
        n = 1
    elif code == 2:
        seg[b] = e1
        seg[b + 1] = e0
        n = 1
    elif code == 3:
        seg[b] = e1
        seg[b + 1] = e3
        n = 1
    elif code == 4:
        seg[b] = e2
        seg[b + 1] = e1
        n = 1
    elif code == 6:
        seg[b] = e2
        seg[b + 1] = e0
        n = 1
    elif code == 7:
        seg[b] = e2
        seg[b + 1] = e3
        n = 1
    elif code == 8:
        seg[b] = e3
        seg[b + 1] = e2
        n = 1
    elif code == 9:
        seg[b] = e0
        seg[b + 1] = e2
        n = 1
    elif code == 11:
        seg[b] = e1
        seg[b + 1] = e2
        n = 1
    elif code == 12:
        seg[b] = e3
        seg[b + 1] = e1
        n = 1
    elif code == 13:
        seg[b] = e0
        seg[b + 1] = e1
        n = 1
    elif code == 14:
        seg[b] = e3
        seg[b + 1] = e0
        n = 1
    elif code == 5 or code == 10:
        centre = 0.25 * (f0 + f1 + f2 + f3)
        if code == 5:
            if centre > iso:  # corners 0 and 2 joined through the centre
                seg[b] = e2
                seg[b + 1] = e3
                seg[b + 2] = e0
                seg[b + 3] = e1
            else:
                seg[b] = e0
                seg[b + 1] = e3
                seg[b + 2] = e2
                seg[b + 3] = e1
        else:
            if centre > iso:  # corners 1 and 3 joined
                seg[b] = e3
                seg[b + 1] = e0
                seg[b + 2] = e1
                seg[b + 3] = e2
            else:
                seg[b] = e1
                seg[b + 1] = e0
                seg[b + 2] = e3
                seg[b + 3] = e2
        n = 2
    count[c] = n
