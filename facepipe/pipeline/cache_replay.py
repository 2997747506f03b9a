"""Replay of a mesh animation (a point cache of a rigged face) with the model's details added.

Two ways to use the cache's motion (``replay --large-scale``):

* ``shell``: the handle vertices are sampled from the cache and replayed as from markers (the
  cache's own surface is ignored): :func:`facepipe.pipeline.replay.replay_windows` with the
  model's evaluator (OpenCL or NumPy);
* ``take`` (the default): the cache's surface is the large-scale motion. Per frame the strain of
  the feature graph is measured on the cache's handle vertices, the details d(f) are evaluated
  and applied in the local frames of the cache's surface. Only the band of the details that the
  cache does not already carry is added (:mod:`facepipe.core.detail_bands`): it is estimated on
  the cache itself, from its deviation from the shell's solution for the same handles, band by band,
  before the replay, and reported.

The head's rigid motion in the cache is found per frame from the handle vertices (the stable
ones where the rig has at least three) against the rest handles; it is needed for the head-space
handles (the novelty gate's motion part, the shell's response) and for ``--head-motion remove``.
Local frames and strain are rotation-invariant, so the details follow the cache's head motion
as they follow the marker replay's.
"""

from __future__ import annotations

import contextlib
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from facepipe.core.detail_bands import DetailBands, banded_detail_model, banded_strain_model, bands_to_add
from facepipe.core.rigid import robust_rigid_fit, stable_marker_pose
from facepipe.core.shell import marker_spacing
from facepipe.core.tangent_frames import local_frames
from facepipe.errors import InputError
from facepipe.mocap.mesh_cache import read_mesh_cache
from facepipe.pipeline.replay import NumpyEvaluator, replay_windows

#: Frames of the cache the band estimate looks at (evenly spread): the α's are a handful of
#: numbers over the whole take, so a sample of frames determines them.
ESTIMATE_FRAMES = 12


@dataclass
class CachePose:
    """The cache's head motion and head-space handles: world = R @ head + t."""

    head: np.ndarray          # (T, H, 3) float64
    rotation: np.ndarray      # (T, 3, 3)
    translation: np.ndarray   # (T, 3)
    notes: list = field(default_factory=list)


#: Anchor vertices the head pose is fitted on, at most (evenly spread over the anchor list).
POSE_POINTS = 2000


def cache_pose(model, cache, chunk: int = 256) -> CachePose:
    """Head motion of every frame of ``cache``: world = R @ head + t.

    The pose comes from the model's anchors, the vertices no expression moves (the back of the
    head, the neck's border): on a rig's cache they move with the head alone, so a robust rigid fit
    of the rest anchors to the cache's gives the head's motion — exactly, on a cache the model
    itself wrote. Without 3 anchors, from the stable handles (all handles without 3 of them).
    """
    handles = model.handle_vertices.astype(np.int64)
    rest_handles = model.rest[handles].astype(np.float64)
    anchors = np.asarray(model.anchors, dtype=np.int64)
    notes: list[str] = []
    world_handles = np.empty((cache.n_frames, len(handles), 3))
    if len(anchors) >= 3:
        pick = anchors[np.unique(np.linspace(0, len(anchors) - 1, min(POSE_POINTS, len(anchors))).astype(int))]
        R = np.empty((cache.n_frames, 3, 3))
        t = np.empty((cache.n_frames, 3))
        rest_pick = model.rest[pick].astype(np.float64)
    for s in range(0, cache.n_frames, chunk):
        block = cache.chunk(s, min(cache.n_frames, s + chunk))
        world_handles[s:s + len(block)] = block[:, handles]
        if len(anchors) >= 3:
            R[s:s + len(block)], t[s:s + len(block)], _ = robust_rigid_fit(rest_pick, block[:, pick])
    if len(anchors) < 3 or not np.isfinite(t).all():
        notes.append("the model has fewer than 3 anchors: the head pose comes from the handle vertices")
        R, t = stable_marker_pose(rest_handles, world_handles, np.asarray(model.stable, dtype=bool), notes)
    head = np.einsum("tji,thj->thi", R, world_handles - t[:, None, :])
    return CachePose(head, R, t, notes)


class CacheDetails(NumpyEvaluator):
    """The details of a model evaluated on a cache's own surface (the ``take`` way of replaying it):
    the reference evaluator's :meth:`~facepipe.pipeline.replay.NumpyEvaluator.world_details` on
    each frame of the cache, the frames streamed by :meth:`stream` (``evaluate``, the shell's large
    scale from handles, is not what a cache take uses).

    Parameters
    ----------
    model : a baked model (psd, wpsd, local_strain or none; local_strain's details follow the
        local strain of the cache's own surface).
    cache : facepipe.mocap.mesh_cache.MeshCache in the rig's units.
    pose : :func:`cache_pose` of the cache.
    """

    device = "cpu (numpy, the cache's surface)"

    def __init__(self, model, cache, pose: CachePose):
        super().__init__(model)
        self.cache = cache
        self.pose = pose
        self.keep = None  # (bands,) fraction of each band added; None: every band whole
        self.bands: DetailBands | None = None
        #: (weights (V, P, 3), const (V, 3) or None) of the added bands when only some are (see
        #: :func:`facepipe.core.detail_bands.banded_detail_model`; a local-strain model's kernel
        #: weights and no constant), else None: the model's own
        self.detail_weights: tuple | None = None
        self.stage_seconds = {"frames": 0.0, "fine_scale": 0.0, "bands": 0.0}

    def estimate(self, frames: int = ESTIMATE_FRAMES, batch: int = 6) -> dict:
        """Choose the bands of the details to add (:func:`facepipe.core.detail_bands.bands_to_add`),
        measured on ``frames`` frames of the cache spread over the take, ``batch`` at a time.

        Returns the report: per band its wavelengths (rig units), the amplitude ratio r_b of the
        cache's deviation from the shell to the details, the projection of the deviation on the
        details, whether the band is added, and the added bands' share of the details' energy.
        """
        model, cache, pose = self.model, self.cache, self.pose
        if model.method == "none":
            return {"method": "none", "note": "the model has no details: the cache is written as it is"}
        spacing = float(model.meta.get("marker_spacing") or marker_spacing(model.rest, model.handle_vertices))
        # single precision: the details are float32 in every output (see DetailBands)
        self.bands = DetailBands(self.rest, self.faces, spacing, single=True)
        index = np.unique(np.linspace(0, cache.n_frames - 1, min(frames, cache.n_frames)).round().astype(int))
        B = model.B.astype(np.float64)  # (for these frames only: not kept as the evaluator's B)
        sums = 0.0
        for s in range(0, len(index), batch):
            k = index[s:s + batch]
            R, t, head = pose.rotation[k], pose.translation[k], pose.head[k]
            surface = np.einsum("cji,cvj->cvi", R, np.stack([cache.frame(int(i)) for i in k]) - t[:, None, :])
            shell = self.rest + np.einsum("vh,chx->cvx", B, head - self.rest_handles, optimize=True)
            D = self.world_details(surface, head)
            sums = sums + self.bands.paired_band_sums(D, surface - shell)
        choice = bands_to_add(sums)
        self.keep = choice["added"]
        if self.keep.any() and not self.keep.all():
            self._filter_weights()
        edges = list(self.bands.wavelengths)
        labels = [f"< {edges[0]:.3g}"] + [f"{a:.3g}–{b:.3g}" for a, b in zip(edges, edges[1:])] + [f"> {edges[-1]:.3g}"]
        return {
            "method": "bands",
            "frames_sampled": int(len(index)),
            "marker_spacing": spacing,
            "band_wavelengths": labels,
            "amplitude_ratio": [float(r) for r in choice["ratio"]],
            "projection": [float(p) for p in choice["projection"]],
            "added": [float(a) for a in choice["added"]],
            "added_fraction": choice["added_energy"],
        }

    def _filter_weights(self) -> None:
        """Replace the details by their added bands, once for the whole take: the examples' details
        filtered in the rest surface's frames and the model fitted to them (no band filter per frame)."""
        t0 = time.perf_counter()
        frames = local_frames(self.rest, self.faces, self.neighbors, self.incidence)
        if self.strain_details is not None:
            self.strain_details = banded_strain_model(self.bands, self.strain_details, frames, self.keep)
            self.detail_weights = (self.strain_details.weights, None)
        else:
            self.details = banded_detail_model(self.bands, self.details, frames, self.keep)
            self.detail_weights = (self.details.weights, self.details.const)
        self.bands.close()  # the factors are not needed again
        self.stage_seconds["bands"] += time.perf_counter() - t0

    def stream(self, head, sink, R=None, t=None, with_large: bool = False) -> None:
        """Evaluate every frame and hand chunks to ``sink(start, final, large, None)`` in order
        (the interface of :func:`facepipe.pipeline.replay.stream_chunks`): ``head`` is the pose's; with
        ``R``/``t`` (head motion kept) the output is in the cache's space, else in head space."""
        T = self.cache.n_frames
        chunk = 8
        keep_motion = R is not None
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="facepipe-sink") as pool:
            pending = None
            for s in range(0, T, chunk):
                e = min(T, s + chunk)
                surface = self.cache.chunk(s, e)
                if not keep_motion:
                    surface = np.einsum("cji,cvj->cvi", self.pose.rotation[s:e],
                                        surface - self.pose.translation[s:e, None, :])
                final = surface
                if self.model.method != "none" and (self.keep is None or np.any(self.keep > 0)):
                    # (the details are those of the added bands already: _filter_weights)
                    final = surface + self.world_details(surface, self.pose.head[s:e])
                if pending is not None:
                    pending.result()
                pending = pool.submit(sink, s, final, surface if with_large else None, None)
            if pending is not None:
                pending.result()

    def close(self) -> None:
        if self.bands is not None:
            self.bands.close()


def replay_mesh_cache(model, take, output, *, large_scale: str = "take", rest_frame: int | None = None,
                      take_units: str | None = None, cache_fps: float | None = None, frames=None,
                      head_motion: str = "keep", chunk: int = 32, save_large: bool = False, marker_evaluator=None,
                      take_engine=None, say=None, open_bar=None, extra_report=None):
    """Replay the mesh cache ``take`` (USD, MDD, PC2, OBJ sequence) onto ``model``'s face into the
    folder ``output``, as ``facepipe replay`` and ``facepipe batch`` do; the
    :class:`~facepipe.pipeline.replay.ReplayResult`.

    large_scale : "take" (the cache's surface plus the band of details it lacks, estimated on the
        cache) or "shell" (the handle vertices replayed as markers, with ``marker_evaluator(model)``).
    take_engine : ``take_engine(details)`` the evaluator for "take" given the NumPy one
        (:class:`CacheDetails`, with its bands chosen): e.g. the OpenCL cache engine; None: NumPy.
    frames : a slice of the cache's frames, or None. ``say(text)``: what the user is told;
    ``open_bar(total)``: a progress bar (a context manager with ``update(n)``), or None.
    extra_report : more for replay.json (e.g. the batch's worker).

    Raises InputError (a cache that is not the rest mesh's, of another scale, with NaNs, ...).
    """
    say = say or (lambda text: None)
    if large_scale not in ("take", "shell"):
        raise InputError(f"large scale {large_scale!r}: 'take' (the cache's surface) or 'shell' (its handles as markers)")
    if cache_fps is not None and cache_fps <= 0:
        raise InputError(f"--cache-fps {cache_fps} must be positive")
    cache, check = read_mesh_cache(take, model.rest, units=model.meta.get("units"), take_units=take_units,
                                   file_order=model.weld_index,
                                   rest_frame=rest_frame, fps=cache_fps, frames=frames)
    say(f"{cache.format} cache: {cache.n_frames} frames × {cache.n_vertices} vertices at {cache.fps:g} frames/s "
        f"({cache.source_units or 'units not stated'}" + (f", × {cache.scale:g} to {cache.units}" if cache.scale != 1
                                                          else "") + f"); frame {check['frame']} matches the rest "
        f"mesh (scale {check['scale']:.4f}, median vertex {check['median_distance']:.3g} off)")
    for note in cache.notes or []:
        say(f"note: {note}")
    pose = cache_pose(model, cache)
    for note in pose.notes:
        say(f"note: {note}")
    report = {"take": str(take), "cache": {"format": cache.format, "fps": cache.fps, "units": cache.units,
                                           "source_units": cache.source_units, "scale": cache.scale,
                                           "rest_check": check, "notes": list(cache.notes or []) + pose.notes,
                                           "large_scale": large_scale, "source": cache_source(take)},
              **(extra_report or {})}
    details = None
    try:
        if large_scale == "shell":
            evaluator = (marker_evaluator or NumpyEvaluator)(model)
        else:
            details = evaluator = CacheDetails(model, cache, pose)
            band = details.estimate()
            report["cache"]["bands"] = band
            if band.get("method") == "bands":
                added = [w for w, a in zip(band["band_wavelengths"], band["added"]) if a]
                say(f"details added: {', '.join(added) if added else 'none'} (wavelength bands, rig units; "
                    f"{100 * band['added_fraction']:.0f} % of the details' energy); the cache's own amplitude per "
                    "band, relative to the details': " + ", ".join(f"{r:.2f}" for r in band["amplitude_ratio"]))
            nothing_to_add = model.method == "none" or (details.keep is not None and not details.keep.any())
            if take_engine is not None and not nothing_to_add:  # (none added: the cache is written as it is)
                evaluator = take_engine(details)
        # the cache's surface is the large scale of "take": exports read it back from the cache
        # (replay.json says where and what it was), so it is written again only when asked
        bar = open_bar(cache.n_frames) if open_bar is not None else contextlib.nullcontext()
        with bar as progress:
            return replay_windows(model, [(pose.head, pose.rotation, pose.translation)], cache.frames, cache.times,
                                  Path(output), evaluator=evaluator, chunk=chunk, head_motion=head_motion,
                                  progress=None if progress is None else progress.update, extra_report=report,
                                  save_large=save_large)
    finally:
        if details is not None:
            details.close()


def cache_source(take) -> dict:
    """Where the cache is and what it was (a file's size and modification time), so exports can read
    its surface back and tell when it has changed since."""
    path = Path(take).resolve()
    if not path.is_file():  # an OBJ sequence (folder or pattern)
        return {"path": str(path)}
    stat = path.stat()
    return {"path": str(path), "size": stat.st_size, "mtime_ns": stat.st_mtime_ns}
