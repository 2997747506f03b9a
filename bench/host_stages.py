"""The host's share of a marker replay, per frame: cleaning (pose and expression fits, smoothing,
gap filling) and the novelty gate's non-negative fits, which run on the CPU beside the kernels.

For each take: cleaning's milliseconds a frame (`prepare_take`, the whole take), and the gate's
(strain and motion parts, chunks of 32 frames as replay hands them over) three ways — every fit
run to the end (what validation needs: ρ itself), as a replay runs them (fits stop once the
confidence is settled within CONFIDENCE_TOLERANCE of 1), and as replay ran them before the exact
solver took over after a few batched steps (up to 2000 batched steps, `gate_ms_per_frame_batched`)
— with the largest difference of each one's confidences from the exact NNLS's. On the ICT kit's
takes where ../shared is beside the checkout (the model baked from configs/ict.toml unless
--ict-model exists; the wrinkled kit's training take with configs/ict_wrinkled.toml, 26
expressions + 80 frames of a performance as examples, --no-tune), and on a generated sample rig.

Usage:  python -m bench.host_stages [--json bench/host_stages.json] [--ict-model /tmp/ict_model.npz]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
KIT = ROOT.parent / "shared" / "data" / "ict"
CHUNK = 32


BATCHED_ONLY = 2000  # the batched steps' cap before the exact solver took fits over after a few


def _model(config: Path, path: Path, *options: str):
    from facepipe.io.model_file import load_model

    if not path.is_file():
        subprocess.run([sys.executable, "-m", "facepipe", "-q", "bake", *options, str(config), "-o", str(path)],
                       check=True, cwd=ROOT)
    return load_model(path)


def measure(model, take_path: Path, repeats: int = 3) -> dict:
    """Cleaning and gate milliseconds a frame of one take (best of ``repeats``)."""
    from facepipe.core.strain import strain_features
    from facepipe.mocap import read_take
    from facepipe.mocap.prepare import prepare_take

    take = read_take(take_path, model.marker_names, units=model.meta["units"])
    T = len(take.frames)
    clean = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        head, _, _, _ = prepare_take(take, model)
        clean = min(clean, time.perf_counter() - t0)
    out = {"take": str(take_path.name), "frames": T, "cleaning_ms_per_frame": 1000 * clean / T}
    gate = model.detail_model().gate
    if gate is None:
        return out
    features = strain_features(head, model.edges, model.rest_lengths)
    moves = head - model.rest[model.handle_vertices]
    chunks = [slice(a, min(T, a + CHUNK)) for a in range(0, T, CHUNK)]

    def run(how: str):
        best, conf = np.inf, None
        for _ in range(repeats):
            t0 = time.perf_counter()
            if how == "replay":
                conf = [gate.site_confidences(features[c], moves[c]) for c in chunks]
            elif how == "batched":
                conf = [gate.site_confidence(gate.novelty(features[c], moves[c], max_iterations=BATCHED_ONLY,
                                                          settled=gate.settled_fraction())) for c in chunks]
            else:
                conf = [gate.site_confidence(gate.novelty(features[c], moves[c])) for c in chunks]
            best = min(best, time.perf_counter() - t0)
        return 1000 * best / T, np.concatenate(conf)

    exact = np.concatenate([gate.site_confidence(_exact_novelty(gate, features[c], moves[c])) for c in chunks])
    out.update(sites=int(gate.index.shape[0]), examples=int(gate.examples.shape[1]))
    for how, label in (("full", "fits_to_the_end"), ("replay", "settled"), ("batched", "batched")):
        ms, conf = run(how)
        out[f"gate_ms_per_frame_{label}"] = ms
        out[f"confidence_difference_{label}"] = float(np.abs(conf - exact).max())
    out["gate_speedup_over_batched"] = out["gate_ms_per_frame_batched"] / out["gate_ms_per_frame_settled"]
    return out


def _exact_novelty(gate, features, moves):
    """ρ of every fit by SciPy's NNLS alone: the reference the three ways are held to."""
    from scipy.optimize import nnls

    parts = [(features[:, gate.index] * gate.sqrt_weight, gate._cone.A)]  # examples scaled to unit norm
    if gate.has_motion:
        parts.append((gate.motion_vectors(moves), gate._motion_cone.A))
    rho = np.zeros(features.shape[:1] + gate.index.shape[:1])
    for x, examples in parts:
        for q, s in np.ndindex(*x.shape[:2]):
            b = x[q, s].astype(np.float64)
            r = nnls(examples[s].T, b, maxiter=50 * examples.shape[1])[1]
            rho[q, s] = max(rho[q, s], min(1.0, r * r / (b @ b + 1e-12)))
    return rho


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", default="bench/host_stages.json")
    ap.add_argument("--ict-model", default=str(Path(tempfile.gettempdir()) / "ict_model.npz"))
    ap.add_argument("--work", default="bench/work/host_stages")
    args = ap.parse_args(argv)
    rows = []
    if (KIT / "train_mocap.csv").is_file():
        model = _model(ROOT / "configs" / "ict.toml", Path(args.ict_model))
        for name in ("train_mocap.csv", "noisy_mocap.csv"):
            rows.append({"rig": "ICT kit", **measure(model, KIT / name)})
        wrinkled = KIT.parent / "ict_wrinkled" / "train_mocap.csv"
        if wrinkled.is_file():
            model = _model(ROOT / "configs" / "ict_wrinkled.toml", Path(args.work) / "wrinkled_model.npz", "--no-tune")
            rows.append({"rig": "wrinkled ICT kit, examples + 80 frames", **measure(model, wrinkled, repeats=1)})
    else:
        print(f"ICT kit not found at {KIT}: the sample rig alone", file=sys.stderr)
    work = Path(args.work)
    rig = work / "rig"
    if not (rig / "sample.toml").is_file():
        subprocess.run([sys.executable, "-m", "facepipe", "-q", "sample", str(rig), "--frames", "240"], check=True)
    model = _model(rig / "sample.toml", work / "model.npz")
    rows.append({"rig": "sample", **measure(model, rig / "take.csv")})
    for r in rows:
        gate = (f"gate {r['examples']} examples: {r['gate_ms_per_frame_batched']:.2f} ms a frame (batched steps) -> "
                f"{r['gate_ms_per_frame_settled']:.2f} ({r['gate_speedup_over_batched']:.1f}x; confidences within "
                f"{r['confidence_difference_batched']:.1e} -> {r['confidence_difference_settled']:.1e} of exact NNLS); "
                f"every fit to the end {r['gate_ms_per_frame_fits_to_the_end']:.2f}"
                if "gate_ms_per_frame_settled" in r else "no gate")
        print(f"{r['rig']} {r['take']} ({r['frames']} frames): cleaning {r['cleaning_ms_per_frame']:.2f} ms a frame; "
              + gate)
    Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
