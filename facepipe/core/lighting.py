"""The light of a frame, fitted to the intensities of points of known normal and albedo.

Classification divides a region's patches by their shading, and the layered texture is relit
with it, so each frame's light is fitted to the footage at points whose normals the geometry
gives and whose albedo the neutral example gave:

* **nine spherical-harmonic terms** (:func:`fit_light`, :func:`light_shading`): the space a
  Lambertian surface's shading under any distant light lies in to within a few percent
  (Ramamoorthi and Hanrahan 2001), fitted by least squares reweighted (Cauchy) so that what
  the model does not hold (an eye, a shadow, a wrinkle) does not pull it; smooth, so it rounds
  off the kink of a light's terminator;
* **an ambient term and two distant lights** (:func:`fit_point_light`, :func:`point_shading`),
  each light's Lambertian cosine clamped at zero (its own shadow side): a key light, and a fill
  light from the other side kept only where it passes the Bayesian information criterion,
  fitted by robust (Cauchy) Levenberg–Marquardt, every frame of a batch settling on its own.

Pure functions over arrays.
"""

from __future__ import annotations

import numpy as np

__all__ = ["LIGHT_MODELS", "sh_basis", "fit_light", "light_residual", "light_shading", "sh_quadratic",
           "point_shading", "fit_point_light", "usable_median"]


def sh_basis(normals: np.ndarray) -> np.ndarray:
    """(..., 9) the real spherical harmonics up to second order (unnormalised) of unit normals
    (..., 3): the space a Lambertian surface's shading under any distant light lies in, to within
    a few percent (Ramamoorthi and Hanrahan 2001)."""
    x, y, z = normals[..., 0], normals[..., 1], normals[..., 2]
    return np.stack([np.ones_like(x), x, y, z, x * y, x * z, y * z, x * x - y * y, 3.0 * z * z - 1.0], axis=-1)


def fit_light(values: np.ndarray, albedo: np.ndarray, normals: np.ndarray, iterations: int = 4) -> np.ndarray:
    """The light (..., 9) that best explains intensities (..., K) of points of known albedo (K,)
    and unit normals (..., K, 3): values ≈ albedo · sh_basis(normals) @ light, by least squares
    reweighted (Cauchy, scale from the median absolute residual) so that what the model does not
    hold — an eye, teeth, a shadow, a wrinkle — does not pull the fit. Points with a non-finite
    value are left out; with fewer than 27 left the light is uniform. Leading axes (frames) are
    fitted independently, in the same products."""
    values = np.asarray(values, dtype=np.float64)
    lead = values.shape[:-1]
    values = values.reshape((-1, values.shape[-1]))
    normals = np.asarray(normals, dtype=np.float64).reshape(values.shape + (3,))
    ok = np.isfinite(values) & np.isfinite(albedo) & np.isfinite(normals).all(axis=-1)
    light = np.zeros(values.shape[:1] + (9,))
    light[:, 0] = 1.0  # too few points seen (a face turned away) to tell a light: a uniform one
    enough = ok.sum(axis=-1) >= 27
    if enough.any():
        light[enough] = _fit_light_rows(values[enough], albedo, normals[enough], ok[enough], iterations)
    return light.reshape(lead + (9,))


def _fit_light_rows(values, albedo, normals, ok, iterations: int) -> np.ndarray:
    A = np.where(ok[..., None], np.nan_to_num(albedo)[:, None] * sh_basis(np.nan_to_num(normals)), 0.0)  # (B, K, 9)
    b = np.where(ok, values, 0.0)
    w = ok.astype(np.float64)
    # a little ridge towards no directional part keeps a fit over few normals' directions bounded
    ridge = 1e-6 * (A * A).sum(axis=(-2, -1)) / ok.sum(axis=-1)
    penalty = ridge[:, None, None] * np.diag(np.r_[0.0, np.ones(8)])
    light = np.zeros(values.shape[:1] + (9,))
    for _ in range(iterations):
        Aw = A * w[..., None]
        # products through BLAS (matmul), not einsum's loops: a tenth of the time
        normal = Aw.swapaxes(-1, -2) @ A + penalty * w.sum(axis=-1)[:, None, None]
        rhs = (Aw.swapaxes(-1, -2) @ b[..., None])[..., 0]
        light = np.stack([np.linalg.lstsq(n, r, rcond=None)[0] for n, r in zip(normal, rhs)])
        r = b - (A @ light[..., None])[..., 0]
        # every row here has points: the median over them is finite
        scale = _robust_scale(r, ok)[:, None]
        w = ok / (1.0 + (r / (2.385 * scale)) ** 2)
    return light


#: How a frame's light is modelled (``[appearance] light_model``): ``point``, an ambient term and
#: two distant lights (a key and a fill, which may be none) whose Lambertian cosines are clamped
#: at zero (:func:`fit_point_light`); ``sh9``, the nine spherical-harmonic terms (:func:`fit_light`).
LIGHT_MODELS = ("point", "sh9")


def usable_median(values: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """The median (B,) of each row of ``values`` (B, K) over its ``usable`` entries (NaN for a row
    with none): with every entry usable the plain median, else the same number as nanmedian
    without its row-by-row loop. The unusable entries are set to infinity, so a row's middle
    order statistics are its usable entries'; one partial sort of all rows puts every row's
    middle positions in place (a full sort of the rows takes about twice as long)."""
    if usable.all():
        return np.median(values, axis=-1)
    count = usable.sum(axis=-1)
    low, high = np.maximum(count - 1, 0)[:, None] // 2, (count // 2)[:, None]
    ordered = np.partition(np.where(usable, values, np.inf), np.unique(np.r_[low[:, 0], high[:, 0]]), axis=-1)
    middle = np.take_along_axis(ordered, low, axis=-1)[:, 0] + np.take_along_axis(ordered, high, axis=-1)[:, 0]
    return np.where(count > 0, 0.5 * middle, np.nan)


def light_residual(values: np.ndarray, albedo: np.ndarray, normals: np.ndarray, light: np.ndarray) -> np.ndarray:
    """(B,) how much of each frame's brightness its light leaves unexplained: the median, over the
    points the frame shows (finite ``values`` (B, K)), of |value − albedo · shading| / (albedo · shading),
    albedo (K,), unit normals (B, K, 3), each frame's light (B, 9) nine terms (:func:`fit_light`)
    or (B, 1 + 3k) an ambient term and distant lights (:func:`fit_point_light`).

    Where the geometry lies on the face in the image this is the light model's own misfit, the
    image noise and what expressions change (a few percent); where it misses the face (the geometry
    of another take or head pose, frames shifted against the footage, another camera) the points
    sample other skin, hair or background and it grows several times over."""
    values = np.asarray(values, dtype=np.float64)
    light = np.asarray(light, dtype=np.float64)
    clean = np.nan_to_num(np.asarray(normals, dtype=np.float64))
    if light.shape[-1] == 9:
        shading = np.einsum("bkc,bc->bk", sh_basis(clean), light)
    else:
        shading = np.stack([point_shading(clean[b], light[b]) for b in range(len(light))]) if len(light) \
            else np.zeros(values.shape)
    predicted = np.asarray(albedo, dtype=np.float64) * shading
    usable = np.isfinite(values) & np.isfinite(predicted) & (predicted > 0) & np.isfinite(normals).all(axis=-1)
    relative = np.abs(np.where(usable, values, 0.0) - predicted) / np.where(usable, predicted, 1.0)
    return usable_median(relative, usable)


def light_shading(normals: np.ndarray, light: np.ndarray, floor: float = 0.05) -> np.ndarray:
    """Shading (...) of unit normals (..., 3) under a light: nine terms (9,) from :func:`fit_light`
    or an ambient term and distant lights (1 + 3k,) from :func:`fit_point_light`; kept above ``floor``
    times its median (a point the light fit calls dark is not divided into noise)."""
    light = np.asarray(light, dtype=np.float64)
    shade = sh_quadratic(normals, light) if len(light) == 9 else point_shading(normals, light)
    return np.maximum(shade, floor * max(float(np.median(shade)), 1e-9))


def point_shading(normals: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Shading (...) of unit normals (..., 3) under an ambient term ``light[0]`` and distant
    lights ``light[1:4]``, ``light[4:7]``, … (each its direction times its strength):
    ambient + Σ max(n·l, 0). A surface facing away from a light gets nothing from it (its
    attached shadow)."""
    light = np.asarray(light, dtype=np.float64)
    normals = np.asarray(normals)
    shade = np.full(normals.shape[:-1], light[0])
    for k in range(1, len(light), 3):
        shade = shade + np.maximum(normals @ light[k:k + 3], 0.0)
    return shade


def fit_point_light(values: np.ndarray, albedo: np.ndarray, normals: np.ndarray, start: np.ndarray | None = None,
                    iterations: int = 12) -> np.ndarray:
    """The ambient term and two distant lights (..., 7) (:func:`point_shading`: a key light and a
    fill light, which may be none) that best explain intensities (..., K) of points of known
    albedo (K,) and unit normals (..., K, 3).

    The nine-term light (:func:`fit_light`) is a smooth approximation of this model: where a
    light grazes the face, its terminator (the line n·l = 0 across a cheek or a fold) is a kink
    that nine terms round off by up to a third of the shading, and dividing by them leaves a
    crease-like band in a patch. Here the kinks are modelled, by robust (Cauchy, as
    :func:`fit_light`) Levenberg–Marquardt:

    * one light, started from the nine-term fit's first-order band (``start`` (..., 9) where
      already fitted) at two strengths of the directional part (the nine terms spread a clamped
      cosine's power over the constant and the quadratic band);
    * then a second light beside it, started at 0.3 of its strength from the other side (the
      key's direction mirrored left–right, and both left–right and up–down), where a set puts
      its fill light.

    Of each stage's starts the one with the smallest median residual is kept, and the fill light
    only where it passes the Bayesian information criterion on the Cauchy likelihood (at the one
    light's scale): under one light, the one light alone. At most ``iterations`` steps each,
    fewer once every step is under a millionth of the light. Leading axes (frames) are fitted
    independently in the same products (each frame's result is the one it gets alone); with
    fewer than 27 usable points the light is uniform."""
    values = np.asarray(values, dtype=np.float64)
    lead = values.shape[:-1]
    values = values.reshape((-1, values.shape[-1]))
    normals = np.asarray(normals, dtype=np.float64).reshape(values.shape + (3,))
    albedo = np.asarray(albedo, dtype=np.float64)
    sh = fit_light(values, albedo, normals) if start is None else np.asarray(start, dtype=np.float64).reshape(-1, 9)
    ok = np.isfinite(values) & np.isfinite(albedo) & np.isfinite(normals).all(axis=-1)
    light = np.zeros(values.shape[:1] + (7,))
    light[:, 0] = 1.0
    enough = ok.sum(axis=-1) >= 27
    if enough.any():
        light[enough] = _fit_two_lights(values[enough], albedo, normals[enough], ok[enough], sh[enough], iterations)
    return light.reshape(lead + (7,))


def _fit_two_lights(values, albedo, normals, ok, sh, iterations: int) -> np.ndarray:
    B = len(values)
    # one light, from the nine terms' first-order band at two strengths
    d = sh[:, None, 1:4] * 2.0 * np.array([1.0, 0.6])[None, :, None]  # (B, 2, 3)
    ambient = np.maximum(sh[:, None, 0] - 0.5 * np.linalg.norm(d, axis=-1), 0.05 * sh[:, None, 0])
    one, r_one, scale = _robust_lm(values, albedo, normals, ok, np.concatenate([ambient[..., None], d], axis=-1),
                                   iterations)
    pick = scale.argmin(axis=1)
    one = np.concatenate([one, np.zeros((B, 2, 3))], axis=-1)[np.arange(B), pick]  # (B, 7)
    r_one, one_scale = r_one[np.arange(B), pick], scale[np.arange(B), pick]
    # a second light from the other side
    key = one[:, 1:4]
    strength = np.linalg.norm(key, axis=-1, keepdims=True)
    mirrors = np.array([[-1.0, 1.0, 1.0], [-1.0, -1.0, 1.0]])
    fill = key[:, None, :] * mirrors[None]
    fill *= 0.3 * strength[:, None] / np.maximum(np.linalg.norm(fill, axis=-1, keepdims=True), 1e-12)
    starts = np.concatenate([np.broadcast_to(np.maximum(one[:, None, :1] - 0.1 * strength[:, None], 0.0), (B, 2, 1)),
                             np.broadcast_to(key[:, None], (B, 2, 3)), fill], axis=-1)
    two, r_two, scale = _robust_lm(values, albedo, normals, ok, starts, iterations)
    pick = scale.argmin(axis=1)
    two, r_two = two[np.arange(B), pick], r_two[np.arange(B), pick]
    # the fill light kept where it explains more than its three values would explain of noise
    # alone (the Bayesian information criterion on the Cauchy likelihood, at the one light's
    # scale): a light fitted to what the model does not hold would otherwise lean on a region
    gain = _cauchy_cost(r_one, ok, one_scale) - _cauchy_cost(r_two, ok, one_scale)
    return np.where((gain > 1.5 * np.log(ok.sum(axis=-1)))[:, None], two, one)


def _cauchy_cost(r: np.ndarray, ok: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """The Cauchy negative log-likelihood (B,) of residuals (B, K) over the usable ones, at the
    robust scales (B,) (:func:`_robust_scale`; the width 2.385 σ, as :func:`fit_light` weighs)."""
    return (np.log1p((r / (2.385 * scale[:, None])) ** 2) * ok).sum(axis=-1)


def _robust_scale(r: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """σ (B,) of residuals (B, K) from their median absolute value over the usable ones."""
    return 1.4826 * usable_median(np.abs(r), ok) + 1e-9  # (every row here has points: finite)


def _robust_lm(values, albedo, normals, ok, starts, iterations: int):
    """Robust Levenberg–Marquardt of :func:`fit_point_light` from ``starts`` (B, S, P): the fitted
    lights (B, S, P), their residuals (B, S, K; 0 where a value is not usable) and the residuals'
    robust scales (B, S) (:func:`_robust_scale`)."""
    B, S, P = starts.shape
    lights = (P - 1) // 3
    # the starts side by side as rows of their own: (B·S, ...)
    p = starts.reshape(B * S, P).copy()
    ok = np.repeat(ok, S, axis=0)
    a = np.where(ok, np.nan_to_num(albedo)[None, :], 0.0)
    n = np.repeat(np.nan_to_num(normals), S, axis=0)
    v = np.where(ok, np.repeat(values, S, axis=0), 0.0)
    # the normal equations' sums over points from weights (B·S, K) in one product each: the normals
    # and their six products (the Jacobian's columns are the albedo, and the albedo times the
    # normal where a light lights it), so no (B·S, K, P) Jacobian is formed in the loop
    upper = np.triu_indices(3)
    moments = np.concatenate([n, n[..., upper[0]] * n[..., upper[1]]], axis=-1)  # (B·S, K, 9)
    quadratic = np.zeros((3, 3), dtype=np.int64)
    quadratic[upper] = np.arange(6)
    quadratic = np.maximum(quadratic, quadratic.T) + 3
    blocks = [slice(1 + 3 * k, 4 + 3 * k) for k in range(lights)]

    def residual(p):
        """The residual (B·S, K) and each light's cosines (its direction times strength)."""
        dots = [(n @ p[:, b, None])[..., 0] for b in blocks]
        return v - a * (p[:, :1] + sum(np.maximum(d, 0.0) for d in dots)), dots

    r, dots = residual(p)
    scale = _robust_scale(r, ok)  # kept the scale of the residuals ``r`` holds
    current = _cauchy_cost(r, ok, scale)
    damping = np.full(len(p), 1e-3)
    settled = np.zeros(len(p), dtype=bool)
    for _ in range(iterations):
        lit = [d > 0.0 for d in dots]
        w = a / (1.0 + (r / (2.385 * scale[:, None])) ** 2)  # the robust weight times the albedo
        m, wr = w * a, w * r
        H = np.empty((len(p), P, P))
        H[:, 0, 0] = m.sum(axis=-1)
        g = np.empty((len(p), P))
        g[:, 0] = wr.sum(axis=-1)
        for i, bi in enumerate(blocks):
            g[:, bi] = ((wr * lit[i])[:, None, :] @ n)[:, 0]
            for j in range(i, lights):
                sums = ((m * (lit[i] & lit[j]))[:, None, :] @ moments)[:, 0]  # (B·S, 9)
                H[:, bi, blocks[j]] = sums[:, quadratic]
                H[:, blocks[j], bi] = sums[:, quadratic]
                if i == j:
                    H[:, 0, bi] = H[:, bi, 0] = sums[:, :3]
        diagonal = np.einsum("bii->bi", H)
        step = np.linalg.solve(H + damping[:, None, None] * np.eye(P) * (diagonal + 1e-12)[:, None, :],
                               g[..., None])[..., 0]
        # a row settles once its step is a millionth of its light, far below any image's noise (and
        # stays: each row's result is the same whatever else is fitted beside it)
        settled |= np.abs(step).max(axis=-1) <= 1e-6 * np.abs(p).max(axis=-1)
        if settled.all():
            break
        p_new = p + step
        r_new, dots_new = residual(p_new)
        trial = _cauchy_cost(r_new, ok, scale)
        better = (trial < current) & ~settled
        p = np.where(better[:, None], p_new, p)
        r = np.where(better[:, None], r_new, r)
        dots = [np.where(better[:, None], dn, d) for dn, d in zip(dots_new, dots)]
        if better.any():
            scale = np.where(better, _robust_scale(r, ok), scale)
            current = np.where(better, _cauchy_cost(r, ok, scale), current)
        damping = np.where(better, np.maximum(damping / 3.0, 1e-7), damping * 10.0)
    return p.reshape(B, S, P), r.reshape(B, S, -1), scale.reshape(B, S)


def sh_quadratic(normals: np.ndarray, light: np.ndarray) -> np.ndarray:
    """``sh_basis(normals) @ light`` (...) evaluated as the quadratic form it is, c + b·n + nᵀMn,
    without the (..., 9) basis: a texture's million texels are shaded in a third of the time."""
    l0, l1, l2, l3, l4, l5, l6, l7, l8 = np.asarray(light, dtype=np.float64)[:9]
    M = np.array([[l7, 0.5 * l4, 0.5 * l5], [0.5 * l4, -l7, 0.5 * l6], [0.5 * l5, 0.5 * l6, 3.0 * l8]])
    n = np.asarray(normals)
    return (l0 - l8) + n @ np.array([l1, l2, l3]) + ((n @ M) * n).sum(axis=-1)
