"""Video takes: 2D landmark readers, cameras, landmark maps, the lift of 2D tracks to 3D (core maths
against independent checks), bad input, and an end-to-end replay of a synthetic filmed take of the
sample rig; on the ICT kit, the numbers of the README's Video takes section."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from facepipe.core.camera import Camera, pixel_rays, project, project_distorted, undistort_points
from facepipe.core.lift import (fade_fill, fit_pose_expression_2d, intersect_ray_plane, intersect_rays_triangles,
                                landmarks_to_handles, rotation_from_vector)
from facepipe.errors import InputError
from tests.conftest import ict_or_skip, run_cli

MATRIX = np.array([[1000.0, 0.0, 639.5], [0.0, 1000.0, 359.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.06, 0.03, 0.0004, -0.0002, 0.0])
CAMERA = Camera(MATRIX, DIST, 1280, 720, "made-up")
#: the rig (+y up, +z toward the viewer) seen from the front: OpenCV's camera has y down, z forward
FACING = np.diag([1.0, -1.0, -1.0])


# ----------------------------------------------------------------------------- core maths


def test_pose_and_expression_recovered_exactly_from_noiseless_projections():
    rng = np.random.default_rng(1)
    L, K, n = 40, 5, 6
    rest = rng.normal(size=(L, 3)) * [6.0, 8.0, 3.0]
    basis = rng.normal(size=(K, L, 3)) * 0.8
    C_true = rng.uniform(0.05, 0.9, size=(n, K))
    R_true = rotation_from_vector(rng.normal(size=(n, 3)) * 0.2) @ FACING
    t_true = np.array([0.0, 0.0, 60.0]) + rng.normal(size=(n, 3))
    y = rest + np.einsum("nk,klc->nlc", C_true, basis)
    pts = project(MATRIX, np.einsum("nij,nlj->nli", R_true, y) + t_true[:, None])
    R0 = rotation_from_vector(rng.normal(size=(n, 3)) * 0.05) @ R_true
    t0 = t_true + rng.normal(size=(n, 3))
    R, t, C, r, _ = fit_pose_expression_2d(pts, np.ones((n, L)), MATRIX, rest, basis, R0, t0, prior=0.0,
                                           iterations=50, tolerance=0.0)
    assert np.abs(r).max() < 1e-6
    assert np.abs(R - R_true).max() < 1e-7
    assert np.abs(t - t_true).max() < 1e-5
    assert np.abs(C - C_true).max() < 1e-6


def test_weights_stay_within_bounds():
    rng = np.random.default_rng(2)
    L, K = 30, 3
    rest = rng.normal(size=(L, 3)) * 5
    basis = rng.normal(size=(K, L, 3))
    C_true = np.array([[1.6, -0.5, 0.4]])  # beyond both bounds
    R_true = FACING[None]
    t_true = np.array([[0.0, 0.0, 50.0]])
    pts = project(MATRIX, np.einsum("nij,nlj->nli", R_true, rest + np.einsum("nk,klc->nlc", C_true, basis))
                  + t_true[:, None])
    _, _, C, _, _ = fit_pose_expression_2d(pts, np.ones((1, L)), MATRIX, rest, basis, R_true, t_true, prior=0.0,
                                           upper=1.0, iterations=60)
    assert C.min() >= 0.0 and C.max() <= 1.0
    assert C[0, 0] == pytest.approx(1.0) and C[0, 1] == pytest.approx(0.0)


def test_cauchy_weights_a_slipped_landmark_away():
    rng = np.random.default_rng(3)
    L = 30
    rest = rng.normal(size=(L, 3)) * 5
    R_true, t_true = FACING[None], np.array([[1.0, -2.0, 50.0]])
    pts = project(MATRIX, np.einsum("nij,nlj->nli", R_true, rest[None]) + t_true[:, None])
    pts[0, 3] += [40.0, -25.0]  # a slipping tracker point
    basis = np.zeros((0, L, 3))
    plain = fit_pose_expression_2d(pts, np.ones((1, L)), MATRIX, rest, basis, R_true, t_true + 0.5, iterations=40)
    robust = fit_pose_expression_2d(pts, np.ones((1, L)), MATRIX, rest, basis, R_true, t_true + 0.5, robust=1.0,
                                    iterations=40)
    assert np.abs(robust[1] - t_true).max() < 0.1 * np.abs(plain[1] - t_true).max()
    assert robust[4][0, 3] < 0.01 * robust[4][0, 4]


def test_ray_intersection_with_a_plane_is_exact():
    rng = np.random.default_rng(4)
    # a tessellated plane z = 5 + 0.2 x - 0.1 y (two triangles per cell) and rays from the origin
    u, v = np.meshgrid(np.linspace(-4, 4, 9), np.linspace(-4, 4, 9))
    P = np.stack([u, v, 5 + 0.2 * u - 0.1 * v], axis=-1).reshape(-1, 3)
    idx = np.arange(81).reshape(9, 9)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    F = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    dirs = np.concatenate([rng.uniform(-0.5, 0.5, size=(50, 2)), np.ones((50, 1))], axis=1)
    tri = np.broadcast_to(P[F], (50,) + P[F].shape)
    s, hit, pts = intersect_rays_triangles(np.zeros((50, 3)), dirs, tri)
    assert hit.all()
    # analytic: s (z - 0.2 x + 0.1 y) = 5
    s_true = 5.0 / (dirs[:, 2] - 0.2 * dirs[:, 0] + 0.1 * dirs[:, 1])
    assert np.allclose(s, s_true, rtol=1e-12)
    s_plane, _ = intersect_ray_plane(np.zeros((50, 3)), dirs, np.array([0, 0, 5.0]), np.array([-0.2, 0.1, 1.0]))
    assert np.allclose(s_plane, s_true, rtol=1e-12)
    # a ray beside the patch misses
    _, hit, pts = intersect_rays_triangles(np.zeros(3), np.array([5.0, 0, 1]), P[F])
    assert not hit and np.isnan(pts).all()


def test_ray_intersection_with_a_sphere_within_its_tessellation():
    trimesh = pytest.importorskip("trimesh")
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=2.0)
    V, F = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    centre = np.array([0.3, -0.2, 10.0])
    rng = np.random.default_rng(5)
    dirs = centre + rng.uniform(-1.2, 1.2, size=(40, 3)) * [1, 1, 0]
    s, hit, pts = intersect_rays_triangles(np.zeros((40, 3)), dirs, np.broadcast_to((V + centre)[F], (40,) + F.shape + (3,)))
    # analytic: the nearest root of |s d - c|² = r²
    a = (dirs ** 2).sum(1)
    b = -2 * (dirs @ centre)
    c = centre @ centre - 4.0
    s_true = (-b - np.sqrt(b * b - 4 * a * c)) / (2 * a)
    edge = np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1).max()
    sagitta = 2.0 * (1 - np.cos(edge / 2.0))  # how far a flat triangle lies inside the sphere
    assert hit.all()
    assert np.all(np.abs(np.linalg.norm(pts - centre, axis=1) - 2.0) <= sagitta + 1e-9)
    assert np.all(s >= s_true - 1e-9)  # the flat facets lie inside the sphere: hit later along the ray


def test_undistortion_inverts_opencv_projection():
    rng = np.random.default_rng(6)
    X = np.concatenate([rng.uniform(-14, 14, size=(100, 2)) * [1.0, 0.55], rng.uniform(40, 60, size=(100, 1))], axis=1)
    distorted = project_distorted(CAMERA, X)
    ideal = undistort_points(CAMERA, distorted)
    assert np.abs(ideal - project(MATRIX, X)).max() < 1e-3
    assert np.abs(distorted - project(MATRIX, X)).max() > 1.0  # the distortion is not nothing
    rays = pixel_rays(MATRIX, ideal)
    assert np.allclose(rays[:, :2], X[:, :2] / X[:, 2:], atol=1e-5)


def test_landmark_map_to_handles_moves_nothing_unseen_and_never_overshoots():
    rng = np.random.default_rng(7)
    H, L = 12, 8
    B = np.zeros((L, H))
    B[:, :6] = rng.dirichlet(np.ones(6), size=L)  # landmarks feel only the first six handles
    edges = np.array([[i, i + 1] for i in range(5)] + [[6, 7], [8, 9]])  # 6..11 not joined to 0..5
    M = landmarks_to_handles(B, edges)
    assert np.abs(M[6:]).max() < 1e-12
    chained = landmarks_to_handles(B, np.array([[i, i + 1] for i in range(H - 1)]))
    assert np.abs(chained[7:]).max() < np.abs(chained[:6]).max()
    # regularised least squares: the landmarks never move by more than the residual asked
    assert np.linalg.norm(B @ M, 2) <= 1.0 + 1e-12
    assert np.allclose(B @ M @ np.ones(L), 1.0, atol=0.1)  # a shift of every landmark is a shift


def test_fade_fill_interpolates_short_gaps_and_decays_long_ones():
    times = np.arange(100) / 30.0
    values = np.ones((100, 1, 2))
    known = np.ones((100, 1), bool)
    known[10:12] = False
    known[40:100] = False
    out = fade_fill(values, known, times, decay=0.2)
    assert np.all(out[10:12] > 0.8)
    assert out[99, 0, 0] < 1e-3 and out[40, 0, 0] > 0.8 and out[70, 0, 0] < 0.01


# ----------------------------------------------------------------------------- files


def _openface_text(frames, times, pts, success=None, confidence=None, extra=True):
    T, L = pts.shape[:2]
    success = np.ones(T, int) if success is None else success
    confidence = np.where(success > 0, 0.98, 0.0) if confidence is None else confidence
    head = ["frame", "face_id", "timestamp", "confidence", "success"] + [f"x_{i}" for i in range(L)] + \
        [f"y_{i}" for i in range(L)] + (["pose_Tx", "AU01_r"] if extra else [])
    rows = [", ".join(head)]
    for f in range(T):
        p = np.where(success[f] > 0, pts[f], 0.0)
        vals = [str(frames[f]), "0", f"{times[f]:.3f}", f"{confidence[f]:.2f}", str(success[f])] + \
            [f"{v:.3f}" for v in p[:, 0]] + [f"{v:.3f}" for v in p[:, 1]] + (["1.0", "0.2"] if extra else [])
        rows.append(", ".join(vals))
    return "\n".join(rows) + "\n"


def test_openface_reader_and_uv_reader_agree(tmp_path):
    from facepipe.mocap import detect_format
    from facepipe.mocap.landmarks2d import read_landmark_take, write_uv_csv

    rng = np.random.default_rng(8)
    pts = rng.uniform(100, 600, size=(5, 4, 2))
    success = np.array([1, 0, 1, 1, 1])
    conf = np.array([0.9, 0.0, 0.3, 0.95, 0.99])
    of = tmp_path / "of.csv"
    of.write_text(_openface_text(np.arange(1, 6), np.arange(5) / 30, pts, success, conf))
    uv = tmp_path / "uv.csv"
    missing = pts.copy()
    missing[1] = np.nan
    missing[2] = np.nan
    write_uv_csv(uv, np.arange(1, 6), np.arange(5) / 30, missing, ["0", "1", "2", "3"])
    assert detect_format(of).name == "openface-csv" and detect_format(uv).name == "uv-csv"
    a = read_landmark_take(of, ["3", "0", "1"])
    b = read_landmark_take(uv, ["3", "0", "1"])
    assert a.failed.tolist() == [False, True, True, False, False]  # success 0, and a confidence of 0.3
    assert np.allclose(a.points, b.points, equal_nan=True, atol=1e-3)
    assert np.allclose(a.points[0], pts[0, [3, 0, 1]], atol=1e-3) and a.extra == ["2"]


def test_a_3d_replay_of_a_2d_take_is_refused_with_the_fix(tmp_path):
    from facepipe.mocap import read_take

    path = tmp_path / "of.csv"
    path.write_text(_openface_text([1, 2], [0, 0.033], np.ones((2, 3, 2)) * 50))
    with pytest.raises(InputError, match="2D landmark tracks.*\n.*--camera"):
        read_take(path, ["M1"], units="cm")


def test_camera_files(tmp_path):
    from facepipe.io.camera_file import read_camera, write_camera

    for name in ("cam.yml", "cam.json", "cam.xml"):
        write_camera(tmp_path / name, CAMERA)
        cam = read_camera(tmp_path / name)
        assert np.allclose(cam.matrix, MATRIX) and np.allclose(cam.distortion, DIST)
        assert (cam.width, cam.height) == (1280, 720)
    with pytest.raises(InputError, match="not found"):
        read_camera(tmp_path / "none.yml")
    (tmp_path / "bad.json").write_text(json.dumps({"image_width": 640, "image_height": 480,
                                                   "camera_matrix": [[1, 0, 2], [0, 1, 3]], "dist_coeffs": []}))
    with pytest.raises(InputError, match=r"bad.json: camera_matrix has shape \(2, 3\)"):
        read_camera(tmp_path / "bad.json")
    (tmp_path / "nosize.json").write_text(json.dumps({"camera_matrix": MATRIX.tolist()}))
    with pytest.raises(InputError, match="lacks 'image_width'"):
        read_camera(tmp_path / "nosize.json")
    (tmp_path / "garbage.yml").write_text("%YAML:1.0\n---\ncamera_matrix: [ 1, 2\n")
    with pytest.raises(InputError, match="garbage.yml"):
        read_camera(tmp_path / "garbage.yml")


@pytest.mark.parametrize("matrix, expected", [
    ("   rows: 3\n   dt: d\n   data: [ 1, 0, 2, 0, 1, 3, 0, 0, 1 ]\n", "camera_matrix has no whole number 'cols'"),
    ("   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1, 0, 2, 0, 1, 3 ]\n",
     "camera_matrix says 3 × 3 but its data holds 6 numbers"),
    ("   rows: 3\n   cols: 3\n   data: [ 1, 0, 2, 0, 1, 3, 0, 0, 1 ]\n", "camera_matrix has no element type"),
])
def test_inconsistent_opencv_matrices_are_refused_before_opencv_reads_them(tmp_path, matrix, expected):
    """A matrix node whose rows, cols and data disagree is an input error; OpenCV itself reads such
    a node past its buffer and the process dies later in malloc."""
    from facepipe.io.camera_file import read_camera

    path = tmp_path / "cam.yml"
    path.write_text("%YAML:1.0\n---\nimage_width: 1280\nimage_height: 720\ncamera_matrix: !!opencv-matrix\n" + matrix)
    for _ in range(20):  # (the heap damage showed only after several reads)
        with pytest.raises(InputError, match=expected):
            read_camera(path)
    path.write_text("%YAML:1.0\n---\n- 1\n- 2\n")  # a list, not a map of keys
    with pytest.raises(InputError, match="no map of keys"):
        read_camera(path)


def test_calibrations_other_tools_write(tmp_path):
    """JSON that OpenCV's FileStorage writes (opencv-matrix objects), and the names other tools
    give the intrinsics, read as the same camera."""
    import cv2

    from facepipe.io.camera_file import read_camera

    fs = cv2.FileStorage(str(tmp_path / "opencv.json"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1280)
    fs.write("image_height", 720)
    fs.write("camera_matrix", MATRIX)
    fs.write("distortion_coefficients", DIST.reshape(1, -1))
    fs.release()
    fx, fy, cx, cy = MATRIX[0, 0], MATRIX[1, 1], MATRIX[0, 2], MATRIX[1, 2]
    variants = {"opencv.json": None,
                "k.json": {"K": MATRIX.tolist(), "dist": DIST.tolist(), "resolution": [1280, 720]},
                "focal.json": {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "D": DIST.tolist(), "width": 1280,
                               "height": 720}}
    for name, content in variants.items():
        if content is not None:
            (tmp_path / name).write_text(json.dumps(content))
        cam = read_camera(tmp_path / name)
        assert np.allclose(cam.matrix, MATRIX) and np.allclose(cam.distortion, DIST), name
        assert (cam.width, cam.height) == (1280, 720), name
    (tmp_path / "nomatrix.json").write_text(json.dumps({"width": 640, "height": 480}))
    with pytest.raises(InputError, match="lacks 'camera_matrix'"):
        read_camera(tmp_path / "nomatrix.json")


def test_landmark_map_errors(tmp_path):
    from facepipe.io.landmark_map import read_landmark_map

    p = tmp_path / "lm.csv"
    p.write_text("name,vertex\n" + "".join(f"{i},{i}\n" for i in range(8)))
    assert read_landmark_map(p, 100).vertices.tolist() == list(range(8))
    p.write_text("name,vertex\n" + "".join(f"{i},{i}\n" for i in range(8)) + "8,100\n")
    with pytest.raises(InputError, match="line 10: landmark 8 is vertex 100, the mesh has 100"):
        read_landmark_map(p, 100)
    p.write_text("name,vertex\n" + "".join(f"{i},{i}\n" for i in range(8)) + "3,9\n")
    with pytest.raises(InputError, match="landmark 3 is also on line 5"):
        read_landmark_map(p, 100)


# ----------------------------------------------------------------------------- a filmed sample rig


class Filmed:
    """The sample rig baked, a known performance of it filmed by a made-up camera."""


@pytest.fixture(scope="module")
def filmed(tmp_path_factory):
    from facepipe.io.camera_file import write_camera
    from facepipe.io.model_file import load_model
    from facepipe.pipeline.replay import NumpyEvaluator

    root = tmp_path_factory.mktemp("video")
    assert run_cli("sample", root / "rig", "--vertices", 3000, "--quiet") == 0
    assert run_cli("bake", root / "rig" / "sample.toml", "-o", root / "model.npz", "--quiet") == 0
    model = load_model(root / "model.npz")
    rest = model.rest.astype(np.float64)
    rng = np.random.default_rng(11)
    # landmarks: 40 vertices spread over the front of the face (farthest points), named 0..39
    front = np.flatnonzero(rest[:, 2] > np.percentile(rest[:, 2], 40))
    chosen = [front[np.argmax(rest[front, 2])]]
    d = np.linalg.norm(rest[front] - rest[chosen[0]], axis=1)
    for _ in range(39):
        chosen.append(front[np.argmax(d)])
        d = np.minimum(d, np.linalg.norm(rest[front] - rest[chosen[-1]], axis=1))
    vertices = np.array(chosen)
    (root / "landmarks.csv").write_text("name,vertex\n" + "".join(f"{i},{v}\n" for i, v in enumerate(vertices)))
    # a performance in the span of the examples, smooth in time, with head motion
    T = 60
    eh = model.example_handles.astype(np.float64)
    K = len(eh) - 1
    phase = rng.uniform(0, 2 * np.pi, K)
    speed = rng.uniform(0.5, 2.0, K)
    tt = np.arange(T) / 30.0
    weights = np.clip(0.5 * np.sin(speed * 2 * np.pi * tt[:, None] + phase) + 0.1, 0.0, 0.8)
    handles = eh[0] + np.einsum("tk,khc->thc", weights, eh[1:] - eh[0])
    truth = NumpyEvaluator(model).evaluate(handles)
    R = rotation_from_vector(np.stack([0.15 * np.sin(2 * tt), 0.25 * np.sin(1.3 * tt), 0.05 * tt], 1)) @ FACING
    t = np.stack([2 * np.sin(tt), np.cos(tt) - 1, 55 + 3 * tt], 1)
    cam = np.einsum("tij,tvj->tvi", R, truth) + t[:, None]
    px = project_distorted(CAMERA, cam[:, vertices]) + rng.normal(scale=0.3, size=(T, len(vertices), 2))
    px[rng.random(px.shape[:2]) < 0.03] = np.nan  # occasional missing samples
    f = Filmed()
    f.root, f.model, f.vertices, f.truth, f.cam, f.px, f.tt, f.R, f.t = root, model, vertices, truth, cam, px, tt, R, t
    f.camera = root / "camera.yml"
    write_camera(f.camera, CAMERA)
    success = np.ones(T, int)
    success[20:23] = 0  # a short tracking failure
    f.take = root / "take_openface.csv"
    f.take.write_text(_openface_text(np.arange(1, T + 1), tt, np.nan_to_num(px, nan=0.0), success))
    f.success = success
    return f


def _replay(f, out, *extra, take=None):
    return run_cli("replay", take or f.take, "-m", f.root / "model.npz", "--camera", f.camera, "--landmarks",
                   f.root / "landmarks.csv", "-o", out, "--backend", "numpy", "--quiet", *extra)


def test_lift_recovers_a_filmed_performance(filmed, tmp_path):
    f = filmed
    # blank the missing samples in the OpenFace file: a take with NaN samples is the u/v CSV's
    from facepipe.mocap.landmarks2d import write_uv_csv

    uv = tmp_path / "take_uv.csv"
    px = f.px.copy()
    px[f.success == 0] = np.nan
    write_uv_csv(uv, np.arange(1, len(px) + 1), f.tt, px, [str(i) for i in range(px.shape[1])])
    errors = {}
    for lift in ("model", "heuristic"):
        assert _replay(f, tmp_path / lift, "--head-motion", "remove", "--lift", lift, take=uv) == 0
        out = np.load(tmp_path / lift / "positions.npy")
        errors[lift] = np.sqrt(((out - f.truth) ** 2).sum(-1).mean())
    motion = np.sqrt(((f.truth - f.model.rest) ** 2).sum(-1).mean())
    assert errors["model"] < 0.25 * motion
    assert errors["model"] < 0.8 * errors["heuristic"]
    report = json.loads((tmp_path / "model" / "replay.json").read_text())["video"]
    assert report["frames_missing"] == 3 and report["frames_filled"] == 3
    assert report["reprojection_px"]["mean"] < 1.5
    assert len(report["head_pose"]["rotation_deg"]) == len(px)


def test_head_motion_keep_writes_camera_coordinates(filmed, tmp_path):
    f = filmed
    assert _replay(f, tmp_path / "keep") == 0
    out = np.load(tmp_path / "keep" / "positions.npy")
    # the face where the camera saw it: its landmarks project onto the tracked points
    px = project_distorted(CAMERA, out[:, f.vertices].astype(np.float64))
    seen = f.success > 0
    err = np.linalg.norm(px[seen] - f.px[seen], axis=-1)
    assert np.nanmean(err) < 1.5
    assert np.abs(out - f.cam).mean() < 0.5 * np.abs(f.cam - f.cam.mean(axis=(0, 1))).mean()
    data = json.loads((tmp_path / "keep" / "replay.json").read_text())
    assert data["coordinates"].startswith("camera")


def test_tracker_lost_the_face_for_a_second(filmed, tmp_path):
    f = filmed
    T = len(f.tt)
    success = np.ones(T, int)
    success[15:45] = 0  # 1 s at 30 fps
    take = tmp_path / "lost.csv"
    take.write_text(_openface_text(np.arange(1, T + 1), f.tt, np.nan_to_num(f.px), success))
    assert _replay(f, tmp_path / "lost", "--head-motion", "remove", take=take) == 0
    report = json.loads((tmp_path / "lost" / "replay.json").read_text())["video"]
    assert report["frames_missing"] == 30 and report["longest_gap_frames"] == 30
    out = np.load(tmp_path / "lost" / "positions.npy")
    assert np.isfinite(out).all()
    # in the middle of the gap the face has faded to neutral
    assert np.abs(out[30] - f.model.rest).max() < 0.1 * np.abs(f.truth - f.model.rest).max()


def _expect_error(f, tmp_path, take, match, *extra, camera=None):
    out = tmp_path / "out"
    code = run_cli("replay", take, "-m", f.root / "model.npz", "--camera", camera or f.camera, "--landmarks",
                   f.root / "landmarks.csv", "-o", out, "--backend", "numpy", "--quiet", *extra)
    assert code == 2
    assert not (out / "positions.npy").exists() and not (out / "replay.json").exists()


def test_a_broken_calibration_matrix_stops_the_replay_with_exit_2(filmed, tmp_path, capsys):
    """Through the command line: a camera matrix node without cols is exit 2 naming it, and the
    replay writes nothing (OpenCV itself would have read it past its buffer)."""
    f = filmed
    text = f.camera.read_text()
    broken = tmp_path / "broken.yml"
    assert "cols: 3" in text
    broken.write_text(text.replace("cols: 3", "", 1))
    _expect_error(f, tmp_path, f.take, None, camera=broken)
    assert "camera_matrix has no whole number 'cols'" in capsys.readouterr().err


def test_bad_takes_exit_2_naming_what_is_wrong(filmed, tmp_path, capsys):
    f = filmed
    T, L = f.px.shape[:2]
    frames, good = np.arange(1, T + 1), np.nan_to_num(f.px)

    def check(name, text, match, **kw):
        p = tmp_path / name
        p.write_text(text)
        _expect_error(f, tmp_path, p, match, **kw)
        err = capsys.readouterr().err
        assert str(p) in err or str(kw.get("camera", "")) in err, err
        import re

        assert re.search(match, err), err

    # a tracker with fewer points than the map names
    check("few.csv", _openface_text(frames, f.tt, good[:, :30]), r"map names 40 landmarks, the take has 30.*30, 31")
    # frames out of order
    back = frames.copy()
    back[10] = 5
    check("order.csv", _openface_text(back, f.tt, good), r"frame 5 \(line 12\): frame number goes back")
    # an infinite coordinate
    inf = _openface_text(frames, f.tt, good).splitlines()
    fields = inf[4].split(", ")
    fields[5 + 7] = "inf"
    inf[4] = ", ".join(fields)
    check("inf.csv", "\n".join(inf) + "\n", r"frame 4 \(line 5\): landmark 7 \(x\) is infinite")
    # every frame failed
    check("failed.csv", _openface_text(frames, f.tt, good, np.zeros(T, int)), r"no frame has a tracked face: 60 of 60")
    # the landmarks outside the camera's stated image (a calibration at half the footage's size)
    from facepipe.io.camera_file import write_camera

    half = tmp_path / "half.yml"
    write_camera(half, Camera(MATRIX / [[2], [2], [1]], DIST, 640, 360))
    check("ok.csv", _openface_text(frames, f.tt, good), r"outside the camera's 640 × 360 image", camera=half)
    # a camera matrix of the wrong shape, a camera that is missing
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"image_width": 1280, "image_height": 720, "camera_matrix": [[1000, 0, 640]],
                               "dist_coeffs": [0, 0, 0, 0]}))
    check("ok2.csv", _openface_text(frames, f.tt, good), r"camera_matrix has shape \(1, 3\)", camera=bad)
    check("ok3.csv", _openface_text(frames, f.tt, good), r"camera calibration not found",
          camera=tmp_path / "nowhere.yml")
    (tmp_path / "ok4.csv").write_text(_openface_text(frames, f.tt, good))
    _expect_error(f, tmp_path, tmp_path / "ok4.csv", None, "--min-confidence", "2")
    assert "--min-confidence 2.0 is outside 0..1" in capsys.readouterr().err


def test_a_2d_take_without_camera_is_refused(filmed, tmp_path, capsys):
    f = filmed
    code = run_cli("replay", f.take, "-m", f.root / "model.npz", "-o", tmp_path / "o", "--quiet")
    assert code == 2
    assert "--camera" in capsys.readouterr().err
    assert not (tmp_path / "o" / "positions.npy").exists()


def test_nan_fields_are_missing_samples_and_the_replay_fills_them(filmed, tmp_path):
    f = filmed
    T = len(f.tt)
    text = _openface_text(np.arange(1, T + 1), f.tt, np.nan_to_num(f.px), f.success).splitlines()
    fields = text[6].split(", ")  # frame 6: landmark 4's x is NaN (a tracker writing nan for a lost point)
    fields[5 + 4] = "nan"
    text[6] = ", ".join(fields)
    take = tmp_path / "nan.csv"
    take.write_text("\n".join(text) + "\n")
    from facepipe.mocap.landmarks2d import read_landmark_take

    read = read_landmark_take(take, [str(i) for i in range(f.px.shape[1])])
    assert np.isnan(read.points[5, 4]).all() and not read.failed[5]  # the sample is missing, the frame kept
    assert _replay(f, tmp_path / "nan", take=take) == 0
    assert np.isfinite(np.load(tmp_path / "nan" / "positions.npy")).all()


def test_more_bad_takes_exit_2_and_write_nothing(filmed, tmp_path, capsys):
    from facepipe.mocap.landmarks2d import write_uv_csv

    f = filmed
    T, L = f.px.shape[:2]
    frames, names = np.arange(1, T + 1), [str(i) for i in range(L)]
    cases = []
    # a repeated frame (two rows of frame 8)
    rep = frames.copy()
    rep[8] = 8
    cases.append(("repeat.csv", rep, f.tt, f.px, r"frame 8 \(line 10\): frame number repeats frame 8"))
    # times that stand still
    still = f.tt.copy()
    still[20] = still[19]
    cases.append(("still.csv", frames, still, f.px, r"frame 21 \(line 22\): time .* is not after"))
    # every frame blank (a u/v take of a tracker that never found the face)
    cases.append(("blank.csv", frames, f.tt, np.full_like(f.px, np.nan), r"no frame has a tracked face: 60 of 60"))
    # a face in every frame, but never 6 of the map's landmarks
    few = np.full_like(f.px, np.nan)
    few[:, :4] = f.px[:, :4]
    cases.append(("few.csv", frames, f.tt, few, r"the others have fewer than 6 landmarks"))
    for name, fr, tt, px, match in cases:
        path = tmp_path / name
        write_uv_csv(path, fr, tt, px, names)
        _expect_error(f, tmp_path, path, match)
        err = capsys.readouterr().err
        assert str(path) in err and __import__("re").search(match, err), err
    # a tracker of other point names than the map's (a 5-point tracker for a 40-point map)
    path = tmp_path / "names.csv"
    write_uv_csv(path, frames, f.tt, f.px[:, :5], ["a", "b", "c", "d", "e"])
    _expect_error(f, tmp_path, path, "")
    assert "the landmark map names 40 landmarks, the take has 5" in capsys.readouterr().err


def test_pinhole_projection_is_opencvs():
    import cv2

    from facepipe.core.render import pinhole_project

    rng = np.random.default_rng(12)
    X = np.concatenate([rng.uniform(-12, 12, size=(200, 2)), rng.uniform(30, 70, size=(200, 1))], axis=1)
    full = [-0.1, 0.04, 0.001, -0.0007, 0.01, 0.02, -0.01, 0.005, 0.001, -0.002, 0.0015, 0.0008, 0.01, -0.02]
    for n in (0, 4, 5, 8, 12, 14):
        dist = np.array(full[:n])
        ours = pinhole_project(MATRIX, dist, X)
        theirs, _ = cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), MATRIX, dist)
        assert np.abs(ours - theirs.reshape(-1, 2)).max() < 1e-8, n
    skewed = MATRIX.copy()
    skewed[0, 1] = 3.0  # (OpenCV's projectPoints ignores a skew; the ideal pinhole keeps it)
    assert np.abs(pinhole_project(skewed, np.zeros(0), X) - project(skewed, X)).max() < 1e-9


def test_image_window_is_the_projection_cropped_and_resampled():
    from facepipe.core.render import image_window, pinhole_project

    rng = np.random.default_rng(13)
    X = np.concatenate([rng.uniform(-10, 10, size=(50, 2)), rng.uniform(40, 60, size=(50, 1))], axis=1)
    full = pinhole_project(MATRIX, DIST, X)
    x0, y0, scale = 300.0, 120.0, 0.37
    window = pinhole_project(image_window(MATRIX, x0, y0, scale), DIST, X)
    assert np.allclose(window, (full - [x0, y0] + 0.5) * scale - 0.5, atol=1e-9)


def test_pinhole_render_draws_the_nearer_surface_where_the_camera_sees_it():
    from facepipe.core.render import PinholeCamera, pinhole_project, render

    def square(centre, half):  # two triangles facing the camera
        c = np.asarray(centre, dtype=np.float64)
        return c + np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]])

    # a small near square in front of a large far one: the near one hides the far one's middle
    V = np.concatenate([square([0, 0, 20], 1.0), square([0, 0, 40], 8.0)])
    F = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    colors = np.repeat([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], 4, axis=0)
    cam = PinholeCamera(np.array([[200.0, 0, 99.5], [0, 200.0, 79.5], [0, 0, 1]]), np.zeros(0), 200, 160)
    img = render(V, F, cam, colors=colors, ambient=1.0, background=(0.0, 0.0, 0.0))
    red, blue = img[..., 0] > 0.5, img[..., 2] > 0.5
    corners = pinhole_project(cam.matrix, cam.distortion, V[:4])
    rows, cols = np.nonzero(red)
    # the near square covers the pixels inside its projected corners (±1 px at the edges)
    assert cols.min() >= corners[:, 0].min() - 1 and cols.max() <= corners[:, 0].max() + 1
    assert rows.min() >= corners[:, 1].min() - 1 and rows.max() <= corners[:, 1].max() + 1
    assert red.sum() == pytest.approx(np.ptp(corners[:, 0]) * np.ptp(corners[:, 1]), rel=0.1)
    assert red[80, 100] and blue[80, 60] and not blue[80, 100]
    # a triangle reaching behind the camera is left out rather than smeared over the image
    behind = np.concatenate([V, [[0, 0, -5.0]]])
    img2 = render(behind, np.concatenate([F, [[0, 1, 8]]]), cam, colors=np.concatenate([colors, [[0, 1, 0]]]),
                  ambient=1.0, background=(0.0, 0.0, 0.0))
    assert np.allclose(img2, img)


def test_preview_of_a_2d_replay_through_its_camera(filmed, tmp_path, capsys):
    from facepipe.cli.preview import preview_replay

    f = filmed
    assert _replay(f, tmp_path / "keep") == 0
    assert _replay(f, tmp_path / "remove", "--head-motion", "remove") == 0
    video = np.load(tmp_path / "keep" / "video.npz")
    assert Path(str(video["camera_path"])).is_absolute() and np.allclose(video["camera_matrix"], MATRIX)
    assert video["tracked"].shape == f.px.shape and video["landmark_vertices"].tolist() == f.vertices.tolist()
    camera = json.loads((tmp_path / "keep" / "replay.json").read_text())["video"]["camera"]
    assert Path(camera["path"]).is_absolute() and np.allclose(camera["matrix"], MATRIX)
    shown = [5, 21, 50]  # frame 21 is one the tracker lost
    summaries = {}
    for mode in ("keep", "remove"):
        summaries[mode] = preview_replay(tmp_path / mode, None, tmp_path / f"{mode}.png", frame_numbers=shown)
        assert (tmp_path / f"{mode}.png").stat().st_size > 10_000
    s = summaries["keep"]
    assert s["view"] == "camera" and s["frames"] == shown
    assert s["reprojection_px"][1] is None and 0 < s["reprojection_px"][0] < 1.5 and s["reprojection_px"][2] < 1.5
    # the same face in the same place whether the replay kept the head motion or not
    assert np.allclose(summaries["remove"]["reprojection_px"][::2], s["reprojection_px"][::2], atol=1e-3)
    x0, y0, w, h = s["window"]
    seen = np.isfinite(f.px[[4, 49]]).all(-1)
    px = f.px[[4, 49]][seen]
    assert (px[:, 0] > x0).all() and (px[:, 0] < x0 + w).all() and (px[:, 1] > y0).all() and (px[:, 1] < y0 + h).all()
    # the command: the camera view by default, --truth only in head space
    assert run_cli("preview", tmp_path / "keep", "-o", tmp_path / "cli.png", "--strip", 2, "--quiet") == 0
    assert run_cli("preview", tmp_path / "keep", "-o", tmp_path / "t.png", "--view", "camera", "--truth",
                   f.root / "rig" / "take_truth.npz") == 2
    assert "--view head" in capsys.readouterr().err and not (tmp_path / "t.png").exists()


def test_camera_view_of_a_3d_replay_is_refused(rig, tmp_path, capsys):
    assert run_cli("preview", rig.replays["wpsd"], "-o", tmp_path / "c.png", "--view", "camera", "--quiet") == 2
    assert "not of a 2D take" in capsys.readouterr().err and not (tmp_path / "c.png").exists()


def test_config_landmarks_baked_into_the_model(filmed, tmp_path, capsys):
    from facepipe.io.config import load_config
    from facepipe.io.model_file import load_model

    f = filmed
    rig_dir = f.root / "rig"
    config = (rig_dir / "sample.toml").read_text()
    bad = rig_dir / "bad_video.toml"
    bad.write_text(config + "\n[video]\nlandmarks = 3\n")
    with pytest.raises(InputError, match=r"\[video\] landmarks = 3 is an integer, expected a string"):
        load_config(bad)
    missing = rig_dir / "missing_video.toml"
    missing.write_text(config + "\n[video]\nlandmarks = \"nowhere.csv\"\n")
    assert run_cli("bake", missing, "-o", tmp_path / "m.npz", "--quiet") == 2
    assert "[video] landmarks" in capsys.readouterr().err and not (tmp_path / "m.npz").exists()
    good = rig_dir / "video.toml"
    good.write_text(config + "\n[video]\nlandmarks = \"../landmarks.csv\"\n")
    assert load_config(good).landmarks == rig_dir / "../landmarks.csv"
    assert run_cli("bake", good, "-o", tmp_path / "lm.npz", "--quiet") == 0
    model = load_model(tmp_path / "lm.npz")
    assert model.landmark_vertices.tolist() == f.vertices.tolist()
    assert model.meta["landmark_names"] == [str(i) for i in range(len(f.vertices))]
    # replay without --landmarks: the model's map
    common = ["-m", tmp_path / "lm.npz", "--camera", f.camera, "--backend", "numpy", "--quiet"]
    assert run_cli("replay", f.take, "-o", tmp_path / "own", *common) == 0
    assert json.loads((tmp_path / "own" / "replay.json").read_text())["video"]["landmarks"] == len(f.vertices)
    # --landmarks overrides it: here a map of 20 of the points
    sub = tmp_path / "sub.csv"
    sub.write_text("name,vertex\n" + "".join(f"{i},{v}\n" for i, v in enumerate(f.vertices[:20])))
    assert run_cli("replay", f.take, "-o", tmp_path / "sub", *common, "--landmarks", sub) == 0
    report = json.loads((tmp_path / "sub" / "replay.json").read_text())["video"]
    assert report["landmarks"] == 20 and report["landmark_map"] == str(sub)
    # a model baked without a map still asks for one
    assert run_cli("replay", f.take, "-o", tmp_path / "none", "-m", f.root / "model.npz", "--camera", f.camera,
                   "--quiet") == 2
    assert "[video] landmarks" in capsys.readouterr().err


# ----------------------------------------------------------------------------- the ICT kit


@pytest.mark.ict
@pytest.mark.slow
def test_ict_video_take(tmp_path, ict_rig_fit):
    from facepipe.io.model_file import model_arrays, save_model

    kit = ict_or_skip()
    video = kit / "video"
    model = tmp_path / "ict.npz"
    save_model(model, *model_arrays(ict_rig_fit[1], ict_rig_fit[0]))  # as `facepipe bake configs/ict.toml`
    truth = np.load(video / "video_truth.npz")
    R, t = truth["rotation"].astype(np.float64), truth["translation"].astype(np.float64)
    head = np.einsum("fji,fvj->fvi", R, truth["positions"].astype(np.float64) - t[:, None])
    face = slice(0, 9409)

    def error(out):
        pos = np.load(out / "positions.npy")
        return float(np.sqrt(((pos - head)[:, face] ** 2).sum(-1).mean(-1)).mean())

    common = ["-m", model, "--backend", "numpy", "--head-motion", "remove", "--quiet"]
    assert run_cli("replay", video / "video_mocap.csv", "-o", tmp_path / "m3d", *common) == 0
    lift = ["--camera", video / "video_camera.yml", "--landmarks", video / "landmarks68.csv"]
    # the model carries configs/ict.toml's [video] landmarks: no --landmarks needed
    assert run_cli("replay", video / "video_openface.csv", "-o", tmp_path / "v2d", *lift[:2], *common) == 0
    assert run_cli("replay", video / "video_openface.csv", "-o", tmp_path / "heur", *lift, "--lift", "heuristic",
                   *common) == 0
    e3d, e2d, eh = error(tmp_path / "m3d"), error(tmp_path / "v2d"), error(tmp_path / "heur")
    assert e2d <= 1.3 * e3d
    assert e2d <= 0.8 * eh
    report = json.loads((tmp_path / "v2d" / "replay.json").read_text())["video"]
    assert report["fit_reprojection_px"]["mean"] <= 1.0
