"""UV rasterisation: exact on affine fields, seams and islands, padding, UDIM tiles, sampling."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage

from facepipe.errors import InputError
from facepipe.pipeline.detail_layers import uv_tangent_frames
from facepipe.core.mesh import Mesh
from facepipe.export.uv_raster import (corner_uv_lookups, mesh_raster, bilinear_lookup, udim_tiles, uv_raster, uv_to_texel)


def texel_uv(width, height):
    """UVs (H, W, 2) of every texel centre, from the documented convention (row 0 = v 1)."""
    j, i = np.meshgrid(np.arange(width), np.arange(height))
    return np.stack([(j + 0.5) / width, 1.0 - (i + 0.5) / height], axis=-1)


def grid_mesh(n=6, islands=False):
    """An n × n vertex grid of quads over [0, 1]² in UV (and in xy), optionally cut into two UV
    islands along x = ½ with the right half moved to u in [0.5, 1] → [0.55, 1.05] · 0.9."""
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="xy")
    V = np.c_[x.ravel(), y.ravel(), np.zeros(n * n)]
    idx = np.arange(n * n).reshape(n, n)
    quads = np.c_[idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()]
    pv = quads.ravel()
    uvs = V[:, :2].copy()
    puv = pv.copy()
    if islands:
        # the right half of the quads gets its own copies of the UVs, shifted: a seam on x = ½
        right = np.repeat(V[quads].mean(axis=1)[:, 0] > 0.5, 4)
        uvs = np.concatenate([uvs * [0.45, 1.0], V[:, :2] * [0.45, 1.0] + [0.5, 0.0]])
        puv = np.where(right, pv + n * n, pv)
    offsets = np.arange(0, len(pv) + 1, 4)
    return Mesh(V, offsets, pv, uvs, puv)


def test_affine_field_is_reproduced_exactly_at_every_covered_texel():
    # one triangle, an affine field: barycentric interpolation is exact
    uv = np.array([[[0.1, 0.2], [0.9, 0.15], [0.4, 0.95]]])
    width, height = 64, 48
    raster = uv_raster(uv, np.array([[0, 1, 2]]), 3, width, height, padding=0)

    def field(p):
        return 2.0 + 3.0 * p[..., 0] - 5.0 * p[..., 1]

    img = raster(field(uv[0]))
    tuv = texel_uv(width, height)
    assert raster.covered.sum() > 500
    np.testing.assert_allclose(img[raster.covered], field(tuv[raster.covered]), atol=1e-5)
    assert (img[~raster.covered] == 0).all()
    # coverage: texel centres inside the triangle, by an independent point-in-triangle test
    a, b, c = uv[0]

    def side(p, q, r):
        return (q[0] - p[0]) * (r[..., 1] - p[1]) - (q[1] - p[1]) * (r[..., 0] - p[0])

    s1, s2, s3 = side(a, b, tuv), side(b, c, tuv), side(c, a, tuv)
    inside = ((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))
    assert np.array_equal(inside, raster.covered)


def test_shared_edges_leave_no_cracks_and_values_are_continuous():
    mesh = grid_mesh(9)
    raster = mesh_raster(mesh, 40, 40, padding=0).tiles[1001]
    # the grid covers [0, 1]²: every texel centre is inside some triangle
    assert raster.covered.all()
    values = mesh.vertices[:, 0] * 3 + mesh.vertices[:, 1] ** 2  # not affine: piecewise linear interpolation
    img = raster(values)
    # compare with scipy's piecewise-linear interpolation on the same triangulation
    from scipy.interpolate import LinearNDInterpolator

    tuv = texel_uv(40, 40)
    # LinearNDInterpolator triangulates itself (Delaunay) - on a regular grid its diagonals may
    # differ from ours, so compare only where the field is affine per cell: the x part
    lin = LinearNDInterpolator(mesh.uvs, mesh.vertices[:, 0] * 3)(tuv)
    np.testing.assert_allclose(raster(mesh.vertices[:, 0] * 3), lin, atol=1e-9)
    assert np.isfinite(img).all() and img.min() >= values.min() - 1e-9 and img.max() <= values.max() + 1e-9


def test_seams_give_each_island_the_vertex_values():
    mesh = grid_mesh(7, islands=True)
    tiles = mesh_raster(mesh, 128, 64, padding=2)
    assert list(tiles.tiles) == [1001]
    raster = tiles.tiles[1001]
    values = np.c_[mesh.vertices[:, 0], mesh.vertices[:, 1], mesh.vertices[:, 0] * mesh.vertices[:, 1]]
    img = raster(values)
    # vertices on the seam x = ½ appear in both islands; each sample returns the vertex value
    v, uv, tile, _ = corner_uv_lookups(mesh)
    on_seam = np.isclose(mesh.vertices[v, 0], 0.5)
    assert on_seam.sum() == 2 * 7  # 7 seam vertices, twice each
    got = bilinear_lookup(img, uv)
    # affine channels: exact, on island borders too (the first padding ring continues the
    # triangles), but for samples on the texture's own border, which clamps half a texel in
    inner = ((uv > 0.5 / 64) & (uv < 1 - 0.5 / 64)).all(axis=1)
    np.testing.assert_allclose(got[inner, :2], values[v[inner], :2], atol=1e-9)
    np.testing.assert_allclose(got[:, :2], values[v, :2], atol=0.5 / 0.45 / 128 + 0.5 / 64)
    # the gap between the islands (u in (0.45, 0.5)) is empty apart from the padding
    x, _ = uv_to_texel(np.array([[0.475, 0.5]]), 128, 64)
    col = int(round(x[0]))
    assert not raster.covered[:, col].any()


def test_padding_continues_the_nearest_triangle_then_clamps_to_it():
    uv = np.array([[[0.3, 0.3], [0.7, 0.3], [0.5, 0.7]]])
    values = np.array([1.0, 2.0, 4.0])  # an affine field of u, v on this triangle

    def field(q):  # the affine function with those corner values
        A = np.c_[uv[0], np.ones(3)]
        coef = np.linalg.solve(A, values)
        return q[..., 0] * coef[0] + q[..., 1] * coef[1] + coef[2]

    tuv = texel_uv(64, 64)
    for padding in (0, 1, 3):
        # the plain rasterisation; the vertex-sample fit moves the texels around the corners only
        r = uv_raster(uv, np.array([[0, 1, 2]]), 3, 64, 64, padding=padding, fit=False)
        dist = scipy.ndimage.distance_transform_edt(~r.covered)
        assert np.array_equal(r.filled, dist <= padding)
        img = r(values, fill=np.nan)
        assert np.isfinite(img[r.filled]).all() and np.isnan(img[~r.filled]).all()
        ring1 = r.filled & ~r.covered & (dist <= 1.5)
        beyond = r.filled & (dist > 1.5)
        # first ring: the linear continuation
        np.testing.assert_allclose(img[ring1], field(tuv[ring1]), atol=1e-5)
        # further out: the closest point of the triangle, bounded by the corner values
        if beyond.any():
            assert img[beyond].min() >= 1.0 - 1e-9 and img[beyond].max() <= 4.0 + 1e-9
        fitted = uv_raster(uv, np.array([[0, 1, 2]]), 3, 64, 64, padding=padding)
        assert np.array_equal(fitted.filled, r.filled)
        moved = np.zeros(64 * 64, dtype=bool)
        moved[fitted.texels[fitted.fit.rows]] = True
        fimg = fitted(values, fill=np.nan)
        assert np.array_equal(fimg[~moved.reshape(64, 64)], img[~moved.reshape(64, 64)], equal_nan=True)
        if padding == 3:  # footprints within the filled texels: the corners give back their values
            plain, fit = (np.abs(bilinear_lookup(m, uv[0]) - values) for m in (img, fimg))
            assert plain.max() > 1e-3 and fit.max() <= 0.01 * plain.max()
    # a texel 3 texels right of the edge (0.7, 0.3)-(0.5, 0.7) shows the value on that edge
    r = uv_raster(uv, np.array([[0, 1, 2]]), 3, 64, 64, padding=3)
    img = r(values)
    a, b = np.array([0.7, 0.3]), np.array([0.5, 0.7])
    dist = scipy.ndimage.distance_transform_edt(~r.covered)
    i, j = np.argwhere((dist > 2) & (dist <= 3) & (np.abs(tuv[..., 1] - 0.5) < 0.02) & (tuv[..., 0] > 0.5))[0]
    s = np.clip((tuv[i, j] - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
    assert img[i, j] == pytest.approx((1 - s) * 2.0 + s * 4.0, abs=1e-6)


def test_vertex_samples_are_given_back_on_both_sides_of_a_seam():
    """UV triangles of a few texels and values that are not affine: plain rasterisation misses the
    values at the vertices' UVs; the fitted texels give them back, per UV corner of a seam vertex
    (vertex values) and per UV index (values that differ across the seam)."""
    mesh = grid_mesh(9, islands=True)
    rng = np.random.default_rng(1)
    v, uv, _, ui = corner_uv_lookups(mesh)
    x, y = uv_to_texel(uv, 40, 40)
    # beyond the outermost texel centres a lookup depends on the wrap mode: not fitted
    inner = (x >= 0) & (x <= 39) & (y >= 0) & (y <= 39)
    assert inner.sum() > 50
    for slots, values, at in (("vertex", rng.normal(size=(mesh.n_vertices, 2)), v),
                              ("uv", rng.normal(size=(len(mesh.uvs), 2)), ui)):
        fitted = mesh_raster(mesh, 40, 40, padding=2, slots=slots).tiles[1001]
        plain = mesh_raster(mesh, 40, 40, padding=2, slots=slots, fit=False).tiles[1001]
        assert np.array_equal(fitted.matrix.toarray(), plain.matrix.toarray())
        span = values[at].max(axis=0) - values[at].min(axis=0)
        before = np.abs(bilinear_lookup(plain(values, dtype=np.float64), uv) - values[at]) / span
        after = np.abs(bilinear_lookup(fitted(values, dtype=np.float64), uv) - values[at]) / span
        assert before[inner].max() > 0.05
        assert after[inner].max() <= 0.01 * before[inner].max(), (slots, after[inner].max(), before[inner].max())
        # the raster's own measure agrees with this one
        errors = fitted.lookup_errors(values, fitted(values, dtype=np.float64))
        assert errors.shape == (len(fitted.lookup_slots), 2)
        assert errors.max() == pytest.approx((after * span).max(), rel=1e-9)
        # only texels in the samples' footprints move
        moved = np.zeros(40 * 40, dtype=bool)
        moved[fitted.texels[fitted.fit.rows]] = True
        same = ~moved.reshape(40, 40)
        np.testing.assert_array_equal(fitted(values)[same], plain(values)[same])


def test_contradicting_samples_get_the_least_squares_compromise():
    # two islands stacked on the same UVs with different values: each corner's lookup can only be
    # one value, the fit makes it the mean, and lookup_errors says how far that is from each
    uv = np.array([[[0.2, 0.2], [0.8, 0.25], [0.5, 0.8]]] * 2)
    r = uv_raster(uv, np.array([[0, 1, 2], [3, 4, 5]]), 6, 32, 32, padding=4)
    assert len(r.lookup_slots) == 6 and len(r.fit.samples) == 6
    values = np.array([0.0, 0.0, 0.0, 1.0, 2.0, 3.0])
    err = r.lookup_errors(values, r(values, dtype=np.float64))
    want = np.abs(values[r.lookup_slots] - np.array([0.5, 1.0, 1.5])[r.lookup_slots % 3])
    np.testing.assert_allclose(err, want, rtol=1e-2)


def test_raster_is_linear_in_the_values():
    mesh = grid_mesh(5, islands=True)
    raster = mesh_raster(mesh, 32, 32, padding=4)
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, mesh.n_vertices, 3))
    left = raster(2.0 * a - 0.5 * b, dtype=np.float64)[1001]
    right = 2.0 * raster(a, dtype=np.float64)[1001] - 0.5 * raster(b, dtype=np.float64)[1001]
    np.testing.assert_allclose(left, right, atol=1e-12)


def test_udim_tiles_and_their_own_rasters():
    mesh = grid_mesh(5)
    # move the quads of the upper half (y > ½) to tile 1012 (u + 1, v + 1)
    upper = np.repeat(mesh.vertices[mesh.polygon_vertices.reshape(-1, 4)].mean(axis=1)[:, 1] > 0.5, 4)
    uvs = np.concatenate([mesh.uvs, mesh.uvs + [1.0, 1.0]])
    mesh = Mesh(mesh.vertices, mesh.polygon_offsets, mesh.polygon_vertices, uvs,
                np.where(upper, mesh.polygon_vertices + len(mesh.uvs), mesh.polygon_vertices))
    tiles = udim_tiles(mesh.uvs[mesh.face_uvs])
    assert set(tiles.tolist()) == {1001, 1012}
    tr = mesh_raster(mesh, 32, 32, padding=1)
    assert tr.udim and list(tr.tiles) == [1001, 1012]
    values = mesh.vertices[:, 1]
    maps = tr(values)
    v, uv, tile, _ = corner_uv_lookups(mesh)
    assert ((uv >= 0) & (uv <= 1)).all()
    for t, img in maps.items():
        s = tile == t
        # half a texel of the (unit-gradient) field at the tile border, where lookups clamp
        np.testing.assert_allclose(bilinear_lookup(img, uv[s]), values[v[s]], atol=0.5 / 32 + 1e-6)
        inner = s & ((uv > 0.5 / 32) & (uv < 1 - 0.5 / 32)).all(axis=1)
        np.testing.assert_allclose(bilinear_lookup(img, uv[inner]), values[v[inner]], atol=1e-6)
    bad = mesh.uvs.copy()
    bad[0] = [-0.5, 0.2]
    with pytest.raises(InputError, match="UDIM"):
        udim_tiles(bad[mesh.face_uvs])


def test_mesh_without_uvs_is_an_input_error():
    mesh = grid_mesh(4)
    bare = Mesh(mesh.vertices, mesh.polygon_offsets, mesh.polygon_vertices, path="bare.obj")
    with pytest.raises(InputError, match="no texture coordinates") as e:
        mesh_raster(bare, 64, 64)
    assert "bare.obj" in str(e.value)


def test_sample_bilinear_matches_scipy():
    rng = np.random.default_rng(3)
    img = rng.normal(size=(17, 23, 3))
    uv = rng.uniform(0.03, 0.97, size=(50, 2))
    x, y = uv_to_texel(uv, 23, 17)
    ref = np.stack([scipy.ndimage.map_coordinates(img[..., c], [y, x], order=1) for c in range(3)], axis=-1)
    np.testing.assert_allclose(bilinear_lookup(img, uv), ref, atol=1e-12)


def test_degenerate_uv_triangles_are_skipped():
    uv = np.array([[[0.2, 0.2], [0.8, 0.2], [0.5, 0.2]], [[0.2, 0.3], [0.8, 0.3], [0.5, 0.9]]])
    r = uv_raster(uv, np.array([[0, 1, 2], [0, 1, 2]]), 3, 32, 32, padding=0)
    assert (r.triangle[r.covered] == 1).all()


def test_uv_tangent_frames_follow_u_and_v_and_flip_on_mirrored_islands():
    # a plane z = 0 with u along a rotated direction in xy and v perpendicular
    ang = 0.4
    du = np.array([np.cos(ang), np.sin(ang), 0.0])
    dv = np.array([-np.sin(ang), np.cos(ang), 0.0])
    P = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float) * 2.0
    uvs = np.stack([P @ du, P @ dv], axis=1) / 4 + 0.5
    faces = np.array([[0, 1, 3], [0, 3, 2]])
    frames = uv_tangent_frames(P[None], faces, faces, uvs)[0]
    np.testing.assert_allclose(frames[:, :, 0], np.tile(du, (4, 1)), atol=1e-12)
    np.testing.assert_allclose(frames[:, :, 1], np.tile(dv, (4, 1)), atol=1e-12)
    np.testing.assert_allclose(frames[:, :, 2], np.tile([0, 0, 1.0], (4, 1)), atol=1e-12)
    # mirror u: t turns round, b keeps following +v, so the frame is left-handed
    mirrored = uvs * [-1, 1] + [1, 0]
    frames = uv_tangent_frames(P[None], faces, faces, mirrored)[0]
    np.testing.assert_allclose(frames[:, :, 0], np.tile(-du, (4, 1)), atol=1e-12)
    np.testing.assert_allclose(frames[:, :, 1], np.tile(dv, (4, 1)), atol=1e-12)
    assert np.allclose(np.linalg.det(frames), -1)
