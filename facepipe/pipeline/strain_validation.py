"""Validating the local-strain detail model's kernel width σ and ridge λ (``[psd] method = "local_strain"``).

The model (:mod:`facepipe.core.strain_details`) is a kernel ridge regression per vertex over the
large-scale surface's local strain there, so its parameters are validated the way ``fit``
validates the others: on the same (training, held-out) splits — held-out time blocks of a
training performance (new mixtures of known expressions) and whole expressions left out (new
expressions) — on an evenly spread sample of vertices, with the shell stiffness chosen before.
Per split and width, one symmetric eigendecomposition of each vertex's kernel matrix,
K = Q Λ Qᵀ, gives the weights of every ridge at once, (K + λI)⁻¹ D = Q (Λ + λI)⁻¹ Qᵀ D.

The choice follows the rules of :mod:`facepipe.pipeline.tune`: with a performance, the smallest
error on its held-out time blocks among the candidates that make no held-out expression worse
than its large scale alone by more than ``max_regression`` (the least harmful where none does
no harm); without one, the smallest held-out error among the candidates that make no held-out
example worse than the config's values (or its large scale alone) by more than that.
"""

from __future__ import annotations

import numpy as np

from facepipe.core.local_strain import StrainOperator, vertex_strain
from facepipe.core.strain_details import squared_distances
from facepipe.parallel import map_blocks


def strain_grid(widths, ridges, default_width: float, default_ridge: float) -> list[tuple[float, float]]:
    """The (σ, λ) candidates: every width with every ridge, the config's own pair among them."""
    w = sorted({float(v) for v in widths} | {float(default_width)})
    r = sorted({float(v) for v in ridges} | {float(default_ridge)})
    return [(a, b) for a in w for b in r]


def sampled_strains(rest: np.ndarray, faces: np.ndarray, neighbors: np.ndarray, large: np.ndarray,
                    sample: np.ndarray) -> np.ndarray:
    """Local strain (E, S, 3) at the ``sample`` vertices of large-scale surfaces (E, V, 3)."""
    op = StrainOperator.of(rest, faces, neighbors)
    return np.stack([vertex_strain(p, op)[sample] for p in large])


def held_out_errors(strains: np.ndarray, details: np.ndarray, splits: list, grid: list[tuple[float, float]],
                    chunk: int = 512) -> dict:
    """RMS over the sampled vertices of every held-out pose's detail residual, per (σ, λ).

    strains, details : (E + 1, S, 3) of the rest pose (0) and the training poses at the sample.
    splits : [(training pose indices, held-out pose indices)], pose 0 always trained on.
    Returns {(σ, λ): (E,) errors}; poses no split holds out stay NaN.
    """
    n_poses, n_vertices = strains.shape[:2]
    sq_error = {c: np.full(n_poses - 1, np.nan) for c in grid}
    widths = sorted({w for w, _ in grid})
    for train, held in splits:
        s_tr = np.ascontiguousarray(np.moveaxis(strains[train], 0, 1))  # (S, N, 3)
        s_he = np.ascontiguousarray(np.moveaxis(strains[held], 0, 1))  # (S, Q, 3)
        d_tr = np.moveaxis(details[train], 0, 1)
        d_he = np.moveaxis(details[held], 0, 1)  # (S, Q, 3)
        d2_tt, d2_ht = squared_distances(s_tr, s_tr), squared_distances(s_he, s_tr)
        for w in widths:
            ridges = [r for ww, r in grid if ww == w]

            def block(start, w=w, ridges=ridges):
                stop = min(n_vertices, start + chunk)
                lam, Q = np.linalg.eigh(np.exp(-0.5 / w ** 2 * d2_tt[start:stop]))
                k_he = np.exp(-0.5 / w ** 2 * d2_ht[start:stop]) @ Q  # (n, Q, N)
                proj = np.swapaxes(Q, 1, 2) @ d_tr[start:stop]  # (n, N, 3)
                out = []
                for r in ridges:
                    res = k_he @ (proj / np.maximum(lam + r, 1e-300)[..., None]) - d_he[start:stop]
                    out.append(np.einsum("vqc,vqc->q", res, res))
                return out

            # summed in block order: the same numbers whatever the thread count
            sums = np.sum(map_blocks(block, range(0, n_vertices, chunk)), axis=0)  # (ridges, Q)
            for r, total in zip(ridges, sums):
                sq_error[(w, r)][held - 1] = total / n_vertices
    return {c: np.sqrt(e) for c, e in sq_error.items()}


def strain_table(errors: dict, large: np.ndarray, frame_cols: np.ndarray, mesh_cols: np.ndarray,
                 default: tuple[float, float], limit: float, fixed: dict) -> tuple[list[dict], dict]:
    """A row per (σ, λ) with the parameters ``fixed`` by stage 1 and the config (k_stretch, β, λ, τ,
    P): with time blocks (``frame_cols``), ``cv_rms`` is their mean error and a row is accepted when
    no held-out expression is worse than its large scale alone by more than ``limit``; without, it
    is the held-out expressions' mean and a row is accepted when none is worse than with the
    config's values (or its large scale alone) by more. Returns the rows and the config's row."""
    reference = np.minimum(errors[default], large)
    rows = []
    for (w, r), e in errors.items():
        row = dict(fixed, strain_width=w, strain_ridge=r)
        if len(frame_cols):
            row.update(cv_rms=float(e[frame_cols].mean()), large_cv_rms=float(large[frame_cols].mean()),
                       worst_vs_large=float(np.max(e[frame_cols] / large[frame_cols])))
            if len(mesh_cols):
                ratio = e[mesh_cols] / large[mesh_cols]
                row.update(expression_cv_rms=float(e[mesh_cols].mean()),
                           expression_large_rms=float(large[mesh_cols].mean()),
                           worst_expression_vs_large=float(ratio.max()), worst_expression=int(mesh_cols[ratio.argmax()]))
            row["accepted"] = bool(row.get("worst_expression_vs_large", 0.0) <= limit)
        else:
            row.update(cv_rms=float(e[mesh_cols].mean()), large_cv_rms=float(large[mesh_cols].mean()),
                       worst_vs_default=float(np.max(e[mesh_cols] / reference[mesh_cols])),
                       worst_vs_large=float(np.max(e[mesh_cols] / large[mesh_cols])))
            row["accepted"] = bool(row["worst_vs_default"] <= limit or (w, r) == default)
        rows.append(row)
    default_row = next(x for x in rows if (x["strain_width"], x["strain_ridge"]) == default)
    return rows, default_row


def choose_strain(rows: list[dict]) -> dict:
    """The accepted row with the smallest ``cv_rms`` (ties: the wider kernel, then the larger
    ridge: the smoother function); the least harmful row (``no_harm`` False) where none is accepted."""
    accepted = [r for r in rows if r["accepted"]]
    if accepted:
        return dict(min(accepted, key=lambda r: (round(r["cv_rms"], 12), -r["strain_width"], -r["strain_ridge"])),
                    no_harm=True)
    return dict(min(rows, key=lambda r: (r.get("worst_expression_vs_large", r["worst_vs_large"]), r["cv_rms"])),
                no_harm=False)
