"""Rock: explicit 3D DDA blocks (models, states, the block step) and convex block geometry. Kernels: rockwave/kernels/dda/."""
