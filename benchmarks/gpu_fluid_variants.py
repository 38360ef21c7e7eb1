"""Issue 7 experiments on the acceleration pass over neighbour lists (kept as a record of what was
tried; the solver's kernels/sph.py particle_acceleration_list took the uniform mass, p/rho^2 array,
no in-kernel fallback and 128-thread blocks from these). Each variant is timed alone on the
same sorted 3D dam-break state, results as JSON lines.

    python -m benchmarks.gpu_fluid_variants --device cuda:0 --spacing 0.0068
"""

from __future__ import annotations

import argparse
import json

import warp as wp

from benchmarks.common import device_name
from benchmarks.gpu_issue7 import _sync_time, fluid_sim
from rockwave.kernels import sph
from rockwave.kernels.sph import FORCE_MOMENTUM, SPHParams, kernel_grad, kernel_laplacian, kernel_w


@wp.func
def pair_acc_uniform(j: int, xi: wp.vec3, vi: wp.vec3, rhoi: float, pi_r2: float, x: wp.array(dtype=wp.vec3),
                     v: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float), pr2: wp.array(dtype=float),
                     particle_mass: wp.array(dtype=float), m_fluid: float, p: SPHParams):
    rij = xi - x[j]
    r2 = wp.length_sq(rij)
    r = wp.sqrt(r2)
    gw = kernel_grad(rij, r, p)
    a = wp.vec3(0.0)
    dv = wp.vec3(0.0)
    if j >= p.n_fluid:
        return -(particle_mass[j] * pi_r2) * gw, dv
    mj = m_fluid
    rhoj = rho[j]
    a = -(mj * (pi_r2 + pr2[j])) * gw
    vj = v[j]
    vij = vi - vj
    if p.mu > 0.0:
        a -= (p.mu * mj / (rhoi * rhoj) * kernel_laplacian(r, p)) * vij
    if p.alpha > 0.0:
        vr = wp.dot(vij, rij)
        if vr < 0.0:
            h_s = 0.5 * p.H
            mu_ij = h_s * vr / (r2 + 0.01 * h_s * h_s)
            a -= mj * (-p.alpha * p.sound_speed * mu_ij / (0.5 * (rhoi + rhoj))) * gw
    if p.xsph > 0.0:
        dv = -(mj / (0.5 * (rhoi + rhoj)) * kernel_w(r2, p)) * vij
    return a, dv


@wp.kernel
def acc_clamped(count: wp.array(dtype=int), nbr: wp.array(dtype=int), x: wp.array(dtype=wp.vec3),
                v: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float), pressure: wp.array(dtype=float),
                particle_mass: wp.array(dtype=float), p: SPHParams, accel: wp.array(dtype=wp.vec3),
                xsph_dv: wp.array(dtype=wp.vec3)):
    """particle_acceleration_list without the grid-query fallback (count clamped to the capacity)."""
    i = wp.tid()
    n = count.shape[0]
    xi = x[i]
    vi = v[i]
    rhoi = rho[i]
    pi = pressure[i]
    a = wp.vec3(0.0)
    dv = wp.vec3(0.0)
    c = wp.min(count[i], nbr.shape[0] // n)
    for k in range(c):
        da, ddv = sph.pair_acceleration(i, nbr[k * n + i], xi, vi, rhoi, pi, x, v, rho, pressure, particle_mass, p)
        a += da
        dv += ddv
    accel[i] = a + p.gravity
    xsph_dv[i] = p.xsph * dv


@wp.kernel
def pressure_over_rho2(rho: wp.array(dtype=float), pressure: wp.array(dtype=float), pr2: wp.array(dtype=float)):
    i = wp.tid()
    pr2[i] = pressure[i] / (rho[i] * rho[i])


@wp.kernel
def acc_uniform(count: wp.array(dtype=int), nbr: wp.array(dtype=int), x: wp.array(dtype=wp.vec3),
                v: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float), pr2: wp.array(dtype=float),
                particle_mass: wp.array(dtype=float), m_fluid: float, p: SPHParams, accel: wp.array(dtype=wp.vec3),
                xsph_dv: wp.array(dtype=wp.vec3)):
    """Clamped, uniform fluid mass (no mass gather for fluid neighbours), p/rho^2 precomputed (momentum form)."""
    i = wp.tid()
    n = count.shape[0]
    xi = x[i]
    vi = v[i]
    rhoi = rho[i]
    pi_r2 = pr2[i]
    a = wp.vec3(0.0)
    dv = wp.vec3(0.0)
    c = wp.min(count[i], nbr.shape[0] // n)
    for k in range(c):
        da, ddv = pair_acc_uniform(nbr[k * n + i], xi, vi, rhoi, pi_r2, x, v, rho, pr2, particle_mass, m_fluid, p)
        a += da
        dv += ddv
    accel[i] = a + p.gravity
    xsph_dv[i] = p.xsph * dv


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--spacing", type=float, default=0.0068)
    ap.add_argument("--reps", type=int, default=20)
    a = ap.parse_args(argv)
    wp.config.quiet = True
    d = a.device
    sim = fluid_sim(d, a.spacing)
    sim.step_many(20)
    for _ in range(3):
        sim.step()
    fs, st, m = sim.fluid_solver, sim.state, sim.fluid
    assert m.params.pressure_form == FORCE_MOMENTUM
    fs.build_cells(st)
    fs.build_neighbour_lists(st)
    n = m.n_fluid
    pr2 = wp.zeros(n, dtype=float, device=d)
    mf = float(m.particle_mass.numpy()[0])
    acc0 = wp.zeros_like(st.accel)
    rows = {}

    def base(bd=None):
        wp.launch(sph.particle_acceleration_list, dim=n, inputs=[fs._nbr_count, fs._nbr, st.x, st.v, st.rho, st.pressure,
                  fs._pr2, m.particle_mass, m.params], outputs=[st.accel, st.xsph_dv], device=d, block_dim=bd)

    variants = {
        "solver_bd256": lambda: base(256),
        "solver_bd128": lambda: base(128),
        "solver_bd64": lambda: base(64),
        "clamped": lambda: wp.launch(acc_clamped, dim=n, inputs=[fs._nbr_count, fs._nbr, st.x, st.v, st.rho, st.pressure,
                                                                m.particle_mass, m.params], outputs=[st.accel, st.xsph_dv], device=d),
        "uniform_mass_pr2": lambda: (wp.launch(pressure_over_rho2, dim=n, inputs=[st.rho, st.pressure, pr2], device=d),
                                     wp.launch(acc_uniform, dim=n, inputs=[fs._nbr_count, fs._nbr, st.x, st.v, st.rho, pr2,
                                               m.particle_mass, mf, m.params], outputs=[st.accel, st.xsph_dv], device=d)),
        "uniform_mass_pr2_bd128": lambda: (wp.launch(pressure_over_rho2, dim=n, inputs=[st.rho, st.pressure, pr2], device=d),
                                           wp.launch(acc_uniform, dim=n, inputs=[fs._nbr_count, fs._nbr, st.x, st.v, st.rho,
                                                     pr2, m.particle_mass, mf, m.params], outputs=[st.accel, st.xsph_dv],
                                                     device=d, block_dim=128)),
        "neighbour_list": lambda: fs.build_neighbour_lists(st),
        "neighbour_list_bd128": lambda: wp.launch(sph.build_neighbour_list_cells, dim=n,
                                                  inputs=[fs.cells, st.x, fs.list_radius, *fs._slot_ranges, fs._always],
                                                  outputs=[fs._nbr_count, fs._nbr, fs._x_build], device=d, block_dim=128),
        "cell_build": lambda: fs.build_cells(st),
    }
    with wp.ScopedDevice(d):
        base()
        wp.copy(acc0, st.accel)
        ref = acc0.numpy()
        for k, f in variants.items():
            f()
            t = _sync_time(f, d, a.reps)
            diff = float(abs(st.accel.numpy() - ref).max() / abs(ref).max()) if not k.startswith(("neighbour", "cell")) else 0.0
            rows[k] = dict(ms=1e3 * t, max_rel_diff=diff)
            print(json.dumps({"variant": k, **rows[k]}), flush=True)
            if not k.startswith(("neighbour", "cell")):
                wp.copy(st.accel, acc0)
    print(json.dumps({"device": device_name(d), "particles": n, "spacing_m": a.spacing}))


if __name__ == "__main__":
    main()
