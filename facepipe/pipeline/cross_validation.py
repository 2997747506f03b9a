"""Validation on held-out examples: how the model does on expressions it was not fitted to.

Examples are left out by *expression*: the left and right halves of one expression
(``smile_L``/``smile_R``, ``browDownLeft``/``browDownRight``) go out together, since one
predicts the other too well to count as unseen.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np

from facepipe.errors import InputError
from facepipe.pipeline.fit import fit_rig
from facepipe.io.model_file import model_from_fit
from facepipe.pipeline.replay import NumpyEvaluator

_SIDE = re.compile(r"(_[LR]|_left|_right|Left|Right)$")


def expression_groups(names: list[str]) -> np.ndarray:
    """Group id per example: names equal once a left/right suffix is removed share a group."""
    keys = [_SIDE.sub("", n) for n in names]
    order = {k: i for i, k in enumerate(dict.fromkeys(keys))}
    return np.array([order[k] for k in keys], dtype=np.int64)


def holdout_folds(names: list[str], k: int) -> list[np.ndarray]:
    """Folds of about ``k`` examples each, whole expression groups at a time, covering every example.

    Groups are dealt round-robin in name order so that each fold mixes regions of the face.
    """
    groups = expression_groups(names)
    n_groups = groups.max() + 1 if len(groups) else 0
    if k < 1 or k >= len(names):
        raise InputError(f"--holdout {k}: needs 1 ≤ K < number of examples ({len(names)})")
    n_folds = max(2, int(round(len(names) / k)))
    n_folds = min(n_folds, n_groups)
    folds = [[] for _ in range(n_folds)]
    for g in range(n_groups):
        folds[g % n_folds] += np.flatnonzero(groups == g).tolist()
    return [np.array(sorted(f)) for f in folds if f]


def holdout_errors(rig, k: int, vertices: slice = slice(None), progress=None) -> dict:
    """Fit without each fold and measure the held-out examples' error, large-scale and final.

    Returns
    -------
    {"folds": [[names]], "examples": {name: {"large_rms", "final_rms", "harm"}}, "summary": {...}}
    where harm = final / large − 1 (positive: the details made that example worse).
    """

    names = list(rig.example_names)
    folds = holdout_folds(names, k)
    out = {}
    for i, fold in enumerate(folds):
        train = np.setdiff1d(np.arange(len(names)), fold)
        sub = dataclasses.replace(rig, example_positions=rig.example_positions[train],
                                  example_names=[names[j] for j in train])
        fit = fit_rig(sub)
        ev = NumpyEvaluator(model_from_fit(fit, sub))
        held = rig.example_positions[fold]
        final, large = ev.evaluate(held[:, rig.handles], with_large=True)
        for j, f_pos, l_pos, truth in zip(fold, final, large, held):
            lr = float(np.sqrt(((l_pos - truth)[vertices] ** 2).sum(-1).mean()))
            fr = float(np.sqrt(((f_pos - truth)[vertices] ** 2).sum(-1).mean()))
            out[names[j]] = {"large_rms": lr, "final_rms": fr, "harm": fr / max(lr, 1e-12) - 1.0}
        if progress is not None:
            progress(i + 1, len(folds))
    harm = np.array([v["harm"] for v in out.values()])
    summary = {
        "folds": len(folds),
        "held_out_per_fold": k,
        "large_rms_mean": float(np.mean([v["large_rms"] for v in out.values()])),
        "final_rms_mean": float(np.mean([v["final_rms"] for v in out.values()])),
        "worst_harm": float(harm.max()),
        "examples_made_worse_over_2pct": int((harm > 0.02).sum()),
    }
    return {"folds": [[names[j] for j in f] for f in folds], "examples": out, "summary": summary}
