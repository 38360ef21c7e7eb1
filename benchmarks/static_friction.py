"""Static friction without creep (issue 36): blocks resting on fixed planes a little below their friction limit.

Each case is a width x width x (aspect x width) block (2600 kg/m3) resting in contact, with no gap and no pre-set
penetration, on a fixed slab dipping ``slope`` degrees, friction angle slope + margin, normal = shear stiffness k
per contact point, gravity from t = 0, run for ``duration`` s at the solver's stable step, once from the plain start
and once from the settled one (BlockOptions.start; BlockSolver.settle). The stiffness axis (``stiffness``) takes:

- ``"default"``: the solver's defaults, k_n = 0.1 E L, k_s = k_n / 2.5;
- ``"<K>Pa/m"``: a joint stiffness K [Pa/m] (the issue's 1 MPa/m - 10 GPa/m), k = K w^2 / 4 per point: the block's
  base face w x w shared by its four corner points (a 20 m block on 1e6 Pa/m gets 1e8 N/m per point, a 0.2 m block
  1e4 N/m per point);
- ``"<k>/pt"``: k [N/m] per contact point whatever the block (the issue's first matrix); run only for widths up to
  ``point_max_width`` (1e6 N/m per point under a 20 m block is m g / (4 k) = metres of penetration: no contact).

Measured at the centre of the block's base, along the dip:

- ``beyond_elastic_mm``: displacement from where it was placed minus the elastic shear deflection with the load
  shared by the four base corners, m g sin(slope) / (4 k_s) (the issue's measure);
- ``slip_mm``: displacement minus the largest spring extension max |f_s| / k_s of its contact points (a corner
  whose normal force is too small for its share of the shear slides until its spring sits at its cap, and the
  others carry more: the elastic deflection of the base is then its most loaded spring's);
- ``locked_mm``: the displacement of the case's locked twin (the same block on its own slab in the same model, same
  start, friction LOCK_DEG = 89 deg on both: mu = 57; ``locked_max_at_cap`` counts its points at their cap, checked at
  every step of the first 2 s (at most 400 times) and 50 times after: 0 means locked), the deflection of this very model (springs, tilt,
  contact geometry) with no slip possible; ``beyond_locked_mm`` = disp_mm - locked_mm (``--no-twins`` leaves them out);
- ``partial_slip_mm``: what statics predicts beyond the locked twin for a block whose uphill corners cannot keep the
  equal shear share the lock gives them (``partial_slip``): they slip at their cap, the downhill pair takes the rest;
  ``beyond_partial_mm`` = beyond_locked_mm - partial_slip_mm; ``max_at_cap``: the most of the block's points at their
  cap in a check (4: it slid as a whole at some time);
- ``creep_um_s``: displacement over the last ``creep_window`` s (10 s of a 60 s run) per second;
- ``points_at_cap``: its contact points whose spring sits at the Coulomb cap at the end (sliding or about to);
- ``tilt_mrad``: its rotation; ``settle_steps``: the settled start's steps (``floor``: it stopped at float32's
  chatter floor, BlockSolver.settle), ``relax_steps``: those of its second stage, friction on under kinetic damping;
- ``since_start_mm``: its displacement since t = 0 (the settled start's equilibrium; the plain start's placed pose),
  ``max_since_start_mm``: the largest |displacement since t = 0| seen in the cap checks and at the end (table column
  'since t=0': a stable block must not move after the equilibrium start).

Targets (issue 36): from the settled start the displacement beyond the elastic deflection <= 0.1 mm after 60 s;
from either start creep < 1 um/s. The summary counts ``beyond_locked_mm`` against the bound (``slip_mm`` in records
without twins) and beside it ``beyond_partial_mm``. Measured (CPU, 2026-11-29, docs/notes.md 'The locked twin'): the
twins stay locked, and a block on soft joints moves beyond its twin by its uphill corners' partial slip, 0.96-1.07 of
``partial_slip`` wherever the overturning moment unloads them (e = (h/w) tan(slope) above the margin's share): the lock
is not the elastic reference of a block at a finite friction (``beyond_elastic_mm`` assumes an equal share;
``slip_mm``, the most loaded spring's extension, reads the partial-slip state but also the base's rocking). Cases whose aspect is beyond the toppling limit h/w = 1 / tan(slope) are not run (they
topple). On springs the limit is lower (``topples_on_springs``): the base's corner pairs, normal stiffness
K w^2 / 4 each, tilt it by the overturning moment, which moves the weight's line further out; the downhill offset
of the weight's line e (a fraction of w / 2) is then e0 / (1 - K_c / K), e0 = (h/w) tan(slope), K_c = 2 rho g h^2 / w^2,
and the block topples when that reaches 1: K < K_c / (1 - e0) (a 0.2 m x 1.02 m block at 0.9 of the limit on
10 deg needs K > 1.3e7 Pa/m, so it topples on 1e7). Blocks of a
(width, stiffness, start) share one model (one block and its slab per case, 3 slab lengths apart), stepped at the
stiffest case's step: the cost is the groups' steps (duration / dt + the settling), not the rows. On a GPU a step of
these small models costs ~0.5 ms whatever its size (launch-bound: 0.41-0.56 ms per step on the H200 in
benchmarks/results/2026-11-28-cuda0-static-friction-20s.json), so ``--estimate`` prints each group's steps and the
estimated wall time at ``--step-cost-us`` without running anything.

    python -m benchmarks.static_friction --device cuda:0 --subset h200 --duration 60   # ~6-8 min on an H200
    python -m benchmarks.static_friction --subset full --duration 60 --estimate        # rows, steps, minutes
    python -m benchmarks.static_friction --device cpu --subset quick --duration 6      # a small CPU subset
    python -m benchmarks.static_friction --device cuda:0 --groups 5:default 20:1e10Pa/m --starts settled \
        --out benchmarks/results/part-a                                                # chosen groups and starts
    python -m benchmarks.static_friction --merge part-a.json part-b.json --out benchmarks/results/whole

``--groups W:SPEC ...`` runs exactly those (width, stiffness) groups over the full matrix's aspects, slopes and
margins; ``--starts`` one start or both; ``--merge`` joins the records of such parts (one device, one duration)
into one table, so that the parts can run side by side as separate processes on one GPU.

The table goes to benchmarks/results/static_friction-<device>[-<subset>].md (and .json).
"""

from __future__ import annotations

import argparse
import math
import time
import warnings

import numpy as np

JOINT = ["1e6Pa/m", "1e8Pa/m", "1e10Pa/m"]
CONFIG = {
    "quick": dict(widths=[1.0, 8.0], aspects=[1.0], slopes=[35.0], margins=[0.1], stiffness=["default", "1e8/pt", "1e8Pa/m"],
                  point_max_width=1.0, duration=6.0, creep_window=1.0),
    # the issue's matrix: 22 (width, stiffness) groups, 352 cases, 704 rows; ~3.4 h on an H200 at 60 s (--estimate)
    "full": dict(widths=[0.2, 1.0, 5.0, 20.0], aspects=[0.5, 1.0, "0.9topple"], slopes=[10.0, 35.0, 60.0],
                 margins=[0.1, 1.0], stiffness=["default", *JOINT, "1e6/pt", "1e8/pt", "1e10/pt"], point_max_width=1.0,
                 duration=60.0, creep_window=10.0),
    # what fits one ~8 minute GPU call at 60 s (with ~2 min of kernel builds; --estimate: 270k steps per start, 320
    # rows, ~5-6 min at 0.5 ms per step plus the settling): every width, slope, aspect, margin and both starts, on
    # the joint stiffnesses whose step is large enough; the small blocks on stiff joints and the defaults (their step
    # is 20-120 us: 0.5-2.5 M steps per 60 s) are the full subset's
    "h200": dict(widths=[0.2, 1.0, 5.0, 20.0], aspects=[0.5, 1.0, "0.9topple"], slopes=[10.0, 35.0, 60.0],
                 margins=[0.1, 1.0], stiffness=["default", "1e6Pa/m", "1e7Pa/m", "1e8Pa/m", "1e9Pa/m"],
                 groups=[[0.2, "1e6Pa/m"], [0.2, "1e7Pa/m"], [1.0, "1e6Pa/m"], [1.0, "1e8Pa/m"], [5.0, "1e6Pa/m"],
                         [5.0, "1e8Pa/m"], [20.0, "1e6Pa/m"], [20.0, "1e8Pa/m"], [20.0, "1e9Pa/m"], [20.0, "default"]],
                 duration=60.0, creep_window=10.0),
}
RHO = 2600.0
# the locked twin's friction angle: mu = tan 89 deg = 57, so a point sticks unless its shear exceeds 57 x its normal
# force (a standing block's least loaded corner carries far more than 1/57 of its shear share); run_group checks it
LOCK_DEG = 89.0


def _rot_y(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])


def _quat(m: np.ndarray) -> tuple:
    """Rotation matrix -> quaternion (x, y, z, w), for a rotation about y."""
    w = math.sqrt(max(0.0, 1 + np.trace(m))) / 2
    return (0.0, math.copysign(math.sqrt(max(0.0, 1 - m[0, 0] + m[1, 1] - m[2, 2])) / 2, m[0, 2] - m[2, 0]), 0.0, w)


def k_point(width: float, spec) -> float | None:
    """Per-point stiffness [N/m] of a stiffness spec for a block of base width x width (None: the solver's default)."""
    if spec in (None, "default"):
        return None
    spec = str(spec)
    if spec.endswith("Pa/m"):  # joint stiffness x the base face's area shared by its 4 corner points
        return float(spec[:-4]) * width * width / 4.0
    if spec.endswith("/pt"):
        return float(spec[:-3])
    return float(spec)  # a bare number: N/m per point (the records of 2026-11-28)


def topple_stiffness(width: float, aspect: float, slope: float) -> float:
    """K [Pa/m] below which a block of that width and aspect on that slope topples on its joint springs (module
    docstring); inf at or beyond the rigid limit."""
    e0 = aspect * math.tan(math.radians(slope))
    if e0 >= 1.0:
        return math.inf
    return 2.0 * RHO * 9.81 * aspect * aspect / (1.0 - e0)


def partial_slip(aspect: float, slope: float, margin: float, k_joint: float) -> float:
    """The displacement beyond the locked twin's of a block whose uphill corners slip, as a fraction of the equal
    share's deflection W sin(slope) / (4 k_s). Statics of a rigid block on four corner springs: the overturning
    moment of the weight about the base leaves the uphill pair a normal force W cos(slope) (1 - e) / 4 each, e the
    weight line's offset on springs (module docstring: e0 / (1 - K_c / K)). Locked, each corner carries the equal
    share W sin(slope) / 4; Coulomb lets an uphill corner keep mu W cos(slope) (1 - e) / 4 at most, and the downhill
    pair takes the rest, W / 4 [2 sin - mu cos (1 - e)] each: its springs stretch beyond the equal share by
    W / (4 k_s) [sin - mu cos (1 - e)], and the base with them. Zero where the uphill corners can keep their share."""
    a, mu = math.radians(slope), math.tan(math.radians(slope + margin))
    e0 = aspect * math.tan(a)
    e = e0 / (1.0 - 2.0 * RHO * 9.81 * aspect * aspect / k_joint) if math.isfinite(k_joint) else e0
    return max(0.0, 1.0 - mu * (1.0 - e) / math.tan(a))


def _joint_k(width: float, spec) -> float:
    """The joint stiffness K [Pa/m] of a stiffness spec on a block of that width (k = K w^2 / 4 per point)."""
    k = k_point(width, spec)
    if k is None:  # the solver's default, 0.1 E L per point: GPa/m joints, far above any K_c here
        return math.inf
    return 4.0 * k / (width * width)


def cases(cfg: dict) -> list:
    """(width, aspect, slope, margin, stiffness spec) of the matrix, toppling aspects left out, per-point stiffnesses
    for widths up to point_max_width only."""
    out = []
    for w in cfg["widths"]:
        for k in cfg["stiffness"]:
            if str(k).endswith("/pt") and w > cfg.get("point_max_width", float("inf")):
                continue
            if cfg.get("groups") and [float(w), str(k)] not in [[float(g[0]), str(g[1])] for g in cfg["groups"]]:
                continue
            for s in cfg["slopes"]:
                limit = 1.0 / math.tan(math.radians(s))
                for a in cfg["aspects"]:
                    asp = 0.9 * limit if a == "0.9topple" else float(a)
                    if asp >= limit:
                        continue
                    if cfg.get("skip_spring_topple", True) and _joint_k(w, k) < topple_stiffness(w, asp, s):
                        continue  # topples on its springs (module docstring), and would stop its group's settling
                    for mg in cfg["margins"]:
                        out.append((float(w), asp, float(s), float(mg), k))
    return out


def group_model(device: str, group: list, twins: bool = False):
    """One model for the cases of ``group`` (same width and stiffness): each block and its slab, side by side.
    ``twins``: each case also gets its locked twin (the same block on its own slab, friction LOCK_DEG on both,
    placed after the cases: block 2 (len(group) + c) + 1 is case c's twin). Returns (model, frames: (R, n, d, h)
    per case)."""
    from rockwave.dda import geometry as G
    from rockwave.dda.blocks import BlockModel, BlockSpec, ContactMaterial

    specs, frames = [], []
    copies = [(c, False) for c in group] + ([(c, True) for c in group] if twins else [])
    for i, ((w, asp, s, mg, k), locked) in enumerate(copies):
        R = _rot_y(s)
        n, d = R @ [0.0, 0.0, 1.0], R @ [1.0, 0.0, 0.0]
        h = asp * w
        slab = (6 * w, 3 * w, w / 2)
        origin = np.array([0.0, 4.0 * w * i, 0.0])  # cases side by side along y, 1 slab width apart
        kp = k_point(w, k)
        mat = ContactMaterial(friction_angle_deg=LOCK_DEG if locked else s + mg, normal_stiffness=kp, shear_stiffness=kp)
        tag = "locked" if locked else ""
        specs.append(BlockSpec(G.box(slab), kind="fixed", orientation=_quat(R), position=tuple(origin), material=mat,
                               name=f"slab{tag}{i}"))
        specs.append(BlockSpec(G.box((w, w, h)), position=tuple(origin + (slab[2] + h) / 2 * n), orientation=_quat(R),
                               density=RHO, material=mat, name=f"block{tag}{i}"))
        if not locked:
            frames.append((R, n, d, h))
    return BlockModel(specs, device=device, check_overlap=False), frames


def group_steps(group: list, duration: float) -> tuple[int, float]:
    """(steps of ``duration`` s, the step [s]) of a group's model, from the solver's stable step (built on the CPU,
    nothing stepped)."""
    from rockwave.dda.blocks import BlockSolver

    model, _ = group_model("cpu", group)
    dt = BlockSolver(model).stable_dt(model.state())
    return int(round(duration / dt)), dt


def _contact_table(state, model) -> tuple:
    """(largest spring extension max |f_s| [N] of each block's contact points, its points at the Coulomb cap) from
    the contact history table (key = A * N + B: the block is B, the slab A)."""
    t = state.tables[0]
    keys, nc, ps = t["keys"].numpy(), t["nc"].numpy(), t["pstart"].numpy()
    shear = np.linalg.norm(t["shear"].numpy(), axis=1)
    fcap = t["fcap"].numpy()
    ext = np.zeros(model.num_blocks)
    at_cap = np.zeros(model.num_blocks, int)  # contact points whose spring sits at its Coulomb cap (sliding)
    for slot in np.nonzero(keys >= 0)[0]:
        b = int(keys[slot] % model.num_blocks)
        if nc[slot]:
            sl = slice(ps[slot], ps[slot] + nc[slot])
            ext[b] = max(ext[b], float(shear[sl].max()))
            at_cap[b] += int(np.count_nonzero(shear[sl] >= 0.999 * fcap[sl]))
    return ext, at_cap


def run_group(device: str, group: list, start: str, duration: float, window: float, twins: bool = True,
              cap_checks: int = 50) -> list:
    """One model for the cases of ``group`` (same width and stiffness): each block and its slab; a row per case.
    ``twins``: each case's locked twin (group_model) is stepped beside it. Every block's contact points are checked
    for the Coulomb cap at every step of the first 2 s (at most 400 checks), ``cap_checks`` times along the rest and at the end (``max_at_cap``, ``locked_max_at_cap``: the
    most points at their cap in a check; ``points_at_cap``: at the end)."""
    import warp as wp

    from rockwave.base.solver import TimeStep
    from rockwave.dda import geometry as G
    from rockwave.dda.blocks import BlockOptions, BlockSolver

    model, frames = group_model(device, group, twins=twins)
    state = model.state()
    solver = BlockSolver(model, options=BlockOptions(start=start))
    t0 = time.perf_counter()
    rep = solver.settle(state) if start == "settled" else {"start": "plain"}
    dt = solver.stable_dt(state)
    dta = wp.array([dt], dtype=float, device=device)
    steps = int(round(duration / dt))
    ncase = len(group)
    copies = 2 if twins else 1
    blocks = np.arange(1, 2 * ncase * copies, 2)  # the cases' blocks, then their twins'
    fr = frames * copies
    base0 = model.base_position[blocks] - np.array([f[3] / 2 * f[1] for f in fr])

    def base_disp():
        x = state.positions_numpy()[blocks]
        q = state.orientations_numpy()[blocks]
        out = np.zeros(len(blocks))
        for c, (R, n, d, h) in enumerate(fr):
            Rq = G.quat_to_matrix(q[c])
            base = x[c] + Rq @ (R.T @ (-h / 2 * n))
            out[c] = (base - base0[c]) @ d
        return out

    d_start = base_disp()  # t = 0: where the start put the blocks (the settled start: its equilibrium)
    moved_max = np.zeros(len(blocks))  # the largest |displacement since t = 0| seen in the checks
    t_window = duration - window
    d_window = None
    max_cap = np.zeros(model.num_blocks, int)  # the most points of each block at their cap in a check
    every = max(1, steps // max(cap_checks, 1))
    # densely over the first 2 s (every step, at most 400 checks): a released block slides within ~0.1-6 s (notes)
    dense_s = 2.0
    dense_every = max(1, int(dense_s / dt) // 400)
    for i in range(steps):
        solver.step(state, TimeStep(dt, state.time, dta))
        if d_window is None and state.time >= t_window - 0.5 * dt:
            d_window = base_disp()
        if cap_checks and ((i + 1) % every == 0 or (state.time <= dense_s and (i + 1) % dense_every == 0)):
            max_cap = np.maximum(max_cap, _contact_table(state, model)[1])
            moved_max = np.maximum(moved_max, np.abs(base_disp() - d_start))
    wp.synchronize_device(device)
    wall = time.perf_counter() - t0
    d_end = base_disp()
    if d_window is None:
        d_window = d_end
    moved_max = np.maximum(moved_max, np.abs(d_end - d_start))
    ext, at_cap = _contact_table(state, model)
    max_cap = np.maximum(max_cap, at_cap)
    twin_cap = max_cap
    ks = model.np["k_s"]
    q = state.orientations_numpy()[blocks]

    def tilt_of(c):
        R = fr[c][0]
        Rq = G.quat_to_matrix(q[c])
        return math.acos(min(1.0, (float(np.trace(Rq @ R.T)) - 1.0) / 2.0))

    rows = []
    for c, (w, asp, s, mg, k) in enumerate(group):
        b = blocks[c]
        m = model.np["mass"][b]
        elastic = m * 9.81 * math.sin(math.radians(s)) / (4.0 * ks[b])
        kp = float(model.np["k_n"][b])
        row = dict(width_m=w, aspect=round(asp, 3), slope_deg=s, margin_deg=mg, stiffness=str(k or "default"),
                   k_n_m=kp, k_joint_pa_m=4.0 * kp / (w * w), k_s=float(ks[b]), start=start, duration_s=steps * dt, steps=steps, dt_s=dt,
                   disp_mm=1e3 * d_end[c], elastic_mm=1e3 * elastic, beyond_elastic_mm=1e3 * (d_end[c] - elastic),
                   slip_mm=1e3 * (d_end[c] - ext[b] / ks[b]),
                   creep_um_s=1e6 * (d_end[c] - d_window[c]) / max(window, 1e-12),
                   since_start_mm=1e3 * (d_end[c] - d_start[c]), max_since_start_mm=1e3 * moved_max[c],
                   tilt_mrad=1e3 * tilt_of(c), settle_steps=rep.get("steps", 0),
                   relax_steps=rep.get("friction_stage", {}).get("steps", 0),
                   topples_on_springs=bool(4.0 * kp / (w * w) < topple_stiffness(w, asp, s)),
                   points_at_cap=int(at_cap[b]), max_at_cap=int(max_cap[b]),
                   floor=bool(rep.get("float32_floor", False)), settled=rep.get("start") == "settled",
                   wall_s=wall)
        if twins:  # the locked twin: this model's elastic deflection (springs, tilt, contact geometry), no slip
            t = ncase + c
            row.update(locked_mm=1e3 * d_end[t], beyond_locked_mm=1e3 * (d_end[c] - d_end[t]),
                       locked_slip_mm=1e3 * (d_end[t] - ext[blocks[t]] / ks[blocks[t]]),
                       locked_creep_um_s=1e6 * (d_end[t] - d_window[t]) / max(window, 1e-12),
                       locked_tilt_mrad=1e3 * tilt_of(t), locked_max_at_cap=int(twin_cap[blocks[t]]),
                       locked_deg=LOCK_DEG)
            # the uphill corners' partial slip (partial_slip) predicted from statics, and what is left beyond it
            ps_mm = 1e3 * elastic * partial_slip(asp, s, mg, 4.0 * kp / (w * w))
            row.update(partial_slip_mm=ps_mm, beyond_partial_mm=row["beyond_locked_mm"] - ps_mm)
            if twin_cap[blocks[t]]:
                warnings.warn(f"the locked twin of w {w:g} h/w {asp:.3g} slope {s:g} +{mg:g} {k} ({start}) had "
                              f"{int(twin_cap[blocks[t]])} contact point(s) at their Coulomb cap at {LOCK_DEG:g} deg: "
                              f"not locked, its locked_mm is not a pure elastic reference")
        rows.append(row)
    return rows


def parse_groups(specs: list) -> list:
    """``["0.2:default", "1:1e10Pa/m"]`` -> [[0.2, "default"], [1.0, "1e10Pa/m"]] (the CLI's --groups)."""
    out = []
    for s in specs:
        w, sep, k = str(s).partition(":")
        if not sep or not k:
            raise ValueError(f"--groups takes WIDTH:STIFFNESS (e.g. 0.2:default, 1:1e10Pa/m, 1:1e8/pt), not {s!r}")
        k_point(float(w), k)  # the stiffness spec must read
        out.append([float(w), k])
    return out


def with_groups(cfg: dict, groups: list) -> dict:
    """cfg restricted to exactly ``groups`` ([[width, spec], ...]): their widths and stiffnesses, per-point specs at any
    width (the full matrix leaves them out above 1 m)."""
    cfg = dict(cfg, groups=groups, widths=sorted({float(g[0]) for g in groups}))
    cfg["stiffness"] = list(dict.fromkeys(str(g[1]) for g in groups))
    cfg.pop("point_max_width", None)
    return cfg


def merge(records: list) -> dict:
    """The rows of several records of one device (parts run side by side, each its own duration: every row keeps
    its duration_s) as one record."""
    devs = {r.get("device") for r in records}
    if len(devs) > 1:
        raise ValueError(f"records of different devices {sorted(map(str, devs))}")
    rows = [row for r in records for row in r["rows"]]
    seen = set()
    for row in rows:
        key = (row["width_m"], row["aspect"], row["slope_deg"], row["margin_deg"], row["stiffness"], row["start"])
        if key in seen:
            raise ValueError(f"row {key} in two records")
        seen.add(key)
    return dict(rows=rows, skipped=[s for r in records for s in r.get("skipped", [])], config=records[0]["config"],
                configs=[r["config"] for r in records], device=records[0].get("device"),
                commit=",".join(dict.fromkeys(str(r.get("commit")) for r in records)))


def groups_of(cfg: dict) -> dict:
    """{(width, stiffness spec): [cases]} of the matrix."""
    groups: dict = {}
    for c in cases(cfg):
        groups.setdefault((c[0], c[4]), []).append(c)
    return groups


def estimate(cfg: dict, step_cost_us: float = 500.0, settle_steps: int = 5000) -> dict:
    """Each group's steps for cfg's duration (both starts; the settled start's settling taken as ``settle_steps``,
    typical of the 2026-11-28 record: 2,700-5,500, up to 20,000 where it does not converge) and the wall time at
    ``step_cost_us`` per step; groups over cfg's max_group_steps are marked skipped (run() leaves them out)."""
    out, total, rows = [], 0.0, 0
    for (w, k), group in groups_of(cfg).items():
        steps, dt = group_steps(group, float(cfg["duration"]))
        skip = steps > cfg.get("max_group_steps", float("inf"))
        wall = 1e-6 * step_cost_us * (2 * steps + settle_steps)
        if not skip:
            total += wall
            rows += 2 * len(group)
        out.append(dict(width_m=w, stiffness=str(k or "default"), cases=len(group), dt_s=dt, steps=steps,
                        est_wall_s=wall, skipped=skip))
    return {"groups": out, "rows": rows, "est_wall_s": total}


def run(device: str, cfg: dict) -> dict:
    """The matrix of cfg (CONFIG's keys); returns {"rows": [...], "skipped": [...]} (one row per case and start;
    the groups whose step count exceeds cfg's max_group_steps are skipped and listed)."""
    from benchmarks.common import log

    rows, skipped = [], []
    for (w, k), group in groups_of(cfg).items():
        if "max_group_steps" in cfg:
            steps, dt = group_steps(group, float(cfg["duration"]))
            if steps > cfg["max_group_steps"]:
                skipped.append(dict(width_m=w, stiffness=str(k or "default"), steps=steps, dt_s=dt))
                log(f"  w {w:g} {k}: {steps} steps of {dt:.3g} s > {cfg['max_group_steps']}: skipped")
                continue
        for start in cfg.get("starts", ("plain", "settled")):
            r = run_group(device, group, start, float(cfg["duration"]), float(cfg["creep_window"]),
                          twins=cfg.get("twins", True))
            for row in r:
                twin = (f", beyond locked {row['beyond_locked_mm']:.4f} mm (twin {row['locked_mm']:.4f} mm, "
                        f"{row['locked_max_at_cap']} at cap)" if "locked_mm" in row else "")
                log(f"  w {row['width_m']:g} h/w {row['aspect']:g} slope {row['slope_deg']:g} +{row['margin_deg']:g} "
                    f"k {row['stiffness']} ({row['k_n_m']:.3g} N/m) {start}: beyond elastic {row['beyond_elastic_mm']:.4f} mm, slip "
                    f"{row['slip_mm']:.4f} mm{twin}, creep {row['creep_um_s']:.4f} um/s ({row['steps']} steps, "
                    f"{row['wall_s']:.0f} s)")
            rows.extend(r)
    return {"rows": rows, "skipped": skipped}


def slip_of(r: dict) -> float:
    """A row's slip against the bound [mm]: beyond_locked_mm (the displacement beyond its locked twin's) where the
    record has a twin, else slip_mm (records before the twins)."""
    return r["beyond_locked_mm"] if "beyond_locked_mm" in r else r["slip_mm"]


def summary(rows: list, slip_bound_mm: float = 0.1, creep_bound_um_s: float = 1.0) -> str:
    """The targets, counted: rows that stand (not topples_on_springs) meeting the slip bound from the settled start
    (slip_of: beyond the locked twin where there is one) and the creep bound from either start; rows predicted to
    topple and whether they did (moved > 10 mm)."""
    for r in rows:
        if "topples_on_springs" not in r:  # older records
            r["topples_on_springs"] = bool(r["k_joint_pa_m"] < topple_stiffness(r["width_m"], r["aspect"], r["slope_deg"]))
    stand = [r for r in rows if not r["topples_on_springs"]]
    settled = [r for r in stand if r["start"] == "settled" and r.get("settled", True)]
    twins = all("beyond_locked_mm" in r for r in settled) and bool(settled)
    measure = "beyond its locked twin's displacement (beyond_locked_mm)" if twins else "slip beyond the elastic deflection (slip_mm)"
    ok_slip = [r for r in settled if slip_of(r) <= slip_bound_mm]
    ok_creep = [r for r in stand if abs(r["creep_um_s"]) < creep_bound_um_s]
    fell = [r for r in rows if r["topples_on_springs"]]
    fell_did = [r for r in fell if abs(r["disp_mm"]) > 10.0]
    not_settled = [r for r in stand if r["start"] == "settled" and not r.get("settled", True)]
    worst_slip = max((abs(slip_of(r)) for r in settled), default=float("nan"))
    worst_creep = max((abs(r["creep_um_s"]) for r in stand), default=float("nan"))
    over = [r for r in settled if slip_of(r) > slip_bound_mm]
    stuck = [r for r in over if r.get("points_at_cap") == 0]
    known = [r for r in over if "points_at_cap" in r]
    stuck_note = (f" Of the {len(over)} beyond it, {len(stuck)} have no contact point at its Coulomb cap at the end."
                  if known else "")
    twin_note = ""
    if twins:
        old_over = [r for r in settled if r["slip_mm"] > slip_bound_mm]
        unlocked = [r for r in rows if r.get("locked_max_at_cap", 0) > 0]
        plain = [r for r in stand if r["start"] == "plain" and "beyond_locked_mm" in r]
        worst_plain = max((abs(r["beyond_locked_mm"]) for r in plain), default=float("nan"))
        part = [r for r in settled if "beyond_partial_mm" in r]
        ok_part = [r for r in part if abs(r["beyond_partial_mm"]) <= slip_bound_mm]
        slid = [r for r in settled if r.get("max_at_cap", 0) >= 4]
        worst_part = max(part, key=lambda r: abs(r["beyond_partial_mm"]), default=None)
        wp_txt = (f"{worst_part['beyond_partial_mm']:.4f} mm: w {worst_part['width_m']:g} h/w {worst_part['aspect']:g} "
                  f"slope {worst_part['slope_deg']:g} +{worst_part['margin_deg']:g} {worst_part['stiffness']}" if worst_part else "-")
        twin_note = (f" Beyond the locked twin plus the uphill corners' partial slip predicted by statics "
                     f"(beyond_partial_mm): {len(ok_part)} of {len(part)} within {slip_bound_mm:g} mm (largest abs {wp_txt});"
                     f" settled rows with every contact point at its cap at some check (the block slid as a whole): "
                     f"{len(slid)}.")
        twin_note += (f" Against the corner-spring measure (slip_mm) {len(old_over)} settled rows would be over "
                     f"{slip_bound_mm:g} mm (largest {max((r['slip_mm'] for r in settled), default=float('nan')):.4f}"
                     f" mm) and against the equal share (beyond_elastic_mm) "
                     f"{sum(r['beyond_elastic_mm'] > slip_bound_mm for r in settled)}. Locked twins with a point at "
                     f"their cap at any check ({LOCK_DEG:g} deg not enough): {len(unlocked)} rows. Plain start beyond "
                     f"its twin (the slip while the contacts load): largest abs {worst_plain:.4f} mm.")
    since = [r for r in settled if "max_since_start_mm" in r]
    if since:  # a stable block must not move after the equilibrium start
        worst = max(since, key=lambda r: r["max_since_start_mm"])
        twin_note += (f" Settled start, the largest displacement after t = 0 seen in the checks (max_since_start_mm): "
                      f"{sum(r['max_since_start_mm'] <= slip_bound_mm for r in since)} of {len(since)} within "
                      f"{slip_bound_mm:g} mm (largest {worst['max_since_start_mm']:.4f} mm: w {worst['width_m']:g} h/w "
                      f"{worst['aspect']:g} slope {worst['slope_deg']:g} +{worst['margin_deg']:g} {worst['stiffness']}).")
    return (f"Standing rows (not predicted to topple on their springs): {len(stand)}. Settled start: {len(ok_slip)} of "
            f"{len(settled)} within {slip_bound_mm:g} mm {measure} (largest abs {worst_slip:.4f} mm; "
            f"{len(not_settled)} more fell back to the plain start).{stuck_note}{twin_note} Creep below "
            f"{creep_bound_um_s:g} um/s: {len(ok_creep)} of {len(stand)} rows, both starts (largest "
            f"{worst_creep:.3f} um/s). Predicted to topple on their springs (K < K_c / (1 - e0)): {len(fell)} rows, "
            f"{len(fell_did)} of them toppled.\n\n")


def table(rows: list) -> str:
    """Markdown: one line per case, the plain start's numbers beside the settled start's."""
    by = {}
    for r in rows:
        k = r.get("stiffness", r["k_n_m"])  # records before the stiffness axis: k_n_m was the spec
        kp = r["k_n_m"] if isinstance(r["k_n_m"], float) and "stiffness" in r else None
        by.setdefault((r["width_m"], r["aspect"], r["slope_deg"], r["margin_deg"], str(k), kp), {})[r["start"]] = r
    twins = any("locked_mm" in r for r in rows)
    tw = "beyond locked mm | partial slip mm | locked mm | max at cap | " if twins else ""
    since = any("max_since_start_mm" in r for r in rows)  # the largest displacement after t = 0 (newer records)
    sc = "since t=0 mm | " if since else ""
    head = (f"| width m | h/w | slope deg | margin deg | stiffness | k N/m per point | settled: {tw}beyond elastic mm | slip mm | "
            f"creep um/s | {sc}plain: {tw}beyond elastic mm | slip mm | creep um/s | {sc}steps | s | settle steps |\n|"
            + "---|" * (15 + 8 * twins + 2 * since) + "\n")
    lines = []
    for key, d in by.items():
        s, p = d.get("settled", {}), d.get("plain", {})

        def f(r, k, fmt):
            return format(r[k], fmt) if k in r else "-"

        kp = "-" if key[5] is None else f"{key[5]:.3g}"
        def t(r):
            if not twins:
                return ""
            cap = f" (twin {r['locked_max_at_cap']} at cap)" if r.get("locked_max_at_cap") else ""
            return (f"{f(r, 'beyond_locked_mm', '.4f')}{cap} | {f(r, 'partial_slip_mm', '.4f')} | {f(r, 'locked_mm', '.4f')} | "
                    f"{r.get('max_at_cap', '-')} | ")

        def m(r):
            return f"{f(r, 'max_since_start_mm', '.4f')} | " if since else ""

        relax = f" + {s['relax_steps']} friction" if s.get("relax_steps") else ""
        lines.append(f"| {key[0]:g} | {key[1]:g} | {key[2]:g} | {key[3]:g} | {key[4]} | {kp} | {t(s)}{f(s, 'beyond_elastic_mm', '.4f')} | "
                     f"{f(s, 'slip_mm', '.4f')} | {f(s, 'creep_um_s', '.4f')} | {m(s)}{t(p)}{f(p, 'beyond_elastic_mm', '.4f')} | "
                     f"{f(p, 'slip_mm', '.4f')} | {f(p, 'creep_um_s', '.4f')} | {m(p)}{s.get('steps', p.get('steps', '-'))} | "
                     f"{format(s.get('duration_s', p.get('duration_s', float('nan'))), '.3g')} | "
                     f"{s.get('settle_steps', '-')}{relax}{' (floor)' if s.get('floor') else ''} |")
    return head + "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.static_friction", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--subset", choices=sorted(CONFIG), default="full",
                    help="the matrix (full), what fits ~8 min on an H200 at 60 s (h200) or a small CPU one (quick)")
    ap.add_argument("--duration", type=float, default=None, help="simulated seconds per case (default: the subset's)")
    ap.add_argument("--creep-window", type=float, default=None,
                    help="creep over the last this many s (default: 10 s, or duration/6 where that is less)")
    ap.add_argument("--stiffness", nargs="+", default=None, help="stiffness specs: default, <K>Pa/m, <k>/pt")
    ap.add_argument("--max-group-steps", type=int, default=None, help="skip groups needing more steps than this")
    ap.add_argument("--estimate", action="store_true", help="print each group's steps and the estimated wall time; run nothing")
    ap.add_argument("--step-cost-us", type=float, default=500.0, help="GPU cost of a step for --estimate (H200: ~500 us)")
    ap.add_argument("--widths", type=float, nargs="+", default=None)
    ap.add_argument("--slopes", type=float, nargs="+", default=None)
    ap.add_argument("--aspects", nargs="+", default=None, help="h/w values or 0.9topple (default: the subset's)")
    ap.add_argument("--margins", type=float, nargs="+", default=None)
    ap.add_argument("--no-twins", action="store_true", help="leave out the locked twins (half the blocks; no beyond_locked_mm)")
    ap.add_argument("--groups", nargs="+", default=None, metavar="W:SPEC",
                    help="exactly these (width, stiffness) groups, e.g. 0.2:default 1:1e10Pa/m (the full matrix's aspects, slopes, margins)")
    ap.add_argument("--starts", nargs="+", choices=["plain", "settled"], default=None, help="one start or both (default both)")
    ap.add_argument("--merge", nargs="+", default=None, metavar="JSON", help="join these records into one (--out) and exit")
    ap.add_argument("--out", default=None, help="result stem (default benchmarks/results/static_friction-<device>)")
    a = ap.parse_args()
    if a.merge:
        import json

        from benchmarks.common import RESULTS, write_json

        rec = merge([json.load(open(f)) for f in a.merge])
        stem = a.out or str(RESULTS / "static_friction-merged")
        cfg = rec["config"]
        spans = sorted({(float(c["duration"]), float(c["creep_window"])) for c in rec["configs"]})
        span = ", ".join(f"{d:g} s (creep over the last {w:g} s)" for d, w in spans)
        md = (f"# Static friction (issue 36): {rec['device']}, commit {rec['commit']}, {span} per case (column 's')"
              f"\n\nMerged from {', '.join(a.merge)}.\n\n")
        md += summary(rec["rows"]) + table(rec["rows"])
        with open(stem + ".md", "w") as f:
            f.write(md)
        write_json(rec, stem + ".json")
        print(md)
        return
    import warp as wp

    from benchmarks.common import RESULTS, commit, device_name, write_json

    wp.config.quiet = True
    cfg = dict(CONFIG[a.subset])
    if a.duration is not None:
        cfg["duration"] = a.duration
        cfg["creep_window"] = min(10.0, a.duration / 6.0)
    if a.creep_window is not None:
        cfg["creep_window"] = a.creep_window
    if a.widths:
        cfg["widths"] = a.widths
        cfg.pop("groups", None)
    if a.stiffness:
        cfg["stiffness"] = a.stiffness
        cfg.pop("groups", None)
    if a.groups:
        cfg = with_groups(dict(CONFIG["full"], duration=cfg["duration"], creep_window=cfg["creep_window"]),
                          parse_groups(a.groups))
    if a.slopes:  # also over --groups
        cfg["slopes"] = a.slopes
    if a.aspects:
        cfg["aspects"] = [x if x == "0.9topple" else float(x) for x in a.aspects]
    if a.margins:
        cfg["margins"] = a.margins
    if a.no_twins:
        cfg["twins"] = False
    if a.starts:
        cfg["starts"] = a.starts
    if a.max_group_steps is not None:
        cfg["max_group_steps"] = a.max_group_steps
    if a.estimate:
        est = estimate(cfg, a.step_cost_us)
        for g in est["groups"]:
            print(f"  w {g['width_m']:g} {g['stiffness']}: {g['cases']} cases, dt {g['dt_s']:.3g} s, {g['steps']} steps, "
                  f"~{g['est_wall_s']:.0f} s for both starts{' (skipped)' if g['skipped'] else ''}")
        print(f"{a.subset}, {cfg['duration']:g} s: {est['rows']} rows, ~{est['est_wall_s'] / 60:.1f} min at "
              f"{a.step_cost_us:g} us per step")
        return
    res = run(a.device, cfg)
    stem = a.out or str(RESULTS / f"static_friction-{a.device.replace(':', '')}-{a.subset}")
    head = (f"# Static friction (issue 36): {device_name(a.device)}, commit {commit()}, {cfg['duration']:g} s per case, "
            f"creep over the last {cfg['creep_window']:g} s\n\n")
    md = head + summary(res["rows"]) + table(res["rows"])
    if res["skipped"]:
        md += "\nSkipped (step count over max_group_steps): " + ", ".join(
            f"w {g['width_m']:g} m {g['stiffness']} ({g['steps']} steps)" for g in res["skipped"]) + "\n"
    with open(stem + ".md", "w") as f:
        f.write(md)
    write_json(dict(res, config=cfg, device=a.device, commit=commit()), stem + ".json")
    print(md)


if __name__ == "__main__":
    main()
