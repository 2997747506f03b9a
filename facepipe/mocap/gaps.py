"""Gap filling by temporal interpolation alone (per marker, PCHIP): the fallback when the
rig's prior is not used (``--no-clean``) and a building block of :mod:`facepipe.mocap.cleaning`."""

from __future__ import annotations

import numpy as np

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
    from scipy.interpolate import PchipInterpolator

    pos = np.array(positions, dtype=np.float64)  # a copy: the caller's array is left alone
    if pos.ndim != 3 or pos.shape[2] != 3:
        raise ValueError(f"positions must be (T, M, 3), got {pos.shape}")
    T, M = pos.shape[:2]
    names = [f"marker{m}" for m in range(M)] if marker_names is None else [str(n) for n in marker_names]
    if len(names) != M:
        raise ValueError(f"{len(names)} marker names for {M} markers")
    if max_gap is not None and (int(max_gap) != max_gap or max_gap < 1):
        raise ValueError(f"max_gap must be a positive integer or None, got {max_gap!r}")
    t = np.arange(T, dtype=np.float64) if times is None else np.asarray(times, dtype=np.float64)
    if t.shape != (T,) or (T > 1 and not (np.diff(t) > 0).all()) or not np.isfinite(t).all():
        raise ValueError("times must be (T,), finite and strictly increasing")

    missing = np.isnan(pos).any(axis=2)  # (T, M)
    pos[missing] = np.nan
    never = [names[m] for m in np.flatnonzero(missing.all(axis=0))] if T else []
    if never:
        shown = ", ".join(never[:12]) + (f" and {len(never) - 12} more" if len(never) > 12 else "")
        raise InputError(
            f"marker(s) never visible in the take: {shown}",
            path=path,
            hint="check the marker's columns in the take, or mark the marker `ignore` in markers.csv",
        )

    # Runs of missing frames, marker by marker: +1/-1 steps of the padded mask.
    step = np.diff(np.pad(missing.T.astype(np.int8), ((0, 0), (1, 1))), axis=1)  # (M, T+1)
    run_m, run_start = np.nonzero(step == 1)
    _, run_stop = np.nonzero(step == -1)  # same marker-major order as the starts
    run_len = run_stop - run_start
    # Length of the gap each missing sample belongs to, in (marker, frame) order.
    sample_len = np.repeat(run_len, run_len)
    mm, tt = np.nonzero(missing.T)
    fill = np.ones(mm.size, dtype=bool) if max_gap is None else sample_len <= max_gap
    do = np.zeros((M, T), dtype=bool)
    do[mm[fill], tt[fill]] = True

    for m in np.flatnonzero(do.any(axis=1)):
        vis = np.flatnonzero(~missing[:, m])
        rows = np.flatnonzero(do[m])
        first, last = vis[0], vis[-1]
        lo, hi = rows[rows < first], rows[rows > last]
        mid = rows[(rows > first) & (rows < last)]
        pos[lo, m] = pos[first, m]
        pos[hi, m] = pos[last, m]
        if mid.size:
            pos[mid, m] = PchipInterpolator(t[vis], pos[vis, m], axis=0)(t[mid])

    n_gaps = np.bincount(run_m, minlength=M)
    n_missing = missing.sum(axis=0)
    n_filled = do.sum(axis=1)
    longest = np.zeros(M, dtype=np.int64)
    np.maximum.at(longest, run_m, run_len)
    report = {
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
    return pos, report
