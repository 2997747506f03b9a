"""Mesh animations as takes: point caches of a rigged face (USD, MDD, PC2, OBJ sequences).

A DCC's keyframed or blend-shape rig exported as a point cache is a dense moving mesh in the
rest mesh's vertex order. The formats' byte layouts live beside their writers
(:mod:`facepipe.io.point_caches` for MDD and PC2, :mod:`facepipe.io.usd_file`); this module
turns what they read into a :class:`MeshCache` and checks it against the model: the vertex count,
finite values, the units (the file's, else the rig's, converted) and that the first frame (or
``rest_frame``) is the model's rest mesh up to a rigid motion and an expression — a cache of
another face, vertex order or scale is an :class:`~facepipe.errors.InputError` (exit status 2).

The formats register in :mod:`facepipe.mocap.registry` (:data:`~facepipe.mocap.registry.MESH_CACHES`)
beside the marker formats.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from facepipe.core.mesh import VertexSelection, welded_frames
from facepipe.core.rigid import similarity_fit
from facepipe.errors import InputError
from facepipe.io.mesh_read import load_vertices
from facepipe.io.point_caches import read_mdd, read_pc2
from facepipe.io.replay_folder import frame_rate
from facepipe.mocap.markers import known_unit_ratios, normalise_units, unit_factor
from facepipe.mocap.registry import MeshCacheFormat, mesh_cache_format, register_mesh_cache

#: Frame rate of caches that store frame numbers only (PC2, OBJ sequences) unless told.
DEFAULT_FPS = 30.0
#: A rest frame whose similarity to the rig's rest mesh has a scale outside this range is of
#: another size (a unit, or another face): as for marker takes (mocap.prepare.SCALE_RANGE).
SCALE_RANGE = (0.75, 1.33)
#: The rest frame matches the rest mesh when, after the similarity, the median vertex lies within
#: this fraction of the mesh's RMS radius: an expression moves part of the face by a few percent
#: of its size, another vertex order moves nearly every vertex by about the radius.
ORDER_TOLERANCE = 0.1


@dataclass
class MeshCache:
    """A mesh animation: every vertex of the rest mesh per frame.

    Attributes
    ----------
    frames : (T,) int64 frame numbers, increasing.
    times : (T,) float64 seconds.
    positions : (T, V, 3) float32 (a memmap for MDD/PC2), in ``units`` (after :func:`read_mesh_cache`,
        the rig's).
    path, format : where it was read from and the format's name.
    fps : frames per second (the file's where it says, else ``DEFAULT_FPS`` or the caller's).
    units : length unit of ``positions``, or None when the file does not say.
    source_units : the unit the file declared (or the caller said) before conversion.
    scale : factor applied to the file's numbers (unit conversion), 1 when none.
    notes : what the reader assumed (JSON-serialisable strings).
    """

    frames: np.ndarray
    times: np.ndarray
    positions: np.ndarray
    path: str
    format: str
    fps: float
    units: str | None = None
    source_units: str | None = None
    scale: float = 1.0
    notes: list = None

    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_vertices(self) -> int:
        return int(self.positions.shape[1])

    def frame(self, t: int) -> np.ndarray:
        """Frame index ``t`` as float64 in ``units`` (the conversion applied lazily: memmaps stay on disk)."""
        return np.asarray(self.positions[t], dtype=np.float64) * self.scale

    def chunk(self, start: int, stop: int) -> np.ndarray:
        """Frames ``start:stop`` as float64 in ``units``."""
        return np.asarray(self.positions[start:stop], dtype=np.float64) * self.scale


# ----------------------------------------------------------------------------- readers


def _frames_from_times(times: np.ndarray, path: Path) -> tuple[np.ndarray, float]:
    fps = frame_rate(times, DEFAULT_FPS)
    return np.round(times * fps).astype(np.int64), fps


def read_mdd_cache(path: Path, fps: float | None = None) -> MeshCache:
    """An MDD file (per-frame times; no units)."""
    times, positions = read_mdd(path)
    if positions.shape[0] > 1 and not (np.diff(times) > 0).all():
        i = int(np.flatnonzero(~(np.diff(times) > 0))[0]) + 1
        raise InputError(f"frame index {i}: its time {times[i]:g} s does not increase", path=path,
                         hint="export the cache again with increasing frame times")
    frames, rate = _frames_from_times(times, path)
    return MeshCache(frames, times, positions, str(path), "mdd", float(fps or rate), notes=[])


def read_pc2_cache(path: Path, fps: float | None = None) -> MeshCache:
    """A PC2 file (start frame and frames between samples; no rate in seconds, no units)."""
    start, step, positions = read_pc2(path)
    numbers = start + step * np.arange(positions.shape[0])
    frames = np.round(numbers).astype(np.int64)
    rate = float(fps or DEFAULT_FPS)
    notes = [] if fps else [f"PC2 stores no frame rate: {rate:g} frames/s assumed (--cache-fps)"]
    return MeshCache(frames, numbers / rate, positions, str(path), "pc2", rate, notes=notes)


def read_usd_cache(path: Path, fps: float | None = None, n_vertices: int | None = None) -> MeshCache:
    """A USD layer's time-sampled mesh (rate and units from the stage's metadata)."""
    # imported when a USD cache is read: pxr takes a while to load, and every take read imports this module
    from facepipe.io.usd_file import read_usd

    data = read_usd(path, n_vertices)
    rate = float(fps or data["fps"])
    times = data["times"] * data["fps"] / rate
    notes = [f"mesh {data['prim']}"]
    return MeshCache(data["frames"], times, data["positions"], str(path), "usd", rate, units=data["units"],
                     notes=notes)


NUMBERED_OBJ = re.compile(r"^(.*?)(\d+)(\.obj)$", re.IGNORECASE)  # an OBJ sequence's frame file


def obj_sequence_files(path: Path) -> list[tuple[int, Path]]:
    """(frame number, file) of an OBJ sequence: a folder of ``*.obj`` or a ``frame_%04d.obj`` pattern.

    Raises
    ------
    InputError
        No files, files of several name patterns, or a frame number missing between the first and last.
    """
    if path.is_dir():
        folder, candidates = path, sorted(path.glob("*.obj")) + sorted(path.glob("*.OBJ"))
        prefix = None
    else:
        folder = path.parent
        text = path.name
        m = re.search(r"%0?(\d*)d", text)
        if m is None:
            raise InputError("not an OBJ sequence: give a folder of OBJ files or a pattern such as frame_%04d.obj",
                             path=path)
        prefix = text[:m.start()]
        candidates = sorted(folder.glob(prefix + "*" + text[m.end():]))
    numbered = []
    for p in candidates:
        m = NUMBERED_OBJ.match(p.name)
        if m and (prefix is None or m.group(1) == prefix):
            numbered.append((m.group(1), int(m.group(2)), p))
    if not numbered:
        raise InputError("no numbered OBJ files (name_0001.obj …) found", path=path,
                         hint="export the animation as an OBJ sequence with frame numbers in the names")
    prefixes = sorted({n[0] for n in numbered})
    if len(prefixes) > 1:
        raise InputError(f"OBJ files of {len(prefixes)} name patterns ({', '.join(p + '####.obj' for p in prefixes[:4])})",
                         path=path, hint="give the pattern of one sequence, e.g. " + prefixes[0] + "%04d.obj")
    numbered.sort(key=lambda n: n[1])
    numbers = np.array([n[1] for n in numbered])
    if len(np.unique(numbers)) != len(numbers):
        dup = int(numbers[np.flatnonzero(np.diff(numbers) == 0)[0]])
        raise InputError(f"frame {dup} appears twice (names with different zero padding)", path=path)
    step = int(np.min(np.diff(numbers))) if len(numbers) > 1 else 1
    gaps = np.flatnonzero(np.diff(numbers) != step)
    if gaps.size:
        missing = int(numbers[gaps[0]] + step)
        raise InputError(f"frame {missing} of the OBJ sequence is missing (between {numbered[gaps[0]][2].name} and "
                         f"{numbered[gaps[0] + 1][2].name}); {gaps.size} gap(s) in all", path=path,
                         hint="export the missing frames again: a cache must have every frame")
    return [(int(n), p) for _, n, p in numbered]


def read_obj_sequence(path: Path, fps: float | None = None) -> MeshCache:
    """An OBJ sequence: one file per frame, the frame number in the name (no rate, no units)."""
    files = obj_sequence_files(path)
    first = load_vertices(files[0][1])
    positions = np.empty((len(files),) + first.shape, dtype=np.float32)
    for k, (number, file) in enumerate(files):
        v = first if k == 0 else load_vertices(file)
        if v.shape != first.shape:
            raise InputError(f"frame {number} has {len(v)} vertices, frame {files[0][0]} {len(first)}", path=file,
                             hint="every file of a cache must have the rest mesh's vertices")
        positions[k] = v
    frames = np.array([n for n, _ in files], dtype=np.int64)
    rate = float(fps or DEFAULT_FPS)
    notes = [] if fps else [f"an OBJ sequence stores no frame rate: {rate:g} frames/s assumed (--cache-fps)"]
    return MeshCache(frames, frames / rate, positions, str(path), "obj-sequence", rate, notes=notes)


def _is_obj_sequence(path: Path) -> bool:
    if path.is_dir():
        return any(path.glob("*.obj")) or any(path.glob("*.OBJ"))
    return "%" in path.name and path.suffix.lower() == ".obj"


register_mesh_cache(MeshCacheFormat("usd", (".usd", ".usdc", ".usda", ".usdz"), read_usd_cache))
register_mesh_cache(MeshCacheFormat("mdd", (".mdd",), read_mdd_cache))
register_mesh_cache(MeshCacheFormat("pc2", (".pc2",), read_pc2_cache))
register_mesh_cache(MeshCacheFormat("obj-sequence", (".obj",), read_obj_sequence, match=_is_obj_sequence))


# ----------------------------------------------------------------------------- checks


def _check_finite(cache: MeshCache) -> None:
    for start in range(0, cache.n_frames, 64):
        block = np.asarray(cache.positions[start:start + 64])
        bad = ~np.isfinite(block).all(axis=2)
        if bad.any():
            t, v = (int(i[0]) for i in np.nonzero(bad))
            raise InputError(f"frame {int(cache.frames[start + t])} (index {start + t}) has NaN or infinite "
                             f"positions, first vertex {v}; {int(bad.sum())} vertex positions in the frames "
                             f"{int(cache.frames[start])}–{int(cache.frames[min(start + 63, cache.n_frames - 1)])}",
                             path=cache.path, hint="export the cache again (a cache must have every vertex of "
                             "every frame)")


def rest_frame_index(cache: MeshCache, rest_frame: int | None) -> int:
    """The index of frame number ``rest_frame`` (None: the first frame)."""
    if rest_frame is None:
        return 0
    hit = np.flatnonzero(cache.frames == rest_frame)
    if hit.size == 0:
        raise InputError(f"--rest-frame {rest_frame} is not a frame of the cache (frames "
                         f"{int(cache.frames[0])}–{int(cache.frames[-1])})", path=cache.path)
    return int(hit[0])


def check_rest_frame(cache: MeshCache, rest: np.ndarray, index: int, rig_units: str | None) -> dict:
    """Check that frame ``index`` is the rest mesh up to a rigid motion and an expression.

    Returns
    -------
    dict: ``scale`` of the similarity (1 for the rig's size), ``median_distance`` and
    ``rms_radius`` (rig units) after it.

    Raises
    ------
    InputError
        A scale outside :data:`SCALE_RANGE` (naming the unit that explains it, if one does), or
        vertices that do not correspond (another vertex order or another face).
    """
    frame = cache.frame(index)
    rest = np.asarray(rest, dtype=np.float64)
    frame_no = int(cache.frames[index])
    radius = float(np.sqrt(((rest - rest.mean(axis=0)) ** 2).sum(axis=1).mean()))
    # the size ratio of the point sets does not depend on which vertex is which (a similarity fit
    # of points in another order shrinks toward scale 0), so units are told apart from order
    s = radius / max(float(np.sqrt(((frame - frame.mean(axis=0)) ** 2).sum(axis=1).mean())), 1e-300)
    if not SCALE_RANGE[0] <= s <= SCALE_RANGE[1]:
        size = 1.0 / s
        source = cache.source_units or rig_units
        unit_hint = "pass --take-units with the cache's unit"
        if source:
            ratios = known_unit_ratios(source)
            unit = min(ratios, key=lambda u: abs(np.log(s) - np.log(ratios[u])))
            if abs(np.log(s) - np.log(ratios[unit])) < np.log(1.25) and unit != source:
                unit_hint = f"the cache seems to be in {unit}, not {source}: pass --take-units {unit}"
            else:
                unit_hint = "no unit explains it: check that the cache is of this model's face"
        raise InputError(f"scale mismatch: frame {frame_no} of the cache is {size:.3g}× the size of the model's rest "
                         f"mesh", path=cache.path, hint=unit_hint)
    s, Q, b = similarity_fit(frame, rest)
    distance = np.linalg.norm(s * frame @ Q.T + b - rest, axis=1)
    median = float(np.median(distance))
    if median > ORDER_TOLERANCE * radius:
        raise InputError(f"frame {frame_no} of the cache does not correspond to the model's rest mesh vertex by "
                         f"vertex: the median vertex lies {median:.3g} from its rest position after the best "
                         f"similarity ({100 * median / radius:.0f} % of the face's radius)", path=cache.path,
                         hint="export the cache in the rest mesh's vertex order (no welding, triangulation or "
                              "reordering), or name a frame close to the rest pose with --rest-frame")
    return {"frame": frame_no, "scale": float(s), "median_distance": median, "rms_radius": radius}


def check_mesh_cache(cache: MeshCache, rest: np.ndarray, *, units: str | None = None, take_units: str | None = None,
                     rest_frame: int | None = None, file_order: np.ndarray | None = None) -> tuple[MeshCache, dict]:
    """Check a mesh cache (read from a file, or frames in memory) against the model's rest mesh
    and put it in the rig's units: the vertex count, finite positions, the units (``take_units``
    overriding what the cache says) and the rest frame (:func:`check_rest_frame`).

    ``file_order``: the model's ``weld_index`` (a rig welded along seams): a cache in the mesh
    file's vertex order (its count) is read through it, one vertex of each welded group.

    Returns (the cache in the rig's units, the rest frame's check report); InputError naming what
    is wrong.
    """
    V = len(rest)
    if file_order is not None and cache.n_vertices == len(file_order) != V:
        cache = replace(cache, positions=welded_frames(cache.positions, file_order),
                        notes=list(cache.notes or []) + [f"the cache is in the mesh file's vertex order ({len(file_order)} "
                                                        f"vertices): read on the model's {V}, welded along seams"])
    if cache.n_vertices != V:
        raise InputError(f"the cache has {cache.n_vertices} vertices per frame, the model's rest mesh {V}",
                         path=cache.path, hint="export the cache of this face's rest mesh (the same topology, no "
                                               "welding or triangulation by the exporter), or replay it with its own model")
    _check_finite(cache)
    target = normalise_units(units, what="rig unit")
    source = normalise_units(take_units, what="take unit") or cache.units
    notes = list(cache.notes or [])
    if source is None and target is not None:
        notes.append(f"the cache does not state its units: taken to be the rig's ({target}); --take-units overrides")
    factor = unit_factor(source, target) if source and target and source != target else 1.0
    cache = replace(cache, units=target or source, source_units=source, scale=factor, notes=notes)
    check = check_rest_frame(cache, rest, rest_frame_index(cache, rest_frame), target)
    return cache, check


def read_mesh_cache(path: str | os.PathLike, rest: np.ndarray, *, units: str | None = None,
                    take_units: str | None = None, rest_frame: int | None = None, fps: float | None = None,
                    frames: slice | None = None, file_order: np.ndarray | None = None) -> tuple[MeshCache, dict]:
    """Read a point cache and check it against the model's rest mesh.

    Parameters
    ----------
    path : a cache file (``.usd*``, ``.mdd``, ``.pc2``), a folder of OBJ files or a ``frame_%04d.obj`` pattern.
    rest : (V, 3) the model's rest positions (rig units).
    units : the rig's units; take_units : the cache's, overriding what the file says (or filling in).
    rest_frame : frame number compared with the rest mesh (default: the first frame).
    fps : frame rate for formats that store none (PC2, OBJ), or overriding the file's.
    frames : rows of the cache to keep (the whole cache is checked).
    file_order : the model's ``weld_index``, if any (see :func:`check_mesh_cache`).

    Returns
    -------
    (MeshCache in the rig's units, check report dict)

    Raises
    ------
    InputError
        See :func:`check_rest_frame`; another vertex count; NaN or infinite values; a missing OBJ frame.
    """
    path = Path(path)
    fmt = mesh_cache_format(path)
    if fmt is None:
        raise InputError("not a mesh cache", path=path)
    if not path.exists() and fmt.name != "obj-sequence":
        raise InputError("cache not found", path=path)
    if fmt.name == "usd":
        cache = fmt.reader(path, fps, n_vertices=len(rest))
    else:
        cache = fmt.reader(path, fps)
    cache, check = check_mesh_cache(cache, rest, units=units, take_units=take_units, rest_frame=rest_frame,
                                    file_order=file_order)
    if frames is not None:
        rows = np.arange(cache.n_frames)[frames]
        if rows.size == 0:
            raise InputError(f"the frame range selects none of the {cache.n_frames} frames", path=path)
        kept = (cache.positions.rows(rows[0], rows[-1] + 1) if isinstance(cache.positions, VertexSelection)
                else cache.positions[rows[0]:rows[-1] + 1])
        cache = replace(cache, frames=cache.frames[rows], times=cache.times[rows], positions=kept)
    return cache, check
