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
    grid = _point_grid(proj, valid, z - tol, cell, max_cells)
    candidates = _candidate_triangles(vertices, faces, grid)
    if candidates is None:
        return hidden
    pair_tri, pair_point = _pairs(candidates, grid)
    if len(pair_tri) == 0:
        return hidden
    # barycentric coordinates and inverse depth are affine in the projected position
    x, y = grid["proj"][pair_point, 0], grid["proj"][pair_point, 1]
    c = candidates["affine"]
    b1 = c[0][pair_tri] * x + c[1][pair_tri] * y + c[2][pair_tri]
    b2 = c[3][pair_tri] * x + c[4][pair_tri] * y + c[5][pair_tri]
    inverse_depth = c[6][pair_tri] * x + c[7][pair_tri] * y + c[8][pair_tri]
    eps = -1e-12
    # nearer than the point less its tolerance: 1/z_hit > 1/(z − tol)
    hit = (b1 >= eps) & (b2 >= eps) & (1.0 - b1 - b2 >= eps) & (inverse_depth * grid["near"][pair_point] > 1.0)
    flat_hidden = np.zeros(len(grid["proj"]), dtype=bool)
    flat_hidden[pair_point[hit]] = True
    hidden[valid] = flat_hidden
    return hidden


def _point_grid(proj: np.ndarray, valid: np.ndarray, near: np.ndarray, cell, max_cells: int) -> dict:
    """The valid points binned in a grid over their projections (every frame the same grid):
    their cells, the points sorted by cell, where each cell's points start, how near a surface
    must come in each cell to hide one of them, and a summed-area table of the occupied cells.
    ``near``: (F, P) the depth a surface must be nearer than to hide each point."""
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
    start = np.cumsum(counts) - counts
    near_p = near[valid]
    farthest = np.full(F * ny * nx, -np.inf)  # the farthest such depth in each cell
    filled = np.flatnonzero(counts)
    farthest[filled] = np.maximum.reduceat(near_p[order], start[filled])
    occupied = np.zeros((F, ny + 1, nx + 1), dtype=np.int64)
    occupied[:, 1:, 1:] = (counts.reshape(F, ny, nx) > 0).cumsum(axis=1).cumsum(axis=2)
    return {"proj": p, "near": near_p, "lo": lo, "cell": cell, "nx": nx,
            "ny": ny, "order": order, "counts": counts, "start": start, "farthest": farthest,
            "occupied": occupied, "farthest_of_frame": farthest.reshape(F, -1).max(axis=1)}


def _candidate_triangles(vertices, faces, grid: dict):
    """Triangles in front of the camera, nearer somewhere than the frame's farthest point and over
    an occupied cell: their frame, nearest depth, bounding box of cells and the affine maps from a
    projected position to their barycentric coordinates b1, b2 and inverse depth (9 arrays)."""
    lo, cell, nx, ny = grid["lo"], grid["cell"], grid["nx"], grid["ny"]
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    S = grid["occupied"].reshape(len(vertices), -1)   # summed-area table per frame, flat
    # every frame's vertices in grid units at once, in single precision (a cell's bounds need no more)
    with np.errstate(divide="ignore", invalid="ignore"):
        GX = ((vertices[..., 0] / vertices[..., 2] - lo[0]) / cell).astype(np.float32)
        GY = ((vertices[..., 1] / vertices[..., 2] - lo[1]) / cell).astype(np.float32)
    Z32 = vertices[..., 2].astype(np.float32)
    near_enough = np.float32(1.0 + 1e-6) * grid["farthest_of_frame"]
    tri_all = _triangles_near_grid(GX, GY, Z32, near_enough, faces, nx, ny)
    a, b, c = a[tri_all], b[tri_all], c[tri_all]
    parts = []
    for f in range(len(vertices)):  # one frame at a time: flat takes
        gx, gy, z32 = GX[f], GY[f], Z32[f]
        z_near = np.minimum(np.minimum(z32[a], z32[b]), z32[c])
        xa, xb, xc, ya, yb, yc = gx[a], gx[b], gx[c], gy[a], gy[b], gy[c]
        with np.errstate(invalid="ignore"):
            x0 = np.minimum(np.minimum(xa, xb), xc)
            x1 = np.maximum(np.maximum(xa, xb), xc)
            y0 = np.minimum(np.minimum(ya, yb), yc)
            y1 = np.maximum(np.maximum(ya, yb), yc)
            keep = ((z_near > 0) & (z_near < near_enough[f])
                    & (x1 >= 0) & (x0 < nx) & (y1 >= 0) & (y0 < ny))
        tri = np.flatnonzero(keep)
        x0 = np.clip(x0[tri], 0, nx - 1).astype(np.int64)
        x1 = np.clip(x1[tri], 0, nx - 1).astype(np.int64)
        y0 = np.clip(y0[tri], 0, ny - 1).astype(np.int64)
        y1 = np.clip(y1[tri], 0, ny - 1).astype(np.int64)
        w = nx + 1
        Sf = S[f]
        occupied = Sf[(y1 + 1) * w + x1 + 1] - Sf[y0 * w + x1 + 1] - Sf[(y1 + 1) * w + x0] + Sf[y0 * w + x0]
        over = occupied > 0
        parts.append((np.full(int(over.sum()), f), tri[over], x0[over], x1[over], y0[over], y1[over]))
    frame, tri, x0, x1, y0, y1 = (np.concatenate(p) for p in zip(*parts))
    if len(tri) == 0:
        return None
    A, B, C = a[tri], b[tri], c[tri]
    px = np.empty((3, len(tri)))
    py = np.empty((3, len(tri)))
    iz = np.empty((3, len(tri)))
    for k, corner in enumerate((A, B, C)):
        X = vertices[frame, corner]
        px[k], py[k], iz[k] = X[:, 0] / X[:, 2], X[:, 1] / X[:, 2], 1.0 / X[:, 2]
    return {"frame": frame, "z_near": 1.0 / iz.max(axis=0), "x0": x0, "x1": x1, "y0": y0, "y1": y1,
            "affine": _affine_maps(px, py, iz)}


def _triangles_near_grid(gx, gy, z, near_enough, faces, nx: int, ny: int) -> np.ndarray:
    """Indices of the triangles that can pass the per-frame test of :func:`_candidate_triangles` in
    some frame. A triangle fails it in a frame when all three corners lie on one far side of the
    grid there (left of it, right, below, above, or no nearer than ``near_enough``, the frame's
    farthest point): each vertex gets one bit per side (Cohen–Sutherland outcodes), the bits a
    vertex has in every frame of the chunk are kept, and a triangle whose corners share one is
    dropped for all frames. Only what the per-frame test drops anyway is dropped (the same
    comparisons on the same single-precision values), so the result does not change; the frames'
    passes then take the triangles near the template points alone, not the whole mesh.

    gx, gy, z : (F, V) float32 vertices in grid units and depth; near_enough : (F,)."""
    with np.errstate(invalid="ignore"):  # NaN (a vertex on the camera plane) sets no bit: kept
        sides = ((gx < 0).astype(np.uint8) | ((gx >= nx).astype(np.uint8) << 1) | ((gy < 0).astype(np.uint8) << 2)
                 | ((gy >= ny).astype(np.uint8) << 3) | ((z >= near_enough[:, None]).astype(np.uint8) << 4))
    always = np.bitwise_and.reduce(sides, axis=0)  # (V,) the sides a vertex is on in every frame
    shared = always[faces[:, 0]] & always[faces[:, 1]] & always[faces[:, 2]]
    return np.flatnonzero(shared == 0)


def _affine_maps(px: np.ndarray, py: np.ndarray, iz: np.ndarray) -> list:
    """Per triangle (corners (3, K) in the projection, inverse depths (3, K)): the coefficients
    (a, b, c) of b1 = a x + b y + c, of b2, and of the inverse depth b0/z0 + b1/z1 + b2/z2;
    degenerate (edge-on) triangles get b1 = NaN (they hide nothing)."""
    e1x, e1y, e2x, e2y = px[1] - px[0], py[1] - py[0], px[2] - px[0], py[2] - py[0]
    det = e1x * e2y - e1y * e2x
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(det != 0, 1.0 / det, np.nan)
    a1, b1 = e2y * inv, -e2x * inv
    a2, b2 = -e1y * inv, e1x * inv
    c1 = -(a1 * px[0] + b1 * py[0])
    c2 = -(a2 * px[0] + b2 * py[0])
    d1, d2 = iz[1] - iz[0], iz[2] - iz[0]  # 1/z = iz0 + b1 d1 + b2 d2
    return [a1, b1, c1, a2, b2, c2, a1 * d1 + a2 * d2, b1 * d1 + b2 * d2, iz[0] + c1 * d1 + c2 * d2]


def _pairs(candidates: dict, grid: dict) -> tuple[np.ndarray, np.ndarray]:
    """Every (candidate triangle, point) whose cells meet and where the triangle comes nearer
    than some point of the cell could be hidden: the triangle's bounding box of cells
    enumerated, each cell's points looked up."""
    x0, y0 = candidates["x0"], candidates["y0"]
    w, h = candidates["x1"] - x0 + 1, candidates["y1"] - y0 + 1
    n = w * h
    tri = np.repeat(np.arange(len(n)), n)
    local = np.arange(len(tri)) - np.repeat(np.cumsum(n) - n, n)
    dy, dx = np.divmod(local, w[tri])
    key = (candidates["frame"][tri] * grid["ny"] + y0[tri] + dy) * grid["nx"] + x0[tri] + dx
    useful = candidates["z_near"][tri] < grid["farthest"][key]
    tri, key = tri[useful], key[useful]
    count = grid["counts"][key]
    pair_tri = np.repeat(tri, count)
    offset = np.arange(len(pair_tri)) - np.repeat(np.cumsum(count) - count, count)
    pair_point = grid["order"][np.repeat(grid["start"][key], count) + offset]
    return pair_tri, pair_point


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
