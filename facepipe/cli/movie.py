"""``facepipe preview OUT --movie preview.mp4|.gif``: a replay rendered over time.

Every replayed frame is rendered (:mod:`facepipe.core.render`) and written through imageio
(MP4 by imageio-ffmpeg's bundled ffmpeg, H.264; GIF by Pillow) at the take's frame rate. Panels,
left to right: the large scale (``with_large``), the final surface, and with a truth the truth and
the final surface's error as a heat map on the truth's surface, one colour scale for the whole
movie. The take's frame number (the number ``replay.json`` holds, as ``--frame`` takes it) and
its time are burnt into every frame, so a moment seen in the movie can be looked up in the take.

A 2D take's replay (``video.npz``) is shown through the footage's camera instead, as the still
preview shows it (:mod:`facepipe.cli.video_preview`): the face in the window of the image it moves
in, the tracked landmarks (green) and the replayed face's landmarks (red) over it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.colors import PowerNorm
from PIL import Image, ImageDraw, ImageFont

from facepipe.core.render import PinholeCamera, frame_camera, image_window, pinhole_project, render
from facepipe.errors import InputError
from facepipe.export.common import check_targets
from facepipe.io.atomic import atomic_path
from facepipe.io.outputs import check_output_path
from facepipe.parallel import map_in_order
from facepipe.pipeline.replay import NumpyEvaluator

MOVIE_SUFFIXES = (".mp4", ".gif")
#: H.264 encoders work on blocks: frames are padded to a multiple of this many pixels
BLOCK = 16
LABEL_H = 22  # pixels of the caption strip above the panels
#: bytes a rendered pixel holds while its frame is drawn: depth, triangle, barycentric coordinates, colour
RENDER_BYTES_PER_PIXEL = 64


def check_movie_path(path: Path, force: bool) -> None:
    """InputError for a movie name of another kind, an unwritable place, or an existing file
    without ``force`` (before any rendering)."""
    if path.suffix.lower() not in MOVIE_SUFFIXES:
        raise InputError(f"cannot write a {path.suffix or 'suffix-less'} movie", path=path,
                         hint=f"name it *{' or *'.join(MOVIE_SUFFIXES)}")
    check_output_path(path, kind="file", what="movie")
    check_targets([path], force, False)


def render_movie(replay, model, path, *, truth_path=None, with_large: bool = False, size: int = 360,
                 view: str = "head", force: bool = False, bar=None) -> dict:
    """Render every frame of a replay into a movie (see the module docstring).

    Parameters
    ----------
    replay : facepipe.io.replay_folder.ReplayDir; model : its Model.
    path : .mp4 or .gif, written atomically; not overwritten without ``force``.
    truth_path : optional truth .npz (adds the truth and the error heat map; head view).
    with_large : add the large-scale surface (from large_scale.npy, else evaluated again).
    size : pixel width of one panel.
    view : "head" (head space, the take's head motion taken out) or "camera" (a 2D take).
    bar : a progress bar (``update(n)``), or None.

    Returns
    -------
    dict: frames, first/last frame numbers, fps, panels, width, height, path, and with a truth the
    colour scale's top (``color_max``) and whether it clips (``color_clipped``).
    """
    path = Path(path)
    check_movie_path(path, force)
    fps = replay.fps
    if view == "camera":
        frames = _CameraFrames(replay, model, size)
    else:
        frames = _HeadFrames(replay, model, size, truth_path, with_large)
    summary = {"frames": replay.n_frames, "first_frame": int(replay.frame_numbers[0]),
               "last_frame": int(replay.frame_numbers[-1]), "fps": fps, "panels": frames.panels, "view": view,
               **frames.scale_summary()}
    font = ImageFont.load_default()
    import imageio.v2 as imageio

    with atomic_path(path) as tmp:
        if path.suffix.lower() == ".gif":
            writer = imageio.get_writer(tmp, format="GIF", mode="I", duration=1000.0 / fps, loop=0)
        else:
            writer = imageio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=7,
                                        macro_block_size=1, pixelformat="yuv420p", ffmpeg_log_level="error")
        try:
            # the panels are rendered on facepipe's threads (NumPy lets them run side by side), a few
            # frames ahead of the writer; captions here (a font is not drawn with from two threads)
            for i, panels in enumerate(map_in_order(frames.panels_of, range(replay.n_frames),
                                                    item_bytes=frames.frame_bytes)):
                image = _caption(panels, frames.panels, int(replay.frame_numbers[i]), float(replay.times[i]),
                                 frames.note, font)
                writer.append_data(image)
                if bar is not None:
                    bar.update(1)
        finally:
            writer.close()
    summary.update(path=str(path), width=int(image.shape[1]), height=int(image.shape[0]))
    return summary


def _caption(panels: list[np.ndarray], titles: list[str], frame: int, seconds: float, note: str, font) -> np.ndarray:
    """The panels side by side under a caption strip (the frame number and time, and each panel's
    title) and over a strip with ``note``, if any; padded to whole encoder blocks. (H, W, 3) uint8."""
    h = max(p.shape[0] for p in panels)
    w = sum(p.shape[1] for p in panels)
    H = -(-(h + LABEL_H * (2 if note else 1)) // BLOCK) * BLOCK
    W = -(-w // BLOCK) * BLOCK
    canvas = np.full((H, W, 3), 255, dtype=np.uint8)
    x = 0
    for p in panels:
        canvas[LABEL_H:LABEL_H + p.shape[0], x:x + p.shape[1]] = np.clip(p * 255 + 0.5, 0, 255).astype(np.uint8)
        x += p.shape[1]
    img = Image.fromarray(canvas)
    draw = ImageDraw.Draw(img)
    x = 0
    for k, (p, title) in enumerate(zip(panels, titles)):
        text = f"frame {frame}  {seconds:.2f} s   {title}" if k == 0 else title
        draw.text((x + 4, 5), text, fill=(0, 0, 0), font=font)
        x += p.shape[1]
    if note:
        draw.text((4, LABEL_H + h + 5), note, fill=(60, 60, 60), font=font)
    return np.asarray(img)


class _HeadFrames:
    """Head-space panels of each frame: [large scale,] final [, truth, |final − truth|]."""

    def __init__(self, replay, model, size, truth_path, with_large):
        from facepipe.core.render import view_direction
        from facepipe.pipeline.evaluate import replay_truth, to_head_space

        self.replay, self.model = replay, model
        self.faces = model.triangles.astype(np.int64)
        self.camera = frame_camera(model.rest.astype(np.float64), view_direction(model), width=size)
        handles = replay.handles
        self.keep = handles["head_motion"] == "keep"
        self.R = handles["rotation"].astype(np.float64)
        self.t = handles["translation"].astype(np.float64)
        self.to_head_space = to_head_space
        self.with_large = with_large
        self.evaluator = NumpyEvaluator(model) if with_large and replay.large_scale is None else None
        self.units = model.meta.get("units", "")
        self.truth = None
        self.panels = (["large scale"] if with_large else []) + ["final"]
        self.note = ""
        if truth_path is not None:
            self.truth = replay_truth(truth_path, replay, model.n_vertices)
            self.color_max, self.largest = self._error_scale()
            self.norm = PowerNorm(0.5, 0.0, self.color_max)
            self.cmap = colormaps["YlOrRd"]
            clipped = " (clipped)" if self.largest > self.color_max else ""
            self.panels += ["truth", f"|final - truth|: 0 to {self.color_max:.2g} {self.units}{clipped}"]

    @property
    def frame_bytes(self) -> int:
        """About what drawing one frame's panels holds (for how many frames are drawn at once)."""
        return RENDER_BYTES_PER_PIXEL * self.camera.width * self.camera.height * len(self.panels)

    def _head(self, x, i):
        return self.to_head_space(x, self.R[i], self.t[i]) if self.keep else np.asarray(x, dtype=np.float64)

    def _error(self, i) -> np.ndarray:
        return np.linalg.norm(self._head(self.replay.positions[i], i) - self.truth.head(i, self._head), axis=1)

    def _error_scale(self) -> tuple[float, float]:
        """One colour scale for the movie: the 99.5th percentile of the final error over up to 60
        evenly spaced frames (a still's scale would flicker from frame to frame); and the largest."""
        T = self.replay.n_frames
        errors = [self._error(i) for i in np.unique(np.linspace(0, T - 1, min(T, 60)).round().astype(int))]
        every = np.concatenate(errors)
        return float(np.percentile(every, 99.5)) or 1e-12, float(every.max())

    def scale_summary(self) -> dict:
        if self.truth is None:
            return {}
        return {"color_max": self.color_max, "color_clipped": bool(self.largest > self.color_max)}

    def panels_of(self, i: int) -> list[np.ndarray]:
        final = self._head(self.replay.positions[i], i)
        images = []
        if self.with_large:
            if self.evaluator is None:
                large = self._head(self.replay.large_scale[i], i)
            else:
                _, large = self.evaluator.evaluate(self.replay.handles["head"][i:i + 1].astype(np.float64),
                                                   with_large=True)
                large = large[0]
            images.append(render(large, self.faces, self.camera))
        images.append(render(final, self.faces, self.camera))
        if self.truth is not None:
            truth = self.truth.head(i, self._head)
            images.append(render(truth, self.faces, self.camera))
            colors = self.cmap(self.norm(self._error(i)))[:, :3]
            images.append(render(truth, self.faces, self.camera, colors=colors))
        return images


class _CameraFrames:
    """A 2D take's replay through the footage's camera, landmarks over it (one panel)."""

    def __init__(self, replay, model, size):
        from facepipe.cli.video_preview import camera_coordinates, face_window

        video = replay.video
        if video is None:
            raise InputError("this replay is not of a 2D take (no video.npz): there is no camera to look through",
                             path=replay.path, hint="make the movie without --view camera")
        self.replay, self.video, self.cam = replay, video, video.camera
        self.faces = model.triangles.astype(np.int64)
        self.camera_coordinates = camera_coordinates
        T = replay.n_frames
        sample = np.unique(np.linspace(0, T - 1, min(T, 30)).round().astype(int))
        projected = [pinhole_project(self.cam.matrix, self.cam.distortion, x)
                     for x in camera_coordinates(replay, sample)]
        # the landmarks the lift used (a failed row's placeholders are not where the face is)
        x0, y0, w, h = face_window(np.concatenate(projected + [video.tracked[video.used]]), self.cam.width,
                                   self.cam.height)
        self.scale = size / w
        self.origin = (x0 - 0.5, y0 - 0.5)
        self.panel = PinholeCamera(image_window(self.cam.matrix, x0, y0, self.scale), self.cam.distortion,
                                   int(size), max(1, int(round(h * self.scale))))
        self.panels = ["camera view"]
        self.note = f"green: tracked, red: replayed; footage px {x0:.0f},{y0:.0f}+"

    def scale_summary(self) -> dict:
        return {}

    @property
    def frame_bytes(self) -> int:
        """About what drawing one frame's panel holds (for how many frames are drawn at once)."""
        return RENDER_BYTES_PER_PIXEL * self.panel.width * self.panel.height

    def panels_of(self, i: int) -> list[np.ndarray]:
        x = self.camera_coordinates(self.replay, [i])[0]
        image = render(x, self.faces, self.panel)
        img = Image.fromarray(np.clip(image * 255 + 0.5, 0, 255).astype(np.uint8))
        draw = ImageDraw.Draw(img)

        def to_panel(p):
            return (p - np.asarray(self.origin)) * self.scale - 0.5

        tracked = self.video.tracked[i]
        for u, v in to_panel(tracked[self.video.used[i]]):
            draw.ellipse((u - 4, v - 4, u + 4, v + 4), outline=(30, 150, 30))
        replayed = pinhole_project(self.cam.matrix, self.cam.distortion, x[self.video.vertices])
        for u, v in to_panel(replayed[np.isfinite(replayed).all(axis=1)]):
            draw.ellipse((u - 1.5, v - 1.5, u + 1.5, v + 1.5), fill=(210, 30, 30))
        return [np.asarray(img, dtype=np.float64) / 255.0]


def movie_command(rep, outdir, model_path, movie, *, view: str, truth_path, with_large: bool, size: int,
                  force: bool) -> None:
    """The body of ``facepipe preview OUT --movie PATH``."""
    from facepipe.io.replay_folder import ReplayDir

    path = Path(movie)
    check_movie_path(path, force)  # before anything is read or rendered
    replay = ReplayDir(outdir)
    model = replay.load_model(model_path)
    if view == "auto":
        view = "camera" if replay.video is not None and truth_path is None and not with_large else "head"
    if view == "camera" and (truth_path is not None or with_large):
        raise InputError("--truth and --with-large-scale are drawn in head space, not through the camera",
                         hint="add --view head")
    with rep.bar(replay.n_frames, desc="movie") as bar:
        s = render_movie(replay, model, path, truth_path=truth_path, with_large=with_large, size=size, view=view,
                         force=force, bar=bar)
    clipped = ""
    if "color_max" in s:
        clipped = f"; error colours 0 to {s['color_max']:.3g} {model.meta.get('units', '')}" + \
            (" (clipped: larger errors drawn red)" if s["color_clipped"] else "")
    rep.say(f"wrote {s['path']}: {s['frames']} frames (take frames {s['first_frame']}..{s['last_frame']}) at "
            f"{s['fps']:g} frames/s, {s['width']}x{s['height']} px, panels: {', '.join(p.split(':')[0] for p in s['panels'])}"
            f"{clipped}")
