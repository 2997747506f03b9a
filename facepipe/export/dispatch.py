"""A replay folder to the formats artists' tools read: the dispatcher behind ``facepipe export``.

============  ==========================================  ===================================
format        writes                                      needs
============  ==========================================  ===================================
``obj``       DEST/frame_NNNN.obj (polygons, UVs)         positions (or large_scale.npy)
``usd``       DEST.usdc: time-sampled UsdGeom.Mesh        positions, frame times
``mdd``       DEST.mdd point cache                        positions, frame times
``pc2``       DEST.pc2 point cache                        positions, uniform frame times
``exr``       DEST/frame_NNNN[.TILE].exr displacement     model with UVs, handles.npz
``wrinkle``   DEST/wrinkle_*.exr + coefficients.csv       PSD model with UVs, handles.npz
============  ==========================================  ===================================
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import Callable

from facepipe.errors import InputError
from facepipe.io.replay_folder import ReplayDir

FORMATS = ("obj", "exr", "wrinkle", "usd", "mdd", "pc2")
SEQUENCE_FORMATS = ("obj", "exr", "wrinkle")


def parse_resolution(text) -> tuple[int, int]:
    """``"2048"`` → (2048, 2048); ``"2048x1024"`` → (width 2048, height 1024).

    Example
    -------
    >>> parse_resolution("1024x512")
    (1024, 512)
    """
    try:
        parts = [int(x) for x in str(text).lower().split("x")]
    except ValueError:
        parts = []
    if len(parts) == 1:
        parts *= 2
    if len(parts) != 2 or not all(16 <= p <= 32768 for p in parts):
        raise InputError(f"--resolution {text!r} is not N or WxH with 16 <= N <= 32768",
                         hint="e.g. --resolution 2048 or --resolution 4096x2048")
    return parts[0], parts[1]


def _nullbar(total, desc="", unit="frame"):
    class _Bar:
        def update(self, n=1):
            pass

    return contextlib.nullcontext(_Bar())


def _file_bytes(paths) -> int:
    return int(sum(Path(p).stat().st_size for p in paths if Path(p).is_file()))


def export_replay(
    outdir,
    fmt: str,
    dest,
    *,
    model_path=None,
    layer: str = "final",
    resolution: tuple[int, int] = (2048, 2048),
    padding: int = 8,
    half: bool | None = None,
    mode: str = "vector",
    space: str = "local",
    start: int = 1,
    up_axis: str = "Y",
    force: bool = False,
    resume: bool = False,
    make_bar: Callable = _nullbar,
) -> dict:
    """Export a replay folder in one format.

    Parameters
    ----------
    outdir : the replay's output folder (:class:`facepipe.io.replay_folder.ReplayDir`).
    fmt : one of :data:`FORMATS`.
    dest : a folder for obj/exr/wrinkle; a file (or an existing folder) for usd/mdd/pc2.
    model_path : model to use instead of the one replay.json names.
    layer : geometry formats: "final" (positions.npy) or "large" (large_scale.npy: the
        surface that displacement maps are applied to).
    resolution : (width, height) texels per UDIM tile of a map.
    padding : texels of edge padding around UV islands.
    half : half-float maps; None = the format's default (exr half, wrinkle float).
    mode : maps: "vector" (R, G, B) or "scalar" (Y, along the normal).
    space : exr vector maps: "local" (the model's frames t, b, n), "tangent" (UV-aligned
        frames, the renderers' tangent space) or "object" (see :mod:`facepipe.pipeline.detail_layers`).
    start : number of the first file of a sequence.
    up_axis : USD stage up axis.
    force, resume : overwrite existing files / keep them and write only what is missing.
    make_bar : ``make_bar(total, desc, unit)`` → context manager with ``update(n)`` (a progress bar).

    Returns
    -------
    dict: format, dest, files (count), bytes, seconds, megabytes_per_second, per format
    details (resolution, tiles, fps, …), and ``notes`` (strings worth telling the user).
    """
    if fmt not in FORMATS:
        raise InputError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    replay = ReplayDir(outdir)
    dest = Path(dest)
    t0 = time.perf_counter()
    info: dict = {"format": fmt}
    if fmt in ("obj", "usd", "mdd", "pc2"):
        positions = replay.layer(layer)
        T = positions.shape[0]
        if fmt == "obj":
            from facepipe.export.common import write_obj_sequence

            model = replay.load_model(model_path)
            with make_bar(T, "export obj") as bar:
                paths = write_obj_sequence(model.mesh(), positions, dest, start=start, force=force, resume=resume,
                                           progress=bar.update)
        else:
            from facepipe.export import caches

            path = caches.cache_path(dest, fmt, name=replay.path.name or "replay")
            fps = replay.fps
            with make_bar(T, f"export {fmt}") as bar:
                if fmt == "mdd":
                    written = caches.write_mdd(path, positions, replay.times, force=force, resume=resume,
                                               progress=bar.update)
                elif fmt == "pc2":
                    written = caches.write_pc2(path, positions, replay.times, fps, force=force, resume=resume,
                                               progress=bar.update)
                else:
                    model = replay.load_model(model_path)
                    written = caches.write_usd(path, model.mesh(), positions, replay.times, fps,
                                               units=model.meta.get("units", ""), up_axis=up_axis,
                                               frame_numbers=replay.frame_numbers,
                                               metadata={"layer": layer, "replay": str(replay.path)},
                                               force=force, resume=resume, progress=bar.update)
            paths = [path]
            info.update(fps=fps, kept_existing=written is None)
        info.update(layer=layer, frames=int(T))
    else:
        from facepipe.export.uv_raster import mesh_raster

        model = replay.load_model(model_path)
        mesh = model.mesh()
        width, height = resolution
        if mode not in ("vector", "scalar"):
            raise ValueError(f"unknown map mode {mode!r}")
        # every refusal before the raster, which takes seconds at 2048² and up
        if fmt == "exr":
            from facepipe.pipeline.detail_layers import DetailLayer

            if mode == "scalar" and space != "local":
                raise InputError("a scalar map is the displacement along the normal; --space applies to vector maps",
                                 hint="drop --space, or export --vector maps")
            detail = DetailLayer(model, space, mesh)  # InputError for a model without details
        else:
            from facepipe.export.exr_maps import check_wrinkle_model

            check_wrinkle_model(model)  # InputError for WPSD and none, with the reason
        handles = replay.handles
        slots = "uv" if (fmt == "exr" and space == "tangent" and mode == "vector") else "vertex"
        raster = mesh_raster(mesh, width, height, padding, slots=slots)  # InputError without UVs
        units = model.meta.get("units", "")
        attrs = {"facepipe/units": units, "facepipe/mode": mode, "facepipe/model": str(replay.model_path(model_path))}
        info.update(resolution=[width, height], tiles=list(raster.tiles), mode=mode, padding=padding)
        if fmt == "exr":
            from facepipe.export.exr_maps import write_displacement_maps

            half = True if half is None else half
            head = handles["head"]
            rot = handles["rotation"] if (space == "object" and handles["head_motion"] == "keep") else None
            frames, times = replay.frame_numbers, replay.times
            attrs.update({"facepipe/space": space,
                          "facepipe/channels": ("R,G,B = x,y,z" if space == "object" else "R,G,B = t,b,n")
                          if mode == "vector" else "Y = n"})

            def values(s, e):
                return detail(head[s:e], None if rot is None else rot[s:e])

            samples: dict = {}
            with make_bar(replay.n_frames, "export exr") as bar:
                per_frame = write_displacement_maps(
                    raster, values, replay.n_frames, dest, mode=mode, half=half, start=start, attributes=attrs,
                    frame_attributes=lambda t: {"facepipe/frame": int(frames[t]), "facepipe/time": float(times[t])},
                    force=force, resume=resume, progress=bar.update, report=samples)
            paths = [p for d in per_frame for p in d.values()]
            info.update(space=space, frames=replay.n_frames, vertex_samples=samples)
            if samples.get("over_limit"):
                w = samples["worst"]
                info.setdefault("notes", []).append(
                    f"{samples['over_limit']} of {samples['samples']} vertex samples of the maps are off by more than "
                    f"{100 * samples['limit']:.0f} % of the detail range (at most {100 * samples['relative']:.2g} %, "
                    f"{'UV' if slots == 'uv' else 'vertex'} {w['slot']} at UV {w['uv'][0]:.4f}, {w['uv'][1]:.4f} "
                    f"in tile {w['tile']}, frame {int(frames[w['frame_index']])}; vertex_samples in --verbose): "
                    f"where the UV layout gives vertices less than a texel each, no map of this size holds every "
                    f"vertex value; a higher --resolution does (and --padding, at island borders)")
        else:
            from facepipe.export.exr_maps import write_wrinkle_maps

            half = False if half is None else half
            P = model.basis_features.shape[0]
            with make_bar(P + 2, "export wrinkle", "file") as bar:
                manifest = write_wrinkle_maps(raster, model, handles["head"], replay.frame_numbers, replay.times, dest,
                                              mode=mode, half=half, attributes=attrs, force=force, resume=resume,
                                              progress=bar.update)
            paths = [dest / n for d in [manifest["constant"]] + [b["maps"] for b in manifest["basis"]]
                     for n in d.values()] + [dest / manifest["coefficients"], dest / "wrinkle.json"]
            info.update(basis_poses=P, frames=replay.n_frames, gate=manifest["gate"])
            # worth a word when it shows (0.1 % of the detail range); wrinkle.json has the figures
            if manifest["gate"].get("active") and manifest["gate"]["relative"] >= 1e-3:
                g = manifest["gate"]
                info.setdefault("notes", []).append(
                    f"the model's novelty gate is not in the blend: at most {g['max_abs']:.3g} "
                    f"({100 * g['relative']:.2g} % of the detail range) from the gated details, at frame "
                    f"{int(replay.frame_numbers[g['worst_frame_index']])} (see wrinkle.json 'gate'); bake with "
                    f"[psd] novelty_tau = 0 for a blend that reproduces the model exactly")
        info["pixel_type"] = "half" if half else "float"
    seconds = time.perf_counter() - t0
    size = _file_bytes(paths)
    info.update(dest=str(dest), files=len(paths), bytes=size, seconds=seconds,
                megabytes_per_second=size / 1e6 / seconds if seconds > 0 else None)
    return info
