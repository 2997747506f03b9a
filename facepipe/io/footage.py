"""Footage: image sequences (PNG, JPEG, TIFF, EXR) and video files, read frame by frame.

A source is

* a folder: its image files, numbered by the last run of digits in their names (in name
  order when none has digits);
* a pattern with a printf field, ``frames/frame_%04d.png`` (``%d`` for unpadded numbers):
  every file it matches, numbered by the field;
* a video file (``.mp4``, ``.mov``, ``.avi``, ``.mkv``, ``.webm``, ``.m4v``), read through
  imageio's ffmpeg plugin, frames numbered from 0.

Frames are returned as float RGB in [0, 1] (8- and 16-bit integers scaled, EXR as stored). A
frame that cannot be read is reported by :func:`read_frames` and skipped, never raised.
"""

from __future__ import annotations

import importlib.util
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from facepipe.errors import InputError

__all__ = ["Footage", "open_footage", "read_frames", "to_gray", "IMAGE_SUFFIXES", "VIDEO_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp")
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v")
_PRINTF = re.compile(r"%(0?\d*)d")
_DIGITS = re.compile(r"(\d+)(?!.*\d)")
_HINT = ("give a folder of images, a pattern such as frames/frame_%04d.png, or a video file "
         f"({', '.join(VIDEO_SUFFIXES)})")


@dataclass
class Footage:
    """An opened source: frame numbers and where each frame comes from.

    source : what was given; kind : "images" or "video"; numbers : (N,) int64 frame numbers;
    paths : per frame its image file (images), empty for a video; fps : a video's frame rate
    where its container says it (None for images).
    """

    source: str
    kind: str
    numbers: np.ndarray
    paths: list = field(default_factory=list)
    fps: float | None = None

    def __len__(self) -> int:
        return len(self.numbers)


def open_footage(source) -> Footage:
    """Find the frames of a folder, printf pattern or video file (see the module docstring).

    Raises
    ------
    InputError
        Nothing there, no frames in it, a frame number given twice, a video that cannot be opened.
    """
    text = str(source)
    path = Path(text)
    if _PRINTF.search(path.name):
        return _pattern(text, path)
    if path.is_dir():
        return _folder(text, path)
    if path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES:
        return _video(text, path)
    if path.is_file():
        raise InputError(f"not footage: {path.suffix or 'no suffix'} is neither an image sequence nor a video",
                         path=path, hint=_HINT)
    raise InputError("footage not found", path=path, hint=_HINT)


def _pattern(text: str, path: Path) -> Footage:
    m = _PRINTF.search(path.name)
    pad = m.group(1)
    digits = rf"\d{{{int(pad)},}}" if pad.startswith("0") and pad != "0" else r"\d+"
    regex = re.compile("^" + re.escape(path.name[:m.start()]) + f"({digits})" + re.escape(path.name[m.end():]) + "$")
    folder = path.parent
    if not folder.is_dir():
        raise InputError("the pattern's folder does not exist", path=folder, hint=_HINT)
    found = sorted((int(mm.group(1)), folder / name) for name in (p.name for p in folder.iterdir())
                   if (mm := regex.match(name)))
    if not found:
        raise InputError(f"no file matches the pattern {path.name}", path=folder, hint=_HINT)
    return _numbered(text, found)


def _folder(text: str, path: Path) -> Footage:
    files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not files:
        raise InputError("no image files in this folder", path=path, hint=_HINT)
    numbers = [_DIGITS.search(p.stem) for p in files]
    if all(numbers):
        return _numbered(text, sorted((int(m.group(1)), p) for m, p in zip(numbers, files)))
    return _numbered(text, list(enumerate(files)))


def _numbered(text: str, found: list) -> Footage:
    numbers = np.array([n for n, _ in found], dtype=np.int64)
    twice = numbers[1:][numbers[1:] == numbers[:-1]]
    if twice.size:
        clash = [str(p) for n, p in found if n == twice[0]]
        raise InputError(f"frame {int(twice[0])} is given by more than one file: {', '.join(clash)}", path=text,
                         hint="keep one image per frame number")
    return Footage(text, "images", numbers, [p for _, p in found])


def _video_reason(exc: Exception) -> str:
    """What went wrong with a video, in a line: ffmpeg's own last error lines, without the build
    banner imageio passes along with them."""
    text = str(exc)
    head, _, stderr = text.partition("=== stderr ===")
    errors = [line.strip() for line in stderr.splitlines()
              if line.strip() and not line.startswith((" ", "\t")) and not line.startswith("ffmpeg version")]
    return "; ".join(errors[-2:]) if errors else " ".join(head.split())


def _video_hint() -> str:
    if importlib.util.find_spec("imageio_ffmpeg") is None:
        return "install imageio-ffmpeg (pip install imageio-ffmpeg), which reads videos"
    return "check that the file plays (a damaged or cut-short video, or not a video), or give its frames as images"


def _video(text: str, path: Path) -> Footage:
    try:
        props = iio.improps(path)
        count = int(props.n_images) if props.n_images and np.isfinite(props.n_images) else 0
    except Exception as exc:  # imageio raises many kinds for unreadable videos
        raise InputError(f"cannot open the video ({_video_reason(exc)})", path=path, hint=_video_hint()) from None
    if count <= 0:  # some containers do not say: count by reading
        try:
            count = sum(1 for _ in iio.imiter(path))
        except Exception as exc:
            raise InputError(f"cannot read the video ({_video_reason(exc)})", path=path, hint=_video_hint()) from None
    try:
        fps = float(iio.immeta(path).get("fps") or 0.0)
    except Exception:  # noqa: BLE001 - a container without the rate: frames by number only
        fps = 0.0
    return Footage(text, "video", np.arange(count, dtype=np.int64), fps=fps if np.isfinite(fps) and fps > 0 else None)


def frames_at(footage: Footage, numbers: np.ndarray, times: np.ndarray | None) -> tuple[np.ndarray, str | None]:
    """The footage's frame for each frame of a take (numbers (T,), and its times (T,) seconds where
    the take records its own), and a note where times decided.

    Trackers number frames from 1 (OpenFace, of a video or of an image sequence), a video counts
    from 0, image files carry numbers of their own; the times a tracker writes start at the
    footage's first frame. So: a video's frame at each time (index = round(time × its rate)); an
    image sequence's frame of the same number where it has every one, else the image at each time
    (its k-th image at k / the take's rate) where the take's times fall on its images; otherwise
    by number (a frame the footage lacks is reported and skipped by the caller)."""
    numbers = np.asarray(numbers, dtype=np.int64)
    if times is None or len(numbers) == 0:
        return numbers, None
    times = np.asarray(times, dtype=np.float64)
    if footage.kind == "video":
        rate = footage.fps
    elif np.isin(numbers, footage.numbers).all():
        return numbers, None
    else:
        steps = np.diff(times)
        rate = 1.0 / float(np.median(steps)) if len(steps) and np.median(steps) > 0 else None
    if rate is None:
        return numbers, None
    index = np.rint(times * rate).astype(np.int64)
    if index.min() < 0 or index.max() >= len(footage):
        return numbers, None
    at = footage.numbers[index]
    if np.array_equal(at, numbers):
        return numbers, None
    what = f"the video's frames, at its {rate:g} frames/s" if footage.kind == "video" else \
        f"the images in order, at the take's {rate:g} frames/s"
    return at, (f"{what}, matched to the take's by time (take frame {int(numbers[0])} is footage frame "
                f"{int(at[0])})")


def _as_float(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype == np.uint8:
        out = image.astype(np.float32) / 255.0
    elif image.dtype == np.uint16:
        out = image.astype(np.float32) / 65535.0
    else:
        out = image.astype(np.float32)
    if out.ndim == 2:
        out = out[..., None]
    if out.shape[-1] < 3:  # grey, or grey and alpha: the grey as RGB (the alpha left out as for RGBA)
        out = np.repeat(out[..., :1], 3, axis=-1)
    return out[..., :3]


def _read_image(path: Path) -> np.ndarray:
    if path.suffix.lower() == ".exr":
        from facepipe.io.exr import read_exr  # lazily: OpenEXR only for EXR footage

        return _as_float(read_exr(path)[0])
    return _as_float(iio.imread(path))


def read_frames(footage: Footage, wanted=None):
    """Yield (frame number, image (H, W, 3) float32 or None, problem or None) for every frame of
    ``wanted`` (frame numbers; default all) in order; a frame absent from the footage or that
    cannot be read comes with image None and the reason."""
    numbers = footage.numbers if wanted is None else np.asarray(wanted, dtype=np.int64)
    if footage.kind == "video":
        yield from _video_frames(footage, numbers)
        return
    where = {int(n): p for n, p in zip(footage.numbers, footage.paths)}
    for n in numbers:
        p = where.get(int(n))
        if p is None:
            yield int(n), None, "no image for this frame"
            continue
        try:
            yield int(n), _read_image(p), None
        except Exception as exc:  # a truncated or corrupt file: report it, go on
            yield int(n), None, f"{p.name} cannot be read ({type(exc).__name__}: {exc})"


def read_frames_of(footage: Footage, at) -> Iterator[tuple[list, np.ndarray | None, str | None]]:
    """Yield (rows, image or None, problem or None): each footage frame of ``at`` (T,) (the
    footage's frame for each row of a take, e.g. :func:`frames_at`) read once, in order, with the
    rows it shows (several where the take is faster than the footage)."""
    rows_of: dict = {}
    for i, n in enumerate(np.asarray(at, dtype=np.int64).tolist()):
        rows_of.setdefault(n, []).append(i)
    for n, image, problem in read_frames(footage, list(rows_of)):
        yield rows_of[n], image, problem


def _video_frames(footage: Footage, numbers: np.ndarray):
    """The video's frames of ``numbers`` in that order, decoded as a stream: one frame held at a
    time (a long HD take does not fit in memory whole); a number before the last one read starts
    the decoding again from the first frame."""
    decoded, at, image, problem = None, -1, None, None
    try:
        for n in (int(n) for n in numbers):
            if n < 0:
                yield n, None, "before the start of the video"
                continue
            if n < at:  # backwards: from the start again
                _close(decoded)
                decoded, at, image, problem = None, -1, None, None
            if decoded is None:
                decoded = iter(iio.imiter(footage.source))
            while at < n and problem is None:
                try:
                    image = next(decoded)
                    at += 1
                except StopIteration:
                    problem = "beyond the end of the video"
                except Exception as exc:  # noqa: BLE001 - a damaged tail: the frames before it were given
                    problem = f"video ends unreadably ({type(exc).__name__})"
            if at == n:
                yield n, _as_float(image), None
            else:
                yield n, None, problem
    finally:
        _close(decoded)  # the decoder's process, also when the caller stops early


def _close(decoded) -> None:
    if decoded is not None and hasattr(decoded, "close"):
        decoded.close()


def to_gray(image: np.ndarray) -> np.ndarray:
    """Luminance (Rec. 709 weights) of an RGB image (H, W, 3)."""
    return image[..., :3] @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
