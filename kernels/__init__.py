"""Warp kernels of rockwave (installed as ``rockwave.kernels``). Kernels only: no host logic.

Each module's docstring names the host module that launches it: sph with rockwave/fluid.py (the SPH
fluid; also reused by rockwave/ghost.py and the gauges of rockwave/simulation.py), ghost with
rockwave/ghost.py, diffusion with the density diffusion of rockwave/fluid.py, sampling with
rockwave/sampling.py, surface with rockwave/export/surface.py, dda with rockwave/blocks.py and coupling
with rockwave/coupling.py.

Each Warp module is built once per device (tests/test_kernel_loads.py): declare a generic kernel's
overloads with the module, define every kernel at import (no kernels made in functions or on first
use), and give a kernel launched at another block size than the rest of its module a module of its own.
"""
