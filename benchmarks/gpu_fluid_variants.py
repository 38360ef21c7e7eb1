"""Issue 7 experiments on the acceleration pass over neighbour lists (kept as a record of what was
tried: the uniform-mass / p/rho^2 variant measured here is now the solver's kernels/sph.py
particle_acceleration_list, timed as solver_bd*; `clamped` is the general-mass pass without a fallback). Each variant is timed alone on the
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
from rockwave.kernels.sph import FORCE_MOMENTUM, SPHParams


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
