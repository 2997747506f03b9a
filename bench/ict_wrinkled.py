"""Bickel et al.'s protocol on the wrinkled ICT kit: learn details from a performance, test on its rest.

Every rig is fitted on the kit's 26 wrinkled expressions and, where it learns from the
performance, on frames [0, 80) of the wrinkled training take (``configs/ict_wrinkled.toml``:
``[examples] sequence_frames``); the take's markers (the truth's handle vertices, in head space)
are replayed and frames [80, 120) are measured over the face area [0, 9409): the RMS against the
wrinkled truth and the *wrinkle recovery* of the kit's README (the least-squares coefficient of
the true wrinkle layer, wrinkled − plain truth, in replay − plain truth; 1 = all of it, 0 = none).

Rows (each a config override; validated as ``fit`` does unless the row says ``--no-tune``):

* large scale: ``[psd] method = "none"``;
* WPSD, examples: the 26 expressions alone, the config's values (interpolation, P = 12);
* WPSD, examples, validated: the same, validated (leaving whole expressions out);
* WPSD + performance: the 26 expressions and the 80 frames, least squares, validated on held-out
  time blocks of the performance (and expressions);
* any ``--option "LABEL:psd.method=NAME,psd.max_poses=40"`` added on the command line (another
  detail model, e.g. a local-strain one, a basis size).

Also the time of ``fit`` (validation included) and of the model's bake, per row, and with
``--split`` the leave-expressions-out no-harm check on the wrinkled expressions
(:mod:`bench.ict_split`: fitted on 20, a take of the other 6; per-frame worst excess over the
large scale and the frames worse by more than 0.002 / 0.01 cm).

Usage: python -m bench.ict_wrinkled [--config CONFIG] [--option LABEL:KEY=VALUE,...] [--split] [--json PATH]
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import numpy as np

from facepipe.io.model_file import model_from_fit
from facepipe.pipeline.fit import fit_rig
from facepipe.pipeline.replay import NumpyEvaluator
from facepipe.pipeline.rig import load_rig, load_sequence
from facepipe.pipeline.tune import choose_parameters

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
FACE = slice(0, 9409)
TEST = (80, 120)

ROWS = [
    ("large scale", {"psd.method": "none"}, False),
    ("WPSD, examples (config's values)", {"examples.sequence": None, "psd.fit": "interpolate", "psd.max_poses": 12},
     False),
    ("WPSD, examples, validated", {"examples.sequence": None, "psd.fit": "interpolate", "psd.max_poses": 12}, True),
    ("WPSD + performance (config's values)", {}, False),
    ("WPSD + performance, validated", {}, True),
]


def parse_option(text: str) -> tuple[str, dict, bool]:
    """``LABEL:psd.method=local,psd.max_poses=40[,tune=false]`` → (label, overrides, validate)."""
    label, _, body = text.partition(":")
    overrides, validate = {}, True
    for item in filter(None, body.split(",")):
        key, _, value = item.partition("=")
        value = value.strip()
        parsed = json.loads(value) if value[:1] in "-0123456789[tfn" else value
        if key.strip() == "tune":
            validate = bool(parsed)
        else:
            overrides[key.strip()] = parsed
    return label, overrides, validate


def configured_rig(config: str, overrides: dict):
    """The rig of ``config`` with ``overrides`` ({"psd.max_poses": 40, "examples.sequence": None, …})."""
    from facepipe.io.config import load_config

    cfg = load_config(config)
    for key, value in overrides.items():
        table, name = key.split(".")
        if table == "examples":
            setattr(cfg, name, value)
            if name == "sequence" and value is None:
                cfg.sequence_frames = None
        else:
            setattr(getattr(cfg, table), name, value)
    return load_rig(cfg)


def test_part(config: str):
    """Frames [80, 120) of the wrinkled take and of the plain kit's take, in head space: (T, V, 3) × 2."""
    rig = load_rig(config, load_examples=False)
    wrinkled, _ = load_sequence(DATA / "ict_wrinkled" / "train_truth.npz", rig.mesh, frames=list(TEST))
    plain, _ = load_sequence(DATA / "ict" / "train_truth.npz", rig.mesh, frames=list(TEST))
    return rig, wrinkled, plain


def recovery(replay: np.ndarray, truth: np.ndarray, plain: np.ndarray) -> np.ndarray:
    """Per frame, k = ⟨P − S, T − S⟩ / ⟨T − S, T − S⟩ over the face area (the kit's README)."""
    layer = (truth - plain)[:, FACE]
    got = (replay - plain)[:, FACE]
    return np.einsum("tvc,tvc->t", got, layer) / np.einsum("tvc,tvc->t", layer, layer)


def face_rms(replay: np.ndarray, truth: np.ndarray) -> np.ndarray:
    d = (replay - truth)[:, FACE]
    return np.sqrt(np.einsum("tvc,tvc->tv", d, d).mean(axis=1))


def run_row(config: str, label: str, overrides: dict, validate: bool, truth, plain, handles) -> dict:
    rig = configured_rig(config, overrides)
    t0 = time.perf_counter()
    report = choose_parameters(rig, validate)
    fit = fit_rig(rig)
    t_fit = time.perf_counter() - t0
    t0 = time.perf_counter()
    model = model_from_fit(fit, rig)
    t_bake = time.perf_counter() - t0
    replay = NumpyEvaluator(model).evaluate(truth[:, handles])
    rms, k = face_rms(replay, truth), recovery(replay, truth, plain)
    chosen = report.get("chosen") if report.get("validated") else None
    row = {"label": label, "overrides": overrides, "validated": bool(report.get("validated")),
           "validation": report.get("validation"), "chosen": chosen, "method": fit.model.method,
           "basis_poses": int(fit.model.basis_features.shape[0] - 1), "examples": len(rig.example_names),
           "face_rms": float(rms.mean()), "face_rms_max": float(rms.max()), "recovery": float(k.mean()),
           "recovery_min": float(k.min()), "fit_s": t_fit, "bake_s": t_bake,
           "per_frame": {"rms": rms.tolist(), "recovery": k.tolist()}}
    print(f"{label:38s} RMS {row['face_rms']:.4f} cm (max {row['face_rms_max']:.4f})  recovery {row['recovery']:.2f} "
          f"(min {row['recovery_min']:.2f})  P {row['basis_poses']}  fit {t_fit:.1f} s  bake {t_bake:.1f} s"
          + (f"  chosen: β×{chosen['beta_scale']:g} τ {chosen['novelty_tau']:g} k {chosen['k_stretch']:g}"
             if chosen else ""), flush=True)
    return row


def split_check(config: str, only: list[str]) -> dict:
    """bench.ict_split on the wrinkled kit: fitted on 20 expressions (and, for the last variant, the
    performance's training frames in which none of the other 6 is active), a take of the other 6."""
    from bench import ict_split

    mesh_rig = configured_rig(config, {"examples.sequence": None, "psd.fit": "interpolate", "psd.max_poses": 12})
    held, keep, take = ict_split.split_take(mesh_rig, 90, 0)
    perf_rig = configured_rig(config, {})
    n_mesh = len(mesh_rig.example_names)
    truth = np.load(DATA / "ict_wrinkled" / "train_truth.npz")
    columns = [list(truth["expressions"]).index(h) for h in held]
    frame_rows = [int(n.rsplit(":", 1)[1]) for n in perf_rig.example_names[n_mesh:]]
    free = [n_mesh + j for j, r in enumerate(frame_rows) if truth["weights"][r, columns].max() <= 0.01]
    variants = [("examples, config's values", mesh_rig, keep, False), ("examples, validated", mesh_rig, keep, True),
                (f"examples + {len(free)} performance frames without them, validated", perf_rig, keep + free, True)]
    out = {"held_out": held}
    for label, base, chosen_examples, validate in variants:
        if only and not any(label.startswith(o) for o in only):
            continue
        rig = copy.copy(base)
        rig.example_positions = base.example_positions[chosen_examples]
        rig.example_names = [base.example_names[i] for i in chosen_examples]
        rig.config = copy.deepcopy(base.config)
        t0 = time.perf_counter()
        report = choose_parameters(rig, validate)
        fit = fit_rig(rig)
        rows = ict_split.summary(ict_split.gate_errors(fit, rig, take))
        out[label] = {"rows": rows, "chosen": report.get("chosen"), "validation": report.get("validation"),
                      "fit_s": time.perf_counter() - t0}
        ict_split.show(f"leave-expressions-out (wrinkled), {label}: {report.get('chosen', '')}", rows)
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=str(ROOT / "configs" / "ict_wrinkled.toml"))
    ap.add_argument("--option", action="append", default=[], help="LABEL:KEY=VALUE,... an extra row")
    ap.add_argument("--only", action="append", default=[], help="run only the rows with these labels")
    ap.add_argument("--split", action="store_true", help="also the leave-expressions-out no-harm check")
    ap.add_argument("--split-only", action="append", default=[], help="only the split variants starting so")
    ap.add_argument("--json", default=str(ROOT / "bench" / "ict_wrinkled.json"))
    args = ap.parse_args()
    rig, truth, plain = test_part(args.config)
    rows = ROWS + [parse_option(o) for o in args.option]
    if args.only:
        rows = [r for r in rows if r[0] in args.only]
    result = {"config": args.config, "test_frames": list(TEST), "rows": []}
    for label, overrides, validate in rows:
        result["rows"].append(run_row(args.config, label, overrides, validate, truth, plain, rig.handles))
    if args.split:
        result["split"] = split_check(args.config, args.split_only)
    Path(args.json).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
