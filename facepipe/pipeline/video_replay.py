"""Replay of a 2D landmark take (one camera): the take read and checked against the camera, lifted
to head-space handles and head pose (:mod:`facepipe.pipeline.video_lift`), replayed, and the
replayed face's own reprojection error measured; for ``facepipe replay`` and ``facepipe batch``."""

from __future__ import annotations

import contextlib
from dataclasses import replace
from pathlib import Path

import numpy as np

from facepipe.errors import InputError
from facepipe.io.landmark_map import model_landmark_map, read_landmark_map
from facepipe.io.video_record import VideoRecord, write_video_record
from facepipe.mocap.landmarks2d import check_in_image, read_landmark_take
from facepipe.pipeline.replay import replay_windows
from facepipe.pipeline.video_lift import LiftOptions, lift_rig, lift_take, reprojection_of_output

__all__ = ["DEFAULT_LIFT", "DEFAULT_MIN_CONFIDENCE", "landmark_map_for", "replay_landmark_take"]

#: what a 2D take's replay does without a lift or a confidence floor given
DEFAULT_LIFT = "model"
DEFAULT_MIN_CONFIDENCE = 0.5


def landmark_map_for(model, landmarks_path, take_path):
    """The landmark map of a 2D take's replay: ``landmarks_path`` (name,vertex CSV) where given, else
    the one the model was baked with ([video] landmarks in its config); InputError without either."""
    if landmarks_path and model.weld_index is not None:
        # a rig welded along seams ([rig] weld): the map numbers the mesh file's vertices, as the config's did
        lmap = read_landmark_map(landmarks_path, len(model.weld_index))
        lmap = replace(lmap, vertices=model.weld_index[lmap.vertices])
    else:
        lmap = read_landmark_map(landmarks_path, model.n_vertices) if landmarks_path else model_landmark_map(model)
    if lmap is None:
        raise InputError("a 2D landmark take needs the landmark map, and this model was baked without one",
                         path=take_path, hint="pass --landmarks MAP.csv (name,vertex: the tracker's point names to rig "
                                              "vertices), or set [video] landmarks in the config and bake again")
    return lmap


def replay_landmark_take(model, take_path, output, camera, landmark_map, make_evaluator, *, lift: str | None = None,
                         frames=None, head_motion: str = "keep", chunk: int = 32, save_large: bool = False,
                         min_confidence: float | None = None, open_bar=None, extra_report=None):
    """Replay the 2D take ``take_path`` seen by ``camera`` (:class:`~facepipe.core.camera.Camera`),
    its tracker's points mapped to rig vertices by ``landmark_map``, into the folder ``output``
    with ``make_evaluator(model)`` (called once the take is read and checked); the :class:`~facepipe.pipeline.replay.ReplayResult` and the video report
    (replay.json's ``video``).

    lift : "model" or "heuristic"; min_confidence : the tracker's confidence floor (None: the defaults).
    frames : a slice of the take's rows, or None; ``open_bar(total)``: a progress bar (a context
    manager with ``update(n)``), or None; extra_report : more for replay.json.

    Raises InputError (landmarks outside the camera's image, a map the take lacks, ...).
    """
    lift = DEFAULT_LIFT if lift is None else lift
    min_confidence = DEFAULT_MIN_CONFIDENCE if min_confidence is None else min_confidence
    if not 0.0 <= min_confidence <= 1.0:
        raise InputError(f"--min-confidence {min_confidence} is outside 0..1")
    take = read_landmark_take(take_path, landmark_map.names, frames, min_confidence=min_confidence)
    check_in_image(take, camera.width, camera.height, str(camera.path))
    evaluator = make_evaluator(model)
    rig = lift_rig(model, landmark_map.vertices)
    result = lift_take(take, camera, rig, LiftOptions(method=lift))
    report = dict(result.report, landmark_map=str(landmark_map.path))
    # where the calibration is, whatever the working directory of a later preview, and what it says
    report["camera"] = dict(report["camera"], path=str(Path(camera.path).resolve()), matrix=camera.matrix.tolist())

    def video_report():  # once positions.npy is complete: the replayed face's own reprojection error
        positions = np.load(Path(output) / "positions.npy", mmap_mode="r")
        rows = np.asarray(positions[:, landmark_map.vertices], dtype=np.float64)
        report["reprojection_px"] = reprojection_of_output(camera, take, rows, result.R, result.t, head_motion,
                                                            result.used)
        # what `facepipe preview` draws the face over (written before replay.json, which comes last)
        used = result.used if result.used is not None else take.visible
        write_video_record(output, VideoRecord(camera, list(landmark_map.names), landmark_map.vertices, take.points,
                                               used, take.failed, take.frames))
        return {"take": str(take_path), "video": report,
                "coordinates": "camera (OpenCV axes, rig units)" if head_motion == "keep" else "rig",
                **(extra_report or {})}

    bar = open_bar(take.n_frames) if open_bar is not None else contextlib.nullcontext()
    with bar as progress:
        out = replay_windows(model, [(result.head, result.R, result.t)], take.frames, take.times, Path(output),
                             chunk=chunk, evaluator=evaluator, head_motion=head_motion,
                             progress=None if progress is None else progress.update, extra_report=video_report,
                             save_large=save_large)
    return out, report
