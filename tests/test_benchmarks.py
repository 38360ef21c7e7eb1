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


def test_spheric_errors_of_the_measurement_itself():
    wl, pr = H.load_spheric()
    t = np.arange(0.01, 1.0, 0.01)
    g = {f"H{i}": H._window_mean(wl, i, t) for i in range(1, 5)}
    g["P1"] = H._window_mean(pr, 1, t)
    e = H.spheric_errors(t, g)
    assert e["error"] < 1e-12
    g["P1"] = g["P1"] + 1000.0 * H.G * H.SPHERIC_H0 * 0.2  # offset by 20% of rho g H0
    assert abs(H.spheric_errors(t, g)["p_rms"] - 0.2) < 1e-9


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

    import benchmarks.__main__ as B

    def killed(dev, cfg):  # a call cut off by its time limit, not an exception the harness would record
        raise KeyboardInterrupt

    monkeypatch.setattr(B, "part_accuracy", lambda dev, cfg: _acc_rows())
    monkeypatch.setattr(B, "part_stability", killed)
    out = tmp_path / "part.json"
    try:
        B.main(["run", "--device", "cpu", "--suite", "quick", "--only", "accuracy", "stability", "--out", str(out)])
    except KeyboardInterrupt:
        pass
    res = json.loads(out.read_text())
    assert res["parts_done"] == ["accuracy"] and res["parts_pending"] == ["stability"]
    assert res["accuracy"]["dam_break_2d"][0]["variant"] == "tait" and "stability" not in res
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]  # the write is atomic: no leftovers
    assert "incomplete" in B.summary(res)


def test_merge_parts_redraws_charts_and_refuses_mixed_devices(tmp_path):
    import json

    import pytest

    import benchmarks.__main__ as B

    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps(_header("cuda:0", "aaa1111", 385.0, accuracy=_acc_rows())))
    b.write_text(json.dumps(_header("cuda:0", "bbb2222", 305.0, peers=_peers())))
    out = tmp_path / "merged" / "full.json"
    B.main(["merge", str(a), str(b), "--out", str(out)])
    res = json.loads(out.read_text())
    assert res["parts_done"] == ["accuracy", "peers"] and res["parts_pending"] == ["stability", "scaling", "wave_maker"]
    assert res["suite_wall_s"] == 690.0 and [m["commit"] for m in res["merged_from"]] == ["aaa1111", "bbb2222"]
    assert (out.parent / "full-accuracy-dam_break_2d.png").stat().st_size > 0
    md = B.markdown(res)
    assert "NVIDIA H100" in md and "CPU's cores" not in md and "aaa1111, bbb2222" in md
    assert "pysplishsplash is not installed" in B.summary(res)
    (tmp_path / "c.json").write_text(json.dumps(_header("cpu", peers=_peers())))
    with pytest.raises(ValueError, match="device"):
        B.merge([a, tmp_path / "c.json"], tmp_path / "x.json")
    B.main(["charts", str(out), "--out-dir", str(tmp_path / "redrawn")])
    assert (tmp_path / "redrawn" / "full-accuracy-dam_break_2d.png").is_file()


def test_splash_scene_matches_rockwave_lattice_and_eos():
    """SPlisHSPlasH's block sampler (round(L / 2r) - 1 per axis from min + 2r) on the padded block gives
    rockwave's cell-centred lattice; stiffness is rockwave's Tait B."""
    from benchmarks.peers import splash as S
    from rockwave.sampling import box_lattice

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
    """The harness's wave_maker part (issue 4's piston check at full size) is summarised and written to
    RESULTS markdown with its class; a record with the H100 figures (16 / 128 layers per depth)."""
    from benchmarks.__main__ import markdown, summary

    rows = [dict(layers=16, particles=2048, error_gauge1=-0.196, error_gauge2=-0.364, wall_s=5.0, class_="outside 10%"),
            dict(layers=128, particles=131072, error_gauge1=-0.074, error_gauge2=-0.175, wall_s=169.0, class_="within 10%")]
    for r in rows:
        r["class"] = r.pop("class_")
    res = {"suite": "full", "device": "cuda:0", "device_name": "NVIDIA H100 80GB HBM3", "date": "2026-11-22", "commit": "x",
           "warp": "1.19.0", "load_average": [0.0, 0.0, 0.0], "wave_maker": {"piston": rows}}
    s = summary(res)
    assert "128 layers/depth  131072 particles gauge_1 -7.4%" in s and "within 10%" in s and "outside 10%" in s
    md = markdown(res)
    assert "| 128 | 131072 | -7.4% | -17.5% | 169 | within 10% |" in md
