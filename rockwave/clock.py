"""The clock: the one place that chooses the time step.

It asks every present solver for its stable limit (rockwave/solver.py) and steps at the smallest:
the fluid's CFL, force and viscous limits (``simulation.cfl_number``), the block contacts' critical
step times ``simulation.block_dt_safety``, half the critical step of the fluid-block penalty spring.
A fixed step (``simulation.time_step = "fixed"``) is checked once against the stability bounds
(fluid 0.4 h/c0, the DDA 2/omega_max, the penalty spring) and refused above them.

The adaptive target is re-evaluated every ``simulation.dt_update_interval`` steps (one host read);
``advance`` divides the time left into equal steps no longer than the target, so frames land exactly.
``limiting`` names the solver whose limit set the current target (run.json, the progress line).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import warp as wp

from rockwave.scene import Scene, SceneError
from rockwave.solver import TimeStep


class Clock:
    """Simulated time, step count and step length of a run.

    time [s], steps, dt [s] (the step in use), target [s] (the adaptive step the next steps aim at),
    limiting (name of the limit that set ``target``), fixed (a scene-given constant step).
    ``dt_array``: wp.array(float, 1) holding dt on the device (kernels and CUDA graphs read it)."""

    def __init__(self, scene: Scene, device: str, limits: dict[str, Callable[[bool], float]],
                 stability_bounds: list[tuple[float, str]]):
        sim = scene.simulation
        self.scene = scene
        self.limits = limits  # name -> f(initial) = stable step of that solver now [s]
        self.fixed = sim.time_step == "fixed"
        self.update_interval = int(sim.dt_update_interval)
        self.time = 0.0
        self.steps = 0
        self.limiting = "fixed" if self.fixed else ""
        self.stability_limit = math.inf
        if stability_bounds:
            self.stability_limit, why = min(stability_bounds)
        if self.fixed:
            if sim.dt_s > self.stability_limit:
                raise SceneError(scene.path, [("simulation.dt_s", f"{sim.dt_s:g} s is above the stability limit "
                                                                  f"{self.stability_limit:.3g} s ({why})")])
            self.target = float(sim.dt_s)
        else:
            self.target = self.adaptive(initial=True)
        self.dt = self.target
        self.dt_array = wp.array([self.dt], dtype=float, device=device)

    def adaptive(self, initial: bool = False) -> float:
        """The smallest of the solvers' stable steps (the scene's duration when none is present).
        ``initial``: before the first step (the fluid assumes rest and gravity's acceleration)."""
        vals = {n: f(initial) for n, f in self.limits.items()}
        if not vals:
            self.limiting = ""
            return self.scene.simulation.duration_s
        self.limiting = min(vals, key=vals.get)
        return vals[self.limiting]

    def set_dt(self, dt: float) -> None:
        if dt != self.dt:
            self.dt = dt
            self.dt_array.fill_(dt)

    def time_step(self) -> TimeStep:
        """The step about to be taken."""
        return TimeStep(self.dt, self.time, self.dt_array)

    def tick(self, n: int = 1) -> None:
        """n steps of the current dt were taken."""
        self.time += n * self.dt
        self.steps += n

    def update_target(self) -> None:
        """Re-evaluate the adaptive target every ``dt_update_interval`` steps."""
        if not self.fixed and self.steps % self.update_interval == 0:
            self.target = self.adaptive()

    def chunk_allowed(self, k: int, n: int) -> bool:
        """May the next k of the n steps left run as one chunk (no target update falls inside it)?"""
        interval = self.update_interval
        return 0 < k <= n and (self.fixed or (-self.steps) % interval == 0 and interval >= k or (-self.steps) % interval >= k)

    # checkpoint (rockwave/checkpoint.py)
    def capture(self) -> dict:
        return {"time": self.time, "steps": self.steps, "dt": self.dt, "_dt_target": self.target}

    def restore(self, meta: dict) -> None:
        self.time = float(meta["time"])
        self.steps = int(meta["steps"])
        self.target = float(meta["_dt_target"])
        self.dt = float(meta["dt"])
        self.dt_array.fill_(self.dt)


def gravity_norm(scene: Scene) -> float:
    return float(np.linalg.norm(scene.gravity.acceleration_m_s2))
