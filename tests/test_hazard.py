"""The hazard summary ([hazard], rockwave/output/hazard.py) against cases with a known answer: a still tank (no crest,
no arrival, nothing crosses), a water column translated at a known speed in zero gravity (arrival time, crest,
volume across a line, run-up map with an isolated particle that must not count), a block coasting at a known
speed (peak speed, runout); and the scene checks of the [hazard] keys."""

import json

import pytest

from rockwave.scene.format import SceneError, parse_scene
from rockwave.sim.simulation import Simulation

from conftest import DEVICE
from helpers import tank_2d


def _run(data, tmp_path, duration):
    sim = Simulation(parse_scene(data, tmp_path / "scene.toml", tmp_path), device=DEVICE)
    summary = sim.run(tmp_path / "out", duration=duration, progress=False, checkpoint_interval_s=0.0)
    on_disk = json.loads((tmp_path / "out" / "hazard.json").read_text())
    assert on_disk == json.loads(json.dumps(summary["hazard"]))  # run.json and hazard.json hold the same summary
    return summary["hazard"], sim


def _no_outputs(d):
    d["output"] = {"usd": "", "gauges_csv": "", "blocks_csv": ""}
    return d


def test_still_tank_has_no_crest_and_no_arrival(tmp_path):
    s = 0.02
    d = _no_outputs(tank_2d(width=0.6, depth=0.16, height=0.3, spacing=s))
    d["hazard"] = {"sample_interval_s": 0.01,
                   "gauges": [{"name": "a", "position_m": [0.15, 0.0]}, {"name": "b", "position_m": [0.45, 0.0]}],
                   "crossings": [{"name": "mid", "position_m": [0.3, 0.0], "normal": [1.0, 0.0]}]}
    hz, sim = _run(d, tmp_path, 0.3)
    assert hz["samples"] >= 30
    for name in ("a", "b"):
        g = hz["gauges"][name]
        assert g["arrival_threshold_m"] == pytest.approx(0.5 * s)  # default: half a spacing
        assert g["still_level_m"] == pytest.approx(0.16, abs=0.25 * s)  # the reading at t = 0: top layer (0.15) + s/2
        assert g["arrival_time_s"] is None, g  # |eta| never above the threshold
        assert g["max_crest_m"] < 0.5 * s and g["deepest_trough_m"] > -0.5 * s
        assert g["max_crest_m"] >= g["deepest_trough_m"]
    c = hz["crossings"]["mid"]
    assert c["initial_volume_m3"] == pytest.approx(0.3 * 0.16, rel=0.02)  # half the water, per metre of depth
    assert abs(c["net_volume_m3"]) < 0.5 * s * s  # less than half a particle's area crosses the middle


def test_translated_column_arrival_crest_volume_and_runup(tmp_path):
    """Zero gravity, free-slip floor: a 0.3 x 0.1 m column moving at u = 1 m/s translates rigidly. Its front (the
    water's edge x = 0.3 m at t = 0) reaches a gauge at x_g at (x_g - 0.3)/u; the crest there is the column top
    (0.1 m above the bed, the still level given as the bed); after T the water past x = 0.45 is (0.3 + uT - 0.45) h.
    A single particle resting on the bed ahead (x = 0.96) and one in the air (x = 0.86) must not count as run-up."""
    s, u, h, T = 0.02, 1.0, 0.1, 0.4
    d = _no_outputs(tank_2d(width=1.0, depth=h, height=0.4, spacing=s))
    d["gravity"] = {"acceleration_m_s2": [0.0, 0.0]}
    d["fluid"]["regions"] = [
        {"box_min_m": [0.0, 0.0], "box_max_m": [0.3, h], "velocity_m_s": [u, 0.0]},
        {"box_min_m": [0.95, 0.0], "box_max_m": [0.97, 0.02]},  # one particle on the bed
        {"box_min_m": [0.85, 0.3], "box_max_m": [0.87, 0.32]},  # one particle in the air
    ]
    d["fluid"]["viscosity"] = {"artificial_alpha": 0.0}
    d["hazard"] = {"sample_interval_s": 0.0025,
                   "gauges": [{"name": f"x{xg}", "position_m": [xg, 0.0], "still_level_m": 0.0, "arrival_threshold_m": h / 2}
                              for xg in (0.45, 0.6)],
                   "runup": [{"name": "line", "start_m": [0.5, 0.0], "end_m": [0.98, 0.0], "columns": 25, "still_level_m": 0.0}],
                   "crossings": [{"name": "x045", "position_m": [0.45, 0.0], "normal": [1.0, 0.0]}]}
    hz, sim = _run(d, tmp_path, T)
    for xg in (0.45, 0.6):
        g = hz["gauges"][f"x{xg}"]
        # wet once the line is within half a spacing of the last particle layer (at 0.3 - s/2 + u t)
        assert g["arrival_time_s"] == pytest.approx((xg - 0.3) / u, abs=0.5 * s / u + 0.0025), g
        assert g["max_crest_m"] == pytest.approx(h, abs=0.5 * s)
    c = hz["crossings"]["x045"]
    assert c["initial_volume_m3"] == pytest.approx(2 * s * s, rel=0.01)  # the two lone particles
    assert c["net_volume_m3"] == pytest.approx((0.3 + u * T - 0.45) * h, rel=0.05)
    r = hz["runup"]["line"]
    assert r["max_runup_m"] == pytest.approx(h, abs=0.5 * s)
    xs = [p[0] for p in r["columns_m"]]
    tops = dict(zip(xs, r["column_max_m"]))
    front = 0.3 + u * T
    for x, top in tops.items():
        if x < front - s:
            assert top == pytest.approx(h, abs=0.5 * s), (x, top)
        elif x > front + s:
            assert top is None, (x, top)  # dry: includes the lone particles at 0.86 (air) and 0.96 (bed)
    lone = [top for x, top in tops.items() if abs(x - 0.96) < 1e-6 or abs(x - 0.86) < 1e-6]
    assert lone == [None, None]  # a column runs through each lone particle, and reads dry


def test_coasting_block_peak_speed_and_runout(tmp_path):
    """A block alone in zero gravity moving at 0.5 m/s: peak speed 0.5 m/s, runout 0.5 T."""
    d = {"simulation": {"dimension": 3, "duration_s": 0.2}, "gravity": {"acceleration_m_s2": [0.0, 0.0, 0.0]},
         "blocks": [{"name": "rock", "shape": "box", "size_m": [0.2, 0.2, 0.2], "position_m": [0.0, 0.0, 1.0],
                     "velocity_m_s": [0.3, 0.4, 0.0], "material": {"normal_stiffness_n_m": 1.0e5}}],  # soft: few steps
         "hazard": {"slides": [{"block": "rock"}]}}
    hz, sim = _run(_no_outputs(d), tmp_path, 0.2)
    sl = hz["slides"]["rock"]
    assert sl["peak_speed_m_s"] == pytest.approx(0.5, rel=1e-5)
    assert sl["runout_m"] == pytest.approx(0.1, rel=1e-4)
    assert sl["final_position_m"] == pytest.approx([0.06, 0.08, 1.0], abs=1e-5)


def test_hazard_keys_are_checked(tmp_path):
    d = tank_2d()
    d["hazard"] = {"gauges": [{"name": "a", "position_m": [0.1, 0.0]}, {"name": "a", "position_m": [5.0, 0.0]}],
                   "runup": [{"name": "r", "start_m": [0.1, 0.0], "end_m": [0.1, 0.3]}],
                   "slides": [{"block": "nope"}],
                   "crossings": [{"name": "c", "position_m": [0.1, 0.0], "normal": [0.0, 1.0]}]}
    with pytest.raises(SceneError) as e:
        parse_scene(d, tmp_path / "bad.toml", tmp_path)
    keys = [k for k, _ in e.value.errors]
    assert "hazard.gauges[1].name" in keys  # used twice
    assert "hazard.gauges[1].position_m" in keys  # outside the tank
    assert "hazard.runup[0].end_m" in keys  # same horizontal position as start_m
    assert "hazard.slides[0].block" in keys  # no such block
    assert "hazard.crossings[0].normal" in keys  # vertical
    assert str(e.value).startswith(str(tmp_path / "bad.toml"))


def test_dry_gauge_without_still_level_is_an_error(tmp_path):
    d = _no_outputs(tank_2d(width=0.6, depth=0.1, height=0.3, spacing=0.02))
    d["fluid"]["regions"] = [{"box_min_m": [0.0, 0.0], "box_max_m": [0.2, 0.1]}]
    d["hazard"] = {"gauges": [{"name": "dry", "position_m": [0.5, 0.0]}]}
    sim = Simulation(parse_scene(d, tmp_path / "s.toml", tmp_path), device=DEVICE)
    with pytest.raises(SceneError, match=r"hazard.gauges\[0\].still_level_m.*reads dry"):
        sim.run(tmp_path / "out", duration=0.01, progress=False)
