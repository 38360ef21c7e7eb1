"""DDA block solver: FCP contact detection, friction, toppling, impact, stacks, deformable and
kinematic blocks, time-step refusal.  Exact solutions as in docs/validation.md 'Rock mechanics verification'
("Rock blocks (exact)").  Small scenes so the Warp CPU backend (one thread) runs them quickly;
set ROCKWAVE_TEST_DEVICE=cuda:0 to run the same tests on a GPU."""

import math
import os

import numpy as np
import pytest
import warp as wp
from hypothesis import example, given, settings
from hypothesis import strategies as st

from rockwave.base.solver import TimeStep
from rockwave.dda import geometry as G
from rockwave.dda.blocks import (
    BlockModel,
    BlockOptions,
    BlockOverlapError,
    BlockSolver,
    BlockSpec,
    ContactMaterial,
    KinematicMotion,
    _sat_overlap,
)

wp.config.quiet = True
DEVICE = os.environ.get("ROCKWAVE_TEST_DEVICE", "cpu")
g = 9.81


class Rotation:
    """Minimal rotation helper (matrix based; quaternions in Warp's x, y, z, w order)."""

    def __init__(self, m):
        self.m = np.asarray(m, dtype=float)

    @staticmethod
    def identity():
        return Rotation(np.eye(3))

    @staticmethod
    def from_axis_angle(axis, angle):
        a = np.asarray(axis, float) / np.linalg.norm(axis)
        K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        return Rotation(np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K)

    @staticmethod
    def from_euler(seq, angles, degrees=False):
        angles = np.atleast_1d(np.asarray(angles, float))
        if degrees:
            angles = np.radians(angles)
        r = Rotation.identity()
        for ax, ang in zip(seq, angles):  # extrinsic (scipy's lower-case): successive fixed-axis turns
            r = Rotation.from_axis_angle({"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1)}[ax], ang) * r
        return r

    @staticmethod
    def from_quat(q):
        return Rotation(G.quat_to_matrix(q))

    @staticmethod
    def align(a, b):
        """Rotation taking unit vector a onto b."""
        a = np.asarray(a, float) / np.linalg.norm(a)
        b = np.asarray(b, float) / np.linalg.norm(b)
        c = np.cross(a, b)
        if np.linalg.norm(c) < 1e-12:
            return Rotation.identity()
        return Rotation.from_axis_angle(c, math.atan2(np.linalg.norm(c), a @ b))

    def __mul__(self, other):
        return Rotation(self.m @ other.m)

    def inv(self):
        return Rotation(self.m.T)

    def apply(self, v):
        return np.asarray(v, float) @ self.m.T

    def magnitude(self):
        return math.acos(max(-1.0, min(1.0, (np.trace(self.m) - 1) / 2)))

    def as_quat(self):
        m = self.m
        w = math.sqrt(max(0.0, 1 + m[0, 0] + m[1, 1] + m[2, 2])) / 2
        x = math.copysign(math.sqrt(max(0.0, 1 + m[0, 0] - m[1, 1] - m[2, 2])) / 2, m[2, 1] - m[1, 2])
        y = math.copysign(math.sqrt(max(0.0, 1 - m[0, 0] + m[1, 1] - m[2, 2])) / 2, m[0, 2] - m[2, 0])
        z = math.copysign(math.sqrt(max(0.0, 1 - m[0, 0] - m[1, 1] + m[2, 2])) / 2, m[1, 0] - m[0, 1])
        return np.array([x, y, z, w])


def quat(rot: Rotation):
    return tuple(rot.as_quat())  # scipy (x, y, z, w) == Warp order


_DT_ARRAYS = {}


def block_step(solver, state, dt):
    """One block step of length dt from the state's time (the clock's TimeStep)."""
    dt_array = _DT_ARRAYS.get(dt)
    if dt_array is None:
        dt_array = _DT_ARRAYS[dt] = wp.array([dt], dtype=float, device=DEVICE)
    solver.step(state, TimeStep(dt, state.time, dt_array))


def detect(specs, options=None, **kw):
    model = BlockModel(specs, device=DEVICE, check_overlap=False, **kw)
    state = model.state()
    solver = BlockSolver(model, options=options)
    solver.detect(state)
    return solver.contacts(state)


# ------------------------------------------------------------------------------------------------
# Fast Common Plane on known configurations
# ------------------------------------------------------------------------------------------------


def test_fcp_vertex_face():
    pen = 5e-4
    # corner of a unit cube pointing straight down onto a fixed slab
    rot = Rotation.align(np.ones(3), [0, 0, -1])
    zc = math.sqrt(3) / 2 - pen
    specs = [
        BlockSpec(G.box((4, 4, 1)), position=(0, 0, -0.5), kind="fixed", name="slab"),
        BlockSpec(G.box((1, 1, 1)), position=(0.3, -0.2, zc), orientation=quat(rot), name="corner"),
    ]
    (c,) = detect(specs)
    assert c["blocks"] == (0, 1)
    assert np.allclose(c["normal"], [0, 0, 1], atol=1e-5)
    assert c["gap"] == pytest.approx(-pen, abs=2e-6)
    assert len(c["points"]) == 1
    assert np.allclose(c["points"][0][:2], [0.3, -0.2], atol=1e-5)
    assert c["depths"][0] == pytest.approx(pen, abs=2e-6)


def _edge_edge_specs(pen, R=Rotation.identity(), shift=np.zeros(3)):
    a = 1.0
    h = a / math.sqrt(2)
    ra = R * Rotation.from_euler("x", 45, degrees=True)  # top edge along x
    rb = R * Rotation.from_euler("y", 45, degrees=True)  # bottom edge along y
    pa = R.apply([0, 0, 0]) + shift
    pb = R.apply([0.1, 0.2, 2 * h - pen]) + shift
    return [
        BlockSpec(G.box((a, a, a)), position=tuple(pa), orientation=quat(ra), kind="fixed", name="lower"),
        BlockSpec(G.box((a, a, a)), position=tuple(pb), orientation=quat(rb), name="upper"),
    ]


def test_fcp_edge_edge():
    pen = 1e-3
    (c,) = detect(_edge_edge_specs(pen))
    assert np.allclose(c["normal"], [0, 0, 1], atol=1e-5)
    assert c["gap"] == pytest.approx(-pen, abs=3e-6)
    assert len(c["points"]) == 1  # one point at the crossing of the two edges
    assert np.allclose(c["points"][0], [0.1, 0.0, 1 / math.sqrt(2) - pen / 2], atol=1e-4)
    assert c["depths"][0] == pytest.approx(pen, abs=3e-6)


def test_fcp_rotated_configuration_is_frame_independent():
    pen = 1e-3
    R = Rotation.from_euler("zyx", [37, -21, 63], degrees=True)
    shift = np.array([1.5, -2.0, 0.7])
    (c,) = detect(_edge_edge_specs(pen, R, shift))
    assert np.allclose(c["normal"], R.apply([0, 0, 1]), atol=1e-4)
    assert c["gap"] == pytest.approx(-pen, abs=1e-5)
    assert len(c["points"]) == 1
    expect = R.apply([0.1, 0.0, 1 / math.sqrt(2) - pen / 2]) + shift
    assert np.allclose(c["points"][0], expect, atol=2e-4)


def _patch_area(points, normal):
    t1 = np.cross(normal, [1, 0, 0] if abs(normal[0]) < 0.6 else [0, 1, 0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(normal, t1)
    p2 = np.stack([points @ t1, points @ t2], axis=1)
    c = p2.mean(axis=0)
    p2 = p2[np.argsort(np.arctan2(p2[:, 1] - c[1], p2[:, 0] - c[0]))]
    return 0.5 * abs(np.sum(p2[:, 0] * np.roll(p2[:, 1], -1) - np.roll(p2[:, 0], -1) * p2[:, 1]))


def test_fcp_face_face_offset_and_rotated():
    pen = 1e-3
    cube = G.box((1, 1, 1))
    # offset by (0.3, 0.2): overlap rectangle 0.7 x 0.8, four points
    specs = [
        BlockSpec(cube, position=(0, 0, 0), kind="fixed", name="lower"),
        BlockSpec(cube, position=(0.3, 0.2, 1 - pen), name="upper"),
    ]
    (c,) = detect(specs)
    assert np.allclose(c["normal"], [0, 0, 1], atol=1e-6)
    assert c["gap"] == pytest.approx(-pen, abs=2e-6)
    assert len(c["points"]) == 4
    assert np.allclose(c["depths"], pen, atol=2e-6)
    assert _patch_area(c["points"], c["normal"]) == pytest.approx(0.7 * 0.8, rel=1e-4)
    # upper cube turned 45 deg about z: octagonal overlap, 8 points, area 1 - 4 * 0.2071^2 = 0.8284
    specs[1] = BlockSpec(cube, position=(0, 0, 1 - pen), orientation=quat(Rotation.from_euler("z", 45, degrees=True)))
    (c,) = detect(specs)
    assert len(c["points"]) == 8
    assert np.allclose(c["depths"], pen, atol=2e-6)
    assert _patch_area(c["points"], c["normal"]) == pytest.approx(2 * math.sqrt(2) - 2, rel=1e-4)



@pytest.mark.parametrize("coop", [False, True])
def test_tilted_flush_faces_keep_their_points_at_any_small_turn(coop):
    # The cross joint of a jointed mass (issue 36, docs/notes.md 'A patch of two flush faces'): cube b on cube a
    # (0.5 m, as the rock mass), shifted 202 um along x (two of its corners beyond a's face), tilted about y (depth
    # +2.7 um at x = +0.25 to -0.5 um at x = -0.25), shifted 0.15 um across and turned by theta about z: its lateral
    # edges and a's are collinear within a fraction of a um (inside the vertex test's tolerance, 1e-6 x the block's
    # 0.87 m), crossing at x = 0.15 um / theta. The patch is a's two corners at x = +0.25 (2.7 um; the depth is zero
    # on a line inside the overlap). Before the fix the "crossing" of the lateral edges, found once their 2D
    # determinant passed 1e-6 |e_a| |e_b|, added two points at ~1.8 um depth from theta = 1.1 urad on (+74% patch
    # force): in a jointed mass such a point came and went every few steps.
    cube = G.box((0.5, 0.5, 0.5))
    tilt = Rotation.from_euler("y", 3.2e-6 / 0.5)
    sums = []
    for theta in np.linspace(0.4e-6, 2.0e-6, 9):
        specs = [BlockSpec(cube, position=(0, 0, 0), kind="fixed", name="a"),
                 BlockSpec(cube, position=(202e-6, -0.15e-6, 0.5 - 1.1e-6), orientation=quat(Rotation.from_euler("z", theta) * tilt),
                           name="b")]
        (c,) = detect(specs, options=BlockOptions(coop_min_vertices=0 if coop else None))
        assert len(c["depths"]) == 2, (theta, c["depths"])
        assert np.allclose(c["points"][:, 0], 0.25, atol=1e-4)
        assert np.allclose(c["depths"], 2.7e-6, atol=0.02e-6)
        sums.append(c["depths"].sum())
    assert np.ptp(sums) < 1e-3 * np.mean(sums)


def test_fcp_separated_gap():
    cube = G.box((1, 1, 1))
    specs = [
        BlockSpec(cube, position=(0, 0, 0), kind="fixed", name="a"),
        BlockSpec(cube, position=(1.1, 0, 0), name="b"),
    ]
    (c,) = detect(specs)
    assert np.allclose(c["normal"], [1, 0, 0], atol=1e-5)
    assert c["gap"] == pytest.approx(0.1, abs=1e-6)
    assert len(c["points"]) == 0
    # rotated 30 deg about z: its x-extent is 0.5 (cos 30 + sin 30) -> gap 1.2 - 0.5 - 0.6830
    specs[1] = BlockSpec(cube, position=(1.2, 0.1, 0.2), orientation=quat(Rotation.from_euler("z", 30, degrees=True)))
    (c,) = detect(specs)
    assert np.allclose(c["normal"], [1, 0, 0], atol=1e-5)
    assert c["gap"] == pytest.approx(1.2 - 0.5 - 0.5 * (math.cos(math.pi / 6) + math.sin(math.pi / 6)), abs=1e-5)
    assert len(c["points"]) == 0


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([-1e-3, -1e-4, 1e-4, 1e-3]))
@example(seed=1175471, target=1e-3)  # FCP stopped at a face plane (tied closest vertices), gap 1.07e-4
@example(seed=746325305, target=1e-4)  # the same, found by a 300-seed scan: gap 1.6e-5
def test_fcp_matches_exact_separating_axis_near_contact(seed, target):
    """Random rock vs box orientations, placed at a given overlap (-) or gap (+) by bisection on the
    exact separating-axis depth: the FCP gap equals it, and contact points appear only on overlap."""
    rng = np.random.default_rng(seed)
    ga = G.box((1.0, 0.6, 0.8))
    gb = G.prism(rng.normal(size=(12, 3)) * 0.4, name="rock")
    ra = Rotation.from_quat(rng.normal(size=4))
    rb = Rotation.from_quat(rng.normal(size=4))
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    va = ga.vertices @ ra.m.T

    def sat_depth(d):
        return _sat_overlap(va, ga, ra.m, gb.vertices @ rb.m.T + d * u, gb, rb.m)

    lo, hi = 0.0, 5.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if sat_depth(mid) > -target else (lo, mid)
    d = 0.5 * (lo + hi)
    specs = [BlockSpec(ga, orientation=tuple(ra.as_quat()), kind="fixed", name="box"),
             BlockSpec(gb, position=tuple(d * u), orientation=tuple(rb.as_quat()), name="rock")]
    (c,) = detect(specs)
    assert c["gap"] == pytest.approx(-sat_depth(d), abs=2e-5)
    assert (len(c["points"]) > 0) == (target < 0)
    if target < 0:
        assert np.all(c["depths"] <= -target + 2e-5)


def test_broad_phase_pairs_unique_and_complete():
    # 3 x 3 x 2 grid of cubes overlapping by 0.5 mm: every pair of neighbours (face, edge or corner
    # neighbours all overlap) exactly once, no far pairs
    cube = G.box((1, 1, 1))
    specs = []
    for i in range(3):
        for j in range(3):
            for k in range(2):
                specs.append(BlockSpec(cube, position=(i * 0.9995, j * 0.9995, k * 0.9995), name=f"c{i}{j}{k}"))
    model = BlockModel(specs, device=DEVICE, check_overlap=False)
    state = model.state()
    solver = BlockSolver(model)
    solver.detect(state)
    cs = solver.contacts(state)
    pairs = [c["blocks"] for c in cs]
    assert len(pairs) == len(set(pairs))
    touching = {c["blocks"] for c in cs if len(c["points"]) > 0}
    pos = model.base_position
    expect = {(a, b) for a in range(len(specs)) for b in range(a + 1, len(specs))
              if np.abs(pos[a] - pos[b]).max() < 1.0}
    assert touching == expect


# ------------------------------------------------------------------------------------------------
# friction on an incline (exact: d = 1/2 g (sin a - cos a tan phi) t^2)
# ------------------------------------------------------------------------------------------------


def incline_specs(alpha_deg, blocks, slope_phi=60.0, kn=1e7, slope_size=(6.0, 4.0, 0.5)):
    """Fixed slope tilted by alpha about y (downhill = +x'); blocks = list of (size, phi, s, y, kind, extra)."""
    R = Rotation.from_euler("y", alpha_deg, degrees=True)
    n = R.apply([0, 0, 1])
    d = R.apply([1, 0, 0])
    yv = R.apply([0, 1, 0])
    specs = [BlockSpec(G.box(slope_size), kind="fixed", orientation=quat(R), name="slope",
                       material=ContactMaterial(friction_angle_deg=slope_phi, normal_stiffness=kn))]
    for k, (size, phi, s, y, kind, extra) in enumerate(blocks):
        rho = 2500.0
        m = rho * np.prod(size)
        pen = m * g * math.cos(math.radians(alpha_deg)) / (4 * kn)
        c = (slope_size[2] / 2 + size[2] / 2 - pen) * n + s * d + y * yv
        specs.append(BlockSpec(G.box(size), position=tuple(c), orientation=quat(R), density=rho, kind=kind,
                               name=f"block{k}", material=ContactMaterial(friction_angle_deg=phi, normal_stiffness=kn),
                               **extra))
    return specs, d, n


def run(model, t_end, dt=None, record=None):
    state = model.state()
    solver = BlockSolver(model)
    dt = dt or solver.stable_dt(state)
    nsteps = int(round(t_end / dt))
    for k in range(nsteps):
        block_step(solver, state, dt)
        if record is not None:
            record(k, state)
    return state, solver, nsteps * dt


def test_block_slides_down_incline_exact():
    alpha, phi = 30.0, 20.0
    # k_n = 1e8: the shear spring starts unloaded and needs mu N / k_s of elastic slip (~ms) before
    # friction reaches mu N; that head start grows as 1/sqrt(k) (0.8% of d at k_n = 1e7, 0.25% here)
    specs, d, n = incline_specs(alpha, [((0.5, 0.5, 0.5), phi, -2.0, 0.0, "rigid", {})], kn=1e8)
    model = BlockModel(specs, device=DEVICE)
    x0 = model.base_position[1]
    state, solver, T = run(model, 1.0)
    disp = (state.positions_numpy()[1] - x0) @ d
    a = g * (math.sin(math.radians(alpha)) - math.cos(math.radians(alpha)) * math.tan(math.radians(phi)))
    assert disp == pytest.approx(0.5 * a * T * T, rel=0.01)
    # stays on the plane, does not rotate
    assert abs((state.positions_numpy()[1] - x0) @ n) < 1e-4
    assert np.linalg.norm(state.angular_velocities_numpy()[1]) < 1e-2
    assert state.contact_counts()[1] == 4


def test_separation_screen_agrees_with_full_narrow_phase():
    # four cubes with 0.2 mm joints sliding and jostling down an incline: step() skips FCP for pairs
    # whose last plane (bounded by the motion since) or warm-start plane still separates them; the full
    # narrow phase (detect(), no screen) at the same poses finds the same touching pairs, and the
    # screened pairs' gaps are lower bounds of FCP's
    blocks = [((0.5, 0.5, 0.5), 30.0, -1.0 + 0.5002 * i, 0.5002 * j, "rigid", {}) for i in range(2) for j in range(2)]
    specs, d, n = incline_specs(30.0, blocks, slope_phi=15.0)
    specs[2].angular_velocity = (0.0, 0.0, 0.5)
    model = BlockModel(specs, device=DEVICE, check_overlap=False)
    state = model.state()
    solver = BlockSolver(model)
    dt = solver.stable_dt(state)
    checked = 0
    for k in range(400):
        block_step(solver, state, dt)
        if k % 40 != 39:
            continue
        # screened narrow phase at the current poses (as the next step would run it), then the full one
        solver.detect(state, screen=True, dt=dt)
        step_cs = {c["blocks"]: c for c in solver.contacts(state)}
        solver.detect(state)  # also clears the forces of the screened pass
        full_cs = {c["blocks"]: c for c in solver.contacts(state)}
        assert set(step_cs) == set(full_cs)
        assert {p for p, c in step_cs.items() if len(c["points"])} == {p for p, c in full_cs.items() if len(c["points"])}
        for p, c in step_cs.items():
            if not len(c["points"]):
                # (a gap of 0 to float32 round-off at these ~1 m coordinates: touching without overlap, no
                # point, in both passes)
                assert -2.4e-7 <= c["gap"] <= full_cs[p]["gap"] + 1e-6
                checked += 1
    assert checked > 0, checked


def test_block_at_rest_when_friction_exceeds_slope():
    alpha, phi = 20.0, 30.0
    specs, d, n = incline_specs(alpha, [((0.5, 0.5, 0.5), phi, 0.0, 0.0, "rigid", {})])
    model = BlockModel(specs, device=DEVICE)
    x0 = model.base_position[1]
    state, solver, T = run(model, 2.0)
    creep = (state.positions_numpy()[1] - x0) @ d
    assert abs(creep) < 1e-3
    assert np.linalg.norm(state.velocities_numpy()[1]) < 1e-3


def test_sliding_versus_toppling_chart():
    # alpha = 30 deg (tan = 0.577); b/h = 1.0 (squat) or 0.1 (slender); phi = 40 or 8 deg.
    # Dynamic margins: a sliding block also topples only if tan(phi) > b/h (friction moment), and a
    # pivoting block also slides only if mu N < m (g sin a - theta'' h / 2); b/h = 0.1 with phi = 8
    # deg meets both clearly (with b/h = 0.3, phi = 20 deg sits on the boundary and only topples).
    alpha = 30.0
    squat, slender = (0.4, 0.4, 0.4), (0.05, 0.4, 0.5)
    cases = {  # name: (size, phi, expected slides, expected topples)
        "stable": (squat, 40.0, False, False),
        "topples": (slender, 40.0, False, True),
        "slides": (squat, 8.0, True, False),
        "slides_and_topples": (slender, 8.0, True, True),
    }
    blocks = [(size, phi, -1.0, -1.5 + k, "rigid", {}) for k, (size, phi, _, _) in enumerate(cases.values())]
    specs, d, n = incline_specs(alpha, blocks, kn=2e6)
    model = BlockModel(specs, device=DEVICE)
    q0 = model.initial_poses()[1]
    hist = []
    run(model, 0.6, record=lambda k, s: hist.append((s.positions_numpy(), s.orientations_numpy())))
    for k, (name, (size, phi, slides, topples)) in enumerate(cases.items()):
        b = k + 1
        # slide = motion of the downhill bottom edge (the toppling pivot) along the slope, measured
        # while the block is still on its base or pivot edge (tilt < 0.5 rad, before it lands)
        pivot_body = np.array([size[0] / 2, 0.0, -size[2] / 2])
        p0 = model.base_position[b] + Rotation.from_quat(q0[b]).apply(pivot_body)
        tilt, slide = 0.0, 0.0
        for pos, quats in hist:
            t_k = (Rotation.from_quat(quats[b]) * Rotation.from_quat(q0[b]).inv()).magnitude()
            if t_k > 0.5:
                break
            tilt = t_k
            slide = (pos[b] + Rotation.from_quat(quats[b]).apply(pivot_body) - p0) @ d
        assert (slide > 0.05) == slides, (name, slide, tilt)
        assert (tilt > 0.2) == topples, (name, slide, tilt)
        if not slides:
            assert abs(slide) < 5e-3, (name, slide)
        if not topples:
            assert tilt < 0.02, (name, tilt)


# ------------------------------------------------------------------------------------------------
# impact, stack, deformable, kinematic, limits
# ------------------------------------------------------------------------------------------------


def test_frictionless_elastic_impact_conserves_momentum_and_energy():
    mat = ContactMaterial(friction_angle_deg=0.0, normal_stiffness=1e7, restitution=1.0)
    cube = G.box((1, 1, 1))
    specs = [
        BlockSpec(cube, position=(0, 0, 0), velocity=(1.0, 0.0, 0.0), material=mat, density=2500, name="a"),
        BlockSpec(cube, position=(1.05, 0.0, 0.0), material=mat, density=2500, name="b"),
    ]
    model = BlockModel(specs, device=DEVICE, gravity=(0, 0, 0))
    s0 = model.state()
    p0, e0 = s0.linear_momentum(), s0.kinetic_energy()
    touched = []
    state, solver, T = run(model, 0.12, dt=2e-4, record=lambda k, s: touched.append(int(s.contact_counts()[0])))
    assert max(touched) == 4 and touched[-1] == 0  # face-face impact happened and ended
    p1, e1 = state.linear_momentum(), state.kinetic_energy()
    assert np.allclose(p1, p0, atol=0.01 * np.linalg.norm(p0))
    assert e1 == pytest.approx(e0, rel=0.01)
    v = state.velocities_numpy()
    # equal masses exchange velocities
    assert v[0][0] == pytest.approx(0.0, abs=0.02) and v[1][0] == pytest.approx(1.0, rel=0.02)


def test_stack_of_five_stays_at_rest():
    kn = 1e7
    a = 0.5
    m = 2500 * a**3
    mat = ContactMaterial(friction_angle_deg=35.0, normal_stiffness=kn)
    specs = [BlockSpec(G.box((3, 3, 0.5)), position=(0, 0, -0.25), kind="fixed", material=mat, name="floor")]
    z = 0.0
    for k in range(5):
        # start at the static penetration of each contact: (5 - k) m g / (4 k_n)
        z -= (5 - k) * m * g / (4 * kn)
        specs.append(BlockSpec(G.box((a, a, a)), position=(0.0, 0.0, z + a / 2), material=mat, density=2500, name=f"s{k}"))
        z += a
    model = BlockModel(specs, device=DEVICE)
    x0 = model.base_position.copy()
    state, solver, T = run(model, 5.0, dt=solver_dt(model, 0.9))
    x = state.positions_numpy()
    assert np.abs(x[1:, :2] - x0[1:, :2]).max() < 1e-5  # no lateral drift
    assert np.abs(x[1:, 2] - x0[1:, 2]).max() < 2e-5  # stays at the static penetration N m g / k_n
    assert np.abs(state.velocities_numpy()[1:]).max() < 1e-4
    assert np.abs(state.angular_velocities_numpy()[1:]).max() < 1e-4
    assert list(state.contact_counts()[1:]) == [8, 8, 8, 8, 4]


def solver_dt(model, safety):
    return BlockSolver(model, options=BlockOptions(dt_safety=safety)).stable_dt(model.state())


def test_rigid_and_stiff_deformable_blocks_agree():
    alpha, phi = 30.0, 20.0
    blocks = [
        ((0.5, 0.5, 0.5), phi, -2.0, -1.0, "rigid", {}),
        ((0.5, 0.5, 0.5), phi, -2.0, 1.0, "deformable", dict(youngs_modulus=2e9, poisson_ratio=0.25)),
    ]
    specs, d, n = incline_specs(alpha, blocks)
    model = BlockModel(specs, device=DEVICE)
    x0 = model.base_position
    state, solver, T = run(model, 0.5)
    x = state.positions_numpy()
    dr = (x[1] - x0[1]) @ d
    dd = (x[2] - x0[2]) @ d
    assert dr > 0.2
    assert dd == pytest.approx(dr, rel=0.01)
    eps = state.strains_numpy()
    assert np.all(eps[1] == 0.0)
    # contact pressure ~ m g cos a / A = 2500 * 9.81 * 0.5 * 0.866 ~ 10.6 kPa -> strains ~ 1e-6..1e-5
    assert 1e-8 < np.abs(eps[2]).max() < 1e-4
    # deformed vertices exported for USD: same count, close to the rigid shape
    wv = state.world_vertices()
    assert wv[2].shape == (8, 3)


def test_deformable_block_self_weight_strain():
    # block resting on a floor: mean vertical stress -rho g h / 2 -> eps_z = -rho g h / (2 E)
    E, rho, h = 1e8, 2500.0, 0.5
    # frictionless floor: base friction would hold back the Poisson expansion
    mat = ContactMaterial(normal_stiffness=1e7, damping_ratio=0.5, friction_angle_deg=0.0)
    specs = [
        BlockSpec(G.box((3, 3, 0.5)), position=(0, 0, -0.25), kind="fixed", material=mat, name="floor"),
        BlockSpec(G.box((0.5, 0.5, h)), position=(0, 0, h / 2 - 2500 * 0.125 * g / 4e7), kind="deformable",
                  density=rho, youngs_modulus=E, poisson_ratio=0.2, strain_damping_ratio=0.5, material=mat, name="soft"),
    ]
    model = BlockModel(specs, device=DEVICE)
    state, solver, T = run(model, 0.3)
    eps = state.strains_numpy()[1]
    assert eps[2] == pytest.approx(-rho * g * h / (2 * E), rel=0.03)
    # lateral strains from Poisson: eps_x = eps_y = -nu eps_z
    assert eps[0] == pytest.approx(-0.2 * eps[2], rel=0.05)


def test_kinematic_block_follows_sinusoid_exactly():
    A = np.array([0.1, 0.0, 0.05])
    f, ph = 2.0, 0.3
    specs = [
        BlockSpec(G.box((0.5, 0.5, 0.5)), position=(1.0, 2.0, 3.0), kind="kinematic",
                  motion=KinematicMotion.sine(A, f, ph), name="piston"),
        BlockSpec(G.box((0.5, 0.5, 0.5)), position=(0, 0, 10.0), name="faraway",
                  material=ContactMaterial(normal_stiffness=1e6)),
    ]
    model = BlockModel(specs, device=DEVICE, gravity=(0, 0, 0))
    state = model.state()
    solver = BlockSolver(model)
    dt = 1e-3
    for k in range(1, 301):
        block_step(solver, state, dt)
        t = k * dt
        if k % 50 == 0:
            x = state.positions_numpy()[0]
            v = state.velocities_numpy()[0]
            assert np.allclose(x, [1, 2, 3] + A * math.sin(2 * math.pi * f * t + ph), atol=2e-6)
            assert np.allclose(v, A * 2 * math.pi * f * math.cos(2 * math.pi * f * t + ph), atol=1e-5)
    # a table motion interpolates linearly and reports the segment slope
    mo = KinematicMotion.table([0.0, 0.1, 0.2], [[0, 0, 0], [0.1, 0, 0], [0.1, 0.2, 0]])
    specs[0] = BlockSpec(G.box((0.5, 0.5, 0.5)), position=(0, 0, 0), kind="kinematic", motion=mo, name="table")
    model = BlockModel(specs, device=DEVICE, gravity=(0, 0, 0))
    state = model.state()
    solver = BlockSolver(model)
    for k in range(150):
        block_step(solver, state, 1e-3)
    assert np.allclose(state.positions_numpy()[0], [0.1, 0.1, 0.0], atol=1e-5)
    assert np.allclose(state.velocities_numpy()[0], [0.0, 2.0, 0.0], atol=1e-4)


def test_kinematic_piston_pushes_block():
    # piston moving +x at 0.5 m/s (table) hits a frictionless free block; restitution e = 0.5 -> the
    # block leaves at v_p (1 + e) = 0.75 m/s and the piston never catches up
    mat = ContactMaterial(friction_angle_deg=0.0, normal_stiffness=1e7, restitution=0.5)
    specs = [
        BlockSpec(G.box((0.5, 0.5, 0.5)), kind="kinematic", material=mat, name="piston",
                  motion=KinematicMotion.table([0.0, 10.0], [[0, 0, 0], [5.0, 0, 0]])),
        BlockSpec(G.box((0.5, 0.5, 0.5)), position=(0.55, 0, 0), material=mat, name="pushed"),
    ]
    model = BlockModel(specs, device=DEVICE, gravity=(0, 0, 0))
    state, solver, T = run(model, 0.4)
    v = state.velocities_numpy()[1]
    assert v[0] == pytest.approx(0.75, rel=0.01)
    assert state.positions_numpy()[1][0] > 0.55 + 0.1
    assert state.contact_counts()[1] == 0


def test_external_force_hook():
    specs = [BlockSpec(G.box((1, 1, 1)), density=1000.0, name="free", material=ContactMaterial(normal_stiffness=1e6))]
    model = BlockModel(specs, device=DEVICE, gravity=(0, 0, 0))
    state = model.state()
    solver = BlockSolver(model)
    dt = 1e-3
    for _ in range(100):
        state.ext_force.assign(np.array([[1000.0, 0.0, 0.0]], np.float32))
        state.ext_torque.assign(np.array([[0.0, 0.0, 1000.0 / 6.0]], np.float32))
        block_step(solver, state, dt)
    assert state.velocities_numpy()[0] == pytest.approx([0.1, 0, 0], abs=1e-6)  # F/m t = 1 * 0.1
    assert state.angular_velocities_numpy()[0][2] == pytest.approx(0.1, rel=1e-4)  # tau / I t
    assert np.all(state.ext_force.numpy() == 0)  # zeroed after use


def test_dt_above_critical_refused():
    specs, d, n = incline_specs(30.0, [((0.5, 0.5, 0.5), 20.0, 0.0, 0.0, "rigid", {})])
    model = BlockModel(specs, device=DEVICE)
    solver = BlockSolver(model)
    state = model.state()
    dc = solver.critical_dt()
    m = 2500 * 0.125
    om_t = math.sqrt(1e7 * 8 / m)
    assert dc < 2 / om_t  # rotation and damping make it stricter than the translational bound
    assert solver.stable_dt(state) == pytest.approx(0.5 * dc)  # BlockOptions.dt_safety = 0.5
    quarter = BlockSolver(model, options=BlockOptions(dt_safety=0.25))
    assert quarter.stable_dt(state) == pytest.approx(0.25 * dc) and quarter.critical_dt() == dc
    with pytest.raises(TypeError, match="dt_safety"):  # the old stable_dt(safety) call
        solver.stable_dt(0.5)
    with pytest.raises(ValueError, match="dt_safety"):
        BlockSolver(model, options=BlockOptions(dt_safety=1.5))
    with pytest.raises(ValueError, match="critical"):
        block_step(solver, state, 1.01 * dc)
    block_step(solver, state, 0.99 * dc)  # just below is accepted


def test_overlapping_initial_blocks_refused_naming_pair():
    cube = G.box((1, 1, 1))
    specs = [
        BlockSpec(cube, position=(0, 0, 0), kind="fixed", name="ground"),
        BlockSpec(cube, position=(3, 0, 0), name="loner"),
        BlockSpec(cube, position=(0.2, 0.1, 0.9), name="sunk"),
    ]
    with pytest.raises(BlockOverlapError) as ei:
        BlockModel(specs, device=DEVICE)
    msg = str(ei.value)
    assert "'ground'" in msg and "'sunk'" in msg and "loner" not in msg
    assert "0.1 m" in msg


def test_free_fall_bounce_restitution():
    # rebound height e^2 H for a linear spring-dashpot with zeta from e (docs/validation.md)
    e, H = 0.6, 0.2
    # stiff contact: gravity during the contact (duration ~ pi sqrt(m / 4k)) biases e by ~ g / (omega v0)
    mat = ContactMaterial(normal_stiffness=2e7, restitution=e, friction_angle_deg=30.0)
    specs = [
        BlockSpec(G.box((3, 3, 0.5)), position=(0, 0, -0.25), kind="fixed", material=mat, name="floor"),
        BlockSpec(G.box((0.4, 0.4, 0.4)), position=(0, 0, 0.2 + H), material=mat, density=2500, name="ball"),
    ]
    model = BlockModel(specs, device=DEVICE)
    zs = []
    dt = 5e-5  # omega dt ~ 0.035
    state, solver, T = run(model, 0.4, dt=dt, record=lambda k, s: zs.append(s.positions_numpy()[1][2]))
    zs = np.array(zs)
    t_hit = math.sqrt(2 * H / g)
    after = zs[int(1.2 * t_hit / dt):]
    rebound = after.max() - 0.2
    # the floor is fixed (m_eff = m); zeta is calibrated for the no-pull contact, so e is exact
    assert rebound == pytest.approx(e * e * H, rel=0.02)


def test_planar_model_moves_in_its_plane():
    """A planar model (2D scenes) keeps blocks in their x-y plane inside BlockSolver.step: z stays at
    the spec's, v_z = 0, spin about z only; fixed blocks are untouched. The same block in a 3D model
    leaves the plane and tumbles."""
    mat = ContactMaterial(normal_stiffness=1e6)
    specs = [
        BlockSpec(G.box((0.5, 0.5, 0.5)), position=(0.0, 0.0, 0.25), velocity=(1.0, 0.5, 2.0),
                  angular_velocity=(3.0, -2.0, 1.0), material=mat, name="free"),
        BlockSpec(G.box((0.5, 0.5, 0.5)), position=(5.0, 0.0, 0.3), kind="fixed", material=mat, name="wall"),
    ]
    out = {}
    for planar in (False, True):
        model = BlockModel(specs, device=DEVICE, gravity=(0.0, -9.81, -9.81), planar=planar)
        assert model.planar == planar
        state = model.state()
        solver = BlockSolver(model)
        for _ in range(10):
            block_step(solver, state, 1e-3)
        out[planar] = (state.positions_numpy(), state.velocities_numpy(), state.angular_velocities_numpy(),
                       state.orientations_numpy())
    x, v, w, q = out[True]
    assert x[0, 2] == pytest.approx(0.25, abs=1e-7) and v[0, 2] == 0.0
    assert x[0, 0] > 0.009 and v[0, 1] < 0.5  # it moves in the plane (and falls along -y)
    assert w[0, 0] == 0.0 and w[0, 1] == 0.0 and w[0, 2] == pytest.approx(1.0, rel=1e-6)
    assert q[0, 0] == 0.0 and q[0, 1] == 0.0 and q[0, 2] == pytest.approx(math.sin(0.005), rel=1e-4)
    assert np.allclose(x[1], [5.0, 0.0, 0.3], atol=1e-7)
    x3, v3, w3, q3 = out[False]
    assert x3[0, 2] > 0.25 + 0.01 and abs(w3[0, 0]) > 1.0 and abs(q3[0, 0]) > 1e-3  # the check is not vacuous


def _cube_on_slope(alpha, phi, size, kn, t_end):
    """A cube resting in contact on a fixed slope (no initial gap, no pre-set penetration, gravity from t = 0).
    Returns (downhill displacement [m], largest elastic shear-spring extension |f_s|/k_s of its contact
    points at the end [m], speed at the end [m/s], T)."""
    R = Rotation.from_euler("y", alpha, degrees=True)
    n, d = R.apply([0, 0, 1]), R.apply([1, 0, 0])
    slope = (6 * size, 3 * size, size / 2)
    mat = ContactMaterial(friction_angle_deg=phi, normal_stiffness=kn)
    specs = [BlockSpec(G.box(slope), kind="fixed", orientation=quat(R), name="slope", material=mat),
             BlockSpec(G.box((size, size, size)), position=tuple((slope[2] + size) / 2 * n), orientation=quat(R),
                       density=2600.0, material=mat)]
    model = BlockModel(specs, device=DEVICE)
    x0 = model.base_position[1]
    state, solver, T = run(model, t_end)
    t = state.tables[0]
    slots = np.nonzero(t["keys"].numpy() >= 0)[0]
    nc = t["nc"].numpy()
    ps = t["pstart"].numpy()
    shear = t["shear"].numpy()
    ext = max(float(np.linalg.norm(shear[ps[s]: ps[s] + nc[s]], axis=1).max(initial=0.0)) for s in slots)
    return ((state.positions_numpy()[1] - x0) @ d, ext / model.np["k_s"][1],
            float(np.linalg.norm(state.velocities_numpy()[1])), T)


@pytest.mark.parametrize("size, kn", [(8.0, None), (1.0, 1e7), (0.5, 5e6)])
def test_static_friction_holds_at_a_small_margin(size, kn):
    # issue 20: friction 0.1 deg above the slope holds: the block moves no more than its elastic shear
    # deflection + 1 mm in 2 s and is at rest (before: the 8 m cube at the default k_n crept 83 mm and
    # was still moving). Causes: a suddenly loaded stuck shear spring overshoots to 2x its load, and the
    # normal spring, started without penetration and damped for restitution 0.5, dips to ~0.78 m g cos a;
    # either exceeds a 0.1 deg margin. Fix (kernels/dda/blocks.py narrow_phase): an overdamped stuck shear
    # dashpot that only takes the Coulomb capacity its spring leaves, critical damping of resting (not
    # impact) normal contacts, both implicit in the block update, and a Coulomb cap on the normal force
    # the implicit step actually applied.
    disp, ext, speed, T = _cube_on_slope(35.0, 35.1, size, kn, 2.0)
    assert disp - ext < 1e-3, (disp, ext)
    assert speed < 1e-3 * size
