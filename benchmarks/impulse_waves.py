"""Landslide impulse waves against the impulse-product relations (issue 41): a shipped 2D study run and its
error table recorded.

Runs a study of scenes/studies/ (default ``impulse_2d_convergence``: four slides at 10, 20 and 40 particles per
water depth) through ``rockwave.app.sweep.run_study`` on one device, then writes the study's comparison table
(a_M, H_M, x_M and the decay H(x) against Heller & Hager 2010, rockwave/output/impulse.py) with each scenario's
resolution and cost, and the mean errors per resolution:

    python -m benchmarks.impulse_waves --device cuda:0                         # the resolution study (H200: ~6 min)
    python -m benchmarks.impulse_waves --device cuda:0 --study impulse_2d      # the 16-scenario study at h/dx = 20
    python -m benchmarks.impulse_waves --device cpu --study FILE.toml --workers 1

Record: benchmarks/results/<date>-<device>-impulse_waves-<study>.json, .md (the comparison table), .csv and .png;
the scenarios' own results stay in --out (default runs/bench_<study>), so a re-run resumes.
"""

from __future__ import annotations

import argparse
import datetime
import json
import shutil
import time
from pathlib import Path

from benchmarks.common import RESULTS, commit, device_name, write_json


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.impulse_waves", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--study", default="impulse_2d_convergence", help="a shipped study's name or a study file")
    ap.add_argument("--out", default=None, help="the study's result folder (default runs/bench_<study>)")
    ap.add_argument("--workers", type=int, default=None, help="local workers (default: the study's workers_per_gpu per GPU)")
    ap.add_argument("--out-dir", default=str(RESULTS), help="folder of the record (default benchmarks/results)")
    a = ap.parse_args(argv)

    from rockwave.app.sweep import load_study, resolve_study, run_study, summarise_study

    path, _ = resolve_study(a.study, None)
    name = Path(path).stem
    out = Path(a.out or f"runs/bench_{name}")
    study = load_study(path, out)
    study.device = a.device
    t0 = time.perf_counter()
    res = run_study(study, workers=a.workers, plots=False)
    wall = time.perf_counter() - t0
    dev = a.device.replace(":", "")
    stem = f"{datetime.date.today().isoformat()}-{dev}-impulse_waves-{name}"
    od = Path(a.out_dir)
    od.mkdir(parents=True, exist_ok=True)
    for key, ext in (("comparison_md", "md"), ("comparison_csv", "csv"), ("comparison_png", "png")):
        if key in res.paths:
            shutil.copyfile(res.paths[key], od / f"{stem}.{ext}")
    record = {"benchmark": "impulse_waves", "study": str(path), "device": a.device, "device_name": device_name(a.device),
              "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), "commit": commit(),
              "wall_s": wall, "ran": res.ran, "skipped": res.skipped, "failed": res.failed,
              "per_resolution": summarise_study(study, by="layers")}
    write_json(record, od / f"{stem}.json")
    print((od / f"{stem}.md").read_text() if (od / f"{stem}.md").is_file() else json.dumps(record, indent=2))
    print(f"saved {od / stem}.json/.md/.csv ({wall:.0f} s)")


if __name__ == "__main__":
    main()
