"""Head stabilisation against an independent check: known rigid motions of known expressions."""

import numpy as np
import pytest

from facepipe.errors import InputError
from facepipe.stabilise import expression_fit, rigid_fit, stabilise


def _rotation(seed, degrees):
    axis = np.random.default_rng(seed).normal(size=3)
    axis /= np.linalg.norm(axis)
    a = np.radians(degrees)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def _rig(seed=0, H=30, E=5):
    rng = np.random.default_rng(seed)
    rest = rng.uniform(-8, 8, size=(H, 3))
    stable = np.zeros(H, bool)
    stable[:6] = True
    disp = rng.normal(scale=0.5, size=(E, H, 3))
    disp[:, :6] *= 0.1  # stable markers move a little with expressions, as on real skin
    prior = np.concatenate([rest[None], rest + disp])
    return rest, stable, prior, disp


def test_rigid_fit_recovers_a_known_motion():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(10, 3))
    R = _rotation(2, 25.0)
    t = np.array([1.0, -2.0, 0.5])
    R2, t2 = rigid_fit(src, src @ R.T + t)
    assert np.allclose(R2, R, atol=1e-12) and np.allclose(t2, t, atol=1e-12)
    # a zero weight ignores a point entirely
    tgt = src @ R.T + t
    tgt[3] += 50.0
    w = np.ones(10)
    w[3] = 0
    R3, _ = rigid_fit(src, tgt, w)
    assert np.allclose(R3, R, atol=1e-12)


def test_stabilise_is_exact_when_the_prior_explains_the_expression():
    rest, stable, prior, disp = _rig()
    T = 12
    w = np.random.default_rng(3).uniform(0, 1, size=(T, disp.shape[0]))
    head_true = rest + np.einsum("te,ehc->thc", w, disp)
    Rs = np.stack([_rotation(10 + i, 3.0 * i) for i in range(T)])
    ts = np.random.default_rng(4).normal(size=(T, 3))
    world = np.einsum("tij,thj->thi", Rs, head_true) + ts[:, None]
    head, R, t = stabilise(world, rest, stable, prior=prior)
    # exact up to the small ridge of the expression fit
    assert np.allclose(R, Rs, atol=1e-4)
    assert np.allclose(head, head_true, atol=2e-3)
    # without the prior the stable markers' own motion reads as head motion
    _, R0, _ = stabilise(world, rest, stable)
    assert np.abs(R0 - Rs).max() > 1e-3


def test_stabilise_with_missing_stable_markers_and_too_few():
    rest, stable, prior, _ = _rig()
    R = _rotation(5, 10.0)
    world = np.repeat((rest @ R.T)[None], 4, axis=0)
    world[1, 0] = np.nan
    world[2, :2] = np.nan
    head, R2, _ = stabilise(world, rest, stable, prior=prior)
    assert np.allclose(R2, R, atol=1e-8)
    world[3, :4] = np.nan
    with pytest.raises(InputError, match="frame 3: fewer than 3 stable markers"):
        stabilise(world, rest, stable, prior=prior)


def test_expression_fit_reproduces_prior_span_with_missing_markers():
    rest, _, prior, disp = _rig()
    head = rest + 0.4 * disp[1] + 0.7 * disp[3]
    head = head[None].copy()
    head[0, 10] = np.nan
    fitted = expression_fit(head, rest, prior, ridge=1e-9)
    assert np.allclose(fitted[0], rest + 0.4 * disp[1] + 0.7 * disp[3], atol=1e-5)
