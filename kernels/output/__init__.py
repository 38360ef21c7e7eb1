"""Warp kernels launched by rockwave/output/ (paired by path: kernels/output/X.py with rockwave/output/X.py)."""
