"""Warp kernels of rockwave (installed as ``rockwave.kernels``). Kernels only: no host logic."""
