"""Speed and accuracy of lifting a 2D landmark take (the ICT kit's video_openface.csv).

Prints the lift's frames per second (the default lift and Fidaleo et al.'s heuristic, lifting
only: reading, the rig set-up and the replay excluded; the best of --repeat runs), and the
face-area (vertices 0:9409) RMS error with head motion removed of:

    the 3D-marker replay of the same performance (video_mocap.csv),
    the 2D replay (default lift) and the heuristic (--lift heuristic),
    and the mean reprojection errors (the fit, and the replayed face's landmarks).

Usage:  python bench/video_lift.py [--model /tmp/ict_model.npz] [--repeat 5] [--json out.json]
The model is baked from configs/ict.toml when the file does not exist. :func:`lift_speed` is the
lifting speed figure of ``make bench`` (bench/results.json, ``video_lift``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
KIT = ROOT.parent / "shared" / "data" / "ict"
VIDEO = KIT / "video"
FACE = slice(0, 9409)


def main() -> None:
    from bench.noisy_take import load_or_bake
    from facepipe.io.camera_file import read_camera
    from facepipe.io.landmark_map import read_landmark_map
    from facepipe.mocap import read_take
    from facepipe.mocap.landmarks2d import read_landmark_take
    from facepipe.mocap.prepare import prepare_take
    from facepipe.pipeline.replay import NumpyEvaluator
    from facepipe.pipeline.video_lift import LiftOptions, lift_rig, lift_take, reprojection_of_output

    ap = argparse.ArgumentParser()
    ap.add_argument("--model", default="/tmp/ict_model.npz")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    if not (VIDEO / "video_openface.csv").is_file():
        sys.exit(f"the ICT kit's video take is not at {VIDEO}")
    model = load_or_bake(Path(args.model))
    camera = read_camera(VIDEO / "video_camera.yml")
    lmap = read_landmark_map(VIDEO / "landmarks68.csv", model.n_vertices)
    take = read_landmark_take(VIDEO / "video_openface.csv", lmap.names)
    t0 = time.perf_counter()
    rig = lift_rig(model, lmap.vertices)
    setup = time.perf_counter() - t0
    truth = np.load(VIDEO / "video_truth.npz")
    R, t = truth["rotation"].astype(np.float64), truth["translation"].astype(np.float64)
    head = np.einsum("fji,fvj->fvi", R, truth["positions"].astype(np.float64) - t[:, None])
    evaluator = NumpyEvaluator(model)

    def face_rms(out):
        return float(np.sqrt(((out - head)[:, FACE] ** 2).sum(-1).mean(-1)).mean())

    result = {"frames": take.n_frames, "landmarks": len(lmap.names), "examples": int(rig.basis.shape[0]),
              "rig_setup_seconds": setup}
    for method in ("model", "heuristic"):
        times = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            lifted = lift_take(take, camera, rig, LiftOptions(method=method))
            times.append(time.perf_counter() - t0)
        out = evaluator.evaluate(lifted.head)
        reproj = reprojection_of_output(camera, take, out[:, lmap.vertices], lifted.R, lifted.t, "remove",
                                        lifted.used)
        result[method] = {"frames_per_second": take.n_frames / min(times), "face_rms": face_rms(out),
                          "fit_reprojection_px": lifted.report["fit_reprojection_px"]["mean"],
                          "replayed_reprojection_px": reproj["mean"]}
    markers = read_take(VIDEO / "video_mocap.csv", model.marker_names, units=model.meta["units"], absent="missing",
                        allow_empty_frames=True)
    h3, _, _, _ = prepare_take(markers, model)
    result["markers_3d"] = {"face_rms": face_rms(evaluator.evaluate(h3))}
    m, h, m3 = result["model"], result["heuristic"], result["markers_3d"]
    result["ratio_2d_to_3d"] = m["face_rms"] / m3["face_rms"]
    result["improvement_over_heuristic"] = 1.0 - m["face_rms"] / h["face_rms"]
    print(f"{take.n_frames} frames, {len(lmap.names)} landmarks, {rig.basis.shape[0]} examples "
          f"(rig set-up {setup:.2f} s, once per replay)")
    print(f"{'':18s} {'frames/s':>9s} {'face RMS':>9s} {'fit px':>7s} {'replayed px':>11s}")
    for name in ("model", "heuristic"):
        r = result[name]
        print(f"lift {name:13s} {r['frames_per_second']:9.0f} {r['face_rms']:9.4f} {r['fit_reprojection_px']:7.3f} "
              f"{r['replayed_reprojection_px']:11.3f}")
    print(f"3D markers         {'':9s} {m3['face_rms']:9.4f}")
    print(f"2D / 3D: {result['ratio_2d_to_3d']:.3f} (asked <= 1.3); better than the heuristic by "
          f"{100 * result['improvement_over_heuristic']:.0f} % (asked >= 20 %)")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))


def lift_speed(work_dir: Path, repeats: int = 3, use_kit: bool = True, log=print) -> dict:
    """Frames per second of the default lift alone (reading, the rig set-up and the replay
    excluded; the median of ``repeats`` runs): on the ICT kit's video take (68 landmarks, 26
    examples) when ../shared is there, else on a take of the sample rig filmed by a made-up camera
    (68 landmarks, 26 examples as well), or with ``use_kit`` False. For ``make bench``
    (:mod:`bench.paper_scale`)."""
    from bench.timing import median_time
    from facepipe.pipeline.video_lift import LiftOptions, lift_rig, lift_take

    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    if use_kit and (VIDEO / "video_openface.csv").is_file():
        from bench.noisy_take import load_or_bake
        from facepipe.io.camera_file import read_camera
        from facepipe.io.landmark_map import read_landmark_map
        from facepipe.mocap.landmarks2d import read_landmark_take

        source = "ICT kit video_openface.csv"
        model = load_or_bake(work_dir / "ict_model.npz")
        camera = read_camera(VIDEO / "video_camera.yml")
        lmap = read_landmark_map(VIDEO / "landmarks68.csv", model.n_vertices)
        vertices = lmap.vertices
        take = read_landmark_take(VIDEO / "video_openface.csv", lmap.names)
    else:
        source = "sample rig filmed by a synthetic camera"
        model, camera, vertices, take = _synthetic_take(work_dir)
    t0 = time.perf_counter()
    rig = lift_rig(model, vertices)
    setup = time.perf_counter() - t0
    lift_take(take, camera, rig)  # warm-up (imports, first allocations)
    seconds = median_time(lambda: lift_take(take, camera, rig, LiftOptions()), repeats)
    out = {"source": source, "frames": take.n_frames, "landmarks": int(len(vertices)),
           "examples": int(rig.basis.shape[0]), "frames_per_second": take.n_frames / seconds,
           "rig_setup_seconds": setup, "repeats": repeats}
    log(f"video lift: {out['frames_per_second']:.0f} frames/s for {out['landmarks']} landmarks and "
        f"{out['examples']} examples ({source}; rig set-up {setup:.2f} s once per take)")
    return out


def _more_examples(rig_dir: Path, n_examples: int) -> None:
    """Up to ``n_examples`` example poses in the sample rig: the sample's own, then asymmetric ones
    (the left half of one with the right half of another, blended across the middle, as the ICT
    kit's left/right expressions) written beside them."""
    from facepipe.io.mesh_read import load_mesh
    from facepipe.io.mesh_write import save_obj

    mesh = load_mesh(rig_dir / "neutral.obj")
    rest = mesh.vertices
    own = sorted((rig_dir / "expressions").glob("*.obj"))
    poses = [load_mesh(p).vertices - rest for p in own]
    x = rest[:, 0] - np.median(rest[:, 0])
    left = 0.5 * (1 + np.tanh(x / (0.1 * np.ptp(rest[:, 0]))))[:, None]
    pairs = [(a, b) for a in range(len(poses)) for b in range(len(poses)) if a != b]
    for k, (a, b) in enumerate(pairs[:max(0, n_examples - len(poses))]):
        save_obj(rig_dir / "expressions" / f"mix_{k:02d}.obj", mesh, rest + left * poses[a] + (1 - left) * poses[b])


def _synthetic_take(work_dir: Path, n_landmarks: int = 68, n_examples: int = 26, n_frames: int = 150):
    """A small sample rig with ``n_examples`` examples, baked, and a performance of it (random mixes
    of the examples, head motion, 0.5 px noise, lens distortion) tracked at ``n_landmarks`` vertices
    spread over the front of the face: (model, camera, landmark vertices, LandmarkTake)."""
    from facepipe.core.camera import Camera, project_distorted
    from facepipe.io.model_file import load_model, model_arrays, save_model
    from facepipe.mocap.landmarks2d import LandmarkTake
    from facepipe.pipeline.fit import fit_rig
    from facepipe.pipeline.replay import NumpyEvaluator
    from facepipe.pipeline.rig import load_rig
    from facepipe.sample_rig import write_sample_rig
    from scipy.spatial.transform import Rotation

    path = work_dir / "sample_model.npz"
    if not path.is_file():
        write_sample_rig(work_dir / "rig", n_vertices=3000, n_examples=min(n_examples, 12), n_frames=8)
        _more_examples(work_dir / "rig", n_examples)
        rig = load_rig(work_dir / "rig" / "sample.toml")
        save_model(path, *model_arrays(fit_rig(rig), rig))
    model = load_model(path)
    rest = model.rest.astype(np.float64)
    front = np.flatnonzero(rest[:, 2] > np.percentile(rest[:, 2], 40))
    chosen = [front[np.argmax(rest[front, 2])]]
    d = np.linalg.norm(rest[front] - rest[chosen[0]], axis=1)
    for _ in range(n_landmarks - 1):  # farthest-point spread over the front
        chosen.append(front[np.argmax(d)])
        d = np.minimum(d, np.linalg.norm(rest[front] - rest[chosen[-1]], axis=1))
    vertices = np.array(chosen)
    rng = np.random.default_rng(0)
    eh = model.example_handles.astype(np.float64)
    tt = np.arange(n_frames) / 30.0
    weights = np.clip(0.5 * np.sin(rng.uniform(0.5, 2.0, len(eh) - 1) * 2 * np.pi * tt[:, None]
                                   + rng.uniform(0, 2 * np.pi, len(eh) - 1)), 0.0, 0.8)
    handles = eh[0] + np.einsum("tk,khc->thc", weights, eh[1:] - eh[0])
    faces = NumpyEvaluator(model).evaluate(handles)[:, vertices]
    size = float(np.ptp(rest, axis=0).max())
    camera = Camera(np.array([[1400.0, 0, 639.5], [0, 1400.0, 359.5], [0, 0, 1]]),
                    np.array([-0.08, 0.05, 0.0005, -0.0003, 0.0]), 1280, 720, "synthetic")
    # the rig (+y up, +z toward the viewer) seen from the front at a distance where it fills the image's height
    R = Rotation.from_rotvec(np.stack([0.1 * np.sin(2 * tt), 0.2 * np.sin(1.3 * tt), 0.03 * tt], 1)).as_matrix() \
        @ np.diag([1.0, -1.0, -1.0])
    t = np.stack([0.05 * size * np.sin(tt), np.zeros_like(tt), np.full_like(tt, 2.2 * size)], 1) \
        - np.einsum("tij,j->ti", R, rest[vertices].mean(axis=0))
    cam = np.einsum("tij,tlj->tli", R, faces) + t[:, None]
    px = project_distorted(camera, cam) + rng.normal(scale=0.5, size=cam.shape[:2] + (2,))
    take = LandmarkTake(np.arange(1, n_frames + 1), tt, px, [str(i) for i in range(n_landmarks)],
                        np.zeros(n_frames, dtype=bool), "synthetic", "uv-csv")
    return model, camera, vertices, take


if __name__ == "__main__":
    main()
