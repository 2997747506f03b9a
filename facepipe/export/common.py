"""Exports of replayed animation: OBJ sequences in the rest mesh's polygons and UVs.

An export is a folder of complete files: every frame is written under a temporary name and
renamed when complete (:mod:`facepipe.io.atomic`), so an interrupted export leaves only whole
frames, and ``resume=True`` carries on after the last one. :func:`check_targets` and
:func:`remove_partial_files` give every other export (maps, caches, previews) the same rules.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Callable

import numpy as np

from facepipe.io.atomic import atomic_open
from facepipe.errors import InputError
from facepipe.core.mesh import Mesh
from facepipe.io.mesh_write import _format_rows, format_obj_faces, format_obj_header
from facepipe.export.registry import ExportOptions
from facepipe.parallel import map_in_order, thread_count

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
    ``v`` block (vectorised, :data:`facepipe.core.mesh.OBJ_SIGNIFICANT_DIGITS` significant digits,
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
    check_flags(force, resume)
    if getattr(positions, "ndim", None) != 3 or positions.shape[1:] != (mesh.n_vertices, 3):
        shape = getattr(positions, "shape", None)
        raise InputError(
            f"positions have shape {shape}, expected (frames, {mesh.n_vertices}, 3) for the rest mesh"
            + (f" {mesh.path}" if mesh.path else ""),
            hint="export positions replayed with this rig's model (the same vertex count and order)",
        )
    dest_dir = Path(dest_dir)
    paths = frame_paths(dest_dir, positions.shape[0], start)
    check_targets(paths, force, resume, folder=dest_dir)
    dest_dir.mkdir(parents=True, exist_ok=True)
    if resume:
        remove_partial_files(paths)

    # the topology is the same in every frame: format it once
    tail = format_obj_header(mesh) + format_obj_faces(mesh)
    header = b"# facepipe OBJ sequence frame %d\n"
    bad = []

    def frames_to_write():
        """(t, positions or None for a frame kept by ``resume``) in order, up to the first frame
        with NaN or infinite positions (kept in ``bad``): the frames before it are all written."""
        for t, path in enumerate(paths):
            if resume and path.exists():
                yield t, None
                continue
            frame = np.asarray(positions[t], dtype=np.float64)
            if not np.isfinite(frame).all():
                bad.append((t, path, frame))
                return
            yield t, frame

    def write_frame(item):
        t, frame = item
        if frame is not None:
            with atomic_open(paths[t], "wb") as fh:
                fh.write(header % (start + t))
                fh.write(_format_rows(b"v", frame))
                fh.write(tail)

    # frames are formatted and written on facepipe's threads (the formatting lets go of Python's
    # lock), as many under way as there are threads, each holding its positions in float64 and
    # its text (about 40 bytes a vertex)
    frame_bytes = mesh.n_vertices * (3 * 8 + 40) + len(tail)
    for _ in map_in_order(write_frame, frames_to_write(), ahead=thread_count(), item_bytes=frame_bytes):
        if progress is not None:
            progress(1)
    if bad:
        t, path, frame = bad[0]
        rows = np.flatnonzero(~np.isfinite(frame).all(axis=1))
        raise InputError(
            f"frame {start + t} (index {t}) has NaN or infinite positions at {len(rows)} vertices, "
            f"first vertex {int(rows[0])}",
            path=path,
            hint="check the replay report for that frame (e.g. lost markers); frames before it "
                 "are written",
        )
    return paths


def export_obj(replay, dest: Path, options: ExportOptions) -> tuple[list[Path], dict]:
    """A replay's layer as an OBJ sequence in ``dest`` (the ``obj`` format's exporter; ``replay``:
    a :class:`facepipe.io.replay_folder.ReplayDir`)."""
    positions = replay.layer(options.layer)
    model = replay.load_model(options.model_path)
    with options.make_bar(positions.shape[0], "export obj") as bar:
        paths = write_obj_sequence(model.mesh(), positions, dest, start=options.start, force=options.force,
                                   resume=options.resume, progress=bar.update)
    return paths, {"layer": options.layer, "frames": int(positions.shape[0])}


def check_flags(force: bool, resume: bool) -> None:
    """InputError when both ``force`` and ``resume`` are given."""
    if force and resume:
        raise InputError("--force and --resume contradict each other: choose one",
                         hint="--force rewrites every file, --resume keeps the files already written")


def check_targets(paths: list[Path], force: bool, resume: bool, folder: Path | None = None) -> None:
    """Refuse an export that would overwrite files, before anything is written.

    Parameters
    ----------
    paths : every file the export will write.
    force : overwriting is allowed.
    resume : existing files will be kept (skipped), so they are no obstacle.
    folder : the destination folder, which must not be a file.

    Raises
    ------
    InputError
        naming the first existing file (and how many more) and the ways out.
    """
    check_flags(force, resume)
    if folder is not None and folder.exists() and not folder.is_dir():
        raise InputError("the export destination is a file, not a folder", path=folder)
    for p in {Path(p).parent for p in paths}:
        if p.exists() and not p.is_dir():
            raise InputError("the export destination is a file, not a folder", path=p)
    if force or resume:
        return
    existing = [p for p in paths if Path(p).exists()]
    if existing:
        more = f" (and {len(existing) - 1} more files)" if len(existing) > 1 else ""
        raise InputError(
            f"the file exists{more}",
            path=existing[0],
            hint="pass --force to overwrite it, --resume to keep the files already written, "
                 "or export to another destination",
        )


def remove_partial_files(paths: list[Path]) -> None:
    """Delete temporary files that a killed export left for any of ``paths``.

    :func:`facepipe.io.atomic.atomic_path` writes ``.NAME.XXXXXX.partSUFFIX`` beside ``NAME``.
    """
    by_dir: dict[Path, set] = {}
    for p in paths:
        by_dir.setdefault(Path(p).parent, set()).add(Path(p).name)
    for folder, names in by_dir.items():
        if not folder.is_dir():
            continue
        for tmp in folder.glob(".*.part*"):
            base = tmp.name[1:].split(".part", 1)[0].rsplit(".", 1)[0]
            if base in names:
                with contextlib.suppress(OSError):
                    tmp.unlink()
