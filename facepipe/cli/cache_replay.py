"""``facepipe replay`` of a mesh animation (USD, MDD, PC2, OBJ sequence): read, check, replay, report."""

from __future__ import annotations

from pathlib import Path

from facepipe.errors import InputError


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
                                           "large_scale": mode, "source": _source(take)}}
    details = None
    if mode == "shell":
        evaluator = make_evaluator(model)
        windows = [(pose.head, pose.rotation, pose.translation)]
        save = save_large
    else:
        details = evaluator = CacheDetails(model, cache, pose)
        band = evaluator.estimate()
        report["cache"]["bands"] = band
        if band.get("method") == "bands":
            added = [w for w, a in zip(band["band_wavelengths"], band["added"]) if a]
            rep.say(f"details added: {', '.join(added) if added else 'none'} (wavelength bands, rig units; "
                    f"{100 * band['added_fraction']:.0f} % of the details' energy); the cache's own amplitude per "
                    "band, relative to the details': " + ", ".join(f"{r:.2f}" for r in band["amplitude_ratio"]))
        evaluator = _take_evaluator(rep, model, cache, pose, evaluator, backend, device, chunk)
        windows = [(pose.head, pose.rotation, pose.translation)]
        # the cache's surface is the large scale: exports read it back from the cache (replay.json
        # says where and what it was), so it is written again only when asked
        save = save_large
    try:
        with rep.bar(cache.n_frames, desc="replay") as bar:
            result = replay_windows(model, windows, cache.frames, cache.times, Path(output), evaluator=evaluator,
                                    chunk=chunk, head_motion=head_motion, progress=bar.update,
                                    extra_report=report, save_large=save)
    finally:
        if mode == "take" and details is not None:
            details.close()
    r = result.report
    rep.say(f"replayed {r['frames']} frames × {r['vertices']} vertices ({r['method']}, large scale from the "
            f"{'cache' if mode == 'take' else 'shell'}, {r['backend']}) at {r['frames_per_second']:.1f} frames/s")
    rep.say(f"head motion up to {r['head_rotation_deg_max']:.1f}° / {r['head_translation_max']:.2f}")
    rep.say(f"wrote {result.positions_path} and {Path(output) / 'replay.json'}")
    return r


def _take_evaluator(rep, model, cache, pose, details, backend: str, device: str | None, chunk: int):
    """The OpenCL cache engine when asked for or (auto) when a device works, else ``details`` (NumPy)."""
    if backend == "numpy" or model.method == "none" or (details.keep is not None and not details.keep.any()):
        return details  # (no band added: the cache is written as it is, nothing to evaluate)
    from facepipe.cli.backend import opencl_or_fallback
    from facepipe.opencl.cache_engine import OpenCLCacheEvaluator

    return opencl_or_fallback(
        rep, backend, lambda: OpenCLCacheEvaluator(model, cache, pose, details, device=device, chunk=chunk),
        lambda: details)


def _source(take: str) -> dict:
    """Where the cache is and what it was (a file's size and modification time), so exports can read
    its surface back and tell when it has changed since."""
    path = Path(take).resolve()
    if not path.is_file():  # an OBJ sequence (folder or pattern)
        return {"path": str(path)}
    stat = path.stat()
    return {"path": str(path), "size": stat.st_size, "mtime_ns": stat.st_mtime_ns}
