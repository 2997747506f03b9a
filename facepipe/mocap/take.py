"""The in-memory take: marker positions per frame, and the checks every format needs.

Readers (one module per file format, see :mod:`facepipe.mocap.registry`) build a
:class:`Take`; :func:`check_order` and :func:`check_values` apply the rules common to all
formats (frames strictly increasing, finite values, something visible in a frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from facepipe.errors import InputError
from facepipe.io.atomic import atomic_open

AXES = ("x", "y", "z")


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
        Marker positions in ``units``; a missing sample is NaN in all three coordinates
        (a rig marker absent from the file is NaN in every frame).
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
    units : str or None
        Length unit of ``positions`` (``"mm"``, ``"cm"``, ``"m"``, ...); None when the file
        does not say (a facepipe CSV): then the rig's units are assumed.
    source_units : str or None
        The unit the file declared (or ``take_units`` given to the reader) before any
        conversion.
    markers : dict
        What name matching did, JSON-serialisable: ``absent`` (rig markers not in the file),
        ``extra``, ``duplicates`` ({rig marker: [file columns]}, the first one used),
        ``renamed`` ({file name: rig marker}, subject prefixes stripped), ``subject``.
    format : str
        The reader's format name (``"facepipe-csv"``, ``"c3d"``, ...).
    """

    frames: np.ndarray
    times: np.ndarray
    positions: np.ndarray
    marker_names: list[str]
    path: str = ""
    extra_markers: list[str] = field(default_factory=list)
    fps: float = float("nan")
    lines: np.ndarray | None = None
    units: str | None = None
    source_units: str | None = None
    markers: dict = field(default_factory=dict)
    format: str = ""

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

    def select(self, rows) -> "Take":
        """The take restricted to ``rows`` (a slice or an index array of frame rows)."""
        return Take(
            frames=self.frames[rows],
            times=self.times[rows],
            positions=self.positions[rows],
            marker_names=self.marker_names,
            path=self.path,
            extra_markers=self.extra_markers,
            fps=self.fps,
            lines=None if self.lines is None else self.lines[rows],
            units=self.units,
            source_units=self.source_units,
            markers=self.markers,
            format=self.format,
        )


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


def check_order(take: Take) -> None:
    """Frames and times of the whole file: present, integral, strictly increasing.

    Raises
    ------
    InputError
        Naming the first frame (and line) out of order, repeated, or without a time.
    """
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


def check_values(take: Take, allow_empty_frames: bool = False) -> None:
    """Marker values of the selected frames: finite, and (unless allowed) a marker visible in every frame.

    A sample with only some coordinates missing cannot be used: it is made fully missing
    (in place).

    Parameters
    ----------
    take : Take
    allow_empty_frames : bool
        Accept frames where every marker is missing (the replay pipeline interpolates
        them); by default they are an error.

    Raises
    ------
    InputError
        An infinite value; a frame without any visible marker (unless allowed); every frame
        empty.
    """
    path = take.path
    pos = take.positions
    inf = np.isinf(pos)
    if inf.any():
        t, m, a = (int(v) for v in np.argwhere(inf)[0])
        raise InputError(
            f"{take.where(t)}: marker {take.marker_names[m]} ({take.marker_names[m]}_{AXES[a]}) is infinite",
            path=path,
            hint="leave the field empty (or write NaN) for a missing sample",
        )
    part = np.isnan(pos).any(axis=2)
    pos[part] = np.nan
    none = np.flatnonzero(part.all(axis=1))
    if none.size == take.n_frames or (none.size and not allow_empty_frames):
        more = f" (and {none.size - 1} other frame(s))" if none.size > 1 else ""
        raise InputError(
            f"{take.where(int(none[0]))}: every marker is missing{more}",
            path=path,
            hint="remove the frame from the take or skip it with --frames A:B"
            if none.size < take.n_frames
            else "no marker of the rig is visible anywhere in the take: check its marker names",
        )


def estimate_fps(times: np.ndarray) -> float:
    """1 / median frame interval of (T,) seconds; NaN below two frames."""
    if times.size < 2:
        return float("nan")
    return float(1.0 / np.median(np.diff(times)))


def write_marker_rows(path, header: str, take: "Take", positions: np.ndarray, row_format: str,
                      with_times: bool = True, footer: str = "") -> None:
    """Write a text take atomically: ``header``, then one formatted row per frame, then ``footer``.

    Parameters
    ----------
    header : text before the rows (its own newlines included).
    positions : (T, M, 3) in the file's units; NaN (a missing sample) becomes an empty field.
    row_format : printf format of a row: frame, [time,] then 3·M coordinates.
    with_times : whether rows carry the take's time after the frame number.
    """

    pos = np.asarray(positions, dtype=np.float64)
    T, M = pos.shape[:2]
    frames = np.asarray(take.frames).tolist()
    times = np.asarray(take.times).tolist()
    with atomic_open(path, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(header)
        for a in range(0, T, 4096):  # blocks: bounded memory for long takes
            b = min(T, a + 4096)
            flat = pos[a:b].reshape(b - a, 3 * M).tolist()
            lead = zip(frames[a:b], times[a:b]) if with_times else ((f,) for f in frames[a:b])
            # only numbers are formatted, so "nan" can only be a missing sample
            text = "\n".join(row_format % (*head, *p) for head, p in zip(lead, flat))
            fh.write(text.replace("nan", "") + "\n")
        fh.write(footer)

