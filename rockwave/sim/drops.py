"""Drop scenes (the zero-gravity and elliptical drops): a Simulation whose water is cut to a disc or ball
about the origin, with a given velocity and pressure field (scene regions are boxes)."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from rockwave.build.builder import seed_particles
from rockwave.build.options import boundary_lattice, fluid_parameters
from rockwave.sim.simulation import Simulation
from rockwave.sph.fluid import Density, FluidSolver, build_fluid_model, density_for_pressure
from rockwave.sph.ghost import GhostFluidSolver


def drop_simulation(scene, radius: float, velocity=None, device: str | None = None, pressure=None, options=None):
    """A Simulation of the scene's fluid cut to a disc (2D) or ball (3D) of ``radius`` about the
    origin, for the drop scenes (scene regions are boxes). ``velocity(x) -> (n, 3)`` sets the initial
    velocities (default: at rest). Continuity density starts at rho0, or, with ``pressure(x) -> (n,)``
    [Pa], at the density that the EOS maps to that pressure; summation recomputes it. ``options``:
    rockwave.sim.simulation.SimulationOptions."""
    sim = Simulation(scene, device=device, options=options)
    with wp.ScopedDevice(sim.device):
        xf, _, _, xb = seed_particles(scene, sim.device)
        xf = xf[np.linalg.norm(xf, axis=1) < radius]
        vf = np.zeros_like(xf) if velocity is None else np.asarray(velocity(xf), float)
        bstep, layers = boundary_lattice(scene)
        sim.fluid = build_fluid_model(xf, vf, xb, fluid_parameters(scene.fluid), scene.dim, scene.gravity.acceleration_m_s2,
                                      sim.device, bstep, layers)
        old = sim.fluid_solver
        if scene.fluid.method == "ghost":
            sim.fluid_solver = GhostFluidSolver(sim.fluid, options=old.options, ghost_options=old.ghost_options)
        else:
            sim.fluid_solver = FluidSolver(sim.fluid, options=old.options)
        sim.state = sim.fluid.state()
        if sim.fluid.density is Density.SUMMATION:
            sim.fluid_solver.compute_density(sim.state)
        elif pressure is not None:
            sim.fluid_solver.set_density(sim.state, density_for_pressure(sim.fluid.params, np.asarray(pressure(xf), float)))
    return sim


def elliptical_drop_simulation(scene, device: str | None = None, a0: float = 100.0):
    """Monaghan's (1994) elliptical drop: the unit disc with u = -a0 x, v = +a0 y and the exact
    initial pressure p = rho0 a0^2 (1 - x^2 - y^2)/2 (incompressible Euler for this flow at t = 0,
    where dA/dt = A^2 (a^4 - b^4)/(a^4 + b^4) = 0), as density through the inverse EOS."""
    rho0 = scene.fluid.rest_density_kg_m3
    return drop_simulation(
        scene, 1.0, device=device,
        velocity=lambda x: np.stack([-a0 * x[:, 0], a0 * x[:, 1], np.zeros(len(x))], axis=1),
        pressure=lambda x: 0.5 * rho0 * a0**2 * np.maximum(1.0 - x[:, 0] ** 2 - x[:, 1] ** 2, 0.0))


def ellipse_semi_axes(x: np.ndarray) -> tuple[float, float]:
    """Semi-axes of the uniform ellipse with the particles' second moments: <x^2> = a^2/4, <y^2> = b^2/4
    (equal-mass particles; centred drop). Less sensitive than max |x| to a single particle at the tip."""
    return 2.0 * math.sqrt(float(np.mean(x[:, 0] ** 2))), 2.0 * math.sqrt(float(np.mean(x[:, 1] ** 2)))
