"""Scene ``[[blocks]]`` entries -> :class:`rockwave.dda.blocks.BlockSpec` list (host side).

A non-convex mesh becomes one rigid compound block (rockwave/dda/geometry.py decompose): its convex parts
are consecutive BlockSpecs marked with :class:`rockwave.dda.blocks.CompoundPart`, all at the body's pose.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from rockwave.base.maths import euler_xyz_deg_to_quat, quat_to_matrix
from rockwave.build.rockmass import rock_mass_specs
from rockwave.build.sampling import MeshInputError, load_trimesh
from rockwave.dda import geometry
from rockwave.dda.blocks import BlockSpec, CompoundPart, ContactMaterial, KinematicMotion
from rockwave.scene.format import Scene, SceneError


def decomposition_of(scene: Scene, b) -> geometry.Decomposition:
    """The entry's decomposition keys as a geometry.Decomposition (cache_dir relative to the scene file)."""
    d = b.decomposition
    cache = None
    if d.cache_dir:
        base = Path(scene.path).parent if scene.path not in ("<scene>", "") else Path.cwd()
        cache = str((base / d.cache_dir).resolve())
    return geometry.Decomposition(max_parts=int(d.max_parts), concavity=float(d.concavity), cache_dir=cache)


def compound_bodies(specs: list[BlockSpec]) -> list[tuple[str, geometry.CompoundBlock]]:
    """(body name, CompoundBlock) of each compound block in specs (its first part's name minus '.part0')."""
    return [(s.name.removesuffix(".part0"), s.compound.body) for s in specs if s.compound is not None and s.compound.part == 0]


def block_specs(scene: Scene) -> list[BlockSpec]:
    """Expand the scene's block entries (arrays, multi-part meshes) into BlockSpecs."""
    specs: list[BlockSpec] = []
    for i, b in enumerate(scene.blocks):
        path = f"blocks[{i}]"
        try:
            if b.shape == "box":
                parts = [geometry.box(b.size_m, name=b.name)]
            elif b.shape == "prism":
                parts = [geometry.prism(b.vertices_m, name=b.name)]
            else:
                loaded = geometry.load_mesh(b.mesh, decomposition=decomposition_of(scene, b), scale=b.mesh_scale)
                parts = loaded if isinstance(loaded, list) else [loaded]
                if b.mesh_scale != 1.0:
                    scaled = []
                    for part in parts:
                        if isinstance(part, geometry.CompoundBlock):  # decomposed at scale already
                            scaled.append(part)
                            continue
                        tm = part.to_trimesh()
                        tm.apply_translation(part.origin_offset)
                        tm.apply_scale(b.mesh_scale)
                        scaled.append(geometry.from_trimesh(tm, name=part.name))
                    parts = scaled
        except (geometry.GeometryError, ValueError) as e:
            key = f"{path}.mesh" if b.shape == "mesh" else f"{path}.{'vertices_m' if b.shape == 'prism' else 'size_m'}"
            if getattr(e, "key", ""):
                key = f"{path}.decomposition.{e.key}"
            raise SceneError(scene.path, [(key, str(e))]) from None
        if b.kind == "deformable" and any(isinstance(p, geometry.CompoundBlock) for p in parts):
            raise SceneError(scene.path, [(f"{path}.kind", "a non-convex mesh becomes a rigid compound block of convex "
                                           "parts; it cannot be 'deformable' (use 'rigid', 'fixed' or 'kinematic')")])
        mat = b.material
        material = ContactMaterial(
            friction_angle_deg=mat.friction_angle_deg, cohesion_pa=mat.cohesion_pa, tensile_strength_pa=mat.tensile_strength_pa,
            normal_stiffness=mat.normal_stiffness_n_m, shear_stiffness=mat.shear_stiffness_n_m,
            restitution=mat.restitution, damping_ratio=mat.damping_ratio)
        motion = None
        if b.kind == "kinematic":
            mo = b.motion
            if mo.type == "sine":
                motion = KinematicMotion.sine(mo.amplitude_m, mo.frequency_hz, mo.phase_rad)
            else:
                motion = KinematicMotion.table(mo.times_s, mo.displacements_m)
        q = euler_xyz_deg_to_quat(b.orientation_deg)
        nx, ny, nz = (int(c) for c in b.array.count)
        rot = quat_to_matrix(q)  # the array's axes turn with the block
        offsets = [rot @ (np.array([ix, iy, iz]) * np.asarray(b.array.spacing_m))
                   for iz in range(nz) for iy in range(ny) for ix in range(nx)]
        many = len(offsets) * len(parts) > 1
        k = 0
        for part in parts:
            base = np.asarray(b.position_m) if b.position_m is not None else np.asarray(part.origin_offset)
            if b.position_m is not None and len(parts) > 1:
                base = base + np.asarray(part.origin_offset)  # keep the parts' relative placement
            for off in offsets:
                name = f"{b.name}_{k}" if many else b.name
                common = dict(position=tuple(base + off), orientation=q, density=b.density_kg_m3,
                              velocity=tuple(b.velocity_m_s), angular_velocity=tuple(b.angular_velocity_rad_s), kind=b.kind,
                              youngs_modulus=b.youngs_modulus_pa, poisson_ratio=b.poisson_ratio, motion=motion,
                              material=material, strain_damping_ratio=b.strain_damping_ratio)
                if isinstance(part, geometry.CompoundBlock):  # one rigid body: its parts, consecutive
                    for j, g in enumerate(part.parts):
                        specs.append(BlockSpec(geometry=g, name=f"{name}.part{j}", compound=CompoundPart(part, j), **common))
                else:
                    specs.append(BlockSpec(geometry=part, name=name, **common))
                k += 1
    from collections import Counter

    specs += rock_mass_specs(scene)  # [[rock_mass]]: blocks cut by joint sets
    specs += tank_specs(scene, specs)  # the [tank] and box obstacles, solid to the blocks (after the scene's own)
    dup = {n for n, c in Counter(s.name for s in specs).items() if c > 1}
    if dup:
        # unique names for USD prims and the CSV
        seen: dict[str, int] = {}
        for s in specs:
            if s.name in dup:
                seen[s.name] = seen.get(s.name, -1) + 1
                s.name = f"{s.name}_{seen[s.name]}"
    return specs


def _world_vertices(spec: BlockSpec) -> np.ndarray:
    return np.asarray(spec.geometry.vertices, float) @ quat_to_matrix(np.asarray(spec.orientation, float)).T + np.asarray(
        spec.position, float)


def _fixed_box(lo, hi, name: str) -> BlockSpec:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return BlockSpec(geometry=geometry.box(hi - lo, name=name), position=tuple(0.5 * (lo + hi)), kind="fixed", name=name,
                     material=ContactMaterial(), tank=True)


def tank_specs(scene: Scene, specs: list[BlockSpec]) -> list[BlockSpec]:
    """The box ``[tank]``'s floor, walls (and lid when its top is closed) and each box obstacle as fixed blocks for
    contact with the scene's blocks (``tank.block_contact``, default on; docs/coupling.md "Tanks and blocks"):
    the boundary particles are walls for the water only, and a block would fall through them.

    Built only when ``specs`` has a rigid or deformable block (fixed and kinematic blocks never touch fixed
    ones). Boxes outside the tank's inner box, ``T`` = the largest moving block's bounding diameter thick
    (nothing tunnels through that), the floor under the walls, the walls between floor and top (their
    corners not overlapping); the default material of a fixed block (friction 30 deg, restitution 0.5,
    k_n = 0.1 E L: a pair uses the softer k_n, so the block's own). 2D: prisms whose z-extent covers every
    block's, grown by half of it each side. Marked ``BlockSpec.tank``: the coupling gives them no penalty
    faces and they get no fixed-block wall particles (the water has the tank's boundary particles there). A
    mesh tank and a non-convex mesh obstacle are not built (a warning: build them of fixed blocks); a convex mesh obstacle
    is its polyhedron."""
    t = scene.tank
    moving = [s for s in specs if s.kind in ("rigid", "deformable")]
    if not moving or (t is None and not scene.obstacles):
        return []
    if t is not None and t.get("block_contact") is False:
        return []
    dim = scene.dim
    verts = np.concatenate([_world_vertices(s) for s in specs])
    T = max(2.0 * float(s.geometry.bounding_radius) for s in moving)
    if dim == 2:
        z0, z1 = float(verts[:, 2].min()), float(verts[:, 2].max())
        dz = max(z1 - z0, 1e-3)
        zr = (z0 - 0.5 * dz, z1 + 0.5 * dz)

    def box(lo, hi, name):  # lo, hi: scene coordinates (dim components)
        lo, hi = list(lo), list(hi)
        if dim == 2:
            lo, hi = lo + [zr[0]], hi + [zr[1]]
        return _fixed_box(lo, hi, name)

    out = []
    if t is not None and t.get("box_min_m") is not None:
        lo, hi = np.asarray(t.box_min_m, float), np.asarray(t.box_max_m, float)
        up = dim - 1
        side = [a for a in range(dim) if a != up]
        g_lo, g_hi = lo - T, hi + T  # grown by the thickness
        f_lo, f_hi = g_lo.copy(), g_hi.copy()
        f_hi[up] = lo[up]
        out.append(box(f_lo, f_hi, "tank.floor"))
        if not t.open_top:
            c_lo, c_hi = g_lo.copy(), g_hi.copy()
            c_lo[up] = hi[up]
            out.append(box(c_lo, c_hi, "tank.lid"))
        for k, a in enumerate(side):  # walls normal to axis a; the first side axis' walls cover the corners
            for end, name in ((0, "min"), (1, "max")):
                w_lo, w_hi = lo.copy(), hi.copy()
                for b in side:
                    if b != a:
                        w_lo[b], w_hi[b] = (g_lo[b], g_hi[b]) if side.index(b) > k else (lo[b], hi[b])
                if end == 0:
                    w_lo[a], w_hi[a] = g_lo[a], lo[a]
                else:
                    w_lo[a], w_hi[a] = hi[a], g_hi[a]
                out.append(box(w_lo, w_hi, f"tank.wall_{'xyz'[a]}{name}"))
    elif t is not None:
        warnings.warn("the mesh [tank] is not solid to blocks (only a box tank is): a block reaching its walls falls "
                      "through them; build the walls a block can reach of fixed [[blocks]]", stacklevel=2)
    skipped = []
    for i, ob in enumerate(scene.obstacles):
        if ob.get("box_min_m") is not None:
            out.append(box(ob.box_min_m, ob.box_max_m, f"obstacle.{i}"))
            continue
        mesh = _convex_obstacle(ob, f"obstacle.{i}")  # a convex mesh: its polyhedron, where it lies
        if mesh is None:
            skipped.append(f"obstacles[{i}]")
        else:
            out.append(BlockSpec(geometry=mesh, position=tuple(mesh.origin_offset), kind="fixed", name=f"obstacle.{i}",
                                 material=ContactMaterial(), tank=True))
    if skipped:
        warnings.warn(f"{', '.join(skipped)}: a non-convex mesh obstacle is not solid to blocks (box and convex mesh "
                      f"obstacles are): a block reaching it passes through; build it of fixed [[blocks]] (shape = "
                      f"'mesh' with a decomposition)", stacklevel=2)
    return out


def _convex_obstacle(ob, name: str):
    """A convex closed mesh obstacle as a ConvexPolyhedron (centred, origin_offset = its centroid in the scene);
    None when the mesh is not convex (geometry.from_trimesh's test against its hull, CONVEXITY_TOL)."""
    try:
        return geometry.from_trimesh(load_trimesh(ob.mesh, ob.mesh_scale, ob.mesh_offset_m), name)
    except (geometry.GeometryError, MeshInputError):  # non-convex; a bad mesh is the boundary builder's SceneError
        return None


def inside_blocks_message(n: int, total: int, where: str = "fluid.regions") -> str:
    """The one-line warning of water seeded inside blocks (the run and ``validate``)."""
    return (f"{where}: {n:,} of {total:,} water particles ({100.0 * n / max(total, 1):.3g}%) lie inside blocks or within "
            f"the contact distance of their faces and are not seeded (removed_inside_blocks in run.json); shrink "
            f"the region or move the blocks if that water was meant to be there")


def tank_overlap_hint(message: str) -> str:
    """An initial-overlap message that names a block of the tank (tank_specs) says what that block is."""
    if "'tank." in message or "'obstacle." in message:
        message += (" (blocks named tank.* and obstacle.* are the [tank]'s walls and the box obstacles, solid to blocks: "
                    "place the blocks inside the tank, or set tank.block_contact = false)")
    return message


def scanned_rock_mesh(radius_m: float = 0.5, subdivisions: int = 3, roughness: float = 0.15, bumps: int = 24,
                      notch_depth: float = 0.7, notch_width_deg: float = 30.0, seed: int = 0):
    """A scanned-rock-like closed, non-convex surface (trimesh.Trimesh, centred near the origin): an
    icosphere of radius_m whose vertices move along their directions d,

        r(d) = radius_m (1 + roughness sum_k a_k exp(-(1 - d.c_k) / s_k)) (1 - notch_depth v(d)),

    with ``bumps`` random Gaussian bumps on the sphere (centres c_k, widths s_k, signed amplitudes a_k;
    lumps and hollows) plus a finer octave of 4 x bumps at a quarter of the amplitude and width, and a notch v(d) = sqrt(max(0, 1 - |angle from the notch plane| / width)
    max(0, d.axis)) on one side of the rock (a deep cleft: the surface there is far from its convex hull).  A radial
    displacement of a sphere keeps the surface closed and free of self-intersections.  Seeded: the
    same seed gives the same mesh."""
    import trimesh

    rng = np.random.default_rng(seed)
    m = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=1.0)
    d = np.asarray(m.vertices, float)
    d /= np.linalg.norm(d, axis=1)[:, None]
    c = rng.normal(size=(bumps, 3))
    c /= np.linalg.norm(c, axis=1)[:, None]
    width = rng.uniform(0.05, 0.3, bumps)
    amp = rng.uniform(-1.0, 1.0, bumps)
    r = 1.0 + roughness * (amp[None, :] * np.exp(-(1.0 - d @ c.T) / width[None, :])).sum(axis=1)
    # a finer octave (knobs and pits a few vertices wide): 4 x the bumps, 1/4 the amplitude and width
    cf = rng.normal(size=(4 * bumps, 3))
    cf /= np.linalg.norm(cf, axis=1)[:, None]
    wf = rng.uniform(0.0125, 0.075, 4 * bumps)
    af = rng.uniform(-0.25, 0.25, 4 * bumps)
    r = r + roughness * (af[None, :] * np.exp(-(1.0 - d @ cf.T) / wf[None, :])).sum(axis=1)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)  # the notch opens towards this direction
    plane_n = np.cross(axis, rng.normal(size=3))
    plane_n /= np.linalg.norm(plane_n)  # the notch plane holds the axis
    ang = np.degrees(np.arcsin(np.clip(np.abs(d @ plane_n), 0.0, 1.0)))
    notch = np.sqrt(np.clip(1.0 - ang / notch_width_deg, 0.0, None) * np.clip(d @ axis, 0.0, None))
    r = r * (1.0 - notch_depth * notch)
    if np.any(r <= 0.05):
        raise ValueError("scanned_rock_mesh: roughness and notch_depth leave no rock (radius <= 0.05 of radius_m)")
    out = trimesh.Trimesh(d * (radius_m * r)[:, None], m.faces, process=False)
    out.apply_translation(-out.center_mass)
    return out
