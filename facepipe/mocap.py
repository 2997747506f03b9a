"""Mocap takes: reading, writing and gap filling.

A take is a sequence of marker positions, one row per captured frame. Readers are
registered per file format in :data:`READERS` (keyed by file suffix); each one
turns a file into a :class:`Take` holding the rig's markers in the rig's order,
and :func:`read_take` applies the checks every format needs (frame order,
finite values, a visible marker in every frame) and the ``--frames`` slice.
Only the facepipe CSV exists today; C3D, TRC or a vendor's CSV are one more
reader function each.

The facepipe CSV (see DESIGN.md, "Mocap CSV")::

    frame,time,M001_x,M001_y,M001_z,M002_x,...
    0,0.000000,-7.34958,3.64373,3.69269,,,,...

One row per frame: an integer frame number, the time in seconds, then x, y, z
of every marker. An empty field or ``NaN`` is a missing sample.

Long takes are common (100k frames × 100 markers is 260 MB of text), so the
CSV body is parsed by a vectorised NumPy decimal parser; blocks it cannot
handle (exponents, ``NaN``, stray characters) go through a per-cell path that
either parses them or names the line and column of the bad cell.
"""

from __future__ import annotations

import difflib
import os
import re
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .atomic import atomic_open
from .errors import InputError

__all__ = [
    "READERS",
    "Take",
    "fill_gaps",
    "match_markers",
    "parse_frame_slice",
    "read_csv_take",
    "read_take",
    "write_take_csv",
]

_AXES = ("x", "y", "z")


@dataclass
class Take:
    """A mocap take: marker positions per frame, rig markers only, in the rig's order.

    Attributes
    ----------
    frames : (T,) int64
        Frame numbers, strictly increasing (not necessarily contiguous).
    times : (T,) float64
        Seconds, strictly increasing.
    positions : (T, M, 3) float64
        Marker positions in the file's units; a missing sample is NaN in all three
        coordinates.
    marker_names : list[str]
        The M rig markers, in the order asked for (the rig's order).
    path : str
        Where the take was read from (for messages).
    extra_markers : list[str]
        Markers in the file that the rig does not use: reported, otherwise ignored.
    fps : float
        Frame rate estimated from ``times`` (1 / median frame interval); NaN when the
        take has fewer than two frames.
    lines : (T,) int64 or None
        The source line of each frame row (1-based) for messages, None for formats
        without lines.
    """

    frames: np.ndarray
    times: np.ndarray
    positions: np.ndarray
    marker_names: list[str]
    path: str = ""
    extra_markers: list[str] = field(default_factory=list)
    fps: float = float("nan")
    lines: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_markers(self) -> int:
        return int(self.positions.shape[1])

    @property
    def missing(self) -> np.ndarray:
        """(T, M) bool: True where a marker sample is missing."""
        return np.isnan(self.positions).any(axis=2)

    def where(self, row: int) -> str:
        """Describe frame row ``row`` for a message: ``frame 12 (line 14)``."""
        text = f"frame {int(self.frames[row])}"
        if self.lines is not None:
            text += f" (line {int(self.lines[row])})"
        return text


# --------------------------------------------------------------------------- registry

#: Reader for each file suffix (lower case, with the dot). A reader is
#: ``reader(path: Path, marker_names: list[str]) -> Take`` returning every frame of
#: the file with ``marker_names`` in that order (use :func:`match_markers` for the
#: "rig marker absent" error); :func:`read_take` does the checks common to all formats.
READERS: dict[str, Callable[[Path, list[str]], Take]] = {}


def _sniff_reader(path: Path) -> Callable[[Path, list[str]], Take] | None:
    """Pick a reader from a file's first bytes when its suffix is not registered."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(256)
    except OSError:
        return None
    head = head.lstrip(b"\xef\xbb\xbf \t\r\n").lower()
    if head.startswith((b"frame,", b'"frame",')):
        return read_csv_take
    return None


def parse_frame_slice(text: str) -> slice:
    """Parse a ``--frames`` value ``A:B`` (rows A to B-1 of the take, Python slice rules).

    Parameters
    ----------
    text : str
        ``"A:B"``, ``"A:"``, ``":B"`` or ``"A:B:STEP"``, integers, negative counting from the end.

    Returns
    -------
    slice

    Example
    -------
    >>> parse_frame_slice("10:20")
    slice(10, 20, None)
    """
    parts = str(text).strip().split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        vals = [int(p) if p.strip() else None for p in parts]
        if len(vals) == 3 and vals[2] is not None and vals[2] <= 0:
            raise ValueError
    except ValueError:
        raise InputError(
            f"bad frame range {text!r}",
            hint="write --frames A:B with integers (rows A to B-1 of the take), e.g. 0:100 or 100:",
        ) from None
    return slice(*vals)


def read_take(path: str | os.PathLike, marker_names, frames: slice | str | None = None) -> Take:
    """Read a mocap take, keeping the rig's markers in the rig's order.

    Parameters
    ----------
    path : str or PathLike
        The take file; its suffix picks the reader in :data:`READERS` (an unknown
        suffix is sniffed).
    marker_names : sequence of str
        The rig's M markers (without ``ignore`` ones), in the rig's order.
    frames : slice or str, optional
        Rows of the file to keep (``slice(A, B)`` or ``"A:B"``, Python slice rules,
        counting frame rows, not frame numbers). The whole file is still checked.

    Returns
    -------
    Take
        ``positions`` is (T, M, 3) float64 with NaN for missing samples.

    Raises
    ------
    InputError
        Unreadable or malformed file, a rig marker absent from the file, frames out
        of order, a frame with no visible marker, no frames.

    Example
    -------
    >>> take = read_take("take.csv", ["M001", "M002"], frames="0:100")  # doctest: +SKIP
    >>> take.positions.shape                                           # doctest: +SKIP
    (100, 2, 3)
    """
    path = Path(path)
    marker_names = [str(n) for n in marker_names]
    if not marker_names:
        raise ValueError("read_take needs at least one marker name")
    if len(set(marker_names)) != len(marker_names):
        raise ValueError("marker_names has duplicates")
    if isinstance(frames, str):
        frames = parse_frame_slice(frames)

    if not path.exists():
        raise InputError("mocap take not found", path=path, hint="check the path of the take")
    if path.is_dir():
        raise InputError("is a folder, not a mocap take", path=path, hint="name the take file itself")
    reader = READERS.get(path.suffix.lower()) or _sniff_reader(path)
    if reader is None:
        raise InputError(
            f"unknown mocap format {path.suffix or '(no suffix)'!r}",
            path=path,
            hint=f"supported: {', '.join(sorted(READERS))} (a facepipe CSV starts with 'frame,time,')",
        )
    take = reader(path, marker_names)
    _check_order(take)

    total = take.n_frames
    if frames is not None:
        take = _slice_take(take, frames)
        if take.n_frames == 0:
            raise InputError(
                f"the frame range {frames.start}:{frames.stop} selects none of the {total} frames",
                path=path,
                hint=f"choose rows within 0:{total}",
            )
    _check_values(take)
    take.fps = _estimate_fps(take.times)
    return take


def match_markers(file_names: list[str], marker_names: list[str], path) -> tuple[np.ndarray, list[str]]:
    """Find the rig's markers among a file's markers.

    Parameters
    ----------
    file_names : list[str]
        Markers in the file, in file order.
    marker_names : list[str]
        The rig's M markers.
    path : str or Path
        The file, for the message.

    Returns
    -------
    index : (M,) int64
        ``file_names[index[m]] == marker_names[m]``.
    extra : list[str]
        File markers the rig does not use, in file order.

    Raises
    ------
    InputError
        Naming every rig marker the file lacks (with close matches when there are any).
    """
    where = {n: i for i, n in enumerate(file_names)}
    absent = [n for n in marker_names if n not in where]
    if absent:
        shown = ", ".join(absent[:12]) + (f" and {len(absent) - 12} more" if len(absent) > 12 else "")
        rig = set(marker_names)
        pool = [n for n in file_names if n not in rig]
        guesses = []
        for n in absent[:5]:
            close = difflib.get_close_matches(n, pool, n=1) or [
                c for c in pool if c.lower() == n.lower()
            ]
            if close:
                guesses.append(f"{close[0]} -> {n}")
        hint = "rename the columns in the take to the rig's marker names, or mark the marker `ignore` in markers.csv"
        if guesses:
            hint += f" (perhaps {', '.join(guesses)})"
        raise InputError(
            f"{len(absent)} rig marker(s) absent from the take: {shown}",
            path=path,
            hint=hint,
        )
    rig = set(marker_names)
    extra = [n for n in file_names if n not in rig]
    return np.array([where[n] for n in marker_names], dtype=np.int64), extra


def _slice_take(take: Take, rows: slice) -> Take:
    return Take(
        frames=take.frames[rows],
        times=take.times[rows],
        positions=take.positions[rows],
        marker_names=take.marker_names,
        path=take.path,
        extra_markers=take.extra_markers,
        fps=take.fps,
        lines=None if take.lines is None else take.lines[rows],
    )


def _check_order(take: Take) -> None:
    """Frames and times of the whole file: present, integral, strictly increasing."""
    path = take.path
    if take.n_frames == 0:
        raise InputError("the take has no frames (only a header)", path=path, hint="export the take again")
    bad = np.flatnonzero(~np.isfinite(take.times))
    if bad.size:
        raise InputError(f"{take.where(int(bad[0]))}: the time is missing or not finite", path=path,
                         hint="every row needs its time in seconds")
    bad = np.flatnonzero(np.diff(take.frames) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        same = take.frames[i] == take.frames[i - 1]
        raise InputError(
            f"{take.where(i)}: frame number {'repeats' if same else 'goes back from'} "
            f"frame {int(take.frames[i - 1])}" + ("" if take.lines is None else f" (line {int(take.lines[i - 1])})"),
            path=path,
            hint="rows must be in increasing frame order without duplicates: sort the file or remove the repeated row",
        )
    bad = np.flatnonzero(np.diff(take.times) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise InputError(
            f"{take.where(i)}: time {take.times[i]:.6g} s is not after the previous row's {take.times[i - 1]:.6g} s",
            path=path,
            hint="times must increase with the frame number",
        )


def _check_values(take: Take) -> None:
    """Marker values of the selected frames: finite, and some marker visible in every frame."""
    path = take.path
    pos = take.positions
    inf = np.isinf(pos)
    if inf.any():
        t, m, a = (int(v) for v in np.argwhere(inf)[0])
        raise InputError(
            f"{take.where(t)}: marker {take.marker_names[m]} ({take.marker_names[m]}_{_AXES[a]}) is infinite",
            path=path,
            hint="leave the field empty (or write NaN) for a missing sample",
        )
    # A sample with only some coordinates missing cannot be used: treat it as missing.
    part = np.isnan(pos).any(axis=2)
    pos[part] = np.nan
    none = np.flatnonzero(part.all(axis=1))
    if none.size:
        more = f" (and {none.size - 1} other frame(s))" if none.size > 1 else ""
        raise InputError(
            f"{take.where(int(none[0]))}: every marker is missing{more}",
            path=path,
            hint="remove the frame from the take or skip it with --frames A:B",
        )


def _estimate_fps(times: np.ndarray) -> float:
    if times.size < 2:
        return float("nan")
    return float(1.0 / np.median(np.diff(times)))


# --------------------------------------------------------------------------- facepipe CSV

_COLUMN_RE = re.compile(r"^(?P<name>.+)_(?P<axis>[xyzXYZ])$")
# What a number cell may look like (the per-cell path): plain decimals, exponents,
# nan/inf. Python's float() also takes "1_000" and non-ASCII digits, which a CSV
# must not silently accept.
_NUMBER_RE = re.compile(
    rb"^[+-]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|nan|inf|infinity)$", re.IGNORECASE
)
# A whole field spelling NaN (between separators): a missing sample like an empty field.
_NAN_FIELD = re.compile(rb"(?<=[,\n])[+-]?nan(?=[,\n])", re.IGNORECASE)
_POW10 = 10.0 ** np.arange(23)
_BLOCK_BYTES = 1 << 22  # rows per parsed block ~ 4 MB of text: bounded temporaries


def read_csv_take(path: Path, marker_names: list[str]) -> Take:
    """Read every frame of a facepipe CSV take.

    Parameters
    ----------
    path : Path
    marker_names : list[str]
        The rig's M markers, in order.

    Returns
    -------
    Take
        All frames of the file, ``positions`` (T, M, 3) float64, ``lines`` set; the
        checks common to all formats are left to :func:`read_take`.

    Raises
    ------
    InputError
        Naming the line (and column) of the first problem.
    """
    data = _read_bytes(path)
    if b"\r" in data:  # Windows (or old Mac) line ends: same line numbers either way
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    lines = data.split(b"\n")
    del data

    # Header: the first non-blank line.
    h = next((i for i, ln in enumerate(lines) if ln.strip()), None)
    if h is None:
        raise InputError(
            "the take is empty",
            path=path,
            hint="a facepipe take starts with the header frame,time,NAME_x,NAME_y,NAME_z,...",
        )
    columns = _header_columns(lines[h], h + 1, path)
    frame_col, time_col, file_markers, marker_cols = _parse_header(columns, h + 1, path)
    n_cols = len(columns)
    index, extra = match_markers(file_markers, marker_names, path)
    # Columns to parse, in output order: frame, time, then x, y, z of each rig marker.
    use = np.concatenate([[frame_col, time_col], marker_cols[index].ravel()]).astype(np.int64)

    # Body rows: skip blank lines, keep each row's line number for messages.
    body = lines[h + 1:]
    del lines
    keep = [i for i, ln in enumerate(body) if ln and not ln.isspace()]
    rows = body if len(keep) == len(body) else [body[i] for i in keep]
    line_no = np.asarray(keep, dtype=np.int64) + (h + 2)
    del body
    counts = np.fromiter((ln.count(b",") for ln in rows), dtype=np.int64, count=len(rows))
    bad = np.flatnonzero(counts != n_cols - 1)
    if bad.size:
        i = int(bad[0])
        short = counts[i] < n_cols - 1
        cut = short and i == len(rows) - 1
        raise InputError(
            f"line {line_no[i]}: {counts[i] + 1} fields, the header has {n_cols}"
            + (" (truncated row)" if short else " (extra fields)"),
            path=path,
            hint=("the file looks cut off: export or copy it again; " if cut else "")
            + "every row needs frame, time and x,y,z of every marker (a missing sample keeps its commas "
            "with empty fields)",
        )

    # Frame and time columns apart from the positions, so that positions are written
    # once, straight into their final (T, M, 3) array.
    n = len(rows)
    stamps = np.empty((n, 2), dtype=np.float64)
    positions = np.empty((n, len(marker_names), 3), dtype=np.float64)
    flat = positions.reshape(n, 3 * len(marker_names))
    # Blocks of ~4 MB keep the parser's temporaries small whatever the take's length,
    # and run on several threads: NumPy releases the GIL inside its array operations.
    width = 1 + sum(len(r) for r in rows[:64]) // max(1, min(64, n))
    step = max(1, _BLOCK_BYTES // width)

    def parse(a: int) -> None:
        block = rows[a:a + step]
        b = a + len(block)
        blob = b"\n".join(block) + b"\n"
        if b"n" in blob or b"N" in blob:  # NaN cells: make them empty, which the fast parser takes
            blob = _NAN_FIELD.sub(b"", blob)
        out = _parse_block_fast(blob, len(block), n_cols)
        out = _parse_block_slow(block, line_no[a:b], use, columns, path) if out is None else out[:, use]
        stamps[a:b] = out[:, :2]
        flat[a:b] = out[:, 2:]

    starts = range(0, n, step)
    workers = min(len(starts), _workers())
    if workers <= 1:
        for a in starts:
            parse(a)
    else:
        pool = ThreadPoolExecutor(workers)
        try:
            for _ in pool.map(parse, starts):  # in order: the first bad line is the one reported
                pass
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    return _take_from_values(stamps, positions, line_no, marker_names, extra, path)


def _workers() -> int:
    try:
        return max(1, min(8, len(os.sched_getaffinity(0))))
    except AttributeError:  # not on Linux
        return max(1, min(8, os.cpu_count() or 1))


def _read_bytes(path: Path) -> bytes:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError("mocap take not found", path=path, hint="check the path of the take") from None
    except IsADirectoryError:
        raise InputError("is a folder, not a mocap take", path=path, hint="name the take file itself") from None
    except OSError as exc:
        raise InputError(f"cannot read the take: {exc.strerror or exc}", path=path,
                         hint="check the file's permissions") from None
    if data.startswith(b"\xef\xbb\xbf"):  # UTF-8 byte-order mark from spreadsheet exports
        data = data[3:]
    if not data or data.isspace():  # (isspace stops at the first character that is not)
        raise InputError(
            "the take is empty",
            path=path,
            hint="a facepipe take starts with the header frame,time,NAME_x,NAME_y,NAME_z,...",
        )
    if b"\x00" in data[:65536]:
        raise InputError(
            "this is a binary file, not a facepipe CSV take",
            path=path,
            hint="convert the take to the facepipe CSV (frame,time,NAME_x,NAME_y,NAME_z,...)",
        )
    return data


def _header_columns(line: bytes, line_no: int, path) -> list[str]:
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(f"line {line_no}: the header is not UTF-8 text", path=path,
                         hint="save the take as UTF-8 CSV") from None
    return [c.strip().strip('"').strip() for c in text.split(",")]


def _parse_header(columns: list[str], line_no: int, path):
    """Split header names into the frame and time columns and marker triples.

    Returns
    -------
    frame_col, time_col : int
    markers : list[str]
        Marker names in order of first appearance.
    marker_cols : (N, 3) int64
        Column of x, y, z of each marker.
    """
    where = f"line {line_no} (header)"
    hint_format = "the header must be frame,time,NAME_x,NAME_y,NAME_z,... (one triple per marker)"
    lower = [c.lower() for c in columns]
    missing = [n for n in ("frame", "time") if n not in lower]
    if missing:
        hint = hint_format
        text = ",".join(columns)
        if len(columns) == 1 and (";" in text or "\t" in text):
            hint = f"the columns seem separated by {';' if ';' in text else 'tabs'}: a facepipe CSV uses commas"
        raise InputError(f"{where}: no {' and no '.join(repr(n) for n in missing)} column", path=path, hint=hint)
    seen: dict[str, int] = {}
    for j, c in enumerate(columns):
        if not c:
            raise InputError(
                f"{where}: column {j + 1} has no name" + (" (a trailing comma?)" if j == len(columns) - 1 else ""),
                path=path, hint=hint_format,
            )
        if c in seen:
            raise InputError(f"{where}: column {c!r} appears twice (columns {seen[c] + 1} and {j + 1})",
                             path=path, hint="rename or remove one of them")
        seen[c] = j
    for n in ("frame", "time"):
        if lower.count(n) > 1:
            raise InputError(f"{where}: more than one {n!r} column", path=path, hint="remove the extra one")
    frame_col, time_col = lower.index("frame"), lower.index("time")
    triples: dict[str, list[int]] = {}
    for j, c in enumerate(columns):
        if j in (frame_col, time_col):
            continue
        m = _COLUMN_RE.match(c)
        if m is None:
            raise InputError(f"{where}: column {j + 1} {c!r} is neither frame, time nor NAME_x/_y/_z",
                             path=path, hint=hint_format)
        slot = triples.setdefault(m["name"], [-1, -1, -1])
        axis = _AXES.index(m["axis"].lower())
        if slot[axis] >= 0:
            raise InputError(f"{where}: columns {slot[axis] + 1} and {j + 1} are both {m['name']}_{_AXES[axis]}",
                             path=path, hint="rename or remove one of them")
        slot[axis] = j
    for name, cols in triples.items():
        if -1 in cols:
            have = [f"{name}_{a}" for a, c in zip(_AXES, cols) if c >= 0]
            lack = [f"{name}_{a}" for a, c in zip(_AXES, cols) if c < 0]
            raise InputError(
                f"{where}: marker {name} has {', '.join(have)} but no {', '.join(lack)}",
                path=path, hint="every marker needs the three columns NAME_x, NAME_y, NAME_z",
            )
    cols = np.array(list(triples.values()), dtype=np.int64).reshape(-1, 3)
    return frame_col, time_col, list(triples), cols


def _parse_block_fast(blob: bytes, n_rows: int, n_cols: int) -> np.ndarray | None:
    """Parse rows of plain decimals (``-12.34567``, empty = NaN) with array operations.

    Parameters
    ----------
    blob : bytes
        ``n_rows`` lines, each ending in a newline, of ``n_cols`` comma-separated fields.

    Returns
    -------
    (n_rows, n_cols) float64, or None when some field is anything else (exponent,
    ``nan``, spaces, too many digits, junk): the caller then parses per cell.

    All fields advance together one character at a time (Horner's rule on the
    digits), so the loop runs as often as the longest field has characters. A value
    is the integer of its digits (below 2**53, so exact) divided by an exact power of
    ten: the one rounding of the division gives the same double as ``float(text)``.
    """
    n_text = len(blob)
    # Padding: reads past a field's end stay inside the buffer (and are masked off).
    buf = np.frombuffer(blob + b"\n" * 18, dtype=np.uint8)
    sep = np.flatnonzero((buf[:n_text] == 44) | (buf[:n_text] == 10))
    n = sep.size
    if n != n_rows * n_cols:
        return None
    starts = np.empty(n, dtype=np.int64)
    starts[0] = 0
    starts[1:] = sep[:-1] + 1
    nonempty = starts < sep
    first = buf[starts]
    signed = ((first == 45) | (first == 43)) & nonempty
    at = starts + signed
    left = sep - at  # characters after the sign
    if int(left.max()) > 17:
        return None
    mantissa = np.zeros(n, dtype=np.int64)
    frac = np.zeros(n, dtype=np.int64)
    seen_dot = np.zeros(n, dtype=bool)
    n_dot = np.zeros(n, dtype=np.int8)
    has_digit = np.zeros(n, dtype=bool)
    n_ok = 0
    for k in range(int(left.max())):
        live = left > k
        c = buf[at + k]
        d = c - np.uint8(48)  # wraps around for bytes below '0'
        is_digit = (d < 10) & live
        is_dot = (c == 46) & live
        n_ok += np.count_nonzero(is_digit) + np.count_nonzero(is_dot)
        seen_dot |= is_dot
        n_dot += is_dot
        has_digit |= is_digit
        mantissa = np.where(is_digit, mantissa * 10 + d, mantissa)
        frac += is_digit & seen_dot
    # Every character a digit or the point, one point at most, a digit in every
    # non-empty field ("-" and "." are not numbers), and an exact mantissa.
    if (
        n_ok != int(left.sum())
        or (n_dot > 1).any()
        or (has_digit != nonempty).any()
        or (mantissa > 2**53).any()
    ):
        return None
    values = mantissa / _POW10[frac]
    neg = signed & (first == 45)
    values[neg] = -values[neg]
    values[~nonempty] = np.nan
    return values.reshape(n_rows, n_cols)


def _parse_block_slow(rows: list[bytes], line_no: np.ndarray, use: np.ndarray, columns: list[str], path) -> np.ndarray:
    """Parse the ``use`` columns of ``rows`` cell by cell, naming the first bad cell.

    Returns
    -------
    (len(rows), len(use)) float64, NaN for empty or ``NaN`` cells.
    """
    out = np.empty((len(rows), use.size), dtype=np.float64)
    cols = use.tolist()
    for r, row in enumerate(rows):
        fields = row.split(b",")
        for k, j in enumerate(cols):
            cell = fields[j].strip()
            if not cell:
                out[r, k] = np.nan
            elif _NUMBER_RE.match(cell):
                out[r, k] = float(cell)
            else:
                shown = cell[:40].decode("utf-8", "replace")
                raise InputError(
                    f"line {line_no[r]}, column {columns[j]!r}: {shown!r} is not a number",
                    path=path,
                    hint="write a decimal number, or leave the field empty (or NaN) for a missing sample",
                )
    return out


def _take_from_values(stamps: np.ndarray, positions: np.ndarray, line_no: np.ndarray,
                      marker_names: list[str], extra: list[str], path) -> Take:
    """Build a Take from parsed (T, 2) frame and time columns and (T, M, 3) positions."""
    frame_f = stamps[:, 0]
    bad = np.flatnonzero(~np.isfinite(frame_f) | (frame_f != np.round(frame_f)) | (np.abs(frame_f) > 2.0**53))
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"line {line_no[i]}, column 'frame': the frame number is missing or not an integer",
            path=path, hint="the first field of every row is its integer frame number",
        )
    return Take(
        frames=frame_f.astype(np.int64),
        times=np.ascontiguousarray(stamps[:, 1]),
        positions=positions,
        marker_names=list(marker_names),
        path=str(path),
        extra_markers=list(extra),
        lines=line_no,
    )


READERS[".csv"] = read_csv_take


def write_take_csv(path: str | os.PathLike, take: Take, decimals: int = 5, time_decimals: int = 6) -> None:
    """Write a take as a facepipe CSV (atomically: no half-written file on failure).

    Parameters
    ----------
    path : str or PathLike
    take : Take
        ``frames`` (T,), ``times`` (T,), ``positions`` (T, M, 3) with NaN for missing
        samples (written as empty fields), ``marker_names`` (M,).
    decimals, time_decimals : int
        Digits after the point for positions and times.

    Example
    -------
    >>> write_take_csv("take.csv", take)  # doctest: +SKIP
    """
    frames = np.asarray(take.frames, dtype=np.int64)
    times = np.asarray(take.times, dtype=np.float64)
    pos = np.asarray(take.positions, dtype=np.float64)
    T, M = pos.shape[0], pos.shape[1]
    if pos.shape != (T, M, 3) or frames.shape != (T,) or times.shape != (T,) or len(take.marker_names) != M:
        raise ValueError("take arrays do not match: frames (T,), times (T,), positions (T, M, 3), M names")
    header = ",".join(["frame", "time"] + [f"{n}_{a}" for n in take.marker_names for a in _AXES])
    row_fmt = ",".join(["%d", f"%.{time_decimals}f"] + [f"%.{decimals}f"] * (3 * M))
    with atomic_open(path, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(header + "\n")
        for a in range(0, T, 4096):  # blocks: bounded memory for long takes
            b = min(T, a + 4096)
            flat = pos[a:b].reshape(b - a, 3 * M)
            # Only numbers are formatted, so "nan" can only be a missing sample.
            text = "\n".join(
                row_fmt % (f, t, *p) for f, t, p in zip(frames[a:b].tolist(), times[a:b].tolist(), flat.tolist())
            )
            fh.write(text.replace("nan", "") + "\n")


# --------------------------------------------------------------------------- gap filling


def fill_gaps(positions, max_gap: int | None = None, *, times=None, marker_names=None, path=None):
    """Fill runs of missing samples per marker: PCHIP inside, held constant at the ends.

    A gap inside the take is filled by the monotone cubic Hermite interpolant
    (:class:`scipy.interpolate.PchipInterpolator`) through the marker's visible
    samples: it passes through the samples on both sides with smooth slopes, and
    on each interval it stays between its two end values (no overshoot however
    long the gap). A gap at the start or end takes the first or last visible value:
    extrapolating a marker's motion past its last sample is not to be trusted.

    Parameters
    ----------
    positions : (T, M, 3) float
        Marker positions, NaN where a sample is missing (a sample with any NaN
        coordinate counts as missing).
    max_gap : int, optional
        Fill only gaps of at most this many frames; longer ones stay NaN and are
        reported as ``unfilled``. None fills every gap.
    times : (T,) float, optional
        Strictly increasing sample times (seconds); the default is the frame index.
    marker_names : list[str], optional
        Names for the report and messages; default ``marker0``, ``marker1``, ...
    path : str, optional
        The take, for messages.

    Returns
    -------
    filled : (T, M, 3) float64
        A copy with the gaps filled.
    report : dict
        JSON-serialisable. ``report["markers"][name]`` has ``gaps`` (number of runs
        of missing frames), ``filled`` (samples filled), ``unfilled`` (samples left
        missing, see ``max_gap``) and ``longest_gap`` (frames); ``report["total"]``
        has ``frames``, ``markers``, ``missing`` (samples), ``missing_fraction``,
        ``gaps``, ``filled``, ``unfilled``, ``longest_gap`` and ``longest_gap_marker``.

    Raises
    ------
    InputError
        A marker that is never visible (naming every such marker).

    Example
    -------
    >>> P = np.zeros((5, 1, 3)); P[:, 0, 0] = [0, 1, np.nan, 3, 4]
    >>> filled, report = fill_gaps(P)
    >>> float(filled[2, 0, 0]), report["total"]["filled"]
    (2.0, 1)
    """
    from scipy.interpolate import PchipInterpolator

    pos = np.array(positions, dtype=np.float64)  # a copy: the caller's array is left alone
    if pos.ndim != 3 or pos.shape[2] != 3:
        raise ValueError(f"positions must be (T, M, 3), got {pos.shape}")
    T, M = pos.shape[:2]
    names = [f"marker{m}" for m in range(M)] if marker_names is None else [str(n) for n in marker_names]
    if len(names) != M:
        raise ValueError(f"{len(names)} marker names for {M} markers")
    if max_gap is not None and (int(max_gap) != max_gap or max_gap < 1):
        raise ValueError(f"max_gap must be a positive integer or None, got {max_gap!r}")
    t = np.arange(T, dtype=np.float64) if times is None else np.asarray(times, dtype=np.float64)
    if t.shape != (T,) or (T > 1 and not (np.diff(t) > 0).all()) or not np.isfinite(t).all():
        raise ValueError("times must be (T,), finite and strictly increasing")

    missing = np.isnan(pos).any(axis=2)  # (T, M)
    pos[missing] = np.nan
    never = [names[m] for m in np.flatnonzero(missing.all(axis=0))] if T else []
    if never:
        shown = ", ".join(never[:12]) + (f" and {len(never) - 12} more" if len(never) > 12 else "")
        raise InputError(
            f"marker(s) never visible in the take: {shown}",
            path=path,
            hint="check the marker's columns in the take, or mark the marker `ignore` in markers.csv",
        )

    # Runs of missing frames, marker by marker: +1/-1 steps of the padded mask.
    step = np.diff(np.pad(missing.T.astype(np.int8), ((0, 0), (1, 1))), axis=1)  # (M, T+1)
    run_m, run_start = np.nonzero(step == 1)
    _, run_stop = np.nonzero(step == -1)  # same marker-major order as the starts
    run_len = run_stop - run_start
    # Length of the gap each missing sample belongs to, in (marker, frame) order.
    sample_len = np.repeat(run_len, run_len)
    mm, tt = np.nonzero(missing.T)
    fill = np.ones(mm.size, dtype=bool) if max_gap is None else sample_len <= max_gap
    do = np.zeros((M, T), dtype=bool)
    do[mm[fill], tt[fill]] = True

    for m in np.flatnonzero(do.any(axis=1)):
        vis = np.flatnonzero(~missing[:, m])
        rows = np.flatnonzero(do[m])
        first, last = vis[0], vis[-1]
        lo, hi = rows[rows < first], rows[rows > last]
        mid = rows[(rows > first) & (rows < last)]
        pos[lo, m] = pos[first, m]
        pos[hi, m] = pos[last, m]
        if mid.size:
            pos[mid, m] = PchipInterpolator(t[vis], pos[vis, m], axis=0)(t[mid])

    n_gaps = np.bincount(run_m, minlength=M)
    n_missing = missing.sum(axis=0)
    n_filled = do.sum(axis=1)
    longest = np.zeros(M, dtype=np.int64)
    np.maximum.at(longest, run_m, run_len)
    report = {
        "markers": {
            names[m]: {
                "gaps": int(n_gaps[m]),
                "filled": int(n_filled[m]),
                "unfilled": int(n_missing[m] - n_filled[m]),
                "longest_gap": int(longest[m]),
            }
            for m in range(M)
        },
        "total": {
            "frames": int(T),
            "markers": int(M),
            "missing": int(n_missing.sum()),
            "missing_fraction": float(n_missing.sum() / max(1, T * M)),
            "gaps": int(n_gaps.sum()),
            "filled": int(n_filled.sum()),
            "unfilled": int(n_missing.sum() - n_filled.sum()),
            "longest_gap": int(longest.max()) if M else 0,
            "longest_gap_marker": names[int(np.argmax(longest))] if M and longest.max() > 0 else None,
        },
    }
    return pos, report
