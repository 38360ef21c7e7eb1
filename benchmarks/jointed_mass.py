"""A jointed rock mass that stands and one that fails (issue 36), at scenes/rock_slope_10k.toml size on a GPU.

The scene's rock mass (bedding parallel to the 20 deg basal plane, cross joints normal to it and vertical joints
along the dip, cubes of 0.5 m) at 100 x 50 x 2 = 10,000 blocks (50 x 25 x 1 m) is set down in contact on the basal
plane (the scene leaves 0.2 mm between them: the region is moved down by that gap), every joint and the basal plane
at one friction angle, k_n per contact point ``--kn`` (5e7 N/m: a joint stiffness of 8e8 Pa/m on a 0.5 m face with
4 points; None: the solver's default 0.1 E L = 5e8). Planar sliding on the bedding and the base needs 20 deg. Two
layers, because a column of cubes h / w > 1 / tan 20 = 2.75 topples at any friction: the scene's ten layers
(h / w = 10) are a toppling slope, not a sliding one (measured on the CPU: a free column of 3 cubes at friction 60
deg tips over; 10 x 6 x 4 blocks collapse by toppling from the free toe). Runs:

- ``locked``: friction 60 deg everywhere (every point sticks) for ``--locked-duration`` s: the elastic deflection;
- ``margin`` +2 deg (22 deg) for ``--duration`` s (60): the largest block displacement must stay within the locked
  run's + 1 mm, every block < 1 um/s over the last 10 s;
- ``margin`` -2 deg (18 deg) for ``--fail-duration`` s: the mass slides (g (sin 20 - cos 20 tan 18) = 0.36 m/s^2).

Every ``--every`` s each run records: blocks moved more than 1 mm, the largest displacement and its block, the
block kinetic energy; at the end the creep rate of every block over the last ``--window`` s (largest and its block),
and the wall time per step. The blocks are stepped through Simulation (the block-only clock at the solver's stable
step), as the CLI runs the scene.

    python -m benchmarks.jointed_mass --device cuda:0                           # 10,000 blocks, 60 s (~6-8 min, H200)
    python -m benchmarks.jointed_mass --device cpu --size 4 2 2 --duration 3 --fail-duration 1 --locked-duration 1

writes benchmarks/results/jointed_mass-<device>.json and .md.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from benchmarks.common import ROOT

SLOPE = 20.0


def jointed_sim(device: str, phi: float, size=(100, 50, 2), kn: float | None = 5.0e7):
    """The rock_slope_10k scene at size (nx, ny, nz) blocks of 0.5 m, in contact with its base, every joint and the
    base at friction angle phi, k_n kn N/m per point (None: the default). Returns the Simulation."""
    import rockwave
    from rockwave.build.rockmass import resize_box_region
    from rockwave.build.rocks import block_specs

    nx, ny, nz = size
    scene = rockwave.load_scene(ROOT / "scenes" / "rock_slope_10k.toml")
    rm = scene.rock_mass[0]
    resize_box_region(rm, [0.5 * nx, 0.5 * ny, 0.5 * nz])
    rm["region"]["box_min_m"][1], rm["region"]["box_max_m"][1] = -0.25 * ny, 0.25 * ny
    # the basal plane (centred on the origin) covers the mass, which starts 10 m up the dip from the origin, with
    # 2.5 m to spare down the dip: a mass hanging over its edge falls off (measured: 100 x 50 x 2 on a 75 m plane)
    half = max(20.0, 0.5 * nx - 10.0 + 2.5)
    scene.blocks[0]["size_m"] = [2.0 * half, max(16.0, 0.5 * ny + 4.0), 1.0]
    n = np.array([math.sin(math.radians(SLOPE)), 0.0, math.cos(math.radians(SLOPE))])
    top = 0.5 * scene.blocks[0]["size_m"][2]
    b = block_specs(scene)[1]
    gap = float(((np.asarray(b.geometry.vertices) + np.asarray(b.position)) @ n).min() - top)
    for key in ("box_min_m", "box_max_m"):
        rm["region"][key] = (np.asarray(rm["region"][key]) - gap * n).tolist()
    for m in (rm["material"], scene.blocks[0]["material"]):
        m["friction_angle_deg"] = phi
        if kn is not None:
            m["normal_stiffness_n_m"] = kn
    for js in rm["joint_sets"]:
        js["friction_angle_deg"] = phi
    return rockwave.Simulation(scene, device=device)


def run_case(device: str, phi: float, duration: float, every: float, window: float, size, kn) -> dict:
    """One run: the record every ``every`` s, the creep over the last ``window`` s, the cost per step."""
    import warp as wp

    from benchmarks.common import log

    t0 = time.perf_counter()
    sim = jointed_sim(device, phi, size, kn)
    build = time.perf_counter() - t0
    x0 = sim.block_positions().copy()
    nb = len(x0)
    rec = []
    d_window = None
    in_window = []  # (t, every block's displacement) at the samples of the last window
    t0 = time.perf_counter()
    t = 0.0
    while t < duration - 1e-9:
        h = min(every, duration - t)
        if d_window is None and t + h >= duration - window - 1e-9:
            sim.advance(duration - window - t)  # land on the window's start
            t = duration - window
            d_window = np.linalg.norm(sim.block_positions() - x0, axis=1)
            in_window.append((t, d_window))
            continue
        sim.advance(h)
        t += h
        wp.synchronize_device(device)
        d = np.linalg.norm(sim.block_positions() - x0, axis=1)
        if d_window is not None:
            in_window.append((t, d))
        worst = int(np.argmax(d))
        rec.append(dict(t_s=round(t, 6), moved_1mm=int((d > 1e-3).sum()), max_disp_mm=1e3 * float(d[worst]), block=worst,
                        kinetic_j=float(sim.block_state.kinetic_energy()), wall_s=time.perf_counter() - t0))
        log(f"  phi {phi:g}: t {t:.2f} s, {rec[-1]['moved_1mm']} of {nb - 1} blocks moved > 1 mm, largest "
            f"{rec[-1]['max_disp_mm']:.4f} mm (block {worst}), KE {rec[-1]['kinetic_j']:.3g} J, {rec[-1]['wall_s']:.0f} s")
    wall = time.perf_counter() - t0
    d = np.linalg.norm(sim.block_positions() - x0, axis=1)
    creep = (d - d_window) / window if d_window is not None else np.full(nb, np.nan)
    creep[0] = 0.0  # the basal plane
    c = int(np.nanargmax(np.abs(creep)))
    # the same rate as the least-squares slope through every sample of the window (a block's vibration at the two
    # ends weighs less than in the end-to-end difference)
    fit = np.full(nb, np.nan)
    if len(in_window) >= 3:
        ts = np.array([a for a, _ in in_window])
        ds = np.stack([b for _, b in in_window])
        tc = ts - ts.mean()
        fit = (tc @ (ds - ds.mean(axis=0))) / (tc @ tc)
        fit[0] = 0.0
    cf = int(np.nanargmax(np.abs(fit))) if np.isfinite(fit).any() else 0
    nsteps = int(round(duration / sim.dt))
    return dict(phi_deg=phi, duration_s=duration, blocks=nb - 1, build_s=build, wall_s=wall, dt_s=sim.dt,
                steps=nsteps, ms_per_step=1e3 * wall / max(nsteps, 1), record=rec,
                final_max_disp_mm=1e3 * float(d.max()), final_moved_1mm=int((d > 1e-3).sum()),
                creep_window_s=window, max_creep_um_s=1e6 * float(creep[c]), creep_block=c,
                fit_samples=len(in_window), max_fit_creep_um_s=1e6 * float(fit[cf]), fit_creep_block=cf,
                blocks_over_1um_s_fit=int((np.abs(fit) > 1e-6).sum()), mean_abs_fit_creep_um_s=1e6 * float(np.nanmean(np.abs(fit[1:]))),
                disp_mm=(1e3 * d).tolist() if nb <= 200 else None)


def run(device: str, size=(100, 50, 2), kn=5.0e7, duration=60.0, fail_duration=10.0, locked_duration=5.0, every=1.0,
        window=10.0, margin=2.0) -> dict:
    locked = run_case(device, 60.0, locked_duration, every, min(window, locked_duration / 2), size, kn)
    stands = run_case(device, SLOPE + margin, duration, every, window, size, kn)
    fails = run_case(device, SLOPE - margin, fail_duration, every, min(window, fail_duration / 2), size, kn)
    return dict(size=list(size), kn=kn, locked=locked, stands=stands, fails=fails,
                stands_within_elastic_1mm=stands["final_max_disp_mm"] <= locked["final_max_disp_mm"] + 1.0,
                stands_at_rest=abs(stands["max_creep_um_s"]) < 1.0, fails_slides=fails["final_moved_1mm"] == fails["blocks"])


def markdown(res: dict, head: str) -> str:
    out = [head, ""]
    for key in ("locked", "stands", "fails"):
        r = res[key]
        out += [f"**{key}** (friction {r['phi_deg']:g} deg, {r['blocks']} blocks, {r['duration_s']:g} s, dt {r['dt_s']:.3g} s, "
                f"{r['steps']} steps, {r['ms_per_step']:.3f} ms per step, build {r['build_s']:.0f} s): largest displacement "
                f"{r['final_max_disp_mm']:.4f} mm, {r['final_moved_1mm']} blocks moved > 1 mm, largest creep over the last "
                f"{r['creep_window_s']:g} s {r['max_creep_um_s']:.4f} um/s (block {r['creep_block']})"
                + (f"; fitted through the window's {r['fit_samples']} samples: largest {r['max_fit_creep_um_s']:.4f} um/s "
                   f"(block {r['fit_creep_block']}), {r['blocks_over_1um_s_fit']} blocks over 1 um/s, mean "
                   f"{r['mean_abs_fit_creep_um_s']:.4f} um/s" if r.get("fit_samples", 0) >= 3 else ""), "",
                "| t s | blocks moved > 1 mm | largest displacement mm | block | kinetic energy J |", "|---|---|---|---|---|"]
        out += [f"| {x['t_s']:g} | {x['moved_1mm']} | {x['max_disp_mm']:.4f} | {x['block']} | {x['kinetic_j']:.4g} |"
                for x in r["record"]]
        out.append("")
    out.append(f"Stands within the locked (elastic) deflection + 1 mm: {res['stands_within_elastic_1mm']}; at rest "
               f"(< 1 um/s): {res['stands_at_rest']}; 2 deg below, every block slides: {res['fails_slides']}")
    return "\n".join(out) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.jointed_mass", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, nargs=3, default=[100, 50, 2], help="blocks along the dip, across, in depth")
    ap.add_argument("--kn", default="5e7", help="k_n N/m per contact point, or 'default' (0.1 E L)")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--fail-duration", type=float, default=10.0)
    ap.add_argument("--locked-duration", type=float, default=5.0)
    ap.add_argument("--every", type=float, default=1.0)
    ap.add_argument("--window", type=float, default=10.0, help="creep over the last this many s")
    ap.add_argument("--margin", type=float, default=2.0, help="friction above / below the 20 deg the geometry needs")
    ap.add_argument("--out", default=None, help="result stem (default benchmarks/results/jointed_mass-<device>)")
    a = ap.parse_args()
    import warp as wp

    from benchmarks.common import RESULTS, commit, device_name, write_json

    wp.config.quiet = True
    kn = None if a.kn == "default" else float(a.kn)
    res = run(a.device, tuple(a.size), kn, a.duration, a.fail_duration, a.locked_duration, a.every,
              min(a.window, a.duration / 2), a.margin)
    stem = a.out or str(RESULTS / f"jointed_mass-{a.device.replace(':', '')}")
    head = (f"# Jointed rock mass, {a.margin:g} deg either side of its limit (issue 36): {device_name(a.device)}, commit "
            f"{commit()}, {a.size[0]} x {a.size[1]} x {a.size[2]} blocks, k_n {a.kn} N/m per point")
    md = markdown(res, head)
    with open(stem + ".md", "w") as f:
        f.write(md)
    write_json(dict(res, device=a.device, commit=commit(), args=vars(a)), stem + ".json")
    print(md)


if __name__ == "__main__":
    main()
