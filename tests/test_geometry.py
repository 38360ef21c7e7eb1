"""Convex block geometry: half-edge invariants, mass properties, mesh validation."""

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from rockwave.dda import geometry as G

WEDGE = [[0, 0, 0], [2, 0, 0], [0, 0, 1], [0, 1.5, 0], [2, 1.5, 0], [0, 1.5, 1]]


def _shapes():
    return {
        "box": G.box((1.0, 2.0, 3.0)),
        "wedge": G.prism(WEDGE, name="wedge"),
        "icosphere": G.from_trimesh(trimesh.creation.icosphere(subdivisions=2, radius=0.7), "icosphere"),
        "cylinder_hull": G.from_trimesh(trimesh.creation.cylinder(radius=0.5, height=1.0, sections=12), "cyl"),
    }


@pytest.mark.parametrize("name", ["box", "wedge", "icosphere", "cylinder_hull"])
def test_half_edge_invariants(name):
    p = _shapes()[name]
    inv = G.half_edge_invariants(p)
    assert all(inv.values()), inv
    # Euler V - E + F = 2 explicitly
    assert p.num_vertices - p.num_half_edges // 2 + p.num_faces == 2


def test_coplanar_triangles_merged_and_counts():
    b = G.box((1, 1, 1))
    assert (b.num_vertices, b.num_faces, b.num_half_edges) == (8, 6, 24)
    assert all(len(f) == 4 for f in b.faces)
    w = G.prism(WEDGE)
    assert (w.num_vertices, w.num_faces) == (6, 5)
    assert sorted(len(f) for f in w.faces) == [3, 3, 4, 4, 4]
    c = _shapes()["cylinder_hull"]
    assert c.num_faces == 12 + 2  # 12 side quads + two 12-gon caps


def test_mass_properties_box_and_wedge():
    sx, sy, sz = 1.0, 2.0, 3.0
    b = G.box((sx, sy, sz))
    assert b.volume == pytest.approx(6.0)
    V = 6.0
    expect = V / 12.0 * np.array([sy**2 + sz**2, sx**2 + sz**2, sx**2 + sy**2])
    assert np.allclose(np.diag(b.inertia_unit), expect)
    assert np.allclose(b.vertices.mean(axis=0), 0.0)
    assert b.bounding_radius == pytest.approx(0.5 * np.sqrt(14.0))
    w = G.prism(WEDGE)
    assert w.volume == pytest.approx(0.5 * 2 * 1 * 1.5)
    # triangle-prism centroid at (2/3, 0.75, 1/3) in the input frame
    assert np.allclose(w.origin_offset, [2 / 3, 0.75, 1 / 3])
    # face planes: all vertices behind, offsets positive (centroid inside)
    assert np.all(w.face_offsets > 0)


def test_walk_faces_around_vertex_is_order_valence():
    b = G.box((1, 1, 1))
    for v in range(b.num_vertices):
        h0 = b.vertex_out_he[v]
        faces = []
        h = h0
        while True:
            faces.append(b.he_face[h])
            h = b.he_twin[b.he_prev[h]]
            if h == h0:
                break
        assert len(faces) == 3 and len(set(faces)) == 3
        # each of those faces contains v
        assert all(v in b.faces[f] for f in faces)


def test_non_convex_refused_with_ratio_and_advice():
    # an L-shaped solid: union of two boxes
    a = trimesh.creation.box((2, 1, 1))
    c = trimesh.creation.box((1, 1, 1))
    c.apply_translation((-0.5, 0, 1))
    lshape = trimesh.boolean.union([a, c], engine="manifold") if trimesh.boolean.engines_available else None
    if lshape is None:
        lshape = trimesh.creation.annulus(r_min=0.5, r_max=1.0, height=1.0)
    with pytest.raises(G.GeometryError) as ei:
        G.from_trimesh(lshape, "lshape.stl")
    msg = str(ei.value)
    assert "lshape.stl" in msg and "not convex" in msg and "hull" in msg and "convex parts" in msg


def test_annulus_refused():
    with pytest.raises(G.GeometryError, match="not convex"):
        G.from_trimesh(trimesh.creation.annulus(r_min=0.5, r_max=1.0, height=1.0), "ring")


def test_open_mesh_refused():
    m = trimesh.creation.box((1, 1, 1))
    m.update_faces(np.arange(len(m.faces)) != 0)  # drop one triangle
    with pytest.raises(G.GeometryError, match="watertight"):
        G.from_trimesh(m, "open_box")


def test_degenerate_refused():
    with pytest.raises(G.GeometryError, match="degenerate|zero"):
        G.prism([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], name="flat")


def test_inverted_normals_fixed_with_warning():
    m = trimesh.creation.box((1, 2, 1))
    m.invert()
    with pytest.warns(UserWarning, match="inverted"):
        p = G.from_trimesh(m, "inv")
    assert p.volume == pytest.approx(2.0)
    assert all(G.half_edge_invariants(p).values())


def test_load_mesh_single_and_multi(tmp_path):
    m = trimesh.creation.box((1, 1, 2))
    m.apply_translation((3, 0, 0))
    f1 = tmp_path / "rock.stl"
    m.export(f1)
    p = G.load_mesh(f1)
    assert isinstance(p, G.ConvexPolyhedron) and p.volume == pytest.approx(2.0)
    assert np.allclose(p.origin_offset, [3, 0, 0])
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box((1, 1, 1)), node_name="a", geom_name="a")
    b = trimesh.creation.icosphere(1)
    b.apply_translation((5, 0, 0))
    scene.add_geometry(b, node_name="b", geom_name="b")
    f2 = tmp_path / "two.glb"
    scene.export(f2)
    parts = G.load_mesh(f2)
    assert isinstance(parts, list) and len(parts) == 2
    assert sorted(round(q.volume, 6) for q in parts)[0] == pytest.approx(1.0)
    with pytest.raises(G.GeometryError, match="does not exist"):
        G.load_mesh(tmp_path / "missing.obj")


@settings(max_examples=15, deadline=None)
@given(st.integers(min_value=0, max_value=10_000), st.integers(min_value=8, max_value=40))
def test_random_hulls_keep_invariants(seed, n):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3)) * np.array([1.0, 0.5, 2.0])
    p = G.prism(pts, name=f"rand{seed}")
    inv = G.half_edge_invariants(p)
    assert all(inv.values()), inv
    hull = trimesh.convex.convex_hull(pts)
    assert p.volume == pytest.approx(hull.volume, rel=1e-9)
