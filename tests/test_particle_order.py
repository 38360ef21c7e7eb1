"""Particle reordering by cell (FluidSolver.reorder / unsort) and stepping in chunks
(Simulation.step_many; CUDA graphs on a GPU): same physics, original ids on output."""

import numpy as np
import pytest
import warp as wp

import rockwave
from rockwave.scene import load_scene

from conftest import DEVICE
from helpers import ROOT


def _sim(spacing=0.08, continuity=False):
    scene = load_scene(ROOT / "scenes" / "dam_break_3d.toml")
    scene.fluid["spacing_m"] = spacing
    if continuity:
        scene.fluid["density"] = "continuity"
    scene.output["gauges"] = []
    return rockwave.Simulation(scene, device=DEVICE)


def test_reorder_is_a_permutation_and_unsort_restores_it():
    sim = _sim()
    for _ in range(5):
        sim.step()
    x0 = sim.state.x.numpy().copy()
    v0 = sim.state.v.numpy().copy()
    fs, nf = sim.fluid_solver, sim.n_fluid
    with wp.ScopedDevice(sim.device):
        fs.reorder(sim.state)
    ids = sim.state.ids.numpy()
    assert sorted(ids.tolist()) == list(range(nf))
    assert not np.array_equal(ids, np.arange(nf))  # the seeding order is not the cell order
    x1 = sim.state.x.numpy()
    assert np.array_equal(x1[:nf], x0[ids]) and np.array_equal(x1[nf:], x0[nf:])  # boundary untouched
    assert np.array_equal(sim.state.v.numpy()[:nf], v0[ids])
    assert np.allclose(sim.positions(), x0[:nf, :3])  # reads restore the original order
    assert np.array_equal(sim.state.ids.numpy(), np.arange(nf))


@pytest.mark.parametrize("continuity", [False, True])
def test_step_many_matches_single_steps(continuity):
    a, b = _sim(continuity=continuity), _sim(continuity=continuity)
    for _ in range(25):
        a.step()
    b.step_many(25)  # two reorder chunks of 10 and 5 single steps
    assert b.steps == 25 and b.time == pytest.approx(a.time)
    s = a.fluid.spacing
    assert np.abs(b.positions() - a.positions()).max() < 1e-3 * s  # summation order only
    assert np.abs(b.densities() - a.densities()).max() < 1e-2
    assert b.pressures() == pytest.approx(a.pressures(), rel=1e-3, abs=1.0)


def test_boundary_particles_are_in_cell_order():
    sim = _sim()
    xb = sim.boundary_positions()
    H = sim.fluid.support_radius
    c = np.floor((xb - xb.min(axis=0)) / H).astype(int)
    key = (c[:, 2] * 10000 + c[:, 1]) * 10000 + c[:, 0]
    assert np.all(np.diff(key) >= 0)
