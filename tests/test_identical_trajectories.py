"""Restructuring guard: every shipped scene gives bit-identical CPU trajectories to the hashes
recorded in tests/golden/trajectories.json (positions, velocities, densities, block poses after a
dozen adaptive steps and a dozen reordered chunk steps). A deliberate physics change regenerates them
with ``python tests/golden/trajectories.py --write`` in the same commit."""

import json

import pytest

from tests.golden.trajectories import FILE, ROOT, scene_hashes

RECORDED = json.loads(FILE.read_text())


@pytest.mark.parametrize("name", sorted(RECORDED))
def test_scene_trajectory_is_bit_identical(name):
    assert scene_hashes(ROOT / "scenes" / f"{name}.toml") == RECORDED[name]
