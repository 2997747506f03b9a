"""Marker names and length units: matching a file's markers to the rig's, converting units.

Capture software names markers ``Subject:Marker`` (Vicon, Motive, many C3D files) while the
rig's ``markers.csv`` has plain names; the match is exact first, then on the name with its
subject prefix stripped (case kept: ``m001`` is not ``M001``, but it is suggested).
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass, field

import numpy as np

from facepipe.errors import InputError

#: metres per unit, for the spellings capture software writes
_METRES = {"mm": 1e-3, "cm": 1e-2, "dm": 1e-1, "m": 1.0, "in": 0.0254, "ft": 0.3048}
_SPELLINGS = {
    "mm": "mm", "millimeter": "mm", "millimeters": "mm", "millimetre": "mm", "millimetres": "mm",
    "cm": "cm", "centimeter": "cm", "centimeters": "cm", "centimetre": "cm", "centimetres": "cm",
    "dm": "dm", "decimeter": "dm", "decimeters": "dm", "decimetre": "dm", "decimetres": "dm",
    "m": "m", "meter": "m", "meters": "m", "metre": "m", "metres": "m",
    "in": "in", "inch": "in", "inches": "in", "ft": "ft", "foot": "ft", "feet": "ft",
}


def normalise_units(text, path=None, what: str = "unit") -> str | None:
    """The canonical spelling (``mm``, ``cm``, ``dm``, ``m``, ``in``, ``ft``) of a length unit.

    Parameters
    ----------
    text : str or None
        As written by capture software (``"Millimeters"``, ``"mm"``, ``"METERS"``); None or
        empty gives None.

    Raises
    ------
    InputError
        An unknown unit.

    Example
    -------
    >>> normalise_units("Millimeters")
    'mm'
    """
    if text is None:
        return None
    key = str(text).strip().strip('"').strip().lower().rstrip(".")
    if not key:
        return None
    if key not in _SPELLINGS:
        raise InputError(f"unknown length {what} {str(text)!r}", path=path,
                         hint=f"use one of {', '.join(_METRES)}")
    return _SPELLINGS[key]


def unit_factor(source: str, target: str) -> float:
    """Multiply lengths in ``source`` units by this to get ``target`` units (both canonical).

    Example
    -------
    >>> unit_factor("mm", "cm")
    0.1
    """
    return _METRES[source] / _METRES[target]


def known_unit_ratios(target: str) -> dict[str, float]:
    """{unit: factor to ``target``} for every known unit (for naming a unit mismatch)."""
    return {u: unit_factor(u, target) for u in _METRES}


@dataclass
class MarkerMatch:
    """Where each rig marker is among a file's markers.

    Attributes
    ----------
    index : (M,) int64
        File marker index of each rig marker, -1 for a rig marker absent from the file.
    report : dict
        ``absent``, ``extra``, ``duplicates``, ``renamed``, ``subject`` (JSON-serialisable).
    """

    index: np.ndarray
    report: dict = field(default_factory=dict)

    @property
    def extra(self) -> list[str]:
        return list(self.report.get("extra", []))


def split_subject(name: str) -> tuple[str, str]:
    """``"Alice:M001"`` -> ``("Alice", "M001")``; a name without ``:`` has subject ``""``."""
    subject, sep, marker = name.rpartition(":")
    return (subject.strip(), marker.strip()) if sep else ("", name.strip())


def match_markers(file_names, marker_names, path=None, *, subject: str | None = None,
                  absent: str = "error") -> MarkerMatch:
    """Find the rig's markers among a file's markers.

    Parameters
    ----------
    file_names : list[str]
        Markers in the file, in file order (``Subject:Marker`` or plain).
    marker_names : list[str]
        The rig's M markers.
    path : str or Path, optional
        The file, for messages.
    subject : str, optional
        Use only this subject's markers (and unprefixed ones) when a file holds several.
    absent : {"error", "missing"}
        A rig marker the file lacks is an error, or is reported and left missing in every
        frame (to be filled from the other markers through the rig's prior). Even with
        "missing", a file lacking more than half the rig's markers is an error (wrong
        take or wrong names).

    Returns
    -------
    MarkerMatch

    Raises
    ------
    InputError
        Absent markers (see ``absent``), markers of several subjects matching the rig
        without ``subject``, an unknown ``subject``.

    Example
    -------
    >>> match_markers(["Bob:A", "Bob:B", "X"], ["B", "A"]).index
    array([1, 0])
    """
    file_names = [str(n) for n in file_names]
    marker_names = [str(n) for n in marker_names]
    parts = [split_subject(n) for n in file_names]
    if subject is not None:
        subjects = {s for s, _ in parts if s}
        if subject not in subjects:
            raise InputError(f"subject {subject!r} is not in the take",
                             path=path, hint=f"subjects in the take: {', '.join(sorted(subjects)) or '(none)'}")
        usable = [s in ("", subject) for s, _ in parts]
    else:
        usable = [True] * len(file_names)
    exact: dict[str, list[int]] = {}
    stripped: dict[str, list[int]] = {}
    for j, (name, (subj, bare)) in enumerate(zip(file_names, parts)):
        if not usable[j]:
            continue
        exact.setdefault(name.strip(), []).append(j)
        stripped.setdefault(bare, []).append(j)
    index = np.full(len(marker_names), -1, dtype=np.int64)
    duplicates: dict[str, list[str]] = {}
    renamed: dict[str, str] = {}
    used_subjects: dict[str, str] = {}
    for m, name in enumerate(marker_names):
        cands = exact.get(name) or stripped.get(name) or []
        if not cands:
            continue
        if len(cands) > 1:
            duplicates[name] = [file_names[j] for j in cands]
        j = cands[0]
        index[m] = j
        if file_names[j] != name:
            renamed[file_names[j]] = name
        subj = parts[j][0]
        if subj:
            used_subjects.setdefault(subj, name)
    if subject is None and len(used_subjects) > 1:
        shown = ", ".join(sorted(used_subjects))
        raise InputError(f"the take holds markers of several subjects that match the rig: {shown}",
                         path=path, hint="choose one with --subject NAME")
    missing = [n for n, j in zip(marker_names, index) if j < 0]
    if missing and (absent == "error" or len(missing) * 2 > len(marker_names)):
        shown = ", ".join(missing[:12]) + (f" and {len(missing) - 12} more" if len(missing) > 12 else "")
        rig = set(marker_names)
        pool = [n for n, (_, b) in zip(file_names, parts) if n not in rig and b not in rig]
        guesses = []
        for n in missing[:5]:
            close = [c for c in pool if split_subject(c)[1].lower() == n.lower()] or difflib.get_close_matches(
                n, pool, n=1)
            if close:
                guesses.append(f"{close[0]} -> {n}")
        hint = "rename the markers in the take to the rig's marker names, or mark the marker `ignore` in markers.csv"
        if guesses:
            hint += f" (perhaps {', '.join(guesses)})"
        raise InputError(f"{len(missing)} rig marker(s) absent from the take: {shown}", path=path, hint=hint)
    chosen = {int(j) for j in index if j >= 0}
    dup_cols = {file_names[j] for name in duplicates for j in (exact.get(name) or stripped.get(name))}
    extra = [n for j, n in enumerate(file_names) if j not in chosen and n not in dup_cols]
    report = {
        "absent": missing,
        "extra": extra,
        "duplicates": duplicates,
        "renamed": renamed,
        "subject": subject if subject is not None else (next(iter(used_subjects)) if used_subjects else None),
    }
    return MarkerMatch(index, report)


def find_markers(file_markers: list[str], marker_names: list[str], path, match=None) -> MarkerMatch:
    """The rig's markers among a file's: ``match(file_markers)`` if given, else :func:`match_markers`."""
    return (match or (lambda names: match_markers(names, marker_names, path)))(file_markers)
