"""The Whittaker smoother of any difference order, and the choice of order and λ, against dense
solves and against known signals in white noise (the independent checks: the normal equations
written out densely, and the truth the noisy series was made from)."""

from __future__ import annotations

import numpy as np
import pytest

from facepipe.core.temporal import LAMBDAS, noise_variance_share, row_decay, smooth_series, whittaker


def _dense_hat(T: int, lam: float, order: int) -> np.ndarray:
    D = np.diff(np.eye(T), order, axis=0)
    return np.linalg.inv(np.eye(T) + lam * D.T @ D)


@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_whittaker_of_any_order_is_the_dense_solve_and_keeps_lower_polynomials(order):
    T = 23
    rng = np.random.default_rng(order)
    y = rng.normal(size=(T, 3))
    np.testing.assert_allclose(whittaker(y, 5.0, order), _dense_hat(T, 5.0, order) @ y, atol=1e-10)
    # a polynomial of degree < order has no differences of that order: kept exactly, ends included
    s = np.linspace(-1.0, 1.0, T)
    poly = np.polyval(rng.normal(size=order), s)[:, None]
    np.testing.assert_allclose(whittaker(poly, 1e6, order), poly, atol=1e-8)
    share = noise_variance_share(T, 5.0, block=6, order=order)
    H = _dense_hat(T, 5.0, order)
    np.testing.assert_allclose(share, np.diag(H @ H.T), rtol=1e-8, atol=1e-12)
    assert share[0] > share[T // 2]  # an end keeps more noise than the middle


def test_too_short_a_series_for_an_order_is_left_alone():
    y = np.arange(4.0)[:, None] ** 3
    np.testing.assert_array_equal(whittaker(y, 10.0, order=4), y)
    np.testing.assert_array_equal(noise_variance_share(4, 10.0, order=4), np.ones(4))
    z, lam, _, order = smooth_series(np.random.default_rng(0).normal(size=(5, 2)), orders=(2, 3, 4))
    assert set(order) <= {2, 3}  # order 4 needs 6 frames to be a candidate


def test_the_order_and_lambda_chosen_have_the_least_gcv_and_risk():
    """Per group, the chosen (order, λ) minimises GCV (or, with the noise known, Mallows' C_p) over all
    candidates, each computed with dense hat matrices."""
    T = 40
    rng = np.random.default_rng(7)
    s = np.linspace(0.0, 1.0, T)
    y = np.stack([np.sin(6 * s), np.sin(6 * s + 1), 0.3 * s, 0.3 * s - 1.0], axis=1) + rng.normal(scale=0.05,
                                                                                                   size=(T, 4))
    groups = np.array([0, 0, 1, 1])
    orders = (2, 3, 4)
    lambdas = LAMBDAS[::3]
    for noise_var in (None, 0.0025):
        z, lam, share, order = smooth_series(y, groups, lambdas, noise_var=noise_var, orders=orders)
        for g in (0, 1):
            cols = groups == g

            def score(o, lam_):
                H = _dense_hat(T, lam_, o)
                rss = np.mean((y[:, cols] - H @ y[:, cols]) ** 2)
                if noise_var is None:
                    return rss / (1 - np.trace(H) / T) ** 2
                return rss - noise_var + 2 * noise_var * np.trace(H) / T

            best = min(score(o, lam_) for o in orders for lam_ in lambdas)
            if noise_var is not None:
                best = min(best, noise_var)  # λ = 0: no smoothing is a candidate with C_p
            chosen = score(order[g], lam[g]) if lam[g] > 0 else noise_var
            assert chosen <= best + 1e-12 * abs(best)
            H = _dense_hat(T, lam[g], order[g])
            np.testing.assert_allclose(z[:, cols], H @ y[:, cols], atol=1e-9)
            assert share[g] == pytest.approx(np.trace(H) / T)


def _smoothing_errors(truth: np.ndarray, draws: int, orders, rng) -> np.ndarray:
    """(T, draws · n) smoothed minus truth (T, n) of ``draws`` draws of unit white noise, each draw its
    own group (its own order and λ), all in one call."""
    T, n = truth.shape
    noisy = np.tile(truth, (1, draws)) + rng.normal(size=(T, draws * n))
    return smooth_series(noisy, groups=np.repeat(np.arange(draws), n), orders=orders)[0] - np.tile(truth, (1, draws))


def test_higher_orders_follow_a_motion_that_accelerates_at_the_ends():
    """A head turning back and forth (largest acceleration at the first and last frames), its
    per-frame estimates noisy, over many draws: with second differences alone the ends are
    continued as straight lines and come out worse than not smoothing at all; with the order
    chosen as well they are better than the raw frames and than second differences alone, and
    within 3× the error of the middle (where both sides help), though never as good."""
    T, draws = 60, 200
    rng = np.random.default_rng(11)
    s = np.arange(T)
    truth = 200.0 * np.cos(2 * np.pi * s / 70.0)[:, None] * np.array([1.0, 0.5, -0.3])
    errors = {}
    for orders in ((2,), (2, 3, 4)):
        errors[orders] = np.sqrt(np.mean(_smoothing_errors(truth, draws, orders, rng) ** 2, axis=1))  # (T,), unit noise
    ends, middle = [0, T - 1], slice(T // 4, 3 * T // 4)
    old, new = errors[(2,)], errors[(2, 3, 4)]
    assert old[ends].mean() > 1.0  # the straight continuation's bias: worse than the raw frames
    assert new[ends].max() < 1.0
    assert new[ends].mean() < 0.8 * old[ends].mean()
    assert new[ends].max() < 3.0 * np.sqrt(np.mean(new[middle] ** 2))
    assert np.mean(new[middle] ** 2) < np.mean(old[middle] ** 2)


def test_a_still_or_straight_series_loses_little_at_its_ends_to_the_higher_orders():
    """Where second differences are the right model (still, or moving straight), choosing among
    the higher orders as well costs the ends little (higher orders extrapolate with more noise)."""
    T, draws = 60, 200
    rng = np.random.default_rng(12)
    for truth in (np.zeros((T, 3)), np.linspace(0.0, 30.0, T)[:, None] * np.array([1.0, -1.0, 0.5])):
        ends = {}
        for orders in ((2,), (2, 3, 4)):
            ends[orders] = np.sqrt(np.mean(_smoothing_errors(truth, draws, orders, rng)[[0, -1]] ** 2))
        assert ends[(2, 3, 4)] < 1.25 * ends[(2,)]
        assert ends[(2, 3, 4)] < 0.5  # still far below the raw frames' noise


def test_row_decay_is_how_fast_the_hat_matrix_falls_off():
    lam = 3.0  # first differences: z + 1/z = 2 + 1/λ, in closed form
    b = 2.0 + 1.0 / lam
    assert row_decay(lam, 1) == pytest.approx((b - np.sqrt(b * b - 4.0)) / 2.0, rel=1e-12)
    for order, lam in [(1, 3.0), (2, 50.0), (3, 200.0), (4, 1000.0)]:
        H = _dense_hat(400, lam, order)
        row = np.abs(H[200, 200:330])
        # the envelope of a row (its peaks, where the solutions oscillate) shrinks by r a frame
        r = row_decay(lam, order)
        fitted = np.exp(np.polyfit(np.arange(40, 120), np.log(np.maximum.accumulate(row[::-1])[::-1][40:120]), 1)[0])
        assert fitted == pytest.approx(r, rel=0.02)


@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_noise_variance_share_on_windows_is_the_whole_takes(order):
    """Each block of H's rows is solved on a window around it (O(T) per strength): the same as the
    dense hat matrix's, up to the rounding of a system with condition number about 1 + λ 4^d."""
    T = 400
    for lam in LAMBDAS[::4]:
        H = _dense_hat(T, lam, order)
        share = noise_variance_share(T, lam, block=32, order=order)
        np.testing.assert_allclose(share, np.sum(H * H, axis=1), rtol=1e-13 * (1.0 + lam * 4.0**order) + 1e-10)
    # the light smoothings' windows were a part of the take: their rows fall below 1e-17 within 150 frames
    assert row_decay(1.0, order) ** 150 < 1e-17 / (1.0 + 4.0**order)
