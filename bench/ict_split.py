"""Leave-expressions-out check on the ICT kit: do the details do harm on unseen expressions?

Fits the config on 20 of the 26 expression meshes and replays a take built from the other 6
with the kit's truth rule (neutral + Σ w_e (expression_e − neutral), smooth random weights).
Prints per method the mean face-area RMS and the worst per-frame ratio to large-scale only.
Usage: python bench/ict_split.py [CONFIG] [--frames 90] [--seed 0]
"""

import argparse
from pathlib import Path

import numpy as np

from facepipe.pipeline.evaluate import frame_errors
from facepipe.pipeline.fit import fit_rig
from facepipe.io.model_file import model_from_fit
from facepipe.pipeline.replay import NumpyEvaluator
from facepipe.pipeline.rig import load_rig

ROOT = Path(__file__).resolve().parents[1]
FACE = slice(0, 9409)


def split_take(rig, n_frames: int, seed: int):
    """Hold out every 4th expression from the second on (6 spread over the face); build their take."""
    names = list(rig.example_names)
    held = [i for i in range(len(names)) if i % 4 == 1][:6]
    keep = [i for i in range(len(names)) if i not in held]
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, n_frames)
    W = np.stack([rng.uniform(0.5, 1.0) * np.exp(-0.5 * ((t - rng.uniform(0, 1)) / rng.uniform(0.08, 0.25)) ** 2)
                  for _ in held], axis=1)
    rest = rig.mesh.vertices
    truth = rest + np.einsum("tk,kvc->tvc", W, rig.example_positions[held] - rest)
    return [names[i] for i in held], keep, truth


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "ict.toml"))
    ap.add_argument("--frames", type=int, default=90)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rig = load_rig(args.config)
    held, keep, truth = split_take(rig, args.frames, args.seed)
    print("held out:", ", ".join(held))
    rig.example_positions = rig.example_positions[keep]
    rig.example_names = [rig.example_names[i] for i in keep]
    fit = fit_rig(rig)
    errors = {}
    for method in ("none", "psd", "wpsd"):
        out = NumpyEvaluator(model_from_fit(fit, rig, method)).evaluate(truth[:, rig.handles])
        errors[method] = frame_errors(out, truth, FACE)[0]
    large = errors["none"]
    for method, e in errors.items():
        name = "large" if method == "none" else method
        print(f"{name:6s} mean RMS {e.mean():.5f}  worst frame / large-scale {np.max(e / large):.4f}")


if __name__ == "__main__":
    main()
