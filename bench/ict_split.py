"""Leave-expressions-out check on the ICT kit: do the details do harm on unseen expressions?

Fits the config on 20 of the 26 expression meshes and replays a take built from the other 6
with the kit's truth rule (neutral + Σ w_e (expression_e − neutral), smooth random weights).
For the config's own values (``fit --no-tune``) and for the values validated on the 20 (what
``fit`` does by default), per detail method and novelty gate (none; strain alone; strain and the
markers' motion, the default), prints the face-area RMS per frame against the large scale alone:
the mean, the worst frame's excess and the frames worse by more than 0.002 and 0.01 cm.
With ``--train`` also the kit's training take (train_truth.npz) replayed by the rig fitted and
validated on all 26 expressions, with each gate.
Usage: python bench/ict_split.py [CONFIG] [--frames 90] [--seed 0] [--train] [--json PATH]
"""

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from facepipe.core.strain import strain_features
from facepipe.core.tangent_frames import local_frames, to_world
from facepipe.io.model_file import model_from_fit
from facepipe.pipeline.evaluate import frame_errors
from facepipe.pipeline.fit import fit_rig
from facepipe.pipeline.replay import NumpyEvaluator
from facepipe.pipeline.rig import load_rig
from facepipe.pipeline.tune import choose_parameters

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


def gate_errors(fit, rig, truth) -> dict:
    """Per-frame face RMS (T,) of the large scale and of the configured method's details under
    each gate: {"large", "no gate", "strain gate", "strain + motion gate"}."""
    model = model_from_fit(fit, rig)
    ev = NumpyEvaluator(model)
    head = truth[:, rig.handles]
    _, large = ev.evaluate(head, with_large=True)
    out = {"large": frame_errors(large, truth, FACE)[0]}
    if ev.details.method == "none":
        return out
    geo = fit.geometry
    frames = local_frames(large, geo.faces, geo.neighbors, geo.incidence)
    f = strain_features(head, geo.edges, geo.rest_lengths)
    u = head - geo.rest[geo.handles]
    raw = dataclasses.replace(ev.details, gate=None).evaluate(f)

    def errors(confidence):
        return frame_errors(large + to_world(frames, raw * confidence[..., None]), truth, FACE)[0]

    out["no gate"] = errors(np.ones(raw.shape[:2]))
    gate = ev.details.gate
    if gate is not None:
        strain = dataclasses.replace(gate, motion_index=None, motion_weight=None, motion_examples=None,
                                     motion_scale=None)
        out["strain gate"] = errors(strain.confidence(f))
        out["strain + motion gate"] = errors(gate.confidence(f, u))
    return out


def summary(errors: dict) -> dict:
    large = errors["large"]
    rows = {}
    for name, e in errors.items():
        excess = e - large
        rows[name] = {"mean": float(e.mean()), "worst_excess": float(excess.max()),
                      "worst_frame": int(excess.argmax()), "large_at_worst": float(large[excess.argmax()]),
                      "frames_worse_0.002": int((excess > 0.002).sum()), "frames_worse_0.01": int((excess > 0.01).sum())}
    return rows


def fitted(config, keep=None, validate=True):
    rig = load_rig(config)
    if keep is not None:
        rig.example_positions = rig.example_positions[keep]
        rig.example_names = [rig.example_names[i] for i in keep]
    t0 = time.perf_counter()
    report = choose_parameters(rig, validate)
    fit = fit_rig(rig)
    return rig, fit, report, time.perf_counter() - t0


def show(title: str, rows: dict) -> None:
    print(title)
    for name, r in rows.items():
        print(f"  {name:22s} mean {r['mean']:.5f}  worst frame {r['worst_frame']:3d}: {r['worst_excess']:+.4f} cm "
              f"(large there {r['large_at_worst']:.4f})  frames worse by >0.002: {r['frames_worse_0.002']:3d}, "
              f">0.01: {r['frames_worse_0.01']}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "ict.toml"))
    ap.add_argument("--frames", type=int, default=90)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--train", action="store_true", help="also the training take, rig fitted on all 26")
    ap.add_argument("--truth", default=str(ROOT.parent / "shared" / "data" / "ict" / "train_truth.npz"))
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    held, keep, truth = split_take(load_rig(args.config), args.frames, args.seed)
    print("held out:", ", ".join(held))
    result = {"held_out": held}
    for label, validate in (("config's values (--no-tune)", False), ("validated (default)", True)):
        rig, fit, report, seconds = fitted(args.config, keep, validate)
        rows = summary(gate_errors(fit, rig, truth))
        result[label] = {"rows": rows, "chosen": report.get("chosen"), "seconds": seconds}
        show(f"split, {label}: {report.get('chosen', '')}", rows)
    if args.train:
        train = np.load(args.truth)["positions"].astype(np.float64)
        for label, validate in (("config's values (--no-tune)", False), ("validated (default)", True)):
            rig, fit, report, seconds = fitted(args.config, None, validate)
            rows = summary(gate_errors(fit, rig, train))
            result[f"train, {label}"] = {"rows": rows, "chosen": report.get("chosen"), "seconds": seconds}
            show(f"training take, {label} ({seconds:.1f} s): {report.get('chosen', '')}", rows)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
