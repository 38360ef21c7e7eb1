"""Non-convex blocks: a closed non-convex mesh -> one rigid compound block of CoACD convex parts
(rockwave/dda/geometry.py decompose, rockwave/dda/blocks.py CompoundPart, kernels/dda/blocks.py compound_loads)."""

import numpy as np
import pytest
import trimesh
import warp as wp

from rockwave.base.maths import euler_xyz_deg_to_quat, quat_to_matrix
from rockwave.base.solver import TimeStep
from rockwave.build.rocks import block_specs
from rockwave.dda import geometry as G
from rockwave.dda.blocks import BlockModel, BlockSolver, BlockSpec, CompoundPart, ContactMaterial
from rockwave.scene.format import SceneError, parse_scene

DEVICE = "cpu"
RHO = 2600.0
G_Z = 9.81


def extruded(poly_xz, reflex: int, depth: float = 0.5) -> trimesh.Trimesh:
    """Closed prism: a simple polygon in x-z (star-shaped from vertex ``reflex``), extruded along y."""
    poly = np.asarray(poly_xz, float)
    n = len(poly)
    V = np.array([(x, -depth / 2, z) for x, z in poly] + [(x, depth / 2, z) for x, z in poly])
    F = []
    for k in range(n):
        i, j = (reflex + k) % n, (reflex + k + 1) % n
        if reflex not in (i, j):
            F += [(reflex, j, i), (n + reflex, n + i, n + j)]
    for i in range(n):
        j = (i + 1) % n
        F += [(i, j, n + j), (i, n + j, n + i)]
    m = trimesh.Trimesh(V, F, process=False)
    if m.volume < 0:
        m.invert()
    return m


def l_mesh(a=1.0, t=0.25, depth=0.5):
    """An L: legs of length a and thickness t along +x and +z from the corner at the origin."""
    return extruded([(0, 0), (a, 0), (a, t), (t, t), (t, a), (0, a)], reflex=3, depth=depth)


def hook_mesh():
    """A hook: an arm on top (x -0.5 .. 0.25, z 0 .. 0.2) and a drop (x 0.05 .. 0.25, z -0.8 .. 0)."""
    return extruded([(-0.5, 0), (0.05, 0), (0.05, -0.8), (0.25, -0.8), (0.25, 0.2), (-0.5, 0.2)], reflex=1)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """One decomposition cache for the module (CoACD runs once per mesh)."""
    return G.Decomposition(cache_dir=str(tmp_path_factory.mktemp("cache")))


def compound(mesh, opt, name="rock"):
    c = G.from_trimesh(mesh, name, opt)
    assert isinstance(c, G.CompoundBlock)
    return c


def compound_specs(c, position, q=(0, 0, 0, 1), **kw):
    return [BlockSpec(geometry=g, position=tuple(position), orientation=q, density=RHO, compound=CompoundPart(c, k),
                      name=f"{c.name}.part{k}", **kw) for k, g in enumerate(c.parts)]


def plane(top=0.0, friction=30.0):
    return BlockSpec(geometry=G.box((8.0, 8.0, 0.4)), position=(0.0, 0.0, top - 0.2), kind="fixed", name="ground",
                     material=ContactMaterial(friction_angle_deg=friction))


def run(model, seconds, record=None):
    solver = BlockSolver(model)
    state = model.state()
    dt = solver.stable_dt(state)
    dta = wp.array([dt], dtype=float, device=DEVICE)
    for k in range(int(round(seconds / dt))):
        solver.step(state, TimeStep(dt, state.time, dta))
        if record is not None and record(solver, state) is False:
            break
    return solver, state


def lowest_z(c, q, x):
    return float((c.mesh_vertices @ quat_to_matrix(q).T + np.asarray(x))[:, 2].min())


def test_mass_properties_are_the_original_mesh(cache):
    m = l_mesh()
    c = compound(m, cache)
    assert c.num_parts >= 2
    ref = m.mass_properties
    assert c.volume == pytest.approx(ref["volume"], rel=1e-12)
    np.testing.assert_allclose(c.origin_offset, ref["center_mass"], atol=1e-12)
    np.testing.assert_allclose(c.inertia_unit, ref["inertia"], atol=1e-12)
    assert abs(c.volume_error) < 0.02  # the parts fill the L
    model = BlockModel(compound_specs(c, c.origin_offset), device=DEVICE)
    for b in range(c.num_parts):  # every part carries the body's mass and inertia, not its own
        assert model.np["mass"][b] == pytest.approx(RHO * ref["volume"], rel=1e-12)
        np.testing.assert_allclose(model.np["inertia"][b], RHO * np.asarray(ref["inertia"]), rtol=1e-12, atol=1e-9)
    assert list(model.body_of) == [0] * c.num_parts and model.lead.sum() == 1
    # parts in the body frame: together they cover the mesh's vertices
    allv = np.concatenate([p.vertices for p in c.parts])
    for v in c.mesh_vertices:
        assert np.min(np.linalg.norm(allv - v, axis=1)) < 0.02


def test_cache_hit_on_second_load(tmp_path, monkeypatch):
    cache = G.Decomposition(cache_dir=str(tmp_path / "cache"))
    first = compound(l_mesh(), cache)
    assert not first.cached
    import coacd

    def no_coacd(*a, **k):
        raise AssertionError("CoACD ran although the decomposition is cached")

    monkeypatch.setattr(coacd, "run_coacd", no_coacd)
    second = compound(l_mesh(), cache)
    assert second.cached and second.num_parts == first.num_parts
    for a, b in zip(first.parts, second.parts):
        np.testing.assert_array_equal(a.vertices, b.vertices)
    # the same shape at another scale and place: the same (normalised) entry, the parts scaled with it
    big = l_mesh()
    big.apply_scale(2.0)
    big.apply_translation((5.0, -1.0, 3.0))
    third = compound(big, cache)
    assert third.cached and third.num_parts == first.num_parts
    assert third.parts_volume == pytest.approx(8 * first.parts_volume, rel=1e-6)
    # another concavity is another decomposition: not served from this cache entry
    with pytest.raises(G.DecompositionError, match="decomposition failed"):
        compound(l_mesh(), G.Decomposition(concavity=0.1, cache_dir=cache.cache_dir))


def test_l_block_rests_on_its_two_feet(cache):
    """An L turned corner-up (a Lambda) dropped 5 mm onto a plane comes to rest on both leg tips:
    contacts on both parts, each carrying half the weight (the L is symmetric about its bisector)."""
    c = compound(l_mesh(), cache)
    q = euler_xyz_deg_to_quat((0.0, 135.0, 0.0))
    x = np.zeros(3)
    x[2] = 0.005 - lowest_z(c, q, x)
    model = BlockModel([plane()] + compound_specs(c, x, q), device=DEVICE)
    solver, state = run(model, 0.5)
    parts = range(1, 1 + c.num_parts)
    xs, qs = state.positions_numpy(), state.orientations_numpy()
    for b in parts:  # one rigid body: every part at the same pose, bit for bit
        np.testing.assert_array_equal(xs[b], xs[1])
        np.testing.assert_array_equal(qs[b], qs[1])
    assert np.linalg.norm(state.velocities_numpy()[1]) < 2e-3
    assert np.linalg.norm(state.angular_velocities_numpy()[1]) < 2e-3
    assert abs(lowest_z(c, qs[1], xs[1])) < 1e-4  # on the plane (penalty sinks ~1e-6 m)
    weight = c.mass(RHO) * G_Z
    load = {}
    for ct in solver.contacts(state):
        i, j = ct["blocks"]
        if 0 in (i, j):
            load[j if i == 0 else i] = load.get(j if i == 0 else i, 0.0) + float(np.sum(ct["normal_forces"]))
    feet = [b for b in parts if load.get(b, 0.0) > 0.0]
    assert len(feet) == 2, load
    assert sum(load.values()) == pytest.approx(weight, rel=0.02)
    for b in feet:
        assert load[b] == pytest.approx(weight / 2, rel=0.05)


def test_fall_matches_convex_block_with_the_same_mass_properties(cache):
    """Until contact, a spinning compound L moves as a convex box with the L's mass, principal moments
    and principal axes (box edges a_i^2 = 6 (I_j + I_k - I_i) / m)."""
    c = compound(l_mesh(), cache)
    mass = c.mass(RHO)
    I = c.inertia(RHO)
    lam, P = np.linalg.eigh(I)
    if np.linalg.det(P) < 0:
        P[:, 2] = -P[:, 2]
    edges = np.sqrt([6 * (lam[1] + lam[2] - lam[0]) / mass, 6 * (lam[0] + lam[2] - lam[1]) / mass,
                     6 * (lam[0] + lam[1] - lam[2]) / mass])
    box = G.box(edges, name="box")
    from scipy.spatial.transform import Rotation

    q0 = euler_xyz_deg_to_quat((10.0, 20.0, 30.0))
    R0 = quat_to_matrix(q0)
    qbox = tuple(Rotation.from_matrix(R0 @ P).as_quat())
    w0, v0 = (1.5, -2.0, 0.7), (0.3, 0.0, 0.0)
    xL, xB = np.array([0.0, -3.0, 1.5]), np.array([0.0, 3.0, 1.5])
    specs = [plane(), BlockSpec(geometry=box, position=tuple(xB), orientation=qbox, density=mass / np.prod(edges),
                                velocity=v0, angular_velocity=w0, name="box")]
    specs += compound_specs(c, xL, q0, velocity=v0, angular_velocity=w0)
    model = BlockModel(specs, device=DEVICE)
    assert model.np["mass"][1] == pytest.approx(mass, rel=1e-12)
    np.testing.assert_allclose(model.np["inertia"][1], np.diag(lam), rtol=1e-9, atol=1e-9 * lam.max())
    seen = {"steps": 0, "contact": False}

    def compare(solver, state):
        if state.contact_counts().any():
            seen["contact"] = True
            return False
        seen["steps"] += 1
        x, q = state.positions_numpy(), state.orientations_numpy()
        w = state.angular_velocities_numpy()
        np.testing.assert_allclose(x[2] - xL, x[1] - xB, atol=2e-5)
        np.testing.assert_allclose(w[2], w[1], rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(quat_to_matrix(q[2]) @ P, G.quat_to_matrix(q[1]), atol=1e-4)

    run(model, 1.0, record=compare)
    assert seen["contact"] and seen["steps"] > 100  # the spin changed the axes a lot before the contact ended it


def test_hook_hangs_over_a_ledge(cache):
    """A hook whose centroid lies past the ledge's edge tips until its drop leans on the ledge's face,
    and stays hooked (its hull would overlap the ledge: only the parts can hang on it)."""
    c = compound(hook_mesh(), cache)
    ledge = BlockSpec(geometry=G.box((1.0, 1.0, 1.5)), position=(-0.5, 0.0, -0.75), kind="fixed", name="ledge",
                      material=ContactMaterial(friction_angle_deg=35.0))
    assert c.origin_offset[0] > 0.0  # the centroid is past the edge: it would tip off without the drop
    x = c.origin_offset + np.array([0.0, 0.0, 0.001])
    model = BlockModel([ledge] + compound_specs(c, x, material=ContactMaterial(friction_angle_deg=35.0)), device=DEVICE)
    solver, state = run(model, 1.0)  # it swings against the face and settles by ~0.9 s
    xe = state.positions_numpy()[1]
    assert np.linalg.norm(state.velocities_numpy()[1]) < 5e-3
    assert abs(xe[2] - x[2]) < 0.05 and abs(xe[0] - x[0]) < 0.06  # hooked, not fallen
    touching = {ct["blocks"][1] for ct in solver.contacts(state) if ct["blocks"][0] == 0 and np.sum(ct["normal_forces"]) > 0}
    assert len(touching) == 2  # on the arm (ledge top) and the drop (ledge face)


# ---- scene keys and errors ----


def _scene(tmp_path, mesh, **block):
    path = tmp_path / "rock.stl"
    mesh.export(path)
    b = {"name": "rock", "shape": "mesh", "mesh": "rock.stl", "decomposition": {"cache_dir": "cache"}}
    b.update(block)
    d = {"simulation": {"dimension": 3, "duration_s": 0.01}, "blocks": [b]}
    return parse_scene(d, tmp_path / "s.toml", base_dir=tmp_path)


def test_scene_builds_compound_and_reports(tmp_path):
    specs = block_specs(_scene(tmp_path, l_mesh(), position_m=[0.0, 0.0, 2.0]))
    assert all(s.compound is not None for s in specs) and len(specs) >= 2
    assert specs[0].name == "rock.part0" and specs[0].position == (0.0, 0.0, 2.0)
    assert (tmp_path / "cache" / "decompositions").exists() is False and any((tmp_path / "cache").glob("*.npz"))
    assert "convex parts" in specs[0].compound.body.summary()


def test_part_bound_error_names_key_and_count(tmp_path):
    n = len(block_specs(_scene(tmp_path, l_mesh())))  # the parts without a tight bound (max_parts 32)
    assert n >= 2
    with pytest.raises(SceneError) as e:
        block_specs(_scene(tmp_path, l_mesh(), decomposition={"cache_dir": "cache", "max_parts": n - 1}))
    assert "blocks[0].decomposition.max_parts" in str(e.value)
    assert f"into {n} convex parts" in str(e.value) and f"max_parts = {n - 1}" in str(e.value)


def test_open_mesh_is_refused(tmp_path):
    m = l_mesh()
    m = trimesh.Trimesh(m.vertices, m.faces[:-1], process=False)
    with pytest.raises(SceneError, match=r"blocks\[0\]\.mesh.*not watertight"):
        block_specs(_scene(tmp_path, m))


def test_deformable_compound_is_refused(tmp_path):
    with pytest.raises(SceneError, match=r"blocks\[0\]\.kind.*rigid compound"):
        block_specs(_scene(tmp_path, l_mesh(), kind="deformable"))


def test_usd_shows_the_original_mesh_moving(tmp_path, capsys):
    """One USD prim per compound block: the original mesh's points (body frame) moved by the body's pose;
    the run prints what the mesh became."""
    from pxr import Usd, UsdGeom

    import rockwave
    from rockwave.app.run import run as run_scene

    scene = _scene(tmp_path, l_mesh(), position_m=[0.0, 0.0, 2.0], angular_velocity_rad_s=[0.0, 1.0, 0.0])
    scene.simulation["duration_s"] = 0.1
    scene.simulation["device"] = "cpu"
    scene.output["frame_rate_hz"] = 20.0
    sim = rockwave.Simulation(scene, device="cpu")
    assert "block 'rock': non-convex mesh -> " in capsys.readouterr().out
    run_scene(sim, tmp_path / "out", progress=False)
    stage = Usd.Stage.Open(str(tmp_path / "out" / "frames.usdc"))
    meshes = [p for p in stage.Traverse() if p.GetTypeName() == "Mesh"]
    assert [str(p.GetPath()) for p in meshes] == ["/World/blocks/rock"]  # no part prims
    mesh = UsdGeom.Mesh(meshes[0])
    body = sim.blocks.specs[0].compound.body
    np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get()), body.mesh_vertices, atol=1e-6)
    assert len(mesh.GetFaceVertexCountsAttr().Get()) == len(body.mesh_triangles)
    end = stage.GetEndTimeCode()
    x = np.array(meshes[0].GetAttribute("xformOp:translate").Get(end))
    np.testing.assert_allclose(x, sim.block_state.positions_numpy()[0], atol=1e-6)
    assert x[2] < 2.0 - 0.5 * G_Z * 0.09 ** 2  # it fell


def test_water_load_on_one_part_moves_the_body_over_multirate_substeps(cache):
    """Multi-rate stepping (BlockSolver.substeps) holds the coupling's load over the sub-steps: a load on
    one part only (water touching one leg) gives the whole body the impulse dt F and the angular impulse
    dt tau about its centroid (no gravity, no contact, from rest), and every part keeps one pose bit for bit."""
    c = compound(l_mesh(), cache)
    model = BlockModel(compound_specs(c, (0.0, 0.0, 2.0)), device=DEVICE, gravity=(0.0, 0.0, 0.0))
    solver, state = BlockSolver(model), model.state()
    F, tau = np.array([30.0, -10.0, 50.0]), np.array([2.0, 5.0, -1.0])
    ext_f, ext_t = np.zeros((c.num_parts, 3), np.float32), np.zeros((c.num_parts, 3), np.float32)
    ext_f[1], ext_t[1] = F, tau
    state.ext_force.assign(ext_f)
    state.ext_torque.assign(ext_t)
    n = 4
    dt = n * 0.5 * solver.critical_dt()
    solver.substeps(state, TimeStep(dt, 0.0, wp.array([dt], dtype=float, device=DEVICE)), n)
    v, w = state.velocities_numpy(), state.angular_velocities_numpy()
    x, q = state.positions_numpy(), state.orientations_numpy()
    assert np.all(v == v[0]) and np.all(w == w[0]) and np.all(x == x[0]) and np.all(q == q[0])
    np.testing.assert_allclose(v[0], dt * F / c.mass(RHO), rtol=1e-4)
    # w(t) solves I_w(t) w' = tau - w x I_w w, close to I^-1 tau t for the small spin reached here
    Iw = quat_to_matrix(q[0]) @ c.inertia(RHO) @ G.quat_to_matrix(q[0]).T
    np.testing.assert_allclose(Iw @ w[0], dt * tau, rtol=2e-3, atol=1e-3 * np.linalg.norm(dt * tau))
