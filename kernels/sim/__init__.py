"""Warp kernels launched by rockwave/sim/ (paired by path: kernels/sim/X.py with rockwave/sim/X.py)."""
