"""Shared helpers for the benchmark scripts: device facts, timing, result files."""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import time
from pathlib import Path

import warp as wp

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"


def device_name(device: str) -> str:
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
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip() or "unknown"
    except OSError:
        return "unknown"


def timed(fn, device: str) -> float:
    wp.synchronize_device(device)
    t = time.perf_counter()
    fn()
    wp.synchronize_device(device)
    return time.perf_counter() - t


def save(name: str, device: str, payload: dict) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    stamp = datetime.date.today().isoformat()
    tag = device.replace(":", "")
    path = RESULTS / f"{stamp}-{name}-{tag}.json"
    payload = {"benchmark": name, "device": device, "device_name": device_name(device), "date": stamp, "commit": commit(), **payload}
    path.write_text(json.dumps(payload, indent=2))
    return path
