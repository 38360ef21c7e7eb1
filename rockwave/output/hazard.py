"""The hazard summary of a run (scene section ``[hazard]``): the numbers a landslide-wave study reports,
reduced on the device while the run goes, never from stored frames.

- Wave gauges (``[[hazard.gauges]]``): the water level on the gauge's vertical line is the height gauge of
  rockwave/sim/readers.py (Gauges: the top of the continuous water column from the bed; spray and jets with air
  below them do not count). eta = level - still level (``still_level_m``, default: the reading at the start
  of the run). Kept: the highest crest max(eta) and the deepest trough min(eta) with their times, and the
  first arrival: the first time |eta| exceeds ``arrival_threshold_m`` (default half the particle spacing: the
  SPH free surface is uncertain by about a quarter spacing), interpolated linearly between two samples.
- Run-up (``[[hazard.runup]]``): ``columns`` vertical lines evenly spaced from ``start_m`` to ``end_m`` (a
  line across the shore; the vertical coordinates are not used), each read as a height gauge. The run-up is
  the highest top of a continuous water column on any of them at any sample: the highest wetted point of the
  shore. The criterion is the height gauge's: a water fraction phi >= 0.5 reaching down to the bed, so a
  single spray particle (phi about 0.25 at its centre) or a film thinner than about one particle layer
  does not count, nor water in the air above a dry bed. The column's position and the per-column maxima
  (a map of run-up along the shore) are reported.
- Slides (``[[hazard.slides]]``): a block's centroid at the start and at the end (runout = the distance
  between them) and its peak speed |v| with its time, sampled after every step (every chunk of steps on a GPU);
  and its motion at every sample time (``motion``: time, centroid, velocity; with ``along``, a direction such as
  down the slope, also the displacement s(t) = (c(t) - c(t_start)).u and the speed v(t).u along its unit vector
  u): the slide's kinematics to set against a friction law or a measured s(t). Kept on the device in a buffer
  that grows by doubling; a batch (rockwave/output/batch.py) does not keep it.
- Crossings (``[[hazard.crossings]]``): the water volume on the positive side of a vertical line (2D) or
  plane (3D) through ``position_m`` with horizontal ``normal``: sum m_j/rho_j over the particles with
  (x_j - p).n > 0. Reported: the net volume moved across since the start V - V0 at the end, and its largest
  value with its time (in 2D a volume per metre of depth, m^3/m).

Gauges, run-up columns and crossings are sampled every ``hazard.sample_interval_s`` of simulated time (at the
first step end at or after each sample time: the recorded time is that step's). The statistics stay on the
device; ``result()`` reads them to the host once. The monitor is a checkpoint provider (group ``hazard``,
rockwave/sim/checkpoint.py: its statistics, still levels, sample count and rhythm), so a run resumed from a
checkpoint reports the whole run's summary, the same as without the interruption (a checkpoint written before
checkpoint format 5 has no such group: the summary then starts at the resumed time, ``t_start_s`` in the result).

Python API::

    sim = rockwave.Simulation("scenes/slide_2d.toml")
    hz = HazardMonitor(sim)
    sim.advance(1.0, watch=hz.after_step)
    print(hz.result())
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import warp as wp

from rockwave.base.maths import pad3
from rockwave.kernels.sim import readers as gauge_k
from rockwave.scene.format import DEFAULT_MAX_COLUMNS, DEFAULT_SAMPLE_INTERVAL_S, SceneError
from rockwave.sim.checkpoint import CheckpointError
from rockwave.sim.readers import Gauges, HostWater, fluid_chunks


def _clean(v):
    """JSON: floats with NaN/inf as None (null), arrays as lists."""
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_clean(x) for x in v]
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


class _Chained:
    """A run loop's watch with the hazard monitor's step hook called first (reads only)."""

    def __init__(self, first, watch):
        self.first, self.watch = first, watch

    def __call__(self):
        self.first()
        if self.watch is not None:
            self.watch()

    def __getattr__(self, name):
        return getattr(self.watch, name)


class SampledRecorder:
    """The step hook shared by HazardMonitor and the batch's BatchHazard (rockwave/output/batch.py): slide speeds
    every step, ``sample()`` when a sample time is reached. Needs sim, device, slide_index, slide_d, slide_stats,
    t_start, interval, next_t and sample()."""

    def wants_water(self) -> bool:
        """Will after_step() read the water now (a sample time reached)? (A distributed run gathers it only then.)"""
        return float(self.sim.time) + 1e-12 >= self.next_t

    def after_step(self) -> None:
        """Block speeds now; the lines and crossings when a sample time has been reached (device launches only)."""
        sim, d = self.sim, self.device
        t = float(sim.time)
        if self.slide_index:
            wp.launch(gauge_k.hazard_block_speed, dim=len(self.slide_index), inputs=[sim.block_state.v, self.slide_d, t],
                      outputs=[self.slide_stats], device=d)
        if self.wants_water():
            self.sample()
            k = math.floor((t - self.t_start) / self.interval + 1e-9) + 1
            self.next_t = self.t_start + k * self.interval

    def wrap(self, watch):
        """Simulation.advance's watch with after_step called first."""
        return _Chained(self.after_step, watch)


class HazardMonitor(SampledRecorder):
    """The scene's [hazard] entries, reduced on the device during a run. ``after_step()`` after every step (or
    ``wrap(watch)`` for Simulation.advance's watch); ``result()`` reads the summary (one host read)."""

    def __init__(self, sim):
        self.sim = sim
        scene = sim.scene
        hz = scene.hazard
        self.device = d = sim.device
        dim, up = scene.dim, scene.dim - 1
        self.dim, self.up = dim, up
        fluid = sim.fluid
        interval = hz.get("sample_interval_s")
        if interval is None:
            interval = min(DEFAULT_SAMPLE_INTERVAL_S, 1.0 / scene.output.frame_rate_hz)
        self.interval = float(interval)
        spacing = float(scene.fluid.spacing_m) if scene.fluid is not None else 0.0
        self.waves = list(hz.get("gauges") or [])
        self.runups = list(hz.get("runup") or [])
        self.crossings = list(hz.get("crossings") or [])
        self.slides = list(hz.get("slides") or [])
        if fluid is None or fluid.n_fluid == 0:
            self.waves, self.runups, self.crossings = [], [], []
        # the vertical lines: wave gauges first, then each run-up line's columns
        lines = [SimpleNamespace(name=g.name, kind="height", position_m=g.position_m) for g in self.waves]
        self.columns = []  # per run-up entry: (offset into the lines, positions (n, dim))
        for r in self.runups:
            n = r.get("columns")
            a, b = np.asarray(r.start_m, float), np.asarray(r.end_m, float)
            length = float(np.linalg.norm(np.delete(b - a, up)))
            if n is None:
                n = int(min(DEFAULT_MAX_COLUMNS, max(2, math.ceil(length / spacing) + 1)))
            pos = a[None, :] + np.linspace(0.0, 1.0, n)[:, None] * (b - a)[None, :]
            pos[:, up] = a[up]
            self.columns.append((len(lines), pos))
            lines += [SimpleNamespace(name=f"{r.name}_{c}", kind="height", position_m=list(p)) for c, p in enumerate(pos)]
        self.n_wave = len(self.waves)
        host = sim.state if isinstance(sim.state, HostWater) else None  # rank 0 of several: the water on the host
        self.gauges = Gauges(scene, fluid, d, sim.blocks, sim.block_state, gauges=lines, host=host) if lines else None
        self.t_start = sim.time
        # still levels: given, or the reading now
        errors = []
        now = None
        if self.gauges is not None:
            now = self.gauges.launch_levels(sim.state).numpy().astype(np.float64)
        still = []
        for i, g in enumerate(self.waves):
            s0 = g.get("still_level_m")
            if s0 is None:
                s0 = float(now[i])
                if not math.isfinite(s0):
                    errors.append((f"hazard.gauges[{i}].still_level_m", f"gauge {g.name!r} at {g.position_m} reads dry at "
                                                                        f"t = {sim.time:g} s: give its still water level"))
            still.append(s0)
        self.runup_still = []
        for i, (r, (off, pos)) in enumerate(zip(self.runups, self.columns)):
            s0 = r.get("still_level_m")
            if s0 is None:
                vals = now[off:off + len(pos)]
                s0 = float(np.nanmax(vals)) if np.isfinite(vals).any() else math.nan
                if not math.isfinite(s0):
                    errors.append((f"hazard.runup[{i}].still_level_m", f"run-up line {r.name!r} is dry along its whole "
                                                                       f"length at t = {sim.time:g} s: give the still water level"))
            self.runup_still.append(s0)
        if errors:
            raise SceneError(scene.path, errors)
        thr = [g.get("arrival_threshold_m") or 0.5 * spacing for g in self.waves]
        self.thresholds = thr
        self.still = still
        nw = max(self.n_wave, 1)
        self.still_d = wp.array(np.asarray(still or [0.0], np.float32), dtype=float, device=d)
        self.thr_d = wp.array(np.asarray(thr or [0.0], np.float32), dtype=float, device=d)
        init = np.zeros((nw, gauge_k.HZ_COLUMNS), np.float32)
        init[:, gauge_k.HZ_MAX] = -np.inf
        init[:, gauge_k.HZ_MIN] = np.inf
        init[:, [gauge_k.HZ_T_MAX, gauge_k.HZ_T_MIN, gauge_k.HZ_ARRIVAL, gauge_k.HZ_PREV_ETA, gauge_k.HZ_PREV_T]] = np.nan
        self.wave_stats = wp.array(init, dtype=float, device=d)
        self.col_stats = []
        for _, pos in self.columns:
            a = np.zeros((len(pos), 2), np.float32)
            a[:, 0] = -np.inf
            a[:, 1] = np.nan
            self.col_stats.append(wp.array(a, dtype=float, device=d))
        nc = max(len(self.crossings), 1)
        self.cross_point = wp.array(np.asarray([pad3(c.position_m) for c in self.crossings] or [[0.0] * 3], np.float32),
                                    dtype=wp.vec3, device=d)
        normals = [np.asarray(pad3(c.normal), float) for c in self.crossings]
        self.cross_normal = wp.array(np.asarray([n / np.linalg.norm(n) for n in normals] or [[1.0, 0, 0]], np.float32),
                                     dtype=wp.vec3, device=d)
        self.cross_vol = wp.zeros(nc, dtype=float, device=d)
        c0 = np.zeros((nc, 4), np.float32)
        c0[:, 0] = np.nan
        c0[:, 2] = -np.inf
        c0[:, 3] = np.nan
        self.cross_stats = wp.array(c0, dtype=float, device=d)
        # slides: block indices by name
        self.slide_index = []
        if self.slides:
            names = sim.blocks.names if sim.blocks is not None else []
            for i, sl in enumerate(self.slides):
                if sl.block not in names:
                    errors.append((f"hazard.slides[{i}].block", f"{sl.block!r} is not the name of a block; the blocks: "
                                                                f"{', '.join(names)}"))
                else:
                    self.slide_index.append(names.index(sl.block))
            if errors:
                raise SceneError(scene.path, errors)
            self.slide_d = wp.array(np.asarray(self.slide_index, np.int32), dtype=int, device=d)
            s0 = np.zeros((len(self.slides), 2), np.float32)
            s0[:, 1] = np.nan
            self.slide_stats = wp.array(s0, dtype=float, device=d)
            self.slide_start = sim.block_state.positions_numpy()[self.slide_index]
            # the motion record: one row per sample and slide (t, centroid, velocity), grown by doubling
            dur = float(getattr(scene.simulation, "duration_s", 0.0) or 0.0)
            cap = max(16, int(math.ceil(max(dur - self.t_start, 0.0) / self.interval)) + 4)
            self.slide_motion = wp.zeros((cap * len(self.slides), 7), dtype=float, device=d)
            self.slide_along = []
            for sl in self.slides:
                u = sl.get("along")
                u = None if u is None else np.asarray(pad3(u), float)
                self.slide_along.append(None if u is None else u / np.linalg.norm(u))
        self.samples = 0
        self.next_t = self.t_start
        self.last_sample_t = None
        self.after_step()  # the first sample: t = t_start

    # ------------------------------------------------------------------------------------------------
    def sample(self) -> None:
        """One sample of the gauges, run-up columns and crossings at the current time (device launches only)."""
        sim, d = self.sim, self.device
        t = float(sim.time)
        if self.gauges is not None:
            level = self.gauges.launch_levels(sim.state)
            if self.n_wave:
                wp.launch(gauge_k.hazard_wave_update, dim=self.n_wave, inputs=[level, self.still_d, self.thr_d, t],
                          outputs=[self.wave_stats], device=d)
            for (off, pos), st in zip(self.columns, self.col_stats):
                wp.launch(gauge_k.hazard_column_update, dim=len(pos), inputs=[level, off, t], outputs=[st], device=d)
        if self.slide_index:
            n = len(self.slide_index)
            if (self.samples + 1) * n > self.slide_motion.shape[0]:
                grown = wp.zeros((2 * self.slide_motion.shape[0], 7), dtype=float, device=d)
                wp.copy(grown, self.slide_motion)
                self.slide_motion = grown
            bs = sim.block_state
            wp.launch(gauge_k.hazard_slide_record, dim=n, inputs=[bs.x, bs.x_lo, bs.v, self.slide_d, self.samples, t],
                      outputs=[self.slide_motion], device=d)
        if self.crossings:
            m = sim.fluid
            self.cross_vol.zero_()
            for k, a in fluid_chunks(sim.state, m, ("x", "rho")):
                wp.launch(gauge_k.hazard_side_volume, dim=(k, len(self.crossings)),
                          inputs=[a["x"], a["rho"], a["mass"], self.cross_point, self.cross_normal],
                          outputs=[self.cross_vol], device=d)
            wp.launch(gauge_k.hazard_crossing_update, dim=len(self.crossings), inputs=[self.cross_vol, t],
                      outputs=[self.cross_stats], device=d)
        self.samples += 1
        self.last_sample_t = t

    # ------------------------------------------------------------------------------------------------
    # checkpoint provider (rockwave/sim/checkpoint.py register): the statistics and the sampling rhythm
    def _arrays(self) -> dict:
        out = {"wave_stats": self.wave_stats, "cross_stats": self.cross_stats}
        out.update({f"col_stats_{i}": a for i, a in enumerate(self.col_stats)})
        if self.slide_index:
            out["slide_stats"] = self.slide_stats
            out["slide_motion"] = self.slide_motion
        return out

    def capture(self):
        meta = {"t_start": self.t_start, "next_t": self.next_t, "last_sample_t": self.last_sample_t,
                "samples": self.samples, "still": [float(x) for x in self.still],
                "runup_still": [float(x) for x in self.runup_still]}
        host = {"slide_start": np.array(self.slide_start)} if self.slide_index else {}
        return {k: wp.clone(a) for k, a in self._arrays().items()}, host, meta

    def pack(self, captured):
        arrays, host, meta = captured
        out = {k: a.numpy() for k, a in arrays.items()}
        out.update(host)
        return out, _clean(dict(meta))

    def restore(self, arrays: dict, meta: dict) -> None:
        mine = self._arrays()
        if "slide_motion" in mine and "slide_motion" not in arrays:  # a checkpoint from before the motion record
            n = len(self.slide_index)
            rows = np.full(((int(meta["samples"]) + 16) * n, 7), np.nan, np.float32)
            self.slide_motion = wp.array(rows, dtype=float, device=self.device)
            mine.pop("slide_motion")
        if set(arrays) - {"slide_start"} != set(mine):
            raise CheckpointError(f"the checkpoint's hazard statistics ({sorted(arrays)}) do not match the scene's [hazard] "
                                  f"({sorted(mine)})")
        for k, a in mine.items():
            if k == "slide_motion" and tuple(a.shape) != tuple(np.shape(arrays[k])):  # a buffer grown to another size
                self.slide_motion = wp.array(np.asarray(arrays[k], np.float32), dtype=float, device=self.device)
                continue
            a.assign(arrays[k])
        self.t_start, self.next_t, self.samples = float(meta["t_start"]), float(meta["next_t"]), int(meta["samples"])
        self.last_sample_t = None if meta["last_sample_t"] is None else float(meta["last_sample_t"])
        self.still = [math.nan if x is None else float(x) for x in meta["still"]]
        self.runup_still = [math.nan if x is None else float(x) for x in meta["runup_still"]]
        self.still_d.assign(np.asarray(self.still or [0.0], np.float32))
        if self.slide_index:
            self.slide_start = np.array(arrays["slide_start"])

    # ------------------------------------------------------------------------------------------------
    def _motion(self, i: int) -> dict:
        """Slide i's motion record: t, centroid, velocity at every sample; with ``along`` the displacement and the
        speed along its unit vector u (s = (c - c_0).u, c_0 the centroid at the start, v_s = v.u)."""
        n = len(self.slide_index)
        rows = self.slide_motion.numpy()[: self.samples * n].astype(np.float64).reshape(self.samples, n, 7)[:, i]
        dim = self.dim
        m = {"t_s": rows[:, 0], "centroid_m": rows[:, 1:1 + dim], "velocity_m_s": rows[:, 4:4 + dim]}
        u = self.slide_along[i]
        if u is not None:
            c, v = rows[:, 1:4], rows[:, 4:7]
            m["along"] = u[:dim]
            c0 = np.asarray(self.slide_start[i], float)[:3]  # the centroid at t_start (float64)
            m["along_m"] = (c - c0) @ u
            m["speed_along_m_s"] = v @ u
        return m

    def result(self) -> dict:
        """The summary (host read of the statistics; a last sample first when the time moved since the last)."""
        sim = self.sim
        if self.last_sample_t is None or sim.time > self.last_sample_t + 1e-12:
            self.sample()
        out = {"t_start_s": self.t_start, "t_end_s": float(sim.time), "sample_interval_s": self.interval,
               "samples": self.samples, "gauges": {}, "runup": {}, "slides": {}, "crossings": {}}
        if self.n_wave:
            w = self.wave_stats.numpy().astype(np.float64)
            for i, g in enumerate(self.waves):
                row = w[i]
                out["gauges"][g.name] = {
                    "position_m": list(g.position_m), "still_level_m": self.still[i],
                    "arrival_threshold_m": self.thresholds[i],
                    "max_crest_m": row[gauge_k.HZ_MAX], "max_crest_time_s": row[gauge_k.HZ_T_MAX],
                    "deepest_trough_m": row[gauge_k.HZ_MIN], "deepest_trough_time_s": row[gauge_k.HZ_T_MIN],
                    "arrival_time_s": row[gauge_k.HZ_ARRIVAL],
                }
        for i, (r, (off, pos), st) in enumerate(zip(self.runups, self.columns, self.col_stats)):
            a = st.numpy().astype(np.float64)
            tops = np.where(np.isfinite(a[:, 0]), a[:, 0], np.nan)
            horiz = [k for k in range(self.dim) if k != self.up]
            if np.isfinite(tops).any():
                c = int(np.nanargmax(tops))
                best, when, at = tops[c], a[c, 1], [pos[c][k] for k in horiz]
            else:
                best, when, at = math.nan, math.nan, None
            out["runup"][r.name] = {
                "max_runup_m": best, "max_runup_above_still_m": best - self.runup_still[i], "still_level_m": self.runup_still[i],
                "max_runup_time_s": when, "max_runup_at_m": at,
                "columns_m": [[p[k] for k in horiz] for p in pos], "column_max_m": tops,
            }
        if self.slide_index:
            s = self.slide_stats.numpy().astype(np.float64)
            end = sim.block_state.positions_numpy()[self.slide_index]
            for i, sl in enumerate(self.slides):
                p0, p1 = self.slide_start[i][: self.dim], end[i][: self.dim]
                out["slides"][sl.block] = {"initial_position_m": p0, "final_position_m": p1,
                                           "runout_m": float(np.linalg.norm(p1 - p0)),
                                           "peak_speed_m_s": s[i, 0], "peak_speed_time_s": s[i, 1],
                                           "motion": self._motion(i)}
        if self.crossings:
            c = self.cross_stats.numpy().astype(np.float64)
            for i, cr in enumerate(self.crossings):
                out["crossings"][cr.name] = {"initial_volume_m3": c[i, 0], "net_volume_m3": c[i, 1],
                                             "max_volume_m3": c[i, 2], "max_volume_time_s": c[i, 3]}
        return _clean(out)


def slide_motion_csv(result: dict) -> str:
    """The slides' motion records of a hazard result as CSV text: t_s, then per slide <block>.x_m ... <block>.vz_m_s
    and, where it has ``along``, <block>.along_m and <block>.speed_along_m_s (one row per sample). '' if no slide."""
    slides = {k: s["motion"] for k, s in result.get("slides", {}).items() if s.get("motion") and s["motion"]["t_s"]}
    if not slides:
        return ""
    first = next(iter(slides.values()))
    n = len(first["t_s"])
    dim = len(first["centroid_m"][0])
    axes = "xyz"[:dim]
    head, cols = ["t_s"], [first["t_s"]]
    for name, m in slides.items():
        for k, a in enumerate(axes):
            head.append(f"{name}.{a}_m")
            cols.append([r[k] for r in m["centroid_m"]])
        for k, a in enumerate(axes):
            head.append(f"{name}.v{a}_m_s")
            cols.append([r[k] for r in m["velocity_m_s"]])
        if "along_m" in m:
            head += [f"{name}.along_m", f"{name}.speed_along_m_s"]
            cols += [m["along_m"], m["speed_along_m_s"]]
    fmt = lambda v: "" if v is None else f"{v:.9g}"  # noqa: E731
    lines = [",".join(head)] + [",".join(fmt(c[r]) for c in cols) for r in range(n)]
    return "\n".join(lines) + "\n"


def flat_metrics(result: dict) -> dict:
    """One row of a study table from a hazard result: '<gauge>.max_crest_m', '<runup>.max_runup_m', ..."""
    row = {}
    for name, g in result.get("gauges", {}).items():
        for k in ("max_crest_m", "max_crest_time_s", "deepest_trough_m", "deepest_trough_time_s", "arrival_time_s"):
            row[f"{name}.{k}"] = g[k]
    for name, r in result.get("runup", {}).items():
        for k in ("max_runup_m", "max_runup_above_still_m", "max_runup_time_s"):
            row[f"{name}.{k}"] = r[k]
        at = r.get("max_runup_at_m")
        row[f"{name}.max_runup_at_m"] = at[0] if at else None
    for name, s in result.get("slides", {}).items():
        for k in ("runout_m", "peak_speed_m_s", "peak_speed_time_s"):
            row[f"{name}.{k}"] = s[k]
        for a, v in zip("xyz", s["final_position_m"]):
            row[f"{name}.final_{a}_m"] = v
    for name, c in result.get("crossings", {}).items():
        for k in ("net_volume_m3", "max_volume_m3", "max_volume_time_s"):
            row[f"{name}.{k}"] = c[k]
    return row
