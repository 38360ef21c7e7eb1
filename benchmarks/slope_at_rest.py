"""Still water over the NTHMP slope starts at rest (issue 41): the shipped scene, its wedge held fixed.

``scenes/nthmp_slide_subaerial.toml`` at the given spacings with the wedge made a fixed block (so nothing should
move), or its 2D cross-section (``--dim 2``: the x-z plane, the slope prism and the tank, no wedge), run for
``--duration`` simulated seconds from the hydrostatic start. Read at 5 ms, 20 ms and every 0.05 s: the fastest
particle, the water's mean vertical velocity, the largest and median pressure over hydrostatic (rho0 g (0 - z))
of the particles within 1.5 spacings of the slope plane z = -x/2 deeper than 0.2 m, the particles below the slope
plane (leaks), and the rise of the surface at the scene's far gauge column (x = 1.092 m, y = 1.365 m in 3D;
x = 5.5 m in 2D) over its start. Before the seeding rule of docs/coupling.md "Seeding next to a block" the 3D scene
at 0.025 m on an H200 read every gauge rising at ~1.7 m/s from t = 0 (+0.17 m at 0.1 s).

    python -m benchmarks.slope_at_rest --device cuda:0 --dim 3 --spacing 0.05 0.025   # H200: a few minutes
    python -m benchmarks.slope_at_rest --dim 2 --spacing 0.1 0.05 0.025                 # CPU: a minute
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "scenes" / "nthmp_slide_subaerial.toml"


def scene_dict(dim: int, spacing: float) -> dict:
    d = tomllib.loads(SCENE.read_text())
    d["fluid"]["spacing_m"] = spacing
    d["output"] = {"usd": ""}
    d.pop("hazard", None)
    if dim == 3:
        for b in d["blocks"]:
            if b["name"] == "wedge":
                b["kind"] = "fixed"
                b.pop("density_kg_m3", None)
        return d
    d["simulation"]["dimension"] = 2
    d["fluid"]["regions"] = [{"box_min_m": [0.0, -2.44], "box_max_m": [6.0, 0.0]}]
    d["tank"] = {"box_min_m": [-1.6, -2.44], "box_max_m": [6.0, 1.2]}
    d["blocks"] = [{"name": "slope", "shape": "prism", "kind": "fixed",
                    "vertices_m": [[x, z, w] for w in (-0.05, 0.05) for x, z in ((4.88, -2.44), (-1.6, -2.44), (-1.6, 0.8))]}]
    return d


def run(dim: int, spacing: float, device: str, duration: float) -> dict:
    import rockwave

    up = dim - 1
    t0 = time.perf_counter()
    sim = rockwave.Simulation(rockwave.parse_scene(scene_dict(dim, spacing)), device=device)
    build_s = time.perf_counter() - t0

    def far_column(x):
        sel = np.abs(x[:, 0] - (1.092 if dim == 3 else 5.5)) < 0.75 * spacing
        if dim == 3:
            sel &= np.abs(x[:, 1] - 1.365) < 0.75 * spacing
        return float(x[sel, up].max())

    x = sim.positions()
    level0 = far_column(x)
    times = sorted({0.005, 0.02} | {round(k * 0.05, 6) for k in range(1, int(duration / 0.05 + 1e-9) + 1)})
    reads = []
    for t in times:
        sim.advance(t - sim.time)
        x, v, p = sim.positions(), sim.velocities(), sim.pressures()
        above = (x[:, up] + 0.5 * x[:, 0]) / math.sqrt(1.25)  # distance above the slope plane z = -x/2
        near = (above < 1.5 * spacing) & (x[:, up] < -0.2) & (x[:, 0] < 4.5)
        if dim == 3:
            near &= np.abs(x[:, 1]) > 0.5  # beside the wedge's track
        excess = p - 1000.0 * 9.81 * np.clip(-x[:, up], 0.0, None)
        r = dict(t_s=float(sim.time), fastest_m_s=float(np.linalg.norm(v, axis=1).max()),
                 mean_vertical_m_s=float(v[:, up].mean()),
                 slope_p_excess_max_pa=float(excess[near].max()), slope_p_excess_median_pa=float(np.median(excess[near])),
                 below_slope=int((above < 0.0).sum()), far_rise_m=far_column(x) - level0)
        reads.append(r)
        print(f"  {dim}D {spacing:g} m t {r['t_s']:.3f}: fastest {r['fastest_m_s']:.3f} m/s, mean v_up "
              f"{r['mean_vertical_m_s']:+.4f}, slope p excess max {r['slope_p_excess_max_pa']:.0f} Pa "
              f"(median {r['slope_p_excess_median_pa']:.0f}), below slope {r['below_slope']}, far rise "
              f"{r['far_rise_m']:+.4f} m", flush=True)
    return dict(dim=dim, spacing_m=spacing, particles=int(sim.n_fluid), removed_inside_blocks=int(sim.removed_inside_blocks),
                build_s=build_s, wall_s=time.perf_counter() - t0, reads=reads)


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.slope_at_rest", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dim", type=int, default=3, choices=[2, 3])
    ap.add_argument("--spacing", type=float, nargs="+", default=[0.05, 0.025])
    ap.add_argument("--duration", type=float, default=0.2, help="simulated s")
    ap.add_argument("--out", default=None, help="stem of the record (default benchmarks/results/<date>-<device>-slope_at_rest)")
    a = ap.parse_args()
    import warp as wp

    from benchmarks.common import RESULTS, commit, device_name, write_json

    wp.config.quiet = True
    stem = a.out or str(RESULTS / (f"{datetime.date.today()}-{a.device.replace(':', '')}-slope_at_rest-{a.dim}d-"
                                   + "-".join(f"{dx:g}m" for dx in a.spacing)))
    rows = []
    for dx in a.spacing:
        rows.append(run(a.dim, dx, a.device, a.duration))
        write_json(dict(rows=rows, device=a.device, device_name=device_name(a.device), commit=commit(), args=vars(a)),
                   stem + ".json")
    print(json.dumps({"record": stem + ".json"}))


if __name__ == "__main__":
    main()
