"""One fluid step's block sub-stepping (multi-rate): the one policy that Simulation and the MPI simulation share.

In multi-rate stepping the blocks take ``clock.substeps`` sub-steps inside each fluid step with the water's load
held (rockwave/sim/clock.py chooses the count from the blocks' stable step). Two savings apply while they are safe,
decided by one host read at the clock's update rhythm (BlockSolver.hold_checks; BlockOptions.hold_contacts):

- the broad phase's candidate pairs are kept through the fluid step while no block moves more than half the
  broad-phase margin in it (``keep_pairs``);
- the first sub-step's contact points are carried through the others while no pair out of contact can close
  before the next check (``hold_contacts``).

The decision is state of the run: it travels in checkpoints with the clock (rockwave/sim/checkpoint.py).
"""

from __future__ import annotations

from dataclasses import dataclass

from rockwave.base.solver import TimeStep
from rockwave.dda.blocks import BlockSolver, BlockState
from rockwave.sim.clock import Clock


@dataclass
class BlockSubstepping:
    """Advances the blocks through one fluid step: ``clock.substeps`` sub-steps of ``ts.dt / substeps``. The solver is
    passed with each step (a Simulation's block solver may be replaced, e.g. with other BlockOptions)."""

    clock: Clock
    pairs_hold: bool | None = None  # the last hold check's verdicts; None: not checked yet in this run
    contacts_hold: bool | None = None

    def advance(self, solver: BlockSolver, state: BlockState, ts: TimeStep) -> None:
        n = self.clock.substeps
        if n > 1 and (self.clock.steps % self.clock.update_interval == 0 or self.pairs_hold is None):
            self.pairs_hold, self.contacts_hold = solver.hold_checks(state, ts.dt, self.clock.update_interval + 1)
        solver.substeps(state, ts, n, keep_pairs=n > 1 and bool(self.pairs_hold),
                             hold_contacts=n > 1 and bool(self.contacts_hold))  # the water's load held
