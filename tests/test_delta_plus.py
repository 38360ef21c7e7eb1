"""The `delta_plus` level (issue 38): the kernel-gradient correction, delta-SPH diffusion of the pressure's density
with the walls in the sum (kernels/sph/diffusion.py), light particle shifting with a free-surface band
(kernels/sph/shifting.py), alpha 0. Water at rest stays hydrostatic, the diffusion of the pressure's density is
antisymmetric and takes nothing from water below rho0, the shift conserves mass and never moves water across its free
surface or into a wall, momentum is kept, the standing wave at a CPU size keeps its amplitude within 1% a period
(`standard` loses 3.75%), and a 2D dam break into a wall keeps its water out of the wall as `standard` does (the
level's first form let the run-up creep a spacing into it). CPU, small."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import rockwave
from benchmarks import harness as H
from benchmarks.harness import standing_wave
from rockwave.base.solver import TimeStep
from rockwave.build.options import fluid_parameters
from rockwave.sph.fluid import FluidSolver, build_fluid_model

from conftest import DEVICE


def _tank(depth=0.3, width=0.6, spacing=0.015, **fluid):
    gauges = [{"name": "corner", "kind": "pressure", "position_m": [0.0, 0.0]},
              {"name": "floor_mid", "kind": "pressure", "position_m": [0.5 * width, 0.0]},
              {"name": "side_mid", "kind": "pressure", "position_m": [0.0, 0.5 * depth]}]
    d = {"simulation": {"dimension": 2, "duration_s": 1.0},
         "fluid": {"spacing_m": spacing, "fidelity": "delta_plus", "eos": {"speed_of_sound_m_s": 20.0},
                   "regions": [{"box_min_m": [0.0, 0.0], "box_max_m": [width, depth]}]},
         "tank": {"box_min_m": [0.0, 0.0], "box_max_m": [width, depth + 0.1]},
         "output": {"gauges": gauges}}
    d["fluid"].update(fluid)
    return d


def test_level_sets_diffusion_shifting_and_no_viscosity_and_ghost_refuses_shifting():
    """The level fills its keys (an expert key given wins); Ghost SPH takes the level without the shifting and the
    diffusion, and shifting set by hand with Ghost SPH is a SceneError naming the key."""
    f = rockwave.parse_scene(_tank()).fluid
    assert (f.kernel, f.support_radius_ratio, f.boundary) == ("wendland", 3.0, "adami")
    assert f.density_diffusion == 0.1 and f.particle_shifting > 0 and f.viscosity.artificial_alpha == 0.0
    assert f.gradient_correction and not f.density_floor and f.density_diffusion_form == "pressure"
    assert rockwave.parse_scene(_tank(particle_shifting=0.0)).fluid.particle_shifting == 0.0
    ghost = _tank(method="ghost")
    g = rockwave.parse_scene(ghost).fluid
    assert g.particle_shifting == 0.0 and g.density_diffusion == 0.0 and not g.gradient_correction
    with pytest.raises(rockwave.SceneError) as e:
        rockwave.parse_scene(_tank(method="ghost", particle_shifting=0.1))
    assert any(k == "fluid.particle_shifting" for k, _ in e.value.errors)


def test_water_at_rest_with_diffusion_and_shifting_stays_hydrostatic():
    """The 2D tank of tests/test_walls.py (0.3 m deep, 0.6 m wide, 0.015 m, c0 20 m/s, 0.5 s) at `delta_plus`: the
    gauges at the corner, mid-floor and mid-wall read rho0 g d within 2% (benchmarks/delta_plus.py, the same tank
    averaged over the last 0.05 s: +0.52 / +0.62 / +0.26%; standard +0.47 / +0.69 / +0.11%), speeds stay
    below 0.1% of c0 (RMS), the surface stays within 0.1 spacing: the diffusion's hydrostatic part is taken out
    (Fourtakas et al. 2019) and the shifting, scaled by the flow's Mach number, leaves still water still."""
    s, depth = 0.015, 0.3
    sim = rockwave.Simulation(rockwave.parse_scene(_tank()), device=DEVICE)
    assert sim.fluid.particle_shifting > 0 and sim.fluid.density_diffusion > 0
    z0 = sim.positions()[:, 1]
    level0 = float(z0[z0 > z0.max() - 0.5 * s].mean())
    sim.advance(0.5)
    z = sim.positions()[:, 1]
    level = float(z[z > z.max() - 0.5 * s].mean())
    assert abs(level - level0) < 0.1 * s, (level, level0)
    speed = np.linalg.norm(sim.velocities(), axis=1)
    assert np.sqrt(np.mean(speed ** 2)) < 1e-3 * 20.0
    g = sim.gauges()
    top = level + 0.5 * s
    for name, zg in (("corner", 0.0), ("floor_mid", 0.0), ("side_mid", 0.5 * depth)):
        ratio = g[name] / (1000.0 * 9.81 * (top - zg))
        assert abs(ratio - 1.0) < 0.02, (name, ratio)


def _sloshing(K=1.0):
    """A 2D tank, water 0.2 m deep (0.01 m), moving with a sloshing velocity field u = 0.3 sin(pi x/L) (and the
    matching w), jittered by 0.1 spacing: the shifts of one step (K large so that they are visible)."""
    d = _tank(depth=0.2, width=0.4, spacing=0.01, particle_shifting=K)
    sim = rockwave.Simulation(rockwave.parse_scene(d), device=DEVICE)
    rng = np.random.default_rng(5)
    nf = sim.n_fluid
    x = sim.state.x.numpy()
    x[:nf, :2] += rng.normal(0.0, 0.1 * 0.01, (nf, 2))
    v = sim.state.v.numpy()
    v[:nf, 0] = 0.3 * np.cos(np.pi * x[:nf, 0] / 0.4)
    sim.state.x.assign(x)
    sim.state.v.assign(v)
    return sim


def test_shifting_keeps_mass_moves_nothing_across_the_free_surface_or_into_a_wall():
    """One step's shifts in jittered sloshing water (K = 1, larger than the level's): the particles of the top layers
    (within one kernel support of the surface) move only along the surface (vertical shift < 2% of a spacing,
    the jittered surface's tilt, and zero on average), the deeper ones are shifted in full (vertical shifts 3x larger), no shift points a particle at the walls closer than the first fluid
    row stood, and the particle count and mass are unchanged after 0.1 s of the sloshing, with no particle past a
    wall or above the water's initial top by more than a spacing."""
    s = 0.01
    sim = _sloshing()
    solver = sim.fluid_solver
    with wp.ScopedDevice(DEVICE):
        solver.build_lists(sim.state)
        solver.particle_shift(sim.state)
    x = sim.state.x.numpy()[: sim.n_fluid]
    dr = solver.shift_displacements.numpy()
    top = x[:, 1].max()
    band = x[:, 1] > top - sim.fluid.support_radius - 0.5 * s
    deep = x[:, 1] < top - 2 * sim.fluid.support_radius
    # along the local surface: a jittered surface tilts its normal, so the vertical part is small, not zero, and it
    # averages out (nothing lifts the water); inside the shift acts in full
    assert np.abs(dr[band, 1]).max() < 0.02 * s, np.abs(dr[band, 1]).max() / s
    assert abs(dr[band, 1].mean()) < 1e-3 * s, dr[band, 1].mean() / s
    assert np.abs(dr[deep, 1]).max() > 3 * np.abs(dr[band, 1]).max(), (np.abs(dr[deep, 1]).max(), np.abs(dr[band, 1]).max())
    nx = x + dr
    assert nx[:, 0].min() > 0.0 and nx[:, 0].max() < 0.4 and nx[:, 1].min() > 0.0
    n0, m0 = sim.n_fluid, sim.fluid.fluid_mass * sim.n_fluid
    sim.advance(0.1)
    x = sim.positions()
    assert sim.n_fluid == n0 and sim.fluid.fluid_mass * sim.n_fluid == m0
    assert x[:, 0].min() > 0.0 and x[:, 0].max() < 0.4 and x[:, 1].min() > 0.0
    assert x[:, 1].max() < top + 0.02 + s  # the sloshing lifts the surface ~1 cm; the shift adds nothing across it


def test_momentum_is_kept_with_diffusion_and_shifting():
    """Water in free flight (no gravity, no walls), jittered, random velocities, `delta_plus`: after 30 steps the
    total momentum is unchanged to 1e-5 of sum m |v| (the diffusion changes densities only, the shift positions
    only, and the pair forces stay antisymmetric)."""
    rng = np.random.default_rng(3)
    s, n = 0.01, 12
    d = {"simulation": {"dimension": 2, "duration_s": 1.0},
         "fluid": {"spacing_m": s, "fidelity": "delta_plus", "eos": {"speed_of_sound_m_s": 20.0},
                   "regions": [{"box_min_m": [0.0, 0.0], "box_max_m": [n * s, n * s]}]},
         "tank": {"box_min_m": [-0.1, -0.1], "box_max_m": [0.3, 0.3]}}
    fl = rockwave.parse_scene(d).fluid
    g = np.arange(n) * s + 0.5 * s
    gx, gy = np.meshgrid(g, g, indexing="ij")
    x = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1) + np.r_[rng.normal(0, 0.1 * s, (gx.size, 2)).T,
                                                                             [np.zeros(gx.size)]].T
    v = np.c_[rng.normal(0.0, 0.3, (gx.size, 2)), np.zeros(gx.size)]
    model = build_fluid_model(x, v, np.zeros((0, 3)), fluid_parameters(fl), 2, [0.0, 0.0, 0.0], DEVICE)
    assert model.particle_shifting > 0 and model.density_diffusion > 0
    st = model.state()
    solver = FluidSolver(model)

    dt = wp.array([2e-4], dtype=float, device=DEVICE)
    p0 = st.v.numpy().sum(axis=0)
    scale = np.abs(st.v.numpy()).sum()
    with wp.ScopedDevice(DEVICE):
        for _ in range(30):
            solver.step(st, TimeStep(dt=2e-4, dt_array=dt, time=0.0))
    p1 = st.v.numpy().sum(axis=0)
    assert np.abs(p1 - p0).max() < 1e-5 * scale, (p1 - p0, scale)
    assert np.abs(solver.shift_displacements.numpy()).max() > 0.0


def test_pressure_density_diffusion_is_antisymmetric_and_takes_nothing_from_water_below_rho0():
    """The diffusion rate of the form 'pressure' (kernels/sph/diffusion.py) in a jittered free block (no walls, no
    gravity) with densities rho0 (1.01 + 2% noise), a third of them below rho0: sum_i V_i rate_i = 0 (the pair
    terms are antisymmetric; to 1e-5 of sum |rate|), a particle below rho0 never loses (the form 'hydrostatic'
    takes from some), the noise above rho0 is damped (the rate opposes it, correlation below -0.5), and inside a
    patch of expanded water the particles whose support holds only expanded water get nothing."""
    from rockwave.kernels.sph import diffusion

    rng = np.random.default_rng(7)
    s, n = 0.01, 14
    d = {"simulation": {"dimension": 2, "duration_s": 1.0},
         "fluid": {"spacing_m": s, "fidelity": "delta_plus", "eos": {"speed_of_sound_m_s": 20.0},
                   "regions": [{"box_min_m": [0.0, 0.0], "box_max_m": [n * s, n * s]}]},
         "tank": {"box_min_m": [-0.1, -0.1], "box_max_m": [0.3, 0.3]}}
    fl = rockwave.parse_scene(d).fluid
    g = np.arange(n) * s + 0.5 * s
    gx, gy = np.meshgrid(g, g, indexing="ij")
    x = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    x[:, :2] += rng.normal(0.0, 0.05 * s, (gx.size, 2))
    model = build_fluid_model(x, np.zeros_like(x), np.zeros((0, 3)), fluid_parameters(fl), 2, [0.0, 0.0, 0.0], DEVICE)
    st, solver = model.state(), FluidSolver(model)
    rho = 1000.0 * (1.0 + 0.02 * rng.normal(0.0, 1.0, len(x)) + 0.01)
    st.rho.assign(rho.astype(np.float32))
    rates = {}
    with wp.ScopedDevice(DEVICE):
        solver.build_lists(st)
        for form in (1, 0):
            out = wp.zeros(model.n_fluid, dtype=float)
            wp.launch(diffusion.density_diffusion_rate, model.n_fluid,
                      inputs=[solver.list_counts, solver.list_entries, st.x, st.rho, model.particle_mass,
                              wp.zeros(1, dtype=wp.vec2), 0, model.params, 0.1, form, 0, wp.zeros(1, dtype=wp.vec3)],
                      outputs=[out])
            rates[form] = out.numpy()
    r = rates[1]
    assert abs(r.sum()) < 1e-5 * np.abs(r).sum(), (r.sum(), np.abs(r).sum())
    below = rho < 1000.0
    assert below.sum() > 0.2 * len(rho)
    assert r[below].min() >= 0.0 and rates[0][below].min() < 0.0
    above = ~below
    assert np.corrcoef(r[above], rho[above])[0, 1] < -0.5
    # a patch of expanded water (radius 5 spacings, every density below rho0): the particles more than H inside it
    # see only expanded neighbours and get nothing
    dist = np.linalg.norm(x[:, :2] - 0.5 * n * s, axis=1)
    patch = dist < 0.05
    rho2 = rho.copy()
    rho2[patch] = 1000.0 * (0.99 - 0.01 * rng.random(patch.sum()))
    st.rho.assign(rho2.astype(np.float32))
    with wp.ScopedDevice(DEVICE):
        out = wp.zeros(model.n_fluid, dtype=float)
        wp.launch(diffusion.density_diffusion_rate, model.n_fluid,
                  inputs=[solver.list_counts, solver.list_entries, st.x, st.rho, model.particle_mass,
                          wp.zeros(1, dtype=wp.vec2), 0, model.params, 0.1, 1, 0, wp.zeros(1, dtype=wp.vec3)],
                  outputs=[out])
    inner = dist < 0.05 - model.support_radius - 0.1 * s
    assert inner.sum() >= 3 and np.abs(out.numpy()[inner]).max() == 0.0
    assert out.numpy()[patch & ~inner].min() >= 0.0


def test_delta_plus_keeps_the_standing_wave():
    """First sloshing mode (k d = 0.9, a = 0.02 m in 0.2 m, c0 12 m/s) at 12 particles per depth, 2 periods, the
    chart's case at a CPU size. Measured here (CPU, 2026-11-29): standard 3.75% per period (period -1.55%), the level
    as first shipped (no correction, K = 0.1) 2.1%, `waves` 1.8%, the level 0.22% (+0.09%; without the shift 0.06%,
    with K = 0.1 1.1%: the shift damps in proportion to K). The bound, 1% per period (the issue's 50-per-depth
    target) with the period within 0.5% of linear theory, standard fails and the level meets."""
    out = {}
    for level in ("standard", "delta_plus"):
        out[level] = standing_wave(DEVICE, 12, {"fluid.fidelity": level}, periods=2, a=0.02, kh=0.9, mode=1,
                                   signal="projection")
    decay = {k: v["decay_per_period"] for k, v in out.items()}
    assert decay["standard"] > 0.01 > abs(decay["delta_plus"]), decay
    assert abs(out["delta_plus"]["period_error"]) < 0.005, out["delta_plus"]["period_error"]


def test_dam_break_into_a_wall_keeps_its_water_out_of_the_wall():
    """2D dam break (Martin & Moyce column, a/20) in a tank 0.35 m long, through the impact on the end wall (0.23 s)
    and the run-up to 0.45 s at `delta_plus`: no particle more than half a spacing past a wall's face and every
    density positive. Measured to 0.6 s (benchmarks/delta_plus.py): the level 0.31 spacing, standard 0.27; the
    continuity density diffused instead of the pressure's ('hydrostatic') 0.62-1.01 (the run-up sheet at 680-980
    kg/m^3 drained the compression of the water pressed into the wall); fluid-only diffusion (the first version)
    put particles 16 spacings into the wall and drove densities to -350 kg/m^3, the blow-up after SPHERIC Test 2's
    impact (kernels/sph/diffusion.py, docs/notes.md 'delta-plus')."""
    dx = H.A_MM / 20
    d = H.scene_dict("dam_break_2d", dx, {"fluid.fidelity": "delta_plus"}, None, H.FORMULATION_KEYS)
    d["tank"]["box_max_m"] = [0.35, 0.4]
    sim = H.build("dam_break_2d", d, DEVICE)
    sim.advance(0.45)
    x, rho = sim.positions(), sim.densities()
    assert x[:, 0].min() > -0.5 * dx and x[:, 0].max() < 0.35 + 0.5 * dx and x[:, 1].min() > -0.5 * dx
    assert rho.min() > 0.0, rho.min()


def test_renormalised_diffusion_vanishes_for_a_linear_density_and_stays_antisymmetric():
    """Antuono et al.'s (2010) renormalised term (fluid.density_diffusion_renormalised, kernels/sph/diffusion.py) in
    the jittered free block of the test above (no walls, no gravity): for a linear density (above rho0, any direction)
    the renormalised gradient is exact and the rate vanishes (to 1e-3 of the plain term's) where the support is full
    and also along the block's straight edges away from its corners (a cut support: there the plain term is a
    one-sided flux, 640-790 kg/m^3/s here; the renormalised one 0.03); with noise added the pair terms stay antisymmetric (sum_i V_i rate_i = 0)
    and the rate opposes the noise. The key without a diffusion to change is a SceneError naming it."""
    from rockwave.kernels.sph import diffusion

    rng = np.random.default_rng(7)
    s, n = 0.01, 14
    d = {"simulation": {"dimension": 2, "duration_s": 1.0},
         "fluid": {"spacing_m": s, "fidelity": "delta_plus", "density_diffusion_renormalised": True,
                   "eos": {"speed_of_sound_m_s": 20.0},
                   "regions": [{"box_min_m": [0.0, 0.0], "box_max_m": [n * s, n * s]}]},
         "tank": {"box_min_m": [-0.1, -0.1], "box_max_m": [0.3, 0.3]}}
    fl = rockwave.parse_scene(d).fluid
    assert fl.density_diffusion_renormalised
    assert not rockwave.parse_scene(_tank()).fluid.density_diffusion_renormalised  # off at the level
    with pytest.raises(rockwave.SceneError) as e:  # no diffusion to change: an error naming the key
        rockwave.parse_scene(_tank(fidelity="standard", density_diffusion_renormalised=True))
    assert any(k == "fluid.density_diffusion_renormalised" for k, _ in e.value.errors)
    g = np.arange(n) * s + 0.5 * s
    gx, gy = np.meshgrid(g, g, indexing="ij")
    x = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    x[:, :2] += rng.normal(0.0, 0.05 * s, (gx.size, 2))
    model = build_fluid_model(x, np.zeros_like(x), np.zeros((0, 3)), fluid_parameters(fl), 2, [0.0, 0.0, 0.0], DEVICE)
    st, solver = model.state(), FluidSolver(model)

    def rates(rho):
        st.rho.assign(rho.astype(np.float32))
        out = {}
        with wp.ScopedDevice(DEVICE):
            grad = wp.zeros(model.n_fluid, dtype=wp.vec3)
            wp.launch(diffusion.density_gradient_renormalised, model.n_fluid,
                      inputs=[solver.list_counts, solver.list_entries, st.x, st.rho, model.particle_mass,
                              wp.zeros(1, dtype=wp.vec2), 0, model.params, 1], outputs=[grad])
            for renorm in (0, 1):
                o = wp.zeros(model.n_fluid, dtype=float)
                wp.launch(diffusion.density_diffusion_rate, model.n_fluid,
                          inputs=[solver.list_counts, solver.list_entries, st.x, st.rho, model.particle_mass,
                                  wp.zeros(1, dtype=wp.vec2), 0, model.params, 0.1, 1, renorm, grad], outputs=[o])
                out[renorm] = o.numpy()
        return out, grad.numpy()

    with wp.ScopedDevice(DEVICE):
        solver.build_lists(st)
    x = st.x.numpy().astype(float)  # the lists' order
    H_ = model.support_radius
    full = np.all((x[:, :2] > H_) & (x[:, :2] < n * s - H_), axis=1)
    # the outer row along the block's edges, away from the corners (a corner's matrix is blended off)
    row = (x[:, :2] < s) | (x[:, :2] > (n - 1) * s)
    mid = (x[:, :2] > 2 * H_) & (x[:, :2] < n * s - 2 * H_)
    edge = (row[:, 0] & mid[:, 1]) | (row[:, 1] & mid[:, 0])
    for direction in ((0.6, -0.8), (1.0, 0.0), (0.0, 1.0)):
        rho = 1040.0 + 300.0 * (direction[0] * x[:, 0] + direction[1] * x[:, 1])
        out, grad = rates(rho)
        assert full.sum() >= 9
        assert np.abs(grad[full, :2] - 300.0 * np.asarray(direction)).max() < 0.01 * 300.0
        assert np.abs(out[1][full]).max() < 1e-3 * np.abs(out[0][full]).max(), (out[1][full], out[0][full])
        assert edge.sum() >= 8 and np.abs(out[1][edge]).max() < 1e-3 * np.abs(out[0][edge]).max()
    rho = 1010.0 * (1.0 + 0.01 * rng.normal(0.0, 1.0, len(x)))
    rho = np.maximum(rho, 1000.5)
    r = rates(rho)[0][1]
    assert abs(r.sum()) < 1e-5 * np.abs(r).sum(), (r.sum(), np.abs(r).sum())
    assert np.corrcoef(r, rho)[0, 1] < -0.5
