"""SPlisHSPlasH side by side: the 3D Martin & Moyce dam break (n^2 = 2 column a x 2a, a slab of depth a
between walls) with WCSPH, the cubic spline kernel, the same particles, support radius, EOS and fixed time
step in both codes, on the CPU. Reports the throughput ratio and the front error of both.

SPlisHSPlasH (pip install pysplishsplash==2.19.0, MIT; extra 'peers') runs in a child process with
LD_PRELOAD=/lib/x86_64-linux-gnu/libGLdispatch.so.0 (its wheel's GL library clashes with the system's).
Its scene JSON is generated here (splash_scene). What is matched, and how:

- Particles: the same lattice. SPlisHSPlasH's FluidBlocks sampler (SimulatorBase::createFluidBlocks, dense
  mode 0) puts round(L / 2r) - 1 particles per axis, the first at min + 2r: a block [0, a] at r = spacing/2
  gets 9 x 19 x 9 = 1539 particles at spacing, 2 spacing, ... where rockwave's cell-centred lattice
  (rockwave/build/sampling.py) gets 10 x 20 x 10 = 2000 at spacing/2, 3 spacing/2, .... The block is therefore
  given as [-spacing/2, a + spacing/2] (and 2a + spacing/2 in height): round(11) - 1 = 10 particles per a,
  the first at +spacing/2, i.e. exactly rockwave's positions (checked: the worker reports the bounds).
  The wall: rockwave's boundary layers continue the fluid lattice outside the tank face (the first at
  -spacing/2, one spacing from the first fluid layer). SPlisHSPlasH samples Akinci 2012 boundary particles
  (boundaryHandlingMethod 0) on the tank mesh (UnitBox) surface. Measured at the first step (the worker
  records the start-up): with the mesh on the tank face (fluid r from the sheet) the density reaches
  1.29 rho0 and the run blows up; with the mesh grown by half a spacing (sheet one spacing from the
  fluid, where rockwave's first boundary layer lies) 1.126 rho0 in the tank corner and 28% of the
  particles above 1.02 rho0 along the walls: a pressure burst throws the column forward (front error
  0.85); grown by one spacing on every side (sheet 1.5 spacings from the fluid) every particle starts at
  rho <= rho0 and at rest. So its tank mesh is the tank grown by one spacing on every side: its walls
  sit about half a spacing further out than rockwave's (front error 0.049 there; 0.109 with the sheet
  two spacings away).
- Kernel: cubic spline for values and gradients (kernel = gradKernel = 0), support 4 r = 2 x spacing
  (rockwave kernel 'cubic_spline', support_radius_ratio 2).
- EOS: SPlisHSPlasH's WCSPH (TimeStepWCSPH.cpp) computes p = stiffness ((rho/rho0)^exponent - 1) after
  clamping rho >= rho0 (so p >= 0); rockwave's Tait is p = B ((rho/rho0)^gamma - 1) with
  B = c0^2 rho0 / gamma and negative pressure clipped (clamp_negative_pressure, default true). So
  stiffness = B = c0^2 rho0 / 7 and exponent = gamma = 7 give the same EOS.
- Density: SPlisHSPlasH's WCSPH sums density (rho_i = sum m_j W_ij + boundary); rockwave runs twice:
  with the same summation density (the matched run that the ratio uses) and with its default
  continuity density (reported as rockwave_continuity).
- Time step: fixed, the same (cflMethod 0, timeStepSize = rockwave dt_s = 0.25 spacing / c0).
- Viscosity: rockwave Monaghan artificial alpha 0.05; SPlisHSPlasH standard viscosity (viscosityMethod 1,
  Viscosity_Standard.cpp: a_i += 2(d+2) nu sum m_j/rho_j (v_ij . x_ij)/(r^2 + 0.01 H^2) gradW) with the
  kinematic viscosity that Monaghan's term equals, nu = alpha c0 h / (2(d+2)) = alpha c0 h / 10 in 3D
  (h = smoothing length = spacing). Left different: rockwave's term acts only on approaching pairs, and
  SPlisHSPlasH puts no viscosity at the walls (viscosityBoundary 0).
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import harness as H
from benchmarks.peers.front import bulk_front

PRELOAD = "/lib/x86_64-linux-gnu/libGLdispatch.so.0"
TANK = (0.35, 0.2)  # tank length (x) and wall height [m], as scenes/dam_break_2d.toml
RHO0 = 1000.0
GAMMA = 7.0
ALPHA = 0.05  # rockwave's artificial viscosity in both runs (its dam-break default)


def available() -> tuple[bool, str]:
    if importlib.util.find_spec("pysplishsplash") is None:
        return False, "pysplishsplash is not installed (pip install pysplishsplash==2.19.0; optional extra 'peers')"
    return True, ""


def unit_box() -> str:
    p = Path(sys.prefix) / "bin" / "data" / "models" / "UnitBox.obj"
    return str(p)


def splash_scene(spacing: float, c0: float, dt: float, a: float = H.A_MM, stiffness: float | None = None,
                 alpha: float = 0.05) -> dict:
    """SPlisHSPlasH scene (y up): tank [0, 0.35] x [0, 0.2] x [0, a], column [0, a] x [0, 2a] x [0, a] on
    rockwave's lattice (the block is padded by half a spacing: see the module docstring)."""
    L, Ht = TANK
    w = a
    e = spacing / 2
    return {
        "Configuration": {
            "particleRadius": spacing / 2, "simulationMethod": 0, "gravitation": [0, -H.G, 0],
            "timeStepSize": dt, "cflMethod": 0, "cflMaxTimeStepSize": dt, "numberOfStepsPerRenderUpdate": 1,
            "kernel": 0, "gradKernel": 0, "boundaryHandlingMethod": 0, "enableZSort": False,
            "enableVTKExport": False, "enablePartioExport": False,
            # 2.19.0 reads the WCSPH parameters from this sub-block (flat "stiffness" keys stay at the default 50:
            # measured, the worker reports the values in use)
            "WCSPH": {"stiffness": stiffness or tait_b(c0), "exponent": GAMMA},
        },
        # "viscosity" here is not read by 2.19.0's loader (stays 0.01): the worker sets it (splash_worker.py)
        "Materials": [{"id": "Fluid", "density0": RHO0, "viscosityMethod": 1, "viscosity": splash_viscosity(alpha, c0, spacing),
                       "viscosityBoundary": 0.0}],
        "RigidBodies": [{
            "geometryFile": unit_box(), "translation": [L / 2, Ht / 2, w / 2], "rotationAxis": [1, 0, 0],
            "rotationAngle": 0, "scale": [L + 2 * spacing, Ht + 2 * spacing, w + 2 * spacing], "isDynamic": False,
            "isWall": True, "mapInvert": True,
            "mapThickness": 0.0, "mapResolution": [40, 30, 15], "samplingMode": 1,
        }],
        "FluidBlocks": [{"denseMode": 0, "start": [-e, -e, -e], "end": [a + e, 2 * a + e, w + e], "translation": [0, 0, 0],
                         "scale": [1, 1, 1]}],
    }


def tait_b(c0: float) -> float:
    """rockwave's Tait B = c0^2 rho0 / gamma = SPlisHSPlasH's WCSPH stiffness (module docstring)."""
    return c0 * c0 * RHO0 / GAMMA


def splash_viscosity(alpha: float, c0: float, spacing: float) -> float:
    """Kinematic viscosity nu of SPlisHSPlasH's standard viscosity equal to Monaghan's artificial
    viscosity alpha: nu = alpha c0 h / (2 (d + 2)), d = 3, h = smoothing length = spacing (support / 2)."""
    return alpha * c0 * spacing / 10.0


def rockwave_scene(spacing: float, c0: float, dt: float, a: float = H.A_MM, density: str = "summation") -> dict:
    L, Ht = TANK
    return {
        "simulation": {"dimension": 3, "duration_s": 1.0, "time_step": "fixed", "dt_s": dt},
        "fluid": {"spacing_m": spacing, "kernel": "cubic_spline", "support_radius_ratio": 2.0, "rest_density_kg_m3": RHO0,
                  "density": density, "clamp_negative_pressure": True, "pressure_force": "momentum",
                  "eos": {"type": "tait", "speed_of_sound_m_s": c0, "gamma": GAMMA},
                  "viscosity": {"artificial_alpha": ALPHA},
                  "regions": [{"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [a, a, 2 * a]}]},
        "tank": {"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [L, a, Ht]},
        "output": {"usd": ""},
    }


def front_errors(front: dict[float, float], a: float = H.A_MM) -> dict:
    """RMS and mean relative front error against Martin & Moyce n^2 = 2 at the measured times present."""
    r = []
    for T, Z in H.martin_moyce("front_n2_2"):
        t = T / math.sqrt(2 * H.G / a)
        x = H._lookup(front, t, 1e-6)
        if x is not None:
            r.append((x / a - Z) / Z)
    r = np.asarray(r)
    return {"front_rms": H._rms(r), "front_bias": float(r.mean()) if len(r) else math.nan, "front_points": int(len(r))}


def run_rockwave(spacing: float, c0: float, dt: float, t_end: float, device: str = "cpu", density: str = "summation") -> dict:
    import rockwave

    def scene():
        return rockwave.parse_scene(rockwave_scene(spacing, c0, dt, density=density), "mm3d.toml", H.ROOT)

    sim = rockwave.Simulation(scene(), device=device)
    tf, _ = H.dam_break_times(t_end=t_end)
    front, front_max = {}, {}
    clock = H.Clock(sim.device)
    for _ in range(3):  # kernel loads
        sim.step(dt)
    sim2 = rockwave.Simulation(scene(), device=device)
    x0 = sim2.positions()[: sim2.n_fluid]
    steps = 0
    for t in tf:
        n0 = sim2.steps
        clock.run(lambda: H._advance_to(sim2, float(t), dt))
        steps += sim2.steps - n0
        front[float(t)] = bulk_front(sim2.positions(), spacing)
        front_max[float(t)] = float(sim2.positions()[:, 0].max())
    nb = float(np.mean(sim2.fluid_solver.neighbour_counts(sim2.state)))
    d = sim2.densities()[: sim2.n_fluid]
    return {"particles": sim2.n_fluid, "boundary_particles": sim2.fluid.n_boundary, "density_method": density,
            "initial_bounds": [x0.min(axis=0).tolist(), x0.max(axis=0).tolist()], "steps": steps, "wall_s": clock.seconds,
            "s_per_step": clock.seconds / max(steps, 1), "neighbours": nb, "dt_s": dt,
            "density_error_mean": float(np.mean(np.abs(d / 1000.0 - 1.0))), **front_errors(front),
            "front_of_any_particle": {k: v for k, v in (("rms", front_errors(front_max)["front_rms"]),
                                                        ("bias", front_errors(front_max)["front_bias"]))}}


def run_splash(spacing: float, c0: float, dt: float, t_end: float, timeout: float = 900, stiffness: float | None = None) -> dict:
    tf, _ = H.dam_break_times(t_end=t_end)
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "splash_dam_break.json"
        scene.write_text(json.dumps(splash_scene(spacing, c0, dt, stiffness=stiffness), indent=1))
        out = Path(tmp) / "result.json"
        env = dict(os.environ, LD_PRELOAD=PRELOAD)
        cmd = [sys.executable, str(Path(__file__).with_name("splash_worker.py")), str(scene), str(out), f"{t_end:.6f}",
               ",".join(f"{t:.9f}" for t in tf), json.dumps({"viscosity": splash_viscosity(ALPHA, c0, spacing)})]
        t0 = time.perf_counter()
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
        wall = time.perf_counter() - t0
        if p.returncode != 0 or not out.is_file():
            tail = (p.stderr or p.stdout).strip().splitlines()[-3:]
            return {"error": f"SPlisHSPlasH exited with {p.returncode}: {' | '.join(tail)[:300]}"}
        r = json.loads(out.read_text())
    r["process_wall_s"] = wall
    # the front sampled at the first step on or after each measured time; the step is small (dt), so
    # the position is taken as at the measured time
    front, front_max = {}, {}
    r["front_samples"] = dict(r["front"])
    for k, (t_got, x, xmax) in r.pop("front").items():
        front[float(k)] = x
        front_max[float(k)] = xmax
    r.update(front_errors(front))
    fm = front_errors(front_max)
    r["front_of_any_particle"] = {"rms": fm["front_rms"], "bias": fm["front_bias"]}
    r["s_per_step"] = r["run_s"] / max(r["steps"], 1)  # the mean: some steps take far longer than the median
    return r


def cpu_warp() -> tuple[bool, str]:
    """Whether this Warp can run kernels on the CPU (the comparison runs rockwave there)."""
    try:
        import warp as wp

        wp.init()
        if hasattr(wp, "is_cpu_available") and not wp.is_cpu_available():
            return False, (f"this Warp {wp.__version__} has no CPU backend (wp.is_cpu_available() is False: built "
                           "without LLVM/Clang), so rockwave cannot run the CPU side of the comparison")
        wp.get_device("cpu")
    except Exception as e:  # noqa: BLE001 - any failure is the reason recorded
        return False, f"Warp's CPU device is unusable here: {type(e).__name__}: {e}"[:300]
    return True, ""


def compare(spacing_ratio: float = 10, c0: float = 15.0, t_end: float | None = None, device: str = "cpu") -> dict:
    """Both codes on the same scene on the CPU; the throughput ratio rockwave / SPlisHSPlasH (particle-steps/s).
    ``device`` is the suite's device: the comparison itself always runs on the CPU. Whatever prevents a side
    from running is recorded as {"skipped": why} or {"error": ...}, never dropped."""
    a = H.A_MM
    spacing = a / spacing_ratio
    dt = round(0.25 * spacing / c0, 7)  # fixed, the same in both (CFL 0.25 at c0)
    tf, _ = H.dam_break_times()
    t_end = float(tf[-1]) if t_end is None else t_end
    res = {"scene": f"3D Martin & Moyce n^2 = 2 dam break, a = {a} m, slab depth a, spacing a/{spacing_ratio:g}",
           "spacing_m": spacing, "c0_m_s": c0, "dt_s": dt, "t_end_s": t_end, "suite_device": device, "run_on": "cpu",
           "kernel": "cubic spline, support 2 x spacing",
           "eos": f"p = B((rho/rho0)^7 - 1), p >= 0; rockwave Tait B = c0^2 rho0/7 = {tait_b(c0):.6g} Pa "
                  "= SPlisHSPlasH WCSPH stiffness, exponent 7",
           "viscosity": f"rockwave artificial alpha {ALPHA}; SPlisHSPlasH standard nu = alpha c0 h/10 = "
                        f"{splash_viscosity(ALPHA, c0, spacing):.4g} m^2/s"}
    ok, why = available()
    if not ok:  # checked first: nothing runs for a comparison that cannot happen
        res["splash"] = {"skipped": why}
        return res
    ok, why = cpu_warp()
    if not ok:
        res["splash"] = {"skipped": why}
        return res
    try:
        res["splash"] = run_splash(spacing, c0, dt, t_end)
    except Exception as e:  # timeout, crash: recorded, never silent
        res["splash"] = {"error": f"{type(e).__name__}: {e}"[:300]}
    for key, density in (("rockwave", "summation"), ("rockwave_continuity", "continuity")):
        try:
            res[key] = run_rockwave(spacing, c0, dt, t_end, "cpu", density)
        except Exception as e:  # noqa: BLE001
            res[key] = {"error": f"{type(e).__name__}: {e}"[:300]}
    s, r = res["splash"], res["rockwave"]
    used = s.get("parameters_used") or {}
    def num(key):
        try:
            return float(used.get(key))
        except (TypeError, ValueError):  # unread by this version of the bindings
            return math.nan

    if used and "particles" in r:  # what SPlisHSPlasH reports it used, against the intent
        res["matched"] = {"particles": s.get("particles") == r["particles"],
                          "initial_bounds": bool(np.allclose(np.asarray(used.get("initial_bounds", np.nan), float),
                                                             np.asarray(r["initial_bounds"])[:, [0, 2, 1]], atol=1e-6)),
                          "stiffness": abs(num("stiffness") / tait_b(c0) - 1) < 1e-4,
                          "exponent": num("exponent") == GAMMA,
                          "time_step": abs(num("time_step") / dt - 1) < 1e-4,
                          "viscosity": abs(num("viscosity") / splash_viscosity(ALPHA, c0, spacing) - 1) < 1e-4}
    if s.get("s_per_step"):
        for key, rk in (("rockwave", "throughput_ratio"), ("rockwave_continuity", "throughput_ratio_continuity")):
            r = res[key]
            if r.get("s_per_step"):
                res[rk] = (r["particles"] / r["s_per_step"]) / (s["particles"] / s["s_per_step"])
    return res
