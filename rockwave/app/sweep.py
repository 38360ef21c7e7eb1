"""Scenario studies: ``python -m rockwave sweep STUDY.toml``.

A study file names a base scene and the keys to vary; each scenario is the base scene with those keys
replaced. Every scenario is validated before anything runs (all bad scenarios reported at once, as one
SceneError naming the study file). Each scenario runs through one entry point, :func:`run_scenario`
(config -> summary), on an existing executor: a local process pool (default; one worker per GPU, or
``workers`` CPU slots) or Ray (``--ray ADDRESS``; GPUs as Ray resources). A Slurm job-array script is
written by ``--slurm``. Results are written atomically per scenario (``scenarios/<id>/result.json``);
a re-run skips the finished ones; a scenario that fails (a blow-up, a bad run) or whose worker dies is
recorded with its error and the others go on. The study table (``study.parquet`` and ``study.csv``)
holds one row per scenario: its varied values and its hazard summary (rockwave/output/hazard.py); plots:
``max_wave_height.png`` (highest crest at each gauge against each varied key) and ``runup.png`` (run-up
along the shore, one line per scenario). Instead of a base scene, ``generator = NAME`` builds each scenario from a
scene maker's parameters (rockwave/app/impulse.py; a ``[generator]`` table holds the fixed ones, ``[[vary]]`` keys
name the varied ones); its comparison joins each row and ``comparison.md``/``.csv``/``.png`` hold the error table.
Shipped studies (scenes/studies/) run by name: ``python -m rockwave sweep impulse_2d``.

Study file::

    [study]
    scene = "../scenes/slide_2d.toml"   # base scene, relative to the study file
    results = "runs/slide_study"        # result folder, relative to the study file (CLI --out overrides)
    sample = "grid"                     # 'grid' (every combination), 'random' or 'lhs' (Latin hypercube) of n
    n = 16                              # random / lhs: number of scenarios
    seed = 0                            # random / lhs
    duration_s = 2.0                    # overrides simulation.duration_s
    keep = ["gauges_csv"]               # outputs each scenario keeps besides run.json and hazard.json
    device = "auto"

    [[vary]]
    key = "blocks[slide].density_kg_m3"        # dotted key into the scene TOML; [i] or [name] picks an entry
    values = [2000.0, 2600.0]
    [[vary]]
    key = "fluid.regions[0].box_max_m[1]"
    range = [0.2, 0.3]                  # grid: `steps` evenly spaced values; random/lhs: uniform in the range
    steps = 3
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import os
import re
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from rockwave.app import batch as batching
from rockwave.app.impulse import GENERATORS
from rockwave.base.device import device_syntax_error, init_warp, quiet_warp
from rockwave.base.files import atomic_write, atomic_write_text
from rockwave.build.builder import seed_particles
from rockwave.output.hazard import flat_metrics
from rockwave.output.impulse import chart as impulse_chart
from rockwave.output.impulse import summarise
from rockwave.scene.format import SceneError, parse_scene
from rockwave.sim.simulation import Simulation

RESULT_FILE = "result.json"
SAMPLES = ("grid", "random", "lhs")
OUTPUT_KEYS = ("usd", "gauges_csv", "blocks_csv", "vtk")
STUDY_KEYS = {"scene", "generator", "results", "sample", "n", "seed", "duration_s", "keep", "device", "workers", "workers_per_gpu"}
VARY_KEYS = {"key", "values", "range", "steps"}


class StudyError(SceneError):
    """A study file, or scenarios of it, that cannot run: one (key, message) per problem, all at once."""


# ------------------------------------------------------------------------------------------------ keys ----
_TOKEN = re.compile(r"([^.\[\]]+)|\[([^\]]*)\]")


def parse_key(key: str) -> list:
    """'blocks[slide].material.friction_angle_deg' -> ['blocks', 'slide' (by name), 'material', ...]; '[2]' -> 2."""
    out, pos = [], 0
    for m in _TOKEN.finditer(key):
        if m.start() != pos and key[pos:m.start()] != ".":
            raise ValueError(f"cannot read the key {key!r} at {key[pos:]!r}")
        pos = m.end()
        if m.group(1) is not None:
            out.append(m.group(1))
        else:
            t = m.group(2).strip()
            out.append(int(t) if re.fullmatch(r"-?\d+", t) else ("name", t.strip("'\"")))
    if pos != len(key) or not out or not isinstance(out[0], str):
        raise ValueError(f"cannot read the key {key!r}")
    return out


def set_key(data: dict, key: str, value) -> None:
    """Replace ``key`` (dotted, with [i] or [name]) in a TOML dict; a missing table on the way is made; an index
    past the end of a list, or a name no entry has, is a ValueError."""
    toks = parse_key(key)
    node = data
    for i, t in enumerate(toks):
        last = i == len(toks) - 1
        if isinstance(t, str):
            if not isinstance(node, dict):
                raise ValueError(f"{key}: {'.'.join(map(str, toks[:i])) or 'the scene'} is not a table")
            if last:
                node[t] = value
                return
            if t not in node:
                node[t] = [] if isinstance(toks[i + 1], (int, tuple)) else {}
            node = node[t]
        else:
            if not isinstance(node, list):
                raise ValueError(f"{key}: {toks[i - 1]} is not a list")
            if isinstance(t, tuple):
                hits = [j for j, e in enumerate(node) if isinstance(e, dict) and e.get("name") == t[1]]
                if not hits:
                    names = [e.get("name") for e in node if isinstance(e, dict) and "name" in e]
                    raise ValueError(f"{key}: no entry of {toks[i - 1]} is named {t[1]!r} (names: {', '.join(map(repr, names)) or 'none'})")
                t = hits[0]
            if not -len(node) <= t < len(node):
                raise ValueError(f"{key}: index {t} is past the end of {toks[i - 1]} ({len(node)} entries)")
            if last:
                node[t] = value
                return
            node = node[t]


# ------------------------------------------------------------------------------------------------ study ---
@dataclass
class Scenario:
    index: int
    params: dict  # varied key -> value
    data: dict  # the scene TOML dict with the values put in
    id: str = ""
    setup: dict = field(default_factory=dict)  # a generated scenario's setup (rockwave/app/impulse.py)


@dataclass
class Study:
    path: Path
    scene_path: Path
    results: Path
    sample: str
    keys: list
    scenarios: list = field(default_factory=list)
    device: str = "auto"
    workers: int = 0
    workers_per_gpu: int = 1
    generator: str | None = None  # a scene maker of rockwave/app/impulse.py GENERATORS


def _values(v: dict, sample: str, where: str, err) -> list | tuple | None:
    """A vary entry's values (list), or its range (lo, hi) for random/lhs sampling."""
    has_values, has_range = "values" in v, "range" in v
    if has_values == has_range:
        err(where, "give exactly one of values = [...] or range = [lo, hi]")
        return None
    if has_values:
        vals = v["values"]
        if not isinstance(vals, list) or not vals:
            err(f"{where}.values", f"expected a non-empty list, got {vals!r}")
            return None
        if "steps" in v:
            err(f"{where}.steps", "goes with range = [lo, hi], not with values")
        return vals
    r = v["range"]
    if (not isinstance(r, list) or len(r) != 2 or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in r)
            or not all(math.isfinite(x) for x in r)):
        err(f"{where}.range", f"expected [lo, hi] (two numbers), got {r!r}")
        return None
    if sample == "grid":
        steps = v.get("steps")
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            err(f"{where}.steps", f"a grid over a range needs steps = a whole number >= 1 of evenly spaced values, got {steps!r}")
            return None
        lo, hi = float(r[0]), float(r[1])
        return [lo] if steps == 1 else [lo + (hi - lo) * k / (steps - 1) for k in range(steps)]
    if "steps" in v:
        err(f"{where}.steps", f"applies to sample = 'grid' only (sample = {sample!r} draws n values from the range)")
    return (float(r[0]), float(r[1]))


def _draw(spec, u: float):
    """The value at u in [0, 1) of a list (one of its entries) or a range (lo + u (hi - lo))."""
    if isinstance(spec, tuple):
        return spec[0] + u * (spec[1] - spec[0])
    return spec[min(int(u * len(spec)), len(spec) - 1)]


def _combinations(specs: list, sample: str, n: int, seed: int) -> list[list]:
    """grid: every combination (the last key fastest); random: each value uniform (seeded); lhs: Latin hypercube,
    each key's [0, 1) cut in n strata, one draw in each, the strata shuffled independently per key (McKay,
    Beckman & Conover 1979)."""
    if sample == "grid":
        return [list(c) for c in itertools.product(*specs)]
    import numpy as np

    rng = np.random.default_rng(seed)
    if sample == "random":
        u = rng.random((n, len(specs)))
    else:
        u = np.empty((n, len(specs)))
        for k in range(len(specs)):
            u[:, k] = (rng.permutation(n) + rng.random(n)) / n
    return [[_plain(_draw(s, float(u[i, k]))) for k, s in enumerate(specs)] for i in range(n)]


def _plain(v):
    """numpy scalars as Python numbers (TOML dicts hold plain values)."""
    if hasattr(v, "item"):
        return v.item()
    return v


def _scenario_id(index: int, params: dict, base_digest: str) -> str:
    h = hashlib.sha1(json.dumps([base_digest, sorted(params.items())], sort_keys=True, default=str).encode()).hexdigest()
    return f"{index:04d}-{h[:8]}"


def load_study(path: str | os.PathLike, results: str | os.PathLike | None = None) -> Study:
    """Read a study file and build and validate every scenario. Raises StudyError listing every problem: the
    study file's own keys, then each bad scenario (its index, its values, the scene key and the problem)."""
    p = Path(path)
    if not p.is_file():
        raise StudyError(p, [("", "study file not found")])
    try:
        data = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, OSError, UnicodeDecodeError) as e:
        raise StudyError(p, [("", f"not a readable TOML file: {e}")]) from None
    errors: list[tuple[str, str]] = []
    err = lambda k, m: errors.append((k, m))  # noqa: E731
    for k in data:
        if k not in ("study", "vary", "generator"):
            err(k, "unknown section; allowed: [study], [[vary]], [generator]")
    st = data.get("study")
    if not isinstance(st, dict):
        raise StudyError(p, [("study", "required table [study] (scene = 'base scene.toml', ...) is missing")])
    for k in st:
        if k not in STUDY_KEYS:
            err(f"study.{k}", f"unknown key; allowed: {', '.join(sorted(STUDY_KEYS))}")
    scene_rel = st.get("scene")
    scene_path = None
    gen_name, gen, gen_fixed = st.get("generator"), None, data.get("generator", {})
    if gen_name is not None:
        if scene_rel is not None:
            err("study.scene", "give a base scene or a generator, not both")
        if gen_name not in GENERATORS:
            err("study.generator", f"{gen_name!r} is not a scene maker; one of {', '.join(map(repr, GENERATORS))}")
        elif not isinstance(gen_fixed, dict):
            err("generator", f"expected a table of {gen_name} parameters, got {gen_fixed!r}")
        else:
            gen = GENERATORS[gen_name]
            for k, m in gen.check(gen_fixed, partial=True):
                err(f"generator.{k}", m)
            scene_path = p.resolve()  # a generated scene's relative paths and messages refer to the study file
    elif "generator" in data:
        err("generator", "a [generator] table needs study.generator = the scene maker's name")
    elif not isinstance(scene_rel, str):
        err("study.scene", f"required: the base scene file (relative to the study file) or a generator, got {scene_rel!r}")
    else:
        scene_path = (p.parent / scene_rel).resolve()
        if not scene_path.is_file():
            err("study.scene", f"file not found: {scene_path}")
            scene_path = None
    sample = st.get("sample", "grid")
    if sample not in SAMPLES:
        err("study.sample", f"{sample!r} is not allowed; one of {', '.join(map(repr, SAMPLES))}")
        sample = "grid"
    n, seed = st.get("n"), st.get("seed", 0)
    if sample != "grid" and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        err("study.n", f"sample = {sample!r} needs n = the number of scenarios (a whole number >= 1), got {n!r}")
    if sample == "grid" and n is not None:
        err("study.n", "applies to sample = 'random' or 'lhs' (a grid runs every combination)")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        err("study.seed", f"expected a whole number >= 0, got {seed!r}")
    dur = st.get("duration_s")
    if dur is not None and (isinstance(dur, bool) or not isinstance(dur, (int, float)) or not 0 < dur < math.inf):
        err("study.duration_s", f"expected a positive number of seconds, got {dur!r}")
    keep = st.get("keep", [])
    if not isinstance(keep, list) or any(k not in OUTPUT_KEYS for k in keep):
        err("study.keep", f"expected a list of outputs from {', '.join(map(repr, OUTPUT_KEYS))} (run.json and hazard.json are "
                          f"always kept), got {keep!r}")
        keep = []
    device = st.get("device", "auto")
    if not isinstance(device, str):
        err("study.device", f"expected a string ('auto', 'cpu', 'cuda', 'cuda:N'), got {device!r}")
    else:

        why = device_syntax_error(device)
        if why:
            err("study.device", why)
    for k in ("workers", "workers_per_gpu"):
        w = st.get(k)
        if w is not None and (isinstance(w, bool) or not isinstance(w, int) or w < (0 if k == "workers" else 1)):
            err(f"study.{k}", f"expected a whole number >= {0 if k == 'workers' else 1}, got {w!r}")
    res = results if results is not None else st.get("results")
    if not isinstance(res, (str, os.PathLike)):
        err("study.results", f"required: the result folder (relative to the study file), got {res!r}")
        res = "."
    res_path = Path(res) if results is not None else (p.parent / res)
    vary = data.get("vary", [])
    if not isinstance(vary, list) or not vary or any(not isinstance(v, dict) for v in vary):
        err("vary", "at least one [[vary]] table (key = 'scene.key', values = [...] or range = [lo, hi]) is needed")
        vary = []
    keys, specs = [], []
    for i, v in enumerate(vary):
        where = f"vary[{i}]"
        for k in v:
            if k not in VARY_KEYS:
                err(f"{where}.{k}", f"unknown key; allowed: {', '.join(sorted(VARY_KEYS))}")
        key = v.get("key")
        if not isinstance(key, str):
            err(f"{where}.key", f"required: a dotted scene key such as 'blocks[slide].density_kg_m3', got {key!r}")
            continue
        try:
            parse_key(key)
        except ValueError as e:
            err(f"{where}.key", str(e))
            continue
        if key in keys:
            err(f"{where}.key", f"{key!r} is varied twice (vary[{keys.index(key)}])")
            continue
        if key == "simulation.duration_s" and dur is not None:
            err(f"{where}.key", "simulation.duration_s is also set by study.duration_s: remove one of them")
            continue
        spec = _values(v, sample, where, err)
        if spec is not None:
            keys.append(key)
            specs.append(spec)
    if errors or scene_path is None:
        raise StudyError(p, errors)
    if gen is not None:
        base_text = json.dumps([gen.name, gen.version, gen_fixed], sort_keys=True).encode()
        base = None
    else:
        base_text = scene_path.read_bytes()
        try:
            base = tomllib.loads(base_text.decode())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise StudyError(p, [("study.scene", f"{scene_path}: not valid TOML: {e}")]) from None
    digest = hashlib.sha1(base_text + json.dumps([dur, keep]).encode()).hexdigest()
    study = Study(path=p.resolve(), scene_path=scene_path, results=res_path, sample=sample, keys=keys, device=device,
                  workers=st.get("workers") or 0, workers_per_gpu=st.get("workers_per_gpu") or 1,
                  generator=gen.name if gen is not None else None)
    for index, combo in enumerate(_combinations(specs, sample, n or 0, seed)):
        params = dict(zip(keys, combo))
        what = ", ".join(f"{k} = {_show(v)}" for k, v in params.items())
        setup = {}
        if gen is not None:  # the maker's parameters build the scene; other (dotted scene) keys are set on it
            gp = {**gen_fixed, **{k: v for k, v in params.items() if k in gen.PARAMS}}
            problems = gen.check(gp)
            for k, m in problems:
                err(f"scenario {index} ({what})", f"{k}: {m}")
            if problems:
                continue
            d, setup = gen.scene(gp)
        else:
            d = copy.deepcopy(base)
        bad = False
        for k, val in params.items():
            if gen is not None and k in gen.PARAMS:
                continue
            try:
                set_key(d, k, val)
            except ValueError as e:
                err(f"scenario {index} ({what})", str(e))
                bad = True
        if bad:
            continue
        d.setdefault("simulation", {})
        d.setdefault("output", {})
        if isinstance(d["simulation"], dict) and dur is not None:
            d["simulation"]["duration_s"] = float(dur)
        if isinstance(d["output"], dict):
            for o in OUTPUT_KEYS:
                if o not in keep:
                    d["output"][o] = ""
            d["output"]["checkpoint_interval_s"] = 0.0  # a scenario is re-run whole; a checkpoint only on a blow-up
        try:
            parse_scene(d, scene_path, scene_path.parent)
        except SceneError as e:
            for k, m in e.errors:
                err(f"scenario {index} ({what})", f"{k}: {m}" if k else m)
            continue
        study.scenarios.append(Scenario(index, params, d, _scenario_id(index, params, digest), setup))
    if errors:
        raise StudyError(p, errors)
    return study


def _show(v) -> str:
    return f"{v:.6g}" if isinstance(v, float) else json.dumps(v) if isinstance(v, (list, dict)) else str(v)


# ------------------------------------------------------------------------------------------ one scenario ---
def scenario_config(study: Study, sc: Scenario) -> dict:
    """The plain (picklable, JSON-able) config of one scenario: what run_scenario needs on any worker."""
    return {"id": sc.id, "index": sc.index, "params": sc.params, "scene": sc.data, "scene_path": str(study.scene_path),
            "out_dir": str((study.results / "scenarios" / sc.id).resolve()), "device": study.device,
            "generator": study.generator, "setup": sc.setup}


def _failed(config: dict, error: str, wall: float = 0.0) -> dict:
    return {"id": config["id"], "index": config["index"], "params": config["params"], "status": "failed", "error": error,
            "metrics": {}, "wall_s": wall}


def run_scenario(config: dict) -> dict:
    """Run one scenario: the scene (config['scene'], a TOML dict) for its duration on config['device'] ('auto':
    the worker's GPU if it was given one, else rockwave.base.device's choice), outputs and hazard.json in
    config['out_dir']. Returns the summary {id, index, params, status 'ok' | 'failed', error, metrics (the hazard
    summary as flat columns), wall_s, steps}; written atomically as out_dir/result.json. Never raises for a
    scenario that fails (bad scene, blow-up, unwritable output): the error is in the summary."""
    if "batch" in config:  # scenarios stepped together (rockwave/app/batch.py): a list of summaries
        return batching.run_batch(config["batch"], run_scenario)
    t0 = time.perf_counter()
    out = Path(config["out_dir"])
    try:

        quiet_warp()

        scene = parse_scene(copy.deepcopy(config["scene"]), config["scene_path"], Path(config["scene_path"]).parent)
        device = config.get("device") or "auto"
        if device == "auto" and os.environ.get("ROCKWAVE_SWEEP_DEVICE"):
            device = os.environ["ROCKWAVE_SWEEP_DEVICE"]  # the local pool gives each worker its GPU
        out.mkdir(parents=True, exist_ok=True)
        sim = Simulation(scene, device=device)
        summary = sim.run(out, progress=False, checkpoint_interval_s=0.0)
        metrics = flat_metrics(summary.get("hazard") or {})
        if config.get("generator"):  # the maker's comparison (e.g. the impulse-wave predictors) joins the row
            metrics.update(GENERATORS[config["generator"]].compare(config["setup"], summary))
            metrics.update({"steps": summary["steps"], "fluid_particles": summary["fluid_particles"]})
        res = {"id": config["id"], "index": config["index"], "params": config["params"], "status": "ok", "error": "",
               "metrics": metrics, "wall_s": time.perf_counter() - t0,
               "steps": summary["steps"], "device": sim.device, "fluid_particles": summary["fluid_particles"]}
    except KeyboardInterrupt:
        raise
    except BaseException as e:  # a failed scenario is a result, not the end of the study
        msg = e.one_line() if isinstance(e, SceneError) else f"{type(e).__name__}: {e}"
        res = _failed(config, msg, time.perf_counter() - t0)
    write_result(out, res)
    return res


def write_result(out: Path, res: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / RESULT_FILE, json.dumps(res, indent=2, default=str))


def read_result(study: Study, sc: Scenario) -> dict | None:
    f = study.results / "scenarios" / sc.id / RESULT_FILE
    try:
        res = json.loads(f.read_text())
    except (OSError, ValueError):
        return None
    return res if res.get("id") == sc.id else None


# ---------------------------------------------------------------------------------------------- progress ---
class StudyProgress:
    """Whole-study progress: done / running / failed / queued and an ETA from the mean wall time of the scenarios
    finished in this session; one line on stderr per event and progress.json in the result folder."""

    def __init__(self, study: Study, total: int, skipped: int, parallel: int, enabled: bool = True, stream=None,
                 write_file: bool = True):
        self.study, self.total, self.skipped, self.parallel = study, total, skipped, max(1, parallel)
        self.write_file = write_file  # not for one array task of many (--only): they would overwrite each other
        self.done = self.failed = 0
        self.walls: list[float] = []
        self.t0 = time.perf_counter()
        self.enabled, self.stream = enabled, stream or sys.stderr
        self.running = 0

    def start(self, running: int) -> None:
        self.running = running
        self.show()

    def finished(self, res: dict, running: int) -> None:
        self.done += 1
        self.failed += res.get("status") != "ok"
        self.walls.append(float(res.get("wall_s") or 0.0))
        self.running = running
        self.show(res)

    def eta_s(self) -> float | None:
        left = self.total - self.skipped - self.done
        if not self.walls:
            return None
        return left * (sum(self.walls) / len(self.walls)) / self.parallel

    def show(self, res: dict | None = None) -> None:
        done = self.skipped + self.done
        queued = self.total - done - self.running
        eta = self.eta_s()
        state = {"total": self.total, "done": done, "failed": self.failed, "running": self.running, "queued": max(queued, 0),
                 "skipped_finished_before": self.skipped, "elapsed_s": time.perf_counter() - self.t0, "eta_s": eta}
        try:

            if self.write_file:
                self.study.results.mkdir(parents=True, exist_ok=True)
                atomic_write_text(self.study.results / "progress.json", json.dumps(state, indent=2))
        except OSError:
            pass
        if not self.enabled:
            return
        last = ""
        if res is not None:
            last = f"; {res['id']} {res['status']}" + (f" ({res['error'][:120]})" if res.get("error") else f" in {res['wall_s']:.1f} s")
        eta_s = "" if eta is None else f", ETA {_fmt(eta)}"
        print(f"sweep: {done}/{self.total} done ({self.failed} failed), {self.running} running, {max(queued, 0)} queued"
              f"{eta_s}{last}", file=self.stream, flush=True)


def _fmt(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s"


# --------------------------------------------------------------------------------------------- executors ---
def _worker_init(slots) -> None:
    """Local pool: each worker takes one device slot (a GPU, or 'cpu') for all its scenarios."""
    dev = slots.get()
    os.environ["ROCKWAVE_SWEEP_DEVICE"] = dev
    if dev == "cpu":
        os.environ.setdefault("OMP_NUM_THREADS", "1")


def local_slots(device: str, workers: int, workers_per_gpu: int) -> list[str]:
    """The device of each local worker: one per GPU (times workers_per_gpu: small scenarios sharing a GPU), or
    ``workers`` CPU slots (default: the CPU count) when there is no GPU or device = 'cpu'."""
    gpus = 0
    if device in ("auto", "cuda") or device.startswith("cuda"):

        init_warp(quiet=True)
        import warp as wp

        gpus = wp.get_cuda_device_count()
    if device.startswith("cuda:"):
        slots = [device] * max(1, workers_per_gpu)
    elif gpus:
        slots = [f"cuda:{g}" for g in range(gpus) for _ in range(max(1, workers_per_gpu))]
    else:
        slots = ["cpu"] * (workers or os.cpu_count() or 1)
    if workers:
        slots = (slots * workers)[:workers]
    return slots


def run_local(configs: list[dict], slots: list[str], on_result, fn=None) -> None:
    """Run the configs in a process pool (spawned workers, one per slot). A worker that dies (killed, out of
    memory, a crash in native code) breaks the pool: the scenarios it held are run again one at a time, each in
    a pool of its own, so the one that kills its worker is found and recorded as failed; the others finish."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    fn = fn or run_scenario
    ctx = mp.get_context("spawn")

    def pool_run(batch: list[dict], n_workers: int, slot_list: list[str]) -> list[dict]:
        q = ctx.Queue()
        for s in slot_list[:n_workers]:
            q.put(s)
        broken = []
        with ProcessPoolExecutor(max_workers=n_workers, mp_context=ctx, initializer=_worker_init, initargs=(q,)) as pool:
            futs = {pool.submit(fn, c): c for c in batch}
            running = len(futs)
            for f in as_completed(futs):
                c = futs[f]
                running -= 1
                try:
                    res = f.result()
                except BrokenProcessPool:
                    broken.append(c)
                    continue
                except Exception as e:  # the call itself failed (unpicklable result ...)
                    res = [_failed(m, f"{type(e).__name__}: {e}") for m in c.get("batch", [c])]
                for r in res if isinstance(res, list) else [res]:
                    on_result(r, min(running, n_workers))
        return broken

    broken = pool_run(configs, max(1, min(len(slots), len(configs))), slots)
    broken = [m for c in broken for m in c.get("batch", [c])]  # a broken batch: its scenarios alone
    for c in broken:  # one at a time: the one whose worker dies is the culprit
        again = pool_run([c], 1, slots)
        if again:
            on_result(_failed(c, "the worker process died (killed, out of memory, or a crash in native code)"), 0)


def _ray_call(config: dict) -> dict:
    return run_scenario(config)


def run_ray(configs: list[dict], address: str | None, on_result, gpus_per_scenario: float = 0.0,
            init_kwargs: dict | None = None) -> None:
    """Run the configs as Ray tasks (num_gpus = gpus_per_scenario each: Ray gives each task its GPU, or a share of
    one, through CUDA_VISIBLE_DEVICES). address: a running cluster ('auto', 'ray://host:10001', ...) or None
    for a local instance (init_kwargs, e.g. num_cpus=2). A task whose worker dies is recorded as failed
    (max_retries = 0: a scenario that kills its worker would kill the next one too). The result folder must
    be on a file system that the workers share (run_scenario writes each result there; the driver writes it
    again from the returned summary)."""
    import ray

    if not ray.is_initialized():
        ray.init(address=address, **(init_kwargs or {}))
    remote = ray.remote(num_cpus=1, num_gpus=gpus_per_scenario, max_retries=0)(_ray_call)
    refs = {remote.remote(c): c for c in configs}
    total_cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
    while refs:
        done, _ = ray.wait(list(refs), num_returns=1)
        for r in done:
            c = refs.pop(r)
            try:
                res = ray.get(r)
            except Exception as e:  # RayTaskError, WorkerCrashedError, ...
                why = f"the Ray task failed: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
                res = [_failed(m, why) for m in c.get("batch", [c])]
            for x in res if isinstance(res, list) else [res]:
                on_result(x, min(len(refs), total_cpus))


# ------------------------------------------------------------------------------------------------ table ----
def study_rows(study: Study) -> list[dict]:
    """One row per scenario (index order): scenario, index, status, error, the varied keys, the hazard metrics.
    Scenarios without a result yet are left out."""
    rows = []
    for sc in study.scenarios:
        res = read_result(study, sc)
        if res is None:
            continue
        row = {"scenario": sc.id, "index": sc.index, "status": res["status"], "error": res.get("error", "")}
        for k in study.keys:
            v = sc.params[k]
            row[k] = json.dumps(v) if isinstance(v, (list, dict)) else v
        row.update(res.get("metrics") or {})
        rows.append(row)
    return rows


def write_table(study: Study, rows: list[dict]) -> dict:
    """study.csv always; study.parquet with pyarrow (the [sweep] extra). Written atomically. Returns the paths."""
    import csv
    import io

    cols: list[str] = []
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r.get(k) is None else repr(r[k]) if isinstance(r.get(k), float) else r.get(k)) for k in cols})
    study.results.mkdir(parents=True, exist_ok=True)
    paths = {"csv": study.results / "study.csv"}
    atomic_write_text(paths["csv"], buf.getvalue())
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        print("sweep: pyarrow is not installed (pip install 'rockwave[sweep]'): study.parquet not written", file=sys.stderr)
        return paths
    table = pa.Table.from_pylist([{k: r.get(k) for k in cols} for r in rows])

    paths["parquet"] = study.results / "study.parquet"
    atomic_write(paths["parquet"], lambda f: pq.write_table(table, f))
    return paths


def write_plots(study: Study, rows: list[dict]) -> list[Path]:
    """max_wave_height.png: the highest crest at each wave gauge against each numeric varied key (one panel per
    key); runup.png: the highest water column top along each run-up line (one line per scenario)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = []
    ok = [r for r in rows if r["status"] == "ok"]
    crest_cols = [c for c in (ok[0] if ok else {}) if c.endswith(".max_crest_m")]
    keys = [k for k in study.keys if ok and all(isinstance(r.get(k), (int, float)) and not isinstance(r.get(k), bool) for r in ok)]
    if ok and crest_cols and keys:
        fig, axes = plt.subplots(1, len(keys), figsize=(4.5 * len(keys), 3.6), squeeze=False)
        for ax, k in zip(axes[0], keys):
            for c in crest_cols:
                pts = sorted((r[k], r[c]) for r in ok if r.get(c) is not None)
                if pts:
                    ax.plot([p[0] for p in pts], [p[1] for p in pts], "o", label=c[: -len(".max_crest_m")], alpha=0.8)
            ax.set_xlabel(k)
            ax.set_ylabel("max crest above still water (m)")
            ax.grid(alpha=0.3)
        axes[0][0].legend(fontsize=7, title="gauge")
        fig.suptitle(f"{study.path.name}: maximum wave crest")
        fig.tight_layout()
        p = study.results / "max_wave_height.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        out.append(p)
    lines = {}
    for sc in study.scenarios:
        hz = study.results / "scenarios" / sc.id / "hazard.json"
        try:
            data = json.loads(hz.read_text())
        except (OSError, ValueError):
            continue
        for name, r in (data.get("runup") or {}).items():
            lines.setdefault(name, []).append((sc, r))
    if lines:
        fig, axes = plt.subplots(1, len(lines), figsize=(6 * len(lines), 3.8), squeeze=False)
        for ax, (name, entries) in zip(axes[0], lines.items()):
            for sc, r in entries:
                x = [c[0] for c in r["columns_m"]]
                y = [v if v is not None else float("nan") for v in r["column_max_m"]]
                label = ", ".join(f"{k.rsplit('.', 1)[-1]}={_show(v)}" for k, v in sc.params.items())
                ax.plot(x, y, "-", lw=1.2, label=label[:60])
            if entries and entries[0][1].get("still_level_m") is not None:
                ax.axhline(entries[0][1]["still_level_m"], color="k", lw=0.8, ls="--", label="still water")
            ax.set_xlabel("position along the shore line (first horizontal coordinate, m)")
            ax.set_ylabel("highest water column top (m)")
            ax.set_title(f"run-up: {name}")
            ax.grid(alpha=0.3)
            if len(entries) <= 12:
                ax.legend(fontsize=6)
        fig.tight_layout()
        p = study.results / "runup.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        out.append(p)
    return out


# ----------------------------------------------------------------------------------- comparison table ----
COMPARISON_COLUMNS = [  # (column, header, format)
    ("index", "#", "{}"), ("F", "F", "{:.2f}"), ("S", "S", "{:.2f}"), ("M", "M", "{:.2f}"), ("alpha_deg", "α °", "{:.0f}"),
    ("front_deg", "front °", "{:.0f}"), ("P", "P", "{:.2f}"), ("layers", "h/dx", "{:.0f}"), ("a_M_pred_m", "a_M pred m", "{:.4f}"), ("a_M_m", "a_M m", "{:.4f}"),
    ("a_M_err", "a_M err", "{:+.1%}"), ("H_M_pred_m", "H_M pred m", "{:.4f}"), ("H_M_m", "H_M m", "{:.4f}"),
    ("H_M_err", "H_M err", "{:+.1%}"), ("x_M_pred_m", "x_M pred m", "{:.2f}"), ("x_M_m", "x_M m", "{:.2f}"),
    ("decay_H_mean_err", "H(x) err", "{:+.1%}"), ("decay_a_mean_err", "a(x) err", "{:+.1%}"), ("F_measured", "F meas.", "{:.2f}"),
    ("energy_to_water_fraction", "E_w/E_s", "{:.1%}"), ("fluid_particles", "particles", "{}"), ("steps", "steps", "{}"),
    ("wall_s", "wall s", "{:.1f}"), ("outside_ranges", "outside data ranges", "{}")]


def comparison_rows(study: Study) -> list[dict]:
    """A generated study's rows with the comparison columns, the scenario's status and its cost (wall_s)."""
    out = []
    for sc in study.scenarios:
        res = read_result(study, sc)
        if res is None:
            continue
        metrics = dict(res.get("metrics") or {})
        try:  # the comparison again from the run's summary: a corrected predictor needs no re-run
            summary = json.loads((study.results / "scenarios" / sc.id / "run.json").read_text())
            metrics.update(GENERATORS[study.generator].compare(sc.setup, summary))
        except (OSError, ValueError, KeyError):
            pass
        r = {"index": sc.index, "scenario": sc.id, "status": res["status"], "error": res.get("error", ""),
             "wall_s": res.get("wall_s"), "device": res.get("device"), **sc.setup, **metrics}
        r = {k: v for k, v in r.items() if "." not in k}  # the hazard's per-gauge columns stay in study.csv
        out.append(r)
    return out


def summarise_study(study: Study, by: str | None = "layers") -> list[dict]:
    """A generated study's mean errors per ``by`` group (rockwave/output/impulse.py summarise)."""
    return summarise(comparison_rows(study), by=by)


def write_comparison(study: Study) -> dict:
    """comparison.csv (every column) and comparison.md (the table of docs/validation.md 'Landslide impulse waves':
    each scenario's error against the predictors, its resolution and cost, then the mean errors per resolution)."""
    import csv
    import io

    rows = comparison_rows(study)
    if not rows:
        return {}
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: "" if r.get(k) is None else r.get(k) for k in cols})
    paths = {"comparison_csv": study.results / "comparison.csv", "comparison_md": study.results / "comparison.md"}
    atomic_write_text(paths["comparison_csv"], buf.getvalue())

    def cell(r, k, f):
        v = r.get(k)
        if v is None or v == "":
            return "–"
        try:
            return f.format(v)
        except (ValueError, TypeError):
            return str(v)

    lines = [f"# {study.path.name}: waves against the impulse-product relations", "",
             "Errors are measured / predicted − 1 (rockwave/output/impulse.py; docs/validation.md 'Landslide impulse waves').",
             "", "| " + " | ".join(h for _, h, _ in COMPARISON_COLUMNS) + " |",
             "|" + "---|" * len(COMPARISON_COLUMNS)]
    for r in rows:
        if r["status"] != "ok":
            lines.append(f"| {r['index']} | failed: {str(r.get('error'))[:100]} |")
            continue
        lines.append("| " + " | ".join(cell(r, k, f) for k, _, f in COMPARISON_COLUMNS) + " |")
    summ = summarise(rows, by="layers")
    if summ:
        lines += ["", "Per resolution (h/dx: particles per water depth): mean signed error, mean |error|, the share "
                  "within ±30%, mean wall time per scenario", "",
                  "| h/dx | scenarios | a_M mean | a_M mean abs | a_M within | H_M mean | H_M mean abs | H_M within | "
                  "x_M mean | H(x) mean | wall s |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        for s in summ:
            lines.append("| " + " | ".join([
                cell(s, "group", "{:.0f}"), str(s["scenarios"]), cell(s, "a_M_mean_err", "{:+.1%}"),
                cell(s, "a_M_mean_abs_err", "{:.1%}"), cell(s, "a_M_within_band", "{:.0%}"), cell(s, "H_M_mean_err", "{:+.1%}"),
                cell(s, "H_M_mean_abs_err", "{:.1%}"), cell(s, "H_M_within_band", "{:.0%}"), cell(s, "x_M_mean_err", "{:+.1%}"),
                cell(s, "decay_H_mean_err", "{:+.1%}"), cell(s, "wall_s_mean", "{:.1f}")]) + " |")
    atomic_write_text(paths["comparison_md"], "\n".join(lines) + "\n")
    profiles = {}  # crest minus trough along the channel, per scenario (hazard.json)
    for sc in study.scenarios:
        try:
            hz = json.loads((study.results / "scenarios" / sc.id / "hazard.json").read_text())
        except (OSError, ValueError):
            continue
        h, x0 = sc.setup.get("h_m"), sc.setup.get("x0_m", 0.0)
        if not h:
            continue
        profiles[sc.index] = [((g["position_m"][0] - x0) / h, (g["max_crest_m"] - g["deepest_trough_m"]) / h)
                              for name, g in hz.get("gauges", {}).items()
                              if name.startswith("x") and g.get("max_crest_m") is not None and g.get("deepest_trough_m") is not None]
    try:
        paths["comparison_png"] = study.results / "comparison.png"
        impulse_chart(rows, profiles, paths["comparison_png"], title=study.path.name)
    except ImportError:  # no matplotlib: the tables are written, the chart is not
        paths.pop("comparison_png")
    return paths


# ----------------------------------------------------------------------------------------------- driver ----
def slurm_script(study: Study, gpus: int = 1, cpus: int = 4, time_limit: str = "04:00:00", batch: int = 1) -> Path:
    """A Slurm job array for sites without Ray: one array task per scenario (``sweep --only INDEX``), or with
    ``batch`` > 1 per batch of that many scenarios (``--only`` each of its indices, ``--batch``), then
    ``sweep --collect`` for the table and plots. Written to RESULTS/sweep.sbatch."""
    res = study.results.resolve()
    if batch > 1:
        groups = batching.batches([scenario_config(study, sc) for sc in study.scenarios], batch)
        lists = " ".join('"' + " ".join(f"--only {c['index']}" for c in g) + '"' for g in groups)
        n = len(groups)
        select = f"TASKS=({lists})\nONLY=${{TASKS[$SLURM_ARRAY_TASK_ID]}}"
        run = f'python -m rockwave sweep {study.path} --out {res} $ONLY --batch {batch} --quiet'
    else:
        n = len(study.scenarios)
        select = ""
        run = f'python -m rockwave sweep {study.path} --out {res} --only "$SLURM_ARRAY_TASK_ID" --quiet'
    text = f"""#!/bin/bash
# Scenario study {study.path.name}: {len(study.scenarios)} scenarios in {n} array tasks (python -m rockwave sweep --slurm).
# Submit:   sbatch {res}/sweep.sbatch
# Then:     python -m rockwave sweep {study.path} --out {res} --collect   (table and plots)
#SBATCH --job-name=rockwave-sweep
#SBATCH --array=0-{n - 1}
#SBATCH --gres=gpu:{gpus}
#SBATCH --cpus-per-task={cpus}
#SBATCH --time={time_limit}
#SBATCH --output={res}/slurm-%A_%a.out
set -euo pipefail
{select}
{run}
"""
    study.results.mkdir(parents=True, exist_ok=True)
    p = study.results / "sweep.sbatch"
    p.write_text(text)
    return p


class GpuSampler:
    """GPU utilisation while a study runs (this machine's GPUs): ``nvidia-smi`` every ``interval`` seconds in a
    thread; ``summary()`` gives the mean and peak utilisation [%] and the peak memory used [MiB] per GPU (None
    without nvidia-smi)."""

    def __init__(self, interval: float = 1.0):
        import shutil
        import threading

        self.interval = interval
        self.rows: list[list[tuple[float, float]]] = []
        self.exe = shutil.which("nvidia-smi")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True) if self.exe else None

    def __enter__(self):
        if self._thread is not None:
            self._thread.start()
        return self

    def __exit__(self, *exc):
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout=5)

    def _run(self) -> None:
        import subprocess

        while not self._stop.is_set():
            try:
                out = subprocess.run([self.exe, "--query-gpu=utilization.gpu,memory.used", "--format=csv,noheader,nounits"],
                                     capture_output=True, text=True, timeout=10).stdout
                self.rows.append([tuple(float(x) for x in line.split(",")) for line in out.strip().splitlines()])
            except (OSError, ValueError, subprocess.SubprocessError):
                pass
            self._stop.wait(self.interval)

    def summary(self) -> dict | None:
        rows = [r for r in self.rows if r and len(r) == len(self.rows[0])]
        if not rows:
            return None
        n = len(rows[0])
        return {"samples": len(rows), "interval_s": self.interval,
                "utilisation_mean_pct": [sum(r[g][0] for r in rows) / len(rows) for g in range(n)],
                "utilisation_max_pct": [max(r[g][0] for r in rows) for g in range(n)],
                "memory_max_mib": [max(r[g][1] for r in rows) for g in range(n)]}


@dataclass
class StudyResult:
    rows: list
    paths: dict
    plots: list
    ran: int
    skipped: int
    failed: int
    wall_s: float


def run_study(study: Study | str | os.PathLike, out: str | os.PathLike | None = None, executor: str = "local",
              workers: int | None = None, ray_address: str | None = None, ray_init: dict | None = None,
              gpus_per_scenario: float | None = None, retry_failed: bool = False, only: list[int] | None = None,
              progress: bool = True, plots: bool = True, fn=None, batch: int = 1) -> StudyResult:
    """Run the scenarios without a result yet (and the failed ones with retry_failed), then write the table and
    plots. executor: 'local' (process pool; ``workers`` slots, default one per GPU or the CPU count), 'ray'
    (``ray_address``; None with ``ray_init`` starts a local instance) or 'inline' (this process, one at a time).
    only: scenario indices to run (a Slurm array task). batch: scenarios stepped together per task
    (rockwave/app/batch.py; 1: one at a time, 0: sized to the device)."""
    if not isinstance(study, Study):
        study = load_study(study, out)
    elif out is not None:
        study.results = Path(out)
    t0 = time.perf_counter()
    todo, skipped = [], 0
    for sc in study.scenarios:
        if only is not None and sc.index not in only:
            continue
        res = read_result(study, sc)
        if res is not None and (res["status"] == "ok" or not retry_failed):
            skipped += 1
            continue
        todo.append(scenario_config(study, sc))
    total = len(study.scenarios) if only is None else len(todo) + skipped
    todo = batch_configs(study, todo, batch)
    if executor == "local":
        slots = local_slots(study.device, workers if workers is not None else study.workers, study.workers_per_gpu)
        parallel = len(slots)
    elif executor == "ray":
        import ray

        if not ray.is_initialized():
            ray.init(address=ray_address, **(ray_init or {}))
        res = ray.cluster_resources()
        gps = gpus_per_scenario or 0.0
        parallel = max(1, int(res.get("GPU", 0) / gps) if gps > 0 else int(res.get("CPU", 1)))
    else:
        parallel = 1
    bar = StudyProgress(study, total, skipped, parallel, enabled=progress, write_file=only is None)
    failed = 0

    def on_result(res: dict, running: int) -> None:
        nonlocal failed
        failed += res["status"] != "ok"
        write_result(Path(study.results / "scenarios" / res["id"]), res)
        bar.finished(res, running)

    sampler = GpuSampler()
    if todo:
        bar.start(min(parallel, len(todo)))
    with sampler:
        _execute(todo, executor, slots if executor == "local" else None, on_result, fn, study, gpus_per_scenario,
                 ray_address, ray_init)
    rows = study_rows(study)
    paths = write_table(study, rows) if only is None else {}
    if only is None and study.generator:
        paths.update(write_comparison(study))
    pics = write_plots(study, rows) if plots and only is None and rows else []
    wall = time.perf_counter() - t0
    if only is None:

        ok_walls = [r.get("wall_s") or 0.0 for r in (read_result(study, s) for s in study.scenarios) if r]
        atomic_write_text(study.results / "study.json", json.dumps({
            "study": str(study.path), "scene": str(study.scene_path), "sample": study.sample, "keys": study.keys,
            "scenarios": len(study.scenarios), "ran_now": len(todo), "skipped": skipped, "failed": sum(r["status"] != "ok" for r in rows),
            "wall_s_this_session": wall, "scenarios_per_hour_this_session": 3600.0 * len(todo) / wall if todo and wall > 0 else None,
            "scenario_wall_s_sum": sum(ok_walls), "executor": executor, "parallel_slots": parallel,
            "gpu": sampler.summary(),
        }, indent=2))
    return StudyResult(rows, paths, pics, len(todo), skipped, failed, wall)


def batch_configs(study: Study, todo: list[dict], size: int) -> list[dict]:
    """The configs packed into batch configs {"batch": [configs]} of one template (rockwave/app/batch.py) of at most
    ``size`` scenarios (0: batching.auto_batch_size of the first scenario's water on the study's device); a batch of
    one stays a plain config."""
    if size == 1 or len(todo) < 2:
        return todo
    kept = [o for o in OUTPUT_KEYS if any((c["scene"].get("output") or {}).get(o) for c in todo)]
    if kept:
        print(f"sweep: study.keep = {kept}: a batch writes run.json and hazard.json only, so the scenarios run one at a time",
              file=sys.stderr)
        return todo
    if size == 0:
        c = todo[0]
        scene = parse_scene(copy.deepcopy(c["scene"]), c["scene_path"], Path(c["scene_path"]).parent)
        dev = "cpu" if study.device == "cpu" or not local_slots(study.device, 0, 1)[0].startswith("cuda") else "cuda"
        size = batching.auto_batch_size(len(seed_particles(scene, "cpu")[0]), dev)
    return [g[0] if len(g) == 1 else {"batch": g, "id": g[0]["id"], "index": g[0]["index"]}
            for g in batching.batches(todo, size)]


def _execute(todo, executor, slots, on_result, fn, study, gpus_per_scenario, ray_address, ray_init) -> None:
    if not todo:
        return
    if executor == "local":
        run_local(todo, slots, on_result, fn)
    elif executor == "ray":
        gps = gpus_per_scenario if gpus_per_scenario is not None else 0.0
        run_ray(todo, ray_address, on_result, gps, ray_init)
    elif executor == "inline":
        for c in todo:
            res = (fn or run_scenario)(c)
            for r in res if isinstance(res, list) else [res]:
                on_result(r, 0)
    else:
        raise ValueError(f"executor {executor!r}: expected 'local', 'ray' or 'inline'")


def shipped_studies_dir() -> Path:
    """The studies shipped with rockwave: ``rockwave.scenes``/studies (the checkout's scenes/studies/)."""
    try:
        from importlib.resources import files

        d = files("rockwave.scenes") / "studies"
        if d.is_dir():
            return Path(str(d))
    except (ImportError, OSError, TypeError, ModuleNotFoundError):
        pass
    return Path(__file__).resolve().parents[2] / "scenes" / "studies"


def resolve_study(name: str, out: str | None) -> tuple[Path, str | None]:
    """A study file, or the name of a shipped study (``impulse_2d`` -> scenes/studies/impulse_2d.toml, its results
    in ./runs/<name> unless ``out`` says otherwise: never inside the installed package)."""
    p = Path(name)
    if p.is_file() or p.suffix == ".toml" or os.sep in name:
        return p, out
    shipped = shipped_studies_dir() / f"{name}.toml"
    if shipped.is_file():
        return shipped, out if out is not None else str(Path("runs") / name)
    return p, out


def cli(args) -> int:
    """``python -m rockwave sweep`` (rockwave/app/cli.py). Exit 0: every scenario ok; 1: some failed; 2: a bad study."""
    try:
        path, out = resolve_study(args.study, args.out)
        study = load_study(path, out)
    except StudyError as e:
        print(str(e), file=sys.stderr)
        return 2
    if args.list:
        for sc in study.scenarios:
            res = read_result(study, sc)
            state = res["status"] if res else "to run"
            print(f"{sc.id}  {state:7s}  " + ", ".join(f"{k} = {_show(v)}" for k, v in sc.params.items()))
        print(f"{study.path}: ok, {len(study.scenarios)} scenarios; results in {study.results}")
        return 0
    if args.slurm:
        print(slurm_script(study, batch=max(1, getattr(args, 'batch', 1))))
        return 0
    if args.collect:
        rows = study_rows(study)
        paths = write_table(study, rows)
        if study.generator:
            write_comparison(study)
        write_plots(study, rows)
        print(f"{len(rows)}/{len(study.scenarios)} scenarios have results; table {paths['csv']}")
        return 0
    executor = "local"
    address = None
    init = None
    if args.ray is not None:
        executor = "ray"
        address = None if args.ray == "local" else args.ray
        init = {"num_cpus": args.workers} if args.ray == "local" and args.workers else None
    elif args.only:
        executor = "inline"  # one array task: this process runs its scenario(s)
    gps = args.gpus_per_scenario
    if executor == "ray" and gps is None:
        import ray

        if not ray.is_initialized():
            ray.init(address=address, **(init or {}))
        gps = 1.0 if ray.cluster_resources().get("GPU", 0) > 0 else 0.0
    try:
        res = run_study(study, executor=executor, workers=args.workers, ray_address=address, ray_init=init,
                        gpus_per_scenario=gps, retry_failed=args.retry_failed, only=args.only, progress=not args.quiet,
                        batch=getattr(args, "batch", 1))
    except KeyboardInterrupt:
        print(f"interrupted: finished scenarios are kept in {study.results}/scenarios; run again to finish the rest",
              file=sys.stderr)
        return 130
    where = f"; table {res.paths['csv']}" if res.paths else ""
    print(f"sweep: {res.ran} run, {res.skipped} finished before, {res.failed} failed, {res.wall_s:.1f} s{where}")
    return 1 if res.failed or any(r["status"] != "ok" for r in res.rows) else 0
