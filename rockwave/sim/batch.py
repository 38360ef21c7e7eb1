"""Many small scenarios stepped as one: spatial batching (issue 40).

A hazard study runs hundreds of scenarios of a few thousand particles each; one of them alone leaves a GPU idle
between kernel launches. :class:`BatchSimulation` places the scenarios of a batch side by side in one set of
arrays, each in its own tile of space, so that one set of launches steps them all:

- **Seeding in the scenario's own frame.** Each scenario is seeded exactly as it would be alone
  (rockwave/build/builder.py seed_fluid: its regions, its tank and obstacle layers, the removal inside its
  blocks, its packed start, its fixed and moving blocks' Adami walls, all anchored to its own water) and then
  moved by its tile's offset; its blocks (rockwave/build/rocks.py block_specs) move by the same offset and are
  renamed ``<k>/<name>``. One fluid model, one block model and one coupling are built from the union.
- **Tiles** form a grid in the horizontal-vertical plane (2D: x and y; 3D: x and y, z up), as square as the
  tiles allow so that the coordinates stay small (float32 positions: the round-off of a position grows with
  its size, ulp(32 m) = 3.8e-6 m against 2.4e-7 m at 3 m). Neighbouring tiles are ``gap`` apart (default:
  8 H and the blocks' broad-phase margin, or more), so no neighbour search, water-block coupling or block contact
  ever pairs two scenarios: every pair term is cut off at H (1 + skin) or the contact distance, all smaller.
- **Each scenario its own step and clock** (``steps="scenario"``, the default): each scenario runs the solo
  clock's rules (rockwave/sim/clock.py; Simulation.advance's loop) on its own clock (:class:`_OwnClocks`): its
  target from its own limits every dt_update_interval of its own steps (the fluid's CFL, force and viscous limits
  over its own particles, kernels/sim/batch.py scenario_motion_extrema; its own blocks' DDA limit, BlockSolver
  .critical_dt_of; the coupling spring where it has blocks), the time to the end divided into equal steps no
  longer than the target, its own multi-rate sub-step count. One launch sequence steps all: the fluid and coupling
  kernels read each particle's step (kernels/sph/fluid.py step_of: a per-particle array filled from its scenario's),
  the block kernels each block's clock (kernels/dda/blocks.py clock_of), max n_k block sub-steps run and a block
  whose scenario has taken its own gets dt = 0 (no integration, no planar projection, its contact history kept).
  A scenario that has landed takes dt = 0 while the others go on. A scenario at its own coordinates reproduces its
  solo run bit for bit; in its tile it differs by the float32 round-off of its translated coordinates
  (tests/test_batch.py).
- **Or one shared step** (``steps="shared"``): the step is the smallest of all scenarios' limits and the block
  sub-step the stiffest block's, so each scenario steps within its own limits, at a step no longer than it would
  take alone; its results differ from the solo run's by the difference of the two step sequences. Kept for
  fluid-only batches on a GPU, whose chunks it replays as CUDA graphs (docs/hazard_and_sweeps.md).
- **Scenarios share the template**: dimension, the [simulation], [gravity], [fluid] (its regions aside),
  [coupling] sections, the boundary lattice, the frame rate and the hazard sampling rhythm; anything else may differ (geometry,
  particle counts, blocks, materials, gauges). A batch of scenes that do not share it is a SceneError naming the
  key.
- **Per-scenario guard** (:meth:`BatchSimulation.check`): NaN/inf, a fluid particle faster than 5 c0 (plus free
  fall outside its domain, as rockwave/sim/guard.py), more than half of its water outside its domain, or a
  particle that left its tile (it could reach a neighbour) fails that scenario alone (:class:`ScenarioFailed`);
  rockwave/app/batch.py then runs the batch again without it, so a blow-up never changes the others' results.

Python API::

    from rockwave.sim.batch import BatchSimulation
    b = BatchSimulation([scene_a, scene_b, scene_c], device="cuda:0")
    b.advance(1.0)
    x_b = b.positions(1)        # scenario 1's fluid positions in its own frame
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import warp as wp

from rockwave.base.device import resolve_device
from rockwave.base.maths import pad3, quat_to_matrix
from rockwave.base.solver import TimeStep
from rockwave.build import builder
from rockwave.build.options import block_options, boundary_lattice, gravity_norm, support_radius_m
from rockwave.build.rocks import block_specs
from rockwave.kernels.dda import blocks as dda_k
from rockwave.kernels.sim import batch as batch_k
from rockwave.scene.format import DEFAULT_SAMPLE_INTERVAL_S, Node, Scene, SceneError
from rockwave.sim.clock import MAX_BLOCK_SUBSTEPS, Clock
from rockwave.sim.guard import ESCAPE_FRACTION, SPEED_FACTOR
from rockwave.sim.simulation import Simulation, SimulationOptions
from rockwave.sim.stepping import BlockSubstepping
from rockwave.sph.fluid import fluid_dt_limit
from rockwave.sph.ghost import GhostFluidSolver

NAME_SEP = "/"  # a batch's block names: "<scenario>/<name>"
PLAN_RING = 8  # pinned host buffers of the per-scenario step plan, used in turn
STEP_MODES = ("scenario", "shared")  # each scenario its own step and clock (the default), or one step for all


class ScenarioFailed(RuntimeError):
    """Scenarios of a batch blew up or left their tiles: ``failures`` {index: message} (every scenario that
    failed the check: a blow-up that reached a neighbour's tile within a frame fails both; the caller runs
    the batch again without them and each of them alone)."""

    def __init__(self, failures: dict[int, str]):
        super().__init__("; ".join(f"scenario {k} of the batch: {m}" for k, m in failures.items()))
        self.failures = failures


# ------------------------------------------------------------------------------------------- template ----
def hazard_interval(scene: Scene) -> float:
    """The hazard sampling interval of a scene [s] (rockwave/output/hazard.py's rule)."""
    hz = scene.hazard or {}
    v = hz.get("sample_interval_s")
    return float(v) if v is not None else min(DEFAULT_SAMPLE_INTERVAL_S, 1.0 / scene.output.frame_rate_hz)


def _without(node, *keys) -> dict:
    return {k: v for k, v in dict(node or {}).items() if k not in keys}


def template_of(scene: Scene) -> dict:
    """What the scenarios of a batch must share (section -> value): everything but geometry, particle counts,
    blocks, materials and gauges."""
    out = {"simulation.dimension": scene.dim,
           "simulation": _without(scene.simulation, "device"),
           "gravity.acceleration_m_s2": list(pad3(scene.gravity.acceleration_m_s2)),
           "fluid": _without(scene.fluid, "regions") if scene.fluid is not None else None,
           "coupling": dict(scene.coupling or {}),
           "hazard.sample_interval_s": hazard_interval(scene),
           "output.frame_rate_hz": float(scene.output.frame_rate_hz)}  # the run loop lands on each frame
    if scene.fluid is not None:
        out["tank (boundary lattice: spacing, layers)"] = list(boundary_lattice(scene))
    return out


def check_template(scenes: list[Scene]) -> None:
    """SceneError (naming the first scene that differs and the key) unless every scene shares the first's
    template."""
    if not scenes:
        raise ValueError("a batch needs at least one scene")
    t0 = template_of(scenes[0])
    for k, s in enumerate(scenes[1:], 1):
        t = template_of(s)
        for key, v in t0.items():
            if t[key] != v:
                detail = ""
                if isinstance(v, dict) and isinstance(t[key], dict):
                    diff = sorted(x for x in set(v) | set(t[key]) if v.get(x) != t[key].get(x))
                    detail = f" ({', '.join(f'{key}.{x}' for x in diff)})"
                raise SceneError(s.path, [(key, f"scenario {k} of the batch differs from scenario 0 in {key}{detail}: "
                                                f"the scenarios of a batch share the dimension, the methods and the "
                                                f"simulation, gravity, fluid (regions aside) and coupling settings; "
                                                f"run it in another batch")])
    if scenes[0].fluid is None:
        raise SceneError(scenes[0].path, [("fluid", "a batch steps scenarios of water (and blocks); this scene has no "
                                                    "[fluid]: run it alone")])


# ------------------------------------------------------------------------------------------- tiles ------
@dataclass
class Tile:
    """One scenario's place in the batch."""

    offset: np.ndarray
    """float64 (3,): added to the scenario's coordinates [m]."""

    lo: np.ndarray
    """float64 (3,): lower corner of the scenario's own extent (its particles +- H and its blocks), own frame [m]."""

    hi: np.ndarray
    """float64 (3,): upper corner [m]."""

    domain_lo: np.ndarray
    """float64 (3,): its particle domain alone (the box of its particles grown by H, as build_fluid_model) [m]."""

    domain_hi: np.ndarray
    fluid: tuple[int, int] = (0, 0)
    """Its fluid particles' range in the batch's seeded order."""

    boundary: tuple[int, int] = (0, 0)
    """Its static boundary particles' range in the seeded (pre-sort) order."""

    blocks: tuple[int, int] = (0, 0)
    """Its blocks' range in the batch's block model."""


def tile_offsets(sizes: np.ndarray, gap: float, dim: int) -> np.ndarray:
    """Offsets of the lower corners of tiles of ``sizes`` (n, 2: width, height in the x-(dim-1) plane) on a grid of
    rows, as square as the tiles allow, centred on the origin: columns = ceil(sqrt(n H / W))."""
    n = len(sizes)
    w, h = float(sizes[:, 0].max()) + gap, float(sizes[:, 1].max()) + gap
    cols = max(1, min(n, int(math.ceil(math.sqrt(n * h / w)))))
    rows = int(math.ceil(n / cols))
    out = np.zeros((n, 2))
    for k in range(n):
        out[k] = ((k % cols) - 0.5 * cols) * w, ((k // cols) - 0.5 * rows) * h
    return out


# ------------------------------------------------------------------------------------------- the batch --
class BatchSimulation(Simulation):
    """Scenarios (Scenes sharing a template) stepped together in one set of arrays; see the module's doc.

    Attributes beyond Simulation's: ``scenes``, ``tiles`` (list of Tile), ``n_scenarios``, ``gap`` [m],
    ``seeds`` (the per-scenario seeds in their own frames), ``removed_inside`` (per scenario). ``scene`` is the
    first scenario's without its gauges and hazard entries (the template: the clock and the solvers read only its
    shared sections).

    Shared by the batch besides the step: the multi-rate block sub-step count (from the stiffest block of the
    batch) and the decisions to keep the broad phase's pairs and to carry contacts through the sub-steps
    (rockwave/sim/stepping.py: held only while they hold for every block of the batch); a batch of more than
    BlockOptions.sync_free_max_blocks blocks runs the block solver's counter-read path. Neither changes the
    contact law, only how often the narrow phase runs."""

    def __init__(self, scenes: list[Scene], device: str | None = None, options: SimulationOptions | None = None,
                 gap: float | None = None, steps: str = "scenario"):
        if steps not in STEP_MODES:
            raise ValueError(f"steps must be one of {STEP_MODES}, got {steps!r}")
        check_template(scenes)
        self.scenes = list(scenes)
        self.n_scenarios = len(scenes)
        scene = scenes[0]
        # the template: scenario 0's shared sections, without its gauges and hazard entries (each scenario's own are
        # read in its own frame by rockwave/output/batch.py; the batch's readers have no gauges of their own)
        self.scene = replace(scene, output=Node({**scene.output, "gauges": []}), hazard=None)
        self.options = options or SimulationOptions()
        self.device = resolve_device(device if device is not None else scene.simulation.device)
        dim, up = scene.dim, scene.dim - 1
        with wp.ScopedDevice(self.device):
            # 1. each scenario alone, in its own frame: blocks (for the seeding), then the particles
            own_specs, own_parts, seeds = [], [], []
            for s in scenes:
                p = builder.Parts()
                specs = block_specs(s) if (s.blocks or s.rock_mass) else []
                if specs:
                    builder.block_model(s, self.device, p, self.options, specs=specs)
                seeds.append(builder.seed_fluid(s, self.device, p, self.options))
                own_specs.append(specs)
                own_parts.append(p)
            H = float(support_radius_m(scene))
            # 2. the tiles: each scenario's extent (particles +- H, blocks' vertices), then a grid of them
            self.tiles = []
            for s, sd, specs, p in zip(scenes, seeds, own_specs, own_parts):
                pts = [a for a in (sd.fluid, sd.boundary, sd.moving) if a is not None and len(a)]
                x = np.concatenate(pts) if pts else np.zeros((1, 3))
                dlo, dhi = x.min(axis=0) - H, x.max(axis=0) + H
                lo, hi = dlo.copy(), dhi.copy()
                if specs:
                    xs, qs = p.block_state.x.numpy().astype(np.float64), p.block_state.q.numpy().astype(np.float64)
                    for b, spec in enumerate(specs):
                        v = np.asarray(spec.geometry.vertices, float) @ quat_to_matrix(qs[b]).T + xs[b]
                        lo, hi = np.minimum(lo, v.min(axis=0)), np.maximum(hi, v.max(axis=0))
                self.tiles.append(Tile(np.zeros(3), lo, hi, dlo, dhi))
            margin = 0.0  # the broad phase's AABB margin (rockwave/dda/blocks.py BlockSolver.margin: 0.05 D50)
            if any(own_specs):
                given = (self.options.blocks or block_options(scene)).aabb_margin_m
                margin = max(0.05 * p.blocks.d50 if given is None else given for p in own_parts if p.blocks is not None)
            skin = 1.0  # the neighbour list's radius is at most 2 H (skin <= 1)
            self.gap = float(gap) if gap is not None else max(8.0 * H, 2.0 * (H * (1 + skin) + margin))
            sizes = np.array([[t.hi[0] - t.lo[0], t.hi[up] - t.lo[up]] for t in self.tiles])
            corner = tile_offsets(sizes, self.gap, dim)
            for t, c in zip(self.tiles, corner):
                t.offset = np.zeros(3)
                t.offset[0] = c[0] - t.lo[0]
                t.offset[up] = c[1] - t.lo[up]
            # 3. the union, moved to the tiles
            xf, vf, depth, xb, xm, mblk, specs_all = [], [], [], [], [], [], []
            nf = nb = nblk = 0
            for k, (t, sd, specs) in enumerate(zip(self.tiles, seeds, own_specs)):
                o = t.offset
                t.fluid = (nf, nf + len(sd.fluid))
                t.boundary = (nb, nb + len(sd.boundary))
                t.blocks = (nblk, nblk + len(specs))
                nf, nb = t.fluid[1], t.boundary[1]
                xf.append(sd.fluid + o)
                vf.append(sd.velocities)
                depth.append(sd.depth)
                if len(sd.boundary):
                    xb.append(sd.boundary + o)
                if sd.moving is not None and len(sd.moving):
                    xm.append(sd.moving + o)
                    mblk.append(sd.moving_blocks + nblk)
                for spec in specs:  # (a kinematic block's motion is a displacement from its position)
                    specs_all.append(replace(spec, name=f"{k}{NAME_SEP}{spec.name}",
                                             position=tuple(np.asarray(spec.position, float) + o)))
                nblk = t.blocks[1]
            self.removed_inside = [p.removed_inside_blocks for p in own_parts]
            self.seeds = seeds
            union = builder.FluidSeeds(np.concatenate(xf), np.concatenate(vf), np.concatenate(depth),
                                       np.concatenate(xb) if xb else np.zeros((0, 3)),
                                       np.concatenate(xm) if xm else None,
                                       np.concatenate(mblk) if mblk else None)
            parts = builder.Parts()
            if specs_all:
                builder.build_blocks(scene, self.device, parts, self.options, specs=specs_all, check_overlap=False)
            builder.build_fluid(scene, self.device, parts, self.options, seeds=union)
            if parts.blocks is not None and parts.fluid.n_fluid:
                builder.build_coupling(scene, parts, self.options)
            del own_parts
        self.estimate = None
        self.fluid, self.state, self.fluid_solver = parts.fluid, parts.state, parts.fluid_solver
        self.blocks, self.block_state, self.block_solver = parts.blocks, parts.block_state, parts.block_solver
        self.coupling = parts.coupling
        self.removed_inside_blocks = sum(self.removed_inside)
        self.gravity = np.asarray(pad3(scene.gravity.acceleration_m_s2))
        self.clock = Clock(scene, self.device, self._limits(), self._stability_bounds(), self._block_substep())
        self.block_stepping = BlockSubstepping(self.clock) if self.block_solver is not None else None
        self.gauge_names = []
        self._readers = None
        self._graphs: dict = {}
        self._graphs_failed = False
        self._plain_runs: set = set()
        self._g = gravity_norm(scene)
        self.step_mode = steps
        self.own = _OwnClocks(self) if steps == "scenario" else None
        if self.fluid_solver is not None and self.fluid.particle_shifting > 0.0 and self.fluid.n_fluid:
            # each scenario's shift from its own largest speed, none while it does not step (kernels/sph/shifting.py)
            owner = np.zeros(self.fluid.n_fluid, np.int32)
            for k, t in enumerate(self.tiles):
                owner[t.fluid[0]:t.fluid[1]] = k
            self.fluid_solver.shift_by_scenario(wp.array(owner, dtype=int, device=self.device), self.n_scenarios)

    # ---------------------------------------------------------------- each scenario its own step ------
    @property
    def times(self) -> np.ndarray:
        """Each scenario's simulated time [s] (float64, (n_scenarios,)); all equal after advance()."""
        return self.own.time.copy() if self.own is not None else np.full(self.n_scenarios, self.clock.time)

    def step(self, dt: float | None = None) -> None:
        """One step: with per-scenario steps each scenario's own current step (``dt``: every scenario that one)."""
        if self.own is None:
            return super().step(dt)
        o = self.own
        dts = o.dt.copy() if dt is None else np.full(self.n_scenarios, float(dt))
        if dt is not None:
            o.set_dt(np.ones(self.n_scenarios, bool), dts)
        self._own_step(dts, np.ones(self.n_scenarios, bool))

    def step_many(self, n: int) -> None:
        """n steps (per-scenario steps: each scenario's own current step, one by one)."""
        if self.own is None:
            return super().step_many(n)
        for _ in range(n):
            self.step()

    def advance(self, duration: float, watch=None) -> None:
        """Advance every scenario by ``duration`` seconds, each landing exactly on the end time. Per-scenario steps:
        each scenario runs the solo loop (Simulation.advance) on its own clock: its adaptive target re-evaluated
        every dt_update_interval of its own steps from its own limits, the time left divided into equal steps no
        longer than the target; one launch of each kernel per step steps all scenarios, a scenario that has landed
        takes dt = 0 (masked) while the others go on. ``watch()`` after every step (``stepped``: the scenarios
        that moved in it)."""
        if self.own is None:
            return super().advance(duration, watch)
        o = self.own
        t_end = o.time + duration  # each its own (all equal after an advance)
        while True:
            left = t_end - o.time
            active = left > 1e-12 * np.maximum(1.0, t_end)
            if not active.any():
                break
            o.update_targets(active)
            n = np.maximum(1, np.ceil(left / o.target - 1e-9))
            dts = np.where(active, left / n, 0.0)
            o.set_dt(active, dts)
            self._own_step(dts, active)
            if watch is not None:
                watch()
        o.time[:] = t_end
        self.clock.time = float(t_end.min())

    def _own_step(self, dts: np.ndarray, active: np.ndarray) -> None:
        """One launch sequence stepping scenario k by dts[k] (0: not at all): the fluid kernels read each
        particle's step (kernels/sim/batch.py particle_steps), the blocks each block's clock."""
        o = self.own
        with wp.ScopedDevice(self.device):
            o.upload_plan(dts, active)  # one host-to-device copy per step: each scenario's time, sub-steps and step
            wp.launch(batch_k.scenario_steps, dim=self.n_scenarios, inputs=[o.plan], outputs=[o.dt_scen])
            nf = self.fluid.n_fluid
            reorder = (wp.get_device(self.device).is_cuda and self.fluid_solver is not None and nf
                       and self.fluid_solver.reorder_interval and self.clock.steps % self.fluid_solver.reorder_interval == 0)
            if reorder:  # a GPU sorts the particles by cell as the solo chunks do (the order changes round-off only)
                self.fluid_solver.reorder(self.state)
            if nf:
                wp.launch(batch_k.particle_steps, dim=nf, inputs=[self.state.ids, o.owner, o.dt_scen], outputs=[o.dt_particle])
            ts = TimeStep(float(dts.max()), float(o.time.min()), o.dt_particle)
            if self.coupling is not None:
                self.coupling.compute(self.state, self.block_state, ts)
            if self.fluid_solver is not None:
                self.fluid_solver.step(self.state, ts)
            if self.coupling is not None:
                self.coupling.apply(self.state, ts)
            if self.block_solver is not None:
                self._own_block_substeps(dts, active)
        o.tick(active, dts)
        o.stepped = active.copy()
        self.clock.steps += 1
        self.clock.time = float(o.time.min())

    def _own_block_substeps(self, dts: np.ndarray, active: np.ndarray) -> None:
        """Each scenario's n_k block sub-steps of dts[k] / n_k (its own count, rockwave/sim/stepping.py with its own
        stable block step) with the water's load held, as BlockSolver.substeps; the batch runs max n_k sub-steps,
        a block whose scenario has taken its own has dt = 0 on its clock (kernels/dda/blocks.py clock_of) and
        stays. The kept-pairs and carried-contacts savings are the batch's (held only while they hold for all)."""
        o, solver, state = self.own, self.block_solver, self.block_state
        n_k = np.where(active, o.substeps, 0)
        N = int(n_k.max())
        if N == 0:
            return
        h_k = np.where(active, dts / np.maximum(n_k, 1), 0.0)
        interval = self.clock.update_interval
        if N > 1 and (self.clock.steps % interval == 0 or o.pairs_hold is None):
            o.pairs_hold, o.contacts_hold = solver.hold_checks(state, float(dts.max()), interval + 1)
        contacts_only = N > 1 and bool(o.pairs_hold) and solver.has_free_blocks
        hold = contacts_only and bool(o.contacts_hold)
        held = o.held
        if N > 1:
            wp.copy(held[0], state.ext_force)  # integrate_blocks zeroes the load after each sub-step
            wp.copy(held[1], state.ext_torque)
        bo = o.block_owner
        h_max = float(h_k.max())
        for i in range(N):
            if i:
                wp.copy(state.ext_force, held[0])
                wp.copy(state.ext_torque, held[1])
            on = i < n_k
            # each block's clock from its scenario's plan, on the device (the solo clock: ts.time + i h + h)
            wp.launch(batch_k.block_clocks, dim=len(bo), inputs=[i, o.plan, o.block_owner_wp], outputs=[o.block_clock],
                      device=self.device)
            # (BlockSolver's own sub-step launches, its CUDA-graph paths aside: they advance one shared clock)
            if i and hold:
                solver._carry_contacts(state)
            elif i and contacts_only:
                solver._prepare(state)
                solver._narrow_phase(state, h_max)
            else:
                solver._contact_forces(state, h_max)
            self._integrate_blocks(on[bo], i)
        state.time = float(o.time.min())

    def _integrate_blocks(self, moving: np.ndarray, i: int) -> None:
        """BlockSolver._integrate with the blocks of the scenarios that have taken their sub-steps (``moving`` False)
        left out of the planar constraint too (its renormalisation of q is not exactly idempotent)."""
        solver, state, m, d = self.block_solver, self.block_state, self.blocks, self.device
        if moving.all():
            return solver._integrate(state)
        if m.num_compounds:
            wp.launch(dda_k.compound_loads, dim=m.num_compounds, inputs=[m.compound_start, m.compound_count, state.loads],
                      device=d)
        wp.launch(dda_k.integrate_blocks, dim=m.num_blocks,
                  inputs=[solver.props, solver.motion, wp.vec3(*m.gravity), solver.block_clock, state.bodies, state.loads],
                  device=d)
        if m.planar:
            o = self.own
            wp.launch(batch_k.idle_kinds, dim=m.num_blocks, inputs=[i, o.plan, o.block_owner_wp, m.kinds,
                                                                   int(dda_k.KIND_FIXED)], outputs=[o.kinds_idle], device=d)
            wp.launch(dda_k.planar_blocks, dim=m.num_blocks, inputs=[m.planar_z, o.kinds_idle, state.bodies], device=d)

    # ---------------------------------------------------------------- per scenario -------------
    def scenario_blocks(self, k: int) -> list[str]:
        """Scenario k's block names as in its scene (without the batch's prefix)."""
        a, b = self.tiles[k].blocks
        return [n.split(NAME_SEP, 1)[1] for n in self.blocks.names[a:b]] if self.blocks is not None else []

    def _own(self, k: int, x: np.ndarray) -> np.ndarray:
        return x - self.tiles[k].offset[: x.shape[1]]

    def positions(self, k: int | None = None) -> np.ndarray:
        """Fluid positions (n, dim) [m]: scenario k's in its own frame, or all in the batch's (k None)."""
        x = super().positions()
        if k is None:
            return x
        a, b = self.tiles[k].fluid
        return self._own(k, x[a:b])

    def velocities(self, k: int | None = None) -> np.ndarray:
        v = super().velocities()
        if k is None:
            return v
        a, b = self.tiles[k].fluid
        return v[a:b]

    def densities(self, k: int | None = None) -> np.ndarray:
        r = super().densities()
        if k is None:
            return r
        a, b = self.tiles[k].fluid
        return r[a:b]

    def block_positions(self, k: int | None = None) -> np.ndarray:
        x = super().block_positions()
        if k is None or self.blocks is None:
            return x
        a, b = self.tiles[k].blocks
        return x[a:b] - self.tiles[k].offset

    def block_velocities(self, k: int | None = None) -> np.ndarray:
        v = super().block_velocities()
        if k is None or self.blocks is None:
            return v
        a, b = self.tiles[k].blocks
        return v[a:b]

    def cross_pairs(self) -> int:
        """Neighbour-list pairs that join particles of two scenarios (0 by construction; a check for tests):
        each particle's scenario from its tile, over the lists of the current positions."""
        owner = self.particle_owner()
        x = np.asarray(self.fluid.initial_positions, float).copy()
        nf = self.fluid.n_fluid
        x[:nf, : self.scene.dim] = self.positions()
        H = self.fluid.support_radius
        from scipy.spatial import cKDTree  # noqa: PLC0415  (tests only)

        pairs = cKDTree(x[:, : self.scene.dim]).query_pairs(2.0 * H, output_type="ndarray")
        return int((owner[pairs[:, 0]] != owner[pairs[:, 1]]).sum())

    def particle_owner(self) -> np.ndarray:
        """int (n_fluid + n_boundary,): each particle's scenario, from the tile its start position lies in."""
        x = np.asarray(self.fluid.initial_positions, float)
        owner = np.full(len(x), -1)
        for k, t in enumerate(self.tiles):
            lo, hi = t.lo + t.offset - 1e-9, t.hi + t.offset + 1e-9
            inside = np.all((x >= lo) & (x <= hi), axis=1)
            owner[inside] = k
        return owner

    # ---------------------------------------------------------------- guard ----------------------
    def check(self, live: list[int] | None = None) -> list[int]:
        """The per-scenario blow-up guard (one host read of positions and velocities): raise ScenarioFailed
        naming every scenario (of ``live``, default all) that has a NaN/inf, a fluid particle faster than
        SPEED_FACTOR c0 (plus the free fall gained below its domain's top, outside it), more than
        ESCAPE_FRACTION of its water outside its domain (grown by 2H), a particle outside its tile grown by
        half the gap less H (it could reach a neighbour), a block with a NaN/inf state or its centroid outside
        its tile grown by half the gap. Returns each scenario's count
        of fluid particles outside its domain."""
        x, v = self.positions(), self.velocities()
        d = x.shape[1]
        H = self.fluid.support_radius
        c_lim = SPEED_FACTOR * self.fluid.sound_speed
        xb = self.block_state.positions_numpy() if self.blocks is not None else None
        vb = self.block_state.velocities_numpy() if self.blocks is not None else None
        counts, failures = [], {}
        for k, t in enumerate(self.tiles):
            if live is not None and k not in live:
                counts.append(0)
                continue
            why, out = self._check_one(k, t, x, v, xb, vb, d, H, c_lim)
            if why:
                failures[k] = why
            counts.append(out)
        if failures:
            raise ScenarioFailed(failures)
        return counts

    def _check_one(self, k, t, x, v, xb, vb, d, H, c_lim) -> tuple[str, int]:
        """(why scenario k fails, '' if it does not; its fluid particles outside its domain)."""
        a, b = t.fluid
        xk, vk = x[a:b] - t.offset[:d], v[a:b]
        bad = ~(np.isfinite(xk).all(1) & np.isfinite(vk).all(1))
        if bad.any():
            i = int(np.argmax(bad))
            return f"fluid particle {i} at {xk[i].tolist()} has a NaN/inf position or velocity", 0
        if xb is not None:
            ba, bb = t.blocks
            if not (np.isfinite(xb[ba:bb]).all() and np.isfinite(vb[ba:bb]).all()):
                return "a block has a NaN/inf position or velocity", 0
            own = xb[ba:bb] - t.offset
            off = np.any((own < t.lo - 0.5 * self.gap) | (own > t.hi + 0.5 * self.gap), axis=1)
            if off.any():
                i = int(np.argmax(off))
                return (f"block {self.scenario_blocks(k)[i]!r} at {own[i].tolist()} left the scenario's tile of the "
                        f"batch: it could reach a neighbour"), 0
        lo, hi = t.domain_lo[:d] - 2 * H, t.domain_hi[:d] + 2 * H
        inside = np.all((xk >= lo) & (xk <= hi), axis=1)
        out = int((~inside).sum())
        speed = np.linalg.norm(vk, axis=1)
        allowed = c_lim + np.where(inside, 0.0, np.sqrt(2.0 * self._g * np.maximum(0.0, hi[d - 1] - xk[:, d - 1])))
        if (speed > allowed).any():
            i = int(np.argmax(speed - allowed))
            return (f"fluid particle {i} at {xk[i].tolist()} moves at {speed[i]:.3g} m/s "
                    f"(> {SPEED_FACTOR:g} c0 = {c_lim:.3g} m/s)"), out
        if out > ESCAPE_FRACTION * max(len(xk), 1):
            return f"{out} of {len(xk)} fluid particles left the domain", out
        tl, th = t.lo[:d] - 0.5 * self.gap + H, t.hi[:d] + 0.5 * self.gap - H
        away = ~np.all((xk >= tl) & (xk <= th), axis=1)
        if away.any():
            i = int(np.argmax(away))
            return (f"fluid particle {i} at {xk[i].tolist()} left the scenario's tile of the batch (its extent grown "
                    f"by {0.5 * self.gap - H:.3g} m): it could reach a neighbour"), out
        return "", out


class _OwnClocks:
    """Each scenario's clock in a batch with per-scenario steps (rockwave/sim/clock.py Clock's rules per scenario):
    time, steps, dt, target, limiting and steps_limited_by, its block sub-step count from its own stable block step;
    the limits from its own particles and blocks (the fluid's CFL, force and viscous limits over its particles, its
    blocks' DDA limit, the coupling spring where it has blocks)."""

    def __init__(self, b: BatchSimulation):
        S = b.n_scenarios
        d = b.device
        sim = b.scene.simulation
        if isinstance(b.fluid_solver, GhostFluidSolver):
            raise SceneError(b.scenes[0].path, [("fluid.method", "a batch with per-scenario steps runs the basic SPH "
                                                                 "method; run Ghost SPH scenarios alone")])
        if b.coupling is not None and b.coupling.walls is not None:
            raise SceneError(b.scenes[0].path, [("coupling.block_walls", "a batch with per-scenario steps has no wall "
                                                 "particles on moving blocks (their acceleration estimate reads one step); "
                                                 "run alone")])
        self.b = b
        self.fixed = sim.time_step == "fixed"
        self.update_interval = int(sim.dt_update_interval)
        self.time = np.zeros(S)
        self.steps = np.zeros(S, np.int64)
        self.block_steps = np.zeros(S, np.int64)
        self.limiting = ["fixed" if self.fixed else ""] * S
        self.steps_limited_by: list[dict] = [{} for _ in range(S)]
        nf = b.fluid.n_fluid
        owner = np.full(max(nf, 1), 0, np.int32)
        for k, t in enumerate(b.tiles):
            owner[t.fluid[0]:t.fluid[1]] = k
        self.owner = wp.array(owner, dtype=int, device=d)
        self.n_fluid = np.array([t.fluid[1] - t.fluid[0] for t in b.tiles])
        self.dt_scen = wp.zeros(S, dtype=float, device=d)
        self.dt_particle = wp.zeros(max(nf, 2), dtype=float, device=d)  # > 1 entry: read per particle (step_of)
        self.extrema = wp.zeros(2 * S, dtype=float, device=d)
        # each scenario's step plan (time, block sub-step length, sub-step count, step), float64 as the host clock:
        # one copy per step through a ring of pinned host buffers (asynchronous on a GPU; a buffer is written again
        # only once the copy out of it has run)
        self.plan = wp.zeros(S, dtype=wp.vec4d, device=d)
        pinned = wp.get_device(d).is_cuda
        self.plan_hosts = [wp.zeros(S, dtype=wp.vec4d, device="cpu", pinned=pinned) for _ in range(PLAN_RING)]
        self.plan_events = [None] * PLAN_RING
        self.plan_uploads = 0
        self.has_blocks = has_blocks = np.array([t.blocks[1] > t.blocks[0] for t in b.tiles])
        self.coupled = has_blocks & (b.coupling is not None)
        self.multirate = has_blocks & bool(b.multirate)
        self.block_stable = np.full(S, math.inf)
        self.critical_block = [None] * S
        if b.block_solver is not None:
            safety = b.block_solver.options.dt_safety
            for k, t in enumerate(b.tiles):
                if has_blocks[k]:
                    crit, self.critical_block[k] = b.block_solver.critical_dt_of(range(*t.blocks))
                    self.block_stable[k] = safety * crit
            nb = b.blocks.num_blocks
            bo = np.zeros(nb, np.int64)
            for k, t in enumerate(b.tiles):
                bo[t.blocks[0]:t.blocks[1]] = k
            self.block_owner = bo
            self.block_owner_wp = wp.array(bo.astype(np.int32), dtype=int, device=d)
            # one clock per block (kernels/dda/blocks.py clock_of): the batch's block solver reads this one
            self.block_clock = wp.zeros(3 * max(nb, 2), dtype=float, device=d)
            b.block_solver.block_clock = self.block_clock
            self.held = (wp.zeros(nb, dtype=wp.vec3, device=d), wp.zeros(nb, dtype=wp.vec3, device=d))
            self.kinds_idle = wp.zeros(nb, dtype=int, device=d)
        self.pairs_hold = self.contacts_hold = None
        self.stepped = np.ones(S, bool)  # the scenarios that moved in the last step (all: at the start)
        self.substeps = np.ones(S, np.int64)
        self.target = np.zeros(S)
        if self.fixed:
            self.target = np.full(S, float(sim.dt_s))
        else:
            self.target = self.adaptive(np.ones(S, bool), initial=True)
        self.dt = self.target.copy()
        self._count_substeps(np.ones(S, bool))

    def limits(self, ks, initial: bool = False) -> list[dict]:
        """Scenario k's limits {name: [s]} in the solo clock's order (fluid, blocks, coupling) for k in ks."""
        b = self.b
        m = b.fluid
        if not initial and m.n_fluid:  # one read of every scenario's largest |v|^2 and |a|^2
            self.extrema.zero_()
            wp.launch(batch_k.scenario_motion_extrema, dim=m.n_fluid,
                      inputs=[b.state.v, b.state.accel, b.state.ids, self.owner], outputs=[self.extrema], device=b.device)
            ext = self.extrema.numpy().reshape(-1, 2)
        out = []
        for k in ks:
            vals = {}
            if self.n_fluid[k]:
                if initial:
                    vals["fluid"] = fluid_dt_limit(m, b.scene.simulation.cfl_number, 0.0, b._g)
                else:
                    vmax2, amax2 = float(ext[k, 0]), float(ext[k, 1])
                    vals["fluid"] = fluid_dt_limit(m, b.fluid_solver.cfl_number, math.sqrt(vmax2), math.sqrt(amax2))
            if self.has_blocks[k] and not self.multirate[k]:  # (multi-rate: the blocks' limit sets the sub-steps)
                vals["blocks"] = self.block_stable[k]
            if self.coupled[k]:
                vals["coupling"] = b.coupling.stable_dt()
            out.append(vals)
        return out

    def adaptive(self, mask: np.ndarray, initial: bool = False) -> np.ndarray:
        """The smallest of each masked scenario's limits (Clock.adaptive per scenario); ``limiting`` names it."""
        out = self.target.copy()
        ks = np.nonzero(mask)[0]
        for k, vals in zip(ks, self.limits(ks, initial)):
            if not vals:
                self.limiting[k] = ""
                out[k] = self.b.scene.simulation.duration_s
                continue
            self.limiting[k] = min(vals, key=vals.get)
            out[k] = vals[self.limiting[k]]
        return out

    def update_targets(self, active: np.ndarray) -> None:
        """Clock.update_target per scenario: every dt_update_interval of its own steps."""
        if self.fixed:
            return
        due = active & (self.steps % self.update_interval == 0)
        if due.any():
            self.target = self.adaptive(due)

    def set_dt(self, mask: np.ndarray, dts: np.ndarray) -> None:
        changed = mask & (dts != self.dt)
        if changed.any():
            self.dt[changed] = dts[changed]
            self._count_substeps(changed)

    def _count_substeps(self, mask: np.ndarray) -> None:
        """Clock._count_substeps per scenario: ceil(dt / its own stable block step) in multi-rate stepping."""
        for k in np.nonzero(mask & self.multirate)[0]:
            n = max(1, math.ceil(self.dt[k] / self.block_stable[k] - 1e-9))
            if n > MAX_BLOCK_SUBSTEPS:
                raise SceneError(self.b.scenes[k].path, [("blocks", f"scenario {k} of the batch needs {n} block sub-steps "
                                                                   f"in a fluid step of {self.dt[k]:.3g} s, more than "
                                                                   f"{MAX_BLOCK_SUBSTEPS}: soften its stiffest block")])
            self.substeps[k] = n

    def upload_plan(self, dts: np.ndarray, active: np.ndarray) -> None:
        """Copy each scenario's plan for this step to the device: its time, block sub-step length dts / n and count n
        (0 for a scenario not stepping), and its step."""
        j = self.plan_uploads % PLAN_RING
        if self.plan_events[j] is not None:
            wp.synchronize_event(self.plan_events[j])
        n_k = np.where(active, self.substeps, 0)
        host = self.plan_hosts[j].numpy()
        host[:, 0] = self.time
        host[:, 1] = np.where(active, dts / np.maximum(n_k, 1), 0.0)
        host[:, 2] = n_k
        host[:, 3] = dts
        wp.copy(self.plan, self.plan_hosts[j])
        if wp.get_device(self.b.device).is_cuda:
            with wp.ScopedDevice(self.b.device):
                self.plan_events[j] = wp.record_event()
        self.plan_uploads += 1

    def tick(self, active: np.ndarray, dts: np.ndarray) -> None:
        self.time[active] += dts[active]
        self.steps[active] += 1
        self.block_steps[active] += self.substeps[active]
        for k in np.nonzero(active)[0]:
            key = self.limiting[k] or "fixed"
            self.steps_limited_by[k][key] = self.steps_limited_by[k].get(key, 0) + 1
