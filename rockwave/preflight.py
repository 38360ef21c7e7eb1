"""Checks made before anything is allocated: meshes and memory.

- :func:`check_meshes`: every mesh a scene names (fluid regions, tank, obstacles, blocks) is read
  once and checked: unreadable, not watertight, zero volume -> error; inverted normals -> fixed
  with a warning; a largest extent above ``MM_SUSPECT_EXTENT_M`` with no explicit ``mesh_scale``
  -> error ("looks like millimetres": set ``mesh_scale = 0.001``, or ``mesh_scale = 1.0`` to keep
  metres). Block meshes must also be convex (checked by :mod:`rockwave.geometry`).
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

import numpy as np

from rockwave.scene import Scene, SceneError

MM_SUSPECT_EXTENT_M = 100.0
MEMORY_FRACTION = 0.9

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
# blocks: per block state/model arrays; contact history tables (2, each cap x (24 + 16 x 40) B)
DEV_PER_BLOCK = 1200
TABLE_SLOT_BYTES = 24 + 16 * 40


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
        H = scene.fluid.support_radius_ratio * s
        if t is not None:
            bstep = s * t.boundary_spacing_ratio
            layers = t.layers or max(1, int(math.ceil(H / bstep - 1e-9)))
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
            from rockwave.fluid import _grid_dims

            lo3 = np.asarray(list(lo) + [0.0] * (3 - dim)) - H
            hi3 = np.asarray(list(hi) + [0.0] * (3 - dim)) + H
            cells = float(np.prod(_grid_dims(lo3, hi3, H, dim)))
    nblocks = 0
    for b in scene.blocks:
        c = b.get("array", {}).get("count", [1, 1, 1]) if isinstance(b.get("array"), dict) else [1, 1, 1]
        nblocks += int(np.prod([max(int(x), 1) for x in c]))
    n_all = nf + nb
    dev = n_all * (DEV_PER_PARTICLE + SNAPSHOT_PER_PARTICLE) + nf * (DEV_PER_FLUID + SNAPSHOT_PER_FLUID) + 8 * cells
    surf = scene.output.get("surface") if scene.fluid is not None else None
    if surf and surf.get("enabled") and lo is not None:
        res = surf.get("resolution_m") or 0.5 * scene.fluid.spacing_m
        nodes = float(np.prod((np.asarray(hi, float) - np.asarray(lo, float)) / res + 1))
        dev += 8 * min(float(surf.get("max_grid_nodes") or 20_000_000), nodes)
    if nblocks:
        cap = 1 << (int(4 * (8 * nblocks + 64)) - 1).bit_length()
        dev += nblocks * DEV_PER_BLOCK + 3 * cap * TABLE_SLOT_BYTES  # two tables + the snapshot
    host = n_all * HOST_PER_PARTICLE + nf * HOST_PER_FLUID + nblocks * 2000
    return Estimate(int(nf), int(nb), nblocks, int(dev), int(host))


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
        return est
    if dev_free is not None and est.device_bytes > MEMORY_FRACTION * dev_free:
        raise SceneError(scene.path, [(key, f"the scene needs about {_fmt_bytes(est.device_bytes)} on {device} "
                                            f"({est.describe()}), but only {_fmt_bytes(dev_free)} is free there{hint}")])
    if host_free is not None and est.host_bytes > MEMORY_FRACTION * host_free:
        raise SceneError(scene.path, [(key, f"the scene needs about {_fmt_bytes(est.host_bytes)} of host memory to set up "
                                            f"({est.describe()}), but only {_fmt_bytes(host_free)} is available{hint}")])
    return est


def check_scene(scene: Scene, device: str) -> Estimate:
    """Mesh checks and the memory estimate; raises SceneError before anything is allocated."""
    meshes = check_meshes(scene)
    return check_memory(scene, device, meshes)


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
