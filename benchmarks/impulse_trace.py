"""One impulse_2d slide traced (issue 41): what the wave gauges read and where the slide is when they read it.

Builds one scenario of the ``impulse_2d`` scene maker (rockwave/app/impulse.py), runs it with the hazard monitor
and records, every ``--every`` seconds, each gauge's water level and the slide's centroid, velocity and
orientation; then prints the slide's kinematics (its centroid's speed where the centroid crosses the still
level, as a measured impact Froude number, and when and where it comes to rest) and, per gauge, the highest
crest with its time and the slide's front at that time, and the comparison with the relations
(rockwave/output/impulse.py). ``--out`` keeps the time series and fluid snapshots (npz) and the summary (json)::

    python -m benchmarks.impulse_trace --froude 2.5 --slope 30 --layers 10 --gauge-max 10
    python -m benchmarks.impulse_trace --froude 2.5 --slope 30 --layers 10 --front 30 --out runs/trace_f30

docs/notes.md "Why the box slides read +100%" used it (CPU, 10 and 20 per depth).
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.impulse_trace", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--froude", type=float, required=True)
    ap.add_argument("--slope", type=float, required=True, help="slope angle alpha, degrees")
    ap.add_argument("--thickness", type=float, default=0.4)
    ap.add_argument("--mass", type=float, default=1.0)
    ap.add_argument("--front", type=float, default=90.0, help="front_deg: the front face's angle to the base (90: box)")
    ap.add_argument("--layers", type=float, default=10.0)
    ap.add_argument("--gauge-max", type=float, default=10.0)
    ap.add_argument("--every", type=float, default=0.004, help="seconds between recorded samples")
    ap.add_argument("--snapshot", type=float, default=0.05, help="seconds between fluid snapshots (with --out)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None, help="folder for trace.npz and trace.json")
    a = ap.parse_args(argv)

    from rockwave.app.impulse import ImpulseChannel2D
    from rockwave.output.hazard import HazardMonitor
    from rockwave.output.impulse import compare_channel
    from rockwave.scene.format import parse_scene
    from rockwave.sim.simulation import Simulation

    params = {"froude": a.froude, "thickness": a.thickness, "mass": a.mass, "slope_deg": a.slope, "layers": a.layers,
              "gauge_max": a.gauge_max, "gauge_min": 0.5, "front_deg": a.front}
    bad = ImpulseChannel2D.check(params)
    if bad:
        raise SystemExit("; ".join(f"{k}: {m}" for k, m in bad))
    scene_d, setup = ImpulseChannel2D.scene(params)
    sim = Simulation(parse_scene(copy.deepcopy(scene_d), "<impulse_trace>", "."), device=a.device)
    hz = HazardMonitor(sim)
    slide = [b["name"] for b in scene_d["blocks"]].index("slide")
    names = [g.name for g in hz.waves]
    xs = np.array([g.position_m[0] for g in hz.waves])
    h = setup["h_m"]
    rec: dict = {"t": [], "pos": [], "vel": [], "ori": [], "eta": []}
    snaps: dict = {}
    due = [0.0, 0.0]

    def watch():
        hz.after_step()
        t = sim.time
        if t >= due[0]:
            due[0] += a.every
            level = hz.gauges.launch_levels(sim.state).numpy()[: len(names)].astype(np.float64)
            rec["t"].append(t)
            rec["eta"].append(level - h)
            rec["pos"].append(sim.block_positions()[slide][:2].tolist())
            rec["vel"].append(sim.block_velocities()[slide][:2].tolist())
            rec["ori"].append(sim.block_state.orientations_numpy()[slide].tolist())
        if a.out and t >= due[1]:
            due[1] += a.snapshot
            snaps[f"snap_{t:.3f}"] = sim.positions()[:, :2].copy()

    t0 = time.perf_counter()
    sim.advance(float(scene_d["simulation"]["duration_s"]), watch=watch)
    wall = time.perf_counter() - t0
    t, pos, vel, eta = (np.asarray(rec[k]) for k in ("t", "pos", "vel", "eta"))
    speed = np.linalg.norm(vel, axis=1)
    # the slide's corner points as built (a prism; empty for the box), kept with --out for plots
    body = np.asarray(next(b for b in scene_d["blocks"] if b["name"] == "slide").get("vertices_m") or [], float)
    summary = {"setup": setup, "wall_s": wall, "particles": sim.n_fluid}
    below = np.nonzero(pos[:, 1] <= h)[0]
    if len(below) and below[0] > 0:  # the centroid crossing the still level, interpolated
        k = below[0]
        w = (pos[k - 1, 1] - h) / (pos[k - 1, 1] - pos[k, 1])
        v = speed[k - 1] + w * (speed[k] - speed[k - 1])
        summary["centroid_at_still_level"] = {"t_s": t[k - 1] + w * (t[k] - t[k - 1]), "speed_m_s": v,
                                              "froude": v / math.sqrt(9.81 * h)}
    rest = np.nonzero(speed < 0.02)[0]
    if len(rest):
        summary["at_rest"] = {"t_s": float(t[rest[0]]), "centroid_m": pos[rest[0]].tolist()}
    hazard = hz.result()
    summary["comparison"] = compare_channel(setup, hazard)
    print(f"slide F {a.froude:g}, alpha {a.slope:g}, front {a.front:g} deg, {a.layers:g} per depth: {sim.n_fluid} particles, "
          f"{wall:.0f} s wall")
    c = summary.get("centroid_at_still_level")
    if c:
        print(f"  centroid at the still level: t = {c['t_s']:.3f} s, |v| = {c['speed_m_s']:.2f} m/s, F = {c['froude']:.2f} "
              f"(launched at F = {a.froude:g})")
    if "at_rest" in summary:
        r = summary["at_rest"]
        print(f"  at rest from t = {r['t_s']:.3f} s, centroid ({r['centroid_m'][0]:.3f}, {r['centroid_m'][1]:.3f}) m")
    print("  x/h   crest m  at t s   slide centroid x m then   trough m")
    for i, x in enumerate(xs):
        e = eta[:, i]
        if not np.isfinite(e).any():
            continue
        k = int(np.nanargmax(e))
        print(f"  {x / h:5.2f}  {e[k]:+.3f}   {t[k]:.3f}    {pos[k, 0]:+.3f}                    {np.nanmin(e):+.3f}")
    cmp = summary["comparison"]

    def f(k, spec, scale=1.0):
        return "-" if cmp.get(k) is None else format(cmp[k] / scale, spec)

    print(f"  relation: P {f('P', '.2f')}, a_M {f('a_M_pred_m', '.4f')} m at {f('x_M_pred_m', '.1f', h)} h; measured a_M "
          f"{f('a_M_m', '.4f')} m ({f('a_M_err', '+.1%')}) at {f('x_M_m', '.1f', h)} h, H_M {f('H_M_err', '+.1%')}, "
          f"decay H(x) past x_M {f('decay_H_mean_err', '+.1%')}")
    if a.out:
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out / "trace.npz", t=t, pos=pos, vel=vel, ori=np.asarray(rec["ori"]), eta=eta, xs=xs,
                            slide_vertices=body, **snaps)
        (out / "trace.json").write_text(json.dumps({**summary, "hazard": hazard, "scene": scene_d}, indent=1, default=float))
        print(f"saved {out}/trace.npz, trace.json")


if __name__ == "__main__":
    main()
