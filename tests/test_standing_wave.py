"""Linear standing gravity wave in a tank of boundary particles (no blocks): the wave's numerical damping
depends on the kernel (docs/notes.md, 'Piston wave maker'). CPU, 2D, small."""

from __future__ import annotations

import math

import numpy as np

import rockwave

from conftest import DEVICE


def standing_wave_amplitudes(fluid: dict, layers: int = 16, periods: int = 3, a: float = 0.02) -> list[float]:
    """Water 0.2 m deep in a tank one wavelength long (k = 7.484 /m, kh = 1.5, the piston wave maker's
    wave), started at eta = 0 with the linear standing-wave velocity of eta = a cos(kx) sin(wt):
    u = -a w cosh(k(z+h))/sinh(kh) sin(kx), w_z = a w sinh(k(z+h))/sinh(kh) cos(kx). Returns the
    first-harmonic amplitude of (eta at the wall x = 0) - (eta mid-tank) over 2, one fit per period, where
    eta is the water depth from the particle volumes m/rho_i in a 0.1 m wide column, minus h."""
    h, s, g = 0.2, 0.2 / layers, 9.81
    k = 7.48394
    om = math.sqrt(g * k * math.tanh(k * h))
    T, L = 2 * math.pi / om, 2 * math.pi / k
    d = {"simulation": {"dimension": 2, "duration_s": 10.0},
         "fluid": {"spacing_m": s, "eos": {"speed_of_sound_m_s": 12.0},
                   "regions": [{"box_min_m": [0.0, 0.0], "box_max_m": [L, h]}], **fluid},
         "tank": {"box_min_m": [0.0, 0.0], "box_max_m": [L, 0.5]}}
    sim = rockwave.Simulation(rockwave.parse_scene(d), device=DEVICE)
    nf = sim.n_fluid
    x = sim.positions()
    v = sim.state.v.numpy().copy()
    z = x[:, 1]
    v[:nf, 0] = -a * om * np.cosh(k * z) / np.sinh(k * h) * np.sin(k * x[:, 0])
    v[:nf, 1] = a * om * np.sinh(k * z) / np.sinh(k * h) * np.cos(k * x[:, 0])
    sim.state.v.assign(v)
    m, w = sim.fluid.fluid_mass, 0.1
    ts, eta = [], []
    while sim.time < periods * T - 1e-9:
        sim.advance(T / 40)
        xx, rho = sim.positions(), sim.densities()
        wall, mid = xx[:, 0] < w, np.abs(xx[:, 0] - 0.5 * L) < 0.5 * w
        eta.append((np.sum(m / rho[wall]) - np.sum(m / rho[mid])) / w)
        ts.append(sim.time)
    ts, eta = np.asarray(ts), np.asarray(eta)
    out = []
    for p in range(periods):
        sl = (ts > p * T + 1e-9) & (ts <= (p + 1) * T + 1e-9)
        A = np.c_[np.ones(sl.sum()), np.cos(om * ts[sl]), np.sin(om * ts[sl])]
        c = np.linalg.lstsq(A, eta[sl], rcond=None)[0]
        out.append(math.hypot(c[1], c[2]) / 2)
    return out


def test_standing_wave_keeps_its_amplitude_with_wendland_kernel():
    """kh = 1.5, a = 0.02 m, 16 layers per depth, c0 12 m/s, no viscosity. With the Wendland C2 kernel at
    support 4 spacings (h = 2 s, ~50 neighbours) the amplitude in the second period is >= 75% of the first
    (measured 0.0201, 0.0173, 0.0172 m and 0.0202, 0.0168, 0.0158 m over three periods in two realisations).
    The default (Mueller poly6/spiky, support 2 s, ~12 neighbours) loses ~30% per period: 0.0188, 0.0121,
    0.0089 m (0.64 of the first period in the second), the damping that keeps the piston wave maker ~20% below
    linear theory (tests/test_coupling.py)."""
    amp = standing_wave_amplitudes({"kernel": "wendland", "support_radius_ratio": 4.0}, periods=2)
    assert 0.015 < amp[0] < 0.025, amp
    assert amp[1] >= 0.75 * amp[0], amp
