"""A small replayed rig shared by the export tests (built once per test session).

A 2,500-vertex sample rig (UVs on a grid, one tile), fitted once; a PSD model without the
novelty gate, one with it, and a WPSD model; for each a replay of the take's truth handles with a synthetic rigid head motion, so that
exports in the take's space and in head space differ; the truth in the take's space.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facepipe.io.model_file import model_arrays, model_from_fit, save_model
from facepipe.pipeline.replay import replay

N_VERTICES = 2500
N_FRAMES = 6


@dataclass
class ExportRig:
    root: Path
    models: dict  # method -> model path
    replays: dict  # method -> replay folder
    truth: Path  # truth .npz in the take's space (positions, frame, time)


def head_motion(n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """A small rigid motion per frame: rotations about a tilted axis up to ~10°, translations ~1 cm."""
    angles = np.radians(np.linspace(0.0, 10.0, n_frames))
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.stack([np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K for a in angles])
    t = np.stack([np.linspace(0, 1.0, n_frames), np.linspace(0, -0.5, n_frames), np.zeros(n_frames)], axis=1)
    return R, t


def build(root: Path) -> ExportRig:
    """Make (or reuse) the rig under ``root``."""
    root = Path(root)
    done = root / "done.json"
    if done.is_file():
        d = json.loads(done.read_text())
        return ExportRig(root, {k: Path(v) for k, v in d["models"].items()},
                         {k: Path(v) for k, v in d["replays"].items()}, Path(d["truth"]))
    from facepipe.pipeline.fit import fit_rig
    from facepipe.pipeline.rig import load_rig
    from facepipe.sample_rig import write_sample_rig

    write_sample_rig(root / "rig", n_vertices=N_VERTICES, n_frames=N_FRAMES)
    rig = load_rig(root / "rig" / "sample.toml")
    fit = fit_rig(rig)
    truth = np.load(root / "rig" / "take_truth.npz")
    head_truth = truth["positions"].astype(np.float64)
    frames = np.arange(10, 10 + N_FRAMES)  # take frame numbers that are not file numbers
    times = frames / 24.0
    R, t = head_motion(N_FRAMES)
    models, replays = {}, {}
    # "psd" without the novelty gate (its details are exactly a frame-constant blend),
    # "psd_gated" and "wpsd" with the rig's gate as configured
    for name in ("psd", "psd_gated", "wpsd"):
        method = name.split("_")[0]
        model = model_from_fit(fit, rig, method=method)
        arrays, meta = model_arrays(fit, rig)
        arrays.update({k: model.arrays[k] for k in ("basis_features", "rbf_weights", "rbf_const")})
        path = root / f"model_{name}.npz"
        meta = dict(meta, method=method, basis=model.meta["basis"])
        if name == "psd":
            meta["novelty_tau"] = 0.0
        save_model(path, arrays, meta)
        from facepipe.io.model_file import load_model

        model = load_model(path)
        head = head_truth[:, model.handle_vertices]
        out = root / f"replay_{name}"
        replay(model, head, R, t, frames, times, out, head_motion="keep", save_large=True)
        models[name], replays[name] = path, out
    world = np.einsum("tij,tvj->tvi", R, head_truth) + t[:, None]
    np.savez(root / "truth.npz", positions=world.astype(np.float32), frame=frames, time=times)
    done.write_text(json.dumps({"models": {k: str(v) for k, v in models.items()},
                                "replays": {k: str(v) for k, v in replays.items()},
                                "truth": str(root / "truth.npz")}))
    return build(root)
