"""The shape of the code, checked by behaviour: readers and recorders only read, the clock alone
chooses the step and says which solver set it, the ghost step composes the fluid step, every solver
state travels in a checkpoint, and an option a method cannot honour is a SceneError."""

import copy
import math

import numpy as np
import pytest

import rockwave
from rockwave.scene.format import SceneError, load_scene, parse_scene
from rockwave.sim import checkpoint

from conftest import DEVICE
from helpers import ROOT, gauge_level_reference, tank_2d, to_toml, with_changes


def _dam_break_3d(spacing=0.08):
    scene = load_scene(ROOT / "scenes" / "dam_break_3d.toml")
    scene.fluid["spacing_m"] = spacing
    return rockwave.Simulation(scene, device=DEVICE)


def _solver_snapshot(sim) -> dict:
    fs, st = sim.fluid_solver, sim.state
    out = {k: getattr(st, k).numpy().copy() for k in ("x", "v", "rho", "pressure", "ids")}
    out.update(nbr=fs.list_entries.numpy().copy(), count=fs.list_counts.numpy().copy(), x_build=fs.list_build_positions.numpy().copy(),
               rebuild=fs.rebuild_flag.numpy().copy(), order=fs.cell_order.numpy().copy())
    return out


def test_readers_leave_the_state_lists_and_order_untouched():
    """After reordered chunk steps (the particles sorted by cell), reading positions, velocities,
    densities, pressures, gauges and the energy changes no array of the state or the solver (particle
    order, neighbour lists, cell grid, rebuild flag), gives the particles in the seeded order, and a run
    that reads after every step stays bit-identical to one that never reads."""
    a, b = _dam_break_3d(), _dam_break_3d()
    assert a.gauge_names, "the scene has gauges"
    a.step_many(12)
    b.step_many(12)
    assert a.fluid_solver.sorted_by_cell
    before = _solver_snapshot(a)
    x, v = a.positions(), a.velocities()
    rho, p = a.densities(), a.pressures()
    g = a.gauges()
    a.kinetic_energy()
    after = _solver_snapshot(a)
    for k in before:
        assert np.array_equal(before[k], after[k]), f"reading changed {k}"
    ids = before["ids"]
    nf = a.n_fluid
    assert np.array_equal(x[ids], before["x"][:nf, :3].astype(np.float64))  # seeded order
    assert np.array_equal(v[ids], before["v"][:nf, :3].astype(np.float64))
    assert np.array_equal(rho[ids], before["rho"].astype(np.float64))
    assert np.array_equal(p[ids], before["pressure"].astype(np.float64))
    assert set(g) == set(a.gauge_names)
    view = a.readers.view("x")  # the fast path: the reader's own host buffer, float32, the seeded order
    assert view.dtype == np.float32 and np.array_equal(view[:, :3].astype(np.float64), x)
    assert np.array_equal(_solver_snapshot(a)["x"], before["x"])
    for _ in range(6):
        a.step()
        a.positions(), a.gauges()
        b.step()
    assert np.array_equal(a.positions(), b.positions()) and np.array_equal(a.densities(), b.densities())


def _gauge_reference(sim) -> dict:
    """The gauges from their definition (rockwave/sim/readers.py Gauges), in numpy."""
    m = sim.fluid
    H = m.support_radius
    out = {}
    for gg in sim.scene.output.gauges:
        pos = np.array(list(gg.position_m) + [0.0] * (3 - len(gg.position_m)))
        if gg.kind == "height":
            out[gg.name] = gauge_level_reference(sim, gg.name)
        else:
            r2 = ((sim.state.x.numpy()[: m.n_fluid].astype(np.float64) - pos) ** 2).sum(1)
            w = np.where(r2 < H * H, 1.0, 0.0)
            out[gg.name] = w  # the pressure check below uses the Shepard sum
    return out


def test_gauges_on_the_device_match_their_definition():
    """Height gauges: the top of the continuous water column (tests/helpers.py gauge_level_reference, numpy on
    the host); pressure gauges: a Shepard interpolation, so within the range of the pressures of the particles in their support (how close
    that is to hydrostatics is the accuracy issue's business, not the reader's)."""
    d = tank_2d(width=0.4, depth=0.2, height=0.4, spacing=0.01)
    d["output"] = {"gauges": [{"name": "h1", "kind": "height", "position_m": [0.1, 0.0]},
                              {"name": "h2", "kind": "height", "position_m": [0.27, 0.0]},
                              {"name": "p", "kind": "pressure", "position_m": [0.2, 0.05]}]}
    sim = rockwave.Simulation(parse_scene(d, "g.toml"), device=DEVICE)
    sim.advance(0.02)
    got, ref = sim.gauges(), _gauge_reference(sim)
    for name in ("h1", "h2"):
        assert got[name] == pytest.approx(ref[name], abs=1e-6), name
        assert got[name] == pytest.approx(0.2, abs=0.5 * 0.01)  # the water's depth at rest
    p = sim.state.pressure.numpy()[ref["p"] > 0]
    assert p.min() - 1e-3 <= got["p"] <= p.max() + 1e-3
    assert got["p"] > 0  # below the surface


def test_the_clock_alone_chooses_the_step_and_names_the_limit():
    """The clock's target is the smallest of the present solvers' limits and it names that solver; the
    fluid-only scene is fluid-limited, a blocks-only scene block-limited, and run.json says which."""
    sim = rockwave.Simulation(parse_scene(tank_2d(), "t.toml"), device=DEVICE)
    assert set(sim.clock.limits) == {"fluid"} and sim.clock.limiting == "fluid"
    sim.advance(0.005)
    sim.clock.steps = 0  # the next update evaluates the limits of the current motion
    sim.clock.update_target()
    assert sim.clock.target == sim.fluid_solver.stable_dt(sim.state)
    blocks = rockwave.Simulation(load_scene(ROOT / "scenes" / "block_on_incline.toml"), device=DEVICE)
    assert blocks.clock.limiting == "blocks" and blocks.clock.target == blocks.block_solver.stable_dt(blocks.block_state)
    coupled = rockwave.Simulation(load_scene(ROOT / "scenes" / "floating_box_2d.toml"), device=DEVICE)
    limits = {n: f(True) for n, f in coupled.clock.limits.items()}
    assert set(limits) == {"fluid", "coupling"}  # multi-rate: the blocks sub-step inside (tests/test_multirate.py)
    assert coupled.clock.target == min(limits.values()) and coupled.clock.limiting == min(limits, key=limits.get)
    block = coupled.block_solver.stable_dt(coupled.block_state)
    assert coupled.clock.substeps == math.ceil(coupled.clock.dt / block - 1e-9) and coupled.clock.block_dt <= block


def test_recorded_run_is_bit_identical_to_advancing_without_outputs(tmp_path):
    """The recorders (USD, gauge and block CSVs, ParaView) and the checkpoint captures only read: a run with
    every output gives the same particles and blocks, bit for bit (CPU), as advancing frame by frame without any."""
    scene = load_scene(ROOT / "scenes" / "floating_box_2d.toml")
    scene.simulation["duration_s"] = 0.1  # 3 frames at 30 Hz
    scene.output["vtk"] = "vtk"
    a = rockwave.Simulation(scene, device=DEVICE)
    a.run(tmp_path / "out", progress=False, checkpoint_interval_s=1e-9)  # a checkpoint written after every frame
    b = rockwave.Simulation(scene, device=DEVICE)
    fps = scene.output.frame_rate_hz
    for f in range(1, int(np.floor(0.1 * fps + 1e-9)) + 1):
        b.advance(f / fps - b.time)
    assert a.steps == b.steps
    if DEVICE == "cpu":
        assert np.array_equal(a.positions(), b.positions()) and np.array_equal(a.velocities(), b.velocities())
        assert np.array_equal(a.block_positions(), b.block_positions())
    else:  # CUDA: the atomics' order differs from run to run, with or without outputs
        assert np.abs(a.positions() - b.positions()).max() < 1e-3 * a.fluid.spacing
    assert (tmp_path / "out" / "vtk" / "rockwave.pvd").is_file() and (tmp_path / "out" / "checkpoint.npz").is_file()


def _ghost_scene(name, **changes):
    d = load_scene(ROOT / "scenes" / name).raw
    return parse_scene(with_changes(copy.deepcopy(d), **changes), name, ROOT / "scenes")


def test_ghost_step_composes_the_fluid_step_and_honours_density_diffusion():
    """Ghost SPH adds its terms through FluidSolver.step's hooks (it has no step of its own), so density
    diffusion, which the copied ghost step used to drop, acts there too: the same scene with and without
    delta = 0.1 ends with other densities, and the added term keeps them bounded."""
    from rockwave.sph.fluid import FluidSolver
    from rockwave.sph.ghost import GhostFluidSolver

    assert GhostFluidSolver.step is FluidSolver.step
    runs = {}
    for delta in (0.0, 0.1):
        sim = rockwave.Simulation(_ghost_scene("ghost_dam_break_case1.toml", **{"fluid.spacing_m": 0.03,
                                                                                 "fluid.density_diffusion": delta}),
                                  device=DEVICE)
        for _ in range(60):
            sim.step()
        runs[delta] = sim
    r0, r1 = runs[0.0].densities(), runs[0.1].densities()
    assert not np.array_equal(r0, r1)
    assert runs[0.1].fluid_solver.diffusion_rate is not None
    assert np.abs(r1 - r1.mean()).max() < 3 * np.abs(r0 - r0.mean()).max()  # no blow-up from the added term


def test_persistent_ghosts_travel_in_checkpoints():
    """The ghost solver's kept ghosts are part of the checkpoint: a simulation restored from a checkpoint
    continues with the same ghosts and the same motion, bit for bit on the CPU, as the one that took it
    (persistent ghosts, summation density: the zero-g disc)."""
    scene = load_scene(ROOT / "scenes" / "drop_zero_g_2d.toml")
    a = rockwave.Simulation(scene, device=DEVICE)
    assert a.fluid_solver.persistent
    for _ in range(5):
        a.step()
    arrays, groups = checkpoint.pack(a, checkpoint.capture(a))
    meta = {"scene": checkpoint.scene_identity(a), "groups": groups}
    assert "fluid/solver/ghost_x" in arrays
    b = rockwave.Simulation(scene, device=DEVICE)
    checkpoint.restore(b, arrays, meta)
    assert b.fluid_solver.n_ghost == a.fluid_solver.n_ghost > 0
    for _ in range(5):
        a.step()
        b.step()
    assert np.array_equal(a.fluid_solver.ghost_positions(), b.fluid_solver.ghost_positions())
    assert np.array_equal(a.positions(), b.positions())


@pytest.mark.parametrize("changes, key", [
    ({"fluid.method": "basic"}, "fluid.ghost"),
    ({"fluid.ghost.persistent": False, "fluid.ghost.sampler": "tile", "fluid.ghost.attempts": 8}, "fluid.ghost.attempts"),
    ({"fluid.density": "continuity", "fluid.ghost.density_cap": True}, "fluid.ghost.density_cap"),
    ({"fluid.density_diffusion": 0.1}, "fluid.density_diffusion"),
])
def test_an_option_the_method_cannot_honour_is_a_scene_error(changes, key):
    """Settings that the chosen method would ignore name their key (the zero-g drop: ghost method,
    persistent darts, summation density, density cap)."""
    with pytest.raises(SceneError) as e:
        _ghost_scene("drop_zero_g_2d.toml", **changes)
    assert key in str(e.value)
    _ghost_scene("drop_zero_g_2d.toml")  # the shipped scene itself is fine


def test_physics_modules_import_no_writer():
    """Solvers, state and the facade load without the USD library or the writers (recorders live in
    rockwave/output, the run loop imports them)."""
    import subprocess
    import sys

    code = ("import sys, rockwave, rockwave.sph.fluid, rockwave.sph.ghost, rockwave.dda.blocks, rockwave.coupling.penalty, rockwave.sim.clock, "
            "rockwave.sim.readers, rockwave.build.builder; "
            "bad = [m for m in sys.modules if m == 'pxr' or m.startswith('pxr.') or m.startswith('rockwave.output')]; "
            "print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stdout + r.stderr


# ------------------------------------------------------------------ the run loop ----------

def _one_frame_scene(duration=0.03):
    d = tank_2d(width=0.1, depth=0.05, height=0.1, spacing=0.01)
    d["simulation"]["duration_s"] = duration
    d["output"] = {"frame_rate_hz": 1.0 / duration}  # one frame: the whole run
    return parse_scene(d, "one_frame.toml")


def test_progress_and_health_checks_run_inside_a_frame(tmp_path, monkeypatch, capsys):
    """Whatever the frame rate, the run loop redraws the progress line and runs the blow-up guard every
    WATCH_INTERVAL_S of wall time inside a frame (here 0: after every step)."""
    from rockwave.app import run as run_mod
    monkeypatch.setattr(run_mod, "WATCH_INTERVAL_S", 0.0)
    sim = rockwave.Simulation(_one_frame_scene(), device=DEVICE)
    calls = []
    check = sim.check_health
    monkeypatch.setattr(sim, "check_health", lambda x, v: calls.append(sim.steps) or check(x, v))
    sim.run(tmp_path, progress=True)
    assert sim.steps > 5
    assert len(calls) > 5  # frame 0, after every step (every chunk of steps on a GPU), frame 1
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "steps/s" in ln]
    assert len(lines) >= len(calls) - 2 and "(fluid)" in lines[0]  # the limit that sets the step


def test_measured_cost_of_the_first_steps_stops_a_run_that_would_not_end(tmp_path, monkeypatch):
    """After its first steps the run loop checks the run length with their measured cost: above the wall
    limit it stops with a SceneError naming the key to change; force=True (CLI --yes) runs on."""
    from rockwave.build import preflight
    monkeypatch.setattr(preflight, "MAX_WALL_S", 1e-6)
    sim = rockwave.Simulation(_one_frame_scene(0.05), device=DEVICE)
    with pytest.raises(SceneError) as e:
        sim.run(tmp_path / "a", progress=False)
    assert "--yes" in str(e.value) and "simulation.duration_s" in str(e.value) and sim.steps <= 60  # stopped early
    sim = rockwave.Simulation(_one_frame_scene(0.05), device=DEVICE)
    assert sim.run(tmp_path / "b", progress=False, force=True)["simulated_s"] == pytest.approx(0.05)


def test_a_run_killed_early_leaves_a_stage_and_a_checkpoint(tmp_path):
    """Killed (SIGKILL) soon after its first frames, a run leaves a USD stage that opens with those frames
    and a checkpoint that --resume continues from (before: nothing until 50 frames and 600 s)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from pxr import Usd

    d = tank_2d(width=0.1, depth=0.05, height=0.1, spacing=0.01)
    d["simulation"]["duration_s"] = 100.0
    d["simulation"]["device"] = DEVICE
    d["output"] = {"frame_rate_hz": 200.0}
    scene = tmp_path / "long.toml"
    scene.write_text(to_toml(d))
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "rockwave", "run", str(scene), "--out", str(out), "--quiet", "--yes"],
                         cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 120
        while time.time() < deadline and not ((out / "checkpoint.npz").exists() and (out / "frames.clips").exists()
                                              and len(list((out / "frames.clips").glob("chunk_*"))) >= 2):
            time.sleep(0.2)
            assert p.poll() is None, p.stderr.read().decode()
    finally:
        os.kill(p.pid, signal.SIGKILL)
        p.wait()
    stage = Usd.Stage.Open(str(out / "frames.usdc"))
    assert stage.GetEndTimeCode() >= 1
    r = subprocess.run([sys.executable, "-m", "rockwave", "run", str(scene), "--out", str(out), "--quiet", "--yes",
                        "--resume", "--duration", "0.03"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr


def test_a_fresh_run_replaces_the_previous_runs_outputs(tmp_path):
    """A fresh run in a folder used before removes what the previous run wrote there (its manifest lists it), so
    the folder never mixes two runs; a file of the user's stays."""
    d = tank_2d(width=0.1, depth=0.05, height=0.1, spacing=0.01)
    d["simulation"]["duration_s"] = 0.02
    d["output"] = {"frame_rate_hz": 100.0, "vtk": "paraview",
                   "gauges": [{"name": "h", "kind": "height", "position_m": [0.05, 0.0]}]}
    rockwave.Simulation(parse_scene(d, "a.toml"), device=DEVICE).run(tmp_path, progress=False)
    assert (tmp_path / "paraview").is_dir() and (tmp_path / "gauges.csv").is_file()
    (tmp_path / "notes.txt").write_text("mine")
    d["output"] = {"frame_rate_hz": 100.0}
    rockwave.Simulation(parse_scene(d, "a.toml"), device=DEVICE).run(tmp_path, progress=False)
    assert not (tmp_path / "paraview").exists() and not (tmp_path / "gauges.csv").exists()
    assert (tmp_path / "frames.usdc").is_file() and (tmp_path / "notes.txt").read_text() == "mine"


def test_resume_with_an_edited_scene_is_refused_or_says_what_changed(tmp_path, capsys):
    """--resume continues a checkpointed state: a changed physics key is refused naming it; a changed step
    setting or duration is allowed and printed."""
    d = tank_2d(width=0.1, depth=0.05, height=0.1, spacing=0.01)
    d["simulation"]["duration_s"] = 0.02
    d["output"] = {"frame_rate_hz": 100.0}
    rockwave.Simulation(parse_scene(d, "a.toml"), device=DEVICE).run(tmp_path, progress=False, checkpoint_interval_s=1e-9)
    edited = copy.deepcopy(d)
    edited["fluid"]["rest_density_kg_m3"] = 1025.0
    with pytest.raises(checkpoint.CheckpointError) as e:
        rockwave.Simulation(parse_scene(edited, "a.toml"), device=DEVICE).run(tmp_path, progress=False, resume=True)
    assert "fluid.rest_density_kg_m3" in str(e.value)
    longer = copy.deepcopy(d)
    longer["simulation"]["duration_s"] = 0.03
    longer["simulation"]["cfl_number"] = 0.2
    s = rockwave.Simulation(parse_scene(longer, "a.toml"), device=DEVICE).run(tmp_path, progress=False, resume=True)
    assert s["resumed_from_frame"] == 2 and "simulation.cfl_number" in capsys.readouterr().err


def test_queued_reads_give_the_state_they_were_queued_after():
    """view_async / gauges_async queue a read behind the steps launched so far: after more steps, result()
    still gives the state at queueing time (two host buffers per quantity), equal to the plain reads then."""
    sim = _dam_break_3d()
    sim.step_many(12)
    x0, g0 = sim.readers.view("x").copy(), sim.gauges()
    px, pg = sim.readers.view_async("x"), sim.readers.gauges_async()
    sim.step_many(3)
    later = sim.readers.view_async("x")  # the other buffer: the pending one stays
    g = pg.result()
    assert np.array_equal(px.result(), x0) and list(g) == list(g0)
    assert np.array_equal(list(g.values()), list(g0.values()), equal_nan=True)  # (a dry height gauge reads NaN)
    assert not np.array_equal(later.result(), x0)
