import numpy as np
import scipy.sparse as sp

from facepipe.core.psd import (edge_weight_matrix, fit_details, greedy_basis, psd_distances, solve_rbf, wpsd_distances, wpsd_edge_weights)


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


def test_wpsd_distance_matches_brute_force():
    f, _ = _random_problem()
    index, weight = _alpha(30, f.shape[1])
    alpha = edge_weight_matrix(index, weight, f.shape[1])
    q = np.random.default_rng(7).normal(scale=0.1, size=(3, f.shape[1]))
    r = wpsd_distances(q, f, alpha)
    for a in range(3):
        for v in (0, 11, 29):
            for i in range(len(f)):
                ref = np.sqrt(sum(weight[v, k] * (q[a, index[v, k]] - f[i, index[v, k]]) ** 2 for k in range(5)))
                assert np.isclose(r[a, v, i], ref, rtol=1e-6)
    # PSD is WPSD with every edge weighted 1
    ones = sp.csr_matrix(np.ones((1, f.shape[1])))
    assert np.allclose(wpsd_distances(q, f, ones)[:, 0], psd_distances(q, f))


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


def test_solve_rbf_smoothing_keeps_system_solvable():
    f, d = _random_problem()
    phi = psd_distances(f, f)
    w, c = solve_rbf(phi, d, smoothing=0.1)
    assert np.isfinite(w).all() and np.isfinite(c).all()


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
    # a vertex far from everything still keeps its nearest edges
    far = np.full((M, 1), 1e6) + dist[:, :1]
    i2, w2 = wpsd_edge_weights(far, edges, rest, beta=10.0, min_weight=0.5, max_edges=8, min_keep=3)
    assert (w2 > 0).sum() >= 3 and np.isfinite(w2).all()


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


def test_pinv_solve_matches_the_pseudo_inverse():
    from facepipe.core.psd import pinv_solve

    rng = np.random.default_rng(4)
    n, P = 400, 6
    A = rng.normal(size=(n, P, P))
    A[::4, 2] = A[::4, 1]                      # exactly singular (duplicate rows and columns)
    A[::4, :, 2] = A[::4, :, 1]
    A[1::4, 3] = A[1::4, 0] * (1 + 1e-9)       # nearly singular: a singular value is cut
    A[2::4, 0] *= 1e3                          # badly scaled, as the weighted rest row
    b = rng.normal(size=(n, P, 3))
    for rcond in (1e-6, 1e-2):
        expected = np.linalg.pinv(A, rcond=rcond) @ b
        got = pinv_solve(A, b, rcond)
        scale = np.abs(expected).max(axis=(1, 2), keepdims=True)
        assert np.abs(got - expected).max(axis=(1, 2), keepdims=True).max() <= 1e-9 * scale.max()
        assert (np.abs(got - expected) <= 1e-9 * scale).all()
    # non-square (least squares) systems take the SVD
    A2, b2 = rng.normal(size=(20, 7, 4)), rng.normal(size=(20, 7, 3))
    assert np.allclose(pinv_solve(A2, b2, 1e-6), np.linalg.pinv(A2, rcond=1e-6) @ b2, rtol=0, atol=1e-13)
    A3, b3 = rng.normal(size=(20, 3, 5)), rng.normal(size=(20, 3, 2))  # and wide ones, and none
    assert np.allclose(pinv_solve(A3, b3, 1e-6), np.linalg.pinv(A3, rcond=1e-6) @ b3, rtol=0, atol=1e-13)
    assert pinv_solve(A3[:0], b3[:0], 1e-6).shape == (0, 5, 2)


def test_solve_rbf_the_same_in_threads_and_in_one():
    features, details = _random_problem(E=6, V=500)
    index, weight = _alpha(500, features.shape[1])
    alpha = edge_weight_matrix(index, weight, features.shape[1])
    phi = np.moveaxis(wpsd_distances(features, features, alpha), 1, 0)
    one = solve_rbf(phi, details, chunk=10_000)   # one block
    many = solve_rbf(phi, details, chunk=37)      # blocks in threads
    assert np.array_equal(one[0], many[0]) and np.array_equal(one[1], many[1])
