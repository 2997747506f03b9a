"""Benchmarks: bake and replay speed on a generated sample rig, against a per-frame solve.

Figures are medians of repeated runs, measured in one process so that ratios compare like
with like. Tests never assert times; `make bench` writes the figures to JSON.
"""

from __future__ import annotations

import platform
import resource
import statistics
import time
from pathlib import Path

import numpy as np


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_bench(work_dir: Path, n_vertices: int = 20000, n_frames: int = 64, repeats: int = 3, chunk: int = 32,
              log=print) -> dict:
    """Generate a sample rig, bake it, and time replay stages and the per-frame solve baseline.

    Returns
    -------
    dict of figures (seconds, frames/s, MB), JSON-serialisable.
    """
    from .fit import fit_rig
    from .model import model_from_fit
    from .replay import NumpyEvaluator
    from .rig import load_rig
    from .sample import write_sample_rig
    from .shell import CholeskyFactor, constrained_split, shell_operator

    work_dir = Path(work_dir)
    t0 = time.perf_counter()
    write_sample_rig(work_dir / "rig", n_vertices=n_vertices, n_frames=n_frames)
    t_sample = time.perf_counter() - t0
    log(f"sample rig: {n_vertices} vertices requested ({t_sample:.1f} s)")

    rss0 = _peak_rss_mb()
    t0 = time.perf_counter()
    rig = load_rig(work_dir / "rig" / "sample.toml")
    fit = fit_rig(rig)
    t_bake = time.perf_counter() - t0
    model = model_from_fit(fit, rig)
    V = model.n_vertices
    log(f"bake (fit): {t_bake:.2f} s, V = {V}, H = {len(model.handle_vertices)}, F = {len(model.edges)}")

    truth = np.load(work_dir / "rig" / "take_truth.npz")["positions"]
    handles = truth[:, model.handle_vertices].astype(np.float64)
    T = handles.shape[0]

    ev = NumpyEvaluator(model)

    def replay_all():
        for s in range(0, T, chunk):
            ev.evaluate(handles[s:s + chunk])

    ev.stage_seconds = dict.fromkeys(ev.stage_seconds, 0.0)
    t_numpy = _median_time(replay_all, repeats)
    stages = {k: v / repeats / T * 1e3 for k, v in ev.stage_seconds.items()}
    log(f"numpy replay: {T / t_numpy:.1f} frames/s ({t_numpy / T * 1e3:.2f} ms/frame)")

    # baseline the paper replaced: factor once, back-substitute every frame
    rest = model.rest.astype(np.float64)
    H = model.handle_vertices.astype(np.int64)
    A = shell_operator(rest, model.triangles, rig.config.shell.k_stretch, rig.config.shell.k_bend,
                       model.meta["marker_spacing"]).tocsc()
    free, _ = constrained_split(V, H, model.anchors)
    A_ff = A[free][:, free]
    A_fh = A[free][:, H]
    factor = CholeskyFactor(A_ff)
    u = handles - rest[H]

    def solve_all():
        out = np.empty((V, 3))
        for f in range(T):
            out[free] = -factor.solve(np.asarray(A_fh @ u[f]))

    t_solve = _median_time(solve_all, repeats)
    log(f"per-frame sparse solve (large scale only): {T / t_solve:.1f} frames/s")
    large_ms = stages["large_scale"]
    return {
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine()},
        "config": {"vertices": V, "handles": int(len(H)), "feature_edges": int(len(model.edges)),
                   "basis_poses": int(model.basis_features.shape[0]), "frames": T, "repeats": repeats,
                   "chunk": chunk},
        "bake": {"seconds": t_bake, "peak_rss_mb": max(_peak_rss_mb(), rss0)},
        "replay_numpy": {"frames_per_second": T / t_numpy, "ms_per_frame": t_numpy / T * 1e3,
                         "stage_ms_per_frame": stages},
        "baseline_sparse_solve": {"frames_per_second": T / t_solve, "ms_per_frame": t_solve / T * 1e3},
        "ratio_large_scale_vs_solve": (t_solve / T * 1e3) / large_ms if large_ms > 0 else None,
        "ratio_numpy_end_to_end_vs_solve": t_solve / t_numpy,
    }
