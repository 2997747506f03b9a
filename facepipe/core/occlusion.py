"""Which points on a mesh a pinhole camera sees: each point's ray cast against the mesh's triangles.

A point on the surface is hidden when a triangle crosses the segment from the camera centre to it
nearer than the point itself (by more than a tolerance: the point's own triangle, and its
neighbours where the surface curves, meet the ray at the point). Under a perspective projection
a triangle stays a triangle, so a triangle crosses a point's ray exactly when the point's
projection (x/z, y/z) lies in the triangle's projection, and it does so at the depth
1 / (b0/z0 + b1/z1 + b2/z2) of the projected barycentric coordinates: the ray cast is exact, in
the ideal pinhole image (lens distortion moves where a ray lands on the sensor, not which surface
it meets first).

Only pairs of a point and a triangle whose projections can meet are tested: the points are
binned in a grid of cells in the projection, triangles not over any occupied cell are dropped at
once (a summed-area table of the occupied cells), and each remaining triangle is tested against
the points of the cells its bounding box covers. Pure functions over arrays.
"""

from __future__ import annotations

import numpy as np

__all__ = ["occluded_points", "segment_hits"]


def occluded_points(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, tolerance, cell: float | None = None,
                    max_cells: int = 1 << 23) -> np.ndarray:
    """Whether each point is hidden from a camera at the origin by the mesh, in every frame.

    Parameters
    ----------
    points : (F, P, 3) camera coordinates (z forward) of points, usually on the mesh's surface.
    vertices : (F, V, 3) the mesh in the same frames and coordinates; faces : (T, 3).
    tolerance : scalar, (P,) or (F, P): a triangle hides a point only where it meets the point's
        ray nearer than the point's depth minus this (a length along z).
    cell : grid cell size in the projection (x/z units); default: about two points per cell.
    max_cells : the grid is coarsened until F × its cells are at most this.

    Returns
    -------
    (F, P) bool. Points at or behind the camera (z ≤ 0) are not called hidden (they are not in
    view at all: the caller tells that apart); triangles with a corner at or behind the camera
    plane are left out.
    """
    points = np.asarray(points, dtype=np.float64)
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    F, P = points.shape[:2]
    hidden = np.zeros((F, P), dtype=bool)
    z = points[..., 2]
    valid = np.isfinite(points).all(axis=-1) & (z > 0)
    if not valid.any() or len(faces) == 0:
        return hidden
    tol = np.broadcast_to(np.asarray(tolerance, dtype=np.float64), (F, P))
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = points[..., :2] / z[..., None]
    grid = _point_grid(proj, valid, cell, max_cells)
    candidates = _candidate_triangles(vertices, faces, grid, np.where(valid, z, -np.inf).max(axis=1))
    if candidates is None:
        return hidden
    frame, tri, tp, tz = candidates
    pair_tri, pair_point = _pairs(frame, tp, grid)
    if len(pair_tri) == 0:
        return hidden
    b = _barycentric(tp[pair_tri], grid["proj"][pair_point])
    inside = (b >= -1e-12).all(axis=-1)
    with np.errstate(divide="ignore"):
        z_hit = 1.0 / (b * (1.0 / tz[pair_tri])).sum(axis=-1)
    flat_z, flat_tol = z[valid], tol[valid]
    hit = inside & (z_hit < flat_z[pair_point] - flat_tol[pair_point])
    flat_hidden = np.zeros(len(flat_z), dtype=bool)
    flat_hidden[pair_point[hit]] = True
    hidden[valid] = flat_hidden
    return hidden


def _point_grid(proj: np.ndarray, valid: np.ndarray, cell, max_cells: int) -> dict:
    """The valid points binned in a grid over their projections (every frame the same grid):
    cell of each, the points sorted by cell, and where each cell's points start."""
    F = proj.shape[0]
    frame = np.broadcast_to(np.arange(F)[:, None], valid.shape)[valid]
    p = proj[valid]
    lo, hi = p.min(axis=0), p.max(axis=0)
    extent = np.maximum(hi - lo, 1e-12)
    if cell is None:  # about two points per cell were they spread evenly over their bounding box
        cell = float(np.sqrt(2.0 * extent[0] * extent[1] * F / len(p)))
    cell = max(float(cell), 1e-12)
    while F * (int(extent[0] / cell) + 1) * (int(extent[1] / cell) + 1) > max_cells:
        cell *= 1.5
    nx, ny = int(extent[0] / cell) + 1, int(extent[1] / cell) + 1
    cx = np.minimum(((p[:, 0] - lo[0]) / cell).astype(np.int64), nx - 1)
    cy = np.minimum(((p[:, 1] - lo[1]) / cell).astype(np.int64), ny - 1)
    key = (frame * ny + cy) * nx + cx
    order = np.argsort(key, kind="stable")
    counts = np.bincount(key, minlength=F * ny * nx)
    occupied = np.zeros((F, ny + 1, nx + 1), dtype=np.int64)
    occupied[:, 1:, 1:] = (counts.reshape(F, ny, nx) > 0).cumsum(axis=1).cumsum(axis=2)
    return {"proj": p, "lo": lo, "cell": cell, "nx": nx, "ny": ny, "order": order, "counts": counts,
            "start": np.cumsum(counts) - counts, "occupied": occupied}


def _cell_box(tp: np.ndarray, grid: dict) -> tuple:
    """Each projected triangle's bounding box in cells, clipped to the grid, and whether it meets it."""
    lo, cell, nx, ny = grid["lo"], grid["cell"], grid["nx"], grid["ny"]
    x0 = np.floor((tp[..., 0].min(axis=-1) - lo[0]) / cell)
    x1 = np.floor((tp[..., 0].max(axis=-1) - lo[0]) / cell)
    y0 = np.floor((tp[..., 1].min(axis=-1) - lo[1]) / cell)
    y1 = np.floor((tp[..., 1].max(axis=-1) - lo[1]) / cell)
    meets = (x1 >= 0) & (x0 <= nx - 1) & (y1 >= 0) & (y0 <= ny - 1)
    clip = lambda a, n: np.clip(a, 0, n - 1).astype(np.int64)  # noqa: E731
    return clip(x0, nx), clip(x1, nx), clip(y0, ny), clip(y1, ny), meets


def _candidate_triangles(vertices, faces, grid: dict, farthest: np.ndarray):
    """Triangles (in front of the camera, nearer somewhere than the frame's farthest point, over an
    occupied cell): their frame, index, projected corners (K, 3, 2) and corner depths (K, 3)."""
    corners = vertices[:, faces]  # (F, T, 3, 3)
    cz = corners[..., 2]
    front = (cz > 1e-12 * np.abs(cz).max()).all(axis=-1) & (cz.min(axis=-1) < farthest[:, None])
    with np.errstate(divide="ignore", invalid="ignore"):
        tp = corners[..., :2] / cz[..., None]
    tp = np.where(front[..., None, None], tp, 0.0)
    x0, x1, y0, y1, meets = _cell_box(tp, grid)
    S = grid["occupied"]
    f = np.arange(len(vertices))[:, None]
    occupied = S[f, y1 + 1, x1 + 1] - S[f, y0, x1 + 1] - S[f, y1 + 1, x0] + S[f, y0, x0]
    keep = front & meets & (occupied > 0)
    if not keep.any():
        return None
    frame, tri = np.nonzero(keep)
    return frame, tri, tp[frame, tri], cz[frame, tri]


def _pairs(frame: np.ndarray, tp: np.ndarray, grid: dict) -> tuple[np.ndarray, np.ndarray]:
    """Every (candidate triangle, point) whose cells meet: the triangle's bounding box of cells
    enumerated, each cell's points looked up."""
    x0, x1, y0, y1, _ = _cell_box(tp, grid)
    w, h = x1 - x0 + 1, y1 - y0 + 1
    n = w * h
    tri = np.repeat(np.arange(len(tp)), n)
    local = np.arange(len(tri)) - np.repeat(np.cumsum(n) - n, n)
    dy, dx = np.divmod(local, w[tri])
    key = (frame[tri] * grid["ny"] + y0[tri] + dy) * grid["nx"] + x0[tri] + dx
    count = grid["counts"][key]
    tri, key, count = tri[count > 0], key[count > 0], count[count > 0]
    pair_tri = np.repeat(tri, count)
    offset = np.arange(len(pair_tri)) - np.repeat(np.cumsum(count) - count, count)
    pair_point = grid["order"][np.repeat(grid["start"][key], count) + offset]
    return pair_tri, pair_point


def _barycentric(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (N, 3) of 2D points (N, 2) in triangles (N, 3, 2); NaN where degenerate."""
    e1, e2, d = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], p - tri[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        b1 = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / det
        b2 = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / det
    return np.stack([1.0 - b1 - b2, b1, b2], axis=1)


def segment_hits(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, tolerance) -> np.ndarray:
    """The same question answered by brute force (every point's ray against every triangle, the
    Möller–Trumbore intersection in 3D): (P,) bool for one frame's points (P, 3) and mesh (V, 3).
    For checks and small meshes; memory P × T."""
    points = np.asarray(points, dtype=np.float64)
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]  # (T, 3, 3)
    a = corners[:, 0]
    e1, e2 = corners[:, 1] - a, corners[:, 2] - a
    d = points[:, None, :]                              # ray direction: the point itself (t = 1 at it)
    pvec = np.cross(d, e2[None])                        # (P, T, 3)
    det = (pvec * e1[None]).sum(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        tvec = -a[None]                                  # ray origin (0) − a
        u = (tvec * pvec).sum(axis=-1) * inv
        qvec = np.cross(tvec, e1[None])
        v = (d * qvec).sum(axis=-1) * inv
        t = (e2[None] * qvec).sum(axis=-1) * inv
    ok = (np.abs(det) > 1e-300) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    z_hit = t * points[:, None, 2]
    tol = np.broadcast_to(np.asarray(tolerance, dtype=np.float64), points.shape[:1])
    return (ok & (z_hit < points[:, None, 2] - tol[:, None])).any(axis=1)
