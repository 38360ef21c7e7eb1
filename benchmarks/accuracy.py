"""Part ``accuracy``: error against wall time per simulated second for the method variants of
benchmarks/harness.py on the 2D dam break (Martin & Moyce) and SPHERIC Test 2, with the Pareto front
and one recommendation per budget."""

from __future__ import annotations

import math

from benchmarks import harness as H
from benchmarks.common import log

A = H.A_MM
CONFIG = {
    "quick": dict(dam_res=[10, 14, 20], dam_variants=list(H.VARIANTS), dam_t_end=0.2,
                  spheric=[(0.06, v) for v in ("tait", "linear", "fixed_dt", "laplacian")] + [(0.045, "tait")],
                  spheric_t_end=0.6),
    "full": dict(dam_res=[10, 20, 40, 80], dam_variants=list(H.VARIANTS), dam_t_end=0.2,
                 spheric=[(s, v) for s in (0.03, 0.02) for v in ("tait", "linear", "fixed_dt", "laplacian", "xsph")]
                 + [(0.015, "tait"), (0.04, "ghost")], spheric_t_end=1.0),
}


def run(dev: str, cfg: dict) -> dict:
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
            f"(h {r.get('h_rms', math.nan):.3f}, P1 {r.get('p_rms', math.nan):.3f}) "
            f"{r.get('wall_per_sim_s', math.nan):8.2f} s/sim-s  {r['class']}")
    add_pareto(out)
    return out


def add_pareto(out: dict) -> None:
    """Mark each case's Pareto rows (``pareto``) and write its recommendations (``<case>_recommendation``)."""
    for case in ("dam_break_2d", "spheric"):
        rows = out.get(case, [])
        front = H.pareto_front([(r.get("wall_per_sim_s", math.nan), r.get("error", math.nan)) for r in rows])
        for i, r in enumerate(rows):
            r["pareto"] = i in front
        out[f"{case}_recommendation"] = recommend(rows, front)


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


def strip_series(part: dict) -> dict:
    """Keep the SPHERIC gauge series only for the finest tait run (to keep the JSON small)."""
    rows = [r for r in part.get("spheric", []) if "series" in r]
    keep = min((r for r in rows if r["variant"] == "tait"), key=lambda r: r["spacing_m"], default=None)
    for r in rows:
        if r is not keep:
            r.pop("series", None)
    return part
