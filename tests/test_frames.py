import numpy as np

import pytest
import scipy.sparse as sp

from facepipe.core.tangent_frames import (frame_neighbors, frames_from_normals, local_frames, to_local, to_world,
                                         vertex_face_matrix, vertex_normals)
from facepipe.core.shell import large_scale_positions, shell_basis
from facepipe.core.vectors import cross, lengths
from facepipe.pipeline.fit import Geometry
from tests.conftest import grid


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_frames_are_orthonormal_and_right_handed(sheet):
    V, F = sheet
    R = local_frames(V, F, frame_neighbors(F, len(V)))
    assert np.allclose(np.einsum("vji,vjk->vik", R, R), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)


def test_flat_sheet_normal_is_z():
    V, F = grid(curved=False)
    n = vertex_normals(V, F)
    assert np.allclose(np.abs(n[:, 2]), 1.0)


def test_frames_rotate_with_the_mesh(sheet):
    V, F = sheet
    nb = frame_neighbors(F, len(V))
    Q = _rotation(4)
    R0 = local_frames(V, F, nb)
    R1 = local_frames(V @ Q.T + 3.0, F, nb)
    assert np.allclose(R1, Q @ R0, atol=1e-10)


def test_batched_frames_equal_single(sheet):
    V, F = sheet
    nb = frame_neighbors(F, len(V))
    batch = np.stack([V, V * 1.1, V + 0.1 * np.sin(V)])
    R = local_frames(batch, F, nb)
    for i in range(3):
        assert np.allclose(R[i], local_frames(batch[i], F, nb))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_cross_and_lengths_are_numpys_bit_for_bit(dtype):
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(2, 1000, 3)).astype(dtype) * 10.0 ** rng.integers(-6, 6, size=(2, 1000, 1))
    assert np.array_equal(cross(a, b), np.cross(a, b)) and cross(a, b).dtype == np.cross(a, b).dtype
    axis = np.array([0.0, 1.0, 0.0])  # broadcast, as the frames' fallbacks use it
    assert np.array_equal(cross(a, axis), np.cross(a, axis))
    batch = a.reshape(10, 100, 3)
    assert np.array_equal(cross(batch, b.reshape(10, 100, 3)), np.cross(batch, b.reshape(10, 100, 3)))
    assert np.array_equal(lengths(a), np.linalg.norm(a, axis=-1))
    assert np.array_equal(lengths(batch, keepdims=True), np.linalg.norm(batch, axis=-1, keepdims=True))


def _frames_by_numpy(V, F, nb):
    """The frames as numpy's own operations give them, spelled out: area-weighted normals, the
    edge to the frame neighbour projected, its fallbacks, b = n × t."""
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    vn = np.asarray(vertex_face_matrix(F, len(V)) @ fn)
    norm = np.linalg.norm(vn, axis=-1, keepdims=True)
    n = np.where(norm > 1e-30, vn / np.where(norm > 1e-30, norm, 1.0), np.array([0.0, 0.0, 1.0])).astype(V.dtype)
    return _frames_from_normals_by_numpy(n, V[nb] - V).astype(V.dtype)


def _frames_from_normals_by_numpy(n, e):
    t = e - np.einsum("...i,...i->...", e, n)[..., None] * n
    alt = np.cross(n, np.array([1.0, 0.0, 0.0]))
    alt = np.where(np.linalg.norm(alt, axis=-1, keepdims=True) < 1e-6, np.cross(n, np.array([0.0, 1.0, 0.0])), alt)
    keep = np.linalg.norm(t, axis=-1, keepdims=True) > 1e-6 * np.maximum(np.linalg.norm(e, axis=-1, keepdims=True),
                                                                         1e-30)
    t = np.where(keep, t, alt)
    tn = np.linalg.norm(t, axis=-1, keepdims=True)
    t = np.where(tn > 1e-30, t / np.where(tn > 1e-30, tn, 1.0), np.array([1.0, 0.0, 0.0]))
    return np.stack([t, np.cross(n, t), n], axis=-1)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_frames_are_numpys_own_arithmetic_bit_for_bit(sheet, dtype):
    V, F = sheet
    V = V.astype(dtype)
    nb = frame_neighbors(F, len(V))
    V[nb[7]] = V[7] + 0.5 * vertex_normals(V, F)[7]  # an edge to the frame neighbour along the normal
    V[nb[30]] = V[30]  # a frame neighbour on top of its vertex
    assert np.array_equal(local_frames(V, F, nb), _frames_by_numpy(V, F, nb))
    # the fallbacks themselves: an edge along the normal, along x (the first fallback is then zero), none
    n = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    e = np.array([[0.0, 0.0, 2.0], [3.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    R = frames_from_normals(n.astype(dtype), e.astype(dtype))
    assert np.array_equal(R, _frames_from_normals_by_numpy(n.astype(dtype), e.astype(dtype)))
    assert np.allclose(R[:, :, 0], [[0, 1, 0], [0, 0, 1], [0, 0, -1]]) and np.allclose(R[:, :, 2], n)


def test_details_of_a_pose_at_rest_are_zero_and_the_others_as_alone(sheet):
    V, F = sheet
    H = np.arange(0, len(V), 9)
    B = shell_basis(V, F, H)
    geo = Geometry(V, F, H, B, np.array([[0, 1]]), np.array([1.0]), frame_neighbors(F, len(V)), 1.0)
    rng = np.random.default_rng(8)
    moved = [V + 0.2 * np.sin(V[:, [1, 2, 0]] * k) + 0.01 * rng.normal(size=V.shape) for k in (1, 2)]
    d = geo.details(np.stack([V, moved[0], V, moved[1]]))
    assert not d[0].any() and not d[2].any()
    for row, pose in zip((1, 3), moved):
        large = large_scale_positions(V, B, (pose[H] - V[H])[None])[0]
        assert np.array_equal(d[row], to_local(local_frames(large, F, geo.neighbors), pose - large))


def test_detail_round_trip(sheet):
    """pose → large-scale + details in local frames → pose, exactly."""
    V, F = sheet
    nb = frame_neighbors(F, len(V))
    H = np.arange(0, len(V), 9)
    B = shell_basis(V, F, H)
    rng = np.random.default_rng(5)
    pose = V + 0.3 * np.sin(V[:, [1, 2, 0]]) + 0.01 * rng.normal(size=V.shape)
    large = large_scale_positions(V, B, (pose[H] - V[H])[None])[0]
    R = local_frames(large, F, nb)
    d = to_local(R, pose - large)
    assert np.allclose(large + to_world(R, d), pose, atol=1e-12)
    assert np.allclose(d[H], 0, atol=1e-12)


def test_frames_of_a_patch_are_the_mesh_frames_at_the_subset():
    """Frames at a vertex subset from the faces around it equal the whole mesh's frames there."""
    import numpy as np

    from facepipe.core.psd import spread_subset
    from facepipe.core.tangent_frames import FramePatch, frame_neighbors, local_frames
    vertices, faces = grid(60, 50)
    V = len(vertices)
    rng = np.random.default_rng(0)
    poses = vertices + rng.normal(scale=0.01, size=(3,) + vertices.shape)
    subset = spread_subset(V, 200)
    whole = local_frames(poses, faces, frame_neighbors(faces, V))[:, subset]
    patch = FramePatch.around(faces, V, subset)
    assert len(patch.vertices) < V / 2
    np.testing.assert_allclose(patch.frames(poses), whole, rtol=0, atol=1e-12)


def test_frame_neighbours_and_incidence_against_plain_constructions(sheet):
    V, F = sheet
    F = np.r_[F, [[0, 5, 3]]]  # and a face listing its corners out of order
    n = len(V) + 1  # a vertex in no face: its own neighbour
    neighbours = [set() for _ in range(n)]
    for a, b, c in F:
        neighbours[a] |= {b, c}
        neighbours[b] |= {a, c}
        neighbours[c] |= {a, b}
    assert frame_neighbors(F, n).tolist() == [min(s) if s else v for v, s in enumerate(neighbours)]
    inc = vertex_face_matrix(F, n)
    ref = sp.csr_matrix((np.ones(F.size), (F.ravel(), np.repeat(np.arange(len(F)), 3))), shape=(n, len(F)))
    assert inc.has_sorted_indices and np.array_equal(inc.indptr, ref.indptr)
    assert np.array_equal(inc.indices, ref.indices)
    assert np.array_equal(inc.data, ref.data)
