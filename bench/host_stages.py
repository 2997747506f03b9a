"""The host's share of a marker replay, per frame: cleaning (pose and expression fits, smoothing,
gap filling) and the novelty gate's non-negative fits, which run on the CPU beside the kernels.

For each take: cleaning's milliseconds a frame (`prepare_take`, the whole take), and the gate's
(strain and motion parts, chunks of 32 frames as replay hands them over) two ways — every fit run
to its tolerance (what validation needs: ρ itself) and as a replay runs them (fits stop once the
confidence is settled within CONFIDENCE_TOLERANCE of 1) — with the largest difference of the
confidences between the two. On the ICT kit's takes where ../shared is beside the checkout (the
model baked from configs/ict.toml unless --ict-model exists), and on a generated sample rig.

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


def _model(config: Path, path: Path):
    from facepipe.io.model_file import load_model

    if not path.is_file():
        subprocess.run([sys.executable, "-m", "facepipe", "-q", "bake", str(config), "-o", str(path)], check=True,
                       cwd=ROOT)
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

    def run(settle: bool):
        best, conf = np.inf, None
        for _ in range(repeats):
            t0 = time.perf_counter()
            if settle:
                conf = np.concatenate([gate.site_confidences(features[c], moves[c]) for c in chunks])
            else:
                conf = np.concatenate([gate.site_confidence(gate.novelty(features[c], moves[c])) for c in chunks])
            best = min(best, time.perf_counter() - t0)
        return 1000 * best / T, conf

    full_ms, full = run(False)
    settled_ms, settled = run(True)
    out.update(sites=int(gate.index.shape[0]), examples=int(gate.examples.shape[1]),
               gate_ms_per_frame_fits_to_tolerance=full_ms, gate_ms_per_frame_settled=settled_ms,
               gate_speedup=full_ms / settled_ms, largest_confidence_difference=float(np.abs(full - settled).max()))
    return out


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
    else:
        print(f"ICT kit not found at {KIT}: the sample rig alone", file=sys.stderr)
    work = Path(args.work)
    rig = work / "rig"
    if not (rig / "sample.toml").is_file():
        subprocess.run([sys.executable, "-m", "facepipe", "-q", "sample", str(rig), "--frames", "240"], check=True)
    model = _model(rig / "sample.toml", work / "model.npz")
    rows.append({"rig": "sample", **measure(model, rig / "take.csv")})
    for r in rows:
        gate = (f"gate {r['gate_ms_per_frame_fits_to_tolerance']:.2f} -> {r['gate_ms_per_frame_settled']:.2f} ms a frame "
                f"({r['gate_speedup']:.1f}x; confidences within {r['largest_confidence_difference']:.1e})"
                if "gate_speedup" in r else "no gate")
        print(f"{r['rig']} {r['take']} ({r['frames']} frames): cleaning {r['cleaning_ms_per_frame']:.2f} ms a frame; "
              + gate)
    Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
