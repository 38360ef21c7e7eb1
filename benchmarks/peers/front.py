"""Dam-break front position measured the same way for rockwave and the peers: the largest x of a
fluid particle that has at least `min_neighbours` other particles within 1.5 spacings (a particle
thrown ahead of the surge does not count). Pure numpy; the SPlisHSPlasH worker imports it by path."""

import numpy as np


def bulk_front(x: np.ndarray, spacing: float, min_neighbours: int = 3, candidates: int = 400) -> float:
    x = np.asarray(x, dtype=np.float64)
    order = np.argsort(-x[:, 0])[:candidates]
    r2 = (1.5 * spacing) ** 2
    for i in order:
        d2 = ((x - x[i]) ** 2).sum(axis=1)
        if int((d2 < r2).sum()) - 1 >= min_neighbours:
            return float(x[i, 0])
    return float(x[order[-1], 0]) if len(order) else float("nan")
