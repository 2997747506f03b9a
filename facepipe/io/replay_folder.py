"""A replay output folder as exporters read it: positions, frame times, handles, model.

``facepipe replay`` writes ``positions.npy`` (T × V × 3 float32), ``replay.json`` (frame
numbers, times, the model's path), ``handles.npz`` (the clean head-space handles and the
head motion), optionally ``large_scale.npy``, and for a 2D take ``video.npz`` (the camera,
landmark map and tracked points: :mod:`facepipe.io.video_record`). From the handles any layer
of the model can be evaluated again (the large-scale shell, the details in local frames)
without replaying the take. Every read is validated: a missing or inconsistent file is an InputError naming it.
"""

from __future__ import annotations

import json
from functools import cached_property
from pathlib import Path

import numpy as np

from facepipe.errors import InputError
from facepipe.io.model_file import Model, load_model
from facepipe.io.video_record import VideoRecord, read_video_record

# a frame rate is "uniform" when every frame interval is within this fraction of the median
_UNIFORM_TOLERANCE = 0.01


class ReplayDir:
    """The outputs of one ``facepipe replay`` run.

    Parameters
    ----------
    path : the replay's output folder.

    Example
    -------
    >>> r = ReplayDir("out")                        # doctest: +SKIP
    >>> r.positions.shape, r.fps                    # doctest: +SKIP
    ((120, 11248, 3), 30.0)
    """

    def __init__(self, path):
        self.path = Path(path)
        if not self.path.is_dir():
            raise InputError("no such replay folder", path=self.path,
                             hint="give the folder written by 'facepipe replay ... -o FOLDER'")
        self._weld_indices: dict = {}  # model path → its weld_index (:meth:`weld_index`)

    @cached_property
    def info(self) -> dict:
        """replay.json as a dict."""
        path = self.path / "replay.json"
        if not path.is_file():
            raise InputError("no replay.json here", path=self.path, hint="give the folder written by 'facepipe replay'")
        try:
            info = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise InputError(f"replay.json is not valid JSON: {exc}", path=path) from None
        for key in ("frame_numbers", "times"):
            if not isinstance(info.get(key), list):
                raise InputError(f"replay.json has no '{key}' list", path=path,
                                 hint="replay the take again with this facepipe version")
        if len(info["frame_numbers"]) != len(info["times"]):
            raise InputError("replay.json has different numbers of frame numbers and times", path=path)
        return info

    @property
    def frame_numbers(self) -> np.ndarray:
        """(T,) int64 frame numbers of the take."""
        return np.asarray(self.info["frame_numbers"], dtype=np.int64)

    @property
    def times(self) -> np.ndarray:
        """(T,) float64 seconds."""
        return np.asarray(self.info["times"], dtype=np.float64)

    @property
    def n_frames(self) -> int:
        return len(self.info["frame_numbers"])

    def _array(self, name: str, required: bool = True, hint: str = "run 'facepipe replay' again"):
        path = self.path / name
        if not path.is_file():
            if not required:
                return None
            raise InputError(f"no {name} here", path=self.path, hint=hint)
        try:
            arr = np.load(path, mmap_mode="r")
        except Exception as exc:  # truncated header, not an npy file
            raise InputError(f"cannot read {name}: {exc}", path=path, hint=hint) from None
        if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] != self.n_frames:
            raise InputError(f"{name} has shape {arr.shape}, expected ({self.n_frames}, vertices, 3) for the "
                             f"{self.n_frames} frames of replay.json", path=path, hint=hint)
        return arr

    @cached_property
    def positions(self) -> np.ndarray:
        """(T, V, 3) float32 memmap of the final positions (the take's space)."""
        return self._array("positions.npy")

    @cached_property
    def large_scale(self):
        """(T, V, 3) float32 memmap of the large-scale positions, or None when not saved. A mesh cache
        replayed as a take without ``--save-large-scale`` has the cache itself as its large scale:
        read back from it, frames when indexed (:class:`_CacheSurface`)."""
        stored = self._array("large_scale.npy", required=False)
        if stored is None and self.large_scale_from_cache:
            return _CacheSurface.of(self)
        return stored

    def layer(self, name: str) -> np.ndarray:
        """Positions of a layer: "final" (positions.npy), "large" (large_scale.npy) or "details"
        (final − large: the fine-scale displacements alone, as vectors in the replay's space)."""
        if name == "final":
            return self.positions
        if name == "large":
            large = self.large_scale
            if large is None:
                raise InputError("this replay has no large_scale.npy", path=self.path,
                                 hint="replay the take with --save-large-scale to export the large-scale layer")
            return large
        if name == "details":
            return _Difference(self.positions, self.layer("large"))
        raise InputError(f"--layer {name} is not a layer of a replay's surface", path=self.path,
                         hint="final, large or details (albedo is a layer of --format textures)")

    @property
    def large_scale_from_cache(self) -> bool:
        """True for a mesh cache replayed with ``--large-scale take``: its large scale is the cache's
        surface, which the model cannot evaluate again from the handles (use the stored layers)."""
        return (self.info.get("cache") or {}).get("large_scale") == "take"

    @cached_property
    def handles(self) -> dict:
        """handles.npz: ``head`` (T, H, 3), ``rotation`` (T, 3, 3), ``translation`` (T, 3), ``head_motion``."""
        path = self.path / "handles.npz"
        hint = "replay the take again with this facepipe version (it writes handles.npz)"
        if not path.is_file():
            raise InputError("no handles.npz here: the model layers cannot be evaluated again", path=self.path,
                             hint=hint)
        try:
            with np.load(path, allow_pickle=False) as data:
                out = {k: data[k] for k in data.files}
        except Exception as exc:
            raise InputError(f"cannot read handles.npz: {exc}", path=path, hint=hint) from None
        T = self.n_frames
        for key, tail in (("head", None), ("rotation", (3, 3)), ("translation", (3,))):
            a = out.get(key)
            if a is None or a.shape[0] != T or (tail is not None and a.shape[1:] != tail):
                raise InputError(f"handles.npz: '{key}' is missing or does not have {T} frames", path=path, hint=hint)
        if not np.isfinite(out["head"]).all():
            t = int(np.flatnonzero(~np.isfinite(out["head"]).all(axis=(1, 2)))[0])
            raise InputError(f"handles.npz: frame {int(self.frame_numbers[t])} has non-finite handles", path=path)
        out["head_motion"] = str(out.get("head_motion", "keep"))
        return out

    @cached_property
    def video(self) -> VideoRecord | None:
        """video.npz of a 2D take's replay (camera, landmark map, tracked points), else None."""
        return read_video_record(self.path, self.n_frames, self.positions.shape[1])

    def model_path(self, override=None) -> Path:
        """The model to use: ``override``, else the one replay.json names, looked for as stored
        (absolute; an older replay's relative path from the working directory), relative to this folder
        (``model_relative``), and an older replay's relative path from this folder and each folder
        above it; the first that exists (the stored path when none does)."""
        if override:
            return Path(override)
        name = self.info.get("model")
        if not name:
            raise InputError("replay.json does not name its model", path=self.path / "replay.json",
                             hint="pass the model with -m MODEL.npz")
        candidates = [Path(name)]
        if self.info.get("model_relative"):
            # resolved as the system opens it, so messages name the file without "folder/../"
            candidates.insert(0, (self.path / self.info["model_relative"]).resolve())
        if not Path(name).is_absolute():
            # an older replay stored the path relative to where it ran, which is most often the
            # replay folder or one of the folders above it
            here = self.path.resolve()
            candidates += [folder / name for folder in (here, *here.parents)]
        return next((p for p in candidates if p.is_file()), Path(name))

    def weld_index(self, override=None) -> np.ndarray | None:
        """The model's ``weld_index`` where the replayed rig was welded along seams (``[rig] weld``:
        the mesh file's vertex order, for what other tools read or give in it), else None; the model
        is read only then, once for each model asked (eval may need it for the truth and the range)."""
        if not self.info.get("welded"):
            return None
        key = str(self.model_path(override))
        if key not in self._weld_indices:
            self._weld_indices[key] = self.load_model(override).weld_index
        return self._weld_indices[key]

    def load_model(self, override=None) -> Model:
        """The model of this replay, checked against the positions' vertex count."""
        path = self.model_path(override)
        if not path.is_file():
            raise InputError("the model this replay names is not there (looked for it as stored in replay.json, "
                             "relative to the replay folder and to the working directory)", path=path,
                             hint="pass the model used for the replay with -m MODEL.npz")
        model = load_model(path)
        V = self.positions.shape[1]
        if model.n_vertices != V:
            raise InputError(f"the model has {model.n_vertices} vertices, the replay's positions {V}", path=path,
                             hint="pass the model used for this replay with -m MODEL.npz")
        return model

    @property
    def fps(self) -> float:
        """Frames per second of the take (from the replay's frame times)."""
        return frame_rate(self.times)


class _CacheSurface:
    """The large scale of a mesh cache replayed as a take, read back from the cache: its rows of the
    replay's frames in the rig's units (the replay's unit scale), moved into head space where the
    replay removed the head motion. (T, V, 3) float32 frames, read when indexed."""

    def __init__(self, positions, rows: np.ndarray, scale: float, rotation=None, translation=None):
        self.positions, self.rows, self.scale = positions, rows, float(scale)
        self.rotation, self.translation = rotation, translation
        self.shape, self.ndim, self.dtype = (len(rows), positions.shape[1], 3), 3, np.dtype(np.float32)

    @classmethod
    def of(cls, replay: "ReplayDir") -> "_CacheSurface":
        from facepipe.mocap.registry import mesh_cache_format

        cache_info = replay.info["cache"]
        source = cache_info.get("source") or {}
        path = Path(source.get("path") or replay.info.get("take", ""))
        hint = ("put the cache back where the replay read it, or replay the take with --save-large-scale to keep "
                "its large scale in the replay folder")
        fmt = mesh_cache_format(path)
        if fmt is None or (not path.exists() and fmt.name != "obj-sequence"):
            raise InputError("this replay's large scale is its mesh cache, which is not there any more", path=path,
                             hint=hint)
        if path.is_file() and source.get("size") is not None:
            stat = path.stat()
            if (stat.st_size, stat.st_mtime_ns) != (source["size"], source["mtime_ns"]):
                raise InputError("the mesh cache has changed since the replay: its large scale cannot be read "
                                 "back from it", path=path, hint=hint)
        V = replay.positions.shape[1]
        cache = fmt.reader(path, cache_info.get("fps"), **({"n_vertices": V} if fmt.name == "usd" else {}))
        row_of = {int(f): i for i, f in enumerate(cache.frames)}
        missing = [int(f) for f in replay.frame_numbers if int(f) not in row_of]
        if cache.n_vertices != V or missing:
            raise InputError("the mesh cache no longer matches the replay (" + (
                f"frame {missing[0]} is not in it" if missing else f"{cache.n_vertices} vertices, not {V}") + ")",
                path=path, hint=hint)
        rows = np.array([row_of[int(f)] for f in replay.frame_numbers], dtype=np.int64)
        R = t = None
        if replay.info.get("head_motion") == "remove":
            R, t = replay.handles["rotation"], replay.handles["translation"]
        return cls(cache.positions, rows, cache_info.get("scale", 1.0), R, t)

    def __len__(self) -> int:
        return self.shape[0]

    def __array__(self, dtype=None, copy=None):
        return self[:] if dtype is None else self[:].astype(dtype)

    def __getitem__(self, index):
        if isinstance(index, tuple):  # frames, then vertices and coordinates
            out = self[index[0]]
            return out[((slice(None),) if out.ndim == 3 else ()) + index[1:]]
        frames = np.arange(self.shape[0])[index]
        one = np.ndim(frames) == 0
        frames = np.atleast_1d(frames)
        rows = self.rows[frames]
        if rows.size and np.array_equal(rows, np.arange(rows[0], rows[0] + rows.size)):
            x = np.asarray(self.positions[rows[0]:rows[0] + rows.size], dtype=np.float64)  # (a memmap reads a slice)
        else:
            x = np.asarray(self.positions[rows], dtype=np.float64)
        x *= self.scale
        if self.rotation is not None:  # world = R head + t
            x = np.einsum("cji,cvj->cvi", self.rotation[frames], x - self.translation[frames, None, :])
        x = x.astype(np.float32)
        return x[0] if one else x


class _Difference:
    """``a − b`` of two (T, V, 3) arrays, frame slices computed when read (memmaps stay on disk)."""

    def __init__(self, a, b):
        self.a, self.b = a, b
        self.shape, self.ndim, self.dtype = a.shape, 3, np.dtype(np.float32)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index):
        return np.asarray(self.a[index], dtype=np.float32) - np.asarray(self.b[index], dtype=np.float32)


def frame_rate(times: np.ndarray, default: float = 30.0) -> float:
    """Frame rate from frame times: 1 / median interval (``default`` for fewer than two frames).

    Parameters
    ----------
    times : (T,) seconds, increasing.

    Returns
    -------
    float frames per second.

    Raises
    ------
    InputError
        Times that do not increase.

    Example
    -------
    >>> frame_rate(np.arange(5) / 30.0)
    30.0
    """
    times = np.asarray(times, dtype=np.float64)
    if times.shape[0] < 2:
        return float(default)
    dt = np.diff(times)
    if not (dt > 0).all():
        i = int(np.flatnonzero(~(dt > 0))[0])
        raise InputError(f"frame times do not increase at frame index {i + 1} ({times[i]} → {times[i + 1]} s)",
                         hint="replay a take whose time column increases")
    fps = 1.0 / float(np.median(dt))
    # takes are recorded at whole (or NTSC) rates; snap what rounding in the CSV blurred
    for nominal in (round(fps), round(fps * 1.001) / 1.001):
        if nominal > 0 and abs(fps - nominal) < 1e-4 * nominal:
            return float(nominal)
    return fps


def is_uniform(times: np.ndarray) -> bool:
    """True when every frame interval is within 1 % of the median (no dropped frames)."""
    times = np.asarray(times, dtype=np.float64)
    if times.shape[0] < 3:
        return True
    dt = np.diff(times)
    return bool(np.abs(dt - np.median(dt)).max() <= _UNIFORM_TOLERANCE * np.median(dt))


def time_codes(times: np.ndarray, fps: float) -> np.ndarray:
    """Time codes (frames at ``fps``) of frame times: ``times × fps``, snapped to integers
    when within 1/100 of a frame (CSV times are rounded; the frames are whole).

    Returns
    -------
    (T,) float64.
    """
    tc = np.asarray(times, dtype=np.float64) * fps
    near = np.abs(tc - np.round(tc)) < 1e-2
    return np.where(near, np.round(tc), tc)
