"""The template points every example shows well (facepipe.pipeline.appearance_points.well_seen_points)
against a brute-force computation on a small synthetic surface."""

import cv2
import numpy as np
import pytest

from facepipe.core.camera import Camera
from facepipe.core.occlusion import segment_hits
from facepipe.pipeline.appearance_points import locate_uv, template_points, well_seen_points


def _sheet(n: int = 24):
    """A sheet over [-1, 1]² (its UVs the same square in [0, 1]²) and its triangles."""
    y, x = np.mgrid[0:n, 0:n] / (n - 1) * 2.0 - 1.0
    uv = np.stack([(x.ravel() + 1) / 2, (y.ravel() + 1) / 2], axis=1)
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return x.ravel(), y.ravel(), uv, faces


def _frames(x, y):
    """Three poses of the sheet, 6 units in front of the camera, and of a flap in front of it (a
    brow over a lid) that hides the points behind it: a ridge across the sheet (rising towards
    the camera, each time higher) turns its slopes away; the sheet's corner leaves the image."""
    frames = []
    for height, tilt, drop in ((0.8, 0.0, 0.0), (1.2, 0.1, 0.1), (1.6, -0.1, 0.2)):
        z = 6.0 - height * np.exp(-((y - 0.2) / 0.12) ** 2) + tilt * x
        flap = np.array([[-0.2, -0.5, 4.0], [0.3, -0.5, 4.0], [-0.2, -0.2 + drop, 4.0], [0.3, -0.2 + drop, 4.0]])
        frames.append(np.concatenate([np.stack([x, y, z], axis=1), flap]))
    return np.stack(frames)


def _brute_force(frames, faces, face, bary, camera, size, sign, min_facing, relative, margin=0.0):
    good, parts = [], []
    for V in frames:
        X = np.einsum("nk,nkc->nc", bary, V[faces[face]])
        px = cv2.projectPoints(X, np.zeros(3), np.zeros(3), camera.matrix, camera.distortion)[0][:, 0]
        inside = ((px[:, 0] >= -0.5) & (px[:, 0] <= camera.width - 0.5) & (px[:, 1] >= -0.5)
                  & (px[:, 1] <= camera.height - 0.5) & (X[:, 2] > 0))
        grid = X.reshape(size, size, 3)
        step = np.linalg.norm(np.diff(grid, axis=1), axis=-1).mean()
        hidden = segment_hits(X, V, faces, step)
        normals = np.zeros_like(V)  # area-weighted vertex normals, one triangle at a time
        for tri in faces:
            cross = np.cross(V[tri[1]] - V[tri[0]], V[tri[2]] - V[tri[0]])
            for v in tri:
                normals[v] += cross
        normals = sign * normals / np.linalg.norm(normals, axis=1, keepdims=True)
        n = np.einsum("nk,nkc->nc", bary, normals[faces[face]])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        cos = (n * -X).sum(axis=1) / np.linalg.norm(X, axis=1)
        ok = inside & ~hidden & (cos > min_facing) & (cos >= relative * np.median(cos))
        # the margin, one pair of points at a time: a point whose sample reaches a failing one fails
        near = np.array([any(not ok[j] and max(abs(px[i, 0] - px[j, 0]), abs(px[i, 1] - px[j, 1])) < margin
                             for j in range(len(px))) for i in range(len(px))])
        good.append(ok & ~near)
        parts.append((inside, hidden, cos))
    return np.all(good, axis=0), *map(np.stack, zip(*parts))


@pytest.mark.parametrize("min_facing,relative,margin", [(0.35, 0.8, 0.0), (0.0, 0.0, 0.0), (0.5, 0.0, 0.0),
                                                        (0.35, 0.8, 14.0), (0.0, 0.0, 30.0)])
def test_well_seen_points_equal_brute_force(min_facing, relative, margin):
    x, y, uv, faces = _sheet()
    frames = _frames(x, y)
    k = len(x)
    mesh_faces = np.concatenate([faces, [[k, k + 1, k + 3], [k, k + 3, k + 2]]])
    size = 16
    camera = Camera(np.array([[700.0, 0, 99.5], [0, 700.0, 99.5], [0, 0, 1]]), np.array([-0.05, 0.01, 0, 0, 0]),
                    200, 200)
    face, bary = locate_uv(template_points([0.1, 0.1, 0.95, 0.95], size)[0], uv[faces])
    assert (face >= 0).all()
    sign = -1.0 if np.cross(frames[0, faces[0, 1]] - frames[0, faces[0, 0]],
                            frames[0, faces[0, 2]] - frames[0, faces[0, 0]])[2] > 0 else 1.0  # out: towards the camera
    got = well_seen_points(frames, mesh_faces, face, bary, camera, size, sign, min_facing, True, relative, margin)
    expected, inside, hidden, cos = _brute_force(frames, mesh_faces, face, bary, camera, size, sign, min_facing, relative,
                                                 margin)
    np.testing.assert_array_equal(got, expected)
    if margin > 0:  # the margin (here about one and two of the grid's steps) takes points the tests alone keep
        plain = well_seen_points(frames, mesh_faces, face, bary, camera, size, sign, min_facing, True, relative)
        assert (plain & ~got).any() and not (got & ~plain).any()
    # the scene exercises every test: points off the image, hidden behind the ridge, turned away
    assert (~inside).any() and hidden.any() and (cos < 0.5).any() and got.any() and not got.all()


def test_seen_fraction_counts_each_regions_stable_points():
    from types import SimpleNamespace

    from facepipe.pipeline.appearance_points import seen_fraction

    rng = np.random.default_rng(3)
    F, R, N = 6, 3, 16  # frames and regions of different counts: a region's own stable set divides
    stable = rng.uniform(size=(R, N)) < 0.6
    seen = rng.uniform(size=(F, R, 5, N)) < 0.7
    got = seen_fraction(seen, SimpleNamespace(template_mask=stable))
    for f in range(F):
        for r in range(R):
            assert got[f, r] == pytest.approx(seen[f, r][:, stable[r]].sum() / (5 * stable[r].sum()))
    np.testing.assert_allclose(seen_fraction(seen, SimpleNamespace(template_mask=None)), seen.mean(axis=(2, 3)))


def _ray_cast_image(camera: Camera, tilt: float, flap: tuple) -> np.ndarray:
    """(H, W, 3) what each pixel centre's ray meets, as one colour per surface, by intersecting
    the rays with the two planes: the flap (z = 4, x, y in ``flap`` = (x0, x1, y0, y1)) green, the
    sheet (z = 6 + tilt·x over [-1, 1]²) blue, nothing red."""
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    d = np.stack([u, v, np.ones_like(u)], axis=-1).astype(float) @ np.linalg.inv(camera.matrix).T  # z = 1
    image = np.zeros(d.shape)
    image[...] = (1.0, 0.0, 0.0)
    t = 6.0 / (1.0 - tilt * d[..., 0])
    on_sheet = (np.abs(t * d[..., 0]) <= 1.0) & (np.abs(t * d[..., 1]) <= 1.0) & (t > 0)
    image[on_sheet] = (0.0, 0.0, 1.0)
    x0, x1, y0, y1 = flap
    on_flap = (4 * d[..., 0] >= x0) & (4 * d[..., 0] <= x1) & (4 * d[..., 1] >= y0) & (4 * d[..., 1] <= y1)
    image[on_flap] = (0.0, 1.0, 0.0)
    return image


@pytest.mark.parametrize("tilt", [0.0, 1.0])
def test_unwrap_keeps_only_texels_whose_pixels_show_their_own_surface(tilt):
    """A sheet partly hidden by a flap in front of it, over a background: a texel is seen only where
    each pixel its bilinear sample reads shows the sheet, so no seen texel takes the flap's or the
    background's colour (before, the texels behind the flap and along every edge did); and every
    texel a few pixels from another surface's pixels is seen, at a grazing tilt too."""
    from facepipe.pipeline.appearance_points import texel_map, unwrap

    x, y, uv, faces = _sheet(33)
    k = len(x)
    flap = (-0.2, 0.3, -0.5, -0.1)
    corners = np.array([[flap[0], flap[2], 4.0], [flap[1], flap[2], 4.0], [flap[0], flap[3], 4.0], [flap[1], flap[3], 4.0]])
    vertices = np.concatenate([np.stack([x, y, 6.0 + tilt * x], axis=1), corners])
    mesh_faces = np.concatenate([faces, [[k, k + 1, k + 3], [k, k + 3, k + 2]]])
    corner_uv = np.concatenate([uv[faces], np.zeros((2, 3, 2))])  # the flap has no texels
    camera = Camera(np.array([[120.0, 0, 49.5], [0, 120.0, 49.5], [0, 0, 1]]), np.zeros(5), 100, 100)
    image = _ray_cast_image(camera, tilt, flap)
    texel_face, texel_bary = texel_map(corner_uv, 128)
    sign = -1.0 if np.cross(*(vertices[faces[0, 1:]] - vertices[faces[0, 0]]))[2] > 0 else 1.0
    colours, seen = unwrap(image, vertices, mesh_faces, texel_face, texel_bary, camera, min_facing=0.2, normal_sign=sign)
    assert seen.any()
    np.testing.assert_allclose(colours[seen], np.broadcast_to([0.0, 0.0, 1.0], colours[seen].shape), atol=1e-12)
    # every texel at least three pixels (along x or y) from a pixel that does not show the sheet is seen
    X = np.einsum("ijk,ijkc->ijc", texel_bary, vertices[mesh_faces[np.maximum(texel_face, 0)]])
    px = cv2.projectPoints(X.reshape(-1, 3), np.zeros(3), np.zeros(3), camera.matrix, camera.distortion)[0][:, 0]
    other = np.argwhere(image[..., 2] < 1.0)[:, ::-1].astype(float)  # (x, y) of the pixels not showing it
    gap = np.abs(px[:, None, :] - other[None]).max(axis=-1).min(axis=1).reshape(seen.shape)
    clear = (texel_face >= 0) & (gap >= 3.0)
    assert clear.sum() > 0.3 * (texel_face >= 0).sum()
    assert seen[clear].all()
