"""``python -m rockwave preview RUN_DIR --frame N``: one frame of a run as a PNG, without a 3D package.

What it reads: the run's USD stage (the path in ``RUN_DIR/run.json`` under ``"usd"``, else the one
``.usdc``/``.usda``/``.usd`` file in RUN_DIR), at time code N (= frame N):
- ``/World/fluid`` points, velocities and ``primvars:pressure`` (particles coloured by speed or
  pressure);
- every ``UsdGeom.Mesh`` under ``/World/blocks`` (points, xform at time N), outlined;
- ``/World/fluid_surface`` in 2D (the contour, drawn as a line);
- the root layer's ``customLayerData["rockwave"]`` for the dimension and the particle spacing
  (a stage without it: 2D when upAxis is Y, spacing from the particle widths).

2D scenes are drawn in their x-y plane. 3D scenes are drawn as an orthographic view along
``--axis`` (default y: the x-z side view; nearer particles drawn over farther ones), or, with
``--slice POS``, only the particles within one spacing of the plane at POS along that axis (blocks:
those the plane cuts).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from rockwave.output.recorders import scene_boxes
from rockwave.scene.format import SceneError, load_scene


class PreviewError(ValueError):
    """The run folder or frame cannot be previewed; the message says why."""


def find_stage(run_dir: str | os.PathLike) -> Path:
    run = Path(run_dir)
    if not run.is_dir():
        raise PreviewError(f"{run}: not a folder")
    info = run / "run.json"
    if info.is_file():
        try:
            usd = json.loads(info.read_text()).get("usd")
        except (OSError, ValueError):
            usd = None
        if usd:
            for cand in (Path(usd), run / Path(usd).name):
                if cand.is_file():
                    return cand
    found = sorted(p for ext in ("*.usdc", "*.usda", "*.usd") for p in run.glob(ext))
    if not found:
        raise PreviewError(f"{run}: no USD stage (run.json names none and there is no .usdc/.usda/.usd file); "
                           "was the run made with output.usd = ''?")
    return found[0]


def _hull(p: np.ndarray) -> np.ndarray:
    """Convex hull (Andrew's monotone chain) of 2D points, counter-clockwise."""
    pts = sorted(set(map(tuple, np.round(p, 12))))
    if len(pts) <= 2:
        return np.asarray(pts)

    def half(seq):
        out = []
        for q in seq:
            while len(out) >= 2 and (out[-1][0] - out[-2][0]) * (q[1] - out[-2][1]) - (out[-1][1] - out[-2][1]) * (q[0] - out[-2][0]) <= 0:
                out.pop()
            out.append(q)
        return out

    lo, hi = half(pts), half(pts[::-1])
    return np.asarray(lo[:-1] + hi[:-1])


def _quat_rows(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of unit quaternions (n, 4) given as (x, y, z, w), for row vectors (p @ R)."""
    x, y, z, w = (q[:, i] for i in range(4))
    r = np.empty((len(q), 3, 3))
    r[:, 0, 0], r[:, 0, 1], r[:, 0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)
    r[:, 1, 0], r[:, 1, 1], r[:, 1, 2] = 2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)
    r[:, 2, 0], r[:, 2, 1], r[:, 2, 2] = 2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)
    return np.transpose(r, (0, 2, 1))  # column-vector matrices transposed: p_world = p @ R^T


def _instances(prim, t) -> list:
    """World vertices of each instance of a PointInstancer whose prototypes are meshes (positions and orientations;
    the float ``orientationsf`` where authored, else ``orientations``)."""
    from pxr import UsdGeom

    inst = UsdGeom.PointInstancer(prim)
    pos = inst.GetPositionsAttr().Get(t)
    if pos is None or len(pos) == 0:
        return []
    pos = np.asarray(pos, np.float64).reshape(-1, 3)
    of = prim.GetAttribute("orientationsf")
    q = of.Get(t) if of and of.HasAuthoredValue() else inst.GetOrientationsAttr().Get(t)
    q = np.asarray(q, np.float64).reshape(-1, 4) if q is not None and len(q) == len(pos) else np.tile([0.0, 0, 0, 1], (len(pos), 1))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    idx = np.asarray(inst.GetProtoIndicesAttr().Get(t), np.int64)
    protos = []
    stage = prim.GetStage()
    for path in inst.GetPrototypesRel().GetTargets():
        p = UsdGeom.Mesh(stage.GetPrimAtPath(path)).GetPointsAttr().Get()
        protos.append(np.asarray(p, np.float64).reshape(-1, 3) if p is not None else np.zeros((0, 3)))
    rot = _quat_rows(q)
    return [protos[k] @ rot[i] + pos[i] for i, k in enumerate(idx)]


def load_frame(run_dir: str | os.PathLike, frame: int | None = None) -> dict:
    """The data of one frame: dict with dim, spacing, frame, time_s, x (n, 3), v (n, 3),
    pressure (n,) or None, blocks (list of world vertex arrays), contour ((S, 2, 3) or None),
    frames (first, last)."""
    from pxr import Usd, UsdGeom

    path = find_stage(run_dir)
    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise PreviewError(f"{path}: cannot open the USD stage")
    first, last = int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode())
    if frame is None:
        frame = last
    if frame < first or frame > last:
        raise PreviewError(f"frame {frame} is not in the run: frames {first}..{last}")
    info = dict(stage.GetRootLayer().customLayerData.get("rockwave", {}))
    dim = int(info.get("dimension") or (2 if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y else 3))
    t = Usd.TimeCode(frame)
    fluid_path = info.get("fluid_prim") or "/World/fluid"
    fluid = stage.GetPrimAtPath(fluid_path)
    x = v = pr = None
    spacing = float(info.get("spacing_m") or 0.0)
    if fluid and fluid.IsValid():
        pts = fluid.GetAttribute("points").Get(t)
        x = np.asarray(pts, np.float64).reshape(-1, 3) if pts is not None else np.zeros((0, 3))
        vel = fluid.GetAttribute("velocities").Get(t)
        v = np.asarray(vel, np.float64).reshape(-1, 3) if vel is not None and len(vel) == len(x) else np.zeros_like(x)
        pa = fluid.GetAttribute("primvars:pressure")
        pv = pa.Get(t) if pa else None
        pr = np.asarray(pv, np.float64) if pv is not None and len(pv) == len(x) else None
        if not spacing:
            w = fluid.GetAttribute("widths").Get()
            spacing = float(w[0]) if w else 0.0
    else:
        x, v = np.zeros((0, 3)), np.zeros((0, 3))
    blocks = []
    root = stage.GetPrimAtPath(info.get("blocks_prim") or "/World/blocks")
    if root and root.IsValid():
        cache = UsdGeom.XformCache(t)
        it = iter(Usd.PrimRange(root))
        for prim in it:
            if prim.IsA(UsdGeom.PointInstancer):  # many blocks: instances of prototype meshes (rockwave/output/recorders.py)
                blocks += _instances(prim, t)
                it.PruneChildren()  # (its prototypes are not blocks of their own)
                continue
            if not prim.IsA(UsdGeom.Mesh):
                continue
            p = UsdGeom.Mesh(prim).GetPointsAttr().Get(t)
            if p is None or len(p) == 0:
                continue
            m = np.asarray(cache.GetLocalToWorldTransform(prim), np.float64)  # row-vector convention
            local = np.asarray(p, np.float64).reshape(-1, 3)
            blocks.append(local @ m[:3, :3] + m[3, :3])
    contour = None
    sp = stage.GetPrimAtPath(info.get("surface_prim") or "/World/fluid_surface")
    if dim == 2 and sp and sp.IsValid() and sp.IsA(UsdGeom.BasisCurves):
        cp = sp.GetAttribute("points").Get(t)
        if cp is not None:
            contour = np.asarray(cp, np.float64).reshape(-1, 2, 3)
    if not spacing and len(x) > 1:
        spacing = float(np.min(np.ptp(x, axis=0)[:dim]) / max(2.0, len(x) ** (1.0 / dim)))
    return {"dim": dim, "spacing": spacing or 0.01, "frame": frame, "time_s": frame / stage.GetTimeCodesPerSecond(),
            "x": x, "v": v, "pressure": pr, "blocks": blocks, "contour": contour, "frames": (first, last), "stage": str(path),
            "boxes": _boxes(info, dim)}


def _boxes(info: dict, dim: int) -> list:
    """(lo (3,), hi (3,), 'tank' | 'obstacle') of the scene's box tank and box obstacles: from the stage's layer data
    (``boxes``, JSON written by rockwave/output/recorders.py), else from the scene file it names (older stages)."""
    def pad(p):
        return np.asarray(list(p) + [0.0] * (3 - len(p)), np.float64)

    try:
        boxes = json.loads(info["boxes"]) if isinstance(info.get("boxes"), str) else None
    except ValueError:
        boxes = None
    if boxes is None and info.get("scene") and Path(str(info["scene"])).is_file():
        try:
            boxes = scene_boxes(load_scene(info["scene"]))
        except (SceneError, OSError, ValueError):
            boxes = None
    return [(pad(lo), pad(hi), what) for lo, hi, what in boxes or []]


_AXES = {"x": 0, "y": 1, "z": 2}
PRESSURE_PERCENTILES = (2.0, 98.0)  # the colour scale of --color pressure


def color_limits(c: np.ndarray, color: str) -> dict:
    """{vmin, vmax} of the colour scale: for pressure the PRESSURE_PERCENTILES (a few hot particles, e.g. at a wall
    impact, must not darken all the others); {} (the data's range) otherwise."""
    if color != "pressure" or len(c) == 0:
        return {}
    lo, hi = np.percentile(c, PRESSURE_PERCENTILES)
    return {"vmin": float(lo), "vmax": float(hi)} if hi > lo else {}


def default_name(frame: int, dim: int, color: str, axis: str = "y", slice_at: float | None = None) -> str:
    """preview_<frame>_<colour>[_<axis>[_at<pos>]].png: different views of one frame get different files."""
    view = "" if dim == 2 else f"_{axis}" + ("" if slice_at is None else f"_at{slice_at:g}")
    return f"preview_{frame:05d}_{color}{view}.png"


def _slice_and_order(x: np.ndarray, c: np.ndarray, blocks: list, depth_axis: int | None, slice_at: float | None,
                     h: float) -> tuple[np.ndarray, np.ndarray, list]:
    """The particles (and blocks) a 3D view shows: those within ``h`` of the slice when one is asked for, drawn
    looking from the low side along the depth axis (far, high first; near last). 2D (no depth axis): as given."""
    if depth_axis is None:
        return x, c, blocks
    if slice_at is not None:
        keep = np.abs(x[:, depth_axis] - slice_at) <= h
        x, c = x[keep], c[keep]
        blocks = [bv for bv in blocks if bv[:, depth_axis].min() <= slice_at <= bv[:, depth_axis].max()]
    order = np.argsort(-x[:, depth_axis])
    return x[order], c[order], blocks


def render_preview(run_dir: str | os.PathLike, frame: int | None = None, color: str = "speed", axis: str = "y",
                   slice_at: float | None = None, out: str | os.PathLike | None = None, dpi: int = 120) -> Path:
    """Draw one frame to a PNG (default ``RUN_DIR/preview_NNNNN.png``); returns its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon, Rectangle

    if color not in ("speed", "pressure"):
        raise PreviewError(f"--color {color!r}: expected speed or pressure")
    if axis not in _AXES:
        raise PreviewError(f"--axis {axis!r}: expected x, y or z")
    d = load_frame(run_dir, frame)
    dim, h = d["dim"], d["spacing"]
    x, v = d["x"], d["v"]
    if color == "pressure":
        if d["pressure"] is None:
            raise PreviewError("the stage has no particle pressure (primvars:pressure); use --color speed")
        c, clabel = d["pressure"], "pressure (Pa)"
    else:
        c, clabel = np.linalg.norm(v, axis=1), "speed (m/s)"
    if dim == 2:
        a, b, depth_axis = 0, 1, None
        view = "x-y plane"
    else:
        depth_axis = _AXES[axis]
        a, b = [k for k in range(3) if k != depth_axis]
        view = f"view along {axis}" if slice_at is None else f"slice {axis} = {slice_at:g} m (+- {h:g} m)"
    x, c, blocks = _slice_and_order(x, c, d["blocks"], depth_axis, slice_at, h)
    pts2 = x[:, [a, b]]
    boxes = [(lo_b, hi_b, what) for lo_b, hi_b, what in d.get("boxes", []) if depth_axis is None or slice_at is None
             or lo_b[depth_axis] - h <= slice_at <= hi_b[depth_axis] + h]  # (a slice shows the obstacles it cuts)
    allp = [pts2] + [bv[:, [a, b]] for bv in blocks] + [np.array([[lo_b[a], lo_b[b]], [hi_b[a], hi_b[b]]]) for lo_b, hi_b, _ in boxes]
    if d["contour"] is not None and len(d["contour"]):
        allp.append(d["contour"].reshape(-1, 3)[:, [a, b]])
    allp = np.concatenate([p for p in allp if len(p)]) if any(len(p) for p in allp) else np.zeros((1, 2))
    lo, hi = allp.min(axis=0) - 2 * h, allp.max(axis=0) + 2 * h
    span = np.maximum(hi - lo, 1e-6)
    width_in = 8.0
    height_in = float(np.clip(width_in * span[1] / span[0], 2.5, 12.0))
    fig, ax = plt.subplots(figsize=(width_in + 1.5, height_in + 0.8), dpi=dpi)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    fig.canvas.draw()
    bbox = ax.get_window_extent()
    pts_per_m = (bbox.width * 72.0 / fig.dpi) / span[0]
    size = max((h * pts_per_m) ** 2, 0.5)
    for lo_b, hi_b, what in boxes:  # the tank's walls and the obstacles (the scene's boxes)
        ax.add_patch(Rectangle((lo_b[a], lo_b[b]), hi_b[a] - lo_b[a], hi_b[b] - lo_b[b], fill=what == "obstacle",
                               facecolor=(0.6, 0.6, 0.6, 0.5), edgecolor="0.25", linewidth=1.5 if what == "tank" else 1.0,
                               zorder=0 if what == "tank" else 3))
    limits = color_limits(c, color)
    sc = ax.scatter(pts2[:, 0], pts2[:, 1], c=c, s=size, cmap="viridis", linewidths=0, marker="o", **limits)
    if len(c):
        fig.colorbar(sc, ax=ax, label=clabel + (f" ({PRESSURE_PERCENTILES[0]:g}-{PRESSURE_PERCENTILES[1]:g} percentiles)"
                                                if limits else ""), shrink=0.8, extend="both" if limits else "neither")
    for bv in blocks:
        hull = _hull(bv[:, [a, b]])
        if len(hull) >= 3:
            ax.add_patch(Polygon(hull, closed=True, facecolor=(0.55, 0.5, 0.45, 0.35), edgecolor="k", linewidth=1.2))
    if d["contour"] is not None and len(d["contour"]):
        from matplotlib.collections import LineCollection

        ax.add_collection(LineCollection(d["contour"][:, :, [a, b]], colors="tab:blue", linewidths=1.0))
    names = "xyz"
    ax.set_xlabel(f"{names[a]} (m)")
    ax.set_ylabel(f"{names[b]} (m)")
    ax.set_title(f"frame {d['frame']}, t = {d['time_s']:.4g} s, {len(pts2)} particles, {len(blocks)} blocks ({view})", fontsize=9)
    out = Path(out) if out else Path(run_dir) / default_name(d["frame"], dim, color, axis, slice_at)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.tmp.png")
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    os.replace(tmp, out)
    return out


def strip_frames(first: int, last: int, n: int) -> list[int]:
    """n frame numbers spread evenly from first to last (both in; fewer when the run has fewer frames)."""
    if n < 1:
        raise PreviewError(f"--strip {n}: expected at least 1 frame")
    return sorted({int(round(f)) for f in np.linspace(first, last, n)})


def render_strip(run_dir: str | os.PathLike, n: int = 6, color: str = "speed", axis: str = "y",
                 slice_at: float | None = None, out: str | os.PathLike | None = None, dpi: int = 80) -> Path:
    """n frames of a run, evenly spread from the first to the last, stacked in one PNG (a frame strip: default
    ``RUN_DIR/strip_<n>_<colour>_<axis>.png``), on one colour scale (speed: 0 to the 99.5th percentile over the frames;
    pressure: the 2nd-98th percentiles over them) and one view (the first frame's water, the blocks and the scene's
    boxes, 5% more on each side); blocks outlined
    as their projected hulls, the tank and box obstacles drawn. Returns its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon, Rectangle

    if color not in ("speed", "pressure"):
        raise PreviewError(f"--color {color!r}: expected speed or pressure")
    if axis not in _AXES:
        raise PreviewError(f"--axis {axis!r}: expected x, y or z")
    first, last = load_frame(run_dir, None)["frames"]
    frames = [load_frame(run_dir, f) for f in strip_frames(first, last, n)]
    dim, h = frames[0]["dim"], frames[0]["spacing"]
    depth_axis = None if dim == 2 else _AXES[axis]
    a, b = (0, 1) if dim == 2 else [k for k in range(3) if k != depth_axis]
    views = []
    for d in frames:
        x = d["x"]
        if color == "pressure":
            if d["pressure"] is None:
                raise PreviewError("the stage has no particle pressure (primvars:pressure); use --color speed")
            c = d["pressure"]
        else:
            c = np.linalg.norm(d["v"], axis=1)
        x, c, blocks = _slice_and_order(x, c, d["blocks"], depth_axis, slice_at, h)
        views.append((d, x[:, [a, b]], c, blocks))
    allc = np.concatenate([c for _, _, c, _ in views]) if views else np.zeros(0)
    if color == "pressure":
        limits = color_limits(allc, color)
    else:
        top = float(np.percentile(allc, 99.5)) if len(allc) else 0.0  # (spray thrown out of the tank aside)
        limits = {"vmin": 0.0, "vmax": top if top > 0 else 1.0}
    boxes = frames[0].get("boxes", [])
    # one view for all frames: the first frame's water, every frame's blocks and the scene's boxes, 5% more on each
    # side (water thrown out of the tank later, which would shrink the scene to a corner, falls outside it)
    pts = [views[0][1]] + [bv[:, [a, b]] for _, _, _, bl in views for bv in bl]
    pts += [np.array([[lo_b[a], lo_b[b]], [hi_b[a], hi_b[b]]]) for lo_b, hi_b, _ in boxes]
    pts = np.concatenate([p for p in pts if len(p)]) if any(len(p) for p in pts) else np.zeros((1, 2))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.05 * (hi - lo) + 2 * h
    lo, hi = lo - pad, hi + pad
    span = np.maximum(hi - lo, 1e-6)
    width_in = 8.0
    panel_in = float(np.clip(width_in * span[1] / span[0], 1.2, 6.0))
    fig, axes = plt.subplots(len(views), 1, figsize=(width_in + 1.5, panel_in * len(views) + 0.6), dpi=dpi,
                             squeeze=False, sharex=True, layout="constrained")
    names = "xyz"
    sc = None
    for ax, (d, p2, c, blocks) in zip(axes[:, 0], views):
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        fig.canvas.draw()
        pts_per_m = (ax.get_window_extent().width * 72.0 / fig.dpi) / span[0]
        for lo_b, hi_b, what in boxes:
            ax.add_patch(Rectangle((lo_b[a], lo_b[b]), hi_b[a] - lo_b[a], hi_b[b] - lo_b[b], fill=what == "obstacle",
                                   facecolor=(0.6, 0.6, 0.6, 0.5), edgecolor="0.25", linewidth=1.0))
        sc = ax.scatter(p2[:, 0], p2[:, 1], c=c, s=max((h * pts_per_m) ** 2, 0.3), cmap="viridis", linewidths=0,
                        marker="o", **limits)
        # a block wholly in front of or behind the water along the view, to two spacings (a side wall of the tank's
        # fixed blocks), is outlined only: filled, its projection would veil the whole view
        if depth_axis is not None and len(d["x"]):
            wlo, whi = np.percentile(d["x"][:, depth_axis], [0.5, 99.5])  # (a few particles out of the tank aside)
        for bv in blocks:
            hull = _hull(bv[:, [a, b]])
            if len(hull) >= 3:
                aside = depth_axis is not None and len(d["x"]) and (bv[:, depth_axis].min() >= whi - 2 * h
                                                                          or bv[:, depth_axis].max() <= wlo + 2 * h)
                ax.add_patch(Polygon(hull, closed=True, fill=not aside, facecolor=(0.55, 0.5, 0.45, 0.35),
                                     edgecolor="0.5" if aside else "k", linewidth=0.6 if aside else 1.0))
        ax.set_ylabel(f"{names[b]} (m)")
        ax.set_title(f"t = {d['time_s']:.3g} s (frame {d['frame']})", fontsize=8, loc="left")
    axes[-1, 0].set_xlabel(f"{names[a]} (m)")
    view = "x-y plane" if dim == 2 else (f"view along {axis}" if slice_at is None else f"slice {axis} = {slice_at:g} m")
    fig.suptitle(f"{Path(frames[0]['stage']).parent.name}: {len(views)} frames, {view}", fontsize=9)
    if sc is not None:
        fig.colorbar(sc, ax=axes[:, 0].tolist(), label="speed (m/s)" if color == "speed" else "pressure (Pa, 2nd-98th percentiles)",
                     shrink=0.6)
    if out is None:
        out = Path(run_dir) / (f"strip_{len(views)}_{color}" + ("" if dim == 2 else f"_{axis}") + ".png")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.tmp.png")
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    os.replace(tmp, out)
    return out
