"""Benchmark harness: error metrics, the run classifier, the Pareto front, and the runners of the
accuracy matrix and the stability sweeps (driven by ``python -m benchmarks run``).

Error metrics (also defined in docs/benchmarks.md, 'Error metrics'):

- 2D dam break (Martin & Moyce 1952, n^2 = 2, a = 0.05715 m):
  ``front_rms`` = RMS over the measured points of (Z_sim - Z_exp) / Z_exp, Z = x_front / a at
  T = t sqrt(2 g / a) (x_front = the largest particle x); ``height_rms`` = RMS of (H_sim - H_exp) / H_exp,
  H = h / (2 a) at tau = t sqrt(g / a) (h: the water height at the back wall, gauge ``column_height``),
  points with tau <= the simulated time; ``error`` = (front_rms + height_rms) / 2. ``front_bias`` = mean
  signed relative front error (SPH runs ahead: no gate, no floor friction); ``front_bias_late`` and
  ``front_rms_late``: the same over the points at T >= 1.5 only. From the front read every sample
  (``front_series``): ``front_speed_ratio`` = the least-squares slope dZ/dT of the simulated front over
  1.5 <= T <= the last measured T, over the slope of the measured points there (the surge's speed, free of
  where it started); ``front_delay_T`` = the start delay Delta T >= 0 that best fits Z_sim(T - Delta T) to the
  measured points at T >= 1.5 (least squares of the relative error; ``front_delay_s`` the same in seconds),
  ``front_bias_late_delayed`` / ``front_rms_late_delayed`` the bias and RMS left after it. A front that runs
  at the measured speed but started early (the experiment's gate lift, Martin & Moyce 1952) shows a speed
  ratio near 1 and a small residual after the delay.
- SPHERIC Test 2 (Kleefsman et al. 2005): ``h_rms`` = mean over H1..H4 of RMS(h_sim - h_exp) / 0.55 m
  (a dry gauge reads 0), ``p_rms`` = RMS(p_sim - p_exp) / (rho0 g 0.55 m) at P1, both over the
  simulated window sampled every 10 ms, the measurement averaged over +-5 ms; ``error`` = (h_rms + p_rms) / 2.
  ``h_max`` = the largest of H1..H4's. P1 impact: ``p1_impact_t_s`` = the first time P1 reaches half the
  measured peak (linear interpolation between samples; the measurement's own, from its raw 1 kHz rows, in
  ``p1_impact_t_exp_s``), ``p1_impact_error`` = relative error of that time; ``p1_peak_error`` = relative error
  of the largest +-5 ms mean of P1 within 0.1 s after the impact against the measurement's largest +-5 ms mean
  there, both at the 10 ms sample times: the simulation's means from P1 read every 1 ms over 0.3-0.6 s (the
  impact; ``p1_fine``), as the measurement's from its 1 kHz rows (``p1_peak_instant_pa``: the largest single
  1 ms reading, for comparison; a WCSPH impact pressure rings at the acoustic period, ~0.3 ms at 0.012 m).
  Without fine samples (older records) the largest single 10 ms sample stands for the peak.
  ``p1_first_error`` / ``p1_after_error`` (issue 38, ``p1_phases``): the mean of P1 over the first 10 ms after
  the impact time (the arrival, one +-5 ms window) and over 40-140 ms after it (the quasi-steady load), each
  against the sensor's over the same span after its own impact time: which part of the signal a peak error is.
  ``p1_noise`` (issue 38): the pressure noise after the impact, ``pressure_noise`` of the 1 ms P1 reads over the
  20 ms from the simulated impact time: RMS(p - p_lp) / RMS(p_lp), p_lp = P1 low-passed at 200 Hz (zero-phase
  second-order Butterworth); the part of the signal above ~200 Hz (up to the 500 Hz of 1 ms reads) relative to
  the load itself. The sensor's own record over the same 20 ms reads ``p1_noise_exp``.
- Standing wave (2D, linear sloshing mode started from its velocity field; ``standing_wave``):
  ``decay_per_period`` = 1 - exp(-beta T) of a damped-sine fit c + A exp(-beta t) sin(w t + phi) to the
  amplitude signal, ``period_error`` = 2 pi / w over the linear-theory period (w^2 = g k tanh(k d)) - 1.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "benchmarks" / "data"
G = 9.81
A_MM = 0.05715  # Martin & Moyce column width a [m] (n^2 = 2)
SPHERIC_H0 = 0.55  # SPHERIC Test 2 water depth [m]
FRONT_LATE_T = 1.5  # front_bias_late: Martin & Moyce points at T >= this (past the start-up of the collapse)

# classifier bounds (docs/benchmarks.md, 'Run classes')
BOUNDS = dict(
    energy_growth=0.10,     # blown up: mechanical energy above its start by 10% of m g H
    escaped_fraction=0.01,  # blown up: more than 1% of the water outside the tank
    density_blowup=0.10,    # blown up: mean |rho/rho0 - 1| above 10%
    density_inaccurate=0.03,  # inaccurate: mean |rho/rho0 - 1| above 3% (WCSPH aims at ~1%)
    error_inaccurate=0.15,  # inaccurate: the case's error metric above 15%
)


# ----------------------------------------------------------------------------------- metrics ----
def martin_moyce(series: str) -> np.ndarray:
    """(time, value) rows of one series of benchmarks/data/martin_moyce_1952.csv."""
    rows = [l.split(",") for l in (DATA / "martin_moyce_1952.csv").read_text().splitlines()
            if l and not l.startswith("#") and not l.startswith("series")]
    return np.array([[float(t), float(v)] for s, t, v in rows if s == series])


def dam_break_times(a: float = A_MM, t_end: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Physical times [s] of the measured front (T) and height (tau) points, optionally cut at t_end."""
    tf = martin_moyce("front_n2_2")[:, 0] / math.sqrt(2 * G / a)
    th = martin_moyce("height_n2_2")[:, 0] / math.sqrt(G / a)
    if t_end is not None:
        tf, th = tf[tf <= t_end + 1e-12], th[th <= t_end + 1e-12]
    return tf, th


def front_speed_and_delay(times: np.ndarray, fronts: np.ndarray, a: float = A_MM, t_late: float = FRONT_LATE_T,
                          max_delay_T: float = 1.0) -> dict:
    """The surge's speed against the measured one and the start delay that best explains the rest (module
    docstring): ``times`` [s] and ``fronts`` x [m] read through the run (every few ms)."""
    ef = martin_moyce("front_n2_2")
    late = ef[ef[:, 0] >= t_late]
    T = np.asarray(times, float) * math.sqrt(2 * G / a)
    Z = np.asarray(fronts, float) / a
    out = {"front_speed_ratio": math.nan, "front_delay_T": math.nan, "front_delay_s": math.nan,
           "front_bias_late_delayed": math.nan, "front_rms_late_delayed": math.nan}
    ok = np.isfinite(Z)
    T, Z = T[ok], Z[ok]
    span = (T >= t_late) & (T <= late[-1, 0] + 1e-9)
    if len(late) < 2 or span.sum() < 3 or T[-1] < late[-1, 0] - 1e-9:
        return out
    out["front_speed_ratio"] = float(np.polyfit(T[span], Z[span], 1)[0] / np.polyfit(late[:, 0], late[:, 1], 1)[0])
    # Delta T on a grid of 0.001 (about 0.05 ms of the experiment's time), the sampled front interpolated
    shifts = np.arange(0.0, max_delay_T + 1e-12, 0.001)
    shifts = shifts[late[0, 0] - shifts >= T[0]]
    rel = np.array([(np.interp(late[:, 0] - d, T, Z) - late[:, 1]) / late[:, 1] for d in shifts])
    k = int(np.argmin(np.sqrt(np.mean(rel * rel, axis=1))))
    out.update(front_delay_T=float(shifts[k]), front_delay_s=float(shifts[k] / math.sqrt(2 * G / a)),
               front_bias_late_delayed=float(rel[k].mean()), front_rms_late_delayed=_rms(rel[k]))
    return out


def dam_break_errors(front: dict[float, float], height: dict[float, float], a: float = A_MM,
                     front_series: tuple | None = None) -> dict:
    """Errors of a 2D dam break against Martin & Moyce (n^2 = 2). ``front``/``height``: time [s] ->
    front position x [m] / water height at the back wall h [m] at the measured times; ``front_series``:
    (times [s], front x [m]) read through the run, for the speed and the start delay."""
    ef = martin_moyce("front_n2_2")
    eh = martin_moyce("height_n2_2")
    rf, rh = [], []
    for T, Z in ef:
        t = T / math.sqrt(2 * G / a)
        x = _lookup(front, t)
        if x is not None:
            rf.append((x / a - Z) / Z)
    for tau, H in eh:
        t = tau / math.sqrt(G / a)
        h = _lookup(height, t)
        if h is not None:
            h = 0.0 if not math.isfinite(h) else h
            rh.append((h / (2 * a) - H) / H)
    rf, rh = np.asarray(rf), np.asarray(rh)
    late = np.asarray([T >= FRONT_LATE_T for T, _ in ef if _lookup(front, T / math.sqrt(2 * G / a)) is not None], bool)
    out = {"front_rms": _rms(rf), "front_bias": float(rf.mean()) if len(rf) else math.nan,
           "front_bias_late": float(rf[late].mean()) if late.any() else math.nan, "front_rms_late": _rms(rf[late]),
           "front_points_late": int(late.sum()),
           "height_rms": _rms(rh), "height_bias": float(rh.mean()) if len(rh) else math.nan,
           "front_points": int(len(rf)), "height_points": int(len(rh))}
    parts = [v for v in (out["front_rms"], out["height_rms"]) if math.isfinite(v)]
    out["error"] = float(np.mean(parts)) if parts else math.nan
    if front_series is not None:
        out.update(front_speed_and_delay(*front_series, a=a))
    return out


def _lookup(d: dict[float, float], t: float, tol: float = 1e-9):
    for k, v in d.items():
        if abs(k - t) <= tol * max(1.0, abs(t)):
            return v
    return None


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(r)))) if len(r) else math.nan


def load_spheric() -> tuple[np.ndarray, np.ndarray]:
    """(water_level rows: t, H1..H4), (pressure rows: t, P1..P8) of SPHERIC Test 2."""
    d = DATA / "spheric_test2"
    return np.loadtxt(d / "water_level.dat", comments="#"), np.loadtxt(d / "pressure.dat", comments="#")


def _window_mean(tab: np.ndarray, col: int, t: np.ndarray, half: float = 0.005) -> np.ndarray:
    tt, vv = tab[:, 0], tab[:, col]
    c = np.concatenate([[0.0], np.cumsum(vv)])
    lo = np.searchsorted(tt, t - half)
    hi = np.searchsorted(tt, t + half)
    n = np.maximum(hi - lo, 1)
    return (c[hi] - c[lo]) / n


def spheric_errors(times: np.ndarray, gauges: dict[str, np.ndarray], rho0: float = 1000.0,
                   p1_fine: tuple | None = None) -> dict:
    """Errors of SPHERIC Test 2 gauges: ``times`` [s], ``gauges`` name -> readings (H1..H4 in m,
    NaN = dry; P1 in Pa); ``p1_fine``: (times, P1 readings) every 1 ms around the impact (module docstring)."""
    wl, pr = load_spheric()
    times = np.asarray(times, float)
    out = {}
    hs = []
    for i, name in enumerate(["H1", "H2", "H3", "H4"]):
        if name in gauges:
            sim = np.nan_to_num(np.asarray(gauges[name], float), nan=0.0)
            e = _rms((sim - _window_mean(wl, 1 + i, times)) / SPHERIC_H0)
            out[f"{name}_rms"] = e
            hs.append(e)
    out["h_rms"] = float(np.mean(hs)) if hs else math.nan
    out["h_max"] = float(np.max(hs)) if hs else math.nan
    if "P1" in gauges:
        sim = np.nan_to_num(np.asarray(gauges["P1"], float), nan=0.0)
        exp = _window_mean(pr, 1, times)
        out["p_rms"] = _rms((sim - exp) / (rho0 * G * SPHERIC_H0))
        out.update(p1_impact(times, sim, pr, p1_fine))
    else:
        out["p_rms"] = math.nan
    parts = [v for v in (out["h_rms"], out["p_rms"]) if math.isfinite(v)]
    out["error"] = float(np.mean(parts)) if parts else math.nan
    return out


def _first_crossing(t: np.ndarray, v: np.ndarray, level: float) -> float:
    """First time v reaches level (linear interpolation between samples); NaN if it never does."""
    i = int(np.argmax(v >= level))
    if v[i] < level:
        return math.nan
    if i == 0:
        return float(t[0])
    return float(t[i - 1] + (level - v[i - 1]) * (t[i] - t[i - 1]) / (v[i] - v[i - 1]))


def pressure_noise(t: np.ndarray, p: np.ndarray, t0: float, window: float = 0.02, cutoff_hz: float = 200.0) -> float:
    """Noise of a pressure signal after an impact (module docstring, ``p1_noise``): over [t0, t0 + window], the RMS
    of p minus its low-pass (zero-phase second-order Butterworth at ``cutoff_hz``, filtered over the whole
    series) over the RMS of that low-pass. Samples at a uniform rate (the median step) above 2 cutoff_hz; NaN
    when the rate is too low, the window has fewer than 5 samples or the low-pass is zero there."""
    from scipy.signal import butter, filtfilt

    t, p = np.asarray(t, float), np.nan_to_num(np.asarray(p, float), nan=0.0)
    if len(t) < 16 or not math.isfinite(t0):
        return math.nan
    step = float(np.median(np.diff(t)))
    fs = 1.0 / step if step > 0 else 0.0
    if fs <= 2.0 * cutoff_hz:
        return math.nan
    b, a = butter(2, cutoff_hz / (0.5 * fs))
    lp = filtfilt(b, a, p)
    w = (t >= t0 - 1e-12) & (t <= t0 + window + 1e-12)
    if w.sum() < 5:
        return math.nan
    ref = float(np.sqrt(np.mean(lp[w] ** 2)))
    return float(np.sqrt(np.mean((p[w] - lp[w]) ** 2)) / ref) if ref > 0 else math.nan


def p1_impact(times: np.ndarray, p1: np.ndarray, pr: np.ndarray, fine: tuple | None = None) -> dict:
    """SPHERIC Test 2 P1 impact time and peak against the measurement (module docstring). ``fine``: (times,
    P1) read every 1 ms around the impact: the impact time from them, and the peak as the largest +-5 ms mean
    at the 10 ms sample times, as the measurement's."""
    times, p1 = np.asarray(times, float), np.asarray(p1, float)
    peak_exp = float(pr[:, 1].max())
    t_exp = _first_crossing(pr[:, 0], pr[:, 1], 0.5 * peak_exp)
    ft = fp = None
    if fine is not None and len(fine[0]):
        ft, fp = np.asarray(fine[0], float), np.nan_to_num(np.asarray(fine[1], float), nan=0.0)
    if ft is not None:
        t_sim = _first_crossing(ft, fp, 0.5 * peak_exp)
    else:
        t_sim = _first_crossing(times, p1, 0.5 * peak_exp) if len(times) else math.nan
    out = {"p1_impact_t_exp_s": t_exp, "p1_impact_t_s": t_sim, "p1_impact_error": t_sim / t_exp - 1.0}
    if ft is not None:  # the noise after the impact, the simulation's and the sensor's (1 kHz rows)
        out["p1_noise"] = pressure_noise(ft, fp, t_sim)
        out["p1_noise_exp"] = pressure_noise(pr[:, 0], pr[:, 1], t_exp)
    w = (times >= t_exp - 0.02) & (times <= t_exp + 0.1)
    if w.any():
        pk_exp = float(_window_mean(pr, 1, times[w]).max())
        t0 = t_sim if math.isfinite(t_sim) else t_exp
        ws = (times >= t0 - 0.02) & (times <= t0 + 0.1)
        if ft is not None and ws.any():
            means = _window_mean(np.c_[ft, fp], 1, times[ws])
            pk = float(means.max())
            inside = (ft >= t0 - 0.02) & (ft <= t0 + 0.1)
            out["p1_peak_instant_pa"] = float(fp[inside].max()) if inside.any() else math.nan
        else:
            pk = float(p1[ws].max()) if ws.any() else math.nan
        out.update(p1_peak_pa=pk, p1_peak_exp_pa=pk_exp, p1_peak_error=pk / pk_exp - 1.0)
    if ft is not None and math.isfinite(t_sim) and math.isfinite(t_exp):
        out.update(p1_phases(ft, fp, t_sim, pr, t_exp))
    return out


P1_FIRST_S = 0.01  # the arrival: the first 10 ms after each one's impact time (one +-5 ms window)
P1_AFTER_S = (0.04, 0.14)  # the quasi-steady load after it: 40-140 ms after each one's impact time


def _mean_between(t: np.ndarray, p: np.ndarray, a: float, b: float) -> float:
    w = (t >= a - 1e-9) & (t < b - 1e-9)
    return float(np.mean(p[w])) if w.any() else math.nan


def p1_phases(ft: np.ndarray, fp: np.ndarray, t_sim: float, pr: np.ndarray, t_exp: float) -> dict:
    """Where a P1 peak error comes from (module docstring): the mean of P1 over the arrival (the first
    P1_FIRST_S after the impact time, the simulation's from its 1 ms reads and its own impact time, the sensor's
    likewise) and over the quasi-steady load after it (P1_AFTER_S after the impact time), each against the
    sensor's: ``p1_first_error``, ``p1_after_error`` (NaN where the reads do not cover the window)."""
    out = {}
    for key, (a, b) in (("first", (0.0, P1_FIRST_S)), ("after", P1_AFTER_S)):
        ms = _mean_between(ft, fp, t_sim + a, t_sim + b)
        me = _mean_between(pr[:, 0], pr[:, 1], t_exp + a, t_exp + b)
        if ft[-1] < t_sim + b - 2e-3:
            ms = math.nan
        out[f"p1_{key}_pa"], out[f"p1_{key}_exp_pa"] = ms, me
        out[f"p1_{key}_error"] = ms / me - 1.0 if math.isfinite(ms) and me > 0 else math.nan
    return out


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the non-dominated points (cost, error), both minimised, sorted by cost. Points with
    a non-finite coordinate are never on the front."""
    idx = [i for i, (c, e) in enumerate(points) if math.isfinite(c) and math.isfinite(e)]
    idx.sort(key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in idx:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def classify(rec: dict, bounds: dict | None = None) -> tuple[str, list[str]]:
    """'refused', 'blown_up', 'inaccurate' or 'stable', with the reasons. ``rec`` keys (all optional):
    refused (str), exception (str), finite (bool), energy_growth, escaped_fraction, density_error,
    error (the case's error metric), error_bound (overrides the default)."""
    b = dict(BOUNDS, **(bounds or {}))
    if rec.get("refused"):
        return "refused", [f"refused: {rec['refused']}"]
    why = []
    if rec.get("exception"):
        why.append(f"exception: {rec['exception']}")
    if rec.get("finite") is False:
        why.append("NaN/inf in the state")
    eg = rec.get("energy_growth")
    if eg is not None and (not math.isfinite(eg) or eg > b["energy_growth"]):
        why.append(f"energy growth {eg:.3g} > {b['energy_growth']:g}")
    ef = rec.get("escaped_fraction")
    if ef is not None and ef > b["escaped_fraction"]:
        why.append(f"{100 * ef:.1f}% of the water left the tank")
    de = rec.get("density_error")
    if de is not None and (not math.isfinite(de) or de > b["density_blowup"]):
        why.append(f"density error {de:.3g} > {b['density_blowup']:g}")
    if why:
        return "blown_up", why
    err, eb = rec.get("error"), rec.get("error_bound", b["error_inaccurate"])
    if err is not None and (not math.isfinite(err) or err > eb):
        why.append(f"error {err:.3g} > {eb:g}")
    if de is not None and de > b["density_inaccurate"]:
        why.append(f"density error {de:.3g} > {b['density_inaccurate']:g}")
    return ("inaccurate", why) if why else ("stable", [])


# ----------------------------------------------------------------------------------- scenes ----
def set_path(d: dict, path: str, value) -> dict:
    node = d
    keys = path.split(".")
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value
    return d


# method variants of the accuracy matrix: name -> dotted scene changes
VARIANTS = {
    "tait": {},
    "linear": {"fluid.eos.type": "linear"},
    # ghost steps at a Courant number of 0.125 (rockwave.sph.ghost.GHOST_CFL_MAX; at 0.25 the ghost pressure term
    # pumped energy into a splash on the GPU); the stability sweep's dt multiples are of this step
    "ghost": {"fluid.method": "ghost", "simulation.cfl_number": 0.125},
    "laplacian": {"fluid.viscosity.artificial_alpha": 0.0, "fluid.viscosity.laplacian_pa_s": 1.0e-3},
    "xsph": {"fluid.viscosity.xsph_epsilon": 0.05},
    "fixed_dt": {"simulation.time_step": "fixed"},  # dt_s set from the spacing (see scene_dict)
}
FIXED_COURANT = 0.375  # fixed step = 0.375 h / (c0 (1 + 0.6 alpha)): 1.5 x the CFL step at rest, under the 0.4 limit


def scene_dict(case: str, spacing: float, variant: dict, c0: float | None = None, strip: tuple = ()) -> dict:
    """Scene dict of a benchmark case ('dam_break_2d' or 'spheric') with a variant's changes. ``strip``:
    [fluid] keys of the scene file removed before the changes (the chart part removes the scene's own
    kernel choice, so that a formulation given as one key, e.g. fluid.fidelity, is not overridden by it)."""
    import rockwave

    name = {"dam_break_2d": "dam_break_2d.toml", "spheric": "dam_break_3d.toml"}[case]
    d = copy.deepcopy(rockwave.load_scene(ROOT / "scenes" / name).raw)
    for k in strip:
        d["fluid"].pop(k, None)
    d["fluid"]["spacing_m"] = spacing
    d["output"]["usd"] = ""
    d["output"].pop("reference", None)
    if c0 is not None:
        d["fluid"]["eos"]["speed_of_sound_m_s"] = c0
    for k, v in variant.items():
        set_path(d, k, v)
    if d["simulation"].get("time_step") == "fixed":
        c = d["fluid"]["eos"]["speed_of_sound_m_s"]
        alpha = d["fluid"].get("viscosity", {}).get("artificial_alpha", 0.0)
        h = spacing * d["fluid"].get("support_radius_ratio", 2.0) / 2
        d["simulation"]["dt_s"] = FIXED_COURANT * h / (c * (1 + 0.6 * alpha))
    return d


def build(case: str, d: dict, device: str):
    import rockwave

    return rockwave.Simulation(rockwave.parse_scene(d, f"{case}.toml", ROOT / "scenes"), device=device)


# ----------------------------------------------------------------------------------- running ---
@dataclass
class Health:
    """Running health record of a fluid run (energy, escape, density) for the classifier."""

    lo: np.ndarray
    hi: np.ndarray
    up: int
    mass: float
    rho0: float
    scale: float
    e0: float | None = None
    energy_growth: float = 0.0
    escaped_fraction: float = 0.0
    density_error: float = 0.0
    finite: bool = True
    samples: int = 0

    @staticmethod
    def of(sim) -> "Health":
        f = sim.fluid
        tank = sim.scene.tank
        dim = sim.scene.dim
        lo = np.asarray(tank.box_min_m, float) - f.spacing
        hi = np.asarray(tank.box_max_m, float) + f.spacing
        hi[dim - 1] = math.inf  # open top: a splash may rise; falling back in is fine
        x = sim.positions()
        height = float(x[:, dim - 1].max() - lo[dim - 1])
        return Health(lo, hi, dim - 1, f.fluid_mass, float(f.params.rest_density), f.fluid_mass * len(x) * G * height)

    def check(self, sim) -> bool:
        """Update from the current state; False when the run cannot go on (non-finite state)."""
        x, v = sim.positions(), sim.velocities()
        self.samples += 1
        if not (np.isfinite(x).all() and np.isfinite(v).all()):
            self.finite = False
            return False
        e = 0.5 * self.mass * float((v * v).sum()) + self.mass * G * float((x[:, self.up] - self.lo[self.up]).sum())
        if self.e0 is None:
            self.e0 = e
        self.energy_growth = max(self.energy_growth, (e - self.e0) / self.scale)
        out = np.any((x < self.lo) | (x > self.hi), axis=1)
        self.escaped_fraction = max(self.escaped_fraction, float(out.mean()))
        rho = sim.densities()[: len(x)]
        de = float(np.mean(np.abs(rho / self.rho0 - 1.0))) if len(rho) else 0.0
        self.density_error = max(self.density_error, de if math.isfinite(de) else math.inf)
        return math.isfinite(de) and self.energy_growth < 10.0 and self.escaped_fraction < 0.5

    def record(self) -> dict:
        return {"finite": self.finite, "energy_growth": self.energy_growth, "escaped_fraction": self.escaped_fraction,
                "density_error": self.density_error}


class Clock:
    """Wall-clock time spent advancing (synchronised), excluding the sampling reads."""

    def __init__(self, device: str):
        self.device, self.seconds = device, 0.0

    def run(self, fn):
        import warp as wp

        wp.synchronize_device(self.device)
        t = time.perf_counter()
        fn()
        wp.synchronize_device(self.device)
        self.seconds += time.perf_counter() - t


def _advance_to(sim, t: float, dt: float | None) -> None:
    """Advance to time t: sim.advance (the scene's stepping), or steps of a forced dt (the stability
    sweep; sim.step(dt) bypasses the scene's fixed-dt limit check) with a shorter last step."""
    if dt is None:
        if t - sim.time > 1e-12:
            sim.advance(t - sim.time)
        return
    while t - sim.time > 1e-12:
        sim.step(min(dt, t - sim.time))


def run_dam_break(device: str, spacing: float, variant: dict, t_end: float, dt: float | None = None,
                  dt_multiple: float | None = None, c0: float | None = None, sample_dt: float = 0.0025,
                  strip: tuple = ()) -> dict:
    """One 2D dam break: errors against Martin & Moyce, wall time per simulated second, health record.
    ``dt_multiple``: step = this x the scene's initial CFL step (forced; the stability sweep)."""
    from rockwave.base.errors import SimulationError
    rec: dict = {"case": "dam_break_2d", "spacing_m": spacing}
    try:
        sim = build("dam_break_2d", scene_dict("dam_break_2d", spacing, variant, c0, strip), device)
    except Exception as e:  # SceneError: a refused set-up
        rec["refused"] = str(e).splitlines()[-1][:200]
        return rec
    rec["particles"] = sim.n_fluid
    rec["fluid"] = fluid_settings(sim)
    rec["cfl_dt_s"] = sim.dt
    if dt_multiple is not None:
        dt = dt_multiple * sim.dt
    rec["dt_s"] = dt if dt is not None else sim.dt
    health = Health.of(sim)
    health.check(sim)
    tf, th = dam_break_times(t_end=t_end)
    ts = np.unique(np.round(np.concatenate([tf, th, np.arange(sample_dt, t_end + 1e-12, sample_dt)]), 12))
    front, height, series = {}, {}, []
    clock = Clock(sim.device)
    steps0 = sim.steps
    try:
        for t in ts:
            clock.run(lambda: _advance_to(sim, float(t), dt))
            if not health.check(sim):
                break
            x_front = float(sim.positions()[:, 0].max())
            series.append((float(t), x_front))
            if np.any(np.isclose(t, tf, rtol=0, atol=1e-12)):
                front[float(tf[np.argmin(np.abs(tf - t))])] = x_front
            if np.any(np.isclose(t, th, rtol=0, atol=1e-12)):
                height[float(th[np.argmin(np.abs(th - t))])] = sim.gauges().get("column_height", math.nan)
    except (SimulationError, ValueError, FloatingPointError) as e:
        rec["exception"] = str(e).splitlines()[0][:200]
    rec.update(health.record())
    rec["simulated_s"] = sim.time
    rec["steps"] = sim.steps - steps0
    rec["wall_s"] = clock.seconds
    rec["wall_per_sim_s"] = clock.seconds / sim.time if sim.time > 0 else math.nan
    if health.finite and not rec.get("exception") and sim.time >= t_end - 1e-9:
        ts_, xs_ = np.array(series).T
        rec.update(dam_break_errors(front, height, front_series=(ts_, xs_)))
    else:
        rec["error"] = math.nan
    return rec


def run_spheric(device: str, spacing: float, variant: dict, t_end: float, sample_dt: float = 0.01,
                strip: tuple = ()) -> dict:
    """One SPHERIC Test 2 run: gauge errors, wall time per simulated second, health record."""
    from rockwave.base.errors import SimulationError
    rec: dict = {"case": "spheric", "spacing_m": spacing}
    try:
        sim = build("spheric", scene_dict("spheric", spacing, variant, strip=strip), device)
    except Exception as e:
        rec["refused"] = str(e).splitlines()[-1][:200]
        return rec
    rec["particles"] = sim.n_fluid
    rec["fluid"] = fluid_settings(sim)
    rec["dt_s"] = sim.dt
    health = Health.of(sim)
    ts = np.arange(sample_dt, t_end + 1e-9, sample_dt)
    g: dict[str, list] = {n: [] for n in sim.gauge_names}
    # P1 every 1 ms over the impact (0.3-0.6 s), for its +-5 ms means (p1_impact)
    t_all = np.unique(np.round(np.concatenate([ts, np.arange(0.3, min(0.6, t_end) + 1e-9, 0.001)]), 9))
    fine_t, fine_p = [], []
    clock = Clock(sim.device)
    steps0 = sim.steps
    try:
        for t in t_all:
            clock.run(lambda: _advance_to(sim, float(t), None))
            coarse = bool(np.isclose(t, ts, rtol=0, atol=1e-9).any())
            if coarse and not health.check(sim):
                break
            r = sim.gauges()
            if 0.3 - 1e-9 <= t <= 0.6 + 1e-9 and "P1" in r:
                fine_t.append(float(t))
                fine_p.append(r["P1"])
            if coarse:
                for n in g:
                    g[n].append(r.get(n, math.nan))
    except (SimulationError, ValueError) as e:
        rec["exception"] = str(e).splitlines()[0][:200]
    rec.update(health.record())
    rec["simulated_s"] = sim.time
    rec["steps"] = sim.steps - steps0
    rec["wall_s"] = clock.seconds
    rec["wall_per_sim_s"] = clock.seconds / sim.time if sim.time > 0 else math.nan
    if health.finite and not rec.get("exception") and len(g.get("H1", [])) == len(ts):
        rec.update(spheric_errors(ts, {k: np.asarray(v) for k, v in g.items()}, p1_fine=(fine_t, fine_p) if fine_t else None))
        rec["p1_fine"] = {"t": np.round(fine_t, 4).tolist(), "P1": np.round(np.asarray(fine_p, float), 1).tolist()}
        rec["series"] = {"t": ts.round(4).tolist(), **{k: np.round(np.asarray(v, float), 5).tolist() for k, v in g.items()}}
    else:
        rec["error"] = math.nan
    return rec


# ---------------------------------------------------------------------------- standing wave ----
FORMULATION_KEYS = ("kernel", "support_radius_ratio", "density", "density_diffusion", "pressure_force", "fidelity",
                    "boundary", "density_floor", "gradient_correction", "particle_shifting", "density_diffusion_form",
                    "shifting_correction", "density_diffusion_renormalised", "wall_work")


def fluid_settings(sim) -> dict:
    """The [fluid] formulation keys the simulation was built with (defaults filled in by the loader): a
    record of what a variant's changes gave."""
    f = sim.scene.fluid if isinstance(sim.scene.fluid, dict) else {}
    out = {k: f[k] for k in FORMULATION_KEYS if k in f}
    out["cfl_number"] = sim.scene.simulation.cfl_number  # the step's Courant number (0.25 before 2026-11-25)
    return out


def linear_wave(depth: float, kh: float, g: float = G) -> tuple[float, float]:
    """(k, omega) of a linear gravity wave with k d = kh: omega^2 = g k tanh(k d)."""
    k = kh / depth
    return k, math.sqrt(g * k * math.tanh(kh))


def standing_wave_dict(layers: int, variant: dict | None = None, depth: float = 0.2, kh: float = 1.5, mode: int = 2,
                       c0: float = 12.0) -> dict:
    """Scene dict of the standing-wave tank: water ``depth`` deep, ``layers`` particles per depth, in a tank of
    boundary particles mode x half a wavelength long (mode 1: the first sloshing mode, eta = a cos(kx), crests
    at the two end walls; mode 2: one wavelength, tests/test_standing_wave.py); c0 m/s, no viscosity; a
    variant's dotted changes applied last (the [fluid] section sets no kernel of its own)."""
    k, _ = linear_wave(depth, kh)
    L = mode * math.pi / k
    d = {"simulation": {"dimension": 2, "duration_s": 10.0},
         "fluid": {"spacing_m": depth / layers, "eos": {"speed_of_sound_m_s": c0},
                   "regions": [{"box_min_m": [0.0, 0.0], "box_max_m": [L, depth]}]},
         "tank": {"box_min_m": [0.0, 0.0], "box_max_m": [L, depth + 0.3]}}
    for key, v in (variant or {}).items():
        set_path(d, key, v)
    return d


def standing_wave(device: str, layers: int, variant: dict | None = None, periods: float = 3, a: float = 0.02,
                  depth: float = 0.2, kh: float = 1.5, mode: int = 2, c0: float = 12.0, samples_per_period: int = 40,
                  column_m: float = 0.1, signal: str = "columns") -> dict:
    """Run the standing wave of ``standing_wave_dict``, started at eta = 0 with the linear standing-wave
    velocity of eta = a cos(kx) sin(wt): u = -a w cosh(k(z+d))/sinh(kd) sin(kx), w_z = a w sinh(k(z+d))/sinh(kd)
    cos(kx). The amplitude signal, sampled ``samples_per_period`` times a period: ``signal = "columns"`` (the
    test's): (eta at the wall x = 0 - eta at the first opposite crest x = pi/k) / 2, eta the water depth from the
    particle volumes m/rho_i in a ``column_m`` wide column (at the end wall for mode 1), minus d; steps of
    spacing^2 / column_m as particles cross a column's edge, a large share of a at a few particles per depth.
    ``"projection"``: the mode's amplitude (2/L) sum_i (m/rho_i) cos(k x_i) = (2/L) int eta cos(kx) dx (the
    still water's part integrates to zero), a sum over every particle without edges. Returns the samples (t, signal), the amplitude of
    each whole period (first-harmonic least-squares fit at the linear-theory frequency, as the test asserts),
    the damped-sine fit's decay_per_period and period_error, and the cost (wall seconds spent advancing,
    synchronised; steps; particles). A scene the loader refuses raises its SceneError."""
    import rockwave

    sim = rockwave.Simulation(rockwave.parse_scene(standing_wave_dict(layers, variant, depth, kh, mode, c0)), device=device)
    k, om = linear_wave(depth, kh)
    T, L = 2 * math.pi / om, mode * math.pi / k
    nf = sim.n_fluid
    x = sim.positions()
    v = sim.state.v.numpy().copy()
    z = x[:, 1]
    v[:nf, 0] = -a * om * np.cosh(k * z) / np.sinh(k * depth) * np.sin(k * x[:, 0])
    v[:nf, 1] = a * om * np.sinh(k * z) / np.sinh(k * depth) * np.cos(k * x[:, 0])
    sim.state.v.assign(v)
    m, w = sim.fluid.fluid_mass, column_m
    clock = Clock(sim.device)
    steps0 = sim.steps
    ts, eta, noise, wave_ke = [], [], [], []
    finite, rho0, dens_err, speed = True, float(sim.fluid.params.rest_density), 0.0, 0.0
    band = 2.0 * sim.fluid.params.H  # the particle-scale band: below twice the kernel support
    while sim.time < periods * T - 1e-9:
        clock.run(lambda: sim.advance(min(T / samples_per_period, periods * T - sim.time)))
        xx, rho = sim.positions(), sim.densities()
        if not (np.isfinite(xx).all() and np.isfinite(rho).all()):
            finite = False
            break
        vv = sim.velocities()
        noise.append(particle_scale_kinetic_energy(xx, vv, m, rho, band, 2))
        wave_ke.append(0.5 * m * float(np.sum(vv ** 2)))
        dens_err = max(dens_err, float(np.mean(np.abs(rho / rho0 - 1.0))))
        speed = max(speed, float(np.sqrt((sim.velocities() ** 2).sum(axis=1)).max()))
        if signal == "projection":
            eta.append(4.0 / L * np.sum(m / rho * np.cos(k * xx[:, 0])))  # twice the amplitude, as the columns'
        else:
            wall = xx[:, 0] < w
            opp = xx[:, 0] > L - w if mode == 1 else np.abs(xx[:, 0] - math.pi / k) < 0.5 * w
            eta.append((np.sum(m / rho[wall]) - np.sum(m / rho[opp])) / w)
        ts.append(sim.time)
    ts, eta = np.asarray(ts), np.asarray(eta)
    amps = []
    for p in range(int(math.floor(periods + 1e-9))):
        sl = (ts > p * T + 1e-9) & (ts <= (p + 1) * T + 1e-9)
        if sl.sum() < 4:
            break
        A = np.c_[np.ones(sl.sum()), np.cos(om * ts[sl]), np.sin(om * ts[sl])]
        c = np.linalg.lstsq(A, eta[sl], rcond=None)[0]
        amps.append(math.hypot(c[1], c[2]) / 2)
    rec = {"particles": nf, "spacing_m": depth / layers, "layers": layers, "depth_m": depth, "kh": kh, "mode": mode,
           "c0_m_s": c0, "amplitude_m": a, "signal": signal, "period_theory_s": T, "finite": finite,
           "density_error": dens_err, "max_speed_m_s": speed,
           "fluid": fluid_settings(sim),
           "simulated_s": sim.time, "steps": sim.steps - steps0, "wall_s": clock.seconds,
           "wall_per_sim_s": clock.seconds / sim.time if sim.time > 0 else math.nan, "amplitudes_m": amps,
           "t": ts, "signal_m": eta / 2, "noise_ke_j": np.asarray(noise), "kinetic_j": np.asarray(wave_ke),
           "noise_growth_per_period": noise_growth_per_period(ts, np.asarray(noise), T) if finite else math.nan,
           "noise_share_end": float(np.mean(noise[-samples_per_period:]) / max(np.mean(wave_ke[-samples_per_period:]), 1e-30))
           if finite and noise else math.nan}
    rec.update(damped_sine_fit(ts, eta / 2, om) if finite and len(ts) >= 8 and sim.time >= 0.99 * T else
               {"decay_per_period": math.nan, "period_error": math.nan})
    return rec


def particle_scale_kinetic_energy(x: np.ndarray, v: np.ndarray, mass: float, rho: np.ndarray, radius: float,
                                  dim: int) -> float:
    """Kinetic energy in the particle-scale band: 1/2 sum_i m |v_i - <v>_i|^2, <v>_i the Shepard average of the
    velocity over the fluid particles within ``radius`` (Wendland C2 weights, volumes m/rho_j; the resolved flow at
    that scale, taken as twice the kernel support). A smooth flow has almost none (a sine of wavelength lambda loses
    ~(2 pi radius / lambda)^2 / 10 of its amplitude to the average); disordered particles and acoustic noise at the
    particle scale put their energy here. 2D: J per metre of depth (m the particle mass per metre)."""
    from scipy.spatial import cKDTree

    x, v = np.asarray(x, float)[:, :dim], np.asarray(v, float)[:, :dim]
    pairs = cKDTree(x).query_pairs(radius, output_type="ndarray")
    i = np.r_[pairs[:, 0], pairs[:, 1], np.arange(len(x))]
    j = np.r_[pairs[:, 1], pairs[:, 0], np.arange(len(x))]
    q = np.linalg.norm(x[i] - x[j], axis=1) / radius
    w = (1.0 - q) ** 4 * (1.0 + 4.0 * q) * (mass / np.asarray(rho, float)[j])  # Wendland C2 shape x volume
    den = np.bincount(i, w, len(x))
    mean = np.stack([np.bincount(i, w * v[j, c], len(x)) for c in range(dim)], axis=1) / den[:, None]
    return float(0.5 * mass * np.sum((v - mean) ** 2))


def noise_growth_per_period(t: np.ndarray, e: np.ndarray, period: float, skip: float = 1.0) -> float:
    """Growth of a positive series per period after the first ``skip`` periods: exp(slope of log e against t/T) - 1
    (a least-squares fit; 0: steady, > 0: growing)."""
    t, e = np.asarray(t, float), np.asarray(e, float)
    sel = (t >= skip * period) & (e > 0)
    if sel.sum() < 4:
        return math.nan
    slope = np.polyfit(t[sel] / period, np.log(e[sel]), 1)[0]
    return float(math.exp(slope) - 1.0)


def damped_sine_fit(t: np.ndarray, y: np.ndarray, om0: float) -> dict:
    """Fit y = c + A exp(-beta t) sin(w t + phi) (start at w = om0); decay_per_period = 1 - exp(-beta 2pi/w),
    period_error = om0 / w - 1, amplitude0_m = |A|, fit_residual = RMS residual / |A|."""
    from scipy.optimize import curve_fit

    t, y = np.asarray(t, float), np.asarray(y, float)

    def f(t, c, A, beta, w, phi):
        return c + A * np.exp(-beta * t) * np.sin(w * t + phi)

    a0 = max(float(np.abs(y).max()), 1e-12)
    best, p = math.inf, None
    for s in (1.0, 0.8, 1.25):  # starting frequencies: the best fit of three
        try:
            q, _ = curve_fit(f, t, y, p0=(0.0, a0, 0.0, s * om0, 0.0), maxfev=20000)
        except (RuntimeError, ValueError, OverflowError):
            continue
        res = float(np.mean((f(t, *q) - y) ** 2))
        if math.isfinite(res) and res < best and q[3] > 0.2 * om0:
            best, p = res, q
    if p is None:
        return {"decay_per_period": math.nan, "period_error": math.nan}
    c, A, beta, w, phi = p
    if A < 0:  # the same curve with phi + pi
        A = -A
    T = 2 * math.pi / abs(w)
    return {"decay_per_period": float(1.0 - math.exp(min(-beta * T, 50.0))), "period_error": float(om0 / abs(w) - 1.0),
            "amplitude0_m": float(A), "fit_residual": float(np.sqrt(np.mean((f(t, *p) - y) ** 2)) / max(A, 1e-12))}


# ------------------------------------------------------------------------------ block sweep ----
def block_stack_dict(k_n: float, n: int = 3, size: float = 0.5, gap: float = 0.001) -> dict:
    """n rock cubes stacked on a fixed base, joints open by ``gap``; contact stiffness k_n per point."""
    mat = {"friction_angle_deg": 30.0, "normal_stiffness_n_m": k_n}
    blocks = [{"name": "base", "shape": "box", "size_m": [3.0, 3.0, 0.2], "position_m": [0.0, 0.0, -0.1],
               "kind": "fixed", "material": dict(mat)}]
    for i in range(n):
        blocks.append({"name": f"rock{i}", "shape": "box", "size_m": [size] * 3,
                       "position_m": [0.0, 0.0, size / 2 + gap + i * (size + gap)], "density_kg_m3": 2600.0,
                       "material": dict(mat)})
    return {"simulation": {"dimension": 3, "duration_s": 1.0}, "blocks": blocks, "output": {"usd": ""}}


def run_block_stack(device: str, k_n: float, dt_multiple: float, t_end: float, n: int = 3, size: float = 0.5) -> dict:
    """Stack of n cubes settling under gravity at dt = dt_multiple x the critical DDA step.
    Classifier record: NaN, energy growth, a block leaving (> size from its column), and the
    error = the largest of sag / (1% of the block size), lateral drift / 1 mm and final kinetic energy /
    (1% of m g size), inaccurate above 1."""
    import rockwave
    from rockwave.base.errors import SimulationError
    rec: dict = {"case": "block_stack", "k_n": k_n, "dt_multiple": dt_multiple}
    try:
        sim = rockwave.Simulation(rockwave.parse_scene(block_stack_dict(k_n, n, size), "block_stack.toml", ROOT), device=device)
    except Exception as e:
        rec["refused"] = str(e).splitlines()[-1][:200]
        return rec
    crit = sim.block_solver.critical_dt()
    dt = dt_multiple * crit
    rec.update(critical_dt_s=crit, dt_s=dt, blocks=n)
    m = float(sim.blocks.np["mass"][1])
    x0 = sim.block_positions()[1:].copy()
    scale = n * m * G * n * size
    e0 = sum(m * G * x0[:, 2]) + sim.kinetic_energy()
    growth, finite, drift = 0.0, True, 0.0
    clock = Clock(sim.device)
    nsample = 20
    try:
        for k in range(1, nsample + 1):
            t = t_end * k / nsample
            clock.run(lambda: _block_advance(sim, t, dt))
            x = sim.block_positions()[1:]
            if not np.isfinite(x).all():
                finite = False
                break
            e = float(m * G * x[:, 2].sum()) + sim.kinetic_energy()
            growth = max(growth, (e - e0) / scale)
            drift = max(drift, float(np.abs(x[:, :2] - x0[:, :2]).max()))
            if drift > size:
                break
    except ValueError as e:  # BlockSolver.step refuses dt above the critical step
        rec["refused"] = str(e).splitlines()[0][:200]
        return rec
    except SimulationError as e:
        rec["exception"] = str(e).splitlines()[0][:200]
    rec["wall_s"] = clock.seconds
    rec["finite"] = finite
    rec["energy_growth"] = growth
    rec["escaped_fraction"] = 1.0 if drift > size else 0.0
    if finite:
        top = sim.block_positions()[-1, 2]
        ideal = size / 2 + (n - 1) * size  # touching, no overlap
        rec["sag_m"] = float(ideal - top)
        rec["drift_m"] = drift
        rec["final_ke_j"] = sim.kinetic_energy()
        # inaccurate: sag deeper than 1% of the block size, lateral drift above 1 mm, or still moving
        rec["error"] = max(rec["sag_m"] / (0.01 * size), drift / 1e-3, rec["final_ke_j"] / (0.01 * m * G * size))
        rec["error_bound"] = 1.0
    return rec


def _block_advance(sim, t: float, dt: float) -> None:
    while t - sim.time > 1e-12:
        sim.step(min(dt, t - sim.time))
