"""Where an appearance model's points lie on the animated surface, and what the camera sees of them.

The rest mesh's UV layout is rasterised once (:func:`texel_map`: every texel's triangle and
barycentric coordinates) and a region's template points located in it (:func:`locate_uv`,
:func:`template_points`), so that in every frame they sit at fixed barycentric coordinates on the
animated surface (:func:`template_positions`), shifted diagonally by half a grid step for the
offset samples. A frame is sampled at them (:func:`sample_template_frames`) or unwrapped into
texture space (:func:`unwrap`) through its geometry and the camera; whether the camera sees a
point — in the image, not hidden by the face (ray cast), facing it well enough and away from
what it does not see — is :func:`sample_template_frames`' and :func:`well_seen_points`' answer,
and whether it sees a texel, one that faces it and whose pixels show its own surface (z-buffer),
:func:`unwrap`'s.
"""

from __future__ import annotations

import numpy as np

from facepipe.core import appearance as ap
from facepipe.core.camera import Camera, project_distorted, project_distorted_fast
from facepipe.core.occlusion import occluded_points
from facepipe.core.raster import triangle_pixels, udim_corner
from facepipe.core.render import rasterize
from facepipe.core.tangent_frames import vertex_face_matrix, vertex_normals
from facepipe.errors import InputError
from facepipe.io.appearance_file import AppearanceModel

__all__ = ["texel_map", "locate_uv", "unwrap", "template_points", "region_template", "template_positions",
           "sample_template_frames", "seen_fraction", "well_seen_points", "point_facing", "point_normals",
           "frame_facing_limits"]


def texel_map(corner_uv: np.ndarray, size: int, tile: int = 1001) -> tuple[np.ndarray, np.ndarray]:
    """Every texel's triangle (size, size) (−1: none) and barycentric coordinates (size, size, 3)
    on the UDIM ``tile`` (1001: u, v in 0–1; 1002: u in 1–2; 1011: v in 1–2).

    Texel (i, j) has its centre at UV (u₀ + (j + ½)/size, v₀ + 1 − (i + ½)/size) (row 0 at the
    tile's top), u₀, v₀ the tile's corner.
    """
    if tile != 1001:
        corner_uv = corner_uv - np.asarray(udim_corner(tile), dtype=corner_uv.dtype)
    p = np.stack([corner_uv[..., 0] * size - 0.5, (1.0 - corner_uv[..., 1]) * size - 0.5], axis=-1)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    ok = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) > 1e-12
    x0 = np.clip(np.ceil(p[..., 0].min(1)), 0, size).astype(np.int64)
    x1 = np.clip(np.floor(p[..., 0].max(1)), -1, size - 1).astype(np.int64)
    y0 = np.clip(np.ceil(p[..., 1].min(1)), 0, size).astype(np.int64)
    y1 = np.clip(np.floor(p[..., 1].max(1)), -1, size - 1).astype(np.int64)
    face = np.full((size, size), -1, dtype=np.int64)
    bary = np.zeros((size, size, 3))
    for t, row, col, b0, b1, b2 in triangle_pixels(p, ok, x0, x1, y0, y1, 1 << 22):
        face[row, col] = t
        bary[row, col] = np.stack([b0, b1, b2], axis=1)
    return face, bary


def locate_uv(points: np.ndarray, corner_uv: np.ndarray, candidates: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """The triangle (N,) (−1 where none) and barycentric coordinates (N, 3) of UV points (N, 2)."""
    from scipy.spatial import cKDTree  # SciPy's import cost only where a model is built

    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    centres = corner_uv.mean(axis=1)
    k = min(candidates, len(centres))
    _, near = cKDTree(centres).query(points, k=k)
    face, bary = _first_containing(points, corner_uv, near.reshape(len(points), k))
    # a point in a long sliver (a card's fan around its centre) may lie in none of the triangles
    # with the nearest centroids: those are searched among every triangle whose box holds them
    low, high = corner_uv.min(axis=1), corner_uv.max(axis=1)
    for i in np.flatnonzero(face < 0):
        boxed = np.flatnonzero(((low <= points[i] + 1e-9) & (points[i] - 1e-9 <= high)).all(axis=1))
        if len(boxed):
            f, b = _first_containing(points[i:i + 1], corner_uv, boxed[None])
            face[i], bary[i] = f[0], b[0]
    return face, bary


def _first_containing(points: np.ndarray, corner_uv: np.ndarray, near: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Of each point's candidate triangles (N, k), the first that holds it (−1: none), and its
    barycentric coordinates there."""
    a, b, c = (corner_uv[near, i] for i in range(3))  # (N, k, 2)
    e1, e2, d = b - a, c - a, points[:, None] - a
    det = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        b1 = (d[..., 0] * e2[..., 1] - d[..., 1] * e2[..., 0]) / det
        b2 = (e1[..., 0] * d[..., 1] - e1[..., 1] * d[..., 0]) / det
        b0 = 1 - b1 - b2
    inside = (np.abs(det) > 1e-14) & (b0 >= -1e-9) & (b1 >= -1e-9) & (b2 >= -1e-9)
    first = np.argmax(inside, axis=1)
    rows = np.arange(len(points))
    found = inside[rows, first]
    face = np.where(found, near[rows, first], -1)
    bary = np.stack([b0[rows, first], b1[rows, first], b2[rows, first]], axis=1)
    return face, np.where(found[:, None], bary, 0.0)


def surface_points(camera_positions: np.ndarray, faces: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Points (..., 3) at fixed barycentric coordinates on the posed triangles."""
    return np.einsum("...k,...kc->...c", bary, camera_positions[faces[face]])


def triangle_normals(camera_positions: np.ndarray, faces: np.ndarray, face: np.ndarray) -> np.ndarray:
    p = camera_positions[faces[face]]
    return np.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :])


#: how far from a texel's point the surface a pixel shows may lie for the pixel to show that texel,
#: in pixels' footprints at the point's depth over the cosine the camera sees it at: a bilinear
#: sample reads pixels up to one pixel away along x and y (√2 along the diagonal), and a surface
#: seen at cosine c moves 1/c as far along itself per pixel
FOOTPRINT_REACH = 2.0


def unwrap(image: np.ndarray, camera_positions: np.ndarray, faces: np.ndarray, texel_face: np.ndarray,
           texel_bary: np.ndarray, camera: Camera, rows=slice(None), cols=slice(None), min_facing: float = 0.2,
           normal_sign: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A frame's colours in texture space over texels [rows, cols]: (h, w, 3) and where seen (h, w).

    A texel is seen where it faces the camera (cosine above ``min_facing``), projects into the
    image, and each of the four pixels its bilinear sample reads shows its own surface
    (:func:`pixels_show_points`): not a lip, lid or nose in front of it, nor the background or
    the mouth's inside beside its edge, whose colours would otherwise be taken for its own."""
    tf = texel_face[rows, cols]
    tb = texel_bary[rows, cols]
    covered = tf >= 0
    out = np.zeros(tf.shape + (3,))
    seen = np.zeros(tf.shape, dtype=bool)
    if not covered.any():
        return out, seen
    X = surface_points(camera_positions, faces, tf[covered], tb[covered])
    cos = normal_sign * ap.facing(triangle_normals(camera_positions, faces, tf[covered]), X)
    pixels = project_distorted(camera, X)
    values, inside = ap.bilinear_sample(image, pixels)
    out[covered] = values
    candidate = inside & (cos > min_facing)
    if candidate.any():
        candidate[candidate] = pixels_show_points(X[candidate], cos[candidate], pixels[candidate], camera_positions,
                                                  faces, camera, image.shape[:2], min_facing)
    seen[covered] = candidate
    return out, seen


def pixels_show_points(points: np.ndarray, cos: np.ndarray, pixels: np.ndarray, camera_positions: np.ndarray,
                       faces: np.ndarray, camera: Camera, image_shape: tuple, min_facing: float) -> np.ndarray:
    """(N,) whether each of the four pixels a bilinear sample at ``pixels`` (N, 2) (inside the image)
    reads shows the surface near the camera-space point (N, 3) it samples: the nearest surface of the
    posed mesh (V, 3) there, a z-buffer over the window of the image the points cover, lies within
    :data:`FOOTPRINT_REACH` footprints of the point (its cosine ``cos`` (N,) toward the camera,
    at least ``min_facing``)."""
    H, W = image_shape
    x0 = np.clip(np.floor(pixels[:, 0]).astype(np.int64), 0, max(W - 2, 0))
    y0 = np.clip(np.floor(pixels[:, 1]).astype(np.int64), 0, max(H - 2, 0))
    left, top = int(x0.min()), int(y0.min())
    right, bottom = min(int(x0.max()) + 1, W - 1), min(int(y0.max()) + 1, H - 1)
    shown = visible_surface(camera_positions, faces, camera, (left, top, right - left + 1, bottom - top + 1))
    reach = FOOTPRINT_REACH * points[:, 2] / float(camera.matrix[0, 0]) / np.maximum(cos, min_facing)
    good = np.ones(len(points), dtype=bool)
    for dy in (0, 1):
        for dx in (0, 1):
            near = shown[np.minimum(y0 + dy, H - 1) - top, np.minimum(x0 + dx, W - 1) - left]
            with np.errstate(invalid="ignore"):  # the background's points are infinitely far
                good &= np.linalg.norm(near - points, axis=1) <= reach
    return good


def visible_surface(camera_positions: np.ndarray, faces: np.ndarray, camera: Camera, window: tuple) -> np.ndarray:
    """(h, w, 3) the camera-space point of the posed mesh (V, 3) nearest the camera at each pixel
    centre of the image's window (x0, y0, w, h) (infinite where no triangle covers it)."""
    x0, y0, w, h = window
    pixels = project_distorted(camera, camera_positions)  # as unwrap projects the texels
    ok = np.isfinite(pixels).all(axis=1) & (camera_positions[:, 2] > 0)
    faces = faces[ok[faces].all(axis=1)]  # a triangle reaching behind the camera is in no pixel
    inverse_depth = np.where(ok, 1.0 / np.where(ok, camera_positions[:, 2], 1.0), 0.0)  # affine over a triangle's image
    face, bary = rasterize(np.where(ok[:, None], pixels - np.array([x0, y0]), 0.0), inverse_depth, faces, w, h)
    # the image's barycentric coordinates, not the surface's: off by a triangle's depth range over
    # its depth, far under a footprint for a face mesh's triangles
    shown = np.einsum("hwk,hwkc->hwc", bary, camera_positions[faces[np.maximum(face, 0)]])
    shown[face < 0] = np.inf
    return shown


def template_points(rect, size: int) -> np.ndarray:
    """(5, size², 2) UV points of a template grid over rect [u0, v0, u1, v1] (rows from the top,
    v decreasing, as images), in place and shifted diagonally by half a grid step."""
    u0, v0, u1, v1 = rect
    du, dv = (u1 - u0) / size, (v1 - v0) / size
    jj, ii = np.meshgrid(np.arange(size), np.arange(size))
    base = np.stack([u0 + (jj + 0.5) * du, v1 - (ii + 0.5) * dv], axis=-1).reshape(-1, 2)
    return np.stack([base + o * np.array([du, -dv]) for o in ap.DIAGONAL_OFFSETS])


def region_template(region, rect, corner_uv, size: int, config_path) -> tuple[np.ndarray, np.ndarray]:
    """A region's template grid (:func:`template_points` over ``rect``, ``size`` to a side) located in
    the UV layout's triangles (``corner_uv``): face (5, size²) and barycentric coordinates (5, size², 3),
    in place and at each diagonal offset; exit 2 (naming the region and ``config_path``) where a
    point lies outside every triangle."""
    pts = template_points(rect, size)
    face, bary = locate_uv(pts.reshape(-1, 2), corner_uv)
    if (face < 0).any():
        k = int(np.argmax(face < 0))
        u, v = pts.reshape(-1, 2)[k]
        raise InputError(f"region {region.name}: template = {region.template} reaches outside the UV layout (at "
                         f"u {u:.4f}, v {v:.4f}, with the half-step offsets)", path=config_path,
                         hint="put the template rectangle well inside the region's UV triangles")
    return face.reshape(5, -1), bary.reshape(5, -1, 3)


def sample_templates(gray: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A frame's template samples (R, 5, size, size), each region's visibility (R,) and which
    template points the camera sees (R, 5, size, size)."""
    patches, visible, seen = sample_template_frames(gray[None], camera_positions[None], model)
    return patches[0], visible[0], seen[0]


def template_positions(camera_positions: np.ndarray, model: AppearanceModel) -> np.ndarray:
    """Camera-space positions (F, R, 5, N, 3) of every template point in frames (F, V, 3)."""
    return np.einsum("rsnk,frsnkc->frsnc", model.template_bary, camera_positions[:, model.faces[model.template_face]])


def sample_template_frames(grays: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, points=None
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Template samples (F, R, 5, size, size) of frames (F, H, W) with their geometry (F, V, 3) in
    camera space, each region's visibility (F, R) and which template points the camera sees
    (F, R, 5, size, size): every frame's points projected at once.

    A point is seen when it projects into the image in front of the camera and (the model's
    ``occlusion``) no part of the face lies in front of it (its ray cast against the animated
    mesh, :func:`facepipe.core.occlusion.occluded_points`: a lowered brow over an eyelid, the
    nose over the far cheek of a turned head). A region is visible when it faces the camera and
    at least ``min_seen`` of its points are seen (``points``: :func:`template_positions` where
    already computed)."""
    F = len(grays)
    X = template_positions(camera_positions, model) if points is None else points  # (F, R, 5, N, 3)
    pixels = project_distorted_fast(model.camera, X)
    values = np.empty(X.shape[:-1])
    seen = np.empty(X.shape[:-1], dtype=bool)
    for f in range(F):
        values[f], seen[f] = ap.bilinear_sample(grays[f], pixels[f])
    seen &= X[..., 2] > 0
    if model.occlusion:
        seen &= ~template_points_hidden(X, camera_positions, model)
    corners = camera_positions[:, model.faces[model.template_face[:, 0]]]  # (F, R, N, 3, 3)
    normal = np.cross(corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :]).sum(axis=2)
    cos = model.normal_sign * ap.facing(normal, X[:, :, 0].mean(axis=2))
    visible = (cos > model.min_facing) & (seen_fraction(seen, model) >= model.min_seen)
    s = model.template_size
    return values.reshape(values.shape[:3] + (s, s)), visible, seen.reshape(seen.shape[:3] + (s, s))


def seen_fraction(seen: np.ndarray, model: AppearanceModel) -> np.ndarray:
    """(F, R) the share of each region's stable template points (all, in models without them) the
    camera sees, over all samples: seen (F, R, 5, N) or (F, R, 5, size, size)."""
    F, R = seen.shape[:2]
    seen = seen.reshape(F, R, 5, -1)
    if model.template_mask is None:
        return seen.mean(axis=(2, 3))
    stable = np.asarray(model.template_mask, dtype=bool)
    return (seen & stable[:, None, :]).sum(axis=(2, 3)) / (seen.shape[2] * stable.sum(axis=-1))


def template_points_hidden(X: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel) -> np.ndarray:
    """Which template points (F, R, 5, N) at camera-space positions X (F, R, 5, N, 3) the face
    hides. A surface hides a point when it crosses the point's ray nearer by more than the
    template's grid step there (the point's own surface, curving, stays within it). The rays
    are cast for the template's grid in place; an offset sample (half a step away) takes its
    grid point's answer: an occluder's edge is not resolved finer than the grid anyway."""
    F, R, S, N = X.shape[:4]
    hidden = grid_points_hidden(X[:, :, 0], camera_positions, model.occluders, model.template_size)
    return np.broadcast_to(hidden[:, :, None], (F, R, S, N))


def grid_points_hidden(grid: np.ndarray, camera_positions: np.ndarray, faces: np.ndarray, size: int) -> np.ndarray:
    """Which points (F, G, N) of template grids (F, G, N = size², 3) in camera space the face
    (F, V, 3) hides, by more than the grid's step (see :func:`template_points_hidden`)."""
    F, G, N = grid.shape[:3]
    rows = grid.reshape(F, G, size, size, 3)
    step = np.linalg.norm(np.diff(rows, axis=3), axis=-1).mean(axis=(2, 3))  # (F, G)
    tolerance = np.broadcast_to(step[:, :, None], (F, G, N)).reshape(F, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        spacing = np.nanmedian(np.linalg.norm(np.diff(rows[..., :2] / rows[..., 2:], axis=3), axis=-1))
    hidden = occluded_points(grid.reshape(F, -1, 3), camera_positions, faces, tolerance,
                             cell=spacing if np.isfinite(spacing) and spacing > 0 else None,
                             groups=np.repeat(np.arange(G), N))  # the triangles culled per region
    return hidden.reshape(F, G, N)


def point_facing(camera_positions: np.ndarray, faces: np.ndarray, face: np.ndarray, bary: np.ndarray,
                 normal_sign: float) -> np.ndarray:
    """Cosine (...) between the smooth surface's normal at points (fixed barycentric coordinates
    face (...), bary (..., 3)) of one frame (V, 3) in camera space and their direction to the camera."""
    X = surface_points(camera_positions, faces, face, bary)
    n = point_normals(camera_positions[None], faces, face, bary, normal_sign)[0]
    return (n * -X).sum(axis=-1) / np.maximum(np.linalg.norm(X, axis=-1), 1e-30)


def well_seen_points(camera_positions: np.ndarray, faces: np.ndarray, face: np.ndarray, bary: np.ndarray,
                     camera: Camera, size: int, normal_sign: float, min_point_facing: float, occlusion: bool = True,
                     min_relative_facing: float = 0.0, unseen_margin: float = 0.0) -> np.ndarray:
    """(N,) which points of a template grid (face (N,), bary (N, 3), size² points) every frame
    (F, V, 3) (camera space: a region's example frames) shows well: in front of the camera and
    inside the image, not hidden by the face (``occlusion``: the ray cast of
    :func:`grid_points_hidden`), facing the camera more than ``min_point_facing`` (cosine of the
    smooth surface's normal) and at least ``min_relative_facing`` times the grid's median cosine
    in that frame, and in the image at least ``unseen_margin`` pixels (along x or y) from every
    point of the grid that fails these tests in that frame. A region's templates and its kept
    coefficients are built on these points and it is matched on them: what an example does not
    show well has no template.

    The relative test finds folds: a point facing the camera much worse than the rest of its
    template lies where the surface turns away (an upper lid rolling into its socket, a lip into
    the mouth); its cell of the grid is squeezed into a fraction of the pixels the others get, and
    what it samples changes with the fold's geometry (blur, aliasing), not with the texture. A
    template that is slanted as a whole (a brow) keeps its points: its median is low too. The
    margin: a point's bilinear sample reads the pixels within one pixel of it, so a point that
    close to a fold, or to where the lid's margin meets the eye, reads part of what lies there —
    the eyeball a lid half-closes over moves through its sample as the lid moves, not its skin."""
    good, pixels = points_seen_well(camera_positions, faces, face, bary, camera, size, normal_sign, min_point_facing,
                                    occlusion, min_relative_facing)
    return with_unseen_margin(good, pixels, unseen_margin)


def points_seen_well(camera_positions: np.ndarray, faces: np.ndarray, face: np.ndarray, bary: np.ndarray,
                     camera: Camera, size: int, normal_sign: float, min_point_facing: float, occlusion: bool = True,
                     min_relative_facing: float = 0.0, occluders: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`well_seen_points`' tests frame by frame, before the margin: (F, N) whether each frame
    shows each point well, and the points' pixels (F, N, 2); ``occluders`` the triangles that may
    hide a point (default ``faces``: a model's are its ``occluders``, the mesh's own)."""
    X = np.einsum("nk,fnkc->fnc", bary, camera_positions[:, faces[face]])     # (F, N, 3)
    pixels = project_distorted_fast(camera, X)
    _, inside = ap.bilinear_sample(np.zeros((camera.height, camera.width)), pixels)
    good = inside & (X[..., 2] > 0)
    if occlusion:
        good &= ~grid_points_hidden(X[:, None], camera_positions, faces if occluders is None else occluders,
                                    size)[:, 0]
    if min_point_facing > 0 or min_relative_facing > 0:
        cos = np.stack([point_facing(c, faces, face, bary, normal_sign) for c in camera_positions])  # (F, N)
        good &= cos > min_point_facing
        good &= cos >= min_relative_facing * np.median(cos, axis=1, keepdims=True)
    return good, pixels


def with_unseen_margin(good: np.ndarray, pixels: np.ndarray, margin: float) -> np.ndarray:
    """(N,) the points every frame shows well (``good`` (F, N), :func:`points_seen_well`) and that lie
    at least ``margin`` pixels from every point a frame does not (pixels (F, N, 2))."""
    if margin > 0:
        good = good & ~near_pixels(pixels, ~good, margin)
    return good.all(axis=0)


def near_pixels(pixels: np.ndarray, of: np.ndarray, margin: float) -> np.ndarray:
    """(F, N) whether each point's pixel (F, N, 2) lies within ``margin`` pixels along both x and
    y (Chebyshev distance below ``margin``) of a point marked in ``of`` (F, N) of its own frame
    (a marked point itself included)."""
    out = np.zeros(of.shape, dtype=bool)
    for f in range(len(pixels)):
        if of[f].any():
            gap = np.abs(pixels[f][:, None, :] - pixels[f][of[f]][None, :, :]).max(axis=-1)  # (N, marked)
            out[f] = gap.min(axis=1) < margin
    return out


def point_normals(camera_positions: np.ndarray, faces: np.ndarray, face: np.ndarray, bary: np.ndarray,
                  normal_sign: float, vn=None) -> np.ndarray:
    """Unit normals (F, ...) of the smooth surface (vertex normals interpolated) at points on the
    posed triangles of frames (F, V, 3): face (...), bary (..., 3), the same in every frame
    (``vn``: the frames' vertex normals (F, V, 3) where already computed)."""
    vn = normal_sign * vertex_normals(camera_positions, faces) if vn is None else vn
    n = np.einsum("...k,f...kc->f...c", bary, vn[:, faces[face]])
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)


def _normal_stencil(model: AppearanceModel):
    """The vertices of the light points' and the templates' triangles, every triangle around them
    and their vertex–triangle incidence: those vertices' normals need only these (built once
    per model). Returns (vertices (M,), local index of every vertex (V,), triangles, incidence (M, T))."""
    if getattr(model, "_stencil", None) is None:
        n_vertices = int(model.faces.max()) + 1
        needed = np.zeros(n_vertices, dtype=bool)
        needed[model.faces[model.light_face].ravel()] = True
        needed[model.faces[model.template_face].ravel()] = True
        vertices = np.flatnonzero(needed)
        local = np.full(n_vertices, -1, dtype=np.int64)
        local[vertices] = np.arange(len(vertices))
        around = model.faces[needed[model.faces].any(axis=1)]
        incidence = vertex_face_matrix(around, n_vertices)[vertices]
        model._stencil = (vertices, local, around, incidence)
    return model._stencil


def stencil_normals(camera_positions: np.ndarray, model: AppearanceModel) -> tuple[np.ndarray, np.ndarray]:
    """Unit vertex normals (F, M, 3) of frames at the stencil's vertices, and the local index map."""
    _, local, around, incidence = _normal_stencil(model)
    v0 = camera_positions[:, around[:, 0]]
    fn = np.cross(camera_positions[:, around[:, 1]] - v0, camera_positions[:, around[:, 2]] - v0)  # (F, T, 3)
    F, T = fn.shape[:2]
    vn = np.asarray(incidence @ np.moveaxis(fn, 1, 0).reshape(T, F * 3)).reshape(-1, F, 3)
    vn = np.moveaxis(vn, 1, 0) * model.normal_sign
    return vn / np.maximum(np.linalg.norm(vn, axis=-1, keepdims=True), 1e-30), local


def template_point_facing(camera_positions: np.ndarray, model: AppearanceModel, normals=None, points=None
                          ) -> np.ndarray:
    """Cosine (F, R, 5, size, size) between the smooth surface's normal at every template point
    and its direction to the camera (``normals``: those normals (F, R, 5, N, 3), ``points``:
    :func:`template_positions`, where known).
    Near 0 the camera sees the skin edge-on: a template's rows crowd into a pixel or two, and
    what is sampled there is the image's blur, not the texture."""
    X = template_positions(camera_positions, model) if points is None else points
    if normals is None:
        normals = point_normals(camera_positions, model.faces, model.template_face, model.template_bary,
                                model.normal_sign)
    cos = (normals * -X).sum(axis=-1) / np.maximum(np.linalg.norm(X, axis=-1), 1e-30)
    s = model.template_size
    return cos.reshape(cos.shape[:3] + (s, s))


def frame_facing_limits(model: AppearanceModel):
    """The cosine under which a frame's template point is left out as seen too edge-on: (R, 5,
    size, size) ``frame_facing_share`` × the least cosine the region's examples saw it at
    (``template_facing``), at least 0 (a point facing away is never read); or, in models with
    the share 0 or without the examples' cosines, the one ``min_point_facing`` for every point.

    Why relative: a point's grid cell gets pixels in proportion to the cosine it is seen at, so a
    frame that sees it at under half the examples' cosine samples it with under half the pixels
    its templates had (blur, not texture) — however the examples framed it. A fixed cosine hides
    a fold that lies on the side of the face (its examples see it at 50–65°) as soon as the head
    turns a little away, while the templates were sampled just as obliquely."""
    if model.frame_facing_share <= 0 or model.template_facing is None:
        return model.min_point_facing
    s = model.template_size
    facing = np.asarray(model.template_facing, dtype=np.float64)
    return np.maximum(model.frame_facing_share * facing, 0.0).reshape(facing.shape[:2] + (s, s))
