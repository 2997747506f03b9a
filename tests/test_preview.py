"""The software renderer (coverage, z-buffer, Lambert), preview images, the fit plot, the export bench."""

from __future__ import annotations

import json

import matplotlib.image
import numpy as np
import pytest

from facepipe.errors import InputError
from facepipe.cli.preview import pick_frames, plot_fit_curves
from facepipe.core.render import Camera, frame_camera, rasterize, render
from tests.conftest import run_cli as run

PNG = b"\x89PNG\r\n\x1a\n"


def square(z=0.0, size=1.0, center=(0.0, 0.0)):
    cx, cy = center
    h = size / 2
    V = np.array([[cx - h, cy - h, z], [cx + h, cy - h, z], [cx + h, cy + h, z], [cx - h, cy + h, z]])
    return V, np.array([[0, 1, 2], [0, 2, 3]])


def front_camera(width=100, height=100, scale=50.0):
    return Camera(np.eye(3), np.zeros(2), scale, width, height)


def test_coverage_is_the_projected_area():
    V, F = square(size=1.0)
    cam = front_camera(scale=40.0)
    pix, depth = cam.project(V)
    face, bary = rasterize(pix, depth, F, cam.width, cam.height)
    # a 1 × 1 square at 40 px per unit covers 40 × 40 pixel centres, no holes on the diagonal
    assert (face >= 0).sum() == 40 * 40
    np.testing.assert_allclose(bary[face >= 0].sum(axis=1), 1.0)
    assert set(np.unique(face)) == {-1, 0, 1}


def test_z_buffer_keeps_the_nearest_surface_whatever_the_order():
    Va, Fa = square(z=0.0, size=1.0)
    Vb, Fb = square(z=0.5, size=1.0, center=(0.5, 0.0))  # nearer (+z to the viewer), overlapping
    cam = front_camera()
    for order in (0, 1):
        parts = [(Va, Fa), (Vb, Fb)] if order == 0 else [(Vb, Fb), (Va, Fa)]
        V = np.concatenate([parts[0][0], parts[1][0]])
        F = np.concatenate([parts[0][1], parts[1][1] + 4])
        colors = np.concatenate([np.tile([1.0, 0, 0], (4, 1)), np.tile([0, 0, 1.0], (4, 1))])
        nearer_is_blue = (order == 0)
        img = render(V, F, cam, colors=colors, ambient=1.0)  # ambient 1: flat colours
        # pixel at x = 0.25 (inside both squares)
        col = int(round(0.25 * 50 + 50 - 0.5))
        rgb = img[50, col]
        assert (rgb[2] == 1.0) == nearer_is_blue and (rgb[0] == 1.0) != nearer_is_blue


def test_lambert_shading_of_a_plane():
    V, F = square(size=1.0)
    cam = front_camera()
    light = np.array([0.0, 0.6, 0.8])
    img = render(V, F, cam, light=light, ambient=0.2)
    inside = img[50, 50]
    # normal +z, n·l = 0.8: grey 0.82 × (0.2 + 0.8 × 0.8)
    np.testing.assert_allclose(inside, 0.82 * (0.2 + 0.8 * 0.8))
    np.testing.assert_allclose(img[2, 2], 1.0)  # background


def test_frame_camera_frames_the_points():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(200, 3)) * [3, 5, 1]
    cam = frame_camera(pts, forward=[0, 0, 1], width=300)
    pix, _ = cam.project(pts)
    assert pix[:, 0].min() >= 0 and pix[:, 0].max() <= 299
    assert pix[:, 1].min() >= 0 and pix[:, 1].max() <= cam.height - 1
    # up in the world is up in the image (smaller row)
    top, bottom = cam.project(np.array([[0, 4.0, 0], [0, -4.0, 0]]))[0][:, 1]
    assert top < bottom


def test_pick_frames():
    rest = np.zeros((3, 3))
    head = np.zeros((5, 3, 3))
    head[3] += 1.0
    assert pick_frames(head, rest).tolist() == [3]
    assert pick_frames(head, rest, 3).tolist() == [0, 2, 4]


def test_preview_with_truth_and_strip(rig, tmp_path, capsys):
    out = tmp_path / "p.png"
    assert run("preview", rig.replays["wpsd"], "-o", out, "--truth", rig.truth, "--strip", "2", "--size", "120") == 0
    assert out.read_bytes()[:8] == PNG
    img = matplotlib.image.imread(out)
    assert img.shape[0] > 2 * 60 and img.shape[1] > 5 * 120 * 0.95  # two rows, five panels
    said = capsys.readouterr().out
    assert "frame 10; RMS vs truth: final" in said and "frame 15" in said
    # not overwritten without --force; bad names and frames are input errors
    assert run("preview", rig.replays["wpsd"], "-o", out) == 2
    assert run("preview", rig.replays["wpsd"], "-o", out, "--force", "--frame", "12", "--size", "64", "-q") == 0
    assert run("preview", rig.replays["wpsd"], "-o", tmp_path / "p.mp4") == 2
    assert "video is not supported" in capsys.readouterr().err
    assert run("preview", rig.replays["wpsd"], "-o", tmp_path / "q.png", "--frame", "99") == 2
    assert "no frame 99" in capsys.readouterr().err
    assert run("preview", rig.replays["wpsd"], "-o", tmp_path / "q.png", "--truth", tmp_path / "none.npz") == 2


def test_preview_errors_match_the_truth(rig):
    """The heat maps' figures are the vertex distances between the replay and the truth."""
    from facepipe.io.model_file import load_model
    from facepipe.cli.preview import render_preview
    from facepipe.io.replay_folder import ReplayDir

    r = ReplayDir(rig.replays["psd"])
    s = render_preview(r, load_model(rig.models["psd"]), rig.root / "psd.png", truth_path=rig.truth,
                       frame_numbers=[13], size=64, force=True)
    pos = np.load(rig.replays["psd"] / "positions.npy")[3].astype(np.float64)
    truth = np.load(rig.truth)["positions"][3].astype(np.float64)
    large = np.load(rig.replays["psd"] / "large_scale.npy")[3].astype(np.float64)
    assert s["frames"] == [13]
    assert s["rms"]["final"][0] == pytest.approx(np.sqrt(((pos - truth) ** 2).sum(1).mean()), rel=1e-5)
    assert s["rms"]["large"][0] == pytest.approx(np.sqrt(((large - truth) ** 2).sum(1).mean()), rel=1e-5)


def test_preview_without_large_scale_evaluates_it(rig, tmp_path):
    import shutil

    r = tmp_path / "r"
    shutil.copytree(rig.replays["wpsd"], r)
    (r / "large_scale.npy").unlink()
    assert run("preview", r, "-o", tmp_path / "a.png", "--size", "64", "-q") == 0


def test_fit_plot(tmp_path):
    report = {"curves": {"psd": [{"poses": i, "mean_rms": 0.1 / (i + 1), "max_rms": 0.2 / (i + 1)} for i in range(5)],
                         "wpsd": [{"poses": i, "mean_rms": 0.05 / (i + 1), "max_rms": 0.1 / (i + 1)}
                                  for i in range(5)]},
              "large_scale_rms": {"mean": 0.12, "max": 0.3}}
    path = plot_fit_curves(report, tmp_path / "fit.png", units="cm")
    assert path.read_bytes()[:8] == PNG
    with pytest.raises(InputError):
        plot_fit_curves(report, tmp_path / "fit.txt")


def test_fit_command_writes_its_plot(rig, tmp_path):
    assert run("fit", rig.root / "rig" / "sample.toml", "-o", tmp_path / "fit.npz", "-q") == 0
    assert (tmp_path / "fit.png").read_bytes()[:8] == PNG
    assert set(json.loads((tmp_path / "fit.json").read_text())["curves"]) == {"psd", "wpsd"}


def test_export_bench_figures(tmp_path):
    from bench.export_speed import run_export_bench
    from facepipe.io.mesh_write import save_obj
    from tests.test_export import rig_mesh

    save_obj(tmp_path / "m.obj", rig_mesh())
    r = run_export_bench(tmp_path / "w", mesh_path=tmp_path / "m.obj", n_frames=2, repeats=1, resolution=32,
                         prefer_ict=False, log=lambda s: None)
    for name in ("obj", "obj_trimesh", "mdd", "pc2", "usd", "exr_half_32", "exr_float_32"):
        assert r[name]["bytes"] > 0 and r[name]["megabytes_per_second"] > 0
    assert r["mdd"]["bytes"] == 8 + 2 * 4 + 2 * 20 * 12 and r["pc2"]["bytes"] == 32 + 2 * 20 * 12
    assert r["obj_vs_trimesh"] > 0 and not r["mesh"]["ict"]


def test_appearance_reconstruction_is_put_over_the_input_frame():
    """The classified take's preview draws the layered texture over the frame: the frame where no
    face is drawn, the face where it covers the pixel, the two blended through its silhouette."""
    from facepipe.cli.appearance_preview import over_footage

    frame = np.random.default_rng(0).uniform(size=(4, 5, 3)).astype(np.float32)
    face = np.full((4, 5, 3), 0.6, dtype=np.float32)
    coverage = np.zeros((4, 5, 3), dtype=np.float32)
    coverage[1:3, 1:4] = 1.0
    coverage[0, 0] = 0.25  # a silhouette pixel, a quarter covered
    out = over_footage(face * coverage, coverage, frame)
    np.testing.assert_array_equal(out[3], frame[3])
    np.testing.assert_allclose(out[1:3, 1:4], 0.6)
    np.testing.assert_allclose(out[0, 0], 0.25 * 0.6 + 0.75 * frame[0, 0], rtol=1e-6)
    np.testing.assert_array_equal(over_footage(face * coverage, coverage, None)[3], 1.0)  # no frame: white
