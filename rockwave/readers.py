"""Readers: host copies of a simulation's state that leave it untouched.

Reading never reorders the particles, never drops the neighbour lists and never invalidates a
captured CUDA graph: when the fluid solver keeps its particles sorted by cell (FluidSolver.reorder),
a reader scatters them into a buffer of its own in the seeded order (state.ids) and copies that.
Gauges (:class:`Gauges`) are evaluated on the device from the current state and come back in one
host read for all gauges.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from rockwave.build import pad3
from rockwave.kernels import fluid as sph
from rockwave.kernels import readers as gk


class Gauges:
    """The scene's gauges (``[[output.gauges]]``) evaluated on the device.

    A 'height' gauge reads the free surface over a horizontal window of the kernel support radius H
    around its vertical line (the finest scale the SPH resolves): the plane is cut into columns one
    particle spacing s wide, those whose centre lies within H are used (2D: 2H/s columns; 3D: 12 at
    H = 2s), each wet column's top is its highest particle + s/2, and the reading is the median over
    the wet columns (NaN when none is wet), so a splashed particle does not set the reading.
    A 'pressure' gauge is the Shepard-normalised SPH interpolation of the pressure at its position [Pa].
    """

    def __init__(self, scene, fluid, device):
        g = scene.output.gauges
        self.names = [gg.name for gg in g]
        self.fluid = fluid
        self.up = scene.dim - 1
        n = len(g)
        self.cols = max(1, int(math.ceil(fluid.support_radius / fluid.spacing - 1e-6)))
        self.pos = wp.array(np.asarray([pad3(gg.position_m) for gg in g] or np.zeros((0, 3)), dtype=np.float32),
                            dtype=wp.vec3, device=device)
        self.is_height = wp.array(np.array([gg.kind == "height" for gg in g] or [0], dtype=np.int32), dtype=int,
                                  device=device)
        self.top = wp.zeros((max(n, 1), 4 * self.cols * self.cols), dtype=float, device=device)
        self.out = wp.zeros(max(n, 1), dtype=float, device=device)
        self.sums = wp.zeros((max(n, 1), 2), dtype=float, device=device)
        self.host = wp.zeros(max(n, 1), dtype=float, device="cpu", pinned=wp.get_device(device).is_cuda)
        self.heights = np.array([gg.kind == "height" for gg in g], dtype=bool)
        self.device = device

    def read(self, state) -> dict[str, float]:
        n, m = len(self.names), self.fluid
        if n == 0 or m.n_fluid == 0:
            return {}
        d = self.device
        self.top.fill_(-1.0e30)
        self.sums.zero_()
        wp.launch(gk.gauge_height, dim=(m.n_fluid, n), inputs=[state.x, self.pos, self.up, m.support_radius, m.spacing,
                                                              self.cols], outputs=[self.top], device=d)
        wp.launch(gk.gauge_pressure_sums, dim=(m.n_fluid, n), inputs=[state.x, state.rho, state.pressure, m.particle_mass,
                                                                     self.pos, m.params], outputs=[self.sums], device=d)
        wp.launch(gk.gauge_pressure, dim=n, inputs=[self.sums], outputs=[self.out], device=d)
        wp.launch(gk.gauge_median, dim=n, inputs=[self.top, self.is_height], outputs=[self.out], device=d)
        wp.copy(self.host, self.out)  # the one host read: every gauge at once
        if wp.get_device(d).is_cuda:
            wp.synchronize_stream(wp.get_stream(d))  # (asynchronous into pinned memory)
        vals = self.host.numpy()
        half = 0.5 * m.spacing
        return {name: float(vals[i]) + (half if self.heights[i] else 0.0) for i, name in enumerate(self.names)}


class Readers:
    """Host copies of a Simulation's fluid arrays in the seeded particle order, and its gauges."""

    def __init__(self, sim):
        self.sim = sim
        self.fluid = sim.fluid
        self.dim = sim.scene.dim
        self._buf = {}  # device buffers in the seeded order (when the solver sorts by cell)
        self._host = {}  # pinned host mirrors (CUDA)
        self._gauges = Gauges(sim.scene, sim.fluid, sim.device) if sim.fluid is not None else None

    def view(self, name: str) -> np.ndarray:
        """state.<name>[:n_fluid] (x, v, rho or pressure) in the seeded order, in the state's precision
        (float32), as a view of a host buffer of this reader (pinned memory on a GPU: one device-to-host copy,
        no allocation). The view is overwritten by the next read of the same quantity: copy it to keep it.
        The fast path for monitoring a large run; positions() etc. return new float64 arrays."""
        st, m = self.sim.state, self.fluid
        a = getattr(st, name)
        nf = m.n_fluid
        if nf == 0:
            return a.numpy()[:0]
        src = a
        if getattr(self.sim.fluid_solver, "sorted_by_cell", False):
            src = self._buf.get(name)
            if src is None:
                src = self._buf[name] = wp.empty(nf, dtype=a.dtype, device=a.device)
            wp.launch(sph.scatter_by, dim=nf, inputs=[st.ids, a, src], device=a.device)
        if not a.device.is_cuda:
            return src.numpy()[:nf]
        host = self._host.get(name)
        if host is None:
            host = self._host[name] = wp.empty(nf, dtype=a.dtype, device="cpu", pinned=True)
        wp.copy(host, src, 0, 0, nf)
        wp.synchronize_stream(wp.get_stream(a.device))  # a copy into pinned memory is asynchronous
        return host.numpy()

    def positions(self) -> np.ndarray:
        if self.fluid is None:
            return np.zeros((0, self.dim))
        return self.view("x")[:, : self.dim].astype(np.float64)

    def velocities(self) -> np.ndarray:
        if self.fluid is None:
            return np.zeros((0, self.dim))
        return self.view("v")[:, : self.dim].astype(np.float64)

    def densities(self) -> np.ndarray:
        return self.view("rho").astype(np.float64)

    def pressures(self) -> np.ndarray:
        return self.view("pressure").astype(np.float64)

    def boundary_positions(self) -> np.ndarray:
        m = self.fluid
        return self.sim.state.x.numpy()[m.n_fluid:, : self.dim].astype(np.float64)

    def gauges(self) -> dict[str, float]:
        if self._gauges is None:
            return {}
        return self._gauges.read(self.sim.state)
