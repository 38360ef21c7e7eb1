"""Issue 42, the last rough edges a new user meets: Warp's kernel cache folder, the shipped scenes by name, the
memory check's 32-bit limit, the keys of run-length messages, validate's measured estimate, many blocks in USD
(batched authoring, a PointInstancer), the preview's files, walls and colours, the run header. (The resume items
are in tests/test_robustness.py, the bad-input tables in tests/test_hardening.py.)"""

import contextlib
import io
import os
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest

import rockwave
from rockwave.app import cli, preview
from rockwave.app.validate import validate
from rockwave.build import preflight
from rockwave.output import recorders as rec
from rockwave.output import usd
from rockwave.scene.format import SceneError, parse_scene

from helpers import ROOT, tank_2d, to_toml


def run_cli(args) -> tuple[int, str, str]:
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = cli.main([str(a) for a in args])
    return rc, err.getvalue(), out.getvalue()


def small_2d(duration=0.02) -> dict:
    d = tank_2d(width=0.1, depth=0.05, height=0.1, spacing=0.01)
    d["simulation"].update(duration_s=duration, device="cpu")
    d["output"] = {"frame_rate_hz": 100.0, "gauges": [{"name": "h", "kind": "height", "position_m": [0.05, 0.0]}]}
    return d


# --------------------------------------------------------------------------------------------
# Warp's kernel cache folder; commands that need no kernels never initialise Warp
# --------------------------------------------------------------------------------------------


def test_a_kernel_cache_folder_that_cannot_be_made_is_named_and_kernel_free_commands_never_initialise_warp(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text(to_toml(small_2d()))
    run = tmp_path / "run"
    assert run_cli(["run", scene, "--quiet", "--out", run])[0] == 0  # (with the working cache)
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    script = textwrap.dedent(f"""
        import contextlib, io, sys
        from rockwave.app import cli
        import warp
        ctx = warp._src.context
        def call(*args):
            err, out = io.StringIO(), io.StringIO()
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
                rc = cli.main(list(args))
            return rc, err.getvalue()
        for args in (["schema"], ["scenes"], ["preview", {str(run)!r}], ["plot", {str(run)!r}]):
            rc, err = call(*args)
            assert rc == 0 and ctx.runtime is None, (args, rc, err)
        for args in (["validate", {str(scene)!r}], ["run", {str(scene)!r}, "--quiet", "--out", {str(tmp_path / "o")!r}], ["info"]):
            rc, err = call(*args)
            print(rc, err.strip().replace("\\n", " | "))
    """)
    env = dict(os.environ, WARP_CACHE_PATH=str(blocker / "cache"))
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    assert len(lines) == 3, r.stdout
    for line in lines:  # exit 2, one line: the folder and the variable to set
        assert line.startswith("2 error: Warp's kernel cache folder") and str(blocker) in line and "WARP_CACHE_PATH" in line, line
        assert "|" not in line and "Traceback" not in line, line


# --------------------------------------------------------------------------------------------
# shipped scenes by name
# --------------------------------------------------------------------------------------------


def test_scenes_lists_the_shipped_scenes_and_a_bare_name_resolves_from_any_folder(tmp_path, monkeypatch):
    rc, _, out = run_cli(["scenes"])
    names = [line.split()[0] for line in out.splitlines()[1:]]
    assert rc == 0 and names == sorted(p.stem for p in (ROOT / "scenes").glob("*.toml")), out
    assert "dam_break_2d" in out and "Martin & Moyce" in out  # with the first sentence of its comment
    monkeypatch.chdir(tmp_path)
    assert cli.resolve_scene("dam_break_2d") == cli.resolve_scene("dam_break_2d.toml") == str(ROOT / "scenes" / "dam_break_2d.toml")
    assert cli.resolve_scene("sub/dam_break_2d.toml") == "sub/dam_break_2d.toml"  # a path stays a path
    rc, err, out = run_cli(["validate", "slide_2d_tiny", "--duration", "0.01"])
    assert rc == 0 and "slide_2d_tiny.toml: ok" in out, err
    (tmp_path / "dam_break_2d.toml").write_text(to_toml(small_2d()))  # a file of that name here wins
    assert cli.resolve_scene("dam_break_2d.toml") == "dam_break_2d.toml"
    rc, err, _ = run_cli(["validate", "no_such_scene"])
    assert rc == 2 and "no_such_scene" in err


# --------------------------------------------------------------------------------------------
# the memory check's 32-bit limit; validate's estimate
# --------------------------------------------------------------------------------------------


def test_a_neighbour_list_beyond_one_warp_array_is_refused_with_the_spacing(tmp_path, monkeypatch):
    """A 13 M-particle 3D dam break with a short --duration on a machine with the memory for it (an H200 host: patched
    here): no run-length refusal, so the memory check must catch the neighbour list of more than 2^31 - 1 entries (it
    used to end in Warp's own array-shape error, exit 1)."""
    monkeypatch.setattr(preflight, "available_bytes", lambda device: (140 * 2**30, 512 * 2**30))
    text = (ROOT / "scenes" / "dam_break_3d.toml").read_text().replace("spacing_m = 0.04", "spacing_m = 0.0037")
    scene = ROOT / "scenes" / "dam_break_3d.toml"
    d = parse_scene(__import__("tomllib").loads(text), scene, scene.parent)
    est = preflight.estimate(d)
    assert est.fluid_particles > 13e6 and est.neighbour_entries >= 2**31
    path = tmp_path / "big.toml"
    path.write_text(text.replace('"data/', f'"{ROOT / "scenes" / "data"}/'))
    for cmd in (["validate", path, "--duration", "0.01"], ["run", path, "--duration", "0.01", "--quiet", "--out", tmp_path / "o"]):
        rc, err, _ = run_cli(cmd)
        lines = [line for line in err.splitlines() if line.strip()]
        assert rc == 2 and len(lines) == 1 and str(path) in lines[0] and "fluid.spacing_m" in lines[0], err
        assert "one Warp array" in lines[0] and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_run_length_messages_name_what_is_wrong():
    with pytest.raises(SceneError) as e:
        preflight.check_run_length(parse_scene(_with(small_2d(), "simulation", duration_s=1e300), "x.toml"), "cpu")
    assert e.value.errors[0][0] == "simulation.duration_s" and "fluid.spacing_m" not in str(e.value)
    d = small_2d()
    d["fluid"]["regions"][0]["velocity_m_s"] = [1e4, 0.0]
    with pytest.raises(SceneError) as e:
        preflight.check_run_length(parse_scene(d, "x.toml"), "cpu")
    key, msg = e.value.errors[0]
    assert key == "fluid.regions[0].velocity_m_s" and "initial speed 1e+04 m/s of fluid.regions[0]" in msg, msg


def _with(d, section, **kw):
    d[section].update(kw)
    return d


def test_validate_measures_the_step_cost_and_takes_the_coupling_limit():
    """validate times a few steps on the device and steps at the built simulation's step where it is smaller (the
    coupling's penalty spring): its estimate of a coupled scene's steps is within 15% of a run's (it was 1.8-1.9x off)."""
    scene = rockwave.load_scene(ROOT / "scenes" / "slide_2d_tiny.toml")
    found = validate(scene, "cpu", duration=0.2)
    rl, sim = found["run_length"], found["simulation"]
    assert rl.measured and "measured here" in rl.describe() and rl.seconds_per_step > 0
    assert rl.dt <= sim.clock.target and sim.clock.limiting == "coupling"
    ran = rockwave.Simulation(scene, device="cpu")
    ran.advance(0.2)
    assert 0.85 < ran.steps / rl.steps < 1.15, (ran.steps, rl.steps)
    nominal = preflight.estimate_run_length(scene, "cpu", duration=0.2)
    assert not nominal.measured and "lower bound" in nominal.describe()


def test_the_usd_output_of_many_blocks_counts_in_the_run_length():
    d = {"simulation": {"duration_s": 10.0, "device": "cpu"}, "output": {"frame_rate_hz": 30.0},
         "blocks": [{"name": "b", "shape": "box", "size_m": [0.5, 0.5, 0.5], "position_m": [0, 0, 0.3],
                     "array": {"count": [100, 100, 100], "spacing_m": [0.6, 0.6, 0.6]}}]}
    rl = preflight.estimate_run_length(parse_scene(d, "x.toml"), "cpu")
    assert rl.blocks == 10**6 and rl.output_s == pytest.approx(preflight.usd_output_seconds(parse_scene(d, "x.toml"), 10**6, 10.0))
    assert rl.output_s > 0 and rl.wall_s >= rl.output_s
    d["blocks"][0]["array"]["count"] = [20, 20, 20]  # mesh prims: the set-up counts too
    few = preflight.usd_output_seconds(parse_scene(d, "x.toml"), 8000, 10.0)
    assert few > preflight.usd_output_seconds(parse_scene(d, "x.toml"), 8000, 10.0, setup=False) > 0
    d["output"]["usd"] = ""
    assert preflight.estimate_run_length(parse_scene(d, "x.toml"), "cpu").output_s == 0.0


# --------------------------------------------------------------------------------------------
# many blocks in USD
# --------------------------------------------------------------------------------------------

BLOCKS = {"simulation": {"duration_s": 0.04, "device": "cpu"}, "output": {"frame_rate_hz": 50.0},
          "blocks": [{"name": "floor", "shape": "box", "size_m": [4.0, 4.0, 0.2], "position_m": [0.0, 0.0, -0.1], "kind": "fixed"},
                     {"name": "cube", "shape": "box", "size_m": [0.2, 0.2, 0.2], "position_m": [-0.5, 0.0, 0.3],
                      "angular_velocity_rad_s": [0.0, 2.0, 1.0], "array": {"count": [2, 2, 1], "spacing_m": [0.5, 0.5, 0.5]}},
                     {"name": "wedge", "shape": "prism", "vertices_m": [[1, 0, 0.1], [1.3, 0, 0.1], [1, 0.3, 0.1], [1, 0, 0.4]]},
                     {"name": "soft", "shape": "box", "size_m": [0.2, 0.2, 0.2], "position_m": [0.5, 1.0, 0.3], "kind": "deformable"}]}


def _reference_blocks(sim, stage):
    """The block prims as UsdGeom authored them one by one before the batched authoring (the layout to keep)."""
    from pxr import UsdGeom, Vt

    UsdGeom.Scope.Define(stage, rec.BLOCKS_PRIM)
    for spec, prim in zip(sim.blocks.specs, rec.block_prim_paths(rec._prim_names(sim.blocks))):
        geo = spec.geometry
        mesh = UsdGeom.Mesh.Define(stage, prim)
        if spec.kind != "deformable":
            mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(geo.vertices, dtype=np.float32)))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray([len(f) for f in geo.faces]))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([int(i) for f in geo.faces for i in f]))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        if spec.kind != "deformable":
            mesh.AddTranslateOp()
            mesh.AddOrientOp()


def _subtree(layer, path):
    from pxr import Sdf

    out = Sdf.Layer.CreateAnonymous(".usda")
    Sdf.CreatePrimInLayer(out, path)
    Sdf.CopySpec(layer, path, out, path)
    return out.ExportToString()


def test_batched_block_authoring_writes_what_usdgeom_wrote(tmp_path):
    from pxr import Usd, UsdGeom

    sim = rockwave.Simulation(parse_scene(BLOCKS, "x.toml"), device="cpu")
    calls = []
    r = rec.UsdRecorder(sim, tmp_path / "frames.usdc", progress=lambda done, total: calls.append((done, total)))
    assert r.n_instanced == 0 and calls[-1] == (sim.blocks.num_blocks, sim.blocks.num_blocks)
    ref = Usd.Stage.CreateInMemory()
    UsdGeom.Xform.Define(ref, "/World")
    _reference_blocks(sim, ref)
    got = _subtree(r.writer.stage.GetRootLayer(), rec.BLOCKS_PRIM)
    assert got == _subtree(ref.GetRootLayer(), rec.BLOCKS_PRIM) and got.count("def Mesh") == sim.blocks.num_blocks
    r.close()


def test_many_blocks_are_the_instances_of_one_point_instancer(tmp_path, monkeypatch):
    """From INSTANCER_MIN_BLOCKS rigid/fixed blocks on (lowered here), they are one PointInstancer whose prototypes are
    their distinct shapes, posed by two arrays a frame; the preview draws them where the simulation has them."""
    from pxr import Usd, UsdGeom

    monkeypatch.setattr(rec, "INSTANCER_MIN_BLOCKS", 4)
    sim = rockwave.Simulation(parse_scene(BLOCKS, "x.toml"), device="cpu")
    sim.run(tmp_path, progress=False)
    stage = Usd.Stage.Open(str(tmp_path / "frames.usdc"))
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath(rec.INSTANCER_PRIM))
    assert inst and len(inst.GetPrototypesRel().GetTargets()) == 3  # floor, cube (4 copies), wedge
    idx = np.asarray(inst.GetProtoIndicesAttr().Get())
    ids = np.asarray(inst.GetIdsAttr().Get())
    names = sim.blocks.names
    assert [names[i] for i in ids] == [n for n in names if n != "soft"] and list(idx) == [0, 1, 1, 1, 1, 2]
    assert stage.GetPrimAtPath(f"{rec.BLOCKS_PRIM}/soft").IsA(UsdGeom.Mesh)  # deformable: its own mesh
    assert not stage.GetPrimAtPath(f"{rec.BLOCKS_PRIM}/cube_0")
    last = int(stage.GetEndTimeCode())
    pos = np.asarray(inst.GetPositionsAttr().Get(last))
    name, _ = usd.instancer_orientation_attr()
    q = np.asarray(stage.GetPrimAtPath(rec.INSTANCER_PRIM).GetAttribute(name).Get(last))
    assert np.allclose(pos, sim.block_positions()[ids], atol=1e-6)
    assert np.allclose(q, sim.block_state.orientations_numpy()[ids], atol=1e-3 if name == "orientations" else 1e-6)
    assert not np.allclose(q[1], [0, 0, 0, 1])  # the cubes turned
    drawn = preview.load_frame(tmp_path, last)["blocks"]
    world = sim.block_state.world_vertices()
    want = [world[names.index("soft")]] + [world[i] for i in ids]  # (the mesh prims come first)
    assert len(drawn) == len(want) and all(np.allclose(a, b, atol=1e-4) for a, b in zip(drawn, want))


# --------------------------------------------------------------------------------------------
# preview
# --------------------------------------------------------------------------------------------


def test_preview_names_each_view_draws_the_tank_and_obstacles_and_scales_pressure_robustly(tmp_path):
    d = {"simulation": {"dimension": 3, "duration_s": 0.02, "device": "cpu"},
         "fluid": {"spacing_m": 0.05, "eos": {"speed_of_sound_m_s": 20.0},
                   "regions": [{"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [0.3, 0.3, 0.3]}]},
         "tank": {"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [1.0, 0.3, 0.5]},
         "obstacles": [{"box_min_m": [0.6, 0.1, 0.0], "box_max_m": [0.7, 0.2, 0.1]}],
         "output": {"frame_rate_hz": 100.0}}
    path = tmp_path / "s.toml"
    path.write_text(to_toml(d))
    out = tmp_path / "run"
    assert run_cli(["run", path, "--quiet", "--out", out])[0] == 0
    files = set()
    for args in (["--color", "pressure"], ["--axis", "z"], ["--axis", "y", "--slice", "0.15"], []):
        rc, err, stdout = run_cli(["preview", out, *args])
        assert rc == 0, err
        files.add(Path(stdout.strip()).name)
    assert files == {"preview_00002_pressure_y.png", "preview_00002_speed_z.png", "preview_00002_speed_y_at0.15.png",
                     "preview_00002_speed_y.png"}
    boxes = preview.load_frame(out)["boxes"]
    assert [w for *_, w in boxes] == ["tank", "obstacle"] and np.allclose(boxes[1][1], [0.7, 0.2, 0.1])
    c = np.concatenate([np.linspace(0.0, 1000.0, 995), np.full(5, 1e6)])  # five hot particles
    lim = preview.color_limits(c, "pressure")
    assert lim["vmax"] < 1100 and lim["vmin"] < 100 and preview.color_limits(c, "speed") == {}
    assert preview.default_name(3, 2, "speed") == "preview_00003_speed.png"


# --------------------------------------------------------------------------------------------
# the run header
# --------------------------------------------------------------------------------------------


def test_the_run_header_names_the_support_radius(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text(to_toml(small_2d(duration=0.01)))
    rc, err, _ = run_cli(["run", path, "--out", tmp_path / "o"])
    header = err.splitlines()[[i for i, line in enumerate(err.splitlines()) if "fluid +" in line][0]]
    assert rc == 0 and "support 0.03 m" in header and "h =" not in header, header  # 3 spacings (standard fidelity)
