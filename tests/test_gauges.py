"""Height gauges read water (rockwave/sim/readers.py Gauges): the top of the continuous water column from the bed,
where the kernel-interpolated water fraction along the gauge's vertical line first drops below 0.5. Still water
reads its level (a lattice whose top particle centres are at z_top: z_top + s/2) within 0.1 spacing, next to walls
and in corners too; water passing overhead with air between does not move the reading (the old definition, the
median of the column tops around the line, did); a dry line reads NaN, also under water in the air; a tilted
surface reads its local height."""

import math

import numpy as np
import pytest

import rockwave
from rockwave.output.batch import BatchHazard
from rockwave.output.hazard import HazardMonitor, flat_metrics
from rockwave.scene.format import parse_scene
from rockwave.sim.batch import BatchSimulation

from conftest import DEVICE
from helpers import gauge_level_reference, tank_2d

S = 0.01  # particle spacing of every scene here


def _height(name, *pos):
    return {"name": name, "kind": "height", "position_m": list(pos)}


def _sim(d, gauges):
    d["output"] = {"gauges": gauges}
    return rockwave.Simulation(parse_scene(d, "gauges.toml"), device=DEVICE)


def _column_top_median(sim, name) -> float:
    """The old height gauge: the plane around the line cut into columns one spacing wide, those whose centre
    lies within H used; the median over the wet columns of their highest particle, + s/2."""
    m, up, dim = sim.fluid, sim.scene.dim - 1, sim.scene.dim
    gg = next(g for g in sim.scene.output.gauges if g.name == name)
    x = sim.state.x.numpy()[: m.n_fluid].astype(np.float64)
    pos = np.array(list(gg.position_m) + [0.0] * (3 - dim))
    horiz = [a for a in range(dim) if a != up]
    ci = [np.floor((x[:, a] - pos[a]) / m.spacing).astype(int) for a in horiz]
    inside = sum(((c + 0.5) * m.spacing) ** 2 for c in ci) < m.support_radius**2
    tops: dict = {}
    for i in np.flatnonzero(inside):
        key = tuple(c[i] for c in ci)
        tops[key] = max(tops.get(key, -np.inf), x[i, up])
    return float(np.median(list(tops.values()))) + 0.5 * m.spacing if tops else math.nan


@pytest.mark.parametrize("kernel", ["muller", "wendland"])
def test_still_water_2d_reads_its_level_within_a_tenth_of_a_spacing(kernel):
    """A 2D tank 0.3 m wide, water 0.15 m deep (top particle centres at 0.145): z_top + s/2 = 0.15 within 0.1 s
    in the middle, half a spacing from the side wall (its particles fill part of the kernel support), at the
    wall's face, and after 0.02 s of stepping; the device matches the definition evaluated in numpy."""
    d = tank_2d(width=0.3, depth=0.15, height=0.3, spacing=S, kernel=kernel)
    sim = _sim(d, [_height("mid", 0.15, 0.0), _height("near_wall", 0.005, 0.0), _height("wall_face", 0.0, 0.0),
                   _height("quarter", 0.2237, 0.0)])
    got = sim.gauges()
    for name, v in got.items():
        assert abs(v - 0.15) < 0.1 * S, (name, (v - 0.15) / S)
        assert v == pytest.approx(gauge_level_reference(sim, name), abs=1e-3 * S), name
    sim.advance(0.02)
    x = sim.positions()
    for name, v in sim.gauges().items():
        top = x[np.abs(x[:, 0] - 0.15) < 0.1, 1].max() + 0.5 * S  # the settled top layer (it sinks a little)
        assert abs(v - top) < 0.2 * S, (name, (v - top) / S)


def test_still_water_3d_reads_its_level_within_a_tenth_of_a_spacing():
    """A 3D tank 0.1 x 0.1 m, water 0.06 m deep: 0.06 within 0.1 s in the middle, next to one wall, in a
    corner (two walls) and off the lattice's lines."""
    d = {
        "simulation": {"dimension": 3, "duration_s": 1.0},
        "fluid": {"spacing_m": S, "eos": {"speed_of_sound_m_s": 20.0}, "viscosity": {"artificial_alpha": 0.3},
                  "regions": [{"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [0.1, 0.1, 0.06]}]},
        "tank": {"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [0.1, 0.1, 0.12]},
    }
    sim = _sim(d, [_height("mid", 0.05, 0.05, 0.0), _height("wall", 0.003, 0.05, 0.0),
                   _height("corner", 0.004, 0.004, 0.0), _height("off", 0.0713, 0.0391, 0.0)])
    for name, v in sim.gauges().items():
        assert abs(v - 0.06) < 0.1 * S, (name, (v - 0.06) / S)
    assert sim.gauges()["mid"] == pytest.approx(gauge_level_reference(sim, "mid"), abs=1e-3 * S)


def test_water_passing_overhead_does_not_count():
    """A blob of water flying at 3 m/s through the air 0.12 m above a 0.08 m deep pool passes over the gauge:
    the old column-top median jumps to the blob's top while the blob covers most of its columns; the water gauge stays at the pool's level.
    A column standing on the pool (no air between) does count."""
    d = tank_2d(width=0.4, depth=0.08, height=0.4, spacing=S)
    d["fluid"]["regions"].append({"box_min_m": [0.02, 0.2], "box_max_m": [0.07, 0.24], "velocity_m_s": [3.0, 0.0]})
    d["fluid"]["regions"].append({"box_min_m": [0.3, 0.08], "box_max_m": [0.34, 0.16]})  # a column on the pool
    sim = _sim(d, [_height("h", 0.15, 0.0), _height("column", 0.32, 0.0)])
    assert sim.gauges()["column"] == pytest.approx(0.16, abs=0.1 * S)
    x = sim.state.x.numpy()  # a thin gap: the pool's top layer (0.075) lifted by 1.5 s to 0.09 over the gauge
    lift = (np.abs(x[:, 0] - 0.15) < 0.06) & (np.abs(x[:, 1] - 0.075) < 1e-4)
    x[lift, 1] += 1.5 * S
    sim.state.x.assign(x)
    assert sim.gauges()["h"] == pytest.approx(0.07, abs=0.15 * S)  # the layer below the gap is the top
    x[lift, 1] -= 1.5 * S
    sim.state.x.assign(x)
    new, old, blob = [], [], []
    while sim.time < 0.045:
        sim.advance(0.0025)
        x = sim.positions()
        b = x[:, 1] > 0.15
        g = sim.gauges()
        new.append(g["h"])
        old.append(_column_top_median(sim, "h"))
        blob.append(abs(x[b, 0].mean() - 0.15) < 0.02)
    new, old, blob = map(np.asarray, (new, old, blob))
    assert blob.sum() >= 3, "the blob passed over the gauge"
    assert old[blob].max() > 0.2, old  # the old definition reads the blob's top (0.24 m) while it covers the line
    assert np.all(np.abs(new - 0.08) < 0.25 * S), (new - 0.08) / S  # the pool's level (it settles a little)
    assert np.all(np.abs(new[blob] - new[~blob].mean()) < 0.1 * S)


def test_dry_line_reads_nan_and_a_wet_one_next_to_it_reads_its_level():
    """Water fills the left half of the tank: a gauge over the dry right half reads NaN (2D and 3D), also with a
    blob of water in the air above it (the water on the line rests on nothing), where the old column-top median
    read the blob's top."""
    d = tank_2d(width=0.4, depth=0.1, height=0.3, spacing=S)
    d["fluid"]["regions"][0]["box_max_m"] = [0.2, 0.1]
    d["fluid"]["regions"].append({"box_min_m": [0.32, 0.15], "box_max_m": [0.38, 0.2]})
    sim = _sim(d, [_height("wet", 0.1, 0.0), _height("dry", 0.27, 0.0), _height("under_blob", 0.35, 0.0)])
    g = sim.gauges()
    assert math.isnan(g["dry"]) and math.isnan(g["under_blob"])
    # the blob's top (0.2 m, lowered 2.4e-5 m by the packed start: each run of water starts at its hydrostatic density)
    assert _column_top_median(sim, "under_blob") == pytest.approx(0.2, abs=0.01 * S)
    assert g["wet"] == pytest.approx(0.1, abs=0.1 * S)
    d3 = {
        "simulation": {"dimension": 3, "duration_s": 1.0},
        "fluid": {"spacing_m": S, "eos": {"speed_of_sound_m_s": 20.0},
                  "regions": [{"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [0.04, 0.04, 0.04]}]},
        "tank": {"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [0.12, 0.04, 0.08]},
    }
    sim3 = _sim(d3, [_height("dry", 0.1, 0.02, 0.0), _height("wet", 0.02, 0.02, 0.0)])
    g3 = sim3.gauges()
    assert math.isnan(g3["dry"]) and g3["wet"] == pytest.approx(0.04, abs=0.1 * S)


def test_tilted_surface_reads_the_local_level():
    """The fluid particles placed on a lattice tilted by 8 degrees (top layer half a spacing below the plane
    z = 0.12 + tan 8deg (x - 0.2)); the others parked far away. Each gauge reads the plane's height at its x
    within 0.1 s, so the readings differ by the slope times their distance."""
    d = tank_2d(width=0.4, depth=0.2, height=0.4, spacing=S)
    gx = [0.1, 0.2, 0.3, 0.02]
    sim = _sim(d, [_height(f"g{i}", x, 0.0) for i, x in enumerate(gx)])
    th = math.radians(8.0)
    t, n = np.array([math.cos(th), math.sin(th)]), np.array([-math.sin(th), math.cos(th)])
    i, j = np.meshgrid(np.arange(-40, 41), np.arange(0, 30), indexing="ij")
    p = np.array([0.2, 0.12]) + np.outer(i.ravel() * S, t) - np.outer((j.ravel() + 0.5) * S, n)
    p = p[(p[:, 0] > 0.5 * S - 1e-9) & (p[:, 0] < 0.4 - 0.5 * S) & (p[:, 1] > 0.5 * S - 1e-9)]
    nf = sim.n_fluid
    assert len(p) <= nf
    x = sim.state.x.numpy()
    x[:len(p), :2], x[:len(p), 2] = p, 0.0
    x[len(p):nf] = [5.0, 5.0, 0.0]  # parked: more than H from every line
    sim.state.x.assign(x)
    sim.state.rho.fill_(sim.fluid.params.rest_density)
    g = sim.gauges()
    for k, xg in enumerate(gx):
        want = 0.12 + math.tan(th) * (xg - 0.2)
        assert abs(g[f"g{k}"] - want) < 0.1 * S, (xg, (g[f"g{k}"] - want) / S)
    assert g["g2"] - g["g0"] == pytest.approx(0.2 * math.tan(th), abs=0.1 * S)


def test_gauges_async_and_profiles():
    """gauges_async() gives what gauges() gives; Gauges.profiles() shows the water fraction ~1 in the bulk
    (poly6 at H = 2 s, midway between lattice columns: 0.972-0.985)."""
    d = tank_2d(width=0.2, depth=0.1, height=0.2, spacing=S, fidelity="draft")  # poly6 at H = 2 s
    sim = _sim(d, [_height("h", 0.1, 0.0), {"name": "p", "kind": "pressure", "position_m": [0.1, 0.05]}])
    pending = sim.readers.gauges_async()
    assert pending.result() == sim.gauges()
    z, phi_f, phi_s = sim.readers._gauges.profiles(sim.state)
    bulk = (z > 0.03) & (z < 0.07)
    assert np.all(np.abs(phi_f[0, bulk] / (1 - phi_s[0, bulk]) - 1.0) < 0.05)  # the lattice ripple off its points: -2 to -3%
    assert np.all(phi_f[0, z > 0.1 + 2 * S] == 0.0)


def _box(name, w, h, x, y, kind="kinematic", velocity=0.0):
    """A 2D box block (0.1 m deep); kinematic: held, or moving along x at ``velocity`` [m/s]."""
    b = {"name": name, "shape": "box", "size_m": [w, h, 0.1], "position_m": [x, y, 0.0], "density_kg_m3": 2600.0,
         "kind": kind}
    if kind == "kinematic":
        b["motion"] = {"type": "table", "times_s": [0.0, 1.0], "displacements_m": [[0.0, 0.0, 0.0], [velocity, 0.0, 0.0]]}
    return b


def _surface_reference(sim, xg) -> float:
    """The highest fluid particle within a spacing of the line x = xg, + s/2 (the level of a lattice's top)."""
    x = sim.positions()
    sel = np.abs(x[:, 0] - xg) < S
    return float(x[sel, 1].max() + 0.5 * S) if sel.any() else math.nan


@pytest.mark.parametrize("kernel", ["muller", "cubic_spline", "wendland"])
def test_the_half_space_share_of_the_kernel(kernel):
    """F(d), the kernel's weight beyond a plane d from its centre (MovingSolids' table, the kernel's slabs summed):
    the slabs add up to the kernel's integral, 1 within 1e-3 (the normalisation; 2D and 3D); F(0) = 1/2 (symmetry),
    F(-H) = 1, F(H) = 0; F falls monotonically; and above the 2D tank's floor a gauge line's phi_s, the wall
    particles' sum, is F(height above the floor's face) within 0.03 (a lattice of particles against the continuum;
    measured 0.010 / 0.015 / 0.017 for poly6 / cubic spline / Wendland): the moving blocks' phi_m and the walls'
    phi_s are the same share."""
    import warp as wp

    from rockwave.kernels.sim import readers as gauge_k
    from rockwave.sim.readers import MovingSolids

    for dim in (2, 3):
        d = tank_2d(width=0.2, depth=0.1, height=0.2, spacing=S, kernel=kernel)
        if dim == 3:
            d["simulation"]["dimension"] = 3
            d["fluid"]["regions"][0] = {"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [0.2, 0.06, 0.1]}
            d["tank"] = {"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [0.2, 0.06, 0.2]}
        sim = _sim(d, [_height("h", 0.1, 0.0)] if dim == 2 else [_height("h", 0.1, 0.03, 0.0)])
        params, dev = sim.fluid.params, sim.fluid.device
        slabs = wp.zeros(MovingSolids.SLABS, dtype=float, device=dev)
        wp.launch(gauge_k.kernel_slabs, dim=MovingSolids.SLABS, inputs=[params, MovingSolids.SLABS], outputs=[slabs],
                  device=dev)
        w = slabs.numpy().astype(np.float64)
        assert abs(w.sum() - 1.0) < 1e-3, (kernel, dim, w.sum())
        F = np.concatenate([np.cumsum(w[::-1])[::-1], [0.0]]) / w.sum()
        n = MovingSolids.SLABS
        assert F[0] == pytest.approx(1.0) and F[-1] == 0.0 and F[n // 2] == pytest.approx(0.5, abs=1e-6)
        assert np.all(np.diff(F) <= 0.0)
        if dim == 2:  # the floor's particles along the line: phi_s against F(z), z above the floor's face (z = 0)
            g = sim.readers._gauges
            z = g.z0 + g.dz * np.arange(g.n_samples)
            H = sim.fluid.support_radius
            near = (z >= 0.0) & (z < H)  # outside the face (the wall is a few layers thick: no half-space inside)
            want = np.interp(z[near], -H + 2 * H * np.arange(n + 1) / n, F)  # F(z): the floor z below the sample
            got = g.phi_s.numpy()[0, near]
            assert np.abs(got - want).max() < 0.03, (kernel, np.abs(got - want).max())


def test_blocks_are_bed_to_the_water_above_them_and_dry_where_out_of_the_water():
    """Still water 0.15 m deep (2D, H = 3 s) around four blocks: a rigid one resting on the floor, its top 0.09 m up
    (beyond the 2H = 0.06 m within which the water must start above the bed: without the moving blocks as solid the
    gauge over it read NaN); one held in the water with water under and over it (it read its underside, 0.035 m);
    a pier standing on the floor through the surface; a hull held through the surface with water under it. Over the
    first two the gauge reads the still level 0.15 within 0.1 s; over the pier and the hull NaN (no free surface:
    the water is pressed against the block, whose top is dry); half a spacing from the pier's side, the block's
    share of the kernel support (phi_m = F(dist)) is taken out of the open space as a wall's: 0.15 within 0.1 s.
    After 0.1 s of stepping the water has moved (the seeded gaps at the blocks' faces close) and each wet gauge
    reads the highest particle within a spacing of its line + s/2 within 0.5 s (the particles are no longer on a
    lattice: this reference scatters by a fraction of a spacing; measured within 0.03 s). 3D: over a box 0.07 m tall
    resting on the floor under 0.1 m of water, and 0.002 m inside its side face, 0.1 within 0.1 s (both read NaN
    without the moving blocks as solid)."""
    d = tank_2d(width=0.5, depth=0.15, height=0.3, spacing=S)
    d["blocks"] = [_box("rest", 0.08, 0.09, 0.06, 0.045, kind="rigid"), _box("held", 0.08, 0.05, 0.17, 0.06),
                   _box("pier", 0.06, 0.25, 0.28, 0.125), _box("hull", 0.08, 0.12, 0.41, 0.14)]
    at = {"rest": 0.06, "held": 0.17, "pier": 0.28, "beside": 0.245, "hull": 0.41, "open": 0.465}
    sim = _sim(d, [_height(k, x, 0.0) for k, x in at.items()])
    assert sim.fluid.support_radius == pytest.approx(3 * S)
    g = sim.gauges()
    assert math.isnan(g["pier"]) and math.isnan(g["hull"]), g
    for k in ("rest", "held", "beside", "open"):
        assert abs(g[k] - 0.15) < 0.1 * S, (k, (g[k] - 0.15) / S)
    sim.advance(0.1)
    g = sim.gauges()
    assert math.isnan(g["pier"]) and math.isnan(g["hull"]), g
    for k in ("rest", "held", "beside", "open"):
        ref = _surface_reference(sim, at[k])
        assert abs(g[k] - ref) < 0.5 * S, (k, (g[k] - ref) / S)
    d3 = {
        "simulation": {"dimension": 3, "duration_s": 1.0},
        "fluid": {"spacing_m": S, "eos": {"speed_of_sound_m_s": 20.0}, "viscosity": {"artificial_alpha": 0.3},
                  "regions": [{"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [0.12, 0.1, 0.1]}]},
        "tank": {"box_min_m": [0.0, 0.0, 0.0], "box_max_m": [0.12, 0.1, 0.2]},
        "blocks": [{"name": "rest", "shape": "box", "size_m": [0.05, 0.05, 0.07], "position_m": [0.06, 0.05, 0.035],
                    "density_kg_m3": 2600.0}],
    }
    g3 = _sim(d3, [_height("over", 0.06, 0.05, 0.0), _height("edge", 0.083, 0.05, 0.0)]).gauges()
    for k, v in g3.items():
        assert abs(v - 0.1) < 0.1 * S, (k, (v - 0.1) / S)


def test_a_block_moving_under_a_gauge_and_one_moving_through_it():
    """Kinematic blocks moved along x in still water 0.15 m deep: a submerged one (0.09 m tall on the floor, 0.5
    m/s) passes under gauge 'sub', a pier through the surface (0.2 m/s) comes over gauge 'pier'. Every 0.025 s: 'sub'
    reads the highest particle within a spacing of its line + s/2 within 0.5 s, over the block and off it (measured:
    within 0.47 s, the block's bow wave raising the water 1.7 cm; without the moving block as solid it read NaN
    while the block was under it); 'pier' reads NaN while the pier covers its line (half a spacing inside the
    faces or more) and the water's top within 0.5 s while its line is half a spacing or more clear."""
    d = tank_2d(width=0.6, depth=0.15, height=0.3, spacing=S)
    d["blocks"] = [_box("sub", 0.08, 0.09, 0.16, 0.045, velocity=0.5), _box("pier", 0.06, 0.25, 0.43, 0.125, velocity=0.2)]
    sim = _sim(d, [_height("sub", 0.25, 0.0), _height("pier", 0.49, 0.0)])
    over, covered, clear = 0, 0, 0
    while sim.time < 0.25 - 1e-9:
        sim.advance(0.025)
        g = sim.gauges()
        xb = sim.block_positions()[:2, 0]
        over += abs(xb[0] - 0.25) < 0.04
        ref = _surface_reference(sim, 0.25)
        assert abs(g["sub"] - ref) < 0.5 * S, (sim.time, xb[0], (g["sub"] - ref) / S)
        gap = abs(xb[1] - 0.49) - 0.03  # the pier's line from its nearer face (< 0: inside)
        if gap < -0.5 * S:
            covered += 1
            assert math.isnan(g["pier"]), (sim.time, g["pier"])
        elif gap > 0.5 * S:
            clear += 1
            ref = _surface_reference(sim, 0.49)
            assert abs(g["pier"] - ref) < 0.5 * S, (sim.time, (g["pier"] - ref) / S)
    assert over >= 3 and covered >= 3 and clear >= 1, (over, covered, clear)


def test_a_batch_reads_the_moving_blocks_as_its_solo_runs_do():
    """Two scenarios of a block (0.09 m tall, on the floor, kinematic at 0.3 / 0.5 m/s) under 0.15 m of water, batched
    (rockwave/output/batch.py BatchHazard): the wave gauge over the block takes its still level from its start-up
    reading, 0.15 within 0.1 s (without the moving blocks as solid it read dry and the run stopped with a SceneError),
    and every gauge statistic after 0.05 s (fixed steps) equals the solo run's within 2e-5 m; the tiles sit on a grid,
    so a line may pass another scenario's tile: each line sees its own scenario's blocks only."""
    scenes = []
    for v in (0.3, 0.5):
        d = tank_2d(width=0.4, depth=0.15, height=0.3, spacing=S)
        d["simulation"].update({"time_step": "fixed", "dt_s": 2.5e-4, "duration_s": 0.05})
        d["blocks"] = [_box("sub", 0.08, 0.09, 0.15, 0.045, velocity=v)]
        d["hazard"] = {"sample_interval_s": 0.01, "gauges": [{"name": "over", "position_m": [0.15, 0.0]},
                                                              {"name": "ahead", "position_m": [0.25, 0.0]}]}
        scenes.append(parse_scene(d, "batch.toml"))
    b = BatchSimulation(scenes, device=DEVICE)
    hz = BatchHazard(b)
    b.advance(0.05, watch=hz.after_step)
    mine = hz.results()
    for k, scene in enumerate(scenes):
        assert abs(mine[k]["gauges"]["over"]["still_level_m"] - 0.15) < 0.1 * S
        sim = rockwave.Simulation(scene, device=DEVICE)
        solo = HazardMonitor(sim)
        sim.advance(0.05, watch=solo.after_step)
        res = solo.result()
        assert abs(res["gauges"]["over"]["still_level_m"] - mine[k]["gauges"]["over"]["still_level_m"]) < 2e-5
        want, got = flat_metrics(res), flat_metrics(mine[k])
        keys = [f"{g}.{m}" for g in ("over", "ahead") for m in ("max_crest_m", "deepest_trough_m")]
        for key in keys:
            assert math.isfinite(want[key]) and abs(want[key] - got[key]) < 2e-5, (k, key, want[key], got[key])
