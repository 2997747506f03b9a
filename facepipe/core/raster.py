"""Triangle coverage: the pixel centres inside triangles, with their barycentric coordinates;
and the UDIM tiles a UV layout's triangles lie on.

Shared by the preview renderer (screen space), the UV rasteriser of the map exports and the
layered textures (texture space).
"""

from __future__ import annotations

import numpy as np

from facepipe.core.runs import offsets_within


def triangle_pixels(p: np.ndarray, ok: np.ndarray, x0: np.ndarray, x1: np.ndarray, y0: np.ndarray,
                    y1: np.ndarray, chunk: int, tolerance: float = 1e-9):
    """The integer pixel centres inside triangles, with their barycentric coordinates.

    Every pixel of each triangle's bounding box is a candidate; candidates are enumerated in
    one flat array (chunks of about ``chunk``), and as barycentric coordinates are affine in
    the pixel position (b1 = a·x + b·y + c, the same for b2) they are computed for all at once.

    Parameters
    ----------
    p : (T, 3, 2) float, corner positions (x, y) in pixels.
    ok : (T,) bool, triangles to scan (not degenerate).
    x0, x1, y0, y1 : (T,) int64, each triangle's bounding box, inclusive, clipped to the image.
    chunk : candidates per chunk (bounded memory).
    tolerance : how far below zero a barycentric coordinate may be on an edge.

    Yields
    ------
    t, row, col : (K,) int64, the triangle and pixel of each covered pixel.
    b0, b1, b2 : (K,) float64, its barycentric coordinates.
    """
    e1 = p[:, 1] - p[:, 0]
    e2 = p[:, 2] - p[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    bw = np.maximum(x1 - x0 + 1, 0)
    counts = np.where(ok, bw * np.maximum(y1 - y0 + 1, 0), 0)
    inv = 1.0 / np.where(ok, det, 1.0)
    c1 = np.stack([e2[:, 1] * inv, -e2[:, 0] * inv], axis=1)
    c2 = np.stack([-e1[:, 1] * inv, e1[:, 0] * inv], axis=1)
    k1 = np.c_[c1, -(c1 * p[:, 0]).sum(axis=1)]
    k2 = np.c_[c2, -(c2 * p[:, 0]).sum(axis=1)]
    bounds = np.searchsorted(np.cumsum(counts), np.arange(0, counts.sum() + chunk, chunk), side="left")
    starts = np.unique(np.r_[0, bounds, p.shape[0]])
    for a, b in zip(starts[:-1], starts[1:]):
        n = counts[a:b]
        if n.sum() == 0:
            continue
        t = np.repeat(np.arange(a, b), n)
        row, col = np.divmod(offsets_within(n), np.repeat(bw[a:b], n))
        col += np.repeat(x0[a:b], n)
        row += np.repeat(y0[a:b], n)
        b1 = k1[t, 0] * col + k1[t, 1] * row + k1[t, 2]
        b2 = k2[t, 0] * col + k2[t, 1] * row + k2[t, 2]
        b0 = 1.0 - b1 - b2
        inside = (b0 >= -tolerance) & (b1 >= -tolerance) & (b2 >= -tolerance)
        yield t[inside], row[inside], col[inside], b0[inside], b1[inside], b2[inside]


def udim_tile_numbers(corner_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """UDIM tile of every triangle (T, 3, 2) from its UV centroid, ``1001 + ⌊u⌋ + 10 ⌊v⌋``, and
    whether the triangle is in the UDIM range (finite, u in [0, 10), v ≥ 0; its tile 0 if not)."""
    centroid = np.asarray(corner_uv, dtype=np.float64).mean(axis=1)
    valid = np.isfinite(centroid).all(axis=1)
    cell = np.floor(np.where(valid[:, None], centroid, 0.0)).astype(np.int64)
    valid &= (cell[:, 0] >= 0) & (cell[:, 0] <= 9) & (cell[:, 1] >= 0)
    return np.where(valid, 1001 + cell[:, 0] + 10 * cell[:, 1], 0), valid


def udim_corner(tile):
    """The UV corner (u₀, v₀) of UDIM tiles (int or array): 1001 is (0, 0), 1002 (1, 0), 1011 (0, 1)."""
    return (tile - 1001) % 10, (tile - 1001) // 10


def edge_padding(covered: np.ndarray, padding: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texels (flat indices) outside ``covered`` (H, W) but within ``padding`` texels of it, the
    covered texel nearest each (flat indices) and their distances: where edge padding takes its
    values from (a bilinear lookup or a mip-map at an island's border reaches beyond it)."""
    from scipy import ndimage  # lazy: only where textures are made

    if not covered.any() or covered.all():
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)
    distance, (ni, nj) = ndimage.distance_transform_edt(~covered, return_indices=True)
    pad = ~covered & (distance <= padding)
    return np.flatnonzero(pad), (ni * covered.shape[1] + nj)[pad], distance[pad]
