"""Vicon Nexus CSV takes: the ``Trajectories`` block of a Nexus CSV export.

::

    Trajectories
    100
    ,,Actor:M001,,,Actor:M002,,,
    Frame,Sub Frame,X,Y,Z,X,Y,Z
    ,,mm,mm,mm,mm,mm,mm
    1,0,12.3,45.6,78.9,,,
    (blank line: end of the block; Devices, Model Outputs, ... blocks are skipped)

Line 2 of the block is the frame rate; marker names (``Subject:Marker``) sit over their X
column; the units row gives the length unit; an empty field is a missing sample. Times are
frame / rate.
"""

from __future__ import annotations

import numpy as np

from facepipe.errors import InputError
from facepipe.mocap.markers import normalise_units
from facepipe.mocap.registry import Format, nominal_rate, marker_label, register
from facepipe.mocap.table import read_lines, read_marker_table, split_fields
from facepipe.mocap.take import Take, write_marker_rows

_HINT = "export the take from Nexus as CSV with the Trajectories block (Frame, Sub Frame, X, Y, Z per marker)"
_BLOCKS = (b"trajectories", b"devices", b"model outputs", b"joints", b"segments")


def _first_cell(line: bytes) -> bytes:
    return line.split(b",", 1)[0].strip().strip(b'"').strip().lower()


def read_vicon_take(path, marker_names: list[str], match=None):
    """Read the Trajectories block of a Vicon Nexus CSV.

    Parameters
    ----------
    path : Path
    marker_names : list[str]
    match : callable(list[str]) -> MarkerMatch, optional

    Returns
    -------
    Take
        ``positions`` (T, M, 3) in the units row's unit; frames from the Frame column,
        times frame / rate.

    Raises
    ------
    InputError
        No Trajectories block, a malformed header (naming its line), bad cells.
    """
    lines, ended = read_lines(path, _HINT)
    start = next((i for i, ln in enumerate(lines) if _first_cell(ln) == b"trajectories"), None)
    if start is None:
        raise InputError("no 'Trajectories' block in this Vicon CSV", path=path, hint=_HINT)
    if start + 4 >= len(lines):
        raise InputError(f"line {start + 1}: the Trajectories block is cut off after its title", path=path,
                         hint=_HINT)
    rate_cell = split_fields(lines[start + 1], b",")[0]
    try:
        rate = float(rate_cell)
    except ValueError:
        rate = float("nan")
    if not np.isfinite(rate) or rate <= 0:
        raise InputError(f"line {start + 2}: {rate_cell!r} is not a frame rate", path=path,
                         hint="the line after 'Trajectories' is the frame rate in Hz")
    names_row = split_fields(lines[start + 2], b",")
    axes_row = split_fields(lines[start + 3], b",")
    units_row = split_fields(lines[start + 4], b",")
    if len(axes_row) < 2 or axes_row[0].lower() != "frame":
        raise InputError(f"line {start + 4}: expected 'Frame,Sub Frame,X,Y,Z,...'", path=path, hint=_HINT)
    file_markers, cols = [], []
    for j in range(2, len(names_row)):
        if names_row[j]:
            if j + 2 >= len(axes_row) or [a.upper() for a in axes_row[j:j + 3]] != ["X", "Y", "Z"]:
                raise InputError(f"line {start + 4}: marker {names_row[j]!r} lacks its X, Y, Z columns",
                                 path=path, hint=_HINT)
            file_markers.append(names_row[j])
            cols.append((j, j + 1, j + 2))
    if not file_markers:
        raise InputError(f"line {start + 3}: no marker names in the Trajectories block", path=path, hint=_HINT)
    unit_cells = {u for (a, _, _) in cols for u in units_row[a:a + 3] if u}
    if len(unit_cells) > 1:
        raise InputError(f"line {start + 5}: markers in different units ({', '.join(sorted(unit_cells))})",
                         path=path, hint="export every trajectory in one unit")
    units = normalise_units(next(iter(unit_cells), None), path, f"unit (line {start + 5})")
    # the block ends at a blank line or the next block's title
    end = next((i for i in range(start + 5, len(lines)) if _first_cell(lines[i]) in _BLOCKS), len(lines))
    return read_marker_table(lines[:end], start + 5, len(axes_row), ["Frame", "Sub Frame"], file_markers, cols,
                             marker_names, path, units, match, rate=rate, ended=ended or end < len(lines),
                             stop_at_blank=True)


def write_vicon_take(path, take: Take, units: str | None = None, subject: str | None = None,
                     decimals: int = 5) -> None:
    """Write a take as a Vicon Nexus CSV Trajectories block, atomically.

    Parameters
    ----------
    path : str or Path
    take : Take
        Times must be frame / rate (the format stores a rate, not times).
    units : str, optional
        The units row (default ``take.units`` or ``mm``).
    subject : str, optional
        Marker names become ``subject:name``.
    decimals : int
    """
    pos = np.asarray(take.positions, dtype=np.float64)
    T, M = pos.shape[:2]
    rate = nominal_rate(take, 100.0)
    units = units or take.units or "mm"
    head = [
        "Trajectories",
        f"{rate:.10g}",
        ",," + ",".join(f"{marker_label(n, subject)},," for n in take.marker_names),
        "Frame,Sub Frame," + ",".join(["X,Y,Z"] * M),
        ",," + ",".join([units] * (3 * M)),
    ]
    fmt = ",".join(["%d", "0"] + [f"%.{decimals}f"] * (3 * M))
    write_marker_rows(path, "\n".join(head) + "\n", take, pos, fmt, with_times=False, footer="\n")


def _sniff(head: bytes) -> bool:
    return _first_cell(head.split(b"\n", 1)[0]) in _BLOCKS


register(Format("vicon-csv", (".csv",), read_vicon_take, write_vicon_take, _sniff))
