"""Scene files: TOML -> validated :class:`Scene`.

Every key is checked against :data:`SCHEMA`. Errors are collected (all at once, not one at a
time) and raised as one :class:`SceneError` whose lines name the scene file, the key path
(``fluid.eos.gamma``) and what is allowed. Units are SI and appear in the key names
(``_m``, ``_s``, ``_kg_m3``, ``_pa`` ...). The scene-format reference docs/scene_format.md is generated from the
same schema (``python -m rockwave schema``), so docs and checks cannot drift apart.
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rockwave.base.device import device_syntax_error
from rockwave.coupling.penalty import CouplingOptions
from rockwave.dda.blocks import (
    DEFAULT_RESTITUTION,
    DEFAULT_YOUNGS_MODULUS,
    PENALTY_FACTOR,
    BlockOptions,
    BlockSpec,
    ContactMaterial,
)
from rockwave.sph.fluid import FluidOptions, FluidParameters, support_radius, walls_cover_support
from rockwave.sph.ghost import DEFAULT_RADIUS_RATIO, DEFAULT_THRESHOLD, GHOST_CFL_MAX, GhostOptions


class SceneError(ValueError):
    """A scene file that cannot be used. ``errors`` holds one ``(key_path, message)`` per problem."""

    def __init__(self, path: str | os.PathLike | None, errors: list[tuple[str, str]]):
        self.path = str(path) if path is not None else "<scene>"
        self.errors = errors
        lines = [f"{self.path}: {key}: {msg}" if key else f"{self.path}: {msg}" for key, msg in errors]
        super().__init__("\n".join(lines))

    def one_line(self) -> str:
        n = len(self.errors)
        head = f"{self.path}: {self.errors[0][0]}: {self.errors[0][1]}" if self.errors[0][0] else f"{self.path}: {self.errors[0][1]}"
        return head if n == 1 else f"{head} (and {n - 1} more problem{'s' if n > 2 else ''}: run 'python -m rockwave validate' to list them)"


# --------------------------------------------------------------------------------------------
# Schema description
# --------------------------------------------------------------------------------------------


@dataclass
class Key:
    """One scene key: its type, default, allowed range or choices and a one-line doc."""

    type: str  # "float", "int", "bool", "str", "path", "vec", "table_list", "section", "floatlist"
    doc: str = ""
    default: Any = None
    required: bool = False
    min: float | None = None  # inclusive unless min_open
    max: float | None = None
    min_open: bool = False
    choices: tuple | None = None
    length: int | str | None = None  # vec length, or "dim" for the scene dimension
    children: dict[str, "Key"] | None = None  # for section / table_list
    optional: bool = False  # an optional section is None when the scene leaves it out

    def allowed(self) -> str:
        parts = []
        if self.choices:
            parts.append("one of " + ", ".join(repr(c) for c in self.choices))
        if self.min is not None or self.max is not None:
            lo = "" if self.min is None else (f"> {self.min:g}" if self.min_open else f">= {self.min:g}")
            hi = "" if self.max is None else f"<= {self.max:g}"
            parts.append(" and ".join(p for p in (lo, hi) if p))
        if self.type == "vec":
            n = "2 (2D) or 3 (3D)" if self.length == "dim" else str(self.length)
            parts.append(f"list of {n} numbers")
        return "; ".join(parts)


def _sec(doc: str, optional: bool = False, **children: Key) -> Key:
    return Key("section", doc=doc, children=children, optional=optional)


def _list(doc: str, **children: Key) -> Key:
    return Key("table_list", doc=doc, default=[], children=children)


_REGION_KEYS = dict(
    box_min_m=Key("vec", "lower corner of a box region", length="dim"),
    box_max_m=Key("vec", "upper corner of a box region", length="dim"),
    mesh=Key("path", "closed mesh file (STL, OBJ, PLY, GLB; through trimesh), path relative to the scene file; 3D only"),
    mesh_scale=Key("float", "uniform scale applied to the mesh (e.g. 0.001 for a mesh in millimetres)", default=1.0, min=0, min_open=True),
    mesh_offset_m=Key("vec", "translation applied to the mesh after scaling", length=3, default=[0.0, 0.0, 0.0]),
)


# fluid.fidelity -> the defaults it gives (a key the scene sets wins). Chosen from the accuracy-against-cost
# measurements in docs/notes.md ('Accuracy against cost', 'Kernel-gradient correction'); 'draft' is the formulation
# that was the default before. No level turns on density diffusion: alone it blew up in SPHERIC Test 2 at 0.012 m on
# the H100 (splash water at a third of rho0 crossed the back wall; density_floor makes it stable) and it changed the
# standing wave's decay by 0.2 points only. 'waves' is 'standard' with the kernel-gradient correction and the
# density floor it needs in violent flows: on the H200 the standing wave decays 0.84% per period at 50 per depth
# (standard 2.3%, high 1.2%) with its period within 0.1%, the wave maker reads -6.8% / -2.6% at 32 layers (standard
# -6.7% / -7.0%), at 1.3x standard's cost in 2D and 1.44x in SPHERIC Test 2 (high: 2.3x); but water at rest reads
# 2-4% high at the walls (standard 1-2%) and the dam-break front runs 0.8 points farther ahead, so it is not the
# default. Ghost SPH takes a level without the correction and the floor (basic WCSPH only; apply_fidelity).
# Every level but draft starts packed at its hydrostatic density with Adami walls that keep their volume
# (packed_start, wall_volume = 'geometric'): water at rest on the H200 (2 s) then reads within 0.8% at the gauges
# and 1.7% at the walls, corners included (uniform start, 'mass': up to 1.8% and 2.7%), the wave maker -6.6% /
# -6.5% at 32 layers for standard (-6.7% / -7.0%) and -3.8% / -1.3% for waves (-6.8% / -2.6%), the standing wave
# and the dam break the same within 0.3 points, SPHERIC Test 2 H1-H4 0.062 (0.060), P1 peak +113% (+139%):
# docs/notes.md 'The balanced start as the default'.
# 'delta_plus' (issue 38, opt-in until the GPU chart confirms it): standard with the kernel-gradient correction (no
# density floor), delta-SPH diffusion of the pressure's density (walls included, kernels/sph/diffusion.py), light
# particle shifting with a free-surface band (K = 0.02, kernels/sph/shifting.py) and alpha 0: docs/physics.md 'The
# delta_plus level', docs/notes.md 'delta-plus' and 'delta-plus, second round'. Ghost SPH takes it without the
# correction, the shifting and the diffusion.
FIDELITY = {
    "draft": dict(kernel="muller", support_radius_ratio=2.0, density_diffusion=0.0, boundary="akinci", artificial_alpha=0.0,
                  density_floor=False, gradient_correction=False, packed_start=False, wall_volume="mass",
                  particle_shifting=0.0, density_diffusion_form="hydrostatic", density_diffusion_renormalised=False),
    "standard": dict(kernel="wendland", support_radius_ratio=3.0, density_diffusion=0.0, boundary="adami", artificial_alpha=0.01,
                     density_floor=False, gradient_correction=False, packed_start=True, wall_volume="geometric",
                     particle_shifting=0.0, density_diffusion_form="hydrostatic", density_diffusion_renormalised=False),
    "high": dict(kernel="wendland", support_radius_ratio=4.0, density_diffusion=0.0, boundary="adami", artificial_alpha=0.01,
                 density_floor=False, gradient_correction=False, packed_start=True, wall_volume="geometric",
                 particle_shifting=0.0, density_diffusion_form="hydrostatic", density_diffusion_renormalised=False),
    "waves": dict(kernel="wendland", support_radius_ratio=3.0, density_diffusion=0.0, boundary="adami", artificial_alpha=0.01,
                  density_floor=True, gradient_correction=True, packed_start=True, wall_volume="geometric",
                  particle_shifting=0.0, density_diffusion_form="hydrostatic", density_diffusion_renormalised=False),
    "delta_plus": dict(kernel="wendland", support_radius_ratio=3.0, density_diffusion=0.1, boundary="adami",
                       artificial_alpha=0.0, density_floor=False, gradient_correction=True, packed_start=True,
                       wall_volume="geometric", particle_shifting=0.02, density_diffusion_form="pressure",
                       density_diffusion_renormalised=False),
}

SCHEMA: dict[str, Key] = {
    "simulation": _sec(
        "run control",
        dimension=Key("int", "2 (x, y with y up; written in the z = 0 plane) or 3 (x, y, z with z up)", default=3, choices=(2, 3)),
        duration_s=Key("float", "simulated time", required=True, min=0, min_open=True),
        time_step=Key("str", "'cfl': adaptive step from the CFL, force and viscous limits; 'fixed': dt_s", default="cfl", choices=("cfl", "fixed")),
        cfl_number=Key("float", "Courant number C in dt <= C h/(c0 + u_max), h = H/2 (docs/physics.md 'Time step and Courant number'; with fluid.method = 'ghost' the default is " f"{GHOST_CFL_MAX:g}, rockwave/sph/ghost.py GHOST_CFL_MAX)", default=FluidOptions.DEFAULT_CFL_NUMBER, min=0, max=1.0, min_open=True),
        dt_s=Key("float", "fixed time step (time_step = 'fixed'); refused if above the stability limit", min=0, min_open=True),
        block_dt_safety=Key("float", "block step = this fraction of the critical DDA step 2/omega_max", default=BlockOptions.dt_safety, min=0.0, max=1.0, min_open=True),
        dt_update_interval=Key("int", "steps between adaptive time-step updates (one host read each)", default=10, min=1, max=10000),
        energy_check=Key("str", "the energy budget's check (rockwave/sim/energy.py): the total energy of water and rock growing beyond the input work of kinematic blocks by more than 1% of the scene's releasable energy is a 'warn'ing, an 'error' (the run stops as on a blow-up) or not checked ('off')", default="warn", choices=("warn", "error", "off")),
        block_contacts=Key("str", "multi-rate block sub-steps: 'held': a fluid step's first sub-step finds the contacts, the others carry them (points moved, depths advanced by the blocks' motion; while every pair out of contact stays farther apart than it can close in the step); 'found': every sub-step runs the narrow phase (docs/coupling.md 'Multi-rate stepping')", default="held" if BlockOptions.hold_contacts else "found", choices=("held", "found")),
        block_stepping=Key("str", "with water and blocks: 'multirate': the water's limits set the step and the blocks sub-step inside it at their own (the water's load held over the step; at most 1000 sub-steps); 'single': one step for both at the smallest limit (docs/coupling.md 'Multi-rate stepping')", default="multirate", choices=("multirate", "single")),
        device=Key("str", "'auto' (first GPU if any, else CPU), 'cpu', 'cuda' or 'cuda:N'; the CLI --device overrides", default="auto"),
        start=Key("str", "how blocks start: 'settled': the blocks resting on another at t = 0 (no initial velocity, gap below 1e-4 of the smaller one's size) are first brought to the equilibrium of their contact springs under gravity with friction locked, then released, so a stable block or rock mass starts at rest with its contacts loaded (blocks in the air or moving start as placed; a resting block that topples or falls even with friction locked is held while the others settle and released as placed, with a warning; a scene that does not come to rest starts plain, with a warning); 'plain': as placed, contacts unloaded and gravity from t = 0, so the contacts load while gravity already pulls (a stable block may slip while they load); run.json 'block_start' says what was done (docs/physics.md 'The start of a block scene')", default=BlockOptions.start, choices=("plain", "settled")),
    ),
    "gravity": _sec(
        "body force",
        acceleration_m_s2=Key("vec", "gravitational acceleration (default: -9.81 along the up axis)", length="dim"),
    ),
    "fluid": _sec(
        "weakly compressible SPH water (leave the section out for a scene of blocks alone)", optional=True,
        spacing_m=Key("float", "initial particle spacing", required=True, min=0, min_open=True),
        rest_density_kg_m3=Key("float", "rest density rho0", default=1000.0, min=0, min_open=True),
        fidelity=Key("str", "speed against accuracy without SPH internals: sets the defaults of kernel, support_radius_ratio, density_diffusion, density_diffusion_form, density_diffusion_renormalised, particle_shifting, gradient_correction, boundary, wall_volume, packed_start and viscosity.artificial_alpha (any of them given in the scene wins); 'draft': the old fast formulation (Mueller kernels at 2 spacings, frozen Akinci walls, no diffusion, uniform start); 'standard': Wendland C2 at 3 spacings, Adami walls keeping their volume, the start packed at its hydrostatic density, alpha 0.01; 'high': as standard at 4 spacings; 'waves': standard with gradient_correction and density_floor, for wave propagation (Ghost SPH takes it without the two); 'delta_plus' (opt-in): standard with gradient_correction (no density floor), delta-SPH diffusion 0.1 of the pressure's density (density_diffusion_form = 'pressure', walls included), particle shifting 0.02 with a free-surface band and alpha 0 (Ghost SPH takes it without the correction, the shifting and the diffusion); docs/validation.md 'Accuracy against cost' compares the levels", default="standard", choices=tuple(FIDELITY)),
        kernel=Key("str", "'muller': poly6 density, spiky pressure gradient, viscosity Laplacian (Mueller 2003); 'cubic_spline': Monaghan cubic spline for all; 'wendland': Wendland C2 (no pairing instability at large support_radius_ratio) for all; h = H/2 for the last two (default: from fidelity)", choices=("muller", "cubic_spline", "wendland")),
        support_radius_ratio=Key("float", "kernel support radius / spacing (2.0 gives ~30 neighbours in 3D, ~12 in 2D; 3.0 ~113 and ~28; above 1: at 1 the nearest neighbours sit on the support's edge; default: from fidelity)", min=1.0, max=5.0, min_open=True),
        boundary=Key("str", "wall treatment of the tank and obstacle particles: 'adami': generalized wall boundary (Adami, Hu & Adams 2012), each wall particle carries the pressure extrapolated from the fluid plus the hydrostatic part, so walls and corners get the fluid's pressure (needs walls as thick as the kernel support); 'akinci': frozen particles pushing with -Psi_b p_i/rho_i^2 grad W (Akinci et al. 2012; cheaper, wall pressure less accurate: docs/physics.md 'Walls'); default: from fidelity", choices=("adami", "akinci")),
        wall_volume=Key("str", "Adami walls: 'mass': a wall particle pushes with its mass m_b = rho0 V_b, so its volume m_b/rho_b shrinks as its pressure rises; 'geometric': it keeps its volume V_b, mass rho_b V_b in the pressure term (Adami et al. 2012 work with volumes). 'geometric' needs packed_start (without it the tank starts out of balance and rings; docs/physics.md 'Walls') (default: from fidelity, 'geometric' with Adami walls at every level but 'draft')", choices=("mass", "geometric")),
        packed_start=Key("bool", "continuity density: each vertical run of fluid particles starts packed at its hydrostatic density (layer spacing dx rho0/rho(d), the run's lowest particle fixed; a run under an obstacle or block stays on the lattice), not on the uniform lattice, so the start is in the discrete balance the uniform lattice misses by 2 g d/c0^2 at depth d (docs/notes.md 'Water at rest on the H200'); the surface settles g d^2/(2 c0^2) lower, as the compressed water does (default: from fidelity, true at every level but 'draft'; off with summation density and Ghost SPH)"),
        wall_slip=Key("str", "Adami walls: 'free' (no viscous force from walls) or 'no_slip' (viscous terms against the extrapolated wall velocity, Adami et al. 2012 eq. 23)", default="free", choices=("free", "no_slip")),
        pressure_force=Key("str", "'momentum': -m_i sum m_j (p_i/rho_i^2 + p_j/rho_j^2) gradW; 'muller': -m_i/rho_i sum m_j (p_i+p_j)/(2 rho_j) gradW", default="momentum", choices=("momentum", "muller")),
        density=Key("str", "'continuity': d rho_i/dt = sum m_j (v_i - v_j).gradW_ij (keeps rho0 at a free surface); 'summation': rho_i = sum m_j W_ij", default="continuity", choices=("continuity", "summation")),
        clamp_negative_pressure=Key("bool", "clip p < 0 to 0 (prevents tensile clumping at a free surface with summation density)", default=True),
        density_floor=Key("bool", "continuity density kept at rho0 or above: with negative pressure clipped a lower density holds no pressure and no energy, only a memory of expansion, and a splash particle whose neighbours left it is compressed back that far before it pushes (kernels/sph/fluid.py continuity_floor). Only 'waves' (with gradient_correction, which needs it) sets it (docs/notes.md 'Density floor'); basic method, continuity density and clamp_negative_pressure only (default: from fidelity, false)"),
        gradient_correction=Key("bool", "kernel-gradient correction in the continuity and pressure terms: G_ij = (L_i + L_j)/2 grad W_ij, L_i the inverse of sum_j V_j grad W_ij (x) (x_j - x_i) (Bonet & Lok 1999; symmetrised, so momentum and the pressure's energy exchange are kept), blended to the plain gradient where the support is short of neighbours (smallest eigenvalue of the matrix below 0.75: the free surface and splash, Marrone et al. 2010; kernels/sph/fluid.py gradient_correction_matrix); pairs with wall particles keep the plain gradient. Use with density_floor in violent flows (docs/notes.md 'Kernel-gradient correction'); basic method only (default: from fidelity, true for 'waves' and 'delta_plus')"),
        density_diffusion=Key("float", "delta of the delta-SPH density diffusion with continuity density (Molteni & Colagrossi 2009, hydrostatic part removed as Fourtakas et al. 2019): d rho_i/dt += delta (H/2) c0 sum_j 2 (rho_j - rho_i - rho0 g.x_ji/c0^2) x_ji.grad_i W_ij/r^2 V_j; 0.1 typical, 0 = off; continuity density only (kernels/sph/diffusion.py; default: from fidelity, 0 with summation density)", min=0.0, max=1.0),
        particle_shifting=Key("float", "K of the particle shifting (delta-plus-SPH, Sun et al. 2017; Lind et al. 2012): each step a particle moves by dr_i = -K Ma H^2 sum_j [1 + 0.2 (W_ij/W(dx))^4] grad W_ij V_j, Ma = max speed / c0, walls counted as water; only along the free surface for particles within one kernel support of it (Marrone et al. 2010's indicator), not at all for splash; at most a quarter spacing a step (kernels/sph/shifting.py); 0 = off; basic method only (default: from fidelity, 0.02 for 'delta_plus', 0 otherwise)", min=0.0, max=5.0),
        density_diffusion_form=Key("str", "what the density diffusion diffuses: 'hydrostatic': the continuity density, its hydrostatic part rho0 g.x_ji/c0^2 taken out of the difference (Fourtakas et al. 2019), the Adami wall particles in the sum with the density of their extrapolated pressure; 'pressure': the same for the density of the pressure, max(rho, rho0) with clipped negative pressure (a density below rho0 holds no pressure; diffused as it is, the run-up sheet on a wall drained the compression of the water pressed into the wall, which then crept into it: docs/physics.md 'The delta_plus level') (kernels/sph/diffusion.py; default: from fidelity)", choices=("hydrostatic", "pressure")),
        density_diffusion_renormalised=Key("bool", "Antuono et al. (2010)'s delta-SPH term: the renormalised density gradients of both particles taken out of the diffusion's difference, psi_ij = 2 (rho_j - rho_i) x_ji/|x_ji|^2 - (<grad rho>_i^L + <grad rho>_j^L), so that it vanishes for any linear density field, also where the support is cut under the free surface (one more neighbour pass; kernels/sph/diffusion.py; default: from fidelity, false for every level)"),
        wall_work=Key("bool", "Adami walls with continuity density: the work of the walls' extrapolated pressure p_b on the water paid by the fluid particles that set it, each by its Shepard share of the extrapolation times p_b/mean(p_b) (at most 2), through its continuity density (kernels/sph/wall_work.py). Without it a block landing on a floor under water gains the water energy from nothing (the p_b half of the wall term is paid by no equation; docs/coupling.md 'Landing under water'); with it sloshing is damped more (standing wave at 12 per depth: 5.1% a period against 3.8%; docs/physics.md 'Walls'). Opt-in; needs fluid.neighbours = 'lists' and one rank", default=FluidParameters.wall_work),
        neighbours=Key("str", "how the fluid passes find their neighbours (the physics is the same, the pairs and their order too): 'lists': a Verlet list of the pairs within (1 + skin) H per particle, rebuilt when a particle may have come within H, read by every pass (4 B a slot, ~1.6x the neighbours: 864 B a particle at support 3); 'cells': no stored list, each pass gathers the particles of the sorted cell grid around the particle's position at the last rebuild (the list build's query) and keeps those within H (docs/physics.md 'Neighbour search'); basic method only", default=FluidOptions.DEFAULT_NEIGHBOURS, choices=FluidOptions.NEIGHBOURS),
        method=Key("str", "'basic': WCSPH as above; 'ghost': Ghost SPH free surface (Schechter & Bridson 2012), ghost air particles seeded each step around the free surface ([fluid.ghost])", default="basic", choices=("basic", "ghost")),
        ghost=_sec(
            "Ghost SPH settings (used when method = 'ghost')",
            surface_threshold=Key("float", "free-surface particles have position divergence div x below this (interior: the dimension); "
                                  f"default {DEFAULT_THRESHOLD[2]:g} in 2D, {DEFAULT_THRESHOLD[3]:g} in 3D", default=GhostOptions.surface_threshold, min=0, max=3, min_open=True),
            sample_radius_ratio=Key("float", f"Poisson-disk radius r / spacing (default {DEFAULT_RADIUS_RATIO[2]:.2f} in 2D, {DEFAULT_RADIUS_RATIO[3]:.2f} in 3D: darts' flat-surface summation density ~ rho0, the tile's ~0.92 rho0)", default=GhostOptions.sample_radius_ratio, min=0.5, max=1.5),
            layer_ratio=Key("float", "ghost layer thickness / kernel support radius", default=GhostOptions.layer_ratio, min=0.25, max=2.0),
            sampler=Key("str", "'tile': the ghosts are the points of a periodic Poisson-disk tile (Bridson 2007, generated once) laid over the space, kept where they pass the liquid rules each step (one parallel pass); 'darts': Poisson-disk dart throwing in the background cells each step (3^dim dependent phases). Default: 'tile', 'darts' with persistent = true", default=GhostOptions.sampler, choices=("tile", "darts")),
            attempts=Key("int", "darts per background cell and round (Bridson's k; one bit each in a 32-bit mask on the parallel path)", default=GhostOptions.attempts, min=1, max=31),
            rounds=Key("int", "passes over the 3^dim independent phases of the background grid (each pass is 3^dim dependent launches on a GPU)", default=GhostOptions.rounds, min=1, max=10),
            pressure_term=Key("bool", "ghosts enter the pressure force through the liquid particle's own p_i/rho_i^2 term (true), or add no pressure force at all (false)", default=GhostOptions.pressure_term),
            density_cap=Key("bool", "summation density: ghosts fill a surface particle's kernel support up to rho0 and no further, rho_i = S_i + min(G_i, max(rho0 - S_i, 0)) (true); or add their full sum (false)", default=GhostOptions.density_cap),
            persistent=Key("bool", "keep last step's ghosts, moved with the mean motion of the liquid around them, and only fill the holes (true); or resample the whole layer each step (false). Needed with summation density (a resampled layer's density noise heats a resting drop)", default=GhostOptions.persistent),
        ),
        eos=_sec(
            "equation of state: give speed_of_sound_m_s, or the constant itself (b_pa for Tait, k_m2_s2 for linear)",
            type=Key("str", "'tait': p = B((rho/rho0)^gamma - 1); 'linear': p = k (rho - rho0)", default="tait", choices=("tait", "linear")),
            speed_of_sound_m_s=Key("float", "c0; sets B = c0^2 rho0/gamma (Tait) or k = c0^2 (linear). Rule: c0 >= 10 u_max", min=0, min_open=True),
            gamma=Key("float", "Tait exponent", default=7.0, min=1.0, max=10.0),
            b_pa=Key("float", "Tait stiffness B", min=0, min_open=True),
            k_m2_s2=Key("float", "linear stiffness k (Pa per kg/m^3)", min=0, min_open=True),
        ),
        viscosity=_sec(
            "viscosity models; any combination (all zero = inviscid)",
            laplacian_pa_s=Key("float", "dynamic viscosity mu of Mueller's Laplacian viscosity (water: 1e-3)", default=0.0, min=0.0),
            artificial_alpha=Key("float", "Monaghan artificial viscosity alpha (default: from fidelity)", min=0.0, max=10.0),
            xsph_epsilon=Key("float", "XSPH velocity smoothing epsilon (0.05 typical)", default=0.0, min=0.0, max=1.0),
        ),
        regions=_list("fluid blocks: a box (box_min_m, box_max_m) or a closed mesh filled on the particle lattice",
                      velocity_m_s=Key("vec", "initial velocity", length="dim"), **_REGION_KEYS),
    ),
    "tank": _sec(
        "container walls for the water, made of boundary particles (Akinci et al. 2012); a box or a closed mesh whose inside holds the water", optional=True,
        box_min_m=Key("vec", "inner lower corner of a box tank", length="dim"),
        box_max_m=Key("vec", "inner upper corner of a box tank", length="dim"),
        open_top=Key("bool", "no wall on the top face of a box tank", default=True),
        mesh=_REGION_KEYS["mesh"], mesh_scale=_REGION_KEYS["mesh_scale"], mesh_offset_m=_REGION_KEYS["mesh_offset_m"],
        boundary_spacing_ratio=Key("float", "boundary particle spacing / fluid spacing", default=1.0, min=0.25, max=2.0),
        layers=Key("int", "boundary particle layers (default: enough to cover the kernel support)", min=1, max=10),
        block_contact=Key("bool", "a box tank (and every box obstacle) is also solid to rock blocks: its floor, walls (and lid when the top is closed) become fixed DDA blocks outside the box, with a fixed block's default material, built when the scene has rigid or deformable blocks (docs/coupling.md 'Tanks and blocks'); a mesh tank or obstacle is not (a warning): build its walls of fixed blocks", default=True),
    ),
    "obstacles": _list("solid obstacles inside the tank, made of boundary particles (box or closed mesh)", **_REGION_KEYS),
    "blocks": _list(
        "rock blocks (explicit 3D DDA; 3D scenes only): convex polyhedra from a primitive or a mesh file; a non-convex closed mesh becomes one rigid block of convex parts (decomposition)",
        name=Key("str", "label (entries of an array or a multi-part mesh get _i suffixes)", default="block"),
        shape=Key("str", "'box' (size_m), 'prism' (convex hull of vertices_m, e.g. a wedge) or 'mesh' (mesh)", required=True, choices=("box", "prism", "mesh")),
        size_m=Key("vec", "box edge lengths", length=3),
        vertices_m=Key("points", "prism corner points (their convex hull is the block)", length=3),
        mesh=Key("path", "closed mesh file (STL, OBJ, PLY, GLB); every part of a multi-part file becomes a block; a non-convex part becomes one rigid compound block of convex parts (decomposition)"),
        mesh_scale=Key("float", "uniform scale for the mesh (0.001 for millimetres)", default=1.0, min=0, min_open=True),
        position_m=Key("vec", "centroid position (default: where the prism vertices or the mesh file put it)", length=3),
        orientation_deg=Key("vec", "rotation as successive turns about the fixed x, y, z axes", length=3, default=[0.0, 0.0, 0.0]),
        density_kg_m3=Key("float", "block density", default=BlockSpec.density, min=0, min_open=True),
        velocity_m_s=Key("vec", "initial velocity", length=3, default=[0.0, 0.0, 0.0]),
        angular_velocity_rad_s=Key("vec", "initial spin (world frame)", length=3, default=[0.0, 0.0, 0.0]),
        kind=Key("str", "'rigid' (6 DOF), 'deformable' (Shi's 12 DOF, constant strain), 'fixed' or 'kinematic' (prescribed motion)", default="rigid", choices=("rigid", "deformable", "fixed", "kinematic")),
        youngs_modulus_pa=Key("float", "Young's modulus E (deformable blocks; also sets the default contact stiffness); default " f"{DEFAULT_YOUNGS_MODULUS / 1e9:g} GPa", min=0, min_open=True),
        poisson_ratio=Key("float", "Poisson ratio", default=BlockSpec.poisson_ratio, min=0.0, max=0.49),
        strain_damping_ratio=Key("float", "damping ratio of a deformable block's strain modes", default=BlockSpec.strain_damping_ratio, min=0.0, max=2.0),
        motion=_sec("prescribed motion of a kinematic block: displacement added to position_m",
                    type=Key("str", "'sine': u = amplitude sin(2 pi f t + phase); 'table': linear in (times_s, displacements_m)", default="sine", choices=("sine", "table")),
                    amplitude_m=Key("vec", "sine amplitude vector", length=3),
                    frequency_hz=Key("float", "sine frequency", min=0.0),
                    phase_rad=Key("float", "sine phase", default=0.0),
                    times_s=Key("floatlist", "table times (strictly increasing)"),
                    displacements_m=Key("points", "table displacements, one [x, y, z] per time", length=3)),
        material=_sec("contact law of the block's surface (a pair uses the weaker of the two; damping the larger)",
                      friction_angle_deg=Key("float", "Coulomb friction angle phi", default=ContactMaterial.friction_angle_deg, min=0.0, max=89.0),
                      cohesion_pa=Key("float", "cohesion c (times each contact point's area share)", default=ContactMaterial.cohesion_pa, min=0.0),
                      tensile_strength_pa=Key("float", "tension allowed per unit area before the cut-off", default=ContactMaterial.tensile_strength_pa, min=0.0),
                      normal_stiffness_n_m=Key("float", f"k_n per contact point (default {PENALTY_FACTOR:g} E L, L = volume^(1/3))", min=0, min_open=True),
                      shear_stiffness_n_m=Key("float", "k_s per contact point (default k_n / (2 (1 + nu)))", min=0, min_open=True),
                      restitution=Key("float", f"normal restitution coefficient e (default {DEFAULT_RESTITUTION:g})", min=0.0, max=1.0),
                      damping_ratio=Key("float", "contact dashpot damping ratio (overrides restitution)", min=0.0, max=10.0)),
        decomposition=_sec("how a non-convex mesh is split into convex parts (CoACD, Wei et al. 2022), cached by mesh hash; the run prints the parts and the volume error",
                           max_parts=Key("int", "the most convex parts a mesh may become; more is an error (raise it or the concavity)", default=32, min=1, max=4096),
                           concavity=Key("float", "CoACD concavity threshold: the allowed distance between the parts' hulls and the mesh, relative to the mesh's bounding-box diagonal (smaller: more, tighter parts)", default=0.05, min=0.01, max=1.0),
                           cache_dir=Key("str", "decomposition cache folder, relative to the scene file ('': $ROCKWAVE_CACHE_DIR/decompositions or ~/.cache/rockwave/decompositions)", default="")),
        array=_sec("many blocks from one entry: a regular array of copies along the block's own (rotated) axes",
                   count=Key("vec", "copies along x, y, z (whole numbers)", length=3, default=[1.0, 1.0, 1.0]),
                   spacing_m=Key("vec", "centre-to-centre spacing along x, y, z", length=3, default=[0.0, 0.0, 0.0])),
    ),
    "coupling": _sec(
        "two-way penalty coupling of water and blocks, f = (K_s d - K_d v_rel.n) n (rockwave/coupling/penalty.py); used when a scene has both", optional=True,
        contact_distance_ratio=Key("float", "contact distance d0 / spacing: water stays this far from block faces (0.5: the particle's half cell, so the water touches the face)", default=CouplingOptions.contact_distance_ratio, min=0.0, max=2.0, min_open=True),
        stiffness_factor=Key("float", "K_s = factor m c0^2 / s^2 (the stiffness of the water itself at 1)", default=CouplingOptions.stiffness_factor, min=0.0, max=10.0, min_open=True),
        damping_ratio=Key("float", "K_d = 2 ratio sqrt(K_s m): damping ratio of the particle-wall spring", default=CouplingOptions.damping_ratio, min=0.0, max=2.0),
        stiffness_n_m=Key("float", "explicit K_s (N/m per particle; per metre of depth in 2D), overrides stiffness_factor", min=0, min_open=True),
        damping_n_s_m=Key("float", "explicit K_d (N s/m), overrides damping_ratio", min=0.0),
        squeeze_out=Key("bool", "water pinched between a moving block and an opposing solid face closer than 2 d0 + H is pushed out along the gap, so a block can settle onto another (rockwave/coupling/penalty.py)", default=CouplingOptions.squeeze_out),
        block_walls=Key("bool", "Adami wall particles on the moving (rigid, deformable, kinematic) blocks that start within reach of the water (its bounding box grown by its largest extent), so the water pushes them with its extrapolated pressure, wall acceleration included, and the penalty is only the guard against penetration (rockwave/coupling/walls.py BlockWalls); needs fluid.boundary = 'adami' and fluid.method = 'basic'; false: the penalty alone (a floating box then floats too deep: docs/coupling.md 'Wall particles on moving blocks')", default=CouplingOptions.block_walls),
        joint_water=Key("bool", "water pressure in the block contacts below the water: at each contact point of two blocks the hydrostatic pressure of the local free surface over it (rho0 g (z_s - z)), normal to the contact over its area share, equal and opposite on the two blocks, so friction acts on the effective normal force (Hoek & Bray's uplift of a joint open to the water; rockwave/coupling/joint_water.py); false: no water in a closed joint, a resting block carries its full weight in friction", default=CouplingOptions.joint_water),
    ),
    "hazard": _sec(
        "hazard summary reduced on the device during a run (rockwave/output/hazard.py), written to hazard.json and run.json", optional=True,
        sample_interval_s=Key("float", "simulated seconds between samples of the wave gauges, run-up lines and crossings (block speeds: every step); default 0.01 s, or the frame interval if shorter", min=0, min_open=True),
        gauges=_list("wave gauges: eta = water level (the height gauge's top of the continuous water column from the bed) - still level; reports the highest crest, the deepest trough, their times, and the first arrival time (|eta| first above arrival_threshold_m, interpolated between samples)",
                     name=Key("str", "gauge name (hazard.json key, study table column prefix)", required=True),
                     position_m=Key("vec", "gauge position (the vertical coordinate is not used)", length="dim", required=True),
                     still_level_m=Key("float", "still water level (default: the gauge's reading at the start of the run)"),
                     arrival_threshold_m=Key("float", "first arrival: the first time |eta| exceeds this (default half the particle spacing)", min=0, min_open=True)),
        runup=_list("run-up along a line across a shore: the highest top of a continuous water column from the bed (phi >= 0.5, as the height gauge: single spray particles and films thinner than about one particle layer read dry) on any of `columns` vertical lines from start_m to end_m, at any sample",
                    name=Key("str", "run-up line name", required=True),
                    start_m=Key("vec", "one end of the line (the vertical coordinate is not used)", length="dim", required=True),
                    end_m=Key("vec", "the other end", length="dim", required=True),
                    columns=Key("int", "vertical lines along it (default: one per particle spacing, at most 256)", min=2, max=1024),
                    still_level_m=Key("float", "still water level for the run-up above it (default: the highest reading along the line at the start)")),
        slides=_list("blocks whose initial and final centroid, runout (distance between them), peak speed and motion (time, centroid, velocity at every sample: hazard.json 'motion', slide_motion.csv) are reported",
                     block=Key("str", "block name (an array's blocks are name_0, name_1, ...)", required=True),
                     along=Key("vec", "a direction (any length), e.g. down the slope: the motion also gives the displacement s(t) = (c(t) - c(0)).u and the speed v(t).u along its unit vector u", length="dim")),
        crossings=_list("water volume moved across a vertical line (2D) or plane (3D): V - V0 of the water on the side the normal points to (2D: per metre of depth)",
                        name=Key("str", "crossing name", required=True),
                        position_m=Key("vec", "a point of the line or plane", length="dim", required=True),
                        normal=Key("vec", "horizontal direction towards the side counted", length="dim", required=True)),
    ),
    "output": _sec(
        "what a run writes into its output folder",
        usd=Key("str", "USD file of the frames ('.usdc' binary or '.usda' text); '' to skip", default="frames.usdc"),
        frame_rate_hz=Key("float", "frames written per simulated second", default=30.0, min=0, min_open=True, max=10000),
        chunk_frames=Key("int", "frames per USD clip file (a long run is a stage of value clips; the first clips hold 1, 2, 4, ... frames so the stage is readable from the first frame)", default=50, min=1),
        gauges_csv=Key("str", "CSV of gauge readings per frame (a file name in the output folder); '' to skip", default="gauges.csv"),
        blocks_csv=Key("str", "CSV of block position, velocity, spin and contact count per frame (a file name in the output folder); '' to skip", default="blocks.csv"),
        energy_csv=Key("str", "CSV of the energy budget per frame: kinetic, potential and elastic energy of water and rock, the penalty springs, the work of kinematic blocks, total and growth (docs/outputs.md 'The energy budget'); '' to skip (run.json keeps the summary)", default="energy.csv"),
        checkpoint_interval_s=Key("float", "wall-clock seconds between checkpoints (checkpoint.npz; 'run --resume' continues from it); 0: only on Ctrl-C or a blow-up", default=600.0, min=0.0),
        gauges=_list("probes read every frame",
                     name=Key("str", "column name in the CSV", required=True),
                     kind=Key("str", "'height': water level on position_m's vertical line, the top of the continuous water column from the bed: where the kernel-interpolated water fraction, going up from the first point where it reaches 0.5, drops below 0.5 (water overhead with air between, such as spray or a jet, does not count; NaN when dry; rockwave/sim/readers.py Gauges); 'pressure': SPH-interpolated (Shepard) pressure at position_m; 'force': the water's pressure force on a block along direction [N; 2D: N per metre of depth], the pressure integrated over the block's faces (rockwave/sim/readers.py ForceGauges; docs/outputs.md 'Force gauges')", required=True, choices=("height", "pressure", "force")),
                     position_m=Key("vec", "probe position, for 'height' and 'pressure' (for 'height' the vertical coordinate is ignored: the line runs from below the tank floor to one domain height above the top)", length="dim"),
                     block=Key("str", "for 'force': the block's name (an array's blocks are name_0, name_1, ...; a multi-part mesh block counts whole), or 'obstacle.<i>' for the box obstacle obstacles[i]"),
                     direction=Key("vec", "for 'force': the direction the force is read along (any length; e.g. [0, 1] for the vertical in 2D)", length="dim")),
        surface=_sec("fluid surface for rendering: a scalar field of the particles on a grid, isosurface by marching cubes (3D mesh /World/fluid_surface) or marching squares (2D contour curves)",
                     enabled=Key("bool", "write the surface into the USD stage (and the ParaView series)", default=True),
                     field=Key("str", "'colour': SPH colour field sum (m/rho) W (cubic spline); 'metaball': sum s^d/V_R (1 - (d/R)^2)^2 (Ghost SPH report)", default="colour", choices=("colour", "metaball")),
                     resolution_m=Key("float", "grid cell size (default: the particle spacing in 3D, half of it in 2D)", min=0, min_open=True),
                     radius_ratio=Key("float", "field support radius R / particle spacing", default=2.0, min=1.0, max=5.0),
                     iso_level=Key("float", "field value at the surface (the field is ~1 in bulk water; 0.5 puts the surface half a spacing past the last particle layer)", default=0.5, min=0, max=1.0, min_open=True),
                     max_grid_nodes=Key("int", "cap on grid nodes per frame; the cell grows to stay under it", default=20_000_000, min=1000)),
        vtk=Key("str", "folder for ParaView output (frame_NNNNN.vtu files: fluid with density, pressure, velocity; blocks as polyhedra; the surface) plus a .pvd series; '' to skip", default=""),
        reference=_list("measured or reference gauge series that 'python -m rockwave plot' overlays on the gauges of the same name",
                        file=Key("path", "text table, path relative to the scene file: first column time in s, then one column per gauge; a '#' header line names the columns ('H1 (m)' matches gauge 'H1')", required=True),
                        label=Key("str", "legend label (default: the file name)"),
                        time_offset_s=Key("float", "added to the reference times", default=0.0),
                        scale=Key("float", "multiplies the reference values", default=1.0)),
    ),
}

# [[rock_mass]]: a region cut into convex blocks by joint sets (rockwave/build/rockmass.py), placed after [[blocks]]
_ROCK_MASS = _list(
    "jointed rock mass (3D DDA blocks; rockwave/build/rockmass.py): a region (box, turned box, hull of points or closed mesh) cut "
    "into convex blocks by planar joint sets. 2D: a box in x-y (y up) extruded depth_m along z, joints dip toward +x or -x",
    name=Key("str", "label; the blocks are name_0, name_1, ...", default="rock"),
    region=_sec(
        "the rock volume: a box (box_min_m, box_max_m, optional orientation_deg), the convex hull of vertices_m, or a closed mesh",
        box_min_m=Key("vec", "lower corner of the box (before turning)", length="dim"),
        box_max_m=Key("vec", "upper corner of the box (before turning)", length="dim"),
        orientation_deg=Key("vec", "the box turned about its centre by successive turns about the fixed x, y, z axes (3D)", length=3, default=[0.0, 0.0, 0.0]),
        vertices_m=Key("points", "points whose convex hull is the region (3D)", length=3),
        mesh=Key("path", "closed mesh file (STL, OBJ, PLY, GLB), may be non-convex (a slope): every cell clipped by it must be one convex piece (a joint plane through each concave edge), else the region is refused (3D)"),
        mesh_scale=Key("float", "uniform scale applied to the mesh", default=1.0, min=0, min_open=True),
        mesh_offset_m=Key("vec", "translation applied to the mesh after scaling", length=3, default=[0.0, 0.0, 0.0]),
        depth_m=Key("float", "2D: extrusion depth along z of the blocks (centred on z = 0)", default=1.0, min=0, min_open=True),
    ),
    origin_m=Key("vec", "a point every set's plane 0 passes through before offset_m (default: the region's first corner: box_min_m turned, else the lower corner of its bounds)", length="dim"),
    seed=Key("int", "seed of the random plane offsets and spacing jitter (the same seed gives the same blocks)", default=0, min=0),
    min_block_size_m=Key("float", "blocks whose largest inscribed sphere is narrower than this (small blocks, thin plates, needles) merge into one or two face neighbours whose union with them is convex; 0: no merging", default=0.0, min=0.0),
    density_kg_m3=Key("float", "rock density", default=BlockSpec.density, min=0, min_open=True),
    kind=Key("str", "'rigid' or 'deformable' (Shi's constant strain)", default="rigid", choices=("rigid", "deformable")),
    youngs_modulus_pa=Key("float", "Young's modulus E (sets the default contact stiffness); default " f"{DEFAULT_YOUNGS_MODULUS / 1e9:g} GPa", min=0, min_open=True),
    poisson_ratio=Key("float", "Poisson ratio", default=BlockSpec.poisson_ratio, min=0.0, max=0.49),
    material=_sec(
        "intact rock: the strength of the rock bridges of non-persistent joints and the contact law of a block with no joint face; stiffness and damping of every block",
        **{k: v for k, v in SCHEMA["blocks"].children["material"].children.items()}),
    joint_sets=_list(
        "planar joint sets: plane k of a set is n.(x - origin_m) = offset_m + k spacing_m, n the plane's upward normal "
        "(sin dip sin dipdir, sin dip cos dipdir, cos dip) with x east, y north, z up (2D: (sin dip sin dipdir, cos dip), y up)",
        name=Key("str", "label for messages", default=""),
        dip_deg=Key("float", "dip: angle of the plane below the horizontal", required=True, min=0.0, max=90.0),
        dip_direction_deg=Key("float", "dip direction: azimuth of the dip, clockwise from north (+y); 2D: 90 (dips toward +x) or 270", required=True, min=0.0, max=360.0),
        spacing_m=Key("float", "normal distance between planes", required=True, min=0, min_open=True),
        offset_m=Key("float", "shift of the planes along n from origin_m", default=0.0),
        random_offset=Key("bool", "shift the planes by a uniform random fraction of the spacing instead (from seed)", default=False),
        spacing_jitter=Key("float", "each spacing is uniform in spacing_m (1 +- jitter) (from seed)", default=0.0, min=0.0, max=0.9),
        persistence=Key("float", "fraction of the plane's area that is open joint; the rest is intact rock bridges, smeared as Jennings' (1970) equivalent strength c = p c_j + (1 - p) c_r (also tan phi and tension); < 1 needs material.cohesion_pa", default=1.0, min=0.0, max=1.0, min_open=True),
        friction_angle_deg=Key("float", "friction angle of the open joint", default=30.0, min=0.0, max=89.0),
        cohesion_pa=Key("float", "cohesion of the open joint", default=0.0, min=0.0),
        tensile_strength_pa=Key("float", "tensile strength of the open joint", default=0.0, min=0.0),
    ),
)
SCHEMA = {k: v for k, v in list(SCHEMA.items())[:list(SCHEMA).index("blocks") + 1]} | {"rock_mass": _ROCK_MASS} | {
    k: v for k, v in list(SCHEMA.items())[list(SCHEMA).index("blocks") + 1:]}
_EOS_KEYS = SCHEMA["fluid"].children["eos"].children


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------


class Node(dict):
    """A validated section: a dict whose keys also read as attributes (``scene.fluid.eos.type``)."""

    def __getattr__(self, name: str):
        try:
            return self[name]
        except KeyError as e:
            raise AttributeError(name) from e


def _type_name(v: Any) -> str:
    return {bool: "boolean", int: "integer", float: "number", str: "string", list: "array", dict: "table"}.get(type(v), type(v).__name__)


class _Validator:
    def __init__(self, base_dir: Path, dim: int):
        self.errors: list[tuple[str, str]] = []
        self.base_dir = base_dir
        self.dim = dim

    def err(self, key: str, msg: str) -> None:
        self.errors.append((key, msg))

    def section(self, data: Any, spec: dict[str, Key], prefix: str) -> Node:
        out = Node()
        if not isinstance(data, dict):
            self.err(prefix, f"expected a table, got {_type_name(data)}")
            data = {}
        for k in data:
            if k not in spec:
                near = [s for s in spec if s.split("_")[0] == str(k).split("_")[0]]
                hint = f"; did you mean {near[0]!r}?" if near else ""
                self.err(f"{prefix}.{k}" if prefix else k, f"unknown key; allowed: {', '.join(spec)}{hint}")
        for name, key in spec.items():
            path = f"{prefix}.{name}" if prefix else name
            if key.type == "section":
                if key.optional and name not in data:
                    out[name] = None
                else:
                    out[name] = self.section(data.get(name, {}), key.children, path)
            elif key.type == "table_list":
                items = data.get(name, [])
                if not isinstance(items, list) or any(not isinstance(i, dict) for i in items):
                    self.err(path, f"expected an array of tables ([[{path}]]), got {_type_name(items)}")
                    items = []
                out[name] = [self.section(item, key.children, f"{path}[{i}]") for i, item in enumerate(items)]
            elif name in data:
                out[name] = self.value(data[name], key, path)
            else:
                if key.required:
                    self.err(path, f"required key is missing ({key.doc})")
                out[name] = key.default
        return out

    def value(self, v: Any, key: Key, path: str) -> Any:
        t = key.type
        if t in ("points", "floatlist"):
            rows = v if t == "points" else [[c] for c in v] if isinstance(v, list) else v
            n = key.length if t == "points" else 1
            ok = isinstance(v, list) and len(v) > 0 and all(
                isinstance(r, list) and len(r) == n and all(not isinstance(c, bool) and isinstance(c, (int, float)) and math.isfinite(c) for c in r)
                for r in rows)
            if not ok:
                what = "a list of [x, y, z] points" if t == "points" else "a non-empty list of numbers"
                return self._bad(path, f"expected {what}, got {v!r}")
            return [[float(c) for c in r] for r in v] if t == "points" else [float(c) for c in v]
        if t == "bool":
            if not isinstance(v, bool):
                return self._bad(path, f"expected true or false, got {_type_name(v)} {v!r}")
        elif t == "int":
            if isinstance(v, bool) or not isinstance(v, int):
                return self._bad(path, f"expected an integer, got {_type_name(v)} {v!r}")
        elif t == "float":
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                return self._bad(path, f"expected a number, got {_type_name(v)} {v!r}")
            v = float(v)
            if not math.isfinite(v):
                return self._bad(path, f"expected a finite number, got {v!r}")
        elif t in ("str", "path"):
            if not isinstance(v, str):
                return self._bad(path, f"expected a string, got {_type_name(v)} {v!r}")
        elif t == "vec":
            n = self.dim if key.length == "dim" else key.length
            if not isinstance(v, list) or any(isinstance(c, bool) or not isinstance(c, (int, float)) for c in v):
                return self._bad(path, f"expected a list of {n} numbers, got {v!r}")
            if len(v) != n:
                what = f" (the scene is {self.dim}D)" if key.length == "dim" else ""
                if key.length == 3 and self.dim == 2 and len(v) == 2 and path.startswith(("blocks", "rock_mass")):
                    return self._bad(path, "expected 3 numbers, got 2: blocks are 3D in a 2D scene too (a 2D block is a prism "
                                           "with a depth along z, moving in the x-y plane); give x, y and z, e.g. size_m = "
                                           "[w, h, depth], position_m = [x, y, 0]")
                return self._bad(path, f"expected {n} numbers{what}, got {len(v)}")
            if not all(math.isfinite(c) for c in v):
                return self._bad(path, f"expected finite numbers, got {v!r}")
            return [float(c) for c in v]
        if key.choices is not None and v not in key.choices:
            return self._bad(path, f"{v!r} is not allowed; {key.allowed()}")
        if t in ("int", "float"):
            lo_bad = key.min is not None and (v <= key.min if key.min_open else v < key.min)
            hi_bad = key.max is not None and v > key.max
            if lo_bad or hi_bad:
                return self._bad(path, f"{v!r} is out of range; allowed: {key.allowed()}")
        if t == "path":
            try:
                p = (self.base_dir / v).resolve()
                p.stat()
            except (RuntimeError, OSError) as e:  # a symlink loop (RuntimeError before Python 3.13), a path too long
                if isinstance(e, FileNotFoundError):
                    return self._bad(path, f"file not found: {self.base_dir / v}")
                why = "a symbolic link loop" if isinstance(e, RuntimeError) or getattr(e, "errno", None) == 40 else \
                    (getattr(e, "strerror", None) or str(e))
                return self._bad(path, f"{v!r} cannot be read: {why} ({self.base_dir / v})")
            if not p.is_file():
                return self._bad(path, f"file not found: {p}")
            return str(p)
        return v

    def _bad(self, path: str, msg: str) -> None:
        self.err(path, msg)
        return None


@dataclass
class Scene:
    """A validated scene. Sections are :class:`Node` dicts with attribute access."""

    path: str
    simulation: Node
    gravity: Node
    fluid: Node | None
    tank: Node | None
    obstacles: list
    output: Node
    blocks: list = field(default_factory=list)
    rock_mass: list = field(default_factory=list)  # [[rock_mass]] (rockwave/build/rockmass.py)
    raw: dict = field(repr=False, default_factory=dict)
    coupling: Node | None = None  # [coupling] (rockwave/coupling/penalty.py); None: defaults
    hazard: Node | None = None  # [hazard] (rockwave/output/hazard.py); None: no hazard summary

    @property
    def dim(self) -> int:
        return int(self.simulation.dimension)

    @property
    def name(self) -> str:
        return Path(self.path).stem


def _cross_checks(v: _Validator, s: Node) -> None:
    """Checks that involve several keys."""
    dim = v.dim
    sim, fl = s["simulation"], s["fluid"]
    if sim["time_step"] == "fixed" and sim["dt_s"] is None:
        v.err("simulation.dt_s", "required when simulation.time_step = 'fixed'")
    _check_run_settings(v, s)
    _check_outputs(v, s)
    _check_blocks(v, s)
    _check_rock_mass(v, s)
    if fl is None:
        if not s["blocks"] and not s["rock_mass"]:
            v.err("fluid", "the scene has neither water ([fluid] with [[fluid.regions]]) nor [[blocks]]")
        if s["tank"] is not None or s["obstacles"]:
            v.err("tank", "a tank or obstacles need water: add a [fluid] section or remove them")
        _check_gauges(v, s)  # (gauges read the water)
        return
    apply_fidelity(v, fl, s["tank"])
    if fl.get("method") == "ghost" and "cfl_number" not in (getattr(v, "raw_simulation", {}) or {}):

        sim["cfl_number"] = GHOST_CFL_MAX  # the ghosts' one-sided pressure term wants the smaller step (rockwave/sph/ghost.py)
    gh = fl.get("ghost") or {}
    if gh.get("sampler") == "tile" and gh.get("persistent"):
        v.err("fluid.ghost.sampler", "the tile sampler does not keep ghosts: persistent = true needs sampler = 'darts'")
    _check_method_options(v, fl)
    cp = s["coupling"] or {}
    if cp.get("block_walls"):
        if fl.get("boundary") != "adami":
            v.err("coupling.block_walls", "wall particles on moving blocks are Adami walls: they need fluid.boundary = "
                                          f"'adami' (it is {fl.get('boundary')!r}); remove the key or change the boundary")
        if fl.get("method") != "basic":
            v.err("coupling.block_walls", "wall particles on moving blocks need fluid.method = 'basic' (Ghost SPH keeps "
                                          "its own copies of the boundary); remove the key or set it false")
    if s["tank"] is None and not any(b["kind"] in ("fixed", "kinematic") for b in s["blocks"]):
        v.err("tank", "the water has no walls: add a [tank] (box_min_m/box_max_m or mesh) or fixed [[blocks]] around it")
    eos = fl["eos"]
    const_key = "b_pa" if eos["type"] == "tait" else "k_m2_s2"
    other_key = "k_m2_s2" if eos["type"] == "tait" else "b_pa"
    if eos[other_key] is not None:
        v.err(f"fluid.eos.{other_key}", f"does not apply to eos.type = {eos['type']!r} (use {const_key})")
    if (eos["speed_of_sound_m_s"] is None) == (eos[const_key] is None):
        v.err("fluid.eos", f"give exactly one of speed_of_sound_m_s or {const_key}")
    else:
        _check_eos_constant(v, fl)

    def check_region(r: Node, path: str, need: bool = True) -> None:
        has_box = r.get("box_min_m") is not None or r.get("box_max_m") is not None
        has_mesh = r.get("mesh") is not None
        if has_box and has_mesh:
            v.err(path, "give either box_min_m/box_max_m or mesh, not both")
        elif has_box:
            lo, hi = r.get("box_min_m"), r.get("box_max_m")
            if lo is None or hi is None:
                v.err(path, "a box needs both box_min_m and box_max_m")
            elif any(b <= a for a, b in zip(lo, hi)):
                v.err(f"{path}.box_max_m", f"must exceed box_min_m in every coordinate (box_min_m = {lo}, box_max_m = {hi})")
        elif has_mesh:
            if dim == 2:
                v.err(f"{path}.mesh", "meshes are 3D only; use a box in a 2D scene")
        elif need and "mesh" not in [e[0].rsplit(".", 1)[-1] for e in v.errors if e[0].startswith(path)]:
            v.err(path, "needs a box (box_min_m, box_max_m) or a mesh")

    if not fl["regions"]:
        v.err("fluid.regions", "at least one [[fluid.regions]] entry is needed")
    for i, r in enumerate(fl["regions"]):
        check_region(r, f"fluid.regions[{i}]")
    if s["tank"] is not None:
        check_region(s["tank"], "tank")
    for i, r in enumerate(s["obstacles"]):
        check_region(r, f"obstacles[{i}]")
    # fluid boxes must lie inside a box tank
    t = s["tank"] or {}
    if t.get("box_min_m") and t.get("box_max_m"):
        for i, r in enumerate(fl["regions"]):
            if r.get("box_min_m") and r.get("box_max_m"):
                if any(a < b - 1e-9 for a, b in zip(r["box_min_m"], t["box_min_m"])) or any(
                    a > b + 1e-9 for a, b in zip(r["box_max_m"], t["box_max_m"])
                ):
                    v.err(f"fluid.regions[{i}]", f"box {r['box_min_m']}..{r['box_max_m']} is not inside the tank {t['box_min_m']}..{t['box_max_m']}")
                else:
                    n = 1.0
                    for a, b in zip(r["box_min_m"], r["box_max_m"]):
                        n *= (b - a) / fl["spacing_m"] if fl["spacing_m"] else 0
                    if n < 1:
                        v.err(f"fluid.regions[{i}]", f"box holds no particle at spacing {fl['spacing_m']} m")
    _check_region_overlaps(v, fl["regions"], fl["spacing_m"])
    _check_gauges(v, s)
    usd = s["output"]["usd"]
    if usd and not (usd.endswith(".usdc") or usd.endswith(".usda") or usd.endswith(".usd")):
        v.err("output.usd", f"{usd!r}: expected a name ending in .usdc, .usda or .usd")


def _check_blocks(v: _Validator, s: Node) -> None:
    blocks = s["blocks"]
    if blocks and v.dim == 2:
        # 2D: blocks are 3D prisms extruded along z (their z-extent is their depth) moving in the x-y plane
        for i, b in enumerate(blocks):
            if any(abs(a) > 0 for a in (b["orientation_deg"] or [0, 0, 0])[:2]):
                v.err(f"blocks[{i}].orientation_deg", "in a 2D scene a block turns about z only (x and y angles 0)")
            if b["velocity_m_s"] and b["velocity_m_s"][2] != 0 or b["angular_velocity_rad_s"] and any(b["angular_velocity_rad_s"][:2]):
                v.err(f"blocks[{i}]", "in a 2D scene a block moves in the x-y plane (velocity z and spin x, y must be 0)")
    for i, b in enumerate(blocks):
        path = f"blocks[{i}]"
        need = {"box": "size_m", "prism": "vertices_m", "mesh": "mesh"}.get(b["shape"])
        if need and b.get(need) is None and not any(e[0] == f"{path}.{need}" for e in v.errors):
            v.err(f"{path}.{need}", f"required for shape = {b['shape']!r}")
        for other in ("size_m", "vertices_m", "mesh"):
            if other != need and b.get(other) is not None:
                v.err(f"{path}.{other}", f"does not apply to shape = {b['shape']!r}")
        if b["shape"] == "box" and b["position_m"] is None and not any(e[0] == f"{path}.position_m" for e in v.errors):
            v.err(f"{path}.position_m", "required for a box")
        if b["shape"] == "prism" and b.get("vertices_m") and len(b["vertices_m"]) < 4:
            v.err(f"{path}.vertices_m", "a prism needs at least 4 points spanning a volume")
        m = b["motion"]
        if b["kind"] == "kinematic":
            if m["type"] == "sine" and (m["amplitude_m"] is None or m["frequency_hz"] is None):
                v.err(f"{path}.motion", "a sine motion needs amplitude_m and frequency_hz")
            if m["type"] == "table":
                if m["times_s"] is None or m["displacements_m"] is None:
                    v.err(f"{path}.motion", "a table motion needs times_s and displacements_m")
                elif len(m["times_s"]) != len(m["displacements_m"]):
                    v.err(f"{path}.motion.displacements_m", f"{len(m['displacements_m'])} rows for {len(m['times_s'])} times")
                elif any(t1 <= t0 for t0, t1 in zip(m["times_s"], m["times_s"][1:])):
                    v.err(f"{path}.motion.times_s", "must be strictly increasing")
        elif any(m[k] is not None for k in ("amplitude_m", "frequency_hz", "times_s", "displacements_m")):
            v.err(f"{path}.motion", f"only kinematic blocks take a motion (kind = {b['kind']!r})")
        cnt = b["array"]["count"]
        if cnt is not None and any(c < 1 or c != int(c) for c in cnt):
            v.err(f"{path}.array.count", f"expected whole numbers >= 1, got {cnt}")
        if b["shape"] == "box" and b.get("size_m") is not None and any(c <= 0 for c in b["size_m"]):
            v.err(f"{path}.size_m", f"box edge lengths must be > 0, got {b['size_m']}")
    given: dict[str, int] = {}
    for i, b in enumerate(blocks):
        raw = v.raw_blocks[i] if i < len(v.raw_blocks) else {}
        name = b.get("name")
        if isinstance(raw, dict) and "name" in raw and isinstance(name, str):
            if not name.strip() or any(ord(c) < 32 for c in name):
                v.err(f"blocks[{i}].name", f"{name!r}: a block name must be non-empty and on one line")
            elif name in given:
                v.err(f"blocks[{i}].name", f"{name!r} is already the name of blocks[{given[name]}]; block names must be unique "
                                           f"(the blocks of one entry's array or mesh get _0, _1, ... suffixes)")
            else:
                given[name] = i


def _check_rock_mass(v: _Validator, s: Node) -> None:
    """A [[rock_mass]] entry: one region form, joint sets, what 2D allows (the cut itself: rockwave/build/rockmass.py)."""
    for i, r in enumerate(s["rock_mass"]):
        path = f"rock_mass[{i}]"
        reg = r["region"]
        forms = [f for f, k in (("box", "box_min_m"), ("vertices_m", "vertices_m"), ("mesh", "mesh")) if reg.get(k) is not None
                 or (f == "box" and reg.get("box_max_m") is not None)]
        bad_key = any(e[0].startswith(f"{path}.region.") for e in v.errors)
        if len(forms) != 1 and not bad_key:
            v.err(f"{path}.region", f"give exactly one of a box (box_min_m, box_max_m), vertices_m or mesh; got {forms or 'none'}")
        elif forms == ["box"]:
            lo, hi = reg.get("box_min_m"), reg.get("box_max_m")
            if lo is None or hi is None:
                v.err(f"{path}.region", "a box needs both box_min_m and box_max_m")
            elif any(b <= a for a, b in zip(lo, hi)):
                v.err(f"{path}.region.box_max_m", f"{hi} must exceed box_min_m {lo} in every coordinate")
        if v.dim == 2:
            for k in ("vertices_m", "mesh"):
                if reg.get(k) is not None:
                    v.err(f"{path}.region.{k}", "3D only; a 2D rock mass is a box")
            if any(reg.get("orientation_deg") or []):
                v.err(f"{path}.region.orientation_deg", "3D only")
        if not r["joint_sets"] and not any(e[0].startswith(f"{path}.joint_sets") for e in v.errors):
            v.err(f"{path}.joint_sets", "at least one [[rock_mass.joint_sets]] entry is needed")
        raw = v.raw_rock_mass[i] if i < len(v.raw_rock_mass) and isinstance(v.raw_rock_mass[i], dict) else {}
        raw_mat = raw.get("material") if isinstance(raw.get("material"), dict) else {}
        for j, js in enumerate(r["joint_sets"]):
            p = js.get("persistence")
            if p is not None and p < 1 and "cohesion_pa" not in raw_mat:
                v.err(f"{path}.joint_sets[{j}].persistence", f"= {p:g} leaves rock bridges whose strength is the intact rock's: "
                                                             f"give {path}.material.cohesion_pa (and tensile_strength_pa)")
            if js.get("random_offset") and isinstance(raw.get("joint_sets"), list) and j < len(raw["joint_sets"]) \
                    and isinstance(raw["joint_sets"][j], dict) and "offset_m" in raw["joint_sets"][j]:
                v.err(f"{path}.joint_sets[{j}].offset_m", "random_offset = true draws the offset: give one of them")


def apply_fidelity(v: _Validator, fl: Node, tank: Node | None) -> None:
    """Fill the formulation keys the scene leaves out from fluid.fidelity (FIDELITY), then check what the chosen
    formulation cannot do: Adami walls need boundary layers as thick as the kernel support."""
    level = FIDELITY.get(fl.get("fidelity")) or FIDELITY["standard"]
    for k in ("kernel", "support_radius_ratio", "boundary", "density_floor", "gradient_correction", "particle_shifting",
              "density_diffusion_form", "density_diffusion_renormalised"):
        if fl.get(k) is None:
            fl[k] = level[k]
            # a level's density floor and gradient correction are for basic WCSPH with continuity density and
            # clipped pressure: where the scene chose otherwise the level gives them off (set by hand they are errors,
            # _check_method_options)
            if k == "density_floor" and (fl.get("method") == "ghost" or fl.get("density") == "summation"
                                         or not fl.get("clamp_negative_pressure")):
                fl[k] = False
            if k == "gradient_correction" and fl.get("method") == "ghost":
                fl[k] = False
            if k == "particle_shifting" and fl.get("method") == "ghost":
                fl[k] = 0.0
    # the start packed at its hydrostatic density and walls that keep their volume (every level but draft): for
    # continuity density and Adami walls only, so where the scene chose otherwise the level gives them off
    if fl.get("packed_start") is None:
        fl["packed_start"] = level["packed_start"] and fl.get("density") != "summation" and fl.get("method") != "ghost"
    if fl.get("wall_volume") is None:
        fl["wall_volume"] = level["wall_volume"] if fl["boundary"] == "adami" else "mass"
    if fl.get("density_diffusion") is None:
        fl["density_diffusion"] = level["density_diffusion"] if fl.get("density") == "continuity" and \
            fl.get("method") != "ghost" else 0.0
    visc = fl.get("viscosity")
    if isinstance(visc, dict) and visc.get("artificial_alpha") is None:
        visc["artificial_alpha"] = level["artificial_alpha"]
    raw = getattr(v, "raw_fluid", {}) or {}
    origin = "fluid.boundary" if "boundary" in raw else f"fluid.fidelity = {fl.get('fidelity')!r}"
    if fl["boundary"] == "adami" and tank is not None and tank.get("layers") is not None:
        ratio = fl.get("support_radius_ratio")
        bratio = tank.get("boundary_spacing_ratio") or 1.0
        # in units of the spacing: layers of bratio against the support of ratio (rockwave/sph/fluid.py)
        if isinstance(ratio, (int, float)) and not walls_cover_support(tank["layers"], bratio, support_radius(1.0, ratio)):
            v.err("tank.layers", f"= {tank['layers']} layers of {bratio:g} spacing are thinner than the kernel support "
                                 f"({ratio:g} spacings); Adami walls ({origin}) need the support covered: remove tank.layers "
                                 "(the default covers it) or set fluid.boundary = 'akinci'")
    if fl.get("packed_start") and fl.get("density") == "summation":
        v.err("fluid.packed_start", "needs fluid.density = 'continuity' (summation density is set by the packing itself)")
    if fl["boundary"] == "akinci" and fl.get("wall_volume") == "geometric":
        v.err("fluid.wall_volume", "'geometric' needs fluid.boundary = 'adami' (Akinci walls carry no pressure of their own)")
    if fl["boundary"] == "akinci" and fl.get("wall_slip") == "no_slip":
        v.err("fluid.wall_slip", "'no_slip' needs fluid.boundary = 'adami' (Akinci walls exert no viscous force)")


# [fluid.ghost] keys that only the dart sampler reads
DART_ONLY_KEYS = ("attempts", "rounds")


def _check_method_options(v: _Validator, fl: Node) -> None:
    """An option that the chosen method cannot honour is an error naming the key, never ignored."""
    raw = getattr(v, "raw_fluid", {}) or {}
    if fl.get("density_floor"):
        why = [w for w, bad in (("fluid.method = 'ghost'", fl.get("method") == "ghost"),
                                ("fluid.density = 'summation'", fl.get("density") == "summation"),
                                ("fluid.clamp_negative_pressure = false", not fl.get("clamp_negative_pressure")))
               if bad]
        if why:
            v.err("fluid.density_floor", f"= true needs basic WCSPH with continuity density and clipped negative pressure, "
                                         f"but the scene has {', '.join(why)} (remove the key or change those)")
    if (fl.get("particle_shifting") or 0.0) > 0.0 and fl.get("method") == "ghost":
        v.err("fluid.particle_shifting", "> 0 needs fluid.method = 'basic': the ghosts stand where a shifted surface "
                                         "particle would move (remove the key or the ghost method)")
    if fl.get("gradient_correction") and fl.get("method") == "ghost":
        v.err("fluid.gradient_correction", "= true needs fluid.method = 'basic': the Ghost SPH passes use the plain "
                                           "kernel gradient (remove the key or the ghost method)")
    if fl.get("neighbours") == "cells" and fl.get("wall_work"):
        v.err("fluid.wall_work", "= true needs fluid.neighbours = 'lists': the wall work pass reads the neighbour list "
                                 "(remove one of the two)")
    if fl.get("neighbours") == "cells" and raw.get("density_diffusion_renormalised"):
        v.err("fluid.density_diffusion_renormalised", "= true needs fluid.neighbours = 'lists': the renormalised "
                                                      "gradient pass reads the neighbour list (remove one of the two)")
    if fl.get("neighbours") == "cells" and fl.get("method") == "ghost":
        v.err("fluid.neighbours", "= 'cells' needs fluid.method = 'basic': the Ghost SPH passes read the neighbour lists "
                                  "(remove the key or the ghost method)")
    raw_ghost = raw.get("ghost") if isinstance(raw.get("ghost"), dict) else {}
    if fl.get("method") != "ghost" and raw_ghost:
        v.err("fluid.ghost", f"sets {sorted(raw_ghost)} but fluid.method = {fl.get('method')!r}: the ghost settings apply "
                             "only with method = 'ghost' (set it, or remove the section)")
    elif raw_ghost:
        sampler = raw_ghost.get("sampler") or ("darts" if raw_ghost.get("persistent") else "tile")
        if sampler == "tile":
            for k in DART_ONLY_KEYS:
                if k in raw_ghost:
                    v.err(f"fluid.ghost.{k}", "applies to the dart sampler only; the tile sampler (the default without "
                                              "persistent = true) places the tile's points: remove it or set sampler = 'darts'")
        if raw_ghost.get("density_cap") and fl.get("density") != "summation":
            v.err("fluid.ghost.density_cap", "caps the summation density; with fluid.density = 'continuity' the ghosts do "
                                             "not enter the density: remove it or set fluid.density = 'summation'")
    dd = fl.get("density_diffusion")
    if isinstance(dd, (int, float)) and dd > 0 and fl.get("density") == "summation":
        v.err("fluid.density_diffusion", "diffuses the continuity density; with fluid.density = 'summation' the density "
                                         "is recomputed each step: remove it or set fluid.density = 'continuity'")
    if raw.get("density_diffusion_renormalised") and not (isinstance(dd, (int, float)) and dd > 0):
        v.err("fluid.density_diffusion_renormalised", "changes the density diffusion's term, and there is no diffusion "
                                                      "(fluid.density_diffusion is 0 here): set fluid.density_diffusion > 0 "
                                                      "or remove it")


# the largest EOS constant (B or k, Pa) the float32 pressure arithmetic takes with room to spare
MAX_EOS_CONSTANT_PA = 1.0e30
OUTPUT_RESERVED = ("run.json", "checkpoint.npz")


def _check_run_settings(v: _Validator, s: Node) -> None:
    """The device name and the direction of gravity."""

    dev = s["simulation"].get("device")
    if dev is not None:
        why = device_syntax_error(dev)
        if why:
            v.err("simulation.device", why)
    g = s["gravity"].get("acceleration_m_s2")
    up = v.dim - 1
    if g is not None and len(g) == v.dim and g[up] > 0:
        axis = "z" if v.dim == 3 else "y"
        down = [0.0] * v.dim
        down[up] = -g[up]
        v.err("gravity.acceleration_m_s2", f"{g} points up (+{axis} is up in a {v.dim}D scene): the water and the blocks "
                                           f"would fall out of the top; gravity pulls down, e.g. {down}")


def _check_eos_constant(v: _Validator, fl: Node) -> None:
    """B = c0^2 rho0 / gamma (Tait) or k = c0^2 (linear) must stay finite in float32."""
    eos, rho0 = fl["eos"], fl["rest_density_kg_m3"]
    c0 = eos["speed_of_sound_m_s"]
    if c0 is None or rho0 is None:
        const = eos["b_pa"] if eos["type"] == "tait" else eos["k_m2_s2"]
        key = "b_pa" if eos["type"] == "tait" else "k_m2_s2"
    else:
        key = "speed_of_sound_m_s"
        try:
            const = c0 * c0 * (rho0 / (eos["gamma"] or _EOS_KEYS["gamma"].default) if eos["type"] == "tait" else 1.0)
        except OverflowError:
            const = math.inf
    if const is not None and not const < MAX_EOS_CONSTANT_PA:
        v.err(f"fluid.eos.{key}", f"gives an EOS stiffness of {const:.3g} (above {MAX_EOS_CONSTANT_PA:g}, out of float32 range); "
                                  f"water needs c0 of about 10 x the fastest flow speed (a few to a few hundred m/s)")


def _check_outputs(v: _Validator, s: Node) -> None:
    """Output names are plain file names in the output folder, distinct from each other."""
    out = s["output"]
    seen: dict[str, str] = {}
    for key in ("usd", "gauges_csv", "blocks_csv", "energy_csv", "vtk"):
        name = out.get(key)
        if not isinstance(name, str) or name == "":
            continue
        path = f"output.{key}"
        if "/" in name or "\\" in name or name in (".", "..") or any(ord(c) < 32 for c in name) or name.strip() != name:
            v.err(path, f"{name!r}: expected a plain file name (written into the output folder), or '' to skip")
        elif name in OUTPUT_RESERVED:
            v.err(path, f"{name!r} is the name of the run's own {name} file; choose another name")
        elif name in seen:
            v.err(path, f"{name!r} is also output.{seen[name]}: two outputs cannot share one file")
        else:
            seen[name] = key


def _box_of(r) -> tuple | None:
    lo, hi = r.get("box_min_m"), r.get("box_max_m")
    if lo is None or hi is None or r.get("mesh") is not None or len(lo) != len(hi) or any(b <= a for a, b in zip(lo, hi)):
        return None
    return lo, hi


def _check_region_overlaps(v: _Validator, regions: list, spacing) -> None:
    """Two fluid boxes that share volume would seed the shared part twice (twice the density)."""
    boxes = [(i, _box_of(r)) for i, r in enumerate(regions)]
    boxes = [(i, b) for i, b in boxes if b is not None]
    tol = 1e-9 if not spacing else 1e-6 * spacing
    for a in range(len(boxes)):
        for b in range(a + 1, len(boxes)):
            (i, (lo1, hi1)), (j, (lo2, hi2)) = boxes[a], boxes[b]
            lo = [max(x, y) for x, y in zip(lo1, lo2)]
            hi = [min(x, y) for x, y in zip(hi1, hi2)]
            if all(h - l > tol for l, h in zip(lo, hi)):
                v.err(f"fluid.regions[{j}]", f"overlaps fluid.regions[{i}] in the box {lo}..{hi}: the water there would be "
                                             f"seeded twice (twice the density); make the boxes touch instead of overlap")


def _check_gauges(v: _Validator, s: Node) -> None:
    """Gauge names (unique, one line, not the time column) and positions (inside a box tank)."""
    gauges = s["output"]["gauges"]
    seen: dict[str, int] = {}
    for i, g in enumerate(gauges):
        n = g.get("name")
        if not isinstance(n, str):
            continue
        if not n.strip() or any(ord(c) < 32 for c in n) or n != n.strip():
            v.err(f"output.gauges[{i}].name", f"{n!r}: a gauge name is a CSV column header: non-empty, on one line, "
                                              f"without leading or trailing spaces")
        elif n == "time_s":
            v.err(f"output.gauges[{i}].name", "'time_s' is the CSV's time column; choose another name")
        elif n in seen:
            v.err("output.gauges", f"gauge name {n!r} is used more than once (output.gauges[{seen[n]}] and [{i}])")
        else:
            seen[n] = i
    names = [b.get("name") for b in (s.get("blocks") or []) + (s.get("rock_mass") or [])]
    for i, g in enumerate(gauges):
        kind = g.get("kind")
        if kind in ("height", "pressure") and g.get("position_m") is None:
            v.err(f"output.gauges[{i}].position_m", f"a '{kind}' gauge needs a position")
        if kind != "force":
            for key in ("block", "direction"):
                if g.get(key) is not None:
                    v.err(f"output.gauges[{i}].{key}", f"only a 'force' gauge has a {key} (this one is '{kind}')")
            continue
        bn, d = g.get("block"), g.get("direction")
        if bn is None:
            v.err(f"output.gauges[{i}].block", "a 'force' gauge needs the name of the block it reads")
        elif isinstance(bn, str) and not any(isinstance(e, str) and block_name_matches(bn, e) for e in names):
            boxes = [f"obstacle.{k}" for k, ob in enumerate(s.get("obstacles") or []) if ob.get("box_min_m") is not None]
            if bn not in boxes:
                v.err(f"output.gauges[{i}].block", f"{bn!r} is not the name of a block or a box obstacle; the scene's "
                                                   f"blocks: {', '.join(repr(e) for e in names) or 'none'}; box "
                                                   f"obstacles: {', '.join(repr(e) for e in boxes) or 'none'}")
        if d is None:
            v.err(f"output.gauges[{i}].direction", "a 'force' gauge needs the direction it reads along, e.g. "
                                                   f"{[0.0] * (v.dim - 1) + [1.0]} for the vertical")
        elif isinstance(d, (list, tuple)) and all(isinstance(c, (int, float)) for c in d) and not any(d):
            v.err(f"output.gauges[{i}].direction", f"{list(d)}: the direction must not be zero")
        if g.get("position_m") is not None:
            v.err(f"output.gauges[{i}].position_m", "a 'force' gauge reads a whole block: no position")
    t, fl = s["tank"], s["fluid"]
    if fl is None and gauges:
        v.err("output.gauges", "needs water: the scene has no [fluid] section and gauges read the water (height, "
                               "pressure and force); remove the [[output.gauges]] entries or add water")
        return
    box = _box_of(t) if t is not None else None
    if box is None or fl is None or not fl.get("spacing_m") or not gauges:
        return  # mesh tanks: rockwave/build/preflight.py checks against the mesh's bounds
    gauge_domain_errors(v.err, gauges, box[0], box[1], v.dim, _support_radius(fl), "the tank")


def _support_radius(fl) -> float:
    """Kernel support radius H [m] of a [fluid] section under validation (rockwave/sph/fluid.py support_radius;
    apply_fidelity has set support_radius_ratio, the draft level's where an error left it unset)."""
    return support_radius(fl["spacing_m"], fl.get("support_radius_ratio") or FIDELITY["draft"]["support_radius_ratio"])


def gauge_domain_errors(err, gauges, lo, hi, dim: int, tol: float, what: str) -> None:
    """A height gauge's horizontal position, or a pressure gauge's position, outside [lo, hi] by more than tol
    (a pressure gauge above the top is allowed up to one tank height: splashes)."""
    up = dim - 1
    for i, g in enumerate(gauges):
        p, kind = g.get("position_m"), g.get("kind")
        if p is None or kind is None or len(p) != dim:
            continue
        axes = [a for a in range(dim) if a != up] if kind == "height" else list(range(dim))
        for a in axes:
            top = hi[a] + (hi[a] - lo[a] if a == up else 0.0)
            if p[a] < lo[a] - tol or p[a] > top + tol:
                name = "xyz"[a]
                where = "below the floor of" if a == up and p[a] < lo[a] else "outside"
                err(f"output.gauges[{i}].position_m", f"{p}: {name} = {p[a]:g} m is {where} {what} "
                                                      f"({name} from {lo[a]:g} to {hi[a]:g} m); the gauge would read nothing")
                break


def parse_scene(data: dict, path: str | os.PathLike = "<scene>", base_dir: str | os.PathLike | None = None) -> Scene:
    """Validate an already-parsed TOML dict. Raises :class:`SceneError` listing every problem."""
    base = Path(base_dir) if base_dir is not None else (Path(path).parent if path != "<scene>" else Path.cwd())
    dim = 3
    sim = data.get("simulation", {}) if isinstance(data, dict) else {}
    if isinstance(sim, dict) and sim.get("dimension") in (2, 3) and not isinstance(sim.get("dimension"), bool):
        dim = sim["dimension"]
    v = _Validator(base, dim)
    raw_blocks = data.get("blocks", []) if isinstance(data, dict) else []
    v.raw_blocks = raw_blocks if isinstance(raw_blocks, list) else []
    raw_rm = data.get("rock_mass", []) if isinstance(data, dict) else []
    v.raw_rock_mass = raw_rm if isinstance(raw_rm, list) else []
    raw_fluid = data.get("fluid") if isinstance(data, dict) else None
    v.raw_fluid = raw_fluid if isinstance(raw_fluid, dict) else {}
    raw_sim = data.get("simulation") if isinstance(data, dict) else None
    v.raw_simulation = raw_sim if isinstance(raw_sim, dict) else {}
    s = v.section(data, SCHEMA, "")
    if not v.errors or all(not e[0].startswith("simulation.dimension") for e in v.errors):
        _cross_checks(v, s)

        check_hazard_keys(v.err, s, dim)
    if s["fluid"] is not None and s["fluid"]["regions"] is None:
        s["fluid"]["regions"] = []
    if s["gravity"]["acceleration_m_s2"] is None:
        s["gravity"]["acceleration_m_s2"] = [0.0, -9.81] if dim == 2 else [0.0, 0.0, -9.81]
    if v.errors:
        raise SceneError(path, v.errors)
    return Scene(path=str(path), simulation=s["simulation"], gravity=s["gravity"], fluid=s["fluid"], tank=s["tank"],
                 obstacles=s["obstacles"], output=s["output"], blocks=s["blocks"], raw=data, coupling=s["coupling"],
                 rock_mass=s["rock_mass"], hazard=s["hazard"])


def load_scene(path: str | os.PathLike) -> Scene:
    """Read and validate a scene file."""
    p = Path(path)
    if not p.is_file():
        raise SceneError(path, [("", "scene file not found")])
    try:
        with open(p, "rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise SceneError(path, [("", f"not valid TOML: {e}")]) from None
    except RecursionError:
        raise SceneError(path, [("", "not a usable TOML file: arrays or tables nested too deeply")]) from None
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(path, [("", f"cannot read: {e}")]) from None
    try:
        return parse_scene(data, p, p.parent)
    except RecursionError:
        raise SceneError(path, [("", "arrays or tables nested too deeply")]) from None


def schema_markdown() -> str:
    """The scene format as a Markdown table (docs/scene_format.md; `python -m rockwave schema`)."""
    rows = ["| key | type | default | allowed | meaning |", "|---|---|---|---|---|"]

    def walk(spec: dict[str, Key], prefix: str) -> None:
        for name, k in spec.items():
            path = f"{prefix}.{name}" if prefix else name
            if k.type == "section":
                rows.append(f"| **[{path}]** | table | | | {k.doc} |")
                walk(k.children, path)
            elif k.type == "table_list":
                rows.append(f"| **[[{path}]]** | array of tables | | | {k.doc} |")
                walk(k.children, path + "[]")
            else:
                d = "required" if k.required else ("" if k.default is None else repr(k.default))
                rows.append(f"| `{path}` | {k.type} | {d} | {k.allowed()} | {k.doc} |")

    walk(SCHEMA, "")
    return "\n".join(rows)


def scene_format_doc() -> str:
    """docs/scene_format.md: the scene format reference, generated from SCHEMA."""
    return ("# Scene format\n\nGenerated by `python -m rockwave schema > docs/scene_format.md` from the schema the loader "
            "checks against (`rockwave/scene/format.py`). Units are SI and appear in the key names. `[[name]]` marks an array "
            "of tables; `name[]` a key inside each of its entries.\n\n" + schema_markdown() + "\n")


# --------------------------------------------------------------------------------------------
# [hazard]: checked against the scene (rockwave/output/hazard.py computes the summary)
# --------------------------------------------------------------------------------------------



DEFAULT_SAMPLE_INTERVAL_S = 0.01
MAX_RUNUP_COLUMNS = 1024
DEFAULT_MAX_COLUMNS = 256


def block_name_matches(name: str, entry_name: str) -> bool:
    """A block's name as the scene writes it: an entry's own name, or name_i for the blocks of an entry's array or
    multi-part mesh."""
    if name == entry_name:
        return True
    head, _, tail = name.rpartition("_")
    return head == entry_name and tail.isdigit()


def check_hazard_keys(err, s, dim: int) -> None:
    """Scene checks of [hazard] (rockwave/scene/format.py calls this with its validator's err(key, message))."""
    hz = s.get("hazard")
    if hz is None:
        return
    up = dim - 1
    needs_water = [k for k in ("gauges", "runup", "crossings") if hz.get(k)]
    if s.get("fluid") is None and needs_water:
        err(f"hazard.{needs_water[0]}", "needs water: the scene has no [fluid] section")
    for lst in ("gauges", "runup", "crossings"):
        seen: dict[str, int] = {}
        for i, e in enumerate(hz.get(lst) or []):
            n = e.get("name")
            if not isinstance(n, str):
                continue
            if not n.strip() or any(ord(c) < 32 for c in n) or n != n.strip():
                err(f"hazard.{lst}[{i}].name", f"{n!r}: a name is a column header: non-empty, on one line, no spaces around it")
            elif n in seen:
                err(f"hazard.{lst}[{i}].name", f"{n!r} is already the name of hazard.{lst}[{seen[n]}]")
            else:
                seen[n] = i
    for i, r in enumerate(hz.get("runup") or []):
        a, b = r.get("start_m"), r.get("end_m")
        if a is not None and b is not None and all(abs(a[k] - b[k]) < 1e-12 for k in range(dim) if k != up):
            err(f"hazard.runup[{i}].end_m", f"{b}: same horizontal position as start_m {a}; the run-up line runs across "
                                            "the shore between two different horizontal positions")
    for i, c in enumerate(hz.get("crossings") or []):
        n = c.get("normal")
        if n is None:
            continue
        if abs(n[up]) > 0 or math.sqrt(sum(x * x for x in n)) == 0:
            err(f"hazard.crossings[{i}].normal", f"{n}: expected a non-zero horizontal direction ({'y' if dim == 2 else 'z'} "
                                                 f"component 0), e.g. {[1.0] + [0.0] * (dim - 1)}")
    names = [b.get("name") for b in (s.get("blocks") or []) + (s.get("rock_mass") or [])]  # rock masses: name_i
    for i, sl in enumerate(hz.get("slides") or []):
        u = sl.get("along")
        if u is not None and math.sqrt(sum(x * x for x in u)) == 0:
            err(f"hazard.slides[{i}].along", f"{u}: expected a non-zero direction")
        bn = sl.get("block")
        if isinstance(bn, str) and not any(isinstance(e, str) and block_name_matches(bn, e) for e in names):
            err(f"hazard.slides[{i}].block", f"{bn!r} is not the name of a block; the scene's blocks: "
                                             f"{', '.join(repr(e) for e in names) or 'none'}")
    t, fl = s.get("tank"), s.get("fluid")
    if t is not None and fl is not None and t.get("box_min_m") and t.get("box_max_m") and fl.get("spacing_m"):

        tol = _support_radius(fl)
        pts = [{"position_m": g.get("position_m"), "kind": "height"} for g in hz.get("gauges") or []]
        gauge_domain_errors(lambda k, m: err(k.replace("output.gauges", "hazard.gauges"), m), pts,
                            t["box_min_m"], t["box_max_m"], dim, tol, "the tank")
        for key in ("start_m", "end_m"):
            pts = [{"position_m": r.get(key), "kind": "height"} for r in hz.get("runup") or []]
            gauge_domain_errors(lambda k, m, key=key: err(k.replace("output.gauges", "hazard.runup").replace("position_m", key), m),
                                pts, t["box_min_m"], t["box_max_m"], dim, tol, "the tank")
