"""One scene on several processes (one per GPU): slab decomposition of the water over MPI.

Launch with ``mpiexec -n N python -m rockwave run SCENE --ranks`` (docs/mpi.md); the MPI world size is detected
without ``--ranks`` too. Each rank runs the unchanged fluid step (rockwave/sph/fluid.py FluidSolver's passes) on its own
device arrays; this module owns what happens around the step.

Decomposition (the slab scheme of GPUSPH, Rustico et al. 2014, "Advances in multi-GPU Smoothed Particle
Hydrodynamics simulations", IEEE TPDS 25(1)):

* Slabs along the longest axis of the fluid's initial bounding box, with faces at equal-count quantiles of the
  initial positions, rounded to float32 (the kernels compare float32 coordinates with them). Rank r owns the
  particles whose coordinate lay in [face_r, face_r+1) at the last list rebuild (outer faces at -inf / +inf).
* Rank arrays, on the device: owned particles (in cell order), the halo from the lower rank, the halo from the
  upper rank, then the rank's walls (those within the halo + H of the slab).
* Halo: the neighbours' owned particles within ``depth`` supports of the slab plus the drift the Verlet skin allows
  between two list rebuilds (halo_width). The forces on an owned particle i read its neighbours' densities *updated
  in the same step*, which a halo slot cannot compute, so inside the step (RankFluidSolver's ``halo_densities``
  pass, after the density passes, before the wall pressure) the owners send each halo particle's new rho, p and
  p/rho^2. depth: 1, +1 with Adami walls (a wall particle within H of i extrapolates the fluid within H of itself),
  +1 with delta-SPH diffusion (it reads the neighbours' densities before that exchange), +1 with particle shifting.
  Halo results (accelerations, new positions) are never used: at the next step the halo slots take their owners'
  x, v and rho again.
* Verlet lists as on one GPU: the halo set is fixed between list rebuilds and refreshed every step (pack_halo /
  unpack_halo into contiguous device buffers, kernels/sim/distributed.py; the transport of rockwave/sim/transport.py:
  NCCL, CUDA-aware MPI or host mpi4py). Each rank runs FluidSolver's skin check over its owned and halo slots; the
  ranks agree by allreduce (MAX) and rebuild together: a *relayout* (migration of the owned particles that left the
  slab, to a neighbour only, since the skin bounds the drift; new halo set; cell order; a solver for the new counts).
  All by device kernels (classify, prefix sum, scatter_flagged, pack_full/unpack_full); the host reads counts only.
* Load balance (at a relayout, every ``balance_interval`` steps or more): the ranks' measured compute seconds per
  step (StepTimer: CUDA events, so a wait inside a stream-ordered exchange is not counted) or their counts; when the
  busiest exceeds (1 + ``balance_tolerance``) x the mean, the faces move to give each rank particles in proportion
  to its speed (DistributedFluid.rebalance).
* dt: every rank reduces max |v|^2 and max |a|^2 of its owned particles (the one-GPU motion_extrema kernel; MPI
  allreduce, max), so the fluid limit is the one-rank limit (Monaghan 1992, FluidSolver.stable_dt); the block and
  coupling limits are replicated.
* Blocks are replicated: each rank computes the water's force on every block from its owned particles only (the
  coupling kernel launched over them), the per-rank loads are summed (reduce on rank 0 + bcast, so all ranks hold
  bit-identical loads) and every rank integrates the blocks identically. The walls' impulse on the water
  (CouplingOptions.track_walls, Coupling.wall_impulse) is summed over the ranks the same way.
* Rank 0 drives: ``advance`` and ``step`` on rank 0 broadcast a command that the other ranks follow (``serve``);
  after each advance the owned particles are gathered (one rank's rows at a time, written by id) into rank 0's
  HostWater (rockwave/sim/readers.py): the whole water in rank 0's host memory, never on a device; readers, gauges,
  the surface, the hazard monitor, run.json and checkpoints on rank 0 are those of a one-rank run, the kernels
  among them run over chunks of it (``output_chunk`` particles at a time). A checkpoint is the whole state: it
  resumes on any number of ranks (rank 0 scatters it again when its clock differs from the last one it
  distributed).
* Start: each rank seeds only its slab (rockwave/build/slab.py: the faces from the whole scene's per-column
  counts, the particles with the whole seeding's positions, densities and ids); rank 0's HostWater is filled by
  the first gather. ``slab_build=False`` (and the scenes the slab build does not cover) build the whole scene on
  every rank, rank 0 scatters it, all drop it from their devices.

Results differ from one rank within float32 round-off, not bit for bit: a rank's neighbour lists hold the same
pairs in another order, so the float32 sums over neighbours are added in another order; the block loads are summed
per rank, then over ranks.
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
from rockwave.build import builder, slab
from rockwave.build.options import coupling_options
from rockwave.kernels.sim import distributed as kd
from rockwave.kernels.sph import fluid as sph
from rockwave.scene.format import Scene, load_scene
from rockwave.sim import checkpoint as ckpt
from rockwave.sim.readers import HostWater
from rockwave.sim.simulation import Simulation, SimulationOptions
from rockwave.sim.transport import KINDS, make_transport
from rockwave.sph.fluid import Density, FluidOptions, FluidSolver, FluidState, fluid_dt_limit

GATHER_WALL_S = 1.0  # rank 0 refreshes its full state inside an advance at most this often (the run loop's watch)
BALANCE_BY = ("time", "count")

_MPI_ENV = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "PMIX_SIZE", "MPI_LOCALNRANKS", "SLURM_NTASKS_PER_STEP")
_FAR = 3.0e38  # +-inf of an outer slab face inside a kernel (float32)


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
    """One GPU per rank: cuda devices are assigned by the rank within its node (MPI_COMM_TYPE_SHARED)."""
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


def halo_width(model, options: FluidOptions) -> tuple[float, int]:
    """Halo width [m] and its depth in supports (module doc): ``depth`` supports of dependencies plus the farthest
    two particles can have moved towards each other since the last list build while the lists are kept: twice the
    skin check's bound on one particle's displacement (H/2 with the relative check, s H / 2 with the absolute one;
    none without a skin: lists rebuilt every step)."""
    H = model.support_radius
    depth = 1 + int(model.params.boundary == sph.BOUNDARY_ADAMI and model.n_boundary > 0) \
        + int(model.density_diffusion > 0.0) + int(model.particle_shifting > 0.0)
    s = float(options.neighbour_skin)
    drift = 0.0 if s <= 0 else (H if options.skin_check == "relative" else s * H)
    return depth * H + drift, depth


class SlabDecomposition:
    """Slab faces along ``axis`` and the halo width; ``owner(c)`` maps coordinates to ranks."""

    def __init__(self, x_fluid: np.ndarray | None, size: int, dim: int, halo: float, axis: int | None = None,
                 inner=None):
        """``inner``: the inner faces given (a slab build: from the whole scene's plane counts, with ``axis``);
        else the quantiles of ``x_fluid``."""
        if inner is None:
            ext = x_fluid[:, :dim].max(axis=0) - x_fluid[:, :dim].min(axis=0) if len(x_fluid) else np.ones(dim)
            axis = int(np.argmax(ext)) if axis is None else int(axis)
            c = np.sort(x_fluid[:, axis]) if len(x_fluid) else np.zeros(1)
            inner = [float(np.quantile(c, r / size)) for r in range(1, size)]
        self.axis = int(axis)
        self.size = size
        self.halo = float(halo)
        self.faces = float32_faces(inner)
        widths = np.diff(self.faces)[1:-1]
        if len(widths) and widths.min() < self.halo:
            raise ValueError(f"{size} ranks cut the water into slabs {widths.min():.3g} m wide along axis {self.axis}, "
                             f"narrower than the halo ({self.halo:.3g} m): use fewer ranks")

    def owner(self, c: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.faces, c, side="right") - 1, 0, self.size - 1)


def float32_faces(inner) -> np.ndarray:
    """Slab faces [-inf, *inner, inf] with the inner faces rounded to float32: the kernels compare float32
    coordinates with them (kernels/sim/distributed.py classify), and the host's owner() must agree exactly."""
    return np.array([-math.inf, *np.asarray(inner, np.float32).astype(np.float64), math.inf])


def balanced_faces(hist: np.ndarray, lo: float, hi: float, share: np.ndarray, faces: np.ndarray,
                   halo: float) -> np.ndarray | None:
    """New slab faces giving rank r the fraction share[r] of the particles, read from ``hist`` (particle counts in
    equal bins over [lo, hi] along the axis): face k at the first bin edge where the cumulative count reaches
    sum(share[:k]) of the total, then moved at most half way towards either neighbouring face of ``faces`` (the
    outer ones taken at lo and hi), so that a particle goes to a neighbour rank only. None when a slab would be
    narrower than ``halo`` or the faces would not increase."""
    bins = len(hist)
    cum = np.cumsum(hist)
    edges = np.linspace(lo, hi, bins + 1)
    targets = np.cumsum(share)[:-1] * cum[-1]
    ends = np.array([lo, *faces[1:-1], hi])
    inner = []
    for k, target in enumerate(targets, start=1):
        f = float(edges[1 + min(int(np.searchsorted(cum, target)), bins - 1)])
        inner.append(min(max(f, 0.5 * (ends[k - 1] + ends[k])), 0.5 * (ends[k] + ends[k + 1])))
    out = float32_faces(inner)
    widths = np.diff(out)[1:-1]
    if (len(widths) and widths.min() < halo) or np.any(np.diff(out) <= 0):
        return None
    return out


def _finite(f: float) -> float:
    return max(-_FAR, min(_FAR, f))


class StepTimer:
    """Wall time of the parts of a rank's steps (CUDA: events on the rank's stream, so a wait inside a
    stream-ordered exchange counts as exchange, not as this rank's compute; CPU: the host clock)."""

    def __init__(self, device):
        self.cuda = wp.get_device(device).is_cuda
        self.device = device
        self.marks: list = []

    def mark(self, name: str) -> None:
        if self.cuda:
            e = wp.Event(self.device, enable_timing=True)
            wp.record_event(e)
            self.marks.append((name, e))
        else:
            self.marks.append((name, time.perf_counter()))

    def lap(self, into: dict) -> None:
        """Add each segment (from one mark to the next, named by its start) to ``into`` [s]; clear."""
        for (name, a), (_, b) in zip(self.marks, self.marks[1:]):
            dt = wp.get_event_elapsed_time(a, b) * 1e-3 if self.cuda else b - a
            into[name] = into.get(name, 0.0) + dt
        self.marks = []


class DistributedFluid:
    """The water of one rank, device-resident: owned particles in slots [0, n_own), the neighbours' halo particles
    after them (from the lower rank, then the upper), then the rank's walls; the rank-local solver around them,
    rebuilt at each list rebuild (migration, new halo set, moved faces)."""

    def __init__(self, sim: Simulation, comm, transport: str = "auto"):
        self.sim, self.comm = sim, comm
        self.rank, self.size = comm.Get_rank(), comm.Get_size()
        m = sim.fluid
        self.global_model = m
        self.device = m.device
        self.options = replace(sim.fluid_solver.options, reorder_interval=0, recorded_launches=False, min_cells=4096)
        width, self.depth = halo_width(m, self.options)
        built = getattr(sim, "_slab", None)  # a slab build: the faces from the whole scene's plane counts
        if built is not None:
            self.dec = SlabDecomposition(None, self.size, m.dim, width, axis=built["axis"], inner=built["inner"])
            self.n_global = int(built["layout"].n_fluid)
        else:
            self.dec = SlabDecomposition(m.initial_positions[: m.n_fluid], self.size, m.dim, width)
            self.n_global = m.n_fluid
        self.fluid_mass = float(np.float32(m.params.fluid_mass))
        self._xb_all = np.asarray(m.initial_positions[m.n_fluid: m.n_total], float)
        self._mb_all = m.particle_mass.numpy()[m.n_fluid:]
        self.lower = self.rank - 1 if self.rank > 0 else None
        self.upper = self.rank + 1 if self.rank < self.size - 1 else None
        self.transport = make_transport(transport, comm, self.device)
        self.solver = None  # RankFluidSolver of the current layout
        self.local = None  # its FluidModel
        self.state = None  # its FluidState
        self.gid = None  # wp.array(int): global id of each owned and halo slot
        self.n_own = self.n_halo = 0
        self.n_halo_from = (0, 0)  # halo particles from the lower and the upper rank
        self._send = (None, None)  # owned slots the lower / upper rank holds as halo (device int arrays)
        self.migrated = 0  # particles this rank received from a neighbour's slab
        self.migrated_total = 0  # rank 0, after a gather: summed over ranks
        self.rebalances = 0  # slab face moves (rebalance)
        self.relayouts = 0  # list rebuilds of the decomposition (each: migration + new halo set + new lists)
        self.solver_reuses = 0  # relayouts that kept the rank's solver (its arrays fit the new counts)
        self._capacity = 0
        self.steps = 0  # steps this rank took
        self.timings: dict[str, float] = {}  # seconds: halo (refresh + densities), check, relayout, compute
        self._since_balance = {"compute": 0.0, "steps": 0}
        self._set_slab()

    # ------------------------------------------------------------ slab and walls ------------
    def _set_slab(self) -> None:
        """This rank's slab [lo, hi) and its walls (within the halo + H of the slab)."""
        ax = self.dec.axis
        self.lo, self.hi = self.dec.faces[self.rank], self.dec.faces[self.rank + 1]
        reach = self.dec.halo + self.global_model.support_radius
        xb = self._xb_all
        sel = (xb[:, ax] >= self.lo - reach) & (xb[:, ax] < self.hi + reach) if len(xb) else np.zeros(0, bool)
        self.boundary_index = np.flatnonzero(sel)
        self.xb, self.mb = xb[self.boundary_index], self._mb_all[self.boundary_index]
        # the walls whose wall pressure this rank reports to rank 0's outputs: those in its slab (each wall on one
        # rank; its fluid within H is in the rank's owned particles and halo)
        self._wall_mine = self.dec.owner(self.xb[:, ax]) == self.rank if len(self.xb) else np.zeros(0, bool)
        d = self.device
        self._xb_dev = wp.array(self.xb.astype(np.float32).reshape(-1, 3), dtype=wp.vec3, device=d)
        self._mb_dev = wp.array(np.asarray(self.mb, np.float32), dtype=float, device=d)
        self.solver = None  # other walls, another domain: a new solver at the next relayout

    # ------------------------------------------------------------ device helpers ------------
    def _launch(self, kernel, n: int, inputs) -> None:
        if n > 0:
            wp.launch(kernel, dim=n, inputs=inputs, device=self.device)

    def _compact(self, flag: wp.array, n: int) -> wp.array:
        """The indices i < n with flag[i] != 0, in order (exclusive scan + scatter, on the device; one host read
        of the count)."""
        d = self.device
        if n == 0:
            return wp.zeros(0, dtype=int, device=d)
        pos = wp.empty(n, dtype=int, device=d)
        wp.utils.array_scan(flag, pos, inclusive=False)
        count = int(pos[n - 1: n].numpy()[0] + flag[n - 1: n].numpy()[0])
        out = wp.empty(count, dtype=int, device=d)
        self._launch(kd.scatter_flagged, n, [flag, pos, out])
        return out

    def _exchange_counts(self, to_lower: int, to_upper: int) -> tuple[int, int]:
        """Message lengths: what this rank sends its neighbours, and gets back from them (host MPI)."""
        got = [0, 0]
        for k, (peer, n) in enumerate(((self.lower, to_lower), (self.upper, to_upper))):
            if peer is None:
                continue
            buf = np.zeros(1, np.int64)
            self.comm.Sendrecv(np.array([n], np.int64), dest=peer, recvbuf=buf, source=peer, sendtag=31, recvtag=31)
            got[k] = int(buf[0])
        return got[0], got[1]

    def _pack_full(self, idx: wp.array) -> wp.array:
        st = self.state
        buf = wp.empty((len(idx), kd.FULL_COLS), dtype=float, device=self.device)
        self._launch(kd.pack_full, len(idx), [idx, self.gid, st.x, st.v, st.rho, st.accel, st.pressure, buf])
        return buf

    def _exchange_full(self, down: wp.array, up: wp.array) -> tuple[wp.array, wp.array]:
        """Full rows of the slots ``down`` to the lower rank and ``up`` to the upper; returns the rows received
        from the lower and from the upper rank (device arrays)."""
        d = self.device
        n_lo, n_hi = self._exchange_counts(len(down), len(up))
        send_lo, send_hi = self._pack_full(down), self._pack_full(up)
        recv_lo = wp.empty((n_lo, kd.FULL_COLS), dtype=float, device=d)
        recv_hi = wp.empty((n_hi, kd.FULL_COLS), dtype=float, device=d)
        self.transport.exchange([(self.lower, send_lo, recv_lo), (self.upper, send_hi, recv_hi)])
        return recv_lo, recv_hi

    # ------------------------------------------------------------ layout ---------------------
    def set_owned(self, rows: np.ndarray) -> None:
        """Start (or restart) from host rows (kd.FULL_COLS layout) of this rank's particles: a partition of the full
        state. Then the halo and the solver (relayout)."""
        d = self.device
        buf = wp.array(np.asarray(rows, np.float32).reshape(-1, kd.FULL_COLS), dtype=float, device=d)
        n = buf.shape[0]
        self.state, self.gid = self._alloc(n, 0), wp.empty(n, dtype=int, device=d)
        st = self.state
        self._launch(kd.unpack_full, n, [buf, 0, self.gid, st.x, st.v, st.rho, st.accel, st.pressure])
        self.n_own, self.n_halo = n, 0
        self._halo_and_solver()

    def _alloc(self, n: int, nb_walls: int):
        d = self.device
        nt = n + nb_walls
        return FluidState(
            x=wp.zeros(nt, dtype=wp.vec3, device=d), v=wp.zeros(nt, dtype=wp.vec3, device=d),
            rho=wp.zeros(n, dtype=float, device=d), pressure=wp.zeros(n, dtype=float, device=d),
            accel=wp.zeros(n, dtype=wp.vec3, device=d), xsph_dv=wp.zeros(n, dtype=wp.vec3, device=d),
            drho_dt=wp.zeros(n, dtype=float, device=d), ids=wp.zeros(n, dtype=int, device=d),
            wall_pressure=wp.zeros(max(nb_walls, 1), dtype=float, device=d),
            wall_velocity=wp.zeros(max(nb_walls, 1), dtype=wp.vec3, device=d))

    def _classify(self, n: int):
        """Flags of slots 0..n-1 against the slab (kd.classify): keep, down, up, halo_down, halo_up."""
        d = self.device
        flags = [wp.zeros(n, dtype=int, device=d) for _ in range(5)]
        self._launch(kd.classify, n, [self.state.x, self.dec.axis, _finite(self.lo), _finite(self.hi), self.dec.halo,
                                      *flags])
        return flags

    def start_walls(self) -> None:
        """The walls' pressure of a fresh layout (a start or a restore), as the one-process build computes it for
        its initial state (Adami walls: extrapolated from the owned and halo fluid; the gauges read it before the
        first step); nothing with other walls."""
        sv = self.solver
        if sv.model.params.boundary == sph.BOUNDARY_ADAMI and sv.model.n_boundary and self.n_own:
            with wp.ScopedDevice(self.device):
                sv.build_cells(self.state)
                sv.wall_pressure(self.state)

    def relayout(self) -> None:
        """At a list rebuild (collective): owned particles that left the slab go to the neighbour (migration; the
        skin check bounds a particle's drift since the last rebuild far below a slab, so only to a neighbour), then
        the new halo set and the solver of the new layout. Device kernels; host reads of counts only."""
        keep, down, up, _, _ = self._classify(self.n_own)
        k_idx, d_idx, u_idx = (self._compact(f, self.n_own) for f in (keep, down, up))
        recv_lo, recv_hi = self._exchange_full(d_idx, u_idx)
        n_keep, n_lo, n_hi = len(k_idx), recv_lo.shape[0], recv_hi.shape[0]
        n = n_keep + n_lo + n_hi
        old, old_gid = self.state, self.gid
        st = self._alloc(n, 0)
        gid = wp.empty(n, dtype=int, device=self.device)
        self._launch(kd.gather_owned, n_keep, [k_idx, old_gid, old.x, old.v, old.rho, old.accel, old.pressure,
                                               gid, st.x, st.v, st.rho, st.accel, st.pressure])
        for off, buf in ((n_keep, recv_lo), (n_keep + n_lo, recv_hi)):
            self._launch(kd.unpack_full, buf.shape[0], [buf, off, gid, st.x, st.v, st.rho, st.accel, st.pressure])
        self.state, self.gid, self.n_own, self.n_halo = st, gid, n, 0
        self.migrated += n_lo + n_hi
        _, down, up, _, _ = self._classify(n)
        if self._compact(down, n).shape[0] + self._compact(up, n).shape[0]:
            raise RuntimeError("a particle crossed a whole slab between two list rebuilds")
        self._halo_and_solver()

    def _halo_and_solver(self) -> None:
        """The halo of the current owned set (the neighbours' owned particles within the halo width of the slab)
        and the rank's arrays and solver for owned + halo + walls; the lists are built at the next step."""
        n_own = self.n_own
        self._sort_owned()
        _, _, _, h_down, h_up = self._classify(n_own)
        self._send = (self._compact(h_down, n_own), self._compact(h_up, n_own))
        recv_lo, recv_hi = self._exchange_full(*self._send)
        n_lo, n_hi = recv_lo.shape[0], recv_hi.shape[0]
        n, nb = n_own + n_lo + n_hi, len(self.xb)
        own, own_gid = self.state, self.gid
        st = self._alloc(n, nb)
        gid = wp.empty(n, dtype=int, device=self.device)
        idx = self._own_idx = wp.array(np.arange(n_own, dtype=np.int32), dtype=int, device=self.device)
        self._launch(kd.gather_owned, n_own, [idx, own_gid, own.x, own.v, own.rho, own.accel, own.pressure,
                                              gid, st.x, st.v, st.rho, st.accel, st.pressure])
        for off, buf in ((n_own, recv_lo), (n_own + n_lo, recv_hi)):
            self._launch(kd.unpack_full, buf.shape[0], [buf, off, gid, st.x, st.v, st.rho, st.accel, st.pressure])
        if nb:
            wp.copy(st.x, self._xb_dev, n, 0, nb)
        self.state, self.gid, self.n_halo, self.n_halo_from = st, gid, n_lo + n_hi, (n_lo, n_hi)
        self._make_solver(n, nb)
        d = self.device
        # the per-step buffers: halo rows (x, v, rho) and halo densities (rho, p, p/rho^2) both ways
        self._halo_bufs = [(wp.empty((len(s), kd.HALO_COLS), dtype=float, device=d),
                            wp.empty((r, kd.HALO_COLS), dtype=float, device=d))
                           for s, r in zip(self._send, self.n_halo_from)]
        self._dens_bufs = [(wp.empty((len(s), kd.DENS_COLS), dtype=float, device=d),
                            wp.empty((r, kd.DENS_COLS), dtype=float, device=d))
                           for s, r in zip(self._send, self.n_halo_from)]
        self.relayouts += 1

    def _sort_owned(self) -> None:
        """The owned particles in cell order (_cell_order)."""
        n, old, old_gid = self.n_own, self.state, self.gid
        if n == 0:
            return
        idx = self._cell_order()
        st, gid = self._alloc(n, 0), wp.empty(n, dtype=int, device=self.device)
        self._launch(kd.gather_owned, n, [idx, old_gid, old.x, old.v, old.rho, old.accel, old.pressure,
                                          gid, st.x, st.v, st.rho, st.accel, st.pressure])
        self.state, self.gid = st, gid

    def _cell_order(self) -> wp.array:
        """The owned slots sorted by cell of edge H (radix sort of the cell keys on the device)."""
        n, d, m = self.n_own, self.device, self.global_model
        order = wp.empty(2 * max(n, 1), dtype=int, device=d)  # the radix sort's scratch: twice the length
        if n == 0:
            return order[:0]
        H = m.support_radius
        lo = np.array(m.domain_lo, float) - H
        dims = np.maximum(np.ceil((np.array(m.domain_hi, float) + H - lo) / H).astype(np.int64), 1)
        while int(np.prod(dims)) >= 2**31:  # coarser cells rather than an overflowing key
            dims = np.maximum(dims // 2, 1)
        cell = float(np.max((np.array(m.domain_hi, float) + H - lo) / dims))
        keys = wp.empty(2 * n, dtype=int, device=d)
        self._launch(kd.cell_keys, n, [self.state.x, wp.vec3(*lo), 1.0 / cell, int(dims[0]), int(dims[1]), int(dims[2]),
                                       keys, order])
        wp.utils.radix_sort_pairs(keys, order, n)
        return order[:n]

    SOLVER_HEADROOM = 1.05  # a rank's solver holds arrays for this many times its particles (+ 256): a relayout reuses it

    def _make_solver(self, n: int, nb: int) -> None:
        """The rank's FluidModel (the global one's parameters, n fluid slots, the rank's walls, a domain around the
        slab) and its RankFluidSolver. The solver is made for a capacity (SOLVER_HEADROOM) and kept over relayouts
        while the slab is unchanged and the particles fit (RankFluidSolver.retarget: no allocation of lists and
        grids, no host work over the walls); else made anew."""
        m, d = self.global_model, self.device
        mass = wp.empty(n + nb, dtype=float, device=d)
        mass.fill_(self.fluid_mass)
        if nb:
            wp.copy(mass, self._mb_dev, n, 0, nb)
        if self.solver is not None and n <= self._capacity:
            self.solver.retarget(n, mass)
            self.local = self.solver.model
            self.solver_reuses += 1
            return
        cap = int(self.SOLVER_HEADROOM * n) + 256
        lo, hi = np.array(m.domain_lo, float), np.array(m.domain_hi, float)
        ax, reach = self.dec.axis, self.dec.halo + 2.0 * m.support_radius
        lo[ax] = max(lo[ax], self.lo - reach) if math.isfinite(self.lo) else lo[ax]
        hi[ax] = min(hi[ax], self.hi + reach) if math.isfinite(self.hi) else hi[ax]
        hi[ax] = max(hi[ax], lo[ax] + m.support_radius)
        # the solver reads the walls' positions from initial_positions (its skin check marks their cells); the
        # fluid rows there are never read (zeros: no copy of the particles to the host)
        init = np.zeros((cap + nb, 3))
        init[cap:] = self.xb
        full = wp.empty(cap + nb, dtype=float, device=d)  # the capacity's masses (the model is retargeted below)
        full.fill_(self.fluid_mass)
        model = replace(m, n_fluid=cap, n_boundary=nb, params=_copy_params(m.params, cap), particle_mass=full,
                        initial_positions=init, initial_velocities=np.zeros((1, 3)), domain_lo=lo, domain_hi=hi)
        self.solver = RankFluidSolver(model, self.options, exchange=self.exchange_densities, comm=self.comm)
        self._capacity = cap
        self.solver.retarget(n, mass)
        self.local = self.solver.model

    # ------------------------------------------------------------ per step --------------------
    def refresh_halo(self) -> None:
        """The halo slots take their owners' current x, v and rho (packed by kernels, device buffers)."""
        st = self.state
        for idx, (send, _) in zip(self._send, self._halo_bufs):
            self._launch(kd.pack_halo, len(idx), [idx, st.x, st.v, st.rho, send])
        (s_lo, r_lo), (s_hi, r_hi) = self._halo_bufs
        self.transport.exchange([(self.lower, s_lo, r_lo), (self.upper, s_hi, r_hi)])
        self._launch(kd.unpack_halo, r_lo.shape[0], [r_lo, self.n_own, st.x, st.v, st.rho])
        self._launch(kd.unpack_halo, r_hi.shape[0], [r_hi, self.n_own + r_lo.shape[0], st.x, st.v, st.rho])

    def exchange_densities(self, state, solver) -> None:
        """Inside the step, after the densities and before the forces (RankFluidSolver's halo_densities pass): the halo
        slots take their owners' new rho, p and p/rho^2, computed there with all their neighbours (a halo slot's own
        sum misses the neighbours beyond the halo)."""
        if self.timer is not None:
            self.timer.mark("halo")
        for idx, (send, _) in zip(self._send, self._dens_bufs):
            self._launch(kd.pack_densities, len(idx), [idx, state.rho, state.pressure, solver._pr2, send])
        (s_lo, r_lo), (s_hi, r_hi) = self._dens_bufs
        self.transport.exchange([(self.lower, s_lo, r_lo), (self.upper, s_hi, r_hi)])
        self._launch(kd.unpack_densities, r_lo.shape[0], [r_lo, self.n_own, state.rho, state.pressure, solver._pr2])
        self._launch(kd.unpack_densities, r_hi.shape[0],
                     [r_hi, self.n_own + r_lo.shape[0], state.rho, state.pressure, solver._pr2])
        if self.timer is not None:
            self.timer.mark("compute")

    timer = None  # StepTimer of the step in flight (DistributedSimulation sets it)

    def lists_expired(self) -> bool:
        """The skin check over owned + halo slots (the halo just refreshed), agreed by all ranks (MAX): True when
        some rank's lists would be rebuilt: then every rank relayouts."""
        MPI = require_mpi()
        mine = 1 if self.solver.build_now else int(self.solver.check_lists(self.state))
        return bool(self.comm.allreduce(mine, op=MPI.MAX))

    def motion_extrema(self) -> tuple[float, float]:
        """Global max |v|^2 and |a|^2 of the owned particles (kernels/sph/fluid.py motion_extrema, allreduce MAX)."""
        MPI = require_mpi()
        ext = wp.zeros(2, dtype=float, device=self.device)
        if self.n_own:
            stride = min(self.n_own, 16384)
            wp.launch(sph.motion_extrema, dim=stride, inputs=[self.state.v, self.state.accel, self.n_own, stride],
                      outputs=[ext], device=self.device)
        out = np.zeros(2)
        self.comm.Allreduce(ext.numpy().astype(np.float64), out, op=MPI.MAX)
        return float(out[0]), float(out[1])

    # ------------------------------------------------------------ load balance ---------------
    def rebalance(self, tolerance: float, by: str = "time", bins: int = 4096) -> bool:
        """Move the slab faces (collective; at a relayout) when the busiest rank's load exceeds (1 + tolerance) x
        the mean: by "time", a rank's load is its measured compute seconds since the last balance (kernels,
        not waits) and each rank's speed is its particles per second; by "count", its owned count. The new faces
        give each rank particles in proportion to its speed, read as quantiles of a histogram of the owned
        coordinates summed over ranks; a face moves at most half way to the next face, so particles move to a
        neighbour only; refused (False) while a slab would be narrower than the halo."""
        MPI = require_mpi()
        comm, ax = self.comm, self.dec.axis
        sb = self._since_balance
        load = float(self.n_own) if by == "count" else sb["compute"] / max(sb["steps"], 1)
        loads = np.array(comm.allgather((load, self.n_own)), float)
        t, n = loads[:, 0], loads[:, 1]
        if by == "time" and not (t > 0).all():
            return False
        if t.max() <= (1.0 + tolerance) * t.mean():
            return False
        self._since_balance = {"compute": 0.0, "steps": 0}
        speed = n / t if by == "time" else np.ones(self.size)
        share = speed / speed.sum()
        c = self.state.x.numpy()[: self.n_own, ax] if self.n_own else np.zeros(0)  # one coordinate (host: histogram)
        ext = np.array([c.min() if len(c) else np.inf, -c.max() if len(c) else np.inf])
        comm.Allreduce(MPI.IN_PLACE, ext, op=MPI.MIN)
        lo, hi = ext[0], -ext[1]
        if not hi > lo:
            return False
        hist = np.histogram(c, bins=bins, range=(lo, hi))[0].astype(np.int64)
        comm.Allreduce(MPI.IN_PLACE, hist, op=MPI.SUM)
        old = self.dec.faces.copy()
        faces = balanced_faces(hist, lo, hi, share, old, self.dec.halo)
        if faces is None or np.array_equal(faces, old):
            return False
        self.dec.faces = faces
        self._set_slab()
        self.rebalances += 1
        return True

    def add_compute(self, seconds: float) -> None:
        self._since_balance["compute"] += seconds
        self._since_balance["steps"] += 1

    # ------------------------------------------------------------ partition / gather --------
    def partition(self, full_state) -> None:
        """Take this rank's particles from rank 0's full state (a fresh scene, or a restored checkpoint): rank 0 sorts
        them by owner and scatters them (host MPI, once per start or restore); then the halo and solver."""
        MPI = require_mpi()
        rows = None
        counts = np.zeros(self.size, np.int64)
        if self.rank == 0:
            rows = state_rows(full_state, self.n_global)
            own = self.dec.owner(rows[:, self.dec.axis].astype(np.float64))
            order = np.argsort(own, kind="stable")
            rows = np.ascontiguousarray(rows[order])
            counts = np.bincount(own, minlength=self.size).astype(np.int64)
        self.comm.Bcast(counts, root=0)
        mine = np.empty((int(counts[self.rank]), kd.FULL_COLS), np.float32)
        sizes = counts * kd.FULL_COLS
        displ = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        self.comm.Scatterv([rows, (sizes, displ), MPI.FLOAT] if self.rank == 0 else None, [mine, MPI.FLOAT], root=0)
        self.set_owned(mine)

    def gather(self) -> None:
        """Rank 0's HostWater (rockwave/sim/readers.py) := the union of the owned particles, in id order (an
        output): rank 0 takes one rank's rows at a time (its own from its device; the others' through MPI into a
        host buffer of that rank's rows) and writes each row to the slot of its id on the host; likewise the
        walls' pressure and velocity, each wall from the rank whose slab holds it. Nothing of the whole scene on
        a device."""
        MPI = require_mpi()
        rows = self._pack_full(self._own_idx) if self.n_own else wp.zeros((0, kd.FULL_COLS), dtype=float,
                                                                             device=self.device)
        counts = np.array(self.comm.allgather(self.n_own), np.int64)
        migrated = self.comm.reduce(self.migrated, op=MPI.SUM, root=0)
        walls = self._wall_rows()
        if self.rank != 0:
            if self.n_own:
                self.comm.Send([np.ascontiguousarray(rows.numpy()), MPI.FLOAT], dest=0, tag=41)
            self.comm.send(walls, dest=0, tag=42)
            return
        self.migrated_total = int(migrated)
        host, nf = self.sim.state, self.n_global
        seen = np.zeros(nf, bool)
        for r in range(self.size):
            if counts[r]:
                if r == 0:
                    buf = rows.numpy()
                else:
                    buf = np.empty((int(counts[r]), kd.FULL_COLS), np.float32)
                    self.comm.Recv([buf, MPI.FLOAT], source=r, tag=41)
                ids = buf[:, 11].astype(np.int64) * ID_SPLIT + buf[:, 12].astype(np.int64)
                if ids.min() < 0 or ids.max() >= nf or seen[ids].any():
                    raise RuntimeError(f"rank {r} sent particle ids outside 0..{nf - 1} or held by another rank")
                seen[ids] = True
                host.x[ids], host.v[ids], host.rho[ids] = buf[:, 0:3], buf[:, 3:6], buf[:, 6]
                host.accel[ids], host.pressure[ids] = buf[:, 7:10], buf[:, 10]
            idx, wp_, wv = walls if r == 0 else self.comm.recv(source=r, tag=42)
            host.wall_pressure[idx], host.wall_velocity[idx] = wp_, wv
        if int(counts.sum()) != nf or not seen.all():
            raise RuntimeError(f"rank 0 gathered {int(counts.sum())} particles for {nf}: a particle was lost or "
                               "duplicated")
        if getattr(self.sim, "_fill_initial", False):  # the start's positions (EnergyBudget's reference)
            self.sim.fluid.initial_positions[:nf] = host.x[:nf]
            self.sim._fill_initial = False

    def _wall_rows(self) -> tuple:
        """(global wall indices, wall pressures, wall velocities) of the walls in this rank's slab."""
        mine = self._wall_mine
        if not mine.any():
            return np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros((0, 3), np.float32)
        k = np.flatnonzero(mine)
        st = self.state
        return (self.boundary_index[k], st.wall_pressure.numpy()[k],
                st.wall_velocity.numpy().reshape(-1, 3)[k])

    def bytes_per_particle(self) -> float:
        """Device bytes this rank holds for its water (rank arrays, solver lists and grids, exchange buffers) per
        particle it owns."""
        seen, total = set(), 0

        def add(a):
            nonlocal total
            if isinstance(a, wp.array) and id(a) not in seen:
                seen.add(id(a))
                total += a.capacity if a.capacity else 0

        for obj in (self.state, self.solver, self.solver.cells if self.solver else None):
            for a in (vars(obj).values() if obj is not None else ()):
                add(a)
        for a in (self.gid, self.local.particle_mass, self._xb_dev, self._mb_dev, *self._send):
            add(a)
        for pair in (*self._halo_bufs, *self._dens_bufs):
            for a in pair:
                add(a)
        return total / max(self.n_own, 1)


ID_SPLIT = 1 << 20  # kernels/sim/distributed.py: a global id in two float32 parts


def state_rows(st: FluidState, nf: int) -> np.ndarray:
    """Host rows (kd.FULL_COLS layout) of the nf fluid particles of ``st`` (a FluidState or a HostWater), in id
    order (the ranks' slots in a reproducible order)."""
    def host(a):
        return a if isinstance(a, np.ndarray) else a.numpy()

    ids = host(st.ids)[:nf].astype(np.int64)
    rows = np.zeros((nf, kd.FULL_COLS), np.float32)
    rows[:, 0:3] = host(st.x)[:nf]
    rows[:, 3:6] = host(st.v)[:nf]
    rows[:, 6] = host(st.rho)[:nf]
    rows[:, 7:10] = host(st.accel)[:nf]
    rows[:, 10] = host(st.pressure)[:nf]
    rows[:, 11], rows[:, 12] = ids // ID_SPLIT, ids % ID_SPLIT
    return rows[np.argsort(ids, kind="stable")]


class RankFluidSolver(FluidSolver):
    """The fluid solver of one rank: FluidSolver's passes, with the halo's densities taken from their owners between
    the density and force passes (a ``halo_densities`` pass before the wall pressure), and the list rebuild decided
    by all ranks together (``check_lists`` before the step; ``build_now`` in the step)."""

    def __init__(self, model, options, exchange, comm=None):
        super().__init__(model, options)
        self.insert_pass("halo_densities", lambda state, dt: exchange(state, self), before="wall_pressure")
        self.build_now = True
        self.comm = comm

    def reduce_shift_speed(self, v2max: wp.array) -> None:
        """The shift's Ma from the fastest particle of the whole scene (allreduce MAX; the rank's own, halo
        included, is what FluidSolver found), as the one-process run takes it: without it each rank shifted by
        its own fastest particle's Ma."""
        if self.comm is None:
            return
        MPI = require_mpi()
        out = np.zeros(1)
        self.comm.Allreduce(v2max.numpy()[:1].astype(np.float64), out, op=MPI.MAX)
        v2max.assign(np.array([out[0]], dtype=np.float32))

    def retarget(self, n: int, mass: wp.array) -> None:
        """The solver of n fluid slots (at most the count it was made for) with the particle masses ``mass``
        (fluid, then the same walls): its arrays are kept (the list stride is their length, kernels/sph/fluid.py),
        the launches take the new counts, and the lists are rebuilt at the next step. Arrays made at first use for
        the count of the time (density diffusion, shifting) are made again when too short."""
        self.model = replace(self.model, n_fluid=n, params=_copy_params(self.model.params, n), particle_mass=mass)
        for name in ("_diff_rate", "_shift_dr"):
            a = getattr(self, name, None)
            if a is not None and a.shape[0] < n:
                setattr(self, name, None)
        self.invalidate_lists()
        self.build_now = True

    def check_lists(self, state) -> bool:
        """This rank's skin check (FluidSolver's): would its lists be rebuilt now?"""
        if self.neighbour_skin <= 0:
            return True
        with wp.ScopedDevice(self.model.device):
            guard = self._list_guard(state)
        if self.host_decides:
            return guard is not None
        return bool(self._rebuild.numpy()[0])

    def _neighbour_lists(self, state, dt) -> bool:
        fused = self._neighbour_lists_with(state, dt, self._always if self.build_now else None)
        self.build_now = False
        return fused


def _lap(timings: dict, key: str, t0: float) -> float:
    """Add the wall time since t0 to timings[key]; return now."""
    now = time.perf_counter()
    timings[key] = timings.get(key, 0.0) + now - t0
    return now


class HostWaterProvider:
    """Rank 0's checkpoint group "fluid" (rockwave/sim/checkpoint.py): the HostWater as the one-process FluidProvider
    writes a FluidState (same names and shapes, id order; the solver's list-build positions and a rebuild flag
    set), so a checkpoint resumes on any number of ranks; restored in id order whatever the writer's slot order."""

    def __init__(self, sim):
        self.sim = sim

    def capture(self):
        h = self.sim.state
        n = h.n_fluid
        arrays = {"x": h.x.copy(), "v": h.v.copy(), "rho": h.rho.copy(), "pressure": h.pressure.copy(),
                  "accel": h.accel.copy(), "xsph_dv": np.zeros((n, 3), np.float32), "drho_dt": np.zeros(n, np.float32),
                  "ids": h.ids.copy(), "wall_pressure": h.wall_pressure.copy(), "wall_velocity": h.wall_velocity.copy(),
                  "solver/x_build": h.x[:n].copy(), "solver/rebuild": np.ones(1, np.int32)}
        return arrays

    def pack(self, captured):
        return captured, {}

    def restore(self, arrays, meta):
        h = self.sim.state
        n = h.n_fluid
        ids = np.asarray(arrays["ids"], np.int64)[:n]
        if len(ids) != n or not np.array_equal(np.sort(ids), np.arange(n)):
            raise ckpt.CheckpointError(f"the checkpoint's fluid ids are not a permutation of 0..{n - 1}")
        for name in ("x", "v", "rho", "pressure", "accel"):
            getattr(h, name)[ids] = np.asarray(arrays[name], np.float32)[:n]
        for name in ("wall_pressure", "wall_velocity"):
            a = np.asarray(arrays[name], np.float32)
            getattr(h, name)[: len(a)] = a


class DistributedSimulation(Simulation):
    """A Simulation stepped by every rank of ``comm`` together (module doc). Rank 0 is the one to use:
    ``run``, ``advance``, ``step`` and the readers work as on one rank; the other ranks call ``serve()``
    (it returns when rank 0 calls ``close()``).

    ``transport``: "auto", "nccl", "cuda-mpi" or "host" (rockwave/sim/transport.py). ``balance_by``: "time" (measured
    per-rank compute time) or "count" (owned particles); ``balance_tolerance`` None: the faces never move.
    ``slab_build``: each rank seeds only its slab (rockwave/build/slab.py; default); False: every rank builds the
    whole scene and rank 0 scatters it (the earlier start, kept for comparisons; also what scenes the slab build
    does not cover take). ``output_chunk``: rank 0 evaluates its outputs on the device this many particles at a time
    (default HostWater.CHUNK); its ``state`` is a HostWater (the whole water on its host) and ``fluid_solver`` None."""

    def __init__(self, scene, device: str | None = None, options: SimulationOptions | None = None, comm=None,
                 balance_tolerance: float | None = 0.1, balance_interval: int = 20, transport: str = "auto",
                 balance_by: str = "time", slab_build: bool = True, output_chunk: int | None = None):
        MPI = require_mpi()
        self._output_chunk = output_chunk
        self._slab_wanted = bool(slab_build)
        if balance_by not in BALANCE_BY:
            raise ValueError(f"balance_by {balance_by!r}: expected one of {', '.join(BALANCE_BY)}")
        self.balance_tolerance, self.balance_interval = balance_tolerance, max(int(balance_interval), 1)
        self.balance_by = balance_by
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
        if self.fluid_solver.cell_gather:
            raise ValueError("--ranks: fluid.neighbours = 'cells' is not decomposed yet (a rank's halo exchange and "
                             "relayouts keep neighbour lists); set fluid.neighbours = 'lists' or run on one rank")
        if self.fluid.wall_work:
            raise ValueError("--ranks: fluid.wall_work is not decomposed yet (its pass reads the walls' pressure of the "
                             "last step, which a relayout does not carry); remove the key or run on one rank")
        if self.fluid.n_moving_walls:
            raise ValueError("--ranks: the wall particles of moving blocks are not decomposed yet; set "
                             "coupling.block_walls = false or run on one rank")
        self._cfl = self.fluid_solver.cfl_number
        self.dfluid = DistributedFluid(self, self.comm, transport)
        if self._slab is not None:  # each rank seeded its own slab: it starts from it
            self.dfluid.set_owned(state_rows(self.state, self.fluid.n_fluid))
            if self.fluid.density is Density.SUMMATION:  # the start's sums with the halo (a slab alone misses some)
                self.dfluid.solver.compute_density(self.dfluid.state)
            self.built = {"seeded": int(self.fluid.n_fluid), "held_points": int(self._slab["held"]),
                          "layout_window_points": int(self._slab["window"]), "whole": int(self.dfluid.n_global),
                          "slab_build": True}
        else:
            self.built = {"seeded": int(self.fluid.n_fluid), "held_points": int(self.fluid.n_fluid),
                          "layout_window_points": 0, "whole": int(self.fluid.n_fluid), "slab_build": False}
            self.dfluid.partition(self.state)
        self.dfluid.start_walls()
        if self.rank == 0:  # the whole scene's water for the outputs: on rank 0's host (HostWater), not on a device
            self._output_water()
        else:
            self._release_global_water()
        self.dfluid.gather()  # fills rank 0's HostWater
        self._synced_time = self.clock.time
        self._last_gather = time.perf_counter()
        self._gather_every_step = scene.hazard is not None  # the hazard monitor may read the water after any step
        # rank 0: a callable, True when a hook will read the water after the step just taken (the hazard monitor's
        # sample times: rockwave/app/run.py sets it); None: after every step with a [hazard] section
        self.gather_when = None
        self._collective = False
        self._busy = False  # rank 0 is inside a command the other ranks follow
        self.timings = self.dfluid.timings

    def _build_parts(self, scene: Scene):
        """Each rank seeds only its slab of the water (rockwave/build/slab.py): the faces from the whole scene's
        plane counts, the particles with the whole seeding's positions and ids; the whole scene's build where the
        slab build does not apply (no water, Ghost SPH, moving blocks' walls, mesh regions in 2D, slabs that
        would be vertical)."""
        self._slab = None
        fl = scene.fluid
        if (not self._slab_wanted or fl is None or not fl.regions or fl.method == "ghost" or builder.block_walls_on(scene, self.options)
                or (scene.dim == 2 and any(r.get("box_min_m") is None for r in fl.regions))):
            return super()._build_parts(scene)
        dev, opts = self.device, self.options
        parts = builder.Parts()
        with wp.ScopedDevice(dev):
            if scene.blocks or scene.rock_mass:
                builder.build_blocks(scene, dev, parts, opts)
            layout = slab.fluid_layout(scene, dev, parts, opts)
            axis = int(np.argmax((layout.hi - layout.lo)[: scene.dim]))
            if axis == scene.dim - 1:
                return super()._build_parts(scene)
            coords, counts = layout.plane_counts(axis)
            inner = [slab.quantile_from_counts(coords, counts, r / self.size) for r in range(1, self.size)]
            faces = float32_faces(inner)
            seeds, ids, held = slab.seed_fluid_slab(scene, dev, parts, layout, axis, faces, self.rank, opts)
            builder.build_fluid(scene, dev, parts, opts, seeds, list_capacity=1)  # the rank's solver steps it
            parts.state.ids.assign(ids.astype(np.int32))
            # the whole scene's box (the cell keys and grids of every rank): all water and walls, grown by H
            m, xb = parts.fluid, layout.boundary
            lo = np.minimum(layout.lo, xb.min(axis=0)) if len(xb) else layout.lo
            hi = np.maximum(layout.hi, xb.max(axis=0)) if len(xb) else layout.hi
            m.domain_lo, m.domain_hi = lo - m.support_radius, hi + m.support_radius
            if parts.blocks is not None:
                builder.build_coupling(scene, parts, opts)
        self._slab = {"layout": layout, "axis": axis, "inner": inner, "held": held, "window": layout.peak_points}
        return parts

    def _output_water(self) -> None:
        """Rank 0: the whole scene's water as a HostWater (rockwave/sim/readers.py: host arrays in id order, filled
        by the gathers; the outputs' kernels see it in chunks) and a FluidModel of the whole scene whose arrays are
        on the host; the device's state and solver of the build are dropped (the rank's own are in dfluid).
        Readers, gauges, the surface, the hazard monitor and checkpoints read the HostWater."""
        loc, df = self.fluid, self.dfluid
        n, nb = df.n_global, loc.n_boundary
        xb = np.asarray(loc.initial_positions[loc.n_fluid:], float)
        init = np.zeros((n + nb, 3))  # the fluid rows from the first gather (energy.py reads the lowest)
        init[n:] = xb
        masses = np.empty(n + nb, np.float32)  # on the host (a Warp view of numpy memory: .numpy() and fluid_mass)
        masses[:n] = df.fluid_mass
        masses[n:] = df._mb_all
        full = replace(loc, n_fluid=n, params=_copy_params(loc.params, n),
                       particle_mass=wp.array(masses, dtype=float, device="cpu", copy=False),
                       initial_positions=init, initial_velocities=np.zeros((1, 3)))
        self.host_masses = masses  # (the view above does not own it)
        self.fluid, self.fluid_solver = full, None
        self.state = HostWater(n, xb, df._mb_all, df.fluid_mass, self.device, chunk=self._output_chunk)
        if self.coupling is not None:
            self.coupling.fluid = full
        ckpt.register(self, "fluid", HostWaterProvider(self))
        self._fill_initial = True

    def _release_global_water(self) -> None:
        """Ranks > 0: free the whole scene's fluid state and its solver (lists, grids) once partitioned."""
        self.state = None
        self.fluid_solver = None

    @property
    def transport(self) -> str:
        return self.dfluid.transport.name

    def run_report(self) -> dict:
        """What run.json records of the ranks (rank 0, after a gather): their number, the transport that ran,
        list rebuilds (relayouts) and steps, face moves, migrated particles, and this rank's seconds by part."""
        df = self.dfluid
        return {"ranks": self.size, "transport": self.transport, "axis": df.dec.axis, "halo_m": df.dec.halo,
                "faces": [float(f) for f in df.dec.faces[1:-1]], "relayouts": df.relayouts, "steps": df.steps,
                "rebalances": df.rebalances, "solver_reuses": df.solver_reuses, "balance_by": self.balance_by, "migrated": df.migrated_total,
                "rank0_owned": df.n_own, "rank0_halo": df.n_halo, "rank0_build": self.built,
                "rank0_bytes_per_particle": round(df.bytes_per_particle(), 1),
                "rank0_output_device_bytes": self.state.device_bytes() if isinstance(self.state, HostWater) else 0,
                "rank0_output_chunk": self.state.chunk if isinstance(self.state, HostWater) else None,
                "rank0_whole_scene_device_arrays": whole_scene_device_arrays(self),
                "rank0_seconds": {k: round(v, 4) for k, v in df.timings.items()}}

    # ------------------------------------------------------------ the clock's questions ----
    def _limits(self) -> dict:
        out = super()._limits()
        if "fluid" in out:
            base = out["fluid"]

            def fluid(initial: bool) -> float:
                if initial:
                    return base(initial)
                if self._collective:
                    v2, a2 = self.dfluid.motion_extrema()
                else:  # rank 0 alone (a checkpoint restore): the whole water on its host, in chunks on the device
                    v2, a2 = self.state.motion_extrema()
                return fluid_dt_limit(self.fluid, self._cfl, math.sqrt(v2), math.sqrt(a2))

            out["fluid"] = fluid
        return out

    def _chunk_size(self) -> int:
        return 0  # step by step (a step exchanges halos)

    def _graph_usable(self) -> bool:
        return False  # a step talks to the other ranks (host MPI for the rebuild vote and dt)

    # ------------------------------------------------------------ one step ------------------
    def _launch_step(self, ts, reorder: bool = False) -> None:
        df, tm = self.dfluid, self.timings
        t = time.perf_counter()
        # a fresh layout (partition, restore) builds its lists in this step; else the ranks vote on the skin check,
        # and a rebuild is a relayout on every rank: faces moved (load balance), migration, new halos, new lists
        expired = not df.solver.build_now and df.lists_expired()
        t = _lap(tm, "check", t)
        if expired:
            if self.balance_tolerance is not None and df._since_balance["steps"] >= self.balance_interval:
                df.rebalance(self.balance_tolerance, self.balance_by)
            df.relayout()
            _lap(tm, "relayout", t)
        timer = df.timer = StepTimer(self.device)
        state, local, solver = df.state, df.local, df.solver
        if self.coupling is not None:
            self._coupled_compute(state, local, ts)
        timer.mark("compute")
        solver.step(state, ts)
        if self.coupling is not None:
            self.coupling.fluid, keep = replace(local, n_fluid=df.n_own), self.coupling.fluid
            try:
                self.coupling.apply(state, ts)
            finally:
                self.coupling.fluid = keep
        # the halo of the next step: the owners' new x, v, rho (every step; the halo set changes at rebuilds only)
        timer.mark("halo")
        df.refresh_halo()
        timer.mark("end")
        wp.synchronize_device(self.device)
        parts: dict[str, float] = {}
        timer.lap(parts)
        df.timer = None
        df.add_compute(parts.get("compute", 0.0))
        for k, v in parts.items():
            tm[k] = tm.get(k, 0.0) + v
        df.steps += 1
        if self.block_solver is not None:  # replicated: identical loads, identical steps on every rank
            self.block_stepping.advance(self.block_solver, self.block_state, ts)

    def _coupled_compute(self, state, local, ts) -> None:
        """The coupling over the owned particles only (they come first); the block loads summed over ranks."""
        MPI = require_mpi()
        bs = self.block_state
        before = [bs.ext_force.numpy().astype(np.float64), bs.ext_torque.numpy().astype(np.float64)]
        impulse0 = self.coupling.wall_impulse.copy()
        if self.coupling.dv.shape[0] < self.dfluid.n_own:  # a slab build sized it for the seeded particles
            self.coupling.dv = wp.zeros(int(self.dfluid.SOLVER_HEADROOM * self.dfluid.n_own) + 256, dtype=wp.vec3,
                                        device=self.device)
        self.coupling.fluid, keep = replace(local, n_fluid=self.dfluid.n_own), self.coupling.fluid
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
        """Rank 0: send the command, with the clock and blocks when the state changed outside the steps (a restore);
        the water then goes out by partition()."""
        sync = None
        if self.clock.time != self._synced_time:
            provs = {k: p for k, p in ckpt.providers(self).items() if k in ("clock", "blocks")}
            sync = {k: p.pack(p.capture()) for k, p in provs.items()}
        self.comm.bcast((cmd, sync, self.clock.capture()), root=0)
        self._apply_sync(sync)

    def _apply_sync(self, sync) -> None:
        if sync is not None:
            if self.rank != 0:
                provs = ckpt.providers(self)
                for k, (arrays, meta) in sync.items():
                    provs[k].restore(arrays, meta)
            self.dfluid.partition(self.state)
            self.dfluid.start_walls()
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
        def due() -> bool:  # rank 0: does anything read the water after this step?
            if time.perf_counter() - self._last_gather >= GATHER_WALL_S:
                return True
            return self._gather_every_step and (self.gather_when is None or bool(self.gather_when()))

        def after_step():
            if self.comm.bcast(due() if self.rank == 0 else None, root=0):
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


def whole_scene_device_arrays(sim) -> int:
    """Live Warp allocations on ``sim``'s device (not views: slices, numpy memory) as long as the whole scene's
    water (n_fluid or n_fluid + n_boundary elements of the whole scene: what rank 0's output state was), other
    than the rank's own step arrays (those reachable from sim.dfluid, whose owned + halo count may equal n)."""
    import gc
    import types

    n, nb = sim.dfluid.n_global, sim.fluid.n_boundary
    dev = wp.get_device(sim.device)
    own, seen, todo = set(), {id(sim)}, [sim.dfluid]
    while todo:  # the objects reachable from the rank's water, not through the simulation
        o = todo.pop()
        if id(o) in seen or isinstance(o, (type, type(sys), types.FunctionType, types.MethodType)):
            continue
        seen.add(id(o))
        if isinstance(o, wp.array):
            own.add(id(o))
        todo.extend(gc.get_referents(o))
    return sum(1 for o in gc.get_objects() if isinstance(o, wp.array) and id(o) not in own
               and getattr(o, "device", None) == dev and getattr(o, "deleter", None) is not None
               and o.ptr is not None and o.shape[0] in (n, n + nb))


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
    ap.add_argument("--device", default="cpu", help="cpu (default) or cuda (one GPU per rank)")
    ap.add_argument("--balance", type=float, default=0.1, help="move the slab faces when a rank's load exceeds "
                    "(1 + BALANCE) x the mean (default 0.1)")
    ap.add_argument("--balance-by", choices=BALANCE_BY, default="count", help="a rank's load: its owned particles "
                    "(count, default: reproducible) or its measured compute time (time)")
    ap.add_argument("--transport", choices=KINDS, default="auto", help="how halos travel (default auto)")
    ap.add_argument("--output-chunk", type=int, default=None, help="rank 0 evaluates its outputs on the device this "
                    "many particles at a time (default HostWater.CHUNK)")
    ap.add_argument("--track-walls", action="store_true", help="sum the fixed and kinematic blocks' force on the "
                    "water (CouplingOptions.track_walls) and save it as wall_impulse")
    a = ap.parse_args(argv)
    wp.config.quiet = True
    options = None
    if a.track_walls:

        options = SimulationOptions(coupling=replace(coupling_options(load_scene(a.scene)), track_walls=True))
    sim = (Simulation(a.scene, device=a.device, options=options) if a.plain else
           DistributedSimulation(a.scene, device=a.device, options=options, balance_tolerance=a.balance,
                                 balance_by=a.balance_by, transport=a.transport, output_chunk=a.output_chunk))
    if not a.plain:  # each rank's seeded particles and the most lattice points its build held
        built = sim.comm.gather(sim.built["seeded"], root=0)
        held = sim.comm.gather(sim.built["held_points"], root=0)
    if not a.plain and sim.rank != 0:
        sim.serve()
        return 0
    for _ in range(a.frames):
        sim.advance(a.duration / a.frames)
    save = dict(x=sim.positions(), v=sim.velocities(), rho=sim.densities(), time=sim.time, steps=sim.steps,
                dt=sim.dt, blocks=sim.block_positions(), block_v=sim.block_velocities(), ranks=getattr(sim, "size", 1),
                wall_impulse=sim.coupling.wall_impulse if sim.coupling is not None else np.zeros(3))
    if not a.plain:
        df = sim.dfluid
        save.update(migrated=df.migrated_total, axis=df.dec.axis, rebalances=df.rebalances, faces=df.dec.faces,
                    relayouts=df.relayouts, rank_steps=df.steps, transport=sim.transport, solver_reuses=df.solver_reuses,
                    bytes_per_particle=df.bytes_per_particle(),
                    whole_device_arrays=whole_scene_device_arrays(sim), host_water=isinstance(sim.state, HostWater),
                    built=np.array(built), built_held=np.array(held), slab_build=sim.built["slab_build"])
        sim.close()
    np.savez(a.out, **save)
    return 0


if __name__ == "__main__":
    sys.exit(_main())
