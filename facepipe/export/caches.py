"""What the point cache exports of a replay share (USD, MDD, PC2: :mod:`facepipe.export.usd`,
:mod:`facepipe.export.mdd`, :mod:`facepipe.export.pc2`): the file a destination names, the
no-overwrite/resume decision, the progress bar and the report. The files themselves are written
by :mod:`facepipe.io.point_caches` and :mod:`facepipe.io.usd_file`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import numpy as np

from facepipe.core.mesh import VertexSelection
from facepipe.errors import InputError
from facepipe.export.common import check_targets, remove_partial_files
from facepipe.export.registry import ExportOptions, get_format


def cache_path(dest: str | os.PathLike, fmt: str, name: str = "replay") -> Path:
    """The file a cache export writes: ``dest`` itself, or ``dest/name.EXT`` for a folder.

    Raises
    ------
    InputError
        A file name whose extension is not one of the format's.
    """
    dest = Path(dest)
    suffixes = get_format(fmt).suffixes
    if dest.is_dir():
        return dest / f"{name}{suffixes[0]}"
    if dest.suffix.lower() not in suffixes:
        raise InputError(f"a {fmt.upper()} cache must be named *{' or *'.join(suffixes)}", path=dest,
                         hint=f"use e.g. -o {dest.with_suffix(suffixes[0]).name}, or give an existing folder")
    return dest


def prepare_cache(path: Path, force: bool, resume: bool) -> bool:
    """True when the file must be written; False when ``resume`` keeps a complete one."""
    check_targets([path], force, resume)
    path.parent.mkdir(parents=True, exist_ok=True)
    if resume:
        remove_partial_files([path])
        return not path.exists()
    return True


#: ``write(path, positions, fps, progress) -> Path | None`` (None: ``resume`` kept the file).
CacheWriter = Callable[[Path, np.ndarray, float, Callable[[int], object]], "Path | None"]


def export_cache(replay, dest: Path, options: ExportOptions, fmt: str, write: CacheWriter,
                 file_order: bool = False) -> tuple[list[Path], dict]:
    """A replay's layer as one cache file (the exporters of the cache formats).

    ``replay``: a :class:`facepipe.io.replay_folder.ReplayDir`; ``dest``: the file, or a folder
    (the replay folder's name and the format's suffix); ``write`` writes the file. ``file_order``:
    a format without topology (MDD, PC2) drives the user's own mesh, so a replay of a rig welded
    along seams (``[rig] weld``) is written in the mesh file's vertex order.
    """
    positions = replay.layer(options.layer)
    order = {}
    weld_index = replay.weld_index(options.model_path) if file_order else None
    if weld_index is not None:
        positions = VertexSelection(positions, weld_index)
        order = {"vertex_order": "mesh file", "notes": [
            f"written in the mesh file's vertex order ({len(weld_index)} vertices, the seams the rig welded split "
            "again), to drive that mesh"]}
    path = cache_path(dest, fmt, name=replay.path.name or "replay")
    fps = replay.fps
    with options.make_bar(positions.shape[0], f"export {fmt}") as bar:
        written = write(path, positions, fps, bar.update)
    return [path], {"fps": fps, "kept_existing": written is None, "layer": options.layer,
                    "frames": int(positions.shape[0]), **order}
