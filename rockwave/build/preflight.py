"""Checks made before anything is allocated: meshes and memory.

- :func:`check_meshes`: every mesh a scene names (fluid regions, tank, obstacles, blocks) is read
  once and checked: unreadable, not watertight, zero volume -> error; inverted normals -> fixed
  with a warning; a largest extent above ``MM_SUSPECT_EXTENT_M`` with no explicit ``mesh_scale``
  -> error ("looks like millimetres": set ``mesh_scale = 0.001``, or ``mesh_scale = 1.0`` to keep
  metres). Block meshes must also be convex (checked by :mod:`rockwave.dda.geometry`).
- :func:`estimate`: particle counts from the regions' volumes and the spacing (box lattices are
  counted exactly, meshes by volume / spacing^d, walls by their shell), blocks from the entries,
  and the bytes they need on the device and on the host.
- :func:`check_memory`: refuses a scene whose estimate exceeds ``MEMORY_FRACTION`` of what the
  device (and, for a GPU, the host) has free, naming how much it needs.
- :func:`output_bytes`: rough size of a run's outputs, compared with the free disk space.
"""

from __future__ import annotations

import math
import os
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from rockwave.build import sampling
from rockwave.build.options import boundary_lattice, coupling_options, fluid_parameters, gravity_norm, support_radius_m
from rockwave.build.rockmass import estimate_block_count
from rockwave.build.rocks import block_specs, decomposition_of, inside_blocks_message, tank_overlap_hint
from rockwave.coupling.penalty import block_signed_distance, seeding_clearance_m
from rockwave.dda import blocks as B
from rockwave.dda import geometry
from rockwave.dda.blocks import BlockModel, BlockOverlapError, BlockSolver, check_initial_overlap_on_device
from rockwave.dda.geometry import GeometryError
from rockwave.scene.format import Node, Scene, SceneError, gauge_domain_errors
from rockwave.sph.fluid import (
    SOUND_SPEED_FACTOR,
    FluidOptions,
    FluidSolver,
    _grid_dims,
    expected_flow_speed,
    fluid_step_limits,
    sound_speed_from_eos,
)

MM_SUSPECT_EXTENT_M = 100.0
MEMORY_FRACTION = 0.9
WARP_MAX_ARRAY = 2**31 - 1  # elements of one Warp array (32-bit shapes)

# device bytes per particle: x, v (vec3 each, all particles), mass (all); rho, pressure, drho_dt,
# accel, xsph_dv (fluid); hash grid ids/cells + sort buffers (~16 B); the frame snapshot for the
# blow-up checkpoint doubles the state (x, v, rho, p, accel, xsph_dv, drho_dt).
DEV_PER_PARTICLE = 12 + 12 + 4 + 16
DEV_PER_FLUID = 4 + 4 + 4 + 12 + 12
SNAPSHOT_PER_PARTICLE = 24
SNAPSHOT_PER_FLUID = 36
# host bytes per particle: seeding in float64 (lattice, masks, concatenations), per-frame read-backs
HOST_PER_PARTICLE = 160
HOST_PER_FLUID = 64
# blocks: per block, everything the block solver holds (BlockSolver.device_bytes: model, state, the two
# contact-history tables sized from the live contacts, broad phase; <= 4 KB measured for cubes 5 cm apart,
# tests/test_contact_pipeline.py) and the checkpoint snapshot of one history table
DEV_PER_BLOCK = 4096
SNAPSHOT_PER_BLOCK = 1024


def _fmt_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{n:.0f} B"
        n /= 1024
    return f"{n:.3g} PiB"


def _explicit(scene: Scene, path: list, key: str) -> bool:
    node = scene.raw
    for p in path:
        try:
            node = node[p]
        except (KeyError, IndexError, TypeError):
            return False
    return isinstance(node, dict) and key in node


# --------------------------------------------------------------------------------------------
# meshes
# --------------------------------------------------------------------------------------------


def _load_raw(path: str):
    import trimesh

    try:
        m = trimesh.load(path, force="mesh")
    except Exception as e:  # trimesh raises many types for unreadable files
        raise ValueError(f"{path}: cannot read mesh ({type(e).__name__}: {e})") from None
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise ValueError(f"{path}: cannot read a triangle mesh from it (unreadable, empty or not a mesh file)")
    return m


def _mm_check(key: str, path: str, extent: float, scale: float, explicit: bool, container: float | None = None) -> str | None:
    """A mesh larger than MM_SUSPECT_EXTENT_M, or 10x larger than the tank that holds it, with no explicit mesh_scale."""
    big = extent > MM_SUSPECT_EXTENT_M or (container is not None and extent > 10.0 * container)
    if big and not explicit:
        where = f" (the tank spans {container:.4g} m)" if container is not None and extent <= MM_SUSPECT_EXTENT_M else ""
        return (f"{path} spans {extent:.4g} m at mesh_scale = {scale:g}{where}: that looks like millimetres; set "
                f"mesh_scale = 0.001 (or write mesh_scale = {scale:g} explicitly to keep these units)")
    return None


def check_meshes(scene: Scene) -> dict:
    """Check every mesh of the scene; returns {key path: trimesh (scaled, offset, outward normals)}
    for fluid regions, tank and obstacles. Raises SceneError naming the key path."""
    errors: list[tuple[str, str]] = []
    loaded = {}
    entries = []
    if scene.fluid is not None:
        entries += [(f"fluid.regions[{i}]", ["fluid", "regions", i], r) for i, r in enumerate(scene.fluid.regions)]
    if scene.tank is not None:
        entries.append(("tank", ["tank"], scene.tank))
    entries += [(f"obstacles[{i}]", ["obstacles", i], r) for i, r in enumerate(scene.obstacles)]
    container = None
    t = scene.tank
    if t is not None and t.get("box_min_m") is not None and t.get("box_max_m") is not None:
        container = float(max(b - a for a, b in zip(t.box_min_m, t.box_max_m)))
    for key, raw_path, r in entries:
        if r.get("mesh") is None:
            continue
        try:
            m = _load_raw(r["mesh"]).copy()
            m.apply_scale(r["mesh_scale"])
            m.apply_translation(np.asarray(r["mesh_offset_m"], dtype=float))
            ext = float(np.max(m.extents))
            mm = _mm_check(key, r["mesh"], ext, r["mesh_scale"], _explicit(scene, raw_path, "mesh_scale"), None if key == "tank" else container)
            if mm:
                raise ValueError(mm)
            if not m.is_watertight:
                raise ValueError(f"{r['mesh']}: mesh is not watertight (it has holes or open edges); inside/outside is undefined")
            vol = float(m.volume)
            if not math.isfinite(vol) or abs(vol) <= 1e-9 * max(ext, 1e-30) ** 3:
                raise ValueError(f"{r['mesh']}: mesh is degenerate (zero volume)")
            if vol < 0:
                warnings.warn(f"{key}.mesh: {r['mesh']}: faces are inverted (inward normals); flipped them", stacklevel=2)
                m.invert()
            loaded[key] = m
        except ValueError as e:
            errors.append((f"{key}.mesh", str(e)))
    for i, b in enumerate(scene.blocks):
        if b.get("shape") != "mesh" or b.get("mesh") is None:
            continue
        try:
            m = _load_raw(b["mesh"])
            ext = float(np.max(m.extents)) * b["mesh_scale"]
            mm = _mm_check(f"blocks[{i}]", b["mesh"], ext, b["mesh_scale"], _explicit(scene, ["blocks", i], "mesh_scale"))
            if mm:
                raise ValueError(mm)
        except ValueError as e:
            errors.append((f"blocks[{i}].mesh", str(e)))
    if errors:
        raise SceneError(scene.path, errors)
    return loaded


# --------------------------------------------------------------------------------------------
# memory
# --------------------------------------------------------------------------------------------


@dataclass
class Estimate:
    fluid_particles: int
    boundary_particles: int
    blocks: int
    device_bytes: int
    host_bytes: int
    neighbour_entries: int = 0  # the fluid's neighbour list: n_fluid x its capacity per particle (one Warp array)

    def describe(self) -> str:
        parts = []
        if self.fluid_particles or self.boundary_particles:
            parts.append(f"{self.fluid_particles:.3g} fluid + {self.boundary_particles:.3g} boundary particles")
        if self.blocks:
            parts.append(f"{self.blocks:,} blocks")
        return " and ".join(parts) or "nothing"


def _box_cells(lo, hi, step) -> list[int]:
    return [max(int(round((b - a) / step)), 1) for a, b in zip(lo, hi)]


def _shell_count(lo, hi, step, layers, outside: bool, open_top: bool, up: int) -> float:
    n = _box_cells(lo, hi, step)
    if outside:
        tot = [c + layers + (0 if (open_top and a == up) else layers) for a, c in enumerate(n)]
        return float(np.prod(np.asarray(tot, float)) - np.prod(np.asarray(n, float)))
    inner = [max(c - 2 * layers, 0) for c in n]
    return float(np.prod(np.asarray(n, float)) - np.prod(np.asarray(inner, float)))


def estimate(scene: Scene, meshes: dict | None = None) -> Estimate:
    """Particle and block counts and the bytes they need, computed from the scene alone."""
    meshes = meshes if meshes is not None else {}
    nf = nb = 0.0
    dim = scene.dim
    up = dim - 1
    cells = 0.0
    lo = hi = None
    if scene.fluid is not None:
        s = scene.fluid.spacing_m
        for i, r in enumerate(scene.fluid.regions):
            if r.get("box_min_m") is not None:
                nf += float(np.prod(np.asarray(_box_cells(r["box_min_m"], r["box_max_m"], s), float)))
            elif f"fluid.regions[{i}]" in meshes:
                nf += abs(float(meshes[f"fluid.regions[{i}]"].volume)) / s ** 3
        t = scene.tank
        H = support_radius_m(scene)
        if t is not None:
            bstep, layers = boundary_lattice(scene)
            if t.get("box_min_m") is not None:
                nb += _shell_count(t.box_min_m, t.box_max_m, bstep, layers, True, t.open_top, up)
                lo, hi = np.asarray(t.box_min_m) - layers * bstep, np.asarray(t.box_max_m) + layers * bstep
            elif "tank" in meshes:
                m = meshes["tank"]
                nb += float(m.area) * layers / bstep ** 2
                lo, hi = m.bounds[0] - layers * bstep, m.bounds[1] + layers * bstep
            for i, ob in enumerate(scene.obstacles):
                if ob.get("box_min_m") is not None:
                    nb += _shell_count(ob.box_min_m, ob.box_max_m, bstep, layers, False, False, up)
                elif f"obstacles[{i}]" in meshes:
                    nb += float(meshes[f"obstacles[{i}]"].area) * layers / bstep ** 2
        if lo is not None:

            lo3 = np.asarray(list(lo) + [0.0] * (3 - dim)) - H
            hi3 = np.asarray(list(hi) + [0.0] * (3 - dim)) + H
            cells = float(np.prod(_grid_dims(lo3, hi3, H, dim)))
    nblocks = 0
    for b in scene.blocks:
        c = b.get("array", {}).get("count", [1, 1, 1]) if isinstance(b.get("array"), dict) else [1, 1, 1]
        nblocks += int(np.prod([max(int(x), 1) for x in c]))

    nblocks += sum(estimate_block_count(r, dim) for r in scene.rock_mass)
    n_all = nf + nb
    entries = 0.0
    if scene.fluid is not None and nf:
        entries = nf * neighbour_capacity(scene)
    dev = n_all * (DEV_PER_PARTICLE + SNAPSHOT_PER_PARTICLE) + nf * (DEV_PER_FLUID + SNAPSHOT_PER_FLUID) + 8 * cells
    dev += 4 * entries + 16 * nf  # the neighbour lists (indices, counts, list-build positions)
    surf = scene.output.get("surface") if scene.fluid is not None else None
    if surf and surf.get("enabled") and lo is not None:
        # rockwave/output/surface.py default_cell (not imported: it loads Warp)
        res = surf.get("resolution_m") or (1.0 if dim == 3 else 0.5) * scene.fluid.spacing_m
        nodes = float(np.prod((np.asarray(hi, float) - np.asarray(lo, float)) / res + 1))
        dev += 8 * min(float(surf.get("max_grid_nodes") or 20_000_000), nodes)
    if nblocks:
        dev += nblocks * (DEV_PER_BLOCK + SNAPSHOT_PER_BLOCK)
    host = n_all * HOST_PER_PARTICLE + nf * HOST_PER_FLUID + nblocks * 2000
    return Estimate(int(nf), int(nb), nblocks, int(dev), int(host), int(entries))


def neighbour_capacity(scene: Scene) -> int:
    """Neighbour-list entries per fluid particle (rockwave/sph/fluid.py FluidSolver.list_capacity at the default skin;
    0 with fluid.neighbours = 'cells', which stores no list)."""
    fl = scene.fluid
    if fl.get("neighbours") == "cells":
        return 0
    t = scene.tank
    ratio = float(t.boundary_spacing_ratio) if t is not None and t.get("boundary_spacing_ratio") else 1.0
    model = SimpleNamespace(support_radius=fl.support_radius_ratio * fl.spacing_m, spacing=fl.spacing_m,
                            boundary_spacing=ratio * fl.spacing_m, dim=scene.dim)
    return FluidSolver.list_capacity(model, FluidOptions().neighbour_skin)


def available_bytes(device: str) -> tuple[int | None, int | None]:
    """(free device bytes, free host bytes); None where unknown. ROCKWAVE_MEMORY_LIMIT_BYTES caps both (tests)."""
    host = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    host = int(line.split()[1]) * 1024
    except OSError:
        try:
            host = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            host = None
    dev = host
    if device != "cpu":
        import warp as wp

        try:
            dev = int(wp.get_device(device).free_memory)
        except Exception:
            dev = None
    cap = os.environ.get("ROCKWAVE_MEMORY_LIMIT_BYTES")
    if cap:
        dev = min(dev, int(float(cap))) if dev is not None else int(float(cap))
        host = min(host, int(float(cap))) if host is not None else int(float(cap))
    return dev, host


def check_memory(scene: Scene, device: str, meshes: dict | None = None) -> Estimate:
    est = estimate(scene, meshes)
    dev_free, host_free = available_bytes(device)
    key = "fluid.spacing_m" if (est.fluid_particles or est.boundary_particles) else "blocks"
    hint = ("; a larger fluid.spacing_m needs less (memory grows as spacing^-" + str(scene.dim) + ")") if key == "fluid.spacing_m" else ""
    if device == "cpu":
        need, free = est.device_bytes + est.host_bytes, dev_free
        if free is not None and need > MEMORY_FRACTION * free:
            raise SceneError(scene.path, [(key, f"the scene needs about {_fmt_bytes(need)} of memory on the CPU "
                                                f"({est.describe()}), but only {_fmt_bytes(free)} is available{hint}")])
        _check_array_limits(scene, est)
        return est
    if dev_free is not None and est.device_bytes > MEMORY_FRACTION * dev_free:
        raise SceneError(scene.path, [(key, f"the scene needs about {_fmt_bytes(est.device_bytes)} on {device} "
                                            f"({est.describe()}), but only {_fmt_bytes(dev_free)} is free there{hint}")])
    if host_free is not None and est.host_bytes > MEMORY_FRACTION * host_free:
        raise SceneError(scene.path, [(key, f"the scene needs about {_fmt_bytes(est.host_bytes)} of host memory to set up "
                                            f"({est.describe()}), but only {_fmt_bytes(host_free)} is available{hint}")])
    _check_array_limits(scene, est)
    return est


def _check_array_limits(scene: Scene, est: Estimate) -> None:
    """The fluid's neighbour list must fit one Warp array (32-bit shapes), even where the memory would hold it."""
    if est.neighbour_entries >= WARP_MAX_ARRAY:  # one Warp array holds < 2^31 elements, however much memory there is
        cap = est.neighbour_entries // max(est.fluid_particles, 1)
        most = WARP_MAX_ARRAY // cap
        raise SceneError(scene.path, [("fluid.spacing_m", f"{est.fluid_particles:.3g} fluid particles need a neighbour list of "
                                                          f"{est.neighbour_entries:.3g} entries ({cap} per particle), more than "
                                                          f"one Warp array holds (2^31 - 1); one device takes at most about "
                                                          f"{most:.3g} particles at this support: a larger fluid.spacing_m (the "
                                                          f"count grows as spacing^-{scene.dim})")])


def check_scene(scene: Scene, device: str, meshes: dict | None = None) -> Estimate:
    """Mesh checks, the memory estimate, gauges against a mesh tank and fluid regions that seed no
    particle; raises SceneError before anything is allocated. ``meshes``: check_meshes(scene), if done."""
    meshes = check_meshes(scene) if meshes is None else meshes
    est = check_memory(scene, device, meshes)
    check_gauges_in_mesh_tank(scene, meshes)
    check_regions_hold_water(scene, meshes)
    return est


# --------------------------------------------------------------------------------------------
# fluid regions and gauges
# --------------------------------------------------------------------------------------------

MAX_SEED_CHECK_POINTS = 2_000_000
HOST_OVERLAP_CHECK_MAX = 2000  # as rockwave/sim/simulation.py: above, the overlap test runs on the device (here: the CPU)  # larger regions are not seeded twice (one that large is not all covered)


def check_gauges_in_mesh_tank(scene: Scene, meshes: dict) -> None:
    """Gauges against the bounds of a mesh tank (box tanks: rockwave/scene/format.py)."""

    if scene.fluid is None or "tank" not in meshes or not scene.output.gauges:
        return
    errors: list[tuple[str, str]] = []
    lo, hi = meshes["tank"].bounds
    gauge_domain_errors(lambda k, m: errors.append((k, m)), scene.output.gauges, list(lo), list(hi), scene.dim,
                        support_radius_m(scene), "the tank mesh's bounds")
    if errors:
        raise SceneError(scene.path, errors)


def _region_points(scene: Scene, meshes: dict, device: str = "cpu"):
    """Per fluid region: (index, key, lattice points left after the tank and obstacle filters (n, 3),
    why it is empty) as seeded in rockwave/sim/simulation.py; regions too large to seed twice are skipped."""
    fl = scene.fluid
    dim, s = scene.dim, fl.spacing_m
    t = scene.tank
    for i, r in enumerate(fl.regions):
        key = f"fluid.regions[{i}]"
        if r.get("box_min_m") is not None:
            n = float(np.prod(np.asarray(_box_cells(r["box_min_m"], r["box_max_m"], s), float)))
            if n > MAX_SEED_CHECK_POINTS:
                continue
            x = sampling.box_lattice(r["box_min_m"], r["box_max_m"], s)
        elif key in meshes:
            m = meshes[key]
            if float(np.prod(np.maximum(m.extents / s, 1.0))) > MAX_SEED_CHECK_POINTS:
                continue
            x = sampling.box_lattice(m.bounds[0], m.bounds[1], s)
            x = x[sampling.mesh_signed_distance(m, x, device) < 0.0]
            if len(x) == 0:
                yield i, key, x, f"the mesh holds no lattice point at spacing {s:g} m (fluid.spacing_m): it is thinner than one spacing"
                continue
        else:
            continue
        if x.shape[1] == 2:
            x = np.concatenate([x, np.zeros((len(x), 1))], axis=1)
        why = ""
        if t is not None and t.get("box_min_m") is not None:
            x = x[np.all((x[:, :dim] > np.asarray(t.box_min_m)) & (x[:, :dim] < np.asarray(t.box_max_m)), axis=1)]
            why = "outside the tank"
        elif t is not None and "tank" in meshes:
            x = x[sampling.mesh_signed_distance(meshes["tank"], x, device) < 0.0]
            why = "outside the tank mesh"
        if len(x):
            why = "inside the obstacles"
        for j, ob in enumerate(scene.obstacles):
            if len(x) == 0:
                break
            if ob.get("box_min_m") is not None:
                inside = sampling.inside_obstacle(x, ob, dim, device)
            elif f"obstacles[{j}]" in meshes:
                inside = sampling.mesh_signed_distance(meshes[f"obstacles[{j}]"], x, device) < 0.0
            else:
                continue
            x = x[~inside]
        yield i, key, x, (f"seeds no water particle: every lattice point is {why}; move the region into the water's "
                          f"part of the tank (or remove it)")


def check_regions_hold_water(scene: Scene, meshes: dict, device: str = "cpu") -> None:
    """A fluid region none of whose lattice points survives seeding (all outside the tank or inside
    obstacles) is an error naming the region, as in the seeding of rockwave/sim/simulation.py."""
    if scene.fluid is None:
        return
    errors = [(key, why) for _, key, x, why in _region_points(scene, meshes, device) if len(x) == 0]
    if errors:
        raise SceneError(scene.path, errors)


def check_water_outside_blocks(scene: Scene, meshes: dict | None = None, model=None, warn: bool = False) -> int:
    """A fluid region all of whose particles lie inside blocks, or closer to their faces than
    the contact distance (removed at seeding, rockwave/build/builder.py remove_inside_blocks), is an
    error naming the region. Builds the block model on the CPU when none is given. ``warn``: a region that
    loses some of its particles so is a one-line warning with the count (as the run prints it). Returns the
    particles that seeding will drop (per region, before a later region's overlap)."""
    if scene.fluid is None or not (scene.blocks or scene.rock_mass):
        return 0

    if meshes is None:
        meshes = check_meshes(scene)
    if model is None:
        model = _block_model(scene, check_overlap=False)
    state = model.state()
    ratio = coupling_options(scene).contact_distance_ratio
    errors = []
    dropped = 0
    steps, scale = sampling.lattice_steps_and_scale(scene.fluid.regions, scene.fluid.spacing_m, scene.dim)
    clearance = seeding_clearance_m(ratio, scene.fluid.spacing_m, steps, scale)  # as the builder's seeding_clearance
    for _, key, x, _ in _region_points(scene, meshes):
        if len(x) == 0:
            continue
        dist, _ = block_signed_distance(model, state, x)
        inside = int((dist < clearance).sum())
        dropped += inside
        if warn and 0 < inside < len(x):
            warnings.warn(inside_blocks_message(inside, len(x), key), stacklevel=2)
        if not (dist >= clearance).any():
            errors.append((key, f"seeds no water particle: every lattice point at spacing {scene.fluid.spacing_m:g} m "
                                f"(fluid.spacing_m) is inside a block or within the contact distance of one; "
                                f"move the blocks or the region, or make the spacing finer"))
    if errors:
        raise SceneError(scene.path, errors)
    return dropped


# --------------------------------------------------------------------------------------------
# blocks (what the run checks when it builds the block model)
# --------------------------------------------------------------------------------------------


def _block_model(scene: Scene, check_overlap: bool = True):
    """The scene's BlockModel on the CPU, built as the run builds it (SceneError naming the problem)."""

    specs = block_specs(scene)  # SceneError naming blocks[i].mesh / vertices_m / size_m
    g = list(scene.gravity.acceleration_m_s2) + [0.0] * (3 - scene.dim)
    host_check = check_overlap and len(specs) <= HOST_OVERLAP_CHECK_MAX  # as the run: exact host test, device FCP for large sets
    try:
        model = BlockModel(specs, device="cpu", gravity=g, check_overlap=host_check)
        if check_overlap and not host_check:

            check_initial_overlap_on_device(BlockSolver(model), model.state())
    except (BlockOverlapError, GeometryError, ValueError, TypeError) as e:
        raise SceneError(scene.path, [("blocks", tank_overlap_hint(str(e)))]) from None
    return model


def check_blocks(scene: Scene) -> int:
    """Block geometry (convex, closed, non-degenerate meshes and prisms), materials and the initial
    overlap (blocks apart from each other and from fixed blocks such as a slope), on the host; and
    water not all inside blocks. Returns the number of blocks. Raises SceneError like the run."""
    if not (scene.blocks or scene.rock_mass):
        return 0
    model = _block_model(scene)
    check_water_outside_blocks(scene, model=model, warn=True)
    return model.num_blocks


# --------------------------------------------------------------------------------------------
# disk
# --------------------------------------------------------------------------------------------


def output_bytes(sim, n_frames: int) -> int:
    """Rough size of a run's outputs: USD frames (positions, velocities, density, pressure), CSV rows, a checkpoint."""
    nf = sim.fluid.n_fluid if sim.fluid is not None else 0
    nb = sim.blocks.num_blocks if sim.blocks is not None else 0
    per_frame = nf * 32 + nb * 200 + 64
    ckpt = nf * 60 + (sim.fluid.n_boundary * 28 if sim.fluid is not None else 0) + nb * 300
    return int(per_frame * (n_frames + 1) + 2 * ckpt)


def check_disk(sim, out: Path, n_frames: int) -> None:
    """Warn (do not refuse: the estimate is rough) when the output folder's disk looks too small."""
    try:
        free = shutil.disk_usage(out).free
    except OSError:
        return
    need = output_bytes(sim, n_frames)
    if need > free:
        warnings.warn(f"{out}: the outputs may need about {_fmt_bytes(need)} but only {_fmt_bytes(free)} is free on that disk; "
                      f"a full disk stops the run with the frames written so far intact", stacklevel=2)


# --------------------------------------------------------------------------------------------
# run length: the number of steps and the wall time, before stepping
# --------------------------------------------------------------------------------------------

MAX_STEPS = 1.0e7  # above this many steps a run is refused unless forced (--yes / force=True)
MAX_WALL_S = 24 * 3600.0  # above this estimated wall time likewise
# Optimistic throughputs for the wall-time estimate before any step was measured (particle steps
# and block steps per second): a scene refused with these would take longer still.
NOMINAL_PARTICLE_STEPS_PER_S = {"cpu": 2.0e6, "cuda": 1.0e9}
NOMINAL_BLOCK_STEPS_PER_S = {"cpu": 2.0e5, "cuda": 1.0e8}
STEP_SECONDS_FLOOR = {"cpu": 2.0e-5, "cuda": 1.0e-4}  # launch overhead of one step, whatever its size
CONTACT_POINTS_FOR_DT = 8  # as BlockSolver(contact_points_for_dt=8) in rockwave/dda/blocks.py
# USD output of the blocks (rockwave/output/recorders.py UsdRecorder; measured on a CPU core, 20k boxes): each block a
# mesh prim below INSTANCER_MIN_BLOCKS blocks (set-up ~1e-4 s a prim, a frame ~2e-4 s a prim with its share of the chunk
# files), from it on the instances of one PointInstancer (two arrays a frame, ~4e-7 s a block with the chunk files)
INSTANCER_MIN_BLOCKS = 10_000
USD_SETUP_S_PER_BLOCK_PRIM = 1.0e-4
USD_FRAME_S_PER_BLOCK_PRIM = 2.0e-4
USD_FRAME_S_PER_INSTANCE = 4.0e-7
LONG_RUN_MIN_DT_S = 1.0e-6  # too many steps of at least this: the duration is blamed, not the step's key
MIN_MACH_MARGIN = 1.0  # c0 below this x the expected flow speed: the water cannot stay weakly compressible


@dataclass
class RunLength:
    """What :func:`estimate_run_length` found.

    steps: simulated steps for ``duration`` s at ``dt`` s; dt_key: the scene key that sets the step
    and dt_why the limit it comes from; seconds_per_step: measured (``measured``) or nominal cost of
    one step on the device; wall_s: steps x seconds_per_step; wall_key: the key that makes a step
    expensive (fluid.spacing_m for many particles, blocks for many blocks) or dt_key;
    flow_speed: expected fastest water speed sqrt(2 g H) + initial speed (m/s), sound_speed: c0.
    """

    steps: float
    dt: float
    dt_key: str
    dt_why: str
    duration: float
    particles: int
    blocks: int
    seconds_per_step: float
    measured: bool
    wall_s: float
    wall_key: str
    flow_speed: float = 0.0
    sound_speed: float | None = None
    flow_key: str = ""
    output_s: float = 0.0  # wall time of the USD output of the blocks (set-up and frames; usd_output_seconds), in wall_s
    flow_what: str = ""  # what flow_speed is made of: "sqrt(2 g H) = ... (+ the initial speed ... of fluid.regions[i])"

    def describe(self) -> str:
        cost = f"{self.seconds_per_step:.3g} s/step{' measured here' if self.measured else ' (nominal: a lower bound)'}"
        if self.output_s >= 0.05 * self.wall_s and self.output_s > 1.0:
            cost += f", {_fmt_wall(self.output_s)} of it the USD output of the blocks"
        return f"about {self.steps:.3g} steps of {self.dt:.3g} s for {self.duration:g} s (~{_fmt_wall(self.wall_s)} at {cost})"


def usd_output_seconds(scene: Scene, blocks: int, duration: float, setup: bool = True) -> float:
    """Wall time of the blocks' USD output (rockwave/output/recorders.py): the set-up of their prims (``setup``) and
    the frames of ``duration`` s; 0 without USD output."""
    if not scene.output.usd or not blocks:
        return 0.0
    frames = math.floor(duration * scene.output.frame_rate_hz + 1e-9) + 1
    if blocks >= INSTANCER_MIN_BLOCKS:
        return frames * blocks * USD_FRAME_S_PER_INSTANCE
    return blocks * ((USD_SETUP_S_PER_BLOCK_PRIM if setup else 0.0) + frames * USD_FRAME_S_PER_BLOCK_PRIM)


def _fmt_wall(s: float) -> str:
    if not math.isfinite(s):
        return "forever"
    if s < 120:
        return f"{s:.3g} s"
    if s < 3 * 3600:
        return f"{s / 60:.3g} min"
    if s < 3 * 86400:
        return f"{s / 3600:.3g} h"
    if s < 3 * 365 * 86400:
        return f"{s / 86400:.3g} days"
    return f"{s / (365 * 86400):.3g} years"


def _water_height_and_speed(scene: Scene) -> tuple[float, float, int | None]:
    """Height of the water column above the lowest floor (box regions and a box tank; mesh regions
    by the mesh file's bounds are not read here: 0), the largest initial speed and the index of the
    region that has it (None: all at rest)."""
    fl, up = scene.fluid, scene.dim - 1
    lo, hi, v0, fast = math.inf, -math.inf, 0.0, None
    for i, r in enumerate(fl.regions):
        if r.get("box_min_m") is not None and r.get("box_max_m") is not None:
            lo, hi = min(lo, r["box_min_m"][up]), max(hi, r["box_max_m"][up])
        if r.get("velocity_m_s") is not None:
            speed = math.sqrt(sum(c * c for c in r["velocity_m_s"]))
            if speed > v0:
                v0, fast = speed, i
    t = scene.tank
    if t is not None and t.get("box_min_m") is not None and hi > -math.inf:
        lo = min(lo, t.box_min_m[up])
    return (hi - lo if hi > lo else 0.0), v0, fast


def _fluid_step(scene: Scene) -> tuple[float, str, str, float, float, str, str] | None:
    """(dt, key, why, c0, flow speed, flow key, what the flow speed is made of) of the fluid's step limits at the
    start."""

    fl = scene.fluid
    if fl is None:
        return None
    fp = fluid_parameters(fl)
    c0 = float(sound_speed_from_eos(fp))
    c_key = "fluid.eos.speed_of_sound_m_s" if fp.eos_speed_of_sound_m_s is not None else (
        "fluid.eos.b_pa" if fp.eos_type == "tait" else "fluid.eos.k_m2_s2")
    g = gravity_norm(scene)
    H, v0, fast = _water_height_and_speed(scene)
    fall = math.sqrt(2.0 * g * H)
    u = expected_flow_speed(g, H, v0)
    flow_what = f"sqrt(2 g H) = {fall:.3g} m/s (H = {H:.3g} m)"
    if fast is not None:
        flow_what += f" + the initial speed {v0:.3g} m/s of fluid.regions[{fast}]"
    h = 0.5 * fp.support_radius_m
    nu = fp.laplacian_viscosity_pa_s / fp.rest_density_kg_m3
    # the solver's rule at the start's speed u and acceleration |g| (rockwave/sph/fluid.py fluid_step_limits)
    limits = fluid_step_limits(fp.support_radius_m, c0, fp.artificial_alpha, nu, scene.simulation.cfl_number, u, g)
    flow_key = "gravity.acceleration_m_s2" if g > 100.0 else (
        f"fluid.regions[{fast}].velocity_m_s" if fast is not None and v0 > fall else c_key)
    why = {"courant": (c_key if c0 >= 100.0 * max(u, 1.0) else (flow_key if u > c0 else "fluid.spacing_m"),
                       f"C h/(c0 + u_max) with h = {h:.3g} m, c0 = {c0:.3g} m/s, u_max = {u:.3g} m/s"),
           "force": ("gravity.acceleration_m_s2", f"0.25 sqrt(h/|g|) with |g| = {g:.3g} m/s^2"),
           "viscous": ("fluid.viscosity.laplacian_pa_s", f"0.125 h^2/nu with nu = {nu:.3g} m^2/s")}
    cands = [(dt, *why[name]) for name, dt in limits.items()]
    dt, key, why = min(cands)
    return dt, key, why, c0, u, flow_key, flow_what


def _block_entries(scene: Scene):
    """(key prefix, entry) of every [[blocks]] entry, and of every [[rock_mass]] as a box of its first three
    spacings (its typical block, rockwave/build/rockmass.py)."""

    for i, b in enumerate(scene.blocks):
        yield f"blocks[{i}]", b
    for i, r in enumerate(scene.rock_mass):
        sp = [js.spacing_m for js in r.joint_sets][:3]
        sp += [min(sp)] * (3 - len(sp)) if sp else [1.0] * 3
        yield f"rock_mass[{i}]", Node(shape="box", size_m=sp, mesh_scale=1.0, kind=r.kind, youngs_modulus_pa=r.youngs_modulus_pa,
                                      density_kg_m3=r.density_kg_m3, material=r.material, name=r.name)


def _block_step(scene: Scene) -> tuple[float, str, str] | None:
    """(dt, key, why): block_dt_safety x the critical DDA step 2/omega (sqrt(1 + zeta^2) - zeta) of the
    stiffest movable block entry, omega from k_n n_c / m and k_n n_c r^2 / I_min (rockwave/dda/blocks.py)."""
    best = None
    for prefix, b in _block_entries(scene):
        if b.kind not in ("rigid", "deformable"):
            continue
        try:
            if b.shape == "box":
                parts = [geometry.box(b.size_m)]
            elif b.shape == "prism":
                parts = [geometry.prism(b.vertices_m)]
            else:

                # a non-convex mesh: its CompoundBlock (decomposed at mesh_scale; the same mass properties API)
                loaded = geometry.load_mesh(b.mesh, decomposition=decomposition_of(scene, b), scale=b.mesh_scale)
                parts = loaded if isinstance(loaded, list) else [loaded]
        except Exception:  # noqa: BLE001  (a bad shape is reported by the block checks, with its key)
            continue
        mat = b.material
        E = B.DEFAULT_YOUNGS_MODULUS if b.youngs_modulus_pa is None else b.youngs_modulus_pa
        try:
            zeta = B.ContactMaterial(restitution=mat.restitution, damping_ratio=mat.damping_ratio).resolved_damping_ratio()
        except ValueError:
            continue
        fac = math.sqrt(1.0 + zeta * zeta) - zeta
        for g in parts:
            scale = b.mesh_scale if b.shape == "mesh" and not isinstance(g, geometry.CompoundBlock) else 1.0
            vol_scale, len_scale = scale ** 3, scale
            mass = g.mass(b.density_kg_m3) * vol_scale
            imin = float(np.linalg.eigvalsh(g.inertia(b.density_kg_m3)).min()) * vol_scale * len_scale ** 2
            r = g.bounding_radius * len_scale
            kn = B.PENALTY_FACTOR * E * g.size * len_scale if mat.normal_stiffness_n_m is None else mat.normal_stiffness_n_m
            if not (mass > 0 and imin > 0 and kn > 0):
                continue
            om = max(math.sqrt(kn * CONTACT_POINTS_FOR_DT / mass), math.sqrt(kn * CONTACT_POINTS_FOR_DT * r * r / imin))
            dt = 2.0 / om * fac
            if b.kind == "deformable":  # strain modes: ~3.5 c / L with c = sqrt(E / rho)
                dt = min(dt, 2.0 / (3.5 * math.sqrt(E / b.density_kg_m3) / (g.size * len_scale)))
            dt *= scene.simulation.block_dt_safety
            if mat.normal_stiffness_n_m is not None and mat.normal_stiffness_n_m > B.PENALTY_FACTOR * E * g.size * len_scale:
                key = f"{prefix}.material.normal_stiffness_n_m"
            elif b.youngs_modulus_pa is not None and b.youngs_modulus_pa > 1e12:
                key = f"{prefix}.youngs_modulus_pa"
            elif b.density_kg_m3 < 100.0:
                key = f"{prefix}.density_kg_m3"
            else:
                key = "simulation.block_dt_safety"
            why = (f"the critical DDA step of {b.name!r} ({prefix}: mass {mass:.3g} kg, contact stiffness k_n = {kn:.3g} N/m)")
            if best is None or dt < best[0]:
                best = (dt, key, why)
    return best


def estimate_run_length(scene: Scene, device: str = "cpu", duration: float | None = None,
                        seconds_per_step: float | None = None, dt: float | None = None, setup: bool = True) -> RunLength:
    """Steps and wall time of a run, from the scene's stability limits alone (no allocation).

    The step is the smallest of: the fluid's CFL step C h/(c0 + u_max) (u_max = sqrt(2 g H) for the
    water height H, plus any initial speed), its force step 0.25 sqrt(h/g) and viscous step
    0.125 h^2/nu; the blocks' critical DDA step times block_dt_safety; ``simulation.dt_s`` when the step
    is fixed; or ``dt`` when given (the step a run actually uses). ``duration`` defaults to
    simulation.duration_s. ``seconds_per_step``: the measured cost of one step (from the first steps of
    a run); without it a nominal, optimistic cost for the device from the particle and block counts (a lower bound). The wall
    time includes the blocks' USD output (usd_output_seconds; its set-up when ``setup``)."""
    sim = scene.simulation
    duration = sim.duration_s if duration is None else float(duration)
    cands = []
    fs = _fluid_step(scene)
    c0 = u = None
    flow_key = flow_what = ""
    if fs is not None:
        cands.append(fs[:3])
        c0, u, flow_key, flow_what = fs[3], fs[4], fs[5], fs[6]
    bs = _block_step(scene) if scene.blocks or scene.rock_mass else None
    if bs is not None and (fs is None or sim.get("block_stepping") == "single"):
        cands.append(bs)  # with water, multi-rate blocks sub-step inside the fluid's step (rockwave/sim/clock.py)
    c = scene.coupling
    if fs is not None and (scene.blocks or scene.rock_mass) and c is not None and c.stiffness_n_m is not None:
        m = scene.fluid.rest_density_kg_m3 * scene.fluid.spacing_m ** scene.dim
        om = math.sqrt(3.0 * c.stiffness_n_m / m)
        cands.append((0.5 * 2.0 / om, "coupling.stiffness_n_m", f"the fluid-block penalty spring K_s = {c.stiffness_n_m:.3g} N/m"))
    if sim.time_step == "fixed" and sim.dt_s is not None:
        cands = [(sim.dt_s, "simulation.dt_s", "the fixed step simulation.dt_s")]
    if dt is not None:
        step, why = float(dt), "the step in use"
        key = min(cands)[1] if cands else "simulation.dt_s"
    elif cands:
        step, key, why = min(cands)
    else:
        step, key, why = duration, "simulation.duration_s", "one step"
    steps = duration / step if step > 0 else math.inf
    est = estimate(scene)
    particles = est.fluid_particles + est.boundary_particles
    kind = "cpu" if device == "cpu" else "cuda"
    if seconds_per_step is None:
        sps = max(STEP_SECONDS_FLOOR[kind], particles / NOMINAL_PARTICLE_STEPS_PER_S[kind]
                  + est.blocks / NOMINAL_BLOCK_STEPS_PER_S[kind])
        measured = False
    else:
        sps, measured = float(seconds_per_step), True
    output_s = usd_output_seconds(scene, est.blocks, duration, setup)
    wall = steps * sps + output_s
    if particles >= 1e6 and particles / NOMINAL_PARTICLE_STEPS_PER_S[kind] >= est.blocks / NOMINAL_BLOCK_STEPS_PER_S[kind]:
        wall_key = "fluid.spacing_m"
    elif est.blocks >= 1e5 or output_s > 0.5 * wall:
        wall_key = "blocks"
    elif step >= 1e-4:
        wall_key = "simulation.duration_s"
    else:
        wall_key = key
    return RunLength(steps=steps, dt=step, dt_key=key, dt_why=why, duration=duration, particles=particles, blocks=est.blocks,
                     seconds_per_step=sps, measured=measured, wall_s=wall, wall_key=wall_key,
                     flow_speed=u or 0.0, sound_speed=c0, flow_key=flow_key, flow_what=flow_what, output_s=output_s)


def check_run_length(scene: Scene, device: str = "cpu", duration: float | None = None, seconds_per_step: float | None = None,
                     dt: float | None = None, force: bool = False, max_steps: float | None = None,
                     max_wall_s: float | None = None, setup: bool = True) -> RunLength:
    """Refuse, before stepping, a run that cannot work or would not end: raises SceneError naming the
    key to change (and saying that ``--yes`` / ``force=True`` runs it anyway) when

    - the speed of sound c0 is below the expected flow speed u_max = sqrt(2 g H) (H: the water's
      height; plus any initial speed): the water cannot stay weakly compressible and the step
      collapses (e.g. gravity 1e6 m/s^2); WCSPH wants c0 >= 10 u_max;
    - the run needs more than ``max_steps`` (default MAX_STEPS = 1e7) steps;
    - or more than ``max_wall_s`` (default MAX_WALL_S = 24 h) of wall time, from ``seconds_per_step``
      when measured (the run loop passes the cost of its first steps, the remaining ``duration`` and
      the ``dt`` in use) or a nominal cost otherwise.

    Returns the :class:`RunLength` (also when forced)."""
    rl = estimate_run_length(scene, device, duration, seconds_per_step, dt, setup)
    if force:
        return rl
    max_steps = MAX_STEPS if max_steps is None else max_steps
    max_wall_s = MAX_WALL_S if max_wall_s is None else max_wall_s
    tail = "; or pass --yes (Python: force=True) to run it anyway"
    if rl.sound_speed is not None and rl.flow_speed > 0 and rl.sound_speed < MIN_MACH_MARGIN * rl.flow_speed:
        target = SOUND_SPEED_FACTOR * rl.flow_speed
        region = rl.flow_key.startswith("fluid.regions")
        key = rl.flow_key if rl.flow_key.startswith(("gravity", "fluid.regions")) else "fluid.eos.speed_of_sound_m_s"
        check = (f"check {rl.flow_key} (a unit mistake?) or raise fluid.eos.speed_of_sound_m_s" if region else
                 "or check gravity.acceleration_m_s2")
        raise SceneError(scene.path, [(key, f"the speed of sound c0 = {rl.sound_speed:.3g} m/s is below the expected flow speed "
                                            f"u_max = {rl.flow_what or 'sqrt(2 g H)'} = {rl.flow_speed:.3g} m/s: the water cannot "
                                            f"stay weakly compressible (it leaks through walls, the step collapses or the run "
                                            f"blows up); weakly compressible SPH wants c0 >= 10 u_max = {target:.3g} m/s "
                                            f"({check}){tail}")])
    if not rl.steps <= max_steps:
        if rl.dt >= LONG_RUN_MIN_DT_S:  # a step of physical size: the duration is what is long
            what = "simulation.duration_s (or --duration)"
            raise SceneError(scene.path, [("simulation.duration_s", f"the run needs {rl.describe()}, more than {max_steps:.3g} "
                                                                    f"steps: a duration of {rl.duration:.3g} s is long for the "
                                                                    f"scene's step (set by {rl.dt_why}); check {what} (a unit "
                                                                    f"mistake?){tail}")])
        raise SceneError(scene.path, [(rl.dt_key, f"the run needs {rl.describe()}, more than {max_steps:.3g} steps; the step is "
                                                  f"set by {rl.dt_why}: check {rl.dt_key} (a unit mistake?){tail}")])
    if not rl.wall_s <= max_wall_s:
        raise SceneError(scene.path, [(rl.wall_key, f"the run needs {rl.describe()}, more than {_fmt_wall(max_wall_s)} on "
                                                    f"{device} ({rl.particles:,} particles, {rl.blocks:,} blocks); "
                                                    f"check {rl.wall_key}{tail}")])
    return rl


def check_before_stepping(scene: Scene, device: str, duration: float | None = None, force: bool = False) -> dict:
    """Every check a run makes before its first step, without allocating the simulation: the scene
    file (already loaded), meshes, memory, fluid regions and gauges (:func:`check_scene`), the block
    geometry and initial overlaps (:func:`check_blocks`) and the run length (:func:`check_run_length`).
    ``python -m rockwave validate`` runs this. Returns {"estimate", "blocks", "run_length"}."""
    est = check_scene(scene, device)
    nb = check_blocks(scene)
    rl = check_run_length(scene, device, duration=duration, force=force)
    return {"estimate": est, "blocks": nb, "run_length": rl}
