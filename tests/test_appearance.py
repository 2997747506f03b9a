"""Appearance from footage end to end on the rendered sample rig, the footage reader and bad input."""

import json
import re
import shutil

import imageio.v3 as iio
import numpy as np
import pytest
from scipy.stats import spearmanr

from facepipe.cli.commands import main
from facepipe.errors import InputError
from facepipe.io.footage import frames_at, open_footage, read_frames

pytestmark = pytest.mark.slow


def _run(*args):
    with pytest.raises(SystemExit) as exc:
        main([str(a) for a in args])
    return exc.value.code


@pytest.fixture(scope="module")
def kit(tmp_path_factory):
    d = tmp_path_factory.mktemp("appearance")
    # 10 examples: the 8 regions' drivers and two other expressions, the rest frames
    assert _run("sample", d, "--vertices", 4000, "--frames", 40, "--examples", 10, "--appearance", "-q") == 0
    assert _run("appearance", "build", d / "appearance" / "appearance.toml", "-o", d / "app.npz", "-q") == 0
    return d


def _q_and_truth(kit, take):
    out = kit / f"cls_{take}"
    assert _run("appearance", "classify", kit / "app.npz", kit / "appearance" / take / "frame_%04d.png",
                "--geometry", kit / "appearance" / f"{take}.npz", "-o", out, "-q") == 0
    q = np.loadtxt(out / "appearance.csv", delimiter=",", skiprows=1)[:, 2:]
    truth = np.loadtxt(kit / "appearance" / f"{take}_truth.csv", delimiter=",", skiprows=1)[:, 1:]
    return q, truth


def test_q_follows_the_truth_activation(kit):
    q, truth = _q_and_truth(kit, "take")
    rho = [spearmanr(q[:, r], truth[:, r]).statistic for r in range(q.shape[1])]
    # most regions track their activation closely from the images alone
    assert np.median(rho) > 0.9, rho
    assert (q >= 0).all() and (q <= 4).all()


def test_head_turned_and_another_light(kit):
    q, truth = _q_and_truth(kit, "take_turned")
    rho = [spearmanr(q[:, r], truth[:, r]).statistic for r in range(q.shape[1])]
    assert np.nanmedian(rho) > 0.8, rho


def test_missing_frame_is_skipped_and_wrong_size_refused(kit, tmp_path):
    frames = tmp_path / "frames"
    shutil.copytree(kit / "appearance" / "take", frames)
    (frames / "frame_0005.png").unlink()
    (frames / "frame_0006.png").write_bytes(b"not a png")
    out = tmp_path / "cls"
    assert _run("appearance", "classify", kit / "app.npz", frames, "--geometry", kit / "appearance" / "take.npz",
                "-o", out, "-q") == 0
    assert '"frame": 5' in (out / "appearance.json").read_text()
    assert '"frame": 6' in (out / "appearance.json").read_text()
    # the skipped frames hold the light of the frame before them: a texture for every frame
    light = np.loadtxt(out / "light.csv", delimiter=",", skiprows=1)
    row = {int(n): k for k, n in enumerate(light[:, 0])}
    np.testing.assert_array_equal(light[row[5], 2:], light[row[4], 2:])
    np.testing.assert_array_equal(light[row[6], 2:], light[row[4], 2:])
    assert np.isfinite(light).all() and not np.array_equal(light[row[7], 2:], light[row[4], 2:])
    img = iio.imread(frames / "frame_0007.png")
    iio.imwrite(frames / "frame_0007.png", img[:-2])
    assert _run("appearance", "classify", kit / "app.npz", frames, "--geometry", kit / "appearance" / "take.npz",
                "-o", out, "-q") == 2


def _edited_config(kit, tmp_path, old, new):
    src = kit / "appearance"
    dst = tmp_path / "appearance"
    shutil.copytree(src, dst)
    cfg = dst / "appearance.toml"
    text = cfg.read_text().replace("../neutral.obj", str(kit / "neutral.obj")).replace("../markers.csv",
                                                                                      str(kit / "markers.csv"))
    assert old in text
    cfg.write_text(text.replace(old, new, 1))
    return cfg


@pytest.mark.parametrize("old,new,message", [
    ("frames = [0, 1, 2, 3, 4]", "frames = [0, 1]", "at least three layers"),
    ("template = [", "template = [0.98, 0.98, 1.2, 1.2] #", "outside the UV layout"),
    ("texture_size = 512", "texture_size = 512.0", "expected an integer"),
    ("rest_frames = [", "rest_frames = [1.5, ", "expected an integer"),
    ("rest_frames = [", "rest_frames = [999, ", "example frame 999"),
    # a card across a hole: the sample face has none its groups rim; a card's template is in its square
    ("frames = [0, 1, 2, 3, 4]", "frames = [0, 1, 2, 3, 4]\ncard = true", "rim"),
    ("template = [", "card = true\ntemplate = [0.5, 0.5, 1.5, 1.5] #", "card's own square"),
    ("frames = [0, 1, 2, 3, 4]", "frames = [0, 1, 2, 3, 4]\ncard = 1", "expected"),
    ("texture_size = 512", 'texture_size = 512\nshading_surface = "cubic"', "not one of auto, plane, quadratic"),
    ("frames = [0, 1, 2, 3, 4]", 'frames = [0, 1, 2, 3, 4]\nshading_surface = "flat"', "shading_surface"),
    ("texture_size = 512", 'texture_size = 512\npeak_interpolation = "cubic"', "not one of segment, parabola"),
    ("texture_size = 512", 'texture_size = 512\nshading_reference = "mean"', "not one of neutral, patch"),
    ("texture_size = 512", 'texture_size = 512\nlight_model = "sh4"', "not one of point, sh9"),
    ("texture_size = 512", "texture_size = 512\nunseen_margin = -1.0", "unseen_margin = -1.0 is not in [0, 8)"),
    ("camera_rotation = [", "camera_rotation = 2 #", "camera_rotation must be 3 × 3 numbers"),  # (was a TypeError)
    ("texture_size = 512", "texture_size = 512\nmin_event = -0.1", "min_event and scale_weights must be ≥ 0"),
    ("texture_size = 512", "texture_size = 512\nrest_explain = 1.5", "rest_explain = 1.5 is not in [0, 1] layers"),
    ("texture_size = 512", "texture_size = 512\nrest_path_tolerance = -1.0", "rest_path_tolerance = -1.0 is not"),
    ("texture_size = 512", "texture_size = 512\nrest_path_tolerance = inf", "rest_path_tolerance = inf is not"),
    ("texture_size = 512", 'texture_size = 512\nrest_explain = "high"', "expected"),
])
def test_bad_config(kit, tmp_path, capsys, old, new, message):
    cfg = _edited_config(kit, tmp_path, old, new)
    assert _run("appearance", "build", cfg, "-o", tmp_path / "x.npz", "-q") == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()


def test_never_visible_region_is_reported_and_neutral(kit, tmp_path, capsys):
    # the whole take seen from behind: every region faces away, keeps neutral, and says so
    geo = np.load(kit / "appearance" / "take.npz")
    pos = geo["positions"].copy()
    centre = pos[0].mean(axis=0)
    pos = (pos - centre) * np.array([-1.0, 1.0, -1.0]) + centre  # turned 180° about the vertical
    np.savez(tmp_path / "behind.npz", positions=pos, frame=geo["frame"])
    assert _run("appearance", "classify", kit / "app.npz", kit / "appearance" / "take",
                "--geometry", tmp_path / "behind.npz", "-o", tmp_path / "cls") == 0
    assert "never visible" in capsys.readouterr().out
    q = np.loadtxt(tmp_path / "cls" / "appearance.csv", delimiter=",", skiprows=1)[:, 2:]
    assert (q == 0).all()


def test_regions_hidden_in_some_frames_are_named_with_their_frames(kit, tmp_path, capsys):
    # frames 5-8 of the take seen from behind: every region hidden there, named with the span
    geo = np.load(kit / "appearance" / "take.npz")
    pos = geo["positions"].copy()
    centre = pos[0].mean(axis=0)
    pos[5:9] = (pos[5:9] - centre) * np.array([-1.0, 1.0, -1.0]) + centre
    np.savez(tmp_path / "partly_behind.npz", positions=pos, frame=geo["frame"])
    assert _run("appearance", "classify", kit / "app.npz", kit / "appearance" / "take",
                "--geometry", tmp_path / "partly_behind.npz", "-o", tmp_path / "cls") == 0
    out = capsys.readouterr().out
    first, last = int(geo["frame"][5]), int(geo["frame"][8])
    assert "hidden in some frames" in out and f"forehead 4 (frames {first}–{last})" in out, out
    report = json.loads((tmp_path / "cls" / "appearance.json").read_text())
    assert set(report["hidden_frames"].values()) == {4}


def test_brief_readings_at_rest_are_counted_and_kept_with_min_event_0(kit, tmp_path, capsys):
    with np.load(kit / "app.npz") as d:
        keep_all = {k: d[k] for k in d.files}
    keep_all["settings"] = np.r_[keep_all["settings"][:7], 0.0]
    np.savez(tmp_path / "keep_all.npz", **keep_all)
    # the take's footage with a burst of image noise on two frames: a brief reading on regions at rest
    footage = tmp_path / "take"
    shutil.copytree(kit / "appearance" / "take", footage)
    rng = np.random.default_rng(5)
    for path in sorted(footage.glob("*.png"))[1:3]:  # frames 0-3: most regions at rest
        image = iio.imread(path).astype(np.float64)
        iio.imwrite(path, np.clip(image + rng.normal(0, 12.0, image.shape), 0, 255).astype(np.uint8))
    streams = {}
    for name, model in (("default", kit / "app.npz"), ("keep_all", tmp_path / "keep_all.npz")):
        assert _run("appearance", "classify", model, footage,
                    "--geometry", kit / "appearance" / "take.npz", "-o", tmp_path / name) == 0
        streams[name] = np.loadtxt(tmp_path / name / "appearance.csv", delimiter=",", skiprows=1)[:, 2:]
    out = capsys.readouterr().out
    counts = json.loads((tmp_path / "default" / "appearance.json").read_text())["brief_readings_at_rest"]
    dropped = streams["default"] != streams["keep_all"]
    # only readings above rest, under a layer, go back to rest, and the report counts exactly those
    assert (streams["default"][dropped] == 0).all() and (streams["keep_all"][dropped] < 1).all()
    assert list(counts.values()) == dropped.sum(axis=0).tolist()
    assert dropped.any() and "set back to rest" in out
    assert "brief_readings_at_rest" in json.loads((tmp_path / "keep_all" / "appearance.json").read_text())
    print("brief readings", counts)


def test_a_hidden_stretch_holds_the_last_reading_seen_well(kit):
    """The face slides out of the image over the take: each region's template leaves the frame by
    degrees. Each hidden frame holds the reading of the last frame with at least WELL_SEEN of its
    stable points in view, decaying from that frame's time — not the last, partial, reading."""
    from facepipe.io.appearance_file import load_appearance
    from facepipe.pipeline.appearance import WELL_SEEN, classify_frames

    model = load_appearance(kit / "app.npz")
    geo = np.load(kit / "appearance" / "take.npz")
    pos, numbers = geo["positions"].astype(np.float64), geo["frame"]
    depth = float((model.to_camera(pos[:1])[..., 2]).mean())
    across = 1.3 * model.camera.width / model.camera.matrix[0, 0] * depth  # the image's width, and more
    shift = np.linspace(0.0, across, len(pos))[:, None, None] * model.rotation[0]  # the camera's x, in the world
    times = numbers / 30.0
    result = classify_frames(model, kit / "appearance" / "take", pos + shift, numbers, times)
    checked = 0
    for r in range(len(model.names)):
        hidden = np.flatnonzero(~result.visible[:, r])
        well = np.flatnonzero(result.visible[:, r] & (result.in_view[:, r] >= WELL_SEEN))
        for f in hidden:
            before = well[well < f]
            if not len(before):
                continue
            g = before[-1]
            expected = 0.0 if result.brief[f, r] else result.raw[g, r] * np.exp(-(times[f] - times[g]) / model.decay)
            assert result.q[f, r] == pytest.approx(expected, abs=1e-12), (model.names[r], f, g)
            # the frames seen after g, only in part, are not what it holds
            checked += bool(result.visible[g + 1:f, r].any())
    assert checked > 0 and (~result.visible[-1]).all()  # partly seen frames, then out of view


def test_offsets_within():
    from facepipe.core.runs import offsets_within

    lengths = np.array([2, 0, 3, 1])
    expected = np.concatenate([np.arange(n) for n in lengths])
    assert offsets_within(lengths).tolist() == expected.tolist() == [0, 1, 0, 1, 2, 0]
    assert offsets_within(np.zeros(0, dtype=int)).size == 0


def test_column_runs():
    from facepipe.core.runs import column_runs

    mask = np.array([[1, 0], [1, 1], [0, 1], [1, 0]], dtype=bool)
    column, start, stop = column_runs(mask)
    assert column.tolist() == [0, 0, 1] and start.tolist() == [0, 3, 1] and stop.tolist() == [2, 4, 3]
    assert [a.tolist() for a in column_runs(mask[:, 0])] == [[0, 0], [0, 3], [2, 4]]
    assert all(len(a) == 0 for a in column_runs(np.zeros((5, 2), dtype=bool)))


def test_footage_patterns_folders_and_video(tmp_path):
    rng = np.random.default_rng(0)
    imgs = [(rng.uniform(size=(32, 48, 3)) * 255).astype(np.uint8) for _ in range(3)]
    for i, im in zip([3, 4, 10], imgs):
        iio.imwrite(tmp_path / f"shot_{i:04d}.png", im)
    fp = open_footage(tmp_path / "shot_%04d.png")
    assert fp.numbers.tolist() == [3, 4, 10]
    assert open_footage(tmp_path).numbers.tolist() == [3, 4, 10]
    got = list(read_frames(fp, [4, 5]))
    assert got[0][1].shape == (32, 48, 3) and abs(got[0][1][0, 0, 0] - imgs[1][0, 0, 0] / 255) < 1e-6
    assert got[1][1] is None and "no image" in got[1][2]
    video = tmp_path / "clip.mp4"
    iio.imwrite(video, np.stack([np.full((32, 48, 3), v, np.uint8) for v in (40, 120, 200)]), fps=30)
    fv = open_footage(video)
    assert len(fv) == 3
    frames = list(read_frames(fv))
    assert [round(float(f[1].mean()) * 255 / 40) for f in frames] == [1, 3, 5]
    with pytest.raises(InputError):
        open_footage(tmp_path / "nothing_%04d.png")
    with pytest.raises(InputError):
        open_footage(tmp_path / "missing.mp4")
    # a take numbered from 1 with its own times (a tracker's) finds the video's frames by time
    assert fv.fps == pytest.approx(30.0)
    at, note = frames_at(fv, np.array([1, 2, 3]), np.array([0.0, 1 / 30, 2 / 30]))
    assert at.tolist() == [0, 1, 2] and "by time" in note
    assert frames_at(fv, np.array([1, 2]), None)[0].tolist() == [1, 2]  # no times: by number
    assert frames_at(fp, np.array([3, 4]), np.array([0.0, 0.1]))[0].tolist() == [3, 4]  # images: by number
    # images the take's numbers miss (a tracker counted them from 1): the images in order, by time
    at, note = frames_at(fp, np.array([1, 2, 3]), np.array([0.0, 1 / 30, 2 / 30]))
    assert at.tolist() == [3, 4, 10] and "images in order" in note
    assert frames_at(fp, np.array([7, 8]), np.array([5.0, 5.1]))[0].tolist() == [7, 8]  # times past them: by number


def test_video_frames_are_decoded_as_a_stream(tmp_path, monkeypatch):
    """A video is read one frame at a time (a long HD take does not fit in memory whole): the first
    wanted frame comes before the rest are decoded; frames asked for out of order, again, past
    the end or before the start come right; the decoder is closed when the caller stops early."""
    import facepipe.io.footage as footage_module

    video = tmp_path / "clip.mp4"
    iio.imwrite(video, np.stack([np.full((16, 16, 3), 10 + 20 * v, np.uint8) for v in range(10)]), fps=30)
    fv = open_footage(video)
    decoded, closed = [], []
    real = footage_module.iio.imiter

    def counting(path):
        try:
            for image in real(path):
                decoded.append(1)
                yield image
        finally:
            closed.append(1)

    monkeypatch.setattr(footage_module.iio, "imiter", counting)
    frames = read_frames(fv, [1, 4, 4, 2, 12, -1, 9])
    assert next(frames)[0] == 1 and len(decoded) == 2  # frames 0 and 1, no more
    got = [(n, None if image is None else round(float(image.mean()) * 255 / 10), problem)
           for n, image, problem in frames]
    assert [(n, level) for n, level, _ in got] == [(4, 9), (4, 9), (2, 5), (12, None), (-1, None), (9, 19)]
    assert "beyond the end" in got[3][2] and "before the start" in got[4][2]
    frames = read_frames(fv, [0, 5])
    next(frames)
    frames.close()  # the caller stops early: the decoder goes with it
    assert len(closed) == 3  # the first pass (left for frame 2), the second (run out at 12), this one


def test_grey_and_grey_alpha_images_read_as_rgb(tmp_path):
    grey = (np.arange(12 * 8).reshape(12, 8) % 256).astype(np.uint8)
    iio.imwrite(tmp_path / "frame_0001.png", grey)
    iio.imwrite(tmp_path / "frame_0002.png", np.stack([grey, np.full_like(grey, 255)], axis=-1))
    frames = list(read_frames(open_footage(tmp_path / "frame_%04d.png")))
    for _, image, problem in frames:
        assert problem is None and image.shape == (12, 8, 3)
        np.testing.assert_allclose(image[..., 1], grey / 255.0, atol=1e-6)


def test_sixteen_bit_tiff_sequences_read_scaled(tmp_path, recwarn):
    """16-bit TIFF plates (common in film) read as floats in [0, 1], through the tifffile package
    (imageio's own TIFF reader is deprecated: no warning of it)."""
    plate = (np.arange(10 * 12 * 3).reshape(10, 12, 3) * 613 % 65536).astype(np.uint16)
    iio.imwrite(tmp_path / "plate.0007.tif", plate)
    (number, image, problem), = read_frames(open_footage(tmp_path))
    assert number == 7 and problem is None
    np.testing.assert_allclose(image, plate / 65535.0, atol=1e-6)
    assert not [w for w in recwarn if "tifffile" in str(w.message)]


def test_examples_from_a_video_and_a_geometry_numbered_from_1(kit, tmp_path):
    """Example footage as a video and example geometry numbered from 1 with its own times (a
    tracker's replay): the same model as with the geometry numbered from 0."""
    from facepipe.io.appearance_file import load_appearance

    examples = kit / "appearance" / "examples"
    frames = [iio.imread(p) for p in sorted(examples.glob("frame_*.png"))]
    iio.imwrite(tmp_path / "examples.mp4", np.stack(frames), fps=30)
    with np.load(kit / "appearance" / "examples.npz") as geometry:
        positions, numbers = geometry["positions"], geometry["frame"]
    assert numbers.tolist() == list(range(len(frames)))
    np.savez(tmp_path / "from1.npz", positions=positions, frame=numbers + 1, time=numbers / 30.0)
    models = {}
    for name, geometry, shift in (("from0", kit / "appearance" / "examples.npz", 0), ("from1", tmp_path / "from1.npz", 1)):
        cfg = _edited_config(kit, tmp_path / name, 'footage = "examples/frame_%04d.png"',
                             f'footage = "{tmp_path / "examples.mp4"}"')
        text = cfg.read_text().replace('geometry = "examples.npz"', f'geometry = "{geometry}"')
        if shift:  # the config names the example frames by the geometry's numbers
            text = re.sub(r"(frames|rest_frames) = \[([0-9, ]*)\]",
                          lambda m: f"{m.group(1)} = [{', '.join(str(int(v) + 1) for v in m.group(2).split(','))}]",
                          text)
            text = text.replace("neutral_frame = 0", "neutral_frame = 1")
        cfg.write_text(text)
        assert _run("appearance", "build", cfg, "-o", tmp_path / f"{name}.npz", "-q") == 0
        models[name] = load_appearance(tmp_path / f"{name}.npz")
    a, b = models["from0"], models["from1"]
    assert all(np.array_equal(x, y) for x, y in zip(a.templates, b.templates))
    assert all(np.array_equal(x, y) for x, y in zip(a.volumes, b.volumes))


def test_video_footage_and_a_take_numbered_from_1_classify_as_from_0(kit, tmp_path, capsys):
    """The footage as a video (frames from 0) and the geometry of a take numbered from 1 with its
    own times, as a tracker's replay is: the same Q as the take numbered from 0 (by number)."""
    frames = [iio.imread(p) for p in sorted((kit / "appearance" / "take").glob("frame_*.png"))]
    video = tmp_path / "take.mp4"
    iio.imwrite(video, np.stack(frames), fps=30)
    with np.load(kit / "appearance" / "take.npz") as geometry:
        positions, numbers = geometry["positions"], geometry["frame"]
    np.savez(tmp_path / "from0.npz", positions=positions, frame=numbers)
    np.savez(tmp_path / "from1.npz", positions=positions, frame=numbers + 1, time=numbers / 30.0)
    q = {}
    for name in ("from0", "from1"):
        assert _run("appearance", "classify", kit / "app.npz", video, "--geometry", tmp_path / f"{name}.npz",
                    "-o", tmp_path / name) == 0
        q[name] = np.loadtxt(tmp_path / name / "appearance.csv", delimiter=",", skiprows=1)
    out = capsys.readouterr().out
    assert "matched to the take's by time" in out and "skipped" not in out
    assert np.array_equal(q["from1"][:, 0], numbers + 1) and np.array_equal(q["from0"][:, 2:], q["from1"][:, 2:])
    assert q["from0"][:, 2:].max() > 1.0  # (the take is active)
    # the preview shows the last frame's own image (video frame 39, not a 40th there is not)
    last = int(numbers[-1]) + 1
    assert _run("preview", tmp_path / "from1", "-o", tmp_path / "p.png", "--frame", last) == 0
    out = capsys.readouterr().out
    assert f"frame {last}; Q" in out and "no input image" not in out


def _classified(kit):
    out = kit / "cls_take"
    if not (out / "appearance.csv").is_file():
        _q_and_truth(kit, "take")
    return out


def test_min_event_is_kept_in_the_model_and_older_models_keep_every_reading(kit, tmp_path):
    from facepipe.io.appearance_file import load_appearance

    model = load_appearance(kit / "app.npz")
    assert model.min_event == pytest.approx(0.07)  # the config's default, as built
    with np.load(kit / "app.npz") as d:
        older = {k: d[k] for k in d.files}
    older["settings"] = older["settings"][:7]  # a model written before min_event
    np.savez(tmp_path / "older.npz", **older)
    assert load_appearance(tmp_path / "older.npz").min_event == 0.0
    older["settings"] = np.r_[older["settings"], np.nan]
    np.savez(tmp_path / "bad.npz", **older)
    with pytest.raises(InputError, match="min_event nan is not a duration"):
        load_appearance(tmp_path / "bad.npz")


def test_a_2d_takes_replay_is_classified_through_its_camera(kit, tmp_path, capsys):
    """The take's geometry as a 2D take's replay writes it (camera coordinates, replay.json says
    so) reads the same Q as the take in world space through the model's camera transform."""
    from facepipe.io.appearance_file import load_appearance

    model = load_appearance(kit / "app.npz")
    with np.load(kit / "appearance" / "take.npz") as geometry:
        world, frames = geometry["positions"], geometry["frame"]
    replay = tmp_path / "replay"
    replay.mkdir()
    np.save(replay / "positions.npy", (world @ model.rotation.T + model.translation).astype(np.float32))
    (replay / "replay.json").write_text(json.dumps({"frame_numbers": frames.tolist(), "times": (frames / 30).tolist(),
                                                    "coordinates": "camera (OpenCV axes, rig units)"}))
    out = tmp_path / "cls"
    assert _run("appearance", "classify", kit / "app.npz", kit / "appearance" / "take" / "frame_%04d.png",
                "--geometry", replay, "-o", out) == 0
    assert "classified through that camera" in capsys.readouterr().out
    q_camera = np.loadtxt(out / "appearance.csv", delimiter=",", skiprows=1)[:, 2:]
    q_world = np.loadtxt(_classified(kit) / "appearance.csv", delimiter=",", skiprows=1)[:, 2:]
    assert np.abs(q_camera - q_world).max() < 0.02  # (the positions rounded to float32)
    # as a replay in the model's world space (no coordinates said) it would be through the model's transform
    assert np.abs(q_world).max() > 1.0
    # example geometry in camera coordinates moved again by the config's camera pose: refused
    cfg = _edited_config(kit, tmp_path / "build", 'geometry = "examples.npz"', f'geometry = "{replay}"')
    assert _run("appearance", "build", cfg, "-o", tmp_path / "m.npz") == 2
    assert "already in its camera's coordinates" in capsys.readouterr().err
    assert not (tmp_path / "m.npz").exists()


def test_one_camera_gives_geometry_and_appearance(kit, tmp_path):
    """Fidaleo et al.'s monocular take end to end: landmarks tracked in the footage (the truth's
    projected through the kit's camera, 0.3 px noise) replayed as a 2D take, and the same
    footage classified with that replay's geometry: Q tracks the truth activation about as well
    as with the truth geometry."""
    import tomllib

    from facepipe.core.camera import project_distorted
    from facepipe.io.camera_file import read_camera
    from tests.test_video import _openface_text

    app = kit / "appearance"
    config = tomllib.loads((app / "appearance.toml").read_text())["appearance"]
    R, t = np.array(config["camera_rotation"]), np.array(config["camera_translation"])
    camera = read_camera(app / "camera.json")
    with np.load(app / "take.npz") as geometry:
        world, frames = geometry["positions"], geometry["frame"]
    front = np.flatnonzero(world[0, :, 2] > np.percentile(world[0, :, 2], 60))
    vertices = front[np.linspace(0, len(front) - 1, 68).astype(int)]
    (tmp_path / "landmarks.csv").write_text("name,vertex\n" + "".join(f"{i},{v}\n" for i, v in enumerate(vertices)))
    pixels = project_distorted(camera, world[:, vertices] @ R.T + t)
    pixels += np.random.default_rng(0).normal(scale=0.3, size=pixels.shape)
    (tmp_path / "tracked.csv").write_text(_openface_text(frames, frames / 30.0, pixels))
    assert _run("bake", kit / "sample.toml", "--no-tune", "-o", tmp_path / "model.npz", "-q") == 0
    assert _run("replay", tmp_path / "tracked.csv", "-m", tmp_path / "model.npz", "--camera", app / "camera.json",
                "--landmarks", tmp_path / "landmarks.csv", "-o", tmp_path / "replay", "-q") == 0
    assert _run("appearance", "classify", kit / "app.npz", app / "take" / "frame_%04d.png", "--geometry",
                tmp_path / "replay", "-o", tmp_path / "cls", "-q") == 0
    q = np.loadtxt(tmp_path / "cls" / "appearance.csv", delimiter=",", skiprows=1)[:, 2:]
    q_truth_geometry, truth = _q_and_truth(kit, "take")
    rho = [spearmanr(q[:, r], truth[:, r]).statistic for r in range(q.shape[1])]
    rho_truth_geometry = [spearmanr(q_truth_geometry[:, r], truth[:, r]).statistic for r in range(q.shape[1])]
    assert np.median(rho) > 0.85 and np.median(rho) > np.median(rho_truth_geometry) - 0.08, (rho, rho_truth_geometry)


def test_texture_export_is_the_layered_lookup_at_q(kit, tmp_path, capsys):
    import cv2

    from facepipe.io.appearance_file import load_appearance

    cls = _classified(kit)
    dest = tmp_path / "tex"
    assert _run("export", cls, "--format", "textures", "--layer", "albedo", "-o", dest) == 0
    said = capsys.readouterr().out
    assert "kbit/s" in said
    summary = json.loads((dest / "textures.json").read_text())
    q = np.loadtxt(dest / "appearance.csv", delimiter=",", skiprows=1)[:, 2:]
    assert summary["frames"] == len(q) and summary["bit_rate_kbit_s"] <= 12.0 and summary["shading"] == "albedo"
    frames = np.loadtxt(dest / "appearance.csv", delimiter=",", skiprows=1)[:, 0]
    assert (summary["first_file"], summary["first_frame"]) == (1, int(frames[0]))  # frame_0001 is the first row
    # 8 regions × 16 bits (Q in 1e-4 steps over 4 layers needs 40001 values) and the light's 7
    # values (the point light: an ambient term, a key and a fill) and 3 colour gains × 16 bits
    # (1e-4 steps over a span of 4) at 30 Hz
    assert summary["bits_per_frame"] == 8 * 16 + 10 * 16 and abs(summary["bit_rate_kbit_s"] - 8.64) < 0.01
    model = load_appearance(kit / "app.npz")
    assert model.albedo
    t = int(np.argmax(q.sum(axis=1)))
    got = cv2.imread(str(dest / f"frame_{t + 1:04d}.png"), cv2.IMREAD_UNCHANGED)[..., ::-1] / 65535.0
    # outside every region's box the texture is the neutral albedo
    outside = np.ones(model.neutral.shape[:2], dtype=bool)
    for alpha, (r0, c0) in zip(model.alphas, model.boxes):
        outside[r0:r0 + alpha.shape[0], c0:c0 + alpha.shape[1]] = False
    np.testing.assert_allclose(got[outside], np.clip(model.neutral_albedo[outside], 0, 1), atol=1e-4)
    # inside a region (alpha 1, no other region there) it is the linear blend of its two layers
    # around Q, computed here by hand: the most active region with such texels of its own
    def own_texels(r):
        (r0, c0), alpha = model.boxes[r], model.alphas[r]
        inner = alpha == 1.0
        for k, (a, (s0, t0)) in enumerate(zip(model.alphas, model.boxes)):
            if k != r:  # leave out texels another region's box also covers
                rows = slice(max(s0 - r0, 0), max(min(s0 + a.shape[0] - r0, alpha.shape[0]), 0))
                cols = slice(max(t0 - c0, 0), max(min(t0 + a.shape[1] - c0, alpha.shape[1]), 0))
                inner[rows, cols] = False
        return inner

    r = next(r for r in np.argsort(-q[t]) if q[t, r] > 0.5 and own_texels(r).sum() > 50)
    inner = own_texels(r)
    lo = min(int(q[t, r]), len(model.volumes[r]) - 2)
    f = q[t, r] - lo
    expected = (1 - f) * model.volumes[r][lo] + f * model.volumes[r][lo + 1]
    (r0, c0), alpha = model.boxes[r], model.alphas[r]
    window = got[r0:r0 + alpha.shape[0], c0:c0 + alpha.shape[1]]
    np.testing.assert_allclose(window[inner], expected[inner], atol=1e-4)


def test_exported_textures_are_the_albedo_shaded_by_each_frames_geometry_and_light(kit, tmp_path):
    """The default textures are the layered albedo times the shading of the frame's own surface
    under the frame's light (light.csv's row). And that shading is the footage's: on the turned
    take (the head turned up to 15° under another light) the skin outside every region, where the
    layers change nothing, is far closer to the frame's own texels than the neutral texture as
    the footage showed it. The renderer lights the face with its own ambient and Lambertian point
    light, warm; the classification fits its light and colour gains from the frame alone: an
    independent check."""
    import cv2

    from facepipe.io.appearance_file import load_appearance, read_light, read_stream
    from facepipe.pipeline.appearance_points import point_normals, texel_map, unwrap
    from facepipe.pipeline.appearance_texture import skin_texels, texel_shading

    cls = kit / "cls_take_turned"
    if not (cls / "appearance.csv").is_file():
        _q_and_truth(kit, "take_turned")
    shaded, albedo = tmp_path / "shaded", tmp_path / "albedo"
    assert _run("export", cls, "--format", "textures", "-o", shaded, "-q") == 0
    assert _run("export", cls, "--format", "textures", "--layer", "albedo", "-o", albedo, "-q") == 0
    assert json.loads((shaded / "textures.json").read_text())["shading"] == "frame"
    model = load_appearance(kit / "app.npz")
    _, numbers, _, q = read_stream(cls)
    light = read_light(cls, numbers)
    with np.load(kit / "appearance" / "take_turned.npz") as geometry:
        world = geometry["positions"]
    texel_face, texel_bary = texel_map(model.corner_uv, model.neutral.shape[0])
    outside = skin_texels(model, texel_face)
    for alpha, (r0, c0) in zip(model.alphas, model.boxes):
        outside[r0:r0 + alpha.shape[0], c0:c0 + alpha.shape[1]] = False
    footage = open_footage(kit / "appearance" / "take_turned" / "frame_%04d.png")
    errors = []
    for t in np.linspace(0, len(numbers) - 1, 5).round().astype(int):
        read = lambda folder: cv2.imread(str(folder / f"frame_{t + 1:04d}.png"),  # noqa: E731
                                         cv2.IMREAD_UNCHANGED)[..., ::-1] / 65535.0
        got, flat = read(shaded), read(albedo)
        camera_positions = model.to_camera(world[t])
        shading = texel_shading(model, camera_positions, light[t], texel_face, texel_bary)
        # a second construction: the texels' normals gathered from their corners, the point light
        # (ambient + the key's and the fill's clamped cosines) the stream carries
        on = skin_texels(model, texel_face)
        normals = point_normals(camera_positions[None], model.faces, texel_face[on], texel_bary[on],
                                model.normal_sign)[0]
        assert light.shape[1] == 10  # an ambient term, a key, a fill; the colour
        ambient, key, fill, red = light[t][0], light[t][1:4], light[t][4:7], light[t][7]
        low, high = shading[on][:, 0].min() / red, shading[on][:, 0].max() / red
        direct = np.clip(ambient + np.maximum(normals @ key, 0) + np.maximum(normals @ fill, 0), low, high)
        np.testing.assert_allclose(shading[on][:, 0], direct * red, rtol=1e-9)
        # on the layout (beyond it each texture repeats its own nearest island texel: edge padding)
        unclipped = (flat > 1e-3) & (flat < 1 - 1e-3) & (got < 1 - 1e-3) & (texel_face >= 0)[..., None]
        np.testing.assert_allclose(got[unclipped], (flat * shading)[unclipped], atol=2e-4)
        image = next(im for _, im, _ in read_frames(footage, numbers[t:t + 1]))
        truth, seen = unwrap(image, camera_positions, model.faces, texel_face, texel_bary, model.camera,
                             min_facing=model.min_facing, normal_sign=model.normal_sign)
        use = seen & outside
        assert use.sum() > 1000
        errors.append([np.sqrt(((texture - truth)[use] ** 2).mean()) for texture in (got, model.neutral)])
    shaded_rms, neutral_rms = np.mean(errors, axis=0)
    assert shaded_rms < 0.4 * neutral_rms, errors


def test_a_layout_on_two_udim_tiles_exports_a_texture_per_tile(kit, tmp_path):
    """Part of the face laid out on UDIM tile 1002 (its UVs moved one tile right, away from every
    region): the model keeps that tile's neutral albedo and the textures export writes
    frame_NNNN.1001.png and frame_NNNN.1002.png; the second tile's texture is its albedo shaded by
    each frame's geometry and light, closer to the turned take's frames than the neutral texture."""
    import cv2

    from facepipe.io.appearance_file import load_appearance, read_light, read_stream
    from facepipe.io.mesh_read import load_mesh
    from facepipe.core.raster import udim_tile_numbers
    from facepipe.pipeline.appearance_points import texel_map, unwrap
    from facepipe.pipeline.appearance_texture import frame_texture

    mesh = load_mesh(kit / "neutral.obj")
    faces, corner = mesh.faces, mesh.face_uvs
    regions = np.zeros(mesh.n_vertices, dtype=bool)
    for group in (kit / "appearance" / "regions").glob("*.txt"):
        regions[np.loadtxt(group, dtype=np.int64)] = True
    uv = mesh.uvs[corner]
    moved = (uv[:, :, 1].mean(axis=1) < 0.2) & ~regions[faces].any(axis=1)
    assert 100 < moved.sum() < 0.5 * len(faces)
    # the moved triangles' corners use the copies; five of them left of tile 1001, outside the UDIM range
    uvs = np.concatenate([mesh.uvs, mesh.uvs + [1.0, 0.0], mesh.uvs - [1.0, 0.0]])
    stray = np.flatnonzero(moved)[:5]
    corner = np.where(moved[:, None], corner + len(mesh.uvs), corner)
    corner[stray] += len(mesh.uvs)
    obj = tmp_path / "two_tiles.obj"
    obj.write_text("".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in mesh.vertices.tolist())
                   + "".join(f"vt {u!r} {v!r}\n" for u, v in uvs.tolist())
                   + "".join("f " + " ".join(f"{a + 1}/{b + 1}" for a, b in zip(f, c)) + "\n"
                             for f, c in zip(faces.tolist(), corner.tolist())))
    tile_of, in_udim = udim_tile_numbers(uvs[corner])
    assert np.unique(tile_of[in_udim]).tolist() == [1001, 1002] and (~in_udim).sum() == 5
    cfg = _edited_config(kit, tmp_path, "mesh = ", f'mesh = "{obj}" #')
    model_path = tmp_path / "app.npz"
    assert _run("appearance", "build", cfg, "-o", model_path, "-q") == 0
    model = load_appearance(model_path)
    assert model.extra_tiles == [1002] and model.tile_albedo.shape == (1,) + model.neutral.shape
    # the stray triangles are named, not silently dropped
    notes = json.loads((tmp_path / "app.json").read_text())["notes"]
    assert any(f"5 triangles of the rest mesh (the first: {stray[0]})" in n and "UDIM range" in n for n in notes)
    # a model file whose other tiles' textures are gone is refused, naming the file
    with np.load(model_path) as d:
        broken = {k: d[k] for k in d.files if k != "tile_albedo"}
    np.savez(tmp_path / "broken.npz", **broken)
    with pytest.raises(InputError, match="other UV tiles' textures are missing"):
        load_appearance(tmp_path / "broken.npz")
    take = "take_turned"
    cls = tmp_path / "cls"
    assert _run("appearance", "classify", model_path, kit / "appearance" / take / "frame_%04d.png",
                "--geometry", kit / "appearance" / f"{take}.npz", "-o", cls, "-q") == 0
    assert _run("export", cls, "--format", "textures", "-m", tmp_path / "broken.npz", "-o", tmp_path / "never") == 2
    assert not (tmp_path / "never").exists()
    out = tmp_path / "textures"
    assert _run("export", cls, "--format", "textures", "-o", out, "-q") == 0
    summary = json.loads((out / "textures.json").read_text())
    assert summary["tiles"] == [1001, 1002] and summary["files"] == "frame_####.<UDIM>.png"
    _, numbers, _, _ = read_stream(cls)
    assert summary["written"] == 2 * len(numbers)
    assert sorted(p.name for p in out.glob("frame_0001.*")) == ["frame_0001.1001.png", "frame_0001.1002.png"]
    light = read_light(cls, numbers)
    with np.load(kit / "appearance" / f"{take}.npz") as geometry:
        world = geometry["positions"]
    size = model.neutral.shape[0]
    texels = texel_map(model.corner_uv, size, 1002)
    assert (texels[0] >= 0).sum() > 1000 and (texel_map(model.corner_uv, size)[0][texels[0] >= 0] < 0).all()
    footage = open_footage(kit / "appearance" / take / "frame_%04d.png")
    errors = []
    for t in np.linspace(0, len(numbers) - 1, 4).round().astype(int):
        got = cv2.imread(str(out / f"frame_{t + 1:04d}.1002.png"), cv2.IMREAD_UNCHANGED)[..., ::-1] / 65535.0
        camera_positions = model.to_camera(world[t])
        np.testing.assert_allclose(got, np.clip(frame_texture(model, None, camera_positions, light[t], texels, 1002), 0, 1),
                                   atol=1e-4)
        image = next(im for _, im, _ in read_frames(footage, numbers[t:t + 1]))
        truth, seen = unwrap(image, camera_positions, model.faces, *texels, model.camera, min_facing=0.5,
                             normal_sign=model.normal_sign)
        assert seen.sum() > 500
        errors.append([np.sqrt(((texture - truth)[seen] ** 2).mean()) for texture in (got, model.tile_neutral[0])])
    shaded_rms, neutral_rms = np.mean(errors, axis=0)
    assert shaded_rms < 0.5 * neutral_rms, errors
    # the preview draws both tiles' textures (the second tile's triangles were left to the frame)
    assert _run("preview", cls, "-o", tmp_path / "preview.png", "-q") == 0


def _obj_with_uvs(path, mesh, uvs, corner):
    """The rest mesh written with other UVs (V', 2) and per-corner UV indices (F, 3)."""
    path.write_text("".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in mesh.vertices.tolist())
                    + "".join(f"vt {u!r} {v!r}\n" for u, v in uvs.tolist())
                    + "".join("f " + " ".join(f"{a + 1}/{b + 1}" for a, b in zip(f, c)) + "\n"
                              for f, c in zip(mesh.faces.tolist(), corner.tolist())))
    return path


def test_a_face_laid_out_on_another_udim_tile(kit, tmp_path, capsys):
    """The whole UV layout (and the templates) one tile right, on 1002: the model is the same as on
    1001 but for the tile (its arrays to round-off), the textures export writes
    frame_NNNN.1002.png with the same pixels; regions on two tiles, or a region over two tiles,
    are refused by name (exit 2)."""
    import cv2

    from facepipe.io.appearance_file import load_appearance
    from facepipe.io.mesh_read import load_mesh

    mesh = load_mesh(kit / "neutral.obj")
    corner = mesh.face_uvs
    obj = _obj_with_uvs(tmp_path / "on_1002.obj", mesh, mesh.uvs + [1.0, 0.0], corner)
    cfg = _edited_config(kit, tmp_path, "mesh = ", f'mesh = "{obj}" #')
    text = re.sub(r"template = \[([^,]+),([^,]+),([^,]+),",
                  lambda m: f"template = [{float(m[1]) + 1.0:.6f},{m[2]}, {float(m[3]) + 1.0:.6f},", cfg.read_text())
    cfg.write_text(text)
    assert _run("appearance", "build", cfg, "-o", tmp_path / "on_1002.npz", "-q") == 0
    assert _run("appearance", "build", kit / "appearance" / "appearance.toml", "-o", tmp_path / "on_1001.npz",
                "-q") == 0
    moved, home = load_appearance(tmp_path / "on_1002.npz"), load_appearance(tmp_path / "on_1001.npz")
    assert (moved.tile, home.tile, moved.all_tiles, moved.extra_tiles) == (1002, 1001, [1002], [])
    np.testing.assert_array_equal(moved.boxes, home.boxes)
    for a, b in zip(moved.volumes + moved.alphas + [moved.neutral, moved.neutral_albedo],
                    home.volumes + home.alphas + [home.neutral, home.neutral_albedo]):
        np.testing.assert_allclose(a, b, atol=1e-6)
    np.testing.assert_allclose(moved.rest_floor, home.rest_floor, atol=1e-9)
    take = kit / "appearance" / "take_turned"
    for name in ("on_1001", "on_1002"):
        assert _run("appearance", "classify", tmp_path / f"{name}.npz", take / "frame_%04d.png", "--geometry",
                    kit / "appearance" / "take_turned.npz", "-o", tmp_path / f"cls_{name}", "-q") == 0
        assert _run("export", tmp_path / f"cls_{name}", "--format", "textures", "-o", tmp_path / f"tex_{name}",
                    "-q") == 0
    summary = json.loads((tmp_path / "tex_on_1002" / "textures.json").read_text())
    assert summary["tiles"] == [1002] and summary["files"] == "frame_####.<UDIM>.png"
    for frame in (1, 12):
        got = cv2.imread(str(tmp_path / "tex_on_1002" / f"frame_{frame:04d}.1002.png"), cv2.IMREAD_UNCHANGED)
        want = cv2.imread(str(tmp_path / "tex_on_1001" / f"frame_{frame:04d}.png"), cv2.IMREAD_UNCHANGED)
        assert np.abs(got.astype(int) - want.astype(int)).max() <= 2  # 16-bit levels
    assert _run("preview", tmp_path / "cls_on_1002", "-o", tmp_path / "preview.png", "-q") == 0

    # one region's triangles moved to 1002, the others left on 1001; then half of that region's
    def whole(name):  # the triangles a region's vertex group holds whole
        return np.isin(mesh.faces, np.loadtxt(kit / "appearance" / "regions" / f"{name}.txt", dtype=np.int64)).all(1)

    names = [p.stem for p in (kit / "appearance" / "regions").glob("*.txt")]
    # a region that shares no triangle with another (the sample's brows)
    alone = next(n for n in sorted(names) if not any((whole(n) & whole(o)).any() for o in names if o != n))
    inside = whole(alone)
    uvs = np.concatenate([mesh.uvs, mesh.uvs + [1.0, 0.0]])
    for case, (moved_faces, message) in enumerate(((inside, "regions lie on different UDIM tiles: "),
                                 (inside & (np.cumsum(inside) <= inside.sum() // 2),
                                  f"region {alone}: its vertex group's triangles lie on UDIM tiles 1001, 1002"))):
        obj = _obj_with_uvs(tmp_path / "split.obj", mesh, uvs, np.where(moved_faces[:, None], corner + len(mesh.uvs),
                                                                        corner))
        cfg = _edited_config(kit, tmp_path / f"case{case}", "mesh = ", f'mesh = "{obj}" #')
        out = tmp_path / "never.npz"
        capsys.readouterr()
        assert _run("appearance", "build", cfg, "-o", out, "-q") == 2
        err = capsys.readouterr().err
        assert message in err and not out.exists(), err
        assert f"{alone} on 1002" in err or "1001, 1002" in err


def test_the_neutral_frame_rebuilt_from_its_albedo_is_its_texture(kit):
    """Albedo and shading undo each other: the neutral example frame's texture, rebuilt at Q = 0
    as its albedo times the shading of its own geometry under its own light, is the neutral
    texture as the footage showed it, on every skin texel that frame shows well (not edge-on)."""
    from facepipe.io.appearance_file import load_appearance
    from facepipe.io.config import load_config
    from facepipe.pipeline.appearance import _read_geometry
    from facepipe.pipeline.appearance_light import frame_light
    from facepipe.pipeline.appearance_points import texel_map, unwrap
    from facepipe.pipeline.appearance_texture import _texel_facing, frame_texture, skin_texels

    model = load_appearance(kit / "app.npz")
    cfg = load_config(kit / "appearance" / "appearance.toml").appearance
    positions, numbers = _read_geometry(cfg.geometry, model.n_vertices)
    n = cfg.neutral_frame
    camera_positions = model.to_camera(positions[list(numbers).index(n)])
    image = next(image for _, image, _ in read_frames(open_footage(cfg.footage), np.array([n])))
    light = frame_light(image, camera_positions, model)
    texels = texel_map(model.corner_uv, model.neutral.shape[0])
    rebuilt = frame_texture(model, np.zeros(len(model.names)), camera_positions, light, texels)
    _, seen = unwrap(image, camera_positions, model.faces, *texels, model.camera, min_facing=model.min_facing,
                     normal_sign=model.normal_sign)
    facing = _texel_facing(model, camera_positions, *texels, slice(None), slice(None))
    use = seen & skin_texels(model, texels[0]) & (facing > max(cfg.min_facing, cfg.min_point_facing))
    assert use.sum() > 0.5 * seen.sum()
    # the regions' alpha ramps blend layer 0 (the same frame) into the neutral albedo: the same values
    np.testing.assert_allclose(rebuilt[use], model.neutral[use], rtol=2e-3, atol=2e-4)
    # the texels just beyond the UV islands (a bilinear lookup's reach at a border) repeat the
    # nearest island texel, shaded as the frame; those far beyond are left alone
    from scipy import ndimage

    from facepipe.pipeline.appearance_texture import EDGE_PADDING

    covered = texels[0] >= 0
    distance, (ii, jj) = ndimage.distance_transform_edt(~covered, return_indices=True)
    ring = ~covered & (distance <= 1.5)
    assert ring.sum() > 0
    np.testing.assert_array_equal(rebuilt[ring], rebuilt[ii[ring], jj[ring]])
    far = ~covered & (distance > EDGE_PADDING)
    unpadded = model.base_texture  # beyond the padding: the albedo's own values (unshaded)
    np.testing.assert_array_equal(rebuilt[far], unpadded[far])


def test_texture_export_refuses_overwrite_resumes_and_writes_exr(kit, tmp_path):
    from facepipe.io.exr import read_exr

    cls = _classified(kit)
    dest = tmp_path / "tex"
    assert _run("export", cls, "--format", "textures", "-o", dest, "--half", "-q") == 0
    assert _run("export", cls, "--format", "textures", "-o", dest, "--half", "-q") == 2  # no overwrite
    first = dest / "frame_0001.exr"
    stamp = first.stat().st_mtime_ns
    (dest / "frame_0003.exr").unlink()
    assert _run("export", cls, "--format", "textures", "-o", dest, "--half", "--resume", "-q") == 0
    assert first.stat().st_mtime_ns == stamp and (dest / "frame_0003.exr").is_file()
    assert json.loads((dest / "textures.json").read_text())["written"] == 1
    image, _ = read_exr(dest / "frame_0003.exr")
    assert image.dtype == np.float16 and image.shape[2] == 3
    # a stream that is not this model's: exit 2
    (tmp_path / "bad").mkdir()
    shutil.copy(cls / "appearance.json", tmp_path / "bad")
    text = (cls / "appearance.csv").read_text().splitlines()
    (tmp_path / "bad" / "appearance.csv").write_text("\n".join([text[0], text[1].rsplit(",", 1)[0] + ",7.5"]) + "\n")
    assert _run("export", tmp_path / "bad", "--format", "textures", "-o", tmp_path / "t2", "-q") == 2
    assert _run("export", tmp_path / "nothing", "--format", "textures", "-o", tmp_path / "t3", "-q") == 2


def test_reconstructed_texture_is_closer_to_the_frames_than_neutral(kit):
    # the frame's texture at the classified Q (the layered albedo shaded by its geometry under the
    # light fitted to it) against each frame's own texels (unwrapped through its truth geometry),
    # relative to the neutral texture's difference, over the regions' texels
    from facepipe.io.appearance_file import load_appearance, read_light, read_stream
    from facepipe.io.mesh_read import load_mesh
    from facepipe.pipeline.appearance import _read_geometry
    from facepipe.pipeline.appearance_points import texel_map
    from facepipe.pipeline.appearance_texture import texture_differences

    model = load_appearance(kit / "app.npz")
    mesh = load_mesh(kit / "neutral.obj")
    cls = _classified(kit)
    _, stream_numbers, _, q = read_stream(cls)
    light = read_light(cls, stream_numbers)
    truth = np.loadtxt(kit / "appearance" / "take_truth.csv", delimiter=",", skiprows=1)[:, 1:]
    positions, numbers = _read_geometry(kit / "appearance" / "take.npz", mesh.n_vertices)
    texel_face, texel_bary = texel_map(mesh.uvs[mesh.face_uvs], model.neutral.shape[0])
    sums, at_truth = np.zeros((len(model.names), 3)), np.zeros((len(model.names), 3))
    for t, (_, image, _) in enumerate(read_frames(open_footage(kit / "appearance" / "take"), numbers)):
        cam = model.to_camera(positions[t])
        sums += texture_differences(model, texel_face, texel_bary, image, cam, q[t], light[t])
        at_truth += texture_differences(model, texel_face, texel_bary, image, cam, truth[t] * 4, light[t])
    ratio = np.sqrt(sums[:, 0].sum() / sums[:, 1].sum())
    ceiling = np.sqrt(at_truth[:, 0].sum() / at_truth[:, 1].sum())
    print("texture RMS ratio", ratio, "at the truth Q", ceiling)
    assert ratio <= 0.5 and ceiling <= 0.5


def test_preview_of_a_classified_take(kit, tmp_path, capsys):
    cls = _classified(kit)
    out = tmp_path / "preview.png"
    assert _run("preview", cls, "-o", out, "--strip", 2) == 0
    said = capsys.readouterr().out
    assert said.count("; Q ") == 2
    image = iio.imread(out)
    assert image.shape[0] > 400 and image.std() > 10  # panels and curves drawn, not a blank page
    assert _run("preview", cls, "-o", out) == 2  # not overwritten without --force
    assert _run("preview", cls, "-o", out, "--frame", 9999, "--force") == 2  # a frame the take lacks
    bare = tmp_path / "old"
    bare.mkdir()
    shutil.copy(cls / "appearance.csv", bare)
    info = json.loads((cls / "appearance.json").read_text())
    info.pop("footage")
    (bare / "appearance.json").write_text(json.dumps(info))
    assert _run("preview", bare, "-o", tmp_path / "p2.png") == 2
    assert "does not name the footage" in capsys.readouterr().err


def test_bad_examples_exit_2(kit, tmp_path, capsys):
    # an example frame of another size than the calibration
    cfg = _edited_config(kit, tmp_path, "neutral_frame = 0", "neutral_frame = 0")
    frame = cfg.parent / "examples" / "frame_0000.png"
    iio.imwrite(frame, iio.imread(frame)[:-4])
    assert _run("appearance", "build", cfg, "-o", tmp_path / "x.npz", "-q") == 2
    assert "calibration" in capsys.readouterr().err


def test_an_example_frame_whose_geometry_misses_the_face_is_noted(kit, tmp_path, capsys):
    """One example frame's geometry moved off its face in the image (as another frame's geometry,
    or a shifted frame number, would be): the build names that frame, and only that one."""
    cfg = _edited_config(kit, tmp_path, "neutral_frame = 0", "neutral_frame = 0")
    examples = cfg.parent / "examples.npz"
    with np.load(examples) as d:
        data = {k: d[k] for k in d.files}
    number = 7  # the brows' second layer
    row = int(np.flatnonzero(data["frame"] == number)[0])
    data["positions"] = data["positions"].copy()
    data["positions"][row] += np.array([1.5, 0.0, 0.0], dtype=data["positions"].dtype)  # 1.5 cm aside
    np.savez(examples, **data)
    assert _run("appearance", "build", cfg, "-o", tmp_path / "x.npz") == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if "seems to miss the face" in line]
    assert len(notes) == 1 and notes[0].startswith(f"note: example frame {number}:"), notes


@pytest.mark.parametrize("edit,message", [
    (lambda d: (d / "regions" / "mouth.txt").write_text("12\n99999999\n"), "line 2"),
    (lambda d: (d / "regions" / "mouth.txt").write_text("# no vertices\n"), "empty"),
    (lambda d: (d / "regions" / "mouth.txt").unlink(), "not found"),
])
def test_bad_vertex_groups_exit_2(kit, tmp_path, capsys, edit, message):
    cfg = _edited_config(kit, tmp_path, "neutral_frame = 0", "neutral_frame = 0")
    edit(cfg.parent)
    assert _run("appearance", "build", cfg, "-o", tmp_path / "x.npz", "-q") == 2
    assert message in capsys.readouterr().err


def test_example_frame_without_geometry_exits_2(kit, tmp_path, capsys):
    cfg = _edited_config(kit, tmp_path, "frames = [0, 1, 2, 3, 4]", "frames = [0, 1, 2, 3, 400]")
    assert _run("appearance", "build", cfg, "-o", tmp_path / "x.npz", "-q") == 2
    assert "frame 400" in capsys.readouterr().err


@pytest.mark.parametrize("old,new,message", [
    ("texture_size = 512", "texture_size = 512\nmin_seen = 0.0", "min_seen"),
    ("texture_size = 512", "texture_size = 512\nmin_point_facing = 1.5", "min_point_facing"),
    ("texture_size = 512", "texture_size = 512\nmin_relative_facing = 1.0", "min_relative_facing"),
    ("texture_size = 512", "texture_size = 512\nframe_facing_share = 1.5", "frame_facing_share"),
    # every point of a template must be seen well in every example: some are not (folds, slants)
    ("texture_size = 512", "texture_size = 512\nmin_seen = 1.0\nmin_relative_facing = 0.95", "seen well"),
])
def test_bad_visibility_settings(kit, tmp_path, capsys, old, new, message):
    cfg = _edited_config(kit, tmp_path, old, new)
    assert _run("appearance", "build", cfg, "-o", tmp_path / "x.npz", "-q") == 2
    assert message in capsys.readouterr().err


def _assert_model_refused(kit, tmp_path, capsys, data: dict, **broken) -> None:
    """A model's arrays ``data`` with the ``broken`` field written in: classification exits 2,
    names the field, and writes no stream."""
    np.savez(tmp_path / "broken.npz", **data, **broken)
    assert _run("appearance", "classify", tmp_path / "broken.npz", kit / "appearance" / "take" / "frame_%04d.png",
                "--geometry", kit / "appearance" / "take.npz", "-o", tmp_path / "cls_broken", "-q") == 2
    err = capsys.readouterr().err
    assert "not an appearance model" in err and all(name in err for name in broken)
    assert not (tmp_path / "cls_broken" / "appearance.csv").exists()


def test_shading_surfaces_chosen_per_region_saved_and_fixed_by_the_config(kit, tmp_path, capsys):
    """``auto`` measures per region what a quadratic keeps of its layers' contrast (the build says
    it); the model keeps each region's surface; the config fixes it for all or for one region."""
    from facepipe.io.appearance_file import load_appearance

    model = load_appearance(kit / "app.npz")
    assert model.shading_orders is not None and set(model.shading_orders.tolist()) <= {1, 2}
    cfg = _edited_config(kit, tmp_path, "texture_size = 512", 'texture_size = 512\nshading_surface = "plane"')
    assert _run("appearance", "build", cfg, "-o", tmp_path / "plane.npz") == 0
    assert "shading surfaces" in capsys.readouterr().out
    assert load_appearance(tmp_path / "plane.npz").shading_orders.tolist() == [1] * len(model.names)
    text = cfg.read_text()
    first = text.index("frames = [", text.index("[appearance.regions."))
    cfg.write_text(text[:first] + 'shading_surface = "quadratic"\n' + text[first:])
    assert _run("appearance", "build", cfg, "-o", tmp_path / "one.npz", "-q") == 0
    one = load_appearance(tmp_path / "one.npz")
    assert one.shading_orders.tolist() == [2] + [1] * (len(model.names) - 1)
    # without shading (patches divided by their mean alone) there is no surface to choose, and
    # the regions still follow their activations
    cfg.write_text(text.replace('shading_surface = "plane"', "shading = false"))
    assert _run("appearance", "build", cfg, "-o", tmp_path / "mean.npz") == 0
    assert "shading surfaces" not in capsys.readouterr().out
    assert _run("appearance", "classify", tmp_path / "mean.npz", kit / "appearance" / "take" / "frame_%04d.png",
                "--geometry", kit / "appearance" / "take.npz", "-o", tmp_path / "cls", "-q") == 0
    q = np.loadtxt(tmp_path / "cls" / "appearance.csv", delimiter=",", skiprows=1)[:, 2:]
    truth = np.loadtxt(kit / "appearance" / "take_truth.csv", delimiter=",", skiprows=1)[:, 1:]
    assert np.median([spearmanr(q[:, r], truth[:, r]).statistic for r in range(q.shape[1])]) > 0.9
    # models before the choice read as the plane everywhere
    assert load_appearance(tmp_path / "plane.npz").shading_orders is not None
    data = dict(np.load(tmp_path / "plane.npz"))
    del data["shading_orders"]
    np.savez(tmp_path / "old.npz", **data)
    assert load_appearance(tmp_path / "old.npz").shading_orders is None
    # a model whose surfaces are not 1 or 2 for each region: refused by name, nothing written
    _assert_model_refused(kit, tmp_path, capsys, data, shading_orders=np.full(len(model.names), 3))


def test_peak_interpolation_saved_and_fixed_by_the_config(kit, tmp_path, capsys):
    """The model keeps how its Q is read (the nearest point of the path through the layers by
    default; the paper's parabola when the config asks); models before the choice read the
    parabola, which they were calibrated with; a model with another value is refused by name."""
    from facepipe.io.appearance_file import load_appearance

    assert load_appearance(kit / "app.npz").peak_interpolation == "segment"
    cfg = _edited_config(kit, tmp_path, "texture_size = 512", 'texture_size = 512\npeak_interpolation = "parabola"')
    assert _run("appearance", "build", cfg, "-o", tmp_path / "parabola.npz") == 0
    assert "by parabola interpolation" in capsys.readouterr().out
    assert load_appearance(tmp_path / "parabola.npz").peak_interpolation == "parabola"
    truth = np.loadtxt(kit / "appearance" / "take_truth.csv", delimiter=",", skiprows=1)[:, 1:]
    errors = {}
    for name in ("parabola", "segment"):
        model = tmp_path / "parabola.npz" if name == "parabola" else kit / "app.npz"
        assert _run("appearance", "classify", model, kit / "appearance" / "take" / "frame_%04d.png",
                    "--geometry", kit / "appearance" / "take.npz", "-o", tmp_path / name, "-q") == 0
        q = np.loadtxt(tmp_path / name / "appearance.csv", delimiter=",", skiprows=1)[:, 2:]
        layers = np.asarray(load_appearance(model).layer_counts) - 1.0
        errors[name] = np.sqrt(np.mean((q - truth * layers) ** 2, axis=0))
    # both follow the take; the path is no worse over the regions on the sample's rendered take
    assert errors["segment"].mean() <= errors["parabola"].mean() * 1.05
    data = dict(np.load(tmp_path / "parabola.npz"))
    del data["peak_interpolation"]
    np.savez(tmp_path / "old.npz", **data)
    assert load_appearance(tmp_path / "old.npz").peak_interpolation == "parabola"
    _assert_model_refused(kit, tmp_path, capsys, data, peak_interpolation=np.array("cubic"))


def test_shading_reference_saved_and_fixed_by_the_config(kit, tmp_path, capsys):
    """The model keeps what its shading surfaces are fitted against (the patch alone by default,
    each region's neutral layer where the config asks); both read the sample's take; models
    before the choice read as the patch, which they were built with; another value is refused."""
    from facepipe.io.appearance_file import load_appearance

    assert load_appearance(kit / "app.npz").shading_reference == "patch"
    cfg = _edited_config(kit, tmp_path, "texture_size = 512", 'texture_size = 512\nshading_reference = "neutral"')
    assert _run("appearance", "build", cfg, "-o", tmp_path / "neutral.npz") == 0
    assert "fitted against each region's neutral layer" in capsys.readouterr().out
    assert load_appearance(tmp_path / "neutral.npz").shading_reference == "neutral"
    # the build's report: a shading ramp over each neutral template reads nothing relative to it
    tilt = json.loads((tmp_path / "neutral.json").read_text())["shading_tilt_q"]
    assert set(tilt) == set(load_appearance(kit / "app.npz").names) and max(tilt.values()) < 1e-6
    truth = np.loadtxt(kit / "appearance" / "take_truth.csv", delimiter=",", skiprows=1)[:, 1:]
    for name, model in (("patch", kit / "app.npz"), ("neutral", tmp_path / "neutral.npz")):
        assert _run("appearance", "classify", model, kit / "appearance" / "take" / "frame_%04d.png",
                    "--geometry", kit / "appearance" / "take.npz", "-o", tmp_path / name, "-q") == 0
        q = np.loadtxt(tmp_path / name / "appearance.csv", delimiter=",", skiprows=1)[:, 2:]
        assert min(spearmanr(q[:, r], truth[:, r]).statistic for r in range(q.shape[1])) > 0.8, name
    data = dict(np.load(tmp_path / "neutral.npz"))
    del data["shading_reference"]
    np.savez(tmp_path / "old.npz", **data)
    assert load_appearance(tmp_path / "old.npz").shading_reference == "patch"
    _assert_model_refused(kit, tmp_path, capsys, data, shading_reference=np.array("mean"))


def test_rest_readings_and_directions_in_a_model_file_are_checked(kit, tmp_path, capsys):
    """A model without the per-reading floors (written before them) loads with one floor per
    region; broken ones are refused by name."""
    from facepipe.io.appearance_file import load_appearance

    data = dict(np.load(kit / "app.npz"))
    assert data["rest_readings"].shape == data["rest_off_path"].shape and "rest_noise" in data
    old = {k: v for k, v in data.items() if not k.startswith(("rest_readings", "rest_off_path", "rest_tolerance",
                                                             "rest_noise", "rest_nuisance"))}
    np.savez(tmp_path / "old.npz", **old)
    model = load_appearance(tmp_path / "old.npz")
    assert model.rest_readings is None and model.rest_tolerance == 0.0 and model.rest_floor is not None
    for name, broken in (("rest_off_path", data["rest_off_path"][:, :2]), ("rest_tolerance", np.array(-1.0)),
                         ("rest_nuisance_0", np.full((1, 7), np.nan))):
        _assert_model_refused(kit, tmp_path, capsys, {k: v for k, v in data.items() if k != name}, **{name: broken})


def test_template_samples_in_a_model_file(kit, tmp_path, capsys):
    """The model keeps each region's layer samples before normalising (a partly seen sample's
    templates are normalised from them); a model without them loads (its partly seen samples
    matched the old way); broken ones are refused by name."""
    from facepipe.io.appearance_file import load_appearance

    data = dict(np.load(kit / "app.npz"))
    model = load_appearance(kit / "app.npz")
    assert len(model.template_patches) == len(model.names)
    for r, patches in enumerate(model.template_patches):
        assert patches.shape == (len(model.templates[r]), model.template_size ** 2)
    np.savez(tmp_path / "old.npz", **{k: v for k, v in data.items() if not k.startswith("template_patches")})
    assert load_appearance(tmp_path / "old.npz").template_patches is None
    for broken in (data["template_patches_0"][:-1], np.full_like(data["template_patches_0"], np.nan)):
        _assert_model_refused(kit, tmp_path, capsys, {k: v for k, v in data.items() if k != "template_patches_0"},
                              template_patches_0=broken)


def test_a_broken_cards_shaded_flag_is_refused(kit, tmp_path, capsys):
    """A model file whose cards_shaded flag is not a true/false, or is set on a model without
    cards (the sample's), is refused by name: exit 2, no stream written."""
    data = dict(np.load(kit / "app.npz"))
    for broken in (np.array([1, 0]), np.array(True)):
        _assert_model_refused(kit, tmp_path, capsys, data, cards_shaded=broken)


def test_a_broken_card_motion_check_is_refused(kit, tmp_path, capsys):
    """A model file whose stored motion check (an eye card's) has a shift that is not > 0, rows
    that are not unit directions, or a reference patch of another size is refused by name: exit 2,
    no stream written."""
    data = dict(np.load(kit / "app.npz"))
    size = int(data["settings"][0])
    check = {"card_motion_reference_0": np.zeros((size, size)),
             "card_motion_reference_seen_0": np.ones((size, size), bool), "card_motion_least_0": np.array(0.5), "card_motion_layers_0": np.array([[1.0, 0.0]]),
             "card_motion_rest_0": np.zeros((0, 2))}
    for key, broken in (("card_motion_least_0", np.array(-1.0)), ("card_motion_layers_0", np.array([[2.0, 0.0]])),
                        ("card_motion_rest_0", np.array([1.0, 0.0])),
                        ("card_motion_reference_0", np.zeros((size - 1, size - 1)))):
        _assert_model_refused(kit, tmp_path, capsys, {**data, **{k: v for k, v in check.items() if k != key}},
                              **{key: broken})


def test_a_frame_leaves_out_the_points_it_sees_at_under_half_the_examples_facing(kit, tmp_path, capsys):
    """In a frame, a template point is left out as edge-on where the frame sees it at under
    frame_facing_share of the least cosine the region's examples saw it at; with the share 0 (and
    in models written before it) where it sees it under min_point_facing. An example frame sees
    every point at least as well as the least of its examples: it loses none to the test."""
    import dataclasses

    from facepipe.io.appearance_file import load_appearance
    from facepipe.io.config import load_config
    from facepipe.io.footage import to_gray
    from facepipe.pipeline.appearance import _read_geometry, sample_patches
    from facepipe.pipeline.appearance_points import template_point_facing

    model = load_appearance(kit / "app.npz")
    s = model.template_size
    positions, numbers = _read_geometry(kit / "appearance" / "take_turned.npz", model.n_vertices)
    footage = open_footage(kit / "appearance" / "take_turned" / "frame_%04d.png")
    grays = np.stack([to_gray(image) for _, image, _ in read_frames(footage, numbers)])
    # the take, and the take turned 35° further about the face's centre, where points fall
    # between the two limits (the test is not the old one renamed)
    centre = positions.mean(axis=(0, 1))
    a = np.deg2rad(35.0)
    yaw = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    examples = model.template_facing.reshape(model.template_facing.shape[:2] + (s, s))
    differ = False
    for world in (positions, (positions - centre) @ yaw.T + centre):
        cams = model.to_camera(world)
        facing = template_point_facing(cams, model)
        untested = sample_patches(grays, cams, dataclasses.replace(model, min_point_facing=0.0))[2]
        seen = sample_patches(grays, cams, model)[2]
        np.testing.assert_array_equal(seen, untested & (facing > 0.5 * examples))
        fixed = sample_patches(grays, cams, dataclasses.replace(model, frame_facing_share=0.0))[2]
        np.testing.assert_array_equal(fixed, untested & (facing > model.min_point_facing))
        differ |= bool((seen != fixed).any())
    assert differ
    # the examples of a region: none of their points is left out as edge-on
    cfg = load_config(kit / "appearance" / "appearance.toml").appearance
    ex_positions, ex_numbers = _read_geometry(cfg.geometry, model.n_vertices)
    ex_grays = np.stack([to_gray(image) for _, image, _ in read_frames(open_footage(cfg.footage), ex_numbers)])
    ex_cams = model.to_camera(ex_positions)
    ex_untested = sample_patches(ex_grays, ex_cams, dataclasses.replace(model, min_point_facing=0.0))[2]
    ex_seen = sample_patches(ex_grays, ex_cams, model)[2]
    for r, region in enumerate(cfg.regions):
        rows = np.isin(ex_numbers, region.frames)
        np.testing.assert_array_equal(ex_seen[rows, r], ex_untested[rows, r])
    # saved with the model; a model without it reads the old test; a share out of [0, 1] is refused
    data = dict(np.load(kit / "app.npz"))
    assert float(data["frame_facing_share"]) == pytest.approx(0.5)
    del data["frame_facing_share"]
    np.savez(tmp_path / "older.npz", **data)
    assert load_appearance(tmp_path / "older.npz").frame_facing_share == 0.0
    _assert_model_refused(kit, tmp_path, capsys, data, frame_facing_share=np.array(1.5))


def test_light_model_saved_and_fixed_by_the_config(kit, tmp_path, capsys):
    """The model keeps the light it was built under (an ambient term and a point light by default,
    the nine terms when the config asks); both follow the take; models before the choice read the
    nine terms, which their light points' albedo was derived under; another value is refused."""
    from facepipe.io.appearance_file import load_appearance

    assert load_appearance(kit / "app.npz").light_model == "point"
    assert json.loads((kit / "app.json").read_text())["light"]["model"] == "point"
    cfg = _edited_config(kit, tmp_path, "texture_size = 512", 'texture_size = 512\nlight_model = "sh9"')
    assert _run("appearance", "build", cfg, "-o", tmp_path / "sh9.npz") == 0
    assert "light fitted as nine spherical-harmonic terms" in capsys.readouterr().out
    assert load_appearance(tmp_path / "sh9.npz").light_model == "sh9"
    assert _run("appearance", "classify", tmp_path / "sh9.npz", kit / "appearance" / "take" / "frame_%04d.png",
                "--geometry", kit / "appearance" / "take.npz", "-o", tmp_path / "cls", "-q") == 0
    q = np.loadtxt(tmp_path / "cls" / "appearance.csv", delimiter=",", skiprows=1)[:, 2:]
    truth = np.loadtxt(kit / "appearance" / "take_truth.csv", delimiter=",", skiprows=1)[:, 1:]
    assert np.median([spearmanr(q[:, r], truth[:, r]).statistic for r in range(q.shape[1])]) > 0.9
    assert json.loads((tmp_path / "cls" / "appearance.json").read_text())["light_model"] == "sh9"
    # the stream carries the light the model fits: the nine terms here, the point light by default
    from facepipe.io.appearance_file import LIGHT_COLUMNS, POINT_LIGHT_COLUMNS, read_light

    assert load_appearance(tmp_path / "sh9.npz").stream_light == "sh9"
    assert (tmp_path / "cls" / "light.csv").read_text().splitlines()[0] == "frame,time," + ",".join(LIGHT_COLUMNS)
    assert read_light(tmp_path / "cls", np.loadtxt(tmp_path / "cls" / "appearance.csv", delimiter=",",
                                                   skiprows=1)[:, 0].astype(int)).shape[1] == 12
    assert load_appearance(kit / "app.npz").stream_light == "point"
    point_cls = _classified(kit)
    assert (point_cls / "light.csv").read_text().splitlines()[0] == "frame,time," + ",".join(POINT_LIGHT_COLUMNS)
    point = dict(np.load(kit / "app.npz"))
    del point["stream_light"]  # models before it: the nine terms in the stream
    np.savez(tmp_path / "older.npz", **point)
    assert load_appearance(tmp_path / "older.npz").stream_light == "sh9"
    _assert_model_refused(kit, tmp_path, capsys, point, stream_light=np.array("sh2"))
    data = dict(np.load(tmp_path / "sh9.npz"))
    # a point light in the stream of a model that fits the nine terms
    _assert_model_refused(kit, tmp_path, capsys, data, stream_light=np.array("point"))
    del data["light_model"]
    np.savez(tmp_path / "old.npz", **data)
    assert load_appearance(tmp_path / "old.npz").light_model == "sh9"
    _assert_model_refused(kit, tmp_path, capsys, data, light_model=np.array("sh2"))
    # the point light without its light points' albedo under it
    _assert_model_refused(kit, tmp_path, capsys, data, light_model=np.array("point"))


def test_unseen_margin_takes_points_beside_unstable_ones_and_yields_to_min_seen(kit, tmp_path, capsys):
    """The margin only removes stable points (those beside points an example does not show
    well); where it would leave a template under min_seen the build narrows it (halved twice,
    then none) and says so, rather than refusing a template that is seen well enough."""
    from facepipe.io.appearance_file import load_appearance

    default = load_appearance(kit / "app.npz").template_mask
    cfg = _edited_config(kit, tmp_path, "texture_size = 512", "texture_size = 512\nunseen_margin = 0")
    assert _run("appearance", "build", cfg, "-o", tmp_path / "none.npz", "-q") == 0
    plain = load_appearance(tmp_path / "none.npz").template_mask
    assert not (default & ~plain).any() and (plain & ~default).any()
    cfg.write_text(cfg.read_text().replace("unseen_margin = 0", "unseen_margin = 7.5"))
    assert _run("appearance", "build", cfg, "-o", tmp_path / "wide.npz") == 0
    assert "the unseen margin (7.5 px) would leave" in capsys.readouterr().out
    wide = load_appearance(tmp_path / "wide.npz")
    assert (wide.template_mask.mean(axis=1) >= wide.min_seen).all()
    assert not (wide.template_mask & ~plain).any()


def test_model_keeps_its_visibility_settings(kit):
    from facepipe.io.appearance_file import load_appearance

    model = load_appearance(kit / "app.npz")
    assert model.occlusion and model.min_seen == 0.5 and model.min_point_facing == pytest.approx(0.35)
    assert model.frame_facing_share == pytest.approx(0.5)
    s = model.template_size
    assert model.template_facing.shape == (len(model.names), 5, s * s)
    assert (model.template_facing <= 1.0).all() and (model.template_facing > 0).mean() > 0.9
    # the stable points: each region's templates are zero off them, and at least min_seen of a template
    assert model.template_mask.shape == (len(model.names), s * s) and model.template_mask.dtype == bool
    assert (model.template_mask.mean(axis=1) >= model.min_seen).all()
    from facepipe.core.appearance import haar_matrix

    H, _ = haar_matrix(s)
    for t, m in zip(model.templates, model.template_mask):
        assert np.abs((t @ H)[:, ~m]).max(initial=0.0) < 1e-9


def test_sample_appearance_without_its_drivers_exits_2_before_writing(tmp_path, capsys):
    """--appearance with too few examples for the regions' drivers is refused before the rig is
    written, naming the missing expressions and the --examples that has them."""
    d = tmp_path / "rig"
    assert _run("sample", d, "--vertices", 2000, "--examples", 7, "--appearance", "-q") == 2
    err = capsys.readouterr().err
    assert "squint_R" in err and "--examples 8" in err
    assert not d.exists()


def _examples_read_zero_at_rest_and_rise(model, cfg, positions, numbers):
    """Q of the example frames: 0 wherever a region is at rest, rising through its own layers to
    the last."""
    from facepipe.pipeline.appearance import classify_frames

    q = classify_frames(model, cfg.footage, positions, numbers, numbers / 30.0).q
    row = {int(n): i for i, n in enumerate(numbers)}
    # the sample's other expressions (no region's driver) are its rest frames: at rest for every region
    assert cfg.rest_frames and not set(cfg.rest_frames) & {f for region in cfg.regions for f in region.frames}
    for r, region in enumerate(cfg.regions):
        own = [row[f] for f in region.frames[1:]]
        rest = [i for i in range(len(numbers)) if i not in own]
        assert (q[rest, r] == 0.0).all(), (region.name, q[rest, r])
        assert q[own[-1], r] == pytest.approx(len(region.frames) - 1, abs=0.05)
        assert np.all(np.diff(q[own, r]) > 0)
    return q


def test_at_rest_examples_reading_high_are_explained_away(kit, tmp_path, capsys):
    """rest_explain: an example frame where a region is at rest but reads above it has its change
    left out of that region's match. It then reads 0 before any floor, the region's floor drops,
    its own layers still rise to the last, the build names the frames, and the model keeps the
    directions (at most three a region)."""
    from facepipe.io.appearance_file import load_appearance
    from facepipe.io.config import load_config
    from facepipe.pipeline.appearance import _read_geometry
    from facepipe.io.footage import open_footage, read_frames, to_gray
    from facepipe.pipeline.appearance import classify_decoded

    base = load_appearance(kit / "app.npz")
    assert base.rest_floor.max() < 0.2 and all(n is None for n in base.rest_nuisance)  # the default: none here
    config = _edited_config(kit, tmp_path, "texture_size = 512", "texture_size = 512\nrest_explain = 0.05")
    out = tmp_path / "explained.npz"
    assert _run("appearance", "build", config, "-o", out) == 0
    said = capsys.readouterr().out
    report = json.loads(out.with_suffix(".json").read_text())
    explained = {n: v["explained"] for n, v in report["rest"].items() if v["explained"]}
    high = [n for n, f in zip(base.names, base.rest_floor) if f > 0.05]
    assert explained and set(explained) <= set(high)
    assert "explained away" in said
    model = load_appearance(out)
    cfg = load_config(config).appearance
    positions, numbers = _read_geometry(cfg.geometry, model.n_vertices)
    grays = np.stack([to_gray(im) for _, im, _ in read_frames(open_footage(cfg.footage), numbers)])
    raw = classify_decoded(grays, np.stack([model.to_camera(p) for p in positions]),
                           model.without_rest_floors()).q
    row = {int(n): i for i, n in enumerate(numbers)}
    for r, name in enumerate(model.names):
        directions = model.rest_nuisance[r]
        assert (directions is not None) == (name in explained)
        if directions is None:
            continue
        assert len(directions) == len(explained[name]) <= 3 and directions.shape[1] == model.template_size ** 2
        # the frame explained away matches the neutral template exactly, and sets the floor no more
        assert all(raw[row[f], r] == pytest.approx(0.0, abs=1e-6) for f in explained[name])
        assert report["rest"][name]["frame"] not in explained[name]
        assert model.rest_floor[r] < base.rest_floor[r]
    _examples_read_zero_at_rest_and_rise(model, cfg, positions, numbers)


def test_an_at_rest_example_like_the_regions_own_motion_is_not_explained_away(kit, tmp_path, capsys, monkeypatch):
    """A frame whose direction would take too much of a layer step with it is kept and noted."""
    import facepipe.pipeline.appearance_build as build

    monkeypatch.setattr(build, "LEAST_STEP_KEPT", 1.0)  # every direction shares some of a step
    config = _edited_config(kit, tmp_path, "texture_size = 512", "texture_size = 512\nrest_explain = 0.05")
    out = tmp_path / "kept.npz"
    assert _run("appearance", "build", config, "-o", out, "-q") == 0
    report = json.loads(out.with_suffix(".json").read_text())
    assert not any(v["explained"] for v in report["rest"].values())
    assert any("not explained away" in note for note in report["notes"])


def test_regions_read_zero_at_rest_in_the_examples(kit, tmp_path, capsys):
    """Rest calibration: every region reads exactly 0 in the example frames where it is at rest
    (the neutral frame, the other regions' examples), still rises to its extreme layer in its
    own, and the build reports the floors. Without it the model has none and Q is the raw one."""
    from facepipe.io.appearance_file import load_appearance, save_appearance
    from facepipe.io.config import load_config
    from facepipe.pipeline.appearance import _read_geometry

    model = load_appearance(kit / "app.npz")
    assert model.rest_floor.shape == (len(model.names),)
    assert (model.rest_floor >= 0).all() and (model.rest_floor <= 1.0).all() and model.rest_floor.max() > 0
    cfg = load_config(kit / "appearance" / "appearance.toml").appearance
    positions, numbers = _read_geometry(cfg.geometry, int(model.faces.max()) + 1)
    q = _examples_read_zero_at_rest_and_rise(model, cfg, positions, numbers)
    # the floors, as the build printed them
    out = tmp_path / "again.npz"
    assert _run("appearance", "build", kit / "appearance" / "appearance.toml", "-o", out) == 0
    assert "rest floors" in capsys.readouterr().out
    report = json.loads(out.with_suffix(".json").read_text())
    assert [report["rest"][n]["floor"] for n in model.names] == pytest.approx(model.rest_floor.tolist())
    # rest_calibration = false: no floor, the raw Q (the same model otherwise)
    config = _edited_config(kit, tmp_path, "texture_size = 512", "texture_size = 512\nrest_calibration = false")
    raw_path = tmp_path / "raw.npz"
    assert _run("appearance", "build", config, "-o", raw_path, "-q") == 0
    raw = load_appearance(raw_path)
    assert raw.rest_floor is None and raw.rest_readings is None
    assert all(n is None for n in raw.rest_nuisance)
    # Q measured from each reading's own floor (the at-rest readings as far off the layer path
    # that hide it): the same readings with the floors stripped, then measured from them
    from facepipe.core.appearance import above_rest
    from facepipe.io.footage import open_footage, read_frames, to_gray
    from facepipe.pipeline.appearance import classify_decoded, rest_floors

    grays = np.stack([to_gray(im) for _, im, _ in read_frames(open_footage(cfg.footage), numbers)])
    cams = np.stack([model.to_camera(p) for p in positions])
    floored = classify_decoded(grays, cams, model)
    stripped = classify_decoded(grays, cams, model.without_rest_floors())
    np.testing.assert_allclose(floored.off_path, stripped.off_path, atol=1e-12)
    np.testing.assert_allclose(above_rest(stripped.q, rest_floors(model, stripped.off_path), model.layer_counts),
                               floored.q, atol=1e-12)
    np.testing.assert_allclose(floored.q, q, atol=1e-12)
    # a model saved without floors (as before them) loads with none
    save_appearance(tmp_path / "old.npz", raw)
    assert load_appearance(tmp_path / "old.npz").rest_floor is None


def test_classify_reports_its_speed_and_the_streams_bit_rate(kit, tmp_path, capsys):
    from facepipe.core.layered_texture import light_bits, stream_bits
    from facepipe.io.appearance_file import STREAM_DECIMALS, load_appearance, read_light, read_stream

    out = tmp_path / "cls"
    assert _run("appearance", "classify", kit / "app.npz", kit / "appearance" / "take" / "frame_%04d.png",
                "--geometry", kit / "appearance" / "take.npz", "-o", out, "--fps", 24) == 0
    said = capsys.readouterr().out
    info = json.loads((out / "appearance.json").read_text())
    q_bits = int(stream_bits(load_appearance(kit / "app.npz").layer_counts, 10.0 ** -STREAM_DECIMALS).sum())
    # Q per region and the frame's light: the point light's seven values and three colour gains
    bits = q_bits + light_bits(10.0 ** -STREAM_DECIMALS, 10)
    assert info["q_bits_per_frame"] == q_bits and info["light_bits_per_frame"] == 10 * 16
    assert read_light(out, read_stream(out)[1]).shape == (info["frames"], 10)
    assert info["stream_bits_per_frame"] == bits and info["stream_kbit_s"] == pytest.approx(bits * 24 / 1000)
    assert info["fps"] == 24 and info["seconds"] > 0
    assert info["frames_per_second"] == pytest.approx(info["frames"] / info["seconds"])
    assert "frames/s" in said and f"{bits * 24 / 1000:.2f} kbit/s at 24 Hz" in said


def test_geometry_that_misses_the_face_in_the_footage_is_named_by_frame(kit, tmp_path, capsys):
    """The head-turned footage classified with the frontal take's geometry (a user giving the wrong
    take): the frames where the head has turned away from where the geometry puts it are named with
    a warning, and the light residual of every frame is in appearance.json; with its own geometry no
    frame is. A model written before the check classifies as before, without it."""
    from facepipe.io.appearance_file import load_appearance

    model = load_appearance(kit / "app.npz")
    assert 0 < model.light_residual < 0.05  # the examples' light leaves a few percent at most
    footage = kit / "appearance" / "take_turned" / "frame_%04d.png"
    checks = {}
    for geometry in ("take", "take_turned"):
        out = tmp_path / geometry
        assert _run("appearance", "classify", kit / "app.npz", footage, "--geometry",
                    kit / "appearance" / f"{geometry}.npz", "-o", out) == 0
        said = capsys.readouterr().out
        checks[geometry] = (said, json.loads((out / "appearance.json").read_text())["footage_check"])
    said, check = checks["take"]
    frames = len(check["light_residual"])
    assert check["frames_off_face"] > frames // 3 and check["ratio_median"] > check["ratio_limit"]
    assert re.search(rf"warning: {check['frames_off_face']} of {frames} frames \(frames \d+", said)
    assert "--geometry is this footage's take" in said
    said, check = checks["take_turned"]
    assert check["frames_off_face"] == 0 and check["ratio_median"] < check["ratio_limit"] / 2
    assert "warning" not in said and len(check["light_residual"]) == frames
    assert f"footage check: the geometry lies on the face in every frame read (the light leaves " \
           f"{check['ratio_median']:.1f}×" in said
    with np.load(kit / "app.npz") as d:
        older = {k: d[k] for k in d.files if k != "light_residual"}
    np.savez(tmp_path / "older.npz", **older)
    assert load_appearance(tmp_path / "older.npz").light_residual is None
    assert _run("appearance", "classify", tmp_path / "older.npz", footage, "--geometry",
                kit / "appearance" / "take.npz", "-o", tmp_path / "older", "-q") == 0
    assert "footage_check" not in json.loads((tmp_path / "older" / "appearance.json").read_text())
    assert (np.loadtxt(tmp_path / "older" / "appearance.csv", delimiter=",", skiprows=1)
            == np.loadtxt(tmp_path / "take" / "appearance.csv", delimiter=",", skiprows=1)).all()
    older["light_residual"] = np.array(np.nan)
    np.savez(tmp_path / "bad.npz", **older)
    with pytest.raises(InputError, match="light_residual nan is not a share"):
        load_appearance(tmp_path / "bad.npz")


def test_footage_that_is_not_there_is_refused_before_any_progress(kit, tmp_path, capsys):
    assert _run("appearance", "classify", kit / "app.npz", tmp_path / "nowhere",
                "--geometry", kit / "appearance" / "take.npz", "-o", tmp_path / "cls") == 2
    said = capsys.readouterr()
    assert "nowhere" in said.err and "classify:" not in said.err + said.out
    assert not (tmp_path / "cls").exists()


def test_frames_classified_on_threads_equal_one_chunk_after_another(kit):
    """classify_decoded shares the chunks among facepipe's threads: the same Q and visibility,
    bit for bit, as classify_chunk over each chunk in turn (frames whose masks differ, so the
    templates' mask cache is filled and read from both threads)."""
    from facepipe.io.appearance_file import load_appearance
    from facepipe.io.footage import to_gray
    from facepipe.parallel import set_thread_count
    from facepipe.pipeline.appearance import _read_geometry, classify_chunk, classify_decoded, region_bank

    model = load_appearance(kit / "app.npz")
    positions, numbers = _read_geometry(kit / "appearance" / "take_turned.npz", model.n_vertices)
    footage = open_footage(kit / "appearance" / "take_turned" / "frame_%04d.png")
    grays = np.stack([to_gray(image) for _, image, _ in read_frames(footage, numbers)])
    cams = model.to_camera(positions)
    one = [classify_chunk(grays[i:i + 4], cams[i:i + 4], model, region_bank(model)) for i in range(0, len(grays), 4)]
    try:
        set_thread_count(3)
        readings = classify_decoded(grays, cams, model, region_bank(model), chunk=4)
    finally:
        set_thread_count(None)
    np.testing.assert_array_equal(readings.q, np.concatenate([c[0] for c in one]))
    np.testing.assert_array_equal(readings.visible, np.concatenate([c[1] for c in one]))
    assert readings.light.shape == (len(grays), 7) and readings.in_view.shape == readings.q.shape
    assert readings.light_residual.shape == (len(grays),) and np.isfinite(readings.light_residual).all()
    empty = classify_decoded(grays[:0], cams[:0], model)
    assert empty.q.shape == (0, len(model.names)) and empty.visible.shape == (0, len(model.names))
    assert empty.light.shape == (0, 7) and empty.in_view.shape == (0, len(model.names))
    assert empty.light_residual.shape == (0,)


def test_textures_without_the_frames_light_or_geometry_are_the_albedo_and_say_so(kit, tmp_path, capsys):
    """A classified folder without light.csv (classified before facepipe wrote it), or whose
    geometry is gone, exports the layered albedo with a note; a broken light.csv, --layer albedo of
    a model that holds the footage's values, and a geometry layer for textures are refused."""
    from facepipe.io.appearance_file import load_appearance, save_appearance

    cls = _classified(kit)
    old = tmp_path / "old"
    shutil.copytree(cls, old)
    (old / "light.csv").unlink()
    assert _run("export", old, "--format", "textures", "-o", tmp_path / "a") == 0
    assert "no light.csv" in capsys.readouterr().out
    assert json.loads((tmp_path / "a" / "textures.json").read_text())["shading"] == "albedo"

    moved = tmp_path / "moved"
    shutil.copytree(cls, moved)
    info = json.loads((moved / "appearance.json").read_text())
    info["geometry"] = str(tmp_path / "gone.npz")
    (moved / "appearance.json").write_text(json.dumps(info))
    assert _run("export", moved, "--format", "textures", "-o", tmp_path / "b") == 0
    assert "gone.npz" in capsys.readouterr().out

    broken = tmp_path / "broken"
    shutil.copytree(cls, broken)
    lines = (broken / "light.csv").read_text().splitlines()
    (broken / "light.csv").write_text("\n".join(lines[:-1]) + "\n")  # a frame short
    assert _run("export", broken, "--format", "textures", "-o", tmp_path / "c") == 2
    assert "light.csv" in capsys.readouterr().err and not (tmp_path / "c").exists()
    (broken / "light.csv").write_text("frame,time,ambient,key\n" + "\n".join(lines[1:]) + "\n")  # a header it does not know
    assert _run("export", broken, "--format", "textures", "-o", tmp_path / "c") == 2
    err = capsys.readouterr().err
    assert "light.csv" in err and "line 1 (frame, time, ambient, key)" in err and not (tmp_path / "c").exists()
    shutil.copy(cls / "light.csv", broken / "light.csv")
    with open(broken / "appearance.csv", "a") as fh:
        fh.write("999,33.3,not a number\n")
    assert _run("export", broken, "--format", "textures", "-o", tmp_path / "c") == 2
    err = capsys.readouterr().err
    assert "appearance.csv" in err and f"line {len(lines) + 1}" in err and not (tmp_path / "c").exists()

    assert _run("export", cls, "--format", "textures", "--layer", "large", "-o", tmp_path / "d") == 2
    assert "not a layer of textures" in capsys.readouterr().err and not (tmp_path / "d").exists()

    model = load_appearance(kit / "app.npz")
    model.neutral_albedo = None  # as a model built without a light fit holds its layers
    save_appearance(tmp_path / "footage.npz", model)
    assert _run("export", cls, "--format", "textures", "-m", tmp_path / "footage.npz", "-o", tmp_path / "e") == 0
    assert json.loads((tmp_path / "e" / "textures.json").read_text())["shading"] == "footage"
    assert _run("export", cls, "--format", "textures", "-m", tmp_path / "footage.npz", "--layer", "albedo",
                "-o", tmp_path / "f") == 2
    assert "holds the footage's values" in capsys.readouterr().err and not (tmp_path / "f").exists()


@pytest.mark.parametrize("damage,message", [
    ("model_cut", "cut short or damaged"),       # an interrupted copy of the model
    ("geometry_cut", "cut short or damaged"),    # ... of the take's geometry
    ("geometry_nan", "frame 3: vertex 10 is not finite"),
])
def test_damaged_model_or_geometry_exits_2_by_name(kit, tmp_path, capsys, damage, message):
    """A model or geometry file cut short, or geometry with a NaN vertex, is refused with the
    file, frame and vertex named: no traceback, no stream written."""
    model, geometry = kit / "app.npz", kit / "appearance" / "take.npz"
    if damage == "model_cut":
        model = tmp_path / "cut.npz"
        model.write_bytes((kit / "app.npz").read_bytes()[:5000])
    elif damage == "geometry_cut":
        geometry = tmp_path / "cut.npz"
        geometry.write_bytes((kit / "appearance" / "take.npz").read_bytes()[:5000])
    else:
        data = dict(np.load(geometry))
        data["positions"] = data["positions"].copy()
        data["positions"][3, 10, 1] = np.nan
        geometry = tmp_path / "nan.npz"
        np.savez(geometry, **data)
    out = tmp_path / "cls"
    assert _run("appearance", "classify", model, kit / "appearance" / "take" / "frame_%04d.png",
                "--geometry", geometry, "-o", out, "-q") == 2
    err = capsys.readouterr().err
    assert message in err and ("cut.npz" in err or "nan.npz" in err) and "Traceback" not in err
    assert not (out / "appearance.csv").exists()


def test_unreadable_video_says_ffmpegs_reason_without_its_banner(tmp_path):
    """A file that is no video: the error gives ffmpeg's own reason in a line, not its build
    banner, and a hint that fits (the reader is installed here)."""
    from facepipe.errors import InputError
    from facepipe.io.footage import open_footage

    video = tmp_path / "take.mp4"
    video.write_bytes(b"not a video at all\n" * 100)
    with pytest.raises(InputError) as info:
        open_footage(video)
    text = str(info.value)
    assert "cannot open the video" in text and "configuration:" not in text and "ffmpeg version" not in text
    assert len(text.splitlines()) <= 3 and "check that the file plays" in (info.value.hint or "")


def test_stream_columns_are_read_by_their_names(kit, tmp_path, capsys):
    """appearance.csv edited in another tool: its region columns in another order read the same
    Q per region; a renamed or repeated column exits 2 naming it (before, the header was not read
    and a column's values went to whichever region stood there)."""
    import shutil

    from facepipe.io.appearance_file import read_stream

    _q_and_truth(kit, "take")
    written = kit / "cls_take"
    rows = [line.split(",") for line in (written / "appearance.csv").read_text().splitlines()]
    width = len(rows[0])
    order = [0, 1] + list(range(width - 1, 1, -1))  # frame, time, then the regions reversed

    def edited(name, transform):
        folder = tmp_path / name
        shutil.copytree(written, folder)
        (folder / "appearance.csv").write_text("\n".join(",".join(transform(r)) for r in rows) + "\n")
        return folder

    _, numbers, times, q = read_stream(written)
    _, numbers2, times2, q2 = read_stream(edited("reordered", lambda r: [r[i] for i in order]))
    assert np.array_equal(numbers, numbers2) and np.array_equal(times, times2) and np.array_equal(q, q2)
    assert np.ptp(q, axis=0).max() > 0  # some region moves: a swap of columns would show
    renamed = edited("renamed", lambda r: [r[0], r[1], "brow" if r is rows[0] else r[2]] + r[3:])
    repeated = edited("repeated", lambda r: r[:3] + ([r[2]] if r is rows[0] else [r[3]]) + r[4:])
    for folder, words in ((renamed, ["missing: " + rows[0][2], "not in the classification: brow"]),
                          (repeated, ["repeated: " + rows[0][2], "missing: " + rows[0][3]])):
        assert _run("export", folder, "--format", "textures", "-o", tmp_path / f"tex_{folder.name}",
                    "-m", kit / "app.npz", "-q") == 2
        err = capsys.readouterr().err
        assert "line 1" in err and all(w in err for w in words), err
        assert not (tmp_path / f"tex_{folder.name}").exists() or not any((tmp_path / f"tex_{folder.name}").iterdir())


@pytest.mark.parametrize("old,new,message", [
    ("frames = [0, 1, 2, 3, 4]", "frames = [0, 1, 1, 3, 4]", "lists frame 1 more than once"),
    ("rest_frames = [", "rest_frames = [1, ", "rest_frames lists frame 1, a layer of region"),
    ("[0.0, -1.0, 0.0]", "[0.0, -2.0, 0.0]", "is not a rotation"),   # scaled
    ("[0.0, -1.0, 0.0]", "[0.0, 1.0, 0.0]", "determinant -1"),       # mirrored
])
def test_contradictory_examples_or_camera_pose_exit_2(kit, tmp_path, capsys, old, new, message):
    """A layer given twice, a rest frame that is a region's layer, or a camera_rotation that is
    no rotation: exit 2 by name (before, the first two built silently — a layer repeated, a region
    counted at rest in its own example — and the last said a template left the image)."""
    cfg = _edited_config(kit, tmp_path, old, new)
    assert _run("appearance", "build", cfg, "-o", tmp_path / "x.npz", "-q") == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()
