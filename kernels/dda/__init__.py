"""Warp kernels launched by rockwave/dda/ (paired by path: kernels/dda/X.py with rockwave/dda/X.py)."""
