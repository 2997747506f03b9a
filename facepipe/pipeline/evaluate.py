"""Error of replayed positions against ground truth."""

from __future__ import annotations

import numpy as np

from facepipe.errors import InputError
from facepipe.io.npz_file import read_truth


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


def frame_errors(positions: np.ndarray, truth: np.ndarray, vertices: slice = slice(None),
                 chunk: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame RMS and max vertex distance over a vertex subset, chunked (memmaps welcome).

    Parameters
    ----------
    positions, truth : (T, V, 3) in the same space and units.

    Returns
    -------
    rms : (T,) float64; max : (T,) float64 (length units).
    """
    T = positions.shape[0]
    rms = np.empty(T)
    mx = np.empty(T)
    for s in range(0, T, chunk):
        d = np.asarray(positions[s:s + chunk, vertices], dtype=np.float64) - np.asarray(
            truth[s:s + chunk, vertices], dtype=np.float64)
        dist2 = np.einsum("tvc,tvc->tv", d, d)
        rms[s:s + chunk] = np.sqrt(dist2.mean(axis=1))
        mx[s:s + chunk] = np.sqrt(dist2.max(axis=1))
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


def match_frames(replay_frames: np.ndarray, truth_frames: np.ndarray, path: str = "") -> np.ndarray:
    """Index into the truth for each replayed frame number; InputError naming a frame it lacks."""
    lookup = {int(f): i for i, f in enumerate(truth_frames)}
    missing = [int(f) for f in replay_frames if int(f) not in lookup]
    if missing:
        raise InputError(f"the truth has no frame {missing[0]} ({len(missing)} replayed frames missing)", path=path)
    return np.array([lookup[int(f)] for f in replay_frames], dtype=np.int64)


def load_truth(path, frame_numbers: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """The truth of a replay: its positions and, per replayed frame, the truth's row.

    Parameters
    ----------
    path : .npz with ``positions`` (F, V, 3) in the take's space and optionally ``frame`` (F,).
    frame_numbers : (T,) the replay's frame numbers.
    n_vertices : V of the model.

    Returns
    -------
    positions : (F, V, 3) memmap-backed array; index : (T,) int64 rows of ``positions``.

    Raises
    ------
    InputError
        Unreadable file, no ``positions``, other vertex count, or replayed frames it lacks.
    """
    positions, frames = read_truth(path)
    if positions.ndim != 3 or positions.shape[1:] != (n_vertices, 3):
        raise InputError(f"truth positions have shape {positions.shape}, the replay ({len(frame_numbers)}, "
                         f"{n_vertices}, 3)", path=path, hint="give the truth of the replayed take")
    return positions, match_frames(np.asarray(frame_numbers), frames, str(path))


def to_head_space(x, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Take-space positions (V, 3) of a frame in head space (world = R head + t)."""
    return (np.asarray(x, dtype=np.float64) - translation) @ rotation
