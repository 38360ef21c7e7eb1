"""Part ``scaling``: throughput and memory as the problem grows.

- fluid: the 3D dam break (SPHERIC Test 2 geometry, scenes/dam_break_3d.toml) at decreasing spacings:
  particles, mean neighbours per particle (fluid and boundary within the support radius) and
  particle-steps/s of complete steps (grid, density, EOS, forces, integration), timed after a warm-up
  that loads the kernels; fixed dt = the scene's initial step, no output during the timed steps;
- blocks: the jointed rock slope (scenes/rock_slope_10k.toml resized) at growing block counts: contacts
  per block after settling and block-steps/s of complete DDA steps;
- coupled: the coupled scenes (scaled by ``coupled_scale``: spacing / s^(1/dim)), particle-steps/s and
  the share of the step spent in the coupling (broad phase, penalty forces, impulse);
- memory: peak memory at two sizes in fresh processes (``python -m benchmarks _mem``); the slope
  between them is the cost per particle / block.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time

import numpy as np

from benchmarks.common import ROOT, log, timed

CONFIG = {
    "quick": dict(fluid_spacings=[0.06, 0.045], fluid_steps=20, block_counts=[100, 400], block_steps=20, block_settle=100,
                  coupled=["wave_maker_small.toml", "sliding_wedge_small.toml"], coupled_steps=5, coupled_scale=[1.0],
                  mem_fluid=[0.06, 0.045], mem_blocks=[100, 400], block_cost=[]),
    "full": dict(fluid_spacings=[0.04, 0.02, 0.015, 0.01], fluid_steps=100, block_counts=[1000, 10000, 100000],
                 block_steps=100, block_settle=300, coupled=["wave_maker.toml", "sliding_wedge.toml"], coupled_steps=50,
                 coupled_scale=[1.0, 2.0], mem_fluid=[0.02, 0.01], mem_blocks=[1000, 10000], block_cost=[]),
}


def fluid_sim(device: str, spacing: float):
    import rockwave

    scene = rockwave.load_scene(ROOT / "scenes" / "dam_break_3d.toml")
    scene.fluid["spacing_m"] = spacing
    scene.output["gauges"] = []
    return rockwave.Simulation(scene, device=device)


def fluid(device: str, spacing: float, steps: int, warmup: int = 20) -> dict:
    sim = fluid_sim(device, spacing)
    for _ in range(warmup):
        sim.step()
    nbrs = float(np.mean(sim.fluid_solver.neighbour_counts(sim.state)))
    t = timed(lambda: [sim.step() for _ in range(steps)], device)
    n = sim.fluid.n_fluid
    return {"spacing_m": spacing, "particles": n, "boundary_particles": sim.fluid.n_boundary, "neighbours": nbrs,
            "steps": steps, "seconds": t, "steps_per_s": steps / t, "particle_steps_per_s": n * steps / t}


def rock_slope_sim(device: str, count: int):
    """The jointed rock slope with about ``count`` blocks (10 layers, 1.6 : 1 in plan) on a base large enough."""
    import rockwave

    scene = rockwave.load_scene(ROOT / "scenes" / "rock_slope_10k.toml")
    nz = 10
    ny = max(1, int(round(math.sqrt(count / nz / 1.6))))
    nx = max(1, int(round(count / nz / ny)))
    from rockwave.build.rockmass import resize_box_region

    rm = scene.rock_mass[0]  # [[rock_mass]] cut into 0.5 m cubes
    resize_box_region(rm, [0.5 * nx, 0.5 * ny, 0.5 * nz])
    rm["region"]["box_min_m"][1], rm["region"]["box_max_m"][1] = -0.25 * ny, 0.25 * ny  # centred across the base
    scene.blocks[0]["size_m"] = [max(40.0, 0.5 * nx + 25.0), max(16.0, 0.5 * ny + 4.0), 1.0]
    return rockwave.Simulation(scene, device=device)


def blocks(device: str, count: int, steps: int, settle: int = 300) -> dict:
    sim = rock_slope_sim(device, count)
    for _ in range(settle):  # close the 0.2 mm joints so contacts exist
        sim.step()
    contacts = float(np.mean(sim.block_state.contact_counts()[1:]))
    t = timed(lambda: [sim.step() for _ in range(steps)], device)
    n = sim.blocks.num_blocks
    mem = sim.block_solver.device_bytes(sim.block_state)  # the whole block solver's arrays, after the steps
    # cost per contact point (issue 36's target: within 1.2x of the record before it): the step's wall time over the
    # points of the pairs (contact_counts counts each point for both of its blocks: n x contacts / 2 points)
    points = 0.5 * n * contacts
    return {"blocks": n, "contacts_per_block": contacts, "steps": steps, "seconds": t, "steps_per_s": steps / t,
            "block_steps_per_s": n * steps / t, "dt_s": sim.dt, "contact_points": points,
            "ns_per_contact_point": 1e9 * t / steps / max(points, 1.0), "device_bytes_per_block": mem["per_block"],
            "history_bytes_per_block": mem["history"] / n}


def coupled(scene_name: str, device: str, steps: int, scale: float) -> dict:
    """A coupled scene at ``scale`` x its particles: ms per step and the coupling's share of it (the
    coupling's compute and apply timed, synchronised, on this instance)."""
    import warp as wp

    import rockwave

    scene = rockwave.load_scene(ROOT / "scenes" / scene_name)
    scene.fluid["spacing_m"] = scene.fluid.spacing_m / scale ** (1.0 / scene.dim)
    sim = rockwave.Simulation(scene, device=device)
    c = sim.coupling
    spent = [0.0]

    def clocked(fn):
        def call(*a):
            wp.synchronize_device(device)
            t = time.perf_counter()
            fn(*a)
            wp.synchronize_device(device)
            spent[0] += time.perf_counter() - t
        return call

    for _ in range(3):  # warm-up (kernel loads)
        sim.step()
    c.compute, c.apply = clocked(c.compute), clocked(c.apply)
    wall = timed(lambda: [sim.step() for _ in range(steps)], device)
    return {"scene": scene_name, "scale": scale, "fluid_particles": sim.n_fluid, "blocks": sim.blocks.num_blocks,
            "active_blocks": c.active_block_count(), "steps": steps, "s_per_step": wall / steps,
            "particle_steps_per_s": sim.n_fluid * steps / wall, "coupling_share": spent[0] / wall,
            "removed_inside_blocks": sim.removed_inside_blocks}


def block_cost(device: str, scene_name: str, block: str, spacing: float, steps: int) -> list[dict]:
    """What one block costs a coupled scene: the scene at ``spacing`` timed over ``steps`` steps (after 5) in the
    order with ``block``, without it, with it (one process), e.g. ``--set 'block_cost=[["sliding_wedge.toml",
    "wedge", 0.01]]'`` (issue 20: the wedge costs <= 5% at >= 1 M particles)."""
    import copy

    import warp as wp

    import rockwave

    path = ROOT / "scenes" / scene_name
    rows = []
    for keep in (True, False, True):
        d = copy.deepcopy(rockwave.load_scene(path).raw)
        d["fluid"]["spacing_m"] = spacing
        if not keep:
            d["blocks"] = [b for b in d["blocks"] if b["name"] != block]
        sim = rockwave.Simulation(rockwave.parse_scene(d, path, path.parent), device=device)
        for _ in range(5):
            sim.step()
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        for _ in range(steps):
            sim.step()
        wp.synchronize_device(device)
        w = time.perf_counter() - t0
        rows.append({"scene": scene_name + ("" if keep else f" ({block} removed)"), "scale": 1.0, "spacing_m": spacing,
                     "fluid_particles": sim.n_fluid, "blocks": sim.blocks.num_blocks, "steps": steps, "s_per_step": w / steps,
                     "particle_steps_per_s": sim.n_fluid * steps / w, "dt_s": sim.clock.dt, "limited_by": sim.clock.limiting})
    with_block = 0.5 * (rows[0]["s_per_step"] + rows[2]["s_per_step"])
    rows[0]["block_cost"] = rows[2]["block_cost"] = with_block / rows[1]["s_per_step"] - 1.0
    return rows


def run(dev: str, cfg: dict) -> dict:
    out = {"fluid": [], "blocks": [], "coupled": [], "memory": []}
    for s in cfg["fluid_spacings"]:
        r = fluid(dev, s, cfg["fluid_steps"], warmup=5)
        out["fluid"].append(r)
        log(f"  fluid {s:g} m: {r['particles']} particles, {r['neighbours']:.1f} nbrs, "
            f"{r['particle_steps_per_s']:.3g} particle-steps/s")
    for c in cfg["block_counts"]:
        r = blocks(dev, c, cfg["block_steps"], cfg["block_settle"])
        out["blocks"].append(r)
        log(f"  blocks {r['blocks']}: {r['contacts_per_block']:.2f} contacts/block, {r['block_steps_per_s']:.3g} block-steps/s, "
            f"{r['ns_per_contact_point']:.1f} ns per contact point, {r['device_bytes_per_block']:.0f} B/block")
    for sc in cfg["coupled"]:
        for s in cfg["coupled_scale"]:
            try:
                r = coupled(sc, dev, cfg["coupled_steps"], s)
            except Exception as e:  # recorded; the other scenes still run
                r = {"scene": sc, "scale": s, "error": str(e)[:200]}
            out["coupled"].append(r)
            log(f"  coupled {sc} x{s:g}: {r.get('fluid_particles')} particles, "
                f"{r.get('particle_steps_per_s', math.nan):.3g} particle-steps/s")
    for scene_name, block, spacing in cfg.get("block_cost", []):
        rows = block_cost(dev, scene_name, block, spacing, cfg["coupled_steps"])
        out["coupled"] += rows
        log(f"  {scene_name} at {spacing:g} m: {rows[0]['fluid_particles']} particles, {block} costs {rows[0]['block_cost']:+.1%}")
    for kind, sizes in (("fluid", cfg["mem_fluid"]), ("blocks", cfg["mem_blocks"])):
        rows = [mem_probe(kind, s, dev) for s in sizes]
        ok = [r for r in rows if "bytes" in r]
        per = None
        if len(ok) >= 2:
            per = (ok[-1]["bytes"] - ok[0]["bytes"]) / max(ok[-1]["count"] - ok[0]["count"], 1)
        how = ("peak RSS of a fresh process above its RSS after importing warp and rockwave (CPU)" if dev == "cpu"
               else "device memory in use after the steps (CUDA)")
        out["memory"].append({"kind": kind, "rows": rows, "bytes_per_item": per,
                              "how": "slope of peak memory between the sizes (removes the fixed cost); " + how})
        item = "particle (fluid + its boundary share)" if kind == "fluid" else "block"
        log(f"  memory {kind}: {per and f'{per:.0f}'} bytes per {item}")
    return out


def mem_probe(kind: str, size: float, dev: str) -> dict:
    cmd = [sys.executable, "-m", "benchmarks", "_mem", kind, str(size), "--device", dev]
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    try:
        return json.loads(p.stdout.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        return {"kind": kind, "size": size, "error": (p.stderr.strip().splitlines() or ["?"])[-1][:200]}


def _vm(key: str) -> int:
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    return 0


def mem_main(kind: str, size: float, dev: str) -> None:
    """One memory probe (run in a fresh process by mem_probe): prints a JSON line."""
    import warp as wp

    wp.config.quiet = True
    import rockwave  # noqa: F401  (its import is part of the baseline)

    wp.init()
    base = None
    base_rss = _vm("VmRSS")
    if dev != "cpu":
        d = wp.get_device(dev)
        base = d.total_memory - d.free_memory
    if kind == "fluid":
        sim = fluid_sim(dev, size)
        count = sim.n_fluid
    else:
        sim = rock_slope_sim(dev, int(size))
        count = sim.blocks.num_blocks
    for _ in range(5):
        sim.step()
    wp.synchronize_device(dev)
    if dev == "cpu":
        used = _vm("VmHWM") - base_rss
    else:
        d = wp.get_device(dev)
        used = d.total_memory - d.free_memory - base
    print(json.dumps({"kind": kind, "size": size, "count": count, "bytes": used, "bytes_per_item": used / max(count, 1)}))
