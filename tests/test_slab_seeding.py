"""A slab's seeding (rockwave/build/slab.py) against the whole scene's (rockwave/build/builder.py seed_fluid).

A rank of a distributed run seeds only its slab; its particles must be the whole seeding's, to the bit: the same
positions (packed start included), velocities, depths (the hydrostatic start), the same removal inside blocks and
the same ids (the whole seeding's order, which the outputs and checkpoints keep), and the slab faces the quantiles
of the whole scene's coordinates. The layout pass runs in windows of a few columns here (WINDOW_POINTS lowered)
so that the window seams are crossed; each slab holds its own particles plus two spacings on each side only.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import warp as wp

from rockwave.build import builder, slab
from rockwave.scene.format import load_scene

ROOT = Path(__file__).resolve().parents[1]

# 2D: two regions, the upper one stacked on the lower on a lattice offset by a third of a spacing (their columns
# link in the packed start), an obstacle box cut out of the water, a tank, the packed start (standard level)
STACKED = """
[simulation]
dimension = 2
duration_s = 0.1

[fluid]
spacing_m = 0.01

[fluid.eos]
type = "tait"
speed_of_sound_m_s = 15.0

[[fluid.regions]]
box_min_m = [0.0, 0.0]
box_max_m = [0.6, 0.1]

[[fluid.regions]]
box_min_m = [0.0033, 0.1]
box_max_m = [0.3033, 0.16]
velocity_m_s = [0.2, 0.0]

[tank]
box_min_m = [0.0, 0.0]
box_max_m = [0.8, 0.4]

[[obstacles]]
box_min_m = [0.35, 0.0]
box_max_m = [0.42, 0.05]
"""


def _whole_and_slabs(scene, ranks: int, monkeypatch, window: int):
    monkeypatch.setattr(slab, "WINDOW_POINTS", window)
    dev = "cpu"
    with wp.ScopedDevice(dev):
        p1, p2 = builder.Parts(), builder.Parts()
        if scene.blocks:
            builder.build_blocks(scene, dev, p1)
            builder.build_blocks(scene, dev, p2)
        whole = builder.seed_fluid(scene, dev, p1)
        layout = slab.fluid_layout(scene, dev, p2)
    return whole, layout, p1, p2


def _check(scene, ranks: int, monkeypatch, window: int):
    whole, layout, p1, p2 = _whole_and_slabs(scene, ranks, monkeypatch, window)
    n = len(whole.fluid)
    assert layout.n_fluid == n
    assert p2.removed_inside_blocks == p1.removed_inside_blocks
    assert np.array_equal(layout.lo, whole.fluid.min(axis=0)) and np.array_equal(layout.hi, whole.fluid.max(axis=0))
    assert np.array_equal(layout.first, whole.fluid[0])
    assert np.array_equal(layout.boundary, whole.boundary)  # tank, obstacles and the fixed blocks' Adami walls
    axis = int(np.argmax((whole.fluid.max(axis=0) - whole.fluid.min(axis=0))[: scene.dim]))
    coords, counts = layout.plane_counts(axis)
    c = np.sort(whole.fluid[:, axis])
    inner = [slab.quantile_from_counts(coords, counts, r / ranks) for r in range(1, ranks)]
    assert inner == [float(np.quantile(c, r / ranks)) for r in range(1, ranks)]
    faces = np.array([-np.inf, *np.asarray(inner, np.float32).astype(np.float64), np.inf])
    own = np.searchsorted(faces, whole.fluid[:, axis].astype(np.float32).astype(np.float64), side="right") - 1
    margin = 2.0 * scene.fluid.spacing_m
    for r in range(ranks):
        with wp.ScopedDevice("cpu"):
            seeds, ids, held = slab.seed_fluid_slab(scene, "cpu", p2, layout, axis, faces, r)
        mine = np.flatnonzero(own == r)
        assert np.array_equal(ids, mine)  # the whole seeding's ids, in its order
        assert np.array_equal(seeds.fluid, whole.fluid[mine])
        assert np.array_equal(seeds.velocities, whole.velocities[mine])
        assert np.array_equal(seeds.depth, whole.depth[mine])
        # held: the slab and two spacings (plus a float32 rounding) each side, with the lattice points dropped
        # there (at most all dropped ones), never the whole water
        lo, hi = faces[r] - margin - 1e-5, faces[r + 1] + margin + 1e-5
        in_window = int(((whole.fluid[:, axis] >= lo) & (whole.fluid[:, axis] < hi)).sum())
        dropped = sum(int(np.prod([len(a) for a in g.axes])) for g in layout.regions) - n  # tank, obstacles, blocks
        assert held <= in_window + dropped and held < n
    return layout


def test_stacked_regions_with_obstacle_2d(tmp_path, monkeypatch):
    p = tmp_path / "stacked.toml"
    p.write_text(STACKED)
    layout = _check(load_scene(p), 3, monkeypatch, window=300)
    assert layout.peak_points < layout.n_fluid  # the layout pass held a window, not the whole lattice


def test_slide_3d_fixed_blocks_removal_adami_walls(monkeypatch):
    """scenes/slide_3d.toml: no tank, fixed blocks (their Adami wall particles anchored on particle 0 and placed
    by the water's box), water removed inside the slope and the beach, the packed start."""
    scene = load_scene(ROOT / "scenes" / "slide_3d.toml")
    scene.fluid["spacing_m"] = 0.04
    layout = _check(scene, 2, monkeypatch, window=400)
    assert layout.removed_inside_blocks > 0


def test_vertical_slabs_are_refused(tmp_path, monkeypatch):
    p = tmp_path / "stacked.toml"
    p.write_text(STACKED)
    scene = load_scene(p)
    _, layout, _, p2 = _whole_and_slabs(scene, 2, monkeypatch, 10_000)
    with pytest.raises(ValueError, match="vertical"):
        slab.seed_fluid_slab(scene, "cpu", p2, layout, 1, np.array([-np.inf, 0.05, np.inf]), 0)
