"""Row-wise arithmetic of 3-vectors on large arrays: cross products and lengths.

The same arithmetic as ``np.cross`` and ``np.linalg.norm(..., axis=-1)`` (so the same bits), a
component at a time: without their temporaries and axis shuffles, about twice as quick on the
million-row arrays of a paper-scale face (normals, frames, areas).
"""

from __future__ import annotations

import numpy as np


def cross(a: np.ndarray, b: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """a × b over the last axis (length 3), broadcast; ``out``: where to write it (not ``a`` or ``b``).

    Example
    -------
    >>> cross(np.array([1.0, 0, 0]), np.array([0.0, 1, 0])).tolist()
    [0.0, 0.0, 1.0]
    """
    if out is None:
        out = np.empty(np.broadcast_shapes(np.shape(a), np.shape(b)), dtype=np.result_type(a, b))
    tmp = np.empty(out.shape[:-1], dtype=out.dtype)
    for k in range(3):  # np.cross's order: a1 b2 − a2 b1, a2 b0 − a0 b2, a0 b1 − a1 b0
        i, j = (k + 1) % 3, (k + 2) % 3
        np.multiply(a[..., i], b[..., j], out=out[..., k])
        np.multiply(a[..., j], b[..., i], out=tmp)
        out[..., k] -= tmp
    return out


def lengths(v: np.ndarray, keepdims: bool = False) -> np.ndarray:
    """|v| over the last axis (length 3): sqrt((x² + y²) + z²), ``np.linalg.norm``'s sum.

    Example
    -------
    >>> lengths(np.array([[3.0, 4.0, 0.0]])).tolist()
    [5.0]
    """
    sq = v * v
    out = sq[..., 0:1] + sq[..., 1:2]
    out += sq[..., 2:3]
    np.sqrt(out, out=out)
    return out if keepdims else out[..., 0]
