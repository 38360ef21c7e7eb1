"""SPH physics: kernel normalisation, momentum conservation (against a brute-force reference),
hydrostatic pressure, 2D dam break against Martin & Moyce (1952)."""

import dataclasses
import math

import numpy as np
import pytest

import rockwave
from rockwave.build.options import fluid_parameters
from rockwave.build.sampling import box_lattice
from rockwave.sph.fluid import FluidSolver, build_fluid_model, calibrate_lattice, make_params

from conftest import DEVICE
from helpers import ROOT, martin_moyce, tank_2d, with_changes


def _fluid_section(kernel="muller", dim=3, **extra):
    d = tank_2d() if dim == 2 else with_changes(tank_2d(), **{"simulation.dimension": 3})
    d["fluid"]["kernel"] = kernel
    d["fluid"]["fidelity"] = "draft"  # support 2 spacings, Akinci walls: what these kernel tests were written for
    d["fluid"].update(extra)
    if dim == 3:
        d["fluid"]["regions"] = [{"box_min_m": [0, 0, 0], "box_max_m": [0.2, 0.2, 0.2]}]
        d["tank"] = {"box_min_m": [0, 0, 0], "box_max_m": [0.2, 0.2, 0.3]}
    return rockwave.parse_scene(d).fluid


@pytest.mark.parametrize("kernel", ["muller", "cubic_spline"])
@pytest.mark.parametrize("dim", [2, 3])
def test_kernel_normalisation(kernel, dim):
    """sum_j dx^d W(x_0 - x_j) -> 1 on a fine lattice (H = 6 dx): the 2D and 3D normalisations are right,
    and the Shepard sum sum_j m_j/rho_j W_ij = 1 holds inside a resting fluid at the working resolution."""
    fl = _fluid_section(kernel, dim)
    p = make_params(fluid_parameters(fl), dim, [0.0] * dim, 0)
    dx = p.H / 6.0
    mass, grad_scale = calibrate_lattice(p, dx, dim, DEVICE)
    w_sum = p.rest_density / mass  # = sum_j W_0j
    assert w_sum * dx**dim == pytest.approx(1.0, abs=0.01)
    # the lattice gradient moment also tends to 1 (scale correction within 1% at H = 6 dx)
    assert grad_scale == pytest.approx(1.0, abs=0.01)

    # Shepard sum inside a resting block of fluid at H = 2 dx (calibrated mass)
    spacing = fl["spacing_m"]
    x = box_lattice([0.0] * dim, [12 * spacing] * dim, spacing)
    x = np.concatenate([x, np.zeros((len(x), 3 - dim))], axis=1)
    fl = dict(fl, density="summation")
    model = build_fluid_model(x, np.zeros_like(x), np.zeros((0, 3)), fluid_parameters(fl), dim, [0.0] * dim, DEVICE)
    state = model.state()
    solver = FluidSolver(model)
    solver.build_grid(state)
    solver.compute_density(state)
    rho = state.rho.numpy()
    centre = np.argmin(np.linalg.norm(x - x.mean(axis=0), axis=1))
    shepard = float(np.sum(model.fluid_mass / rho[centre] * _w_numpy(kernel, dim, np.linalg.norm(x - x[centre], axis=1), model.support_radius)))
    assert shepard == pytest.approx(1.0, abs=1e-3)
    assert rho[centre] == pytest.approx(1000.0, rel=1e-4)


def _w_numpy(kernel, dim, r, H):
    """Reference kernels written from the formulas (Mueller 2003; Monaghan 1992), independent of the Warp code."""
    if kernel == "muller":
        c = 315.0 / (64 * math.pi * H**9) if dim == 3 else 4.0 / (math.pi * H**8)
        return np.where(r < H, c * (H * H - r * r) ** 3, 0.0)
    h = H / 2
    q = r / h
    s = 1 / (math.pi * h**3) if dim == 3 else 10 / (7 * math.pi * h**2)
    return s * np.where(q < 1, 1 - 1.5 * q**2 + 0.75 * q**3, np.where(q < 2, 0.25 * (2 - q) ** 3, 0.0))


def _grad_numpy(kernel, dim, rij, H):
    r = np.linalg.norm(rij, axis=-1)
    safe = np.where(r > 0, r, 1.0)
    if kernel == "muller":
        c = 45 / (math.pi * H**6) if dim == 3 else 30 / (math.pi * H**5)
        dw = np.where((r < H) & (r > 0), -c * (H - r) ** 2, 0.0)
    else:
        h = H / 2
        q = r / h
        s = (1 / (math.pi * h**3) if dim == 3 else 10 / (7 * math.pi * h**2)) / h
        dw = np.where(q < 1, s * (-3 * q + 2.25 * q**2), np.where(q < 2, -0.75 * s * (2 - q) ** 2, 0.0))
        dw = np.where(r > 0, dw, 0.0)
    return (dw / safe)[..., None] * rij


@pytest.mark.parametrize("form", ["momentum", "muller"])
@pytest.mark.parametrize("kernel", ["muller", "cubic_spline"])
def test_pair_forces_conserve_momentum_and_match_reference(form, kernel):
    """Random, disordered particles with random velocities: the total of all pair forces (pressure,
    Mueller viscosity, Monaghan viscosity) is zero, and every acceleration matches a brute-force
    numpy evaluation of the same formulas."""
    rng = np.random.default_rng(1)
    dim = 3
    fl = _fluid_section(kernel, dim, pressure_force=form, density="summation", clamp_negative_pressure=False,
                        viscosity={"artificial_alpha": 0.2, "laplacian_pa_s": 0.5, "xsph_epsilon": 0.0})
    spacing = fl["spacing_m"]
    x = box_lattice([0, 0, 0], [6 * spacing] * 3, spacing) + rng.normal(0, 0.15 * spacing, (216, 3))
    v = rng.normal(0, 0.5, x.shape)
    model = build_fluid_model(x, v, np.zeros((0, 3)), fluid_parameters(fl), dim, [0.0, 0.0, 0.0], DEVICE)
    s = model.state()
    solver = FluidSolver(model)
    solver.build_grid(s)
    solver.compute_density(s)
    solver.pair_accelerations(s)
    a = s.accel.numpy().astype(np.float64)
    m = model.fluid_mass
    total = (m * a).sum(axis=0)
    scale = (m * np.abs(a)).sum()
    assert np.all(np.abs(total) < 1e-5 * scale), f"net internal force {total} (scale {scale})"

    # brute force
    X = s.x.numpy().astype(np.float64)
    H = model.support_radius
    rij = X[:, None, :] - X[None, :, :]
    r = np.linalg.norm(rij, axis=2)
    rho = m * _w_numpy(kernel, dim, r, H).sum(axis=1)
    p = model.params
    pr = p.eos_b * ((rho / 1000.0) ** 7 - 1)
    gw = model.params.grad_scale * _grad_numpy(kernel, dim, rij, H)
    if form == "momentum":
        f = (pr / rho**2)[:, None] + (pr / rho**2)[None, :]
    else:
        f = (pr[:, None] + pr[None, :]) / (2 * rho[:, None] * rho[None, :])
    ref = -(m * f[..., None] * gw).sum(axis=1)
    vij = v[:, None, :] - v[None, :, :]
    vr = (vij * rij).sum(axis=2)
    hs = H / 2
    mu_ij = np.where(vr < 0, hs * vr / (r * r + 0.01 * hs * hs), 0.0)
    Pi = -0.2 * p.sound_speed * mu_ij / (0.5 * (rho[:, None] + rho[None, :]))
    ref -= (m * Pi[..., None] * gw).sum(axis=1)
    lap = np.where(r < H, (45 / (math.pi * H**6)) * (H - r), 0.0)
    ref += (0.5 * m / (rho[:, None] * rho[None, :]) * lap)[..., None].__mul__(-vij).sum(axis=1)
    assert np.allclose(rho, s.rho.numpy(), rtol=1e-4)
    assert np.max(np.abs(a - ref)) < 2e-4 * np.max(np.abs(ref))


def test_hydrostatic_tank_2d():
    """A 2D tank 0.2 m deep (20 particles) settles to p = rho0 g (H - z): the fitted pressure gradient
    below the surface layer is rho0 g within 7%, the pressure at mid-depth within 10% of rho0 g H/2
    (the column settles by ~1.5% of its depth, included through the measured surface), no particle
    leaves the tank and the water stays at rest: RMS speed over the second second below 0.1% of c0 (the issue's
    water-at-rest target; the default's start is packed at its hydrostatic density, so there is little to decay:
    measured 5e-4 m/s, 2.5e-5 c0; the uniform start's energy decayed by 5x). The profile is averaged over
    1.0-2.0 s, two periods of the first sloshing mode. Measured: gradient +4% (muller kernel, before the standard
    level), the discretisation error of WCSPH with 20 particles per depth."""
    sim = rockwave.Simulation(rockwave.parse_scene(tank_2d()), device=DEVICE)
    ke0 = []
    xs, ps = [], []
    for k in range(40):
        sim.advance(0.05)
        ke0.append(sim.kinetic_energy())
        if k >= 20:
            xs.append(sim.positions())
            ps.append(sim.pressures())
    x, p = np.concatenate(xs), np.concatenate(ps)
    surface = np.percentile(sim.positions()[:, 1], 99.5) + 0.5 * sim.fluid.spacing
    inner = (x[:, 1] > 0.03) & (x[:, 1] < surface - 0.03)
    slope = -np.polyfit(x[inner, 1], p[inner], 1)[0]
    assert slope == pytest.approx(1000 * 9.81, rel=0.07)
    mid = np.abs(x[:, 1] - surface / 2) < 0.01
    assert p[mid].mean() == pytest.approx(1000 * 9.81 * surface / 2, rel=0.10)
    final = sim.positions()
    assert np.all((final[:, 0] > 0) & (final[:, 0] < 0.2) & (final[:, 1] > 0)), "a particle left the tank"
    mass = sim.fluid.n_fluid * sim.fluid.params.fluid_mass
    rms = np.sqrt(2.0 * np.asarray(ke0[-20:]) / mass)
    assert rms.max() < 1e-3 * 20.0, f"the water did not stay at rest: RMS speed {rms}"


def test_dam_break_2d_front_against_martin_moyce():
    """n^2 = 2 column (a = 0.05715 m) at a/14 spacing: the surge front Z = x/a at T = t sqrt(2g/a) in
    [1.2, 3.0] stays within 20% of Martin & Moyce's measurements, and within 12% from T = 1.95 on.
    SPH with no gate and no floor friction runs ahead, most at the start, where the experiment's
    gate was still lifting. Measured here: +17% at T = 1.19, +9% to +11% for T >= 1.98."""
    a = 0.05715
    d = rockwave.load_scene(ROOT / "scenes" / "dam_break_2d.toml").raw
    d = with_changes(d, **{"fluid.spacing_m": a / 14})
    sim = rockwave.Simulation(rockwave.parse_scene(d, "dam_break_2d.toml", ROOT / "scenes"), device=DEVICE)
    exp = martin_moyce("front_n2_2")
    exp = exp[(exp[:, 0] >= 1.2) & (exp[:, 0] <= 3.0)]
    errs = []
    for T, Z in exp:
        t = T / math.sqrt(2 * 9.81 / a)
        sim.advance(t - sim.time)
        front = sim.positions()[:, 0].max() / a
        errs.append((front - Z) / Z)
    errs = np.array(errs)
    assert np.all(np.abs(errs) < 0.20), f"front errors {np.round(errs, 3)}"
    assert np.all(np.abs(errs[exp[:, 0] >= 1.95]) < 0.12), f"front errors {np.round(errs, 3)}"


def test_xsph_matches_reference():
    """XSPH correction dv_i = eps sum_j m_j / rho_ij (v_j - v_i) W_ij against a numpy evaluation."""
    rng = np.random.default_rng(3)
    fl = _fluid_section("cubic_spline", 3, density="summation", viscosity={"artificial_alpha": 0.0, "xsph_epsilon": 0.05})
    spacing = fl["spacing_m"]
    x = box_lattice([0, 0, 0], [5 * spacing] * 3, spacing) + rng.normal(0, 0.1 * spacing, (125, 3))
    v = rng.normal(0, 0.5, x.shape)
    model = build_fluid_model(x, v, np.zeros((0, 3)), fluid_parameters(fl), 3, [0.0, 0.0, 0.0], DEVICE)
    s = model.state()
    solver = FluidSolver(model)
    solver.build_grid(s)
    solver.compute_density(s)
    solver.pair_accelerations(s)
    X = s.x.numpy().astype(np.float64)
    rho = s.rho.numpy().astype(np.float64)
    r = np.linalg.norm(X[:, None] - X[None], axis=2)
    W = _w_numpy("cubic_spline", 3, r, model.support_radius)
    np.fill_diagonal(W, 0.0)
    rbar = 0.5 * (rho[:, None] + rho[None, :])
    ref = 0.05 * ((model.fluid_mass / rbar * W)[..., None] * (v[None, :, :] - v[:, None, :])).sum(axis=1)
    got = s.xsph_dv.numpy()
    assert np.max(np.abs(got - ref)) < 1e-4 * np.max(np.abs(ref)) + 1e-7
    # XSPH conserves momentum: the corrections of all particles sum to ~zero (weighted by mass)
    assert np.linalg.norm(got.sum(axis=0)) < 1e-4 * np.abs(got).sum()


def test_mesh_fluid_region_and_mesh_tank(tmp_path):
    """A fluid region and a tank given as closed meshes (through trimesh, inside test by Warp's winding
    number): the particle count matches the region's volume / spacing^3 within the lattice's surface
    error, every particle is inside the ball, and boundary particles surround the water."""
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    ball.apply_translation([0.15, 0.15, 0.15])
    ball.export(tmp_path / "ball.stl")
    tank = trimesh.creation.box((0.3, 0.3, 0.3))
    tank.apply_translation([0.15, 0.15, 0.15])
    tank.export(tmp_path / "tank.stl")
    d = {"simulation": {"duration_s": 0.01}, "fluid": {"spacing_m": 0.01, "eos": {"speed_of_sound_m_s": 10.0},
                                                        "regions": [{"mesh": "ball.stl"}]},
         "tank": {"mesh": "tank.stl"}}
    sim = rockwave.Simulation(rockwave.parse_scene(d, tmp_path / "m.toml", tmp_path), device=DEVICE)
    x = sim.positions()
    assert len(x) == pytest.approx(ball.volume / 0.01**3, rel=0.05)
    assert np.all(np.linalg.norm(x - 0.15, axis=1) < 0.1)
    b = sim.boundary_positions()
    assert b.min() < 0 and b.max() > 0.3
    outside = np.any((b < 0) | (b > 0.3), axis=1)
    assert outside.all(), "boundary particles of a container lie outside its inner surface"
    sim.advance(0.01)
    assert np.isfinite(sim.positions()).all()


def test_neighbour_lists_hold_particles_at_a_fine_wall():
    """Walls at half the fluid spacing (the Ghost SPH report's dam breaks, basic SPH here): a particle at a
    wall has half its support at 4x the lattice density. The list capacity counts that
    (FluidSolver.list_capacity), so no list overflows into the cell-scan passes: before, 117 of 3,600
    particles did every step. The capacity stays the fluid lattice's for walls at the fluid spacing."""
    d = rockwave.load_scene(ROOT / "scenes" / "ghost_dam_break_case1.toml").raw
    d = with_changes(d, **{"fluid.method": "basic", "fluid.spacing_m": 0.03})
    sim = rockwave.Simulation(rockwave.parse_scene(d, "case1", ROOT / "scenes"), device=DEVICE)
    assert sim.fluid.boundary_spacing == pytest.approx(0.5 * sim.fluid.spacing)
    for _ in range(5):
        sim.step()
    fs = sim.fluid_solver
    counts = fs.list_counts.numpy()
    assert fs.list_overflow() == 0
    fluid_lattice_only = dataclasses.replace(sim.fluid, boundary_spacing=0.0)
    assert counts.max() > FluidSolver.list_capacity(fluid_lattice_only, fs.neighbour_skin), "the wall lists would have fit anyway"
    d2 = with_changes(rockwave.load_scene(ROOT / "scenes" / "dam_break_2d.toml").raw, **{"fluid.spacing_m": 0.02, "fluid.fidelity": "draft"})
    sim2 = rockwave.Simulation(rockwave.parse_scene(d2, "dam_break_2d", ROOT / "scenes"), device=DEVICE)
    assert sim2.fluid_solver.neighbour_cap < fs.neighbour_cap


def test_step_stability_limit_of_the_lattice_analysis_and_the_default_courant_number():
    """benchmarks/courant.py: the semi-implicit Euler step is linearly stable on the lattice below C_max =
    2 / (h max|G(k)|) (dt = C h / c0); for Wendland C2 at 3 spacings in 2D C_max = 1.76. A tank at rest (walls,
    gravity, a 1e-4 m/s velocity noise) stepped at a fixed C = 1.4 stays quiet for 400 steps; at C = 2.0 it
    blows up. The default Courant number (simulation.cfl_number, 0.6) is at most 0.35 C_max for every kernel and
    support the schema offers (a margin of 2.9 on the lattice, ~2.5 against the tank's 1.5-1.7; at 0.6 and 0.8 the
    chart's cases read as at 0.4: docs/notes.md 'Courant number 0.6')."""
    from benchmarks.courant import lattice_acoustic_limit
    from rockwave.scene.format import SCHEMA

    c_max = lattice_acoustic_limit("wendland", 3.0, 2)
    assert 1.6 < c_max < 1.9, c_max
    speeds = {}
    for C in (1.4, 2.0):
        d = {"simulation": {"dimension": 2, "duration_s": 1.0},
             "fluid": {"spacing_m": 0.01, "fidelity": "standard", "eos": {"speed_of_sound_m_s": 10.0},
                       "viscosity": {"artificial_alpha": 0.0}, "regions": [{"box_min_m": [0, 0], "box_max_m": [0.2, 0.1]}]},
             "tank": {"box_min_m": [0, 0], "box_max_m": [0.2, 0.2]}}
        sim = rockwave.Simulation(rockwave.parse_scene(d), device=DEVICE)
        v0 = sim.state.v.numpy()
        v0[: sim.n_fluid, :2] += np.random.default_rng(0).normal(0.0, 1e-4, (sim.n_fluid, 2))
        sim.state.v.assign(v0)
        dt = C * 0.5 * sim.fluid.support_radius / 10.0
        for _ in range(400):
            sim.step(dt)
        v = sim.velocities()
        speeds[C] = float(np.abs(v).max()) if np.isfinite(v).all() else math.inf
    assert speeds[1.4] < 0.05 and speeds[2.0] > 1.0, speeds
    default = SCHEMA["simulation"].children["cfl_number"].default
    for kernel, ratio in (("muller", 2.0), ("cubic_spline", 3.0), ("wendland", 2.5), ("wendland", 3.0), ("wendland", 4.0)):
        assert default <= 0.35 * lattice_acoustic_limit(kernel, ratio, 2), (kernel, ratio)


def test_density_floor_forgets_expansion_and_changes_no_energy():
    """fluid.density_floor (kernels/sph/fluid.py continuity_floor): a 2D block of water spreading in zero gravity
    (u = k x from its centre) keeps rho >= rho0 with the floor and falls below rho0 without; negative pressure
    is clipped either way, so both spread ballistically with the same kinetic energy. Turned back (v -> -v), the
    floored block pushes as soon as it is compressed; without the floor it is compressed back through its whole
    deficit first and reads no pressure half-way."""
    out = {}
    for floor in (True, False):
        d = {"simulation": {"dimension": 2, "duration_s": 1.0},
             "gravity": {"acceleration_m_s2": [0.0, 0.0]},
             "fluid": {"spacing_m": 0.01, "fidelity": "standard", "density_floor": floor,
                       "eos": {"speed_of_sound_m_s": 10.0}, "viscosity": {"artificial_alpha": 0.0},
                       "regions": [{"box_min_m": [0.4, 0.4], "box_max_m": [0.6, 0.6]}]},
             "tank": {"box_min_m": [0.0, 0.0], "box_max_m": [1.0, 1.0]}}
        sim = rockwave.Simulation(rockwave.parse_scene(d), device=DEVICE)
        n = sim.n_fluid
        x = sim.positions()
        v = sim.state.v.numpy()
        v[:n, :2] = 2.0 * (x[:n, :2] - 0.5)  # u = k x, k = 2 /s: 0.2 m/s at the block's edge
        sim.state.v.assign(v)
        dt = 2.0e-4
        for _ in range(100):  # 0.02 s: the block's span grows 4%
            sim.step(dt)
        rho = sim.densities()
        ke = 0.5 * sim.fluid.fluid_mass * float((sim.velocities() ** 2).sum())
        v = sim.state.v.numpy()
        v[:n] = -v[:n]
        sim.state.v.assign(v)
        for _ in range(50):  # half way back
            sim.step(dt)
        out[floor] = (float(rho.min()), ke, float(sim.state.pressure.numpy()[:n].max()))
    (rmin_f, ke_f, pmax_f), (rmin_n, ke_n, pmax_n) = out[True], out[False]
    assert rmin_f >= 1000.0 and rmin_n < 990.0, out
    assert abs(ke_f / ke_n - 1.0) < 1e-4, out
    assert pmax_f > 100.0 and pmax_n == 0.0, out


def test_density_floor_refused_where_it_cannot_act():
    """fluid.density_floor with Ghost SPH, summation density or unclipped pressure is a SceneError naming the key."""
    base = {"simulation": {"dimension": 2, "duration_s": 1.0},
            "fluid": {"spacing_m": 0.02, "density_floor": True, "eos": {"speed_of_sound_m_s": 10.0}, "regions": [{"box_min_m": [0, 0], "box_max_m": [0.2, 0.1]}]},
            "tank": {"box_min_m": [0, 0], "box_max_m": [0.2, 0.2]}}
    assert rockwave.parse_scene(base).fluid["density_floor"] is True
    for key, value, text in (("method", "ghost", "fluid.method = 'ghost'"), ("density", "summation", "summation"),
                             ("clamp_negative_pressure", False, "clamp_negative_pressure = false")):
        bad = {**base, "fluid": {**base["fluid"], key: value}}
        with pytest.raises(rockwave.SceneError, match=r"fluid\.density_floor") as e:
            rockwave.parse_scene(bad)
        assert text in str(e.value)


def test_device_bytes_count_every_fluid_array_once():
    """FluidSolver.device_bytes (benchmarks/fluid_bytes.py's per-level table, issue 40): the lists are the slots
    and counts exactly (4 B x (capacity + 1) per fluid particle), a buffer made after the first step (the shifting's,
    at delta_plus) is counted, and the parts add up to the total."""
    out = {}
    for level in ("standard", "delta_plus"):
        sim = rockwave.Simulation(rockwave.parse_scene(tank_2d(fidelity=level)), device=DEVICE)
        sim.step_many(2)
        s = sim.fluid_solver
        b = s.device_bytes(sim.state)
        nf = sim.fluid.n_fluid
        assert b["lists"] == 4 * (s.neighbour_cap + 1) * nf
        assert b["total"] == sum(v for k, v in b.items() if k not in ("total", "per_particle"))
        assert b["per_particle"] == pytest.approx(b["total"] / nf)
        assert b["state"] >= nf * (3 * 12 + 3 * 4)  # at least x, v, accel and rho, pressure, drho_dt of the fluid
        out[level] = b
    # delta_plus keeps the shifting's four per-particle buffers (lambda, two gradients, the shift: 40 B) more
    assert out["delta_plus"]["solver"] - out["standard"]["solver"] >= 40 * nf
