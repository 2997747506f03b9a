"""Baselines that users compare facepipe against, evaluated on one take.

Bickel et al. 2008 (§6.1, Fig. 4–5) compare pose-space details with blend shapes driven by
the same markers:

* global blend shapes — one convex combination of the example poses whose markers best
  match the frame's markers;
* locally controlled blend shapes — per vertex, the combination whose strain best matches
  the frame's strain on the feature edges near the vertex (the WPSD metric, eq. 3);

plus the large-scale deformers alone (thin shell, RBF volume morph). Everything works in
head space; outputs are mapped to the take's space with the head motion for comparison.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.optimize import nnls

from facepipe.pipeline.evaluate import frame_errors
from facepipe.io.model_file import model_from_fit
from facepipe.pipeline.local_strain_fit import fit_local_strain
from facepipe.core.rbf_morph import multiquadric_basis, phantom_points
from facepipe.pipeline.replay import NumpyEvaluator
from facepipe.io.atomic import atomic_path


def global_blend_weights(prior: np.ndarray, handles: np.ndarray, sum_weight: float = 1e3) -> np.ndarray:
    """Convex weights of the rig's poses matching each frame's handles.

    Parameters
    ----------
    prior : (E, H, 3) head-space handles of the poses (rest first); handles : (T, H, 3).
    sum_weight : weight of the Σ w = 1 row in the non-negative least squares.

    Returns
    -------
    (T, E) weights, w ≥ 0, Σ w ≈ 1.
    """
    E = prior.shape[0]
    A = np.vstack([prior.reshape(E, -1).T, sum_weight * np.ones((1, E))])
    out = np.empty((handles.shape[0], E))
    for i, frame in enumerate(handles.reshape(handles.shape[0], -1)):
        out[i] = nnls(A, np.concatenate([frame, [sum_weight]]))[0]
    return out


def local_blend_operator(example_features: np.ndarray, edge_index: np.ndarray, edge_weight: np.ndarray,
                         ridge: float = 1e-3) -> np.ndarray:
    """Per-vertex least-squares map from local strain to blend weights of the examples.

    w_v = argmin Σ_k α_vk (f_{e_k} − Σ_j w_j f_{j, e_k})² + μ |w|², μ = ridge × mean Gram diagonal.

    Parameters
    ----------
    example_features : (E, F) strain of the examples (not the rest pose).
    edge_index, edge_weight : (V, K) the WPSD edges and weights α of every vertex.

    Returns
    -------
    M : (V, E, K) with w_v = M_v @ f[edge_index[v]].
    """
    A = np.moveaxis(example_features[:, edge_index], 0, 1)  # (V, E, K)
    Aw = A * edge_weight[:, None, :]
    G = np.einsum("vek,vjk->vej", Aw, A)
    mu = ridge * np.maximum(np.einsum("vee->v", G) / G.shape[1], 1e-12)
    G = G + mu[:, None, None] * np.eye(G.shape[1])
    return np.linalg.solve(G, Aw)


def local_blend_positions(M: np.ndarray, edge_index: np.ndarray, features: np.ndarray, rest: np.ndarray,
                          example_offsets: np.ndarray) -> np.ndarray:
    """Locally controlled blend shapes: (T, F) strain → (T, V, 3) head-space positions.

    example_offsets : (E, V, 3) example positions minus rest.
    """
    w = np.einsum("vek,tvk->tve", M, features[:, edge_index])
    return rest + np.einsum("tve,evc->tvc", w, example_offsets)


def compare_methods(fit, rig, head: np.ndarray, R: np.ndarray, t: np.ndarray, truth: np.ndarray,
                    vertices: slice | np.ndarray = slice(None), chunk: int = 16, log=None) -> dict:
    """Error of every baseline and of PSD/WPSD at each basis size on one take.

    Parameters
    ----------
    fit, rig : a FitResult and its Rig (examples in memory).
    head : (T, H, 3) head-space handles; R, t : head motion (world = R head + t).
    truth : (T, V, 3) world positions.

    Returns
    -------
    {"rows": [{"method", "poses", "rms_mean", "rms_p95", "rms_max", "frames_per_second"}],
     "curves": {"psd": [...], "wpsd": [...]}} (curves: rows by basis size); the local-strain model's
    row ("local strain") has every training pose (``poses``: the examples).
    """

    geo = fit.geometry
    T = head.shape[0]

    def score(name, produce, poses=None):
        errs = []
        t0 = time.perf_counter()
        for s in range(0, T, chunk):
            pos = produce(s, min(T, s + chunk))
            errs.append(frame_errors(pos, truth[s:s + chunk], vertices)[0])
        seconds = time.perf_counter() - t0
        rms = np.concatenate(errs)
        row = {"method": name, "poses": poses, "rms_mean": float(rms.mean()), "rms_p95": float(np.percentile(rms, 95)),
               "rms_max": float(rms.max()), "frames_per_second": T / seconds, "per_frame_rms": rms.tolist()}
        if log:
            log(f"  {name:24s} {'' if poses is None else f'P={poses:<3d}'} RMS mean {row['rms_mean']:.5f}")
        return row

    def world(fn):
        return lambda s, e: np.einsum("tij,tvj->tvi", R[s:e], fn(s, e)) + t[s:e, None, :]

    rows = []
    shell_eval = NumpyEvaluator(model_from_fit(fit, rig, "none"))
    rows.append(score("shell (large-scale)", world(lambda s, e: shell_eval.evaluate(head[s:e]))))
    phantoms = phantom_points(geo.rest, geo.faces, rig.anchors, geo.handles)
    B_rbf = multiquadric_basis(geo.rest, geo.handles, phantoms, rig.config.shell.rbf_lambda)
    rest_h = geo.rest[geo.handles]
    rows.append(score("rbf morph (large-scale)",
                      world(lambda s, e: geo.rest + np.einsum("vh,thc->tvc", B_rbf, head[s:e] - rest_h))))
    prior = np.concatenate([rest_h[None], rig.example_positions[:, geo.handles]])
    poses = np.concatenate([geo.rest[None], rig.example_positions])
    wg = global_blend_weights(prior, head)
    rows.append(score("global blend shapes", world(lambda s, e: np.einsum("te,evc->tvc", wg[s:e], poses))))
    M = local_blend_operator(fit.features[1:], fit.edge_index, fit.edge_weight)
    offsets = rig.example_positions - geo.rest
    rows.append(score("local blend shapes", world(lambda s, e: local_blend_positions(
        M, fit.edge_index, geo.features(head[s:e]), geo.rest, offsets))))
    curves = {}
    for method in ("psd", "wpsd"):
        if method not in fit.bases:
            continue
        curves[method] = []
        for n in range(len(fit.bases[method])):
            ev = NumpyEvaluator(model_from_fit(fit, rig, method, n))
            row = score(method.upper(), world(lambda s, e, ev=ev: ev.evaluate(head[s:e])), n)
            curves[method].append(row)
        rows.append(curves[method][-1])
    if len(fit.example_names) > 1:  # details over the large scale's local strain, every training pose
        strain = fit.strain_model if fit.strain_model is not None else fit_local_strain(
            fit.geometry, np.concatenate([fit.geometry.rest[None, fit.geometry.handles],
                                          rig.example_positions[:, fit.geometry.handles]]).astype(np.float64), fit.details, fit.config.strain_width, fit.config.strain_ridge)
        ev = NumpyEvaluator(model_from_fit(fit, rig, "local_strain", strain_model=strain))
        rows.append(score("local strain", world(lambda s, e: ev.evaluate(head[s:e])), len(fit.example_names) - 1))
    return {"rows": rows, "curves": curves}


def plot_comparison(result: dict, path, title: str = "") -> None:
    """The paper's Fig. 4: error against basis size for PSD/WPSD, baselines as lines (PNG)."""
    import matplotlib  # lazily: only `eval --compare` plots (seconds of start-up)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    for method, rows in result["curves"].items():
        ax.plot([r["poses"] for r in rows], [r["rms_mean"] for r in rows], marker="o", label=method.upper())
    styles = iter(["--", ":", "-.", (0, (5, 1))])
    for row in result["rows"]:
        if row["poses"] is None:
            ax.axhline(row["rms_mean"], linestyle=next(styles, "--"), color="gray", label=row["method"])
    ax.set_xlabel("example poses in the basis (P)")
    ax.set_ylabel("mean per-frame RMS error")
    ax.set_title(title or "error against basis size")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
