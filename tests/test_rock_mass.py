"""[[rock_mass]]: regions cut into convex blocks by joint sets (rockwave/build/rockmass.py)."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

from rockwave.build.rockmass import (
    JointSet,
    box_halfspaces,
    cut_box,
    cut_convex,
    cut_mesh,
    hull_halfspaces,
    jennings_strength,
    joint_normal,
    merge_slivers,
)
from rockwave.scene.format import SceneError, parse_scene

OBLIQUE = [JointSet(60, 30, 0.3, random_offset=True), JointSet(70, 200, 0.4, random_offset=True),
           JointSet(15, 100, 0.25, random_offset=True)]


def normals(sets, dim=3):
    return np.array([joint_normal(s.dip_deg, s.dip_direction_deg, dim) for s in sets])


def cut_region(lo, hi, sets, seed=0, R=None, origin=None):
    A, b, c = box_halfspaces(lo, hi, R)
    return cut_convex(A, b, c, sets, normals(sets), c[0] if origin is None else origin, seed=seed), A, b


def test_joint_normal_geological_convention():
    # dip 30 toward east (90): the plane falls toward +x, its upward normal leans to +x
    assert np.allclose(joint_normal(30, 90), [0.5, 0, math.cos(math.radians(30))])
    assert np.allclose(joint_normal(90, 0), [0, 1, 0])  # vertical, striking east-west
    assert np.allclose(joint_normal(0, 123), [0, 0, 1])  # horizontal
    assert np.allclose(joint_normal(30, 270, dim=2), [-0.5, math.cos(math.radians(30)), 0])


def test_volumes_sum_and_faces_lie_on_planes():
    rot = trimesh.transformations.rotation_matrix(0.4, [0.3, 1, 0.2])[:3, :3]
    for R in (None, rot):
        cut, A, b = cut_region([0, 0, 0], [2.0, 1.5, 1.0], OBLIQUE, seed=5, R=R)
        cut = merge_slivers(cut, 0.06)
        assert cut.merged > 0 and len(cut) > 50
        assert abs(cut.volumes.sum() / 3.0 - 1) < 1e-9
        assert (cut.volumes >= 0.06 ** 3).all()
        planes = [(s, n, t) for s, (n, ts) in enumerate(zip(cut.normals, cut.positions)) for t in ts]
        planes += [(-1, n, t) for n, t in zip(A, b)]  # the region's faces
        for i in range(len(cut)):
            v = cut.block_vertices(i)
            h = ConvexHull(v)
            assert abs(h.volume - cut.volumes[i]) < 1e-9 * cut.volumes[i]
            sets_on = set()
            for eq in h.equations:
                n, d = eq[:3], -eq[3]
                on = [s for s, pn, t in planes if abs(abs(n @ pn) - 1) < 1e-9 and abs(d - np.sign(n @ pn) * t) < 1e-9]
                assert on, (i, eq)  # every face lies on a joint plane or the region boundary
                sets_on.update(s for s in on if s >= 0)
            # the sets the block has faces on (they give its contact material)
            assert sets_on == set(np.flatnonzero(cut.on_set[i])), i


def test_hull_region_volume():
    pts = np.array([[0, 0, 0], [3, 0, 0], [0, 2, 0], [3, 2, 0], [0, 0, 1], [3, 0, 1], [0, 2, 2.5], [3, 2, 2.5]], float)
    A, b, c = hull_halfspaces(pts)
    cut = cut_convex(A, b, c, OBLIQUE, normals(OBLIQUE), c.min(axis=0), seed=1)
    assert abs(cut.volumes.sum() / ConvexHull(pts).volume - 1) < 1e-9


@pytest.mark.parametrize("offsets", [(0.0, 0.0, 0.0), (0.1, 0.25, 0.05), (0.49, 0.01, 0.2)])
def test_orthogonal_sets_analytic_count(offsets):
    size = np.array([3.0, 2.0, 1.2])
    spacing = [0.5, 0.4, 0.3]
    sets = [JointSet(90, 90, spacing[0], offset_m=offsets[0]), JointSet(90, 0, spacing[1], offset_m=offsets[1]),
            JointSet(0, 0, spacing[2], offset_m=offsets[2])]
    cut, _, _ = cut_region([0, 0, 0], size, sets)
    # slabs along an axis: 1 + the planes o + k s strictly inside (0, L)
    expect = 1
    for L, s, o in zip(size, spacing, offsets):
        ks = np.arange(-1, int(L / s) + 2)
        t = o + ks * s
        expect *= 1 + int(np.sum((t > 1e-9) & (t < L - 1e-9)))
    assert len(cut) == expect
    assert abs(cut.volumes.sum() / size.prod() - 1) < 1e-12
    assert len(cut_box([0, 0, 0], size, sets)) == expect  # the benchmarks' entry point


def test_slivers_merge_into_neighbours():
    # 1.0 m cut every 0.3 m along x leaves 0.1 m thick slabs at the far end (y, z: 0.25 m, no sliver)
    sets = [JointSet(90, 90, 0.3), JointSet(90, 0, 0.25), JointSet(0, 0, 0.25)]
    cut, _, _ = cut_region([0, 0, 0], [1.0, 1.0, 1.0], sets)
    assert len(cut) == 64
    merged = merge_slivers(cut, 0.2)  # the 0.1 x 0.25 x 0.25 slabs (inscribed sphere 0.1 m) join the blocks beside
    assert len(merged) == 48 and merged.merged == 16
    assert abs(merged.volumes.sum() - 1.0) < 1e-12
    for i in range(len(merged)):
        v = merged.block_vertices(i)
        assert abs(ConvexHull(v).volume - merged.volumes[i]) < 1e-9  # still convex: its hull holds exactly its volume
        assert np.ptp(v, axis=0).min() >= 0.25 - 1e-9  # boxes: the thinnest side is the inscribed sphere's diameter
    assert sorted(np.round(np.ptp(merged.block_vertices(i), axis=0)[0], 9) for i in range(len(merged)))[-16:] == [0.4] * 16
    # a thin plate: V^(1/3) = 0.22 m but only 0.05 m thick, merged all the same
    plate = merge_slivers(cut_region([0, 0, 0], [1.0, 1.0, 1.0], [JointSet(0, 0, 0.95)])[0], 0.1)
    assert len(plate) == 1


def test_seed_reproduces():
    a = merge_slivers(cut_region([0, 0, 0], [2, 1.5, 1], OBLIQUE, seed=7)[0], 0.05)
    b = merge_slivers(cut_region([0, 0, 0], [2, 1.5, 1], OBLIQUE, seed=7)[0], 0.05)
    c = merge_slivers(cut_region([0, 0, 0], [2, 1.5, 1], OBLIQUE, seed=8)[0], 0.05)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.start, b.start)
    assert len(a) != len(c) or not np.allclose(a.volumes, c.volumes)


def test_mesh_regions():
    from rockwave.build.rockmass import RockMassError

    # a convex slope section: a box with its crest cut at 40 degrees
    slope = trimesh.convex.convex_hull(np.array([[0, 0, 0], [3, 0, 0], [0, 1, 0], [3, 1, 0], [0, 0, 2], [0, 1, 2],
                                                 [3 - 2 / math.tan(math.radians(40)), 0, 2],
                                                 [3 - 2 / math.tan(math.radians(40)), 1, 2]], float))
    cut = cut_mesh(slope, OBLIQUE, normals(OBLIQUE), [0, 0, 0], seed=2)
    assert len(cut) > 50 and abs(cut.volumes.sum() / slope.volume - 1) < 1e-9
    # an L-shaped section (a slope with a bench): cut cell by cell; fine while joint planes run through its
    # concave edge (x = 1, z = 1), refused when a cell straddles it
    L = _l_mesh()
    assert L.is_watertight and abs(L.volume - 3.0) < 1e-12
    sets = [JointSet(90, 90, 0.5), JointSet(0, 0, 0.5), JointSet(90, 0, 0.3, random_offset=True)]
    cut = cut_mesh(L, sets, normals(sets), [0, 0, 0], seed=3)
    y_slabs = 1 + int(np.sum((cut.positions[2] > 1e-9) & (cut.positions[2] < 1 - 1e-9)))
    assert len(cut) == 12 * y_slabs and abs(cut.volumes.sum() / 3.0 - 1) < 1e-9
    faces = [(n, t) for n, ts in zip(cut.normals, cut.positions) for t in ts]
    faces += [(n, float(n @ v)) for n, v in zip(L.face_normals, L.triangles[:, 0])]
    for i in range(len(cut)):
        for eq in ConvexHull(cut.block_vertices(i)).equations:
            assert any(abs(abs(eq[:3] @ n) - 1) < 1e-9 and abs(-eq[3] - np.sign(eq[:3] @ n) * t) < 1e-9 for n, t in faces)
    with pytest.raises(RockMassError, match=r"not one convex piece: volume [0-9.]+ m\^3, its hull [0-9.]+ m\^3"):
        cut_mesh(L, OBLIQUE, normals(OBLIQUE), [0, 0, 0])


def _l_mesh() -> trimesh.Trimesh:
    """Closed L-shaped prism (x-z profile extruded 1 m along y)."""
    prof = [[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]]  # (x, z)
    v = np.array([[x, y, z] for y in (0.0, 1.0) for x, z in prof], float)
    n = len(prof)
    faces = [[0, 1, 2], [0, 2, 3], [0, 3, 5], [3, 4, 5]]  # the y = 0 profile, split into triangles
    faces = [[a, c, b] for a, b, c in faces] + [[a + n, b + n, c + n] for a, b, c in faces]
    for k in range(n):  # the sides
        a, b = k, (k + 1) % n
        faces += [[a, b, b + n], [a, b + n, a + n]]
    m = trimesh.Trimesh(v, faces, process=True)
    trimesh.repair.fix_normals(m)
    return m


def test_jennings_materials():
    js = JointSet(0, 0, 1.0, persistence=0.6, friction_angle_deg=25, cohesion_pa=1e4, tensile_strength_pa=0.0)
    phi, c, t = jennings_strength(js, 40.0, 1e6, 5e5)
    assert math.isclose(math.tan(math.radians(phi)), 0.6 * math.tan(math.radians(25)) + 0.4 * math.tan(math.radians(40)))
    assert math.isclose(c, 0.6e4 + 0.4e6) and math.isclose(t, 0.4 * 5e5)


# --------------------------------------------------------------------------------------------
# scene files
# --------------------------------------------------------------------------------------------

SCENE = {
    "simulation": {"duration_s": 0.05},
    "blocks": [{"name": "floor", "shape": "box", "size_m": [4.0, 4.0, 0.5], "position_m": [0.5, 0.5, -0.25], "kind": "fixed"}],
    "rock_mass": [{
        "name": "rock", "region": {"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [1.0, 0.8, 0.6]}, "min_block_size_m": 0.1,
        "material": {"cohesion_pa": 1e5, "tensile_strength_pa": 1e4},
        "joint_sets": [{"dip_deg": 90, "dip_direction_deg": 90, "spacing_m": 0.5, "friction_angle_deg": 35,
                        "cohesion_pa": 2e5, "tensile_strength_pa": 1e4},
                       {"dip_deg": 90, "dip_direction_deg": 0, "spacing_m": 0.4, "friction_angle_deg": 30,
                        "cohesion_pa": 1e5, "tensile_strength_pa": 1e4},
                       {"dip_deg": 0, "dip_direction_deg": 0, "spacing_m": 0.3, "friction_angle_deg": 20, "persistence": 0.5}]}],
    "output": {"usd": ""},
}


def scene(**changes):
    d = copy.deepcopy(SCENE)
    for path, val in changes.items():
        node = d
        keys = path.split("__")
        for k in keys[:-1]:
            node = node[int(k)] if k.isdigit() else node[k]
        node[keys[-1]] = val
    return d


def scene_error(d, what="<test>"):
    from rockwave.build.rocks import block_specs

    with pytest.raises(SceneError) as e:
        block_specs(parse_scene(d, what))
    return str(e.value)


def test_scene_blocks_and_materials():
    from rockwave.build.rocks import block_specs

    specs = block_specs(parse_scene(scene()))
    rock = [s for s in specs if s.name.startswith("rock_")]
    assert len(rock) == 2 * 2 * 2
    assert abs(sum(s.geometry.volume for s in rock) - 0.48) < 1e-12
    # every block has faces on all three sets: the weakest (Jennings) of 35, 30 and the bridged 20 / intact 30 degrees
    phi = math.degrees(math.atan(0.5 * math.tan(math.radians(20)) + 0.5 * math.tan(math.radians(30))))
    for s in rock:
        assert math.isclose(s.material.friction_angle_deg, min(30.0, phi))
        # cohesion: min(2e5, 1e5, 0.5 x 0 + 0.5 x 1e5); tension: min(1e4, 1e4, 0.5 x 0 + 0.5 x 1e4)
        assert math.isclose(s.material.cohesion_pa, 0.5e5) and math.isclose(s.material.tensile_strength_pa, 0.5e4)


def test_bad_input_names_key_and_number():
    msg = scene_error(scene(rock_mass__0__joint_sets__1__spacing_m=0.0))
    assert "rock_mass[0].joint_sets[1].spacing_m" in msg and "0.0" in msg
    msg = scene_error(scene(rock_mass__0__min_block_size_m=2.0))  # the whole region is smaller than that
    assert "rock_mass[0].min_block_size_m" in msg and "= 2 m" in msg
    flat = scene(rock_mass__0__region={"vertices_m": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]})
    assert "rock_mass[0].region.vertices_m" in scene_error(flat)
    d = scene()
    del d["rock_mass"][0]["material"]
    msg = scene_error(d)
    assert "rock_mass[0].joint_sets[2].persistence" in msg and "0.5" in msg
    msg = scene_error(scene(rock_mass__0__joint_sets=[]))
    assert "rock_mass[0].joint_sets" in msg
    d = scene(rock_mass__0__joint_sets__0__dip_direction_deg=45.0)
    d["simulation"]["dimension"] = 2
    d["blocks"] = [{"name": "floor", "shape": "box", "size_m": [4.0, 0.5, 1.0], "position_m": [0.5, -0.25, 0.0], "kind": "fixed"}]
    d["rock_mass"][0]["region"] = {"box_min_m": [0.0, 0.0], "box_max_m": [1.0, 0.6]}
    msg = scene_error(d)
    assert "rock_mass[0].joint_sets[0].dip_direction_deg" in msg and "45" in msg


def test_2d_rock_mass():
    from rockwave.build.rocks import block_specs

    d = scene()
    d["simulation"]["dimension"] = 2
    d["blocks"] = [{"name": "floor", "shape": "box", "size_m": [4.0, 0.5, 1.0], "position_m": [0.5, -0.25, 0.0], "kind": "fixed"}]
    d["rock_mass"][0]["region"] = {"box_min_m": [0.0, 0.0], "box_max_m": [1.0, 0.6], "depth_m": 0.5}
    d["rock_mass"][0]["joint_sets"] = [{"dip_deg": 90, "dip_direction_deg": 90, "spacing_m": 0.5},
                                       {"dip_deg": 0, "dip_direction_deg": 270, "spacing_m": 0.3}]
    rock = [s for s in block_specs(parse_scene(d)) if s.name.startswith("rock_")]
    assert len(rock) == 4 and abs(sum(s.geometry.volume for s in rock) - 0.3) < 1e-12
    assert all(abs(s.position[2]) < 1e-12 for s in rock)


def test_cut_rock_mass_settles_under_gravity():
    import rockwave

    sim = rockwave.Simulation(parse_scene(scene()), device="cpu")
    assert sim.blocks.num_blocks == 9
    x0 = sim.block_positions().copy()
    sim.advance(0.05)
    x, v = sim.block_positions(), sim.block_velocities()
    assert np.isfinite(x).all() and np.abs(x - x0).max() < 1e-4  # resting: settles by the contact compliance only
    assert np.abs(v).max() < 1e-2
    assert (x[1:, 2] > 0.1).all()  # still on the floor, none fell through


def test_mesh_region_in_a_scene(tmp_path):
    from rockwave.build.rocks import block_specs

    top = 3 - 2 / math.tan(math.radians(40))
    slope = trimesh.convex.convex_hull(np.array([[0, 0, 0], [3, 0, 0], [0, 1, 0], [3, 1, 0], [0, 0, 2], [0, 1, 2],
                                                 [top, 0, 2], [top, 1, 2]], float))
    slope.export(tmp_path / "slope.stl")
    _l_mesh().export(tmp_path / "l.stl")
    d = scene(rock_mass__0__region={"mesh": "slope.stl"})
    d["blocks"][0].update(size_m=[6.0, 4.0, 0.5], position_m=[1.5, 0.5, -0.25])
    rock = [s for s in block_specs(parse_scene(d, tmp_path / "s.toml")) if s.name.startswith("rock_")]
    stored = trimesh.load(tmp_path / "slope.stl")  # STL keeps float32 vertices
    vol = np.array([s.geometry.volume for s in rock])
    assert abs(vol.sum() / stored.volume - 1) < 1e-9
    # the blocks' centroids and shared shapes put the mass where the slope has it
    com = (vol[:, None] * np.array([s.position for s in rock])).sum(axis=0) / vol.sum()
    assert np.allclose(com, stored.center_mass, atol=1e-9)
    eq = ConvexHull(stored.vertices).equations
    for s in rock:  # each block's world vertices lie in the slope
        w = s.geometry.vertices + np.asarray(s.position)
        assert (w @ eq[:, :3].T + eq[:, 3] < 1e-6).all()
    with pytest.raises(SceneError) as e:
        # joint planes at x = 0.2 + 0.5 k and z = 0.3 k: none runs through the concave edge (x = 1, z = 1)
        block_specs(parse_scene(scene(rock_mass__0__region={"mesh": "l.stl"}, rock_mass__0__joint_sets__0__offset_m=0.2),
                                tmp_path / "s.toml"))
    assert "rock_mass[0].region.mesh" in str(e.value) and "not one convex piece" in str(e.value)


def test_irregular_blocks_settle_without_blowing_up():
    """Oblique sets: wedges and irregular blocks, slivers merged, resting on the floor and on each other."""
    import rockwave

    d = scene(rock_mass__0__seed=4, rock_mass__0__min_block_size_m=0.12, rock_mass__0__joint_sets=[
        {"dip_deg": 60, "dip_direction_deg": 30, "spacing_m": 0.3, "random_offset": True},
        {"dip_deg": 70, "dip_direction_deg": 200, "spacing_m": 0.35, "random_offset": True},
        {"dip_deg": 15, "dip_direction_deg": 100, "spacing_m": 0.25, "random_offset": True}])
    d["simulation"]["duration_s"] = 0.01
    sim = rockwave.Simulation(parse_scene(d), device="cpu")
    assert sim.blocks.num_blocks > 10
    x0 = sim.block_positions().copy()
    sim.advance(0.01)  # free fall would reach 0.1 m/s and 0.5 mm
    x, v = sim.block_positions(), sim.block_velocities()
    assert np.isfinite(x).all() and np.abs(x - x0).max() < 2e-4 and np.abs(v).max() < 0.03


def test_rock_mass_blocks_in_hazard_and_substep_errors():
    """A rock mass's blocks (name_i) are blocks of the scene for [hazard] slides, and a rock mass too stiff for
    multi-rate sub-stepping is refused naming its own stiffness key."""
    import tomllib
    from pathlib import Path

    import rockwave

    d = scene()
    d["hazard"] = {"slides": [{"block": "rock_3"}]}
    parse_scene(d)  # no error: rock_3 is one of the rock mass's blocks
    d["hazard"] = {"slides": [{"block": "granite_3"}]}
    with pytest.raises(SceneError, match=r"hazard\.slides\[0\]\.block"):
        parse_scene(d)
    path = Path(__file__).resolve().parent.parent / "scenes" / "submarine_slide_2d.toml"
    d = tomllib.loads(path.read_text())
    d["fluid"]["spacing_m"] = 0.04
    d["rock_mass"] = [{"name": "boulders", "region": {"box_min_m": [2.6, 0.0], "box_max_m": [3.0, 0.2], "depth_m": 0.1},
                       "material": {"normal_stiffness_n_m": 1.0e14},
                       "joint_sets": [{"dip_deg": 90, "dip_direction_deg": 90, "spacing_m": 0.2}]}]
    with pytest.raises(SceneError, match=r"rock_mass\[0\]\.material\.normal_stiffness_n_m") as e:
        rockwave.Simulation(parse_scene(d, path, path.parent), device="cpu")
    assert "'boulders_" in str(e.value)
