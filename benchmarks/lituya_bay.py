"""The Lituya Bay showcase run and its record: ``python -m benchmarks.lituya_bay --device cuda:0``.

Runs scenes/lituya_bay.toml (a rock slide into a fjord-like inlet at the 1:675 scale of Fritz, Hager & Minor 2001;
docs/validation.md "Showcase") at ``--spacing`` (default the scene's 0.009 m) for ``--duration`` (default the scene's
2.0 s), draws its frame strip (rockwave/app/preview.py render_strip: 6 frames, side view, speed), and writes
benchmarks/results/<date>-<device>-lituya_bay-<spacing>.json and .md (``--out`` another stem) with the PNG beside
them: particles, steps, wall time, the run-up on each line against the 1:675 scaling of the observed 524 m
(0.776 m: a scale, not a target; the geometry is ours, not Gilbert Inlet's), the gauges' crests and the slide's
runout and peak speed. The run's outputs (USD frames, hazard.json, gauges.csv, slide_motion.csv) stay in --runs.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import shutil
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "scenes" / "lituya_bay.toml"
RUNUP_1_675_M = 524.0 / 675.0  # Fritz et al. (2001): 524 m run-up on the spur opposite the impact, at 1:675


def run_case(spacing: float | None, device: str, duration: float | None, runs: Path, strip: int) -> dict:
    import rockwave
    from rockwave.app.preview import render_strip
    from rockwave.app.run import run
    from rockwave.scene.format import parse_scene

    d = tomllib.loads(SCENE.read_text())
    if spacing:
        d["fluid"]["spacing_m"] = spacing
    spacing = d["fluid"]["spacing_m"]
    out = runs / f"{spacing:g}"
    t0 = time.time()
    sim = rockwave.Simulation(parse_scene(d, str(SCENE)), device=device)
    build_s = time.time() - t0
    t0 = time.time()
    summary = run(sim, out, duration=duration, progress=False, force=True)
    wall = time.time() - t0
    hz = summary["hazard"]
    png = render_strip(out, strip) if strip else None
    return {
        "spacing_m": spacing, "per_depth": 0.181 / spacing, "particles": int(summary["fluid_particles"]),
        "steps": summary.get("steps"), "build_s": build_s, "wall_s": wall,
        "particles_outside_domain": summary.get("particles_outside_domain"),
        "runup": {k: {q: r[q] for q in ("max_runup_above_still_m", "max_runup_time_s", "max_runup_at_m")}
                  for k, r in hz["runup"].items()},
        "runup_1_675_m": RUNUP_1_675_M,
        "gauges": {k: {q: g.get(q) for q in ("max_crest_m", "max_crest_time_s", "deepest_trough_m", "arrival_time_s")}
                   for k, g in hz["gauges"].items()},
        "slides": {k: {q: s[q] for q in ("runout_m", "peak_speed_m_s", "final_position_m")} for k, s in hz["slides"].items()},
        "outputs": str(out), "strip": str(png) if png else None,
    }


def _f(v, fmt=".3f"):
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def markdown(r: dict, device_label: str, commit_id: str) -> str:
    lines = [f"# Lituya Bay showcase ({device_label}, commit {commit_id})", "",
             f"scenes/lituya_bay.toml at {r['spacing_m']:g} m ({r['per_depth']:.1f} particles per depth): "
             f"{r['particles']:,} water particles, {r['steps']} steps, {r['wall_s']:.0f} s wall (build {r['build_s']:.0f} s); "
             f"{r['particles_outside_domain']} particles out of the tank.", "",
             "| run-up line | max above still (m) | at t (s) | 1:675 scaling of the observed 524 m (m) |", "|---|---|---|---|"]
    for k, u in r["runup"].items():
        lines.append(f"| {k} | {_f(u['max_runup_above_still_m'])} | {_f(u['max_runup_time_s'], '.2f')} | {r['runup_1_675_m']:.3f} |")
    lines += ["", "| gauge | max crest (m) | at t (s) | deepest trough (m) | arrival (s) |", "|---|---|---|---|---|"]
    for k, g in r["gauges"].items():
        lines.append(f"| {k} | {_f(g['max_crest_m'])} | {_f(g['max_crest_time_s'], '.2f')} | {_f(g['deepest_trough_m'])} "
                     f"| {_f(g['arrival_time_s'], '.2f')} |")
    lines += ["", "| slide block | runout (m) | peak speed (m/s) |", "|---|---|---|"]
    for k, s in r["slides"].items():
        lines.append(f"| {k} | {_f(s['runout_m'])} | {_f(s['peak_speed_m_s'])} |")
    if r.get("strip"):
        lines += ["", f"![frame strip]({Path(r['strip']).name})"]
    lines += ["", "The geometry is ours (docs/validation.md \"Showcase\"): the 0.776 m is a scale, not a target."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.lituya_bay", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--spacing", type=float, default=None, help="particle spacing in m (default: the scene's, 0.009)")
    ap.add_argument("--duration", type=float, default=None, help="simulated s (default: the scene's, 2.0 s)")
    ap.add_argument("--strip", type=int, default=6, help="frames in the strip PNG (0: none)")
    ap.add_argument("--runs", default=str(ROOT / "runs" / "lituya_bay"), help="folder of the run's outputs")
    ap.add_argument("--out", default=None, help="stem of the record (default benchmarks/results/<date>-<device>-lituya_bay-<spacing>)")
    a = ap.parse_args()
    import warp as wp

    from benchmarks.common import RESULTS, commit, device_name, log, write_json

    wp.config.quiet = True
    r = run_case(a.spacing, a.device, a.duration, Path(a.runs), a.strip)
    stem = a.out or str(RESULTS / f"{datetime.date.today()}-{a.device.replace(':', '')}-lituya_bay-{r['spacing_m']:g}m")
    if r["strip"]:
        dest = Path(stem + "-strip.png")
        shutil.copyfile(r["strip"], dest)
        r["strip"] = str(dest)
    log(f"  {r['spacing_m']:g} m: {r['particles']} particles, {r['steps']} steps, {r['wall_s']:.0f} s; run-up "
        + ", ".join(f"{k} {_f(u['max_runup_above_still_m'])}" for k, u in r["runup"].items()) + f" m (1:675: {RUNUP_1_675_M:.3f})")
    md = markdown(r, device_name(a.device), commit())
    Path(stem + ".md").write_text(md)
    write_json(dict(row=r, device=a.device, commit=commit(), args=vars(a)), stem + ".json")
    print(md)
    print(json.dumps({"record": stem + ".json"}))


if __name__ == "__main__":
    main()
