"""The rendered test footage's region layout: UV stretch and template placement on the surface."""

import numpy as np

from facepipe.appearance_sample import region_layout, uv_scales
from facepipe.pipeline.appearance_points import locate_uv, template_points


def _grid(n=41, hole=None, stretch=(1.0, 1.0)):
    """A flat n × n vertex grid over [0, 1]² (z = 0), UV = (x / stretch_u, y / stretch_v) scaled into
    [0, 1], optionally without the triangles whose centre lies in a disc hole = (cx, cy, r)."""
    y, x = np.mgrid[0:n, 0:n] / (n - 1)
    rest = np.stack([x.ravel() * stretch[0], y.ravel() * stretch[1], np.zeros(n * n)], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    uv = np.stack([x.ravel(), y.ravel()], axis=1)
    if hole is not None:
        centre = uv[faces].mean(axis=1)
        faces = faces[np.hypot(centre[:, 0] - hole[0], centre[:, 1] - hole[1]) > hole[2]]
    return rest, faces, uv[faces]


def test_uv_scales_are_the_stretch_of_the_layout():
    rest, faces, corner_uv = _grid(stretch=(3.0, 0.5))
    s = uv_scales(rest, faces, corner_uv)
    assert np.allclose(s, [3.0, 0.5])


def test_template_lies_inside_its_region_away_from_a_hole_sized_on_the_surface():
    rest, faces, corner_uv = _grid(hole=(0.5, 0.5, 0.12), stretch=(2.0, 1.0))
    # the region moves most at the hole's rim (as lips round the mouth), fading out by 0.35
    r = np.hypot(rest[:, 0] / 2.0 - 0.5, rest[:, 1] - 0.5)
    disp = np.zeros((1, len(rest), 3))
    disp[0, :, 2] = np.clip(1.0 - (r - 0.12) / 0.25, 0.0, 1.0)
    (o,) = region_layout(rest, faces, corner_uv, disp, share=0.25, resolution=256)
    u0, v0, u1, v1 = o["template"]
    pts = template_points(o["template"], 16).reshape(-1, 2)
    assert (locate_uv(pts, corner_uv)[0] >= 0).all()  # on the surface, not over the hole
    assert (np.hypot(pts[:, 0] - 0.5, pts[:, 1] - 0.5) > 0.12).all()
    # within the moving ring (displacement ≥ share of the largest: r ≤ 0.12 + 0.75 · 0.25)
    assert (np.hypot(pts[:, 0] - 0.5, pts[:, 1] - 0.5) < 0.12 + 0.75 * 0.25 + 1e-9).all()
    # its sides in surface units are the layout's half-sizes: the UV rectangle undoes the 2 : 1 stretch
    assert np.allclose([(u1 - u0) * 2.0, v1 - v0], 2 * np.asarray(o["half"]), rtol=0.05)
    assert min(o["half"]) > 0.015  # not a degenerate sliver


def test_test_footage_light_follows_lamberts_law():
    """The footage's light: ambient plus the cosine towards a distant light, nothing from the light
    where a surface faces away from it (its attached shadow); the two-sided variant that reproduces
    the older footage lights both sides alike."""
    import numpy as np

    from facepipe.appearance_sample import make_scene, other_light

    rest = np.random.default_rng(0).uniform(-5, 5, (200, 3))
    scene = make_scene(rest, 64)
    angles = np.linspace(0.0, np.pi, 7)
    # normals in the plane of the light and an axis across it, at 0..180° from the light
    across = np.cross(scene.light, [0.0, 1.0, 0.0])
    across /= np.linalg.norm(across)
    normals = np.cos(angles)[:, None] * scene.light + np.sin(angles)[:, None] * across
    expected = scene.ambient + (1 - scene.ambient) * np.clip(np.cos(angles), 0, None)
    np.testing.assert_allclose(scene.shading(normals), expected, atol=1e-12)
    np.testing.assert_allclose(scene.shading(normals[angles >= np.pi / 2]), scene.ambient, atol=1e-12)
    both = make_scene(rest, 64, two_sided=True)
    np.testing.assert_allclose(both.shading(normals), both.shading(-normals), atol=1e-12)
    assert other_light(both).two_sided and not other_light(scene).two_sided
