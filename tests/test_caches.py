"""Point caches read back by independent readers: pxr for USD, spec-level struct readers for MDD/PC2."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from facepipe.errors import InputError
from facepipe.io.model_file import load_model
from facepipe.io.point_caches import write_mdd, write_pc2
from facepipe.io.replay_folder import frame_rate, is_uniform, time_codes
from facepipe.io.usd_file import write_usd
from tests.test_export import rig_mesh, sequence
from tests.conftest import run_cli as run


def read_mdd(path):
    """MDD by the spec: big-endian int32 frames, int32 points, float32 times, float32 xyz per frame."""
    data = Path(path).read_bytes()
    T, V = struct.unpack_from(">ii", data, 0)
    times = struct.unpack_from(f">{T}f", data, 8)
    off = 8 + 4 * T
    assert len(data) == off + 12 * T * V, "file size"
    xyz = struct.unpack_from(f">{3 * T * V}f", data, off)
    return np.array(times), np.array(xyz, dtype=np.float32).reshape(T, V, 3)


def read_pc2(path):
    """PC2 by the spec: 'POINTCACHE2\\0', int32 version, int32 points, float32 start, float32 rate,
    int32 samples, then little-endian float32 xyz per sample."""
    data = Path(path).read_bytes()
    magic, version, V, start, rate, T = struct.unpack_from("<12siiffi", data, 0)
    assert struct.calcsize("<12siiffi") == 32
    assert len(data) == 32 + 12 * T * V, "file size"
    xyz = struct.unpack_from(f"<{3 * T * V}f", data, 32)
    return magic, version, start, rate, np.array(xyz, dtype=np.float32).reshape(T, V, 3)


def test_mdd_round_trip_byte_exact(tmp_path):
    mesh = rig_mesh()
    pos = sequence(mesh, 5)
    times = np.arange(5) / 30.0
    write_mdd(tmp_path / "a.mdd", pos, times)
    back_times, back = read_mdd(tmp_path / "a.mdd")
    assert np.array_equal(back, pos)
    assert np.array_equal(back_times.astype(np.float32), times.astype(np.float32))
    raw = (tmp_path / "a.mdd").read_bytes()
    assert raw[:8] == bytes([0, 0, 0, 5, 0, 0, 0, 20])  # big-endian frame and point counts


def test_pc2_round_trip_byte_exact(tmp_path):
    mesh = rig_mesh()
    pos = sequence(mesh, 4)
    times = (np.arange(4) + 12) / 25.0
    write_pc2(tmp_path / "a.pc2", pos, times, fps=25.0)
    magic, version, start, rate, back = read_pc2(tmp_path / "a.pc2")
    assert magic == b"POINTCACHE2\0" and version == 1 and rate == 1.0 and start == 12.0
    assert np.array_equal(back, pos)
    raw = (tmp_path / "a.pc2").read_bytes()
    assert raw[12:20] == bytes([1, 0, 0, 0, 20, 0, 0, 0])  # little-endian version and point count


def test_pc2_refuses_dropped_frames(tmp_path):
    mesh = rig_mesh()
    times = np.array([0, 1, 2, 4]) / 30.0
    with pytest.raises(InputError, match="not uniform"):
        write_pc2(tmp_path / "a.pc2", sequence(mesh, 4), times, fps=30.0)
    assert not (tmp_path / "a.pc2").exists()
    write_mdd(tmp_path / "a.mdd", sequence(mesh, 4), times)  # MDD keeps per-frame times
    assert np.allclose(read_mdd(tmp_path / "a.mdd")[0], times)


def test_usd_round_trip_with_pxr(tmp_path):
    from pxr import Usd, UsdGeom

    mesh = rig_mesh()
    pos = sequence(mesh, 3)
    times = np.array([10, 11, 12]) / 24.0
    write_usd(tmp_path / "a.usdc", mesh, pos, times, fps=24.0, units="cm", frame_numbers=np.array([10, 11, 12]))
    stage = Usd.Stage.Open(str(tmp_path / "a.usdc"))
    assert stage.GetRootLayer().GetFileFormat().formatId == "usdc"
    assert stage.GetTimeCodesPerSecond() == 24.0 and stage.GetFramesPerSecond() == 24.0
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (10.0, 12.0)
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert stage.GetDefaultPrim().GetPath() == "/Face"
    geom = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/skin"))
    assert np.array_equal(np.asarray(geom.GetFaceVertexCountsAttr().Get()), mesh.polygon_sizes)
    assert np.array_equal(np.asarray(geom.GetFaceVertexIndicesAttr().Get()), mesh.polygon_vertices)
    assert geom.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
    st = UsdGeom.PrimvarsAPI(geom.GetPrim()).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.faceVarying and st.IsIndexed()
    assert st.GetTypeName() == "texCoord2f[]"
    assert np.array_equal(np.asarray(st.GetIndices()), mesh.polygon_uvs)
    assert np.array_equal(np.asarray(st.Get()), mesh.uvs.astype(np.float32))
    # the face-varying UVs resolve to the same per-corner UVs as the OBJ
    assert np.array_equal(np.asarray(st.ComputeFlattened()), mesh.uvs[mesh.polygon_uvs].astype(np.float32))
    points = geom.GetPointsAttr()
    assert points.GetTimeSamples() == [10.0, 11.0, 12.0]
    for t, tc in enumerate((10.0, 11.0, 12.0)):
        assert np.array_equal(np.asarray(points.Get(tc)), pos[t])
        ext = np.asarray(geom.GetExtentAttr().Get(tc))
        assert np.array_equal(ext, np.stack([pos[t].min(0), pos[t].max(0)]))
    assert list(stage.GetRootLayer().customLayerData["frame_numbers"]) == [10, 11, 12]
    # USD's own validators (schema types, stage metadata, composition) find nothing to report
    from pxr import UsdValidation

    registry = UsdValidation.ValidationRegistry()
    assert UsdValidation.ValidationContext(registry.GetOrLoadAllValidators()).Validate(stage) == []
    # between samples USD interpolates linearly: half way between frames 10 and 11
    np.testing.assert_allclose(np.asarray(points.Get(10.5)), 0.5 * (pos[0] + pos[1]), rtol=1e-6, atol=1e-6)


def test_usda_text_layer(tmp_path):
    from pxr import Usd, UsdGeom

    mesh = rig_mesh()
    pos = sequence(mesh, 2)
    write_usd(tmp_path / "a.usda", mesh, pos, np.array([0.0, 0.04]), fps=25.0, up_axis="Z")
    assert (tmp_path / "a.usda").read_text().startswith("#usda 1.0")
    stage = Usd.Stage.Open(str(tmp_path / "a.usda"))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert np.array_equal(np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath("/Face/skin")).GetPointsAttr().Get(1.0)), pos[1])


def test_cli_caches_of_a_replay(rig, tmp_path):
    from pxr import Usd, UsdGeom

    r = rig.replays["wpsd"]
    pos = np.load(r / "positions.npy")
    large = np.load(r / "large_scale.npy")
    assert run("export", r, "--format", "usd", "-o", tmp_path / "take.usdc", "-q") == 0
    assert run("export", r, "--format", "mdd", "-o", tmp_path / "take.mdd", "-q") == 0
    assert run("export", r, "--format", "pc2", "-o", tmp_path / "take.pc2", "-q") == 0
    assert run("export", r, "--format", "mdd", "--layer", "large", "-o", tmp_path / "large.mdd", "-q") == 0
    stage = Usd.Stage.Open(str(tmp_path / "take.usdc"))
    # the fixture's take: frames 10..15 at 24 fps
    assert stage.GetTimeCodesPerSecond() == 24.0 and stage.GetStartTimeCode() == 10.0
    pts = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/skin")).GetPointsAttr()
    assert np.array_equal(np.asarray(pts.Get(15.0)), pos[5])
    times, mdd = read_mdd(tmp_path / "take.mdd")
    assert np.array_equal(mdd, pos) and np.allclose(times, np.arange(10, 16) / 24.0)
    _, _, start, _, pc2 = read_pc2(tmp_path / "take.pc2")
    assert start == 10.0 and np.array_equal(pc2, pos)
    assert np.array_equal(read_mdd(tmp_path / "large.mdd")[1], large)
    # an existing folder gets a file named after the replay folder
    (tmp_path / "d").mkdir()
    assert run("export", r, "--format", "pc2", "-o", tmp_path / "d", "-q") == 0
    assert (tmp_path / "d" / f"{r.name}.pc2").is_file()


def test_cli_cache_safety(rig, tmp_path, capsys):
    r = rig.replays["psd"]
    dest = tmp_path / "take.mdd"
    assert run("export", r, "--format", "mdd", "-o", dest, "-q") == 0
    before = dest.read_bytes()
    assert run("export", r, "--format", "mdd", "-o", dest, "-q") == 2
    assert "--force" in capsys.readouterr().err
    (tmp_path / ".take.mdd.xyz123.part.mdd").write_bytes(b"left by a killed run")
    assert run("export", r, "--format", "mdd", "-o", dest, "--resume", "-q") == 0
    assert dest.read_bytes() == before and not (tmp_path / ".take.mdd.xyz123.part.mdd").exists()
    assert run("export", r, "--format", "mdd", "-o", dest, "--force", "-q") == 0
    assert run("export", r, "--format", "mdd", "-o", tmp_path / "take.pc2") == 2
    assert "must be named *.mdd" in capsys.readouterr().err
    assert run("export", r, "--format", "usd", "-o", tmp_path / "take.abc") == 2
    # --layer large needs the replay's large_scale.npy
    import shutil

    bare = tmp_path / "bare"
    shutil.copytree(r, bare)
    (bare / "large_scale.npy").unlink()
    assert run("export", bare, "--format", "pc2", "--layer", "large", "-o", tmp_path / "l.pc2") == 2
    assert "--save-large-scale" in capsys.readouterr().err


def test_interrupted_cache_leaves_no_file(tmp_path):
    mesh = rig_mesh()
    pos = sequence(mesh, 4)

    def boom(n):
        raise KeyboardInterrupt("simulated")

    for writer, name in ((write_mdd, "a.mdd"), (write_pc2, "a.pc2")):
        args = (tmp_path / name, pos, np.arange(4) / 30.0) + ((30.0,) if writer is write_pc2 else ())
        with pytest.raises(KeyboardInterrupt):
            writer(*args, progress=boom)
    with pytest.raises(KeyboardInterrupt):
        write_usd(tmp_path / "a.usdc", mesh, pos, np.arange(4) / 30.0, 30.0, progress=boom)
    assert list(tmp_path.iterdir()) == []


def test_frame_rate_and_time_codes():
    assert frame_rate(np.round(np.arange(10) / 30.0, 6)) == 30.0
    assert frame_rate(np.arange(10) / (30000 / 1001)) == pytest.approx(30000 / 1001)
    assert frame_rate(np.array([0.5])) == 30.0
    assert frame_rate(np.arange(5) * 0.0123) == pytest.approx(1 / 0.0123)
    with pytest.raises(InputError, match="do not increase"):
        frame_rate(np.array([0.0, 0.1, 0.1]))
    assert np.array_equal(time_codes(np.round(np.arange(4) / 30.0, 6), 30.0), [0, 1, 2, 3])
    assert is_uniform(np.arange(5) / 30.0) and not is_uniform(np.array([0, 1, 2, 4]) / 30.0)


def test_model_mesh_matches_usd_topology(rig, tmp_path):
    from pxr import Usd, UsdGeom

    model = load_model(rig.models["psd"])
    assert run("export", rig.replays["psd"], "--format", "usd", "-o", tmp_path / "a.usd", "-q") == 0
    stage = Usd.Stage.Open(str(tmp_path / "a.usd"))
    geom = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/skin"))
    assert np.array_equal(np.asarray(geom.GetFaceVertexIndicesAttr().Get()), model.polygon_vertices)
