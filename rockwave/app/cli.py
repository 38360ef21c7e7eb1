"""Command line: ``python -m rockwave run|validate|scenes|info|schema|preview|plot|sweep``. A thin layer over the Python API."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from rockwave.app.plot import plot_gauges
from rockwave.app.preview import PreviewError, render_preview, render_strip
from rockwave.app.sweep import cli as sweep_cli
from rockwave.app.validate import check_built, validate
from rockwave.base.device import DeviceError, WarpCacheError, init_warp, quiet_warp, resolve_device
from rockwave.base.errors import SimulationError
from rockwave.build import preflight
from rockwave.scene.format import SceneError, load_scene, scene_format_doc
from rockwave.sim.checkpoint import CheckpointError
from rockwave.sim.distributed import BALANCE_BY, DistributedSimulation, world_size_from_env
from rockwave.sim.simulation import Simulation
from rockwave.sim.transport import KINDS as TRANSPORTS

DEFAULT_SCENE_NAME = "dam_break_3d.toml"


def default_scene() -> Path:
    """The built-in default scene: shipped inside the package as ``rockwave.scenes`` (the top-level
    scenes/ folder of a checkout), so it is found from any install and any working folder."""
    try:
        from importlib.resources import files

        p = files("rockwave.scenes") / DEFAULT_SCENE_NAME
        if p.is_file():
            return Path(str(p))
    except (ImportError, OSError, TypeError):
        pass
    return Path(__file__).resolve().parents[2] / "scenes" / DEFAULT_SCENE_NAME  # the checkout's scenes/ folder


def _shipped_dir() -> Path:
    return default_scene().parent


def shipped_scenes() -> list[Path]:
    """The scenes shipped with rockwave (``rockwave.scenes``, the checkout's scenes/ folder), sorted by name."""
    return sorted(_shipped_dir().glob("*.toml"))


def scene_summary(path: Path) -> str:
    """The first sentence of a scene file's leading comment (what ``python -m rockwave scenes`` lists)."""
    lines = []
    try:
        with open(path, encoding="utf-8") as f:
            for line in f:
                if not line.startswith("#"):
                    break
                lines.append(line.lstrip("#").strip())
    except (OSError, UnicodeDecodeError):
        return ""
    text = " ".join(l for l in lines if l)
    for m in re.finditer(r"([A-Za-z.]*)\.\s", text):  # the first full stop that does not end an abbreviation
        if len(m.group(1)) > 1 and not m.group(1)[0].isupper() and m.group(1).lower() not in ("al", "fig", "eq", "eqs", "vol", "e.g", "i.e", "cf", "no", "pp"):
            text = text[: m.end(1) + 1]
            break
    return text if len(text) <= 160 else text[:157].rsplit(" ", 1)[0] + " ..."


def resolve_scene(arg: str) -> str:
    """A scene argument as given, or, when no such file exists and it is a bare name, the shipped scene of that name
    (``dam_break_2d`` or ``dam_break_2d.toml``: found from a wheel install and from any folder)."""
    p = Path(arg)
    if p.exists() or len(p.parts) != 1:
        return arg
    name = p.name if p.suffix == ".toml" else p.name + ".toml"
    shipped = _shipped_dir() / name
    return str(shipped) if shipped.is_file() else arg


def _list_scenes() -> int:
    scenes = shipped_scenes()
    width = max((len(p.stem) for p in scenes), default=0)
    print(f"shipped scenes ({_shipped_dir()}); run one by name, e.g. python -m rockwave run {scenes[0].stem if scenes else 'NAME'}:")
    for p in scenes:
        print(f"  {p.stem:<{width}}  {scene_summary(p)}")
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m rockwave", description="rockwave: rock masses and water (SPH + DDA on NVIDIA Warp)")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run a scene and write USD frames, gauges and run.json")
    r.add_argument("scene", nargs="?", default=None, help=f"scene TOML file, or the name of a shipped scene (python -m rockwave scenes; default: the built-in {DEFAULT_SCENE_NAME})")
    r.add_argument("--device", default=None, help="auto | cpu | cuda | cuda:N (default: the scene's, normally auto)")
    r.add_argument("--out", default=None, help="output folder (default: runs/<scene name>)")
    r.add_argument("--duration", type=float, default=None, help="simulated seconds (overrides simulation.duration_s)")
    r.add_argument("--quiet", action="store_true", help="no progress bar and no Warp messages")
    r.add_argument("--yes", action="store_true", help="run even when the run-length check estimates more than 1e7 steps or "
                   "24 h of wall time, or a speed of sound below the expected flow speed")
    r.add_argument("--resume", action="store_true", help="continue from the output folder's checkpoint.npz (written every "
                   "output.checkpoint_interval_s of wall-clock time, on Ctrl-C and on a blow-up)")
    r.add_argument("--checkpoint-every", type=float, default=None, metavar="SECONDS",
                   help="wall-clock seconds between checkpoints (overrides output.checkpoint_interval_s; 0: none)")
    r.add_argument("--ranks", action="store_true", help="one scene on all ranks of the MPI job (mpiexec -n N ...; detected "
                   "without the flag when the MPI world has more than one rank; docs/mpi.md)")
    r.add_argument("--transport", choices=TRANSPORTS, default="auto",
                   help="with ranks: how halos travel between them: nccl (GPU to GPU), cuda-mpi (a CUDA-aware MPI), "
                   "host (mpi4py on host copies; the CPU path) or auto (the first of these that runs; run.json's "
                   "ranks.transport says which did)")
    r.add_argument("--balance-by", choices=BALANCE_BY, default="time",
                   help="with ranks: the slab faces follow each rank's measured compute time (time, default) or its "
                   "particle count (count)")
    r.add_argument("--output-chunk", type=int, default=None, metavar="PARTICLES",
                   help="with ranks: rank 0 holds the whole water on the host and evaluates the outputs (gauges, surface, "
                   "hazard) on its device this many particles at a time (default 2^21; docs/mpi.md)")
    v = sub.add_parser("validate", help="check a scene file without running it: every check 'run' makes before its first step")
    v.add_argument("scene", nargs="?", default=None, help=f"scene TOML file, or the name of a shipped scene (python -m rockwave scenes; default: the built-in {DEFAULT_SCENE_NAME})")
    v.add_argument("--device", default=None, help="device the memory and run-length estimates are for (default: the scene's)")
    v.add_argument("--duration", type=float, default=None, help="simulated seconds (as for run)")
    v.add_argument("--yes", action="store_true", help="do not refuse a long run (as for run)")
    sub.add_parser("info", help="Warp version and devices")
    sub.add_parser("scenes", help="list the shipped scenes (run or validate one by its bare name, e.g. dam_break_2d)")
    sub.add_parser("schema", help="print the scene format as a Markdown table")
    pv = sub.add_parser("preview", help="draw one frame of a run as a PNG (particles coloured by speed or pressure, blocks outlined)")
    pv.add_argument("run_dir", help="a run's output folder (holds run.json and the USD stage)")
    pv.add_argument("--frame", type=int, default=None, help="frame number (default: the last)")
    pv.add_argument("--color", choices=("speed", "pressure"), default="speed", help="particle colour (default: speed)")
    pv.add_argument("--axis", choices=("x", "y", "z"), default="y", help="3D: look along this axis (default: y, the x-z side view)")
    pv.add_argument("--slice", type=float, default=None, dest="slice_at", help="3D: only particles within one spacing of the plane at this position along --axis")
    pv.add_argument("--out", default=None, help="PNG path (default: RUN_DIR/preview_NNNNN.png, or RUN_DIR/strip_N_<colour>_<axis>.png)")
    pv.add_argument("--strip", type=int, default=None, metavar="N", help="a frame strip: N frames from the first to the last, stacked in one PNG on one colour scale (instead of --frame)")
    pl = sub.add_parser("plot", help="draw a run's gauge time series (with the scene's reference data) as a PNG")
    pl.add_argument("run_dir", help="a run's output folder (holds gauges.csv / blocks.csv and run.json)")
    pl.add_argument("--scene", default=None, help="scene file for gauge kinds and references (default: the one in run.json)")
    pl.add_argument("--out", default=None, help="PNG path (default: RUN_DIR/gauges.png)")
    sw = sub.add_parser("sweep", help="run a scenario study: a base scene with keys varied (grid, random or Latin hypercube), "
                        "each scenario's hazard summary in one table (rockwave/app/sweep.py)")
    sw.add_argument("study", help="study TOML file ([study] scene or generator, results, sample; [[vary]] key, values or "
                    "range), or the name of a shipped study (scenes/studies/: impulse_2d, impulse_2d_convergence, impulse_2d_front)")
    sw.add_argument("--out", default=None, help="result folder (default: the study's results)")
    sw.add_argument("--workers", type=int, default=None, help="local workers (default: one per GPU, else the CPU count)")
    sw.add_argument("--ray", default=None, metavar="ADDRESS", help="run on a Ray cluster ('auto', 'ray://HOST:10001'; "
                    "'local' starts one here) instead of the local process pool")
    sw.add_argument("--gpus-per-scenario", type=float, default=None, help="Ray: GPUs per scenario (a fraction shares one GPU "
                    "among small scenarios; default 1 when the cluster has GPUs, else 0)")
    sw.add_argument("--retry-failed", action="store_true", help="run the failed scenarios again (finished ones are skipped)")
    sw.add_argument("--only", type=int, action="append", default=None, metavar="INDEX", help="run only this scenario "
                    "(a Slurm array task); repeatable")
    sw.add_argument("--batch", type=int, default=1, metavar="N", help="step N scenarios of one template together on one "
                    "device (rockwave/app/batch.py; 0: as many as a particle budget fills, 1 (default): one at a time); "
                    "each still writes its own result and hazard summary")
    sw.add_argument("--collect", action="store_true", help="run nothing: write the table and plots from the results so far")
    sw.add_argument("--slurm", action="store_true", help="write RESULTS/sweep.sbatch (a job array, one task per scenario) and stop")
    sw.add_argument("--list", action="store_true", help="validate the study and list its scenarios; run nothing")
    sw.add_argument("--quiet", action="store_true", help="no progress lines")
    return p


def _fail(msg: str, code: int = 2) -> int:
    print(f"error: {msg}", file=sys.stderr)
    return code


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return _main(args)
    except WarpCacheError as e:  # the folder and WARP_CACHE_PATH, one line (commands that need kernels)
        return _fail(str(e))


def _main(args) -> int:
    if args.command != "run" or args.quiet:
        quiet_warp(init=False)  # Warp is initialised where a device or kernels are needed (resolve_device), not here

    if args.command == "schema":
        sys.stdout.write(scene_format_doc())
        return 0
    if args.command == "scenes":
        return _list_scenes()
    if args.command in ("preview", "plot"):

        try:
            if args.command == "preview":

                if args.strip is not None:
                    path = render_strip(args.run_dir, args.strip, args.color, args.axis, args.slice_at, args.out)
                else:
                    path = render_preview(args.run_dir, args.frame, args.color, args.axis, args.slice_at, args.out)
            else:

                path = plot_gauges(args.run_dir, args.out, scene=args.scene)
        except (PreviewError, SceneError) as e:
            return _fail(e.one_line() if isinstance(e, SceneError) else str(e))
        print(path)
        return 0
    if args.command == "sweep":

        return sweep_cli(args)
    if args.command == "info":
        import warp as wp

        init_warp()
        print(f"rockwave {__import__('rockwave').__version__}, warp {wp.__version__}")
        for d in wp.get_devices():
            extra = ""
            if d.is_cuda:
                extra = f", {d.total_memory / 2**30:.1f} GiB, sm_{d.arch}"
            print(f"  {d.alias}: {d.name}{extra}")
        return 0
    scene_path = resolve_scene(args.scene) if args.scene else str(default_scene())
    try:
        scene = load_scene(scene_path)
    except SceneError as e:
        if args.command == "validate":
            print(str(e), file=sys.stderr)
            return 2
        return _fail(e.one_line())
    if args.duration is not None and not (args.duration > 0 and args.duration < float("inf")):
        return _fail(f"--duration must be a positive number of seconds, got {args.duration}")

    try:
        device = resolve_device(args.device if args.device is not None else scene.simulation.device)
    except DeviceError as e:
        return _fail(f"--device: {e}" if args.device is not None else f"{scene_path}: simulation.device: {e}")
    import warnings

    warnings.formatwarning = lambda msg, *a, **k: f"warning: {msg}\n"
    if args.command == "validate":
        try:
            found = validate(scene, device, duration=args.duration, force=args.yes)
        except SceneError as e:
            print(str(e), file=sys.stderr)
            return 2
        except (SimulationError, ValueError, OSError) as e:  # as run reports them before its first step
            return _fail(str(e), 1)
        rl = found["run_length"]
        print(f"{scene_path}: ok ({scene.dim}D, {len(scene.fluid.regions) if scene.fluid is not None else 0} fluid region(s), "
              f"{len(scene.blocks)} block entr{'y' if len(scene.blocks) == 1 else 'ies'}"
              + (f", {len(scene.rock_mass)} rock mass{'' if len(scene.rock_mass) == 1 else 'es'}" if scene.rock_mass else "")
              + f", duration {rl.duration:g} s; "
              f"on {device}: {rl.describe()})")
        return 0
    # run: the checks of validate that need no block model (Simulation builds the blocks and checks them)
    try:
        meshes = preflight.check_meshes(scene)
        preflight.check_scene(scene, device, meshes)
        preflight.check_water_outside_blocks(scene, meshes)  # (scenes of water and blocks)
        preflight.check_run_length(scene, device, duration=args.duration, force=args.yes)
    except SceneError as e:
        return _fail(e.one_line())

    if args.checkpoint_every is not None and not (0 <= args.checkpoint_every < float("inf")):
        return _fail(f"--checkpoint-every must be a number of seconds >= 0, got {args.checkpoint_every}")

    out = Path(args.out) if args.out else Path("runs") / scene.name

    ranks, sim = args.ranks or world_size_from_env() > 1, None
    try:
        if ranks:  # rockwave/sim/distributed.py: rank 0 runs the loop below, the other ranks follow it

            sim = DistributedSimulation(scene, device=device, transport=args.transport, balance_by=args.balance_by,
                                        output_chunk=args.output_chunk)
            if sim.rank != 0:
                sim.serve()
                return 0
            print(f"{sim.size} ranks, slabs along axis {sim.dfluid.dec.axis} (halo {sim.dfluid.dec.halo:g} m, transport "
                  f"{sim.transport})", file=sys.stderr)
        else:
            sim = Simulation(scene, device=device)
        sim.run_length_forced = bool(args.yes)  # --yes, for the run loop's own run-length check
        check_built(sim)
        if not args.quiet:
            parts = []
            if sim.fluid is not None:
                parts.append(f"{sim.fluid.n_fluid:,} fluid + {sim.fluid.n_boundary:,} boundary particles "
                             f"(support {sim.fluid.support_radius:g} m, c0 = {sim.fluid.sound_speed:.3g} m/s)")
            if sim.blocks is not None:
                parts.append(f"{sim.blocks.num_blocks:,} blocks (critical step {sim.block_solver.critical_dt():.3g} s)")
            print(f"{scene_path}: {' and '.join(parts)} on {sim.device}, dt = {sim.dt:.3g} s", file=sys.stderr)
        summary = sim.run(out, duration=args.duration, progress=not args.quiet, resume=args.resume,
                          checkpoint_interval_s=args.checkpoint_every)
    except SceneError as e:
        return _fail(e.one_line())
    except CheckpointError as e:
        return _fail(str(e))
    except (SimulationError, ValueError, OSError) as e:
        return _fail(str(e), 1)
    except KeyboardInterrupt:
        print(f"interrupted: frames written so far are in {out}; continue with --resume", file=sys.stderr)
        return 130
    finally:
        if ranks and sim is not None and getattr(sim, "rank", 1) == 0:
            sim.finish()  # release the other ranks (or abort them when rank 0 stopped inside a step)
    rates = [f"{summary[k]:.3g} {k.replace('_per_s', '').replace('_', '-')}/s" for k in ("particle_steps_per_s", "block_steps_per_s") if summary.get(k)]
    left = summary.get("particles_outside_domain") or 0
    left = f"; {left} fluid particle(s) left the tank (particles_outside_domain in run.json)" if left else ""
    print(f"done: {summary['simulated_s']:.3g} s simulated in {summary['steps']} steps, {summary['wall_s']:.1f} s wall"
          f" ({', '.join(rates)}){left}; outputs in {out}")
    return 0
