"""A block resting under still water on a slope, a little above and below its friction limit (issue 36).

2D: a 0.1 m square rock (2600 kg/m3, 0.1 m deep) rests in contact, with no gap, on a fixed slab dipping ``alpha``
(20 deg) inside a [tank] filled with water to 0.35 m (the rock's top ~0.09 m below the surface), friction angle
alpha + margin on both, k_n per contact point ``kn`` (1e6 N/m; k_s the default k_n / 2.5), the rock an Adami wall to
the water (coupling.block_walls).

The limit: a fully submerged block on a plane in hydrostatic water carries the water's pressure on every face,
whose resultant is the buoyancy rho_w g V, straight up; the load on the contact is the buoyant weight
(rho_s - rho_w) g V, vertical, so its shear / normal ratio is tan(alpha) as in air and the limit is
tan(phi) = tan(alpha) whatever the buoyancy. Where the water does not reach the contact face (a closed joint: no
uplift under the base), the normal force is larger by the base's pressure times its area and the block is more
stable: the margin alpha + 0.5 deg is then a lower bound on the real one.

The start (``--settle``, s): the rock starts settled (BlockOptions.start, its springs loaded by its weight with
friction locked), then is held (HeldBlocks: stepped as a fixed block, springs untouched) while the water settles
around it with its velocities halved every 0.02 s (settle_water: the seeded water flows into the gaps left around
the blocks, and the sloshing that starts is damped), and released as it is at t = 0. ``--settle 0`` is the seeded
water's start: the water collapses into those gaps, its kinetic energy 3.5 J/m at 0.02 m, and pushes the rock
~1.2 mm down the dip in the first 0.3 s (real slip under a transient load), after which it holds.

Reported per run, along the dip (down-slope positive) from the release: the centroid's displacement, split into the
base centre's translation and the rigid turn's share (centroid minus base); the base's translation split into its
springs' elastic change (the mean shear spring force of the rock's contact points along the dip, its change / k_s)
and the slip beyond it; the turn about z; the rates of the centroid, the slip and the turn over the last ``window``
s; the contact points at their Coulomb cap; the water's kinetic energy at the release and at the end. The target
(issue 36): slip <= 0.1 mm, < 1 um/s over the last 10 s. The springs give back the dry weight's shear at the
release (the buoyancy takes rho_w g V sin(alpha) off it; no uplift under the base adds its pressure x area to
the normal force): a few um up the dip, elastic.

    python -m benchmarks.submerged_block --device cuda:0 --spacing 0.01 --duration 30 --settle 3   # GPU, ~6 min
    python -m benchmarks.submerged_block --spacing 0.02 --duration 3 --settle 1                    # CPU, ~30 s

writes benchmarks/results/submerged_block-<device>.json and .md (``--out`` another stem).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

ALPHA = 20.0
RHO_ROCK, RHO_WATER = 2600.0, 1000.0


def submerged_scene(margin: float, spacing: float = 0.02, kn: float = 1.0e6, alpha: float = ALPHA,
                    duration: float = 1.0) -> tuple[dict, np.ndarray]:
    """The 2D scene (a dict for rockwave.scene.format.parse_scene) and the down-slope unit vector."""
    a = math.radians(alpha)
    n = np.array([-math.sin(a), math.cos(a), 0.0])  # the slab's top normal (the slab turned by alpha about z)
    down = np.array([-math.cos(a), -math.sin(a), 0.0])
    centre, thick, size = np.array([0.3, 0.12, 0.0]), 0.06, 0.1
    pos = centre + (thick / 2 + size / 2) * n
    mat = {"friction_angle_deg": alpha + margin, "normal_stiffness_n_m": kn}
    scene = {"simulation": {"dimension": 2, "duration_s": duration},
             "fluid": {"spacing_m": spacing, "eos": {"speed_of_sound_m_s": 15.0}, "viscosity": {"artificial_alpha": 0.05},
                       "regions": [{"box_min_m": [0.0, 0.0], "box_max_m": [0.6, 0.35]}]},
             "tank": {"box_min_m": [0.0, 0.0], "box_max_m": [0.6, 0.5]},
             "blocks": [{"name": "slab", "shape": "box", "size_m": [0.5, thick, 0.1], "position_m": centre.tolist(),
                         "orientation_deg": [0.0, 0.0, alpha], "kind": "fixed", "material": mat},
                        {"name": "rock", "shape": "box", "size_m": [size, size, 0.1], "position_m": pos.tolist(),
                         "orientation_deg": [0.0, 0.0, alpha], "density_kg_m3": RHO_ROCK, "material": mat}],
             "coupling": {"block_walls": True}}
    return scene, down


class HeldBlocks:
    """Hold blocks where they are while the water settles around them (``with HeldBlocks(sim, [i]): ...``): the block
    solver steps them as fixed blocks with no inverse mass (the argument groups BlockSolver.settle uses for the blocks
    it holds), so they neither move nor load their contact springs; the coupling still sees them as free blocks (its
    wall particles at rest with them, the water's reaction into their loads, dropped by the fixed step). On leaving
    they are released as they are, springs as they were (the settled start's). The solver's captured CUDA graphs of
    block sub-steps are dropped on entry and exit (they bind the argument groups)."""

    def __init__(self, sim, blocks):
        self.sim, self.blocks = sim, list(blocks)

    def __enter__(self):
        import warp as wp

        from rockwave.kernels.dda import blocks as dda_k

        solver, m = self.sim.block_solver, self.sim.blocks
        props = dda_k.BlockProps()
        for name in ("inertia_body", "inv_inertia_body", "strain_minv", "strain_k", "strain_damp"):
            setattr(props, name, getattr(m, name))
        kinds, inv_mass = m.kinds.numpy().copy(), m.inv_mass.numpy().copy()  # (on the CPU numpy() is a view)
        kinds[self.blocks], inv_mass[self.blocks] = int(dda_k.KIND_FIXED), 0.0
        props.kinds = wp.array(kinds.astype(np.int32), dtype=int, device=m.device)
        props.inv_mass = wp.array(inv_mass.astype(np.float32), dtype=float, device=m.device)
        self._clear_graphs()
        solver.props = props
        return self

    def __exit__(self, *exc):
        self.sim.block_solver.props = self.sim.blocks.props
        self._clear_graphs()
        bs = self.sim.block_state
        for name in ("v", "w"):  # released at rest
            a = getattr(bs, name).numpy().copy()
            a[self.blocks] = 0.0
            getattr(bs, name).assign(a)

    def _clear_graphs(self):
        graphs = getattr(self.sim.block_solver, "_substep_graphs", None)
        if graphs:
            graphs.clear()


def water_kinetic(sim) -> float:
    """The water's kinetic energy [J per m of depth in 2D]."""
    v = sim.velocities()
    return 0.5 * sim.fluid.fluid_mass * float((v * v).sum())


def settle_water(sim, hold: list, duration: float, damp_every: float = 0.02, factor: float = 0.5) -> list:
    """The water brought to rest around the held blocks: ``duration`` s with the fluid's velocities scaled by
    ``factor`` every ``damp_every`` s (a dynamic relaxation: the seeded water flows into the gaps left around the
    blocks and the sloshing it starts is damped, so the water comes to its hydrostatic equilibrium with the blocks in
    place), then the clock set back to 0. Returns [(t, water kinetic energy)] at each damping."""
    import warp as wp

    out = []
    n = sim.n_fluid
    with HeldBlocks(sim, hold):
        t = 0.0
        while t < duration - 1e-9:
            sim.advance(damp_every)
            t += damp_every
            out.append((t, water_kinetic(sim)))
            v = sim.state.v.numpy().copy()
            v[:n] *= factor
            sim.state.v.assign(v)
            wp.synchronize_device(sim.device)
    sim.clock.time = 0.0
    return out


def rock_state(sim, ib: int, down: np.ndarray, h: float) -> dict:
    """The rock's pose and its contact points with the slab: the centroid, its base centre (centroid - h/2 along its
    own up axis), its turn about z [rad], the contact points' shear spring force along the dip on the rock (mean),
    normal forces (sum) and how many sit at their Coulomb cap."""
    from rockwave.dda import geometry as G

    bs = sim.block_state
    x = bs.positions_numpy()[ib].astype(np.float64)
    q = bs.q.numpy()[ib].astype(np.float64) + bs.q_lo.numpy()[ib]
    R = G.quat_to_matrix(q)
    base = x + R @ np.array([0.0, -h / 2, 0.0])
    t = bs.tables[0]
    keys, nc, ps = t["keys"].numpy(), t["nc"].numpy(), t["pstart"].numpy()
    sh, fn, fc = t["shear"].numpy(), t["fn"].numpy(), t["fcap"].numpy()
    shear, normal, cap, npts = [], 0.0, 0, 0
    for slot in np.nonzero(keys >= 0)[0]:
        k = int(keys[slot])
        a, b = divmod(k, sim.blocks.num_blocks)
        if ib not in (a, b):
            continue
        sign = 1.0 if b == ib else -1.0  # the table holds the force on B
        for i in range(ps[slot], ps[slot] + nc[slot]):
            shear.append(sign * float(sh[i] @ down))
            normal += float(fn[i])
            cap += int(np.linalg.norm(sh[i]) >= 0.999 * fc[i])
            npts += 1
    return dict(x=x, base=base, turn=2.0 * math.atan2(q[2], q[3]), shear=float(np.mean(shear)) if shear else 0.0,
                normal=normal, at_cap=cap, points=npts)


def run_case(device: str, margin: float, spacing: float, kn: float, duration: float, window: float,
             settle: float = 2.0, every: float = 0.05, joint_water: bool = False) -> dict:
    """One run: the water settled for ``settle`` s around the held rock (0: the seeded water's start, as before),
    then ``duration`` s with the rock free. Recorded every ``every`` s from the release: the centroid's displacement
    along the dip, split into the base's translation (its elastic part, the mean shear spring's change / k_s, and the
    slip beyond it) and the rigid turn's share (centroid minus base), the water's kinetic energy. ``joint_water``:
    coupling.joint_water (the water's pressure in the joint: the contact carries the buoyant weight)."""
    import warnings

    import rockwave
    from rockwave.scene.format import parse_scene

    scene, down = submerged_scene(margin, spacing, kn, duration=duration)
    scene["coupling"]["joint_water"] = joint_water
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the water seeded inside the slab and the rock is reported, and expected
        sim = rockwave.Simulation(parse_scene(scene), device=device)
    names = [s.name for s in sim.blocks.specs]
    ib = names.index("rock")
    h = 0.1
    t0 = time.perf_counter()
    settle_rec = settle_water(sim, [ib], settle) if settle > 0 else []
    wall_settle = time.perf_counter() - t0
    s0 = rock_state(sim, ib, down, h)
    k_s = float(sim.blocks.np["k_s"][ib])
    rec = []

    def sample(t):
        s = rock_state(sim, ib, down, h)
        disp = float((s["x"] - s0["x"]) @ down)
        base = float((s["base"] - s0["base"]) @ down)
        elastic = -(s["shear"] - s0["shear"]) / k_s  # the shear spring on the rock opposes its displacement
        rec.append(dict(t=t, disp_um=1e6 * disp, base_um=1e6 * base, elastic_um=1e6 * elastic,
                        slip_um=1e6 * (base - elastic), turn_share_um=1e6 * (disp - base),
                        turn_urad=1e6 * (s["turn"] - s0["turn"]), normal_n=s["normal"], at_cap=s["at_cap"],
                        points=s["points"], water_kinetic_j=water_kinetic(sim)))

    sample(0.0)
    t0 = time.perf_counter()
    t = 0.0
    while t < duration - 1e-9:
        step = min(every, duration - t)
        sim.advance(step)
        t += step
        sample(t)
    wall = time.perf_counter() - t0
    ts = np.array([r["t"] for r in rec])
    iw = int(np.searchsorted(ts, ts[-1] - window - 1e-9))
    m = float(sim.blocks.np["mass"][ib])
    elastic_buoyant = m * (1.0 - RHO_WATER / RHO_ROCK) * 9.81 * math.sin(math.radians(ALPHA)) / (2.0 * k_s)
    dt_w = ts[-1] - ts[iw]
    end, wst = rec[-1], rec[iw]
    return dict(margin_deg=margin, joint_water=joint_water, spacing_m=spacing, kn=kn, particles=sim.n_fluid, duration_s=duration, settle_s=settle,
                wall_settle_s=wall_settle, wall_s=wall, elastic_buoyant_um=1e6 * elastic_buoyant,
                disp_um=end["disp_um"], base_um=end["base_um"], elastic_um=end["elastic_um"], slip_um=end["slip_um"],
                turn_share_um=end["turn_share_um"], turn_urad=end["turn_urad"], at_cap=end["at_cap"], points=end["points"],
                window_s=float(dt_w), creep_um_s=(end["disp_um"] - wst["disp_um"]) / dt_w,
                slip_rate_um_s=(end["slip_um"] - wst["slip_um"]) / dt_w,
                turn_rate_urad_s=(end["turn_urad"] - wst["turn_urad"]) / dt_w,
                water_kinetic_release_j=rec[0]["water_kinetic_j"], water_kinetic_end_j=end["water_kinetic_j"],
                settle_record=[[float(a), float(b)] for a, b in settle_rec], record=rec)


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.submerged_block", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--spacing", type=float, default=0.02)
    ap.add_argument("--kn", type=float, default=1.0e6)
    ap.add_argument("--margins", type=float, nargs="+", default=[0.5])
    ap.add_argument("--duration", type=float, default=3.0, help="s after the release")
    ap.add_argument("--settle", type=float, default=2.0,
                    help="s of damped water around the held rock before the release (0: the seeded water's start)")
    ap.add_argument("--joint-water", action="store_true", help="coupling.joint_water: the water's pressure in the joint")
    ap.add_argument("--window", type=float, default=None, help="creep over the last this many s (default: 10 s or duration / 3)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    import warp as wp

    from benchmarks.common import RESULTS, commit, device_name, log, write_json

    wp.config.quiet = True
    window = a.window if a.window is not None else min(10.0, a.duration / 3)
    rows = []
    for mg in a.margins:
        r = run_case(a.device, mg, a.spacing, a.kn, a.duration, window, settle=a.settle, joint_water=a.joint_water)
        log(f"  margin {mg:+g} deg: {r['particles']} particles, settled {r['settle_s']:g} s; after {r['duration_s']:g} s "
            f"{r['disp_um']:.3f} um (base {r['base_um']:.3f}: elastic {r['elastic_um']:.3f}, slip {r['slip_um']:.3f}; "
            f"turn {r['turn_urad']:.2f} urad, {r['turn_share_um']:.3f} um), creep {r['creep_um_s']:.4f} um/s, slip "
            f"{r['slip_rate_um_s']:.4f} um/s over the last {r['window_s']:g} s, points at cap {r['at_cap']}/{r['points']}, "
            f"water KE {r['water_kinetic_release_j']:.3g} -> {r['water_kinetic_end_j']:.3g} J/m "
            f"({r['wall_settle_s']:.0f} + {r['wall_s']:.0f} s)")
        rows.append(r)
    stem = a.out or str(RESULTS / f"submerged_block-{a.device.replace(':', '')}")
    md = [f"# Block under still water, alpha {ALPHA:g} deg (issue 36): {device_name(a.device)}, commit {commit()}, "
          f"spacing {a.spacing:g} m, k_n {a.kn:g} N/m per point, water settled {a.settle:g} s around the held rock, "
          f"then {a.duration:g} s free" + (", water in the joint (coupling.joint_water)" if a.joint_water else ""), "",
          "Displacements along the dip from the release, down-slope positive: the centroid's = the base's + the turn's "
          "share; the base's = its springs' elastic change + slip. Rates over the last window.", "",
          "| margin deg | particles | centroid um | base um | elastic um | slip um | turn urad (share um) | "
          "creep um/s | slip um/s | turn urad/s | at cap | water KE release, end J/m | wall s |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    md += [f"| {r['margin_deg']:+g} | {r['particles']} | {r['disp_um']:.3f} | {r['base_um']:.3f} | {r['elastic_um']:.3f} | "
           f"{r['slip_um']:.3f} | {r['turn_urad']:.2f} ({r['turn_share_um']:.3f}) | {r['creep_um_s']:.4f} | "
           f"{r['slip_rate_um_s']:.4f} | {r['turn_rate_urad_s']:.3f} | {r['at_cap']}/{r['points']} | "
           f"{r['water_kinetic_release_j']:.3g}, {r['water_kinetic_end_j']:.3g} | "
           f"{r['wall_settle_s']:.0f} + {r['wall_s']:.0f} |" for r in rows]
    with open(stem + ".md", "w") as f:
        f.write("\n".join(md) + "\n")
    write_json(dict(rows=rows, device=a.device, commit=commit(), args=vars(a)), stem + ".json")
    print("\n".join(md))


if __name__ == "__main__":
    main()
