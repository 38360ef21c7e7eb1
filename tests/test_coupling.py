"""Two-way SPH-DDA coupling (rockwave/coupling/penalty.py): Archimedes in 2D and 3D, a sinking block, a piston
wave maker against linear theory, a wedge sliding into water, no particle inside a block, momentum
accounting, scene rules. CPU, small scenes (Warp's CPU backend runs a kernel on one thread)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import rockwave
from rockwave.coupling.penalty import block_signed_distance
from rockwave.scene.format import SceneError, load_scene, parse_scene

from conftest import DEVICE

SCENES = Path(__file__).resolve().parent.parent / "scenes"


def _sim(name: str) -> rockwave.Simulation:
    return rockwave.Simulation(load_scene(SCENES / name), device=DEVICE)


def _rebuild(sim, blocks=None, coupling=None) -> None:
    """Rebuild sim's block solver and coupling with changed options (before its first step: the
    solvers then hold nothing but buffers); ``blocks`` / ``coupling``: dicts of option fields."""
    from dataclasses import replace

    from rockwave.build.options import block_options, coupling_options
    from rockwave.coupling.penalty import Coupling
    from rockwave.dda.blocks import BlockSolver

    assert sim.steps == 0
    if blocks:
        sim.block_solver = BlockSolver(sim.blocks, options=replace(block_options(sim.scene), **blocks))
    if coupling:
        walls = sim.coupling.walls  # the moving blocks' wall particles belong to the fluid model: kept
        sim.coupling = Coupling(sim.fluid, sim.blocks, sim.scene.dim,
                                options=replace(coupling_options(sim.scene), **coupling))
        sim.coupling.walls = walls


def _min_block_distance(sim) -> float:
    x = sim.state.x.numpy()[: sim.n_fluid]
    return float(block_signed_distance(sim.blocks, sim.block_state, x)[0].min())


def _draft_series(sim, name: str, h: float, t_end: float, t_avg: float) -> float:
    """Time-averaged (gauge level - block bottom) over [t_avg, t_end]."""
    b, up = sim.blocks.names.index(name), sim.scene.dim - 1
    rows = []
    while sim.time < t_end - 1e-9:
        sim.advance(0.02)
        if sim.time >= t_avg:
            level = np.nanmean(list(sim.gauges().values()))
            rows.append(level - (sim.block_positions()[b][up] - 0.5 * h))
    return float(np.mean(rows))


def test_floating_box_2d_archimedes():
    """A 0.4 x 0.2 m box of density 500 released 0.01 m too high settles at draft h rho_s/rho_w = 0.1 m."""
    sim = _sim("floating_box_2d.toml")
    assert sim.removed_inside_blocks == 9 * 40  # rows y = 0.265 .. 0.345 under x = 0.3 .. 0.7
    draft = _draft_series(sim, "box", 0.2, 1.0, 0.3)
    assert abs(draft / 0.1 - 1.0) < 0.05, draft
    assert _min_block_distance(sim) > 0.0


def test_floating_box_3d_archimedes():
    """3D box (density 800, h = 0.25 m) in a tank made of fixed blocks: draft 0.2 m within 5%."""
    sim = _sim("floating_box_small.toml")
    assert sim.scene.tank is None and sim.fluid.n_moving_walls > 0  # the tank is blocks only; the box an Adami wall
    draft = _draft_series(sim, "box", 0.25, 0.8, 0.3)
    assert abs(draft / 0.2 - 1.0) < 0.05, draft
    assert _min_block_distance(sim) > 0.0


def test_sinking_block_reaches_floor_and_water_returns_to_hydrostatic():
    """A 0.1 m block of density 2000 sinks through 0.3 m of water and lands on the floor block: the
    water film under it is squeezed out (rockwave/coupling/penalty.py, squeeze-out), so the block's bottom
    touches the floor (DDA contact, the floor carries the block) with no particle left under or
    inside it, and the water returns to hydrostatic pressure."""
    sim = _sim("sinking_block_small.toml")
    b, floor = sim.blocks.names.index("block"), sim.blocks.names.index("floor")
    s = sim.fluid.spacing
    y0 = sim.block_positions()[b][1]
    sim.advance(0.6)
    ratios = []
    # the still-water level from the water's area (0.6 m wide tank, the 0.1 m block submerged on the floor): the
    # level gauge reads the continuous column at its own line, while the sloshing left by the impact runs up the
    # walls where the pressure probes are
    level = (sim.n_fluid * s * s + 0.1 * 0.1) / 0.6
    for _ in range(12):  # 0.65 .. 1.2 s: averages over the sloshing left by the impact
        sim.advance(0.05)
        g = sim.gauges()
        for k, y in (("p_left_low", 0.05), ("p_left_mid", 0.15), ("p_right_low", 0.05)):
            ratios.append(g[k] / (1000.0 * 9.81 * (level - y)))
    xb = sim.block_positions()[b]
    bottom = xb[1] - 0.05  # the floor's top face is y = 0
    assert y0 - 0.05 > 0.1  # it started 10 spacings above the floor
    # on the floor: only the DDA contact overlap (k_n = 5e5 N/m: ~2e-5 m = 0.002 s measured), no water film
    assert abs(bottom) < 0.05 * s, bottom / s
    assert abs(sim.block_velocities()[b][1]) < 0.02
    contact = [c for c in sim.block_solver.contacts(sim.block_state) if set(c["blocks"]) == {b, floor}]
    assert contact and contact[0]["gap"] <= 0.0 and len(contact[0]["normal_forces"]) >= 2
    # the floor carries at least the submerged weight (m - rho_w V) g = 9.81 N (measured 37.6 N: with
    # no water under the block the water above presses it down as well)
    submerged = (sim.blocks.np["mass"][b] - 1000.0 * 0.1 ** 3) * 9.81
    assert contact[0]["normal_forces"].sum() > submerged, contact[0]["normal_forces"]
    x = sim.positions()
    under = (np.abs(x[:, 0] - xb[0]) < 0.05) & (x[:, 1] < xb[1])
    assert not under.any(), x[under]
    assert _min_block_distance(sim) > 0.0  # no particle inside any block
    # WCSPH pressure noise and sloshing: +-40% per sample; the mean of 36 samples within 20% of rho g d from the
    # mean level: measured +14.8%. The walls here are fixed blocks, which push the water by the penalty coupling,
    # not with the fluid's pressure (Adami walls are boundary particles only): the probes next to them read high.
    # (Against the old height gauge, which counted the sheet running up the wall, the same run read -0.6%.)
    assert abs(np.mean(ratios) - 1.0) < 0.2, ratios


def _first_harmonic_height(t, y, omega: float) -> float:
    """Wave height 2 sqrt(b^2 + c^2) of the least-squares fit y = a + b cos(omega t) + c sin(omega t)
    (a window of whole periods). Unlike max - min it is not decided by one splash particle or by the
    second harmonic of a steep wave."""
    t = np.asarray(t)
    A = np.c_[np.ones_like(t), np.cos(omega * t), np.sin(omega * t)]
    a, b, c = np.linalg.lstsq(A, np.asarray(y), rcond=None)[0]
    return 2.0 * math.hypot(b, c)


def test_piston_wave_maker_linear_theory():
    """Piston wave maker (kh = 1.5, S = 0.03 m, h = 0.2 m = 16 spacings) against linear theory.

    Coupling: the water at the piston face moves with the full stroke (first harmonic of the mean
    x of the particles next to the face: 0.0299-0.0300 m measured for S = 0.03 m).
    Wave: first-harmonic height (see _first_harmonic_height) of gauge_1 (0.35 m from the piston) over the two
    periods ending at 2.6 s, against the linear solution of the same flume, start and window
    (benchmarks/wave_maker.py flume_linear_eta: 1.0107 x the steady formula H/S = 2 (cosh 2kh - 1)/(sinh 2kh +
    2kh) = 1.39 there). Measured on this CPU with the scene's formulation (the standard level, penalty piston):
    -10% (docs/notes.md 'Piston wave maker'; realisations spread about +-3%; with fluid.fidelity = 'draft' -29%).
    Asserted: within 16% (the measured -10% plus twice the spread)."""
    sim = _sim("wave_maker_small.toml")
    h, S, f = 0.2, 0.03, 1.2970
    om = 2 * math.pi * f
    k = om * om / 9.81
    for _ in range(50):  # dispersion om^2 = g k tanh(kh)
        k = om * om / (9.81 * math.tanh(k * h))
    ratio = 2 * (math.cosh(2 * k * h) - 1) / (math.sinh(2 * k * h) + 2 * k * h)
    s = sim.fluid.spacing
    b = sim.blocks.names.index("piston")
    t_end = 2.6
    t_start = t_end - 2.0 / f  # two whole periods: 1.06 .. 2.6 s
    ts, eta, face, water = [], [], [], []
    while sim.time < t_end - 1e-9:
        sim.advance(0.02)
        x = sim.positions()
        layers = [x[np.abs(x[:, 1] - y) < 0.5 * s, 0].min() for y in np.arange(0.5 * s, 0.75 * h, s)]
        ts.append(sim.time)
        face.append(sim.block_positions()[b][0] + 0.05)
        water.append(np.mean(layers))  # the water's edge at the piston, mean over depth
        eta.append(sim.gauges()["gauge_1"])
    ts, eta = np.asarray(ts), np.asarray(eta)
    assert abs(_first_harmonic_height(ts, face, om) / S - 1.0) < 1e-3
    assert abs(_first_harmonic_height(ts, water, om) / S - 1.0) < 0.03
    w = ts > t_start - 1e-6
    H = _first_harmonic_height(ts[w], eta[w], om)
    from benchmarks.wave_maker import flume_reference

    H_lin = flume_reference(t_end=t_end, x_gauges=(0.35,))[0.35]
    assert abs(H_lin / (ratio * S) - 1.0 - 0.0107) < 0.002  # the flume's solution against the steady formula
    print(f"gauge_1: H = {H:.5f} m, flume's linear solution {H_lin:.5f} m ({H / H_lin - 1:+.1%})")
    assert abs(H / H_lin - 1.0) < 0.16, (H, H_lin)
    assert _min_block_distance(sim) > 0.0


def test_sliding_wedge_enters_decelerates_and_pushes_a_crest():
    sim = _sim("sliding_wedge_small.toml")
    b = sim.blocks.names.index("wedge")
    level = 0.25
    speeds, xs = [], []
    crest = 0.0
    while sim.time < 1.0 - 1e-9:
        sim.advance(0.05)
        v = sim.block_velocities()[b]
        speeds.append(float(np.hypot(v[0], v[1])))
        xs.append(sim.block_positions()[b].copy())
        x = sim.positions()
        front = xs[-1][0] + 0.1
        ahead = (x[:, 0] > front) & (x[:, 0] < front + 0.4)
        if ahead.any() and sim.time > 0.45:  # after the wedge reaches the water (0.43 s dry sliding)
            crest = max(crest, float(x[ahead, 1].max() + 0.5 * sim.fluid.spacing - level))
    speeds = np.asarray(speeds)
    i_max = int(np.argmax(speeds))
    assert xs[-1][1] < level - 0.05  # entered the water
    assert speeds[-1] < 0.6 * speeds[i_max] and i_max < len(speeds) - 3  # slowed down after entry
    assert crest > 0.04  # a leading crest ahead of the wedge (measured 0.10 m; 0.02 m at rest near the shore)
    assert _min_block_distance(sim) > 0.0


def test_momentum_accounting_water_and_blocks():
    """Water + a free block in a tank of fixed blocks: the change of total momentum equals the
    impulse of gravity and of the fixed walls (tracked coupling forces) up to float32 round-off. The draft
    formulation: track_walls sums the penalty forces, and on the standard level the fixed blocks are Adami walls
    (boundary particles, not tracked; the block walls' exchange is test_block_walls.py's)."""
    import tomllib

    data = tomllib.loads((SCENES / "sinking_block_small.toml").read_text())
    data["fluid"]["fidelity"] = "draft"
    data["coupling"].pop("block_walls")
    sim = rockwave.Simulation(parse_scene(data, SCENES / "sinking_block_small.toml"), device=DEVICE)
    _rebuild(sim, coupling=dict(track_walls=True))
    assert sim.coupling.track_walls
    b = sim.blocks.names.index("block")
    depth = sim.coupling.depth[b]  # 2D: water momentum per metre of depth, the block's over its depth

    def momentum():
        return depth * sim.fluid.fluid_mass * sim.velocities().sum(axis=0) + sim.blocks.np["mass"][b] * sim.block_velocities()[b][:2]

    p0, t0 = momentum(), sim.time
    sim.advance(0.25)  # the block sinks freely; it has not reached the floor yet
    assert sim.block_positions()[b][1] - 0.05 > 0.05
    m_tot = depth * sim.fluid.fluid_mass * sim.n_fluid + sim.blocks.np["mass"][b]
    gravity = m_tot * np.array([0.0, -9.81]) * (sim.time - t0)
    walls = depth * sim.coupling.wall_impulse[:2]
    resid = momentum() - p0 - gravity - walls
    scale = np.linalg.norm(gravity)
    # float32 state: each step adds ~1e-7 relative round-off in ~1700 particle velocities;
    # 1e-3 of the gravity impulse is ~50x the accumulated round-off measured here (a coupling force
    # applied to one side only would miss by the block's buoyancy, ~40% of it)
    assert np.linalg.norm(resid) < 1e-3 * scale, (resid, scale)
    assert abs(walls[1]) > 0.5 * scale  # the floor carried the water: the check is not vacuous


def test_scene_rules_and_broad_phase():
    base = {"simulation": {"dimension": 2, "duration_s": 0.1}, "fluid": {"spacing_m": 0.01, "eos": {"speed_of_sound_m_s": 10.0},
                                                                         "regions": [{"box_min_m": [0, 0], "box_max_m": [0.1, 0.1]}]}}
    with pytest.raises(SceneError, match="no walls"):
        parse_scene(base)
    walls = dict(base, blocks=[{"shape": "box", "size_m": [1, 0.1, 0.1], "position_m": [0, -0.05, 0], "kind": "fixed"}])
    parse_scene(walls)  # fixed blocks bound the water: no [tank] needed
    bad = dict(walls, blocks=walls["blocks"] + [{"shape": "box", "size_m": [0.1, 0.1, 0.1], "position_m": [0, 1, 0], "orientation_deg": [10, 0, 0]}])
    with pytest.raises(SceneError, match="turns about z only"):
        parse_scene(bad)
    # a block far above the water costs no coupling work: it never becomes a candidate, whether the
    # particles test the few blocks' grown boxes directly or look them up in the (block, cell) hash
    from rockwave.coupling.penalty import CouplingOptions

    far = dict(walls, blocks=walls["blocks"] + [{"shape": "box", "size_m": [0.1, 0.1, 0.1], "position_m": [0.05, 2.0, 0],
                                                 "material": {"normal_stiffness_n_m": 1e5}}])
    for direct_max in (CouplingOptions().direct_max_blocks, 0):
        sim = _sim("sinking_block_small.toml")
        _rebuild(sim, coupling=dict(direct_max_blocks=direct_max))
        sim.step()
        assert sim.coupling.direct == (direct_max > 0)
        assert sim.blocks.names.index("block") in sim.coupling.candidate_blocks()
        sim2 = rockwave.Simulation(parse_scene(far), device=DEVICE)
        _rebuild(sim2, coupling=dict(direct_max_blocks=direct_max))
        sim2.step()
        assert sim2.coupling.candidate_blocks() == {0}  # the floor only
        if direct_max == 0:
            assert sim2.coupling.ncell.numpy()[1] == 0 and sim2.coupling.n_large == 0


def test_sync_free_step_matches_the_counter_read_path():
    """With few blocks the coupling and DDA broad phases run at fixed capacities and read nothing back
    per step (launch dims at capacity, kernels stop at the device counts); the motion is the same as
    with the per-step counter reads and grown capacities."""

    def run(sync_free: bool):
        sim = _sim("sliding_wedge_small.toml")
        if not sync_free:
            _rebuild(sim, blocks=dict(sync_free_max_blocks=0),
                     coupling=dict(sync_free_max_entries=0, direct_max_blocks=0))
        assert sim.block_solver.sync_free == sync_free and sim.coupling.sync_free == sync_free
        for _ in range(150):
            sim.step()
        return sim

    a = run(True)
    b = run(False)
    assert a.block_solver.pair_count == b.block_solver.pair_count > 0
    assert a.coupling.direct and not b.coupling.direct  # boxes tested directly vs the (block, cell) hash
    assert a.coupling.candidate_blocks() == b.coupling.candidate_blocks()
    assert np.allclose(a.block_positions(), b.block_positions(), atol=1e-6)
    assert np.allclose(a.positions(), b.positions(), atol=1e-6)


def test_options_from_scene():
    """BlockOptions / CouplingOptions of a scene (rockwave/build/options.py block_options, coupling_options) read
    simulation.block_dt_safety and the [coupling] section; the solvers use them (d0, K_s, K_d, squeeze gap, both step
    limits); no section: the defaults."""
    import tomllib

    from rockwave.build.options import block_options, coupling_options
    from rockwave.coupling.penalty import CouplingOptions, default_penalty
    from rockwave.dda.blocks import BlockOptions

    data = tomllib.loads((SCENES / "sinking_block_small.toml").read_text())
    data.pop("coupling", None)
    scene = parse_scene(data, SCENES / "sinking_block_small.toml")
    assert coupling_options(scene) == CouplingOptions() and block_options(scene) == BlockOptions()
    data["simulation"]["block_dt_safety"] = 0.3
    data["coupling"] = {"contact_distance_ratio": 0.4, "stiffness_factor": 2.0, "damping_ratio": 0.25,
                        "damping_n_s_m": 3.0, "squeeze_out": False}
    scene = parse_scene(data, SCENES / "sinking_block_small.toml")
    co = coupling_options(scene)
    assert (co.contact_distance_ratio, co.stiffness_factor, co.damping_ratio, co.stiffness_n_m, co.damping_n_s_m,
            co.squeeze_out) == (0.4, 2.0, 0.25, None, 3.0, False)
    assert block_options(scene).dt_safety == 0.3
    sim = rockwave.Simulation(scene, device=DEVICE)
    c, s = sim.coupling, sim.fluid.spacing
    assert c.options == co and c.d0 == pytest.approx(0.4 * s) and c.squeeze_gap == 0.0
    assert c.k_s == pytest.approx(default_penalty(sim.fluid.fluid_mass, sim.fluid.sound_speed, s, 2.0, 0.25)[0])
    assert c.k_d == 3.0
    assert c.stable_dt() == pytest.approx(0.5 * c.critical_dt())
    assert sim.block_solver.stable_dt(sim.block_state) == pytest.approx(0.3 * sim.block_solver.critical_dt())
    assert sim.dt <= c.stable_dt() and sim.clock.block_dt <= sim.block_solver.stable_dt(sim.block_state)  # multi-rate
