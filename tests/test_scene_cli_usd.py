"""Scene validation (all errors at once, with key paths), CLI exit codes, USD output."""

import subprocess
import sys

import numpy as np
import pytest

import rockwave
from rockwave.scene.format import SceneError, load_scene, parse_scene

from conftest import DEVICE
from helpers import ROOT, tank_2d, with_changes


def _errors(d):
    with pytest.raises(SceneError) as e:
        parse_scene(d, "bad.toml")
    return e.value.errors, str(e.value)


def test_shipped_scenes_validate():
    for p in sorted((ROOT / "scenes").glob("*.toml")):
        load_scene(p)


def test_all_errors_reported_at_once_with_key_paths():
    d = tank_2d()
    d["fluid"]["eos"]["gamma"] = -1.0  # out of range
    d["fluid"]["spacing_m"] = "small"  # wrong type
    d["fluid"]["viscosity"]["xsph"] = 0.1  # unknown key
    d["simulation"]["time_step"] = "magic"  # not a choice
    d["output"] = {"frame_rate_hz": float("nan")}
    errors, text = _errors(d)
    keys = {k for k, _ in errors}
    assert {"fluid.eos.gamma", "fluid.spacing_m", "fluid.viscosity.xsph", "simulation.time_step", "output.frame_rate_hz"} <= keys
    assert all(line.startswith("bad.toml: ") for line in text.splitlines())
    assert "xsph_epsilon" in text  # the unknown key lists what is allowed
    assert ">= 1" in dict(errors)["fluid.eos.gamma"]


def test_cross_key_errors():
    d = tank_2d()
    d["fluid"]["regions"][0]["box_max_m"] = [0.5, 0.1]  # outside the 0.2 m wide tank
    d["fluid"]["eos"]["b_pa"] = 2000.0  # both c0 and B given
    d["simulation"]["time_step"] = "fixed"  # without dt_s
    errors, _ = _errors(d)
    keys = [k for k, _ in errors]
    assert "fluid.eos" in keys and "simulation.dt_s" in keys and "fluid.regions[0]" in keys
    d = tank_2d()
    d["tank"]["box_min_m"] = [0.0, 0.0, 0.0]  # 3 numbers in a 2D scene
    errors, text = _errors(d)
    assert "tank.box_min_m" in dict(errors) and "2D" in text


def test_missing_mesh_file_named():
    d = with_changes(tank_2d(), **{"simulation.dimension": 3})
    d["fluid"]["regions"] = [{"mesh": "nowhere.stl"}]
    d["tank"] = {"box_min_m": [0, 0, 0], "box_max_m": [1, 1, 1]}
    errors, text = _errors(d)
    assert ("fluid.regions[0].mesh" in dict(errors)) and "file not found" in text


def test_time_step_above_stability_limit_refused():
    d = with_changes(tank_2d(), **{"simulation.time_step": "fixed", "simulation.dt_s": 0.01})
    with pytest.raises(SceneError) as e:
        rockwave.Simulation(parse_scene(d, "x.toml"), device=DEVICE)
    assert "simulation.dt_s" in str(e.value) and "stability limit" in str(e.value)


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "rockwave", *args], capture_output=True, text=True, cwd=cwd, timeout=300)


def test_cli_errors_are_one_line_without_traceback(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[simulation]\nduration_s = -1\n[fluid]\nspacing_m = 0.01\nkernel = "nope"\n')
    r = _cli("run", str(bad), "--out", str(tmp_path / "out"))
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    err = [l for l in r.stderr.splitlines() if l.startswith("error:")]
    assert len(err) == 1 and "bad.toml" in err[0] and "simulation.duration_s" in err[0]
    assert not (tmp_path / "out").exists()  # nothing written
    r = _cli("validate", str(bad))
    assert r.returncode == 2 and "fluid.kernel" in r.stderr and "simulation.duration_s" in r.stderr
    r = _cli("run", str(tmp_path / "missing.toml"))
    assert r.returncode == 2 and "not found" in r.stderr
    bad.write_text("[simulation\n")
    r = _cli("validate", str(bad))
    assert r.returncode == 2 and "not valid TOML" in r.stderr


def test_cli_run_writes_usd_with_expected_frames(tmp_path):
    """A short 2D run through the CLI: the USD stage opens with pxr, has the right metadata and
    one time sample per frame, the particle positions match the last state, gauges.csv has a row per frame."""
    from pxr import Usd, UsdGeom

    scene = tmp_path / "tank.toml"
    scene.write_text("""
[simulation]
dimension = 2
duration_s = 0.05
device = "cpu"
[fluid]
spacing_m = 0.01
fidelity = "draft"
[fluid.eos]
speed_of_sound_m_s = 20.0
[[fluid.regions]]
box_min_m = [0.0, 0.0]
box_max_m = [0.1, 0.1]
[tank]
box_min_m = [0.0, 0.0]
box_max_m = [0.3, 0.2]
[output]
frame_rate_hz = 100.0
chunk_frames = 2
[[output.gauges]]
name = "h"
kind = "height"
position_m = [0.05, 0.0]
""")
    out = tmp_path / "run"
    r = _cli("run", str(scene), "--out", str(out), "--quiet", "--device", "cpu")
    assert r.returncode == 0, r.stderr
    stage = Usd.Stage.Open(str(out / "frames.usdc"))
    assert UsdGeom.GetStageUpAxis(stage) == "Y"
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 100.0
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == 5
    pts = UsdGeom.Points(stage.GetPrimAtPath("/World/fluid"))
    assert pts.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    first = np.array(pts.GetPointsAttr().Get(0))
    last = np.array(pts.GetPointsAttr().Get(5))
    assert first.shape == (100, 3) and np.all(first[:, 2] == 0.0)
    assert np.all(last[:, 1] < first[:, 1] + 1e-3)  # the block falls/spreads, nothing jumps up
    assert len(pts.GetIdsAttr().Get()) == 100
    rows = (out / "gauges.csv").read_text().splitlines()
    assert rows[0] == "time_s,h" and len(rows) == 7
    # --duration override
    r = _cli("run", str(scene), "--out", str(tmp_path / "run2"), "--quiet", "--duration", "0.02", "--device", "cpu")
    assert r.returncode == 0
    stage = Usd.Stage.Open(str(tmp_path / "run2" / "frames.usdc"))
    assert stage.GetEndTimeCode() == 2


def test_python_api_steps_and_reads_arrays():
    sim = rockwave.Simulation(parse_scene(tank_2d()), device=DEVICE)
    x0 = sim.positions()
    sim.advance(0.01)
    assert sim.time == pytest.approx(0.01)
    assert sim.positions().shape == x0.shape == (400, 2)
    assert np.isfinite(sim.pressures()).all() and sim.densities().min() > 900


def test_scene_format_doc_is_current():
    """docs/scene_format.md is generated from the schema the loader uses: regenerate it with
    `python -m rockwave schema > docs/scene_format.md` after changing a key."""
    from rockwave.scene.format import scene_format_doc

    assert (ROOT / "docs" / "scene_format.md").read_text() == scene_format_doc()
