"""The landmark map: which rig vertex each 2D tracker point is (``name,vertex`` CSV).

Tracker points are named as the tracker numbers them (OpenFace's ``0`` … ``67`` for columns
``x_0``/``y_0`` …; a plain 2D CSV's column stems). They need not be rig markers.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facepipe.errors import InputError

__all__ = ["LandmarkMap", "model_landmark_map", "read_landmark_map"]


@dataclass(frozen=True)
class LandmarkMap:
    """Tracker point names and the rig vertex of each (in the file's order)."""

    names: list
    vertices: np.ndarray
    path: str = ""


def read_landmark_map(path, n_vertices: int, given_by: str = "--landmarks") -> LandmarkMap:
    """Read ``name,vertex`` rows (a header line ``name,vertex`` is optional); ``given_by`` says
    where the path came from (for the message of a missing file).

    Raises
    ------
    InputError
        Missing file, a row that is not ``name,vertex``, a vertex outside the mesh, a repeated
        name, fewer than 6 landmarks (a head pose needs them).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("landmark map not found", path=path,
                         hint=f"give a name,vertex CSV from the tracker's point names to rig vertices with {given_by}")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the landmark map ({exc})", path=path) from None
    names, vertices, lines = [], [], {}
    for lineno, row in enumerate(csv.reader(text.splitlines()), start=1):
        row = [c.strip() for c in row]
        if not row or not any(row) or row[0].startswith("#"):
            continue
        if lineno == 1 and row[:2] == ["name", "vertex"]:
            continue
        if len(row) < 2 or not row[0]:
            raise InputError(f"line {lineno}: expected name,vertex, got {','.join(row)!r}", path=path,
                             hint="one tracker point per line: its name and the rig vertex (0-based) it sits on")
        try:
            v = int(row[1])
        except ValueError:
            raise InputError(f"line {lineno}: vertex {row[1]!r} of landmark {row[0]} is not an integer", path=path,
                             hint="vertices are 0-based indices of the rig's mesh") from None
        if not 0 <= v < n_vertices:
            raise InputError(f"line {lineno}: landmark {row[0]} is vertex {v}, the mesh has {n_vertices} vertices",
                             path=path, hint="vertices are 0-based indices of the rig's rest mesh")
        if row[0] in lines:
            raise InputError(f"line {lineno}: landmark {row[0]} is also on line {lines[row[0]]}", path=path,
                             hint="each tracker point once")
        lines[row[0]] = lineno
        names.append(row[0])
        vertices.append(v)
    if len(names) < 6:
        raise InputError(f"the landmark map has {len(names)} landmark(s); the head pose needs at least 6", path=path,
                         hint="map the tracker's points (e.g. OpenFace's 68) to rig vertices")
    return LandmarkMap(names, np.asarray(vertices, dtype=np.int64), str(path))


def model_landmark_map(model) -> LandmarkMap | None:
    """The landmark map a model was baked with (``[video] landmarks`` in its config), or None."""
    names = model.meta.get("landmark_names")
    if model.landmark_vertices is None or names is None:
        return None
    return LandmarkMap(list(names), np.asarray(model.landmark_vertices, dtype=np.int64),
                       f"{model.path} (baked from [video] landmarks {model.meta.get('landmark_map', '')})")
