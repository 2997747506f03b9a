"""Meshes split along UV seams or hard edges (vertices on top of each other that no face joins, as
engines and some exporters write them): refused with the fix named, or welded with ``[rig] weld``
into the same rig as the unsplit mesh."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from facepipe.core.mesh import Mesh, coincident_vertices, weld_vertices
from facepipe.io.mesh_read import load_mesh, load_vertices
from facepipe.io.mesh_write import save_obj
from facepipe.io.model_file import load_model
from facepipe.pipeline.rig import split_vertices
from tests.conftest import run_cli as run


def split_mesh(mesh: Mesh, right: np.ndarray) -> tuple[Mesh, np.ndarray]:
    """The mesh with the vertices shared by the polygons ``right`` (N,) bool and the others
    duplicated (appended), the ``right`` polygons using the copies; the seam's original indices."""
    offsets, corners = mesh.polygon_offsets, np.asarray(mesh.polygon_vertices, dtype=np.int64)
    polygon = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    on_right = np.zeros(mesh.n_vertices, bool)
    on_left = np.zeros(mesh.n_vertices, bool)
    on_right[corners[right[polygon]]] = True
    on_left[corners[~right[polygon]]] = True
    seam = np.flatnonzero(on_right & on_left)
    copy = np.full(mesh.n_vertices, -1)
    copy[seam] = mesh.n_vertices + np.arange(len(seam))
    moved = right[polygon] & (copy[corners] >= 0)
    corners = np.where(moved, copy[corners], corners)
    vertices = np.concatenate([mesh.vertices, mesh.vertices[seam]])
    return replace(mesh, vertices=vertices, polygon_vertices=corners), seam


def _grid(n=6) -> Mesh:
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    quads = [[r * n + c, r * n + c + 1, (r + 1) * n + c + 1, (r + 1) * n + c] for r in range(n - 1) for c in range(n - 1)]
    return Mesh(vertices, np.arange(0, 4 * len(quads) + 1, 4), np.array(quads).ravel())


def test_welding_a_split_mesh_gives_back_the_unsplit_one():
    grid = _grid()
    centroid_x = grid.vertices[grid.polygon_vertices.reshape(-1, 4)].mean(axis=1)[:, 0]
    split, seam = split_mesh(grid, centroid_x > 2.5)
    assert len(seam) == 6 and split.n_vertices == 42
    representative = coincident_vertices(split.vertices)
    np.testing.assert_array_equal(representative[36:], seam)
    welded, keep, index = weld_vertices(split, representative)
    np.testing.assert_array_equal(welded.vertices, grid.vertices)
    np.testing.assert_array_equal(welded.polygon_vertices, grid.polygon_vertices)
    np.testing.assert_array_equal(keep, np.arange(36))
    np.testing.assert_array_equal(index[36:], seam)


def test_vertices_that_part_in_a_pose_are_not_a_seam():
    """Lips that touch at rest and part when the jaw opens are two vertices, not one split."""
    rest = np.array([[0.0, 0, 0], [1, 0, 0], [0, 0, 0]])
    parted = rest + np.array([[0, 0.1, 0], [0, 0, 0], [0, -0.1, 0]])
    assert split_vertices(rest, parted[None]) is None
    np.testing.assert_array_equal(split_vertices(rest, rest[None] + 0.5), [0, 1, 0])
    assert split_vertices(rest[:2], np.zeros((0, 2, 3))) is None


@pytest.fixture(scope="module")
def rigs(tmp_path_factory):
    """The sample rig, and a copy whose rest mesh and examples are split along a seam down the face."""
    d = tmp_path_factory.mktemp("weld")
    assert run("sample", d / "whole", "--vertices", 2000, "--frames", 12, "--examples", 4, "-q") == 0
    whole = d / "whole"
    mesh = load_mesh(whole / "neutral.obj")
    centroid_x = np.array([mesh.vertices[mesh.polygon_vertices[a:b]].mean(axis=0)[0]
                           for a, b in zip(mesh.polygon_offsets[:-1], mesh.polygon_offsets[1:])])
    split, seam = split_mesh(mesh, centroid_x > np.median(centroid_x))
    cut = d / "split"
    cut.mkdir()
    for name in ("markers.csv", "anchors.txt", "sample.toml", "take.csv"):
        (cut / name).write_bytes((whole / name).read_bytes())
    save_obj(cut / "neutral.obj", split)
    (cut / "expressions").mkdir()
    for pose in sorted((whole / "expressions").glob("*.obj")):
        v = load_vertices(pose)
        save_obj(cut / "expressions" / pose.name, replace(split, vertices=np.concatenate([v, v[seam]])))
    return d, seam, mesh.n_vertices


def test_a_split_mesh_is_refused_with_the_fix(rigs, capsys):
    d, seam, n = rigs
    assert run("fit", d / "split" / "sample.toml", "--no-tune", "-o", d / "refused.npz", "-q") == 2
    err = capsys.readouterr().err
    assert f"{len(seam)} vertices sit exactly on another vertex" in err and "weld = true" in err
    assert not (d / "refused.npz").exists()


def _baked(d) -> None:
    """The split rig welded (``weld = true``) and the whole rig, baked and their takes replayed."""
    config = d / "split" / "sample_weld.toml"
    if not config.exists():
        text = (d / "split" / "sample.toml").read_text()
        config.write_text(text.replace('units = "cm"', 'units = "cm"\nweld = true', 1))
    for name, rig, cfg in (("welded", d / "split", config), ("whole", d / "whole", d / "whole" / "sample.toml")):
        if not (d / f"out_{name}" / "positions.npy").exists():
            assert run("bake", cfg, "--no-tune", "-o", d / f"{name}.npz", "-q") == 0
            assert run("replay", rig / "take.csv", "-m", d / f"{name}.npz", "-o", d / f"out_{name}", "--backend",
                       "numpy", "-q") == 0


def test_weld_gives_the_unsplit_rigs_replay(rigs, capsys):
    d, seam, n = rigs
    _baked(d)
    assert run("fit", d / "split" / "sample_weld.toml", "--no-tune", "-o", d / "welded_fit.npz") == 0
    assert f"{len(seam)} vertices split along seams welded" in capsys.readouterr().out
    welded = np.load(d / "out_welded" / "positions.npy")
    assert welded.shape[1] == n
    np.testing.assert_array_equal(welded, np.load(d / "out_whole" / "positions.npy"))
    assert load_model(d / "welded.npz").meta["welded"] == {"vertices": n + len(seam), "welded": n, "split": len(seam)}


def test_caches_in_the_mesh_files_order_go_in_and_out(rigs, capsys):
    """MDD and PC2 exports of a welded rig's replay are in the mesh file's vertex order (to drive
    the user's own mesh, the seams' copies equal); a cache in that order replays on the welded
    model (NumPy and OpenCL) as the unsplit rig replays the unsplit cache; a cache of neither
    count is refused."""
    from facepipe.io.point_caches import read_mdd, read_pc2, write_mdd

    d, seam, n = rigs
    _baked(d)
    assert run("export", d / "out_welded", "--format", "mdd", "-o", d / "welded.mdd") == 0
    assert "mesh file's vertex order" in capsys.readouterr().out
    assert run("export", d / "out_welded", "--format", "pc2", "-o", d / "welded.pc2", "-q") == 0
    final = np.load(d / "out_welded" / "positions.npy")
    for frames in (read_mdd(d / "welded.mdd")[1], read_pc2(d / "welded.pc2")[2]):
        assert frames.shape[1] == n + len(seam)
        np.testing.assert_array_equal(frames[:, :n], final)
        np.testing.assert_array_equal(frames[:, n:], final[:, seam])
    times, smooth = read_mdd(d / "whole" / "take_smooth.mdd")[:2]
    write_mdd(d / "split_smooth.mdd", np.concatenate([smooth, smooth[:, seam]], axis=1), times)
    for backend in ("numpy", "auto"):
        for name, cache, model in (("split", d / "split_smooth.mdd", "welded"),
                                   ("whole", d / "whole" / "take_smooth.mdd", "whole")):
            assert run("replay", cache, "-m", d / f"{model}.npz", "-o", d / f"cache_{name}_{backend}", "--backend",
                       backend, "-q") == 0
        np.testing.assert_array_equal(np.load(d / f"cache_split_{backend}" / "positions.npy"),
                                      np.load(d / f"cache_whole_{backend}" / "positions.npy"))
    write_mdd(d / "wrong.mdd", smooth[:, :-1], times)
    assert run("replay", d / "wrong.mdd", "-m", d / "welded.npz", "-o", d / "wrong", "-q") == 2
    assert "vertices per frame" in capsys.readouterr().err and not (d / "wrong" / "positions.npy").exists()


def test_a_welded_rigs_replay_is_geometry_in_the_mesh_files_order(rigs):
    """Appearance works on the mesh file (its UV layout, its vertex groups): a welded rig's replay
    given as a take's geometry is read in the file's order."""
    from facepipe.pipeline.appearance import read_take_geometry

    d, seam, n = rigs
    _baked(d)
    geometry = read_take_geometry(d / "out_welded", n + len(seam))
    final = np.load(d / "out_welded" / "positions.npy")
    positions = np.asarray(geometry.positions)
    assert positions.shape == (len(final), n + len(seam), 3)
    np.testing.assert_array_equal(positions[:, :n], final)
    np.testing.assert_array_equal(positions[:, n:], final[:, seam])
    np.testing.assert_array_equal(read_take_geometry(d / "out_welded", n).positions, final)


def test_transfer_onto_a_split_target_needs_target_weld_and_then_equals_the_unsplit_one(rigs, capsys):
    d, seam, n = rigs
    _baked(d)
    rows = (d / "whole" / "markers.csv").read_text().splitlines()[1:]
    points = d / "points.csv"
    points.write_text("name,vertex\n" + "".join(f"{r.split(',')[0]},{r.split(',')[1]}\n" for r in rows[::2]))
    args = ("transfer", d / "whole.npz", "--source-points", points, "--target-points", points, "-q")
    assert run(*args, "--target", d / "split" / "neutral.obj", "-o", d / "t_refused.npz") == 2
    assert "--target-weld" in capsys.readouterr().err and not (d / "t_refused.npz").exists()
    assert run(*args, "--target", d / "split" / "neutral.obj", "-o", d / "t_split.npz", "--target-weld") == 0
    assert run(*args, "--target", d / "whole" / "neutral.obj", "-o", d / "t_whole.npz") == 0
    split, whole = load_model(d / "t_split.npz"), load_model(d / "t_whole.npz")
    assert split.meta["welded"]["split"] == len(seam) and len(split.weld_index) == n + len(seam)
    for key in ("rest", "B", "rbf_weights", "handle_vertices", "anchors"):
        np.testing.assert_array_equal(getattr(split, key), getattr(whole, key))


def test_an_island_a_seam_cuts_off_is_named_with_the_weld_hint(rigs, tmp_path, capsys):
    """A seam around one polygon cuts it off as a part without a handle or anchor: that error comes
    first (before the examples are read) and its hint points at the seams."""
    d, _, _ = rigs
    whole = d / "whole"
    mesh = load_mesh(whole / "neutral.obj")
    taken = {int(r.split(",")[1]) for r in (whole / "markers.csv").read_text().splitlines()[1:]}
    taken |= {int(x) for x in (whole / "anchors.txt").read_text().split()}
    free = [k for k, (a, b) in enumerate(zip(mesh.polygon_offsets[:-1], mesh.polygon_offsets[1:]))
            if not taken & set(mesh.polygon_vertices[a:b].tolist())]
    island = np.zeros(mesh.n_polygons, bool)
    island[free[len(free) // 2]] = True
    split, _ = split_mesh(mesh, island)
    rig = tmp_path / "rig"
    rig.mkdir()
    for name in ("markers.csv", "anchors.txt", "sample.toml"):
        (rig / name).write_bytes((whole / name).read_bytes())
    save_obj(rig / "neutral.obj", split)
    (rig / "expressions").mkdir()
    assert run("fit", rig / "sample.toml", "--no-tune", "-o", tmp_path / "fit.npz", "-q") == 2
    err = capsys.readouterr().err
    assert "no handle or anchor vertex" in err and "weld = true" in err


def test_a_landmark_map_given_at_replay_numbers_the_mesh_files_vertices(rigs):
    """A welded model's --landmarks map, like its config's, names the mesh file's vertices."""
    from facepipe.pipeline.video_replay import landmark_map_for

    d, seam, n = rigs
    _baked(d)
    model = load_model(d / "welded.npz")
    path = d / "landmarks.csv"
    file_vertices = [0, 1, 2, 3, n, n + len(seam) - 1]  # the last two: copies at the seam
    path.write_text("name,vertex\n" + "".join(f"p{i},{v}\n" for i, v in enumerate(file_vertices)))
    lmap = landmark_map_for(model, path, d / "take.csv")
    assert lmap.vertices.tolist() == [0, 1, 2, 3, int(seam[0]), int(seam[-1])]


def _split_truth(d, seam, path) -> None:
    """The sample take's truth on the split mesh (the seams' copies appended), written to ``path``."""
    truth = np.load(d / "whole" / "take_truth.npz")
    np.savez(path, **{k: truth[k] for k in truth.files if k != "positions"},
             positions=np.concatenate([truth["positions"], truth["positions"][:, seam]], axis=1))


def test_eval_reads_a_truth_in_the_mesh_files_order(rigs, capsys):
    """A welded rig's replay evaluated against a truth of the split mesh (the user's own): the same
    figures as against the unsplit truth."""
    d, seam, n = rigs
    _baked(d)
    _split_truth(d, seam, d / "split_truth.npz")
    printed = []
    for path in (d / "split_truth.npz", d / "whole" / "take_truth.npz"):
        assert run("eval", d / "out_welded", "--truth", path) == 0
        printed.append(capsys.readouterr().out.split("wrote")[0])
    assert printed[0] == printed[1] and "RMS mean" in printed[0]


def test_eval_vertices_number_the_mesh_files_vertices(rigs, capsys):
    """``eval --vertices A:B`` on a welded rig's replay numbers the mesh file's vertices (as the
    user's tools do): the seams' copies, past the welded count, are measured on their welded
    vertices, and the whole file's range gives the seams twice, as the file has them."""
    d, seam, n = rigs
    _baked(d)
    _split_truth(d, seam, d / "split_truth.npz")
    # the unsplit replay equals the welded one: its error on the seam's vertices, computed here
    whole = np.load(d / "out_whole" / "positions.npy").astype(np.float64)
    truth = np.load(d / "whole" / "take_truth.npz")["positions"].astype(np.float64)
    frames = json.loads((d / "out_whole" / "replay.json").read_text())["frame_numbers"]
    truth = truth[np.asarray(frames)]
    for span, vertices in ((f"{n}:{n + len(seam)}", seam), (f"0:{n + len(seam)}", np.r_[np.arange(n), seam])):
        assert run("eval", d / "out_welded", "--truth", d / "split_truth.npz", "--vertices", span) == 0
        assert "of the mesh file" in capsys.readouterr().out
        result = json.loads((d / "out_welded" / "eval.json").read_text())
        assert result["vertices_numbered_by"] == "mesh file" and result["vertices"] == [int(x) for x in span.split(":")]
        expected = np.sqrt((np.linalg.norm(whole[:, vertices] - truth[:, vertices], axis=-1) ** 2).mean(axis=1))
        np.testing.assert_allclose(result["final"]["per_frame_rms"], expected, rtol=1e-9, atol=1e-12)
    # past the file's vertices: refused, naming its range, and no eval.json written
    (d / "out_welded" / "eval.json").unlink()
    assert run("eval", d / "out_welded", "--truth", d / "split_truth.npz", "--vertices", f"0:{n + len(seam) + 1}") == 2
    assert f"[0, {n + len(seam)})" in capsys.readouterr().err
    assert not (d / "out_welded" / "eval.json").exists()


def test_add_details_keeps_the_mesh_files_order(rigs):
    """The API on a welded rig: frames in the mesh file's order come back in it, the seams' copies
    moving together, the welded vertices as from frames in the model's order."""
    import facepipe

    d, seam, n = rigs
    _baked(d)
    model = facepipe.load_model(d / "welded.npz")
    times, smooth = read_mdd_frames(d / "whole" / "take_smooth.mdd")
    split = facepipe.add_details(model, np.concatenate([smooth, smooth[:, seam]], axis=1))
    welded = facepipe.add_details(model, smooth)
    assert split.positions.shape == (len(smooth), n + len(seam), 3)
    np.testing.assert_array_equal(split.positions[:, :n], welded.positions)
    np.testing.assert_array_equal(split.positions[:, n:], welded.positions[:, seam])


def read_mdd_frames(path):
    from facepipe.io.point_caches import read_mdd

    times, frames = read_mdd(path)[:2]
    return times, np.asarray(frames, dtype=np.float64)


def test_the_editor_reads_a_truth_in_the_mesh_files_order(rigs, tmp_path):
    from facepipe.cli.editor import prepared_take
    from facepipe.editor.session import EditorSession

    d, seam, n = rigs
    _baked(d)
    _split_truth(d, seam, tmp_path / "split_truth.npz")
    model = load_model(d / "welded.npz")
    take = prepared_take(d / "split" / "take.csv", model)
    sessions = [EditorSession(model, take, tmp_path / f"e{i}.json", mode="server", truth_path=path)
                for i, path in enumerate((tmp_path / "split_truth.npz", d / "whole" / "take_truth.npz"))]
    try:
        np.testing.assert_array_equal(sessions[0].truth[0], sessions[1].truth[0])
        assert sessions[0].truth[0].shape[1] == n
    finally:
        for session in sessions:
            session.close()


def _split_config(d, tmp_path, replace_in=None):
    """A copy of the split rig's files in ``tmp_path`` with its config's text changed by ``replace_in``."""
    rig = tmp_path / "rig"
    rig.mkdir()
    for f in (d / "split").iterdir():
        if f.is_file():
            (rig / f.name).write_bytes(f.read_bytes())
    (rig / "expressions").symlink_to(d / "split" / "expressions")
    text = (rig / "sample.toml").read_text()
    (rig / "sample.toml").write_text(replace_in(text) if replace_in else text)
    return rig


@pytest.mark.parametrize("case", ["weld not a bool", "markers on both copies of a seam vertex"])
def test_bad_weld_input_is_refused_before_any_output(rigs, tmp_path, capsys, case):
    d, seam, n = rigs
    if case == "weld not a bool":
        rig = _split_config(d, tmp_path, lambda t: t.replace('units = "cm"', 'units = "cm"\nweld = "yes"', 1))
        expected = ['weld = "yes"', "true or false"]
    else:
        rig = _split_config(d, tmp_path, lambda t: t.replace('units = "cm"', 'units = "cm"\nweld = true', 1))
        lines = (rig / "markers.csv").read_text().splitlines()
        lines.append(f"EXTRA,{n + 0},handle")  # the copy of seam vertex seam[0], which a marker may hold too
        lines.append(f"EXTRA2,{int(seam[0])},handle")
        (rig / "markers.csv").write_text("\n".join(lines) + "\n")
        expected = ["EXTRA", "EXTRA2", "copies of one vertex split at a seam"]
    assert run("fit", rig / "sample.toml", "--no-tune", "-o", tmp_path / "fit.npz", "-q") == 2
    err = capsys.readouterr().err
    assert all(e in err for e in expected), err
    assert "Traceback" not in err and not (tmp_path / "fit.npz").exists()


def test_a_welded_models_landmark_map_out_of_the_files_range_is_refused(rigs, tmp_path):
    from facepipe.errors import InputError
    from facepipe.pipeline.video_replay import landmark_map_for

    d, seam, n = rigs
    _baked(d)
    model = load_model(d / "welded.npz")
    path = tmp_path / "landmarks.csv"
    path.write_text("name,vertex\n" + "".join(f"p{i},{i}\n" for i in range(5)) + f"p5,{n + len(seam)}\n")
    with pytest.raises(InputError, match=str(n + len(seam))):
        landmark_map_for(model, path, tmp_path / "take.csv")
