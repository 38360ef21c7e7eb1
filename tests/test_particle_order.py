"""Particle reordering by cell (FluidSolver.reorder / unsort) and stepping in chunks
(Simulation.step_many; CUDA graphs on a GPU): same physics, original ids on output."""

import numpy as np
import pytest
import warp as wp
from scipy.spatial import cKDTree

import rockwave
from rockwave.base.solver import TimeStep
from rockwave.scene.format import load_scene
from rockwave.sim.simulation import SimulationOptions
from rockwave.sph.fluid import FluidOptions

from conftest import DEVICE
from helpers import ROOT


def _options(**fluid) -> SimulationOptions:
    return SimulationOptions(fluid=FluidOptions(**fluid))


def _sim(spacing=0.08, continuity=False, **fluid):
    scene = load_scene(ROOT / "scenes" / "dam_break_3d.toml")
    scene.fluid["spacing_m"] = spacing
    scene.fluid["density"] = "continuity" if continuity else "summation"  # the scene's default is continuity
    scene.output["gauges"] = []
    return rockwave.Simulation(scene, device=DEVICE, options=_options(**fluid))


def _ts(dt: wp.array) -> TimeStep:
    """A fluid step of the length held in the device array dt."""
    return TimeStep(float(dt.numpy()[0]), 0.0, dt)


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
    assert np.allclose(sim.positions(), x0[:nf, :3])  # reads give the seeded order
    assert np.array_equal(sim.state.ids.numpy(), ids)  # and leave the state as it is
    with wp.ScopedDevice(sim.device):
        fs.unsort(sim.state)
    assert np.array_equal(sim.state.ids.numpy(), np.arange(nf)) and np.array_equal(sim.state.x.numpy(), x0)


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
    u = (xb.astype(np.float64) - xb.min(axis=0)) / H

    def key(c):
        return (c[:, 2] * 10000 + c[:, 1]) * 10000 + c[:, 0]

    # a particle on a cell border (walls on the water's lattice put whole rows there) may fall on either side once
    # its position is rounded to float32: each next key at least the last one's with the border taken low
    lo, hi = key(np.floor(u - 1e-4).astype(int)), key(np.floor(u + 1e-4).astype(int))
    assert np.all(hi[1:] >= lo[:-1])


def _random_model(dim, wrapped, n_side=7):
    from test_sph import _fluid_section

    from rockwave.build.options import fluid_parameters
    from rockwave.build.sampling import box_lattice
    from rockwave.sph.fluid import FluidSolver, build_fluid_model

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
    model = build_fluid_model(x, rng.normal(0, 0.5, x.shape) * ([1] * dim + [0] * (3 - dim)), xb, fluid_parameters(fl), dim,
                              [0.0] * dim, DEVICE)
    # wrapped: force the cell grid to wrap (hash) in every dimension
    solver = FluidSolver(model, options=FluidOptions(min_cells=16, cells_per_particle=0) if wrapped else None)
    return model, solver


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("wrapped", [False, True])
@pytest.mark.parametrize("skin", [0.0, 0.2])
def test_neighbour_lists_match_brute_force(dim, wrapped, skin):
    """The cell grid (x-cells R/4, y/z cells R, culled column runs; wrapped like a hash grid when the
    domain needs too many cells) finds exactly the particles within the list radius R = (1 + skin) H of
    each fluid particle, fluid and boundary, self excluded."""
    model, solver = _random_model(dim, wrapped)
    solver.set_neighbour_skin(skin)
    if wrapped:
        g = solver.cells
        assert g.nx * g.ny * g.nz <= 16 and g.ny == 3  # rows and columns alias
    s = model.state()
    with wp.ScopedDevice(DEVICE):
        solver.build_cells(s)
        solver.build_neighbour_lists(s)
    n = model.n_fluid
    cnt = solver.list_counts.numpy()
    nbr = solver.list_entries.numpy().reshape(solver.neighbour_cap, n)
    X = s.x.numpy().astype(np.float64)
    d = np.linalg.norm(X[:n, None, :] - X[None, :, :], axis=2)
    H = solver.list_radius
    for i in range(n):
        want = set(np.flatnonzero(d[i] < H).tolist()) - {i}
        got = set(nbr[: cnt[i], i].tolist())
        assert cnt[i] == len(want) and got == want, f"particle {i}"


def test_neighbour_list_overflow_falls_back_to_cell_query():
    """Particles with more neighbours than the list holds get the same density and acceleration
    from the cell-grid query."""

    model, solver = _random_model(3, wrapped=False)
    s = model.state()
    n = model.n_fluid

    def rates():
        with wp.ScopedDevice(DEVICE):
            solver.compute_density(s)
            solver.pair_accelerations(s, lists_built=True)
        return s.rho.numpy().copy(), s.accel.numpy().copy(), s.xsph_dv.numpy().copy()

    full = rates()
    solver.set_list_capacity(8)
    small = rates()
    assert solver.list_overflow() > 0.5 * n
    for a, b in zip(full, small):
        assert np.allclose(a, b, rtol=1e-5, atol=1e-5 * np.abs(a).max())


# ---------------------------------------------------------------- neighbour skin (Verlet lists) ----------

class _BuildCounter:
    """Counts list builds of a solver from its stored build positions (works in the device-flag mode too)."""

    def __init__(self, fs):
        self.fs, self.last, self.builds = fs, fs.list_build_positions.numpy().copy(), 0

    def update(self):
        x = self.fs.list_build_positions.numpy()
        if not np.array_equal(x, self.last):
            self.builds += 1
            self.last = x.copy()


_STATE_FIELDS = ("x", "v", "rho", "pressure", "accel", "xsph_dv", "drho_dt", "ids")


def _dam_break(density, **fluid):
    return _sim(continuity=density == "continuity", **fluid)


@pytest.mark.parametrize("density", ["summation", "continuity"])
@pytest.mark.parametrize("host_decides", [True, False])
def test_neighbour_skin_matches_rebuilding_every_step(density, host_decides):
    """With a skin the list is kept over several steps and the density and force passes skip its pairs
    at r >= H: after a stretch of flowing dam break the state equals the run that rebuilds every step
    (summation order only), in both the CPU's host-decided and the GPU's device-flag mode."""
    a = _dam_break(density, neighbour_skin=0.0)
    a.advance(0.3)  # a flowing collapse, not the start at rest
    b = _dam_break(density, neighbour_skin=0.1)
    assert b.fluid.density_mode == density
    fs = b.fluid_solver
    fs.host_decides = host_decides
    with wp.ScopedDevice(a.device):
        a.fluid_solver.unsort(a.state)  # (the CPU steps one by one: already in the seeded order)
    for k in _STATE_FIELDS:
        getattr(b.state, k).assign(getattr(a.state, k))
    b.clock.set_dt(a.dt)
    count = _BuildCounter(fs)
    n = 24
    for _ in range(n):
        a.step()
        b.step()
        count.update()
    assert 2 <= count.builds < n / 2  # rebuilt as the flow moves, but kept over several steps
    assert a.fluid_solver.list_overflow() == 0 and fs.list_overflow() == 0
    s = a.fluid.spacing
    assert np.abs(b.positions() - a.positions()).max() < 1e-4 * s
    assert np.abs(b.densities() - a.densities()).max() < 1e-2
    acc_a, acc_b = a.state.accel.numpy(), b.state.accel.numpy()
    assert np.abs(acc_b - acc_a).max() < 1e-4 * np.abs(acc_a).max()


def test_neighbour_skin_coupled_scene_matches():
    """A coupled scene (the coupling moves fluid particles after the fluid step): the same motion with
    and without the skin."""
    def run(skin):
        sim = rockwave.Simulation(load_scene(ROOT / "scenes" / "sliding_wedge_small.toml"), device=DEVICE,
                                  options=_options(neighbour_skin=skin))
        count = _BuildCounter(sim.fluid_solver)
        for _ in range(120):
            sim.step()
            count.update()
        return sim, count.builds

    (a, _), (b, builds) = run(0.0), run(0.1)
    assert builds < 60
    assert np.abs(a.coupling.dv.numpy()).max() > 0  # the block pushes the water
    assert np.allclose(a.block_positions(), b.block_positions(), atol=1e-5)
    assert np.abs(b.positions() - a.positions()).max() < 1e-4 * a.fluid.spacing
    assert np.abs(b.densities() - a.densities()).max() < 2e-2


@pytest.mark.parametrize("host_decides", [True, False])
def test_neighbour_skin_rebuilds_after_large_displacement(host_decides):
    """A list is kept while every particle moved less than skin/2 since the build and rebuilt (equal to
    brute force within the list radius at the new positions) as soon as one moves further, whatever moved
    it (here: the positions assigned directly)."""
    model, solver = _random_model(3, wrapped=False)
    solver.set_neighbour_skin(0.2)
    solver.host_decides = host_decides
    s = model.state()
    s.v.zero_()
    dt = wp.array([1e-6], dtype=float, device=DEVICE)
    n, H = model.n_fluid, model.support_radius
    R = solver.list_radius

    def lists():
        cnt = solver.list_counts.numpy()
        nbr = solver.list_entries.numpy().reshape(solver.neighbour_cap, n)
        return [set(nbr[: cnt[i], i].tolist()) for i in range(n)]

    def brute(X):
        d = np.linalg.norm(X[:n, None, :] - X[None, :, :], axis=2)
        return [set(np.flatnonzero(d[i] < R).tolist()) - {i} for i in range(n)]

    with wp.ScopedDevice(DEVICE):
        X0 = s.x.numpy().astype(np.float64)
        solver.step(s, _ts(dt))
        assert lists() == brute(X0)
        # a small move of one particle (< skin/2): the list is kept
        x = s.x.numpy()
        x[5] += np.array([0.4 * 0.5 * 0.2 * H, 0.0, 0.0], dtype=np.float32)
        s.x.assign(x)
        solver.step(s, _ts(dt))
        assert np.array_equal(solver.list_build_positions.numpy()[:n], X0[:n].astype(np.float32))
        assert lists() == brute(X0)
        # one particle jumps by 0.6 H: the list is rebuilt at the new positions
        x = s.x.numpy()
        x[7] += np.array([0.0, 0.6 * H, 0.0], dtype=np.float32)
        s.x.assign(x)
        X1 = s.x.numpy().astype(np.float64)
        solver.step(s, _ts(dt))
        assert np.array_equal(solver.list_build_positions.numpy()[:n], X1[:n].astype(np.float32))
        assert lists() == brute(X1)
        # a large velocity for every particle: rebuilt each step
        s.v.assign(np.random.default_rng(1).normal(0, 0.3 * H / 1e-6, (model.n_total, 3)).astype(np.float32) *
                   (np.arange(model.n_total) < n)[:, None])
        for _ in range(2):
            X = s.x.numpy().astype(np.float64)
            solver.step(s, _ts(dt))
            assert lists() == brute(X)
        # and the rates equal a solver without a skin on the same state
        ref = FluidSolver_with_skin(model, 0.0)
        s2 = model.state()
        for k in _STATE_FIELDS:
            getattr(s2, k).assign(getattr(s, k))
        solver.step(s, _ts(dt))
        ref.step(s2, _ts(dt))
        for k in ("rho", "accel", "xsph_dv", "x"):
            u, w = getattr(s, k).numpy(), getattr(s2, k).numpy()
            assert np.allclose(u, w, rtol=1e-5, atol=1e-5 * np.abs(w).max()), k


def FluidSolver_with_skin(model, skin):
    from rockwave.sph.fluid import FluidSolver

    return FluidSolver(model, neighbour_skin=skin)


def test_reorder_and_unsort_force_a_rebuild():
    sim = _sim(neighbour_skin=0.1)
    fs = sim.fluid_solver
    sim.step()
    assert int(fs.rebuild_flag.numpy()[0]) == 0
    with wp.ScopedDevice(sim.device):
        fs.reorder(sim.state)
    assert int(fs.rebuild_flag.numpy()[0]) == 1
    sim.step()
    assert int(fs.rebuild_flag.numpy()[0]) == 0
    with wp.ScopedDevice(sim.device):
        fs.unsort(sim.state)
    assert int(fs.rebuild_flag.numpy()[0]) == 1


@pytest.mark.parametrize("host_decides", [True, False])
def test_neighbour_skin_overflow_fallback_on_a_kept_grid(host_decides):
    """Overflowed lists are summed by a cell query of radius H + skin on the grid of the last build,
    which is kept with the list: after every particle moved (less than skin/2) without a rebuild, the
    rates equal those of a solver without a skin and with room for every neighbour."""
    from rockwave.sph.fluid import FluidSolver

    model, solver = _random_model(3, wrapped=False)
    solver.set_neighbour_skin(0.2)
    solver.host_decides = host_decides
    n, H = model.n_fluid, model.support_radius
    solver.set_list_capacity(8)
    ref = FluidSolver(model, neighbour_skin=0.0)
    s, s2 = model.state(), model.state()
    dt = wp.array([1e-7], dtype=float, device=DEVICE)
    with wp.ScopedDevice(DEVICE):
        solver.step(s, _ts(dt))
        xb = solver.list_build_positions.numpy().copy()
        assert solver.list_overflow() > 0.5 * n
        d = np.random.default_rng(2).normal(size=(model.n_total, 3))
        d *= (0.45 * 0.1 * H / np.linalg.norm(d, axis=1))[:, None] * (np.arange(model.n_total) < n)[:, None]
        x = s.x.numpy() + d.astype(np.float32)
        for k in _STATE_FIELDS:
            getattr(s2, k).assign(getattr(s, k))
        s.x.assign(x)
        s2.x.assign(x)
        solver.step(s, _ts(dt))
        ref.step(s2, _ts(dt))
        assert np.array_equal(solver.list_build_positions.numpy(), xb)  # the list and grid were kept
    for k in ("rho", "accel", "xsph_dv"):
        u, w = getattr(s, k).numpy(), getattr(s2, k).numpy()
        assert np.allclose(u, w, rtol=1e-5, atol=1e-5 * np.abs(w).max()), k


def test_relative_skin_check_keeps_every_neighbour_and_rebuilds_less():
    """The relative skin check (FluidOptions.skin_check = "relative": rebuild when two particles in the same
    or adjacent 2H cells may have moved s H relative to each other, or one moved (2H - H)/2): over a
    flowing 3D dam break every pair closer than H at the positions a step starts from (the positions its density
    and force passes use the list at) is in the list of that step (brute force), and the lists are rebuilt less
    often than with the absolute check (any particle moved s H / 2). The check runs at the start of a step, so the
    list need not hold the pairs of the step's end positions (at Courant number 0.6 two pairs at step 146 were
    not, until the next step's check rebuilt it). Measured (this test, C 0.4): 200 steps, relative 19 builds,
    absolute 33; at 10,850 particles over 0.3 s 196 vs 330."""
    assert FluidOptions().skin_check == "relative"
    builds = {}
    for mode in ("relative", "absolute"):
        sim = _dam_break("continuity", skin_check=mode, relative_min_particles_cuda=0)  # (GPU: on at any size)
        fs = sim.fluid_solver
        assert fs.relative_skin_check == (mode == "relative")
        H = sim.fluid.support_radius
        n = sim.n_fluid
        count = _BuildCounter(fs)  # (list_builds counts host-decided builds only: the CPU's)
        for step in range(200):
            x = sim.state.x.numpy().copy()  # the step's start positions (single steps keep the particle order)
            sim.step()
            count.update()
            if mode != "relative":
                continue
            cnt, nbr, cap = fs.list_counts.numpy(), fs.list_entries.numpy(), fs.neighbour_cap
            # every pair (fluid i, any j) closer than H (a k-d tree: all pairs within H, self pairs dropped) ...
            near = cKDTree(x[:n]).sparse_distance_matrix(cKDTree(x), H, output_type="ndarray")
            near = near[(near["i"] != near["j"]) & (near["v"] < H) & (cnt[near["i"]] <= cap)]
            # ... is among the listed ones (entry k of particle i at nbr[k n + i], k < cnt[i])
            k, i = np.nonzero(np.arange(cap)[:, None] < np.minimum(cnt, cap)[None, :])
            listed = i.astype(np.int64) * len(x) + nbr[k * n + i]
            missing = ~np.isin(near["i"].astype(np.int64) * len(x) + near["j"], listed)
            assert not missing.any(), f"step {step}: {int(missing.sum())} neighbour pairs missing from the lists"
        builds[mode] = count.builds
        assert np.abs(sim.velocities()).max() > 1.0  # the water flows
    assert builds["relative"] < 0.8 * builds["absolute"], builds


@pytest.mark.skipif(not wp.get_device(DEVICE).is_cuda, reason="CUDA graphs: GPU only")
def test_single_steps_replay_a_captured_step_on_a_gpu():
    """Single steps (sim.step, and advance's steps outside the reorder chunks, e.g. between gauge reads a few
    steps apart) replay one captured step on a GPU: the same trajectory as plain launches, and the list
    rebuild a conditional node (plain launches would sort by cell every step)."""
    a = _sim(continuity=True)
    b = rockwave.Simulation(a.scene, device=DEVICE, options=SimulationOptions(fluid=FluidOptions(), cuda_graphs=False))
    for sim in (a, b):
        for _ in range(3):
            sim.advance(3.5 * sim.dt)  # 3 or 4 steps per call: no chunk of 10 fits
        sim.step_many(12)  # one chunk, two steps
    assert ("step",) in a._plain_runs and any(k[-1:] == ("step",) for k in a._graphs)
    assert not b._graphs and b.steps == a.steps and b.time == pytest.approx(a.time)
    assert np.abs(b.positions() - a.positions()).max() < 1e-3 * a.fluid.spacing
