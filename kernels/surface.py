"""Warp kernels for render outputs: a smooth scalar field of the fluid on a regular grid, and
marching squares for 2D contours (3D isosurfaces use Warp's own marching cubes).

Fields (``kind``), both normalised so that the field is ~1 inside bulk water and ~0.5 at the
free surface of a particle lattice:
- 0, SPH colour field: c(x) = sum_j (m_j / rho_j) W(|x - x_j|, R), Monaghan's cubic spline with
  compact support R (smoothing length R/2);
- 1, metaball field (Ghost SPH report): f(x) = sum_j s^d / V_R (1 - (d/R)^2)^2 for d < R, where
  s^d / V_R makes the sum over a filled lattice of spacing s equal 1 (V_R = 32 pi R^3 / 105 in
  3D, pi R^2 / 3 in 2D).
"""

import warp as wp

PI = wp.constant(3.14159265358979)


@wp.func
def cubic_spline(r: float, R: float, dim: int) -> float:
    h = 0.5 * R
    q = r / h
    sigma = float(0.0)
    if dim == 3:
        sigma = 1.0 / (PI * h * h * h)
    else:
        sigma = 10.0 / (7.0 * PI * h * h)
    w = float(0.0)
    if q < 1.0:
        w = 1.0 - 1.5 * q * q + 0.75 * q * q * q
    elif q < 2.0:
        t = 2.0 - q
        w = 0.25 * t * t * t
    return sigma * w


@wp.kernel
def fluid_field(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    mass: float,
    lower: wp.vec3,
    cell: float,
    R: float,
    kind: int,
    dim: int,
    metaball_norm: float,
    field: wp.array3d(dtype=float),
):
    i, j, k = wp.tid()
    p = lower + wp.vec3(float(i), float(j), float(k)) * cell
    s = float(0.0)
    query = wp.hash_grid_query(grid, p, R)
    idx = int(0)
    while wp.hash_grid_query_next(query, idx):
        d = wp.length(x[idx] - p)
        if d < R:
            if kind == 0:
                s += mass / rho[idx] * cubic_spline(d, R, dim)
            else:
                u = 1.0 - (d / R) * (d / R)
                s += metaball_norm * u * u
    field[i, j, k] = s


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
