"""MDD point caches (LightWave/Blender/Max point oven) of a replay.

Big-endian: int32 frame count, int32 point count, one float32 time in seconds per frame, then
per frame the points as float32 x, y, z (the rest mesh's vertex order).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Callable

import numpy as np

from facepipe.export.caches import check_positions, export_cache, prepare_cache, write_frames
from facepipe.export.registry import ExportOptions
from facepipe.io.atomic import atomic_open

MDD_HEADER = struct.Struct(">ii")


def write_mdd(path: str | os.PathLike, positions, times: np.ndarray, *, force: bool = False, resume: bool = False,
              progress: Callable[[int], object] | None = None) -> Path | None:
    """Write an MDD point cache (big-endian), streaming one frame at a time.

    Parameters
    ----------
    path : ``.mdd`` file.
    positions : (T, V, 3) float array or memmap, length units.
    times : (T,) seconds of every frame.
    force, resume : overwrite an existing file / keep it.
    progress : called with the number of frames written.

    Returns
    -------
    Path written, or None when ``resume`` kept an existing file.
    """
    path = Path(path)
    check_positions(positions, None, path)
    T, V = positions.shape[:2]
    if len(times) != T:
        raise ValueError(f"{len(times)} times for {T} frames")
    if not prepare_cache(path, force, resume):
        return None
    with atomic_open(path, "wb") as fh:
        fh.write(MDD_HEADER.pack(T, V))
        fh.write(np.asarray(times, dtype=">f4").tobytes())
        write_frames(fh, positions, path, ">f4", progress)
    return path


def export_mdd(replay, dest: Path, options: ExportOptions) -> tuple[list[Path], dict]:
    """The replay's layer as an MDD cache (the ``mdd`` format's exporter)."""
    return export_cache(replay, dest, options, "mdd", lambda path, positions, fps, progress: write_mdd(
        path, positions, replay.times, force=options.force, resume=options.resume, progress=progress))
