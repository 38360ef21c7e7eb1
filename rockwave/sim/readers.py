"""Readers: host copies of a simulation's state that leave it untouched.

Reading never reorders the particles, never drops the neighbour lists and never invalidates a
captured CUDA graph: when the fluid solver keeps its particles sorted by cell (FluidSolver.reorder),
a reader scatters them into a buffer of its own in the seeded order (state.ids) and copies that.
Gauges (:class:`Gauges`) are evaluated on the device from the current state and come back in one
host read for all gauges.

For monitoring a large run on a GPU, ``view_async`` and ``gauges_async`` queue a read behind the steps
launched so far and return at once; ``result()`` waits for it. Launching the next steps before waiting keeps
the GPU busy while the copy is on its way (benchmarks/readers.py, mode "async")::

    pending = None
    while running:
        sim.step_many(10)
        if pending:
            x, g = pending[0].result(), pending[1].result()   # the state after the previous block
        pending = sim.readers.view_async("x"), sim.readers.gauges_async()
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from rockwave.base.maths import pad3, quat_to_matrix
from rockwave.coupling.penalty import block_signed_distance
from rockwave.dda.geometry import box, shifted
from rockwave.kernels.coupling import penalty as penalty_k
from rockwave.kernels.sim import readers as gauge_k
from rockwave.kernels.sph import fluid as sph


def face_samples(geometry, dim: int, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points on a convex block's faces in its body frame and the area vector A_k n_k (outward) each stands for,
    about ``step`` apart: 3D, every face's fan triangles cut into m^2 similar triangles (m = ceil(longest edge /
    step)), one point at each centroid; 2D (a prism along z, the water in the x-y plane at z = 0), the side faces'
    edges in the x-y plane cut into ceil(length / step) pieces, one point at each middle, per metre of depth (the
    end caps carry no water)."""
    pts, areas = [], []
    V = np.asarray(geometry.vertices, float)
    for f, n in zip(geometry.faces, np.asarray(geometry.face_normals, float)):
        loop = V[np.asarray(f)]
        if dim == 2:
            if abs(n[2]) > 0.5:
                continue
            xy = np.unique(np.round(loop[:, :2], 12), axis=0)
            if len(xy) != 2:  # (a side face of a prism has two distinct x-y corners)
                continue
            a, b = xy
            length = float(np.linalg.norm(b - a))
            m = max(1, math.ceil(length / step))
            t = (np.arange(m) + 0.5) / m
            seg = a[None, :] + t[:, None] * (b - a)[None, :]
            pts.append(np.column_stack([seg, np.zeros(m)]))
            nxy = np.array([n[0], n[1], 0.0]) / max(math.hypot(n[0], n[1]), 1e-30)
            areas.append(np.repeat((length / m) * nxy[None, :], m, axis=0))
            continue
        for i in range(1, len(loop) - 1):
            p0, e1, e2 = loop[0], loop[i] - loop[0], loop[i + 1] - loop[0]
            area = 0.5 * float(np.linalg.norm(np.cross(e1, e2)))
            m = max(1, math.ceil(max(np.linalg.norm(e1), np.linalg.norm(e2), np.linalg.norm(e2 - e1)) / step))
            ab = []
            for u in range(m):  # the m^2 sub-triangles' centroids in (e1, e2) coordinates
                for v in range(m - u):
                    ab.append(((u + 1.0 / 3.0) / m, (v + 1.0 / 3.0) / m))
                    if v < m - u - 1:
                        ab.append(((u + 2.0 / 3.0) / m, (v + 2.0 / 3.0) / m))
            ab = np.asarray(ab)
            pts.append(p0[None, :] + ab[:, :1] * e1[None, :] + ab[:, 1:] * e2[None, :])
            areas.append(np.repeat((area / (m * m)) * n[None, :], len(ab), axis=0))
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(pts), np.concatenate(areas)


class HostWater:
    """The whole scene's water held on the host (rank 0 of a distributed run, rockwave/sim/distributed.py): numpy
    float32 arrays in id order (x and v: the fluid, then the static walls; rho, pressure, accel: the fluid; the
    walls' pressure and velocity), filled from the ranks a chunk at a time. Device kernels see it in chunks of at
    most ``chunk`` particles (``fluid_chunks``, ``wall_chunks``), copied into device buffers that are kept from
    call to call: the device holds ``chunk`` particles of it, never the whole scene. A sum over particles (the
    gauges' profiles and Shepard sums, the hazard's volumes, the surface field) is the sum of the chunks' sums."""

    CHUNK = 1 << 21  # particles per chunk (at most 52 B each of device buffers: x, v, a, rho, p, mass, the walls')

    def __init__(self, n_fluid: int, xb: np.ndarray, wall_mass: np.ndarray, fluid_mass: float, device,
                 chunk: int | None = None):
        n, nb = int(n_fluid), len(xb)
        self.n_fluid, self.n_boundary = n, nb
        self.x = np.zeros((n + nb, 3), np.float32)
        self.x[n:] = np.asarray(xb, np.float32).reshape(-1, 3)
        self.v = np.zeros((n + nb, 3), np.float32)
        self.rho = np.zeros(n, np.float32)
        self.pressure = np.zeros(n, np.float32)
        self.accel = np.zeros((n, 3), np.float32)
        self.ids = np.arange(n, dtype=np.int32)  # id order: slot i holds particle i
        self.wall_pressure = np.zeros(max(nb, 1), np.float32)
        self.wall_velocity = np.zeros((max(nb, 1), 3), np.float32)
        self.fluid_mass = float(fluid_mass)
        self.wall_mass = np.asarray(wall_mass, np.float32).reshape(-1)
        self.device = device
        self.chunk = max(int(chunk or self.CHUNK), 1)
        self._dev: dict[str, wp.array] = {}  # the chunk buffers on the device

    def _upload(self, name: str, host: np.ndarray, dtype) -> wp.array:
        """host (rows of one chunk) in the device buffer ``name`` (made once: a chunk, or less in a small scene)."""
        buf = self._dev.get(name)
        if buf is None:
            buf = self._dev[name] = wp.empty(self._length(), dtype=dtype, device=self.device)
        n = len(host)
        if n:
            wp.copy(buf, wp.array(np.ascontiguousarray(host), dtype=dtype, device="cpu", copy=False), 0, 0, n)
        return buf[:n]

    def _length(self) -> int:
        return max(min(self.chunk, max(self.n_fluid, self.n_boundary)), 1)

    def _mass(self, n: int) -> wp.array:
        buf = self._dev.get("mass")
        if buf is None:
            buf = self._dev["mass"] = wp.empty(self._length(), dtype=float, device=self.device)
            buf.fill_(self.fluid_mass)
        return buf[:n]

    def fluid_chunks(self, fields=("x", "rho", "pressure")):
        """The fluid in chunks: (n, arrays) with arrays[f] the device copy of ``f`` of particles [start, start + n)
        and arrays["mass"] their masses (all equal: a distributed run's fluid particles share one mass)."""
        types = {"x": wp.vec3, "v": wp.vec3, "accel": wp.vec3, "rho": float, "pressure": float}
        for s in range(0, self.n_fluid, self.chunk):
            e = min(s + self.chunk, self.n_fluid)
            arrays = {f: self._upload(f, getattr(self, f)[s:e], types[f]) for f in fields}
            arrays["mass"] = self._mass(e - s)
            yield e - s, arrays

    def wall_chunks(self):
        """The static walls in chunks: (n, positions, pressures, masses) device copies."""
        nf = self.n_fluid
        for s in range(0, self.n_boundary, self.chunk):
            e = min(s + self.chunk, self.n_boundary)
            yield (e - s, self._upload("x", self.x[nf + s: nf + e], wp.vec3),
                   self._upload("wall_pressure", self.wall_pressure[s:e], float),
                   self._upload("wall_mass", self.wall_mass[s:e], float))

    def motion_extrema(self) -> tuple[float, float]:
        """max |v|^2 and |a|^2 over the fluid (kernels/sph/fluid.py motion_extrema over the chunks)."""
        out = wp.zeros(2, dtype=float, device=self.device)
        for n, a in self.fluid_chunks(("v", "accel")):
            stride = min(n, 16384)
            wp.launch(sph.motion_extrema, dim=stride, inputs=[a["v"], a["accel"], n, stride], outputs=[out],
                      device=self.device)
        v2, a2 = (float(c) for c in out.numpy())
        return v2, a2

    def device_bytes(self) -> int:
        """Bytes of the chunk buffers on the device."""
        return sum(b.capacity for b in self._dev.values())


def _params_with(p, n_fluid: int):
    """A copy of the SPHParams ``p`` with ``n_fluid`` fluid particles."""
    q = sph.SPHParams()
    for name in sph.SPHParams.vars:
        setattr(q, name, getattr(p, name))
    q.n_fluid = n_fluid
    return q


def fluid_chunks(state, m, fields=("x", "rho", "pressure")):
    """(n, arrays) over the fluid of ``state``: a HostWater's chunks, or the device state in one piece."""
    if isinstance(state, HostWater):
        yield from state.fluid_chunks(fields)
        return
    arrays = {f: getattr(state, f) for f in fields}
    arrays["mass"] = m.particle_mass
    yield m.n_fluid, arrays


class ForceGauges:
    """Force gauges (``[[output.gauges]]`` kind 'force'): the water's pressure force on a block along a direction,
    F . e = -sum_k p(x_k) A_k (n_k . e) over points x_k on the block's faces (face_samples, half a particle spacing
    apart), posed with the block now (a deformable block's strain is not followed). p(x_k) is the Shepard
    interpolation over the fluid and, with Adami walls, the wall particles (kernels/sim/readers.py
    surface_pressure); a point where the water fills less than WET_MIN of the kernel support reads 0 (a face on the
    floor, pressed on another block or above the water). With Adami walls on the block (coupling.block_walls, or a
    fixed block) the interpolation is centred on the face and still water gives Archimedes' force (test:
    tests/test_force_gauges.py); other wall kinds read the pressure of the water half a support off the face.
    Viscous shear is not included (SPH's artificial viscosity carries no physical shear stress). 2D: N per metre
    of depth. A multi-part block (mesh) sums its parts' faces; faces shared by two parts are dry."""

    WET_MIN = 0.1

    def __init__(self, gauges, rows: list[int], fluid, blocks, device, dim: int, obstacles=()):
        self.rows, self.fluid, self.blocks, self.device, self.dim = rows, fluid, blocks, device, dim
        names = blocks.names if blocks is not None else []
        pts, areas, part, owner = [], [], [], []
        self.direction = np.zeros((len(rows), 3))
        for gi, g in enumerate(gauges):
            parts = [b for b, nm in enumerate(names) if nm == g.block or nm.startswith(g.block + ".part")]
            e = pad3(g.direction)
            self.direction[gi] = np.asarray(e, float) / np.linalg.norm(e)
            shapes = [(blocks.specs[b].geometry, b) for b in parts]
            if not parts and g.block.startswith("obstacle."):  # a box obstacle: fixed, sampled where it lies (part -1)
                k = int(g.block.split(".", 1)[1])
                lo, hi = np.asarray(pad3(obstacles[k].box_min_m), float), np.asarray(pad3(obstacles[k].box_max_m), float)
                if dim == 2:
                    lo[2], hi[2] = -0.5, 0.5
                shapes = [(shifted(box(hi - lo), 0.5 * (lo + hi)), -1)]
            if not shapes:
                raise ValueError(f"force gauge {g.name!r}: no block named {g.block!r}")
            for geom, b in shapes:
                r, a = face_samples(geom, dim, 0.5 * fluid.spacing)
                pts.append(r)
                areas.append(a)
                part.append(np.full(len(r), b))
                owner.append(np.full(len(r), gi))
        self.body_r = np.concatenate(pts)
        self.body_a = np.concatenate(areas)
        self.part = np.concatenate(part)
        self.owner = np.concatenate(owner)
        self.points = wp.zeros(len(self.body_r), dtype=wp.vec3, device=device)
        self.p = wp.zeros(len(self.body_r), dtype=float, device=device)
        self.grid = wp.HashGrid(128, 128, 128 if dim == 3 else 1, device=device)

    def world(self, block_state) -> tuple[np.ndarray, np.ndarray]:
        """The sample points and their area vectors posed with the blocks now."""
        pts, areas = self.body_r.copy(), self.body_a.copy()  # part -1: a box obstacle, in the world frame
        moving = self.part >= 0
        if moving.any():
            x = block_state.positions_numpy().astype(np.float64)
            q = block_state.orientations_numpy().astype(np.float64)
            R = np.stack([quat_to_matrix(qq) for qq in q])[self.part[moving]]
            pts[moving] = x[self.part[moving]] + np.einsum("kij,kj->ki", R, self.body_r[moving])
            areas[moving] = np.einsum("kij,kj->ki", R, self.body_a[moving])
        if self.dim == 2:
            pts[:, 2] = 0.0
        return pts, areas

    def pressures(self, state, block_state) -> tuple[np.ndarray, np.ndarray]:
        """(p at every sample point [Pa], the posed area vectors)."""
        m = self.fluid
        pts, areas = self.world(block_state)
        self.points.assign(pts.astype(np.float32))
        if isinstance(state, HostWater):
            return self._chunked_pressures(state), areas
        n_all = m.n_fluid + m.n_boundary
        self.grid.build(state.x, m.support_radius)
        adami = int(m.params.boundary == sph.BOUNDARY_ADAMI and m.n_boundary > 0)
        wp.launch(gauge_k.surface_pressure, dim=len(pts),
                  inputs=[self.grid.id, state.x, state.rho, state.pressure, state.wall_pressure, m.particle_mass, adami,
                          n_all, self.points, m.params, self.WET_MIN], outputs=[self.p], device=self.device)
        return self.p.numpy().astype(np.float64), areas

    def _chunked_pressures(self, host: HostWater) -> np.ndarray:
        """pressures() over a HostWater: the four Shepard sums at each point (fluid and wall, numerator and
        volume) summed over its chunks (a hash grid of each chunk), then surface_pressure's ratio."""
        m, d, n = self.fluid, self.device, len(self.body_r)
        sums = wp.zeros((n, 4), dtype=float, device=d)
        for k, a in host.fluid_chunks():
            self.grid.build(a["x"], m.support_radius)
            wp.launch(gauge_k.surface_pressure_sums, dim=n, inputs=[self.grid.id, a["x"], a["rho"], a["pressure"], a["mass"],
                                                                  0, k, self.points, m.params], outputs=[sums], device=d)
        if m.params.boundary == sph.BOUNDARY_ADAMI and m.n_boundary:
            for k, xw, pw, mw in host.wall_chunks():
                self.grid.build(xw, m.support_radius)
                wp.launch(gauge_k.surface_pressure_sums, dim=n, inputs=[self.grid.id, xw, pw, pw, mw, 1, k, self.points,
                                                                      m.params], outputs=[sums], device=d)
        wp.launch(gauge_k.surface_pressure_finish, dim=n, inputs=[sums, self.WET_MIN], outputs=[self.p], device=d)
        return self.p.numpy().astype(np.float64)

    def read(self, state, block_state) -> np.ndarray:
        """Each gauge's force along its direction [N; 2D N/m]."""
        p, areas = self.pressures(state, block_state)
        f = -(p[:, None] * areas)  # the water pushes on a face against its outward normal
        out = np.zeros(len(self.rows))
        np.add.at(out, self.owner, np.einsum("kj,kj->k", f, self.direction[self.owner]))
        return out


class MovingSolids:
    """The moving blocks (every block not 'fixed': rigid, deformable, kinematic, compound parts) as solid on the
    height gauges' lines, evaluated at each read from the blocks' poses (kernels/sim/readers.py
    moving_solid_profile): at a sample a signed distance ``dist`` from block b (max over its face planes, rigidly
    moved), the block's solid fraction is phi_m = 1 inside (dist < 0) and F(dist) within H outside, F(d) the
    kernel's weight beyond a plane d from the kernel's centre (1/2 on the face, 0 from H out; the scene's kernel
    integrated once in slabs, kernel_slabs): what a flat face's wall particles would add to phi_s. Where blocks
    meet, the largest.

    ``line_solids[g]``: the blocks line g may meet (all moving blocks; a batch line: its scenario's). Rows of
    ``phi`` follow the lines; ``launch(block_state)`` fills it."""

    SLABS = 256  # F tabulated at SLABS + 1 distances across [-H, H]

    def __init__(self, blocks, moving: list[int], line_solids: list[list[int]], line_pos: wp.array, z0: np.ndarray,
                 dz: np.ndarray, n: np.ndarray, n_samples: int, up: int, params, device):
        self.blocks, self.device, self.up = blocks, device, up
        self.H = float(params.H)
        arr = lambda a, dt=int: wp.array(np.asarray(a), dtype=dt, device=device)  # noqa: E731
        fb, normals, offsets, first, count, radius = [], [], [], [], [], []
        for b in moving:
            g = blocks.specs[b].geometry
            first.append(len(fb))
            count.append(g.num_faces)
            fb += [b] * g.num_faces
            normals.append(np.asarray(g.face_normals, np.float32))
            offsets.append(np.asarray(g.face_offsets, np.float32))
            radius.append(float(np.linalg.norm(np.asarray(g.vertices, float), axis=1).max()))  # about the centroid
        self.face_block = arr(np.asarray(fb, np.int32))
        self.body_normal = wp.array(np.concatenate(normals), dtype=wp.vec3, device=device)
        self.body_offset = arr(np.concatenate(offsets), float)
        self.plane_n = wp.zeros(len(fb), dtype=wp.vec3, device=device)
        self.plane_d = wp.zeros(len(fb), dtype=float, device=device)
        self.solid_block = arr(np.asarray(moving, np.int32))
        self.solid_radius = arr(np.asarray(radius, np.float32), float)
        self.face_first, self.face_count = arr(np.asarray(first, np.int32)), arr(np.asarray(count, np.int32))
        flat, sf, sc, seen = [], [], [], {}
        for lst in line_solids:  # lines with the same blocks share their entries (a solo run: all lines)
            key = tuple(lst)
            if key not in seen:
                seen[key] = len(flat)
                flat += list(lst)
            sf.append(seen[key])
            sc.append(len(lst))
        self.max_count = max(sc) if sc else 0
        self.solid_first, self.solid_count = arr(np.asarray(sf, np.int32)), arr(np.asarray(sc, np.int32))
        self.solid_list = arr(np.asarray(flat or [0], np.int32))
        self.line_pos = line_pos
        self.z0, self.dz = arr(np.asarray(z0, np.float32), float), arr(np.asarray(dz, np.float32), float)
        self.n = arr(np.asarray(n, np.int32))
        self.phi = wp.zeros((len(line_solids), n_samples), dtype=float, device=device)
        slabs = wp.zeros(self.SLABS, dtype=float, device=device)
        wp.launch(gauge_k.kernel_slabs, dim=self.SLABS, inputs=[params, self.SLABS], outputs=[slabs], device=device)
        w = slabs.numpy().astype(np.float64)
        F = np.concatenate([np.cumsum(w[::-1])[::-1], [0.0]]) / w.sum()  # F(d_i), d_i = -H + i 2H/SLABS
        self.table = arr(F.astype(np.float32), float)

    def launch(self, block_state) -> wp.array:
        """phi_m along the lines now (device launches only); returns ``phi``."""
        d = self.device
        self.phi.zero_()
        if self.max_count == 0:
            return self.phi
        wp.launch(penalty_k.face_planes, dim=self.face_block.shape[0],
                  inputs=[self.face_block, self.body_normal, self.body_offset, block_state.x, block_state.q],
                  outputs=[self.plane_n, self.plane_d], device=d)
        wp.launch(gauge_k.moving_solid_profile, dim=(self.phi.shape[0], self.max_count),
                  inputs=[self.line_pos, self.z0, self.dz, self.n, self.solid_first, self.solid_count, self.solid_list,
                          self.solid_block, self.solid_radius, self.face_first, self.face_count, self.plane_n,
                          self.plane_d, block_state.x, self.up, self.H, self.table], outputs=[self.phi], device=d)
        return self.phi


def moving_blocks(specs) -> list[int]:
    """Indices of the blocks that move (not 'fixed'; the [tank]'s blocks are fixed)."""
    return [b for b, spec in enumerate(specs) if spec.kind != "fixed" and not getattr(spec, "tank", False)]


class Gauges:
    """The scene's gauges (``[[output.gauges]]``) evaluated on the device.

    A 'height' gauge reads the top of the continuous water column from the bed along its vertical line
    (the gauge's horizontal position; its vertical coordinate is not used). The line runs from the
    bottom of the particle domain (below the tank floor: the lowest boundary or fluid particle less the
    kernel support H) to one domain height above its top, sampled every s/8 (s: particle spacing). At
    each sample z the water fraction is phi(z) = phi_f / (1 - phi_s), with phi_f = sum_j (m_j/rho_j)
    W(|x(z) - x_j|) over the fluid particles (the scene's kernel) and phi_s the same sum over the static
    boundary particles (volume Psi_b/rho0; computed once): away from walls phi = phi_f; next to a wall,
    whose particles fill part of the kernel support, bulk water still reads 1; where 1 - phi_s < 0.2 (inside
    a wall) phi = 0. Going up from the lower end, the bed is where phi first reaches 0.5 and the reading is
    where it next drops below 0.5, linearly interpolated between the two samples. Water overhead with air
    between (spray, a jet, a splash) does not count; a film too thin to reach phi = 0.5 (about one particle
    layer) reads dry. NaN when dry. Still water whose top particle layer is at z_top reads z_top + s/2.
    The column must start within 2H of the bed, the lowest point of the line not inside a wall (boundary
    particles, or a fixed DDA block: a floor, beach or wall of blocks); water on the line that rests on
    nothing (a jet over a dry bed) reads NaN. Moving blocks are solid too (MovingSolids, at every read from their
    poses): phi = phi_f / (1 - phi_s - phi_m), phi_m = 1 inside a block and the kernel's half-space share F(dist)
    within H outside it; so over a submerged block the reading is the surface above it, and a line through a block
    that is out of the water there (the water pressed against it, its top dry) reads NaN (docs/outputs.md).
    A 'pressure' gauge is the Shepard-normalised SPH interpolation of the pressure at its position [Pa], over
    the fluid particles and, with Adami walls, the wall particles (whose pressure continues the fluid's), so a
    sensor placed on a wall surface reads the wall pressure there.
    """

    MAX_SAMPLES = 1 << 16  # per gauge line; the step grows past s/8 only for a domain 8192 spacings tall

    def __init__(self, scene, fluid, device, blocks=None, block_state=None, gauges=None, host=None):
        """``host``: the HostWater the readings will come from (rank 0 of a distributed run; its static walls)."""
        g = scene.output.gauges if gauges is None else gauges  # gauges: objects with name, kind, position_m
        self.names = [gg.name for gg in g]
        self.fluid = fluid
        self.up = up = scene.dim - 1
        n = len(g)
        forces = [i for i, gg in enumerate(g) if gg.kind == "force"]
        self.block_state = block_state
        self.forces = (ForceGauges([g[i] for i in forces], forces, fluid, blocks, device, scene.dim, scene.obstacles)
                       if forces else None)
        self.pos = wp.array(np.asarray([pad3(gg.position_m) if gg.kind != "force" else (0.0, 0.0, 0.0) for gg in g]
                                       or np.zeros((0, 3)), dtype=np.float32), dtype=wp.vec3, device=device)
        heights = [gg.kind == "height" for gg in g]
        self.is_height = wp.array(np.array(heights or [0], dtype=np.int32), dtype=int, device=device)
        lo, hi = float(fluid.domain_lo[up]), float(fluid.domain_hi[up])
        top = hi + (hi - lo)  # one domain height above: a column running up a wall or overtopping it
        self.dz = max(fluid.spacing / 8.0, (top - lo) / (self.MAX_SAMPLES - 1))
        self.z0 = lo
        # the water must reach phi = 0.5 within 2H of the bed (the lowest point of the line not inside a wall):
        # water on a dry bed sits there within ~H/2, while the bottom of the line is H below the lowest particle
        self.reach = int(math.ceil(2.0 * fluid.support_radius / self.dz))
        self.n_samples = int(math.ceil((top - lo) / self.dz)) + 1 if any(heights) else 1
        rows = max(n, 1)
        self.phi_f = wp.zeros((rows, self.n_samples), dtype=float, device=device)
        self.phi_s = wp.zeros((rows, self.n_samples), dtype=float, device=device)
        nf, nb = fluid.n_fluid, fluid.n_boundary - getattr(fluid, "n_moving_walls", 0)
        if any(heights) and nb and host is not None:  # the walls of a HostWater, in chunks
            for k, xw, _, mw in host.wall_chunks():
                wp.launch(gauge_k.gauge_solid_profile, dim=(k, n), inputs=[xw, mw, 0, self.pos, self.is_height, up,
                                                                          self.z0, self.dz, fluid.params],
                          outputs=[self.phi_s], device=device)
        elif any(heights) and nb:  # the static walls: their fraction along the lines once (not the moving blocks')
            xb = wp.array(np.asarray(fluid.initial_positions[nf:nf + nb], dtype=np.float32), dtype=wp.vec3, device=device)
            wp.launch(gauge_k.gauge_solid_profile, dim=(nb, n), inputs=[xb, fluid.particle_mass, nf, self.pos, self.is_height,
                                                                   up, self.z0, self.dz, fluid.params],
                      outputs=[self.phi_s], device=device)
        if any(heights) and blocks is not None and any(spec.kind == "fixed" and not spec.tank for spec in blocks.specs):
            self._add_fixed_blocks(blocks, block_state, heights)
        self.moving = None  # the moving blocks' fraction along the lines, at each read (MovingSolids)
        movers = moving_blocks(blocks.specs) if any(heights) and blocks is not None and block_state is not None else []
        if movers:
            self.moving = MovingSolids(blocks, movers, [list(range(len(movers))) if h else [] for h in heights], self.pos,
                                       np.full(rows, self.z0), np.full(rows, self.dz), np.full(rows, self.n_samples),
                                       self.n_samples, up, fluid.params, device)
        self.out = wp.zeros(rows, dtype=float, device=device)
        self.sums = wp.zeros((rows, 2), dtype=float, device=device)
        pinned = wp.get_device(device).is_cuda
        self.hosts = [wp.zeros(rows, dtype=float, device="cpu", pinned=pinned) for _ in range(2)]  # used in turn
        self.any_height = any(heights)
        self.device = device

    def _add_fixed_blocks(self, blocks, block_state, heights) -> None:
        """Samples inside a fixed DDA block (a floor, a beach, a wall built of blocks: no boundary particles)
        count as wall (phi_s = 1), so the bed on such a line is the block's top (once, at start-up: fixed blocks
        do not move)."""

        z = self.z0 + self.dz * np.arange(self.n_samples)
        pos = self.pos.numpy().astype(np.float64)
        phi_s = self.phi_s.numpy()
        fixed = np.array([spec.kind == "fixed" and not spec.tank for spec in blocks.specs])  # the [tank]: its particles
        for gi, is_h in enumerate(heights):
            if not is_h:
                continue
            pts = np.repeat(pos[gi][None, :], len(z), axis=0)
            pts[:, self.up] = z
            dist, which = block_signed_distance(blocks, block_state, pts)
            phi_s[gi, (dist < 0.0) & fixed[which]] = 1.0
        self.phi_s.assign(phi_s)

    def read(self, state) -> dict[str, float]:
        """The readings now (one host read for all gauges)."""
        return self.read_async(state).result()

    def read_async(self, state) -> "PendingRead":
        """Queue the readings on the device (the copy to the host included); ``result()`` waits for them. The
        host may launch more steps in between, which keeps the GPU busy while the copy is on its way."""
        n, m = len(self.names), self.fluid
        if n == 0 or m.n_fluid == 0:
            return PendingRead(None, None, lambda a: {})
        d = self.device
        self.sums.zero_()
        for k, a in fluid_chunks(state, m):
            wp.launch(gauge_k.gauge_pressure_sums, dim=(k, n), inputs=[a["x"], a["rho"], a["pressure"], a["mass"], self.pos,
                                                                 m.params], outputs=[self.sums], device=d)
        if m.params.boundary == sph.BOUNDARY_ADAMI and m.n_boundary:  # Adami walls carry the fluid's pressure
            if isinstance(state, HostWater):  # the walls' chunks: wall b at slot b (n_fluid 0 in the kernel's params)
                p0 = _params_with(m.params, 0)
                for k, xw, pw, mw in state.wall_chunks():
                    wp.launch(gauge_k.gauge_pressure_wall_sums, dim=(k, n), inputs=[xw, pw, mw, self.pos, p0],
                              outputs=[self.sums], device=d)
            else:
                wp.launch(gauge_k.gauge_pressure_wall_sums, dim=(m.n_boundary, n),
                          inputs=[state.x, state.wall_pressure, m.particle_mass, self.pos, m.params], outputs=[self.sums],
                          device=d)
        wp.launch(gauge_k.gauge_pressure, dim=n, inputs=[self.sums], outputs=[self.out], device=d)
        self.launch_levels(state)
        names = self.names
        forces = None
        if self.forces is not None:  # (read at once: the blocks' poses come to the host for the sample points)
            forces = dict(zip(self.forces.rows, self.forces.read(state, self.block_state)))

        def finish(vals):
            return {name: float(forces[i] if forces and i in forces else vals[i]) for i, name in enumerate(names)}

        self.hosts.reverse()
        return _queue_copy(self.hosts[0], self.out, n, d, finish)

    def launch_levels(self, state) -> wp.array:
        """Queue the height gauges' readings into ``self.out`` on the device (no host read; rockwave/output/hazard.py
        reduces them there). Returns ``self.out``."""
        m = self.fluid
        if self.any_height and m.n_fluid:
            self.phi_f.zero_()
            for k, a in fluid_chunks(state, m, ("x", "rho")):
                wp.launch(gauge_k.gauge_fluid_profile, dim=(k, len(self.names)),
                          inputs=[a["x"], a["rho"], a["mass"], self.pos, self.is_height, self.up, self.z0, self.dz,
                                  m.params], outputs=[self.phi_f], device=self.device)
            moving = self.moving.launch(self.block_state) if self.moving is not None else self.phi_s
            wp.launch(gauge_k.gauge_level, dim=len(self.names),
                      inputs=[self.phi_f, self.phi_s, moving, int(self.moving is not None), self.is_height, self.z0,
                              self.dz, self.reach], outputs=[self.out], device=self.device)
        return self.out

    def profiles(self, state) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(z, phi_f, phi_s) along the height gauges' lines now (host copies; rows in gauge order; phi_s the solid
        fraction: the static walls' and the moving blocks' phi_m): for inspecting a reading."""
        self.read(state)
        z = self.z0 + self.dz * np.arange(self.n_samples)
        solid = self.phi_s.numpy().copy()
        if self.moving is not None:
            solid += self.moving.phi.numpy()
        return z, self.phi_f.numpy().copy(), solid


class PendingRead:
    """A read queued on the device: ``result()`` waits for its copy to reach the host and returns it."""

    def __init__(self, host, event, finish):
        self.host, self.event, self.finish = host, event, finish

    def result(self):
        if self.event is not None:
            wp.synchronize_event(self.event)
        return self.finish(self.host.numpy() if self.host is not None else None)


def _queue_copy(host: wp.array, src: wp.array, n: int, device, finish) -> PendingRead:
    """Copy src[:n] into the host buffer on the device's stream and record an event after it (CUDA; on the
    CPU the copy is done at once)."""
    wp.copy(host, src, 0, 0, n)
    event = None
    if wp.get_device(device).is_cuda:
        with wp.ScopedDevice(device):
            event = wp.record_event()  # a copy into pinned memory is asynchronous
    return PendingRead(host, event, finish)


class Readers:
    """Host copies of a Simulation's fluid arrays in the seeded particle order, and its gauges."""

    def __init__(self, sim):
        self.sim = sim
        self.fluid = sim.fluid
        self.dim = sim.scene.dim
        self._buf = {}  # device buffers in the seeded order (when the solver sorts by cell)
        self._host = {}  # host buffers, two per quantity (pinned on CUDA)
        self._copied = {}  # CUDA: the event after the last copy of each quantity to the host
        self._stream = None  # CUDA: the stream of the copies to the host
        host = sim.state if isinstance(sim.state, HostWater) else None
        self._gauges = (Gauges(sim.scene, sim.fluid, sim.device, getattr(sim, "blocks", None),
                               getattr(sim, "block_state", None), host=host) if sim.fluid is not None else None)

    def view(self, name: str) -> np.ndarray:
        """state.<name>[:n_fluid] (x, v, rho or pressure) in the seeded order, in the state's precision
        (float32), as a view of a host buffer of this reader (pinned memory on a GPU: one device-to-host copy,
        no allocation). The view is overwritten by the read after next of the same quantity: copy it to keep it.
        The fast path for monitoring a large run; positions() etc. return new float64 arrays."""
        return self.view_async(name).result()

    def view_async(self, name: str) -> PendingRead:
        """``view(name)`` queued on the device: ``result()`` waits for it. Each quantity has two host buffers
        used in turn, so a pending read stays valid while the next one of the same quantity is queued (a
        monitoring loop can launch the next steps before it waits: the GPU never idles on the copy)."""
        st, m = self.sim.state, self.fluid
        a = getattr(st, name)
        nf = m.n_fluid
        if isinstance(st, HostWater):  # already on the host, in id order (the seeded order)
            return PendingRead(None, None, lambda h: a[:nf])
        if nf == 0:
            return PendingRead(None, None, lambda h: a.numpy()[:0])
        pair = self._host.get(name)
        if pair is None:
            pinned = a.device.is_cuda
            pair = self._host[name] = [wp.empty(nf, dtype=a.dtype, device="cpu", pinned=pinned) for _ in range(2)]
        pair.reverse()  # the other buffer of the two (never the state's own memory, also on the CPU)
        sorted_ = getattr(self.sim.fluid_solver, "sorted_by_cell", False)
        if not a.device.is_cuda:
            if sorted_:
                a = self._snapshot(name, a, st.ids, nf)
            return _queue_copy(pair[0], a, nf, a.device, lambda h: h)
        # CUDA: a snapshot in the seeded order on the compute stream (cheap), then the copy to the host on a
        # side stream, so the next steps run while the copy engine works; the next snapshot of this quantity
        # waits for that copy
        compute = wp.get_stream(a.device)
        busy = self._copied.get(name)
        if busy is not None:
            compute.wait_event(busy)
        snap = self._snapshot(name, a, st.ids if sorted_ else None, nf)
        side = self._side_stream(a.device)
        side.wait_stream(compute)
        with wp.ScopedStream(side):
            wp.copy(pair[0], snap, 0, 0, nf)
            event = wp.record_event()
        self._copied[name] = event
        return PendingRead(pair[0], event, lambda h: h)

    def _snapshot(self, name: str, a: wp.array, ids, nf: int) -> wp.array:
        """state.<name>[:n_fluid] in the seeded order in a device buffer of ours (scattered by ids when sorted)."""
        buf = self._buf.get(name)
        if buf is None:
            buf = self._buf[name] = wp.empty(nf, dtype=a.dtype, device=a.device)
        if ids is not None:
            wp.launch(sph.scatter_by, dim=nf, inputs=[ids, a, buf], device=a.device)
        else:
            wp.copy(buf, a, 0, 0, nf)
        return buf

    def _side_stream(self, device):
        if self._stream is None:
            self._stream = wp.Stream(device)
        return self._stream

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
        m, st = self.fluid, self.sim.state
        x = st.x if isinstance(st, HostWater) else st.x.numpy()
        return x[m.n_fluid:, : self.dim].astype(np.float64)

    def gauges(self) -> dict[str, float]:
        if self._gauges is None:
            return {}
        return self._gauges.read(self.sim.state)

    def gauges_async(self) -> PendingRead:
        """gauges() queued on the device; ``result()`` waits for the readings."""
        if self._gauges is None:
            return PendingRead(None, None, lambda a: {})
        return self._gauges.read_async(self.sim.state)
