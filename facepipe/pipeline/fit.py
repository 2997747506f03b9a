"""Fitting: large-scale basis, feature graph, details of the examples, greedy PSD/WPSD basis.

Everything here is arrays in, arrays out; the rig loader and the CLI do the I/O.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from facepipe.errors import InputError
from facepipe.io.config import Config, load_config
from facepipe.parallel import serial_blas
from facepipe.core.tangent_frames import frame_neighbors, local_frames, to_local, vertex_face_matrix
from facepipe.core.psd import (DetailModel, default_beta, edge_weight_matrix, fit_details, greedy_basis, rms_per_pose,
                               spread_subset, wpsd_edge_weights)
from facepipe.core.novelty import NoveltyGate, edge_distances, novelty_gate
from facepipe.core.rbf_morph import multiquadric_basis, phantom_points
from facepipe.pipeline.rig import Rig, load_rig
from facepipe.core.shell import ShellBasis, large_scale_positions, marker_spacing, solve_shell_basis
from facepipe.pipeline.geodesics import Geodesics
from facepipe.pipeline.local_strain_fit import fit_local_strain
from facepipe.core.strain import (auto_feature_graph, edge_graph, edge_lengths, graph_from_pairs, strain_features)
import csv
from pathlib import Path


@dataclass
class Geometry:
    """Rest-pose quantities shared by fitting and replay.

    rest : (V, 3); faces : (T, 3); handles : (H,) vertex indices; B : (V, H) large-scale basis;
    edges : (F, 2) handle-index pairs; rest_lengths : (F,); neighbors : (V,) frame neighbours;
    spacing : mean marker spacing (length units); solver : the sparse solver that factored the
    shell (None: the RBF morph, a dense solve); solver_passed_over : solvers tried before it, and why.
    """

    rest: np.ndarray
    faces: np.ndarray
    handles: np.ndarray
    B: np.ndarray
    edges: np.ndarray
    rest_lengths: np.ndarray
    neighbors: np.ndarray
    spacing: float
    incidence: sp.csr_matrix = field(repr=False, default=None)
    solver: str | None = None
    solver_passed_over: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.incidence is None:
            self.incidence = vertex_face_matrix(self.faces, self.rest.shape[0])

    def large_scale(self, poses: np.ndarray) -> np.ndarray:
        """Large-scale positions (E, V, 3) of poses (E, V, 3) from their handle vertices."""
        return large_scale_positions(self.rest, self.B, poses[:, self.handles] - self.rest[self.handles])

    def frames(self, positions: np.ndarray) -> np.ndarray:
        return local_frames(positions, self.faces, self.neighbors, self.incidence)

    def features(self, handle_positions: np.ndarray) -> np.ndarray:
        return strain_features(handle_positions, self.edges, self.rest_lengths)

    def details(self, poses: np.ndarray, chunk: int = 16) -> np.ndarray:
        """Details d = Rᵀ (pose − large-scale) in the large-scale mesh's local frames: (E, V, 3).

        A pose that is the rest mesh itself (the fit's pose 0) is its own large scale: its details
        are zero without computing its frames (at 530k vertices a seventh of this step)."""
        out = np.zeros_like(poses, dtype=np.float64)
        moved = np.flatnonzero([not np.array_equal(p, self.rest) for p in poses])
        for s in range(0, len(moved), chunk):
            rows = moved[s:s + chunk]
            some = poses[rows]
            large = self.large_scale(some)
            out[rows] = to_local(self.frames(large), some - large)
        return out


def solve_large_scale_basis(rest: np.ndarray, faces: np.ndarray, handles: np.ndarray, anchors: np.ndarray,
                            shell, spacing: float | None = None) -> ShellBasis:
    """The large-scale basis B (V, H) of a mesh, the thin shell or the RBF volume morph, with the
    sparse solver that factored the shell (None for the RBF morph: a dense solve).

    Parameters
    ----------
    rest : (V, 3); faces : (T, 3); handles : (H,) and anchors : (A,) vertex indices.
    shell : a :class:`~facepipe.io.config.ShellConfig` (or anything with its attributes: method,
        k_stretch, k_bend, rbf_lambda, phantoms).
    spacing : marker spacing h (length units); default: mean nearest-handle distance.
    """
    if spacing is None:
        spacing = marker_spacing(rest, handles)
    if getattr(shell, "method", "shell") == "rbf":
        phantoms = phantom_points(rest, faces, anchors, handles, shell.phantoms or None)
        return ShellBasis(multiquadric_basis(rest, handles, phantoms, shell.rbf_lambda), None)
    return solve_shell_basis(rest, faces, handles, anchors, k_stretch=shell.k_stretch, k_bend=shell.k_bend,
                             spacing=spacing)


def feature_graph(rig: Rig, mesh_graph: sp.csr_matrix | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The rig's feature edges (F, 2) (handle-index pairs) and their rest lengths (F,).

    ``mesh_graph``: the mesh's :func:`~facepipe.core.strain.edge_graph`, if at hand."""
    cfg = rig.config
    rest, handles = rig.mesh.vertices, rig.handles
    if cfg.graph == "auto":
        edges = auto_feature_graph(rest, rig.mesh.faces, handles, graph=mesh_graph)
    else:
        edges = graph_from_pairs(read_graph_csv(cfg.path.parent / cfg.graph), rig.markers.handle_names,
                                 str(cfg.path.parent / cfg.graph))
    if len(edges) == 0:
        raise InputError("the feature graph has no edges", path=cfg.path, hint="check the markers or give a graph CSV")
    rest_lengths = edge_lengths(rest[handles], edges)
    short = np.flatnonzero(rest_lengths < 1e-9 * max(marker_spacing(rest, handles), 1e-300))
    if len(short):
        a, b = edges[short[0]]
        names = rig.markers.handle_names
        raise InputError(f"feature edge {names[a]}–{names[b]} has zero rest length", path=cfg.markers)
    return edges, rest_lengths


def build_geometry(rig: Rig, k_stretch: float | None = None, k_bend: float | None = None,
                   graph: tuple[np.ndarray, np.ndarray] | None = None, basis: ShellBasis | None = None) -> Geometry:
    """Large-scale basis and feature graph of a rig (``graph``: from :func:`feature_graph`, if at hand;
    ``basis``: the large-scale basis of the rig's own deformer, if already solved)."""
    cfg = rig.config
    mesh = rig.mesh
    rest = mesh.vertices
    faces = mesh.faces
    handles = rig.handles
    spacing = marker_spacing(rest, handles)
    edges, rest_lengths = graph if graph is not None else feature_graph(rig)
    shell = cfg.shell
    if k_stretch is not None or k_bend is not None:
        shell = dataclasses.replace(shell, k_stretch=shell.k_stretch if k_stretch is None else k_stretch,
                                    k_bend=shell.k_bend if k_bend is None else k_bend)
    if basis is None or k_stretch is not None or k_bend is not None:
        basis = solve_large_scale_basis(rest, faces, handles, rig.anchors, shell, spacing)
    return Geometry(rest, faces, handles, basis.B, edges, rest_lengths, frame_neighbors(faces, len(rest)), spacing,
                    solver=basis.solver, solver_passed_over=basis.passed_over)


def read_graph_csv(path) -> list[tuple[str, str]]:
    """Marker-name pairs, one per line (``a,b``; a header ``a,b`` or comments are allowed)."""

    if not Path(path).is_file():
        raise InputError("feature graph file not found", path=path, hint="[features] graph = 'auto' or a CSV")
    pairs = []
    with open(path, newline="", encoding="utf-8") as fh:
        for line_no, row in enumerate(csv.reader(fh), start=1):
            row = [c.strip() for c in row if c.strip()]
            if not row or row[0].startswith("#"):
                continue
            if len(row) != 2:
                raise InputError(f"line {line_no}: expected two marker names", path=path)
            pairs.append((row[0], row[1]))
    return pairs


@dataclass
class FitResult:
    geometry: Geometry
    example_names: list[str]
    features: np.ndarray  # (E + 1, F), pose 0 = rest
    details: np.ndarray  # (E + 1, V, 3), pose 0 = rest
    method: str
    model: DetailModel
    basis: list[int]
    curves: dict  # method -> list of {"poses", "added", "mean_rms", "max_rms"}
    edge_index: np.ndarray | None
    edge_weight: np.ndarray | None
    beta: float
    report: dict
    bases: dict = field(default_factory=dict)  # method -> greedy basis (pose indices, rest first)
    alpha: sp.csr_matrix | None = None

    def detail_model(self, method: str, n_poses: int | None = None) -> DetailModel:
        """The model of ``method`` with the first ``n_poses`` greedily chosen poses (all by default)."""
        if method == "none":
            return dataclasses.replace(fit_details("psd", self.features, self.details, [0], "interpolate"),
                                       method="none")
        basis = self.bases[method] if n_poses is None else self.bases[method][: n_poses + 1]
        cfg = self.config
        model = fit_details(method, self.features, self.details, basis, cfg.fit, self.alpha, cfg.rcond,
                            cfg.smoothing)
        return dataclasses.replace(model, gate=self.gate)

    config: object = None
    gate: NoveltyGate | None = None
    strain_model: object = None  # method local_strain: a core.strain_details.StrainDetailModel


def handle_geodesics(mesh, handles: np.ndarray) -> Geodesics:
    """The Dijkstra runs from the handles over the mesh edges, started (the WPSD weights need them).

    They are the longest single-threaded part of a fit; on a large mesh a second process takes
    them on at once (:class:`~facepipe.pipeline.geodesics.Geodesics`)."""
    return Geodesics(edge_graph(mesh.vertices, mesh.faces, mesh.edges), handles)  # (the edges: kept for check_pose)


#: The steps of :func:`fit_config` (``stage`` is called with each as it starts); validation, run
#: between loading and the geometry by ``prepare``, has progress of its own.
FIT_STAGES = ("reading the rig", "validating parameters", "geodesic distances", "WPSD weights",
              "shell and local frames", "details of the examples", "greedy basis", "final detail model")


def fit_config(config, progress=None, prepare=None, stage=None, early_basis: bool = False, on_geometry=None
               ) -> tuple[Rig, "FitResult"]:
    """:func:`~facepipe.pipeline.rig.load_rig` and :func:`fit_rig`, with the geodesics from the handles
    started as soon as the rest mesh and markers are read, while the examples are still loading.

    ``prepare(rig, geodesics)``, if given, runs between the two (it may change ``rig.config``;
    ``geodesics.finish()`` gives the distances, which the fit then reuses). The load time is in
    ``fit.report["seconds"]["load"]``. ``stage(name)`` is called as each of :data:`FIT_STAGES` starts.

    ``early_basis``: the large-scale basis of the config's own deformer is solved in a thread from
    then on too, while the examples load (on a large mesh that wait is seconds, and the sparse
    factorisation runs in native code, off Python's lock); the fit uses it unless ``prepare``
    changed the deformer's parameters. Set it where validation will not run (it would compete
    with validation for the cores, for a basis validation may discard).

    ``on_geometry(rig, geometry)``: see :func:`fit_rig`.
    """
    stage = stage or (lambda name: None)
    t0 = time.perf_counter()
    config = config if isinstance(config, Config) else load_config(config)
    started: list[Geodesics] = []
    early: list = []  # (the deformer's parameters it was solved for, its Future)
    pool = ThreadPoolExecutor(1, thread_name_prefix="shell-basis") if early_basis else None

    def on_mesh(mesh, markers, anchors):
        if pool is not None:  # first: the longest wait, and the geodesics' start takes the main thread a while
            early.append((config.shell, pool.submit(solve_large_scale_basis, mesh.vertices, mesh.faces,
                                                    markers.handle_vertices, anchors, config.shell)))
        started.append(handle_geodesics(mesh, markers.handle_vertices))

    try:
        stage(FIT_STAGES[0])
        rig = load_rig(config, on_mesh=on_mesh)
        t_load = time.perf_counter() - t0
        stage(FIT_STAGES[1])
        if prepare is not None:
            prepare(rig, started[0])
        basis = None
        if early and rig.config.shell == early[0][0]:  # else validation chose other values
            basis = early[0][1].result  # waited for in the fit's shell stage
        fit = fit_rig(rig, progress=progress, geodesics=started[0], stage=stage, basis=basis, on_geometry=on_geometry)
    finally:
        for job in started:
            job.close()
        if pool is not None:
            pool.shutdown(wait=False)  # an error before the basis was needed: it finishes on its own and is dropped
    fit.report["seconds"]["load"] = t_load
    fit.report["shell_basis_early"] = basis is not None
    return rig, fit


def fit_rig(rig: Rig, progress=None, geodesics: Geodesics | None = None, stage=None,
            basis: ShellBasis | Callable[[], ShellBasis] | None = None,
            on_geometry: Callable[[Rig, Geometry], None] | None = None) -> FitResult:
    """Fit the whole rig: geometry, details of every example, greedy basis for PSD and WPSD.

    The configured method's model is returned; the error curves of both methods are reported
    (the paper's Fig. 4: error against basis size). ``geodesics``: the Dijkstra runs from
    ``rig.handles``, if already started (:func:`fit_config`); they are started here otherwise.
    ``stage(name)`` is called as each of the :data:`FIT_STAGES` after validation starts.
    ``basis``: the large-scale basis of the rig's deformer, if already solved, or a function that
    waits for it (:func:`fit_config`: solved while the examples loaded).
    ``on_geometry(rig, geometry)`` is called as soon as the large-scale geometry is final, before
    the details are fitted (a bake starts writing the model's geometry then).
    """
    stage = stage or (lambda name: None)
    cfg = rig.config.psd
    seconds: dict[str, float] = {}
    clock = [time.perf_counter()]

    def lap(name):
        now = time.perf_counter()
        seconds[name] = seconds.get(name, 0.0) + now - clock[0]
        clock[0] = now

    t0 = clock[0]
    rest, handles = rig.mesh.vertices, rig.handles
    if geodesics is None:
        geodesics = handle_geodesics(rig.mesh, handles)
    elif geodesics.n_vertices != rest.shape[0] or not np.array_equal(geodesics.sources, handles):
        raise ValueError("the geodesics were started for another mesh or other handles")
    # what needs no large-scale basis comes first (the features, the WPSD weights and the novelty
    # gate): where the basis is still being solved (fit_config) it is done while that runs
    try:
        graph = feature_graph(rig, geodesics.graph)
        edges, rest_lengths = graph
        beta = cfg.beta or default_beta(rest_lengths, cfg.beta_scale)
        poses = np.concatenate([rest[None], rig.example_positions]) if len(rig.example_positions) else rest[None]
        features = strain_features(poses[:, handles], edges, rest_lengths)
        stage(FIT_STAGES[2])
        distances = geodesics.finish()  # (H, V)
    finally:
        geodesics.close()
    lap("geodesics_wait")
    seconds["geodesics_child_sources"] = geodesics.child_sources
    stage(FIT_STAGES[3])
    edge_index, edge_weight = wpsd_edge_weights(distances, edges, rest_lengths, beta, cfg.min_edge_weight,
                                                cfg.max_edges_per_vertex)
    handle_distances = np.ascontiguousarray(distances[:, handles])
    del distances
    alpha = edge_weight_matrix(edge_index, edge_weight, len(edges))
    gate = None
    if cfg.novelty_tau > 0 and len(poses) > 1:
        with serial_blas():  # an SVD per site
            gate = novelty_gate(features[1:], edge_distances(handle_distances, edges), alpha,
                                cfg.novelty_tau, cfg.novelty_radius * float(np.median(rest_lengths)),
                                example_displacements=poses[1:, handles] - rest[handles],
                                marker_distance=handle_distances, edges=edges)
    lap("weights")
    stage(FIT_STAGES[4])
    geo = build_geometry(rig, graph=graph, basis=basis() if callable(basis) else basis)
    if on_geometry is not None:
        on_geometry(rig, geo)
    lap("geometry")
    stage(FIT_STAGES[5])
    details = geo.details(poses)
    large_only = rms_per_pose(np.zeros_like(details[1:]), details[1:])
    lap("details")
    methods = ["psd", "wpsd"] if len(poses) > 1 else []
    stage(FIT_STAGES[6])
    curves, models, sample = greedy_bases(cfg, methods, features, details, alpha, progress)
    lap("greedy")
    stage(FIT_STAGES[7])
    model, basis = final_detail_model(cfg, models, features, details, alpha, len(sample) < geo.rest.shape[0], gate)
    strain_model = None
    if cfg.method == "local_strain" and len(poses) > 1:  # details over the large scale's local strain
        strain_model = fit_local_strain(geo, poses[:, geo.handles], details, cfg.strain_width, cfg.strain_ridge)
        model = dataclasses.replace(model, method="local_strain", gate=None)
    lap("final_fit")
    seconds["total"] = time.perf_counter() - t0
    names = ["rest"] + list(rig.example_names)
    report = {
        "vertices": int(geo.rest.shape[0]),
        "triangles": int(geo.faces.shape[0]),
        "handles": int(len(geo.handles)),
        "anchors": int(len(rig.anchors)),
        "feature_edges": int(len(geo.edges)),
        "marker_spacing": geo.spacing,
        "examples": len(rig.example_names),
        "method": cfg.method,
        "fit": cfg.fit,
        "beta": beta,
        "deformer": rig.config.shell.method,
        "shell_solver": geo.solver,
        "shell_solver_passed_over": geo.solver_passed_over,
        "k_stretch": rig.config.shell.k_stretch,
        "k_bend": rig.config.shell.k_bend,
        "edges_per_vertex_mean": float((edge_weight > 0).sum(axis=1).mean()),
        # parts of the mesh apart from every marker (an eyeball, teeth): no feature edge reaches them
        "vertices_without_edges": int((edge_weight.sum(axis=1) == 0).sum()),
        "large_scale_rms": {"mean": float(large_only.mean()) if len(large_only) else 0.0,
                            "max": float(large_only.max()) if len(large_only) else 0.0},
        "basis": [names[i] for i in basis],
        "curves": {m: [dict(c, added=names[c["added"]]) for c in curve] for m, curve in curves.items()},
        "greedy_vertices": int(len(sample)) if methods else 0,
        "geodesics": geodesics.where,
        "seconds": seconds,
        "digest": rig.digest,
    }
    return FitResult(geo, names, features, details, cfg.method, model, basis, curves, edge_index, edge_weight,
                     beta, report, bases={m: b for m, (_, b) in models.items()}, alpha=alpha, config=cfg, gate=gate,
                     strain_model=strain_model)


def greedy_bases(cfg, methods: list[str], features: np.ndarray, details: np.ndarray, alpha: sp.csr_matrix,
                 progress=None) -> tuple[dict, dict, np.ndarray]:
    """The greedy basis of every method in ``methods``, chosen on an evenly spread vertex sample.

    The greedy choice scores every training pose at every basis size; the per-vertex systems are
    independent, so an evenly spread sample of vertices measures those errors as well as all of
    them (at 530k vertices, 32k give each pose's RMS to well under 1 %) for a fraction of the
    cost. The chosen basis is then fitted once on every vertex (:func:`final_detail_model`).

    Returns
    -------
    curves {method: error curve}, models {method: (model on the sample, basis)}, the sample (vertex indices).
    """
    n_vertices = details.shape[1]
    sample = spread_subset(n_vertices, cfg.greedy_vertices)
    sampled = len(sample) < n_vertices
    details_s = details[:, sample] if sampled else details
    alpha_s = alpha[sample] if sampled else alpha
    curves, models = {}, {}
    for method in methods:
        model, basis, curve = greedy_basis(method, features, details_s, cfg.fit, cfg.max_poses, cfg.tolerance,
                                           alpha=alpha_s, rcond=cfg.rcond, smoothing=cfg.smoothing,
                                           progress=(lambda n, c, m=method: progress(m, n, c)) if progress else None)
        curves[method] = curve
        models[method] = (model, basis)
    return curves, models, sample


def final_detail_model(cfg, models: dict, features: np.ndarray, details: np.ndarray, alpha: sp.csr_matrix,
                       sampled: bool, gate: NoveltyGate | None) -> tuple[DetailModel, list[int]]:
    """The configured method's model on every vertex, with its basis: the greedy one refitted on
    all vertices when it was chosen on a sample; the rest pose alone for method ``none`` (or
    without examples)."""
    if cfg.method in ("none", "local_strain") or not models:  # (local_strain: fitted by fit_rig)
        return dataclasses.replace(fit_details("psd", features, details, [0], "interpolate"), method="none"), [0]
    model, basis = models[cfg.method]
    if sampled:
        model = fit_details(cfg.method, features, details, basis, cfg.fit, alpha, cfg.rcond, cfg.smoothing)
    return dataclasses.replace(model, gate=gate), basis
