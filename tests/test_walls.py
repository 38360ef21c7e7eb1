"""The accurate default formulation (fluid.fidelity = 'standard': Wendland C2 at 3 spacings, Adami et al.
2012 walls): water at rest has the hydrostatic pressure on its walls and corners
and stays at rest; the fidelity levels and the wall keys reach the solver; the new terms keep momentum.
CPU, small 2D and 3D tanks."""

from __future__ import annotations

import numpy as np
import pytest

import rockwave
from rockwave.scene.format import SceneError

from conftest import DEVICE

G = 9.81


def _tank(dim: int, depth: float, width: float, spacing: float, **fluid) -> dict:
    lo, hi = [0.0] * dim, [width] * (dim - 1) + [depth]
    gauges = [{"name": "corner", "kind": "pressure", "position_m": [0.0] * dim},
              {"name": "floor_mid", "kind": "pressure", "position_m": [0.5 * width] * (dim - 1) + [0.0]},
              {"name": "side_mid", "kind": "pressure", "position_m": [0.0] + [0.5 * width] * (dim - 2) + [0.5 * depth]}]
    return {"simulation": {"dimension": dim, "duration_s": 1.0},
            "fluid": {"spacing_m": spacing, "eos": {"speed_of_sound_m_s": 20.0},
                      "regions": [{"box_min_m": lo, "box_max_m": hi}], **fluid},
            "tank": {"box_min_m": lo, "box_max_m": [width] * (dim - 1) + [depth + 0.1]},
            "output": {"gauges": gauges}}


def _level(sim, dim: int) -> float:
    """The surface level: the mean height of the top layer of particles (those within half a spacing of the
    highest) plus half a spacing."""
    z = sim.positions()[:, dim - 1]
    s = sim.fluid.spacing
    return float(z[z > z.max() - 0.5 * s].mean()) + 0.5 * s


def _at_rest(sim, dim: int, duration: float):
    """Advance; return (surface level, wall particle positions and pressures, gauges, fluid speeds)."""
    sim.advance(duration)
    top = _level(sim, dim)
    nf = sim.fluid.n_fluid
    xb = sim.fluid.initial_positions[nf:]
    pw = sim.state.wall_pressure.numpy()[: len(xb)].astype(np.float64)
    speed = np.linalg.norm(sim.velocities(), axis=1)
    return top, xb, pw, sim.gauges(), speed


@pytest.mark.parametrize("dim", [2, 3])
def test_water_at_rest_has_hydrostatic_wall_pressure_with_corners(dim):
    """A tank at rest (2D: 0.3 m deep, 0.6 m wide, 0.015 m spacing, 0.5 s; 3D: 0.12 m cube of water at 0.015 m,
    0.25 s), c0 = 20 m/s, default formulation. Every wall particle of the first layer more than one kernel support
    below the surface reads p_b = rho0 g (level - z_b) within 2.5% of the water's weight rho0 g D (the wall's own
    pressure, Adami 2012; measured at worst 2.07% (2D) and 2.37% (3D) high, both at the floor next to a corner:
    the issue's 2% is not met there at this resolution; the H100 runs at 100 layers read 1.8% and 2.0%);
    the pressure gauges at the floor corner, mid-floor and mid-depth on the side wall read within 2% of rho0 g d in
    2D and 3% in the coarse 3D tank (3D side_mid measured +2.7%; on the H100 at 100 and 30 layers all three read
    +0.9% to +1.8%); particle speeds stay below 0.1% of c0 (RMS) and the surface does not
    move (within 0.1 spacing). Before (Akinci walls, Mueller kernels: fidelity = 'draft') the same 2D tank read
    2.96, 1.97 and 1.61 rho0 g d at those gauges and its particles moved at 0.1 m/s RMS."""
    s = 0.015
    depth, width, t = (0.3, 0.6, 0.5) if dim == 2 else (0.12, 0.12, 0.25)
    sim = rockwave.Simulation(rockwave.parse_scene(_tank(dim, depth, width, s)), device=DEVICE)
    level0 = _level(sim, dim)
    top, xb, pw, gauges, speed = _at_rest(sim, dim, t)
    assert abs(top - level0) < 0.1 * s, (top, level0)
    assert np.sqrt(np.mean(speed ** 2)) < 1e-3 * 20.0, np.sqrt(np.mean(speed ** 2))
    up = dim - 1
    first = np.all((xb[:, :up] > -s) & (xb[:, :up] < width + s), axis=1) & (xb[:, up] > -s) & (xb[:, up] < top)
    first &= np.any(np.abs(xb[:, :up] + 0.5 * s) < 1e-6, axis=1) | (np.abs(xb[:, up] + 0.5 * s) < 1e-6)
    first &= xb[:, up] < top - sim.fluid.support_radius  # below the free surface's truncated kernel
    assert first.sum() > 10
    exact = 1000.0 * G * (top - xb[first, up])
    err = np.abs(pw[first] - exact) / (1000.0 * G * depth)
    assert err.max() < 0.025, (err.max(), xb[first][np.argmax(err)])
    for name, z in (("corner", 0.0), ("floor_mid", 0.0), ("side_mid", 0.5 * depth)):
        ratio = gauges[name] / (1000.0 * G * (top - z))
        assert abs(ratio - 1.0) < (0.02 if dim == 2 else 0.03), (name, ratio)


def test_fidelity_levels_set_the_formulation_and_expert_keys_win():
    """fluid.fidelity fills the formulation keys the scene leaves out; a key the scene gives wins."""
    d = _tank(2, 0.1, 0.1, 0.01)
    f = {lvl: rockwave.parse_scene(dict(d, fluid=dict(d["fluid"], fidelity=lvl))).fluid for lvl in ("draft", "standard", "high")}
    assert (f["draft"].kernel, f["draft"].support_radius_ratio, f["draft"].boundary, f["draft"].density_diffusion) == \
        ("muller", 2.0, "akinci", 0.0)
    assert (f["standard"].kernel, f["standard"].support_radius_ratio, f["standard"].boundary) == ("wendland", 3.0, "adami")
    assert f["standard"].density_diffusion == 0.0 and f["standard"].viscosity.artificial_alpha == 0.01
    assert f["high"].support_radius_ratio == 4.0
    assert rockwave.parse_scene(d).fluid.kernel == "wendland"  # 'standard' is the default
    mixed = rockwave.parse_scene(dict(d, fluid=dict(d["fluid"], fidelity="high", kernel="cubic_spline",
                                                    viscosity={"artificial_alpha": 0.2}))).fluid
    assert (mixed.kernel, mixed.support_radius_ratio, mixed.viscosity.artificial_alpha) == ("cubic_spline", 4.0, 0.2)
    summ = rockwave.parse_scene(dict(d, fluid=dict(d["fluid"], density="summation"))).fluid
    assert summ.density_diffusion == 0.0  # the diffusion is for continuity density: not an error when implied


def test_formulations_the_walls_cannot_do_are_errors_naming_the_key():
    d = _tank(2, 0.1, 0.1, 0.01)
    thin = dict(d, tank=dict(d["tank"], layers=1))
    with pytest.raises(SceneError, match="tank.layers"):
        rockwave.parse_scene(thin)
    rockwave.parse_scene(dict(thin, fluid=dict(d["fluid"], boundary="akinci")))  # thin Akinci walls are fine
    with pytest.raises(SceneError, match="fluid.wall_slip"):
        rockwave.parse_scene(dict(d, fluid=dict(d["fluid"], boundary="akinci", wall_slip="no_slip")))
    with pytest.raises(SceneError, match="fluid.fidelity"):
        rockwave.parse_scene(dict(d, fluid=dict(d["fluid"], fidelity="ultra")))


def test_no_slip_walls_slow_a_flow_along_the_wall():
    """A layer of water moving at 0.2 m/s along the floor of a 2D tank without gravity for 0.05 s: with no-slip
    Adami walls the water next to the floor slows (the viscous term against the wall's extrapolated velocity,
    -v_fluid, Adami 2012 eq. 23); with free-slip walls it keeps its speed."""
    out = {}
    for slip in ("free", "no_slip"):
        d = _tank(2, 0.06, 0.6, 0.01, wall_slip=slip, viscosity={"artificial_alpha": 0.5})
        d["gravity"] = {"acceleration_m_s2": [0.0, -1e-6]}
        d["fluid"]["regions"] = [{"box_min_m": [0.1, 0.0], "box_max_m": [0.4, 0.06], "velocity_m_s": [0.2, 0.0]}]
        d["output"] = {}
        sim = rockwave.Simulation(rockwave.parse_scene(d), device=DEVICE)
        sim.advance(0.05)
        x, v = sim.positions(), sim.velocities()
        low = (x[:, 1] < 0.015) & (x[:, 0] > 0.2) & (x[:, 0] < 0.35)
        out[slip] = float(v[low, 0].mean())
    assert out["free"] > 0.19, out
    assert out["no_slip"] < 0.9 * out["free"], out


def test_new_terms_conserve_momentum_in_free_flight():
    """A disc of water with random velocities and no walls or gravity under the default formulation with delta-SPH
    density diffusion added (Wendland, continuity density, artificial viscosity): the total momentum is unchanged by 50
    steps (the pair forces are antisymmetric; the diffusion moves density, not momentum). The tank is far away."""
    d = _tank(2, 0.1, 0.1, 0.01, density_diffusion=0.1)
    d["fluid"]["regions"] = [{"box_min_m": [0.3, 0.3], "box_max_m": [0.4, 0.4]}]
    d["tank"] = {"box_min_m": [0.0, 0.0], "box_max_m": [0.8, 0.8]}
    d["gravity"] = {"acceleration_m_s2": [0.0, -1e-9]}
    d["output"] = {}
    d["simulation"]["time_step"] = "fixed"
    d["simulation"]["dt_s"] = 1e-4
    sim = rockwave.Simulation(rockwave.parse_scene(d), device=DEVICE)
    rng = np.random.default_rng(3)
    v = sim.state.v.numpy()
    nf = sim.fluid.n_fluid
    v[:nf, :2] = rng.normal(0.0, 0.5, (nf, 2))
    sim.state.v.assign(v)
    p0 = sim.velocities().astype(np.float64).sum(axis=0)
    sim.advance(50 * 1e-4)
    p1 = sim.velocities().astype(np.float64).sum(axis=0)
    scale = np.abs(sim.velocities()).sum()
    assert np.all(np.abs(p1 - p0) < 1e-5 * scale), (p0, p1, scale)


def test_ghost_sph_runs_on_the_default_formulation():
    """Ghost SPH composes the fluid step, so the Adami walls and the Wendland kernel of the default apply to it:
    the report's dam break (case 1) at 0.03 m on fidelity 'standard' runs 0.2 s with finite state, ghosts seeded,
    every particle inside the tank, the front moving out (Martin & Moyce: ~0.27 m from the 0.2 m column)."""
    from helpers import ROOT

    d = rockwave.load_scene(ROOT / "scenes" / "ghost_dam_break_case1.toml").raw
    d["fluid"].update(fidelity="standard", spacing_m=0.03)
    for k in ("kernel", "support_radius_ratio"):
        d["fluid"].pop(k, None)
    sim = rockwave.Simulation(rockwave.parse_scene(d, "case1", ROOT / "scenes"), device=DEVICE)
    assert sim.fluid.params.boundary == 1 and sim.fluid.support_radius == pytest.approx(0.09)
    front0 = float(sim.positions()[:, 0].max())
    sim.advance(0.2)
    x = sim.positions()
    assert np.isfinite(x).all() and sim.fluid_solver.n_ghost > 0
    lo, hi = np.array(d["tank"]["box_min_m"]), np.array(d["tank"]["box_max_m"])
    assert np.all((x[:, :2] > lo - 1e-6) & (x[:, 0:1] < hi[0] + 1e-6))
    assert float(x[:, 0].max()) > front0 + 0.05


@pytest.mark.parametrize("dim", [2, 3])
def test_fixed_blocks_are_adami_walls(dim):
    """A tank made of fixed blocks (no [tank]) holding water at rest, default formulation: the blocks' faces get
    wall particles (rockwave/build/builder.py fixed_block_walls) and read the hydrostatic pressure as the [tank] walls do.
    2D: 0.3 m deep, 0.6 m wide, 0.015 m, 0.5 s (measured single reads at 0.5 s before the packed start became the
    default: corner +0.8%, floor +1.0%, side +0.5%); 3D: 0.12 m cube at 0.015 m, 0.25 s, whose single reads swing
    +-2.5% with the tank's acoustic period (4 D/c0 = 24 ms): the gauges are averaged over the last 0.1 s (measured
    over 0.25-0.5 s: -0.5 / +1.4 / +1.6%, the uniform start and wall mass -0.3 / +1.4 / +1.6%). With the penalty walls alone (before) the same 2D tank read 2.11, 1.36 and 1.49 rho0 g d
    and moved at 0.1% of c0."""
    s = 0.015
    depth, width, t = (0.3, 0.6, 0.5) if dim == 2 else (0.12, 0.12, 0.25)
    d = _tank(dim, depth, width, s)
    del d["tank"]
    th, tall = 0.1, depth + 0.1
    z = [0.0] if dim == 2 else []

    def box(name, lo, hi):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        size = list(hi - lo) + ([0.1] if dim == 2 else [])
        centre = list(0.5 * (lo + hi)) + z
        return {"name": name, "shape": "box", "size_m": size, "position_m": centre, "kind": "fixed"}

    if dim == 2:
        d["blocks"] = [box("floor", [-th, -th], [width + th, 0.0]), box("left", [-th, 0.0], [0.0, tall]),
                       box("right", [width, 0.0], [width + th, tall])]
    else:
        d["blocks"] = [box("floor", [-th, -th, -th], [width + th, width + th, 0.0]),
                       box("x0", [-th, -th, 0.0], [0.0, width + th, tall]), box("x1", [width, -th, 0.0], [width + th, width + th, tall]),
                       box("y0", [0.0, -th, 0.0], [width, 0.0, tall]), box("y1", [0.0, width, 0.0], [width, width + th, tall])]
    sim = rockwave.Simulation(rockwave.parse_scene(d), device=DEVICE)
    assert sim.fluid.n_boundary > 0
    level0 = _level(sim, dim)
    ratios = []
    for tr in np.linspace(t - 0.1, t, 5):  # the mean over the last 0.1 s: the small tank's acoustic swing is +-2.5%
        top, xb, pw, gauges, speed = _at_rest(sim, dim, tr - sim.time)
        ratios.append([gauges[name] / (1000.0 * G * (top - zg)) for name, zg in
                       (("corner", 0.0), ("floor_mid", 0.0), ("side_mid", 0.5 * depth))])
    assert abs(top - level0) < 0.1 * s, (top, level0)
    assert np.sqrt(np.mean(speed ** 2)) < 1e-3 * 20.0, np.sqrt(np.mean(speed ** 2))
    mean = np.mean(ratios, axis=0)
    assert np.all(np.abs(mean - 1.0) < (0.02 if dim == 2 else 0.03)), mean
    draft = rockwave.Simulation(rockwave.parse_scene(dict(d, fluid=dict(d["fluid"], fidelity="draft"))), device=DEVICE)
    assert draft.fluid.n_boundary == 0  # Akinci walls: fixed blocks stay penalty walls


def test_packed_start_spaces_each_run_at_its_hydrostatic_density():
    """rockwave.build.builder.packed_start: along a lattice column, each gap dx becomes dx rho0/rho(mid-depth) from the
    run's lowest particle up; a gap wider than 1.5 spacings (an obstacle) starts a new run anchored at its own lowest
    particle; a run whose top is not the free surface (under the obstacle) stays as it was; other columns and axes
    are untouched."""
    from rockwave.build.builder import packed_start

    dx = 0.01
    z = np.concatenate([(np.arange(10) + 0.5) * dx, (np.arange(14, 20) + 0.5) * dx])  # a run, an obstacle's gap, a run
    col = np.stack([np.full(len(z), 0.05), z, np.zeros(len(z))], axis=1)
    other = col.copy()
    other[:, 0] += dx
    x = np.concatenate([col, other[::-1]])  # any order
    depth = 0.2 - x[:, 1]
    ratio = lambda d: 1.0 + 0.01 * d / 0.2  # noqa: E731  rho/rho0 rising 1% over the column's depth
    out = packed_start(x, depth, ratio, dx, up=1)
    assert np.array_equal(out[:, 0], x[:, 0]) and np.array_equal(out[:, 2], x[:, 2])
    for sel in (slice(0, len(z)), slice(len(z), None)):
        xs, os_ = x[sel], out[sel]
        o = np.argsort(xs[:, 1])
        zs, zo, ds = xs[o, 1], os_[o, 1], depth[sel][o]
        assert np.array_equal(zo[:10], zs[:10])  # the run under the obstacle: its top 0.105 m deep
        assert zo[10] == zs[10]  # the surface run's lowest particle stays
        mid = 0.5 * (ds[1:] + ds[:-1])
        np.testing.assert_allclose(np.diff(zo)[10:], dx / ratio(mid[10:]), rtol=1e-12)
        assert zo[-1] < zs[-1] - 5e-5


@pytest.mark.parametrize("key, value, level", [("wall_volume", "geometric", "draft"), ("packed_start", True, None)])
def test_wall_volume_and_packed_start_refuse_what_they_cannot_do(key, value, level):
    d = _tank(2, 0.1, 0.1, 0.01, **{key: value})
    if level:
        d["fluid"]["fidelity"] = level  # Akinci walls
    else:
        d["fluid"]["density"] = "summation"
    with pytest.raises(SceneError, match=f"fluid.{key}"):
        rockwave.parse_scene(d)


def test_packed_start_with_geometric_walls_reads_hydrostatics_closer():
    """The 3D tank of benchmarks/at_rest.py at 12 layers (0.3 m cube of water, 0.025 m spacing, c0 20 m/s), 1 s,
    readings averaged over the second half: with the uniform start and wall mass (fluid.packed_start = false,
    fluid.wall_volume = 'mass', the standard level before 2026-11-28) the gauges read up to 1.9% and the wall
    particles up to 2.0% above rho0 g (level - z) (the uniform start out of the discrete balance by 2 g d/c0^2, and
    the walls' volume shrinking with their pressure: docs/notes.md "Water at rest on the H200"); the default
    (packed start, geometric wall volume) measured 1.2% and 1.25%."""
    from benchmarks.at_rest import surface_level, tank_scene

    res = {}
    for name, extra in (("uniform", {"packed_start": False, "wall_volume": "mass"}), ("default", {})):
        sc = tank_scene(3, 12, 1.0, "standard")
        sc["fluid"].update(extra)
        sim = rockwave.Simulation(rockwave.parse_scene(sc), device=DEVICE)
        s, nf = sim.fluid.spacing, sim.fluid.n_fluid
        xb = sim.fluid.initial_positions[nf:]
        top0 = surface_level(sim.positions(), 3, s)
        first = np.all((xb[:, :2] > -s) & (xb[:, :2] < 0.3 + s), axis=1) & (xb[:, 2] > -s)
        first &= np.any(np.abs(xb[:, :2] + 0.5 * s) < 1e-6, axis=1) | (np.abs(xb[:, 2] + 0.5 * s) < 1e-6)
        first &= xb[:, 2] < top0 - sim.fluid.support_radius
        walls, gauges = [], []
        for t in np.arange(0.55, 1.0 + 1e-9, 0.05):
            sim.advance(t - sim.time)
            top = surface_level(sim.positions(), 3, s)
            walls.append(sim.state.wall_pressure.numpy()[: len(xb)][first] / (1000.0 * G * 0.3)
                         - (top - xb[first, 2]) / 0.3)
            g = sim.gauges()
            gauges.append([g[k] / (1000.0 * G * (top - z)) - 1 for k, z in (("corner", 0), ("floor_mid", 0), ("side_mid", 0.15))])
        speed = np.linalg.norm(sim.velocities(), axis=1)
        assert np.sqrt(np.mean(speed ** 2)) < 1e-3 * 20.0
        res[name] = (np.abs(np.mean(gauges, axis=0)).max(), np.abs(np.mean(walls, axis=0)).max())
    assert res["default"][0] < 0.015 and res["default"][1] < 0.015, res
    assert res["default"][0] < res["uniform"][0] - 0.004 and res["default"][1] < res["uniform"][1] - 0.004, res


@pytest.mark.parametrize("dim", [2, 3])
def test_open_tank_walls_rise_on_the_waters_lattice(dim):
    """rockwave.build.sampling.box_shell: an open tank whose height is not a whole number of spacings (0.4 m at 0.015 m)
    gets side-wall particles on the water's rows (the floor's lattice with the exact step: a lattice stretched to
    end at the top put them between the rows and gave each 0.6% less volume than the wall force assumes, reading
    +0.6% at 40 layers; docs/notes.md 'Water at rest on the H200'), up to the first whole step at or above the
    top; the floor's layers below keep the exact step too."""
    from rockwave.build import sampling
    s, layers, up = 0.015, 3, dim - 1
    lo, hi = [0.0] * dim, [0.3] * (dim - 1) + [0.4]
    b = sampling.box_shell(lo, hi, s, layers, True, True, up)
    z = np.unique(np.round(b[:, up], 12))
    water = sampling.box_lattice([0.0] * dim, [0.3] * (dim - 1) + [0.3], s)[:, up]
    rows = (np.arange(-layers, 27) + 0.5) * s  # 27 rows reach 0.405 m >= 0.4 m
    np.testing.assert_allclose(z, rows, atol=1e-12)
    assert np.all(np.isin(np.round(water, 12), np.round(z, 12)))
    assert z.max() + 0.5 * s >= 0.4 and z.max() - 0.5 * s < 0.4


def _slope_tank(angle_deg: float, s: float, depth: float = 0.61, length: float = 1.6) -> tuple[dict, float, float]:
    """2D tank of still water over a fixed prism whose face rises at angle_deg from the floor at x_toe (the NTHMP
    slope's cross-section, scaled); the region's depth is no whole number of spacings, so its lattice meets the face
    at every offset along it. Returns (scene, tan angle, x_toe)."""
    t = float(np.tan(np.radians(angle_deg)))
    x_toe = 0.3 + depth / t
    verts = [[x_toe, 0.0], [-0.2, 0.0], [-0.2, t * (x_toe + 0.2)]]
    d = {
        "simulation": {"dimension": 2, "duration_s": 1.0},
        "fluid": {"spacing_m": s, "eos": {"speed_of_sound_m_s": 10.0 * float(np.sqrt(G * depth))},
                  "regions": [{"box_min_m": [0.0, 0.0], "box_max_m": [length, depth]}]},
        "tank": {"box_min_m": [0.0, 0.0], "box_max_m": [length, 1.5 * depth]},
        "blocks": [{"name": "slope", "shape": "prism", "kind": "fixed",
                    "vertices_m": [[x, y, z] for z in (-0.05, 0.05) for x, y in verts]}],
    }
    return d, t, x_toe


@pytest.mark.parametrize("angle, depth", [(26.565, 0.62), (45.0, 0.62), (26.565, 0.61)])
def test_still_water_over_a_tilted_fixed_block_stays_at_rest(angle, depth):
    """Issue 41: still water over a fixed block's tilted face starts at rest. The axis-aligned lattice cuts a tilted
    face at an offset that depends on the geometry: seeded down to half the contact distance (d0/2 = s/4), the
    particles between d0/2 and d0 met the penalty spring at t = 0 and were blasted off the face (0.62 m deep: 12 and 8
    such particles; fastest 3.3 and 0.8 m/s after 30 ms, the water body's mean vertical velocity +0.08 and +0.10 m/s;
    the NTHMP slope's water at 4-5 m/s, 120 kPa over hydrostatic); and the fixed block's wall lattice (points inside
    the face only) left a band empty between the wall and the water, into which the water fell (0.61 m deep: no
    particle in the spring, fastest 0.50 m/s, mean -0.015 m/s). Now water is seeded no closer than d0 and the wall
    particles fill the water's own lattice up to it (rockwave/build/builder.py seeding_clearance, fixed_block_walls):
    fastest 0.020-0.024 m/s after 30 ms and 0.040-0.042 m/s after 0.1 s, as the same tank without the block (0.024
    and 0.042 m/s). 2D, 0.03 m, c0 = 10 (g h)^1/2 = 24-25 m/s; no particle below the face after 0.1 s."""
    s = 0.03
    d, t, x_toe = _slope_tank(angle, s, depth=depth)
    sim = rockwave.Simulation(rockwave.parse_scene(d), device=DEVICE)

    def above_face(x):  # signed distance above the face y = t (x_toe - x)
        return (x[:, 1] - t * (x_toe - x[:, 0])) / np.sqrt(1.0 + t * t)

    assert above_face(sim.positions()).min() >= 0.5 * s * (1.0 - 0.02)  # the clearance: d0 on the fitted lattice
    sim.advance(0.03)
    v = sim.velocities()
    speed = np.linalg.norm(v, axis=1)
    assert speed.max() < 0.05, speed.max()  # (g h)^1/2 = 2.5 m/s
    assert abs(float(v[:, 1].mean())) < 0.005, v[:, 1].mean()
    sim.advance(0.07)
    assert above_face(sim.positions()).min() > 0.0
    assert np.linalg.norm(sim.velocities(), axis=1).max() < 0.1
