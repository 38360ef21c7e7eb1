"""Scenario studies in batches: many small scenarios stepped together on one device (rockwave/sim/batch.py).

:func:`run_batch` is the batch counterpart of rockwave/app/sweep.py run_scenario: a list of scenario configs in,
one summary per scenario out, each written as ``result.json`` (and ``hazard.json``, ``run.json``) in the
scenario's own folder, exactly where and as a solo run writes them. The scenarios are grouped by template
(rockwave/sim/batch.py template_of: scenarios that differ in a shared setting go to separate batches) and each
group runs as one BatchSimulation, frame by frame as the solo run loop does (rockwave/app/run.py), with the
per-scenario guard after every frame. A scenario that fails in the batch (a blow-up, a particle leaving its tile)
is taken out, the batch is run again from the start without it (so the others' results are never those of a
batch with a blown-up member: the shared step would have followed it), and the failed one then runs alone
(run_scenario), whose result, ok or failed, is its result. A batch that cannot be built (a scene error of one of
its scenarios) runs its scenarios alone. Timings are not in the results' metrics; ``wall_s`` of a batched scenario
is its share of the batch's wall time.

:func:`batches` packs configs into batches of at most ``size`` scenarios of one template (``size`` 0: sized to the
device by a particle budget, :func:`auto_batch_size`).
"""

from __future__ import annotations

import copy
import json
import os
import time
from pathlib import Path

from rockwave.base.device import quiet_warp, resolve_device
from rockwave.base.files import atomic_write_text
from rockwave.output.batch import BatchHazard
from rockwave.output.hazard import flat_metrics
from rockwave.scene.format import SceneError, parse_scene
from rockwave.sim.batch import BatchSimulation, ScenarioFailed, template_of

PARTICLES_PER_BATCH_GPU = 1_000_000  # fluid particles a GPU batch aims at (auto size): ~300 slide_2d scenarios
PARTICLES_PER_BATCH_CPU = 20_000  # on the CPU a batch saves little (no launches to amortise): small batches


def auto_batch_size(n_fluid: int, device: str) -> int:
    """Scenarios per batch from a particle budget: PARTICLES_PER_BATCH_GPU fluid particles on a GPU (the step of
    1 M particles fills an H100/H200: docs/hazard_and_sweeps.md), PARTICLES_PER_BATCH_CPU on the CPU."""
    budget = PARTICLES_PER_BATCH_CPU if device == "cpu" else PARTICLES_PER_BATCH_GPU
    return max(1, min(1024, budget // max(n_fluid, 1)))


def template_key(config: dict) -> str:
    """A hashable form of a config's template (configs with equal keys may share a batch)."""
    scene = parse_scene(copy.deepcopy(config["scene"]), config["scene_path"], Path(config["scene_path"]).parent)
    return json.dumps(template_of(scene), sort_keys=True, default=str)


def batches(configs: list[dict], size: int) -> list[list[dict]]:
    """Configs packed into batches of at most ``size`` (>= 1) of one template, in index order within each."""
    groups: dict[str, list[dict]] = {}
    for c in configs:
        try:
            key = template_key(c)
        except SceneError:
            key = f"bad:{c['id']}"  # run_scenario reports it
        groups.setdefault(key, []).append(c)
    out = []
    for g in groups.values():
        out += [g[i:i + size] for i in range(0, len(g), size)]
    return out


def _device(config: dict) -> str:
    device = config.get("device") or "auto"
    if device == "auto" and os.environ.get("ROCKWAVE_SWEEP_DEVICE"):
        device = os.environ["ROCKWAVE_SWEEP_DEVICE"]
    return device


def _failed(config: dict, error: str) -> dict:
    return {"id": config["id"], "index": config["index"], "params": config["params"], "status": "failed", "error": error,
            "metrics": {}, "wall_s": 0.0}


def write_result(out: Path, res: dict) -> None:
    """result.json, atomically (rockwave/app/sweep.py reads it)."""
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "result.json", json.dumps(res, indent=2, default=str))


def run_batch(configs: list[dict], solo, steps: str = "scenario") -> list[dict]:
    """Run scenario configs (rockwave/app/sweep.py scenario_config) as batches of one template; returns their
    summaries (in the order given), each written as result.json in its out_dir. ``solo``: the one-scenario entry
    point (rockwave/app/sweep.py run_scenario) for the scenarios that fail in a batch. ``steps``: "scenario" (each
    scenario its own step and clock, the default) or "shared" (rockwave/sim/batch.py). Never raises for a scenario
    that fails."""
    quiet_warp()
    results: dict[str, dict] = {}
    groups: dict[str, list] = {}
    for c in configs:
        try:
            scene = parse_scene(copy.deepcopy(c["scene"]), c["scene_path"], Path(c["scene_path"]).parent)
        except SceneError as e:
            results[c["id"]] = res = _failed(c, e.one_line())
            write_result(Path(c["out_dir"]), res)
            continue
        groups.setdefault(json.dumps(template_of(scene), sort_keys=True, default=str), []).append((c, scene))
    for members in groups.values():
        alone = []
        live = list(members)
        while live:
            try:
                done = _run_one_batch(live, steps)
            except ScenarioFailed as e:  # run again without them; they run alone below
                alone += [live[k][0] for k in sorted(e.failures)]
                live = [m for k, m in enumerate(live) if k not in e.failures]
                continue
            except SceneError:  # a batch that cannot be built: each alone (its own error, if any, is its result)
                alone += [c for c, _ in live]
                break
            for res in done:
                write_result(Path(next(c["out_dir"] for c, _ in live if c["id"] == res["id"])), res)
                results[res["id"]] = res
            break
        for c in alone:
            results[c["id"]] = solo(c)
    return [results[c["id"]] for c in configs]


def _run_one_batch(members: list, steps: str = "scenario") -> list[dict]:
    """One BatchSimulation of (config, scene) pairs, frame by frame to the end; the summaries (not yet written)."""
    t0 = time.perf_counter()
    configs, scenes = [m[0] for m in members], [m[1] for m in members]
    device = resolve_device(_device(configs[0]))
    sim = BatchSimulation(scenes, device=device, steps=steps)
    hz = BatchHazard(sim)
    scene = scenes[0]
    duration = float(scene.simulation.duration_s)
    frame_dt = 1.0 / float(scene.output.frame_rate_hz)
    n_frames = int(duration / frame_dt + 1e-9)
    outside = [0] * len(scenes)
    for f in range(1, n_frames + 1):
        sim.advance(f * frame_dt - sim.time, hz.after_step)
        outside = sim.check()
    rest = duration - sim.time
    if rest > 1e-9:
        sim.advance(rest, hz.after_step)
        outside = sim.check()
    summaries = hz.results()
    wall = time.perf_counter() - t0
    out = []
    own = sim.own
    for k, (c, s, h) in enumerate(zip(configs, scenes, summaries)):
        a, b = sim.tiles[k].fluid
        if own is not None:  # its own clock (the default: rockwave/sim/batch.py)
            steps, limiting, limited = int(own.steps[k]), own.limiting[k], dict(own.steps_limited_by[k])
            substeps = int(own.substeps[k]) if own.multirate[k] else None
        else:
            steps, limiting, limited = sim.steps, sim.clock.limiting, dict(sim.clock.steps_limited_by)
            substeps = sim.clock.substeps if sim.clock.block_substep is not None else None
        run = {"scene": str(Path(c["scene_path"]).resolve()), "device": sim.device, "fluid_particles": b - a,
               "removed_inside_blocks": sim.removed_inside[k], "simulated_s": float(sim.times[k]), "steps": steps,
               "step_limited_by": limiting, "steps_limited_by": limited, "block_substeps": substeps,
               "batch_steps": sim.step_mode, "batch_launches": sim.steps,
               "particles_outside_domain": outside[k], "wall_s_batch": wall,
               "batch": {"scenarios": len(scenes), "position": k, "tile_offset_m": sim.tiles[k].offset.tolist(),
                         "gap_m": sim.gap, "fluid_particles": sim.n_fluid},
               "hazard": h}
        d = Path(c["out_dir"])
        d.mkdir(parents=True, exist_ok=True)
        atomic_write_text(d / "hazard.json", json.dumps(h, indent=2))
        atomic_write_text(d / "run.json", json.dumps(run, indent=2, default=str))
        out.append({"id": c["id"], "index": c["index"], "params": c["params"], "status": "ok", "error": "",
                    "metrics": flat_metrics(h), "wall_s": wall / len(scenes), "steps": steps, "device": sim.device,
                    "fluid_particles": b - a, "batch_size": len(scenes)})
    return out
