"""Scene -> typed options and parameters: the one place that reads the scene's keys for the solvers.

The physics packages (rockwave/sph, dda, coupling) never see a Scene or its dicts: the builder hands them
what this module makes of the scene, typed, with the units in the names:

- :func:`fluid_parameters`: the [fluid] section as :class:`rockwave.sph.fluid.FluidParameters`;
  :func:`sph_params`: the kernels' SPHParams of a scene (rockwave.sph.fluid.make_params);
- :func:`fluid_options`, :func:`ghost_options`, :func:`block_options`, :func:`coupling_options`: the solvers'
  Options, the scene's settings merged with those given in Python (rockwave.sim.simulation.SimulationOptions);
- derived quantities of a scene, each computed by one function of rockwave/sph/fluid.py that every caller shares
  (builder, preflight, guard): :func:`support_radius_m`, :func:`boundary_lattice`.

Each option's default lives in its Options dataclass; the scene SCHEMA (rockwave/scene/format.py) takes it from
there (tests/test_defaults.py).
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from typing import Protocol

import numpy as np

from rockwave.coupling.penalty import CouplingOptions
from rockwave.dda.blocks import BlockOptions
from rockwave.kernels.sph import fluid as sph
from rockwave.scene.format import Node, Scene
from rockwave.sph.fluid import Density, FluidOptions, FluidParameters, make_params, support_radius, wall_layers
from rockwave.sph.ghost import GHOST_CFL_MAX, GhostOptions


class SolverOptions(Protocol):
    """What the builder reads of the options given in Python (rockwave.sim.simulation.SimulationOptions): each
    solver's options, None for the scene's settings and the defaults."""

    fluid: FluidOptions | None
    ghost: GhostOptions | None
    blocks: BlockOptions | None
    coupling: CouplingOptions | None


# [fluid.ghost] keys -> GhostOptions fields of the same name (the scene's settings of the ghost solver)
GHOST_SCENE_KEYS = ("surface_threshold", "sample_radius_ratio", "layer_ratio", "sampler", "attempts", "rounds",
                    "pressure_term", "density_cap", "persistent")


def fluid_parameters(fluid: Node | dict) -> FluidParameters:
    """The fluid's formulation from a validated scene's [fluid] section (``scene.fluid``; a dict of the same keys)."""
    eos, visc = fluid["eos"], fluid["viscosity"]
    return FluidParameters(
        spacing_m=fluid["spacing_m"],
        rest_density_kg_m3=fluid["rest_density_kg_m3"],
        kernel=fluid["kernel"],
        support_radius_ratio=fluid["support_radius_ratio"],
        eos_type=eos["type"],
        eos_gamma=eos["gamma"],
        eos_speed_of_sound_m_s=eos["speed_of_sound_m_s"],
        eos_b_pa=eos["b_pa"],
        eos_k_m2_s2=eos["k_m2_s2"],
        clamp_negative_pressure=bool(fluid["clamp_negative_pressure"]),
        density_floor=bool(fluid.get("density_floor")),
        pressure_force=fluid["pressure_force"],
        laplacian_viscosity_pa_s=visc["laplacian_pa_s"],
        artificial_alpha=visc["artificial_alpha"],
        xsph_epsilon=visc["xsph_epsilon"],
        boundary="adami" if fluid.get("boundary") == "adami" else "akinci",
        wall_slip="no_slip" if fluid.get("wall_slip") == "no_slip" else "free",
        gradient_correction=bool(fluid.get("gradient_correction")),
        wall_volume="geometric" if fluid.get("wall_volume") == "geometric" else "mass",
        density=Density.SUMMATION if fluid["density"] == "summation" else Density.CONTINUITY,
        density_diffusion=float(fluid.get("density_diffusion", 0.0) or 0.0),
        particle_shifting=float(fluid.get("particle_shifting", 0.0) or 0.0),
        density_diffusion_form=fluid.get("density_diffusion_form") or "hydrostatic",
        density_diffusion_renormalised=bool(fluid.get("density_diffusion_renormalised")),
        wall_work=bool(fluid.get("wall_work", FluidParameters.wall_work)),
    )


def sph_params(scene: Scene, n_fluid: int) -> sph.SPHParams:
    """The kernels' parameters of the scene's fluid (before the lattice calibration of build_fluid_model)."""
    return make_params(fluid_parameters(scene.fluid), scene.dim, scene.gravity.acceleration_m_s2, n_fluid)


def support_radius_m(scene: Scene) -> float:
    """Kernel support radius H [m] of the scene's fluid (rockwave.sph.fluid.support_radius)."""
    return support_radius(scene.fluid.spacing_m, scene.fluid.support_radius_ratio)


def boundary_lattice(scene: Scene) -> tuple[float, int]:
    """Boundary particle spacing [m] and number of layers of a scene's walls (tank and obstacles; without a tank:
    those of the wall particles on fixed blocks, rockwave/build/builder.py fixed_block_walls): tank.layers, or
    enough to cover the kernel support (rockwave.sph.fluid.wall_layers)."""
    t, spacing = scene.tank, scene.fluid.spacing_m
    H = support_radius_m(scene)
    if t is None:
        return spacing, wall_layers(H, spacing)
    bstep = spacing * t.boundary_spacing_ratio
    return bstep, (t.layers or wall_layers(H, bstep))


def gravity_norm(scene: Scene) -> float:
    """|g| [m/s^2] of the scene."""
    return float(np.linalg.norm(scene.gravity.acceleration_m_s2))


def fluid_options(scene: Scene, base: FluidOptions | None = None) -> FluidOptions:
    """The fluid solver's options: ``base`` (Python; None: the defaults) with the scene's Courant number
    (``simulation.cfl_number``) where ``base.cfl_number`` is None and its neighbour search (``fluid.neighbours``)
    where ``base.neighbours`` is None."""
    o = base or FluidOptions()
    if o.cfl_number is None:
        o = replace(o, cfl_number=scene.simulation.cfl_number)
    if o.neighbours is None:
        given = scene.fluid.get("neighbours") if scene.fluid is not None else None
        o = replace(o, neighbours=given or FluidOptions.DEFAULT_NEIGHBOURS)
    return o


def ghost_options(scene: Scene, base: GhostOptions | None = None) -> GhostOptions:
    """The ghost solver's options: ``base`` (Python: the sampling knobs; None: the defaults) with the settings of the
    scene's [fluid.ghost] section (GHOST_SCENE_KEYS; a key the section leaves unset keeps base's value)."""
    o = base or GhostOptions()
    gh = (scene.fluid.get("ghost") if scene.fluid is not None else None) or {}
    kw = {k: gh.get(k) for k in GHOST_SCENE_KEYS if gh.get(k) is not None}
    return replace(o, **kw) if kw else o


def warn_unstable_step(scene: Scene) -> None:
    """Warn when a ghost scene steps with a Courant number above GHOST_CFL_MAX (rockwave/sph/ghost.py)."""
    sim = scene.simulation
    if sim.time_step == "cfl" and sim.cfl_number > GHOST_CFL_MAX:
        warnings.warn(f"{scene.path}: simulation.cfl_number = {sim.cfl_number:g} with fluid.method = 'ghost': ghost steps "
                      f"above a Courant number of {GHOST_CFL_MAX} were measured to gain energy and blow up in a "
                      f"splash (dam break case 3); use simulation.cfl_number <= {GHOST_CFL_MAX}", stacklevel=3)


def block_options(scene: Scene) -> BlockOptions:
    """The block solver's options a scene sets (``simulation.block_dt_safety``, ``simulation.block_contacts``,
    ``simulation.start``), the defaults for the rest."""
    kw = {}
    safety = scene.simulation.get("block_dt_safety")
    if safety is not None:
        kw["dt_safety"] = float(safety)
    if scene.simulation.get("block_contacts") == "found":
        kw["hold_contacts"] = False
    if scene.simulation.get("start") is not None:
        kw["start"] = scene.simulation.get("start")
    return BlockOptions(**kw)


def coupling_options(scene: Scene) -> CouplingOptions:
    """The coupling's options of the scene's ``[coupling]`` section (the defaults where it gives none)."""
    c = scene.coupling
    if c is None:
        return CouplingOptions()
    d = CouplingOptions()

    def pick(key):
        v = c.get(key)
        return getattr(d, key) if v is None else v

    return CouplingOptions(contact_distance_ratio=float(pick("contact_distance_ratio")),
                           stiffness_factor=float(pick("stiffness_factor")),
                           damping_ratio=float(pick("damping_ratio")),
                           stiffness_n_m=c.get("stiffness_n_m"), damping_n_s_m=c.get("damping_n_s_m"),
                           squeeze_out=c.get("squeeze_out") is not False, block_walls=bool(c.get("block_walls")),
                           joint_water=bool(pick("joint_water")))
