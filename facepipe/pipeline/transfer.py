"""Detail transfer: a model learned on one face, moved onto another face (Bickel et al. 2008, §5.4).

A dense correspondence comes from a few dozen marked points on both faces:

1. a similarity (scale, rotation, translation) maps the source's points onto the target's;
2. the aligned source is deformed so that its points land exactly on the target's (the
   linear thin shell with the points as handles, or the RBF volume morph where a part of the
   source holds no point);
3. every target vertex is projected onto the closest point of the deformed source whose
   triangle faces the same way (normal check), which gives it a source triangle and
   barycentric weights.

The model is then rebuilt on the target's own mesh: the large-scale basis B from the
target's shell, local frames from the target's topology, the feature graph between the
target's markers (the same marker pairs, the target's rest lengths), and the per-vertex
pose-space data interpolated barycentrically: the WPSD edge weights α (renormalised, at most
as many edges per vertex as on the source) and the details of the basis poses, rotated from
the source's local frames into the target's and fitted again with the target's α so that the
target reproduces the interpolated details exactly at the basis poses. Strain is relative
stretch, so the basis features carry over unchanged; details are lengths and are scaled by
the similarity's scale.

Everything here is arrays in, arrays out, except :func:`transfer_files` (the CLI's entry).
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from facepipe.errors import InputError
from facepipe.core.closest import project_points
from facepipe.core.nonrigid import Refinement, refine_to_surface
from facepipe.core.tangent_frames import frame_neighbors, local_frames, to_local, to_world, vertex_normals
from facepipe.core.mesh import (check_components, check_marker_vertices, check_mesh, coincident_vertices,
                                component_labels, weld_vertices)
from facepipe.io.mesh_read import load_mesh
from facepipe.core.psd import edge_weight_matrix, fit_details
from facepipe.core.rbf_morph import multiquadric_basis
from facepipe.core.rigid import similarity_fit
from facepipe.core.runs import offsets_within
from facepipe.core.shell import marker_spacing, shell_basis
from facepipe.core.strain import edge_lengths
from facepipe.io.atomic import atomic_path
from facepipe.io.model_file import load_model, save_model
from facepipe.mocap.markers import known_unit_ratios, normalise_units, unit_factor
from facepipe.pipeline.fit import solve_large_scale_basis
from facepipe.pipeline.rig import load_anchors, load_markers, name_vertex_rows, split_mesh_error

MIN_POINTS = 4
# a point farther than this fraction of the points' RMS radius from where the similarity of
# all the others puts it does not mark the same feature on both faces (a swapped name)
MISMATCH_FRACTION = 0.3
# target vertices farther than this fraction of the points' spacing from the deformed source
# are not explained by the fit: the deformation only controls the surface at that scale
FAR_FRACTION = 0.5


# ----------------------------------------------------------------------------- points


def read_points(path, n_vertices: int) -> dict[str, int]:
    """Correspondence points of a face: a CSV ``name,vertex`` (header and ``#`` comments allowed).

    Returns
    -------
    {name: vertex} in the file's order (0-based vertices).
    """
    names, vertices, lines = [], [], []
    for line_no, name, vertex, _ in name_vertex_rows(path, "point"):
        names.append(name)
        vertices.append(vertex)
        lines.append(line_no)
    check_marker_vertices(np.asarray(vertices, dtype=np.int64), n_vertices, names, path, lines=lines)
    return dict(zip(names, vertices))


def match_points(source: dict[str, int], target: dict[str, int], source_path="", target_path=""):
    """The points both files name, in the source's order.

    Returns
    -------
    names : list[str]; source_vertices, target_vertices : (N,) int64.

    Raises
    ------
    InputError
        A name in one file only (a typo would silently drop a point), or fewer than
        :data:`MIN_POINTS` points.
    """
    only_s = [n for n in source if n not in target]
    only_t = [n for n in target if n not in source]
    if only_s or only_t:
        parts = []
        if only_s:
            parts.append(f"{len(only_s)} only in {source_path or 'the source points'}: {', '.join(only_s[:8])}")
        if only_t:
            parts.append(f"{len(only_t)} only in {target_path or 'the target points'}: {', '.join(only_t[:8])}")
        raise InputError("the point files name different points (" + "; ".join(parts) + ")", path=target_path,
                         hint="mark the same named points on both faces (about 40, spread over the face)")
    names = list(source)
    if len(names) < MIN_POINTS:
        raise InputError(f"{len(names)} correspondence points; at least {MIN_POINTS} are needed", path=source_path,
                         hint="mark about 40 points spread over the face (eye and mouth corners, nose, chin, "
                              "brows, cheeks, jaw line) on both faces")
    return (names, np.array([source[n] for n in names], dtype=np.int64),
            np.array([target[n] for n in names], dtype=np.int64))


def similarity_align(source_points: np.ndarray, target_points: np.ndarray, names=None, path=""):
    """Similarity target ≈ s R source + t of the points, checked for points that do not match.

    Parameters
    ----------
    source_points, target_points : (N, 3) positions of the same named points.

    Returns
    -------
    s : float; R : (3, 3); t : (3,); residual : (N,) distance of each aligned point from its
    target (length units of the target).

    Raises
    ------
    InputError
        Degenerate points (all on a line), or a point whose residual exceeds
        :data:`MISMATCH_FRACTION` of the points' RMS radius — it is named.
    """
    src = np.asarray(source_points, dtype=np.float64)
    tgt = np.asarray(target_points, dtype=np.float64)
    centred = tgt - tgt.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[1] <= 1e-6 * max(sv[0], 1e-300):
        raise InputError("the correspondence points lie on a line: no orientation can be found", path=path,
                         hint="spread the points over the face")
    s, R, t = similarity_fit(src, tgt)
    s, R, t = float(s), np.asarray(R), np.asarray(t)
    residual = np.linalg.norm(s * src @ R.T + t - tgt, axis=1)
    radius = float(np.sqrt((centred ** 2).sum(axis=1).mean()))
    bad = np.flatnonzero(residual > MISMATCH_FRACTION * radius)
    if bad.size:
        worst = bad[np.argsort(-residual[bad])]
        label = [f"{names[i] if names else i} ({residual[i]:.3g} off)" for i in worst[:5]]
        raise InputError(f"{bad.size} point(s) do not match after aligning the faces: {', '.join(label)}; "
                         f"the points' radius is {radius:.3g}", path=path,
                         hint="check that each named point marks the same feature on both faces "
                              "(left and right swapped? a vertex index off?)")
    return s, R, t, residual


# ----------------------------------------------------------------------------- deform and project


def deform_to_points(vertices: np.ndarray, faces: np.ndarray, point_vertices: np.ndarray,
                     targets: np.ndarray, method: str = "auto") -> tuple[np.ndarray, str]:
    """Deform a mesh so that its point vertices move exactly onto ``targets``.

    Parameters
    ----------
    vertices : (V, 3); faces : (T, 3); point_vertices : (N,) int; targets : (N, 3).
    method : "shell" (biharmonic thin shell over the mesh, the points as handles), "rbf"
        (RBF volume morph: needs no connectivity) or "auto" (the shell when every connected
        part of the mesh holds a point, else the morph).

    Returns
    -------
    deformed : (V, 3); the method used.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    point_vertices = np.asarray(point_vertices, dtype=np.int64)
    u_h = np.asarray(targets, dtype=np.float64) - vertices[point_vertices]
    if method == "auto":
        method = "shell" if _every_part_has(faces, len(vertices), point_vertices) else "rbf"
    if method == "shell":
        B = shell_basis(vertices, faces, point_vertices, None, k_stretch=0.0, k_bend=1.0)
    elif method == "rbf":
        B = multiquadric_basis(vertices, point_vertices, np.zeros(0, dtype=np.int64), 0.0)
    else:
        raise ValueError(f"unknown deformation {method!r}")
    deformed = vertices + B @ u_h
    deformed[point_vertices] = targets  # exactly, whatever the solver's rounding
    return deformed, method


def _every_part_has(faces: np.ndarray, n_vertices: int, vertices: np.ndarray) -> bool:

    f = np.asarray(faces, dtype=np.int64)
    g = sp.coo_matrix((np.ones(2 * len(f)), (np.r_[f[:, 0], f[:, 1]], np.r_[f[:, 1], f[:, 2]])),
                      shape=(n_vertices, n_vertices))
    _, labels = connected_components(g, directed=False)
    return bool(np.isin(np.unique(labels), labels[vertices]).all())


@dataclass
class Correspondence:
    """Target vertices on the source surface, and how the source was brought onto the target.

    Attributes
    ----------
    face : (Vt,) int64 source triangle of every target vertex; bary : (Vt, 3) its weights.
    distance : (Vt,) from the target vertex to the deformed source (target length units).
    normal_ok : (Vt,) bool: the source triangle faces the target vertex's way.
    deformed : (Vs, 3) the source after the similarity and the fit to the target's points.
    scale, rotation, translation : the similarity source → target.
    point_residual : (N,) the points' distances after the similarity alone.
    point_spacing : mean nearest-neighbour distance of the target's points.
    method : the deformation used ("shell" or "rbf").
    refinement : the non-rigid refinement onto the target's surface (None when not refined).
    """
    face: np.ndarray
    bary: np.ndarray
    distance: np.ndarray
    normal_ok: np.ndarray
    deformed: np.ndarray
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    point_residual: np.ndarray
    point_spacing: float
    method: str
    source_faces: np.ndarray = field(repr=False, default=None)
    refinement: Refinement | None = field(repr=False, default=None)

    def matrix(self, n_source: int) -> sp.csr_matrix:
        """(Vt, Vs) sparse interpolation matrix: target values = W @ source values."""
        rows = np.repeat(np.arange(len(self.face)), 3)
        cols = self.source_faces[self.face].ravel()
        return sp.csr_matrix((self.bary.ravel(), (rows, cols)), shape=(len(self.face), n_source))


def correspond(source_vertices: np.ndarray, source_faces: np.ndarray, target_vertices: np.ndarray,
               target_faces: np.ndarray, source_points: np.ndarray, target_points: np.ndarray,
               names: list[str] | None = None, deform: str = "auto", path="", refine: bool = True) -> Correspondence:
    """Dense correspondence from marked points (see the module docstring).

    Parameters
    ----------
    source_vertices : (Vs, 3); source_faces : (Ts, 3); target_vertices : (Vt, 3); target_faces : (Tt, 3).
    source_points, target_points : (N,) vertex indices of the same named points on each mesh.
    deform : "auto" | "shell" | "rbf", see :func:`deform_to_points`.
    refine : after the fit to the points, move the whole source onto the target surface
        (:func:`facepipe.core.nonrigid.refine_to_surface`), so parts without points correspond too.
    """
    src = np.asarray(source_vertices, dtype=np.float64)
    tgt = np.asarray(target_vertices, dtype=np.float64)
    tp = tgt[target_points]
    s, R, t, residual = similarity_align(src[source_points], tp, names, path)
    aligned = s * src @ R.T + t
    deformed, method = deform_to_points(aligned, source_faces, source_points, tp, deform)
    spacing = float(cKDTree(tp).query(tp, k=2)[0][:, 1].mean())
    refinement = None
    if refine:
        refinement = refine_to_surface(deformed, source_faces, tgt, target_faces, source_points, spacing)
        deformed = refinement.vertices
    normals = vertex_normals(tgt, np.asarray(target_faces, dtype=np.int64))
    face, bary, dist, ok = project_points(tgt, normals, deformed, source_faces)
    return Correspondence(face, bary, dist, ok, deformed, s, R, t, residual, spacing, method,
                          np.asarray(source_faces, dtype=np.int64), refinement)


def check_far(corr: Correspondence, max_distance: float | None = None) -> tuple[np.ndarray, float]:
    """Target vertices left far from the source: (indices, the limit used).

    ``max_distance`` None: :data:`FAR_FRACTION` × the target points' spacing.
    """
    limit = FAR_FRACTION * corr.point_spacing if max_distance is None else float(max_distance)
    return np.flatnonzero(corr.distance > limit), limit


def describe_far(far: np.ndarray, corr: Correspondence, target_vertices: np.ndarray, point_names: list[str],
                 target_point_vertices: np.ndarray, limit: float) -> str:
    """'N of V target vertices are farther than L from the source: vertex 12 (0.8 from it, near point chin) …'"""
    tv = np.asarray(target_vertices, dtype=np.float64)
    worst = far[np.argsort(-corr.distance[far])][:5]
    _, nearest = cKDTree(tv[target_point_vertices]).query(tv[worst])
    where = [f"vertex {int(v)} ({corr.distance[v]:.3g} off, nearest point {point_names[int(k)]!r})"
             for v, k in zip(worst, np.atleast_1d(nearest))]
    lo, hi = tv[far].min(axis=0), tv[far].max(axis=0)
    box = ", ".join(f"{a}: {x:.3g}..{y:.3g}" for a, x, y in zip("xyz", lo, hi))
    return (f"{far.size} of {len(tv)} target vertices are farther than {limit:.3g} from the source surface "
            f"after the fit to the points; the worst: " + "; ".join(where) + f"; they span {box}")


# ----------------------------------------------------------------------------- the model


def map_vertices(positions: np.ndarray, target_vertices: np.ndarray, exclude: np.ndarray | None = None,
                 k: int = 16) -> tuple[np.ndarray, int]:
    """Nearest target vertex of each position, every one distinct and none in ``exclude``.

    Returns
    -------
    (N,) int64 vertex indices; how many had to take a farther vertex than their nearest.
    """
    tree = cKDTree(target_vertices)
    k = min(k, len(target_vertices))
    dist, idx = tree.query(positions, k=k)
    dist, idx = dist.reshape(len(positions), k), idx.reshape(len(positions), k)
    taken = set() if exclude is None else set(int(v) for v in exclude)
    out = np.empty(len(positions), dtype=np.int64)
    moved = 0
    for i in np.argsort(dist[:, 0], kind="stable"):  # the best-placed ones choose first
        for j in range(k):
            v = int(idx[i, j])
            if v not in taken:
                out[i] = v
                moved += j > 0
                taken.add(v)
                break
        else:
            out[i] = -1
    return out, moved


def interpolate_alpha(W: sp.csr_matrix, alpha: sp.csr_matrix, max_edges: int,
                      chunk: int = 65536) -> tuple[np.ndarray, np.ndarray]:
    """WPSD edge weights of the target: barycentric mix of the source's, top ``max_edges``, rows sum 1.

    Parameters
    ----------
    W : (Vt, Vs) interpolation matrix (rows sum 1); alpha : (Vs, F) the source's weights.

    Returns
    -------
    edge_index : (Vt, K) int32; edge_weight : (Vt, K) float32 (unused slots 0).
    """
    V, K = W.shape[0], max_edges
    index = np.zeros((V, K), dtype=np.int32)
    weight = np.zeros((V, K), dtype=np.float32)
    for start in range(0, V, chunk):
        A = (W[start:start + chunk] @ alpha).tocsr()
        n = A.shape[0]
        counts = np.diff(A.indptr)
        width = max(int(counts.max(initial=0)), 1)
        rows = np.repeat(np.arange(n), counts)
        cols = offsets_within(counts)
        dense_w = np.zeros((n, width))
        dense_i = np.zeros((n, width), dtype=np.int64)
        dense_w[rows, cols] = A.data
        dense_i[rows, cols] = A.indices
        order = np.argsort(-dense_w, axis=1, kind="stable")[:, :K]
        top_w = np.take_along_axis(dense_w, order, axis=1)
        total = top_w.sum(axis=1, keepdims=True)
        k = top_w.shape[1]
        weight[start:start + n, :k] = top_w / np.where(total > 0, total, 1.0)
        index[start:start + n, :k] = np.take_along_axis(dense_i, order, axis=1)
    return index, weight


def transfer_model(model, target, corr: Correspondence, target_handles: np.ndarray | None = None,
                   scale_details: bool = True, units: str | None = None,
                   extra_anchors: np.ndarray | None = None) -> tuple[dict, dict, dict]:
    """The source model rebuilt on the target mesh.

    Parameters
    ----------
    model : facepipe.io.model_file.Model, the source.
    target : facepipe.core.mesh.Mesh, the target's rest mesh (polygons and UVs are kept).
    corr : the correspondence from :func:`correspond`.
    target_handles : (H,) the target's marker vertices in the model's marker order, or None to
        map each source marker to the nearest target vertex through the correspondence.
    scale_details : scale the details by the similarity's scale (faces of different sizes, and
        the units' ratio where they differ); without, by the units' ratio alone.
    units : the target mesh's length unit (canonical, :func:`facepipe.mocap.markers.normalise_units`),
        the new model's; None: the model's own.
    extra_anchors : target vertices held with the head besides those mapped from the source's
        anchors (a part of the target the source lacks: an eyeball, teeth).

    Returns
    -------
    arrays, meta : for :func:`facepipe.io.model_file.save_model`; report : dict (markers, anchors, times).
    """
    t0 = time.perf_counter()
    rest_t = np.asarray(target.vertices, dtype=np.float64)
    faces_t = np.asarray(target.faces, dtype=np.int64)
    report: dict = {}
    target_handles, report["markers"] = target_markers(model, target, corr, target_handles)
    anchors_t = target_anchors(model, rest_t, corr, target_handles)
    if extra_anchors is not None and len(extra_anchors):
        anchors_t = np.setdiff1d(np.union1d(anchors_t, np.asarray(extra_anchors, dtype=np.int64)), target_handles)
    report["anchors"] = {"source": int(len(model.anchors)), "target": int(len(anchors_t)),
                         "given": int(0 if extra_anchors is None else len(extra_anchors))}

    # large scale: the target's own shell (or morph), with the source's settings
    shell = source_shell_settings(model.meta)
    if shell.method != "rbf":
        check_components(target, np.concatenate([target_handles, anchors_t]), "marker or anchor",
                         hint="hold each such part (an eyeball, teeth) with the head: give --target-anchors FILE "
                              "listing one of its vertices (one index per line); or remove it from the target")
    spacing = marker_spacing(rest_t, target_handles)
    t1 = time.perf_counter()
    basis = solve_large_scale_basis(rest_t, faces_t, target_handles, anchors_t, shell, spacing)
    B = basis.B
    report["seconds_basis"] = time.perf_counter() - t1
    edges = model.edges.astype(np.int64)
    rest_lengths = _target_rest_lengths(rest_t[target_handles], edges, spacing, model.marker_names, target.path)

    # per-vertex pose-space data, through the correspondence
    W = corr.matrix(model.n_vertices)
    neighbors_t = frame_neighbors(faces_t, len(rest_t))
    alpha_s = edge_weight_matrix(model.edge_index, model.edge_weight, len(edges))
    edge_index, edge_weight = interpolate_alpha(W, alpha_s, model.edge_index.shape[1])
    alpha_t = edge_weight_matrix(edge_index, edge_weight, len(edges))
    source_units = model.meta.get("units", "cm")
    units = units or source_units
    rbf_weights, rbf_const = transferred_details(model, corr, W, local_frames(rest_t, faces_t, neighbors_t), alpha_t,
                                                 corr.scale if scale_details else unit_factor(source_units, units))
    # a part of the target that no marker drives (an eyeball held by --target-anchors) moves with the
    # head alone: it takes no details from the source skin it was mapped onto
    _, labels = component_labels(target)
    undriven = ~np.isin(labels, labels[target_handles])
    rbf_weights[undriven] = 0.0
    rbf_const[undriven] = 0.0
    report["vertices_without_details"] = int(undriven.sum())

    arrays = {
        "rest": rest_t,
        "triangles": faces_t,
        "polygon_offsets": target.polygon_offsets,
        "polygon_vertices": target.polygon_vertices,
        "handle_vertices": target_handles,
        "stable": model.stable,
        "anchors": anchors_t,
        "B": B,
        "edges": edges,
        "rest_lengths": rest_lengths,
        "frame_neighbors": neighbors_t,
        "basis_features": model.basis_features.astype(np.float64),
        "rbf_weights": rbf_weights,
        "rbf_const": rbf_const,
        "edge_index": edge_index,
        "edge_weight": edge_weight,
        "example_handles": transferred_example_handles(model.example_handles.astype(np.float64),
                                                       rest_t[target_handles], corr.scale, corr.rotation),
    }
    for key in ("novelty_index", "novelty_weight", "novelty_examples", "novelty_solve"):
        if key in model.arrays:  # per feature edge, not per vertex: the same on any mesh
            arrays[key] = model.arrays[key]
    if target.uvs is not None:
        arrays["uvs"] = target.uvs
        arrays["polygon_uvs"] = target.polygon_uvs
    # a 2D tracker's landmark map names source vertices: the target's is given with --landmarks
    meta = {k: v for k, v in model.meta.items() if k not in ("landmark_names", "landmark_map")}
    meta.update(
        config=f"transfer of {model.path} onto {target.path}",
        units=units,
        marker_spacing=spacing,
        shell=dict(model.meta.get("shell", {}), solver=basis.solver),  # the target's own factorisation
        beta=float(model.meta.get("beta", 0.0)) / corr.scale if model.meta.get("beta") else model.meta.get("beta"),
    )
    report["seconds"] = time.perf_counter() - t0
    return arrays, meta, report


def target_markers(model, target, corr: Correspondence, target_handles: np.ndarray | None) -> tuple[np.ndarray, dict]:
    """The target's marker vertices (given, or each source marker mapped to its own nearest target
    vertex through the correspondence) and the report on them (how they were found, offsets
    from where the correspondence puts the source's markers)."""
    rest_t = np.asarray(target.vertices, dtype=np.float64)
    handles_s = model.handle_vertices.astype(np.int64)
    if target_handles is None:
        target_handles, moved = map_vertices(corr.deformed[handles_s], rest_t)
        if (target_handles < 0).any():
            raise InputError("the target mesh is too coarse to give every marker a vertex of its own",
                             path=target.path, hint="give --target-markers, or use a finer target")
        report = {"mapped": len(model.marker_names), "moved_to_a_farther_vertex": int(moved)}
    else:
        report = {"given": len(model.marker_names)}
    target_handles = np.asarray(target_handles, dtype=np.int64)
    report["offset"] = _stats(np.linalg.norm(rest_t[target_handles] - corr.deformed[handles_s], axis=1))
    return target_handles, report


def target_anchors(model, rest_t: np.ndarray, corr: Correspondence, target_handles: np.ndarray) -> np.ndarray:
    """The target vertices nearest the source's anchors as the correspondence places them (markers excluded)."""
    anchors_s = model.anchors.astype(np.int64)
    if not len(anchors_s):
        return np.zeros(0, dtype=np.int64)
    near = cKDTree(rest_t).query(corr.deformed[anchors_s])[1]
    return np.setdiff1d(np.unique(near), target_handles)


def source_shell_settings(meta: dict) -> SimpleNamespace:
    """The source model's large-scale settings (method, stiffness, RBF smoothing and phantoms),
    with the k_stretch that ``fit --tune`` chose if it did, for the target's own basis."""
    shell_meta = dict(meta.get("shell", {}))
    if "k_stretch" in meta.get("tuned", {}):  # `fit --tune` chose the shell's stretch
        shell_meta["k_stretch"] = meta["tuned"]["k_stretch"]
    return SimpleNamespace(method=shell_meta.get("method", "shell"), k_stretch=shell_meta.get("k_stretch", 0.0),
                           k_bend=shell_meta.get("k_bend", 1.0), rbf_lambda=shell_meta.get("rbf_lambda", 0.01),
                           phantoms=int(shell_meta.get("phantoms", 0)))


def _target_rest_lengths(handle_positions: np.ndarray, edges: np.ndarray, spacing: float, names: list[str],
                         path) -> np.ndarray:
    """The feature edges' rest lengths on the target; InputError for an edge of zero length."""
    rest_lengths = edge_lengths(handle_positions, edges)
    short = np.flatnonzero(rest_lengths < 1e-9 * max(spacing, 1e-300))
    if short.size:
        a, b = edges[short[0]]
        raise InputError(f"on the target, feature edge {names[a]}–{names[b]} has zero rest length "
                         "(both markers on one vertex)", path=path, hint="check --target-markers")
    return rest_lengths


def transferred_details(model, corr: Correspondence, W: sp.csr_matrix, frames_t: np.ndarray, alpha_t: sp.csr_matrix,
                        detail_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The RBF weights (Vt, P, 3) and constants (Vt, 3) of the target's details.

    The source's raw (ungated) details at its basis poses, rotated from its local frames on the
    deformed source to world, interpolated onto the target (``W``), scaled, rotated into the
    target's frames ``frames_t`` and fitted again with the target's α, so the target reproduces
    them at the basis poses. Zeros for a model without details.
    """
    Vt = frames_t.shape[0]
    if model.method == "none":
        return np.zeros((Vt,) + model.rbf_weights.shape[1:]), np.zeros((Vt, 3))
    basis_features = model.basis_features.astype(np.float64)
    P = basis_features.shape[0]
    frames_s = local_frames(corr.deformed, model.triangles.astype(np.int64), model.frame_neighbors.astype(np.int64))
    # the raw details: the gate is applied on the target as on the source
    source = replace(model.detail_model(np.float64), gate=None)
    values = source.evaluate(basis_features)  # (P, Vs, 3) in the source's local frames
    world = to_world(frames_s, values)  # on the source as it lies on the target
    mapped = np.stack([W @ world[i] for i in range(P)]) * detail_scale
    local = to_local(frames_t, mapped)
    fitted = fit_details(model.method, basis_features, local, list(range(P)), "interpolate",
                         alpha_t if model.method == "wpsd" else None)
    return fitted.weights, fitted.const


def transferred_example_handles(example_handles: np.ndarray, target_rest_handles: np.ndarray, scale: float,
                                rotation: np.ndarray) -> np.ndarray:
    """The examples' marker positions (E + 1, H, 3; rest first) on the target: their displacements
    from the source's rest, rotated and scaled by the similarity, added to the target's markers."""
    return target_rest_handles[None] + scale * np.einsum("ij,ehj->ehi", rotation,
                                                         example_handles - example_handles[:1])


def _stats(x: np.ndarray) -> dict:
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return {}
    return {"median": float(np.median(x)), "p90": float(np.percentile(x, 90)),
            "p99": float(np.percentile(x, 99)), "max": float(x.max())}


# ----------------------------------------------------------------------------- files


#: The steps of :func:`transfer_files`, as a progress bar names them.
TRANSFER_STAGES = ("reading the model and the target", "corresponding the faces", "the target's shell and details",
                   "writing the model")


def transfer_files(model_path, target_path, source_points_path, target_points_path, output,
                   target_markers_path=None, deform: str = "auto", max_distance: float | None = None,
                   allow_far: bool = False, scale_details: bool = True, refine: bool = True,
                   target_units: str | None = None, target_anchors_path=None, target_weld: bool = False,
                   stage=None) -> dict:
    """``facepipe transfer``: read, correspond, transfer, write the model and its JSON summary.

    ``target_units``: the target mesh's length unit as written by the user (``mm``,
    ``Millimeters``, …), the new model's; None: the model's own. ``target_anchors_path``: a file
    of target vertices (one per line) held with the head besides the source's anchors.
    ``target_weld``: weld a target mesh split along seams (else it is refused); every target file
    (points, markers, anchors) then numbers the mesh file's vertices, as does a welded source's
    points file. ``stage(name)`` is called as each of :data:`TRANSFER_STAGES` starts (a progress bar).

    Returns
    -------
    The summary (also written as OUTPUT with the suffix .json).
    """
    t0 = time.perf_counter()
    stage = stage or (lambda name: None)
    stage(TRANSFER_STAGES[0])
    model = load_model(model_path)
    source_units = model.meta.get("units", "cm")
    units = normalise_units(target_units, what="unit (--target-units)") or source_units
    if model.method == "local_strain":
        raise InputError("transfer does not carry a local-strain model (its details are per-vertex functions of the "
                         "source's own strain)", path=model_path,
                         hint="bake the source rig with [psd] method = 'wpsd' or 'psd' to transfer it")
    target = load_mesh(target_path)
    n_file = target.n_vertices
    representative = coincident_vertices(target.vertices)
    weld_index = None
    if (representative != np.arange(n_file)).any():
        if not target_weld:
            raise split_mesh_error(target, representative, "pass --target-weld", where="")
        target, _, weld_index = weld_vertices(target, representative)
    check_mesh(target)

    def on_target(vertices) -> np.ndarray:  # the mesh file's numbering, on the (welded) target
        vertices = np.asarray(vertices, dtype=np.int64)
        return vertices if weld_index is None else weld_index[vertices]

    def on_source(points):  # a welded source's points number its mesh file's vertices
        return points if model.weld_index is None else {k: int(model.weld_index[v]) for k, v in points.items()}

    src_pts = on_source(read_points(source_points_path, model.n_vertices if model.weld_index is None
                                    else len(model.weld_index)))
    target_points = read_points(target_points_path, n_file)
    tgt_pts = dict(zip(target_points, on_target(list(target_points.values())).tolist()))
    names, sp_idx, tp_idx = match_points(src_pts, tgt_pts, source_points_path, target_points_path)
    target_handles = None
    if target_markers_path is not None:
        target_handles = on_target(read_target_markers(target_markers_path, model.marker_names, n_file))
    extra_anchors = on_target(load_anchors(target_anchors_path, n_file)) if target_anchors_path else None

    stage(TRANSFER_STAGES[1])
    corr = correspond(model.rest.astype(np.float64), model.triangles.astype(np.int64), target.vertices,
                      target.faces, sp_idx, tp_idx, names, deform, path=target_points_path, refine=refine)
    far, limit = check_far(corr, max_distance)
    if far.size and not allow_far:
        raise InputError(describe_far(far, corr, target.vertices, names, tp_idx, limit), path=target_path,
                         hint="mark more points where the faces differ (or check them); --max-distance D raises the "
                              "limit; --allow-far maps those vertices anyway (to the nearest source surface)")
    stage(TRANSFER_STAGES[2])
    arrays, meta, report = transfer_model(model, target, corr, target_handles, scale_details, units, extra_anchors)
    if weld_index is not None:  # --target-weld: the mesh file's count, the model's, and its vertex order
        arrays["weld_index"] = weld_index
        meta["welded"] = {"vertices": n_file, "welded": target.n_vertices, "split": int(n_file - target.n_vertices)}
    meta["config_digest"] = _inputs_digest(
        (model_path, target_path, source_points_path, target_points_path, target_markers_path, target_anchors_path),
        [deform, max_distance, scale_details, refine, units] + (["weld"] if weld_index is not None else []))
    summary = {
        "source": str(model_path),
        "target": str(target_path),
        "output": str(output),
        "source_vertices": int(model.n_vertices),
        "target_vertices": int(target.n_vertices),
        "vertices_mapped": int(target.n_vertices),
        "points": len(names),
        **correspondence_summary(corr, far, limit),
        "detail_scale": corr.scale if scale_details else unit_factor(source_units, units),
        "units": {"source": source_units, "target": units},
        "method": meta["method"],
        "uvs": target.uvs is not None,
        "notes": transfer_notes(corr, far, limit, target.uvs is not None, source_units, units,
                                given_units=target_units is not None) + (
            [f"--target-weld: {n_file - target.n_vertices} vertices split along seams welded, so the new model has "
             f"{target.n_vertices} vertices (the mesh file {n_file}); MDD and PC2 exports keep the file's order"]
            if weld_index is not None else []) + (
            [f"{report['vertices_without_details']} target vertices lie in parts that no marker drives (held by "
             "anchors): they move with the head and get no details"] if report["vertices_without_details"] else []),
        **report,
    }
    meta["transfer"] = {k: summary[k] for k in ("source", "target", "points", "deformation", "far_vertices",
                                                "detail_scale", "refined")}
    stage(TRANSFER_STAGES[3])
    save_model(output, arrays, meta)
    summary["seconds_total"] = time.perf_counter() - t0
    with atomic_path(Path(output).with_suffix(".json")) as tmp:
        tmp.write_text(json.dumps(summary, indent=2))
    return summary


def read_target_markers(path, marker_names: list[str], n_vertices: int) -> np.ndarray:
    """The target's vertex of every model marker, in the model's order, from a markers.csv;
    InputError naming the markers the file lacks."""
    markers = load_markers(Path(path), n_vertices)
    lookup = dict(zip(markers.names, markers.vertices.tolist()))
    missing = [n for n in marker_names if n not in lookup]
    if missing:
        raise InputError(f"{len(missing)} of the model's markers are not in the file: {', '.join(missing[:8])}",
                         path=path, hint="name every marker of the source model (markers.csv "
                                         "format: name,vertex[,role])")
    return np.array([lookup[n] for n in marker_names], dtype=np.int64)


def _inputs_digest(paths, options: list) -> str:
    """A short digest of the input files' bytes (those given) and the options."""
    digest = hashlib.sha256()
    for p in paths:
        if p is not None:
            digest.update(Path(p).read_bytes())
    digest.update(json.dumps(options).encode())
    return digest.hexdigest()[:16]


def correspondence_summary(corr: Correspondence, far: np.ndarray, limit: float) -> dict:
    """The summary's account of the correspondence: similarity, point residuals, deformation,
    projection distances, far vertices and normal mismatches."""
    return {
        "similarity": {"scale": corr.scale, "rotation_deg": float(np.degrees(np.arccos(np.clip(
            (np.trace(corr.rotation) - 1) / 2, -1, 1)))), "translation": corr.translation.tolist()},
        "point_residual_after_similarity": _stats(corr.point_residual),
        "point_spacing": corr.point_spacing,
        "deformation": corr.method,
        "projection_distance": _stats(corr.distance),
        "far_limit": limit,
        "far_vertices": int(far.size),
        "far_examples": [int(v) for v in far[np.argsort(-corr.distance[far])][:20]],
        "normal_mismatches": int((~corr.normal_ok).sum()),
        "refined": refinement_summary(corr),
    }


def refinement_summary(corr: Correspondence) -> dict | None:
    """How far the refined source lies from the target: both ways (target vertices to the refined
    source, refined source vertices to the target), mean, p95 and max; the stiffness steps and the
    share of source vertices paired with the target in the last one. None without refinement."""
    r = corr.refinement
    if r is None:
        return None

    def spread(x):
        return {"mean": float(np.mean(x)), "p95": float(np.percentile(x, 95)), "max": float(np.max(x))}

    return {"target_to_source": spread(corr.distance), "source_to_target": spread(r.distance),
            "stiffness_lengths": [float(x) for x in r.lengths], "paired_fraction": float(r.paired.mean())}


def transfer_notes(corr: Correspondence, far: np.ndarray, limit: float, target_has_uvs: bool, units: str,
                   target_units: str | None = None, given_units: bool = False) -> list[str]:
    """What the user should know about a transfer: no UVs on the target, far vertices mapped
    anyway, a size that suggests other units (``units`` the model's, ``target_units`` the
    target's, as given or the model's), vertices without a source triangle facing their way."""
    target_units = target_units or units
    notes = []
    if not target_has_uvs:
        notes.append("the target has no UVs: map exports (exr, wrinkle) of its replays will be refused")
    if far.size:
        notes.append(f"{far.size} target vertices farther than {limit:.3g} from the source were mapped anyway "
                     "(--allow-far)")
    size = corr.scale / unit_factor(units, target_units)  # the faces' size ratio in one unit
    if not 0.75 <= size <= 1.33:
        # a ratio a unit explains (a face in mm against a model in cm: 10) is named
        likely = [u for u, f in known_unit_ratios(units).items() if u != target_units and 0.75 <= corr.scale * f <= 1.33]
        where = f"in {target_units}" if given_units else f"in the model's units ({units})"
        advice = (f"if its mesh is in {likely[0]}, give --target-units {likely[0]}" if likely
                  else "check the target mesh's units")
        notes.append(f"the target, {where}, is {size:.3g}× the size of the source: {advice} — the new model's "
                     f"units are {target_units}")
    bad_normals = int((~corr.normal_ok).sum())
    if bad_normals:
        notes.append(f"{bad_normals} target vertices found no source triangle facing their way within the "
                     "candidates: mapped to the nearest")
    return notes
