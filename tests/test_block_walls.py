"""Adami wall particles on moving blocks (coupling.block_walls; rockwave/coupling/walls.py BlockWalls): the water
pushes a block with its extrapolated wall pressure (Adami, Hu & Adams 2012, eq. 27 with the wall's
acceleration), the reaction goes onto the block equal and opposite, and a floating box takes Archimedes' draft
with the standard formulation (with the penalty alone it floats 9% high in 2D)."""

import numpy as np
import pytest

import rockwave
from rockwave.coupling.penalty import CouplingOptions
from rockwave.scene.format import SceneError
from rockwave.sim.simulation import SimulationOptions

DEVICE = "cpu"
G = 9.81
S = 0.02  # spacing [m]
W, D = 0.8, 0.3  # tank width, water depth [m]
BW, BH, DEPTH = 0.24, 0.16, 0.1  # box width, height, z-extent [m]


def _scene(kind="rigid", rho_b=500.0, lift=0.0, walls=True, gravity=None, velocity=None):
    """A 2D tank of still water (standard formulation) with a box of density rho_b placed at Archimedes' draft
    (raised by ``lift``)."""
    draft = rho_b / 1000.0 * BH
    box = {"name": "box", "shape": "box", "size_m": [BW, BH, DEPTH], "position_m": [W / 2, D - draft + BH / 2 + lift, 0.0],
           "density_kg_m3": rho_b, "kind": kind, "material": {"normal_stiffness_n_m": 1e5}}
    if kind == "kinematic":
        box["motion"] = {"type": "sine", "amplitude_m": [0.0, 0.0, 0.0], "frequency_hz": 1.0}
    if velocity is not None:
        box["velocity_m_s"] = velocity
    d = {"simulation": {"dimension": 2, "duration_s": 1.0},
         "fluid": {"spacing_m": S, "eos": {"speed_of_sound_m_s": 15.0}, "viscosity": {"artificial_alpha": 0.05},
                   "regions": [{"box_min_m": [0.0, 0.0], "box_max_m": [W, D]}]},
         "tank": {"box_min_m": [0.0, 0.0], "box_max_m": [W, D + 0.2]},
         "blocks": [box], "coupling": {"block_walls": walls}}
    if gravity is not None:
        d["gravity"] = {"acceleration_m_s2": gravity}
    return d


def test_wall_particles_follow_the_block():
    """The wall particles are a shell inside the box's faces, layers * step deep, half a step in from each face
    (so the wall pressure acts on the block's own faces), and are placed each step from the block's pose."""
    sim = rockwave.Simulation(rockwave.parse_scene(_scene(lift=0.01)), device=DEVICE)
    f = sim.fluid
    nw = f.n_moving_walls
    assert nw > 0 and sim.coupling.walls.n == nw
    x0 = sim.block_positions()[0]
    xw = f.initial_positions[f.n_fluid + f.n_static_boundary:][:, :2] - x0[:2]
    H = f.support_radius
    assert np.all(np.abs(xw[:, 0]) < BW / 2) and np.all(np.abs(xw[:, 1]) < BH / 2)
    inset = np.minimum(BW / 2 - np.abs(xw[:, 0]), BH / 2 - np.abs(xw[:, 1]))  # depth under the surface
    assert abs(inset.min() - 0.5 * S) < 1e-6 and inset.max() < H
    sim.advance(0.05)
    xb, q = sim.block_positions()[0], sim.block_state.orientations_numpy()[0]
    assert np.linalg.norm(xb - x0) > 5e-4  # it fell (0.67 mm; 1.65 mm before the walls' pressure work was paired)
    from rockwave.base.maths import quat_to_matrix

    body = sim.coupling.walls.body_r.numpy().astype(float)
    want = body @ quat_to_matrix(q).T + xb
    now = sim.state.x.numpy()[f.n_fluid + f.n_static_boundary:].astype(float)
    assert np.allclose(now[:, :2], want[:, :2], atol=1e-5) and np.all(now[:, 2] == 0.0)


def test_kinematic_box_feels_the_buoyancy():
    """A box held at rest (kinematic) at draft d in still water: the water's net vertical force on it (wall
    particles + penalty) is the buoyancy rho g B d times its z-extent, within 3%: the water's free surface and
    so d are uncertain by a few per cent of a spacing once the water has settled around the box (measured:
    +0.5%, 99.9% of it carried by the wall particles; with the penalty alone -6.2%). The wall particles of the
    row under the bottom face (away from the corners) carry the hydrostatic pressure of their depth, rho g
    (level - y), within 4% on average over the window (measured +1.1%; single samples swing +-5% with the water
    column's acoustic oscillation, period ~4 D / c0 = 0.08 s)."""
    opts = SimulationOptions(coupling=CouplingOptions(block_walls=True, track_walls=True))
    sim = rockwave.Simulation(rockwave.parse_scene(_scene(kind="kinematic")), device=DEVICE, options=opts)
    walls, f = sim.coupling.walls, sim.fluid
    ns = f.n_static_boundary
    xw = sim.state.x.numpy()[f.n_fluid + ns:]
    xb = sim.block_positions()[0]
    row = (xw[:, 1] < xb[1] - BH / 2 + 0.6 * S) & (np.abs(xw[:, 0] - xb[0]) < BW / 2 - 1.5 * S)  # under the bottom
    assert row.sum() == round(BW / S) - 4
    sim.advance(0.15)  # the water settles around the box
    t0, imp0 = sim.time, sim.coupling.wall_impulse.copy()
    wall_imp = np.zeros(3)
    ratios = []
    while sim.time < 0.45 - 1e-9:
        sim.step()
        wall_imp += sim.dt * walls.water_force.numpy()[0]
        if sim.steps % 5 == 0:  # (the box is at rest: its wall particles stay where they are)
            ratios.append(sim.state.wall_pressure.numpy()[ns:][row] / (1000.0 * G * (D - xw[row, 1])))
    span = sim.time - t0
    penalty = -DEPTH * (sim.coupling.wall_impulse - imp0)[1] / span  # the penalty's on the box (wall_impulse: per m)
    total = wall_imp[1] / span + penalty
    buoyancy = 1000.0 * G * BW * (500.0 / 1000.0 * BH) * DEPTH
    assert abs(total / buoyancy - 1.0) < 0.03, (total, buoyancy, penalty)
    assert wall_imp[1] / span > 0.9 * buoyancy  # the wall pressure, not the penalty, carries it
    assert abs(np.mean(ratios) - 1.0) < 0.04, np.mean(ratios)


def test_floating_box_settles_to_archimedes_draft():
    """A free box of half the water's density released one spacing above Archimedes' draft (0.08 m, 4 spacings)
    falls and heaves about it: the mean of (water level at the tank's ends - box bottom) over 0.3-1.05 s (one
    heave period, 0.75 s) is the draft within 3% (measured -0.9%; the box and the water start on the water's
    lattice, whose rows end half a spacing from the box's faces as the wall particles' begin half a spacing in).
    With the penalty alone (coupling.block_walls = false) this box sinks to a draft 9% deep (docs/notes.md)."""
    d = _scene(lift=S)
    d["output"] = {"gauges": [{"name": "left", "kind": "height", "position_m": [0.06, 0.0]},
                              {"name": "right", "kind": "height", "position_m": [W - 0.06, 0.0]}]}
    sim = rockwave.Simulation(rockwave.parse_scene(d), device=DEVICE)
    drafts, lowest = [], np.inf
    while sim.time < 1.05 - 1e-9:
        sim.advance(0.02)
        bottom = sim.block_positions()[0, 1] - BH / 2
        lowest = min(lowest, bottom)
        if sim.time > 0.3 - 1e-9:
            g = sim.gauges()
            drafts.append(0.5 * (g["left"] + g["right"]) - bottom)
    draft = float(np.mean(drafts))
    assert lowest < D - 0.5 * BH  # released a spacing above, it fell past Archimedes' position
    assert abs(draft / (0.5 * BH) - 1.0) < 0.03, draft


def test_water_and_block_exchange_equal_and_opposite_forces():
    """No gravity, a free box moving at 0.5 m/s into a patch of water well inside the tank: the total momentum
    (water per metre times the box's z-extent, plus the box) stays what it was to float32 round-off while the
    box gives a large part of its momentum to the water, most of it through its wall particles (measured: the box
    slows to 0.29 m/s in 0.2 s, 86% of its momentum change through the wall particles, the total momentum
    kept to 6e-7)."""
    d = _scene(rho_b=1000.0, gravity=[0.0, 0.0], velocity=[0.5, 0.0, 0.0])
    d["fluid"]["regions"] = [{"box_min_m": [0.4, 0.1], "box_max_m": [0.62, 0.34]}]
    d["tank"] = {"box_min_m": [-0.2, -0.2], "box_max_m": [1.2, 0.7]}
    d["blocks"][0]["position_m"] = [0.25, 0.22, 0.0]
    d["blocks"][0]["size_m"] = [0.12, 0.12, DEPTH]
    sim = rockwave.Simulation(rockwave.parse_scene(d), device=DEVICE)
    mb = float(sim.blocks.np["mass"][0])
    m = sim.fluid.fluid_mass

    def momentum():
        return m * DEPTH * sim.velocities().astype(np.float64).sum(axis=0)[:2] + mb * sim.block_velocities()[0, :2]

    p0 = momentum()
    walls = sim.coupling.walls
    wall_imp = 0.0
    while sim.time < 0.2 - 1e-9:
        sim.step()
        wall_imp += sim.dt * walls.water_force.numpy()[0, 0]
    p1 = momentum()
    vb = sim.block_velocities()[0, 0]
    assert vb < 0.4, vb  # the water took a large part of the box's momentum
    assert wall_imp < 0.5 * mb * (vb - 0.5)  # most of it through the wall particles
    assert np.linalg.norm(p1 - p0) < 2e-5 * np.linalg.norm(p0), (p0, p1)


def test_block_walls_need_adami_walls_and_the_basic_method():
    d = _scene()
    d["fluid"]["boundary"] = "akinci"
    with pytest.raises(SceneError, match="coupling.block_walls"):
        rockwave.parse_scene(d)
    d = _scene()
    d["fluid"]["method"] = "ghost"
    with pytest.raises(SceneError, match="coupling.block_walls"):
        rockwave.parse_scene(d)
    sim = rockwave.Simulation(rockwave.parse_scene(_scene(walls=False)), device=DEVICE)
    assert sim.fluid.n_moving_walls == 0 and sim.coupling.walls is None


def test_resume_from_a_checkpoint_is_bit_identical():
    """The walls' state travels in checkpoints (their positions in the fluid state, their list-build positions
    with the fluid solver's, the blocks' last velocities for the acceleration term): a run resumed from a
    checkpoint continues bit for bit (CPU)."""
    from rockwave.sim import checkpoint
    scene = rockwave.parse_scene(_scene(lift=S))
    a = rockwave.Simulation(scene, device=DEVICE)
    a.advance(0.06)
    arrays, metas = checkpoint.pack(a, checkpoint.capture(a))
    assert "block_walls" in metas and "fluid/solver/wall_build" in arrays
    meta = {"scene": checkpoint.scene_identity(a), "groups": metas}
    a.advance(0.06)
    b = rockwave.Simulation(scene, device=DEVICE)
    checkpoint.restore(b, arrays, meta)
    b.advance(0.06)
    assert a.steps == b.steps
    assert np.array_equal(a.positions(), b.positions()) and np.array_equal(a.block_positions(), b.block_positions())
    assert np.array_equal(a.state.x.numpy(), b.state.x.numpy())  # the wall particles too


def test_wall_acceleration_of_a_moving_piston():
    """The wall acceleration term of Adami's eq. 27 gets the block's acceleration: a kinematic box moving as
    x = A sin(w t) in the water gives its wall particles a = -A w^2 sin(w t) (the velocity difference over the
    last step, evaluated half a step back: within 1e-3 of A w^2, measured 2.5e-5: float32 velocities differenced
    over one step)."""
    A, f = 0.01, 2.0
    d = _scene(kind="kinematic")
    d["blocks"][0]["motion"] = {"type": "sine", "amplitude_m": [A, 0.0, 0.0], "frequency_hz": f}
    sim = rockwave.Simulation(rockwave.parse_scene(d), device=DEVICE)
    fl, om = sim.fluid, 2.0 * np.pi * f
    worst = 0.0
    for _ in range(40):
        t, dt_prev = sim.time, sim.dt
        sim.step()
        if sim.steps < 3:
            continue
        a = sim.fluid_solver.wall_accel.numpy()[fl.n_static_boundary:]  # set at the start of the step just taken
        want = -A * om * om * np.sin(om * (t - 0.5 * dt_prev))
        assert np.allclose(a[:, 1:], 0.0, atol=1e-6)  # rigid translation: every particle the same, along x
        worst = max(worst, float(np.abs(a[:, 0] - want).max()))
    assert worst < 1e-3 * A * om * om, worst
