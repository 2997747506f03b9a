"""EXR displacement maps and wrinkle-map sets: read back with OpenEXR, checked against the model.

The reference values are computed independently of the export path: the final and
large-scale surfaces of the NumPy evaluator (or the replay's own positions.npy and
large_scale.npy), the local frames of the large-scale surface, and plain NumPy distances.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import scipy.ndimage

import facepipe.export.exr_maps as maps
from facepipe.errors import InputError
from facepipe.core.tangent_frames import local_frames, to_local
from facepipe.pipeline.detail_layers import uv_tangent_frames
from facepipe.io.model_file import load_model, save_model
from facepipe.pipeline.replay import NumpyEvaluator
from facepipe.export.uv_raster import corner_uv_lookups, uv_to_texel
from tests.conftest import ict_or_skip
from tests.conftest import run_cli as run


def read(path):
    """Channels of an EXR as float64 arrays, and its header (OpenEXR's own reader)."""
    f = OpenEXR.File(str(path), separate_channels=True)
    ch = f.channels()
    names = sorted(ch)
    img = np.stack([ch[c].pixels.astype(np.float64) for c in ("R", "G", "B")], axis=-1) if names == ["B", "G", "R"] \
        else ch["Y"].pixels.astype(np.float64)
    return img, f.header(), {c: ch[c].pixels.dtype for c in names}


def sample(img, uv):
    """Bilinear lookup by scipy (texel centres at (i + ½)/size, row 0 = v 1)."""
    H, W = img.shape[:2]
    x, y = uv_to_texel(uv, W, H)
    chans = img[..., None] if img.ndim == 2 else img
    out = np.stack([scipy.ndimage.map_coordinates(chans[..., c], [y, x], order=1, mode="nearest")
                    for c in range(chans.shape[-1])], axis=-1)
    return out[:, 0] if img.ndim == 2 else out


def reference(model, replay_dir):
    """Final and large-scale surfaces in head space, and the details in local frames."""
    head = np.load(replay_dir / "handles.npz")["head"].astype(np.float64)
    final, large = NumpyEvaluator(model).evaluate(head, with_large=True)
    frames = local_frames(large, model.triangles.astype(np.int64), model.frame_neighbors.astype(np.int64))
    return final, large, frames, to_local(frames, final - large)


def relative_errors(got, want, floor=1e-6):
    """|got − want| over the per-channel range of want (at least ``floor``): (n, C)."""
    rng = want.max(axis=0) - want.min(axis=0)
    # a still frame (the rest pose) has no details at all: judge it against the map's own
    # precision instead of dividing by a zero range
    return np.abs(got - want) / np.maximum(rng, floor)


def test_detail_layer_is_final_minus_large_in_every_space(rig):
    from facepipe.pipeline.detail_layers import DetailLayer

    model = load_model(rig.models["wpsd"])
    replay_dir = rig.replays["wpsd"]
    h = np.load(replay_dir / "handles.npz")
    final, large, frames, local = reference(model, replay_dir)
    np.testing.assert_allclose(DetailLayer(model)(h["head"]), local, atol=1e-9)
    # object space in the take's space: the replay's own files, to float32 rounding
    pos = np.load(replay_dir / "positions.npy").astype(np.float64)
    lg = np.load(replay_dir / "large_scale.npy").astype(np.float64)
    obj = DetailLayer(model, "object")(h["head"], h["rotation"])
    np.testing.assert_allclose(obj, pos - lg, atol=1e-5 * np.abs(pos).max())
    # tangent space: an orthonormal change of basis per UV corner of the same vectors
    mesh = model.mesh()
    tan = DetailLayer(model, "tangent", mesh)(h["head"])
    v, _, _, ui = corner_uv_lookups(mesh)
    np.testing.assert_allclose(np.linalg.norm(tan[:, ui], axis=2), np.linalg.norm(local[:, v], axis=2), atol=1e-9)
    np.testing.assert_allclose(tan[:, ui, 2], local[:, v, 2], atol=1e-9)  # the n coordinate is shared


def test_maps_at_2048_give_back_every_vertex_sample(rig, tmp_path):
    """Bilinear lookups at the vertices' UVs return the vertex values in every space and in scalar
    maps, at every sample, to half-float rounding; plain rasterisation misses by several times more."""
    from dataclasses import replace

    from facepipe.pipeline.detail_layers import DetailLayer
    from facepipe.export.uv_raster import mesh_raster

    model = load_model(rig.models["wpsd"])
    mesh = model.mesh()
    replay_dir = rig.replays["wpsd"]
    head = np.load(replay_dir / "handles.npz")["head"]
    pick = [1, 5]  # two frames keep the test quick; the CLI path is exercised below at lower resolutions
    final, large, _, local = reference(model, replay_dir)
    v, uv, tile, ui = corner_uv_lookups(mesh)
    assert set(tile.tolist()) == {1001}
    frames = uv_tangent_frames(large, mesh.faces, mesh.face_uvs, mesh.uvs)
    want = {"local": local[:, v], "object": (final - large)[:, v],  # head space: no rotation below
            "tangent": np.einsum("tnji,tnj->tni", frames[:, ui], (final - large)[:, v]), "scalar": local[:, v, 2]}
    rasters = {"vertex": mesh_raster(mesh, 2048, 2048), "uv": mesh_raster(mesh, 2048, 2048, slots="uv")}
    for name, reference_values in want.items():
        space, mode = ("local", "scalar") if name == "scalar" else (name, "vector")
        layer = DetailLayer(model, space, mesh)
        raster = rasters[layer.slots]
        report = {}
        paths = maps.write_displacement_maps(raster, lambda s, e: layer(head[pick][s:e]), 2, tmp_path / name,
                                             mode=mode, attributes={"facepipe/space": space}, report=report)
        plain = replace(raster.tiles[1001], fit=None)
        for k, t in enumerate(pick):
            img, header, dtypes = read(paths[k][1001])
            assert img.shape == ((2048, 2048, 3) if mode == "vector" else (2048, 2048))
            assert header["compression"] == OpenEXR.ZIP_COMPRESSION
            assert set(dtypes.values()) == {np.dtype(np.float16)}
            err = relative_errors(sample(img, uv), reference_values[t])
            assert err.max() <= 1e-3, (name, t, err.max(axis=0))
            values = layer(head[[t]])[0]
            before = relative_errors(sample(plain(values if mode == "vector" else values[:, 2]), uv),
                                     reference_values[t])
            assert before.max() >= 3 * max(err.max(), 1e-3), (name, t, before.max(), err.max())
        # the export's own report: every sample, measured on the half floats written
        assert report["samples"] == len(raster.tiles[1001].lookup_slots) and report["frames"] == 2
        assert report["over_limit"] == 0 and report["relative"] <= 1e-3, report


def test_cli_maps_files_and_header(rig, tmp_path):
    dest = tmp_path / "exr"
    assert run("export", rig.replays["wpsd"], "--format", "exr", "-o", dest, "--resolution", "96x64", "--start", "0",
               "-q") == 0
    files = sorted(dest.glob("*.exr"))
    assert [f.name for f in files] == [f"frame_{i:04d}.exr" for i in range(0, 6)]
    for t, f in enumerate(files):
        img, header, dtypes = read(f)
        assert img.shape == (64, 96, 3) and set(dtypes.values()) == {np.dtype(np.float16)}
        assert header["facepipe/space"] == "local" and header["facepipe/frame"] == 10 + t
        assert header["facepipe/time"] == pytest.approx((10 + t) / 24.0)
        assert header["facepipe/units"] == "cm" and header["facepipe/channels"] == "R,G,B = t,b,n"
    assert run("export", rig.replays["wpsd"], "--format", "exr", "-o", tmp_path / "x", "--resolution", "8") == 2


def test_object_and_tangent_maps_against_the_replay(rig, tmp_path):
    model = load_model(rig.models["wpsd"])
    replay_dir = rig.replays["wpsd"]
    mesh = model.mesh()
    v, uv, _, uv_index = corner_uv_lookups(mesh)
    # object space: the replay's own final − large, in the take's space (head motion kept)
    pos = np.load(replay_dir / "positions.npy").astype(np.float64)
    large = np.load(replay_dir / "large_scale.npy").astype(np.float64)
    assert run("export", replay_dir, "--format", "exr", "--space", "object", "--float", "-o", tmp_path / "obj",
               "--resolution", "512", "-q") == 0
    for t in (0, 5):
        img, header, dtypes = read(tmp_path / "obj" / f"frame_{t + 1:04d}.exr")
        assert set(dtypes.values()) == {np.dtype(np.float32)} and header["facepipe/space"] == "object"
        want = (pos[t] - large[t])[v]
        # a still frame has no details: its floating-point residue is judged on the take's detail scale
        err = relative_errors(sample(img, uv), want, floor=1e-2 * np.abs(pos - large).max())
        assert err.max() <= 0.04 and np.percentile(err, 99) <= 0.02, err.max(axis=0)
    # tangent space: the same vectors (in head space) in UV-aligned frames of the large surface
    final_head, large_head, _, _ = reference(model, replay_dir)
    frames = uv_tangent_frames(large_head, mesh.faces, mesh.face_uvs, mesh.uvs)
    assert run("export", replay_dir, "--format", "exr", "--space", "tangent", "--float", "-o", tmp_path / "tan",
               "--resolution", "512", "-q") == 0
    for t in (0, 5):
        img, header, _ = read(tmp_path / "tan" / f"frame_{t + 1:04d}.exr")
        d = (final_head[t] - large_head[t])[v]
        want = np.einsum("nji,nj->ni", frames[t][uv_index], d)
        # a still frame has no details: its floating-point residue is judged on the take's detail scale
        err = relative_errors(sample(img, uv), want, floor=1e-2 * np.abs(pos - large).max())
        assert err.max() <= 0.04 and np.percentile(err, 99) <= 0.02, err.max(axis=0)
        # the n channel is the same in every tangent convention
        np.testing.assert_allclose(want[:, 2], np.einsum("nj,nj->n", frames[t][uv_index][:, :, 2], d))


def test_scalar_maps_are_the_normal_channel(rig, tmp_path):
    r = rig.replays["wpsd"]
    assert run("export", r, "--format", "exr", "--float", "--resolution", "128", "-o", tmp_path / "v", "-q") == 0
    assert run("export", r, "--format", "exr", "--float", "--scalar", "--resolution", "128", "-o", tmp_path / "s",
               "-q") == 0
    vec, _, _ = read(tmp_path / "v" / "frame_0003.exr")
    sca, header, dtypes = read(tmp_path / "s" / "frame_0003.exr")
    assert list(dtypes) == ["Y"] and header["facepipe/channels"] == "Y = n"
    assert np.array_equal(sca, vec[..., 2])
    assert run("export", r, "--format", "exr", "--scalar", "--space", "object", "-o", tmp_path / "x", "-q") == 2


def test_no_overwrite_resume_and_interruption(rig, tmp_path, monkeypatch):
    r = rig.replays["wpsd"]
    dest = tmp_path / "m"
    args = ("export", r, "--format", "exr", "--resolution", "64", "-o", dest, "-q")
    real = maps.write_exr

    def failing(path, image, **kw):
        if Path(path).name == "frame_0003.exr":
            raise KeyboardInterrupt("simulated")
        return real(path, image, **kw)

    monkeypatch.setattr(maps, "write_exr", failing)
    with pytest.raises(KeyboardInterrupt):
        from facepipe.export.dispatch import export_replay

        export_replay(r, "exr", dest, resolution=(64, 64))
    # frames are written on threads, a frame ahead: the one after the interrupted frame may be
    # complete too; every file there is a whole map, none is a leftover part
    written = sorted(p.name for p in dest.iterdir())
    assert written[:2] == ["frame_0001.exr", "frame_0002.exr"] and set(written) <= {
        "frame_0001.exr", "frame_0002.exr", "frame_0004.exr"}, written
    for name in written:
        assert read(dest / name)[0].shape[:2] == (64, 64)
    monkeypatch.setattr(maps, "write_exr", real)
    (dest / ".frame_0004.exr.abc123.part.exr").write_bytes(b"half a map")
    first = (dest / "frame_0001.exr").read_bytes()
    assert run(*args) == 2  # exists: refused
    assert run(*args, "--resume") == 0
    assert sorted(p.name for p in dest.iterdir()) == [f"frame_{i:04d}.exr" for i in range(1, 7)]
    assert (dest / "frame_0001.exr").read_bytes() == first
    assert run(*args, "--force") == 0
    assert run(*args, "--force", "--resume") == 2


def test_wrinkle_maps_blend_to_the_per_frame_maps(rig, tmp_path):
    r = rig.replays["psd"]
    model = load_model(rig.models["psd"])
    assert run("export", r, "--format", "wrinkle", "--resolution", "256", "-o", tmp_path / "w", "-q") == 0
    assert run("export", r, "--format", "exr", "--float", "--resolution", "256", "-o", tmp_path / "e", "-q") == 0
    manifest = json.loads((tmp_path / "w" / "wrinkle.json").read_text())
    assert manifest["formula"] == "map(frame) = C + sum_i coeff_i(frame) * M_i"
    assert manifest["gate"] == {"active": False}
    P = model.basis_features.shape[0]
    assert len(manifest["basis"]) == P and manifest["pixel_type"] == "float"
    const, _, dtypes = read(tmp_path / "w" / manifest["constant"]["1001"])
    assert set(dtypes.values()) == {np.dtype(np.float32)}
    basis = [read(tmp_path / "w" / b["maps"]["1001"])[0] for b in manifest["basis"]]
    with open(tmp_path / "w" / "coefficients.csv") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["frame", "time"] + [b["coefficient"] for b in manifest["basis"]]
    table = np.array(rows[1:], dtype=np.float64)
    np.testing.assert_array_equal(table[:, 0], np.arange(10, 16))
    # coefficients: strain features by hand, then Euclidean distances to the basis poses
    head = np.load(r / "handles.npz")["head"].astype(np.float64)
    e = model.edges
    f = (np.linalg.norm(head[:, e[:, 0]] - head[:, e[:, 1]], axis=2) - model.rest_lengths) / model.rest_lengths
    phi = np.linalg.norm(f[:, None, :] - model.basis_features[None].astype(np.float64), axis=2)
    np.testing.assert_allclose(table[:, 2:], phi, rtol=1e-6, atol=1e-9)
    for t in range(table.shape[0]):
        blended = maps.blend_wrinkle_maps(const, basis, table[t, 2:])
        frame, _, _ = read(tmp_path / "e" / f"frame_{t + 1:04d}.exr")
        # float32 rounding of the maps, summed over the blend's terms
        bound = 2 ** -22 * (np.abs(const) + sum(abs(c) * np.abs(m) for c, m in zip(table[t, 2:], basis))).max()
        np.testing.assert_allclose(blended, frame, rtol=0, atol=bound)
        assert np.abs(frame).max() == 0 or np.abs(blended - frame).max() <= 1e-4 * np.abs(frame).max() + bound
    # the set is written whole or resumed, never overwritten silently
    w = ("export", r, "--format", "wrinkle", "--resolution", "256", "-o", tmp_path / "w", "-q")
    before = {p.name: p.read_bytes() for p in (tmp_path / "w").iterdir()}
    assert run(*w) == 2
    (tmp_path / "w" / "coefficients.csv").unlink()
    assert run(*w, "--resume") == 0
    assert {p.name: p.read_bytes() for p in (tmp_path / "w").iterdir()} == before


def test_wrinkle_maps_of_a_gated_model_report_the_gate(rig, tmp_path, capsys):
    """The novelty gate scales details per vertex and frame: the set holds the ungated blend
    and wrinkle.json says how far that is from the model, as measured here independently."""
    r = rig.replays["psd_gated"]
    model = load_model(rig.models["psd_gated"])
    assert model.meta["novelty_tau"] > 0
    assert run("export", r, "--format", "wrinkle", "--resolution", "64", "-o", tmp_path / "w") == 0
    gate = json.loads((tmp_path / "w" / "wrinkle.json").read_text())["gate"]
    assert gate["active"] and not gate["included"]
    _, _, _, gated = reference(model, r)
    _, _, coeff = maps.read_coefficients(tmp_path / "w" / "coefficients.csv")
    ungated = model.rbf_const.astype(np.float64) + np.einsum("tp,vpc->tvc", coeff,
                                                             model.rbf_weights.astype(np.float64))
    dev = np.abs(gated - ungated).max(axis=(1, 2))
    np.testing.assert_allclose(gate["per_frame_max_abs"], dev, rtol=1e-6, atol=1e-9)
    assert gate["relative"] == pytest.approx(dev.max() / (gated.max() - gated.min()), rel=1e-6)
    said = "novelty gate is not in the blend" in capsys.readouterr().out
    assert said == (gate["relative"] >= 1e-3)


def test_wrinkle_maps_refuse_wpsd_and_none(rig, tmp_path, capsys):
    assert run("export", rig.replays["wpsd"], "--format", "wrinkle", "-o", tmp_path / "w") == 2
    err = capsys.readouterr().err
    assert "WPSD" in err and "per vertex" in err and "--format exr" in err
    assert not (tmp_path / "w").exists()
    model = load_model(rig.models["psd"])
    save_model(tmp_path / "none.npz", model.arrays, dict(model.meta, method="none"))
    assert run("export", rig.replays["psd"], "--format", "wrinkle", "-m", tmp_path / "none.npz",
               "-o", tmp_path / "n") == 2
    assert run("export", rig.replays["psd"], "--format", "exr", "-m", tmp_path / "none.npz",
               "-o", tmp_path / "n") == 2
    assert "no fine-scale details" in capsys.readouterr().err


def test_model_without_uvs_is_refused_with_exit_2(rig, tmp_path, capsys):
    model = load_model(rig.models["psd"])
    arrays = {k: v for k, v in model.arrays.items() if k not in ("uvs", "polygon_uvs")}
    save_model(tmp_path / "nouv.npz", arrays, model.meta)
    for fmt in ("exr", "wrinkle"):
        assert run("export", rig.replays["psd"], "--format", fmt, "-m", tmp_path / "nouv.npz",
                   "-o", tmp_path / fmt) == 2
        assert "no texture coordinates" in capsys.readouterr().err
    # geometry still exports without UVs
    assert run("export", rig.replays["psd"], "--format", "mdd", "-m", tmp_path / "nouv.npz",
               "-o", tmp_path / "a.mdd", "-q") == 0


def test_udim_layouts_name_the_tile(tmp_path):
    from facepipe.export.uv_raster import TiledRaster, uv_raster

    uv = np.array([[[0.1, 0.1], [0.9, 0.1], [0.5, 0.9]]])
    tiles = TiledRaster({1001: uv_raster(uv, np.array([[0, 1, 2]]), 3, 16, 16),
                         1002: uv_raster(uv, np.array([[2, 1, 0]]), 3, 16, 16)})
    paths = maps.write_displacement_maps(tiles, lambda s, e: np.ones((e - s, 3, 3)), 2, tmp_path, start=7)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame_0007.1001.exr", "frame_0007.1002.exr",
                                                         "frame_0008.1001.exr", "frame_0008.1002.exr"]
    assert paths[1][1002].name == "frame_0008.1002.exr"
    img, header, _ = read(paths[0][1002])
    assert header["facepipe/tile"] == 1002 and img.shape == (16, 16, 3)


def test_non_finite_displacement_names_the_frame(tmp_path):
    from facepipe.export.uv_raster import TiledRaster, uv_raster

    tiles = TiledRaster({1001: uv_raster(np.array([[[0.1, 0.1], [0.9, 0.1], [0.5, 0.9]]]),
                                         np.array([[0, 1, 2]]), 3, 8, 8)})

    def layer(s, e):
        d = np.zeros((e - s, 3, 3))
        if s <= 1 < e:
            d[1 - s, 2] = np.nan
        return d

    with pytest.raises(InputError, match="frame 2 .* first vertex 2"):
        maps.write_displacement_maps(tiles, layer, 3, tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["frame_0001.exr"]


def unresolvable_samples(uv, width, height):
    """Vertex samples (UVs within one tile) that no map of this size gives back for every choice of
    values: those in a cluster of overlapping bilinear footprints whose weights have a lower rank
    than the number of distinct sample positions (more UV corners than texels can tell apart)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    from facepipe.export.uv_raster import bilinear_footprint

    index, weight = bilinear_footprint(uv, width, height)
    n = len(uv)
    B = sp.csr_matrix((weight.ravel(), index.ravel(), np.arange(0, 4 * n + 1, 4)), shape=(n, width * height))
    B.sum_duplicates()
    B.eliminate_zeros()
    B = B[:, np.unique(B.indices)].tocsr()
    n_comp, texel_comp = connected_components((B.T @ B).tocsr(), directed=False)
    comp = texel_comp[B.indices[B.indptr[:-1]]]
    bad = np.zeros(n, dtype=bool)
    for c in np.flatnonzero(np.bincount(comp, minlength=n_comp) > 1):
        rows = np.flatnonzero(comp == c)
        block = B[rows][:, np.flatnonzero(texel_comp == c)].toarray()
        bad[rows] = np.linalg.matrix_rank(block) < len(np.unique(uv[rows], axis=0))
    return bad


@pytest.mark.ict
def test_ict_maps_give_back_every_vertex_sample_the_layout_resolves(tmp_path, ict_rig_fit):
    """The ICT kit at 2048² (two UDIM tiles), a fitted model replayed on two expressive frames: in
    every space and in scalar maps, every vertex sample (each UV corner of a seam vertex) is within
    2 % of the range, where plain rasterisation misses rim samples (triangles of a few texels) by
    more. The exception is what no map of this size can hold: clusters of UV corners closer than
    the texels can tell apart (the nostrils' insides), found from the layout alone; the export
    reports them."""
    kit = ict_or_skip()
    from facepipe.export.dispatch import export_replay
    from facepipe.io.model_file import model_from_fit
    from facepipe.pipeline.replay import replay
    from facepipe.export.uv_raster import mesh_raster

    rig, fit = ict_rig_fit
    model = model_from_fit(rig=rig, fit=fit)
    truth = np.load(kit / "train_truth.npz")
    # pursed lips and closed eyes (rims), and a frame whose details in the nostrils no map of this
    # size can hold in local frames
    pick = np.array([40, 104])
    head = truth["positions"][pick][:, model.handle_vertices].astype(np.float64)
    eye = np.broadcast_to(np.eye(3), (2, 3, 3))
    model.path = str(tmp_path / "model.npz")
    save_model(model.path, model.arrays, model.meta)
    r = tmp_path / "r"
    replay(load_model(model.path), head, eye, np.zeros((2, 3)), truth["frame"][pick], truth["time"][pick], r,
           save_large=True)
    model = load_model(model.path)
    mesh = model.mesh()
    v, uv, tile, ui = corner_uv_lookups(mesh)
    assert set(tile.tolist()) == {1001, 1002}
    unresolvable = np.zeros(len(v), dtype=bool)
    for k in (1001, 1002):
        unresolvable[tile == k] = unresolvable_samples(uv[tile == k], 2048, 2048)
    assert unresolvable.mean() < 0.05, unresolvable.sum()

    final, large, _, local = reference(model, r)  # head space = the replay's space (no head motion)
    frames = uv_tangent_frames(large, mesh.faces, mesh.face_uvs, mesh.uvs)
    want = {"object": (final - large)[:, v], "local": local[:, v], "scalar": local[:, v, 2],
            "tangent": np.einsum("tnji,tnj->tni", frames[:, ui], (final - large)[:, v])}

    def sample_back(folder, t):
        got = np.zeros(want[name].shape[1:])
        for k in (1001, 1002):
            img, _, _ = read(folder / f"frame_{t + 1:04d}.{k}.exr")
            got[tile == k] = sample(img, uv[tile == k])
        return got

    for name in want:
        space, mode = ("local", "scalar") if name == "scalar" else (name, "vector")
        info = export_replay(r, "exr", tmp_path / name, space=space, mode=mode)
        for t in range(2):
            err = relative_errors(sample_back(tmp_path / name, t), want[name][t]).reshape(len(v), -1).max(axis=1)
            assert err[~unresolvable].max() <= 0.02, (name, t, np.sort(err[~unresolvable])[-5:])
        # the export measures the same and says where it misses: only where the layout cannot resolve
        report = info["vertex_samples"]
        assert report["frames"] == 2 and report["samples"] >= len(np.unique(uv, axis=0))
        if report["over_limit"]:
            w = report["worst"]
            at = np.flatnonzero((tile == w["tile"]) & (np.abs(uv - w["uv"]).max(axis=1) < 1e-12))
            assert unresolvable[at].all() and any("vertex samples" in note for note in info["notes"])

    # the frames exercise the fit: plain rasterisation misses resolvable (rim) samples by more than 2 %
    plain = mesh_raster(mesh, 2048, 2048, fit=False).tiles
    for t in range(2):
        got = np.zeros((len(v), 3))
        for k in (1001, 1002):
            got[tile == k] = sample(plain[k](local[t]), uv[tile == k])
        err = relative_errors(got, want["local"][t]).max(axis=1)
        assert (err[~unresolvable] > 0.02).sum() >= 1, np.sort(err[~unresolvable])[-5:]
