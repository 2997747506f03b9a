"""Ray casting of points against a mesh (core/occlusion): against a sphere's analytic visibility
and against brute-force Möller–Trumbore intersection on random meshes."""

import numpy as np
import pytest

from facepipe.core.occlusion import occluded_points, segment_hits


def _sphere(n_lat=40, n_lon=80, radius=1.0, centre=(0.0, 0.0, 5.0)):
    lat = np.linspace(0, np.pi, n_lat)
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    v = radius * np.stack([np.sin(la) * np.cos(lo), np.sin(la) * np.sin(lo), np.cos(la)], -1).reshape(-1, 3)
    faces = []
    for i in range(n_lat - 1):
        for j in range(n_lon):
            a, b = i * n_lon + j, i * n_lon + (j + 1) % n_lon
            c, d = a + n_lon, b + n_lon
            faces += [(a, c, b), (b, c, d)]
    faces = np.array(faces)
    v = v + np.asarray(centre)
    # drop degenerate triangles at the poles (repeated vertices there)
    keep = np.linalg.norm(np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]), axis=1) > 1e-12
    return v, faces[keep]


def _surface_points(v, faces, n, rng):
    tri = rng.integers(0, len(faces), n)
    b = rng.dirichlet(np.ones(3), n)
    return np.einsum("nk,nkc->nc", b, v[faces[tri]]), tri


def test_sphere_far_side_hidden_near_side_seen():
    rng = np.random.default_rng(1)
    v, faces = _sphere()
    p, _ = _surface_points(v, faces, 4000, rng)
    centre = np.array([0.0, 0.0, 5.0])
    cos = ((p - centre) * -p).sum(1) / (np.linalg.norm(p - centre, axis=1) * np.linalg.norm(p, axis=1))
    hidden = occluded_points(p[None], v[None], faces, 1e-6)[0]
    clear = np.abs(cos) > 0.15  # away from the silhouette, where the facets decide
    assert clear.sum() > 3000
    np.testing.assert_array_equal(hidden[clear], cos[clear] < 0)


def test_random_meshes_match_brute_force():
    rng = np.random.default_rng(2)
    for trial in range(3):
        # two wavy sheets, one partly in front of the other, and a few loose triangles
        gx, gy = np.meshgrid(np.linspace(-1, 1, 15), np.linspace(-1, 1, 15))
        sheets, faces = [], []
        for k, (dz, shift) in enumerate([(6.0, 0.0), (4.5, 0.6 * rng.uniform(-1, 1))]):
            z = dz + 0.2 * np.sin(3 * gx + trial) * np.cos(2 * gy)
            sheets.append(np.stack([gx + shift, gy * 0.7, z], -1).reshape(-1, 3))
            base = k * gx.size
            for i in range(14):
                for j in range(14):
                    a = base + i * 15 + j
                    faces += [(a, a + 1, a + 15), (a + 1, a + 16, a + 15)]
        loose = (rng.uniform([-1, -1, 3], [1, 1, 7], size=(10, 1, 3)) + rng.normal(0, 0.15, (10, 3, 3))).reshape(30, 3)
        v = np.vstack(sheets + [loose])
        faces = np.vstack([np.array(faces), len(v) - 30 + np.arange(30).reshape(10, 3)])
        p, _ = _surface_points(v, faces[:784], 3000, rng)
        frames = np.stack([p, p * 1.01])
        verts = np.stack([v, v * 1.01])
        fast = occluded_points(frames, verts, faces, 1e-6)
        for f in range(2):
            slow = segment_hits(frames[f], verts[f], faces, 1e-6)
            assert slow.sum() > 100 and (~slow).sum() > 100
            np.testing.assert_array_equal(fast[f], slow)
        # a coarser grid (fewer, larger cells) changes only the work, not the answer
        np.testing.assert_array_equal(occluded_points(frames, verts, faces, 1e-6, cell=0.3), fast)


def test_tolerance_and_points_behind_camera():
    # a triangle 0.1 in front of a point hides it below that tolerance only
    v = np.array([[-1.0, -1.0, 4.9], [1.0, -1.0, 4.9], [0.0, 1.0, 4.9]])
    faces = np.array([[0, 1, 2]])
    p = np.array([[[0.0, 0.0, 5.0], [0.0, 0.0, -5.0], [5.0, 5.0, 5.0]]])
    np.testing.assert_array_equal(occluded_points(p, v[None], faces, 0.05)[0], [True, False, False])
    np.testing.assert_array_equal(occluded_points(p, v[None], faces, 0.2)[0], [False, False, False])


def test_point_facing_of_a_tilted_plane():
    # a square facing the camera, then turned 60° about the vertical: the cosine is 1, then 0.5
    # (at the centre, where the direction to the camera is the optical axis)
    from facepipe.pipeline.appearance_points import point_facing

    v = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    face, bary = np.array([0]), np.array([[0.5, 0.0, 0.5]])  # the centre (0, 0)
    for degrees, expected in ((0.0, 1.0), (60.0, 0.5)):
        a = np.deg2rad(degrees)
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        cam = v @ R.T + np.array([0.0, 0.0, 50.0])
        sign = -1.0 if np.cross(cam[1] - cam[0], cam[2] - cam[0])[2] > 0 else 1.0  # the side toward the camera
        assert point_facing(cam, faces, face, bary, sign)[0] == pytest.approx(expected, abs=1e-9)


def test_culling_per_group_matches_brute_force():
    # small clusters of points (a template's) on a far wavy sheet behind a nearer, moving one:
    # the triangles culled against each cluster's box, the answer the brute-force cast's
    import facepipe.core.occlusion as occlusion

    rng = np.random.default_rng(5)
    gx, gy = np.meshgrid(np.linspace(-2, 2, 41), np.linspace(-2, 2, 41))
    quads = [(i * 41 + j, i * 41 + j + 1, (i + 1) * 41 + j) for i in range(40) for j in range(40)]
    quads += [(i * 41 + j + 1, (i + 1) * 41 + j + 1, (i + 1) * 41 + j) for i in range(40) for j in range(40)]
    grid_faces = np.array(quads)
    far = np.stack([gx, gy, 8.0 + 0.3 * np.sin(2 * gx) * np.cos(gy)], -1).reshape(-1, 3)
    faces = np.vstack([grid_faces, grid_faces + len(far)])
    centres = rng.uniform(-1.5, 1.5, size=(5, 2))
    groups = np.repeat(np.arange(5), 60)
    xy = centres[groups] + rng.uniform(-0.15, 0.15, size=(300, 2))
    z = 8.0 + 0.3 * np.sin(2 * xy[:, 0]) * np.cos(xy[:, 1])
    points, verts = [], []
    for f in range(3):  # the near sheet moves across the clusters from frame to frame
        near = np.stack([0.2 * gx + 0.3 * f - 0.3, 0.2 * gy, np.full_like(gx, 5.0)], -1).reshape(-1, 3)
        verts.append(np.vstack([far, near]))
        points.append(np.column_stack([xy, z]))
    points, verts = np.stack(points), np.stack(verts)
    kept = []
    original = occlusion._triangles_near_groups

    def spy(*args):
        kept.append(len(original(*args)))
        return original(*args)

    occlusion._triangles_near_groups = spy
    try:
        culled = occluded_points(points, verts, faces, 1e-6, groups=groups)
        whole = occluded_points(points, verts, faces, 1e-6)
    finally:
        occlusion._triangles_near_groups = original
    assert kept[0] < 0.5 * len(faces)  # the culling did drop most of the mesh
    for f in range(3):
        slow = segment_hits(points[f], verts[f], faces, 1e-6)
        assert slow.sum() > 20 and (~slow).sum() > 20
        np.testing.assert_array_equal(culled[f], slow)
    np.testing.assert_array_equal(culled, whole)
