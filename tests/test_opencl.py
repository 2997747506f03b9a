"""The OpenCL replay engine against the NumPy reference, on PoCL's CPU device (or any device).

Tolerance: 1e-4 × the mesh's bounding-box diagonal (float32 kernels, float64 reference).
Tests skip cleanly when no OpenCL device exists; the 'no platform' paths are simulated.
"""

import json

import numpy as np
import pytest

from facepipe import opencl
from facepipe.errors import InputError
from facepipe.pipeline.fit import fit_rig
from facepipe.core.tangent_frames import vertex_normals
from facepipe.io.model_file import model_from_fit
from facepipe.pipeline.replay import NumpyEvaluator, NpyWriter, stream_chunks
from facepipe.pipeline.rig import load_rig
from facepipe.sample_rig import write_sample_rig
from tests.conftest import ict_or_skip
from tests.conftest import run_cli as run

TOL = 1e-4


def _device_or_skip():
    if not opencl.opencl_available():
        pytest.skip("no OpenCL device that compiles kernels (pip install pocl-binary-distribution gives a CPU one; "
                    "where its LLVM does not know the CPU, a distribution's PoCL: apt install pocl-opencl-icd)")


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    d = tmp_path_factory.mktemp("ocl")
    write_sample_rig(d / "rig", n_vertices=3000, n_examples=6, n_frames=40)
    rig = load_rig(d / "rig" / "sample.toml")
    fit = fit_rig(rig)
    truth = np.load(d / "rig" / "take_truth.npz")["positions"]
    head = truth[:, rig.handles].astype(np.float64)
    diag = float(np.linalg.norm(np.ptp(rig.mesh.vertices, axis=0)))
    return d, rig, fit, head, diag


def _motion(T, seed=3):
    """Arbitrary rotations and translations: exercises the device-side head motion."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(T, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                  2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                  2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1).reshape(T, 3, 3)
    return R, rng.normal(scale=5.0, size=(T, 3))


# ----------------------------------------------------------------------------- host tables


def test_vertex_face_ring_gives_each_face_in_its_winding():
    faces = np.array([[0, 1, 2], [0, 2, 3], [3, 2, 4]])
    ptr, ring = opencl.vertex_face_ring(faces, 6)
    assert ptr.tolist() == [0, 2, 3, 6, 8, 9, 9]  # vertex 5 has no face
    for v in range(5):
        for a, b in ring[ptr[v]:ptr[v + 1]]:
            rotations = {(v, a, b), (a, b, v), (b, v, a)}
            assert any(tuple(f) in rotations for f in faces.tolist())


def _fan_faces(ptr, fan):
    """The (v, a, b) faces a fan table lists, and each vertex's fan count."""
    faces, fans = [], []
    for v in range(len(ptr) - 1):
        prev, count = None, 0
        for j in fan[ptr[v]:ptr[v + 1]].tolist():
            if j < 0:
                prev, count = ~j, count + 1
            else:
                faces.append((v, prev, j))
                prev = j
        fans.append(count)
    return faces, fans


def _ring_faces(ptr, ring):
    return [(v, int(a), int(b)) for v in range(len(ptr) - 1) for a, b in ring[ptr[v]:ptr[v + 1]]]


def test_vertex_fans_list_every_face_once_chained_around_its_vertex():
    # a hexagon around 0 (closed fan), its rim vertices (open fans), an isolated vertex 7
    hexagon = [[0, i, i % 6 + 1] for i in range(1, 7)]
    ptr, fan = opencl.vertex_fans(np.array(hexagon), 8)
    assert fan[ptr[0]:ptr[1]].tolist() == [~1, 2, 3, 4, 5, 6, 1]  # closed: the first neighbour again
    assert fan[ptr[1]:ptr[2]].tolist() == [~2, 0, 6]  # faces (1, 2, 0) then (1, 0, 6)
    assert ptr[7] == ptr[8]
    # non-manifold: two fans meeting at vertex 0 only (a bow tie), a flipped face, a degenerate one
    odd = np.array(hexagon + [[0, 7, 8], [0, 8, 9], [0, 10, 9], [0, 11, 11]])
    ptr, fan = opencl.vertex_fans(odd, 12)
    faces, fans = _fan_faces(ptr, fan)
    ring_ptr, ring = opencl.vertex_face_ring(odd, 12)
    assert sorted(faces) == sorted(_ring_faces(ring_ptr, ring))
    assert fans[0] == 4  # the hexagon, 7-8-9, the flipped (10, 9), the degenerate (11, 11)


def test_vertex_fans_normals_match_the_face_sum(sheet):
    """On a mesh with borders and shuffled faces: the fans' Σ cross(d_prev, d_j) is the sum of
    the incident faces' area-weighted normals; every vertex of the sheet's interior has one fan."""
    V, F = sheet
    rng = np.random.default_rng(3)
    F = F[rng.permutation(len(F))]
    pos = V + rng.normal(scale=0.1, size=V.shape)
    ptr, fan = opencl.vertex_fans(F, len(V))
    faces, fans = _fan_faces(ptr, fan)
    assert len(faces) == 3 * len(F) and max(fans) == 1  # each face once at each corner
    n_fan = np.zeros_like(pos)
    v, a, b = np.array(faces).T
    np.add.at(n_fan, v, np.cross(pos[a] - pos[v], pos[b] - pos[v]))
    face_n = np.cross(pos[F[:, 1]] - pos[F[:, 0]], pos[F[:, 2]] - pos[F[:, 0]])
    n_face = np.zeros_like(pos)
    for k in range(3):
        np.add.at(n_face, F[:, k], face_n)
    assert np.allclose(n_fan, n_face, rtol=1e-12, atol=1e-12)


def test_locality_order_only_reorders_scattered_meshes(sheet):
    V, F = sheet
    assert opencl.locality_order(F, len(V), "auto") is None  # scan-ordered grid: already local
    shuffle = np.random.default_rng(0).permutation(len(V))
    inv = np.argsort(shuffle)
    perm = opencl.locality_order(inv[F], len(V), "auto")
    assert perm is not None and sorted(perm.tolist()) == list(range(len(V)))
    with pytest.raises(ValueError):
        opencl.locality_order(F, len(V), np.zeros(len(V), dtype=int))


def test_compact_edges_moves_dropped_edges_last():
    index = np.array([[3, 1, 2], [0, 4, 5]])
    weight = np.array([[0.0, 0.6, 0.4], [0.5, 0.0, 0.5]], dtype=np.float32)
    i, w, n = opencl.compact_edges(index, weight)
    assert n.tolist() == [2, 2] and i.tolist() == [[1, 2, 3], [0, 5, 4]] and w[:, 2].tolist() == [0, 0]


# ----------------------------------------------------------------------------- against the reference


@pytest.mark.parametrize("method", ["wpsd", "psd", "none"])
@pytest.mark.parametrize("options", [{}, {"vector_width": 1, "chunk": 16}, {"vector_width": 4, "chunk": 12},
                                     {"vector_width": 16, "chunk": 32}, {"reorder": "rcm", "chunk": 8}])
def test_matches_numpy_reference(sample, method, options):
    _device_or_skip()
    _, rig, fit, head, diag = sample
    model = model_from_fit(fit, rig, method)
    ref_final, ref_large = NumpyEvaluator(model).evaluate(head, with_large=True)
    ev = opencl.OpenCLEvaluator(model, **options)
    final, large = ev.evaluate(head, with_large=True)
    assert final.shape == ref_final.shape and final.dtype == np.float32
    assert np.abs(final - ref_final).max() <= TOL * diag
    assert np.abs(large - ref_large).max() <= TOL * diag
    assert ev.backend == "opencl" and "compute units" in ev.device
    assert ev.stage_seconds["large_scale"] > 0 and ev.stage_seconds["frames_fine_scale"] > 0


def test_wpsd_details_keep_float_accuracy_at_the_example_poses(sample):
    """At and near a basis pose the kernel's expanded distance Σα f² − 2Σα b f + Σα b² cancels;
    the kernel sums those distances term by term there. The details (final − large scale) at the
    examples themselves and at small steps from them match the reference to the accuracy of
    float32 positions (a few ulps of the largest coordinate), where the expansion alone is ten
    times further off (measured on this rig: 1.9e-6 against 6.0e-5 cm; an ulp at 11 cm is 9.5e-7)."""
    _device_or_skip()
    _, rig, fit, _, _ = sample
    model = model_from_fit(fit, rig, "wpsd")
    poses = rig.example_positions[:, rig.handles].astype(np.float64)
    step = 1e-4 * float(np.median(model.rest_lengths))
    head = np.concatenate([poses, poses + np.random.default_rng(2).normal(scale=step, size=poses.shape)])
    ref_final, ref_large = NumpyEvaluator(model).evaluate(head, with_large=True)
    final, large = opencl.OpenCLEvaluator(model).evaluate(head, with_large=True)
    ref_detail = ref_final - ref_large
    error = np.abs((final - large) - ref_detail).max()
    assert error <= 4 * np.finfo(np.float32).eps * np.abs(ref_final).max()


def test_tangent_fallback_where_the_frame_edge_lies_along_the_normal(sample):
    """A vertex whose frame neighbour sits straight along its normal has no tangent from that edge:
    kernel and reference both take n × x̂ (the kernel tests the lengths squared). Made by moving
    a far vertex (the frame neighbour) onto the normal; details there are a constant in the frame,
    so a wrong tangent shows in the positions."""
    import dataclasses

    _device_or_skip()
    _, rig, fit, _, diag = sample
    model = model_from_fit(fit, rig, "psd")
    rest = model.rest.astype(np.float64).copy()
    normals = vertex_normals(rest, model.triangles.astype(np.int64))
    handles = set(model.handle_vertices.tolist())
    faces = model.triangles.astype(np.int64)
    v = next(i for i in range(0, len(rest), 7) if i not in handles)
    near = set(faces[(faces == v).any(axis=1)].ravel().tolist())
    far = np.argsort(-np.linalg.norm(rest - rest[v], axis=1))
    w = int(next(i for i in far if i not in handles and i not in near))
    rest[w] = rest[v] + 0.5 * normals[v]
    neighbors = model.frame_neighbors.copy()
    neighbors[v] = w
    const = np.asarray(model.rbf_const).copy()
    const[v] = [0.3, -0.2, 0.1]
    model = dataclasses.replace(model, rest=rest.astype(model.rest.dtype), frame_neighbors=neighbors,
                                rbf_const=const.astype(np.asarray(model.rbf_const).dtype))
    head = np.repeat(rest[model.handle_vertices][None], 2, axis=0)  # the rest pose: large = rest
    ref_final, ref_large = NumpyEvaluator(model).evaluate(head, with_large=True)
    final, large = opencl.OpenCLEvaluator(model).evaluate(head, with_large=True)
    n = normals[v] / np.linalg.norm(normals[v])
    t = np.cross(n, [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t)
    expected = np.column_stack([t, np.cross(n, t), n]) @ const[v]
    assert np.abs((ref_final - ref_large)[:, v] - expected).max() < 1e-6  # the reference took the fallback
    assert np.abs(final - ref_final).max() <= TOL * diag


def test_head_motion_normals_and_permuted_order(sample):
    _device_or_skip()
    _, rig, fit, head, diag = sample
    model = model_from_fit(fit, rig, "wpsd")
    R, t = _motion(len(head))
    ref_final, ref_large = NumpyEvaluator(model).evaluate(head, with_large=True)
    ref_world = np.einsum("cij,cvj->cvi", R, ref_final) + t[:, None]
    ref_large_world = np.einsum("cij,cvj->cvi", R, ref_large) + t[:, None]
    perm = np.random.default_rng(1).permutation(model.n_vertices)  # worst case for locality
    ev = opencl.OpenCLEvaluator(model, reorder=perm, chunk=16)
    final, large, normals = ev.evaluate(head, with_large=True, rigid=(R, t), with_normals=True)
    scale = diag + np.abs(t).max()
    assert np.abs(final - ref_world).max() <= TOL * scale
    assert np.abs(large - ref_large_world).max() <= TOL * scale
    ref_normals = np.einsum("cij,cvj->cvi", R, vertex_normals(ref_final, model.triangles.astype(np.int64)))
    assert np.abs(normals - ref_normals).max() <= 1e-3
    assert np.allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-5)


def test_stream_delivers_chunks_in_order_and_propagates_sink_errors(sample):
    _device_or_skip()
    _, rig, fit, head, _ = sample
    ev = opencl.OpenCLEvaluator(model_from_fit(fit, rig, "psd"), chunk=8, slots=3)
    starts = []
    ev.stream(head[:27], lambda s, f, l, n: starts.append((s, f.shape[0], l, n)))
    assert [(s, n) for s, n, _, _ in starts] == [(0, 8), (8, 8), (16, 8), (24, 3)]
    assert all(l is None and n is None for _, _, l, n in starts)

    def broken(start, *_):
        if start == 8:
            raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        ev.stream(head, broken)
    ev.stream(head[:4], lambda *a: None)  # still usable afterwards


def test_kernels_write_a_callers_array_in_place(sample):
    """``evaluate(out=)`` / ``stream(destination=)``: the same positions as without; on a CPU device
    the chunks handed to the sink are the destination's own memory (no copy out of the device)."""
    _device_or_skip()
    _, rig, fit, head, _ = sample
    model = model_from_fit(fit, rig, "wpsd")
    R, t = _motion(len(head), seed=7)
    ev = opencl.OpenCLEvaluator(model, chunk=16)
    expected = ev.evaluate(head, rigid=(R, t))
    dest = np.full((len(head), model.n_vertices, 3), np.nan, dtype=np.float32)
    seen = []
    ev.stream(head, lambda s, f, l, n: seen.append((s, f.ctypes.data == dest[s:].ctypes.data,
                                                     np.array_equal(f, dest[s:s + len(f)]))), R, t, destination=dest)
    assert np.array_equal(dest, expected)
    assert [s for s, _, _ in seen] == [0, 16, 32] and all(same for _, _, same in seen)
    if ev.on_host_cores:
        assert all(in_place for _, in_place, _ in seen)
    out = np.empty_like(dest)
    assert ev.evaluate(head, rigid=(R, t), out=out) is out and np.array_equal(out, expected)
    with pytest.raises(ValueError, match="destination"):
        ev.stream(head, lambda *a: None, destination=dest[:, :10])


def test_stream_chunks_drives_numpy_and_opencl_alike(sample, tmp_path):
    _device_or_skip()
    _, rig, fit, head, diag = sample
    model = model_from_fit(fit, rig, "wpsd")
    R, t = _motion(len(head), seed=5)
    outputs = {}
    for name, ev in (("numpy", NumpyEvaluator(model)), ("opencl", opencl.OpenCLEvaluator(model, chunk=16))):
        path = tmp_path / f"{name}.npy"
        with NpyWriter(path, (len(head), model.n_vertices, 3)) as w:
            stream_chunks(ev, head, lambda s, f, l, n: w.write(f), R, t, chunk=16)
        outputs[name] = np.load(path)
    assert np.abs(outputs["numpy"] - outputs["opencl"]).max() <= TOL * (diag + np.abs(t).max())


def test_replay_in_windows_equals_replay_whole(sample, tmp_path):
    """A take handed over window by window (cleaned while the previous window is evaluated) gives the
    same files as the whole take at once; an error in a later window leaves no positions file."""
    from facepipe.pipeline.replay import replay, replay_windows

    _, rig, fit, head, _ = sample
    model = model_from_fit(fit, rig, "wpsd")
    R, t = _motion(len(head), seed=7)
    frames = np.arange(len(head))
    times = frames / 30.0
    whole = replay(model, head, R, t, frames, times, tmp_path / "whole", chunk=8)
    cuts = [0, 5, 6, 23, len(head)]
    windows = [(head[a:b], R[a:b], t[a:b]) for a, b in zip(cuts, cuts[1:])]

    class OffHost(NumpyEvaluator):  # as a GPU: the next window is prepared on a thread meanwhile
        on_host_cores = False

    for name, ev in (("parts", NumpyEvaluator(model)), ("overlapped", OffHost(model))):
        parts = replay_windows(model, iter(windows), frames, times, tmp_path / name, evaluator=ev, chunk=8,
                               extra_report=lambda: {"windows": len(windows)})
        np.testing.assert_array_equal(np.load(parts.positions_path), np.load(whole.positions_path))
        a, b = np.load(tmp_path / "whole" / "handles.npz"), np.load(tmp_path / name / "handles.npz")
        for key in ("head", "rotation", "translation", "frame"):
            np.testing.assert_array_equal(a[key], b[key])
        assert parts.report["windows"] == 4 and parts.report["frames"] == len(head)

    def failing():
        yield windows[0]
        raise RuntimeError("window 2 could not be cleaned")

    for ev in (NumpyEvaluator(model), OffHost(model)):
        with pytest.raises(RuntimeError, match="window 2"):
            replay_windows(model, failing(), frames, times, tmp_path / "failed", evaluator=ev, chunk=8)
        assert not (tmp_path / "failed" / "positions.npy").exists()


def test_prefetched_keeps_order_raises_in_place_and_stops():
    import threading

    from facepipe.pipeline.replay import prefetched

    assert list(prefetched(iter(range(5)))) == [0, 1, 2, 3, 4]

    def bad():
        yield 1
        raise ValueError("the second item")

    items = prefetched(bad())
    assert next(items) == 1
    with pytest.raises(ValueError, match="second item"):
        next(items)
    before = threading.active_count()
    items = prefetched(iter(range(100)))
    assert next(items) == 0
    items.close()  # the consumer stops early: the producer thread ends too
    assert threading.active_count() == before


# ----------------------------------------------------------------------------- devices and the CLI


def test_device_selection(monkeypatch):
    _device_or_skip()
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    devices = opencl.list_devices()
    first = opencl.select_device()
    assert first in [d for _, _, d in devices]
    p, d, dev = devices[0]
    assert opencl.select_device(f"{p}:{d}") == dev
    assert opencl.select_device(dev.name.split()[0].lower()) is not None
    monkeypatch.setenv("PYOPENCL_CTX", f"{p}:{d}")
    assert opencl.select_device() == dev
    with pytest.raises(InputError, match="matches no OpenCL device"):
        opencl.select_device("no-such-device-xyz")


def test_devices_that_cannot_compile_are_passed_over(monkeypatch):
    """A driver may list a device it cannot compile for (PoCL whose LLVM does not know the CPU):
    the automatic choice takes the next device that compiles; with none left, a clear error that
    carries the driver's reason. Simulated with stand-in devices, so it runs without a driver."""
    from types import SimpleNamespace

    pytest.importorskip("pyopencl")
    import pyopencl as cl

    def fake(ptr, name, version):
        platform = SimpleNamespace(name="Portable Computing Language", version=version)
        return SimpleNamespace(int_ptr=ptr, name=name, platform=platform, type=cl.device_type.CPU)

    old, new = fake(101, "pthread-old", "PoCL 3.0 LLVM 14"), fake(102, "pthread-new", "PoCL 3.1 LLVM 15")
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    monkeypatch.setattr(opencl.device, "list_devices", lambda: [(0, 0, old), (1, 0, new)])
    monkeypatch.setattr(opencl.device, "_compile_errors",
                        {101: "PoCL 3.0 LLVM 14: error: unknown target CPU 'generic'", 102: None})
    assert opencl.select_device() is new
    assert opencl.select_device("0:0") is old  # asked for by name: its own build error will say why
    monkeypatch.setattr(opencl.device, "list_devices", lambda: [(0, 0, old)])
    with pytest.raises(InputError, match="can compile kernels.*unknown target CPU 'generic'") as err:
        opencl.select_device()
    assert "--backend numpy" in str(err.value.hint)


@pytest.fixture(scope="module")
def baked(sample):
    d = sample[0]
    assert run("bake", d / "rig" / "sample.toml", "-o", d / "model.npz", "-q") == 0
    return d


def test_cli_replay_records_backend_and_device(baked):
    _device_or_skip()
    d = baked
    assert run("replay", d / "rig" / "take.csv", "-m", d / "model.npz", "-o", d / "ocl", "--backend", "opencl",
               "--chunk", "16", "--frames", "3:29", "--save-large-scale", "-q") == 0
    report = json.loads((d / "ocl" / "replay.json").read_text())
    assert report["backend"] == "opencl" and "compute units" in report["device"]
    assert report["frames"] == 26 and "frames_fine_scale" in report["stage_seconds"]
    assert run("replay", d / "rig" / "take.csv", "-m", d / "model.npz", "-o", d / "np", "--backend", "numpy",
               "--frames", "3:29", "--save-large-scale", "-q") == 0
    assert json.loads((d / "np" / "replay.json").read_text())["backend"] == "numpy"
    diag = sample_diag = float(np.linalg.norm(np.ptp(np.load(d / "np" / "positions.npy")[0], axis=0)))
    for name in ("positions.npy", "large_scale.npy"):
        a, b = np.load(d / "ocl" / name), np.load(d / "np" / name)
        assert a.shape == b.shape == (26, a.shape[1], 3)
        assert np.abs(a - b).max() <= TOL * max(diag, sample_diag)


def test_cli_replay_cleans_a_long_take_window_by_window(baked, monkeypatch):
    """replay cleans a take longer than a window window by window (here 8 frames, 4 of context) and
    says so in replay.json; the result stays that of the whole take up to the windows' own noise
    estimates (this take has no noise)."""
    from facepipe.mocap import prepare

    d = baked
    assert run("replay", d / "rig" / "take.csv", "-m", d / "model.npz", "-o", d / "w1", "--backend", "numpy",
               "-q") == 0
    monkeypatch.setattr(prepare, "CLEAN_WINDOW", 8)
    monkeypatch.setattr(prepare, "clean_margin", lambda options, fps: 4)
    assert run("replay", d / "rig" / "take.csv", "-m", d / "model.npz", "-o", d / "w8", "--backend", "numpy",
               "-q") == 0
    one, eight = (json.loads((d / name / "replay.json").read_text()) for name in ("w1", "w8"))
    assert "windows" not in one["mocap"]["cleaning"]["noise"]
    assert eight["mocap"]["cleaning"]["noise"]["windows"] == 5 and eight["frames"] == one["frames"] == 40
    a, b = np.load(d / "w1" / "positions.npy"), np.load(d / "w8" / "positions.npy")
    diag = float(np.linalg.norm(np.ptp(a[0], axis=0)))
    assert np.abs(a - b).max() <= 1e-3 * diag


def test_cli_without_opencl_platform(baked, monkeypatch, capsys):
    d = baked
    monkeypatch.setattr(opencl.device, "list_devices", lambda: [])
    assert run("replay", d / "rig" / "take.csv", "-m", d / "model.npz", "-o", d / "none", "--backend",
               "opencl") == 2
    err = capsys.readouterr().err
    assert "no OpenCL platform" in err and "--backend numpy" in err
    assert not (d / "none" / "positions.npy").exists()
    # the default (auto) falls back to NumPy and says so
    assert run("replay", d / "rig" / "take.csv", "-m", d / "model.npz", "-o", d / "auto", "--frames", "0:4") == 0
    assert "NumPy backend" in capsys.readouterr().out
    assert json.loads((d / "auto" / "replay.json").read_text())["backend"] == "numpy"


def test_driver_that_cannot_compile_for_this_cpu_is_unavailable(monkeypatch):
    """A PoCL whose LLVM does not know the CPU fails every build with 'unknown target CPU': that is
    OpenCLUnavailable (an InputError: exit status 2 with --backend opencl, NumPy with auto)."""
    _device_or_skip()
    import pyopencl as cl

    class Refusing:
        def __init__(self, *args):
            pass

        def build(self, options=()):
            raise cl.RuntimeError("clBuildProgram failed: BUILD_PROGRAM_FAILURE\nerror: unknown target CPU 'generic'")

    context, _ = opencl.device.open_device(None)
    monkeypatch.setattr(cl, "Program", Refusing)
    monkeypatch.setattr(opencl.device, "_compile_errors", {})  # the driver's probe is refused too
    with pytest.raises(opencl.OpenCLUnavailable, match="cannot compile kernels for this CPU"):
        opencl.device.build_program(context, {"FOR_THIS_TEST": 1})


def test_a_changed_kernel_source_is_compiled_again(monkeypatch):
    """The program cache keys on the source text: a kernel changed in the same process (a
    benchmark's variant) is built from the new text, while the same text is built once."""
    _device_or_skip()
    context, _ = opencl.device.open_device(None)
    texts = iter(["__kernel void k(__global float *x) { x[0] = 1.0f; }",
                  "__kernel void k(__global float *x) { x[0] = 1.0f; }",
                  "__kernel void k(__global float *x) { x[0] = 2.0f; }"])
    monkeypatch.setattr(opencl.device, "kernel_source", lambda name="replay.cl": next(texts))
    first = opencl.device.build_program(context, {"FOR_THIS_TEST": 2})
    assert opencl.device.build_program(context, {"FOR_THIS_TEST": 2}) is first
    assert opencl.device.build_program(context, {"FOR_THIS_TEST": 2}) is not first


def test_cli_bad_device_is_input_error(baked, capsys):
    _device_or_skip()
    d = baked
    assert run("replay", d / "rig" / "take.csv", "-m", d / "model.npz", "-o", d / "bad", "--device",
               "no-such-device-xyz") == 2
    assert "matches no OpenCL device" in capsys.readouterr().err


# ----------------------------------------------------------------------------- the ICT kit


@pytest.mark.ict
def test_ict_matches_numpy_reference(ict_rig_fit):
    _device_or_skip()
    rig, fit = ict_rig_fit
    truth = np.load(ict_or_skip() / "train_truth.npz")["positions"][:48]
    head = truth[:, rig.handles].astype(np.float64)
    diag = float(np.linalg.norm(np.ptp(rig.mesh.vertices, axis=0)))
    for method in ("wpsd", "psd"):
        model = model_from_fit(fit, rig, method)
        ref = NumpyEvaluator(model).evaluate(head)
        out = opencl.OpenCLEvaluator(model, reorder="rcm").evaluate(head)
        assert np.abs(out - ref).max() <= TOL * diag, method


def test_bench_end_to_end_on_a_small_rig(tmp_path):
    """`python -m bench.paper_scale` at a small size, on the generated rig alone: every section is
    measured and written (no times asserted)."""
    from click.testing import CliRunner

    from bench.paper_scale import main as bench_main

    _device_or_skip()
    out = tmp_path / "results.json"
    result = CliRunner().invoke(bench_main, ["-o", str(out), "--vertices", "2500", "--frames", "8", "--repeats", "1",
                                             "--bake-repeats", "3", "--work", str(tmp_path / "work"), "--no-kit",
                                             "--exr-resolution", "256", "-q"])
    assert result.exit_code == 0, result.output
    res = json.loads(out.read_text())
    runs = res["bake"]["runs_seconds"]
    assert len(runs) == 3 and round(res["bake"]["seconds"], 2) == sorted(runs)[1]  # the median run
    assert res["bake"]["peak_rss_mb"] > 0 and res["bake"]["fit_phases"]["geometry"] > 0
    for section in ("replay_opencl", "replay_numpy", "baseline_sparse_solve", "ratios", "export", "video_lift"):
        assert res[section], section
    assert res["baseline_sparse_solve"]["frames_per_second"] > 0
    assert res["replay_opencl"]["in_memory"]["frames_per_second"] > 0
    after = res["replay_opencl"]["roofline"]["after"]
    for clock in ("busy", "wall"):
        assert set(after[clock]) == {"host_tables", "large_scale", "frames", "fine_scale", "output", "host_copy",
                                     "positions_write"}
    assert after["busy"]["large_scale"]["ratio_to_limit"] > 0
    assert res["limits"]["fma_gflops"]["wall"] > 0 and res["limits"]["copy_gbs"]["wall"] > 0
    assert set(res["bake"]["phases_seconds"]) >= {"load", "geometry", "details", "greedy", "save"}
    assert res["video_lift"]["frames_per_second"] > 0 and res["video_lift"]["landmarks"] == 68
