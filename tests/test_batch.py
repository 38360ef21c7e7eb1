"""Batched scenarios (rockwave/sim/batch.py, rockwave/output/batch.py, rockwave/app/batch.py; issue 40): a batch of
slide_2d_tiny variants (different friction, water depth and so particle count, slide position) stepped together
gives each scenario's solo trajectory and hazard summary within float32 round-off when the step is the same
(a fixed step; the block sub-step is the same: the varied keys leave the stiffest block's step alone); no
neighbour pair or block contact joins two scenarios; a scenario that blows up in a batch fails alone; the sweep
packs scenarios into batches."""

from __future__ import annotations

import copy
import json
import math
import tomllib

import numpy as np
import pytest

from rockwave.app import batch as batching
from rockwave.app import sweep
from rockwave.output.batch import BatchHazard
from rockwave.output.hazard import HazardMonitor, flat_metrics
from rockwave.scene.format import SceneError, parse_scene
from rockwave.sim.batch import BatchSimulation, check_template
from rockwave.sim.simulation import Simulation

from conftest import DEVICE
from helpers import ROOT, tank_2d

SCENE = ROOT / "scenes" / "slide_2d_tiny.toml"
T = 0.04  # 100 fixed steps of 4e-4 s
DT = 4e-4


def _variant(friction=15.0, depth=None, slide_dx=0.0, **sim) -> dict:
    d = tomllib.loads(SCENE.read_text())
    d["simulation"].update({"time_step": "fixed", "dt_s": DT, "duration_s": T, **sim})
    for b in d["blocks"]:
        if b["name"] == "slide":
            b["material"]["friction_angle_deg"] = friction
            b["position_m"][0] += slide_dx
    if depth is not None:
        d["fluid"]["regions"][0]["box_max_m"][1] = depth
    return d


def _scene(d: dict):
    return parse_scene(copy.deepcopy(d), SCENE, SCENE.parent)


VARIANTS = [_variant(), _variant(friction=22.0, depth=0.2), _variant(friction=10.0, slide_dx=0.05)]


@pytest.fixture(scope="module")
def batch_run():
    b = BatchSimulation([_scene(d) for d in VARIANTS], device=DEVICE)
    hz = BatchHazard(b)
    b.advance(T, watch=hz.after_step)
    return b, hz.results()


def test_batch_equals_solo_within_round_off(batch_run):
    b, summaries = batch_run
    assert len({b.tiles[k].fluid[1] - b.tiles[k].fluid[0] for k in range(3)}) >= 2  # particle counts differ
    spacing = 0.025
    for k, d in enumerate(VARIANTS):
        sim = Simulation(_scene(d), device=DEVICE)
        hz = HazardMonitor(sim)
        sim.advance(T, watch=hz.after_step)
        assert sim.steps == b.steps and sim.clock.substeps == b.clock.substeps
        dx = np.abs(sim.positions() - b.positions(k))
        # float32 positions at the tile's offset (a few metres) round by an ulp, ~5e-7 m, a step: after 100 steps
        # of a slide entering water the typical particle differs by about that much, the largest by < 1% of the
        # spacing
        ulp = float(np.spacing(np.float32(np.abs(b.positions()).max())))
        assert dx.max() < 0.01 * spacing and np.median(dx) < 4 * ulp
        assert np.abs(sim.block_positions() - b.block_positions(k)).max() < 1e-6
        solo, mine = flat_metrics(hz.result()), flat_metrics(summaries[k])
        assert solo.keys() == mine.keys()
        for key, v in solo.items():
            w = mine[key]
            if key.endswith("_time_s") and not key.endswith("arrival_time_s"):
                continue  # the time of an extreme may jump between near-equal samples
            if v is None or (isinstance(v, float) and math.isnan(v)):
                assert w is None or math.isnan(w), key
            else:
                assert abs(v - w) < 2e-5, (key, v, w)


def test_tiles_never_pair_two_scenarios(batch_run):
    b, _ = batch_run
    assert b.cross_pairs() == 0  # no two particles of different scenarios within 2 H (the largest list radius)
    for t1, t2 in zip(b.tiles[:-1], b.tiles[1:]):
        lo1, hi1, lo2, hi2 = t1.lo + t1.offset, t1.hi + t1.offset, t2.lo + t2.offset, t2.hi + t2.offset
        sep = np.maximum(lo2 - hi1, lo1 - hi2)[:2].max()
        assert sep >= b.gap - 1e-9
    owner = {}
    for k, t in enumerate(b.tiles):
        for i in range(*t.blocks):
            owner[i] = k
    pairs = b.block_solver.contacts(b.block_state)
    assert pairs  # the slides rest on their planes
    for c in pairs:  # the broad phase's candidates (AABBs grown by the margin) never join two scenarios
        i, j = c["blocks"]
        assert owner[i] == owner[j]


def test_template_mismatch_is_a_scene_error():
    a, c = _scene(_variant()), _variant()
    c["fluid"]["eos"]["speed_of_sound_m_s"] = 20.0
    with pytest.raises(SceneError, match="fluid.eos"):
        check_template([a, _scene(c)])


def _configs(tmp_path, variants):
    return [{"id": f"{i:04d}-x", "index": i, "params": {"i": i}, "scene": d, "scene_path": str(SCENE),
             "out_dir": str(tmp_path / f"s{i}"), "device": DEVICE} for i, d in enumerate(variants)]


def test_a_blow_up_fails_its_scenario_alone(tmp_path):
    bad = _variant(duration_s=0.04)
    # straight up at > 5 c0 (c0 = 15 m/s: the guard's runaway speed) from the bottom right of the 2 x 2 tile grid,
    # where no tile lies above: its water reaches no other scenario
    bad["fluid"]["regions"][0]["velocity_m_s"] = [0.0, 80.0]
    variants = [_variant(), bad, _variant(friction=22.0)]
    alone = []

    def solo(c):
        alone.append(c["index"])
        return sweep.run_scenario(c)

    res = batching.run_batch(_configs(tmp_path, variants), solo)
    assert [r["status"] for r in res] == ["ok", "failed", "ok"]
    assert alone == [1] and "m/s" in res[1]["error"]  # its solo run's verdict
    assert res[0]["batch_size"] == res[2]["batch_size"] == 2  # the others again, from the start, without it
    for i in (0, 2):
        saved = json.loads((tmp_path / f"s{i}" / "result.json").read_text())
        assert saved["status"] == "ok" and saved["metrics"] == res[i]["metrics"]
        assert (tmp_path / f"s{i}" / "hazard.json").is_file()


def test_sweep_packs_batches(tmp_path, capsys):
    study = tmp_path / "study.toml"
    study.write_text(f"""
[study]
scene = "{SCENE}"
results = "out"
duration_s = 0.04
device = "{DEVICE}"
[[vary]]
key = "blocks[slide].material.friction_angle_deg"
values = [10.0, 20.0, 25.0]
""")
    st = sweep.load_study(study)
    todo = [sweep.scenario_config(st, sc) for sc in st.scenarios]
    packed = sweep.batch_configs(st, todo, 2)
    assert [len(c.get("batch", [c])) for c in packed] == [2, 1]
    res = sweep.run_study(st, executor="inline", batch=0, plots=False, progress=False)  # auto: all 3 in one
    assert res.failed == 0 and [r["status"] for r in res.rows] == ["ok"] * 3
    for sc in st.scenarios:
        r = sweep.read_result(st, sc)
        assert r["batch_size"] == 3 and r["metrics"]["g0.2.max_crest_m"] is not None
    assert (st.results / "study.csv").is_file()
    from rockwave.app.cli import main

    out = tmp_path / "cli"  # the command line: one array task's scenarios, stepped as one batch
    assert main(["sweep", str(study), "--out", str(out), "--only", "0", "--only", "2", "--batch", "2", "--quiet"]) == 0
    st2 = sweep.load_study(study, out)
    got = {sc.index: sweep.read_result(st2, sc) for sc in st2.scenarios}
    assert got[1] is None and got[0]["batch_size"] == got[2]["batch_size"] == 2
    assert abs(got[0]["metrics"]["slide.runout_m"] - sweep.read_result(st, st.scenarios[0])["metrics"]["slide.runout_m"]) < 1e-6
    assert main(["sweep", str(study), "--slurm", "--batch", "2"]) == 0
    text = (st.results / "sweep.sbatch").read_text()
    assert "--array=0-1" in text and "--only 0 --only 1" in text and "--batch 2" in text


def _slides(**changes) -> list[dict]:
    """slide_2d_tiny variants with the adaptive step (simulation.time_step = 'cfl'): the slide's density and contact
    stiffness set its stable block sub-step (4 sub-steps of the coupling spring's step at 2500 kg/m^3 and 1e6 N/m,
    3 at 2000 kg/m^3 and 3e5 N/m)."""
    out = []
    for rho, kn, depth in ((2000.0, 3e5, 0.2), (2500.0, 1e6, None), (3000.0, 1e6, None)):
        d = _variant(time_step="cfl", depth=depth, **changes)
        del d["simulation"]["dt_s"]
        for b in d["blocks"]:
            if b["name"] == "slide":
                b["density_kg_m3"] = rho
                b["material"]["normal_stiffness_n_m"] = kn
        out.append(d)
    return out


def test_shared_step_batch_keeps_each_limit():
    """The shared step (steps = 'shared'): the batch steps at the smallest limit of its scenarios and sub-steps the
    blocks at the stiffest block's step, so each scenario takes steps and sub-steps no longer than alone; over these
    0.04 s the step is the coupling spring's for all, so the results agree within round-off too."""
    variants = _slides()
    b = BatchSimulation([_scene(d) for d in variants], device=DEVICE, steps="shared")
    hz = BatchHazard(b)
    b.advance(T, watch=hz.after_step)
    summaries = hz.results()
    for k, d in enumerate(variants):
        sim = Simulation(_scene(d), device=DEVICE)
        h = HazardMonitor(sim)
        sim.advance(T, watch=h.after_step)
        assert b.steps >= sim.steps and b.clock.block_dt <= sim.clock.block_dt * (1 + 1e-9)
        assert np.abs(sim.positions() - b.positions(k)).max() < 0.01 * 0.025
        solo, mine = flat_metrics(h.result()), flat_metrics(summaries[k])
        for key, v in solo.items():
            if key.endswith("_time_s") or v is None:
                continue
            assert abs(v - mine[key]) < 2e-5, (key, v, mine[key])


def _jets(T_end: float) -> list[dict]:
    """Dam breaks in box tanks of different widths and columns, the third column thrown at the wall at 3 m/s (its CFL
    step c h / (c0 (1 + 0.6 alpha) + u_max) is shorter: 150 steps against 134 over 0.05 s); a wave gauge and a
    crossing sampled every 5 ms."""
    out = []
    for w, col, h, u in ((0.3, 0.1, 0.15, 0.0), (0.4, 0.12, 0.1, 0.0), (0.25, 0.06, 0.2, 3.0)):
        d = tank_2d(width=w, depth=h, height=0.3, spacing=0.01)
        d["fluid"]["regions"][0].update(box_max_m=[col, h], velocity_m_s=[u, 0.0])
        d["simulation"].update({"duration_s": T_end})
        d["hazard"] = {"sample_interval_s": 0.005, "gauges": [{"name": "g", "position_m": [0.05, 0.0]}],
                       "crossings": [{"name": "c", "position_m": [0.11, 0.0], "normal": [1.0, 0.0]}]}
        out.append(d)
    return out


def _differences(solo: dict, mine: dict) -> dict:
    """|solo - batch| of every number of two flat hazard summaries (inf where one is missing or NaN alone)."""
    out = {}
    assert solo.keys() == mine.keys()
    for key, v in solo.items():
        w = mine[key]
        if v is None or w is None or (isinstance(v, float) and (math.isnan(v) or math.isnan(w))):
            out[key] = 0.0 if (v is None and w is None) or (v is not None and w is not None and math.isnan(v) and math.isnan(w)) else math.inf
        else:
            out[key] = abs(v - w)
    return out


def test_each_scenario_takes_its_own_adaptive_steps():
    """Per-scenario steps (the default): each scenario of a batch takes the step sequence it takes alone (its own
    CFL limit from its own particles, its own landing on the sample times), so its positions agree with its solo
    run's within float32 round-off and every number of its hazard summary, the times of its extremes and its
    arrival time included, within 1e-6 (the levels and volumes differ by an ulp or two of float32; the sample
    times are the same step ends). The shared step (the smallest limit for all) moves the first two by ~1.7e-5 m and
    their gauges by up to 1.7e-5 m: it fails the same checks (asserted below)."""
    T_end = 0.05
    variants = _jets(T_end)
    scenes = lambda: [parse_scene(copy.deepcopy(d)) for d in variants]  # noqa: E731
    solo = []
    for s in scenes():
        sim = Simulation(s, device=DEVICE)
        h = HazardMonitor(sim)
        sim.advance(T_end, watch=h.after_step)
        solo.append((sim, flat_metrics(h.result()), h.result()["samples"]))
    assert len({sim.steps for sim, _, _ in solo}) == 2  # the jet's steps are shorter
    worst = {}
    for mode in ("scenario", "shared"):
        b = BatchSimulation(scenes(), device=DEVICE, steps=mode)
        hz = BatchHazard(b)
        b.advance(T_end, watch=hz.after_step)
        summaries = hz.results()
        assert np.all(b.times == T_end)
        worst[mode] = []
        for k, (sim, metrics, samples) in enumerate(solo):
            dx = np.abs(sim.positions() - b.positions(k)).max()
            dh = max(_differences(metrics, flat_metrics(summaries[k])).values())
            worst[mode].append((dx, dh))
            if mode == "scenario":
                assert b.own.steps[k] == sim.steps and b.own.steps_limited_by[k] == sim.clock.steps_limited_by
                assert summaries[k]["samples"] == samples
                assert dx < 1e-3 * 0.01, (k, dx)
                assert dh < 1e-6, (k, dh)
    assert max(max(dx / 1e-5, dh / 1e-6) for dx, dh in worst["shared"]) > 1.0  # the shared step fails these checks


def test_a_scenario_in_its_own_frame_is_its_solo_run(monkeypatch):
    """The step itself is exact: a scenario placed at its own coordinates (tile offset zero; its batch-mate, with 4
    block sub-steps to its 3, to its right) takes its solo run's steps and sub-steps bit for bit: the same block
    trajectory and the same hazard summary, number for number; its water agrees within an ulp (the union's cell
    grid orders some neighbour sums differently). What a tiled batch adds is only the float32 round-off of the
    translated coordinates (test_each_scenario_takes_its_own_adaptive_steps)."""
    import rockwave.sim.batch as batch_sim

    T_end = 0.06
    variants = _slides(duration_s=T_end)[:2]
    first = BatchSimulation([_scene(d) for d in variants], device=DEVICE)
    lo, hi, gap = first.tiles[0].lo, first.tiles[0].hi, first.gap
    monkeypatch.setattr(batch_sim, "tile_offsets", lambda sizes, g, dim: np.array([[lo[0], lo[1]], [hi[0] + gap, lo[1]]]))
    b = BatchSimulation([_scene(d) for d in variants], device=DEVICE)
    assert np.all(b.tiles[0].offset == 0.0) and list(b.own.substeps) == [3, 4]
    hz = BatchHazard(b)
    b.advance(T_end, watch=hz.after_step)
    sim = Simulation(_scene(variants[0]), device=DEVICE)
    h = HazardMonitor(sim)
    sim.advance(T_end, watch=h.after_step)
    assert sim.clock.substeps == 3 and b.own.steps[0] == sim.steps
    assert np.array_equal(sim.block_positions(), b.block_positions(0))
    assert np.abs(sim.positions() - b.positions(0)).max() < 1e-6
    assert flat_metrics(h.result()) == flat_metrics(hz.results()[0])


def test_dam_breaks_in_tanks_batch_as_alone():
    """Scenarios with their own [tank] (box tanks of different widths: the tank's wall particles are seeded per
    scenario), dam breaks of different columns, a wave gauge whose still level is read at the start (no
    still_level_m) and a crossing: 250 fixed steps, batch against solo within round-off."""
    variants = []
    for w, col, h in ((0.3, 0.1, 0.15), (0.4, 0.12, 0.1)):
        d = tank_2d(width=w, depth=h, height=0.3, spacing=0.01)
        d["fluid"]["regions"][0]["box_max_m"] = [col, h]
        d["simulation"].update({"time_step": "fixed", "dt_s": 2e-4, "duration_s": 0.05})
        d["hazard"] = {"sample_interval_s": 0.005,
                       "gauges": [{"name": "g", "position_m": [0.05, 0.0]}],
                       "crossings": [{"name": "c", "position_m": [0.11, 0.0], "normal": [1.0, 0.0]}]}
        variants.append(d)
    scenes = [parse_scene(copy.deepcopy(d)) for d in variants]
    b = BatchSimulation(scenes, device=DEVICE)
    hz = BatchHazard(b)
    b.advance(0.05, watch=hz.after_step)
    summaries = hz.results()
    for k, d in enumerate(variants):
        sim = Simulation(parse_scene(copy.deepcopy(d)), device=DEVICE)
        h = HazardMonitor(sim)
        sim.advance(0.05, watch=h.after_step)
        ulp = float(np.spacing(np.float32(np.abs(b.positions()).max())))
        dx = np.abs(sim.positions() - b.positions(k))
        assert dx.max() < 0.01 * 0.01 and np.median(dx) < 4 * ulp
        solo, mine = h.result(), summaries[k]
        assert abs(solo["gauges"]["g"]["still_level_m"] - mine["gauges"]["g"]["still_level_m"]) < 1e-6
        assert abs(solo["gauges"]["g"]["deepest_trough_m"] - mine["gauges"]["g"]["deepest_trough_m"]) < 2e-5
        assert solo["gauges"]["g"]["deepest_trough_m"] < -0.005  # the column has fallen at the gauge
        assert mine["crossings"]["c"]["net_volume_m3"] > 1e-4  # water has crossed x = 0.11 m
        assert abs(solo["crossings"]["c"]["net_volume_m3"] - mine["crossings"]["c"]["net_volume_m3"]) < 1e-7


def test_particle_shifting_batches_as_alone(monkeypatch):
    """fluid.fidelity = "delta_plus" (density diffusion and particle shifting) with per-scenario steps: the shift's
    Mach number is each scenario's own (its fastest particle, kernels/sph/shifting.py), and a scenario that does not
    step is not shifted, so each scenario's water agrees with its solo run's within float32 round-off. With the
    batch's fastest particle for all (the jet at 3 m/s beside two still columns) the still ones shift ~3x too far
    and leave that bound (asserted below through the solver's one-Mach path)."""
    import rockwave.sph.fluid as fluid_mod

    T_end = 0.03
    variants = _jets(T_end)
    for d in variants:
        d["fluid"]["fidelity"] = "delta_plus"
    scenes = lambda: [parse_scene(copy.deepcopy(d)) for d in variants]  # noqa: E731
    solo = []
    for s in scenes():
        sim = Simulation(s, device=DEVICE)
        sim.advance(T_end)
        solo.append(sim)

    def worst_dx():
        b = BatchSimulation(scenes(), device=DEVICE)
        b.advance(T_end)
        assert np.all(b.times == T_end)
        for k, sim in enumerate(solo):
            assert b.own.steps[k] == sim.steps
        return [float(np.abs(sim.positions() - b.positions(k)).max()) for k, sim in enumerate(solo)]

    own = worst_dx()
    print("per-scenario Mach: largest |dx| [m]", own)
    assert max(own) < 1e-5, own
    monkeypatch.setattr(fluid_mod.FluidSolver, "shift_by_scenario", lambda self, owner, n: None)
    shared_mach = worst_dx()
    print("the batch's Mach for all: largest |dx| [m]", shared_mach)
    assert max(shared_mach[:2]) > 1e-5, shared_mach
