"""Preview of a 2D take's replay: the replayed face seen through the camera of the footage.

One panel per chosen frame: the replayed face in camera coordinates, projected through the
calibration the replay was lifted with (lens distortion included, :func:`pinhole_project`) and
shaded, in the footage's pixel coordinates (the axes are the footage's pixels; the panels show the
window of the image the face moves in over the chosen frames). Over it: the tracked landmarks
(circles; those the lift set aside as slipping are crosses) and the replayed face's landmark
vertices projected through the same camera (dots) — where a dot sits in its circle the replay
overlays the footage. The camera, landmark map and tracked points come from the replay folder's
``video.npz`` (:mod:`facepipe.io.video_record`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.lines import Line2D

from facepipe.cli.preview import _figure, _save, _shown_frames, check_image_path
from facepipe.core.render import PinholeCamera, image_window, pinhole_project, render
from facepipe.errors import InputError

__all__ = ["render_camera_preview", "camera_coordinates", "face_window"]

MAX_COLUMNS = 3


def camera_coordinates(replay, index: np.ndarray) -> list[np.ndarray]:
    """The replayed surfaces of the frames ``index`` in the camera's coordinates (T, V, 3): as
    written with ``--head-motion keep``, else moved there by the lifted head pose."""
    handles = replay.handles
    R = handles["rotation"].astype(np.float64)
    t = handles["translation"].astype(np.float64)
    keep = handles["head_motion"] == "keep"
    out = []
    for i in index:
        x = np.asarray(replay.positions[i], dtype=np.float64)
        out.append(x if keep else x @ R[i].T + t[i])
    return out


def face_window(pixels: np.ndarray, width: int, height: int, margin: float = 0.08):
    """The window of a width × height image holding ``pixels`` (…, 2; NaN ignored) with a margin (a
    fraction of their extent), within the image; the whole image when nothing of them is in it.

    Returns (x0, y0, w, h): the centre of the window's first pixel (pixel centres at integers, so
    its edge is at x0 − ½) and its size in pixels."""
    p = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    p = p[np.isfinite(p).all(axis=1)]
    inside = p[(p[:, 0] >= -0.5) & (p[:, 0] <= width - 0.5) & (p[:, 1] >= -0.5) & (p[:, 1] <= height - 0.5)]
    if len(inside) == 0:
        return 0.0, 0.0, float(width), float(height)
    lo, hi = inside.min(axis=0), inside.max(axis=0)
    pad = margin * max(hi[0] - lo[0], hi[1] - lo[1], 1.0)
    x0, y0 = max(-0.5, lo[0] - pad), max(-0.5, lo[1] - pad)
    x1, y1 = min(width - 0.5, hi[0] + pad), min(height - 0.5, hi[1] + pad)
    return float(x0 + 0.5), float(y0 + 0.5), float(x1 - x0), float(y1 - y0)


def render_camera_preview(replay, model, path: str | os.PathLike, *, frame_numbers=None, strip: int = 0,
                          size: int = 420, force: bool = False) -> dict:
    """Render the camera-view preview of a 2D take's replay (see the module docstring).

    Parameters
    ----------
    replay : facepipe.io.replay_folder.ReplayDir of a 2D take (with ``video.npz``).
    model : its Model (the triangles to draw).
    path : image to write, atomically; not overwritten without ``force``.
    frame_numbers, strip : the frames shown (as :func:`facepipe.cli.preview.render_preview`).
    size : pixel width of one panel.

    Returns
    -------
    dict: ``frames`` shown, per frame the RMS distance (px) between the tracked landmarks the lift
    used and the replayed face's (``reprojection_px``, None where the tracker lost the face), the
    image ``window`` (x0, y0, width, height in the footage's pixels) and ``path``.
    """
    path = Path(path)
    check_image_path(path, force)
    video = replay.video
    if video is None:
        raise InputError("this replay is not of a 2D take (no video.npz): there is no camera to look through",
                         path=replay.path, hint="preview it without --view camera")
    cam = video.camera
    index = _shown_frames(replay, replay.handles["head"], model, frame_numbers, strip)
    surfaces = camera_coordinates(replay, index)
    faces = model.triangles.astype(np.int64)
    projected = [pinhole_project(cam.matrix, cam.distortion, x) for x in surfaces]
    x0, y0, w, h = face_window(np.concatenate(projected + [video.tracked[index].reshape(-1, 2)]), cam.width,
                               cam.height)
    scale = size / w
    panel = PinholeCamera(image_window(cam.matrix, x0, y0, scale), cam.distortion, int(size),
                          max(1, int(round(h * scale))))
    extent = (x0 - 0.5, x0 - 0.5 + panel.width / scale, y0 - 0.5 + panel.height / scale, y0 - 0.5)
    columns = min(MAX_COLUMNS, len(index))
    rows = -(-len(index) // columns)
    fig, axes = _grid(panel, rows, columns)
    summary = {"frames": [], "reprojection_px": [], "window": [x0, y0, w, h], "view": "camera"}
    for k, (i, x, px) in enumerate(zip(index, surfaces, projected)):
        ax = axes[k // columns, k % columns]
        ax.imshow(render(x, faces, panel), extent=extent, interpolation="antialiased")
        tracked, used = video.tracked[i], video.used[i]
        replayed = px[video.vertices]
        slipped = np.isfinite(tracked).all(axis=1) & ~used
        ax.plot(tracked[used, 0], tracked[used, 1], "o", ms=5, mfc="none", mec="tab:green", mew=0.9)
        ax.plot(tracked[slipped, 0], tracked[slipped, 1], "x", ms=5, color="tab:orange", mew=1.1)
        ax.plot(replayed[:, 0], replayed[:, 1], ".", ms=3, color="tab:red")
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.tick_params(labelsize=6, length=2)
        frame = int(replay.frame_numbers[i])
        if used.any():
            rms = float(np.sqrt((np.linalg.norm(replayed[used] - tracked[used], axis=1) ** 2).mean()))
            note = f"reprojection RMS {rms:.2f} px"
        else:
            rms = None
            note = "tracker lost the face: pose interpolated"
        ax.set_title(f"frame {frame}: {note}", fontsize=8)
        summary["frames"].append(frame)
        summary["reprojection_px"].append(rms)
    for k in range(len(index), rows * columns):
        axes[k // columns, k % columns].set_axis_off()
    fig.legend(handles=[Line2D([], [], ls="", marker="o", mfc="none", mec="tab:green", label="tracked landmark"),
                        Line2D([], [], ls="", marker="x", color="tab:orange", label="set aside (slipping)"),
                        Line2D([], [], ls="", marker=".", color="tab:red", label="replayed face's landmark")],
               loc="lower center", ncol=3, fontsize=8, frameon=False)
    _save(fig, path, force)
    summary["path"] = str(path)
    return summary


def _grid(panel: PinholeCamera, rows: int, columns: int, dpi: int = 100):
    """A figure of rows × columns panels of the camera window's size with room for titles, tick
    labels and the legend: (figure, (rows, columns) axes)."""
    panel_w, panel_h = panel.width / dpi, panel.height / dpi
    title_h, ticks_w, legend_h = 0.3, 0.45, 0.35
    fig_w = (panel_w + ticks_w) * columns
    fig_h = (panel_h + title_h + 0.2) * rows + legend_h
    fig = _figure(fig_w, fig_h, dpi)
    fig.subplots_adjust(left=ticks_w / fig_w, right=1 - 0.05 / fig_w, top=1 - title_h / fig_h,
                        bottom=(legend_h + 0.2) / fig_h, wspace=ticks_w / panel_w,
                        hspace=(title_h + 0.2) / panel_h)
    return fig, np.atleast_2d(fig.subplots(rows, columns, squeeze=False))
