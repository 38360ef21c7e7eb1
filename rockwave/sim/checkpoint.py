"""Checkpoints and resume: the whole state of a run in one file, written atomically.

A checkpoint is ``<out>/checkpoint.npz`` (numpy ``.npz``, uncompressed): arrays named
``<group>/<field>`` and one ``meta`` entry (UTF-8 JSON) with the format version, the frame it was
taken after, the clock, the scene (path, SHA-256, particle and block counts) and the state of every
output writer (USD chunks written and the open chunk saved beside them, rows of the CSVs, the
ParaView series). Checkpoints are always taken at a frame boundary, after the frame's outputs are
written, so a resumed run starts at the next frame with outputs that match the state.

What is saved is collected from *providers*, one per state group:

- ``clock``: the clock's time, steps, dt and adaptive target (rockwave/sim/clock.py);
- ``fluid``: every ``wp.array`` field of the :class:`rockwave.sph.fluid.FluidState` and what the fluid
  solver keeps between steps (``checkpoint_arrays``: the list-build positions, from which a restore
  rebuilds the same neighbour lists; Ghost SPH: its ghosts);
- ``blocks``: the :class:`rockwave.dda.blocks.BlockState` arrays, its time, the contact-history hash
  table (occupied slots only) and the block solver's buffer capacities (they fix the order of the
  contact pairs and with it the float sums, so a resumed CPU run is bit-identical);
- anything registered with :func:`register`: a state object added later (ghost particles, the
  coupling) makes its arrays travel with one call::

      from rockwave.sim import checkpoint
      checkpoint.register(sim, "ghost", lambda: sim.ghost_state)   # every wp.array attribute

  or with an object that has ``capture()``, ``pack(captured) -> (arrays, meta)`` and
  ``restore(arrays, meta)`` (see :class:`ArrayGroup`).

During a run the state is captured after every frame (device-side copies with ``wp.clone``), so
when the blow-up guard stops a run the checkpoint holds the last good frame.
"""

from __future__ import annotations

import csv
import io
import json
import os
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import warp as wp

from rockwave.base.files import atomic_write, file_sha256

# 3: block centroids carry their float32 compensation (blocks/x_lo, blocks/world_verts_arm); 4: no
# blocks/world_verts (the world vertices are x + arm, not stored) and the narrow phase's reference as a pose
# (blocks/q_ref, x_lo_ref, strain_ref), not as vertices (blocks/wv_ref); 5: block orientations carry their
# float32 compensation too (blocks/q_lo, issue 36); the block solver's pair list (blocks/pairs/*) and the
# held-contact decision of the multi-rate stepping (its meta "hold"), so a run with held contacts resumes bit for
# bit; the clock's counters of the whole run (steps_limited_by, block_steps); the hazard monitor's statistics
# (group "hazard", rockwave/output/hazard.py)
FORMAT_VERSION = 5
READABLE_FORMATS = (2, 3, 4, 5)  # 2: read with zero compensation (the centroids as saved); 2, 3: world_verts dropped;
# 2-4: q_lo = 0 (the orientations as saved) and no pair list (the first step after the resume runs its own broad
# phase and hold check: not bit for bit)
FILE_NAME = "checkpoint.npz"


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used for this scene or output folder (missing, other scene, torn outputs)."""


# --------------------------------------------------------------------------------------------
# atomic files
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# providers
# --------------------------------------------------------------------------------------------


def _wp_arrays(obj, fields=None) -> dict[str, wp.array]:
    if obj is None:
        return {}
    if fields is not None:
        return {n: getattr(obj, n) for n in fields}
    return {k: v for k, v in vars(obj).items() if isinstance(v, wp.array)}


def _assign(obj, name: str, arr: wp.array, a: np.ndarray) -> None:
    """Copy host data into a device array, reallocating it when the length changed."""
    if arr.shape[0] == a.shape[0]:
        try:
            arr.assign(a)
            return
        except (ValueError, RuntimeError, TypeError):
            pass
    setattr(obj, name, wp.array(a, dtype=arr.dtype, device=arr.device))


class ArrayGroup:
    """Every ``wp.array`` attribute (or the named ``fields``) of the object ``get()`` returns.
    ``get`` is called each time, so a state object that is replaced (e.g. after particles are
    removed) is still found. Arrays whose length changed are reallocated on restore."""

    def __init__(self, get: Callable[[], Any], fields: list[str] | None = None):
        self.get = get
        self.fields = fields

    def capture(self):
        return {n: wp.clone(a) for n, a in _wp_arrays(self.get(), self.fields).items()}

    def pack(self, captured) -> tuple[dict, dict]:
        return {n: a.numpy() for n, a in captured.items()}, {}

    def restore(self, arrays: dict, meta: dict) -> None:
        obj = self.get()
        cur = _wp_arrays(obj, self.fields)
        missing = set(cur) - set(arrays)
        if missing:
            raise CheckpointError(f"the checkpoint lacks {sorted(missing)}")
        for n, a in arrays.items():
            if n in cur:
                _assign(obj, n, cur[n], a)


class ClockProvider:
    """The clock (rockwave/sim/clock.py): time, steps, dt, the adaptive target."""

    def __init__(self, sim):
        self.sim = sim

    def capture(self):
        return self.sim.clock.capture()

    def pack(self, captured):
        return {}, dict(captured)

    def restore(self, arrays, meta):
        self.sim.clock.restore(meta)


class FluidProvider:
    """The FluidState arrays and what the fluid solver keeps between steps (its checkpoint_arrays: the
    list-build positions; a ghost solver also its ghosts)."""

    def __init__(self, sim):
        self.sim = sim

    def capture(self):
        sim = self.sim
        state = {n: wp.clone(a) for n, a in _wp_arrays(sim.state).items()}
        solver = {n: wp.clone(a) for n, a in sim.fluid_solver.checkpoint_arrays().items()}
        return state, solver, sim.fluid_solver.checkpoint_meta()

    def pack(self, captured):
        state, solver, meta = captured
        out = {n: a.numpy() for n, a in state.items()}
        out.update({f"solver/{n}": a.numpy() for n, a in solver.items()})
        return out, dict(meta)

    def restore(self, arrays, meta):
        sim = self.sim
        plain = {n: a for n, a in arrays.items() if not n.startswith("solver/")}
        ArrayGroup(lambda: sim.state).restore(plain, {})
        solver = {n[len("solver/"):]: a for n, a in arrays.items() if n.startswith("solver/")}
        sim.fluid_solver.restore_checkpoint(sim.state, solver, meta)


_SLOT_FIELDS = ("keys", "normal", "gapb", "nc", "pstart")  # per pair slot; the other table fields are per point
# the broad phase's pair list (BlockSolver.pair_list: the pairs, their history slots and gaps, the screened lists) and
# the boxes it was built in (lo_bp, hi_bp: a kept list is rebuilt once a block leaves them)
_PAIR_FIELDS = ("pairs", "pair_gap", "pair_slot", "pair_oslot", "active", "active_big")


def _hold_decision(sim) -> list | None:
    """The multi-rate stepping's last hold-check verdicts (rockwave/sim/stepping.py), None before the first."""
    bs = getattr(sim, "block_stepping", None)
    if bs is None or bs.pairs_hold is None:
        return None
    return [bool(bs.pairs_hold), bool(bs.contacts_hold)]


class BlockProvider:
    """BlockState arrays + time, the contact history (tables[0], occupied slots), solver capacities, and what the
    next step reads from the last one outside the BlockState: the pair list of the last broad phase (a kept list
    serves later steps; the hold check of the multi-rate stepping reads its pairs, gaps and slots) and the held-
    contact decision of the multi-rate stepping (rockwave/sim/stepping.py BlockSubstepping.pairs_hold, contacts_hold: taken every
    dt_update_interval steps and used until the next check; a resume between two checks must use the same)."""

    def __init__(self, sim):
        self.sim = sim

    def capture(self):
        sim = self.sim
        st, sol = sim.block_state, sim.block_solver
        arrays = {n: wp.clone(a) for n, a in _wp_arrays(st).items()}
        table = {k: wp.clone(a) for k, a in st.tables[0].items()}
        pairs = {n: wp.clone(getattr(sol, n)) for n in _PAIR_FIELDS + ("counters", "lo_bp", "hi_bp")}
        meta = {"time": st.time, "table_cap": st.table_cap, "point_cap": st.point_cap, "entry_cap": sol.entry_cap,
                "large_cap": int(sol.large_list.shape[0]), "pair_cap": sol.pair_cap,
                "pair_count": int(sol._pair_count), "narrow_phases": int(sol.narrow_phases),
                "hold": _hold_decision(sim)}
        return arrays, table, pairs, meta

    def pack(self, captured):
        arrays, table, pairs, meta = captured
        out = {n: a.numpy() for n, a in arrays.items()}
        counters = pairs["counters"].numpy()
        live = min(int(counters[0]), int(meta["pair_cap"]))  # the pairs the last broad phase wrote
        out["pairs/counters"] = counters
        for n in ("lo_bp", "hi_bp"):
            out[f"pairs/{n}"] = pairs[n].numpy()
        for n in _PAIR_FIELDS:
            out[f"pairs/{n}"] = pairs[n].numpy()[:live]
        keys = table["keys"].numpy()
        occ = np.nonzero(keys >= 0)[0]
        used = int(table["pcount"].numpy()[0])
        out["table/slots"] = occ.astype(np.int64)
        for k, a in table.items():
            h = a.numpy()
            if k == "pcount":
                out[f"table/{k}"] = h
            elif k in _SLOT_FIELDS:  # per pair slot: the occupied ones
                out[f"table/{k}"] = h[occ]
            else:  # per contact point: the pool entries taken
                out[f"table/{k}"] = h[:used]
        return out, dict(meta)

    def restore(self, arrays, meta):
        sim = self.sim
        st, sol = sim.block_state, sim.block_solver
        if sol.entry_cap != meta["entry_cap"]:
            sol._alloc_entries(int(meta["entry_cap"]))
        if sol.large_list.shape[0] != meta["large_cap"]:
            sol._alloc_large(int(meta["large_cap"]))
        if sol.pair_cap != meta["pair_cap"]:
            sol._alloc_pairs(int(meta["pair_cap"]))
        cap = int(meta["table_cap"])
        st.tables = [None, None]
        st.alloc_tables(cap, int(meta["point_cap"]))
        t = st.tables[0]
        slots = arrays["table/slots"]
        for k, a in t.items():
            h = a.numpy()
            saved = arrays[f"table/{k}"]
            if k == "pcount":
                h[:] = saved
            elif k in _SLOT_FIELDS:
                h[slots] = saved
            else:
                h[: saved.shape[0]] = saved
            a.assign(h)
        plain = {n: a for n, a in arrays.items() if not n.startswith(("table/", "pairs/"))}
        ArrayGroup(lambda: st).restore(plain, {})
        st.time = float(meta["time"])
        if "pairs/counters" in arrays:  # format 5: the pair list and the held-contact decision
            for n in ("counters", "lo_bp", "hi_bp") + _PAIR_FIELDS:
                a, saved = getattr(sol, n), arrays[f"pairs/{n}"]
                h = a.numpy()
                h[: saved.shape[0]] = saved
                a.assign(h)
            sol._pair_count = int(meta["pair_count"])
            sol.narrow_phases = max(sol.narrow_phases, int(meta["narrow_phases"]))  # (hold_checks: after a narrow phase)
            if meta.get("hold") is not None and getattr(sim, "block_stepping", None) is not None:
                sim.block_stepping.pairs_hold, sim.block_stepping.contacts_hold = (bool(x) for x in meta["hold"])


# groups a checkpoint written before they were saved may lack (the caller handles their absence: the run loop
# restarts the hazard statistics at the resumed time)
OPTIONAL_GROUPS = ("hazard",)


def register(sim, name: str, provider) -> None:
    """Add a state group to ``sim``'s checkpoints: ``provider`` is a callable returning the state
    object (all its ``wp.array`` attributes are saved) or a provider object (capture/pack/restore)."""
    if callable(provider) and not hasattr(provider, "capture"):
        provider = ArrayGroup(provider)
    sim.__dict__.setdefault("checkpoint_providers", {})[name] = provider


def providers(sim) -> dict:
    out: dict[str, Any] = {"clock": ClockProvider(sim)}
    if getattr(sim, "fluid", None) is not None:
        out["fluid"] = FluidProvider(sim)
    if getattr(sim, "blocks", None) is not None:
        out["blocks"] = BlockProvider(sim)
    out.update(getattr(sim, "checkpoint_providers", {}))
    return out


# --------------------------------------------------------------------------------------------
# scene identity
# --------------------------------------------------------------------------------------------


def scene_identity(sim) -> dict:
    s = sim.scene
    sha = None
    if s.path != "<scene>" and Path(s.path).is_file():
        sha = file_sha256(Path(s.path))
    return {"path": str(s.path), "sha256": sha, "dimension": s.dim,
            "n_fluid": sim.fluid.n_fluid if sim.fluid is not None else 0,
            "n_boundary": sim.fluid.n_boundary if sim.fluid is not None else 0,
            "n_blocks": sim.blocks.num_blocks if sim.blocks is not None else 0,
            "time_step": {k: s.simulation.get(k) for k in ("time_step", "cfl_number", "dt_s", "block_dt_safety", "dt_update_interval")},
            "frame_rate_hz": s.output.frame_rate_hz, "usd": s.output.usd,
            "raw": json.loads(json.dumps(s.raw, default=str)) if isinstance(s.raw, dict) else None}


# scene keys a resumed run may change (the step settings, e.g. a smaller cfl_number after a blow-up; the run's length,
# device and checkpoint interval); any other change would continue another scene's state
RESUMABLE_CHANGES = ("simulation.duration_s", "simulation.cfl_number", "simulation.dt_s", "simulation.block_dt_safety",
                     "simulation.dt_update_interval", "simulation.time_step", "simulation.device",
                     "output.checkpoint_interval_s")


def scene_changes(old, new, prefix: str = "") -> list[tuple[str, object, object]]:
    """(key path, before, now) of every value that differs between two raw scene dicts."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new), key=str):
            out += scene_changes(old.get(k), new.get(k), f"{prefix}.{k}" if prefix else str(k))
        return out
    return [] if old == new else [(prefix, old, new)]


# --------------------------------------------------------------------------------------------
# reading and writing
# --------------------------------------------------------------------------------------------


def write_file(path: Path, arrays: dict[str, np.ndarray], meta: dict) -> None:
    payload = dict(arrays)
    payload["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    atomic_write(path, lambda f: np.savez(f, **payload))


def read_file(path: str | os.PathLike) -> tuple[dict, dict]:
    """(arrays, meta) of a checkpoint file."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint to resume from: {path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(arrays.pop("meta").tobytes().decode())
    except (OSError, ValueError, KeyError) as e:
        raise CheckpointError(f"{path}: not a readable checkpoint ({e})") from None
    if meta.get("format") not in READABLE_FORMATS:
        raise CheckpointError(f"{path}: checkpoint format {meta.get('format')!r}, this rockwave reads "
                              f"{', '.join(map(str, READABLE_FORMATS))}")
    return arrays, meta


def capture(sim) -> dict:
    """Device-side copy of every provider's state (cheap; no host transfer; the simulation is untouched)."""
    return {name: p.capture() for name, p in providers(sim).items()}


def pack(sim, captured: dict) -> tuple[dict, dict]:
    arrays, metas = {}, {}
    provs = providers(sim)
    for name, cap in captured.items():
        a, m = provs[name].pack(cap)
        arrays.update({f"{name}/{k}": v for k, v in a.items()})
        metas[name] = m
    return arrays, metas


def restore(sim, arrays: dict, meta: dict) -> None:
    """Load a checkpoint's state into ``sim`` (built from the same scene)."""
    ident, now = meta["scene"], scene_identity(sim)
    for k in ("dimension", "n_fluid", "n_boundary", "n_blocks"):
        if ident[k] != now[k]:
            raise CheckpointError(f"the checkpoint was taken for another scene ({k} = {ident[k]}, this scene gives {now[k]})")
    if ident.get("raw") is not None and now.get("raw") is not None:
        changes = scene_changes(ident["raw"], now["raw"])
        bad = [c for c in changes if c[0] not in RESUMABLE_CHANGES]
        if bad:
            what = "; ".join(f"{k}: {a!r} -> {b!r}" for k, a, b in bad[:8]) + (" ..." if len(bad) > 8 else "")
            raise CheckpointError(f"the scene changed since the checkpoint ({what}); a resumed run continues the "
                                  f"checkpointed state, so only {', '.join(RESUMABLE_CHANGES)} may change: restore the "
                                  f"scene or start a fresh run (without --resume)")
        if changes:
            import sys

            print("resuming with changed settings: " + "; ".join(f"{k}: {a!r} -> {b!r}" for k, a, b in changes),
                  file=sys.stderr)
    if "blocks/v" in arrays:  # written before issue 36's v_step: a kinematic block's step velocity starts as its v
        arrays = dict(arrays)
        arrays.setdefault("blocks/v_step", arrays["blocks/v"])
    if meta.get("format") in (2, 3, 4) and "blocks/q" in arrays:
        arrays = dict(arrays)  # before the orientations' compensation: q as saved, q_lo = 0
        arrays.setdefault("blocks/q_lo", np.zeros_like(arrays["blocks/q"]))
    if meta.get("format") in (2, 3) and "blocks/world_verts" in arrays:
        arrays = dict(arrays)
        wv = arrays.pop("blocks/world_verts")  # format 4 forms x + arm where needed
        # format 4 keeps the last narrow phase's pose, not its vertices (wv_ref): restored as "no reference"
        # (pose_motion then certifies no pair separated for one step; the run goes on, not bit for bit)
        arrays.pop("blocks/wv_ref", None)
        st = sim.block_state
        for k in ("x_ref", "q_ref", "x_lo_ref", "strain_ref"):
            a = getattr(st, k)
            arrays[f"blocks/{k}"] = np.zeros((a.shape[0],) + tuple(a.dtype._shape_), np.float32)
        if meta.get("format") == 2:
            # before the compensated block positions (issue 20): the centroids as saved, the arms from the
            # saved world vertices (each step recomputes both from the pose before use)
            arrays.setdefault("blocks/x_lo", np.zeros_like(arrays["blocks/x"]))
            arm = wv - arrays["blocks/x"][sim.blocks.vert_block.numpy()]
            arrays.setdefault("blocks/world_verts_arm", arm.astype(np.float32))
    if "blocks/q" in arrays and "blocks/q_lo_ref" not in arrays:
        # written before the vertex arms' float64 parts (issue 36): arm_lo is formed again at the next step's
        # block_world_vertices; q_lo_ref = 0 leaves pose_motion's bound that reference's q_lo (~1e-7 of a vertex's
        # arm) wider, which certifies nothing wrongly
        arrays = dict(arrays)
        arrays["blocks/q_lo_ref"] = np.zeros_like(arrays["blocks/q"])
        if "blocks/world_verts_arm" in arrays:
            arrays.setdefault("blocks/world_verts_arm_lo", np.zeros_like(arrays["blocks/world_verts_arm"]))
    provs = providers(sim)
    for name in meta["groups"]:
        if name not in provs:
            raise CheckpointError(f"the checkpoint holds state group {name!r} that this simulation does not have")
        pre = f"{name}/"
        provs[name].restore({k[len(pre):]: v for k, v in arrays.items() if k.startswith(pre)}, meta["groups"][name])
    for name in provs:
        if name not in meta["groups"] and name not in OPTIONAL_GROUPS:
            raise CheckpointError(f"the checkpoint lacks state group {name!r}")
    if ident["time_step"] != now["time_step"]:
        # the scene's step settings changed (e.g. a smaller cfl_number after a blow-up): use them now
        sim.clock.target = sim.scene.simulation.dt_s if sim.fixed else sim.clock.adaptive()


# --------------------------------------------------------------------------------------------
# CSV logs
# --------------------------------------------------------------------------------------------


def csv_state(path: Path | None, rows: list) -> dict | None:
    if path is None or not path.exists():
        return None
    return {"file": path.name, "rows": len(rows), "bytes": path.stat().st_size, "sha256": file_sha256(path)}


def csv_restore(path: Path | None, state: dict | None, header: list[str]) -> list[list[str]]:
    """The rows a CSV log held at the checkpoint (as strings, rewritten unchanged by the writer)."""
    if state is None or path is None:
        return []
    if not path.is_file():
        raise CheckpointError(f"cannot resume: {path} is missing")
    if path.stat().st_size < state["bytes"] or file_sha256(path, state["bytes"]) != state["sha256"]:
        raise CheckpointError(f"cannot resume: {path} does not start with what the checkpoint recorded (was it edited?)")
    with open(path, "rb") as f:
        text = f.read(state["bytes"]).decode()
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or rows[0] != header:
        raise CheckpointError(f"cannot resume: {path} has columns {rows[0] if rows else []}, the scene gives {header}")
    body = rows[1:]
    if len(body) != state["rows"]:
        raise CheckpointError(f"cannot resume: {path} holds {len(body)} rows, the checkpoint recorded {state['rows']}")
    return body


# --------------------------------------------------------------------------------------------
# the checkpointer of a run
# --------------------------------------------------------------------------------------------


class RunCheckpointer:
    """Captures the state after every frame and writes ``checkpoint.npz`` after the first computed frame,
    then every ``interval_s`` seconds of wall-clock time (0: only on a blow-up, Ctrl-C or at the end when asked)."""

    def __init__(self, sim, out: Path, interval_s: float, t0: float, outputs: Callable[[], dict]):
        self.sim = sim
        self.out = Path(out)
        self.path = self.out / FILE_NAME
        self.interval = float(interval_s)
        self.t0 = t0
        self.outputs = outputs  # -> {"usd": recorder|None, "csv": {name: recorder|None}, "vtk": recorder|None, "escaped": int}
        self.snapshot = None
        self.frame = -1
        self.next_due = time.monotonic() + self.interval
        self.written_frame = None

    def frame_done(self, frame: int) -> None:
        self.snapshot = capture(self.sim)
        self.frame = frame
        # the first computed frame is checkpointed at once (a run killed early can be resumed), then by wall time
        first = self.written_frame is None and frame >= 1
        if self.interval > 0 and (first or time.monotonic() >= self.next_due):
            self.write()

    def write(self, reason: str = "interval") -> Path | None:
        """Write the last captured frame; returns the path (None before the first frame)."""
        if self.snapshot is None:
            return None
        arrays, groups = pack(self.sim, self.snapshot)
        o = self.outputs()
        tag = f"{self.frame:06d}"
        usd = o.get("usd")
        meta = {"format": FORMAT_VERSION, "frame": self.frame, "t0": self.t0, "reason": reason,
                "written_unix_s": time.time(), "scene": scene_identity(self.sim), "groups": groups,
                "escaped": int(o.get("escaped", 0)), "wall_s": float(o.get("wall_s", 0.0)),
                "usd": usd.checkpoint_state(tag) if usd is not None else None,
                "csv": {name: r.checkpoint_state(tag) for name, r in o.get("csv", {}).items() if r is not None},
                "vtk": o["vtk"].checkpoint_state(tag) if o.get("vtk") is not None else None}
        write_file(self.path, arrays, meta)
        self.written_frame = self.frame
        self.next_due = time.monotonic() + self.interval
        if usd is not None:
            writer = usd.writer
            keep = meta["usd"]["open_chunk"]
            for p in writer.clip_dir.glob(f"open_*{writer.ext}"):
                if p.name != keep:
                    try:
                        p.unlink()
                    except OSError:
                        pass
        return self.path


def clear(out: Path) -> None:
    """Remove a previous run's checkpoint (a fresh run must not be resumed from a stale one)."""
    try:
        (Path(out) / FILE_NAME).unlink()
    except FileNotFoundError:
        pass
