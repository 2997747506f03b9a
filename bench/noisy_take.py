"""Accuracy of replaying a noisy, occluded take with head motion (the ICT kit's noisy_mocap.csv).

Replays ../shared/data/ict/noisy_mocap.csv and a clean take made from noisy_truth.npz (the
truth's positions at the marker vertices: world space, head motion included, no noise, no
gaps) through the same pipeline as `facepipe replay` (read_take -> prepare_take -> model), and
prints the face-area (vertices 0:9409) RMS error against the truth per variant:

    noisy / clean mean RMS, their ratio (the issue asks <= 1.25) and the worst per-frame ratio
    (issue #22 asks <= 1.5 on every frame), for cleaning and stabilisation on / off, smoothing,
    and the pipeline before this work (stable-marker stabilisation + PCHIP gap filling) for reference.

Per frame it also prints what the noise alone moves (noisy vs clean replay) at the take's ends and in
its interior, the pose bounds of the take's first frames, and with --draws N the per-frame ratios
over N fresh noise draws of the same truth and gaps (the kit's take is one draw); with
--smoother-grid N, the first frame's ratio with the expression known, placed by every pose
smoother of the cleaning's family (orders 2-4, λ over its candidates), over N draws.

Usage:  PYTHONPATH=. python bench/noisy_take.py [--model /tmp/ict_model.npz] [--json out.json] [--draws N] [--smoother-grid N]
The model is baked from configs/ict.toml (`facepipe bake`: the validated rig) when the file does not exist.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
KIT = ROOT.parent / "shared" / "data" / "ict"
FACE = slice(0, 9409)


def load_or_bake(path: Path):
    """The model at ``path``, baked first from configs/ict.toml as `facepipe bake` does (the
    validated rig, the default) when the file does not exist."""
    from facepipe.io.model_file import load_model

    if not path.is_file():
        print(f"baking {path} from configs/ict.toml (validated) ...", file=sys.stderr)
        subprocess.run([sys.executable, "-m", "facepipe", "-q", "bake", str(ROOT / "configs" / "ict.toml"),
                        "-o", str(path)], check=True, cwd=ROOT)
    return load_model(path)


def replay_errors(take, model, truth, evaluator, **options):
    """Per-frame face RMS (final and large-scale) of a take replayed with PrepareOptions(**options), the
    report, and the final face in world space."""
    from facepipe.mocap.cleaning import CleanOptions
    from facepipe.mocap.prepare import PrepareOptions, prepare_take

    smooth = options.pop("smooth", 0.0)
    head, R, t, report = prepare_take(take, model, PrepareOptions(clean_options=CleanOptions(smooth=smooth),
                                                                  **options))
    final, large = evaluator.evaluate(head, with_large=True)
    errs, worlds = [], []
    for out in (final, large):
        worlds.append(np.einsum("tij,tvj->tvi", R, out) + t[:, None, :])
        errs.append(np.sqrt(((worlds[-1] - truth)[:, FACE] ** 2).sum(-1).mean(-1)))
    return errs[0], errs[1], report, worlds[0]


def legacy_errors(take, model, truth, evaluator):
    """The pipeline before issue #4: stable-marker stabilisation (with the prior) + PCHIP filling."""
    from facepipe.mocap import fill_gaps
    from facepipe.core.rigid import interpolate_poses, stable_marker_pose

    rest = model.rest[model.handle_vertices].astype(np.float64)
    R, t = stable_marker_pose(rest, take.positions, model.stable.astype(bool), [])
    R, t, _ = interpolate_poses(R, t, take.times)
    head = np.einsum("tji,thj->thi", R, take.positions - t[:, None, :])
    head, _ = fill_gaps(head, times=take.times)
    out = evaluator.evaluate(head)
    world = np.einsum("tij,tvj->tvi", R, out) + t[:, None, :]
    return np.sqrt(((world - truth)[:, FACE] ** 2).sum(-1).mean(-1))


def single_frame_pose_bound(take, model, truth, data):
    """Per-frame face RMS of the true shape placed by the best rigid fit of its own markers to the
    noisy visible ones: what one frame's markers can tell of the head pose even when the expression
    is known exactly. A take's first and last frames have no neighbours on one side, so no cleaning
    gets far below this there."""
    from facepipe.core.rigid import rigid_fit

    R_true, t_true = data["rotation"], data["translation"]
    head_truth = np.einsum("tji,tvj->tvi", R_true, truth - t_true[:, None, :])
    errs = np.empty(len(truth))
    for f in range(len(truth)):
        seen = np.isfinite(take.positions[f]).all(axis=1)
        R, t = rigid_fit(head_truth[f, model.handle_vertices][seen], take.positions[f][seen])
        world = head_truth[f] @ R.T + t
        errs[f] = np.sqrt(((world - truth[f])[FACE] ** 2).sum(-1).mean())
    return errs


def _true_shape_poses(positions: np.ndarray, truth: np.ndarray, data, handles: np.ndarray):
    """Each frame's best rigid fit (R, t) of the true shape's markers (head space) to the markers
    ``positions`` (T, H, 3; NaN where missing), and those head-space markers (T, H, 3)."""
    from facepipe.core.rigid import rigid_fit

    head = np.einsum("tji,tvj->tvi", data["rotation"], truth - data["translation"][:, None, :])[:, handles]
    seen = np.isfinite(positions).all(axis=-1)
    R, t = rigid_fit(head, np.where(seen[..., None], positions, 0.0), seen.astype(np.float64))
    return R, t, head


def _placed_errors(R: np.ndarray, t: np.ndarray, head_shape: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per-frame face RMS (T,) of a head-space shape (T, V, 3) placed by poses R, t."""
    world = np.einsum("tij,tvj->tvi", R, head_shape[:, FACE]) + t[:, None, :]
    return np.sqrt(((world - truth[:, FACE]) ** 2).sum(-1).mean(-1))


def _noise_draw(noisy, truth: np.ndarray, handles: np.ndarray, sigma: float, k: int) -> np.ndarray:
    """Draw k of the take's markers: the truth's with fresh Gaussian noise σ, missing where the kit's take is."""
    rng = np.random.default_rng(1000 + k)
    markers = truth[:, handles] + rng.normal(scale=sigma, size=noisy.positions.shape)
    markers[~np.isfinite(noisy.positions).all(axis=-1)] = np.nan
    return markers


def smoothed_pose_bound(take, model, truth, data, evaluator, clean_head):
    """Per-frame face RMS of the clean replay's shape placed by the pose cleaning would give if it
    knew the true expression: each frame's best rigid fit of the true shape's markers to the noisy
    ones, smoothed over the take as cleaning smooths poses. What the first and last frames reach
    when only the head pose is estimated; the expression's noise comes on top."""
    from facepipe.mocap.cleaning import _smooth_poses

    R, t, head = _true_shape_poses(take.positions, truth, data, model.handle_vertices)
    R, t = _smooth_poses(R, t, head.mean(axis=(0, 1)))
    return _placed_errors(R, t, evaluator.evaluate(clean_head), truth)


def smoother_grid_bound(noisy, model, truth, data, clean_final, clean_errors, sigma: float, draws: int) -> dict:
    """What any Whittaker smoother of the head poses can reach at the take's first frame, with the
    expression known: per noise draw (the measured σ, the kit's gaps) each frame's pose is the best
    rigid fit of the true shape's markers to the noisy ones, then rotation and centre are smoothed
    with one order and λ (orders 2-4, every 4th λ of the cleaning's candidates), and the clean
    replay's face (``clean_final``, head space) is placed by it, as :func:`smoothed_pose_bound` does
    with the cleaning's own choice. Per setting the first frame's ratio to the clean replay, median
    over the draws, and the interior's worst frame (median over the draws)."""
    from scipy.spatial.transform import Rotation

    from facepipe.core.temporal import LAMBDAS, whittaker

    fits = [_true_shape_poses(_noise_draw(noisy, truth, model.handle_vertices, sigma, k), truth, data,
                              model.handle_vertices) for k in range(draws)]
    centre = fits[0][2].mean(axis=(0, 1))

    def ratio(R, t):
        return _placed_errors(R, t, clean_final, truth) / clean_errors

    def smoothed(R, t, order, lam):
        mean = Rotation.from_matrix(R).mean()
        v = whittaker((mean.inv() * Rotation.from_matrix(R)).as_rotvec(), lam, order)
        moved = whittaker(np.einsum("tij,j->ti", R, centre) + t, lam, order)
        Rs = (mean * Rotation.from_rotvec(v)).as_matrix()
        return Rs, moved - np.einsum("tij,j->ti", Rs, centre)

    raw = np.array([ratio(R, t) for R, t, _ in fits])
    settings = []
    for order in (2, 3, 4):
        for lam in LAMBDAS[::4]:
            r = np.array([ratio(*smoothed(R, t, order, lam)) for R, t, _ in fits])
            settings.append({"order": order, "lambda": float(lam), "first_median": float(np.median(r[:, 0])),
                             "interior_worst_median": float(np.median(r[:, 5:-5].max(axis=1)))})
    best = min(settings, key=lambda s: s["first_median"])
    print(f"first frame with the expression known, {draws} draws: single frame median {np.median(raw[:, 0]):.2f}; "
          f"best Whittaker smoother (order {best['order']}, λ {best['lambda']:.3g}) median {best['first_median']:.2f}, "
          f"interior worst {best['interior_worst_median']:.2f}")
    return {"single_frame_first_median": float(np.median(raw[:, 0])), "best": best, "settings": settings}


def noise_draws(noisy, model, truth, evaluator, clean_errors, sigma: float, draws: int, data, clean_head) -> dict:
    """The kit's take is one draw of its noise: the same truth and gaps with fresh Gaussian noise of the
    measured σ, ``draws`` times; per draw the first and last frames' ratio to the clean replay, the
    worst frame's and the mean's. Says how much of a frame's ratio is the draw. Per draw also the
    first and last frames' ratio with the head pose alone estimated (:func:`smoothed_pose_bound`):
    what no better expression estimate can go below."""
    from facepipe.mocap import Take

    out = {"first": [], "last": [], "worst": [], "mean": [], "pose_alone_first": [], "pose_alone_last": []}
    for k in range(draws):
        markers = _noise_draw(noisy, truth, model.handle_vertices, sigma, k)
        take = Take(frames=noisy.frames.copy(), times=noisy.times.copy(), positions=markers,
                    marker_names=noisy.marker_names, path="(draw)", units=noisy.units, source_units=noisy.units,
                    format="facepipe-csv")
        ratio = replay_errors(take, model, truth, evaluator)[0] / clean_errors
        pose_alone = smoothed_pose_bound(take, model, truth, data, evaluator, clean_head) / clean_errors
        for key, value in (("first", ratio[0]), ("last", ratio[-1]), ("worst", ratio.max()),
                           ("mean", ratio.mean()), ("pose_alone_first", pose_alone[0]),
                           ("pose_alone_last", pose_alone[-1])):
            out[key].append(float(value))
    print(f"{draws} fresh noise draws (σ {sigma:.4f}, the kit's gaps), per-frame ratio: first frame median "
          f"{np.median(out['first']):.2f} (range {min(out['first']):.2f}–{max(out['first']):.2f}), last frame median "
          f"{np.median(out['last']):.2f}, worst frame median {np.median(out['worst']):.2f}, "
          f"mean of the per-frame ratios {np.mean(out['mean']):.3f}")
    print(f"  the head pose alone (true expression): first frame median {np.median(out['pose_alone_first']):.2f} "
          f"(range {min(out['pose_alone_first']):.2f}–{max(out['pose_alone_first']):.2f}), last frame median "
          f"{np.median(out['pose_alone_last']):.2f}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default=str(Path(tempfile.gettempdir()) / "ict_model.npz"))
    ap.add_argument("--json", default=None)
    ap.add_argument("--draws", type=int, default=0, help="also replay this many fresh noise draws of the take")
    ap.add_argument("--smoother-grid", type=int, default=0, metavar="DRAWS",
                    help="also the first frame's bound over every pose smoother of the cleaning's family, "
                         "with the expression known, over this many noise draws")
    args = ap.parse_args(argv)
    if args.draws < 0 or args.smoother_grid < 0:
        ap.error("--draws and --smoother-grid take a number of noise draws, 0 or more")
    if not (KIT / "noisy_mocap.csv").is_file():
        print(f"the ICT kit is not at {KIT}", file=sys.stderr)
        return 1
    from facepipe.mocap import Take, read_take
    from facepipe.pipeline.replay import NumpyEvaluator

    model = load_or_bake(Path(args.model))
    names = model.marker_names
    units = model.meta["units"]
    noisy = read_take(KIT / "noisy_mocap.csv", names, units=units)
    data = np.load(KIT / "noisy_truth.npz")
    truth = data["positions"].astype(np.float64)
    clean = Take(frames=noisy.frames.copy(), times=noisy.times.copy(),
                 positions=truth[:, model.handle_vertices].copy(), marker_names=names, path="(truth markers)",
                 units=units, source_units=units, format="facepipe-csv")
    ev = NumpyEvaluator(model)

    variants = [
        ("default (stabilise + clean)", {}),
        ("smooth 1 frame", {"smooth": 1.0}),
        ("smooth 2 frames", {"smooth": 2.0}),
        ("--no-clean", {"clean": False}),
        ("--no-stabilise", {"stabilise": False}),
        ("--no-clean --no-stabilise", {"clean": False, "stabilise": False}),
    ]
    rows = []
    ref_clean, _, _, clean_world = replay_errors(clean, model, truth, ev)
    print(f"{'variant':30s} {'noisy':>8s} {'clean':>8s} {'ratio':>6s} {'worst':>6s} {'vs ref':>7s} "
          f"{'worst':>6s} {'large n':>8s} {'large c':>8s}")
    for label, opts in variants:
        en, ln, rep, world = replay_errors(noisy, model, truth, ev, **dict(opts))
        ec, lc, _, _ = replay_errors(clean, model, truth, ev, **dict(opts))
        if not rows:  # the default: what the noise alone moves, the clean replay's own error aside
            noise_moved = np.sqrt(((world - clean_world)[:, FACE] ** 2).sum(-1).mean(-1))
        row = {"variant": label, "noisy_rms": float(en.mean()), "clean_rms": float(ec.mean()),
               "ratio": float(en.mean() / ec.mean()), "worst_frame_ratio": float((en / ec).max()),
               "ratio_vs_default_clean": float(en.mean() / ref_clean.mean()),
               "worst_vs_default_clean": float((en / ref_clean).max()),
               "large_scale_noisy_rms": float(ln.mean()), "large_scale_clean_rms": float(lc.mean()),
               "outliers": rep["total"].get("outliers"), "noise_sigma": rep["cleaning"].get("noise", {}).get("sigma"),
               "frame_ratios_first": [float(x) for x in (en / ec)[:10]],
               "frame_ratios_last": [float(x) for x in (en / ec)[-10:]],
               "frames_over_1_5": int(((en / ec) > 1.5).sum())}
        rows.append(row)
        print(f"{label:30s} {row['noisy_rms']:8.5f} {row['clean_rms']:8.5f} {row['ratio']:6.3f} "
              f"{row['worst_frame_ratio']:6.2f} {row['ratio_vs_default_clean']:7.3f} "
              f"{row['worst_vs_default_clean']:6.2f} "
              f"{row['large_scale_noisy_rms']:8.5f} {row['large_scale_clean_rms']:8.5f}")
    first = rows[0]
    interior = float(np.median(noise_moved[10:-10]))
    first.update({"noise_moved_first": [float(x) for x in noise_moved[:10]],
                  "noise_moved_last": [float(x) for x in noise_moved[-10:]], "noise_moved_interior_median": interior,
                  "first_frame_ratio_at_interior_noise": float(np.hypot(ref_clean[0], interior) / ref_clean[0])})
    print("default, per-frame ratio (noisy / clean), first 10 frames: "
          + " ".join(f"{x:.2f}" for x in first["frame_ratios_first"]))
    print("                                           last 10 frames:  "
          + " ".join(f"{x:.2f}" for x in first["frame_ratios_last"]))
    print("what the noise moves (cm, noisy vs clean replay), first 3: " + " ".join(f"{x:.4f}" for x in noise_moved[:3])
          + "  last 3: " + " ".join(f"{x:.4f}" for x in noise_moved[-3:]) + f"  interior median {interior:.4f}; "
          f"frame 0 moved only that much would be {first['first_frame_ratio_at_interior_noise']:.2f}x its clean error")
    from facepipe.mocap.prepare import prepare_take

    clean_head = prepare_take(clean, model)[0]
    if args.draws:
        first["draws"] = noise_draws(noisy, model, truth, ev, ref_clean, rows[0]["noise_sigma"], args.draws, data,
                                     clean_head)
    if args.smoother_grid:
        first["smoother_grid"] = smoother_grid_bound(noisy, model, truth, data, ev.evaluate(clean_head), ref_clean,
                                                     rows[0]["noise_sigma"], args.smoother_grid)
    bound = single_frame_pose_bound(noisy, model, truth, data)
    first["single_frame_pose_bound_first"] = [float(x) for x in bound[:10]]
    first["single_frame_pose_bound_ratio_first"] = [float(x) for x in np.sqrt(bound**2 + ref_clean**2)[:10] / ref_clean[:10]]
    print("single-frame pose bound (cm, true expression, best rigid fit to the noisy markers), first 10: "
          + " ".join(f"{x:.4f}" for x in bound[:10]))
    print("  clean error with that pose error added (ratio to clean), first 10 frames:           "
          + " ".join(f"{x:.2f}" for x in first["single_frame_pose_bound_ratio_first"]))
    placed = smoothed_pose_bound(noisy, model, truth, data, ev, clean_head)
    first["smoothed_pose_bound_ratio_first"] = [float(x) for x in (placed / ref_clean)[:10]]
    first["smoothed_pose_bound_ratio_last"] = [float(x) for x in (placed / ref_clean)[-10:]]
    first["smoothed_pose_bound_worst_ratio"] = float((placed / ref_clean).max())
    print("the clean replay placed by the smoothed pose of the true expression's rigid fits (ratio to clean), "
          "first 10: " + " ".join(f"{x:.2f}" for x in first["smoothed_pose_bound_ratio_first"]))
    old = legacy_errors(noisy, model, truth, ev)
    old_clean = legacy_errors(clean, model, truth, ev)
    rows.append({"variant": "before #4 (stable Kabsch + PCHIP)", "noisy_rms": float(old.mean()),
                 "clean_rms": float(old_clean.mean()), "ratio": float(old.mean() / old_clean.mean()),
                 "worst_frame_ratio": float((old / old_clean).max()),
                 "ratio_vs_default_clean": float(old.mean() / ref_clean.mean()),
                 "worst_vs_default_clean": float((old / ref_clean).max())})
    r = rows[-1]
    print(f"{r['variant']:30s} {r['noisy_rms']:8.5f} {r['clean_rms']:8.5f} {r['ratio']:6.3f} "
          f"{r['worst_frame_ratio']:6.2f} {r['ratio_vs_default_clean']:7.3f} {r['worst_vs_default_clean']:6.2f}")
    print("ratio / worst: noisy vs the clean take through the same variant; vs ref: against the clean take "
          "through the default pipeline; large n / c: the shell alone (no details), noisy / clean take. "
          "Units: cm, face area 0:9409.")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
