"""USD layers (usd-core) of a replay: ``.usdc``, ``.usd`` or ``.usda``.

One ``UsdGeom.Mesh`` ``/Face/skin`` with the original polygons
(``faceVertexCounts``/``faceVertexIndices``), the UVs as the face-varying, indexed primvar
``primvars:st``, no subdivision, and time-sampled ``points`` and ``extent`` at time codes
``time × fps`` (``timeCodesPerSecond`` = the take's frame rate), with ``metersPerUnit`` from the
rig's units. The points keep the rest mesh's vertex order.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import numpy as np
from pxr import Sdf, Usd, UsdGeom, Vt

from facepipe.export.caches import cache_frame, check_positions, export_cache, prepare_cache
from facepipe.export.registry import ExportOptions
from facepipe.io.atomic import atomic_path
from facepipe.io.replay_folder import time_codes

# metres per unit of the rig's length units (USD's metersPerUnit)
_METERS_PER_UNIT = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "inch": 0.0254, "ft": 0.3048, "dm": 0.1}


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
    path = Path(path)
    check_positions(positions, mesh.n_vertices, path)
    T = positions.shape[0]
    if not prepare_cache(path, force, resume):
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


def export_usd(replay, dest: Path, options: ExportOptions) -> tuple[list[Path], dict]:
    """The replay's layer as a USD layer on the rest mesh (the ``usd`` format's exporter)."""

    def write(path, positions, fps, progress):
        model = replay.load_model(options.model_path)
        return write_usd(path, model.mesh(), positions, replay.times, fps, units=model.meta.get("units", ""),
                         up_axis=options.up_axis, frame_numbers=replay.frame_numbers,
                         metadata={"layer": options.layer, "replay": str(replay.path)},
                         force=options.force, resume=options.resume, progress=progress)

    return export_cache(replay, dest, options, "usd", write)
