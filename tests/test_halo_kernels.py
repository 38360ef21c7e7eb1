"""The halo and migration kernels of the slab decomposition (kernels/sim/distributed.py) on one process: packed
rows unpack to the same particles (round trip, global ids beyond float32's 2^24 included), the slab
classification and its compaction agree with numpy, and the host transport moves a buffer intact (to itself over
MPI_COMM_SELF)."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from rockwave.kernels.sim import distributed as kd

D = "cpu"


def _particles(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1.0, 1.0, (n, 3)).astype(np.float32)
    v = rng.normal(0.0, 1.0, (n, 3)).astype(np.float32)
    rho = rng.uniform(990.0, 1010.0, n).astype(np.float32)
    a = rng.normal(0.0, 10.0, (n, 3)).astype(np.float32)
    p = rng.uniform(-50.0, 5000.0, n).astype(np.float32)
    gid = rng.choice(np.array([0, 1, 2**24 + 1, 2**31 - 1, 123456789, 2**20, 2**20 - 1], np.int64), n).astype(np.int32)
    return x, v, rho, a, p, gid


def _wp(a, dtype):
    return wp.array(a, dtype=dtype, device=D)


def test_unpack_by_id_writes_each_row_to_its_ids_slot():
    """Rank 0's gather (kd.unpack_by_id): rows in any order land in the slots of their ids (ids beyond 2^20, split
    in two float32 parts), seen counts each id's rows (a doubled row: 2, a lost one: 0), an id beyond n is dropped."""
    n = 2**20 + 8
    x, v, rho, a, p, _ = _particles(6, seed=3)
    gid = np.array([2**20 + 7, 5, 2**20 - 1, 0, 5, n + 3], np.int32)  # 5 twice; n + 3 out of range
    src = [_wp(x, wp.vec3), _wp(v, wp.vec3), _wp(rho, float), _wp(a, wp.vec3), _wp(p, float), _wp(gid, int)]
    buf = wp.zeros((6, kd.FULL_COLS), dtype=float, device=D)
    wp.launch(kd.pack_full, 6, [_wp(np.arange(6, dtype=np.int32), int), src[5], *src[:5], buf], device=D)
    dst = [wp.zeros(n, dtype=t, device=D) for t in (wp.vec3, wp.vec3, float, wp.vec3, float, int)]
    seen = wp.zeros(n, dtype=int, device=D)
    wp.launch(kd.unpack_by_id, 6, [buf, n, *dst, seen], device=D)
    for k in (0, 2, 3):
        i = gid[k]
        for s, d in zip((x, v, rho, a, p), dst[:5]):
            assert np.array_equal(d.numpy()[i], s[k])
        assert dst[5].numpy()[i] == i
    got = seen.numpy()
    assert got[5] == 2 and got[[2**20 + 7, 2**20 - 1, 0]].tolist() == [1, 1, 1] and got.sum() == 5


def test_pack_unpack_round_trip():
    n, off = 37, 5
    x, v, rho, a, p, gid = _particles(n)
    idx = np.array([3, 0, 36, 17, 17, 8], np.int32)  # any slots, in any order, repeats allowed
    src = [_wp(x, wp.vec3), _wp(v, wp.vec3), _wp(rho, float), _wp(a, wp.vec3), _wp(p, float), _wp(gid, int)]
    k = len(idx)
    # the full rows (migration, new halos)
    buf = wp.zeros((k, kd.FULL_COLS), dtype=float, device=D)
    wp.launch(kd.pack_full, k, [_wp(idx, int), src[5], *src[:5], buf], device=D)
    m = off + k
    dst = [wp.zeros(m, dtype=wp.vec3, device=D), wp.zeros(m, dtype=wp.vec3, device=D), wp.zeros(m, dtype=float, device=D),
           wp.zeros(m, dtype=wp.vec3, device=D), wp.zeros(m, dtype=float, device=D), wp.zeros(m, dtype=int, device=D)]
    wp.launch(kd.unpack_full, k, [buf, off, dst[5], *dst[:5]], device=D)
    for s, d in zip((x, v, rho, a, p, gid), dst):
        assert np.array_equal(d.numpy()[off:], s[idx])  # bit for bit, ids above 2^24 too
        assert not np.any(d.numpy()[:off])  # slots before the offset untouched
    # the per-step halo rows (x, v, rho) and the halo densities (rho, p, p/rho^2)
    hb = wp.zeros((k, kd.HALO_COLS), dtype=float, device=D)
    wp.launch(kd.pack_halo, k, [_wp(idx, int), src[0], src[1], src[2], hb], device=D)
    hx, hv, hr = (wp.zeros(m, dtype=t, device=D) for t in (wp.vec3, wp.vec3, float))
    wp.launch(kd.unpack_halo, k, [hb, off, hx, hv, hr], device=D)
    assert np.array_equal(hx.numpy()[off:], x[idx]) and np.array_equal(hv.numpy()[off:], v[idx])
    assert np.array_equal(hr.numpy()[off:], rho[idx])
    pr2 = (p / rho**2).astype(np.float32)
    db = wp.zeros((k, kd.DENS_COLS), dtype=float, device=D)
    wp.launch(kd.pack_densities, k, [_wp(idx, int), src[2], src[4], _wp(pr2, float), db], device=D)
    out = [wp.zeros(m, dtype=float, device=D) for _ in range(3)]
    wp.launch(kd.unpack_densities, k, [db, off, *out], device=D)
    for s, d in zip((rho, p, pr2), out):
        assert np.array_equal(d.numpy()[off:], s[idx])


@pytest.mark.parametrize("lo, hi", [(-0.3, 0.4), (-3.0e38, 0.1), (0.2, 3.0e38)])
def test_classify_and_compaction_match_numpy(lo, hi):
    n, halo, axis = 500, 0.15, 1
    x = _particles(n, seed=3)[0]
    flags = [wp.zeros(n, dtype=int, device=D) for _ in range(5)]
    wp.launch(kd.classify, n, [_wp(x, wp.vec3), axis, lo, hi, halo, *flags], device=D)
    c = x[:, axis]
    lo32, hi32 = np.float32(lo), np.float32(hi)
    expect = [(c >= lo32) & (c < hi32), c < lo32, c >= hi32, c < lo32 + np.float32(halo), c >= hi32 - np.float32(halo)]
    for f, e in zip(flags, expect):
        assert np.array_equal(f.numpy().astype(bool), e)
        pos = wp.zeros(n, dtype=int, device=D)
        wp.utils.array_scan(f, pos, inclusive=False)
        out = wp.zeros(int(e.sum()), dtype=int, device=D)
        wp.launch(kd.scatter_flagged, n, [f, pos, out], device=D)
        assert np.array_equal(out.numpy(), np.flatnonzero(e))  # the flagged slots, in order


def test_host_transport_moves_buffers_intact():
    """HostTransport (the CPU path): a rank sending to itself over MPI_COMM_SELF gets its rows back bit for bit."""
    MPI = pytest.importorskip("mpi4py.MPI", reason="needs mpi4py (pip install 'rockwave[mpi]')")
    from rockwave.sim.transport import make_transport

    t = make_transport("auto", MPI.COMM_SELF, D)
    assert t.name == "host"
    rows = np.random.default_rng(5).normal(size=(11, kd.HALO_COLS)).astype(np.float32)
    send = wp.array(rows, dtype=float, device=D)
    recv = wp.zeros((11, kd.HALO_COLS), dtype=float, device=D)
    t.exchange([(0, send, recv), (None, None, None)])
    assert np.array_equal(recv.numpy(), rows)
    with pytest.raises(ValueError, match="CUDA device"):
        make_transport("cuda-mpi", MPI.COMM_SELF, D)


def test_balanced_faces_follow_the_ranks_speeds():
    """The load balance's new faces (rockwave/sim/distributed.py balanced_faces): water spread evenly over [0, 1];
    a rank twice as fast as its neighbour gets twice the particles; a face moves at most half way to the next
    face (particles go to a neighbour only); no slab narrower than the halo."""
    from rockwave.sim.distributed import balanced_faces

    hist = np.full(1000, 10)
    two = np.array([-np.inf, 0.5, np.inf])
    assert balanced_faces(hist, 0.0, 1.0, np.array([0.5, 0.5]), two, 0.05)[1] == pytest.approx(0.5, abs=1e-3)
    speed = np.array([500.0, 500.0]) / np.array([2.0, 1.0])  # particles per compute second: rank 1 twice as fast
    f = balanced_faces(hist, 0.0, 1.0, speed / speed.sum(), two, 0.05)
    assert f[1] == pytest.approx(1.0 / 3.0, abs=1e-3) and f[1] == np.float32(f[1])  # float32 faces
    assert balanced_faces(hist, 0.0, 1.0, np.array([0.1, 0.9]), two, 0.05)[1] == pytest.approx(0.25)  # half way
    three = np.array([-np.inf, 1.0 / 3.0, 2.0 / 3.0, np.inf])
    f = balanced_faces(hist, 0.0, 1.0, np.array([0.2, 0.6, 0.2]), three, 0.1)
    assert f[1:3] == pytest.approx([0.2, 0.8], abs=1e-3)
    assert balanced_faces(hist, 0.0, 1.0, np.array([0.2, 0.6, 0.2]), three, 0.7) is None  # middle slab < halo
