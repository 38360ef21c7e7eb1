"""Two-way coupling between the SPH water and the DDA rock blocks (docs/coupling.md).

What lives where:

* ``CouplingOptions``: the penalty and broad-phase knobs (contact distance ratio, stiffness factor /
  damping ratio or explicit K_s / K_d, squeeze-out, dt safety, capacity paths), defaults equal to the
  shipped values (the scene format takes its defaults from here; rockwave/build/options.py coupling_options reads
  the scene's ``[coupling]`` section).
* ``Coupling(fluid_model, block_model, dim, options=...)``: the model-level data (body-frame face
  planes, 2D depths, penalty constants) and its work buffers (broad phase, impulses ``dv``); it keeps
  nothing from one step to the next. ``compute`` reads a FluidState and a BlockState and writes ``dv``
  and the blocks' ``ext_force`` / ``ext_torque``; ``apply`` adds ``dv`` to the fluid. Per step
  (one rockwave.base.solver.TimeStep, dt read on the device from ``ts.dt_array``):
  ``compute(fluid_state, block_state, ts)`` before the fluid step, ``apply(fluid_state, ts)`` after
  it, then the block step. Step limits: ``critical_dt()`` is the particle-wall spring's stability
  limit (a fixed step must stay below it); ``stable_dt()`` = options.dt_safety (0.5) x that is the
  coupling's share of the adaptive step.
* ``block_signed_distance``, ``default_penalty``: helpers (start-up particle removal, tests).
* Kernels: kernels/coupling/penalty.py.

Penalty method of the SPH-DDA paper (Eq. 22): a fluid particle closer than the contact distance
d0 to a block face (or inside the block) is pushed out along the face's outward normal n by

    f = (K_s d - K_d (v_rel . n)) n,   d = d0 - dist  (penetration past the contact distance),

clipped at zero, and the block receives -f at the particle's projection on the face (force and
torque about its centroid, through BlockState.ext_force / ext_torque). Fixed and kinematic blocks
are walls, slopes and pistons for the water: a tank can be built from blocks.

Defaults (from the fluid's speed of sound c0, particle mass m and spacing s):

* d0 = s/2: lattice particles sit half a spacing from the faces of the box they fill, so the water
  touches the surface (each particle stands for the s^dim cell around it) instead of floating on
  a gap; this makes the displaced volume, and so the buoyancy, that of the block itself.
* K_s = m c0^2 / s^2 (= rho0 c0^2 s^(dim-2)): the stiffness of one particle's column of water
  compressed by d along n, so the wall is exactly as stiff as the water (penetration under a
  pressure p is d/s = p/(rho0 c0^2) = Mach^2-small); its contact frequency sqrt(K_s/m) = c0/s
  keeps omega dt = CFL number, inside the fluid's own step.
* K_d = 2 zeta sqrt(K_s m) with zeta = 0.5: half-critical damping of that particle-wall spring,
  so a particle hitting a wall does not bounce off (the paper leaves K_s, K_d open).

Squeeze-out of pinched water (``squeeze_out``, on by default). A block sinking onto a floor (or
sliding onto another block) must drive the water film between the two faces out sideways. With the
penalty alone it does not: the film's last two particle layers each sit at d0 from one face, the
block's weight reaches the floor through them as wall forces (d0 + s + d0 = 2 spacings of gap), and
the SPH pressure inside the film, whose particles all miss the kernel support on both sides, shows
no clear excess over the surrounding water (film particles 0-9 kPa in a checkerboard, the floor
row outside ~5 kPa), so nothing pushes the film out: the block stayed 2.0-2.1 spacings above the
floor from 0.45 s to the end of the run (1.2 s). In the
continuum the film carries the block's submerged weight with a pressure above the surroundings,
and that pressure gradient drains it (inviscid, in ~L/sqrt(dp/rho) ~ 0.05 s for a 0.1 m block);
the pressure field across a film thinner than a kernel support is not resolved, so the coupling
supplies the drainage itself:

* a particle touching block a (dist_a < d0) is *pinched* when another solid b has a face opposing
  a's (n_a . n_b < -cos 45 deg) with w = dist_a + dist_b < w_s = 2 d0 + H: the particles touching
  one face then have neighbours touching the other, the film is at most one kernel support thick;
* the normal force of a and of b on it becomes mag (n + lambda t): t is the way out along the gap,
  towards the nearest side face of the moving block (the shortest drainage path, as in squeeze flow
  between plates), lambda = (w_s - w)/(w_s - 2 d0) in [0, 1], i.e. the fraction of its load a pinched
  particle turns into an outward push grows to all of it where a particle no longer fits (w <= 2 d0).
  The reaction -mag (n + lambda t) goes to the block as before (the outward pushes on the two sides
  of a face cancel), so momentum is still exchanged exactly; between two fixed blocks nothing moves
  and nothing is squeezed.

The block then closes the gap and lands in DDA contact with the floor block (sinking_block_small:
bottom 2e-5 m = 0.002 spacings inside the floor, the DDA contact overlap, with no particle left
under it; before: 2.07 spacings of trapped film). The broad phase grows each block's box by
max(d0, w_s) so the opposing solid is among a particle's candidates.

Order within one step (both solvers on one clock, Simulation.step): forces from the state at t
are computed first (they only read x(t), v(t) and the block poses); the fluid step runs; the
coupling impulse dt f/m is then added exactly as if f/m had been part of the semi-implicit Euler
acceleration (v += dt f/m, x += dt^2 f/m); the block step uses the reactions. The exchange is
therefore equal and opposite within each step: water + blocks conserve momentum up to the
external forces (gravity, fixed walls, kinematic blocks, tank particles). With multi-rate stepping
(rockwave/sim/clock.py) the block step is n sub-steps of dt/n with the reactions held over all of them
(BlockSolver.substeps): the blocks still receive -f dt, the impulse the water took, once per fluid step.

2D scenes: blocks are 3D prisms extruded along z (their z-extent is their depth; they move in the
x-y plane only: BlockModel(planar=True), enforced inside BlockSolver.step). A 2D particle's mass and forces are per metre of depth,
so the block receives f times its z-extent.

Deformable blocks are coupled through their rigid motion (faces moved rigidly; their strains,
~1e-5 for rock, are neglected here). Strain rates are not included in v_rel.

Wall particles on moving blocks (``coupling.block_walls``, :class:`BlockWalls`): with Adami walls the
moving blocks near the water also carry wall particles that move with them, so the water pushes them with
its extrapolated pressure (Adami et al. 2012, eq. 27, with the wall's acceleration) and the penalty above is
only the guard against penetration, as on fixed blocks. Their reactions go to the same ext_force /
ext_torque, after the fluid's force pass and before the block step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from rockwave.base.maths import next_pow2, quat_to_matrix
from rockwave.base.solver import TimeStep
from rockwave.coupling.joint_water import JointWater
from rockwave.kernels.coupling import penalty as penalty_k
from rockwave.kernels.dda import blocks as dda_k


@dataclass(frozen=True)
class CouplingOptions:
    """Knobs of the water-block coupling: ``Coupling(fluid, blocks, dim, options=CouplingOptions(...))``.
    The defaults are the shipped values (the scene format takes its defaults from here); rockwave/build/options.py
    coupling_options reads the scene's ``[coupling]`` section."""

    contact_distance_ratio: float = 0.5
    """Contact distance d0 / particle spacing [-] (scene: coupling.contact_distance_ratio)."""

    stiffness_factor: float = 1.0
    """K_s = stiffness_factor m c0^2 / s^2 [-] (scene: coupling.stiffness_factor)."""

    damping_ratio: float = 0.5
    """K_d = 2 damping_ratio sqrt(K_s m) [-] (scene: coupling.damping_ratio)."""

    stiffness_n_m: float | None = None
    """Explicit K_s [N/m per particle; per metre of depth in 2D], overrides stiffness_factor
    (scene: coupling.stiffness_n_m)."""

    damping_n_s_m: float | None = None
    """Explicit K_d [N s/m per particle; per metre of depth in 2D], overrides damping_ratio
    (scene: coupling.damping_n_s_m)."""

    squeeze_out: bool = True
    """Push water pinched between two opposing solid faces out along the gap (module docstring;
    scene: coupling.squeeze_out)."""

    dt_safety: float = 0.5
    """stable_dt = dt_safety x critical_dt(): the coupling's share of the adaptive step [-]."""

    cell_size_m: float | None = None
    """Broad-phase cell size [m]; None: max(4 s, H) (s spacing, H kernel support radius)."""

    max_cells: int = 4096
    """A block whose grown box covers more cells than this goes to the large list that every
    particle tests [cells]."""

    direct_max_blocks: int = 16
    """Up to this many blocks every particle tests every block's grown box directly (a few compares)
    and the (block, cell) hash is not built [blocks]."""

    sync_free_max_entries: int = 1 << 20
    """Up to this many possible (block, cell) entries (blocks x max_cells) the entry capacity is
    allocated whole and a step reads nothing back; above it, it grows on a counter read [entries]."""

    track_walls: bool = False
    """Sum the forces of fixed and kinematic blocks on the water into Coupling.wall_impulse [N s]
    (diagnostics: one host read per step)."""

    block_walls: bool = False
    """Adami wall particles on the moving blocks within reach of the water (BlockWalls; scene:
    coupling.block_walls; needs fluid.boundary = 'adami' and the basic method). False: the penalty alone."""

    joint_water: bool = False
    """Water pressure in the block contacts below the water: the hydrostatic pressure of the local free surface at
    each contact point, normal to the contact over its area share, equal and opposite on the two blocks, so the
    Coulomb cap acts on the effective normal force (rockwave/coupling/joint_water.py; scene: coupling.joint_water).
    False: no water in a closed joint (a resting block carries its full weight, not its buoyant weight, in friction)."""


def default_penalty(particle_mass: float, sound_speed: float, spacing: float,
                    stiffness_factor: float = CouplingOptions.stiffness_factor,
                    damping_ratio: float = CouplingOptions.damping_ratio):
    """(K_s, K_d) = (f m c0^2 / s^2, 2 zeta sqrt(K_s m)); see the module docstring."""
    ks = stiffness_factor * particle_mass * sound_speed ** 2 / spacing ** 2
    return ks, 2.0 * damping_ratio * math.sqrt(ks * particle_mass)


class Coupling:
    """Penalty coupling of a FluidModel/FluidState with a BlockModel/BlockState.

    Build it only when a scene has both water and blocks. Each step: ``compute(fluid_state,
    block_state, ts)`` before the fluid step, ``apply(fluid_state, ts)`` after it, then the block
    step. Limits: ``critical_dt()`` (the particle-wall spring's stability limit, for a fixed step) and
    ``stable_dt()`` = options.dt_safety x that (the adaptive step).
    Attributes: options, k_s [N/m], k_d [N s/m], d0 [m], cell [m] (broad-phase cell), dim.
    """

    def __init__(self, fluid, blocks, dim: int, options: CouplingOptions | None = None):
        self.options = opt = options if options is not None else CouplingOptions()
        self.fluid, self.blocks, self.dim = fluid, blocks, dim
        self.device = fluid.device
        s = fluid.spacing
        m = fluid.fluid_mass
        ks0, kd0 = default_penalty(m, fluid.sound_speed, s, opt.stiffness_factor, opt.damping_ratio)
        self.k_s = float(opt.stiffness_n_m) if opt.stiffness_n_m is not None else ks0
        self.k_d = float(opt.damping_n_s_m) if opt.damping_n_s_m is not None else (2.0 * opt.damping_ratio * math.sqrt(self.k_s * m))
        self.d0 = opt.contact_distance_ratio * s
        # squeeze-out gap w_s = 2 d0 + H (module docstring); 0: off
        self.squeeze_gap = 2.0 * self.d0 + fluid.support_radius if opt.squeeze_out else 0.0
        self.reach = max(self.d0, self.squeeze_gap)  # broad phase: blocks within reach of a particle are candidates
        self.cell = float(opt.cell_size_m) if opt.cell_size_m else max(4.0 * s, fluid.support_radius)
        self.max_cells = int(opt.max_cells)
        d = self.device
        nb = blocks.num_blocks
        # body-frame face planes (rigid motion) and each face's block
        normals, offsets, fblock = [], [], []
        for b, spec in enumerate(blocks.specs):
            g = spec.geometry
            normals.append(g.face_normals)
            offsets.append(g.face_offsets)
            fblock.append(np.full(g.num_faces, b))
        self.num_faces = int(sum(len(o) for o in offsets))
        self.face_block = wp.array(np.concatenate(fblock).astype(np.int32), dtype=int, device=d)
        self.body_normal = wp.array(np.concatenate(normals).astype(np.float32), dtype=wp.vec3, device=d)
        self.body_offset = wp.array(np.concatenate(offsets).astype(np.float32), dtype=float, device=d)
        self.plane_n = wp.zeros(self.num_faces, dtype=wp.vec3, device=d)
        self.plane_d = wp.zeros(self.num_faces, dtype=float, device=d)
        # 2D: forces per metre of depth times the block's z-extent
        scale = np.ones(nb)
        if dim == 2:
            for b, spec in enumerate(blocks.specs):
                v = spec.geometry.vertices @ quat_to_matrix(np.asarray(spec.orientation, float)).T
                scale[b] = float(v[:, 2].max() - v[:, 2].min())
        self.depth = scale
        self.depth_scale = wp.array(scale.astype(np.float32), dtype=float, device=d)
        self.bounds = wp.zeros(6, dtype=float, device=d)
        self._bounds_init = wp.array(np.array([1e30] * 3 + [-1e30] * 3, np.float32), dtype=float, device=d)
        self.wv = wp.zeros(blocks.num_vertices, dtype=wp.vec3, device=d)
        self.cell_lo = wp.zeros(nb, dtype=wp.vec3i, device=d)
        self.cell_hi = wp.zeros(nb, dtype=wp.vec3i, device=d)
        self.ncell = wp.zeros(nb, dtype=int, device=d)
        self.cell_offset = wp.zeros(nb, dtype=int, device=d)
        self.large = wp.zeros(nb, dtype=int, device=d)
        self.box_lo = wp.zeros(nb, dtype=wp.vec3, device=d)  # grown, clipped AABB of each block (block_cells)
        self.box_hi = wp.zeros(nb, dtype=wp.vec3, device=d)
        self.counters = wp.zeros(2, dtype=int, device=d)  # [0] (block, cell) entries, [1] large blocks
        # kernel argument groups (kernels/coupling/penalty.py), built once (grid: refreshed when it grows)
        self.faces = penalty_k.BlockFaces()
        self.faces.face_start, self.faces.face_count = blocks.face_start, blocks.face_count
        self.faces.plane_n, self.faces.plane_d = self.plane_n, self.plane_d
        self.faces.kinds, self.faces.depth_scale = blocks.kinds, self.depth_scale
        # blocks of the [tank] (BlockSpec.tank: solid to blocks; the water has the tank's boundary particles there):
        # no penalty force, only the opposing face of a squeeze-out pinch
        tank = np.array([bool(getattr(spec, "tank", False)) for spec in blocks.specs], np.int32)
        self.faces.wall_only = wp.array(tank, dtype=int, device=d)
        g = self.grid = penalty_k.CouplingGrid()
        g.cell_lo, g.cell_hi, g.ncell, g.cell_offset = self.cell_lo, self.cell_hi, self.ncell, self.cell_offset
        g.large, g.counters, g.box_lo, g.box_hi = self.large, self.counters, self.box_lo, self.box_hi
        self.params = penalty_k.CouplingParams()
        p = self.params
        p.k_s, p.k_d, p.d0 = self.k_s, self.k_d, self.d0
        p.inv_s = 1.0 / self.cell
        p.track_walls = 1 if opt.track_walls else 0
        p.squeeze_gap = self.squeeze_gap
        g = float(np.linalg.norm(blocks.gravity))
        p.squeeze_speed = max(math.sqrt(g * self.d0), 1e-6)
        # Few blocks: every particle tests every block's grown box (no hash). Up to 2^20 possible entries
        # (blocks x max_cells): the entry capacity is allocated whole and the step reads nothing back (the
        # GPU never waits for the host). More: it grows on a counter read. The path is chosen here, once.
        self.direct = nb <= opt.direct_max_blocks
        self.sync_free = self.direct or nb * self.max_cells <= opt.sync_free_max_entries
        self._alloc(16 if self.direct else nb * self.max_cells if self.sync_free else 1024)
        self._hash_blocks = self._hash_none if self.direct else self._hash_sync_free if self.sync_free else self._hash_counted
        self.dv = wp.zeros(fluid.n_fluid, dtype=wp.vec3, device=d)
        self.wall_force = wp.zeros(1, dtype=wp.vec3, device=d)
        # work of the kinematic blocks on the water since the last take_wall_work() [J; J/m in 2D] (the energy budget)
        self.wall_work = wp.zeros(1, dtype=float, device=d)
        self.has_kinematic = bool(np.any(blocks.np["kinds"] == 3))
        # squeeze-out energy (kernels/coupling/penalty.py squeeze_energy): per block, this step's (power taken by the
        # closing gaps, power given by the push) and the push's scale for the next step
        self.sq_power = wp.zeros(nb, dtype=wp.vec2, device=d)
        self.sq_scale = wp.ones(nb, dtype=float, device=d)
        self.wall_impulse = np.zeros(3)  # sum of dt x (force of fixed/kinematic blocks on the water), when tracked
        self.active_blocks = 0  # blocks near water in the last step (host copy, diagnostics)
        self.walls = None  # BlockWalls: Adami wall particles of the moving blocks (rockwave/build/builder.py sets it)
        # pore pressure in the block contacts below the water (coupling.joint_water)
        self.joint_water = JointWater(fluid, blocks, fluid.params.rest_density) if opt.joint_water else None
        self._n_large = 0
        self._total = 0

    @property
    def track_walls(self) -> bool:
        """options.track_walls: fixed at construction (the kernel parameters are built once)."""
        return self.options.track_walls

    @property
    def n_large(self) -> int:
        """Blocks of the last broad phase that every particle tests (over max_cells cells)."""
        return int(self.counters.numpy()[1]) if self.sync_free else self._n_large

    def _alloc(self, n_entries: int):
        d = self.device
        self.entry_cap = max(16, n_entries)
        self.nbuckets = next_pow2(2 * self.entry_cap)
        self.entry_block = wp.zeros(self.entry_cap, dtype=int, device=d)
        self.entry_cell = wp.zeros(self.entry_cap, dtype=wp.vec3i, device=d)
        self.bucket_count = wp.zeros(self.nbuckets, dtype=int, device=d)
        self.bucket_start = wp.zeros(self.nbuckets, dtype=int, device=d)
        self.bucket_fill = wp.zeros(self.nbuckets, dtype=int, device=d)
        g = self.grid
        g.nbuckets = self.nbuckets
        g.entry_block, g.entry_cell = self.entry_block, self.entry_cell
        g.bucket_count, g.bucket_start, g.bucket_fill = self.bucket_count, self.bucket_start, self.bucket_fill

    def critical_dt(self) -> float:
        """Stability limit of the particle-wall spring-dashpot [s] (a particle touching up to 3 faces):
        2/omega (sqrt(1 + zeta^2) - zeta), omega = sqrt(3 K_s / m). A fixed step must not exceed it."""
        m = self.fluid.fluid_mass
        om = math.sqrt(3.0 * self.k_s / m)
        z = self.k_d / (2.0 * math.sqrt(3.0 * self.k_s * m))
        return 2.0 / om * (math.sqrt(1.0 + z * z) - z)

    def stable_dt(self, state=None) -> float:
        """The coupling's limit on the adaptive step [s]: options.dt_safety x critical_dt() (it depends
        on the fluid model and the penalty only, not on a state)."""
        return self.options.dt_safety * self.critical_dt()

    # ------------------------------------------------------------------ geometry ----------
    def update_planes(self, block_state) -> None:
        wp.launch(penalty_k.face_planes, dim=self.num_faces,
                  inputs=[self.face_block, self.body_normal, self.body_offset, block_state.x, block_state.q],
                  outputs=[self.plane_n, self.plane_d], device=self.device)

    def signed_distance(self, points: np.ndarray, block_state) -> tuple[np.ndarray, np.ndarray]:
        """(smallest signed distance to any block [m], that block's index) for (n, 3) points."""
        return block_signed_distance(self.blocks, block_state, points)

    def _broad_phase(self, fluid_state, block_state) -> None:
        m, d, nf = self.blocks, self.device, self.fluid.n_fluid
        wp.copy(self.bounds, self._bounds_init)
        stride = min(nf, 16384)
        wp.launch(penalty_k.fluid_bounds, dim=stride, inputs=[fluid_state.x, nf, stride], outputs=[self.bounds], device=d)
        wp.launch(dda_k.world_vertices, dim=m.num_vertices,
                  inputs=[m.body_verts, m.vert_block, block_state.x, block_state.q, block_state.strain, m.kinds, self.wv], device=d)
        self.counters.zero_()
        wp.launch(penalty_k.block_cells, dim=m.num_blocks,
                  inputs=[self.wv, m.vert_start, m.vert_count, self.bounds, self.reach + 1e-6, 1.0 / self.cell,
                          -1 if self.direct else self.max_cells, self.grid], device=d)
        self._hash_blocks()

    def _hash_none(self) -> None:
        """Direct path: every block near water is in the large list; the buckets stay empty."""
        self._total = 0

    def _hash_sync_free(self) -> None:
        self._fill_buckets(self.entry_cap)  # launch dims; the kernels stop at counters[0]

    def _hash_counted(self) -> None:
        total, self._n_large = (int(c) for c in self.counters.numpy())  # one host read per step: capacity
        if total > self.entry_cap:
            self._alloc(2 * total)
        self._fill_buckets(total)

    def _fill_buckets(self, total: int) -> None:
        d = self.device
        self.bucket_count.zero_()
        self.bucket_fill.zero_()
        if total:
            # one thread per (block, cell) entry, not a serial loop per block (kernels/coupling/penalty.py)
            wp.utils.array_scan(self.ncell, self.cell_offset, inclusive=False)
            wp.launch(penalty_k.count_buckets, dim=total, inputs=[self.grid], device=d)
            wp.utils.array_scan(self.bucket_count, self.bucket_start, inclusive=False)
            wp.launch(penalty_k.fill_buckets, dim=total, inputs=[self.grid], device=d)
        self._total = total

    def _nothing_near(self) -> bool:
        """Counter-read path only: no block near water in the last broad phase (host counts)."""
        return not self.sync_free and self._total == 0 and self._n_large == 0

    def compute(self, fluid_state, block_state, ts: TimeStep) -> None:
        """Penalty forces from the state at ts.time: particle impulses ts.dt f/m (dt read on the device
        from ts.dt_array) into self.dv, reactions into block_state.ext_force / ext_torque. With wall particles
        on moving blocks (self.walls) they are placed first, at the blocks' poses of ts.time."""
        nf = self.fluid.n_fluid
        if nf == 0:
            return
        if self.walls is not None:
            self.walls.place(fluid_state, block_state, ts)
        if self.joint_water is not None:
            self.joint_water.apply(fluid_state, block_state)
        self._broad_phase(fluid_state, block_state)
        if self._nothing_near():
            self.dv.zero_()
            return
        self.update_planes(block_state)
        if self.track_walls:
            self.wall_force.zero_()
        wp.launch(penalty_k.particle_block_forces, dim=nf,
                  inputs=[fluid_state.x, fluid_state.v, self.fluid.particle_mass, ts.dt_array, self.params, self.grid,
                          self.faces, block_state.bodies, block_state.loads, self.wall_force, self.wall_work, self.sq_power,
                          self.sq_scale],
                  outputs=[self.dv], device=self.device)
        if self.squeeze_gap > 0.0:
            wp.launch(penalty_k.squeeze_energy, dim=self.blocks.num_blocks, inputs=[self.sq_power, self.sq_scale],
                      device=self.device)
        if self.track_walls:
            self.wall_impulse += float(ts.dt_array.numpy()[0]) * self.wall_force.numpy()[0].astype(np.float64)

    def apply(self, fluid_state, ts: TimeStep) -> None:
        """Add the impulses of the last compute to the fluid after its step (x += dt dv, v += dv)."""
        nf = self.fluid.n_fluid
        if nf and self.walls is not None and self.has_kinematic:  # the work of kinematic blocks' wall particles
            self.walls.add_wall_work(self.wall_work, ts)
        if nf == 0 or self._nothing_near():
            return
        wp.launch(penalty_k.apply_dv, dim=nf, inputs=[self.dv, ts.dt_array], outputs=[fluid_state.x, fluid_state.v], device=self.device)

    def take_wall_work(self) -> float:
        """The work of the kinematic blocks on the water since the last call [J; J/m in 2D] (one host read)."""
        if not self.has_kinematic:
            return 0.0
        w = float(self.wall_work.numpy()[0])
        self.wall_work.zero_()
        return w

    def candidate_blocks(self) -> set[int]:
        """Blocks that the last compute tested against particles (near water): in the (block, cell)
        hash or the large list (a host read)."""
        large = self.large.numpy()[: self.n_large]
        return {int(b) for b in np.flatnonzero(self.ncell.numpy() > 0)} | {int(b) for b in large}

    def active_block_count(self) -> int:
        """Blocks whose grown AABB touches the water's AABB (from the last compute)."""
        return int((self.ncell.numpy() > 0).sum()) + self.n_large


def seed_clearance_m(contact_distance_ratio: float, spacing_m: float) -> float:
    """Water is seeded no closer to a block's faces than the contact distance d0 [m], where the penalty spring is at
    rest (the builder drops the particles closer, rockwave/build/builder.py seeding_clearance, and puts wall
    particles there on a fixed block; preflight refuses a region that would keep none). Half of it (d0/2) let
    particles start in the spring on a tilted face (issue 41)."""
    return contact_distance_ratio * spacing_m


def seeding_clearance_m(contact_distance_ratio: float, spacing_m: float, lattice_steps, coordinate_scale_m: float) -> float:
    """The clearance the seeding keeps from block faces [m]: the contact distance d0 = contact_distance_ratio x the
    seeding lattice's step (its smallest fitted step ``lattice_steps``, at most ``spacing_m``), so that the penalty
    spring is at rest at t = 0. A particle seeded between d0/2 and d0 of a tilted face (an axis-aligned lattice cuts a
    tilted face at any offset) met the spring force K_s (d0 - dist), up to m c0^2 / (4 s), a pressure of order
    rho0 c0^2 / 8 over the face (issue 41: still water on the NTHMP slope was blasted off it at 4-5 m/s). On a face the
    lattice fills up to (a region's edge on it) a particle lies half a step away, at this clearance, and stays: less
    the float32 round-off of the distances (block_signed_distance) at coordinates of ``coordinate_scale_m``."""
    step = min([float(spacing_m)] + [float(h) for h in lattice_steps])
    return seed_clearance_m(contact_distance_ratio, step) - 8.0 * float(np.finfo(np.float32).eps) * max(coordinate_scale_m, 1.0)


def block_signed_distance(blocks, block_state, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest signed distance (negative inside) of each point to any block, and that block
    (max over face planes of the rigidly moved block; brute force over blocks: start-up and tests)."""
    d = blocks.device
    if len(points) == 0:
        return np.zeros(0), np.zeros(0, int)
    normals, offsets, fblock = [], [], []
    for b, spec in enumerate(blocks.specs):
        normals.append(spec.geometry.face_normals)
        offsets.append(spec.geometry.face_offsets)
        fblock.append(np.full(spec.geometry.num_faces, b))
    nfaces = int(sum(len(o) for o in offsets))
    pn = wp.zeros(nfaces, dtype=wp.vec3, device=d)
    pd = wp.zeros(nfaces, dtype=float, device=d)
    wp.launch(penalty_k.face_planes, dim=nfaces,
              inputs=[wp.array(np.concatenate(fblock).astype(np.int32), dtype=int, device=d),
                      wp.array(np.concatenate(normals).astype(np.float32), dtype=wp.vec3, device=d),
                      wp.array(np.concatenate(offsets).astype(np.float32), dtype=float, device=d), block_state.x, block_state.q],
              outputs=[pn, pd], device=d)
    pts = wp.array(np.asarray(points, np.float32), dtype=wp.vec3, device=d)
    out = wp.zeros(len(points), dtype=float, device=d)
    which = wp.zeros(len(points), dtype=int, device=d)
    wp.launch(penalty_k.signed_distance_to_blocks, dim=len(points),
              inputs=[pts, blocks.num_blocks, blocks.face_start, blocks.face_count, pn, pd], outputs=[out, which], device=d)
    return out.numpy().astype(np.float64), which.numpy()
