"""Part ``wave_maker``: the piston wave maker against linear wavemaker theory as the resolution grows
(issue 4, full size of tests/test_coupling.py::test_piston_wave_maker_linear_theory):
scenes/wave_maker_small.toml (2D, h = 0.2 m, S = 0.03 m, f = 1.297 Hz, kh = 1.5) at 16, 32, 64 ... particle
layers per depth; first-harmonic wave height at gauge_1 (0.35 m) and gauge_2 (0.7 m) over the two periods
ending at 2.6 s, against H/S = 2 (cosh 2kh - 1)/(sinh 2kh + 2kh); class "within 10%" or "outside 10%" at gauge_1.
"""

from __future__ import annotations

import math

import numpy as np

from benchmarks.common import ROOT, log

CONFIG = {"quick": dict(wave_layers=[16]), "full": dict(wave_layers=[16, 32, 64, 128])}


def first_harmonic_height(t, y, omega):
    """2 |c1| of the least-squares fit y = a + b cos(wt) + c sin(wt) (the test's measure)."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    A = np.stack([np.ones_like(t), np.cos(omega * t), np.sin(omega * t)], axis=1)
    c = np.linalg.lstsq(A, y, rcond=None)[0]
    return 2.0 * math.hypot(c[1], c[2])


def theory(h=0.2, S=0.03, f=1.2970):
    om = 2 * math.pi * f
    k = om * om / 9.81
    for _ in range(50):
        k = om * om / (9.81 * math.tanh(k * h))
    return 2 * (math.cosh(2 * k * h) - 1) / (math.sinh(2 * k * h) + 2 * k * h) * S, om


def piston_dict(layers: int, variant: dict | None = None, strip: tuple = ()) -> dict:
    """Scene dict of scenes/wave_maker_small.toml at ``layers`` particles per depth: ``strip`` [fluid] keys
    removed, then a variant's dotted changes (benchmarks/harness.py set_path)."""
    import copy

    import rockwave
    from benchmarks.harness import set_path

    d = copy.deepcopy(rockwave.load_scene(ROOT / "scenes" / "wave_maker_small.toml").raw)
    for k in strip:
        d["fluid"].pop(k, None)
    d["fluid"]["spacing_m"] = 0.2 / layers
    for k, v in (variant or {}).items():
        set_path(d, k, v)
    return d


def piston(device, layers, t_end=2.6, variant: dict | None = None, strip: tuple = ()):
    """One wave-maker run: first-harmonic heights at the gauges over the two periods ending at t_end; wall_s =
    seconds spent advancing (synchronised, gauge reads excluded), steps, particles."""
    import rockwave
    from benchmarks.harness import Clock, fluid_settings

    scene = rockwave.parse_scene(piston_dict(layers, variant, strip), "wave_maker_small.toml", ROOT / "scenes")
    H_th, om = theory()
    sim = rockwave.Simulation(scene, device=device)
    clock = Clock(sim.device)
    steps0 = sim.steps
    ts, g1, g2 = [], [], []
    while sim.time < t_end - 1e-9:
        clock.run(lambda: sim.advance(min(0.02, t_end - sim.time)))
        g = sim.gauges()
        ts.append(sim.time)
        g1.append(g["gauge_1"])
        g2.append(g["gauge_2"])
    wall = clock.seconds
    ts = np.asarray(ts)
    w = ts > t_end - 2.0 * 2 * math.pi / om - 1e-6
    h1 = first_harmonic_height(ts[w], np.asarray(g1)[w], om)
    h2 = first_harmonic_height(ts[w], np.asarray(g2)[w], om)
    return dict(layers=layers, spacing_m=0.2 / layers, particles=sim.n_fluid, steps=sim.steps - steps0, wall_s=wall,
                simulated_s=sim.time, wall_per_sim_s=wall / sim.time, fluid=fluid_settings(sim), H_theory_m=H_th,
                H_gauge1_m=h1, H_gauge2_m=h2, error_gauge1=h1 / H_th - 1, error_gauge2=h2 / H_th - 1)


def run(dev: str, cfg: dict) -> dict:
    rows = []
    for n in cfg["wave_layers"]:
        r = piston(dev, n)
        r["class"] = "within 10%" if abs(r["error_gauge1"]) <= 0.10 else "outside 10%"
        rows.append(r)
        log(f"  wave maker {n:4d} layers/depth n={r['particles']:7d} gauge_1 {r['error_gauge1']:+.1%} gauge_2 "
            f"{r['error_gauge2']:+.1%} ({r['wall_s']:.0f} s)  {r['class']}")
    return {"piston": rows}
