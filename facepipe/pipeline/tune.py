"""Choosing the rig's parameters by validation on its own examples (what ``fit`` does by default).

Two stages, both deterministic and bounded by the candidate grid of the ``[tune]`` table:

1. **Shell stiffness.** The large-scale basis B depends only on the mesh, the markers and
   k_stretch/k_bend, never on the examples, so every example is unseen by it: the large-scale
   error of the examples, driven by their own marker positions, validates each k_stretch
   directly (one factorisation per candidate; the feature graph, distances and frames are
   shared).
2. **Details.** With the chosen shell, the WPSD falloff β, the RBF regularisation λ and the
   basis size P are chosen by cross-validation: whole expressions are left out (left and right
   halves together, see :mod:`facepipe.pipeline.cross_validation`), the greedy basis is grown on the rest, and
   the held-out examples are predicted at every basis size, so P costs nothing extra. The
   per-vertex RBF systems are independent, so the details are fitted and scored on an evenly
   spread sample of the vertices: the same numbers those vertices get from a full fit, at a
   cost that does not grow with the mesh's resolution.

The error of a held-out example is the RMS over the chosen vertices of (final − truth). Since
final = large + R·d with orthonormal frames R, it equals the RMS of the detail residual in the
local frames, so the large-scale surfaces and frames are computed once per k_stretch.

The defaults of the config are always among the candidates. A candidate is accepted only if no
held-out example gets worse than with the defaults by more than ``max_regression``; among the
accepted ones that validate as well as the best (within a standard error) and no worse than the
defaults, the largest basis wins (see :func:`tune_rig`). So tuning never picks a setting validated
worse than the defaults. When the validated error with details is above the large-scale-only
error by more than ``max_regression`` the details would do harm: ``fallback`` then turns them off
(method ``none``); details the novelty gate fades on held-out expressions are neutral there and kept.
"""

from __future__ import annotations

import copy
import threading
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from facepipe.errors import InputError
from facepipe.parallel import map_blocks, serial_blas
from facepipe.core.psd import edge_weight_matrix, greedy_basis, rms_per_pose, spread_subset, wpsd_edge_weights
from facepipe.core.novelty import edge_distances, novelty_gate
from facepipe.core.shell import ShellParts, marker_spacing, shell_displacements
from facepipe.core.tangent_frames import FramePatch, frame_neighbors, to_local
from facepipe.core.strain import edge_graph
from facepipe.pipeline.geodesics import geodesic_from
from facepipe.pipeline.cross_validation import expression_groups, holdout_folds
from facepipe.pipeline.evaluate import parse_vertex_range
from facepipe.pipeline.fit import Geometry, feature_graph
from facepipe.pipeline.strain_validation import (choose_strain, held_out_errors, sampled_strains, strain_grid,
                                                   strain_table)


def _with_unique(values, default) -> list[float]:
    """Candidates, sorted, with the default among them."""
    return sorted({float(v) for v in values} | {float(default)})


def tune_rig(rig, tune=None, progress=None, geodesics=None) -> dict:
    """Validate the candidates of ``tune`` on the rig's examples; return the report.

    Parameters
    ----------
    rig : a loaded :class:`facepipe.pipeline.rig.Rig` with at least 2 examples.
    tune : :class:`facepipe.io.config.TuneConfig` candidate ranges (default: the config's ``[tune]`` table).
    progress : optional callable(stage: str, done: int, total: int).
    geodesics : the rig's :class:`~facepipe.pipeline.geodesics.Geodesics` from its handles, if already started.

    Returns
    -------
    {"shell": [{"k_stretch", "large_rms"}], "details": [{"k_stretch", "beta_scale", "smoothing",
    "poses", "cv_rms"}], "large_cv_rms": {k: rms}, "default": {...}, "chosen": {...},
    "harm": bool, "fallback": bool, "folds": [[names]], "seconds": {...}}
    """
    tune = tune or rig.config.tune
    cfg = rig.config
    check_tunable(cfg, len(rig.example_names), list(rig.example_names))
    names = list(rig.example_names)
    vertices, sample = _validation_vertices(tune, rig.mesh.n_vertices)
    t0 = time.perf_counter()
    say = progress or (lambda *a: None)
    limit = 1.0 + tune.max_regression

    # ---- stage 1: shell stiffness, validated by the examples' large-scale error
    geo = _shape_geometry(rig, geodesics)
    poses = np.concatenate([geo.rest[None], rig.example_positions])
    features = geo.features(poses[:, geo.handles])
    default = _default_parameters(cfg, geo.rest_lengths, len(names))
    k_values = _with_unique(tune.k_stretch, default["k_stretch"])
    sampled_details, shell_errors = _shell_candidates(rig, geo, poses, vertices, sample, k_values, say)
    t_shell = time.perf_counter() - t0
    shell_rows = shell_table(shell_errors, default["k_stretch"], limit)
    best_k = min((r for r in shell_rows if r["accepted"]), key=lambda r: (r["large_rms"], r["k_stretch"]))["k_stretch"]

    # ---- stage 2: β, λ, τ and P by leaving whole expressions out (and, with a training
    # performance, blocks of its frames)
    n_frames = sequence_pose_count(cfg, names)
    mesh_names = names[:len(names) - n_frames]
    time_splits = time_block_splits(len(mesh_names), n_frames, tune.folds) \
        if n_frames >= MIN_FRAMES_PER_BLOCK * tune.folds else []
    expression_ok = len(mesh_names) >= 3 and len(set(expression_groups(mesh_names).tolist())) >= 2
    splits = time_splits + (expression_splits(mesh_names, tune.folds) if expression_ok else [])
    if cfg.psd.method == "local_strain":  # its own parameters, σ and λ of the kernel regression
        return _strain_report(rig, geo, poses, sampled_details[best_k], sample, best_k, splits,
                              dict(n_meshes=len(mesh_names), time_splits=time_splits, expression_ok=expression_ok),
                              default, limit, dict(shell=shell_rows, k_values=k_values, t0=t0, t_shell=t_shell))
    distances = geodesics.finish() if geodesics is not None else \
        geodesic_from(edge_graph(geo.rest, geo.faces), geo.handles)
    max_poses = min(max(tune.max_poses, default["poses"]), len(names))
    # β shapes WPSD's per-vertex distances only; PSD has one distance per pose
    beta_values = _with_unique(tune.beta_scale if cfg.psd.method == "wpsd" else [], default["beta_scale"])
    # λ regularises square (interpolation) systems only: a least-squares fit does not depend on it
    smooth_values = _with_unique(tune.smoothing if cfg.psd.fit == "interpolate" else [], default["smoothing"])
    tau_values = _with_unique(tune.novelty_tau, default["novelty_tau"])
    grid = detail_grid(best_k, default, beta_values, smooth_values)
    alphas = _sample_edge_weights(distances, geo, sample, beta_values, cfg.psd)
    details = {k: sampled_details[k] for k in {g[0] for g in grid}}
    # held-out error without details
    large = {k: rms_per_pose(np.zeros_like(details[k][1:]), details[k][1:]) for k in details}
    # thousands of small SVDs and solves per split, shared among facepipe's threads (serial_blas)
    with serial_blas():
        errors, dropped = _cross_validate_details(
            cfg.psd, features, details, alphas, splits, grid, tau_values, default, best_k, max_poses,
            site_distance=edge_distances(distances[:, geo.handles], geo.edges),
            radius=cfg.psd.novelty_radius * float(np.median(geo.rest_lengths)),
            moves=poses[:, geo.handles] - geo.rest[geo.handles], marker_distance=distances[:, geo.handles],
            edges=geo.edges, say=say,
            drop_on=np.concatenate([h for _, h in time_splits]) - 1 if time_splits else None)
    t_details = time.perf_counter() - t0 - t_shell
    default_key = (default["k_stretch"], default["beta_scale"], default["smoothing"], default["novelty_tau"])
    # a fold whose training set is smaller than P keeps its largest basis for the larger P
    errors = {key: _fill_forward(e) for key, e in errors.items()}
    mesh_cols = np.arange(len(mesh_names)) if expression_ok else np.zeros(0, dtype=np.int64)
    if time_splits:
        frame_cols = np.arange(len(mesh_names), len(names))
        rows, default_row = performance_table(errors, large, frame_cols, mesh_cols, default_key, default["poses"],
                                              max_poses, limit)
        chosen = choose_for_performance(rows)
        validation = "time blocks + expressions" if expression_ok else "time blocks"
    else:
        errors = {key: e[:, mesh_cols] for key, e in errors.items()}
        large = {k: e[mesh_cols] for k, e in large.items()}
        rows, default_row = detail_table(errors, large, default_key, default["poses"], max_poses, limit)
        chosen = choose_candidate(rows, errors, default_row)
        chosen = dict(chosen, large_cv_rms=float(large[chosen["k_stretch"]].mean()))
        validation = "expressions"  # whole expressions left out: new expressions
    # harm only where the details validate worse than the large scale alone by more than a held-out
    # example may regress: where the novelty gate fades them on the held-out (new) expressions they
    # are neutral there, and they still carry the mixtures of the known expressions, which leaving
    # whole expressions out does not measure (held-out time blocks of a performance do: with one,
    # this is judged on them)
    harm = chosen["cv_rms"] > limit * chosen["large_cv_rms"]
    return {
        "method": cfg.psd.method,
        "vertices": tune.vertices or "all",
        "sample_vertices": int(len(sample)),
        "examples": names,
        "validation": validation,
        "time_blocks": [[names[h[0] - 1], names[h[-1] - 1]] for _, h in time_splits],
        "expression_folds": len(splits) - len(time_splits),
        "folds": [[names[j - 1] for j in held] for _, held in splits],
        "stopped_early": [{"k_stretch": k, "beta_scale": b, "smoothing": s, "after_folds": n}
                          for (k, b, s), n in dropped.items()],
        "max_regression": tune.max_regression,
        "shell": shell_rows,
        "details": rows,
        "large_cv_rms": {str(k): float(v.mean()) for k, v in large.items()},
        "default": dict(default, cv_rms=default_row["cv_rms"]),
        "chosen": chosen,
        "harm": bool(harm),
        "fallback": bool(harm and tune.fallback),
        "candidates": {"k_stretch": k_values, "beta_scale": beta_values, "smoothing": smooth_values,
                       "novelty_tau": tau_values, "max_poses": max_poses},
        "seconds": {"shell": t_shell, "details": t_details, "total": time.perf_counter() - t0},
    }


def _strain_report(rig, geo, poses: np.ndarray, details: np.ndarray, sample: np.ndarray, best_k: float,
                   splits: list, layout: dict, default: dict, limit: float, stage1: dict) -> dict:
    """Stage 2 of :func:`tune_rig` for method ``local_strain``: σ and λ of the kernel regression,
    cross-validated on ``splits`` (:mod:`facepipe.pipeline.strain_validation`) with the chosen
    shell; ``details`` (E + 1, S, 3) of the poses on the ``sample`` vertices with that shell."""
    cfg, tune = rig.config, rig.config.tune
    t_details = time.perf_counter()
    large = geo.rest + shell_displacements(geo.rest, geo.faces, geo.handles, rig.anchors,
                                           poses[:, geo.handles] - geo.rest[geo.handles], k_stretch=best_k,
                                           k_bend=cfg.shell.k_bend, spacing=geo.spacing)
    strains = sampled_strains(geo.rest, geo.faces, geo.neighbors, large, sample)
    del large
    grid = strain_grid(tune.strain_width, tune.strain_ridge, cfg.psd.strain_width, cfg.psd.strain_ridge)
    errors = held_out_errors(strains, details, splits, grid)
    large_errors = rms_per_pose(np.zeros_like(details[1:]), details[1:])
    n_meshes, time_splits = layout["n_meshes"], layout["time_splits"]
    mesh_cols = np.arange(n_meshes) if layout["expression_ok"] else np.zeros(0, dtype=np.int64)
    frame_cols = np.arange(n_meshes, len(poses) - 1) if time_splits else np.zeros(0, dtype=np.int64)
    fixed = dict(k_stretch=best_k, beta_scale=default["beta_scale"], smoothing=default["smoothing"],
                 novelty_tau=0.0, poses=default["poses"])
    default_pair = (float(cfg.psd.strain_width), float(cfg.psd.strain_ridge))
    rows, default_row = strain_table(errors, large_errors, frame_cols, mesh_cols, default_pair, limit, fixed)
    chosen = choose_strain(rows)
    harm = chosen["cv_rms"] > limit * chosen["large_cv_rms"]
    names = list(rig.example_names)
    now = time.perf_counter()
    return {
        "method": "local_strain",
        "vertices": tune.vertices or "all",
        "sample_vertices": int(len(sample)),
        "examples": names,
        "validation": ("time blocks + expressions" if len(mesh_cols) else "time blocks") if time_splits
        else "expressions",
        "time_blocks": [[names[h[0] - 1], names[h[-1] - 1]] for _, h in time_splits],
        "expression_folds": len(splits) - len(time_splits),
        "folds": [[names[j - 1] for j in held] for _, held in splits],
        "stopped_early": [],
        "max_regression": tune.max_regression,
        "shell": stage1["shell"],
        "details": rows,
        "large_cv_rms": {str(best_k): float(large_errors.mean())},
        "default": dict(default, strain_width=default_pair[0], strain_ridge=default_pair[1],
                        cv_rms=default_row["cv_rms"]),
        "chosen": chosen,
        "harm": bool(harm),
        "fallback": bool(harm and tune.fallback),
        "candidates": {"k_stretch": stage1["k_values"], "strain_width": sorted({w for w, _ in grid}),
                       "strain_ridge": sorted({r for _, r in grid})},
        "seconds": {"shell": stage1["t_shell"], "details": now - t_details, "total": now - stage1["t0"]},
    }


def validation_obstacle(cfg, names: list[str]) -> str | None:
    """Why the rig's examples cannot validate its parameters, or None when they can: a thin shell
    (whose stiffness is chosen), a detail method, at least 3 examples in at least 2 expressions
    (left and right halves count as one), so that every fold leaves some out and trains on others."""
    if cfg.shell.method != "shell":
        return "validation chooses the thin shell's stiffness and [shell] method is 'rbf'"
    if cfg.psd.method == "none":
        return "[psd] method is 'none': there are no details to validate"
    n_frames = sequence_pose_count(cfg, names)
    if n_frames >= MIN_FRAMES_PER_BLOCK * cfg.tune.folds:
        return None  # held-out time blocks of the performance validate
    meshes = names[:len(names) - n_frames]
    if len(meshes) < 3:
        return (f"validation needs at least 3 example meshes to cross-validate (the rig has {len(meshes)}) or a "
                f"training performance of at least {MIN_FRAMES_PER_BLOCK * cfg.tune.folds} frames "
                f"({cfg.tune.folds} time blocks of {MIN_FRAMES_PER_BLOCK})")
    if len(set(expression_groups(meshes).tolist())) < 2:
        return "validation leaves whole expressions out and the examples are all one expression (left/right halves)"
    return None


# a held-out time block has at least this many frames (else the performance is not held out in blocks)
MIN_FRAMES_PER_BLOCK = 4


def sequence_pose_count(cfg, names: list[str]) -> int:
    """How many of the examples (the last ones) are frames of the config's ``[examples] sequence``."""
    if cfg.sequence is None:
        return 0
    prefix = f"{Path(cfg.sequence).stem}:"
    count = 0
    for name in reversed(names):
        if not name.startswith(prefix):
            break
        count += 1
    return count


def time_block_splits(n_meshes: int, n_frames: int, blocks: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(training, held-out) pose indices that hold out contiguous blocks of a performance's frames
    (new mixtures of the known expressions). Poses: 0 the rest pose, 1 … n_meshes the example
    meshes, then the frames in take order.

    A block is held out whole, and the frames within a quarter of a block's length on either side
    of it are left out of its training set too, so that no frame is validated by its neighbours
    (consecutive frames of a take are nearly the same pose). Every frame is held out once."""
    edges = np.linspace(0, n_frames, blocks + 1).round().astype(np.int64)
    margin = max(1, int(n_frames // blocks) // 4)
    frames = np.arange(n_frames)
    splits = []
    for a, b in zip(edges[:-1], edges[1:]):
        keep = frames[(frames < a - margin) | (frames >= b + margin)]
        train = np.concatenate([np.arange(n_meshes + 1), n_meshes + 1 + keep])
        splits.append((train, n_meshes + 1 + frames[a:b]))
    return splits


def check_tunable(cfg, n_examples: int, names: list[str] | None = None) -> None:
    """InputError unless the rig's examples can validate its parameters (:func:`validation_obstacle`)."""
    why = validation_obstacle(cfg, names if names is not None else [f"example{i}" for i in range(n_examples)])
    if why is not None:
        raise InputError(why, path=cfg.path, hint="change the config or the examples as it says, or fit with --no-tune")


def choose_parameters(rig, enabled: bool = True, progress=None, geodesics=None) -> dict:
    """The validated choice that ``fit`` makes by default: when ``enabled`` and the examples allow
    it, :func:`tune_rig`, and ``rig.config`` switched to the chosen values; otherwise the config's
    own values stay.

    Returns the tuning report with ``"validated": True``, or ``{"validated": False, "reason": why}``
    (``"disabled"`` when not ``enabled``).
    """
    if not enabled:
        return {"validated": False, "reason": "disabled"}
    why = validation_obstacle(rig.config, list(rig.example_names))
    if why is not None:
        return {"validated": False, "reason": why}
    report = tune_rig(rig, progress=progress, geodesics=geodesics)
    rig.config = tuned_config(rig.config, report)
    return dict(report, validated=True)


def _validation_vertices(tune, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """The vertices errors are measured on (``tune.vertices``, else all) and the evenly spread
    sample of them the details are cross-validated on."""
    vertices = np.arange(n_vertices)[parse_vertex_range(tune.vertices, n_vertices) if tune.vertices else slice(None)]
    return vertices, vertices[spread_subset(len(vertices), tune.sample_vertices)]


def _default_parameters(cfg, rest_lengths: np.ndarray, n_examples: int) -> dict:
    """The config's own values of the tuned parameters (always among the candidates)."""
    return {"k_stretch": cfg.shell.k_stretch, "beta_scale": _default_beta_scale(cfg.psd, rest_lengths),
            "smoothing": cfg.psd.smoothing, "novelty_tau": cfg.psd.novelty_tau,
            "poses": min(cfg.psd.max_poses, n_examples)}


def _shape_geometry(rig, geodesics=None) -> Geometry:
    """The rig's geometry without a large-scale basis (validation solves the shell per stiffness
    for the examples alone): rest mesh, feature graph, frame neighbours, marker spacing."""
    rest, faces, handles = rig.mesh.vertices, rig.mesh.faces, rig.handles
    edges, rest_lengths = feature_graph(rig, geodesics.graph if geodesics is not None else None)
    return Geometry(rest, faces, handles, None, edges, rest_lengths, frame_neighbors(faces, len(rest)),
                    marker_spacing(rest, handles))


def _shell_candidates(rig, geo, poses: np.ndarray, vertices: np.ndarray, sample: np.ndarray,
                      k_values: list[float], say) -> tuple[dict, dict]:
    """Per k_stretch, the poses' details on the ``sample`` vertices and the examples' large-scale
    RMS on ``vertices``: ({k: (E + 1, S, 3)}, {k: (E,) errors}).

    B is not needed for this: one factorisation per k and the poses' own right-hand sides
    (:func:`~facepipe.core.shell.shell_displacements`), whatever the number of handles."""
    cfg = rig.config
    details, shell_errors = {}, {}
    moves = poses[:, geo.handles] - geo.rest[geo.handles]
    patch = FramePatch.around(geo.faces, len(geo.rest), sample)
    parts = ShellParts.of(geo.rest, geo.faces)  # the Laplacian's products, shared by every k
    keep: dict = {}  # one factor, factored again for each k (its analysis kept: the same pattern)
    try:
        for i, k in enumerate(k_values):
            large = geo.rest + shell_displacements(geo.rest, geo.faces, geo.handles, rig.anchors, moves, k_stretch=k,
                                                   k_bend=cfg.shell.k_bend, spacing=geo.spacing, parts=parts,
                                                   keep=keep)
            shell_errors[k] = rms_per_pose(large[1:], poses[1:], vertices)
            details[k] = to_local(patch.frames(large), poses[:, sample] - large[:, sample])
            del large
            say("shell", i + 1, len(k_values))
    finally:
        if keep.get("factor") is not None:
            keep["factor"].close()
    return details, shell_errors


def shell_table(shell_errors: dict, default_k: float, limit: float) -> list[dict]:
    """A row per k_stretch: mean large-scale RMS, worst ratio to the default's per example, and
    whether that ratio is within ``limit`` (accepted)."""
    rows = [{"k_stretch": k, "large_rms": float(e.mean()),
             "worst_vs_default": float(np.max(e / shell_errors[default_k])),
             "per_example": e.tolist()} for k, e in shell_errors.items()]
    for r in rows:
        r["accepted"] = r["worst_vs_default"] <= limit
    return rows


def detail_grid(best_k: float, default: dict, beta_values: list[float], smooth_values: list[float]) -> list[tuple]:
    """The (k_stretch, β, λ) candidates of stage 2: every β and λ with the chosen shell, and the
    defaults with the default shell when the chosen one differs."""
    grid = [(best_k, b, s) for b in beta_values for s in smooth_values]
    if best_k != default["k_stretch"]:
        grid.append((default["k_stretch"], default["beta_scale"], default["smoothing"]))
    return grid


def _sample_edge_weights(distances: np.ndarray, geo, sample: np.ndarray, beta_values: list[float], psd) -> dict:
    """The WPSD edge weights α of the sampled vertices per β scale: {β: (S, F) sparse}."""
    alphas = {}
    for b in beta_values:
        index, weight = wpsd_edge_weights(distances[:, sample], geo.edges, geo.rest_lengths,
                                          b / np.median(geo.rest_lengths), psd.min_edge_weight,
                                          psd.max_edges_per_vertex)
        alphas[b] = edge_weight_matrix(index, weight, len(geo.edges))
    return alphas


def expression_splits(names: list[str], folds: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(training, held-out) pose indices (pose 0 is the rest pose, always trained on) that leave
    whole expressions out (:func:`~facepipe.pipeline.cross_validation.holdout_folds`): new
    expressions. Every example is held out once.

    Validation takes any list of such splits over the rest pose and the training poses, so other
    schemes (held-out time blocks of a captured performance: new mixtures of known expressions)
    produce splits of the same form."""
    groups = holdout_folds(names, max(1, int(round(len(names) / max(folds, 2)))))
    n_poses = len(names) + 1
    return [(np.concatenate([[0], np.setdiff1d(np.arange(1, n_poses), g + 1)]), g + 1) for g in groups]


def _cross_validate_details(psd, features: np.ndarray, details: dict, alphas: dict, splits: list, grid: list,
                            tau_values: list[float], default: dict, best_k: float, max_poses: int, *,
                            site_distance: np.ndarray, radius: float, moves: np.ndarray,
                            marker_distance: np.ndarray, edges: np.ndarray, say,
                            drop_on: np.ndarray | None = None) -> tuple[dict, dict]:
    """The held-out error of every example per (k, β, λ, τ) and basis size.

    For each (training, held-out) split the greedy basis grows on the training poses and
    predicts the held-out ones at every basis size. Returns ({(k, β, λ, τ): (max_poses + 1, E)
    RMS, NaN where a split's basis stops short}, {(k, β, λ): splits done before it was dropped}
    for the candidates stopped early (:func:`_clearly_worse`).

    The novelty gate depends on the poses' strain and handle motion alone (not on k, β or λ), and
    τ only rescales its output: its non-negative fits run once per split, and every β (how sites
    reach vertices) and τ is scored on them. ``moves`` (E + 1, H, 3): the poses' handle displacements, ``marker_distance``
    (H, H) and ``edges`` (F, 2) for the gate's motion part. ``drop_on``: the examples (indices
    into the E) whose errors decide the early drop (default: all).
    """
    n_poses = features.shape[0]
    errors: dict[tuple, np.ndarray] = {}
    default_shell = (default["k_stretch"], default["beta_scale"], default["smoothing"])
    live = list(grid)
    dropped: dict[tuple, int] = {}
    count, lock = [0, 0], threading.Lock()  # fits done; fits done before this split
    for i, (train, held) in enumerate(splits):
        P_max = min(max_poses, len(train) - 1)
        identity = sp.identity(features.shape[1], format="csr")
        gate = novelty_gate(features[train[1:]], site_distance, identity, 1.0, radius,
                            example_displacements=moves[train[1:]], marker_distance=marker_distance, edges=edges)
        rho = gate.novelty(features[held], moves[held])
        taus = {c: tau_values if c != default_shell or best_k == default["k_stretch"] else [default["novelty_tau"]]
                for c in live}
        for (k, b, s), ts in taus.items():
            for t in ts:
                errors.setdefault((k, b, s, t), np.full((max_poses + 1, n_poses - 1), np.nan))

        def validate(candidate, train=train, held=held, P_max=P_max, gate=gate, rho=rho):
            k, b, s = candidate
            confidence = {t: np.asarray(alphas[b] @ gate.site_confidence(rho, t).T).T[..., None]
                          for t in taus[candidate]}

            def observe(model, basis):
                raw = model.evaluate(features[held])
                for t, c in confidence.items():  # each candidate writes only its own rows
                    errors[(k, b, s, t)][len(basis) - 1, held - 1] = rms_per_pose(raw * c, details[k][held])

            greedy_basis(psd.method, features[train], details[k][train], psd.fit, P_max,
                         alpha=alphas[b], rcond=psd.rcond, smoothing=s, observe=observe)
            with lock:
                count[0] += 1
                # the total shrinks as candidates are dropped
                say("details", count[0], count[1] + len(live) * (len(splits) - i))

        # the candidates' greedy fits are independent (small LAPACK calls that release the GIL)
        map_blocks(validate, list(live))
        count[1] = count[0]
        seen = np.concatenate([h for _, h in splits[:i + 1]]) - 1
        if drop_on is not None:
            seen = np.intersect1d(seen, drop_on)
        for candidate in _clearly_worse(errors, live, seen, keep=default_shell) if i + 1 < len(splits) else []:
            live.remove(candidate)
            dropped[candidate] = i + 1
    for candidate in dropped:  # its errors are partial: it takes no part in the choice
        for key in [key for key in errors if key[:3] == candidate]:
            del errors[key]
    return errors, dropped


# A candidate is dropped from the remaining splits once its held-out error so far is above the
# best candidate's by this many standard errors of their paired per-example differences: the
# choice keeps only candidates within one standard error of the best, so such a candidate is
# practically never chosen, and every split after it is saved.
CLEARLY_WORSE_SE = 3.0


def _clearly_worse(errors: dict, live: list, seen: np.ndarray, keep: tuple) -> list:
    """The (k, β, λ) candidates whose best (τ, P) so far is clearly worse than the best candidate's
    on the held-out examples ``seen`` so far (never ``keep``, the defaults' reference)."""
    if len(seen) < 3:
        return []
    best_rows = {}
    for (k, b, s, t), e in errors.items():
        if (k, b, s) not in live:
            continue
        filled = _fill_forward(e[:, seen])[1:]
        row = filled[int(np.nanargmin(filled.mean(axis=1)))]
        if (k, b, s) not in best_rows or row.mean() < best_rows[(k, b, s)].mean():
            best_rows[(k, b, s)] = row
    leader = min(best_rows, key=lambda c: best_rows[c].mean())
    out = []
    for candidate, row in best_rows.items():
        diff = row - best_rows[leader]
        if candidate in (leader, keep):
            continue
        if diff.mean() > CLEARLY_WORSE_SE * diff.std(ddof=1) / np.sqrt(len(diff)):
            out.append(candidate)
    return out


def detail_table(errors: dict, large: dict, default_key: tuple, default_poses: int, max_poses: int,
                 limit: float) -> tuple[list[dict], dict]:
    """A row per (k, β, λ, τ) and basis size: mean held-out RMS, worst ratios per example to the
    defaults (their model or their large scale alone, whichever is better) and to the large scale,
    accepted when the first is within ``limit``. Returns the rows and the defaults' row (always
    accepted)."""
    reference = np.minimum(errors[default_key][default_poses], large[default_key[0]])
    rows = []
    for (k, b, s, t), e in errors.items():
        for P in range(1, max_poses + 1):
            rows.append({"k_stretch": k, "beta_scale": b, "smoothing": s, "novelty_tau": t, "poses": P,
                         "cv_rms": float(e[P].mean()),
                         "worst_vs_default": float(np.max(e[P] / reference)),
                         "worst_vs_large": float(np.max(e[P] / large[k])),
                         "accepted": bool(np.max(e[P] / reference) <= limit)})
    default_row = next(r for r in rows if _key(r) + (r["poses"],) == default_key + (default_poses,))
    default_row["accepted"] = True  # the defaults are always a candidate
    return rows, default_row


def choose_candidate(rows: list[dict], errors: dict, default_row: dict) -> dict:
    """The chosen row among the accepted ones.

    Held-out expressions are unseen, so the novelty gate keeps their details small and the basis
    size barely shows in their error; yet every pose added is one more expression (and its
    mixtures) reproduced exactly. So among the candidates that validate as well as the best —
    within one standard error of the paired per-example differences — and no worse than the
    defaults, the largest basis wins, then the stronger gate (smaller τ: a margin for expressions
    validation has not seen).
    """
    accepted = [r for r in rows if r["accepted"]]
    best = min(accepted, key=lambda r: (round(r["cv_rms"], 12), r["poses"]))
    best_errors = errors[_key(best)][best["poses"]]

    def tied(r):
        diff = errors[_key(r)][r["poses"]] - best_errors
        return diff.mean() <= diff.std(ddof=1) / np.sqrt(len(diff)) if len(diff) > 1 else r is best

    return min((r for r in accepted if tied(r) and r["cv_rms"] <= default_row["cv_rms"]),
               key=lambda r: (-r["poses"], r["novelty_tau"], round(r["cv_rms"], 12)))


def performance_table(errors: dict, large: dict, frame_cols: np.ndarray, mesh_cols: np.ndarray, default_key: tuple,
                      default_poses: int, max_poses: int, limit: float) -> tuple[list[dict], dict]:
    """A row per (k, β, λ, τ) and basis size when a performance's frames are held out in time blocks:
    ``cv_rms`` is their mean error (new mixtures), ``expression_cv_rms`` the held-out expressions'
    (new expressions) and ``worst_expression_vs_large`` the largest ratio of a held-out
    expression's error to its large scale alone. Accepted (no harm) when that ratio is within
    ``limit`` (every row, without expressions to hold out). Returns the rows and the defaults' row."""
    rows = []
    for (k, b, s, t), e in errors.items():
        frame_large = large[k][frame_cols]
        for P in range(1, max_poses + 1):
            row = {"k_stretch": k, "beta_scale": b, "smoothing": s, "novelty_tau": t, "poses": P,
                   "cv_rms": float(e[P, frame_cols].mean()), "large_cv_rms": float(frame_large.mean()),
                   "worst_vs_large": float(np.max(e[P, frame_cols] / frame_large))}
            if len(mesh_cols):
                ratio = e[P, mesh_cols] / large[k][mesh_cols]
                row.update(expression_cv_rms=float(e[P, mesh_cols].mean()),
                           expression_large_rms=float(large[k][mesh_cols].mean()),
                           worst_expression_vs_large=float(ratio.max()), worst_expression=int(mesh_cols[ratio.argmax()]))
            row["accepted"] = bool(row.get("worst_expression_vs_large", 0.0) <= limit)
            rows.append(row)
    default_row = next(r for r in rows if _key(r) + (r["poses"],) == default_key + (default_poses,))
    return rows, default_row


def choose_for_performance(rows: list[dict]) -> dict:
    """The row with the smallest error on the held-out time blocks (new mixtures of the known
    expressions: the common use) among those that do no harm on held-out expressions; ties go to
    the larger basis, then the stronger gate. Where no candidate does no harm, the one that does
    least (``no_harm`` False in the row returned): details that help on new mixtures are never
    switched off for failing to extrapolate."""
    accepted = [r for r in rows if r["accepted"]]
    if accepted:
        best = min(accepted, key=lambda r: (round(r["cv_rms"], 12), -r["poses"], r["novelty_tau"]))
        return dict(best, no_harm=True)
    return dict(min(rows, key=lambda r: (r["worst_expression_vs_large"], r["cv_rms"])), no_harm=False)


def _key(row: dict) -> tuple:
    return row["k_stretch"], row["beta_scale"], row["smoothing"], row["novelty_tau"]


def _default_beta_scale(psd, rest_lengths) -> float:
    """The config's β as a multiple of 1/median feature-edge length."""
    return float(psd.beta * np.median(rest_lengths)) if psd.beta else float(psd.beta_scale)


def _fill_forward(values: np.ndarray) -> np.ndarray:
    """Rows (basis sizes) left NaN take the row above."""
    out = values.copy()
    for i in range(1, len(out)):
        out[i] = np.where(np.isnan(out[i]), out[i - 1], out[i])
    return out


def tuned_config(config, report: dict):
    """A copy of the rig config with the chosen values (and method ``none`` on fallback)."""
    chosen = report["chosen"]
    out = copy.deepcopy(config)
    out.shell.k_stretch = float(chosen["k_stretch"])
    out.psd.beta = 0.0
    out.psd.beta_scale = float(chosen["beta_scale"])
    out.psd.smoothing = float(chosen["smoothing"])
    out.psd.max_poses = int(chosen["poses"])
    out.psd.novelty_tau = float(chosen["novelty_tau"])
    if "strain_width" in chosen:  # method local_strain
        out.psd.strain_width = float(chosen["strain_width"])
        out.psd.strain_ridge = float(chosen["strain_ridge"])
    if report["fallback"]:
        out.psd.method = "none"
    return out
