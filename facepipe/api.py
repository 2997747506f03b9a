"""facepipe as a library: load a model, read a take, replay marker frames onto the face.

The command line (``facepipe replay``) streams long takes to disk; these functions keep
everything in memory, for scripts, notebooks and other tools that hold a take as arrays::

    import facepipe

    model = facepipe.load_model("model.npz")
    take = facepipe.read_take("take.c3d", model)          # the rig's markers, in the rig's units
    result = facepipe.replay_take(model, take)            # aligned, stabilised, cleaned, evaluated
    result.positions                                      # (T, V, 3) in the take's space

    head_space = result.handles                           # (T, H, 3) clean handle positions
    faces = facepipe.evaluate(model, head_space)          # (T, V, 3): the face for any handle frames

    wrinkled = facepipe.add_details(model, rig_frames)    # a rig's own animation (T, V, 3) with the details
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from facepipe.errors import InputError
from facepipe.io.model_file import Model
from facepipe.io.model_file import load_model as _load_model_file
from facepipe.mocap.cleaning import CleanOptions
from facepipe.mocap.prepare import PrepareOptions, prepare_take
from facepipe.mocap.registry import read_take as _read_take_file
from facepipe.mocap.take import Take
from facepipe.pipeline.replay import NumpyEvaluator

__all__ = ["Model", "ReplayedTake", "Take", "add_details", "evaluate", "load_model", "read_take", "replay_take"]


def load_model(path: str | os.PathLike) -> Model:
    """A baked model (``facepipe bake``), checked; :class:`InputError` names what is wrong."""
    return _load_model_file(path)


def read_take(path: str | os.PathLike, model: Model, *, take_units: str | None = None,
              subject: str | None = None, frames: slice | str | None = None) -> Take:
    """A mocap take (facepipe CSV, C3D, TRC, Vicon or Motive CSV) with ``model``'s markers in its
    order and units; markers the file lacks are missing (NaN), filled when the take is replayed."""
    return _read_take_file(path, model.marker_names, frames, units=model.meta.get("units"),
                           take_units=take_units, subject=subject, absent="missing", allow_empty_frames=True)


@dataclass
class ReplayedTake:
    """A take replayed onto the full-resolution face.

    Attributes
    ----------
    positions : (T, V, 3) float64, the final surface (head motion kept, as the take moves).
    handles : (T, H, 3) float64, the clean handle positions in head space (rig space).
    rotation, translation : (T, 3, 3), (T, 3): the head's motion, world = R · head + t.
    report : what alignment, stabilisation and cleaning did (as ``replay.json``'s ``mocap``).
    """

    positions: np.ndarray
    handles: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    report: dict


def replay_take(model: Model, take: Take, *, neutral_frame: int | None = None, stabilise: bool = True,
                clean: bool = True, smooth: float = 0.0, head_motion: str = "keep") -> ReplayedTake:
    """Align, stabilise and clean ``take`` as ``facepipe replay`` does, and evaluate every frame
    with the NumPy reference (float64).

    ``head_motion="remove"`` leaves the face in rig space.
    """
    if head_motion not in ("keep", "remove"):
        raise InputError(f"head_motion must be 'keep' or 'remove', not {head_motion!r}")
    options = PrepareOptions(neutral_frame=neutral_frame, stabilise=stabilise, clean=clean,
                             clean_options=CleanOptions(smooth=smooth))
    handles, R, t, report = prepare_take(take, model, options)
    positions = evaluate(model, handles)
    if head_motion == "keep":
        positions = np.einsum("fij,fvj->fvi", R, positions) + t[:, None, :]
    return ReplayedTake(positions, handles, R, t, report)


def evaluate(model: Model, handle_positions: np.ndarray) -> np.ndarray:
    """The face (T, V, 3) for head-space handle positions (T, H, 3) or (H, 3), in ``model``'s
    handle order: the shell's large-scale surface plus the pose-space details."""
    handles = np.asarray(handle_positions, dtype=np.float64)
    single = handles.ndim == 2
    if single:
        handles = handles[None]
    H = len(model.handle_vertices)
    if handles.ndim != 3 or handles.shape[1:] != (H, 3):
        raise InputError(f"handle positions of shape {np.shape(handle_positions)}: the model has {H} handles, "
                         f"so (frames, {H}, 3) or ({H}, 3) is expected")
    if not np.isfinite(handles).all():
        frame = int(np.flatnonzero(~np.isfinite(handles).all(axis=(1, 2)))[0])
        raise InputError(f"handle positions of frame {frame} are not finite",
                         hint="fill gaps first (replay_take cleans a take)")
    positions = NumpyEvaluator(model).evaluate(handles)
    return positions[0] if single else positions


def add_details(model: Model, frames: np.ndarray, *, units: str | None = None, rest_frame: int = 0,
                fps: float = 30.0, head_motion: str = "keep") -> ReplayedTake:
    """The fine-scale details on a mesh animation made elsewhere (a rig's point cache as arrays),
    as ``facepipe replay CACHE --large-scale take`` does: the frames' own surface is the large
    scale, and the details are evaluated at the strain measured on it and added in its local
    frames — only the band of them the animation lacks, estimated from the frames themselves.

    frames : (T, V, 3) or (V, 3) every vertex of the model's rest mesh, in its vertex order (or, for
        a rig welded along seams, the mesh file's: the result is then in that order too), in
        ``units`` (default: the model's); frame ``rest_frame`` (an index) must be the rest face up to
        a rigid motion and an expression.
    fps : the frames' rate (their times in the result's report).
    head_motion : "keep" (the frames' own space) or "remove" (rig space).

    Returns the frames with their details (``positions``, float64, the shape of ``frames``); its
    ``handles`` are the handle vertices in head space, ``rotation``/``translation`` the head's
    motion fitted on the model's anchors, ``report["cache"]`` what was checked and the bands added.
    """
    from facepipe.mocap.mesh_cache import MeshCache, check_mesh_cache  # noqa: I001 (lazy: SciPy-free import)
    from facepipe.pipeline.cache_replay import CacheDetails, cache_pose

    if head_motion not in ("keep", "remove"):
        raise InputError(f"head_motion must be 'keep' or 'remove', not {head_motion!r}")
    if not fps > 0:
        raise InputError(f"fps must be positive, not {fps!r}")
    positions = np.asarray(frames)
    single = positions.ndim == 2
    if single:
        positions = positions[None]
    if positions.ndim != 3 or positions.shape[-1] != 3 or not len(positions):
        raise InputError(f"frames of shape {np.shape(frames)}: (frames, {model.n_vertices}, 3) or "
                         f"({model.n_vertices}, 3) is expected")
    T = len(positions)
    if not 0 <= rest_frame < T:
        raise InputError(f"rest_frame {rest_frame} is not a frame index (0 to {T - 1})")
    cache = MeshCache(frames=np.arange(T), times=np.arange(T) / float(fps), positions=positions, path="(frames)",
                      format="array", fps=float(fps))
    cache, check = check_mesh_cache(cache, model.rest, units=model.meta.get("units"), take_units=units,
                                    rest_frame=rest_frame, file_order=model.weld_index)
    pose = cache_pose(model, cache)
    details = CacheDetails(model, cache, pose)
    out = np.empty((T, model.n_vertices, 3))

    def keep(start, final, large, _):
        out[start:start + len(final)] = final

    try:
        bands = details.estimate()
        motion = (pose.rotation, pose.translation) if head_motion == "keep" else (None, None)
        details.stream(pose.head, keep, *motion)
    finally:
        details.close()
    report = {"cache": {"units": cache.units, "source_units": cache.source_units, "scale": cache.scale,
                        "rest_check": check, "notes": list(cache.notes or []) + pose.notes, "bands": bands}}
    if model.weld_index is not None and positions.shape[1] == len(model.weld_index) != model.n_vertices:
        out = out[:, model.weld_index]  # frames given in the mesh file's order (a welded rig) come back in it
    return ReplayedTake(out[0] if single else out, pose.head, pose.rotation, pose.translation, report)
