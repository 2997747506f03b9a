"""Edits over a take: the easing maths, EDITS.json, the edit history, and replay --edits."""

import json

import numpy as np
import pytest

from facepipe.core.edits import HandleEdit, apply_edits, edit_offsets, edit_weight, smoothstep
from facepipe.editor.edits_model import EditHistory
from facepipe.errors import InputError
from facepipe.io.edits_file import edits_from_data, edits_to_data, read_edits, write_edits
from tests.conftest import run_cli

NAMES = ["A", "B", "C"]


def test_smoothstep_ends_and_slopes():
    x = np.linspace(0, 1, 101)
    y = smoothstep(x)
    assert y[0] == 0 and y[-1] == 1 and np.all(np.diff(y) > 0)
    np.testing.assert_allclose(y + y[::-1], 1.0, atol=1e-15)  # point-symmetric about (½, ½)
    h = 1e-6  # zero slope at both ends: no jump in velocity where an edit starts or ends
    assert smoothstep(h) / h < 1e-5 and (1 - smoothstep(1 - h)) / h < 1e-5
    assert smoothstep(-3) == 0 and smoothstep(7) == 1


def test_edit_weight_keys_and_eases():
    edit = HandleEdit(frame=20, offsets={0: (1, 0, 0)}, ease_in=10, ease_out=4)
    frames = np.array([5, 10, 15, 20, 22, 24, 30])
    w = edit_weight(edit, frames)
    # by hand: 3x² − 2x³ at x = (10 − (20 − f)) / 10 before the key, x = (4 − (f − 20)) / 4 after
    np.testing.assert_allclose(w, [0, 0, 0.5, 1, 0.5, 0, 0], atol=1e-15)
    step = HandleEdit(frame=20, offsets={0: (1, 0, 0)})
    np.testing.assert_array_equal(edit_weight(step, np.array([19, 20, 21])), [0, 1, 0])


def test_offsets_add_and_apply():
    a = HandleEdit(10, {0: (1.0, 2.0, 3.0)}, 4, 4)
    b = HandleEdit(12, {0: (0.5, 0.0, 0.0), 2: (0.0, -1.0, 0.0)}, 2, 6)
    frames = np.arange(0, 25)
    both = edit_offsets([a, b], frames, 3)
    np.testing.assert_allclose(both, edit_offsets([a], frames, 3) + edit_offsets([b], frames, 3))
    assert not both[:, 1].any()  # an untouched handle stays
    np.testing.assert_allclose(both[10, 0], [1.0 + 0.5 * smoothstep(0.0), 2.0, 3.0])
    head = np.random.default_rng(0).normal(size=(25, 3, 3))
    np.testing.assert_allclose(apply_edits(head, frames, [a, b]) - head, both)
    assert apply_edits(head, frames, []) is head


def test_edits_file_round_trip(tmp_path):
    edits = [HandleEdit(3.0, {1: (0.1, 0.2, 0.3)}, 5.0, 2.0), HandleEdit(7.0, {0: (0.0, 0.0, -1.0)}, 0.0, 0.0)]
    path = tmp_path / "edits.json"
    write_edits(path, edits, NAMES, "cm")
    assert read_edits(path, NAMES, "cm") == edits
    assert json.loads(path.read_text())["edits"][0]["offsets"] == {"B": [0.1, 0.2, 0.3]}
    assert not list(tmp_path.glob(".*part*"))  # written through a temporary name


@pytest.mark.parametrize("change, words", [
    (lambda d: d.update(format="other"), "not an edits file"),
    (lambda d: d.update(version=9), "version 9"),
    (lambda d: d.update(units="mm"), "in 'mm'"),
    (lambda d: d.update(edits={}), "must be a list"),
    (lambda d: d["edits"][0]["offsets"].update(Z=[0, 0, 0]), "handle 'Z'"),
    (lambda d: d["edits"][0]["offsets"].update(A=[0, 0]), "write [dx, dy, dz]"),
    (lambda d: d["edits"][0]["offsets"].update(A=[0, "1", 0]), "finite number"),
    (lambda d: d["edits"][0]["offsets"].update(A=[0, float("nan"), 0]), "finite number"),
    (lambda d: d["edits"][0].update(ease_in=-1), "at least 0"),
    (lambda d: d["edits"][0].update(frame=True), "finite number"),
    (lambda d: d["edits"][0].pop("frame"), "no \"frame\""),
    (lambda d: d["edits"][0].update(weight=1), "unknown keys"),
])
def test_malformed_edits_are_refused(change, words):
    data = edits_to_data([HandleEdit(3.0, {0: (0.1, 0.2, 0.3)}, 1.0, 1.0)], NAMES, "cm")
    change(data)
    with pytest.raises(InputError, match="edit") as exc:
        edits_from_data(data, NAMES, "e.json", units="cm")
    assert words in str(exc.value) and "e.json" in str(exc.value)


def test_unreadable_json_names_the_line(tmp_path):
    path = tmp_path / "bad.json"
    path.write_text('{\n  "format": "facepipe-edits",\n  oops\n}')
    with pytest.raises(InputError, match="line 3"):
        read_edits(path, NAMES)


def test_history_merges_undoes_and_redoes():
    history = EditHistory()
    history.add_offset(5, 0, (1, 0, 0), 2, 2)
    history.add_offset(5, 0, (0, 1, 0), 2, 2)  # the same key and easing: one edit, offsets summed
    history.add_offset(5, 1, (0, 0, 1), 2, 2)
    history.add_offset(5, 0, (1, 1, 1), 0, 0)  # other easing: its own edit
    assert len(history.edits) == 2
    assert history.edits[0].offsets == {0: (1.0, 1.0, 0.0), 1: (0.0, 0.0, 1.0)}
    history.undo()
    history.undo()
    assert history.edits[0].offsets == {0: (1.0, 1.0, 0.0)} and history.can_redo
    history.redo()
    assert history.edits[0].offsets[1] == (0.0, 0.0, 1.0)
    history.add_offset(9, 2, (1, 1, 1), 0, 0)
    assert not history.can_redo  # a new change drops what could be redone
    while history.undo():
        pass
    assert history.edits == []


def test_replay_refuses_malformed_edits(rig, tmp_path):
    bad = tmp_path / "edits.json"
    bad.write_text(json.dumps({"format": "facepipe-edits", "version": 1, "edits": [{"frame": 1, "offsets": {}}]}))
    take = tmp_path / "take.csv"
    take.write_text("frame,time\n1,0.0\n")
    code = run_cli("replay", take, "-m", rig.models["wpsd"], "-o", tmp_path / "out", "--edits", bad, "-q")
    assert code == 2
