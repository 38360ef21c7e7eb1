"""The one command of the benchmarks (docs/benchmarks.md):

    python -m benchmarks list                                  # the parts and what each measures
    python -m benchmarks run --device cpu --suite quick        # every part, small sizes (2-core CPU)
    python -m benchmarks run --device cuda:0 --suite full --only scaling peers
    python -m benchmarks run --device cuda:0 --suite full --only chart --formulation 'adami={"fluid.boundary": "adami"}'
    python -m benchmarks merge FILE.json ... --out MERGED.json # parts of one suite and device into one record
    python -m benchmarks charts FILE.json                      # redraw a record's PNG charts
    python -m benchmarks report                                # regenerate benchmarks/RESULTS.md from the records

``run`` writes one record, <out-dir>/<date>-<device>[-<suite>-<parts>].json (default out-dir
benchmarks/results), with the device name, date and commit, rewritten (temp file + rename) after every
finished part: a run killed part-way keeps the parts that finished (``parts_done``; ``parts_pending`` lists
the rest). A part that raises is recorded as ``<part>_error`` and the others still run. The full suite
does not fit one 10-minute GPU call: run it in calls of a few parts each, then merge.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import inspect
import json
import os
import sys
import time
import traceback
from pathlib import Path

from benchmarks import report
from benchmarks.common import RESULTS, commit, device_name, log, rel, write_json

# part name -> module with CONFIG {"quick": {...}, "full": {...}} and run(device, cfg) -> dict
PARTS = {
    "accuracy": "benchmarks.accuracy",
    "stability": "benchmarks.stability",
    "scaling": "benchmarks.scaling",
    "peers": "benchmarks.peers",
    "wave_maker": "benchmarks.wave_maker",
    "ghost_cost": "benchmarks.ghost_cost",
    "ghost_accuracy": "benchmarks.ghost_accuracy",
    "readers": "benchmarks.readers",
    "surface": "benchmarks.surface",
    "multirate": "benchmarks.multirate",
    "chart": "benchmarks.chart",
    "block_contacts": "benchmarks.block_contacts",
    "nonconvex": "benchmarks.nonconvex",
    "at_rest": "benchmarks.at_rest",
    "batched_sweep": "benchmarks.batched_sweep",
    "delta_plus": "benchmarks.delta_plus",
    "energy_budget": "benchmarks.energy_budget",
}
SUITES = ("quick", "full")
HEADER = ("suite", "device", "device_name", "date", "time_utc", "commit", "warp", "load_average", "bounds", "config")


def part(name: str):
    return importlib.import_module(PARTS[name])


def config(suite: str, parts: list[str]) -> dict:
    cfg = {}
    for p in parts:
        cfg.update(part(p).CONFIG[suite])
    return cfg


def run(device: str, suite: str, parts: list[str], out: Path | None = None, out_dir: Path = RESULTS,
        settings: dict | None = None) -> dict:
    """Run ``parts`` of ``suite`` on ``device``; the record is written after every part (and after every row of
    a part whose run takes a third argument ``save``). ``settings``: configuration entries that replace the
    suite's (``--set``, ``--formulation``)."""
    import warp as wp

    from benchmarks import harness as H

    wp.config.quiet = True
    wp.init()
    from rockwave import resolve_device
    dev = resolve_device(device)
    stamp = datetime.date.today().isoformat()
    stem = f"{stamp}-{dev.replace(':', '')}" + ("" if parts == list(PARTS) else f"-{suite}-{'-'.join(parts)}")
    path = Path(out) if out else Path(out_dir) / f"{stem}.json"
    cfg = config(suite, parts)
    unknown = sorted(set(settings or {}) - set(cfg))
    if unknown:
        raise ValueError(f"--set: {', '.join(unknown)} not in the configuration of {', '.join(parts)} "
                         f"(keys: {', '.join(sorted(cfg))})")
    cfg.update(settings or {})
    res = {"suite": suite, "device": dev, "device_name": device_name(dev), "date": stamp,
           "time_utc": datetime.datetime.now(datetime.UTC).strftime("%H:%M"), "commit": commit(),
           "warp": wp.__version__, "load_average": os.getloadavg(), "bounds": H.BOUNDS, "config": cfg,
           "record": rel(path), "parts_done": [], "parts_pending": list(parts), "part_wall_s": {}, "suite_wall_s": 0.0}
    write_json(res, path)
    t0 = time.perf_counter()
    for p in parts:
        log(f"[{p}]")
        t = time.perf_counter()
        def save(partial, p=p):  # a part's rows so far: kept if the run is cut off
            res[p] = partial
            write_json(res, path)

        try:
            mod = part(p)
            res[p] = mod.run(dev, cfg, save) if "save" in inspect.signature(mod.run).parameters else mod.run(dev, cfg)
            if p == "accuracy":
                part(p).strip_series(res[p])
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
        res["charts"] = report.charts(res, path.stem, path.parent)
    except Exception as e:  # the JSON is written; charts can be redrawn with `python -m benchmarks charts`
        res["charts"] = []
        res["charts_error"] = f"{type(e).__name__}: {e}"
        log(f"  charts failed: {res['charts_error']}")
    write_json(res, path)
    return res


def merge(files: list, out, force: bool = False) -> dict:
    """Merge records of parts of one suite on one device. A part present in several files is taken from
    the last one that finished it (a part with a ``merge`` function, as ``chart``, combines its rows); a
    part's error is kept only when no file finished that part. Header fields come from the first file;
    ``merged_from`` records each file's parts, commit, date and wall time; ``suite_wall_s`` is the sum of the
    files' wall times."""
    recs = [(str(f), json.loads(Path(f).read_text())) for f in files]
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
            res[p] = part(p).merge(res[p], r[p]) if p in res and hasattr(part(p), "merge") else r[p]
            res.pop(p + "_error", None)
            if p in r.get("part_wall_s", {}):
                res["part_wall_s"][p] = r["part_wall_s"][p]
            if p not in done:
                done.append(p)
        for p in PARTS:
            if p + "_error" in r and p not in res:
                res[p + "_error"] = r[p + "_error"]
        res["merged_from"].append({"file": rel(f), "parts": parts, "commit": r.get("commit"), "date": r.get("date"),
                                   "time_utc": r.get("time_utc"), "suite_wall_s": r.get("suite_wall_s"),
                                   "load_average": r.get("load_average")})
    res["parts_done"] = [p for p in PARTS if p in done]
    res["parts_pending"] = [p for p in PARTS if p not in done and any(p in r.get("parts_pending", []) for _, r in recs)]
    res["suite_wall_s"] = sum(r.get("suite_wall_s") or 0.0 for _, r in recs)
    out = Path(out)
    res["record"] = rel(out)
    res["charts"] = report.charts(res, out.stem, out.parent)
    write_json(res, out)
    return res


def run_settings(a, parts: list[str]) -> dict:
    """Configuration entries from ``--set``, ``--formulation`` and ``--formulations``."""
    out = {}
    for item in a.set:
        key, sep, val = item.partition("=")
        if not sep:
            raise ValueError(f"--set {item!r}: expected KEY=VALUE")
        try:
            out[key] = json.loads(val)
        except json.JSONDecodeError:
            out[key] = val
    known = config(a.suite, parts)
    unknown = sorted(set(out) - set(known))
    if unknown:
        raise ValueError(f"--set: {', '.join(unknown)} not in the configuration of {', '.join(parts)} "
                         f"(keys: {', '.join(sorted(known))})")
    if a.formulation or a.formulations:
        from benchmarks import chart

        forms = dict(out.get("chart_formulations", config(a.suite, parts).get("chart_formulations", chart.FORMULATIONS)))
        for item in a.formulation:
            name, changes = chart.parse_formulation(item)
            forms[name] = changes
        if a.formulations:
            missing = [n for n in a.formulations if n not in forms]
            if missing:
                raise ValueError(f"--formulations: unknown {', '.join(missing)} (known: {', '.join(forms)})")
            forms = {n: forms[n] for n in a.formulations}
        out["chart_formulations"] = forms
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("list", help="the parts and what each measures")
    r = sub.add_parser("run", help="run parts of a suite (the record is rewritten after every finished part)")
    r.add_argument("--device", default="cpu")
    r.add_argument("--suite", choices=SUITES, default="quick")
    r.add_argument("--only", nargs="+", choices=list(PARTS), default=None, help="parts to run (default: all)")
    r.add_argument("--out-dir", default=str(RESULTS), help="folder of the record and its charts (default benchmarks/results)")
    r.add_argument("--out", default=None, help="record path (overrides --out-dir; charts go next to it)")
    r.add_argument("--set", action="append", default=[], metavar="KEY=JSON",
                   help="replace a configuration entry of the suite, e.g. --set 'chart_cases=[\"dam_break\"]' "
                        "(a value that is not JSON is taken as a string)")
    r.add_argument("--formulation", action="append", default=[], metavar="NAME=JSON",
                   help="chart: add or replace a formulation, e.g. --formulation "
                        "'fidelity=high={\"fluid.fidelity\": \"high\"}'")
    r.add_argument("--formulations", nargs="+", default=None, metavar="NAME",
                   help="chart: run only these formulations, in this order")
    mg = sub.add_parser("merge", help="merge records of parts of one suite and device; redraw charts, print the tables")
    mg.add_argument("json", nargs="+")
    mg.add_argument("--out", required=True, help="merged record path; charts go next to it as <stem>-*.png")
    mg.add_argument("--force", action="store_true", help="merge files of different suites or devices anyway")
    ch = sub.add_parser("charts", help="redraw the PNG charts of a record")
    ch.add_argument("json")
    ch.add_argument("--out-dir", default=None, help="folder for the PNGs (default: the record's folder)")
    md = sub.add_parser("markdown", help="print the Markdown tables of one record")
    md.add_argument("json")
    rp = sub.add_parser("report", help="regenerate benchmarks/RESULTS.md from the records in benchmarks/results/")
    rp.add_argument("--results", default=str(RESULTS), help="folder of the records")
    rp.add_argument("--out", default=str(RESULTS.parent / "RESULTS.md"))
    rp.add_argument("--check", action="store_true", help="exit 1 if the file differs from what the records give")
    m = sub.add_parser("_mem", help=argparse.SUPPRESS)
    m.add_argument("kind")
    m.add_argument("size", type=float)
    m.add_argument("--device", default="cpu")
    a = ap.parse_args(argv)
    if a.cmd == "list":
        for name in PARTS:
            print(f"{name}: {part(name).__doc__.strip().splitlines()[0]}")
    elif a.cmd == "markdown":
        print(report.markdown(json.loads(Path(a.json).read_text())))
    elif a.cmd == "charts":
        src = Path(a.json)
        for c in report.charts(json.loads(src.read_text()), src.stem, a.out_dir or src.parent):
            print(f"chart {c}")
    elif a.cmd == "report":
        text, out = report.render_results(a.results), Path(a.out)
        if a.check:
            if not out.is_file() or out.read_text() != text:
                sys.exit(f"{out} differs from the records in {a.results}: run python -m benchmarks report")
            return
        out.write_text(text)
        print(f"wrote {out}")
    elif a.cmd == "merge":
        try:
            res = merge(a.json, a.out, a.force)
        except ValueError as e:
            sys.exit(str(e))
        print(report.summary(res))
        print(f"\nsaved {a.out}")
    elif a.cmd == "_mem":
        from benchmarks import scaling

        scaling.mem_main(a.kind, a.size, a.device)
    else:  # run
        parts = [p for p in PARTS if p in a.only] if a.only else list(PARTS)
        try:
            settings = run_settings(a, parts)
        except ValueError as e:
            sys.exit(str(e))
        res = run(a.device, a.suite, parts, a.out, a.out_dir, settings)
        print()
        print(report.summary(res))
        print(f"\nsaved {res['record']}")
