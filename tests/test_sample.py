"""Tests of the synthetic sample rig (facepipe.sample_rig): files, geometry, wrinkles, take."""

import csv
import tomllib
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from facepipe import sample_rig as sample
from facepipe.errors import InputError
from facepipe.io.mesh_read import load_mesh

N = 3000
FRAMES = 12


@pytest.fixture(scope="module")
def rig():
    return sample.make_sample_arrays(N, n_frames=FRAMES, seed=3)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("sample")
    info = sample.write_sample_rig(out, n_vertices=N, n_frames=FRAMES, seed=3)
    return out, info


def _edges(faces):
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return e


# ----------------------------------------------------------------------------- files


def test_files_exist_and_counts(written, rig):
    out, info = written
    for name in ("sample.toml", "neutral.obj", "markers.csv", "anchors.txt", "take.csv", "take_truth.npz"):
        assert (out / name).is_file(), name
    assert len(info["expressions"]) == 8
    assert info["vertices"] == rig.mesh.n_vertices
    assert info["markers"] == 96 and info["handles"] == 90 and info["stable"] == 6
    assert info["frames"] == FRAMES
    assert not list(out.rglob("*.part*")), "temporary files left behind"


def test_obj_reads_back_with_uvs(written, rig):
    out, _ = written
    mesh = load_mesh(out / "neutral.obj")
    assert mesh.n_vertices == rig.mesh.n_vertices
    np.testing.assert_allclose(mesh.vertices, rig.mesh.vertices, atol=1e-5)
    assert mesh.uvs is not None and mesh.polygon_uvs is not None
    np.testing.assert_allclose(mesh.uvs[mesh.polygon_uvs], rig.mesh.uvs[rig.mesh.polygon_uvs], atol=1e-7)
    assert mesh.uvs.min() >= 0.0 and mesh.uvs.max() <= 1.0
    np.testing.assert_array_equal(mesh.faces, rig.mesh.faces)


def test_expression_objs(written, rig):
    out, _ = written
    names = sorted(Path(p).stem for p in (out / "expressions").glob("*.obj"))
    assert names == rig.example_names
    for k, name in enumerate(rig.example_names):
        mesh = load_mesh(out / "expressions" / f"{name}.obj")
        np.testing.assert_array_equal(mesh.faces, rig.mesh.faces)
        np.testing.assert_allclose(mesh.vertices, rig.example_positions[k], atol=1e-5)


def test_markers_and_anchors_files(written, rig):
    out, _ = written
    with open(out / "markers.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["name", "vertex", "role"]
    rows = rows[1:]
    assert [r[0] for r in rows] == rig.marker_names
    assert [int(r[1]) for r in rows] == rig.marker_vertices.tolist()
    roles = [r[2] for r in rows]
    assert roles == ["handle"] * 90 + ["stable"] * 6     # stable markers last
    anchors = np.loadtxt(out / "anchors.txt", dtype=np.int64)
    np.testing.assert_array_equal(anchors, rig.anchors)


def test_config(written):
    out, _ = written
    with open(out / "sample.toml", "rb") as fh:
        cfg = tomllib.load(fh)
    assert cfg["rig"] == {"mesh": "neutral.obj", "markers": "markers.csv", "anchors": "anchors.txt", "units": "cm"}
    for key in ("mesh", "markers", "anchors"):
        assert (out / cfg["rig"][key]).is_file()
    assert cfg["examples"]["meshes"] == ["expressions/*.obj"]
    assert len(list(out.glob(cfg["examples"]["meshes"][0]))) == 8
    assert cfg["features"]["graph"] == "auto"
    assert cfg["psd"]["method"] == "wpsd" and cfg["psd"]["fit"] == "interpolate"
    assert cfg["psd"]["max_poses"] == 8
    assert {"k_stretch", "k_bend"} <= set(cfg["shell"])


def test_take_csv_matches_truth(written, rig):
    out, _ = written
    with open(out / "take.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    header = rows[0]
    assert header[:2] == ["frame", "time"]
    assert header[2:] == [f"{n}_{c}" for n in rig.marker_names for c in "xyz"]
    assert header[-3:] == ["S06_x", "S06_y", "S06_z"]
    data = np.array(rows[1:], dtype=np.float64)
    assert data.shape == (FRAMES, 2 + 3 * 96)
    np.testing.assert_array_equal(data[:, 0], np.arange(FRAMES))
    np.testing.assert_allclose(data[:, 1], np.arange(FRAMES) / 30.0, atol=1e-6)
    assert all(len(cell.split(".")[1]) == 5 for cell in rows[1][2:])
    truth = np.load(out / "take_truth.npz")
    markers = truth["positions"][:, rig.marker_vertices].reshape(FRAMES, -1)
    np.testing.assert_allclose(data[:, 2:], markers, atol=1e-5)


def test_truth_npz_layout(written, rig):
    out, _ = written
    truth = np.load(out / "take_truth.npz")
    assert set(truth.files) == {"positions", "frame", "time", "rotation", "translation", "weights", "expressions"}
    V = rig.mesh.n_vertices
    assert truth["positions"].dtype == np.float32 and truth["positions"].shape == (FRAMES, V, 3)
    assert truth["frame"].dtype == np.int32 and truth["time"].dtype == np.float64
    assert truth["rotation"].dtype == np.float32 and truth["translation"].dtype == np.float32
    np.testing.assert_array_equal(truth["rotation"], np.broadcast_to(np.eye(3), (FRAMES, 3, 3)))
    np.testing.assert_array_equal(truth["translation"], 0)
    assert truth["weights"].dtype == np.float32 and truth["weights"].shape == (FRAMES, 8)
    assert truth["expressions"].dtype.kind == "U"
    assert truth["expressions"].tolist() == rig.example_names
    np.testing.assert_array_equal(truth["positions"], rig.take_positions)


def test_rewrite_removes_stale_examples_and_refuses_strangers(tmp_path):
    sample.write_sample_rig(tmp_path, n_vertices=2000, n_examples=8, n_frames=2)
    sample.write_sample_rig(tmp_path, n_vertices=2000, n_examples=6, n_frames=2)
    assert len(list((tmp_path / "expressions").glob("*.obj"))) == 6
    (tmp_path / "expressions" / "mine.obj").write_text("v 0 0 0\n")
    with pytest.raises(InputError, match="mine.obj"):
        sample.write_sample_rig(tmp_path, n_vertices=2000, n_frames=2)


# ----------------------------------------------------------------------------- geometry


def test_vertex_count_respected():
    for n in (2500, 9000):
        rest = sample._face_mesh(n)[0]
        assert abs(rest.shape[0] - n) <= 0.15 * n


def test_mesh_is_a_clean_manifold(rig):
    V, F = rig.mesh.vertices, rig.mesh.faces
    assert np.array_equal(np.unique(F), np.arange(len(V))), "unreferenced vertices"
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    assert area.min() > 1e-3 * area.mean()
    e = _edges(F)
    key = np.sort(e, axis=1)
    uniq, count = np.unique(key, axis=0, return_counts=True)
    assert count.max() <= 2, "an edge in more than two triangles"
    # consistently oriented: every directed edge appears once
    assert len(np.unique(e, axis=0)) == len(e)
    # no bow-tie vertex: each boundary vertex lies on exactly two boundary edges
    boundary = uniq[count == 1]
    assert np.all(np.bincount(boundary.ravel())[np.unique(boundary)] == 2)
    adj = scipy.sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(V), len(V)))
    assert connected_components(adj, directed=False)[0] == 1
    # Euler characteristic of a disc with one hole (the mouth slit): V - E + F = 0
    assert len(V) - len(uniq) + len(F) == 0


def test_size_and_markers(rig):
    V = rig.mesh.vertices
    extent = V.max(axis=0) - V.min(axis=0)
    assert 14 < extent[0] < 18 and 18 < extent[1] < 23 and 5 < extent[2] < 12
    mv = rig.marker_vertices
    assert len(np.unique(mv)) == 96
    assert rig.marker_names[:3] == ["M001", "M002", "M003"] and rig.marker_names[-1] == "S06"
    assert not np.isin(mv, rig.anchors).any()
    d = cKDTree(V[mv]).query(V[mv], k=2)[0][:, 1]
    assert 1.4 < d.mean() < 2.0
    # stable markers barely move in any expression
    still = np.linalg.norm(rig.example_positions[:, mv[90:]] - V[mv[90:]], axis=2)
    assert still.max() < 0.15


def test_markers_do_not_depend_on_resolution(rig):
    fine = sample.make_sample_arrays(12000, n_frames=1)
    a = rig.face_coords[rig.marker_vertices]
    b = fine.face_coords[fine.marker_vertices]
    assert np.abs(a - b).max() < 0.4            # within a coarse grid cell


# ----------------------------------------------------------------------------- examples


def test_anchors_never_move(rig):
    rest = rig.mesh.vertices[rig.anchors]
    np.testing.assert_array_equal(rig.example_positions[:, rig.anchors], np.broadcast_to(rest, (8,) + rest.shape))
    np.testing.assert_array_equal(rig.take_positions[:, rig.anchors],
                                  np.broadcast_to(rest.astype(np.float32), (FRAMES,) + rest.shape))


def test_examples_move_by_centimetres(rig):
    d = np.linalg.norm(rig.example_positions - rig.mesh.vertices, axis=2).max(axis=1)
    assert np.all((d > 0.3) & (d < 1.6))


def test_wrinkles_only_where_compressed(rig):
    for k, name in enumerate(rig.example_names):
        w = rig.example_wrinkles[k]
        compressed = rig.example_compression[k].max(axis=1) > sample.WRINKLE_CRITICAL
        assert np.all(w[~compressed] == 0), name
        assert np.abs(w).max() > 0.03, name
        assert np.abs(w).max() <= 2 * sample.WRINKLE_MAX + 1e-12, name


def test_wrinkles_finer_than_markers(rig):
    mv = rig.marker_vertices
    spacing = cKDTree(rig.mesh.vertices[mv]).query(rig.mesh.vertices[mv], k=2)[0][:, 1].mean()
    assert spacing > 2 * rig.wavelength


def test_wrinkle_wavelength_on_the_surface():
    # the forehead wrinkles of browRaise: horizontal lines, so along the mid line x = 0 the
    # offsets oscillate with the wavelength in y
    rig = sample.make_sample_arrays(20000, n_frames=1)
    k = rig.example_names.index("browRaise")
    xy = rig.face_coords
    line = np.flatnonzero(np.abs(xy[:, 0]) < 1e-9)
    line = line[np.argsort(xy[line, 1])]
    w, y = rig.example_wrinkles[k][line], xy[line, 1]
    strong = np.abs(w) > 0.3 * np.abs(w).max()
    peaks = y[1:-1][(w[1:-1] > w[:-2]) & (w[1:-1] > w[2:]) & strong[1:-1]]
    assert len(peaks) >= 3
    np.testing.assert_allclose(np.median(np.diff(peaks)), rig.wavelength, rtol=0.15)


# ----------------------------------------------------------------------------- take


def test_take_weights(rig):
    W = rig.take_weights
    assert W.shape == (FRAMES, 8) and W.dtype == np.float32
    assert W.min() >= 0 and W.max() <= 1
    long = sample.make_sample_arrays(N, n_frames=120, seed=0).take_weights
    assert np.all(long.max(axis=0) > 0.4), "every expression appears"
    active = (long > 0.05).sum(axis=1).mean()
    assert 1.0 < active < 5.0
    assert np.abs(np.diff(long, axis=0)).max() < 0.25, "weights vary smoothly"


def test_take_is_nonlinear_in_the_weights():
    rig = sample.make_sample_arrays(N, n_frames=60, seed=1)
    neutral = rig.mesh.vertices
    blend = neutral + np.einsum("te,evk->tvk", rig.take_weights.astype(np.float64), rig.example_positions - neutral)
    diff = np.linalg.norm(rig.take_positions - blend, axis=2)
    assert diff.max() > 0.02                    # wrinkles of a mix are not the mix of the wrinkles
    assert diff.max() < 0.5


def test_deterministic(rig):
    again = sample.make_sample_arrays(N, n_frames=FRAMES, seed=3)
    for name in ("marker_vertices", "anchors", "example_positions", "take_positions", "take_weights"):
        np.testing.assert_array_equal(getattr(rig, name), getattr(again, name))
    np.testing.assert_array_equal(rig.mesh.vertices, again.mesh.vertices)
    other = sample.make_sample_arrays(N, n_frames=FRAMES, seed=4)
    np.testing.assert_array_equal(rig.example_positions, other.example_positions)
    assert not np.array_equal(rig.take_weights, other.take_weights)


@pytest.mark.parametrize("kwargs", [{"n_vertices": 100}, {"n_examples": 0}, {"n_examples": 13},
                                    {"n_frames": 0}])
def test_bad_counts(kwargs):
    with pytest.raises(InputError):
        sample.make_sample_arrays(**{"n_vertices": N, **kwargs})
