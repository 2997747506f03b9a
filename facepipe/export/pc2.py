"""PC2 point caches (3ds Max / Blender Point Cache 2) of a replay.

Little-endian: ``b"POINTCACHE2\\0"``, int32 version 1, int32 point count, float32 start frame,
float32 sample rate (frames between samples, 1), int32 sample count, then per sample the points
as float32 x, y, z (the rest mesh's vertex order). PC2 has no per-sample times, so a take with
dropped frames (non-uniform times) is refused.
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
from facepipe.io.replay_folder import is_uniform, time_codes

PC2_HEADER = struct.Struct("<12siiffi")
PC2_MAGIC = b"POINTCACHE2\0"


def write_pc2(path: str | os.PathLike, positions, times: np.ndarray, fps: float, *, force: bool = False,
              resume: bool = False, progress: Callable[[int], object] | None = None) -> Path | None:
    """Write a PC2 point cache (little-endian), streaming one frame at a time.

    Parameters
    ----------
    path : ``.pc2`` file.
    positions : (T, V, 3), length units.
    times : (T,) seconds; must be uniform (PC2 stores a start frame and a sample rate only).
    fps : frames per second; the start frame is ``times[0] × fps`` (see
        :func:`facepipe.io.replay_folder.time_codes`), the sample rate 1 (a sample every frame).

    Returns
    -------
    Path written, or None when ``resume`` kept an existing file.

    Raises
    ------
    InputError
        Non-uniform frame times (dropped frames): PC2 cannot place them.
    """
    path = Path(path)
    check_positions(positions, None, path)
    T, V = positions.shape[:2]
    if not is_uniform(times):
        raise InputError("the take's frame times are not uniform (dropped frames?): PC2 stores only a start frame "
                         "and a fixed sample rate", path=path,
                         hint="export MDD or USD, which store a time per frame")
    if not prepare_cache(path, force, resume):
        return None
    start = float(time_codes(np.asarray(times[:1]), fps)[0])
    with atomic_open(path, "wb") as fh:
        fh.write(PC2_HEADER.pack(PC2_MAGIC, 1, V, start, 1.0, T))
        write_frames(fh, positions, path, "<f4", progress)
    return path


def read_pc2(path: str | os.PathLike) -> tuple[float, float, np.ndarray]:
    """Read a PC2 point cache: (start frame, frames between samples, positions (T, V, 3) float32 memmap).

    Raises
    ------
    InputError
        Not a PC2 file (magic), an unknown version, or a size other than the header's counts say.
    """
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(PC2_HEADER.size)
    if len(head) < PC2_HEADER.size or head[:len(PC2_MAGIC)] != PC2_MAGIC:
        raise InputError("not a PC2 point cache (no POINTCACHE2 header)", path=path,
                         hint="export the cache again as PC2, or give a cache of another format by its suffix")
    _, version, V, start, rate, T = PC2_HEADER.unpack(head)
    expected = PC2_HEADER.size + 12 * T * V
    if version != 1 or T <= 0 or V <= 0 or size != expected:
        raise InputError(f"the header says version {version}, {T} samples of {V} points ({expected} bytes); the "
                         f"file has {size} bytes", path=path, hint="the file is truncated or damaged: export it again")
    if not (np.isfinite(start) and np.isfinite(rate) and rate > 0):
        raise InputError(f"the header's start frame {start} or sample rate {rate} is not usable", path=path)
    positions = np.memmap(path, dtype="<f4", mode="r", offset=PC2_HEADER.size, shape=(T, V, 3))
    return float(start), float(rate), positions


def export_pc2(replay, dest: Path, options: ExportOptions) -> tuple[list[Path], dict]:
    """The replay's layer as a PC2 cache (the ``pc2`` format's exporter)."""
    return export_cache(replay, dest, options, "pc2", lambda path, positions, fps, progress: write_pc2(
        path, positions, replay.times, fps, force=options.force, resume=options.resume, progress=progress))
