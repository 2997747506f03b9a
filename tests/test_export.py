"""OBJ sequence export: round trip, no silent overwrite, resume, atomic frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import facepipe.export.common as export
from facepipe.errors import InputError
from facepipe.export.common import frame_paths, write_obj_sequence
from facepipe.core.mesh import Mesh
from facepipe.io.mesh_read import load_mesh

SHARED = Path(__file__).parents[1] / ".." / "shared"
ICT = SHARED / "data" / "ict"


def rig_mesh() -> Mesh:
    """A 5 x 4 grid of quads and two triangles, with seams in the UVs and two named groups."""
    nx, ny = 5, 4
    u, v = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float), indexing="ij")
    V = np.c_[u.ravel(), v.ravel(), np.sin(u.ravel())]
    idx = np.arange(nx * ny).reshape(nx, ny)
    quads = np.c_[idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()]
    polys = [list(q) for q in quads[:-1]]
    a, b, c, d = quads[-1]
    polys += [[a, b, c], [a, c, d]]
    sizes = [len(p) for p in polys]
    offsets = np.r_[0, np.cumsum(sizes)]
    pv = np.concatenate(polys)
    # per-corner UVs: every corner its own UV (a seam everywhere), values with many digits
    rng = np.random.default_rng(0)
    uvs = rng.random((len(pv), 2))
    groups = np.repeat([1, 2], [6, len(polys) - 6]).astype(np.int32)
    return Mesh(V, offsets, pv, uvs, np.arange(len(pv)), groups, ["default", "brow", "mouth"], path="rig.obj")


def sequence(mesh: Mesh, n_frames: int = 4) -> np.ndarray:
    rng = np.random.default_rng(1)
    t = np.arange(n_frames)[:, None, None]
    return (mesh.vertices[None] * (1 + 0.1 * t) + rng.normal(scale=0.3, size=(n_frames, mesh.n_vertices, 3))
            ).astype(np.float32)


def test_sequence_round_trip(tmp_path):
    mesh = rig_mesh()
    positions = sequence(mesh)
    paths = write_obj_sequence(mesh, positions, tmp_path / "obj")
    assert [p.name for p in paths] == [f"frame_000{i}.obj" for i in range(1, 5)]
    for t, p in enumerate(paths):
        back = load_mesh(p)
        np.testing.assert_allclose(back.vertices, positions[t], rtol=1e-6, atol=1e-6 * np.abs(positions[t]).max())
        # 9 significant digits give float32 back bit for bit
        assert np.array_equal(back.vertices.astype(np.float32), positions[t])
        assert np.array_equal(back.polygon_offsets, mesh.polygon_offsets)
        assert np.array_equal(back.polygon_vertices, mesh.polygon_vertices)
        assert np.array_equal(back.polygon_uvs, mesh.polygon_uvs)
        np.testing.assert_allclose(back.uvs, mesh.uvs, rtol=1e-8, atol=1e-12)
        assert [back.group_names[g] for g in back.polygon_groups] == \
            [mesh.group_names[g] for g in mesh.polygon_groups]


def test_memmap_positions_and_start_number(tmp_path):
    mesh = rig_mesh()
    np.save(tmp_path / "positions.npy", sequence(mesh, 3))
    positions = np.load(tmp_path / "positions.npy", mmap_mode="r")
    paths = write_obj_sequence(mesh, positions, tmp_path / "obj", start=9)
    assert [p.name for p in paths] == ["frame_0009.obj", "frame_0010.obj", "frame_0011.obj"]
    assert np.array_equal(load_mesh(paths[2]).vertices.astype(np.float32), positions[2])


def test_frame_names_widen_past_9999():
    assert frame_paths("d", 2, start=9999)[-1].name == "frame_10000.obj"
    assert frame_paths("d", 2, start=9999)[0].name == "frame_09999.obj"


def test_existing_files_are_not_overwritten_without_force(tmp_path):
    mesh = rig_mesh()
    positions = sequence(mesh, 3)
    dest = tmp_path / "obj"
    dest.mkdir()
    (dest / "frame_0002.obj").write_text("keep me")
    with pytest.raises(InputError) as e:
        write_obj_sequence(mesh, positions, dest)
    assert "frame_0002.obj" in str(e.value) and "--force" in str(e.value)
    # refused before writing anything
    assert sorted(p.name for p in dest.iterdir()) == ["frame_0002.obj"]
    assert (dest / "frame_0002.obj").read_text() == "keep me"
    write_obj_sequence(mesh, positions, dest, force=True)
    assert np.array_equal(load_mesh(dest / "frame_0002.obj").vertices.astype(np.float32), positions[1])


def test_resume_writes_only_missing_frames(tmp_path):
    mesh = rig_mesh()
    positions = sequence(mesh, 4)
    dest = tmp_path / "obj"
    paths = write_obj_sequence(mesh, positions, dest)
    paths[0].write_text("# already done\n")  # marks a frame that resume must leave alone
    paths[2].unlink()
    (dest / ".frame_0004.obj.abc123.part.obj").write_text("half a frame from a killed run")
    done = []
    again = write_obj_sequence(mesh, positions, dest, resume=True, progress=done.append)
    assert again == paths and sum(done) == 4
    assert paths[0].read_text() == "# already done\n"
    assert np.array_equal(load_mesh(paths[2]).vertices.astype(np.float32), positions[2])
    assert sorted(p.name for p in dest.iterdir()) == [p.name for p in paths]  # leftovers removed


def test_interrupted_export_leaves_only_complete_files(tmp_path, monkeypatch):
    mesh = rig_mesh()
    positions = sequence(mesh, 4)
    dest = tmp_path / "obj"
    real = export._format_rows

    def failing(tag, values):
        # the third frame's vertex block fails after its file was opened
        if np.array_equal(values, positions[2]):
            raise KeyboardInterrupt("simulated interruption")
        return real(tag, values)

    monkeypatch.setattr(export, "_format_rows", failing)
    with pytest.raises(KeyboardInterrupt):
        write_obj_sequence(mesh, positions, dest)
    # the frames before it are written, the one interrupted is not there at all (no partial file, no
    # temporary); the frame after it may have been written beside it (frames are written on threads)
    names = sorted(p.name for p in dest.iterdir())
    assert names[:2] == ["frame_0001.obj", "frame_0002.obj"] and set(names) <= {"frame_0001.obj", "frame_0002.obj",
                                                                                  "frame_0004.obj"}
    for name in names:
        t = int(name[6:10]) - 1
        assert np.array_equal(load_mesh(dest / name).vertices.astype(np.float32), positions[t])
    monkeypatch.setattr(export, "_format_rows", real)
    paths = write_obj_sequence(mesh, positions, dest, resume=True)
    for t, p in enumerate(paths):
        assert np.array_equal(load_mesh(p).vertices.astype(np.float32), positions[t])


def test_failure_while_writing_the_file_leaves_no_partial_file(tmp_path, monkeypatch):
    import facepipe.io.atomic as atomic

    mesh = rig_mesh()
    dest = tmp_path / "obj"
    real_open = open

    class Exploding:
        def __init__(self, fh):
            self.fh = fh
            self.n = 0

        def write(self, data):
            self.n += 1
            if self.n == 2:  # header written, vertex block half way: the disk "fills up"
                self.fh.write(data[: len(data) // 2])
                raise OSError(28, "No space left on device")
            return self.fh.write(data)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return self.fh.__exit__(*exc)

    monkeypatch.setattr(atomic, "open", lambda *a, **k: Exploding(real_open(*a, **k)), raising=False)
    with pytest.raises(OSError):
        write_obj_sequence(mesh, sequence(mesh, 2), dest)
    assert list(dest.iterdir()) == []


def test_bad_inputs(tmp_path):
    mesh = rig_mesh()
    positions = sequence(mesh, 2)
    with pytest.raises(InputError, match=r"expected \(frames, 20, 3\)"):
        write_obj_sequence(mesh, positions[:, :-1], tmp_path / "a")
    with pytest.raises(InputError, match="contradict"):
        write_obj_sequence(mesh, positions, tmp_path / "b", force=True, resume=True)
    positions[1, 7, 2] = np.nan
    with pytest.raises(InputError) as e:
        write_obj_sequence(mesh, positions, tmp_path / "c")
    assert "frame 2" in str(e.value) and "vertex 7" in str(e.value)
    assert [p.name for p in (tmp_path / "c").iterdir()] == ["frame_0001.obj"]


@pytest.mark.ict
def test_ict_frames_round_trip(tmp_path):
    if not (ICT / "neutral.obj").is_file():
        pytest.skip(f"the ICT kit is not there ({ICT}): /work/shared is absent in this checkout")
    mesh = load_mesh(ICT / "neutral.obj")
    rng = np.random.default_rng(0)
    positions = (mesh.vertices[None] + rng.normal(scale=0.05, size=(2, mesh.n_vertices, 3))).astype(np.float32)
    paths = write_obj_sequence(mesh, positions, tmp_path)
    back = load_mesh(paths[1])
    assert np.array_equal(back.vertices.astype(np.float32), positions[1])
    assert np.array_equal(back.polygon_vertices, mesh.polygon_vertices)
    assert np.array_equal(back.polygon_uvs, mesh.polygon_uvs)
    np.testing.assert_allclose(back.uvs, mesh.uvs, rtol=1e-8)
