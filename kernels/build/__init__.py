"""Warp kernels launched by rockwave/build/ (paired by path: kernels/build/X.py with rockwave/build/X.py)."""
