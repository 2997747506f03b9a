"""``facepipe replay`` of a mesh animation (USD, MDD, PC2, OBJ sequence): read, check, replay, report."""

from __future__ import annotations


def replay_cache(rep, take: str, model_path: str, output: str, *, large_scale: str | None, rest_frame: int | None,
                 take_units: str | None, cache_fps: float | None, frames_text: str | None, head_motion: str,
                 chunk: int, save_large: bool, make_evaluator, backend: str = "numpy",
                 device: str | None = None) -> dict:
    """Replay the point cache ``take`` onto ``model_path``'s face; returns replay.json's content.

    ``large_scale``: "take" (default: the cache's surface plus the band of details it lacks) or
    "shell" (the handle vertices replayed as markers). ``make_evaluator(model)``: the marker
    replay's evaluator, used for "shell". ``backend``, ``device``: for "take", as for markers (auto:
    OpenCL where a device works, else the NumPy reference).
    """
    from facepipe.io.model_file import load_model
    from facepipe.mocap import parse_frame_slice
    from facepipe.cli.commands import _said_device, say_replayed
    from facepipe.pipeline.backend import cache_evaluator
    from facepipe.pipeline.cache_replay import replay_mesh_cache

    mode = large_scale or "take"
    model = load_model(model_path)
    result = replay_mesh_cache(
        model, take, output, large_scale=mode, rest_frame=rest_frame, take_units=take_units, cache_fps=cache_fps,
        frames=parse_frame_slice(frames_text) if frames_text else None, head_motion=head_motion, chunk=chunk,
        save_large=save_large, marker_evaluator=make_evaluator,
        take_engine=lambda details: _said_device(rep, cache_evaluator(details, backend, device, chunk,
                                                                      note=lambda text: rep.say(f"note: {text}"))),
        say=rep.say, open_bar=lambda total: rep.bar(total, desc="replay"))
    say_replayed(rep, result, large_scale_from="cache" if mode == "take" else "shell")
    return result.report
