"""Appearance from footage (Fidaleo et al. 2000, §V): the model's build and the per-frame classification.

**Build** (``facepipe appearance build CONFIG``): the rest mesh's UV layout is rasterised once
(every texel's triangle and barycentric coordinates); each example frame is unwrapped into it
through its geometry and the camera (texels facing away are taken from the neutral texture);
a region's layers are its example frames' texels inside its vertex group's UV triangles, with
an alpha ramp into the neutral texture at its border. Its template is a template_size² grid of
UV points in the template rectangle, located in the UV triangles once (fixed barycentric
coordinates), also shifted diagonally by half a grid step for the offset samples; the
templates are those points' samples in the example frames. Each region's rest floor is the
highest Q it reads in the example frames where it is at rest (:func:`calibrate_rest`). A
``card`` region (an eye) lies on a card across the hole its vertex group rims
(:func:`region_cards`, :mod:`facepipe.core.hole_cards`): the cards' triangles follow the mesh's,
their vertices its vertices, in a free square of the UV layout, and every frame's positions are
extended with them (:meth:`AppearanceModel.with_cards`). With a light fit the neutral texture
and every layer are divided by the shading of their own frame (:func:`to_albedo`): the model holds
the skin's albedo, and a frame's texture is that albedo at its Q times the shading of the frame's
own geometry under its own light (:func:`frame_texture`).

**Classification** (``facepipe appearance classify``): per frame the template points are put on
the animated surface through their barycentric coordinates, projected through the camera
(OpenCV's distortion) and sampled bilinearly from the frame's luminance; the five samples are
classified (:func:`facepipe.core.appearance.classify`) and Q measured from the region's rest
floor; a region whose template faces away from the camera, falls outside the image or whose
frame is missing keeps its last value read with most of its template in view (:data:`WELL_SEEN`),
decaying to neutral; a reading that leaves rest for less
than ``min_event`` seconds (one or two frames at 30 Hz) and stays under a layer is image noise,
and set back to rest. Each frame's light (nine
coefficients, :func:`frame_lights`) is part of the result: the texture's shading comes from it.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from facepipe.core import appearance as ap, layered_texture, lighting
from facepipe.core.camera import Camera, project_distorted, project_distorted_fast
from facepipe.core.hole_cards import boundary_loops, hole_cards, stable_vertices
from facepipe.core.occlusion import occluded_points
from facepipe.core.mesh import VertexSelection
from facepipe.core.raster import triangle_pixels, udim_corner, udim_tile_numbers
from facepipe.core.tangent_frames import vertex_face_matrix, vertex_normals
from facepipe.errors import InputError
from facepipe.parallel import map_blocks, serial_blas, thread_count
from facepipe.io.appearance_file import AppearanceModel
from facepipe.io.footage import Footage, frames_at, open_footage, read_frames_of, to_gray

__all__ = ["texel_map", "locate_uv", "unwrap", "build_appearance", "AppearanceModel", "classify_frames", "classify_image", "classify_decoded",
           "classify_chunk", "frame_texture", "frame_light", "frame_lights", "frame_colours", "texel_shading", "skin_texels",
           "to_albedo",
           "texture_differences", "well_seen_points", "region_bank"]


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

    centres = corner_uv.mean(axis=1)
    k = min(candidates, len(centres))
    _, near = cKDTree(centres).query(points, k=k)
    near = near.reshape(len(points), k)
    a, b, c = (corner_uv[near, i] for i in range(3))  # (N, k, 2)
    e1, e2, d = b - a, c - a, points[:, None] - a
    det = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        b1 = (d[..., 0] * e2[..., 1] - d[..., 1] * e2[..., 0]) / det
        b2 = (e1[..., 0] * d[..., 1] - e1[..., 1] * d[..., 0]) / det
        b0 = 1 - b1 - b2
    inside = (np.abs(det) > 1e-14) & (b0 >= -1e-9) & (b1 >= -1e-9) & (b2 >= -1e-9)
    first = np.argmax(inside, axis=1)
    found = inside[np.arange(len(points)), first]
    rows = np.arange(len(points))
    face = np.where(found, near[rows, first], -1)
    bary = np.stack([b0[rows, first], b1[rows, first], b2[rows, first]], axis=1)
    return face, np.where(found[:, None], bary, 0.0)


def surface_points(camera_positions: np.ndarray, faces: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Points (..., 3) at fixed barycentric coordinates on the posed triangles."""
    return np.einsum("...k,...kc->...c", bary, camera_positions[faces[face]])


def triangle_normals(camera_positions: np.ndarray, faces: np.ndarray, face: np.ndarray) -> np.ndarray:
    p = camera_positions[faces[face]]
    return np.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :])


def unwrap(image: np.ndarray, camera_positions: np.ndarray, faces: np.ndarray, texel_face: np.ndarray,
           texel_bary: np.ndarray, camera: Camera, rows=slice(None), cols=slice(None), min_facing: float = 0.2,
           normal_sign: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A frame's colours in texture space over texels [rows, cols]: (h, w, 3) and where seen (h, w)."""
    tf = texel_face[rows, cols]
    tb = texel_bary[rows, cols]
    covered = tf >= 0
    out = np.zeros(tf.shape + (3,))
    seen = np.zeros(tf.shape, dtype=bool)
    if not covered.any():
        return out, seen
    X = surface_points(camera_positions, faces, tf[covered], tb[covered])
    cos = normal_sign * ap.facing(triangle_normals(camera_positions, faces, tf[covered]), X)
    values, inside = ap.bilinear_sample(image, project_distorted(camera, X))
    out[covered] = values
    seen[covered] = inside & (cos > min_facing)
    return out, seen


def template_points(rect, size: int) -> np.ndarray:
    """(5, size², 2) UV points of a template grid over rect [u0, v0, u1, v1] (rows from the top,
    v decreasing, as images), in place and shifted diagonally by half a grid step."""
    u0, v0, u1, v1 = rect
    du, dv = (u1 - u0) / size, (v1 - v0) / size
    jj, ii = np.meshgrid(np.arange(size), np.arange(size))
    base = np.stack([u0 + (jj + 0.5) * du, v1 - (ii + 0.5) * dv], axis=-1).reshape(-1, 2)
    return np.stack([base + o * np.array([du, -dv]) for o in ap.DIAGONAL_OFFSETS])


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


def region_bank(model: AppearanceModel) -> ap.RegionBank:
    """The model's templates for :func:`facepipe.core.appearance.classify_regions`."""
    return ap.RegionBank(model.templates, model.indices, model.weights, model.template_mask, model.shading_orders)


def template_points_hidden(X: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel) -> np.ndarray:
    """Which template points (F, R, 5, N) at camera-space positions X (F, R, 5, N, 3) the face
    hides. A surface hides a point when it crosses the point's ray nearer by more than the
    template's grid step there (the point's own surface, curving, stays within it). The rays
    are cast for the template's grid in place; an offset sample (half a step away) takes its
    grid point's answer: an occluder's edge is not resolved finer than the grid anyway."""
    F, R, S, N = X.shape[:4]
    hidden = grid_points_hidden(X[:, :, 0], camera_positions, model.faces, model.template_size)
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


@dataclass
class TakeGeometry:
    """A take's geometry as read once: positions (T, V, 3), frame numbers (T,), its own frame
    times (T,) seconds where it records them (else None), whether the positions are in a camera's
    coordinates (a 2D take's replay; else world positions) and that camera where the replay
    recorded it."""

    positions: np.ndarray
    numbers: np.ndarray
    times: np.ndarray | None = None
    in_camera: bool = False
    camera: Camera | None = None


def read_take_geometry(path, n_vertices: int) -> TakeGeometry:
    """:class:`TakeGeometry` from an .npz (``positions``, optional ``frame`` and ``time``) or a replay
    folder (``positions.npy`` and ``replay.json``; ``video.npz`` for a 2D take's camera)."""
    from facepipe.io.replay_folder import ReplayDir

    path = Path(path)
    times = camera = None
    in_camera = False
    if path.is_dir():
        replay = ReplayDir(path)
        positions, numbers, times = replay.positions, replay.frame_numbers, replay.times
        if positions.shape[1] != n_vertices and (replay.info.get("welded") or {}).get("vertices") == n_vertices:
            # a rig welded along seams ([rig] weld) replayed: its positions in the mesh file's order
            positions = VertexSelection(positions, replay.weld_index())
        in_camera = str(replay.info.get("coordinates", "")).startswith("camera")
        video = replay.video if in_camera else None
        camera = None if video is None else video.camera
    elif path.is_file():
        try:
            with np.load(path) as data:
                positions = np.asarray(data["positions"])
                numbers = np.asarray(data["frame"]) if "frame" in data else np.arange(len(positions))
                times = np.asarray(data["time"], dtype=np.float64) if "time" in data else None
        except (OSError, ValueError, KeyError) as exc:
            raise InputError(f"not a geometry .npz with 'positions' ({exc})", path=path,
                             hint="positions (T, V, 3) and frame (T,), or a replay folder") from None
    else:
        raise InputError("geometry not found", path=path, hint="an .npz with positions and frame, or a replay folder")
    if positions.ndim != 3 or positions.shape[1:] != (n_vertices, 3):
        raise InputError(f"positions have shape {positions.shape}, the rest mesh has {n_vertices} vertices",
                         path=path, hint="give the geometry of this rig's mesh")
    if times is not None and times.shape != (len(positions),):
        times = None  # not one a frame: the frames' numbers alone say which footage is theirs
    return TakeGeometry(positions, np.asarray(numbers, dtype=np.int64), times, in_camera, camera)


def _read_geometry(path, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions (T, V, 3) and frame numbers (T,) of a take's geometry (:func:`read_take_geometry`)."""
    geometry = read_take_geometry(path, n_vertices)
    return geometry.positions, geometry.numbers


def take_geometry(path, model: AppearanceModel) -> tuple[TakeGeometry, AppearanceModel, str | None]:
    """The geometry of a take to classify (:func:`read_take_geometry`), the model to classify it
    with, and a note or None.

    A 2D take's replay is written in its camera's coordinates (``replay.json``: ``coordinates``)
    and its footage is that camera's: the model classifies it through that camera, its positions
    taken as they are (the model's world-to-camera transform, which is the example footage's, is
    the identity here). The note says so, and where that calibration is not the model's."""
    geometry = read_take_geometry(path, model.n_vertices)
    if not geometry.in_camera:
        return geometry, model, None
    camera = geometry.camera or model.camera  # (a replay without its camera's record: the model's)
    same = (camera.width, camera.height) == (model.camera.width, model.camera.height) and np.allclose(
        camera.matrix, model.camera.matrix) and np.allclose(np.ravel(camera.distortion), np.ravel(model.camera.distortion))
    note = ("the geometry is a 2D take's replay, in its camera's coordinates: classified through that camera"
            + ("" if same else " (not the calibration the model was built with: its footage is that camera's)"))
    return geometry, replace(model, rotation=np.eye(3), translation=np.zeros(3), camera=camera), note


def _example_frames(cfg, footage_numbers_needed, geometry: TakeGeometry, camera: Camera) -> dict:
    """The example frames the regions name: frame number → (RGB image, camera-space positions).
    Each is the footage's frame of that number, or the one at the geometry's own time for it
    (:func:`facepipe.io.footage.frames_at`)."""
    index = {int(n): i for i, n in enumerate(geometry.numbers)}
    needed = np.array(sorted(footage_numbers_needed), dtype=np.int64)
    for n in needed:
        if int(n) not in index:
            raise InputError(f"example frame {int(n)} has no geometry", path=cfg.geometry,
                             hint="the geometry's frame numbers must include the example frames")
    rows = np.array([index[int(n)] for n in needed], dtype=np.int64)
    footage = open_footage(cfg.footage)
    at, _ = frames_at(footage, needed, None if geometry.times is None else geometry.times[rows])
    frames = {}
    for shown, image, problem in read_frames_of(footage, at):
        for k in shown:
            n = int(needed[k])
            if image is None:
                raise InputError(f"example frame {n}: {problem}", path=cfg.footage,
                                 hint="every frame an [appearance.regions] table names must be readable")
            _check_size(image, camera, n, cfg.footage)
            frames[n] = (image, geometry.positions[rows[k]])
    return frames


def _check_size(image: np.ndarray, camera: Camera, number: int, source) -> None:
    if image.shape[:2] != (camera.height, camera.width):
        raise InputError(f"frame {number} is {image.shape[1]} × {image.shape[0]} pixels, the camera's calibration "
                         f"is for {camera.width} × {camera.height}", path=source,
                         hint="use footage at the calibrated size, or a calibration for this size")


#: Rings of triangles from a card's centre to its rim; and the smallest UV square a card may get (texels)
CARD_RINGS = 4
MIN_CARD_TEXELS = 16


def free_uv_squares(corner_uv: np.ndarray, size: int, count: int, gap: int = 2, tile: int = 1001) -> list:
    """``count`` UV squares [u0, v0, u1, v1] where the layout (at ``size`` texels) has no triangle
    on UDIM ``tile``, largest first, each ``gap`` texels from any triangle and the others; their
    sides in texels."""
    import cv2  # OpenCV's distance transform: only where a model with cards is built

    covered = texel_map(corner_uv, size, tile)[0] >= 0
    u0, v0 = udim_corner(tile)
    free = np.pad(~covered, 1).astype(np.uint8)  # the texture's border counts as used
    squares = []
    for _ in range(count):
        # the chessboard distance to the nearest used texel: the half-side of the largest square there
        half = cv2.distanceTransform(free, cv2.DIST_C, 3)[1:-1, 1:-1]
        i, j = np.unravel_index(int(np.argmax(half)), half.shape)
        h = int(half[i, j]) - gap
        side = 2 * h - 1
        squares.append(([u0 + (j - h + 1) / size, v0 + 1.0 - (i + h) / size, u0 + (j + h) / size,
                         v0 + 1.0 - (i - h + 1) / size], side))
        free[1 + max(i - h - gap, 0):1 + i + h + gap, 1 + max(j - h - gap, 0):1 + j + h + gap] = 0
    return squares


def region_cards(cfg, mesh, groups: dict, corner_uv: np.ndarray, positions: np.ndarray, config_path,
                 tile: int = 1001):
    """Cards (:func:`facepipe.core.hole_cards.hole_cards`) across the holes that the ``card``
    regions' vertex groups (``groups``: region name → vertex mask, :func:`group_masks`) rim, each
    in a free square of the UV layout on ``tile``, carried by the vertices
    that move least over the geometry's frames ``positions`` (T, V, 3); and region name → card.
    (None, {}) where no region is a card."""
    wanted = [r for r in cfg.regions if r.card]
    if not wanted:
        return None, {}
    loops = boundary_loops(mesh.faces)
    chosen, card_of = [], {}
    for region in wanted:
        share = [float(groups[region.name][loop].mean()) for loop in loops]
        best = int(np.argmax(share)) if share else -1
        if best < 0 or share[best] < 0.5:
            raise InputError(f"region {region.name}: card = true, but its vertex group holds at most "
                             f"{max(share, default=0):.0%} of any hole's rim (the mesh has {len(loops)} holes or "
                             f"open borders)", path=region.vertices,
                             hint="list the vertices around the hole the card spans (an eye's lid rims), or "
                                  "leave card out for a region on the surface")
        for other, c in card_of.items():
            if chosen[c] == best:
                raise InputError(f"regions {other} and {region.name} are cards across the same hole",
                                 path=config_path, hint="one card region per hole")
        card_of[region.name] = len(chosen)
        chosen.append(best)
    squares = free_uv_squares(corner_uv, cfg.texture_size, len(chosen), tile=tile)
    for (square, side), region in zip(squares, wanted):
        if side < MIN_CARD_TEXELS:
            raise InputError(f"region {region.name}: the UV layout has room for a card of {max(side, 0)} texels at "
                             f"texture_size = {cfg.texture_size}, under {MIN_CARD_TEXELS}", path=config_path,
                             hint="raise texture_size, or leave free space in the UV layout for the cards")
    cards = hole_cards(mesh.vertices, [loops[b] for b in chosen], np.array([sq for sq, _ in squares]),
                       stable_vertices(mesh.vertices, positions), CARD_RINGS)
    return cards, card_of


def group_masks(cfg, n_vertices: int, config_path) -> dict:
    """Region name → (V,) mask of its vertex group, each group file read and checked once."""
    masks = {}
    for region in cfg.regions:
        masks[region.name] = np.zeros(n_vertices, dtype=bool)
        masks[region.name][_read_group(region, n_vertices, config_path)] = True
    return masks


def regions_tile(cfg, mesh, groups: dict, tile_of: np.ndarray, in_udim: np.ndarray, config_path) -> int:
    """The UDIM tile every region lies on (1001 where none has a triangle in the UDIM range): the
    tile of a region's triangles (those its vertex group holds whole; a card region's, those that
    touch its rim). A region over two tiles, or regions on different tiles, are refused: a region's
    layers are one box of one tile's texture, and the layered texture is one tile's."""
    where = {}
    for region in cfg.regions:
        inside = groups[region.name][mesh.faces]
        triangles = (inside.any(axis=1) if region.card else inside.all(axis=1)) & in_udim
        found = np.unique(tile_of[triangles])
        if len(found) > 1:
            raise InputError(f"region {region.name}: its vertex group's triangles lie on UDIM tiles "
                             f"{', '.join(map(str, found))}", path=region.vertices,
                             hint="a region's layers are one box of one tile's texture: lay the region out on one "
                                  "tile, or split it into a region per tile")
        if len(found):
            where[region.name] = int(found[0])
    if len(set(where.values())) > 1:
        raise InputError("the regions lie on different UDIM tiles: " + ", ".join(f"{n} on {t}" for n, t in where.items()),
                         path=config_path, hint="lay every region out on one tile (the layered texture's); the "
                                                "other tiles keep the neutral texture")
    return next(iter(where.values()), 1001)


def build_appearance(config, mesh, camera: Camera, progress=None) -> tuple[AppearanceModel, dict]:
    """Build the appearance model from a config's ``[appearance]`` table (see the module docstring)."""
    cfg = config.appearance
    faces = mesh.faces
    if mesh.face_uvs is None:
        raise InputError("the rest mesh has no UVs: the layered texture needs its UV layout", path=config.mesh)
    corner_uv = mesh.uvs[mesh.face_uvs]
    R = np.asarray(cfg.camera_rotation, dtype=np.float64)
    t = np.asarray(cfg.camera_translation, dtype=np.float64)
    geometry = read_take_geometry(cfg.geometry, mesh.n_vertices)
    positions = geometry.positions
    if geometry.in_camera and not (np.allclose(R, np.eye(3)) and np.allclose(t, 0.0)):
        raise InputError("the example geometry is a 2D take's replay, already in its camera's coordinates, and the "
                         "config moves it again by camera_rotation/camera_translation", path=config.path,
                         hint="leave camera_rotation and camera_translation out of [appearance] for this geometry")
    # the regions' UDIM tile: their layered texture's (the others keep the neutral texture)
    tile_of, in_udim = udim_tile_numbers(corner_uv)
    groups = group_masks(cfg, mesh.n_vertices, config.path)
    home = regions_tile(cfg, mesh, groups, tile_of, in_udim, config.path)
    cards, card_of = region_cards(cfg, mesh, groups, corner_uv, positions, config.path, home)
    if cards is not None:  # the cards' triangles after the mesh's, their vertices after its vertices
        faces = np.concatenate([faces, cards.faces])
        corner_uv = np.concatenate([corner_uv, cards.corner_uv])
        positions = cards.extend(positions)
    needed = {cfg.neutral_frame} | {f for r in cfg.regions for f in r.frames} | set(cfg.rest_frames)
    frames = _example_frames(cfg, needed, replace(geometry, positions=positions), camera)  # (the cards' too)
    cam_pos = {n: positions_world @ R.T + t for n, (_, positions_world) in frames.items()}
    S = cfg.texture_size
    texel_face, texel_bary = texel_map(corner_uv, S, home)
    neutral_cam = cam_pos[cfg.neutral_frame]
    covered = texel_face >= 0
    cos = ap.facing(triangle_normals(neutral_cam, faces, texel_face[covered]),
                    surface_points(neutral_cam, faces, texel_face[covered], texel_bary[covered]))
    normal_sign = 1.0 if np.median(cos) >= 0 else -1.0
    neutral, seen = unwrap(frames[cfg.neutral_frame][0], neutral_cam, faces, texel_face, texel_bary, camera,
                           min_facing=cfg.min_facing, normal_sign=normal_sign)
    # texels the neutral frame does not show (edge-on, behind the head) continue the skin around them
    neutral = layered_texture.fill_unseen(neutral, seen) if seen.any() else np.full_like(neutral, 0.5)
    # the layout's other UDIM tiles (a head's scalp, neck, ears) hold no region: their neutral texture
    tiles = {t: _tile_neutral(frames[cfg.neutral_frame][0], neutral_cam, faces, texel_map(corner_uv, S, t), camera,
                              cfg, normal_sign, np.median(neutral[seen], axis=0) if seen.any() else 0.5)
             for t in np.unique(tile_of[in_udim]).tolist() if t != home}
    light = _example_light(neutral, seen, neutral_cam, faces, texel_face, texel_bary, normal_sign,
                           cfg.light_model) if cfg.light_fit else None
    weights = ap.coefficient_weights(cfg.template_size, cfg.scale_weights)
    names, volumes, alphas, boxes, tfaces, tbarys, templates, indices, notes = [], [], [], [], [], [], [], [], []
    facing_examples, masks, layer_seen, orders, surfaces = [], [], [], [], {}
    if not in_udim.all():
        notes.append(f"{int((~in_udim).sum())} triangles of the rest mesh (the first: {int(np.argmin(in_udim))}) have "
                     "UVs outside the UDIM range (u in 0–10, v ≥ 0): the textures leave them out")
    for region in cfg.regions:
        if region.name in card_of:
            triangles = np.zeros(len(faces), dtype=bool)
            triangles[len(mesh.faces):] = cards.card == card_of[region.name]
            square = cards.squares[card_of[region.name]]
            u0, v0, u1, v1 = region.template  # in the card's own square
            rect = [square[0] + u0 * (square[2] - square[0]), square[1] + v0 * (square[3] - square[1]),
                    square[0] + u1 * (square[2] - square[0]), square[1] + v1 * (square[3] - square[1])]
        else:
            triangles = np.zeros(len(faces), dtype=bool)
            triangles[:len(mesh.faces)] = groups[region.name][mesh.faces].all(axis=1)
            rect = region.template
        vol, alpha, box, seen_in = _region_volume(region, config, faces, triangles, frames, cam_pos, texel_face,
                                                  texel_bary, camera, neutral, cfg, normal_sign)
        layer_seen.append(seen_in)
        face, bary = _region_template(region, rect, corner_uv, cfg.template_size, config.path)
        gray = [to_gray(frames[f][0]) for f in region.frames]
        patches = []
        facing_examples.append(np.min([point_facing(cam_pos[f], faces, face, bary, normal_sign)
                                       for f in region.frames], axis=0))
        seen_well, pixels = points_seen_well(np.stack([cam_pos[f] for f in region.frames]), faces, face[0], bary[0],
                                             camera, cfg.template_size, normal_sign, cfg.min_point_facing,
                                             cfg.occlusion, cfg.min_relative_facing)
        stable = with_unseen_margin(seen_well, pixels, cfg.unseen_margin)
        # a small template in few pixels (a lid at low resolution): where the margin would take too
        # much of it, a narrower one (halved twice, then none), since matching on too little of
        # it is worse than reading part of a fold's edge
        margin, full = cfg.unseen_margin, stable.mean()
        while stable.mean() < cfg.min_seen and margin > 0:
            margin = margin / 2.0 if margin > cfg.unseen_margin / 4.0 else 0.0
            stable = with_unseen_margin(seen_well, pixels, margin)
        if margin != cfg.unseen_margin and stable.mean() >= cfg.min_seen:
            notes.append(f"region {region.name}: the unseen margin ({cfg.unseen_margin:g} px) would leave {full:.0%} "
                         f"of its template, under min_seen = {cfg.min_seen:g}: "
                         + (f"kept with {margin:g} px" if margin > 0 else "its points kept without it")
                         + f" ({stable.mean():.0%})")
        if stable.mean() < cfg.min_seen:
            raise InputError(f"region {region.name}: only {stable.mean():.0%} of its template is seen well (in the "
                             f"image, not hidden, not edge-on) in every example frame, under min_seen = "
                             f"{cfg.min_seen}", path=config.path,
                             hint="move the template to where every example shows the region, or lower "
                                  "min_point_facing / min_seen")
        masks.append(stable)
        for g, f in zip(gray, region.frames):
            X = surface_points(cam_pos[f], faces, face[0], bary[0])
            values, inside = ap.bilinear_sample(g, project_distorted(camera, X))
            if not inside.all():
                raise InputError(f"region {region.name}: its template leaves the image in example frame {f}",
                                 path=config.path, hint="choose example frames where the region is in view")
            if light is not None:  # the example's own shading out: the templates hold the albedo's structure
                normals = point_normals(cam_pos[f][None], faces, face[0], bary[0], normal_sign)[0]
                values = values / lighting.light_shading(normals, light["light"])
            patches.append(values.reshape(cfg.template_size, cfg.template_size))
        # the templates, and the coefficients kept, of the stable points alone: what rolls out of
        # view in some example (an eyelid into its socket) neither dominates the selection nor
        # takes up the normalisation's plane
        size = cfg.template_size
        stack, mask = np.stack(patches), stable.reshape(size, size)
        order, kept = _shading_surface(cfg, region, stack, mask, weights)
        if cfg.shading:  # (else the patches are divided by their mean alone)
            surfaces[region.name] = {"surface": ap.SHADING_ORDERS[order], "contrast_kept": kept}
        coeffs = ap.haar_coefficients(ap.normalise_patches(stack, order if cfg.shading else 0, mask))
        orders.append(order)
        names.append(region.name)
        volumes.append(vol.astype(np.float32))
        alphas.append(alpha.astype(np.float32))
        boxes.append(box)
        tfaces.append(face)
        tbarys.append(bary)
        templates.append(coeffs)
        indices.append(ap.select_coefficients(coeffs, cfg.keep))
        if progress is not None:
            progress(1)
    model = AppearanceModel(names, camera, R, t, faces, normal_sign, np.stack(tfaces), np.stack(tbarys), templates,
                            indices, weights, cfg.template_size, cfg.min_facing, cfg.decay,
                            neutral.astype(np.float32), volumes, alphas, np.asarray(boxes, dtype=np.int64),
                            cfg.shading, *((light["face"], light["bary"], light["albedo"]) if light else (None,) * 3),
                            corner_uv.astype(np.float32), cfg.min_seen, cfg.occlusion, cfg.min_point_facing,
                            np.stack(facing_examples).astype(np.float32), np.stack(masks),
                            card_rest=None if cards is None else cards.rest,
                            card_stable=None if cards is None else cards.stable,
                            card_stable_rest=None if cards is None else cards.stable_rest,
                            light_colour=None if light is None else light["colour"].astype(np.float32),
                            tiles=np.array(list(tiles), dtype=np.int64) if tiles else None,
                            tile_neutral=np.stack([t["texture"] for t in tiles.values()]) if tiles else None,
                            tile=home, shading_orders=np.asarray(orders, dtype=np.int64),
                            peak_interpolation=cfg.peak_interpolation, min_event=cfg.min_event,
                            light_model=cfg.light_model if light is not None else "sh9",
                            light_point_albedo=None if light is None else light["point_albedo"])
    if light is not None:
        to_albedo(model, cfg, frames, cam_pos, seen, layer_seen, (texel_face, texel_bary), tiles)
    rest = calibrate_rest(model, cfg, frames, cam_pos, notes) if cfg.rest_calibration else {}
    info = {"regions": names, "layers": model.layer_counts, "texture_size": S, "tiles": model.all_tiles,
            "albedo": model.albedo, "rest": rest, "shading": surfaces, "peak_interpolation": model.peak_interpolation,
            "notes": notes}
    if light is not None:
        info["light"] = {"model": model.light_model, "examples": light["light"].tolist()}
    if cards is not None:
        info["cards"] = {name: {"uv_square": cards.squares[c].tolist(),
                                "rim_vertices": int(cards.rim_sizes[c]),
                                "carried_by_vertices": int(len(cards.stable))}
                         for name, c in card_of.items()}
    return model, info


#: A rest floor is kept to at most this many layers; above half a layer the build says so.
MOST_REST_FLOOR = 1.0


def calibrate_rest(model: AppearanceModel, cfg, frames: dict, cam_pos: dict, notes: list) -> dict:
    """Set the model's rest floors from the example frames, and return them per region.

    A region is at rest in every example frame but its own layers above the neutral one (the
    neutral frame, the other regions' examples and the ``rest_frames``, other expressions where
    no region is active: frames where the rest of the face moves): the highest Q it reads there
    is its floor (:func:`facepipe.core.appearance.rest_floor`), which classification measures Q
    from. A floor above half a layer is noted: the region's template
    sees another region's motion (a brow lowered over the lid), and the floor hides that much of
    its own first layer.
    """
    numbers = sorted(frames)
    grays = np.stack([to_gray(frames[n][0]) for n in numbers])
    cams = np.stack([cam_pos[n] for n in numbers])
    bank = region_bank(model)
    readings = classify_decoded(grays, cams, model, bank).q
    at_rest = np.array([[n not in set(region.frames[1:]) for region in cfg.regions] for n in numbers])
    floor, row = ap.rest_floor(readings, at_rest, MOST_REST_FLOOR)
    model.rest_floor = floor
    out = {}
    for r, name in enumerate(model.names):
        frame = int(numbers[row[r]]) if row[r] >= 0 else None
        out[name] = {"floor": float(floor[r]), "frame": frame}
        if frame is None:
            notes.append(f"region {name}: no example frame shows it at rest (seen): its rest floor is 0")
        elif readings[row[r], r] > 0.5 * MOST_REST_FLOOR:
            notes.append(f"region {name} reads Q {readings[row[r], r]:.2f} at rest in example frame {frame}: its "
                         f"template sees that frame's motion; Q is measured from {floor[r]:.2f}")
    return out


def _tile_neutral(image: np.ndarray, neutral_cam: np.ndarray, faces: np.ndarray, texels, camera: Camera, cfg,
                  normal_sign: float, fill) -> dict:
    """The neutral frame's texture on another UDIM tile (its texel map ``texels``), what the
    frame does not show filled from what it does (``fill``, a colour, where it shows nothing of
    the tile): {"texture", "seen", "texels"}."""
    texture, seen = unwrap(image, neutral_cam, faces, *texels, camera, min_facing=cfg.min_facing,
                           normal_sign=normal_sign)
    texture = layered_texture.fill_unseen(texture, seen) if seen.any() else np.broadcast_to(np.asarray(fill, dtype=np.float64),
                                                                                 texture.shape).copy()
    return {"texture": texture.astype(np.float32), "seen": seen, "texels": texels}


def _neutral_albedo(model: AppearanceModel, texture: np.ndarray, seen: np.ndarray, texels, neutral_cam: np.ndarray,
                    light: np.ndarray, cfg) -> np.ndarray:
    """A tile's neutral texture (S, S, 3) with the neutral frame's shading divided out where the
    frame shows the skin (``seen``); the rest filled from the texels it shows well (better than
    ``min_point_facing``): one seen near edge-on is a smear of a few pixels under the light fit's
    least certain normals, and a fill spreads its error over everything beyond it (as a template
    point seen so is left out). Off the skin (a card, no triangle) the texture is kept."""
    texel_face, texel_bary = texels
    everywhere = (slice(None), slice(None))
    skin = skin_texels(model, texel_face)
    shading = texel_shading(model, neutral_cam, light, texel_face, texel_bary, *everywhere)
    seen = seen & skin
    albedo = np.where(seen[..., None], texture / shading, texture)
    well_seen = seen & (_texel_facing(model, neutral_cam, texel_face, texel_bary, *everywhere)
                        > max(cfg.min_facing, cfg.min_point_facing))
    if well_seen.any():
        albedo = np.where((skin & ~seen)[..., None], layered_texture.fill_unseen(albedo, well_seen), albedo)
    return albedo


def to_albedo(model: AppearanceModel, cfg, frames: dict, cam_pos: dict, neutral_seen: np.ndarray,
              layer_seen: list, texels, tiles: dict | None = None) -> None:
    """Divide the shading of their own frame out of the neutral texture and every layer: the model
    then holds the skin's albedo (``neutral_albedo``, its volumes; ``neutral`` stays the neutral
    frame's texture as the footage showed it), and a frame's texture is that albedo at its Q
    times the shading of its own geometry under its own light (:func:`frame_texture`) — what no
    layer index can carry: how the face's large-scale motion (a jaw opening, a cheek raised) and
    the head's turning under the light change the shading over every region.

    Each example frame's light is fitted as a classified frame's is (:func:`frame_light`). A
    layer's texels that its own frame does not show hold the neutral albedo; texels the neutral
    frame does not show are filled (:func:`facepipe.core.layered_texture.fill_unseen`) from those it
    sees better than ``min_point_facing``. The cards' texels (an eye behind its opening) keep
    their values: a card's plane is not the surface the footage shows there. ``tiles``: the
    layout's other UDIM tiles (:func:`_tile_neutral` of each), whose neutral texture becomes
    ``tile_albedo`` the same way."""
    texel_face, texel_bary = texels
    used = sorted({cfg.neutral_frame} | {f for region in cfg.regions for f in region.frames})
    # a frame at a time: the frames' positions together would be the examples' count times the mesh
    lights = {f: frame_light(frames[f][0], cam_pos[f], model) for f in used}
    skin = skin_texels(model, texel_face)
    neutral_cam, neutral_light = cam_pos[cfg.neutral_frame], lights[cfg.neutral_frame]
    albedo = _neutral_albedo(model, model.neutral, neutral_seen, texels, neutral_cam, neutral_light, cfg)
    if tiles:
        model.tile_albedo = np.stack([_neutral_albedo(model, t["texture"], t["seen"], t["texels"], neutral_cam,
                                                      neutral_light, cfg) for t in tiles.values()]).astype(np.float32)
    volumes = []
    for r, region in enumerate(cfg.regions):
        (h, w), (r0, c0) = model.alphas[r].shape, model.boxes[r]
        rows, cols = slice(r0, r0 + h), slice(c0, c0 + w)
        layers = []
        for k, f in enumerate(region.frames):
            own = texel_shading(model, cam_pos[f], lights[f], texel_face, texel_bary, rows, cols)
            layer = np.where((layer_seen[r][k] & skin[rows, cols])[..., None], model.volumes[r][k] / own,
                             albedo[rows, cols])
            layers.append(np.where(skin[rows, cols][..., None], layer, model.volumes[r][k]))
        volumes.append(np.stack(layers).astype(np.float32))
    model.neutral_albedo, model.volumes = albedo.astype(np.float32), volumes


def _texel_facing(model: AppearanceModel, camera_positions: np.ndarray, texel_face: np.ndarray,
                  texel_bary: np.ndarray, rows, cols) -> np.ndarray:
    """(h, w) the cosine between the smooth surface's normal at the texels [rows, cols] of one frame
    (V, 3, camera space) and their direction to the camera; −1 off the UV layout."""
    tf, tb = texel_face[rows, cols], texel_bary[rows, cols]
    out = np.full(tf.shape, -1.0)
    covered = tf >= 0
    if covered.any():
        out[covered] = point_facing(camera_positions, model.faces, tf[covered], tb[covered], model.normal_sign)
    return out


def skin_texels(model: AppearanceModel, texel_face: np.ndarray) -> np.ndarray:
    """(S, S) the texels on the rest mesh's triangles (not on a card, not outside the UV layout)."""
    on_card = model.faces.min(axis=1) >= model.n_vertices  # a card's triangles use only its vertices
    return (texel_face >= 0) & ~on_card[np.maximum(texel_face, 0)]


def texel_shading(model: AppearanceModel, camera_positions: np.ndarray, light: np.ndarray, texel_face: np.ndarray,
                  texel_bary: np.ndarray, rows=slice(None), cols=slice(None)) -> np.ndarray:
    """(h, w, 3) the shading of the texels [rows, cols] on one frame's surface (V, 3), camera
    space, under its light (12,): the grey light's (:func:`facepipe.core.lighting.light_shading`
    of its first nine values) times its colour (the last three; white for a light of nine); 1
    off the skin.

    Kept within the shading of the light points the frame's light was fitted on (those facing the
    camera): a normal the fit never saw (the face's rim, turned away) would get the nine terms'
    extrapolation, a bright or dark band the footage does not have."""
    whole = all(isinstance(i, slice) and i == slice(None) for i in (rows, cols))
    on, interpolation = _texel_interpolation(model, texel_face[rows, cols], texel_bary[rows, cols],
                                             texel_face if whole else None)
    out = np.ones(on.shape + (3,))
    if on.any():
        grey, colour = light[:9], (light[9:12] if len(light) >= 12 else np.ones(3))
        vn = model.normal_sign * vertex_normals(camera_positions[None], model.faces)
        normals = interpolation @ vn[0]
        normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-30)
        shading = np.clip(lighting.light_shading(normals, grey), *_fitted_shading_range(model, camera_positions, grey, vn))
        out[on] = shading[:, None] * colour
    return out


def _texel_interpolation(model: AppearanceModel, texel_face: np.ndarray, texel_bary: np.ndarray, key=None):
    """The skin texels (h, w) of a texel map and the sparse matrix (N, V) that interpolates vertex
    values at them (their barycentric weights): a frame's texel normals are one sparse product.
    With ``key`` (the whole texel map: one per UDIM tile) the pair is kept on the model for the
    next frame."""
    kept = getattr(model, "_texel_interpolations", None)
    if kept is None:
        kept = model._texel_interpolations = {}
    cached = kept.get(id(key)) if key is not None else None
    if cached is not None and cached[0] is key:
        return cached[1], cached[2]
    import scipy.sparse as sp

    on = skin_texels(model, texel_face)
    face, bary = texel_face[on], texel_bary[on]
    n = len(face)
    matrix = sp.csr_matrix((np.asarray(bary, dtype=np.float64).ravel(), (np.repeat(np.arange(n), 3),
                            model.faces[face].ravel())), shape=(n, int(model.faces.max()) + 1))
    if key is not None:
        if len(kept) >= 16:  # a texel map per UDIM tile: a head has a few
            kept.clear()
        kept[id(key)] = (key, on, matrix)
    return on, matrix


def _fitted_shading_range(model: AppearanceModel, camera_positions: np.ndarray, light: np.ndarray, vn: np.ndarray):
    """(low, high) the shading of the model's light points that face the camera in this frame
    (V, 3; ``vn`` (1, V, 3) its vertex normals) under its grey light (9,): the normals
    :func:`frame_lights` fitted it on ((0, inf) where none)."""
    X = surface_points(camera_positions, model.faces, model.light_face, model.light_bary)
    normals = point_normals(camera_positions[None], model.faces, model.light_face, model.light_bary, 1.0, vn)[0]
    facing = (normals * -X).sum(axis=-1) > model.min_facing * np.linalg.norm(X, axis=-1)
    if not facing.any():
        return 0.0, np.inf
    shading = lighting.light_shading(normals[facing], light)
    return float(shading.min()), float(shading.max())


def frame_texture(model: AppearanceModel, q: np.ndarray, camera_positions: np.ndarray | None = None,
                  light: np.ndarray | None = None, texels=None, tile: int | None = None) -> np.ndarray:
    """A frame's texture (S, S, 3) on UDIM ``tile``: on the regions' tile (``model.tile``, the
    default) the layered texture at Q (R,), on the model's other tiles (``model.tiles``, where no
    region lies) their neutral texture. For a model that holds albedo, that albedo times the
    shading of the frame's surface (V, 3, camera space) under its light (12,) on the skin (as the
    camera saw it); the albedo alone where either is not given. ``texels``: the tile's
    :func:`texel_map` where already made."""
    tile = model.tile if tile is None else tile
    if tile == model.tile:
        texture = layered_texture.compose_texture(model.base_texture, model.volumes, model.alphas, model.boxes, q)
    else:
        k = model.extra_tiles.index(tile)
        texture = model.tile_albedo[k] if model.albedo else model.tile_neutral[k]
    if not (model.albedo and camera_positions is not None and light is not None):
        return texture
    texel_face, texel_bary = texel_map(model.corner_uv, model.neutral.shape[0], tile) if texels is None else texels
    return texture * texel_shading(model, camera_positions, light, texel_face, texel_bary)


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
                     min_relative_facing: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`well_seen_points`' tests frame by frame, before the margin: (F, N) whether each frame
    shows each point well, and the points' pixels (F, N, 2)."""
    X = np.einsum("nk,fnkc->fnc", bary, camera_positions[:, faces[face]])     # (F, N, 3)
    pixels = project_distorted_fast(camera, X)
    _, inside = ap.bilinear_sample(np.zeros((camera.height, camera.width)), pixels)
    good = inside & (X[..., 2] > 0)
    if occlusion:
        good &= ~grid_points_hidden(X[:, None], camera_positions, faces, size)[:, 0]
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


def _stencil_normals(camera_positions: np.ndarray, model: AppearanceModel) -> tuple[np.ndarray, np.ndarray]:
    """Unit vertex normals (F, M, 3) of frames at the stencil's vertices, and the local index map."""
    _, local, around, incidence = _normal_stencil(model)
    v0 = camera_positions[:, around[:, 0]]
    fn = np.cross(camera_positions[:, around[:, 1]] - v0, camera_positions[:, around[:, 2]] - v0)  # (F, T, 3)
    F, T = fn.shape[:2]
    vn = np.asarray(incidence @ np.moveaxis(fn, 1, 0).reshape(T, F * 3)).reshape(-1, F, 3)
    vn = np.moveaxis(vn, 1, 0) * model.normal_sign
    return vn / np.maximum(np.linalg.norm(vn, axis=-1, keepdims=True), 1e-30), local


def _example_light(neutral, seen, neutral_cam, faces, texel_face, texel_bary, normal_sign, light_model: str,
                   samples: int = 2000):
    """The example footage's light fitted over the neutral texture's texels (their albedo taken
    as uniform: the fit is robust to what differs; its scale such that the median texel's shading
    is 1), and ``samples`` texels spread over the surface, where each frame's light will be fitted,
    with their albedo under it (grey, and colour: RGB over the grey shading).

    ``light`` is the light the templates are divided by, under ``light_model``
    (:data:`facepipe.core.lighting.LIGHT_MODELS`). ``albedo`` and ``colour`` are derived under
    the nine-term light, which the stream and the textures carry; with the point light also
    ``point_albedo``, under it: each light is fitted over the albedo its own model gives."""
    rows, cols = np.nonzero(seen & (texel_face >= 0))
    if len(rows) < 50:
        return None
    pick = np.random.default_rng(0).choice(len(rows), size=min(samples * 4, len(rows)), replace=False)
    rows, cols = rows[pick], cols[pick]
    face, bary = texel_face[rows, cols], texel_bary[rows, cols]
    normals = point_normals(neutral_cam[None], faces, face, bary, normal_sign)[0]
    lum = to_gray(neutral[rows, cols])

    def scaled(light):
        # the neutral frame's shading 1 on the median texel: the albedo it gives (and the layers')
        # is about as bright as the footage, in the range images hold
        return light / float(np.median(lighting.light_shading(normals, light)))

    light = scaled(lighting.fit_light(lum, np.ones(len(lum)), normals))
    shading = lighting.light_shading(normals, light)
    keep = slice(0, min(samples, len(rows)))
    out = {"light": light, "face": face[keep].astype(np.int64), "bary": bary[keep], "albedo": (lum / shading)[keep],
           "colour": (neutral[rows, cols] / shading[:, None])[keep], "point_albedo": None}
    if light_model == "point":
        out["light"] = scaled(lighting.fit_point_light(lum, np.ones(len(lum)), normals, start=light))
        out["point_albedo"] = (lum / lighting.light_shading(normals, out["light"]))[keep]
    return out


def _region_volume(region, config, faces, triangles, frames, cam_pos, texel_face, texel_bary, camera, neutral, cfg,
                   normal_sign):
    """A region's texture volume (n, h, w, 3) over its UV box, its alpha (h, w), the box's corner
    and where each layer's own example frame shows its texels (n, h, w) (elsewhere the neutral
    texture's): the texels of its ``triangles`` (F,) (a mask over ``faces``)."""
    mask = (texel_face >= 0) & triangles[np.maximum(texel_face, 0)]
    if not mask.any():
        raise InputError(f"region {region.name}: its vertex group covers no texel of the UV layout", path=config.path,
                         hint="the group needs whole triangles with UVs (or a larger texture_size)")
    r_idx, c_idx = np.nonzero(mask)
    rows, cols = slice(r_idx.min(), r_idx.max() + 1), slice(c_idx.min(), c_idx.max() + 1)
    layers, seen_in = [], []
    for f in region.frames:
        colours, seen = unwrap(frames[f][0], cam_pos[f], faces, texel_face, texel_bary, camera, rows, cols,
                               cfg.min_facing, normal_sign)
        layers.append(np.where(seen[..., None], colours, neutral[rows, cols]))
        seen_in.append(seen)
    alpha = layered_texture.region_alpha(mask[rows, cols], cfg.ramp)
    return np.stack(layers), alpha, (rows.start, cols.start), np.stack(seen_in)


def _shading_surface(cfg, region, patches: np.ndarray, mask: np.ndarray, weights: np.ndarray
                     ) -> tuple[int, float | None]:
    """The order of the shading surface a region's patches (its layers, n × size × size, over the
    stable texels ``mask``) are divided by: the region's ``shading_surface``, else the table's;
    "auto" chooses by :func:`facepipe.core.appearance.shading_order`. With it the share of the
    layers' contrast the quadratic keeps (None where not measured)."""
    surface = region.shading_surface or cfg.shading_surface
    if surface != "auto" or not cfg.shading:
        return (2 if surface == "quadratic" else 1), None
    return ap.shading_order(patches, mask, weights, cfg.keep)


def _read_group(region, n_vertices: int, config_path) -> np.ndarray:
    path = region.vertices
    if not path.is_file():
        raise InputError(f"region {region.name}: vertex group file not found", path=path,
                         hint="one 0-based vertex index per line")
    values = []
    for line_no, line in enumerate(path.read_text().splitlines(), start=1):
        text = line.split("#")[0].strip()
        if not text:
            continue
        if not text.isdigit() or int(text) >= n_vertices:
            raise InputError(f"line {line_no}: {text!r} is not a vertex index below {n_vertices}", path=path)
        values.append(int(text))
    if not values:
        raise InputError(f"region {region.name}: the vertex group is empty", path=path)
    return np.asarray(values, dtype=np.int64)


def _region_template(region, rect, corner_uv, size: int, config_path) -> tuple[np.ndarray, np.ndarray]:
    pts = template_points(rect, size)
    face, bary = locate_uv(pts.reshape(-1, 2), corner_uv)
    if (face < 0).any():
        k = int(np.argmax(face < 0))
        u, v = pts.reshape(-1, 2)[k]
        raise InputError(f"region {region.name}: template = {region.template} reaches outside the UV layout (at "
                         f"u {u:.4f}, v {v:.4f}, with the half-step offsets)", path=config_path,
                         hint="put the template rectangle well inside the region's UV triangles")
    return face.reshape(5, -1), bary.reshape(5, -1, 3)


def texture_differences(model: AppearanceModel, texel_face: np.ndarray, texel_bary: np.ndarray, image: np.ndarray,
                        camera_positions: np.ndarray, q: np.ndarray, light: np.ndarray | None = None) -> np.ndarray:
    """How far the frame's texture at Q (:func:`frame_texture`, shaded under ``light`` (9,) where
    the model holds albedo) and the neutral texture are from a frame's own texels.

    The frame (RGB image, its geometry in camera space) is unwrapped into the texture through the
    rest mesh's texel map (:func:`texel_map` at the model's texture size) as the layers were.
    Returns (R, 3) per region over its texels (alpha > 0) the frame shows: the sum of squared
    differences of the reconstruction at ``q`` (R,), that of the neutral texture (as the neutral
    frame showed it: what a face without the stream would wear), and the count of texel channels —
    an RMS ratio below 1 says the stream brings the texture closer to the frame.
    """
    out = np.zeros((len(model.names), 3))
    texture = frame_texture(model, q, camera_positions, light, (texel_face, texel_bary))
    for r, (alpha, (r0, c0)) in enumerate(zip(model.alphas, model.boxes)):
        rows, cols = slice(r0, r0 + alpha.shape[0]), slice(c0, c0 + alpha.shape[1])
        truth, seen = unwrap(image, camera_positions, model.faces, texel_face, texel_bary, model.camera, rows, cols,
                             model.min_facing, model.normal_sign)
        use = seen & (alpha > 0)
        out[r] = (((texture[rows, cols] - truth)[use] ** 2).sum(), ((model.neutral[rows, cols] - truth)[use] ** 2).sum(),
                  3 * use.sum())
    return out


@dataclass
class Classification:
    """Q (T, R) after hold and decay and with brief departures from rest dropped
    (:func:`facepipe.core.appearance.drop_short_events`), raw (T, R) before (NaN where hidden), visible (T, R), frame
    numbers (T,), times (T,), problems: (frame, text) of frames that were skipped; light (T, 12):
    each frame's grey light (:func:`frame_lights`) and its colour (:func:`frame_colours`) (a
    skipped frame holds the last one fitted, the first ones the first), None for a model without
    light points."""

    names: list
    q: np.ndarray
    raw: np.ndarray
    visible: np.ndarray
    numbers: np.ndarray
    times: np.ndarray
    problems: list
    light: np.ndarray | None = None
    brief: np.ndarray | None = None  # (T, R) readings set back to rest as brief (``min_event``)
    in_view: np.ndarray | None = None  # (T, R) share of each region's stable template points in view (NaN: skipped)


def classify_frames(model: AppearanceModel, footage_source, positions: np.ndarray, numbers: np.ndarray,
                    times: np.ndarray, progress=None, chunk: int = 8, footage_numbers=None) -> Classification:
    """Classify every frame of the geometry (world positions (T, V, 3), frame numbers (T,)) in the
    footage (a path, pattern or folder, or a :class:`~facepipe.io.footage.Footage` already opened):
    each geometry frame's image is the footage's frame of the same number, or of
    ``footage_numbers`` (T,) where given (e.g. :func:`facepipe.io.footage.frames_at`).

    The next frames are read and decoded in a worker thread while these are classified (image
    decoding releases the GIL); ``chunk`` frames are classified at once, all their regions and
    offsets in the same products, a chunk on each of facepipe's threads (:func:`classify_decoded`).
    """
    footage = footage_source if isinstance(footage_source, Footage) else open_footage(footage_source)
    T, Rn = len(numbers), len(model.names)
    raw = np.full((T, Rn), np.nan)
    visible = np.zeros((T, Rn), dtype=bool)
    in_view = np.full((T, Rn), np.nan)
    light = None if model.light_face is None else np.full((T, 12), np.nan)
    problems = []
    bank = region_bank(model)
    rows, grays, images = [], [], []
    batch = chunk * thread_count()  # a chunk for each of facepipe's threads

    def flush():
        if rows:
            readings = classify_decoded(np.stack(grays), model.to_camera(positions[rows]), model, bank, chunk,
                                        images=np.stack(images))
            raw[rows], visible[rows], in_view[rows] = readings.q, readings.visible, readings.in_view
            if light is not None:
                light[rows] = readings.light
            if progress is not None:
                progress(len(rows))
        rows.clear()
        grays.clear()
        images.clear()

    at = numbers if footage_numbers is None else footage_numbers
    for shown, image, problem in _read_ahead(read_frames_of(footage, at)):
        if image is None:
            problems += [(int(numbers[i]), problem) for i in shown]  # said by the take's frame numbers
            if progress is not None:
                progress(len(shown))
            continue
        if image.shape[:2] != (model.camera.height, model.camera.width):
            _check_size(image, model.camera, int(at[shown[0]]), footage.source)
        gray = to_gray(image)
        for i in shown:
            rows.append(i)
            grays.append(gray)
            images.append(image[..., :3])
            if len(rows) == batch:
                flush()
    flush()
    # a hidden stretch holds the last reading taken with most of the template in view
    well_seen = visible & (np.nan_to_num(in_view) >= max(WELL_SEEN, model.min_seen))
    held = ap.hold_and_decay(np.nan_to_num(raw), visible, times, model.decay, well_seen)
    q = ap.drop_short_events(held, times, model.min_event)
    return Classification(list(model.names), q, raw, visible, np.asarray(numbers), np.asarray(times), problems,
                          None if light is None else _held(light, WHITE_LIGHT), brief=(held > 0) & (q == 0),
                          in_view=in_view)


#: A hidden region holds its last reading taken with at least this share of its template's stable
#: points in view — in the image and not hidden by the face (or ``min_seen``, if higher): the frames
#: before a lid closes over an eyeball read what is left of it, and holding that would carry it
#: through the blink. Points turned edge-on do not count against it: a region turning away is read
#: well until it is hidden.
WELL_SEEN = 0.9

#: A uniform white light: what a frame gets when no frame of the take could be classified.
WHITE_LIGHT = np.r_[1.0, np.zeros(8), np.ones(3)]


def _held(rows: np.ndarray, default: np.ndarray) -> np.ndarray:
    """Rows (T, n) with every NaN row (a frame not classified) replaced by the last finite one
    before it, or the first after it at the start; ``default`` (n,) everywhere when none is finite."""
    known = np.isfinite(rows).all(axis=1)
    if not known.any():
        return np.tile(default, (len(rows), 1))
    index = np.maximum.accumulate(np.where(known, np.arange(len(rows)), -1))
    index[index < 0] = int(np.argmax(known))
    return rows[index]


@dataclass
class FrameReadings:
    """What :func:`classify_decoded` reads of frames: Q (F, R), NaN where a region is hidden;
    each region's visibility (F, R); each frame's nine-term light (F, 9), or (F, 12) with its
    colour where the frames' RGB images were given (None for a model without light points); and
    the share of each region's stable template points in view (F, R; :func:`_classify_chunk`)."""

    q: np.ndarray
    visible: np.ndarray
    light: np.ndarray | None
    in_view: np.ndarray


def classify_decoded(grays: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, bank=None,
                     chunk: int = 8, images: np.ndarray | None = None) -> FrameReadings:
    """:func:`classify_chunk` of decoded frames (F, H, W) with their geometry in camera space
    (F, V, 3), ``chunk`` frames at a time on facepipe's threads (:func:`facepipe.parallel.map_blocks`):
    the same numbers as one chunk after another, about 1.5 times the frames a second on two cores
    (most of a chunk's time is in NumPy, which lets the other thread run). ``images``: the frames
    in RGB (F, H, W, 3), for each frame's light colour."""
    bank = region_bank(model) if bank is None else bank
    if len(grays) == 0:
        n = len(model.names)
        light = None if model.light_face is None else np.zeros((0, 9 if images is None else 12))
        return FrameReadings(np.zeros((0, n)), np.zeros((0, n), dtype=bool), light, np.zeros((0, n)))
    with serial_blas():  # process-wide: entered once here, not by each thread
        parts = map_blocks(lambda i: _classify_chunk(grays[i:i + chunk], camera_positions[i:i + chunk], model, bank,
                                                     None if images is None else images[i:i + chunk]),
                           range(0, len(grays), chunk))
    return FrameReadings(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                         None if model.light_face is None else np.concatenate([p[2] for p in parts]),
                         np.concatenate([p[3] for p in parts]))


def classify_chunk(grays: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, bank=None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Q (F, R) of frames' luminance (F, H, W) with their geometry in camera space (F, V, 3), NaN
    where a region is hidden, and each region's visibility (F, R).

    BLAS runs on one thread here: its products are small (a light fit's 9 × 9, a chunk's
    patches), and OpenBLAS's threads only wait on each other over them, taking CPU time from
    whatever else runs (a classification's CPU time halves)."""
    with serial_blas():
        return _classify_chunk(grays, camera_positions, model, bank)[:2]


def _classify_chunk(grays, camera_positions, model: AppearanceModel, bank, images=None):
    """Q (F, R), visibility (F, R), each frame's light (:func:`frame_shading`; None without light
    points) and the share of each region's stable template points in view (F, R): in the image
    and not hidden by the face, however edge-on."""
    bank = region_bank(model) if bank is None else bank
    points = template_positions(camera_positions, model)
    patches, visible, seen = sample_template_frames(grays, camera_positions, model, points)
    in_view = seen_fraction(seen, model)  # in the image, not hidden by the face (edge-on or not)
    normals = light = None
    if model.light_face is not None:
        shading, normals, light = frame_shading(grays, camera_positions, model, images)
        patches = patches / shading
    if model.min_point_facing > 0:
        seen = seen & (template_point_facing(camera_positions, model, normals, points) > model.min_point_facing)
        if model.template_mask is None and model.template_facing is not None:
            # models before the stable points: a point the examples saw edge-on has no template worth matching
            s = model.template_size
            seen &= (model.template_facing > model.min_point_facing).reshape(model.template_facing.shape[:2] + (s, s))
        visible &= seen_fraction(seen, model) >= model.min_seen
    q, _ = ap.classify_regions(patches, bank, model.shading, seen, model.min_seen, model.peak_interpolation)
    visible &= np.isfinite(q)
    if model.rest_floor is not None:
        q = ap.above_rest(q, model.rest_floor, model.layer_counts)
    return np.where(visible, q, np.nan), visible, light, in_view


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


def _light_points(camera_positions: np.ndarray, model: AppearanceModel, stencil=None):
    """The model's light points in frames (F, V, 3, camera space): their unit normals (F, K, 3),
    pixels (F, K, 2) and whether each faces the camera (F, K). ``stencil``: :func:`_stencil_normals`
    of these frames where already computed."""
    vn, local = _stencil_normals(camera_positions, model) if stencil is None else stencil
    X = np.einsum("kj,fkjc->fkc", model.light_bary, camera_positions[:, model.faces[model.light_face]])  # (F, K, 3)
    normals = point_normals(camera_positions, local[model.faces], model.light_face, model.light_bary, 1.0, vn)
    facing = (normals * -X).sum(axis=-1) > model.min_facing * np.linalg.norm(X, axis=-1)
    return normals, project_distorted_fast(model.camera, X), facing


def _light_point_values(images: np.ndarray, points) -> np.ndarray:
    """(F, K[, C]) the light points' values (:func:`_light_points`) sampled from the images
    (F, H, W[, C]), NaN where outside the image or not facing the camera."""
    _, pixels, facing = points
    values = np.empty(pixels.shape[:2] + images.shape[3:])
    for f in range(len(images)):
        sampled, inside = ap.bilinear_sample(images[f], pixels[f])
        values[f] = sampled
        values[f][~(facing[f] & inside)] = np.nan
    return values


def frame_lights(grays: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, points=None
                 ) -> np.ndarray:
    """(F, 9) each frame's grey light, fitted (:func:`facepipe.core.lighting.fit_light`) over the
    model's light points: their albedo known, their normals from the frame's geometry (F, V, 3,
    camera space), their values sampled from its luminance (F, H, W) where in the image and facing
    the camera. ``points``: :func:`_light_points` of these frames where already computed."""
    points = _light_points(camera_positions, model) if points is None else points
    return lighting.fit_light(_light_point_values(grays, points), model.light_albedo, points[0])


def frame_colours(images: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, lights: np.ndarray,
                  points=None) -> np.ndarray:
    """(F, 3) each frame's light colour: per channel the median, over the light points the frame
    shows, of their value in the RGB frame (F, H, W, 3) over their colour albedo times their
    shading under the frame's grey light (F, 9). About 1 for the light the examples were shot
    under; a warmer light reads red over blue. White (1, 1, 1) where the model keeps no colour
    albedo or too few points are seen. ``points``: as for :func:`frame_lights`."""
    out = np.ones((len(images), 3))
    if model.light_colour is None:
        return out
    points = _light_points(camera_positions, model) if points is None else points
    values, normals = _light_point_values(images, points), points[0]  # (F, K, 3) both
    for f in range(len(images)):
        seen = np.isfinite(values[f]).all(axis=-1)
        if seen.sum() >= 27:  # as many as a light fit needs
            predicted = model.light_colour[seen] * lighting.light_shading(normals[f][seen], lights[f])[:, None]
            out[f] = np.median(values[f][seen] / np.maximum(predicted, 1e-6), axis=0)
    return out


def frame_light(image: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel) -> np.ndarray:
    """(12,) one RGB frame's (H, W, 3) light with its geometry (V, 3, camera space): the grey
    light's nine coefficients (:func:`frame_lights`) and its colour (:func:`frame_colours`)."""
    points = _light_points(camera_positions[None], model)
    grey = frame_lights(to_gray(image)[None], camera_positions[None], model, points)
    return np.concatenate([grey, frame_colours(image[None, ..., :3], camera_positions[None], model, grey, points)],
                          axis=1)[0]


def frame_shading(grays: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, images=None):
    """The shading (F, R, 5, size, size) at the template points of frames under each frame's light
    (fitted as the model's ``light_model`` says), the template points' unit normals (F, R, 5, N, 3)
    and the nine-term lights (:func:`frame_lights`), which the stream carries: (F, 9),
    or with the frames' RGB ``images`` (F, H, W, 3) (F, 12), their colour after them
    (:func:`frame_colours`, from the same light points)."""
    stencil = _stencil_normals(camera_positions, model)
    vn, local = stencil
    points = _light_points(camera_positions, model, stencil)
    values = _light_point_values(grays, points)
    light = lighting.fit_light(values, model.light_albedo, points[0])  # (F, 9): the stream's light (frame_lights)
    # the templates' shading under the model's own light (a point light's terminator is a kink nine terms round off)
    shading_light = lighting.fit_point_light(values, model.light_point_albedo, points[0], start=light) \
        if model.light_model == "point" else light
    if images is not None:
        light = np.concatenate([light, frame_colours(images, camera_positions, model, light, points)], axis=1)
    t_normals = point_normals(camera_positions, local[model.faces], model.template_face, model.template_bary, 1.0,
                              vn)  # (F, R, 5, N, 3)
    out = np.stack([lighting.light_shading(t_normals[f], shading_light[f]) for f in range(len(grays))])
    s = model.template_size
    return out.reshape(out.shape[:3] + (s, s)), t_normals, light


def classify_image(gray: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, bank=None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Q (R,) of one frame's luminance (NaN where hidden) and each region's visibility (R,)."""
    q, seen = classify_chunk(gray[None], camera_positions[None], model, bank)
    return q[0], seen[0]


def _read_ahead(frames, depth: int = 4):
    """The items of an iterator, produced up to ``depth`` ahead by a worker thread (which stops
    when the consumer does, e.g. on bad input)."""
    box: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def hand_over(item) -> bool:
        while not stop.is_set():
            try:
                box.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def work():
        try:
            for item in frames:
                if not hand_over(item):
                    return
        except BaseException as exc:  # raised in the consumer
            hand_over(exc)
        hand_over(done)

    worker = threading.Thread(target=work, daemon=True)
    worker.start()
    try:
        while True:
            item = box.get()
            if item is done:
                break
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        worker.join()
