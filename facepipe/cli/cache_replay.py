"""``facepipe replay`` of a mesh animation (USD, MDD, PC2, OBJ sequence): read, check, replay, report."""

from __future__ import annotations

from pathlib import Path

from facepipe.errors import InputError


def replay_cache(rep, take: str, model_path: str, output: str, *, large_scale: str | None, rest_frame: int | None,
                 take_units: str | None, cache_fps: float | None, frames_text: str | None, head_motion: str,
                 chunk: int, save_large: bool, make_evaluator) -> dict:
    """Replay the point cache ``take`` onto ``model_path``'s face; returns replay.json's content.

    ``large_scale``: "take" (default: the cache's surface plus the band of details it lacks) or
    "shell" (the handle vertices replayed as markers). ``make_evaluator(model)``: the marker
    replay's evaluator, used for "shell".
    """
    from facepipe.io.model_file import load_model
    from facepipe.mocap import parse_frame_slice
    from facepipe.mocap.mesh_cache import read_mesh_cache
    from facepipe.pipeline.cache_replay import CacheDetails, cache_pose
    from facepipe.pipeline.replay import replay_windows

    mode = large_scale or "take"
    if cache_fps is not None and cache_fps <= 0:
        raise InputError(f"--cache-fps {cache_fps} must be positive")
    model = load_model(model_path)
    units = model.meta.get("units")
    frames = parse_frame_slice(frames_text) if frames_text else None
    cache, check = read_mesh_cache(take, model.rest, units=units, take_units=take_units, rest_frame=rest_frame,
                                   fps=cache_fps, frames=frames)
    rep.say(f"{cache.format} cache: {cache.n_frames} frames × {cache.n_vertices} vertices at {cache.fps:g} frames/s "
            f"({cache.source_units or 'units not stated'}" + (f", × {cache.scale:g} to {cache.units}" if cache.scale != 1
                                                              else "") + f"); frame {check['frame']} matches the rest "
            f"mesh (scale {check['scale']:.4f}, median vertex {check['median_distance']:.3g} off)")
    for note in cache.notes or []:
        rep.say(f"note: {note}")
    pose = cache_pose(model, cache)
    for note in pose.notes:
        rep.say(f"note: {note}")
    report = {"take": str(take), "cache": {"format": cache.format, "fps": cache.fps, "units": cache.units,
                                           "source_units": cache.source_units, "scale": cache.scale,
                                           "rest_check": check, "notes": list(cache.notes or []) + pose.notes,
                                           "large_scale": mode}}
    if mode == "shell":
        evaluator = make_evaluator(model)
        windows = [(pose.head, pose.rotation, pose.translation)]
        save = save_large
    else:
        evaluator = CacheDetails(model, cache, pose)
        band = evaluator.estimate()
        report["cache"]["bands"] = band
        if band.get("method") == "bands":
            added = [w for w, a in zip(band["band_wavelengths"], band["added"]) if a]
            rep.say(f"details added: {', '.join(added) if added else 'none'} (wavelength bands, rig units; "
                    f"{100 * band['added_fraction']:.0f} % of the details' energy); the cache's own amplitude per "
                    "band, relative to the details': " + ", ".join(f"{r:.2f}" for r in band["amplitude_ratio"]))
        windows = [(pose.head, pose.rotation, pose.translation)]
        save = True  # the cache's surface is the large scale: kept for --layer large / details exports
    try:
        with rep.bar(cache.n_frames, desc="replay") as bar:
            result = replay_windows(model, windows, cache.frames, cache.times, Path(output), evaluator=evaluator,
                                    chunk=chunk, head_motion=head_motion, progress=bar.update,
                                    extra_report=report, save_large=save)
    finally:
        close = getattr(evaluator, "close", None)
        if mode == "take" and close is not None:
            close()
    r = result.report
    rep.say(f"replayed {r['frames']} frames × {r['vertices']} vertices ({r['method']}, large scale from the "
            f"{'cache' if mode == 'take' else 'shell'}, {r['backend']}) at {r['frames_per_second']:.1f} frames/s")
    rep.say(f"head motion up to {r['head_rotation_deg_max']:.1f}° / {r['head_translation_max']:.2f}")
    rep.say(f"wrote {result.positions_path} and {Path(output) / 'replay.json'}")
    return r
