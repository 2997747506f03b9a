"""Local strain of a surface (core.local_strain), the detail model over it (core.strain_details),
and the ``local_strain`` method end to end: fit, bake, replay on NumPy and OpenCL."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facepipe import opencl
from facepipe.core.local_strain import (StrainOperator, principal_strains, ring_strain_coefficients,
                                        ring_vertex_strain, triangle_green_strain, vertex_strain)
from facepipe.core.strain_details import fit_strain_details
from facepipe.io.model_file import load_model, model_from_fit
from facepipe.io.point_caches import read_mdd, write_mdd
from facepipe.pipeline.fit import fit_rig
from facepipe.pipeline.replay import NumpyEvaluator
from facepipe.pipeline.rig import load_rig
from facepipe.sample_rig import write_sample_rig
from tests.conftest import grid
from tests.conftest import run_cli as run


# ----------------------------------------------------------------------------- strain, analytic


def test_rest_and_rigid_motions_have_zero_strain():
    V, F = grid()
    op = StrainOperator.of(V, F)
    R = Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_matrix()
    moved = np.stack([V, V @ R.T + np.array([3.0, -2.0, 7.0])])
    assert np.abs(vertex_strain(moved, op)).max() < 1e-12


@pytest.mark.parametrize("curved", [False, True])
def test_uniform_scaling_gives_its_green_strain_in_every_direction(curved):
    V, F = grid(curved=curved)
    op = StrainOperator.of(V, F)
    s = 0.9  # 10 % compression: E = ½ (s² − 1) along every tangent direction
    assert np.allclose(np.linalg.eigvalsh(triangle_green_strain(V * s, op)), 0.5 * (s * s - 1), atol=1e-12)
    principal = principal_strains(vertex_strain(V * s, op))
    # on a curved sheet the faces around a vertex tilt away from its tangent plane: their tensors,
    # read in that plane, are foreshortened by the tilt's cos² (here within 0.1 %)
    assert np.allclose(principal, 0.5 * (s * s - 1), rtol=1e-3 if curved else 1e-12, atol=1e-12)


def test_stretch_along_x_and_simple_shear_of_a_flat_sheet():
    V, F = grid(curved=False)
    op = StrainOperator.of(V, F)
    E = triangle_green_strain(V * np.array([1.2, 1.0, 1.0]), op)
    # each triangle's frame is its own; its tensor's invariants are the stretch's
    assert np.allclose(np.trace(E, axis1=1, axis2=2), 0.5 * (1.44 - 1))
    assert np.allclose(np.linalg.det(E), 0.0, atol=1e-12)
    g = 0.3  # x += g y: F = [[1, g], [0, 1]], E = ½ [[0, g], [g, g²]]
    sheared = V + np.outer(V[:, 1], [g, 0.0, 0.0])
    s = vertex_strain(sheared, op)  # in the vertex frames: invariants of E
    expected = np.linalg.eigvalsh(0.5 * np.array([[0.0, g], [g, g * g]]))
    assert np.allclose(principal_strains(s), expected, atol=1e-12)


def test_frobenius_norm_does_not_depend_on_the_tangent_choice():
    V, F = grid()
    rng = np.random.default_rng(0)
    P = V + 0.2 * rng.normal(size=V.shape)
    a = vertex_strain(P, StrainOperator.of(V, F))
    b = vertex_strain(P, StrainOperator.of(V, F, neighbors=_other_neighbors(F, len(V))))
    assert np.allclose(np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1), atol=1e-12)
    assert np.allclose(principal_strains(a), principal_strains(b), atol=1e-12)


def _other_neighbors(faces, n):
    """The highest-index neighbour of every vertex (the default frame takes the lowest)."""
    nb = np.full(n, -1)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    np.maximum.at(nb, e[:, 0], e[:, 1])
    return nb


def test_ring_form_equals_the_face_form():
    V, F = grid()
    op = StrainOperator.of(V, F)
    coeff, const = ring_strain_coefficients(V, op)
    rng = np.random.default_rng(1)
    P = np.stack([V + 0.3 * rng.normal(size=V.shape), V * 1.1])
    assert np.allclose(ring_vertex_strain(P, F, coeff, const), vertex_strain(P, op), atol=1e-12)


# ----------------------------------------------------------------------------- the detail model


def test_kernel_regression_reproduces_samples_and_vanishes_far_from_them():
    rng = np.random.default_rng(2)
    N, V = 6, 5
    strains = np.concatenate([np.zeros((1, V, 3)), rng.uniform(-0.3, 0.1, size=(N - 1, V, 3))])
    details = np.concatenate([np.zeros((1, V, 3)), rng.normal(size=(N - 1, V, 3))])
    model = fit_strain_details(strains, details, width=0.05, ridge=1e-9)
    assert np.allclose(model.evaluate(strains), details, atol=1e-5)
    assert np.abs(model.evaluate(np.full((1, V, 3), 5.0))).max() < 1e-12  # no harm far from the data


def test_kernel_regression_learns_a_compression_threshold():
    """d = max(0, −ε − 0.1) along the normal, sampled at a few compressions, recovered between them."""
    eps = np.linspace(0.0, -0.4, 17)
    strains = np.zeros((len(eps), 1, 3))
    strains[:, 0, 0] = eps
    details = np.zeros_like(strains)
    details[:, 0, 2] = np.maximum(0.0, -eps - 0.1)
    model = fit_strain_details(strains, details, width=0.05, ridge=1e-6)
    query = np.zeros((3, 1, 3))
    query[:, 0, 0] = [-0.0375, -0.2125, -0.3375]
    assert np.allclose(model.evaluate(query)[:, 0, 2], [0.0, 0.1125, 0.2375], atol=0.01)


def test_fit_rejects_bad_width():
    with pytest.raises(ValueError):
        fit_strain_details(np.zeros((2, 1, 3)), np.zeros((2, 1, 3)), width=0.0)


# ----------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def strain_rig(tmp_path_factory):
    d = tmp_path_factory.mktemp("local_strain")
    write_sample_rig(d / "rig", n_vertices=3000, n_examples=6, n_frames=40)
    cfg = d / "rig" / "sample.toml"
    cfg.write_text(cfg.read_text().replace('method = "wpsd"', 'method = "local_strain"', 1))
    rig = load_rig(cfg)
    fit = fit_rig(rig)
    truth = np.load(d / "rig" / "take_truth.npz")["positions"]
    return d, rig, fit, truth


def test_fit_reproduces_the_examples_and_keeps_other_methods(strain_rig):
    _, rig, fit, _ = strain_rig
    assert fit.model.method == "local_strain" and fit.strain_model is not None
    model = model_from_fit(fit, rig)
    ev = NumpyEvaluator(model)
    poses = rig.example_positions
    final, large = ev.evaluate(poses[:, rig.handles], with_large=True)
    err = np.sqrt(((final - poses) ** 2).sum(-1).mean(-1))
    err_large = np.sqrt(((large - poses) ** 2).sum(-1).mean(-1))
    assert np.all(err < err_large)  # (a ridge: close to the examples, not exactly on them)
    # WPSD from the same fit is the WPSD of a fit configured for it
    wpsd = model_from_fit(fit, rig, "wpsd")
    assert wpsd.method == "wpsd" and wpsd.strain_samples is None


def test_cli_fit_bake_replay(strain_rig, tmp_path):
    d, rig, fit, truth = strain_rig
    cfg = d / "rig" / "sample.toml"
    assert run("fit", cfg, "-o", tmp_path / "fit.npz", "--quiet") == 0
    assert run("bake", tmp_path / "fit.npz", "-o", tmp_path / "model.npz", "--quiet") == 0
    model = load_model(tmp_path / "model.npz")
    assert model.method == "local_strain" and model.strain_samples.shape == model.strain_weights.shape
    assert run("replay", d / "rig" / "take.csv", "-m", tmp_path / "model.npz", "-o", tmp_path / "out",
               "--backend", "numpy", "--quiet") == 0
    positions = np.load(tmp_path / "out" / "positions.npy")
    assert positions.shape == truth.shape


def test_config_refuses_bad_strain_width(strain_rig, tmp_path, capsys):
    d, *_ = strain_rig
    cfg = d / "rig" / "sample.toml"
    bad = tmp_path / "bad.toml"
    bad.write_text(cfg.read_text().replace('method = "local_strain"', 'method = "local_strain"\nstrain_width = 0.0', 1)
                   .replace('"neutral.obj"', f'"{(d / "rig" / "neutral.obj").as_posix()}"'))
    assert run("fit", bad, "-o", tmp_path / "fit.npz", "--quiet") == 2
    assert "strain_width" in capsys.readouterr().err


@pytest.mark.parametrize("options", [{}, {"vector_width": 1, "chunk": 16}, {"reorder": "rcm", "chunk": 8}])
def test_opencl_matches_numpy(strain_rig, options):
    if not opencl.opencl_available():
        pytest.skip("no OpenCL device (pip install pocl-binary-distribution gives a CPU one)")
    _, rig, fit, truth = strain_rig
    model = model_from_fit(fit, rig)
    head = truth[:, rig.handles].astype(np.float64)
    ref = NumpyEvaluator(model).evaluate(head)
    final = opencl.OpenCLEvaluator(model, **options).evaluate(head)
    diag = float(np.linalg.norm(np.ptp(rig.mesh.vertices, axis=0)))
    assert np.abs(final - ref).max() <= 1e-4 * diag
    # the details themselves, not only the sum: the kernels' detail layer against the reference's
    _, large = NumpyEvaluator(model).evaluate(head, with_large=True)
    assert np.abs((final - large) - (ref - large)).max() <= 0.02 * np.abs(ref - large).max() + 1e-5 * diag


def test_compare_includes_the_local_strain_model(strain_rig):
    from facepipe.pipeline.baselines import compare_methods

    _, rig, fit, truth = strain_rig
    head = truth[:, rig.handles].astype(np.float64)
    T = len(head)
    result = compare_methods(fit, rig, head, np.tile(np.eye(3), (T, 1, 1)), np.zeros((T, 3)), truth)
    rows = {r["method"]: r for r in result["rows"]}
    assert "local strain" in rows and rows["local strain"]["poses"] == len(rig.example_names)
    ev = NumpyEvaluator(model_from_fit(fit, rig))  # the same model as the rig's own
    own = np.sqrt(((ev.evaluate(head) - truth) ** 2).sum(-1).mean(-1))
    assert np.isclose(rows["local strain"]["rms_mean"], own.mean())


def test_large_batches_are_taken_pose_by_pose_with_the_same_result():
    V, F = grid(nx=120, ny=100)
    op = StrainOperator.of(V, F)
    rng = np.random.default_rng(3)
    poses = V + 0.05 * rng.normal(size=(60,) + V.shape)  # 60 × 23562 faces: over the batching threshold
    batched = vertex_strain(poses, op)
    assert np.allclose(batched[:2], vertex_strain(poses[:2], op), rtol=0, atol=1e-14)  # (2 poses: one batch)


def test_detail_layer_gives_the_local_strain_details_in_local_frames(strain_rig):
    from facepipe.core.tangent_frames import local_frames, to_world
    from facepipe.pipeline.detail_layers import DetailLayer

    _, rig, fit, truth = strain_rig
    model = model_from_fit(fit, rig)
    head = truth[:8, rig.handles].astype(np.float64)
    local = DetailLayer(model)(head)
    final, large = NumpyEvaluator(model).evaluate(head, with_large=True)
    frames = local_frames(large, model.triangles.astype(np.int64), model.frame_neighbors.astype(np.int64))
    assert np.allclose(large + to_world(frames, local), final, atol=1e-9)
    assert np.abs(local).max() > 0


def test_wrinkle_maps_and_transfer_refuse_a_local_strain_model(strain_rig, tmp_path):
    from facepipe.errors import InputError
    from facepipe.export.exr_maps import check_wrinkle_model
    from facepipe.io.model_file import model_arrays, save_model
    from facepipe.pipeline.transfer import transfer_files

    _, rig, fit, _ = strain_rig
    with pytest.raises(InputError, match="local strain"):
        check_wrinkle_model(model_from_fit(fit, rig))
    save_model(tmp_path / "model.npz", *model_arrays(fit, rig))
    with pytest.raises(InputError, match="local-strain"):
        transfer_files(tmp_path / "model.npz", tmp_path / "other.obj", tmp_path / "a.csv", tmp_path / "b.csv",
                       tmp_path / "out.npz")


# ----------------------------------------------------------------------------- mesh caches as takes


def test_training_details_are_the_fitted_targets_and_bands_refit():
    """(K + λ I) w gives back exactly what the model was fitted to; the banded refit with every
    band added is the model itself, and with some bands it reproduces (up to the ridge) the
    chosen bands of the training details at the training strains, the rest pose without details."""
    from facepipe.core.detail_bands import DetailBands, banded_strain_model
    from facepipe.core.tangent_frames import frame_neighbors, local_frames, to_world

    V, F = grid(24, 20)
    rng = np.random.default_rng(11)
    strains = np.concatenate([np.zeros((1, len(V), 3)), rng.normal(scale=0.05, size=(4, len(V), 3))])
    details = rng.normal(scale=0.05, size=strains.shape)
    details[0] = 0.0
    model = fit_strain_details(strains, details, width=0.04, ridge=1e-3)
    np.testing.assert_allclose(model.training_details(), details, atol=1e-12)
    frames = local_frames(V, F, frame_neighbors(F, len(V)))
    bands = DetailBands(V, F, spacing=1.5)
    same = banded_strain_model(bands, model, frames, np.ones(bands.n_bands))
    np.testing.assert_allclose(same.weights, model.weights, atol=1e-8)
    assert (same.width, same.ridge) == (model.width, model.ridge)
    added = np.array([1, 1, 1, 0, 0, 0, 0, 0.0])
    sharp = fit_strain_details(strains, details, width=0.04, ridge=1e-9)
    banded = banded_strain_model(bands, sharp, frames, added)
    expected = bands.combine(to_world(frames, details), added)
    expected[0] = 0.0
    got = to_world(frames, banded.evaluate(strains))
    np.testing.assert_allclose(got, expected, atol=1e-6 * float(np.abs(expected).max()))
    bands.close()


def test_cache_take_of_a_local_strain_model(strain_rig, tmp_path):
    """A local-strain model replays mesh caches: the marker replay's own large scale as a cache
    gets every band and gives the marker replay's face (its details follow the strain of the
    cache's surface, which is that large scale); the smooth cache of the take gets only the bands
    it lacks, the same on NumPy and OpenCL."""
    d, rig, fit, truth = strain_rig
    cfg = d / "rig" / "sample.toml"
    model = tmp_path / "model.npz"
    assert run("bake", cfg, "-o", model, "--no-tune", "--quiet") == 0
    assert run("replay", d / "rig" / "take.csv", "-m", model, "-o", tmp_path / "markers", "--backend", "numpy",
               "--save-large-scale", "--quiet") == 0
    final = np.load(tmp_path / "markers" / "positions.npy")
    large = np.load(tmp_path / "markers" / "large_scale.npy")
    write_mdd(tmp_path / "large.mdd", large, np.arange(len(large)) / 24.0)
    assert run("replay", tmp_path / "large.mdd", "-m", model, "-o", tmp_path / "take", "--backend", "numpy",
               "--quiet") == 0
    size = float(np.ptp(final, axis=(0, 1)).max())
    assert np.abs(np.load(tmp_path / "take" / "positions.npy") - final).max() < 1e-4 * size
    smooth = d / "rig" / "take_smooth.mdd"
    assert run("replay", smooth, "-m", model, "-o", tmp_path / "np", "--backend", "numpy", "--quiet") == 0
    bands = json.loads((tmp_path / "np" / "replay.json").read_text())["cache"]["bands"]
    assert 0 < bands["added_fraction"] < 1
    positions = np.load(tmp_path / "np" / "positions.npy")
    cache_error = np.sqrt(((read_mdd(smooth)[1] - truth) ** 2).sum(-1).mean())
    assert np.sqrt(((positions - truth) ** 2).sum(-1).mean()) < cache_error
    if not opencl.opencl_available():
        pytest.skip("no OpenCL device (pip install pocl-binary-distribution gives a CPU one)")
    assert run("replay", smooth, "-m", model, "-o", tmp_path / "cl", "--backend", "opencl", "--quiet") == 0
    assert np.abs(np.load(tmp_path / "cl" / "positions.npy") - positions).max() < 1e-5 * size


def test_editor_evaluates_a_local_strain_model_on_the_server(strain_rig, tmp_path, capsys):
    """The page evaluates PSD and WPSD only: a local-strain model's session is a server one (its
    frames the replay's, details included), and asking for the page's evaluation is refused."""
    from facepipe.cli.editor import prepared_take
    from facepipe.editor.session import EditorSession
    from facepipe.errors import InputError

    d, *_ = strain_rig
    model_path = tmp_path / "model.npz"
    assert run("bake", d / "rig" / "sample.toml", "-o", model_path, "--no-tune", "--quiet") == 0
    model = load_model(model_path)
    take = prepared_take(d / "rig" / "take.csv", model)
    session = EditorSession(model, take, tmp_path / "e.json")
    assert session.mode == "server"
    final, large = session.evaluate(session.handles(10))
    want = NumpyEvaluator(model).evaluate(session.handles(10)[None])[0]
    np.testing.assert_allclose(final, want, atol=1e-5)
    assert np.abs(final - large).max() > 1e-3  # the details are there
    session.close()
    with pytest.raises(InputError, match="on the server"):
        EditorSession(model, take, tmp_path / "e.json", mode="browser")
    assert run("edit", model_path, d / "rig" / "take.csv", "--evaluate", "browser", "--port", 0) == 2
    assert "--evaluate server" in capsys.readouterr().err
