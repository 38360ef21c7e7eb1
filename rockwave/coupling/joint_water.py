"""Water pressure in the joints between blocks (coupling.joint_water; kernels/coupling/joint_water.py).

The SPH water does not enter a closed joint (no particle fits in a contact, and those seeded within the contact
distance of a face are removed), so a block resting under water feels the water's pressure on its wetted faces but
none under its base: it carries its full weight, not its buoyant weight, in friction, and holds far below the limit
that rock mechanics gives a submerged joint (docs/notes.md 'Verification cases that stand', 'Newmark ratchet').
``JointWater`` adds the missing pore pressure: at each contact point of two blocks, the hydrostatic pressure of the
water over it, u = rho0 |g| (z_s - z), from the local free surface z_s (a map of the highest fluid particle per
column of one spacing, rebuilt every step), acting normal to the contact over the point's share of the patch, equal
and opposite on the two blocks. The penalty's normal force then drops by the uplift U and the Coulomb cap with it:
mu (F_n - U), Hoek & Bray's effective normal force for a joint open to the water. A point with no water in its
column or the two beside it each way (a joint under an emergent block, away from its sides) gets none.

Cost: one pass over the fluid particles (an atomic max into the map) and one thread per contact pair, each step.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from rockwave.kernels.coupling import joint_water as jw_k


class JointWater:
    """Pore pressure in the block contacts below the water (module docstring). ``fluid``: the FluidModel (spacing,
    up axis, domain, rest density); ``blocks``: the BlockModel (gravity, kinds)."""

    def __init__(self, fluid, blocks, rest_density: float):
        self.fluid, self.blocks = fluid, blocks
        self.device = d = fluid.device
        s = float(fluid.spacing)
        self.up = int(fluid.up)
        lo = np.asarray(fluid.domain_lo, float).reshape(-1)
        hi = np.asarray(fluid.domain_hi, float).reshape(-1)
        lo3, hi3 = np.zeros(3), np.zeros(3)
        lo3[:lo.size], hi3[:hi.size] = lo, hi
        axes = [a for a in range(3) if a != self.up][:2]
        if fluid.dim == 2:
            axes = [0, 2]
        ncol = [max(int(np.ceil((hi3[a] - lo3[a]) / s)), 1) if not (fluid.dim == 2 and a == 2) else 1 for a in axes]
        self.lo = wp.vec3(*lo3.astype(np.float32))
        self.inv_s = 1.0 / s
        self.half_s = 0.5 * s
        self.ncol = wp.vec2i(*ncol)
        self.rho_g = float(rest_density) * float(np.linalg.norm(blocks.gravity))
        self.height = wp.zeros(ncol[0] * ncol[1], dtype=float, device=d)

    def apply(self, fluid_state, block_state) -> None:
        """The uplift of this step (from the contacts of the last block step) into block_state.ext_force /
        ext_torque, which the block step that follows consumes."""
        self.height.fill_(float(jw_k.NO_WATER))
        nf = self.fluid.n_fluid
        if nf == 0:
            return
        wp.launch(jw_k.surface_map, dim=nf, inputs=[fluid_state.x, self.lo, self.inv_s, self.ncol, self.up],
                  outputs=[self.height], device=self.device)
        table = block_state.table_views[0]
        wp.launch(jw_k.joint_uplift, dim=table.keys.shape[0],
                  inputs=[table, self.blocks.num_blocks, self.blocks.kinds, block_state.bodies, self.lo, self.inv_s,
                          self.ncol, self.up, self.half_s, self.rho_g, self.height, block_state.loads],
                  device=self.device)
