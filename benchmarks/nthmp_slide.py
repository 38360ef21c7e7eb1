"""NTHMP landslide benchmark 3 (Liu et al. 2005: a rigid wedge down a 1:2 slope into still water 2.44 m deep):
scenes/nthmp_slide_subaerial.toml and nthmp_slide_submarine.toml run at one or more spacings, each through the
run loop (rockwave.app.run: hazard.json, gauges.csv every 0.02 s, slide_motion.csv every 0.01 s, blocks.csv),
then summarised for the comparison with the laboratory (docs/validation.md 'NTHMP benchmark 3'):

- the slide: its displacement s and speed v down the slope at 0.25 s steps, the initial acceleration (parabola
  through s(t) over the first 0.1 s) against the dry slope's Coulomb law g (sin theta - Cn cos theta) and the
  buoyant weight's (1 - rho_w/rho_b) times it, the mean acceleration over the first 0.5 s, a_0 and u_t of Watts'
  s(t) = (u_t^2/a_0) ln cosh(a_0 t/u_t) fitted to the whole s(t) (the usual summary of a measured slide motion),
  the peak speed, and the time the wedge's front reaches the slope's toe (x = 4.88 m) if it does;
- the wave gauges (x/b = 1.2 at y/b = 0, 0.5, 1, 1.5; x/b = 2 on the centre line): first arrival, highest crest,
  deepest trough and their times (the centre-line gauges take the wedge as bed: the free surface over it while it
  passes under them, NaN while its top under the line is out of the water; the record keeps the time series at
  0.02 s);
- the run-up lines at y = 0, b/2, b: the highest water up the slope above the still level and where.

    python -m benchmarks.nthmp_slide --device cuda:0 --cases subaerial            # 0.025 m (~2 M particles), ~3-5 min on an H200
    python -m benchmarks.nthmp_slide --device cuda:0 --cases submarine
    python -m benchmarks.nthmp_slide --device cuda:0 --spacing 0.04               # both starts, ~2-3 min
    python -m benchmarks.nthmp_slide --device cuda:0 --spacing 0.02 --cases subaerial   # ~4.1 M particles, ~6-8 min
    python -m benchmarks.nthmp_slide --device cpu --spacing 0.2 --duration 0.3    # the pipeline on a CPU, ~20 s

writes benchmarks/results/<date>-<device>-nthmp_slide-<cases>-<spacings>.json and .md (``--out`` another stem) and
each run's outputs under runs/nthmp_slide/<case>-<spacing>/ (``--runs`` another folder).
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import math
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
G = 9.81
THETA = math.atan(0.5)
X_TOE = 4.88  # the slope meets the tank floor (z = -2.44 m)
B = 0.91  # the wedge's length


def _wedge(d: dict) -> dict:
    return next(b for b in d["blocks"] if b["name"] == "wedge")


def watts_fit(t: np.ndarray, s: np.ndarray) -> tuple[float, float]:
    """(a_0, u_t) of s(t) = (u_t^2 / a_0) ln cosh(a_0 t / u_t) (Watts 1998; Grilli & Watts 2005: a slide starting
    from rest with initial acceleration a_0 and terminal speed u_t) fitted to the computed s(t) by least squares;
    NaN where it does not fit (fewer than 5 samples, or no convergence)."""
    from scipy.optimize import curve_fit

    def model(tt, a0, ut):
        x = np.clip(a0 * tt / ut, 0.0, 50.0)
        return (ut * ut / a0) * (x + np.log1p(np.exp(-2.0 * x)) - math.log(2.0))  # ln cosh x, without overflow

    if len(t) < 5 or s[-1] <= 0:
        return math.nan, math.nan
    v_end = s[-1] / t[-1] * 2.0
    try:
        (a0, ut), _ = curve_fit(model, t, s, p0=(2.0 * s[-1] / t[-1] ** 2, max(v_end, 0.1)),
                                bounds=([1e-3, 1e-3], [50.0, 50.0]), maxfev=5000)
    except (RuntimeError, ValueError):
        return math.nan, math.nan
    return float(a0), float(ut)


def run_case(case: str, spacing: float, device: str, duration: float | None, runs: Path, reuse: bool = False) -> dict:
    import rockwave
    from rockwave.app.run import run
    from rockwave.scene.format import parse_scene

    path = ROOT / "scenes" / f"nthmp_slide_{case}.toml"
    d = tomllib.loads(path.read_text())
    d["fluid"]["spacing_m"] = spacing
    out = runs / f"{case}-{spacing:g}"
    if reuse and (out / "run.json").is_file() and (out / "hazard.json").is_file():  # summarise a finished run
        summary = json.loads((out / "run.json").read_text())
        build_s, wall = math.nan, float(summary.get("wall_s") or math.nan)
    else:
        t0 = time.time()
        sim = rockwave.Simulation(parse_scene(d, str(path)), device=device)
        build_s = time.time() - t0
        t0 = time.time()
        summary = run(sim, out, duration=duration, progress=False, force=True)
        wall = time.time() - t0
    hz = summary["hazard"]
    w = _wedge(d)
    cn = math.tan(math.radians(w["material"]["friction_angle_deg"]))
    rho_b = w["density_kg_m3"]
    law = G * (math.sin(THETA) - cn * math.cos(THETA))
    m = hz["slides"]["wedge"]["motion"]
    t, s, v = (np.asarray(m[k], float) for k in ("t_s", "along_m", "speed_along_m_s"))
    early = (t > 0.0) & (t <= 0.1 + 1e-9)
    a0 = 2.0 * float(np.polyfit(t[early], s[early], 2)[0]) if early.sum() >= 4 else math.nan
    i05 = int(np.searchsorted(t, 0.5 - 1e-9))
    a05 = 2.0 * s[i05] / t[i05] ** 2 if i05 < len(t) and t[i05] > 0 else math.nan
    # the front's x: the wedge's front face is 2/3 b ahead of its centroid along x (a right triangle's centroid)
    c = np.asarray(m["centroid_m"], float)
    front_x = c[:, 0] + (2.0 / 3.0) * B
    at_toe = np.nonzero(front_x >= X_TOE)[0]
    fa0, fut = watts_fit(t, s)
    table = []
    for tk in np.arange(0.25, t[-1] + 1e-9, 0.25):
        i = int(np.argmin(np.abs(t - tk)))
        table.append({"t_s": float(t[i]), "s_m": float(s[i]), "v_m_s": float(v[i])})
    series = {}
    gauges_csv = out / "gauges.csv"
    if gauges_csv.is_file():
        rows = list(csv.reader(gauges_csv.open()))
        head, body = rows[0], np.asarray([[float(x) if x not in ("", "nan") else math.nan for x in r] for r in rows[1:]])
        series = {"t_s": body[:, 0].tolist(), **{h: body[:, k].tolist() for k, h in enumerate(head) if k}}
    return {
        "case": case, "spacing_m": spacing, "particles": int(summary["fluid_particles"]),
        "steps": summary.get("steps"), "simulated_s": float(t[-1]) if len(t) else 0.0, "build_s": build_s, "wall_s": wall,
        "friction_cn": cn, "wedge_density_kg_m3": rho_b, "law_dry_m_s2": law, "law_buoyant_m_s2": (1.0 - 1000.0 / rho_b) * law,
        "a_initial_m_s2": a0, "a_mean_0_0.5s_m_s2": a05, "watts_a0_m_s2": fa0, "watts_ut_m_s": fut, "peak_speed_m_s": hz["slides"]["wedge"]["peak_speed_m_s"],
        "front_at_toe_s": float(t[at_toe[0]]) if len(at_toe) else None, "slide_table": table,
        "gauges": hz["gauges"], "runup": {k: {q: r[q] for q in ("max_runup_m", "max_runup_above_still_m", "max_runup_time_s",
                                                               "max_runup_at_m")} for k, r in hz["runup"].items()},
        "gauge_series": series, "outputs": str(out),
    }


def _f(v, fmt=".3f"):
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def markdown(rows: list[dict], device_label: str, commit_id: str) -> str:
    md = [f"# NTHMP landslide benchmark 3 (Liu et al. 2005 wedge), {device_label}, commit {commit_id}", "",
          "Slide: initial acceleration (parabola through s(t), 0-0.1 s) and mean over 0-0.5 s against the dry slope's "
          "law g (sin theta - Cn cos theta) and the buoyant weight's; s and v down the slope.", "",
          "Watts fit: a_0, u_t of s(t) = (u_t^2/a_0) ln cosh(a_0 t/u_t) through the whole computed s(t).", "",
          "| case | spacing m | particles | steps | wall s | a(0-0.1 s) | a(0-0.5 s) | dry law | buoyant law | Watts a_0 | "
          "Watts u_t | peak v m/s | front at toe s |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['case']} | {r['spacing_m']:g} | {r['particles']} | {r['steps']} | {r['wall_s']:.0f} | "
                  f"{_f(r['a_initial_m_s2'])} | {_f(r['a_mean_0_0.5s_m_s2'])} | {r['law_dry_m_s2']:.3f} | "
                  f"{r['law_buoyant_m_s2']:.3f} | {_f(r['watts_a0_m_s2'])} | {_f(r['watts_ut_m_s'])} | "
                  f"{_f(r['peak_speed_m_s'])} | {_f(r['front_at_toe_s'], '.2f')} |")
    md += ["", "s (m) and v (m/s) down the slope:", ""]
    for r in rows:
        md.append(f"- {r['case']} {r['spacing_m']:g} m: " + ", ".join(f"t {e['t_s']:.2f}: {e['s_m']:.3f} / {e['v_m_s']:.2f}"
                                                                       for e in r["slide_table"]))
    md += ["", "Wave gauges (eta, m; times s; centre-line gauges read the free surface over the wedge as it passes under them):", "",
           "| case | spacing m | gauge | arrival | crest (t) | trough (t) |", "|---|---|---|---|---|---|"]
    for r in rows:
        for name, g in r["gauges"].items():
            md.append(f"| {r['case']} | {r['spacing_m']:g} | {name} | {_f(g['arrival_time_s'], '.3f')} | "
                      f"{_f(g['max_crest_m'], '.4f')} ({_f(g['max_crest_time_s'], '.2f')}) | "
                      f"{_f(g['deepest_trough_m'], '.4f')} ({_f(g['deepest_trough_time_s'], '.2f')}) |")
    md += ["", "Run-up above the still level (m), its time (s) and x (m):", "",
           "| case | spacing m | line | run-up | time | x |", "|---|---|---|---|---|---|"]
    for r in rows:
        for name, u in r["runup"].items():
            at = u["max_runup_at_m"]
            md.append(f"| {r['case']} | {r['spacing_m']:g} | {name} | {_f(u['max_runup_above_still_m'], '.4f')} | "
                      f"{_f(u['max_runup_time_s'], '.2f')} | {_f(at[0] if at else None, '.3f')} |")
    return "\n".join(md) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.nthmp_slide", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cases", nargs="+", default=["subaerial", "submarine"], choices=["subaerial", "submarine"])
    ap.add_argument("--spacing", type=float, nargs="+", default=[0.025])
    ap.add_argument("--duration", type=float, default=None, help="simulated s (default: the scene's, 3 s)")
    ap.add_argument("--runs", default=str(ROOT / "runs" / "nthmp_slide"), help="folder of the runs' outputs")
    ap.add_argument("--reuse", action="store_true", help="summarise the runs already in --runs instead of running them")
    ap.add_argument("--out", default=None, help="stem of the record (default benchmarks/results/<date>-<device>-nthmp_slide)")
    a = ap.parse_args()
    import warp as wp

    from benchmarks.common import RESULTS, commit, device_name, log, write_json

    wp.config.quiet = True
    rows = []
    stem = a.out or str(RESULTS / (f"{datetime.date.today()}-{a.device.replace(':', '')}-nthmp_slide-{'-'.join(a.cases)}-"
                                   + "-".join(f"{dx:g}m" for dx in a.spacing)))
    for dx in a.spacing:
        for case in a.cases:
            r = run_case(case, dx, a.device, a.duration, Path(a.runs), reuse=a.reuse)
            log(f"  {case} {dx:g} m: {r['particles']} particles, {r['steps']} steps, {r['wall_s']:.0f} s; a0 "
                f"{r['a_initial_m_s2']:.3f} (dry law {r['law_dry_m_s2']:.3f}, buoyant {r['law_buoyant_m_s2']:.3f}) m/s^2")
            rows.append(r)
            md = markdown(rows, device_name(a.device), commit())
            Path(stem + ".md").write_text(md)
            write_json(dict(rows=rows, device=a.device, commit=commit(), args=vars(a)), stem + ".json")
    print(md)
    print(json.dumps({"record": stem + ".json"}))


if __name__ == "__main__":
    main()
