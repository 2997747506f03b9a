"""Accuracy table on the ICT kit: large-scale only, PSD and WPSD at P = 1, 3, 6, 12.

Fits configs/ict.toml (or the config given), replays the markers of a take with truth and
prints mean / 95th-percentile per-frame RMS over a vertex range. Usage:
    python bench/ict_table.py [CONFIG] [--truth TRUTH.npz] [--vertices 0:9409] [--json OUT]
"""

import argparse
import json
from pathlib import Path

import numpy as np

from facepipe.pipeline.evaluate import frame_errors, parse_vertex_range
from facepipe.pipeline.fit import fit_rig
from facepipe.io.model_file import model_from_fit
from facepipe.pipeline.replay import NumpyEvaluator
from facepipe.pipeline.rig import load_rig

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "ict.toml"))
    ap.add_argument("--truth", default=str(ROOT.parent / "shared" / "data" / "ict" / "train_truth.npz"))
    ap.add_argument("--vertices", default="0:9409")
    ap.add_argument("--poses", default="1,3,6,12")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    rig = load_rig(args.config)
    fit = fit_rig(rig)
    truth = np.load(args.truth)["positions"].astype(np.float64)
    verts = parse_vertex_range(args.vertices, truth.shape[1])
    rows = []

    def run(method, n):
        out = NumpyEvaluator(model_from_fit(fit, rig, method, n)).evaluate(truth[:, rig.handles])
        rms, _ = frame_errors(out, truth, verts)
        rows.append({"method": method, "poses": n, "rms_mean": float(rms.mean()),
                     "rms_p95": float(np.percentile(rms, 95))})

    run("none", 0)
    for method in ("psd", "wpsd"):
        for n in [int(p) for p in args.poses.split(",")]:
            run(method, n)
    base = rows[0]["rms_mean"]
    print(f"{'method':8s} {'P':>3s} {'mean RMS':>10s} {'p95 RMS':>10s} {'ratio':>6s}")
    for r in rows:
        name = "large" if r["method"] == "none" else r["method"]
        print(f"{name:8s} {r['poses']:3d} {r['rms_mean']:10.4f} {r['rms_p95']:10.4f} {r['rms_mean'] / base:6.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"config": args.config, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
