"""Render-ready outputs: fluid surface (3D mesh, 2D contour), USD time samples, ParaView series,
preview and plot commands."""

import json
from pathlib import Path

import numpy as np
import pytest
import warp as wp

import rockwave
from rockwave.app.cli import main
from rockwave.app.plot import gauge_series, read_reference
from rockwave.app.preview import PreviewError, load_frame
from rockwave.output import vtk
from rockwave.output.surface import SurfaceExtractor

from conftest import DEVICE
from helpers import DATA, tank_2d, with_changes

S = 0.02  # particle spacing of the 3D tests


def _lattice(counts, s):
    g = np.stack(np.meshgrid(*[np.arange(n) for n in counts], indexing="ij"), -1).reshape(-1, len(counts))
    x = np.zeros((len(g), 3))
    x[:, : len(counts)] = (g + 0.5) * s
    return x


def _extract(x, dim, s, **kw):
    xa = wp.array(x.astype(np.float32), dtype=wp.vec3, device=DEVICE)
    rho = wp.array(np.full(len(x), 1000.0, np.float32), dtype=float, device=DEVICE)
    return SurfaceExtractor(dim, s, 1000.0 * s**dim, DEVICE, **kw).extract(xa, rho)


def _tank_3d(depth=0.08, **output):
    return {
        "simulation": {"dimension": 3, "duration_s": 0.05},
        "fluid": {"spacing_m": S, "eos": {"speed_of_sound_m_s": 20.0}, "viscosity": {"artificial_alpha": 0.3},
                  "regions": [{"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [0.12, 0.12, depth]}]},
        "tank": {"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [0.12, 0.12, 0.2]},
        "output": {"frame_rate_hz": 40.0, **output},
    }


@pytest.mark.parametrize("field", ["colour", "metaball"])
@pytest.mark.parametrize("resolution", [None, 0.5 * S])  # the default cell (one spacing in 3D) and half of it
def test_lattice_box_surface_is_flat_at_the_top_of_the_water(field, resolution):
    m = _extract(_lattice((6, 6, 5), S), 3, S, field=field, resolution_m=resolution)  # water fills [0, 0.12]^2 x [0, 0.1]
    p, n = m.points, m.normals()
    assert len(m.triangles) > (100 if resolution else 40) and m.triangles.max() < len(p)
    top = (p[:, 2] > 0.08) & (np.abs(n[:, 2]) > 0.9) & np.all((p[:, :2] > 0.03) & (p[:, :2] < 0.09), axis=1)
    assert top.sum() > (20 if resolution else 3)  # the vertices over the middle 0.06 x 0.06 m
    assert np.abs(p[top, 2] - 0.1).max() < 0.05 * S  # flat, at the height the particles stand for
    assert (n[top, 2] > 0.9).all()  # normals point out of the water (up)
    c = p.mean(axis=0)
    assert (np.einsum("ij,ij->i", p - c, n) > 0).mean() > 0.95  # and outward all round


@pytest.mark.parametrize("field", ["colour", "metaball"])
def test_default_grid_of_one_spacing_keeps_a_resting_box_flat_at_its_height(field):
    """The default 3D cell is one particle spacing (rockwave/output/surface.py default_cell). Whatever the grid's
    offset against the particles (the box passed in shifted by a fraction of a cell), the top of a resting box of
    water is flat at its height within a tenth of a spacing, as on a grid of half a spacing; the buffers are kept
    from frame to frame and a second frame gives the same mesh."""
    x = _lattice((8, 8, 6), S)  # water fills [0, 0.16]^2 x [0, 0.12]
    xa = wp.array(x.astype(np.float32), dtype=wp.vec3, device=DEVICE)
    rho = wp.array(np.full(len(x), 1000.0, np.float32), dtype=float, device=DEVICE)
    for res in (None, 0.5 * S):
        ex = SurfaceExtractor(3, S, 1000.0 * S**3, DEVICE, field=field, resolution_m=res)
        assert ex.cell == (S if res is None else res)
        for off in np.linspace(0.0, 1.0, 5)[:-1]:
            m = ex.extract(xa, rho, x.min(axis=0) - off * ex.cell, x.max(axis=0))
            p, n = m.points, m.normals()
            top = (p[:, 2] > 0.1) & (n[:, 2] > 0.9) & np.all((p[:, :2] > 0.04) & (p[:, :2] < 0.12), axis=1)
            assert top.sum() >= 9, (res, off)
            assert np.abs(p[top, 2] - 0.12).max() < 0.1 * S, (res, off)
        kept = {k: b.ptr for k, b in ex._buffers.items()}
        again = ex.extract(xa, rho, x.min(axis=0) - off * ex.cell, x.max(axis=0))
        assert {k: b.ptr for k, b in ex._buffers.items()} == kept  # no new allocation for the same box
        np.testing.assert_array_equal(again.points, m.points)
        np.testing.assert_array_equal(again.triangles, m.triangles)


def _field_reference(x, rho, mass, lower, cell, shape, R, kind, dim, metaball_norm):
    """The surface field written out in numpy (float64), all particles against every node: the colour
    field sum_j m/rho_j W(d, R) with Monaghan's cubic spline (h = R/2), or the metaball field
    sum_j norm (1 - (d/R)^2)^2, over the particles closer than R."""
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    nodes = np.asarray(lower, np.float64) + idx * cell
    d = np.linalg.norm(nodes[:, None, :] - x[None, :, :].astype(np.float64), axis=2)
    if kind == "colour":
        h = 0.5 * R
        q = d / h
        sigma = 1.0 / (np.pi * h**3) if dim == 3 else 10.0 / (7.0 * np.pi * h * h)
        w = sigma * np.where(q < 1.0, 1.0 - 1.5 * q**2 + 0.75 * q**3, 0.25 * np.clip(2.0 - q, 0.0, None) ** 3)
        terms = mass / rho[None, :].astype(np.float64) * w
    else:
        terms = metaball_norm * (1.0 - (d / R) ** 2) ** 2
    return np.where(d < R, terms, 0.0).sum(axis=1).reshape(shape)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("field", ["colour", "metaball"])
def test_surface_field_gather_equals_the_sum_over_all_particles(dim, field):
    """The field gathered from the sorted particle cells (kernels/output/surface.py fluid_field) equals the plain sum
    over every particle, up to float32 round-off: random particles and densities, a cell size that does not
    divide the spacing, runs of 1, 3 and the default nodes per thread, and a box given smaller than the
    particles' (particles outside the grid join its edge cells)."""
    rng = np.random.default_rng(7 + dim)
    s = 0.02
    n = 400 if dim == 3 else 300
    x = np.zeros((n, 3), np.float32)
    x[:, :dim] = rng.uniform(0.0, [0.14, 0.1, 0.12][:dim], size=(n, dim))
    rho = rng.uniform(950.0, 1050.0, n).astype(np.float32)
    mass = 1000.0 * s**dim
    xa = wp.array(x, dtype=wp.vec3, device=DEVICE)
    ra = wp.array(rho, dtype=float, device=DEVICE)
    lo, hi = x.min(axis=0) + 0.06, x.max(axis=0) - 0.02  # the grid (box + R + a cell) leaves particles out
    if dim == 2:
        lo[2] = hi[2] = 0.0
    for run in (1, 3, None):
        ex = SurfaceExtractor(dim, s, mass, DEVICE, resolution_m=0.0073, field=field)
        if run is not None:
            ex.node_run = run
        f, lower, cell = ex.field(xa, ra, lo, hi)
        got = f.numpy()
        ref = _field_reference(x, rho, mass, np.asarray(lower, np.float32), np.float32(cell), got.shape, ex.radius,
                               field, dim, ex.metaball_norm)
        assert got.shape[2] == (1 if dim == 2 else got.shape[2]) and (ref > 0.3).sum() > 50
        np.testing.assert_allclose(got, ref, rtol=2e-5, atol=2e-5 * ref.max())


def test_2d_contour_is_closed_counter_clockwise_and_at_the_right_height():
    m = _extract(_lattice((10, 8), S), 2, S)  # water fills [0, 0.2] x [0, 0.16]
    seg = m.points.reshape(-1, 2, 3)
    assert m.segments.shape == (len(seg), 2) and np.allclose(seg[:, :, 2], 0.0)
    area = 0.5 * np.sum(seg[:, 0, 0] * seg[:, 1, 1] - seg[:, 1, 0] * seg[:, 0, 1])  # shoelace over the segments
    assert area == pytest.approx(0.2 * 0.16, rel=0.05)  # closed, water on the left
    top = seg[(seg[:, :, 1].mean(axis=1) > 0.12) & (np.abs(seg[:, :, 0].mean(axis=1) - 0.1) < 0.06)]
    assert len(top) > 5 and np.abs(top[:, :, 1] - 0.16).max() < 0.05 * S
    assert len(_extract(np.zeros((0, 3)), 2, S).points) == 0


def test_resting_tank_surface_in_the_stage(tmp_path):
    from pxr import Usd

    sim = rockwave.Simulation(rockwave.parse_scene(_tank_3d()), device=DEVICE)
    sim.run(tmp_path, progress=False)
    st = Usd.Stage.Open(str(tmp_path / "frames.usdc"))
    mesh = st.GetPrimAtPath("/World/fluid_surface")
    assert mesh.GetTypeName() == "Mesh" and mesh.GetAttribute("subdivisionScheme").Get() == "none"
    p = np.asarray(mesh.GetAttribute("points").Get(2), np.float64)
    counts = np.asarray(mesh.GetAttribute("faceVertexCounts").Get(2))
    idx = np.asarray(mesh.GetAttribute("faceVertexIndices").Get(2))
    assert (counts == 3).all() and len(idx) == 3 * len(counts) and idx.max() < len(p)
    assert len(mesh.GetAttribute("normals").Get(2)) == len(p)
    x = np.asarray(st.GetPrimAtPath("/World/fluid").GetAttribute("points").Get(2), np.float64)
    inner = np.all((p[:, :2] > 0.03) & (p[:, :2] < 0.09), axis=1) & (p[:, 2] > 0.05)
    assert inner.sum() >= 9  # at least the 3 x 3 vertices of the default grid (one spacing) over the middle
    top = p[inner, 2]
    assert top.max() - top.min() < 0.25 * S  # flat
    layer = x[np.all((x[:, :2] > 0.03) & (x[:, :2] < 0.09), axis=1) & (x[:, 2] > 0.08 - S), 2]
    surface_level = np.median(layer) + 0.5 * S  # half a spacing above the top particle layer
    assert abs(np.median(top) - surface_level) < 0.25 * S
    assert abs(np.median(top) - 0.08) < 0.25 * S  # the depth the tank was filled to


def test_stage_time_samples_match_frames_written(tmp_path):
    from pxr import Usd

    d = with_changes(tank_2d(width=0.1, depth=0.1, height=0.2), **{"simulation.duration_s": 0.1, "output.frame_rate_hz": 50.0,
                                                                  "output.chunk_frames": 2, "output.vtk": "paraview"})
    sim = rockwave.Simulation(rockwave.parse_scene(d), device=DEVICE)
    sim.run(tmp_path, progress=False)
    frames = list(range(6))  # 0.1 s at 50 Hz: frames 0..5
    st = Usd.Stage.Open(str(tmp_path / "frames.usdc"))
    assert (st.GetStartTimeCode(), st.GetEndTimeCode()) == (0, 5) and st.GetTimeCodesPerSecond() == 50.0
    assert len(list((tmp_path / "frames.clips").glob("chunk_*.usdc"))) == 4  # frames [0], [1, 2], [3, 4], [5]
    fluid, surf = st.GetPrimAtPath("/World/fluid"), st.GetPrimAtPath("/World/fluid_surface")
    assert surf.GetTypeName() == "BasisCurves"
    for prim, attr in ((fluid, "points"), (fluid, "primvars:pressure"), (fluid, "primvars:density"), (surf, "points"), (surf, "curveVertexCounts")):
        assert prim.GetAttribute(attr).GetTimeSamples() == frames, attr
    info = st.GetRootLayer().customLayerData["rockwave"]
    assert info["dimension"] == 2 and info["spacing_m"] == pytest.approx(0.01)
    # each frame's contour surrounds that frame's particles
    for f in (0, 5):
        x = np.asarray(fluid.GetAttribute("points").Get(f))
        c = np.asarray(surf.GetAttribute("points").Get(f))
        assert len(surf.GetAttribute("curveVertexCounts").Get(f)) * 2 == len(c)
        assert c[:, 1].max() == pytest.approx(x[:, 1].max() + 0.005, abs=0.004)
    # ParaView series: one .vtu per part and frame, listed in the .pvd at the frame times
    pv = tmp_path / "paraview"
    assert sorted(p.name for p in pv.glob("fluid_*.vtu")) == [f"fluid_{f:05d}.vtu" for f in frames]
    import xml.etree.ElementTree as ET

    ds = ET.parse(pv / "rockwave.pvd").getroot().iter("DataSet")
    times = sorted({float(e.get("timestep")) for e in ds})
    assert times == pytest.approx([f / 50.0 for f in frames])
    a = vtk.read_vtu_arrays(pv / "fluid_00005.vtu")
    n = sim.fluid.n_fluid
    assert len(a["Points"]) == 3 * n and len(a["pressure"]) == n and len(a["velocity"]) == 3 * n
    assert a["density"] == pytest.approx(sim.densities()[:n], rel=1e-5)
    assert (a["types"] == vtk.VTK_VERTEX).all()


def test_vtk_blocks_are_polyhedra(tmp_path):
    import xml.etree.ElementTree as ET

    cube = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    faces = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    path = tmp_path / "b.vtu"
    path.write_bytes(vtk.blocks_vtu([(cube, faces), (cube + 2.0, faces)]))
    root = ET.parse(path).getroot()
    assert root.find(".//Piece").get("NumberOfCells") == "2"
    a = vtk.read_vtu_arrays(path)
    assert list(a["types"]) == [vtk.VTK_POLYHEDRON] * 2 and list(a["offsets"]) == [8, 16]
    f = a["faces"]
    assert f[0] == 6 and list(f[1:6]) == [4, 0, 3, 2, 1] and list(a["faceoffsets"]) == [31, 62]
    assert list(f[31 + 2: 31 + 6]) == [8 + i for i in faces[0]]  # second block's ids shifted


def _png_ok(path: Path):
    import matplotlib.image as mpimg

    assert path.is_file() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = mpimg.imread(path)
    assert img.shape[0] > 100 and img.shape[1] > 100
    assert img[..., :3].std() > 0.02  # something was drawn


def test_preview_and_plot_commands_write_images(tmp_path, capsys):
    ref = tmp_path / "ref.dat"
    ref.write_text("# time (s)\tH1 (m)\tP9 (Pa)\n0.0\t0.10\t1\n0.05\t0.11\t2\n0.1\t0.12\t3\n")
    scene = with_changes(tank_2d(width=0.1, depth=0.1, height=0.2), **{
        "simulation.duration_s": 0.1, "output.frame_rate_hz": 40.0,
        "output.gauges": [{"name": "H1", "kind": "height", "position_m": [0.05, 0.0]},
                          {"name": "P1", "kind": "pressure", "position_m": [0.05, 0.02]}]})

    scene_file = tmp_path / "scene.toml"
    scene_file.write_text(_toml(scene) + f'\n[[output.reference]]\nfile = "{ref.name}"\nlabel = "measured"\n')
    run = tmp_path / "run"
    assert main(["run", str(scene_file), "--out", str(run), "--device", DEVICE, "--quiet"]) == 0
    assert main(["preview", str(run), "--frame", "2"]) == 0
    _png_ok(run / "preview_00002_speed.png")  # named by frame and colour (and view in 3D: issue 42)
    assert main(["preview", str(run), "--color", "pressure", "--out", str(tmp_path / "p.png")]) == 0
    _png_ok(tmp_path / "p.png")
    assert main(["plot", str(run)]) == 0
    _png_ok(run / "gauges.png")
    panels, t0, t1 = gauge_series(run)
    assert (t0, t1) == (0.0, pytest.approx(0.1))
    heights = {label: (t, y) for label, t, y, _ in panels["water height (m)"]}
    assert set(heights) == {"H1", "H1 measured"}  # the reference column of the same name, only
    assert heights["H1 measured"][1] == pytest.approx([0.10, 0.11, 0.12])
    assert [l[0] for l in panels["pressure (Pa)"]] == ["P1"]
    assert main(["preview", str(run), "--frame", "99"]) == 2
    assert "frames 0..4" in capsys.readouterr().err
    assert main(["preview", str(tmp_path)]) == 2  # no stage there


def test_preview_3d_outlines_blocks(tmp_path):
    d = _tank_3d(depth=0.06)
    d["tank"]["box_max_m"] = [0.3, 0.12, 0.2]
    d["blocks"] = [{"name": "rock", "shape": "box", "size_m": [0.05, 0.05, 0.05], "position_m": [0.22, 0.06, 0.025], "kind": "fixed"}]
    d["simulation"]["duration_s"] = 0.025
    rockwave.Simulation(rockwave.parse_scene(d), device=DEVICE).run(tmp_path, progress=False)
    fr = load_frame(tmp_path, 1)
    assert fr["dim"] == 3 and len(fr["x"]) > 0 and len(fr["blocks"]) == 1
    b = fr["blocks"][0]
    assert b.min(axis=0) == pytest.approx([0.195, 0.035, 0.0], abs=1e-4) and b.max(axis=0) == pytest.approx([0.245, 0.085, 0.05], abs=1e-4)
    for args in (["--axis", "y"], ["--axis", "x", "--slice", "0.06", "--color", "pressure"]):
        out = tmp_path / f"p{args[1]}.png"
        assert main(["preview", str(tmp_path), "--out", str(out), *args]) == 0
        _png_ok(out)
    with pytest.raises(PreviewError):
        load_frame(tmp_path, 7)
    panels, _, _ = gauge_series(tmp_path)  # blocks.csv: displacement from the first frame (a fixed block: none)
    (label, t, disp, _), = panels["block displacement (m)"]
    assert label == "rock" and len(t) == 2 and np.allclose(disp, 0.0)
    assert main(["plot", str(tmp_path)]) == 0
    _png_ok(tmp_path / "gauges.png")


def test_reference_table_reads_spheric_headers():
    t, cols = read_reference(DATA / "spheric_test2" / "water_level.dat")
    assert list(cols) == ["H1", "H2", "H3", "H4"] and len(t) == len(cols["H4"]) > 1000
    assert cols["H4"][0] == pytest.approx(0.5466666667) and np.all(np.diff(t) > 0)
    _, p = read_reference(DATA / "spheric_test2" / "pressure.dat")
    assert list(p) == [f"P{i}" for i in range(1, 9)]


def _toml(d: dict, prefix: str = "") -> str:
    """A minimal TOML writer for the scene dicts of these tests."""
    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        return repr(v)

    lines, subs = [], []
    for k, v in d.items():
        if isinstance(v, dict):
            subs.append((k, v))
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            for item in v:
                subs.append((k, [item]))
        else:
            lines.append(f"{k} = {val(v)}")
    out = ([f"[{prefix}]"] if prefix and lines else []) + lines
    for k, v in subs:
        name = f"{prefix}.{k}" if prefix else k
        if isinstance(v, list):
            item = v[0]
            out.append(f"[[{name}]]")
            out += [f"{kk} = {val(vv)}" for kk, vv in item.items()]
        else:
            out.append(_toml(v, name))
    return "\n".join(out)
