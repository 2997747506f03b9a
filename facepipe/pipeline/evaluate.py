"""Error of replayed positions against ground truth."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facepipe.core.mesh import welded_frames
from facepipe.errors import InputError
from facepipe.io.npz_file import read_truth, read_truth_extras


def parse_vertex_range(text: str | None, n_vertices: int) -> slice:
    """``"A:B"`` (either side optional) → slice over vertices; None or "" → all.

    Example
    -------
    >>> parse_vertex_range("0:9409", 11248)
    slice(0, 9409, None)
    """
    if not text:
        return slice(0, n_vertices)
    try:
        a, b = (text.split(":") + [""])[:2]
        start = int(a) if a else 0
        stop = int(b) if b else n_vertices
    except ValueError:
        raise InputError(f"vertex range {text!r} is not of the form A:B") from None
    if not 0 <= start < stop <= n_vertices:
        raise InputError(f"vertex range {text!r} is outside [0, {n_vertices})")
    return slice(start, stop)


def frame_errors(positions: np.ndarray, truth: np.ndarray, vertices: slice | np.ndarray = slice(None),
                 chunk: int = 64, pose=None, truth_pose=None) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame RMS and max vertex distance over a vertex subset (a slice or indices, which may
    repeat: a welded mesh's vertices seen in the mesh file's numbering), chunked (memmaps welcome).

    Parameters
    ----------
    positions, truth : (T, V, 3) in the same space and units; or each in its own space, with
        ``pose``, ``truth_pose`` = (rotation (T, 3, 3), translation (T, 3)) of the head in it
        (world = R · head + t): then both are compared in head space.

    Returns
    -------
    rms : (T,) float64; max : (T,) float64 (length units).
    """
    T = positions.shape[0]
    rms = np.empty(T)
    mx = np.empty(T)
    for s in range(0, T, chunk):
        rows = slice(s, s + chunk)
        a = np.asarray(positions[rows, vertices], dtype=np.float64)
        b = np.asarray(truth[rows, vertices], dtype=np.float64)
        if pose is not None:
            a = to_head_space(a, pose[0][rows], pose[1][rows])
        if truth_pose is not None:
            b = to_head_space(b, truth_pose[0][rows], truth_pose[1][rows])
        d = a - b
        dist2 = np.einsum("tvc,tvc->tv", d, d)
        rms[rows] = np.sqrt(dist2.mean(axis=1))
        mx[rows] = np.sqrt(dist2.max(axis=1))
    return rms, mx


def summarize(rms: np.ndarray, mx: np.ndarray) -> dict:
    """Mean / median / 95th percentile / max of per-frame errors."""
    return {
        "frames": int(len(rms)),
        "rms_mean": float(rms.mean()),
        "rms_median": float(np.median(rms)),
        "rms_p95": float(np.percentile(rms, 95)),
        "rms_max": float(rms.max()),
        "max_error": float(mx.max()),
    }


def match_frames(replay_frames: np.ndarray, truth_frames: np.ndarray, path: str = "", replay_times=None,
                 truth_times=None, report: dict | None = None) -> np.ndarray:
    """Index into the truth for each replayed frame: by frame number; or, where the truth lacks some
    of the replay's numbers but both have times and every replayed frame's time is within a
    quarter frame of one of the truth's (trackers number frames from 1, many files from 0), by
    time. ``report["frames_matched_by"]`` says which ("number" or "time"). InputError naming a
    frame the truth lacks otherwise."""
    lookup = {int(f): i for i, f in enumerate(truth_frames)}
    missing = [int(f) for f in replay_frames if int(f) not in lookup]
    report = {} if report is None else report
    if not missing:
        report["frames_matched_by"] = "number"
        return np.array([lookup[int(f)] for f in replay_frames], dtype=np.int64)
    by_time = _match_times(replay_times, truth_times)
    if by_time is not None:
        report["frames_matched_by"] = "time"
        return by_time
    hint = ("the truth's frame numbers must be the take's (or both must have times: 'time' in the truth)"
            if truth_times is None else "the take's frames are not the truth's, by number or by time")
    raise InputError(f"the truth has no frame {missing[0]} ({len(missing)} replayed frames missing)", path=path,
                     hint=hint)


def _match_times(replay_times, truth_times) -> np.ndarray | None:
    if replay_times is None or truth_times is None or len(truth_times) < 2:
        return None
    a = np.asarray(replay_times, dtype=np.float64)
    b = np.asarray(truth_times, dtype=np.float64)
    order = np.argsort(b)
    sorted_b = b[order]
    step = float(np.median(np.diff(sorted_b)))
    if not (step > 0 and np.isfinite(a).all() and np.isfinite(b).all()):
        return None
    after = np.clip(np.searchsorted(sorted_b, a), 1, len(b) - 1)
    nearest = np.where(np.abs(sorted_b[after - 1] - a) <= np.abs(sorted_b[after] - a), after - 1, after)
    index = order[nearest]
    return index.astype(np.int64) if (np.abs(b[index] - a) <= 0.25 * step).all() else None


def load_truth(path, frame_numbers: np.ndarray, n_vertices: int, frame_times=None,
               report: dict | None = None, file_order=None) -> tuple[np.ndarray, np.ndarray]:
    """The truth of a replay: its positions and, per replayed frame, the truth's row
    (:func:`truth_rows`)."""
    positions, index, _ = truth_rows(path, frame_numbers, n_vertices, frame_times, report, file_order)
    return positions, index


def truth_rows(path, frame_numbers: np.ndarray, n_vertices: int, frame_times=None,
               report: dict | None = None, file_order=None) -> tuple[np.ndarray, np.ndarray, dict]:
    """The truth of a replay: its positions, per replayed frame the truth's row, and what else the
    file says of its frames (:func:`facepipe.io.npz_file.read_truth_extras`), each read once.

    Parameters
    ----------
    path : .npz with ``positions`` (F, V, 3) in the take's space and optionally ``frame`` (F,),
        ``time`` (F,) and the head's ``rotation``/``translation``.
    frame_numbers, frame_times : (T,) the replay's frame numbers and times (see :func:`match_frames`).
    n_vertices : V of the model.
    file_order : a callable giving the model's ``weld_index`` or None (:meth:`ReplayDir.weld_index
        <facepipe.io.replay_folder.ReplayDir.weld_index>`), called only for a truth of another
        vertex count: a truth in the mesh file's order of a rig welded along seams is read on the
        welded vertices.

    Returns
    -------
    positions : (F, V, 3); index : (T,) int64 rows of ``positions``; extras : dict.

    Raises
    ------
    InputError
        Unreadable file, no ``positions``, other vertex count, or replayed frames it lacks.
    """
    positions, frames = read_truth(path)
    if file_order is not None and positions.ndim == 3 and positions.shape[1] != n_vertices:
        weld_index = file_order()
        if weld_index is not None and positions.shape[1] == len(weld_index):
            positions = welded_frames(positions, weld_index)
    if positions.ndim != 3 or positions.shape[1:] != (n_vertices, 3):
        raise InputError(f"truth positions have shape {positions.shape}, the replay ({len(frame_numbers)}, "
                         f"{n_vertices}, 3)", path=path, hint="give the truth of the replayed take")
    extras = read_truth_extras(path, len(positions))
    index = match_frames(np.asarray(frame_numbers), frames, str(path), frame_times,
                         extras.get("time") if frame_times is not None else None, report)
    return positions, index, extras


@dataclass
class ReplayTruth:
    """The truth of a replay's frames: the truth file's ``positions`` (F, V, 3), the row ``index``
    (T,) of each replayed frame, and the truth's own head pose per replayed frame where the file
    has one (``rotation`` (T, 3, 3), ``translation`` (T, 3); else None)."""

    positions: np.ndarray
    index: np.ndarray
    rotation: np.ndarray | None = None
    translation: np.ndarray | None = None

    def head(self, i: int, replay_head) -> np.ndarray:
        """Replayed frame ``i``'s truth in head space (V, 3): by the truth's own pose where it has
        one, else by ``replay_head(x, i)`` (the replay's pose: the truth is in the take's space)."""
        x = self.positions[self.index[i]]
        if self.rotation is None:
            return replay_head(x, i)
        return to_head_space(x, self.rotation[i], self.translation[i])


def replay_truth(path, replay, n_vertices: int) -> ReplayTruth:
    """:func:`load_truth` for a replay folder (its frame numbers, else its times), with the truth's head pose."""
    positions, index, extras = truth_rows(path, replay.frame_numbers, n_vertices, replay.times,
                                          file_order=replay.weld_index)
    if "rotation" in extras and "translation" in extras:
        return ReplayTruth(positions, index, extras["rotation"][index], extras["translation"][index])
    return ReplayTruth(positions, index)


def to_head_space(x, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Take-space positions (V, 3) of a frame in head space (world = R head + t): Rᵀ (x − t); or
    of frames, (T, V, 3) with rotations (T, 3, 3) and translations (T, 3)."""
    return (np.asarray(x, dtype=np.float64) - np.asarray(translation)[..., None, :]) @ rotation
