"""Warp kernels of the DDA block solver's cooperative narrow phase (rockwave.kernels.dda.blocks_coop): the
narrow phase of pairs of big blocks, one thread block per pair. A module of its own because it is launched
at its own block size (BlockOptions.narrow_block_dim; Warp builds a module once per block size), and only
when a model has such pairs. Sources and conventions: kernels/dda/blocks.py (Nezami et al. 2004, Fast Common
Plane; Gregorius 2013, the SAT's Minkowski-face test)."""

import warp as wp

from rockwave.kernels.dda.blocks import (
    FCP_MAX_ITER,
    MAX_VALENCE,
    SAT_EDGE_PAIRS,
    BlockBodies,
    BlockTopology,
    ContactTable,
    PairList,
    PointCoord,
    PointKey,
    WorldVerts,
    add_contact,
    column_depth,
    column_through,
    contact_tangent,
    crossing_depth,
    face_normal,
    face_plane_of_he,
    he_dest,
    minkowski_edge_face,
    pair_origin,
    pair_vertex,
    patch_crossing,
    sat_recheck,
)

wp.set_module_options({"enable_backward": False})  # forward kernels only: nothing here is differentiated

# ----------------------------------------------------------------------------------------------
# narrow phase of big blocks: one thread block per pair (narrow_phase_coop). The same algorithm as
# narrow_phase, step for step: every loop over a block's vertices, faces or half-edge pairs is cut into
# chunks of block_dim work items, one per lane; a lane's result reaches the others through a tile
# (extents: a block-wide min; candidate planes and contact points: each chunk's results are taken in
# item order by every lane alike). So every lane holds the same plane and points, the result is the
# serial one bit for bit (ties broken by the lowest index, as the serial loops do), and with
# block_dim = 1 (Warp's CPU default) it is the serial loop itself.
# ----------------------------------------------------------------------------------------------

BIG_INDEX = wp.constant(2147483647)


@wp.func
def coop_extents(
    n: wp.vec3, sA: int, cA: int, sB: int, cB: int, wv: wp.array(dtype=wp.vec3), dA: wp.vec3, dB: wp.vec3, lane: int, bd: int, want_index: int
):
    # extent_along(n) of both blocks (lo, ilo, hi, ihi of A, then of B), lanes over the vertices;
    # the index reduction (first vertex attaining the extreme, as extent_along) only when want_index
    lA = float(1.0e30)
    hA = float(-1.0e30)
    lB = float(1.0e30)
    hB = float(-1.0e30)
    ilA = BIG_INDEX
    ihA = BIG_INDEX
    ilB = BIG_INDEX
    ihB = BIG_INDEX
    ndA = wp.dot(n, dA)
    ndB = wp.dot(n, dB)
    k = lane
    while k < cA:
        d = wp.dot(n, wv[sA + k]) + ndA
        if d < lA:
            lA = d
            ilA = sA + k
        if d > hA:
            hA = d
            ihA = sA + k
        k += bd
    k = lane
    while k < cB:
        d = wp.dot(n, wv[sB + k]) + ndB
        if d < lB:
            lB = d
            ilB = sB + k
        if d > hB:
            hB = d
            ihB = sB + k
        k += bd
    m = wp.tile_reduce(wp.min, wp.tile(wp.vec4(lA, -hA, lB, -hB), preserve_type=True))[0]
    iv = wp.vec4i(sA, sA, sB, sB)
    if want_index != 0:
        c = wp.vec4i(BIG_INDEX, BIG_INDEX, BIG_INDEX, BIG_INDEX)
        if lA == m[0]:
            c[0] = ilA
        if -hA == m[1]:
            c[1] = ihA
        if lB == m[2]:
            c[2] = ilB
        if -hB == m[3]:
            c[3] = ihB
        mi = wp.tile_reduce(wp.min, wp.tile(c, preserve_type=True))[0]
        for j in range(4):
            if mi[j] != BIG_INDEX:
                iv[j] = mi[j]
    return m[0], iv[0], -m[1], iv[1], m[2], iv[2], -m[3], iv[3]


@wp.func
def signed_gap_coop(n: wp.vec3, sA: int, cA: int, sB: int, cB: int, wv: wp.array(dtype=wp.vec3), dA: wp.vec3, dB: wp.vec3, lane: int, bd: int):
    # signed_gap, lanes over the vertices
    loA, ilA, hiA, ihA, loB, ilB, hiB, ihB = coop_extents(n, sA, cA, sB, cB, wv, dA, dB, lane, bd, 0)
    gp = loB - hiA
    gm = loA - hiB
    if gm > gp:
        return -n, gm
    return n, gp


@wp.func
def try_plane_coop(
    cand: wp.vec3, best_n: wp.vec3, best_gap: float, sA: int, cA: int, sB: int, cB: int,
    wv: wp.array(dtype=wp.vec3), dA: wp.vec3, dB: wp.vec3, lane: int, bd: int,
):
    # try_plane, lanes over the vertices
    ln = wp.length(cand)
    if ln < 1.0e-12:
        return best_n, best_gap
    nn, g = signed_gap_coop(cand / ln, sA, cA, sB, cB, wv, dA, dB, lane, bd)
    if g > best_gap + 1.0e-9:
        return nn, g
    return best_n, best_gap


@wp.func
def fcp_candidates_coop(
    a: int,
    b: int,
    best_n: wp.vec3,
    best_gap: float,
    sA: int,
    cA: int,
    sB: int,
    cB: int,
    wv: wp.array(dtype=wp.vec3),
    dA: wp.vec3,
    dB: wp.vec3,
    vertex_out_he: wp.array(dtype=int),
    he_vertex: wp.array(dtype=int),
    he_next: wp.array(dtype=int),
    he_twin: wp.array(dtype=int),
    lane: int,
    bd: int,
):
    # fcp_candidates (the candidates of the vertex pair in its order), each plane's gap over the lanes
    xa = pair_vertex(wv, dA, a)
    xb = pair_vertex(wv, dB, b)
    dab = xb - xa
    best_n, best_gap = try_plane_coop(dab, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB, lane, bd)
    h0 = vertex_out_he[a]
    h = h0
    for ka in range(MAX_VALENCE):
        nf, df = face_plane_of_he(h, wv, dA, he_vertex, he_next)
        best_n, best_gap = try_plane_coop(nf, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB, lane, bd)
        ea = wv[he_dest(h, he_vertex, he_next)] - wv[a]
        le = wp.length(ea)
        if le > 0.0:
            eh = ea / le
            best_n, best_gap = try_plane_coop(dab - wp.dot(dab, eh) * eh, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB, lane, bd)
        g0 = vertex_out_he[b]
        g = g0
        for kb in range(MAX_VALENCE):
            eb = wv[he_dest(g, he_vertex, he_next)] - wv[b]
            c = wp.cross(ea, eb)
            if wp.length(c) > 1.0e-6 * wp.length(ea) * wp.length(eb):
                best_n, best_gap = try_plane_coop(c, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB, lane, bd)
            g = he_next[he_twin[g]]
            if g == g0:
                break
        h = he_next[he_twin[h]]
        if h == h0:
            break
    g0 = vertex_out_he[b]
    g = g0
    for kb in range(MAX_VALENCE):
        nf, df = face_plane_of_he(g, wv, dB, he_vertex, he_next)
        best_n, best_gap = try_plane_coop(-nf, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB, lane, bd)
        eb = wv[he_dest(g, he_vertex, he_next)] - wv[b]
        le = wp.length(eb)
        if le > 0.0:
            eh = eb / le
            best_n, best_gap = try_plane_coop(dab - wp.dot(dab, eh) * eh, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB, lane, bd)
        g = he_next[he_twin[g]]
        if g == g0:
            break
    return best_n, best_gap


@wp.func
def fcp_touching_coop(
    n: wp.vec3,
    gap: float,
    tie: float,
    hiA: float,
    loB: float,
    sA: int,
    cA: int,
    sB: int,
    cB: int,
    fsA: int,
    fcA: int,
    fsB: int,
    fcB: int,
    face_he: wp.array(dtype=int),
    wv: wp.array(dtype=wp.vec3),
    dA: wp.vec3,
    dB: wp.vec3,
    he_vertex: wp.array(dtype=int),
    he_next: wp.array(dtype=int),
    lane: int,
    bd: int,
):
    # fcp_touching: is any closest vertex certified (lanes over the vertices of both blocks)
    found = int(0)
    k = lane
    while k < cA:
        p = pair_vertex(wv, dA, sA + k)
        if wp.dot(n, p) >= hiA - tie:
            t_lo, t_hi, hit = column_through(p, n, fsB, fcB, face_he, wv, dB, he_vertex, he_next, tie)
            if hit == 1 and t_lo <= gap + tie:
                found = 1
        k += bd
    k = lane
    while k < cB:
        p = pair_vertex(wv, dB, sB + k)
        if wp.dot(n, p) <= loB + tie:
            t_lo, t_hi, hit = column_through(p, n, fsA, fcA, face_he, wv, dA, he_vertex, he_next, tie)
            if hit == 1 and t_hi >= -gap - tie:
                found = 1
        k += bd
    return wp.tile_reduce(wp.max, wp.tile(found))[0]


@wp.func
def fcp_plane_coop(
    n0: wp.vec3,
    tie: float,
    sA: int,
    cA: int,
    sB: int,
    cB: int,
    fsA: int,
    fcA: int,
    fsB: int,
    fcB: int,
    face_he: wp.array(dtype=int),
    wv: wp.array(dtype=wp.vec3),
    dA: wp.vec3,
    dB: wp.vec3,
    vertex_out_he: wp.array(dtype=int),
    he_vertex: wp.array(dtype=int),
    he_next: wp.array(dtype=int),
    he_twin: wp.array(dtype=int),
    lane: int,
    bd: int,
):
    # fcp_plane, step for step (see there); extents, gaps and certificates over the lanes
    best_n, best_gap = signed_gap_coop(n0, sA, cA, sB, cB, wv, dA, dB, lane, bd)
    a = int(-1)
    b = int(-1)
    for it in range(FCP_MAX_ITER):
        n = best_n
        gap0 = best_gap
        loA, ilA, hiA, ihA, loB, ilB, hiB, ihB = coop_extents(n, sA, cA, sB, cB, wv, dA, dB, lane, bd, 1)
        if ihA != a or ilB != b:
            a = ihA
            b = ilB
            best_n, best_gap = fcp_candidates_coop(
                a, b, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB, vertex_out_he, he_vertex, he_next, he_twin, lane, bd
            )
        else:
            if gap0 <= 0.0:
                break
            touching = fcp_touching_coop(n, gap0, tie, hiA, loB, sA, cA, sB, cB, fsA, fcA, fsB, fcB, face_he, wv, dA, dB,
                                         he_vertex, he_next, lane, bd)
            if touching == 1:
                break
            # every pair of closest vertices (a separated pair FCP did not certify: rare), in order
            for ka in range(cA):
                va = sA + ka
                if wp.dot(n, pair_vertex(wv, dA, va)) >= hiA - tie:
                    for kb in range(cB):
                        vb = sB + kb
                        if wp.dot(n, pair_vertex(wv, dB, vb)) <= loB + tie:
                            best_n, best_gap = fcp_candidates_coop(
                                va, vb, best_n, best_gap, sA, cA, sB, cB, wv, dA, dB,
                                vertex_out_he, he_vertex, he_next, he_twin, lane, bd,
                            )
            if best_gap <= gap0:
                break
    return best_n, best_gap


@wp.kernel
def narrow_phase_coop(
    pl: PairList,
    verts: WorldVerts,
    topo: BlockTopology,
    bodies: BlockBodies,
    prev: ContactTable,
    cur: ContactTable,
):
    """narrow_phase for the pairs of big blocks (pl.active_big), one thread block per pair: FCP with
    its SAT fallback and the contact points, the work over vertices, faces and half-edge pairs spread
    over the block's lanes (see above); the same plane, gap and points as narrow_phase."""
    vert_start = topo.vert_start
    vert_count = topo.vert_count
    face_start = topo.face_start
    face_count = topo.face_count
    face_he = topo.face_he
    vertex_out_he = topo.vertex_out_he
    he_vertex = topo.he_vertex
    he_next = topo.he_next
    he_twin = topo.he_twin
    he_walk = topo.he_walk
    block_size = topo.block_size
    x = bodies.x
    bi, lane = wp.tid()
    bd = wp.block_dim()
    if bi >= pl.counters[4]:
        return
    tid = pl.active_big[bi]
    A = pl.pairs[tid][0]
    B = pl.pairs[tid][1]
    o = pair_origin(A, B, x, block_size)  # the pair frame (pair_vertex): the centroids there
    dA = x[A] - o
    dB = x[B] - o
    wv = verts.arm  # each vertex relative to its block's float32 centroid
    slot = pl.slot[tid]
    oslot = pl.oslot[tid]
    sA = vert_start[A]
    cA = vert_count[A]
    sB = vert_start[B]
    cB = vert_count[B]
    hsA = topo.he_start[A]
    hcA = topo.he_count[A]
    hsB = topo.he_start[B]
    hcB = topo.he_count[B]
    n0 = x[B] - x[A]
    if oslot >= 0:
        n0 = prev.normal[oslot]
    if wp.length(n0) < 1.0e-12:
        n0 = wp.vec3(0.0, 0.0, 1.0)
    tie = 1.0e-6 * (block_size[A] + block_size[B] + wp.length(dA) + wp.length(dB))
    fsA = face_start[A]
    fcA = face_count[A]
    fsB = face_start[B]
    fcB = face_count[B]
    n, gap = fcp_plane_coop(wp.normalize(n0), tie, sA, cA, sB, cB, fsA, fcA, fsB, fcB, face_he, wv, dA, dB,
                            vertex_out_he, he_vertex, he_next, he_twin, lane, bd)
    if gap < 0.0 and sat_recheck(oslot, gap, prev.gapb):
        # SAT fallback (narrow_phase, new or jumping contacts only): every face normal, then the edge-pair axes
        n1 = n
        g1 = gap
        for k in range(fcA):
            nf, df = face_plane_of_he(face_he[fsA + k], wv, dA, he_vertex, he_next)
            n1, g1 = try_plane_coop(nf, n1, g1, sA, cA, sB, cB, wv, dA, dB, lane, bd)
        for k in range(fcB):
            nf, df = face_plane_of_he(face_he[fsB + k], wv, dB, he_vertex, he_next)
            n1, g1 = try_plane_coop(nf, n1, g1, sA, cA, sB, cB, wv, dA, dB, lane, bd)
        if (cA + fcA - 2) * (cB + fcB - 2) <= SAT_EDGE_PAIRS:
            # work items: (half-edge of A, half-edge of B) in walk order; a lane tests its item's
            # Minkowski-face condition, the chunk's axes are then tried in item order
            total = hcA * hcB
            c0 = int(0)
            while c0 < total:
                item = c0 + lane
                ok = int(0)
                ax = wp.vec3(0.0, 0.0, 0.0)
                if item < total:
                    h = he_walk[hsA + item // hcB]
                    gg = he_walk[hsB + item % hcB]
                    va = he_vertex[h]
                    ua = he_dest(h, he_vertex, he_next)
                    vb = he_vertex[gg]
                    ub = he_dest(gg, he_vertex, he_next)
                    if va < ua and vb < ub:
                        ea = wv[ua] - wv[va]
                        ax = wp.cross(ea, wv[ub] - wv[vb])
                        if wp.length(ax) > 1.0e-6 * wp.length(ea) * wp.length(wv[ub] - wv[vb]):
                            fa1 = face_normal(h, wv, he_vertex, he_next)
                            fa2 = face_normal(he_twin[h], wv, he_vertex, he_next)
                            fb1 = face_normal(gg, wv, he_vertex, he_next)
                            fb2 = face_normal(he_twin[gg], wv, he_vertex, he_next)
                            if minkowski_edge_face(fa1, fa2, -fb1, -fb2):
                                ok = 1
                t_ok = wp.tile(ok)
                t_ax = wp.tile(ax, preserve_type=True)
                for j in range(bd):
                    if t_ok[j] == 1:
                        n1, g1 = try_plane_coop(t_ax[j], n1, g1, sA, cA, sB, cB, wv, dA, dB, lane, bd)
                c0 += bd
        if g1 > gap + 1.0e-7:
            n, gap = fcp_plane_coop(n1, tie, sA, cA, sB, cB, fsA, fcA, fsB, fcB, face_he, wv, dA, dB,
                                    vertex_out_he, he_vertex, he_next, he_twin, lane, bd)
    if lane == 0:
        cur.normal[slot] = n
        cur.gapb[slot] = gap
        pl.gap[tid] = gap
        cur.nc[slot] = 0
        cur.pstart[slot] = 0
    if gap > 0.0:
        return
    size = wp.min(block_size[A], block_size[B])
    tol = 1.0e-6 * size
    dup_tol = 1.0e-4 * size
    over = -gap
    loA, ilA, hiA, ihA, loB, ilB, hiB, ihB = coop_extents(n, sA, cA, sB, cB, wv, dA, dB, lane, bd, 0)
    nc = int(0)
    px = PointCoord()
    py = PointCoord()
    pz = PointCoord()
    pd = PointCoord()
    pka = PointKey()
    pkb = PointKey()
    # vertices of A inside B, then of B inside A (work items: the vertices)
    for side in range(2):
        s0 = sA
        cnt = cA
        fs = fsB
        fc = fcB
        dv = dA  # the vertices' block's centroid in the pair frame, and the faces'
        dfc = dB
        if side == 1:
            s0 = sB
            cnt = cB
            fs = fsA
            fc = fcA
            dv = dB
            dfc = dA
        c0 = int(0)
        while c0 < cnt:
            k = c0 + lane
            ok = int(0)
            p = wp.vec3(0.0, 0.0, 0.0)
            d = float(0.0)
            if k < cnt:
                pv = pair_vertex(wv, dv, s0 + k)
                if side == 0:
                    if wp.dot(n, pv) >= loB - tol:
                        t_lo, t_hi, hit = column_through(pv, n, fs, fc, face_he, wv, dfc, he_vertex, he_next, tol)
                        if hit == 1:  # the depth in float64 from the arms' hi and lo parts (column_depth)
                            d = wp.min(column_depth(s0 + k, dv, n, fs, fc, face_he, verts, dfc, he_vertex, he_next, 0),
                                       over + tol)
                        if hit == 1 and d > 0.0:
                            ok = 1
                            p = pv + (0.5 * t_lo) * n
                else:
                    if wp.dot(n, pv) <= hiA + tol:
                        t_lo, t_hi, hit = column_through(pv, n, fs, fc, face_he, wv, dfc, he_vertex, he_next, tol)
                        if hit == 1:
                            d = wp.min(column_depth(s0 + k, dv, n, fs, fc, face_he, verts, dfc, he_vertex, he_next, 1),
                                       over + tol)
                        if hit == 1 and d > 0.0:
                            ok = 1
                            p = pv + (0.5 * t_hi) * n
            t_ok = wp.tile(ok)
            t_p = wp.tile(p, preserve_type=True)
            t_d = wp.tile(d)
            for j in range(bd):
                if t_ok[j] == 1:
                    ka = s0 + c0 + j
                    kb = int(-1)
                    if side == 1:
                        kb = ka
                        ka = -1
                    nc, px, py, pz, pd, pka, pkb = add_contact(nc, t_p[j], t_d[j], ka, kb, dup_tol, px, py, pz, pd, pka, pkb)
            c0 += bd
    # edge-edge crossings of the two patches (work items: (half-edge of A, half-edge of B) in walk order)
    t1 = contact_tangent(n)
    t2 = wp.cross(n, t1)
    total = hcA * hcB
    c0 = int(0)
    while c0 < total:
        item = c0 + lane
        ok = int(0)
        p = wp.vec3(0.0, 0.0, 0.0)
        d = float(0.0)
        ha = int(0)
        hb2 = int(0)
        if item < total:
            h = he_walk[hsA + item // hcB]
            g = he_walk[hsB + item % hcB]
            va = he_vertex[h]
            pa = pair_vertex(wv, dA, va)
            vb = he_vertex[g]
            pb = pair_vertex(wv, dB, vb)
            if wp.dot(n, pa) >= loB - tol and wp.dot(n, pb) <= hiA + tol:
                ua = he_dest(h, he_vertex, he_next)
                qa = pair_vertex(wv, dA, ua)
                ub = he_dest(g, he_vertex, he_next)
                qb = pair_vertex(wv, dB, ub)
                if (wp.dot(n, qa) < loB - tol or va < ua) and (wp.dot(n, qb) > hiA + tol or vb < ub):
                    cr, s, u = patch_crossing(va, ua, vb, ub, dA, dB, t1, t2, tol, verts)  # a vertex of the patch (narrow_phase)
                    if cr:
                        xa_ = pa + s * (qa - pa)
                        xb_ = pb + u * (qb - pb)
                        d = wp.min(crossing_depth(va, ua, vb, ub, dA, dB, s, u, n, verts), over + tol)
                        if d > 0.0:
                            ok = 1
                            p = 0.5 * (xa_ + xb_)
                            ha = wp.min(h, he_twin[h])
                            hb2 = wp.min(g, he_twin[g])
        t_ok = wp.tile(ok)
        t_p = wp.tile(p, preserve_type=True)
        t_d = wp.tile(d)
        t_ha = wp.tile(ha)
        t_hb = wp.tile(hb2)
        for j in range(bd):
            if t_ok[j] == 1:
                nc, px, py, pz, pd, pka, pkb = add_contact(nc, t_p[j], t_d[j], t_ha[j], t_hb[j], dup_tol, px, py, pz, pd, pka, pkb)
        c0 += bd
    if lane == 0 and nc > 0:
        base = wp.atomic_add(cur.pcount, 0, nc)
        if base + nc <= cur.pos.shape[0]:
            oA = dA + bodies.x_lo[A]  # A's centroid x + x_lo in the pair frame
            for k in range(nc):
                cur.pos[base + k] = wp.vec3(px[k], py[k], pz[k]) - oA  # relative to A's centroid (contact_forces)
                cur.depth[base + k] = pd[k]
                cur.ckey[base + k] = wp.vec2i(pka[k], pkb[k])
            cur.nc[slot] = nc
            cur.pstart[slot] = base
