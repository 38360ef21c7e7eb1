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


@wp.func
def substep_of(plan: wp.array(dtype=wp.vec4d), k: int, i: int):
    """Scenario k's i-th block sub-step: (its end time, its length), or (its time, 0) past its own count. plan[k] =
    (time, sub-step length h, sub-step count n, step dt), float64 as the host's clock; t = time + i h + h, the solo
    clock's sum in the same order."""
    p = plan[k]
    if wp.float64(i) < p[2]:
        h = p[1]
        return wp.vec2d(p[0] + wp.float64(i) * h + h, h)
    return wp.vec2d(p[0], wp.float64(0.0))


@wp.kernel
def scenario_steps(plan: wp.array(dtype=wp.vec4d), out: wp.array(dtype=float)):
    """out[k] = scenario k's step, rounded to float32 as the solo clock's dt array."""
    k = wp.tid()
    out[k] = float(plan[k][3])


@wp.kernel
def block_clocks(i: int, plan: wp.array(dtype=wp.vec4d), owner: wp.array(dtype=int), out: wp.array(dtype=float)):
    """Each block's clock (kernels/dda/blocks.py clock_of: end time, length, locked flag) for the batch's i-th block
    sub-step, from its scenario's plan; length 0 once its scenario has taken its own sub-steps."""
    b = wp.tid()
    s = substep_of(plan, owner[b], i)
    out[3 * b] = float(s[0])
    out[3 * b + 1] = float(s[1])
    out[3 * b + 2] = 0.0


@wp.kernel
def idle_kinds(i: int, plan: wp.array(dtype=wp.vec4d), owner: wp.array(dtype=int), kinds: wp.array(dtype=int),
               fixed: int, out: wp.array(dtype=int)):
    """A block's kind while its scenario takes the i-th sub-step, else ``fixed`` (left out of the planar projection)."""
    b = wp.tid()
    out[b] = kinds[b]
    if substep_of(plan, owner[b], i)[1] == wp.float64(0.0):
        out[b] = fixed
