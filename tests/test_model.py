"""The model file's schema: a typed Model, older files read the same, the rest mesh's groups kept."""

import json
from dataclasses import fields, is_dataclass

import numpy as np
import pytest

from facepipe.core.mesh import Mesh
from facepipe.io.mesh_read import load_mesh
from facepipe.io.mesh_write import save_obj
from facepipe.errors import InputError
from facepipe.export.common import write_obj_sequence
from facepipe.io.model_file import (Model, add_model_arrays, geometry_to, load_model, model_arrays, model_from_fit,
                                    save_model)
from facepipe.io.npz_file import NpzWriter
from facepipe.pipeline.fit import fit_rig
from facepipe.pipeline.rig import load_rig
from facepipe.sample_rig import write_sample_rig

# every array a model file of format version 1 held before the groups were kept, and its dtype
# there (facepipe's save_model of that version)
DTYPES_BEFORE = {"rest": np.float32, "triangles": np.int32, "polygon_offsets": np.int64, "polygon_vertices": np.int32,
                 "handle_vertices": np.int32, "stable": np.bool_, "anchors": np.int32, "B": np.float32,
                 "edges": np.int32, "rest_lengths": np.float32, "frame_neighbors": np.int32,
                 "basis_features": np.float32, "rbf_weights": np.float32, "rbf_const": np.float32,
                 "edge_index": np.int32, "edge_weight": np.float32, "example_handles": np.float32}
OPTIONAL_BEFORE = {"uvs": np.float32, "polygon_uvs": np.int32, "novelty_index": np.int32,
                   "novelty_weight": np.float32, "novelty_examples": np.float32, "novelty_solve": np.float32,
                   # the novelty gate's motion part
                   "novelty_motion_index": np.int32, "novelty_motion_weight": np.float32,
                   "novelty_motion_examples": np.float32, "novelty_motion_scale": np.float32}
ARRAYS_BEFORE = list(DTYPES_BEFORE)
GROUP_NAMES = ["default", "brow", "cheek", "jaw"]


def group_rest_mesh(path) -> Mesh:
    """Rewrite the OBJ at ``path`` with its polygons in named groups: bands across the face,
    every band in several runs (polygon order is row by row), a few polygons left ungrouped."""
    mesh = load_mesh(path)
    centre = np.add.reduceat(mesh.vertices[mesh.polygon_vertices], mesh.polygon_offsets[:-1]) \
        / mesh.polygon_sizes[:, None]
    x = centre[:, 0]
    band = np.digitize(x, np.quantile(x, [0.3, 0.6])) + 1  # 1, 2 or 3
    band[:5] = 0  # "default": written as `g default` where it starts a run
    grouped = Mesh(mesh.vertices, mesh.polygon_offsets, mesh.polygon_vertices, mesh.uvs, mesh.polygon_uvs,
                   band.astype(np.int32), list(GROUP_NAMES), path=str(path))
    save_obj(path, grouped)
    return grouped


@pytest.fixture(scope="module")
def grouped(tmp_path_factory):
    """A small sample rig whose rest mesh has OBJ groups, fitted."""
    root = tmp_path_factory.mktemp("grouped")
    info = write_sample_rig(root / "rig", n_vertices=2000, n_examples=3, n_frames=4)
    mesh = group_rest_mesh(info["mesh"])
    rig = load_rig(info["config"])
    return root, mesh, rig, fit_rig(rig)


def test_model_is_a_dataclass_with_every_field_named_and_typed():
    assert is_dataclass(Model) and "__getattr__" not in vars(Model)
    by_name = {f.name: f for f in fields(Model)}
    assert set(ARRAYS_BEFORE + list(OPTIONAL_BEFORE) + ["polygon_groups", "group_names", "landmark_vertices",
                                                         "weld_index", "strain_samples", "strain_weights", "meta",
                                                         "path"]) == set(by_name)
    for name in ARRAYS_BEFORE + list(OPTIONAL_BEFORE) + ["polygon_groups", "group_names", "landmark_vertices",
                                                         "weld_index"]:
        assert "dtype" in by_name[name].metadata, name  # the dtype it is stored as
        assert by_name[name].type, name
        assert f"\n    {name}" in Model.__doc__ or f", {name}" in Model.__doc__, f"{name} is not documented"
    for name in list(OPTIONAL_BEFORE) + ["polygon_groups", "group_names", "landmark_vertices", "weld_index"]:
        assert by_name[name].default is None and "None" in str(by_name[name].type), name


def test_a_file_written_before_loads_the_same(grouped, tmp_path):
    """A model file as format version 1 wrote it (its arrays only, no groups) loads field by field
    as stored; the optional parts it lacks are None; it saves back to the same arrays."""
    _, _, rig, fit = grouped
    arrays, meta = model_arrays(fit, rig)
    path = tmp_path / "before.npz"
    out = {k: np.ascontiguousarray(arrays[k], dtype=d) for k, d in {**DTYPES_BEFORE, **OPTIONAL_BEFORE}.items()
           if k in arrays}
    out["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez(path, **out)

    model = load_model(path)
    for name, stored in out.items():
        if name != "meta":
            got = getattr(model, name)
            assert got.dtype == stored.dtype and np.array_equal(got, stored), name
    assert model.meta == meta and model.method == meta["method"] and model.n_vertices == rig.mesh.n_vertices
    assert model.polygon_groups is None and model.group_names is None
    assert model.mesh().polygon_groups is None and model.mesh().uvs is not None
    save_model(tmp_path / "again.npz", model.arrays, model.meta)
    with np.load(tmp_path / "again.npz") as again:
        assert set(again.files) == set(out)
        for name in out:
            assert np.array_equal(again[name], out[name]), name


def test_groups_are_kept_through_fit_bake_and_export(grouped, tmp_path):
    _, mesh, rig, fit = grouped
    memory = model_from_fit(fit, rig)
    assert memory.group_names == GROUP_NAMES and np.array_equal(memory.polygon_groups, mesh.polygon_groups)
    arrays, meta = model_arrays(fit, rig)
    save_model(tmp_path / "m.npz", arrays, meta)
    model = load_model(tmp_path / "m.npz")
    assert model.group_names == GROUP_NAMES and model.polygon_groups.dtype == np.int32
    np.testing.assert_array_equal(model.polygon_groups, mesh.polygon_groups)
    paths = write_obj_sequence(model.mesh(), model.rest[None], tmp_path / "obj")
    back = load_mesh(paths[0])
    assert [back.group_names[g] for g in back.polygon_groups] == [GROUP_NAMES[g] for g in mesh.polygon_groups]


def test_a_mesh_without_named_groups_stores_none(grouped):
    _, _, rig, fit = grouped
    plain = Mesh(rig.mesh.vertices, rig.mesh.polygon_offsets, rig.mesh.polygon_vertices, rig.mesh.uvs,
                 rig.mesh.polygon_uvs, np.zeros(rig.mesh.n_polygons, np.int32), ["default"])
    rig_plain = type(rig)(rig.config, plain, rig.markers, rig.anchors, rig.example_names, rig.example_positions,
                          rig.digest)
    arrays, _ = model_arrays(fit, rig_plain)
    assert "polygon_groups" not in arrays and "group_names" not in arrays


@pytest.mark.parametrize("change, message", [
    (lambda a: a.pop("group_names"), "without their names"),
    (lambda a: a.pop("polygon_groups"), "without their names"),
    (lambda a: a.update(polygon_groups=a["polygon_groups"][:-1]), "polygon groups have shape"),
    (lambda a: a.update(polygon_groups=a["polygon_groups"] + 4), "not all among the 4 group names"),
])
def test_corrupt_groups_are_refused(grouped, tmp_path, change, message):
    _, _, rig, fit = grouped
    arrays, meta = model_arrays(fit, rig)
    change(arrays)
    save_model(tmp_path / "bad.npz", arrays, meta)
    with pytest.raises(InputError, match=message):
        load_model(tmp_path / "bad.npz")


def test_a_bake_that_writes_its_geometry_while_fitting_writes_the_same_file(grouped, tmp_path):
    """The bake hands the geometry to the writer as soon as it is solved (``on_geometry``) and the
    rest at the end: the file holds what save_model writes at once, member for member."""
    _, _, rig, fit = grouped
    arrays, meta = model_arrays(fit, rig)
    save_model(tmp_path / "at_once.npz", arrays, meta)
    with NpzWriter(tmp_path / "in_parts.npz") as npz:
        refit = fit_rig(rig, on_geometry=geometry_to(npz))
        assert "B" in npz and "rbf_weights" not in npz  # the geometry went first
        add_model_arrays(npz, *model_arrays(refit, rig))
    with np.load(tmp_path / "at_once.npz") as a, np.load(tmp_path / "in_parts.npz") as b:
        assert sorted(a.files) == sorted(b.files)
        for name in a.files:
            assert a[name].dtype == b[name].dtype and np.array_equal(a[name], b[name]), name
    assert load_model(tmp_path / "in_parts.npz").meta == meta


@pytest.mark.parametrize("chunked_bytes", [0, 4096, 1 << 30])
def test_large_members_cast_a_chunk_at_a_time_are_the_bytes_np_savez_writes(tmp_path, monkeypatch, chunked_bytes):
    """Above NpzWriter.CHUNKED_BYTES an array to be cast or laid out anew is converted 16 MB at a
    time (no whole copy): each member is byte for byte what np.savez writes of the converted array."""
    import zipfile

    monkeypatch.setattr(NpzWriter, "CHUNKED_BYTES", chunked_bytes)
    rng = np.random.default_rng(5)
    arrays = {"f_order": (np.asfortranarray(rng.normal(size=(3000, 89))), np.float32),
              "strided": (rng.normal(size=(700, 3, 4))[:, ::2], None),
              "same": (np.arange(5000, dtype=np.int64).reshape(50, 100), np.int32),
              "one_d": (rng.normal(size=20001), np.float32),
              "empty": (np.zeros((0, 3)), np.float32)}
    with NpzWriter(tmp_path / "parts.npz") as npz:
        for name, (a, dtype) in arrays.items():
            npz.add(name, a, dtype)
    np.savez(tmp_path / "whole.npz", **{name: np.ascontiguousarray(a, dtype=dtype) for name, (a, dtype) in arrays.items()})
    with zipfile.ZipFile(tmp_path / "parts.npz") as p, zipfile.ZipFile(tmp_path / "whole.npz") as w:
        for name in arrays:
            assert p.read(name + ".npy") == w.read(name + ".npy"), name


def test_an_archive_written_in_parts_is_whole_or_absent(tmp_path):
    rng = np.random.default_rng(2)
    big = rng.normal(size=(300, 89))
    with NpzWriter(tmp_path / "a.npz") as npz:
        npz.add("big", np.asfortranarray(big), np.float32)
        npz.add("names", np.asarray(["brow", "jaw"]))
        with pytest.raises(ValueError, match="already in the archive"):
            npz.add("big", big)
    with np.load(tmp_path / "a.npz") as a:
        assert a["big"].dtype == np.float32 and np.array_equal(a["big"], big.astype(np.float32))
        assert a["names"].tolist() == ["brow", "jaw"]
    # an error in the caller's block: no file under the name, no temporary file left beside it
    with pytest.raises(KeyboardInterrupt):
        with NpzWriter(tmp_path / "b.npz") as npz:
            npz.add("big", big)
            raise KeyboardInterrupt
    # an error in a background write (here an array that cannot be cast) is raised at the end
    with pytest.raises(ValueError):
        with NpzWriter(tmp_path / "c.npz") as npz:
            npz.add("big", big)
            npz.add("text", np.asarray(["not a number"]), np.float64)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz"]
    # an existing file of the name is replaced only by a whole one
    (tmp_path / "d.npz").write_bytes(b"the previous bake")
    with pytest.raises(RuntimeError):
        with NpzWriter(tmp_path / "d.npz") as npz:
            npz.add("big", big)
            raise RuntimeError("the fit failed")
    assert (tmp_path / "d.npz").read_bytes() == b"the previous bake"


def test_a_bake_that_fails_after_writing_its_geometry_leaves_no_file(tmp_path, monkeypatch, capsys):
    """The geometry is already being written when a later stage fails: `facepipe bake` exits 2
    with the error, and neither the model nor its temporary file is left (an older model of the
    name stays whole)."""
    import facepipe.pipeline.fit as fit_module
    from facepipe.errors import InputError
    from tests.conftest import run_cli

    info = write_sample_rig(tmp_path / "rig", n_vertices=2000, n_examples=3, n_frames=4)
    out = tmp_path / "out"
    out.mkdir()
    (out / "model.npz").write_bytes(b"an older bake")
    written = []

    def greedy_fails(*args, **kwargs):
        written.extend(p.name for p in out.iterdir())
        raise InputError("the examples disagree", path=info["config"])

    monkeypatch.setattr(fit_module, "greedy_bases", greedy_fails)
    assert run_cli("bake", info["config"], "-o", out / "model.npz", "--no-tune", "-q") == 2
    assert "the examples disagree" in capsys.readouterr().err
    assert any(name.endswith(".part.npz") for name in written)  # the geometry was being written
    assert sorted(p.name for p in out.iterdir()) == ["model.npz"]
    assert (out / "model.npz").read_bytes() == b"an older bake"
