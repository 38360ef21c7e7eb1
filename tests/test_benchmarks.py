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
