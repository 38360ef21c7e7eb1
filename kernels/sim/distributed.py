"""Halo and migration kernels of the slab decomposition, launched by rockwave/sim/distributed.py (DistributedFluid):
particles packed into contiguous device buffers (one float32 row per particle) and unpacked into the rank's
arrays, and the classification of the owned particles against the slab faces at a list rebuild.

Row layouts (columns):
  HALO_COLS = 7:  x (3), v (3), rho              the halo refresh at each step's start
  DENS_COLS = 3:  rho, p, p / rho^2              the halo densities inside the step (after the density passes)
  FULL_COLS = 13: x (3), v (3), rho, a (3), p, id_hi, id_lo   migration and new halos at a rebuild
(a global id, int32, in two float32 parts: id // 2^20 and id % 2^20, integers below 2^24, exact in float32).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # forward kernels only

HALO_COLS = 7
DENS_COLS = 3
FULL_COLS = 13
ID_SPLIT = wp.constant(1048576)  # 2^20


@wp.kernel
def pack_halo(idx: wp.array(dtype=int), x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
              rho: wp.array(dtype=float), buf: wp.array2d(dtype=float)):
    """buf[k] = (x, v, rho) of slot idx[k]."""
    k = wp.tid()
    i = idx[k]
    xi = x[i]
    vi = v[i]
    for c in range(3):
        buf[k, c] = xi[c]
        buf[k, 3 + c] = vi[c]
    buf[k, 6] = rho[i]


@wp.kernel
def unpack_halo(buf: wp.array2d(dtype=float), offset: int, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                rho: wp.array(dtype=float)):
    """Slot offset + k := row k of buf (pack_halo's layout)."""
    k = wp.tid()
    i = offset + k
    x[i] = wp.vec3(buf[k, 0], buf[k, 1], buf[k, 2])
    v[i] = wp.vec3(buf[k, 3], buf[k, 4], buf[k, 5])
    rho[i] = buf[k, 6]


@wp.kernel
def pack_densities(idx: wp.array(dtype=int), rho: wp.array(dtype=float), p: wp.array(dtype=float),
                   pr2: wp.array(dtype=float), buf: wp.array2d(dtype=float)):
    k = wp.tid()
    i = idx[k]
    buf[k, 0] = rho[i]
    buf[k, 1] = p[i]
    buf[k, 2] = pr2[i]


@wp.kernel
def unpack_densities(buf: wp.array2d(dtype=float), offset: int, rho: wp.array(dtype=float), p: wp.array(dtype=float),
                     pr2: wp.array(dtype=float)):
    k = wp.tid()
    i = offset + k
    rho[i] = buf[k, 0]
    p[i] = buf[k, 1]
    pr2[i] = buf[k, 2]


@wp.kernel
def pack_full(idx: wp.array(dtype=int), gid: wp.array(dtype=int), x: wp.array(dtype=wp.vec3),
              v: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float), a: wp.array(dtype=wp.vec3),
              p: wp.array(dtype=float), buf: wp.array2d(dtype=float)):
    """buf[k] = the whole state of slot idx[k] (FULL_COLS layout)."""
    k = wp.tid()
    i = idx[k]
    xi = x[i]
    vi = v[i]
    ai = a[i]
    for c in range(3):
        buf[k, c] = xi[c]
        buf[k, 3 + c] = vi[c]
        buf[k, 7 + c] = ai[c]
    buf[k, 6] = rho[i]
    buf[k, 10] = p[i]
    g = gid[i]
    hi = g // ID_SPLIT
    buf[k, 11] = float(hi)
    buf[k, 12] = float(g - hi * ID_SPLIT)


@wp.kernel
def unpack_full(buf: wp.array2d(dtype=float), offset: int, gid: wp.array(dtype=int), x: wp.array(dtype=wp.vec3),
                v: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float), a: wp.array(dtype=wp.vec3),
                p: wp.array(dtype=float)):
    """Slot offset + k := row k of buf (pack_full's layout)."""
    k = wp.tid()
    i = offset + k
    x[i] = wp.vec3(buf[k, 0], buf[k, 1], buf[k, 2])
    v[i] = wp.vec3(buf[k, 3], buf[k, 4], buf[k, 5])
    rho[i] = buf[k, 6]
    a[i] = wp.vec3(buf[k, 7], buf[k, 8], buf[k, 9])
    p[i] = buf[k, 10]
    gid[i] = int(buf[k, 11]) * ID_SPLIT + int(buf[k, 12])


@wp.kernel
def unpack_by_id(buf: wp.array2d(dtype=float), n: int, x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
                 rho: wp.array(dtype=float), a: wp.array(dtype=wp.vec3), p: wp.array(dtype=float),
                 ids: wp.array(dtype=int), seen: wp.array(dtype=int)):
    """Slot id := row k of buf (pack_full's layout), id its global id (rank 0's whole state, in id order); seen[id]
    counts the rows of each id (a lost or doubled particle leaves a 0 or a 2); an id outside [0, n) is dropped."""
    k = wp.tid()
    i = int(buf[k, 11]) * ID_SPLIT + int(buf[k, 12])
    if i < 0 or i >= n:
        return
    x[i] = wp.vec3(buf[k, 0], buf[k, 1], buf[k, 2])
    v[i] = wp.vec3(buf[k, 3], buf[k, 4], buf[k, 5])
    rho[i] = buf[k, 6]
    a[i] = wp.vec3(buf[k, 7], buf[k, 8], buf[k, 9])
    p[i] = buf[k, 10]
    ids[i] = i
    wp.atomic_add(seen, i, 1)


@wp.kernel
def classify(x: wp.array(dtype=wp.vec3), axis: int, lo: float, hi: float, halo: float,
             keep: wp.array(dtype=int), down: wp.array(dtype=int), up: wp.array(dtype=int),
             halo_down: wp.array(dtype=int), halo_up: wp.array(dtype=int)):
    """Particle i against the slab [lo, hi) (lo = -inf / hi = +inf at the outer ranks, passed as +-3e38):
    keep / down (c < lo, to the lower rank) / up (c >= hi); halo_down (c < lo + halo: in the lower rank's halo) and
    halo_up (c >= hi - halo). 0/1 flags for the compaction (scan + scatter_flagged). The faces are float32 values
    (rockwave/sim/distributed.py SlabDecomposition), so the host's owner() agrees with this test."""
    i = wp.tid()
    c = x[i][axis]
    k = 0
    d = 0
    u = 0
    if c < lo:
        d = 1
    elif c >= hi:
        u = 1
    else:
        k = 1
    keep[i] = k
    down[i] = d
    up[i] = u
    hd = 0
    hu = 0
    if c < lo + halo:
        hd = 1
    if c >= hi - halo:
        hu = 1
    halo_down[i] = hd
    halo_up[i] = hu


@wp.kernel
def scatter_flagged(flag: wp.array(dtype=int), pos: wp.array(dtype=int), out: wp.array(dtype=int)):
    """Stream compaction: out[pos[i]] = i where flag[i] (pos: the exclusive prefix sum of flag)."""
    i = wp.tid()
    if flag[i] != 0:
        out[pos[i]] = i


@wp.kernel
def gather_owned(idx: wp.array(dtype=int), gid: wp.array(dtype=int), x: wp.array(dtype=wp.vec3),
                 v: wp.array(dtype=wp.vec3), rho: wp.array(dtype=float), a: wp.array(dtype=wp.vec3),
                 p: wp.array(dtype=float), gid_out: wp.array(dtype=int), x_out: wp.array(dtype=wp.vec3),
                 v_out: wp.array(dtype=wp.vec3), rho_out: wp.array(dtype=float), a_out: wp.array(dtype=wp.vec3),
                 p_out: wp.array(dtype=float)):
    """Slot k of the new arrays := slot idx[k] of the old (the particles a rank keeps at a rebuild)."""
    k = wp.tid()
    i = idx[k]
    gid_out[k] = gid[i]
    x_out[k] = x[i]
    v_out[k] = v[i]
    rho_out[k] = rho[i]
    a_out[k] = a[i]
    p_out[k] = p[i]


@wp.kernel
def owned_extrema(v: wp.array(dtype=wp.vec3), a: wp.array(dtype=wp.vec3), n: int, stride: int,
                  out: wp.array(dtype=float)):
    """out = (max |v|^2, max |a|^2) over slots 0..n-1 (the owned particles), strided atomics."""
    t = wp.tid()
    vm = float(0.0)
    am = float(0.0)
    i = t
    while i < n:
        vm = wp.max(vm, wp.length_sq(v[i]))
        am = wp.max(am, wp.length_sq(a[i]))
        i += stride
    wp.atomic_max(out, 0, vm)
    wp.atomic_max(out, 1, am)


@wp.kernel
def cell_keys(x: wp.array(dtype=wp.vec3), lo: wp.vec3, inv_c: float, nx: int, ny: int, nz: int,
              keys: wp.array(dtype=int), order: wp.array(dtype=int)):
    """The cell (edge 1/inv_c, from lo, clamped to nx x ny x nz) of particle i as a sort key, and order[i] = i: the
    owned particles go into cell order at a relayout (coherent neighbour reads, as FluidSolver.reorder on one
    process)."""
    i = wp.tid()
    d = (x[i] - lo) * inv_c
    cx = wp.clamp(int(wp.floor(d[0])), 0, nx - 1)
    cy = wp.clamp(int(wp.floor(d[1])), 0, ny - 1)
    cz = wp.clamp(int(wp.floor(d[2])), 0, nz - 1)
    keys[i] = cx + nx * (cy + ny * cz)
    order[i] = i
