"""Warp kernels launched by rockwave/coupling/ (paired by path: kernels/coupling/X.py with rockwave/coupling/X.py)."""
