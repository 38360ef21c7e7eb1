"""Runs one SPlisHSPlasH scene headless inside its own process (started by benchmarks/peers/splash.py
with LD_PRELOAD set for the wheel's GL library; /work/shared/peers.md) and writes a JSON result:
fluid particles, per-step wall times, and the front (largest x of the fluid) at the sample times.

    python benchmarks/peers/splash_worker.py SCENE.json OUT.json T_END SAMPLE_TIMES_CSV
"""

import json
import os
import sys
import time

import numpy as np


def main() -> None:
    scene, out, t_end, samples = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4]
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
    stamps, front, k = [], {}, [0]

    def cb():
        stamps.append(time.perf_counter())
        t = tm.getTime()
        while k[0] < len(ts) and t >= ts[k[0]] - 1e-9:
            fm = sim.getFluidModel(0)
            n = fm.numActiveParticles()
            x = np.array(fm.getFieldBuffer("position"), copy=False)[:n]
            front[ts[k[0]]] = [t, float(x[:, 0].max())]
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
           "front": front}
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
