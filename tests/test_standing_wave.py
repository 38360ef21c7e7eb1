"""Linear standing gravity wave in a tank of boundary particles (no blocks): the wave's numerical damping
depends on the kernel (docs/notes.md, 'Piston wave maker'). CPU, 2D, small."""

from __future__ import annotations

import pytest

from benchmarks.harness import standing_wave

from conftest import DEVICE


def standing_wave_amplitudes(variant: dict, layers: int = 16, periods: int = 3, a: float = 0.02) -> list[float]:
    """Water 0.2 m deep in a tank one wavelength long (k = 7.5 /m, kh = 1.5, the piston wave maker's wave),
    started at eta = 0 with the linear standing-wave velocity; the first-harmonic amplitude of each period
    (benchmarks/harness.py standing_wave, which the benchmark part ``chart`` runs in the first sloshing mode)."""
    return standing_wave(DEVICE, layers, variant, periods=periods, a=a, kh=1.5, mode=2)["amplitudes_m"]


def test_standing_wave_keeps_its_amplitude_with_wendland_kernel():
    """kh = 1.5, a = 0.02 m, 16 layers per depth, c0 12 m/s, no viscosity. With the Wendland C2 kernel at
    support 4 spacings (h = 2 s, ~50 neighbours) the amplitude in the second period is >= 75% of the first
    (measured 0.0201, 0.0173, 0.0172 m and 0.0202, 0.0168, 0.0158 m over three periods in two realisations).
    The default (Mueller poly6/spiky, support 2 s, ~12 neighbours) loses ~30% per period: 0.0188, 0.0121,
    0.0089 m (0.64 of the first period in the second), the damping that keeps the piston wave maker ~20% below
    linear theory (tests/test_coupling.py)."""
    amp = standing_wave_amplitudes({"fluid.kernel": "wendland", "fluid.support_radius_ratio": 4.0}, periods=2)
    assert 0.015 < amp[0] < 0.025, amp
    assert amp[1] >= 0.75 * amp[0], amp


def test_default_formulation_damps_the_standing_wave_far_less_than_draft():
    """The same wave (kh = 1.5, 16 layers per depth: a CPU size), three periods. The decay per period at this
    resolution is dominated by the kernel's smoothing of a wave 67 spacings long; measured on the CPU: default
    (fidelity 'standard', Wendland C2 at 3 spacings, Adami walls) 14% then 9% per period, 'draft' (the old
    default) 31% and 31%. The bound, at most 20% per period from the second period on and at most two thirds of
    draft's, holds with margin at this resolution and fails for the old formulation; the issue's 1% per period
    is a 50-per-depth figure, measured on the H100 (docs/validation.md 'Accuracy against cost': 2.35%)."""
    std = standing_wave_amplitudes({"fluid.fidelity": "standard"}, periods=3)
    old = standing_wave_amplitudes({"fluid.fidelity": "draft"}, periods=3)
    decay = lambda a: 1.0 - a[2] / a[1]  # noqa: E731 (the first period holds the start-up transient)
    assert decay(std) < 0.20, std
    assert decay(std) < (2.0 / 3.0) * decay(old), (std, old)


def test_particle_scale_band_holds_the_noise_not_the_flow():
    """The particle-scale kinetic energy (benchmarks/harness.py particle_scale_kinetic_energy: v minus its Shepard
    average over twice the support) of a lattice: a long sine flow (wavelength 40 spacings, averaged over 6
    spacings) puts < 1% of its kinetic energy there, a +-u checkerboard all of it (within 5%), and the two add."""
    import numpy as np

    from benchmarks.harness import particle_scale_kinetic_energy

    s, m, n = 0.01, 0.1, 80
    ij = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2)
    x = np.c_[(ij + 0.5) * s, np.zeros(len(ij))]
    rho = np.full(len(x), 1000.0)
    smooth = np.c_[np.sin(2 * np.pi * x[:, 0] / (40 * s)), np.zeros(len(x)), np.zeros(len(x))]
    check = np.c_[np.where(ij.sum(1) % 2 == 0, 0.1, -0.1), np.zeros(len(x)), np.zeros(len(x))]
    ke = lambda v: 0.5 * m * float(np.sum(v ** 2))  # noqa: E731
    band = lambda v: particle_scale_kinetic_energy(x, v, m, rho, 6 * s, 2)  # noqa: E731
    assert band(smooth) < 0.01 * ke(smooth)
    assert abs(band(check) / ke(check) - 1.0) < 0.05
    assert band(smooth + check) == pytest.approx(band(smooth) + band(check), rel=0.05)


def test_default_level_grows_no_particle_scale_noise_over_ten_periods():
    """Issue 38's target on particle-scale noise, at a CPU size: the standing wave (kh = 1.5, a = 0.02 m, 12 layers
    per depth, 600 particles) over 10 periods at the default level. The kinetic energy in the particle-scale band
    does not grow (fitted over periods 2-10; measured -10% per period, 14 and 16 layers -7%, 20 layers -3%) and
    stays a small share of the wave's (3.0% in the last period). Where it breaks: at 10 layers (the amplitude one
    spacing) the same run goes unstable after five periods, the band's energy growing 2.5x per period and the
    wave's kinetic energy 130x in ten (docs/notes.md 'Particle-scale noise')."""
    r = standing_wave(DEVICE, 12, {"fluid.fidelity": "standard"}, periods=10, a=0.02, kh=1.5, mode=2,
                      samples_per_period=20)
    assert r["finite"]
    assert r["noise_growth_per_period"] < 0.02, r["noise_growth_per_period"]
    assert r["noise_share_end"] < 0.06, r["noise_share_end"]
