"""End-to-end runs of the command line on the built-in sample rig, and its bad-input paths."""

import json
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import add_detached_part, run_cli as run

BOUNDS = json.loads((Path(__file__).parent / "data" / "sample_bounds.json").read_text())


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    """sample → fit → bake → replay → export → eval, once for the module."""
    d = tmp_path_factory.mktemp("e2e")
    rig = d / "rig"
    assert run("sample", rig, "--vertices", BOUNDS["vertices"], "--frames", BOUNDS["frames"], "-q") == 0
    assert run("fit", rig / "sample.toml", "-o", d / "fit.npz", "-q") == 0
    assert run("bake", d / "fit.npz", "-o", d / "model.npz", "-q") == 0
    assert run("replay", rig / "take.csv", "-m", d / "model.npz", "-o", d / "out", "--save-large-scale", "-q") == 0
    assert run("eval", d / "out", "--truth", rig / "take_truth.npz", "--large-scale", "-q") == 0
    return d


def test_outputs_and_reports(pipeline):
    d = pipeline
    pos = np.load(d / "out" / "positions.npy", mmap_mode="r")
    assert pos.dtype == np.float32 and pos.shape[0] == BOUNDS["frames"]
    report = json.loads((d / "out" / "replay.json").read_text())
    # --backend auto (the default): OpenCL where a device works (PoCL's CPU one here), else NumPy
    assert report["frames"] == BOUNDS["frames"] and report["backend"] in ("opencl", "numpy")
    fit = json.loads((d / "fit.json").read_text())
    assert set(fit["curves"]) == {"psd", "wpsd"}
    assert not list(d.rglob("*.part*")), "temporary files left behind"


def test_error_figures_within_stored_bounds(pipeline):
    ev = json.loads((pipeline / "out" / "eval.json").read_text())
    final, large = ev["final"]["rms_mean"], ev["large_scale"]["rms_mean"]
    assert final <= BOUNDS["final_rms_mean_max"], final
    assert large <= BOUNDS["large_rms_mean_max"], large
    assert large / final >= BOUNDS["wpsd_gain_min"], large / final


def test_export_obj_sequence(pipeline):
    d = pipeline
    assert run("export", d / "out", "--format", "obj", "-o", d / "obj", "-q") == 0
    files = sorted((d / "obj").glob("frame_*.obj"))
    assert len(files) == BOUNDS["frames"] and files[0].name == "frame_0001.obj"
    from facepipe.io.mesh_read import load_mesh

    first = load_mesh(files[0])
    pos = np.load(d / "out" / "positions.npy")
    assert np.allclose(first.vertices, pos[0], atol=1e-4)
    assert first.uvs is not None
    # no overwrite without --force
    assert run("export", d / "out", "--format", "obj", "-o", d / "obj", "-q") == 2
    assert run("export", d / "out", "--format", "obj", "-o", d / "obj", "-q", "--force") == 0


def test_export_obj_writes_the_rest_mesh_groups(tmp_path):
    """A rest mesh with OBJ groups: sample → fit → bake → replay → export obj gives every frame
    the input's `g` lines, on the same polygons."""
    from facepipe.io.mesh_read import load_mesh
    from tests.test_model import group_rest_mesh

    rig = tmp_path / "rig"
    assert run("sample", rig, "--vertices", 2000, "--frames", 3, "-q") == 0
    group_rest_mesh(rig / "neutral.obj")
    assert run("fit", rig / "sample.toml", "-o", tmp_path / "fit.npz", "-q") == 0
    assert run("bake", tmp_path / "fit.npz", "-o", tmp_path / "model.npz", "-q") == 0
    assert run("replay", rig / "take.csv", "-m", tmp_path / "model.npz", "-o", tmp_path / "out", "-q") == 0
    assert run("export", tmp_path / "out", "--format", "obj", "-o", tmp_path / "obj", "-q") == 0

    def groups(path):
        """Each `g` line with the number of `f` lines before it, and every polygon's group."""
        lines = path.read_text().splitlines()
        faces = np.cumsum([line.startswith("f ") for line in lines])
        mesh = load_mesh(path)
        return ([(int(n), line) for n, line in zip(faces, lines) if line.startswith("g ")],
                [mesh.group_names[g] for g in mesh.polygon_groups], mesh.polygon_vertices)

    given = groups(rig / "neutral.obj")
    assert len(given[0]) > 3 and len(set(given[1])) == 4
    frames = sorted((tmp_path / "obj").glob("frame_*.obj"))
    assert len(frames) == 3
    for frame in frames:
        got = groups(frame)
        assert got[0] == given[0] and got[1] == given[1] and np.array_equal(got[2], given[2]), frame.name


def test_bake_from_config_equals_bake_from_fit(pipeline, tmp_path):
    d = pipeline
    assert run("bake", d / "rig" / "sample.toml", "-o", tmp_path / "m.npz", "-q") == 0
    a, b = np.load(d / "model.npz"), np.load(tmp_path / "m.npz")
    for key in ("B", "rbf_weights", "edge_weight"):
        assert np.array_equal(a[key], b[key])


def test_frames_option(pipeline, tmp_path):
    d = pipeline
    assert run("replay", d / "rig" / "take.csv", "-m", d / "model.npz", "-o", tmp_path / "o", "--frames", "5:9",
               "-q") == 0
    full = np.load(d / "out" / "positions.npy")
    part = np.load(tmp_path / "o" / "positions.npy")
    assert part.shape[0] == 4 and np.allclose(part, full[5:9], atol=1e-5)


def test_bad_inputs_exit_2_with_message(pipeline, tmp_path, capsys, monkeypatch):
    d = pipeline
    assert run("fit", tmp_path / "missing.toml") == 2
    err = capsys.readouterr().err
    assert "config file not found" in err and "fit:" not in err  # said alone: no steps' bar opened first
    assert run("bake", tmp_path / "missing.npz", "-o", tmp_path / "m.npz") == 2
    err = capsys.readouterr().err
    assert "fit file not found" in err and "bake:" not in err
    bad = tmp_path / "bad.toml"
    bad.write_text((d / "rig" / "sample.toml").read_text().replace('markers = "markers.csv"',
                                                                     'markers = "nope.csv"'))
    assert run("fit", bad) == 2
    # a config in another folder: relative paths now point nowhere
    assert "not found" in capsys.readouterr().err
    markers = (d / "rig" / "markers.csv").read_text().splitlines()
    markers[3] = markers[3].split(",")[0] + ",99999999,handle"
    (d / "rig" / "bad_markers.csv").write_text("\n".join(markers) + "\n")
    cfg = d / "rig" / "bad_markers.toml"
    cfg.write_text((d / "rig" / "sample.toml").read_text().replace("markers.csv", "bad_markers.csv"))
    assert run("fit", cfg, "-o", tmp_path / "f.npz") == 2
    err = capsys.readouterr().err
    assert "99999999" in err and "line 4" in err
    assert not (tmp_path / "f.npz").exists()
    # a model file that is not one
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    assert run("replay", d / "rig" / "take.csv", "-m", junk, "-o", tmp_path / "o2") == 2
    assert "junk.npz" in capsys.readouterr().err
    assert not (tmp_path / "o2" / "positions.npy").exists()
    # a take that is truncated
    take = (d / "rig" / "take.csv").read_text().splitlines()
    (tmp_path / "cut.csv").write_text("\n".join(take[:5] + [take[5][: len(take[5]) // 2]]) + "\n")
    assert run("replay", tmp_path / "cut.csv", "-m", d / "model.npz", "-o", tmp_path / "o3") == 2
    assert "line 6" in capsys.readouterr().err
    assert not (tmp_path / "o3" / "positions.npy").exists()
    # the device is set up while the take is read: the take's error is the one reported
    from facepipe.opencl import device as cl_device

    monkeypatch.setattr(cl_device, "list_devices", lambda: [])
    assert run("replay", tmp_path / "cut.csv", "-m", d / "model.npz", "-o", tmp_path / "o4", "--backend",
               "opencl") == 2
    err = capsys.readouterr().err
    assert "line 6" in err and "OpenCL" not in err
    assert not (tmp_path / "o4" / "positions.npy").exists()


def test_help_everywhere():
    for cmd in ([], ["fit"], ["bake"], ["replay"], ["export"], ["eval"], ["sample"], ["transfer"], ["preview"]):
        assert run(*cmd, "--help") == 0


def test_examples_from_a_captured_sequence(pipeline, tmp_path):
    """[examples] sequence: frames of a take with truth serve as example poses (with meshes or alone)."""
    from facepipe.pipeline.fit import fit_rig
    from facepipe.pipeline.rig import load_rig

    rig_dir = pipeline / "rig"
    cfg = rig_dir / "seq.toml"
    text = (rig_dir / "sample.toml").read_text()
    text = text.replace('meshes = ["expressions/*.obj"]', "meshes = []")
    text = text.replace('sequence = ""', 'sequence = "take_truth.npz"\nsequence_stride = 10')
    cfg.write_text(text)
    rig = load_rig(cfg)
    assert len(rig.example_names) == (BOUNDS["frames"] + 9) // 10
    assert rig.example_names[1].endswith(":10")
    fit = fit_rig(rig)
    assert fit.report["curves"]["wpsd"][-1]["mean_rms"] < fit.report["curves"]["wpsd"][0]["mean_rms"]


def test_greedy_scored_on_a_vertex_sample(pipeline):
    """[psd] greedy_vertices: the basis is chosen on a spread sample, then fitted on every vertex."""
    from facepipe.pipeline.fit import fit_rig
    from facepipe.core.psd import fit_details
    from facepipe.pipeline.rig import load_rig

    rig = load_rig(pipeline / "rig" / "sample.toml")
    rig.config.psd.greedy_vertices = 0
    full = fit_rig(rig)
    V = rig.mesh.n_vertices
    rig.config.psd.greedy_vertices = V // 4
    part = fit_rig(rig)
    assert full.report["greedy_vertices"] == V and part.report["greedy_vertices"] == V // 4
    assert part.basis == full.basis
    # the model covers every vertex and equals a fit of that basis on all of them
    again = fit_details(part.method, part.features, part.details, part.basis, rig.config.psd.fit, part.alpha,
                        rig.config.psd.rcond, rig.config.psd.smoothing)
    assert part.model.weights.shape[0] == V
    np.testing.assert_allclose(part.model.weights, again.weights, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(part.model.weights, full.model.weights)
    # the sampled error curve estimates the full one
    for a, b in zip(part.curves["wpsd"], full.curves["wpsd"]):
        assert a["mean_rms"] == pytest.approx(b["mean_rms"], rel=0.25, abs=1e-9)


def test_geodesics_from_a_second_process_give_the_same_fit(pipeline, monkeypatch):
    """On a large mesh a child process starts the geodesics as soon as the rest mesh is read and this
    one joins in when it needs them: the same fit as computing them here."""
    import time

    from facepipe.pipeline import fit as fit_module
    from facepipe.pipeline import geodesics
    from facepipe.pipeline.rig import load_rig

    here = fit_module.fit_rig(load_rig(pipeline / "rig" / "sample.toml"))
    monkeypatch.setattr(geodesics, "GEODESICS_IN_A_PROCESS", 0)
    monkeypatch.setattr(geodesics, "GEODESICS_ON_DEVICE", False)  # the second process (the device: test_strain)
    graph = fit_module.feature_graph

    def slow_graph(*args, **kwargs):  # long enough for the child to start and take sources
        time.sleep(2.0)
        return graph(*args, **kwargs)

    monkeypatch.setattr(fit_module, "feature_graph", slow_graph)
    _, there = fit_module.fit_config(pipeline / "rig" / "sample.toml")
    assert there.report["seconds"]["geodesics_child_sources"] > 0
    assert there.report["seconds"]["load"] > 0
    np.testing.assert_array_equal(there.edge_weight, here.edge_weight)
    np.testing.assert_array_equal(there.edge_index, here.edge_index)
    np.testing.assert_array_equal(there.model.weights, here.model.weights)
    np.testing.assert_array_equal(there.gate.examples, here.gate.examples)


def test_early_shell_basis_gives_the_same_fit_and_yields_to_validation(pipeline):
    """The basis solved in a thread while the examples load is the one the fit would solve; where
    validation (``prepare``) changes the shell's stiffness the fit solves the basis for the new one."""
    import dataclasses

    from facepipe.pipeline import fit as fit_module
    from facepipe.pipeline.rig import load_rig

    config = pipeline / "rig" / "sample.toml"
    _, plain = fit_module.fit_config(config)
    _, early = fit_module.fit_config(config, early_basis=True)
    assert early.report["shell_basis_early"] and not plain.report["shell_basis_early"]
    np.testing.assert_array_equal(early.geometry.B, plain.geometry.B)
    np.testing.assert_array_equal(early.model.weights, plain.model.weights)

    def stiffer(rig, geodesics):
        rig.config = dataclasses.replace(rig.config, shell=dataclasses.replace(rig.config.shell, k_stretch=0.5))

    _, changed = fit_module.fit_config(config, prepare=stiffer, early_basis=True)
    assert not changed.report["shell_basis_early"]
    rig = load_rig(config)
    stiffer(rig, None)
    np.testing.assert_allclose(changed.geometry.B, fit_module.build_geometry(rig).B, atol=1e-12)
    assert np.abs(changed.geometry.B - plain.geometry.B).max() > 1e-6


def test_bad_psd_counts_exit_2_without_output(pipeline, tmp_path, capsys):
    rig = pipeline / "rig"
    for key, value in (("greedy_vertices", -1),):
        cfg = rig / f"bad_{key}.toml"
        cfg.write_text((rig / "sample.toml").read_text().replace("[psd]", f"[psd]\n{key} = {value}"))
        out = tmp_path / f"{key}.npz"
        assert run("fit", cfg, "-o", out) == 2
        err = capsys.readouterr().err
        assert "[psd]" in err and "greedy_vertices" in err and str(cfg) in err
        assert not out.exists()


def test_examples_read_by_a_second_process_are_the_same(pipeline, tmp_path, monkeypatch):
    """Large example sets are read by a child process: the same poses and digest, the same errors."""
    import shutil

    from facepipe.pipeline import rig as rig_module
    from facepipe.errors import InputError

    here = rig_module.load_rig(pipeline / "rig" / "sample.toml")
    monkeypatch.setattr(rig_module, "EXAMPLES_IN_A_PROCESS", 0)
    there = rig_module.load_rig(pipeline / "rig" / "sample.toml")
    assert there.example_names == here.example_names and there.digest == here.digest
    np.testing.assert_array_equal(there.example_positions, here.example_positions)
    # a broken second example: the child gives up on it, this process names it
    copy = tmp_path / "rig"
    shutil.copytree(pipeline / "rig", copy)
    second = sorted((copy / "expressions").glob("*.obj"))[1]
    text = second.read_text().splitlines()
    first_v = next(i for i, line in enumerate(text) if line.startswith("v "))
    text[first_v] = "v 1.0 nan 2.0"
    second.write_text("\n".join(text) + "\n")
    with pytest.raises(InputError) as exc:
        rig_module.load_rig(copy / "sample.toml")
    assert second.name in str(exc.value)


def test_bad_inputs_of_the_checking_commands(pipeline, tmp_path, capsys):
    d = pipeline
    rig = d / "rig"
    cfg = rig / "bad_method.toml"
    cfg.write_text((rig / "sample.toml").read_text().replace("[shell]", '[shell]\nmethod = "spline"'))
    assert run("fit", cfg, "-o", tmp_path / "f.npz") == 2
    assert "method = 'spline'" in capsys.readouterr().err and not (tmp_path / "f.npz").exists()
    assert run("fit", rig / "sample.toml", "-o", tmp_path / "f.npz", "--holdout", "999") == 2
    assert "--holdout 999" in capsys.readouterr().err and not (tmp_path / "f.npz").exists()
    # --compare needs the replay's handles and a config of the same rig
    (tmp_path / "r").mkdir()
    for name in ("replay.json", "positions.npy"):
        (tmp_path / "r" / name).write_bytes((d / "out" / name).read_bytes())
    assert run("eval", tmp_path / "r", "--truth", rig / "take_truth.npz", "--compare", rig / "sample.toml") == 2
    assert "no handles.npz" in capsys.readouterr().err
    assert not (tmp_path / "r" / "compare.json").exists()


def test_replay_reports_novelty_fits_stopped_by_their_cap(pipeline, tmp_path, monkeypatch):
    """A gate whose non-negative fits neither converge within their cap nor are finished by the
    exact solver says how many in replay.json (0 when all converged), on both backends."""
    import scipy.optimize
    from facepipe.core.novelty import NoveltyGate

    converged = json.loads((pipeline / "out" / "replay.json").read_text())
    assert converged["novelty_fits_at_cap"] == 0
    novelty = NoveltyGate.novelty
    monkeypatch.setattr(NoveltyGate, "novelty",
                        lambda self, f, displacements=None, tolerance=1e-14, max_iterations=2, settled=None:
                        novelty(self, f, displacements, tolerance, max_iterations))  # no fit settles early

    def exact_solver_gives_up(*args, **kwargs):
        raise RuntimeError("Maximum number of iterations reached.")

    monkeypatch.setattr(scipy.optimize, "nnls", exact_solver_gives_up)  # (the gate imports it where it calls it)
    for backend in ("numpy", "opencl"):
        out = tmp_path / backend
        code = run("replay", pipeline / "rig" / "take.csv", "-m", pipeline / "model.npz", "-o", out, "--backend",
                   backend, "--frames", "0:8", "-q")
        if code == 2 and backend == "opencl":
            continue  # no OpenCL device here
        assert code == 0
        assert json.loads((out / "replay.json").read_text())["novelty_fits_at_cap"] > 0, backend


def test_options_that_do_not_apply_to_the_take_are_refused(pipeline, tmp_path, capsys):
    """Marker-take options on a mesh cache and 2D-take options on a marker take: exit 2 naming them,
    nothing written (they used to be silently ignored)."""
    d = pipeline
    cache = d / "rig" / "take_smooth.mdd"
    for options, named in ((["--neutral-frame", "0"], "--neutral-frame"),
                           (["--no-stabilise", "--smooth", "2"], "--no-stabilise, --smooth")):
        out = tmp_path / named.replace(",", "").replace(" ", "")
        assert run("replay", cache, "-m", d / "model.npz", "-o", out, *options) == 2
        err = capsys.readouterr().err
        assert named in err and "mesh cache" in err and "take_smooth.mdd" in err
        assert not (out / "positions.npy").exists()
    out = tmp_path / "lift"
    assert run("replay", d / "rig" / "take.csv", "-m", d / "model.npz", "-o", out, "--lift", "heuristic") == 2
    assert "--lift does not apply to a marker take" in capsys.readouterr().err
    assert not (out / "positions.npy").exists()


def test_a_separate_part_held_by_an_anchor_moves_with_the_head(tmp_path, capsys):
    """A part of the mesh apart from the markers (an eyeball, teeth): without a constraint the fit
    stops with exit 2 and says to anchor it; with one of its vertices among the anchors the rig fits
    (a note says the part gets no details) and replays, the part still in head space."""
    rig = tmp_path / "rig"
    assert run("sample", rig, "--vertices", 2000, "--frames", 12, "--examples", 4, "-q") == 0
    offset = np.array([0.0, 0.0, 6.0])
    first = add_detached_part(rig / "neutral.obj", offset)
    for pose in sorted((rig / "expressions").glob("*.obj")):
        add_detached_part(pose, offset)
    assert run("fit", rig / "sample.toml", "--no-tune", "-o", tmp_path / "fit.npz", "-q") == 2
    err = capsys.readouterr().err
    assert f"containing vertex {first}" in err and "anchors file" in err
    with open(rig / "anchors.txt", "a") as f:
        f.write(f"{first}\n")
    assert run("fit", rig / "sample.toml", "--no-tune", "-o", tmp_path / "fit.npz") == 0
    assert "6 vertices lie in parts of the mesh that no marker reaches" in capsys.readouterr().out
    assert json.loads((tmp_path / "fit.json").read_text())["vertices_without_edges"] == 6
    assert run("bake", tmp_path / "fit.npz", "-o", tmp_path / "model.npz", "-q") == 0
    for backend in ("numpy", "auto"):
        out = tmp_path / f"out_{backend}"
        assert run("replay", rig / "take.csv", "-m", tmp_path / "model.npz", "-o", out, "--backend", backend,
                   "--head-motion", "remove", "-q") == 0
        positions = np.load(out / "positions.npy")
        assert np.isfinite(positions).all()
        from facepipe.io.mesh_read import load_mesh

        rest = load_mesh(rig / "neutral.obj").vertices
        np.testing.assert_allclose(positions[:, first:], np.broadcast_to(rest[first:], positions[:, first:].shape),
                                   atol=1e-5)
        assert np.abs(positions[:, :first] - rest[:first]).max() > 0.1  # the face moves
