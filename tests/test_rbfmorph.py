import numpy as np
import pytest

from facepipe.errors import InputError
from facepipe.core.rbf_morph import (boundary_vertices, farthest_point_subset, multiquadric_basis, phantom_points)
from tests.conftest import grid


def _setup():
    V, F = grid(20, 18)
    handles = np.arange(3, len(V), 11)
    return V, F, handles


def test_interpolates_markers_and_reproduces_affine_motion():
    V, F, H = _setup()
    B = multiquadric_basis(V, H, np.array([], dtype=np.int64), regularization=0.0)
    assert np.allclose(B[H], np.eye(len(H)), atol=1e-8)
    assert np.allclose(B.sum(axis=1), 1.0, atol=1e-8)
    A = np.array([[1.1, 0.2, 0.0], [-0.1, 0.9, 0.3], [0.05, 0.0, 1.2]])
    b = np.array([0.3, -0.2, 1.0])
    uH = V[H] @ (A - np.eye(3)).T + b
    assert np.allclose(B @ uH, V @ (A - np.eye(3)).T + b, atol=1e-7)


def test_phantoms_stay_still_and_regularization_smooths():
    V, F, H = _setup()
    ph = phantom_points(V, F, np.array([], dtype=np.int64), H)
    assert len(ph) > 0 and not np.intersect1d(ph, H).size
    B0 = multiquadric_basis(V, H, ph, regularization=0.0)
    assert np.allclose(B0[ph], 0.0, atol=1e-8)
    rng = np.random.default_rng(0)
    noise = rng.normal(scale=0.05, size=(len(H), 3))
    B1 = multiquadric_basis(V, H, ph, regularization=0.5)
    assert np.isfinite(B1).all()
    # smoothing: the morph no longer passes exactly through noisy markers, and is smoother
    assert np.abs(B1[H] @ noise - noise).max() > 1e-4
    assert np.linalg.norm(B1 @ noise) < np.linalg.norm(B0 @ noise)


def test_works_without_connectivity_on_several_parts():
    V, F, H = _setup()
    V2 = np.concatenate([V, V[:50] + [0.0, 0.0, 3.0]])  # a second, unconnected part (no faces needed)
    B = multiquadric_basis(V2, H, np.array([], dtype=np.int64), regularization=0.0)
    assert B.shape == (len(V2), len(H))
    # exact at the markers, and an affine motion of the markers moves the unconnected part with them
    assert np.allclose(B[H], np.eye(len(H)), atol=1e-8)
    A = np.array([[0.9, 0.1, 0.0], [0.0, 1.1, -0.2], [0.1, 0.0, 1.0]])
    uH = V2[H] @ (A - np.eye(3)).T + [0.2, -0.1, 0.3]
    assert np.allclose(B @ uH, V2 @ (A - np.eye(3)).T + [0.2, -0.1, 0.3], atol=1e-7)


def test_coincident_centres_are_reported():
    V, F, H = _setup()
    V = V.copy()
    V[H[1]] = V[H[0]]
    with pytest.raises(InputError, match="coincide"):
        multiquadric_basis(V, H, np.array([], dtype=np.int64))


def test_helpers():
    V, F, _ = _setup()
    b = boundary_vertices(F)
    assert len(b) == 2 * (20 + 18) - 4
    pts = np.random.default_rng(1).uniform(size=(200, 3))
    idx = farthest_point_subset(pts, 10)
    assert len(set(idx.tolist())) == 10
