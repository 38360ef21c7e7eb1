"""The fluid step's linear stability limit on a particle lattice, for each kernel and support (the reason for the
default Courant number, ``simulation.cfl_number``; docs/notes.md 'Time step').

Linearised about water at rest on the initial lattice (spacing dx, V = dx^dim, the code's own kernel gradient
with its lattice calibration), continuity density and the momentum-conserving pressure force reduce to the
acoustic system d(rho')/dt = -rho0 D v',  dv'/dt = -(c0^2/rho0) D rho', where D is the SPH gradient / divergence
with symbol i G(k), G(k) = sum_j V sin(k . r_j) grad W(r_j) (the sum_j V grad W part cancels on the lattice).
So omega(k) = c0 |G(k)|, and the semi-implicit Euler step of rockwave/sph/fluid.py (density first, then velocity and
position) is stable while omega dt < 2 for every k: with dt = C h / c0 (h = H/2) that is
C < C_max = 2 / (h max_k |G(k)|). The default Courant number is a fraction of C_max: what is left covers the
nonlinear events (impacts, splashes) that the linear analysis does not see.

``python -m benchmarks.courant`` prints C_max for the kernels and supports the scene schema offers.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import warp as wp

from rockwave.kernels.sph import fluid as sph


@wp.kernel
def _lattice_gradients(r: wp.array(dtype=wp.vec3), p: sph.SPHParams, g: wp.array(dtype=wp.vec3)):
    """g[j] = grad_i W(x_i - x_j) at x_i - x_j = -r[j] (the code's kernel_grad, calibration included)."""
    j = wp.tid()
    rij = -r[j]
    g[j] = sph.kernel_grad(rij, wp.length(rij), p)


def lattice_acoustic_limit(kernel: str, support_ratio: float, dim: int, k_points: int | None = None) -> float:
    """C_max for ``kernel`` ('muller', 'cubic_spline', 'wendland') at ``support_ratio`` spacings in ``dim``
    dimensions (module docstring); |G(k)| maximised over a k_points^dim grid of the first Brillouin zone's
    positive quadrant (G is odd in each component, so that quadrant holds the maximum)."""
    import rockwave
    from rockwave.build.options import fluid_parameters
    from rockwave.sph.fluid import calibrate_lattice, make_params

    k_points = k_points or (48 if dim == 2 else 20)
    dx = 1.0
    d = {"simulation": {"dimension": dim, "duration_s": 1.0},
         "fluid": {"spacing_m": dx, "kernel": kernel, "support_radius_ratio": support_ratio,
                   "eos": {"speed_of_sound_m_s": 10.0}, "regions": [{"box_min_m": [0.0] * dim, "box_max_m": [1.0] * dim}]},
         "tank": {"box_min_m": [0.0] * dim, "box_max_m": [1.0] * dim}}
    scene = rockwave.parse_scene(d)
    p = make_params(fluid_parameters(scene.fluid), dim, [0.0] * dim, 1)
    p.fluid_mass, p.grad_scale = calibrate_lattice(p, dx, dim, "cpu")
    n = int(math.ceil(support_ratio)) + 1
    pts = np.array([q for q in itertools.product(range(-n, n + 1), repeat=dim) if any(q)], float)
    pts = pts[np.linalg.norm(pts, axis=1) < support_ratio * dx]
    r3 = np.c_[pts, np.zeros((len(pts), 3 - dim))].astype(np.float32)
    g = wp.zeros(len(pts), dtype=wp.vec3, device="cpu")
    wp.launch(_lattice_gradients, dim=len(pts), inputs=[wp.array(r3, dtype=wp.vec3, device="cpu"), p], outputs=[g],
              device="cpu")
    grad = g.numpy()[:, :dim].astype(np.float64) * dx ** dim  # V_j grad W_j
    ks = np.linspace(0.0, math.pi / dx, k_points)
    kk = np.array(list(itertools.product(ks, repeat=dim)))
    G = np.sin(kk @ pts.T) @ grad  # (k, dim)
    return 2.0 / (0.5 * support_ratio * dx * float(np.linalg.norm(G, axis=1).max()))


def main() -> None:
    for dim in (2, 3):
        for kernel, ratio in (("muller", 2.0), ("cubic_spline", 3.0), ("wendland", 2.5), ("wendland", 3.0),
                              ("wendland", 4.0)):
            print(f"{dim}D {kernel:12s} support {ratio:g} spacings: C_max = {lattice_acoustic_limit(kernel, ratio, dim):.2f}")


if __name__ == "__main__":
    main()
