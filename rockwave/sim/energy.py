"""The energy budget of a run: what water and rock hold, what moving walls put in, and whether the total grew.

Every output frame (rockwave/output/recorders.py EnergyRecorder; energy.csv, run.json "energy") the budget reads:

- water: kinetic 1/2 m v^2, potential m |g| h (h: height above the lowest start point of water or rock, along
  gravity) and elastic, the equation of state's stored energy m e(rho) with e = int_rho0^rho p/r^2 dr (Tait:
  B/rho0 ((r^(g-1) - 1)/(g-1) + 1/r - 1), linear: k (ln r + 1/r - 1), r = rho/rho0; 0 below rho0 when negative
  pressures are clamped);
- rock (rigid and deformable blocks; a compound block once): kinetic (translation, rotation, strain rate),
  potential, elastic (the contact springs 1/2 F_n delta at each contact point of the last step, the strain
  energy 1/2 eps.K.eps of deformable blocks);
- coupling: the penalty springs 1/2 K_s (d0 - dist)^2 of the particles within the contact distance of a block;
- input: the work of kinematic blocks (pistons, paddles) on the water, through the penalty and their wall
  particles, summed on the device every step (rockwave/coupling/penalty.py wall_work).

2D scenes are per metre of depth: the water's energies are, and each block's are divided by its z-extent (the
coupling gives a block the water's per-metre force times that extent, so this is the pair's common measure).

``growth`` = total - total at the start - input work: what no mechanism accounts for. Dissipation (artificial
viscosity, the contact dashpots, friction, density diffusion) makes it negative; a positive growth beyond
round-off is energy the numerics created. The guard (rockwave/sim/guard.py) warns, or stops with
``simulation.energy_check = "error"``, when it exceeds ENERGY_GROWTH_LIMIT of the budget's scale (the energy the
scene can release: its moving mass falling through its height, plus the start's kinetic energy). Not accounted:
the work of kinematic blocks on other blocks through DDA contacts (``input_complete`` is then False and the check
is left open).
"""

from __future__ import annotations

import numpy as np

from rockwave.base.maths import quat_to_matrix
from rockwave.coupling.penalty import block_signed_distance

ENERGY_GROWTH_LIMIT = 0.01  # of the budget's scale: growth above it is reported (and fatal with energy_check = "error")

COLUMNS = ["time_s", "water_kinetic_j", "water_potential_j", "water_elastic_j", "rock_kinetic_j", "rock_potential_j",
           "rock_elastic_j", "coupling_elastic_j", "input_work_j", "total_j", "growth_j"]


def eos_energy(rho: np.ndarray, params) -> np.ndarray:
    """Stored energy per unit mass e(rho) = int_rho0^rho p(r)/r^2 dr of the scene's equation of state [J/kg]."""
    rho0 = float(params.rest_density)
    r = np.asarray(rho, np.float64) / rho0
    B = float(params.eos_b)
    if int(params.eos) == 0:  # Tait: p = B (r^gamma - 1)
        g = float(params.eos_gamma)
        e = (B / rho0) * ((r ** (g - 1.0) - 1.0) / (g - 1.0) + 1.0 / r - 1.0)
    else:  # linear: p = k (rho - rho0)
        e = B * (np.log(r) + 1.0 / r - 1.0)
    if int(getattr(params, "clamp_negative", 0)):
        e = np.where(r > 1.0, e, 0.0)
    return e


class EnergyBudget:
    """The energy budget of a Simulation (module docstring). ``measure(x, v, rho)`` -> one row (dict of COLUMNS);
    ``summary()`` -> run.json's "energy"."""

    def __init__(self, sim):
        self.sim = sim
        s = sim.scene
        self.dim = s.dim
        g = np.asarray(list(s.gravity.acceleration_m_s2) + [0.0] * (3 - s.dim), float)
        self.g = float(np.linalg.norm(g))
        self.up_dir = -g / self.g if self.g > 0 else np.zeros(3)
        self.units = "J" if s.dim == 3 else "J/m"
        f = sim.fluid
        self.has_water = f is not None and f.n_fluid > 0
        m = sim.blocks
        self.blocks = m
        heights = []
        if self.has_water:
            self.water_mass = f.particle_mass.numpy()[: f.n_fluid].astype(np.float64)
            heights.append(float((np.asarray(f.initial_positions, float)[: f.n_fluid] @ self.up_dir).min()))
        if m is not None:
            self.rock = np.nonzero(m.movable & m.lead)[0]
            depth = np.ones(m.num_blocks)
            if s.dim == 2:
                for b, spec in enumerate(m.specs):
                    v = np.asarray(spec.geometry.vertices, float) @ quat_to_matrix(np.asarray(spec.orientation, float)).T
                    depth[b] = float(v[:, 2].max() - v[:, 2].min())
            self.per_depth = 1.0 / depth
            if len(self.rock):
                heights.append(float((m.base_position[self.rock] @ self.up_dir - m.np["radius"][self.rock]).min()))
            self.rock_depth = float(np.median(depth[self.rock])) if len(self.rock) else 1.0
            kinds = m.np["kinds"]
            self.input_complete = not (np.any(kinds == 3) and len(self.rock))  # kinematic blocks touching blocks
        else:
            self.rock = np.zeros(0, int)
            self.input_complete = True
        self.h0 = min(heights) if heights else 0.0
        self.input_work = 0.0
        self.start = None
        self.last = None
        self.max_growth = 0.0
        self.max_growth_time = 0.0
        self.scale = None

    # ------------------------------------------------------------------------------------------------
    def _input_work(self) -> float:
        c = self.sim.coupling
        if c is None:
            return self.input_work
        self.input_work += c.take_wall_work()
        return self.input_work

    def _water(self, x, v, rho) -> tuple[float, float, float]:
        m = self.water_mass
        n = len(m)
        x = np.asarray(x, np.float64)[:n]
        v = np.asarray(v, np.float64)[:n]
        d = x.shape[1]
        ke = 0.5 * float((m * (v * v).sum(axis=1)).sum())
        pe = self.g * float((m * (x @ self.up_dir[:d] - self.h0)).sum())
        el = float((m * eos_energy(np.asarray(rho, np.float64)[:n], self.sim.fluid.params)).sum()) if rho is not None else 0.0
        return ke, pe, el

    def _rock(self) -> tuple[float, float, float]:
        m, st = self.blocks, self.sim.block_state
        if m is None or not len(self.rock):
            return 0.0, 0.0, 0.0
        x, v, w = st.positions_numpy(), st.velocities_numpy(), st.angular_velocities_numpy()
        q = st.orientations_numpy()
        mass, inertia, kinds = m.np["mass"], m.np["inertia"], m.np["kinds"]
        ke = pe = el = 0.0
        deformable = np.any(kinds[self.rock] == 1)
        if deformable:
            sr = st.strain_rate.numpy().astype(np.float64)
            eps = st.strain.numpy().astype(np.float64)
            sk = m.strain_k.numpy().astype(np.float64)
        for b in self.rock:
            R = quat_to_matrix(q[b])
            k = 0.5 * mass[b] * v[b] @ v[b] + 0.5 * w[b] @ (R @ inertia[b] @ R.T) @ w[b]
            e = 0.0
            if kinds[b] == 1:
                k += 0.5 * sr[b] @ m.strain_mass[b] @ sr[b]
                e += 0.5 * eps[b] @ sk[b] @ eps[b]
            ke += k * self.per_depth[b]
            pe += mass[b] * self.g * (x[b] @ self.up_dir - self.h0) * self.per_depth[b]
            el += e * self.per_depth[b]
        t = st.tables[0]
        n = int(t["pcount"].numpy()[0])
        if n:
            fn = t["fn"].numpy()[:n].astype(np.float64)
            dep = t["depth"].numpy()[:n].astype(np.float64)
            el += 0.5 * float((np.maximum(fn, 0.0) * np.maximum(dep, 0.0)).sum()) / self.rock_depth
        return ke, pe, el

    def _coupling(self, x) -> float:
        c = self.sim.coupling
        if c is None or not self.has_water:
            return 0.0
        n = len(self.water_mass)
        pts = np.zeros((n, 3))
        xx = np.asarray(x, np.float64)[:n]
        pts[:, : xx.shape[1]] = xx
        dist, which = block_signed_distance(self.blocks, self.sim.block_state, pts)
        tank = np.array([bool(s.tank) for s in self.blocks.specs])
        pen = np.where(tank[which], 0.0, np.maximum(c.d0 - dist, 0.0))
        return 0.5 * c.k_s * float((pen * pen).sum())

    def measure(self, x=None, v=None, rho=None) -> dict:
        """One row of the budget now (x, v, rho: the frame's host copies of the fluid; read here when None)."""
        sim = self.sim
        row = dict.fromkeys(COLUMNS, 0.0)
        row["time_s"] = float(sim.time)
        if self.has_water:
            if x is None:
                x, v, rho = sim.positions(), sim.velocities(), sim.densities()
            row["water_kinetic_j"], row["water_potential_j"], row["water_elastic_j"] = self._water(x, v, rho)
            row["coupling_elastic_j"] = self._coupling(x)
        row["rock_kinetic_j"], row["rock_potential_j"], row["rock_elastic_j"] = self._rock()
        row["input_work_j"] = self._input_work()
        total = sum(row[k] for k in COLUMNS[1:8])
        row["total_j"] = total
        if self.start is None:
            self.start = row
            self.scale = self._scale(row)
        row["growth_j"] = total - self.start["total_j"] - row["input_work_j"]
        if row["growth_j"] > self.max_growth:
            self.max_growth, self.max_growth_time = row["growth_j"], row["time_s"]
        self.last = row
        return row

    def resume(self, first: list, last: list, columns: list) -> None:
        """Go on after a resume: the start row and the input work so far from energy.csv's first and last rows."""
        self.start = dict(zip(columns, first))
        self.scale = self._scale(self.start)
        self.input_work = float(dict(zip(columns, last))["input_work_j"])

    def _scale(self, row: dict) -> float:
        """The energy the scene can release [J or J/m]: its water and rock falling through the scene's height (the
        start's potential energies, taken from the lowest start point) plus the start's kinetic energies."""
        e = row["water_potential_j"] + row["rock_potential_j"] + row["water_kinetic_j"] + row["rock_kinetic_j"]
        return max(e, 1e-12)

    @property
    def limit(self) -> float:
        return ENERGY_GROWTH_LIMIT * (self.scale or 0.0)

    def exceeded(self, row: dict) -> bool:
        return self.input_complete and row["growth_j"] > self.limit

    def summary(self) -> dict:
        """run.json's "energy": units, the start and end rows, the input work, the largest growth and the check."""
        if self.start is None:
            return {}
        end = self.last
        check = ("open: kinematic blocks do work on blocks through contacts, not accounted" if not self.input_complete
                 else "exceeded" if self.max_growth > self.limit else "ok")
        return {
            "units": self.units,
            "start": self.start,
            "end": end,
            "input_work_j": end["input_work_j"],
            "dissipated_j": self.start["total_j"] + end["input_work_j"] - end["total_j"],
            "max_growth_j": self.max_growth,
            "max_growth_time_s": self.max_growth_time,
            "scale_j": self.scale,
            "limit_j": self.limit,
            "max_growth_fraction": self.max_growth / self.scale if self.scale else 0.0,
            "check": check,
        }


def fmt_growth(b: EnergyBudget, row: dict) -> str:
    u = b.units
    return (f"t = {row['time_s']:.4g} s: the energy budget grew by {row['growth_j']:.4g} {u} beyond the input work "
            f"({100.0 * row['growth_j'] / b.scale:.3g}% of the scene's releasable energy {b.scale:.4g} {u}, limit "
            f"{100 * ENERGY_GROWTH_LIMIT:g}%): water kinetic {row['water_kinetic_j']:.4g}, rock kinetic "
            f"{row['rock_kinetic_j']:.4g} {u}; energy.csv has the components")

