"""The Python API: the same faces as the command line's replay, and clear errors."""

import json

import numpy as np
import pytest

import facepipe
from tests.conftest import run_cli as run


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    d = tmp_path_factory.mktemp("api")
    assert run("sample", d / "rig", "--vertices", 2000, "--frames", 24, "-q") == 0
    assert run("bake", d / "rig" / "sample.toml", "-o", d / "model.npz", "-q") == 0
    assert run("replay", d / "rig" / "take.csv", "-m", d / "model.npz", "-o", d / "out", "--backend", "numpy",
               "-q") == 0
    return d


def test_replay_take_gives_the_command_lines_faces(baked):
    model = facepipe.load_model(baked / "model.npz")
    take = facepipe.read_take(baked / "rig" / "take.csv", model)
    result = facepipe.replay_take(model, take)
    written = np.load(baked / "out" / "positions.npy")
    assert result.positions.shape == written.shape
    # the command line stores float32
    np.testing.assert_allclose(result.positions, written, atol=1e-5 * np.ptp(model.rest, axis=0).max())
    handles = np.load(baked / "out" / "handles.npz")
    np.testing.assert_allclose(result.handles, handles["head"], atol=1e-5)
    report = json.loads((baked / "out" / "replay.json").read_text())
    assert result.report["markers"] == report["markers"]


def test_evaluate_single_and_batched_frames_agree(baked):
    model = facepipe.load_model(baked / "model.npz")
    rest_handles = model.rest[model.handle_vertices]
    size = float(np.ptp(model.rest, axis=0).max())
    # the rest handles give the rest face (B is stored in float32)
    np.testing.assert_allclose(facepipe.evaluate(model, rest_handles), model.rest, atol=1e-6 * size)
    frames = rest_handles[None] + np.random.default_rng(0).normal(0, 0.01, (3,) + rest_handles.shape)
    batch = facepipe.evaluate(model, frames)
    np.testing.assert_allclose(batch[1], facepipe.evaluate(model, frames[1]), atol=1e-6 * size)


def test_bad_handle_arrays_are_input_errors(baked):
    model = facepipe.load_model(baked / "model.npz")
    with pytest.raises(facepipe.InputError, match="handles"):
        facepipe.evaluate(model, np.zeros((2, 5, 3)))
    bad = np.repeat(model.rest[model.handle_vertices][None], 2, axis=0)
    bad[1, 0, 0] = np.nan
    with pytest.raises(facepipe.InputError, match="frame 1"):
        facepipe.evaluate(model, bad)
    with pytest.raises(AttributeError):
        facepipe.no_such_function  # noqa: B018


def test_import_facepipe_stays_light():
    import subprocess
    import sys

    # listing the API (tab completion) imports nothing either
    code = "import sys, facepipe; names = dir(facepipe); print('scipy' in sys.modules, set(facepipe.__all__) <= set(names))"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout.strip() == "False True"
