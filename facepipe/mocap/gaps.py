"""Gap filling by temporal interpolation alone (per marker, PCHIP): the fallback when the
rig's prior is not used (``--no-clean``) and a building block of :mod:`facepipe.mocap.cleaning`."""

from __future__ import annotations

import numpy as np

from facepipe.core.runs import column_runs
from facepipe.errors import InputError


def fill_gaps(positions, max_gap: int | None = None, *, times=None, marker_names=None, path=None):
    """Fill runs of missing samples per marker: PCHIP inside, held constant at the ends.

    A gap inside the take is filled by the monotone cubic Hermite interpolant
    (:class:`scipy.interpolate.PchipInterpolator`) through the marker's visible
    samples: it passes through the samples on both sides with smooth slopes, and
    on each interval it stays between its two end values (no overshoot however
    long the gap). A gap at the start or end takes the first or last visible value:
    extrapolating a marker's motion past its last sample is not to be trusted.

    Parameters
    ----------
    positions : (T, M, 3) float
        Marker positions, NaN where a sample is missing (a sample with any NaN
        coordinate counts as missing).
    max_gap : int, optional
        Fill only gaps of at most this many frames; longer ones stay NaN and are
        reported as ``unfilled``. None fills every gap.
    times : (T,) float, optional
        Strictly increasing sample times (seconds); the default is the frame index.
    marker_names : list[str], optional
        Names for the report and messages; default ``marker0``, ``marker1``, ...
    path : str, optional
        The take, for messages.

    Returns
    -------
    filled : (T, M, 3) float64
        A copy with the gaps filled.
    report : dict
        JSON-serialisable. ``report["markers"][name]`` has ``gaps`` (number of runs
        of missing frames), ``filled`` (samples filled), ``unfilled`` (samples left
        missing, see ``max_gap``) and ``longest_gap`` (frames); ``report["total"]``
        has ``frames``, ``markers``, ``missing`` (samples), ``missing_fraction``,
        ``gaps``, ``filled``, ``unfilled``, ``longest_gap`` and ``longest_gap_marker``.

    Raises
    ------
    InputError
        A marker that is never visible (naming every such marker).

    Example
    -------
    >>> P = np.zeros((5, 1, 3)); P[:, 0, 0] = [0, 1, np.nan, 3, 4]
    >>> filled, report = fill_gaps(P)
    >>> float(filled[2, 0, 0]), report["total"]["filled"]
    (2.0, 1)
    """
    pos = np.array(positions, dtype=np.float64)  # a copy: the caller's array is left alone
    if pos.ndim != 3 or pos.shape[2] != 3:
        raise ValueError(f"positions must be (T, M, 3), got {pos.shape}")
    T, M = pos.shape[:2]
    names = [f"marker{m}" for m in range(M)] if marker_names is None else [str(n) for n in marker_names]
    if len(names) != M:
        raise ValueError(f"{len(names)} marker names for {M} markers")
    if max_gap is not None and (int(max_gap) != max_gap or max_gap < 1):
        raise ValueError(f"max_gap must be a positive integer or None, got {max_gap!r}")
    t = _sample_times(times, T)

    missing = np.isnan(pos).any(axis=2)  # (T, M)
    pos[missing] = np.nan
    _refuse_never_visible(missing, names, path)
    run_m, run_start, run_stop = column_runs(missing)  # marker by marker
    run_len = run_stop - run_start
    to_fill = _samples_to_fill(missing, run_len, max_gap)
    for m in np.flatnonzero(to_fill.any(axis=1)):
        _fill_marker(pos[:, m], t, ~missing[:, m], to_fill[m])  # pos[:, m] is a view: filled in place
    return pos, _gap_report(missing, to_fill, run_m, run_len, names)


def _sample_times(times, T: int) -> np.ndarray:
    """(T,) sample times: the frame index by default, else checked to be finite and increasing."""
    t = np.arange(T, dtype=np.float64) if times is None else np.asarray(times, dtype=np.float64)
    if t.shape != (T,) or (T > 1 and not (np.diff(t) > 0).all()) or not np.isfinite(t).all():
        raise ValueError("times must be (T,), finite and strictly increasing")
    return t


def _refuse_never_visible(missing: np.ndarray, names: list[str], path) -> None:
    """An InputError naming every marker missing in all frames of ``missing`` (T, M)."""
    never = [names[m] for m in np.flatnonzero(missing.all(axis=0))] if len(missing) else []
    if never:
        shown = ", ".join(never[:12]) + (f" and {len(never) - 12} more" if len(never) > 12 else "")
        raise InputError(
            f"marker(s) never visible in the take: {shown}",
            path=path,
            hint="check the marker's columns in the take, or mark the marker `ignore` in markers.csv",
        )


def _samples_to_fill(missing: np.ndarray, run_len: np.ndarray, max_gap: int | None) -> np.ndarray:
    """(M, T) the missing samples in gaps of at most ``max_gap`` frames (all of them without one)."""
    T, M = missing.shape
    sample_len = np.repeat(run_len, run_len)  # the length of each missing sample's gap, (marker, frame) order
    mm, tt = np.nonzero(missing.T)
    fill = np.ones(mm.size, dtype=bool) if max_gap is None else sample_len <= max_gap
    to_fill = np.zeros((M, T), dtype=bool)
    to_fill[mm[fill], tt[fill]] = True
    return to_fill


def _fill_marker(track: np.ndarray, t: np.ndarray, visible: np.ndarray, rows_to_fill: np.ndarray) -> None:
    """Fill one marker's (T, 3) ``track`` in place at ``rows_to_fill``: PCHIP between its visible
    samples, the first or last visible value before and after them."""
    from scipy.interpolate import PchipInterpolator  # lazy: the CLI starts without scipy

    vis = np.flatnonzero(visible)
    rows = np.flatnonzero(rows_to_fill)
    first, last = vis[0], vis[-1]
    track[rows[rows < first]] = track[first]
    track[rows[rows > last]] = track[last]
    mid = rows[(rows > first) & (rows < last)]
    if mid.size:
        track[mid] = PchipInterpolator(t[vis], track[vis], axis=0)(t[mid])


def _gap_report(missing: np.ndarray, to_fill: np.ndarray, run_m: np.ndarray, run_len: np.ndarray,
                names: list[str]) -> dict:
    """The report of :func:`fill_gaps` (see there)."""
    T, M = missing.shape
    n_gaps = np.bincount(run_m, minlength=M)
    n_missing = missing.sum(axis=0)
    n_filled = to_fill.sum(axis=1)
    longest = np.zeros(M, dtype=np.int64)
    np.maximum.at(longest, run_m, run_len)
    return {
        "markers": {
            names[m]: {
                "gaps": int(n_gaps[m]),
                "filled": int(n_filled[m]),
                "unfilled": int(n_missing[m] - n_filled[m]),
                "longest_gap": int(longest[m]),
            }
            for m in range(M)
        },
        "total": {
            "frames": int(T),
            "markers": int(M),
            "missing": int(n_missing.sum()),
            "missing_fraction": float(n_missing.sum() / max(1, T * M)),
            "gaps": int(n_gaps.sum()),
            "filled": int(n_filled.sum()),
            "unfilled": int(n_missing.sum() - n_filled.sum()),
            "longest_gap": int(longest.max()) if M else 0,
            "longest_gap_marker": names[int(np.argmax(longest))] if M and longest.max() > 0 else None,
        },
    }
