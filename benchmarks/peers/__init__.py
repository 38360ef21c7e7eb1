"""Peer codes run side by side with rockwave (benchmarks/peers/splash.py, warp_example.py)."""
