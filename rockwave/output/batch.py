"""The hazard summaries of a batch of scenarios (rockwave/sim/batch.py BatchSimulation), reduced on the device.

Each scenario's [hazard] entries are those of rockwave/output/hazard.py HazardMonitor, with the same sampling
(every ``hazard.sample_interval_s`` at the first step end at or after each sample time; block speeds after every
step or chunk) and the same statistics kernels (kernels/sim/readers.py). What the batch changes is only where the
lines are evaluated: every scenario's height-gauge lines and run-up columns are one launch over all fluid
particles x the most lines of a scenario, each particle adding only to its own scenario's lines (kernels/output/
batch.py), and each line keeps the samples it has alone: its scenario's own domain sets the line's lower end, its
spacing and its length (rockwave/sim/readers.py Gauges, built for the scenario in its own frame, gives them and the
walls' fraction phi_s along the line). Positions are moved back to the scenario's frame in the result, so a
scenario's hazard.json reads as its solo run's.

Python API::

    b = BatchSimulation(scenes)
    hz = BatchHazard(b)
    b.advance(1.0, watch=hz.after_step)
    summaries = hz.results()        # one dict per scenario, HazardMonitor.result()'s form
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import warp as wp

from rockwave.base.maths import pad3, quat_to_matrix
from rockwave.kernels.output import batch as batch_k
from rockwave.kernels.sim import readers as gauge_k
from rockwave.output.hazard import SampledRecorder, _clean
from rockwave.scene.format import DEFAULT_MAX_COLUMNS, SceneError
from rockwave.sim.batch import hazard_interval
from rockwave.sim.readers import Gauges, MovingSolids, moving_blocks


class BatchHazard(SampledRecorder):
    """Every scenario's [hazard] of a BatchSimulation; ``after_step()`` after every step or chunk (or
    ``wrap(watch)``), ``results()`` the summaries (one host read)."""

    def __init__(self, batch):
        self.sim = sim = batch
        self.device = d = sim.device
        scene = sim.scene
        self.dim, self.up = scene.dim, scene.dim - 1
        up = self.up
        fluid = sim.fluid
        self.interval = hazard_interval(sim.scenes[0])  # (shared by the template; sim.scene, the template, has no [hazard])
        spacing = float(scene.fluid.spacing_m)
        nf = fluid.n_fluid
        masses = fluid.particle_mass.numpy()
        bmass = self._boundary_masses(masses)
        self.per = []  # per scenario: its entries and their rows
        rows_pos, rows_z0, rows_dz, rows_n, rows_reach, phi_s_rows = [], [], [], [], [], []
        line_movers = []  # each line's moving blocks (its scenario's)
        line_first, line_count = [], []
        cross_first, cross_count, cross_pt, cross_n = [], [], [], []
        wave_rows, still, thr, col_rows = [], [], [], []
        slide_index, slide_start = [], []
        wave_scen, col_scen, cross_scen, slide_scen = [], [], [], []  # each row's scenario
        owner = np.full(nf, -1, np.int32)
        for k, (s, t, seeds) in enumerate(zip(sim.scenes, sim.tiles, sim.seeds)):
            a, b = t.fluid
            owner[a:b] = k
            hz = s.hazard or {}
            waves = list(hz.get("gauges") or [])
            runups = list(hz.get("runup") or [])
            crossings = list(hz.get("crossings") or [])
            slides = list(hz.get("slides") or [])
            if b == a:
                waves, runups, crossings = [], [], []
            lines = [SimpleNamespace(name=g.name, kind="height", position_m=g.position_m) for g in waves]
            columns = []
            for r in runups:
                n = r.get("columns")
                p0, p1 = np.asarray(r.start_m, float), np.asarray(r.end_m, float)
                length = float(np.linalg.norm(np.delete(p1 - p0, up)))
                if n is None:
                    n = int(min(DEFAULT_MAX_COLUMNS, max(2, math.ceil(length / spacing) + 1)))
                pos = p0[None, :] + np.linspace(0.0, 1.0, n)[:, None] * (p1 - p0)[None, :]
                pos[:, up] = p0[up]
                columns.append((len(lines), pos))
                lines += [SimpleNamespace(name=f"{r.name}_{c}", kind="height", position_m=list(p)) for c, p in enumerate(pos)]
            off = t.offset
            first = len(rows_pos)
            line_first.append(first)
            line_count.append(len(lines))
            gauges = None
            if lines:
                view = SimpleNamespace(domain_lo=t.domain_lo, domain_hi=t.domain_hi, spacing=fluid.spacing,
                                       support_radius=fluid.support_radius, n_fluid=b - a, n_boundary=len(seeds.boundary),
                                       n_moving_walls=0, params=fluid.params,
                                       initial_positions=np.concatenate([seeds.fluid, seeds.boundary]),
                                       particle_mass=wp.array(np.concatenate([masses[a:b], bmass[k]]).astype(np.float32),
                                                              dtype=float, device=d))
                gauges = Gauges(s, view, d, gauges=lines)
                phi_s = gauges.phi_s.numpy()
                self._fixed_blocks(k, gauges, phi_s)
                movers = [] if sim.blocks is None else moving_blocks(sim.blocks.specs[t.blocks[0]:t.blocks[1]])
                if movers:  # the still levels below read the scenario's own moving blocks in its own frame
                    self._own_movers(k, gauges, movers)
                movers = [t.blocks[0] + j for j in movers]
                for i, ln in enumerate(lines):
                    line_movers.append(movers)
                    rows_pos.append(np.asarray(pad3(ln.position_m), float) + off)
                    rows_z0.append(gauges.z0 + off[up])
                    rows_dz.append(gauges.dz)
                    rows_n.append(gauges.n_samples)
                    rows_reach.append(gauges.reach)
                    phi_s_rows.append(phi_s[i])
            # still levels: given, or the reading now (in the batch frame below)
            now = None
            if gauges is not None and (any(g.get("still_level_m") is None for g in waves)
                                       or any(r.get("still_level_m") is None for r in runups)):
                now = gauges.launch_levels(_OwnState(sim, k)).numpy().astype(np.float64)
            errors, st_w, st_r = [], [], []
            wave_scen += [k] * len(waves)
            cross_scen += [k] * len(crossings)
            for i, g in enumerate(waves):
                s0 = g.get("still_level_m")
                if s0 is None:
                    s0 = float(now[i])
                    if not math.isfinite(s0):
                        errors.append((f"hazard.gauges[{i}].still_level_m", f"gauge {g.name!r} at {g.position_m} reads dry "
                                                                            f"at t = {sim.time:g} s: give its still water level"))
                st_w.append(s0)
                wave_rows.append(first + i)
                still.append(s0 + off[up])
                thr.append(g.get("arrival_threshold_m") or 0.5 * spacing)
            for i, (r, (o, pos)) in enumerate(zip(runups, columns)):
                s0 = r.get("still_level_m")
                if s0 is None:
                    vals = now[o:o + len(pos)]
                    s0 = float(np.nanmax(vals)) if np.isfinite(vals).any() else math.nan
                    if not math.isfinite(s0):
                        errors.append((f"hazard.runup[{i}].still_level_m", f"run-up line {r.name!r} is dry along its whole "
                                                                           f"length at t = {sim.time:g} s: give the still water level"))
                st_r.append(s0)
            col_start = len(col_rows)
            for o, pos in columns:
                col_rows += list(range(first + o, first + o + len(pos)))
                col_scen += [k] * len(pos)
            cross_first.append(len(cross_pt))
            cross_count.append(len(crossings))
            for c in crossings:
                cross_pt.append(np.asarray(pad3(c.position_m), float) + off)
                nn = np.asarray(pad3(c.normal), float)
                cross_n.append(nn / np.linalg.norm(nn))
            names = sim.scenario_blocks(k)
            sl_first = len(slide_index)
            for i, sl in enumerate(slides):
                if sl.block not in names:
                    errors.append((f"hazard.slides[{i}].block", f"{sl.block!r} is not the name of a block; the blocks: "
                                                                f"{', '.join(names)}"))
                else:
                    slide_index.append(t.blocks[0] + names.index(sl.block))
                    slide_scen.append(k)
            if errors:
                raise SceneError(s.path, errors)
            if slides:
                slide_start += list(sim.block_positions(k)[[names.index(sl.block) for sl in slides]])
            self.per.append(SimpleNamespace(waves=waves, runups=runups, crossings=crossings, slides=slides,
                                            columns=columns, still=st_w, runup_still=st_r, thresholds=thr[-len(waves):] if waves else [],
                                            wave_first=len(wave_rows) - len(waves), col_first=col_start,
                                            cross_first=cross_first[-1], slide_first=sl_first))
        self.n_rows = n_rows = len(rows_pos)
        self.max_lines = max(line_count) if line_count else 0
        self.max_cross = max(cross_count) if cross_count else 0
        ns = max(rows_n) if rows_n else 1
        arr = lambda a, dt=float: wp.array(np.asarray(a), dtype=dt, device=d)  # noqa: E731
        self.owner = wp.array(owner, dtype=int, device=d)
        if n_rows:
            self.line_first, self.line_count = arr(line_first, int), arr(line_count, int)
            self.line_pos = wp.array(np.asarray(rows_pos, np.float32), dtype=wp.vec3, device=d)
            self.line_z0, self.line_dz = arr(np.asarray(rows_z0, np.float32)), arr(np.asarray(rows_dz, np.float32))
            self.line_n, self.line_reach = arr(np.asarray(rows_n, np.int32), int), arr(np.asarray(rows_reach, np.int32), int)
            solid = np.zeros((n_rows, ns), np.float32)
            for i, r in enumerate(phi_s_rows):
                solid[i, :len(r)] = r
            self.phi_s = wp.array(solid, dtype=float, device=d)
            self.phi_f = wp.zeros((n_rows, ns), dtype=float, device=d)
            self.level = wp.zeros(n_rows, dtype=float, device=d)
            movers = sorted({b for lst in line_movers for b in lst})
            self.moving = None  # the moving blocks on the lines (rockwave/sim/readers.py MovingSolids)
            if movers:
                where = {b: i for i, b in enumerate(movers)}
                self.moving = MovingSolids(sim.blocks, movers, [[where[b] for b in lst] for lst in line_movers],
                                           self.line_pos, np.asarray(rows_z0), np.asarray(rows_dz), np.asarray(rows_n), ns,
                                           up, fluid.params, d)
        nw, ncol = max(len(wave_rows), 1), max(len(col_rows), 1)
        self.n_wave, self.n_col = len(wave_rows), len(col_rows)
        self.wave_rows, self.col_rows = arr(wave_rows or [0], int), arr(col_rows or [0], int)
        self.wave_level, self.col_level = wp.zeros(nw, dtype=float, device=d), wp.zeros(ncol, dtype=float, device=d)
        self.still_d = arr(np.asarray(still or [0.0], np.float32))
        self.thr_d = arr(np.asarray(thr or [0.0], np.float32))
        init = np.zeros((nw, gauge_k.HZ_COLUMNS), np.float32)
        init[:, gauge_k.HZ_MAX] = -np.inf
        init[:, gauge_k.HZ_MIN] = np.inf
        init[:, [gauge_k.HZ_T_MAX, gauge_k.HZ_T_MIN, gauge_k.HZ_ARRIVAL, gauge_k.HZ_PREV_ETA, gauge_k.HZ_PREV_T]] = np.nan
        self.wave_stats = wp.array(init, dtype=float, device=d)
        c = np.zeros((ncol, 2), np.float32)
        c[:, 0], c[:, 1] = -np.inf, np.nan
        self.col_stats = wp.array(c, dtype=float, device=d)
        nc = max(len(cross_pt), 1)
        self.n_cross = len(cross_pt)
        self.cross_first, self.cross_count = arr(cross_first or [0], int), arr(cross_count or [0], int)
        self.cross_point = wp.array(np.asarray(cross_pt or [[0.0] * 3], np.float32), dtype=wp.vec3, device=d)
        self.cross_normal = wp.array(np.asarray(cross_n or [[1.0, 0, 0]], np.float32), dtype=wp.vec3, device=d)
        self.cross_vol = wp.zeros(nc, dtype=float, device=d)
        c0 = np.zeros((nc, 4), np.float32)
        c0[:, 0], c0[:, 2], c0[:, 3] = np.nan, -np.inf, np.nan
        self.cross_stats = wp.array(c0, dtype=float, device=d)
        self.slide_index = slide_index
        if slide_index:
            self.slide_d = arr(np.asarray(slide_index, np.int32), int)
            s0 = np.zeros((len(slide_index), 2), np.float32)
            s0[:, 1] = np.nan
            self.slide_stats = wp.array(s0, dtype=float, device=d)
            self.slide_start = np.asarray(slide_start)
        self.t_start = sim.time
        self.samples = 0
        self.next_t = self.t_start
        self.last_sample_t = None
        # per-scenario steps (sim.own): each scenario samples at its own times, as its solo run
        self.own = sim.own is not None
        S = sim.n_scenarios
        self.t_starts = sim.times
        self.next_ts = self.t_starts.copy()
        self.samples_k = np.zeros(S, np.int64)
        self.last_ts = np.full(S, np.nan)
        self.scen_t = wp.zeros(S, dtype=float, device=d)
        self.scen_on = wp.zeros(S, dtype=int, device=d)
        self.wave_scen, self.col_scen = arr(wave_scen or [0], int), arr(col_scen or [0], int)
        self.cross_scen, self.slide_scen = arr(cross_scen or [0], int), arr(slide_scen or [0], int)
        self.after_step()

    def after_step(self) -> None:
        """Per-scenario steps: each scenario that stepped reads its slides' speeds and, at its own sample times, its
        lines and crossings (SampledRecorder.after_step per scenario); a shared step: SampledRecorder's."""
        if not self.own:
            return super().after_step()
        sim = self.sim
        t = sim.times
        stepped = sim.own.stepped
        if self.slide_index:
            self._scenario_flags(t, stepped)
            wp.launch(batch_k.batch_block_speed, dim=len(self.slide_index),
                      inputs=[sim.block_state.v, self.slide_d, self.slide_scen, self.scen_t, self.scen_on],
                      outputs=[self.slide_stats], device=self.device)
        due = stepped & (t + 1e-12 >= self.next_ts)
        if due.any():
            self.sample(due)
            k = np.floor((t[due] - self.t_starts[due]) / self.interval + 1e-9) + 1
            self.next_ts[due] = self.t_starts[due] + k * self.interval

    def _scenario_flags(self, t: np.ndarray, on: np.ndarray) -> None:
        self.scen_t.assign(t.astype(np.float32))  # (float32 on the device, as the solo run's time argument)
        self.scen_on.assign(on.astype(np.int32))

    # ------------------------------------------------------------------------------------------------
    def _boundary_masses(self, masses: np.ndarray) -> list[np.ndarray]:
        """Each scenario's static boundary masses in its seeded order (build_fluid_model stores the union's static
        boundary particles sorted by cell: the same sort undone here)."""
        sim, f = self.sim, self.sim.fluid
        nf = f.n_fluid
        xb = np.concatenate([sd.boundary + t.offset for sd, t in zip(sim.seeds, sim.tiles)])
        nb = len(xb)
        out = np.empty(nb, np.float64)
        if nb > 1:
            c = np.floor((xb - xb.min(axis=0)) / f.params.H).astype(np.int64)
            order = np.lexsort((c[:, 0], c[:, 1], c[:, 2]))
            out[order] = masses[nf:nf + nb]
        elif nb:
            out[:] = masses[nf:nf + nb]
        return [out[t.boundary[0]:t.boundary[1]] for t in sim.tiles]

    def _own_movers(self, k: int, gauges, movers: list[int]) -> None:
        """Scenario k's moving blocks (``movers``: indices among its blocks) on its Gauges' lines, posed in its own
        frame, for the start-up reading."""
        sim, d = self.sim, self.device
        a, b = sim.tiles[k].blocks
        n = len(gauges.names)
        gauges.moving = MovingSolids(SimpleNamespace(specs=sim.blocks.specs[a:b]), movers, [list(range(len(movers)))] * n,
                                     gauges.pos, np.full(n, gauges.z0), np.full(n, gauges.dz), np.full(n, gauges.n_samples),
                                     gauges.n_samples, gauges.up, sim.fluid.params, d)
        gauges.block_state = SimpleNamespace(
            x=wp.array(sim.block_positions(k).astype(np.float32), dtype=wp.vec3, device=d),
            q=wp.array(sim.block_state.orientations_numpy()[a:b].astype(np.float32), dtype=wp.quat, device=d))

    def _fixed_blocks(self, k: int, gauges, phi_s: np.ndarray) -> None:
        """Samples inside a fixed block count as wall (Gauges._add_fixed_blocks: the block nearest to the sample by
        signed distance, here over the scenario's own blocks in its own frame)."""
        sim = self.sim
        if sim.blocks is None:
            return
        a, b = sim.tiles[k].blocks
        specs = sim.blocks.specs[a:b]
        if not any(s.kind == "fixed" and not s.tank for s in specs):
            return
        xs = sim.block_positions(k)
        qs = sim.block_state.orientations_numpy()[a:b]
        z = gauges.z0 + gauges.dz * np.arange(gauges.n_samples)
        pos = gauges.pos.numpy().astype(np.float64)
        pts = np.repeat(pos[:, None, :], len(z), axis=1)  # (lines, samples, 3)
        pts[:, :, gauges.up] = z[None, :]
        pts = pts.reshape(-1, 3)
        fixed = np.array([s.kind == "fixed" and not s.tank for s in specs])
        best = np.full(len(pts), np.inf)
        which = np.zeros(len(pts), np.int64)
        for j, spec in enumerate(specs):
            R = quat_to_matrix(qs[j])
            n = np.asarray(spec.geometry.face_normals, float) @ R.T
            off = np.asarray(spec.geometry.face_offsets, float) + n @ xs[j]
            dist = np.full(len(pts), -np.inf)
            for f in range(len(n)):  # max over the face planes (a 1D pass each: no small-axis reduce)
                np.maximum(dist, pts[:, 0] * n[f, 0] + pts[:, 1] * n[f, 1] + pts[:, 2] * n[f, 2] - off[f], out=dist)
            closer = dist < best
            best[closer], which[closer] = dist[closer], j
        inside = ((best < 0.0) & fixed[which]).reshape(len(pos), len(z))
        phi_s[:, : len(z)][inside] = 1.0

    # ------------------------------------------------------------------------------------------------
    def sample(self, due: np.ndarray | None = None) -> None:
        """One sample of every line and crossing; per-scenario steps: of the scenarios in ``due`` (bool), each at its
        own time (the lines are evaluated for all, the statistics updated for those)."""
        sim, d = self.sim, self.device
        t = float(sim.time)
        own = self.own
        if own:
            if due is None:
                due = np.ones(sim.n_scenarios, bool)
            ts = sim.times
            self._scenario_flags(ts, due)
        st, m = sim.state, sim.fluid
        if self.n_rows and m.n_fluid:
            self.phi_f.zero_()
            wp.launch(batch_k.batch_line_profile, dim=(m.n_fluid, self.max_lines),
                      inputs=[st.x, st.rho, m.particle_mass, st.ids, self.owner, self.line_first, self.line_count,
                              self.line_pos, self.line_z0, self.line_dz, self.up, m.params], outputs=[self.phi_f], device=d)
            moving = self.moving.launch(sim.block_state) if self.moving is not None else self.phi_s
            wp.launch(batch_k.batch_line_level, dim=self.n_rows,
                      inputs=[self.phi_f, self.phi_s, moving, int(self.moving is not None), self.line_n, self.line_z0,
                              self.line_dz, self.line_reach], outputs=[self.level], device=d)
            if self.n_wave:
                wp.launch(batch_k.gather, dim=self.n_wave, inputs=[self.level, self.wave_rows], outputs=[self.wave_level], device=d)
                if own:
                    wp.launch(batch_k.batch_wave_update, dim=self.n_wave,
                              inputs=[self.wave_level, self.still_d, self.thr_d, self.wave_scen, self.scen_t, self.scen_on],
                              outputs=[self.wave_stats], device=d)
                else:
                    wp.launch(gauge_k.hazard_wave_update, dim=self.n_wave, inputs=[self.wave_level, self.still_d, self.thr_d, t],
                              outputs=[self.wave_stats], device=d)
            if self.n_col:
                wp.launch(batch_k.gather, dim=self.n_col, inputs=[self.level, self.col_rows], outputs=[self.col_level], device=d)
                if own:
                    wp.launch(batch_k.batch_column_update, dim=self.n_col,
                              inputs=[self.col_level, self.col_scen, self.scen_t, self.scen_on], outputs=[self.col_stats],
                              device=d)
                else:
                    wp.launch(gauge_k.hazard_column_update, dim=self.n_col, inputs=[self.col_level, 0, t],
                              outputs=[self.col_stats], device=d)
        if self.n_cross and m.n_fluid:
            self.cross_vol.zero_()
            wp.launch(batch_k.batch_side_volume, dim=(m.n_fluid, self.max_cross),
                      inputs=[st.x, st.rho, m.particle_mass, st.ids, self.owner, self.cross_first, self.cross_count,
                              self.cross_point, self.cross_normal], outputs=[self.cross_vol], device=d)
            if own:
                wp.launch(batch_k.batch_crossing_update, dim=self.n_cross,
                          inputs=[self.cross_vol, self.cross_scen, self.scen_t, self.scen_on], outputs=[self.cross_stats],
                          device=d)
            else:
                wp.launch(gauge_k.hazard_crossing_update, dim=self.n_cross, inputs=[self.cross_vol, t],
                          outputs=[self.cross_stats], device=d)
        if own:
            self.samples_k[due] += 1
            self.last_ts[due] = ts[due]
        else:
            self.samples += 1
            self.last_sample_t = t

    # ------------------------------------------------------------------------------------------------
    def results(self) -> list[dict]:
        """Each scenario's summary, in HazardMonitor.result()'s form and its own frame (one host read)."""
        sim = self.sim
        if self.own:
            t = sim.times
            due = ~(t <= self.last_ts + 1e-12)  # (NaN: never sampled)
            if due.any():
                self.sample(due)
        elif self.last_sample_t is None or sim.time > self.last_sample_t + 1e-12:
            self.sample()
        w = self.wave_stats.numpy().astype(np.float64)
        cols = self.col_stats.numpy().astype(np.float64)
        cs = self.cross_stats.numpy().astype(np.float64)
        ss = self.slide_stats.numpy().astype(np.float64) if self.slide_index else None
        up, dim = self.up, self.dim
        horiz = [i for i in range(dim) if i != up]
        out = []
        for k, p in enumerate(self.per):
            off_up = float(sim.tiles[k].offset[up])
            if self.own:
                t0, t1, n = float(self.t_starts[k]), float(sim.times[k]), int(self.samples_k[k])
            else:
                t0, t1, n = self.t_start, float(sim.time), self.samples
            res = {"t_start_s": t0, "t_end_s": t1, "sample_interval_s": self.interval,
                   "samples": n, "gauges": {}, "runup": {}, "slides": {}, "crossings": {}}
            for i, g in enumerate(p.waves):
                row = w[p.wave_first + i]
                res["gauges"][g.name] = {
                    "position_m": list(g.position_m), "still_level_m": p.still[i], "arrival_threshold_m": p.thresholds[i],
                    "max_crest_m": row[gauge_k.HZ_MAX], "max_crest_time_s": row[gauge_k.HZ_T_MAX],
                    "deepest_trough_m": row[gauge_k.HZ_MIN], "deepest_trough_time_s": row[gauge_k.HZ_T_MIN],
                    "arrival_time_s": row[gauge_k.HZ_ARRIVAL]}
            c0 = p.col_first
            for i, (r, (_, pos)) in enumerate(zip(p.runups, p.columns)):
                a = cols[c0:c0 + len(pos)]
                c0 += len(pos)
                tops = np.where(np.isfinite(a[:, 0]), a[:, 0] - off_up, np.nan)
                if np.isfinite(tops).any():
                    c = int(np.nanargmax(tops))
                    best, when, at = tops[c], a[c, 1], [pos[c][j] for j in horiz]
                else:
                    best, when, at = math.nan, math.nan, None
                res["runup"][r.name] = {
                    "max_runup_m": best, "max_runup_above_still_m": best - p.runup_still[i], "still_level_m": p.runup_still[i],
                    "max_runup_time_s": when, "max_runup_at_m": at,
                    "columns_m": [[q[j] for j in horiz] for q in pos], "column_max_m": tops}
            if p.slides:
                end = sim.block_positions(k)
                names = sim.scenario_blocks(k)
                for i, sl in enumerate(p.slides):
                    p0, p1 = self.slide_start[p.slide_first + i][:dim], end[names.index(sl.block)][:dim]
                    s = ss[p.slide_first + i]
                    res["slides"][sl.block] = {"initial_position_m": p0, "final_position_m": p1,
                                               "runout_m": float(np.linalg.norm(p1 - p0)),
                                               "peak_speed_m_s": s[0], "peak_speed_time_s": s[1]}
            for i, cr in enumerate(p.crossings):
                c = cs[p.cross_first + i]
                res["crossings"][cr.name] = {"initial_volume_m3": c[0], "net_volume_m3": c[1],
                                             "max_volume_m3": c[2], "max_volume_time_s": c[3]}
            out.append(_clean(res))
        return out


class _OwnState:
    """Scenario k's fluid state for its Gauges at start-up (the still levels): its particles in its own frame."""

    def __init__(self, sim, k: int):
        a, b = sim.tiles[k].fluid
        d = sim.device
        nf = sim.fluid.n_fluid
        x = sim.state.x.numpy()[:nf]
        rho = sim.state.rho.numpy()[:nf]
        ids = sim.state.ids.numpy()[:nf]
        sel = (ids >= a) & (ids < b)
        order = np.argsort(ids[sel])
        xk = x[sel][order].astype(np.float64) - sim.tiles[k].offset
        self.x = wp.array(xk.astype(np.float32), dtype=wp.vec3, device=d)
        self.rho = wp.array(rho[sel][order], dtype=float, device=d)
