"""TRC takes (the tab-separated marker format of Motion Analysis, OpenSim and Motive).

::

    PathFileType  4  (X/Y/Z)  take.trc
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
    30.00     30.00       60         96          mm     30.00         1                   60
    Frame#  Time  M001        M002  ...
                  X1  Y1  Z1  X2  Y2  Z2 ...
    (blank line)
    1  0.000  12.3  45.6  78.9  ...

Marker names sit over their X column; an empty field is a missing sample.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facepipe.errors import InputError
from facepipe.mocap.markers import normalise_units
from facepipe.mocap.registry import Format, nominal_rate, marker_label, register
from facepipe.mocap.table import read_lines, read_marker_table, split_fields
from facepipe.mocap.take import Take, write_marker_rows

_HINT = "a TRC take starts with PathFileType, then the DataRate ... Units header and its values"


def read_trc_take(path: Path, marker_names: list[str], match=None) -> Take:
    """Read every frame of a TRC take.

    Parameters
    ----------
    path : Path
    marker_names : list[str]
    match : callable(list[str]) -> MarkerMatch, optional

    Returns
    -------
    Take
        ``positions`` (T, M, 3) in the header's ``Units``; frames and times from the
        ``Frame#`` and ``Time`` columns.

    Raises
    ------
    InputError
        Naming the line of a malformed header or body row.
    """
    lines, ended = read_lines(path, _HINT)
    if len(lines) < 5 or not lines[0].lstrip().lower().startswith(b"pathfiletype"):
        raise InputError("not a TRC file (line 1 must start with PathFileType)", path=path, hint=_HINT)
    keys = split_fields(lines[1], b"\t")
    vals = split_fields(lines[2], b"\t")
    info = {k.lower(): v for k, v in zip(keys, vals) if k}
    if "units" not in info:
        raise InputError("line 2 (header): no Units column", path=path, hint=_HINT)
    units = normalise_units(info["units"], path, "unit (line 3, Units)")
    names_row = split_fields(lines[3], b"\t")
    axes_row = split_fields(lines[4], b"\t")
    if len(names_row) < 2 or names_row[0].lower().rstrip("#") != "frame" or names_row[1].lower() != "time":
        raise InputError("line 4 (header): expected Frame# and Time, then the marker names", path=path, hint=_HINT)
    file_markers, cols = [], []
    for j in range(2, len(names_row)):
        if names_row[j]:
            if j + 2 >= len(axes_row):
                raise InputError(f"line 5 (header): marker {names_row[j]!r} lacks its X, Y, Z columns",
                                 path=path, hint=_HINT)
            file_markers.append(names_row[j])
            cols.append((j, j + 1, j + 2))
    if not file_markers:
        raise InputError("line 4 (header): no marker names", path=path, hint=_HINT)
    n_cols = max(len(axes_row), len(names_row), cols[-1][2] + 1)
    return read_marker_table(lines, 5, n_cols, ["Frame#", "Time"], file_markers, cols, marker_names, path, units,
                             match, sep=b"\t", ended=ended)


def write_trc_take(path, take: Take, units: str | None = None, subject: str | None = None,
                   decimals: int = 5) -> None:
    """Write a take as TRC (tab-separated, empty fields for missing samples), atomically.

    Parameters
    ----------
    path : str or Path
    take : Take
    units : str, optional
        Declared in the header (default ``take.units`` or ``mm``).
    subject : str, optional
        Prefix marker names with ``subject:``.
    decimals : int
    """
    pos = np.asarray(take.positions, dtype=np.float64)
    T, M = pos.shape[:2]
    rate = nominal_rate(take, 30.0)
    units = units or take.units or "mm"
    first = int(take.frames[0]) if T else 1
    head = [
        f"PathFileType\t4\t(X/Y/Z)\t{Path(path).name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate:.6g}\t{rate:.6g}\t{T}\t{M}\t{units}\t{rate:.6g}\t{first}\t{T}",
        "Frame#\tTime\t" + "\t".join(f"{marker_label(n, subject)}\t\t" for n in take.marker_names).rstrip("\t"),
        "\t\t" + "\t".join(f"X{k + 1}\tY{k + 1}\tZ{k + 1}" for k in range(M)),
        "",
    ]
    fmt = "\t".join(["%d", "%.6f"] + [f"%.{decimals}f"] * (3 * M))
    write_marker_rows(path, "\n".join(head) + "\n", take, pos, fmt)


def _sniff(head: bytes) -> bool:
    return head.lower().startswith(b"pathfiletype")


register(Format("trc", (".trc",), read_trc_take, write_trc_take, _sniff))
