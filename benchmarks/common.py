"""Shared helpers of the benchmark parts: paths, device facts, timing, result files."""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"


def log(msg: str) -> None:
    print(msg, flush=True)


def device_name(device: str) -> str:
    import warp as wp

    d = wp.get_device(device)
    if d.is_cuda:
        return d.name
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip() + f" ({os.cpu_count()} cores; Warp CPU runs a kernel on one thread)"
    except OSError:
        pass
    return platform.processor() or "cpu"


def commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
        return out.stdout.strip() or "unknown"
    except OSError:
        return "unknown"


def timed(fn, device: str) -> float:
    """Wall seconds of fn(), synchronised with the device before and after."""
    import warp as wp

    wp.synchronize_device(device)
    t = time.perf_counter()
    fn()
    wp.synchronize_device(device)
    return time.perf_counter() - t


def rel(path) -> str:
    """A path relative to the repository where it lies inside it."""
    try:
        return str(Path(path).resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def jdefault(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def write_json(res: dict, path) -> None:
    """Write a result JSON atomically (temp file in the same folder, then rename): a run killed while
    writing leaves the previous complete file, never a truncated one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w") as f:
        json.dump(res, f, indent=1, default=jdefault)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def fmt_value(v, fmt: str = ".3f", missing: str = "-") -> str:
    """``v`` formatted, or ``missing`` where it is absent or not finite."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return missing
    return format(v, fmt)


def write_record(stem: str, rows: list, head: str, markdown, device: str, args) -> None:
    """A benchmark's record: ``stem``.md (``head`` and the table ``markdown(rows, head)``) and ``stem``.json (the
    rows with device, commit, date and the command's arguments); the table is also printed."""
    table = markdown(rows, head)
    with open(stem + ".md", "w") as fh:
        fh.write(table)
    write_json(dict(rows=rows, device=device, device_name=device_name(device), commit=commit(),
                    date=time.strftime("%Y-%m-%d"), args=vars(args)), stem + ".json")
    print(table)
