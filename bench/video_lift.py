"""Speed and accuracy of lifting a 2D landmark take (the ICT kit's video_openface.csv).

Prints the lift's frames per second (the default lift and Fidaleo et al.'s heuristic, lifting
only: reading, the rig set-up and the replay excluded; the best of --repeat runs), and the
face-area (vertices 0:9409) RMS error with head motion removed of:

    the 3D-marker replay of the same performance (video_mocap.csv),
    the 2D replay (default lift) and the heuristic (--lift heuristic),
    and the mean reprojection errors (the fit, and the replayed face's landmarks).

Usage:  python bench/video_lift.py [--model /tmp/ict_model.npz] [--repeat 5] [--json out.json]
The model is baked from configs/ict.toml when the file does not exist.
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


if __name__ == "__main__":
    main()
