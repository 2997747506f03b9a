"""Batch replay on a Dask LocalCluster against the user's baseline: one `facepipe replay` per take.

Makes a sample rig (``facepipe sample``), bakes it, writes N takes of the sample's motion (each
read from another starting frame, back and forth so every take is smooth), then in the same run:

* **serial**: ``facepipe replay TAKE -m MODEL -o serial/<stem>`` for every take, one after another,
  each a new process (Python start-up, model load, OpenCL kernel build, every time);
* **batch**: ``facepipe batch TAKES -m MODEL -o batch --workers W`` (one process; each worker loads
  the model and builds the kernels once);
* **one process** (for reference): every take replayed one after another in this process with one
  model and one evaluator, as a worker does: what the batch gains by running takes side by side
  alone, start-up costs aside.

Reports wall times, the throughput ratio and whether every positions.npy is identical to the byte.
Run from the repository root: ``python -m bench.batch_speed -o bench/batch.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def write_takes(take_csv: Path, out_dir: Path, count: int, frames: int | None = None) -> list[Path]:
    """``count`` takes from one facepipe CSV take: take i starts at another frame and runs back
    and forth through the rows (no jump anywhere), with the original frame and time columns."""
    lines = Path(take_csv).read_text().splitlines()
    header, rows = lines[0], lines[1:]
    T = len(rows)
    frames = frames or T
    stamps = [r.split(",", 2)[:2] for r in rows]
    values = [r.split(",", 2)[2] for r in rows]
    out_dir.mkdir(parents=True, exist_ok=True)
    period = max(1, 2 * (T - 1))
    paths = []
    for i in range(count):
        start = (i * 37) % period
        text = [header]
        for k in range(frames):
            p = (start + k) % period
            src = p if p < T else period - p  # reflect: back and forth through the rows
            frame, t = stamps[k % T] if k < T else (str(k), f"{k / 30.0:.6f}")
            text.append(f"{frame},{t},{values[src]}")
        path = out_dir / f"take_{i:03d}.csv"
        path.write_text("\n".join(text) + "\n")
        paths.append(path)
    return paths


def one_process(takes: list[Path], model_path: Path, out: Path, backend: str) -> float:
    """Seconds to replay every take in this process, loading the model and building the evaluator once."""
    from facepipe.io.model_file import load_model
    from facepipe.pipeline.batch import ReplayOptions, make_evaluator, replay_into

    t0 = time.perf_counter()
    options = ReplayOptions(backend=backend)
    model = load_model(model_path)
    evaluator, _ = make_evaluator(model, options.backend, options.device, options.chunk)
    for take in takes:
        replay_into(str(take), out / take.stem, model, evaluator, options, {})
    return time.perf_counter() - t0


def _run(args: list, env=None) -> float:
    t0 = time.perf_counter()
    subprocess.run(args, check=True, env=env, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default="bench/batch.json")
    parser.add_argument("--work", default="bench/work/batch")
    parser.add_argument("--takes", type=int, default=32)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--vertices", type=int, default=20000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--backend", default="auto", help="replay's --backend for every run")
    parser.add_argument("--no-one-process", dest="one_process", action="store_false",
                        help="leave out the reference run of every take in this process")
    a = parser.parse_args(argv)
    work = Path(a.work)
    fp = [sys.executable, "-m", "facepipe", "--quiet"]
    model = work / "model.npz"
    rig = work / "rig"
    if not model.is_file():
        subprocess.run(fp + ["sample", rig, "--vertices", str(a.vertices), "--frames", str(a.frames)], check=True)
        subprocess.run(fp + ["bake", rig / "sample.toml", "--no-tune", "-o", model], check=True)
    takes = write_takes(rig / "take.csv", work / "takes", a.takes, a.frames)
    serial_dir, batch_dir, one_dir = work / "serial", work / "batch", work / "one_process"
    for d in (serial_dir, batch_dir, one_dir):
        subprocess.run(["rm", "-rf", str(d)], check=True)
    backend = ["--backend", a.backend]
    serial_seconds = sum(_run(fp + ["replay", t, "-m", model, "-o", serial_dir / t.stem] + backend) for t in takes)
    batch_seconds = _run(fp + ["batch", *takes, "-m", model, "-o", batch_dir, "--workers", str(a.workers)] + backend)
    one_seconds = one_process(takes, model, one_dir, a.backend) if a.one_process else None
    identical = all(np.array_equal(np.load(serial_dir / t.stem / "positions.npy"),
                                   np.load(batch_dir / t.stem / "positions.npy")) for t in takes)
    identical_one = None if one_seconds is None else all(
        np.array_equal(np.load(serial_dir / t.stem / "positions.npy"), np.load(one_dir / t.stem / "positions.npy"))
        for t in takes)
    report = json.loads((batch_dir / "batch.json").read_text())
    first = json.loads((serial_dir / takes[0].stem / "replay.json").read_text())
    result = {
        "takes": len(takes), "frames_per_take": a.frames, "vertices": first["vertices"], "backend": first["backend"],
        "model_bytes": model.stat().st_size, "workers": a.workers, "cpus": os.cpu_count(),
        "serial_seconds": serial_seconds, "serial_seconds_per_take": serial_seconds / len(takes),
        "batch_seconds": batch_seconds, "batch_seconds_per_take": batch_seconds / len(takes),
        "batch_task_seconds_per_take": report["totals"]["task_seconds"] / len(takes),
        "throughput_ratio": serial_seconds / batch_seconds,
        "identical_outputs": bool(identical),
        "batch_ok": report["totals"]["ok"], "batch_failed": report["totals"]["failed"],
        "one_process_seconds": one_seconds,
        "ratio_to_one_process": None if one_seconds is None else one_seconds / batch_seconds,
        "one_process_identical": identical_one,
    }
    Path(a.output).parent.mkdir(parents=True, exist_ok=True)
    Path(a.output).write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
