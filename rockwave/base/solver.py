"""The contract every solver keeps (rockwave/sph/fluid.py, rockwave/sph/ghost.py, rockwave/dda/blocks.py).

A solver advances a state by one step and reports the largest step that is stable for that state
now; it keeps no data between steps that a checkpoint of its state would miss. The clock
(rockwave/sim/clock.py) is the only place that chooses dt: it asks every present solver for its limit.

    limit = solver.stable_dt(state)          # [s]
    solver.step(state, TimeStep(dt, time, dt_array))
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import warp as wp


@dataclass
class TimeStep:
    """One step of the clock.

    dt: step length [s]. time: simulated time at the start of the step [s].
    dt_array: wp.array(float, 1) on the solver's device holding dt; kernels read dt from it, so one
    captured CUDA graph serves every dt.
    """

    dt: float
    time: float
    dt_array: wp.array


class Solver(Protocol):
    def stable_dt(self, state: Any) -> float:
        """Largest stable step for ``state`` as it is now [s]."""

    def step(self, state: Any, ts: TimeStep) -> None:
        """Advance ``state`` from ts.time to ts.time + ts.dt."""
