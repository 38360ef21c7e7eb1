"""Ghost SPH free surface (Schechter & Bridson 2012) for the weakly compressible SPH solver.

Selected per scene with ``fluid.method = "ghost"`` (settings in ``[fluid.ghost]``); a basic scene
never imports this module. :class:`GhostFluidSolver` is a :class:`rockwave.sph.fluid.FluidSolver`
whose step first seeds ghost air particles around the free surface and then runs the same SPH
kernels on fluid + boundary + ghost particles:

1. FluidSolver's cell grid and Verlet neighbour lists (liquid + boundary, rebuilt when a particle
   moved skin/2); copy fluid and boundary positions/velocities into extended arrays, build the hash
   grid the darts query;
2. free-surface particles: position divergence ``div x_i`` below a threshold;
3. ghost air particles within one kernel radius of the liquid, from a Poisson-disk set
   (``kernels/sph/ghost.py``). ``sampler = "tile"`` (default): the points of a periodic Poisson-disk tile
   (``poisson_disk_tile``, Bridson 2007, generated once) that lie in the layer and pass the liquid rules,
   one launch (``tile_ghosts``). ``sampler = "darts"`` (and with ``persistent``): dart throwing in the
   background cells in 3^d phases; on a GPU every dart of every active cell is screened in one launch and
   the phases only test darts against new ghosts (``parallel_darts``); on the CPU the same decisions cell
   by cell (``throw_darts``). Mass = liquid mass (or number-density mass), velocity = nearest liquid
   particle's, density = rho0 (p = 0);
4. a hash grid over the ghosts alone; density (summation or continuity) and forces over the lists,
   plus the ghosts' part from the ghost grid (only for liquid particles within H of a ghost). Ghosts count in
   the summation density (not in the continuity rate: see ``ghost_continuity``); in the pressure force they enter only through the liquid particle's own
   ``p_i/rho_i^2`` term (their pressure is zero); no viscosity or XSPH with ghosts.

Summation density (``[fluid.ghost]``, all off by default; on in scenes/drop_zero_g_2d.toml):
``density_cap`` lets the ghosts fill a surface particle's density up to rho0 and no further;
``pressure_term = false`` takes the ghosts out of the pressure force (the paper's rule; the one-sided
term pumps energy); ``persistent`` keeps last step's ghosts, moved by the kernel-weighted mean
displacement of the liquid around them, drops them only past looser limits than the seeding rules
and throws darts only into the holes. Without these a resting drop with summation density flies
apart (tests/test_ghost.py::test_zero_gravity_drop_keeps_shape_with_ghosts_and_basic_summation_clumps).

Walls: the tank and obstacle boundary particles are static layers at least one kernel radius thick
with lattice-calibrated masses, i.e. they already are the "ghost solid particles" of the paper
(they complete the density sums at walls and push with the Akinci term); they are not resampled.

One host read per step on a GPU: the ghost count (to size the ghost grid build and grow the buffers)
with the per-phase active-cell counts, which size the next step's dart (or tile) launches (each thread takes
every size-th cell of its phase, so a launch smaller than the count is exact; the first sampling
launches over a host bound, ``phase_bound``, or reads the counts where that bound is large). A round
of darts replays as one CUDA graph (``graph_darts``), the step's other launches are recorded once and
replayed (``FluidSolver._launch``): a GPU ghost step of a few thousand particles is set by launch
latency and host work, not by the device.
"""

from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from rockwave.kernels.sph import fluid as sph
from rockwave.kernels.sph import ghost as gk
from rockwave.sph.fluid import Density, FluidModel, FluidOptions, FluidSolver, FluidState, _grid_dims

# Free-surface threshold on div x (the full value is the dimension). 2D: 1.5 as in the report and
# Lee et al. (2008). 3D: measured on lattice blocks and spheres (tests/test_ghost.py): interior 3.0,
# flat face 1.9-2.0, edges/corners below, one layer in 2.7-2.9; 2.4 flags the outer layer only.
DEFAULT_THRESHOLD = {2: 1.5, 3: 2.4}
# Poisson-disk radius / spacing. A saturated random disk packing has ~0.70/r^2 points per area
# (0.73/r^3 per volume in 3D), the liquid lattice 1/dx^d; with finite attempts the packing is not
# saturated. Calibrated so the summation density of a flat surface layer comes out at rho0
# within about 2% (tests/test_ghost.py::test_ghosts_complete_surface_density).
DEFAULT_RADIUS_RATIO = {2: 0.80, 3: 0.85}
# The tile sampler uses the same radius. Its layer has gaps next to the liquid (tile points within r_liquid of it
# are dropped, not replaced), so its flat-surface summation density is ~8% low (0.92 rho0, tests); a smaller
# radius would fill it (0.65 dx: 0.945 rho0 in 2D) but its denser ghosts' pressure term pushed particles
# through the walls in the case-3 splash at 0.01 m (3 of 6 H100 runs; none at 0.72 and 0.80: docs/notes.md).
# Summation density with ghosts wants persistent ghosts anyway, which only the darts keep.
# Courant number above which the ghosts' one-sided pressure term was measured to pump energy into a
# splash: case 3 on an H100 (runs differ in the atomics' order), at 0.25 two of three 0.03 m runs
# gained energy (one x5.3, a particle 0.46 m out) and the 0.01 m scene blew up (x584); at 0.125 none
# of seven runs did (docs/notes.md). The ghost scenes use 0.125.
GHOST_CFL_MAX = 0.125

# (rockwave/build/options.py warn_unstable_step warns of a ghost scene above it)


# periodic Poisson-disk tile of the tile sampler: cells per axis (r/sqrt(d) wide: 36 dx in 2D, 12 dx in 3D)
TILE_CELLS = {2: 63, 3: 24}
_TILES = {}


def poisson_disk_tile(k: int, dim: int, seed: int = 1, attempts: int = 30) -> np.ndarray:
    """A periodic Poisson-disk set in a box of k^dim unit cells, radius sqrt(dim) (so at most one point per
    cell), by Bridson's (2007) algorithm: candidates uniform in the annulus r..2r around a random active
    sample, the first farther than r from every sample (periodic distance) accepted and made active, an
    active sample with ``attempts`` rejections retired. Points (n, dim) in cell units; cached per process."""
    key = (k, dim, seed, attempts)
    if key in _TILES:
        return _TILES[key]
    import itertools

    r = math.sqrt(dim)
    L = float(k)
    rng = np.random.default_rng(seed)
    owner = -np.ones((k,) * dim, dtype=np.int64)
    pts = np.zeros((k ** dim, dim))
    offs = np.array(list(itertools.product(range(-2, 3), repeat=dim)))  # r < 2 cells
    n = 0

    def add(y):
        nonlocal n
        pts[n] = y
        owner[tuple(np.floor(y).astype(int) % k)] = n
        n += 1

    add(rng.random(dim) * L)
    active = [0]
    while active:
        ia = int(rng.integers(len(active)))
        u = rng.random(attempts)
        if dim == 2:
            ang = rng.random(attempts) * 2.0 * math.pi
            d = np.sqrt(r * r * (1.0 + 3.0 * u))[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
        else:
            w = rng.normal(size=(attempts, 3))
            d = np.cbrt(r ** 3 * (1.0 + 7.0 * u))[:, None] * w / np.linalg.norm(w, axis=1)[:, None]
        cand = (pts[active[ia]] + d) % L
        cells = (np.floor(cand).astype(int)[:, None, :] + offs[None]) % k
        own = owner[tuple(cells[..., a] for a in range(dim))]
        q = pts[np.maximum(own, 0)] - cand[:, None, :]
        q -= L * np.round(q / L)
        free = ~((own >= 0) & ((q * q).sum(-1) < r * r)).any(1)
        if free.any():
            add(cand[int(np.argmax(free))])
            active.append(n - 1)
        else:
            active[ia] = active[-1]
            active.pop()
    _TILES[key] = pts[:n].copy()
    return _TILES[key]


def tile_offsets(points: np.ndarray, k: int, dim: int) -> np.ndarray:
    """Per cell of the k^dim tile (x fastest) the offset of its point in the cell (0..1 per axis), or -1."""
    out = np.full((k ** dim, 3), -1.0, dtype=np.float32)
    c = np.floor(points).astype(int) % k
    idx = c[:, 0] + k * c[:, 1] + (k * k * c[:, 2] if dim == 3 else 0)
    out[idx, :dim] = points - np.floor(points)
    if dim == 2:
        out[idx, 2] = 0.0
    return out


class Sampler(str, enum.Enum):
    """How ghost positions are drawn (``fluid.ghost.sampler``), chosen once at build time."""

    TILE = "tile"  # the points of a periodic Poisson-disk tile that pass the liquid rules (one launch)
    DARTS = "darts"  # dart throwing in the background cells in 3^d phases (persistent ghosts)


@dataclass
class GhostOptions:
    """Everything the ghost solver is told (Python API: ``GhostFluidSolver(model, options=..., ghost_options=...)``,
    ``Simulation(scene, options=SimulationOptions(ghost=...))``).

    The first fields are the scene's ``[fluid.ghost]`` settings (rockwave/build/options.py ghost_options fills them from
    the scene, over the values given in Python; the scene format takes its defaults from here). The rest are not in
    the scene format: the ghost stream's seed and sampling knobs, none of which changes which ghosts are placed
    (except tile_points)."""

    surface_threshold: float | None = None
    """Free-surface particles have position divergence div x below this [-] (interior: the dimension); None:
    DEFAULT_THRESHOLD[dim]. Scene: fluid.ghost.surface_threshold."""

    sample_radius_ratio: float | None = None
    """Poisson-disk radius r / particle spacing [-]; None: DEFAULT_RADIUS_RATIO[dim]. Scene:
    fluid.ghost.sample_radius_ratio."""

    layer_ratio: float = 1.0
    """Ghost layer thickness / kernel support radius H [-]. Scene: fluid.ghost.layer_ratio."""

    sampler: str | None = None
    """"tile" (the points of a periodic Poisson-disk tile, one launch) or "darts" (dart throwing in 3^d phases);
    None: "darts" with persistent, else "tile" (GhostFluidSolver.default_sampler). Scene: fluid.ghost.sampler."""

    attempts: int = 16
    """Darts per background cell and round [-] (one pass of 16: as many ghosts as two passes of 8, +0.6..3.5% on the
    same liquid, with half the dependent dart launches on a GPU: docs/notes.md). Scene: fluid.ghost.attempts."""

    rounds: int = 1
    """Passes over the 3^d phases of the background grid [-]. Scene: fluid.ghost.rounds."""

    pressure_term: bool = True
    """Ghosts (p = 0) enter the pressure force through the liquid particle's own p_i/rho_i^2 term (True), or add no
    pressure force at all (False; the elliptical drop). Scene: fluid.ghost.pressure_term."""

    density_cap: bool = False
    """Summation density: the ghosts fill a surface particle's kernel support up to rho0 and no further (air at
    p = 0 cannot compress the liquid). Scene: fluid.ghost.density_cap."""

    persistent: bool = False
    """Keep last step's ghosts (moved with the liquid around them) and only fill the holes; drop a ghost only past
    looser limits than the seeding rules (hysteresis). Needs the dart sampler. Scene: fluid.ghost.persistent."""

    seed: int = 1
    """Seed of the dart streams [-]: one random stream per background cell, the same every step (unless
    fresh_darts), so that where the liquid has not moved the ghosts come out the same."""

    fresh_darts: bool = False
    """Draw new darts every step (a new random layer each step; with a stiff EOS it heats a resting drop)."""

    number_density_mass: bool = True
    """Ghost mass from the liquid's number density (True) or the liquid particle mass."""

    phase_launches: bool = False
    """On the CPU too, one dart launch per phase sized by the host bound (the GPU's pattern; tests)."""

    shortcuts: bool = True
    """Skip cells without a query where every dart would fall near a ghost (False: the same ghosts, more queries;
    tests compare both)."""

    parallel_darts: bool | None = None
    """Screen every dart of every active cell in one launch, the dependent phase launches only test darts against
    the new ghosts (the same ghosts as the serial throw; None: on CUDA, where a phase launch lasts as long as its
    slowest thread)."""

    parallel_bound_max: int = 1 << 16
    """Parallel darts without a host read while the phase bound is at most this [cells]."""

    graph_darts: bool = True
    """On CUDA, a round of parallel darts sized by the host bound replays as one CUDA graph."""

    conflict_span: int | None = None
    """dart_conflicts threads per (cell, cell of its 5^d block) (1) or per row of 5 (5); None: 1 in 3D (H100, 3D
    drop 0.44 -> 0.32 ms a step), 5 in 2D."""

    tile_points: np.ndarray | None = None
    """float64 (n, dim): the tile's points in cell units instead of poisson_disk_tile's (tests)."""

    dart_launch_size: int | None = None
    """Parallel darts: at most this many threads along a phase's cells (tests)."""


class GhostFluidSolver(FluidSolver):
    """FluidSolver with ghost air particles (Schechter & Bridson 2012).

    Attributes (beyond FluidSolver's):
        sampler: "tile" (points of a periodic Poisson-disk tile, one launch) or "darts" (dart throwing
        in 3^d phases; with persistent ghosts); threshold: free-surface threshold on div x; r: Poisson-disk radius [m];
        layer: ghost layer thickness [m]; attempts, rounds: darts per cell per round, rounds.
        n_ghost: ghosts in use this step; capacity: ghost slots allocated (grows on demand).
        x_ext, v_ext, mass_ext: wp.array(n_fluid + n_boundary + capacity): fluid, boundary, ghosts.
        div: wp.array(float, n_fluid) position divergence; surface: wp.array(int, n_fluid) 1 at the surface.
        sample_seconds: wall time spent in ghost sampling (only counted when ``profile`` is true).
    """

    default_reorder_interval = 0  # the grid also holds the ghosts: particles keep their order
    default_recorded_launches = True  # FluidSolver._launch: the ghost step cannot run in a CUDA graph (host reads)
    capturable = False  # one host read a step (the ghost count)
    default_sampler = "tile"

    def __init__(self, model: FluidModel, options: FluidOptions | None = None, ghost_options: GhostOptions | None = None):
        if options is not None and options.reorder_interval:
            raise ValueError(f"FluidOptions.reorder_interval = {options.reorder_interval}: Ghost SPH keeps the particle "
                             "order (its grid also holds the ghosts); leave it None or 0")
        if options is not None and options.neighbours == "cells":
            raise ValueError("FluidOptions.neighbours = 'cells': the Ghost SPH passes read the neighbour lists; "
                             "use 'lists' (or None)")
        super().__init__(model, options)
        self.replace_pass("neighbour_lists", self._ghost_lists_pass)
        self.replace_pass("density", self._ghost_density_pass)
        self.insert_pass("ghost_pressure", self._ghost_pressure_pass, after="pair_forces")
        go = ghost_options or GhostOptions()
        self.ghost_options = go
        self.phase_launches = go.phase_launches
        self.shortcuts = go.shortcuts
        self.parallel_darts = go.parallel_darts
        self.parallel_bound_max = go.parallel_bound_max
        self.graph_darts = go.graph_darts
        self.conflict_span = go.conflict_span
        self.tile_points = go.tile_points
        self.dart_launch_size = go.dart_launch_size
        d = model.device
        dim = model.dim
        self.threshold = float(go.surface_threshold if go.surface_threshold is not None else DEFAULT_THRESHOLD[dim])
        # "darts": dart throwing in the background cells each step; "tile": the points of a periodic
        # Poisson-disk tile that pass the liquid rules (poisson_disk_tile; one launch, no phases)
        persistent = bool(go.persistent)
        name = str(go.sampler or ("darts" if persistent else self.default_sampler))
        if name not in ("darts", "tile"):
            raise ValueError(f"GhostOptions.sampler = {name!r} (fluid.ghost.sampler): expected 'darts' or 'tile'")
        self.sampler = Sampler(name)
        if self.sampler is Sampler.TILE and persistent:
            raise ValueError("GhostOptions.sampler = 'tile' (fluid.ghost.sampler) does not keep ghosts (persistent = true "
                             "needs 'darts')")
        ratio = go.sample_radius_ratio if go.sample_radius_ratio is not None else DEFAULT_RADIUS_RATIO[dim]
        self.r = float(ratio) * model.spacing
        self.layer = float(go.layer_ratio) * model.support_radius
        # liquid particles own a cell of width dx, ghosts one of width ~r: keep the centres half of each apart
        self.r_liquid = 0.5 * (model.spacing + self.r)
        self.number_density_mass = bool(go.number_density_mass)
        self.attempts = int(go.attempts)
        self.rounds = int(go.rounds)
        self.profile = False
        self.sample_seconds = 0.0
        self.n_ghost = 0
        self._seed = 0
        # Darts are drawn from one random stream per background cell that is the same every step
        # (fresh_darts = False): where the liquid has not moved, the ghosts come out the same, so
        # the unavoidable density error of a random layer is a fixed offset instead of a new random
        # force every step (which, with a stiff EOS, heats a resting drop until it flies apart).
        self.seed = int(go.seed)
        self.fresh_darts = bool(go.fresh_darts)
        # persistent, density_cap, pressure_term: GhostOptions
        self.persistent = persistent
        self.density_cap = bool(go.density_cap)
        self.ghost_pressure_term = bool(go.pressure_term)
        # background grid over the model domain grown by the layer
        g = gk.GhostGrid()
        cell = self.r / math.sqrt(dim)
        lo = np.asarray(model.domain_lo, float) - self.layer
        hi = np.asarray(model.domain_hi, float) + self.layer
        n = np.maximum(np.ceil((hi - lo) / cell).astype(int), 1)
        if dim == 2:
            lo[2], n[2] = 0.0, 1
        ncell = int(np.prod(n))
        if ncell > 400_000_000:
            raise ValueError(f"ghost background grid of {ncell:,} cells (domain {np.round(hi - lo, 3).tolist()} m at "
                             f"{cell:.3g} m): reduce the domain or raise fluid.ghost.sample_radius_ratio")
        g.lo = wp.vec3(*lo.tolist())
        g.cell, g.nx, g.ny, g.nz, g.dim, g.r, g.layer = cell, int(n[0]), int(n[1]), int(n[2]), dim, self.r, self.layer
        g.r_liquid = self.r_liquid
        g.liquid_volume = model.fluid_mass / model.params.rest_density
        # 0.5 seeded ghosts in pockets of the churning water between the obstacle and the wall (case
        # 3): their one-sided pressure term pumped energy in (x1.8 in 0.3 s); 0.3 keeps them outside
        g.colour_max = 0.3
        self.bg = g
        # the ghosts alone in a hash grid of cell H (the step reaches liquid and boundary neighbours
        # through FluidSolver's cell grid and neighbour lists, the ghosts through this grid)
        self.ghost_grid = wp.HashGrid(*_grid_dims(lo, hi, model.support_radius, dim), device=d)
        self.keep_liquid = 0.6 * self.r_liquid
        self.keep_ghost = 0.6 * self.r
        self.keep_colour = 0.45
        # dense per-cell arrays are stamped, never cleared: cell_mark (active this sampling),
        # ghost_stamp/cell_ghost (the cell's ghost); the active cells go to compact per-phase lists
        self._stamp = 0
        self.cell_mark = wp.zeros(ncell, dtype=int, device=d)
        self.ghost_stamp = wp.zeros(ncell, dtype=int, device=d)
        self.cell_ghost = wp.zeros(ncell, dtype=int, device=d)
        # cell_class: stamp once a cell was classified open (its first hash query of this sampling);
        # wall_closed: 1 for cells wholly within r_liquid of a (static) wall particle, set at the first sampling
        self.cell_class = wp.zeros(ncell, dtype=int, device=d)
        self.wall_closed = wp.zeros(ncell, dtype=int, device=d)
        self._walls_closed = False
        self.div = wp.zeros(model.n_fluid, dtype=float, device=d)
        self.surface = wp.zeros(model.n_fluid, dtype=int, device=d)
        self.n_phases = 27 if dim == 3 else 9
        self.tile_k = 0
        tile = np.full((1, 3), -1.0, dtype=np.float32)
        if self.sampler is Sampler.TILE:
            k = TILE_CELLS[dim]
            pts = self.tile_points if self.tile_points is not None else poisson_disk_tile(k, dim)
            tile = tile_offsets(pts, k, dim)
            self.tile_k = k
        self.tile = wp.array(tile, dtype=wp.vec3, device=d)
        # the tile's rows along x (CSR): the x indices (mod k) of the cells of row (j mod k) + k (k mod k) with a point
        k = max(self.tile_k, 1)
        has = (tile[:, 0] >= 0).reshape(-1, k) if self.tile_k else np.zeros((1, 1), bool)
        first = np.concatenate([[0], np.cumsum(has.sum(axis=1))]).astype(np.int32)
        cells = np.nonzero(has)[1].astype(np.int32) if has.any() else np.zeros(1, np.int32)
        self.tile_row_first = wp.array(first, dtype=int, device=d)
        self.tile_row_cells = wp.array(cells, dtype=int, device=d)
        self.phase_cap = int(np.prod([-(-g.nx // 3), -(-g.ny // 3), -(-g.nz // 3)]))  # cells of one phase
        # [0] ghost slots used, [1] ghosts dropped (persistent), [2:] active cells per phase (phase_count): the
        # step's one host read takes them all (the phase counts size the next step's dart launches on CUDA)
        self.count = wp.zeros(2 + self.n_phases, dtype=int, device=d)
        self.phase_count = self.count[2:]
        self._last_counts = None
        # parallel darts: bit t of dart_mask[c] = dart t of cell c passed the screens, of dart_reject[c] = a
        # new ghost lies within r of it (both zero between samplings: place_darts clears them)
        self.dart_mask = wp.zeros(ncell, dtype=int, device=d)
        self.dart_reject = wp.zeros(ncell, dtype=int, device=d)
        self.phase_list = wp.zeros(self.n_phases * self.phase_cap, dtype=int, device=d)
        self.dart_ids = wp.zeros(2, dtype=int, device=d)  # [stamp, seed] of the round (set_dart_ids)
        self._dart_graphs = {}  # CUDA graphs of a round of parallel darts, by buffers and launch sizes
        self._dart_graph_warm = set()
        # host bound on the active cells of one phase: a surface particle marks the cells of the box
        # [x - layer, x + layer], at most m per axis, ceil(m/3) per axis in one phase
        m_axis = int(2.0 * self.layer / cell) + 2
        self.mark_slices = m_axis  # mark_active_cells: a thread per surface particle and slice of its box
        self.phase_bound = min(self.phase_cap, model.n_fluid * (-(-m_axis // 3)) ** dim)
        # GPU: launch over this bound without reading the counts back, up to this many threads a launch
        self.phase_bound_max = 1 << 19
        # near[i] == _near_stamp: liquid particle i has a ghost within H this step (set by ghost_mass_split)
        self._near = wp.zeros(model.n_fluid, dtype=int, device=d)
        self._near_stamp = 0
        # Continuity density sums liquid and boundary neighbours only. Ghosts are resampled every
        # step, so (v_i - v_ghost).grad W (v_ghost = nearest liquid particle's) is no rate of any
        # real change; it drained spray and wall-run-up particles to negative densities and sent
        # particles through the walls (case 1/3 dam breaks). 1 restores ghosts in the sum.
        self.ghost_continuity = 0
        self._alloc(max(1024, 2 * model.n_fluid))

    # ------------------------------------------------------------------ buffers --------------
    def _alloc(self, capacity: int) -> None:
        m, d = self.model, self.model.device
        ns = m.n_total
        self.capacity = capacity
        self._recorded = {}
        self._views = {}  # _x_view
        self.x_ext = wp.zeros(ns + capacity, dtype=wp.vec3, device=d)
        self.v_ext = wp.zeros(ns + capacity, dtype=wp.vec3, device=d)
        self.mass_ext = wp.full(ns + capacity, m.fluid_mass, dtype=float, device=d)
        wp.copy(self.mass_ext, m.particle_mass, 0, 0, ns)
        # the same masses with ghosts at zero: the force pass when ghosts must add no pressure force
        self.mass_force = wp.zeros(ns + capacity, dtype=float, device=d)
        wp.copy(self.mass_force, m.particle_mass, 0, 0, ns)
        self.ghost_of = wp.zeros(capacity, dtype=int, device=d)
        # persistent ghosts: keep flags, compaction scratch
        self.keep = wp.zeros(capacity, dtype=int, device=d)
        self._flag = wp.zeros(capacity, dtype=int, device=d)
        self._rank = wp.zeros(capacity, dtype=int, device=d)
        self._x_tmp = wp.zeros(capacity, dtype=wp.vec3, device=d)
        self._v_tmp = wp.zeros(capacity, dtype=wp.vec3, device=d)
        self._owner_tmp = wp.zeros(capacity, dtype=int, device=d)
        self.grid.reserve(ns + capacity)
        self.ghost_grid.reserve(capacity)

    # ------------------------------------------------------------------ sampling -------------
    def sample_ghosts(self, state: FluidState, dt: wp.array | None = None) -> int:
        """Free-surface detection and ghost seeding for the current positions (persistent: last
        step's ghosts moved with their owners, the ones that break the rules dropped, the holes
        filled). Leaves the hash grid built over fluid + boundary + ghosts. Returns the number of ghosts.
        ``dt`` (continuity density): the step's continuity rate is summed in the same pass over the
        neighbour lists as div x, and the density advanced by dt right after (step then skips its own
        continuity pass)."""
        m = self.model
        ns = m.n_total
        t0 = time.perf_counter() if self.profile else 0.0
        n_old = self.n_ghost if self.persistent else 0
        if n_old:
            # x_ext[:n_fluid] still holds the liquid positions of the last sampling
            # (the grid is still last step's, over these old positions)
            self._launch(gk.advect_ghosts, n_old, [self.grid.id, state.x, self.ghost_of, ns, m.params],
                         [self.x_ext])
        self._launch(gk.begin_sampling, ns, [state.x, state.v], [self.x_ext, self.v_ext, self.count])
        self.grid.build(self._x_view(0, ns + n_old), m.support_radius)
        # liquid and boundary neighbours from the neighbour lists (current: _update_lists ran first)
        if dt is not None:
            # div x and the continuity rate in one pass (same bits as the two passes), then rho advanced
            self._launch(gk.continuity_rate_and_divergence_list, m.n_fluid,
                         [self._nbr_count, self._nbr, self.grid.id, self.x_ext, state.v, state.rho, self.mass_ext,
                          m.params, ns, self.threshold],
                         [state.drho_dt, self.div, self.surface])
            self._launch(gk.advance_density_rate, m.n_fluid, [self._nbr_count, self._nbr, dt, m.params],
                         [state.drho_dt, state.rho, state.pressure, self._pr2])
        else:
            self._launch(gk.position_divergence_list, m.n_fluid,
                         [self._nbr_count, self._nbr, self.grid.id, self.x_ext, state.rho, self.mass_ext, m.params, ns,
                          self.threshold],
                         [self.div, self.surface])
        if n_old:
            self._launch(gk.keep_ghosts, n_old,
                         [self.grid.id, self.x_ext, m.n_fluid, ns, self.bg, m.params, self.keep_liquid,
                          self.keep_colour, self.keep_ghost],
                         [self.keep, self.count, self.v_ext, self.ghost_of])
        if self.shortcuts and not self._walls_closed:  # static walls: once (shortcuts: set before the first sampling)
            if m.n_boundary:
                wp.launch(gk.close_covered_cells, dim=m.n_boundary, inputs=[self.x_ext[m.n_fluid: ns], self.bg, 1],
                          outputs=[self.wall_closed], device=m.device)
            self._walls_closed = True
        while True:
            self._stamp += 1
            self._launch(gk.begin_round, self.n_phases, [n_old], [self.phase_count, self.count])
            # close the cells that no dart can pass before listing the active cells: wholly within
            # r_liquid of a liquid particle (the classification's "covered" test, done here by a
            # scatter over the liquid instead of a hash query per cell), and the kept ghosts' cells
            if self.shortcuts:
                self._launch(gk.close_covered_cells, m.n_fluid, [self.x_ext, self.bg, -self._stamp], [self.ghost_stamp])
            if n_old:
                self._launch(gk.close_kept_cells, n_old, [self.x_ext, self.keep, ns, self.bg, self._stamp],
                             [self.ghost_stamp])
            per_slice = self.mark_slices if m.device.is_cuda else 1  # CPU: a thread per particle
            self._launch(gk.mark_active_cells, (m.n_fluid, per_slice),
                         [self.x_ext, self.surface, self.bg, self._stamp, self.cell_mark, self.ghost_stamp,
                          self.wall_closed, self.phase_count, self.phase_list, self.phase_cap, self.tile, self.tile_k,
                          self.tile_row_first, self.tile_row_cells, self.mark_slices, per_slice])
            # Warp's CPU backend runs a launch in index order on one thread (phase_launches: the GPU's
            # launch pattern on the CPU too, for tests)
            serial = not m.device.is_cuda and not self.phase_launches
            parallel = m.device.is_cuda if self.parallel_darts is None else bool(self.parallel_darts)
            graph_ok = False
            if parallel:
                if m.device.is_cuda and self._last_counts is not None:
                    # CUDA: launch sizes from the last sampling's counts (read with the ghost count), x1.5 and
                    # a power of two (few distinct sizes: few graph captures); a thread takes every size-th
                    # cell of its phase, so a launch smaller than this sampling's count is still exact
                    last = 2 ** np.ceil(np.log2(1.5 * self._last_counts + 32))
                    counts = np.minimum(self.phase_bound, last).astype(int)
                    graph_ok = True
                elif self.phase_bound > self.parallel_bound_max:
                    counts = self.phase_count.numpy()  # (first sampling, large bound: one more host read)
                else:
                    counts = np.full(self.n_phases, self.phase_bound)  # threads past the count return
                    graph_ok = True
                if self.dart_launch_size:
                    counts = np.minimum(counts, self.dart_launch_size)
            elif serial or self.phase_bound > self.phase_bound_max:
                counts = self.phase_count.numpy()  # host read: launch over the active cells only
            else:
                # GPU: no host read; each phase launch covers the bound on its active cells, and
                # threads past phase_count[k] return at once
                counts = np.full(self.n_phases, self.phase_bound)
            if self.sampler is Sampler.TILE:
                # one launch over every phase's listed cells: the tile points are r apart already
                most = int(counts.max())
                if most:
                    self._launch(gk.tile_ghosts, (self.n_phases, most),
                                 [self.grid.id, self.x_ext, self.v_ext, m.n_fluid, ns, self.bg, m.params, self.phase_count,
                                  self.phase_list, self.phase_cap, self.tile, self.tile_k, self.count, self.capacity, most],
                                 [self.x_ext, self.v_ext, self.ghost_of])
            for rnd in range(self.rounds if self.sampler is Sampler.DARTS else 0):
                seed = self.seed + rnd
                if self.fresh_darts:
                    self._seed += 1
                    seed = self.seed + self._seed
                # one launch for all phases in turn (CPU), or one per phase (GPU), over the active cells only
                launches = [(0, self.n_phases, int(counts.max()))] if serial else [(k, 1, int(counts[k])) for k in range(self.n_phases)]
                if parallel:
                    self._parallel_darts(seed, counts, n_old, graph_ok)
                    continue
                for k, nph, ncell in launches:
                    if ncell == 0:
                        continue
                    wp.launch(gk.throw_darts, dim=(nph, ncell),
                              inputs=[self.grid.id, self.x_ext, self.v_ext, m.n_fluid, ns, self.bg, m.params, seed,
                                      self.attempts, self._stamp, self.cell_class, self.phase_count, self.phase_list,
                                      self.phase_cap, k, self.cell_ghost, self.ghost_stamp, self.count, self.capacity,
                                      self.keep, n_old, int(self.shortcuts)],
                              outputs=[self.x_ext, self.v_ext, self.ghost_of], device=m.device)
            read = self.count.numpy()
            n, dropped = int(read[0]), int(read[1])
            self._last_counts = read[2:].copy()
            if n <= self.capacity:
                if parallel and n > n_old and self.sampler is Sampler.DARTS:
                    # the new ghosts' velocity and owner: the nearest liquid particle
                    self._launch(gk.ghost_nearest_liquid, n - n_old,
                                 [self.grid.id, m.n_fluid, ns, self.bg, n_old],
                                 [self.x_ext, self.v_ext, self.ghost_of])
                break
            # more ghosts than slots: grow and sample again (rare; the buffers only grow)
            keep = [a for a in (self.x_ext, self.v_ext, self.ghost_of, self.keep)]
            self._alloc(int(1.5 * n) + 1024)
            wp.copy(self.x_ext, keep[0], 0, 0, ns + n_old)
            wp.copy(self.v_ext, keep[1], 0, 0, ns + n_old)
            if n_old:
                wp.copy(self.ghost_of, keep[2], 0, 0, n_old)
                wp.copy(self.keep, keep[3], 0, 0, n_old)
            self.grid.build(self.x_ext[: ns + n_old], m.support_radius)
        if dropped:
            # stable compaction: kept old ghosts first, then the new ones
            wp.launch(gk.ghost_flags, dim=n, inputs=[self.keep, n_old], outputs=[self._flag], device=m.device)
            wp.utils.array_scan(self._flag[:n], self._rank[:n], inclusive=False)
            wp.launch(gk.compact_ghosts, dim=n, inputs=[self._flag, self._rank, ns, self.x_ext, self.v_ext, self.ghost_of],
                      outputs=[self._x_tmp, self._v_tmp, self._owner_tmp], device=m.device)
            n -= dropped
            if n:
                wp.copy(self.x_ext, self._x_tmp, ns, 0, n)
                wp.copy(self.v_ext, self._v_tmp, ns, 0, n)
                wp.copy(self.ghost_of, self._owner_tmp, 0, 0, n)
        self.n_ghost = n
        # the ghosts alone in their own grid (self.grid stays the one over fluid + boundary [+ old ghosts])
        if n:
            self.ghost_grid.build(self._x_view(ns, ns + n), m.support_radius)
        if n:
            # ghost masses (number_density_mass) and the liquid particles with a ghost within H
            self._near_stamp += 1
            self._launch(gk.ghost_mass_split, n,
                         [self.grid.id, self.ghost_grid.id, self.x_ext, m.params, ns,
                          self._n_dev(n) if self.persistent else self.count,  # (count[0] = n without drops)
                          int(self.number_density_mass), self._near_stamp, self._near],
                         [self.mass_ext])
        if self.profile:
            wp.synchronize_device(m.device)
            self.sample_seconds += time.perf_counter() - t0
        return n

    def _x_view(self, lo: int, hi: int) -> wp.array:
        """x_ext[lo:hi], the view kept while the buffers and bounds stay (a new view costs the host ~30 µs)."""
        views = self._views
        key = (lo, hi)
        v = views.get(key)
        if v is None:
            if len(views) > 64:
                views.clear()
            v = views[key] = self.x_ext[lo:hi]
        return v

    def _parallel_darts(self, seed: int, counts: np.ndarray, n_old: int, graph_ok: bool = False) -> None:
        """One round of the parallel darts: screen every dart of every active cell against the liquid,
        walls, kept ghosts and the layer/colour rules, then per phase: the darts left against the new
        ghosts around each cell, and the first free one placed. ``counts``: launch size per phase (each
        thread takes every size-th active cell of its phase). The stamp and seed go to the device
        (``dart_ids``); the 1 + 2 x 3^d launches of the round are recorded once and replayed, and on
        CUDA, unless the sizes came from a read of this sampling's counts (``graph_ok``), replayed as one
        CUDA graph per set of sizes (``graph_darts``): a round is then one host call."""
        m = self.model
        most = int(counts.max())
        if most == 0:
            return
        self._launch(gk.set_dart_ids, 1, [self._stamp, seed], [self.dart_ids])
        if self.graph_darts and graph_ok and n_old == 0 and self.recorded_launches and m.device.is_cuda:
            key = (id(self.x_ext), self.capacity, self.attempts, tuple(counts.tolist()))
            graph = self._dart_graphs.get(key)
            if graph is None:
                # capture at a key's second use (the first runs plain: modules loaded, recorded commands built)
                if key not in self._dart_graph_warm:
                    self._dart_round(counts, n_old)
                    self._dart_graph_warm.add(key)
                    return
                if len(self._dart_graphs) >= 32:
                    self._dart_graphs.clear()
                wp.capture_begin(m.device, force_module_load=False)
                try:
                    self._dart_round(counts, n_old)
                finally:
                    graph = self._dart_graphs[key] = wp.capture_end(m.device)
            wp.capture_launch(graph)
            return
        self._dart_round(counts, n_old)

    def _dart_round(self, counts: np.ndarray, n_old: int) -> None:
        """The launches of one round of parallel darts (see _parallel_darts)."""
        m = self.model
        ns = m.n_total
        most = int(counts.max())
        self._launch(gk.dart_screen, (self.n_phases, most),
                     [self.grid.id, self.x_ext, m.n_fluid, ns, self.bg, m.params, self.dart_ids, self.attempts,
                      self.phase_count, self.phase_list, self.phase_cap, self.ghost_stamp, self.keep, n_old],
                     [self.dart_mask, most])
        cmds = self._phase_commands()
        # threads per cell: the cells (span 1) or rows of 5 cells (span 5) of the 5^d block around it
        span = self._conflict_span()
        rows = 5 ** m.dim // span
        for k in range(self.n_phases):
            n = int(counts[k])
            if n == 0:
                continue
            conflicts, place = cmds[k]
            if conflicts[1] != n:  # launch size n, and each thread takes every n-th cell (stride)
                conflicts[0].set_dim((n, rows))
                place[0].set_dim(n)
                conflicts[0].set_param_by_name("stride", n)
                place[0].set_param_by_name("stride", n)
                conflicts[1] = place[1] = n
            conflicts[0].launch()
            place[0].launch()

    def _conflict_span(self) -> int:
        return self.conflict_span or (1 if self.model.dim == 3 else 5)

    def _phase_commands(self):
        """Recorded [dart_conflicts, dim] and [place_darts, dim] launches per phase, for the current buffers."""
        key = (id(self.x_ext), self.capacity, self._conflict_span())
        if getattr(self, "_cmds_key", None) != key:
            m = self.model
            cmds = []
            for k in range(self.n_phases):
                conflicts = wp.launch(gk.dart_conflicts, dim=(1, 1),
                                      inputs=[self.bg, self.dart_ids, self.attempts, self.phase_count, self.phase_list,
                                              self.phase_cap, k, self.dart_mask, self.cell_ghost, self.ghost_stamp,
                                              self.x_ext],
                                      outputs=[self.dart_reject, self._conflict_span(), 1], device=m.device, record_cmd=True)
                place = wp.launch(gk.place_darts, dim=1,
                                  inputs=[self.bg, self.dart_ids, self.attempts, self.phase_count, self.phase_list,
                                          self.phase_cap, k, self.dart_mask, self.dart_reject, self.cell_ghost,
                                          self.ghost_stamp, self.count, self.capacity, m.n_total],
                                  outputs=[self.x_ext, 1], device=m.device, record_cmd=True)
                cmds.append(([conflicts, 1], [place, 1]))
            self._cmds, self._cmds_key = cmds, key
        return self._cmds

    @property
    def n_active(self) -> int:
        """Background cells active in the last sampling (a host read)."""
        return int(self.phase_count.numpy().sum())

    def _n_dev(self, n: int) -> wp.array:
        """A device scalar holding n (the ghost count for launches over the ghost slots)."""
        if getattr(self, "_n_ghost_arr", None) is None:
            self._n_ghost_arr = wp.zeros(1, dtype=int, device=self.model.device)
        self._n_ghost_arr.fill_(n)
        return self._n_ghost_arr

    # ------------------------------------------------------------------ solver interface -----
    def _update_lists(self, state: FluidState, force: bool = False) -> None:
        """FluidSolver's cell grid and Verlet neighbour lists (liquid and boundary neighbours within
        (1 + skin) H), rebuilt when a particle moved skin/2 since the last build (or ``force``)."""
        guard = self._always if force else self._list_guard(state)
        if guard is not None:
            self.build_cells(state, guard)
            self.build_neighbour_lists(state, guard)
            self._lists_built()

    def compute_density(self, state: FluidState, lists: bool = False) -> None:
        """Summation density with ghosts (initial state in summation mode)."""
        self._update_lists(state, force=not lists)
        self.sample_ghosts(state)
        self._summation_density(state)

    def _summation_density(self, state: FluidState) -> None:
        """Summation density over the neighbour lists (liquid and boundary, self included), then the
        ghosts' part (all of it, or capped at rho0: density_cap) from the ghost grid."""
        m = self.model
        self._launch(sph.particle_density_summation_list, m.n_fluid,
                     [self._nbr_count, self._nbr, state.x, m.particle_mass, m.params],
                     [state.rho, state.pressure, self._pr2])
        self._density_overflow(state, None, summation=True)
        self._ghost_density(state, self._zero_dt, 1 if self.density_cap else 0)

    def _ghost_density(self, state: FluidState, dt: wp.array, mode: int) -> None:
        m = self.model
        if self.n_ghost:
            self._launch(gk.ghost_density, m.n_fluid,
                         [self.ghost_grid.id, self.x_ext, self.v_ext, self.mass_ext, dt, m.params, m.n_total, mode,
                          self._near_stamp, self._near],
                         [state.drho_dt, state.rho, state.pressure, self._pr2])

    # FluidSolver.step's passes: the ghost step is the fluid step with three of them replaced or added (__init__)
    def _ghost_lists_pass(self, state: FluidState, dt: wp.array) -> None:
        """The liquid and boundary lists (never fused with the density: the ghosts come first)."""
        self._update_lists(state)

    def _ghost_density_pass(self, state: FluidState, dt: wp.array) -> None:
        """Ghost sampling, then the density over the lists plus the ghosts' part. Continuity: the rate over
        liquid and boundary is summed in sample_ghosts' div x pass (ghosts only with ghost_continuity, see
        __init__), the overflowed lists' rate here."""
        continuity = self.model.density is Density.CONTINUITY
        self.sample_ghosts(state, dt if continuity else None)
        if not continuity:
            self._summation_density(state)
        else:
            self._density_overflow(state, dt, summation=False)
            if self.ghost_continuity:
                self._ghost_density(state, dt, 2)

    def _ghost_pressure_pass(self, state: FluidState, dt: wp.array) -> None:
        """The ghosts' pressure term (they enter only through the liquid particle's own p_i/rho_i^2)."""
        m = self.model
        if self.n_ghost and self.ghost_pressure_term:
            self._launch(gk.ghost_pressure_force, m.n_fluid,
                         [self.ghost_grid.id, self.x_ext, self.mass_ext, self._pr2, m.params, m.n_total, self._near_stamp,
                          self._near],
                         [state.accel])

    # ------------------------------------------------------------------ checkpoint -----------
    def checkpoint_arrays(self) -> dict:
        """FluidSolver's, plus the ghosts of the last sampling (kept ones seed the next with persistent)."""
        out = super().checkpoint_arrays()
        ns, n = self.model.n_total, self.n_ghost
        if self.persistent and n:
            out.update(ghost_x=self.x_ext[: ns + n], ghost_v=self.v_ext[: ns + n], ghost_mass=self.mass_ext[: ns + n],
                       ghost_of=self.ghost_of[:n])
        return out

    def checkpoint_meta(self) -> dict:
        return {"n_ghost": self.n_ghost, "seed_counter": self._seed}

    def restore_checkpoint(self, state: FluidState, arrays: dict, meta: dict) -> None:
        super().restore_checkpoint(state, arrays, meta)
        self._seed = int(meta.get("seed_counter", 0))
        n = int(meta.get("n_ghost", 0))
        self.n_ghost = 0
        if self.persistent and n and "ghost_x" in arrays:
            ns = self.model.n_total
            if n > self.capacity:
                self._alloc(int(1.5 * n) + 1024)
            d = self.model.device
            wp.copy(self.x_ext, wp.array(arrays["ghost_x"], dtype=wp.vec3, device=d), 0, 0, ns + n)
            wp.copy(self.v_ext, wp.array(arrays["ghost_v"], dtype=wp.vec3, device=d), 0, 0, ns + n)
            wp.copy(self.mass_ext, wp.array(arrays["ghost_mass"], dtype=float, device=d), 0, 0, ns + n)
            wp.copy(self.ghost_of, wp.array(arrays["ghost_of"], dtype=int, device=d), 0, 0, n)
            # the grid the next sampling moves the kept ghosts with: over the liquid and ghosts of the last one
            self.grid.build(self._x_view(0, ns + n), self.model.support_radius)
            self.n_ghost = n

    # ------------------------------------------------------------------ reading --------------
    def ghost_positions(self) -> np.ndarray:
        """Positions of the ghosts of the last sampling, (n_ghost, 3) [m]."""
        ns = self.model.n_total
        return self.x_ext.numpy()[ns: ns + self.n_ghost].astype(np.float64)

    def ghost_velocities(self) -> np.ndarray:
        ns = self.model.n_total
        return self.v_ext.numpy()[ns: ns + self.n_ghost].astype(np.float64)

    def surface_flags(self) -> np.ndarray:
        return self.surface.numpy().astype(bool)

    def divergence(self) -> np.ndarray:
        return self.div.numpy().astype(np.float64)
