"""Blow-up guard: checks the state after every frame and stops a run that has gone unstable.

Fatal (a :class:`BlowUpError` giving step, time, where, and a suggested time step):
- a NaN or inf in any fluid particle's position or velocity, or any block's pose or velocity;
- a fluid particle faster than ``SPEED_FACTOR`` x the speed of sound c0 (plus free fall, outside the domain);
- a block faster than its bar wave speed sqrt(E / rho) (linear speed, or spin x bounding radius);
- more than ``ESCAPE_FRACTION`` of the water outside the domain (the water flew apart);
- the mechanical energy (kinetic + gravitational, water and blocks) rising between two frames by
  more than ``ENERGY_JUMP`` x its scale (total mass x |g| x domain height + initial kinetic energy).

Leaks (a box tank): each fluid particle that has left the tank is counted once, exactly (per
particle, at the frames), as either thrown over the open top (it was above the walls' top: a
splash, not fatal) or gone through a wall or the floor (never above the top). :attr:`HealthGuard.left`
is the one count of particles outside the tank that the run loop writes to run.json
(``particles_outside_domain``) and the CLI prints; a warning names the split when the first ones
leave. More than ``LEAK_FRACTION`` of the water through the walls is fatal (:class:`LeakError`),
naming the key to change. Without a box tank, the count is of particles outside the domain.
Particles outside keep falling: their speed limit is raised by the free-fall speed
sqrt(2 g depth below the domain's top).

The advice of a blow-up names what fixes it: a speed of sound below 10 x the expected flow speed
u_max ~ sqrt(2 g H) (H: the water's initial height) is raised first (a smaller time step does not
cure a too-compressible fluid); otherwise a smaller time step (cfl_number, block_dt_safety or dt_s).
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from rockwave.build.options import boundary_lattice, gravity_norm
from rockwave.dda.blocks import DEFAULT_YOUNGS_MODULUS
from rockwave.sim.energy import fmt_growth
from rockwave.sph.fluid import SOUND_SPEED_FACTOR, expected_flow_speed

SPEED_FACTOR = 5.0
ESCAPE_FRACTION = 0.5
ENERGY_JUMP = 0.5
LEAK_FRACTION = 0.02  # of the water through the tank walls: fatal above


class BlowUpError(RuntimeError):
    """Raised (as a SimulationError) by the guard; ``step``, ``time``, ``suggested_dt`` (None when a smaller
    step is not the cure), ``key`` (the scene key to change)."""


class LeakError(BlowUpError):
    """More than LEAK_FRACTION of the water left through the tank walls."""


def _fmt(p) -> str:
    return "[" + ", ".join(f"{float(c):.4g}" for c in p) + "]"


class HealthGuard:
    def __init__(self, sim):
        self.sim = sim
        s = sim.scene
        self.g = gravity_norm(s)
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
            E = np.array([sp.youngs_modulus or DEFAULT_YOUNGS_MODULUS for sp in m.specs])
            rho = np.array([sp.density for sp in m.specs])
            self.block_wave_speed = np.sqrt(E / rho)
        height = (hi - lo) if hi > lo else 1.0
        self.energy_scale = mass * self.g * height
        self.energy_scale += self._energy()[0]  # initial kinetic + potential above the floor
        self._init_water_and_tank()

    def _init_water_and_tank(self) -> None:
        """Expected flow speed u_max = sqrt(2 g H) + initial speed (H: the water's height above the
        floor) and the box tank's walls for the leak count."""
        sim, s = self.sim, self.sim.scene
        self.flow_speed, self.water_height, self.sound_speed = 0.0, 0.0, None
        self.tank = None
        self.left_wall = self.left_top = self.above_top = None
        self.left = 0
        if sim.fluid is None or not sim.fluid.n_fluid:
            return
        x, v = sim.positions(), sim.velocities()
        floor = float(x[:, self.up].min()) - 0.5 * sim.fluid.spacing
        t = s.tank
        if t is not None and t.get("box_min_m") is not None:
            bstep, layers = boundary_lattice(s)  # the builder's walls (rockwave/build/options.py)
            lo, hi = np.asarray(t.box_min_m, float), np.asarray(t.box_max_m, float)
            # a particle has left once it is past the walls' outer faces
            self.tank = (lo - layers * bstep, hi + layers * bstep, hi[self.up], bool(t.open_top))
            floor = min(floor, float(lo[self.up]))
            n = len(x)
            self.left_wall = np.zeros(n, bool)
            self.left_top = np.zeros(n, bool)
            self.above_top = np.zeros(n, bool)
        self.water_height = max(float(x[:, self.up].max()) + 0.5 * sim.fluid.spacing - floor, 0.0)
        v0 = float(np.sqrt((v * v).sum(axis=1)).max()) if len(v) else 0.0
        self.flow_speed = expected_flow_speed(self.g, self.water_height, v0)
        self.sound_speed = float(sim.fluid.sound_speed)

    def _sound_speed_advice(self) -> str | None:
        """'set fluid.eos.speed_of_sound_m_s >= ...' when c0 < SOUND_SPEED_FACTOR (10) u_max, else None."""
        c0, u = self.sound_speed, self.flow_speed
        if c0 is None or not u > 0 or c0 >= SOUND_SPEED_FACTOR * u:
            return None
        return (f"the speed of sound c0 = {c0:.3g} m/s is below 10 x the expected flow speed u_max ~ sqrt(2 g H) = {u:.3g} m/s "
                f"(H = {self.water_height:.3g} m of water): the water is too compressible and a smaller time step does not "
                f"help; set fluid.eos.speed_of_sound_m_s >= {SOUND_SPEED_FACTOR * u:.3g}")

    def _count_leaks(self, x: np.ndarray) -> tuple[int, int]:
        """(through the walls, over the open top), counted once per particle since the start."""
        if self.tank is None or self.left_wall is None or len(self.left_wall) != len(x):
            return 0, 0
        lo, hi, top, open_top = self.tank
        d, up = x.shape[1], self.up
        lo, hi = lo[:d], hi[:d]
        side = [a for a in range(d) if a != up]
        self.above_top |= x[:, up] > top
        out_side = np.any((x[:, side] < lo[side]) | (x[:, side] > hi[side]), axis=1)
        below = x[:, up] < lo[up]
        lid = (x[:, up] > hi[up]) if not open_top else np.zeros(len(x), bool)
        over = out_side & open_top & (self.above_top | (x[:, up] > top)) & ~below
        through = (below | lid | (out_side & ~over)) & ~self.left_top
        self.left_top |= over & ~self.left_wall
        self.left_wall |= through
        return int(self.left_wall.sum()), int(self.left_top.sum())

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
        sound = None if block else self._sound_speed_advice()
        new = None
        if sound is not None:
            advice, key = sound, "fluid.eos.speed_of_sound_m_s"
        elif isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0:
            new = 0.5 * dt
            if sim.fixed:
                key, how = "simulation.dt_s", f"simulation.dt_s = {new:.3g}"
            elif block:
                key, how = "simulation.block_dt_safety", f"simulation.block_dt_safety = {0.5 * s.block_dt_safety:.3g}"
            else:
                key, how = "simulation.cfl_number", f"simulation.cfl_number = {0.5 * s.cfl_number:.3g}"
            advice = f"suggested time step {new:.3g} s (now {dt:.3g} s): set {how}"
        else:
            key = "simulation.block_dt_safety" if block else "simulation.cfl_number"
            advice = f"check the scene's stiffnesses and {key}"
        err = BlowUpError(f"blow-up at step {sim.steps}, t = {sim.time:.6g} s: {what}; {advice}")
        err.step, err.time, err.suggested_dt, err.key = sim.steps, sim.time, new, key
        raise err

    def _leak_fail(self, through: int, n: int) -> None:
        sim = self.sim
        advice = self._sound_speed_advice()
        if advice is not None:
            key = "fluid.eos.speed_of_sound_m_s"
        else:
            t = sim.scene.tank
            key = "tank.layers"
            layers = t.layers or "the default"
            advice = (f"the walls are too thin for the pressure: set tank.layers above {layers} "
                      f"(or a smaller tank.boundary_spacing_ratio)")
        err = LeakError(f"{through} of {n} fluid particles ({100.0 * through / n:.3g}%) left through the tank walls by "
                        f"t = {sim.time:.6g} s (step {sim.steps}; more than {100 * LEAK_FRACTION:g}% is fatal): {advice}")
        err.step, err.time, err.suggested_dt, err.key = sim.steps, sim.time, None, key
        raise err

    def check_energy(self, budget, row: dict) -> bool:
        """The energy budget's check (rockwave/sim/energy.py) on a frame's row: growth beyond the input work by more
        than ENERGY_GROWTH_LIMIT of the scene's releasable energy warns once (``simulation.energy_check = "warn"``,
        the default) or stops the run as a blow-up (``"error"``). Returns whether the row is within the bound."""
        mode = self.sim.scene.simulation.get("energy_check", "warn")
        if mode == "off" or not budget.exceeded(row):
            return True
        what = fmt_growth(budget, row)
        if mode == "error":
            err = BlowUpError(f"energy created at step {self.sim.steps}, {what} (simulation.energy_check = 'error')")
            err.step, err.time, err.suggested_dt, err.key = self.sim.steps, self.sim.time, None, "simulation.energy_check"
            raise err
        if not getattr(self, "warned_energy", False):
            warnings.warn(f"{what}; not fatal (simulation.energy_check = 'error' stops the run)", stacklevel=2)
            self.warned_energy = True
        return False

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
            through = over = None
            if self.tank is not None:
                through, over = self._count_leaks(x)
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
            if through is not None:
                if through > LEAK_FRACTION * len(x):
                    self._leak_fail(through, len(x))
                escaped = through + over
        if escaped and not self.warned_escape:
            import warnings

            split = (f" ({through} through the tank walls, {over} thrown over the open top)"
                     if self.tank is not None and through is not None else "")
            warnings.warn(f"t = {sim.time:.4g} s: {escaped} fluid particle(s) have left the tank so far{split}; not fatal "
                          f"(through the walls: up to {100 * LEAK_FRACTION:g}% of the water); the final count is "
                          f"particles_outside_domain in run.json and on the 'done' line", stacklevel=2)
            self.warned_escape = True
        self.escaped = self.left = escaped
        if self.g > 0 or self.energy_scale > 0:
            e, where = self._energy(x if sim.fluid is not None and sim.fluid.n_fluid else None, v)
            if self.prev_energy is not None and e - self.prev_energy > ENERGY_JUMP * self.energy_scale:
                self._fail(f"the mechanical energy jumped from {self.prev_energy:.4g} J to {e:.4g} J in one frame "
                           f"(scale {self.energy_scale:.3g} J); most energetic: {where}",
                           block=where.startswith("block"))
            self.prev_energy = e
        return escaped
