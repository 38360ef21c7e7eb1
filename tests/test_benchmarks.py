"""The benchmark harness's classifier and metrics (benchmarks/harness.py); no timings here."""

import math

import numpy as np

from benchmarks import harness as H


def test_classifier_labels():
    assert H.classify({"finite": False})[0] == "blown_up"
    assert H.classify({"finite": True, "exception": "blow-up at step 10"})[0] == "blown_up"
    assert H.classify({"finite": True, "energy_growth": 0.5})[0] == "blown_up"
    assert H.classify({"finite": True, "energy_growth": math.nan})[0] == "blown_up"
    assert H.classify({"finite": True, "escaped_fraction": 0.2})[0] == "blown_up"
    assert H.classify({"finite": True, "density_error": 0.3})[0] == "blown_up"
    assert H.classify({"finite": True, "density_error": 0.05, "error": 0.05})[0] == "inaccurate"
    assert H.classify({"finite": True, "density_error": 0.01, "error": 0.4})[0] == "inaccurate"
    assert H.classify({"finite": True, "density_error": 0.01, "error": math.nan})[0] == "inaccurate"
    assert H.classify({"finite": True, "density_error": 0.01, "error": 0.05, "energy_growth": 0.0})[0] == "stable"
    assert H.classify({"refused": "dt above the critical step", "finite": False})[0] == "refused"
    assert H.classify({"finite": True, "error": 0.5, "error_bound": 1.0})[0] == "stable"


def test_pareto_front_of_known_points():
    pts = [(1.0, 0.5), (2.0, 0.3), (2.5, 0.4), (4.0, 0.1), (3.0, 0.3), (0.5, math.nan), (8.0, 0.1), (0.8, 0.9)]
    assert H.pareto_front(pts) == [7, 0, 1, 3]
    assert H.pareto_front([]) == []


def test_dam_break_errors_exact_and_offset():
    a = H.A_MM
    ef, eh = H.martin_moyce("front_n2_2"), H.martin_moyce("height_n2_2")
    front = {T / math.sqrt(2 * H.G / a): Z * a for T, Z in ef}
    height = {tau / math.sqrt(H.G / a): Hh * 2 * a for tau, Hh in eh}
    e = H.dam_break_errors(front, height)
    assert e["error"] < 1e-12 and e["front_points"] == len(ef) and e["height_points"] == len(eh)
    ahead = {t: 1.1 * x for t, x in front.items()}
    e = H.dam_break_errors(ahead, height)
    assert abs(e["front_rms"] - 0.1) < 1e-9 and abs(e["front_bias"] - 0.1) < 1e-9 and abs(e["error"] - 0.05) < 1e-9
    dry = {t: math.nan for t in height}  # a dry gauge reads 0: error 100%
    assert abs(H.dam_break_errors(front, dry)["height_rms"] - 1.0) < 1e-12


def test_front_speed_and_start_delay_are_told_apart():
    """A front that is the measurement moved earlier by a known delay reads speed ratio 1 and that delay; a
    front that runs 10% faster reads speed ratio 1.1 and leaves a residual no delay removes."""
    a, s = H.A_MM, math.sqrt(2 * H.G / H.A_MM)
    ef = H.martin_moyce("front_n2_2")
    late = ef[ef[:, 0] >= 1.5]
    fit = np.polyfit(late[:, 0], late[:, 1], 1)  # the measured surge after T = 1.5, a straight line
    T = np.arange(0.0, 3.6, 0.02)
    for delay in (0.0, 0.2):
        e = H.front_speed_and_delay(T / s, np.polyval(fit, T + delay) * a)
        assert abs(e["front_speed_ratio"] - 1) < 1e-9 and abs(e["front_delay_T"] - delay) < 1.5e-3, e
        assert abs(e["front_delay_s"] - e["front_delay_T"] / s) < 1e-12
        assert e["front_rms_late_delayed"] < 0.02 and abs(e["front_bias_late_delayed"]) < 0.01, e
    fast = H.front_speed_and_delay(T / s, (fit[0] * 1.1 * T + fit[1]) * a)
    assert abs(fast["front_speed_ratio"] - 1.1) < 1e-9, fast
    assert fast["front_rms_late_delayed"] > 0.02  # a wrong speed is not a start delay
    # a run that stopped before the last measured point gives no figures
    assert math.isnan(H.front_speed_and_delay(T[:100] / s, np.polyval(fit, T[:100]) * a)["front_speed_ratio"])


def test_spheric_errors_of_the_measurement_itself():
    wl, pr = H.load_spheric()
    t = np.arange(0.01, 1.0, 0.01)
    g = {f"H{i}": H._window_mean(wl, i, t) for i in range(1, 5)}
    g["P1"] = H._window_mean(pr, 1, t)
    e = H.spheric_errors(t, g)
    assert e["error"] < 1e-12
    g["P1"] = g["P1"] + 1000.0 * H.G * H.SPHERIC_H0 * 0.2  # offset by 20% of rho g H0
    assert abs(H.spheric_errors(t, g)["p_rms"] - 0.2) < 1e-9


def test_p1_peak_from_fine_samples_is_a_window_mean_as_the_measurement():
    """P1 read every 1 ms around the impact: the peak compared is the +-5 ms mean at the 10 ms sample times, as
    the measurement's; a reading of the measurement itself scores zero, and a 0.3 ms spike of 10x the peak at one
    1 ms reading (an acoustic ring) moves the mean peak by at most a tenth of itself, not tenfold."""
    wl, pr = H.load_spheric()
    t = np.arange(0.01, 1.0, 0.01)
    ft = np.round(np.arange(0.3, 0.6 + 1e-9, 0.001), 6)
    fp = np.interp(ft, pr[:, 0], pr[:, 1])
    e = H.p1_impact(t, H._window_mean(pr, 1, t), pr, (ft, fp))
    assert abs(e["p1_peak_error"]) < 0.02 and abs(e["p1_impact_error"]) < 0.01, e
    spiked = fp.copy()
    spiked[np.argmax(fp)] *= 10.0
    e2 = H.p1_impact(t, H._window_mean(pr, 1, t), pr, (ft, spiked))
    assert e2["p1_peak_instant_pa"] > 5 * e["p1_peak_pa"]
    assert e2["p1_peak_pa"] < e["p1_peak_pa"] + 0.1 * e2["p1_peak_instant_pa"], (e, e2)


def test_p1_phases_tell_the_arrival_from_the_load_after_it():
    """p1_phases splits a P1 reading into the arrival (the first 10 ms after the impact time) and the
    quasi-steady load 40-140 ms after it, each against the sensor's: the sensor's own record scores zero in both; an
    arrival spike (3 ms at 5x the peak) shows in the first and not after; a load 20% high from the arrival on shows
    +20% after."""
    wl, pr = H.load_spheric()
    t = np.arange(0.01, 1.0, 0.01)
    ft = np.round(np.arange(0.3, 0.6 + 1e-9, 0.001), 6)
    fp = np.interp(ft, pr[:, 0], pr[:, 1])
    e = H.p1_impact(t, H._window_mean(pr, 1, t), pr, (ft, fp))
    # (the arrival's steep rise read every 1 ms against the sensor's own rows: a few per cent)
    assert abs(e["p1_first_error"]) < 0.05 and abs(e["p1_after_error"]) < 0.01, e
    t0 = e["p1_impact_t_s"]
    spiked = fp.copy()
    arrival = (ft >= t0) & (ft < t0 + 0.003)
    spiked[arrival] = 5.0 * pr[:, 1].max()
    e2 = H.p1_impact(t, H._window_mean(pr, 1, t), pr, (ft, spiked))
    assert e2["p1_first_error"] > 0.5 and abs(e2["p1_after_error"]) < 0.01, e2
    high = np.where(ft >= t0, 1.2 * fp, fp)
    e3 = H.p1_impact(t, H._window_mean(pr, 1, t), pr, (ft, high))
    assert abs(e3["p1_after_error"] - 0.2) < 0.01 and abs(e3["p1_first_error"] - 0.2) < 0.05, e3
    # reads that stop before the window leave it open
    short = ft < 0.45
    e4 = H.p1_impact(t, H._window_mean(pr, 1, t), pr, (ft[short], fp[short]))
    assert math.isnan(e4["p1_after_error"]) and math.isfinite(e4["p1_first_error"])


# ------------------------------------------------------------- result files: incremental writes, merge ----
def _acc_rows():
    rows = [{"variant": v, "resolution": f"a/{n}", "particles": n * n * 2, "error": e, "wall_per_sim_s": w, "class": "stable",
             "front_rms": e, "front_bias": e, "height_rms": e, "pareto": p}
            for v, n, e, w, p in (("tait", 10, 0.09, 1.0, True), ("tait", 20, 0.07, 4.0, True), ("linear", 10, 0.1, 2.0, False))]
    return {"dam_break_2d": rows, "spheric": [], "dam_break_2d_recommendation": ["budget 1 s or more: tait at a/10"],
            "spheric_recommendation": []}


def _peers():
    return {"splash": {"splash": {"skipped": "pysplishsplash is not installed"}},
            "warp_example": {"error": "not run in this test"}}


def _header(device="cpu", commit="abc1234", wall=10.0, **parts):
    return {"suite": "full", "device": device, "device_name": "NVIDIA H100" if device != "cpu" else "a CPU",
            "date": "2026-11-22", "time_utc": "05:00", "commit": commit, "warp": "1.19.0", "load_average": [0.5, 0.5, 0.5],
            "suite_wall_s": wall, "part_wall_s": {p: wall for p in parts}, "parts_done": list(parts), **parts}


def test_run_writes_json_after_each_part_and_keeps_finished_parts_when_killed(tmp_path, monkeypatch):
    import json

    from benchmarks import accuracy, cli, report, stability

    def killed(dev, cfg):  # a call cut off by its time limit, not an exception the harness would record
        raise KeyboardInterrupt

    monkeypatch.setattr(accuracy, "run", lambda dev, cfg: _acc_rows())
    monkeypatch.setattr(stability, "run", killed)
    out = tmp_path / "part.json"
    try:
        cli.main(["run", "--device", "cpu", "--suite", "quick", "--only", "accuracy", "stability", "--out", str(out)])
    except KeyboardInterrupt:
        pass
    res = json.loads(out.read_text())
    assert res["parts_done"] == ["accuracy"] and res["parts_pending"] == ["stability"]
    assert res["accuracy"]["dam_break_2d"][0]["variant"] == "tait" and "stability" not in res
    assert res["device_name"] and res["date"] and res["commit"] and res["config"]["dam_res"] == [10, 14, 20]
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]  # the write is atomic: no leftovers
    assert "Incomplete: not run or not finished: stability" in report.markdown(res)


def test_a_failing_part_is_recorded_and_the_others_run(tmp_path, monkeypatch):
    import json

    from benchmarks import cli, wave_maker

    def broken(dev, cfg):
        raise RuntimeError("no such scene")

    monkeypatch.setattr(wave_maker, "run", broken)
    monkeypatch.setattr(cli.report, "charts", lambda res, stem, out_dir=None: [])
    monkeypatch.setattr("benchmarks.peers.run", lambda dev, cfg: _peers())
    cli.main(["run", "--device", "cpu", "--only", "wave_maker", "peers", "--out-dir", str(tmp_path)])
    (out,) = tmp_path.glob("*-cpu-quick-peers-wave_maker.json")
    res = json.loads(out.read_text())
    assert res["parts_done"] == ["peers", "wave_maker"] and "wave_maker" not in res
    assert res["wave_maker_error"].startswith("RuntimeError: no such scene") and res["peers"] == _peers()


def test_merge_parts_redraws_charts_and_refuses_mixed_devices(tmp_path):
    import json

    import pytest

    from benchmarks import cli, report

    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps(_header("cuda:0", "aaa1111", 385.0, accuracy=_acc_rows())))
    b.write_text(json.dumps(_header("cuda:0", "bbb2222", 305.0, peers=_peers())))
    out = tmp_path / "merged" / "full.json"
    cli.main(["merge", str(a), str(b), "--out", str(out)])
    res = json.loads(out.read_text())
    assert res["parts_done"] == ["accuracy", "peers"] and res["parts_pending"] == []
    assert res["suite_wall_s"] == 690.0 and [m["commit"] for m in res["merged_from"]] == ["aaa1111", "bbb2222"]
    assert (out.parent / "full-accuracy-dam_break_2d.png").stat().st_size > 0
    md = report.markdown(res)
    assert "NVIDIA H100" in md and "Commit: aaa1111, bbb2222." in md and "other processes share the CPU" not in md
    assert "| tait | a/20 | 800 | 0.070 * |" in md and "SPlisHSPlasH: pysplishsplash is not installed" in md
    (tmp_path / "c.json").write_text(json.dumps(_header("cpu", peers=_peers())))
    with pytest.raises(ValueError, match="device"):
        cli.merge([a, tmp_path / "c.json"], tmp_path / "x.json")
    cli.main(["charts", str(out), "--out-dir", str(tmp_path / "redrawn")])
    assert (tmp_path / "redrawn" / "full-accuracy-dam_break_2d.png").is_file()


def test_splash_scene_matches_rockwave_lattice_and_eos():
    """SPlisHSPlasH's block sampler (round(L / 2r) - 1 per axis from min + 2r) on the padded block gives
    rockwave's cell-centred lattice; stiffness is rockwave's Tait B."""
    from benchmarks.peers import splash as S
    from rockwave.build.sampling import box_lattice

    a = H.A_MM
    sp = a / 10
    sc = S.splash_scene(sp, 15.0, 1e-4)
    blk = sc["FluidBlocks"][0]
    d = 2 * sc["Configuration"]["particleRadius"]
    axes = []
    for lo, hi in zip(blk["start"], blk["end"]):
        n = int(round((hi - lo) / d)) - 1
        axes.append(lo + d + d * np.arange(n))
    ours = box_lattice([0, 0, 0], [a, 2 * a, a], sp)  # y up in SPlisHSPlasH
    assert np.prod([len(x) for x in axes]) == len(ours) == 2000
    assert np.allclose([x.min() for x in axes], ours.min(axis=0)) and np.allclose([x.max() for x in axes], ours.max(axis=0))
    assert abs(sc["Configuration"]["WCSPH"]["stiffness"] - 15.0 ** 2 * 1000.0 / 7.0) < 1e-9
    assert sc["Configuration"]["WCSPH"]["exponent"] == 7.0 and sc["Configuration"]["kernel"] == 0


def test_wave_maker_part_reports_the_10_percent_check():
    """The wave_maker part's table (issue 4's piston check at full size), from a record with the H100
    figures (16 / 128 layers per depth)."""
    from benchmarks.report import markdown
    from benchmarks.wave_maker import theory

    H = theory()[0]  # a record of before the flume's solution: heights and errors against the steady formula
    rows = [dict(layers=16, particles=2048, error_gauge1=-0.196, error_gauge2=-0.364, wall_s=5.0, **{"class": "outside 10%"}),
            dict(layers=128, particles=131072, error_gauge1=-0.074, error_gauge2=-0.175, wall_s=169.0, simulated_s=2.6,
                 H_gauge1_m=0.926 * H, H_gauge2_m=0.825 * H, **{"class": "within 10%"})]
    res = {"suite": "full", "device": "cuda:0", "device_name": "NVIDIA H100 80GB HBM3", "date": "2026-11-22", "commit": "x",
           "warp": "1.19.0", "load_average": [0.0, 0.0, 0.0], "wave_maker": {"piston": rows}}
    md = markdown(res)
    # against the flume's solution: 0.926 / 1.0107 - 1 = -8.4%, 0.825 / 0.9597 - 1 = -14.0%
    assert "| 128 | 131072 | -8.4% (-7.4%) | -14.0% (-17.5%) | 169 | within 10% |" in md, md
    assert "| 16 | 2048 | - (-19.6%) | - (-36.4%) |" in md


def test_ghost_parts_tables():
    from benchmarks.report import markdown

    cost = {"cases": [{"scene": "ghost_dam_break_case1.toml", "spacing_m": 0.01, "fluid": 3600, "ghosts": 137, "basic_ms": 0.536,
                       "ghost_ms": 0.771, "ratio": 1.4384, "sampling_share": 0.25, "basic_graph_ms": 0.09, "ratio_graph": 8.57},
                      {"scene": "dam_break_3d.toml", "spacing_m": 0.01, "error": "RuntimeError: out of memory"}]}
    acc = {"rows": [{"case": 1, "method": "tile", "spacing": 0.01, "n_fluid": 3600, "front_error_mean": 0.106,
                     "front_error_max": 0.151},
                    {"case": 3, "method": "basic", "spacing": 0.01, "n_fluid": 3600, "finite": False}]}
    md = markdown({"suite": "full", "device": "cuda:0", "device_name": "GPU", "date": "d", "commit": "c", "ghost_cost": cost,
                   "ghost_accuracy": acc})
    assert "| ghost_dam_break_case1.toml | 0.01 | 3600 | 137 | 0.536 | 0.771 | 1.44 | 0.090 (8.57) | 25% |" in md
    assert "RuntimeError: out of memory" in md
    assert "mean +10.6%, largest +15.1%" in md and "non-finite state" in md


def test_parts_share_one_cli_and_disjoint_config_keys():
    """Every part has a quick and a full configuration; the keys of different parts never collide (a run of
    several parts merges them into one configuration)."""
    from benchmarks import cli

    seen = {}
    for name in cli.PARTS:
        mod = cli.part(name)
        assert callable(mod.run) and set(mod.CONFIG) == set(cli.SUITES), name
        assert set(mod.CONFIG["quick"]) == set(mod.CONFIG["full"]), name
        for key in mod.CONFIG["quick"]:
            assert key not in seen, f"{name} and {seen.get(key)} both use {key}"
            seen[key] = name


def test_results_md_is_generated_from_the_records():
    """benchmarks/RESULTS.md is what `python -m benchmarks report` writes from benchmarks/results/*.json;
    every record keeps the device name, date and commit, and the charts it names exist."""
    from benchmarks import report
    from benchmarks.common import RESULTS, ROOT

    assert (RESULTS.parent / "RESULTS.md").read_text() == report.render_results(), "run python -m benchmarks report"
    recs = report.records()
    assert len(recs) >= 5
    for path, r in recs:
        assert r["device_name"] and r["date"] and r["commit"] not in ("", "unknown"), path.name
        for c in r.get("charts", []):
            assert (ROOT / c).is_file(), (path.name, c)


# ------------------------------------------------------------------------------------ chart part ----
def test_formulation_parsing_and_optional_keys():
    from benchmarks import chart

    assert chart.parse_formulation('fidelity=high={"fluid.fidelity": "high"}') == ("fidelity=high", {"fluid.fidelity": "high"})
    ch, dropped = chart.resolve({"fluid.kernel": "wendland", "fluid.no_such_key?": 1, "fluid.density_diffusion?": 0.1})
    assert ch == {"fluid.kernel": "wendland", "fluid.density_diffusion": 0.1} and dropped == ["fluid.no_such_key"]
    # the case builders take the formulation's kernel, not the scene file's "muller"
    assert chart.refused("dam_break", {"fluid.kernel": "wendland"}) is None
    assert "no_such_key" in chart.refused("dam_break", {"fluid.no_such_key": 1})
    d = H.scene_dict("dam_break_2d", H.A_MM / 10, {}, strip=H.FORMULATION_KEYS)
    assert "kernel" not in d["fluid"] and "fidelity" not in d["fluid"]


def test_chart_part_smoke(tmp_path):
    """A tiny chart run on the CPU: every case but SPHERIC (skipped on the CPU) at one coarse resolution, two
    formulations and one the scene loader refuses; the record's fields, finite and sane errors, the table and
    the PNG."""
    from benchmarks import chart, report

    cfg = dict(chart.CONFIG["quick"], chart_standing_ppd=[6], chart_wave_layers=[6], chart_dam_res=[8],
               chart_dam_t_end=0.1, chart_formulations={"old-default": chart.FORMULATIONS["draft"],
                                                        "wendland-3": chart.FORMULATIONS["wendland-3-akinci"],
                                                        "not-yet": {"fluid.no_such_key": "x"}})
    saved = []
    part = chart.run("cpu", cfg, saved.append)
    assert saved and saved[-1] is part
    rows = {(r["case"], r["formulation"]): r for r in part["rows"]}
    assert set(rows) == {(c, f) for c in ("standing_wave", "wave_maker", "dam_break") for f in ("old-default", "wendland-3")}
    assert {(s["case"], s["formulation"]) for s in part["skipped"]} == (
        {(c, "not-yet") for c in ("standing_wave", "wave_maker", "dam_break")} | {("spheric", "*")})
    for r in rows.values():
        assert not r.get("exception"), r
        assert r["particles"] > 0 and r["steps"] > 0 and r["wall_s"] > 0, r
        assert r["wall_per_sim_s"] > 0 and r["particle_steps_per_s"] > 0 and math.isfinite(r["error"]), r
        assert r["class"] in ("stable", "inaccurate", "-"), r
    for f, kernel in (("old-default", "muller"), ("wendland-3", "wendland")):
        sw = rows[("standing_wave", f)]
        assert sw["fluid"]["kernel"] == kernel  # the formulation reached the simulation
        assert -0.05 < sw["decay_per_period"] < 0.95 and abs(sw["period_error"]) < 0.2, sw
        assert sw["density_error"] < 0.03 and sw["max_speed_m_s"] < 1.0 and sw["class"] == "stable", sw
        assert len(sw["amplitudes_m"]) == 2 and 0.005 < sw["amplitudes_m"][0] < 0.03, sw
        wm = rows[("wave_maker", f)]
        assert 0 <= wm["error"] < 1 and wm["H_gauge1_m"] > 0, wm
        db = rows[("dam_break", f)]
        assert db["fluid"]["kernel"] == kernel and db["front_points_late"] > 0
        assert abs(db["front_bias_late"]) < 1 and db["error"] == abs(db["front_bias_late"]), db
    # the kernel choice shows: the old default damps the wave more than Wendland at 3 spacings
    assert rows[("standing_wave", "old-default")]["decay_per_period"] > rows[("standing_wave", "wendland-3")]["decay_per_period"]
    res = {"suite": "quick", "device": "cpu", "device_name": "a CPU", "date": "2026-11-24", "commit": "x", "chart": part}
    md = report.markdown(res)
    blown = dict(rows[("standing_wave", "old-default")], max_speed_m_s=20.0)
    assert chart.health_class(blown)[0] == "blown_up"
    assert "| standing_wave | wendland-3 | 6 /depth |" in md and "skipped: dam_break, not-yet: fluid.no_such_key" in md
    paths = report.charts(res, "smoke", tmp_path)
    assert (tmp_path / "smoke-chart.png").stat().st_size > 0 and any(p.endswith("smoke-chart.png") for p in paths)
    merged = chart.merge(part, {"rows": [dict(rows[("dam_break", "old-default")], error=0.5)], "skipped": []})
    assert len(merged["rows"]) == len(part["rows"]) and [r["error"] for r in merged["rows"] if r["case"] == "dam_break"
                                                          and r["formulation"] == "old-default"] == [0.5]


def test_dualsphysics_case_and_scoring(tmp_path):
    """The DualSPHysics side by side (benchmarks/peers/dualsphysics.py): the case rewrite sets spacing, h/dp,
    duration and the four gauges; gauges that read the measured level score ~0, a 5.5 cm offset scores 0.1,
    and a dry line (level = its lowest point) reads 0."""
    from pathlib import Path

    from benchmarks.peers import dualsphysics as D

    src = ('<case><casedef><constantsdef><hdp value="2" /></constantsdef><geometry><definition dp="0.015">'
           '</definition></geometry></casedef><execution><parameters>'
           '<parameter key="TimeMax" value="2" /></parameters>\n    </execution></case>')
    x = D.case_xml(src, 0.012, 1.5, 1.5)
    assert 'dp="0.012"' in x and '<hdp value="1.5"' in x and 'key="TimeMax" value="1.5"' in x
    assert x.count("<swl ") == 4 and 'point0 x="2.638" y="0.5" z="0.006"' in x
    with np.testing.assert_raises(ValueError):
        D.case_xml(src.replace("TimeMax", "TimeMin"), 0.012, 2.0, 1.5)
    wl, _ = H.load_spheric()
    t = np.arange(0.0, 1.5 + 1e-9, 0.01)

    def write(folder: Path, offset: float):
        folder.mkdir()
        for i, (name, xg) in enumerate(D.GAUGES.items()):
            level = np.interp(t, wl[:, 0], wl[:, 1 + i]) + offset
            z0 = 0.006
            rows = [f"{tt:.6f};{xg};0.5;{max(h, z0):.6f};{xg};0.5;{z0};{xg};0.5;1" for tt, h in zip(t, level)]
            (folder / f"GaugesSWL_{name}.csv").write_text("time [s];swlx [m];swly [m];swlz [m];pos0x;pos0y;pos0z;pos2x;pos2y;pos2z\n"
                                                          + "\n".join(rows) + "\n")

    write(tmp_path / "exact", 0.0)
    write(tmp_path / "high", 0.055)
    exact = D.score(tmp_path / "exact", wall_s=30.0)
    assert exact["h_rms"] < 0.01 and abs(exact["wall_per_sim_s"] - 20.0) < 1e-9
    high = D.score(tmp_path / "high")
    assert abs(high["H2_rms"] - 0.1) < 0.01  # H2 is wet throughout: the offset shows in full
    tt, h = D.read_gauge(tmp_path / "exact" / "GaugesSWL_H1.csv")
    assert h[0] == 0.0  # dry at the start: the lowest point reads 0


def test_flume_linear_solution_of_the_piston_wave_maker():
    """benchmarks/wave_maker.py flume_linear_eta, the wave maker's reference: it keeps the water's volume (the
    piston's displaced X h spread over the flume), starts flat, tends to the steady piston formula in a long
    flume once the start has passed, and in the 1.6 m flume of the benchmark window differs from that formula by
    +1.1% at gauge_1 and -4.0% at gauge_2 (the wave train's front still passing)."""
    from benchmarks.wave_maker import flume_linear_eta, flume_reference, theory

    H_steady, om = theory()
    xs = np.linspace(0.0, 1.6, 3201)
    for t in (0.3, 1.0, 2.2):
        eta = np.array([flume_linear_eta(x, t)[0] for x in xs])
        assert abs(np.trapezoid(eta, xs) - 0.015 * math.sin(om * t) * 0.2) < 1e-7
    assert abs(flume_linear_eta(0.35, 0.0)[0]) < 1e-12 and abs(flume_linear_eta(1.0, 0.0)[0]) < 1e-12
    long = flume_reference(t_end=8.0, x_gauges=(0.35, 1.0), L=12.0, modes=3000)
    assert abs(long[0.35] / H_steady - 1) < 0.003 and abs(long[1.0] / H_steady - 1) < 0.003, long
    ref = flume_reference()
    assert abs(ref[0.35] / H_steady - 1 - 0.0107) < 0.002 and abs(ref[0.7] / H_steady - 1 + 0.0403) < 0.002, ref
    # modes enough: doubling them moves nothing
    assert abs(flume_reference(modes=1200)[0.7] / ref[0.7] - 1) < 1e-4


def test_at_rest_part_reads_hydrostatics_on_a_small_tank():
    """The `at_rest` part on a coarse 2D tank (20 layers, 0.2 s, CPU): its gauges read rho0 g (level - z) within
    3% and its wall particles within 3% of rho0 g d (the physics is tests/test_walls.py's; here the part's
    reading of it), the water stays still, and the report prints the row."""
    from benchmarks import at_rest
    from benchmarks.report import markdown

    part = at_rest.run("cpu", dict(at_rest_cases=[[2, 20, 0.2]], at_rest_levels=[["standard", None]]))
    (r,) = part["rows"]
    assert r["finite"] and r["fluid"]["boundary"] == "adami" and r["wall_particles"] > 10, r
    assert max(abs(r[n] - 1) for n in ("corner", "floor_mid", "side_mid")) == r["gauge_error_max"] < 0.03, r
    assert r["wall_error_max"] < 0.03 and r["speed_rms_c0"] < 1e-3 and abs(r["drift_spacings"]) < 0.1, r
    md = markdown({"suite": "quick", "device": "cpu", "device_name": "a CPU", "date": "d", "commit": "c", "at_rest": part})
    assert f"| standard | default | 2 | 20 | {r['particles']} | 0.20 | {r['corner']:.4f} |" in md, md
    assert r["reads"] == 20 and r["gauge_error_max_last"] < 0.05, r


def test_static_friction_groups_starts_and_merge():
    # --groups runs exactly the named (width, stiffness) groups over the full matrix's aspects, slopes and margins
    # (a per-point spec at any width); --merge joins parts of one device and duration, each row once
    import pytest

    from benchmarks import static_friction as S

    groups = S.parse_groups(["0.2:default", "5:1e8/pt", "20:1e10Pa/m"])
    assert groups == [[0.2, "default"], [5.0, "1e8/pt"], [20.0, "1e10Pa/m"]]
    cfg = S.with_groups(dict(S.CONFIG["full"]), groups)
    by = S.groups_of(cfg)
    assert sorted(by) == [(0.2, "default"), (5.0, "1e8/pt"), (20.0, "1e10Pa/m")]
    full = S.groups_of(S.CONFIG["full"])
    assert by[(0.2, "default")] == full[(0.2, "default")]  # the same cases as in the full matrix
    assert len(by[(5.0, "1e8/pt")]) == len(full[(5.0, "default")])
    for bad in (["0.2"], ["1:"], ["1:soft"]):
        with pytest.raises(ValueError):
            S.parse_groups(bad)
    row = dict(width_m=1.0, aspect=1.0, slope_deg=35.0, margin_deg=0.1, stiffness="default", start="plain")

    def part(rows, dur=60.0):
        return dict(rows=rows, config=dict(duration=dur, creep_window=10.0), device="cuda:0", commit="c")

    rec = S.merge([part([row]), part([dict(row, start="settled")])])
    assert len(rec["rows"]) == 2 and rec["device"] == "cuda:0"
    with pytest.raises(ValueError):
        S.merge([part([row]), part([row])])
    rec = S.merge([part([row]), part([dict(row, start="settled")], dur=20.0)])  # each part its own span
    assert [c["duration"] for c in rec["configs"]] == [60.0, 20.0]
    with pytest.raises(ValueError):
        S.merge([part([row]), dict(part([dict(row, start="settled")]), device="cpu")])
