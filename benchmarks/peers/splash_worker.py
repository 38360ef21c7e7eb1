"""Runs one SPlisHSPlasH scene headless inside its own process (started by benchmarks/peers/splash.py
with LD_PRELOAD set for the wheel's GL library, which clashes with the system's) and writes a JSON result:
fluid particles, per-step wall times, and the front at the sample times (benchmarks/peers/front.py
bulk_front, and the largest x of any particle).

    python benchmarks/peers/splash_worker.py SCENE.json OUT.json T_END SAMPLE_TIMES_CSV [SETTINGS_JSON]

SETTINGS_JSON (optional), e.g. {"viscosity": 4.3e-4}: set after initSimulation through the parameter API,
for values that SPlisHSPlasH 2.19.0's scene loader does not take from the scene file (the standard
viscosity's "viscosity" in a Materials entry is left at its default 0.01: measured).
"""

import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from front import bulk_front  # noqa: E402  (benchmarks/peers/front.py: the same front measure as rockwave's)


def main() -> None:
    scene, out, t_end, samples = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4]
    settings = json.loads(sys.argv[5]) if len(sys.argv) > 5 else {}
    ts = [float(s) for s in samples.split(",") if s]
    import pysplishsplash as sph

    base = sph.Exec.SimulatorBase()
    outdir = os.path.join(os.path.dirname(out), "splash_out")
    base.init(sceneFile=os.path.abspath(scene), useGui=False, initialPause=False, stopAt=t_end, outputDir=outdir)
    t0 = time.perf_counter()
    base.initSimulation()
    init_s = time.perf_counter() - t0
    sim = sph.Simulation.getCurrent()
    tm = sph.TimeManager.getCurrent()
    fm0 = sim.getFluidModel(0)
    n0 = fm0.numActiveParticles()
    x0 = np.array(fm0.getFieldBuffer("position"), copy=False)[:n0]
    bounds0 = [x0.min(axis=0).tolist(), x0.max(axis=0).tolist()]

    def apply_settings():
        if "viscosity" in settings:
            sim.getFluidModel(0).getViscosityBase().setValueFloat(sph.Viscosity_Standard.VISCOSITY_COEFFICIENT,
                                                                  float(settings["viscosity"]))

    def parameters():
        """The parameters SPlisHSPlasH actually uses (a misspelt or unread scene key is silently ignored)."""
        fm = sim.getFluidModel(0)
        used = {"initial_bounds": bounds0, "support_radius": float(sim.getSupportRadius()),
                "particle_radius": float(sim.getParticleRadius()), "kernel": int(sim.getKernel()),
                "grad_kernel": int(sim.getGradKernel()), "boundary_handling": str(sim.getBoundaryHandlingMethod()),
                "time_step": float(tm.getTimeStepSize())}
        for name, get in (("stiffness", lambda: sim.getTimeStep().getValueFloat(sph.TimeStepWCSPH.STIFFNESS)),
                          ("exponent", lambda: sim.getTimeStep().getValueFloat(sph.TimeStepWCSPH.EXPONENT)),
                          ("viscosity",
                           lambda: fm.getViscosityBase().getValueFloat(sph.Viscosity_Standard.VISCOSITY_COEFFICIENT)),
                          ("viscosity_method", lambda: type(fm.getViscosityBase()).__name__)):
            try:
                used[name] = get()
            except Exception as e:  # bindings differ between versions: say so
                used[name] = f"unread: {type(e).__name__}: {e}"[:120]
        return used

    apply_settings()
    seen = {}
    stamps, front, k = [], {}, [0]

    def cb():
        stamps.append(time.perf_counter())
        if len(stamps) == 1:  # after the first step: what the run uses (runSimulation re-reads some parameters)
            seen["first_step"] = parameters()
        if len(stamps) in (1, 10, 100):  # start-up state: density and speed extremes
            fm = sim.getFluidModel(0)
            n = fm.numActiveParticles()
            rho = np.array(fm.getFieldBuffer("density"), copy=False)[:n]
            v = np.array(fm.getFieldBuffer("velocity"), copy=False)[:n]
            xs = np.array(fm.getFieldBuffer("position"), copy=False)[:n]
            seen[f"step_{len(stamps)}"] = {"rho_max": float(rho.max()), "rho_min": float(rho.min()),
                                           "rho_mean": float(rho.mean()), "v_max": float(np.linalg.norm(v, axis=1).max()),
                                           "x_of_rho_max": xs[int(np.argmax(rho))].tolist(),
                                           "fraction_over_1_02": float((rho > 1020.0).mean()),
                                           "bounds": [xs.min(axis=0).tolist(), xs.max(axis=0).tolist()]}
        t = tm.getTime()
        while k[0] < len(ts) and t >= ts[k[0]] - 1e-9:
            fm = sim.getFluidModel(0)
            n = fm.numActiveParticles()
            x = np.array(fm.getFieldBuffer("position"), copy=False)[:n]
            front[ts[k[0]]] = [t, bulk_front(x, 2.0 * float(sim.getParticleRadius())), float(x[:, 0].max())]
            k[0] += 1

    base.setTimeStepCB(cb)
    t1 = time.perf_counter()
    base.runSimulation()
    run_s = time.perf_counter() - t1
    fm = sim.getFluidModel(0)
    n = fm.numActiveParticles()
    dts = np.diff(stamps)
    res = {"particles": int(n), "init_s": init_s, "run_s": run_s, "steps": len(stamps),
           "simulated_s": float(tm.getTime()), "dt_s": float(tm.getTimeStepSize()),
           "s_per_step_median": float(np.median(dts[5:])) if len(dts) > 10 else None,
           "s_per_step_mean": float(dts[5:].mean()) if len(dts) > 10 else None,
           "front": front, "parameters_used": seen.get("first_step"), "parameters_at_end": parameters(),
           "start_up": {k: v for k, v in seen.items() if k.startswith("step_")}}
    try:
        x = np.array(fm.getFieldBuffer("position"), copy=False)[:n]
        res["finite"] = bool(np.isfinite(x).all())
        d = np.array(fm.getFieldBuffer("density"), copy=False)[:n]
        res["density_error_mean"] = float(np.mean(np.abs(d / 1000.0 - 1.0)))
    except Exception as e:  # field names differ between methods
        res["field_error"] = str(e)
    with open(out, "w") as f:
        json.dump(res, f)
    base.cleanup()


if __name__ == "__main__":
    main()
