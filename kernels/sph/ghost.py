"""Ghost SPH kernels (Warp; same code on CPU and CUDA), launched by rockwave/sph/ghost.py (GhostFluidSolver).

Schechter & Bridson, "Ghost SPH for animating water", ACM TOG 31(4), 2012: each step, free-surface
particles are found, and "ghost" air particles are seeded around them by Poisson-disk sampling out
to one kernel radius. Ghosts carry the liquid particle mass, the velocity of the nearest liquid
particle and the rest density (so p = 0). They fill the kernel support of surface particles, which
removes the density deficiency of SPH at a free surface.

Array layout used here (the "extended" arrays of :class:`rockwave.sph.ghost.GhostFluidSolver`):
``[0, n_fluid)`` fluid, ``[n_fluid, n_static)`` static boundary particles, ``[n_static, n_static +
n_ghost)`` ghosts. The SPH kernels of ``sph.py`` treat every index >= n_fluid as a particle without
pressure of its own (Akinci's boundary term ``-m_j p_i/rho_i^2 grad W_ij``), which is exactly the
ghost rule p_ghost = 0; they are excluded from viscosity and XSPH there.

Sampling, tile sampler (the default; ``tile_ghosts``): the candidates are the points of a periodic
Poisson-disk tile (Bridson 2007, generated once on the host) laid over the background grid below, at
most one per cell. The surface particles list the cells of their layer that hold a tile point
(``mark_active_cells`` with the tile, visiting only those cells of each row), and one launch keeps the
points that pass the liquid rules: they are r apart by construction, so there are no phases.

Sampling, darts (parallel dart throwing, after Bridson 2007's rejection rule): a background grid of cell
size r/sqrt(d) holds at most one ghost per cell. Cells near a surface particle are marked active and
appended to a compact list per phase (3^d phases: cell index mod 3 along each axis; two cells of one
phase are at least two cells apart, i.e. farther than r, so all cells of a phase throw darts at the
same time without conflicts). Dart launches run over these lists only, and per-cell stamps replace
clearing the dense grid: the work scales with the surface, not with the domain. A dart is accepted when it lies within ``layer`` of a liquid particle and no
closer than r to any liquid, boundary or ghost particle.

Cells where no dart can pass are skipped without a hash query wherever that is exact: cells wholly
within r_liquid of a liquid particle are closed by a scatter over the liquid before the listing
(about 60% of the active cells inside the liquid in 3D, 80% in 2D), cells wholly within r_liquid of
a wall particle are never listed, a new ghost closes the neighbouring cells wholly within r of it,
and a cell tests its darts against the ghosts around it before its query (most cells outside the
liquid are within r of a ghost by then). The ghosts come out bit for bit as without these skips
(tests/test_ghost.py::test_cell_skips_place_the_same_ghosts).

Two forms of the dart throwing with the same accept decisions: ``throw_darts`` (a thread per cell
does all of a cell's tests inside the phase launch; the CPU path, where the skips save work) and
the parallel darts (``dart_screen``, ``dart_conflicts``, ``place_darts``, ``ghost_nearest_liquid``;
the GPU path), where no phase thread runs a query: a GPU phase launch lasts as long as its slowest
thread (tests/test_ghost.py::test_parallel_darts_place_the_same_ghosts).
"""

import warp as wp

from rockwave.kernels.sph.fluid import SPHParams, kernel_grad, kernel_w, store_density

wp.set_module_options({"enable_backward": False})  # forward kernels only: nothing here is differentiated


@wp.struct
class GhostGrid:
    """Dense background grid for the sampling (cells of size r/sqrt(dim))."""

    lo: wp.vec3  # lower corner [m]
    cell: float  # cell width [m]
    nx: int
    ny: int
    nz: int  # 1 in 2D
    dim: int
    r: float  # Poisson-disk radius between ghosts [m]
    r_liquid: float  # no ghost closer than this to a liquid or boundary particle [m]
    layer: float  # ghosts lie within this distance of a liquid particle [m]
    liquid_volume: float  # m / rho0 of a liquid particle [m^dim]
    colour_max: float  # ghosts only where the liquid colour field sum_j V_j W is below this (outside the liquid)


@wp.func
def cell_coord(g: GhostGrid, x: wp.vec3) -> wp.vec3i:
    c = (x - g.lo) / g.cell
    k = int(0)
    if g.dim == 3:
        k = int(wp.floor(c[2]))
    return wp.vec3i(int(wp.floor(c[0])), int(wp.floor(c[1])), k)


@wp.func
def cell_index(g: GhostGrid, i: int, j: int, k: int) -> int:
    return (k * g.ny + j) * g.nx + i


@wp.func
def position_divergence_term(rij: wp.vec3, r: float, j: int, rho: wp.array(dtype=float),
                             particle_mass: wp.array(dtype=float), p: SPHParams):
    """One neighbour's term of div x_i = sum_j V_j (x_j - x_i) . grad_i W_ij over liquid and boundary
    neighbours (Lee et al. 2008; Schechter & Bridson 2012, sec. 4), V_j = m_j/rho_j (rho0 for boundary
    particles); rij = x_i - x_j, r = |rij| < H. The sum equals the dimension inside the liquid (the
    kernel gradient is lattice-calibrated) and drops at a free surface."""
    rj = p.rest_density
    if j < p.n_fluid:
        rj = rho[j]
    return -particle_mass[j] / rj * wp.dot(rij, kernel_grad(rij, r, p))


@wp.func
def phase_of(i: int, j: int, k: int) -> int:
    return (i % 3) + 3 * (j % 3) + 9 * (k % 3)


@wp.func
def cell_centre(g: GhostGrid, i: int, j: int, k: int) -> wp.vec3:
    half = 0.5 * g.cell
    c = g.lo + wp.vec3(float(i) * g.cell + half, float(j) * g.cell + half, float(k) * g.cell + half)
    if g.dim == 2:
        c = wp.vec3(c[0], c[1], 0.0)
    return c


@wp.func
def cell_ijk(g: GhostGrid, c: int) -> wp.vec3i:
    """Cell coordinates of the flat cell index c."""
    return wp.vec3i(c % g.nx, (c // g.nx) % g.ny, c // (g.nx * g.ny))


@wp.func
def cell_corner(g: GhostGrid, i: int, j: int, k: int) -> wp.vec3:
    """Lower corner of cell (i, j, k): a dart of the cell is corner + cell * (u, u, u), u uniform in [0, 1)."""
    return g.lo + wp.vec3(float(i) * g.cell, float(j) * g.cell, float(k) * g.cell)


@wp.func
def close_neighbour_cells(g: GhostGrid, c: int, ijk: wp.vec3i, y: wp.vec3, stamp: int, ghost_stamp: wp.array(dtype=int)):
    """A new ghost at y in cell c closes (ghost_stamp = -stamp) the neighbouring cells wholly within r of
    it: it rejects all their darts. They are of other phases, so no other thread of the phase launch
    writes or decides them."""
    half_diag = 0.5 * g.cell * wp.sqrt(float(g.dim))
    eps = 1.0e-4 * g.cell
    for k in range(wp.max(ijk[2] - 1, 0), wp.min(ijk[2] + 1, g.nz - 1) + 1):
        for jj in range(wp.max(ijk[1] - 1, 0), wp.min(ijk[1] + 1, g.ny - 1) + 1):
            for ii in range(wp.max(ijk[0] - 1, 0), wp.min(ijk[0] + 1, g.nx - 1) + 1):
                n = cell_index(g, ii, jj, k)
                if n != c and ghost_stamp[n] != stamp:
                    if wp.length(cell_centre(g, ii, jj, k) - y) + half_diag + eps < g.r:
                        ghost_stamp[n] = -stamp


@wp.kernel
def close_covered_cells(
    x: wp.array(dtype=wp.vec3),
    g: GhostGrid,
    value: int,
    cell_state: wp.array(dtype=int),
):
    """Set ``cell_state[c] = value`` for every background cell wholly within r_liquid of particle
    tid: every dart there is rejected by this particle. The same float test as the "covered"
    classification of ``throw_darts`` (``|c - x| + half_diag < r_liquid``), so closing these cells
    before the darts (without a query per cell) changes no decision. Per step over the liquid
    (``ghost_stamp``, value -stamp); once over the static boundary particles (``wall_closed``, 1)."""
    i = wp.tid()
    xi = x[i]
    half_diag = 0.5 * g.cell * wp.sqrt(float(g.dim))
    reach = g.r_liquid - half_diag
    if reach <= 0.0:
        return
    lo = cell_coord(g, xi - wp.vec3(reach))
    hi = cell_coord(g, xi + wp.vec3(reach))
    if g.dim == 2:
        lo = wp.vec3i(lo[0], lo[1], 0)
        hi = wp.vec3i(hi[0], hi[1], 0)
    for k in range(wp.max(lo[2], 0), wp.min(hi[2], g.nz - 1) + 1):
        for jj in range(wp.max(lo[1], 0), wp.min(hi[1], g.ny - 1) + 1):
            for ii in range(wp.max(lo[0], 0), wp.min(hi[0], g.nx - 1) + 1):
                rc = cell_centre(g, ii, jj, k) - xi
                if wp.length(rc) + half_diag < g.r_liquid:
                    cell_state[cell_index(g, ii, jj, k)] = value


@wp.func
def tile_index(i: int, j: int, k: int, tile_k: int) -> int:
    """Cell (i, j, k) of the background grid -> its cell in the periodic tile of tile_k^d cells."""
    return (i % tile_k) + tile_k * ((j % tile_k) + tile_k * (k % tile_k))


@wp.func
def mark_slice(
    x: wp.array(dtype=wp.vec3),
    surface: wp.array(dtype=int),
    g: GhostGrid,
    stamp: int,
    cell_mark: wp.array(dtype=int),
    ghost_stamp: wp.array(dtype=int),
    wall_closed: wp.array(dtype=int),
    phase_count: wp.array(dtype=int),
    phase_list: wp.array(dtype=int),
    phase_cap: int,
    i: int,
    s: int,
):
    """Mark the background cells that meet the disc/ball of radius ``layer`` around each surface
    particle (the dart tests decide the rest) and append each newly marked cell once to the list of
    its phase (``phase_list[ph * phase_cap + slot]``, ``phase_count[ph]`` slots). ``cell_mark`` holds
    the stamp of the sampling that last marked a cell, so the dense grid is never cleared. Cells
    already closed (``ghost_stamp == -stamp``: wholly within r_liquid of a liquid particle, or a
    kept ghost's cell) and cells wholly within r_liquid of a wall particle (``wall_closed``) are
    not listed: no dart there can pass. Particle i, the s-th slice of its box of cells (along z in 3D, y
    in 2D)."""
    if surface[i] == 0:
        return
    xi = x[i]
    reach = g.layer
    lo = cell_coord(g, xi - wp.vec3(reach))
    hi = cell_coord(g, xi + wp.vec3(reach))
    if g.dim == 2:
        if lo[1] + s > hi[1]:
            return
        lo = wp.vec3i(lo[0], lo[1] + s, 0)
        hi = wp.vec3i(hi[0], lo[1], 0)
    else:
        if lo[2] + s > hi[2]:
            return
        lo = wp.vec3i(lo[0], lo[1], lo[2] + s)
        hi = wp.vec3i(hi[0], hi[1], lo[2])
    half_diag = 0.5 * g.cell * wp.sqrt(float(g.dim))
    for k in range(wp.max(lo[2], 0), wp.min(hi[2], g.nz - 1) + 1):
        for jj in range(wp.max(lo[1], 0), wp.min(hi[1], g.ny - 1) + 1):
            for ii in range(wp.max(lo[0], 0), wp.min(hi[0], g.nx - 1) + 1):
                c = cell_centre(g, ii, jj, k)
                # skip cells wholly inside the disc of radius r_liquid around x_i (every dart there is
                # rejected) or wholly beyond the layer
                dist = wp.length(c - xi)
                if dist + half_diag < g.r_liquid or dist - half_diag > reach:
                    continue
                ci = cell_index(g, ii, jj, k)
                if ghost_stamp[ci] == -stamp or wall_closed[ci] != 0:
                    continue
                if wp.atomic_max(cell_mark, ci, stamp) < stamp:
                    ph = phase_of(ii, jj, k)
                    slot = wp.atomic_add(phase_count, ph, 1)
                    phase_list[ph * phase_cap + slot] = ci




@wp.func
def mark_tile_slice(
    x: wp.array(dtype=wp.vec3),
    g: GhostGrid,
    stamp: int,
    cell_mark: wp.array(dtype=int),
    ghost_stamp: wp.array(dtype=int),
    wall_closed: wp.array(dtype=int),
    phase_count: wp.array(dtype=int),
    phase_list: wp.array(dtype=int),
    phase_cap: int,
    tile: wp.array(dtype=wp.vec3),
    tile_k: int,
    row_first: wp.array(dtype=int),
    row_cells: wp.array(dtype=int),
    i: int,
    s: int,
):
    """mark_slice for the tile sampler: only the cells whose tile point lies within the layer of surface
    particle i and not within r_liquid of it are listed. Each row of the box along x visits only the
    cells of the row that hold a tile point (``row_cells[row_first[r]:row_first[r + 1]]``: their x
    index modulo tile_k, for row r = (j mod k) + k (k mod k)), not every cell."""
    xi = x[i]
    reach = g.layer
    lo = cell_coord(g, xi - wp.vec3(reach))
    hi = cell_coord(g, xi + wp.vec3(reach))
    if g.dim == 2:
        if lo[1] + s > hi[1]:
            return
        lo = wp.vec3i(lo[0], lo[1] + s, 0)
        hi = wp.vec3i(hi[0], lo[1], 0)
    else:
        if lo[2] + s > hi[2]:
            return
        lo = wp.vec3i(lo[0], lo[1], lo[2] + s)
        hi = wp.vec3i(hi[0], hi[1], lo[2])
    rl2 = g.r_liquid * g.r_liquid
    layer2 = reach * reach
    i0 = wp.max(lo[0], 0)
    i1 = wp.min(hi[0], g.nx - 1)
    if i0 > i1:
        return
    for k in range(wp.max(lo[2], 0), wp.min(hi[2], g.nz - 1) + 1):
        for jj in range(wp.max(lo[1], 0), wp.min(hi[1], g.ny - 1) + 1):
            row = (jj % tile_k) + tile_k * (k % tile_k)
            tile_row = tile_k * row  # tile index of the row's first cell
            cell_row = g.nx * (jj + g.ny * k)  # background index of the row's cell 0
            base = i0 - i0 % tile_k  # the period holding i0
            for m in range(row_first[row], row_first[row + 1]):
                o = row_cells[m]
                ii = base + o
                if ii < i0:
                    ii += tile_k
                off = tile[tile_row + o]
                while ii <= i1:
                    y = cell_corner(g, ii, jj, k) + g.cell * off  # (as tile_ghosts computes it)
                    if g.dim == 2:
                        y = wp.vec3(y[0], y[1], 0.0)
                    d2 = wp.length_sq(y - xi)
                    if d2 >= rl2 and d2 <= layer2:
                        ci = cell_row + ii
                        if ghost_stamp[ci] != -stamp and wall_closed[ci] == 0:
                            if wp.atomic_max(cell_mark, ci, stamp) < stamp:
                                ph = phase_of(ii, jj, k)
                                slot = wp.atomic_add(phase_count, ph, 1)
                                phase_list[ph * phase_cap + slot] = ci
                    ii += tile_k


@wp.kernel
def mark_active_cells(
    x: wp.array(dtype=wp.vec3),
    surface: wp.array(dtype=int),
    g: GhostGrid,
    stamp: int,
    cell_mark: wp.array(dtype=int),
    ghost_stamp: wp.array(dtype=int),
    wall_closed: wp.array(dtype=int),
    phase_count: wp.array(dtype=int),
    phase_list: wp.array(dtype=int),
    phase_cap: int,
    tile: wp.array(dtype=wp.vec3),
    tile_k: int,
    row_first: wp.array(dtype=int),
    row_cells: wp.array(dtype=int),
    n_slices: int,
    slice_step: int,
):
    """mark_slice for thread (i, s0): particle i and slices s0, s0 + slice_step, ... < n_slices of its box: a
    thread per slice on a GPU, a thread per particle on the CPU (fewer threads; on its one thread the list
    appends come in the same order)."""
    i, s0 = wp.tid()
    if surface[i] == 0:
        return
    s = s0
    while s < n_slices:
        if tile_k > 0:
            mark_tile_slice(x, g, stamp, cell_mark, ghost_stamp, wall_closed, phase_count, phase_list, phase_cap, tile,
                            tile_k, row_first, row_cells, i, s)
        else:
            mark_slice(x, surface, g, stamp, cell_mark, ghost_stamp, wall_closed, phase_count, phase_list, phase_cap,
                       i, s)
        s += slice_step


# Per-cell candidate lists of throw_darts (local vectors): the ghosts, and the liquid/boundary
# particles, near enough to the cell to reject one of its darts; on overflow the full tests run.
GHOST_CAP = 32
LIQUID_CAP = 48
ghost_list = wp.types.vector(length=GHOST_CAP, dtype=int)
liquid_list = wp.types.vector(length=LIQUID_CAP, dtype=int)


@wp.func
def near_new_ghost(
    y: wp.vec3,
    x_ghost: wp.array(dtype=wp.vec3),
    ghosts: ghost_list,
    n_gh: int,
    g: GhostGrid,
    ci: int,
    cj: int,
    k0: int,
    k1: int,
    stamp: int,
    ghost_stamp: wp.array(dtype=int),
    cell_ghost: wp.array(dtype=int),
) -> int:
    """1 if a listed ghost (up to GHOST_CAP), or beyond the cap any ghost of this sampling in the
    5^d block of cells around (ci, cj, k0..k1), lies closer than r to y."""
    r2 = g.r * g.r
    if n_gh <= GHOST_CAP:
        for m in range(n_gh):
            if wp.length_sq(x_ghost[ghosts[m]] - y) < r2:
                return 1
        return 0
    for k in range(k0, k1 + 1):
        for jj in range(wp.max(cj - 2, 0), wp.min(cj + 2, g.ny - 1) + 1):
            for ii in range(wp.max(ci - 2, 0), wp.min(ci + 2, g.nx - 1) + 1):
                n = cell_index(g, ii, jj, k)
                if ghost_stamp[n] == stamp:
                    if wp.length_sq(x_ghost[cell_ghost[n]] - y) < r2:
                        return 1
    return 0


@wp.kernel
def throw_darts(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    n_fluid: int,
    n_static: int,
    g: GhostGrid,
    p: SPHParams,
    seed: int,
    attempts: int,
    stamp: int,
    cell_class: wp.array(dtype=int),
    phase_count: wp.array(dtype=int),
    phase_list: wp.array(dtype=int),
    phase_cap: int,
    offset: int,
    cell_ghost: wp.array(dtype=int),
    ghost_stamp: wp.array(dtype=int),
    count: wp.array(dtype=int),
    capacity: int,
    keep: wp.array(dtype=int),
    n_old: int,
    shortcuts: int,
    x_ghost: wp.array(dtype=wp.vec3),
    v_ghost: wp.array(dtype=wp.vec3),
    ghost_of: wp.array(dtype=int),
):
    """Dart throwing over the active cells of phases ``offset + tid[0]`` only (thread (ph, t): the
    t-th listed cell of phase ph). On a GPU it is launched once per phase (dim (1, count)): cells of
    one phase are 3 apart along each axis, farther than r, so they never conflict. Warp's CPU backend
    runs a launch on one thread in index order, so there one launch covers all phases in turn
    (dim (n_phases, max count)), with the same result as phase-by-phase launches. Each thread tries up to ``attempts`` uniform darts in its cell and keeps
    the first that passes Bridson's (2007) rejection test against liquid, boundary and ghost
    particles. A cell's ghost is ``cell_ghost[c]`` when ``ghost_stamp[c] == stamp`` (no clearing).
    Accepted ghosts are appended at ``n_static + count`` (``x_ghost``/``v_ghost`` alias the
    extended x/v arrays).

    Order of the work (cheapest first): the thread lists the ghosts of this sampling in the 5^d
    block of cells within r + half diagonal of the cell centre (a dart lies within the half diagonal
    of the centre) and, without kept old ghosts, tests its darts against them first: when every dart
    falls within r of a ghost (most cells outside the liquid once their neighbours have ghosts), the
    cell is done for this round without a hash query. Otherwise one hash query gathers the liquid and
    boundary particles within r_liquid + half diagonal and the kept old ghosts within r + half
    diagonal; on the cell's first query of this sampling (``cell_class[c] != stamp``) it also
    classifies the cell (radius ``layer``) and closes it (``ghost_stamp = -stamp``) when no dart can
    pass. Each dart then tests the short lists (up to GHOST_CAP / LIQUID_CAP entries; beyond, the full
    block scan / hash query of a dart) and, if it passes, the nearest liquid particle within the
    layer and the liquid colour field (one query of radius ``layer``). The accept decisions are the
    same as testing every dart against every particle, and do not depend on which round classifies.
    A new ghost closes the neighbouring cells wholly within r of it. ``shortcuts`` 0: no test of the
    darts against the ghosts before the query and no closing of neighbours (reference for tests).
    Persistent ghosts: the ``n_old`` ghosts of the last step sit at ``n_static ..`` (in the hash grid),
    those with ``keep`` reject darts within r, and new ghosts are appended after them."""
    ph, t_cell = wp.tid()
    if t_cell >= phase_count[offset + ph]:
        return
    c = phase_list[(offset + ph) * phase_cap + t_cell]
    if ghost_stamp[c] == stamp or ghost_stamp[c] == -stamp:  # has a ghost / closed
        return
    ijk = cell_ijk(g, c)
    ci = ijk[0]
    cj = ijk[1]
    ck = ijk[2]
    half_diag = 0.5 * g.cell * wp.sqrt(float(g.dim))
    xc = cell_centre(g, ci, cj, ck)
    rl2 = g.r_liquid * g.r_liquid
    # a dart is within half_diag of xc: only particles within (test radius + half_diag) can reject it
    # (a small margin against rounding: an extra candidate never changes a decision)
    eps = 1.0e-4 * g.cell
    reach_l = g.r_liquid + half_diag + eps
    reach_g = g.r + half_diag + eps
    base = cell_corner(g, ci, cj, ck)
    # new ghosts of this sampling in the 5^d block of cells around (at most one per cell)
    ghosts = ghost_list()
    n_gh = int(0)
    k0 = ck
    k1 = ck
    if g.dim == 3:
        k0 = wp.max(ck - 2, 0)
        k1 = wp.min(ck + 2, g.nz - 1)
    for k in range(k0, k1 + 1):
        for jj in range(wp.max(cj - 2, 0), wp.min(cj + 2, g.ny - 1) + 1):
            for ii in range(wp.max(ci - 2, 0), wp.min(ci + 2, g.nx - 1) + 1):
                n = cell_index(g, ii, jj, k)
                if ghost_stamp[n] == stamp:
                    o = cell_ghost[n]
                    if wp.length(x_ghost[o] - xc) < reach_g:
                        if n_gh < GHOST_CAP:
                            ghosts[n_gh] = o
                        n_gh += 1
    if shortcuts != 0 and n_old == 0 and n_gh > 0:
        # darts against the new ghosts first (the same darts as below): none free -> no query
        rng0 = wp.rand_init(seed, c)
        free = int(0)
        for t in range(attempts):
            y0 = base + g.cell * wp.vec3(wp.randf(rng0), wp.randf(rng0), wp.randf(rng0))
            if g.dim == 2:
                y0 = wp.vec3(y0[0], y0[1], 0.0)
            if near_new_ghost(y0, x_ghost, ghosts, n_gh, g, ci, cj, k0, k1, stamp, ghost_stamp, cell_ghost) == 0:
                free = 1
                break
        if free == 0:
            return
    liquid = liquid_list()
    n_liq = int(0)
    classify = int(0)
    if cell_class[c] != stamp:
        classify = 1
    # the gather query: radius max(reach_l, reach_g), and the layer on the first query (classification)
    rq = wp.max(reach_l, reach_g)
    if classify != 0:
        rq = wp.max(rq, g.layer)
    col = float(0.0)
    grad = wp.vec3(0.0)
    covered = int(0)
    qc = wp.hash_grid_query(grid, xc, rq)
    jc = int(0)
    while wp.hash_grid_query_next(qc, jc):
        rc = xc - x[jc]
        if jc < n_static:
            dc = wp.length(rc)
            if classify != 0:
                # first visit: close cells where no dart can pass. Inside the liquid: the colour field at the
                # centre, less |grad colour| times the half diagonal (first order) and a 0.1 margin, still
                # above colour_max everywhere in the cell. Covered: the whole cell within r_liquid of one
                # liquid or boundary particle.
                if dc <= g.layer:
                    if dc + half_diag < g.r_liquid:
                        covered = 1
                    if jc < n_fluid and dc < p.H:
                        col += g.liquid_volume * kernel_w(dc * dc, p)
                        grad += g.liquid_volume * kernel_grad(rc, dc, p)
            if dc < reach_l:
                if n_liq < LIQUID_CAP:
                    liquid[n_liq] = jc
                n_liq += 1
        elif jc < n_static + n_old:
            if keep[jc - n_static] != 0:
                if wp.length(rc) < reach_g:
                    if n_gh < GHOST_CAP:
                        ghosts[n_gh] = jc
                    n_gh += 1
    if classify != 0:
        if covered != 0 or col - wp.length(grad) * half_diag - 0.1 > g.colour_max:
            ghost_stamp[c] = -stamp
            return
        cell_class[c] = stamp
    rng = wp.rand_init(seed, c)
    for t in range(attempts):
        y = base + g.cell * wp.vec3(wp.randf(rng), wp.randf(rng), wp.randf(rng))
        if g.dim == 2:
            y = wp.vec3(y[0], y[1], 0.0)
        # ghosts: none closer than r (kept old ghosts: listed, or in the hash query below beyond the cap)
        if near_new_ghost(y, x_ghost, ghosts, n_gh, g, ci, cj, k0, k1, stamp, ghost_stamp, cell_ghost) != 0:
            continue
        # liquid and boundary particles: none closer than r_liquid (and kept ghosts beyond the list)
        ok = int(1)
        j = int(0)
        if n_liq <= LIQUID_CAP and n_gh <= GHOST_CAP:
            for m in range(n_liq):
                if wp.length_sq(x[liquid[m]] - y) < rl2:
                    ok = 0
                    break
        else:
            q = wp.hash_grid_query(grid, y, g.r_liquid)
            while wp.hash_grid_query_next(q, j):
                if j < n_static:
                    if wp.length_sq(x[j] - y) < rl2:
                        ok = 0
                        break
                elif j < n_static + n_old:
                    if keep[j - n_static] != 0 and wp.length_sq(x[j] - y) < g.r * g.r:
                        ok = 0
                        break
        if ok == 0:
            continue
        # nearest liquid particle within the layer; outside the liquid only: a gap inside the liquid
        # wider than r_liquid must not get a ghost (a ghost there adds density, pushes the gap open
        # and seeds more ghosts: an air bubble that grows)
        best = float(1.0e30)
        nearest = int(-1)
        colour = float(0.0)
        q2 = wp.hash_grid_query(grid, y, g.layer)
        while wp.hash_grid_query_next(q2, j):
            if j < n_fluid:
                d2 = wp.length_sq(x[j] - y)
                colour += g.liquid_volume * kernel_w(d2, p)
                if d2 < best:
                    best = d2
                    nearest = j
        if nearest < 0 or best > g.layer * g.layer or colour > g.colour_max:
            continue
        slot = wp.atomic_add(count, 0, 1)
        if slot < capacity:
            o = n_static + slot
            x_ghost[o] = y
            v_ghost[o] = v[nearest]
            ghost_of[slot] = nearest
            cell_ghost[c] = o
            ghost_stamp[c] = stamp
            if shortcuts == 0:
                return
            close_neighbour_cells(g, c, ijk, y, stamp, ghost_stamp)
        return


# ---- Tile sampler (GhostFluidSolver sampler = "tile") ---------------------------------------------
# The candidates are the points of a periodic Poisson-disk tile laid over the background grid (at most
# one per cell: cells are r/sqrt(d) wide), generated once (rockwave/sph/ghost.py poisson_disk_tile). They are
# r apart by construction, so a step only keeps those that pass the liquid rules: one launch, no phases.


@wp.kernel
def tile_ghosts(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    n_fluid: int,
    n_static: int,
    g: GhostGrid,
    p: SPHParams,
    phase_count: wp.array(dtype=int),
    phase_list: wp.array(dtype=int),
    phase_cap: int,
    tile: wp.array(dtype=wp.vec3),
    tile_k: int,
    count: wp.array(dtype=int),
    capacity: int,
    stride: int,
    x_ghost: wp.array(dtype=wp.vec3),
    v_ghost: wp.array(dtype=wp.vec3),
    ghost_of: wp.array(dtype=int),
):
    """Thread (ph, t): the t-th, t + stride-th, ... listed cell of phase ph. The cell's tile point y becomes
    a ghost when no liquid or boundary particle lies within r_liquid of it, a liquid particle lies within
    the layer, and the liquid colour field sum_j V_j W(y - x_j) is at most colour_max (outside the liquid):
    the rules of the darts, tested with one hash query. Velocity and owner: the nearest liquid particle."""
    ph, t0 = wp.tid()
    t_cell = t0
    rl2 = g.r_liquid * g.r_liquid
    layer2 = g.layer * g.layer
    H2 = p.H * p.H
    radius = wp.max(g.r_liquid, wp.max(g.layer, p.H))
    while t_cell < phase_count[ph]:
        c = phase_list[ph * phase_cap + t_cell]
        t_cell += stride
        ijk = cell_ijk(g, c)
        off = tile[tile_index(ijk[0], ijk[1], ijk[2], tile_k)]
        if off[0] < 0.0:
            continue
        y = cell_corner(g, ijk[0], ijk[1], ijk[2]) + g.cell * off
        if g.dim == 2:
            y = wp.vec3(y[0], y[1], 0.0)
        ok = int(1)
        best = float(1.0e30)
        nearest = int(-1)
        colour = float(0.0)
        j = int(0)
        q = wp.hash_grid_query(grid, y, radius)
        while wp.hash_grid_query_next(q, j):
            if j < n_static:
                d2 = wp.length_sq(x[j] - y)
                if d2 < rl2:
                    ok = 0
                    break
                if j < n_fluid:
                    if d2 <= layer2 and d2 < best:
                        best = d2
                        nearest = j
                    if d2 < H2:
                        colour += g.liquid_volume * kernel_w(d2, p)
                        if colour > g.colour_max:
                            ok = 0
                            break
        if ok == 0 or nearest < 0:
            continue
        slot = wp.atomic_add(count, 0, 1)
        if slot < capacity:
            o = n_static + slot
            x_ghost[o] = y
            v_ghost[o] = v[nearest]
            ghost_of[slot] = nearest


# ---- Parallel dart throwing (the GPU path; GhostFluidSolver.parallel_darts) -----------------------
# The work that does not depend on the ghosts of this sampling is taken out of the dependent phase
# launches: one launch screens every dart of every active cell against the liquid, the walls, the
# kept old ghosts and the layer and colour rules (dart_screen, a thread per cell), and each of
# the 3^d phases is two short launches: the darts left against each new ghost around the cell (a
# thread per (cell, row of the 5^d block): dart_conflicts), then the first free dart placed (place_darts). The
# nearest liquid particle (the ghost's velocity) is found afterwards, a thread per new ghost
# (ghost_nearest_liquid). In throw_darts a phase launch lasts as long as its slowest thread's serial
# queries (one per dart that passes the liquid test); here no phase thread queries or loops over a
# block of cells.


# liquid and boundary particles near enough to a cell to reject one of its darts or to count in the
# colour field at a dart (dart_screen's per-cell list); on overflow each dart runs its own query
SCREEN_CAP = 96
screen_list = wp.types.vector(length=SCREEN_CAP, dtype=int)


@wp.func
def screen_cell(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    n_fluid: int,
    n_static: int,
    g: GhostGrid,
    p: SPHParams,
    ids: wp.array(dtype=int),
    attempts: int,
    phase_count: wp.array(dtype=int),
    phase_list: wp.array(dtype=int),
    phase_cap: int,
    ghost_stamp: wp.array(dtype=int),
    keep: wp.array(dtype=int),
    n_old: int,
    dart_mask: wp.array(dtype=int),
    ph: int,
    t_cell: int,
):
    """Thread (ph, t): the t-th active cell of phase ph (all phases in one launch). Closes the cell
    (``ghost_stamp = -stamp``) when no dart can pass: wholly within r_liquid of one liquid or boundary
    particle, or inside the liquid by the colour field at its centre. Otherwise sets bit t of
    ``dart_mask[c]`` for each dart t that passes every rule that does not depend on this sampling's
    ghosts: no liquid or boundary particle within r_liquid, no kept old ghost within r, a liquid
    particle within the layer, liquid colour field sum_j V_j W(y - x_j) at most colour_max. One hash
    query per cell gathers the particles that can matter (within the test radius plus the half
    diagonal of the cell: a dart lies within the half diagonal of the centre); every dart is tested
    against that list. ``dart_mask`` is zero on entry (place_darts clears it). ``ids`` = [stamp of this
    sampling, dart seed of this round] in device memory (as for dart_conflicts and place_darts), so that a
    recorded CUDA graph of the round replays with the values of each step."""
    stamp = ids[0]
    seed = ids[1]
    if t_cell >= phase_count[ph]:
        return
    c = phase_list[ph * phase_cap + t_cell]
    if ghost_stamp[c] == stamp or ghost_stamp[c] == -stamp:  # has a ghost (earlier round) / closed
        return
    ijk = cell_ijk(g, c)
    ci = ijk[0]
    cj = ijk[1]
    ck = ijk[2]
    half_diag = 0.5 * g.cell * wp.sqrt(float(g.dim))
    xc = cell_centre(g, ci, cj, ck)
    rl2 = g.r_liquid * g.r_liquid
    r2 = g.r * g.r
    layer2 = g.layer * g.layer
    H2 = p.H * p.H
    # (a small margin against rounding: an extra candidate never changes a decision)
    eps = 1.0e-4 * g.cell
    reach_l = wp.max(g.r_liquid, wp.max(g.layer, p.H)) + half_diag + eps
    reach_g = g.r + half_diag + eps
    base = cell_corner(g, ci, cj, ck)
    near = screen_list()
    n_near = int(0)
    kept = ghost_list()
    n_kept = int(0)
    col = float(0.0)
    grad = wp.vec3(0.0)
    covered = int(0)
    qc = wp.hash_grid_query(grid, xc, wp.max(reach_l, reach_g))
    jc = int(0)
    while wp.hash_grid_query_next(qc, jc):
        rc = xc - x[jc]
        if jc < n_static:
            dc = wp.length(rc)
            # close cells where no dart can pass. Inside the liquid: the colour field at the centre, less
            # |grad colour| times the half diagonal (first order) and a 0.1 margin, still above
            # colour_max everywhere in the cell. Covered: the whole cell within r_liquid of one particle.
            if dc <= g.layer:
                if dc + half_diag < g.r_liquid:
                    covered = 1
                if jc < n_fluid and dc < p.H:
                    col += g.liquid_volume * kernel_w(dc * dc, p)
                    grad += g.liquid_volume * kernel_grad(rc, dc, p)
            if dc < reach_l:
                if n_near < SCREEN_CAP:
                    near[n_near] = jc
                n_near += 1
        elif jc < n_static + n_old:
            if keep[jc - n_static] != 0:
                if wp.length(rc) < reach_g:
                    if n_kept < GHOST_CAP:
                        kept[n_kept] = jc
                    n_kept += 1
    if covered != 0 or col - wp.length(grad) * half_diag - 0.1 > g.colour_max:
        ghost_stamp[c] = -stamp
        return
    lists = int(0)
    if n_near <= SCREEN_CAP and n_kept <= GHOST_CAP:
        lists = 1
    rng = wp.rand_init(seed, c)
    mask = int(0)
    for t in range(attempts):
        y = base + g.cell * wp.vec3(wp.randf(rng), wp.randf(rng), wp.randf(rng))
        if g.dim == 2:
            y = wp.vec3(y[0], y[1], 0.0)
        ok = int(1)
        inside = int(0)  # a liquid particle within the layer
        colour = float(0.0)
        if lists != 0:
            for m in range(n_kept):
                if wp.length_sq(x[kept[m]] - y) < r2:
                    ok = 0
                    break
            if ok != 0:
                for m in range(n_near):
                    j = near[m]
                    d2 = wp.length_sq(x[j] - y)
                    if d2 < rl2:
                        ok = 0
                        break
                    if j < n_fluid:
                        if d2 <= layer2:
                            inside = 1
                        if d2 < H2:  # (kernel_w is zero beyond H: the same sum)
                            colour += g.liquid_volume * kernel_w(d2, p)
                            if colour > g.colour_max:
                                ok = 0
                                break
        else:
            j = int(0)
            q = wp.hash_grid_query(grid, y, wp.max(wp.max(g.r_liquid, g.r), wp.max(g.layer, p.H)))
            while wp.hash_grid_query_next(q, j):
                if j < n_static:
                    d2 = wp.length_sq(x[j] - y)
                    if d2 < rl2:
                        ok = 0
                        break
                    if j < n_fluid:
                        if d2 <= layer2:
                            inside = 1
                        colour += g.liquid_volume * kernel_w(d2, p)
                elif j < n_static + n_old:
                    if keep[j - n_static] != 0 and wp.length_sq(x[j] - y) < r2:
                        ok = 0
                        break
        if ok != 0 and inside != 0 and colour <= g.colour_max:
            mask = mask | (1 << t)
    dart_mask[c] = mask


@wp.kernel
def dart_screen(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    n_fluid: int,
    n_static: int,
    g: GhostGrid,
    p: SPHParams,
    ids: wp.array(dtype=int),
    attempts: int,
    phase_count: wp.array(dtype=int),
    phase_list: wp.array(dtype=int),
    phase_cap: int,
    ghost_stamp: wp.array(dtype=int),
    keep: wp.array(dtype=int),
    n_old: int,
    dart_mask: wp.array(dtype=int),
    stride: int,
):
    """screen_cell over (phase, active cell): a thread takes every ``stride``-th active cell of its phase
    (stride = the launch size along the cells), so the launch may be smaller than the count."""
    ph, t0 = wp.tid()
    t_cell = t0
    while t_cell < phase_count[ph]:
        screen_cell(grid, x, n_fluid, n_static, g, p, ids, attempts, phase_count, phase_list, phase_cap, ghost_stamp,
                    keep, n_old, dart_mask, ph, t_cell)
        t_cell += stride


@wp.func
def conflicts_cell_row(
    g: GhostGrid,
    ids: wp.array(dtype=int),
    attempts: int,
    phase_count: wp.array(dtype=int),
    phase_list: wp.array(dtype=int),
    phase_cap: int,
    phase: int,
    dart_mask: wp.array(dtype=int),
    cell_ghost: wp.array(dtype=int),
    ghost_stamp: wp.array(dtype=int),
    x_ghost: wp.array(dtype=wp.vec3),
    reject: wp.array(dtype=int),
    span: int,
    t_cell: int,
    o: int,
):
    """First launch of a phase (thread (t, o): the t-th active cell of the phase and, span 5, the o-th
    row of 5 cells along x of the 5^d block around it, or, span 1, its o-th cell): for each ghost of
    this sampling there, or-s into ``reject[c]`` the bits of the cell's darts left in dart_mask that
    lie within r of it. A ghost farther than two cells cannot reach a dart of the cell (cells are
    r/sqrt(d) wide)."""
    stamp = ids[0]
    seed = ids[1]
    if t_cell >= phase_count[phase]:
        return
    c = phase_list[phase * phase_cap + t_cell]
    mask = dart_mask[c]
    if mask == 0:
        return
    ijk = cell_ijk(g, c)
    ci = ijk[0]
    cj = ijk[1]
    ck = ijk[2]
    row = o
    i_lo = wp.max(ci - 2, 0)
    i_hi = wp.min(ci + 2, g.nx - 1)
    if span == 1:
        row = o // 5
        i_lo = ci + o % 5 - 2
        i_hi = i_lo
        if i_lo < 0 or i_lo >= g.nx:
            return
    jj = cj + row % 5 - 2
    kk = ck + row // 5 - 2
    if g.dim == 2:
        kk = ck
    if jj < 0 or jj >= g.ny or kk < 0 or kk >= g.nz:
        return
    base = cell_corner(g, ci, cj, ck)
    # a dart lies within the half diagonal of the centre: a ghost farther than r + half diagonal rejects none
    centre = cell_centre(g, ci, cj, ck)
    reach_g = g.r + 0.5 * g.cell * wp.sqrt(float(g.dim)) + 1.0e-4 * g.cell
    r2 = g.r * g.r
    bits = int(0)
    for ii in range(i_lo, i_hi + 1):
        n = cell_index(g, ii, jj, kk)
        if ghost_stamp[n] == stamp:
            yg = x_ghost[cell_ghost[n]]
            if wp.length(yg - centre) < reach_g:
                rng = wp.rand_init(seed, c)
                for t in range(attempts):
                    y = base + g.cell * wp.vec3(wp.randf(rng), wp.randf(rng), wp.randf(rng))
                    if g.dim == 2:
                        y = wp.vec3(y[0], y[1], 0.0)
                    if (mask & (1 << t)) != 0:
                        if wp.length_sq(yg - y) < r2:
                            bits = bits | (1 << t)
    if bits != 0:
        wp.atomic_or(reject, c, bits)


@wp.kernel
def dart_conflicts(
    g: GhostGrid,
    ids: wp.array(dtype=int),
    attempts: int,
    phase_count: wp.array(dtype=int),
    phase_list: wp.array(dtype=int),
    phase_cap: int,
    phase: int,
    dart_mask: wp.array(dtype=int),
    cell_ghost: wp.array(dtype=int),
    ghost_stamp: wp.array(dtype=int),
    x_ghost: wp.array(dtype=wp.vec3),
    reject: wp.array(dtype=int),
    span: int,
    stride: int,
):
    """conflicts_cell_row over (active cell of the phase, cell or row of its block): a thread takes every
    ``stride``-th active cell of the phase (stride = the launch size along the cells)."""
    t0, o = wp.tid()
    t_cell = t0
    while t_cell < phase_count[phase]:
        conflicts_cell_row(g, ids, attempts, phase_count, phase_list, phase_cap, phase, dart_mask, cell_ghost,
                           ghost_stamp, x_ghost, reject, span, t_cell, o)
        t_cell += stride


@wp.func
def place_cell(
    g: GhostGrid,
    ids: wp.array(dtype=int),
    attempts: int,
    phase_count: wp.array(dtype=int),
    phase_list: wp.array(dtype=int),
    phase_cap: int,
    phase: int,
    dart_mask: wp.array(dtype=int),
    reject: wp.array(dtype=int),
    cell_ghost: wp.array(dtype=int),
    ghost_stamp: wp.array(dtype=int),
    count: wp.array(dtype=int),
    capacity: int,
    n_static: int,
    x_ghost: wp.array(dtype=wp.vec3),
    t_cell: int,
):
    """Second launch of a phase (thread t: the t-th active cell of the phase): places the first dart
    of the cell that passed dart_screen and that no ghost rejected (dart_conflicts), and clears the
    cell's dart_mask and reject words for the next sampling. Velocity and owner come from
    ghost_nearest_liquid. Unlike throw_darts it does not close the neighbouring cells wholly within r
    of the new ghost: their darts are all rejected by dart_conflicts anyway (the same decisions), and
    the 3^d cell reads and writes were a serial chain that set the length of each phase launch on a GPU."""
    stamp = ids[0]
    seed = ids[1]
    if t_cell >= phase_count[phase]:
        return
    c = phase_list[phase * phase_cap + t_cell]
    mask = dart_mask[c]
    rej = reject[c]
    dart_mask[c] = 0
    reject[c] = 0
    if ghost_stamp[c] == stamp or ghost_stamp[c] == -stamp:  # has a ghost / closed
        return
    free = mask & (-1 ^ rej)
    if free == 0:
        return
    ijk = cell_ijk(g, c)
    base = cell_corner(g, ijk[0], ijk[1], ijk[2])
    rng = wp.rand_init(seed, c)
    for t in range(attempts):
        y = base + g.cell * wp.vec3(wp.randf(rng), wp.randf(rng), wp.randf(rng))
        if g.dim == 2:
            y = wp.vec3(y[0], y[1], 0.0)
        if (free & (1 << t)) == 0:
            continue
        slot = wp.atomic_add(count, 0, 1)
        if slot < capacity:
            o = n_static + slot
            x_ghost[o] = y
            cell_ghost[c] = o
            ghost_stamp[c] = stamp
        return


@wp.kernel
def place_darts(
    g: GhostGrid,
    ids: wp.array(dtype=int),
    attempts: int,
    phase_count: wp.array(dtype=int),
    phase_list: wp.array(dtype=int),
    phase_cap: int,
    phase: int,
    dart_mask: wp.array(dtype=int),
    reject: wp.array(dtype=int),
    cell_ghost: wp.array(dtype=int),
    ghost_stamp: wp.array(dtype=int),
    count: wp.array(dtype=int),
    capacity: int,
    n_static: int,
    x_ghost: wp.array(dtype=wp.vec3),
    stride: int,
):
    """place_cell over the active cells of the phase: a thread takes every ``stride``-th active cell (stride =
    the launch size)."""
    t0 = wp.tid()
    t_cell = t0
    while t_cell < phase_count[phase]:
        place_cell(g, ids, attempts, phase_count, phase_list, phase_cap, phase, dart_mask, reject, cell_ghost,
                   ghost_stamp, count, capacity, n_static, x_ghost, t_cell)
        t_cell += stride


@wp.kernel
def ghost_nearest_liquid(
    grid: wp.uint64,
    n_fluid: int,
    n_static: int,
    g: GhostGrid,
    first: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    ghost_of: wp.array(dtype=int),
):
    """Velocity and owner of the new ghost in slot first + tid: the nearest liquid particle within
    the layer (the query and order of throw_darts: the same particle)."""
    i = first + wp.tid()
    o = n_static + i
    y = x[o]
    best = float(1.0e30)
    nearest = int(-1)
    j = int(0)
    q = wp.hash_grid_query(grid, y, g.layer)
    while wp.hash_grid_query_next(q, j):
        if j < n_fluid:
            d2 = wp.length_sq(x[j] - y)
            if d2 < best:
                best = d2
                nearest = j
    ghost_of[i] = nearest
    v[o] = v[nearest]


# ------------------------------------------------------------------ persistent ghosts ----------
# With ``fluid.ghost.persistent`` the ghosts of the last step are kept: moved with their owner (the
# liquid particle that was nearest), dropped only when they clearly break the ghost rules (with a
# margin: hysteresis), and the darts only fill the holes. A resampled layer changes discretely every
# step (a ghost at 0.9 dx adds ~15% of rho0 to a surface particle's summation density), and that
# noise heats a drop with summation density until it flies apart; persistent ghosts change only
# where the liquid really opens or closes a gap.


@wp.kernel
def begin_sampling(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    x_ext: wp.array(dtype=wp.vec3),
    v_ext: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=int),
):
    """Copy the liquid and boundary positions and velocities into the extended arrays (thread i:
    particle i) and zero the ghost counters (one launch instead of two copies and a memset)."""
    i = wp.tid()
    x_ext[i] = x[i]
    v_ext[i] = v[i]
    if i == 0:
        count[0] = 0
        count[1] = 0


@wp.kernel
def begin_round(n_old: int, phase_count: wp.array(dtype=int), count: wp.array(dtype=int)):
    """Zero the per-phase active-cell counts (thread k: phase k); thread 0 puts the first free ghost
    slot (after the kept old ghosts) in count[0]."""
    k = wp.tid()
    phase_count[k] = 0
    if k == 0:
        count[0] = n_old


@wp.kernel
def advect_ghosts(
    grid: wp.uint64,
    x_new: wp.array(dtype=wp.vec3),
    ghost_of: wp.array(dtype=int),
    n_static: int,
    p: SPHParams,
    x: wp.array(dtype=wp.vec3),
):
    """Move each ghost with the liquid around it: by the kernel-weighted (Shepard) mean of the
    liquid displacements over the last step, sum_j W_gj (x_new_j - x_old_j) / sum_j W_gj; by its
    owner's displacement where no liquid particle lies within the support. ``x_new`` holds the
    liquid's new positions, ``x[:n_fluid]`` still the old ones and ``grid`` is last step's (built
    over the old positions). The mean, not the nearest particle's motion: a surface particle that
    moves relative to its neighbours (e.g. pulled in by a density deficit) must not carry its
    ghosts along, or the deficit never relaxes and pushes it on for ever. Launched over the
    previous step's ghosts; x = the extended positions."""
    g = wp.tid()
    o = n_static + g
    y = x[o]
    num = wp.vec3(0.0)
    den = float(0.0)
    q = wp.hash_grid_query(grid, y, p.H)
    j = int(0)
    while wp.hash_grid_query_next(q, j):
        if j < p.n_fluid:
            w = kernel_w(wp.length_sq(x[j] - y), p)
            num += w * (x_new[j] - x[j])
            den += w
    if den > 0.0:
        x[o] = y + num / den
    else:
        k = ghost_of[g]
        x[o] = y + (x_new[k] - x[k])


@wp.kernel
def keep_ghosts(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    n_fluid: int,
    n_static: int,
    g: GhostGrid,
    p: SPHParams,
    keep_liquid: float,
    keep_colour: float,
    keep_ghost: float,
    keep: wp.array(dtype=int),
    count: wp.array(dtype=int),
    v: wp.array(dtype=wp.vec3),
    ghost_of: wp.array(dtype=int),
):
    """Which of last step's ghosts (advected) stay: the nearest liquid particle within the layer, no
    liquid or boundary particle closer than ``keep_liquid``, the liquid colour field below
    ``keep_colour``, no ghost of lower index closer than ``keep_ghost`` (so that of two ghosts pushed
    together one stays). The thresholds are looser than the seeding rules (r_liquid, colour_max, r):
    a ghost is not dropped and re-seeded back and forth at the margin. A kept ghost takes the
    velocity and ownership of its nearest liquid particle. ``count[1]`` counts the dropped ones."""
    gi = wp.tid()
    o = n_static + gi
    y = x[o]
    best = float(1.0e30)
    nearest = int(-1)
    colour = float(0.0)
    ok = int(1)
    kl2 = keep_liquid * keep_liquid
    kg2 = keep_ghost * keep_ghost
    q = wp.hash_grid_query(grid, y, g.layer)
    j = int(0)
    while wp.hash_grid_query_next(q, j):
        d2 = wp.length_sq(x[j] - y)
        if j < n_static:
            if d2 < kl2:
                ok = 0
            if j < n_fluid:
                colour += g.liquid_volume * kernel_w(d2, p)
                if d2 < best:
                    best = d2
                    nearest = j
        elif j < o:
            if d2 < kg2:
                ok = 0
    if nearest < 0 or best > g.layer * g.layer or colour > keep_colour:
        ok = 0
    keep[gi] = ok
    if ok == 0:
        wp.atomic_add(count, 1, 1)
    else:
        v[o] = v[nearest]
        ghost_of[gi] = nearest


@wp.kernel
def close_kept_cells(
    x: wp.array(dtype=wp.vec3),
    keep: wp.array(dtype=int),
    n_static: int,
    g: GhostGrid,
    stamp: int,
    ghost_stamp: wp.array(dtype=int),
):
    """Close the background cell of each kept ghost for the darts (any dart there is within r of it)."""
    gi = wp.tid()
    if keep[gi] == 0:
        return
    c = cell_coord(g, x[n_static + gi])
    if c[0] < 0 or c[1] < 0 or c[2] < 0 or c[0] >= g.nx or c[1] >= g.ny or c[2] >= g.nz:
        return
    ghost_stamp[cell_index(g, c[0], c[1], c[2])] = -stamp


@wp.kernel
def ghost_flags(keep: wp.array(dtype=int), n_old: int, flag: wp.array(dtype=int)):
    """flag = 1 for a kept old ghost and for every new ghost (slots >= n_old)."""
    gi = wp.tid()
    f = int(1)
    if gi < n_old:
        f = keep[gi]
    flag[gi] = f


@wp.kernel
def compact_ghosts(
    flag: wp.array(dtype=int),
    rank: wp.array(dtype=int),
    n_static: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    ghost_of: wp.array(dtype=int),
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    owner_out: wp.array(dtype=int),
):
    """Stable compaction of the flagged ghosts (rank = exclusive scan of flag) into the out arrays."""
    gi = wp.tid()
    if flag[gi] == 0:
        return
    k = rank[gi]
    x_out[k] = x[n_static + gi]
    v_out[k] = v[n_static + gi]
    owner_out[k] = ghost_of[gi]


# ------------------------------------------------------------------ step over the neighbour lists ------
# The ghost step reuses the fluid solver's cell grid and Verlet neighbour lists (kernels/sph/fluid.py) for
# every liquid-liquid and liquid-boundary pair (position divergence, density, forces) and reaches the
# ghosts through a small hash grid over the ghosts alone: the same sums as one hash-grid query over
# fluid + boundary + ghosts, in another order (float rounding only).


@wp.func
def divergence_by_query(grid: wp.uint64, i: int, xi: wp.vec3, x: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float),
                        particle_mass: wp.array(dtype=float), p: SPHParams, n_static: int) -> float:
    """div x_i over a query of ``grid`` (liquid and boundary neighbours; index >= n_static skipped): the
    fallback for a particle whose neighbour list overflowed."""
    s = float(0.0)
    q = wp.hash_grid_query(grid, xi, p.H)
    j = int(0)
    while wp.hash_grid_query_next(q, j):
        if j == i or j >= n_static:
            continue
        rij = xi - x[j]
        r = wp.length(rij)
        if r < p.H:
            s += position_divergence_term(rij, r, j, rho, particle_mass, p)
    return s


@wp.kernel
def position_divergence_list(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    p: SPHParams,
    n_static: int,
    threshold: float,
    div: wp.array(dtype=float),
    surface: wp.array(dtype=int),
):
    """Free-surface detection: div x_i (position_divergence_term) over the neighbour list (liquid and
    boundary neighbours; pairs out to the list radius are skipped past H); a particle whose list overflowed
    sums over a query of ``grid`` (fluid + boundary [+ ghosts], index >= n_static skipped) instead.
    Particles below ``threshold`` are surface particles."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    xi = x[i]
    s = float(0.0)
    H2 = p.H * p.H
    if c <= nbr.shape[0] // n:
        for k in range(c):
            j = nbr[k * n + i]
            rij = xi - x[j]
            r2 = wp.length_sq(rij)
            if r2 < H2:
                s += position_divergence_term(rij, wp.sqrt(r2), j, rho, particle_mass, p)
    else:
        s = divergence_by_query(grid, i, xi, x, rho, particle_mass, p, n_static)
    div[i] = s
    surface[i] = wp.where(s < threshold, 1, 0)


@wp.kernel
def continuity_rate_and_divergence_list(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    p: SPHParams,
    n_static: int,
    threshold: float,
    drho_dt: wp.array(dtype=float),
    div: wp.array(dtype=float),
    surface: wp.array(dtype=int),
):
    """position_divergence_list and the continuity rate of sph.particle_density_continuity_list in one pass
    over the neighbour list (the same terms in the same order: the same bits). The density itself is not
    advanced here (div x reads the neighbours' rho: advance_density_rate does it after this launch); an
    overflowed list gets div x from a query of ``grid`` and its rate from sph.particle_density_overflow."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    xi = x[i]
    vi = v[i]
    s = float(0.0)
    rate = float(0.0)
    H2 = p.H * p.H
    if c <= nbr.shape[0] // n:
        for k in range(c):
            j = nbr[k * n + i]
            rij = xi - x[j]
            r2 = wp.length_sq(rij)
            if r2 < H2:
                r = wp.sqrt(r2)
                g = kernel_grad(rij, r, p)
                rj = p.rest_density
                if j < p.n_fluid:
                    rj = rho[j]
                    rate += p.fluid_mass * wp.dot(vi - v[j], g)
                else:
                    rate += particle_mass[j] * wp.dot(vi, g)
                s += -particle_mass[j] / rj * wp.dot(rij, g)
        drho_dt[i] = rate
    else:
        s = divergence_by_query(grid, i, xi, x, rho, particle_mass, p, n_static)
    div[i] = s
    surface[i] = wp.where(s < threshold, 1, 0)


@wp.kernel
def advance_density_rate(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    dt: wp.array(dtype=float),
    p: SPHParams,
    drho_dt: wp.array(dtype=float),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
):
    """rho_i += dt d rho_i/dt, p_i = EOS(rho_i), pr2_i = p_i/rho_i^2 after continuity_rate_and_divergence_list
    (particles whose list overflowed: sph.particle_density_overflow)."""
    i = wp.tid()
    n = count.shape[0]
    if count[i] > nbr.shape[0] // n:
        return
    store_density(i, rho[i] + dt[0] * drho_dt[i], p, rho, pressure, pr2)


@wp.kernel
def ghost_mass_split(
    grid: wp.uint64,
    ghost_grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    p: SPHParams,
    n_static: int,
    count: wp.array(dtype=int),
    set_mass: int,
    stamp: int,
    near: wp.array(dtype=int),
    particle_mass: wp.array(dtype=float),
):
    """Marks the liquid particles within H of a ghost (``near[i] = stamp``: the ghost passes of the step
    skip the others without a query) and, with ``set_mass``, the ghost mass from its number density (as
    Akinci et al. 2012 do for boundary particles): m_g = rho0 / sum_k W_gk over the liquid neighbours from
    ``grid`` (fluid + boundary [+ old ghosts]; liquid only) and the ghosts from ``ghost_grid`` (ghosts only,
    index k is slot n_static + k), self included. On a lattice of spacing dx this is the liquid particle
    mass; a ghost that the random sampling placed close to others gets less, which cancels most of the
    density noise of a random ghost layer. Launched over the ghosts (threads at or past count[0] return)."""
    gi = wp.tid()
    if gi >= count[0]:
        return
    o = gi + n_static
    xg = x[o]
    s = float(0.0)
    H2 = p.H * p.H
    q = wp.hash_grid_query(grid, xg, p.H)
    k = int(0)
    while wp.hash_grid_query_next(q, k):
        if k < p.n_fluid:
            r2 = wp.length_sq(xg - x[k])
            if r2 < H2:
                near[k] = stamp
            s += kernel_w(r2, p)
    if set_mass == 0:
        return
    qg = wp.hash_grid_query(ghost_grid, xg, p.H)
    while wp.hash_grid_query_next(qg, k):
        s += kernel_w(wp.length_sq(xg - x[n_static + k]), p)
    particle_mass[o] = p.rest_density / s


@wp.kernel
def ghost_density(
    ghost_grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=float),
    dt: wp.array(dtype=float),
    p: SPHParams,
    n_static: int,
    mode: int,
    stamp: int,
    near: wp.array(dtype=int),
    drho_dt: wp.array(dtype=float),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
):
    """The ghosts' part of the density, after the list pass over liquid and boundary (rho_i = S_i):
    mode 0 summation rho_i = S_i + G_i; mode 1 capped rho_i = S_i + min(G_i, max(rho0 - S_i, 0)): the
    ghosts fill the missing part of the kernel support and no more (air at p = 0 completes a surface
    particle's density up to rho0 but cannot compress it: the random layer's density excess would push the
    particle away from the liquid, and its ghosts, carried with it, keep pushing); mode 2 continuity with
    ghosts in the rate, rho_i += dt sum_g m_g (v_i - v_g) . grad W_ig (ghost velocity: the nearest liquid
    particle's, Schechter & Bridson 2012). Then p_i and p_i/rho_i^2.
    Particles with no ghost within H (near[i] != stamp) keep the list pass's values without a query."""
    i = wp.tid()
    if near[i] != stamp:
        return
    xi = x[i]
    vi = v[i]
    gs = float(0.0)
    q = wp.hash_grid_query(ghost_grid, xi, p.H)
    k = int(0)
    while wp.hash_grid_query_next(q, k):
        o = n_static + k
        rij = xi - x[o]
        r2 = wp.length_sq(rij)
        if mode == 2:
            if r2 < p.H * p.H:
                gs += particle_mass[o] * wp.dot(vi - v[o], kernel_grad(rij, wp.sqrt(r2), p))
        else:
            gs += particle_mass[o] * kernel_w(r2, p)
    if gs == 0.0:
        return  # no ghost within H: rho, p and p/rho^2 of the list pass stand
    s = rho[i]
    r = s + gs
    if mode == 1:
        r = s + wp.min(gs, wp.max(p.rest_density - s, 0.0))
    elif mode == 2:
        drho_dt[i] = drho_dt[i] + gs
        r = s + dt[0] * gs
    store_density(i, r, p, rho, pressure, pr2)


@wp.kernel
def ghost_pressure_force(
    ghost_grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
    p: SPHParams,
    n_static: int,
    stamp: int,
    near: wp.array(dtype=int),
    accel: wp.array(dtype=wp.vec3),
):
    """The ghosts' pressure term after the list force pass: a_i -= sum_g m_g p_i/rho_i^2 grad W_ig (the
    boundary rule of pair_acceleration: ghosts have p = 0, no viscosity or XSPH); only particles with
    a ghost within H (near[i] == stamp) query the ghost grid."""
    i = wp.tid()
    if near[i] != stamp:
        return
    xi = x[i]
    a = wp.vec3(0.0)
    q = wp.hash_grid_query(ghost_grid, xi, p.H)
    k = int(0)
    found = int(0)
    while wp.hash_grid_query_next(q, k):
        o = n_static + k
        rij = xi - x[o]
        r2 = wp.length_sq(rij)
        if r2 < p.H * p.H and r2 > 0.0:
            a -= particle_mass[o] * kernel_grad(rij, wp.sqrt(r2), p)
            found = 1
    if found != 0:
        accel[i] = accel[i] + pr2[i] * a


@wp.kernel
def set_dart_ids(stamp: int, seed: int, ids: wp.array(dtype=int)):
    """ids = [stamp, seed] for the dart launches of one round (read on the device: see dart_screen)."""
    ids[0] = stamp
    ids[1] = seed
