"""What a new user meets in the first hour: outputs checked before any work, replay folders that
find their model from anywhere, readable refusals of wrong files, no litter after an interrupt,
honest progress and counts, units on printed numbers."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT, run_cli as run


@pytest.fixture(scope="module")
def kit(tmp_path_factory):
    """A small sample rig, fitted with the config's values, baked and replayed (paths relative to
    the rig's parent, as a user typing them there would give them)."""
    d = tmp_path_factory.mktemp("first_hour")
    cwd = os.getcwd()
    os.chdir(d)
    try:
        assert run("sample", "rig", "--vertices", 2000, "--frames", 24, "--examples", 6, "-q") == 0
        assert run("bake", "rig/sample.toml", "--no-tune", "-o", "model.npz", "-q") == 0
        assert run("replay", "rig/take.csv", "-m", "model.npz", "-o", "out", "--backend", "numpy", "-q") == 0
    finally:
        os.chdir(cwd)
    return d


def test_check_output_path_refuses_what_cannot_be_written(tmp_path, monkeypatch):
    from facepipe.errors import InputError
    from facepipe.io.outputs import check_output_path

    afile = tmp_path / "afile"
    afile.write_text("x")
    for kind in ("file", "folder", "either"):
        with pytest.raises(InputError, match="afile is a file, not a folder"):
            check_output_path(afile / "deeper" / "out", kind=kind)
    with pytest.raises(InputError, match="is a file, not a folder"):
        check_output_path(afile, kind="folder")
    with pytest.raises(InputError, match="is a folder"):
        check_output_path(tmp_path, kind="file")
    assert check_output_path(tmp_path / "new" / "x.npz") == tmp_path / "new" / "x.npz"
    # a folder without write permission (tested through os.access: root may write anywhere)
    locked = tmp_path / "locked"
    locked.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p) == locked else real(p, mode))
    with pytest.raises(InputError, match="not writable"):
        check_output_path(locked / "sub" / "x.npz")
    with pytest.raises(InputError, match="no permission"):
        check_output_path(locked, kind="folder")


@pytest.mark.parametrize("command", [
    ["replay", "{rig}/take.csv", "-m", "{model}", "-o", "{bad}"],
    ["sample", "{bad}"],
    ["fit", "{rig}/sample.toml", "-o", "{bad}/fit.npz"],
    ["bake", "{rig}/sample.toml", "-o", "{bad}/model.npz"],
    ["export", "{out}", "--format", "obj", "-o", "{bad}"],
    ["export", "{out}", "--format", "exr", "-o", "{bad}"],
    ["export", "{out}", "--format", "usd", "-o", "{bad}/take.usdc"],
    ["preview", "{out}", "-o", "{bad}/preview.png"],
])
def test_an_output_under_a_file_stops_before_any_work(kit, tmp_path, capsys, monkeypatch, command):
    (tmp_path / "afile").write_text("not a folder")
    bad = tmp_path / "afile" / "out"
    # work started before the check would be an internal error (exit 1), not exit 2
    import facepipe.cli.fitting
    import facepipe.io.model_file
    import facepipe.io.replay_folder

    def no_work(*args, **kwargs):
        raise AssertionError("work started before the output was checked")

    monkeypatch.setattr(facepipe.io.model_file, "load_model", no_work)
    monkeypatch.setattr(facepipe.io.replay_folder.ReplayDir, "load_model", no_work)
    monkeypatch.setattr(facepipe.cli.fitting, "run_fit", no_work)
    monkeypatch.setattr(facepipe.cli.fitting, "fit_to_model", no_work)
    args = [a.format(rig=kit / "rig", model=kit / "model.npz", out=kit / "out", bad=bad) for a in command]
    assert run(*args, "-q") == 2
    err = capsys.readouterr().err
    assert "afile is a file, not a folder" in err and "Traceback" not in err


def test_a_full_disk_is_said_plainly_and_leaves_no_partial_file(kit, tmp_path, capsys, monkeypatch):
    """A disk that fills while positions stream out: the folder and the reason, exit 1, no
    traceback or "internal error" (nothing to report), and no partial positions.npy."""
    import errno

    from facepipe.io import npy_stream

    real_write = os.write
    calls = []

    def full(fd, data):
        calls.append(fd)
        if len(calls) > 1:  # the header goes out, the first rows do not
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(npy_stream.os, "write", full)
    out = tmp_path / "out"
    assert run("replay", kit / "rig" / "take.csv", "-m", kit / "model.npz", "-o", out, "--backend", "numpy",
               "-q") == 1
    err = capsys.readouterr().err
    assert f"error: {out}: No space left on device" in err and "-o" in err
    assert "Traceback" not in err and "internal error" not in err
    assert not list(out.glob("*positions*"))


def test_system_errors_name_the_path_and_the_fix(tmp_path):
    import errno

    from facepipe.errors import describe_system_error
    from facepipe.io.atomic import atomic_path

    with pytest.raises(OSError) as info:
        with atomic_path(tmp_path / "sub" / "x.bin") as tmp:
            tmp.write_bytes(b"123")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert info.value.filename == str(tmp_path / "sub") and not list((tmp_path / "sub").iterdir())
    with pytest.raises(OSError) as other:  # another error keeps its own (no file named)
        with atomic_path(tmp_path / "y.bin"):
            raise OSError(errno.EIO, "Input/output error")
    assert other.value.filename is None
    text = describe_system_error(PermissionError(errno.EACCES, "Permission denied", "/srv/out"))
    assert text.startswith("/srv/out: Permission denied") and "allowed" in text
    assert "not enough memory" in describe_system_error(MemoryError()) and "--frames" in describe_system_error(
        MemoryError())


def test_an_interrupt_as_the_temporary_file_is_made_leaves_nothing(tmp_path, monkeypatch):
    """Ctrl-C or SIGTERM arrive between bytecodes: one right after the temporary file appears (the
    moment a watcher sees it) still finds its name and removes it; the file gets the usual mode."""
    import facepipe.io.atomic as atomic

    real_close = atomic.os.close

    def interrupted(fd):
        real_close(fd)
        raise KeyboardInterrupt

    monkeypatch.setattr(atomic.os, "close", interrupted)
    with pytest.raises(KeyboardInterrupt):
        with atomic.atomic_path(tmp_path / "positions.npy"):
            pass
    assert not list(tmp_path.iterdir())
    monkeypatch.setattr(atomic.os, "close", real_close)
    umask = os.umask(0o022)
    try:
        with atomic.atomic_path(tmp_path / "x.bin") as tmp:
            assert tmp.name.startswith(".x.bin.") and tmp.name.endswith(".part.bin") and tmp.is_file()
            tmp.write_bytes(b"1")
    finally:
        os.umask(umask)
    assert (tmp_path / "x.bin").stat().st_mode & 0o777 == 0o644 and [p.name for p in tmp_path.iterdir()] == ["x.bin"]


def test_export_and_preview_find_the_model_from_anywhere(kit, tmp_path, monkeypatch):
    info = json.loads((kit / "out" / "replay.json").read_text())
    assert Path(info["model"]).is_absolute() and info["model_relative"] == "../model.npz"
    monkeypatch.chdir(tmp_path)  # elsewhere: the model path typed at replay time means nothing here
    assert run("export", kit / "out", "--format", "obj", "-o", tmp_path / "obj", "-q") == 0
    assert run("preview", kit / "out", "-o", tmp_path / "p.png", "-q") == 0
    # moved together with its model: found relative to the replay folder
    moved = tmp_path / "moved"
    shutil.copytree(kit / "out", moved / "out")
    shutil.copy(kit / "model.npz", moved / "model.npz")
    info_moved = dict(info, model=str(tmp_path / "gone" / "model.npz"))
    (moved / "out" / "replay.json").write_text(json.dumps(info_moved))
    assert run("export", moved / "out", "--format", "mdd", "-o", tmp_path / "a.mdd", "-q") == 0
    # an older replay: the model path relative to where replay ran, nothing else
    old = dict(info, model="model.npz")
    del old["model_relative"]
    (moved / "out" / "replay.json").write_text(json.dumps(old))
    assert run("export", moved / "out", "--format", "obj", "-o", tmp_path / "obj_old", "-q") == 0


def test_a_text_file_for_a_model_or_truth_says_what_it_should_be(kit, tmp_path, capsys):
    text = tmp_path / "model.npz"
    text.write_text("neutral.obj\nmarkers.csv\n")
    assert run("replay", kit / "rig" / "take.csv", "-m", text, "-o", tmp_path / "o", "-q") == 2
    err = capsys.readouterr().err
    assert "text file" in err and "a model file written by 'facepipe bake'" in err
    assert "pickle" not in err.lower()
    assert run("eval", kit / "out", "--truth", text, "-q") == 2
    err = capsys.readouterr().err
    assert "text file" in err and "'positions'" in err and "pickle" not in err.lower()
    assert run("preview", kit / "out", "--truth", text, "-o", tmp_path / "p.png", "-q") == 2
    assert "pickle" not in capsys.readouterr().err.lower()


def test_replay_into_an_earlier_replay_needs_force_and_clears_stale_results(kit, tmp_path, capsys):
    out = tmp_path / "out"
    common = [kit / "rig" / "take.csv", "-m", kit / "model.npz", "-o", out, "--backend", "numpy", "-q"]
    assert run("replay", *common, "--save-large-scale") == 0
    assert run("eval", out, "--truth", kit / "rig" / "take_truth.npz", "-q") == 0
    before = (out / "positions.npy").stat().st_mtime_ns
    assert run("replay", *common) == 2
    assert "earlier replay" in capsys.readouterr().err and (out / "positions.npy").stat().st_mtime_ns == before
    assert run("replay", *common, "--force") == 0
    assert (out / "positions.npy").is_file() and (out / "replay.json").is_file()
    assert not (out / "eval.json").exists() and not (out / "large_scale.npy").exists()


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_during_replay_leaves_no_partial_files(kit, tmp_path, signum):
    long_rig = tmp_path / "rig"
    assert run("sample", long_rig, "--vertices", 2000, "--frames", 1500, "--examples", 6, "-q") == 0
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "facepipe", "replay", str(long_rig / "take.csv"), "-m",
                             str(kit / "model.npz"), "-o", str(out), "--backend", "numpy", "--chunk", "1", "-q"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            # a shell's background job inherits SIGINT ignored; a terminal's Ctrl-C is not
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 300
    parts = []
    while time.monotonic() < deadline and proc.poll() is None:
        parts = list(out.glob(".*.part*")) if out.is_dir() else []
        if parts:
            break
        time.sleep(0.02)
    assert parts, "the replay finished before it was caught writing"
    # without --save-large-scale no large-scale file is begun
    assert all("large_scale" not in p.name for p in parts), parts
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signum, err.decode()  # 143 for SIGTERM, 130 for Ctrl-C
    assert b"interrupted" in err
    assert not list(out.glob(".*.part*")) and not (out / "positions.npy").exists()


def test_export_resume_counts_written_and_kept(kit, tmp_path, capsys):
    dest = tmp_path / "obj"
    assert run("export", kit / "out", "--format", "obj", "-o", dest) == 0
    files = sorted(dest.glob("frame_*.obj"))
    assert f"wrote {len(files)} OBJ files" in capsys.readouterr().out
    for f in files[10:]:  # as an interrupted export leaves it
        f.unlink()
    assert run("export", kit / "out", "--format", "obj", "-o", dest, "--resume") == 0
    out = capsys.readouterr().out
    assert f"wrote {len(files) - 10} OBJ files" in out and "kept 10 already there" in out


def test_steps_report_progress(kit, tmp_path):
    from facepipe.mocap.cleaning import CLEAN_STEPS, clean_take
    from facepipe.pipeline.fit import FIT_STAGES, fit_config

    truth = np.load(kit / "rig" / "take_truth.npz")
    from facepipe.io.model_file import load_model

    model = load_model(kit / "model.npz")
    handles = truth["positions"][:, model.handle_vertices].astype(np.float64)
    rest = model.rest[model.handle_vertices].astype(np.float64)
    seen = []
    clean_take(handles + 0.001 * np.random.default_rng(0).standard_normal(handles.shape), rest,
               np.zeros((0,) + rest.shape), np.ones(len(rest), bool), np.arange(len(handles)) / 30.0,
               progress=seen.append)
    assert tuple(seen) == CLEAN_STEPS
    stages = []
    fit_config(kit / "rig" / "sample.toml", stage=stages.append)
    assert tuple(stages) == FIT_STAGES


def test_progress_bars_of_fit_bake_and_replay(kit, tmp_path, capsys):
    assert run("fit", kit / "rig" / "sample.toml", "--no-tune", "-o", tmp_path / "fit.npz") == 0
    err = capsys.readouterr().err
    assert err.count("fit: 8/8 steps") == 1 and "greedy basis" in err  # "done" drawn once
    assert run("bake", tmp_path / "fit.npz", "-o", tmp_path / "model.npz") == 0
    assert capsys.readouterr().err.count("bake: 2/2 steps") == 1
    assert run("replay", kit / "rig" / "take.csv", "-m", kit / "model.npz", "-o", tmp_path / "o", "--backend",
               "numpy") == 0
    captured = capsys.readouterr()
    # cleaning has its bar, closed before the frame bar opens on the same line (in a log: no
    # cursor-up escape, no second "done")
    assert captured.err.count("clean: 4/4 steps") == 1
    assert captured.err.index("clean: 4/4 steps") < captured.err.index("replay:")
    assert "\x1b[A" not in captured.err
    assert "cm translation" in captured.out and "noise σ ≈" in captured.out
    assert captured.out.split("noise σ ≈")[1].split()[1] == "cm"


def test_quiet_hides_every_bar(kit, tmp_path, capsys):
    assert run("replay", kit / "rig" / "take.csv", "-m", kit / "model.npz", "-o", tmp_path / "o", "--backend",
               "numpy", "-q") == 0
    assert capsys.readouterr().err == ""


def test_units_on_eval_and_clipped_colour_scales(kit, tmp_path, capsys):
    assert run("eval", kit / "out", "--truth", kit / "rig" / "take_truth.npz") == 0
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("final:")][0]
    assert line.count(" cm") == 4, line
    from facepipe.cli.preview import preview_replay

    s = preview_replay(kit / "out", None, tmp_path / "p.png", truth_path=kit / "rig" / "take_truth.npz")
    largest = max(s["max"]["final"] + s["max"]["large"])
    assert s["color_clipped"] == (largest > s["color_max"])


def test_error_axis_is_scaled_to_the_data():
    from facepipe.cli.preview import error_axis

    log, bottom, below = error_axis([0.02, 0.01, 0.004, 1e-17, 0.0])
    assert log and 1e-4 < bottom < 0.004 and below == 2
    assert error_axis([0.02, 0.01]) == (False, None, 0)


def test_bars_redraw_rarely_in_a_log():
    """A bar writing to a file or pipe (a batch job's log) redraws every LOG_REFRESH_SECONDS, not
    ten times a second; on a terminal as tqdm does; first and last lines are written either way."""
    import io

    from facepipe.cli.commands import Reporter
    from facepipe.cli.progress import LOG_REFRESH_SECONDS, StageBar, refresh_seconds

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    assert refresh_seconds(io.StringIO()) == LOG_REFRESH_SECONDS >= 5
    assert refresh_seconds(Terminal()) == 0.1
    assert refresh_seconds(object()) == LOG_REFRESH_SECONDS  # no isatty at all
    log = io.StringIO()
    with _stderr(log):
        with Reporter().bar(100, desc="replay") as bar:
            assert bar.mininterval == LOG_REFRESH_SECONDS
            for _ in range(100):
                bar.update(1)
        with StageBar(2, "fit") as steps:
            steps.step("one")
            steps.step("two")
    text = log.getvalue()
    assert text.count("replay:") == 2 and "100/100" in text  # opened and closed, nothing between
    assert "fit: 2/2 steps" in text


def _stderr(stream):
    import contextlib

    return contextlib.redirect_stderr(stream)
