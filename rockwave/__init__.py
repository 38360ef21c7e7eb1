"""rockwave: rock masses and water. SPH fluid and explicit 3D DDA rock blocks on NVIDIA Warp."""

from rockwave.base.errors import SimulationError
from rockwave.scene.format import Scene, SceneError, load_scene, parse_scene
from rockwave.sim.simulation import Simulation, resolve_device

__version__ = "0.1.0"
__all__ = ["Scene", "SceneError", "Simulation", "SimulationError", "load_scene", "parse_scene", "resolve_device"]
