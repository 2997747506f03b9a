"""``facepipe replay`` of a 2D landmark take: read, check, lift to 3D, replay, report."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facepipe.errors import InputError
from facepipe.io.camera_file import read_camera
from facepipe.io.landmark_map import model_landmark_map, read_landmark_map
from facepipe.io.model_file import load_model
from facepipe.io.video_record import VideoRecord, write_video_record
from facepipe.mocap.landmarks2d import check_in_image, is_landmark_take, read_landmark_take
from facepipe.mocap.take import parse_frame_slice
from facepipe.pipeline.replay import replay_windows
from facepipe.pipeline.video_lift import LiftOptions, lift_rig, lift_take, reprojection_of_output, summary_lines

__all__ = ["replay_video"]


def replay_video(rep, take_path, model_path, output, *, camera_path, landmarks_path, lift: str, frames_text,
                 head_motion: str, chunk: int, save_large: bool, make_evaluator, min_confidence: float) -> None:
    """Replay a 2D take: ``make_evaluator(model)`` gives the replay evaluator (as for 3D takes)."""
    take_path = Path(take_path)
    if not take_path.is_file():
        raise InputError("take not found", path=take_path, hint="check the path of the take")
    if not is_landmark_take(take_path):
        raise InputError("--camera and --landmarks are for 2D landmark takes; this take is not one", path=take_path,
                         hint="replay 3D markers without --camera/--landmarks; a 2D take is an OpenFace CSV or "
                              "frame,time,NAME_u,NAME_v,…")
    if camera_path is None:
        raise InputError("a 2D landmark take needs the camera's calibration", path=take_path,
                         hint="pass --camera CALIBRATION.yml (OpenCV FileStorage) or .json")
    if not 0.0 <= min_confidence <= 1.0:
        raise InputError(f"--min-confidence {min_confidence} is outside 0..1")
    camera = read_camera(camera_path)
    model = load_model(model_path)
    # --landmarks overrides the map the model was baked with ([video] landmarks in its config)
    lmap = read_landmark_map(landmarks_path, model.n_vertices) if landmarks_path else model_landmark_map(model)
    if lmap is None:
        raise InputError("a 2D landmark take needs the landmark map, and this model was baked without one",
                         path=take_path, hint="pass --landmarks MAP.csv (name,vertex: the tracker's point names to rig "
                                              "vertices), or set [video] landmarks in the config and bake again")
    take = read_landmark_take(take_path, lmap.names, parse_frame_slice(frames_text) if frames_text else None,
                              min_confidence=min_confidence)
    check_in_image(take, camera.width, camera.height, str(camera.path))
    evaluator = make_evaluator(model)
    rig = lift_rig(model, lmap.vertices)
    result = lift_take(take, camera, rig, LiftOptions(method=lift))
    report = dict(result.report, landmark_map=str(lmap.path))
    # where the calibration is, whatever the working directory of a later preview, and what it says
    report["camera"] = dict(report["camera"], path=str(Path(camera.path).resolve()), matrix=camera.matrix.tolist())

    def video_report():  # once positions.npy is complete: the replayed face's own reprojection error
        positions = np.load(Path(output) / "positions.npy", mmap_mode="r")
        rows = np.asarray(positions[:, lmap.vertices], dtype=np.float64)
        report["reprojection_px"] = reprojection_of_output(camera, take, rows, result.R, result.t, head_motion,
                                                            result.used)
        # what `facepipe preview` draws the face over (written before replay.json, which comes last)
        used = result.used if result.used is not None else take.visible
        write_video_record(output, VideoRecord(camera, list(lmap.names), lmap.vertices, take.points, used,
                                               take.failed, take.frames))
        return {"take": str(take_path), "video": report, "coordinates": "camera (OpenCV axes, rig units)"
                if head_motion == "keep" else "rig"}

    windows = [(result.head, result.R, result.t)]
    with rep.bar(take.n_frames, desc="replay") as bar:
        out = replay_windows(model, windows, take.frames, take.times, Path(output), chunk=chunk, evaluator=evaluator,
                             head_motion=head_motion, progress=bar.update, extra_report=video_report,
                             save_large=save_large)
    r = out.report
    rep.say(f"replayed {r['frames']} frames × {r['vertices']} vertices ({r['method']}, {r['backend']}) "
            f"at {r['frames_per_second']:.1f} frames/s")
    for line in summary_lines(report):
        rep.say(line)
    rep.say(f"wrote {out.positions_path} and {Path(output) / 'replay.json'}"
            + (" (camera coordinates)" if head_motion == "keep" else " (rig space)"))
