"""rockwave benchmarks: speed and accuracy on CPU and CUDA (python -m benchmarks ...)."""
