"""USD layers (usd-core) of a face's animation: ``.usdc``, ``.usd`` or ``.usda``, written and read.

One ``UsdGeom.Mesh`` ``/Face/skin`` with the original polygons
(``faceVertexCounts``/``faceVertexIndices``), the UVs as the face-varying, indexed primvar
``primvars:st``, no subdivision, and time-sampled ``points`` and ``extent`` at time codes
``time × fps`` (``timeCodesPerSecond`` = the take's frame rate), with ``metersPerUnit`` from the
rig's units. The points keep the rest mesh's vertex order. Reading takes any layer's animated mesh.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import numpy as np
from pxr import Sdf, Usd, UsdGeom, Vt

from facepipe.errors import InputError
from facepipe.io.atomic import atomic_path
from facepipe.io.point_caches import cache_frame, check_positions
from facepipe.io.replay_folder import time_codes

# metres per unit of the rig's length units (USD's metersPerUnit)
_METERS_PER_UNIT = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "inch": 0.0254, "ft": 0.3048, "dm": 0.1}


def write_usd(path: str | os.PathLike, mesh, positions, times: np.ndarray, fps: float, *, units: str = "cm",
              up_axis: str = "Y", frame_numbers: np.ndarray | None = None, metadata: dict | None = None,
              progress: Callable[[int], object] | None = None) -> Path:
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
    progress : called with the number of frames added.

    Returns
    -------
    Path written (replaced atomically if it exists).

    Notes
    -----
    The layer is built in memory (about 12 bytes per vertex and frame) and exported once.
    """
    path = Path(path)
    check_positions(positions, mesh.n_vertices, path)
    T = positions.shape[0]
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
        frame = cache_frame(positions, t, path)
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


def _units_of(meters_per_unit: float) -> str | None:
    """The unit name of a ``metersPerUnit`` value (None for one facepipe does not name)."""
    for name in ("m", "dm", "cm", "mm", "in", "ft"):
        if abs(meters_per_unit - _METERS_PER_UNIT[name]) <= 1e-9 * _METERS_PER_UNIT[name]:
            return name
    return None


def _animated_mesh(stage, path: Path, n_vertices: int | None):
    """The ``UsdGeom.Mesh`` whose points are time-sampled (the one with ``n_vertices`` points among several)."""
    meshes = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    animated = [m for m in meshes if m.GetPointsAttr().GetNumTimeSamples() > 0]
    if not animated:
        raise InputError(f"no UsdGeom.Mesh with time-sampled points ({len(meshes)} mesh(es), none animated)",
                         path=path, hint="export the animation as time-sampled points (a point cache), not a rig")
    if len(animated) > 1 and n_vertices is not None:
        sized = [m for m in animated if len(m.GetPointsAttr().Get(m.GetPointsAttr().GetTimeSamples()[0])) ==
                 n_vertices]
        animated = sized or animated
    if len(animated) > 1:
        raise InputError(f"{len(animated)} animated meshes: "
                         f"{', '.join(str(m.GetPath()) for m in animated[:5])}", path=path,
                         hint="export the face's mesh alone")
    return animated[0]


def read_usd(path: str | os.PathLike, n_vertices: int | None = None) -> dict:
    """Read the time-sampled points of a USD layer's animated ``UsdGeom.Mesh``.

    The points are taken in world space (the prim's transforms at each time code applied).

    Parameters
    ----------
    path : ``.usd``, ``.usdc``, ``.usda`` (or ``.usdz``).
    n_vertices : picks the mesh with this many points where several are animated.

    Returns
    -------
    dict with ``positions`` (T, V, 3) float32, ``times`` (T,) seconds (time code /
    ``timeCodesPerSecond``), ``frames`` (T,) int64 (the layer's ``frame_numbers`` when facepipe wrote
    it, else the rounded time codes), ``fps`` (``timeCodesPerSecond``), ``units`` (from
    ``metersPerUnit``, None when the layer does not say or names no known unit), ``prim``.

    Raises
    ------
    InputError
        A layer USD cannot open, no animated mesh, several, or frames of different point counts.
    """
    path = Path(path)
    try:
        stage = Usd.Stage.Open(str(path))
    except Exception as exc:  # pxr raises Tf.ErrorException for unreadable layers
        raise InputError(f"USD cannot open the layer: {str(exc).strip().splitlines()[-1]}", path=path,
                         hint="export the cache again as .usd/.usdc/.usda") from None
    mesh = _animated_mesh(stage, path, n_vertices)
    attr = mesh.GetPointsAttr()
    codes = np.asarray(attr.GetTimeSamples(), dtype=np.float64)
    cache = UsdGeom.XformCache()
    frames = []
    for k, code in enumerate(codes):
        points = np.asarray(attr.Get(code), dtype=np.float64)
        if k and points.shape != frames[0].shape:
            raise InputError(f"time code {code:g} has {len(points)} points, the first {len(frames[0])}", path=path,
                             hint="a point cache keeps one vertex count for the whole animation")
        cache.SetTime(Usd.TimeCode(code))
        M = np.asarray(cache.GetLocalToWorldTransform(mesh.GetPrim()), dtype=np.float64)  # row-vector convention
        if not np.allclose(M, np.eye(4)):
            points = points @ M[:3, :3] + M[3, :3]
        frames.append(points.astype(np.float32))
    tcps = float(stage.GetTimeCodesPerSecond()) if stage.HasAuthoredMetadata("timeCodesPerSecond") else None
    fps = tcps or float(stage.GetFramesPerSecond() or 24.0)
    data = stage.GetRootLayer().customLayerData or {}
    numbers = data.get("frame_numbers")
    if numbers is not None and len(numbers) == len(codes):
        frame_numbers = np.asarray(list(numbers), dtype=np.int64)
    else:
        frame_numbers = np.round(codes).astype(np.int64)
    units = _units_of(float(UsdGeom.GetStageMetersPerUnit(stage))) if UsdGeom.StageHasAuthoredMetersPerUnit(
        stage) else None
    return {"positions": np.stack(frames), "times": codes / fps, "frames": frame_numbers, "fps": fps,
            "units": units, "prim": str(mesh.GetPath())}
