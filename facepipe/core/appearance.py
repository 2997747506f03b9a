"""Appearance from footage: Haar-wavelet classification of texture patches against templates
(Fidaleo et al. 2000, §V). The layered texture that the layer index Q indexes is in
:mod:`facepipe.core.layered_texture`; the light that patches are divided by, in
:mod:`facepipe.core.lighting`.

A region of the face has n templates, texture patches of it from example frames ordered from
neutral (layer 0) to extreme (layer n − 1). A frame's patch of the region (sampled at fixed
barycentric coordinates on the animated surface, so pose-normalised) is compared with every
template in a truncated Haar basis, and the match distances give a continuous layer index
Q ∈ [0, n − 1]:

* **Haar decomposition** of a size × size patch (size a power of two) with PyWavelets, as one
  orthonormal matrix (built by transforming the basis images) so a batch of patches is one
  product; every coefficient has a scale, 0 the patch mean, then the detail levels from
  coarse to fine;
* **coefficient selection**: per region, the ``keep`` coefficients largest over its templates
  (root mean square). One set per region, not per template, so the distances to the
  templates are sums over the same terms and comparable;
* **match distance**: per-scale weighted squared difference on the kept coefficients (the
  paper's weights 2, 4, 2, 1, 0, coarse to fine): a squared Euclidean distance, the same terms
  for every template of a region;
* **interpolation between templates** (:func:`segment_index`, the default): the point nearest
  the patch on the path through the templates in layer order, straight between adjacent ones —
  the layered texture blends adjacent layers linearly, so this is the Q whose texture looks most
  like the patch. It needs only the distances and those between adjacent templates (the law of
  cosines); a template reads its own index and a blend of two adjacent ones its weight however
  the layers are spaced. The paper's **peak interpolation** (:func:`peak_index`): the vertex of
  the parabola through the best template's distance and its two neighbours, kept within half a
  layer of the best — exact only for templates evenly spaced along a line (a layer between a
  near and a far neighbour reads off its own index: 0.79 for layer 1 of the ICT kit's right
  eyelid);
* **rest floor**: the highest Q a region reads while it is at rest (in the examples of the
  other regions, where the rest of the face moves): Q is measured from it (:func:`above_rest`),
  so a region at rest reads exactly 0, not a level of its own that flickers; or each reading
  from its own (:func:`conditional_floor`): only the at-rest readings that lie as far off the
  path for their Q (:func:`off_path_ratio`) hide it, so a small activation on the path is not
  hidden by another expression that reads as much off it;
* **explained away**: another expression's change of a region's patch (:func:`rest_direction`)
  left out of its match (:class:`RegionBank`'s ``nuisance``), so that expression at any weight
  reads the neutral layer;
* **visibility**: a region facing away from the camera keeps its last value, decaying
  exponentially to neutral (0).

Patches are divided by their shading before the transform, the plane through their
intensities (a change of exposure, of the light's strength and, to first order, of its
direction leaves them unchanged), or per region the quadratic, which takes out a light's
curvature over the patch too where it keeps most of the region's own change
(:func:`shading_order`): what is classified is the texture's structure. The surface is fitted
either through the patch's own intensities or as the shading that maps the region's neutral
layer onto the patch (:data:`SHADING_REFERENCES`): the second takes a smooth light over the
neutral texture out exactly, where the first reads a dark iris lit more on one side as moved.

Pure functions over arrays.
"""

from __future__ import annotations

import functools

import numpy as np
import pywt

from facepipe.core.runs import column_runs, offsets_within

__all__ = ["DEFAULT_SCALE_WEIGHTS", "haar_matrix", "haar_coefficients", "normalise_patches", "select_coefficients",
           "RegionBank", "classify_regions", "coefficient_weights", "match_distances", "peak_index", "segment_index",
           "PEAK_INTERPOLATIONS", "classify", "hold_and_decay", "drop_short_events", "bilinear_sample",
           "facing", "rest_floor", "above_rest", "DIAGONAL_OFFSETS", "SHADING_ORDERS",
           "QUADRATIC_LEAST_KEPT", "SHADING_REFERENCES", "neutral_reference", "SHADING_TILT", "shading_tilt_readings",
           "layer_contrast", "shading_order", "rest_direction", "kept_step_shares",
           "off_path_ratio", "conditional_floor", "OFF_PATH_LEAST_Q", "MOST_REST_FLOOR"]

#: The paper's weights per scale, coarse to fine: patch mean, then the detail levels of a 16 × 16 patch.
DEFAULT_SCALE_WEIGHTS = (2.0, 4.0, 2.0, 1.0, 0.0)

#: The five samples of a patch: in place and shifted diagonally (units of the template's spacing).
DIAGONAL_OFFSETS = np.array([[0.0, 0.0], [0.5, 0.5], [-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5]])


@functools.lru_cache(maxsize=8)
def haar_matrix(size: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """The 2D Haar transform of a size × size patch as a matrix, and each coefficient's scale.

    Returns
    -------
    H : (size², size²) float64, orthonormal; coefficients = H @ patch.ravel(), in the order
        ``pywt.coeffs_to_array`` lays out ``pywt.wavedec2(patch, "haar")``.
    scale : (size²,) int64, 0 for the approximation (the patch mean times size), 1 for the
        coarsest detail level … log2(size) for the finest.
    """
    if size < 2 or size & (size - 1):
        raise ValueError(f"patch size {size} is not a power of two ≥ 2")
    levels = int(np.log2(size))
    n = size * size
    H = np.empty((n, n))
    for k in range(n):  # the transform of the k-th basis image is the k-th column
        basis = np.zeros(n)
        basis[k] = 1.0
        coeffs = pywt.wavedec2(basis.reshape(size, size), "haar", level=levels)
        H[:, k] = pywt.coeffs_to_array(coeffs)[0].ravel()
    coeffs = pywt.wavedec2(np.zeros((size, size)), "haar", level=levels)
    labels = [np.zeros_like(coeffs[0], dtype=np.int64)]
    for level, details in enumerate(coeffs[1:], start=1):
        labels.append(tuple(np.full_like(d, level, dtype=np.int64) for d in details))
    scale = pywt.coeffs_to_array(labels)[0].ravel().astype(np.int64)
    H.flags.writeable = False
    scale.flags.writeable = False
    return H, scale


def haar_coefficients(patches: np.ndarray) -> np.ndarray:
    """Haar coefficients (..., size²) of square patches (..., size, size)."""
    patches = np.asarray(patches, dtype=np.float64)
    size = patches.shape[-1]
    H, _ = haar_matrix(size)
    return patches.reshape(patches.shape[:-2] + (size * size,)) @ H.T


def normalise_patches(patches: np.ndarray, shading: int = 1, mask: np.ndarray | None = None,
                      reference: np.ndarray | None = None) -> np.ndarray:
    """Patches divided by their shading: the least-squares surface through their intensities of
    order ``shading`` (:data:`SHADING_ORDERS`: 1 the plane a + b·x + c·y, 2 the quadratic that
    adds x², x·y, y²; ``True`` is 1), or with 0 (``False``) their mean alone.

    Light varies slowly over a small patch of skin, the texture it shows (wrinkles, pores, folds)
    fast: over a patch a few millimetres wide the shading of a smooth light is close to linear,
    so dividing by the plane takes out a change of exposure, of the light's strength and of its
    direction to first order, while a fold's darkening (its structure within the patch, and its
    mean relative to the patch's gradient) stays. Over a curved patch (a cheek's fold, the
    mouth's corner) a light from the side or a turned head shades it along a curve the plane
    leaves behind, and the quadratic takes it out too, at the price of the part of the region's
    own change that is that smooth (an iris moving, a lid closing: see :func:`shading_order`). A
    patch whose surface nears zero somewhere (a patch mostly in shadow) is divided by at least a
    tenth of its mean.

    ``reference`` (broadcastable to the patches; :func:`neutral_reference`): the surface S is
    instead the one that maps it onto each patch (patch ≈ S · reference, least squares over the
    mask), so a patch that is the reference under any shading of that order reads the reference
    exactly. Through the patch alone the plane takes out such a shading exactly only where the
    texture under it is even: an iris lit more on one side would look moved.
    """
    patches = np.asarray(patches, dtype=np.float64)
    order = int(shading)
    if reference is not None and not order:
        reference = None  # the mean alone needs none
    if mask is None and (order > 1 or reference is not None):
        mask = np.ones(patches.shape[-2:], dtype=bool)
    if mask is not None:
        return _normalise_masked(patches, np.asarray(mask, dtype=bool), order, reference)
    mean = patches.mean(axis=(-2, -1), keepdims=True)
    if not order:
        return patches / np.maximum(np.abs(mean), 1e-6)
    h, w = patches.shape[-2:]
    y = (np.arange(h) - 0.5 * (h - 1))[:, None]
    x = (np.arange(w) - 0.5 * (w - 1))[None, :]
    # the centred coordinates are orthogonal to the constant and to each other on the grid
    bx = (patches * x).sum(axis=(-2, -1), keepdims=True) / (h * (x * x).sum())
    by = (patches * y).sum(axis=(-2, -1), keepdims=True) / (w * (y * y).sum())
    plane = mean + bx * x + by * y
    floor = np.maximum(0.1 * np.abs(mean), 1e-6)
    return patches / np.maximum(plane, floor)


def _normalise_masked(patches: np.ndarray, mask: np.ndarray, shading: int, reference: np.ndarray | None = None) -> np.ndarray:
    """:func:`normalise_patches` with the mean and the surface fitted over the texels of ``mask``
    (..., h, w) alone (the seen part of a partly hidden patch); texels off the mask are 0. The
    mask may have fewer leading axes' lengths than the patches (broadcast: one mask, many patches)."""
    h, w = patches.shape[-2:]
    flat = patches.reshape(patches.shape[:-2] + (h * w,))
    m = np.asarray(mask, dtype=bool).reshape(mask.shape[:-2] + (h * w,))
    ref = None if reference is None else np.asarray(reference, dtype=np.float64).reshape(np.shape(reference)[:-2] + (h * w,))
    plane, mean = _masked_plane(flat, m, shading, ref)
    floor = np.maximum(0.1 * np.abs(mean), 1e-6)
    return np.where(m, flat / np.maximum(plane, floor), 0.0).reshape(patches.shape)


#: The shading surfaces a patch can be divided by: order → name (0: the patch's mean alone).
SHADING_ORDERS = {0: "mean", 1: "plane", 2: "quadratic"}

#: What a patch's shading surface is fitted against: its region's neutral template (the shading
#: that maps it onto the patch: :func:`normalise_patches`' ``reference``), or the patch alone.
SHADING_REFERENCES = ("neutral", "patch")


@functools.lru_cache(maxsize=8)
def _plane_basis(h: int, w: int, order: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The surface's basis (k, h·w): 1, x, y about the centre (and x², x·y, y² for order 2, in
    units of the half-size, which keeps the normal equations balanced); and its products (k², h·w)."""
    y, x = np.meshgrid(np.arange(h) - 0.5 * (h - 1), np.arange(w) - 0.5 * (w - 1), indexing="ij")
    terms = [np.ones(h * w), x.ravel(), y.ravel()]
    if order >= 2:
        u, v = x.ravel() / (0.5 * w), y.ravel() / (0.5 * h)
        terms += [u * u, u * v, v * v]
    basis = np.stack(terms)
    k = len(basis)
    return basis, (basis[:, None, :] * basis[None, :, :]).reshape(k * k, h * w)


def _masked_plane(values: np.ndarray, mask: np.ndarray, shading: int,
                  reference: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares surface of order ``shading`` (..., N) (the mean alone for 0) through
    values (..., N) of a square patch over the texels of mask (broadcastable to them), and the mean (..., 1).

    With a ``reference`` (..., N) (broadcastable): the surface S that maps it onto the values
    (values ≈ S · reference, least squares), and for the mean the values' mean over the
    reference's: the shading of a patch relative to a known texture instead of its own."""
    m = mask.astype(np.float64)
    count = np.maximum(m.sum(axis=-1, keepdims=True), 1.0)
    mean = (values * m).sum(axis=-1, keepdims=True) / count
    if not int(shading):
        return np.broadcast_to(mean, values.shape), mean
    side = int(round(np.sqrt(values.shape[-1])))
    basis, products = _plane_basis(side, side, int(shading))
    k = len(basis)
    if reference is not None:
        r = np.asarray(reference, dtype=np.float64)
        mean = mean / np.maximum(np.abs((r * m).sum(axis=-1, keepdims=True) / count), 1e-6)
        m_ref = m * r                                                 # the reference's weight in the fit
        normal = ((m_ref * r) @ products.T).reshape((m_ref * r).shape[:-1] + (k, k))
        rhs = (values * m_ref) @ basis.T
    else:
        normal = (m @ products.T).reshape(m.shape[:-1] + (k, k))       # one per mask, shared by its patches
        rhs = (values * m) @ basis.T                                     # (..., k)
    # a seen part too thin to fix the surface (a line, a few texels) is divided by its mean alone
    diagonal = np.sqrt(np.maximum(np.diagonal(normal, axis1=-2, axis2=-1), 1e-300))
    well_posed = np.linalg.det(normal / (diagonal[..., :, None] * diagonal[..., None, :])) > 1e-8
    safe = np.where(well_posed[..., None, None], normal, np.eye(k))
    safe = np.broadcast_to(safe, rhs.shape[:-1] + (k, k))
    coef = np.linalg.solve(safe, rhs[..., None])[..., 0]
    fallback = np.concatenate([mean, np.zeros(mean.shape[:-1] + (k - 1,))], axis=-1)
    coef = np.where(np.broadcast_to(well_posed, rhs.shape[:-1])[..., None], coef, fallback)
    return coef @ basis, mean


#: The quadratic shading surface is used where it keeps at least this share of a region's layer
#: contrast (what the plane keeps): it costs a wrinkle region little, an iris or a closing lid much.
QUADRATIC_LEAST_KEPT = 0.75


def layer_contrast(patches: np.ndarray, order: int, mask: np.ndarray | None, weights: np.ndarray,
                   keep: int = 50) -> float:
    """How far a region's layers (n, size, size) stand from its neutral one (layer 0), normalised
    by the shading surface of ``order`` over ``mask``: the sum over the layers of their match
    distance to it, on the coefficients that normalisation would keep."""
    coefficients = haar_coefficients(normalise_patches(patches, order, mask))
    kept = select_coefficients(coefficients, keep)
    return float(match_distances(coefficients[1:], coefficients[:1], kept, weights).sum())


def shading_order(patches: np.ndarray, mask: np.ndarray | None, weights: np.ndarray, keep: int = 50,
                  least_kept: float = QUADRATIC_LEAST_KEPT) -> tuple[int, float]:
    """The shading surface a region's patches are divided by, from its layers (n, size, size):
    the quadratic (2) where it keeps at least ``least_kept`` of the contrast the plane keeps
    (:func:`layer_contrast`), else the plane (1); and that share.

    A quadratic takes out more of a light's shading over a curved patch (a light from the side,
    a turned head), and with it the part of the region's own change that is as smooth: little
    of a wrinkle's lines, much of an iris moving across an eye or of a lid closing over it, whose
    layers the plane keeps apart better."""
    plane = layer_contrast(patches, 1, mask, weights, keep)
    kept = layer_contrast(patches, 2, mask, weights, keep) / plane if plane > 0 else 0.0
    return (2 if kept >= least_kept else 1), kept


def neutral_reference(patches: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """A region's neutral layer (the first of ``patches`` (n, size, size)) over its mean on
    ``mask``: the texture whose shading the region's patches are measured relative to
    (:func:`normalise_patches`' ``reference``)."""
    neutral = np.asarray(patches[0], dtype=np.float64)
    values = neutral if mask is None else neutral[np.asarray(mask, dtype=bool)]
    return neutral / max(abs(float(values.mean())), 1e-6)


def select_coefficients(template_coefficients: np.ndarray, keep: int = 50) -> np.ndarray:
    """Indices of the ``keep`` coefficients largest over a region's templates (RMS), sorted.

    template_coefficients : (n, C).
    """
    c = np.asarray(template_coefficients, dtype=np.float64)
    rms = np.sqrt((c * c).mean(axis=0))
    keep = min(int(keep), c.shape[1])
    return np.sort(np.argsort(-rms, kind="stable")[:keep])


def coefficient_weights(size: int, scale_weights=DEFAULT_SCALE_WEIGHTS) -> np.ndarray:
    """(size²,) the weight of every coefficient from the weights per scale (coarse to fine);
    scales beyond the list get its last weight."""
    _, scale = haar_matrix(size)
    w = np.asarray(scale_weights, dtype=np.float64)
    return w[np.minimum(scale, len(w) - 1)]


def match_distances(query: np.ndarray, templates: np.ndarray, indices: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted squared distances (..., n) of query coefficients (..., C) to templates (n, C) over
    the kept ``indices``, each coefficient weighted by ``weights`` (C,)."""
    q = np.asarray(query, dtype=np.float64)[..., indices]
    t = np.asarray(templates, dtype=np.float64)[:, indices]
    w = np.asarray(weights, dtype=np.float64)[indices]
    # |q - t|²_w = q·wq − 2 q·wt + t·wt, all templates in one product
    return ((q * q * w).sum(axis=-1)[..., None] - 2.0 * (q * w) @ t.T + (t * t * w).sum(axis=-1))


def peak_index(distances: np.ndarray) -> np.ndarray:
    """Continuous index (...) of the smallest of distances (..., n), n ≥ 3: the vertex of the parabola
    through the best one and its neighbours (the nearest three at the ends), within half a
    layer of the best and within [0, n − 1]. Trailing infinite distances are absent templates
    (regions with fewer layers padded to the most): n is each row's count of finite ones."""
    d = np.asarray(distances, dtype=np.float64)
    n = np.isfinite(d).sum(axis=-1)
    if (n < 3).any():
        raise ValueError("peak interpolation needs at least three templates")
    best = np.argmin(d, axis=-1)
    centre = np.clip(best, 1, n - 2)
    dm = np.take_along_axis(d, (centre - 1)[..., None], -1)[..., 0]
    d0 = np.take_along_axis(d, centre[..., None], -1)[..., 0]
    dp = np.take_along_axis(d, (centre + 1)[..., None], -1)[..., 0]
    curvature = dm - 2.0 * d0 + dp
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = centre + 0.5 * (dm - dp) / curvature
    vertex = np.where(curvature > 0, vertex, best)  # no minimum there: the best template itself
    return np.clip(np.clip(vertex, best - 0.5, best + 0.5), 0.0, n - 1.0)


#: How a continuous layer index is read from the match distances: ``segment`` (the nearest point
#: of the path through the templates, :func:`segment_index`) or ``parabola`` (:func:`peak_index`).
PEAK_INTERPOLATIONS = ("segment", "parabola")


def segment_index(distances: np.ndarray, gaps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Continuous index (...) of the point nearest the query on the path through the templates in
    layer order (straight between adjacent ones, as the layered texture blends them), and the
    query's squared distance (...) to that point.

    distances : (..., n) squared distances of the query to the templates; gaps : (..., n − 1)
    squared distances between adjacent templates, in the same metric. On segment k (templates
    k and k + 1, gap L) the nearest point lies at α = (d_k − d_{k+1} + L) / 2L (the law of
    cosines), clipped to [0, 1], at squared distance d_k − α (d_k − d_{k+1} + L) + α² L; the
    nearest of the segments gives Q = k + α. A template reads its own index exactly, whatever
    the spacing of its neighbours, and a blend of two adjacent templates its blend weight —
    which the parabola through three distances gives only for templates evenly spaced on a
    line. Absent templates (infinite distances, padding) and repeated ones (gap 0) take no part;
    a query with no finite distance gets NaN.
    """
    d = np.asarray(distances, dtype=np.float64)
    g = np.asarray(gaps, dtype=np.float64)
    a, b = d[..., :-1], d[..., 1:]
    usable = np.isfinite(a) & np.isfinite(b) & np.isfinite(g) & (g > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        toward = a - b + g
        alpha = np.where(usable, np.clip(toward / (2.0 * g), 0.0, 1.0), 0.0)
        along = np.where(usable, a - alpha * toward + alpha * alpha * g, a)
    # the last template as a point of its own: reached by its segment where there is one
    ends = np.concatenate([along, d[..., -1:]], axis=-1)
    step = np.concatenate([alpha, np.zeros(d.shape[:-1] + (1,))], axis=-1)
    ends = np.where(np.isnan(ends), np.inf, ends)
    k = np.argmin(ends, axis=-1)
    residual = np.take_along_axis(ends, k[..., None], -1)[..., 0]
    q = k + np.take_along_axis(step, k[..., None], -1)[..., 0]
    return np.where(np.isfinite(residual), q, np.nan), np.maximum(residual, 0.0)


#: A rest floor is kept to at most this many layers.
MOST_REST_FLOOR = 1.0


def rest_floor(readings: np.ndarray, at_rest: np.ndarray, most: float = MOST_REST_FLOOR) -> tuple[np.ndarray, np.ndarray]:
    """Each region's rest floor: the highest Q (R,) it reads among frames where it is at rest, at
    most ``most`` layers, and the row (R,) that reads it (−1 where no frame is at rest).

    readings : (F, R) Q of F frames (NaN where hidden); at_rest : (F, R) whether the region is at
    rest in the frame. Why the highest: Q's offset at rest is not noise alone but what the rest of
    the face does to the region's patch (another expression's shading, a brow lowered over a
    lid; with the parabola, its bias where the templates' distances are not one), and every such
    frame seen should read 0.
    """
    q = np.where(np.asarray(at_rest, dtype=bool), np.asarray(readings, dtype=np.float64), np.nan)
    q = np.where(np.isfinite(q), q, -np.inf)
    row = np.argmax(q, axis=0)
    top = q[row, np.arange(q.shape[1])]
    found = np.isfinite(top)
    return np.where(found, np.clip(top, 0.0, most), 0.0), np.where(found, row, -1)


#: Q under which a reading's off-path ratio is taken at this Q (:func:`off_path_ratio`): a reading
#: at rest is off the path by its noise whatever its Q, and its ratio stays finite.
OFF_PATH_LEAST_Q = 0.01


def off_path_ratio(q: np.ndarray, distance: np.ndarray, first_gap: np.ndarray) -> np.ndarray:
    """(..., R) how far readings lie off their region's layer path for their Q: the squared
    distance to the path (:func:`classify_regions`' second output, (..., R)) over the first layer
    step's squared length (R,) and over Q² (Q at least :data:`OFF_PATH_LEAST_Q`).

    Why over Q²: another expression at weight w moves a region's patch w times its full change
    (to first order), so it reads w times its Q and lies w² times its squared distance off the
    path: the ratio is the expression's at any weight, while the region's own motion lies on the
    path (a ratio of noise over Q², small once Q is).
    """
    q = np.maximum(np.nan_to_num(np.asarray(q, dtype=np.float64), nan=0.0), OFF_PATH_LEAST_Q)
    return np.asarray(distance, dtype=np.float64) / (np.asarray(first_gap, dtype=np.float64) * q * q)


def conditional_floor(off_path: np.ndarray, rest_q: np.ndarray, rest_off_path: np.ndarray, tolerance: float,
                      noise: float = 0.0, most: float = MOST_REST_FLOOR) -> np.ndarray:
    """(..., R) each reading's rest floor: the highest Q (at most ``most``) among the at-rest
    readings (K, R) (NaN: not at rest or not seen) that are at most ``noise`` layers, or at most
    ``tolerance`` times as far off the path (:func:`off_path_ratio`) as the reading (..., R); 0
    where none is.

    An example at rest that reads above the noise because another expression moves the
    region's patch off its path only hides readings as far off the path, scaled to their Q, as
    it is: the same expression at a smaller weight (``tolerance`` for how far from linear the
    patch's change is). A reading on the path (the region's own motion) is hidden only by the
    noise's readings. Those hide every reading: noise moves a patch along the path as readily
    as off it, and the examples are too few to sample where. ``tolerance`` inf: every at-rest
    reading counts, the floor of :func:`rest_floor`.
    """
    rest_q = np.asarray(rest_q, dtype=np.float64)
    usable = np.isfinite(rest_q) & ~np.isnan(np.asarray(rest_off_path, dtype=np.float64))
    values = np.where(usable, np.clip(np.nan_to_num(rest_q), 0.0, most), 0.0)          # (K, R)
    if not np.isfinite(tolerance):
        return np.broadcast_to(values.max(axis=0, initial=0.0), np.shape(off_path)).copy()
    # noise-level readings hide every reading: noise lies off the path or along it alike
    limit = np.where(usable, np.where(values <= noise, 0.0, rest_off_path), np.inf)
    applies = limit <= tolerance * np.asarray(off_path, dtype=np.float64)[..., None, :]   # (..., K, R)
    return np.where(applies, values, 0.0).max(axis=-2, initial=0.0)


def above_rest(q: np.ndarray, floor: np.ndarray, layers) -> np.ndarray:
    """Q (..., R) measured from the regions' rest floors (R,), or each reading's own (..., R)
    (:func:`conditional_floor`): 0 at or below its floor, rising linearly to n − 1 at n − 1 (the
    extreme layer stays where it is), NaN kept. Monotone for one floor: the order of the frames
    above it is unchanged."""
    q = np.asarray(q, dtype=np.float64)
    floor = np.asarray(floor, dtype=np.float64)
    top = np.asarray(layers, dtype=np.float64) - 1.0
    scaled = np.clip((q - floor) * top / np.maximum(top - floor, 1e-12), 0.0, top)
    return np.where(np.isnan(q), np.nan, scaled)


def classify(patches: np.ndarray, templates: np.ndarray, indices: np.ndarray, weights: np.ndarray,
             shading: bool = True, interpolation: str = "segment") -> tuple[np.ndarray, np.ndarray]:
    """Layer index of the best of several samples of a patch.

    patches : (..., S, size, size) S samples (e.g. diagonal offsets) of one patch, raw intensities.
    templates : (n, C) normalised templates' coefficients; indices, weights : see :func:`match_distances`.

    Returns
    -------
    Q : (...) continuous layer index of the sample that matches the templates most closely
        (``interpolation``: see :func:`classify_regions`).
    distance : (...) that sample's squared distance to the path through the templates
        (``segment``) or to its best template (``parabola``).
    """
    if interpolation not in PEAK_INTERPOLATIONS:
        raise ValueError(f"interpolation {interpolation!r} is not one of {', '.join(PEAK_INTERPOLATIONS)}")
    coefficients = haar_coefficients(normalise_patches(patches, shading))
    d = match_distances(coefficients, templates, indices, weights)  # (..., S, n)
    if interpolation == "segment":
        gaps = np.diag(match_distances(np.asarray(templates)[1:], np.asarray(templates)[:-1], indices, weights))
        return _nearest_sample(*segment_index(d, np.broadcast_to(gaps, d.shape[:-1] + gaps.shape)))
    best = d.min(axis=-1)
    sample = np.argmin(best, axis=-1)
    chosen = np.take_along_axis(d, sample[..., None, None], axis=-2)[..., 0, :]
    return peak_index(chosen), np.take_along_axis(best, sample[..., None], -1)[..., 0]


class RegionBank:
    """Every region's templates in one padded array, for classifying all regions at once.

    templates : per region (n_r, C) normalised templates' coefficients; indices : per region its
    kept coefficients; weights : (C,). A region's coefficient weights are zero off its kept set
    and its missing templates (n_r below the most) are at infinite distance, so one batched
    product gives every region's distances over its own terms, as :func:`match_distances` does.

    masks : optional (R, C) bool, each region's stable texels (e.g. the template points every example shows well):
    its templates were normalised over them and are zero elsewhere (``normalise_patches`` with
    that mask), and a region's patches are matched on them alone (:func:`classify_regions`).
    None: every texel. orders : optional (R,) each region's shading surface
    (:func:`normalise_patches`; its templates were normalised by it); None: the plane for all.

    nuisance : optional, per region None or (k, size²) texel differences from its neutral
    template (normalised as the templates are, zero off its stable texels) that are not the
    region's own motion: what another expression does to its patch (:func:`rest_direction`). They
    are **explained away**: every distance (to a template, between adjacent templates) is measured
    with its component in their span (weighted, over the kept terms) left out, so a patch that
    differs from a template only by some of them matches it; on a partly seen sample, by the span
    of their seen texels. Each region's own layers still read their index as long as the span
    leaves part of every layer step (the build checks: :func:`kept_step_shares`).

    patches : optional, per region (n_r, size²) its templates' samples before normalising. A
    partly seen sample's templates are then normalised from them over its seen texels, exactly as
    the sample is; without them, from the normalised templates (their surface over the stable
    texels put back, the seen texels' divided out), which is close only while most of a patch is
    seen (a lid over half the eyeball read 0.5 layer of gaze that way, 0.07 exactly).

    relative : each region's patches are shaded relative to its neutral template (the first,
    as stored: :func:`normalise_patches`' ``reference``; its templates were normalised so) instead
    of by a surface through each patch alone; with ``shading`` off, by their mean as before.
    """

    MASK_CACHE = 1024  # (region, mask) pairs whose normalised templates are kept: 12 kB each at 6 layers of 16²

    def __init__(self, templates, indices, weights, masks=None, orders=None, nuisance=None, patches=None,
                 relative: bool = False):
        self._mask_cache: dict = {}
        R = len(templates)
        C = len(weights)
        self.orders = np.ones(R, dtype=np.int64) if orders is None else np.asarray(orders, dtype=np.int64).reshape(R)
        self.masks = np.ones((R, C), dtype=bool) if masks is None else np.asarray(masks, dtype=bool).reshape(R, C)
        if not self.masks.any(axis=1).all():
            raise ValueError("a region's stable mask is empty")
        self.masked = not self.masks.all()
        self.mask_count = self.masks.sum(axis=1).astype(np.float64)  # (R,)
        n_max = max(len(t) for t in templates)
        self.weights = np.zeros((R, C))
        self.templates = np.zeros((R, n_max, C))
        self.absent = np.zeros((R, n_max), dtype=bool)
        for r, (t, idx) in enumerate(zip(templates, indices)):
            self.weights[r, idx] = np.asarray(weights, dtype=np.float64)[idx]
            self.templates[r, :len(t)] = t
            self.absent[r, len(t):] = True
        self.wt = self.weights[:, None, :] * self.templates  # (R, n, C)
        self.tt = (self.wt * self.templates).sum(axis=-1)      # (R, n)
        step = np.diff(self.templates, axis=1)                 # (R, n − 1, C) between adjacent layers
        self.gaps = np.where(self.absent[:, 1:], np.inf, np.einsum("rkc,rc->rk", step * step, self.weights))
        H, _ = haar_matrix(int(round(np.sqrt(C))))
        self.pixels = self.templates @ H                         # (R, n, size²) the normalised templates themselves
        # shading relative to the neutral template (None: to each patch's own surface)
        self.reference = self.pixels[:, 0].copy() if relative else None   # (R, size²)
        self.raw = None                                          # (R, n, size²) their samples before normalising
        if patches is not None:
            if len(patches) != R or any(np.shape(p) != (len(t), C) for p, t in zip(patches, templates)):
                raise ValueError("patches are not (templates, texels) for every region")
            self.raw = np.ones((R, n_max, C))                     # (absent templates: never matched)
            for r, p in enumerate(patches):
                self.raw[r, :len(p)] = p
        # without the samples: the normalised templates' surfaces over the stable texels
        # (:func:`normalise_patches` of a normalised template: near 1), with shading (each region's
        # own surface) and without (the mean: templates stored divided by their mean are 1 on
        # average exactly), which a partly seen sample's templates put back (_masked_templates)
        self.plane_all = {}
        for shading in (True, False) if self.raw is None else ():
            self.plane_all[shading] = np.empty_like(self.pixels)
            for order, rows in self.order_groups(shading):
                self.plane_all[shading][rows] = _masked_plane(self.pixels[rows], self.masks[rows][:, None, :], order)[0]
        # the Haar rows of each region's kept coefficients (padded with zero-weight rows)
        kept = max(len(i) for i in indices)
        self.kept_rows = np.zeros((R, kept, C))
        self.kept_weights = np.zeros((R, kept))
        for r, idx in enumerate(indices):
            self.kept_rows[r, :len(idx)] = H[idx]
            self.kept_weights[r, :len(idx)] = np.asarray(weights, dtype=np.float64)[idx]
        # explained-away directions: per region None or (C, m), columns whose products with a
        # coefficient difference are its weighted components in their span (orthonormal there)
        self.nuisance = [None] * R if nuisance is None else [None if n is None or len(n) == 0
                                                              else np.asarray(n, dtype=np.float64).reshape(len(n), -1)
                                                              for n in nuisance]
        if len(self.nuisance) != R:
            raise ValueError(f"nuisance has {len(self.nuisance)} regions, the templates {R}")
        self.spans = [None if n is None else _weighted_span(n @ H.T, self.weights[r]) for r, n in enumerate(self.nuisance)]
        for r, span in enumerate(self.spans):
            if span is not None:
                self.gaps[r] = np.where(np.isfinite(self.gaps[r]),
                                        np.maximum(self.gaps[r] - _span_norms(step[r], span), 0.0), self.gaps[r])

    def reference_of(self, region, shape: tuple = (-1,)):
        """The neutral templates a sample of ``region`` is shaded relative to, each (size²,) or
        reshaped to ``shape``, or None (the mean alone, without ``shading``, ignores them:
        :func:`normalise_patches`)."""
        if self.reference is None:
            return None
        ref = self.reference[region]
        return ref.reshape(ref.shape[:-1] + tuple(shape))

    def order_groups(self, shading: bool = True):
        """(order, region indices) for each shading surface the regions use (0, the mean, for all
        without ``shading``)."""
        orders = self.orders if shading else np.zeros_like(self.orders)
        return [(int(o), np.flatnonzero(orders == o)) for o in np.unique(orders)]

    def masked_distances(self, normalised: np.ndarray, mask: np.ndarray, region: np.ndarray,
                         shading: bool = True, with_gaps: bool = False):
        """(M, n) distances of partly seen patches to their region's templates over the seen texels.

        normalised : (M, size, size) patches normalised over their seen texels; mask : (M, size,
        size) the seen texels (within the region's stable ones); region : (M,) each patch's
        region. The templates are normalised over the same texels (a plane fitted over part of a
        patch takes up part of its pattern: patch and template alike), and compared with the
        patch on those texels only (the difference there, zero elsewhere, in the region's Haar
        terms), scaled by the region's stable texels over those seen so that partly and wholly
        seen samples compare. With every stable texel seen this is :meth:`distances`.
        ``with_gaps``: also (M, n − 1) the distances between adjacent templates so normalised
        (:func:`segment_index`), as :attr:`gaps` is for the wholly seen.
        """
        M = len(region)
        m = np.asarray(mask, dtype=bool).reshape(M, 1, -1)
        templates = self._masked_templates(m[:, 0], np.asarray(region), shading)  # (M, n, size²)
        diff = np.asarray(normalised).reshape(M, 1, -1) - templates              # 0 off the mask
        scale = (self.mask_count[region] / np.maximum(m.sum(axis=(1, 2)), 1.0))[:, None]
        steps = np.diff(templates, axis=1) if with_gaps else None
        d = self._kept_norms(diff, region, m[:, 0]) * scale
        d = np.where(self.absent[region], np.inf, d)
        if not with_gaps:
            return d
        gaps = self._kept_norms(steps, region, m[:, 0]) * scale
        return d, np.where(self.absent[region][:, 1:], np.inf, gaps)

    def _kept_norms(self, diff: np.ndarray, region: np.ndarray, seen: np.ndarray | None = None) -> np.ndarray:
        """(M, k) weighted squared norms of texel differences (M, k, size²) in their regions' kept
        Haar terms, less their components in the region's explained-away span over the ``seen``
        texels (M, size²)."""
        out = np.empty(diff.shape[:2])
        for r in np.unique(region):  # each region's kept Haar rows on its own patches (no gathered copies)
            rows = region == r
            c = diff[rows] @ self.kept_rows[r].T                                  # (m, k, kept)
            out[rows] = (c * c) @ self.kept_weights[r]
            if self.nuisance[r] is not None:
                # the directions over each sample's seen texels (all without ``seen``), in the same kept terms
                dirs = self.nuisance[r][None] if seen is None else self.nuisance[r][None] * seen[rows][:, None, :]
                seen_dirs = dirs @ self.kept_rows[r].T                                    # (m or 1, j, kept)
                seen_dirs = np.broadcast_to(seen_dirs, (int(rows.sum()),) + seen_dirs.shape[1:])
                root = np.sqrt(self.kept_weights[r])
                basis = _orthonormal_columns(np.swapaxes(seen_dirs * root, 1, 2))              # (m, kept, j)
                out[rows] = np.maximum(out[rows] - (((c * root) @ basis) ** 2).sum(-1), 0.0)
        return out

    def _masked_templates(self, masks: np.ndarray, region: np.ndarray, shading: bool) -> np.ndarray:
        """(M, n, size²) each region's templates normalised over a mask (M, size²), zero off it.

        With the templates' samples (``patches``) they are normalised over the mask as a sample is
        (exact). Else from the stored templates, normalised over the region's stable texels (by
        their surface over those): that surface back, the seen texels' surface out (the same with
        all seen; close while most of the patch is seen). What a
        camera cannot see of a region (a fold turned edge-on, a brow over the lid) changes slowly,
        so the same masks come back frame after frame: each (region, mask) is normalised once and
        kept (up to ``MASK_CACHE`` of them)."""
        keys = [(int(r), int(self.orders[r]) if shading else 0, k.tobytes()) for r, k in zip(region, masks)]
        cache = self._mask_cache
        # each key looked up once: another thread classifying other frames may clear the cache
        kept, new = {}, {}
        for i, key in enumerate(keys):
            if key in kept or key in new:
                continue
            hit = cache.get(key)
            if hit is None:
                new[key] = i
            else:
                kept[key] = hit
        found = {}
        if new:
            first = np.fromiter(new.values(), dtype=np.int64, count=len(new))
            m = masks[first][:, None, :]
            # from the samples where the model keeps them (exact), else from the normalised templates
            templates = (self.pixels if self.raw is None else self.raw)[region[first]]
            plane_seen, mean = np.empty_like(templates), np.empty(templates.shape[:-1] + (1,))
            order = np.array([k[1] for k in new])
            for o in np.unique(order):
                rows = order == o
                plane_seen[rows], mean[rows] = _masked_plane(templates[rows], m[rows], int(o),
                                                             self.reference_of(region[first][rows], (1, -1)))
            floor = np.maximum(0.1 * np.abs(mean), 1e-6)
            # (a surface fitted against the reference maps the stored neutral onto itself: nothing to put back)
            exact = self.raw is not None or (self.reference is not None and shading)
            stored = 1.0 if exact else self.plane_all[bool(shading)][region[first]]
            normalised = np.where(m, templates * stored / np.maximum(plane_seen, floor), 0.0)
            found = dict(zip(new, normalised))
        out = np.stack([found[k] if k in found else kept[k] for k in keys])
        if len(cache) + len(found) > self.MASK_CACHE:
            cache.clear()
        cache.update(found)
        return out

    def distances(self, coefficients: np.ndarray) -> np.ndarray:
        """(..., R, S, n) distances of coefficients (..., R, S, C) to every region's templates."""
        q = np.asarray(coefficients, dtype=np.float64)
        qq = np.einsum("...rsc,rc->...rs", q * q, self.weights)
        qt = np.einsum("...rsc,rnc->...rsn", q, self.wt)
        d = qq[..., None] - 2.0 * qt + self.tt[:, None, :]
        for r, span in enumerate(self.spans):
            if span is not None:
                part = (q[..., r, :, None, :] - self.templates[r]) @ span   # (..., S, n, m)
                d[..., r, :, :] = np.maximum(d[..., r, :, :] - (part * part).sum(-1), 0.0)
        return np.where(self.absent[:, None, :], np.inf, d)


def _weighted_span(directions: np.ndarray, weights: np.ndarray) -> np.ndarray | None:
    """(C, m) columns V with V.T @ x the components of a coefficient vector x (C,) in an
    orthonormal basis of the span of ``directions`` (k, C) under the metric diag(weights); None
    where they span nothing."""
    root = np.sqrt(np.asarray(weights, dtype=np.float64))
    basis = _orthonormal_columns((np.asarray(directions, dtype=np.float64) * root).T[None])[0]
    basis = basis[:, np.abs(basis).sum(axis=0) > 0]
    return None if basis.shape[1] == 0 else root[:, None] * basis


def _orthonormal_columns(a: np.ndarray) -> np.ndarray:
    """Orthonormal bases (..., n, k) of the column spaces of a stack of matrices (..., n, k),
    columns that add nothing (a direction within the others' span, or zero) set to zero."""
    q, r = np.linalg.qr(a)
    diag = np.abs(np.diagonal(r, axis1=-2, axis2=-1))                      # (..., k)
    scale = np.abs(r).max(axis=(-2, -1), keepdims=True)[..., 0]            # (..., 1)
    return q * (diag > 1e-9 * np.maximum(scale, 1e-300))[..., None, :]


def _span_norms(diff: np.ndarray, span: np.ndarray) -> np.ndarray:
    """(...) squared norms of coefficient differences (..., C) within a span (:func:`_weighted_span`)."""
    part = np.asarray(diff) @ span
    return (part * part).sum(-1)


def rest_direction(bank: RegionBank, patch: np.ndarray, region: int, shading: bool = True) -> np.ndarray:
    """(size²,) the texel difference of a wholly seen patch (size, size) of ``region`` (raw
    intensities, e.g. an example frame where the region is at rest) from its neutral template,
    both normalised as the region's templates are (zero off its stable texels): a direction to
    explain away (:class:`RegionBank`'s ``nuisance``)."""
    patch = np.asarray(patch, dtype=np.float64)
    order = int(bank.orders[region]) if shading else 0  # as _normalise_regions normalises the region
    stable = bank.masks[region].reshape(patch.shape) if bank.masked else None
    normalised = normalise_patches(patch, order, stable, bank.reference_of(region, patch.shape)).reshape(-1)
    return np.where(bank.masks[region], normalised - bank.pixels[region, 0], 0.0)


def kept_step_shares(bank: RegionBank, region: int, directions: np.ndarray) -> np.ndarray:
    """(n − 1,) the share of each of a region's layer steps (squared weighted distance between
    adjacent templates) left once ``directions`` (k, size²) are explained away: 1 where they are
    unlike the region's motion, near 0 where they would take a layer step with them."""
    H, _ = haar_matrix(int(round(np.sqrt(bank.templates.shape[-1]))))
    span = _weighted_span(np.asarray(directions, dtype=np.float64) @ H.T, bank.weights[region])
    n = int((~bank.absent[region]).sum())
    step = np.diff(bank.templates[region, :n], axis=0)
    whole = (step * step) @ bank.weights[region]
    kept = whole if span is None else whole - _span_norms(step, span)
    return np.clip(kept / np.maximum(whole, 1e-300), 0.0, 1.0)


def classify_regions(patches: np.ndarray, bank: RegionBank, shading: bool = True, seen: np.ndarray | None = None,
                     min_seen: float = 0.5, interpolation: str = "segment") -> tuple[np.ndarray, np.ndarray]:
    """:func:`classify` of every region at once: patches (..., R, S, size, size) → Q (..., R) and
    the chosen sample's smallest distance (..., R).

    A region's patches are normalised and matched over its stable texels (the bank's masks; all
    by default). seen : (..., R, S, size, size) which texels of the samples the camera sees
    (None: all). A sample with some stable texels hidden is matched on its seen ones
    (:meth:`RegionBank.masked_distances`); a sample with under ``min_seen`` of its stable texels
    seen takes no part, and a region none of whose samples does gets Q NaN (the caller holds
    its last value).

    ``interpolation`` (:data:`PEAK_INTERPOLATIONS`): ``segment``, the nearest point of the path
    through the templates (:func:`segment_index`), the sample nearest it kept, its squared
    distance returned; ``parabola``, the sample nearest a template kept and the parabola's vertex
    there (:func:`peak_index`), that template's distance returned.
    """
    if interpolation not in PEAK_INTERPOLATIONS:
        raise ValueError(f"interpolation {interpolation!r} is not one of {', '.join(PEAK_INTERPOLATIONS)}")
    coefficients = haar_coefficients(_normalise_regions(patches, bank, shading))
    d = bank.distances(coefficients)  # (..., R, S, n)
    if interpolation == "segment":
        gaps = np.broadcast_to(bank.gaps[:, None, :], d.shape[:-1] + (d.shape[-1] - 1,))
        if seen is not None:
            d, gaps = _distances_of_seen(patches, seen, bank, shading, d, min_seen, gaps)
        return _nearest_sample(*segment_index(d, gaps))              # (..., R, S) → (..., R)
    if seen is not None:
        d = _distances_of_seen(patches, seen, bank, shading, d, min_seen)
    best = d.min(axis=-1)
    sample = np.argmin(best, axis=-1)
    chosen = np.take_along_axis(d, sample[..., None, None], axis=-2)[..., 0, :]
    usable = np.isfinite(np.take_along_axis(best, sample[..., None], -1)[..., 0])
    q = np.full(usable.shape, np.nan)
    q[usable] = peak_index(chosen[usable])
    return q, np.take_along_axis(best, sample[..., None], -1)[..., 0]


#: The shading ramp of :func:`shading_tilt_readings`: ± this share from a template's middle to its
#: edge (a side light's change of gradient over a small patch of a curved surface).
SHADING_TILT = 0.15


def shading_tilt_readings(bank: RegionBank, neutral: np.ndarray, shading: bool = True, tilt: float = SHADING_TILT,
                          interpolation: str = "segment") -> np.ndarray:
    """(R,) the largest Q each region's neutral template samples (R, size, size) read (before any
    rest floor) multiplied by a linear shading ramp of ± ``tilt`` from the middle to the edge, along
    x or y, each way: 0 where the shading surface takes such a light out. Divided by the surface
    through the patch alone, it is exactly 0 only over an even texture (a dark iris whose one side
    is lit more looks moved); fitted against the neutral layer (``relative`` banks), over any."""
    neutral = np.asarray(neutral, dtype=np.float64)
    R, s = len(neutral), neutral.shape[-1]
    ramp = (np.arange(s) - 0.5 * (s - 1)) / (0.5 * (s - 1))
    fields = [ramp[None, :], ramp[:, None]]
    lit = np.stack([neutral * (1.0 + sign * tilt * field) for sign in (-1.0, 1.0) for field in fields])  # (4, R, s, s)
    samples = np.broadcast_to(lit[:, :, None], (len(lit), R, len(DIAGONAL_OFFSETS), s, s))
    q, _ = classify_regions(samples, bank, shading, None, interpolation=interpolation)
    return np.nan_to_num(q).max(axis=0)


def _nearest_sample(q: np.ndarray, residual: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Q (...) and squared distance (...) of the sample (last axis of :func:`segment_index`'s
    outputs) nearest the path through the templates; NaN and infinite where no sample reads one."""
    sample = np.argmin(np.where(np.isnan(q), np.inf, residual), axis=-1)[..., None]
    q = np.take_along_axis(q, sample, -1)[..., 0]
    return q, np.where(np.isnan(q), np.inf, np.take_along_axis(residual, sample, -1)[..., 0])


def _normalise_regions(patches: np.ndarray, bank: RegionBank, shading: bool) -> np.ndarray:
    """Patches (..., R, S, size, size) normalised over their region's stable texels, each region
    by its own shading surface (:meth:`RegionBank.order_groups`)."""
    size = patches.shape[-1]
    stable = bank.masks.reshape(-1, 1, size, size)  # (R, 1, size, size): every sample alike
    groups = bank.order_groups(shading)
    if len(groups) == 1:
        return normalise_patches(patches, groups[0][0], stable if bank.masked else None,
                                 bank.reference_of(slice(None), (1, size, size)))
    out = np.empty(np.shape(patches))
    for order, rows in groups:
        out[..., rows, :, :, :] = normalise_patches(patches[..., rows, :, :, :], order, stable[rows],
                                                    bank.reference_of(rows, (1, size, size)))
    return out


def _distances_of_seen(patches, seen, bank: RegionBank, shading: bool, d: np.ndarray, min_seen: float, gaps=None):
    """Distances (..., R, S, n) with the partly seen samples' over their seen texels, and those
    of the samples seen too little infinite; with ``gaps`` (..., R, S, n − 1) (the templates'
    adjacent distances) those too, the partly seen samples' over their seen texels."""
    size = patches.shape[-1]
    stable = bank.masks.reshape(-1, 1, size, size)
    seen = np.asarray(seen, dtype=bool) & stable                # texels off a region's stable set never count
    count = seen.sum(axis=(-2, -1))                             # (..., R, S)
    fraction = count / bank.mask_count[:, None]
    partial = (fraction >= min_seen) & (count < bank.mask_count[:, None])
    d = np.where((fraction < min_seen)[..., None], np.inf, d)
    if partial.any():
        idx = np.nonzero(partial)
        region = idx[-2]
        picked, picked_seen = patches[idx], seen[idx]
        part = np.empty(picked.shape)  # (M, size, size), each by its region's surface
        orders = bank.orders[region] if shading else np.zeros_like(region)
        for o in np.unique(orders):
            rows = orders == o
            part[rows] = normalise_patches(picked[rows], int(o), picked_seen[rows],
                                           bank.reference_of(region[rows], (size, size)))
        if gaps is None:
            d[idx] = bank.masked_distances(part, seen[idx], region, shading)
        else:
            gaps = np.array(gaps)  # (a broadcast view before)
            d[idx], gaps[idx] = bank.masked_distances(part, seen[idx], region, shading, with_gaps=True)
    return d if gaps is None else (d, gaps)


def hold_and_decay(values: np.ndarray, visible: np.ndarray, times: np.ndarray, decay: float,
                   well_seen: np.ndarray | None = None) -> np.ndarray:
    """Hidden samples keep the last value read while the region was seen well, decaying
    exponentially toward 0 (neutral) with the time since that reading.

    values, visible : (T, R); times : (T,) seconds; decay : time constant in seconds (0: drop to
    neutral at once); well_seen : (T, R) the visible samples a hidden stretch may hold (default:
    every visible one) — a region going out of view through a partial occlusion (a lid closing
    over the eyeball) reads its last visible frames from a part of its template, and holding
    that reading would carry it through the whole hidden stretch. Before a region is first seen
    well it is neutral.
    """
    values = np.asarray(values, dtype=np.float64)
    visible = np.asarray(visible, dtype=bool)
    source = visible if well_seen is None else visible & np.asarray(well_seen, dtype=bool)
    out = np.zeros_like(values)
    last = np.zeros(values.shape[1])
    last_time = np.full(values.shape[1], -np.inf)
    for t in range(values.shape[0]):
        last = np.where(source[t], values[t], last)
        last_time = np.where(source[t], times[t], last_time)
        age = times[t] - last_time
        factor = np.exp(-age / decay) if decay > 0 else (age == 0).astype(np.float64)
        out[t] = np.where(visible[t], values[t], last * np.where(np.isfinite(age), factor, 0.0))
    return out


def drop_short_events(q: np.ndarray, times: np.ndarray, min_event: float, below: float = 1.0) -> np.ndarray:
    """Q (T, R) with each brief departure from rest set back to rest: a run of frames above rest
    (Q > 0) with rest on both sides, seen for less than ``min_event`` seconds (from its first
    frame's time to its last's, plus the take's median frame step: k frames of an even take last
    k steps) and never reaching ``below`` (one layer by default).

    Faces do not move that fast (a blink, the quickest action, takes about a tenth of a second),
    but a per-frame classifier reads the image noise of one or two frames as a small motion; on a
    region at rest for most of a take those readings are what the stream would show. The time, not
    a frame count, sets what is brief, so 24, 30 or 60 Hz footage is treated alike. A run at the
    take's first or last frame is kept (its length is not known), and so is one reaching a layer
    (a real fast motion: only small readings are taken for noise). ``min_event`` 0 keeps all.
    """
    q = np.array(q, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64)
    T = q.shape[0]
    steps = np.diff(times)
    step = float(np.median(steps)) if steps.size else 0.0
    if min_event <= 0 or T < 3 or not step > 0:
        return q
    column, start, stop = column_runs(q > 0)
    # a run of k frames lasts k steps; at exactly min_event (a frame rate it divides) it is kept
    brief = ((start > 0) & (stop < T) & (times[stop - 1] - times[start] + step < min_event * (1.0 - 1e-9)))
    column, start, length = column[brief], start[brief], (stop - start)[brief]
    if not length.size:
        return q
    frames = np.repeat(start, length) + offsets_within(length)
    columns = np.repeat(column, length)
    peak = np.maximum.reduceat(q[frames, columns], np.cumsum(length) - length)  # runs are never empty
    small = np.repeat(peak < below, length)
    q[frames[small], columns[small]] = 0.0
    return q


def bilinear_sample(image: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of an image (H, W[, C]) at pixel positions xy (..., 2) (x right, y down,
    pixel centres at integers); returns the values (...[, C]) and whether each position lies
    inside the image (outside ones are clamped to the border)."""
    image = np.asarray(image)
    H, W = image.shape[:2]
    x, y = xy[..., 0], xy[..., 1]
    inside = np.isfinite(x) & np.isfinite(y) & (x >= -0.5) & (x <= W - 0.5) & (y >= -0.5) & (y <= H - 0.5)
    x = np.clip(np.nan_to_num(x), 0.0, W - 1.0)
    y = np.clip(np.nan_to_num(y), 0.0, H - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), W - 2) if W > 1 else np.zeros_like(x, dtype=np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), H - 2) if H > 1 else np.zeros_like(y, dtype=np.int64)
    fx, fy = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    if image.ndim == 3:
        fx, fy = fx[..., None], fy[..., None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy, inside


def facing(normals: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Cosine (...) between surface normals (..., 3) and the direction to a camera at the origin
    (camera coordinates, points (..., 3)): > 0 faces the camera."""
    n = normals / np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-30)
    to_camera = -points / np.maximum(np.linalg.norm(points, axis=-1, keepdims=True), 1e-30)
    return (n * to_camera).sum(axis=-1)
