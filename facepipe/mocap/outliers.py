"""Capture noise and outliers in a take's marker residuals (what the rig's prior does not explain).

:func:`noise_sigma` measures the white capture noise σ from the residuals' second temporal
differences (robustly); :func:`find_jumps` finds samples that jumped away and back — spikes and
short plateaus, discontinuous steps large for their marker that nearly cancel — which cleaning
then drops and fills like gaps. A real expression the examples lack moves a residual
continuously, and a fast marker has large typical steps: neither is a jump. Pure functions over
arrays (:mod:`facepipe.mocap.cleaning` builds on them).
"""

from __future__ import annotations

import numpy as np

__all__ = ["noise_sigma", "find_jumps", "nanmedian_or_zero", "nanmean_or_zero"]


def noise_sigma(residual: np.ndarray, visible: np.ndarray) -> float:
    """Capture noise σ (per coordinate) from residual trajectories.

    White noise of σ gives second temporal differences of σ √6; the expression's own
    motion, already mostly removed from a residual, adds little. Robust (median absolute
    deviation), so outliers and the odd fast motion do not inflate it.

    Parameters
    ----------
    residual : (T, H, 3); visible : (T, H) bool.

    Returns
    -------
    float ≥ 0 (0 when fewer than 3 consecutive visible samples exist).
    """
    if residual.shape[0] < 3:
        return 0.0
    d2 = residual[2:] - 2 * residual[1:-1] + residual[:-2]
    ok = visible[2:] & visible[1:-1] & visible[:-2]
    vals = d2[ok]
    if vals.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(vals)) / np.sqrt(6.0))


def find_jumps(residual: np.ndarray, known: np.ndarray, floor: float, factor: float = 5.0,
               max_run: int = 30) -> np.ndarray:
    """Samples of each marker that jumped away and back: spikes and short plateaus.

    A jump is a single-frame step of a marker's residual trajectory (what the prior does not
    explain) that is large both absolutely (``floor``) and for that marker (``factor`` × its
    robust step scale: the median step length / 1.538, the median length of a 3D unit
    Gaussian), followed within ``max_run`` frames by a step back (the two steps nearly
    cancel). Both steps must be discontinuities (the steps just before and after them are
    small): a real expression the examples lack moves the residual continuously even when
    fast (a blink over 2–3 frames), and a marker that moves fast has large typical steps:
    neither is a jump. A one-frame spike is also found against the mean of its two
    neighbours, and a stretch of at most 2 frames cut off by the take's ends or a gap across
    one such step is an outlier too. A step without a return (a marker that stays moved) is
    left alone.

    Parameters
    ----------
    residual : (T, H, 3), NaN where unknown
    known : (T, H) bool
    floor : float, length units
    factor : float
    max_run : int, frames

    Returns
    -------
    (T, H) bool

    Example
    -------
    >>> r = np.zeros((9, 1, 3)); r[4, 0, 0] = 1.0
    >>> np.flatnonzero(find_jumps(r, np.ones((9, 1), bool), floor=0.1)[:, 0]).tolist()
    [4]
    """
    T, H = known.shape
    out = np.zeros((T, H), dtype=bool)
    if T < 3:
        return out
    step = residual[1:] - residual[:-1]  # (T-1, H, 3): step into frame t+1
    ok = known[1:] & known[:-1]
    size = np.where(ok, np.linalg.norm(np.nan_to_num(step), axis=-1), np.nan)
    # per-coordinate scale: the median length of a 3D Gaussian step is 1.538 σ
    scale = nanmedian_or_zero(size, axis=0) / 1.538
    big = ok & (np.nan_to_num(size) > np.maximum(floor, factor * scale))  # (T-1, H) big steps
    out[1:-1] |= _spikes(residual, known, floor, factor)
    for m in np.flatnonzero(big.any(axis=0)):
        _mark_cut_off_stretches(out[:, m], big[:, m], ok[:, m], size[:, m], known[:, m])
    for m in np.flatnonzero(big.sum(axis=0) >= 2):
        _mark_jumps_and_returns(out[:, m], big[:, m], ok[:, m], size[:, m], step[:, m], max_run)
    return out


def nanmedian_or_zero(x: np.ndarray, axis: int) -> np.ndarray:
    """np.nanmedian along ``axis``, 0 for a slice without a number (where numpy would warn and give NaN)."""
    empty = np.isnan(x).all(axis=axis, keepdims=True)
    return np.nanmedian(np.where(empty, 0.0, x), axis=axis)


def nanmean_or_zero(x: np.ndarray, axis: int) -> np.ndarray:
    """np.nanmean along ``axis``, 0 for a slice without a number (where numpy would warn and give NaN)."""
    empty = np.isnan(x).all(axis=axis, keepdims=True)
    return np.nanmean(np.where(empty, 0.0, x), axis=axis)


def _spikes(residual: np.ndarray, known: np.ndarray, floor: float, factor: float) -> np.ndarray:
    """(T-2, H) one-frame spikes at frames 1..T-2: the sample against the mean of its neighbours (a
    better signal-to-noise than either step), far beyond the marker's typical deviation (and
    ``floor``), with the neighbours agreeing with each other."""
    mid = residual[1:-1] - 0.5 * (residual[:-2] + residual[2:])
    ok3 = known[1:-1] & known[:-2] & known[2:]
    dev = np.where(ok3, np.linalg.norm(np.nan_to_num(mid), axis=-1), np.nan)
    dev_scale = nanmedian_or_zero(dev, axis=0) / 1.538
    across = np.linalg.norm(np.nan_to_num(residual[2:] - residual[:-2]), axis=-1)
    dev = np.nan_to_num(dev)
    return ok3 & (dev > np.maximum(floor, factor * dev_scale)) & (across < 0.5 * dev)


def _mark_cut_off_stretches(out: np.ndarray, big: np.ndarray, ok: np.ndarray, size: np.ndarray,
                            known: np.ndarray, edge: int = 2) -> None:
    """One marker: mark in ``out`` (T,) a stretch of at most ``edge`` known frames cut off by the
    take's ends or a gap across one big calm step (big, ok, size: (T-1,) of its steps)."""
    for a in np.flatnonzero(big):
        calm = all(not ok[k] or size[k] < 0.25 * size[a] for k in (a - 1, a + 1) if 0 <= k < len(big))
        if not calm:
            continue
        before = a + 1 - _run_start(known, a)  # known frames up to a
        after = _run_stop(known, a + 1) - (a + 1)
        if before <= edge < after:
            out[a + 1 - before:a + 1] = True
        elif after <= edge < before:
            out[a + 1:a + 1 + after] = True


def _mark_jumps_and_returns(out: np.ndarray, big: np.ndarray, ok: np.ndarray, size: np.ndarray,
                            step: np.ndarray, max_run: int) -> None:
    """One marker: mark in ``out`` (T,) the frames between a big step and one back within
    ``max_run`` frames that nearly cancels it, both discontinuities (step: (T-1, 3))."""
    ups = np.flatnonzero(big)
    used = np.zeros(ups.size, dtype=bool)
    for i, a in enumerate(ups):
        if used[i]:
            continue
        for j in range(i + 1, ups.size):
            b = ups[j]
            if b - a > max_run:
                break
            sa, sb = step[a], step[b]
            na, nb = np.linalg.norm(sa), np.linalg.norm(sb)
            # a discontinuity, not a fast but continuous motion (a blink the examples lack):
            # the steps just before and after each jump are small
            around = [k for k in (a - 1, a + 1, b - 1, b + 1) if 0 <= k < len(big) and k not in (a, b)]
            calm = all(not ok[k] or size[k] < 0.25 * min(na, nb) for k in around)
            if calm and np.linalg.norm(sa + sb) < 0.5 * max(na, nb):
                out[a + 1:b + 1] = True  # frames a+1 .. b moved away
                used[i] = used[j] = True
                break


def _run_start(known: np.ndarray, t: int) -> int:
    """First frame of the run of known samples that contains frame t."""
    while t > 0 and known[t - 1]:
        t -= 1
    return t


def _run_stop(known: np.ndarray, t: int) -> int:
    """One past the last frame of the run of known samples that contains frame t."""
    while t < len(known) and known[t]:
        t += 1
    return t
