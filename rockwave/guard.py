"""Blow-up guard: checks the state after every frame and stops a run that has gone unstable.

Fatal (a :class:`BlowUpError` giving step, time, where, and a suggested time step):
- a NaN or inf in any fluid particle's position or velocity, or any block's pose or velocity;
- a fluid particle faster than ``SPEED_FACTOR`` x the speed of sound c0 (plus free fall, outside the domain);
- a block faster than its bar wave speed sqrt(E / rho) (linear speed, or spin x bounding radius);
- more than ``ESCAPE_FRACTION`` of the water outside the domain (the water flew apart);
- the mechanical energy (kinetic + gravitational, water and blocks) rising between two frames by
  more than ``ENERGY_JUMP`` x its scale (total mass x |g| x domain height + initial kinetic energy).

Not fatal: fluid particles that leave the domain in a stable run (a splash over a wall); they are
counted (``particles_outside_domain`` in run.json, and a warning when the first ones leave); since
they keep falling, their speed limit is raised by the free-fall speed sqrt(2 g depth below the
domain's top).
"""

from __future__ import annotations

import math

import numpy as np

SPEED_FACTOR = 5.0
ESCAPE_FRACTION = 0.5
ENERGY_JUMP = 0.5


class BlowUpError(RuntimeError):
    """Raised (as a SimulationError) by the guard; ``step``, ``time``, ``where``, ``position``, ``suggested_dt``."""


def _fmt(p) -> str:
    return "[" + ", ".join(f"{float(c):.4g}" for c in p) + "]"


class HealthGuard:
    def __init__(self, sim):
        self.sim = sim
        s = sim.scene
        self.g = float(np.linalg.norm(s.gravity.acceleration_m_s2))
        self.up = s.dim - 1
        self.prev_energy = None
        self.escaped = 0
        self.warned_escape = False
        mass, lo, hi = 0.0, math.inf, -math.inf
        if sim.fluid is not None and sim.fluid.n_fluid:
            f = sim.fluid
            mass += f.fluid_mass * f.n_fluid
            lo, hi = min(lo, f.domain_lo[self.up]), max(hi, f.domain_hi[self.up])
        self.block_wave_speed = None
        if sim.blocks is not None:
            m = sim.blocks
            mass += float(m.np["mass"][m.movable].sum())
            pos = m.base_position[:, 2 if s.dim == 3 else self.up]
            r = m.np["radius"]
            lo, hi = min(lo, float((pos - r).min())), max(hi, float((pos + r).max()))
            E = np.array([sp.youngs_modulus or 10.0e9 for sp in m.specs])
            rho = np.array([sp.density for sp in m.specs])
            self.block_wave_speed = np.sqrt(E / rho)
        height = (hi - lo) if hi > lo else 1.0
        self.energy_scale = mass * self.g * height
        self.energy_scale += self._energy()[0]  # initial kinetic + potential above the floor

    # ---------------------------------------------------------------------------------------
    def _energy(self, x=None, v=None) -> tuple[float, str]:
        """Mechanical energy relative to the domain floor and a description of the most energetic body."""
        sim = self.sim
        e, best, where = 0.0, -1.0, ""
        if sim.fluid is not None and sim.fluid.n_fluid:
            if x is None:
                x, v = sim.positions(), sim.velocities()
            m = sim.fluid.fluid_mass
            z0 = sim.fluid.domain_lo[self.up]
            ke = 0.5 * m * (v * v).sum(axis=1)
            e += float(ke.sum() + m * self.g * (x[:, self.up] - z0).sum())
            if len(ke):
                i = int(np.argmax(ke))
                best, where = float(ke[i]), f"fluid particle {i} at {_fmt(x[i])} moving at {math.sqrt(2 * ke[i] / m):.3g} m/s"
        if sim.blocks is not None:
            st, mod = sim.block_state, sim.blocks
            xb, vb = st.positions_numpy(), st.velocities_numpy()
            mb = mod.np["mass"]
            e += st.kinetic_energy()
            mov = mod.movable
            e += float((mb[mov] * self.g * xb[mov, 2 if sim.scene.dim == 3 else self.up]).sum())
            keb = 0.5 * mb * (vb * vb).sum(axis=1) * mov
            if len(keb) and keb.max() > best:
                b = int(np.argmax(keb))
                where = f"block {mod.names[b]!r} (#{b}) at {_fmt(xb[b])} moving at {np.linalg.norm(vb[b]):.3g} m/s"
        return e, where

    def _fail(self, what: str, block: bool = False) -> None:
        sim = self.sim
        s = sim.scene.simulation
        dt = sim.dt
        new = 0.5 * dt
        if sim.fixed:
            how = f"simulation.dt_s = {new:.3g}"
        elif block:
            how = f"simulation.block_dt_safety = {0.5 * s.block_dt_safety:.3g}"
        else:
            how = f"simulation.cfl_number = {0.5 * s.cfl_number:.3g}"
        err = BlowUpError(f"blow-up at step {sim.steps}, t = {sim.time:.6g} s: {what}; suggested time step {new:.3g} s "
                          f"(now {dt:.3g} s): set {how}")
        err.step, err.time, err.suggested_dt = sim.steps, sim.time, new
        raise err

    def check(self, x: np.ndarray, v: np.ndarray) -> int:
        """Raise on a blow-up; return the number of fluid particles outside the domain."""
        sim = self.sim
        if sim.blocks is not None:
            st, mod = sim.block_state, sim.blocks
            xb, vb = st.positions_numpy(), st.velocities_numpy()
            wb, qb = st.angular_velocities_numpy(), st.orientations_numpy()
            bad = ~(np.isfinite(xb).all(1) & np.isfinite(vb).all(1) & np.isfinite(wb).all(1) & np.isfinite(qb).all(1))
            if bad.any():
                b = int(np.argmax(bad))
                self._fail(f"block {mod.names[b]!r} (#{b}) at {_fmt(xb[b])} has a NaN/inf position or velocity", block=True)
            speed = np.maximum(np.linalg.norm(vb, axis=1), np.linalg.norm(wb, axis=1) * mod.np["radius"])
            over = speed > self.block_wave_speed
            if over.any():
                b = int(np.argmax(speed / self.block_wave_speed))
                self._fail(f"block {mod.names[b]!r} (#{b}) at {_fmt(xb[b])} moves at {speed[b]:.3g} m/s, faster than "
                           f"its bar wave speed sqrt(E/rho) = {self.block_wave_speed[b]:.3g} m/s", block=True)
        escaped = 0
        if sim.fluid is not None and len(x):
            f = sim.fluid
            bad = ~(np.isfinite(x).all(1) & np.isfinite(v).all(1))
            if bad.any():
                i = int(np.argmax(bad))
                self._fail(f"fluid particle {i} at {_fmt(x[i])} has a NaN/inf position or velocity")
            d = x.shape[1]
            lo = f.domain_lo[:d] - 2 * f.support_radius
            hi = f.domain_hi[:d] + 2 * f.support_radius
            inside = np.all((x >= lo) & (x <= hi), axis=1)
            escaped = int((~inside).sum())
            speed = np.linalg.norm(v, axis=1)
            limit = SPEED_FACTOR * f.sound_speed
            # an escaped particle keeps falling: allow it the free-fall speed gained below the domain's top
            allowed = limit + np.where(inside, 0.0, np.sqrt(2.0 * self.g * np.maximum(0.0, hi[self.up] - x[:, self.up])))
            if (speed > allowed).any():
                i = int(np.argmax(speed - allowed))
                self._fail(f"fluid particle {i} at {_fmt(x[i])} moves at {speed[i]:.3g} m/s (> {SPEED_FACTOR:g} c0 = {limit:.3g} m/s)")
            if escaped > ESCAPE_FRACTION * len(x):
                i = int(np.argmax(~inside))
                self._fail(f"{escaped} of {len(x)} fluid particles left the domain {_fmt(lo)}..{_fmt(hi)} "
                           f"(e.g. particle {i} at {_fmt(x[i])})")
        if escaped and not self.warned_escape:
            import warnings

            warnings.warn(f"t = {sim.time:.4g} s: {escaped} fluid particle(s) left the domain; they are counted "
                          f"(particles_outside_domain in run.json), not fatal", stacklevel=2)
            self.warned_escape = True
        self.escaped = escaped
        if self.g > 0 or self.energy_scale > 0:
            e, where = self._energy(x if sim.fluid is not None and sim.fluid.n_fluid else None, v)
            if self.prev_energy is not None and e - self.prev_energy > ENERGY_JUMP * self.energy_scale:
                self._fail(f"the mechanical energy jumped from {self.prev_energy:.4g} J to {e:.4g} J in one frame "
                           f"(scale {self.energy_scale:.3g} J); most energetic: {where}",
                           block=where.startswith("block"))
            self.prev_energy = e
        return escaped
