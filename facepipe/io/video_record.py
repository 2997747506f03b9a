"""``video.npz`` in a replay folder: what a 2D take's replay was made from, for previews.

A replay of a 2D landmark take writes beside ``positions.npy``: the camera it was lifted through
(matrix, distortion, image size and the calibration file's absolute path), the landmark map (names
and rig vertices) and the tracked points per frame in pixels of the footage (NaN where missing),
with the samples the lift used (tracked and not slipping). ``facepipe preview`` draws the replayed
face through that camera with the tracked and reprojected landmarks over it, without the take,
the calibration file or the map having to be where they were.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facepipe.core.camera import Camera
from facepipe.errors import InputError
from facepipe.io.atomic import atomic_path

__all__ = ["VideoRecord", "read_video_record", "write_video_record", "VIDEO_RECORD"]

VIDEO_RECORD = "video.npz"


@dataclass
class VideoRecord:
    """camera : the calibration; names (L,), vertices (L,) : the landmark map; tracked (T, L, 2) :
    pixels of the footage, NaN where missing; used (T, L) : samples the lift used; failed (T,) :
    frames the tracker reported lost; frames (T,) : take frame numbers."""

    camera: Camera
    names: list
    vertices: np.ndarray
    tracked: np.ndarray
    used: np.ndarray
    failed: np.ndarray
    frames: np.ndarray


def write_video_record(folder, record: VideoRecord) -> Path:
    """Write ``folder/video.npz`` atomically; returns its path."""
    path = Path(folder) / VIDEO_RECORD
    cam = record.camera
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, camera_matrix=np.asarray(cam.matrix, dtype=np.float64),
                     distortion=np.asarray(cam.distortion, dtype=np.float64).reshape(-1),
                     image_size=np.array([cam.width, cam.height], dtype=np.int64),
                     camera_path=np.array(str(Path(cam.path).resolve()) if cam.path else ""),
                     landmark_names=np.asarray([str(n) for n in record.names], dtype=np.str_),
                     landmark_vertices=np.asarray(record.vertices, dtype=np.int64),
                     tracked=np.asarray(record.tracked, dtype=np.float64),
                     used=np.asarray(record.used, dtype=bool), failed=np.asarray(record.failed, dtype=bool),
                     frame=np.asarray(record.frames, dtype=np.int64))
    return path


def read_video_record(folder, n_frames: int, n_vertices: int) -> VideoRecord | None:
    """``folder/video.npz``, checked against the replay's frame and vertex counts; None when the
    replay is not of a 2D take (no such file).

    Raises
    ------
    InputError
        An unreadable or inconsistent file, naming it.
    """
    path = Path(folder) / VIDEO_RECORD
    if not path.is_file():
        return None
    hint = "replay the 2D take again with this facepipe version"
    try:
        with np.load(path, allow_pickle=False) as data:
            d = {k: data[k] for k in data.files}
        matrix, dist = d["camera_matrix"].astype(np.float64), d["distortion"].astype(np.float64)
        width, height = (int(v) for v in d["image_size"])
        names, vertices = [str(n) for n in d["landmark_names"]], d["landmark_vertices"].astype(np.int64)
        tracked, used, failed = d["tracked"].astype(np.float64), d["used"].astype(bool), d["failed"].astype(bool)
        frames = d["frame"].astype(np.int64)
        camera_path = str(d["camera_path"])
    except Exception as exc:  # a truncated file, a missing key
        raise InputError(f"cannot read {VIDEO_RECORD} ({exc.__class__.__name__}: {exc})", path=path,
                         hint=hint) from None
    L = len(names)
    problems = [
        (matrix.shape == (3, 3), f"camera_matrix has shape {matrix.shape}"),
        (vertices.shape == (L,) and (L == 0 or (vertices.min() >= 0 and vertices.max() < n_vertices)),
         f"the landmark vertices do not fit the replay's {n_vertices} vertices"),
        (tracked.shape == (n_frames, L, 2), f"tracked points have shape {tracked.shape}, the replay "
                                            f"{n_frames} frames of {L} landmarks"),
        (used.shape == (n_frames, L) and failed.shape == (n_frames,) and frames.shape == (n_frames,),
         "the per-frame arrays do not match the replay's frames"),
    ]
    for ok, message in problems:
        if not ok:
            raise InputError(f"{VIDEO_RECORD}: {message}", path=path, hint=hint)
    return VideoRecord(Camera(matrix, dist, width, height, camera_path), names, vertices, tracked, used, failed,
                       frames)
