"""Newcomer and bad-input hardening (issue 24): install from anywhere, one-line errors with exit code 2
instead of tracebacks, validate = every check run makes before stepping, no silently accepted
mistakes, the run-length check, leak counting and blow-up advice, quiet Warp, the progress bar and
warnings, and a fuzz test of mutated shipped scenes through validate and run."""

import contextlib
import copy
import io
import json
import math
import shutil
import subprocess
import sys
import tomllib
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import rockwave
from rockwave.app import cli
from rockwave.app.progress import Progress
from rockwave.build import preflight
from rockwave.build.rockmass import resize_box_region
from rockwave.scene.format import SceneError, load_scene, parse_scene

from conftest import DEVICE
from helpers import ROOT, tank_2d, to_toml

# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def run_cli(args) -> tuple[int, str, str]:
    """cli.main in-process: (exit code, stderr, stdout); an uncaught exception fails the test."""
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = cli.main([str(a) for a in args])
    return rc, err.getvalue(), out.getvalue()


def small_2d() -> dict:
    d = tank_2d(width=0.1, depth=0.05, height=0.1, spacing=0.01)
    d["simulation"]["duration_s"] = 0.01
    d["simulation"]["device"] = "cpu"
    d["output"] = {"frame_rate_hz": 100.0, "gauges": [{"name": "h", "kind": "height", "position_m": [0.05, 0.0]}]}
    return d


def blocks_scene(*blocks) -> dict:
    return {"simulation": {"duration_s": 0.01, "device": "cpu"}, "output": {"frame_rate_hz": 100.0}, "blocks": list(blocks)}


def write(tmp: Path, d: dict, name="s.toml") -> Path:
    p = tmp / name
    p.write_text(to_toml(d))
    return p


def both(tmp: Path, scene: Path, *extra) -> tuple[tuple[int, str], tuple[int, str]]:
    """validate and run (CPU, a short run) of one scene file: ((rc, stderr), (rc, stderr))."""
    rv, ev, _ = run_cli(["validate", scene, "--device", "cpu", *extra])
    out = tmp / "out"
    rr, er, _ = run_cli(["run", scene, "--device", "cpu", "--quiet", "--out", out, *extra])
    return (rv, ev), (rr, er)


def assert_user_error(scene: Path, rc_err, key: str | None = None, text: str | None = None, one_line: bool = True) -> None:
    rc, err = rc_err
    assert rc == 2, err
    assert "Traceback" not in err
    lines = [l for l in err.splitlines() if l.strip() and not l.startswith("Warp CUDA")]
    if one_line:
        assert len(lines) == 1 and lines[0].startswith(f"error: {scene}: ") or lines[0].startswith("error: --device"), err
    assert key is None or key in err, (key, err)
    assert text is None or text in err, (text, err)


# --------------------------------------------------------------------------------------------
# 1. install from anywhere
# --------------------------------------------------------------------------------------------


def test_default_scene_ships_inside_the_package_and_is_found_from_another_folder(tmp_path):
    from importlib.resources import files

    p = cli.default_scene()
    assert p.is_file() and p.name == "dam_break_3d.toml"
    assert Path(str(files("rockwave.scenes") / "dam_break_3d.toml")).resolve() == p.resolve()
    scene = load_scene(p)  # its reference data (output.reference[].file) resolve next to it
    refs = [r.file for r in scene.output.reference]
    assert refs and all(Path(f).is_file() and Path(p).parent in Path(f).parents for f in refs)
    r = subprocess.run([sys.executable, "-m", "rockwave", "validate", "--device", "cpu"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "dam_break_3d.toml: ok" in r.stdout, r.stderr


def test_wheel_holds_the_scenes_and_their_data_and_declares_the_mesh_dependencies(tmp_path):
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "-q", "-w", str(tmp_path)],
                       capture_output=True, text=True, timeout=300)
    if r.returncode != 0:
        pytest.skip(f"cannot build a wheel here: {r.stderr[-300:]}")
    (whl,) = tmp_path.glob("rockwave-*.whl")
    with zipfile.ZipFile(whl) as z:
        names = set(z.namelist())
        meta = z.read(next(n for n in names if n.endswith("dist-info/METADATA"))).decode()
    shipped = {f"rockwave/scenes/{p.name}" for p in (ROOT / "scenes").glob("*.toml")}
    assert shipped and shipped <= names
    studies = {f"rockwave/scenes/studies/{p.name}" for p in (ROOT / "scenes" / "studies").glob("*.toml")}
    assert studies and studies <= names  # python -m rockwave sweep impulse_2d finds them in any install
    assert {"rockwave/scenes/data/spheric_test2/water_level.dat", "rockwave/scenes/data/spheric_test2/pressure.dat"} <= names
    assert "rockwave/base/device.py" in names and "rockwave/kernels/sph/fluid.py" in names
    requires = [l.split(":", 1)[1].strip().lower() for l in meta.splitlines() if l.startswith("Requires-Dist:") and "extra ==" not in l]
    for dep in ("charset-normalizer", "scipy", "trimesh"):
        assert any(q.startswith(dep) for q in requires), (dep, requires)


# --------------------------------------------------------------------------------------------
# 2. tracebacks become one-line errors
# --------------------------------------------------------------------------------------------


def _mut(d, **paths):
    d = copy.deepcopy(d)
    for path, value in paths.items():
        node = d
        keys = path.split(".")
        for k in keys[:-1]:
            node = node[int(k)] if isinstance(node, list) else node.setdefault(k, {})
        node[keys[-1]] = value
    return d


TRACEBACK_CASES = {
    "huge speed of sound": (lambda: _mut(small_2d(), **{"fluid.eos.speed_of_sound_m_s": 1e300}), "fluid.eos.speed_of_sound_m_s"),
    "support radius ratio 1": (lambda: _mut(small_2d(), **{"fluid.support_radius_ratio": 1.0}), "fluid.support_radius_ratio"),
    "gravity up": (lambda: _mut(small_2d(), **{"gravity.acceleration_m_s2": [0.0, 9.81]}), "gravity.acceleration_m_s2"),
    "wrong type in a block array": (lambda: blocks_scene({"shape": "box", "size_m": [1, 1, 1], "position_m": [0, 0, 1],
                                                          "array": {"count": [1, "x", 1]}}), "blocks[0].array.count"),
    "region under an obstacle": (lambda: _mut(small_2d(), obstacles=[{"box_min_m": [0.0, 0.0], "box_max_m": [0.1, 0.06]}]),
                                 "fluid.regions[0]"),
}


@pytest.mark.parametrize("case", sorted(TRACEBACK_CASES))
def test_former_tracebacks_are_one_line_errors(tmp_path, case):
    make, key = TRACEBACK_CASES[case]
    scene = write(tmp_path, make())
    v, r = both(tmp_path, scene)
    assert_user_error(scene, v, key, one_line=False)
    assert_user_error(scene, r, key)
    assert not (tmp_path / "out").exists()


def test_region_outside_a_mesh_tank_and_deep_toml(tmp_path):
    import trimesh

    m = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    m.apply_translation((0.05, 0.05, 0.05))
    m.export(tmp_path / "tank.stl")
    d = small_2d()
    d["simulation"]["dimension"] = 3
    d["fluid"]["spacing_m"] = 0.02
    d["fluid"]["regions"] = [{"box_min_m": [0.5, 0.5, 0.0], "box_max_m": [0.6, 0.6, 0.05]}]
    d["tank"] = {"mesh": str(tmp_path / "tank.stl")}
    d["output"]["gauges"] = []
    scene = write(tmp_path, d)
    v, r = both(tmp_path, scene)
    assert_user_error(scene, v, "fluid.regions[0]", "outside the tank mesh", one_line=False)
    assert_user_error(scene, r, "fluid.regions[0]", "seeds no water particle")
    deep = tmp_path / "deep.toml"
    deep.write_text("a = " + "[" * 3000 + "1" + "]" * 3000 + "\n")
    v, r = both(tmp_path, deep)
    assert_user_error(deep, v, None, "nested too deeply", one_line=False)
    assert_user_error(deep, r, None, "nested too deeply")


@pytest.mark.parametrize("device", ["gpu", "cuda:99", "CPU", "cuda:-1", ""])
def test_unknown_devices_exit_2_without_traceback(tmp_path, device):
    import warp as wp

    wp.init()
    if device == "cuda:99" and wp.get_cuda_device_count() > 99:
        pytest.skip("a machine with 100 GPUs")
    ok = write(tmp_path, small_2d(), "ok.toml")
    for cmd in ("run", "validate"):
        rc, err, _ = run_cli([cmd, ok, "--device", device, "--out", tmp_path / "o"] if cmd == "run" else [cmd, ok, "--device", device])
        assert rc == 2 and "Traceback" not in err and err.startswith("error: --device: "), err
    bad = write(tmp_path, _mut(small_2d(), **{"simulation.device": device}), "bad.toml")
    v = run_cli(["validate", bad])[:2]
    r = run_cli(["run", bad, "--quiet", "--out", tmp_path / "out"])[:2]
    assert_user_error(bad, v, "simulation.device", one_line=False)
    assert_user_error(bad, r, "simulation.device")
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match="cuda:99|not a device name"):
        rockwave.Simulation(parse_scene(small_2d(), "x.toml"), device=device)


# --------------------------------------------------------------------------------------------
# 3. validate runs every check run runs before stepping
# --------------------------------------------------------------------------------------------


def _mesh_file(tmp, name, kind):
    import trimesh

    if kind == "garbage":
        (tmp / name).write_bytes(b"solid x\nthis is not a mesh \x00\x01\xff")
        return tmp / name
    if kind == "empty":
        (tmp / name).write_text("")
        return tmp / name
    m = trimesh.creation.box(extents=(0.04, 0.04, 0.04) if kind != "mm" else (40, 40, 40))
    m.apply_translation((0.05, 0.05, 0.04) if kind != "mm" else (50, 50, 40))
    if kind == "flat":
        m.vertices[:, 2] = 0.04
    if kind == "open":
        m = trimesh.Trimesh(m.vertices, m.faces[:-2], process=False)
    if kind == "dent":  # closed, not convex: one corner pushed towards the centre
        v = m.vertices.copy()
        i = int(np.argmax(v.sum(axis=1)))
        v[i] = v[i] + 0.8 * (m.centroid - v[i])
        m = trimesh.Trimesh(v, m.faces, process=False)
    p = tmp / name
    m.export(p)
    return p


def _region_mesh_scene(tmp, kind):
    d = small_2d()
    d["simulation"]["dimension"] = 3
    d["fluid"]["spacing_m"] = 0.02
    d["fluid"]["regions"] = [{"mesh": str(_mesh_file(tmp, f"r_{kind}.stl", kind))}]
    d["tank"] = {"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [0.1, 0.1, 0.1]}
    d["output"]["gauges"] = []
    return d


def _block_mesh_scene(tmp, kind, **block):
    return blocks_scene({"shape": "mesh", "mesh": str(_mesh_file(tmp, f"b_{kind}.stl", kind)), "position_m": [0, 0, 1], **block})


BOX = {"shape": "box", "size_m": [1.0, 1.0, 1.0]}
SLOPE = {"name": "slope", "shape": "prism", "kind": "fixed",
         "vertices_m": [[-3, -1, 0], [3, -1, 0], [-3, 1, 0], [3, 1, 0], [-3, -1, 2], [-3, 1, 2]]}
VALIDATE_CASES = {
    "region mesh open": (lambda t: _region_mesh_scene(t, "open"), "fluid.regions[0].mesh"),
    "region mesh empty": (lambda t: _region_mesh_scene(t, "empty"), "fluid.regions[0].mesh"),
    "region mesh garbage": (lambda t: _region_mesh_scene(t, "garbage"), "fluid.regions[0].mesh"),
    "region mesh flat": (lambda t: _region_mesh_scene(t, "flat"), "fluid.regions[0].mesh"),
    "region mesh in millimetres": (lambda t: _region_mesh_scene(t, "mm"), "fluid.regions[0].mesh"),
    "block mesh not convex, over its part bound": (lambda t: _block_mesh_scene(
        t, "dent", decomposition={"max_parts": 1, "concavity": 0.01, "cache_dir": str(t / "cache")}), "blocks[0].decomposition.max_parts"),
    "block mesh open": (lambda t: _block_mesh_scene(t, "open"), "blocks[0].mesh"),
    "overlapping blocks": (lambda t: blocks_scene(dict(BOX, name="a", position_m=[0, 0, 1]), dict(BOX, name="b", position_m=[0.5, 0, 1])),
                           "overlap"),
    "block inside the slope": (lambda t: blocks_scene(SLOPE, dict(BOX, name="rock", position_m=[-2.0, 0.0, 1.0])), "overlap"),
    "duplicate block names": (lambda t: blocks_scene(dict(BOX, name="a", position_m=[0, 0, 1]), dict(BOX, name="a", position_m=[3, 0, 1])),
                              "blocks[1].name"),
    "zero block size": (lambda t: blocks_scene(dict(BOX, size_m=[1.0, 0.0, 1.0], position_m=[0, 0, 1])), "blocks[0].size_m"),
    "negative block size": (lambda t: blocks_scene(dict(BOX, size_m=[1.0, -1.0, 1.0], position_m=[0, 0, 1])), "blocks[0].size_m"),
    "coplanar prism": (lambda t: blocks_scene({"shape": "prism", "vertices_m": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]}),
                       "blocks[0].vertices_m"),
    "1e9 blocks": (lambda t: blocks_scene(dict(BOX, position_m=[0, 0, 1], array={"count": [1000, 1000, 1000], "spacing_m": [1.5, 1.5, 1.5]})),
                   "needs about"),
    "1e10 particles": (lambda t: _mut(small_2d(), **{"fluid.spacing_m": 1e-6}), "fluid.spacing_m"),
    "gauge file is the USD file": (lambda t: _mut(small_2d(), **{"output.gauges_csv": "frames.usdc"}), "output.gauges_csv"),
    # issue 42
    "fixed step above the stability limit": (lambda t: _mut(small_2d(), **{"simulation.time_step": "fixed", "simulation.dt_s": 0.01}),
                                             "simulation.dt_s"),
    "height gauge in a blocks-only scene": (lambda t: _mut(blocks_scene(dict(BOX, name="b", position_m=[0, 0, 1])),
                                                           **{"output.gauges": [{"name": "h", "kind": "height", "position_m": [0, 0, 0]}]}),
                                            "output.gauges"),
    "block mesh is a symlink loop": (lambda t: _symlink_loop_scene(t), "blocks[0].mesh"),
    "2D block given 2 numbers": (lambda t: _mut(small_2d(), blocks=[dict(BOX, size_m=[0.02, 0.02], position_m=[0.05, 0.08])]),
                                 "blocks[0].size_m"),
}


def _symlink_loop_scene(tmp):
    (tmp / "loop_a.obj").symlink_to(tmp / "loop_b.obj")
    (tmp / "loop_b.obj").symlink_to(tmp / "loop_a.obj")
    return blocks_scene({"name": "m", "shape": "mesh", "mesh": str(tmp / "loop_a.obj"), "position_m": [0, 0, 1]})


@pytest.mark.parametrize("case", sorted(VALIDATE_CASES))
def test_validate_refuses_what_run_refuses(tmp_path, case):
    make, text = VALIDATE_CASES[case]
    scene = write(tmp_path, make(tmp_path))
    v, r = both(tmp_path, scene)
    assert_user_error(scene, v, None, text, one_line=False)
    assert_user_error(scene, r, None, text)
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------
# 4. silently accepted mistakes
# --------------------------------------------------------------------------------------------


def _errors(d) -> dict:
    with pytest.raises(SceneError) as e:
        parse_scene(d, "x.toml")
    return dict(e.value.errors)


def test_mistakes_that_were_accepted_silently():
    d = small_2d()
    d["fluid"]["regions"].append({"box_min_m": [0.05, 0.02], "box_max_m": [0.1, 0.05]})
    errs = _errors(d)
    assert "fluid.regions[1]" in errs and "fluid.regions[0]" in errs["fluid.regions[1]"] and "twice" in errs["fluid.regions[1]"]
    touching = small_2d()
    touching["fluid"]["regions"] = [{"box_min_m": [0.0, 0.0], "box_max_m": [0.05, 0.05]}, {"box_min_m": [0.05, 0.0], "box_max_m": [0.1, 0.05]}]
    parse_scene(touching, "x.toml")  # boxes that touch are fine
    for dev in ("gpu", "", "cuda:x", " cpu"):
        assert "simulation.device" in _errors(_mut(small_2d(), **{"simulation.device": dev}))
    for pos, kind, why in (([5.0, 0.0], "height", "outside"), ([0.05, -1.0], "pressure", "below the floor"),
                           ([-3.0, 0.05], "pressure", "outside")):
        errs = _errors(_mut(small_2d(), **{"output.gauges": [{"name": "g", "kind": kind, "position_m": pos}]}))
        assert why in errs["output.gauges[0].position_m"]
    for name in ("", "  ", "a\nb", "time_s"):
        errs = _errors(_mut(small_2d(), **{"output.gauges": [{"name": name, "kind": "height", "position_m": [0.05, 0.0]}]}))
        assert "output.gauges[0].name" in errs
    parse_scene(_mut(small_2d(), **{"output.gauges": [{"name": "h", "kind": "pressure", "position_m": [0.05, 0.15]}]}), "x.toml")


def test_empty_gauges_csv_means_skip(tmp_path):
    scene = write(tmp_path, _mut(small_2d(), **{"output.gauges_csv": "", "simulation.duration_s": 0.02}))
    rc, err, _ = run_cli(["run", scene, "--quiet", "--out", tmp_path / "o"])
    assert rc == 0, err
    assert (tmp_path / "o" / "run.json").is_file() and not [p for p in (tmp_path / "o").glob("*.csv") if p.name != "energy.csv"]


# --------------------------------------------------------------------------------------------
# 5. run-length check
# --------------------------------------------------------------------------------------------

BLOCK = {"name": "rock", "shape": "box", "size_m": [1.0, 1.0, 1.0], "position_m": [0.0, 0.0, 1.0]}
FLOOR = {"name": "floor", "shape": "box", "size_m": [4.0, 4.0, 0.5], "position_m": [0.0, 0.0, 0.25], "kind": "fixed"}
RUN_LENGTH_CASES = {
    "speed of sound 1e7": (lambda: _mut(small_2d(), **{"fluid.eos.speed_of_sound_m_s": 1e7}), "fluid.eos.speed_of_sound_m_s"),
    "gravity 1e6": (lambda: _mut(small_2d(), **{"gravity.acceleration_m_s2": [0.0, -1e6]}), "gravity.acceleration_m_s2"),
    "viscosity 1e9": (lambda: _mut(small_2d(), **{"fluid.viscosity.laplacian_pa_s": 1e9}), "fluid.viscosity.laplacian_pa_s"),
    "block density 1e-6": (lambda: _mut(blocks_scene(FLOOR, dict(BLOCK, density_kg_m3=1e-6)), **{"simulation.duration_s": 2.0}),
                           "blocks[1].density_kg_m3"),
    "contact stiffness 1e30": (lambda: blocks_scene(FLOOR, dict(BLOCK, material={"normal_stiffness_n_m": 1e30})),
                               "blocks[1].material.normal_stiffness_n_m"),
    "fixed dt 1e-9": (lambda: _mut(small_2d(), **{"simulation.time_step": "fixed", "simulation.dt_s": 1e-9, "simulation.duration_s": 1.0}),
                      "simulation.dt_s"),
    "spacing far below the scene size": (lambda: _mut(small_2d(), **{"fluid.spacing_m": 2e-5, "simulation.duration_s": 10.0}),
                                         "fluid.spacing_m"),
    # issue 42: the key of what is wrong, not of the step
    "duration 1e300": (lambda: _mut(small_2d(), **{"simulation.duration_s": 1e300}), "simulation.duration_s"),
    "region velocity 1e4": (lambda: _mut(small_2d(), **{"fluid.regions.0.velocity_m_s": [1e4, 0.0]}), "fluid.regions[0].velocity_m_s"),
}


@pytest.mark.parametrize("case", sorted(RUN_LENGTH_CASES))
def test_run_length_check_stops_unit_mistakes_before_stepping(tmp_path, case):
    make, key = RUN_LENGTH_CASES[case]
    d = make()
    scene = parse_scene(copy.deepcopy(d), "x.toml")
    with pytest.raises(SceneError) as e:
        preflight.check_run_length(scene, "cpu")
    assert [k for k, _ in e.value.errors] == [key], e.value
    assert "--yes" in str(e.value)
    rl = preflight.check_run_length(scene, "cpu", force=True)
    assert rl.steps > 0 and rl.wall_s > 0
    path = write(tmp_path, d)
    v, r = both(tmp_path, path)
    assert_user_error(path, v, key, one_line=False)
    assert_user_error(path, r, key)


def test_run_length_estimate_and_measured_cost():
    scene = parse_scene(small_2d(), "x.toml")
    rl = preflight.estimate_run_length(scene, "cpu")
    assert not rl.measured and rl.dt_key and rl.steps == pytest.approx(scene.simulation.duration_s / rl.dt)
    assert preflight.check_run_length(scene, "cpu").steps == rl.steps
    # a measured cost (as the run loop passes after its first steps) and the step in use
    slow = preflight.estimate_run_length(scene, "cpu", duration=2.0, seconds_per_step=0.5, dt=1e-4)
    assert slow.measured and slow.steps == pytest.approx(2e4) and slow.wall_s == pytest.approx(1e4)
    with pytest.raises(SceneError, match="more than 60 min"):
        preflight.check_run_length(scene, "cpu", duration=2.0, seconds_per_step=0.5, dt=1e-4, max_wall_s=3600)
    with pytest.raises(SceneError, match="more than 1e\\+03 steps"):
        preflight.check_run_length(scene, "cpu", max_steps=1e3, duration=1.0)
    # every shipped scene passes (all stay far below the thresholds)
    for p in sorted((ROOT / "scenes").glob("*.toml")):
        rl = preflight.check_run_length(load_scene(p), "cpu")
        assert rl.steps < 1e6, p


def test_yes_runs_a_refused_scene(tmp_path):
    d = _mut(small_2d(), **{"fluid.eos.speed_of_sound_m_s": 0.5, "simulation.duration_s": 0.02})
    path = write(tmp_path, d)
    rc, err, _ = run_cli(["run", path, "--quiet", "--out", tmp_path / "o"])
    assert rc == 2 and "fluid.eos.speed_of_sound_m_s" in err and "below the expected flow speed" in err
    rc, err, _ = run_cli(["validate", path, "--yes"])
    assert rc == 0, err
    rc, err, _ = run_cli(["run", path, "--quiet", "--yes", "--out", tmp_path / "o"])
    assert rc in (0, 1) and "Traceback" not in err, err


# --------------------------------------------------------------------------------------------
# 6. guard: blow-up advice, leaks
# --------------------------------------------------------------------------------------------


def _poison_after(sim, steps):
    step = sim.step

    def wrapped(dt=None):
        step(dt)
        if sim.steps == steps:
            v = sim.state.v.numpy()
            v[3] = (np.nan, 0.0, 0.0)
            sim.state.v.assign(v)

    sim.step = wrapped


def test_blowup_advice_names_the_speed_of_sound_when_it_is_too_low(tmp_path):
    d = _mut(small_2d(), **{"fluid.eos.speed_of_sound_m_s": 3.0, "simulation.duration_s": 0.05})  # 10 u_max ~ 9.9 m/s
    sim = rockwave.Simulation(parse_scene(d, "x.toml"), device=DEVICE)
    _poison_after(sim, 5)
    with pytest.raises(rockwave.SimulationError) as e:
        sim.run(tmp_path, progress=False, checkpoint_interval_s=0)
    msg = str(e.value)
    assert "set fluid.eos.speed_of_sound_m_s >= 9." in msg and "simulation.cfl_number" not in msg and "suggested time step" not in msg
    assert e.value.suggested_dt is None and e.value.key == "fluid.eos.speed_of_sound_m_s"


def test_blowup_advice_never_suggests_an_infinite_step():
    from rockwave.sim.guard import BlowUpError, HealthGuard

    sim = rockwave.Simulation(parse_scene(small_2d(), "x.toml"), device=DEVICE)
    guard = HealthGuard(sim)
    sim.clock.dt = math.inf
    with pytest.raises(BlowUpError) as e:
        guard._fail("something")
    assert "inf s" not in str(e.value) and "suggested time step" not in str(e.value) and "cfl_number" in str(e.value)
    assert e.value.suggested_dt is None


def test_leaks_counted_exactly_through_walls_or_over_the_top():
    from rockwave.sim.guard import HealthGuard

    sim = rockwave.Simulation(parse_scene(small_2d(), "x.toml"), device=DEVICE)
    g = HealthGuard(sim)
    x = sim.positions().copy()
    assert g._count_leaks(x) == (0, 0)
    x[0] = (-0.5, 0.02)  # through the left wall (never above the top, 0.1 m)
    x[1] = (0.05, -0.5)  # through the floor
    x[2] = (0.05, 0.5)  # above the open top: not left
    assert g._count_leaks(x) == (2, 0)
    x[2] = (0.5, 0.3)  # now outside, having been above the top: thrown over
    x[3] = (0.5, 0.3)  # outside above the top at once: thrown over
    assert g._count_leaks(x) == (2, 2)
    x[3] = (0.5, -0.01)  # falls down beside the tank: still over the top, counted once
    assert g._count_leaks(x) == (2, 2)


def test_water_leaking_through_the_walls_stops_the_run_with_the_key_to_change(tmp_path):
    scene = ROOT / "scenes" / "hydrostatic_tank.toml"
    d = tomllib.loads(scene.read_text())
    d["fluid"]["eos"]["speed_of_sound_m_s"] = 2.0
    d["fluid"]["fidelity"] = "draft"  # frozen (Akinci) walls: the ones this soft water leaks through
    d["simulation"].update(device="cpu", duration_s=1.0)
    path = write(tmp_path, d)
    rc, err, _ = run_cli(["run", path, "--quiet", "--out", tmp_path / "o"])
    assert rc == 2 and "below the expected flow speed" in err  # refused before stepping ...
    rc, err, _ = run_cli(["run", path, "--quiet", "--yes", "--out", tmp_path / "o"])  # ... and stopped when forced
    lines = [l for l in err.splitlines() if l.startswith("error:")]
    assert rc == 1 and len(lines) == 1 and "Traceback" not in err, err
    assert "left through the tank walls" in lines[0] and "fluid.eos.speed_of_sound_m_s >= 24" in lines[0]


def test_run_json_and_console_report_the_same_leak_count(tmp_path):
    d = small_2d()
    d["simulation"]["duration_s"] = 0.3
    d["fluid"]["regions"].append({"box_min_m": [0.0, 0.08], "box_max_m": [0.02, 0.1], "velocity_m_s": [-1.5, 3.0]})
    path = write(tmp_path, d)
    rc, err, out = run_cli(["run", path, "--quiet", "--out", tmp_path / "o"])
    assert rc == 0, err
    n = json.loads((tmp_path / "o" / "run.json").read_text())["particles_outside_domain"]
    assert n > 0 and f"; {n} fluid particle(s) left the tank" in out


# --------------------------------------------------------------------------------------------
# 7. quiet Warp; warnings on their own line
# --------------------------------------------------------------------------------------------


def test_quiet_prints_no_warp_banner_or_module_lines(tmp_path):
    path = write(tmp_path, small_2d())
    r = subprocess.run([sys.executable, "-m", "rockwave", "run", str(path), "--quiet", "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    noise = [l for l in (r.stderr + r.stdout).splitlines() if l.startswith(("Warp ", "Module ", "   "))]
    assert not noise, noise


def test_quiet_run_prints_no_warp_line_at_all(tmp_path):
    """`run --quiet` is fully quiet: not even the "Warp CUDA warning: Could not find or load the NVIDIA CUDA
    driver" note that Warp's native library writes to file descriptor 2 on a machine without a GPU
    (rockwave.base.device.init_warp holds it back), and no Warp deprecation note from the surface."""
    d = small_2d()
    d["output"]["surface"] = {"enabled": True}
    path = write(tmp_path, d)
    r = subprocess.run([sys.executable, "-m", "rockwave", "run", str(path), "--quiet", "--device", "cpu", "--duration", "0.002",
                        "--out", str(tmp_path / "o")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    warp_lines = [l for l in (r.stderr + r.stdout).splitlines() if "Warp" in l or "NVIDIA" in l]
    assert not warp_lines, warp_lines


def test_quiet_warp_init_keeps_real_errors_visible(monkeypatch, capfd):
    """init_warp(quiet=True) drops only the no-driver note written to descriptor 2 during wp.init(); any other
    native line comes back on stderr, and when the init fails everything written is shown before the error."""
    import os

    import warp as wp

    from rockwave.base.device import NO_DRIVER_NOTE, init_warp

    def noisy_init():
        os.write(2, f"Warp CUDA warning: {NO_DRIVER_NOTE}. GPU execution will not be available.\n".encode())
        os.write(2, b"Warp CUDA error: something real\n")

    monkeypatch.setattr(wp, "init", noisy_init)
    init_warp(quiet=True)
    err = capfd.readouterr().err
    assert "something real" in err and NO_DRIVER_NOTE not in err

    def failing_init():
        noisy_init()
        raise RuntimeError("init failed")

    monkeypatch.setattr(wp, "init", failing_init)
    with pytest.raises(RuntimeError, match="init failed"):
        init_warp(quiet=True)
    err = capfd.readouterr().err
    assert "something real" in err and NO_DRIVER_NOTE in err
    os.write(2, b"descriptor 2 restored\n")
    assert "descriptor 2 restored" in capfd.readouterr().err


class _Tty(io.StringIO):
    def isatty(self):
        return True


def test_a_warning_starts_on_a_fresh_line_below_the_progress_bar():
    stream = _Tty()
    old = warnings.showwarning
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        seen = []
        warnings.showwarning = lambda message, *a, **k: (stream.write(f"warning: {message}\n"), seen.append(message))
        bar = Progress(1.0, 10, stream=stream)
        bar.update(0.5, 10, force=True)
        warnings.warn("careful")
        bar.update(0.7, 14, force=True)
        bar.close()
        warnings.warn("after")
    warnings.showwarning = old
    text = stream.getvalue()
    assert "\nwarning: careful\n" in text and "s\rwarning" not in text and "ETA" in text.split("warning: careful")[0]
    assert text.endswith("\nwarning: after\n") and len(seen) == 2


# --------------------------------------------------------------------------------------------
# 8. fuzz: mutations of every shipped scene through validate and run
# --------------------------------------------------------------------------------------------

SHIPPED = sorted(p.stem for p in (ROOT / "scenes").glob("*.toml"))
FUZZ_PARTICLES = 1500
FUZZ_MAX_STEPS = 1500
FUZZ_EXAMPLES = 12  # per shipped scene, derandomized: the same mutations on every run  # validate and run refuse the same longer runs (patched thresholds)


def _absolute_paths(node, base: Path):
    if isinstance(node, dict):
        for k, v in node.items():
            if k in ("mesh", "file", "cache_dir") and isinstance(v, str):
                node[k] = str((base / v).resolve())
            else:
                _absolute_paths(v, base)
    elif isinstance(node, list):
        for v in node:
            _absolute_paths(v, base)


def _small(name: str) -> dict:
    """A shipped scene made small: few particles and blocks, a few steps, no surface."""
    d = tomllib.loads((ROOT / "scenes" / f"{name}.toml").read_text())
    _absolute_paths(d, ROOT / "scenes")
    d["simulation"].update(device="cpu", duration_s=0.002)
    out = d.setdefault("output", {})
    out.update(frame_rate_hz=1000.0, checkpoint_interval_s=0.0, vtk="")
    out["surface"] = {"enabled": False}
    for b in d.get("blocks", []):
        if "array" in b:
            b["array"]["count"] = [min(c, 2) for c in b["array"].get("count", [1, 1, 1])]
    for r in d.get("rock_mass", []):  # a corner of the mass (rock_slope_10k: 10,000 blocks -> 27)
        reg = r.get("region", {})
        if {"box_min_m", "box_max_m", "orientation_deg"} <= set(reg):
            resize_box_region(r, [min(1.5, hi - lo) for lo, hi in zip(reg["box_min_m"], reg["box_max_m"])])
    if "fluid" in d:
        est = preflight.estimate(parse_scene(copy.deepcopy(d), ROOT / "scenes" / f"{name}.toml"))
        n = est.fluid_particles + est.boundary_particles
        if n > FUZZ_PARTICLES:
            d["fluid"]["spacing_m"] *= (n / FUZZ_PARTICLES) ** (1.0 / d["simulation"].get("dimension", 3)) * 1.05
    return d


def _leaves(node, prefix=()):
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _leaves(v, prefix + (k,))
    elif isinstance(node, list) and node and all(isinstance(i, dict) for i in node):
        for i, v in enumerate(node):
            yield from _leaves(v, prefix + (i,))
    else:
        yield prefix


@st.composite
def _scene_mutation(draw, d):
    """One mutation of a scene dict: a leaf scaled, negated, zeroed, retyped, emptied or removed; an
    unknown key; or one of the unit mistakes and odd values seen in the field."""
    d = copy.deepcopy(d)
    leaves = sorted(_leaves(d), key=str)
    kind = draw(st.sampled_from(["scale", "value", "delete", "unknown", "special"]))
    if kind == "special":
        path, value = draw(st.sampled_from([
            (("simulation", "device"), "gpu"), (("simulation", "device"), ""), (("simulation", "duration_s"), 1e9),
            (("gravity", "acceleration_m_s2"), [0.0, 0.0, 1e6]), (("gravity", "acceleration_m_s2"), [0.0, 9.81]),
            (("fluid", "support_radius_ratio"), 1.0), (("fluid", "eos", "speed_of_sound_m_s"), 1e300),
            (("output", "gauges_csv"), ""), (("output", "usd"), "gauges.csv"), (("simulation", "time_step"), "fixed"),
        ]))
    else:
        path = draw(st.sampled_from(leaves))
        value = None
    node = d
    for k in path[:-1]:
        if isinstance(node, dict) and k in node or isinstance(node, list) and isinstance(k, int) and k < len(node):
            node = node[k]
        else:
            return d, ("skip", path)
    last = path[-1]
    if not isinstance(node, dict):
        return d, ("skip", path)
    old = node.get(last)
    if kind == "special":
        node[last] = value
    elif kind == "delete":
        node.pop(last, None)
    elif kind == "unknown":
        node[last + "_zz"] = 1.0
    elif kind == "value":
        node[last] = draw(st.sampled_from(["", "x", True, 0, -1, [], [1.0], {"a": 1}, 1e30, -1e-30]))
    else:
        f = draw(st.sampled_from([0.0, -1.0, 1e-6, 1e6, 1e30, 0.5, 2.0, 10.0]))
        if isinstance(old, bool) or old is None:
            node[last] = not old if isinstance(old, bool) else f
        elif isinstance(old, (int, float)):
            node[last] = type(old)(old * f) if isinstance(old, float) else int(old * f)
        elif isinstance(old, list) and old and all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in old):
            i = draw(st.integers(0, len(old) - 1))
            node[last] = list(old)
            node[last][i] = old[i] * f
        else:
            node[last] = f
    return d, (kind, path)


@pytest.mark.parametrize("name", SHIPPED)
def test_fuzz_mutated_shipped_scenes_validate_and_run_agree(tmp_path, name):
    """Each mutated scene: validate and run (a few steps, CPU) end in success or a one-line error with
    exit code 2 (a run may also end in a one-line blow-up, exit 1, and both in exit 1 when the build itself fails);
    never a traceback; and validate refuses exactly what run refuses before stepping."""
    base = _small(name)
    for b in base.get("blocks", []):  # a shipped decomposition cache is copied: mutations never write into scenes/
        cache = b.get("decomposition", {}).get("cache_dir")
        if cache:
            b["decomposition"]["cache_dir"] = str(shutil.copytree(cache, tmp_path / "decompositions", dirs_exist_ok=True))
    counter = iter(range(10**6))

    @settings(max_examples=FUZZ_EXAMPLES, derandomize=True, deadline=None, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
    @given(_scene_mutation(base))
    @example((base, ("none", ())))  # the small scene itself runs
    def check(mutated):
        d, what = mutated
        folder = tmp_path / str(next(counter))
        folder.mkdir()
        path = folder / f"{name}.toml"
        try:
            path.write_text(to_toml(d))
        except TypeError:
            return
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(preflight, "MAX_STEPS", FUZZ_MAX_STEPS)
            mp.setattr(preflight, "MAX_WALL_S", 60.0)
            rv, ev, _ = run_cli(["validate", path, "--device", "cpu"])
            rr, er, _ = run_cli(["run", path, "--device", "cpu", "--quiet", "--out", folder / "out"])
        assert rv in (0, 1, 2) and rr in (0, 1, 2), (what, ev, er)
        assert rv != 1 or rr == 1, (what, ev, er)  # validate builds the simulation: a build that fails fails in both
        assert "Traceback" not in ev + er
        if rr:
            lines = [l for l in er.splitlines() if l.startswith("error:")]
            assert len(lines) == 1, (what, er)
        assert (rv == 2) == (rr == 2), (what, ev, er)

    check()
