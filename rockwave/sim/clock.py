"""The clock: the one place that chooses the time step.

It asks every present solver for its stable limit (rockwave/base/solver.py) and steps at the smallest:
the fluid's CFL, force and viscous limits (``simulation.cfl_number``), the block contacts' critical
step times ``simulation.block_dt_safety``, half the critical step of the fluid-block penalty spring.
A fixed step (``simulation.time_step = "fixed"``) is checked once against the stability bounds
(fluid 0.4 h/c0, the DDA 2/omega_max, the penalty spring) and refused above them.

The adaptive target is re-evaluated every ``simulation.dt_update_interval`` steps (one host read);
``advance`` divides the time left into equal steps no longer than the target, so frames land exactly.
``limiting`` names the solver whose limit set the current target (run.json, the progress line).

Multi-rate stepping (``simulation.block_stepping = "multirate"``, the default; docs/coupling.md "Multi-rate
stepping"). In a scene with water and blocks the step is set by the fluid-rate limits alone (the
fluid's, and the coupling's penalty spring, which acts on the particles once per fluid step); the
blocks' contacts and integration run ``substeps`` = ceil(dt / block stable step) sub-steps of
dt / substeps inside each step, with the water's force and torque on each block held over the step
(rockwave/dda/blocks.py BlockSolver.substeps), so the impulse the water gives a block over the step is
exactly the one it takes (-f dt each side). The count follows dt (``set_dt``); above
MAX_BLOCK_SUBSTEPS it is a SceneError naming the stiffness to soften. ``"single"`` is the old
behaviour: every limit caps the one step, one block step per step.
"""

from __future__ import annotations

import math
from typing import Callable

import warp as wp

from rockwave.base.solver import TimeStep
from rockwave.build.options import gravity_norm as gravity_norm  # |g| of a scene (re-exported: rockwave/sim/simulation.py)
from rockwave.scene.format import Scene, SceneError

MAX_BLOCK_SUBSTEPS = 1000  # block sub-steps per fluid step above which a scene is refused


class Clock:
    """Simulated time, step count and step length of a run.

    time [s], steps, dt [s] (the step in use), target [s] (the adaptive step the next steps aim at),
    limiting (name of the limit that set ``target``), fixed (a scene-given constant step).
    ``dt_array``: wp.array(float, 1) holding dt on the device (kernels and CUDA graphs read it).
    ``substeps``: block sub-steps per step (1 unless ``block_substep`` is given), ``block_dt`` [s] their length;
    ``steps_limited_by`` (limit name -> steps it set) and ``block_steps`` count the whole run's steps (a resumed
    run's clock restores them with the time and the step count).

    ``block_substep`` (multi-rate): (stable block step [s], f(n, dt) -> the SceneError to raise when
    the count n for a step dt is above MAX_BLOCK_SUBSTEPS); the blocks' limit is then not among ``limits``."""

    def __init__(self, scene: Scene, device: str, limits: dict[str, Callable[[bool], float]],
                 stability_bounds: list[tuple[float, str]],
                 block_substep: tuple[float, Callable[[int, float], SceneError]] | None = None):
        sim = scene.simulation
        self.scene = scene
        self.limits = limits  # name -> f(initial) = stable step of that solver now [s]
        self.block_substep = block_substep
        self.substeps = 1
        self.steps_limited_by: dict[str, int] = {}  # limit name -> steps it set (the whole run; run.json)
        self.block_steps = 0  # block (sub-)steps taken (the whole run)
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
        self._count_substeps()
        self.dt_array = wp.array([self.dt], dtype=float, device=device)

    @property
    def block_dt(self) -> float:
        """Length of one block (sub-)step [s]."""
        return self.dt / self.substeps

    def _count_substeps(self) -> None:
        """substeps = ceil(dt / stable block step) in multi-rate stepping (1 otherwise)."""
        if self.block_substep is None:
            return
        stable, error = self.block_substep
        n = max(1, math.ceil(self.dt / stable - 1e-9))
        if n > MAX_BLOCK_SUBSTEPS:
            raise error(n, self.dt)
        self.substeps = n

    def describe(self) -> str:
        """The step and what set it, e.g. '0.000249 s (fluid), blocks 20 x 1.24e-05 s' (the progress line)."""
        s = f"{self.dt:.3g} s ({self.limiting or 'fixed'})"
        if self.block_substep is not None:
            s += f", blocks {self.substeps} x {self.block_dt:.3g} s"
        return s

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
            self._count_substeps()
            self.dt_array.fill_(dt)

    def time_step(self) -> TimeStep:
        """The step about to be taken."""
        return TimeStep(self.dt, self.time, self.dt_array)

    def tick(self, n: int = 1) -> None:
        """n steps of the current dt were taken."""
        self.time += n * self.dt
        self.steps += n
        key = self.limiting or "fixed"
        self.steps_limited_by[key] = self.steps_limited_by.get(key, 0) + n
        self.block_steps += n * self.substeps

    def update_target(self) -> None:
        """Re-evaluate the adaptive target every ``dt_update_interval`` steps."""
        if not self.fixed and self.steps % self.update_interval == 0:
            self.target = self.adaptive()

    def chunk_allowed(self, k: int, n: int) -> bool:
        """May the next k of the n steps left run as one chunk (no target update falls inside it)?"""
        interval = self.update_interval
        return 0 < k <= n and (self.fixed or (-self.steps) % interval == 0 and interval >= k or (-self.steps) % interval >= k)

    # checkpoint (rockwave/sim/checkpoint.py)
    def capture(self) -> dict:
        return {"time": self.time, "steps": self.steps, "dt": self.dt, "_dt_target": self.target, "limiting": self.limiting,
                "steps_limited_by": dict(self.steps_limited_by), "block_steps": self.block_steps}

    def restore(self, meta: dict) -> None:
        self.time = float(meta["time"])
        self.steps = int(meta["steps"])
        self.target = float(meta["_dt_target"])
        self.dt = float(meta["dt"])
        if "steps_limited_by" in meta:  # (checkpoint format 5; before: the counters start from the resume)
            self.limiting = str(meta["limiting"])
            self.steps_limited_by = {str(k): int(v) for k, v in meta["steps_limited_by"].items()}
            self.block_steps = int(meta["block_steps"])
        self._count_substeps()
        self.dt_array.fill_(self.dt)

