"""The facepipe CSV take format (see the README, "Mocap takes")::

    frame,time,M001_x,M001_y,M001_z,M002_x,...
    0,0.000000,-7.34958,3.64373,3.69269,,,,...

One row per frame: an integer frame number, the time in seconds, then x, y, z of every
marker. An empty field or ``NaN`` is a missing sample. The file does not record its units:
it is taken to be in the rig's units (``--take-units`` says otherwise).

Long takes are common (100k frames × 100 markers is 260 MB of text), so the CSV body is
parsed by a vectorised NumPy decimal parser; blocks it cannot handle (exponents, ``NaN``,
stray characters) go through a per-cell path that either parses them or names the line and
column of the bad cell.
"""

from __future__ import annotations

import os
import re
from dataclasses import replace
from pathlib import Path

import numpy as np

from facepipe.errors import InputError
from facepipe.mocap.markers import find_markers
from facepipe.mocap.registry import Format, marker_label, register
from facepipe.mocap.take import AXES as _AXES
from facepipe.mocap.take import Take, write_marker_rows
from facepipe.parallel import map_blocks

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


def read_csv_take(path: Path, marker_names: list[str], match=None) -> Take:
    """Read every frame of a facepipe CSV take.

    Parameters
    ----------
    path : Path
    marker_names : list[str]
        The rig's M markers, in order.
    match : callable(list[str]) -> MarkerMatch, optional
        Finds the rig's markers among the file's (default: exact names or subject
        prefixes stripped, absent markers an error).

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
    lines = _text_lines(_read_bytes(path))
    h = _header_line(lines, path)
    columns = _header_columns(lines[h], h + 1, path)
    frame_col, time_col, file_markers, marker_cols = _parse_header(columns, h + 1, path)
    found = find_markers(file_markers, marker_names, path, match)
    present = found.index >= 0
    # Columns to parse, in output order: frame, time, then x, y, z of each rig marker
    # in the file (absent ones stay NaN).
    use = np.concatenate([[frame_col, time_col], marker_cols[found.index[present]].ravel()]).astype(np.int64)
    rows, line_no = _body_rows(lines, h)
    del lines
    _check_field_counts(rows, line_no, len(columns), path)
    stamps, positions = _parse_rows(rows, line_no, use, columns, present, path)
    return replace(_take_from_values(stamps, positions, line_no, marker_names, found.extra, path),
                   markers=found.report)


def _text_lines(data: bytes) -> list[bytes]:
    """The file's lines, whatever its line ends (Windows or old Mac ones give the same line numbers)."""
    if b"\r" in data:
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    return data.split(b"\n")


def _header_line(lines: list[bytes], path) -> int:
    """Index of the header: the first non-blank line."""
    h = next((i for i, ln in enumerate(lines) if ln.strip()), None)
    if h is None:
        raise InputError(
            "the take is empty",
            path=path,
            hint="a facepipe take starts with the header frame,time,NAME_x,NAME_y,NAME_z,...",
        )
    return h


def _body_rows(lines: list[bytes], h: int) -> tuple[list[bytes], np.ndarray]:
    """The rows after the header line ``h``, blank lines skipped, and each row's line number."""
    body = lines[h + 1:]
    keep = [i for i, ln in enumerate(body) if ln and not ln.isspace()]
    rows = body if len(keep) == len(body) else [body[i] for i in keep]
    return rows, np.asarray(keep, dtype=np.int64) + (h + 2)


def _check_field_counts(rows: list[bytes], line_no: np.ndarray, n_cols: int, path) -> None:
    """Every row has the header's number of fields; else name the first row that has not."""
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


def _parse_rows(rows: list[bytes], line_no: np.ndarray, use: np.ndarray, columns: list[str], present: np.ndarray,
                path) -> tuple[np.ndarray, np.ndarray]:
    """Parse the ``use`` columns of the rows: frame and time (T, 2) and positions (T, M, 3) of the
    rig's M markers, NaN for those ``present`` says the file lacks.

    Frame and time are kept apart from the positions, so that positions are written once,
    straight into their final array. Blocks of ~4 MB keep the parser's temporaries small
    whatever the take's length, and run on several threads: NumPy releases the GIL inside its
    array operations.
    """
    n = len(rows)
    n_cols = len(columns)
    stamps = np.empty((n, 2), dtype=np.float64)
    positions = np.empty((n, len(present), 3), dtype=np.float64)
    # all present (the usual case): parse straight into the result
    inner = positions if present.all() else np.empty((n, int(present.sum()), 3), dtype=np.float64)
    flat = inner.reshape(n, 3 * inner.shape[1])
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

    # in order: the first bad line is the one reported
    map_blocks(parse, range(0, n, step))
    if inner is not positions:
        positions[:, present] = inner
        positions[:, ~present] = np.nan
    return stamps, positions


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


def write_take_csv(path: str | os.PathLike, take: Take, decimals: int = 5, time_decimals: int = 6,
                   subject: str | None = None) -> None:
    """Write a take as a facepipe CSV (atomically: no half-written file on failure).

    Parameters
    ----------
    path : str or PathLike
    take : Take
        ``frames`` (T,), ``times`` (T,), ``positions`` (T, M, 3) with NaN for missing
        samples (written as empty fields), ``marker_names`` (M,).
    decimals, time_decimals : int
        Digits after the point for positions and times.
    subject : str, optional
        Prefix every marker name with ``subject:`` (as capture software does).

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
    header = ",".join(["frame", "time"] + [f"{marker_label(n, subject)}_{a}" for n in take.marker_names for a in _AXES])
    row_fmt = ",".join(["%d", f"%.{time_decimals}f"] + [f"%.{decimals}f"] * (3 * M))
    write_marker_rows(path, header + "\n", take, pos, row_fmt)





def _write(path, take: Take, units=None, **options) -> None:
    write_take_csv(path, take, **options)  # the format has no units: the caller keeps track


def _sniff(head: bytes) -> bool:
    first = head.split(b"\n", 1)[0].lower().replace(b'"', b"")
    coords = [c.strip() for c in first.strip().split(b",")[2:]]
    uv = bool(coords) and all(c.endswith((b"_u", b"_v")) for c in coords)  # a 2D take (mocap/landmarks2d.py)
    return first.startswith(b"frame,") and b",time" in first and not uv


register(Format("facepipe-csv", (".csv", ".txt"), read_csv_take, _write, _sniff))
