"""Rock-mechanics verification set (issue 20): a block on an incline at a 0.1 degree friction margin over
block sizes, slenderness and contact stiffnesses; a wedge on two joints against Hoek & Bray's limit
equilibrium; a block on a shaking slope against Newmark's (1965) rigid-plastic sliding. One or two blocks
on fixed or kinematic blocks, short runs: cheap on Warp's CPU backend.  docs/validation.md "Rock mechanics
verification" lists these with their measured errors."""

import dataclasses
import math
import os

import numpy as np
import pytest
import warp as wp

import rockwave
from rockwave.base.solver import TimeStep
from rockwave.dda import geometry as G
from rockwave.dda.blocks import BlockModel, BlockSolver, BlockSpec, ContactMaterial, KinematicMotion
from rockwave.scene.format import load_scene

wp.config.quiet = True
DEVICE = os.environ.get("ROCKWAVE_TEST_DEVICE", "cpu")
g = 9.81
RHO = 2600.0
SCENES = os.path.join(os.path.dirname(__file__), os.pardir, "scenes")


def rot_y(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])


def rot_x(deg):
    a = math.radians(deg)
    return np.array([[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]])


def mat_to_quat(m):
    """Rotation matrix -> quaternion (x, y, z, w), Warp's order."""
    w = math.sqrt(max(0.0, 1 + m[0, 0] + m[1, 1] + m[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + m[0, 0] - m[1, 1] - m[2, 2])) / 2, m[2, 1] - m[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - m[0, 0] + m[1, 1] - m[2, 2])) / 2, m[0, 2] - m[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - m[0, 0] - m[1, 1] + m[2, 2])) / 2, m[1, 0] - m[0, 1])
    return (x, y, z, w)


def simulate(model, t_end, record=None):
    """Run the block solver at its stable step for t_end; record(t, state) after every step."""
    state = model.state()
    solver = BlockSolver(model)
    dt = solver.stable_dt(state)
    dt_array = wp.array([dt], dtype=float, device=DEVICE)
    nsteps = int(round(t_end / dt))
    for _ in range(nsteps):
        solver.step(state, TimeStep(dt, state.time, dt_array))
        if record is not None:
            record(state.time, state)
    return state, nsteps * dt


def shear_extension(model, state):
    """Largest elastic shear-spring extension |f_s| / k_s over the contact points of the state [m]."""
    t = state.tables[0]
    slots = np.nonzero(t["keys"].numpy() >= 0)[0]
    nc = t["nc"].numpy()
    start = t["pstart"].numpy()  # a pair's points: pool entries pstart .. pstart + nc
    shear = t["shear"].numpy()
    ext = max((float(np.linalg.norm(shear[start[s]:start[s] + nc[s]], axis=1).max(initial=0.0)) for s in slots),
              default=0.0)
    return ext / float(model.np["k_s"][-1])


# ------------------------------------------------------------------------------------------------
# block on an incline at a 0.1 degree friction margin, and sliding below it
# ------------------------------------------------------------------------------------------------


def block_on_slope(alpha, phi, width, height, kn, t_end, info=None):
    """A width x width x height block resting in contact on a fixed slope (no gap, no pre-set penetration,
    gravity from t = 0).  Returns (downhill displacement of the centre of its base [m], elastic shear
    extension at the end [m], speed at the end [m/s], tilt [rad], T [s]); info (a dict, optional) gets the
    block's mass [kg] and k_s [N/m per point]."""
    R = rot_y(alpha)
    n, d = R @ [0, 0, 1], R @ [1, 0, 0]
    slope = (6 * width, 3 * width, width / 2)
    mat = ContactMaterial(friction_angle_deg=phi, normal_stiffness=kn)
    specs = [BlockSpec(G.box(slope), kind="fixed", orientation=mat_to_quat(R), name="slope", material=mat),
             BlockSpec(G.box((width, width, height)), position=tuple((slope[2] + height) / 2 * n),
                       orientation=mat_to_quat(R), density=RHO, material=mat, name="block")]
    model = BlockModel(specs, device=DEVICE)
    if info is not None:
        info.update(mass=float(model.np["mass"][1]), k_s=float(model.np["k_s"][1]))
    x0 = model.base_position[1]
    state, T = simulate(model, t_end)
    Rq = G.quat_to_matrix(state.orientations_numpy()[1])
    base = state.positions_numpy()[1] + Rq @ (R.T @ (-height / 2 * n))
    tilt = math.acos(min(1.0, float(np.trace(Rq @ R.T) - 1) / 2))
    return ((base - (x0 - height / 2 * n)) @ d, shear_extension(model, state),
            float(np.linalg.norm(state.velocities_numpy()[1])), tilt, T)


def soft_joint_kn(width):
    """Per-point normal stiffness of a soft joint: 1e7 N/m for a metre-sized block, scaled with the face area
    share of a point (a joint stiffness in Pa/m times the area, k ~ width^2)."""
    return 1.0e7 * width * width


# (width [m], height / width, k_n per point [N/m] or None for the default 0.1 E L): 0.5 to 10 m, squat to
# slender (the toppling limit on 35 degrees is h/w = 1 / tan 35 = 1.43), soft joints to the default
STATIC_CASES = [
    (0.5, 0.5, "soft"), (0.5, 1.2, "soft"), (2.0, 0.5, None), (2.0, 1.2, None),
    (10.0, 0.5, "soft"), (10.0, 1.0, None), (1.0, 1.35, 1.0e8),
]


@pytest.mark.parametrize("width, aspect, kn", STATIC_CASES)
def test_static_friction_holds_over_sizes_shapes_and_stiffnesses(width, aspect, kn):
    # issue 20: friction 0.1 deg above a 35 deg slope, started in contact without pre-set penetration,
    # gravity from t = 0: in 2 s the base moves no more than its elastic shear deflection + 0.1 mm, and the
    # block is at rest. Issue 36 (float32 orientations no longer round a resting block's turn away): measured
    # disp - ext -0.02 .. -4.4 mm (the most loaded spring's extension exceeds the base's motion), speed <= 5e-6 m/s
    # (before: 1 mm and 1e-3 x width m/s allowed; the creep rate itself: tests/test_static_friction.py)
    kn = soft_joint_kn(width) if kn == "soft" else kn
    disp, ext, speed, tilt, T = block_on_slope(35.0, 35.1, width, aspect * width, kn, 2.0)
    assert disp - ext < 1e-4, (disp, ext)
    assert speed < 1e-5, speed
    assert tilt < 2e-3, tilt  # elastic tilt only: neither toppling nor lifting


@pytest.mark.parametrize("width, aspect, kn", [(10.0, 1.2, "soft"), (10.0, 1.4, "soft"), (1.0, 1.35, "soft"),
                                               (10.0, 1.2, None)])
def test_static_friction_holds_for_slender_blocks(width, aspect, kn):
    # issue 20, slender blocks up to the toppling limit (h/w 1 / tan 35 = 1.43): their uphill points carry
    # little of the normal force, and gravity from t = 0 pitches them forward. Before the overdamped rocking
    # dashpot of a resting face (kernels/dda/blocks.py contact_forces) the 10 m block of h/w 1.2 on a soft joint
    # slid 31.4 mm against 20.3 mm of spring extension (11.0 mm without slip); now 6.7 mm. Checked against
    # both the springs' extension and the deflection with no slip at all, m g sin a / (4 k_s) (a box face on a
    # larger face touches at its 4 corners)
    kn = soft_joint_kn(width) if kn == "soft" else kn
    info = {}
    disp, ext, speed, tilt, T = block_on_slope(35.0, 35.1, width, aspect * width, kn, 2.0, info)
    no_slip = info["mass"] * g * math.sin(math.radians(35.0)) / (4 * info["k_s"])
    # issue 36: measured disp - ext <= -1.2 mm, disp - no_slip <= -0.35 mm; the soft 10 m blocks still rock at 2 s
    # (6e-5 and 1.4e-4 x width m/s: the overdamped rocking mode of a plain start decays with ~0.7 s), the others
    # move <= 2e-6 m/s
    assert disp - ext < 1e-4, (disp, ext)
    assert disp < no_slip + 1e-4, (disp, no_slip)
    assert speed < 2e-4 * width, speed
    assert tilt < 2e-3, tilt


@pytest.mark.parametrize("width, aspect, kn", [(0.5, 1.0, "soft"), (2.0, 1.2, "soft"), (10.0, 1.0, None)])
def test_sliding_block_matches_exact_displacement(width, aspect, kn):
    # friction below the slope (phi 30 on 35 deg): d = 1/2 g (sin a - cos a tan phi) t^2 within 1%
    kn = soft_joint_kn(width) if kn == "soft" else kn
    disp, ext, speed, tilt, T = block_on_slope(35.0, 30.0, width, aspect * width, kn, 1.0)
    a = g * (math.sin(math.radians(35.0)) - math.cos(math.radians(35.0)) * math.tan(math.radians(30.0)))
    assert disp == pytest.approx(0.5 * a * T * T, rel=0.01)


# ------------------------------------------------------------------------------------------------
# wedge on two joints (Hoek & Bray)
# ------------------------------------------------------------------------------------------------


def wedge_limit(psi, delta_a, delta_b):
    """Hoek & Bray (Rock Slope Engineering, 4th ed., ch. 8 (wedge), eq. for the wedge factor): a wedge on two
    planes A and B through a line plunging at psi, each plane dipping at delta_a / delta_b from the horizontal
    in the section normal to that line.  The normal reactions balance the weight's component normal to the
    line, W cos(psi): R_A n_A + R_B n_B = W cos(psi) e_z, so R_A = W cos(psi) sin(delta_b) / sin(delta_a +
    delta_b), R_B = W cos(psi) sin(delta_a) / sin(delta_a + delta_b) (for a symmetric wedge R_A + R_B =
    W cos(psi) sin(beta) / sin(xi / 2), beta = 90 deg, xi = 180 deg - 2 delta: Hoek & Bray's wedge factor).
    FS = (R_A + R_B) tan(phi) / (W sin(psi)); returns ((R_A + R_B) / (W cos psi), the limit friction angle
    [deg] where FS = 1)."""
    a, b, p = (math.radians(v) for v in (delta_a, delta_b, psi))
    k = (math.sin(a) + math.sin(b)) / math.sin(a + b)
    return k, math.degrees(math.atan(math.tan(p) / k))


def wedge_specs(psi, delta_a, delta_b, phi, kn=None, height=0.4, length=1.0, start=-1.0, shift=0.0):
    """A triangular prism wedge resting in contact (no gap, no pre-set penetration) in the groove of two fixed
    boxes whose top faces are the joint planes A and B.  Local frame: the line of intersection along x
    (downhill), plane A rising towards +y at delta_a, plane B towards -y at delta_b; the whole set is turned
    by psi about y so the line plunges at psi, then moved by shift [m] along the line (the same scene at
    another place in the world frame).  Returns (specs, world direction of the line, wedge mass)."""
    a, b = math.radians(delta_a), math.radians(delta_b)
    Rw = rot_y(psi)
    mat = ContactMaterial(friction_angle_deg=phi, normal_stiffness=kn)
    pa = np.array([0.0, height / math.tan(a), height])  # top corners of the section (on plane A / B)
    pb = np.array([0.0, -height / math.tan(b), height])
    section = [np.zeros(3), pa, pb]
    verts = [s + [x, 0.0, 0.0] for s in section for x in (-length / 2, length / 2)]
    centroid = np.mean(section, axis=0) + [start, 0.0, 0.0]
    verts_world = [Rw @ v for v in verts]
    poly = G.prism([v - Rw @ np.mean(section, axis=0) for v in verts_world], name="wedge")
    specs = []
    gap = 1e-3  # the two joint blocks stop 1 mm short of the groove line (they do not touch each other)
    for name, R_j, side, w in (("joint_A", rot_x(delta_a), 1.0, 1.5), ("joint_B", rot_x(-delta_b), -1.0, 1.5)):
        size = (4.0, w, 0.3)
        c = R_j @ [0.0, side * (gap + w / 2), -size[2] / 2]
        specs.append(BlockSpec(G.box(size), kind="fixed", position=tuple(Rw @ c), orientation=mat_to_quat(Rw @ R_j),
                               name=name, material=mat))
    specs.append(BlockSpec(poly, position=tuple(Rw @ centroid), density=RHO, material=mat, name="wedge"))
    mass = RHO * 0.5 * height * (pa[1] - pb[1]) * length
    line = Rw @ [1.0, 0.0, 0.0]
    specs = [dataclasses.replace(s, position=tuple(np.asarray(s.position) + shift * line)) for s in specs]
    return specs, line, mass


def wedge_run(psi, delta_a, delta_b, phi, t_end, kn=None, t_mid=None, shift=0.0):
    """The wedge after t_end: (displacement along the line of intersection [m], elastic shear extension [m],
    speed [m/s], acceleration along the line from t_mid to t_end [m/s^2], T [s])."""
    specs, line, mass = wedge_specs(psi, delta_a, delta_b, phi, kn=kn, shift=shift)
    model = BlockModel(specs, device=DEVICE)
    x0 = model.base_position[2]
    mid = []

    def record(t, state):
        if t_mid is not None and not mid and t >= t_mid:
            mid.append((t, float(state.velocities_numpy()[2] @ line)))

    state, T = simulate(model, t_end, record)
    v_end = float(state.velocities_numpy()[2] @ line)
    accel = (v_end - mid[0][1]) / (T - mid[0][0]) if mid else None
    return ((state.positions_numpy()[2] - x0) @ line, shear_extension(model, state),
            float(np.linalg.norm(state.velocities_numpy()[2])), accel, T)


WEDGE = (30.0, 40.0, 55.0)  # plunge of the line of intersection, dips of planes A and B in its normal section


def test_hoek_bray_wedge_limit():
    # the asymmetric wedge's limit friction angle from Hoek & Bray's reactions (21.48 deg; the plane failure
    # limit would be 30 deg): 0.5 deg above it the wedge holds (moves less than its elastic shear deflection + 1 mm, at rest), 0.5 deg below
    # it slides, and once sliding its acceleration along the line is g (sin psi - k cos psi tan phi).
    # Soft joints (k_n 1e7 N/m per point for this 0.4 m x 1 m wedge, 390 kg).
    psi, da, db = WEDGE
    k, phi_lim = wedge_limit(psi, da, db)
    assert 1.46 < k < 1.47 and 21.4 < phi_lim < 21.5  # the reference itself (sin 40 + sin 55) / sin 95
    disp, ext, speed, _, T = wedge_run(psi, da, db, phi_lim + 0.5, 2.0, kn=1e7)
    assert disp - ext < 1e-3 and speed < 1e-3, (disp, ext, speed)
    phi = phi_lim - 0.5
    disp, ext, speed, accel, T = wedge_run(psi, da, db, phi, 2.0, kn=1e7, t_mid=1.0)
    a = g * (math.sin(math.radians(psi)) - k * math.cos(math.radians(psi)) * math.tan(math.radians(phi)))
    assert disp > 0.1, disp  # 0.5 a T^2 = 0.25 m
    assert accel == pytest.approx(a, rel=0.03), (accel, a)


def test_hoek_bray_wedge_slides_below_the_limit_at_the_default_stiffness():
    # issue 20: the wedge sits ~1.2 um deep at the default k_n, its centroid ~1 m from the origin where the float32
    # spacing is 6-12e-8 m; with plain float32 centroids and world vertices it crept at 3.3 mm/s. With the
    # compensated centroid (x + x_lo) and the pair-frame narrow phase it slides as near the origin (docs/notes.md)
    psi, da, db = WEDGE
    k, phi_lim = wedge_limit(psi, da, db)
    phi = phi_lim - 0.5
    disp, ext, speed, accel, T = wedge_run(psi, da, db, phi, 1.0)
    a = g * (math.sin(math.radians(psi)) - k * math.cos(math.radians(psi)) * math.tan(math.radians(phi)))
    assert disp > 0.25 * a * T * T, (disp, 0.5 * a * T * T)  # at least half the analytic 62 mm


def test_hoek_bray_wedge_holds_above_the_limit_at_the_default_stiffness():
    # issue 20: 0.5 deg above the limit at the default k_n, ~1 m from the origin, the wedge holds as with soft
    # joints (moves less than its elastic shear deflection + 1 mm in 1 s, at rest). Measured over 2 s: 0.019 mm,
    # 1.6e-6 m/s; with plain float32 centroids it crept
    psi, da, db = WEDGE
    k, phi_lim = wedge_limit(psi, da, db)
    disp, ext, speed, _, T = wedge_run(psi, da, db, phi_lim + 0.5, 1.0)
    assert disp - ext < 1e-3 and speed < 1e-3, (disp, ext, speed)


def test_hoek_bray_wedge_slides_at_the_default_stiffness_near_the_world_origin():
    # the contact law at the default (stiff) k_n: the scene of the test above moved 1 m along its line so the
    # wedge starts within 0.3 m of the world origin: 0.5 deg below the limit it accelerates at
    # g (sin psi - k cos psi tan phi) (measured -0.8% from 0.25 to 0.5 s with plain float32 centroids, +0.01%
    # now; the same +0.02% at 1 m, 10 m and 100 m: tests/test_block_precision.py checks the far positions)
    psi, da, db = WEDGE
    k, phi_lim = wedge_limit(psi, da, db)
    phi = phi_lim - 0.5
    disp, ext, speed, accel, T = wedge_run(psi, da, db, phi, 0.5, t_mid=0.25, shift=1.0)
    a = g * (math.sin(math.radians(psi)) - k * math.cos(math.radians(psi)) * math.tan(math.radians(phi)))
    assert accel == pytest.approx(a, rel=0.03), (accel, a)


# ------------------------------------------------------------------------------------------------
# block on a shaking slope (Newmark 1965)
# ------------------------------------------------------------------------------------------------


def newmark_displacement(beta, phi, base_accel, t_end, dt=2e-5):
    """Newmark (1965, "Effects of earthquakes on dams and embankments", Geotechnique 15(2)) rigid-plastic
    sliding block on a plane inclined at beta, friction angle phi, whose base accelerates along the plane by
    base_accel(t) (positive downhill).  Relative to the base, with u downhill:
        sliding downhill (du/dt > 0):  d2u/dt2 = g sin(beta) - a_b(t) - g cos(beta) tan(phi)
        sliding uphill   (du/dt < 0):  d2u/dt2 = g sin(beta) - a_b(t) + g cos(beta) tan(phi)
    and at rest on the base (du/dt = 0) while |g sin(beta) - a_b(t)| <= g cos(beta) tan(phi).  Integrated at
    a fine step; a sliding phase ends on the step where du/dt changes sign.  Returns u(t_end) [m]."""
    b, mu = math.radians(beta), math.tan(math.radians(phi))
    drive0, fric = g * math.sin(b), g * math.cos(b) * mu
    u, v = 0.0, 0.0
    for k in range(int(round(t_end / dt))):
        t = (k + 0.5) * dt
        drive = drive0 - base_accel(t)
        if v == 0.0:
            if abs(drive) <= fric:
                continue
            a = drive - math.copysign(fric, drive)
        else:
            a = drive - math.copysign(fric, v)
        v_new = v + a * dt
        if v != 0.0 and v_new * v < 0.0:
            u += 0.5 * v * (v / -a)  # stops within the step
            v = 0.0
        else:
            u += 0.5 * (v + v_new) * dt
            v = v_new
    return u


def shaking_slope(beta, phi, amp, freq, t_end, width=1.0, kn=None):
    """A width-sized cube resting in contact on a kinematic slope that moves along its own dip direction by
    u_b = amp sin(2 pi freq t); the block starts with the base's velocity (both at zero acceleration).
    Returns (the block's displacement relative to the base along the dip [m], T [s])."""
    R = rot_y(beta)
    n, d = R @ [0, 0, 1], R @ [1, 0, 0]
    omega = 2 * math.pi * freq
    slope = (6 * width, 3 * width, width / 2)
    mat = ContactMaterial(friction_angle_deg=phi, normal_stiffness=kn)
    specs = [BlockSpec(G.box(slope), kind="kinematic", orientation=mat_to_quat(R), name="base", material=mat,
                       motion=KinematicMotion.sine(tuple(amp * d), freq)),
             BlockSpec(G.box((width, width, width)), position=tuple((slope[2] + width) / 2 * n),
                       orientation=mat_to_quat(R), density=RHO, material=mat, name="block",
                       velocity=tuple(amp * omega * d))]
    model = BlockModel(specs, device=DEVICE)
    x0 = model.base_position
    state, T = simulate(model, t_end)
    x = state.positions_numpy()
    return float(((x[1] - x0[1]) - (x[0] - x0[0])) @ d), T


NEWMARK = (20.0, 30.0, 2.0)  # slope beta [deg], friction phi [deg], shaking frequency [Hz]; a_y = 0.20 g


def test_newmark_reference_integrator():
    # the reference itself: no shaking and phi < beta slides as 1/2 g (sin b - cos b tan phi) t^2; a stable
    # block under no shaking stays; a constant uphill base acceleration beyond the yield one slides as
    # 1/2 (a_0 - a_y) t^2
    a = g * (math.sin(math.radians(30.0)) - math.cos(math.radians(30.0)) * math.tan(math.radians(20.0)))
    assert newmark_displacement(30.0, 20.0, lambda t: 0.0, 1.0) == pytest.approx(0.5 * a, rel=1e-4)
    assert newmark_displacement(20.0, 30.0, lambda t: 0.0, 1.0) == 0.0
    a_y = g * (math.cos(math.radians(20.0)) * math.tan(math.radians(30.0)) - math.sin(math.radians(20.0)))
    assert newmark_displacement(20.0, 30.0, lambda t: -3.0, 1.0) == pytest.approx(0.5 * (3.0 - a_y), rel=1e-4)


@pytest.mark.parametrize("peak_g", [0.3, 0.6])
def test_newmark_block_on_shaking_slope(peak_g):
    # a 1 m cube on a 20 deg slope (phi 30 deg: yield acceleration 0.20 g along the slope) shaken along its
    # dip at 2 Hz with peak acceleration 0.3 g / 0.6 g for 2 s (4 cycles; the uphill yield, 0.88 g, is not
    # reached): its permanent displacement relative to the base is Newmark's within 5% (measured +0.35% /
    # +0.24% at k_n 1e8 N/m per point)
    beta, phi, freq = NEWMARK
    omega = 2 * math.pi * freq
    amp = peak_g * g / omega**2
    disp, T = shaking_slope(beta, phi, amp, freq, 2.0, kn=1e8)
    ref = newmark_displacement(beta, phi, lambda t: -amp * omega**2 * math.sin(omega * t), T)
    assert ref > 0.03, ref  # 40 mm / 352 mm: the shaking is strong enough to slide, every cycle
    assert disp == pytest.approx(ref, rel=0.05), (disp, ref)


# ------------------------------------------------------------------------------------------------
# the shipped scenes (Simulation path, as the CLI runs them)
# ------------------------------------------------------------------------------------------------


def test_wedge_scene_slides_at_the_hoek_bray_acceleration():
    # scenes/wedge_hoek_bray.toml: phi 21.0 deg, 0.48 deg below the limit; acceleration along the line of
    # intersection from the positions at 1, 1.5 and 2 s
    psi, da, db = WEDGE
    k, phi_lim = wedge_limit(psi, da, db)
    sim = rockwave.Simulation(load_scene(os.path.join(SCENES, "wedge_hoek_bray.toml")), device=DEVICE)
    line = rot_y(psi) @ [1.0, 0.0, 0.0]
    x = []
    for t in (1.0, 0.5, 0.5):
        sim.advance(t)
        x.append(float(sim.block_positions()[2] @ line))
    accel = (x[2] - 2 * x[1] + x[0]) / 0.25
    a = g * (math.sin(math.radians(psi)) - k * math.cos(math.radians(psi)) * math.tan(math.radians(21.0)))
    assert accel == pytest.approx(a, rel=0.03), (accel, a)


def test_newmark_scene_matches_the_rigid_plastic_displacement():
    # scenes/newmark_shaking_base.toml: the cube's displacement relative to the shaken slope after 2 s
    beta, phi, freq = NEWMARK
    omega = 2 * math.pi * freq
    amp = 0.4 * g / omega**2
    sim = rockwave.Simulation(load_scene(os.path.join(SCENES, "newmark_shaking_base.toml")), device=DEVICE)
    d = rot_y(beta) @ [1.0, 0.0, 0.0]
    x0 = sim.block_positions().copy()
    sim.advance(2.0)
    x = sim.block_positions()
    disp = float(((x[1] - x0[1]) - (x[0] - x0[0])) @ d)
    ref = newmark_displacement(beta, phi, lambda t: -amp * omega**2 * math.sin(omega * t), 2.0)
    assert disp == pytest.approx(ref, rel=0.05), (disp, ref)
