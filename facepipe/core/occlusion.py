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
binned in a grid of cells in the projection; the triangles are first culled, once for all the
frames of a call, to those whose bounding box over the frames meets the box of cells of some
group of points (a template's; by default all points are one group); in each frame those not
over any occupied cell are dropped (a summed-area table of the occupied cells), and each
remaining triangle is tested against the points of the cells its bounding box covers. Pure
functions over arrays.
"""

from __future__ import annotations

import numpy as np

from facepipe.core.runs import offsets_within

__all__ = ["occluded_points", "segment_hits"]


def occluded_points(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, tolerance, cell: float | None = None,
                    max_cells: int = 1 << 23, groups: np.ndarray | None = None) -> np.ndarray:
    """Whether each point is hidden from a camera at the origin by the mesh, in every frame.

    Parameters
    ----------
    points : (F, P, 3) camera coordinates (z forward) of points, usually on the mesh's surface.
    vertices : (F, V, 3) the mesh in the same frames and coordinates; faces : (T, 3).
    tolerance : scalar, (P,) or (F, P): a triangle hides a point only where it meets the point's
        ray nearer than the point's depth minus this (a length along z).
    cell : grid cell size in the projection (x/z units); default: about two points per cell.
    max_cells : the grid is coarsened until F × its cells are at most this.
    groups : (P,) optional labels of points that lie together in the image (a template's): the
        triangles are first culled to those over some group's bounding box (in every frame of the
        call), not over the bounding box of all points. Speed only: the answer is the same.

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
    label = np.zeros(P, dtype=np.int64) if groups is None else np.asarray(groups, dtype=np.int64)
    grid["group_boxes"] = _group_cell_boxes(np.broadcast_to(label, (F, P))[valid], grid)
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
    return {"proj": p, "near": near_p, "lo": lo, "cell": cell, "nx": nx, "cx": cx, "cy": cy,
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
    tri_all = _triangles_near_groups(GX, GY, Z32, near_enough, faces, grid["group_boxes"])
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


def _group_cell_boxes(label: np.ndarray, grid: dict) -> np.ndarray:
    """(G, 4) the cells each group of points occupies over all frames: first and last column, first
    and last row (labels (M,) of the grid's valid points)."""
    _, group = np.unique(label, return_inverse=True)
    G = int(group.max()) + 1
    boxes = np.empty((G, 4), dtype=np.int64)
    for k, cells in enumerate((grid["cx"], grid["cy"])):
        boxes[:, 2 * k] = np.full(G, np.iinfo(np.int64).max)
        np.minimum.at(boxes[:, 2 * k], group, cells)
        boxes[:, 2 * k + 1] = np.full(G, np.iinfo(np.int64).min)
        np.maximum.at(boxes[:, 2 * k + 1], group, cells)
    return boxes


def _triangles_near_groups(gx, gy, z, near_enough, faces, boxes) -> np.ndarray:
    """Indices of the triangles that can pass the per-frame test of :func:`_candidate_triangles` in
    some frame: those whose bounding box in grid units, over all frames, meets some group's box of
    cells (``boxes`` (G, 4) from :func:`_group_cell_boxes`; every occupied cell lies in one), and
    that come nearer than ``near_enough`` (F,) (the frame's farthest point) in some frame. A
    triangle dropped here would be dropped by the per-frame test in every frame (the same
    comparisons of the same single-precision values against whole cells), so the answer does
    not change; the per-frame passes then take the triangles near the points, not the whole mesh.
    A vertex with a NaN coordinate (on the camera plane) keeps its triangles (the comparisons
    are written so that NaN fails them).

    gx, gy, z : (F, V) float32 vertices in grid units and depth."""
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    lo_x, hi_x, lo_y, hi_y = gx.min(axis=0), gx.max(axis=0), gy.min(axis=0), gy.max(axis=0)
    x0 = np.minimum(np.minimum(lo_x[a], lo_x[b]), lo_x[c])
    x1 = np.maximum(np.maximum(hi_x[a], hi_x[b]), hi_x[c])
    y0 = np.minimum(np.minimum(lo_y[a], lo_y[b]), lo_y[c])
    y1 = np.maximum(np.maximum(hi_y[a], hi_y[b]), hi_y[c])
    near = np.zeros(len(faces), dtype=bool)
    for bx0, bx1, by0, by1 in boxes:
        near |= ~((x1 < bx0) | (x0 >= bx1 + 1) | (y1 < by0) | (y0 >= by1 + 1))
    far = (z >= near_enough[:, None]).all(axis=0)  # (V,) no nearer than the frame's farthest point in any frame
    near &= ~(far[a] & far[b] & far[c])
    return np.flatnonzero(near)


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
    local = offsets_within(n)
    dy, dx = np.divmod(local, w[tri])
    key = (candidates["frame"][tri] * grid["ny"] + y0[tri] + dy) * grid["nx"] + x0[tri] + dx
    useful = candidates["z_near"][tri] < grid["farthest"][key]
    tri, key = tri[useful], key[useful]
    count = grid["counts"][key]
    pair_tri = np.repeat(tri, count)
    offset = offsets_within(count)
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
