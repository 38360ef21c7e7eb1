"""A one-line progress bar on stderr: simulated time, steps/s, particle count, ETA."""

from __future__ import annotations

import sys
import time


class Progress:
    def __init__(self, duration: float, particles: int, enabled: bool = True, stream=None, unit: str = "particles"):
        self.duration = duration
        self.particles = particles
        self.unit = unit
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.t0 = time.perf_counter()
        self.last = 0.0
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()

    def update(self, sim_time: float, steps: int, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if not force and now - self.last < (0.2 if self.tty else 5.0):
            return
        self.last = now
        wall = now - self.t0
        frac = min(sim_time / self.duration, 1.0) if self.duration > 0 else 1.0
        eta = wall * (1 - frac) / frac if frac > 0 else float("nan")
        width = 24
        filled = int(frac * width)
        bar = "#" * filled + "-" * (width - filled)
        line = (f"[{bar}] t = {sim_time:.3f}/{self.duration:.3f} s  {steps / wall if wall > 0 else 0:,.0f} steps/s  "
                f"{self.particles:,} {self.unit}  ETA {_fmt(eta)}")
        self.stream.write(("\r" + line) if self.tty else (line + "\n"))
        self.stream.flush()

    def close(self) -> None:
        if self.enabled and self.tty:
            self.stream.write("\n")
            self.stream.flush()


def _fmt(s: float) -> str:
    if s != s:
        return "?"
    s = int(s)
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"
