"""The appearance classification's maths (facepipe.core.appearance) against independent checks."""

import numpy as np
import pytest
from scipy import ndimage
from scipy.stats import spearmanr

from facepipe.core.appearance import (DEFAULT_SCALE_WEIGHTS, PEAK_INTERPOLATIONS, RegionBank, above_rest,
                                      bilinear_sample, classify, classify_regions, coefficient_weights,
                                      drop_short_events, facing, haar_coefficients, haar_matrix, hold_and_decay,
                                      match_distances, neutral_reference, normalise_patches, peak_index,
                                      rest_direction, rest_floor, segment_index, select_coefficients,
                                      shading_tilt_readings)
from facepipe.core.layered_texture import compose_texture, layer_lookup, region_alpha


def test_haar_2x2_by_hand():
    a, b, c, d = 1.0, 2.0, 3.0, 4.0
    coeffs = haar_coefficients(np.array([[a, b], [c, d]]))
    # coeffs_to_array's 2x2 layout, row-major: approximation, the difference between the columns,
    # the difference between the rows, the diagonal one (PyWavelets' Haar high-pass: first minus second)
    expected = [(a + b + c + d) / 2, (a - b + c - d) / 2, (a + b - c - d) / 2, (a - b - c + d) / 2]
    np.testing.assert_allclose(coeffs, expected, atol=1e-12)
    _, scale = haar_matrix(2)
    np.testing.assert_array_equal(scale, [0, 1, 1, 1])


def test_haar_4x4_blocks_by_hand():
    # constant 2x2 blocks: the finest details vanish and the coarse level is the 2x2 transform of
    # the block means, times 2 (each block mean carries a 2x2 block's energy)
    blocks = np.array([[1.0, 5.0], [-2.0, 3.0]])
    patch = np.kron(blocks, np.ones((2, 2)))
    coeffs = haar_coefficients(patch)
    _, scale = haar_matrix(4)
    np.testing.assert_allclose(coeffs[scale == 2], 0.0, atol=1e-12)
    coarse = haar_coefficients(blocks) * 2.0
    np.testing.assert_allclose(coeffs[scale < 2], coarse, atol=1e-12)


def test_haar_matrix_orthonormal_and_scales():
    H, scale = haar_matrix(16)
    np.testing.assert_allclose(H @ H.T, np.eye(256), atol=1e-12)
    assert [int((scale == s).sum()) for s in range(5)] == [1, 3, 12, 48, 192]
    w = coefficient_weights(16, DEFAULT_SCALE_WEIGHTS)
    assert w[scale == 1].tolist() == [4.0] * 3 and (w[scale == 4] == 0).all()


def test_peak_interpolation_exact_on_parabola():
    j = np.arange(6.0)
    for q in [0.0, 0.3, 1.5, 2.49, 3.7, 5.0]:
        d = 2.5 * (j - q) ** 2 + 7.0
        assert peak_index(d) == pytest.approx(q, abs=1e-12)
    flat = np.ones(4)
    assert peak_index(flat) == 0.0
    with pytest.raises(ValueError):
        peak_index(np.ones(2))


def _nearest_on_path(point, templates, w):
    """(index, squared distance) of the point of the path through templates (n, C) nearest ``point``
    (C,) under weights w (C,): each segment's projection in the coefficients themselves."""
    best = (np.inf, np.nan)
    for k in range(len(templates) - 1):
        a, step = templates[k], templates[k + 1] - templates[k]
        alpha = np.clip(np.sum(w * (point - a) * step) / np.sum(w * step * step), 0.0, 1.0)
        gap = np.sum(w * (point - a - alpha * step) ** 2)
        if gap < best[0]:
            best = (gap, k + alpha)
    return best[1], best[0]


def test_segment_index_reads_templates_and_their_blends_exactly():
    # templates neither evenly spaced nor on a line: a template reads its index, a blend of two
    # adjacent ones its blend weight (what the layered texture shows at that Q); the parabola
    # through three distances does neither
    rng = np.random.default_rng(40)
    w = rng.uniform(0.5, 2.0, size=12)
    templates = np.cumsum(rng.normal(size=(5, 12)) * np.array([1, 0.3, 2.0, 0.7, 1.5])[:, None], axis=0)

    def dist(x):
        return ((x[None, :] - templates) ** 2 * w).sum(axis=1)

    gaps = ((np.diff(templates, axis=0) ** 2) * w).sum(axis=1)
    for k in range(5):
        q, residual = segment_index(dist(templates[k]), gaps)
        assert q == pytest.approx(k, abs=1e-12) and residual == pytest.approx(0.0, abs=1e-9)
    for k, beta in [(0, 0.3), (1, 0.5), (2, 0.9), (3, 0.05)]:
        x = (1 - beta) * templates[k] + beta * templates[k + 1]
        q, residual = segment_index(dist(x), gaps)
        assert q == pytest.approx(k + beta, abs=1e-9) and residual == pytest.approx(0.0, abs=1e-9)
    assert abs(peak_index(dist(templates[1])) - 1.0) > 1e-3  # what the change is for
    # off the path: the nearest point, against the projection in the coefficients
    for x in rng.normal(size=(20, 12)) * 2.0 + templates.mean(axis=0):
        q, residual = segment_index(dist(x), gaps)
        along, gap = _nearest_on_path(x, templates, w)
        assert q == pytest.approx(along, abs=1e-9) and residual == pytest.approx(gap, rel=1e-9, abs=1e-12)
    # batched as one call
    X = rng.normal(size=(2, 3, 12))
    D = ((X[..., None, :] - templates) ** 2 * w).sum(axis=-1)
    q, residual = segment_index(D, np.broadcast_to(gaps, (2, 3, 4)))
    for i in range(2):
        for j in range(3):
            assert q[i, j] == pytest.approx(segment_index(D[i, j], gaps)[0], abs=1e-12)


def test_segment_index_skips_absent_and_repeated_templates():
    d = np.array([4.0, 1.0, 0.25, np.inf, np.inf])       # a region of 3 layers padded to 5
    gaps = np.array([1.0, 1.0, np.inf, np.inf])
    q, residual = segment_index(d, gaps)
    # by hand on segment 1–2: α = (1 − 0.25 + 1) / 2 = 0.875, 1 − 0.875 · 1.75 + 0.875² = 15 / 64
    assert q == pytest.approx(1.875, abs=1e-12) and residual == pytest.approx(15 / 64, abs=1e-12)
    # two identical templates (gap 0): the path goes on from them, no division by zero
    q, _ = segment_index(np.array([1.0, 1.0, 0.0]), np.array([0.0, 1.0]))
    assert q == pytest.approx(2.0)
    q, residual = segment_index(np.full(4, np.inf), np.full(3, np.inf))
    assert np.isnan(q) and residual == np.inf


def test_distances_equal_direct_weighted_sum():
    rng = np.random.default_rng(1)
    q, t = rng.normal(size=(7, 256)), rng.normal(size=(4, 256))
    idx = select_coefficients(t, 50)
    w = coefficient_weights(16)
    direct = np.array([[np.sum(w[idx] * (qq[idx] - tt[idx]) ** 2) for tt in t] for qq in q])
    np.testing.assert_allclose(match_distances(q, t, idx, w), direct, rtol=1e-10)
    assert len(idx) == 50 and np.all(np.diff(idx) > 0)


def _blend_templates(rng, n):
    x = np.linspace(0, 1, 16)
    a = 1.0 + 0.05 * rng.normal(size=(16, 16))
    b = a + 0.3 * np.sin(2 * np.pi * 3 * x)[:, None] * np.ones(16)  # stripes appear: a wrinkle
    return a, b, [a + (b - a) * k / (n - 1) for k in range(n)]


def test_q_monotone_in_a_synthetic_blend():
    rng = np.random.default_rng(0)
    n = 5
    a, b, layers = _blend_templates(rng, n)
    templates = haar_coefficients(normalise_patches(np.stack(layers)))
    idx = select_coefficients(templates, 50)
    w = coefficient_weights(16)
    s = np.linspace(0, 1, 41)
    patches = np.stack([a + (b - a) * v for v in s])[:, None]  # one sample each
    q, _ = classify(patches * 0.7, templates, idx, w)  # a darker exposure: normalised away
    assert np.all(np.diff(q) >= -1e-9)
    np.testing.assert_allclose(q, s * (n - 1), atol=0.05)
    # noise: still ordered
    noisy = patches + 0.005 * rng.normal(size=patches.shape)
    qn, _ = classify(noisy, templates, idx, w)
    assert spearmanr(qn, s).statistic > 0.99


def test_best_of_offset_samples_is_kept():
    rng = np.random.default_rng(2)
    a, b, layers = _blend_templates(rng, 4)
    templates = haar_coefficients(normalise_patches(np.stack(layers)))
    idx, w = select_coefficients(templates, 50), coefficient_weights(16)
    good = a + (b - a) * (2 / 3)
    junk = rng.uniform(0.5, 1.5, size=(16, 16))
    q, d = classify(np.stack([junk, good, junk])[None], templates, idx, w)
    # exact match (distance 0) with the second sample; the parabola's vertex is exactly 2 only where
    # the layers are evenly spaced in coefficient space, which dividing by the shading plane bends slightly
    assert q[0] == pytest.approx(2.0, abs=0.01) and d[0] == pytest.approx(0.0, abs=1e-9)
    q, d = classify(np.stack([junk, good, junk])[None], haar_coefficients(normalise_patches(np.stack(layers), False)),
                    idx, w, shading=False)
    assert q[0] == pytest.approx(2.0, abs=1e-6) and d[0] == pytest.approx(0.0, abs=1e-9)


def test_shading_plane_against_least_squares():
    rng = np.random.default_rng(5)
    patches = rng.uniform(0.5, 1.5, size=(3, 8, 16))
    yy, xx = np.mgrid[0:8, 0:16]
    A = np.stack([np.ones(128), xx.ravel(), yy.ravel()], axis=1)
    for p, got in zip(patches, normalise_patches(patches)):
        plane = (A @ np.linalg.lstsq(A, p.ravel(), rcond=None)[0]).reshape(8, 16)
        np.testing.assert_allclose(got, p / plane, rtol=1e-12)
    # a patch that is all shading (a plane) normalises to ones; a uniform gain changes nothing
    plane = 0.8 + 0.01 * xx - 0.02 * yy
    np.testing.assert_allclose(normalise_patches(plane), 1.0, atol=1e-12)
    np.testing.assert_allclose(normalise_patches(3.0 * patches), normalise_patches(patches), rtol=1e-12)


def test_all_regions_at_once_match_one_by_one():
    rng = np.random.default_rng(6)
    counts = [3, 5, 4]
    w = coefficient_weights(16)
    templates = [haar_coefficients(normalise_patches(rng.uniform(0.5, 1.5, size=(n, 16, 16)))) for n in counts]
    indices = [select_coefficients(t, k) for t, k in zip(templates, (50, 30, 80))]
    bank = RegionBank(templates, indices, w)
    patches = rng.uniform(0.5, 1.5, size=(7, 3, 5, 16, 16))  # frames, regions, samples
    q, d = classify_regions(patches, bank)
    for r in range(3):
        qr, dr = classify(patches[:, r], templates[r], indices[r], w)
        np.testing.assert_allclose(q[:, r], qr, atol=1e-9)
        np.testing.assert_allclose(d[:, r], dr, rtol=1e-9)
    assert (q[:, 0] <= 2).all() and (q[:, 2] <= 3).all()


def test_hold_and_decay():
    v = np.array([[1.0], [2.0], [5.0], [5.0], [3.0]])
    seen = np.array([[False], [True], [False], [False], [True]])
    t = np.arange(5.0)
    out = hold_and_decay(v, seen, t, decay=2.0)[:, 0]
    np.testing.assert_allclose(out, [0.0, 2.0, 2.0 * np.exp(-0.5), 2.0 * np.exp(-1.0), 3.0])
    np.testing.assert_allclose(hold_and_decay(v, seen, t, decay=0.0)[:, 0], [0, 2, 0, 0, 3])
    # frame 1 is seen, but not well (a lid half over the region): the hidden frames 2-3 hold frame 0's
    # reading instead, decaying from frame 0's time; frame 1 shows its own reading
    seen0 = np.array([[True], [True], [False], [False], [True]])
    well = np.array([[True], [False], [True], [True], [True]])  # (well_seen on hidden frames counts for nothing)
    out = hold_and_decay(v, seen0, t, decay=2.0, well_seen=well)[:, 0]
    np.testing.assert_allclose(out, [1.0, 2.0, np.exp(-1.0), np.exp(-1.5), 3.0])
    # never seen well before a hidden frame: neutral there
    np.testing.assert_allclose(hold_and_decay(v, seen0, t, 2.0, np.zeros_like(well))[:, 0], [1, 2, 0, 0, 3])


def _blips(fps: float, widths, peak: float = 0.3, gap: int = 12):
    """A take at ``fps`` of rest with, per width, a run of that many frames at ``peak`` (rest between)."""
    q = np.zeros(gap)
    for w in widths:
        q = np.r_[q, np.full(w, peak), np.zeros(gap)]
    return q[:, None], np.arange(len(q)) / fps


@pytest.mark.parametrize("fps, dropped, kept", [(30.0, [1, 2], [3, 4]), (60.0, [1, 2, 3, 4], [5, 6]),
                                                (24.0, [1], [2, 3]), (25.0, [1], [2])])
def test_drop_short_events_by_time_not_frames(fps, dropped, kept):
    # 70 ms: what a run of k frames lasts is k frame steps, so the frame rate sets how many go
    q, t = _blips(fps, dropped + kept)
    out = drop_short_events(q, t, min_event=0.07)[:, 0]
    runs = np.split(out, np.flatnonzero(np.diff((q[:, 0] > 0).astype(int))) + 1)[1::2]
    assert [r.max() for r in runs] == [0.0] * len(dropped) + [0.3] * len(kept)


def test_drop_short_events_keeps_what_may_be_motion():
    q, t = _blips(30.0, [1, 2])
    # a brief run that reaches a layer is a fast motion, not noise
    big = q.copy()
    big[big > 0] = 1.5
    np.testing.assert_array_equal(drop_short_events(big, t, 0.07), big)
    # runs at the take's first or last frame (their length is unknown), and min_event 0
    edge = np.r_[[0.2], np.zeros(10), [0.2]][:, None]
    np.testing.assert_array_equal(drop_short_events(edge, np.arange(12) / 30.0, 0.07), edge)
    np.testing.assert_array_equal(drop_short_events(q, t, 0.0), q)
    # regions apart: a blip in one, a long run in the other
    both = np.c_[q[:, 0], np.r_[np.zeros(5), np.full(10, 0.2), np.zeros(len(q) - 15)]]
    out = drop_short_events(both, t, 0.07)
    assert out[:, 0].max() == 0.0 and np.array_equal(out[:, 1], both[:, 1])


def test_drop_short_events_measures_time_across_dropped_frames():
    # two readings a frame apart in the list, but 0.1 s apart in time (footage frames missing between)
    q = np.r_[np.zeros(5), [0.3, 0.3], np.zeros(5)][:, None]
    t = np.r_[np.arange(6) / 30.0, 5 / 30.0 + 0.1 + np.arange(6) / 30.0]
    np.testing.assert_array_equal(drop_short_events(q, t, 0.07), q)
    np.testing.assert_array_equal(drop_short_events(q, np.arange(12) / 30.0, 0.07)[:, 0], np.zeros(12))


def test_bilinear_matches_map_coordinates():
    rng = np.random.default_rng(3)
    img = rng.normal(size=(20, 30))
    xy = rng.uniform([0, 0], [29, 19], size=(100, 2))
    vals, inside = bilinear_sample(img, xy)
    ref = ndimage.map_coordinates(img, [xy[:, 1], xy[:, 0]], order=1)
    np.testing.assert_allclose(vals, ref, atol=1e-12)
    assert inside.all()
    _, inside = bilinear_sample(img, np.array([[-1.0, 3.0], [3.0, 19.6], [np.nan, 1.0]]))
    assert not inside.any()


def test_facing():
    pts = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 10.0]])
    assert facing(np.array([[0, 0, -1.0], [0, 0, 1.0]]), pts).tolist() == [1.0, -1.0]


def test_alpha_ramp_and_layers():
    mask = np.zeros((40, 40), bool)
    mask[5:35, 5:35] = True
    alpha = region_alpha(mask, ramp=10)
    assert alpha[0, 0] == 0 and alpha[20, 20] == 1.0
    np.testing.assert_allclose(alpha[20, 5:16], np.minimum(np.arange(1, 12) / 10, 1.0))
    layers = np.arange(3.0)[:, None, None, None] * np.ones((3, 2, 2, 1))
    assert layer_lookup(layers, 1.25)[0, 0, 0] == pytest.approx(1.25)
    assert layer_lookup(layers, 9)[0, 0, 0] == 2.0
    neutral = np.zeros((10, 10, 1))
    out = compose_texture(neutral, [layers], [np.ones((2, 2))], [(3, 4)], np.array([2.0]))
    assert out[3:5, 4:6].min() == 2.0 and out.sum() == 8.0


@pytest.mark.parametrize("distortion", [[-0.05, 0.02, 0, 0, 0], [0.1, -0.2, 0.001, -0.002, 0.05],
                                        [0.1, -0.2, 0.001, -0.002, 0.05, 0.01, 0.02, -0.03],
                                        [0.1, -0.2, 0.001, -0.002, 0.05, 0.01, 0.02, -0.03, 0.001, 0.002, -0.001, 0.003],
                                        [0.1, -0.2, 0.001, -0.002, 0.05, 0, 0, 0, 0, 0, 0, 0, 0.01, -0.02]])
def test_numpy_projection_matches_opencv(distortion):
    from facepipe.core.camera import Camera, project_distorted, project_distorted_fast

    rng = np.random.default_rng(7)
    X = rng.uniform([-3, -2, 8], [3, 2, 20], size=(500, 3))
    camera = Camera(np.array([[800, 0, 320], [0, 780, 240], [0, 0, 1.0]]), np.array(distortion), 640, 480, "test")
    np.testing.assert_allclose(project_distorted_fast(camera, X), project_distorted(camera, X), atol=1e-9)


def test_light_fit_recovers_a_lambertian_light_despite_outliers():
    from facepipe.core.lighting import fit_light, light_shading, sh_basis

    rng = np.random.default_rng(8)
    normals = rng.normal(size=(3000, 3))
    normals[:, 2] = -np.abs(normals[:, 2])  # the half facing the camera
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    albedo = rng.uniform(0.3, 0.9, size=3000)
    light = np.array([0.5, 0.1, -0.2, -0.3, 0.05, 0.0, 0.02, 0.04, 0.03])
    values = albedo * (sh_basis(normals) @ light)
    values[:300] = rng.uniform(0, 1, size=300)  # an eye, teeth, a shadow: what the model does not hold
    values[300:310] = np.nan
    got = fit_light(values, albedo, normals)
    np.testing.assert_allclose(sh_basis(normals[310:]) @ got, sh_basis(normals[310:]) @ light, atol=2e-3)
    # a second construction of the basis: the Lambertian shading of a distant light l is linear in
    # (1, n, quadratic terms); a light along -z gives shading growing with -n_z
    assert sh_basis(np.array([0.0, 0.0, -1.0]))[3] == -1.0 and sh_basis(np.array([1.0, 0, 0]))[7] == 1.0
    assert (light_shading(normals, -light) > 0).all()  # the floor keeps it positive


def test_usable_median_is_nanmedian_row_by_row():
    """The light fits' robust scale: each row's median over its usable entries is NumPy's
    nanmedian of the row with the others NaN, exactly (odd and even counts, rows sharing a count
    and not, a row with one entry, a row with none: NaN, and every entry usable)."""
    import warnings

    from facepipe.core.lighting import usable_median

    rng = np.random.default_rng(5)
    values = rng.normal(size=(9, 40))
    usable = rng.random((9, 40)) < 0.6
    usable[1] = usable[0]          # rows of one frame share their usable points
    usable[2, :] = False           # none
    usable[3, :] = False
    usable[3, 7] = True            # one
    usable[4, :] = True            # all of one row
    usable[5, :] = usable[5, :] & (np.arange(40) < 12)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # nanmedian of the empty row
        expected = np.nanmedian(np.where(usable, values, np.nan), axis=-1)
    got = usable_median(values, usable)
    assert np.array_equal(np.isnan(got), np.isnan(expected))
    assert np.array_equal(got[~np.isnan(got)], expected[~np.isnan(expected)])
    assert np.array_equal(usable_median(values, np.ones_like(usable)), np.median(values, axis=-1))


def test_light_residual_is_the_median_relative_misfit_of_each_frame():
    """An independent construction: intensities made exactly by a light read 0; scaled by 1 ± e
    at every point they read e (the median of |e|); points without a value are left out; a frame
    with no point left reads NaN. The same for an ambient and distant light, by its own shading."""
    from facepipe.core.lighting import light_residual, point_shading, sh_basis

    rng = np.random.default_rng(11)
    normals = rng.normal(size=(3, 400, 3))
    normals[..., 2] = -np.abs(normals[..., 2])
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    albedo = rng.uniform(0.3, 0.9, size=400)
    sh = np.array([[0.8, 0.1, -0.2, -0.3, 0.05, 0.0, 0.02, 0.04, 0.03]] * 3)
    exact = albedo * np.einsum("bkc,bc->bk", sh_basis(normals), sh)
    assert (exact > 0).all()
    np.testing.assert_allclose(light_residual(exact, albedo, normals, sh), 0.0, atol=1e-12)
    error = np.array([0.02, 0.05, 0.3])
    signs = rng.choice([-1.0, 1.0], size=(3, 400))
    off = exact * (1.0 + signs * error[:, None])
    off[1, :150] = np.nan  # points the frame does not show
    off[2] = np.nan
    got = light_residual(off, albedo, normals, sh)
    np.testing.assert_allclose(got[:2], error[:2], rtol=1e-9)
    assert np.isnan(got[2])
    point = np.array([[0.3, -0.2, -0.3, -0.9]] * 3)  # ambient + a key light towards the camera's side
    lit = albedo * np.stack([point_shading(normals[b], point[b]) for b in range(3)])
    keep = lit > 0
    off = np.where(keep, lit * (1.0 + signs * error[:, None]), np.nan)
    np.testing.assert_allclose(light_residual(off, albedo, normals, point), error, rtol=1e-9)


def test_light_shading_as_a_quadratic_form_is_the_basis_product():
    from facepipe.core.lighting import sh_basis, sh_quadratic

    rng = np.random.default_rng(10)
    normals = rng.normal(size=(4, 50, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    for light in rng.normal(size=(5, 9)):
        np.testing.assert_allclose(sh_quadratic(normals, light), sh_basis(normals) @ light, atol=1e-12)


def test_light_fit_with_too_few_points_is_uniform():
    from facepipe.core.lighting import fit_light, light_shading

    normals = np.tile([0.0, 0.0, -1.0], (30, 1))
    values = np.full(30, np.nan)
    values[:5] = 0.5
    light = fit_light(values, np.ones(30), normals)
    np.testing.assert_allclose(light_shading(normals, light), 1.0)


def test_light_fit_of_frames_at_once_matches_one_by_one():
    from facepipe.core.lighting import fit_light

    rng = np.random.default_rng(9)
    normals = rng.normal(size=(3, 400, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    albedo = rng.uniform(0.3, 0.9, size=400)
    values = rng.uniform(0.2, 0.8, size=(3, 400))
    values[1, :390] = np.nan  # a frame that sees too little: uniform
    together = fit_light(values, albedo, normals)
    for f in range(3):
        np.testing.assert_allclose(together[f], fit_light(values[f], albedo, normals[f]), atol=1e-10)
    np.testing.assert_allclose(together[1], np.r_[1.0, np.zeros(8)])


def _faces_of_a_head(rng, count):
    """Unit normals of the half of a sphere facing a camera looking along +z."""
    normals = rng.normal(size=(count, 3))
    normals[:, 2] = -np.abs(normals[:, 2])
    return normals / np.linalg.norm(normals, axis=-1, keepdims=True)


def test_point_shading_is_lamberts_cosine_clamped_at_zero():
    from facepipe.core.lighting import light_shading, point_shading

    light = np.array([0.2, 0.0, 0.0, -0.8])  # ambient 0.2, a light of strength 0.8 towards the camera
    normals = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [np.sin(0.5), 0.0, -np.cos(0.5)], [1.0, 0.0, 0.0]])
    np.testing.assert_allclose(point_shading(normals, light), [1.0, 0.2, 0.2 + 0.8 * np.cos(0.5), 0.2])
    # light_shading tells the model by the light's length: four values are a point light
    np.testing.assert_allclose(light_shading(normals, light), point_shading(normals, light))


@pytest.mark.parametrize("fill", [None, [-0.25, -0.1, -0.2]])
def test_point_light_fit_recovers_a_key_and_a_fill_light_despite_outliers(fill):
    from facepipe.core.lighting import fit_light, fit_point_light, point_shading, sh_basis

    rng = np.random.default_rng(12)
    normals = _faces_of_a_head(rng, 3000)
    albedo = rng.uniform(0.3, 0.9, size=3000)
    # a key light from the side: a third of the face in its attached shadow; with a fill from the other
    light = np.r_[0.15, 0.7, -0.2, -0.25, [] if fill is None else fill]
    values = albedo * point_shading(normals, light) + rng.normal(0.0, 0.003, size=3000)
    values[:300] = rng.uniform(0, 1, size=300)  # what the model does not hold
    values[300:310] = np.nan
    got = fit_point_light(values, albedo, normals)
    assert got.shape == (7,)
    keep = slice(310, None)
    error_point = np.abs(point_shading(normals[keep], got) - point_shading(normals[keep], light))
    np.testing.assert_allclose(got[1:4], light[1:4], atol=0.03)  # the key light itself
    # the nine terms cannot follow the terminators' kinks: an independent check that the model matters
    nine = fit_light(values, albedo, normals)
    error_nine = np.abs(sh_basis(normals[keep]) @ nine - point_shading(normals[keep], light))
    assert error_point.max() < 0.02 < error_nine.max()


def test_point_light_fit_of_frames_at_once_matches_one_by_one():
    from facepipe.core.lighting import fit_point_light, point_shading

    rng = np.random.default_rng(13)
    normals = np.stack([_faces_of_a_head(rng, 500) for _ in range(4)])
    albedo = rng.uniform(0.3, 0.9, size=500)
    lights = np.array([[0.3, 0.0, 0.0, -0.7, 0.0, 0.0, 0.0], [0.1, -0.6, 0.3, -0.3, 0.3, 0.1, -0.2],
                       [0.5, 0.2, 0.2, -0.2, 0.0, 0.0, 0.0], [0.3, 0.0, 0.0, -0.7, 0.0, 0.0, 0.0]])
    values = np.stack([albedo * point_shading(n, light) for n, light in zip(normals, lights)])
    values[2, :480] = np.nan  # a frame that sees too little: uniform
    values[3, :100] = np.nan  # one that sees part of the face
    together = fit_point_light(values, albedo, normals)
    for f in range(4):
        np.testing.assert_allclose(together[f], fit_point_light(values[f], albedo, normals[f]), atol=1e-10)
    np.testing.assert_allclose(together[2], np.r_[1.0, np.zeros(6)])
    for f in (0, 1, 3):
        np.testing.assert_allclose(point_shading(normals[f], together[f]), point_shading(normals[f], lights[f]),
                                   atol=1e-4)


def test_masked_normalisation_and_distances_reduce_to_the_whole_patch():
    rng = np.random.default_rng(11)
    patches = rng.uniform(0.5, 1.5, size=(4, 16, 16))
    full = np.ones(patches.shape, dtype=bool)
    np.testing.assert_allclose(normalise_patches(patches, True, full), normalise_patches(patches), rtol=1e-10)
    np.testing.assert_allclose(normalise_patches(patches, False, full), normalise_patches(patches, False), rtol=1e-10)
    # over a mask: the plane is the least-squares plane of the seen texels (checked with lstsq)
    mask = rng.uniform(size=(16, 16)) < 0.6
    yy, xx = np.mgrid[0:16, 0:16] - 7.5
    A = np.stack([np.ones(mask.sum()), xx[mask], yy[mask]], axis=1)
    coef = np.linalg.lstsq(A, patches[0][mask], rcond=None)[0]
    got = normalise_patches(patches[0], True, mask)
    np.testing.assert_allclose(got[mask], patches[0][mask] / (A @ coef), rtol=1e-10)
    assert (got[~mask] == 0).all()
    templates = [haar_coefficients(normalise_patches(rng.uniform(0.5, 1.5, size=(n, 16, 16)))) for n in (3, 5)]
    bank = RegionBank(templates, [select_coefficients(t, 50) for t in templates], coefficient_weights(16))
    region = np.array([0, 1, 1, 0])
    norm = normalise_patches(patches)
    whole = bank.distances(haar_coefficients(norm)[:, None, None, :].repeat(2, axis=1))[np.arange(4), region, 0]
    masked = bank.masked_distances(norm, full, region)
    np.testing.assert_allclose(masked, whole, rtol=1e-9)


def test_partly_hidden_patch_classified_on_its_seen_texels():
    rng = np.random.default_rng(12)
    a, b, layers = _blend_templates(rng, 5)
    templates = haar_coefficients(normalise_patches(np.stack(layers)))
    bank = RegionBank([templates], [select_coefficients(templates, 50)], coefficient_weights(16))
    truth = np.linspace(0.2, 3.8, 10)
    patches = np.stack([a + (b - a) * t / 4 for t in truth])[:, None, None]  # (T, R=1, S=1, 16, 16)
    seen = np.ones(patches.shape, dtype=bool)
    seen[..., :6, :] = False            # the top rows covered (a brow over an eyelid) by a brighter fold
    covered = np.where(seen, patches, 1.4 + 0.2 * rng.uniform(size=patches.shape))
    q_blind, _ = classify_regions(covered, bank)
    q_seen, _ = classify_regions(covered, bank, seen=seen)
    assert np.abs(q_seen[:, 0] - truth).max() < 0.15
    assert np.abs(q_blind[:, 0] - truth).max() > 0.5
    # seen too little: the sample takes no part; no usable sample: NaN (held by the caller)
    two = np.concatenate([covered, patches], axis=2)                 # (T, 1, 2, 16, 16)
    seen2 = np.concatenate([np.zeros_like(seen), seen], axis=2)
    np.testing.assert_allclose(classify_regions(two, bank, seen=seen2)[0], q_seen, atol=1e-12)
    assert np.isnan(classify_regions(covered, bank, seen=np.zeros_like(seen))[0]).all()


def test_partly_seen_exact_template_reads_its_own_index_with_either_shading():
    # templates stored divided by their mean (shading off) or by their plane: a partly seen
    # sample of a template reads that template's index either way (its stored surface, taken
    # back before the seen texels' surface is divided out, is the one it was stored by; exactly
    # for the mean, to the plane of a plane-divided template for the plane)
    rng = np.random.default_rng(21)
    a, b, layers = _blend_templates(rng, 5)
    yy, xx = np.mgrid[0:16, 0:16] - 7.5
    lit = np.stack(layers) * (1.0 + 0.04 * xx + 0.02 * yy)   # a strong gradient: plane and mean differ
    seen = np.ones((5, 1, 1, 16, 16), dtype=bool)
    seen[..., :5, :] = False
    for shading in (True, False):
        templates = haar_coefficients(normalise_patches(lit, shading))
        bank = RegionBank([templates], [select_coefficients(templates, 50)], coefficient_weights(16))
        q, _ = classify_regions(lit[:, None, None], bank, shading=shading, seen=seen)
        np.testing.assert_allclose(q[:, 0], np.arange(5), atol=0.02 if shading else 1e-9)


def test_partly_seen_samples_match_templates_normalised_from_their_samples():
    # with the layers' samples kept, a partly seen sample's templates are normalised over its
    # seen texels as it is: any layer, however little of it is seen and whatever the surface,
    # reads its own index; from the normalised templates alone that holds only while most is seen
    rng = np.random.default_rng(22)
    a, b, layers = _blend_templates(rng, 5)
    yy, xx = np.mgrid[0:16, 0:16] - 7.5
    lit = np.stack(layers) * (1.0 + 0.04 * xx + 0.02 * yy + 0.002 * xx * yy)
    seen = np.ones((5, 1, 1, 16, 16), dtype=bool)
    seen[..., :9, :] = False                            # over half the patch hidden (a lid over an eye)
    for order in (0, 1, 2):
        templates = haar_coefficients(normalise_patches(lit, order))
        indices, w = [select_coefficients(templates, 50)], coefficient_weights(16)
        exact = RegionBank([templates], indices, w, orders=[max(order, 1)], patches=[lit.reshape(5, -1)])
        q, residual = classify_regions(lit[:, None, None], exact, shading=order > 0, seen=seen, min_seen=0.3)
        np.testing.assert_allclose(q[:, 0], np.arange(5), atol=1e-9)
        assert residual.max() < 1e-9
        # the distances are those of the templates normalised over the seen texels by hand (scaled
        # by the texels over those seen, so partly and wholly seen samples compare)
        part = normalise_patches(lit[2], order, seen[0, 0, 0])
        by_hand = haar_coefficients(normalise_patches(lit, order, seen[0, 0, 0]))
        d = exact.masked_distances(part[None], seen[0, 0, :1], np.array([0]), shading=order > 0)
        diff = (haar_coefficients(part) - by_hand)[:, indices[0]]
        scale = 256 / seen[0, 0, 0].sum()
        np.testing.assert_allclose(d[0], scale * (diff ** 2 * w[indices[0]]).sum(-1), rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="patches"):
        RegionBank([templates], indices, w, patches=[lit.reshape(5, -1)[:4]])


def test_masked_templates_kept_per_mask_give_the_same_distances():
    # the templates normalised over a mask are kept and reused: distances from a bank that has
    # seen the masks (and one whose store overflows and is emptied) equal a fresh bank's, and each
    # sample's equal those of it matched alone
    rng = np.random.default_rng(21)
    templates = [haar_coefficients(normalise_patches(rng.uniform(0.5, 1.5, size=(n, 16, 16)))) for n in (3, 5)]
    args = (templates, [select_coefficients(t, 50) for t in templates], coefficient_weights(16))
    masks = rng.uniform(size=(3, 16, 16)) < 0.7
    pick = np.array([0, 1, 2, 0, 1, 1, 2, 0])
    region = np.array([0, 1, 1, 0, 0, 1, 0, 1])
    mask = masks[pick]
    norm = normalise_patches(rng.uniform(0.5, 1.5, size=(8, 16, 16)), True, mask)
    fresh = RegionBank(*args).masked_distances(norm, mask, region)
    alone = np.concatenate([RegionBank(*args).masked_distances(norm[i:i + 1], mask[i:i + 1], region[i:i + 1])
                            for i in range(8)])
    np.testing.assert_allclose(fresh, alone, rtol=1e-12)
    warm = RegionBank(*args)
    warm.masked_distances(norm[:3], mask[:3], region[:3])      # some masks stored first
    np.testing.assert_allclose(warm.masked_distances(norm, mask, region), fresh, rtol=1e-12)
    np.testing.assert_allclose(warm.masked_distances(norm, mask, region), fresh, rtol=1e-12)  # all from the store
    small = RegionBank(*args)
    small.MASK_CACHE = 2
    small.masked_distances(norm[:3], mask[:3], region[:3])
    np.testing.assert_allclose(small.masked_distances(norm, mask, region), fresh, rtol=1e-12)
    assert len(small._mask_cache) <= max(2, len(set(zip(pick, region))))


def test_half_rolled_away_template_classified_on_its_stable_half():
    # the lower half of a region's template rolls out of view (an upper lid into its socket):
    # in every example, and in the frames, it shows something unrelated to the layer (the fold
    # seen edge-on: dark, changing with the geometry). Templates, kept coefficients and the match
    # on the stable half recover Q; on the whole patch the rolled half decides.
    rng = np.random.default_rng(31)
    n = 5
    a, b, _ = _blend_templates(rng, n)
    stable = np.zeros((16, 16), dtype=bool)
    stable[:8] = True

    def rolled(k):  # what the rolled-away half shows: dark folds whose place moves with the fold
        fold = 0.3 + 0.6 * rng.uniform(size=(16, 16))
        return np.where(stable, 0.0, fold * (1.0 + np.sin(k + np.arange(16))[None, :]))

    def sample(t):
        return np.where(stable, a + (b - a) * t / (n - 1), rolled(7.3 * t))

    examples = np.stack([sample(k) for k in range(n)])
    w = coefficient_weights(16)
    masked = haar_coefficients(normalise_patches(examples, True, stable))
    whole = haar_coefficients(normalise_patches(examples))
    bank = RegionBank([masked], [select_coefficients(masked, 50)], w, masks=stable.reshape(1, -1))
    blind = RegionBank([whole], [select_coefficients(whole, 50)], w)
    # the kept coefficients are chosen on the stable half: none whose Haar row lies on the rolled half alone
    H, _ = haar_matrix(16)
    assert (np.abs(H[select_coefficients(masked, 50)][:, stable.ravel()]).max(axis=1) > 0).all()
    assert not (np.abs(H[select_coefficients(whole, 50)][:, stable.ravel()]).max(axis=1) > 0).all()
    truth = np.linspace(0.1, 3.9, 12)
    patches = np.stack([sample(t) for t in truth])[:, None, None] * 0.8  # (T, R=1, S=1, 16, 16), another exposure
    q, _ = classify_regions(patches, bank)
    q_blind, _ = classify_regions(patches, blind)
    assert np.abs(q[:, 0] - truth).max() < 0.15
    assert np.abs(q_blind[:, 0] - truth).max() > 0.5
    # part of the stable half hidden as well: matched on what is left of it, still within 0.15
    seen = np.ones(patches.shape, dtype=bool)
    seen[..., :3, :] = False
    q_part, _ = classify_regions(np.where(seen, patches, 5.0), bank, seen=seen)
    assert np.abs(q_part[:, 0] - truth).max() < 0.15


def test_bank_with_stable_masks_against_direct_distances():
    # distances of a masked bank: the patch normalised over its region's mask (plane by lstsq),
    # its Haar coefficients against the stored templates on the kept terms, summed by hand
    rng = np.random.default_rng(32)
    masks = rng.uniform(size=(2, 16, 16)) < 0.7
    raw = [rng.uniform(0.5, 1.5, size=(k, 16, 16)) for k in (3, 5)]
    templates = [haar_coefficients(normalise_patches(t, True, m)) for t, m in zip(raw, masks)]
    indices = [select_coefficients(t, 40) for t in templates]
    w = coefficient_weights(16)
    bank = RegionBank(templates, indices, w, masks=masks.reshape(2, -1))
    patches = rng.uniform(0.5, 1.5, size=(3, 2, 1, 16, 16))
    yy, xx = np.mgrid[0:16, 0:16] - 7.5
    q, d = classify_regions(patches, bank, interpolation="parabola")
    q_path, d_path = classify_regions(patches, bank)
    for r in range(2):
        m = masks[r]
        A = np.stack([np.ones(m.sum()), xx[m], yy[m]], axis=1)
        for f in range(3):
            p = patches[f, r, 0]
            norm = np.zeros((16, 16))
            norm[m] = p[m] / (A @ np.linalg.lstsq(A, p[m], rcond=None)[0])
            c = haar_coefficients(norm)
            direct = [np.sum(w[indices[r]] * (c[indices[r]] - t[indices[r]]) ** 2) for t in templates[r]]
            assert d[f, r] == pytest.approx(min(direct), rel=1e-9)
            assert q[f, r] == pytest.approx(peak_index(np.array(direct)), abs=1e-9)
            along, gap = _nearest_on_path(c[indices[r]], templates[r][:, indices[r]], w[indices[r]])
            assert q_path[f, r] == pytest.approx(along, abs=1e-9)
            assert d_path[f, r] == pytest.approx(gap, rel=1e-9)
    # every stable texel seen: the masked match is the plain one
    norm = normalise_patches(patches[:, 0, 0], True, masks[0])
    plain = bank.distances(haar_coefficients(norm)[:, None, None, :].repeat(2, axis=1))[:, 0, 0]
    np.testing.assert_allclose(bank.masked_distances(norm, np.broadcast_to(masks[0], norm.shape), np.zeros(3, int)),
                               plain, rtol=1e-9)
    with pytest.raises(ValueError):
        RegionBank(templates, indices, w, masks=np.zeros((2, 256), dtype=bool))


def test_rest_floor_is_the_highest_reading_at_rest():
    readings = np.array([[0.1, 0.0, np.nan],
                         [0.3, 2.0, np.nan],
                         [np.nan, 0.2, 0.4],
                         [2.5, 0.1, 0.7]])
    at_rest = np.array([[True, True, True],
                        [True, False, True],     # region 1's own layer: not at rest
                        [True, True, False],
                        [False, True, True]])
    floor, row = rest_floor(readings, at_rest, most=0.5)
    # region 0: the highest of 0.1, 0.3 (NaN, hidden, and its own frame 3 ignored); region 1: 0.2;
    # region 2: 0.7 capped at 0.5 (frame 2 is its own layer); the rows that read them
    np.testing.assert_allclose(floor, [0.3, 0.2, 0.5])
    np.testing.assert_array_equal(row, [1, 2, 3])
    # a region never seen at rest: floor 0, no row
    floor, row = rest_floor(readings[:, :1], np.zeros((4, 1), dtype=bool))
    assert floor[0] == 0.0 and row[0] == -1


def test_above_rest_is_zero_below_the_floor_monotone_and_keeps_the_extreme():
    q = np.linspace(0.0, 4.0, 81)[:, None].repeat(2, axis=1)
    q[5, 1] = np.nan
    out = above_rest(q, np.array([0.4, 0.0]), [5, 5])
    assert (out[q[:, 0] <= 0.4, 0] == 0.0).all()
    assert np.all(np.diff(out[:, 0]) >= 0) and np.all(np.diff(out[q[:, 0] > 0.4, 0]) > 0)
    assert out[-1, 0] == pytest.approx(4.0)
    # linear between: the floor to 0, the extreme layer to itself
    np.testing.assert_allclose(out[q[:, 0] > 0.4, 0], (q[q[:, 0] > 0.4, 0] - 0.4) * 4.0 / 3.6)
    # a zero floor changes nothing, a hidden region stays NaN
    assert np.isnan(out[5, 1])
    np.testing.assert_array_equal(np.delete(out[:, 1], 5), np.delete(q[:, 1], 5))


def test_unseen_texels_continue_the_texture_around_them():
    """Push-pull fill: seen texels untouched, a constant kept exactly (to float32), a hole in a
    linear ramp filled close to the ramp and within the values at its border, a hole's fill
    nearer the colour beside it than the image's mean (what a flat fill gives)."""
    from facepipe.core.layered_texture import fill_unseen

    rng = np.random.default_rng(1)
    image = rng.uniform(size=(37, 53, 3))
    seen = np.ones((37, 53), dtype=bool)
    seen[5:20, 10:40] = False
    out = fill_unseen(image, seen)
    assert out.dtype == image.dtype
    np.testing.assert_array_equal(out[seen], image[seen])
    np.testing.assert_allclose(fill_unseen(np.full((37, 53, 3), 0.3), seen), 0.3, atol=1e-6)

    y, x = np.mgrid[0:64, 0:64]
    ramp = np.repeat((x / 63.0)[..., None], 3, axis=-1)
    hole = np.ones((64, 64), dtype=bool)
    hole[20:30, 20:30] = False
    filled = fill_unseen(ramp, hole)[~hole]
    assert np.abs(filled - ramp[~hole]).max() < 0.02
    assert filled.min() >= 19 / 63.0 - 1e-6 and filled.max() <= 30 / 63.0 + 1e-6

    halves = np.zeros((32, 64, 1))
    halves[:, 32:] = 1.0  # dark left, bright right; a hole in the bright half, next to nothing dark
    gap = np.ones((32, 64), dtype=bool)
    gap[10:20, 44:54] = False
    assert fill_unseen(halves, gap)[~gap].min() > 0.9  # a flat fill would give the mean, about 0.5

    nothing = np.zeros((4, 4), dtype=bool)
    np.testing.assert_array_equal(fill_unseen(image[:4, :4], nothing), image[:4, :4])


def test_quadratic_shading_against_least_squares():
    # order 2: the least-squares quadratic through the patch (checked with lstsq), over the whole
    # patch and over a mask; a patch that is all quadratic shading normalises to ones, which the
    # plane cannot do
    from facepipe.core.appearance import normalise_patches as norm
    rng = np.random.default_rng(31)
    patches = rng.uniform(0.5, 1.5, size=(3, 16, 16))
    yy, xx = np.mgrid[0:16, 0:16] - 7.5
    A = np.stack([np.ones(256), xx.ravel(), yy.ravel(), xx.ravel() ** 2, xx.ravel() * yy.ravel(), yy.ravel() ** 2], 1)
    for p, got in zip(patches, norm(patches, 2)):
        np.testing.assert_allclose(got, p / (A @ np.linalg.lstsq(A, p.ravel(), rcond=None)[0]).reshape(16, 16),
                                   rtol=1e-10)
    mask = rng.uniform(size=(16, 16)) < 0.6
    Am = A[mask.ravel()]
    coef = np.linalg.lstsq(Am, patches[0][mask], rcond=None)[0]
    got = norm(patches[0], 2, mask)
    np.testing.assert_allclose(got[mask], patches[0][mask] / (Am @ coef), rtol=1e-10)
    assert (got[~mask] == 0).all()
    curved = 0.9 + 0.01 * xx - 0.002 * xx ** 2 + 0.001 * xx * yy - 0.003 * yy ** 2
    np.testing.assert_allclose(norm(curved, 2), 1.0, atol=1e-12)
    assert np.abs(norm(curved, 1) - 1.0).max() > 0.05
    # a texture under a curved light: the quadratic gives back the texture's own normalisation
    texture = 1.0 + 0.1 * np.sin(xx * 1.7) * np.cos(yy * 1.3)
    np.testing.assert_allclose(norm(texture * curved, 2), norm(texture, 2), atol=0.01)
    assert np.abs(norm(texture * curved, 1) - norm(texture, 1)).max() > 0.05


def test_shading_order_keeps_a_wrinkle_region_quadratic_and_a_moving_iris_planar():
    from facepipe.core.appearance import shading_order
    yy, xx = np.mgrid[0:16, 0:16] - 7.5
    w = coefficient_weights(16)
    # wrinkles: lines deepening from layer to layer, fast over the patch
    lines = [1.0 - 0.1 * k * (np.cos(xx * 1.2) > 0.3) for k in range(5)]
    order, kept = shading_order(np.stack(lines), None, w)
    assert order == 2 and kept > 0.9
    # an iris filling the patch, moving across it: a change as smooth as the shading
    iris = [1.0 - 0.6 * np.exp(-((xx - 2.0 * k + 4.0) ** 2 + yy ** 2) / 80.0) for k in range(5)]
    order, kept = shading_order(np.stack(iris), None, w)
    assert order == 1 and kept < 0.75


def test_regions_with_their_own_shading_surfaces_match_one_by_one():
    rng = np.random.default_rng(32)
    w = coefficient_weights(16)
    orders = [1, 2, 2]
    raw = [rng.uniform(0.5, 1.5, size=(n, 16, 16)) for n in (3, 5, 4)]
    templates = [haar_coefficients(normalise_patches(t, o)) for t, o in zip(raw, orders)]
    indices = [select_coefficients(t, 50) for t in templates]
    bank = RegionBank(templates, indices, w, orders=orders)
    patches = rng.uniform(0.5, 1.5, size=(6, 3, 5, 16, 16))
    q, d = classify_regions(patches, bank)
    for r, o in enumerate(orders):
        qr, dr = classify(patches[:, r], templates[r], indices[r], w, shading=o)
        np.testing.assert_allclose(q[:, r], qr, atol=1e-9)
        np.testing.assert_allclose(d[:, r], dr, rtol=1e-9)
    # partly seen samples: the masked templates too are normalised by each region's own surface
    seen = np.ones(patches.shape, dtype=bool)
    seen[..., :4, :] = False
    q_seen, _ = classify_regions(patches, bank, seen=seen)
    for r, o in enumerate(orders):
        one = RegionBank([templates[r]], [indices[r]], w, orders=[o])
        np.testing.assert_allclose(q_seen[:, r], classify_regions(patches[:, r:r + 1], one, seen=seen[:, r:r + 1])[0][:, 0],
                                   atol=1e-9)
    # without shading every region is divided by its mean alone
    q_mean, _ = classify_regions(patches, bank, shading=False)
    np.testing.assert_allclose(q_mean[:, 0], classify(patches[:, 0], templates[0], indices[0], w, shading=False)[0],
                               atol=1e-9)


def test_config_offers_the_interpolations_classification_knows():
    from facepipe.io.config import PEAK_INTERPOLATIONS as offered

    assert offered == PEAK_INTERPOLATIONS


def test_config_offers_the_shading_references_classification_knows():
    from facepipe.core.appearance import SHADING_REFERENCES
    from facepipe.io.config import SHADING_REFERENCES as offered

    assert offered == SHADING_REFERENCES


def test_config_offers_the_light_models_classification_knows():
    from facepipe.core.lighting import LIGHT_MODELS
    from facepipe.io.config import LIGHT_MODELS as offered

    assert offered == LIGHT_MODELS


def _line_layers(rng, n=5, size=16):
    """n templates (n, size, size) evenly along a straight line in texel space (1 plus patterns
    without a plane's part: the shading plane of any sum of them is 1, so the normalisation
    leaves them as they are) and an off-line pattern, part of it along the layers' step: another
    expression that reads as the region's first layers."""
    yy, xx = np.mgrid[0:size, 0:size] - (size - 1) / 2.0
    plane = np.stack([np.ones(size * size), xx.ravel(), yy.ravel()], axis=1)

    def pattern():
        p = ndimage.gaussian_filter(rng.normal(size=(size, size)), 1.0).ravel()
        p = p - plane @ np.linalg.lstsq(plane, p, rcond=None)[0]
        return (0.1 * p / p.std()).reshape(size, size)
    start, step = 1.0 + pattern(), pattern()
    off = 0.6 * step + pattern()
    layers = np.stack([start + k * step for k in range(n)])
    return layers, step, off


def _bank(layers, nuisance=None, keep=64):
    templates = haar_coefficients(normalise_patches(layers))
    return RegionBank([templates], [select_coefficients(templates, keep)], coefficient_weights(16),
                      nuisance=None if nuisance is None else [nuisance])


def test_explained_away_directions_are_left_out_of_every_distance():
    """With directions explained away, a patch's distance to a template is the least weighted
    distance over the kept terms once any combination of the directions is taken off: checked
    against a least-squares solve, wholly seen and over part of the texels."""
    from facepipe.core.appearance import rest_direction

    rng = np.random.default_rng(31)
    layers, _, off = _line_layers(rng)
    plain = _bank(layers)
    extra = 1.0 + _line_layers(rng)[2]
    dirs = np.stack([rest_direction(plain, 1.0 + off, 0), rest_direction(plain, extra, 0)])
    bank = _bank(layers, dirs)
    H, _ = haar_matrix(16)
    idx = np.asarray(select_coefficients(plain.templates[0], 64))
    root = np.sqrt(coefficient_weights(16)[idx])

    def least(diff_pixels, directions):  # weighted kept-term residual of a texel difference
        a = (directions @ H.T)[:, idx].T * root[:, None]
        b = (diff_pixels @ H.T)[idx] * root
        x, *_ = np.linalg.lstsq(a, b, rcond=None)
        return float(((b - a @ x) ** 2).sum())

    patches = 1.0 + 0.1 * rng.normal(size=(6, 16, 16))
    coefficients = haar_coefficients(normalise_patches(patches))
    d = bank.distances(coefficients[:, None, None, :])[:, 0, 0]              # (6, n)
    pixels = normalise_patches(patches).reshape(6, -1)
    for i in range(6):
        for k in range(5):
            assert d[i, k] == pytest.approx(least(pixels[i] - bank.pixels[0, k], dirs), rel=1e-9, abs=1e-12)
    # the layer steps as the solve leaves them
    for k in range(4):
        assert bank.gaps[0, k] == pytest.approx(least(bank.pixels[0, k + 1] - bank.pixels[0, k], dirs), rel=1e-9)
    # over part of the texels: the directions over those texels only
    seen = np.ones((6, 16, 16), dtype=bool)
    seen[:, :5] = False
    norm = np.stack([normalise_patches(p, True, m) for p, m in zip(patches, seen)])
    masked = bank.masked_distances(norm, seen, np.zeros(6, dtype=int))
    templates = bank._masked_templates(seen.reshape(6, -1), np.zeros(6, dtype=int), True)
    scale = 256 / seen[0].sum()
    m = seen.reshape(6, -1)
    for i in range(6):
        for k in range(5):
            diff = np.where(m[i], norm[i].reshape(-1) - templates[i, k], 0.0)
            assert masked[i, k] == pytest.approx(scale * least(diff, dirs * m[i]), rel=1e-9, abs=1e-12)


def test_a_patch_off_its_layers_by_explained_directions_reads_its_layer():
    """A template plus any amount of an explained-away pattern reads the template's index,
    wholly seen or partly; without it the pattern's share along the layers moves Q."""
    from facepipe.core.appearance import kept_step_shares, rest_direction

    rng = np.random.default_rng(32)
    layers, step, off = _line_layers(rng)
    plain = _bank(layers)
    direction = rest_direction(plain, layers[0] + off, 0)   # an example at rest: the neutral plus it
    np.testing.assert_allclose(direction, off.reshape(-1), atol=1e-12)
    bank = _bank(layers, direction[None])
    k = np.array([0, 1, 2, 3, 4, 0, 2])
    amount = np.array([0.5, 1.0, -0.7, 0.3, 0.8, 1.5, 0.0])
    patches = (layers[k] + amount[:, None, None] * off)[:, None, None]       # (7, R=1, S=1, 16, 16)
    q, _ = classify_regions(patches, bank)
    np.testing.assert_allclose(q[:, 0], k, atol=1e-9)
    q_plain, _ = classify_regions(patches, plain)
    assert 0.1 < q_plain[0, 0] < q_plain[5, 0]   # the neutral plus the pattern reads part of a layer
    # partly seen (the top rows hidden by something else): the pattern over the seen texels goes too
    seen = np.ones(patches.shape, dtype=bool)
    seen[..., :4, :] = False
    # (near: the shading plane fitted over the seen texels is no longer exactly 1)
    q_seen, _ = classify_regions(np.where(seen, patches, 3.0), bank, seen=seen)
    q_seen_plain, _ = classify_regions(np.where(seen, patches, 3.0), plain, seen=seen)
    assert np.abs(q_seen[:, 0] - k).max() < 0.1 < q_seen_plain[5, 0]
    # the share of each layer step that survives: all of it for an unrelated pattern, none for
    # the step itself
    assert kept_step_shares(plain, 0, step.reshape(1, -1)) == pytest.approx(0.0, abs=1e-9)
    shares = kept_step_shares(plain, 0, direction[None])
    assert np.all((shares > 0.0) & (shares < 1.0))
    unrelated = _line_layers(np.random.default_rng(5))[1].reshape(1, -1)
    assert kept_step_shares(plain, 0, unrelated).min() > 0.9
    with pytest.raises(ValueError, match="nuisance has 2 regions"):
        RegionBank([plain.templates[0]], [select_coefficients(plain.templates[0], 64)], coefficient_weights(16),
                   nuisance=[None, None])


def test_off_path_ratio_is_the_same_at_any_weight_of_another_expression():
    """Another expression at weight w reads w times its Q and lies w² times its squared distance
    off the layers: the off-path ratio is its own at every weight; the region's own motion reads
    none (on the path)."""
    from facepipe.core.appearance import off_path_ratio

    rng = np.random.default_rng(33)
    layers, step, off = _line_layers(rng)
    bank = _bank(layers)
    w = np.array([0.1, 0.25, 0.5, 1.0])
    patches = (layers[0] + w[:, None, None] * off)[:, None, None]
    q, d = classify_regions(patches, bank)
    ratio = off_path_ratio(q, d, bank.gaps[:, 0])[:, 0]
    assert np.all(q[:, 0] > 0) and np.all(np.diff(q[:, 0]) > 0)
    np.testing.assert_allclose(ratio, ratio[-1], rtol=1e-6)
    on = (layers[0] + w[:, None, None] * step)[:, None, None]
    q_on, d_on = classify_regions(on, bank)
    np.testing.assert_allclose(q_on[:, 0], w, atol=1e-9)
    assert np.all(off_path_ratio(q_on, d_on, bank.gaps[:, 0]) < 1e-9)
    # Q 0 (or hidden, NaN) is taken at the least Q: finite
    assert np.isfinite(off_path_ratio(np.array([[0.0], [np.nan]]), np.array([[0.2], [0.3]]), bank.gaps[:, 0])).all()


def test_conditional_floor_counts_only_at_rest_readings_as_far_off_the_path():
    from facepipe.core.appearance import conditional_floor

    # region 0: an expression reading 0.4 far off the path (ratio 2) and noise reading 0.1 off
    # it by 50; region 1: nothing at rest (NaN), region 2: a reading capped at 1 layer
    rest_q = np.array([[0.4, np.nan, 1.7], [0.1, np.nan, 0.2], [np.nan, np.nan, 0.3]])
    rest_ratio = np.array([[2.0, np.nan, 0.5], [50.0, np.nan, 1.0], [np.nan, np.nan, 1.0]])
    off = np.array([[0.01, 1.0, 0.1],      # on the path: nothing hides it
                    [1.0, 1.0, 0.3],       # half as far off as the expression: tolerance 2 hides it
                    [0.9, 5.0, 0.5],       # under half
                    [30.0, 0.0, 10.0]])    # noise-like: the noise's floor and the expression's
    got = conditional_floor(off, rest_q, rest_ratio, 2.0)
    np.testing.assert_allclose(got, [[0.0, 0.0, 0.0], [0.4, 0.0, 1.0], [0.0, 0.0, 1.0], [0.4, 0.0, 1.0]])
    # infinite tolerance: the highest at-rest reading for every reading (rest_floor's)
    floor, _ = rest_floor(rest_q, np.isfinite(rest_q))
    np.testing.assert_allclose(conditional_floor(off, rest_q, rest_ratio, np.inf), np.broadcast_to(floor, off.shape))
    # at-rest readings at or below the noise level hide every reading, on the path or off it
    np.testing.assert_allclose(conditional_floor(off, rest_q, rest_ratio, 2.0, noise=0.2),
                               [[0.1, 0.0, 0.2], [0.4, 0.0, 1.0], [0.1, 0.0, 1.0], [0.4, 0.0, 1.0]])
    # a frame reading below its own floor reads 0; above it, measured from it
    np.testing.assert_allclose(above_rest(np.array([[0.3, 2.0, 0.5]]), got[1:2], [5, 5, 5]), [[0.0, 2.0, 0.0]])


def _iris_layers(n: int = 5) -> np.ndarray:
    """(n, 16, 16) a dark disc on a bright ground moving right a pixel per layer: a gaze."""
    yy, xx = np.mgrid[0:16, 0:16] - 7.5
    return np.stack([1.0 - 0.8 * (np.hypot(xx - k, yy) < 4.0) for k in range(n)])


def test_shading_relative_to_the_neutral_takes_a_smooth_light_out_exactly():
    # a patch that is the neutral layer under a smooth shading (a plane for order 1, a quadratic
    # for order 2) reads the neutral exactly when its surface is fitted against the neutral, over
    # a partial mask too; through the patch alone the dark disc tilts the plane and it does not
    layers = _iris_layers()
    yy, xx = np.mgrid[0:16, 0:16] - 7.5
    mask = np.ones((16, 16), dtype=bool)
    mask[:3] = False
    reference = neutral_reference(layers, mask)
    np.testing.assert_allclose(reference[mask].mean(), 1.0, rtol=1e-12)
    shadings = {1: 0.6 * (1.0 + 0.02 * xx - 0.015 * yy), 2: 0.6 * (1.0 + 0.02 * xx + 0.001 * xx * yy - 0.0008 * yy * yy)}
    for order, shade in shadings.items():
        got = normalise_patches(layers[0] * shade, order, mask, reference)
        np.testing.assert_allclose(got[mask], reference[mask], rtol=1e-10)
        assert (got[~mask] == 0).all()
        alone = normalise_patches(layers[0] * shade, order, mask) - normalise_patches(layers[0], order, mask)
        assert np.abs(alone[mask]).max() > 1e-2
    # the reference's own layers: normalised against it, the neutral is the reference
    np.testing.assert_allclose(normalise_patches(layers, 1, mask, reference)[0][mask], reference[mask], rtol=1e-12)
    # without a surface (the mean alone) there is nothing to fit against
    np.testing.assert_allclose(normalise_patches(layers, 0, None, reference), normalise_patches(layers, 0), rtol=1e-12)


def test_region_bank_relative_to_the_neutral_reads_a_lit_neutral_as_rest():
    # templates normalised against the neutral layer: the neutral under a side light's ramp reads
    # Q 0 exactly, wholly or partly seen, with or without the layers' samples, and its direction
    # to explain away is nothing; each layer still reads its own index. Through each patch alone
    # the same ramp leaves the neutral template's match
    layers = _iris_layers()
    yy, xx = np.mgrid[0:16, 0:16] - 7.5
    ramp = 1.0 + 0.02 * xx - 0.01 * yy
    w = coefficient_weights(16)
    reference = neutral_reference(layers)
    templates = haar_coefficients(normalise_patches(layers, 1, None, reference))
    indices = [select_coefficients(templates, 50)]
    lit = np.broadcast_to(layers[0] * ramp, (1, 1, 5, 16, 16))
    seen = np.ones((1, 1, 5, 16, 16), dtype=bool)
    seen[..., :6, :] = False
    for patches in (None, [layers.reshape(5, -1)]):
        bank = RegionBank([templates], indices, w, patches=patches, relative=True)
        for part in (None, seen):
            q, residual = classify_regions(lit, bank, seen=part, min_seen=0.3)
            assert q[0, 0] == pytest.approx(0.0, abs=1e-9) and residual[0, 0] < 1e-12
        q, _ = classify_regions(layers[:, None, None], bank)
        np.testing.assert_allclose(q[:, 0], np.arange(5), atol=1e-9)
        np.testing.assert_allclose(rest_direction(bank, layers[0] * ramp, 0), 0.0, atol=1e-12)
    own = haar_coefficients(normalise_patches(layers, 1))
    _, residual = classify_regions(lit, RegionBank([own], [select_coefficients(own, 50)], w))
    assert residual[0, 0] > 1e-4


def test_shading_tilt_readings_are_zero_where_the_surface_takes_a_ramp_out():
    # a ramp over an even neutral (its layers add a wrinkle's stripes) is taken out by the plane
    # through the patch; over the iris only by the surface fitted against the neutral layer
    rng = np.random.default_rng(23)
    w = coefficient_weights(16)
    _, _, stripes = _blend_templates(rng, 5)
    even = np.stack(stripes) - stripes[0] + 1.0                 # the neutral exactly 1
    iris = _iris_layers()
    banks = []
    for layers, relative in ((even, False), (iris, True), (iris, False)):
        reference = neutral_reference(layers) if relative else None
        t = haar_coefficients(normalise_patches(layers, 1, None, reference))
        banks.append((RegionBank([t], [select_coefficients(t, 50)], w, relative=relative), layers[:1]))
    for bank, neutral in banks[:2]:
        np.testing.assert_allclose(shading_tilt_readings(bank, neutral), 0.0, atol=1e-9)
    # the readings are those of the four ramps classified one by one
    bank, neutral = banks[2]
    yy, xx = np.mgrid[0:16, 0:16] - 7.5
    by_hand = max(classify_regions(np.broadcast_to(neutral[0] * (1 + t * f / 7.5), (1, 1, 5, 16, 16)), bank)[0][0, 0]
                  for t in (-0.15, 0.15) for f in (xx, yy))
    np.testing.assert_allclose(shading_tilt_readings(bank, neutral), [by_hand], atol=1e-12)
