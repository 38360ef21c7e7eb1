"""Fluid passes over the neighbour list that read each neighbour as two 16-byte words.

The list passes (kernels/sph.py particle_density_continuity_list, particle_acceleration_list) gather,
per list entry, x_j and v_j (3 floats each), rho_j and p_j/rho_j^2 from four arrays: up to 9 load
instructions touching 4 memory sectors. Here the same data sit in two float4 arrays,
    xq_j = (x_j, p_j/rho_j^2)   for fluid j,   (x_b, Psi_b)   for boundary b (its mass-like volume weight),
    vq_j = (v_j, rho_j)         for fluid j,
written once per step (pack_particles before the density pass; the density pass adds its own
p/rho^2 and rho as the fourth components), and read with one aligned 16-byte load each (ldg.128 on
CUDA). The physics is that of kernels/sph.py: the pair terms are its functions.
"""

import warp as wp

from .sph import SPHParams, equation_of_state, kernel_grad, pair_acceleration_terms

# one 16-byte load on CUDA (Warp's vec4 has 4-byte alignment, so nvcc would split it into four);
# Warp allocations are 256-byte aligned, so element j of a vec4 array is 16-byte aligned
_LOAD4 = """
#if defined(__CUDA_ARCH__)
    const float4 q = __ldg(reinterpret_cast<const float4*>(a.data) + j);
    return wp::vec4(q.x, q.y, q.z, q.w);
#else
    return a.data[j];
#endif
"""


@wp.func_native(_LOAD4)
def load4(a: wp.array(dtype=wp.vec4), j: int) -> wp.vec4:
    ...


@wp.func
def xyz(q: wp.vec4) -> wp.vec3:
    return wp.vec3(q[0], q[1], q[2])


@wp.kernel
def pack_particles(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=float),
    n_fluid: int,
    xq: wp.array(dtype=wp.vec4),
    vq: wp.array(dtype=wp.vec4),
):
    """xq = (x, 0) and vq = (v, 0) for fluid particles, xq = (x, Psi) for boundary particles (all n_total)."""
    i = wp.tid()
    xi = x[i]
    if i < n_fluid:
        xq[i] = wp.vec4(xi[0], xi[1], xi[2], 0.0)
        vi = v[i]
        vq[i] = wp.vec4(vi[0], vi[1], vi[2], 0.0)
    else:
        xq[i] = wp.vec4(xi[0], xi[1], xi[2], particle_mass[i])


@wp.kernel
def particle_density_continuity_packed(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    dt: wp.array(dtype=float),
    p: SPHParams,
    xq: wp.array(dtype=wp.vec4),
    vq: wp.array(dtype=wp.vec4),
    drho_dt: wp.array(dtype=float),
    rho: wp.array(dtype=float),
    pressure: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
):
    """kernels/sph.py particle_density_continuity_list on the packed arrays:
    d rho_i/dt = sum_j m_j (v_i - v_j) . grad W_ij (boundary particles at rest), rho_i += dt d rho_i/dt,
    p_i = EOS(rho_i); also stores p_i/rho_i^2 and rho_i as the fourth components of xq_i and vq_i (other
    threads read only the first three of those words in this pass)."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    if c > nbr.shape[0] // n:
        return
    qi = xq[i]
    xi = xyz(qi)
    vi4 = vq[i]
    vi = xyz(vi4)
    s = float(0.0)
    for k in range(c):
        j = nbr[k * n + i]
        qj = load4(xq, j)
        rij = xi - xyz(qj)
        r2 = wp.length_sq(rij)
        if r2 < p.H * p.H:  # a list built with a skin also holds pairs out to H + skin
            g = kernel_grad(rij, wp.sqrt(r2), p)
            if j < p.n_fluid:
                s += p.fluid_mass * wp.dot(vi - xyz(load4(vq, j)), g)
            else:
                s += qj[3] * wp.dot(vi, g)
    drho_dt[i] = s
    rr = rho[i] + dt[0] * s
    rho[i] = rr
    pr = equation_of_state(rr, p)
    pressure[i] = pr
    q2 = pr / (rr * rr)
    pr2[i] = q2
    xq[i] = wp.vec4(xi[0], xi[1], xi[2], q2)
    vq[i] = wp.vec4(vi[0], vi[1], vi[2], rr)


@wp.kernel
def repack_overflowed(
    count: wp.array(dtype=int),
    cap: int,
    rho: wp.array(dtype=float),
    pr2: wp.array(dtype=float),
    xq: wp.array(dtype=wp.vec4),
    vq: wp.array(dtype=wp.vec4),
):
    """The fourth components for particles whose list overflowed (their density came from the overflow pass)."""
    i = wp.tid()
    if count[i] <= cap:
        return
    q = xq[i]
    xq[i] = wp.vec4(q[0], q[1], q[2], pr2[i])
    w = vq[i]
    vq[i] = wp.vec4(w[0], w[1], w[2], rho[i])


@wp.kernel
def particle_acceleration_packed(
    count: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    p: SPHParams,
    xq: wp.array(dtype=wp.vec4),
    vq: wp.array(dtype=wp.vec4),
    accel: wp.array(dtype=wp.vec3),
    xsph_dv: wp.array(dtype=wp.vec3),
):
    """kernels/sph.py particle_acceleration_list on the packed arrays (the fluid mass, p/rho^2 from xq)."""
    i = wp.tid()
    n = count.shape[0]
    c = count[i]
    if c > nbr.shape[0] // n:
        return
    qi = xq[i]
    xi = xyz(qi)
    wi = vq[i]
    vi = xyz(wi)
    rhoi = wi[3]
    pi_r2 = qi[3]
    pi = pi_r2 * rhoi * rhoi
    a = wp.vec3(0.0)
    dv = wp.vec3(0.0)
    for k in range(c):
        j = nbr[k * n + i]
        qj = load4(xq, j)
        rij = xi - xyz(qj)
        r2 = wp.length_sq(rij)
        if r2 < p.H * p.H:
            r = wp.sqrt(r2)
            gw = kernel_grad(rij, r, p)
            if j >= p.n_fluid:
                # Akinci et al. 2012 boundary pressure: a_i -= Psi_b p_i/rho_i^2 grad W_ib (walls at rest)
                a -= (qj[3] * pi_r2) * gw
            else:
                wj = load4(vq, j)
                rhoj = wj[3]
                da, ddv = pair_acceleration_terms(rij, r2, r, gw, vi - xyz(wj), rhoi, pi, pi_r2, rhoj,
                                                  qj[3] * rhoj * rhoj, qj[3], p)
                a += da
                dv += ddv
    accel[i] = a + p.gravity
    xsph_dv[i] = p.xsph * dv
