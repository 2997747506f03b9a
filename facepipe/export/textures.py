"""The ``textures`` export: a classified take's layered texture, frame by frame, and its Q stream.

Input: a folder written by ``facepipe appearance classify`` (``appearance.csv``: frame, time, Q
per region; ``appearance.json``: the appearance model's path), or a replay folder it was
classified into. Per frame the texture is the neutral texture with every region's volume looked
up trilinearly at its Q (:func:`facepipe.core.appearance.compose_texture`), in the rest mesh's UV
layout at the model's ``texture_size`` (the layers' own resolution: ``--resolution`` does not
apply). The textures are rebuilt from the stream as written (Q to four decimals), so what the
files show is what a receiver of the stream would render.

Writes ``DEST/frame_NNNN.png`` (16-bit RGB, the footage's values), or ``.exr`` with ``--half`` /
``--float``; ``DEST/appearance.csv`` (the stream) and ``DEST/textures.json`` (regions, layers,
frame rate and the stream's bit rate). Frames are written atomically; existing files are refused
without ``--force`` and kept with ``--resume``.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from facepipe.core.appearance import compose_texture, stream_bits
from facepipe.errors import InputError
from facepipe.export.common import check_targets, frame_paths, remove_partial_files
from facepipe.export.registry import ExportOptions
from facepipe.io.appearance_file import STREAM_DECIMALS, format_stream, load_appearance, read_stream
from facepipe.io.atomic import atomic_path
from facepipe.io.exr import write_exr

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
    fps = _frame_rate(times, numbers, source)
    suffix = ".png" if options.half is None else ".exr"
    paths = frame_paths(dest, len(numbers), options.start, suffix)
    csv, summary = dest / "appearance.csv", dest / "textures.json"
    check_targets(paths + [csv, summary], options.force, options.resume, folder=dest)
    dest.mkdir(parents=True, exist_ok=True)
    if options.resume:
        remove_partial_files(paths + [csv, summary])
    with atomic_path(csv) as tmp:
        Path(tmp).write_text(format_stream(model.names, numbers, times, q))
    region_bits = stream_bits(counts, 10.0 ** -STREAM_DECIMALS)
    bits = int(region_bits.sum())
    written = 0
    with options.make_bar(len(paths), "export textures") as bar:
        for t, path in enumerate(paths):
            if not (options.resume and path.exists()):
                texture = compose_texture(model.neutral, model.volumes, model.alphas, model.boxes, q[t])
                write_texture(path, texture, options.half)
                written += 1
            bar.update(1)
    details = {"frames": len(paths), "written": written, "regions": list(model.names),
               "layers": counts.tolist(), "texture_size": int(model.neutral.shape[0]),
               "pixels": "png16" if suffix == ".png" else ("exr half" if options.half else "exr float"),
               "fps": fps, "bits_per_region": region_bits.tolist(), "bits_per_frame": bits, "bit_rate_kbit_s": bits * fps / 1000.0,
               "stream": str(csv), "model": str(model_path.resolve())}
    with atomic_path(summary) as tmp:
        Path(tmp).write_text(json.dumps(details, indent=1))
    details["notes"] = [f"Q stream: {len(model.names)} regions, {bits} bits a frame at {fps:g} Hz = "
                        f"{details['bit_rate_kbit_s']:.2f} kbit/s (textures.json)"]
    return paths + [csv, summary], details
