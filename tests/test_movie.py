"""``facepipe preview --movie``: every replayed frame, in order, the take's frame numbers burnt in."""

import json
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import run_cli as run
from tests.test_first_hour import kit  # noqa: F401 - the replayed sample rig (a fixture)
from tests.test_video import _replay, filmed  # noqa: F401 - a 2D take and its camera (a fixture)


def _read(path):
    import imageio.v2 as imageio

    reader = imageio.get_reader(path)
    frames = [np.asarray(f, dtype=np.float64)[..., :3] for f in reader]
    meta = reader.get_meta_data()
    reader.close()
    return frames, meta


def test_movie_of_a_3d_replay_shows_every_frame_in_order(kit, tmp_path, capsys):  # noqa: F811
    from facepipe.cli.movie import _HeadFrames, _caption
    from facepipe.io.replay_folder import ReplayDir
    from PIL import ImageFont

    movie = tmp_path / "take.mp4"
    truth = kit / "rig" / "take_truth.npz"
    assert run("preview", kit / "out", "--movie", movie, "--truth", truth, "--with-large-scale", "--size", 160) == 0
    out = capsys.readouterr()
    assert "wrote" in out.out and "movie:" in out.err and "frames 0..23" in out.out
    frames, meta = _read(movie)
    replay = ReplayDir(kit / "out")
    assert len(frames) == replay.n_frames and meta["fps"] == pytest.approx(replay.fps)
    # each decoded frame is closest to the frame composed for it (order and content), up to the codec's loss
    from facepipe.io.model_file import load_model

    panels = _HeadFrames(replay, load_model(kit / "model.npz"), 160, truth, True)
    font = ImageFont.load_default()
    for i in (0, 11, 23):
        want = _caption(panels.panels_of(i), panels.panels, int(replay.frame_numbers[i]), float(replay.times[i]),
                        "", font).astype(np.float64)
        assert want.shape == frames[i].shape
        errs = [np.abs(frames[j] - want).mean() for j in range(len(frames))]
        assert int(np.argmin(errs)) == i and errs[i] < 6.0, (i, errs[i])
    # the burnt-in caption differs between frames (their numbers and times), the panels' row of
    # a still take differs only where the face moves
    a = _caption(panels.panels_of(0), panels.panels, 0, 0.0, "", font)
    b = _caption(panels.panels_of(0), panels.panels, 17, 0.5, "", font)
    assert (a[:20] != b[:20]).any() and (a[30:] == b[30:]).all()
    # no overwrite without --force; a suffix that is no movie; all before rendering
    assert run("preview", kit / "out", "--movie", movie, "-q") == 2
    assert run("preview", kit / "out", "--movie", tmp_path / "take.avi", "-q") == 2
    assert "mp4 or *.gif" in capsys.readouterr().err
    assert run("preview", kit / "out", "--movie", tmp_path / "s.mp4", "--strip", 3, "-q") == 2
    assert "every replayed frame" in capsys.readouterr().err and not (tmp_path / "s.mp4").exists()


def test_gif_movie(kit, tmp_path):  # noqa: F811
    gif = tmp_path / "take.gif"
    assert run("preview", kit / "out", "--movie", gif, "--size", 96, "-q") == 0
    frames, _ = _read(gif)
    info = json.loads((kit / "out" / "replay.json").read_text())
    assert len(frames) == info["frames"]
    assert not list(tmp_path.glob(".*.part*"))


def test_movie_of_a_2d_take_looks_through_its_camera(filmed, tmp_path):  # noqa: F811
    from facepipe.cli.movie import render_movie
    from facepipe.io.model_file import load_model
    from facepipe.io.replay_folder import ReplayDir

    assert _replay(filmed, tmp_path / "keep") == 0
    assert run("preview", tmp_path / "keep", "--movie", tmp_path / "cam.mp4", "--size", 200, "-q") == 0
    frames, _ = _read(tmp_path / "cam.mp4")
    replay = ReplayDir(tmp_path / "keep")
    assert len(frames) == replay.n_frames
    s = render_movie(replay, load_model(filmed.root / "model.npz"), tmp_path / "cam.gif", view="camera", size=120)
    assert s["view"] == "camera" and s["first_frame"] == int(replay.frame_numbers[0]) == 1
    # the replayed face's landmarks (red dots) are drawn where the camera sees them
    red = [((f[..., 0] > 170) & (f[..., 1] < 80) & (f[..., 2] < 80)).sum() for f in frames[:5]]
    assert min(red) > 20, red
