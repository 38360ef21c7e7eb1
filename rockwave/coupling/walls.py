"""Adami wall particles on moving blocks: the water pushes a block with its extrapolated pressure (BlockWalls)."""

from __future__ import annotations

import numpy as np
import warp as wp

from rockwave.base.maths import quat_to_matrix
from rockwave.base.solver import TimeStep
from rockwave.kernels.coupling import walls as walls_k


class BlockWalls:
    """Adami et al. (2012) wall particles on the moving blocks (rigid, deformable, kinematic, compound parts),
    so that the water pushes a block with its extrapolated pressure, not only through the penalty.

    A lattice of the boundary spacing inside each block's faces, ``layers * step`` deep (the kernel support;
    rockwave/build/builder.py moving_block_walls), kept in the body frame (``body_r``, one block index each in
    ``wall_block``). They are the last boundary particles of the fluid (FluidModel.n_moving_walls). Each
    step, before the fluid step (Coupling.compute -> place), every particle is put at x = c + R r with the
    block's rigid velocity v = v_c + w x R r and acceleration a = a_c + alpha x R r + w x (w x R r), a_c and
    alpha from the block's velocities at the last two steps (block_wall_motion). The fluid step then
    extrapolates their pressure (Adami's eq. 27 with the wall acceleration term,
    p_w = (sum_f p_f W_wf + (g - a_w) . sum_f rho_f r_wf W_wf) / sum_f W_wf) and no-slip velocity
    (2 v_w - the fluid's, eq. 23), the fluid feels them in its force pass, and after it (the solver's
    ``block_wall_reactions`` pass, before the integration) block_wall_reactions sums the same pair forces, with the
    opposite sign, onto the blocks: into ``water_force`` / ``water_torque`` (N, N m about the centroid, per
    block, every moving block: diagnostics) and, for rigid and deformable blocks, into the loads the penalty
    uses (ext_force / ext_torque), so multi-rate stepping holds them over the block sub-steps as it does the
    penalty's. The penalty force stays as the guard against penetration (as on fixed blocks): the water sits
    half a spacing from a face, where the penalty (contact distance d0 = s/2) is just reached.

    They move, so they are re-binned in the fluid's cell grid at every list build like the fluid particles, and
    the Verlet lists' displacement checks cover them (FluidSolver._list_guard); the wall pressure's cell query
    starts at their positions of the last build (kernels/sph/fluid.py wall_pressure_adami).
    """

    def __init__(self, solver, blocks, block_state, world_positions: np.ndarray, wall_block: np.ndarray,
                 depth_scale: wp.array, dim: int):
        m = solver.model
        self.solver, self.blocks, self.dim = solver, blocks, dim
        self.device = d = m.device
        self.n = n = int(len(wall_block))
        assert n == m.n_moving_walls, (n, m.n_moving_walls)
        x = block_state.x.numpy().astype(np.float64)
        q = block_state.q.numpy().astype(np.float64)
        wb = np.asarray(wall_block, np.int64)
        body = np.zeros((n, 3))
        for b in np.unique(wb):
            sel = wb == b
            body[sel] = (np.asarray(world_positions, float)[sel] - x[b]) @ quat_to_matrix(q[b])  # R^T (p - c)
        self.body_r = wp.array(body.astype(np.float32), dtype=wp.vec3, device=d)
        self.wall_block = wp.array(wb.astype(np.int32), dtype=int, device=d)
        self.depth_scale = depth_scale
        nb = blocks.num_blocks
        self.count_per_block = np.bincount(wb, minlength=nb)
        self.v_prev = wp.clone(block_state.v)
        self.w_prev = wp.clone(block_state.w)
        self.dt_prev = wp.zeros(1, dtype=float, device=d)  # 0: no step yet (no acceleration)
        self.acc = wp.zeros(nb, dtype=wp.vec3, device=d)
        self.ang_acc = wp.zeros(nb, dtype=wp.vec3, device=d)
        self.water_force = wp.zeros(nb, dtype=wp.vec3, device=d)
        self.water_torque = wp.zeros(nb, dtype=wp.vec3, device=d)
        self.x_off = m.n_fluid + m.n_static_boundary  # first wall particle in the fluid arrays
        self.b_off = m.n_static_boundary  # ... among the boundary particles
        solver.insert_pass("block_wall_reactions", lambda state, dt: self.react(solver, state), after="pair_forces")

    def place(self, fluid_state, block_state, ts: TimeStep) -> None:
        """Put the wall particles at the blocks' poses (positions, velocities, accelerations) for this step."""
        d, m = self.device, self.solver.model
        wp.launch(walls_k.block_wall_motion, dim=self.blocks.num_blocks,
                  inputs=[block_state.bodies, self.dt_prev], outputs=[self.v_prev, self.w_prev, self.acc, self.ang_acc],
                  device=d)
        wp.copy(self.dt_prev, ts.dt_array)
        wp.launch(walls_k.place_block_walls, dim=self.n,
                  inputs=[self.body_r, self.wall_block, block_state.bodies, self.acc, self.ang_acc, int(m.dim == 2),
                          self.x_off, self.b_off],
                  outputs=[fluid_state.x, fluid_state.v, self.solver.wall_accel], device=d)
        self.water_force.zero_()
        self.water_torque.zero_()
        self._block_state = block_state

    def react(self, solver, state) -> None:
        """After the fluid's force pass: the water's force on the wall particles, onto their blocks."""
        m = solver.model
        if m.n_fluid == 0:
            return
        bs = self._block_state
        wp.launch(walls_k.block_wall_reactions, dim=self.n,
                  inputs=[solver.cells, *solver._slot_ranges, solver.list_radius, state.x, state.v, state.rho, solver._pr2,
                          m.particle_mass, solver._wall_pr2, state.wall_velocity, solver._xq, self.b_off, self.wall_block,
                          m.params, bs.bodies, self.blocks.kinds, self.depth_scale, bs.loads],
                  outputs=[self.water_force, self.water_torque], device=self.device)

    def add_wall_work(self, wall_work: wp.array, ts: TimeStep) -> None:
        """Add the kinematic blocks' work on the water through their wall particles over the step to wall_work[0]
        (the energy budget; the forces of the step's react pass, the blocks' velocities at its start)."""
        bs = self._block_state
        wp.launch(walls_k.kinematic_wall_work, dim=self.blocks.num_blocks,
                  inputs=[self.blocks.kinds, bs.bodies, self.water_force, self.water_torque, self.depth_scale, ts.dt_array],
                  outputs=[wall_work], device=self.device)

    def checkpoint_arrays(self) -> dict:
        """What the walls keep between steps: the blocks' velocities of the last step and its length (the
        acceleration estimate); the positions are in the fluid state."""
        return {"v_prev": self.v_prev, "w_prev": self.w_prev, "dt_prev": self.dt_prev}
