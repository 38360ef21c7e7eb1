"""The block-contact pipeline at scale (issues 20 and 21): the cooperative narrow phase of big blocks
(kernels/dda/blocks_coop.py narrow_phase_coop, one thread block per pair) gives the serial narrow phase's
contacts bit for bit, and the block solver's device memory stays within 4 KB per block because the
contact history is sized from the live pairs and contact points."""

import math

import numpy as np
import pytest
import warp as wp

from rockwave.base.solver import TimeStep
from rockwave.dda import geometry as G
from rockwave.dda.blocks import BlockModel, BlockOptions, BlockSolver, BlockSpec, ContactMaterial

DEVICE = "cpu"
SERIAL = BlockOptions(coop_min_vertices=10**9)  # every pair on the one-thread narrow phase
COOP = BlockOptions(coop_min_vertices=32)  # pairs of > 32 vertices cooperative (the GPU default; off on the CPU)


def _step(solver, state, dt):
    solver.step(state, TimeStep(dt, state.time, None))


def _prism_on_slope(alpha_deg=5.0, phi_deg=30.0, sides=25, r=0.5, length=1.0, lift=0.0):
    """A 50-vertex prism (a regular 25-gon extruded along y) on a side face, just above a fixed slope
    dipping alpha along x (below its 7.2 degree tipping angle), axis along the strike."""
    th = -0.5 * math.pi + math.pi / sides + 2 * math.pi * np.arange(sides) / sides
    ring = np.stack([r * np.cos(th), np.zeros(sides), r * np.sin(th)], axis=1)
    pts = np.concatenate([ring + [0, -length / 2, 0], ring + [0, length / 2, 0]])
    prism = G.prism(pts, name="prism")
    a = math.radians(alpha_deg)
    q = (0.0, math.sin(a / 2), 0.0, math.cos(a / 2))  # rotation about y
    n = np.array([math.sin(a), 0.0, math.cos(a)])
    t = 0.5
    mat = ContactMaterial(friction_angle_deg=phi_deg)
    centre_to_face = -prism.vertices[:, 2].min()  # centroid to the bottom side face
    specs = [BlockSpec(G.box((6.0, 3.0, 2 * t)), kind="fixed", orientation=q, name="slope", material=mat),
             BlockSpec(prism, position=tuple((t + centre_to_face + lift) * n), orientation=q, density=2600.0,
                       material=mat, name="prism")]
    return specs


def _run(specs, options, steps, every=None):
    model = BlockModel(specs, device=DEVICE)
    state = model.state()
    solver = BlockSolver(model, options=options)
    dt = solver.stable_dt(state)
    seen = []
    for k in range(steps):
        _step(solver, state, dt)
        if every and (k + 1) % every == 0:
            seen.append(solver.contacts(state))
    return model, state, solver, seen


def _same_contacts(ca, cb):
    assert len(ca) == len(cb)
    for a, b in zip(ca, cb):
        assert a["blocks"] == b["blocks"]
        for key in ("normal", "gap", "points", "depths", "normal_forces"):
            assert np.array_equal(np.asarray(a[key]), np.asarray(b[key])), key


def test_prism_contact_equals_the_serial_narrow_phase_and_runs_cooperatively():
    # issue 20: a 50-vertex prism against a fixed slope. Its pairs go to narrow_phase_coop (one thread
    # block per pair: the FCP extents and candidate gaps, the SAT fallback over faces and half-edge
    # pairs and the contact points spread over the lanes); the result is the serial one bit for bit:
    # the same contact points, depths and normal forces, the same trajectory
    specs = _prism_on_slope()
    m1, s1, sol1, c1 = _run(specs, COOP, 200, every=50)
    assert sol1.has_big_pairs
    assert int(sol1.counters.numpy()[4]) == 1  # the last narrow phase gave the pair to narrow_phase_coop
    m0, s0, sol0, c0 = _run(specs, SERIAL, 200, every=50)
    assert not sol0.has_big_pairs
    for a, b in zip(c1, c0):
        _same_contacts(a, b)
    assert np.array_equal(s1.positions_numpy(), s0.positions_numpy())
    assert np.array_equal(s1.orientations_numpy(), s0.orientations_numpy())
    # the physics it compares is not vacuous: the prism rests on its side face (friction 30 deg on a
    # 5 deg slope, below its 7.2 deg tipping angle: it neither slides nor rolls), whose points carry its
    # weight's normal component m g cos(alpha) (the penalty springs still ring about it by a few %)
    last = c0[-1][0]
    assert last["gap"] < 0 and len(last["points"]) >= 2
    fn = float(np.sum(last["normal_forces"]))
    assert fn == pytest.approx(9.81 * m0.np["mass"][1] * math.cos(math.radians(5.0)), rel=0.05)
    assert np.linalg.norm(s0.positions_numpy()[1] - m0.base_position[1]) < 1e-3


def test_cooperative_lanes_give_the_same_contacts():
    # with several lanes per pair (Warp's CPU block emulation), every chunk of vertices / half-edge
    # pairs is shared out; ties, chunk order and the reductions must still give the serial result
    specs = _prism_on_slope()
    _, s0, _, c0 = _run(specs, SERIAL, 40, every=20)
    old = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        _, s1, sol1, c1 = _run(specs, BlockOptions(narrow_block_dim=8, coop_min_vertices=8), 40, every=20)
    finally:
        wp.config.enable_cpu_blocks = old
    assert int(sol1.counters.numpy()[4]) == 1
    for a, b in zip(c1, c0):
        _same_contacts(a, b)
    assert np.array_equal(s1.positions_numpy(), s0.positions_numpy())


def _grid(n, steps, layers=4, shrink_pool=False):
    from benchmarks.block_contacts import grid_specs

    model = BlockModel(grid_specs(n, layers), device=DEVICE, check_overlap=False)
    state = model.state()
    solver = BlockSolver(model)
    if shrink_pool:  # a pool far below the live contact points: the first narrow phase must grow it
        state.alloc_tables(state.table_cap, 8)
    dt = solver.stable_dt(state)
    for _ in range(steps):
        _step(solver, state, dt)
    return model, state, solver


def test_block_solver_memory_per_block_within_4_kb():
    # issue 21: 1,000 cubes in columns of 4 on a floor, 5 cm apart (10 candidate pairs per block: the
    # AABB margin reaches the side neighbours), resting from t = 0. Every device array of the block
    # solver (model, state, both history tables, broad phase) counted: <= 4 KB per block (before:
    # ~54 KB, the history tables a capacity per block), so 1 M blocks take < 4 GB
    n = 1000
    model, state, solver = _grid(n, 20)
    mem = solver.device_bytes(state)
    assert mem["per_block"] <= 4096, mem
    assert mem["total"] == mem["model"] + mem["state"] + mem["history"] + mem["solver"]
    # the history is sized from the live pairs and points, not from a capacity per block
    live_points = int(state.tables[0]["pcount"].numpy()[0])
    assert state.table_cap <= 3 * solver.pair_count // 2 + 64 + n // 10
    assert state.point_cap <= max(4 * n + 64, 3 * live_points // 2 + 64)
    # the physics the pool holds: every face-to-face contact found with its 4 corners (columns of 4:
    # 8 points on each of the lower 3 blocks, 4 on the top one, 7 per block on average)
    assert live_points == 4 * n
    counts = state.contact_counts()[1:].reshape(-1, 4)
    assert np.all(counts == [8, 8, 8, 4])


def test_point_pool_growth_redoes_the_step_bit_for_bit():
    # the counter-read path (> 64 blocks) starting from an 8-point pool: the first narrow phase overflows,
    # the pool grows to the live points and the narrow phase is redone from zeroed accumulators; the
    # trajectory is the one of a pool that was large enough
    _, s0, sol0 = _grid(100, 6)
    _, s1, sol1 = _grid(100, 6, shrink_pool=True)
    assert sol0.point_regrows == 0 and sol1.point_regrows >= 1
    assert s1.point_cap >= int(s1.tables[0]["pcount"].numpy()[0]) > 8
    for a, b in ((s0.positions_numpy(), s1.positions_numpy()), (s0.velocities_numpy(), s1.velocities_numpy()),
                 (s0.angular_velocities_numpy(), s1.angular_velocities_numpy())):
        assert np.array_equal(a, b)
