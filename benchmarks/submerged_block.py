"""A block resting under still water on a slope, a little above and below its friction limit (issue 36).

2D: a 0.1 m square rock (2600 kg/m3, 0.1 m deep) rests in contact, with no gap, on a fixed slab dipping ``alpha``
(20 deg) inside a [tank] filled with water to 0.35 m (the rock's top ~0.09 m below the surface), friction angle
alpha + margin on both, k_n per contact point ``kn`` (1e6 N/m; k_s the default k_n / 2.5), the rock an Adami wall to
the water (coupling.block_walls).

The limit: a fully submerged block on a plane in hydrostatic water carries the water's pressure on every face,
whose resultant is the buoyancy rho_w g V, straight up; the load on the contact is the buoyant weight
(rho_s - rho_w) g V, vertical, so its shear / normal ratio is tan(alpha) as in air and the limit is
tan(phi) = tan(alpha) whatever the buoyancy. Where the water does not reach the contact face (a closed joint: no
uplift under the base), the normal force is larger by the base's pressure times its area and the block is more
stable: the margin alpha + 0.5 deg is then a lower bound on the real one.

Reported per run, along the dip (down-slope positive) at the rock's centroid: the displacement after ``t_calm`` s
(the water's start: the seeded water is not in equilibrium around the blocks and sloshes; its kinetic energy is
reported), the displacement after that to the end (``after_calm_um``), the creep over the last ``window`` s, the
water's kinetic energy then, and the elastic shear deflection under the buoyant weight m' g sin(alpha) / (2 k_s)
(the prism's two base corners).

    python -m benchmarks.submerged_block --device cuda:0 --spacing 0.005 --duration 60   # GPU
    python -m benchmarks.submerged_block --spacing 0.02 --duration 3                     # CPU, ~1 min

writes benchmarks/results/submerged_block-<device>.json and .md.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

ALPHA = 20.0
RHO_ROCK, RHO_WATER = 2600.0, 1000.0


def submerged_scene(margin: float, spacing: float = 0.02, kn: float = 1.0e6, alpha: float = ALPHA,
                    duration: float = 1.0) -> tuple[dict, np.ndarray]:
    """The 2D scene (a dict for rockwave.scene.format.parse_scene) and the down-slope unit vector."""
    a = math.radians(alpha)
    n = np.array([-math.sin(a), math.cos(a), 0.0])  # the slab's top normal (the slab turned by alpha about z)
    down = np.array([-math.cos(a), -math.sin(a), 0.0])
    centre, thick, size = np.array([0.3, 0.12, 0.0]), 0.06, 0.1
    pos = centre + (thick / 2 + size / 2) * n
    mat = {"friction_angle_deg": alpha + margin, "normal_stiffness_n_m": kn}
    scene = {"simulation": {"dimension": 2, "duration_s": duration},
             "fluid": {"spacing_m": spacing, "eos": {"speed_of_sound_m_s": 15.0}, "viscosity": {"artificial_alpha": 0.05},
                       "regions": [{"box_min_m": [0.0, 0.0], "box_max_m": [0.6, 0.35]}]},
             "tank": {"box_min_m": [0.0, 0.0], "box_max_m": [0.6, 0.5]},
             "blocks": [{"name": "slab", "shape": "box", "size_m": [0.5, thick, 0.1], "position_m": centre.tolist(),
                         "orientation_deg": [0.0, 0.0, alpha], "kind": "fixed", "material": mat},
                        {"name": "rock", "shape": "box", "size_m": [size, size, 0.1], "position_m": pos.tolist(),
                         "orientation_deg": [0.0, 0.0, alpha], "density_kg_m3": RHO_ROCK, "material": mat}],
             "coupling": {"block_walls": True}}
    return scene, down


def run_case(device: str, margin: float, spacing: float, kn: float, duration: float, t_calm: float, window: float,
             every: float = 0.05) -> dict:
    """One run; the record (t, displacement down the dip [um], water + block kinetic energy [J/m]) every ``every`` s."""
    import warnings

    import rockwave
    from rockwave.scene.format import parse_scene

    scene, down = submerged_scene(margin, spacing, kn, duration=duration)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the water seeded inside the slab and the rock is reported, and expected
        sim = rockwave.Simulation(parse_scene(scene), device=device)
    names = [s.name for s in sim.blocks.specs]
    ib = names.index("rock")
    x0 = sim.block_positions()[ib].copy()
    ts, ds, ke = [0.0], [0.0], [sim.kinetic_energy()]
    t0 = time.perf_counter()
    while ts[-1] < duration - 1e-9:
        h = min(every, duration - ts[-1])
        sim.advance(h)
        ts.append(ts[-1] + h)
        ds.append(float((sim.block_positions()[ib] - x0) @ down))
        ke.append(sim.kinetic_energy())
    wall = time.perf_counter() - t0
    ts, ds, ke = np.array(ts), np.array(ds), np.array(ke)
    ic = int(np.searchsorted(ts, t_calm - 1e-9))
    iw = int(np.searchsorted(ts, ts[-1] - window - 1e-9))
    m = float(sim.blocks.np["mass"][ib])
    k_s = float(sim.blocks.np["k_s"][ib])
    elastic = m * (1.0 - RHO_WATER / RHO_ROCK) * 9.81 * math.sin(math.radians(ALPHA)) / (2.0 * k_s)
    return dict(margin_deg=margin, spacing_m=spacing, kn=kn, particles=sim.n_fluid, duration_s=duration,
                wall_s=wall, elastic_um=1e6 * elastic, disp_um=1e6 * ds[-1], start_slip_um=1e6 * ds[ic],
                after_calm_um=1e6 * (ds[-1] - ds[ic]), t_calm_s=t_calm,
                creep_um_s=1e6 * (ds[-1] - ds[iw]) / (ts[-1] - ts[iw]), window_s=float(ts[-1] - ts[iw]),
                kinetic_at_calm_j=float(ke[ic]), kinetic_end_j=float(ke[-1]),
                record=[[float(a), 1e6 * float(b), float(c)] for a, b, c in zip(ts, ds, ke)])


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.submerged_block", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--spacing", type=float, default=0.02)
    ap.add_argument("--kn", type=float, default=1.0e6)
    ap.add_argument("--margins", type=float, nargs="+", default=[0.5, -0.5])
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--t-calm", type=float, default=None, help="the water's start ends here (default: duration / 3)")
    ap.add_argument("--window", type=float, default=None, help="creep over the last this many s (default: 10 s or duration / 3)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    import warp as wp

    from benchmarks.common import RESULTS, commit, device_name, log, write_json

    wp.config.quiet = True
    t_calm = a.t_calm if a.t_calm is not None else a.duration / 3
    window = a.window if a.window is not None else min(10.0, a.duration / 3)
    rows = []
    for mg in a.margins:
        r = run_case(a.device, mg, a.spacing, a.kn, a.duration, t_calm, window)
        log(f"  margin {mg:+g} deg: {r['particles']} particles, start slip {r['start_slip_um']:.2f} um by {t_calm:g} s, "
            f"then {r['after_calm_um']:.3f} um, creep {r['creep_um_s']:.4f} um/s over the last {r['window_s']:g} s, "
            f"water KE {r['kinetic_at_calm_j']:.3g} -> {r['kinetic_end_j']:.3g} J/m ({r['wall_s']:.0f} s)")
        rows.append(r)
    stem = a.out or str(RESULTS / f"submerged_block-{a.device.replace(':', '')}")
    md = [f"# Block under still water, alpha {ALPHA:g} deg (issue 36): {device_name(a.device)}, commit {commit()}, "
          f"spacing {a.spacing:g} m, k_n {a.kn:g} N/m per point, {a.duration:g} s", "",
          "| margin deg | particles | start slip um (to t_calm) | after t_calm um | creep um/s (last window) | "
          "elastic um | water KE at t_calm, end J/m | wall s |", "|---|---|---|---|---|---|---|---|"]
    md += [f"| {r['margin_deg']:+g} | {r['particles']} | {r['start_slip_um']:.2f} ({r['t_calm_s']:g} s) | "
           f"{r['after_calm_um']:.3f} | {r['creep_um_s']:.4f} ({r['window_s']:g} s) | {r['elastic_um']:.2f} | "
           f"{r['kinetic_at_calm_j']:.3g}, {r['kinetic_end_j']:.3g} | {r['wall_s']:.0f} |" for r in rows]
    with open(stem + ".md", "w") as f:
        f.write("\n".join(md) + "\n")
    write_json(dict(rows=rows, device=a.device, commit=commit(), args=vars(a)), stem + ".json")
    print("\n".join(md))


if __name__ == "__main__":
    main()
