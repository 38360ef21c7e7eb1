"""Water: weakly compressible SPH (the fluid model, state and step) and Ghost SPH. Kernels: rockwave/kernels/sph/."""
