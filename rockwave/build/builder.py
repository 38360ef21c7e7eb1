"""Scene -> models and states: everything a :class:`rockwave.Simulation` is made of, built once.

- :func:`seed_particles`: fluid particles filling the scene's regions, boundary particles of the
  tank walls and obstacles (host arrays);
- :func:`build_fluid`: :class:`rockwave.sph.fluid.FluidModel`, its state at the hydrostatic start and
  the fluid solver the scene asks for (basic or Ghost SPH);
- :func:`build_blocks`: :class:`rockwave.dda.blocks.BlockModel`, its state and solver;
- :func:`build_coupling`: the penalty coupling of water and blocks (only when both are present).

Nothing here steps or writes; bad input becomes a :class:`rockwave.scene.format.SceneError` naming the key.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from rockwave.base.maths import pad3, quat_to_matrix
from rockwave.build import sampling
from rockwave.build.options import (
    SolverOptions,
    block_options,
    boundary_lattice,
    coupling_options,
    fluid_options,
    fluid_parameters,
    ghost_options,
    gravity_norm,
    sph_params,
    support_radius_m,
    warn_unstable_step,
)
from rockwave.build.rocks import block_specs, compound_bodies, inside_blocks_message, tank_overlap_hint
from rockwave.coupling.penalty import Coupling, CouplingOptions, block_signed_distance, seeding_clearance_m
from rockwave.coupling.walls import BlockWalls
from rockwave.dda.blocks import (
    BlockModel,
    BlockOptions,
    BlockOverlapError,
    BlockSolver,
    BlockState,
    check_initial_overlap_on_device,
)
from rockwave.dda.geometry import GeometryError
from rockwave.scene.format import Scene, SceneError
from rockwave.sph.fluid import (
    Density,
    FluidModel,
    FluidOptions,
    FluidSolver,
    FluidState,
    build_fluid_model,
    hydrostatic_density,
)
from rockwave.sph.ghost import GhostFluidSolver, GhostOptions


def packed_start(x: np.ndarray, depth: np.ndarray, rho_ratio, spacing: float, up: int,
                 origin: np.ndarray | None = None) -> np.ndarray:
    """Fluid positions ``x`` (n, 3) with each vertical run of lattice particles packed at its hydrostatic density
    (fluid.packed_start): along a column of the lattice, from the run's lowest particle up, each gap of dx
    becomes dx rho0/rho at the gap's mid-depth, ``rho_ratio(depth)`` = rho/rho0 (depth: below the region's top,
    the weight above it). A run ends where the column has a gap wider than 1.5 spacings (an obstacle, another
    region). Only a run whose top is the free surface (its top particle less than a spacing deep) is packed: one
    under an obstacle or a block would open a gap of ~L g d/c0^2 under it, farther from the wall particles than the
    lattice's spacing, and the water there would hold ~10% more pressure (tests/test_block_walls.py's kinematic box
    read +11.5%); such runs keep the uniform lattice. Why pack: on the uniform lattice the continuity density
    rho(d) > rho0 is out of step with the spacing, and the momentum form's balance then needs
    p = rho0 g d (1 + 2 g d/c0^2), 1.5% too much at the floor of a 0.3 m tank at c0 = 20 m/s (docs/notes.md
    "Water at rest on the H200"). ``origin``: the lowest coordinates (3,) of the whole scene's water, from which the
    columns are counted (None: of ``x``; a slab's seeding gives the whole scene's, rockwave/build/slab.py)."""
    if len(x) < 2:
        return x
    side = [a for a in range(3) if a != up]
    ref = x[:, side].min(axis=0) if origin is None else np.asarray(origin, float)[side]
    col = np.round((x[:, side] - ref) / spacing).astype(np.int64)  # whole steps from the lowest
    order = np.lexsort((x[:, up], col[:, 1], col[:, 0]))
    z, d, c = x[order, up], depth[order], col[order]
    gap = np.diff(z)
    linked = np.all(c[1:] == c[:-1], axis=1) & (gap < 1.5 * spacing)
    shrink = np.where(linked, gap * (1.0 - 1.0 / rho_ratio(0.5 * (d[1:] + d[:-1]))), 0.0)
    run = np.concatenate([[0], np.cumsum(~linked)])  # run index of each sorted particle
    last = np.r_[np.nonzero(~linked)[0], len(z) - 1]  # each run's top particle
    free = d[last] < spacing  # runs that end at the free surface
    shrink = np.where(free[run[1:]], shrink, 0.0)
    first = np.searchsorted(run, run)  # each particle's run's first (lowest) particle
    # the shrinks summed up each run from its first particle, run by run (a sum over one column only: the same
    # float64 values whatever other columns are seeded with it, as a slab's seeding needs)
    pos = np.arange(len(z)) - first
    step = np.concatenate([[0.0], shrink])
    step[pos == 0] = 0.0  # each particle's gap below it within its run (0 at a run's first)
    runs, longest = int(run[-1]) + 1, int(pos.max()) + 1
    if runs * longest <= 4 * len(z) + 4096:  # a row per run, summed along the row (sequentially, as the loop)
        rows = np.zeros((runs, longest))
        rows[run, pos] = step
        total = np.cumsum(rows, axis=1)[run, pos]
    else:  # runs of very unequal lengths: position by position up the runs
        total = np.zeros(len(z))
        by_pos = np.argsort(pos, kind="stable")
        bounds = np.searchsorted(pos[by_pos], np.arange(longest + 1))
        for k in range(1, longest):
            i = by_pos[bounds[k]: bounds[k + 1]]
            total[i] = total[i - 1] + step[i]
    out = np.array(x, dtype=np.float64, copy=True)
    out[order, up] = z - total
    return out


def water_bounds(fluid_x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lowest, highest, first particle) of the seeded water: what the walls of the blocks are placed by."""
    return fluid_x.min(axis=0), fluid_x.max(axis=0), np.asarray(fluid_x[0], float)


def fixed_block_walls(scene: Scene, parts: "Parts", fluid_x, step: float, layers: int, clearance: float = 0.0) -> np.ndarray:
    """Wall particles inside the faces of the fixed blocks, for Adami walls (``fluid.boundary = "adami"``): a
    lattice of ``step`` over each fixed block, kept within ``layers * step`` under its surface (the kernel
    support), so that water on a fixed slope, floor or tank wall made of blocks feels the extrapolated wall
    pressure (Adami et al. 2012) as it does at the [tank] walls; the penalty force of the coupling stays as the
    guard against penetration. Only where the water can reach: within its seeded bounding box grown by its own
    largest extent (farther faces keep the penalty alone). A point inside an earlier fixed block (or within the
    clearance of one) is left out (no double walls where blocks overlap). Moving blocks get theirs from
    :func:`moving_block_walls`. ``fluid_x``: the water's positions, or its :func:`water_bounds` (a slab's seeding:
    the whole scene's).

    The lattice is the water's own continued into the block (when the walls' step is the water's spacing,
    tank.boundary_spacing_ratio 1): that of the first region whose lattice, grown by the kernel support, meets the
    block's bounding box (sampling.region_lattice: its fitted steps; through the water's first particle for the
    first region, as before), and every lattice point closer to the block than ``clearance`` (where the seeding
    removed the water, :func:`seeding_clearance`) is a wall particle too: water and wall share one lattice split at
    one distance, with no hole and no overlap between them on a face at any angle (issue 41: a tilted face cuts the
    lattice at any offset; with the wall points inside the face only, a band up to the clearance wide was left
    empty and the water fell into it). Otherwise: the lattice of ``step`` through the first particle, points inside
    the blocks only."""
    dim = scene.dim
    if parts.blocks is None or len(fluid_x) == 0:
        return np.zeros((0, 3))
    lo_f, hi_f, first = fluid_x if isinstance(fluid_x, tuple) else water_bounds(fluid_x)
    specs = [s for s in parts.blocks.specs if s.kind == "fixed" and not s.tank]  # the [tank] has its own particles
    if not specs:
        return np.zeros((0, 3))
    own = abs(step - scene.fluid.spacing_m) <= 1e-9 * step
    lattices = [sampling.region_lattice(r, scene.fluid.spacing_m, dim) for r in scene.fluid.regions] if own else []
    if not own:
        clearance = 0.0
    H = support_radius_m(scene)
    grow = float(np.max(hi_f[:dim] - lo_f[:dim]))
    reach_lo, reach_hi = lo_f - grow, hi_f + grow
    depth = layers * step
    anchor, steps = np.asarray(first, float)[:dim], np.full(dim, float(step))
    planes, out = [], []
    for spec in specs:
        R = quat_to_matrix(spec.orientation)
        n = np.asarray(spec.geometry.face_normals, float) @ R.T
        d = np.asarray(spec.geometry.face_offsets, float) + n @ np.asarray(spec.position, float)
        if dim == 2:  # the extrusion's caps are not walls in 2D
            side = np.abs(n[:, 2]) < 0.5
            n, d = n[side], d[side]
        verts = np.asarray(spec.geometry.vertices, float) @ R.T + np.asarray(spec.position, float)
        lo = np.maximum(verts.min(axis=0) - clearance, reach_lo)[:dim]
        hi = np.minimum(verts.max(axis=0) + clearance, reach_hi)[:dim]
        if np.any(hi <= lo):
            planes.append((n, d))
            continue
        if lattices:  # the lattice of the first region the block meets
            k = next((i for i, (a, _, b) in enumerate(lattices)
                      if np.all(a[:dim] - H <= hi) and np.all(b[:dim] + H >= lo)), 0)
            st = np.asarray(lattices[k][1], float)[:dim]
            anchor = np.asarray(first if k == 0 else lattices[k][0], float)[:dim]
            steps = np.where(np.abs(st - step) <= 1e-9 * step, step, st)  # a step that fits exactly: the step itself
        # the water's own lattice continued into the block: water filling a box up to a face sits step/2 from it,
        # and so do the first wall layer's particles on the other side
        k0 = np.floor((lo - anchor) / steps)
        k1 = np.ceil((hi - anchor) / steps)
        axes = [anchor[i] + np.arange(k0[i], k1[i] + 1) * steps[i] for i in range(dim)]
        g = np.meshgrid(*axes, indexing="ij")
        pts = np.zeros((g[0].size, 3))
        for i in range(dim):
            pts[:, i] = g[i].ravel()
        sd = (pts @ n.T - d).max(axis=1)
        pts = pts[(sd < clearance) & (sd > -depth)]
        for n2, d2 in planes:  # inside an earlier fixed block (or within the clearance of it): already wall
            if len(pts) and len(n2):
                pts = pts[(pts @ n2.T - d2).max(axis=1) >= clearance]
        planes.append((n, d))
        out.append(pts)
    return np.concatenate(out) if out else np.zeros((0, 3))


def _body_shell(verts: np.ndarray, n: np.ndarray, d: np.ndarray, step: float, depth: float, dim: int) -> np.ndarray:
    """Body-frame points inside the convex block {n . r <= d} within ``depth`` of its surface, on a lattice
    fitted to the block's body-frame bounding box as sampling.box_shell fits obstacles: along each axis
    n = round(L / step) cells of L / n, points at their centres, so that a box's faces lie half a (fitted) step
    from the nearest layer, as the water's lattice particles lie from the faces of the box they fill: the wall
    pressure then acts on the block's own faces (a lattice off by a fraction of a step moves the effective face
    by as much: the 3D floating box read its full weight in buoyancy 0.4 spacing above equilibrium)."""
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    axes = []
    for i in range(dim):
        k = max(int(round((hi[i] - lo[i]) / step)), 1)
        h = (hi[i] - lo[i]) / k
        axes.append(lo[i] + (np.arange(k) + 0.5) * h)
    g = np.meshgrid(*axes, indexing="ij")
    pts = np.zeros((g[0].size, 3))
    for i in range(dim):
        pts[:, i] = g[i].ravel()
    sd = (pts @ n.T - d).max(axis=1)
    return pts[(sd < 0.0) & (sd > -depth)]


def moving_block_walls(scene: Scene, parts: "Parts", fluid_x: np.ndarray, step: float, layers: int):
    """Wall particles of the moving blocks (rigid, deformable, kinematic; the parts of a compound block), for
    Adami walls on them (rockwave/coupling/walls.py BlockWalls): a lattice of about ``step`` fitted to each block in
    its body frame (:func:`_body_shell`), inside all of its faces (a moving block may turn any face to the
    water), ``layers * step`` deep, placed at the blocks' poses at t = 0 (2D: prisms turning about z, the lattice
    in the x-y plane at z = 0, the caps left out). Only blocks that start within reach of the water
    (its seeded bounding box grown by its own largest extent, as for fixed blocks) get them: a block farther
    away (a rock falling from high above, most of a jointed slope) keeps the penalty coupling alone, which
    bounds the cost for scenes of many blocks; ``coupling.block_walls = false`` turns them off entirely.
    Returns (world positions (n, 3), block index (n,))."""
    dim = scene.dim
    empty = (np.zeros((0, 3)), np.zeros(0, np.int64))
    if parts.blocks is None or len(fluid_x) == 0:
        return empty

    lo_f, hi_f = fluid_x.min(axis=0), fluid_x.max(axis=0)
    grow = float(np.max(hi_f[:dim] - lo_f[:dim]))
    reach_lo, reach_hi = lo_f - grow, hi_f + grow
    depth = layers * step
    xs = parts.block_state.x.numpy().astype(np.float64)
    qs = parts.block_state.q.numpy().astype(np.float64)
    pts_all, idx = [], []
    for b, spec in enumerate(parts.blocks.specs):
        if spec.kind == "fixed":
            continue
        R = quat_to_matrix(qs[b])
        bv = np.asarray(spec.geometry.vertices, float)  # body frame
        verts = bv @ R.T + xs[b]
        if np.any(verts.max(axis=0)[:dim] < reach_lo[:dim]) or np.any(verts.min(axis=0)[:dim] > reach_hi[:dim]):
            continue
        n = np.asarray(spec.geometry.face_normals, float)
        d = np.asarray(spec.geometry.face_offsets, float)
        if dim == 2:  # the extrusion's caps are not walls in 2D
            side = np.abs(n[:, 2]) < 0.5
            n, d = n[side], d[side]
        pts = _body_shell(bv, n, d, step, depth, dim) @ R.T + xs[b]
        if dim == 2:
            pts[:, 2] = 0.0
        pts_all.append(pts)
        idx.append(np.full(len(pts), b, np.int64))
    if not pts_all:
        return empty
    return np.concatenate(pts_all), np.concatenate(idx)


def block_walls_on(scene: Scene, options: SolverOptions | None = None) -> bool:
    """Do the moving blocks get Adami wall particles? coupling.block_walls (or CouplingOptions.block_walls);
    off unless asked for (the scene's validation refuses it without Adami walls or with Ghost SPH)."""
    if scene.fluid is None:
        return False
    return bool(solver_coupling_options(scene, options).block_walls)


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
        vel = pad3(r.velocity_m_s) if r.velocity_m_s is not None else [0.0, 0.0, 0.0]
        vs.append(np.tile(np.asarray(vel, float), (len(p), 1)))
    x = np.concatenate(xs) if xs else np.zeros((0, 3))
    v = np.concatenate(vs) if vs else np.zeros((0, 3))
    depth = np.concatenate(ds) if ds else np.zeros(0)
    keep = fluid_keep(scene, device, x)
    return x[keep], v[keep], depth[keep], boundary_particles(scene, device)


def boundary_particles(scene: Scene, device: str) -> np.ndarray:
    """Boundary particles of the tank walls and obstacles (n, 3) (z = 0 in 2D)."""
    t, up = scene.tank, scene.dim - 1
    bstep, layers = boundary_lattice(scene)
    parts = []
    try:
        if t is not None and t.box_min_m is not None:
            parts.append(sampling.box_shell(t.box_min_m, t.box_max_m, bstep, layers, True, t.open_top, up))
        elif t is not None:
            parts.append(sampling.mesh_shell(t.mesh, t.mesh_scale, t.mesh_offset_m, bstep, layers, True, device))
    except sampling.MeshInputError as e:
        raise SceneError(scene.path, [("tank.mesh", str(e))]) from None
    for i, ob in enumerate(scene.obstacles):
        try:
            if ob.box_min_m is not None:
                parts.append(sampling.box_shell(ob.box_min_m, ob.box_max_m, bstep, layers, False, False, up))
            else:
                parts.append(sampling.mesh_shell(ob.mesh, ob.mesh_scale, ob.mesh_offset_m, bstep, layers, False, device))
        except sampling.MeshInputError as e:
            raise SceneError(scene.path, [(f"obstacles[{i}].mesh", str(e))]) from None
    return np.concatenate(parts) if parts else np.zeros((0, 3))


def fluid_keep(scene: Scene, device: str, x: np.ndarray) -> np.ndarray:
    """Mask of the lattice points ``x`` (n, 3) that stay water: inside the tank, outside every obstacle (a pointwise
    test: the whole scene's seeding and a slab's (rockwave/build/slab.py) keep the same points)."""
    t, dim = scene.tank, scene.dim
    try:
        if t is None:  # walls from fixed blocks (rockwave/coupling/penalty.py)
            keep = np.ones(len(x), bool)
        elif t.box_min_m is not None:
            keep = np.all((x[:, :dim] > np.asarray(t.box_min_m)) & (x[:, :dim] < np.asarray(t.box_max_m)), axis=1)
        else:
            tm = sampling.load_trimesh(t.mesh, t.mesh_scale, t.mesh_offset_m)
            keep = sampling.mesh_signed_distance(tm, x, device) < 0
    except sampling.MeshInputError as e:
        raise SceneError(scene.path, [("tank.mesh", str(e))]) from None
    for i, ob in enumerate(scene.obstacles):
        try:
            keep &= ~sampling.inside_obstacle(x, ob, dim, device)
        except sampling.MeshInputError as e:
            raise SceneError(scene.path, [(f"obstacles[{i}].mesh", str(e))]) from None
    return keep


@dataclass
class Parts:
    """What a scene is made of on the device (None where the scene has none of it)."""

    fluid: FluidModel | None = None
    """The fluid's static data."""

    state: FluidState | None = None
    """The fluid's state at the start (hydrostatic density, the wall pressures of Adami walls)."""

    fluid_solver: FluidSolver | None = None
    """FluidSolver, or GhostFluidSolver with fluid.method = "ghost"."""

    blocks: BlockModel | None = None
    """The blocks' static data."""

    block_state: BlockState | None = None
    """The blocks' state at the start."""

    block_solver: BlockSolver | None = None
    """The DDA block solver."""

    coupling: Coupling | None = None
    """The penalty coupling of water and blocks (only when the scene has both)."""

    removed_inside_blocks: int = 0
    """Fluid particles dropped at seeding because they lay inside a block (or within half the contact distance
    of its faces)."""

    moving_wall_blocks: np.ndarray | None = None
    """int64 (n_moving_walls,): block index of each wall particle of a moving block (BlockWalls)."""


def build(scene: Scene, device: str, options: SolverOptions | None = None) -> Parts:
    """All parts of ``scene`` on ``device`` (``options``: rockwave.sim.simulation.SimulationOptions, whose solver
    options given in Python win over the scene's as rockwave/build/options.py says)."""
    parts = Parts()
    with wp.ScopedDevice(device):
        if scene.blocks or scene.rock_mass:
            build_blocks(scene, device, parts, options)
        if scene.fluid is not None:
            build_fluid(scene, device, parts, options)
        if parts.blocks is not None and parts.fluid is not None and parts.fluid.n_fluid:
            build_coupling(scene, parts, options)
    return parts


@dataclass
class FluidSeeds:
    """The host arrays a fluid model is made from (:func:`seed_fluid`): positions (n, 3) [m] in the scene's frame."""

    fluid: np.ndarray
    """Fluid positions after the removal inside blocks and the packed start."""

    velocities: np.ndarray
    """Fluid velocities [m/s]."""

    depth: np.ndarray
    """Depth of each fluid particle below its region's top [m] (the hydrostatic start)."""

    boundary: np.ndarray
    """Static boundary particles: the tank's and obstacles' layers, the fixed blocks' Adami walls."""

    moving: np.ndarray | None = None
    """Wall particles of the moving blocks (None: none asked for)."""

    moving_blocks: np.ndarray | None = None
    """int64 block index of each moving wall particle."""


def seed_fluid(scene: Scene, device: str, parts: Parts, options: SolverOptions | None = None) -> FluidSeeds:
    """Every particle of the scene's water and walls on the host, as :func:`build_fluid` places them (``parts``: the
    blocks already built; its ``removed_inside_blocks`` is set). rockwave/sim/batch.py seeds each scenario of a batch
    with it, in the scenario's own frame, before moving it to its tile."""
    xf, vf, depth, xb = seed_particles(scene, device)
    clearance = 0.0
    if parts.blocks is not None:
        clearance = seeding_clearance(scene, options)
        xf, vf, depth = remove_inside_blocks(scene, parts, xf, vf, depth, options, clearance)
    if scene.fluid.packed_start and len(xf):

        rho0 = scene.fluid.rest_density_kg_m3
        params = sph_params(scene, len(xf))
        g = gravity_norm(scene)
        xf = packed_start(xf, depth, lambda d: hydrostatic_density(params, g * d) / rho0, scene.fluid.spacing_m, scene.dim - 1)
    bstep, layers = boundary_lattice(scene)
    if scene.fluid.boundary == "adami" and parts.blocks is not None:
        xw = fixed_block_walls(scene, parts, xf, bstep, layers, clearance)
        if len(xw):
            xb = np.concatenate([xb, xw]) if len(xb) else xw
    xm = mb = None
    if parts.blocks is not None and block_walls_on(scene, options):
        xm, mb = moving_block_walls(scene, parts, xf, bstep, layers)
        if len(xm):
            print(f"moving blocks: {len(xm)} Adami wall particles on {len(np.unique(mb))} blocks", flush=True)
    return FluidSeeds(xf, vf, depth, xb, xm, mb)


def build_fluid(scene: Scene, device: str, parts: Parts, options: SolverOptions | None = None,
                seeds: FluidSeeds | None = None, list_capacity: int | None = None) -> None:
    """The fluid model, its start state and solver (``seeds``: given, e.g. a batch's tiles; None: :func:`seed_fluid`;
    ``list_capacity``: the solver's neighbour slots per particle, None: FluidSolver's; a distributed rank's start,
    whose steps run on another solver, takes 1)."""
    if seeds is None:
        seeds = seed_fluid(scene, device, parts, options)
    parts.moving_wall_blocks = seeds.moving_blocks
    xf, vf, depth, xb, xm = seeds.fluid, seeds.velocities, seeds.depth, seeds.boundary, seeds.moving
    bstep, layers = boundary_lattice(scene)
    fluid = build_fluid_model(xf, vf, xb, fluid_parameters(scene.fluid), scene.dim, scene.gravity.acceleration_m_s2, device,
                              bstep, layers, moving_wall_positions=xm)
    fopts = fluid_options(scene, _given(options, "fluid", FluidOptions))  # the Courant number from the scene
    if scene.fluid.method == "ghost":

        warn_unstable_step(scene)
        gopts = ghost_options(scene, _given(options, "ghost", GhostOptions))  # the [fluid.ghost] settings from the scene
        solver = GhostFluidSolver(fluid, options=fopts, ghost_options=gopts)
    else:
        solver = FluidSolver(fluid, options=fopts, list_capacity=list_capacity)
    state = fluid.state()
    if fluid.n_fluid:
        if fluid.density is Density.SUMMATION:
            solver.compute_density(state)
        else:
            g = gravity_norm(scene)
            solver.set_density(state, hydrostatic_density(fluid.params, g * depth))
        if scene.fluid.boundary == "adami" and fluid.n_boundary:  # the wall pressures of the initial state (gauges)
            solver.build_cells(state)
            solver.wall_pressure(state)
    parts.fluid, parts.state, parts.fluid_solver = fluid, state, solver


def build_blocks(scene: Scene, device: str, parts: Parts, options: SolverOptions | None = None,
                 specs: list | None = None, check_overlap: bool = True) -> None:
    """The block model, its state and solver (``specs``: given, e.g. a batch's tiles, each checked for overlaps
    alone: ``check_overlap`` False; None: the scene's)."""
    if specs is None:
        specs = block_specs(scene)

    for name, body in compound_bodies(specs):  # what each non-convex mesh became
        print(f"block '{name}': non-convex mesh -> {body.summary()}", flush=True)
    host_check = check_overlap and len(specs) <= 2000  # exact host test for small sets; device FCP for large ones
    try:
        # 2D: extruded prisms moving in the x-y plane (planar: the block step keeps them there)
        blocks = BlockModel(specs, device=device, gravity=pad3(scene.gravity.acceleration_m_s2), check_overlap=host_check,
                            planar=scene.dim == 2)
        solver = BlockSolver(blocks, options=_given(options, "blocks", BlockOptions) or block_options(scene))
        state = blocks.state()
        if check_overlap and not host_check:
            check_initial_overlap_on_device(solver, state)
    except (BlockOverlapError, GeometryError, ValueError) as e:
        raise SceneError(scene.path, [("blocks", tank_overlap_hint(str(e)))]) from None
    if solver.options.start == "settled":  # simulation.start: the blocks at rest start in equilibrium
        solver.settle(state)
    parts.blocks, parts.block_state, parts.block_solver = blocks, state, solver


def block_model(scene: Scene, device: str, parts: Parts, options: SolverOptions | None = None,
                specs: list | None = None) -> None:
    """The blocks at their start for seeding the water around them (rockwave/sim/batch.py seeds each scenario of a
    batch so): the model and its state, checked for overlaps; the solver only when the blocks start settled
    (simulation.start = 'settled': the seeding sees them after the settling, as build_blocks leaves them)."""
    if specs is None:
        specs = block_specs(scene)
    opts = _given(options, "blocks", BlockOptions) or block_options(scene)
    if opts.start == "settled" or len(specs) > 2000:
        build_blocks(scene, device, parts, options, specs=specs)
        return
    try:
        blocks = BlockModel(specs, device=device, gravity=pad3(scene.gravity.acceleration_m_s2), check_overlap=True,
                            planar=scene.dim == 2)
    except (BlockOverlapError, GeometryError, ValueError) as e:
        raise SceneError(scene.path, [("blocks", tank_overlap_hint(str(e)))]) from None
    parts.blocks, parts.block_state = blocks, blocks.state()


def seeding_clearance(scene: Scene, options: SolverOptions | None = None) -> float:
    """How close to a block's face water is seeded [m] (rockwave/coupling/penalty.py seeding_clearance_m: the contact
    distance on the seeding lattice, where the penalty spring is at rest), from the regions' lattices alone (a slab's
    seeding, rockwave/build/slab.py, finds the same)."""
    ratio = solver_coupling_options(scene, options).contact_distance_ratio
    steps, scale = sampling.lattice_steps_and_scale(scene.fluid.regions, scene.fluid.spacing_m, scene.dim)
    return seeding_clearance_m(ratio, scene.fluid.spacing_m, steps, scale)


def remove_inside_blocks(scene: Scene, parts: Parts, xf, vf, depth, options: SolverOptions | None = None,
                         clearance: float | None = None):
    """Drop fluid particles inside a block, or closer to its faces than ``clearance`` (None: :func:`seeding_clearance`,
    the contact distance); the count goes to ``parts.removed_inside_blocks`` and run.json."""
    if clearance is None:
        clearance = seeding_clearance(scene, options)
    dist, _ = block_signed_distance(parts.blocks, parts.block_state, xf)
    keep = dist >= clearance
    parts.removed_inside_blocks = n = int((~keep).sum())
    if n:
        warnings.warn(inside_blocks_message(n, len(keep)), stacklevel=2)
    return xf[keep], vf[keep], depth[keep]


def build_coupling(scene: Scene, parts: Parts, options: SolverOptions | None = None) -> None:
    parts.coupling = c = Coupling(parts.fluid, parts.blocks, scene.dim, options=solver_coupling_options(scene, options))
    f = parts.fluid
    if f.n_moving_walls:

        xm = np.asarray(f.initial_positions, float)[f.n_fluid + f.n_static_boundary: f.n_total]
        c.walls = BlockWalls(parts.fluid_solver, parts.blocks, parts.block_state, xm, parts.moving_wall_blocks,
                             c.depth_scale, scene.dim)


def solver_coupling_options(scene: Scene, options: SolverOptions | None = None) -> CouplingOptions:
    """The coupling's options: passed in Python (SimulationOptions.coupling), else the scene's ``[coupling]`` section."""

    return _given(options, "coupling", CouplingOptions) or coupling_options(scene)


def _given(options: SolverOptions | None, name: str, kind: type):
    """The ``name`` options given in Python (SimulationOptions.fluid, .ghost, .blocks, .coupling), or None."""
    o = getattr(options, name, None)
    if o is not None and not isinstance(o, kind):
        raise TypeError(f"SimulationOptions.{name}: expected {kind.__name__} or None, got {type(o).__name__}")
    return o
