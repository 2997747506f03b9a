"""Expressions that resemble a scaled example at the markers, whose large scale alone is right.

The failure the novelty gate's motion part is for: the markers of an unseen expression show a
scaled example's strain, but the face is not that example's (an eyelid lowered by the gaze looks
like a partial blink). Built on the ICT kit, for every example e and a few weights w: the
handles move by w·ΔH_e plus an out-of-surface motion of the same size along the rest surface's
normal (which changes the feature edges' lengths only to second order), and the truth is the
large-scale surface of those handles — so the large scale alone is right and any detail is harm.
Prints, per novelty gate, the mean excess over the large scale and the worst frames.
With a config that learns from a performance (``configs/ict_wrinkled.toml``) the take is built from
the example meshes alone and the rig is the one fitted on the meshes and the performance.
``--tau`` also scores the strain + motion gate at other thresholds (on the same non-negative fits:
τ only rescales their output), to tell how much of the harm the chosen τ lets through.
Usage: python -m bench.ict_resembling [CONFIG] [--no-tune] [--tau T ...] [--json PATH]
"""

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from facepipe.core.strain import strain_features
from facepipe.core.tangent_frames import local_frames, to_world, vertex_normals
from facepipe.io.model_file import model_from_fit
from facepipe.pipeline.evaluate import frame_errors
from facepipe.pipeline.fit import fit_rig
from facepipe.pipeline.replay import NumpyEvaluator
from facepipe.pipeline.rig import load_rig
from facepipe.pipeline.tune import choose_parameters, sequence_pose_count

ROOT = Path(__file__).resolve().parents[1]
FACE = slice(0, 9409)
WEIGHTS = (0.2, 0.4, 0.6)


def example_meshes(rig) -> int:
    """How many of the rig's examples are expression meshes (the frames of a training performance
    come after them and are not expressions of their own)."""
    return len(rig.example_names) - sequence_pose_count(rig.config, list(rig.example_names))


def resembling_take(rig, geo):
    """Handles (T, H, 3) and truth (T, V, 3): each example mesh scaled, its handles also moved along
    the rest normal by as much as they move, the truth the large scale of those handles."""
    rest = geo.rest
    normals = vertex_normals(rest, geo.faces)[geo.handles]
    moves = rig.example_positions[:example_meshes(rig), geo.handles] - rest[geo.handles]  # (E, H, 3)
    frames = []
    for move in moves:
        for w in WEIGHTS:
            size = np.linalg.norm(w * move, axis=1, keepdims=True)
            frames.append(w * move - size * normals)  # sinks where the example moves
    u = np.stack(frames)
    truth = rest + np.einsum("vh,thc->tvc", geo.B, u)  # the large scale of these handles
    return rest[geo.handles] + u, truth


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("config", nargs="?", default=str(ROOT / "configs" / "ict.toml"))
    ap.add_argument("--no-tune", action="store_true")
    ap.add_argument("--json", default=None)
    ap.add_argument("--tau", type=float, nargs="*", default=[], help="also score the gate at these thresholds")
    args = ap.parse_args()
    rig = load_rig(args.config)
    report = choose_parameters(rig, not args.no_tune)
    fit = fit_rig(rig)
    geo = fit.geometry
    head, truth = resembling_take(rig, geo)
    ev = NumpyEvaluator(model_from_fit(fit, rig))
    _, large = ev.evaluate(head, with_large=True)
    frames = local_frames(large, geo.faces, geo.neighbors, geo.incidence)
    f = strain_features(head, geo.edges, geo.rest_lengths)
    u = head - geo.rest[geo.handles]
    raw = dataclasses.replace(ev.details, gate=None).evaluate(f)
    gate = ev.details.gate
    strain = dataclasses.replace(gate, motion_index=None, motion_weight=None, motion_examples=None, motion_scale=None)
    e_large = frame_errors(large, truth, FACE)[0]
    result = {"chosen": report.get("chosen"), "frames": len(head), "large_mean": float(e_large.mean())}
    print(f"{len(head)} frames ({example_meshes(rig)} example meshes × weights {WEIGHTS}); large scale mean "
          f"{e_large.mean():.5f} cm; values {report.get('chosen', 'of the config')}")
    rho = gate.novelty(f, u)
    at_tau = [(f"strain + motion, τ {t:g}", np.asarray(gate.alpha @ gate.site_confidence(rho, t).T).T)
              for t in args.tau]
    for name, confidence in [("no gate", np.ones(raw.shape[:2])), ("strain gate", strain.confidence(f)),
                             ("strain + motion gate", np.asarray(gate.alpha @ gate.site_confidence(rho).T).T)] + at_tau:
        e = frame_errors(large + to_world(frames, raw * confidence[..., None]), truth, FACE)[0]
        excess = e - e_large
        worst = np.argsort(-excess)[:3]
        result[name] = {"mean": float(e.mean()), "worst_excess": float(excess.max()),
                        "frames_worse_0.002": int((excess > 0.002).sum()),
                        "frames_worse_0.01": int((excess > 0.01).sum())}
        print(f"  {name:26s} mean {e.mean():.5f}  worst +{excess.max():.4f} cm  frames worse by >0.002: "
              f"{(excess > 0.002).sum():3d}, >0.01: {(excess > 0.01).sum():3d}  worst frames: "
              + ", ".join(f"{rig.example_names[i // len(WEIGHTS)]}×{WEIGHTS[i % len(WEIGHTS)]} +{excess[i]:.4f}"
                          for i in worst))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
