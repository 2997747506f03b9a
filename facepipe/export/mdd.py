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

from facepipe.errors import InputError
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


def read_mdd(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read an MDD point cache: (times (T,) float64 seconds, positions (T, V, 3) float32 memmap).

    Raises
    ------
    InputError
        A file too short for its header, or whose size is not what its counts say.
    """
    path = Path(path)
    size = path.stat().st_size
    if size < MDD_HEADER.size:
        raise InputError("too short for an MDD header (8 bytes)", path=path, hint="export the cache again")
    with open(path, "rb") as fh:
        T, V = MDD_HEADER.unpack(fh.read(MDD_HEADER.size))
    expected = MDD_HEADER.size + 4 * T + 12 * T * V if T >= 0 and V >= 0 else -1
    if T <= 0 or V <= 0 or size != expected:
        raise InputError(f"the header says {T} frames of {V} points ({expected} bytes), the file has {size} bytes",
                         path=path, hint="the file is truncated or not an MDD cache: export it again")
    times = np.fromfile(path, dtype=">f4", count=T, offset=MDD_HEADER.size).astype(np.float64)
    positions = np.memmap(path, dtype=">f4", mode="r", offset=MDD_HEADER.size + 4 * T, shape=(T, V, 3))
    return times, positions


def export_mdd(replay, dest: Path, options: ExportOptions) -> tuple[list[Path], dict]:
    """The replay's layer as an MDD cache (the ``mdd`` format's exporter)."""
    return export_cache(replay, dest, options, "mdd", lambda path, positions, fps, progress: write_mdd(
        path, positions, replay.times, force=options.force, resume=options.resume, progress=progress))
