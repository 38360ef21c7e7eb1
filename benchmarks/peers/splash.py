"""SPlisHSPlasH side by side: the 3D Martin & Moyce dam break (n^2 = 2 column a x 2a, a slab of depth a
between walls) with WCSPH, the cubic spline kernel, the same spacing, support radius and fixed time step
in both codes, on the CPU. Reports the throughput ratio and the front error of both.

SPlisHSPlasH (pip install pysplishsplash==2.19.0, MIT) runs in a child process with
LD_PRELOAD=/lib/x86_64-linux-gnu/libGLdispatch.so.0 (its wheel's GL library clashes with the system's;
/work/shared/peers.md). Its scene JSON is generated here (splash_scene). Parameters matched:
particle radius r = spacing / 2 and kernel support 4 r = 2 x spacing (rockwave support_radius_ratio 2),
cubic spline kernel and gradient (kernel = gradKernel = 0), Akinci 2012 boundary particles
(boundaryHandlingMethod 0), WCSPH (simulationMethod 0) with exponent 7 and stiffness B = c0^2 rho0 / 7
(the Tait constant rockwave uses), fixed step (cflMethod 0). Viscosity: SPlisHSPlasH standard 0.01
(its dam-break default), rockwave artificial alpha 0.05 (its dam-break default).
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

PRELOAD = "/lib/x86_64-linux-gnu/libGLdispatch.so.0"
TANK = (0.35, 0.2)  # tank length (x) and wall height [m], as scenes/dam_break_2d.toml


def available() -> tuple[bool, str]:
    if importlib.util.find_spec("pysplishsplash") is None:
        return False, "pysplishsplash is not installed (pip install pysplishsplash==2.19.0; optional extra 'peers')"
    return True, ""


def unit_box() -> str:
    p = Path(sys.prefix) / "bin" / "data" / "models" / "UnitBox.obj"
    return str(p)


def splash_scene(spacing: float, c0: float, dt: float, a: float = H.A_MM, stiffness: float | None = None) -> dict:
    """SPlisHSPlasH scene (y up): tank [0, 0.35] x [0, 0.2] x [0, a], column [0, a] x [0, 2a] x [0, a]."""
    L, Ht = TANK
    w = a
    return {
        "Configuration": {
            "particleRadius": spacing / 2, "simulationMethod": 0, "gravitation": [0, -H.G, 0],
            "timeStepSize": dt, "cflMethod": 0, "cflMaxTimeStepSize": dt, "numberOfStepsPerRenderUpdate": 1,
            "kernel": 0, "gradKernel": 0, "boundaryHandlingMethod": 0, "enableZSort": False,
            "enableVTKExport": False, "enablePartioExport": False,
            "WCSPH": {"stiffness": stiffness or c0 * c0 * 1000.0 / 7.0, "exponent": 7},
        },
        "Materials": [{"id": "Fluid", "density0": 1000, "viscosityMethod": 1, "Standard viscosity": {"viscosity": 0.01}}],
        "RigidBodies": [{
            "geometryFile": unit_box(), "translation": [L / 2, Ht / 2, w / 2], "rotationAxis": [1, 0, 0],
            "rotationAngle": 0, "scale": [L, Ht, w], "isDynamic": False, "isWall": True, "mapInvert": True,
            "mapThickness": 0.0, "mapResolution": [40, 30, 15], "samplingMode": 1,
        }],
        "FluidBlocks": [{"denseMode": 0, "start": [0.0, 0.0, 0.0], "end": [a, 2 * a, w], "translation": [0, 0, 0],
                         "scale": [1, 1, 1]}],
    }


def rockwave_scene(spacing: float, c0: float, dt: float, a: float = H.A_MM) -> dict:
    L, Ht = TANK
    return {
        "simulation": {"dimension": 3, "duration_s": 1.0, "time_step": "fixed", "dt_s": dt},
        "fluid": {"spacing_m": spacing, "kernel": "cubic_spline", "support_radius_ratio": 2.0,
                  "eos": {"type": "tait", "speed_of_sound_m_s": c0, "gamma": 7.0},
                  "viscosity": {"artificial_alpha": 0.05},
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


def run_rockwave(spacing: float, c0: float, dt: float, t_end: float, device: str = "cpu") -> dict:
    import warp as wp
    import rockwave

    sim = rockwave.Simulation(rockwave.parse_scene(rockwave_scene(spacing, c0, dt), "mm3d.toml", H.ROOT), device=device)
    tf, _ = H.dam_break_times(t_end=t_end)
    front = {}
    clock = H.Clock(sim.device)
    for _ in range(3):  # kernel loads
        sim.step(dt)
    sim2 = rockwave.Simulation(rockwave.parse_scene(rockwave_scene(spacing, c0, dt), "mm3d.toml", H.ROOT), device=device)
    steps = 0
    for t in tf:
        n0 = sim2.steps
        clock.run(lambda: H._advance_to(sim2, float(t), dt))
        steps += sim2.steps - n0
        front[float(t)] = float(sim2.positions()[:, 0].max())
    nb = float(np.mean(sim2.fluid_solver.neighbour_counts(sim2.state)))
    d = sim2.densities()[: sim2.n_fluid]
    return {"particles": sim2.n_fluid, "boundary_particles": sim2.fluid.n_boundary, "steps": steps, "wall_s": clock.seconds,
            "s_per_step": clock.seconds / max(steps, 1), "neighbours": nb, "dt_s": dt,
            "density_error_mean": float(np.mean(np.abs(d / 1000.0 - 1.0))), **front_errors(front)}


def run_splash(spacing: float, c0: float, dt: float, t_end: float, timeout: float = 900, stiffness: float | None = None) -> dict:
    tf, _ = H.dam_break_times(t_end=t_end)
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "splash_dam_break.json"
        scene.write_text(json.dumps(splash_scene(spacing, c0, dt, stiffness=stiffness), indent=1))
        out = Path(tmp) / "result.json"
        env = dict(os.environ, LD_PRELOAD=PRELOAD)
        cmd = [sys.executable, str(Path(__file__).with_name("splash_worker.py")), str(scene), str(out), f"{t_end:.6f}",
               ",".join(f"{t:.9f}" for t in tf)]
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
    front = {}
    for k, (t_got, x) in r.pop("front").items():
        front[float(k)] = x
    r.update(front_errors(front))
    r["s_per_step"] = r["run_s"] / max(r["steps"], 1)  # the mean: some steps take far longer than the median
    return r


def compare(spacing_ratio: float = 10, c0: float = 15.0, t_end: float | None = None, device: str = "cpu") -> dict:
    """Both codes on the same scene; the throughput ratio rockwave / SPlisHSPlasH (particle-steps/s)."""
    a = H.A_MM
    spacing = a / spacing_ratio
    dt = round(0.25 * spacing / c0, 7)  # fixed, the same in both (CFL 0.25 at c0)
    tf, _ = H.dam_break_times()
    t_end = float(tf[-1]) if t_end is None else t_end
    res = {"scene": f"3D Martin & Moyce n^2 = 2 dam break, a = {a} m, slab depth a, spacing a/{spacing_ratio:g}",
           "spacing_m": spacing, "c0_m_s": c0, "dt_s": dt, "t_end_s": t_end, "kernel": "cubic spline, support 2 x spacing"}
    ok, why = available()
    res["rockwave"] = run_rockwave(spacing, c0, dt, t_end, device)
    if not ok:
        res["splash"] = {"skipped": why}
        return res
    try:
        res["splash"] = run_splash(spacing, c0, dt, t_end)
    except Exception as e:  # timeout, crash: recorded, never silent
        res["splash"] = {"error": f"{type(e).__name__}: {e}"[:300]}
    s, r = res["splash"], res["rockwave"]
    if s.get("s_per_step"):
        res["throughput_ratio"] = (r["particles"] / r["s_per_step"]) / (s["particles"] / s["s_per_step"])
    return res
