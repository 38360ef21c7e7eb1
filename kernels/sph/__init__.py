"""Warp kernels launched by rockwave/sph/ (paired by path: kernels/sph/X.py with rockwave/sph/X.py)."""
