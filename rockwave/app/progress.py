"""A one-line progress bar on stderr: simulated time, steps/s, particle count, ETA.

On a terminal the bar is redrawn in place (carriage return, no newline). While it is shown, a
warning (warnings.warn) first ends the bar's line, so that the warning starts on a line of its own
and the bar continues below it (:meth:`Progress.break_line`, installed as a warnings.showwarning hook
until :meth:`Progress.close`)."""

from __future__ import annotations

import sys
import time
import warnings


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
        self._open_line = False  # the bar is on screen without its newline
        self._hook = None
        self._previous_hook = None
        if self.enabled and self.tty:
            self._previous_hook = warnings.showwarning

            def hook(*args, **kwargs):
                self.break_line()
                return self._previous_hook(*args, **kwargs)

            self._hook = hook
            warnings.showwarning = hook

    def break_line(self) -> None:
        """End the bar's line (if one is open) so that the next output starts on a fresh line."""
        if self._open_line:
            self.stream.write("\n")
            self.stream.flush()
            self._open_line = False

    def update(self, sim_time: float, steps: int, force: bool = False, note: str = "") -> None:
        """Redraw (at most every 0.2 s on a terminal, 5 s otherwise, unless ``force``); ``note`` is appended
        (the run loop: which solver's limit sets the step)."""
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
                f"{self.particles:,} {self.unit}  ETA {_fmt(eta)}" + (f"  {note}" if note else ""))
        if self.tty:
            self.stream.write("\r" + line)
            self._open_line = True
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self) -> None:
        self.break_line()
        if self._hook is not None:
            if warnings.showwarning is self._hook:  # someone else's hook installed since stays theirs
                warnings.showwarning = self._previous_hook
            self._hook = None


def _fmt(s: float) -> str:
    if s != s:
        return "?"
    s = int(s)
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"
