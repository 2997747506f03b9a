"""The local-strain detail model on the wrinkled ICT kit (../shared/data/ict_wrinkled, see its README).

(a) Kit protocol: fit on the 26 wrinkled expressions (and, for the "+ take" rows, frames 0–79 of
    the wrinkled training take as further training poses), replay the take's markers
    (train_mocap.csv), measure frames 80–119: face RMS (cm, vertices 0:9409) and wrinkle recovery
    k = ⟨P − S, T − S⟩ / ⟨T − S, T − S⟩ (T wrinkled truth, S plain truth), for the large scale
    alone, WPSD (the config's values) and the local-strain model.
(b) Leave expressions out: fit on 20 wrinkled expressions (every 4th from the second held out, as
    bench/ict_split.py), replay (i) the 6 held-out wrinkled expressions themselves and (ii) the
    frames of the training take whose strongest expression is a held-out one; RMS, recovery and
    the worst frame's excess over the large scale alone.
Replay speed of each model (NumPy, and OpenCL where a device exists) on the kit's mesh.

Usage: python -m bench.ict_wrinkled_local [--json bench/ict_wrinkled_local.json] [--no-performance]
"""

import argparse
import csv
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from facepipe import opencl
from facepipe.io.model_file import model_from_fit
from facepipe.pipeline.fit import fit_rig
from facepipe.pipeline.replay import NumpyEvaluator
from facepipe.pipeline.rig import load_rig

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
FACE = slice(0, 9409)
TRAIN, TEST = slice(0, 80), slice(80, 120)


def take_markers(path: Path, names: list[str]) -> np.ndarray:
    """Head-space marker positions (T, H, 3) of a facepipe CSV take, in the rig's handle order."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    header, values = rows[0], np.array(rows[1:], dtype=np.float64)
    column = {name: i for i, name in enumerate(header)}
    return np.stack([values[:, [column[f"{n}_x"], column[f"{n}_y"], column[f"{n}_z"]]] for n in names], axis=1)


def scores(P: np.ndarray, T: np.ndarray, S: np.ndarray, large_rms: np.ndarray | None = None) -> dict:
    """Face RMS per frame, its mean, the wrinkle recovery over all frames, the worst excess over the large scale."""
    rms = np.sqrt(((P - T)[:, FACE] ** 2).sum(-1).mean(-1))
    a, b = (P - S)[:, FACE], (T - S)[:, FACE]
    out = {"rms_mean": float(rms.mean()), "recovery": float((a * b).sum() / (b * b).sum()), "per_frame": rms}
    if large_rms is not None:
        excess = rms - large_rms
        out.update(worst_excess=float(excess.max()), frames_worse_0_01=int((excess > 0.01).sum()),
                   frames_better=int((excess < 0).sum()))
    return out


def replay_rows(models: dict, head: np.ndarray, T: np.ndarray, S: np.ndarray) -> dict:
    rows = {}
    large_rms = None
    for name, model in models.items():
        ev = NumpyEvaluator(model)
        t0 = time.perf_counter()
        P = ev.evaluate(head)
        seconds = time.perf_counter() - t0
        row = scores(P, T, S, large_rms)
        if large_rms is None:
            large_rms = row["per_frame"]
        row["numpy_frames_per_second"] = len(head) / seconds
        rows[name] = row
    for row in rows.values():
        row.pop("per_frame")
    return rows


def show(title: str, rows: dict) -> None:
    print(title)
    for name, r in rows.items():
        extra = "" if "worst_excess" not in r else (f"  worst frame {r['worst_excess']:+.4f} cm, frames worse by >0.01: "
                                                    f"{r['frames_worse_0_01']}, better: {r['frames_better']}")
        print(f"  {name:28s} RMS {r['rms_mean']:.4f} cm  recovery {r['recovery']:+.3f}{extra}", flush=True)


def with_examples(rig, positions: np.ndarray, names: list[str], **psd):
    rig = dataclasses.replace(rig, example_positions=positions, example_names=names)
    if psd:
        rig.config = dataclasses.replace(rig.config, psd=dataclasses.replace(rig.config.psd, **psd))
    return rig


def kit_protocol(rig, take_head, T, S, performance: bool) -> dict:
    fit = fit_rig(rig)
    models = {"large scale": model_from_fit(fit, rig, "none"), "WPSD (config's values)": model_from_fit(fit, rig),
              "local strain": model_from_fit(fit, rig, "local_strain")}
    seconds = {}
    if performance:
        seq = T[TRAIN]
        names = list(rig.example_names) + [f"take:{i}" for i in range(len(seq))]
        rig_seq = with_examples(rig, np.concatenate([rig.example_positions, seq]), names)
        t0 = time.perf_counter()
        fit_seq = fit_rig(with_examples(rig_seq, rig_seq.example_positions, names, method="local_strain"))
        seconds["local strain + take: fit"] = time.perf_counter() - t0
        models["local strain + take 0-79"] = model_from_fit(fit_seq, rig_seq)
        rig_ls = with_examples(rig_seq, rig_seq.example_positions, names, fit="least-squares", max_poses=26)
        t0 = time.perf_counter()
        fit_ls = fit_rig(rig_ls)
        seconds["WPSD P=26 least squares + take: fit"] = time.perf_counter() - t0
        models["WPSD P=26 LS + take 0-79"] = model_from_fit(fit_ls, rig_ls)
    rows = replay_rows(models, take_head[TEST], T[TEST], S[TEST])
    opencl_fps = {}
    if opencl.opencl_available():
        for name, model in models.items():
            ev = opencl.OpenCLEvaluator(model)
            ev.evaluate(take_head[TEST])  # (compiles)
            t0 = time.perf_counter()
            ev.evaluate(take_head[TEST])
            opencl_fps[name] = 40 / (time.perf_counter() - t0)
            rows[name]["opencl_frames_per_second"] = opencl_fps[name]
    return {"rows": rows, "seconds": seconds}


def leave_expressions_out(rig, plain_rig, take_head, T, S, weights) -> dict:
    names = list(rig.example_names)
    held = [i for i in range(len(names)) if i % 4 == 1][:6]
    keep = [i for i in range(len(names)) if i not in held]
    sub = with_examples(rig, rig.example_positions[keep], [names[i] for i in keep])
    fit = fit_rig(sub)
    models = {"large scale": model_from_fit(fit, sub, "none"), "WPSD (config's values)": model_from_fit(fit, sub),
              "local strain": model_from_fit(fit, sub, "local_strain")}
    wrinkled = rig.example_positions[held]
    plain = plain_rig.example_positions[[plain_rig.example_names.index(names[i]) for i in held]]
    meshes = replay_rows(models, wrinkled[:, rig.handles], wrinkled, plain)
    frames = np.flatnonzero(np.isin(weights.argmax(axis=1), held))
    take = replay_rows(models, take_head[frames], T[frames], S[frames])
    return {"held_out": [names[i] for i in held], "take_frames": frames.tolist(), "expressions": meshes,
            "take": take}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=str(ROOT / "configs" / "ict_wrinkled_examples.toml"))
    ap.add_argument("--plain-config", default=str(ROOT / "configs" / "ict.toml"))
    ap.add_argument("--no-performance", action="store_true", help="skip the rows trained on the take's frames 0–79")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    rig = load_rig(args.config)
    plain_rig = load_rig(args.plain_config)
    wrinkled = np.load(DATA / "ict_wrinkled" / "train_truth.npz")
    T = wrinkled["positions"].astype(np.float64)
    S = np.load(DATA / "ict" / "train_truth.npz")["positions"].astype(np.float64)
    head = take_markers(DATA / "ict_wrinkled" / "train_mocap.csv", rig.markers.handle_names)
    result = {"kit": kit_protocol(rig, head, T, S, not args.no_performance)}
    show("(a) kit protocol: fit on the 26 wrinkled expressions, replay the take's markers, frames 80-119",
         result["kit"]["rows"])
    lo = leave_expressions_out(rig, plain_rig, head, T, S, wrinkled["weights"])
    result["leave_expressions_out"] = lo
    show(f"(b) fit on 20, the 6 held-out wrinkled expressions ({', '.join(lo['held_out'])})", lo["expressions"])
    show(f"(b) fit on 20, the {len(lo['take_frames'])} take frames led by a held-out expression", lo["take"])
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
