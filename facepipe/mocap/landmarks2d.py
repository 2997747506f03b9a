"""2D landmark takes (monocular video tracked by OpenFace, MediaPipe, dlib-style trackers).

Two formats, registered with the mocap registry so that a take is recognised by its content:

- **OpenFace 2.0** ``FeatureExtraction`` CSV: ``frame, face_id, timestamp, confidence, success,
  x_0 … x_67, y_0 … y_67`` (columns separated by ``", "``; other columns ignored). A row with
  ``success`` 0 or a confidence below ``min_confidence`` is a missing frame (OpenFace writes
  zeros there); a blank or ``nan`` coordinate a missing sample. Point ``N`` is named ``N``.
- **plain 2D CSV**: ``frame,time,NAME_u,NAME_v,…`` in pixels of the footage, a blank (or
  ``NaN``) field a missing sample.

Pixels are those of the footage as filmed (distorted); the camera's undistortion comes later
(:func:`facepipe.core.camera.undistort_points`). A 3D replay given such a take stops with the
advice to pass ``--camera`` and ``--landmarks``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from facepipe.errors import InputError
from facepipe.mocap.registry import Format, detect_format, register
from facepipe.mocap.take import estimate_fps

__all__ = ["LandmarkTake", "TWO_D_FORMATS", "check_in_image", "is_landmark_take", "read_landmark_take",
           "write_uv_csv"]

#: Formats whose takes are 2D landmark tracks.
TWO_D_FORMATS = ("openface-csv", "uv-csv")
#: Fewer visible landmarks than this in a frame: no head pose there, the frame counts as missing.
MIN_LANDMARKS = 6


@dataclass
class LandmarkTake:
    """A 2D take: tracked points per frame, in pixels of the footage, in the landmark map's order.

    Attributes
    ----------
    frames : (T,) int64, strictly increasing; times : (T,) float64 seconds, strictly increasing.
    points : (T, L, 2) float64 pixels, NaN where missing.
    names : the L landmark names (the map's order).
    failed : (T,) bool, frames the tracker reported as failed (or below the confidence floor).
    confidence : (T,) float64 or None (OpenFace's per-frame confidence).
    lines : (T,) int64 source lines (1-based) for messages.
    extra : names of tracked points the map does not use (ignored).
    """

    frames: np.ndarray
    times: np.ndarray
    points: np.ndarray
    names: list
    failed: np.ndarray
    path: str = ""
    format: str = ""
    confidence: np.ndarray | None = None
    lines: np.ndarray | None = None
    extra: list = field(default_factory=list)
    fps: float = float("nan")

    @property
    def n_frames(self) -> int:
        return int(self.points.shape[0])

    @property
    def visible(self) -> np.ndarray:
        """(T, L) bool: samples present."""
        return np.isfinite(self.points).all(axis=-1)

    def where(self, row: int) -> str:
        text = f"frame {int(self.frames[row])}"
        if self.lines is not None:
            text += f" (line {int(self.lines[row])})"
        return text

    def select(self, rows) -> "LandmarkTake":
        return LandmarkTake(self.frames[rows], self.times[rows], self.points[rows], self.names, self.failed[rows],
                            self.path, self.format, None if self.confidence is None else self.confidence[rows],
                            None if self.lines is None else self.lines[rows], self.extra, self.fps)


# ----------------------------------------------------------------------------- parsing


def _split_rows(path: Path):
    """(header fields, [(line number, fields)]) of a comma-separated text file."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the take ({exc})", path=path) from None
    lines = text.splitlines()
    rows = [(i, line) for i, line in enumerate(lines, start=1) if line.strip()]
    if not rows:
        raise InputError("the take is empty", path=path, hint="export the tracker's output again")
    header = [c.strip().strip('"') for c in rows[0][1].split(",")]
    body = [(i, [c.strip() for c in line.split(",")]) for i, line in rows[1:]]
    return header, body


def _numbers(path: Path, header: list, body: list, columns: list[int], what: list[str]) -> np.ndarray:
    """(rows, len(columns)) float64 of the given columns; blank or NaN fields are NaN.

    Raises InputError naming line and column for a short row or a field that is not a number."""
    n = len(header)
    out = np.full((len(body), len(columns)), np.nan)
    for r, (lineno, fields) in enumerate(body):
        if len(fields) < n:
            raise InputError(f"line {lineno}: {len(fields)} fields, the header has {n}", path=path,
                             hint="the row is cut short: export the take again")
        for c, col in enumerate(columns):
            text = fields[col]
            if not text:
                continue
            try:
                out[r, c] = float(text)
            except ValueError:
                raise InputError(f"line {lineno}: {what[c]} is {text!r}, not a number", path=path,
                                 hint="leave a missing sample empty") from None
    return out


def _frames_and_times(path: Path, body, frame_col: np.ndarray, times: np.ndarray):
    lines = np.array([lineno for lineno, _ in body], dtype=np.int64)
    bad = np.flatnonzero(~np.isfinite(frame_col) | (frame_col != np.round(frame_col)))
    if bad.size:
        raise InputError(f"line {lines[bad[0]]}: the frame number is missing or not an integer", path=path,
                         hint="every row starts with its frame number")
    bad = np.flatnonzero(~np.isfinite(times))
    if bad.size:
        raise InputError(f"line {lines[bad[0]]}: the time is missing or not finite", path=path,
                         hint="every row needs its time in seconds")
    frames = frame_col.astype(np.int64)
    bad = np.flatnonzero(np.diff(frames) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        same = frames[i] == frames[i - 1]
        raise InputError(f"frame {frames[i]} (line {lines[i]}): frame number {'repeats' if same else 'goes back from'} "
                         f"frame {frames[i - 1]} (line {lines[i - 1]})", path=path,
                         hint="rows must be in increasing frame order without duplicates: sort the file or remove "
                              "the repeated row")
    bad = np.flatnonzero(np.diff(times) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise InputError(f"frame {frames[i]} (line {lines[i]}): time {times[i]:.6g} s is not after the previous "
                         f"row's {times[i - 1]:.6g} s", path=path, hint="times must increase with the frame number")
    return frames, times.astype(np.float64), lines


def _select_landmarks(path: Path, available: list, names: list, count_note: str) -> list[int]:
    index = {n: i for i, n in enumerate(available)}
    absent = [n for n in names if n not in index]
    if absent:
        raise InputError(
            f"the landmark map names {len(names)} landmarks, the take has {len(available)} ({count_note}); "
            f"not in the take: {', '.join(absent[:10])}" + (" ..." if len(absent) > 10 else ""),
            path=path, hint="use a landmark map for this tracker's points (its names are the take's point names), "
                            "or drop those rows from the map")
    return [index[n] for n in names]


def read_openface(path, names: list, min_confidence: float = 0.5) -> LandmarkTake:
    """Read an OpenFace 2.0 FeatureExtraction CSV, keeping the landmarks ``names`` (in that order)."""
    path = Path(path)
    header, body = _split_rows(path)
    col = {h: i for i, h in enumerate(header)}
    for key in ("frame", "timestamp", "success"):
        if key not in col:
            raise InputError(f"not an OpenFace CSV: no {key!r} column", path=path,
                             hint="give FeatureExtraction's CSV (frame, face_id, timestamp, confidence, success, x_0 …)")
    if not body:
        raise InputError("the take has no frames (only a header)", path=path, hint="export the take again")
    points = sorted(int(m.group(1)) for h in header if (m := re.fullmatch(r"x_(\d+)", h)) and f"y_{m.group(1)}" in col)
    available = [str(p) for p in points]
    use = _select_landmarks(path, available, names, f"x_0 … x_{points[-1]}" if points else "no x_N/y_N columns")
    xs = [col[f"x_{available[u]}"] for u in use]
    ys = [col[f"y_{available[u]}"] for u in use]
    conf_col = col.get("confidence")
    head = [col["frame"], col["timestamp"], col["success"]] + ([conf_col] if conf_col is not None else [])
    what = ["frame", "timestamp", "success"] + (["confidence"] if conf_col is not None else [])
    data = _numbers(path, header, body, head + xs + ys, what + [f"x_{names[i]}" for i in range(len(use))]
                    + [f"y_{names[i]}" for i in range(len(use))])
    frames, times, lines = _frames_and_times(path, body, data[:, 0], data[:, 1])
    L = len(use)
    off = len(head)
    pts = np.stack([data[:, off:off + L], data[:, off + L:off + 2 * L]], axis=-1)
    _check_finite(path, pts, frames, lines, names)
    success = np.nan_to_num(data[:, 2]) > 0.5
    confidence = data[:, 3] if conf_col is not None else None
    failed = ~success
    if confidence is not None:
        failed |= ~(np.nan_to_num(confidence) >= min_confidence)
    pts[failed] = np.nan
    pts[np.isnan(pts).any(axis=-1)] = np.nan  # a sample with one coordinate (a NaN field) is missing
    take = LandmarkTake(frames, times, pts, list(names), failed, str(path), "openface-csv", confidence, lines,
                        [n for n in available if n not in set(names)])
    return _finish(take)


def read_uv_csv(path, names: list) -> LandmarkTake:
    """Read a plain 2D CSV ``frame,time,NAME_u,NAME_v,…`` (pixels), keeping the landmarks ``names``."""
    path = Path(path)
    header, body = _split_rows(path)
    if header[:2] != ["frame", "time"]:
        raise InputError("a 2D CSV starts with the columns frame,time", path=path,
                         hint="header: frame,time,NAME_u,NAME_v,… (pixels)")
    if not body:
        raise InputError("the take has no frames (only a header)", path=path, hint="export the take again")
    col = {h: i for i, h in enumerate(header)}
    available = [h[:-2] for h in header[2:] if h.endswith("_u") and f"{h[:-2]}_v" in col]
    use = _select_landmarks(path, available, names, "columns NAME_u, NAME_v")
    cols = [0, 1] + [col[f"{available[u]}_u"] for u in use] + [col[f"{available[u]}_v"] for u in use]
    what = ["frame", "time"] + [f"{n}_u" for n in names] + [f"{n}_v" for n in names]
    data = _numbers(path, header, body, cols, what)
    frames, times, lines = _frames_and_times(path, body, data[:, 0], data[:, 1])
    L = len(use)
    pts = np.stack([data[:, 2:2 + L], data[:, 2 + L:2 + 2 * L]], axis=-1)
    _check_finite(path, pts, frames, lines, names)
    half = np.isnan(pts).any(axis=-1)
    pts[half] = np.nan
    failed = half.all(axis=1)
    take = LandmarkTake(frames, times, pts, list(names), failed, str(path), "uv-csv", None, lines,
                        [n for n in available if n not in set(names)])
    return _finish(take)


def _check_finite(path, pts, frames, lines, names):
    inf = np.isinf(pts)
    if inf.any():
        t, m, a = (int(v) for v in np.argwhere(inf)[0])
        raise InputError(f"frame {frames[t]} (line {lines[t]}): landmark {names[m]} "
                         f"({'xy'[a]}) is infinite", path=path, hint="leave the field empty for a missing sample")


def _finish(take: LandmarkTake) -> LandmarkTake:
    return replace(take, fps=estimate_fps(take.times))


def write_uv_csv(path, frames, times, points, names, decimals: int = 3) -> None:
    """Write a plain 2D CSV (atomically); NaN samples are left blank."""
    from facepipe.io.atomic import atomic_open

    pts = np.asarray(points, dtype=np.float64)
    header = ",".join(["frame", "time"] + [f"{n}_{a}" for n in names for a in "uv"])
    row = ",".join(["%d", "%.6f"] + [f"%.{decimals}f"] * (2 * len(names)))
    with atomic_open(path, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(header + "\n")
        for f, t, p in zip(np.asarray(frames).tolist(), np.asarray(times).tolist(), pts.reshape(len(pts), -1).tolist()):
            fh.write((row % (f, t, *p)).replace("nan", "") + "\n")


# ----------------------------------------------------------------------------- the whole read


def is_landmark_take(path) -> bool:
    """Whether a take file holds 2D landmark tracks (by its content)."""
    path = Path(path)
    if not path.is_file():
        return False
    try:
        return detect_format(path).name in TWO_D_FORMATS
    except InputError:
        return False


def read_landmark_take(path, names: list, frames: slice | None = None, min_confidence: float = 0.5) -> LandmarkTake:
    """Read a 2D landmark take in either format, keeping the landmark map's points in its order.

    Parameters
    ----------
    names : the landmark map's names.
    frames : rows of the take to keep (the whole file is still checked).
    min_confidence : OpenFace rows below this confidence are missing frames.

    Raises
    ------
    InputError
        Not a 2D take, malformed rows (line and column named), frames or times out of order,
        infinite values, map landmarks the take lacks, no frame with enough landmarks.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("take not found", path=path, hint="check the path of the take")
    fmt = detect_format(path)
    if fmt.name == "openface-csv":
        take = read_openface(path, names, min_confidence)
    elif fmt.name == "uv-csv":
        take = read_uv_csv(path, names)
    else:
        raise InputError(f"a {fmt.name} take holds 3D markers, not 2D landmarks", path=path,
                         hint="replay it without --camera")
    if frames is not None:
        total = take.n_frames
        take = take.select(frames)
        if take.n_frames == 0:
            raise InputError(f"the frame range selects none of the {total} frames", path=path,
                             hint=f"choose rows within 0:{total} with --frames A:B")
    enough = take.visible.sum(axis=1) >= min(MIN_LANDMARKS, len(names))
    if not enough.any():
        failed = int(take.failed.sum())
        raise InputError(f"no frame has a tracked face: {failed} of {take.n_frames} frames failed"
                         + ("" if failed == take.n_frames else f", the others have fewer than {MIN_LANDMARKS} "
                                                              "landmarks"), path=path,
                         hint="track the video again (is the face visible?), or lower --min-confidence")
    return take


def check_in_image(take: LandmarkTake, width: int, height: int, camera_path: str = "") -> None:
    """Landmarks must lie in the camera's stated image (a margin of 5 % allows trackers' extrapolation).

    Raises
    ------
    InputError
        Naming the frame, line and landmark, and both sizes: a calibration of another
        resolution than the footage's is the usual cause.
    """
    pts = take.points
    margin_u, margin_v = 0.05 * width, 0.05 * height
    out = (pts[..., 0] < -margin_u) | (pts[..., 0] > width - 1 + margin_u) | \
          (pts[..., 1] < -margin_v) | (pts[..., 1] > height - 1 + margin_v)
    if out.any():
        t, m = (int(v) for v in np.argwhere(out)[0])
        u, v = pts[t, m]
        extent = np.nanmax(pts.reshape(-1, 2), axis=0)
        raise InputError(
            f"{take.where(t)}: landmark {take.names[m]} is at ({u:.1f}, {v:.1f}) px, outside the camera's "
            f"{width} × {height} image ({int(out.sum())} sample(s) outside; the landmarks reach "
            f"{extent[0]:.0f} × {extent[1]:.0f} px)", path=take.path,
            hint=f"the calibration {camera_path} is for another resolution than the footage: calibrate at the "
                 "footage's resolution, or scale camera_matrix and the image size by the resize factor")


# ----------------------------------------------------------------------------- registry


def _not_3d(path, marker_names=None, match=None):
    raise InputError("this take holds 2D landmark tracks, not 3D markers", path=path,
                     hint="replay it with --camera CALIBRATION and --landmarks MAP (see the README's Video takes)")


def _no_writer(path, take, units=None, **options):
    raise ValueError("2D takes are written with facepipe.mocap.landmarks2d.write_uv_csv")


def _sniff_openface(head: bytes) -> bool:
    first = head.split(b"\n", 1)[0].lower().replace(b" ", b"").replace(b'"', b"")
    return first.startswith(b"frame,") and b",success" in first and b",x_0" in first


def _sniff_uv(head: bytes) -> bool:
    first = head.split(b"\n", 1)[0].strip().lower().replace(b'"', b"").split(b",")
    coords = [c.strip() for c in first[2:]]
    return [c.strip() for c in first[:2]] == [b"frame", b"time"] and bool(coords) and \
        all(c.endswith(b"_u") or c.endswith(b"_v") for c in coords)


# after the 3D formats (a file no format recognises is still read, and refused, as a facepipe CSV);
# the facepipe CSV's sniff leaves frame,time,NAME_u,NAME_v,… headers to the u/v format
register(Format("openface-csv", (".csv",), _not_3d, _no_writer, _sniff_openface))
register(Format("uv-csv", (".csv",), _not_3d, _no_writer, _sniff_uv))
