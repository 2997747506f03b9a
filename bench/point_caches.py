"""Point caches replayed as takes (``replay CACHE --large-scale take``) on the ICT kit and the sample rig.

    python bench/point_caches.py [--work DIR] [--json bench/point_caches.json]

1. ICT ``train_mocap.csv`` replayed from markers (NumPy reference, ``--save-large-scale``); its large
   scale exported as MDD and USD and replayed with ``--large-scale take``: the largest distance from
   the marker replay's final positions (cm), and between the USD and MDD replays.
2. ICT ``train_truth.npz`` with each frame's displacement smoothed by 20 iterations of uniform
   Laplacian smoothing (half-way to the neighbours' mean), as a PC2: per-frame face-area RMS error
   of the replay against the truth, relative to the cache's own (largest rise).
   The same for ``face_a`` (its own truth, smoothed) through the kit's model transferred onto it.
3. The sample rig's smooth cache (``take_smooth.mdd``, the truth without its wrinkles): mean error
   of the replay relative to the cache's, and frames made worse (with the marker replay's error
   on them), over every vertex and over vertices 0:9409; the same cache through a local-strain
   model of the rig (``[psd] method = "local_strain"``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import scipy.sparse as sp

ROOT = Path(__file__).resolve().parents[1]
KIT = ROOT.parent / "shared" / "data" / "ict"
FACE = slice(0, 9409)  # the face area of the ICT mesh (the sample rig is all face: measured over every vertex)


def facepipe(*args) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    subprocess.run([sys.executable, "-m", "facepipe", *map(str, args)], check=True, env=env)


def face_rms(positions: np.ndarray, truth: np.ndarray, face=FACE) -> np.ndarray:
    return np.sqrt(((np.asarray(positions, np.float64) - truth)[:, face] ** 2).sum(-1).mean(-1))


def smoothed_displacements(rest: np.ndarray, faces: np.ndarray, positions: np.ndarray, iterations: int = 20):
    """Each frame's displacement from ``rest`` moved half-way to its mesh neighbours' mean, ``iterations`` times."""
    V = len(rest)
    i = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2], faces[:, 1], faces[:, 2], faces[:, 0]])
    j = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0], faces[:, 0], faces[:, 1], faces[:, 2]])
    A = sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(V, V))
    A.data[:] = 1.0
    mean = sp.diags(1.0 / np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1)) @ A
    d = np.asarray(positions, np.float64) - rest
    for _ in range(iterations):
        d = 0.5 * d + 0.5 * np.stack([mean @ x for x in d])
    return rest + d


def ict_cases(work: Path, out: dict) -> None:
    from facepipe.io.model_file import load_model
    from facepipe.io.point_caches import write_pc2

    model_path = work / "ict.npz"
    if not model_path.is_file():
        facepipe("bake", ROOT / "configs" / "ict.toml", "-o", model_path, "--no-tune", "-q")
    facepipe("replay", KIT / "train_mocap.csv", "-m", model_path, "-o", work / "markers", "--save-large-scale",
             "--backend", "numpy", "-q")
    facepipe("export", work / "markers", "--format", "mdd", "--layer", "large", "-o", work / "large.mdd", "--force", "-q")
    facepipe("export", work / "markers", "--format", "usd", "--layer", "large", "-o", work / "large.usdc", "--force",
             "-q")
    marker = np.load(work / "markers" / "positions.npy")
    runs = {}
    for name in ("mdd", "usdc"):
        facepipe("replay", work / f"large.{name}", "-m", model_path, "-o", work / f"take_{name}", "-q")
        runs[name] = np.load(work / f"take_{name}" / "positions.npy")
    out["ict_large_scale_cache"] = {
        "max_distance_mdd_cm": float(np.linalg.norm(runs["mdd"] - marker, axis=-1).max()),
        "max_distance_usd_cm": float(np.linalg.norm(runs["usdc"] - marker, axis=-1).max()),
        "usd_equals_mdd": bool(np.array_equal(runs["mdd"], runs["usdc"])),
        "bands": json.loads((work / "take_mdd" / "replay.json").read_text())["cache"]["bands"],
    }
    model = load_model(model_path)
    tt = np.load(KIT / "train_truth.npz")
    truth = tt["positions"].astype(np.float64)
    smooth = smoothed_displacements(model.rest.astype(np.float64), model.triangles.astype(np.int64), truth)
    write_pc2(work / "smooth.pc2", smooth.astype(np.float32), tt["time"], 30.0)
    facepipe("replay", work / "smooth.pc2", "-m", model_path, "-o", work / "take_smooth", "-q")
    cache_err = face_rms(smooth, truth)
    take_err = face_rms(np.load(work / "take_smooth" / "positions.npy"), truth)
    out["ict_smoothed_truth"] = {
        "cache_vs_truth_rms_cm": float(cache_err.mean()),
        "take_vs_truth_rms_cm": float(take_err.mean()),
        "largest_frame_rise_percent": float(100 * (take_err / cache_err - 1).max()),
        "bands": json.loads((work / "take_smooth" / "replay.json").read_text())["cache"]["bands"],
    }


def transfer_case(work: Path, out: dict, face: str = "face_a") -> None:
    """The kit's model transferred onto another identity, that face's own smoothed-truth cache replayed."""
    from facepipe.core.rbf_morph import farthest_point_subset
    from facepipe.io.mesh_read import load_mesh
    from facepipe.io.model_file import load_model
    from facepipe.io.point_caches import write_pc2

    source = load_model(work / "ict.npz")
    neutral = source.rest.astype(np.float64)
    points = farthest_point_subset(neutral, 40, seed_index=int(source.handle_vertices[0]))
    for name in ("source", face):  # same topology: the same vertex ids mark the same places
        (work / f"points_{name}.csv").write_text("name,vertex\n" + "".join(f"P{i:02d},{int(v)}\n"
                                                                           for i, v in enumerate(points)))
    target = KIT / "identities" / f"{face}.obj"
    model_path = work / f"{face}.npz"
    facepipe("transfer", work / "ict.npz", "--target", target, "--source-points", work / "points_source.csv",
             "--target-points", work / f"points_{face}.csv", "--target-markers", KIT / "markers.csv", "-o",
             model_path, "-q")
    X = load_mesh(target).vertices
    tt = np.load(KIT / "train_truth.npz")
    truth = X + (tt["positions"].astype(np.float64) - neutral)  # expressions do not depend on the identity
    smooth = smoothed_displacements(X, source.triangles.astype(np.int64), truth)
    write_pc2(work / f"{face}_smooth.pc2", smooth.astype(np.float32), tt["time"], 30.0)
    facepipe("replay", work / f"{face}_smooth.pc2", "-m", model_path, "-o", work / f"take_{face}", "-q")
    cache_err = face_rms(smooth, truth)
    take_err = face_rms(np.load(work / f"take_{face}" / "positions.npy"), truth)
    out[f"ict_smoothed_truth_{face}_transferred"] = {
        "cache_vs_truth_rms_cm": float(cache_err.mean()),
        "take_vs_truth_rms_cm": float(take_err.mean()),
        "largest_frame_rise_percent": float(100 * (take_err / cache_err - 1).max()),
        "bands": json.loads((work / f"take_{face}" / "replay.json").read_text())["cache"]["bands"],
    }


def sample_case(work: Path, out: dict) -> None:
    """The sample rig's smooth cache, over every vertex (the rig is all face) and, as before, over
    vertices 0:9409 (the ICT face area's range: on the sample's grid, its lower rows). Frames
    made worse are listed with the cache's, the take's and the marker replay's error there."""
    from facepipe.io.point_caches import read_mdd

    rig = work / "sample"
    facepipe("sample", rig, "-q")
    facepipe("bake", rig / "sample.toml", "-o", work / "sample.npz", "--no-tune", "-q")
    facepipe("replay", rig / "take_smooth.mdd", "-m", work / "sample.npz", "-o", work / "sample_take", "-q",
             "--force")
    facepipe("replay", rig / "take.csv", "-m", work / "sample.npz", "-o", work / "sample_markers", "-q", "--force")
    truth = np.load(rig / "take_truth.npz")["positions"].astype(np.float64)
    cache = read_mdd(rig / "take_smooth.mdd")[1]
    take = np.load(work / "sample_take" / "positions.npy")
    markers = np.load(work / "sample_markers" / "positions.npy")
    result = {}
    for name, region in (("all_vertices", slice(None)), ("vertices_0_9409", FACE)):
        cache_err, take_err, marker_err = (face_rms(x, truth, region) for x in (cache, take, markers))
        worse = np.flatnonzero(take_err > cache_err)
        result[name] = {
            "cache_vs_truth_rms": float(cache_err.mean()),
            "take_vs_truth_rms": float(take_err.mean()),
            "marker_replay_vs_truth_rms": float(marker_err.mean()),
            "ratio": float(take_err.mean() / cache_err.mean()),
            "frames_worse": int(worse.size),
            "frames": int(len(cache_err)),
            "worse_frames": [{"frame": int(f), "cache": float(cache_err[f]), "take": float(take_err[f]),
                              "marker_replay": float(marker_err[f])} for f in worse],
        }
    result["bands"] = json.loads((work / "sample_take" / "replay.json").read_text())["cache"]["bands"]
    out["sample_smooth_cache"] = result
    # the same cache through a local-strain model of the same rig: its details at the local strain
    # of the cache's own surface, its added bands refitted from its training details
    config = rig / "sample_local_strain.toml"
    config.write_text((rig / "sample.toml").read_text().replace('method = "wpsd"', 'method = "local_strain"', 1))
    facepipe("bake", config, "-o", work / "sample_ls.npz", "--no-tune", "-q")
    facepipe("replay", rig / "take_smooth.mdd", "-m", work / "sample_ls.npz", "-o", work / "sample_ls_take", "-q",
             "--force")
    cache_err = face_rms(cache, truth, slice(None))
    take_err = face_rms(np.load(work / "sample_ls_take" / "positions.npy"), truth, slice(None))
    out["sample_smooth_cache_local_strain"] = {
        "cache_vs_truth_rms": float(cache_err.mean()), "take_vs_truth_rms": float(take_err.mean()),
        "ratio": float(take_err.mean() / cache_err.mean()), "frames_worse": int((take_err > cache_err).sum()),
        "largest_rise": float((take_err - cache_err).max()),
        "bands": json.loads((work / "sample_ls_take" / "replay.json").read_text())["cache"]["bands"],
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", default=str(Path(tempfile.gettempdir()) / "facepipe_point_caches"))
    ap.add_argument("--json", default=str(ROOT / "bench" / "point_caches.json"))
    args = ap.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    sys.path.insert(0, str(ROOT))
    out: dict = {}
    sample_case(work, out)
    if (KIT / "neutral.obj").is_file():
        ict_cases(work, out)
        transfer_case(work, out)
    else:
        print(f"the ICT kit is not at {KIT}: its cases are skipped", file=sys.stderr)
    Path(args.json).write_text(json.dumps(out, indent=2))
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
