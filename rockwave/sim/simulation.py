"""The facade: a scene made runnable.

Data flows one way::

    scene file -> Scene (rockwave/scene/format.py, validated)
               -> models + states + solvers (rockwave/build/builder.py)
               -> Clock (rockwave/sim/clock.py) advances the states with the solvers (rockwave/base/solver.py)
               -> readers (rockwave/sim/readers.py) and recorders (rockwave/output/recorders.py) only read

Python API::

    import rockwave
    sim = rockwave.Simulation(rockwave.load_scene("scenes/dam_break_2d.toml"), device="cpu")
    sim.advance(0.1)                 # simulate 0.1 s
    x = sim.positions()              # (n_fluid, dim) numpy array; reading never changes the state
    sim.run("runs/dam_break_2d")     # the whole scene, with outputs (rockwave/app/run.py)
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import warp as wp

from rockwave.base.device import resolve_device  # noqa: F401  (rockwave/base/device.py; re-exported)
from rockwave.base.errors import SimulationError
from rockwave.base.maths import pad3
from rockwave.base.solver import TimeStep
from rockwave.build import (
    builder,
    preflight,  # meshes and the memory estimate, before anything is allocated
)
from rockwave.coupling.penalty import CouplingOptions
from rockwave.dda.blocks import BlockOptions
from rockwave.scene.format import Scene, SceneError, load_scene
from rockwave.sim import checkpoint
from rockwave.sim.clock import MAX_BLOCK_SUBSTEPS, Clock, gravity_norm
from rockwave.sim.energy import EnergyBudget
from rockwave.sim.guard import BlowUpError, HealthGuard
from rockwave.sim.readers import Readers
from rockwave.sim.stepping import BlockSubstepping
from rockwave.sph.fluid import FluidOptions, fluid_dt_limit
from rockwave.sph.ghost import GhostOptions


@dataclass
class SimulationOptions:
    """Tuning of the parts, passed in Python (``Simulation(scene, options=...)``); defaults are the
    measured best (docs/notes.md). None: the part's own defaults and the scene's settings (rockwave/build/options.py
    says how the two meet)."""

    fluid: FluidOptions | None = None
    """The fluid solver's options (None: the defaults); cfl_number None takes the scene's simulation.cfl_number."""

    ghost: GhostOptions | None = None
    """The ghost solver's options (None: the defaults); the scene's [fluid.ghost] settings replace its scene fields
    (attempts, rounds, sampler, ...)."""

    blocks: BlockOptions | None = None
    """The block solver's options (None: the scene's simulation.block_dt_safety and block_contacts, the defaults
    for the rest)."""

    coupling: CouplingOptions | None = None
    """The water-block coupling's options (None: the scene's [coupling] section)."""

    cuda_graphs: bool = True
    """Replay a chunk of fluid-only steps, and each single step outside the chunks, as a captured CUDA graph on a
    GPU."""


class Simulation:
    """A scene made runnable: models, states, solvers, the clock and the readers.

    Attributes: ``scene``, ``device``, ``clock`` (time [s], steps, dt [s]), ``fluid`` (FluidModel),
    ``state`` (FluidState), ``fluid_solver``, ``blocks`` (BlockModel), ``block_state``,
    ``block_solver``, ``coupling`` (None where the scene has none of them)."""

    def __init__(self, scene: Scene | str | os.PathLike, device: str | None = None,
                 options: SimulationOptions | None = None):
        if not isinstance(scene, Scene):
            scene = load_scene(scene)
        self.scene = scene
        self.options = options or SimulationOptions()
        self.device = resolve_device(device if device is not None else scene.simulation.device)

        self.estimate = preflight.check_scene(scene, self.device)
        parts = self._build_parts(scene)
        self.fluid, self.state, self.fluid_solver = parts.fluid, parts.state, parts.fluid_solver
        self.blocks, self.block_state, self.block_solver = parts.blocks, parts.block_state, parts.block_solver
        self.coupling = parts.coupling
        self.removed_inside_blocks = parts.removed_inside_blocks
        self.gravity = np.asarray(pad3(scene.gravity.acceleration_m_s2))
        self.clock = Clock(scene, self.device, self._limits(), self._stability_bounds(), self._block_substep())
        self.block_stepping = BlockSubstepping(self.clock) if self.block_solver is not None else None
        self.gauge_names = [g.name for g in scene.output.gauges]
        if self.coupling is not None and self.coupling.walls is not None:  # the walls' acceleration estimate
            walls = self.coupling.walls
            checkpoint.register(self, "block_walls", checkpoint.ArrayGroup(lambda: walls, ["v_prev", "w_prev", "dt_prev"]))
        self._readers = None
        self._graphs: dict = {}  # captured CUDA graphs of chunks and single steps (_replay)
        self._graphs_failed = False
        self._plain_runs: set = set()  # kinds of launches run plainly once (their kernels are loaded)

    def _build_parts(self, scene: Scene):
        """The scene's models, states and solvers (rockwave/build/builder.py; a rank of a distributed run builds
        only its slab of the water)."""
        return builder.build(scene, self.device, self.options)

    # ---------------------------------------------------------------- the clock's questions ----
    @property
    def multirate(self) -> bool:
        """Blocks sub-step inside each fluid step (simulation.block_stepping = 'multirate' with water and
        blocks; rockwave/sim/clock.py)."""
        return (self.block_solver is not None and self.coupling is not None
                and self.scene.simulation.get("block_stepping", "multirate") == "multirate")

    def _block_substep(self):
        """Multi-rate: (the blocks' stable step [s], f(n) -> the SceneError of a sub-step count n above
        the cap, naming the stiffness to soften); None: one block step per step."""
        if not self.multirate:
            return None

        stable = self.block_solver.stable_dt(self.block_state)

        def error(n: int, dt: float) -> SceneError:
            b, mode = self.block_solver.critical_block()
            name = self.blocks.names[b]
            hits = [f"{sec}[{i}]" for sec, ents in (("blocks", self.scene.blocks), ("rock_mass", self.scene.rock_mass))
                    for i, e in enumerate(ents) if name == e.name or name.startswith(f"{e.name}_")]
            where = hits[0] if hits else "blocks"
            if mode == "strain":
                key, what = f"{where}.youngs_modulus_pa", "the strain modes of the deformable block"
            else:
                key = f"{where}.material.normal_stiffness_n_m"
                what = f"its contact stiffness k_n = {self.blocks.np['k_n'][b]:.3g} N/m per point"
            return SceneError(self.scene.path, [(key, (
                f"block {name!r} needs {n} sub-steps of {stable:.3g} s in each fluid step of {dt:.3g} s, more than "
                f"{MAX_BLOCK_SUBSTEPS} ({what}); soften it (the sub-step grows as 1/sqrt(k)) or set "
                f"simulation.block_stepping = 'single'"))])

        return stable, error

    def _limits(self) -> dict:
        """Each present solver's stable step, f(initial) [s] (rockwave/sim/clock.py); in multi-rate stepping
        the blocks' limit sets their sub-step instead (_block_substep)."""
        out = {}
        if self.fluid is not None and self.fluid.n_fluid:

            g = gravity_norm(self.scene)
            out["fluid"] = lambda initial: (fluid_dt_limit(self.fluid, self.scene.simulation.cfl_number, 0.0, g) if initial
                                            else self.fluid_solver.stable_dt(self.state))
        if self.block_solver is not None and not self.multirate:
            out["blocks"] = lambda initial: self.block_solver.stable_dt(self.block_state)  # dt_safety x critical
        if self.coupling is not None:
            out["coupling"] = lambda initial: self.coupling.stable_dt()  # dt_safety (0.5) x critical
        return out

    def _stability_bounds(self) -> list:
        """Hard limits a fixed step must respect: fluid at rest (0.4 h/c0, gravity), blocks 2/omega_max."""
        out = []
        if self.fluid is not None:

            out.append((fluid_dt_limit(self.fluid, 0.4, 0.0, gravity_norm(self.scene)),
                        f"0.4 h/c0 with h = {0.5 * self.fluid.support_radius:g} m, c0 = {self.fluid.sound_speed:g} m/s"))
        if self.block_solver is not None and not self.multirate:
            out.append((self.block_solver.critical_dt(), "the critical DDA step 2/omega_max of the stiffest block contact"))
        if self.coupling is not None:
            out.append((self.coupling.critical_dt(),
                        "the critical step of the fluid-block penalty spring (coupling.stiffness_factor)"))
        return out

    # clock views (read-only conveniences)
    time = property(lambda self: self.clock.time)
    steps = property(lambda self: self.clock.steps)
    dt = property(lambda self: self.clock.dt)
    fixed = property(lambda self: self.clock.fixed)
    dt_limit = property(lambda self: self.clock.stability_limit)

    # ---------------------------------------------------------------- stepping --------------
    def step(self, dt: float | None = None) -> None:
        """One step of length ``dt`` (default: the current step)."""
        if dt is not None:
            self.clock.set_dt(dt)
        with wp.ScopedDevice(self.device):
            # a fluid-only scene on a GPU replays one captured step: plain launches would sort the particles
            # by cell every step (the skipped list build's radix sort) and wait on the host's launches
            ts = self.clock.time_step()
            if not self._replay(("step",), lambda: self._launch_step(ts)):
                self._launch_step(ts)
                self._plain_runs.add(("step",))
        self.clock.tick()

    def _launch_step(self, ts: TimeStep, reorder: bool = False) -> None:
        """The launches of one step; ``reorder`` first sorts the fluid particles by cell."""
        if reorder:
            self.fluid_solver.reorder(self.state)
        if self.coupling is not None:  # forces from the state at t (rockwave/coupling/penalty.py)
            self.coupling.compute(self.state, self.block_state, ts)
        if self.fluid_solver is not None:
            self.fluid_solver.step(self.state, ts)
        if self.coupling is not None:
            self.coupling.apply(self.state, ts)
        if self.block_solver is not None:  # 2D: with the planar constraint
            self.block_stepping.advance(self.block_solver, self.block_state, ts)

    # Chunks (step_many; advance on a GPU): a reorder of the fluid by cell, then reorder_interval
    # steps. A fluid-only scene on a GPU replays a chunk as one CUDA graph (dt is read from the device
    # array clock.dt_array, so one graph serves every dt); blocks and the coupling read counters back
    # each step, and the ghost step reads its ghost count, so their chunks are plain launches. The block
    # sub-step count (multi-rate) follows dt alone, so it is fixed within a chunk.
    def _chunk_size(self) -> int:
        fs = self.fluid_solver
        if fs is None or self.fluid.n_fluid == 0:
            return 0
        return fs.reorder_interval

    def _graph_usable(self) -> bool:
        return (self.options.cuda_graphs and not self._graphs_failed and self.coupling is None
                and self.block_solver is None and self.fluid_solver is not None
                and wp.get_device(self.device).is_cuda and self.fluid_solver.capturable)

    def _replay(self, key: tuple, launches) -> bool:
        """Launch the CUDA graph of ``launches`` (a function that makes the launches) under ``key``, captured on
        its first use, once a plain run of the same launches has loaded their kernels. False where graphs are not
        usable or not yet: the caller launches plainly and adds the key to _plain_runs. The graphs read dt from
        the device array and rebuild the neighbour lists as a conditional node (rockwave/sph/fluid.py), so one graph
        serves every step of its kind; reallocated lists (FluidSolver.arrays_version) get a new capture."""
        if not (self._graph_usable() and key in self._plain_runs):
            return False
        full = (id(self.state), id(self.fluid_solver), self.fluid_solver.arrays_version) + key
        g = self._graphs.get(full)
        if g is None:
            try:
                with wp.ScopedCapture(device=self.device, force_module_load=False) as cap:
                    launches()
            except Exception:  # capture unsupported here: plain launches from now on
                self._graphs_failed = True
                self._graphs.clear()
                return False
            g = self._graphs[full] = cap.graph
        wp.capture_launch(g)
        return True

    def _run_chunk(self, k: int) -> None:
        """k steps at the current dt after a reorder: one graph launch (_replay) or plain launches."""
        clock = self.clock
        with wp.ScopedDevice(self.device):
            def launches():
                for j in range(k):
                    self._launch_step(clock.time_step(), reorder=j == 0)

            if not self._replay(("chunk", k), launches):
                t0 = clock.time
                for j in range(k):  # each step at its own start time (kinematic blocks read it)
                    self._launch_step(TimeStep(clock.dt, t0 + j * clock.dt, clock.dt_array), reorder=j == 0)
                self._plain_runs.add(("chunk", k))
        clock.tick(k)

    def step_many(self, n: int) -> None:
        """n steps at the current dt, in reorder chunks (CUDA graphs where possible)."""
        k = self._chunk_size()
        while k and n >= k:
            self._run_chunk(k)
            n -= k
        for _ in range(n):
            self.step()

    def advance(self, duration: float, watch=None) -> None:
        """Advance by ``duration`` seconds, landing exactly on the end time. ``watch()``, when given, is
        called after every step or chunk (an observer: the run loop's wall-clock progress and health checks;
        it must only read)."""
        clock = self.clock
        t_end = clock.time + duration
        while t_end - clock.time > 1e-12 * max(1.0, t_end):
            clock.update_target()
            remaining = t_end - clock.time
            n = max(1, math.ceil(remaining / clock.target - 1e-9))
            k = self._chunk_size() if wp.get_device(self.device).is_cuda else 0  # the CPU path steps one by one
            if clock.chunk_allowed(k, n):
                clock.set_dt(remaining / n)
                self._run_chunk(k)
            else:
                self.step(remaining / n)
            if watch is not None:
                watch()
        clock.time = t_end

    # ---------------------------------------------------------------- reading -----------------
    @property
    def readers(self):
        """rockwave.sim.readers.Readers of this simulation (host copies in the seeded particle order)."""

        if self._readers is None or self._readers.fluid is not self.fluid:
            self._readers = Readers(self)
        return self._readers

    @property
    def n_fluid(self) -> int:
        return self.fluid.n_fluid if self.fluid is not None else 0

    def positions(self) -> np.ndarray:
        """Fluid particle positions, (n_fluid, dim) [m]."""
        return self.readers.positions()

    def velocities(self) -> np.ndarray:
        """Fluid particle velocities, (n_fluid, dim) [m/s]."""
        return self.readers.velocities()

    def densities(self) -> np.ndarray:
        """Fluid particle densities, (n_fluid,) [kg/m^3]."""
        return self.readers.densities()

    def pressures(self) -> np.ndarray:
        """Fluid particle pressures, (n_fluid,) [Pa]."""
        return self.readers.pressures()

    def boundary_positions(self) -> np.ndarray:
        return self.readers.boundary_positions()

    def block_positions(self) -> np.ndarray:
        """Block centroids, (n_blocks, 3) [m]."""
        return self.block_state.positions_numpy() if self.blocks is not None else np.zeros((0, 3))

    def block_velocities(self) -> np.ndarray:
        return self.block_state.velocities_numpy() if self.blocks is not None else np.zeros((0, 3))

    def kinetic_energy(self) -> float:
        """Kinetic energy of the water (per metre of depth in 2D) plus the blocks [J]."""
        e = 0.0
        if self.fluid is not None:
            v = self.velocities()
            e += 0.5 * self.fluid.fluid_mass * float((v * v).sum())
        if self.blocks is not None:
            e += self.block_state.kinetic_energy()
        return e

    def gauges(self) -> dict[str, float]:
        """Current gauge readings by name: 'height' gauges in m (NaN when dry), 'pressure' gauges in Pa, 'force'
        gauges in N (2D: N per metre) (rockwave/sim/readers.py Gauges, evaluated on the device)."""
        return self.readers.gauges()

    def check_health(self, x: np.ndarray, v: np.ndarray) -> int:
        """Blow-up guard (rockwave/sim/guard.py): raise SimulationError on NaN/inf, runaway speed, the water
        flying apart or an energy jump (the message gives step, time, where and a suggested time step);
        return the count of fluid particles outside the domain (not fatal)."""
        try:
            return self.guard.check(x, v)
        except BlowUpError as e:
            err = SimulationError(str(e))
            err.__dict__.update(e.__dict__)
            raise err from None

    @property
    def guard(self) -> HealthGuard:
        """The blow-up guard of this run (rockwave/sim/guard.py HealthGuard): made at its first check; its counters
        (``left``: fluid particles outside the domain, ``left_top``) are the run's."""
        if getattr(self, "_guard", None) is None:
            self._guard = HealthGuard(self)
        return self._guard

    @property
    def energy(self):
        """The run's energy budget (rockwave/sim/energy.py EnergyBudget): ``sim.energy.measure()`` reads one row
        (the first call sets the start every later row is compared with)."""
        if getattr(self, "_energy", None) is None:
            self._energy = EnergyBudget(self)
        return self._energy

    def check_energy(self, row: dict) -> bool:
        """The guard's energy check on a budget row (rockwave/sim/guard.py check_energy): a warning, or a
        SimulationError with simulation.energy_check = 'error'; False when the growth is beyond the bound."""
        try:
            return self.guard.check_energy(self.energy, row)
        except BlowUpError as e:
            err = SimulationError(str(e))
            err.__dict__.update(e.__dict__)
            raise err from None

    # ---------------------------------------------------------------- running -----------------
    def run(self, out_dir: str | os.PathLike, duration: float | None = None, progress: bool = True,
            resume: bool = False, checkpoint_interval_s: float | None = None, force: bool = False) -> dict:
        """Run the scene with outputs into ``out_dir``; see rockwave.app.run.run."""
        from rockwave.app.run import run  # the one upward import (tests/test_layers.py EXCEPTIONS): the run loop

        return run(self, out_dir, duration=duration, progress=progress, resume=resume,
                   checkpoint_interval_s=checkpoint_interval_s, force=force)
