"""Part ``delta_plus`` (issue 38): the delta-SPH candidates side by side in one run, at a CPU size (``quick``) or
larger (``full``). For each variant (dotted scene changes, as the chart's formulations):

- ``standing``: the chart's standing wave (harness.standing_wave: first sloshing mode, k d = 0.9, a = 0.02 m in
  0.2 m, c0 12 m/s, no viscosity) at ``dp_standing_ppd`` particles per depth over ``dp_standing_periods`` periods:
  decay per period and period error of the damped-sine fit, the cost (wall s per simulated s);
- ``wall``: a 2D dam break into a wall (the Martin & Moyce column of scenes/dam_break_2d.toml at a / ``dp_dam_n``,
  its tank shortened to 0.35 m so the surge hits the end wall at ~0.23 s and runs up it), a pressure gauge on the
  end wall 1 cm up read every 0.5 ms: the impact time (first crossing of half the peak), the peak of the +-5 ms
  means and of the single reads, the noise after the impact (harness.pressure_noise: RMS above 200 Hz over the
  low-pass RMS, 20 ms), the deepest any particle got past a wall's face (spacings) and the lowest density;
- ``rest``: water at rest (benchmarks/at_rest.py's 2D tank, 0.3 m deep) at ``dp_rest_layers`` layers for
  ``dp_rest_t`` s: the corner, mid-floor and mid-wall gauges / rho0 g d and the worst first-layer wall particle.

Each variant runs the three after a short warm-up (its kernels built out of the timing). Rows are saved as they
finish.
"""

from __future__ import annotations

import math
import time

import numpy as np

from benchmarks import harness as H
from benchmarks.common import log

# the variants: the levels and the steps between the level as first shipped (2026-11-28) and as it is now
# (docs/notes.md 'delta-plus, second round'); the first round's other candidates (Antuono et al.'s renormalised
# diffusion over the fluid, the wall density extrapolated with the renormalised gradient, the shift's Taylor
# correction) were measured with this part at commit eb4b419 and left out
OLD = {"fluid.fidelity": "delta_plus", "fluid.density_diffusion_form": "hydrostatic", "fluid.gradient_correction": False,
       "fluid.particle_shifting": 0.1}
VARIANTS = {
    "standard": {"fluid.fidelity": "standard"},
    "waves": {"fluid.fidelity": "waves"},
    "delta_plus_1128": dict(OLD),  # the level as the 2026-11-28 H200 chart ran it
    "old+pressure": OLD | {"fluid.density_diffusion_form": "pressure"},
    "old+kgc": OLD | {"fluid.gradient_correction": True},
    "old+kgc+K0": OLD | {"fluid.gradient_correction": True, "fluid.particle_shifting": 0.0},
    "delta_plus": {"fluid.fidelity": "delta_plus"},  # the level now: pressure + kgc + K 0.02
    "delta_plus_K0": {"fluid.fidelity": "delta_plus", "fluid.particle_shifting": 0.0},
    "delta_plus_K0.1": {"fluid.fidelity": "delta_plus", "fluid.particle_shifting": 0.1},
    # sixth round (docs/notes.md 'delta-plus, sixth round'): the plain momentum and continuity equations (no
    # correction) with Antuono et al.'s renormalised diffusion, alpha 0 / 0.01 / 0.02 (benchmarks/chart.py's
    # formulations of the same names), and the level without the correction at alpha 0 / 0.01
    "delta_plus_nokgc": {"fluid.fidelity": "delta_plus", "fluid.gradient_correction": False},
    "delta_plus_nokgc_a01": {"fluid.fidelity": "delta_plus", "fluid.gradient_correction": False,
                             "fluid.viscosity.artificial_alpha": 0.01},
    "delta_plus_renorm": {"fluid.fidelity": "delta_plus", "fluid.gradient_correction": False,
                          "fluid.density_diffusion_renormalised": True},
    "delta_plus_renorm_a01": {"fluid.fidelity": "delta_plus", "fluid.gradient_correction": False,
                              "fluid.density_diffusion_renormalised": True, "fluid.viscosity.artificial_alpha": 0.01},
    "delta_plus_renorm_a02": {"fluid.fidelity": "delta_plus", "fluid.gradient_correction": False,
                              "fluid.density_diffusion_renormalised": True, "fluid.viscosity.artificial_alpha": 0.02},
}
CONFIG = {
    "quick": dict(dp_variants=["standard", "delta_plus_1128", "delta_plus", "delta_plus_K0"], dp_standing_ppd=12, dp_standing_periods=2.0, dp_dam_n=20,
                  dp_dam_t_end=0.6, dp_rest_layers=20, dp_rest_t=0.5, dp_parts=["standing", "wall", "rest"]),
    "full": dict(dp_variants=["standard", "waves", "delta_plus_1128", "delta_plus", "delta_plus_K0"], dp_standing_ppd=50, dp_standing_periods=2.0, dp_dam_n=80,
                 dp_dam_t_end=0.6, dp_rest_layers=100, dp_rest_t=2.0, dp_parts=["standing", "wall", "rest"]),
}
WALL_X = 0.35  # the shortened tank's end wall [m]
WALL_TOP = 0.4  # its walls' height [m]
GAUGE_DT = 5e-4  # wall gauge read interval [s]


def standing(dev: str, variant: dict, ppd: int, periods: float) -> dict:
    r = H.standing_wave(dev, ppd, variant, periods=periods, **{k: v for k, v in H_STANDING.items()})
    return {k: r[k] for k in ("particles", "decay_per_period", "period_error", "density_error", "wall_per_sim_s",
                              "steps", "finite")}


H_STANDING = dict(a=0.02, kh=0.9, mode=1, signal="projection")


def wall_impact(dev: str, variant: dict, n: int, t_end: float) -> dict:
    """The 2D dam break into the end wall (module docstring)."""
    dx = H.A_MM / n
    d = H.scene_dict("dam_break_2d", dx, variant, None, H.FORMULATION_KEYS)
    d["tank"]["box_max_m"] = [WALL_X, WALL_TOP]
    d["output"]["gauges"] = [{"name": "wall", "kind": "pressure", "position_m": [WALL_X, 0.01]}]
    sim = H.build("dam_break_2d", d, dev)
    ts, ps = [], []
    pen, rho_min = 0.0, math.inf
    t0 = time.perf_counter()
    steps0 = sim.steps
    while sim.time < t_end - 1e-9:
        sim.advance(min(GAUGE_DT, t_end - sim.time))
        ts.append(sim.time)
        ps.append(float(sim.gauges().get("wall", math.nan)))
        if len(ts) % 20 == 0 or sim.time >= t_end - 1e-9:
            x, rho = sim.positions(), sim.densities()
            if not (np.isfinite(x).all() and np.isfinite(rho).all()):
                break
            low = x[:, 1] < WALL_TOP - dx  # (water thrown over the wall's top is no penetration)
            pen = max(pen, float(max(x[low, 0].max() - WALL_X, -x[low, 0].min(), -x[:, 1].min())) / dx)
            rho_min = min(rho_min, float(rho.min()))
    wall = time.perf_counter() - t0
    t, p = np.asarray(ts), np.nan_to_num(np.asarray(ps), nan=0.0)
    rec = {"particles": sim.n_fluid, "spacing_m": dx, "steps": sim.steps - steps0, "wall_s": wall,
           "penetration_spacings": pen, "rho_min": rho_min, "simulated_s": sim.time}
    if len(t) > 20 and p.max() > 0:
        peak_raw = float(p.max())
        k = int(np.argmax(p > 0.5 * peak_raw))
        t_imp = float(t[k])
        half = int(round(0.005 / GAUGE_DT))
        means = np.convolve(p, np.ones(2 * half + 1) / (2 * half + 1), mode="same")
        rec.update(impact_t_s=t_imp, peak_pa=float(means.max()), peak_raw_pa=peak_raw,
                   noise=H.pressure_noise(t, p, t_imp), t=t.tolist(), p=p.tolist())
    return rec


def rest(dev: str, variant: dict, layers: int, t_end: float) -> dict:
    from benchmarks.at_rest import measure

    keys: dict = {}
    for k, v in variant.items():  # the [fluid] keys, dotted sub-keys (viscosity.artificial_alpha) as tables
        if k.startswith("fluid.") and k != "fluid.fidelity":
            *path, last = k.split(".")[1:]
            node = keys
            for p in path:
                node = node.setdefault(p, {})
            node[last] = v
    r = measure(dev, 2, layers, t_end, variant.get("fluid.fidelity", "standard"), None, keys)
    return {k: r.get(k) for k in ("corner", "floor_mid", "side_mid", "wall_error_max", "speed_rms_c0",
                                  "drift_spacings", "wall_per_sim_s")}


def run(dev: str, cfg: dict, save=None) -> dict:
    out = {"rows": []}
    for name in cfg["dp_variants"]:
        v = VARIANTS[name]
        row = {"variant": name, "changes": v}
        H.standing_wave(dev, 6, v, periods=0.05, **H_STANDING)  # warm-up: kernel builds out of the timing
        if "standing" in cfg["dp_parts"]:
            row["standing"] = s = standing(dev, v, cfg["dp_standing_ppd"], cfg["dp_standing_periods"])
            log(f"  {name:18s} standing {cfg['dp_standing_ppd']}/depth: decay {s['decay_per_period']:+.4f}/period, "
                f"period {s['period_error']:+.4f}, {s['wall_per_sim_s']:.2f} s/s")
        if "wall" in cfg["dp_parts"]:
            row["wall"] = w = wall_impact(dev, v, cfg["dp_dam_n"], cfg["dp_dam_t_end"])
            log(f"  {name:18s} wall impact a/{cfg['dp_dam_n']}: t {w.get('impact_t_s', math.nan):.4f} s, peak "
                f"{w.get('peak_pa', math.nan):.0f} Pa (reads {w.get('peak_raw_pa', math.nan):.0f}), noise "
                f"{w.get('noise', math.nan):.3f}, past a wall {w['penetration_spacings']:.2f} dx, rho min "
                f"{w['rho_min']:.0f}, {w['wall_s']:.1f} s")
        if "rest" in cfg["dp_parts"]:
            row["rest"] = r = rest(dev, v, cfg["dp_rest_layers"], cfg["dp_rest_t"])
            log(f"  {name:18s} at rest {cfg['dp_rest_layers']} layers: corner {r['corner']:.4f} floor {r['floor_mid']:.4f}"
                f" side {r['side_mid']:.4f} walls {r.get('wall_error_max') or math.nan:.4f}")
        out["rows"].append(row)
        if save is not None:
            save(out)
    return out
