"""HostWater (rockwave/sim/readers.py): the whole water on the host, the outputs' kernels over device chunks of it.

Rank 0 of a distributed run reads its outputs from a HostWater; here one process's state is copied into one (in id
order) and every output is read both ways: from the device state in one pass and from the HostWater 37 particles at
a time (of 200). The height and pressure gauges and the dt's motion extrema add the same terms in the same order on
the CPU (the chunks follow the particle order) and agree to the bit; the force gauges (a hash grid per chunk) and the
surface field (a node's sum chunk by chunk) add them in another order: float32 round-off.
"""

from __future__ import annotations

import numpy as np
import warp as wp

import rockwave
from rockwave.output import surface as surf
from rockwave.sim.readers import Gauges, HostWater

from helpers import tank_2d

CHUNK = 37


def _scene():
    d = tank_2d(width=0.4, depth=0.1, height=0.3)
    d["fluid"]["regions"] = [{"box_min_m": [0.0, 0.0], "box_max_m": [0.2, 0.1]}]
    d["obstacles"] = [{"box_min_m": [0.2, 0.0], "box_max_m": [0.22, 0.05]}]
    d["output"] = {"gauges": [
        {"name": "level", "kind": "height", "position_m": [0.1, 0.0]},
        {"name": "bed", "kind": "pressure", "position_m": [0.05, 0.01]},
        {"name": "push", "kind": "force", "block": "obstacle.0", "direction": [1.0, 0.0]}]}
    return rockwave.parse_scene(d)


def _host_copy(sim) -> HostWater:
    m, st = sim.fluid, sim.state
    n = m.n_fluid
    mass = m.particle_mass.numpy()
    assert np.all(mass[:n] == mass[0])  # one fluid mass (HostWater's)
    host = HostWater(n, m.initial_positions[n:], mass[n:], float(mass[0]), sim.device, chunk=CHUNK)
    ids = st.ids.numpy()[:n]
    host.x[ids], host.v[ids] = st.x.numpy()[:n], st.v.numpy()[:n]
    host.rho[ids], host.pressure[ids], host.accel[ids] = st.rho.numpy(), st.pressure.numpy(), st.accel.numpy()
    host.x[n:] = st.x.numpy()[n:]
    host.wall_pressure[:] = st.wall_pressure.numpy()
    return host


def test_outputs_over_chunks_equal_one_pass():
    sim = rockwave.Simulation(_scene(), device="cpu")
    sim.advance(0.03)
    host = _host_copy(sim)
    n = sim.fluid.n_fluid
    assert n == 200 and host.chunk < n
    # a device state in id order (the one-pass reference reads the particles in the same order as the chunks)
    st = sim.state
    one = Gauges(sim.scene, sim.fluid, "cpu", sim.blocks, sim.block_state)
    chunked = Gauges(sim.scene, sim.fluid, "cpu", sim.blocks, sim.block_state, host=host)
    ref = wp.clone(st.x), wp.clone(st.rho), wp.clone(st.pressure)
    st.x.assign(host.x)
    st.rho.assign(host.rho)
    st.pressure.assign(host.pressure)
    a, b = one.read(st), chunked.read(host)
    assert a["bed"] > 100.0 and a["push"] > 1.0 and 0.05 < a["level"] < 0.11
    assert a["level"] == b["level"] and a["bed"] == b["bed"]
    assert abs(a["push"] - b["push"]) <= 1e-5 * abs(a["push"])
    # the surface: the field summed chunk by chunk
    ex = surf.extractor_for(sim.scene, sim.fluid, "cpu")
    lo, hi = host.x[:n].min(axis=0), host.x[:n].max(axis=0)
    m1 = ex.extract(st.x[:n], st.rho, lo, hi)
    m2 = ex.extract_parts(((c["x"], c["rho"]) for _, c in host.fluid_chunks(("x", "rho"))), lo, hi)
    assert len(m1.points) > 20 and m1.points.shape == m2.points.shape
    assert np.abs(m1.points - m2.points).max() <= 1e-6  # m
    # dt's extrema (max |v|^2, |a|^2): a maximum, exact in any order
    v2 = (st.v.numpy()[:n].astype(np.float64) ** 2).sum(axis=1).max()
    got = host.motion_extrema()
    assert abs(got[0] - v2) <= 1e-6 * v2 and got[1] > 0.0
    for arr, keep in zip((st.x, st.rho, st.pressure), ref):
        arr.assign(keep)
    # the device holds chunk buffers only: none as long as the water
    assert all(b.shape[0] == CHUNK for b in host._dev.values())
