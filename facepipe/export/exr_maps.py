"""Texture maps of the fine-scale layer: per-frame EXR displacement maps and wrinkle-map sets.

**Displacement maps** (``--format exr``): for every frame, the detail layer (final −
large-scale) rasterised into the rest mesh's UV layout (:mod:`facepipe.export.uv_raster`):

* ``vector``: channels R, G, B = the displacement's coordinates in a frame per point:
  ``space="local"``, the model's local frames (t, b, n) (its detail layer exactly);
  ``space="tangent"``, UV-aligned tangent frames (t along +u, b along +v, n), the tangent
  space of renderers' vector displacement; ``space="object"``, the displacement vector in
  the replay's output space (object-space vector displacement in Maya/Arnold, Houdini or
  Blender, added to the large-scale mesh);
* ``scalar``: channel Y = the displacement along the normal (the n coordinate).

The model's local frames take t from a fixed neighbour of each vertex (:mod:`facepipe.core.tangent_frames`),
which turns by tens of degrees from one vertex to the next (median 50° between neighbours
on the ICT mesh), so the t and b channels of ``local`` maps are exact at the vertices but
interpolate differently oriented frames between them. The n channel (and ``scalar``),
``tangent`` and ``object`` maps have no such caveat (:mod:`facepipe.pipeline.detail_layers`).

At the vertices' UVs a bilinear lookup gives the vertex values back (the raster fits the
texels there, :class:`facepipe.export.uv_raster.LookupFit`) wherever the layout has texels enough; the
export measures it on the pixels it writes, frame by frame (``report``, :func:`lookup_report`).

**Wrinkle maps** (``--format wrinkle``, PSD models): a PSD detail is
d_v(f) = c_v + Σ_i w_{v,i} φ_i(f) with coefficients φ_i(f) = |f − f_i| shared by every
vertex. Rasterising is linear, so the P + 1 maps C = map(c) and M_i = map(w_{·,i}) are
written once and a frame's map is the blend

    map(frame) = C + Σ_i coeff_i(frame) · M_i          (coeff_i = φ_i, one CSV row per frame)

— the layered, low-bandwidth scheme of Fidaleo et al. 2000 that real-time engines evaluate in
a shader. WPSD weighs the distances per vertex (r_{v,i}), so its coefficients are per vertex:
no frame-constant blend reproduces it, and the export is refused. A model with a novelty gate
(details faded per vertex on unseen strain) is exported without the gate, and ``wrinkle.json``
says how far, at most, the blend is from the gated details (``gate``).

Files (``NNNN`` numbers frames from ``start``; ``.TILE`` is added for UDIM layouts that use
tiles other than 1001): ``DEST/frame_NNNN[.TILE].exr``; ``DEST/wrinkle_const[.TILE].exr``,
``DEST/wrinkle_PP[.TILE].exr``, ``DEST/coefficients.csv`` and ``DEST/wrinkle.json``.
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path
from typing import Callable

import numpy as np

from facepipe.io.atomic import atomic_open
from facepipe.errors import InputError
from facepipe.io.exr import write_exr
from facepipe.parallel import map_in_order, thread_count
from facepipe.export.common import check_targets, frame_paths, remove_partial_files
from facepipe.export.registry import ExportOptions
from facepipe.export.uv_raster import TiledRaster, mesh_raster, require_uvs
from facepipe.pipeline.detail_layers import DetailLayer, StoredDetailLayer, require_details

MODES = ("vector", "scalar")


def map_paths(dest_dir: Path, stem: str, tiles: list[int], udim: bool) -> dict:
    """{tile: path} of one map: ``dest_dir/stem.exr`` or ``dest_dir/stem.TILE.exr``."""
    return {t: Path(dest_dir) / (f"{stem}.{t}.exr" if udim else f"{stem}.exr") for t in tiles}


def _channels(values: np.ndarray, mode: str) -> np.ndarray:
    """(…, V, 3) displacements → what a map shows: the vector, or its n coordinate."""
    return values if mode == "vector" else values[..., 2]


def write_displacement_maps(
    raster: TiledRaster,
    layer: Callable[[int, int], np.ndarray],
    n_frames: int,
    dest_dir: str | os.PathLike,
    *,
    mode: str = "vector",
    half: bool = True,
    start: int = 1,
    attributes: dict | None = None,
    frame_attributes: Callable[[int], dict] | None = None,
    force: bool = False,
    resume: bool = False,
    chunk: int = 16,
    progress: Callable[[int], object] | None = None,
    report: dict | None = None,
) -> list[dict]:
    """Write one EXR displacement map per frame (per UDIM tile), atomically.

    Parameters
    ----------
    raster : the rest mesh's UV layout at the chosen resolution (:func:`facepipe.export.uv_raster.mesh_raster`).
    layer : callable ``(s, e) -> (e - s, S, 3)`` displacements of frames s..e-1 per raster
        slot (vertex or UV index; e.g. a :class:`facepipe.pipeline.detail_layers.DetailLayer` over the
        replay's handles), length units.
    n_frames : T.
    dest_dir : folder, created if missing.
    mode : "vector" (R, G, B) or "scalar" (Y = the n coordinate).
    half : half floats (default) or 32-bit floats.
    start : number of the first frame's file.
    attributes : header attributes of every file; ``frame_attributes(t)`` adds per-frame ones.
    force, resume : overwrite existing files / keep them and write only the missing frames.
    chunk : frames evaluated together.
    progress : called with the number of frames done.
    report : a dict to fill with how well the written maps (in their pixel type) give back the
        vertex values by bilinear lookup at the vertices' UVs (:func:`lookup_report`).

    Returns
    -------
    list of {tile: Path}, one per frame.

    Raises
    ------
    InputError
        Existing files without force/resume, non-finite displacements (naming the frame).
    """
    if mode not in MODES:
        raise ValueError(f"unknown map mode {mode!r}")
    dest_dir = Path(dest_dir)
    tiles = list(raster.tiles)
    stems = [p.stem for p in frame_paths(dest_dir, n_frames, start, suffix=".exr")]
    paths = [map_paths(dest_dir, stem, tiles, raster.udim) for stem in stems]
    flat = [p for per in paths for p in per.values()]
    check_targets(flat, force, resume, folder=dest_dir)
    dest_dir.mkdir(parents=True, exist_ok=True)
    if resume:
        remove_partial_files(flat)
    check = _LookupCheck(raster) if report is not None else None
    # a frame's maps in float64 while rastered, and their copy in the file's pixel type
    frame_bytes = sum(r.width * r.height for r in raster.tiles.values()) * (3 if mode == "vector" else 1) * 12
    for s in range(0, n_frames, chunk):
        e = min(n_frames, s + chunk)
        todo = [t for t in range(s, e) if not (resume and all(p.exists() for p in paths[t].values()))]
        if not todo:
            if progress is not None:
                progress(e - s)
            continue
        values = np.asarray(layer(s, e))
        # a frame with non-finite values stops the export there: the frames before it are written
        bad_frame = next((t for t in todo if not np.isfinite(values[t - s]).all()), None)
        writing = todo if bad_frame is None else [t for t in todo if t < bad_frame]

        def write_frame(t):
            attrs = dict(attributes or {})
            if frame_attributes is not None:
                attrs.update(frame_attributes(t))
            images = raster(_channels(values[t - s], mode))
            for tile, image in images.items():
                write_exr(paths[t][tile], image, half=half, attributes=dict(attrs, **{"facepipe/tile": tile}))
            return t, (images if check is not None else None)

        kept = (e if bad_frame is None else bad_frame) - s - len(writing)  # the frames a resume keeps
        if progress is not None and kept:
            progress(kept)
        # frames are rastered and compressed on facepipe's threads (both let go of Python's lock),
        # as many under way as there are threads (a 2048² frame's maps are a few hundred MB)
        for t, images in map_in_order(write_frame, writing, ahead=thread_count(), item_bytes=frame_bytes):
            if check is not None:
                check.add(t, _channels(values[t - s], mode), images, np.float16 if half else np.float32)
            if progress is not None:
                progress(1)
        if bad_frame is not None:
            v = values[bad_frame - s]
            vertex = int(np.flatnonzero(~np.isfinite(v).all(axis=1))[0])
            raise InputError(f"frame {start + bad_frame} (index {bad_frame}) has non-finite displacements, first "
                             f"vertex {vertex}", path=next(iter(paths[bad_frame].values())),
                             hint="check the replay report for that frame; the maps before it are written")
    if check is not None:
        report.update(check.result())
    return paths


class _LookupCheck:
    """Accumulates, over frames, the vertex-sample errors of maps (see :func:`lookup_report`)."""

    def __init__(self, raster: TiledRaster):
        self.raster = raster
        self.err = {}  # tile -> (n, C) largest error per sample over the frames
        self.where = {}  # tile -> (n, C) frame index of it
        self.lo = self.hi = None
        self.frames = 0

    def add(self, t: int, values: np.ndarray, images: dict, pixel_type) -> None:
        values = values.reshape(values.shape[0], -1)
        for tile, image in images.items():
            r = self.raster.tiles[tile]
            e = r.lookup_errors(values, image, pixel_type).reshape(r.lookup_slots.shape[0], -1)
            if tile not in self.err:
                self.err[tile], self.where[tile] = e, np.full(e.shape, t)
            else:
                worse = e > self.err[tile]
                self.err[tile] = np.where(worse, e, self.err[tile])
                self.where[tile] = np.where(worse, t, self.where[tile])
            vs = values[r.lookup_slots]
            if vs.shape[0]:
                lo, hi = vs.min(axis=0), vs.max(axis=0)
                self.lo = lo if self.lo is None else np.minimum(self.lo, lo)
                self.hi = hi if self.hi is None else np.maximum(self.hi, hi)
        self.frames += 1

    def result(self) -> dict:
        return lookup_report(self.raster, self.err, self.where, self.lo, self.hi, self.frames)


def lookup_report(raster: TiledRaster, err: dict, where: dict, lo, hi, frames: int, limit: float = 0.02) -> dict:
    """How well maps give back the vertex values at the vertices' UVs, over a take.

    Every vertex lookup (a distinct vertex/UV pair, :attr:`facepipe.export.uv_raster.UVRaster.lookup_slots`)
    is looked up bilinearly in its tile's map and compared with its value; errors are relative
    to each channel's range over the lookups and frames.

    Returns
    -------
    dict: ``samples``, ``frames``, ``max_abs`` (per channel, length units), ``range`` (per
    channel), ``relative`` (the worst, over channels), ``over_limit`` (samples above ``limit``
    of the range) and ``limit``, ``worst`` (tile, slot, uv, channel, frame index).
    """
    if not err or lo is None:
        return {"samples": 0, "frames": frames}
    rng = np.maximum(hi - lo, np.finfo(np.float64).tiny)
    C = rng.shape[0]
    max_abs = np.max([e.max(axis=0) if e.shape[0] else np.zeros(C) for e in err.values()], axis=0)
    rel = {tile: e / rng for tile, e in err.items()}
    tile = max(rel, key=lambda k: rel[k].max() if rel[k].size else -1.0)
    k, c = np.unravel_index(int(np.argmax(rel[tile])), rel[tile].shape) if rel[tile].size else (0, 0)
    r = raster.tiles[tile]
    worst = {"tile": int(tile), "slot": int(r.lookup_slots[k]), "uv": [float(x) for x in r.lookup_uv[k]],
             "channel": int(c), "frame_index": int(where[tile][k, c])} if rel[tile].size else None
    return {
        "samples": int(sum(e.shape[0] for e in err.values())), "frames": int(frames),
        "max_abs": [float(x) for x in max_abs], "range": [float(x) for x in hi - lo],
        "relative": float(max(e.max() if e.size else 0.0 for e in rel.values())),
        "limit": limit, "over_limit": int(sum((e > limit).any(axis=1).sum() for e in rel.values())),
        "worst": worst}


# ----------------------------------------------------------------------------- wrinkle maps


def wrinkle_coefficients(model, head: np.ndarray) -> np.ndarray:
    """Per-frame blend coefficients φ_i(f) = |f − f_i| of a PSD model.

    Parameters
    ----------
    model : facepipe.io.model_file.Model with method "psd".
    head : (T, H, 3) head-space handles.

    Returns
    -------
    (T, P) float64, P basis poses (the rest pose first).
    """
    check_wrinkle_model(model)
    layer = DetailLayer(model, "local")
    return layer.details.distances(layer.features(head))


def gate_deviation(model, head: np.ndarray, coeff: np.ndarray, weights: np.ndarray, const: np.ndarray, mode: str,
                   chunk: int = 16) -> dict:
    """How far the blend is from the model's details when a novelty gate fades them.

    A gated model multiplies its details by a per-vertex confidence that depends on the
    frame's strain (:class:`facepipe.core.novelty.NoveltyGate`): a per-vertex, per-frame factor that no
    frame-constant blend of maps carries. The wrinkle set holds the ungated blend; this
    measures, at the vertices, what that leaves out.

    Returns
    -------
    dict: ``included`` (False), ``novelty_tau``, ``max_abs`` (length units), ``relative`` (to
    the range of the gated details over the take), ``worst_frame_index``, ``per_frame_max_abs``;
    or {"active": False} for a model without a gate.
    """
    layer = DetailLayer(model, "local")
    if layer.details.gate is None:
        return {"active": False}
    T = coeff.shape[0]
    dev = np.zeros(T)
    lo, hi = np.inf, -np.inf
    for s in range(0, T, chunk):
        gated = _channels(layer(head[s:s + chunk]), mode)
        blend = _channels(const + np.einsum("tp,vpc->tvc", coeff[s:s + chunk], weights, optimize=True), mode)
        dev[s:s + chunk] = np.abs(gated - blend).reshape(gated.shape[0], -1).max(axis=1)
        lo, hi = min(lo, float(gated.min())), max(hi, float(gated.max()))
    worst = int(np.argmax(dev))
    return {"active": True, "included": False, "novelty_tau": float(model.meta.get("novelty_tau", 0.0)),
            "note": "the model fades details per vertex where the strain is unlike the examples' (novelty gate); "
                    "a frame-constant blend cannot carry that factor, so the maps hold the ungated details",
            "max_abs": float(dev[worst]), "relative": float(dev[worst] / (hi - lo)) if hi > lo else 0.0,
            "worst_frame_index": worst, "per_frame_max_abs": [float(x) for x in dev]}


def check_map_model(model) -> None:
    """InputError unless the model can give displacement maps: details, and UVs to lay them out in
    (the ``exr`` format's check of a model, before any take is replayed)."""
    require_details(model)
    require_uvs(model.mesh())


def check_wrinkle_set_model(model) -> None:
    """:func:`check_wrinkle_model` and UVs (the ``wrinkle`` format's check of a model)."""
    check_wrinkle_model(model)
    require_uvs(model.mesh())


def check_wrinkle_model(model) -> None:
    """InputError unless the model's details are a frame-constant blend (PSD)."""
    if model.method == "psd":
        return
    if model.method == "wpsd":
        raise InputError(
            "wrinkle maps need one blend coefficient per basis pose and frame, but this WPSD model weighs the "
            "pose-space distances per vertex (r_v,i), so its coefficients differ from vertex to vertex: no "
            "frame-constant blend of maps reproduces it",
            path=model.path or None,
            hint="export per-frame displacement maps (--format exr), or bake the rig with [psd] method = 'psd' "
                 "for wrinkle maps")
    if model.method == "local_strain":
        raise InputError("wrinkle maps need one blend coefficient per basis pose and frame, but this model's details "
                         "are per-vertex functions of the local strain: no frame-constant blend of maps reproduces "
                         "them", path=model.path or None,
                         hint="export per-frame displacement maps (--format exr), or bake the rig with "
                              "[psd] method = 'psd' for wrinkle maps")
    raise InputError("the model has no fine-scale details (method 'none'): there are no wrinkles to export",
                     path=model.path or None, hint="bake the rig with [psd] method = 'psd'")


def _index_width(n: int) -> int:
    return max(2, len(str(n - 1)))


def wrinkle_file_names(n_basis: int) -> list[str]:
    """Stems of the wrinkle maps: the constant first, then one per basis pose.

    Example
    -------
    >>> wrinkle_file_names(2)
    ['wrinkle_const', 'wrinkle_00', 'wrinkle_01']
    """
    width = _index_width(n_basis)
    return ["wrinkle_const"] + [f"wrinkle_{i:0{width}d}" for i in range(n_basis)]


def write_wrinkle_maps(
    raster: TiledRaster,
    model,
    head: np.ndarray,
    frame_numbers: np.ndarray,
    times: np.ndarray,
    dest_dir: str | os.PathLike,
    *,
    mode: str = "vector",
    half: bool = False,
    attributes: dict | None = None,
    force: bool = False,
    resume: bool = False,
    progress: Callable[[int], object] | None = None,
) -> dict:
    """Write a wrinkle-map set: the constant and basis maps, the coefficient CSV, a manifest.

    Parameters
    ----------
    raster : the UV layout (:func:`facepipe.export.uv_raster.mesh_raster`).
    model : a PSD model (InputError for WPSD or none, with the reason).
    head : (T, H, 3) head-space handles of the replay.
    frame_numbers, times : (T,) of the replay.
    dest_dir : folder, created if missing.
    mode : "vector" (t, b, n in R, G, B) or "scalar" (n in Y).
    half : half-float maps. Off by default: the φ_i are large next to the details they
        make (Σ_i w_i = 0, the terms cancel), so rounding the M_i to 3 digits is amplified.
    force, resume : as for every export.
    progress : called with 1 per file written or kept.

    Returns
    -------
    dict, the manifest (also written as ``wrinkle.json``): formula, files, basis names, units.
    """
    if mode not in MODES:
        raise ValueError(f"unknown map mode {mode!r}")
    check_wrinkle_model(model)
    dest_dir = Path(dest_dir)
    coeff = wrinkle_coefficients(model, head)  # (T, P)
    P = coeff.shape[1]
    stems = wrinkle_file_names(P)
    maps = {stem: map_paths(dest_dir, stem, list(raster.tiles), raster.udim) for stem in stems}
    csv_path = dest_dir / "coefficients.csv"
    manifest_path = dest_dir / "wrinkle.json"
    flat = [p for per in maps.values() for p in per.values()] + [csv_path, manifest_path]
    check_targets(flat, force, resume, folder=dest_dir)
    dest_dir.mkdir(parents=True, exist_ok=True)
    if resume:
        remove_partial_files(flat)

    weights = model.rbf_weights.astype(np.float64)  # (V, P, 3)
    const = model.rbf_const.astype(np.float64)  # (V, 3)
    gate = gate_deviation(model, head, coeff, weights, const, mode)
    basis_names = list(model.meta.get("basis", [])) or [f"pose_{i}" for i in range(P)]
    fields = [const] + [weights[:, i] for i in range(P)]
    base_attrs = dict(attributes or {}, **{"facepipe/space": "local", "facepipe/mode": mode})
    for k, (stem, field) in enumerate(zip(stems, fields)):
        role = "constant C" if k == 0 else f"basis map M_{k - 1} ({basis_names[k - 1]})"
        _write_wrinkle_map(raster, field, maps[stem], mode, half, dict(base_attrs, **{"facepipe/map": role}), resume)
        if progress is not None:
            progress(1)

    columns = coefficient_columns(P)
    if not (resume and csv_path.exists()):
        with atomic_open(csv_path, "w") as fh:
            fh.write(format_coefficients(columns, frame_numbers, times, coeff))
    if progress is not None:
        progress(1)

    manifest = wrinkle_manifest(maps, stems, basis_names, columns, csv_path.name, raster, mode, half,
                                (attributes or {}).get("facepipe/units", ""), int(coeff.shape[0]), gate)
    if not (resume and manifest_path.exists()):
        with atomic_open(manifest_path, "w") as fh:
            fh.write(json.dumps(manifest, indent=2))
    return manifest


def _write_wrinkle_map(raster: TiledRaster, field: np.ndarray, paths: dict, mode: str, half: bool, attributes: dict,
                       resume: bool) -> None:
    """One wrinkle map (a per-vertex field) into its tiles' files, rasterised only if a file is missing."""
    images = None
    for tile, path in paths.items():
        if resume and path.exists():
            continue
        if images is None:
            images = raster(_channels(field, mode))
        write_exr(path, images[tile], half=half, attributes=dict(attributes, **{"facepipe/tile": tile}))


def coefficient_columns(n_basis: int) -> list[str]:
    """The header of ``coefficients.csv``: frame, time, coeff_00 … (one per basis pose)."""
    return ["frame", "time"] + [f"coeff_{i:0{_index_width(n_basis)}d}" for i in range(n_basis)]


def format_coefficients(columns: list[str], frame_numbers: np.ndarray, times: np.ndarray, coeff: np.ndarray) -> str:
    """``coefficients.csv``: the header, then per frame its number, time and (P,) coefficients."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for t in range(coeff.shape[0]):
        # repr of a float64 round-trips exactly; engines parse it as float32
        w.writerow([int(frame_numbers[t]), repr(float(times[t]))] + [repr(float(x)) for x in coeff[t]])
    return buf.getvalue()


def wrinkle_manifest(maps: dict, stems: list[str], basis_names: list[str], columns: list[str], coefficients: str,
                     raster: TiledRaster, mode: str, half: bool, units: str, frames: int, gate: dict) -> dict:
    """``wrinkle.json``: how to blend the set (formula, files per tile, coefficients) and what it holds.

    ``maps``: {stem: {tile: path}} of the constant (``stems[0]``) and basis maps.
    """
    tiles = list(raster.tiles)
    return {
        "kind": "facepipe-wrinkle-maps",
        "formula": "map(frame) = C + sum_i coeff_i(frame) * M_i",
        "constant": {str(t): p.name for t, p in maps[stems[0]].items()},
        "basis": [{"index": i, "pose": basis_names[i], "coefficient": columns[2 + i],
                   "maps": {str(t): p.name for t, p in maps[stems[1 + i]].items()}} for i in range(len(stems) - 1)],
        "coefficients": coefficients,
        "coefficient_definition": "coeff_i = |f - f_i|: Euclidean distance of the frame's strain features f "
                                  "(relative length changes of the feature-graph edges) to basis pose i's",
        "mode": mode,
        "channels": "R,G,B = displacement along the local frame's t, b, n" if mode == "vector"
                    else "Y = displacement along the normal n",
        "space": "local frames (t, b, n) of the large-scale surface; see facepipe.core.tangent_frames",
        "units": units,
        "pixel_type": "half" if half else "float",
        "resolution": [raster.tiles[tiles[0]].width, raster.tiles[tiles[0]].height],
        "tiles": tiles,
        "frames": frames,
        "gate": gate,
    }


def read_coefficients(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read ``coefficients.csv``: frame numbers (T,), times (T,), coefficients (T, P)."""
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return data[:, 0].astype(np.int64), data[:, 1], data[:, 2:]


def blend_wrinkle_maps(const: np.ndarray, basis: list[np.ndarray], coeff: np.ndarray) -> np.ndarray:
    """A frame's map from a wrinkle set: C + Σ_i coeff_i M_i (what an engine's shader does).

    Parameters
    ----------
    const : (H, W[, C]) the constant map; basis : P maps like it; coeff : (P,) the frame's row.

    Returns
    -------
    (H, W[, C]) float64.
    """
    out = np.asarray(const, dtype=np.float64).copy()
    for c, m in zip(coeff, basis):
        out += float(c) * np.asarray(m, dtype=np.float64)
    return out



# ----------------------------------------------------------------------------- exporters of a replay


def export_exr(replay, dest: Path, options: ExportOptions) -> tuple[list[Path], dict]:
    """A replay's detail layer as per-frame displacement maps in ``dest`` (the ``exr`` format's
    exporter; ``replay``: a :class:`facepipe.io.replay_folder.ReplayDir`)."""
    model, mesh = _map_model(replay, options)
    mode, space = options.mode, options.space
    # every refusal before the raster, which takes seconds at 2048² and up
    if mode == "scalar" and space != "local":
        raise InputError("a scalar map is the displacement along the normal; --space applies to vector maps",
                         hint="drop --space, or export --vector maps")
    detail = DetailLayer(model, space, mesh)  # InputError for a model without details
    handles = replay.handles
    slots = "uv" if (space == "tangent" and mode == "vector") else "vertex"
    raster, attrs, info = _map_raster(replay, model, mesh, options, slots)
    half = True if options.half is None else options.half
    head = handles["head"]
    rot = handles["rotation"] if (space == "object" and handles["head_motion"] == "keep") else None
    frames, times = replay.frame_numbers, replay.times
    attrs.update({"facepipe/space": space,
                  "facepipe/channels": ("R,G,B = x,y,z" if space == "object" else "R,G,B = t,b,n")
                  if mode == "vector" else "Y = n"})

    if replay.large_scale_from_cache:
        # a mesh cache's large scale is its own surface: the stored layers give the details added to it
        values = StoredDetailLayer(replay, model, space, mesh)
    else:
        def values(s, e):
            return detail(head[s:e], None if rot is None else rot[s:e])

    samples: dict = {}
    with options.make_bar(replay.n_frames, "export exr") as bar:
        per_frame = write_displacement_maps(
            raster, values, replay.n_frames, dest, mode=mode, half=half, start=options.start, attributes=attrs,
            frame_attributes=lambda t: {"facepipe/frame": int(frames[t]), "facepipe/time": float(times[t])},
            force=options.force, resume=options.resume, progress=bar.update, report=samples)
    paths = [p for d in per_frame for p in d.values()]
    info.update(space=space, frames=replay.n_frames, vertex_samples=samples)
    if samples.get("over_limit"):
        info["notes"] = [_sample_note(samples, slots, frames)]
    info["pixel_type"] = "half" if half else "float"
    return paths, info


def export_wrinkle(replay, dest: Path, options: ExportOptions) -> tuple[list[Path], dict]:
    """A PSD replay's wrinkle-map set in ``dest`` (the ``wrinkle`` format's exporter)."""
    model, mesh = _map_model(replay, options)
    check_wrinkle_model(model)  # InputError for WPSD and none, with the reason
    handles = replay.handles
    raster, attrs, info = _map_raster(replay, model, mesh, options, "vertex")
    half = False if options.half is None else options.half
    P = model.basis_features.shape[0]
    with options.make_bar(P + 2, "export wrinkle", "file") as bar:
        manifest = write_wrinkle_maps(raster, model, handles["head"], replay.frame_numbers, replay.times, dest,
                                      mode=options.mode, half=half, attributes=attrs, force=options.force,
                                      resume=options.resume, progress=bar.update)
    paths = [dest / n for d in [manifest["constant"]] + [b["maps"] for b in manifest["basis"]]
             for n in d.values()] + [dest / manifest["coefficients"], dest / "wrinkle.json"]
    info.update(basis_poses=P, frames=replay.n_frames, gate=manifest["gate"])
    # worth a word when it shows (0.1 % of the detail range); wrinkle.json has the figures
    if manifest["gate"].get("active") and manifest["gate"]["relative"] >= 1e-3:
        info["notes"] = [_gate_note(manifest["gate"], replay.frame_numbers)]
    info["pixel_type"] = "half" if half else "float"
    return paths, info


def _map_model(replay, options: ExportOptions):
    """The model and rest mesh of a map export; ValueError for an unknown map mode."""
    model = replay.load_model(options.model_path)
    mesh = model.mesh()
    if options.mode not in MODES:
        raise ValueError(f"unknown map mode {options.mode!r}")
    return model, mesh


def _map_raster(replay, model, mesh, options: ExportOptions, slots: str) -> tuple[TiledRaster, dict, dict]:
    """The UV raster of a map export (InputError without UVs), the maps' header attributes and
    the report's map details."""
    width, height = options.resolution
    raster = mesh_raster(mesh, width, height, options.padding, slots=slots)
    attrs = {"facepipe/units": model.meta.get("units", ""), "facepipe/mode": options.mode,
             "facepipe/model": str(replay.model_path(options.model_path))}
    info = {"resolution": [width, height], "tiles": list(raster.tiles), "mode": options.mode,
            "padding": options.padding}
    return raster, attrs, info


def _sample_note(samples: dict, slots: str, frames: np.ndarray) -> str:
    """What to tell the user when maps miss vertex values (see :func:`lookup_report`)."""
    w = samples["worst"]
    return (f"{samples['over_limit']} of {samples['samples']} vertex samples of the maps are off by more than "
            f"{100 * samples['limit']:.0f} % of the detail range (at most {100 * samples['relative']:.2g} %, "
            f"{'UV' if slots == 'uv' else 'vertex'} {w['slot']} at UV {w['uv'][0]:.4f}, {w['uv'][1]:.4f} "
            f"in tile {w['tile']}, frame {int(frames[w['frame_index']])}; vertex_samples in --verbose): "
            f"where the UV layout gives vertices less than a texel each, no map of this size holds every "
            f"vertex value; a higher --resolution does (and --padding, at island borders)")


def _gate_note(gate: dict, frame_numbers: np.ndarray) -> str:
    """What to tell the user when a wrinkle set leaves out a novelty gate that shows."""
    return (f"the model's novelty gate is not in the blend: at most {gate['max_abs']:.3g} "
            f"({100 * gate['relative']:.2g} % of the detail range) from the gated details, at frame "
            f"{int(frame_numbers[gate['worst_frame_index']])} (see wrinkle.json 'gate'); bake with "
            f"[psd] novelty_tau = 0 for a blend that reproduces the model exactly")
