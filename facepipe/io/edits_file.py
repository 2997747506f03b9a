"""EDITS.json: handle edits over a take, by handle name (see :mod:`facepipe.core.edits`).

::

    {"format": "facepipe-edits", "version": 1, "units": "cm",
     "edits": [{"frame": 12, "ease_in": 8, "ease_out": 8, "offsets": {"BROW_L": [0.0, 0.3, 0.0]}}]}

Handles are named as in the model (``marker_names``), so a file outlives a rebake of the rig.
Anything malformed is an :class:`InputError` naming the file, the edit and what to write.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from facepipe.core.edits import HandleEdit
from facepipe.errors import InputError
from facepipe.io.atomic import atomic_open

FORMAT = "facepipe-edits"
VERSION = 1


def _number(value, what: str, path, minimum: float | None = None) -> float:
    # a bool is an int to Python but never a number of frames or centimetres
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{what} is {value!r}; write a finite number", path=path)
    if minimum is not None and value < minimum:
        raise InputError(f"{what} is {value}; it must be at least {minimum}", path=path)
    return float(value)


def edits_from_data(data, handle_names: list[str], path="(edits)", units: str | None = None) -> list[HandleEdit]:
    """Validated edits from parsed JSON, handle names resolved to indices; ``units``, the rig's, must
    match the file's where both are given (offsets are never rescaled silently)."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputError(f"not an edits file: expected a JSON object with \"format\": \"{FORMAT}\"", path=path)
    if data.get("version") != VERSION:
        raise InputError(f"edits format version {data.get('version')!r} is not supported (this facepipe reads "
                         f"version {VERSION})", path=path)
    if units and data.get("units") and data["units"] != units:
        raise InputError(f"the offsets are in {data['units']!r} but the model is in {units!r}",
                         path=path, hint="edit this model in `facepipe edit` or convert the offsets")
    items = data.get("edits")
    if not isinstance(items, list):
        raise InputError("\"edits\" must be a list of edits", path=path)
    index = {name: i for i, name in enumerate(handle_names)}
    edits = []
    for k, item in enumerate(items):
        where = f"edit {k}"
        if not isinstance(item, dict):
            raise InputError(f"{where} is {item!r}; write an object with frame, ease_in, ease_out, offsets",
                             path=path)
        unknown = set(item) - {"frame", "ease_in", "ease_out", "offsets"}
        if unknown:
            raise InputError(f"{where} has unknown keys {sorted(unknown)}; the keys are frame, ease_in, ease_out, "
                             f"offsets", path=path)
        if "frame" not in item:
            raise InputError(f"{where} has no \"frame\" (its key frame number)", path=path)
        offsets = item.get("offsets")
        if not isinstance(offsets, dict) or not offsets:
            raise InputError(f"{where}: \"offsets\" must map handle names to [dx, dy, dz]", path=path)
        resolved = {}
        for name, offset in offsets.items():
            if name not in index:
                raise InputError(f"{where} moves handle {name!r}, which the model does not have",
                                 path=path, hint=f"handles are {', '.join(handle_names[:8])}…")
            if not isinstance(offset, list) or len(offset) != 3:
                raise InputError(f"{where}: the offset of {name!r} is {offset!r}; write [dx, dy, dz]", path=path)
            resolved[index[name]] = tuple(_number(v, f"{where}: offset of {name!r}", path) for v in offset)
        edits.append(HandleEdit(frame=_number(item["frame"], f"{where}: frame", path), offsets=resolved,
                                ease_in=_number(item.get("ease_in", 0), f"{where}: ease_in", path, 0.0),
                                ease_out=_number(item.get("ease_out", 0), f"{where}: ease_out", path, 0.0)))
    return edits


def edits_to_data(edits: list[HandleEdit], handle_names: list[str], units: str | None = None) -> dict:
    """The JSON form of edits (inverse of :func:`edits_from_data`)."""
    return {"format": FORMAT, "version": VERSION, "units": units,
            "edits": [{"frame": e.frame, "ease_in": e.ease_in, "ease_out": e.ease_out,
                       "offsets": {handle_names[h]: [float(v) for v in o] for h, o in e.offsets.items()}}
                      for e in edits]}


def read_edits(path, handle_names: list[str], units: str | None = None) -> list[HandleEdit]:
    """Edits from an EDITS.json file; InputError (exit 2) for anything malformed."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise InputError(f"cannot read the edits: {exc.strerror}", path=path) from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}", path=path) from None
    return edits_from_data(data, handle_names, path, units)


def write_edits(path, edits: list[HandleEdit], handle_names: list[str], units: str | None = None) -> None:
    """Write EDITS.json atomically (a temporary name renamed into place)."""
    with atomic_open(path) as fh:
        json.dump(edits_to_data(edits, handle_names, units), fh, indent=2)
