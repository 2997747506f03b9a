import numpy as np

from facepipe.core.tangent_frames import frame_neighbors, local_frames, to_local, to_world, vertex_normals
from facepipe.core.shell import large_scale_positions, shell_basis
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
