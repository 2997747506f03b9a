"""Exports of replayed animation: OBJ sequences in the rest mesh's polygons and UVs.

An export is a folder of complete files: every frame is written under a temporary name and
renamed when complete (:mod:`facepipe.atomic`), so an interrupted export leaves only whole
frames, and ``resume=True`` carries on after the last one.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Callable

import numpy as np

from .atomic import atomic_open
from .errors import InputError
from .mesh import Mesh, _format_rows, format_obj_faces, format_obj_header

FRAME_PREFIX = "frame_"


def frame_paths(dest_dir: str | os.PathLike, n_frames: int, start: int = 1, suffix: str = ".obj") -> list[Path]:
    """File names of a sequence: ``dest_dir/frame_0001.obj`` ...

    The number is zero-padded to four digits, or more when the last frame needs them, so that
    the names sort in frame order.

    Parameters
    ----------
    dest_dir : folder
    n_frames : int
    start : int, number of the first frame
    suffix : str, file extension with its dot

    Returns
    -------
    list of ``n_frames`` Paths

    Example
    -------
    >>> [p.name for p in frame_paths("out", 2)]
    ['frame_0001.obj', 'frame_0002.obj']
    """
    dest_dir = Path(dest_dir)
    last = start + max(n_frames, 1) - 1
    width = max(4, len(str(last)))
    return [dest_dir / f"{FRAME_PREFIX}{start + t:0{width}d}{suffix}" for t in range(n_frames)]


def write_obj_sequence(
    mesh: Mesh,
    positions: np.ndarray,
    dest_dir: str | os.PathLike,
    start: int = 1,
    force: bool = False,
    progress: Callable[[int], object] | None = None,
    resume: bool = False,
) -> list[Path]:
    """Write one OBJ per frame with the rest mesh's polygons, UVs and groups.

    The topology block (``vt`` and ``f`` lines) is formatted once; each frame formats only its
    ``v`` block (vectorised, :data:`facepipe.mesh.OBJ_SIGNIFICANT_DIGITS` significant digits,
    enough to give back float32 positions exactly) and is written atomically.

    Parameters
    ----------
    mesh : Mesh
        The rest mesh: polygons, UVs and groups of every frame.
    positions : (T, V, 3) float array or memmap
        Vertex positions per frame in the rest mesh's vertex order (e.g. ``positions.npy`` of a
        replay, opened with ``mmap_mode="r"``: frames are read one at a time).
    dest_dir : folder, created if missing
    start : int
        Number of the first frame's file (``frame_0001.obj`` for 1).
    force : bool
        Overwrite existing frame files. Without it an existing file is an error.
    progress : callable or None
        Called with the number of frames just done (written or skipped), e.g. ``tqdm.update``.
    resume : bool
        Skip frames whose file exists (an interrupted export leaves only complete files), and
        remove temporary files a killed export left behind.

    Returns
    -------
    list of Path, every frame's file in frame order (written or skipped).

    Raises
    ------
    InputError
        Positions of the wrong shape, a frame with NaN/inf (naming the frame), an existing file
        without ``force``/``resume`` (naming the file), or ``force`` with ``resume``.

    Example
    -------
    >>> write_obj_sequence(mesh, np.load("out/positions.npy", mmap_mode="r"), "obj")  # doctest: +SKIP
    """
    if force and resume:
        raise InputError("--force and --resume contradict each other: choose one",
                         hint="--force rewrites every frame, --resume keeps the frames already written")
    if getattr(positions, "ndim", None) != 3 or positions.shape[1:] != (mesh.n_vertices, 3):
        shape = getattr(positions, "shape", None)
        raise InputError(
            f"positions have shape {shape}, expected (frames, {mesh.n_vertices}, 3) for the rest mesh"
            + (f" {mesh.path}" if mesh.path else ""),
            hint="export positions replayed with this rig's model (the same vertex count and order)",
        )
    dest_dir = Path(dest_dir)
    paths = frame_paths(dest_dir, positions.shape[0], start)
    if dest_dir.exists() and not dest_dir.is_dir():
        raise InputError("the export destination is a file, not a folder", path=dest_dir)
    if not force and not resume:
        # check every name before writing anything: a refused export must not be half done
        existing = [p for p in paths if p.exists()]
        if existing:
            more = f" (and {len(existing) - 1} more frames)" if len(existing) > 1 else ""
            raise InputError(
                f"the file exists{more}",
                path=existing[0],
                hint="pass --force to overwrite it, --resume to keep the frames already written, "
                     "or export to another folder",
            )
    dest_dir.mkdir(parents=True, exist_ok=True)
    if resume:
        _remove_partial_files(dest_dir)

    # the topology is the same in every frame: format it once
    tail = format_obj_header(mesh) + format_obj_faces(mesh)
    header = b"# facepipe OBJ sequence frame %d\n"
    for t, path in enumerate(paths):
        if resume and path.exists():
            if progress is not None:
                progress(1)
            continue
        frame = np.asarray(positions[t], dtype=np.float64)
        if not np.isfinite(frame).all():
            bad = np.flatnonzero(~np.isfinite(frame).all(axis=1))
            raise InputError(
                f"frame {start + t} (index {t}) has NaN or infinite positions at {len(bad)} vertices, "
                f"first vertex {int(bad[0])}",
                path=path,
                hint="check the replay report for that frame (e.g. lost markers); frames before it "
                     "are written",
            )
        with atomic_open(path, "wb") as fh:
            fh.write(header % (start + t))
            fh.write(_format_rows(b"v", frame))
            fh.write(tail)
        if progress is not None:
            progress(1)
    return paths


def _remove_partial_files(dest_dir: Path) -> None:
    """Delete temporary frame files (``.frame_*.part.obj``) of an export that was killed."""
    for tmp in dest_dir.glob(f".{FRAME_PREFIX}*.part*"):
        with contextlib.suppress(OSError):
            tmp.unlink()
