"""Mesh caches as takes: readers (round trips through the writers), checks against the rest mesh,
the details' bands, and replays of caches (take and shell) against the marker replay they came from."""

from __future__ import annotations

import json

import numpy as np
import pytest

from facepipe.core.detail_bands import DetailBands, band_sums, banded_detail_model, bands_to_add
from facepipe.errors import InputError
from facepipe.io.mesh_write import save_obj
from facepipe.io.model_file import load_model
from facepipe.io.point_caches import read_mdd, read_pc2, write_mdd, write_pc2
from facepipe.io.replay_folder import ReplayDir
from facepipe.mocap.mesh_cache import read_mesh_cache
from facepipe.mocap.registry import mesh_cache_format
from tests.conftest import grid, ict_or_skip, run_cli


def _replay_large(rig, name="wpsd"):
    out = rig.replays[name]
    info = json.loads((out / "replay.json").read_text())
    return out, np.load(out / "large_scale.npy"), np.load(out / "positions.npy"), np.asarray(info["times"])


# ----------------------------------------------------------------------------- readers


def test_mdd_and_pc2_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    positions = rng.normal(size=(5, 7, 3)).astype(np.float32)
    times = np.arange(3, 8) / 24.0
    write_mdd(tmp_path / "a.mdd", positions, times)
    t, p = read_mdd(tmp_path / "a.mdd")
    np.testing.assert_array_equal(p, positions)
    np.testing.assert_allclose(t, times, rtol=1e-6)
    write_pc2(tmp_path / "a.pc2", positions, times, 24.0)
    start, step, p = read_pc2(tmp_path / "a.pc2")
    np.testing.assert_array_equal(p, positions)
    assert (start, step) == (3.0, 1.0)


def test_truncated_caches_are_input_errors(tmp_path):
    positions = np.zeros((3, 4, 3), np.float32)
    write_mdd(tmp_path / "a.mdd", positions, np.arange(3) / 30.0)
    write_pc2(tmp_path / "a.pc2", positions, np.arange(3) / 30.0, 30.0)
    for name in ("a.mdd", "a.pc2"):
        data = (tmp_path / name).read_bytes()
        (tmp_path / name).write_bytes(data[:-5])
    with pytest.raises(InputError, match="bytes"):
        read_mdd(tmp_path / "a.mdd")
    with pytest.raises(InputError, match="bytes"):
        read_pc2(tmp_path / "a.pc2")


def test_formats_are_recognised(tmp_path):
    (tmp_path / "seq").mkdir()
    assert mesh_cache_format(tmp_path / "x.usdc").name == "usd"
    assert mesh_cache_format(tmp_path / "x.mdd").name == "mdd"
    assert mesh_cache_format(tmp_path / "x.pc2").name == "pc2"
    assert mesh_cache_format(tmp_path / "frame_%04d.obj").name == "obj-sequence"
    assert mesh_cache_format(tmp_path / "take.csv") is None
    assert mesh_cache_format(tmp_path / "seq") is None  # an empty folder is no sequence


# ----------------------------------------------------------------------------- bands


def test_bands_sum_to_the_field_and_keep_constants(sheet):
    V, F = sheet
    bands = DetailBands(V, F, spacing=2.0)
    rng = np.random.default_rng(1)
    D = rng.normal(size=(2, len(V), 3))
    parts = bands.split(D)
    assert len(parts) == bands.n_bands
    np.testing.assert_allclose(sum(parts), D, atol=1e-12)
    # (M + ℓ²K) c = M c for a constant field (K's rows sum to zero): a constant passes every low-pass
    const = np.broadcast_to(np.array([0.3, -1.0, 2.0]), (1, len(V), 3))
    np.testing.assert_allclose(bands.lowpass(2, const), const, atol=1e-10)
    # combine telescopes the bands: the same as weighting the split
    w = np.array([1, 1, 0.5, 0.5, 0, 0, 0, 1.0])
    np.testing.assert_allclose(bands.combine(D, w), sum(c * p for c, p in zip(w, parts)), atol=1e-10)
    np.testing.assert_allclose(bands.combine(D, np.full(bands.n_bands, 0.7)), 0.7 * D)
    # a low-pass smooths: the finest band holds most of white noise, little of a smooth wave
    wave = np.sin(V[:, :1] / 3.0) * np.ones((1, 3))
    fine_noise = np.linalg.norm(parts[0]) / np.linalg.norm(D)
    fine_wave = np.linalg.norm(bands.split(wave[None])[0]) / np.linalg.norm(wave)
    assert fine_wave < 0.05 < fine_noise


def test_single_precision_bands_match_the_double_precision_reference():
    """The replay's band filter (single-precision factors, float32 details in and out) against the
    double-precision one, the reference: within 1e-5 of the details' amplitude (float32's
    resolution is 6e-8; the single-precision Cholesky loses a little more to the condition of
    M + ℓ²K). The same fields, float64 in, keep float64 through the single factor."""
    V, F = grid(40, 36)
    reference = DetailBands(V, F, spacing=2.0)
    fast = DetailBands(V, F, spacing=2.0, single=True)
    rng = np.random.default_rng(3)
    wave = np.sin(V[:, :1] / 2.5) * np.cos(V[:, 1:2] / 1.7) * np.array([0.2, -0.1, 0.3])
    D = (rng.normal(scale=0.05, size=(4, len(V), 3)) + wave).astype(np.float32)
    amplitude = float(np.abs(D).max())
    for w in (np.array([1, 1, 1, 0, 0, 0, 0, 0.0]), np.array([1, 1, 0.5, 0.5, 0, 0, 0, 1.0])):
        expected = reference.combine(D.astype(np.float64), w)
        got = fast.combine(D, w)
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, expected, atol=1e-5 * amplitude, rtol=0)
        assert fast.combine(D.astype(np.float64), w).dtype == np.float64
    for level in range(len(fast.wavelengths)):
        np.testing.assert_allclose(fast.lowpass(level, D), reference.lowpass(level, D), atol=1e-5 * amplitude, rtol=0)
    reference.close()
    fast.close()


def test_single_precision_factor_solves_a_known_system():
    """CholeskyFactor(single=True) on a system with a known solution: float32 out where PARDISO took
    it, the exact solution to float32 accuracy (the other backends stay in float64)."""
    import scipy.sparse as sp

    from facepipe.core.shell import CholeskyFactor

    n = 500
    lap = sp.diags([-np.ones(n - 1), 2.05 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1], format="csr")
    x = np.random.default_rng(4).normal(size=(n, 6))
    factor = CholeskyFactor(lap, single=True)
    got = factor.solve(lap @ x)
    assert got.dtype == (np.float32 if factor.single else np.float64)
    assert factor.single == (factor.backend == "pardiso")
    np.testing.assert_allclose(got, x, atol=1e-4 * np.abs(x).max(), rtol=0)
    factor.close()


def test_bands_to_add():
    rng = np.random.default_rng(2)
    V, F = grid(20, 18)
    bands = DetailBands(V, F, spacing=2.0)
    D = bands.split(rng.normal(size=(1, len(V), 3)))
    # a cache the shell made (no deviation) gets every band; one that has the details gets none
    assert bands_to_add(band_sums(D, [np.zeros_like(d) for d in D]))["added"].all()
    assert not bands_to_add(band_sums(D, D))["added"].any()
    # a cache with only the coarse bands of its own: the fine ones are added
    own = [np.zeros_like(d) for d in D[:3]] + D[3:]
    assert bands_to_add(band_sums(D, own))["added"].tolist() == [1.0] * 3 + [0.0] * (len(D) - 3)


def test_paired_band_sums_equal_the_bands_split_whole():
    """The streamed sums of two fields' bands (low-passed together, two bands held at a time) equal
    band_sums of their full splits, double and single precision."""
    rng = np.random.default_rng(4)
    V, F = grid(20, 18)
    for single, dtype, tol in ((False, np.float64, 1e-12), (True, np.float32, 1e-5)):
        bands = DetailBands(V, F, spacing=2.0, single=single)
        D = rng.normal(size=(3, len(V), 3)).astype(dtype)
        E = (0.5 * D + rng.normal(size=D.shape)).astype(dtype)
        whole = band_sums(bands.split(D), bands.split(E))
        np.testing.assert_allclose(bands.paired_band_sums(D, E), whole, rtol=tol, atol=tol * np.abs(whole).max())
        bands.close()


def _detail_model(method, V, rng, P=5, F=12):
    """A fitted PSD or WPSD detail model on the mesh V (rest pose first, its details zero)."""
    import scipy.sparse as sp

    from facepipe.core.psd import fit_details

    features = np.vstack([np.zeros(F), rng.normal(scale=0.2, size=(P - 1, F))])
    details = rng.normal(scale=0.05, size=(P, len(V), 3))
    details[0] = 0.0
    alpha = None
    if method == "wpsd":  # every vertex weighs a few edges, the weights varying over the mesh
        rows = np.repeat(np.arange(len(V)), 3)
        cols = (rows + np.tile([0, 4, 7], len(V))) % F
        w = 0.5 + 0.5 * np.sin(V[rows, 0] / 2.0 + cols) ** 2
        alpha = sp.csr_matrix((w, (rows, cols)), shape=(len(V), F))
    return fit_details(method, features, details, list(range(P)), "interpolate", alpha), features


@pytest.mark.parametrize("method", ["psd", "wpsd"])
def test_banded_detail_model_filters_the_examples(method):
    """The model refitted to its examples' chosen bands gives, at every basis pose, exactly those
    bands of the original details (world vectors in the frames used), none at the rest pose;
    with every band added it is the original model; for PSD (one kernel for all vertices) the
    filter commutes with the interpolation, so any pose's details are the original's bands."""
    from facepipe.core.tangent_frames import frame_neighbors, local_frames, to_world

    V, F = grid(24, 20)
    rng = np.random.default_rng(5)
    model, features = _detail_model(method, V, rng)
    frames = local_frames(V, F, frame_neighbors(F, len(V)))
    bands = DetailBands(V, F, spacing=1.5)
    same = banded_detail_model(bands, model, frames, np.ones(bands.n_bands))
    np.testing.assert_allclose(same.weights, model.weights, atol=1e-8)
    np.testing.assert_allclose(same.const, model.const, atol=1e-8)
    added = np.array([1, 1, 1, 0, 0, 0, 0, 0.0])
    banded = banded_detail_model(bands, model, frames, added)
    poses = np.vstack([features, rng.normal(scale=0.2, size=(3, features.shape[1]))])
    world = to_world(frames, model.evaluate(poses))
    expected = bands.combine(world, added)
    got = to_world(frames, banded.evaluate(poses))
    amplitude = float(np.abs(expected).max())
    np.testing.assert_allclose(got[:len(features)], expected[:len(features)], atol=1e-9 * amplitude)
    assert np.abs(got[0]).max() < 1e-12  # the rest pose gets no details
    between = np.abs(got[len(features):] - expected[len(features):]).max() / amplitude
    if method == "psd":
        assert between < 1e-9
    else:  # the per-vertex kernel: close (far closer than the unfiltered details are)
        assert between < 0.5 * np.abs(world - expected).max() / amplitude
    bands.close()


# ----------------------------------------------------------------------------- replays


def test_large_scale_cache_replays_to_the_marker_replay(rig, tmp_path):
    out, large, final, times = _replay_large(rig)
    write_mdd(tmp_path / "large.mdd", large, times)
    size = float(np.ptp(final, axis=(0, 1)).max())
    assert run_cli("replay", tmp_path / "large.mdd", "-m", rig.models["wpsd"], "-o", tmp_path / "take",
                   "--cache-fps", 24, "-q") == 0
    take = np.load(tmp_path / "take" / "positions.npy")
    assert np.abs(take - final).max() < 1e-5 * size
    report = json.loads((tmp_path / "take" / "replay.json").read_text())
    assert report["cache"]["bands"]["added_fraction"] == pytest.approx(1.0)
    assert report["frame_numbers"] == json.loads((out / "replay.json").read_text())["frame_numbers"]
    # the cache's surface is the large scale: read back from the cache, not written again
    assert not (tmp_path / "take" / "large_scale.npy").exists()
    np.testing.assert_allclose(ReplayDir(tmp_path / "take").layer("large")[:], large, atol=1e-6 * size)
    # shell: the handle vertices replayed as markers give the same face
    assert run_cli("replay", tmp_path / "large.mdd", "-m", rig.models["wpsd"], "-o", tmp_path / "shell",
                   "--large-scale", "shell", "--backend", "numpy", "-q") == 0
    assert np.abs(np.load(tmp_path / "shell" / "positions.npy") - final).max() < 1e-4 * size


def test_usd_and_obj_sequence_match_mdd(rig, tmp_path):
    from facepipe.io.usd_file import write_usd

    _, large, final, times = _replay_large(rig)
    model = load_model(rig.models["wpsd"])
    write_mdd(tmp_path / "large.mdd", large, times)
    write_usd(tmp_path / "large.usdc", model.mesh(), large, times, 24.0, units="cm")
    (tmp_path / "seq").mkdir()
    mesh = model.mesh()
    for k, frame in enumerate(large):
        save_obj(tmp_path / "seq" / f"frame_{k + 1:04d}.obj", mesh, frame)
    runs = {}
    for name, path in (("mdd", tmp_path / "large.mdd"), ("usd", tmp_path / "large.usdc"),
                       ("obj", tmp_path / "seq")):
        assert run_cli("replay", path, "-m", rig.models["wpsd"], "-o", tmp_path / name, "-q") == 0
        runs[name] = np.load(tmp_path / name / "positions.npy")
    np.testing.assert_array_equal(runs["usd"], runs["mdd"])
    assert np.abs(runs["obj"] - runs["mdd"]).max() < 1e-4
    cache, _ = read_mesh_cache(tmp_path / "large.usdc", model.rest, units="cm")
    assert cache.fps == 24.0 and cache.units == "cm"
    np.testing.assert_allclose(cache.times, times, atol=1e-6)


def test_bad_caches_exit_2(rig, tmp_path, capsys):
    _, large, _, times = _replay_large(rig)
    model = rig.models["wpsd"]

    def replay(path, *extra):
        code = run_cli("replay", path, "-m", model, "-o", tmp_path / "out", "-q", "--force", *extra)
        return code, capsys.readouterr().err

    write_mdd(tmp_path / "fewer.mdd", large[:, :-3], times)
    code, err = replay(tmp_path / "fewer.mdd")
    assert code == 2 and "vertices per frame" in err
    nan = large.copy()
    nan[2, 17] = np.nan
    with open(tmp_path / "nan.mdd", "wb") as fh:  # the writer refuses NaN: write the bytes directly
        fh.write(np.array([len(nan), nan.shape[1]], ">i4").tobytes() + times.astype(">f4").tobytes()
                 + nan.astype(">f4").tobytes())
    code, err = replay(tmp_path / "nan.mdd")
    assert code == 2 and "NaN" in err and "first vertex 17" in err
    write_mdd(tmp_path / "mm.mdd", large * 10, times)
    code, err = replay(tmp_path / "mm.mdd")
    assert code == 2 and "scale mismatch" in err and "--take-units mm" in err
    assert replay(tmp_path / "mm.mdd", "--take-units", "mm")[0] == 0
    order = np.random.default_rng(0).permutation(large.shape[1])
    write_mdd(tmp_path / "order.mdd", large[:, order], times)
    code, err = replay(tmp_path / "order.mdd")
    assert code == 2 and "vertex by vertex" in err
    code, err = replay(tmp_path / "fewer.mdd", "--rest-frame", 99)
    assert code == 2
    (tmp_path / "seq").mkdir()
    mesh = load_model(model).mesh()
    for k in (1, 2, 4):
        save_obj(tmp_path / "seq" / f"frame_{k:04d}.obj", mesh, large[0])
    code, err = replay(tmp_path / "seq")
    assert code == 2 and "frame 3 of the OBJ sequence is missing" in err
    code, err = replay(tmp_path / "mm.mdd", "--large-scale", "take", "--take-units", "mm", "--rest-frame", 11)
    assert code == 0


def test_sample_writes_the_smooth_cache(tmp_path):
    from facepipe.sample_rig import make_sample_arrays, write_sample_rig

    info = write_sample_rig(tmp_path, n_vertices=3000, n_examples=6, n_frames=5)
    rig = make_sample_arrays(3000, n_examples=6, n_frames=5)
    times, smooth = read_mdd(info["smooth_cache"])
    np.testing.assert_array_equal(smooth, rig.take_smooth)
    np.testing.assert_allclose(times, rig.take_times, atol=1e-6)
    # the truth differs from the smooth motion by the wrinkles alone: along the normal, zero where
    # nothing compresses (the rest frame of a take at rest, the anchors)
    np.testing.assert_array_equal(rig.take_positions[:, rig.anchors], smooth[:, rig.anchors])


def test_details_layer_exports(rig, tmp_path):
    from facepipe.io.exr import read_exr  # noqa: F401  (the EXR reader is there)

    _, large, final, times = _replay_large(rig)
    write_mdd(tmp_path / "large.mdd", large, times)
    assert run_cli("replay", tmp_path / "large.mdd", "-m", rig.models["wpsd"], "-o", tmp_path / "take", "-q") == 0
    assert run_cli("export", tmp_path / "take", "--format", "mdd", "--layer", "details", "-o",
                   tmp_path / "details.mdd", "-q") == 0
    _, details = read_mdd(tmp_path / "details.mdd")
    np.testing.assert_allclose(details, final - large, atol=1e-5)
    assert run_cli("export", tmp_path / "take", "--format", "exr", "--resolution", 64, "-o", tmp_path / "maps",
                   "-q") == 0
    assert len(list((tmp_path / "maps").glob("*.exr"))) == len(times)


def test_cache_take_large_scale_read_back_from_the_cache(rig, tmp_path, capsys):
    """A cache take keeps no copy of the cache: its large scale is read back from the cache (the rows
    of the replayed frames, in the rig's units), equal to what --save-large-scale writes; a cache
    moved or changed since the replay is a clear exit 2 that says how to keep the layer."""
    _, large, final, times = _replay_large(rig)
    cache = tmp_path / "large.mdd"
    write_mdd(cache, (large * 10.0).astype(np.float32), times)  # in mm: the replay scales it back
    args = ("-m", rig.models["wpsd"], "--take-units", "mm", "--frames", "2:", "--backend", "numpy", "-q")
    assert run_cli("replay", cache, "-o", tmp_path / "kept", "--save-large-scale", *args) == 0
    assert run_cli("replay", cache, "-o", tmp_path / "read", *args) == 0
    assert not (tmp_path / "read" / "large_scale.npy").exists()
    stored = np.load(tmp_path / "kept" / "large_scale.npy")
    read = ReplayDir(tmp_path / "read")
    np.testing.assert_allclose(read.layer("large")[:], stored, rtol=0, atol=1e-6)
    np.testing.assert_allclose(read.large_scale[-2], stored[-2], rtol=0, atol=1e-6)
    assert np.asarray(read.large_scale).shape == stored.shape
    np.testing.assert_allclose(read.large_scale[[3, 0]], stored[[3, 0]], rtol=0, atol=1e-6)
    assert run_cli("export", tmp_path / "read", "--format", "mdd", "--layer", "details", "-o",
                   tmp_path / "details.mdd", "-q") == 0
    np.testing.assert_allclose(read_mdd(tmp_path / "details.mdd")[1], np.load(tmp_path / "read" / "positions.npy")
                               - stored, rtol=0, atol=1e-5)
    # eval --large-scale scores the layer read back (against itself as the truth: 0)
    frames = json.loads((tmp_path / "read" / "replay.json").read_text())["frame_numbers"]
    np.savez(tmp_path / "truth.npz", positions=stored, frame=np.asarray(frames))
    assert run_cli("eval", tmp_path / "read", "--truth", tmp_path / "truth.npz", "--large-scale", "-q") == 0
    assert json.loads((tmp_path / "read" / "eval.json").read_text())["large_scale"]["max_error"] < 1e-5
    # changed since: refused, not silently another surface
    write_mdd(cache, (large * 10.0 + 1.0).astype(np.float32), times)
    capsys.readouterr()
    assert run_cli("export", tmp_path / "read", "--format", "mdd", "--layer", "large", "-o", tmp_path / "l.mdd") == 2
    err = capsys.readouterr().err
    assert "changed since the replay" in err and "--save-large-scale" in err
    assert not (tmp_path / "l.mdd").exists() and not list(tmp_path.glob(".l.mdd*"))  # nothing half-written
    cache.unlink()
    assert run_cli("export", tmp_path / "read", "--format", "mdd", "--layer", "large", "-o", tmp_path / "l.mdd") == 2
    assert "not there any more" in capsys.readouterr().err
    assert not (tmp_path / "l.mdd").exists() and not list(tmp_path.glob(".l.mdd*"))
    # the replay that kept its layer does not need the cache
    assert run_cli("export", tmp_path / "kept", "--format", "mdd", "--layer", "large", "-o", tmp_path / "k.mdd",
                   "-q") == 0


def test_opencl_take_matches_numpy(rig, tmp_path):
    pytest.importorskip("pyopencl")
    from facepipe.opencl import OpenCLUnavailable  # noqa: F401

    _, large, final, times = _replay_large(rig)
    write_mdd(tmp_path / "large.mdd", large, times)
    size = float(np.ptp(final, axis=(0, 1)).max())
    assert run_cli("replay", tmp_path / "large.mdd", "-m", rig.models["wpsd"], "-o", tmp_path / "np",
                   "--backend", "numpy", "-q") == 0
    code = run_cli("replay", tmp_path / "large.mdd", "-m", rig.models["wpsd"], "-o", tmp_path / "cl",
                   "--backend", "opencl", "-q")
    if code == 2:
        pytest.skip("no OpenCL device")
    assert json.loads((tmp_path / "cl" / "replay.json").read_text())["backend"] == "opencl"
    assert np.abs(np.load(tmp_path / "cl" / "positions.npy") - np.load(tmp_path / "np" / "positions.npy")).max() \
        < 1e-5 * size


def test_smooth_cache_bands_opencl_and_numpy_agree(rig, tmp_path):
    """The sample rig's smooth cache: the bands chosen and the replay the same on both backends."""
    cache = rig.root / "rig" / "take_smooth.mdd"
    assert run_cli("replay", cache, "-m", rig.models["wpsd"], "-o", tmp_path / "np", "--backend", "numpy",
                   "-q") == 0
    report = json.loads((tmp_path / "np" / "replay.json").read_text())["cache"]["bands"]
    assert len(report["added"]) == len(report["amplitude_ratio"]) == 8
    code = run_cli("replay", cache, "-m", rig.models["wpsd"], "-o", tmp_path / "cl", "--backend", "opencl", "-q")
    if code == 2:
        pytest.skip("no OpenCL device")
    a, b = np.load(tmp_path / "np" / "positions.npy"), np.load(tmp_path / "cl" / "positions.npy")
    assert np.abs(a - b).max() < 1e-5 * float(np.ptp(a, axis=(0, 1)).max())


def test_head_moving_cache_opencl_and_numpy_agree(rig, tmp_path):
    """A cache whose head turns (the smooth cache moved rigidly per frame), head motion kept and
    removed: OpenCL (the cache's own surface used as it is when the motion is kept) and NumPy
    agree, and the kept replay is the removed one moved by the head's motion."""
    from scipy.spatial.transform import Rotation

    _, positions = read_mdd(rig.root / "rig" / "take_smooth.mdd")
    T = len(positions)
    angles = np.stack([np.linspace(0, 12, T), np.linspace(0, -7, T), np.linspace(0, 4, T)], axis=1)
    R = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()
    t = np.stack([np.linspace(0, 1.5, T), np.zeros(T), np.linspace(0, -2.0, T)], axis=1)
    moved = np.einsum("tij,tvj->tvi", R, positions) + t[:, None]
    write_mdd(tmp_path / "moved.mdd", moved.astype(np.float32), np.arange(T) / 30.0)
    size = float(np.ptp(moved, axis=(0, 1)).max())
    out = {}
    for backend in ("numpy", "opencl"):
        for motion in ("keep", "remove"):
            code = run_cli("replay", tmp_path / "moved.mdd", "-m", rig.models["wpsd"], "-o",
                           tmp_path / f"{backend}_{motion}", "--backend", backend, "--head-motion", motion, "-q",
                           *(["--save-large-scale"] if backend == "numpy" else []))  # written by the replay vs read back
            if code == 2 and backend == "opencl":
                pytest.skip("no OpenCL device")
            assert code == 0
            folder = ReplayDir(tmp_path / f"{backend}_{motion}")  # (the large scale read back from the cache)
            out[backend, motion] = {"positions": np.asarray(folder.positions), "large_scale": folder.layer("large")[:]}
    for motion in ("keep", "remove"):
        for k in ("positions", "large_scale"):
            assert np.abs(out["opencl", motion][k] - out["numpy", motion][k]).max() < 1e-5 * size, (motion, k)
    pose = np.load(tmp_path / "numpy_keep" / "handles.npz")
    Rp, tp = pose["rotation"], pose["translation"]
    turned = np.einsum("tij,tvj->tvi", Rp, out["numpy", "remove"]["positions"].astype(np.float64)) + tp[:, None]
    assert np.abs(turned - out["numpy", "keep"]["positions"]).max() < 1e-5 * size


def test_ict_large_scale_cache_reproduces_the_marker_replay(ict_rig_fit, tmp_path):
    """ICT kit: frames of the training take replayed from its truth's handles, the large scale written
    as MDD and replayed as a take: the marker replay's final positions within 1e-4 cm."""
    from facepipe.io.model_file import model_from_fit, save_model
    from facepipe.pipeline.replay import replay

    rig_, fit = ict_rig_fit
    model = model_from_fit(fit, rig_)
    save_model(tmp_path / "model.npz", model.arrays, model.meta)
    model = load_model(tmp_path / "model.npz")
    kit = ict_or_skip()
    truth = np.load(kit / "train_truth.npz")["positions"][::20].astype(np.float64)
    frames = np.arange(len(truth))
    head = truth[:, model.handle_vertices]
    R = np.broadcast_to(np.eye(3), (len(frames), 3, 3))
    t = np.zeros((len(frames), 3))
    replay(model, head, R, t, frames, frames / 30.0, tmp_path / "markers", save_large=True)
    large = np.load(tmp_path / "markers" / "large_scale.npy")
    write_mdd(tmp_path / "large.mdd", large, frames / 30.0)
    assert run_cli("replay", tmp_path / "large.mdd", "-m", tmp_path / "model.npz", "-o", tmp_path / "take",
                   "--backend", "numpy", "-q") == 0
    final = np.load(tmp_path / "markers" / "positions.npy")
    assert np.linalg.norm(np.load(tmp_path / "take" / "positions.npy") - final, axis=-1).max() < 1e-4
