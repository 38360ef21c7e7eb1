"""Antuono et al.'s (2010) renormalised density diffusion and the shift's Taylor correction (issue 38;
kernels/sph/diffusion.py renormalised_gradients, density_diffusion_rate_renormalised; kernels/sph/shifting.py
apply_shift_corrected). CPU, small."""

from __future__ import annotations

import numpy as np
import warp as wp

import rockwave
from rockwave.base.solver import TimeStep
from rockwave.build.options import fluid_parameters
from rockwave.kernels.sph import diffusion
from rockwave.sph.fluid import FluidSolver, build_fluid_model

from conftest import DEVICE

RENORM = {"fidelity": "delta_plus", "density_diffusion_form": "renormalised", "shifting_correction": "taylor"}


def _block(n=14, s=0.01, jitter=0.05, seed=1, gravity=(0.0, -9.81, 0.0), **fluid):
    """A free square of water (every side a free surface, four corners), jittered, no walls."""
    d = {"simulation": {"dimension": 2, "duration_s": 1.0},
         "fluid": {"spacing_m": s, "eos": {"speed_of_sound_m_s": 20.0}, **RENORM, **fluid,
                   "regions": [{"box_min_m": [0.0, 0.0], "box_max_m": [n * s, n * s]}]},
         "tank": {"box_min_m": [-0.1, -0.1], "box_max_m": [0.3, 0.3]}}
    fl = rockwave.parse_scene(d).fluid
    g = np.arange(n) * s + 0.5 * s
    gx, gy = np.meshgrid(g, g, indexing="ij")
    x = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    rng = np.random.default_rng(seed)
    x[:, :2] += rng.normal(0.0, jitter * s, (gx.size, 2))
    model = build_fluid_model(x, np.zeros_like(x), np.zeros((0, 3)), fluid_parameters(fl), 2, list(gravity), DEVICE)
    return model, x, rng


def _rate(solver, model, st):
    with wp.ScopedDevice(DEVICE):
        solver.renormalised_gradients(st)
        out = wp.zeros(model.n_fluid, dtype=float)
        wp.launch(diffusion.density_diffusion_rate_renormalised, model.n_fluid,
                  inputs=[solver.list_counts, solver.list_entries, st.x, st.rho, solver.density_gradients, model.params,
                          0.1], outputs=[out])
    return out.numpy()


def test_renormalised_diffusion_is_exact_for_any_linear_field_and_conserves_and_damps_noise():
    """A jittered free block (surface on four sides and four corners: truncated supports everywhere at its edge),
    density rho0 + G.x with G = (30, -50) kg/m^4 (not the hydrostatic direction) and velocity V x: the renormalised
    gradients are G within 0.01 kg/m^4 (measured 3e-3, float32 round-off of |G| = 58) and V within 1e-4 /s, the renormalised diffusion rate is
    zero up to round-off (max |rate| 0.03 kg/m^3/s, against 104 for the hydrostatic form, which removes only the
    hydrostatic gradient) at every particle, the surface and corners included. With noise added: sum_i V_i rate_i
    = 0 (the pair terms are antisymmetric; to 1e-6 of sum |rate|) and the rate opposes the noise (correlation
    below -0.8; measured -0.88)."""
    model, x, rng = _block(gravity=(0.0, 0.0, 0.0))
    st, solver = model.state(), FluidSolver(model)
    G = np.array([30.0, -50.0, 0.0])
    # the corners' supports are a quarter full (lambda ~ 0.25): their renormalisation weight is partial
    s, side = model.spacing, 14 * model.spacing
    edge = np.minimum(x[:, :2], side - x[:, :2]) < 2.5 * s
    full = ~(edge[:, 0] & edge[:, 1])
    V = np.array([[0.5, 1.0, 0.0], [-2.0, 0.3, 0.0], [0.0, 0.0, 0.0]])
    rho = 1000.0 + x @ G
    st.rho.assign(rho.astype(np.float32))
    st.v.assign((x @ V.T).astype(np.float32))
    with wp.ScopedDevice(DEVICE):
        solver.build_lists(st)
    r = _rate(solver, model, st)
    gr, gv = solver.density_gradients.numpy(), solver.velocity_gradients.numpy()
    assert np.abs(gr[full, :2] - G[:2]).max() < 0.01, np.abs(gr[full, :2] - G[:2]).max()
    assert np.abs(gv[full, :2, :2] - V[:2, :2]).max() < 1e-4, np.abs(gv[full, :2, :2] - V[:2, :2]).max()
    assert np.abs(r[full]).max() < 0.5, np.abs(r[full]).max()
    with wp.ScopedDevice(DEVICE):
        plain = wp.zeros(model.n_fluid, dtype=float)
        wp.launch(diffusion.density_diffusion_rate, model.n_fluid,
                  inputs=[solver.list_counts, solver.list_entries, st.x, st.rho, model.particle_mass,
                          wp.zeros(1, dtype=wp.vec2), 0, model.params, 0.1], outputs=[plain])
    assert np.abs(plain.numpy()[full]).max() > 100 * np.abs(r[full]).max()
    noise = rng.normal(0.0, 1.0, rho.size)
    st.rho.assign((rho + noise).astype(np.float32))
    r = _rate(solver, model, st)
    assert abs(r.sum()) < 1e-6 * np.abs(r).sum(), (r.sum(), np.abs(r).sum())
    assert np.corrcoef(r, noise)[0, 1] < -0.8, np.corrcoef(r, noise)[0, 1]


def test_taylor_shift_keeps_mass_and_momentum_in_free_flight():
    """The free block without gravity, random velocities, renormalised diffusion and shifting with the Taylor
    correction (K = 1, ten times the level's, so the shifts are large): particle count and mass unchanged; the
    velocity correction v += <grad v>^L dr is not a pair term, so momentum is not kept to round-off: after 30 steps
    its change is below 1e-3 of sum m |v| (measured 2e-6)."""
    model, x, rng = _block(gravity=(0.0, 0.0, 0.0), particle_shifting=1.0)
    assert model.shift_taylor and model.renormalised_diffusion
    st, solver = model.state(), FluidSolver(model)
    st.v.assign(np.c_[rng.normal(0.0, 0.3, (len(x), 2)), np.zeros(len(x))].astype(np.float32))
    dt = wp.array([2e-4], dtype=float, device=DEVICE)
    p0, scale = st.v.numpy().sum(axis=0), np.abs(st.v.numpy()).sum()
    with wp.ScopedDevice(DEVICE):
        for _ in range(30):
            solver.step(st, TimeStep(dt=2e-4, dt_array=dt, time=0.0))
    assert np.abs(solver.shift_displacements.numpy()).max() > 0.0
    dp = np.abs(st.v.numpy().sum(axis=0) - p0).max()
    assert dp < 1e-3 * scale, (dp, scale)
    assert st.x.numpy().shape[0] == len(x) and np.isfinite(st.x.numpy()).all()
