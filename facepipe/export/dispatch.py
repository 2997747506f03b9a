"""A replay folder to the formats artists' tools read: the dispatcher behind ``facepipe export``.

The formats are registered in :mod:`facepipe.export.registry`:

============  ==========================================  ===================================
format        writes                                      needs
============  ==========================================  ===================================
``obj``       DEST/frame_NNNN.obj (polygons, UVs)         positions (or large_scale.npy)
``usd``       DEST.usdc: time-sampled UsdGeom.Mesh        positions, frame times
``mdd``       DEST.mdd point cache                        positions, frame times
``pc2``       DEST.pc2 point cache                        positions, uniform frame times
``exr``       DEST/frame_NNNN[.TILE].exr displacement     model with UVs, handles.npz
``wrinkle``   DEST/wrinkle_*.exr + coefficients.csv       PSD model with UVs, handles.npz
``textures``  DEST/frame_NNNN.png|exr + appearance.csv    appearance.csv (classify), its model
============  ==========================================  ===================================
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from facepipe.errors import InputError
from facepipe.export.registry import FORMATS, ExportOptions, get_format, null_bar
from facepipe.io.outputs import check_output_path
from facepipe.io.replay_folder import ReplayDir

#: Formats that write a folder of files (the others write one file).
SEQUENCE_FORMATS = tuple(name for name, fmt in FORMATS.items() if not fmt.suffixes)


def parse_resolution(text) -> tuple[int, int]:
    """``"2048"`` → (2048, 2048); ``"2048x1024"`` → (width 2048, height 1024).

    Example
    -------
    >>> parse_resolution("1024x512")
    (1024, 512)
    """
    try:
        parts = [int(x) for x in str(text).lower().split("x")]
    except ValueError:
        parts = []
    if len(parts) == 1:
        parts *= 2
    if len(parts) != 2 or not all(16 <= p <= 32768 for p in parts):
        raise InputError(f"--resolution {text!r} is not N or WxH with 16 <= N <= 32768",
                         hint="e.g. --resolution 2048 or --resolution 4096x2048")
    return parts[0], parts[1]


def _file_bytes(paths) -> int:
    return int(sum(Path(p).stat().st_size for p in paths if Path(p).is_file()))


def export_replay(
    outdir,
    fmt: str,
    dest,
    *,
    model_path=None,
    layer: str = "final",
    resolution: tuple[int, int] = (2048, 2048),
    padding: int = 8,
    half: bool | None = None,
    mode: str = "vector",
    space: str = "local",
    start: int = 1,
    up_axis: str = "Y",
    force: bool = False,
    resume: bool = False,
    make_bar: Callable = null_bar,
) -> dict:
    """Export a replay folder in one format.

    Parameters
    ----------
    outdir : the replay's output folder (:class:`facepipe.io.replay_folder.ReplayDir`).
    fmt : one of the registered formats (:data:`facepipe.export.registry.FORMATS`).
    dest : a folder for obj/exr/wrinkle; a file (or an existing folder) for usd/mdd/pc2.
    model_path, layer, resolution, padding, half, mode, space, start, up_axis, force, resume, make_bar :
        the :class:`facepipe.export.registry.ExportOptions`.

    Returns
    -------
    dict: format, dest, files (count), bytes, seconds, megabytes_per_second, per format
    details (resolution, tiles, fps, …), and ``notes`` (strings worth telling the user).
    """
    export_format = get_format(fmt)
    check_output_path(dest, kind="either" if export_format.suffixes else "folder", what="export destination")
    options = ExportOptions(model_path=model_path, layer=layer, resolution=resolution, padding=padding, half=half,
                            mode=mode, space=space, start=start, up_axis=up_axis, force=force, resume=resume,
                            make_bar=make_bar)
    replay = ReplayDir(outdir)
    dest = Path(dest)
    before = _file_identities(dest)
    t0 = time.perf_counter()
    paths, details = export_format.export(replay, dest, options)
    info = {"format": fmt, **details}
    seconds = time.perf_counter() - t0
    # a file --resume kept is the very file that was there before (every write renames a new
    # file into place, so a rewritten one has another identity)
    kept = [p for p in paths if before.get(_key(p)) is not None and before[_key(p)] == _identity(p)]
    written = [p for p in paths if p not in kept]
    size = _file_bytes(written)
    info.update(dest=str(dest), files=len(paths), written=len(written), kept=len(kept), bytes=size,
                seconds=seconds, megabytes_per_second=size / 1e6 / seconds if seconds > 0 else None)
    return info


def _key(path) -> str:
    return str(Path(path).absolute())


def _identity(path) -> tuple | None:
    """(device, inode, size, modification time) of a file, or None when there is none."""
    try:
        st = Path(path).stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


def _file_identities(dest: Path) -> dict:
    """The identity of every file at ``dest`` (a file, or the files in a folder) before an export."""
    if dest.is_file():
        return {_key(dest): _identity(dest)}
    if dest.is_dir():
        return {_key(p): _identity(p) for p in dest.rglob("*") if p.is_file()}
    return {}
