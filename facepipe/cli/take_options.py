"""The options of the kinds of take that are not marker takes, shared by ``replay`` and ``batch``:
mesh caches' and 2D landmark takes'. Their defaults are None, what each kind does without them
(``batch`` fingerprints only the options given)."""

from __future__ import annotations

import click

from facepipe.pipeline.video_replay import DEFAULT_LIFT, DEFAULT_MIN_CONFIDENCE


def mesh_cache_options(command):
    """--large-scale, --rest-frame, --cache-fps."""
    for option in reversed((
            click.option("--large-scale", "large_scale", type=click.Choice(["take", "shell"]), default=None,
                         help="Mesh caches (USD, MDD, PC2, OBJ sequence): take = the cache's surface plus the band of "
                              "details it lacks (estimated on the cache) [default]; shell = its handle vertices "
                              "replayed as markers."),
            click.option("--rest-frame", type=int, default=None,
                         help="Mesh caches: frame number checked against the model's rest mesh [default: the first]."),
            click.option("--cache-fps", type=float, default=None,
                         help="Mesh caches: frame rate, for PC2 and OBJ sequences that store none (30), or overriding "
                              "the file's."))):
        command = option(command)
    return command


def landmark_take_options(command):
    """--camera, --landmarks, --lift, --min-confidence."""
    for option in reversed((
            click.option("--camera", "camera_path", default=None, type=click.Path(dir_okay=False),
                         help="2D takes: the camera's calibration (OpenCV FileStorage .yml/.xml, or .json)."),
            click.option("--landmarks", "landmarks_path", default=None, type=click.Path(dir_okay=False),
                         help="2D takes: name,vertex CSV from the tracker's point names to rig vertices [default: the "
                              "model's, from its config's [video] landmarks]."),
            click.option("--lift", type=click.Choice(["model", "heuristic"]), default=None,
                         help=f"2D takes: pose and expression through the rig's examples, or Fidaleo et al.'s "
                              f"heuristic [default: {DEFAULT_LIFT}]."),
            click.option("--min-confidence", type=float, default=None,
                         help=f"2D takes (OpenFace): rows below this tracking confidence are missing frames [default: "
                              f"{DEFAULT_MIN_CONFIDENCE}]."))):
        command = option(command)
    return command
