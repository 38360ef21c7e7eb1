"""``python -m rockwave plot RUN_DIR``: the gauge time series of a run as a PNG.

What it reads: ``RUN_DIR/gauges.csv`` (time_s, then one column per gauge) and ``RUN_DIR/blocks.csv``
(block centroids per frame: drawn as displacement from the first frame); the scene named in
``RUN_DIR/run.json`` (or ``--scene``) for the CSV names, each gauge's kind (one panel per kind:
water height, pressure) and ``[[output.reference]]``: reference series overlaid on the gauges of
the same name (e.g. the SPHERIC Test 2 measurements in benchmarks/data/spheric_test2/).
Without a readable scene every gauge column goes in one panel.
"""

from __future__ import annotations

import csv
import json
import os
import re
from pathlib import Path

import numpy as np

from rockwave.app.preview import PreviewError
from rockwave.scene.format import SceneError, load_scene

_UNITS = {"height": "water height (m)", "pressure": "pressure (Pa)"}


def read_reference(path: str | os.PathLike) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A reference table: whitespace, tab or comma separated; '#' lines are comments, the last one
    before the data (or a first non-numeric line) names the columns ('H1 (m)' -> 'H1').
    Returns (times, {column name: values})."""
    header = None
    rows = []
    for line in Path(path).read_text().splitlines():
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            if not rows:
                header = s.lstrip("#").strip()
            continue
        parts = [p for p in re.split(r"[,\t]" if ("," in s or "\t" in s) else r"\s+", s) if p.strip() != ""]
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            if not rows:
                header = s
            continue
    if not rows:
        raise ValueError(f"{path}: no numeric rows")
    n = min(len(r) for r in rows)
    data = np.array([r[:n] for r in rows], np.float64)
    names = []
    if header:
        if "," in header or "\t" in header:
            cols = [c.strip() for c in re.split(r"[,\t]", header) if c.strip()]
        else:  # 'time (s) H1 (m)': drop the bracketed units
            cols = [c for c in header.split() if not c.startswith(("(", "["))]
        names = [re.split(r"[\s(\[]", c, maxsplit=1)[0] for c in cols]
    if len(names) != n:
        names = ["time"] + [f"col{i}" for i in range(1, n)]
    return data[:, 0], {names[i]: data[:, i] for i in range(1, n)}


def _read_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    with open(path, newline="") as f:
        r = list(csv.reader(f))
    return (r[0], r[1:]) if r else ([], [])


def _scene_for(run: Path, scene_path=None):
    if scene_path is None:
        try:
            scene_path = json.loads((run / "run.json").read_text()).get("scene")
        except (OSError, ValueError):
            scene_path = None
    if not scene_path or scene_path == "<scene>":
        return None
    try:
        return load_scene(scene_path)
    except SceneError:
        return None


def gauge_series(run_dir: str | os.PathLike, scene=None) -> tuple[dict[str, list], float, float]:
    """The series that :func:`plot_gauges` draws: {panel title: [(label, t, y, line style)]}
    ('-' run, '--' reference) and the run's time range."""
    run = Path(run_dir)
    if not run.is_dir():
        raise PreviewError(f"{run}: not a folder")
    if scene is None or isinstance(scene, (str, os.PathLike)):
        scene = _scene_for(run, scene)
    gcsv = run / (scene.output.gauges_csv if scene is not None and scene.output.gauges_csv else "gauges.csv")
    bname = scene.output.get("blocks_csv") if scene is not None else None
    bcsv = run / (bname or "blocks.csv")
    kinds = {g.name: g.kind for g in scene.output.gauges} if scene is not None else {}
    panels: dict[str, list] = {}  # panel title -> [(label, t, y, style)]
    t_lo, t_hi = np.inf, -np.inf
    if gcsv.is_file():
        head, rows = _read_csv(gcsv)
        if rows:
            data = np.array([[float(c) if c not in ("", "nan") else np.nan for c in r] for r in rows], np.float64)
            t = data[:, 0]
            t_lo, t_hi = min(t_lo, t.min()), max(t_hi, t.max())
            for j, name in enumerate(head[1:], start=1):
                panel = _UNITS.get(kinds.get(name), "gauge reading")
                panels.setdefault(panel, []).append((name, t, data[:, j], "-"))
    if bcsv.is_file():
        head, rows = _read_csv(bcsv)
        if rows and {"time_s", "name", "x_m", "y_m", "z_m"} <= set(head):
            it, iname = head.index("time_s"), head.index("name")
            ix = [head.index(k) for k in ("x_m", "y_m", "z_m")]
            series: dict[str, list] = {}
            for r in rows:
                series.setdefault(r[iname], []).append([float(r[it])] + [float(r[k]) for k in ix])
            shown = list(series)[:12]
            for name in shown:
                a = np.array(series[name])
                disp = np.linalg.norm(a[:, 1:] - a[0, 1:], axis=1)
                t_lo, t_hi = min(t_lo, a[:, 0].min()), max(t_hi, a[:, 0].max())
                title = "block displacement (m)" + (f" (first {len(shown)} of {len(series)} blocks)" if len(series) > len(shown) else "")
                panels.setdefault(title, []).append((name, a[:, 0], disp, "-"))
    if not panels:
        raise PreviewError(f"{run}: nothing to plot (no {gcsv.name} with gauge rows and no {bcsv.name})")
    if scene is not None:
        for ref in scene.output.get("reference") or []:
            try:
                rt, cols = read_reference(ref.file)
            except (OSError, ValueError) as e:
                raise PreviewError(f"reference {ref.file}: {e}") from None
            rt = rt + float(ref.time_offset_s or 0.0)
            label = ref.label or Path(ref.file).name
            for lines in panels.values():
                for name, *_ in list(lines):
                    if name in cols:
                        keep = (rt >= t_lo - 1e-9) & (rt <= t_hi + 1e-9) if np.isfinite(t_lo) and t_hi > t_lo else slice(None)
                        lines.append((f"{name} {label}", rt[keep], cols[name][keep] * float(ref.scale), "--"))
    return panels, t_lo, t_hi


def plot_gauges(run_dir: str | os.PathLike, out: str | os.PathLike | None = None, scene=None, dpi: int = 120) -> Path:
    """Draw the run's gauges (and block displacements, and references) to a PNG (default
    ``RUN_DIR/gauges.png``); returns its path. ``scene``: a Scene or a scene path (default: from run.json)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = Path(run_dir)
    panels, t_lo, t_hi = gauge_series(run, scene)
    fig, axes = plt.subplots(len(panels), 1, figsize=(9, 3.2 * len(panels)), dpi=dpi, sharex=True, squeeze=False)
    for ax, (title, lines) in zip(axes[:, 0], panels.items()):
        colours = {}
        for name, t, y, style in lines:
            base = name.split(" ", 1)[0]
            if style == "-":
                (ln,) = ax.plot(t, y, style, linewidth=1.4, marker="." if len(t) < 40 else None, label=name)
                colours[base] = ln.get_color()
            else:
                ax.plot(t, y, style, linewidth=0.9, color=colours.get(base, "k"), alpha=0.8, label=name)
        ax.set_ylabel(title.split(" (first")[0])
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, ncol=2, loc="best")
        if "(first" in title:
            ax.set_title(title, fontsize=8)
    axes[-1, 0].set_xlabel("time (s)")
    if np.isfinite(t_lo) and t_hi > t_lo:
        axes[-1, 0].set_xlim(t_lo, t_hi)
    fig.suptitle(f"{run.name}: gauges", fontsize=10)
    fig.tight_layout()
    out = Path(out) if out else run / "gauges.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.tmp.png")
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    os.replace(tmp, out)
    return out
