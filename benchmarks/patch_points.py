"""Contact points that appear without history in a resting jointed mass (issue 36): the flicker of a patch's points.

The jointed mass of benchmarks/jointed_mass.py (``jointed_sim``, friction 22 deg on the 20 deg base, plain start) is
run ``--at`` s, then ``--steps`` block steps one by one. After each, every contact point of the step's table is
matched to last step's points of its pair as contact_forces matches history: by feature key, else the nearest
unclaimed point within dup_tol = 1e-4 x the block size in the contact plane. A point with neither appears without
history; one that appears with a normal force above ``--force`` N appeared at a depth (not by closing): a step in
force of k_n x depth. Reports those per second, by feature (vertex of A, vertex of B, edge crossing) and the pairs
where they appear most (docs/notes.md 'A patch of two flush faces'). The tables are read back every step: a CPU
diagnostic at small size, not a GPU benchmark.

    python -m benchmarks.patch_points --size 20 10 2 --at 2 --steps 200     # ~1-2 min on one free core
"""

from __future__ import annotations

import argparse
import collections

import numpy as np


def table_points(state) -> dict:
    """This step's contact points (BlockState.tables[0]) per pair key: feature keys, positions (relative to the first
    block's centroid), normal forces, the pair's normal."""
    t = state.tables[0]
    keys, nc, ps = t["keys"].numpy(), t["nc"].numpy(), t["pstart"].numpy()
    ck, pos, fn, nrm = t["ckey"].numpy(), t["pos"].numpy(), t["fn"].numpy(), t["normal"].numpy()
    return {int(keys[s]): (ck[ps[s]:ps[s] + nc[s]].copy(), pos[ps[s]:ps[s] + nc[s]].copy(), fn[ps[s]:ps[s] + nc[s]].copy(), nrm[s].copy())
            for s in np.nonzero((keys >= 0) & (nc > 0))[0]}


def new_points(prev: dict, cur: dict, dup_tol: float) -> list:
    """(pair key, feature, normal force) of every point of ``cur`` without history in ``prev`` (key, then position)."""
    out = []
    for key, (ck, pos, fn, nrm) in cur.items():
        hist = [-1] * len(fn)
        o = prev.get(key)
        if o is not None:
            claimed = set()
            for k in range(len(fn)):
                for m in range(len(o[0])):
                    if tuple(o[0][m]) == tuple(ck[k]):
                        hist[k] = m
                        claimed.add(m)
            for k in range(len(fn)):
                if hist[k] < 0:
                    best, bm = dup_tol, -1
                    for m in range(len(o[0])):
                        if m not in claimed:
                            dp = pos[k] - o[1][m]
                            dl = float(np.linalg.norm(dp - dp.dot(nrm) * nrm))
                            if dl < best:
                                best, bm = dl, m
                    if bm >= 0:
                        hist[k] = bm
                        claimed.add(bm)
        for k in range(len(fn)):
            if hist[k] < 0:
                a, b = int(ck[k][0]), int(ck[k][1])
                out.append((key, "crossing" if a >= 0 and b >= 0 else ("vertex of A" if a >= 0 else "vertex of B"), float(fn[k])))
    return out


def run(device: str, size, at: float, steps: int, force: float, kn: float = 1.0e7) -> dict:
    from benchmarks.jointed_mass import jointed_sim

    sim = jointed_sim(device, 22.0, tuple(size), kn)
    sim.advance(at)
    st = sim.block_state
    nb = st.model.num_blocks
    dup_tol = 1.0e-4 * float(np.min(st.model.topology.block_size.numpy()[1:]))  # narrow_phase's, for the cubes
    prev = table_points(st)
    npts, new = 0, []
    for _ in range(steps):
        sim.step()
        cur = table_points(st)
        npts += sum(len(v[2]) for v in cur.values())
        new += new_points(prev, cur, dup_tol)
        prev = cur
    span = steps * sim.dt
    big = [p for p in new if p[2] > force]
    return dict(size=list(size), at_s=at, steps=steps, span_s=span, points_per_step=npts / steps,
                new_per_s=len(new) / span, new_above_force_per_s=len(big) / span, force_n=force,
                by_feature=dict(collections.Counter(p[1] for p in big)),
                by_pair=[[k // nb, k % nb, c] for k, c in collections.Counter(p[0] for p in big).most_common(8)])


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.patch_points", description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, nargs=3, default=[20, 10, 2])
    ap.add_argument("--at", type=float, default=2.0, help="s of simulated time before counting")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--force", type=float, default=10.0, help="N: a new point above this appeared at a depth")
    a = ap.parse_args()
    import warp as wp

    wp.config.quiet = True
    r = run(a.device, a.size, a.at, a.steps, a.force)
    print(f"{r['size']} at {r['at_s']:g} s, {r['steps']} steps ({r['span_s']:.4f} s): {r['points_per_step']:.0f} points per step, "
          f"{r['new_per_s']:.0f} new per s, {r['new_above_force_per_s']:.0f} per s above {r['force_n']:g} N "
          f"{r['by_feature']}; pairs (A, B, count): {r['by_pair']}")


if __name__ == "__main__":
    main()
