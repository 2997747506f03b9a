"""Animated point caches of a replay: USD (usd-core), MDD and PC2.

All three keep the rest mesh's vertex order, so they play back on the rest mesh (OBJ/FBX of
the rig) in Maya, Houdini, Blender, 3ds Max or a USD viewer:

* **USD** (``.usdc``, ``.usd`` or ``.usda``): one ``UsdGeom.Mesh`` ``/Face/skin`` with the
  original polygons (``faceVertexCounts``/``faceVertexIndices``), the UVs as the
  face-varying, indexed primvar ``primvars:st``, no subdivision, and time-sampled
  ``points`` and ``extent`` at time codes ``time × fps`` (``timeCodesPerSecond`` = the
  take's frame rate), with ``metersPerUnit`` from the rig's units;
* **MDD** (LightWave/Blender/Max point oven): big-endian; int32 frame count, int32 point
  count, one float32 time in seconds per frame, then per frame the points as float32 x, y, z;
* **PC2** (3ds Max / Blender Point Cache 2): little-endian; ``b"POINTCACHE2\\0"``, int32
  version 1, int32 point count, float32 start frame, float32 sample rate (frames between
  samples, 1), int32 sample count, then per sample the points as float32 x, y, z. PC2 has
  no per-sample times, so a take with dropped frames (non-uniform times) is refused.

Each file is written under a temporary name and renamed when complete.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Callable

import numpy as np

from facepipe.io.atomic import atomic_open, atomic_path
from facepipe.errors import InputError
from facepipe.export.common import check_targets, remove_partial_files
from facepipe.io.replay_folder import is_uniform, time_codes

FORMATS = {"usd": (".usdc", ".usd", ".usda"), "mdd": (".mdd",), "pc2": (".pc2",)}

# metres per unit of the rig's length units (USD's metersPerUnit)
_METERS_PER_UNIT = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "inch": 0.0254, "ft": 0.3048, "dm": 0.1}

MDD_HEADER = struct.Struct(">ii")
PC2_HEADER = struct.Struct("<12siiffi")
PC2_MAGIC = b"POINTCACHE2\0"


def cache_path(dest: str | os.PathLike, fmt: str, name: str = "replay") -> Path:
    """The file a cache export writes: ``dest`` itself, or ``dest/name.EXT`` for a folder.

    Raises
    ------
    InputError
        A file name whose extension is not one of the format's.
    """
    dest = Path(dest)
    if dest.is_dir():
        return dest / f"{name}{FORMATS[fmt][0]}"
    if dest.suffix.lower() not in FORMATS[fmt]:
        raise InputError(f"a {fmt.upper()} cache must be named *{' or *'.join(FORMATS[fmt])}", path=dest,
                         hint=f"use e.g. -o {dest.with_suffix(FORMATS[fmt][0]).name}, or give an existing folder")
    return dest


def _prepare(path: Path, force: bool, resume: bool) -> bool:
    """True when the file must be written; False when ``resume`` keeps a complete one."""
    check_targets([path], force, resume)
    path.parent.mkdir(parents=True, exist_ok=True)
    if resume:
        remove_partial_files([path])
        return not path.exists()
    return True


def _check_positions(positions, n_vertices: int | None, path: Path) -> None:
    if getattr(positions, "ndim", None) != 3 or positions.shape[2] != 3 or (
            n_vertices is not None and positions.shape[1] != n_vertices):
        raise InputError(f"positions have shape {getattr(positions, 'shape', None)}, expected (frames, "
                         f"{n_vertices if n_vertices is not None else 'V'}, 3)", path=path,
                         hint="export positions replayed with this rig's model")
    if positions.shape[0] == 0:
        raise InputError("the replay has no frames", path=path)


def _frame(positions, t: int, path: Path) -> np.ndarray:
    frame = np.asarray(positions[t], dtype=np.float32)
    if not np.isfinite(frame).all():
        bad = int(np.flatnonzero(~np.isfinite(frame).all(axis=1))[0])
        raise InputError(f"frame index {t} has NaN or infinite positions, first vertex {bad}", path=path,
                         hint="check the replay report for that frame (e.g. lost markers)")
    return frame


def write_mdd(path: str | os.PathLike, positions, times: np.ndarray, *, force: bool = False, resume: bool = False,
              progress: Callable[[int], object] | None = None) -> Path | None:
    """Write an MDD point cache (big-endian), streaming one frame at a time.

    Parameters
    ----------
    path : ``.mdd`` file.
    positions : (T, V, 3) float array or memmap, length units.
    times : (T,) seconds of every frame.
    force, resume : overwrite an existing file / keep it.
    progress : called with the number of frames written.

    Returns
    -------
    Path written, or None when ``resume`` kept an existing file.
    """
    path = Path(path)
    _check_positions(positions, None, path)
    T, V = positions.shape[:2]
    if len(times) != T:
        raise ValueError(f"{len(times)} times for {T} frames")
    if not _prepare(path, force, resume):
        return None
    with atomic_open(path, "wb") as fh:
        fh.write(MDD_HEADER.pack(T, V))
        fh.write(np.asarray(times, dtype=">f4").tobytes())
        for t in range(T):
            fh.write(_frame(positions, t, path).astype(">f4").tobytes())
            if progress is not None:
                progress(1)
    return path


def write_pc2(path: str | os.PathLike, positions, times: np.ndarray, fps: float, *, force: bool = False,
              resume: bool = False, progress: Callable[[int], object] | None = None) -> Path | None:
    """Write a PC2 point cache (little-endian), streaming one frame at a time.

    Parameters
    ----------
    path : ``.pc2`` file.
    positions : (T, V, 3), length units.
    times : (T,) seconds; must be uniform (PC2 stores a start frame and a sample rate only).
    fps : frames per second; the start frame is ``times[0] × fps`` (see
        :func:`facepipe.io.replay_folder.time_codes`), the sample rate 1 (a sample every frame).

    Returns
    -------
    Path written, or None when ``resume`` kept an existing file.

    Raises
    ------
    InputError
        Non-uniform frame times (dropped frames): PC2 cannot place them.
    """
    path = Path(path)
    _check_positions(positions, None, path)
    T, V = positions.shape[:2]
    if not is_uniform(times):
        raise InputError("the take's frame times are not uniform (dropped frames?): PC2 stores only a start frame "
                         "and a fixed sample rate", path=path,
                         hint="export MDD or USD, which store a time per frame")
    if not _prepare(path, force, resume):
        return None
    start = float(time_codes(np.asarray(times[:1]), fps)[0])
    with atomic_open(path, "wb") as fh:
        fh.write(PC2_HEADER.pack(PC2_MAGIC, 1, V, start, 1.0, T))
        for t in range(T):
            fh.write(_frame(positions, t, path).astype("<f4").tobytes())
            if progress is not None:
                progress(1)
    return path


def write_usd(path: str | os.PathLike, mesh, positions, times: np.ndarray, fps: float, *, units: str = "cm",
              up_axis: str = "Y", frame_numbers: np.ndarray | None = None, metadata: dict | None = None,
              force: bool = False, resume: bool = False,
              progress: Callable[[int], object] | None = None) -> Path | None:
    """Write the animation as a USD layer with one time-sampled ``UsdGeom.Mesh``.

    Parameters
    ----------
    path : ``.usdc`` (binary crate; also ``.usd``) or ``.usda`` (text).
    mesh : facepipe.core.mesh.Mesh, the rest mesh: polygons and UVs (``primvars:st``).
    positions : (T, V, 3), length units, in the mesh's vertex order.
    times : (T,) seconds; time codes are ``times × fps`` (snapped to whole frames).
    fps : the take's frame rate: ``timeCodesPerSecond`` and ``framesPerSecond``.
    units : the rig's length units (``metersPerUnit``; unknown units leave the USD default).
    up_axis : "Y" or "Z".
    frame_numbers : (T,) the take's frame numbers, stored in the layer's ``customLayerData``.
    metadata : more ``customLayerData`` (str/int/float values).
    force, resume, progress : as for every export (progress: frames added).

    Returns
    -------
    Path written, or None when ``resume`` kept an existing file.

    Notes
    -----
    The layer is built in memory (about 12 bytes per vertex and frame) and exported once.
    """
    from pxr import Sdf, Usd, UsdGeom, Vt

    path = Path(path)
    _check_positions(positions, mesh.n_vertices, path)
    T = positions.shape[0]
    if not _prepare(path, force, resume):
        return None
    tc = time_codes(times, fps)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if up_axis.upper() == "Z" else UsdGeom.Tokens.y)
    if units.lower() in _METERS_PER_UNIT:
        UsdGeom.SetStageMetersPerUnit(stage, _METERS_PER_UNIT[units.lower()])
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetFramesPerSecond(float(fps))
    stage.SetStartTimeCode(float(tc[0]))
    stage.SetEndTimeCode(float(tc[-1]))
    root = UsdGeom.Xform.Define(stage, "/Face")
    stage.SetDefaultPrim(root.GetPrim())
    geom = UsdGeom.Mesh.Define(stage, "/Face/skin")
    geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.diff(mesh.polygon_offsets).astype(np.int32)))
    geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(mesh.polygon_vertices, dtype=np.int32)))
    geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)  # a dense scan, not a subdivision cage
    geom.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)  # OBJ winding: counter-clockwise
    if mesh.uvs is not None and mesh.polygon_uvs is not None:
        st = UsdGeom.PrimvarsAPI(geom.GetPrim()).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                               UsdGeom.Tokens.faceVarying)
        st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(mesh.uvs, dtype=np.float32)))
        st.SetIndices(Vt.IntArray.FromNumpy(np.asarray(mesh.polygon_uvs, dtype=np.int32)))
    points = geom.CreatePointsAttr()
    extent = geom.CreateExtentAttr()
    for t in range(T):
        frame = _frame(positions, t, path)
        points.Set(Vt.Vec3fArray.FromNumpy(frame), float(tc[t]))
        extent.Set(Vt.Vec3fArray.FromNumpy(np.stack([frame.min(axis=0), frame.max(axis=0)])), float(tc[t]))
        if progress is not None:
            progress(1)
    data = {"generator": "facepipe", "fps": float(fps)}
    if frame_numbers is not None:
        data["frame_numbers"] = Vt.IntArray.FromNumpy(np.asarray(frame_numbers, dtype=np.int32))
    data.update(metadata or {})
    stage.GetRootLayer().customLayerData = data
    with atomic_path(path) as tmp:
        if not stage.GetRootLayer().Export(str(tmp)):
            raise OSError(f"USD could not write {tmp}")
    return path
