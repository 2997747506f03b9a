"""One registry of take formats (meshio-style): a reader and a writer per format.

A format module registers itself with :func:`register`; :func:`read_take` picks the
format from the file's suffix and first bytes (several formats share ``.csv``), reads it,
converts units and applies the checks common to all formats; :func:`write_take` writes
any registered format.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from facepipe.errors import InputError
from facepipe.mocap.markers import MarkerMatch, match_markers, normalise_units, unit_factor
from facepipe.mocap.take import Take, check_order, check_values, estimate_fps, parse_frame_slice

#: ``reader(path, marker_names, match) -> Take``: every frame of the file with the rig's
#: markers in the rig's order, ``match(file_marker_names) -> MarkerMatch`` (NaN columns for
#: absent markers), ``units`` as the file declares them (canonical spelling) or None.
Reader = Callable[[Path, list, Callable[[list], MarkerMatch]], Take]
#: ``writer(path, take, units) -> None``: write atomically, positions given in ``units``.
Writer = Callable[..., None]


@dataclass(frozen=True)
class Format:
    """A registered take format.

    Attributes
    ----------
    name : str
        ``facepipe-csv``, ``c3d``, ``trc``, ``vicon-csv``, ``motive-csv``.
    suffixes : tuple[str, ...]
        Lower-case suffixes with the dot.
    reader, writer : callables (see :data:`Reader`, :data:`Writer`).
    sniff : callable(bytes) -> bool
        True when the first bytes of a file (BOM and leading blanks removed) look like
        this format.
    """

    name: str
    suffixes: tuple
    reader: Reader
    writer: Writer
    sniff: Callable[[bytes], bool]


FORMATS: dict[str, Format] = {}
#: Reader per suffix, for callers of the first version of this module (the first format
#: registered for a suffix).
READERS: dict[str, Callable] = {}
#: Writer per format name.
WRITERS: dict[str, Writer] = {}

#: Bytes of memory a reader needs per byte of file, roughly (text: the bytes, the split
#: lines and the parsed arrays; C3D: the library's copy and ours).
_MEMORY_PER_BYTE = {"text": 3.0, "binary": 4.0}


def register(fmt: Format) -> None:
    """Add a format to the registry (a later one with the same name replaces it)."""
    FORMATS[fmt.name] = fmt
    WRITERS[fmt.name] = fmt.writer
    for s in fmt.suffixes:
        READERS.setdefault(s, fmt.reader)


def _head(path: Path) -> bytes:
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return b""
    return head.lstrip(b"\xef\xbb\xbf \t\r\n")


def detect_format(path: Path, name: str | None = None) -> Format:
    """The format of a take file: ``name`` if given, else by first bytes, else by suffix.

    Raises
    ------
    InputError
        An unknown format name or an unrecognised file.
    """
    if name is not None:
        if name not in FORMATS:
            raise InputError(f"unknown take format {name!r}", hint=f"choose one of {', '.join(sorted(FORMATS))}")
        return FORMATS[name]
    head = _head(path)
    suffix = path.suffix.lower()
    by_suffix = [f for f in FORMATS.values() if suffix in f.suffixes]
    for fmt in by_suffix + [f for f in FORMATS.values() if f not in by_suffix]:
        if head and fmt.sniff(head):
            return fmt
    if by_suffix:
        return by_suffix[0]  # its reader names what is wrong with the file
    raise InputError(
        f"unknown mocap format {path.suffix or '(no suffix)'!r}",
        path=path,
        hint=f"supported: {', '.join(sorted({s for f in FORMATS.values() for s in f.suffixes}))} "
        "(a facepipe CSV starts with 'frame,time,')" + (
            f"; mesh caches: {', '.join(sorted({s for f in MESH_CACHES.values() if f.match is None for s in f.suffixes}))}"
            ", or an OBJ sequence (a folder of OBJ files, or frame_%04d.obj)" if MESH_CACHES else ""),
    )


def available_memory() -> int | None:
    """Bytes of memory available to this process now (Linux ``MemAvailable``), or None."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _check_memory(path: Path, fmt: Format) -> None:
    size = path.stat().st_size
    need = size * _MEMORY_PER_BYTE["binary" if fmt.name == "c3d" else "text"]
    have = available_memory()
    if have is not None and need > have:
        raise InputError(
            f"the take is {size / 1e9:.1f} GB: reading it needs about {need / 1e9:.1f} GB of memory, "
            f"{have / 1e9:.1f} GB is available",
            path=path,
            hint="split the take into shorter parts in the capture software (or with a script) and replay "
            "them one by one; the parts can be joined afterwards since frames are independent",
        )


def read_take(path: str | os.PathLike, marker_names, frames: slice | str | None = None, *,
              units: str | None = None, take_units: str | None = None, subject: str | None = None,
              absent: str = "error", allow_empty_frames: bool = False, format: str | None = None) -> Take:
    """Read a mocap take in any registered format, keeping the rig's markers in the rig's order.

    Parameters
    ----------
    path : str or PathLike
        The take file; its format is found from its first bytes and suffix.
    marker_names : sequence of str
        The rig's M markers (without ``ignore`` ones), in the rig's order.
    frames : slice or str, optional
        Rows of the file to keep (``slice(A, B)`` or ``"A:B"``, Python slice rules,
        counting frame rows, not frame numbers). The whole file is still checked.
    units : str, optional
        Convert positions to these units (the rig's, e.g. ``"cm"``). A file that does not
        declare its units (facepipe CSV) is taken to be in these units.
    take_units : str, optional
        The file's units, overriding what it declares (or filling in when it does not).
    subject : str, optional
        With markers of several subjects in the file, use this one's.
    absent : {"error", "missing"}
        What a rig marker absent from the file is (see :func:`match_markers`).
    allow_empty_frames : bool
        Accept frames where no rig marker is visible.
    format : str, optional
        Force a format (a key of :data:`FORMATS`).

    Returns
    -------
    Take
        ``positions`` is (T, M, 3) float64 in ``units`` (or the file's), NaN for missing
        samples; ``markers`` reports absent, extra, duplicate and renamed markers.

    Raises
    ------
    InputError
        Unreadable or malformed file (naming line/frame and marker), rig markers absent,
        frames out of order, a frame with no visible marker, no frames, a take too large for
        memory.

    Example
    -------
    >>> take = read_take("take.c3d", ["M001", "M002"], units="cm")  # doctest: +SKIP
    >>> take.positions.shape                                          # doctest: +SKIP
    (1200, 2, 3)
    """
    path = Path(path)
    marker_names = [str(n) for n in marker_names]
    if not marker_names:
        raise ValueError("read_take needs at least one marker name")
    if len(set(marker_names)) != len(marker_names):
        raise ValueError("marker_names has duplicates")
    if absent not in ("error", "missing"):
        raise ValueError(f"absent must be 'error' or 'missing', got {absent!r}")
    if isinstance(frames, str):
        frames = parse_frame_slice(frames)
    target = normalise_units(units, what="rig unit")
    override = normalise_units(take_units, what="take unit")

    if not path.exists():
        raise InputError("mocap take not found", path=path, hint="check the path of the take")
    if path.is_dir():
        raise InputError("is a folder, not a mocap take", path=path, hint="name the take file itself")
    fmt = detect_format(path, format)
    _check_memory(path, fmt)

    def match(file_names):
        return match_markers(file_names, marker_names, path, subject=subject, absent=absent)

    take = replace(fmt.reader(path, marker_names, match), format=fmt.name, path=str(path))
    check_order(take)

    source = override or take.units or target
    factor = unit_factor(source, target) if source is not None and target is not None and source != target else 1.0
    take = replace(take, positions=take.positions * factor if factor != 1.0 else take.positions,
                   source_units=source, units=target or source)

    total = take.n_frames
    if frames is not None:
        take = take.select(frames)
        if take.n_frames == 0:
            raise InputError(
                f"the frame range {frames.start}:{frames.stop} selects none of the {total} frames",
                path=path,
                hint=f"choose rows within 0:{total}",
            )
    check_values(take, allow_empty_frames=allow_empty_frames)
    return replace(take, fps=estimate_fps(take.times))


def write_take(path: str | os.PathLike, take: Take, format: str | None = None, *, units: str | None = None,
               **options) -> None:
    """Write a take in a registered format (atomically).

    Parameters
    ----------
    path : str or PathLike
    take : Take
        ``positions`` in ``take.units`` (None: written as they are).
    format : str, optional
        A key of :data:`FORMATS`; default from the suffix (``.csv`` is the facepipe CSV).
    units : str, optional
        Units to write in (positions converted from ``take.units``); formats that record
        units (C3D, TRC, Vicon, Motive) declare them.
    **options
        Passed to the format's writer (e.g. ``subject="Actor"`` to prefix marker names,
        ``decimals``).

    Example
    -------
    >>> write_take("take.trc", take, units="mm", subject="Actor")  # doctest: +SKIP
    """
    path = Path(path)
    if format is None:
        suffix = path.suffix.lower()
        fmt = next((f for f in FORMATS.values() if suffix in f.suffixes), None)
        if fmt is None:
            raise ValueError(f"no take format for suffix {suffix!r}; name one of {sorted(FORMATS)}")
    else:
        fmt = FORMATS[format]
    units = normalise_units(units) if units else None
    if units and take.units and units != take.units:
        take = replace(take, positions=np.asarray(take.positions, dtype=np.float64) * unit_factor(take.units, units),
                       units=units)
    fmt.writer(path, take, units or take.units, **options)


@dataclass(frozen=True)
class MeshCacheFormat:
    """A registered mesh-animation take format (a point cache of every vertex, see :mod:`facepipe.mocap.mesh_cache`).

    Attributes
    ----------
    name : ``usd``, ``mdd``, ``pc2``, ``obj-sequence``.
    suffixes : lower-case suffixes with the dot.
    reader : ``reader(path, fps, **options) -> MeshCache``.
    match : callable(Path) -> bool, for formats a suffix alone does not tell (an OBJ sequence
        is a folder or a ``%04d`` pattern; a single ``.obj`` is a mesh); None: the suffix decides.
    """

    name: str
    suffixes: tuple
    reader: Callable
    match: Callable[[Path], bool] | None = None


#: Mesh-cache formats by name (registered by :mod:`facepipe.mocap.mesh_cache`).
MESH_CACHES: dict[str, MeshCacheFormat] = {}


def register_mesh_cache(fmt: MeshCacheFormat) -> None:
    """Add a mesh-cache format to the registry (a later one with the same name replaces it)."""
    MESH_CACHES[fmt.name] = fmt


def mesh_cache_format(path: str | os.PathLike) -> MeshCacheFormat | None:
    """The mesh-cache format of ``path`` (a file, a folder of OBJ files or a ``%04d`` pattern), or None
    when it is not one (then it is a marker take)."""
    path = Path(path)
    suffix = "" if path.is_dir() else path.suffix.lower()
    for fmt in MESH_CACHES.values():
        if fmt.match is not None:
            if fmt.match(path):
                return fmt
        elif suffix in fmt.suffixes:
            return fmt
    return None


def frames_from_rate(first: int, count: int, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """Frame numbers ``first, first+1, ...`` and their times ``frame / rate`` (formats without times)."""
    frames = np.arange(first, first + count, dtype=np.int64)
    return frames, frames / float(rate)


def marker_label(name: str, subject: str | None) -> str:
    """``Subject:Name`` for writers that prefix marker names with a subject."""
    return f"{subject}:{name}" if subject else name


def nominal_rate(take: Take, default: float) -> float:
    """The take's frame rate for formats that store a rate: ``fps`` rounded to 0.01 Hz when
    that is within 0.01 % (times written with 6 decimals give 30.0003 for 30 Hz)."""
    fps = take.fps if np.isfinite(take.fps) else (estimate_fps(np.asarray(take.times)) if len(take.times) > 1
                                                   else float("nan"))
    if not np.isfinite(fps) or fps <= 0:
        return float(default)
    near = round(fps, 2)
    return float(near) if abs(fps - near) <= 1e-4 * fps else float(fps)
