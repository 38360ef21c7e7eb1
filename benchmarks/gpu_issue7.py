"""Issue 7 measurements in one process (few GPU calls): fluid step variants and per-pass times,
block-step phases, coupled-step split. Writes JSON to --out.

    python -m benchmarks.gpu_issue7 --device cuda:0 --out /tmp/r
    python -m benchmarks.gpu_issue7 --device cpu --parts skin --spacings 0.04 --skins 0 0.05 0.1
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import warp as wp

import rockwave
from benchmarks.common import ROOT, commit, device_name
from rockwave.kernels import sph


@wp.kernel
def hashgrid_neighbour_list(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    H: float,
    cap: int,
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
):
    """The neighbour list from a 27-cell wp.HashGrid query (the solver's list before the cell grid; kept
    here for the side-by-side timing)."""
    i = wp.tid()
    n = count.shape[0]
    xi = x[i]
    c = int(0)
    q = wp.hash_grid_query(grid, xi, H)
    j = int(0)
    while wp.hash_grid_query_next(q, j):
        if j != i and wp.length_sq(xi - x[j]) < H * H:
            if c < cap:
                nbr[c * n + i] = j
            c += 1
    count[i] = c


def _sync_time(fn, device, reps=1):
    wp.synchronize_device(device)
    t = time.perf_counter()
    for _ in range(reps):
        fn()
    wp.synchronize_device(device)
    return (time.perf_counter() - t) / reps


def fluid_sim(device, spacing, cell_ratio=1.0):
    from rockwave.fluid import FluidSolver

    FluidSolver.cell_ratio = cell_ratio
    scene = rockwave.load_scene(ROOT / "scenes" / "dam_break_3d.toml")
    scene.fluid["spacing_m"] = spacing
    scene.output["gauges"] = []
    sim = rockwave.Simulation(scene, device=device)
    FluidSolver.cell_ratio = 1.0
    return sim


def fluid_variants(device, spacing, steps, variants):
    out = []
    for name, cell_ratio, mode in variants:
        sim = fluid_sim(device, spacing, cell_ratio)
        n = sim.n_fluid
        if name.startswith("shuffled"):  # a mixed flow: particle order uncorrelated with position
            fs = sim.fluid_solver
            b = fs._order_buffers()
            b["perm"].assign(np.random.default_rng(0).permutation(n).astype(np.int32))
            with wp.ScopedDevice(device):
                fs._permute(sph.gather_by, b["perm"], (sim.state.x, sim.state.v, sim.state.rho, sim.state.ids))
                fs._in_original_order = False
                fs.build_grid(sim.state)
        if mode == "step":
            for _ in range(20):
                sim.step()
            t = _sync_time(lambda: [sim.step() for _ in range(steps)], device)
        else:
            sim.use_graphs = mode == "graph"
            sim.step_many(30)  # loads kernels, captures the graph
            t = _sync_time(lambda: sim.step_many(steps), device)
        nb = float(np.mean(sim.fluid_solver.neighbour_counts(sim.state)))
        r = dict(variant=name, spacing_m=spacing, particles=n, boundary=sim.fluid.n_boundary, neighbours=nb,
                 cell_ratio=cell_ratio, mode=mode, s_per_step=t / steps, particle_steps_per_s=n * steps / t,
                 graph=bool(getattr(sim, "_graph_key", None)) and not getattr(sim, "_graph_failed", False))
        print(json.dumps(r), flush=True)
        out.append(r)
        del sim
    return out


def fluid_passes(device, spacing, reps=20, sort=True, cell_ratio=1.0):
    """ms per pass of one step (each pass timed alone, reps times, after the particles are sorted)."""
    sim = fluid_sim(device, spacing, cell_ratio)
    sim.step_many(20 if sort else 0)
    for _ in range(5):
        sim.step()
    fs, st, m, dt = sim.fluid_solver, sim.state, sim.fluid, sim._dt_dev
    d = device
    passes = {
        "grid_build": lambda: fs.build_grid(st),
        "cell_build": lambda: fs.build_cells(st),
        "neighbour_list_hashgrid": lambda: wp.launch(
            hashgrid_neighbour_list, dim=m.n_fluid, inputs=[fs.grid.id, st.x, m.support_radius, fs.neighbour_cap],
            outputs=[fs._nbr_count, fs._nbr], device=d),
        "neighbour_list": lambda: fs.build_neighbour_lists(st),
        "skin_check": lambda: fs._list_guard(st),
        "neighbour_list_continuity": lambda: wp.launch(
            sph.neighbour_list_density, dim=m.n_fluid,
            inputs=[fs.cells, *fs._slot_ranges, fs.list_radius, st.x, st.v, m.particle_mass, dt, m.params,
                    sph.DENSITY_CONTINUITY],
            outputs=[fs._nbr_count, fs._nbr, st.drho_dt, st.rho, st.pressure, fs._pr2, fs._x_build], device=d),
        "density_summation_list": lambda: fs.compute_density(st, lists=True),
        "density_continuity_list": lambda: wp.launch(
            sph.particle_density_continuity_list, dim=m.n_fluid,
            inputs=[fs._nbr_count, fs._nbr, st.x, st.v, m.particle_mass, dt, m.params],
            outputs=[st.drho_dt, st.rho, st.pressure, fs._pr2], device=d),
        "density_overflow_check": lambda: fs._density_overflow(st, dt, summation=False),
        "acceleration_list": lambda: wp.launch(
            sph.particle_acceleration_list, dim=m.n_fluid,
            inputs=[fs._nbr_count, fs._nbr, st.x, st.v, st.rho, st.pressure, fs._pr2, m.particle_mass, m.params],
            outputs=[st.accel, st.xsph_dv], device=d, block_dim=fs._block_dim),
        "acceleration_grid_query": lambda: wp.launch(
            sph.particle_acceleration, dim=m.n_fluid,
            inputs=[fs.grid.id, st.x, st.v, st.rho, st.pressure, m.particle_mass, m.params],
            outputs=[st.accel, st.xsph_dv], device=d),
        "integrate": lambda: wp.launch(sph.integrate_particles, dim=m.n_fluid, inputs=[st.accel, st.xsph_dv, dt],
                                       outputs=[st.x, st.v], device=d),
        "reorder": lambda: fs.reorder(st),
        "full_step": lambda: sim.step(),
        "full_step_fused": lambda: (setattr(fs, "fused_density", True), sim.step(), setattr(fs, "fused_density", d == "cpu")),
    }
    g = fs.cells
    r = {"spacing_m": spacing, "particles": m.n_fluid, "sorted": sort, "cell_ratio": cell_ratio,
         "neighbour_skin": fs.neighbour_skin,
         "list_capacity": fs.neighbour_cap, "cell_dims": [g.nx, g.ny, g.nz]}
    with wp.ScopedDevice(d):
        for k, f in passes.items():
            f()
            r[k + "_ms"] = 1e3 * _sync_time(f, d, reps)
    fs.build_cells(st)
    fs.build_neighbour_lists(st)
    cnt = fs._nbr_count.numpy()
    r["list_overflow"] = int((cnt > fs.neighbour_cap).sum())
    r["busy"] = gpu_busy(lambda: [sim.step() for _ in range(20)], d, 20)
    r["neighbours_mean"] = float(cnt.mean())
    r["neighbours_max"] = int(cnt.max())
    print(json.dumps(r), flush=True)
    return r


def fluid_skin(device, spacing, skins, flow_s=0.3, steps=60):
    """ms per step of the dam break after flow_s seconds of flow for each neighbour skin (fraction of H),
    every skin from the same state (plain steps, no reorder chunks), and how many steps a list lasts
    (counted in a second pass with a host read of the build positions per step)."""
    sim = fluid_sim(device, spacing)
    fs, st = sim.fluid_solver, sim.state
    t0 = time.perf_counter()
    sim.advance(flow_s)
    names = ("x", "v", "rho", "pressure", "accel", "xsph_dv", "drho_dt", "ids")
    snap = {k: wp.clone(getattr(st, k)) for k in names}
    out = []
    for skin in skins:
        res = {}
        for phase in ("time", "count"):
            for k in names:
                wp.copy(getattr(st, k), snap[k])
            fs.set_neighbour_skin(skin)
            with wp.ScopedDevice(device):
                sim.step()
                if phase == "time":
                    res["s_per_step"] = _sync_time(lambda: [sim.step() for _ in range(steps)], device) / steps
                else:
                    builds, last = 0, fs._x_build.numpy().copy()
                    for _ in range(steps):
                        sim.step()
                        xb = fs._x_build.numpy()
                        builds += int(not np.array_equal(xb, last))
                        last = xb.copy()
                    res["builds"] = builds
        r = dict(spacing_m=spacing, particles=sim.n_fluid, flow_s=flow_s, skin=skin, steps=steps,
                 ms_per_step=1e3 * res["s_per_step"], list_builds=res["builds"],
                 steps_per_list=steps / max(res["builds"], 1), list_capacity=fs.neighbour_cap, dt_s=sim.dt,
                 advance_s=time.perf_counter() - t0)
        print(json.dumps(r), flush=True)
        out.append(r)
    return out


def fluid_flow(device, spacing, flow_s=0.3, steps=200, skin_check=None):
    """The user's path on a flowing dam break: advance(flow_s) (timed per step), then reorder chunks
    (step_many, CUDA graphs) from the flowing state, their GPU-busy breakdown, and the per-pass times
    there; the adaptive-dt host read (stable_dt) timed alone."""
    from rockwave.fluid import FluidSolver

    old_check = FluidSolver.skin_check
    if skin_check:
        FluidSolver.skin_check = skin_check
    sim = fluid_sim(device, spacing)
    FluidSolver.skin_check = old_check
    fs, st = sim.fluid_solver, sim.state
    sim.advance(0.002)  # kernels loaded, graph captured
    sim.step()  # a plain step loads what the graph path did not (a one-off of 9-13 s in the first process call)
    wp.synchronize_device(device)
    # the slowest host calls of the advance loop (a one-off such as a kernel load or a graph capture
    # shows as one long call; a slow flow as many)
    slow = []
    for name in ("_run_chunk", "step", "_update_dt_target", "_canonical"):
        f = getattr(sim, name)

        def timed(*a, _f=f, _name=name, **k):
            t = time.perf_counter()
            out = _f(*a, **k)
            dt_call = time.perf_counter() - t
            if dt_call > 0.05:
                slow.append(dict(call=_name, step=sim.steps, t_s=sim.time, seconds=dt_call))
            return out
        setattr(sim, name, timed)
    s0, t0 = sim.steps, time.perf_counter()
    segments = []
    seg = 0.01
    while sim.time < flow_s - 1e-9:
        if sim.time > 0.05:
            seg = 0.05
        s1, t1 = sim.steps, time.perf_counter()
        sim.advance(min(seg, flow_s - sim.time))
        wp.synchronize_device(device)
        segments.append(dict(t_end_s=sim.time, steps=sim.steps - s1, ms_per_step=1e3 * (time.perf_counter() - t1) / max(sim.steps - s1, 1)))
    adv = (time.perf_counter() - t0) / max(sim.steps - s0, 1)
    n = sim.n_fluid
    for name in ("_run_chunk", "step", "_update_dt_target", "_canonical"):
        delattr(sim, name)
    sim.step_many(20)
    t = _sync_time(lambda: sim.step_many(steps), device) / steps
    busy = gpu_busy(lambda: sim.step_many(100), device, 100)
    busy_steps = gpu_busy(lambda: [sim.step() for _ in range(30)], device, 30)  # per kernel (no graph)
    builds, last = 0, fs._x_build.numpy().copy()  # list builds over 60 plain steps (a host read per step)
    for _ in range(60):
        sim.step()
        xb = fs._x_build.numpy()
        builds += int(not np.array_equal(xb, last))
        last = xb.copy()
    with wp.ScopedDevice(device):
        sdt = _sync_time(lambda: fs.stable_dt(st, 0.3), device, 10)
        sim.step_many(10)
        cnt = fs._nbr_count.numpy()
    r = dict(spacing_m=spacing, particles=n, skin_check=fs.skin_check if fs._check is not None else "absolute",
             flow_s=flow_s, time_s=sim.time, dt_s=sim.dt,
             advance_ms_per_step=1e3 * adv, advance_steps=sim.steps - s0,
             chunk_ms_per_step=1e3 * t, particle_steps_per_s=n / t, busy=busy, busy_steps=busy_steps,
             segments=segments, slow_calls=slow[:20], list_builds_in_60_steps=builds, stable_dt_ms=1e3 * sdt,
             neighbours_mean=float(cnt.mean()), neighbours_max=int(cnt.max()), list_capacity=fs.neighbour_cap,
             list_overflow=int((cnt > fs.neighbour_cap).sum()), cell_dims=[fs.cells.nx, fs.cells.ny, fs.cells.nz])
    print(json.dumps(r), flush=True)
    return r


def graph_check(device, spacing, steps=400):
    """The same dam break advanced in reorder chunks with CUDA graphs (the list rebuild a conditional node)
    and with plain launches: the largest position difference after `steps` steps (0: identical), and
    whether the graph path was taken."""
    from rockwave.fluid import FluidSolver

    out = {}
    for name, graphs, cond in (("graph", True, True), ("graph_unconditional", True, False), ("plain", False, True),
                               ("plain_again", False, True)):
        FluidSolver.conditional_rebuild = cond
        sim = fluid_sim(device, spacing)
        sim.use_graphs = graphs
        sim.step_many(steps)
        out[name] = (sim.positions(), bool(getattr(sim, "_graph_key", None)) and not getattr(sim, "_graph_failed", False))
    FluidSolver.conditional_rebuild = True
    ref = out["plain"][0]
    r = dict(spacing_m=spacing, steps=steps, graph_used=out["graph"][1],
             max_abs_diff_m={k: float(np.abs(v[0] - ref).max()) for k, v in out.items()})
    print(json.dumps(r), flush=True)
    return r


def blocks_phases(device, count, steps=20, settle=300, joint=0.0002):
    from benchmarks.blocks_bench import run as _  # noqa: F401 (same scene construction)
    scene = rockwave.load_scene(ROOT / "scenes" / "rock_slope_10k.toml")
    nz = 10
    ny = max(1, int(round(math.sqrt(count / nz / 1.6))))
    nx = max(1, int(round(count / nz / ny)))
    pitch = 0.5 + joint  # 0.5 m cubes, `joint` m apart (0: touching, so a packed block has ~6 neighbours in contact)
    scene.blocks[1]["array"]["count"] = [float(nx), float(ny), float(nz)]
    scene.blocks[1]["array"]["spacing_m"] = [pitch] * 3
    scene.blocks[0]["size_m"] = [max(40.0, pitch * nx + 25.0), max(16.0, pitch * ny + 4.0), 1.0]
    scene.blocks[1]["position_m"][1] = -pitch * ny / 2
    t0 = time.perf_counter()
    sim = rockwave.Simulation(scene, device=device)
    setup = time.perf_counter() - t0
    for _ in range(settle):
        sim.step()
    bs, st = sim.block_solver, sim.block_state
    m = sim.blocks
    dt = sim.dt
    times = {"prepare": 0.0, "broad_phase": 0.0, "narrow_phase": 0.0, "integrate": 0.0}
    wp.synchronize_device(device)
    full = _sync_time(lambda: [sim.step() for _ in range(steps)], device) / steps
    touching, points = [], []
    with wp.ScopedDevice(device):
        for _ in range(steps):
            touching.append(int((st.tables[0]["nc"].numpy() > 0).sum()))  # pairs with contact points
            points.append(float(np.mean(st.contact_counts()[1:])))
            times["prepare"] += _sync_time(lambda: bs._prepare(st), device)
            times["broad_phase"] += _sync_time(lambda: bs._broad_phase(), device)
            times["narrow_phase"] += _sync_time(lambda: bs._narrow_phase(st, dt), device)
            times["integrate"] += _sync_time(lambda: bs._integrate(st, dt, sim.time), device)
    r = {"blocks": m.num_blocks, "joint_m": joint, "settle_steps": settle, "pairs_touching": float(np.mean(touching)),
         "touching_neighbours_per_block": 2.0 * float(np.mean(touching)) / m.num_blocks, "pairs": bs.pair_count, "pair_cap": bs.pair_cap, "table_cap": st.table_cap,
         "contact_points_per_block": float(np.mean(points)), "setup_s": setup,
         "step_ms": full * 1e3, "block_steps_per_s": m.num_blocks / full,
         **{k + "_ms": 1e3 * v / steps for k, v in times.items()}}
    print(json.dumps(r), flush=True)
    return r


def gpu_busy(fn, device, steps):
    """GPU time per step by activity name (CUDA event timing of every kernel, memcpy, memset) against
    the wall time per step: their difference is the GPU left idle (host reads, launch latency)."""
    if not wp.get_device(device).is_cuda:
        return {}
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    fn()
    res = wp.timing_end()
    wall = (time.perf_counter() - t0) / steps
    by = {}
    for r in res:
        by[r.name] = by.get(r.name, 0.0) + r.elapsed / steps
    top = dict(sorted(by.items(), key=lambda kv: -kv[1])[:12])
    return {"wall_ms_timed": 1e3 * wall, "gpu_busy_ms": sum(by.values()), "launches_per_step": len(res) / steps,
            "top_ms": top}


def coupled_split(device, scale, steps=50, without=()):
    """The sliding wedge scaled to `scale` x the particles: step-by-step and chunked ms per step, GPU
    busy breakdowns of both, per-part times; `without` names blocks left out (("wedge",): the same
    fluid in the same block tank without the block)."""
    scene = rockwave.load_scene(ROOT / "scenes" / "sliding_wedge.toml")
    scene.fluid["spacing_m"] = scene.fluid.spacing_m / scale ** (1.0 / scene.dim)
    scene.blocks[:] = [b for b in scene.blocks if b["name"] not in without]
    sim = rockwave.Simulation(scene, device=device)
    for _ in range(5):
        sim.step()
    full = _sync_time(lambda: [sim.step() for _ in range(steps)], device) / steps
    sim.step_many(20)  # loads the reorder kernels (a one-off of ~24 s in the first call of a process)
    chunked = _sync_time(lambda: sim.step_many(steps), device) / steps  # with reorder chunks
    c, st, bst, fs = sim.coupling, sim.state, sim.block_state, sim.fluid_solver
    from rockwave.kernels import coupling as CK

    nf = sim.n_fluid
    from rockwave.solver import TimeStep

    ts = TimeStep(sim.dt, sim.time, sim._dt_dev)
    with wp.ScopedDevice(device):
        parts = {
            "coupling_compute": lambda: c.compute(st, bst, ts),
            "coupling_apply": lambda: c.apply(st, ts),
            "fluid_bounds": lambda: (wp.copy(c.bounds, c._bounds_init),
                                     wp.launch(CK.fluid_bounds, dim=min(nf, 16384), inputs=[st.x, nf, min(nf, 16384)],
                                               outputs=[c.bounds])),
            "broad_phase": lambda: c._broad_phase(st, bst),
            "fluid_step": lambda: fs.step(st, sim._dt_dev),
            "block_step": lambda: sim.block_solver.step(bst, ts),
        }
        r = {"scale": scale, "without": list(without), "particles": nf, "blocks": sim.blocks.num_blocks, "step_ms": full * 1e3,
             "chunked_step_ms": chunked * 1e3, "particle_steps_per_s": nf / full, "particle_steps_per_s_chunked": nf / chunked}
        r["busy"] = gpu_busy(lambda: [sim.step() for _ in range(20)], device, 20)
        r["busy_chunked"] = gpu_busy(lambda: sim.step_many(20), device, 20)
        for k, f in parts.items():
            if k == "block_step" and sim.block_solver is None:
                continue
            f()
            r[k + "_ms"] = 1e3 * _sync_time(f, device, 10)
    print(json.dumps(r), flush=True)
    return r


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--out", default=".")
    ap.add_argument("--parts", nargs="+", default=["fluid", "passes", "blocks", "coupled"])
    ap.add_argument("--spacings", type=float, nargs="+", default=[0.02, 0.0085, 0.0068])
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--block-counts", type=int, nargs="+", default=[10000, 100000])
    ap.add_argument("--coupled-scale", type=float, default=41.0)
    ap.add_argument("--cell-ratios", type=float, nargs="+", default=[1.0, 0.5])
    ap.add_argument("--skins", type=float, nargs="+", default=[0.0, 0.05, 0.1, 0.15])
    ap.add_argument("--flow-s", type=float, default=0.3)
    ap.add_argument("--joints", type=float, nargs="+", default=[0.0002], help="gaps between the blocks [m]")
    ap.add_argument("--settle", type=int, default=300, help="block steps before the timing")
    ap.add_argument("--skin-checks", nargs="+", default=["relative", "absolute"], help="flow part: FluidSolver.skin_check values")
    a = ap.parse_args(argv)
    wp.config.quiet = True
    res = {"device_name": device_name(a.device), "commit": commit(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    t0 = time.perf_counter()
    wp.init()
    if "fluid" in a.parts:
        v = [("step_unsorted", 1.0, "step"), ("chunks_sorted", 1.0, "plain"), ("graph_sorted", 1.0, "graph")]
        v += [(f"graph_sorted_cell{r:g}", r, "graph") for r in a.cell_ratios if r != 1.0]
        v += [("shuffled_step_unsorted", 1.0, "step"), ("shuffled_graph_sorted", 1.0, "graph")]
        res["fluid"] = [r for s in a.spacings for r in fluid_variants(a.device, s, a.steps, v)]
    if "passes" in a.parts:
        res["passes"] = [fluid_passes(a.device, a.spacings[-1], sort=False), fluid_passes(a.device, a.spacings[-1])]
        res["passes"] += [fluid_passes(a.device, a.spacings[-1], cell_ratio=r) for r in a.cell_ratios if r != 1.0]
    if "skin" in a.parts:
        res["skin"] = fluid_skin(a.device, a.spacings[-1], a.skins, a.flow_s, min(a.steps, 60))
    if "graphcheck" in a.parts:
        res["graphcheck"] = [graph_check(a.device, s) for s in a.spacings]
    if "flow" in a.parts:
        res["flow"] = [fluid_flow(a.device, s, a.flow_s, skin_check=k) for s in a.spacings for k in a.skin_checks]
    if "blocks" in a.parts:
        res["blocks"] = [blocks_phases(a.device, c, settle=a.settle, joint=j) for c in a.block_counts for j in a.joints]
    if "coupled" in a.parts:
        res["coupled"] = [coupled_split(a.device, a.coupled_scale), coupled_split(a.device, a.coupled_scale, without=("wedge",))]
    res["wall_s"] = time.perf_counter() - t0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"issue7-{'-'.join(a.parts)}.json").write_text(json.dumps(res, indent=2))
    print("wall", res["wall_s"])


if __name__ == "__main__":
    main()
