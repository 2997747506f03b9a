"""``facepipe preview`` of a classified take (a folder with ``appearance.csv``): per chosen frame
the input frame and the face rendered through the same camera with that frame's texture
(:func:`facepipe.pipeline.appearance_texture.frame_texture`: the layered albedo at its Q shaded by the
frame's geometry under its light, or a model's layers as the footage showed them) over the input frame,
side by side over the face's window of the image; below them the Q curves of every region over
the take, the shown frames marked. The footage, geometry and model are the ones ``appearance.json`` names.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from facepipe.appearance_sample import Scene, render_frame
from facepipe.cli.preview import _figure, _save, check_image_path
from facepipe.core.camera import project_distorted_fast
from facepipe.errors import InputError
from facepipe.io.appearance_file import load_appearance, read_light, read_stream
from facepipe.io.footage import frames_at, open_footage, read_frames_of
from facepipe.core.raster import udim_corner, udim_tile_numbers
from facepipe.pipeline.appearance import take_geometry
from facepipe.pipeline.appearance_points import texel_map
from facepipe.pipeline.appearance_texture import frame_texture

__all__ = ["render_appearance_preview", "is_classified", "over_footage"]


def is_classified(folder) -> bool:
    """Whether a folder holds a classification (``appearance.csv`` and ``appearance.json``)."""
    folder = Path(folder)
    return (folder / "appearance.csv").is_file() and (folder / "appearance.json").is_file()


def _shown(numbers: np.ndarray, q: np.ndarray, frame_numbers, strip: int) -> np.ndarray:
    if frame_numbers:
        missing = [f for f in frame_numbers if f not in set(numbers.tolist())]
        if missing:
            raise InputError(f"frame {missing[0]} is not in the classified take ({numbers[0]}..{numbers[-1]})",
                             hint="choose --frame among the take's frame numbers")
        return np.array([int(np.flatnonzero(numbers == f)[0]) for f in frame_numbers])
    if strip > 0:
        return np.unique(np.linspace(0, len(numbers) - 1, min(strip, len(numbers))).round().astype(np.int64))
    return np.array([int(np.argmax(q.sum(axis=1)))])  # the frame furthest from neutral


def render_appearance_preview(folder, path: str | os.PathLike, *, model_path=None, frame_numbers=None, strip: int = 0,
                              size: int = 420, force: bool = False) -> dict:
    """Render the preview (see the module docstring); returns ``frames`` shown, their ``q`` and ``path``."""
    path = Path(path)
    check_image_path(path, force)
    folder = Path(folder)
    info, numbers, times, q = read_stream(folder)
    for key in ("footage", "geometry"):
        if not info.get(key):
            raise InputError(f"appearance.json does not name the {key} classified", path=folder / "appearance.json",
                             hint="classify the footage again with this facepipe version")
    model = load_appearance(model_path or info["model"])
    if model.corner_uv is None:
        raise InputError("the appearance model has no UVs to render its texture with", path=model_path or info["model"],
                         hint="build it again with this facepipe version: facepipe appearance build CONFIG")
    geometry, model, _ = take_geometry(info["geometry"], model)
    positions = geometry.positions
    index = _shown(numbers, q, frame_numbers, strip)
    row_of = {int(n): i for i, n in enumerate(geometry.numbers)}
    footage = open_footage(info["footage"])
    # the footage's frames as classification found them (by the take's own times where it has them)
    at, _ = frames_at(footage, geometry.numbers, geometry.times)
    shown_at = np.array([at[row_of[int(numbers[i])]] if int(numbers[i]) in row_of else numbers[i] for i in index])
    images = {int(numbers[index[k]]): (image, problem)
              for rows, image, problem in read_frames_of(footage, shown_at) for k in rows}
    light = read_light(folder, numbers)
    tiles = model.all_tiles
    size_t = model.neutral.shape[0]
    texels = {t: texel_map(model.corner_uv, size_t, t) for t in tiles} if model.albedo and light is not None else {}
    cam = model.camera
    # unlit: ambient 1 shows the texture's own values (the frame's shading is in them: its light on
    # its geometry, or the footage's own in a model without albedo layers)
    scene = Scene(cam.matrix, cam.distortion, cam.width, cam.height, model.rotation, model.translation,
                  np.array([0.0, 0.0, -1.0]), (1.0, 1.0, 1.0), 1.0)
    # the model's UDIM tiles side by side in one texture (tile k at u in k..k+1 over K); triangles
    # on a tile the model has no texture for are left out, the frame showing there
    faces, corner_uv = _atlas_layout(model.faces, model.corner_uv, tiles)
    rows = len(index)
    panel_w = size / 100.0
    fig = _figure(2 * panel_w, rows * panel_w + 2.4)
    grid = fig.add_gridspec(rows + 1, 2, height_ratios=[panel_w] * rows + [2.2], hspace=0.25, wspace=0.04,
                            left=0.06, right=0.98, top=0.97, bottom=0.06)
    for k, i in enumerate(index):
        n = int(numbers[i])
        if n not in row_of:
            raise InputError(f"frame {n} has no geometry", path=info["geometry"])
        world = positions[row_of[n]]
        drawn = model.with_cards(world)  # the cards extended once: drawn in world space, textured in camera space
        where, lit = drawn @ model.rotation.T + model.translation, None if light is None else light[i]
        texture = np.ascontiguousarray(np.concatenate(
            [frame_texture(model, q[i], where, lit, texels.get(t), t) for t in tiles], axis=1), dtype=np.float32)
        image, problem = images.get(n, (None, "not read"))
        # over black, with the share of each pixel the face covers: the face's colour
        # premultiplied by its coverage, so its silhouette blends into the frame
        face, coverage = render_frame(drawn, faces, corner_uv, texture, scene, background=0.0, with_coverage=True)
        rendered = over_footage(face, coverage[..., None], image)
        x0, x1, y0, y1 = _window(model, where)
        for c, (picture, title) in enumerate(((image, f"frame {n}: input"),
                                              (rendered, "layered texture at Q, over the input frame"))):
            ax = fig.add_subplot(grid[k, c])
            if picture is None:
                ax.text(0.5, 0.5, f"no image: {problem}", ha="center", va="center", fontsize=8)
            else:
                ax.imshow(np.clip(picture[y0:y1, x0:x1, :3], 0, 1), interpolation="antialiased")
            ax.set_title(title, fontsize=8)
            ax.set_axis_off()
    ax = fig.add_subplot(grid[rows, :])
    for r, name in enumerate(model.names):
        ax.plot(numbers, q[:, r], lw=1.0, label=name)
    for i in index:
        ax.axvline(numbers[i], color="k", lw=0.6, ls="--")
    ax.set_xlabel("frame", fontsize=8)
    ax.set_ylabel("Q (layer)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=6, ncol=4, loc="upper right", frameon=False)
    _save(fig, path, force)
    return {"frames": [int(numbers[i]) for i in index], "q": q[index].tolist(), "path": str(path),
            "view": "appearance",
            "unread": {int(n): problem for n, (image, problem) in images.items() if image is None}}


def _atlas_layout(faces: np.ndarray, corner_uv: np.ndarray, tiles: list) -> tuple[np.ndarray, np.ndarray]:
    """The triangles (F, 3) on the UDIM ``tiles`` and their UVs (F, 3, 2) in an atlas of those tiles
    side by side, tile k at u in [k/K, (k+1)/K] (each tile's texture is square)."""
    tile, valid = udim_tile_numbers(corner_uv)
    keep = valid & np.isin(tile, tiles)
    slot = np.searchsorted(np.asarray(tiles), tile[keep])
    corner = np.stack(udim_corner(np.asarray(tiles)[slot]), axis=1)
    uv = corner_uv[keep] - corner[:, None, :]
    uv[..., 0] = (uv[..., 0] + slot[:, None]) / len(tiles)
    return faces[keep], uv


def over_footage(rendered: np.ndarray, coverage: np.ndarray, image: np.ndarray | None) -> np.ndarray:
    """The reconstruction over the input frame (both (H, W, 3)): ``rendered`` over black, i.e.
    premultiplied by ``coverage``, the share of each pixel the face covers. The frame shows where
    the face is not drawn (background, hair, the mouth's and eyes' openings) and through its
    silhouette, so the two panels differ only where the face's texture does; white stands in for
    a frame that could not be read."""
    under = np.ones_like(rendered) if image is None else np.asarray(image, dtype=np.float32)[..., :3]
    return rendered + (1.0 - np.clip(coverage, 0.0, 1.0)) * under


def _window(model, camera_positions: np.ndarray, margin: float = 0.08) -> tuple[int, int, int, int]:
    """The face's square window of the image (x0, x1, y0, y1), from its vertices (V, 3) in camera
    space projected."""
    px = project_distorted_fast(model.camera, camera_positions)
    px = px[np.isfinite(px).all(axis=1)]
    lo, hi = px.min(axis=0), px.max(axis=0)
    side = (1 + 2 * margin) * float(max(hi - lo))
    centre = 0.5 * (lo + hi)
    W, H = model.camera.width, model.camera.height
    x0 = int(np.clip(centre[0] - side / 2, 0, W - 1))
    y0 = int(np.clip(centre[1] - side / 2, 0, H - 1))
    return x0, int(np.clip(x0 + side, x0 + 1, W)), y0, int(np.clip(y0 + side, y0 + 1, H))
