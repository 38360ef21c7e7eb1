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


def _random_model(dim, monkeypatch, wrapped, n_side=7):
    from rockwave.fluid import FluidSolver, build_fluid_model
    from test_sph import _fluid_section
    from rockwave.sampling import box_lattice

    rng = np.random.default_rng(3)
    fl = _fluid_section("muller", dim, density="summation", clamp_negative_pressure=False,
                        viscosity={"artificial_alpha": 0.2, "laplacian_pa_s": 0.5, "xsph_epsilon": 0.05})
    s = fl["spacing_m"]
    x = box_lattice([0.0] * dim, [n_side * s] * dim, s)
    x = x + rng.normal(0, 0.2 * s, x.shape)
    x = np.concatenate([x, np.zeros((len(x), 3 - dim))], axis=1)
    xb = box_lattice([0.0] * dim, [n_side * s, 2 * s] + [n_side * s] * (dim - 2), s)  # a wall layer
    xb = np.concatenate([xb, np.zeros((len(xb), 3 - dim))], axis=1)
    xb[:, 1] -= 2.5 * s
    if wrapped:  # force the cell grid to wrap (hash) in every dimension
        monkeypatch.setattr(FluidSolver, "min_cells", 16)
        monkeypatch.setattr(FluidSolver, "cells_per_particle", 0)
    model = build_fluid_model(x, rng.normal(0, 0.5, x.shape) * ([1] * dim + [0] * (3 - dim)), xb, fl, dim,
                              [0.0] * dim, DEVICE)
    solver = FluidSolver(model)
    return model, solver


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("wrapped", [False, True])
def test_neighbour_lists_match_brute_force(dim, wrapped, monkeypatch):
    """The cell grid (x-cells H/4, y/z cells H, culled column runs; wrapped like a hash grid when the
    domain needs too many cells) finds exactly the particles within H of each fluid particle, fluid
    and boundary, self excluded."""
    model, solver = _random_model(dim, monkeypatch, wrapped)
    if wrapped:
        g = solver.cells
        assert g.nx * g.ny * g.nz <= 16 and g.ny == 3  # rows and columns alias
    s = model.state()
    with wp.ScopedDevice(DEVICE):
        solver.build_cells(s)
        solver.build_neighbour_lists(s)
    n = model.n_fluid
    cnt = solver._nbr_count.numpy()
    nbr = solver._nbr.numpy().reshape(solver.neighbour_cap, n)
    X = s.x.numpy().astype(np.float64)
    d = np.linalg.norm(X[:n, None, :] - X[None, :, :], axis=2)
    H = model.support_radius
    for i in range(n):
        want = set(np.flatnonzero(d[i] < H).tolist()) - {i}
        got = set(nbr[: cnt[i], i].tolist())
        assert cnt[i] == len(want) and got == want, f"particle {i}"


def test_neighbour_list_overflow_falls_back_to_cell_query(monkeypatch):
    """Particles with more neighbours than the list holds get the same density and acceleration
    from the cell-grid query."""
    from rockwave.kernels import sph

    model, solver = _random_model(3, monkeypatch, wrapped=False)
    s = model.state()
    n = model.n_fluid

    def rates():
        with wp.ScopedDevice(DEVICE):
            solver.compute_density(s)
            wp.launch(sph.particle_acceleration_list, dim=n,
                      inputs=[solver._nbr_count, solver._nbr, s.x, s.v, s.rho, s.pressure, solver._pr2,
                              model.particle_mass, model.params], outputs=[s.accel, s.xsph_dv], device=DEVICE)
            wp.launch(sph.particle_acceleration_overflow, dim=n,
                      inputs=[solver.cells, *solver._slot_ranges, solver._nbr_count, solver.neighbour_cap, s.x, s.v,
                              s.rho, s.pressure, model.particle_mass, model.params], outputs=[s.accel, s.xsph_dv],
                      device=DEVICE)
        return s.rho.numpy().copy(), s.accel.numpy().copy(), s.xsph_dv.numpy().copy()

    full = rates()
    solver.neighbour_cap = 8
    solver._nbr = wp.zeros(8 * n, dtype=int, device=DEVICE)
    small = rates()
    assert solver.list_overflow() > 0.5 * n
    for a, b in zip(full, small):
        assert np.allclose(a, b, rtol=1e-5, atol=1e-5 * np.abs(a).max())
