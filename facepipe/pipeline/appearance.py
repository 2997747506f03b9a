"""Appearance from footage (Fidaleo et al. 2000, §V): the per-frame classification, and the take's geometry.

Per frame the template points are put on the animated surface through their barycentric
coordinates, projected through the camera (OpenCV's distortion) and sampled bilinearly from the
frame's luminance (:mod:`facepipe.pipeline.appearance_points`); the patches are divided by the
frame's shading (:mod:`facepipe.pipeline.appearance_light`), the five samples are classified
(:func:`facepipe.core.appearance.classify`) and Q measured from the region's rest floor; a
region whose template faces away from the camera, falls outside the image or whose frame is
missing keeps its last value read with most of its template in view (:data:`WELL_SEEN`),
decaying to neutral; a reading that leaves rest for less than ``min_event`` seconds (one or two
frames at 30 Hz) and stays under a layer is image noise, and set back to rest. Each frame's
light (the model's ``stream_light``: the point light's seven values or the nine terms, and the
colour; :func:`facepipe.pipeline.appearance_light.frame_shading`) is part of the result: the
texture's shading comes from it.

The model is built by :mod:`facepipe.pipeline.appearance_build`; a frame's texture is
:mod:`facepipe.pipeline.appearance_texture`.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from facepipe.core import appearance as ap
from facepipe.core.camera import Camera
from facepipe.core.card_motion import moves_along
from facepipe.core.mesh import VertexSelection
from facepipe.errors import InputError
from facepipe.io.appearance_file import AppearanceModel
from facepipe.io.footage import Footage, open_footage, read_frames_of, to_gray
from facepipe.io.npz_file import NPZ_READ_ERRORS, open_npz
from facepipe.parallel import map_blocks, serial_blas, thread_count
from facepipe.pipeline.appearance_light import frame_shading
from facepipe.pipeline.appearance_points import (frame_facing_limits, sample_template_frames, seen_fraction,
                                                 template_point_facing, template_positions)

__all__ = ["classify_frames", "classify_image", "classify_decoded", "classify_chunk", "region_bank",
           "Classification", "FrameReadings", "take_geometry", "read_take_geometry", "TakeGeometry", "WELL_SEEN",
           "examples_at_rest", "check_finite_positions"]




def region_bank(model: AppearanceModel) -> ap.RegionBank:
    """The model's templates for :func:`facepipe.core.appearance.classify_regions`."""
    return ap.RegionBank(model.templates, model.indices, model.weights, model.template_mask, model.shading_orders,
                         model.rest_nuisance, model.template_patches,
                         relative=model.shading_reference == "neutral")


@dataclass
class TakeGeometry:
    """A take's geometry as read once: positions (T, V, 3), frame numbers (T,), its own frame
    times (T,) seconds where it records them (else None), whether the positions are in a camera's
    coordinates (a 2D take's replay; else world positions) and that camera where the replay
    recorded it."""

    positions: np.ndarray
    numbers: np.ndarray
    times: np.ndarray | None = None
    in_camera: bool = False
    camera: Camera | None = None


def read_take_geometry(path, n_vertices: int) -> TakeGeometry:
    """:class:`TakeGeometry` from an .npz (``positions``, optional ``frame`` and ``time``) or a replay
    folder (``positions.npy`` and ``replay.json``; ``video.npz`` for a 2D take's camera)."""
    from facepipe.io.replay_folder import ReplayDir

    path = Path(path)
    times = camera = None
    in_camera = False
    if path.is_dir():
        replay = ReplayDir(path)
        positions, numbers, times = replay.positions, replay.frame_numbers, replay.times
        if positions.shape[1] != n_vertices and (replay.info.get("welded") or {}).get("vertices") == n_vertices:
            # a rig welded along seams ([rig] weld) replayed: its positions in the mesh file's order
            positions = VertexSelection(positions, replay.weld_index())
        in_camera = str(replay.info.get("coordinates", "")).startswith("camera")
        video = replay.video if in_camera else None
        camera = None if video is None else video.camera
    elif path.is_file():
        hint = "positions (T, V, 3) and frame (T,), or a replay folder"
        try:
            with open_npz(path, "a take's geometry", hint) as data:
                positions = np.asarray(data["positions"])
                numbers = np.asarray(data["frame"]) if "frame" in data else np.arange(len(positions))
                times = np.asarray(data["time"], dtype=np.float64) if "time" in data else None
        except NPZ_READ_ERRORS as exc:
            raise InputError(f"not a geometry .npz with 'positions' ({exc})", path=path, hint=hint) from None
    else:
        raise InputError("geometry not found", path=path, hint="an .npz with positions and frame, or a replay folder")
    if positions.ndim != 3 or positions.shape[1:] != (n_vertices, 3):
        raise InputError(f"positions have shape {positions.shape}, the rest mesh has {n_vertices} vertices",
                         path=path, hint="give the geometry of this rig's mesh")
    if path.is_file():  # a replay folder's positions are facepipe's own, and may be larger than memory
        check_finite_positions(positions, numbers, path)
    if times is not None and times.shape != (len(positions),):
        times = None  # not one a frame: the frames' numbers alone say which footage is theirs
    return TakeGeometry(positions, np.asarray(numbers, dtype=np.int64), times, in_camera, camera)


def check_finite_positions(positions: np.ndarray, numbers: np.ndarray, path) -> None:
    """Exit 2 (naming ``path``, the first frame and vertex, and how many frames) where a frame of
    positions (T, V, 3) with frame numbers (T,) holds a non-finite coordinate: a NaN vertex would
    project nowhere and blank the regions and light that use it without a word."""
    bad = ~np.isfinite(positions).all(axis=2)  # (T, V)
    if bad.any():
        row, vertex = (int(i) for i in np.argwhere(bad)[0])
        frames = int(bad.any(axis=1).sum())
        raise InputError(f"frame {int(numbers[row])}: vertex {vertex} is not finite "
                         f"({', '.join(f'{x:g}' for x in positions[row, vertex])})"
                         + (f"; {frames} frames hold such vertices" if frames > 1 else ""), path=path,
                         hint="fill the geometry's gaps (replay the take, whose gaps facepipe fills) or leave "
                              "those frames out of the .npz")


def _read_geometry(path, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions (T, V, 3) and frame numbers (T,) of a take's geometry (:func:`read_take_geometry`)."""
    geometry = read_take_geometry(path, n_vertices)
    return geometry.positions, geometry.numbers


def take_geometry(path, model: AppearanceModel) -> tuple[TakeGeometry, AppearanceModel, str | None]:
    """The geometry of a take to classify (:func:`read_take_geometry`), the model to classify it
    with, and a note or None.

    A 2D take's replay is written in its camera's coordinates (``replay.json``: ``coordinates``)
    and its footage is that camera's: the model classifies it through that camera, its positions
    taken as they are (the model's world-to-camera transform, which is the example footage's, is
    the identity here). The note says so, and where that calibration is not the model's."""
    geometry = read_take_geometry(path, model.n_vertices)
    if not geometry.in_camera:
        return geometry, model, None
    camera = geometry.camera or model.camera  # (a replay without its camera's record: the model's)
    same = (camera.width, camera.height) == (model.camera.width, model.camera.height) and np.allclose(
        camera.matrix, model.camera.matrix) and np.allclose(np.ravel(camera.distortion), np.ravel(model.camera.distortion))
    note = ("the geometry is a 2D take's replay, in its camera's coordinates: classified through that camera"
            + ("" if same else " (not the calibration the model was built with: its footage is that camera's)"))
    return geometry, replace(model, rotation=np.eye(3), translation=np.zeros(3), camera=camera), note


def check_frame_size(image: np.ndarray, camera: Camera, number: int, source) -> None:
    """InputError naming the frame and the footage where an image is not the camera's size."""
    if image.shape[:2] != (camera.height, camera.width):
        raise InputError(f"frame {number} is {image.shape[1]} × {image.shape[0]} pixels, the camera's calibration "
                         f"is for {camera.width} × {camera.height}", path=source,
                         hint="use footage at the calibrated size, or a calibration for this size")


@dataclass
class Classification:
    """Q (T, R) after hold and decay and with brief departures from rest dropped
    (:func:`facepipe.core.appearance.drop_short_events`), raw (T, R) before (NaN where hidden), visible (T, R), frame
    numbers (T,), times (T,), problems: (frame, text) of frames that were skipped; light (T, 12) or
    (T, 10): each frame's grey light as the stream carries it (the model's ``stream_light``) and
    its colour (:func:`frame_colours`) (a
    skipped frame holds the last one fitted, the first ones the first), None for a model without
    light points."""

    names: list
    q: np.ndarray
    raw: np.ndarray
    visible: np.ndarray
    numbers: np.ndarray
    times: np.ndarray
    problems: list
    light: np.ndarray | None = None
    brief: np.ndarray | None = None  # (T, R) readings set back to rest as brief (``min_event``)
    in_view: np.ndarray | None = None  # (T, R) share of each region's stable template points in view (NaN: skipped)
    light_residual: np.ndarray | None = None  # (T,) what each frame's light leaves unexplained (NaN: skipped)


def classify_frames(model: AppearanceModel, footage_source, positions: np.ndarray, numbers: np.ndarray,
                    times: np.ndarray, progress=None, chunk: int = 8, footage_numbers=None) -> Classification:
    """Classify every frame of the geometry (world positions (T, V, 3), frame numbers (T,)) in the
    footage (a path, pattern or folder, or a :class:`~facepipe.io.footage.Footage` already opened):
    each geometry frame's image is the footage's frame of the same number, or of
    ``footage_numbers`` (T,) where given (e.g. :func:`facepipe.io.footage.frames_at`).

    The next frames are read and decoded in a worker thread while these are classified (image
    decoding releases the GIL); ``chunk`` frames are classified at once, all their regions and
    offsets in the same products, a chunk on each of facepipe's threads (:func:`classify_decoded`).
    """
    footage = footage_source if isinstance(footage_source, Footage) else open_footage(footage_source)
    T, Rn = len(numbers), len(model.names)
    raw = np.full((T, Rn), np.nan)
    visible = np.zeros((T, Rn), dtype=bool)
    in_view = np.full((T, Rn), np.nan)
    light = None if model.light_face is None else np.full((T, model.stream_terms + 3), np.nan)
    light_residual = None if model.light_face is None else np.full(T, np.nan)
    problems = []
    bank = region_bank(model)
    rows, grays, images = [], [], []
    batch = chunk * thread_count()  # a chunk for each of facepipe's threads

    def flush():
        if rows:
            readings = classify_decoded(np.stack(grays), model.to_camera(positions[rows]), model, bank, chunk,
                                        images=np.stack(images))
            raw[rows], visible[rows], in_view[rows] = readings.q, readings.visible, readings.in_view
            if light is not None:
                light[rows] = readings.light
                light_residual[rows] = readings.light_residual
            if progress is not None:
                progress(len(rows))
        rows.clear()
        grays.clear()
        images.clear()

    at = numbers if footage_numbers is None else footage_numbers
    for shown, image, problem in _read_ahead(read_frames_of(footage, at)):
        if image is None:
            problems += [(int(numbers[i]), problem) for i in shown]  # said by the take's frame numbers
            if progress is not None:
                progress(len(shown))
            continue
        if image.shape[:2] != (model.camera.height, model.camera.width):
            check_frame_size(image, model.camera, int(at[shown[0]]), footage.source)
        gray = to_gray(image)
        for i in shown:
            rows.append(i)
            grays.append(gray)
            images.append(image[..., :3])
            if len(rows) == batch:
                flush()
    flush()
    # a hidden stretch holds the last reading taken with most of the template in view
    well_seen = visible & (np.nan_to_num(in_view) >= max(WELL_SEEN, model.min_seen))
    held = ap.hold_and_decay(np.nan_to_num(raw), visible, times, model.decay, well_seen)
    q = ap.drop_short_events(held, times, model.min_event)
    return Classification(list(model.names), q, raw, visible, np.asarray(numbers), np.asarray(times), problems,
                          None if light is None else _held(light, WHITE_LIGHT), brief=(held > 0) & (q == 0),
                          in_view=in_view, light_residual=light_residual)


#: A frame whose light leaves more than this many times the example footage's share of its light
#: points' brightness unexplained (:func:`off_face_frames`) has geometry that misses the face in
#: the image. Where the geometry lies on the face a frame reads up to about 6 times the examples'
#: share (another light, the head turned, every region moving at once, measured on rendered
#: takes); geometry of another head pose reads 10 to 30 times it.
OFF_FACE_RATIO = 8.0


def off_face_frames(result: "Classification", model: AppearanceModel) -> dict | None:
    """Whether the take's geometry lies on the face in its footage, frame by frame: each classified
    frame's light residual (``result.light_residual``) against the example footage's
    (``model.light_residual``); None for a model without light points or written before the check.

    Returns {"examples": the examples' residual, "median": the take's, "ratio": their ratio,
    "limit": :data:`OFF_FACE_RATIO`, "off_face": (T,) bool, the frames above it}."""
    if result.light_residual is None or model.light_residual is None or not model.light_residual > 0:
        return None
    read = np.isfinite(result.light_residual)
    ratio = np.where(read, result.light_residual, 0.0) / model.light_residual
    median = float(np.median(result.light_residual[read])) if read.any() else float("nan")
    return {"examples": float(model.light_residual), "median": median, "ratio": median / model.light_residual,
            "limit": OFF_FACE_RATIO, "off_face": read & (ratio > OFF_FACE_RATIO)}


#: A hidden region holds its last reading taken with at least this share of its template's stable
#: points in view — in the image and not hidden by the face (or ``min_seen``, if higher): the frames
#: before a lid closes over an eyeball read what is left of it, and holding that would carry it
#: through the blink. Points turned edge-on do not count against it: a region turning away is read
#: well until it is hidden.
WELL_SEEN = 0.9


#: A uniform white light: what a frame gets when no frame of the take could be classified.
WHITE_LIGHT = np.r_[1.0, np.zeros(8), np.ones(3)]


def _held(rows: np.ndarray, default: np.ndarray) -> np.ndarray:
    """Rows (T, n) with every NaN row (a frame not classified) replaced by the last finite one
    before it, or the first after it at the start; ``default`` (n,) everywhere when none is finite."""
    known = np.isfinite(rows).all(axis=1)
    if not known.any():
        return np.tile(default, (len(rows), 1))
    index = np.maximum.accumulate(np.where(known, np.arange(len(rows)), -1))
    index[index < 0] = int(np.argmax(known))
    return rows[index]


@dataclass
class FrameReadings:
    """What :func:`classify_decoded` reads of frames: Q (F, R), NaN where a region is hidden;
    each region's visibility (F, R); each frame's light as the stream carries it (F, 9) or (F, 7),
    with its colour (F, 12) or (F, 10) where the frames' RGB images were given (None for a model without light points); the
    share of each region's stable template points in view (F, R; :func:`_classify_chunk`); what
    each frame's light leaves unexplained (F,) (:func:`~facepipe.pipeline.appearance_light.frame_light_residuals`;
    None without light points); and how far each reading lies off its region's layer path for its
    Q (F, R; :func:`facepipe.core.appearance.off_path_ratio`)."""

    q: np.ndarray
    visible: np.ndarray
    light: np.ndarray | None
    in_view: np.ndarray
    light_residual: np.ndarray | None = None
    off_path: np.ndarray | None = None


def classify_decoded(grays: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, bank=None,
                     chunk: int = 8, images: np.ndarray | None = None) -> FrameReadings:
    """:func:`classify_chunk` of decoded frames (F, H, W) with their geometry in camera space
    (F, V, 3), ``chunk`` frames at a time on facepipe's threads (:func:`facepipe.parallel.map_blocks`):
    the same numbers as one chunk after another, about 1.5 times the frames a second on two cores
    (most of a chunk's time is in NumPy, which lets the other thread run). ``images``: the frames
    in RGB (F, H, W, 3), for each frame's light colour."""
    bank = region_bank(model) if bank is None else bank
    if len(grays) == 0:
        n = len(model.names)
        light = None if model.light_face is None else np.zeros((0, model.stream_terms + (0 if images is None else 3)))
        return FrameReadings(np.zeros((0, n)), np.zeros((0, n), dtype=bool), light, np.zeros((0, n)),
                             None if light is None else np.zeros(0), np.zeros((0, n)))
    with serial_blas():  # process-wide: entered once here, not by each thread
        parts = map_blocks(lambda i: _classify_chunk(grays[i:i + chunk], camera_positions[i:i + chunk], model, bank,
                                                     None if images is None else images[i:i + chunk]),
                           range(0, len(grays), chunk))
    lit = model.light_face is not None
    return FrameReadings(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                         np.concatenate([p[2] for p in parts]) if lit else None,
                         np.concatenate([p[3] for p in parts]), np.concatenate([p[4] for p in parts]) if lit else None,
                         np.concatenate([p[5] for p in parts]))


def classify_chunk(grays: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, bank=None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Q (F, R) of frames' luminance (F, H, W) with their geometry in camera space (F, V, 3), NaN
    where a region is hidden, and each region's visibility (F, R).

    BLAS runs on one thread here: its products are small (a light fit's 9 × 9, a chunk's
    patches), and OpenBLAS's threads only wait on each other over them, taking CPU time from
    whatever else runs (a classification's CPU time halves)."""
    with serial_blas():
        return _classify_chunk(grays, camera_positions, model, bank)[:2]


def _classify_chunk(grays, camera_positions, model: AppearanceModel, bank, images=None):
    """Q (F, R), visibility (F, R), each frame's light (:func:`frame_shading`; None without light
    points), the share of each region's stable template points in view (F, R): in the image
    and not hidden by the face, however edge-on, what each frame's light leaves unexplained
    (F,) (None without light points), and how far each reading lies off its layer path (F, R)."""
    bank = region_bank(model) if bank is None else bank
    patches, visible, seen, in_view, light, residual = sample_patches(grays, camera_positions, model, images)
    q, visible, off_path = read_patches(patches, visible, seen, model, bank)
    return q, visible, light, in_view, residual, off_path


def read_patches(patches, visible, seen, model: AppearanceModel, bank):
    """Q (F, R) of sampled patches (:func:`sample_patches`) measured from the rest floors (NaN
    where a region is hidden or reads nothing), the visibility (F, R) with the regions that read
    nothing hidden, and how far each reading lies off its layer path (F, R)."""
    q, distance = ap.classify_regions(patches, bank, model.shading, seen, model.min_seen, model.peak_interpolation)
    q = checked_card_motion(q, patches, seen, model)
    visible = visible & np.isfinite(q)
    off_path = np.where(visible, ap.off_path_ratio(q, distance, bank.gaps[:, 0]), np.nan)
    floor = rest_floors(model, off_path)
    if floor is not None:
        q = ap.above_rest(q, floor, model.layer_counts)
    return np.where(visible, q, np.nan), visible, off_path


def checked_card_motion(q: np.ndarray, patches, seen, model: AppearanceModel) -> np.ndarray:
    """Q (F, R) with each card region that has a motion check (``model.card_motion``) read as at
    rest (0) in the frames whose patch (in place, of ``patches`` (F, R, S, size, size) seeing
    ``seen``) did not move along its layers' path (:mod:`facepipe.core.card_motion`: a look
    across the path, a lid narrowing the opening)."""
    if not model.card_motion:
        return q
    q = np.array(q, dtype=np.float64)
    for r, motion in enumerate(model.card_motion):
        if motion is not None:
            own = moves_along(motion.shifts(patches[:, r, 0], seen[:, r, 0]), motion)
            q[:, r] = np.where(own | np.isnan(q[:, r]), q[:, r], 0.0)
    return q


def sample_patches(grays, camera_positions, model: AppearanceModel, images=None):
    """What classification matches, per frame (F, H, W) with its geometry in camera space (F, V,
    3): the template patches (F, R, S, size, size) with each frame's light divided out, each
    region's visibility (F, R), the template points each sample sees (F, R, S, size, size), the
    share of the stable points in view (F, R), each frame's light and what it leaves unexplained
    (None without light points)."""
    points = template_positions(camera_positions, model)
    patches, visible, seen = sample_template_frames(grays, camera_positions, model, points)
    in_view = seen_fraction(seen, model)  # in the image, not hidden by the face (edge-on or not)
    normals = light = residual = None
    if model.light_face is not None:
        shading, normals, light, residual = frame_shading(grays, camera_positions, model, images)
        patches = patches / shading
    if model.min_point_facing > 0:
        seen = seen & (template_point_facing(camera_positions, model, normals, points) > frame_facing_limits(model))
        if model.template_mask is None and model.template_facing is not None:
            # models before the stable points: a point the examples saw edge-on has no template worth matching
            s = model.template_size
            seen &= (model.template_facing > model.min_point_facing).reshape(model.template_facing.shape[:2] + (s, s))
        visible &= seen_fraction(seen, model) >= model.min_seen
    return patches, visible, seen, in_view, light, residual


def examples_at_rest(cfg, numbers: list) -> np.ndarray:
    """(F, R) whether each region is at rest in each example frame (``numbers``): every frame but
    its own layers above the neutral one."""
    return np.array([[n not in set(region.frames[1:]) for region in cfg.regions] for n in numbers])


def rest_floors(model: AppearanceModel, off_path: np.ndarray) -> np.ndarray | None:
    """Each reading's rest floor (F, R) from how far it lies off its layer path (F, R): the
    at-rest examples' readings that hide it (:func:`facepipe.core.appearance.conditional_floor`,
    ``model.rest_tolerance``, ``model.rest_noise``), or the regions' single floors (R,) where the model keeps no such
    readings (built before them, or with ``rest_path_tolerance = 0``); None without a floor."""
    if model.rest_readings is not None and model.rest_tolerance > 0:
        return ap.conditional_floor(off_path, model.rest_readings, model.rest_off_path, model.rest_tolerance,
                                    model.rest_noise)
    return model.rest_floor


def classify_image(gray: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, bank=None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Q (R,) of one frame's luminance (NaN where hidden) and each region's visibility (R,)."""
    q, seen = classify_chunk(gray[None], camera_positions[None], model, bank)
    return q[0], seen[0]


def _read_ahead(frames, depth: int = 4):
    """The items of an iterator, produced up to ``depth`` ahead by a worker thread (which stops
    when the consumer does, e.g. on bad input)."""
    box: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def hand_over(item) -> bool:
        while not stop.is_set():
            try:
                box.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def work():
        try:
            for item in frames:
                if not hand_over(item):
                    return
        except BaseException as exc:  # raised in the consumer
            hand_over(exc)
        hand_over(done)

    worker = threading.Thread(target=work, daemon=True)
    worker.start()
    try:
        while True:
            item = box.get()
            if item is done:
                break
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        worker.join()
