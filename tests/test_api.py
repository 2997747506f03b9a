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


def test_add_details_gives_the_command_lines_cache_take(baked):
    """The sample's smooth cache (its truth without the wrinkles) as arrays: the command line's
    `replay CACHE` (the take way) to float32, the same bands; in mm with units="mm"."""
    from facepipe.io.point_caches import read_mdd

    model = facepipe.load_model(baked / "model.npz")
    cache = baked / "rig" / "take_smooth.mdd"
    assert run("replay", cache, "-m", baked / "model.npz", "-o", baked / "cache_out", "--backend", "numpy", "-q") == 0
    written = np.load(baked / "cache_out" / "positions.npy")
    frames = read_mdd(cache)[1].astype(np.float64)
    result = facepipe.add_details(model, frames)
    size = float(np.ptp(model.rest, axis=0).max())
    assert result.positions.shape == frames.shape
    np.testing.assert_allclose(result.positions, written, atol=1e-6 * size)
    report = json.loads((baked / "cache_out" / "replay.json").read_text())
    assert result.report["cache"]["bands"]["added"] == report["cache"]["bands"]["added"]
    np.testing.assert_allclose(facepipe.add_details(model, 10.0 * frames, units="mm").positions, result.positions,
                               atol=1e-6 * size)


def test_add_details_on_the_shells_surface_gives_the_marker_replay(baked):
    """The marker replay's own large scale lacks every band of the details: with them added it is
    the marker replay's face (Bickel et al.'s check); one frame alone, in rig space, likewise."""
    model = facepipe.load_model(baked / "model.npz")
    out = baked / "with_large"
    assert run("replay", baked / "rig" / "take.csv", "-m", baked / "model.npz", "-o", out, "--backend", "numpy",
               "--save-large-scale", "-q") == 0
    large = np.load(out / "large_scale.npy").astype(np.float64)
    final = np.load(out / "positions.npy").astype(np.float64)
    size = float(np.ptp(model.rest, axis=0).max())
    detail = np.abs(final - large).max()
    assert detail > 1e-3 * size
    result = facepipe.add_details(model, large)
    assert all(result.report["cache"]["bands"]["added"])
    assert np.abs(result.positions - final).max() < 1e-4 * detail  # (float32 files)
    one = facepipe.add_details(model, large[7], head_motion="remove")
    head = facepipe.add_details(model, large, head_motion="remove").positions[7]
    assert one.positions.shape == large[7].shape
    np.testing.assert_allclose(one.positions, head, atol=1e-9 * size)


def test_add_details_bad_frames_are_input_errors(baked):
    model = facepipe.load_model(baked / "model.npz")
    rest = model.rest.astype(np.float64)
    with pytest.raises(facepipe.InputError, match="vertices"):
        facepipe.add_details(model, rest[:-1])
    bad = np.repeat(rest[None], 2, axis=0)
    bad[1, 3, 0] = np.nan
    with pytest.raises(facepipe.InputError, match="NaN"):
        facepipe.add_details(model, bad)
    with pytest.raises(facepipe.InputError, match="in mm"):  # numbers in mm said to be the rig's cm
        facepipe.add_details(model, 10.0 * rest)
    with pytest.raises(facepipe.InputError, match="correspond"):
        facepipe.add_details(model, rest[np.random.default_rng(0).permutation(len(rest))])
    with pytest.raises(facepipe.InputError, match="rest_frame"):
        facepipe.add_details(model, rest, rest_frame=3)


def test_import_facepipe_stays_light():
    import subprocess
    import sys

    # listing the API (tab completion) imports nothing either
    code = "import sys, facepipe; names = dir(facepipe); print('scipy' in sys.modules, set(facepipe.__all__) <= set(names))"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout.strip() == "False True"
