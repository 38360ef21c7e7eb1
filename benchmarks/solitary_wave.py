"""A solitary wave made by a piston and run along a flat flume (issue 38: waves that keep their height over many
depths, and no growth of particle-scale noise).

2D: water ``depth`` d deep, a kinematic piston at x = 0 that moves as Goring (1978) prescribes for a first-order
(Boussinesq) solitary wave of height H,

    eta(x, t) = H sech^2(k (x - c t - x0)),   k = sqrt(3 H / (4 d^3)),   c = sqrt(g (d + H)),
    dX/dt = c eta(X, t) / (d + eta(X, t))       (the piston's speed is the wave's depth-mean velocity),

x0 = 3.8 / k ahead of the piston's start (the stroke sqrt(16 H d / 3) is done in ~7.6 / (k c) s); the flume runs
``travel`` depths past the wave's generation to the end wall of a ``[tank]`` (Adami walls). Water levels are read from the particles'
volumes spread over two spacings either side (``water_level``) at gauges 5, 10, 15, ... depths from the piston (the height read, the water
depth less the still level read at the start, every ``read`` s). Reported: each gauge's peak against H, the celerity from the peaks' arrival times
against c, and the kinetic energy in the particle-scale band (benchmarks/harness.py
particle_scale_kinetic_energy) with its growth per unit time after the wave has formed, and its share of the
wave's kinetic energy; the drift of the water's mean density and the energy budget's largest growth beyond the
piston's work (rockwave/sim/energy.py), as a share of the scene's releasable energy.

A solitary wave of permanent form in an inviscid fluid keeps H and c (to first order in H/d; measured waves
lose ~1-2% of H per 10 depths to the flume's boundary layers at lab scale, which an inviscid run does not have).

    python -m benchmarks.solitary_wave --layers 8 --travel 15                # CPU, ~2 min
    python -m benchmarks.solitary_wave --device cuda:0 --layers 20 40 --travel 30

writes benchmarks/results/<date>-<device>-solitary_wave.json and .md.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from benchmarks.harness import noise_growth_per_period, particle_scale_kinetic_energy

G = 9.81


def goring_piston(depth: float, height: float, dt: float = 1e-3) -> tuple[np.ndarray, np.ndarray, float]:
    """(times, piston x, x0): Goring's trajectory of a piston starting at x = 0, integrated with RK4."""
    k = math.sqrt(3.0 * height / (4.0 * depth ** 3))
    c = math.sqrt(G * (depth + height))
    x0 = 3.8 / k
    t_end = 2.0 * x0 / c

    def speed(t, X):
        eta = height / math.cosh(k * (X - c * t + x0)) ** 2
        return c * eta / (depth + eta)

    ts, xs = [0.0], [0.0]
    t, X = 0.0, 0.0
    while t < t_end - 1e-12:
        h = min(dt, t_end - t)
        k1 = speed(t, X)
        k2 = speed(t + h / 2, X + h * k1 / 2)
        k3 = speed(t + h / 2, X + h * k2 / 2)
        k4 = speed(t + h, X + h * k3)
        X += h * (k1 + 2 * k2 + 2 * k3 + k4) / 6
        t += h
        ts.append(t)
        xs.append(X)
    return np.asarray(ts), np.asarray(xs), x0


def scene_dict(layers: int, depth: float = 0.1, height_ratio: float = 0.2, travel: float = 15.0, c0: float | None = None,
               variant: dict | None = None) -> tuple[dict, dict]:
    """The scene (a dict for rockwave.scene.format.parse_scene) and the wave's facts."""
    from benchmarks.harness import set_path

    H = height_ratio * depth
    ts, xs, x0 = goring_piston(depth, H)
    stroke = float(xs[-1])
    length = stroke + x0 + travel * depth + 2.0 * depth  # the wave formed ~x0 ahead of the stroke's end, then travel
    c = math.sqrt(G * (depth + H))
    c0 = c0 or 10.0 * c
    s = depth / layers
    step = max(1, len(ts) // 400)  # ~400 table rows
    tt, xx = ts[::step].tolist(), xs[::step].tolist()
    if tt[-1] != ts[-1]:
        tt.append(float(ts[-1]))
        xx.append(float(xs[-1]))
    wall = 0.1 * depth + 3 * s
    d = {"simulation": {"dimension": 2, "duration_s": 10.0},
         "fluid": {"spacing_m": s, "eos": {"speed_of_sound_m_s": c0},
                   "regions": [{"box_min_m": [0.0, 0.0], "box_max_m": [length, depth]}]},
         "tank": {"box_min_m": [-wall - s, 0.0], "box_max_m": [length, 3.0 * depth]},
         "blocks": [
             {"name": "piston", "shape": "box", "size_m": [wall, 2.5 * depth, 0.1],
              "position_m": [-wall / 2, 1.25 * depth + 0.02 * s, 0.0], "kind": "kinematic",
              "motion": {"type": "table", "times_s": tt, "displacements_m": [[x, 0.0, 0.0] for x in xx]}}]}
    for key, v in (variant or {}).items():
        set_path(d, key, v)
    facts = {"depth_m": depth, "height_m": H, "k_per_m": math.sqrt(3 * H / (4 * depth ** 3)), "celerity_m_s": c,
             "stroke_m": stroke, "generation_s": float(ts[-1]), "x0_m": x0, "length_m": length, "spacing_m": s,
             "layers": layers, "c0_m_s": c0}
    return d, facts


def water_level(x: np.ndarray, vol: np.ndarray, at: float, half: float) -> float:
    """The water depth at x = ``at``: the particles' volumes m/rho spread over x with a hat of half-width ``half``
    (weights (1 - |x - at| / half) / half, which integrate to 1: a lattice of spacing s <= half reads its depth
    without the jumps of a sharp-edged column)."""
    w = np.clip(1.0 - np.abs(x - at) / half, 0.0, None) / half
    return float(np.sum(w * vol))


def run(device: str, layers: int, depth: float = 0.1, height_ratio: float = 0.2, travel: float = 15.0,
        read: float = 0.01, variant: dict | None = None) -> dict:
    import rockwave

    d, f = scene_dict(layers, depth, height_ratio, travel, variant=variant)
    sim = rockwave.Simulation(rockwave.parse_scene(d), device=device)
    m, s, c = sim.fluid.fluid_mass, f["spacing_m"], f["celerity_m_s"]
    band = 2.0 * sim.fluid.params.H
    gauges = np.arange(5.0, travel + f["x0_m"] / depth + 1e-9, 5.0) * depth + f["stroke_m"]
    gauges = gauges[gauges < f["length_m"] - 3 * depth]
    t_end = f["generation_s"] + (gauges[-1] - f["stroke_m"] + 2 * depth) / c
    ts, levels, noise, kin = [], [], [], []
    vol0 = m / sim.densities()
    budget = sim.energy
    budget.measure()
    rho_mean0, budget_growth = float(sim.densities().mean()), []
    rest = [water_level(sim.positions()[:, 0], vol0, g, 2.0 * s) for g in gauges]  # the still level (packed start)
    t0 = time.perf_counter()
    while sim.time < t_end - 1e-9:
        sim.advance(min(read, t_end - sim.time))
        x, rho, v = sim.positions(), sim.densities(), sim.velocities()
        if not (np.isfinite(x).all() and np.isfinite(v).all()):
            break
        vol = m / rho
        levels.append([water_level(x[:, 0], vol, g, 2.0 * s) - r0 for g, r0 in zip(gauges, rest)])
        noise.append(particle_scale_kinetic_energy(x, v, m, rho, band, 2))
        kin.append(0.5 * m * float(np.sum(v ** 2)))
        budget_growth.append(float(budget.measure(x, v, rho)["growth_j"]))
        ts.append(sim.time)
    wall = time.perf_counter() - t0
    ts, levels, noise, kin = np.asarray(ts), np.asarray(levels), np.asarray(noise), np.asarray(kin)
    peaks = levels.max(axis=0) if len(ts) else np.full(len(gauges), np.nan)
    arrivals = np.array([ts[int(np.argmax(levels[:, i]))] for i in range(len(gauges))]) if len(ts) else np.full(len(gauges), np.nan)
    cel = float(np.polyfit(arrivals, gauges, 1)[0]) if len(gauges) >= 2 else math.nan
    formed = ts >= f["generation_s"]
    unit = depth / c  # time to run one depth
    growth = noise_growth_per_period(ts[formed] - f["generation_s"], noise[formed], 10.0 * unit, skip=0.0)
    return dict(f, particles=sim.n_fluid, t=ts.tolist(), levels_m=levels.tolist(), noise_j=noise.tolist(),
                kinetic_j=kin.tolist(), gauges_m=gauges.tolist(),
                gauge_depths=((gauges - f["stroke_m"]) / depth).tolist(), peaks_m=peaks.tolist(),
                height_ratio_at_gauges=(peaks / f["height_m"]).tolist(), arrivals_s=arrivals.tolist(),
                celerity_measured_m_s=cel, celerity_error=cel / c - 1.0,
                noise_growth_per_10_depths=growth,
                noise_share_end=float(noise[-10:].mean() / max(kin[-10:].mean(), 1e-30)) if len(ts) else math.nan,
                mean_density_drift=float(sim.densities().mean()) / rho_mean0 - 1.0,
                energy_growth_j=float(max(budget_growth)) if budget_growth else math.nan,
                energy_growth_fraction=float(max(budget_growth)) / budget.scale if budget_growth and budget.scale else math.nan,
                simulated_s=float(sim.time), steps=sim.steps, wall_s=wall, finite=bool(len(ts) and ts[-1] >= t_end - 1e-6),
                fluid=variant or {})


def _pct(v, fmt: str) -> str:
    return "-" if v is None or not math.isfinite(v) else format(v, fmt)


def markdown(rows: list[dict], head: str) -> str:
    out = [head, "", "| level | layers | particles | H/d | peak / H at 5, 10, ... depths | celerity error | "
           "particle-scale KE growth per 10 depths | its share of the KE at the end | mean density drift | energy growth beyond "
           "the piston's work / releasable | wall s |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r.get('level', '-')} | {r['layers']} | {r['particles']} | {r['height_m'] / r['depth_m']:.2f} | "
                   + ", ".join(f"{x:.3f}" for x in r["height_ratio_at_gauges"])
                   + f" | {r['celerity_error']:+.2%} | {r['noise_growth_per_10_depths']:+.1%} | {r['noise_share_end']:.1%} | "
                   f"{_pct(r.get('mean_density_drift'), '+.2%')} | {_pct(r.get('energy_growth_fraction'), '.2%')} | "
                   f"{r['wall_s']:.0f} |")
    return "\n".join(out) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.solitary_wave", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--layers", type=int, nargs="+", default=[8])
    ap.add_argument("--levels", nargs="+", default=["standard"], help="fluid.fidelity levels, side by side")
    ap.add_argument("--height", type=float, default=0.2, help="H / d")
    ap.add_argument("--travel", type=float, default=15.0, help="depths run after the wave has formed")
    ap.add_argument("--depth", type=float, default=0.1)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    import warp as wp

    from benchmarks.common import RESULTS, commit, device_name, write_record

    wp.config.quiet = True
    rows = []
    for level in a.levels:
        for layers in a.layers:
            r = run(a.device, layers, a.depth, a.height, a.travel, variant={"fluid.fidelity": level})
            r["level"] = level
            rows.append(r)
            print(markdown([r], "").splitlines()[-1], flush=True)
    date = time.strftime("%Y-%m-%d")
    stem = a.out or str(RESULTS / f"{date}-{a.device.replace(':', '')}-solitary_wave")
    head = (f"# Solitary wave, H/d {a.height:g}, {a.travel:g} depths (issue 38): {device_name(a.device)}, commit {commit()}, "
            f"{date}")
    write_record(stem, rows, head, markdown, a.device, a)


if __name__ == "__main__":
    main()
