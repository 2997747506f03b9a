"""``facepipe replay`` of a 2D landmark take: read, check, lift to 3D, replay, report."""

from __future__ import annotations

from pathlib import Path

from facepipe.errors import InputError
from facepipe.io.camera_file import read_camera
from facepipe.io.model_file import load_model
from facepipe.mocap.landmarks2d import is_landmark_take
from facepipe.mocap.take import parse_frame_slice
from facepipe.pipeline.video_lift import summary_lines
from facepipe.pipeline.video_replay import landmark_map_for, replay_landmark_take

__all__ = ["replay_video"]


def replay_video(rep, take_path, model_path, output, *, camera_path, landmarks_path, lift: str | None, frames_text,
                 head_motion: str, chunk: int, save_large: bool, make_evaluator, min_confidence: float | None) -> None:
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
    camera = read_camera(camera_path)
    model = load_model(model_path)
    lmap = landmark_map_for(model, landmarks_path, take_path)  # --landmarks overrides the model's
    out, report = replay_landmark_take(
        model, take_path, output, camera, lmap, make_evaluator, lift=lift,
        frames=parse_frame_slice(frames_text) if frames_text else None, head_motion=head_motion, chunk=chunk,
        save_large=save_large, min_confidence=min_confidence, open_bar=lambda total: rep.bar(total, desc="replay"))
    from facepipe.cli.commands import say_replayed

    say_replayed(rep, out, summary_lines(report), head_motion=False,
                 space=" (camera coordinates)" if head_motion == "keep" else " (rig space)")
