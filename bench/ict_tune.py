"""Defaults against `fit --tune` on the ICT kit: the train take and the leave-expressions-out split.

1. Fit on all 26 expressions with the config's defaults and with tuning; replay the markers of
   train_mocap.csv's truth; face-area RMS per frame, large scale and final.
2. Fit (and tune) on 20 expressions only; replay a take built from the other 6 with the kit's
   truth rule (bench/ict_split.py); the final error per frame against the default large-scale
   error and against the tuned large-scale error. Also the values tuned on all 26, fitted on 20.
Usage: python bench/ict_tune.py [CONFIG] [--json bench/ict_tune.json]
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from facepipe.pipeline.evaluate import frame_errors
from facepipe.pipeline.fit import fit_rig
from facepipe.io.model_file import model_from_fit
from facepipe.pipeline.replay import NumpyEvaluator
from facepipe.pipeline.rig import load_rig
from facepipe.pipeline.tune import tune_rig, tuned_config

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from ict_split import split_take  # noqa: E402

FACE = slice(0, 9409)


def errors(rig, truth, tune: bool, chosen: dict | None = None):
    """Per-frame face RMS of large scale and final for a fit with defaults, tuning, or given values."""
    t0 = time.perf_counter()
    report = None
    if tune:
        report = tune_rig(rig)
        rig.config = tuned_config(rig.config, report)
    elif chosen is not None:
        rig.config = tuned_config(rig.config, {"chosen": chosen, "fallback": False})
    fit = fit_rig(rig)
    seconds = time.perf_counter() - t0
    out = {}
    for name, method in (("large", "none"), ("final", None)):
        pos = NumpyEvaluator(model_from_fit(fit, rig, method)).evaluate(truth[:, rig.handles])
        out[name] = frame_errors(pos, truth, FACE)[0]
    return out, report, seconds


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "ict.toml"))
    ap.add_argument("--truth", default=str(ROOT.parent / "shared" / "data" / "ict" / "train_truth.npz"))
    ap.add_argument("--json", default=str(ROOT / "bench" / "ict_tune.json"))
    args = ap.parse_args()
    result = {}
    truth = np.load(args.truth)["positions"].astype(np.float64)
    default, _, t_default = errors(load_rig(args.config), truth, tune=False)
    tuned, report, t_tuned = errors(load_rig(args.config), truth, tune=True)
    result["train"] = {
        "default_large": float(default["large"].mean()), "default_final": float(default["final"].mean()),
        "tuned_large": float(tuned["large"].mean()), "tuned_final": float(tuned["final"].mean()),
        "improvement_vs_default_final": float(1 - tuned["final"].mean() / default["final"].mean()),
        "tune_seconds": report["seconds"]["total"], "fit_seconds": {"default": t_default, "tuned": t_tuned},
        "chosen": report["chosen"], "default_cv": report["default"],
    }
    rig = load_rig(args.config)
    held, keep, split = split_take(rig, 90, 0)

    def training_rig():
        r = load_rig(args.config)
        r.example_positions = r.example_positions[keep]
        r.example_names = [r.example_names[i] for i in keep]
        return r

    d_split, _, _ = errors(training_rig(), split, tune=False)
    t_split, split_report, _ = errors(training_rig(), split, tune=True)
    # the values tuned on all 26 expressions, fitted on the 20
    v_split, _, _ = errors(training_rig(), split, tune=False, chosen=report["chosen"])
    result["split"] = {
        "held_out": held,
        "default_large": float(d_split["large"].mean()), "default_final": float(d_split["final"].mean()),
        "tuned_large": float(t_split["large"].mean()), "tuned_final": float(t_split["final"].mean()),
        "worst_tuned_final_over_default_large": float(np.max(t_split["final"] / d_split["large"])),
        "worst_tuned_final_over_tuned_large": float(np.max(t_split["final"] / t_split["large"])),
        "worst_default_final_over_default_large": float(np.max(d_split["final"] / d_split["large"])),
        "chosen": split_report["chosen"], "fallback": split_report["fallback"],
        "values_tuned_on_26": {
            "final": float(v_split["final"].mean()), "large": float(v_split["large"].mean()),
            "worst_final_over_default_large": float(np.max(v_split["final"] / d_split["large"])),
            "worst_final_over_large": float(np.max(v_split["final"] / v_split["large"]))},
    }
    for part, r in result.items():
        print(part, json.dumps({k: v for k, v in r.items() if k not in ("chosen", "default_cv", "held_out")}))
        print("  chosen", r["chosen"])
    Path(args.json).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
