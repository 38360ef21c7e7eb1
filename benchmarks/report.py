"""Reading result records: Markdown tables of each part (``markdown``), benchmarks/RESULTS.md generated
from every record in benchmarks/results/ (``render_results``), and PNG charts (``charts``).

A result record is the JSON that ``python -m benchmarks run`` writes: a header (suite, device,
device_name, date, time_utc, commit, warp, load_average, config; ``merged_from`` for merged records,
``note`` for provenance written by hand) and one key per part that ran (benchmarks/cli.py, PARTS).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from benchmarks.common import RESULTS, ROOT, rel
from benchmarks.common import fmt_value as _f

PART_ORDER = ("accuracy", "stability", "scaling", "peers", "wave_maker", "ghost_cost", "ghost_accuracy", "readers", "surface",
              "multirate", "chart", "block_contacts", "nonconvex", "at_rest", "energy_budget", "batched_sweep")


# ----------------------------------------------------------------------------------- tables ----
def _table(head: list[str], rows: list[list]) -> list[str]:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return lines + ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]


def commits(res: dict) -> str:
    cs = [m.get("commit") for m in res.get("merged_from", [])] or [res.get("commit")]
    return ", ".join(dict.fromkeys(c for c in cs if c)) or "unknown"


def _accuracy(acc: dict) -> list[str]:
    L = []
    for case, title in (("dam_break_2d", "2D dam break vs Martin & Moyce (t <= 0.2 s)"), ("spheric", "SPHERIC Test 2")):
        rows = acc.get(case, [])
        if not rows:
            continue
        L += [f"### {title}", "", "Error as defined in benchmarks/harness.py; * = Pareto front of error against wall time.", ""]
        out = []
        for r in rows:
            if case == "dam_break_2d":
                parts = (f"front {_f(r.get('front_rms'))} (bias {_f(r.get('front_bias'), '+.3f')}), "
                         f"height {_f(r.get('height_rms'))}")
            else:
                parts = f"H {_f(r.get('h_rms'))}, P1 {_f(r.get('p_rms'))}"
            out.append([r["variant"], r["resolution"], r.get("particles", 0),
                        _f(r.get("error")) + (" *" if r.get("pareto") else ""), parts, _f(r.get("wall_per_sim_s"), ".2f"),
                        r.get("class", "-")])
        L += _table(["variant", "resolution", "particles", "error", "parts", "wall s / sim s", "class"], out)
        L += [""] + [f"- {x}" for x in acc.get(f"{case}_recommendation", [])] + [""]
    return L


def _stability(st: dict) -> list[str]:
    L = []
    fl = st.get("fluid", [])
    if fl:
        mults = sorted({r["dt_multiple"] for r in fl})
        L += ["### Stability: fluid (2D dam break, dt = k x the CFL step)", "",
              "Class of each run (stable, inaccurate, blown_up, refused) and the largest stable k.", ""]
        out = []
        for m in sorted({r["method"] for r in fl}):
            for c0 in sorted({r["c0"] for r in fl}):
                cls = {r["dt_multiple"]: r["class"] for r in fl if r["method"] == m and r["c0"] == c0}
                ok = [k for k, c in cls.items() if c == "stable"]
                out.append([m, f"{c0:g}"] + [cls.get(k, "-") for k in mults] + [f"{max(ok):g}" if ok else "none"])
        L += _table(["method", "c0 m/s"] + [f"k = {k:g}" for k in mults] + ["largest stable k"], out) + [""]
    bl = st.get("blocks", [])
    if bl:
        mults = sorted({r["dt_multiple"] for r in bl})
        L += ["### Stability: blocks (3-cube stack, dt = k x the critical DDA step)", ""]
        out = []
        for kn in sorted({r["k_n"] for r in bl}):
            cls = {r["dt_multiple"]: r["class"] for r in bl if r["k_n"] == kn}
            out.append([f"{kn:.0e}"] + [cls.get(k, "-") for k in mults])
        L += _table(["k_n N/m"] + [f"k = {k:g}" for k in mults], out) + [""]
    return L


def _ns_per_point(r: dict) -> float:
    """Block step wall time per contact point (blocks x points per block / 2); records before it was stored
    carry the step time and the points per block."""
    if "ns_per_contact_point" in r:
        return r["ns_per_contact_point"]
    return 1e9 * r["seconds"] / r["steps"] / max(r["blocks"] * r["contacts_per_block"] / 2, 1.0)


def _scaling(sc: dict) -> list[str]:
    L = []
    if sc.get("fluid"):
        L += ["### Fluid step throughput (3D dam break)", ""]
        L += _table(["spacing m", "fluid particles", "neighbours", "steps/s", "particle-steps/s", "neighbour pairs/s"],
                    [[f"{r['spacing_m']:g}", r["particles"], _f(r["neighbours"], ".1f"), _f(r["steps_per_s"], ".1f"),
                      _f(r["particle_steps_per_s"], ".3g"), _f(r["particle_steps_per_s"] * r["neighbours"], ".3g")]
                     for r in sc["fluid"]]) + [""]
    if sc.get("blocks"):
        L += ["### Block step throughput (jointed rock slope)", ""]
        L += _table(["blocks", "contacts/block", "steps/s", "block-steps/s", "ns per contact point", "solver bytes/block"],
                    [[r["blocks"], _f(r["contacts_per_block"], ".2f"), _f(r["steps_per_s"], ".1f"),
                      _f(r["block_steps_per_s"], ".3g"), _f(_ns_per_point(r), ".1f"),
                      _f(r.get("device_bytes_per_block"), ".0f")] for r in sc["blocks"]]) + [""]
    if sc.get("coupled"):
        L += ["### Coupled SPH-DDA throughput", ""]
        L += _table(["scene", "scale", "fluid particles", "blocks", "ms/step", "particle-steps/s", "coupling share"],
                    [[r["scene"], _f(r.get("scale"), "g"), r.get("fluid_particles", "-"), r.get("blocks", "-"),
                      _f(r.get("s_per_step", math.nan) * 1e3, ".2f"), _f(r.get("particle_steps_per_s"), ".3g"),
                      _f(r.get("coupling_share"), ".1%") if "error" not in r else r["error"][:80]] for r in sc["coupled"]]) + [""]
    if sc.get("memory"):
        L += ["### Memory", ""]
        L += _table(["kind", "sizes (count)", "bytes per item", "how"],
                    [[m["kind"], ", ".join(str(r.get("count", r.get("error", "?"))) for r in m["rows"]),
                      _f(m.get("bytes_per_item"), ".0f"), m.get("how", "")] for m in sc["memory"]]) + [""]
    return L


def _dualsphysics(ds: dict) -> list[str]:
    L = [f"DualSPHysics side by side ({ds.get('case', '')}; benchmarks/peers/dualsphysics.py): water-level RMS / 0.55 m "
         "per gauge, scored by the same function.", ""]
    rows = [[r["code"], r.get("settings", ""), r.get("particles", "-"), _f(r.get("H1_rms")), _f(r.get("H2_rms")),
             _f(r.get("H3_rms")), _f(r.get("H4_rms")), _f(r.get("h_rms")), _f(r.get("h_max")), _f(r.get("wall_per_sim_s"), ".1f")]
            for r in ds.get("runs", [])]
    return L + _table(["code", "settings", "fluid particles", "H1", "H2", "H3", "H4", "mean", "max", "wall s / sim s"], rows) + [""]


def _peers(pe: dict) -> list[str]:
    L = ["### Peers", ""]
    if "dualsphysics" in pe:
        L += _dualsphysics(pe["dualsphysics"])
        if "splash" not in pe and "warp_example" not in pe:
            return L
    s = pe.get("splash", {})
    sp, rw, rc = s.get("splash", {}), s.get("rockwave", {}), s.get("rockwave_continuity", {})
    if "particles" in sp and "particles" in rw:
        rows = [["SPlisHSPlasH WCSPH", sp["particles"], _f(sp["s_per_step"] * 1e3, ".2f"), _f(sp["front_rms"]),
                 _f(sp["front_bias"], "+.3f"), "1"],
                ["rockwave, summation density (as SPlisHSPlasH)", rw["particles"], _f(rw["s_per_step"] * 1e3, ".2f"),
                 _f(rw["front_rms"]), _f(rw["front_bias"], "+.3f"), _f(s.get("throughput_ratio"), ".2f")]]
        if "particles" in rc:
            rows.append(["rockwave, continuity density (its default)", rc["particles"], _f(rc["s_per_step"] * 1e3, ".2f"),
                         _f(rc["front_rms"]), _f(rc["front_bias"], "+.3f"), _f(s.get("throughput_ratio_continuity"), ".2f")])
        L += ["2D dam break, same lattice and EOS (benchmarks/peers/); throughput ratio = rockwave / SPlisHSPlasH.", ""]
        L += _table(["code", "particles", "ms/step", "front error", "front bias", "throughput ratio"], rows) + [""]
    else:
        why = sp.get("skipped") or sp.get("error") or s.get("error") or "not run"
        L += [f"SPlisHSPlasH: {why}", ""]
    w = pe.get("warp_example", {})
    if "throughput_ratio" in w:
        we, r = w["warp_example"], w["rockwave"]
        L += _table(["code", "particles", "neighbours", "particle-steps/s", "ratio rockwave / example"],
                    [["Warp example_sph.py", we["particles"], _f(we["neighbours"], ".1f"),
                      _f(we["particle_steps_per_s"], ".3g"), ""],
                     ["rockwave 3D dam break", r.get("particles", "-"), _f(r["neighbours"], ".1f"),
                      _f(r["particle_steps_per_s"], ".3g"), _f(w["throughput_ratio"], ".2f")]]) + [""]
    else:
        L += [f"Warp example: {w.get('error', 'not run')}", ""]
    return L


def _wave_maker(wm: dict) -> list[str]:
    L = ["### Piston wave maker vs linear theory (wave_maker_small, first-harmonic height)", ""]
    from benchmarks.wave_maker import with_flume_errors

    rows = [with_flume_errors(dict(r)) for r in wm["piston"]]
    L += ["H / H_linear - 1, H_linear from the linear solution of the same flume, start and window "
          "(benchmarks/wave_maker.py flume_linear_eta) and, in brackets, from the steady piston formula. The class of "
          "records written before the flume's solution existed is against the steady formula.", ""]
    L += _table(["layers per depth", "particles", "gauge_1 (0.35 m)", "gauge_2 (0.7 m)", "wall s", "class"],
                [[r["layers"], r["particles"],
                  f"{_f(r.get('error_flume_gauge1'), '+.1%')} ({_f(r['error_gauge1'], '+.1%')})",
                  f"{_f(r.get('error_flume_gauge2'), '+.1%')} ({_f(r['error_gauge2'], '+.1%')})",
                  _f(r["wall_s"], ".0f"), r["class"]] for r in rows])
    return L + [""]


def _ghost_cost(gc: dict) -> list[str]:
    L = ["### Ghost SPH cost against basic SPH (fastest timed block of each, step by step)", ""]
    rows = []
    for r in gc["cases"]:
        if "error" in r:
            rows.append([r["scene"], _f(r.get("spacing_m"), "g"), "-", "-", "-", "-", "-", "-", r["error"][:80]])
            continue
        graph = f"{_f(r.get('basic_graph_ms'))} ({_f(r.get('ratio_graph'), '.2f')})" if "basic_graph_ms" in r else "-"
        rows.append([r["scene"], _f(r["spacing_m"], "g"), r["fluid"], r["ghosts"], _f(r["basic_ms"]), _f(r["ghost_ms"]),
                     _f(r["ratio"], ".2f"), graph, _f(r["sampling_share"], ".0%")])
    L += _table(["scene", "spacing m", "fluid", "ghosts", "basic ms", "ghost ms", "ghost / basic",
                 "basic in CUDA graphs ms (ghost / that)", "sampling share"], rows) + [""]
    for r in gc["cases"]:
        b = r.get("ghost_busy")
        if b:
            top = ", ".join(f"{k} {v:.3f}" for k, v in list(b["top_ms"].items())[:6])
            L.append(f"- {r['scene']} {r['spacing_m']:g} m: ghost step {b['gpu_busy_ms']:.3f} ms GPU busy "
                     f"of {b['wall_ms']:.3f} ms wall, "
                     f"{b['launches_per_step']:.0f} launches; top kernels (ms): {top}")
    return L + [""]


def _ghost_accuracy(ga: dict) -> list[str]:
    L = ["### Ghost SPH accuracy (scenes/ghost_dam_break_case1..3)", ""]
    rows = []
    for r in ga["rows"]:
        if r["case"] == 1:
            what = (f"front vs Martin & Moyce: mean {_f(r['front_error_mean'], '+.1%')}, "
                    f"largest {_f(r['front_error_max'], '+.1%')}")
        elif r["case"] == 2:
            what = (f"centroid {_f(r['centroid_dx'])} dx, front difference {_f(r['front_difference_dx'])} dx, "
                    f"mirror distance {_f(r['mirror_distance_dx'], '.2f')} dx")
        elif not r.get("finite", True):
            what = "non-finite state"
        else:
            what = (f"max E/E(0) {_f(r['max_E_over_E0'])}, largest rise {_f(r['largest_rise_over_E0'], '+.4f')} E(0), "
                    f"deepest past a face {_f(r['deepest_past_wall_dx'], '.2f')} dx, {r['over_top']} over the open top")
        rows.append([r["case"], r["method"], _f(r["spacing"], "g"), r["n_fluid"], what, _f(r.get("wall_s"), ".0f"),
                     r.get("commit", "")])
    head = ["case", "method", "spacing m", "fluid", "result", "wall s"]
    if not any(r.get("commit") for r in ga["rows"]):
        rows = [r[:-1] for r in rows]
    else:
        head.append("commit")
    return L + _table(head, rows) + [""]


def _readers(rd: dict) -> list[str]:
    L = [f"Reading every gauge and all positions after every {rd['block_steps']} steps (benchmarks/readers.py):", ""]
    return L + _table(["spacing m", "fluid particles", "gauges", "ms/step", "reading copies: ms/step", "overhead",
                       "reading views: ms/step", "overhead", "queued reads: ms/step", "overhead"],
                      [[f"{r['spacing_m']:g}", r["particles"], r["gauges"], _f(r["step_ms"], ".3f"),
                        _f(r["copy_ms"], ".3f"), _f(r["copy_overhead"], "+.1%"), _f(r.get("view_ms"), ".3f"),
                        _f(r.get("view_overhead"), "+.1%"), _f(r.get("async_ms"), ".3f"),
                        _f(r.get("async_overhead"), "+.1%")] for r in rd["cases"]]) + [""]


def _surface(su: dict) -> list[str]:
    L = ["The fluid surface of one output frame against a fluid step of the same scene, same process (benchmarks/surface.py):", ""]
    return L + _table(["scene", "spacing m", "cell m", "fluid particles", "grid nodes", "triangles", "ms/step", "surface ms", "in steps",
                       "field in steps", "mesh in steps"],
                      [[r["scene"], f"{r['spacing_m']:g}", _f(r.get("cell_m"), ".4g"), r["particles"], r.get("grid_nodes") or "-", r["triangles"],
                        _f(r["step_s"] * 1e3, ".2f"), _f(r["surface_s"] * 1e3, ".2f"), _f(r["surface_in_steps"], ".2f"),
                        _f(r.get("field_in_steps"), ".2f"), _f(r.get("mesh_in_steps"), ".2f")] for r in su["cases"]]) + [""]


def _at_rest(ar: dict) -> list[str]:
    L = ["Water at rest in a tank (benchmarks/at_rest.py; 2D 0.3 m deep, 0.6 m wide; 3D a 0.3 m cube; c0 20 m/s): pressure "
         "gauges over rho0 g (level - z), averaged over the run's last tenth (1 is exact; the target: within 2%; "
         "the largest error of the last single read in its own column), the largest error of the first layer of wall particles below one "
         "support from the surface (/ rho0 g d, averaged the same way; Adami walls only), RMS speed / c0 (target < 1e-3), "
         "the surface's drift:", ""]
    return L + _table(["level", "C", "dim", "layers", "particles", "simulated s", "corner", "mid-floor", "mid-wall", "gauges, last read",
                       "walls (largest, at)", "speed RMS / c0", "drift (spacings)", "s / sim s"],
                      [[r["level"] + "".join(f", {k} = {v}" for k, v in (r.get("keys") or {}).items()),
                        _f(r.get("cfl"), "g", "default"), r["dim"], r["layers"], r["particles"], _f(r["simulated_s"], ".2f"),
                        _f(r["corner"], ".4f"), _f(r["floor_mid"], ".4f"), _f(r["side_mid"], ".4f"),
                        _f(r.get("gauge_error_max_last"), ".2%"),
                        (f"{_f(r.get('wall_error_max'), '.2%')} at {r['wall_error_at']}" if r.get("wall_error_at") else "-"),
                        _f(r["speed_rms_c0"], ".2e"), _f(r["drift_spacings"], "+.3f"), _f(r["wall_per_sim_s"], ".3g")]
                       for r in ar["rows"]]) + [""]


def _chart(ch: dict) -> list[str]:
    from benchmarks.chart import table_rows

    sw = ch.get("standing_wave", {})
    L = ["### Accuracy against cost of the formulations (part `chart`)", "",
         "error: standing wave |amplitude decay per period| (first sloshing mode, k d = "
         f"{sw.get('kh', '?')}, a = {sw.get('a', '?')} m in {sw.get('depth', '?')} m); wave maker |H/H_linear - 1|, "
         "the larger of gauge_1 and gauge_2 against the flume's linear solution (records before 2026-11-25: gauge_1 "
         "against the steady formula); dam break |mean front bias| over T >= 1.5; SPHERIC Test 2 water-level RMS / 0.55 m, H1-H4 "
         "mean (benchmarks/chart.py, benchmarks/harness.py); class: the run's health (harness classifier; blown-up "
         "runs are left out of the chart). Formulations:", ""]
    L += [f"- `{n}`: {', '.join(f'{k} = {v!r}' for k, v in c.items()) or 'the scenes as they are'}"
          for n, c in ch.get("formulations", {}).items()]
    L += [""] + _table(["case", "formulation", "resolution", "particles", "error", "errors", "wall s / sim s", "steps",
                        "particle-steps/s", "class"], table_rows(ch)) + [""]
    L += [f"- skipped: {s['case']}, {s['formulation']}: {s['why']}" for s in ch.get("skipped", [])]
    return L + ([""] if ch.get("skipped") else [])


def _nonconvex(nc: dict) -> list[str]:
    L = ["Scanned-rock-like boulders (non-convex, CoACD parts) falling onto a slope (benchmarks/nonconvex.py):", ""]
    return L + _table(["boulders", "parts each", "volume error", "decomposition s", "cached load s", "ms/step",
                       "boulder-steps/s", "part-steps/s", "contacts per boulder", "travel m"],
                      [[r["boulders"], r["parts_per_boulder"], _f(r["volume_error"], "+.2%"), _f(r["decompose_s"], ".1f"),
                        _f(r["cached_load_s"], ".2f"), _f(r["step_ms"], ".3f"), _f(r["body_steps_per_s"], ".3g"),
                        _f(r["part_steps_per_s"], ".3g"), _f(r["contacts_per_boulder"], ".1f"), _f(r["travel_m"], ".2f")]
                       for r in nc["cases"]]) + [""]


def _multirate(mr: dict) -> list[str]:
    L = ["### Multi-rate stepping: submarine_slide_2d (wall s per simulated s)", ""]
    L += _table(["spacing m", "run", "particles", "step s (set by)", "block sub-steps", "wall s / sim s", "ratio"],
                [[_f(r["spacing_m"], "g"), r["variant"], r["particles"], f"{r['dt_s']:.3g} ({r['limited_by']})",
                  r["block_substeps"], _f(r["wall_per_sim_s"], ".3g"),
                  f"{r['over_no_block']:.2f} of no_block" if "over_no_block" in r else
                  f"{r['over_multirate']:.1f}x multirate" if "over_multirate" in r else ""] for r in mr["runs"]])
    return L + [""]


def _block_contacts(bc: dict) -> list[str]:
    L = ["Cubes in columns of 4 on a floor settling under gravity, the DDA block solver alone (benchmarks/block_contacts.py):", ""]
    return L + _table(["blocks", "build s", "block-steps/s", "bytes/block", "history bytes/block", "contact points/block",
                       "candidate pairs/block"],
                      [[r["blocks"], _f(r["build_s"], ".1f"), _f(r["block_steps_per_s"], ".4g"), _f(r["bytes_per_block"], ".0f"),
                        _f(r["bytes"]["history"] / r["blocks"], ".0f"), _f(r["points_per_block"], ".2f"),
                        _f(r["pairs_per_block"], ".2f")] for r in bc["cases"]]) + [""] + _table(
        ["50-vertex prisms on a slope", "cooperative ms/step", "one thread per pair ms/step", "speed-up", "same trajectory"],
        [[r["prisms"], _f(r["coop_ms_per_step"], ".3f"), _f(r["serial_ms_per_step"], ".3f"), _f(r["coop_speedup"], ".2f"),
          r["same_trajectory"]] for r in bc.get("prisms", [])]) + [""]


def _energy_budget(eb: dict) -> list[str]:
    L = ["### Energy budget of the shipped scenes (benchmarks/energy_budget.py)", "",
         f"Bound: {eb.get('bound', '')}. Growth: the largest (total - start - input work); rise: the largest rise of the "
         "total less the input work above its lowest value so far (energy made after earlier dissipation); both over the "
         "scene's releasable energy (scale). Blocks: the moving ones.", ""]
    out = []
    for r in eb.get("scenes", []):
        if "error" in r:
            out.append([r["scene"], "-", "-", "-", "-", "-", "-", "-", "-", f"error: {r['error'][:80]}"])
            continue
        t = _f(r["t_reached_s"], ".3g") + (" (wall limit)" if r.get("stopped") else "")
        if r["scale_j"] > 1e-9:
            growth, rise = (_f(100 * r[k], ".3g") + "%" for k in ("max_growth_fraction", "max_rise_fraction"))
        else:  # nothing releasable (no gravity, at rest): the absolute figures
            growth, rise = (f"{_f(r[k], '.3g')} {r['units']}" for k in ("max_growth_j", "max_rise_j"))
        out.append([r["scene"], f"{r['dim']}D", r["fluid_particles"], r["blocks"], r["spacing_note"], t,
                    f"{_f(r['scale_j'], '.4g')} {r['units']}", growth, rise, r["check"]])
    return L + _table(["scene", "dim", "particles", "blocks", "spacing", "t reached s", "scale", "max growth",
                       "max rise", "check"], out) + [""]


def _batched_sweep(b: dict) -> list[str]:
    """Scenarios per hour, solo against batched (benchmarks/batched_sweep.py), and the batches' agreement with solo."""
    L = [f"### Batched sweep ({b.get('scene')}, {_f(b.get('duration_s'), 'g')} s scenarios)", ""]
    L += _table(["mode", "scenarios", "workers", "wall s", "scenarios/h", "x solo_1", "particles"],
                [[r["mode"], r["scenarios"], r.get("workers", "-"), _f(r.get("wall_s"), ".1f"),
                  _f(r.get("scenarios_per_hour"), ".0f"), _f(r.get("ratio_to_solo_1"), ".1f"),
                  r.get("batch_fluid_particles", r.get("fluid_particles_per_scenario", "-"))] if "skipped" not in r else
                 [r["mode"], r["scenarios"], "-", "-", "skipped: " + r["skipped"], "-", "-"] for r in b.get("rows", [])])
    for mode, a in b.get("agreement_with_solo", {}).items():
        L += ["", f"{mode} against solo ({a.get('scenarios_compared')} scenarios), largest differences: crest "
              f"{_f(a.get('height_m'), '.3g')} m, arrival {_f(a.get('arrival_s'), '.3g')} s, runout "
              f"{_f(a.get('runout_m'), '.3g')} m, speed {_f(a.get('speed_m_s'), '.3g')} m/s, volume "
              f"{_f(a.get('volume_m3'), '.3g')} m^3"
              + (f"; identical summaries {a['identical_summaries']}" if "identical_summaries" in a else "")]
    return L + [""]


TABLES = {"multirate": _multirate, "accuracy": _accuracy, "stability": _stability, "scaling": _scaling, "peers": _peers, "wave_maker": _wave_maker,
          "ghost_cost": _ghost_cost, "ghost_accuracy": _ghost_accuracy, "readers": _readers, "surface": _surface,
          "chart": _chart, "block_contacts": _block_contacts, "nonconvex": _nonconvex,
          "at_rest": _at_rest, "energy_budget": _energy_budget, "batched_sweep": _batched_sweep}


def title(res: dict) -> str:
    parts = [p for p in PART_ORDER if p in res]
    return f"{res.get('device_name', '?')} ({res.get('device')}), suite `{res.get('suite')}`: {', '.join(parts)}"


def markdown(res: dict, level: int = 2) -> str:
    """A Markdown section of a result record: header facts, then one table (or more) per part."""
    when = f"{res.get('date', '?')}" + (f" {res['time_utc']} UTC" if res.get("time_utc") else "")
    load = res.get("load_average")
    facts = [f"Machine: {res.get('device_name', '?')}" + (f", warp {res['warp']}" if res.get("warp") else "") + ".",
             f"Date: {when}.", f"Commit: {commits(res)}."]
    if load:
        facts.append(f"Load average at start: {', '.join(f'{x:.1f}' for x in load)}"
                     + (" (other processes share the CPU: timings are upper bounds)." if str(res.get("device")).startswith("cpu")
                        else " (the host CPU's)."))
    if res.get("suite_wall_s"):
        facts.append(f"Wall time: {res['suite_wall_s']:.0f} s.")
    if res.get("record"):
        facts.append(f"Record: `{res['record']}`.")
    L = ["#" * level + " " + title(res), "", " ".join(facts), ""]
    for m in res.get("merged_from", []):
        wall = f", {m['suite_wall_s']:.0f} s" if m.get("suite_wall_s") else ""
        L.append(f"- part file `{m['file']}`: {', '.join(m['parts'])}; commit {m.get('commit')}, {m.get('date')} "
                 f"{m.get('time_utc') or ''} UTC{wall}")
    if res.get("merged_from"):
        L.append("")
    if res.get("note"):
        L += [f"Note: {res['note']}", ""]
    if res.get("parts_pending"):
        L += [f"Incomplete: not run or not finished: {', '.join(res['parts_pending'])}.", ""]
    for p in PART_ORDER:
        if p in res:
            L += TABLES[p](res[p])
        if p + "_error" in res:
            L += [f"Part {p} failed: `{res[p + '_error'].splitlines()[0]}`", ""]
    shown = [c for c in res.get("charts", []) if (ROOT / c).is_file()]
    if shown:
        L += ["Charts: " + ", ".join(f"[{Path(c).name}]({os.path.relpath(ROOT / c, RESULTS.parent)})" for c in shown), ""]
    return "\n".join(L)


summary = markdown  # what `run` and `merge` print


def records(folder=RESULTS) -> list[tuple[Path, dict]]:
    """The result records in ``folder`` (JSON files with a suite header), CPU first, then by date and time."""
    out = []
    for p in sorted(Path(folder).glob("*.json")):
        res = json.loads(p.read_text())
        if isinstance(res, dict) and "suite" in res and "device" in res:
            out.append((p, res))
    return sorted(out, key=lambda pr: (not str(pr[1]["device"]).startswith("cpu"), pr[1].get("date", ""),
                                       pr[1].get("time_utc") or "", pr[0].name))


HEAD = """# rockwave benchmark results

Generated by `python -m benchmarks report` from the result records in `benchmarks/results/*.json`: do not
edit by hand (tests/test_benchmarks.py checks that this file matches the records). How to run the parts:
docs/benchmarks.md. Figures measured outside the harness, and the measurements behind today's defaults and
designs: docs/notes.md.

Every record names its machine, date and commit. Timings are of complete steps after a warm-up that
loads the kernels. CPU figures come from Warp's CPU backend, which runs each kernel on one thread: they
show the code runs, not what a multi-core CPU could do. Error metrics and the run classifier:
benchmarks/harness.py.
"""


def render_results(folder=RESULTS) -> str:
    """The text of benchmarks/RESULTS.md: the head, an index of the records, one section per record."""
    recs = records(folder)
    L = [HEAD, "## Records", ""]
    L += [f"{i}. {title(r)}, {r.get('date')}, commit {commits(r)}: `{p.name}`" for i, (p, r) in enumerate(recs, 1)]
    L.append("")
    for p, r in recs:
        L += [markdown(dict(r, record=rel(p))), ""]
    return "\n".join(L).rstrip() + "\n"


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
                    ax.annotate(r["resolution"], (r["wall_per_sim_s"], r["error"]), fontsize=6, xytext=(3, 2),
                                textcoords="offset points")
            pf = sorted([r for r in rows if r.get("pareto")], key=lambda r: r["wall_per_sim_s"])
            ax.step([r["wall_per_sim_s"] for r in pf], [r["error"] for r in pf], where="post", color="k", lw=1,
                    label="Pareto front")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("wall-clock seconds per simulated second")
            ax.set_ylabel("error (docs/benchmarks.md)")
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
    ch = res.get("chart")
    if ch and ch.get("rows"):
        from benchmarks.chart import METRICS, chart

        fig, axs = plt.subplots(2, 3, figsize=(13, 7.5))
        flat = axs.ravel()
        chart(lambda i: flat[i], ch, res.get("device", "?"))
        for ax in flat[len(METRICS):]:
            ax.axis("off")
        fig.suptitle(f"error against cost, one point per formulation and resolution - {res.get('device_name', '?')}, "
                     f"commit {res.get('commit', '?')}", fontsize=9)
        fig.tight_layout()
        save(fig, "chart")
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


