"""Part ``multirate``: the cost of a coupled slide with multi-rate stepping (issue 20; docs/coupling.md "Multi-rate
stepping"). scenes/submarine_slide_2d.toml at each spacing, three runs timed over the same simulated
window after a warm-up (kernels loaded): ``multirate`` (the default: the fluid's limit sets the step, the
block sub-steps), ``single`` (simulation.block_stepping = 'single': one step for both at the block
contact's limit; a shorter window, it is slow) and ``no_block`` (the slide removed, the fixed slope kept).
Cost = wall-clock seconds per simulated second; the issue's target is multirate / no_block <= 1.3 at
>= 90,000 particles (5 mm). Each row also records the step, what set it and the block sub-steps.
"""

from __future__ import annotations

import copy

import numpy as np

from benchmarks.common import ROOT, log

CONFIG = {"quick": dict(slide_spacings=[0.04], slide_duration_s=0.05, slide_single_duration_s=0.02),
          "full": dict(slide_spacings=[0.02, 0.01, 0.005], slide_duration_s=0.5, slide_single_duration_s=0.1)}
SCENE = ROOT / "scenes" / "submarine_slide_2d.toml"
WARMUP_S = 0.005


def slide_dict(spacing: float, variant: str) -> dict:
    """The scene dict at ``spacing`` for a variant: 'multirate', 'single' or 'no_block'."""
    import rockwave

    d = copy.deepcopy(rockwave.load_scene(SCENE).raw)
    d["fluid"]["spacing_m"] = spacing
    d["simulation"]["block_stepping"] = "single" if variant == "single" else "multirate"
    if variant == "no_block":
        d["blocks"] = [b for b in d["blocks"] if b["name"] != "slide"]
    return d


def slide_run(device: str, spacing: float, variant: str, duration: float) -> dict:
    import rockwave
    from benchmarks.harness import Clock

    sim = rockwave.Simulation(rockwave.parse_scene(slide_dict(spacing, variant), SCENE, SCENE.parent), device=device)
    sim.advance(WARMUP_S)
    b = sim.blocks.names.index("slide") if "slide" in sim.blocks.names else None
    x0 = sim.block_positions()[b].copy() if b is not None else None
    steps0, block_steps0, t0 = sim.steps, sim.clock.block_steps, sim.time
    clock = Clock(sim.device)
    clock.run(lambda: sim.advance(duration))
    c = sim.clock
    return dict(spacing_m=spacing, variant=variant, particles=sim.n_fluid, simulated_s=sim.time - t0,
                steps=sim.steps - steps0, block_steps=c.block_steps - block_steps0, dt_s=c.dt, limited_by=c.limiting,
                block_substeps=c.substeps, wall_s=clock.seconds, wall_per_sim_s=clock.seconds / (sim.time - t0),
                slide_travel_m=float(np.linalg.norm(sim.block_positions()[b] - x0)) if b is not None else None)


def run(dev: str, cfg: dict) -> dict:
    rows = []
    for s in cfg["slide_spacings"]:
        group = {}
        for variant in ("multirate", "no_block", "single"):
            T = cfg["slide_single_duration_s"] if variant == "single" else cfg["slide_duration_s"]
            r = group[variant] = slide_run(dev, s, variant, T)
            rows.append(r)
            log(f"  slide {s:g} m {variant:9s} n={r['particles']:7d} dt {r['dt_s']:.3g} s ({r['limited_by']}) "
                f"x{r['block_substeps']} blocks: {r['wall_per_sim_s']:.3g} wall s per simulated s")
        ratio = group["multirate"]["wall_per_sim_s"] / group["no_block"]["wall_per_sim_s"]
        group["multirate"]["over_no_block"] = ratio
        group["single"]["over_multirate"] = group["single"]["wall_per_sim_s"] / group["multirate"]["wall_per_sim_s"]
        log(f"  slide {s:g} m: multirate / no_block = {ratio:.2f} (target <= 1.3), "
            f"single / multirate = {group['single']['over_multirate']:.1f}")
    return {"runs": rows}
