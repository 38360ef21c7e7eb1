"""Static friction without creep (issue 36): blocks resting on fixed planes a little below their friction limit.

Each case is a width x width x (aspect x width) block (2600 kg/m3) resting in contact, with no gap and no pre-set
penetration, on a fixed slab dipping ``slope`` degrees, friction angle slope + margin, normal = shear stiffness k
per contact point (None: the solver's defaults, k_n = 0.1 E L, k_s = k_n / 2.5), gravity from t = 0, run for
``duration`` s at the solver's stable step, once from the plain start and once from the settled one
(BlockOptions.start; BlockSolver.settle). Measured at the centre of the block's base, along the dip:

- ``beyond_elastic_mm``: displacement from where it was placed minus the elastic shear deflection with the load
  shared by the four base corners, m g sin(slope) / (4 k_s) (the issue's measure);
- ``slip_mm``: displacement minus the largest spring extension max |f_s| / k_s of its contact points (a corner
  whose normal force is too small for its share of the shear slides until its spring sits at its cap, and the
  others carry more: the elastic deflection of the base is then its most loaded spring's);
- ``creep_um_s``: displacement over the last ``creep_window`` s (10 s of a 60 s run) per second;
- ``tilt_mrad``: its rotation; ``settle_steps``: the settled start's steps (``floor``: it stopped at float32's
  chatter floor, BlockSolver.settle).

Targets (issue 36): from the settled start beyond_elastic <= 0.1 mm after 60 s; from either start creep < 1 um/s.
Cases whose aspect is beyond the toppling limit h/w = 1 / tan(slope) are not run (they topple). Blocks of a
(width, k, start) share one model (one block and its slab per case, 3 slab lengths apart), stepped at the
stiffest case's step, so the GPU runs ~16 models per start instead of ~300.

    python -m benchmarks.static_friction --device cuda --duration 60            # the matrix, 60 s (GPU)
    python -m benchmarks.static_friction --device cpu --subset quick --duration 6   # a small CPU subset

The table goes to benchmarks/results/static_friction-<device>.md (and .json).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

CONFIG = {
    "quick": dict(widths=[1.0, 8.0], aspects=[1.0], slopes=[35.0], margins=[0.1], stiffness=[None, 1.0e8],
                  duration=6.0, creep_window=1.0),
    "full": dict(widths=[0.2, 1.0, 5.0, 20.0], aspects=[0.5, 1.0, "0.9topple"], slopes=[10.0, 35.0, 60.0],
                 margins=[0.1, 1.0], stiffness=[None, 1.0e6, 1.0e8, 1.0e10], duration=60.0, creep_window=10.0),
}
RHO = 2600.0


def _rot_y(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])


def _quat(m: np.ndarray) -> tuple:
    """Rotation matrix -> quaternion (x, y, z, w), for a rotation about y."""
    w = math.sqrt(max(0.0, 1 + np.trace(m))) / 2
    return (0.0, math.copysign(math.sqrt(max(0.0, 1 - m[0, 0] + m[1, 1] - m[2, 2])) / 2, m[0, 2] - m[2, 0]), 0.0, w)


def cases(cfg: dict) -> list:
    """(width, aspect, slope, margin, k) of the matrix, toppling aspects left out."""
    out = []
    for w in cfg["widths"]:
        for k in cfg["stiffness"]:
            for s in cfg["slopes"]:
                limit = 1.0 / math.tan(math.radians(s))
                for a in cfg["aspects"]:
                    asp = 0.9 * limit if a == "0.9topple" else float(a)
                    if asp >= limit:
                        continue
                    for mg in cfg["margins"]:
                        out.append((float(w), asp, float(s), float(mg), k))
    return out


def run_group(device: str, group: list, start: str, duration: float, window: float) -> list:
    """One model for the cases of ``group`` (same width and k): each block and its slab; returns a row per case."""
    import warp as wp

    from rockwave.base.solver import TimeStep
    from rockwave.dda import geometry as G
    from rockwave.dda.blocks import BlockModel, BlockOptions, BlockSolver, BlockSpec, ContactMaterial

    specs, frames = [], []
    for i, (w, asp, s, mg, k) in enumerate(group):
        R = _rot_y(s)
        n, d = R @ [0.0, 0.0, 1.0], R @ [1.0, 0.0, 0.0]
        h = asp * w
        slab = (6 * w, 3 * w, w / 2)
        origin = np.array([0.0, 4.0 * w * i, 0.0])  # cases side by side along y, 1 slab width apart
        mat = ContactMaterial(friction_angle_deg=s + mg, normal_stiffness=k, shear_stiffness=k)
        specs.append(BlockSpec(G.box(slab), kind="fixed", orientation=_quat(R), position=tuple(origin), material=mat,
                               name=f"slab{i}"))
        specs.append(BlockSpec(G.box((w, w, h)), position=tuple(origin + (slab[2] + h) / 2 * n), orientation=_quat(R),
                               density=RHO, material=mat, name=f"block{i}"))
        frames.append((R, n, d, h))
    model = BlockModel(specs, device=device, check_overlap=False)
    state = model.state()
    solver = BlockSolver(model, options=BlockOptions(start=start))
    t0 = time.perf_counter()
    rep = solver.settle(state) if start == "settled" else {"start": "plain"}
    dt = solver.stable_dt(state)
    dta = wp.array([dt], dtype=float, device=device)
    steps = int(round(duration / dt))
    blocks = np.arange(1, 2 * len(group), 2)
    base0 = model.base_position[blocks] - np.array([f[3] / 2 * f[1] for f in frames])

    def base_disp():
        x = state.positions_numpy()[blocks]
        q = state.orientations_numpy()[blocks]
        out = np.zeros(len(group))
        for c, (R, n, d, h) in enumerate(frames):
            Rq = G.quat_to_matrix(q[c])
            base = x[c] + Rq @ (R.T @ (-h / 2 * n))
            out[c] = (base - base0[c]) @ d
        return out

    t_window = duration - window
    d_window = None
    for i in range(steps):
        solver.step(state, TimeStep(dt, state.time, dta))
        if d_window is None and state.time >= t_window - 0.5 * dt:
            d_window = base_disp()
    wp.synchronize_device(device)
    wall = time.perf_counter() - t0
    d_end = base_disp()
    if d_window is None:
        d_window = d_end
    # largest spring extension of each block's contact points (history table: key = A * N + B)
    t = state.tables[0]
    keys, nc, ps = t["keys"].numpy(), t["nc"].numpy(), t["pstart"].numpy()
    shear = np.linalg.norm(t["shear"].numpy(), axis=1)
    ext = np.zeros(model.num_blocks)
    for slot in np.nonzero(keys >= 0)[0]:
        b = int(keys[slot] % model.num_blocks)
        if nc[slot]:
            ext[b] = max(ext[b], float(shear[ps[slot]: ps[slot] + nc[slot]].max()))
    ks = model.np["k_s"]
    q = state.orientations_numpy()[blocks]
    rows = []
    for c, (w, asp, s, mg, k) in enumerate(group):
        b = blocks[c]
        m = model.np["mass"][b]
        elastic = m * 9.81 * math.sin(math.radians(s)) / (4.0 * ks[b])
        R = frames[c][0]
        Rq = G.quat_to_matrix(q[c])
        tilt = math.acos(min(1.0, (float(np.trace(Rq @ R.T)) - 1.0) / 2.0))
        rows.append(dict(width_m=w, aspect=round(asp, 3), slope_deg=s, margin_deg=mg, k_n_m=k if k is not None else "default",
                         k_s=float(ks[b]), start=start, duration_s=steps * dt, steps=steps, dt_s=dt,
                         disp_mm=1e3 * d_end[c], elastic_mm=1e3 * elastic, beyond_elastic_mm=1e3 * (d_end[c] - elastic),
                         slip_mm=1e3 * (d_end[c] - ext[b] / ks[b]),
                         creep_um_s=1e6 * (d_end[c] - d_window[c]) / max(window, 1e-12),
                         tilt_mrad=1e3 * tilt, settle_steps=rep.get("steps", 0),
                         floor=bool(rep.get("float32_floor", False)), settled=rep.get("start") == "settled",
                         wall_s=wall))
    return rows


def run(device: str, cfg: dict) -> dict:
    """The matrix of cfg (CONFIG's keys); returns {"rows": [...]} (one row per case and start)."""
    from benchmarks.common import log

    allc = cases(cfg)
    groups: dict = {}
    for c in allc:
        groups.setdefault((c[0], c[4]), []).append(c)
    rows = []
    for (w, k), group in groups.items():
        for start in ("plain", "settled"):
            r = run_group(device, group, start, float(cfg["duration"]), float(cfg["creep_window"]))
            for row in r:
                log(f"  w {row['width_m']:g} h/w {row['aspect']:g} slope {row['slope_deg']:g} +{row['margin_deg']:g} "
                    f"k {row['k_n_m']} {start}: beyond elastic {row['beyond_elastic_mm']:.4f} mm, slip "
                    f"{row['slip_mm']:.4f} mm, creep {row['creep_um_s']:.4f} um/s ({row['steps']} steps, "
                    f"{row['wall_s']:.0f} s)")
            rows.extend(r)
    return {"rows": rows}


def table(rows: list) -> str:
    """Markdown: one line per case, the plain start's numbers beside the settled start's."""
    by = {}
    for r in rows:
        by.setdefault((r["width_m"], r["aspect"], r["slope_deg"], r["margin_deg"], str(r["k_n_m"])), {})[r["start"]] = r
    head = ("| width m | h/w | slope deg | margin deg | k N/m | settled: beyond elastic mm | slip mm | creep um/s | "
            "plain: beyond elastic mm | slip mm | creep um/s | steps | settle steps |\n|" + "---|" * 13 + "\n")
    lines = []
    for key, d in by.items():
        s, p = d.get("settled", {}), d.get("plain", {})

        def f(r, k, fmt):
            return format(r[k], fmt) if k in r else "-"

        lines.append(f"| {key[0]:g} | {key[1]:g} | {key[2]:g} | {key[3]:g} | {key[4]} | {f(s, 'beyond_elastic_mm', '.4f')} | "
                     f"{f(s, 'slip_mm', '.4f')} | {f(s, 'creep_um_s', '.4f')} | {f(p, 'beyond_elastic_mm', '.4f')} | "
                     f"{f(p, 'slip_mm', '.4f')} | {f(p, 'creep_um_s', '.4f')} | {s.get('steps', p.get('steps', '-'))} | "
                     f"{s.get('settle_steps', '-')}{' (floor)' if s.get('floor') else ''} |")
    return head + "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.static_friction", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--subset", choices=sorted(CONFIG), default="full", help="the matrix (full) or a small CPU one (quick)")
    ap.add_argument("--duration", type=float, default=None, help="simulated seconds per case (default: the subset's)")
    ap.add_argument("--creep-window", type=float, default=None, help="creep over the last this many s (default: duration/6)")
    ap.add_argument("--widths", type=float, nargs="+", default=None)
    ap.add_argument("--slopes", type=float, nargs="+", default=None)
    ap.add_argument("--out", default=None, help="result stem (default benchmarks/results/static_friction-<device>)")
    a = ap.parse_args()
    import warp as wp

    from benchmarks.common import RESULTS, commit, device_name, write_json

    wp.config.quiet = True
    cfg = dict(CONFIG[a.subset])
    if a.duration is not None:
        cfg["duration"] = a.duration
        cfg["creep_window"] = a.duration / 6.0
    if a.creep_window is not None:
        cfg["creep_window"] = a.creep_window
    if a.widths:
        cfg["widths"] = a.widths
    if a.slopes:
        cfg["slopes"] = a.slopes
    res = run(a.device, cfg)
    stem = a.out or str(RESULTS / f"static_friction-{a.device.replace(':', '')}")
    head = (f"# Static friction (issue 36): {device_name(a.device)}, commit {commit()}, {cfg['duration']:g} s per case, "
            f"creep over the last {cfg['creep_window']:g} s\n\n")
    md = head + table(res["rows"])
    with open(stem + ".md", "w") as f:
        f.write(md)
    write_json(dict(res, config=cfg, device=a.device, commit=commit()), stem + ".json")
    print(md)


if __name__ == "__main__":
    main()
