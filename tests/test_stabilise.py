"""Rigid and similarity fits against known transforms; robust fits with outliers; pose interpolation."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facepipe.core.rigid import interpolate_poses, rigid_fit, robust_rigid_fit, similarity_fit


def _motion(seed, degrees=20.0):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    R = Rotation.from_rotvec(np.radians(degrees) * axis / np.linalg.norm(axis)).as_matrix()
    return R, rng.normal(scale=3.0, size=3)


def test_similarity_fit_recovers_scale_rotation_translation():
    P = np.random.default_rng(0).normal(scale=5.0, size=(12, 3))
    R, t = _motion(1, 35.0)
    s, R2, t2 = similarity_fit(P, 0.1 * P @ R.T + t)  # e.g. mm read as cm
    assert s == pytest.approx(0.1, rel=1e-12)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12)
    # batched, with a zero weight ignoring a wild point
    Q = np.stack([2.0 * P @ R.T + t, P.copy()])
    Q[0, 4] += 100.0
    w = np.ones((2, 12))
    w[0, 4] = 0
    s, R3, _ = similarity_fit(P, Q, w)
    np.testing.assert_allclose(s, [2.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(R3[0], R, atol=1e-12)
    np.testing.assert_allclose(R3[1], np.eye(3), atol=1e-12)


def test_similarity_fit_never_reflects():
    P = np.random.default_rng(2).normal(size=(8, 3))
    _, R, _ = similarity_fit(P, P * [-1.0, 1.0, 1.0])  # a mirror image: best proper rotation
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_robust_rigid_fit_ignores_jumping_points():
    rng = np.random.default_rng(3)
    src = rng.normal(scale=6.0, size=(10, 3))
    R, t = _motion(4)
    tgt = np.repeat((src @ R.T + t)[None], 3, axis=0)
    tgt[0, 2] += [4.0, -3.0, 2.0]  # one marker jumped
    tgt[1, [1, 5]] += 2.0  # two slid
    tgt[2, 7] = np.nan  # missing
    R2, t2, w = robust_rigid_fit(src, tgt)
    np.testing.assert_allclose(R2, np.repeat(R[None], 3, 0), atol=1e-6)
    np.testing.assert_allclose(t2, np.repeat(t[None], 3, 0), atol=1e-5)
    assert w[0, 2] < 1e-6 and w[2, 7] == 0 and w[0, 0] == pytest.approx(1.0)
    # plain Kabsch is pulled off by the jump
    R3, _ = rigid_fit(src, np.nan_to_num(tgt[0]))
    assert np.abs(R3 - R).max() > 1e-3


def test_robust_rigid_fit_ignores_missing_source_points():
    # a missing point of the source (a neutral take's first frame) is left out like a missing
    # target point: a finite pose, the one fitted to the visible points alone
    rng = np.random.default_rng(5)
    src = rng.normal(scale=6.0, size=(9, 3))
    R, t = _motion(6)
    tgt = np.repeat((src @ R.T + t)[None], 3, axis=0) + rng.normal(scale=0.01, size=(3, 9, 3))
    tgt[1, 4] += [3.0, 0.0, -2.0]  # a jump, so the reweighting matters
    tgt[2, 6] = np.nan
    gappy = src.copy()
    gappy[2] = np.nan
    R2, t2, w = robust_rigid_fit(gappy, tgt)
    vis = np.arange(9) != 2
    R3, t3, w3 = robust_rigid_fit(src[vis], tgt[:, vis])
    assert np.isfinite(R2).all() and np.isfinite(t2).all()
    np.testing.assert_allclose(R2, R3, rtol=0, atol=1e-12)
    np.testing.assert_allclose(t2, t3, rtol=0, atol=1e-12)
    assert (w[:, 2] == 0).all()
    np.testing.assert_allclose(w[:, vis], w3, rtol=0, atol=1e-12)
    # per frame sources, one missing a point in one frame only
    per_frame = np.repeat(src[None], 3, axis=0)
    per_frame[1, 2] = np.nan
    R4, t4, w4 = robust_rigid_fit(per_frame, tgt)
    R5, t5, _ = robust_rigid_fit(src[vis], tgt[1:2, vis])
    np.testing.assert_allclose(R4[1], R5[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(t4[1], t5[0], rtol=0, atol=1e-12)
    assert w4[1, 2] == 0 and (w4[[0, 2], 2] > 0).all()


def test_robust_rigid_fit_needs_three_points():
    src = np.eye(3)
    tgt = np.array([[[1.0, 0, 0], [0, 1, 0], [np.nan] * 3], [[1.0, 0, 0], [0, 1, 0], [0, 0, 1]]])
    R, t, _ = robust_rigid_fit(src, tgt)
    assert np.isnan(R[0]).all() and np.isnan(t[0]).all()
    np.testing.assert_allclose(R[1], np.eye(3), atol=1e-12)


def test_interpolate_poses_slerps_between_known_frames():
    R0, R1 = np.eye(3), Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix()
    R = np.stack([R0, np.full((3, 3), np.nan), R1, np.full((3, 3), np.nan)])
    t = np.array([[0.0, 0, 0], [np.nan] * 3, [2.0, 0, 0], [np.nan] * 3])
    R2, t2, filled = interpolate_poses(R, t, times=np.array([0.0, 0.5, 1.0, 2.0]))
    np.testing.assert_allclose(R2[1], Rotation.from_rotvec([0, 0, np.pi / 4]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(t2[1], [1.0, 0, 0])
    np.testing.assert_allclose(R2[3], R1)  # held after the last known frame
    assert filled.tolist() == [False, True, False, True]
    with pytest.raises(ValueError):
        interpolate_poses(np.full((2, 3, 3), np.nan), np.full((2, 3), np.nan))


def _rotation(seed, degrees):
    axis = np.random.default_rng(seed).normal(size=3)
    axis /= np.linalg.norm(axis)
    a = np.radians(degrees)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


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
