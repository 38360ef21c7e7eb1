"""The shipped scenes, installed as package data (``importlib.resources.files("rockwave.scenes")``):
the default scene of ``python -m rockwave run`` and the data files they reference (data/)."""
