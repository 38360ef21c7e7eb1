"""Force gauges ([[output.gauges]] kind 'force', rockwave/sim/readers.py ForceGauges): the water's pressure force
on a block, the pressure integrated over its faces, checked against Archimedes on a fixed block in still water and
on a floating block's weight."""

import tomllib

import numpy as np
import pytest

import rockwave
from rockwave.dda import geometry as G
from rockwave.scene.format import SceneError, parse_scene
from rockwave.sim.readers import face_samples

from conftest import DEVICE
from helpers import ROOT, tank_2d


def test_face_samples_integrate_area_and_closure():
    # the area vectors of a closed surface sum to zero, and their magnitudes to its area (3D box; 2D per metre)
    g = G.box((0.3, 0.2, 0.1))
    pts, a = face_samples(g, 3, 0.02)
    assert np.abs(a.sum(axis=0)).max() < 1e-12
    assert np.linalg.norm(a, axis=1).sum() == pytest.approx(2 * (0.06 + 0.03 + 0.02), rel=1e-12)
    assert np.abs(pts).max(axis=0) == pytest.approx([0.15, 0.1, 0.05], abs=0.01)
    pts2, a2 = face_samples(g, 2, 0.02)  # the prism's side faces in the x-y plane: perimeter 1.0 m per metre
    assert np.linalg.norm(a2, axis=1).sum() == pytest.approx(1.0, rel=1e-12) and np.all(pts2[:, 2] == 0.0)
    # the divergence theorem: -sum_k z_k (A_k n_k) = buoyancy of unit pressure gradient = the volume (along z)
    assert -(pts[:, 2] * a[:, 2]).sum() == pytest.approx(-g.volume, rel=1e-9)


@pytest.mark.parametrize("solid", ["block", "obstacle"])
def test_submerged_fixed_block_feels_archimedes_force(solid):
    # a 0.1 x 0.1 m fixed block (Adami walls), or a box obstacle (boundary particles), in the middle of 0.4 m of
    # still water (2D, 0.01 m): the water's vertical force on it is rho g A = 98.1 N/m (Archimedes; measured on
    # the block +2.1%, 100.2 N/m, over 0.1-0.6 s) and the sideways one nil (measured < 0.04 N/m)
    d = tank_2d(width=0.6, depth=0.4, height=0.5, spacing=0.01)
    if solid == "block":
        d["blocks"] = [{"name": "rock", "shape": "box", "kind": "fixed", "size_m": [0.1, 0.1, 0.1], "position_m": [0.3, 0.2, 0.0]}]
        name = "rock"
    else:
        d["obstacles"] = [{"box_min_m": [0.25, 0.15], "box_max_m": [0.35, 0.25]}]
        name = "obstacle.0"
    d["output"] = {"gauges": [{"name": "lift", "kind": "force", "block": name, "direction": [0.0, 2.0]},
                              {"name": "push", "kind": "force", "block": name, "direction": [1.0, 0.0]}]}
    sim = rockwave.Simulation(parse_scene(d, "tank.toml"), device=DEVICE)
    lift, push = [], []
    for _ in range(6):
        sim.advance(0.1)
        g = sim.gauges()
        lift.append(g["lift"])
        push.append(g["push"])
    archimedes = 1000.0 * 9.81 * 0.1 * 0.1
    assert np.mean(lift) == pytest.approx(archimedes, rel=0.04), lift
    assert np.abs(push).max() < 0.01 * archimedes, push


def test_floating_box_is_carried_by_its_weight():
    # scenes/floating_box_2d.toml (a 0.4 x 0.2 m box of 500 kg/m^3, an Adami wall, heaving as it settles): the
    # water's vertical force averaged over 0.3-1 s equals its weight, 392.4 N/m (measured -1.2%)
    d = tomllib.loads((ROOT / "scenes" / "floating_box_2d.toml").read_text())
    d["output"]["gauges"] = [{"name": "lift", "kind": "force", "block": "box", "direction": [0.0, 1.0]}]
    sim = rockwave.Simulation(parse_scene(d, ROOT / "scenes" / "floating_box_2d.toml"), device=DEVICE)
    rows = []
    while sim.time < 1.0 - 1e-9:
        sim.advance(0.02)
        if sim.time >= 0.3:
            rows.append(sim.gauges()["lift"])
    assert np.mean(rows) == pytest.approx(500.0 * 0.4 * 0.2 * 9.81, rel=0.03), np.mean(rows)


@pytest.mark.parametrize("gauge, key, words", [
    ({"kind": "force", "direction": [0.0, 1.0]}, "output.gauges[0].block", "needs the name"),
    ({"kind": "force", "block": "nope", "direction": [0.0, 1.0]}, "output.gauges[0].block", "not the name of a block"),
    ({"kind": "force", "block": "obstacle.3", "direction": [0.0, 1.0]}, "output.gauges[0].block", "box obstacles: none"),
    ({"kind": "force", "block": "rock"}, "output.gauges[0].direction", "needs the direction"),
    ({"kind": "force", "block": "rock", "direction": [0.0, 0.0]}, "output.gauges[0].direction", "must not be zero"),
    ({"kind": "force", "block": "rock", "direction": [0.0, 1.0], "position_m": [0.1, 0.1]}, "output.gauges[0].position_m",
     "no position"),
    ({"kind": "pressure"}, "output.gauges[0].position_m", "needs a position"),
    ({"kind": "pressure", "position_m": [0.1, 0.1], "block": "rock"}, "output.gauges[0].block", "only a 'force' gauge"),
])
def test_force_gauge_errors_name_the_key(gauge, key, words):
    d = tank_2d(width=0.6, depth=0.4, height=0.5, spacing=0.02)
    d["blocks"] = [{"name": "rock", "shape": "box", "kind": "fixed", "size_m": [0.1, 0.1, 0.1], "position_m": [0.3, 0.2, 0.0]}]
    d["output"] = {"gauges": [dict(name="g", **gauge)]}
    with pytest.raises(SceneError) as e:
        parse_scene(d, "tank.toml")
    assert key in str(e.value) and words in str(e.value), str(e.value)
