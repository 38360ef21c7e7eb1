"""One scene on several processes (one per GPU): slab decomposition of the water over MPI.

Launch with ``mpiexec -n N python -m rockwave run SCENE --ranks`` (docs/mpi.md); the
MPI world size is detected without ``--ranks`` too. Each rank runs the unchanged fluid solver
(rockwave/sph/fluid.py FluidSolver.step) on its own arrays; this module owns what happens around the step.

Decomposition (the slab scheme of GPUSPH, Rustico et al. 2014, "Advances in multi-GPU Smoothed Particle
Hydrodynamics simulations", IEEE TPDS 25(1)):

* Slabs along the longest axis of the fluid's initial bounding box, with faces at equal-count quantiles of
  the initial particle positions (the load balance of the start). Rank r owns the fluid particles whose
  coordinate lies in [face_r, face_r+1) (the outer faces at -inf / +inf, so particles leaving the domain
  stay owned).
* Halo, one kernel support H wide: the neighbours' owned particles within H of the slab (positions,
  velocities, densities, pressures) are fluid in the rank's arrays, after the owned ones. The forces on an
  owned particle i read its neighbours' densities *updated in the same step* (summation: rho_j = sum_k m_k
  W_jk; continuity: rho_j += dt sum_k m_k v_jk . grad W_jk), which a halo slot cannot compute (its k reach
  2 H past the face). So the step's halo densities come from their owners: RankFluidSolver (FluidSolver with
  its ``wall_pressure`` hook, which runs after the density passes and before the forces) sends each owned
  particle's new rho, p and p/rho^2 to the ranks that hold it as halo, and takes theirs for its halo slots
  (a second exchange inside the step; the step itself is FluidSolver.step, unchanged). One more support with
  Adami walls (a wall particle within H of i extrapolates its pressure from the fluid within H of itself) and
  one more with the delta-SPH density diffusion (it reads the neighbours' densities before the exchange).
  Halo results (accelerations, new positions) are thrown away after the step: they are never integrated
  into the rank's owned set.
* Boundary (wall) particles are static: each rank keeps those within its slab widened by the halo + H.
* Migration: after the step, owned particles whose coordinate left the slab go to the neighbour rank
  (a particle moves far less than one slab per step: CFL).
* Load balance: every ``balance_interval`` steps, when the busiest rank owns more than (1 + ``balance_tolerance``)
  x the mean count, the faces move to equal-count quantiles of a histogram of the owned coordinates summed over
  the ranks, and the particles go to their new owners (all-to-all); refused while a slab would be narrower
  than the halo.
* dt: every rank reduces max |v|^2 and max |a|^2 of its owned particles (MPI allreduce, max), so the fluid
  limit is the one-rank limit (Monaghan 1992, FluidSolver.stable_dt); the block and coupling limits are
  replicated.
* Blocks are replicated: each rank computes the water's force on every block from its owned particles
  only (the coupling kernel launched over them), the per-rank loads are summed (reduce on rank 0 + bcast,
  so all ranks hold bit-identical loads) and every rank integrates the blocks identically. The walls' impulse
  on the water (CouplingOptions.track_walls, Coupling.wall_impulse) is summed over the ranks the same way.
* Rank 0 drives: ``advance`` and ``step`` on rank 0 broadcast a command that the other ranks follow
  (``serve``); after each advance the owned particles are gathered into rank 0's full FluidState, so
  readers, gauges, recorders, run.json and checkpoints on rank 0 are those of a one-rank run. A checkpoint
  is the full state: it resumes on any number of ranks (the state is repartitioned when rank 0's clock
  differs from the last one it distributed).

The CPU path packs halo and migration buffers with numpy on the host (one float64 row per particle:
id, x, v, rho, a, p) and exchanges them with mpi4py (host MPI); the rank's solver arrays are rebuilt from
them each step (the solver object itself when the local count changes). Not done yet: Warp packing kernels and
NCCL (nccl4py) on GPUs with device-resident buffers, Ghost SPH, per-rank memory below the full state (every
rank builds the whole scene once).

Results differ from one rank within float round-off, not bit for bit: a rank's neighbour lists hold the
same pairs in another order (its cell sort sees other slots), so the float32 sums over neighbours are
added in another order; the block loads are summed per rank, then over ranks.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import replace

import numpy as np
import warp as wp

from rockwave.base.device import resolve_device
from rockwave.build.options import coupling_options
from rockwave.kernels.sph import fluid as sph
from rockwave.scene.format import Scene, load_scene
from rockwave.sim import checkpoint as ckpt
from rockwave.sim.simulation import Simulation, SimulationOptions
from rockwave.sph.fluid import FluidOptions, FluidSolver, FluidState, fluid_dt_limit

# columns of a particle row (float64; ids are exact below 2^53, float32 values exactly)
GID, X, V, RHO, A, P = 0, slice(1, 4), slice(4, 7), 7, slice(8, 11), 11
ROW = 12
GATHER_WALL_S = 1.0  # rank 0 refreshes its full state inside an advance at most this often (the run loop's watch)

_MPI_ENV = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "PMIX_SIZE", "MPI_LOCALNRANKS", "SLURM_NTASKS_PER_STEP")


def world_size_from_env() -> int:
    """The MPI world size the launcher announces in the environment (1 when not under mpiexec/srun)."""
    for k in _MPI_ENV:
        v = os.environ.get(k)
        if v and v.isdigit():
            return int(v)
    return 1


def require_mpi():
    """mpi4py's MPI module, or an ImportError naming the extra to install."""
    try:
        from mpi4py import MPI
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(f"several ranks need mpi4py and an MPI (pip install 'rockwave[mpi]'): {e}") from None
    return MPI


def rank_device(device: str, comm) -> str:
    """One GPU per rank: cuda devices are assigned by the rank within its node."""
    if not device.startswith("cuda"):
        return device
    MPI = require_mpi()
    local = comm.Split_type(MPI.COMM_TYPE_SHARED).Get_rank()
    return f"cuda:{local % max(wp.get_cuda_device_count(), 1)}"


def _copy_params(p, n_fluid: int):
    q = sph.SPHParams()
    for name in sph.SPHParams.vars:
        setattr(q, name, getattr(p, name))
    q.n_fluid = n_fluid
    return q


class SlabDecomposition:
    """Slab faces along ``axis`` and the halo width; ``owner(c)`` maps coordinates to ranks."""

    def __init__(self, x_fluid: np.ndarray, size: int, dim: int, support: float, depth: int, axis: int | None = None):
        ext = x_fluid[:, :dim].max(axis=0) - x_fluid[:, :dim].min(axis=0) if len(x_fluid) else np.ones(dim)
        self.axis = int(np.argmax(ext)) if axis is None else int(axis)
        self.size = size
        self.halo = depth * support
        c = np.sort(x_fluid[:, self.axis]) if len(x_fluid) else np.zeros(1)
        inner = [float(np.quantile(c, r / size)) for r in range(1, size)]
        self.faces = np.array([-math.inf, *inner, math.inf])
        widths = np.diff(self.faces)[1:-1]
        if len(widths) and widths.min() < self.halo:
            raise ValueError(f"{size} ranks cut the water into slabs {widths.min():.3g} m wide along axis {self.axis}, "
                             f"narrower than the halo ({self.halo:.3g} m = {depth} kernel supports): use fewer ranks")

    def owner(self, c: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.faces, c, side="right") - 1, 0, self.size - 1)


class DistributedFluid:
    """The owned particles of one rank (host rows, see GID...P) and the rank-local solver around them."""

    def __init__(self, sim: Simulation, comm):
        self.sim, self.comm = sim, comm
        self.rank, self.size = comm.Get_rank(), comm.Get_size()
        m = sim.fluid
        self.global_model = m

        # supports of halo (module doc): 1, +1 with Adami walls (a wall particle within H of a particle extrapolates
        # the fluid within H of itself), +1 with delta-SPH diffusion (it reads the neighbours' densities before
        # the halo's come from their owners; +1 with particle shifting: a particle's shift reads its neighbours'
        # free-surface indicators)
        depth = 1 + int(m.params.boundary == sph.BOUNDARY_ADAMI and m.n_boundary > 0) + int(m.density_diffusion > 0.0) \
            + int(m.particle_shifting > 0.0)
        self.dec = SlabDecomposition(m.initial_positions[: m.n_fluid], self.size, m.dim, m.support_radius, depth)
        mass = m.particle_mass.numpy()
        self.fluid_mass = float(mass[0])
        self._xb_all = np.asarray(m.initial_positions[m.n_fluid: m.n_total], float)
        self._mb_all = mass[m.n_fluid:]
        self._set_slab()
        self.lower = self.rank - 1 if self.rank > 0 else None
        self.upper = self.rank + 1 if self.rank < self.size - 1 else None
        self.options = replace(sim.options.fluid or _fluid_options(sim), neighbour_skin=0.0, reorder_interval=0,
                               recorded_launches=False, min_cells=4096)
        self._solver = None  # (n_local, FluidSolver, FluidModel)
        self.rows = np.zeros((0, ROW))
        self.n_halo = 0
        self.migrated = 0  # particles this rank received from a neighbour's slab
        self.migrated_total = 0  # rank 0, after a gather: summed over ranks
        self.rebalances = 0  # slab face moves (rebalance)

    def _set_slab(self) -> None:
        """This rank's slab [lo, hi) and its walls (within the halo + H of the slab)."""
        ax = self.dec.axis
        self.lo, self.hi = self.dec.faces[self.rank], self.dec.faces[self.rank + 1]
        reach = self.dec.halo + self.global_model.support_radius
        xb = self._xb_all
        sel = (xb[:, ax] >= self.lo - reach) & (xb[:, ax] < self.hi + reach) if len(xb) else np.zeros(0, bool)
        self.boundary_index = np.flatnonzero(sel)
        self.xb, self.mb = xb[self.boundary_index], self._mb_all[self.boundary_index]
        self._solver = None

    def rebalance(self, tolerance: float, bins: int = 4096) -> bool:
        """Move the slab faces when the busiest rank owns more than (1 + tolerance) x the mean count: new faces at
        equal-count quantiles of a histogram of the owned coordinates summed over ranks (``bins`` bins between the
        water's extremes); particles go to their new owners (all-to-all). Refused (False) when a slab would be
        narrower than the halo. Collective."""
        MPI = require_mpi()
        comm, ax = self.comm, 1 + self.dec.axis
        counts = np.array(comm.allgather(len(self.rows)))
        if counts.max() <= (1.0 + tolerance) * counts.mean():
            return False
        c = self.rows[:, ax]
        ext = np.array([c.min() if len(c) else np.inf, -c.max() if len(c) else np.inf])
        comm.Allreduce(MPI.IN_PLACE, ext, op=MPI.MIN)
        lo, hi = ext[0], -ext[1]
        if not hi > lo:
            return False
        hist = np.histogram(c, bins=bins, range=(lo, hi))[0].astype(np.int64)
        comm.Allreduce(MPI.IN_PLACE, hist, op=MPI.SUM)
        cum = np.cumsum(hist)
        edges = np.linspace(lo, hi, bins + 1)
        inner = [float(edges[1 + np.searchsorted(cum, r * cum[-1] / self.size)]) for r in range(1, self.size)]
        faces = np.array([-np.inf, *inner, np.inf])
        widths = np.diff(faces)[1:-1]
        if (len(widths) and widths.min() < self.dec.halo) or np.any(np.diff(faces) <= 0):
            return False
        self.dec.faces = faces
        own = self.dec.owner(c)
        parts = comm.alltoall([self.rows[own == r] for r in range(self.size)])
        self.rows = np.concatenate(parts)
        self._set_slab()
        self.rebalances += 1
        return True

    # ------------------------------------------------------------ partition / gather --------
    def partition(self) -> None:
        """Take this rank's particles from the simulation's full state (identical on every rank)."""
        st, nf = self.sim.state, self.global_model.n_fluid
        rows = np.zeros((nf, ROW))
        ids = st.ids.numpy()
        rows[ids, GID] = ids
        rows[ids, X] = st.x.numpy()[:nf]
        rows[ids, V] = st.v.numpy()[:nf]
        rows[ids, RHO] = st.rho.numpy()
        rows[ids, A] = st.accel.numpy()
        rows[ids, P] = st.pressure.numpy()
        self.rows = rows[self.dec.owner(rows[:, 1 + self.dec.axis]) == self.rank]

    def gather(self) -> None:
        """Rank 0's full FluidState := the union of the owned particles, in id order."""
        parts = self.comm.gather((self.rows, self.migrated), root=0)
        if self.rank != 0:
            return
        rows = np.concatenate([p[0] for p in parts])
        self.migrated_total = int(sum(p[1] for p in parts))
        m, st = self.global_model, self.sim.state
        nf = m.n_fluid
        if len(rows) != nf or not np.array_equal(np.sort(rows[:, GID]).astype(np.int64), np.arange(nf)):
            raise RuntimeError(f"rank 0 gathered {len(rows)} particles for {nf}: a particle was lost or duplicated")
        rows = rows[np.argsort(rows[:, GID])]
        x = st.x.numpy()
        x[:nf] = rows[:, X]
        v = st.v.numpy()
        v[:nf] = rows[:, V]
        st.x.assign(x)
        st.v.assign(v)
        st.rho.assign(rows[:, RHO].astype(np.float32))
        st.accel.assign(rows[:, A].astype(np.float32))
        st.pressure.assign(rows[:, P].astype(np.float32))
        st.ids.assign(np.arange(nf, dtype=np.int32))
        self.sim.fluid_solver._in_original_order = True
        self.sim.fluid_solver.invalidate_lists()

    # ------------------------------------------------------------ exchange ------------------
    def _sendrecv(self, to_lower: np.ndarray, to_upper: np.ndarray) -> np.ndarray:
        """Rows to the lower and upper neighbours; returns the rows received from both (host MPI)."""
        MPI = require_mpi()
        comm, got = self.comm, []
        lower = self.lower if self.lower is not None else MPI.PROC_NULL
        upper = self.upper if self.upper is not None else MPI.PROC_NULL
        for dest, src, buf in ((lower, upper, to_lower), (upper, lower, to_upper)):
            n_in = np.zeros(1, np.int64)
            comm.Sendrecv(np.array([len(buf)], np.int64), dest=dest, recvbuf=n_in, source=src, sendtag=1, recvtag=1)
            recv = np.empty((int(n_in[0]) if src != MPI.PROC_NULL else 0, buf.shape[1]))
            comm.Sendrecv(np.ascontiguousarray(buf), dest=dest, recvbuf=recv, source=src, sendtag=2, recvtag=2)
            got.append(recv)
        return np.concatenate(got)

    def halo(self) -> np.ndarray:
        """The neighbours' owned particles within the halo width of this rank's slab."""
        c = self.rows[:, 1 + self.dec.axis]
        h = self.dec.halo
        none = np.zeros(0, np.int64)
        self._sent = (np.flatnonzero(c < self.lo + h) if self.lower is not None else none,
                      np.flatnonzero(c >= self.hi - h) if self.upper is not None else none)
        return self._sendrecv(self.rows[self._sent[0]], self.rows[self._sent[1]])

    def exchange_densities(self, state, solver) -> None:
        """Inside the step, after the densities and before the forces (RankFluidSolver's halo_densities pass): the halo
        particles take their owners' new rho, p and p/rho^2, computed there with all their neighbours (a halo
        slot's own sum misses the neighbours beyond the halo). The halo rows are in the order halo() received
        them, and the owners send the same rows in the same order."""
        n_own = len(self.rows)
        n = n_own + self.n_halo
        cols = [state.rho, state.pressure, solver._pr2]
        vals = np.stack([a.numpy()[:n].astype(np.float64) for a in cols], axis=1)
        got = self._sendrecv(vals[self._sent[0]], vals[self._sent[1]])
        if len(got) != self.n_halo:
            raise RuntimeError(f"density exchange: {len(got)} values for {self.n_halo} halo particles")
        vals[n_own:] = got
        for k, a in enumerate(cols):
            h = a.numpy()
            h[:n] = vals[:, k]
            a.assign(h)

    def migrate(self) -> None:
        """Owned particles that crossed a slab face go to the neighbour that owns them now."""
        own = self.dec.owner(self.rows[:, 1 + self.dec.axis])
        keep = own == self.rank
        if (np.abs(own - self.rank) > 1).any():
            raise RuntimeError("a particle crossed a whole slab in one step")
        new = self._sendrecv(self.rows[own < self.rank], self.rows[own > self.rank])
        self.rows = np.concatenate([self.rows[keep], new])
        self.migrated += len(new)
        if len(new) and (self.dec.owner(new[:, 1 + self.dec.axis]) != self.rank).any():
            raise RuntimeError("a migrated particle landed on a rank that does not own it")

    # ------------------------------------------------------------ local arrays --------------
    def local_state(self, halo_rows: np.ndarray):
        """The rank's FluidState: owned particles, then halo particles (fluid, not kept), then its walls;
        the solver is rebuilt when the local particle count changes."""

        m, d = self.global_model, self.global_model.device
        rows = np.concatenate([self.rows, halo_rows])
        n, nb = len(rows), len(self.xb)
        self.n_halo = len(halo_rows)
        if self._solver is None or self._solver[0] != n:
            pos = np.concatenate([rows[:, X], self.xb])
            mass = np.concatenate([np.full(n, self.fluid_mass), self.mb]).astype(np.float32)
            local = replace(m, n_fluid=n, n_boundary=nb, params=_copy_params(m.params, n),
                            particle_mass=wp.array(mass, dtype=float, device=d),
                            initial_positions=pos, initial_velocities=np.zeros_like(pos))
            self._solver = (n, RankFluidSolver(local, self.options, exchange=self.exchange_densities), local)
        local = self._solver[2]
        nw = max(nb, 1)
        x = np.concatenate([rows[:, X], self.xb]).astype(np.float32)
        v = np.concatenate([rows[:, V], np.zeros((nb, 3))]).astype(np.float32)
        return FluidState(
            x=wp.array(x, dtype=wp.vec3, device=d), v=wp.array(v, dtype=wp.vec3, device=d),
            rho=wp.array(rows[:, RHO].astype(np.float32), dtype=float, device=d),
            pressure=wp.array(rows[:, P].astype(np.float32), dtype=float, device=d),
            accel=wp.zeros(n, dtype=wp.vec3, device=d), xsph_dv=wp.zeros(n, dtype=wp.vec3, device=d),
            drho_dt=wp.zeros(n, dtype=float, device=d), ids=wp.array(np.arange(n, dtype=np.int32), dtype=int, device=d),
            wall_pressure=wp.zeros(nw, dtype=float, device=d), wall_velocity=wp.zeros(nw, dtype=wp.vec3, device=d)), local

    def read_back(self, state) -> None:
        """The owned particles' new values (the halo's are dropped)."""
        n = len(self.rows)
        self.rows[:, X] = state.x.numpy()[:n]
        self.rows[:, V] = state.v.numpy()[:n]
        self.rows[:, RHO] = state.rho.numpy()[:n]
        self.rows[:, A] = state.accel.numpy()[:n]
        self.rows[:, P] = state.pressure.numpy()[:n]

    def motion_extrema(self) -> tuple[float, float]:
        """Global max |v|^2 and |a|^2 of the water (float32 squares as kernels/sph/fluid.py motion_extrema)."""
        MPI = require_mpi()
        v = self.rows[:, V].astype(np.float32)
        a = self.rows[:, A].astype(np.float32)
        loc = np.array([float((v * v).sum(axis=1).max()) if len(v) else 0.0,
                        float((a * a).sum(axis=1).max()) if len(a) else 0.0])
        out = np.zeros(2)
        self.comm.Allreduce(loc, out, op=MPI.MAX)
        return float(out[0]), float(out[1])


class RankFluidSolver(FluidSolver):
    """The fluid solver of one rank: FluidSolver.step unchanged, with the halo's densities taken from their
    owners between the density and force passes (a ``halo_densities`` pass before the wall pressure)."""

    def __init__(self, model, options, exchange):
        super().__init__(model, options)
        self.insert_pass("halo_densities", lambda state, dt: exchange(state, self), before="wall_pressure")


def _lap(timings: dict, key: str, t0: float) -> float:
    """Add the wall time since t0 to timings[key]; return now."""
    now = time.perf_counter()
    timings[key] = timings.get(key, 0.0) + now - t0
    return now


def _fluid_options(sim):
    return FluidOptions(cfl_number=sim.fluid_solver.cfl_number)


class DistributedSimulation(Simulation):
    """A Simulation stepped by every rank of ``comm`` together (module doc). Rank 0 is the one to use:
    ``run``, ``advance``, ``step`` and the readers work as on one rank; the other ranks call ``serve()``
    (it returns when rank 0 calls ``close()``)."""

    def __init__(self, scene, device: str | None = None, options: SimulationOptions | None = None, comm=None,
                 balance_tolerance: float | None = 0.1, balance_interval: int = 20):
        MPI = require_mpi()
        self.balance_tolerance, self.balance_interval = balance_tolerance, max(int(balance_interval), 1)
        self.comm = comm if comm is not None else MPI.COMM_WORLD
        self.rank, self.size = self.comm.Get_rank(), self.comm.Get_size()

        if not isinstance(scene, Scene):
            scene = load_scene(scene)
        dev = rank_device(resolve_device(device if device is not None else scene.simulation.device), self.comm)
        super().__init__(scene, dev, options)
        if self.fluid is None or self.fluid.n_fluid == 0:
            raise ValueError("--ranks decomposes the water: this scene has none (run it on one rank)")
        if type(self.fluid_solver) is not FluidSolver:
            raise ValueError("--ranks: Ghost SPH (fluid.method = 'ghost') is not decomposed yet; run it on one rank")
        if self.fluid.n_moving_walls:
            raise ValueError("--ranks: the wall particles of moving blocks are not decomposed yet; set "
                             "coupling.block_walls = false or run on one rank")
        self.dfluid = DistributedFluid(self, self.comm)
        self.dfluid.partition()
        self._synced_time = self.clock.time
        self._last_gather = time.perf_counter()
        self._gather_every_step = scene.hazard is not None  # the hazard monitor reads the state after every step
        self._collective = False
        self._busy = False  # rank 0 is inside a command the other ranks follow
        # wall seconds of this rank's steps: halo + migration + rebalance ("exchange"), host rows <-> rank arrays
        # and solver (re)allocation ("local_arrays"), the fluid step with the coupling ("fluid_step")
        self.timings: dict[str, float] = {}

    # ------------------------------------------------------------ the clock's questions ----
    def _limits(self) -> dict:
        out = super()._limits()
        if "fluid" in out:
            base = out["fluid"]

            def fluid(initial: bool) -> float:
                if initial or not self._collective:  # rank 0 alone (a checkpoint restore): its full state
                    return base(initial)

                v2, a2 = self.dfluid.motion_extrema()
                return fluid_dt_limit(self.fluid, self.fluid_solver.cfl_number, math.sqrt(v2), math.sqrt(a2))

            out["fluid"] = fluid
        return out

    def _chunk_size(self) -> int:
        return 0  # step by step (a step exchanges halos)

    # ------------------------------------------------------------ one step ------------------
    def _launch_step(self, ts, reorder: bool = False) -> None:
        df, tm = self.dfluid, self.timings
        t = time.perf_counter()
        if self.balance_tolerance is not None and self.clock.steps % self.balance_interval == 0:
            df.rebalance(self.balance_tolerance)
        halo = df.halo()
        t = _lap(tm, "exchange", t)
        state, local = df.local_state(halo)
        solver = df._solver[1]
        t = _lap(tm, "local_arrays", t)
        if self.coupling is not None:
            self._coupled_compute(state, local, ts)
        solver.step(state, ts)
        if self.coupling is not None:
            self.coupling.fluid, keep = replace(local, n_fluid=len(df.rows)), self.coupling.fluid
            try:
                self.coupling.apply(state, ts)
            finally:
                self.coupling.fluid = keep
        wp.synchronize_device(self.device)
        t = _lap(tm, "fluid_step", t)
        df.read_back(state)
        t = _lap(tm, "local_arrays", t)
        df.migrate()
        t = _lap(tm, "exchange", t)
        if self.block_solver is not None:  # replicated: identical loads, identical steps on every rank
            self.block_stepping.advance(self.block_solver, self.block_state, ts)

    def _coupled_compute(self, state, local, ts) -> None:
        """The coupling over the owned particles only (they come first); the block loads summed over ranks."""
        MPI = require_mpi()
        bs = self.block_state
        before = [bs.ext_force.numpy().astype(np.float64), bs.ext_torque.numpy().astype(np.float64)]
        impulse0 = self.coupling.wall_impulse.copy()
        self.coupling.fluid, keep = replace(local, n_fluid=len(self.dfluid.rows)), self.coupling.fluid
        try:
            self.coupling.compute(state, bs, ts)
        finally:
            self.coupling.fluid = keep
        if self.coupling.track_walls:  # the walls' impulse on the water: this rank's particles, summed over ranks
            mine, total_impulse = self.coupling.wall_impulse - impulse0, np.zeros(3)
            self.comm.Allreduce(mine, total_impulse, op=MPI.SUM)
            self.coupling.wall_impulse = impulse0 + total_impulse
        delta = np.concatenate([bs.ext_force.numpy() - before[0], bs.ext_torque.numpy() - before[1]]).astype(np.float64)
        total = np.zeros_like(delta)
        self.comm.Reduce(delta, total, op=MPI.SUM, root=0)  # then bcast: every rank holds the same sum
        self.comm.Bcast(total, root=0)
        nb = len(before[0])
        bs.ext_force.assign((before[0] + total[:nb]).astype(np.float32))
        bs.ext_torque.assign((before[1] + total[nb:]).astype(np.float32))

    # ------------------------------------------------------------ rank 0 drives -------------
    def _command(self, cmd: tuple) -> None:
        """Rank 0: send the command, with the full state when it changed outside the steps (a restore)."""
        sync = None
        if self.clock.time != self._synced_time:
            provs = {k: p for k, p in ckpt.providers(self).items() if k in ("clock", "fluid", "blocks")}
            sync = {k: p.pack(p.capture()) for k, p in provs.items()}
        self.comm.bcast((cmd, sync, self.clock.capture()), root=0)
        self._apply_sync(sync)

    def _apply_sync(self, sync) -> None:
        if sync is not None:
            if self.rank != 0:
                provs = ckpt.providers(self)
                for k, (arrays, meta) in sync.items():
                    provs[k].restore(arrays, meta)
            self.dfluid.partition()
            self._synced_time = self.clock.time

    def serve(self) -> None:
        """Ranks > 0: follow rank 0's commands until it calls close()."""
        while True:
            cmd, sync, clock = self.comm.bcast(None, root=0)
            self.clock.restore(clock)
            self._apply_sync(sync)
            if cmd[0] == "stop":
                return
            if cmd[0] == "advance":
                self._advance(cmd[1], None, cmd[2])
            elif cmd[0] == "step":
                self._step(cmd[1])
            elif cmd[0] == "gather":
                self.dfluid.gather()

    def close(self) -> None:
        """Rank 0: release the other ranks from serve()."""
        if self.rank == 0 and self.size > 1:
            self._command(("stop",))

    def finish(self) -> None:
        """Rank 0 at the end of a run: close(), or MPI Abort when an error left the other ranks inside a step
        (they wait in a collective that rank 0 will not join)."""
        if self._busy:
            require_mpi().COMM_WORLD.Abort(1)
        self.close()

    def advance(self, duration: float, watch=None, gather: bool = True) -> None:
        """As Simulation.advance, on every rank; ``gather``: refresh rank 0's full state at the end (False:
        a timing that leaves it out; call gather() before reading)."""
        if self.rank == 0:
            self._command(("advance", duration, gather))
        self._busy = True
        self._advance(duration, watch if self.rank == 0 else None, gather)
        self._busy = False

    def step(self, dt: float | None = None) -> None:
        if self._collective:  # inside advance: every rank is stepping
            return super().step(dt)
        if self.rank == 0:
            self._command(("step", dt))
        self._busy = True
        self._step(dt)
        self._busy = False

    def gather(self) -> None:
        """Rank 0: refresh the full state from the ranks (advance and step do it when they end)."""
        if self.rank == 0:
            self._command(("gather",))
        self.dfluid.gather()

    def _step(self, dt) -> None:
        self._collective = True
        try:
            super().step(dt)
        finally:
            self._collective = False
        self.dfluid.gather()
        self._synced_time = self.clock.time

    def _advance(self, duration: float, watch, gather: bool = True) -> None:
        def after_step():
            now = self.comm.bcast(time.perf_counter() - self._last_gather >= GATHER_WALL_S if self.rank == 0 else None,
                                  root=0)
            if now or self._gather_every_step:
                self.dfluid.gather()
                self._last_gather = time.perf_counter()
            if watch is not None:
                watch()

        self._collective = True
        try:
            super().advance(duration, after_step)
        finally:
            self._collective = False
        if gather:
            self.dfluid.gather()
            self._last_gather = time.perf_counter()
        else:
            self.comm.Barrier()  # every rank finished its steps
        self._synced_time = self.clock.time


def _main(argv=None) -> int:
    """``mpiexec -n N python -m rockwave.sim.distributed SCENE --duration T --out STATE.npz``: advance T seconds
    on N ranks (``--plain``: the one-process Simulation, no MPI) and save the gathered particles and blocks
    (tests, comparisons of rank counts)."""
    ap = argparse.ArgumentParser(prog="python -m rockwave.sim.distributed")
    ap.add_argument("scene")
    ap.add_argument("--duration", type=float, required=True, help="simulated seconds")
    ap.add_argument("--frames", type=int, default=1, help="advance in this many equal parts (default 1)")
    ap.add_argument("--out", required=True, help=".npz of positions, velocities, densities, block poses")
    ap.add_argument("--plain", action="store_true", help="the one-process Simulation, no MPI")
    ap.add_argument("--balance", type=float, default=0.1, help="move the slab faces when a rank owns more than "
                    "(1 + BALANCE) x the mean (default 0.1)")
    ap.add_argument("--track-walls", action="store_true", help="sum the fixed and kinematic blocks' force on the "
                    "water (CouplingOptions.track_walls) and save it as wall_impulse")
    a = ap.parse_args(argv)
    wp.config.quiet = True
    options = None
    if a.track_walls:

        options = SimulationOptions(coupling=replace(coupling_options(load_scene(a.scene)), track_walls=True))
    sim = (Simulation(a.scene, device="cpu", options=options) if a.plain else
           DistributedSimulation(a.scene, device="cpu", options=options, balance_tolerance=a.balance))
    if not a.plain and sim.rank != 0:
        sim.serve()
        return 0
    for _ in range(a.frames):
        sim.advance(a.duration / a.frames)
    save = dict(x=sim.positions(), v=sim.velocities(), rho=sim.densities(), time=sim.time, steps=sim.steps,
                dt=sim.dt, blocks=sim.block_positions(), block_v=sim.block_velocities(),
                ranks=getattr(sim, "size", 1), migrated=sim.dfluid.migrated_total if not a.plain else 0,
                axis=sim.dfluid.dec.axis if not a.plain else -1, rebalances=sim.dfluid.rebalances if not a.plain else 0, faces=sim.dfluid.dec.faces if not a.plain else [],
                wall_impulse=sim.coupling.wall_impulse if sim.coupling is not None else np.zeros(3))
    if not a.plain:
        sim.close()
    np.savez(a.out, **save)
    return 0


if __name__ == "__main__":
    sys.exit(_main())
