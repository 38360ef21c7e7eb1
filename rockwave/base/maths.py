"""Small vector and quaternion maths on the host (numpy). Quaternions are (x, y, z, w), Warp's order."""

from __future__ import annotations

import math

import numpy as np


def pad3(v) -> list[float]:
    """A 2- or 3-vector as 3 components (z = 0 in 2D)."""
    return list(v) + [0.0] * (3 - len(v))


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion given as (x, y, z, w) (Warp's order)."""
    x, y, z, w = (float(c) for c in q)
    n = np.sqrt(x * x + y * y + z * z + w * w)
    if n == 0:
        raise ValueError("zero quaternion")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_multiply(a, b):
    """Hamilton product a b of quaternions given as (x, y, z, w)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


def euler_xyz_deg_to_quat(angles) -> tuple:
    """Successive turns about the fixed x, then y, then z axes: q = q_z q_y q_x (x, y, z, w)."""
    q = (0.0, 0.0, 0.0, 1.0)
    for axis, deg in zip(np.eye(3), angles):
        h = math.radians(deg) / 2
        q = quat_multiply((*(axis * math.sin(h)), math.cos(h)), q)
    return q


def next_pow2(n: int) -> int:
    """The power of two at or above n, at least 16 (hash-table and bucket sizes)."""
    return 1 << max(4, int(math.ceil(math.log2(max(1, n)))))
