"""Replay speed of the local-strain detail model at the paper's scale (~530k vertices, 1M triangles).

Times replay only: the model's arrays are synthetic (the sample face's mesh at that resolution,
a random large-scale basis B, random training strains and weights), which costs what a fitted
model costs, without the minutes of a bake at that size. Compares, on the same mesh and engine,
the large scale alone (method none) with the local-strain model for N training poses.

Usage: python -m bench.local_strain_speed [--vertices 530000] [--poses 27] [--frames 64] [--json PATH]
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

from facepipe import opencl
from facepipe.core.tangent_frames import frame_neighbors
from facepipe.io.model_file import FORMAT_VERSION, MODEL_KIND, Model
from facepipe.pipeline.replay import NumpyEvaluator
from facepipe.sample_rig import _face_mesh


def synthetic_model(n_vertices: int, n_poses: int, n_handles: int, method: str, seed: int = 0) -> Model:
    vertices, faces, *_ = _face_mesh(n_vertices)
    V = len(vertices)
    rng = np.random.default_rng(seed)
    handles = np.sort(rng.choice(V, n_handles, replace=False))
    B = rng.uniform(0, 1, size=(V, n_handles)).astype(np.float32)
    B /= B.sum(axis=1, keepdims=True)
    edges = np.stack([np.arange(n_handles - 1), np.arange(1, n_handles)], 1)
    arrays = dict(rest=vertices, triangles=faces, polygon_offsets=np.arange(0, 3 * len(faces) + 1, 3),
                  polygon_vertices=faces.ravel(), handle_vertices=handles, stable=np.zeros(n_handles, bool),
                  anchors=np.zeros(0, np.int32), B=B, edges=edges, rest_lengths=np.ones(len(edges)),
                  frame_neighbors=frame_neighbors(faces, V), basis_features=np.zeros((1, len(edges))),
                  rbf_weights=np.zeros((V, 1, 3)), rbf_const=np.zeros((V, 3)),
                  edge_index=np.zeros((V, 1), np.int32), edge_weight=np.zeros((V, 1)),
                  example_handles=vertices[handles][None])
    meta = {"kind": MODEL_KIND, "format_version": FORMAT_VERSION, "method": method,
            "marker_names": [f"M{i}" for i in range(n_handles)], "novelty_tau": 0.0}
    if method == "local_strain":
        arrays.update(strain_samples=rng.normal(scale=0.05, size=(V, n_poses, 3)).astype(np.float32),
                      strain_weights=rng.normal(scale=0.01, size=(V, n_poses, 3)).astype(np.float32))
        meta["strain_width"] = 0.08
    return Model.from_arrays(arrays, meta, "(synthetic)")


def fps(evaluator, head: np.ndarray, repeats: int = 2) -> float:
    evaluator.evaluate(head[: min(len(head), 8)])  # (compiles, warms the caches)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        evaluator.evaluate(head)
        best = min(best, time.perf_counter() - t0)
    return len(head) / best


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--vertices", type=int, default=530000)
    ap.add_argument("--poses", type=int, default=27)
    ap.add_argument("--handles", type=int, default=89)
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--numpy-frames", type=int, default=8)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    result = {}
    for method in ("none", "local_strain"):
        model = synthetic_model(args.vertices, args.poses, args.handles, method)
        rng = np.random.default_rng(1)
        head = model.rest[model.handle_vertices][None] + rng.normal(scale=0.1, size=(args.frames, args.handles, 3))
        row = {"vertices": model.n_vertices, "triangles": int(len(model.triangles)),
               "poses": args.poses if method == "local_strain" else 0,
               "numpy_frames_per_second": fps(NumpyEvaluator(model), head[: args.numpy_frames], repeats=1)}
        if opencl.opencl_available():
            ev = opencl.OpenCLEvaluator(model)
            row["opencl_frames_per_second"] = fps(ev, head)
            row["opencl_device"] = ev.device
        result[method] = row
        print(method, row, flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
