"""Runs of consecutive frames in per-frame masks: a marker's gaps, a region's hidden spans."""

from __future__ import annotations

import numpy as np

__all__ = ["column_runs", "offsets_within"]


def column_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The runs of True down each column of a (T, M) mask (a (T,) mask is one column).

    Returns column, start and stop (exclusive) arrays of the runs, column by column, each
    column's in frame order.

    >>> column_runs(np.array([[1, 0], [1, 1], [0, 1], [1, 0]], dtype=bool))
    (array([0, 0, 1]), array([0, 3, 1]), array([2, 4, 3]))
    """
    m = np.asarray(mask, dtype=bool)
    m = m[:, None] if m.ndim == 1 else m
    step = np.diff(np.pad(m.T.astype(np.int8), ((0, 0), (1, 1))), axis=1)  # +1 at a run's start, −1 after its end
    column, start = np.nonzero(step == 1)
    _, stop = np.nonzero(step == -1)  # the same column-major order as the starts
    return column, start, stop


def offsets_within(lengths: np.ndarray) -> np.ndarray:
    """0, 1, …, n − 1 for each n of ``lengths`` (non-negative ints), concatenated: each item's
    place in its run, once the runs are laid end to end.

    >>> offsets_within(np.array([2, 0, 3]))
    array([0, 1, 0, 1, 2])
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    starts = np.cumsum(lengths) - lengths
    return np.arange(int(lengths.sum())) - np.repeat(starts, lengths)
