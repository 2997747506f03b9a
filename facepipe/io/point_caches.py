"""MDD and PC2 point cache files: their byte layouts, written and read.

All point caches keep the rest mesh's vertex order, so they play back on the rest mesh (OBJ/FBX
of the rig) in Maya, Houdini, Blender, 3ds Max or a USD viewer. A file is written under a
temporary name and renamed when complete (:mod:`facepipe.io.atomic`); whether an existing file
may be replaced (``--force``, ``--resume``) is the export's decision (:mod:`facepipe.export.caches`).

MDD (LightWave/Blender/Max point oven), big-endian: int32 frame count, int32 point count, one
float32 time in seconds per frame, then per frame the points as float32 x, y, z.

PC2 (3ds Max / Blender Point Cache 2), little-endian: ``b"POINTCACHE2\\0"``, int32 version 1,
int32 point count, float32 start frame, float32 sample rate (frames between samples, 1), int32
sample count, then per sample the points as float32 x, y, z. PC2 has no per-sample times, so a
take with dropped frames (non-uniform times) is refused.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Callable

import numpy as np

from facepipe.errors import InputError
from facepipe.io.atomic import atomic_open
from facepipe.io.replay_folder import is_uniform, time_codes

MDD_HEADER = struct.Struct(">ii")
PC2_HEADER = struct.Struct("<12siiffi")
PC2_MAGIC = b"POINTCACHE2\0"


# ----------------------------------------------------------------------------- shared by the writers


def check_positions(positions, n_vertices: int | None, path: Path) -> None:
    """InputError unless ``positions`` is (frames ≥ 1, V, 3) (``n_vertices`` V, if given)."""
    if getattr(positions, "ndim", None) != 3 or positions.shape[2] != 3 or (
            n_vertices is not None and positions.shape[1] != n_vertices):
        raise InputError(f"positions have shape {getattr(positions, 'shape', None)}, expected (frames, "
                         f"{n_vertices if n_vertices is not None else 'V'}, 3)", path=path,
                         hint="export positions replayed with this rig's model")
    if positions.shape[0] == 0:
        raise InputError("the replay has no frames", path=path)


def cache_frame(positions, t: int, path: Path) -> np.ndarray:
    """Frame ``t`` as float32; InputError naming the first vertex that is not finite."""
    frame = np.asarray(positions[t], dtype=np.float32)
    if not np.isfinite(frame).all():
        bad = int(np.flatnonzero(~np.isfinite(frame).all(axis=1))[0])
        raise InputError(f"frame index {t} has NaN or infinite positions, first vertex {bad}", path=path,
                         hint="check the replay report for that frame (e.g. lost markers)")
    return frame


def write_frames(fh, positions, path: Path, dtype: str, progress=None) -> None:
    """Every frame's positions as raw ``dtype`` values (the body of MDD and PC2 files), checked."""
    for t in range(len(positions)):
        fh.write(cache_frame(positions, t, path).astype(dtype).tobytes())
        if progress is not None:
            progress(1)


# ----------------------------------------------------------------------------- MDD


def write_mdd(path: str | os.PathLike, positions, times: np.ndarray, *,
              progress: Callable[[int], object] | None = None) -> Path:
    """Write an MDD point cache (big-endian), streaming one frame at a time.

    Parameters
    ----------
    path : ``.mdd`` file (replaced atomically if it exists).
    positions : (T, V, 3) float array or memmap, length units.
    times : (T,) seconds of every frame.
    progress : called with the number of frames written.

    Returns
    -------
    Path written.
    """
    path = Path(path)
    check_positions(positions, None, path)
    T, V = positions.shape[:2]
    if len(times) != T:
        raise ValueError(f"{len(times)} times for {T} frames")
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


# ----------------------------------------------------------------------------- PC2


def check_pc2_times(times: np.ndarray, path: Path) -> None:
    """InputError unless the frame times are uniform (PC2 stores a start frame and a sample rate only)."""
    if not is_uniform(times):
        raise InputError("the take's frame times are not uniform (dropped frames?): PC2 stores only a start frame "
                         "and a fixed sample rate", path=path,
                         hint="export MDD or USD, which store a time per frame")


def write_pc2(path: str | os.PathLike, positions, times: np.ndarray, fps: float, *,
              progress: Callable[[int], object] | None = None) -> Path:
    """Write a PC2 point cache (little-endian), streaming one frame at a time.

    Parameters
    ----------
    path : ``.pc2`` file (replaced atomically if it exists).
    positions : (T, V, 3), length units.
    times : (T,) seconds; must be uniform (PC2 stores a start frame and a sample rate only).
    fps : frames per second; the start frame is ``times[0] × fps`` (see
        :func:`facepipe.io.replay_folder.time_codes`), the sample rate 1 (a sample every frame).
    progress : called with the number of frames written.

    Returns
    -------
    Path written.

    Raises
    ------
    InputError
        Non-uniform frame times (dropped frames): PC2 cannot place them.
    """
    path = Path(path)
    check_positions(positions, None, path)
    T, V = positions.shape[:2]
    check_pc2_times(times, path)
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
