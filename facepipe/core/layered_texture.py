"""The layered texture a region's layer index Q indexes, and the stream that carries Q.

A region's layers (n, h, w, C), neutral first, form a texture volume; a frame's texture is the
neutral texture plus, per region, its layer at Q (linear between layers, bilinear within one:
the trilinear lookup of the volume) blended in by an alpha that ramps from the region's border
(Fidaleo et al. 2000, §V). The stream sends each region's Q, and each frame's light, in fixed
steps: :func:`stream_bits` and :func:`light_bits` give its bits per frame. Texels no example saw
are filled from those around them (:func:`fill_unseen`).

Pure functions over arrays.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["region_alpha", "layer_lookup", "compose_texture", "stream_bits", "light_bits", "LIGHT_SPAN", "fill_unseen"]


def region_alpha(mask: np.ndarray, ramp: float = 10.0) -> np.ndarray:
    """(H, W) blend weight of a region's texture: 0 outside the mask, rising linearly over ``ramp``
    texels from its border to 1 inside."""
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return np.zeros(mask.shape)
    inside = ndimage.distance_transform_edt(mask)  # 1 at the border texels, growing inward
    return np.clip(inside / max(float(ramp), 1e-9), 0.0, 1.0) * mask


def layer_lookup(layers: np.ndarray, q: float) -> np.ndarray:
    """A texture volume (n, H, W[, C]) at the continuous layer index q (linear between layers; with
    the bilinear lookup within a layer this is the trilinear lookup of the volume)."""
    n = layers.shape[0]
    q = float(np.clip(q, 0.0, n - 1.0))
    lo = min(int(np.floor(q)), n - 2) if n > 1 else 0
    f = q - lo
    if n == 1:
        return layers[0]
    return layers[lo] * (1.0 - f) + layers[lo + 1] * f


def compose_texture(neutral: np.ndarray, volumes, alphas, boxes, q: np.ndarray) -> np.ndarray:
    """The frame's texture: the neutral texture plus every region's change at its Q.

    neutral : (H, W, C); volumes : per region (n, h, w, C), layer 0 its neutral; alphas : per
    region (h, w); boxes : per region (row0, col0) of its volume in the texture; q : (R,) layer
    indices. A region adds alpha · (its layer at Q − the neutral texture): alone it is the alpha
    blend of its layer over the neutral texture, and where regions overlap (a brow's area
    reaching into the forehead's) their changes add, rather than the last region covering the
    others' with its own neutral texels.
    """
    out = np.array(neutral, dtype=np.float64, copy=True)
    for volume, alpha, (r0, c0), qr in zip(volumes, alphas, boxes, q):
        h, w = alpha.shape
        change = layer_lookup(volume, qr) - neutral[r0:r0 + h, c0:c0 + w]
        out[r0:r0 + h, c0:c0 + w] += change * alpha[..., None]
    return out


def stream_bits(layer_counts, step: float) -> np.ndarray:
    """Bits per frame (R,) that each region's Q needs when sent in steps of ``step`` layers: Q of a
    region of n layers takes (n − 1) / step + 1 values, coded in a whole number of bits."""
    counts = np.asarray(layer_counts, dtype=np.float64)
    levels = np.floor((counts - 1.0) / step + 0.5) + 1.0
    return np.ceil(np.log2(np.maximum(levels, 2.0))).astype(np.int64)


#: The span a frame's light values are coded over (the coefficients lie well inside ±1: luminance in
#: [0, 1] over albedo near 1; the colour gains near 1), for the light stream's bit rate.
LIGHT_SPAN = 4.0


def light_bits(step: float, terms: int = 12) -> int:
    """Bits per frame of a light of ``terms`` values (nine coefficients and three colour gains; a
    point light's seven and three: 10) sent in steps of ``step`` over :data:`LIGHT_SPAN`."""
    return terms * int(np.ceil(np.log2(LIGHT_SPAN / step + 1.0)))


def fill_unseen(image: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """``image`` (H, W, C) with its texels not ``seen`` (H, W) filled by push-pull (Gortler et al.
    1996): each coarser level averages the seen texels under it, and a texel nobody saw takes,
    level by level back up, the finest average around it. A hole's fill continues the colours at
    its border and shades smoothly into those further off, where one flat colour would meet the
    seen texture at a hard seam. Seen texels are returned as they are; with none seen, the image."""
    import cv2  # lazy: only a build needs it

    seen = np.asarray(seen, dtype=bool)
    if seen.all() or not seen.any():
        return np.array(image, copy=True)
    weight = seen.astype(np.float32)
    acc = np.asarray(image, dtype=np.float32) * weight[..., None]
    levels = [(acc, weight)]
    while max(weight.shape) > 1:
        size = (max(1, (weight.shape[1] + 1) // 2), max(1, (weight.shape[0] + 1) // 2))
        acc = cv2.resize(acc, size, interpolation=cv2.INTER_AREA).reshape(size[::-1] + acc.shape[2:])
        weight = cv2.resize(weight, size, interpolation=cv2.INTER_AREA)
        levels.append((acc, weight))
    acc, weight = levels[-1]
    filled = acc / np.maximum(weight, 1e-12)[..., None]  # the coarsest level: the mean of the seen texels
    for acc, weight in reversed(levels[:-1]):
        up = cv2.resize(filled, (weight.shape[1], weight.shape[0]), interpolation=cv2.INTER_LINEAR)
        # a level's own average (acc / weight) where it saw the share ``weight`` of its texels, the
        # coarser one for the rest: acc is that average already weighted
        filled = acc + (1.0 - weight[..., None]) * up.reshape(weight.shape + acc.shape[2:])
    return np.where(seen[..., None], image, filled.astype(np.asarray(image).dtype))
