"""The Newmark block shaken below its yield acceleration, for many cycles (issue 36: no ratchet).

The cube of tests/test_standing_rock.py (1 m, 2600 kg/m3, on a kinematic slope of 20 deg, friction 30 deg: yield
acceleration a_y = g (cos 20 tan 30 - sin 20) = 0.20 g along the slope) shaken along the dip at ``--peak`` (0.15 g)
by u_b = A (1 - cos w t), 2 Hz (``--motion table``: a table every 1 ms, as the test; ``sine``: A sin(w t), the cube
started with the base's velocity). Newmark's rigid block never slides; the discrete one must not either once its
corners have shaken down (the first cycle or two). Per case, the cube's displacement relative to the slope along the
dip at the start of every cycle (the same phase: same base acceleration, same elastic load): the first cycle's step
(the shakedown), the largest |step| over the last 10 cycles, and the rate over the last 10 cycles [um/s] (the issue's
bound: < 1 um/s). Cases: k_n in ``--kn`` (N/m per point), rigid and deformable cubes.

    python -m benchmarks.newmark_ratchet --device cuda:0 --duration 60          # 8 cases, ~10-15 min on an H200
    python -m benchmarks.newmark_ratchet --device cpu --duration 2 --kn 1e8     # CPU smoke run, ~1 min

writes benchmarks/results/newmark_ratchet-<device>.json and .md.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

G = 9.81
BETA, PHI, FREQ = 20.0, 30.0, 2.0


def rot_y(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])


def quat_y(deg: float) -> tuple:
    a = math.radians(deg) / 2
    return (0.0, math.sin(a), 0.0, math.cos(a))  # x, y, z, w


def run_case(device: str, peak_g: float, duration: float, kn: float, kind: str, motion: str) -> dict:
    """One shaken cube; returns its per-cycle record."""
    import warp as wp

    from rockwave.base.solver import TimeStep
    from rockwave.dda import geometry as Gm
    from rockwave.dda.blocks import BlockModel, BlockSolver, BlockSpec, ContactMaterial, KinematicMotion

    w = 2.0 * math.pi * FREQ
    A = peak_g * G / w**2
    R = rot_y(BETA)
    n, d = R @ [0.0, 0.0, 1.0], R @ [1.0, 0.0, 0.0]
    mat = ContactMaterial(friction_angle_deg=PHI, normal_stiffness=kn)
    if motion == "table":
        tt = np.linspace(0.0, duration, int(round(duration / 1.0e-3)) + 1)
        mo, v0 = KinematicMotion.table(tt, np.outer(A * (1.0 - np.cos(w * tt)), d)), (0.0, 0.0, 0.0)
    else:
        mo, v0 = KinematicMotion.sine(tuple(A * d), FREQ), tuple(A * w * d)
    slope = (6.0, 3.0, 0.5)
    specs = [BlockSpec(Gm.box(slope), kind="kinematic", orientation=quat_y(BETA), name="base", material=mat, motion=mo),
             BlockSpec(Gm.box((1.0, 1.0, 1.0)), position=tuple((slope[2] + 1.0) / 2 * n), orientation=quat_y(BETA),
                       density=2600.0, material=mat, name="block", kind=kind, velocity=v0)]
    model = BlockModel(specs, device=device)
    solver, state = BlockSolver(model), model.state()
    x0 = model.base_position
    dt = solver.stable_dt(state)
    dta = wp.array([dt], dtype=float, device=device)
    n_steps = int(round(duration / dt))

    def rel():
        p = state.positions_numpy()
        return float(((p[1] - x0[1]) - (p[0] - x0[0])) @ d)

    # the displacement at t = c / f exactly, interpolated linearly between the two steps around it (a step of
    # 2 ms at k_n 1e7 against the elastic response's ~3 mm/s would otherwise jitter the samples by several um)
    at, next_c = [rel()], 1
    t_prev, r_prev = state.time, at[0]
    t0 = time.perf_counter()
    for _ in range(n_steps):
        solver.step(state, TimeStep(dt, state.time, dta))
        tc = next_c / FREQ
        if state.time >= tc - 1.5 * dt:
            r_now = rel()
            if state.time >= tc:
                at.append(r_prev + (r_now - r_prev) * (tc - t_prev) / (state.time - t_prev))
                next_c += 1
            t_prev, r_prev = state.time, r_now
        else:
            t_prev = state.time
    wall = time.perf_counter() - t0
    steps = np.diff(at)
    last = steps[-10:] if len(steps) > 10 else steps[1:]
    return dict(kind=kind, motion=motion, kn=kn, peak_g=peak_g, dt=dt, steps=n_steps, cycles=len(steps),
                first_cycle_um=1e6 * float(steps[0]) if len(steps) else None,
                last10_max_abs_um=1e6 * float(np.abs(last).max()) if len(last) else None,
                last10_rate_um_s=1e6 * float(last.sum() * FREQ / len(last)) if len(last) else None,
                total_um=1e6 * float(at[-1] - at[0]), per_cycle_um=[1e6 * float(s) for s in steps],
                wall_s=wall, ms_per_step=1e3 * wall / max(n_steps, 1))


def _num(v) -> str:
    return "-" if v is None else f"{v:.3f}"


def markdown(rows: list[dict], head: str) -> str:
    out = [head, "", "| cube | motion | k_n (N/m/pt) | dt (ms) | cycles | first cycle (um) | max last 10 (um) | "
           "rate last 10 (um/s) | ms/step |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['kind']} | {r['motion']} | {r['kn']:.0e} | {1e3 * r['dt']:.3f} | {r['cycles']} | "
                   f"{_num(r['first_cycle_um'])} | {_num(r['last10_max_abs_um'])} | {_num(r['last10_rate_um_s'])} | "
                   f"{r['ms_per_step']:.2f} |")
    return "\n".join(out) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.newmark_ratchet", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--peak", type=float, default=0.15, help="peak base acceleration [g] (yield: 0.20 g)")
    ap.add_argument("--kn", type=float, nargs="+", default=[1.0e7, 1.0e8], help="k_n N/m per contact point")
    ap.add_argument("--kinds", nargs="+", default=["rigid", "deformable"])
    ap.add_argument("--motions", nargs="+", default=["table", "sine"])
    ap.add_argument("--out", default=None, help="result stem (default benchmarks/results/newmark_ratchet-<device>)")
    a = ap.parse_args()
    import warp as wp

    from benchmarks.common import RESULTS, commit, device_name, write_json

    wp.config.quiet = True
    rows = []
    for kn in a.kn:
        for kind in a.kinds:
            for motion in a.motions:
                r = run_case(a.device, a.peak, a.duration, kn, kind, motion)
                print(markdown([r], "").strip().splitlines()[-1], flush=True)
                rows.append(r)
    stem = a.out or str(RESULTS / f"newmark_ratchet-{a.device.replace(':', '')}")
    head = (f"# Newmark block shaken at {a.peak:g} g (yield 0.20 g) for {a.duration:g} s (issue 36): "
            f"{device_name(a.device)}, commit {commit()}")
    md = markdown(rows, head)
    with open(stem + ".md", "w") as f:
        f.write(md)
    write_json(dict(rows=rows, device=a.device, commit=commit(), args=vars(a)), stem + ".json")
    print(md)


if __name__ == "__main__":
    main()
