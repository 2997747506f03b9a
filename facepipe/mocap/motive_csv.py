"""OptiTrack Motive CSV takes (export format 1.2x).

::

    Format Version,1.23,Take Name,t,...,Export Frame Rate,120.000000,...,Length Units,Millimeters,...
    (blank line)
    ,Type,Marker,Marker,Marker,Rigid Body,...
    ,Name,Actor:M001,Actor:M001,Actor:M001,Head,...
    ,ID,1,1,1,...
    ,,Position,Position,Position,Rotation,...
    Frame,Time (Seconds),X,Y,Z,X,...
    0,0.000000,12.3,45.6,78.9,...

Only ``Marker`` columns' ``Position`` X, Y, Z are read (rigid bodies, bones and their
constraint markers are other assets); a blank cell is a missing sample (an occlusion). The
first line's ``Length Units`` gives the unit (files without it are taken to be in the rig's
units, and the alignment's scale check catches a mismatch).
"""

from __future__ import annotations

import numpy as np

from facepipe.errors import InputError
from facepipe.mocap.markers import normalise_units
from facepipe.mocap.registry import Format, nominal_rate, marker_label, register
from facepipe.mocap.table import read_lines, read_marker_table, split_fields
from facepipe.mocap.take import Take, write_marker_rows

_HINT = "export the take from Motive as CSV with markers and the header rows (Type, Name, ID, Position, Frame)"


def _label(cells: list[str]) -> str:
    """The row label of a header row: in column 1 (format 1.2x) or column 0 (older)."""
    for c in cells[:2]:
        if c:
            return c.lower()
    return ""


def read_motive_take(path, marker_names: list[str], match=None) -> Take:
    """Read the markers of an OptiTrack Motive CSV export.

    Parameters
    ----------
    path : Path
    marker_names : list[str]
    match : callable(list[str]) -> MarkerMatch, optional

    Returns
    -------
    Take
        ``positions`` (T, M, 3) in ``Length Units``; frames and times from the Frame and
        Time (Seconds) columns.

    Raises
    ------
    InputError
        A malformed header (naming its line), no marker columns, bad cells.
    """
    lines, ended = read_lines(path, _HINT)
    first = split_fields(lines[0], b",")
    if not first or first[0].lower() != "format version":
        raise InputError("not a Motive CSV (line 1 must start with 'Format Version')", path=path, hint=_HINT)
    info = {first[k].lower(): first[k + 1] for k in range(0, len(first) - 1, 2)}
    units = normalise_units(info.get("length units"), path, "unit (Length Units)")
    axis_line = next((i for i, ln in enumerate(lines[:64]) if split_fields(ln, b",")[0].lower() == "frame"), None)
    if axis_line is None:
        raise InputError("no 'Frame,Time (Seconds),X,Y,Z,...' header row", path=path, hint=_HINT)
    rows = {}
    for i in range(1, axis_line):
        cells = split_fields(lines[i], b",")
        label = _label(cells)
        if label in ("type", "name", "id", "parent"):
            rows[label] = (i, cells)
        elif any(c.lower() in ("position", "rotation") for c in cells):
            rows["component"] = (i, cells)
    for need in ("type", "name", "component"):
        if need not in rows:
            raise InputError(f"line {axis_line + 1}: the header has no {need.title()} row above it",
                             path=path, hint=_HINT)
    axes = split_fields(lines[axis_line], b",")
    n_cols = len(axes)

    def cell(key, j):
        cells = rows[key][1]
        return cells[j] if j < len(cells) else ""

    triples: dict[str, list[int]] = {}
    for j in range(2, n_cols):
        if cell("type", j).lower() != "marker" or cell("component", j).lower() != "position":
            continue
        axis = axes[j].upper()
        if axis not in ("X", "Y", "Z"):
            continue
        triples.setdefault(cell("name", j), [-1, -1, -1])["XYZ".index(axis)] = j
    for name, cols in triples.items():
        if -1 in cols or not name:
            raise InputError(f"line {rows['name'][0] + 1}: marker {name!r} lacks some of its X, Y, Z columns",
                             path=path, hint=_HINT)
    if not triples:
        raise InputError("no marker position columns (Type 'Marker', 'Position', X/Y/Z)", path=path,
                         hint="enable Markers in Motive's CSV export options")
    head = [axes[0] or "Frame", axes[1] if n_cols > 1 else "Time"]
    return read_marker_table(lines, axis_line + 1, n_cols, head, list(triples), list(triples.values()),
                             marker_names, path, units, match, frame_name="Frame", ended=ended)


_UNIT_WORDS = {"mm": "Millimeters", "cm": "Centimeters", "m": "Meters", "in": "Inches", "dm": "Decimeters",
               "ft": "Feet"}


def write_motive_take(path, take: Take, units: str | None = None, subject: str | None = None,
                      decimals: int = 6) -> None:
    """Write a take as a Motive CSV (format 1.23, markers only), atomically.

    Parameters
    ----------
    path : str or Path
    take : Take
    units : str, optional
        ``Length Units`` (default ``take.units`` or ``m``, Motive's default).
    subject : str, optional
        Marker names become ``subject:name``.
    decimals : int
    """
    pos = np.asarray(take.positions, dtype=np.float64)
    T, M = pos.shape[:2]
    rate = nominal_rate(take, 120.0)
    units = units or take.units or "m"
    names = [marker_label(n, subject) for n in take.marker_names]
    head = [
        f"Format Version,1.23,Take Name,facepipe,Take Notes,,Capture Frame Rate,{rate:.6f},"
        f"Export Frame Rate,{rate:.6f},Capture Start Time,,Capture Start Frame,{int(take.frames[0]) if T else 0},"
        f"Total Frames in Take,{T},Total Exported Frames,{T},Rotation Type,Quaternion,"
        f"Length Units,{_UNIT_WORDS[units]},Coordinate Space,Global",
        "",
        ",Type," + ",".join(["Marker"] * (3 * M)),
        ",Name," + ",".join(n for n in names for _ in range(3)),
        ",ID," + ",".join(str(k + 1) for k in range(M) for _ in range(3)),
        ",," + ",".join(["Position"] * (3 * M)),
        "Frame,Time (Seconds)," + ",".join(["X,Y,Z"] * M),
    ]
    fmt = ",".join(["%d", "%.6f"] + [f"%.{decimals}f"] * (3 * M))
    write_marker_rows(path, "\n".join(head) + "\n", take, pos, fmt)


def _sniff(head: bytes) -> bool:
    return head.lower().startswith((b"format version,", b'"format version",'))


register(Format("motive-csv", (".csv",), read_motive_take, write_motive_take, _sniff))
