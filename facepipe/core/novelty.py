"""The novelty gate: details faded out where the strain is unlike any mixture of the examples'.

φ(r) = r extrapolates: on an expression no example shows, pose-space details can make the face
worse than the large-scale motion alone. Seen expressions and their mixtures produce strain
(nearly) in the cone of the examples' strain around each place on the face — non-negative
combinations. At every feature edge (a *site*) the strain of the edges around it is fitted by
the examples' strain there (non-negative least squares, batched projected-gradient steps
finished by an exact active-set solve); the unexplained fraction ρ gives the site a confidence
that reaches the vertices through the WPSD edge weights (:class:`NoveltyGate`,
:func:`novelty_gate`). Pure functions over arrays.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp

logger = logging.getLogger(__name__)

__all__ = ["edge_distances", "NOVELTY_TOLERANCE", "NOVELTY_MIN_BATCHED_STEPS", "novelty_batched_steps",
           "CONFIDENCE_TOLERANCE", "NoveltyFit", "NoveltyGate", "novelty_gate", "motion_vectors"]


def edge_distances(marker_distances: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Surface distance between feature edges: mean geodesic distance of their end markers.

    Parameters
    ----------
    marker_distances : (M, M) geodesic distances between markers; edges : (F, 2).

    Returns
    -------
    (F, F) float64, length units.
    """
    a, b = edges[:, 0], edges[:, 1]
    D = marker_distances
    return 0.25 * (D[np.ix_(a, a)] + D[np.ix_(a, b)] + D[np.ix_(b, a)] + D[np.ix_(b, b)])


# The non-negative fits of the novelty gate stop where a projected-gradient step moves the
# coefficients by less than this fraction of the site's strain ...
NOVELTY_TOLERANCE = 1e-5
# ... or after a few steps, when the exact active-set solver takes the fit over. Batched steps
# settle the many plainly explained fits cheaply; the rest converge slowly (along nearly
# coinciding examples, most of all with many examples such as a performance's frames: thousands
# of steps) and one Lawson–Hanson solve each is both exact and far quicker (ICT kit, 32 frames of
# the noisy take: 0.56 s with up to 2000 steps, confidences 3.6e-3 off; 0.33 s exact; 26
# expressions + 80 frames: 15 s → 2 s). At least this many steps ...
NOVELTY_MIN_BATCHED_STEPS = 16
# ... or, with few examples, as many as cost about one exact solve: a batched step costs ~E² a fit,
# the solver's call a fixed overhead that weighs most where E is small (8 examples: 64 steps)
_EXACT_SOLVE_IN_STEPS = 512


def novelty_batched_steps(n_examples: int) -> int:
    """The batched steps a gate's fit gets before the exact solver takes it over."""
    return max(NOVELTY_MIN_BATCHED_STEPS, _EXACT_SOLVE_IN_STEPS // max(1, n_examples))


# A replay needs each site's confidence, not ρ itself: a fit whose coefficients already leave so
# little unexplained that the confidence is within this of 1 stops there (most fits of a take of
# seen expressions and their mixtures do within a few steps)
CONFIDENCE_TOLERANCE = 1e-6
# the fits iterate in units of this many queries of one site (a site's Gram matrix shared by its
# unit): a unit leaves the batch when all its fits have stopped, so one slow fit holds back a few
# columns, not every query of its site ...
_FIT_UNIT = 8
# ... with as many units per site as keep the Gram matrices gathered for them within this (a cone
# of many examples, such as a performance's frames, gets larger units: fewer copies of big matrices)
_UNIT_GRAM_BYTES = 64 << 20


@dataclass(frozen=True)
class NoveltyFit:
    """The novelty of a batch of strain vectors and how its non-negative fits went.

    Attributes
    ----------
    rho : (Q, F) unexplained fraction per query and site.
    iterations : steps taken by the slowest batched fit.
    unconverged : (query, site) fits left short of the tolerance: stopped by the batched fits'
        iteration cap and not finished by the exact solver either.
    finished_exactly : (query, site) fits that the cap stopped and an exact active-set solve finished.
    """

    rho: np.ndarray
    iterations: int
    unconverged: int
    finished_exactly: int = 0


@dataclass
class NoveltyGate:
    """Fades the details out where the strain is unlike any mixture of the examples'.

    φ(r) = r extrapolates: on an expression no example shows, the details can make the face
    worse than the large-scale motion alone. Seen expressions and their mixtures produce
    strain (nearly) in the cone of the examples' strain around each place on the face —
    non-negative combinations: a frown is not an inverted smile, though the inverse lies in
    their span. For every feature edge (a *site*), the strain of the edges around it is
    fitted by the examples' strain there (non-negative least squares); the
    unexplained fraction ρ gives the site a confidence 1 / (1 + (ρ/τ)⁶) — near 1 while most
    of the strain is explained, half at ρ = τ, near 0 beyond — which reaches the vertices
    through the WPSD edge weights α. Computed at the F sites, not per vertex, it costs the
    same at any mesh resolution.

    Strain alone is not enough: a feature edge's length changes only to second order when its
    markers move out of the surface, so an expression whose markers bulge or sink differently
    (an eyelid lowered by the gaze rather than by a blink) can show the strain of a scaled
    example and receive that example's details. With the *motion* part (built from the
    examples' handle displacements) the test at a site also takes the relative displacements of
    the markers around it (weighted like the edges, the site's mean displacement removed, so a
    translation of the region is no novelty) must lie in the cone of the examples' own (a
    non-negative fit of its own), and ρ is the larger of the two parts' unexplained fractions —
    never below the strain part's own.

    Attributes
    ----------
    index : (F, K) int32 neighbour edges of each site; sqrt_weight : (F, K) their √weights.
    examples : (F, E, K) the examples' weighted local strain at each site.
    solve : (F, E, K) its regularised pseudo-inverse (coefficients = solve @ x).
    tau : fraction of unexplained strain at which confidence is one half (0 disables).
    alpha : (V, F) sparse vertex weights over the sites.
    unconverged_fits : running count of the (query, site) fits that :meth:`novelty` stopped at
        the iteration cap, for a caller's report (each such call also logs a warning).
    motion_index : (F, M) int32 handles around each site, or None (strain only).
    motion_weight : (F, M) their weights (summing to 1 per site).
    motion_examples : (F, E, 3M) the examples' relative handle displacements per site, scaled.
    motion_scale : (F,) the scale of the motion part per site (1 / the feature edges' median length).
    """

    index: np.ndarray
    sqrt_weight: np.ndarray
    examples: np.ndarray
    solve: np.ndarray
    tau: float
    alpha: sp.csr_matrix
    sharpness: float = 6.0  # seen mixtures leave ρ well below τ, unseen expressions well above: a steep step
    unconverged_fits: int = field(default=0, compare=False)
    motion_index: np.ndarray | None = None
    motion_weight: np.ndarray | None = None
    motion_examples: np.ndarray | None = None
    motion_scale: np.ndarray | None = None

    @property
    def has_motion(self) -> bool:
        return self.motion_examples is not None

    def motion_vectors(self, displacements: np.ndarray) -> np.ndarray:
        """The motion part of the site vectors: handle displacements (Q, H, 3) → (Q, F, 3M)."""
        return motion_vectors(displacements, self.motion_index, self.motion_weight, self.motion_scale)

    def novelty(self, features: np.ndarray, displacements: np.ndarray | None = None,
                tolerance: float = NOVELTY_TOLERANCE, max_iterations: int | None = None,
                settled: float | None = None) -> np.ndarray:
        """Unexplained fraction ρ ∈ [0, 1] per site: (Q, F) [, handle displacements (Q, H, 3)] →
        (Q, F); see :meth:`novelty_fit`.

        Fits left unconverged are added to :attr:`unconverged_fits` and logged."""
        fit = self.novelty_fit(features, displacements, tolerance, max_iterations, settled=settled)
        if fit.unconverged:
            self.unconverged_fits += fit.unconverged
            logger.warning("novelty gate: %d of %d site fits stopped after %d iterations, short of the tolerance "
                           "%g", fit.unconverged, fit.rho.size, fit.iterations, tolerance)
        return fit.rho

    def novelty_fit(self, features: np.ndarray, displacements: np.ndarray | None = None,
                    tolerance: float = NOVELTY_TOLERANCE, max_iterations: int | None = None,
                    finish_exactly: bool = True, settled: float | None = None) -> NoveltyFit:
        """ρ per query and site, with the iterations taken and the fits left unconverged.

        The non-negative coefficients are found by accelerated projected gradient (FISTA) on
        the E × E normal equations of every site at once, started from the clipped least-squares
        solution. Clipping alone is no cone test: where examples overlap, the unconstrained fit
        takes negative parts that, cut off, leave seen mixtures looking twice as novel.

        A fit stops once a step moves its coefficients (of the examples scaled to unit norm) by
        at most ``tolerance`` × the norm of its strain, or after ``max_iterations`` steps
        (default: :func:`novelty_batched_steps` of the examples' count). A
        stopped fit is left as it is while the others go on (where it stops does not depend on
        the other queries in the batch), and sites whose fits have all stopped leave the batch.
        FISTA is slow along directions where examples nearly coincide, so the fits the cap
        (a few steps by default) stops are finished (``finish_exactly``) by an active-set NNLS
        (Lawson–Hanson, SciPy), exact in finitely many steps; only a fit that solver cannot
        finish either is ``unconverged``.

        With ``settled`` (a fraction), a fit also stops as soon as its coefficients leave at most
        that fraction of its vector unexplained: its ρ is then that upper bound, not the exact
        value (any non-negative coefficients bound ρ from above). :meth:`confidence` settles fits
        whose confidence is already within :data:`CONFIDENCE_TOLERANCE` of 1.

        With a motion part (:attr:`motion_examples`), ``displacements`` (Q, H, 3) are the
        handles' displacements from the rest pose; the motion is fitted by its own non-negative
        fit (strain is not linear in the motion: one set of coefficients for both would call
        large genuine mixtures novel) and ρ is the larger of the two unexplained fractions.
        """
        x = features[:, self.index] * self.sqrt_weight  # (Q, F, K)
        max_iterations = novelty_batched_steps(self.examples.shape[1]) if max_iterations is None else max_iterations
        if self.examples.shape[1] == 0:
            return NoveltyFit(np.ones(x.shape[:2]), 0, 0)
        fits = [_cone_fit(x, self._cone, tolerance, max_iterations, finish_exactly, settled)]
        if self.has_motion:
            if displacements is None:
                raise ValueError("this novelty gate tests the handles' motion too: pass their displacements")
            fits.append(_cone_fit(self.motion_vectors(displacements), self._motion_cone, tolerance, max_iterations,
                                  finish_exactly, settled))
        return NoveltyFit(np.maximum.reduce([f.rho for f in fits]), max(f.iterations for f in fits),
                          sum(f.unconverged for f in fits), sum(f.finished_exactly for f in fits))

    @cached_property
    def _cone(self) -> "_Cone":
        return _Cone.of(self.examples, self.solve)

    @cached_property
    def _motion_cone(self) -> "_Cone":
        motion = self.motion_examples.astype(np.float64)
        solve = np.linalg.pinv(np.swapaxes(motion, 1, 2), rcond=1e-2) if motion.shape[1] else motion
        return _Cone.of(motion, solve)

    def site_confidence(self, rho: np.ndarray, tau: float | None = None) -> np.ndarray:
        """Per-site confidence 1 / (1 + (ρ/τ)^sharpness) from the unexplained fractions ρ (Q, F);
        ``tau`` defaults to the gate's own (validation scores several τ on one set of fits)."""
        tau = self.tau if tau is None else tau
        if tau <= 0:
            return np.ones_like(rho)
        return 1.0 / (1.0 + (rho / tau) ** self.sharpness)

    def settled_fraction(self, tolerance: float = CONFIDENCE_TOLERANCE) -> float:
        """The unexplained fraction below which a site's confidence is within ``tolerance`` of 1."""
        return self.tau * (tolerance / (1.0 - tolerance)) ** (1.0 / self.sharpness)

    def site_confidences(self, features: np.ndarray, displacements: np.ndarray | None = None) -> np.ndarray:
        """Per-site confidence (Q, F), each within :data:`CONFIDENCE_TOLERANCE` of the exact fits'
        (fits stop once that is settled): (Q, F) [, handle displacements (Q, H, 3)]."""
        if self.tau <= 0:
            return np.ones(features.shape[:1] + self.index.shape[:1])
        return self.site_confidence(self.novelty(features, displacements, settled=self.settled_fraction()))

    def confidence(self, features: np.ndarray, displacements: np.ndarray | None = None) -> np.ndarray:
        """Per-vertex confidence in [0, 1]: (Q, F) [, handle displacements (Q, H, 3)] → (Q, V)."""
        if self.tau <= 0:
            return np.ones((features.shape[0], self.alpha.shape[0]))
        return np.asarray(self.alpha @ self.site_confidences(features, displacements).T).T


@dataclass(frozen=True)
class _Cone:
    """The examples of one part of the site vectors, batched over the sites: (F, E, D) scaled to
    unit norm per example and site (Jacobi: an example that barely reaches a site is as quick to
    fit as a strong one; positive scales keep the cone; examples with nothing at the site get
    scale 0: they cannot explain anything there), their Gram matrices, FISTA steps, the norms,
    and the pseudo-inverse (F, E, D) of the unscaled examples for the first guess."""

    A: np.ndarray
    gram: np.ndarray
    step: np.ndarray
    norm: np.ndarray
    solve: np.ndarray

    @classmethod
    def of(cls, examples: np.ndarray, solve: np.ndarray) -> "_Cone":
        A = examples.astype(np.float64)  # (F, E, D)
        norm = np.sqrt(np.einsum("sek,sek->se", A, A))  # (F, E)
        live = norm > 1e-12 * max(float(norm.max(initial=0.0)), 1e-300)
        A = A * np.where(live, 1.0 / np.maximum(norm, 1e-300), 0.0)[..., None]
        gram = np.matmul(A, np.swapaxes(A, 1, 2))  # (F, E, E)
        step = 1.0 / np.maximum(np.linalg.eigvalsh(gram)[:, -1], 1e-30)[:, None, None]
        return cls(A, gram, step, np.where(live, norm, 0.0), solve.astype(np.float64))


def _cone_fit(x: np.ndarray, cone: _Cone, tolerance: float, max_iterations: int, finish_exactly: bool,
              settled: float | None = None) -> NoveltyFit:
    """The non-negative fits of the site vectors x (Q, F, D) by the cone's examples and their
    unexplained fractions: see :meth:`NoveltyGate.novelty_fit`.

    The fits iterate in units of :data:`_FIT_UNIT` queries of one site: (U, E, B) coefficients,
    each unit with its site's Gram matrix, so a unit leaves the batch once all its fits have
    stopped. Every fit takes the same steps whichever unit or batch it is in."""
    energy = np.einsum("qsk,qsk->qs", x, x)  # (Q, F)
    A, gram, step, norm = cone.A, cone.gram, cone.step, cone.norm
    xs = np.moveaxis(x, 0, 2)  # (F, D, Q)
    b = np.matmul(A, xs)  # Aᵀx: (F, E, Q)
    coef = np.maximum(np.matmul(cone.solve, xs), 0.0) * norm[..., None]
    F, E, Q = coef.shape
    units_per_site = max(1, _UNIT_GRAM_BYTES // max(1, F * E * E * 8))
    units = _FitUnits(F, Q, max(1, min(_FIT_UNIT, Q), -(-Q // units_per_site)))
    # the units still iterating and their fits' state
    live = np.arange(units.count)
    c, bl, en = units.split(coef), units.split(b), units.split(energy.T)
    y = c.copy()
    g, st = (gram, step) if units.n == 1 else (gram[units.site], step[units.site])  # one unit a site: no copy
    limit = tolerance * np.sqrt(en)  # (U, B)
    bound = None if settled is None else settled * (en + 1e-12)
    active = units.split(np.ones((F, Q), dtype=bool), fill=False)
    if bound is not None:  # the first guess may settle a fit already
        active &= ~(_unexplained(c, bl, g, en) <= bound)
    t = 1.0
    iterations = 0
    while live.size and iterations < max_iterations:
        finished = ~active.any(axis=1)
        # units whose fits have all stopped leave the batch, a few at a time (the copies cost)
        if finished.sum() * 8 >= live.size:
            units.store(live[finished], c[finished])
            keep = ~finished
            live, c, y, g, st, bl, en, limit, active = (a[keep] for a in (live, c, y, g, st, bl, en, limit, active))
            if bound is not None:
                bound = bound[keep]
            if not live.size:
                break
        new = np.matmul(g, y)
        new -= bl
        new *= st
        np.subtract(y, new, out=new)
        np.maximum(new, 0.0, out=new)
        moved = y - new
        moved = np.sqrt(np.einsum("ueq,ueq->uq", moved, moved))
        t_new = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
        # (a mask of the arrays' own shape: selecting through a broadcast one is several times slower)
        going = np.repeat(active[:, None], c.shape[1], axis=1)
        # y ← new + m (new − c), c ← new, where the fit is still going
        momentum = new - c
        momentum *= (t - 1.0) / t_new
        momentum += new
        y = np.where(going, momentum, y)
        c = np.where(going, new, c)
        t = t_new
        iterations += 1
        active &= ~(moved <= limit)
        if bound is not None and iterations % 4 == 0:  # (every few steps: it costs a step's products)
            active &= ~(_unexplained(c, bl, g, en) <= bound)
    finished = 0
    if live.size:
        if finish_exactly and active.any():
            finished = _finish_exactly(c, active, units.site[live], units.query[live], xs, A)
        units.store(live, c)
    coef = units.join(E)
    residual = energy - (2.0 * np.einsum("seq,seq->qs", coef, b)
                         - np.einsum("seq,seq->qs", coef, np.matmul(gram, coef)))
    # a site barely strained (or moved) at all is treated as seen (its details are near zero anyway)
    rho = np.clip(np.maximum(residual, 0.0) / (energy + 1e-12), 0.0, 1.0)
    return NoveltyFit(rho, iterations, int(active.sum()) if live.size else 0, finished)


def _unexplained(c: np.ndarray, b: np.ndarray, gram: np.ndarray, energy: np.ndarray) -> np.ndarray:
    """|x − Aᵀc|² of coefficients c (U, E, B), from Aᵀx = b (U, E, B), the Gram matrices (U, E, E)
    and |x|² (U, B)."""
    return energy - (2.0 * np.einsum("ueq,ueq->uq", c, b) - np.einsum("ueq,ueq->uq", c, np.matmul(gram, c)))


class _FitUnits:
    """(F, ..., Q) arrays of per-site, per-query values as units of ``size`` queries of one site:
    (F·n, ..., size), n = ⌈Q / size⌉, the last unit of a site padded; ``site`` (U,) and ``query``
    (U, size) say whose (−1: padding). :meth:`store` keeps units' coefficients as they finish and
    :meth:`join` gives the (F, E, Q) coefficients back."""

    def __init__(self, sites: int, queries: int, size: int):
        self.F, self.Q, self.size = sites, queries, size
        self.n = -(-queries // size)
        self.count = sites * self.n
        self.site = np.repeat(np.arange(sites), self.n)
        q = np.arange(self.n * size).reshape(self.n, size)
        self.query = np.tile(np.where(q < queries, q, -1), (sites, 1))
        self._out: np.ndarray | None = None

    def split(self, a: np.ndarray, fill=0.0) -> np.ndarray:
        pad = self.n * self.size - self.Q
        if pad:
            a = np.concatenate([a, np.full(a.shape[:-1] + (pad,), fill, dtype=a.dtype)], axis=-1)
        a = a.reshape(a.shape[:-1] + (self.n, self.size))
        return np.ascontiguousarray(np.moveaxis(a, -2, 1)).reshape((self.count,) + a.shape[1:-2] + (self.size,))

    def store(self, ids: np.ndarray, c: np.ndarray) -> None:
        if self._out is None:
            self._out = np.zeros((self.count,) + c.shape[1:])
        self._out[ids] = c

    def join(self, E: int) -> np.ndarray:
        if self._out is None:
            self._out = np.zeros((self.count, E, self.size))
        out = np.moveaxis(self._out.reshape(self.F, self.n, E, self.size), 1, 2)
        return out.reshape(self.F, E, self.n * self.size)[..., :self.Q]


def _finish_exactly(c: np.ndarray, active: np.ndarray, site: np.ndarray, query: np.ndarray, xs: np.ndarray,
                    A: np.ndarray) -> int:
    """Solve the still ``active`` fits exactly in place (``c``: (U, E, B) coefficients of units of
    the sites ``site`` (U,) and queries ``query`` (U, B), in the unit-norm examples' scale); marks
    them done. Returns how many."""
    from scipy.optimize import nnls  # (rarely needed: SciPy's optimize is a tenth of a second to import)

    done = 0
    for u, j in np.argwhere(active):
        try:
            c[u, :, j] = nnls(A[site[u]].T, xs[site[u], :, query[u, j]], maxiter=10 * A.shape[1])[0]
        except RuntimeError:  # its own cap (10 E steps, SciPy's default 3 E), rare: the batched iterate stays, reported
            continue
        active[u, j] = False
        done += 1
    return done


def novelty_gate(example_features: np.ndarray, edge_distance: np.ndarray, alpha: sp.csr_matrix, tau: float,
                 radius: float, max_edges: int = 48, rcond: float = 1e-2, *,
                 example_displacements: np.ndarray | None = None, marker_distance: np.ndarray | None = None,
                 edges: np.ndarray | None = None) -> NoveltyGate:
    """Build the gate from the examples' strain features (and, given their handle displacements,
    their motion: see :class:`NoveltyGate`).

    Parameters
    ----------
    example_features : (E, F) strain of the example poses (not the rest pose).
    edge_distance : (F, F) from :func:`edge_distances`; radius : Gaussian radius of a site's
        neighbourhood, length units.
    alpha : (V, F) WPSD vertex weights; tau : see :class:`NoveltyGate`.
    rcond : relative cut-off of the pseudo-inverse (nearly parallel examples).
    example_displacements : (E, H, 3) the examples' handle displacements from the rest pose;
        with ``marker_distance`` (H, H) geodesic distances between the handles and ``edges``
        (F, 2) the feature edges, adds the motion part. A site's markers are the
        ``max_edges // 2`` nearest (a triangulated graph has about three edges per vertex, and
        each edge's two ends are shared: about that many markers lie on a site's edges),
        weighted by the same Gaussian.
    """
    F = edge_distance.shape[0]
    K = min(max_edges, F)
    W = np.exp(-((edge_distance / radius) ** 2))
    index = np.argsort(-W, axis=1, kind="stable")[:, :K]
    sqrt_weight = np.sqrt(np.take_along_axis(W, index, axis=1))
    A = np.moveaxis(example_features[:, index] * sqrt_weight[None], 1, 0)  # (F, E, K)
    solve = np.linalg.pinv(np.swapaxes(A, 1, 2), rcond=rcond) if A.shape[1] else A  # (F, E, K)
    gate = NoveltyGate(index.astype(np.int32), sqrt_weight.astype(np.float32), A.astype(np.float32),
                       solve.astype(np.float32), float(tau), alpha)
    if example_displacements is None:
        return gate
    if marker_distance is None or edges is None:
        raise ValueError("the motion part needs the handles' distances and the feature edges")
    # a site's distance to a marker: the mean of its two end markers' (as between edges)
    site_marker = 0.5 * (marker_distance[edges[:, 0]] + marker_distance[edges[:, 1]])  # (F, H)
    M = min(max(K // 2, 1), site_marker.shape[1])
    Wm = np.exp(-((site_marker / radius) ** 2))
    motion_index = np.argsort(-Wm, axis=1, kind="stable")[:, :M]
    motion_weight = np.take_along_axis(Wm, motion_index, axis=1)
    motion_weight /= np.maximum(motion_weight.sum(axis=1, keepdims=True), 1e-300)
    # motion in units of the feature edges' length, as strain is: the floor below which a site
    # counts as unmoved then means the same for both parts
    length = float(np.median(marker_distance[edges[:, 0], edges[:, 1]]))
    scale = np.full(F, 1.0 / length if length > 0 else 1.0)
    examples = np.moveaxis(motion_vectors(example_displacements, motion_index, motion_weight, scale), 1, 0)
    return dataclasses.replace(gate, motion_index=motion_index.astype(np.int32),
                               motion_weight=motion_weight.astype(np.float32),
                               motion_examples=examples.astype(np.float32), motion_scale=scale.astype(np.float32))


def motion_vectors(displacements: np.ndarray, index: np.ndarray, weight: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """The relative motion of the markers around each site: handle displacements (Q, H, 3), the
    sites' markers ``index`` (F, M) with ``weight`` (F, M) summing to 1 and ``scale`` (F,) →
    (Q, F, 3M): √w_m (u_m − Σ w u) × scale, the site's weighted mean displacement removed."""
    d = np.asarray(displacements, dtype=np.float64)
    (Q, H, _), (F, M) = d.shape, index.shape
    # gathered as (F, M, Q·3), so the mean's removal and the weights run along rows of Q·3 values
    # (along the last axis of 3 they are several times slower); the same sums, the same bits
    u = np.ascontiguousarray(d.transpose(1, 0, 2)).reshape(H, Q * 3)[index]
    w = np.asarray(weight, dtype=np.float64)
    u -= np.einsum("fm,fmk->fk", w, u)[:, None, :]
    u *= (np.sqrt(w) * np.asarray(scale, dtype=np.float64)[:, None])[:, :, None]
    return np.ascontiguousarray(u.reshape(F, M, Q, 3).transpose(2, 0, 1, 3)).reshape(Q, F, M * 3)
