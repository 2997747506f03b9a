"""Appearance of a monocular take on the ICT kit, geometry and appearance from the same camera:
the rendered footage of ``bench/appearance_ict.py`` (``--out``), its truth landmarks (the kit's
``video/landmarks68.csv`` vertices) projected through that camera with 0.5 px noise as a tracker
would give them (frames numbered from 1, times from 0), lifted and replayed with a model of the
kit (``-m``, baked from ``configs/ict.toml``), and the same footage classified with that replay's
geometry. Spearman of Q with the truth activation per region and Q's RMS error against the truth's
layer index, beside the truth geometry's, and the
lifted face's error in the camera's coordinates. Writes bench/appearance_ict_lifted.json (or --json).

    python bench/appearance_ict.py --out /tmp/ict_appearance          # the footage, once
    facepipe bake configs/ict.toml -o /tmp/ict_model.npz
    python bench/appearance_ict_lifted.py --out /tmp/ict_appearance -m /tmp/ict_model.npz
"""

from __future__ import annotations

import argparse
import json
import sys
import tomllib
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's facepipe, however it is run

from facepipe.cli.commands import main as facepipe_main
from facepipe.core.camera import project_distorted
from facepipe.io.camera_file import read_camera
from facepipe.mocap.landmarks2d import write_uv_csv

KIT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ict"


def facepipe(*args) -> None:
    try:
        facepipe_main([str(a) for a in args])
    except SystemExit as exc:
        if exc.code:
            raise RuntimeError(f"facepipe {' '.join(map(str, args[:2]))} exited {exc.code}") from None


def spearman(q: np.ndarray, act: np.ndarray) -> tuple[list, list]:
    """All frames', and the active frames', Spearman correlation per region."""
    active = act > 0
    return ([float(spearmanr(q[:, r], act[:, r]).statistic) for r in range(q.shape[1])],
            [float(spearmanr(q[active[:, r], r], act[active[:, r], r]).statistic) for r in range(q.shape[1])])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="/tmp/ict_appearance", help="footage rendered by bench/appearance_ict.py")
    ap.add_argument("-m", "--model", required=True, help="a model of the kit with the 68-landmark map (configs/ict.toml)")
    ap.add_argument("--noise", type=float, default=0.5, help="tracking noise, pixels")
    ap.add_argument("--json", default="bench/appearance_ict_lifted.json")
    args = ap.parse_args()
    out = Path(args.out)
    work = out / "lifted"
    work.mkdir(exist_ok=True)
    config = tomllib.loads((out / "appearance.toml").read_text())["appearance"]
    R, t = np.array(config["camera_rotation"]), np.array(config["camera_translation"])
    camera = read_camera(out / "camera.json")
    landmarks = np.loadtxt(KIT / "video" / "landmarks68.csv", delimiter=",", skiprows=1, dtype=np.int64, ndmin=2)
    names, vertices = [str(n) for n in landmarks[:, 0]], landmarks[:, 1]
    facepipe("-q", "appearance", "build", out / "appearance.toml", "-o", work / "appearance.npz")
    rng = np.random.default_rng(0)
    result = {"noise_px": args.noise, "landmarks": len(names)}
    for take in ("take", "take_turned"):
        with np.load(out / f"{take}.npz") as geometry:
            world, frames = geometry["positions"], geometry["frame"]
        in_camera = world @ R.T + t
        pixels = project_distorted(camera, in_camera[:, vertices]) + rng.normal(scale=args.noise,
                                                                                size=(len(world), len(vertices), 2))
        tracked = work / f"{take}_tracked.csv"
        write_uv_csv(tracked, frames + 1, frames / 30.0, pixels, names)
        replay = work / f"{take}_replay"
        facepipe("-q", "replay", tracked, "-m", args.model, "--camera", out / "camera.json", "--landmarks",
                 KIT / "video" / "landmarks68.csv", "-o", replay, "--force")
        act = np.loadtxt(out / f"{take}_truth.csv", delimiter=",", skiprows=1, ndmin=2)[:, 1:]
        row = {}
        for label, geometry in (("lifted", replay), ("truth_geometry", out / f"{take}.npz")):
            classified = work / f"{take}_{label}"
            facepipe("-q", "appearance", "classify", work / "appearance.npz", out / take / "frame_%04d.png",
                     "--geometry", geometry, "-o", classified)
            q = np.loadtxt(classified / "appearance.csv", delimiter=",", skiprows=1, ndmin=2)[:, 2:]
            row[label] = dict(zip(("spearman", "spearman_active_frames"), spearman(q, act)))
            layers = np.array(json.loads((work / "appearance.json").read_text())["layers"])
            row[label]["q_rms_error_layers"] = np.sqrt(((q - act * (layers - 1)) ** 2).mean(axis=0)).tolist()
            check = json.loads((classified / "appearance.json").read_text())["footage_check"]
            residual = np.array([np.nan if x is None else x for x in check["light_residual"]])
            row[label]["footage_check"] = {"ratio_median": check["ratio_median"],
                                           "ratio_max": float(np.nanmax(residual) / check["light_residual_examples"]),
                                           "frames_off_face": check["frames_off_face"], "frames": len(residual)}
        lifted = np.load(replay / "positions.npy")
        face = np.linalg.norm(lifted[:, :9409] - in_camera[:, :9409], axis=-1)
        row["lifted_face_rms_cm"] = float(np.sqrt((face ** 2).mean(axis=1)).mean())
        row["reprojection_px"] = json.loads((replay / "replay.json").read_text())["video"]["reprojection_px"]["mean"]
        result[take] = row
        for label in ("lifted", "truth_geometry"):
            check = row[label]["footage_check"]
            print(take, f"{label:15s}", "all", " ".join(f"{v:.2f}" for v in row[label]["spearman"]), "| active",
                  " ".join(f"{v:.2f}" for v in row[label]["spearman_active_frames"]), "| Q error",
                  " ".join(f"{v:.2f}" for v in row[label]["q_rms_error_layers"]),
                  f"| light residual {check['ratio_median']:.1f}x the examples' (largest {check['ratio_max']:.1f}x), "
                  f"{check['frames_off_face']} frames off the face")
        print(take, f"lifted face RMS {row['lifted_face_rms_cm']:.3f} cm (camera coordinates), landmark reprojection "
                    f"{row['reprojection_px']:.2f} px")
    Path(args.json).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
