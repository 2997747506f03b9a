"""Numeric tables under a vendor header (TRC, Vicon CSV, Motive CSV): rows to arrays.

The header of each vendor format is parsed by its own module; the body is rows of numbers
with empty fields for missing samples, parsed here with the facepipe CSV's vectorised
parser (and its per-cell fallback that names the bad cell).
"""

from __future__ import annotations

import numpy as np

from facepipe.errors import InputError
from facepipe.mocap.facepipe_csv import (_BLOCK_BYTES, _NAN_FIELD, _parse_block_fast, _parse_block_slow, _read_bytes)
from facepipe.mocap.markers import find_markers
from facepipe.mocap.take import Take


def read_lines(path, binary_hint: str) -> tuple[list[bytes], bool]:
    """The file's lines (line ends normalised, BOM removed) and whether it ended with a newline.

    Raises
    ------
    InputError
        Empty, unreadable or binary file.
    """
    try:
        data = _read_bytes(path)
    except InputError as exc:
        if "binary file" in str(exc):
            raise InputError("this is a binary file, not a text take", path=path, hint=binary_hint) from None
        raise
    if b"\r" in data:
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    ends = data.endswith(b"\n")
    return data.split(b"\n"), ends


def split_fields(line: bytes, sep: bytes) -> list[str]:
    """Header cells of a line, decoded and stripped of spaces and quotes."""
    text = line.decode("utf-8", "replace")
    return [c.strip().strip('"').strip() for c in text.split(sep.decode())]


def parse_rows(lines: list[bytes], first: int, n_cols: int, use: np.ndarray, columns: list[str], path,
               sep: bytes = b",", ended: bool = True, stop_at_blank: bool = False):
    """Parse the numeric body ``lines[first:]`` into the ``use`` columns.

    Parameters
    ----------
    lines : list[bytes]
        All lines of the file (for line numbers).
    first : int
        Index of the first body line.
    n_cols : int
        Fields per row in the header. Shorter rows are padded with empty fields (writers
        drop trailing missing samples), except a last line cut off without its newline.
    use : (U,) int64
        Columns to keep, in output order.
    columns : list[str]
        Column names for messages.
    sep : bytes
        Field separator.
    ended : bool
        Whether the file ended with a newline.
    stop_at_blank : bool
        Stop at the first blank line after some rows (a block in a multi-block file);
        otherwise blank lines are skipped.

    Returns
    -------
    values : (T, U) float64, NaN for empty fields
    line_no : (T,) int64, 1-based line of each row

    Raises
    ------
    InputError
        A truncated last row, extra non-empty fields, a cell that is not a number (naming
        line and column).
    """
    rows, numbers = [], []
    last = len(lines) - 1
    while last >= first and not lines[last].strip():
        last -= 1
    for i in range(first, last + 1):
        ln = lines[i]
        if not ln.strip():
            if stop_at_blank and rows:
                break
            continue
        if sep != b",":
            ln = ln.replace(b",", b"\x00").replace(sep, b",")  # a stray comma must not split a cell
        n = ln.count(b",") + 1
        if n < n_cols:
            if i == last and not ended:
                raise InputError(f"line {i + 1}: {n} fields, the header has {n_cols} (truncated row)", path=path,
                                 hint="the file looks cut off: export or copy it again")
            ln = ln + b"," * (n_cols - n)
        elif n > n_cols:
            head, _, tail = _split_at(ln, n_cols)
            if tail.strip(b", \t"):
                raise InputError(f"line {i + 1}: {n} fields, the header has {n_cols} (extra fields)", path=path,
                                 hint="every row needs the header's columns, no more")
            ln = head
        rows.append(ln)
        numbers.append(i + 1)
    line_no = np.asarray(numbers, dtype=np.int64)
    out = np.empty((len(rows), use.size), dtype=np.float64)
    width = 1 + sum(len(r) for r in rows[:64]) // max(1, min(64, len(rows)))
    step = max(1, _BLOCK_BYTES // width)
    for a in range(0, len(rows), step):
        block = rows[a:a + step]
        blob = b"\n".join(block) + b"\n"
        if b"n" in blob or b"N" in blob:
            blob = _NAN_FIELD.sub(b"", blob)
        vals = _parse_block_fast(blob, len(block), n_cols)
        out[a:a + len(block)] = (_parse_block_slow(block, line_no[a:a + len(block)], use, columns, path)
                                 if vals is None else vals[:, use])
    return out, line_no


def _split_at(line: bytes, n: int) -> tuple[bytes, bytes, bytes]:
    """Split after the n-th field: (first n fields, separator, rest)."""
    pos = -1
    for _ in range(n):
        pos = line.find(b",", pos + 1)
        if pos < 0:
            return line, b"", b""
    return line[:pos], b",", line[pos + 1:]


def frame_column(values: np.ndarray, line_no: np.ndarray, name: str, path) -> np.ndarray:
    """Integer frame numbers from a parsed column; InputError naming the first bad line."""
    bad = np.flatnonzero(~np.isfinite(values) | (values != np.round(values)) | (np.abs(values) > 2.0**53))
    if bad.size:
        raise InputError(f"line {line_no[bad[0]]}, column {name!r}: the frame number is missing or not an integer",
                         path=path, hint="the first field of every row is its integer frame number")
    return values.astype(np.int64)


def read_marker_table(lines: list[bytes], first: int, n_cols: int, head: list[str], file_markers: list[str],
                      cols, marker_names: list[str], path, units: str | None, match=None, rate: float | None = None,
                      frame_name: str | None = None, **options) -> Take:
    """Match a vendor header's markers to the rig's, parse the body and build the Take.

    Parameters
    ----------
    lines : list[bytes]
    first : int
        Index of the first body line.
    n_cols : int
        Fields per row in the header.
    head : list[str]
        Names of the leading columns (frame, then time or sub frame) for messages.
    file_markers : list[str]
        The file's markers, in file order.
    cols : sequence of (3,) int
        The X, Y, Z column of each file marker.
    marker_names : list[str]
    path : Path
    units : str or None
    match : callable(list[str]) -> MarkerMatch, optional
    rate : float, optional
        Times are frame / rate; without it they are the second leading column.
    frame_name : str, optional
        The frame column's name in messages (default ``head[0]``).
    **options
        ``sep``, ``ended``, ``stop_at_blank`` for :func:`parse_rows`.

    Returns
    -------
    Take
        ``positions`` (T, M, 3), NaN for rig markers absent from the file; ``lines`` set.
    """
    found = find_markers(file_markers, marker_names, path, match)
    present = found.index >= 0
    col = np.asarray(cols, dtype=np.int64)
    columns = list(head) + [""] * (n_cols - len(head))
    for name, (a, b, c) in zip(file_markers, col.tolist()):
        columns[a], columns[b], columns[c] = f"{name} X", f"{name} Y", f"{name} Z"
    lead = [0] if rate is not None else [0, 1]
    use = np.concatenate([lead, col[found.index[present]].ravel()]).astype(np.int64)
    values, line_no = parse_rows(lines, first, n_cols, use, columns, path, **options)
    frames = frame_column(values[:, 0], line_no, frame_name or head[0], path)
    positions = np.full((len(values), len(marker_names), 3), np.nan)
    positions[:, present] = values[:, len(lead):].reshape(len(values), int(present.sum()), 3)
    times = frames / rate if rate is not None else values[:, 1].copy()
    return Take(frames=frames, times=times, positions=positions, marker_names=list(marker_names), path=str(path),
                extra_markers=found.extra, lines=line_no, units=units, markers=found.report)
