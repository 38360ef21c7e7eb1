"""Weakly compressible SPH: static :class:`FluidModel`, per-step :class:`FluidState`, and
:class:`FluidSolver`, which orders the kernel launches of one fluid step.

Particle arrays hold the fluid particles first and the static boundary particles (walls,
obstacles; Akinci et al. 2012) after them, so one ``wp.HashGrid`` serves both.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, replace
from types import SimpleNamespace
from typing import ClassVar

import numpy as np
import warp as wp

from rockwave.base.solver import TimeStep
from rockwave.kernels.sph import diffusion, gather, shifting, wall_work
from rockwave.kernels.sph import fluid as sph


class Density(enum.IntEnum):
    """How the fluid density is found each step (``fluid.density``), chosen once at build time."""

    SUMMATION = sph.DENSITY_SUMMATION  # rho_i = sum_j m_j W_ij
    CONTINUITY = sph.DENSITY_CONTINUITY  # d rho_i / dt = sum_j m_j (v_i - v_j) . grad W_ij


@dataclass
class FluidOptions:
    """Tuning of the fluid solver (Python API: ``Simulation(scene, options=SimulationOptions(fluid=...))``,
    ``FluidSolver(model, options=...)``). The defaults are measured (docs/notes.md); none changes the physics, only
    the cost (but cfl_number, the adaptive step's Courant number)."""

    DEFAULT_CFL_NUMBER: ClassVar[float] = 0.6
    """The Courant number when cfl_number is None and no scene gives one [-] (the default of the scene's
    ``simulation.cfl_number``: rockwave/scene/format.py takes it from here)."""

    neighbour_skin: float = 0.05
    """Verlet-list skin as a fraction of the support radius H [-]; the list holds pairs within (1 + skin) H and is
    kept until a displacement check fails (0: rebuilt every step). 0.05: a 3D dam break keeps a list ~3 steps, CPU
    step 19.6 -> 14.0 ms at 10.9k particles."""

    skin_check: str = "relative"
    """"relative" (rebuild when two particles that may have become neighbours moved skin H relative to each other;
    cells of 2H by build position) or "absolute" (any particle moved skin H/2)."""

    reorder_interval: int | None = None
    """Steps between sorts of the fluid particles by cell on a GPU and in step_many [steps] (0: never; None: 10, or
    0 for Ghost SPH, whose grid also holds the ghosts)."""

    recorded_launches: bool | None = None
    """Record the per-step launches once and replay them (None: on for Ghost SPH, whose step cannot be a CUDA
    graph; the basic step is replayed as a CUDA graph instead)."""

    fused_density: bool | None = None
    """Build the neighbour list and the density in one pass (None: on the CPU, where it saves a traversal, 17.1 vs
    19.8 ms/step at 10k particles; off on CUDA, 2.16 ms fused vs 1.03 + 0.55 ms apart on an H100 at 2.16 M
    particles)."""

    conditional_rebuild: bool = True
    """In a CUDA graph, the list rebuild is a conditional node on the device flag."""

    cell_ratio: float = 1.0
    """Hash-grid cell width / H [-]."""

    cell_subdivision_x: int = 4
    """The list cell grid's x-cells are H/n wide [-]."""

    cell_span: int = 1
    """The cell grid's y and z cells are R/n wide (R the list radius) and a query visits the (2n + 1)^2 columns
    around a particle's (2n + 1 in 2D) [-]. 1: 9 columns, candidates ~3.5x the sphere of R (3.8x the neighbours
    within H at support 3); 2: 25 columns, ~2.2x (Monte Carlo over the particle's place in its cell). Measured on the
    CPU (3D dam break, 10,850 particles, standard): 2 is slower, 157 vs 131 ms/step with lists and 205 vs 170 with
    the cell gather (the runs' setup outweighs the candidates saved); a GPU may differ
    (benchmarks/neighbour_gather.py --cell-span)."""

    min_cells: int = 1 << 20
    """The list cell grid wraps past max(min_cells, cells_per_particle x particles) cells [cells]."""

    cells_per_particle: int = 4
    """See min_cells [cells per particle]."""

    check_cells_per_particle: int = 4
    """The relative skin check falls back to "absolute" past this many cells a particle [cells per particle]."""

    relative_min_particles_cuda: int = 250_000
    """On a GPU the relative check starts at this many particles [particles] (below, its 5 extra launches cost more
    than the builds they save: H100, 3,600 particles, 0.46 -> 0.69 ms/step)."""

    cfl_number: float | None = None
    """Courant number C of the adaptive step, dt <= C h/(c0 + u_max) [-] (None: the scene's ``simulation.cfl_number``
    when built from a scene, else DEFAULT_CFL_NUMBER)."""

    DEFAULT_NEIGHBOURS: ClassVar[str] = "lists"
    """The neighbour search when neighbours is None and no scene gives one (the default of the scene's
    ``fluid.neighbours``: rockwave/scene/format.py takes it from here)."""

    NEIGHBOURS: ClassVar[tuple[str, ...]] = ("lists", "cells")

    neighbours: str | None = None
    """How the fluid passes find their neighbours: "lists" (a Verlet list of the pairs within (1 + skin) H, built when
    the skin check says so, read by every pass) or "cells" (no stored list: each pass gathers from the sorted cell
    grid that the list path builds, kernels/sph/gather.py; the same pairs in the same order, 4 B x list_capacity
    less per particle). None: the scene's ``fluid.neighbours`` when built from a scene, else DEFAULT_NEIGHBOURS."""

    gather_prefilter: bool = False
    """With neighbours = "cells": keep the slot-ordered positions of the last build (12 B per particle, walls
    included, as the lists have) and test each candidate's build position against R first, as the list build does,
    before reading its current position (kernels/sph/gather.py candidate). The same pairs either way."""

    def __post_init__(self):
        if self.neighbours is not None and self.neighbours not in self.NEIGHBOURS:
            raise ValueError(f"FluidOptions.neighbours = {self.neighbours!r}: expected 'lists' or 'cells'")
        if self.skin_check not in ("relative", "absolute"):
            raise ValueError(f"FluidOptions.skin_check = {self.skin_check!r}: expected 'relative' or 'absolute'")
        if self.neighbour_skin < 0:
            raise ValueError(f"FluidOptions.neighbour_skin = {self.neighbour_skin}: must be >= 0")
        if self.cell_span < 1:
            raise ValueError(f"FluidOptions.cell_span = {self.cell_span}: must be >= 1")


@dataclass(frozen=True)
class FluidParameters:
    """The fluid's physical formulation, typed, SI units in the names: what ``make_params`` and
    ``build_fluid_model`` are made from (a scene's [fluid] section becomes one in rockwave/build/options.py
    fluid_parameters; the scene format documents each choice)."""

    spacing_m: float
    """Initial particle spacing dx [m]."""

    rest_density_kg_m3: float
    """Rest density rho0 [kg/m^3]."""

    kernel: str
    """Smoothing kernel: "muller", "cubic_spline" or "wendland"."""

    support_radius_ratio: float
    """Kernel support radius H / spacing [-] (support_radius)."""

    eos_type: str
    """Equation of state: "tait" (p = B ((rho/rho0)^gamma - 1)) or "linear" (p = k (rho - rho0))."""

    eos_gamma: float
    """Tait exponent gamma [-]."""

    eos_speed_of_sound_m_s: float | None
    """Speed of sound c0 [m/s], or None when the constant (eos_b_pa or eos_k_m2_s2) is given instead."""

    eos_b_pa: float | None
    """Tait stiffness B [Pa], or None (from c0: B = c0^2 rho0 / gamma)."""

    eos_k_m2_s2: float | None
    """Linear stiffness k [m^2/s^2] (Pa per kg/m^3), or None (from c0: k = c0^2)."""

    clamp_negative_pressure: bool
    """Clip p < 0 to 0."""

    density_floor: bool
    """Keep the continuity density at rho0 or above (kernels/sph/fluid.py continuity_floor)."""

    pressure_force: str
    """"momentum" (p_i/rho_i^2 + p_j/rho_j^2) or "muller" ((p_i + p_j)/(2 rho_j)) pressure force."""

    laplacian_viscosity_pa_s: float
    """Dynamic viscosity mu of the Laplacian viscosity [Pa s]."""

    artificial_alpha: float
    """Monaghan artificial viscosity alpha [-]."""

    xsph_epsilon: float
    """XSPH velocity smoothing epsilon [-]."""

    boundary: str
    """Walls: "adami" (extrapolated wall pressure) or "akinci" (frozen particles, -Psi_b p_i/rho_i^2 grad W)."""

    wall_slip: str
    """Adami walls: "free" or "no_slip"."""

    gradient_correction: bool
    """Kernel-gradient correction in the continuity and pressure terms (kernels/sph/fluid.py
    gradient_correction_matrix)."""

    wall_volume: str
    """Adami walls: "mass" (a wall particle pushes with its mass) or "geometric" (it keeps its volume)."""

    density: Density
    """Summation or continuity density."""

    density_diffusion: float
    """delta of the delta-SPH density diffusion [-] (0: off; kernels/sph/diffusion.py)."""

    particle_shifting: float = 0.0
    """K of the particle shifting [-] (0: off; kernels/sph/shifting.py)."""

    density_diffusion_form: str = "hydrostatic"
    """"hydrostatic" (the continuity density diffused, hydrostatic part removed (Fourtakas et al. 2019), Adami walls
    in the sum) or "pressure" (the same for the density of the pressure, max(rho, rho0) with clipped negative
    pressure; kernels/sph/diffusion.py)."""

    density_diffusion_renormalised: bool = False
    """Antuono et al. (2010)'s form: the renormalised density gradients taken out of the diffusion's difference
    (kernels/sph/diffusion.py)."""

    wall_work: bool = False
    """Adami walls with continuity density: the work of the walls' extrapolated pressure paid by the fluid particles
    that set it (kernels/sph/wall_work.py). Opt-in: it stops a landing under water from creating energy, and damps
    sloshing more (docs/physics.md 'Walls')."""

    @property
    def support_radius_m(self) -> float:
        """Kernel support radius H [m] (support_radius)."""
        return support_radius(self.spacing_m, self.support_radius_ratio)


def support_radius(spacing_m: float, support_radius_ratio: float) -> float:
    """Kernel support radius H = support_radius_ratio x spacing [m]: the one formula every caller uses (the SPH
    parameters, the boundary lattice, preflight, the guard, the scene's gauge checks)."""
    return support_radius_ratio * spacing_m


# weakly compressible SPH wants c0 >= SOUND_SPEED_FACTOR x the fastest flow speed (density variations ~1%)
SOUND_SPEED_FACTOR = 10.0


def expected_flow_speed(gravity_m_s2: float, water_height_m: float, initial_speed_m_s: float = 0.0) -> float:
    """Expected largest flow speed u_max ~ sqrt(2 |g| H) + the fastest initial speed [m/s] (H: the water's height):
    the speed of sound's yardstick in preflight (rockwave/build/preflight.py) and the blow-up guard
    (rockwave/sim/guard.py)."""
    return math.sqrt(2.0 * gravity_m_s2 * water_height_m) + initial_speed_m_s


def wall_layers(support_radius_m: float, boundary_spacing_m: float) -> int:
    """Boundary particle layers of spacing boundary_spacing_m that cover the kernel support H (at least one)."""
    return max(1, int(math.ceil(support_radius_m / boundary_spacing_m - 1e-9)))


def walls_cover_support(layers: int, boundary_spacing_m: float, support_radius_m: float) -> bool:
    """Do ``layers`` boundary layers of spacing boundary_spacing_m cover the kernel support H (within 0.1%)? Adami
    walls need it; build_fluid_model calibrates such walls' masses on the lattice (else Akinci's Psi_b)."""
    return layers * boundary_spacing_m >= 0.999 * support_radius_m


def sound_speed_from_eos(fp: FluidParameters) -> float:
    """c0 [m/s] from the EOS constants: Tait c0^2 = gamma B / rho0; linear c0^2 = k."""
    if fp.eos_speed_of_sound_m_s is not None:
        return float(fp.eos_speed_of_sound_m_s)
    if fp.eos_type == "tait":
        return math.sqrt(fp.eos_gamma * fp.eos_b_pa / fp.rest_density_kg_m3)
    return math.sqrt(fp.eos_k_m2_s2)


def eos_constant(fp: FluidParameters) -> float:
    """Tait B = c0^2 rho0 / gamma (Pa) or linear k = c0^2 (m^2/s^2)."""
    if fp.eos_type == "tait":
        if fp.eos_b_pa is not None:
            return float(fp.eos_b_pa)
        return fp.eos_speed_of_sound_m_s ** 2 * fp.rest_density_kg_m3 / fp.eos_gamma
    if fp.eos_k_m2_s2 is not None:
        return float(fp.eos_k_m2_s2)
    return fp.eos_speed_of_sound_m_s ** 2


@dataclass
class FluidModel:
    """Static fluid data (build_fluid_model). Particle arrays hold the fluid particles first, then the boundary
    particles (static ones, then the wall particles of moving blocks)."""

    dim: int
    """Dimensions, 2 or 3."""

    up: int
    """Index of the vertical axis (1 in 2D, 2 in 3D)."""

    n_fluid: int
    """Fluid particles."""

    n_boundary: int
    """Boundary particles (static walls, obstacles and fixed blocks, then n_moving_walls)."""

    spacing: float
    """Initial fluid particle spacing dx [m]."""

    support_radius: float
    """Kernel support radius H [m] (support_radius; params.H)."""

    particle_mass: wp.array
    """wp.array(float32, n_fluid + n_boundary): fluid particle mass [kg], or the boundary particle's Psi_b [kg]."""

    params: sph.SPHParams
    """The kernels' parameters (kernels/sph/fluid.py SPHParams, float32 fields), passed to every kernel."""

    sound_speed: float
    """Speed of sound c0 [m/s]."""

    kinematic_viscosity: float
    """Laplacian viscosity mu / rho0 [m^2/s]."""

    density: Density
    """Summation or continuity density, chosen once (FluidParameters.density)."""

    domain_lo: np.ndarray
    """float64 (3,): lower corner of the box of all particles grown by H [m]."""

    domain_hi: np.ndarray
    """float64 (3,): upper corner of that box [m]."""

    initial_positions: np.ndarray
    """float64 (n_fluid + n_boundary, 3): positions at the start [m] (z = 0 in 2D)."""

    initial_velocities: np.ndarray
    """float64 (n_fluid + n_boundary, 3): velocities at the start [m/s] (boundary rows zero)."""

    device: wp.context.Device
    """The Warp device of every array."""

    density_diffusion: float = 0.0
    """delta of the delta-SPH density diffusion [-] (kernels/sph/diffusion.py); 0: off."""

    boundary_spacing: float = 0.0
    """Boundary particle lattice spacing [m]; 0: the fluid spacing (or no boundary)."""

    n_moving_walls: int = 0
    """The last n_moving_walls boundary particles are the wall particles of moving blocks
    (rockwave/coupling/walls.py BlockWalls places them each step); the others are static."""

    particle_shifting: float = 0.0
    """K of the particle shifting [-] (kernels/sph/shifting.py); 0: off."""

    density_diffusion_form: str = "hydrostatic"
    """FluidParameters.density_diffusion_form: "hydrostatic" or "pressure" (kernels/sph/diffusion.py)."""

    density_diffusion_renormalised: bool = False
    """FluidParameters.density_diffusion_renormalised (kernels/sph/diffusion.py)."""

    wall_work: bool = False
    """FluidParameters.wall_work (kernels/sph/wall_work.py)."""

    @property
    def n_static_boundary(self) -> int:
        """Boundary particles that never move (tank, obstacles, fixed blocks)."""
        return self.n_boundary - self.n_moving_walls

    @property
    def density_mode(self) -> str:
        """"summation" or "continuity" (the scene's word for ``density``)."""
        return self.density.name.lower()

    @property
    def n_total(self) -> int:
        return self.n_fluid + self.n_boundary

    @property
    def fluid_mass(self) -> float:
        return float(self.particle_mass.numpy()[0]) if self.n_fluid else 0.0

    def state(self) -> "FluidState":
        """Allocate a state holding the initial positions and velocities."""
        d = self.device
        nf = self.n_fluid
        x = wp.array(self.initial_positions.astype(np.float32), dtype=wp.vec3, device=d)
        v = wp.array(self.initial_velocities.astype(np.float32), dtype=wp.vec3, device=d)
        rest = np.full(nf, self.params.rest_density, dtype=np.float32)
        return FluidState(
            x=x,
            v=v,
            rho=wp.array(rest, dtype=float, device=d),
            pressure=wp.zeros(nf, dtype=float, device=d),
            accel=wp.zeros(nf, dtype=wp.vec3, device=d),
            xsph_dv=wp.zeros(nf, dtype=wp.vec3, device=d),
            drho_dt=wp.zeros(nf, dtype=float, device=d),
            ids=wp.array(np.arange(nf, dtype=np.int32), dtype=int, device=d),
            wall_pressure=wp.zeros(max(self.n_boundary, 1), dtype=float, device=d),
            wall_velocity=wp.zeros(max(self.n_boundary, 1), dtype=wp.vec3, device=d),
        )


@dataclass
class FluidState:
    """Arrays that change each step (device arrays of the model's device; fluid particles first, then boundary).
    FluidSolver.reorder sorts the fluid by cell (ids keeps each slot's original index); FluidSolver.unsort restores
    ids = 0..n_fluid-1."""

    x: wp.array
    """wp.array(vec3 float32, n_fluid + n_boundary): positions [m]."""

    v: wp.array
    """wp.array(vec3 float32, n_fluid + n_boundary): velocities [m/s] (static boundary entries zero)."""

    rho: wp.array
    """wp.array(float32, n_fluid): densities [kg/m^3]."""

    pressure: wp.array
    """wp.array(float32, n_fluid): pressures [Pa]."""

    accel: wp.array
    """wp.array(vec3 float32, n_fluid): accelerations of the last step [m/s^2]."""

    xsph_dv: wp.array
    """wp.array(vec3 float32, n_fluid): XSPH velocity corrections of the last step [m/s]."""

    drho_dt: wp.array
    """wp.array(float32, n_fluid): continuity density rate of the last step [kg/m^3/s]."""

    ids: wp.array
    """wp.array(int32, n_fluid): original index of the fluid particle stored at each slot."""

    wall_pressure: wp.array
    """wp.array(float32, max(n_boundary, 1)): with Adami walls the pressure of each boundary particle, extrapolated
    from the fluid in each step [Pa] (0 with Akinci walls)."""

    wall_velocity: wp.array
    """wp.array(vec3 float32, max(n_boundary, 1)): Adami no-slip walls: the extrapolated wall velocity of the viscous
    terms [m/s]."""


def make_params(fp: FluidParameters, dim: int, gravity, n_fluid: int) -> sph.SPHParams:
    """The kernels' parameters (kernels/sph/fluid.py SPHParams) of the formulation ``fp`` in ``dim`` dimensions,
    gravity [m/s^2] (dim components), n_fluid fluid particles; the lattice calibration (fluid_mass, grad_scale)
    is build_fluid_model's."""
    rho0 = fp.rest_density_kg_m3
    p = sph.SPHParams()
    p.dim = dim
    p.kernel = {"muller": 0, "cubic_spline": 1, "wendland": 2}[fp.kernel]
    p.H = support_radius(fp.spacing_m, fp.support_radius_ratio)
    p.rest_density = rho0
    p.eos = 0 if fp.eos_type == "tait" else 1
    p.eos_b = eos_constant(fp)
    p.eos_gamma = fp.eos_gamma
    p.clamp_negative = 1 if fp.clamp_negative_pressure else 0
    # the continuity density's floor at rho0 (kernels/sph/fluid.py continuity_floor); the loader refuses it with Ghost SPH,
    # summation density or unclipped pressure (rockwave/scene/format.py _check_method_options)
    p.density_floor = 1 if fp.density_floor else 0
    p.pressure_form = 0 if fp.pressure_force == "momentum" else 1
    p.sound_speed = sound_speed_from_eos(fp)
    p.mu = fp.laplacian_viscosity_pa_s
    p.alpha = fp.artificial_alpha
    p.xsph = fp.xsph_epsilon
    g = list(gravity) + [0.0] * (3 - len(gravity))
    p.gravity = wp.vec3(*g)
    p.n_fluid = n_fluid
    p.boundary = sph.BOUNDARY_ADAMI if fp.boundary == "adami" else sph.BOUNDARY_AKINCI
    p.no_slip = 1 if fp.wall_slip == "no_slip" else 0
    p.gradient_correction = 1 if fp.gradient_correction else 0
    p.wall_volume = 1 if fp.wall_volume == "geometric" else 0
    p.grad_scale = 1.0
    p.fluid_mass = 0.0  # set by build_fluid_model (calibrated)
    set_kernel_constants(p)
    return p


def set_kernel_constants(p: sph.SPHParams) -> None:
    """Mueller kernel constants for p.H and p.dim (kernels/sph/fluid.py kernel_w, spiky_grad, kernel_laplacian)."""
    H = float(p.H)
    if p.dim == 3:
        p.w_coef = 315.0 / (64.0 * math.pi * H ** 9)
        p.grad_coef = 45.0 / (math.pi * H ** 6)
        p.lap_coef = 45.0 / (math.pi * H ** 6)
    else:
        p.w_coef = 4.0 / (math.pi * H ** 8)
        p.grad_coef = 30.0 / (math.pi * H ** 5)
        p.lap_coef = 40.0 / (math.pi * H ** 5)


def _grid_dims(lo: np.ndarray, hi: np.ndarray, cell: float, dim: int) -> tuple[int, int, int]:
    """Hash-grid dimensions covering the domain (cells hash modulo dims), capped for memory."""
    n = np.ceil((hi - lo) / cell).astype(int) + 2
    n = np.clip(n, 1, 1024)
    if dim == 2:
        n[2] = 1
    while int(np.prod(n)) > 64_000_000:
        n = np.maximum(n // 2, 1)
    return int(n[0]), int(n[1]), int(n[2])


class FluidSolver:
    """Advances a :class:`FluidState` by one step: neighbour grid, density + EOS, forces,
    semi-implicit Euler. Each call launches a fixed set of kernels and never reads back to the
    host, so the step can be captured in a CUDA graph.

    Particle order: ``reorder`` (Simulation runs it every ``reorder_interval`` steps in step_many and
    in advance on a GPU) sorts
    the fluid particles by cell so that neighbour reads are coherent; boundary
    particles stay after them (build_fluid_model sorts them once). ``state.ids`` keeps each slot's
    original index and ``unsort`` restores the original order (Simulation does it before any read).

    Neighbour skin (Verlet list): with ``neighbour_skin`` = s > 0 the list holds the pairs within
    R = (1 + s) H and is kept over several steps; the density and force passes skip its pairs at
    r >= H. Each step kernels compare every fluid position with the one stored at the build and set a
    device flag when two particles that may have become neighbours moved s H or more relative to each
    other (``skin_check`` "relative": displacement boxes per 2H cell of build position, adjacent cells
    compared, static boundary particles at rest, the wall particles of moving blocks checked as the fluid's; also when one moved H/2) or, with "absolute", when any moved
    s H / 2 (either way every pair now closer than H was closer than R at the build). The cell-grid kernels and the list build run every step and return at once while the
    flag is clear, so no host read is needed (CUDA graphs); on the CPU the host reads the flag and skips
    the launches (and the radix sort). The check compares positions slot by slot, so it covers every
    change of x (the coupling's corrections, checkpoint restores, assignments); reorder and unsort set
    the flag as well (they permute the slots and reorder rebuilds the grid), and so does a checkpoint
    capture or restore (rockwave/sim/checkpoint.py: a resumed run rebuilds where the running one does, so a
    resume stays bit-identical). s = 0: rebuild every step."""

    def __init__(self, model: FluidModel, options: FluidOptions | None = None, neighbour_skin: float | None = None,
                 list_capacity: int | None = None):
        """``list_capacity``: neighbour slots per particle (None: from the lattice, _init_lists); a solver that
        only holds a state for reading (rank 0's whole water in a distributed run) takes 1."""
        o = options or FluidOptions()
        if neighbour_skin is not None:
            o = replace(o, neighbour_skin=float(neighbour_skin))
        self.options = o
        self._recorded = {}  # _launch: recorded launches by kernel and argument arrays
        self.model = model
        d = model.device
        is_cuda = wp.get_device(d).is_cuda
        self.neighbour_skin = float(o.neighbour_skin)
        self.reorder_interval = self.default_reorder_interval if o.reorder_interval is None else int(o.reorder_interval)
        self.recorded_launches = self.default_recorded_launches if o.recorded_launches is None else bool(o.recorded_launches)
        # fluid.neighbours = 'cells': no stored list, each pass gathers from the cell grid (kernels/sph/gather.py)
        self.cell_gather = (o.neighbours or FluidOptions.DEFAULT_NEIGHBOURS) == "cells"
        if self.cell_gather and model.wall_work:  # a scene gets a SceneError (scene/format.py)
            raise ValueError("wall_work needs neighbours = 'lists': its pass reads the neighbour list")
        if self.cell_gather and model.density_diffusion_renormalised:  # a scene gets a SceneError (scene/format.py)
            raise ValueError("density_diffusion_renormalised needs neighbours = 'lists': its gradient pass reads the "
                             "neighbour list")
        self.fused_density = (not is_cuda) if o.fused_density is None else bool(o.fused_density)
        self.fused_density = self.fused_density and not self.cell_gather
        self.cell_span = int(o.cell_span)
        self.gather_prefilter = self.cell_gather and bool(o.gather_prefilter)
        self._slot_positions = not self.cell_gather or self.gather_prefilter  # cells.x_sorted kept
        self.cfl_number = FluidOptions.DEFAULT_CFL_NUMBER if o.cfl_number is None else float(o.cfl_number)
        self.skin_check = o.skin_check
        self.conditional_rebuild = o.conditional_rebuild
        self.cell = model.support_radius * o.cell_ratio
        dims = _grid_dims(model.domain_lo, model.domain_hi, self.cell, model.dim)
        self.grid = wp.HashGrid(*dims, device=d)
        self.grid_dims = dims
        self.grid.reserve(model.n_total)
        self._extrema = wp.zeros(2, dtype=float, device=d)
        self._in_original_order = True  # False after a reorder, until unsort
        self._order_buf = None
        self._always = wp.ones(1, dtype=int, device=d)  # the rebuild flag of unconditional builds
        self._rebuild = wp.ones(1, dtype=int, device=d)  # 1: the list must be rebuilt this step
        self.host_decides = not is_cuda  # CPU: read the flag, skip the launches
        self.list_builds = 0  # host-decided builds (CPU), for tests and measurements
        nf = max(model.n_fluid, 1)
        self._pr2 = wp.zeros(nf, dtype=float, device=d)  # p / rho^2 of this step (kernels/sph/fluid.py pair_acceleration_fluid)
        self._wall_pr2 = wp.zeros(max(model.n_boundary, 1), dtype=wp.vec2, device=d)  # (p_b / rho_b^2, rho_b / rho0) (Adami walls)
        self._zero_dt = wp.zeros(1, dtype=float, device=d)
        # fluid.gradient_correction: L_i of every fluid particle, computed each step after the lists
        # (kernels/sph/fluid.py gradient_correction_matrix); a one-entry placeholder without it
        self.kgc = wp.zeros(nf if model.params.gradient_correction else 1, dtype=wp.mat33, device=d)
        # wall particles of moving blocks (rockwave/coupling/walls.py BlockWalls): their acceleration a_b (Adami 2012
        # eq. 27, written by the coupling each step; zero for static walls) and their positions at the last list
        # build (_xq: the cell queries of the wall pressure start there; static walls: their own positions)
        self.wall_accel = wp.zeros(max(model.n_boundary, 1), dtype=wp.vec3, device=d)
        self._wall_rate = wp.zeros(max(model.n_boundary, 1), dtype=float, device=d)  # kernels/sph/wall_work.py
        self._xq = None
        if model.n_moving_walls:
            xb = np.asarray(model.initial_positions, float)[model.n_fluid: model.n_total]
            self._xq = wp.array(xb.astype(np.float32), dtype=wp.vec3, device=d)
        self.passes = self._default_passes()  # the step: an ordered list of named passes (FluidSolver.step)
        self._block_dim = 128 if is_cuda else 256  # force pass: 0.84 vs 0.91 ms at 256 (H100, 2.16 M)
        self._init_lists(list_capacity)

    default_reorder_interval = 10  # FluidOptions.reorder_interval = None
    default_recorded_launches = False  # FluidOptions.recorded_launches = None
    capturable = True  # a step is launches only: a chunk of steps can be one CUDA graph

    @property
    def sorted_by_cell(self) -> bool:
        """True while the fluid particles are in cell order (after reorder; state.ids gives the seeded order)."""
        return not self._in_original_order

    def set_list_capacity(self, capacity: int) -> None:
        """Neighbour slots per particle (fewer than the neighbours: the rest come from the cell query of the
        overflow passes); the lists are rebuilt at the next step."""
        self._init_lists(capacity)

    def set_neighbour_skin(self, skin: float) -> None:
        """Change the skin (fraction of H): reallocates the lists and the cell grid; the next step rebuilds."""
        self.neighbour_skin = float(skin)
        self._init_lists()

    def _init_lists(self, capacity: int | None = None) -> None:
        """Neighbour lists (kernels/sph/fluid.py build_neighbour_list_cells): count[i] and nbr[k * n_fluid + i]
        for k < cap; cap ~1.6x the neighbours within the list radius in the initial lattice (or ``capacity``)."""
        m, d = self.model, self.model.device
        if self.neighbour_skin < 0:
            raise ValueError(f"neighbour_skin {self.neighbour_skin} < 0")
        self.list_radius = m.support_radius * (1.0 + self.neighbour_skin)
        self.neighbour_cap = self.list_capacity(m, self.neighbour_skin) if capacity is None else int(capacity)
        nf = max(m.n_fluid, 1)
        if self.cell_gather:  # no list: one-entry placeholders (the passes gather from the cell grid)
            self.neighbour_cap = 0
            self._nbr_count = wp.zeros(1, dtype=int, device=d)
            self._nbr = wp.zeros(1, dtype=int, device=d)
        else:
            self._nbr_count = wp.zeros(nf, dtype=int, device=d)
            self._nbr = wp.zeros(nf * self.neighbour_cap, dtype=int, device=d)
        self._x_build = wp.zeros(nf, dtype=wp.vec3, device=d)
        self._rebuild.fill_(1)
        self.arrays_version = getattr(self, "arrays_version", 0) + 1  # captured graphs of older arrays are stale
        self._init_cells()
        self._init_check_grid()

    # The skin check (class doc): "relative" rebuilds a list when two particles that may have become
    # neighbours moved s H relative to each other (cells of 2 H by build position, kernels/sph/fluid.py
    # displacement_check_cells); "absolute" when any particle moved s H / 2. In a flowing 3D dam break
    # the water moves together: a list then lasts ~9x longer (10,850 particles, 0.3 s: 37 builds with an
    # exact test, 331 with "absolute"). "relative" falls back to "absolute" past check_cells_per_particle.

    def _init_check_grid(self) -> None:
        m, d = self.model, self.model.device
        self._check = None
        if self.skin_check != "relative" or self.neighbour_skin <= 0 or m.n_fluid == 0:
            return
        if m.device.is_cuda and m.n_fluid < self.options.relative_min_particles_cuda:
            return
        c = 2.0 * m.support_radius
        lo = np.asarray(m.domain_lo, float) - c
        dims = np.maximum(np.ceil((np.asarray(m.domain_hi, float) + c - lo) / c).astype(np.int64), 1)
        if m.dim == 2:
            dims[2] = 1
        n_cells = int(np.prod(dims))
        if n_cells > self.options.check_cells_per_particle * m.n_fluid + 4096:
            return
        g = sph.CheckGrid()
        g.lo = wp.vec3(*[float(a) for a in lo])
        g.inv_c = 1.0 / c
        g.nx, g.ny, g.nz = (int(a) for a in dims)
        self._check = g
        self._check_width = c
        self._d_lo = wp.zeros(n_cells, dtype=wp.vec3, device=d)
        self._d_hi = wp.zeros(n_cells, dtype=wp.vec3, device=d)
        self._overflowed = wp.ones(1, dtype=int, device=d)
        self._moved = wp.zeros(1, dtype=int, device=d)  # a particle moved s H / 2 since the build
        # cells holding boundary particles (static): their displacement boxes include d = 0
        wall = np.zeros(n_cells, np.int32)
        if m.n_static_boundary:  # (the wall particles of moving blocks enter the boxes as the fluid does)
            xb = np.asarray(m.initial_positions, float)[m.n_fluid: m.n_fluid + m.n_static_boundary].reshape(-1, 3)
            idx = np.clip(np.floor((xb - lo) / c).astype(np.int64), 0, dims - 1)
            wall[idx[:, 0] + dims[0] * (idx[:, 1] + dims[1] * idx[:, 2])] = 1
        self._wall_cells = wp.array(wall, dtype=int, device=d)

    def _init_cells(self) -> None:
        """The cell grid of the neighbour lists: dimensions covering the domain (+2R, R the list radius),
        wrapped (hashed) when that would exceed max(min_cells, cells_per_particle x particles) cells."""
        m, d = self.model, self.model.device
        H = self.list_radius
        span = self.cell_span
        c = H * 1.0001 / span  # a neighbour within R is at most span y/z cells away despite rounding
        cx = H / self.options.cell_subdivision_x
        lo = np.asarray(m.domain_lo, float) - 2 * H
        hi = np.asarray(m.domain_hi, float) + 2 * H
        dims = np.maximum(np.ceil((hi - lo) / np.array([cx, c, c])).astype(np.int64) + 1, 1)
        if m.dim == 2:
            dims[2] = 1
        limit = min(max(self.options.min_cells, self.options.cells_per_particle * m.n_total), 1 << 26)
        # wrapped y/z rows keep >= 2 span + 1 cells so the columns around a particle never alias
        side = 2 * span + 1
        floor = np.array([1, min(side, dims[1]), min(side, dims[2])])
        while int(np.prod(dims)) > limit and np.any(dims > floor):
            k = int(np.argmax(np.where(dims > floor, dims, 0)))
            dims[k] = max(floor[k], (dims[k] + 1) // 2)
        n_cells = int(np.prod(dims))
        nt = max(m.n_total, 1)
        self._cell_keys = wp.zeros(2 * nt, dtype=int, device=d)
        self._cell_order = wp.zeros(2 * nt, dtype=int, device=d)
        self._cell_first = wp.zeros(n_cells + 1, dtype=int, device=d)
        self._cell_bits = max(1, int(n_cells).bit_length())
        g = sph.CellGrid()
        g.lo = wp.vec3(*[float(a) for a in lo])
        g.inv_cx = 1.0 / cx
        g.c = c
        g.span = span
        g.nx, g.ny, g.nz = (int(a) for a in dims)
        g.first = self._cell_first
        g.order = self._cell_order
        # positions in slot order: the list build's candidates (the gather reads them only with gather_prefilter)
        self._x_sorted = wp.zeros(nt if self._slot_positions else 1, dtype=wp.vec3, device=d)
        g.x_sorted = self._x_sorted
        g.prefilter = 1 if self.gather_prefilter else 0
        self.cells = g
        # (2 span + 1)^2 columns (2 span + 1 in 2D: those of dz = 0) x 2 parts
        self._slot_ranges = (0, 2 * side * side) if m.dim == 3 else (2 * span * side, 2 * (span + 1) * side)

    def _launch(self, kernel, dim, inputs, outputs=(), block_dim: int = 256) -> None:
        """wp.launch for the per-step launches: with ``recorded_launches``, recorded once per kernel and
        argument arrays, then replayed with the scalar arguments and the launch size updated (a plain
        wp.launch packs every argument each time: on a GPU the host, not the device, sets the pace of a
        small step launched step by step; the ghost solver, whose step cannot be a CUDA graph). Else a
        plain wp.launch (the basic step: on a GPU `advance` replays it as a CUDA graph)."""
        m = self.model
        if not self.recorded_launches:
            wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=m.device, block_dim=block_dim)
            return
        args = (*inputs, *outputs)
        scalar = tuple(isinstance(a, (int, float, np.integer, np.floating)) for a in args)
        arrays = tuple(None if sc else id(a) for a, sc in zip(args, scalar))
        entry = self._recorded.get(kernel.key)
        if entry is None or entry[3] != arrays:
            cmd = wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=m.device, block_dim=block_dim,
                            record_cmd=True)
            # (args keeps the recorded arrays alive, so their ids stay theirs)
            entry = self._recorded[kernel.key] = [cmd, list(args), dim, arrays]
        else:
            cmd, values, last_dim = entry[0], entry[1], entry[2]
            for i, sc in enumerate(scalar):
                if sc and args[i] != values[i]:
                    cmd.set_param_at_index(i, args[i])
                    values[i] = args[i]
            if dim != last_dim:
                cmd.set_dim(dim)
                entry[2] = dim
        entry[0].launch()

    def build_cells(self, state: FluidState, rebuild: wp.array | None = None) -> None:
        """Sort all particles (fluid and boundary) by cell: cells.order, cells.first, cells.x_sorted.
        ``rebuild``: a device flag; while rebuild[0] == 0 the kernels return at once (the radix sort still
        runs; on the unchanged sorted keys it keeps the order). None: always."""
        m = self.model
        f = self._always if rebuild is None else rebuild
        self._launch(sph.cell_keys, m.n_total, [self.cells, state.x, self._cell_keys, self._cell_order, f])
        wp.utils.radix_sort_pairs(self._cell_keys, self._cell_order, m.n_total, 0, self._cell_bits)
        self._launch(sph.cell_first, self._cell_first.shape[0], [self._cell_keys, m.n_total, self._cell_first, f])
        if self._slot_positions:
            self._launch(sph.gather_sorted_positions, m.n_total, [self._cell_order, state.x, self._x_sorted, f])

    @staticmethod
    def list_capacity(model: "FluidModel", skin: float = 0.0) -> int:
        """~1.6x the lattice neighbours within the list radius. With a boundary lattice finer than the fluid's,
        a particle at a wall has half its support at the boundary density (spacing/bstep)^dim times the
        fluid's: counted, or those particles overflow every step (the overflow passes then scan cells: 117 of
        3,600 particles in the report's 2D dam breaks with walls at half the spacing, 0.1 ms a step on an H100)."""
        r = model.support_radius * (1.0 + skin) / model.spacing
        lattice = math.pi * r ** 3 * 4.0 / 3.0 if model.dim == 3 else math.pi * r * r
        if 0.0 < model.boundary_spacing < model.spacing:
            lattice *= 0.5 * (1.0 + (model.spacing / model.boundary_spacing) ** model.dim)
        return int(8 * math.ceil(1.6 * lattice / 8.0))

    # ---------------------------------------------------------------- particle order ----------
    def _order_buffers(self):
        if self._order_buf is None:
            m, d = self.model, self.model.device
            nt, nf = m.n_total, m.n_fluid
            self._order_buf = dict(flag=wp.zeros(nt, dtype=int, device=d), rank=wp.zeros(nt, dtype=int, device=d),
                                   perm=wp.zeros(nf, dtype=int, device=d), vec=wp.zeros(nf, dtype=wp.vec3, device=d),
                                   f=wp.zeros(nf, dtype=float, device=d), i=wp.zeros(nf, dtype=int, device=d))
        return self._order_buf

    def _permute(self, kernel, index: wp.array, arrays) -> None:
        b, m = self._order_buf, self.model
        for a in arrays:
            tmp = b["vec"] if a.dtype == wp.vec3 else (b["i"] if a.dtype == wp.int32 else b["f"])
            wp.launch(kernel, dim=m.n_fluid, inputs=[index, a, tmp], device=m.device)
            wp.copy(a, tmp, 0, 0, m.n_fluid)

    def reorder(self, state: FluidState) -> None:
        """Sort the fluid particles by cell (kernels/sph/fluid.py CellGrid order; any permutation is correct).
        Launches only: capturable in a CUDA graph."""
        m = self.model
        b = self._order_buffers()
        self.build_cells(state)
        order = self._cell_order
        wp.launch(sph.sorted_fluid_flags, dim=m.n_total, inputs=[order, m.n_fluid, b["flag"]], device=m.device)
        wp.utils.array_scan(b["flag"], b["rank"], inclusive=False)
        wp.launch(sph.sorted_fluid_perm, dim=m.n_total, inputs=[order, m.n_fluid, b["flag"], b["rank"], b["perm"]],
                  device=m.device)
        # accel, xsph_dv, drho_dt, pressure are recomputed by the next step before they are read
        # (stable_dt's maxima do not depend on the order)
        self._permute(sph.gather_by, b["perm"], (state.x, state.v, state.rho, state.ids))
        self._in_original_order = False
        self.invalidate_lists()  # the slots changed and the grid is the pre-permutation one

    def unsort(self, state: FluidState) -> None:
        """Restore the original particle order (ids = 0..n_fluid-1), so that host reads, outputs and
        checkpoints see the particles as seeded. Cheap when the order is already original."""
        m = self.model
        if self._in_original_order or m.n_fluid == 0:
            return
        self._order_buffers()
        self._permute(sph.scatter_by, state.ids, (state.x, state.v, state.rho, state.pressure, state.accel,
                                                  state.xsph_dv, state.drho_dt))
        wp.launch(sph.iota, dim=m.n_fluid, inputs=[state.ids], device=m.device)
        self._in_original_order = True
        self.invalidate_lists()

    def build_grid(self, state: FluidState) -> None:
        """wp.HashGrid of all particles, for queries outside the step (gauges, neighbour counts, boundary
        volumes, the ghost solver); the step itself uses the cell grid (build_cells)."""
        self.grid.build(state.x, self.cell)

    def build_neighbour_lists(self, state: FluidState, rebuild: wp.array | None = None) -> None:
        """Neighbours within the list radius (1 + neighbour_skin) H of each fluid particle (after
        build_cells); ``rebuild`` as in build_cells."""
        m = self.model
        f = self._always if rebuild is None else rebuild
        if self.cell_gather:  # no list: the build positions only (the skin check's, and the gathers' query centres)
            self._launch(gather.store_build_positions_all, m.n_fluid, [state.x, f, self._x_build])
        else:
            self._launch(sph.build_neighbour_list_cells, m.n_fluid,
                         [self.cells, state.x, self.list_radius, *self._slot_ranges, f],
                         [self._nbr_count, self._nbr, self._x_build])
        self._store_wall_build(state, f)
        self._flag_overflow(f)

    def _store_wall_build(self, state: FluidState, rebuild: wp.array) -> None:
        """At a list build: the positions of the moving blocks' wall particles (their displacement checks)."""
        m = self.model
        if m.n_moving_walls:
            self._launch(sph.store_build_positions, m.n_moving_walls,
                         [state.x, m.n_fluid + m.n_static_boundary, rebuild, self._xq, m.n_static_boundary])

    def _flag_overflow(self, rebuild: wp.array) -> None:
        """After a list build: does a list of this build overflow? (the relative skin check needs to know)"""
        m = self.model
        if self._check is not None:
            self._launch(sph.list_overflow_reset, 1, [rebuild, self._overflowed])
            if not self.cell_gather:  # (a gather never overflows)
                self._launch(sph.list_overflow_flag, m.n_fluid, [self._nbr_count, self.neighbour_cap, rebuild, self._overflowed])

    def _list_guard(self, state: FluidState):
        """Start of a step: the displacement check. Returns the flag the cell grid and list build take,
        or None when the host knows the list is still valid (CPU: the launches are skipped)."""
        m = self.model
        if self.neighbour_skin <= 0:
            self.list_builds += 1
            return self._always
        half = 0.5 * self.neighbour_skin * m.support_radius
        nw, w_off, wb_off = m.n_moving_walls, m.n_fluid + m.n_static_boundary, m.n_static_boundary
        if self._check is None:
            self._launch(sph.list_displacement_check, m.n_fluid, [state.x, 0, self._x_build, 0, half * half, self._rebuild])
            if nw:  # the moving walls' particles, as the fluid's
                self._launch(sph.list_displacement_check, nw, [state.x, w_off, self._xq, wb_off, half * half, self._rebuild])
        else:
            # first the absolute test into `moved`: while no particle moved s H / 2 (early in a flow, at rest)
            # the relative kernels return at once (0.2 ms of the relative test saved on an H100 at 2.16 M)
            g = self._check
            self._moved.zero_()
            self._launch(sph.list_displacement_check, m.n_fluid, [state.x, 0, self._x_build, 0, half * half, self._moved])
            if nw:
                self._launch(sph.list_displacement_check, nw, [state.x, w_off, self._xq, wb_off, half * half, self._moved])
            self._d_lo.fill_(wp.vec3(1.0e30))
            self._d_hi.fill_(wp.vec3(-1.0e30))
            self._launch(sph.displacement_bounds, m.n_fluid,
                         [g, state.x, 0, self._x_build, 0, half * half, self._overflowed, self._moved, self._d_lo, self._d_hi,
                          self._rebuild])
            if nw:
                self._launch(sph.displacement_bounds, nw,
                             [g, state.x, w_off, self._xq, wb_off, half * half, self._overflowed, self._moved, self._d_lo,
                              self._d_hi, self._rebuild])
            skin = self.neighbour_skin * m.support_radius
            reach = 0.5 * (self._check_width - m.support_radius)
            self._launch(sph.displacement_check_cells, self._d_lo.shape[0],
                         [g, self._d_lo, self._d_hi, self._wall_cells, skin * skin, reach * reach, self._moved,
                          self._rebuild])
        if not self.host_decides:
            return self._rebuild
        if int(self._rebuild.numpy()[0]) == 0:
            return None
        self.list_builds += 1
        return self._always

    def invalidate_lists(self) -> None:
        """Rebuild the cell grid and neighbour list at the next step (a device-side fill, capturable)."""
        self._rebuild.fill_(1)

    def _lists_built(self) -> None:
        if self.neighbour_skin > 0:
            self._rebuild.zero_()

    def gradient_correction(self, state: FluidState) -> None:
        """fluid.gradient_correction: the matrices L_i of this step into self.kgc (kernels/sph/fluid.py
        gradient_correction_matrix), after the lists and before the density; nothing without the correction."""
        m = self.model
        if m.params.gradient_correction and self.cell_gather:
            self._launch(gather.gradient_correction_cells, m.n_fluid,
                         [*self._gather_args(), state.x, state.rho, m.particle_mass, m.params], [self.kgc])
        elif m.params.gradient_correction:
            self._launch(sph.gradient_correction_matrix, m.n_fluid,
                         [self._nbr_count, self._nbr, state.x, state.rho, m.particle_mass, m.params], [self.kgc])

    def compute_density(self, state: FluidState, lists: bool = False) -> None:
        """Summation density and pressure (before the first step, and each step in summation mode;
        ``lists``: the cell grid and neighbour lists are current)."""
        m = self.model
        if not lists:
            self.build_cells(state)
            self.build_neighbour_lists(state)
            self._lists_built()
        if self.cell_gather:
            self._launch(gather.particle_density_cells, m.n_fluid,
                         [*self._gather_args(), state.x, state.v, m.particle_mass, self._zero_dt, self.kgc, m.params,
                          int(Density.SUMMATION)], [state.drho_dt, state.rho, state.pressure, self._pr2])
            return
        self._launch(sph.particle_density_summation_list, m.n_fluid,
                     [self._nbr_count, self._nbr, state.x, m.particle_mass, m.params],
                     [state.rho, state.pressure, self._pr2])
        self._density_overflow(state, None, summation=True)

    def _gather_args(self) -> tuple:
        """The cell gather's first arguments (kernels/sph/gather.py): the grid, its slot ranges, the query radius (the
        list radius) and the query centres (the fluid's positions at the last build)."""
        return (self.cells, *self._slot_ranges, self.list_radius, self._x_build)

    def _density_overflow(self, state: FluidState, dt, summation: bool) -> None:
        m = self.model
        self._launch(sph.particle_density_overflow, m.n_fluid,
                     [self.cells, *self._slot_ranges, self.list_radius, self._nbr_count, self.neighbour_cap, state.x,
                      state.v, m.particle_mass, dt if dt is not None else self._zero_dt, self.kgc, m.params, 1 if summation else 0],
                     [state.drho_dt, state.rho, state.pressure, self._pr2])

    def set_density(self, state: FluidState, rho: np.ndarray) -> None:
        """Set the fluid densities (continuity mode's initial condition) and their pressures."""
        m = self.model
        state.rho.assign(np.asarray(rho, dtype=np.float32))
        wp.launch(sph.equation_of_state_pass, dim=m.n_fluid, inputs=[state.rho, m.params], outputs=[state.pressure], device=m.device)

    def device_bytes(self, state: FluidState) -> dict:
        """Device memory of the fluid [bytes], each Warp array counted once at its capacity: the neighbour lists
        (``lists``: slots and counts), the rest of the solver's buffers (``solver``), the model (``model``: boundary
        lattice, masses, parameters) and the state (``state``); ``hash_grid``: Warp's HashGrid, estimated (its
        buffers are not Warp arrays: a cell index, a point index and their sort's double buffers per reserved
        point, a start and an end per cell); ``total`` and ``per_particle`` (total / fluid particles)."""
        seen = set()

        def walk(obj, skip=()):
            tot = 0
            items = obj.items() if isinstance(obj, dict) else vars(obj).items()
            for name, a in items:
                if isinstance(a, dict):
                    tot += walk(a)
                elif isinstance(a, (list, tuple)):
                    tot += walk(dict(enumerate(a)))
                elif isinstance(a, wp.array) and a.ptr is not None and id(a) not in seen and name not in skip:
                    seen.add(id(a))
                    tot += a.capacity
            return tot

        m = self.model
        out = dict(lists=walk(dict(slots=self._nbr, counts=self._nbr_count)), state=walk(state), model=walk(m))
        out["solver"] = walk(self, skip=("model",))
        cells = int(np.prod(self.grid_dims)) if getattr(self, "grid_dims", None) is not None else 0
        out["hash_grid"] = 16 * int(m.n_total) + 8 * cells
        out["total"] = sum(out.values())
        out["per_particle"] = out["total"] / max(m.n_fluid, 1)
        return out

    # ---------------------------------------------------------------- read-only views -----------
    # The solver's own arrays for diagnostics and tests (read them; the step owns them).
    list_counts = property(lambda self: self._nbr_count, doc="wp.array(int, n_fluid): neighbours in each list")
    list_entries = property(lambda self: self._nbr, doc="wp.array(int, cap * n_fluid): list slots, column-major")
    list_build_positions = property(lambda self: self._x_build, doc="wp.array(vec3): positions at the last list build [m]")
    rebuild_flag = property(lambda self: self._rebuild, doc="wp.array(int, 1): 1 when the next step rebuilds the lists")
    cell_order = property(lambda self: self._cell_order, doc="wp.array(int): particle index of each cell-sorted slot")
    relative_skin_check = property(lambda self: self._check is not None,
                                   doc="bool: the Verlet lists' skin is checked pairwise ('relative'), not per particle")
    diffusion_rate = property(lambda self: getattr(self, "_diff_rate", None),
                              doc="wp.array(float, n_fluid) or None: the last density-diffusion rate [kg/m^3/s]")
    shift_displacements = property(lambda self: getattr(self, "_shift_dr", None),
                                   doc="wp.array(vec3, n_fluid) or None: the last step's particle shifts [m]")
    surface_indicator = property(lambda self: getattr(self, "_shift_lam", None),
                                 doc="wp.array(float, n_fluid) or None: the last free-surface indicator lambda_i")

    # ---------------------------------------------------------------- the step: named passes ----
    # The one way to extend the fluid step: an ordered list of named passes, each f(state, dt) with dt the device
    # array of the step's length. A variant solver (rockwave/sph/ghost.py) or an attached part (the wall particles of
    # moving blocks, rockwave/coupling/walls.py; a rank's halo exchange, rockwave/sim/distributed.py) replaces or
    # inserts passes by name (replace_pass / insert_pass); nothing copies the sequence.
    PASS_NAMES = ("neighbour_lists", "gradient_correction", "density", "wall_work", "density_diffusion",
                  "wall_pressure", "pair_forces", "shifting", "integrate", "shift")

    def _default_passes(self) -> list:
        return [("neighbour_lists", self._neighbour_lists_pass), ("gradient_correction", self._gradient_correction_pass),
                ("density", self._density_pass), ("wall_work", self._wall_work_pass),
                ("density_diffusion", self._density_diffusion_pass), ("wall_pressure", self._wall_pressure_pass),
                ("pair_forces", self._pair_forces_pass),
                ("shifting", self._shifting_pass), ("integrate", self._integrate_pass), ("shift", self._shift_pass)]

    def pass_names(self) -> list[str]:
        return [name for name, _ in self.passes]

    def _pass_index(self, name: str) -> int:
        names = self.pass_names()
        if name not in names:
            raise KeyError(f"no fluid pass {name!r} (passes: {', '.join(names)})")
        return names.index(name)

    def replace_pass(self, name: str, fn) -> None:
        """Run ``fn(state, dt)`` in place of the pass ``name``."""
        self.passes[self._pass_index(name)] = (name, fn)

    def insert_pass(self, name: str, fn, *, after: str | None = None, before: str | None = None) -> None:
        """Add the pass ``name`` = ``fn(state, dt)`` right after (or before) an existing pass."""
        if (after is None) == (before is None):
            raise ValueError("insert_pass: give exactly one of after= or before=")
        if name in self.pass_names():
            raise ValueError(f"a fluid pass {name!r} exists already")
        i = self._pass_index(after) + 1 if after is not None else self._pass_index(before)
        self.passes.insert(i, (name, fn))

    def step(self, state: FluidState, ts: TimeStep) -> None:
        """One step of length ts.dt (kernels read it from the device array ts.dt_array): the passes in order
        (neighbour lists, density (summation, or continuity advanced by dt) and pressure, density diffusion, wall
        pressure, acceleration and XSPH, semi-implicit Euler)."""
        if self.model.n_fluid == 0:
            return
        dt = ts.dt_array
        for _, run_pass in self.passes:
            run_pass(state, dt)

    def _neighbour_lists_pass(self, state: FluidState, dt: wp.array) -> None:
        self._density_done = self._neighbour_lists(state, dt)

    def _gradient_correction_pass(self, state: FluidState, dt: wp.array) -> None:
        self.gradient_correction(state)

    def _density_pass(self, state: FluidState, dt: wp.array) -> None:
        self._density(state, dt, self._density_done)

    def _wall_work_pass(self, state: FluidState, dt: wp.array) -> None:
        self.wall_work(state, dt)

    def _density_diffusion_pass(self, state: FluidState, dt: wp.array) -> None:
        m = self.model
        if m.density_diffusion > 0.0 and m.density is Density.CONTINUITY:
            self._density_diffusion(state, dt)

    def _wall_pressure_pass(self, state: FluidState, dt: wp.array) -> None:
        self.wall_pressure(state)

    def _shifting_pass(self, state: FluidState, dt: wp.array) -> None:
        """fluid.particle_shifting: each particle's shift of this step from the step's start positions (free-surface
        indicator, concentration gradients, then the shift with its free-surface band; kernels/sph/shifting.py),
        applied after the integration (the ``shift`` pass). Nothing without it."""
        if self.model.particle_shifting > 0.0:
            self.particle_shift(state, dt)

    def _shift_pass(self, state: FluidState, dt: wp.array) -> None:
        if self.model.particle_shifting > 0.0:
            self._launch(shifting.apply_shift, self.model.n_fluid, [self._shift_dr, state.x])

    def reduce_shift_speed(self, v2max: wp.array) -> None:
        """The shift's largest |v|^2 over the whole scene from this solver's (one process: itself; a rank of a
        distributed run: the maximum over the ranks, rockwave/sim/distributed.py)."""

    def shift_by_scenario(self, owner: wp.array, n_scenarios: int) -> None:
        """A batch of scenarios with their own steps (rockwave/sim/batch.py): each particle's shift from its own
        scenario's largest speed (``owner``: the scenario of each seeded particle), none while its step is 0."""
        self._shift_owner = owner
        self._shift_v2 = wp.zeros(max(int(n_scenarios), 2), dtype=float, device=self.model.device)

    def particle_shift(self, state: FluidState, dt: wp.array | None = None) -> None:
        """The shifts of this step into ``shift_displacements`` (positions unchanged; the lists must be current).
        ``dt``: the step array (a particle whose step is 0 is not shifted); None: shifted."""
        m = self.model
        if getattr(self, "_shift_owner", None) is None:
            self._shift_owner = wp.zeros(1, dtype=int, device=m.device)
        if getattr(self, "_shift_dr", None) is None:
            nf, d = m.n_fluid, m.device
            self._shift_lam = wp.zeros(nf, dtype=float, device=d)
            self._shift_gc = wp.zeros(nf, dtype=wp.vec3, device=d)
            self._shift_gs = wp.zeros(nf, dtype=wp.vec3, device=d)
            self._shift_dr = wp.zeros(nf, dtype=wp.vec3, device=d)
            if getattr(self, "_shift_v2", None) is None:
                self._shift_v2 = wp.zeros(1, dtype=float, device=d)
            self._shift_one = wp.ones(1, dtype=float, device=d)  # the step when none is given: any non-zero
            self._shift_wdx = float(lattice_kernel_value(m.params, m.spacing, d))
        if self.cell_gather:
            self._launch(gather.surface_and_concentration_cells, m.n_fluid,
                         [*self._gather_args(), state.x, state.rho, m.particle_mass, m.params, self._shift_wdx],
                         [self._shift_lam, self._shift_gc, self._shift_gs])
        else:
            self._launch(shifting.surface_and_concentration, m.n_fluid,
                         [self._nbr_count, self._nbr, state.x, state.rho, m.particle_mass, m.params, self._shift_wdx],
                         [self._shift_lam, self._shift_gc, self._shift_gs])
        self._shift_v2.zero_()
        if self._shift_v2.shape[0] > 1:  # by scenario (shift_by_scenario)
            self._launch(shifting.scenario_speed_max, m.n_fluid, [state.v, state.ids, self._shift_owner, self._shift_v2])
        else:
            stride = min(m.n_fluid, 16384)
            self._launch(shifting.speed_max, stride, [state.v, m.n_fluid, stride, self._shift_v2])
            self.reduce_shift_speed(self._shift_v2)
        shift_args = [state.x, self._shift_lam, self._shift_gc, self._shift_gs, self._shift_v2, state.ids,
                      self._shift_owner, self._shift_one if dt is None else dt, m.params, m.particle_shifting, m.spacing]
        if self.cell_gather:
            self._launch(gather.shift_displacement_cells, m.n_fluid, [*self._gather_args(), *shift_args], [self._shift_dr])
        else:
            self._launch(shifting.shift_displacement, m.n_fluid, [self._nbr_count, self._nbr, *shift_args], [self._shift_dr])

    def _pair_forces_pass(self, state: FluidState, dt: wp.array) -> None:
        """Acceleration and XSPH velocity of every fluid particle from its neighbours (the lists, then the
        particles whose lists overflowed)."""
        m = self.model
        if self.cell_gather:
            self._launch(gather.particle_acceleration_cells, m.n_fluid,
                         [*self._gather_args(), state.x, state.v, state.rho, state.pressure, self._pr2, m.particle_mass,
                          self._wall_pr2, state.wall_velocity, self.kgc, m.params],
                         [state.accel, state.xsph_dv], block_dim=self._block_dim)
            return
        self._launch(sph.particle_acceleration_list, m.n_fluid,
                     [self._nbr_count, self._nbr, state.x, state.v, state.rho, state.pressure, self._pr2,
                      m.particle_mass, self._wall_pr2, state.wall_velocity, self.kgc, m.params],
                     [state.accel, state.xsph_dv], block_dim=self._block_dim)
        self._launch(sph.particle_acceleration_overflow, m.n_fluid,
                     [self.cells, *self._slot_ranges, self.list_radius, self._nbr_count, self.neighbour_cap, state.x,
                      state.v, state.rho, state.pressure, m.particle_mass, self._wall_pr2, state.wall_velocity, self.kgc,
                      m.params],
                     [state.accel, state.xsph_dv])

    def build_lists(self, state: FluidState) -> None:
        """The cell grid and the neighbour lists of the current positions, outside a step (diagnostics, tests)."""
        with wp.ScopedDevice(self.model.device):
            self.build_cells(state)
            self.build_neighbour_lists(state)
            self._lists_built()

    def pair_accelerations(self, state: FluidState, lists_built: bool = False) -> None:
        """The step's pair forces for the current density and pressure, without moving a particle: lists built
        (unless ``lists_built``), wall pressure extrapolated, then state.accel (pressure + viscosity + gravity) and
        state.xsph_dv."""
        with wp.ScopedDevice(self.model.device):
            if not lists_built:
                self.build_lists(state)
            self.wall_pressure(state)
            self._pair_forces_pass(state, None)

    def _integrate_pass(self, state: FluidState, dt: wp.array) -> None:
        self._launch(sph.integrate_particles, self.model.n_fluid, [state.accel, state.xsph_dv, dt], [state.x, state.v])

    def wall_pressure(self, state: FluidState) -> None:
        """Adami et al. (2012) walls: each boundary particle's pressure (and no-slip velocity) extrapolated from the
        fluid around it (kernels/sph/fluid.py wall_pressure_adami), after the density of this step and before the
        forces. Nothing with Akinci walls. Needs the cell grid of the last list build (or a newer one)."""
        m = self.model
        if m.params.boundary != sph.BOUNDARY_ADAMI or m.n_boundary == 0 or m.n_fluid == 0:
            return
        xq, q_off = (state.x, m.n_fluid) if self._xq is None else (self._xq, 0)
        self._launch(sph.wall_pressure_adami, m.n_boundary,
                     [self.cells, *self._slot_ranges, self.list_radius, state.x, state.v, state.rho, state.pressure,
                      xq, q_off, self.wall_accel, m.params],
                     [state.wall_pressure, self._wall_pr2, state.wall_velocity])

    def wall_work(self, state: FluidState, dt: wp.array) -> None:
        """Adami walls with continuity density: the work of the walls' extrapolated pressure on the water, paid by
        the fluid particles that set it (kernels/sph/wall_work.py: each wall's rate of the fluid's summation density,
        then the fluid's continuity density by their Shepard weights). After the density pass and before the wall
        pressure, which then extrapolates the paired density (after it, the wall pressure lagged a step behind
        and still water in a 2D tank grew unstable: RMS speed 0.09 m/s after 0.5 s against 0.003); c_b from the
        walls' pressure of the last step (state.wall_pressure). The cell grid and lists of this step."""
        m = self.model
        if (not m.wall_work or m.params.boundary != sph.BOUNDARY_ADAMI or m.density is not Density.CONTINUITY
                or m.n_boundary == 0 or m.n_fluid == 0):
            return
        xq, q_off = (state.x, m.n_fluid) if self._xq is None else (self._xq, 0)
        self._launch(wall_work.wall_density_rate, m.n_boundary,
                     [self.cells, *self._slot_ranges, self.list_radius, state.x, state.v, m.particle_mass, xq, q_off,
                      state.wall_pressure, state.pressure, m.params], [self._wall_rate])
        self._launch(wall_work.paired_wall_density, m.n_fluid,
                     [self._nbr_count, self._nbr, self.cells, *self._slot_ranges, self.list_radius, state.x,
                      m.particle_mass, self._wall_rate, dt, m.params],
                     [state.drho_dt, state.rho, state.pressure, self._pr2])

    def _neighbour_lists(self, state: FluidState, dt: wp.array) -> bool:
        """The cell grid and Verlet lists, rebuilt when the skin check says so. Returns True when the
        density was computed in the same pass (fused_density)."""
        return self._neighbour_lists_with(state, dt, self._list_guard(state))

    def _neighbour_lists_with(self, state: FluidState, dt: wp.array, guard) -> bool:
        """The list pass with the skin check's answer ``guard`` (_list_guard's: None, a flag to launch on, or
        self._always); a rank of a decomposition decides it with the other ranks (rockwave/sim/distributed.py)."""
        m = self.model
        # the fused list build + density needs the host to know that the list is rebuilt this step
        fused = self.fused_density and guard is self._always and not m.params.gradient_correction  # L_i first
        if guard is self._rebuild and self.conditional_rebuild and m.device.is_capturing:
            # in a CUDA graph the rebuild is a conditional node on the device flag: the steps that keep
            # the list skip the radix sort and the cell/list launches instead of running them to no effect
            def rebuild():
                self.build_cells(state, self._always)
                self.build_neighbour_lists(state, self._always)
                self._lists_built()

            wp.capture_if(self._rebuild, on_true=rebuild)
            guard = None
        if guard is not None:
            self.build_cells(state, guard)
            if fused:
                self._launch(sph.neighbour_list_density, m.n_fluid,
                             [self.cells, *self._slot_ranges, self.list_radius, state.x, state.v, m.particle_mass, dt,
                              m.params, int(m.density), self.kgc],
                             [self._nbr_count, self._nbr, state.drho_dt, state.rho, state.pressure, self._pr2,
                              self._x_build])
                self._store_wall_build(state, guard)
                self._flag_overflow(guard)
            else:
                self.build_neighbour_lists(state, guard)
            self._lists_built()
        return fused

    def _density(self, state: FluidState, dt: wp.array, done: bool) -> None:
        """Density and pressure over the lists (unless the list pass computed them)."""
        if done:
            return
        m = self.model
        if m.density is Density.SUMMATION:
            self.compute_density(state, lists=True)
        elif self.cell_gather:
            self._launch(gather.particle_density_cells, m.n_fluid,
                         [*self._gather_args(), state.x, state.v, m.particle_mass, dt, self.kgc, m.params,
                          int(Density.CONTINUITY)], [state.drho_dt, state.rho, state.pressure, self._pr2])
        else:
            self._launch(sph.particle_density_continuity_list, m.n_fluid,
                         [self._nbr_count, self._nbr, state.x, state.v, m.particle_mass, dt, self.kgc, m.params],
                         [state.drho_dt, state.rho, state.pressure, self._pr2])
            self._density_overflow(state, dt, summation=False)

    def _density_diffusion(self, state: FluidState, dt: wp.array) -> None:
        """delta-SPH density diffusion after the continuity density (opt-in; kernels/sph/diffusion.py)."""

        m = self.model
        renorm = int(m.density_diffusion_renormalised)
        if getattr(self, "_diff_rate", None) is None:
            self._diff_rate = wp.zeros(m.n_fluid, dtype=float, device=m.device)
            # Antuono et al.'s renormalised density gradients (kernels/sph/diffusion.py); a one-entry placeholder without
            self._diff_grad = wp.zeros(m.n_fluid if renorm else 1, dtype=wp.vec3, device=m.device)
        # Adami walls take part with the density of their pressure extrapolated from this step's density (the
        # root of the blow-up after an impact, kernels/sph/diffusion.py); the wall_pressure pass then extrapolates
        # again from the diffused density
        walls = int(m.params.boundary == sph.BOUNDARY_ADAMI and m.n_boundary > 0)
        if walls:
            self.wall_pressure(state)
        pd = int(m.density_diffusion_form == "pressure")
        if self.cell_gather:
            self._launch(gather.density_diffusion_rate_cells, m.n_fluid,
                         [*self._gather_args(), state.x, state.rho, m.particle_mass, self._wall_pr2, walls, m.params,
                          m.density_diffusion, pd], [self._diff_rate])
        else:
            if renorm:
                self._launch(diffusion.density_gradient_renormalised, m.n_fluid,
                             [self._nbr_count, self._nbr, state.x, state.rho, m.particle_mass, self._wall_pr2, walls,
                              m.params, pd], [self._diff_grad])
            self._launch(diffusion.density_diffusion_rate, m.n_fluid,
                         [self._nbr_count, self._nbr, state.x, state.rho, m.particle_mass, self._wall_pr2, walls,
                          m.params, m.density_diffusion, pd, renorm, self._diff_grad], [self._diff_rate])
        self._launch(diffusion.apply_density_diffusion, m.n_fluid, [self._diff_rate, dt, m.params],
                     [state.drho_dt, state.rho, state.pressure, self._pr2])

    # ---------------------------------------------------------------- checkpoint ------------
    def checkpoint_arrays(self) -> dict[str, wp.array]:
        """What the solver keeps between steps beyond the state: the positions of the last list build and the
        rebuild flag (the lists themselves are rebuilt from them on restore, in the same order)."""
        out = {"x_build": self._x_build, "rebuild": self._rebuild}
        if self._xq is not None:  # the moving walls' build positions
            out["wall_build"] = self._xq
        return out

    def checkpoint_meta(self) -> dict:
        """Host values the solver keeps between steps (none here)."""
        return {}

    def restore_checkpoint(self, state: FluidState, arrays: dict, meta: dict) -> None:
        """After ``state`` was restored: the particle order flag and the neighbour lists of the checkpointed
        run, rebuilt from its list-build positions (the same lists, in the same order: a resumed run is
        bit-identical on the CPU)."""
        m = self.model
        nf = m.n_fluid
        self._in_original_order = bool(np.array_equal(state.ids.numpy(), np.arange(nf)))
        if nf == 0:
            return
        x = wp.clone(state.x)
        wp.copy(x, wp.array(np.asarray(arrays["x_build"], np.float32), dtype=wp.vec3, device=m.device), 0, 0, nf)
        if self._xq is not None:
            self._xq.assign(np.asarray(arrays["wall_build"], np.float32))
            wp.copy(x, self._xq, nf, 0, m.n_boundary)
        at_build = SimpleNamespace(x=x)  # the list builds read positions only
        self.build_cells(at_build)
        self.build_neighbour_lists(at_build)
        self._rebuild.assign(np.asarray(arrays["rebuild"], np.int32))

    def list_overflow(self) -> int:
        """Fluid particles whose last neighbour list overflowed the capacity (summed by a cell-grid query)."""
        if self.cell_gather or self.model.n_fluid == 0:  # a gather has no capacity to overflow
            return 0
        return int((self._nbr_count.numpy() > self.neighbour_cap).sum())

    def pair_counts(self, state: FluidState) -> np.ndarray:
        """Neighbours within H of each fluid particle (int, n_fluid, slot order) as the step's passes see them: the
        pairs of the current lists closer than H, or those of the cell gather (``neighbours = 'cells'``). The lists
        or cell grid must be current (after a step or build_lists)."""
        m = self.model
        out = wp.zeros(m.n_fluid, dtype=int, device=m.device)
        if self.cell_gather:
            wp.launch(gather.neighbour_count_cells, dim=m.n_fluid,
                      inputs=[*self._gather_args(), state.x, m.support_radius], outputs=[out], device=m.device)
        else:
            wp.launch(gather.neighbour_count_list, dim=m.n_fluid,
                      inputs=[self._nbr_count, self._nbr, state.x, m.support_radius], outputs=[out], device=m.device)
        counts = out.numpy()
        if counts.min(initial=0) < 0:
            raise RuntimeError("pair_counts: a neighbour list overflowed its capacity")
        return counts

    def stable_dt(self, state: FluidState, cfl: float | None = None) -> float:
        """Largest stable step for the current motion (one host read; cfl: default ``cfl_number``):
        min(C h/(c0 (1 + 0.6 alpha) + u_max), 0.25 sqrt(h/a_max), 0.125 h^2/nu), h = H/2 (Monaghan 1992)."""
        m = self.model
        self._extrema.zero_()
        if m.n_fluid:
            stride = min(m.n_fluid, 16384)
            wp.launch(sph.motion_extrema, dim=stride, inputs=[state.v, state.accel, m.n_fluid, stride], outputs=[self._extrema],
                      device=m.device)
        vmax2, amax2 = (float(a) for a in self._extrema.numpy())
        return fluid_dt_limit(m, self.cfl_number if cfl is None else cfl, math.sqrt(vmax2), math.sqrt(amax2))

    def neighbour_counts(self, state: FluidState) -> np.ndarray:
        m = self.model
        self.build_grid(state)
        out = wp.zeros(m.n_fluid, dtype=int, device=m.device)
        wp.launch(sph.neighbour_count, dim=m.n_fluid, inputs=[self.grid.id, state.x, m.support_radius], outputs=[out], device=m.device)
        return out.numpy()


def fluid_step_limits(support_radius_m: float, sound_speed_m_s: float, artificial_alpha: float,
                      kinematic_viscosity_m2_s: float, cfl: float, u_max_m_s: float, a_max_m_s2: float) -> dict[str, float]:
    """The fluid's step limits [s] (Monaghan 1992), h = H/2: "courant": C h/(c0 (1 + 0.6 alpha) + u_max); "force":
    0.25 sqrt(h/a_max) (when a_max > 0); "viscous": 0.125 h^2/nu (when nu > 0). The one CFL rule: the solver's
    adaptive step (fluid_dt_limit) and the preflight estimate (rockwave/build/preflight.py) both take it."""
    h = 0.5 * support_radius_m
    c = sound_speed_m_s * (1.0 + 0.6 * artificial_alpha)
    out = {"courant": cfl * h / (c + u_max_m_s)}
    if a_max_m_s2 > 0:
        out["force"] = 0.25 * math.sqrt(h / a_max_m_s2)
    if kinematic_viscosity_m2_s > 0:
        out["viscous"] = 0.125 * h * h / kinematic_viscosity_m2_s
    return out


def fluid_dt_limit(m: FluidModel, cfl: float, u_max: float, a_max: float) -> float:
    """The smallest of the model's step limits [s] (fluid_step_limits) at the largest speed u_max [m/s] and
    acceleration a_max [m/s^2]."""
    return min(fluid_step_limits(m.support_radius, m.sound_speed, m.params.alpha, m.kinematic_viscosity, cfl, u_max,
                                 a_max).values())


def calibrate_lattice(params: sph.SPHParams, spacing: float, dim: int, device) -> tuple[float, float]:
    """Particle mass and kernel-gradient scale from a full lattice of the given spacing.

    m = rho0 / sum_j W_0j, so a particle inside the fluid at rest has exactly rho0; and
    s = 1 / (sum_j V_j (x_j - x_0)_x dW/dx), V_j = m/rho0, so the SPH gradient of a linear
    field is exact on the lattice. At H = 2 spacing the raw lattice sums miss both by several
    per cent, which shows as a hydrostatic pressure gradient off by as much."""
    k = int(math.ceil(params.H / spacing)) + 1
    r = np.arange(-k, k + 1) * spacing
    g = np.meshgrid(*([r] * dim), indexing="ij")
    pts = np.stack([c.ravel() for c in g] + [np.zeros(g[0].size)] * (3 - dim), axis=1).astype(np.float32)
    centre = pts.shape[0] // 2
    pts[[0, centre]] = pts[[centre, 0]]
    xa = wp.array(pts, dtype=wp.vec3, device=device)
    w = wp.zeros(len(pts), dtype=float, device=device)
    gx = wp.zeros(len(pts), dtype=float, device=device)
    wp.launch(sph.lattice_moments, dim=len(pts), inputs=[xa, params], outputs=[w, gx], device=device)
    w_sum, grad_moment = float(np.sum(w.numpy(), dtype=np.float64)), float(np.sum(gx.numpy(), dtype=np.float64))
    mass = params.rest_density / w_sum
    return mass, w_sum / grad_moment


def lattice_kernel_value(params: sph.SPHParams, spacing: float, device) -> float:
    """W(dx) of the scene's kernel at one particle spacing (the anti-clumping term's reference)."""
    pts = wp.array(np.array([[0.0, 0.0, 0.0], [spacing, 0.0, 0.0]], np.float32), dtype=wp.vec3, device=device)
    w = wp.zeros(2, dtype=float, device=device)
    gx = wp.zeros(2, dtype=float, device=device)
    wp.launch(sph.lattice_moments, dim=2, inputs=[pts, params], outputs=[w, gx], device=device)
    return float(w.numpy()[1])


def build_fluid_model(fluid_positions: np.ndarray, fluid_velocities: np.ndarray, boundary_positions: np.ndarray,
                      fp: FluidParameters, dim: int, gravity, device, boundary_spacing: float | None = None,
                      boundary_layers: int | None = None, moving_wall_positions: np.ndarray | None = None) -> FluidModel:
    """Assemble the model of the formulation ``fp``: calibrated particle mass and boundary masses Psi_b.
    Positions and velocities (n, 3) [m], [m/s]; gravity [m/s^2] (dim components); boundary_spacing [m] (None: the
    fluid spacing) and boundary_layers (None: as thick as the support) of the boundary lattice.

    ``moving_wall_positions``: the wall particles of moving blocks at the start (rockwave/coupling/walls.py BlockWalls),
    appended after the static boundary particles in the order given (their blocks place them each step).

    Boundary walls whose layers cover the kernel support act as frozen fluid: Psi_b is the
    lattice-calibrated mass at the boundary spacing. Thinner walls use Akinci et al. (2012):
    Psi_b = rho0 / sum_k W_bk. Both push with Akinci's single term -Psi_b p_i/rho_i^2 grad W,
    the force that conserves energy with the density sum (a mirrored 2 p_i/rho_i^2 gained
    energy in a resting tank)."""
    nf, nb = len(fluid_positions), len(boundary_positions)
    params = make_params(fp, dim, gravity, nf)
    if nb > 1:  # static boundary particles in cell order (coherent neighbour reads; the fluid is reordered as it moves)
        bp = np.asarray(boundary_positions, dtype=np.float64)
        c = np.floor((bp - bp.min(axis=0)) / params.H).astype(np.int64)
        boundary_positions = bp[np.lexsort((c[:, 0], c[:, 1], c[:, 2]))]
    n_moving = 0 if moving_wall_positions is None else len(moving_wall_positions)
    if n_moving:
        boundary_positions = np.concatenate([np.asarray(boundary_positions, float).reshape(-1, 3),
                                             np.asarray(moving_wall_positions, float)])
        nb += n_moving
    spacing = fp.spacing_m
    bstep = boundary_spacing or spacing
    full_support = boundary_layers is None or walls_cover_support(boundary_layers, bstep, params.H)
    x = np.concatenate([fluid_positions, boundary_positions]).astype(np.float64) if nb else fluid_positions.astype(np.float64)
    v = np.zeros_like(x)
    v[:nf] = fluid_velocities
    lo = x.min(axis=0) - params.H if len(x) else np.zeros(3)
    hi = x.max(axis=0) + params.H if len(x) else np.ones(3)
    mass, params.grad_scale = calibrate_lattice(params, spacing, dim, device)
    params.fluid_mass = mass
    masses = wp.array(np.full(nf + nb, mass, dtype=np.float32), dtype=float, device=device)
    model = FluidModel(
        dim=dim, up=dim - 1, n_fluid=nf, n_boundary=nb, spacing=spacing, support_radius=params.H,
        particle_mass=masses, params=params, sound_speed=params.sound_speed,
        kinematic_viscosity=params.mu / params.rest_density,
        density=fp.density,
        domain_lo=lo, domain_hi=hi, initial_positions=x, initial_velocities=v, device=wp.get_device(device),
        density_diffusion=float(fp.density_diffusion),
        boundary_spacing=float(bstep) if nb else 0.0, n_moving_walls=n_moving,
        particle_shifting=float(fp.particle_shifting),
        density_diffusion_form=fp.density_diffusion_form,
        density_diffusion_renormalised=bool(fp.density_diffusion_renormalised),
        wall_work=bool(fp.wall_work),
    )
    if nb and full_support:
        mb = calibrate_lattice(params, bstep, dim, device)[0]
        masses.assign(np.concatenate([np.full(nf, mass), np.full(nb, mb)]).astype(np.float32))
    elif nb:
        solver = FluidSolver(model)
        xa = wp.array(x.astype(np.float32), dtype=wp.vec3, device=device)
        solver.grid.build(xa, params.H)
        wp.launch(sph.boundary_volume, dim=nb, inputs=[solver.grid.id, xa, params], outputs=[masses], device=device)
    return model


def density_for_pressure(params: sph.SPHParams, p: np.ndarray) -> np.ndarray:
    """Inverse EOS, the one there is: the density [kg/m^3] whose pressure is p [Pa] under the EOS of ``params``:
    Tait rho = rho0 (1 + p/B)^(1/gamma); linear rho = rho0 + p/k."""
    rho0 = params.rest_density
    if params.eos == 0:
        return rho0 * (1.0 + p / params.eos_b) ** (1.0 / params.eos_gamma)
    return rho0 + p / params.eos_b


def hydrostatic_density(params: sph.SPHParams, g_depth: np.ndarray) -> np.ndarray:
    """The density [kg/m^3] whose pressure is the hydrostatic p = rho0 g d (g_depth = |g| d [m^2/s^2]) under the EOS of
    ``params`` (density_for_pressure): Tait rho = rho0 (1 + rho0 g d / B)^(1/gamma); linear rho0 + rho0 g d / k."""
    return density_for_pressure(params, params.rest_density * g_depth)
