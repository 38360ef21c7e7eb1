"""Part ``batched_sweep``: scenarios per hour of a hazard study, solo against batched (issue 40).

slide_2d-class scenarios (scenes/slide_2d.toml: 2D, ~3.2 k particles, 3 s; a Latin hypercube over the slide's
density 2000-3000 kg/m^3 and friction angle 10-20 degrees, as the issue 22 study) run side by side in one call:

- ``solo_1``: one scenario at a time in this process (rockwave/app/sweep.py run_scenario, as a one-worker sweep);
- ``solo_4``: four worker processes sharing the device (sweep.run_local, as ``sweep --workers 4``);
- ``batch_N``: N scenarios stepped together (rockwave/app/batch.py run_batch, as ``sweep --batch N``).

Rows that would overrun ``bs_budget_s`` (from the start of the solo rows; the last batch's time scaled by its
size) are skipped and say so: ``--batches 256`` alone runs the largest in a call of its own. Each row: scenarios,
wall seconds (build, run and writing included; the kernels are loaded before the first row),
scenarios per hour, and the step count. Agreement: the hazard metrics of the scenarios that ran both solo and in a
batch (the batches start with the solo rows' scenarios): the largest difference of each kind (crest heights and
run-up [m], arrival times [s], runout [m], volumes [m^3/m]) and how many summaries are identical, number for number.
``bs_modes``: the batches' step rule, each a row per batch size: "scenario" (each scenario its own step and clock,
the default: its solo step sequence, so the differences are the float32 round-off of its tile's coordinates grown
by the splash) and "shared" (one step, the smallest limit of the batch: two valid step sequences differ).

    python -m benchmarks run --device cuda:0 --suite full --only batched_sweep      # ~8 min on an H200
    python -m benchmarks run --device cuda:0 --suite full --only batched_sweep --set bs_duration_s=1.0 \
        --set 'bs_batches=[64,256]' --set 'bs_modes=["scenario","shared"]'          # per-scenario vs shared steps
    python -m benchmarks.batched_sweep --device cuda:0 --batches 16 64 256          # the same, standalone
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

CONFIG = {
    "quick": dict(bs_scene="slide_2d_tiny.toml", bs_duration_s=0.1, bs_solo=2, bs_workers=2, bs_solo_workers_n=2,
                  bs_batches=[2, 4], bs_budget_s=600.0, bs_modes=["scenario", "shared"]),
    "full": dict(bs_scene="slide_2d.toml", bs_duration_s=3.0, bs_solo=2, bs_workers=4, bs_solo_workers_n=4,
                 bs_batches=[16, 64, 256], bs_budget_s=480.0, bs_modes=["scenario"]),
}


def _study(tmp: Path, scene: str, n: int, duration: float, device: str):
    from rockwave.app import sweep

    root = Path(__file__).resolve().parents[1]
    p = tmp / "study.toml"
    p.write_text(f"""
[study]
scene = "{root / 'scenes' / scene}"
results = "out"
sample = "lhs"
n = {n}
seed = 0
duration_s = {duration}
device = "{device}"
[[vary]]
key = "blocks[slide].density_kg_m3"
range = [2000.0, 3000.0]
[[vary]]
key = "blocks[slide].material.friction_angle_deg"
range = [10.0, 20.0]
""")
    return sweep.load_study(p)


def _configs(study, tag: str, indices):
    import copy

    from rockwave.app import sweep

    out = []
    for sc in [study.scenarios[i] for i in indices]:
        c = copy.deepcopy(sweep.scenario_config(study, sc))
        c["out_dir"] = str(study.results / tag / sc.id)
        out.append(c)
    return out


def _agreement(solo: dict, other: dict) -> dict:
    """The largest |difference| of each metric kind between two {id: metrics} maps (common ids)."""
    kinds = {"height_m": ("max_crest_m", "deepest_trough_m", "max_runup_m", "max_runup_above_still_m"),
             "arrival_s": ("arrival_time_s",), "runout_m": ("runout_m",), "speed_m_s": ("peak_speed_m_s",),
             "volume_m3": ("net_volume_m3", "max_volume_m3")}
    out = {k: 0.0 for k in kinds}
    n = same = 0
    for sid, m in solo.items():
        if sid not in other:
            continue
        n += 1
        same += all(v == other[sid].get(key) or (isinstance(v, float) and isinstance(other[sid].get(key), float)
                                                  and math.isnan(v) and math.isnan(other[sid][key])) for key, v in m.items())
        for key, v in m.items():
            w = other[sid].get(key)
            for kind, ends in kinds.items():
                if key.rsplit(".", 1)[-1] in ends and v is not None and w is not None and math.isfinite(v) and math.isfinite(w):
                    out[kind] = max(out[kind], abs(v - w))
    out["scenarios_compared"] = n
    out["identical_summaries"] = same
    return out


def run(device: str, cfg: dict) -> dict:
    from rockwave.app import batch as batching
    from rockwave.app import sweep

    n_max = max([cfg["bs_solo"], cfg["bs_solo_workers_n"], *cfg["bs_batches"]])
    rows, solo_metrics = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        study = _study(Path(tmp), cfg["bs_scene"], n_max, cfg["bs_duration_s"], device)
        # load the kernels first (a short batch of two): no row pays the compilation
        warm = _configs(study, "warm", range(2))
        for c in warm:
            c["scene"]["simulation"]["duration_s"] = 0.01
        batching.run_batch(warm, sweep.run_scenario)
        sweep.run_scenario(warm[0])

        def record(tag, n, wall, results, workers=1):
            ok = [r for r in results if r["status"] == "ok"]
            row = {"mode": tag, "scenarios": n, "workers": workers, "wall_s": wall, "scenarios_per_hour": 3600.0 * n / wall,
                   "failed": n - len(ok), "steps_max": max((r.get("steps") or 0) for r in results) if results else 0,
                   "fluid_particles_per_scenario": ok[0].get("fluid_particles") if ok else None}
            rows.append(row)
            print(f"  {tag}: {n} scenarios, {wall:.1f} s, {row['scenarios_per_hour']:.0f} scenarios/h, "
                  f"{row['failed']} failed", flush=True)  # each row as it finishes: a cut-off run keeps its figures
            return row

        t0 = t0_all = time.perf_counter()
        res = [sweep.run_scenario(c) for c in _configs(study, "solo_1", range(cfg["bs_solo"]))]
        record("solo_1", len(res), time.perf_counter() - t0, res)
        solo_metrics = {r["id"]: r["metrics"] for r in res if r["status"] == "ok"}

        got = []
        cs = _configs(study, "solo_w", range(cfg["bs_solo_workers_n"]))
        t0 = time.perf_counter()
        sweep.run_local(cs, sweep.local_slots(device, cfg["bs_workers"], cfg["bs_workers"]),
                        lambda r, running: got.append(r))
        record(f"solo_{cfg['bs_workers']}_workers", len(got), time.perf_counter() - t0, got, cfg["bs_workers"])

        agreement = {}
        for n, mode in [(n, mode) for n in cfg["bs_batches"] for mode in cfg.get("bs_modes", ["scenario"])]:
            tag = f"batch_{n}" if mode == "scenario" else f"batch_{n}_{mode}"
            ran = [r for r in rows if r["mode"].startswith("batch_") and "wall_s" in r]
            if ran:  # a batch of n takes about as long as the last one that ran, scaled by its scenarios
                last = ran[-1]  # (launch-bound below, so this overestimates)
                guess = last["wall_s"] * n / last["scenarios"]
                if time.perf_counter() - t0_all + guess > cfg["bs_budget_s"]:
                    rows.append({"mode": tag, "scenarios": n, "skipped": f"over the {cfg['bs_budget_s']:.0f} s "
                                 f"budget (estimated {guess:.0f} s)"})
                    continue
            cs = _configs(study, tag, range(n))
            t0 = time.perf_counter()
            res = batching.run_batch(cs, sweep.run_scenario, steps=mode)
            row = record(tag, n, time.perf_counter() - t0, res)
            row["batch_fluid_particles"] = n * (row["fluid_particles_per_scenario"] or 0)
            row["steps"] = mode
            agreement[tag] = _agreement(solo_metrics, {r["id"]: r["metrics"] for r in res if r["status"] == "ok"})
    base = next(r for r in rows if r["mode"] == "solo_1")["scenarios_per_hour"]
    for r in rows:
        if "scenarios_per_hour" in r:
            r["ratio_to_solo_1"] = r["scenarios_per_hour"] / base
    return {"rows": rows, "agreement_with_solo": agreement, "scene": cfg["bs_scene"], "duration_s": cfg["bs_duration_s"],
            "reference": "issue 22: 228 scenarios/h with 4 workers on an H100 (slide_2d, 3 s)"}


def markdown(res: dict) -> str:
    part = res.get("batched_sweep", res)
    lines = ["| mode | scenarios | wall s | scenarios/h | x solo_1 | steps | failed |", "|---|---|---|---|---|---|---|"]
    for r in part["rows"]:
        if "skipped" in r:
            lines.append(f"| {r['mode']} | {r['scenarios']} | skipped: {r['skipped']} | | | | |")
            continue
        lines.append(f"| {r['mode']} | {r['scenarios']} | {r['wall_s']:.1f} | {r['scenarios_per_hour']:.0f} | "
                     f"{r['ratio_to_solo_1']:.2f} | {r['steps_max']} | {r['failed']} |")
    lines.append("")
    for k, a in part["agreement_with_solo"].items():
        lines.append(f"- {k} vs solo ({a['scenarios_compared']} scenarios): " + ", ".join(
            f"{x} {v:.3g}" for x, v in a.items() if x not in ("scenarios_compared", "identical_summaries"))
            + f"; identical summaries: {a.get('identical_summaries', 0)}")
    return "\n".join(lines)


if __name__ == "__main__":
    import argparse
    import json

    from benchmarks.common import RESULTS, commit, device_name, write_json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--suite", default="full", choices=("quick", "full"))
    ap.add_argument("--batches", type=int, nargs="*", default=None)
    a = ap.parse_args()
    cfg = dict(CONFIG[a.suite])
    if a.batches:
        cfg["bs_batches"] = a.batches
    import datetime

    res = {"device": a.device, "device_name": device_name(a.device), "date": datetime.date.today().isoformat(),
           "commit": commit(), "batched_sweep": run(a.device, cfg)}
    stem = f"{res['date']}-{a.device.replace(':', '')}-batched_sweep"
    write_json(res, RESULTS / f"{stem}.json")
    (RESULTS / f"{stem}.md").write_text(markdown(res) + "\n")
    print(json.dumps(res["batched_sweep"], indent=2, default=str))
