"""``python -m rockwave validate``: every check ``run`` makes before its first step, and a run-length estimate
measured on the device at hand.

:func:`validate` first makes the checks that allocate nothing (rockwave/build/preflight.py check_before_stepping:
the scene file, meshes, memory, regions, gauges, block geometry and overlaps, the run length from the scene's
limits), then builds the :class:`rockwave.sim.simulation.Simulation` as ``run`` does, which makes the checks of
the build (the clock's fixed step against the stability limits, the multi-rate sub-step cap, the blocks and the
coupling as built), :func:`check_built` (water left after seeding) and the hazard monitor's (still levels), so
validate and run refuse the same scenes. Last it times a few steps (after one that loads the kernels) and
estimates the run's wall time from them, at the smaller of the scene's expected step (the fluid's limit at the
expected flow speed) and the built simulation's (which includes the coupling's penalty spring), plus the USD
output of the blocks (preflight.usd_output_seconds).
"""

from __future__ import annotations

import time

from rockwave.base.errors import SimulationError
from rockwave.build import preflight
from rockwave.output.hazard import HazardMonitor
from rockwave.scene.format import Scene, SceneError
from rockwave.sim.simulation import Simulation

CALIBRATION_STEPS = 5  # timed steps (after one that loads the kernels) ...
CALIBRATION_WALL_S = 2.0  # ... or fewer once they took this long


def check_built(sim) -> None:
    """The checks of a built simulation that run makes before stepping (SceneError)."""
    if sim.fluid is not None and sim.fluid.n_fluid == 0:
        raise SceneError(sim.scene.path, [("fluid.regions", "no water particle is left after seeding (outside the tank, "
                                                            "inside obstacles or blocks)")])


def measure_step(sim, steps: int = CALIBRATION_STEPS, wall_s: float = CALIBRATION_WALL_S) -> float | None:
    """Seconds per step of ``sim`` on its device: one step to load the kernels, then up to ``steps`` timed steps (fewer
    once ``wall_s`` has passed). None when a step fails (the run would report it; the estimate is then nominal)."""
    try:
        sim.step()
        t0 = time.perf_counter()
        n = 0
        while n < steps and (n == 0 or time.perf_counter() - t0 < wall_s):
            sim.step()
            n += 1
        return (time.perf_counter() - t0) / n
    except (SimulationError, ValueError, RuntimeError, ArithmeticError):
        return None


def validate(scene: Scene, device: str, duration: float | None = None, force: bool = False, measure: bool = True) -> dict:
    """Every check a run makes before stepping (SceneError on the first refusal) and the run-length estimate.
    Returns {"estimate", "blocks", "run_length" (preflight.RunLength, measured unless ``measure`` is False or a step
    failed), "simulation"}."""
    found = preflight.check_before_stepping(scene, device, duration=duration, force=force)
    sim = Simulation(scene, device=device)
    check_built(sim)
    if scene.hazard is not None:
        HazardMonitor(sim)
    sps = measure_step(sim) if measure else None
    if sps is not None:
        nominal = found["run_length"]
        dt = sim.clock.dt if sim.fixed else min(nominal.dt, sim.clock.target)
        found["run_length"] = preflight.check_run_length(scene, device, duration=duration, seconds_per_step=sps, dt=dt,
                                                         force=force)
    found["simulation"] = sim
    return found
