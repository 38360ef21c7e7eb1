"""The kernel-gradient correction (fluid.gradient_correction, part of fidelity 'waves'): its matrices make the
gradient of a linear field exact inside disordered water, its pair forces keep momentum, water at rest keeps
hydrostatic wall pressure, a dam break keeps its water inside the tank, and the standing wave loses less than with
the standard level. CPU, small."""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

import rockwave
from benchmarks import harness as H
from benchmarks.harness import standing_wave
from rockwave.build.options import fluid_parameters
from rockwave.sph.fluid import FluidSolver, build_fluid_model

from conftest import DEVICE


def _wendland_grad(rij: np.ndarray, H_: float, dim: int) -> np.ndarray:
    """grad_i W_ij of the Wendland C2 kernel of support H_ (h = H_/2), uncalibrated."""
    r = np.linalg.norm(rij, axis=-1)
    h = H_ / 2
    q = r / h
    a = 7 / (4 * math.pi * h * h) if dim == 2 else 21 / (16 * math.pi * h**3)
    dw = np.where(q < 2, a / h * (-5 * q * (1 - q / 2) ** 3), 0.0)
    safe = np.where(r > 0, r, 1.0)
    return (np.where(r > 0, dw, 0.0) / safe)[..., None] * rij


def _disordered_model(dim: int, correction: bool):
    """A block of water 12 spacings across (2D) / 8 (3D) jittered by 0.15 spacing, no walls, Wendland at 3 spacings."""
    rng = np.random.default_rng(3)
    s = 0.01
    n = 12 if dim == 2 else 8
    d = {"simulation": {"dimension": dim, "duration_s": 1.0},
         "fluid": {"spacing_m": s, "fidelity": "standard", "gradient_correction": correction, "eos": {"speed_of_sound_m_s": 20.0},
                   "regions": [{"box_min_m": [0.0] * dim, "box_max_m": [n * s] * dim}]},
         "tank": {"box_min_m": [-0.1] * dim, "box_max_m": [0.3] * dim}}
    fl = rockwave.parse_scene(d).fluid
    g = np.arange(n) * s + 0.5 * s
    grids = np.meshgrid(g, g, *([g] if dim == 3 else [np.zeros(1)]), indexing="ij")
    x = np.stack([a.ravel() for a in grids], axis=1)
    jitter = rng.normal(0.0, 0.15 * s, x.shape)
    if dim == 2:
        jitter[:, 2] = 0.0
    x = x + jitter
    v = rng.normal(0.0, 0.3, x.shape)
    if dim == 2:
        v[:, 2] = 0.0
    model = build_fluid_model(x, v, np.zeros((0, 3)), fluid_parameters(fl), dim, [0.0, 0.0, 0.0], DEVICE)
    return model, s, n


def _prepared(model):
    """State and solver with the lists, the summation density and (with the correction) the matrices L_i."""
    st = model.state()
    solver = FluidSolver(model)
    with wp.ScopedDevice(DEVICE):
        solver.build_cells(st)
        solver.build_neighbour_lists(st)
        solver.compute_density(st)
        solver.gradient_correction(st)
    return st, solver


@pytest.mark.parametrize("dim", [2, 3])
def test_corrected_gradient_of_a_linear_field_is_exact_inside_disordered_water(dim):
    """f = c . x sampled on jittered particles: sum_j V_j (f_j - f_i) L_i grad W_ij = c for every particle whose
    correction is full (Bonet & Lok 1999), to float32 precision; the plain gradient is off by several percent there."""
    model, s, n = _disordered_model(dim, True)
    st, solver = _prepared(model)
    X = st.x.numpy().astype(np.float64)
    rho = st.rho.numpy().astype(np.float64)
    L = solver.kgc.numpy().astype(np.float64)
    m = model.fluid_mass
    Hs = model.support_radius
    c = np.array([0.7, -1.3, 0.4 if dim == 3 else 0.0])
    f = X @ c
    rij = X[:, None, :] - X[None, :, :]
    gw = model.params.grad_scale * _wendland_grad(rij, Hs, dim)
    V = m / rho
    grad_plain = ((V[None, :] * (f[None, :] - f[:, None]))[..., None] * gw).sum(axis=1)
    grad_corr = np.einsum("iab,ib->ia", L, grad_plain)
    centre = np.full(3, 0.5 * n * s)
    inner = np.all(np.abs(X - centre)[:, :dim] < 0.5 * n * s - Hs, axis=1)  # full support of water
    assert inner.sum() >= 8
    full = inner & (np.abs(np.linalg.det(L[:, :dim, :dim]) - 1.0) > 1e-4)  # the correction acts there
    assert full.sum() >= 8
    err_corr = np.abs(grad_corr[inner] - c).max() / np.abs(c).max()
    err_plain = np.abs(grad_plain[inner] - c).max() / np.abs(c).max()
    assert err_corr < 2e-4, err_corr
    assert err_plain > 0.03, err_plain  # the jitter makes the plain gradient inexact: the test can tell


def test_corrected_pair_forces_conserve_momentum():
    """Random disordered water with random velocities: the total of all pair forces with the symmetric corrected
    gradient G_ij = (L_i + L_j)/2 grad W_ij is zero (G_ji = -G_ij), while the forces differ from the plain ones."""
    totals, accels = {}, {}
    for corr in (False, True):
        model, s, n = _disordered_model(3, corr)
        st, solver = _prepared(model)
        with wp.ScopedDevice(DEVICE):
            solver.pair_accelerations(st, lists_built=True)
        a = st.accel.numpy().astype(np.float64)  # gravity is zero here
        totals[corr] = (np.abs((model.fluid_mass * a).sum(axis=0)) / (model.fluid_mass * np.abs(a)).sum()).max()
        accels[corr] = a
    assert totals[True] < 1e-5, totals
    assert np.abs(accels[True] - accels[False]).max() > 0.01 * np.abs(accels[False]).max()


def _tank(dim: int, depth: float, width: float, spacing: float) -> dict:
    lo, hi = [0.0] * dim, [width] * (dim - 1) + [depth]
    gauges = [{"name": "corner", "kind": "pressure", "position_m": [0.0] * dim},
              {"name": "floor_mid", "kind": "pressure", "position_m": [0.5 * width] * (dim - 1) + [0.0]},
              {"name": "side_mid", "kind": "pressure", "position_m": [0.0] + [0.5 * width] * (dim - 2) + [0.5 * depth]}]
    return {"simulation": {"dimension": dim, "duration_s": 1.0},
            "fluid": {"spacing_m": spacing, "fidelity": "waves", "eos": {"speed_of_sound_m_s": 20.0},
                      "regions": [{"box_min_m": lo, "box_max_m": hi}]},
            "tank": {"box_min_m": lo, "box_max_m": [width] * (dim - 1) + [depth + 0.1]},
            "output": {"gauges": gauges}}


@pytest.mark.parametrize("dim", [2, 3])
def test_water_at_rest_with_the_waves_level_stays_hydrostatic_and_still(dim):
    """The tanks of tests/test_walls.py (2D: 0.3 m deep, 0.6 m wide, 0.5 s; 3D: a 0.12 m cube of water, 0.25 s;
    0.015 m spacing, c0 20 m/s) at fidelity 'waves': particle speeds stay below 0.1% of c0 (RMS), the surface
    stays put within 0.1 spacing, and the pressure gauges read rho0 g d within 5%. Measured here, corner /
    mid-floor / mid-wall: 2D +2.7 / +2.2 / +4.4% (standard +1.5 / +1.5 / +1.4%), 3D +0.1 / +2.6 / +3.0% (standard
    -0.7 / +1.3 / +2.4%); speeds 0.03% (2D) and 0.07% (3D) of c0. The fluid pairs next to a wall are corrected and
    the wall pairs are not, which shifts the balance there; the issue's 2% is met by the default level, not by this
    one (docs/notes.md 'Kernel-gradient correction')."""
    s = 0.015
    depth, width, t = (0.3, 0.6, 0.5) if dim == 2 else (0.12, 0.12, 0.25)
    up = dim - 1
    sim = rockwave.Simulation(rockwave.parse_scene(_tank(dim, depth, width, s)), device=DEVICE)
    assert sim.fluid.params.gradient_correction == 1
    z0 = sim.positions()[:, up]
    level0 = float(z0[z0 > z0.max() - 0.5 * s].mean())
    sim.advance(t)
    z = sim.positions()[:, up]
    level = float(z[z > z.max() - 0.5 * s].mean())
    assert abs(level - level0) < 0.1 * s, (level, level0)
    speed = np.linalg.norm(sim.velocities(), axis=1)
    assert np.sqrt(np.mean(speed ** 2)) < 1e-3 * 20.0
    top = level + 0.5 * s
    g = sim.gauges()
    for name, zg in (("corner", 0.0), ("floor_mid", 0.0), ("side_mid", 0.5 * depth)):
        ratio = g[name] / (1000.0 * 9.81 * (top - zg))
        assert abs(ratio - 1.0) < 0.05, (name, ratio)


def test_dam_break_with_the_correction_keeps_its_water_in_the_tank():
    """2D dam break (Martin & Moyce column, a/20) to 0.2 s with fidelity 'waves': no particle crosses the floor or the
    back wall. Correcting the fluid-wall pairs too (L_i grad W_ib) let the water's sliding velocity into the
    wall-normal density rate, and particles sank through the floor from 0.06 s (CPU, same case; 4-6% of the water
    left the tank on the H200); the front stays within 15% of the standard level's."""
    fronts = {}
    for level in ("standard", "waves"):
        sim = H.build("dam_break_2d", H.scene_dict("dam_break_2d", H.A_MM / 20, {"fluid.fidelity": level}, None,
                                                   H.FORMULATION_KEYS), DEVICE)
        sim.advance(0.2)
        x = sim.positions()
        assert x[:, 1].min() > 0.0 and x[:, 0].min() > 0.0, (level, x[:, 1].min(), x[:, 0].min())
        fronts[level] = x[:, 0].max()
    assert fronts["waves"] == pytest.approx(fronts["standard"], rel=0.15), fronts


def test_waves_level_damps_the_standing_wave_less_than_standard():
    """First sloshing mode (k d = 0.9, a = 0.02 m in 0.2 m, c0 12 m/s) at 12 particles per depth, 2 periods (the
    chart's case at a CPU size). Measured here: standard 3.8% per period (period -2.0%), waves 1.1% (-0.5%); on the
    H200 at 50 per depth 2.3% and 0.84%. The bound: waves decays at most 60% of standard's, and its period is within
    1% of linear theory (standard's is not at this size)."""
    out = {}
    for level in ("standard", "waves"):
        r = standing_wave(DEVICE, 12, {"fluid.fidelity": level}, periods=2, a=0.02, kh=0.9, mode=1, signal="projection")
        out[level] = r
    assert out["waves"]["decay_per_period"] < 0.6 * out["standard"]["decay_per_period"], \
        {k: v["decay_per_period"] for k, v in out.items()}
    assert abs(out["waves"]["period_error"]) < 0.01, out["waves"]["period_error"]
