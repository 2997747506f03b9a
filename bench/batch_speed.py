"""Batch replay on a Dask LocalCluster against the user's baseline: one `facepipe replay` per take.

Makes a sample rig (``facepipe sample``), bakes it, writes N takes of the sample's motion (each
read from another starting frame, back and forth so every take is smooth), then in the same run:

* **serial**: ``facepipe replay TAKE -m MODEL -o serial/<stem>`` for every take, one after another,
  each a new process (Python start-up, model load, OpenCL kernel build, every time), half of the
  takes before the batch and half after;
* **batch**: ``facepipe batch TAKES -m MODEL -o batch --workers W`` (one process; each worker loads
  the model and builds the kernels once);
* **one process** (for reference): every take replayed one after another in this process with one
  model and one evaluator, as a worker does: what the batch gains by running takes side by side
  alone, start-up costs aside.

Reports wall times and the throughput ratio, the CPU time and page faults each way spends per
take (what a machine shared with other work blurs least), the load average around and during the
run, and whether every positions.npy is identical to the byte.
Run from the repository root: ``python -m bench.batch_speed -o bench/batch.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import threading
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


def one_process(takes: list[Path], model_path: Path, out: Path, backend: str) -> None:
    """Replay every take in this process, loading the model and building the evaluator once."""
    from facepipe.io.model_file import load_model
    from facepipe.batch.jobs import ModelRef, ReplayOptions, file_digest, replay_into

    options = ReplayOptions(backend=backend)
    model = load_model(model_path)
    # the evaluator is this process's for the model (made for the first take, reused by the rest),
    # as each batch worker holds one
    ref = ModelRef(str(Path(model_path).resolve()), file_digest(model_path))
    for take in takes:
        replay_into(str(take), out / take.stem, model, ref, options, {"batch": {}})


def _usage() -> tuple[float, int]:
    """User + system CPU seconds and minor page faults of this process and of its children that
    have ended (the replay processes, the local cluster's workers, and the PoCL threads within them)."""
    both = (resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN))
    return sum(r.ru_utime + r.ru_stime for r in both), sum(r.ru_minflt for r in both)


def measured(function, *args) -> tuple[float, float, int]:
    """(wall seconds, CPU seconds, minor page faults) of ``function(*args)``."""
    wall, (cpu, faults) = time.perf_counter(), _usage()
    function(*args)
    cpu_after, faults_after = _usage()
    return time.perf_counter() - wall, cpu_after - cpu, faults_after - faults


class LoadSampler:
    """The machine's 1-minute load average every ``interval`` seconds while the bench runs (the
    other work on a shared machine, which the wall-clock figures depend on)."""

    def __init__(self, interval: float = 10.0):
        self.samples = [os.getloadavg()[0]]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(interval,), daemon=True)
        self._thread.start()

    def _run(self, interval: float) -> None:
        while not self._stop.wait(interval):
            self.samples.append(os.getloadavg()[0])

    def stop(self) -> list[float]:
        self._stop.set()
        self._thread.join()
        self.samples.append(os.getloadavg()[0])
        return [min(self.samples), max(self.samples)]


def _run(args: list) -> None:
    subprocess.run([str(a) for a in args], check=True, stdout=subprocess.DEVNULL)


def _same(a: Path, b: Path, takes) -> bool:
    return all(np.array_equal(np.load(a / t.stem / "positions.npy"), np.load(b / t.stem / "positions.npy"))
               for t in takes)


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
        _run(fp + ["sample", rig, "--vertices", a.vertices, "--frames", a.frames])
        _run(fp + ["bake", rig / "sample.toml", "--no-tune", "-o", model])
    takes = write_takes(rig / "take.csv", work / "takes", a.takes, a.frames)
    serial_dir, batch_dir, one_dir = work / "serial", work / "batch", work / "one_process"
    for d in (serial_dir, batch_dir, one_dir):
        subprocess.run(["rm", "-rf", str(d)], check=True)
    backend = ["--backend", a.backend]
    half = len(takes) // 2
    loads = [os.getloadavg()[0]]
    sampler = LoadSampler()

    def serial(part):
        for t in part:
            _run(fp + ["replay", t, "-m", model, "-o", serial_dir / t.stem] + backend)

    # the machine may be shared: the baseline runs in two halves, before and after the batch, so a
    # change of the other load weighs on both
    wall_a, cpu_a, faults_a = measured(serial, takes[:half])
    batch_wall, batch_cpu, batch_faults = measured(_run, fp + ["batch", *takes, "-m", model, "-o", batch_dir,
                                                               "--workers", str(a.workers)] + backend)
    one_wall, one_cpu, _ = measured(one_process, takes, model, one_dir, a.backend) if a.one_process \
        else (None, None, None)
    wall_b, cpu_b, faults_b = measured(serial, takes[half:])
    loads.append(os.getloadavg()[0])
    load_range = sampler.stop()
    serial_wall, serial_cpu = wall_a + wall_b, cpu_a + cpu_b
    report = json.loads((batch_dir / "batch.json").read_text())
    first = json.loads((serial_dir / takes[0].stem / "replay.json").read_text())
    n = len(takes)
    result = {
        "takes": n, "frames_per_take": a.frames, "vertices": first["vertices"], "backend": first["backend"],
        "model_bytes": model.stat().st_size, "workers": a.workers, "cpus": os.cpu_count(),
        "load_average_before_after": loads,
        "load_average_min_max": load_range,  # sampled every 10 s during the run
        "serial_seconds": serial_wall, "serial_seconds_per_take": serial_wall / n,
        "batch_seconds": batch_wall, "batch_seconds_per_take": batch_wall / n,
        "throughput_ratio": serial_wall / batch_wall,
        "serial_cpu_seconds_per_take": serial_cpu / n, "batch_cpu_seconds_per_take": batch_cpu / n,
        "cpu_ratio": serial_cpu / batch_cpu,
        "serial_page_faults_per_take": (faults_a + faults_b) / n, "batch_page_faults_per_take": batch_faults / n,
        "batch_task_seconds_per_take": report["totals"]["task_seconds"] / n,
        "identical_outputs": _same(serial_dir, batch_dir, takes),
        "batch_ok": report["totals"]["ok"], "batch_failed": report["totals"]["failed"],
        "one_process_seconds": one_wall,
        "one_process_cpu_seconds_per_take": None if one_cpu is None else one_cpu / n,
        "ratio_to_one_process": None if one_wall is None else one_wall / batch_wall,
        "one_process_identical": None if one_wall is None else _same(serial_dir, one_dir, takes),
    }
    Path(a.output).parent.mkdir(parents=True, exist_ok=True)
    Path(a.output).write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
