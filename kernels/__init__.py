"""Warp kernels of rockwave (installed as ``rockwave.kernels``). Kernels only: no host logic.

A kernel module pairs with the host module of the same name: fluid with rockwave/sph/fluid.py (the SPH fluid
step; its helpers are shared by ghost, diffusion, readers and surface), ghost with rockwave/sph/ghost.py,
blocks with rockwave/dda/blocks.py (DDA; blocks_coop: its cooperative narrow phase of big blocks, launched at
its own block size), coupling with rockwave/coupling/penalty.py, readers with rockwave/sim/readers.py
(gauges), sampling with rockwave/build/sampling.py, surface with rockwave/output/surface.py; diffusion is the
density diffusion term of rockwave/sph/fluid.py. Host modules import the fluid kernels as ``sph``.

Each Warp module is built once per device (tests/test_kernel_loads.py): declare a generic kernel's
overloads with the module, define every kernel at import (no kernels made in functions or on first
use), and give a kernel launched at another block size than the rest of its module a module of its own.
"""
