"""Part ``chart``: accuracy against cost of the fluid formulations (issue 19): for each case, formulation and
resolution one point (error, wall seconds per simulated second), with steps, particles and particle-steps/s.

Cases (errors defined in benchmarks/harness.py):

- ``standing_wave``: 2D first sloshing mode, k d = 0.9, a = 0.02 m in d = 0.2 m, c0 12 m/s, no viscosity
  (harness.standing_wave, the set-up of tests/test_standing_wave.py); error = amplitude decay per period
  (damped-sine fit) and period error against linear theory; resolution = particles per depth.
- ``wave_maker``: the piston wave maker (benchmarks/wave_maker.py, scenes/wave_maker_small.toml); error = the larger
  |H/H_linear - 1| of gauge_1 and gauge_2, H_linear from the linear solution of the same flume and window
  (wave_maker.flume_linear_eta); resolution = particle layers per depth.
- ``dam_break``: 2D dam break against Martin & Moyce (harness.run_dam_break); error = |mean front bias| over
  T >= 1.5 (and the front + height RMS); resolution = a / n.
- ``spheric``: SPHERIC Test 2 (3D; harness.run_spheric); error = RMS water-level error / 0.55 m averaged over
  H1-H4 (and the largest), P1 impact time and peak; resolution = spacing. Run on CUDA only unless
  ``chart_spheric_on_cpu``.

Formulations: ``FORMULATIONS`` below (name -> dotted scene changes, as harness.VARIANTS), the one place to add
one; or from the command line, ``--formulation 'NAME={"fluid.kernel": "wendland"}'`` (adds or replaces) and
``--formulations NAME ...`` (runs only these). A key ending in ``?`` is applied only where the scene schema
knows it (a formulation that should pin a key that does not exist yet). A formulation whose changes the scene
loader refuses is skipped with the loader's reason (a row with ``skipped``), so new keys can be listed before
they exist. The case builders remove the scene files' own formulation keys (harness.FORMULATION_KEYS: kernel,
support ratio, density, diffusion, pressure force, fidelity, boundary) before applying a formulation, so a
one-key formulation (fluid.fidelity) is not overridden by a scene's ``kernel = "muller"``; each row records
the [fluid] formulation keys the simulation was built with (``fluid``). Viscosity stays the case's (dam break
alpha 0.05, SPHERIC alpha 0.05 + XSPH 0.05, wave maker and standing wave none) unless a formulation sets it.

Each (case, formulation) pair runs a short warm-up at its coarsest resolution first (kernel loads out of the
timing). Rows are saved to the record as they finish (a run cut off by a time limit keeps them).
"""

from __future__ import annotations

import json
import math

import numpy as np

from benchmarks import harness as H
from benchmarks.common import fmt_value as _f
from benchmarks.common import log

# name -> dotted scene changes: the three fidelity levels (fluid.fidelity; "draft" is the formulation that was the
# default before issue 19) and expert variants around the default.
FORMULATIONS: dict[str, dict] = {
    "draft": {"fluid.fidelity": "draft"},  # the old default: Mueller kernels at 2 spacings, Akinci walls
    "standard": {"fluid.fidelity": "standard"},  # the default: Wendland C2 at 3 spacings, Adami walls
    "high": {"fluid.fidelity": "high"},  # Wendland C2 at 4 spacings, Adami walls
    "wendland-3-akinci": {"fluid.kernel": "wendland", "fluid.support_radius_ratio": 3.0, "fluid.boundary": "akinci"},
    "cubic-3": {"fluid.fidelity": "standard", "fluid.kernel": "cubic_spline"},
    "standard+diffusion": {"fluid.fidelity": "standard", "fluid.density_diffusion": 0.1},
    # fidelity 'waves': standard with the kernel-gradient correction and the density floor (docs/notes.md
    # 'Kernel-gradient correction'); the 2026-11-28 H200 record calls it standard+kgc
    "waves": {"fluid.fidelity": "waves"},
    # fidelity 'delta_plus' (issue 38): standard with the kernel-gradient correction, delta-SPH diffusion of the
    # pressure's density (walls included) and light particle shifting, alpha 0 (docs/physics.md 'The delta_plus level')
    "delta_plus": {"fluid.fidelity": "delta_plus"},
    # the level as the 2026-11-28 H200 record ran it: the continuity density diffused, no correction, K = 0.1
    "delta_plus_1128": {"fluid.fidelity": "delta_plus", "fluid.density_diffusion_form": "hydrostatic",
                        "fluid.gradient_correction": False, "fluid.particle_shifting": 0.1},
    # the level without shifting (on the CPU the shift adds ~11 K points of decay per period to the standing wave)
    "delta_plus_K0": {"fluid.fidelity": "delta_plus", "fluid.particle_shifting": 0.0},
    # issue 38, third round (docs/notes.md 'delta-plus, third round'): Adami wall particles on the moving blocks (the
    # wave maker's piston: scenes/wave_maker_small.toml has the penalty alone), and the level's P1 arrival against
    # its artificial viscosity (standard's alpha 0.01) and its gradient correction
    "standard_bw": {"fluid.fidelity": "standard", "coupling.block_walls": True},
    "delta_plus_bw": {"fluid.fidelity": "delta_plus", "coupling.block_walls": True},
    "delta_plus_a01": {"fluid.fidelity": "delta_plus", "fluid.viscosity.artificial_alpha": 0.01},
    "delta_plus_nokgc": {"fluid.fidelity": "delta_plus", "fluid.gradient_correction": False},
    # issue 38, sixth round: the plain (pairwise antisymmetric) momentum and continuity equations with Antuono et al.'s
    # renormalised diffusion (the corrected gradient in the diffusion alone), alpha 0 / 0.01 / 0.02; and the level
    # without the correction at alpha 0.01 (the viscosity's share without the renormalised diffusion)
    "delta_plus_renorm": {"fluid.fidelity": "delta_plus", "fluid.gradient_correction": False,
                          "fluid.density_diffusion_renormalised": True},
    "delta_plus_renorm_a01": {"fluid.fidelity": "delta_plus", "fluid.gradient_correction": False,
                              "fluid.density_diffusion_renormalised": True, "fluid.viscosity.artificial_alpha": 0.01},
    "delta_plus_renorm_a02": {"fluid.fidelity": "delta_plus", "fluid.gradient_correction": False,
                              "fluid.density_diffusion_renormalised": True, "fluid.viscosity.artificial_alpha": 0.02},
    "delta_plus_nokgc_a01": {"fluid.fidelity": "delta_plus", "fluid.gradient_correction": False,
                             "fluid.viscosity.artificial_alpha": 0.01},
    # issue 37: the Adami walls' pressure work paired (fluid.wall_work, opt-in; docs/physics.md 'Walls'): what it costs
    # the waves at the chart's resolutions
    "standard_wallwork": {"fluid.fidelity": "standard", "fluid.wall_work": True},
    "delta_plus_wallwork": {"fluid.fidelity": "delta_plus", "fluid.wall_work": True},
}
CASES = ("standing_wave", "wave_maker", "dam_break", "spheric")
STANDING = dict(depth=0.2, kh=0.9, mode=1, a=0.02, c0=12.0, signal="projection")  # first sloshing mode

# Sizes. quick: a 2-core CPU in a few minutes (Warp's CPU backend runs a kernel on one thread; 200 s at load
# average 5). full: one H100 call of ~8 minutes: ~285 s of runs by the model of `python -m benchmarks.chart
# --plan full` plus kernel compilation on a fresh machine (~2 min: the wave_maker record's first run) and the
# warm-ups. The finer resolutions (standing wave 200 per depth, wave maker 64 layers, dam break a/160: ~370 s
# more) fit a second call: EXTRA below, docs/benchmarks.md.
CONFIG = {
    "quick": dict(chart_cases=list(CASES), chart_formulations=dict(FORMULATIONS), chart_standing_ppd=[8, 12],
                  chart_standing_periods=2.0, chart_wave_layers=[8, 12], chart_wave_t_end=2.6, chart_dam_res=[10, 20],
                  chart_dam_t_end=0.2, chart_spheric=[0.1], chart_spheric_t_end=0.1, chart_spheric_on_cpu=False),
    "full": dict(chart_cases=list(CASES), chart_formulations=dict(FORMULATIONS), chart_standing_ppd=[25, 50, 100],
                 chart_standing_periods=2.0, chart_wave_layers=[16, 32], chart_wave_t_end=2.6,
                 chart_dam_res=[20, 40, 80], chart_dam_t_end=0.2, chart_spheric=[0.02, 0.012],
                 chart_spheric_t_end=1.5, chart_spheric_on_cpu=False),
}
# the second full call: --set each of these (docs/benchmarks.md), then merge the two records
EXTRA = dict(chart_cases=["standing_wave", "wave_maker", "dam_break"], chart_standing_ppd=[200], chart_wave_layers=[64],
             chart_dam_res=[160])

# what the chart plots: (case, row key, panel title); |value| on log axes
METRICS = (("standing_wave", "decay_per_period", "standing wave: amplitude decay per period"),
           ("standing_wave", "period_error", "standing wave: |period error|"),
           ("wave_maker", "error", "piston wave maker: |H / H_linear - 1|, worse gauge"),
           ("dam_break", "error", "2D dam break: |front bias|, T >= 1.5"),
           ("spheric", "error", "SPHERIC Test 2: water level RMS / 0.55 m, H1-H4 mean"),
           ("spheric", "p1_noise", "SPHERIC Test 2: P1 noise > 200 Hz / low-pass, 20 ms after impact"))


# ------------------------------------------------------------------------------- formulations ----
def parse_formulation(text: str) -> tuple[str, dict]:
    """'NAME={json}' -> (NAME, dict); the name may contain '=' (e.g. 'fidelity=high={"fluid.fidelity": "high"}')."""
    i = text.find("={")
    if i <= 0:
        raise ValueError(f"--formulation {text!r}: expected NAME={{JSON object of dotted scene keys}}")
    changes = json.loads(text[i + 1:])
    if not isinstance(changes, dict):
        raise ValueError(f"--formulation {text!r}: the changes must be a JSON object")
    return text[:i], changes


def _schema_has(path: str) -> bool:
    from rockwave.scene.format import SCHEMA

    node = SCHEMA
    for k in path.split("."):
        key = node.get(k) if isinstance(node, dict) else None
        if key is None:
            return False
        node = key.children if key.children else None
    return True


def resolve(changes: dict) -> tuple[dict, list[str]]:
    """The changes to apply: keys ending in '?' kept only where the schema knows them; also the dropped keys."""
    out, dropped = {}, []
    for k, v in changes.items():
        if k.endswith("?"):
            if _schema_has(k[:-1]):
                out[k[:-1]] = v
            else:
                dropped.append(k[:-1])
        else:
            out[k] = v
    return out, dropped


def refused(case: str, changes: dict) -> str | None:
    """The scene loader's reason for refusing ``changes`` on a case's scene, or None when it takes them."""
    import rockwave
    from benchmarks.wave_maker import piston_dict

    if case == "standing_wave":
        d = _standing_dict(10, changes)
    elif case == "wave_maker":
        d = piston_dict(16, changes, strip=H.FORMULATION_KEYS)
    elif case == "dam_break":
        d = H.scene_dict("dam_break_2d", H.A_MM / 10, changes, strip=H.FORMULATION_KEYS)
    else:
        d = H.scene_dict("spheric", 0.1, changes, strip=H.FORMULATION_KEYS)
    try:
        rockwave.parse_scene(d, f"{case}.toml", H.ROOT / "scenes")
    except rockwave.SceneError as e:
        return "; ".join(f"{k}: {m}" if k else m for k, m in e.errors)[:300]
    return None


def _standing_dict(ppd, changes):
    return H.standing_wave_dict(ppd, changes, STANDING["depth"], STANDING["kh"], STANDING["mode"], STANDING["c0"])


# ------------------------------------------------------------------------------------ runners ----
def _standing(dev, ppd, ch, periods):
    r = H.standing_wave(dev, ppd, ch, periods=periods, **STANDING)
    r.pop("t"), r.pop("signal_m"), r.pop("noise_ke_j"), r.pop("kinetic_j")
    r["error"] = abs(r["decay_per_period"]) if math.isfinite(r["decay_per_period"]) else math.nan
    return r


def _wave(dev, layers, ch, t_end):
    from benchmarks.wave_maker import piston

    r = piston(dev, layers, t_end, ch, strip=H.FORMULATION_KEYS)
    # the larger of the two gauges' errors against the linear solution of the same flume and window
    r["error"] = max(abs(r["error_flume_gauge1"]), abs(r["error_flume_gauge2"])) if t_end >= 2.6 - 1e-9 else math.nan
    return r


def _dam(dev, n, ch, t_end):
    r = H.run_dam_break(dev, H.A_MM / n, ch, t_end, strip=H.FORMULATION_KEYS)
    r["layers"] = n
    r["error"], r["error_rms"] = abs(r.get("front_bias_late", math.nan)), r.get("error", math.nan)
    return r


def box_force_summary(series: dict, key: str = "box_force", window_s: float = 0.15) -> dict:
    """The surge's load on the SPHERIC box from its force gauge's 10 ms reads (scenes/dam_break_3d.toml
    ``box_force``, N along the surge): the arrival (first read above 5% of the peak), the peak read and its time,
    and the mean over ``window_s`` from the arrival (the first impact's load, less sensitive to one read)."""
    if key not in series or not series.get("t"):
        return {}
    t, f = np.asarray(series["t"], float), np.nan_to_num(np.asarray(series[key], float))
    i = int(np.argmax(f))
    if f[i] <= 0.0:
        return {}
    a = int(np.argmax(f > 0.05 * f[i]))
    w = (t >= t[a]) & (t < t[a] + window_s - 1e-9)
    return {"box_force_arrival_s": float(t[a]), "box_force_peak_n": float(f[i]), "box_force_peak_t_s": float(t[i]),
            "box_force_impact_mean_n": float(f[w].mean())}


def _spheric(dev, s, ch, t_end):
    r = H.run_spheric(dev, s, ch, t_end, strip=H.FORMULATION_KEYS)  # keeps the gauge series (10 ms) and P1's 1 ms reads
    r["error"], r["error_hp"] = r.get("h_rms", math.nan), r.get("error", math.nan)
    r.update(box_force_summary(r.get("series", {})))
    return r


def _label(case, res):
    return {"standing_wave": f"{res} /depth", "wave_maker": f"{res} /depth", "dam_break": f"a/{res}"}.get(case, f"{res:g} m")


def plan(cfg: dict) -> list[tuple]:
    """(case, resolutions, runner, runner's duration argument, simulated seconds, warm-up argument)."""
    periods = cfg["chart_standing_periods"]
    T = 2 * math.pi / H.linear_wave(STANDING["depth"], STANDING["kh"])[1]
    return [("standing_wave", cfg["chart_standing_ppd"], _standing, periods, periods * T, 0.25),
            ("wave_maker", cfg["chart_wave_layers"], _wave, cfg["chart_wave_t_end"], cfg["chart_wave_t_end"], 0.05),
            ("dam_break", cfg["chart_dam_res"], _dam, cfg["chart_dam_t_end"], cfg["chart_dam_t_end"], 0.002),
            ("spheric", cfg["chart_spheric"], _spheric, cfg["chart_spheric_t_end"], cfg["chart_spheric_t_end"], 0.01)]


def run(dev: str, cfg: dict, save=None) -> dict:
    """Rows of every case x formulation x resolution of ``cfg``; ``save(part)`` after each row."""
    forms = cfg["chart_formulations"]
    out = {"formulations": forms, "standing_wave": dict(STANDING), "rows": [], "skipped": []}
    cuda = str(dev).startswith("cuda")
    for case, resolutions, runner, arg, sim_t, warm_t in plan(cfg):
        if case not in cfg["chart_cases"] or not resolutions:
            continue
        if case == "spheric" and not cuda and not cfg["chart_spheric_on_cpu"]:
            why = "SPHERIC Test 2 runs on CUDA only (chart_spheric_on_cpu = false: far too big for Warp's one-thread CPU)"
            out["skipped"].append({"case": case, "formulation": "*", "why": why})
            log(f"  {case}: skipped: {why}")
            continue
        for name, changes in forms.items():
            ch, dropped = resolve(changes)
            why = refused(case, ch)
            if why:
                out["skipped"].append({"case": case, "formulation": name, "why": why})
                log(f"  {case} {name}: skipped, the scene loader refuses it: {why}")
                if save:
                    save(out)
                continue
            try:
                runner(dev, min(resolutions), ch, warm_t)  # kernel loads out of the timing
            except Exception as e:  # noqa: BLE001 - recorded on the rows below
                log(f"  {case} {name}: warm-up failed: {type(e).__name__}: {e}")
            for res in resolutions:
                try:
                    r = runner(dev, res, ch, arg)
                except Exception as e:  # noqa: BLE001 - a failing run is a row, the others still run
                    r = {"exception": f"{type(e).__name__}: {str(e).splitlines()[0][:200]}", "error": math.nan}
                r.update(case=case, formulation=name, resolution=res, label=_label(case, res))
                if dropped:
                    r["dropped_keys"] = dropped
                wall, sim = r.get("wall_s", math.nan), r.get("simulated_s", sim_t)
                r.setdefault("simulated_s", sim)
                r.setdefault("wall_per_sim_s", wall / sim if sim else math.nan)
                r["particle_steps_per_s"] = r.get("particles", 0) * r.get("steps", 0) / wall if wall and wall > 0 else math.nan
                r["class"], r["why"] = health_class(r)
                out["rows"].append(r)
                log("  " + line(r))
                if save:
                    save(out)
    return out


def health_class(r: dict) -> tuple[str, list[str]]:
    """harness.classify on the run's health record (NaN, energy growth, escape, density error; not the case's
    error, whose scale differs per case); the standing wave adds a particle faster than c0 / 2 (the linear
    wave's orbital speeds are ~0.2 m/s). The chart leaves blown-up runs out; the table names them."""
    rec = {k: r[k] for k in ("finite", "energy_growth", "escaped_fraction", "density_error", "exception") if k in r}
    if r.get("case") == "standing_wave" and r.get("max_speed_m_s", 0.0) > 0.5 * STANDING["c0"]:
        rec["finite"] = rec.get("finite", True)
        cls, why = H.classify(rec)
        if cls != "blown_up":
            cls, why = "blown_up", []
        return cls, why + [f"a particle at {r['max_speed_m_s']:.3g} m/s > c0 / 2"]
    return H.classify(rec) if rec else ("-", [])


def line(r: dict) -> str:
    def f(k, fmt=".3g"):
        v = r.get(k)
        return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)

    extra = {"standing_wave": f"decay/period {f('decay_per_period', '+.4f')} period error {f('period_error', '+.4f')} "
                              f"noise/period {f('noise_growth_per_period', '+.3f')}",
             "wave_maker": f"gauge_1 {f('error_flume_gauge1', '+.3f')} gauge_2 {f('error_flume_gauge2', '+.3f')} (flume's linear solution)",
             "dam_break": f"front bias T>=1.5 {f('front_bias_late', '+.3f')} rms {f('error_rms', '.3f')} "
                          f"speed x{f('front_speed_ratio', '.3f')} delay {f('front_delay_s', '.4f')} s",
             "spheric": f"H mean {f('h_rms', '.3f')} max {f('h_max', '.3f')} P1 t {f('p1_impact_error', '+.3f')} "
                        f"peak {f('p1_peak_error', '+.3f')} (arrival {f('p1_first_error', '+.3f')}, after "
                        f"{f('p1_after_error', '+.3f')}) noise {f('p1_noise', '.3f')}"}[r["case"]]
    ex = f" {r['exception']}" if r.get("exception") else ""
    ex += f"  {r.get('class', '')}" + (f" ({'; '.join(r['why'])})" if r.get("why") else "")
    return (f"{r['case']:13s} {r['formulation']:22s} {r['label']:>12s} n={r.get('particles', 0):7d} "
            f"steps={r.get('steps', 0):7d} {f('wall_per_sim_s', '8.2f')} s/sim-s {f('particle_steps_per_s', '.3g')} "
            f"p-steps/s  {extra}{ex}")


def merge(a: dict, b: dict) -> dict:
    """Rows of two records of this part: b's row replaces a's for the same case, formulation and resolution."""
    key = lambda r: (r["case"], r["formulation"], r["resolution"])  # noqa: E731
    rows = {key(r): r for r in a.get("rows", [])}
    rows.update({key(r): r for r in b.get("rows", [])})
    skipped = {(s["case"], s["formulation"]): s for s in a.get("skipped", []) + b.get("skipped", [])}
    for r in rows.values():
        skipped.pop((r["case"], r["formulation"]), None)
    return {"formulations": {**a.get("formulations", {}), **b.get("formulations", {})},
            "standing_wave": b.get("standing_wave", a.get("standing_wave")), "rows": list(rows.values()),
            "skipped": list(skipped.values())}


# --------------------------------------------------------------------------------- estimates ----
def estimate(cfg: dict, device: str = "cpu") -> list[dict]:
    """Particles and steps of every run of ``cfg`` (scenes built here, not run; steps = simulated time / the
    initial CFL step x 1.1: the step shrinks a little as the water moves), and an H100 time model, n = fluid
    particles, r = support / spacing, cost per particle ~ neighbours^0.5 (the issue's SPHERIC figures: Wendland
    at 3 spacings cost 1.86x the old default per step for 3.4x the neighbours):
    2D fluid only (CUDA graphs) 0.15 ms + n (r/2)^1.5 / 1e9 s per step; the wave maker 1.1 ms per step (coupled:
    plain launches and host reads each step; the wave_maker record: 1.08-1.22 ms/step at 8k-131k particles);
    3D 0.2 ms + n (r/2)^1.5 / 1.2e9 s (the readers record: 0.818 ms/step at 1.02 M particles, the old default)."""
    import rockwave
    from benchmarks.wave_maker import piston_dict

    rows = []
    for case, resolutions, _, arg, sim_t, _w in plan(cfg):
        if case not in cfg["chart_cases"]:
            continue
        for name, changes in cfg["chart_formulations"].items():
            ch, _ = resolve(changes)
            if refused(case, ch):
                continue
            for res in resolutions:
                if case == "standing_wave":
                    d = _standing_dict(res, ch)
                elif case == "wave_maker":
                    d = piston_dict(res, ch, strip=H.FORMULATION_KEYS)
                elif case == "dam_break":
                    d = H.scene_dict("dam_break_2d", H.A_MM / res, ch, strip=H.FORMULATION_KEYS)
                else:
                    d = H.scene_dict("spheric", res, ch, strip=H.FORMULATION_KEYS)
                sc = rockwave.parse_scene(d, f"{case}.toml", H.ROOT / "scenes")
                n, dt = _count(sc, device)
                steps = 1.1 * sim_t / dt
                work = n * (float(sc.fluid.get("support_radius_ratio", 2.0)) / 2) ** 1.5
                per = {"wave_maker": 1.1e-3, "spheric": 2e-4 + work / 1.2e9}.get(case, 1.5e-4 + work / 1e9)
                rows.append(dict(case=case, formulation=name, resolution=res, particles=n, steps=int(steps),
                                 est_h100_s=steps * per))
    return rows


def _count(scene, device):
    """(fluid particles, initial step) of a scene, without running it."""
    import rockwave

    sim = rockwave.Simulation(scene, device=device)
    return sim.n_fluid, sim.dt


def main(argv=None) -> None:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m benchmarks.chart", description="particle and step counts of the "
                                 "chart part's runs and an H100 time estimate (nothing is run)")
    ap.add_argument("--plan", choices=list(CONFIG) + ["extra"], default="full",
                    help="a suite's configuration, or 'extra': full with EXTRA (the second call)")
    a = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    rows = estimate(dict(CONFIG["full"], **EXTRA) if a.plan == "extra" else CONFIG[a.plan])
    total = 0.0
    for r in rows:
        total += r["est_h100_s"]
        print(f"{r['case']:13s} {r['formulation']:22s} {r['resolution']:>6} n={r['particles']:8d} steps={r['steps']:8d} "
              f"~{r['est_h100_s']:6.1f} s")
    by = {}
    for r in rows:
        by[r["case"]] = by.get(r["case"], 0.0) + r["est_h100_s"]
    print("per case:", ", ".join(f"{k} {v:.0f} s" for k, v in by.items()), f"; total ~{total:.0f} s on an H100 "
          "(plus warm-ups and kernel loads)")


def table_rows(part: dict) -> list[list]:
    """Rows for the Markdown table (benchmarks/report.py)."""

    out = []
    for r in part.get("rows", []):
        c = r["case"]
        if c == "standing_wave":
            err = f"decay/period {_f(r.get('decay_per_period'), '+.1%')}, period {_f(r.get('period_error'), '+.2%')}"
            if r.get("noise_growth_per_period") is not None:
                err += (f"; particle-scale KE {_f(r.get('noise_growth_per_period'), '+.1%')} per period, "
                        f"{_f(r.get('noise_share_end'), '.1%')} of the KE in the last period")
        elif c == "wave_maker":
            from benchmarks.wave_maker import with_flume_errors

            r = with_flume_errors(dict(r))
            err = (f"gauge_1 {_f(r.get('error_flume_gauge1'), '+.1%')}, gauge_2 {_f(r.get('error_flume_gauge2'), '+.1%')} "
                   f"(flume's linear solution; steady formula {_f(r.get('error_gauge1'), '+.1%')}, "
                   f"{_f(r.get('error_gauge2'), '+.1%')})")
        elif c == "dam_break":
            err = (f"front bias T>=1.5 {_f(r.get('front_bias_late'), '+.1%')}, front+height RMS "
                   f"{_f(r.get('error_rms'), '.3f')}")
            if r.get("front_speed_ratio") is not None and math.isfinite(r["front_speed_ratio"]):
                err += (f"; front speed x{r['front_speed_ratio']:.3f}, start {1e3 * r['front_delay_s']:.1f} ms early "
                        f"(then bias {_f(r.get('front_bias_late_delayed'), '+.1%')}, "
                        f"RMS {_f(r.get('front_rms_late_delayed'), '.1%')})")
        else:
            err = (f"H1-H4 mean {_f(r.get('h_rms'))}, max {_f(r.get('h_max'))}; P1 impact t "
                   f"{_f(r.get('p1_impact_error'), '+.1%')}, peak {_f(r.get('p1_peak_error'), '+.0%')}")
            if r.get("p1_noise") is not None:
                err += f", noise {_f(r.get('p1_noise'), '.2f')} (sensor {_f(r.get('p1_noise_exp'), '.2f')})"
            bf = box_force_summary(r.get("series", {})) if "box_force_peak_n" not in r else r
            if bf:
                err += (f"; box force peak {bf['box_force_peak_n']:.0f} N at {bf['box_force_peak_t_s']:.2f} s, "
                        f"{bf['box_force_impact_mean_n']:.0f} N over 0.15 s from {bf['box_force_arrival_s']:.2f} s")
        if r.get("exception"):
            err += f"; {r['exception'][:80]}"
        cls = r.get("class", "-") + (f": {'; '.join(r['why'])[:120]}" if r.get("why") else "")
        out.append([c, r["formulation"], r["label"], r.get("particles", "-"), _f(r.get("error"), ".3g"), err,
                    _f(r.get("wall_per_sim_s"), ".3g"), r.get("steps", "-"), _f(r.get("particle_steps_per_s"), ".3g"), cls])
    return out


def chart(ax_of, part: dict, device: str) -> None:
    """Draw the panels: ``ax_of(i)`` gives the axes of METRICS[i]."""
    rows = part.get("rows", [])
    names = list(part.get("formulations", {})) or sorted({r["formulation"] for r in rows})
    marks = "osD^v<>p*hX"
    for i, (case, key, title) in enumerate(METRICS):
        ax = ax_of(i)
        for j, name in enumerate(names):
            rr = sorted([r for r in rows if r["case"] == case and r["formulation"] == name
                         and r.get("class") != "blown_up"
                         and math.isfinite(r.get(key, math.nan)) and math.isfinite(r.get("wall_per_sim_s", math.nan))
                         and r.get("wall_per_sim_s", 0) > 0], key=lambda r: r["resolution"])
            if not rr:
                continue
            x = [r["wall_per_sim_s"] for r in rr]
            y = [max(abs(r[key]), 1e-5) for r in rr]
            ax.plot(x, y, marker=marks[j % len(marks)], color=f"C{j}", label=name)
            for r, xx, yy in zip(rr, x, y):
                ax.annotate(str(r["resolution"]), (xx, yy), fontsize=6, xytext=(3, 2), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(title, fontsize=8)
        ax.set_xlabel(f"wall s per simulated s ({device})", fontsize=7)
        ax.grid(True, which="both", alpha=0.3)
        ax.tick_params(labelsize=7)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6)
        else:
            ax.text(0.5, 0.5, "not run", transform=ax.transAxes, ha="center", va="center", fontsize=9, color="0.5")
    return None


if __name__ == "__main__":
    main()
