"""Pose-space deformation of fine-scale details over strain features.

Bickel et al. 2008, §5.2–5.3. A detail d_v (3-vector in vertex v's local frame) is an RBF
function of the strain feature vector f:

    d_v(f) = Σ_i w_{v,i} φ(r_{v,i}(f)) + c_v,      φ(r) = r

* PSD: r_i(f) = |f − f_i|, one distance per basis pose, shared by all vertices.
* WPSD: r_{v,i}(f)² = Σ_e α_{v,e} (f_e − f_{i,e})², each vertex weighs the feature edges
  near it, so independent regions of the face (left brow, right mouth corner) combine
  freely from a small basis.

φ(r) = r is conditionally negative definite of order 1: the constant term c_v with the
side condition Σ_i w_{v,i} = 0 makes the interpolation system non-singular for distinct
poses. A per-vertex WPSD system is singular where two basis poses have the same strain on
all of the vertex's edges (a left-side expression seen from the right cheek looks like the
rest pose); those systems are solved in the least-squares sense by a truncated
pseudo-inverse, which averages coincident poses instead of blowing up, with the rest pose
itself always met exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from facepipe.core.growing_lstsq import GrowingRbfSystems, truncated_normal_solve
from facepipe.core.novelty import NoveltyGate
from facepipe.parallel import map_blocks

METHODS = ("wpsd", "psd", "none")
REST_ROW_WEIGHT = 1e3
# Pseudo-inverse cut-off of the RBF systems, relative to the largest singular value of the system
# left once the rest row is met. It used to be 1e-6 of a system with the rest row weighted 1e3
# times, whose largest singular value came from that weight: about 3e-4 of the system's own
# (ICT kit: 2.9e-4 to 4.4e-4 from vertex to vertex). 3e-4 keeps that regularisation of nearly
# coincident poses, now the same for every vertex whatever the weight.
DEFAULT_RCOND = 3e-4


# ----------------------------------------------------------------------------- weights


def default_beta(rest_lengths: np.ndarray, scale: float = 1.0) -> float:
    """WPSD falloff β (1/length) from the feature-edge spacing: β = scale / median(l)."""
    return float(scale / np.median(rest_lengths))


def wpsd_edge_weights(marker_distances: np.ndarray, edges: np.ndarray, rest_lengths: np.ndarray, beta: float,
                      min_weight: float = 0.025, max_edges: int = 16, min_keep: int = 3,
                      chunk: int = 2048) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex feature-edge weights α_{v,e} = exp(−β (L_{v,e} − l_e)), normalised.

    L_{v,e} is the sum of the geodesic distances from v to the edge's two markers, so
    L − l is 0 on the edge and grows with the distance from it.

    Parameters
    ----------
    marker_distances : (M, V) geodesic distances from each marker to each vertex (length
        units; ``inf`` where unreachable).
    edges : (F, 2) marker index pairs; rest_lengths : (F,) lengths.
    beta : falloff (1/length).
    min_weight : normalised weights below it are dropped ...
    max_edges : ... and at most this many edges are kept per vertex (the largest) ...
    min_keep : ... but never fewer than this, so a vertex far from every edge still
        keeps its nearest ones.

    Returns
    -------
    edge_index : (V, K) int32 feature-edge indices, K = min(max_edges, F).
    edge_weight : (V, K) float32, each row sums to 1; unused slots have weight 0. A vertex that no
        marker reaches (every distance ``inf``: a part of the mesh apart from the markers') has
        weight 0 everywhere, so its details are zero.
    """
    edges = np.asarray(edges, dtype=np.int64)
    F = edges.shape[0]
    V = marker_distances.shape[1]
    K = min(max_edges, F)
    keep_min = min(min_keep, K)
    index = np.zeros((V, K), dtype=np.int32)
    weight = np.zeros((V, K), dtype=np.float32)

    def block(start):
        stop = min(V, start + chunk)
        # small blocks keep the (n, F) temporaries in cache (large blocks spill it); they are
        # updated in place, the same arithmetic as out-of-place. The block's distances are turned
        # to vertex rows first (M columns, fewer than the F edges), so the sums come out in rows.
        D = np.ascontiguousarray(marker_distances[:, start:stop].T)  # (n, M)
        excess = D[:, edges[:, 0]]
        excess += D[:, edges[:, 1]]  # (n, F)
        excess -= rest_lengths[None, :]
        del D
        np.copyto(excess, np.inf, where=~np.isfinite(excess))
        # the largest weights are the smallest excesses: choose them first, then take exp of K
        # values per vertex rather than of all F
        top = np.argpartition(excess, K - 1, axis=1)[:, :K] if K < F else np.tile(np.arange(F), (stop - start, 1))
        ex = np.take_along_axis(excess, top, axis=1)
        del excess
        order = np.argsort(ex, axis=1)
        top = np.take_along_axis(top, order, axis=1)
        ex = np.take_along_axis(ex, order, axis=1)
        # subtracting the per-vertex minimum leaves the normalised weights unchanged and
        # keeps far vertices (neck, back of the head) from underflowing to all-zero
        base = ex[:, :1]
        ex -= np.where(np.isfinite(base), base, 0.0)
        a = np.exp(-beta * ex)  # exp(−inf) = 0: unreachable edges weigh nothing
        total = a.sum(axis=1, keepdims=True)
        a = a / np.where(total > 0, total, 1.0)
        drop = a < min_weight
        drop[:, :keep_min] = False
        a = np.where(drop, 0.0, a)
        total = a.sum(axis=1, keepdims=True)
        # a vertex no marker reaches (a separate part: an eyeball, teeth) keeps no edge: no details
        a = a / np.where(total > 0, total, 1.0)
        index[start:stop] = top
        weight[start:stop] = a

    map_blocks(block, range(0, V, chunk))
    return index, weight


def edge_weight_matrix(edge_index: np.ndarray, edge_weight: np.ndarray, n_edges: int) -> sp.csr_matrix:
    """The α as a sparse (V, F) matrix, so per-vertex weighted sums are one sparse product."""
    V, K = edge_index.shape
    # K slots a row: the rows of a coordinate list, without its conversion; then, as that
    # conversion does, the columns sorted (a slot repeated summed), and the unused slots dropped
    index_type = np.int32 if V * K < 2**31 else np.int64
    # (copies: W is changed in place below, and must not share the caller's arrays)
    W = sp.csr_matrix((edge_weight.astype(np.float64).ravel(), edge_index.astype(index_type).ravel(),
                       np.arange(0, V * K + 1, K, dtype=index_type)), shape=(V, n_edges))
    W.sum_duplicates()
    W.eliminate_zeros()
    return W


# ----------------------------------------------------------------------------- distances


def psd_distances(features: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Global pose-space distances |f − f_i|: (Q, F), (P, F) → (Q, P)."""
    diff = features[:, None, :] - basis[None, :, :]
    return np.sqrt(np.einsum("qpf,qpf->qp", diff, diff))


def wpsd_distances(features: np.ndarray, basis: np.ndarray, alpha: sp.csr_matrix, chunk: int = 32768) -> np.ndarray:
    """Per-vertex weighted distances: (Q, F), (P, F), α (V, F) → (Q, V, P).

    The squared strain differences form a (Q·P, F) table; the α-weighted sums over each
    vertex's edges are then one sparse product, taken over blocks of vertices on the shared
    threads (SciPy's sparse product releases the GIL) so that the temporaries stay small (each
    vertex's sum is the same either way).
    """
    Q, P = features.shape[0], basis.shape[0]
    sq = ((features[:, None, :] - basis[None, :, :]) ** 2).reshape(Q * P, -1).T  # (F, Q*P)
    V = alpha.shape[0]
    out = np.empty((Q, V, P))

    def block(start):
        r2 = np.asarray(alpha[start:start + chunk] @ sq)  # (n, Q*P)
        np.maximum(r2, 0.0, out=r2)
        np.sqrt(r2, out=r2)
        out[:, start:start + chunk] = r2.reshape(-1, Q, P).transpose(1, 0, 2)

    map_blocks(block, range(0, V, chunk))
    return out


# ----------------------------------------------------------------------------- solve


def solve_rbf(phi: np.ndarray, targets: np.ndarray, rcond: float = DEFAULT_RCOND, smoothing: float = 0.0,
              chunk: int = 16384) -> tuple[np.ndarray, np.ndarray]:
    """Weights and constant of d = Σ_i w_i φ_i + c, by interpolation or least squares.

    Solves, per vertex, the rows [Φ 1] [w; c] = D together with the side condition
    Σ_i w_i = 0 (least squares when there are more rows than basis poses; exact
    interpolation when Φ is the basis-to-basis matrix and non-singular).

    Parameters
    ----------
    phi : (R, P) shared kernel matrix (PSD) or (V, R, P) per vertex (WPSD); R rows are
        training poses, P basis poses.
    targets : (R, V, 3) details to reproduce; row 0 must be the rest pose (details zero), which
        is reproduced exactly, even where other poses coincide with it.
    rcond : singular values below ``rcond`` × the largest are cut (coincident poses), in the
        system left once the rest row is met (:func:`rest_exact_solve`).
    smoothing : λ ≥ 0, relative to the mean kernel value; with R = P uses Φ − λI (for
        φ = r, which is conditionally negative definite, Φ + λI can become singular).

    Returns
    -------
    weights : (V, P, 3) float64; const : (V, 3) float64.
    """
    R, V = targets.shape[0], targets.shape[1]
    shared = phi.ndim == 2
    P = phi.shape[-1]
    if shared:
        x = _solve_block(phi[None], targets.reshape(R, -1)[None], rcond, smoothing)[0]  # (P+1, V*3)
        x = x.reshape(P + 1, V, 3)
        return np.moveaxis(x[:P], 0, 1), x[P]
    weights = np.zeros((V, P, 3))
    const = np.zeros((V, 3))
    # a vertex whose details are zero in every row (skin the anchors hold, parts no marker moves:
    # a fifth of a face with its head and neck) has the zero solution of its linear system: only
    # the others are solved
    moving = np.flatnonzero(np.any(targets != 0, axis=(0, 2)))
    every = len(moving) == V

    def block(start):
        rows = slice(start, min(V, start + chunk)) if every else moving[start:start + chunk]
        rhs = np.moveaxis(targets[:, rows], 1, 0)  # (n, R, 3)
        x = _solve_block(_rows_in_layout(phi, rows), rhs, rcond, smoothing)  # (n, P+1, 3)
        weights[rows] = x[:, :P]
        const[rows] = x[:, P]

    # the blocks write disjoint rows and each vertex sees the same arithmetic on any thread and in
    # any block, so the result is the same bit for bit however many threads share them
    map_blocks(block, range(0, len(moving), chunk))
    return weights, const


def _rows_in_layout(a: np.ndarray, rows) -> np.ndarray:
    """``a[rows]`` laid out in memory as a slice of ``a`` is (its axes' order in memory kept): a
    reduction over it then adds in the same order as over a slice, so a row's sums are the same
    bit for bit whichever rows it is gathered with."""
    if isinstance(rows, slice):
        return a[rows]
    out = np.empty_like(a[:len(rows)])  # order "K": a's layout
    out[...] = a[rows]
    return out


def _solve_block(phi: np.ndarray, rhs: np.ndarray, rcond: float, smoothing: float) -> np.ndarray:
    """Batched least-squares solve of [Φ s·1; s·1ᵀ 0] [w; c/s] = [D; 0], the rest row exactly."""
    n, R, P = phi.shape
    scale = np.abs(phi).mean(axis=(1, 2), keepdims=True)
    scale = np.where(scale > 0, scale, 1.0)
    A = np.zeros((n, R + 1, P + 1))
    A[:, :R, :P] = phi
    if smoothing and R == P:
        A[:, :R, :P] -= smoothing * scale * np.eye(P)
    # the constant column is scaled like Φ so the SVD cut-off treats both alike
    A[:, :R, P] = scale[:, 0, 0][:, None]
    A[:, R, :P] = scale[:, 0, 0][:, None]
    b = np.zeros((n, R + 1, rhs.shape[-1]))
    b[:, :R] = rhs
    # row 0 is the rest pose, whose details are zero by construction: where coincident poses
    # are averaged, the rest pose must still come out exactly (a still face stays still)
    x = rest_exact_solve(A, b, rcond)
    x[:, P] *= scale[:, 0, 0][:, None]
    return x


def rest_exact_solve(A: np.ndarray, b: np.ndarray, rcond: float) -> np.ndarray:
    """Least squares of A x = b for a batch (n, R, P), (n, R, k), with row 0 met exactly and the
    other rows solved by a truncated pseudo-inverse.

    Row 0 is the rest pose. Weighting it heavily in one least-squares system would move the
    pseudo-inverse's cut-off with the weight (σ_max grows with it); instead the other rows are
    solved within the constraint, on the system left once row 0 is met (:func:`constrained_pinv_solve`),
    and ``rcond`` is relative to that system's largest singular value, whatever row 0's scale.

    Square systems where no singular value is cut satisfy every row exactly: they are solved by
    the inverse of A with row 0 weighted by ``REST_ROW_WEIGHT`` (the weight does not change that
    solution, only its round-off; kept so that the arithmetic is what it always was). The test
    for them: σ_min of the constrained system ≥ σ_min(A_w) ≥ 1 / ‖A_w⁻¹‖_F and its σ_max ≤
    ‖A[1:]‖_F, so where ‖A[1:]‖_F ‖A_w⁻¹‖_F < 1 / (2 rcond) nothing would be cut.
    """
    n, R, P = A.shape
    if R != P or n == 0:
        return constrained_pinv_solve(A, b, rcond)
    # a system with two equal rows (poses that coincide where a vertex's edges are: most vertices
    # of a face, far from some expression's motion) is exactly singular: it goes to the
    # pseudo-inverse without an inverse tried first (which fails, for its whole stack)
    x = np.empty((n, P, b.shape[-1]))
    to_truncate = repeated_rows(A)  # and below, those whose inverse is not clear of the cut-off
    try_inverse = np.flatnonzero(~to_truncate)
    weighted = A[try_inverse]
    weighted[:, 0] *= REST_ROW_WEIGHT
    weighted_b = b[try_inverse]
    weighted_b[:, 0] *= REST_ROW_WEIGHT
    inv, clear = _inverse_where_clear(weighted, np.einsum("nij,nij->n", A[try_inverse, 1:], A[try_inverse, 1:]),
                                      rcond)
    x[try_inverse[clear]] = inv[clear] @ weighted_b[clear]
    to_truncate[try_inverse[~clear]] = True
    if to_truncate.any():
        x[to_truncate] = constrained_pinv_solve(A[to_truncate], b[to_truncate], rcond)
    return x


def repeated_rows(A: np.ndarray) -> np.ndarray:
    """(n,) whether each of a stack of matrices (n, R, P) has two rows exactly equal."""
    R = A.shape[1]
    out = np.zeros(A.shape[0], dtype=bool)
    for i in range(R):
        for j in range(i + 1, R):
            # the first entries tell most pairs apart; the whole rows are compared where they agree
            candidates = np.flatnonzero((A[:, i, 0] == A[:, j, 0]) & ~out)
            if candidates.shape[0]:
                out[candidates[(A[candidates, i] == A[candidates, j]).all(axis=-1)]] = True
    return out


def batched_inverse(A: np.ndarray) -> np.ndarray:
    """Inverses of a stack of square matrices (n, P, P), NaN where a matrix is exactly singular.

    ``np.linalg.inv`` raises for the whole stack when one matrix is singular: the stack is
    inverted in one call, and only where that raises does ``slogdet`` (which factors every matrix
    as ``inv`` does, LAPACK's LU with partial pivoting) tell the exactly singular ones (a zero
    pivot: log-determinant −inf), the others then inverted in one call. Each matrix is inverted
    on its own (LAPACK per matrix), so its inverse is the same bit for bit whichever others share
    the stack.
    """
    inv = np.full(A.shape, np.nan)
    if A.shape[0] == 0:
        return inv
    try:
        return np.linalg.inv(A)
    except np.linalg.LinAlgError:
        pass
    _, logdet = np.linalg.slogdet(A)
    regular = np.isfinite(logdet)
    try:
        if regular.any():
            inv[regular] = np.linalg.inv(A[regular])
    except np.linalg.LinAlgError:  # pragma: no cover - a LAPACK whose LU pivots differ between the two
        for i in np.flatnonzero(regular):
            try:
                inv[i] = np.linalg.inv(A[i])
            except np.linalg.LinAlgError:
                pass
    return inv


def _inverse_where_clear(A: np.ndarray, squared_scale: np.ndarray, rcond: float) -> tuple[np.ndarray, np.ndarray]:
    """Batched inverses of A and where they are safe to use instead of a truncated pseudo-inverse:
    ``scale · ‖A⁻¹‖_F · rcond < 1/2`` with ``scale² = squared_scale`` (n,), an upper bound of the
    largest singular value the cut-off is relative to (‖A⁻¹‖_F bounds 1 / σ_min from above)."""
    inv = batched_inverse(A)
    with np.errstate(all="ignore"):
        cond = np.sqrt(squared_scale * np.einsum("nij,nij->n", inv, inv))
    return inv, cond * rcond < 0.5  # False for NaN (singular)


def svd_solve(A: np.ndarray, b: np.ndarray, rcond: float) -> np.ndarray:
    """``np.linalg.pinv(A, rcond) @ b`` for a batch, applied from the SVD without forming the
    pseudo-inverse (the same cut: singular values at most ``rcond`` × the largest are dropped;
    a fifth less time on 8 × 8 systems)."""
    if A.shape[0] == 0:
        return np.zeros(A.shape[:1] + A.shape[2:] + b.shape[2:])
    u, s, vt = np.linalg.svd(A, full_matrices=False)
    large = s > rcond * s[:, :1]
    s_inv = np.divide(1.0, s, out=np.zeros_like(s), where=large)
    return np.matmul(vt.transpose(0, 2, 1), s_inv[:, :, None] * np.matmul(u.transpose(0, 2, 1), b))


# The truncated solves go through the normal equations (a symmetric eigen-decomposition, a third
# quicker than the SVD of the system on the small per-vertex systems) where the cut-off leaves
# them accurate: the kept eigenvalues are then at least rcond² ≥ 1e-8 of the largest, each
# computed to about 1e-16 of the largest, so to about 2e-8 of itself or better. Smaller cut-offs
# use the SVD.
NORMAL_EQUATIONS_MIN_RCOND = 1e-4


def truncated_solve(A: np.ndarray, b: np.ndarray, rcond: float) -> np.ndarray:
    """``np.linalg.pinv(A, rcond) @ b`` for a batch (n, R, P), (n, R, k): from the normal
    equations where ``rcond`` ≥ :data:`NORMAL_EQUATIONS_MIN_RCOND`, else by :func:`svd_solve`."""
    if rcond < NORMAL_EQUATIONS_MIN_RCOND or A.shape[0] == 0:
        return svd_solve(A, b, rcond)
    At = np.swapaxes(A, 1, 2)
    return truncated_normal_solve(np.matmul(At, A), np.matmul(At, b), rcond)


def constrained_pinv_solve(A: np.ndarray, b: np.ndarray, rcond: float) -> np.ndarray:
    """Minimum-norm least squares of rows 1: of A x = b subject to row 0 holding exactly, for a
    batch (n, R, P), (n, R, k); singular values at most ``rcond`` × the largest of the
    constrained system are dropped. Row 0 must not be zero.

    A Householder reflection H maps row 0's a₀ onto the first axis (H a₀ = α e₀), so with
    x = H y the constraint fixes y₀ = b₀ / α and leaves y₁: free: the other rows become
    (A₁H)[:, 1:] y₁: = b₁ − (A₁H)[:, 0] y₀, solved by :func:`truncated_solve`. Scaling row 0
    (and b₀) changes neither the constraint nor that system, so it cannot move the cut-off.
    """
    n, R, P = A.shape
    if n == 0:
        return np.zeros((0, P) + b.shape[2:])
    a0 = A[:, 0]
    norm = np.sqrt(np.einsum("np,np->n", a0, a0))
    if not (norm > 0).all():
        raise ValueError("the exactly met row is zero")
    sign = np.where(a0[:, 0] >= 0, 1.0, -1.0)
    v = a0.copy()
    v[:, 0] += sign * norm  # same signs added: no cancellation
    H = np.eye(P) - (2.0 / np.einsum("np,np->n", v, v))[:, None, None] * (v[:, :, None] * v[:, None, :])
    y0 = b[:, 0] / (-sign * norm)[:, None]  # (n, k)
    C = np.matmul(A[:, 1:], H)  # (n, R−1, P)
    if R > 1 and P > 1:
        rest = truncated_solve(C[:, :, 1:], b[:, 1:] - C[:, :, :1] * y0[:, None, :], rcond)
    else:  # nothing left to fit, or nothing left to fit it with
        rest = np.zeros((n, P - 1, b.shape[-1]))
    return np.matmul(H, np.concatenate([y0[:, None], rest], axis=1))


# ----------------------------------------------------------------------------- model


@dataclass
class DetailModel:
    """A fitted pose-space detail model.

    Attributes
    ----------
    method : "psd" | "wpsd" | "none"
    basis_features : (P, F) strain features of the basis poses (the rest pose first).
    weights : (V, P, 3) RBF weights; const : (V, 3) constant term (local-frame units).
    alpha : (V, F) sparse WPSD edge weights (None for PSD).
    gate : optional :class:`NoveltyGate` fading details out on strain unlike the examples'.
    """

    method: str
    basis_features: np.ndarray
    weights: np.ndarray
    const: np.ndarray
    alpha: sp.csr_matrix | None = None
    gate: NoveltyGate | None = None

    def distances(self, features: np.ndarray) -> np.ndarray:
        """Kernel values: (Q, P) for PSD, (Q, V, P) for WPSD."""
        return kernel_matrix(self.method, features, self.basis_features, self.alpha)

    def evaluate(self, features: np.ndarray, displacements: np.ndarray | None = None) -> np.ndarray:
        """Details in local frames for strain features (Q, F) → (Q, V, 3); ``displacements``
        (Q, H, 3), the handles' displacements from the rest pose, for a gate that tests motion."""
        if self.method == "none":
            return np.zeros((features.shape[0],) + self.const.shape)
        phi = self.distances(features)
        if phi.ndim == 2:
            d = np.einsum("qp,vpc->qvc", phi, self.weights, optimize=True) + self.const
        else:
            d = np.einsum("qvp,vpc->qvc", phi, self.weights, optimize=True) + self.const
        if self.gate is not None:
            d *= self.gate.confidence(features, displacements)[..., None]
        return d


def kernel_matrix(method: str, features: np.ndarray, basis: np.ndarray, alpha: sp.csr_matrix | None) -> np.ndarray:
    """φ(r) = r between query poses and basis poses for the given method."""
    if method == "psd":
        return psd_distances(features, basis)
    if method == "wpsd":
        return wpsd_distances(features, basis, alpha)
    raise ValueError(f"unknown pose-space method {method!r}")


def fit_details(method: str, features: np.ndarray, details: np.ndarray, basis: list[int], fit: str,
                alpha: sp.csr_matrix | None = None, rcond: float = DEFAULT_RCOND,
                smoothing: float = 0.0) -> DetailModel:
    """Fit the RBF weights for a chosen basis.

    Parameters
    ----------
    features : (E, F) strain features of the training poses (pose 0 is the rest pose).
    details : (E, V, 3) their details in local frames.
    basis : indices into the training poses of the basis poses.
    fit : "interpolate" (exact at the basis poses) or "least-squares" (over all E poses).
    """
    basis_features = features[basis]
    rows = basis if fit == "interpolate" else list(range(features.shape[0]))
    phi = kernel_matrix(method, features[rows], basis_features, alpha)  # (R, P) or (R, V, P)
    if phi.ndim == 3:
        phi = np.moveaxis(phi, 1, 0)  # (V, R, P)
    weights, const = solve_rbf(phi, details[rows], rcond=rcond, smoothing=smoothing)
    return DetailModel(method, basis_features, weights, const, alpha)


def spread_subset(n: int, count: int) -> np.ndarray:
    """``count`` indices evenly spread over ``range(n)`` (all of them when count is 0 or ≥ n)."""
    if count <= 0 or count >= n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, count).round().astype(np.int64))


def rms_per_pose(predicted: np.ndarray, target: np.ndarray, vertices: slice | np.ndarray = slice(None)) -> np.ndarray:
    """RMS vertex distance per pose: (E, V, 3), (E, V, 3) → (E,)."""
    d = predicted[:, vertices] - target[:, vertices]
    return np.sqrt(np.einsum("evc,evc->ev", d, d).mean(axis=1))


def greedy_basis(method: str, features: np.ndarray, details: np.ndarray, fit: str, max_poses: int,
                 tolerance: float = 0.0, alpha: sp.csr_matrix | None = None, rcond: float = DEFAULT_RCOND,
                 smoothing: float = 0.0, error_vertices: slice | np.ndarray = slice(None),
                 candidates: np.ndarray | None = None, progress=None,
                 observe=None) -> tuple[DetailModel, list[int], list[dict]]:
    """Greedy basis selection: start from the rest pose, add the worst-fit pose.

    Parameters
    ----------
    features : (E, F), details : (E, V, 3) training poses; pose 0 must be the rest pose.
    max_poses : number of poses to add beyond the rest pose.
    tolerance : stop when the worst training error (RMS, length units) falls below it.
    candidates : indices allowed into the basis (default: every pose but the rest).
    observe : optional callable(model, basis) called with the model of every basis size
        (cross-validation scores held-out poses along the way).

    Returns
    -------
    model : the DetailModel of the final basis.
    basis : its pose indices (rest first).
    curve : one dict per basis size: {"poses": n_added, "added": index, "mean_rms", "max_rms"}
        — the error of the training poses as the basis grows.
    """
    E = features.shape[0]
    if candidates is None:
        candidates = np.arange(1, E)
    if method == "wpsd" and fit == "least-squares" and E > min(max_poses, len(candidates)) + 1:
        return _greedy_wpsd_least_squares(features, details, max_poses, tolerance, alpha, rcond, error_vertices,
                                          candidates, progress, observe)
    basis = [0]
    curve = []
    model = fit_details(method, features, details, basis, fit, alpha, rcond, smoothing)
    while True:
        if observe is not None:
            observe(model, list(basis))
        err = rms_per_pose(model.evaluate(features), details, error_vertices)
        curve.append({"poses": len(basis) - 1, "added": int(basis[-1]),
                      "mean_rms": float(err[1:].mean()) if E > 1 else 0.0, "max_rms": float(err.max())})
        if progress is not None:
            progress(len(basis) - 1, curve[-1])
        open_ = [int(c) for c in candidates if c not in basis]
        if len(basis) - 1 >= max_poses or not open_ or err.max() <= tolerance:
            break
        worst = open_[int(np.argmax(err[open_]))]
        basis.append(worst)
        model = fit_details(method, features, details, basis, fit, alpha, rcond, smoothing)
    return model, basis, curve


def _greedy_wpsd_least_squares(features, details, max_poses, tolerance, alpha, rcond, error_vertices, candidates,
                               progress, observe) -> tuple[DetailModel, list[int], list[dict]]:
    """:func:`greedy_basis` for WPSD fitted by least squares to more training poses than the basis
    will hold, with each basis pose's kernel column computed once and the normal equations grown
    (:class:`~facepipe.core.growing_lstsq.GrowingRbfSystems`). The poses are scored (and passed to
    ``observe``) along the way by the Tikhonov counterpart of the truncated pseudo-inverse, a
    batched LU rather than an SVD per vertex and step; the model returned is the exact one of
    :func:`fit_details` for the chosen basis."""
    V = details.shape[1]
    n_add = min(max_poses, len(candidates))
    mask = np.zeros(V, dtype=bool)
    mask[error_vertices] = True
    systems = GrowingRbfSystems(details, n_add + 1, mask)
    n_error = int(mask.sum())
    basis, curve = [0], []
    while True:
        diff = features - features[basis[-1]]
        systems.add_column(np.sqrt(np.maximum(np.asarray(alpha @ (diff * diff).T), 0.0)))  # (V, E)
        weights, const, squared = systems.solve(rcond, exact=False)
        if observe is not None:
            observe(DetailModel("wpsd", features[basis], weights, const, alpha), list(basis))
        err = np.sqrt(squared / max(n_error, 1))
        curve.append({"poses": len(basis) - 1, "added": int(basis[-1]),
                      "mean_rms": float(err[1:].mean()), "max_rms": float(err.max())})
        if progress is not None:
            progress(len(basis) - 1, curve[-1])
        open_ = [int(c) for c in candidates if c not in basis]
        if len(basis) - 1 >= n_add or not open_ or err.max() <= tolerance:
            weights, const, _ = systems.solve(rcond, exact=True)
            return DetailModel("wpsd", features[basis], weights, const, alpha), basis, curve
        basis.append(open_[int(np.argmax(err[open_]))])
