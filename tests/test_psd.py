import inspect

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from facepipe.core import psd
from facepipe.core.psd import (batched_inverse, edge_weight_matrix, fit_details, greedy_basis, psd_distances, solve_rbf, wpsd_distances, wpsd_edge_weights)


def _random_problem(E=7, F=12, V=30, seed=0):
    rng = np.random.default_rng(seed)
    features = rng.normal(scale=0.1, size=(E, F))
    features[0] = 0.0
    details = rng.normal(scale=0.05, size=(E, V, 3))
    details[0] = 0.0
    return features, details


def _alpha(V, F, K=5, seed=1):
    rng = np.random.default_rng(seed)
    index = np.stack([rng.choice(F, K, replace=False) for _ in range(V)]).astype(np.int32)
    weight = rng.uniform(0.1, 1.0, size=(V, K))
    weight /= weight.sum(axis=1, keepdims=True)
    return index, weight.astype(np.float32)


def test_psd_interpolates_basis_exactly():
    f, d = _random_problem()
    model = fit_details("psd", f, d, list(range(len(f))), "interpolate")
    assert np.abs(model.evaluate(f) - d).max() < 1e-9


def test_wpsd_interpolates_basis_exactly_when_poses_differ_locally():
    f, d = _random_problem()
    index, weight = _alpha(d.shape[1], f.shape[1])
    alpha = edge_weight_matrix(index, weight, f.shape[1])
    model = fit_details("wpsd", f, d, list(range(len(f))), "interpolate", alpha)
    assert np.abs(model.evaluate(f) - d).max() < 1e-7


def test_psd_kernel_is_the_distance_in_pose_space():
    f, _ = _random_problem()
    q = np.random.default_rng(7).normal(scale=0.1, size=(4, f.shape[1]))
    direct = np.array([[np.sqrt(sum((q[a, e] - f[i, e]) ** 2 for e in range(f.shape[1]))) for i in range(len(f))]
                       for a in range(len(q))])
    assert np.allclose(psd_distances(q, f), direct, rtol=1e-13, atol=0)
    model = fit_details("psd", f, _random_problem()[1], [0, 2, 5], "interpolate")
    assert np.allclose(model.distances(q), direct[:, [0, 2, 5]], rtol=1e-13, atol=0)
    assert np.array_equal(np.diag(psd_distances(f, f)), np.zeros(len(f)))


def test_wpsd_distance_matches_brute_force():
    f, _ = _random_problem()
    index, weight = _alpha(30, f.shape[1])
    alpha = edge_weight_matrix(index, weight, f.shape[1])
    q = np.random.default_rng(7).normal(scale=0.1, size=(3, f.shape[1]))
    r = wpsd_distances(q, f, alpha, chunk=7)  # several blocks of vertices
    for a in range(3):
        for v in range(30):
            for i in range(len(f)):
                ref = np.sqrt(sum(float(weight[v, k]) * (q[a, index[v, k]] - f[i, index[v, k]]) ** 2 for k in range(5)))
                assert np.isclose(r[a, v, i], ref, rtol=1e-12, atol=0)
    # PSD is WPSD with every edge weighted 1
    ones = sp.csr_matrix(np.ones((1, f.shape[1])))
    assert np.allclose(wpsd_distances(q, f, ones)[:, 0], psd_distances(q, f), rtol=1e-13, atol=0)


def test_cardinal_functions_interpolate_and_sum_to_one():
    """With one vertex per basis pose, detail 1 at its pose and 0 at the others, the fitted functions
    are the cardinal functions: δ at the basis poses and, as constants are reproduced, a
    partition of unity everywhere (PSD, and WPSD with the same edge weights at every vertex)."""
    f, _ = _random_problem(E=6)
    P = len(f)
    d = np.zeros((P, P, 3))
    d[np.arange(P), np.arange(P), 0] = 1.0
    far = np.random.default_rng(3).normal(scale=0.2, size=(9, f.shape[1]))
    index, weight = _alpha(1, f.shape[1])
    same = edge_weight_matrix(np.repeat(index, P, 0), np.repeat(weight, P, 0), f.shape[1])
    for method, alpha in (("psd", None), ("wpsd", same)):
        model = fit_details(method, f, d, list(range(P)), "interpolate", alpha)
        assert np.allclose(model.evaluate(f)[..., 0], np.eye(P), rtol=0, atol=1e-9)
        assert np.allclose(model.evaluate(far)[..., 0].sum(axis=1), 1.0, rtol=0, atol=1e-9)
        assert np.allclose(model.evaluate(far)[..., 1:], 0.0, rtol=0, atol=1e-12)


def test_constant_details_reproduced_everywhere():
    f, d = _random_problem()
    d[:] = np.array([0.1, -0.2, 0.3])
    model = fit_details("psd", f, d, list(range(len(f))), "interpolate")
    far = np.random.default_rng(3).normal(size=(5, f.shape[1]))
    assert np.allclose(model.evaluate(far), d[0], atol=1e-9)


def test_coincident_poses_are_averaged_not_blown_up():
    f, d = _random_problem()
    f[3] = f[2]  # two poses with the same strain but different details
    model = fit_details("psd", f, d, list(range(len(f))), "interpolate")
    assert np.abs(model.weights).max() < 1e3
    pred = model.evaluate(f[2:3])[0]
    assert np.allclose(pred, 0.5 * (d[2] + d[3]), atol=1e-6)


def test_least_squares_recovers_a_true_rbf():
    f, _ = _random_problem(E=20)
    basis = [0, 3, 7, 11]
    rng = np.random.default_rng(9)
    w = rng.normal(size=(30, len(basis), 3))
    w -= w.mean(axis=1, keepdims=True)  # the side condition Σ w = 0
    c = rng.normal(size=(30, 3))
    phi = psd_distances(f, f[basis])
    d = np.einsum("ep,vpc->evc", phi, w) + c
    model = fit_details("psd", f, d, basis, "least-squares")
    assert np.allclose(model.weights, w, atol=1e-8)
    assert np.allclose(model.const, c, atol=1e-8)


def _bordered(phi):
    """[Φ s·1; s·1ᵀ 0] with s = mean |Φ|, the system solve_rbf solves (s scales the constant)."""
    R, P = phi.shape
    s = np.abs(phi).mean()
    A = np.zeros((R + 1, P + 1))
    A[:R, :P] = phi
    A[:R, P] = s
    A[R, :P] = s
    return A, s


def test_solve_rbf_smoothing_solves_the_shifted_system():
    f, d = _random_problem()
    phi = psd_distances(f, f)
    lam = 0.1
    w, c = solve_rbf(phi, d, smoothing=lam)
    A, s = _bordered(phi)
    A[:len(f), :len(f)] -= lam * s * np.eye(len(f))  # Φ − λ s I
    rhs = np.concatenate([d.reshape(len(f), -1), np.zeros((1, d.shape[1] * 3))])
    x = np.linalg.solve(A, rhs).reshape(len(f) + 1, -1, 3)
    assert np.allclose(w, np.moveaxis(x[:-1], 0, 1), rtol=0, atol=1e-10)
    assert np.allclose(c, x[-1] * s, rtol=0, atol=1e-10)


def test_solve_rbf_matches_lstsq():
    """Interpolation: the bordered system's solution (numpy's LAPACK least squares of a square,
    non-singular system). Least squares over more poses than basis poses: the rest row met
    exactly, the other rows in the least-squares sense — by lstsq on the constraint's null space."""
    f, d = _random_problem(E=12, V=5)
    phi = psd_distances(f, f[:7])
    for rows in (slice(0, 7), slice(None)):
        p, targets = phi[rows], d[rows]
        w, c = solve_rbf(p, targets)
        A, s = _bordered(p)
        b = np.concatenate([targets.reshape(len(p), -1), np.zeros((1, targets.shape[1] * 3))])
        if len(p) == p.shape[1]:
            x = np.linalg.lstsq(A, b, rcond=None)[0]
        else:
            N = scipy.linalg.null_space(A[:1])
            x0 = A[0][:, None] * b[:1] / (A[0] @ A[0])
            x = x0 + N @ np.linalg.lstsq(A[1:] @ N, b[1:] - A[1:] @ x0, rcond=None)[0]
            assert np.allclose(A[0] @ x, 0.0, rtol=0, atol=1e-14)  # the rest pose stays still
        x = x.reshape(p.shape[1] + 1, -1, 3)
        assert np.allclose(w, np.moveaxis(x[:-1], 0, 1), rtol=0, atol=1e-10)
        assert np.allclose(c, x[-1] * s, rtol=0, atol=1e-10)


def test_rest_pose_is_met_exactly_where_another_pose_looks_like_it():
    """A pose with the rest pose's strain but other details (a one-sided expression seen from the
    other cheek) is averaged away, and the rest pose still comes out as exactly zero."""
    f, d = _random_problem()
    f[4] = f[0]
    model = fit_details("psd", f, d, list(range(len(f))), "interpolate")
    assert np.abs(model.evaluate(f[:1])).max() < 1e-14
    assert np.abs(model.weights).max() < 1e3


def test_cut_off_does_not_move_with_the_rest_row_weight(monkeypatch):
    """Two poses 1e-5 apart (relative): with rcond = 1e-6 nothing is to be cut. How heavily the
    rest row is weighted must not decide that (it once scaled σ_max and so the cut-off)."""
    f, d = _random_problem(E=8)
    rng = np.random.default_rng(11)
    f[5] = f[4] + 1e-5 * np.abs(f).max() * rng.normal(size=f.shape[1])
    results = {}
    for weight in (1.0, 1e3, 1e6):
        monkeypatch.setattr(psd, "REST_ROW_WEIGHT", weight)
        for fit in ("interpolate", "least-squares"):
            basis = list(range(len(f))) if fit == "interpolate" else [0, 1, 2, 4, 5]
            model = fit_details("psd", f, d, basis, fit, rcond=1e-6)
            results.setdefault(fit, []).append(np.concatenate([model.weights.ravel(), model.const.ravel()]))
    for fit, xs in results.items():
        scale = np.abs(xs[0]).max()
        for x in xs[1:]:
            assert np.abs(x - xs[0]).max() <= 1e-8 * scale, fit


def test_no_private_numpy_api():
    assert "_umath_linalg" not in inspect.getsource(psd)


def test_batched_inverse_is_numpys_inverse_and_nan_where_singular():
    rng = np.random.default_rng(2)
    A = rng.integers(-2, 3, size=(500, 5, 5)).astype(float)  # small integers: many exactly singular
    A[::7, 3] = A[::7, 1]
    inv = batched_inverse(A)
    singular = 0
    for a, i in zip(A, inv):  # numpy's inverse of each matrix alone: the same, or raises
        try:
            expected = np.linalg.inv(a)
        except np.linalg.LinAlgError:
            singular += 1
            assert np.isnan(i).all()
        else:
            assert np.array_equal(i, expected)
    assert 0 < singular < len(A)
    assert batched_inverse(A[:0]).shape == (0, 5, 5)
    regular = A[np.isfinite(inv).all(axis=(1, 2))]  # no singular one: the stack in one call, the same bits
    assert np.array_equal(batched_inverse(regular), inv[np.isfinite(inv).all(axis=(1, 2))])


def test_rest_exact_solve_sends_repeated_rows_to_the_pseudo_inverse_alone():
    """Systems with two equal rows (coincident poses) skip the inverse: each system of a stack
    mixing them with regular and nearly singular ones is solved as when solved alone, and the
    repeated ones exactly as the constrained pseudo-inverse solves them."""
    from facepipe.core.psd import DEFAULT_RCOND, constrained_pinv_solve, repeated_rows, rest_exact_solve

    rng = np.random.default_rng(5)
    n, P = 60, 6
    pts = rng.normal(size=(n, P, 3))
    pts[::3, 4] = pts[::3, 2]            # two coincident poses
    pts[1::3, 3] = pts[1::3, 0]          # a pose coincident with the rest pose
    pts[2::6, 5] = pts[2::6, 1] + 1e-9   # nearly coincident: not repeated, but cut
    A = np.zeros((n, P + 1, P + 1))
    A[:, :P, :P] = np.linalg.norm(pts[:, :, None] - pts[:, None, :], axis=-1)
    A[:, :P, P] = A[:, P, :P] = 1.0
    b = np.concatenate([np.zeros((n, 1, 3)), rng.normal(size=(n, P - 1, 3)), np.zeros((n, 1, 3))], axis=1)
    singular = repeated_rows(A)
    assert singular[::3].all() and singular[1::3].all() and not singular[2::3].any()
    x = rest_exact_solve(A, b, DEFAULT_RCOND)
    for k in range(n):
        assert np.array_equal(x[k], rest_exact_solve(A[k:k + 1], b[k:k + 1], DEFAULT_RCOND)[0])
    assert np.array_equal(x[singular], constrained_pinv_solve(A[singular], b[singular], DEFAULT_RCOND))
    assert np.allclose(np.einsum("nij,njc->nic", A[:, :1], x), 0.0, atol=1e-12)  # the rest row, exactly
    regular = np.flatnonzero(~singular)[1::2]
    assert np.allclose(np.einsum("nij,njc->nic", A[regular], x[regular]), b[regular], atol=1e-9)


def test_edge_weights_normalised_bounded_and_local():
    rng = np.random.default_rng(0)
    M, V = 10, 50
    markers = rng.uniform(0, 10, size=(M, 2))
    verts = rng.uniform(0, 10, size=(V, 2))
    dist = np.linalg.norm(markers[:, None] - verts[None], axis=-1)
    edges = np.array([[i, j] for i in range(M) for j in range(i + 1, M)])
    rest = np.linalg.norm(markers[edges[:, 0]] - markers[edges[:, 1]], axis=1)
    index, weight = wpsd_edge_weights(dist, edges, rest, beta=1.0, min_weight=0.05, max_edges=8, min_keep=3)
    assert index.shape == (V, 8)
    assert np.allclose(weight.sum(axis=1), 1.0, atol=1e-6)
    assert ((weight > 0).sum(axis=1) >= 3).all()
    assert (weight[weight > 0] >= 0.05 - 1e-7).all() or ((weight > 0).sum(axis=1) == 3).any()
    # the heaviest edge of each vertex is the one it is closest to (smallest L − l)
    excess = (dist[edges[:, 0]] + dist[edges[:, 1]] - rest[:, None]).T
    assert (index[:, 0] == excess.argmin(axis=1)).all()
    # against the definition, vertex by vertex: the 8 edges of largest α ∝ exp(−β (L − l)),
    # normalised, those under 5 % dropped unless among the largest 3, normalised again
    for v in range(V):
        order = np.argsort(excess[v], kind="stable")[:8]
        keep = np.exp(-1.0 * excess[v, order])
        keep /= keep.sum()
        keep = np.where((keep < 0.05) & (np.arange(8) >= 3), 0.0, keep)
        assert np.array_equal(index[v], order)
        assert np.allclose(weight[v], keep / keep.sum(), rtol=1e-6, atol=1e-7)
    # a vertex far from everything still keeps its nearest edges, with the weights they would have
    # without the offset (which cancels out in the normalisation)
    far = np.full((M, 1), 1e6) + dist[:, :1]
    i2, w2 = wpsd_edge_weights(far, edges, rest, beta=10.0, min_weight=0.5, max_edges=8, min_keep=3)
    i1, w1 = wpsd_edge_weights(dist[:, :1], edges, rest, beta=10.0, min_weight=0.5, max_edges=8, min_keep=3)
    assert (w2 > 0).sum() >= 3
    assert np.array_equal(i2[w2 > 0], i1[w1 > 0]) and np.allclose(w2, w1, rtol=1e-5, atol=1e-6)


def test_a_vertex_no_marker_reaches_keeps_no_edge():
    """Vertices of a separate part (every geodesic distance inf) weigh no edge — no NaN — so their
    WPSD distances are 0 and a fit gives them no details; the others are as without them."""
    rng = np.random.default_rng(1)
    M, V = 6, 20
    dist = rng.uniform(0.0, 5.0, size=(M, V))
    dist[:, 15:] = np.inf
    edges = np.array([[i, j] for i in range(M) for j in range(i + 1, M)])
    rest = rng.uniform(0.5, 1.0, size=len(edges))
    index, weight = wpsd_edge_weights(dist, edges, rest, beta=1.0, max_edges=8)
    assert np.isfinite(weight).all() and (weight[15:] == 0).all()
    np.testing.assert_allclose(weight[:15].sum(axis=1), 1.0, atol=1e-6)
    i0, w0 = wpsd_edge_weights(dist[:, :15], edges, rest, beta=1.0, max_edges=8)
    assert np.array_equal(index[:15], i0) and np.array_equal(weight[:15], w0)
    alpha = edge_weight_matrix(index, weight, len(edges))
    features = rng.normal(0, 0.1, size=(4, len(edges)))
    features[0] = 0.0  # the rest pose
    details = rng.normal(0, 0.01, size=(4, V, 3))
    details[0] = 0.0
    model = fit_details("wpsd", features, details, [0, 1, 2, 3], "interpolate", alpha)
    out = model.evaluate(features)
    assert np.isfinite(out).all() and (out[:, 15:] == 0).all()
    np.testing.assert_allclose(out[:, :15], details[:, :15], atol=1e-9)


def test_greedy_starts_from_rest_and_reaches_zero_error_with_all_poses():
    f, d = _random_problem()
    model, basis, curve = greedy_basis("psd", f, d, "interpolate", max_poses=len(f) - 1)
    assert basis[0] == 0 and sorted(basis) == list(range(len(f)))
    assert curve[0]["poses"] == 0 and curve[-1]["max_rms"] < 1e-9
    # the first pose added is the worst fit by the rest pose alone (largest detail)
    rms = np.sqrt((d ** 2).sum(-1).mean(-1))
    assert basis[1] == int(np.argmax(rms[1:]) + 1)


def test_greedy_stops_at_tolerance():
    f, d = _random_problem()
    _, basis, curve = greedy_basis("psd", f, d, "interpolate", max_poses=6, tolerance=1.0)
    assert basis == [0] and len(curve) == 1


def _brute_force_greedy(f, d, steps):
    """The greedy rule written out: interpolate the basis by the bordered system, score every
    pose by its RMS error, add the worst pose not yet in the basis."""
    basis, curve = [0], []
    for _ in range(steps + 1):
        P = len(basis)
        phi = np.array([[np.linalg.norm(f[i] - f[j]) for j in basis] for i in basis])
        M = np.block([[phi, np.ones((P, 1))], [np.ones((1, P)), np.zeros((1, 1))]])
        rhs = np.concatenate([d[basis].reshape(P, -1), np.zeros((1, d.shape[1] * 3))])
        x = np.linalg.solve(M, rhs)
        q = np.array([[np.linalg.norm(f[e] - f[j]) for j in basis] for e in range(len(f))])
        pred = (q @ x[:P] + x[P]).reshape(d.shape)
        err = np.sqrt(((pred - d) ** 2).sum(-1).mean(-1))
        curve.append(err.max())
        open_ = [e for e in range(1, len(f)) if e not in basis]
        if len(curve) > steps or not open_:
            break
        basis.append(open_[int(np.argmax(err[open_]))])
    return basis, curve


def test_greedy_picks_what_brute_force_picks():
    for seed in range(4):
        f, d = _random_problem(E=7, V=6, seed=seed)
        _, basis, curve = greedy_basis("psd", f, d, "interpolate", max_poses=5)
        ref_basis, ref_curve = _brute_force_greedy(f, d, 5)
        assert basis == ref_basis
        assert np.allclose([c["max_rms"] for c in curve], ref_curve, rtol=1e-9, atol=1e-12)


def test_svd_solve_matches_the_pseudo_inverse():
    from facepipe.core.psd import svd_solve

    rng = np.random.default_rng(4)
    n, P = 400, 6
    A = rng.normal(size=(n, P, P))
    A[::4, 2] = A[::4, 1]                      # exactly singular (duplicate rows and columns)
    A[::4, :, 2] = A[::4, :, 1]
    A[1::4, 3] = A[1::4, 0] * (1 + 1e-9)       # nearly singular: a singular value is cut
    b = rng.normal(size=(n, P, 3))
    for rcond in (1e-6, 1e-2):
        expected = np.linalg.pinv(A, rcond=rcond) @ b
        scale = np.abs(expected).max(axis=(1, 2), keepdims=True)
        assert (np.abs(svd_solve(A, b, rcond) - expected) <= 1e-9 * scale).all()
    # non-square (least squares and wide) systems
    A2, b2 = rng.normal(size=(20, 7, 4)), rng.normal(size=(20, 7, 3))
    assert np.allclose(svd_solve(A2, b2, 1e-6), np.linalg.pinv(A2, rcond=1e-6) @ b2, rtol=0, atol=1e-13)
    A3, b3 = rng.normal(size=(20, 3, 5)), rng.normal(size=(20, 3, 2))
    assert np.allclose(svd_solve(A3, b3, 1e-6), np.linalg.pinv(A3, rcond=1e-6) @ b3, rtol=0, atol=1e-13)


def test_truncated_solve_matches_the_pseudo_inverse_by_either_route():
    """The normal equations (cut-offs from NORMAL_EQUATIONS_MIN_RCOND up) and the SVD (below it)
    give ``pinv(A, rcond) @ b``: exactly singular, nearly singular and regular systems, square
    and least squares."""
    from facepipe.core.psd import NORMAL_EQUATIONS_MIN_RCOND, svd_solve, truncated_solve

    rng = np.random.default_rng(7)
    n, P = 400, 7
    A = rng.normal(size=(n, P, P)) * rng.uniform(0.1, 10.0, size=(n, 1, 1))
    A[::4, 2] = A[::4, 1]                      # exactly singular (duplicate rows and columns)
    A[::4, :, 2] = A[::4, :, 1]
    A[1::4, 3] = A[1::4, 0] * (1 + 1e-9)       # nearly singular: a singular value is cut
    b = rng.normal(size=(n, P, 3))
    tall = rng.normal(size=(50, 12, 5))
    tall[:, :, 4] = tall[:, :, 3] * (1 + 1e-10)
    b_tall = rng.normal(size=(50, 12, 2))
    for rcond in (NORMAL_EQUATIONS_MIN_RCOND, 3e-4, 1e-2, 1e-9):
        for M, rhs in ((A, b), (tall, b_tall)):
            expected = np.linalg.pinv(M, rcond=rcond) @ rhs
            scale = np.abs(expected).max(axis=(1, 2), keepdims=True)
            got = truncated_solve(M, rhs, rcond)
            assert (np.abs(got - expected) <= 1e-7 * scale).all(), rcond
            if rcond < NORMAL_EQUATIONS_MIN_RCOND:  # the SVD route, as it was
                assert np.array_equal(got, svd_solve(M, rhs, rcond))
    assert truncated_solve(np.zeros((0, 3, 3)), np.zeros((0, 3, 1)), 3e-4).shape == (0, 3, 1)
    assert not truncated_solve(np.zeros((2, 3, 3)), np.ones((2, 3, 1)), 3e-4).any()  # nothing to keep


def test_solve_rbf_the_same_in_threads_and_in_one():
    features, details = _random_problem(E=6, V=500)
    index, weight = _alpha(500, features.shape[1])
    alpha = edge_weight_matrix(index, weight, features.shape[1])
    phi = np.moveaxis(wpsd_distances(features, features, alpha), 1, 0)
    one = solve_rbf(phi, details, chunk=10_000)   # one block
    many = solve_rbf(phi, details, chunk=37)      # blocks in threads
    assert np.array_equal(one[0], many[0]) and np.array_equal(one[1], many[1])


def test_edge_weight_matrix_is_the_coordinate_lists_matrix():
    """The α matrix equals SciPy's from a coordinate list (its columns sorted, a repeated slot
    summed, the unused slots' zeros dropped), bit for bit."""
    rng = np.random.default_rng(6)
    index = rng.integers(0, 7, size=(500, 5)).astype(np.int32)  # repeats within a row, too
    weight = rng.random((500, 5)).astype(np.float32)
    weight[weight < 0.3] = 0.0
    given = index.copy(), weight.copy()
    W = edge_weight_matrix(index, weight, 7)
    assert np.array_equal(index, given[0]) and np.array_equal(weight, given[1])  # the caller's arrays untouched
    rows = np.repeat(np.arange(500), 5)
    ref = sp.csr_matrix((weight.ravel().astype(np.float64), (rows, index.ravel())), shape=(500, 7))
    ref.eliminate_zeros()
    assert W.has_canonical_format and W.nnz == ref.nnz
    assert np.array_equal(W.indptr, ref.indptr) and np.array_equal(W.indices, ref.indices)
    assert np.array_equal(W.data, ref.data)
