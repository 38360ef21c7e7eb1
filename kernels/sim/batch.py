"""Kernels of a batch of scenarios with their own time steps (rockwave/sim/batch.py BatchSimulation): each fluid
particle's step from its scenario's, and each scenario's largest speed and acceleration (its own CFL and force
limits, kernels/sph/fluid.py motion_extrema per scenario)."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def particle_steps(ids: wp.array(dtype=int), scenario: wp.array(dtype=int), dt: wp.array(dtype=float),
                   out: wp.array(dtype=float)):
    """out[i] = dt[scenario of particle i] (ids: the seeded index of the particle now in slot i; scenario: by seeded
    index). 0 for a scenario that is not stepping: its particles stay where they are."""
    i = wp.tid()
    out[i] = dt[scenario[ids[i]]]


@wp.kernel
def scenario_motion_extrema(v: wp.array(dtype=wp.vec3), accel: wp.array(dtype=wp.vec3), ids: wp.array(dtype=int),
                            scenario: wp.array(dtype=int), out: wp.array(dtype=float)):
    """out[2 k] = max |v|^2, out[2 k + 1] = max |a|^2 over scenario k's fluid particles (zeroed by the caller)."""
    i = wp.tid()
    k = scenario[ids[i]]
    wp.atomic_max(out, 2 * k, wp.length_sq(v[i]))
    wp.atomic_max(out, 2 * k + 1, wp.length_sq(accel[i]))
