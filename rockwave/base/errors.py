"""Errors a run raises that every layer may need (the scene's own SceneError lives with the scene format)."""


class SimulationError(RuntimeError):
    """The run cannot go on (blow-up, unwritable output); the message says where and why."""
