"""One home per default (issue 35): an option's default lives in its Options dataclass (or the physics dataclass
the builder fills) and the scene SCHEMA takes it from there; the builder's scene -> options adapters
(rockwave/build/options.py) turn a scene that sets nothing into the dataclasses' defaults."""

import ast
import dataclasses

import pytest

import rockwave
from rockwave.build.options import (
    GHOST_SCENE_KEYS,
    block_options,
    coupling_options,
    fluid_options,
    ghost_options,
)
from rockwave.coupling.penalty import CouplingOptions
from rockwave.dda.blocks import BlockOptions, BlockSpec, ContactMaterial
from rockwave.scene.format import SCHEMA
from rockwave.sph.fluid import FluidOptions
from rockwave.sph.ghost import GhostOptions

from helpers import ROOT, tank_2d, with_changes

# scene key path -> (class, field): the scene key's default must be that field's default. Written out by hand, so
# that a default written twice (a literal in SCHEMA, another in the dataclass) fails here whichever side changes.
FIELD_DEFAULTS = {
    "simulation.block_dt_safety": (BlockOptions, "dt_safety"),
    "fluid.ghost.surface_threshold": (GhostOptions, "surface_threshold"),
    "fluid.ghost.sample_radius_ratio": (GhostOptions, "sample_radius_ratio"),
    "fluid.ghost.layer_ratio": (GhostOptions, "layer_ratio"),
    "fluid.ghost.sampler": (GhostOptions, "sampler"),
    "fluid.ghost.attempts": (GhostOptions, "attempts"),
    "fluid.ghost.rounds": (GhostOptions, "rounds"),
    "fluid.ghost.pressure_term": (GhostOptions, "pressure_term"),
    "fluid.ghost.density_cap": (GhostOptions, "density_cap"),
    "fluid.ghost.persistent": (GhostOptions, "persistent"),
    "coupling.contact_distance_ratio": (CouplingOptions, "contact_distance_ratio"),
    "coupling.stiffness_factor": (CouplingOptions, "stiffness_factor"),
    "coupling.damping_ratio": (CouplingOptions, "damping_ratio"),
    "coupling.stiffness_n_m": (CouplingOptions, "stiffness_n_m"),
    "coupling.damping_n_s_m": (CouplingOptions, "damping_n_s_m"),
    "coupling.squeeze_out": (CouplingOptions, "squeeze_out"),
    "coupling.block_walls": (CouplingOptions, "block_walls"),
    "coupling.joint_water": (CouplingOptions, "joint_water"),
    "blocks.density_kg_m3": (BlockSpec, "density"),
    "blocks.poisson_ratio": (BlockSpec, "poisson_ratio"),
    "blocks.strain_damping_ratio": (BlockSpec, "strain_damping_ratio"),
    "blocks.material.friction_angle_deg": (ContactMaterial, "friction_angle_deg"),
    "blocks.material.cohesion_pa": (ContactMaterial, "cohesion_pa"),
    "blocks.material.tensile_strength_pa": (ContactMaterial, "tensile_strength_pa"),
    "rock_mass.density_kg_m3": (BlockSpec, "density"),
    "rock_mass.poisson_ratio": (BlockSpec, "poisson_ratio"),
    "rock_mass.material.friction_angle_deg": (ContactMaterial, "friction_angle_deg"),
    "rock_mass.material.cohesion_pa": (ContactMaterial, "cohesion_pa"),
    "rock_mass.material.tensile_strength_pa": (ContactMaterial, "tensile_strength_pa"),
}

# scene keys whose default is another form of an Options default: path -> (expected schema default, why)
OTHER_DEFAULTS = {
    "simulation.cfl_number": (FluidOptions.DEFAULT_CFL_NUMBER, "FluidOptions.DEFAULT_CFL_NUMBER (cfl_number None)"),
    "simulation.block_contacts": ("held" if BlockOptions.hold_contacts else "found", "BlockOptions.hold_contacts"),
}


def _schema_key(path: str):
    spec, key = SCHEMA, None
    for part in path.split("."):
        key = spec[part]
        spec = key.children or {}
    return key


def _field_default(cls, name: str):
    f = {f.name: f for f in dataclasses.fields(cls)}[name]
    assert f.default is not dataclasses.MISSING, f"{cls.__name__}.{name} has no plain default"
    return f.default


@pytest.mark.parametrize("path", sorted(FIELD_DEFAULTS))
def test_schema_default_is_the_field_default(path):
    cls, name = FIELD_DEFAULTS[path]
    assert _schema_key(path).default == _field_default(cls, name), f"{path} vs {cls.__name__}.{name}"


@pytest.mark.parametrize("path", sorted(OTHER_DEFAULTS))
def test_schema_default_is_the_options_default(path):
    expected, why = OTHER_DEFAULTS[path]
    assert _schema_key(path).default == expected, f"{path} vs {why}"


def test_every_option_section_key_is_mapped():
    """Every key of [fluid.ghost] and [coupling] is a field of GhostOptions / CouplingOptions, mapped above (a new key
    gets its default from the dataclass, and a line here)."""
    for section, cls in (("fluid.ghost", GhostOptions), ("coupling", CouplingOptions)):
        for name in _schema_key(section).children:
            assert f"{section}.{name}" in FIELD_DEFAULTS, f"{section}.{name}: not mapped to {cls.__name__}"
            assert name in {f.name for f in dataclasses.fields(cls)}
    assert set(GHOST_SCENE_KEYS) == set(_schema_key("fluid.ghost").children)


def _literal_defaults(path) -> dict[str, object]:
    """Key name -> default of every Key(...) call in SCHEMA's source whose default is a literal number or bool."""
    tree = ast.parse(path.read_text())
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and isinstance(node.value, ast.Call) and getattr(node.value.func, "id", "") == "Key":
            for kw in node.value.keywords:
                if kw.arg == "default" and isinstance(kw.value, ast.Constant):
                    out.setdefault(node.arg, []).append(kw.value.value)
    return out


def test_mapped_schema_defaults_are_not_literals():
    """The mapped keys take their default from the dataclass (no second literal in rockwave/scene/format.py)."""
    literals = _literal_defaults(ROOT / "rockwave" / "scene" / "format.py")
    for path in list(FIELD_DEFAULTS) + list(OTHER_DEFAULTS):
        name = path.rsplit(".", 1)[-1]
        if name in ("friction_angle_deg", "cohesion_pa", "tensile_strength_pa"):
            continue  # the joint sets' keys of the same names are the joints' own (rockwave/build/rockmass.py)
        if _schema_key(path).default is None:
            continue
        assert name not in literals, f"{path}: a literal default in SCHEMA ({literals[name]}); take it from the dataclass"


def test_a_scene_that_sets_nothing_gives_the_option_defaults():
    """The builder's adapters turn the schema's defaults into the dataclasses' defaults."""
    d = with_changes(tank_2d(), **{"fluid.method": "ghost", "fluid.fidelity": "draft", "coupling": {}})
    scene = rockwave.parse_scene(d)
    assert block_options(scene) == BlockOptions()
    assert coupling_options(scene) == CouplingOptions()
    g = ghost_options(scene)
    assert all(getattr(g, k) == getattr(GhostOptions(), k) for k in GHOST_SCENE_KEYS)
    plain = rockwave.parse_scene(tank_2d())
    assert fluid_options(plain).cfl_number == FluidOptions.DEFAULT_CFL_NUMBER


def test_the_scene_sets_the_ghost_settings_over_python_and_keeps_the_knobs():
    d = with_changes(tank_2d(), **{"fluid.method": "ghost", "fluid.fidelity": "draft", "fluid.ghost.sampler": "darts",
                                   "fluid.ghost.attempts": 8, "fluid.ghost.layer_ratio": 1.5})
    g = ghost_options(rockwave.parse_scene(d), GhostOptions(attempts=4, shortcuts=False, surface_threshold=1.2))
    assert (g.sampler, g.attempts, g.layer_ratio, g.shortcuts, g.surface_threshold) == ("darts", 8, 1.5, False, 1.2)
