"""The run loop: a simulation advanced frame by frame, its outputs recorded, checkpointed and
guarded.

``run(sim, out_dir)`` (also ``Simulation.run`` and ``python -m rockwave run``): after each output
frame the state is read once into a :class:`rockwave.output.recorders.Frame`, checked by the blow-up
guard (rockwave/sim/guard.py) and handed to the recorders; a device-side copy of the state is kept for
the checkpoint (rockwave/sim/checkpoint.py), written every ``output.checkpoint_interval_s`` of wall time,
on a blow-up and on Ctrl-C. The summary goes to ``run.json``.
"""

from __future__ import annotations

import json
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path

from rockwave.app.progress import Progress
from rockwave.base.errors import SimulationError
from rockwave.base.files import atomic_write_text
from rockwave.build import preflight
from rockwave.output import recorders as rec
from rockwave.output import surface as surf
from rockwave.output.hazard import HazardMonitor, slide_motion_csv
from rockwave.scene.format import SCHEMA
from rockwave.sim import checkpoint as ckpt

WATCH_INTERVAL_S = 2.0  # wall seconds between progress lines and health checks inside a frame
COST_STEPS = 5  # steps after the first whose measured cost feeds the run-length check


HAZARD_FILE = "hazard.json"  # the [hazard] summary (rockwave/output/hazard.py), also under "hazard" in run.json
SLIDE_MOTION_FILE = "slide_motion.csv"  # [[hazard.slides]]: each slide's centroid and velocity at every sample
MANIFEST = ".rockwave-outputs.json"  # the outputs a run writes into its folder (removed by the next fresh run there)


def _summary_path(out: Path) -> Path:
    return out / "run.json"


def _replace_previous_outputs(out: Path, names: list[str]) -> None:
    """A fresh run in a folder used before: remove what the previous run listed as its outputs (a reused folder
    must not mix two runs: stale frames, a VTK series or a CSV the new scene does not write), then list ours."""
    import shutil

    m = out / MANIFEST
    old = []
    if m.is_file():
        try:
            old = json.loads(m.read_text()).get("outputs", [])
        except (OSError, ValueError):
            old = []
    root = out.resolve()
    for n in old:
        p = (out / n).resolve()
        if p == root or root not in p.parents:  # only what lies inside the folder
            continue
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        elif p.exists():
            p.unlink()
    atomic_write_text(m, json.dumps({"outputs": names}))


class _Watch:
    """Called after every step (Simulation.advance's ``watch``): every WATCH_INTERVAL_S of wall time, whatever
    the frame rate, it redraws the progress line and runs the blow-up guard on the current state (reads
    only); once the first steps are done (kernels compiled), it checks the run length with their measured
    cost (rockwave/build/preflight.py check_run_length: a run that would take days stops with the key to change)."""

    def __init__(self, sim, bar, t_end: float, t0: float, force: bool, health):
        self.sim, self.bar, self.t_end, self.t0, self.force, self.health = sim, bar, t_end, t0, force, health
        self.last = time.perf_counter()
        self.first = None  # (wall, steps) after the first step
        self.cost_checked = False

    def note(self) -> str:
        return f"step {self.sim.clock.describe()}"

    def __call__(self) -> None:
        sim = self.sim
        now = time.perf_counter()
        if self.first is None:
            self.first = (now, sim.steps)
        elif not self.cost_checked and sim.steps - self.first[1] >= COST_STEPS and (
                now - self.first[0] > 0.5 or sim.steps - self.first[1] >= 10 * COST_STEPS):
            per_step = (now - self.first[0]) / (sim.steps - self.first[1])
            preflight.check_run_length(sim.scene, sim.device, duration=max(self.t_end - sim.time, 0.0),
                                       seconds_per_step=per_step, dt=sim.dt, force=self.force, setup=False)
            self.cost_checked = True
        if now - self.last >= WATCH_INTERVAL_S:
            self.last = now
            self.health()
            self.bar.update(sim.time - self.t0, sim.steps, force=True, note=self.note())


def _setup_progress(what: str, unit: str, every_s: float = WATCH_INTERVAL_S):
    """progress(done, total) for a long set-up step: a line on stderr every ``every_s`` of wall time and at the end,
    once it has lasted that long (a quick set-up prints nothing)."""
    t0 = time.perf_counter()
    last = [t0]

    def progress(done: int, total: int) -> None:
        now = time.perf_counter()
        if now - last[0] >= every_s or (done >= total and now - t0 >= every_s):
            last[0] = now
            print(f"{what}: {done:,} / {total:,} {unit} ({now - t0:.0f} s)", file=sys.stderr, flush=True)

    return progress


def _finished_summary(out: Path, sim, meta: dict, duration: float) -> dict | None:
    """``--resume`` of a run that already reached its end: the run.json it wrote (unchanged: nothing is run again,
    no output is rewritten), after a line saying so; None when there is more to simulate (a longer duration) or no
    readable summary of a finished run."""
    if meta.get("reason") != "end" or meta["t0"] + duration - sim.time > 1e-9:
        return None
    try:
        summary = json.loads(_summary_path(out).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(summary, dict) or summary.get("interrupted") or "steps" not in summary:
        return None
    print(f"nothing to resume: the run in {out} already reached its end (t = {sim.time:.6g} s); {_summary_path(out)} is "
          f"unchanged (a longer --duration or simulation.duration_s continues it)", file=sys.stderr)
    return summary


def run(sim, out_dir: str | os.PathLike, duration: float | None = None, progress: bool = True,
        resume: bool = False, checkpoint_interval_s: float | None = None, force: bool = False) -> dict:
    """Run ``sim``'s scene for ``duration`` (default: the scene's), writing outputs into ``out_dir``.
    Returns the run summary (also written as ``run.json``).

    ``resume``: continue from ``out_dir/checkpoint.npz`` (rockwave/sim/checkpoint.py) with the outputs
    written so far. ``checkpoint_interval_s``: wall-clock seconds between checkpoints (default
    ``output.checkpoint_interval_s``; 0: none, except on a blow-up or Ctrl-C). Ctrl-C finishes the
    current frame, writes a checkpoint, closes the USD stage and raises KeyboardInterrupt. ``force``: run even when
    the measured cost of the first steps says the run would take longer than preflight.MAX_WALL_S (CLI --yes).

    Outputs from the first frame on: the USD stage opens after frame 0 (its first chunks are short,
    rockwave/output/usd.py), the first checkpoint is written after the first computed frame, then every
    ``checkpoint_interval_s`` of wall time."""

    scene = sim.scene
    out = Path(out_dir)
    resumed = ckpt.read_file(out / ckpt.FILE_NAME) if resume else None
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write_test"
        probe.write_bytes(b"ok")
        probe.unlink()
    except OSError as e:
        raise SimulationError(f"output folder {out} is not writable: {e}") from None
    duration = scene.simulation.duration_s if duration is None else duration
    fps = scene.output.frame_rate_hz
    hazard = None
    if scene.hazard is not None:  # [hazard]: statistics reduced on the device after each step (rockwave/output/hazard.py)
        # made from the scene's initial state (its still levels and slide starts), then restored with the rest: a
        # resumed run's summary is the whole run's
        hazard = HazardMonitor(sim)
        ckpt.register(sim, "hazard", hazard)
        if hasattr(sim, "gather_when"):  # several ranks: the water comes to rank 0 at the sample times only
            sim.gather_when = hazard.wants_water
    if resumed is not None:
        ckpt.restore(sim, *resumed)
        meta = resumed[1]
        print(f"resuming {out} from frame {meta['frame']} (t = {sim.time:.6g} s, step {sim.steps})", file=sys.stderr)
        if hazard is not None and "hazard" not in meta["groups"]:  # a checkpoint from before format 5
            hazard = HazardMonitor(sim)
            ckpt.register(sim, "hazard", hazard)
            if hasattr(sim, "gather_when"):
                sim.gather_when = hazard.wants_water
            print(f"warning: the checkpoint holds no hazard statistics (written by an older rockwave): {HAZARD_FILE} "
                  f"covers t >= {sim.time:.6g} s only", file=sys.stderr)
    else:
        ckpt.clear(out)
    n_frames = int(math.floor(duration * fps + 1e-9))
    frame_dt = 1.0 / fps
    nf = sim.n_fluid

    # recorders (rockwave/output/recorders.py)

    o = scene.output
    if resumed is None:  # before the recorders make their files and folders
        names = ["run.json", ckpt.FILE_NAME] + ([HAZARD_FILE] if scene.hazard is not None else [])
        if scene.hazard is not None and scene.hazard.get("slides"):
            names.append(SLIDE_MOTION_FILE)
        if o.usd:
            names += [o.usd, Path(o.usd).stem + ".clips"]
        if sim.gauge_names and o.gauges_csv:
            names.append(o.gauges_csv)
        if sim.blocks is not None and o.blocks_csv:
            names.append(o.blocks_csv)
        if o.get("energy_csv"):
            names.append(o.energy_csv)
        if o.get("vtk"):
            names.append(o.vtk)
        _replace_previous_outputs(out, names)
    surface = None
    if nf and (o.usd or o.get("vtk")):  # the surface goes nowhere else
        surface = surf.extractor_for(scene, sim.fluid, sim.device)
    usd = rec.UsdRecorder(sim, out / o.usd, surface, progress=_setup_progress("USD set-up", "block prims") if progress else None) \
        if o.usd else None
    gauges = rec.gauge_csv(out / o.gauges_csv, sim.gauge_names) if sim.gauge_names and o.gauges_csv else None
    blocks = (rec.block_csv(out / o.blocks_csv, sim.blocks.names, skip=[i for i, sp in enumerate(sim.blocks.specs) if sp.tank])
              if sim.blocks is not None and o.blocks_csv else None)
    vtk = rec.VtkRecorder(sim, out / o.vtk) if o.get("vtk") else None
    energy = rec.EnergyRecorder(sim, out / o.energy_csv if o.get("energy_csv") else None)  # the budget, checked each frame
    recorders = [r for r in (usd, vtk, blocks, gauges, energy) if r is not None]

    bar = Progress(duration, nf if nf else (sim.blocks.num_blocks if sim.blocks is not None else 0), enabled=progress,
                   unit="particles" if nf else "blocks")
    wall0 = time.perf_counter()
    escaped = 0
    t0 = sim.time
    interrupted = False
    first, steps0, block_steps0 = 0, sim.steps, sim.clock.block_steps
    wall_before = 0.0  # wall time of the run's earlier processes (a resumed run)
    if resumed is not None:  # outputs continue where the checkpoint was taken
        meta = resumed[1]
        t0, first, escaped = meta["t0"], meta["frame"] + 1, meta["escaped"]
        wall_before = float(meta.get("wall_s") or 0.0)
        try:
            if usd is not None:
                usd.restore(meta["usd"])
            if gauges is not None:
                gauges.restore(meta["csv"].get("gauges"))
            if blocks is not None:
                blocks.restore(meta["csv"].get("blocks"))
            energy.restore(meta["csv"].get("energy"))
        except (OSError, ValueError) as e:
            raise ckpt.CheckpointError(f"cannot resume in {out}: {e}") from None
        if vtk is not None:
            vtk.restore(meta.get("vtk"))
        done = _finished_summary(out, sim, meta, duration)  # (the outputs checked first: they end where it ended)
        if done is not None:
            for r in recorders:
                r.close()
            bar.close()
            return done
    else:
        preflight.check_disk(sim, out, n_frames)

    default_interval = SCHEMA["output"].children["checkpoint_interval_s"].default  # its one home: the scene schema
    interval = o.get("checkpoint_interval_s", default_interval) if checkpoint_interval_s is None else checkpoint_interval_s
    checkpointer = ckpt.RunCheckpointer(sim, out, interval, t0, lambda: {
        "usd": usd, "escaped": escaped, "vtk": vtk, "csv": {"gauges": gauges, "blocks": blocks, "energy": energy},
        "wall_s": wall_before + time.perf_counter() - wall0})

    def check_health(f: rec.Frame) -> None:
        nonlocal escaped
        left = sim.check_health(f.x[:, : scene.dim], f.v[:, : scene.dim])
        if sim.fluid is not None:
            escaped = left

    def write_frame(index: int) -> None:
        f = rec.Frame(sim, index, surface)
        check_health(f)
        for r in recorders:
            r.frame(f)

    watch = _Watch(sim, bar, t0 + duration, t0, force or bool(getattr(sim, "run_length_forced", False)),
                   lambda: check_health(rec.Frame(sim, -1)))

    if hazard is not None:
        watch = hazard.wrap(watch)

    stop = []

    def on_sigint(signum, frm):
        if stop:  # a second Ctrl-C stops at once
            raise KeyboardInterrupt
        stop.append(True)
        print("\ninterrupted: finishing the current frame, then writing a checkpoint (Ctrl-C again to stop at once)",
              file=sys.stderr)

    old_handler = signal.signal(signal.SIGINT, on_sigint) if threading.current_thread() is threading.main_thread() else None
    failed = False
    try:
        if first == 0:
            write_frame(0)
            checkpointer.frame_done(0)
        for f in range(max(first, 1), n_frames + 1):
            if stop:
                break
            sim.advance(t0 + f * frame_dt - sim.time, watch)
            write_frame(f)
            checkpointer.frame_done(f)
            bar.update(sim.time - t0, sim.steps, note=watch.note())
        if stop:
            interrupted = True
            checkpointer.write("interrupt")
        else:
            rest = t0 + duration - sim.time
            if rest > 1e-9:
                sim.advance(rest, watch)
            if checkpointer.interval > 0:
                if usd is not None:  # the last chunk closed first: the checkpoint then holds no copy of it
                    usd.writer.flush()
                checkpointer.write("end")
    except KeyboardInterrupt:
        interrupted = True
    except SimulationError as e:  # blow-up: the outputs end at the last good frame, which is checkpointed
        failed = True
        try:
            path = checkpointer.write("blow-up")
            kept = f"; frames up to {checkpointer.frame} are kept in {out}" if checkpointer.frame >= 0 else ""
            more = f"; checkpoint of frame {checkpointer.frame} written to {path} (continue with --resume)" if path else ""
        except OSError as we:
            kept, more = "", f"; no checkpoint written ({we})"
        err = SimulationError(f"{e}{kept}{more}")
        err.__dict__.update(e.__dict__)
        raise err from None
    except OSError as e:  # full disk, folder removed: what was written stays as it was
        failed = True
        last = checkpointer.written_frame
        raise SimulationError(f"cannot write the outputs in {out}: {e}; the files written before are intact "
                              f"(last frame computed {checkpointer.frame}"
                              f"{', last checkpoint frame ' + str(last) if last is not None else ''})") from None
    finally:
        if old_handler is not None:
            signal.signal(signal.SIGINT, old_handler)
        for r in recorders:
            try:
                r.close()
            except OSError:
                if not failed:
                    raise
        bar.close()
    wall = time.perf_counter() - wall0
    summary = {
        "scene": str(Path(scene.path).resolve()) if scene.path != "<scene>" else scene.path,
        "device": sim.device,
        "fluid_particles": nf,
        "boundary_particles": sim.fluid.n_boundary if sim.fluid is not None else 0,
        "blocks": sim.blocks.num_blocks if sim.blocks is not None else 0,
        "removed_inside_blocks": sim.removed_inside_blocks,
        "simulated_s": sim.time - t0,
        "steps": sim.steps,
        "step_limited_by": sim.clock.limiting,
        "steps_limited_by": dict(sim.clock.steps_limited_by),
        "block_substeps": sim.clock.substeps if sim.clock.block_substep is not None else None,
        "block_steps": sim.clock.block_steps if sim.blocks is not None else None,
        "block_start": dict(sim.block_solver.start_report) if sim.block_solver is not None else None,
        "wall_s": wall_before + wall,  # the whole run's (a resumed run: every process's)
        "wall_s_this_process": wall,
        "particle_steps_per_s": nf * (sim.steps - steps0) / wall if wall > 0 and nf else None,
        "block_steps_per_s": (sim.blocks.num_blocks * (sim.clock.block_steps - block_steps0) / wall  # sub-steps counted
                              if wall > 0 and sim.blocks is not None else None),
        "particles_outside_domain": escaped,
        "usd": str(out / o.usd) if usd is not None else None,
        "interrupted": interrupted,
        "resumed_from_frame": resumed[1]["frame"] if resumed is not None else None,
        "checkpoint": str(checkpointer.path) if checkpointer.written_frame is not None else None,
    }
    summary["energy"] = energy.summary()
    if hasattr(sim, "run_report"):  # several ranks (rockwave/sim/distributed.py): the transport that ran, rebuilds, balance
        summary["ranks"] = sim.run_report()
    if hazard is not None:
        summary["hazard"] = hazard.result()
        atomic_write_text(out / HAZARD_FILE, json.dumps(summary["hazard"], indent=2))
        motion = slide_motion_csv(summary["hazard"])
        if motion:
            atomic_write_text(out / SLIDE_MOTION_FILE, motion)
    atomic_write_text(_summary_path(out), json.dumps(summary, indent=2))
    if interrupted:
        raise KeyboardInterrupt
    return summary

