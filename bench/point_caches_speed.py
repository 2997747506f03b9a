"""Throughput of a point cache replayed as a take (``--large-scale take``) against the marker replay.

    python -m bench.point_caches_speed [--vertices 530000] [--frames 32] [--json bench/point_caches_speed.json]

A sample rig of the paper's size (89 markers, 6 examples) is generated and baked (``--no-tune``); its
take is replayed from markers (default backend: OpenCL where a device works); its smooth cache
(``take_smooth.mdd``, written by ``facepipe sample``: some bands of the details added, filtered once
into the model's weights before the replay) and the marker replay's own large scale as an MDD
(every band added) are replayed as takes. Per-stage seconds (``stage_seconds``) are the replay's:
device kernels from profiling events, host stages (the cache's frames laid out for the device,
the handles' tables, the sink's writing) from the clock. Frames per second are the
replays' own (``replay.json``: the replay after the model is loaded and, for the cache, after the
bands are chosen), and the whole command's wall time beside them.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def facepipe(*args) -> float:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "facepipe", *map(str, args)], check=True, env=env)
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", default=str(Path(tempfile.gettempdir()) / "facepipe_point_caches_speed"))
    ap.add_argument("--vertices", type=int, default=530000)
    ap.add_argument("--frames", type=int, default=32)
    ap.add_argument("--json", default=str(ROOT / "bench" / "point_caches_speed.json"))
    args = ap.parse_args(argv)
    work = Path(args.work)
    rig = work / "rig"
    model = work / "model.npz"
    if not (rig / "take_smooth.mdd").is_file():
        facepipe("sample", rig, "--vertices", args.vertices, "--markers", 89, "--examples", 6, "--frames",
                 args.frames, "-q")
    if not model.is_file():
        facepipe("bake", rig / "sample.toml", "-o", model, "--no-tune", "-q")
    out = {"vertices": args.vertices, "frames": args.frames}
    # a cache the shell made (every band of the details added: nothing solved on the host)
    large = work / "large.mdd"
    if not large.is_file():
        facepipe("replay", rig / "take.csv", "-m", model, "-o", work / "large_replay", "--save-large-scale", "-q")
        facepipe("export", work / "large_replay", "--format", "mdd", "--layer", "large", "-o", large, "-q")
    runs = [("marker_replay", rig / "take.csv", []), ("marker_replay_numpy", rig / "take.csv", ["--backend", "numpy"]),
            ("cache_take", rig / "take_smooth.mdd", []), ("cache_take_every_band", large, []),
            ("cache_shell", rig / "take_smooth.mdd", ["--large-scale", "shell"])]
    for name, take, extra in runs:
        wall = facepipe("replay", take, "-m", model, "-o", work / name, "-q", "--force", *extra)
        info = json.loads((work / name / "replay.json").read_text())
        out[name] = {"frames_per_second": info["frames_per_second"], "backend": info["backend"],
                     "command_seconds": wall, "stage_seconds": info["stage_seconds"]}
        print(f"{name}: {info['frames_per_second']:.2f} frames/s ({info['backend']}), command {wall:.1f} s",
              file=sys.stderr)
    for name in ("cache_take", "cache_take_every_band"):
        out[f"{name}_vs_marker_replay"] = out[name]["frames_per_second"] / out["marker_replay"]["frames_per_second"]
    Path(args.json).write_text(json.dumps(out, indent=2))
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
