"""Kernels for seeding particles in and around triangle meshes (Warp), launched by rockwave/build/sampling.py."""

import warp as wp

wp.set_module_options({"enable_backward": False})  # forward kernels only: nothing here is differentiated


@wp.kernel
def mesh_signed_distance(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    max_dist: float,
    out: wp.array(dtype=float),
):
    """Signed distance of each point to a closed mesh (negative inside). The sign comes from the
    generalised winding number, which is robust for meshes with small defects."""
    i = wp.tid()
    x = points[i]
    q = wp.mesh_query_point_sign_winding_number(mesh, x, max_dist)
    if q.result:
        c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        out[i] = q.sign * wp.length(x - c)
    else:
        out[i] = max_dist  # farther than max_dist from every face (callers pass max_dist > domain size)
