"""Evaluation against truth: frames matched by number or by time, and errors in head space."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facepipe.errors import InputError
from facepipe.pipeline.evaluate import frame_errors, match_frames, to_head_space
from tests.conftest import run_cli as run


def test_frames_matched_by_number_else_by_time():
    report = {}
    assert match_frames(np.array([3, 4]), np.arange(6), report=report).tolist() == [3, 4]
    assert report["frames_matched_by"] == "number"
    # a tracker counts from 1, the truth from 0: the times agree
    index = match_frames(np.arange(1, 6), np.arange(5), "t.npz", np.arange(5) / 30.0, np.arange(5) / 30.0 + 0.002,
                         report)
    assert index.tolist() == [0, 1, 2, 3, 4] and report["frames_matched_by"] == "time"
    # the truth in another order, by time
    assert match_frames(np.array([7, 9]), np.array([2, 1, 0]), "", np.array([0.0, 2 / 30]),
                        np.array([2, 1, 0]) / 30.0).tolist() == [2, 0]
    with pytest.raises(InputError, match="no frame 5"):  # numbers differ and no times
        match_frames(np.arange(1, 6), np.arange(5), "t.npz")
    with pytest.raises(InputError, match="no frame 5"):  # a time half a frame off is no frame of the truth
        match_frames(np.arange(1, 6), np.arange(5), "t.npz", np.arange(5) / 30.0 + 0.5 / 30, np.arange(5) / 30.0)


def test_head_space_errors_undo_each_sides_own_motion():
    rng = np.random.default_rng(3)
    T, V = 5, 40
    head = rng.normal(size=(T, V, 3))
    truth_head = head + 0.01 * rng.normal(size=(T, V, 3))
    R1, R2 = Rotation.random(T, random_state=1).as_matrix(), Rotation.random(T, random_state=2).as_matrix()
    t1, t2 = rng.normal(size=(T, 3)), rng.normal(size=(T, 3))
    moved = np.einsum("tij,tvj->tvi", R1, head) + t1[:, None]
    truth_moved = np.einsum("tij,tvj->tvi", R2, truth_head) + t2[:, None]
    assert np.allclose(to_head_space(moved, R1, t1), head)
    direct = frame_errors(head, truth_head)
    both = frame_errors(moved, truth_moved, pose=(R1, t1), truth_pose=(R2, t2))
    assert np.allclose(direct, both)
    assert not np.allclose(frame_errors(moved, truth_moved)[0], direct[0])


def test_eval_of_a_replay_against_a_truth_in_another_space_and_numbering(tmp_path):
    """The replay against a truth whose head moves elsewhere and whose frames count from 1 more:
    head space and time give the errors of the replay against its own truth."""
    rig = tmp_path / "rig"
    assert run("sample", rig, "--vertices", 2000, "--frames", 12, "-q") == 0
    assert run("bake", rig / "sample.toml", "--no-tune", "-o", tmp_path / "model.npz", "-q") == 0
    assert run("replay", rig / "take.csv", "-m", tmp_path / "model.npz", "-o", tmp_path / "out", "-q",
               "--backend", "numpy") == 0
    assert run("eval", tmp_path / "out", "--truth", rig / "take_truth.npz", "-q") == 0
    plain = json.loads((tmp_path / "out" / "eval.json").read_text())
    assert plain["space"] == "take" and plain["frames_matched_by"] == "number"

    truth = dict(np.load(rig / "take_truth.npz"))
    T = len(truth["positions"])
    R = Rotation.from_rotvec(np.linspace([0, 0.1, 0], [0.2, -0.3, 0.1], T)).as_matrix()
    t = np.linspace([1.0, 2.0, 3.0], [4.0, -2.0, 0.5], T)
    replay = json.loads((tmp_path / "out" / "replay.json").read_text())
    other = {"positions": np.einsum("tij,tvj->tvi", R, truth["positions"]) + t[:, None],
             "frame": np.asarray(truth["frame"]) + 100, "time": np.asarray(replay["times"]),
             "rotation": R, "translation": t}
    np.savez(tmp_path / "other.npz", **other)
    assert run("eval", tmp_path / "out", "--truth", tmp_path / "other.npz", "--space", "head", "-q") == 0
    moved = json.loads((tmp_path / "out" / "eval.json").read_text())
    assert moved["space"] == "head" and moved["frames_matched_by"] == "time"
    # (head space also takes out the replay's own estimate of its head's pose, here near the identity: 1e-5 cm)
    assert np.allclose(moved["final"]["per_frame_rms"], plain["final"]["per_frame_rms"], rtol=1e-3, atol=1e-5)
    # without the truth's pose there is no head space to compare in
    del other["rotation"]
    np.savez(tmp_path / "no_pose.npz", **other)
    assert run("eval", tmp_path / "out", "--truth", tmp_path / "no_pose.npz", "--space", "head", "-q") == 2
