"""rockwave: rock masses and water. SPH fluid and explicit 3D DDA rock blocks on NVIDIA Warp.

The public face: a scene file (or dict) becomes a :class:`Simulation`; the Options classes tune its parts::

    from rockwave import Simulation, SimulationOptions, FluidOptions, load_scene
    sim = Simulation(load_scene("scenes/dam_break_2d.toml"), options=SimulationOptions(fluid=FluidOptions()))
    sim.run("runs/dam_break_2d")
"""

from rockwave.base.device import resolve_device
from rockwave.base.errors import SimulationError
from rockwave.coupling.penalty import CouplingOptions
from rockwave.dda.blocks import BlockOptions
from rockwave.scene.format import Scene, SceneError, load_scene, parse_scene
from rockwave.sim.simulation import Simulation, SimulationOptions
from rockwave.sph.fluid import FluidOptions
from rockwave.sph.ghost import GhostOptions

__version__ = "0.1.0"
__all__ = ["BlockOptions", "CouplingOptions", "FluidOptions", "GhostOptions", "Scene", "SceneError", "Simulation",
           "SimulationError", "SimulationOptions", "load_scene", "parse_scene", "resolve_device"]
