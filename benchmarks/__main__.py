"""One command for the benchmark suite (README, "Benchmarks"):

    python -m benchmarks run --device cpu --suite quick       # 2-core CPU, < 15 minutes
    python -m benchmarks run --device cuda:0 --suite full     # all parts in one process (~17 min on an H100)

Writes benchmarks/results/<date>-<device>.json (every run's record), PNG charts
benchmarks/results/<date>-<device>-*.png, and prints a summary table. Parts: accuracy against speed
(2D dam break vs Martin & Moyce, SPHERIC Test 2), stability maps (fluid dt x c0, blocks dt x k_n),
scaling (benchmarks/fluid_bench.py, blocks_bench.py, coupled_bench.py) with peak memory, the
peers (SPlisHSPlasH on the CPU, Warp's example_sph.py), and the piston wave maker against linear theory
as the resolution grows (benchmarks/wave_maker_accuracy.py; the 10% check of issue 4 at full size). ``--only accuracy stability ...`` picks parts;
a run of some parts writes <date>-<device>-<suite>-<parts>.json unless --out says otherwise.

The JSON is rewritten (temp file + rename) after every finished part, so a run killed part-way keeps
the parts that finished (``parts_done``; ``parts_pending`` lists the rest). The full suite does not fit
one 10-minute call on an H100 (accuracy ~385 s, stability ~336 s, scaling + peers ~305 s): on a GPU
lease run it as four calls, then merge (merge checks the suite and device agree, redraws the charts
and prints the summary of the whole):

    python -m benchmarks run --device cuda:0 --suite full --only accuracy    # call 1
    python -m benchmarks run --device cuda:0 --suite full --only stability   # call 2
    python -m benchmarks run --device cuda:0 --suite full --only scaling peers   # call 3
    python -m benchmarks run --device cuda:0 --suite full --only wave_maker      # call 4 (~4 min)
    python -m benchmarks merge benchmarks/results/<date>-cuda0-full-*.json --out benchmarks/results/<date>-cuda0-full.json

    python -m benchmarks charts FILE.json      # redraw the PNG charts of any result JSON (next to it)
    python -m benchmarks markdown FILE.json    # a RESULTS.md section from any result JSON
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import subprocess
import sys
import time
import traceback

import numpy as np

from benchmarks import harness as H
from benchmarks.common import RESULTS, ROOT, commit, device_name

A = H.A_MM
SUITES = {
    "quick": dict(
        dam_res=[10, 14, 20], dam_variants=list(H.VARIANTS), dam_t_end=0.2,
        spheric=[(0.06, v) for v in ("tait", "linear", "fixed_dt", "laplacian")] + [(0.045, "tait")], spheric_t_end=0.6,
        stab_res=10, stab_t_end=0.12, stab_mult=[0.5, 1, 2, 4, 8, 16], stab_c0=[5, 10, 20, 40, 80],
        stab_methods=["tait", "linear", "ghost"],
        blk_k=[1e6, 1e7, 1e8, 1e9, 1e10], blk_mult=[0.25, 0.5, 1.0, 2.0], blk_t_end=0.3,
        fluid_spacings=[0.06, 0.045], fluid_steps=20, block_counts=[100, 400], block_steps=20, block_settle=100,
        coupled=["wave_maker_small.toml", "sliding_wedge_small.toml"], coupled_steps=5, coupled_scale=[1.0],
        mem_fluid=[0.06, 0.045], mem_blocks=[100, 400],
        splash_res=10, warp_example_spacing=0.06, wave_layers=[16],
    ),
    "full": dict(
        dam_res=[10, 20, 40, 80], dam_variants=list(H.VARIANTS), dam_t_end=0.2,
        spheric=[(s, v) for s in (0.03, 0.02) for v in ("tait", "linear", "fixed_dt", "laplacian", "xsph")]
        + [(0.015, "tait"), (0.04, "ghost")], spheric_t_end=1.0,
        stab_res=20, stab_t_end=0.12, stab_mult=[0.5, 1, 2, 4, 8, 16], stab_c0=[5, 10, 20, 40, 80],
        stab_methods=["tait", "linear", "ghost"],
        blk_k=[1e6, 1e7, 1e8, 1e9, 1e10], blk_mult=[0.25, 0.5, 1.0, 2.0], blk_t_end=0.3,
        fluid_spacings=[0.04, 0.02, 0.015, 0.01], fluid_steps=100, block_counts=[1000, 10000, 100000], block_steps=100,
        block_settle=300, coupled=["wave_maker.toml", "sliding_wedge.toml"], coupled_steps=50, coupled_scale=[1.0, 2.0],
        mem_fluid=[0.02, 0.01], mem_blocks=[1000, 10000],
        splash_res=10, warp_example_spacing=0.02, wave_layers=[16, 32, 64, 128],
    ),
}


def log(msg: str) -> None:
    print(msg, flush=True)


def jdefault(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


# ------------------------------------------------------------------------------------ parts ----
def part_accuracy(dev: str, cfg: dict) -> dict:
    out = {"dam_break_2d": [], "spheric": []}
    for n in cfg["dam_res"]:
        for v in cfg["dam_variants"]:
            if n == cfg["dam_res"][0]:  # warm-up: kernel loads out of the timing
                H.run_dam_break(dev, A / n, H.VARIANTS[v], 0.002)
            r = H.run_dam_break(dev, A / n, H.VARIANTS[v], cfg["dam_t_end"])
            r.update(variant=v, resolution=f"a/{n}")
            r["class"], r["why"] = H.classify(r)
            out["dam_break_2d"].append(r)
            log(f"  dam_break_2d a/{n:<3d} {v:10s} n={r.get('particles', 0):6d} error={r.get('error', math.nan):.3f} "
                f"(front {r.get('front_rms', math.nan):.3f}, height {r.get('height_rms', math.nan):.3f}) "
                f"{r.get('wall_per_sim_s', math.nan):8.2f} s/sim-s  {r['class']}")
    warmed = set()
    for s, v in cfg["spheric"]:
        if v not in warmed:
            H.run_spheric(dev, max(s, 0.06), H.VARIANTS[v], 0.01)
            warmed.add(v)
        r = H.run_spheric(dev, s, H.VARIANTS[v], cfg["spheric_t_end"])
        r.update(variant=v, resolution=f"{s:g} m")
        r["class"], r["why"] = H.classify(r)
        out["spheric"].append(r)
        log(f"  spheric {s:6.3f} m {v:10s} n={r.get('particles', 0):7d} error={r.get('error', math.nan):.3f} "
            f"(h {r.get('h_rms', math.nan):.3f}, P1 {r.get('p_rms', math.nan):.3f}) {r.get('wall_per_sim_s', math.nan):8.2f} s/sim-s  {r['class']}")
    for case, rows in list(out.items()):
        pts = [(r.get("wall_per_sim_s", math.nan), r.get("error", math.nan)) for r in rows]
        front = H.pareto_front(pts)
        for i, r in enumerate(rows):
            r["pareto"] = i in front
        out[f"{case}_recommendation"] = recommend(rows, front)
    return out


def part_wave_maker(dev: str, cfg: dict) -> dict:
    """Issue 4's piston check at growing resolution (benchmarks/wave_maker_accuracy.py): first-harmonic
    wave height at gauge_1 against linear wavemaker theory, class "within 10%" or "outside 10%"."""
    from benchmarks import wave_maker_accuracy as W

    rows = []
    for n in cfg["wave_layers"]:
        r = W.run(dev, n)
        r["class"] = "within 10%" if abs(r["error_gauge1"]) <= 0.10 else "outside 10%"
        rows.append(r)
        log(f"  wave maker {n:4d} layers/depth n={r['particles']:7d} gauge_1 {r['error_gauge1']:+.1%} gauge_2 "
            f"{r['error_gauge2']:+.1%} ({r['wall_s']:.0f} s)  {r['class']}")
    return {"piston": rows}


def recommend(rows: list, front: list[int]) -> list[str]:
    """One line per Pareto point: the setting to pick for a budget of wall seconds per simulated second."""
    lines = []
    for k, i in enumerate(front):
        r = rows[i]
        nxt = rows[front[k + 1]]["wall_per_sim_s"] if k + 1 < len(front) else None
        span = f"{r['wall_per_sim_s']:.3g} s" + (f" to {nxt:.3g} s" if nxt else " or more")
        lines.append(f"budget {span} of wall time per simulated second: {r['variant']} at {r['resolution']} "
                     f"({r['particles']} particles, error {r['error']:.3f})")
    return lines


def part_stability(dev: str, cfg: dict) -> dict:
    out = {"fluid": [], "blocks": []}
    n = cfg["stab_res"]
    for m in cfg["stab_methods"]:
        H.run_dam_break(dev, A / n, H.VARIANTS[m], 0.002)
        for c0 in cfg["stab_c0"]:
            for k in cfg["stab_mult"]:
                r = H.run_dam_break(dev, A / n, H.VARIANTS[m], cfg["stab_t_end"], dt_multiple=k, c0=c0)
                r.update(method=m, c0=c0, dt_multiple=k)
                r["class"], r["why"] = H.classify(r)
                out["fluid"].append(r)
        row = " ".join(f"{r['class'][:4]}" for r in out["fluid"] if r["method"] == m)
        log(f"  fluid stability {m:8s} ({len(cfg['stab_c0'])} c0 x {len(cfg['stab_mult'])} dt): {row}")
    for kn in cfg["blk_k"]:
        for k in cfg["blk_mult"]:
            r = H.run_block_stack(dev, kn, k, cfg["blk_t_end"])
            r["class"], r["why"] = H.classify(r)
            out["blocks"].append(r)
    log("  block stability: " + " ".join(r["class"][:4] for r in out["blocks"]))
    return out


def part_scaling(dev: str, cfg: dict) -> dict:
    from benchmarks import blocks_bench, coupled_bench, fluid_bench

    out = {"fluid": [], "blocks": [], "coupled": [], "memory": []}
    for s in cfg["fluid_spacings"]:
        r = fluid_bench.run(dev, s, cfg["fluid_steps"], warmup=5)
        out["fluid"].append(r)
        log(f"  fluid {s:g} m: {r['particles']} particles, {r['neighbours']:.1f} nbrs, {r['particle_steps_per_s']:.3g} particle-steps/s")
    for c in cfg["block_counts"]:
        r = blocks_bench.run(dev, c, cfg["block_steps"], cfg["block_settle"])
        out["blocks"].append(r)
        log(f"  blocks {r['blocks']}: {r['contacts_per_block']:.2f} contacts/block, {r['block_steps_per_s']:.3g} block-steps/s")
    for sc in cfg["coupled"]:
        for s in cfg["coupled_scale"]:
            try:
                r = coupled_bench.bench(sc, dev, cfg["coupled_steps"], s)
            except Exception as e:
                r = {"scene": sc, "error": str(e)[:200]}
            out["coupled"].append(r)
            log(f"  coupled {sc} x{s:g}: {r.get('fluid_particles')} particles, {r.get('particle_steps_per_s', math.nan):.3g} particle-steps/s")
    for kind, sizes in (("fluid", cfg["mem_fluid"]), ("blocks", cfg["mem_blocks"])):
        rows = [mem_probe(kind, s, dev) for s in sizes]
        ok = [r for r in rows if "bytes" in r]
        per = None
        if len(ok) >= 2:
            per = (ok[-1]["bytes"] - ok[0]["bytes"]) / max(ok[-1]["count"] - ok[0]["count"], 1)
        out["memory"].append({"kind": kind, "rows": rows, "bytes_per_item": per,
                              "how": "slope of peak memory between the sizes (removes the fixed cost); "
                                     + ("peak RSS of a fresh process above its RSS after importing warp and rockwave (CPU)" if dev == "cpu" else "device memory in use after the steps (CUDA)")})
        log(f"  memory {kind}: {per and f'{per:.0f}'} bytes per {'particle (fluid + its boundary share)' if kind == 'fluid' else 'block'}")
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


def _mem_main(kind: str, size: float, dev: str) -> None:
    import resource

    import warp as wp

    wp.config.quiet = True
    import rockwave

    wp.init()
    base = None
    base_rss = _vm("VmRSS")
    if dev != "cpu":
        d = wp.get_device(dev)
        base = d.total_memory - d.free_memory
    if kind == "fluid":
        scene = rockwave.load_scene(ROOT / "scenes" / "dam_break_3d.toml")
        scene.fluid["spacing_m"] = size
        scene.output["gauges"] = []
        sim = rockwave.Simulation(scene, device=dev)
        count = sim.n_fluid
    else:
        from benchmarks import blocks_bench

        scene = rockwave.load_scene(ROOT / "scenes" / "rock_slope_10k.toml")
        nz = 10
        ny = max(1, int(round(math.sqrt(size / nz / 1.6))))
        nx = max(1, int(round(size / nz / ny)))
        scene.blocks[1]["array"]["count"] = [float(nx), float(ny), float(nz)]
        scene.blocks[0]["size_m"] = [max(40.0, 0.5002 * nx + 25.0), max(16.0, 0.5002 * ny + 4.0), 1.0]
        scene.blocks[1]["position_m"][1] = -0.5002 * ny / 2
        sim = rockwave.Simulation(scene, device=dev)
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


def part_peers(dev: str, cfg: dict) -> dict:
    from benchmarks.peers import splash, warp_example

    out = {}
    try:
        out["splash"] = splash.compare(cfg["splash_res"], device=dev)  # runs on the CPU whatever the suite's device
        log("  " + summary({"peers": {"splash": out["splash"]}, "suite": "", "device": dev, "device_name": "", "date": "", "commit": ""})
            .split("\n")[3].strip())
    except Exception as e:
        out["splash"] = {"error": f"{type(e).__name__}: {e}"[:300], "trace": traceback.format_exc()[-800:]}
        log(f"  SPlisHSPlasH comparison failed: {out['splash']['error']}")
    try:
        out["warp_example"] = warp_example.compare(cfg["warp_example_spacing"], dev)
        w = out["warp_example"]
        log(f"  Warp example_sph at {w['warp_example']['particles']} particles ({w['warp_example']['neighbours']:.1f} nbrs): "
            f"{w['warp_example']['particle_steps_per_s']:.3g} particle-steps/s; rockwave {w['rockwave']['particle_steps_per_s']:.3g} "
            f"({w['rockwave']['neighbours']:.1f} nbrs); ratio {w['throughput_ratio']:.2f}")
    except Exception as e:
        out["warp_example"] = {"error": f"{type(e).__name__}: {e}"[:300]}
        log(f"  Warp example failed: {out['warp_example']['error']}")
    return out


# ----------------------------------------------------------------------------------- charts ----
CLASS_COLOURS = {"stable": "#2ca02c", "inaccurate": "#ff7f0e", "blown_up": "#d62728", "refused": "#7f7f7f"}


def charts(res: dict, stem: str, out_dir=None) -> list[str]:
    """PNG charts of the parts present in ``res``, written as <out_dir>/<stem>-<chart>.png (default
    benchmarks/results); returns their paths (relative to the repository where they lie inside it)."""
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []

    out_dir = Path(out_dir) if out_dir is not None else RESULTS
    out_dir.mkdir(parents=True, exist_ok=True)

    def save(fig, name):
        p = out_dir / f"{stem}-{name}.png"
        tmp = p.with_name(p.stem + ".tmp.png")
        fig.savefig(tmp, dpi=80, bbox_inches="tight")
        plt.close(fig)
        os.replace(tmp, p)
        try:
            paths.append(str(p.resolve().relative_to(ROOT)))
        except ValueError:
            paths.append(str(p))

    acc = res.get("accuracy")
    if acc:
        for case, title in (("dam_break_2d", "2D dam break vs Martin & Moyce"), ("spheric", "SPHERIC Test 2 (H1-H4, P1)")):
            rows = [r for r in acc[case] if math.isfinite(r.get("error", math.nan))]
            if not rows:
                continue
            fig, ax = plt.subplots(figsize=(7, 4.5))
            variants = sorted({r["variant"] for r in rows})
            marks = "osD^v<>p*"
            for j, v in enumerate(variants):
                rr = [r for r in rows if r["variant"] == v]
                ax.scatter([r["wall_per_sim_s"] for r in rr], [r["error"] for r in rr], marker=marks[j % len(marks)], label=v)
                for r in rr:
                    ax.annotate(r["resolution"], (r["wall_per_sim_s"], r["error"]), fontsize=6, xytext=(3, 2), textcoords="offset points")
            pf = sorted([r for r in rows if r.get("pareto")], key=lambda r: r["wall_per_sim_s"])
            ax.step([r["wall_per_sim_s"] for r in pf], [r["error"] for r in pf], where="post", color="k", lw=1, label="Pareto front")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("wall-clock seconds per simulated second")
            ax.set_ylabel("error (README, Benchmarks)")
            ax.set_title(f"{title} - {res['device']}")
            ax.legend(fontsize=7)
            ax.grid(True, which="both", alpha=0.3)
            save(fig, f"accuracy-{case}")
    st = res.get("stability")
    if st:
        methods = sorted({r["method"] for r in st["fluid"]})
        fig, axs = plt.subplots(1, len(methods) + 1, figsize=(4 * (len(methods) + 1), 3.6))
        for ax, m in zip(axs, methods):
            rr = [r for r in st["fluid"] if r["method"] == m]
            _map(ax, rr, "dt_multiple", "c0", f"fluid {m}", "dt / CFL step", "c0 [m/s]")
        _map(axs[-1], st["blocks"], "dt_multiple", "k_n", "blocks (3-cube stack)", "dt / critical DDA step", "k_n [N/m]")
        handles = [plt.Line2D([], [], marker="s", ls="", color=c, label=k) for k, c in CLASS_COLOURS.items()]
        fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=8)
        fig.tight_layout(rect=(0, 0.08, 1, 1))
        save(fig, "stability")
    sc = res.get("scaling")
    if sc:
        fig, axs = plt.subplots(1, 2, figsize=(9, 3.6))
        f = sc["fluid"]
        axs[0].plot([r["particles"] for r in f], [r["particle_steps_per_s"] for r in f], "o-", label="fluid (3D dam break)")
        cp = [r for r in sc["coupled"] if "particle_steps_per_s" in r]
        axs[0].plot([r["fluid_particles"] for r in cp], [r["particle_steps_per_s"] for r in cp], "s", label="coupled scenes")
        for r in f:
            axs[0].annotate(f"{r['neighbours']:.0f} nbrs", (r["particles"], r["particle_steps_per_s"]), fontsize=7)
        axs[0].set_xscale("log")
        axs[0].set_xlabel("fluid particles")
        axs[0].set_ylabel("particle-steps/s")
        axs[0].legend(fontsize=7)
        b = sc["blocks"]
        axs[1].plot([r["blocks"] for r in b], [r["block_steps_per_s"] for r in b], "o-")
        for r in b:
            axs[1].annotate(f"{r['contacts_per_block']:.1f} contacts", (r["blocks"], r["block_steps_per_s"]), fontsize=7)
        axs[1].set_xscale("log")
        axs[1].set_xlabel("blocks")
        axs[1].set_ylabel("block-steps/s")
        for ax in axs:
            ax.grid(True, alpha=0.3)
        fig.suptitle(f"scaling - {res['device']}")
        fig.tight_layout()
        save(fig, "scaling")
    return paths


def _map(ax, rows, xk, yk, title, xl, yl):
    xs = sorted({r[xk] for r in rows})
    ys = sorted({r[yk] for r in rows})
    for r in rows:
        ax.add_patch(__import__("matplotlib.patches", fromlist=["Rectangle"]).Rectangle(
            (xs.index(r[xk]) - 0.5, ys.index(r[yk]) - 0.5), 1, 1, color=CLASS_COLOURS[r["class"]]))
    ax.set_xlim(-0.5, len(xs) - 0.5)
    ax.set_ylim(-0.5, len(ys) - 0.5)
    ax.set_xticks(range(len(xs)), [f"{x:g}" for x in xs])
    ax.set_yticks(range(len(ys)), [f"{y:g}" for y in ys])
    ax.set_title(title, fontsize=9)
    ax.set_xlabel(xl)
    ax.set_ylabel(yl)


# ---------------------------------------------------------------------------------- summary ----
def _commits(res: dict) -> str:
    cs = [m.get("commit") for m in res.get("merged_from", [])] or [res.get("commit")]
    return ", ".join(dict.fromkeys(c for c in cs if c)) or "unknown"


def _machine_note(res: dict) -> str:
    """What the timings are of: a shared CPU (upper bounds) or a GPU (the load average is the host's)."""
    if str(res.get("device", "cpu")).startswith("cpu"):
        return "other processes share the CPU's cores, so timings are upper bounds"
    return f"timings are of the GPU ({res.get('device_name')}); the load average is the host CPU's"


def summary(res: dict) -> str:
    L = [f"# rockwave benchmarks: suite {res['suite']}, {res['device']} ({res['device_name']}), {res['date']}, commit {_commits(res)}"]
    if res.get("parts_pending"):
        L.append(f"(incomplete: parts done {', '.join(res.get('parts_done', [])) or 'none'}; not run or not finished: {', '.join(res['parts_pending'])})")
    acc = res.get("accuracy")
    if acc:
        for case in ("dam_break_2d", "spheric"):
            L.append(f"\n{case}: error vs wall s per simulated s (* = Pareto front)")
            L.append(f"{'variant':10s} {'resolution':>10s} {'particles':>9s} {'error':>7s} {'s/sim-s':>9s}  class")
            for r in acc[case]:
                L.append(f"{r['variant']:10s} {r['resolution']:>10s} {r.get('particles', 0):9d} {r.get('error', math.nan):7.3f} "
                         f"{r.get('wall_per_sim_s', math.nan):9.2f}{' *' if r.get('pareto') else '  '} {r['class']}")
            for line in acc.get(f"{case}_recommendation", []):
                L.append("  -> " + line)
    st = res.get("stability")
    if st:
        L.append("\nstability (largest stable dt multiple per c0 / k_n)")
        for m in sorted({r["method"] for r in st["fluid"]}):
            parts = []
            for c0 in sorted({r["c0"] for r in st["fluid"]}):
                ok = [r["dt_multiple"] for r in st["fluid"] if r["method"] == m and r["c0"] == c0 and r["class"] == "stable"]
                parts.append(f"c0 {c0:g}: {max(ok):g}" if ok else f"c0 {c0:g}: none")
            L.append(f"  fluid {m:8s} " + ", ".join(parts))
        for kn in sorted({r["k_n"] for r in st["blocks"]}):
            cls = {r["dt_multiple"]: r["class"] for r in st["blocks"] if r["k_n"] == kn}
            L.append(f"  blocks k_n {kn:.0e}: " + ", ".join(f"{k:g}x {c}" for k, c in sorted(cls.items())))
    sc = res.get("scaling")
    if sc:
        L.append("\nscaling")
        for r in sc["fluid"]:
            L.append(f"  fluid {r['particles']:8d} particles {r['neighbours']:5.1f} nbrs {r['particle_steps_per_s']:.3g} particle-steps/s")
        for r in sc["blocks"]:
            L.append(f"  blocks {r['blocks']:7d} {r['contacts_per_block']:5.2f} contacts/block {r['block_steps_per_s']:.3g} block-steps/s")
        for r in sc["coupled"]:
            L.append(f"  coupled {r.get('scene')}: {r.get('fluid_particles')} particles {r.get('particle_steps_per_s', math.nan):.3g} particle-steps/s")
        for m in sc["memory"]:
            L.append(f"  memory {m['kind']}: {m['bytes_per_item'] and round(m['bytes_per_item'])} bytes per {'particle' if m['kind'] == 'fluid' else 'block'}")
    pe = res.get("peers")
    if pe:
        L.append("\npeers")
        s = pe.get("splash", {})
        sp, rw, rc = s.get("splash", {}), s.get("rockwave", {}), s.get("rockwave_continuity", {})
        if "particles" in sp and "particles" in rw:
            L.append(f"  SPlisHSPlasH WCSPH {sp['particles']} particles {sp['s_per_step'] * 1e3:.2f} ms/step, front error {sp['front_rms']:.3f} "
                     f"(bias {sp['front_bias']:+.3f}); rockwave (same EOS, summation density) {rw['particles']} particles "
                     f"{rw['s_per_step'] * 1e3:.2f} ms/step, front error {rw['front_rms']:.3f} (bias {rw['front_bias']:+.3f}); "
                     f"ratio {s.get('throughput_ratio', math.nan):.2f}")
            if "particles" in rc:
                L.append(f"  rockwave (continuity density, its default) {rc['s_per_step'] * 1e3:.2f} ms/step, front error {rc['front_rms']:.3f} "
                         f"(bias {rc['front_bias']:+.3f}); ratio {s.get('throughput_ratio_continuity', math.nan):.2f}")
        else:
            why = sp.get("skipped") or sp.get("error") or s.get("error") or "not run"
            L.append(f"  SPlisHSPlasH: {why}" + (f"; rockwave front error {rw['front_rms']:.3f}" if "front_rms" in rw else "")
                     + (f"; rockwave: {rw['error']}" if "error" in rw else ""))
        w = pe.get("warp_example", {})
        if "throughput_ratio" in w:
            L.append(f"  Warp example_sph {w['warp_example']['particles']} particles {w['warp_example']['neighbours']:.1f} nbrs "
                     f"{w['warp_example']['particle_steps_per_s']:.3g} particle-steps/s; rockwave {w['rockwave']['neighbours']:.1f} nbrs "
                     f"{w['rockwave']['particle_steps_per_s']:.3g}; ratio {w['throughput_ratio']:.2f}")
        else:
            L.append(f"  Warp example: {w.get('error')}")
    wm = res.get("wave_maker")
    if wm:
        L.append("\npiston wave maker vs linear theory (wave_maker_small, gauge_1 at 0.35 m)")
        for r in wm["piston"]:
            L.append(f"  {r['layers']:4d} layers/depth {r['particles']:7d} particles gauge_1 {r['error_gauge1']:+.1%} "
                     f"gauge_2 {r['error_gauge2']:+.1%}  {r['class']}")
    L.append(f"\nwall time of the suite: {res.get('suite_wall_s', math.nan):.0f} s"
             + (" (" + ", ".join(f"{k} {v:.0f} s" for k, v in res["part_wall_s"].items()) + ")" if res.get("part_wall_s") else ""))
    return "\n".join(L)


def markdown(res: dict) -> str:
    """A benchmarks/RESULTS.md section from a result JSON (python -m benchmarks markdown FILE)."""
    L = [f"## Benchmark suite `{res['suite']}` ({res['device']}) - python -m benchmarks run", "",
         f"Machine: {res['device_name']}, warp {res['warp']}. Date: {res['date']} {res.get('time_utc', '')} UTC. "
         f"Commit: {_commits(res)}. Load average at start: {', '.join(f'{x:.1f}' for x in res['load_average'])} "
         f"({_machine_note(res)}). Suite wall time {res.get('suite_wall_s', math.nan):.0f} s. "
         f"Record: `{res.get('record') or 'benchmarks/results/' + res['date'] + '-' + res['device'].replace(':', '') + '.json'}`.", ""]
    for m in res.get("merged_from", []):
        L.insert(-1, f"Merged part file `{m['file']}`: {', '.join(m['parts'])}; commit {m.get('commit')}, {m.get('date')} "
                     f"{m.get('time_utc', '')} UTC, {m.get('suite_wall_s', math.nan):.0f} s.")
    if res.get("parts_pending"):
        L.insert(-1, f"Incomplete: not run or not finished: {', '.join(res['parts_pending'])}.")
    acc = res.get("accuracy")
    if acc:
        for case, title in (("dam_break_2d", "2D dam break vs Martin & Moyce (t <= 0.2 s)"), ("spheric", "SPHERIC Test 2")):
            L += [f"**{title}** (* = Pareto front)", "", "| variant | resolution | particles | error | parts | wall s / sim s | class |",
                  "|---|---|---|---|---|---|---|"]
            for r in acc[case]:
                parts = (f"front {r.get('front_rms', math.nan):.3f} (bias {r.get('front_bias', math.nan):+.3f}), height {r.get('height_rms', math.nan):.3f}"
                         if case == "dam_break_2d" else f"H {r.get('h_rms', math.nan):.3f}, P1 {r.get('p_rms', math.nan):.3f}")
                L.append(f"| {r['variant']} | {r['resolution']} | {r.get('particles', 0)} | {r.get('error', math.nan):.3f}{' *' if r.get('pareto') else ''} "
                         f"| {parts} | {r.get('wall_per_sim_s', math.nan):.1f} | {r['class']} |")
            L += [""] + [f"- {x}" for x in acc.get(f"{case}_recommendation", [])] + [""]
    text = summary(res).split("\n")
    wm = res.get("wave_maker")
    if wm:
        L += ["**Piston wave maker vs linear theory** (wave_maker_small, first-harmonic height at gauge_1, 0.35 m)", "",
              "| layers per depth | particles | gauge_1 | gauge_2 | wall s | class |", "|---|---|---|---|---|---|"]
        L += [f"| {r['layers']} | {r['particles']} | {r['error_gauge1']:+.1%} | {r['error_gauge2']:+.1%} | {r['wall_s']:.0f} | {r['class']} |"
              for r in wm["piston"]] + [""]
    for head in ("stability", "scaling", "peers"):
        if head in res:
            i = next((k for k, l in enumerate(text) if l.startswith(head)), None)
            if i is not None:
                block = []
                for l in text[i:]:
                    if not l.strip():
                        break
                    block.append(l)
                L += [f"**{block[0]}**", "", "```"] + block[1:] + ["```", ""]
    return "\n".join(L)


def strip_series(res: dict) -> dict:
    """The JSON keeps SPHERIC gauge series only for the finest tait run (to keep the file small)."""
    acc = res.get("accuracy")
    if acc:
        rows = [r for r in acc["spheric"] if "series" in r]
        keep = min((r for r in rows if r["variant"] == "tait"), key=lambda r: r["spacing_m"], default=None)
        for r in rows:
            if r is not keep:
                r.pop("series", None)
    return res


PARTS = ["accuracy", "stability", "scaling", "peers", "wave_maker"]
HEADER = ("suite", "device", "device_name", "date", "time_utc", "commit", "warp", "load_average", "bounds", "config")


def write_json(res: dict, path) -> None:
    """Write the result JSON atomically (temp file in the same folder, then rename): a run killed while
    writing leaves the previous complete file, never a truncated one."""
    import copy
    from pathlib import Path

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w") as f:
        json.dump(strip_series(copy.deepcopy(res)), f, indent=1, default=jdefault)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _rel(path) -> str:
    from pathlib import Path

    try:
        return str(Path(path).resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def merge(files: list, out, force: bool = False) -> dict:
    """Merge result JSONs of parts of one suite on one device (python -m benchmarks merge). A part
    present in several files is taken from the last one that finished it; a part's error is kept only
    when no file finished that part. Header fields come from the first file; ``merged_from`` records
    each file's parts, commit, date and wall time; ``suite_wall_s`` is the sum of the files' wall times."""
    from pathlib import Path

    recs = [(str(f), json.load(open(f))) for f in files]
    if not recs:
        raise ValueError("merge: no files")
    for key in ("suite", "device"):
        vals = {r.get(key) for _, r in recs}
        if len(vals) > 1 and not force:
            raise ValueError(f"merge: the files differ in {key} ({', '.join(map(str, sorted(vals, key=str)))}); "
                             "merge parts of one suite on one device (or pass --force)")
    first = recs[0][1]
    res = {k: first[k] for k in HEADER if k in first}
    res["merged_from"], res["part_wall_s"], done = [], {}, []
    for f, r in recs:
        parts = [p for p in PARTS if p in r]
        for p in parts:
            if p in res:
                log(f"  merge: {p} from {f} replaces the earlier file's")
            res[p] = r[p]
            res.pop(p + "_error", None)
            if p in r.get("part_wall_s", {}):
                res["part_wall_s"][p] = r["part_wall_s"][p]
            if p not in done:
                done.append(p)
        for p in PARTS:
            if p + "_error" in r and p not in res:
                res[p + "_error"] = r[p + "_error"]
        res["merged_from"].append({"file": _rel(f), "parts": parts, "commit": r.get("commit"), "date": r.get("date"),
                                   "time_utc": r.get("time_utc"), "suite_wall_s": r.get("suite_wall_s"),
                                   "load_average": r.get("load_average")})
    res["parts_done"] = [p for p in PARTS if p in done]
    res["parts_pending"] = [p for p in PARTS if p not in done]
    res["suite_wall_s"] = sum(r.get("suite_wall_s") or 0.0 for _, r in recs)
    out = Path(out)
    res["record"] = _rel(out)
    res["charts"] = charts(res, out.stem, out.parent)
    write_json(res, out)
    return res


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="run a suite (the JSON is rewritten after every finished part)")
    r.add_argument("--device", default="cpu")
    r.add_argument("--suite", choices=list(SUITES), default="quick")
    r.add_argument("--only", nargs="+", choices=PARTS, default=None)
    r.add_argument("--out", default=None, help="JSON path (default benchmarks/results/<date>-<device>.json; "
                                               "with --only, <date>-<device>-<suite>-<parts>.json)")
    mg = sub.add_parser("merge", help="merge part JSONs of one suite and device; redraw charts, print the summary")
    mg.add_argument("json", nargs="+")
    mg.add_argument("--out", required=True, help="merged JSON path; charts go next to it as <stem>-*.png")
    mg.add_argument("--force", action="store_true", help="merge files of different suites or devices anyway")
    ch = sub.add_parser("charts", help="redraw the PNG charts of a result JSON")
    ch.add_argument("json")
    ch.add_argument("--out-dir", default=None, help="folder for the PNGs (default: the JSON's folder)")
    md = sub.add_parser("markdown", help="print a RESULTS.md section from a result JSON")
    md.add_argument("json")
    m = sub.add_parser("_mem", help=argparse.SUPPRESS)
    m.add_argument("kind")
    m.add_argument("size", type=float)
    m.add_argument("--device", default="cpu")
    a = ap.parse_args(argv)
    if a.cmd == "markdown":
        print(markdown(json.load(open(a.json))))
        return
    if a.cmd == "charts":
        from pathlib import Path

        src = Path(a.json)
        for c in charts(json.load(open(src)), src.stem, a.out_dir or src.parent):
            print(f"chart {c}")
        return
    if a.cmd == "merge":
        try:
            res = merge(a.json, a.out, a.force)
        except ValueError as e:
            sys.exit(str(e))
        print(summary(res))
        print(f"\nsaved {a.out}")
        for c in res["charts"]:
            print(f"chart {c}")
        return
    if a.cmd == "_mem":
        _mem_main(a.kind, a.size, a.device)
        return
    import warp as wp

    wp.config.quiet = True
    wp.init()
    from rockwave import resolve_device

    dev = resolve_device(a.device)
    cfg = SUITES[a.suite]
    parts = [p for p in PARTS if p in a.only] if a.only else list(PARTS)
    stamp = datetime.date.today().isoformat()
    stem = f"{stamp}-{dev.replace(':', '')}" + ("" if parts == PARTS else f"-{a.suite}-{'-'.join(parts)}")
    from pathlib import Path

    path = Path(a.out) if a.out else RESULTS / f"{stem}.json"
    stem = path.stem
    res = {"suite": a.suite, "device": dev, "device_name": device_name(dev), "date": stamp,
           "time_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%H:%M"), "commit": commit(),
           "warp": wp.__version__, "load_average": os.getloadavg(), "bounds": H.BOUNDS, "config": cfg,
           "record": _rel(path), "parts_done": [], "parts_pending": list(parts), "part_wall_s": {}, "suite_wall_s": 0.0}
    write_json(res, path)
    t0 = time.perf_counter()
    fns = {"accuracy": part_accuracy, "stability": part_stability, "scaling": part_scaling, "peers": part_peers,
           "wave_maker": part_wave_maker}
    for p in parts:
        log(f"[{p}]")
        t = time.perf_counter()
        try:
            res[p] = fns[p](dev, cfg)
        except Exception as e:  # a failing part is recorded; the others still run
            res[p + "_error"] = f"{type(e).__name__}: {e}\n{traceback.format_exc()[-1500:]}"
            log(f"  {p} failed: {type(e).__name__}: {e}")
        res["part_wall_s"][p] = time.perf_counter() - t
        res["parts_done"].append(p)
        res["parts_pending"].remove(p)
        res["suite_wall_s"] = time.perf_counter() - t0
        write_json(res, path)  # a run killed in a later part keeps this one
        log(f"  ({res['part_wall_s'][p]:.0f} s; saved {path})")
    try:
        res["charts"] = charts(res, stem, path.parent)
    except Exception as e:  # the JSON is written; charts can be redrawn with `python -m benchmarks charts`
        res["charts"] = []
        res["charts_error"] = f"{type(e).__name__}: {e}"
        log(f"  charts failed: {res['charts_error']}")
    write_json(res, path)
    print()
    print(summary(res))
    print(f"\nsaved {path}")
    for c in res["charts"]:
        print(f"chart {c}")


if __name__ == "__main__":
    main()
