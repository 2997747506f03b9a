"""Per-frame evaluation of a model: the NumPy reference path and the chunked replay driver.

Per frame: handle positions (head space) → u_H → large-scale u = B u_H → local frames of
the large-scale mesh → strain features f → details d(f) → final = large + R d.
"""

from __future__ import annotations

import json
import os
from contextlib import nullcontext
import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from facepipe.io.atomic import atomic_path
from facepipe.core.edits import HandleEdit, apply_edits
from facepipe.core.tangent_frames import local_frames, to_world, vertex_face_matrix
from facepipe.io.model_file import Model
from facepipe.io.npy_stream import NpyWriter
from facepipe.core.strain import strain_features
from facepipe.core.local_strain import StrainOperator, vertex_strain
import queue
import threading
from concurrent.futures import ThreadPoolExecutor


class NumpyEvaluator:
    """Reference evaluation of a model on frames of handle positions (float64 arithmetic)."""

    backend = "numpy"
    device = "cpu (numpy)"
    on_host_cores = True  # (see the OpenCL evaluator)

    def __init__(self, model: Model):
        self.model = model
        self.rest = model.rest.astype(np.float64)
        self.handles = model.handle_vertices.astype(np.int64)
        self.rest_handles = self.rest[self.handles]
        self.faces = model.triangles.astype(np.int64)
        self.neighbors = model.frame_neighbors.astype(np.int64)
        self.edges = model.edges.astype(np.int64)
        self.rest_lengths = model.rest_lengths.astype(np.float64)
        self.incidence = vertex_face_matrix(self.faces, len(self.rest))
        self.details = model.detail_model(np.float64)
        # method local_strain: details over the large-scale surface's own local strain
        self.strain_details = model.strain_detail_model(np.float64)
        self.strain_operator = None if self.strain_details is None else \
            StrainOperator.of(self.rest, self.faces, self.neighbors)
        self.stage_seconds = {"large_scale": 0.0, "frames": 0.0, "fine_scale": 0.0}

    @cached_property
    def B(self) -> np.ndarray:
        """The large-scale basis in float64, made at the first evaluation (a mesh cache's details
        never need it)."""
        return self.model.B.astype(np.float64)

    @property
    def novelty_fits_at_cap(self) -> int | None:
        """Novelty-gate fits stopped by their iteration cap so far (None without a gate)."""
        gate = None if self.details is None else self.details.gate
        return None if gate is None else gate.unconverged_fits

    def evaluate(self, handle_positions: np.ndarray, with_large: bool = False):
        """Final positions (C, V, 3) for head-space handle positions (C, H, 3).

        With ``with_large`` also returns the large-scale positions.
        """
        t0 = time.perf_counter()
        u = handle_positions - self.rest_handles
        large = np.einsum("vh,chx->cvx", self.B, u, optimize=True) + self.rest
        self.stage_seconds["large_scale"] += time.perf_counter() - t0
        final = large
        if self.details.method != "none":
            final = large + self.world_details(large, handle_positions)
        return (final, large) if with_large else final

    def world_details(self, surface: np.ndarray, handle_positions: np.ndarray) -> np.ndarray:
        """The details (C, V, 3) as vectors in the space of a large-scale ``surface`` (C, V, 3), in
        its local frames: at the surface's own local strain for a local-strain model, else at the
        feature strain of the head-space handles (C, H, 3)."""
        t0 = time.perf_counter()
        frames = local_frames(surface, self.faces, self.neighbors, self.incidence)
        t1 = time.perf_counter()
        if self.strain_details is not None:
            local = self.strain_details.evaluate(vertex_strain(surface, self.strain_operator))
        else:
            local = self.details.evaluate(strain_features(handle_positions, self.edges, self.rest_lengths),
                                          handle_positions - self.rest_handles)
        d = to_world(frames, local)
        self.stage_seconds["frames"] += t1 - t0
        self.stage_seconds["fine_scale"] += time.perf_counter() - t1
        return d


def prefetched(items):
    """The items of an iterable, each next one computed on a thread while the caller works on the
    current one (an error is raised where that item would have come)."""

    box: queue.Queue = queue.Queue(maxsize=1)
    done = object()
    stop = threading.Event()

    def produce():
        try:
            for item in items:
                box.put((item, None))
                if stop.is_set():
                    return
            box.put((done, None))
        except BaseException as exc:  # noqa: BLE001 - raised in the caller's thread
            box.put((None, exc))

    worker = threading.Thread(target=produce, daemon=True)
    worker.start()
    try:
        while True:
            item, error = box.get()
            if error is not None:
                raise error
            if item is done:
                return
            yield item
    finally:
        stop.set()
        while worker.is_alive():  # let a producer blocked on a full box finish
            try:
                box.get(timeout=0.1)
            except queue.Empty:
                pass


def stream_chunks(evaluator, head: np.ndarray, sink, R: np.ndarray | None = None, t: np.ndarray | None = None,
                  chunk: int = 32, with_large: bool = False, placement=None) -> None:
    """Evaluate a take chunk by chunk and hand each chunk to ``sink`` in frame order, pipelined.

    An evaluator with a ``stream`` method (the OpenCL one) runs its own pipeline, head motion
    included, on the device. Any other (NumpyEvaluator) is driven here: chunk k + 1 is evaluated
    while a worker thread sinks chunk k, so writing overlaps computing.

    Parameters
    ----------
    head : (T, H, 3) head-space handle positions.
    sink : callable(start, final (n, V, 3), large (n, V, 3) or None, normals None).
    R, t : optional (T, 3, 3), (T, 3) head motion applied to the outputs (world = R p + t).
    chunk : frames per evaluate() call (the OpenCL evaluator uses the chunk it was built with).
    placement : optional callable(start, n, index) → (memory, offset) or None, where an
        evaluator whose ``takes_placement`` is true may produce the final positions in place
        (see :meth:`facepipe.opencl.engine.OpenCLEvaluator.stream`); others ignore it.
    """
    if hasattr(evaluator, "stream"):
        if placement is not None and getattr(evaluator, "takes_placement", False):
            evaluator.stream(head, sink, R, t, with_large=with_large, placement=placement)
        else:
            evaluator.stream(head, sink, R, t, with_large=with_large)
        return

    T = head.shape[0]
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="facepipe-sink") as pool:
        pending = None
        for s in range(0, T, chunk):
            e = min(T, s + chunk)
            final, large = evaluator.evaluate(head[s:e], with_large=True)
            if R is not None:
                final = np.einsum("cij,cvj->cvi", R[s:e], final) + t[s:e, None, :]
                if with_large:
                    large = np.einsum("cij,cvj->cvi", R[s:e], large) + t[s:e, None, :]
            if pending is not None:
                pending.result()
            pending = pool.submit(sink, s, final, large if with_large else None, None)
        if pending is not None:
            pending.result()


def edited_windows(windows, frames: np.ndarray, edits: list[HandleEdit]):
    """The (head, R, t) windows with the edits' handle offsets added to head, by the frames' numbers."""
    start = 0
    for head, R, t in windows:
        n = len(head)
        yield apply_edits(head, frames[start:start + n], edits), R, t
        start += n


@dataclass
class ReplayResult:
    positions_path: Path
    report: dict


def replay(model: Model, head: np.ndarray, R: np.ndarray, t: np.ndarray, frames: np.ndarray, times: np.ndarray,
           out_dir: Path, evaluator=None, chunk: int = 32, head_motion: str = "keep", progress=None,
           extra_report=None, save_large: bool = False) -> ReplayResult:
    """Replay handle trajectories onto the full mesh: :func:`replay_windows` with one window."""
    return replay_windows(model, [(head, R, t)], frames, times, out_dir, evaluator, chunk, head_motion, progress,
                          extra_report, save_large)


def replay_windows(model: Model, windows, frames: np.ndarray, times: np.ndarray, out_dir: Path, evaluator=None,
                   chunk: int = 32, head_motion: str = "keep", progress=None, extra_report=None,
                   save_large: bool = False) -> ReplayResult:
    """Replay handle trajectories onto the full mesh, streaming positions to disk.

    Parameters
    ----------
    windows : iterable of (head, R, t) for consecutive frames (e.g. a take cleaned window by
        window, :func:`facepipe.mocap.prepare.prepare_take_windows`): head (n, H, 3) clean handle
        positions in head (rig) space, rig units; R, t (n, 3, 3), (n, 3) the head's rigid
        motion, world = R @ head + t. Where the evaluator runs off the host's cores (a GPU), the
        next window is taken on a second thread while this one is evaluated (on a CPU device
        both would compete for the same cores: there they take turns).
    frames : (T,) frame numbers; times : (T,) seconds, of all the windows' frames.
    out_dir : gets ``positions.npy`` (float32, T × V × 3, written chunk by chunk while the next
        chunk is evaluated, renamed into place when complete), ``replay.json``, and ``handles.npz`` (the clean head-space
        handles and the head motion: what an exporter needs to re-evaluate any layer of the model).
    head_motion : "keep" re-applies the head's rigid motion to the output, "remove" leaves
        the face in rig space.
    progress : callable(n_frames_done) or None.
    extra_report : dict for replay.json, or a callable returning it once the windows are taken.
    """
    evaluator = evaluator or NumpyEvaluator(model)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    T = len(frames)
    V = model.n_vertices
    heads, rotations, translations = [], [], []
    t_start = time.perf_counter()
    final_path = out_dir / "positions.npy"
    large_path = out_dir / "large_scale.npy"
    # no temporary large-scale file unless it is asked for (an interrupted replay leaves none)
    with atomic_path(final_path) as tmp, (atomic_path(large_path) if save_large else nullcontext()) as tmp_large:
        # positions stream to disk in frame order while the next chunk is evaluated
        regions = getattr(evaluator, "placement_regions", None)
        with NpyWriter(tmp, (T, V, 3), regions=regions) as out, \
                NpyWriter(tmp_large if save_large else None, (T, V, 3)) as out_large:
            def sink(start, final, large=None, normals=None):
                out.write(final)
                if save_large:
                    out_large.write(large)
                if progress is not None:
                    progress(final.shape[0])

            keep = head_motion == "keep"
            overlap = not getattr(evaluator, "on_host_cores", True)
            done = 0
            for head, R, t in (prefetched(windows) if overlap else windows):
                # where the evaluator can, it writes the positions into the writer's own aligned
                # memory, which goes to disk with no copy
                stream_chunks(evaluator, head, sink, R if keep else None, t if keep else None, chunk=chunk,
                              with_large=save_large,
                              placement=lambda s, n, i, first=done: out.placement(first + s, n, i))
                done += len(head)
                heads.append(head.astype(np.float32))
                rotations.append(R)
                translations.append(t)
            if sum(len(h) for h in heads) != T:
                raise ValueError(f"the windows hold {sum(len(h) for h in heads)} frames, not {T}")
    head = np.concatenate(heads) if heads else np.zeros((0, len(model.handle_vertices), 3), np.float32)
    R = np.concatenate(rotations) if rotations else np.zeros((0, 3, 3))
    t = np.concatenate(translations) if translations else np.zeros((0, 3))
    if not save_large:
        large_path.unlink(missing_ok=True)
    with atomic_path(out_dir / "handles.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, head=head.astype(np.float32), rotation=R.astype(np.float32),
                     translation=t.astype(np.float32), frame=np.asarray(frames), time=np.asarray(times),
                     head_motion=np.array(head_motion))
    seconds = time.perf_counter() - t_start
    angles = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    report = {
        "frames": int(T),
        "first_frame": int(frames[0]) if T else None,
        "last_frame": int(frames[-1]) if T else None,
        "frame_numbers": [int(f) for f in frames],
        "times": [float(x) for x in times],
        "vertices": int(V),
        "method": model.method,
        "backend": evaluator.backend,
        "device": evaluator.device,
        "head_motion": head_motion,
        "head_rotation_deg_max": float(angles.max()) if T else 0.0,
        "head_translation_max": float(np.linalg.norm(t, axis=1).max()) if T else 0.0,
        "units": model.meta.get("units") or None,  # of positions, errors and translations
        "seconds": seconds,
        "frames_per_second": T / seconds if seconds > 0 else None,
        "stage_seconds": dict(evaluator.stage_seconds),
        # the gate's non-negative fits that stopped at their iteration cap (their confidence is
        # that of the last iterate); None without a gate
        "novelty_fits_at_cap": evaluator.novelty_fits_at_cap,
        # absolute, and relative to this folder: found wherever a later export or preview runs
        # from, and after the replay and model folders are moved together
        "model": str(Path(model.path).resolve()) if model.path else None,
        "model_relative": os.path.relpath(Path(model.path).resolve(), out_dir.resolve()) if model.path else None,
        "config_digest": model.meta.get("config_digest"),
    }
    if model.meta.get("welded"):  # [rig] weld: the positions are the welded mesh's (MDD, PC2 export the file's order)
        report["welded"] = dict(model.meta["welded"])
    if callable(extra_report):  # (what the windows made known, now that they are all taken)
        extra_report = extra_report()
    if extra_report:
        report.update(extra_report)
    with atomic_path(out_dir / "replay.json") as tmp:
        tmp.write_text(json.dumps(report, indent=2))
    return ReplayResult(final_path, report)
