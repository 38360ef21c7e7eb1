"""Hazard kernels of a batch of scenarios (rockwave/output/batch.py BatchHazard): the height-gauge lines, run-up
columns and crossings of every scenario in one launch each, a particle counted only on its own scenario's lines
(its scenario: scenario[ids[j]], ids the seeded index of the particle in slot j)."""

import warp as wp

from rockwave.kernels.sim.readers import column_sample, column_top, crossing_sample, line_add, speed_sample, wave_sample
from rockwave.kernels.sph.fluid import SPHParams

wp.set_module_options({"enable_backward": False})


@wp.kernel
def batch_line_profile(
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    ids: wp.array(dtype=int),
    scenario: wp.array(dtype=int),
    line_first: wp.array(dtype=int),
    line_count: wp.array(dtype=int),
    line_pos: wp.array(dtype=wp.vec3),
    line_z0: wp.array(dtype=float),
    line_dz: wp.array(dtype=float),
    up: int,
    p: SPHParams,
    prof: wp.array2d(dtype=float),
):
    """phi_f(z_k) = sum_j V_j W along each line of the particle's own scenario (launched over fluid particles x the
    most lines of a scenario; rockwave/kernels/sim/readers.py gauge_fluid_profile per scenario)."""
    j, g = wp.tid()
    k = scenario[ids[j]]
    if k < 0 or g >= line_count[k]:
        return
    row = line_first[k] + g
    line_add(x[j], particle_mass[j] / rho[j], line_pos[row], up, line_z0[row], line_dz[row], p, prof, row)


@wp.kernel
def batch_line_level(
    fluid: wp.array2d(dtype=float),
    solid: wp.array2d(dtype=float),
    moving: wp.array2d(dtype=float),
    has_moving: int,
    n_samples: wp.array(dtype=int),
    z0: wp.array(dtype=float),
    dz: wp.array(dtype=float),
    reach: wp.array(dtype=int),
    out: wp.array(dtype=float),
):
    """The top of the continuous water column on each line with its own samples (readers.py gauge_level)."""
    g = wp.tid()
    out[g] = column_top(fluid, solid, moving, has_moving, g, n_samples[g], z0[g], dz[g], reach[g])


@wp.kernel
def gather(src: wp.array(dtype=float), index: wp.array(dtype=int), out: wp.array(dtype=float)):
    """out[i] = src[index[i]]."""
    i = wp.tid()
    out[i] = src[index[i]]


@wp.kernel
def batch_side_volume(
    x: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    particle_mass: wp.array(dtype=float),
    ids: wp.array(dtype=int),
    scenario: wp.array(dtype=int),
    cross_first: wp.array(dtype=int),
    cross_count: wp.array(dtype=int),
    point: wp.array(dtype=wp.vec3),
    normal: wp.array(dtype=wp.vec3),
    vol: wp.array(dtype=float),
):
    """vol[l] += m_j / rho_j for the particles of line l's scenario on its positive side (readers.py
    hazard_side_volume per scenario; launched over fluid particles x the most crossings of a scenario)."""
    j, c = wp.tid()
    k = scenario[ids[j]]
    if k < 0 or c >= cross_count[k]:
        return
    l = cross_first[k] + c
    if wp.dot(x[j] - point[l], normal[l]) > 0.0:
        wp.atomic_add(vol, l, particle_mass[j] / rho[j])


# Each scenario's own clock (BatchSimulation with per-scenario steps): a row is updated only when its scenario
# samples now (on[k] = 1), at its scenario's time t[k] (readers.py's updates per scenario).
@wp.kernel
def batch_wave_update(level: wp.array(dtype=float), still: wp.array(dtype=float), threshold: wp.array(dtype=float),
                      row_scenario: wp.array(dtype=int), t: wp.array(dtype=float), on: wp.array(dtype=int),
                      stats: wp.array2d(dtype=float)):
    """readers.py hazard_wave_update for the wave gauges of the scenarios that sample now."""
    g = wp.tid()
    k = row_scenario[g]
    if on[k] != 0:
        wave_sample(g, level[g], still[g], threshold[g], t[k], stats)


@wp.kernel
def batch_column_update(level: wp.array(dtype=float), row_scenario: wp.array(dtype=int), t: wp.array(dtype=float),
                        on: wp.array(dtype=int), stats: wp.array2d(dtype=float)):
    """readers.py hazard_column_update for the run-up columns of the scenarios that sample now."""
    c = wp.tid()
    k = row_scenario[c]
    if on[k] != 0:
        column_sample(c, level[c], t[k], stats)


@wp.kernel
def batch_crossing_update(vol: wp.array(dtype=float), row_scenario: wp.array(dtype=int), t: wp.array(dtype=float),
                          on: wp.array(dtype=int), stats: wp.array2d(dtype=float)):
    """readers.py hazard_crossing_update for the crossings of the scenarios that sample now."""
    l = wp.tid()
    k = row_scenario[l]
    if on[k] != 0:
        crossing_sample(l, vol[l], t[k], stats)


@wp.kernel
def batch_block_speed(v: wp.array(dtype=wp.vec3), index: wp.array(dtype=int), row_scenario: wp.array(dtype=int),
                      t: wp.array(dtype=float), on: wp.array(dtype=int), stats: wp.array2d(dtype=float)):
    """readers.py hazard_block_speed for the slides of the scenarios that stepped (each after its own steps)."""
    i = wp.tid()
    k = row_scenario[i]
    if on[k] != 0:
        speed_sample(i, wp.length(v[index[i]]), t[k], stats)
