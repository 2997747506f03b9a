"""Whether an eye card's content moved along its layers' path: a check on the Haar reading.

An eye card's layers (:mod:`facepipe.core.hole_cards`) are one gaze at increasing strength: the
iris slides across the card in one direction. The Haar match reads every change of the card's
patch as a point on that path, so what moves the patch otherwise reads as gaze too: a look up
(the iris sliding across the path), a lid narrowing the opening (the iris staying where it is), a
blink under another light. Those frames are the most of a take's frames at rest, and each one read
above its floor ranks a rest frame among the gazes.

The card's motion tells them apart. A frame's patch is aligned with the neutral template by the
whole-texel shift of best masked normalised cross-correlation (over the texels both show: a lid
hides some), refined by a parabola to a fraction of a texel. The layers' own shifts give the
path's directions; the example frames at rest that move the card beyond the noise give the lines
of motion that are not the region's (a look up, either way along it: a lid closing over it moves
the match the other way). A reading counts only where its shift goes beyond ``least`` (half the
first layer's shift) and lies nearer in direction to one of the layers' than to any of those lines;
else it is the region at rest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

__all__ = ["CardMotion", "ALONG_COSINE", "LEAST_OF_FIRST_LAYER", "LEAST_OVERLAP", "LEAST_FIRST_SHIFT", "masked_shifts",
           "card_shifts", "card_motion", "moves_along"]

#: A frame's shift must exceed this share of the first layer's (its direction is noise below it).
LEAST_OF_FIRST_LAYER = 0.5
#: A shift is measured only where the frame and the reference both show this share of the
#: reference's texels (else NaN: a lid over most of the card).
LEAST_OVERLAP = 0.3
#: A shift counts as the card's own motion only within 45° of one of its layers' directions: more
#: along the path than across it (else a turned head's or another light's slant of the match).
ALONG_COSINE = float(np.cos(np.pi / 4))
#: Texels: the least shift of the first layer for a card to have a motion check (a card whose
#: layers barely move its content is read by its Haar match alone).
LEAST_FIRST_SHIFT = 0.5


@dataclass
class CardMotion:
    """A card region's motion check (:func:`moves_along`): ``reference`` (s, s) its neutral patch
    and ``reference_seen`` (s, s) the texels the neutral frame shows, which shifts are measured
    against (:func:`masked_shifts`); ``least`` (texels), the shortest shift read as motion;
    ``layers`` (m, 2) the unit directions of its layers' shifts (x, y in template texels, y
    down); ``rest`` (k, 2) unit lines of the at-rest examples' shifts (either sense)."""

    reference: np.ndarray
    reference_seen: np.ndarray
    least: float
    layers: np.ndarray
    rest: np.ndarray

    def shifts(self, patches: np.ndarray, seen: np.ndarray) -> np.ndarray:
        """(..., 2) :func:`card_shifts` of patches (..., s, s) seeing ``seen`` against the reference."""
        return card_shifts(self.reference, self.reference_seen, patches, seen)


def card_shifts(reference: np.ndarray, reference_seen: np.ndarray, patches: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(..., 2) :func:`masked_shifts` of a card's patches against its neutral ``reference``,
    searched within half the patch's side (a full gaze moves the iris about a third of it)."""
    return masked_shifts(reference, reference_seen, patches, seen, np.shape(reference)[0] // 2)


def masked_shifts(reference: np.ndarray, reference_seen: np.ndarray, patches: np.ndarray, seen: np.ndarray,
                  most: int, least_overlap: float = LEAST_OVERLAP) -> np.ndarray:
    """(..., 2) the shift (x, y, texels) that carries ``reference`` (s, s) onto each of ``patches``
    (..., s, s): patch(p + shift) ≈ reference(p), the whole-texel shift within ±``most`` of
    highest normalised cross-correlation over the texels both see (``reference_seen`` (s, s),
    ``seen`` (..., s, s)), refined along each axis by the parabola through it and its
    neighbours (at most half a texel). NaN where no shift leaves ``least_overlap`` of the
    reference's seen texels seen in both, or none correlates."""
    ref = np.asarray(reference, dtype=np.float64)
    ref_seen = np.asarray(reference_seen, dtype=bool)
    patches = np.asarray(patches, dtype=np.float64)
    seen = np.asarray(seen, dtype=bool)
    size = ref.shape[0]
    lead = patches.shape[:-2]
    flat = patches.reshape((-1, size, size))
    flat_seen = seen.reshape((-1, size, size))
    out = np.full((len(flat), 2), np.nan)
    for start in range(0, len(flat), _CHUNK):  # a chunk's windows: (2·most + 1)² copies of its patches
        part = slice(start, start + _CHUNK)
        out[part] = _best_shifts(ref, ref_seen, flat[part], flat_seen[part], most, least_overlap)
    return out.reshape(lead + (2,))


#: Patches aligned at once by :func:`masked_shifts` (its memory: 289 windows of each at ±8 texels).
_CHUNK = 16


def _best_shifts(ref, ref_seen, flat, flat_seen, most: int, least_overlap: float) -> np.ndarray:
    """:func:`masked_shifts` of patches (P, s, s): every whole-texel shift's correlation at once."""
    size = ref.shape[0]
    pad = ((0, 0), (most, most), (most, most))
    windows = sliding_window_view(np.pad(np.where(flat_seen, flat, 0.0), pad), (size, size), axis=(1, 2))
    window_seen = sliding_window_view(np.pad(flat_seen, pad), (size, size), axis=(1, 2))
    both = window_seen & ref_seen  # (P, 2m+1, 2m+1, s, s): window (i, j) starts at shift (j − m, i − m)
    count = both.sum(axis=(-2, -1)).astype(np.float64)
    a = np.where(both, ref, 0.0)
    b = np.where(both, windows, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        sa, sb = a.sum(axis=(-2, -1)), b.sum(axis=(-2, -1))
        saa = (a * a).sum(axis=(-2, -1)) - sa * sa / count
        sbb = (b * b).sum(axis=(-2, -1)) - sb * sb / count
        sab = (a * b).sum(axis=(-2, -1)) - sa * sb / count
        score = sab / np.sqrt(saa * sbb)
    score = np.where((count >= least_overlap * ref_seen.sum()) & np.isfinite(score), score, np.nan)
    out = np.full((len(flat), 2), np.nan)
    for p in range(len(flat)):
        s = score[p]
        if not np.isfinite(s).any():
            continue
        i, j = np.unravel_index(np.nanargmax(s), s.shape)
        row = np.pad(s[i], 1, constant_values=np.nan)[j:j + 3]  # the best and its neighbours (NaN past the edge)
        column = np.pad(s[:, j], 1, constant_values=np.nan)[i:i + 3]
        out[p] = (j - most + _vertex(*row), i - most + _vertex(*column))
    return out


def _vertex(before: float, best: float, after: float) -> float:
    """The offset (within ±½) of the parabola's peak through three equally spaced scores."""
    if not (np.isfinite(before) and np.isfinite(after)):
        return 0.0
    curve = before - 2.0 * best + after
    return float(np.clip(0.5 * (before - after) / curve, -0.5, 0.5)) if curve < 0 else 0.0


def card_motion(reference: np.ndarray, reference_seen: np.ndarray, layer_shifts: np.ndarray, rest_shifts: np.ndarray,
                least_of_first: float = LEAST_OF_FIRST_LAYER) -> CardMotion | None:
    """A card's motion check against its neutral patch ``reference`` (s, s) seeing
    ``reference_seen`` (s, s), from its layers' shifts (n, 2) (the neutral first, read against
    itself) and its at-rest examples' (k, 2) (NaN rows: not measured). None where the first
    layer moves the card's content less than :data:`LEAST_FIRST_SHIFT` (or is not measured):
    its layers are not a motion across the card."""
    layers = np.asarray(layer_shifts, dtype=np.float64)[1:]
    rest = np.asarray(rest_shifts, dtype=np.float64).reshape(-1, 2)
    lengths = np.linalg.norm(layers, axis=1)
    if not (np.isfinite(lengths[0]) and lengths[0] >= LEAST_FIRST_SHIFT):
        return None
    least = least_of_first * float(lengths[0])
    usable = np.isfinite(lengths) & (lengths > least)
    rest_lengths = np.linalg.norm(rest, axis=1)
    moved = np.isfinite(rest_lengths) & (rest_lengths > least)
    return CardMotion(np.asarray(reference, dtype=np.float64), np.asarray(reference_seen, dtype=bool), least,
                      layers[usable] / lengths[usable, None], rest[moved] / rest_lengths[moved, None])


def moves_along(shifts: np.ndarray, motion: CardMotion) -> np.ndarray:
    """(...) whether shifts (..., 2) are the card's own motion (:mod:`this module <facepipe.core.card_motion>`):
    longer than ``motion.least`` and nearer in direction to one of its layers' than to any at-rest
    line. A shift not measured (NaN) counts as motion: nothing tells it apart, the Haar reading stands."""
    s = np.asarray(shifts, dtype=np.float64)
    length = np.linalg.norm(s, axis=-1)
    unit = s / np.where(length > 0, length, 1.0)[..., None]
    along = (unit @ motion.layers.T).max(axis=-1, initial=-np.inf)
    across = np.abs(unit @ motion.rest.T).max(axis=-1, initial=-np.inf)
    return np.where(np.isnan(length), True, (length > motion.least) & (along > np.maximum(across, ALONG_COSINE)))
