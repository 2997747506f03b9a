"""The ``textures`` export: a classified take's layered texture, frame by frame, and its Q stream.

Input: a folder written by ``facepipe appearance classify`` (``appearance.csv``: frame, time, Q
per region; ``light.csv``: each frame's light; ``appearance.json``: the appearance model's and the
geometry's paths), or a replay folder it was classified into. Per frame the texture is the
neutral texture with every region's volume looked up trilinearly at its Q
(:func:`facepipe.core.layered_texture.compose_texture`), in the rest mesh's UV layout at the model's
``texture_size`` (the layers' own resolution: ``--resolution`` does not apply). A model that holds
albedo (built with a light fit) gives the texture as the camera saw it: the layered albedo times
the shading of the frame's own geometry under the frame's light
(:func:`facepipe.pipeline.appearance_texture.frame_texture`); ``--layer albedo`` writes the albedo alone,
for a renderer that lights the face itself. The textures are rebuilt from the stream as written
(to four decimals), so what the files show is what a receiver of the stream would render.

Writes ``DEST/frame_NNNN.png`` (16-bit RGB, the footage's values), or ``.exr`` with ``--half`` /
``--float``; where the rest mesh's UV layout uses other UDIM tiles than 1001 (a head's scalp and
neck, or a face laid out on another tile), one file per tile and frame, ``DEST/frame_NNNN.1001.png``,
``frame_NNNN.1002.png`` … (the regions lie on one tile; the others hold their neutral albedo,
shaded as the regions' tile is); ``DEST/appearance.csv`` (the stream) and ``DEST/textures.json`` (regions, layers,
frame rate and the stream's bit rate). Frames are written atomically; existing files are refused
without ``--force`` and kept with ``--resume``.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from facepipe.core.layered_texture import light_bits, stream_bits
from facepipe.errors import InputError
from facepipe.export.common import check_targets, frame_paths, remove_partial_files
from facepipe.export.registry import ExportOptions
from facepipe.io.appearance_file import (STREAM_DECIMALS, format_light, format_stream, load_appearance, read_light,
                                         read_stream)
from facepipe.io.atomic import atomic_path
from facepipe.io.exr import write_exr
from facepipe.parallel import map_in_order, thread_count
from facepipe.pipeline.appearance import take_geometry
from facepipe.pipeline.appearance_points import texel_map
from facepipe.pipeline.appearance_texture import frame_texture

__all__ = ["export_textures", "write_texture"]


def write_texture(path: Path, texture: np.ndarray, half: bool | None) -> None:
    """One texture (H, W, 3), values in [0, 1]: 16-bit PNG (``half`` None) or EXR (half / float)."""
    if path.suffix == ".exr":
        write_exr(path, texture, half=bool(half), attributes={"facepipe/content": "layered texture"})
        return
    pixels = np.round(np.clip(texture, 0.0, 1.0) * 65535.0).astype(np.uint16)
    with atomic_path(path) as tmp:
        # OpenCV writes 16-bit RGB PNG (Pillow does not); its channel order is BGR
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(pixels[..., ::-1])):
            raise OSError(f"could not write {path}")


def _frame_rate(times: np.ndarray, numbers: np.ndarray, source: Path) -> float:
    steps = np.diff(times)
    if len(steps) == 0:
        return 30.0
    if not (steps > 0).all():
        k = int(np.argmax(steps <= 0)) + 1
        raise InputError(f"frame {int(numbers[k])}: its time does not increase", path=source / "appearance.csv",
                         hint="classify the footage again (its frame numbers must increase)")
    return round(float(1.0 / np.median(steps)), 3)  # the times are written to microseconds


def export_textures(replay, dest: Path, options: ExportOptions) -> tuple[list[Path], dict]:
    """The ``textures`` format's exporter (``replay``: the classified folder as a ReplayDir)."""
    source = Path(replay.path)
    info, numbers, times, q = read_stream(source)
    model_path = Path(options.model_path) if options.model_path else Path(info["model"])
    model = load_appearance(model_path)
    if list(model.names) != list(info["regions"]):
        raise InputError(f"the stream's regions {info['regions']} are not the model's {list(model.names)}",
                         path=model_path, hint="give the appearance model the footage was classified with (-m)")
    counts = np.asarray(model.layer_counts)
    outside = (q < 0) | (q > counts - 1) | ~np.isfinite(q)
    if outside.any():
        t, r = np.argwhere(outside)[0]
        raise InputError(f"frame {int(numbers[t])}: Q of {model.names[r]} is {q[t, r]}, outside 0..{counts[r] - 1}",
                         path=source / "appearance.csv", hint="classify the footage again with this model")
    if options.layer not in ("final", "albedo"):
        raise InputError(f"--layer {options.layer} is not a layer of textures", path=source,
                         hint="textures: --layer final (as the camera saw the face) or albedo (the layers' albedo)")
    fps = _frame_rate(times, numbers, source)
    light = read_light(source, numbers)
    shading, camera_positions, notes = _frame_shading(model, info, numbers, light, options.layer)
    suffix = ".png" if options.half is None else ".exr"
    tiles = model.all_tiles
    # the first tile alone: frame_0001.png; else the UDIM convention, frame_0001.1001.png, frame_0001.1002.png
    udim = tiles != [1001]
    by_tile = {t: frame_paths(dest, len(numbers), options.start, f".{t}{suffix}" if udim else suffix) for t in tiles}
    paths = [by_tile[t][i] for i in range(len(numbers)) for t in tiles]
    csv, light_csv, summary = dest / "appearance.csv", dest / "light.csv", dest / "textures.json"
    streams = [csv] + ([light_csv] if light is not None else [])
    check_targets(paths + streams + [summary], options.force, options.resume, folder=dest)
    dest.mkdir(parents=True, exist_ok=True)
    if options.resume:
        remove_partial_files(paths + streams + [summary])
    with atomic_path(csv) as tmp:
        Path(tmp).write_text(format_stream(model.names, numbers, times, q))
    if light is not None:
        with atomic_path(light_csv) as tmp:
            Path(tmp).write_text(format_light(numbers, times, light))
    step = 10.0 ** -STREAM_DECIMALS
    region_bits = stream_bits(counts, step)
    frame_light_bits = light_bits(step, light.shape[1]) if light is not None else 0
    bits = int(region_bits.sum()) + frame_light_bits
    written = 0
    size = model.neutral.shape[0]
    texels = {t: texel_map(model.corner_uv, size, t) for t in tiles} if camera_positions else {}

    def write_frame(i: int) -> int:
        todo = [t for t in tiles if not (options.resume and by_tile[t][i].exists())]
        where = camera_positions(i) if camera_positions and todo else None
        for t in todo:
            texture = frame_texture(model, q[i], where, None if where is None else light[i], texels.get(t), t)
            write_texture(by_tile[t][i], texture, options.half)
        return len(todo)

    # frames on facepipe's threads (at the usual 2K texture NumPy, the encoders and the writes let
    # go of Python's lock: twice the frames a second on two cores), as many under way as threads;
    # a tile's texture and its shading's temporaries are a few (size², 3) float64 arrays
    frame_bytes = 4 * 3 * 8 * size * size
    with options.make_bar(len(numbers), "export textures") as bar:
        for count in map_in_order(write_frame, range(len(numbers)), ahead=thread_count(), item_bytes=frame_bytes):
            written += count
            bar.update(1)
    digits = len(by_tile[tiles[0]][0].name.split(".")[0]) - len("frame_")
    details = {"frames": len(numbers), "written": written, "tiles": tiles,
               "files": "frame_" + "#" * digits + (".<UDIM>" if udim else "") + suffix,
               # file number start + i holds appearance.csv's row i: the take's frame numbers[i]
               "first_file": int(options.start), "first_frame": int(numbers[0]),
               "regions": list(model.names),
               "layers": counts.tolist(), "texture_size": int(size),
               "pixels": "png16" if suffix == ".png" else ("exr half" if options.half else "exr float"),
               "shading": shading, "fps": fps, "bits_per_region": region_bits.tolist(),
               "light_bits_per_frame": frame_light_bits, "bits_per_frame": bits,
               "bit_rate_kbit_s": bits * fps / 1000.0, "stream": str(csv),
               "light_stream": str(light_csv) if light is not None else None, "model": str(model_path.resolve())}
    with atomic_path(summary) as tmp:
        Path(tmp).write_text(json.dumps(details, indent=1))
    light_part = f" + light {frame_light_bits}" if frame_light_bits else ""
    details["notes"] = notes + [f"stream: {len(model.names)} regions' Q{light_part}, {bits} bits a frame at "
                                f"{fps:g} Hz = {details['bit_rate_kbit_s']:.2f} kbit/s (textures.json)"]
    return paths + streams + [summary], details


def _frame_shading(model, info: dict, numbers: np.ndarray, light, layer: str):
    """What the textures hold (textures.json's ``shading``: ``frame``, the layered albedo times each
    frame's shading, its geometry under its light; ``albedo``, the layered albedo alone; ``footage``,
    the layers as the footage showed them, a model built without a light fit), for ``frame`` a
    function of the stream's row giving the frame's positions in camera space (one frame at a time:
    a long take's would not fit at once), else None, and notes. A model that holds albedo needs
    the stream's light and the classified geometry for ``frame``; without either it writes the
    albedo, and says why."""
    if not model.albedo:
        if layer == "albedo":
            raise InputError("--layer albedo: this appearance model holds the footage's values, shading included",
                             path=info["model"], hint="build the model again (its light fit on) for albedo layers")
        return "footage", None, []
    if layer == "albedo":
        return "albedo", None, []
    if light is None:
        return "albedo", None, ["the folder has no light.csv (classified before facepipe wrote it): the textures "
                                "are the layered albedo, unshaded; classify again for shaded ones"]
    geometry_path = info.get("geometry")
    if not geometry_path or not Path(geometry_path).exists():
        return "albedo", None, [f"the classified geometry ({geometry_path}) is not there: the textures are the "
                                "layered albedo, unshaded"]
    geometry, model_for_take, _ = take_geometry(geometry_path, model)
    if not np.array_equal(np.asarray(geometry.numbers), np.asarray(numbers)):
        raise InputError("the classified geometry's frames are not the stream's", path=geometry_path,
                         hint="classify the footage again with this geometry")
    return "frame", lambda t: model_for_take.to_camera(geometry.positions[t]), []
