"""The fit file and the baked model file: write, read, validate, version.

A model is one ``.npz`` (float32 for the large arrays) with everything replay and export
need: rest mesh and its polygons/UVs/groups, handles, B, feature graph, WPSD edge weights,
RBF weights; :class:`Model` lists them. It carries a format version and the digest of the
config and input files it was made from.
"""

from __future__ import annotations

import json
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from facepipe.io.npz_file import NpzWriter, open_npz
from facepipe.errors import InputError
from facepipe.core.mesh import Mesh
from facepipe.core.psd import DetailModel, edge_weight_matrix
from facepipe.core.novelty import NoveltyGate
from facepipe.core.strain_details import DEFAULT_RIDGE, StrainDetailModel

FORMAT_VERSION = 1
MODEL_KIND = "facepipe-model"
FIT_KIND = "facepipe-fit"


def _stored(dtype, optional: bool = False):
    """A :class:`Model` field kept in the ``.npz`` as ``dtype``; an optional one is None where
    the file lacks it (older files, or a model without that part)."""
    return field(default=None, metadata={"dtype": dtype}) if optional else field(metadata={"dtype": dtype})


@dataclass(eq=False)
class Model:
    """A baked model: the arrays replay and export read, its metadata and where it came from.

    Read by :func:`load_model` (arrays in their stored dtypes) or made by
    :func:`model_from_fit` (in memory, as computed). The file is a ``.npz`` with one array per
    field below (the optional ones only where the model has them) and ``meta`` (JSON bytes);
    each field's ``metadata["dtype"]`` is the dtype it is stored as. Shapes: V vertices, T
    triangles, N polygons with C corners, H handles, A anchors, F feature edges, P basis poses
    (the rest pose first), K edge weights per vertex, E example poses.

    Attributes
    ----------
    rest : (V, 3) rest positions.
    triangles : (T, 3) the rest mesh's polygons fan-triangulated (the shell's and frames' mesh).
    polygon_offsets : (N + 1,) polygon ``k`` is ``polygon_vertices[offsets[k]:offsets[k + 1]]``.
    polygon_vertices : (C,) vertex of every polygon corner (export writes these polygons).
    handle_vertices : (H,) the vertex each handle (marker driving the shell) sits on.
    stable : (H,) the handles used for head motion (role ``stable``).
    anchors : (A,) vertices fixed to the skull.
    B : (V, H) large-scale basis: positions = rest + B @ handle displacements.
    edges : (F, 2) feature graph, pairs of handle indices.
    rest_lengths : (F,) the feature edges' lengths at rest.
    frame_neighbors : (V,) the neighbour that fixes each vertex's tangent frame.
    basis_features : (P, F) strain features of the basis poses.
    rbf_weights : (V, P, 3) RBF weights of the details, in local frames.
    rbf_const : (V, 3) constant term of the details.
    edge_index, edge_weight : (V, K) each vertex's feature edges and WPSD weights α.
    example_handles : (E + 1, H, 3) head-space handles of the rest pose and every example (the
        rig's prior over marker configurations).
    meta : dict, the JSON metadata: ``kind``, ``format_version``, ``method`` (psd | wpsd |
        none), ``marker_names`` (H), ``units``, ``config``, ``config_digest``, ``basis`` and
        ``example_names`` (pose names), ``beta``, ``novelty_tau``, ``marker_spacing``, ``shell``
        (the large-scale settings), ``smoothing``, and ``tuned`` after ``fit --tune``. A plain
        dict, so a key added by a newer version reads the same.
    uvs : (U, 2) texture coordinates, or None.
    polygon_uvs : (C,) UV of every polygon corner, or None.
    novelty_index, novelty_weight : (F, K) the novelty gate's neighbour edges per site and their
        √weights, or None without a gate.
    novelty_examples, novelty_solve : (F, E, K) the examples' local strain per site and its
        regularised pseudo-inverse, or None without a gate.
    novelty_motion_index, novelty_motion_weight : (F, M) the handles around each site and their
        weights, or None (a gate of strain alone).
    novelty_motion_examples, novelty_motion_scale : (F, E, 3M) the examples' relative handle motion
        around each site and (F,) its scale: the gate's motion part, or None.
    polygon_groups : (N,) index into ``group_names`` of every polygon's OBJ group (``g``), or None
        (a rest mesh without groups, or a file written before groups were kept).
    group_names : list of str, the OBJ group names (``"default"`` before the first ``g``), or None.
    strain_samples, strain_weights : (V, N, 3) method ``local_strain``: the N training poses' local
        strain at every vertex and the kernel weights of the details over it (the kernel's width
        is ``meta["strain_width"]``), or None for the other methods.
    weld_index : (V_file,) the model vertex of every vertex of the mesh file, where ``[rig] weld``
        welded vertices split along seams (mesh caches in the file's order are read through it,
        MDD and PC2 exports written in that order), or None.
    landmark_vertices : (L,) the rig vertex of every point of a 2D tracker (the config's
        ``[video] landmarks``; their names are ``meta["landmark_names"]``), or None.
    path : where the model was read from ("(in memory)" for :func:`model_from_fit`).
    """

    rest: np.ndarray = _stored(np.float32)
    triangles: np.ndarray = _stored(np.int32)
    polygon_offsets: np.ndarray = _stored(np.int64)
    polygon_vertices: np.ndarray = _stored(np.int32)
    handle_vertices: np.ndarray = _stored(np.int32)
    stable: np.ndarray = _stored(np.bool_)
    anchors: np.ndarray = _stored(np.int32)
    B: np.ndarray = _stored(np.float32)
    edges: np.ndarray = _stored(np.int32)
    rest_lengths: np.ndarray = _stored(np.float32)
    frame_neighbors: np.ndarray = _stored(np.int32)
    basis_features: np.ndarray = _stored(np.float32)
    rbf_weights: np.ndarray = _stored(np.float32)
    rbf_const: np.ndarray = _stored(np.float32)
    edge_index: np.ndarray = _stored(np.int32)
    edge_weight: np.ndarray = _stored(np.float32)
    example_handles: np.ndarray = _stored(np.float32)
    meta: dict = field(default_factory=dict)
    uvs: np.ndarray | None = _stored(np.float32, optional=True)
    polygon_uvs: np.ndarray | None = _stored(np.int32, optional=True)
    novelty_index: np.ndarray | None = _stored(np.int32, optional=True)
    novelty_weight: np.ndarray | None = _stored(np.float32, optional=True)
    novelty_examples: np.ndarray | None = _stored(np.float32, optional=True)
    novelty_solve: np.ndarray | None = _stored(np.float32, optional=True)
    novelty_motion_index: np.ndarray | None = _stored(np.int32, optional=True)
    novelty_motion_weight: np.ndarray | None = _stored(np.float32, optional=True)
    novelty_motion_examples: np.ndarray | None = _stored(np.float32, optional=True)
    novelty_motion_scale: np.ndarray | None = _stored(np.float32, optional=True)
    polygon_groups: np.ndarray | None = _stored(np.int32, optional=True)
    group_names: list[str] | None = _stored(np.str_, optional=True)
    landmark_vertices: np.ndarray | None = _stored(np.int32, optional=True)
    weld_index: np.ndarray | None = _stored(np.int32, optional=True)
    strain_samples: np.ndarray | None = _stored(np.float32, optional=True)
    strain_weights: np.ndarray | None = _stored(np.float32, optional=True)
    path: str = ""

    @classmethod
    def from_arrays(cls, arrays: dict, meta: dict, path: str = "") -> "Model":
        """A Model from a dict of its arrays (as :func:`model_arrays` gives them; missing
        optional ones are None, names that are no field are ignored)."""
        values = {name: arrays[name] for name in _MODEL_ARRAYS}
        values.update({name: arrays.get(name) for name in _OPTIONAL})
        if values["group_names"] is not None:
            values["group_names"] = [str(name) for name in values["group_names"]]
        return cls(**values, meta=meta, path=str(path))

    @property
    def arrays(self) -> dict:
        """The stored arrays by name (a new dict, without the optional ones the model lacks):
        what :func:`save_model` writes."""
        return {name: getattr(self, name) for name in {**_MODEL_ARRAYS, **_OPTIONAL}
                if getattr(self, name) is not None}

    @property
    def method(self) -> str:
        return self.meta["method"]

    @property
    def marker_names(self) -> list[str]:
        return list(self.meta["marker_names"])

    @property
    def n_vertices(self) -> int:
        return int(self.rest.shape[0])

    def detail_model(self, dtype=np.float64) -> DetailModel:
        weights = edge_weight_matrix(self.edge_index, self.edge_weight, len(self.edges)).astype(dtype)
        return DetailModel(self.method, self.basis_features.astype(dtype), self.rbf_weights.astype(dtype),
                           self.rbf_const.astype(dtype), weights if self.method == "wpsd" else None,
                           self.novelty_gate(weights, dtype))

    def strain_detail_model(self, dtype=np.float64) -> StrainDetailModel | None:
        """The local-strain detail model (method ``local_strain``), else None."""
        if self.method != "local_strain":
            return None
        return StrainDetailModel(self.strain_samples.astype(dtype), self.strain_weights.astype(dtype),
                                 float(self.meta["strain_width"]),
                                 float(self.meta.get("strain_ridge", DEFAULT_RIDGE)))

    def novelty_gate(self, alpha: sp.spmatrix, dtype=np.float64) -> NoveltyGate | None:
        """The model's novelty gate with the site-to-vertex weights ``alpha`` (the model's own α,
        or another: the OpenCL engine takes per-site factors with the identity); None without one."""
        if self.novelty_solve is None or not self.meta.get("novelty_tau", 0) > 0:
            return None
        motion = {}
        if self.novelty_motion_examples is not None:
            motion = dict(motion_index=self.novelty_motion_index, motion_weight=self.novelty_motion_weight.astype(dtype),
                          motion_examples=self.novelty_motion_examples.astype(dtype),
                          motion_scale=self.novelty_motion_scale.astype(dtype))
        return NoveltyGate(self.novelty_index, self.novelty_weight.astype(dtype), self.novelty_examples.astype(dtype),
                           self.novelty_solve.astype(dtype), float(self.meta["novelty_tau"]), alpha, **motion)

    def mesh(self) -> Mesh:
        """The rest mesh with its original polygons, UVs and groups (for export)."""
        return Mesh(
            vertices=self.rest.astype(np.float64),
            polygon_offsets=self.polygon_offsets.astype(np.int64),
            polygon_vertices=self.polygon_vertices.astype(np.int64),
            uvs=None if self.uvs is None else self.uvs.astype(np.float64),
            polygon_uvs=None if self.polygon_uvs is None else self.polygon_uvs.astype(np.int64),
            polygon_groups=None if self.polygon_groups is None else self.polygon_groups.astype(np.int32),
            group_names=list(self.group_names or []),
            path=self.path,
        )


# name -> dtype written: every array replay or export reads, then those a model may lack
_MODEL_ARRAYS = {f.name: f.metadata["dtype"] for f in fields(Model) if "dtype" in f.metadata and f.default is MISSING}
_OPTIONAL = {f.name: f.metadata["dtype"] for f in fields(Model) if "dtype" in f.metadata and f.default is None}


def geometry_arrays(geo, rig) -> dict:
    """The arrays of a model that its rig and large-scale geometry fix (the rest mesh, B, the
    feature graph, ...): known once the shell basis is solved, before the details are fitted, and
    two thirds of a model file (so a bake writes them while it fits the rest)."""
    mesh = rig.mesh
    arrays = {
        "rest": geo.rest,
        "triangles": geo.faces,
        "polygon_offsets": mesh.polygon_offsets,
        "polygon_vertices": mesh.polygon_vertices,
        "handle_vertices": geo.handles,
        "stable": rig.markers.stable,
        "anchors": rig.anchors,
        "B": geo.B,
        "edges": geo.edges,
        "rest_lengths": geo.rest_lengths,
        "frame_neighbors": geo.neighbors,
        # head-space handle positions of the rest pose and every example: the rig's prior over
        # marker configurations (gap filling, blend-shape baselines)
        "example_handles": np.concatenate([geo.rest[None, geo.handles], rig.example_positions[:, geo.handles]]),
    }
    if mesh.uvs is not None:
        arrays["uvs"] = mesh.uvs
        arrays["polygon_uvs"] = mesh.polygon_uvs
    # the OBJ groups, for the OBJ export to write back (none kept when every polygon is in the
    # unnamed group "default": such a mesh's model is as before)
    if mesh.polygon_groups is not None and any(name != "default" for name in mesh.group_names):
        arrays["polygon_groups"] = mesh.polygon_groups
        arrays["group_names"] = np.asarray(mesh.group_names, dtype=np.str_)
    if rig.welded is not None:
        arrays["weld_index"] = rig.weld_index
    if rig.landmarks is not None:
        arrays["landmark_vertices"] = rig.landmarks.vertices
    return arrays


def geometry_to(npz: NpzWriter):
    """An ``on_geometry(rig, geometry)`` for :func:`~facepipe.pipeline.fit.fit_rig` that hands the
    model's :func:`geometry_arrays` to ``npz`` (the bake writes them while it fits the details)."""
    return lambda rig, geo: add_model_arrays(npz, geometry_arrays(geo, rig))


def model_arrays(fit, rig) -> tuple[dict, dict]:
    """Arrays and metadata of a model from a FitResult and its Rig."""
    geo = fit.geometry
    arrays = dict(geometry_arrays(geo, rig), basis_features=fit.model.basis_features, rbf_weights=fit.model.weights,
                  rbf_const=fit.model.const, edge_index=fit.edge_index, edge_weight=fit.edge_weight)
    gate = fit.model.gate
    if gate is not None:
        arrays.update(novelty_index=gate.index, novelty_weight=gate.sqrt_weight, novelty_examples=gate.examples,
                      novelty_solve=gate.solve)
        if gate.has_motion:
            arrays.update(novelty_motion_index=gate.motion_index, novelty_motion_weight=gate.motion_weight,
                          novelty_motion_examples=gate.motion_examples, novelty_motion_scale=gate.motion_scale)
    meta = {
        "kind": MODEL_KIND,
        "format_version": FORMAT_VERSION,
        "method": fit.model.method,
        "marker_names": rig.markers.handle_names,
        "units": rig.config.units,
        "config": str(rig.config.path),
        "config_digest": rig.digest,
        "basis": [fit.example_names[i] for i in fit.basis],
        "example_names": list(fit.example_names),
        "beta": fit.beta,
        "novelty_tau": 0.0 if gate is None else gate.tau,
        "marker_spacing": geo.spacing,
        "shell": {"k_stretch": rig.config.shell.k_stretch, "k_bend": rig.config.shell.k_bend,
                  "method": rig.config.shell.method, "rbf_lambda": rig.config.shell.rbf_lambda,
                  "phantoms": rig.config.shell.phantoms, "solver": geo.solver},
        "smoothing": rig.config.psd.smoothing,
    }
    strain = getattr(fit, "strain_model", None)
    if fit.model.method == "local_strain" and strain is not None:
        arrays.update(strain_samples=strain.samples, strain_weights=strain.weights)
        meta["strain_width"], meta["strain_ridge"] = strain.width, strain.ridge
    if rig.welded is not None:  # [rig] weld: the mesh file's count, the model's, and its vertex order
        meta["welded"] = dict(rig.welded)
    if rig.landmarks is not None:  # a 2D take replays with this map unless --landmarks gives another
        meta["landmark_names"] = list(rig.landmarks.names)
        meta["landmark_map"] = str(rig.landmarks.path)
    if "tune" in fit.report:  # the values `fit --tune` chose, with their validated error
        meta["tuned"] = dict(fit.report["tune"]["chosen"], fallback=fit.report["tune"]["fallback"])
    return arrays, meta


def save_model(path, arrays: dict, meta: dict) -> None:
    """Write a model .npz atomically, casting arrays to their stored dtypes."""
    with NpzWriter(path) as npz:
        add_model_arrays(npz, arrays, meta)


def add_model_arrays(npz: NpzWriter, arrays: dict, meta: dict | None = None, dtypes: bool = True) -> None:
    """Hand a model's arrays to an open :class:`~facepipe.io.npz_file.NpzWriter`, each in its
    stored dtype (``dtypes``; else as computed, as a fit file keeps them), except those it holds
    already; then ``meta``, if given (the last member: the file is complete).

    A bake hands over :func:`geometry_arrays` as soon as the shell basis is solved, and the
    rest once fitted: the same file as :func:`save_model` writes at the end."""
    for name, dtype in {**_MODEL_ARRAYS, **_OPTIONAL}.items():
        if arrays.get(name) is not None and name not in npz:
            npz.add(name, arrays[name], dtype if dtypes else None)
    if meta is not None:
        npz.add("meta", np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8))


def load_model(path) -> Model:
    """Read and validate a model file; InputError for anything but a complete, current model."""
    meta, data = _read_npz(path, MODEL_KIND)
    missing = [k for k in _MODEL_ARRAYS if k not in data]
    if missing:
        raise InputError(f"model file lacks {missing}", path=path, hint="bake it again with this facepipe version")
    arrays = {k: data[k] for k in list(_MODEL_ARRAYS) + list(_OPTIONAL) if k in data}
    V = arrays["rest"].shape[0]
    H = arrays["handle_vertices"].shape[0]
    checks = [
        (arrays["B"].shape == (V, H), f"B has shape {arrays['B'].shape}, expected ({V}, {H})"),
        (len(meta.get("marker_names", [])) == H, "marker names do not match the handles"),
        (arrays["rbf_weights"].shape[0] == V, "RBF weights do not match the vertex count"),
        (arrays["edge_index"].shape[0] == V, "edge weights do not match the vertex count"),
        (arrays["basis_features"].shape[1] == arrays["edges"].shape[0], "basis features do not match the graph"),
        (meta.get("method") in ("psd", "wpsd", "local_strain", "none"), f"unknown method {meta.get('method')!r}"),
        (meta.get("method") != "local_strain" or ("strain_samples" in arrays and "strain_weights" in arrays
         and arrays["strain_samples"].shape == arrays["strain_weights"].shape
         and arrays["strain_samples"].shape[0] == V and "strain_width" in meta),
         "a local_strain model without matching strain samples, weights and width"),
        (("polygon_groups" in arrays) == ("group_names" in arrays), "polygon groups without their names or back"),
        (("landmark_vertices" in arrays) == ("landmark_names" in meta), "landmark vertices without their names or back"),
    ]
    if "landmark_vertices" in arrays and "landmark_names" in meta:
        lv = arrays["landmark_vertices"]
        checks += [(lv.shape == (len(meta["landmark_names"]),) and (lv.size == 0 or 0 <= lv.min() and lv.max() < V),
                    "the landmark map's vertices do not match its names or the mesh")]
    if "weld_index" in arrays:
        wi = arrays["weld_index"]
        checks += [(wi.ndim == 1 and wi.size >= V and 0 <= wi.min() and wi.max() < V
                    and np.unique(wi).size == V, "the weld index does not map the mesh file onto the mesh")]
    if "polygon_groups" in arrays and "group_names" in arrays:
        groups, n_names = arrays["polygon_groups"], len(arrays["group_names"])
        n_polygons = arrays["polygon_offsets"].shape[0] - 1
        checks += [
            (groups.shape == (n_polygons,), f"polygon groups have shape {groups.shape}, expected ({n_polygons},)"),
            (arrays["group_names"].dtype.kind == "U", "group names are not text"),
            (groups.size == 0 or 0 <= groups.min() and groups.max() < n_names,
             f"polygon groups are not all among the {n_names} group names"),
        ]
    for ok, message in checks:
        if not ok:
            raise InputError(f"corrupt model: {message}", path=path, hint="bake the model again")
    return Model.from_arrays(arrays, meta, str(path))


def _read_npz(path, kind: str) -> tuple[dict, dict]:
    path = Path(path)
    name = "fit" if kind == FIT_KIND else "model"
    expected = f"a {name} file written by 'facepipe {'fit' if kind == FIT_KIND else 'bake'}'"
    with open_npz(path, expected, hint=f"give the {name} file (e.g. {name}.npz)") as npz:
        try:
            data = dict(npz)
            meta = json.loads(bytes(data.pop("meta")).decode())
        except Exception as exc:  # damaged members, no or bad metadata: not our file, or truncated
            raise InputError(f"not a readable facepipe file ({exc.__class__.__name__}: {exc}); expected {expected}",
                             path=path) from None
    if meta.get("kind") != kind:
        raise InputError(f"this is a {meta.get('kind', 'unknown')} file, expected a {kind} file", path=path)
    if meta.get("format_version") != FORMAT_VERSION:
        raise InputError(f"format version {meta.get('format_version')} is not {FORMAT_VERSION}", path=path,
                         hint="re-run fit/bake with this facepipe version")
    return meta, data


def save_fit(path, fit, rig) -> None:
    """Write the fit file: the model's arrays plus per-example features, details and the report."""
    arrays, meta = model_arrays(fit, rig)
    extra = {
        "example_features": fit.features.astype(np.float32),
        "example_details": fit.details.astype(np.float32),
        "basis_index": np.asarray(fit.basis, dtype=np.int32),
    }
    with NpzWriter(path) as npz:
        for name, array in extra.items():
            npz.add(name, array)
        add_model_arrays(npz, arrays, dict(meta, kind=FIT_KIND, report=fit.report), dtypes=False)


def load_fit(path) -> tuple[dict, dict]:
    """Arrays and metadata of a fit file (for bake)."""
    meta, data = _read_npz(path, FIT_KIND)
    return data, meta


def fit_to_model(path_in, path_out, stage=None) -> dict:
    """Bake a fit file into a model file; returns the model metadata. ``stage(name)`` is called as
    reading and writing start (a large model takes seconds for each)."""
    stage = stage or (lambda name: None)
    stage("reading the fit")
    data, meta = load_fit(path_in)
    stage("writing the model")
    meta = {k: v for k, v in meta.items() if k != "report"}
    meta["kind"] = MODEL_KIND
    save_model(path_out, data, meta)
    return meta



def model_from_fit(fit, rig, method: str | None = None, n_poses: int | None = None,
                   strain_model: StrainDetailModel | None = None) -> Model:
    """An in-memory Model from a FitResult, optionally of another method or a smaller basis
    (method ``local_strain`` from a fit of another method: pass its ``strain_model``, from
    :func:`facepipe.pipeline.local_strain_fit.fit_local_strain`)."""

    arrays, meta = model_arrays(fit, rig)
    if method == "local_strain":
        strain = strain_model if strain_model is not None else fit.strain_model
        if strain is None:
            raise ValueError("a local-strain model from a fit of another method needs its strain_model")
        none = fit.detail_model("none")
        arrays.update(basis_features=none.basis_features, rbf_weights=none.weights, rbf_const=none.const,
                      strain_samples=strain.samples, strain_weights=strain.weights)
        arrays = {k: v for k, v in arrays.items() if not k.startswith("novelty_")}
        meta = dict(meta, method=method, basis=["rest"], strain_width=strain.width, strain_ridge=strain.ridge,
                    novelty_tau=0.0)
    elif method is not None or n_poses is not None:
        method = method or fit.method
        detail = fit.detail_model(method, n_poses)
        arrays.update(basis_features=detail.basis_features, rbf_weights=detail.weights, rbf_const=detail.const,
                      strain_samples=None, strain_weights=None)
        meta.pop("strain_width", None)
        meta.pop("strain_ridge", None)
        basis = [0] if method == "none" else fit.bases[method][: None if n_poses is None else n_poses + 1]
        meta = dict(meta, method=method, basis=[fit.example_names[i] for i in basis])
    return Model.from_arrays(arrays, meta, "(in memory)")
