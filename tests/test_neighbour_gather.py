"""fluid.neighbours = 'cells' (issue 40): the fluid passes gather their neighbours from the sorted cell grid instead
of reading a stored Verlet list (kernels/sph/gather.py). The same pairs, in the same order: the trajectories equal
the list path's within round-off, the neighbour counts are the same, and the list's bytes are gone."""

import copy

import numpy as np
import pytest
from scipy.spatial import cKDTree

import rockwave
from rockwave.scene.format import SceneError
from rockwave.sim.batch import BatchSimulation
from rockwave.sim.simulation import SimulationOptions
from rockwave.sph.fluid import FluidOptions

from conftest import DEVICE
from helpers import ROOT, tank_2d, with_changes

# positions of the two paths after the run: within TOL of the largest coordinate (float32 round-off grown over the
# run). With the default cell_span the passes visit the same pairs in the same order (the gather's query is the list
# build's): on the CPU the runs are then bit-identical (measured at every level); cell_span = 2 visits them in
# another order (measured: 3e-7 and 6e-8 of the largest coordinate in 3D and 2D here).
TOL = 1e-5


def _scene(dim: int, level: str, neighbours: str | None, **extra):
    if dim == 2:  # a 2D dam break: a 0.2 m column in a 0.5 m tank, 400 particles
        d = tank_2d(width=0.2, depth=0.2, height=0.3, spacing=0.01, fidelity=level)
        d["tank"]["box_max_m"] = [0.5, 0.3]
    else:  # SPHERIC Test 2's tank at 0.08 m: 1,260 particles, 7,028 wall particles at the default level
        d = with_changes(rockwave.load_scene(ROOT / "scenes" / "dam_break_3d.toml").raw,
                         **{"fluid.spacing_m": 0.08, "fluid.fidelity": level, "output.gauges": []})
    if neighbours is not None:
        d["fluid"]["neighbours"] = neighbours
    d["fluid"].update(extra)
    return rockwave.parse_scene(d, "gather", ROOT / "scenes")


@pytest.mark.parametrize("dim, level, steps, span, prefilter", [
    (2, "standard", 80, 1, False), (3, "standard", 30, 1, False), (2, "delta_plus", 60, 1, False),
    (3, "waves", 20, 1, False), (2, "draft", 60, 1, False), (2, "standard", 80, 2, False), (3, "standard", 30, 2, False),
    (3, "delta_plus", 20, 1, True)])
def test_cell_gather_trajectory_equals_the_lists(dim, level, steps, span, prefilter):
    """A dam break stepped both ways (adaptive step, Verlet skin, Adami walls at every level but draft's Akinci
    walls; waves: the gradient correction; delta_plus: the density diffusion and the particle shifting; span 2: the
    gather's grid of 25 columns, its pairs in another order than the lists'): positions within TOL of the largest
    coordinate (prefilter: the candidates first tested at their build positions, as the list build does),
    densities within 1e-2 kg/m^3, the lists rebuilt at the same steps, the same neighbour counts within H
    at the same positions."""
    a = rockwave.Simulation(_scene(dim, level, "lists"), device=DEVICE)
    b = rockwave.Simulation(_scene(dim, level, "cells"), device=DEVICE,
                            options=SimulationOptions(fluid=FluidOptions(cell_span=span, gather_prefilter=prefilter)))
    sims = {"lists": a, "cells": b}
    assert not a.fluid_solver.cell_gather and b.fluid_solver.cell_gather
    for s in sims.values():
        s.step_many(steps)
    assert a.time == b.time > 0
    assert np.abs(a.velocities()).max() > 0.1  # the column is falling
    assert a.fluid_solver.list_builds == b.fluid_solver.list_builds >= 2  # the grid kept over steps, then rebuilt
    dx = np.abs(a.positions() - b.positions()).max()
    assert dx <= TOL * np.abs(a.positions()).max(), dx
    assert np.abs(a.densities() - b.densities()).max() <= 1e-2
    for k in ("x", "v", "rho", "ids"):  # the same state in both, its grid and lists built anew
        getattr(b.state, k).assign(getattr(a.state, k))
    for s in (a, b):
        s.fluid_solver.build_lists(s.state)
    ca, cb = a.fluid_solver.pair_counts(a.state), b.fluid_solver.pair_counts(b.state)
    assert np.array_equal(ca, cb)
    # and against a brute-force count of the particles within H (fluid and walls) at the current positions
    x = b.state.x.numpy().astype(np.float64)
    nf, H = b.fluid.n_fluid, b.fluid.support_radius
    brute = np.array([len(n) - 1 for n in cKDTree(x).query_ball_point(x[:nf], H * (1 - 1e-6))])
    assert np.abs(cb - brute).max() <= 1  # (a pair within float32 rounding of H may count either way)
    assert cb.mean() > (80 if dim == 3 and level != "draft" else 8)


def test_cell_gather_drops_the_list_bytes():
    """FluidSolver.device_bytes at the default level: the gather keeps no list (two one-entry placeholders) and no
    slot-ordered positions; everything else is the list path's."""
    out = {}
    for nb in ("lists", "cells"):
        sim = rockwave.Simulation(_scene(2, "standard", nb), device=DEVICE)
        sim.step_many(2)
        out[nb] = sim.fluid_solver.device_bytes(sim.state)
        nf, nt, cap = sim.fluid.n_fluid, sim.fluid.n_total, sim.fluid_solver.neighbour_cap
        if nb == "lists":
            cap_lists = cap
    assert out["lists"]["lists"] == 4 * (cap_lists + 1) * nf
    assert out["cells"]["lists"] == 8
    assert out["lists"]["solver"] - out["cells"]["solver"] == 12 * (nt - 1)  # the slot-ordered positions
    for k in ("state", "model", "hash_grid"):
        assert out["lists"][k] == out["cells"][k]


def test_cell_gather_in_a_batch_equals_the_lists():
    """A batch of two scenarios with their own steps (rockwave/sim/batch.py) steps the same with the gather."""
    variants = []
    for w in (0.3, 0.4):
        d = tank_2d(width=0.1, depth=0.1, height=0.2, spacing=0.01)
        d["tank"]["box_max_m"] = [w, 0.2]
        d["simulation"]["duration_s"] = 0.02
        variants.append(d)

    def run(nb):
        scenes = []
        for d in variants:
            d = copy.deepcopy(d)
            d["fluid"]["neighbours"] = nb
            scenes.append(rockwave.parse_scene(d))
        b = BatchSimulation(scenes, device=DEVICE)
        b.advance(0.02)
        return b

    a, b = run("lists"), run("cells")
    assert b.fluid_solver.cell_gather
    for k in range(2):
        assert np.abs(a.positions(k) - b.positions(k)).max() <= TOL * 0.01


def test_neighbours_option_is_checked():
    """fluid.neighbours: a scene key with the default of FluidOptions ('lists'), an unknown value a SceneError naming
    the key, 'cells' with Ghost SPH, the renormalised diffusion or the wall work a SceneError (their passes read lists); the Python option wins over the scene's and
    refuses an unknown value; the Ghost solver refuses the gather."""
    assert FluidOptions.DEFAULT_NEIGHBOURS == "lists"
    assert _scene(2, "standard", None).fluid["neighbours"] == "lists"
    with pytest.raises(SceneError, match="fluid.neighbours"):
        _scene(2, "standard", "verlet")
    ghost = tank_2d(method="ghost", neighbours="cells")
    with pytest.raises(SceneError, match="fluid.neighbours"):
        rockwave.parse_scene(ghost)
    with pytest.raises(ValueError, match="neighbours"):
        FluidOptions(neighbours="grid")
    renorm = tank_2d(neighbours="cells", density_diffusion=0.1, density_diffusion_renormalised=True)
    with pytest.raises(SceneError, match="fluid.density_diffusion_renormalised"):  # its gradient pass reads lists
        rockwave.parse_scene(renorm)
    with pytest.raises(SceneError, match="fluid.wall_work"):  # the wall work pass reads lists
        rockwave.parse_scene(tank_2d(neighbours="cells", wall_work=True))
    sim = rockwave.Simulation(_scene(2, "standard", "lists"), device=DEVICE,
                              options=SimulationOptions(fluid=FluidOptions(neighbours="cells")))
    assert sim.fluid_solver.cell_gather and sim.fluid_solver.neighbour_cap == 0
    sim = rockwave.Simulation(_scene(2, "standard", "cells"), device=DEVICE)
    assert sim.fluid_solver.cell_gather
    from rockwave.sph.ghost import GhostFluidSolver
    with pytest.raises(ValueError, match="neighbours = 'cells'"):
        GhostFluidSolver(sim.fluid, FluidOptions(neighbours="cells"))


def test_cell_gather_with_moving_block_walls_and_a_checkpoint():
    """A floating box with wall particles (coupling.block_walls: moving Adami walls, their own skin check): the
    gather steps it as the lists do, and a run resumed from a checkpoint continues bit for bit (the build
    positions travel in it; the gather queries from them)."""
    from test_block_walls import S
    from test_block_walls import _scene as box_scene

    from rockwave.sim import checkpoint

    def scene(nb):
        d = box_scene(lift=S)
        d["fluid"]["neighbours"] = nb
        return rockwave.parse_scene(d)

    a = rockwave.Simulation(scene("lists"), device=DEVICE)
    b = rockwave.Simulation(scene("cells"), device=DEVICE)
    assert b.fluid.n_moving_walls > 0 and b.fluid_solver.cell_gather
    for s in (a, b):
        s.advance(0.06)
    arrays, metas = checkpoint.pack(b, checkpoint.capture(b))
    meta = {"scene": checkpoint.scene_identity(b), "groups": metas}
    for s in (a, b):
        s.advance(0.06)
    assert a.steps == b.steps
    assert np.abs(a.positions() - b.positions()).max() <= TOL * np.abs(a.positions()).max()
    assert np.abs(a.block_positions() - b.block_positions()).max() <= TOL
    c = rockwave.Simulation(scene("cells"), device=DEVICE)
    checkpoint.restore(c, arrays, meta)
    c.advance(0.06)
    assert c.steps == b.steps
    assert np.array_equal(b.state.x.numpy(), c.state.x.numpy())  # the wall particles too
