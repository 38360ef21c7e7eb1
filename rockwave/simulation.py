"""The clock: builds the model from a scene, chooses the time step, advances the solvers and
writes frames, gauges and a run summary.

Python API::

    import rockwave
    sim = rockwave.Simulation(rockwave.load_scene("scenes/dam_break_2d.toml"), device="cpu")
    sim.advance(0.1)                 # simulate 0.1 s
    x = sim.positions()              # (n_fluid, dim) numpy array
    sim.run("runs/dam_break_2d")     # the whole scene, with outputs
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import sys
import time
from pathlib import Path

import re

import numpy as np
import warp as wp
from pxr import Gf

from rockwave import sampling
from rockwave.fluid import FluidSolver, build_fluid_model, fluid_dt_limit
from rockwave.kernels import sph
from rockwave.scene import Scene, SceneError, load_scene
from rockwave.device import resolve_device  # noqa: F401  (rockwave/device.py; re-exported)


class SimulationError(RuntimeError):
    """The run cannot go on (blow-up, unwritable output); the message says where and why."""


def hydrostatic_density(model, g_depth: np.ndarray) -> np.ndarray:
    """Density that makes p = rho0 g d under the EOS (validation/README.md, Hydrostatics):
    Tait rho = rho0 (1 + rho0 g d / B)^(1/gamma); linear rho = rho0 + rho0 g d / k."""
    p = model.params
    rho0 = p.rest_density
    if p.eos == 0:
        return rho0 * (1.0 + rho0 * g_depth / p.eos_b) ** (1.0 / p.eos_gamma)
    return rho0 + rho0 * g_depth / p.eos_b


def _pad3(v) -> list[float]:
    return list(v) + [0.0] * (3 - len(v))


def boundary_lattice(scene: Scene) -> tuple[float, int]:
    """Boundary particle spacing and number of layers for a scene."""
    t, spacing = scene.tank, scene.fluid.spacing_m
    if t is None:  # water held by fixed blocks only (rockwave/coupling.py): no boundary particles
        return spacing, 1
    bstep = spacing * t.boundary_spacing_ratio
    H = scene.fluid.support_radius_ratio * spacing
    return bstep, (t.layers or max(1, int(math.ceil(H / bstep - 1e-9))))


def seed_particles(scene: Scene, device: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fluid positions, velocities, depths below their region's top (for the hydrostatic start),
    and boundary positions for a scene (positions (n, 3), z = 0 in 2D)."""
    fl, dim = scene.fluid, scene.dim
    up = dim - 1
    spacing = fl.spacing_m
    xs, vs, ds = [], [], []
    for r in fl.regions:
        try:
            p = sampling.fill_region(r, spacing, dim, device)
        except sampling.MeshInputError as e:
            raise SceneError(scene.path, [("fluid.regions", str(e))]) from None
        xs.append(p)
        ds.append(p[:, up].max() + 0.5 * spacing - p[:, up] if len(p) else np.zeros(0))
        vel = _pad3(r.velocity_m_s) if r.velocity_m_s is not None else [0.0, 0.0, 0.0]
        vs.append(np.tile(np.asarray(vel, float), (len(p), 1)))
    x = np.concatenate(xs) if xs else np.zeros((0, 3))
    v = np.concatenate(vs) if vs else np.zeros((0, 3))
    depth = np.concatenate(ds) if ds else np.zeros(0)
    # Boundary particles: tank walls and obstacles.
    t = scene.tank
    bstep, layers = boundary_lattice(scene)
    parts = []
    try:
        if t is None:  # walls from fixed blocks (rockwave/coupling.py)
            keep = np.ones(len(x), bool)
        elif t.box_min_m is not None:
            parts.append(sampling.box_shell(t.box_min_m, t.box_max_m, bstep, layers, True, t.open_top, up))
            keep = np.all((x[:, :dim] > np.asarray(t.box_min_m)) & (x[:, :dim] < np.asarray(t.box_max_m)), axis=1)
        else:
            parts.append(sampling.mesh_shell(t.mesh, t.mesh_scale, t.mesh_offset_m, bstep, layers, True, device))
            tm = sampling.load_trimesh(t.mesh, t.mesh_scale, t.mesh_offset_m)
            keep = sampling.mesh_signed_distance(tm, x, device) < 0
    except sampling.MeshInputError as e:
        raise SceneError(scene.path, [("tank.mesh", str(e))]) from None
    x, v, depth = x[keep], v[keep], depth[keep]
    for i, ob in enumerate(scene.obstacles):
        try:
            if ob.box_min_m is not None:
                parts.append(sampling.box_shell(ob.box_min_m, ob.box_max_m, bstep, layers, False, False, up))
            else:
                parts.append(sampling.mesh_shell(ob.mesh, ob.mesh_scale, ob.mesh_offset_m, bstep, layers, False, device))
            inside = sampling.inside_obstacle(x, ob, dim, device)
        except sampling.MeshInputError as e:
            raise SceneError(scene.path, [(f"obstacles[{i}].mesh", str(e))]) from None
        x, v, depth = x[~inside], v[~inside], depth[~inside]
    b = np.concatenate(parts) if parts else np.zeros((0, 3))
    return x, v, depth, b


class Simulation:
    """A scene made runnable: model, state, solvers and the clock.

    Attributes: ``scene``, ``device``, ``fluid`` (FluidModel), ``state`` (FluidState),
    ``time`` [s], ``steps``, ``dt`` [s] (the step in use).
    """

    def __init__(self, scene: Scene | str | os.PathLike, device: str | None = None):
        if not isinstance(scene, Scene):
            scene = load_scene(scene)
        self.scene = scene
        self.device = resolve_device(device if device is not None else scene.simulation.device)
        from rockwave import preflight  # meshes and the memory estimate, before anything is allocated

        self.estimate = preflight.check_scene(scene, self.device)
        self.fluid = self.fluid_solver = self.state = None
        self.blocks = self.block_solver = self.block_state = None
        g = float(np.linalg.norm(scene.gravity.acceleration_m_s2))
        self.coupling = None
        self.removed_inside_blocks = 0
        with wp.ScopedDevice(self.device):
            if scene.blocks:
                self._build_blocks()
            if scene.fluid is not None:
                xf, vf, depth, xb = seed_particles(scene, self.device)
                if self.blocks is not None:
                    xf, vf, depth = self._remove_inside_blocks(xf, vf, depth)
                bstep, layers = boundary_lattice(scene)
                self.fluid = build_fluid_model(xf, vf, xb, scene.fluid, scene.dim, scene.gravity.acceleration_m_s2,
                                               self.device, bstep, layers)
                if scene.fluid.method == "ghost":
                    from rockwave.ghost import GhostFluidSolver, warn_unstable_step  # basic scenes never load it

                    warn_unstable_step(scene)
                    self.fluid_solver = GhostFluidSolver(self.fluid, scene.fluid.ghost)
                else:
                    self.fluid_solver = FluidSolver(self.fluid)
                self.state = self.fluid.state()
                if self.fluid.n_fluid:
                    self.fluid_solver.build_grid(self.state)
                    if self.fluid.density_mode == "summation":
                        self.fluid_solver.compute_density(self.state)
                    else:
                        self.fluid_solver.set_density(self.state, hydrostatic_density(self.fluid, g * depth))
            if self.blocks is not None and self.fluid is not None and self.fluid.n_fluid:
                self._build_coupling()
        self.time = 0.0
        self.steps = 0
        self.gravity = np.asarray(_pad3(scene.gravity.acceleration_m_s2))
        sim = scene.simulation
        self.fixed = sim.time_step == "fixed"
        # stability bounds: fluid at rest (0.4 h/c0, force limit from gravity); blocks 2/omega_max
        limits = []
        if self.fluid is not None:
            limits.append((fluid_dt_limit(self.fluid, 0.4, 0.0, g),
                           f"0.4 h/c0 with h = {0.5 * self.fluid.support_radius:g} m, c0 = {self.fluid.sound_speed:g} m/s"))
        if self.block_solver is not None:
            limits.append((self.block_solver.critical_dt(), "the critical DDA step 2/omega_max of the stiffest block contact"))
        if self.coupling is not None:
            limits.append((self.coupling.critical_dt(), "the critical step of the fluid-block penalty spring (coupling.stiffness_factor)"))
        self.dt_limit, why = min(limits)
        if self.fixed:
            if sim.dt_s > self.dt_limit:
                raise SceneError(scene.path, [("simulation.dt_s", f"{sim.dt_s:g} s is above the stability limit {self.dt_limit:.3g} s ({why})")])
            self._dt_target = sim.dt_s
        else:
            self._dt_target = self._adaptive_dt(initial=True)
        self.dt = self._dt_target
        self._dt_dev = wp.array([self.dt], dtype=float, device=self.device)
        self._up = scene.dim - 1
        gauges = scene.output.gauges
        self.gauge_names = [gg.name for gg in gauges]
        self._gauge_kind = [gg.kind for gg in gauges]
        self._gauge_pos = wp.array(np.asarray([_pad3(gg.position_m) for gg in gauges] or np.zeros((0, 3)), dtype=np.float32),
                                   dtype=wp.vec3, device=self.device)

    def _build_blocks(self) -> None:
        from rockwave.blocks import BlockModel, BlockOverlapError, BlockSolver, check_initial_overlap_on_device
        from rockwave.geometry import GeometryError
        from rockwave.rocks import block_specs

        specs = block_specs(self.scene)
        host_check = len(specs) <= 2000  # exact host test for small sets; device FCP for large ones
        try:
            self.blocks = BlockModel(specs, device=self.device, gravity=_pad3(self.scene.gravity.acceleration_m_s2),
                                     check_overlap=host_check)
            self.block_solver = BlockSolver(self.blocks)
            self.block_state = self.blocks.state()
            if not host_check:
                check_initial_overlap_on_device(self.block_solver, self.block_state)
        except BlockOverlapError as e:
            raise SceneError(self.scene.path, [("blocks", str(e))]) from None
        except (GeometryError, ValueError) as e:
            raise SceneError(self.scene.path, [("blocks", str(e))]) from None
        self._planar = None
        if self.scene.dim == 2:  # 2D: extruded prisms moving in the x-y plane (rockwave/coupling.py)
            z0 = wp.array(self.blocks.base_position[:, 2].astype(np.float32), dtype=float, device=self.device)
            self._planar = (z0, self.blocks.kinds)

    def _remove_inside_blocks(self, xf, vf, depth):
        """Drop fluid particles inside a block, or closer to its faces than half the contact distance
        (rockwave/coupling.py); the count is kept in ``removed_inside_blocks`` and run.json."""
        from rockwave.coupling import DEFAULT_D0_RATIO, block_signed_distance

        c = self.scene.coupling
        ratio = c.contact_distance_ratio if c is not None and c.contact_distance_ratio is not None else DEFAULT_D0_RATIO
        dist, _ = block_signed_distance(self.blocks, self.block_state, xf)
        keep = dist >= 0.5 * ratio * self.scene.fluid.spacing_m
        self.removed_inside_blocks = int((~keep).sum())
        return xf[keep], vf[keep], depth[keep]

    def _build_coupling(self) -> None:
        from rockwave.coupling import Coupling

        c = self.scene.coupling
        kw = {}
        if c is not None:
            kw = dict(stiffness_factor=c.stiffness_factor, damping_ratio=c.damping_ratio, k_s=c.stiffness_n_m, k_d=c.damping_n_s_m,
                      d0=None if c.contact_distance_ratio is None else c.contact_distance_ratio * self.fluid.spacing,
                      squeeze_out=c.squeeze_out is not False)
        self.coupling = Coupling(self.fluid, self.blocks, self.scene.dim, **kw)

    def _adaptive_dt(self, initial: bool = False) -> float:
        """The smaller of the fluid's CFL/force/viscous step and half the critical DDA step."""
        sim = self.scene.simulation
        dts = []
        if self.fluid is not None and self.fluid.n_fluid:
            if initial:
                dts.append(fluid_dt_limit(self.fluid, sim.cfl_number, 0.0, float(np.linalg.norm(self.scene.gravity.acceleration_m_s2))))
            else:
                dts.append(self.fluid_solver.stable_dt(self.state, sim.cfl_number))
        if self.block_solver is not None:
            dts.append(self.block_solver.stable_dt(sim.block_dt_safety))
        if self.coupling is not None:
            dts.append(0.5 * self.coupling.critical_dt())
        return min(dts) if dts else sim.duration_s

    # ---------------------------------------------------------------- stepping --------------
    def _set_dt(self, dt: float) -> None:
        if dt != self.dt:
            self.dt = dt
            self._dt_dev.fill_(dt)

    def step(self, dt: float | None = None) -> None:
        """One step of length ``dt`` (default: the current step)."""
        if dt is not None:
            self._set_dt(dt)
        with wp.ScopedDevice(self.device):
            self._launch_step()
        self.time += self.dt
        self.steps += 1

    def _launch_step(self, reorder: bool = False) -> None:
        """The launches of one step at the current dt (device array _dt_dev); ``reorder`` first sorts
        the fluid particles by cell (FluidSolver.reorder)."""
        if reorder:
            self.fluid_solver.reorder(self.state)
        if self.coupling is not None:  # forces from the state at t (rockwave/coupling.py)
            self.coupling.compute(self.state, self.block_state, self._dt_dev)
        if self.fluid_solver is not None:
            self.fluid_solver.step(self.state, self._dt_dev)
        if self.coupling is not None:
            self.coupling.apply(self.state, self._dt_dev)
        if self.block_solver is not None:
            self.block_solver.step(self.block_state, self.dt, self.time)
            if self._planar is not None:
                from rockwave.coupling import planar_constraint

                planar_constraint(self.block_state, *self._planar)

    # Chunks (step_many; advance on a GPU): a reorder of the fluid by cell, then
    # fluid_solver.reorder_interval steps. A fluid-only scene on a GPU replays a chunk as one CUDA
    # graph (dt is read from the device array _dt_dev, so one graph serves every dt); blocks and the
    # coupling read counters back each step, so their chunks are plain launches.
    use_graphs = True

    def _chunk_size(self) -> int:
        fs = self.fluid_solver
        if fs is None or self.fluid.n_fluid == 0 or fs.reorder_interval <= 0:
            return 0
        return fs.reorder_interval

    def _graph_usable(self) -> bool:
        return (self.use_graphs and not getattr(self, "_graph_failed", False) and self.coupling is None
                and self.block_solver is None and wp.get_device(self.device).is_cuda
                and type(self.fluid_solver).step is FluidSolver.step)

    def _run_chunk(self, k: int) -> None:
        """k steps at the current dt after a reorder: one graph launch (captured on the second use,
        after a plain chunk has loaded the kernels) or plain launches."""
        with wp.ScopedDevice(self.device):
            key = (id(self.state), id(self.fluid_solver), k)
            done = False
            if self._graph_usable() and getattr(self, "_chunks_plain", 0) > 0:
                if getattr(self, "_graph_key", None) != key:
                    try:
                        with wp.ScopedCapture(device=self.device, force_module_load=False) as cap:
                            for j in range(k):
                                self._launch_step(reorder=j == 0)
                        self._graph, self._graph_key = cap.graph, key
                    except Exception:  # capture unsupported here: plain launches from now on
                        self._graph_failed = True
                if getattr(self, "_graph_key", None) == key and not getattr(self, "_graph_failed", False):
                    wp.capture_launch(self._graph)
                    done = True
            if not done:
                for j in range(k):
                    self._launch_step(reorder=j == 0)
                self._chunks_plain = getattr(self, "_chunks_plain", 0) + 1
        self.time += k * self.dt
        self.steps += k

    def step_many(self, n: int) -> None:
        """n steps at the current dt, in reorder chunks (CUDA graphs where possible). The state
        arrays are then in the solver's particle order (state.ids); positions() etc. restore the
        original order."""
        k = self._chunk_size()
        while k and n >= k:
            self._run_chunk(k)
            n -= k
        for _ in range(n):
            self.step()

    def _canonical(self) -> None:
        """Put the fluid back in its original particle order before a host read."""
        if self.fluid_solver is not None and self.state is not None:
            with wp.ScopedDevice(self.device):
                self.fluid_solver.unsort(self.state)

    def _update_dt_target(self) -> None:
        if not self.fixed and self.steps % self.scene.simulation.dt_update_interval == 0:
            self._dt_target = self._adaptive_dt()

    def advance(self, duration: float) -> None:
        """Advance by ``duration`` seconds, landing exactly on the end time."""
        t_end = self.time + duration
        while t_end - self.time > 1e-12 * max(1.0, t_end):
            self._update_dt_target()
            remaining = t_end - self.time
            n = max(1, math.ceil(remaining / self._dt_target - 1e-9))
            k = self._chunk_size() if wp.get_device(self.device).is_cuda else 0  # the CPU path steps one by one
            interval = self.scene.simulation.dt_update_interval
            # a chunk must not pass a step where the adaptive dt is updated
            if 0 < k <= n and (self.fixed or (-self.steps) % interval == 0 and interval >= k or (-self.steps) % interval >= k):
                self._set_dt(remaining / n)
                self._run_chunk(k)
                continue
            self.step(remaining / n)
        self.time = t_end
        self._canonical()

    # ---------------------------------------------------------------- reading -----------------
    @property
    def n_fluid(self) -> int:
        return self.fluid.n_fluid if self.fluid is not None else 0

    def positions(self) -> np.ndarray:
        """Fluid particle positions, (n_fluid, dim) [m]."""
        if self.fluid is None:
            return np.zeros((0, self.scene.dim))
        self._canonical()
        return self.state.x.numpy()[: self.fluid.n_fluid, : self.scene.dim].astype(np.float64)

    def velocities(self) -> np.ndarray:
        if self.fluid is None:
            return np.zeros((0, self.scene.dim))
        self._canonical()
        return self.state.v.numpy()[: self.fluid.n_fluid, : self.scene.dim].astype(np.float64)

    def block_positions(self) -> np.ndarray:
        """Block centroids, (n_blocks, 3) [m]."""
        return self.block_state.positions_numpy() if self.blocks is not None else np.zeros((0, 3))

    def block_velocities(self) -> np.ndarray:
        return self.block_state.velocities_numpy() if self.blocks is not None else np.zeros((0, 3))

    def densities(self) -> np.ndarray:
        self._canonical()
        return self.state.rho.numpy().astype(np.float64)

    def pressures(self) -> np.ndarray:
        self._canonical()
        return self.state.pressure.numpy().astype(np.float64)

    def boundary_positions(self) -> np.ndarray:
        return self.state.x.numpy()[self.fluid.n_fluid:, : self.scene.dim].astype(np.float64)

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
        """Current gauge readings: 'height' gauges in m (NaN when dry), 'pressure' gauges in Pa.

        A 'height' gauge reads the free surface over a horizontal window of the kernel support radius H
        around its vertical line (the finest scale the SPH resolves): the plane is cut into columns one
        particle spacing s wide, those whose centre lies within H are used (2D: 2H/s columns; 3D: 12 at
        H = 2s), each wet column's top is its highest particle + s/2, and the reading is the median over
        the wet columns (NaN when none is wet). A splashed particle or a column whose top particle has
        just drifted into its neighbour does not move it (before: the highest particle within s decided
        the reading alone, so single splash particles set wave heights).
        """
        n = len(self.gauge_names)
        if n == 0 or self.n_fluid == 0:
            return {}
        m = self.fluid
        cols = max(1, int(math.ceil(m.support_radius / m.spacing - 1e-6)))
        with wp.ScopedDevice(self.device):
            top = wp.full((n, 4 * cols * cols), -1.0e30, dtype=float)
            wp.launch(sph.gauge_height, dim=(m.n_fluid, n), inputs=[self.state.x, self._gauge_pos, self._up, m.support_radius, m.spacing, cols],
                      outputs=[top])
            self.fluid_solver.build_grid(self.state)
            pr = wp.zeros(n, dtype=float)
            wp.launch(sph.gauge_pressure, dim=n, inputs=[self.fluid_solver.grid.id, self.state.x, self.state.rho, self.state.pressure,
                                                       m.particle_mass, self._gauge_pos, m.params], outputs=[pr])
        tn, pn = top.numpy(), pr.numpy()
        out = {}
        for i, (name, kind) in enumerate(zip(self.gauge_names, self._gauge_kind)):
            if kind == "height":
                wet = tn[i][tn[i] > -1e29]
                out[name] = float(np.median(wet) + 0.5 * m.spacing) if len(wet) else float("nan")
            else:
                out[name] = float(pn[i])
        return out

    def check_health(self, x: np.ndarray, v: np.ndarray) -> int:
        """Blow-up guard (rockwave/guard.py): raise SimulationError on NaN/inf, runaway speed, the water
        flying apart or an energy jump (the message gives step, time, where and a suggested time step);
        return the count of fluid particles outside the domain (not fatal)."""
        from rockwave.guard import BlowUpError, HealthGuard

        if getattr(self, "_guard", None) is None:
            self._guard = HealthGuard(self)
        try:
            return self._guard.check(x, v)
        except BlowUpError as e:
            err = SimulationError(str(e))
            err.__dict__.update(e.__dict__)
            raise err from None

    # ---------------------------------------------------------------- running -----------------
    def run(self, out_dir: str | os.PathLike, duration: float | None = None, progress: bool = True,
            resume: bool = False, checkpoint_interval_s: float | None = None) -> dict:
        """Run the scene for ``duration`` (default: the scene's), writing outputs into ``out_dir``.
        Returns the run summary (also written as ``run.json``).

        ``resume``: continue from ``out_dir/checkpoint.npz`` (rockwave/checkpoint.py) with the outputs
        written so far. ``checkpoint_interval_s``: wall-clock seconds between checkpoints (default
        ``output.checkpoint_interval_s``; 0: none, except on a blow-up or Ctrl-C). Ctrl-C finishes the
        current frame, writes a checkpoint, closes the USD stage and raises KeyboardInterrupt."""
        from rockwave import checkpoint as ckpt
        from rockwave.export.usd import UsdFrameWriter, points_setup
        from rockwave.progress import Progress

        scene = self.scene
        out = Path(out_dir)
        resumed = ckpt.read_file(out / ckpt.FILE_NAME) if resume else None
        try:
            out.mkdir(parents=True, exist_ok=True)
            probe = out / ".write_test"
            probe.write_bytes(b"ok")
            probe.unlink()
        except OSError as e:
            raise SimulationError(f"output folder {out} is not writable: {e}") from None
        duration = scene.simulation.duration_s if duration is None else duration
        fps = scene.output.frame_rate_hz
        if resumed is not None:
            ckpt.restore(self, *resumed)
        else:
            ckpt.clear(out)
        n_frames = int(math.floor(duration * fps + 1e-9))
        frame_dt = 1.0 / fps
        nf, dim = self.n_fluid, scene.dim
        block_prims = block_prim_paths(self.blocks.names) if self.blocks is not None else []
        deformable = [s.kind == "deformable" for s in self.blocks.specs] if self.blocks is not None else []
        writer = None
        from rockwave.export.render import RenderOutputs

        render = RenderOutputs(self, out)  # fluid surface, fluid fields, ParaView series (rockwave/export/render.py)
        if scene.output.usd:
            def setup(stage):
                render.usd_setup(stage)
                if self.fluid is not None:
                    points_setup("/World/fluid", nf, self.fluid.spacing)(stage)
                if self.blocks is not None:
                    blocks_setup(stage, self.blocks, block_prims)

            writer = UsdFrameWriter(out / scene.output.usd, fps, "Z" if dim == 3 else "Y", setup, scene.output.chunk_frames)
        gauge_rows: list[list[float]] = []
        gauge_path = out / scene.output.gauges_csv if self.gauge_names and scene.output.gauges_csv else None
        block_rows: list[list] = []
        block_path = out / scene.output.blocks_csv if self.blocks is not None and scene.output.blocks_csv else None
        bar = Progress(duration, nf if nf else (self.blocks.num_blocks if self.blocks is not None else 0), enabled=progress,
                       unit="particles" if nf else "blocks")
        wall0 = time.perf_counter()
        escaped = 0
        t0 = self.time
        interrupted = False
        first, steps0 = 0, self.steps
        if resumed is not None:  # outputs continue where the checkpoint was taken
            meta = resumed[1]
            t0, first, escaped = meta["t0"], meta["frame"] + 1, meta["escaped"]
            try:
                if writer is not None and meta["usd"] is not None:
                    writer.restore_checkpoint_state(meta["usd"])
                gauge_rows[:] = ckpt.csv_restore(gauge_path, meta["csv"].get("gauges"), ["time_s"] + self.gauge_names)
                block_rows[:] = ckpt.csv_restore(block_path, meta["csv"].get("blocks"), BLOCK_CSV_HEADER)
            except (OSError, ValueError) as e:
                raise ckpt.CheckpointError(f"cannot resume in {out}: {e}") from None
            if getattr(render, "vtk", None) is not None and meta.get("vtk") is not None:
                render.vtk.entries = [tuple(e) for e in meta["vtk"]]
        else:
            from rockwave import preflight

            preflight.check_disk(self, out, n_frames)
        interval = scene.output.get("checkpoint_interval_s", 600.0) if checkpoint_interval_s is None else checkpoint_interval_s
        checkpointer = ckpt.RunCheckpointer(self, out, interval, t0, lambda: {
            "usd": writer, "escaped": escaped, "vtk": getattr(render, "vtk", None),
            "csv": {"gauges": (gauge_path, gauge_rows), "blocks": (block_path, block_rows)}})

        def write_frame(frame: int) -> None:
            nonlocal escaped
            samples = {}
            if self.fluid is not None:
                x = self.state.x.numpy()[:nf]
                v = self.state.v.numpy()[:nf]
                escaped = self.check_health(x[:, :dim], v[:, :dim])
                samples[("/World/fluid", "points", "point3f[]")] = x
                samples[("/World/fluid", "velocities", "vector3f[]")] = v
            else:
                self.check_health(np.zeros((0, dim)), np.zeros((0, dim)))
            if self.blocks is not None:
                bx = self.block_state.positions_numpy()
                bq = self.block_state.orientations_numpy()
                bv = self.block_state.velocities_numpy()
                bw = self.block_state.angular_velocities_numpy()
                nc = self.block_state.contact_counts()
                verts = self.block_state.world_vertices() if any(deformable) else None
                for i, prim in enumerate(block_prims):
                    if deformable[i]:
                        samples[(prim, "points", "point3f[]")] = verts[i]
                    else:
                        samples[(prim, "xformOp:translate", "double3")] = bx[i]
                        samples[(prim, "xformOp:orient", "quatf")] = Gf.Quatf(float(bq[i, 3]), float(bq[i, 0]), float(bq[i, 1]), float(bq[i, 2]))
                    block_rows.append([self.time, i, self.blocks.names[i], *map(float, bx[i]), *map(float, bv[i]), *map(float, bw[i]), int(nc[i])])
                if block_path is not None:
                    _write_csv_atomic(block_path, BLOCK_CSV_HEADER, block_rows)
            render.frame(frame, samples)
            if writer is not None:
                writer.write_frame(frame, samples)
            if gauge_path is not None:
                g = self.gauges()
                gauge_rows.append([self.time] + [g[n] for n in self.gauge_names])
                _write_csv_atomic(gauge_path, ["time_s"] + self.gauge_names, gauge_rows)

        import signal
        import threading

        stop = []

        def on_sigint(signum, frm):
            if stop:  # a second Ctrl-C stops at once
                raise KeyboardInterrupt
            stop.append(True)
            print("\ninterrupted: finishing the current frame, then writing a checkpoint (Ctrl-C again to stop at once)",
                  file=sys.stderr)

        old_handler = signal.signal(signal.SIGINT, on_sigint) if threading.current_thread() is threading.main_thread() else None
        failed = False
        try:
            if first == 0:
                write_frame(0)
                checkpointer.frame_done(0)
            for f in range(max(first, 1), n_frames + 1):
                if stop:
                    break
                self.advance(t0 + f * frame_dt - self.time)
                write_frame(f)
                checkpointer.frame_done(f)
                bar.update(self.time - t0, self.steps)
            if stop:
                interrupted = True
                checkpointer.write("interrupt")
            else:
                rest = t0 + duration - self.time
                if rest > 1e-9:
                    self.advance(rest)
                if checkpointer.interval > 0:
                    checkpointer.write("end")
        except KeyboardInterrupt:
            interrupted = True
        except SimulationError as e:  # blow-up: the outputs end at the last good frame, which is checkpointed
            failed = True
            try:
                path = checkpointer.write("blow-up")
                kept = f"; frames up to {checkpointer.frame} are kept in {out}" if checkpointer.frame >= 0 else ""
                more = f"; checkpoint of frame {checkpointer.frame} written to {path} (continue with --resume)" if path else ""
            except OSError as we:
                kept, more = "", f"; no checkpoint written ({we})"
            err = SimulationError(f"{e}{kept}{more}")
            err.__dict__.update(e.__dict__)
            raise err from None
        except OSError as e:  # full disk, folder removed: what was written stays as it was
            failed = True
            raise SimulationError(f"cannot write the outputs in {out}: {e}; the files written before are intact "
                                  f"(last frame computed {checkpointer.frame}"
                                  f"{', last checkpoint frame ' + str(checkpointer.written_frame) if checkpointer.written_frame is not None else ''})") from None
        finally:
            if old_handler is not None:
                signal.signal(signal.SIGINT, old_handler)
            if writer is not None:
                try:
                    writer.close()
                except OSError:
                    if not failed:
                        raise
            bar.close()
        wall = time.perf_counter() - wall0
        summary = {
            "scene": str(Path(scene.path).resolve()) if scene.path != "<scene>" else scene.path,
            "device": self.device,
            "fluid_particles": nf,
            "boundary_particles": self.fluid.n_boundary if self.fluid is not None else 0,
            "blocks": self.blocks.num_blocks if self.blocks is not None else 0,
            "removed_inside_blocks": self.removed_inside_blocks,
            "simulated_s": self.time - t0,
            "steps": self.steps,
            "wall_s": wall,
            "particle_steps_per_s": nf * (self.steps - steps0) / wall if wall > 0 and nf else None,
            "block_steps_per_s": self.blocks.num_blocks * (self.steps - steps0) / wall if wall > 0 and self.blocks is not None else None,
            "particles_outside_domain": escaped,
            "usd": str(out / scene.output.usd) if writer else None,
            "interrupted": interrupted,
            "resumed_from_frame": resumed[1]["frame"] if resumed is not None else None,
            "checkpoint": str(checkpointer.path) if checkpointer.written_frame is not None else None,
        }
        _write_text_atomic(out / "run.json", json.dumps(summary, indent=2))
        if interrupted:
            raise KeyboardInterrupt
        return summary


def block_prim_paths(names: list[str]) -> list[str]:
    """Valid, unique USD prim paths /World/blocks/<name> for block names."""
    out, seen = [], set()
    for n in names:
        p = re.sub(r"[^A-Za-z0-9_]", "_", n) or "block"
        if p[0].isdigit():
            p = "b_" + p
        base, k = p, 1
        while p in seen:
            p = f"{base}_{k}"
            k += 1
        seen.add(p)
        out.append(f"/World/blocks/{p}")
    return out


def blocks_setup(stage, blocks, prims: list[str]) -> None:
    """Static part of the block meshes: body-frame points and polygon faces; rigid, fixed and
    kinematic blocks move by time-sampled translate + orient ops, deformable ones by their points."""
    from pxr import UsdGeom, Vt

    UsdGeom.Scope.Define(stage, "/World/blocks")
    for spec, prim in zip(blocks.specs, prims):
        geo = spec.geometry
        mesh = UsdGeom.Mesh.Define(stage, prim)
        if spec.kind != "deformable":  # a deformable block's points come from the clips (a default here would hide them)
            mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(geo.vertices, dtype=np.float32)))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray([len(f) for f in geo.faces]))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([int(i) for f in geo.faces for i in f]))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        if spec.kind != "deformable":
            mesh.AddTranslateOp()
            mesh.AddOrientOp()


BLOCK_CSV_HEADER = ["time_s", "block", "name", "x_m", "y_m", "z_m", "vx_m_s", "vy_m_s", "vz_m_s",
                    "wx_rad_s", "wy_rad_s", "wz_rad_s", "contacts"]


def _write_text_atomic(path: Path, text: str) -> None:
    """Temporary file, fsync, rename (rockwave/checkpoint.py): a failure leaves the old file as it was."""
    from rockwave.checkpoint import atomic_write

    atomic_write(path, text.encode())


def _write_csv_atomic(path: Path, header: list[str], rows: list[list[float]]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(header)
    for r in rows:
        w.writerow([f"{c:.6g}" if isinstance(c, float) else c for c in r])
    _write_text_atomic(path, buf.getvalue())
