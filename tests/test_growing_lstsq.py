"""The grown least-squares WPSD systems against the RBF solve of every basis afresh."""

import numpy as np

from facepipe.core.growing_lstsq import GrowingRbfSystems, tikhonov_normal_solve, truncated_normal_solve
from facepipe.core.psd import (edge_weight_matrix, fit_details, greedy_basis, kernel_matrix, rms_per_pose,
                               solve_rbf)


def _problem(seed=0, E=24, V=40, F=12, K=4):
    rng = np.random.default_rng(seed)
    features = np.concatenate([np.zeros((1, F)), rng.normal(scale=0.1, size=(E - 1, F))])
    details = rng.normal(size=(E, V, 3))
    details[0] = 0.0
    index = np.stack([rng.choice(F, K, replace=False) for _ in range(V)])
    weight = rng.uniform(0.1, 1.0, size=(V, K))
    weight /= weight.sum(axis=1, keepdims=True)
    return features, details, edge_weight_matrix(index, weight, F)


def _grown(features, details, alpha, basis):
    systems = GrowingRbfSystems(details, len(basis), np.ones(details.shape[1], dtype=bool), chunk=16)
    for p in basis:
        systems.add_column(np.moveaxis(kernel_matrix("wpsd", features, features[[p]], alpha)[..., 0], 0, 1))
    return systems


def test_grown_systems_give_the_fresh_truncated_solve():
    features, details, alpha = _problem()
    basis = [0, 5, 3, 17, 9, 11, 2]
    for n in range(1, len(basis) + 1):
        weights, const, squared = _grown(features, details, alpha, basis[:n]).solve(3e-4, exact=True)
        fresh = fit_details("wpsd", features, details, basis[:n], "least-squares", alpha)
        np.testing.assert_allclose(weights, fresh.weights, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(const, fresh.const, rtol=1e-6, atol=1e-8)
        err = rms_per_pose(fresh.evaluate(features), details)
        np.testing.assert_allclose(np.sqrt(squared / details.shape[1]), err, rtol=1e-8, atol=1e-12)


def test_tikhonov_scores_are_the_damped_least_squares_solution():
    """A second implementation: the constrained system eliminated by a null-space basis of the rest
    row and the damped least squares solved by lstsq on the stacked system [C; √λ I]."""
    features, details, alpha = _problem(seed=3, E=14, V=6)
    basis = [0, 4, 9, 2]
    weights, const, _ = _grown(features, details, alpha, basis).solve(1e-2, exact=False)
    phi = np.moveaxis(kernel_matrix("wpsd", features, features[basis], alpha), 1, 0)  # (V, E, P)
    P = len(basis)
    for v in range(details.shape[1]):
        s = np.abs(phi[v]).mean()
        A = np.zeros((len(features) + 1, P + 1))
        A[:-1, :P], A[:-1, P], A[-1, :P] = phi[v], s, s
        b = np.concatenate([details[:, v], np.zeros((1, 3))])
        # x = x0 + N y with a0·x0 = b0 and a0·N = 0
        a0 = A[0]
        x0 = np.outer(a0, b[0]) / (a0 @ a0)
        N = np.linalg.svd(a0[None])[2][1:].T
        C, r = A[1:] @ N, b[1:] - A[1:] @ x0
        lam = 1e-4 * np.trace(C.T @ C)
        y = np.linalg.lstsq(np.vstack([C, np.sqrt(lam) * np.eye(P)]), np.vstack([r, np.zeros((P, 3))]),
                            rcond=None)[0]
        x = x0 + N @ y
        np.testing.assert_allclose(weights[v], x[:P], rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(const[v], x[P] * s, rtol=1e-6, atol=1e-9)


def test_greedy_least_squares_wpsd_returns_the_exact_model_of_its_basis():
    features, details, alpha = _problem()
    seen = []
    model, basis, curve = greedy_basis("wpsd", features, details, "least-squares", 9, alpha=alpha,
                                       observe=lambda m, b: seen.append(list(b)))
    assert len(basis) == 10 and len(set(basis)) == 10 and basis[0] == 0 and seen[-1] == basis
    fresh = fit_details("wpsd", features, details, basis, "least-squares", alpha)
    np.testing.assert_allclose(model.weights, fresh.weights, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(model.evaluate(features[:1]), 0.0, atol=1e-10)  # the rest pose exactly
    assert curve[-1]["mean_rms"] < curve[0]["mean_rms"]


def test_normal_solves_against_the_pseudo_inverse():
    rng = np.random.default_rng(2)
    C = rng.normal(size=(5, 9, 4))
    C[:, :, 3] = C[:, :, 2] * (1 + 1e-9)  # a nearly dependent column: cut
    r = rng.normal(size=(5, 9, 2))
    N, Ctr = np.swapaxes(C, 1, 2) @ C, np.swapaxes(C, 1, 2) @ r
    want = np.stack([np.linalg.pinv(c, rcond=1e-4) @ b for c, b in zip(C, r)])
    np.testing.assert_allclose(truncated_normal_solve(N, Ctr, 1e-4), want, rtol=1e-6, atol=1e-8)
    # the damped solution tends to the truncated one as the damping vanishes
    np.testing.assert_allclose(tikhonov_normal_solve(N, Ctr, 1e-6), want, rtol=1e-3, atol=1e-4)
    assert np.isfinite(solve_rbf(np.zeros((3, 2)), np.zeros((3, 1, 3)))[0]).all()
