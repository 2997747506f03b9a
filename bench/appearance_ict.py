"""Appearance classification on rendered footage of the ICT kit: Spearman correlation of Q with
the truth activation per region, frontal and with the head turned (up to 15°) under another light,
the reconstructed texture's RMS difference to the frames' own texels against the neutral
texture's, the Q stream's bit rate, and classification speed. Writes bench/appearance_ict.json
(or --json). Run from the repository root:

    python bench/appearance_ict.py [--out /tmp/ict_appearance] [--take train|video] [--reuse]

--take: the performance rendered: the kit's train_truth.npz or video/video_truth.npz geometry and
weights (most frames there have a region's activation exactly 0: tied ranks), or ``sweep``, a take
built from the kit's expressions in which every region's drivers sweep smoothly between 0.05 and
0.95 at their own rate and phase (no ties, every region moving at once); --reuse: classify
footage already rendered in --out; --identity face_a|face_b: the same on one of the kit's other
faces (identities/, same topology): its expressions and the take's frames are the kit's
displacements from the neutral added to that face, as the kit's README defines their truth (the
take's head motion kept), so the region layout, templates and eye openings are found afresh;
--two-sided-light: render lit as the footage before 2026-12 was (Lambert's cosine taken in absolute
value: a surface facing away from the light lit as if it faced it), to reproduce earlier figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import pearsonr, spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's facepipe, however it is run

from facepipe.appearance_sample import write_appearance_kit
from facepipe.core.appearance import SHADING_ORDERS, SHADING_TILT
from facepipe.core.layered_texture import light_bits, stream_bits
from facepipe.core.hole_cards import boundary_loops
from facepipe.io.appearance_file import STREAM_DECIMALS
from facepipe.io.camera_file import read_camera
from facepipe.io.config import load_config
from facepipe.io.footage import open_footage, read_frames, to_gray
from facepipe.io.mesh_read import load_mesh, load_vertices
from facepipe.pipeline.appearance import _read_geometry, classify_decoded, classify_frames, off_face_frames, region_bank
from facepipe.pipeline.appearance_build import build_appearance
from facepipe.pipeline.appearance_points import texel_map
from facepipe.pipeline.appearance_texture import texture_differences

KIT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ict"
TAKES = {"train": KIT / "train_truth.npz", "video": KIT / "video" / "video_truth.npz", "sweep": None}
DRIVERS = {"forehead": ["browInnerUp_L", "browInnerUp_R"], "brow_L": ["browDown_L"], "brow_R": ["browDown_R"],
           "eyelid_L": ["eyeBlink_L"], "eyelid_R": ["eyeBlink_R"], "nasolabial_L": ["mouthSmile_L"],
           "nasolabial_R": ["mouthSmile_R"], "mouth": ["mouthPucker"],
           "eyeball_L": ["eyeLookIn_L"], "eyeball_R": ["eyeLookOut_R"]}
# the eyeballs drawn behind the eye openings turn with the gaze expressions: (region, yaw, pitch)
# in degrees at full weight (yaw to the subject's left, pitch down; both of the kit's sideways
# looks turn to the subject's right)
GAZE = {"eyeLookIn_L": ("eyeball_L", -25.0, 0.0), "eyeLookOut_R": ("eyeball_R", -25.0, 0.0),
        "eyeLookUp_L": ("eyeball_L", 0.0, -20.0), "eyeLookUp_R": ("eyeball_R", 0.0, -20.0)}
EYE_OPENINGS = {"eyeball_L": "eyeBlink_L", "eyeball_R": "eyeBlink_R"}


def eye_rims(rest: np.ndarray, faces: np.ndarray, expressions: dict) -> dict:
    """Each eyeball region's eye opening: the mesh's hole whose rim its eye's blink moves most."""
    loops = boundary_loops(faces)
    return {region: max(loops, key=lambda loop: float(np.linalg.norm(expressions[blink][loop] - rest[loop],
                                                                     axis=1).mean()))
            for region, blink in EYE_OPENINGS.items()}


def sweep_take(rest: np.ndarray, expressions: dict, frames: int = 120) -> tuple[np.ndarray, np.ndarray, list]:
    """Positions (T, V, 3) and weights (T, K) of a take in which each region's drivers sweep
    between 0.05 and 0.95 (raised cosines of different periods and phases), other expressions 0."""
    names = sorted(expressions)
    t = np.arange(frames) / frames
    weights = np.zeros((frames, len(names)))
    for r, drivers in enumerate(DRIVERS.values()):
        sweep = 0.05 + 0.9 * 0.5 * (1 - np.cos(2 * np.pi * ((1.0 + 0.37 * r) * t + 0.13 * r)))
        for d in drivers:
            weights[:, names.index(d)] = sweep
    deltas = np.stack([expressions[n] - rest for n in names])
    return rest + np.tensordot(weights, deltas, axes=1), weights, names


def identity_geometry(face: np.ndarray, neutral: np.ndarray, expressions: dict, world: np.ndarray,
                      truth) -> tuple[dict, np.ndarray]:
    """Another face's expressions and take: the kit's displacements from its neutral added to
    ``face`` (V, 3) (an ICT expression's displacement does not depend on the identity); the take's
    head motion (``rotation``/``translation`` in ``truth``, world = head · Rᵀ + t) is taken out
    first and put back after."""
    moved = {n: face + (e - neutral) for n, e in expressions.items()}
    if "rotation" in truth and "translation" in truth:
        R, t = np.asarray(truth["rotation"]), np.asarray(truth["translation"])
        head = np.einsum("tvi,tij->tvj", world - t[:, None, :], R)
        return moved, np.einsum("tvj,tij->tvi", face + (head - neutral), R) + t[:, None, :]
    return moved, face + (world - neutral)


def q_errors(q: np.ndarray, act: np.ndarray, names: list, layer_counts) -> dict:
    """RMS of Q − the truth's layer index (activation 0 … 1 over the layers), per region and in all,
    in layers, over the frames where the region is seen: how far the stream is off, which no tie
    among the truth's zeros caps (the rank correlation's limit on these takes)."""
    truth = act * (np.asarray(layer_counts, dtype=np.float64) - 1.0)
    err = np.where(np.isfinite(q), q - truth, np.nan)
    per = np.sqrt(np.nanmean(err ** 2, axis=0))
    return {"q_rms_error_layers": dict(zip(names, per.tolist())), "q_rms_error_layers_mean": float(per.mean())}


def correlations(q: np.ndarray, act: np.ndarray, names: list) -> dict:
    def safe(f, a, b):
        return float(f(a, b).statistic) if np.ptp(a) > 0 and np.ptp(b) > 0 else float("nan")

    # most frames of a take have a region's activation exactly 0 (tied ranks): the Spearman
    # correlation an estimator reaches that is exact but for 1 % noise shows what ties cost
    rng = np.random.default_rng(0)
    # over the frames where the region is active (truth > 0) there are no ties: what the ranking
    # of the active frames is worth, reported beside the all-frames figure, not instead of it
    active = act > 0
    return {"spearman": {n: safe(spearmanr, q[:, r], act[:, r]) for r, n in enumerate(names)},
            "pearson": {n: safe(pearsonr, q[:, r], act[:, r]) for r, n in enumerate(names)},
            "spearman_active_frames": {n: safe(spearmanr, q[active[:, r], r], act[active[:, r], r])
                                       for r, n in enumerate(names)},
            "active_frames": {n: int(active[:, r].sum()) for r, n in enumerate(names)},
            "spearman_of_truth_with_1pct_noise": {n: safe(spearmanr, act[:, r] + 0.01 * rng.normal(size=len(act)),
                                                          act[:, r]) for r, n in enumerate(names)},
            "zero_activation_fraction": {n: float((act[:, r] <= 0).mean()) for r, n in enumerate(names)}}


#: An eye card is read over the frames where its lid is this far closed at most (its eyelid
#: region's activation, the blink): beyond it the lid covers much of the card.
LID_OPEN = 0.3


def open_lid_correlations(q: np.ndarray, act: np.ndarray, names: list) -> dict:
    """Spearman and Pearson of each eyeball region's Q with its truth over the frames where its
    eye's lid is open (its eyelid region's activation under :data:`LID_OPEN`), and how many: a
    closing lid covers the card and the region holds its last reading, which the all-frames
    figures of a take that blinks through its gazes (the sweep) are mostly made of."""
    out = {}
    for r, name in enumerate(names):
        lid = name.replace("eyeball", "eyelid")
        if name.startswith("eyeball") and lid in names:
            open_ = act[:, names.index(lid)] < LID_OPEN
            a, x = act[open_, r], q[open_, r]
            ok = open_.sum() > 2 and np.ptp(a) > 0 and np.ptp(x) > 0
            out[name] = {"frames": int(open_.sum()), "spearman": float(spearmanr(x, a).statistic) if ok else float("nan"),
                         "pearson": float(pearsonr(x, a).statistic) if ok else float("nan")}
    return {"eyeballs_lid_open": out}


def footage_check(c, model) -> dict:
    """The classification's footage check (:func:`off_face_frames`): each frame's light residual
    over the example footage's, its median and largest, and the frames it calls off the face."""
    check = off_face_frames(c, model)
    ratio = c.light_residual / check["examples"]
    return {"ratio_median": check["ratio"], "ratio_max": float(np.nanmax(ratio)), "ratio_limit": check["limit"],
            "frames_off_face": int(check["off_face"].sum()), "frames": len(ratio)}


def _check_words(check: dict) -> str:
    return (f"light residual {check['ratio_median']:.1f}x the examples' (largest {check['ratio_max']:.1f}x), "
            f"{check['frames_off_face']} of {check['frames']} frames off the face")


def throughput(model, out: Path, take: str, positions: np.ndarray, numbers: np.ndarray) -> dict:
    """Frames/s of the classification alone (all regions of a frame: sampling, the frame's light,
    Haar, match) on frames already decoded, in chunks of 8 frames on facepipe's threads as
    ``classify_frames`` runs it:
    per second of wall time and per second of this process's CPU time (on a machine shared with
    other work the wall time measures the share of the cores the process got)."""
    footage = open_footage(out / take / "frame_%04d.png")
    grays = np.stack([to_gray(image) for _, image, _ in read_frames(footage, numbers)])
    cam = np.stack([model.to_camera(p) for p in positions])
    bank = region_bank(model)
    out = {}
    # the model as built, then without the edge-on points' test, then without the occlusion test too
    variants = {"": {}, "_without_edge_on_test": {"min_point_facing": 0.0},
                "_without_visibility_tests": {"min_point_facing": 0.0, "occlusion": False}}
    def best_of_three(m, b):
        wall, cpu = np.inf, np.inf
        for _ in range(3):  # the best of three passes: the machine is shared
            t0, c0 = time.perf_counter(), time.process_time()
            classify_decoded(grays, cam, m, b)
            wall, cpu = min(wall, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
        return len(grays) / wall, len(grays) / cpu

    for suffix, change in variants.items():
        out[f"classification_frames_per_second{suffix}"], out[f"classification_frames_per_cpu_second{suffix}"] = \
            best_of_three(dataclasses.replace(model, **change), bank)
    if len(model.names) > 8:  # eight regions: the skin's, without the eyeballs' cards
        eight = first_regions(model, 8)
        out["classification_frames_per_second_eight_regions"], \
            out["classification_frames_per_cpu_second_eight_regions"] = best_of_three(eight, region_bank(eight))
    return out


def first_regions(model, n: int):
    """The model with its first n regions only (every per-region array cut to them)."""
    per_region = {k: getattr(model, k)[:n] for k in ("names", "template_face", "template_bary", "templates",
                                                      "indices", "volumes", "alphas", "boxes")}
    for k in ("template_facing", "template_mask", "rest_floor", "shading_orders", "rest_nuisance", "template_patches",
              "card_motion"):
        if getattr(model, k) is not None:
            per_region[k] = getattr(model, k)[:n]
    for k in ("rest_readings", "rest_off_path"):
        if getattr(model, k) is not None:
            per_region[k] = getattr(model, k)[:, :n]
    return dataclasses.replace(model, **per_region)


def texture_ratio(model, mesh, out: Path, take: str, positions: np.ndarray, numbers: np.ndarray, q: np.ndarray,
                  q_truth: np.ndarray, light) -> dict:
    """RMS of (layered texture at Q − the frame's texels) over that of (neutral − the frame's
    texels), on the regions' texels, over the take; in all and per region; with the classified Q
    and with the truth activation as Q (what the layered texture itself reaches). The
    reconstruction is the frame's texture as facepipe exports it: the layered albedo shaded by the
    frame's geometry under the light classification fitted to the frame (``light``: (T, 9), or None
    for a model that holds the footage's values). Also each region's RMS difference itself
    (``texture_rms_per_region``, intensities 0–1, at the classified Q): under another light than
    the examples' the neutral texture is off everywhere and the ratio flatters every region."""
    texel_face, texel_bary = texel_map(model.corner_uv, model.neutral.shape[0], model.tile)  # the cards' squares too
    sums = np.zeros((2, len(model.names), 3))
    active = np.zeros((2, len(model.names), 3))  # each region's sums over the frames it is active in
    footage = open_footage(out / take / "frame_%04d.png")
    for i, (_, image, _) in enumerate(read_frames(footage, numbers)):
        cam = model.to_camera(positions[i])
        for k, qq in enumerate((q[i], q_truth[i])):
            d = texture_differences(model, texel_face, texel_bary, image, cam, qq, None if light is None else light[i])
            sums[k] += d
            active[k] += d * (q_truth[i] > 0)[:, None]
    # in a frame where a region is neutral the layered texture at Q = 0 is the neutral texture:
    # both differences are the same (noise, other expressions' shading) and pull the ratio to 1
    # however well the active frames are rebuilt; over the active frames alone that is out
    return {"texture_rms_ratio_active_frames": float(np.sqrt(active[0, :, 0].sum() / active[0, :, 1].sum())),
            "texture_rms_ratio_active_frames_at_truth_q": float(np.sqrt(active[1, :, 0].sum()
                                                                        / active[1, :, 1].sum())),
            "texture_rms_ratio_active_frames_per_region": dict(zip(model.names, np.sqrt(
                active[0, :, 0] / np.maximum(active[0, :, 1], 1e-300)).tolist())),
            "texture_rms_ratio": float(np.sqrt(sums[0, :, 0].sum() / sums[0, :, 1].sum())),
            "texture_rms_ratio_at_truth_q": float(np.sqrt(sums[1, :, 0].sum() / sums[1, :, 1].sum())),
            "texture_rms_ratio_per_region": dict(zip(model.names, np.sqrt(sums[0, :, 0] / sums[0, :, 1]).tolist())),
            "texture_rms_per_region": dict(zip(model.names, np.sqrt(sums[0, :, 0] / np.maximum(sums[0, :, 2], 1)).tolist())),
            "texture_rms_ratio_at_truth_q_per_region": dict(zip(model.names,
                                                                np.sqrt(sums[1, :, 0] / sums[1, :, 1]).tolist()))}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="/tmp/ict_appearance")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--take", choices=list(TAKES), default="train")
    ap.add_argument("--reuse", action="store_true", help="classify footage already rendered in --out")
    ap.add_argument("--identity", choices=["face_a", "face_b"], default=None,
                    help="render and classify one of the kit's other faces (identities/)")
    ap.add_argument("--json", default="bench/appearance_ict.json")
    ap.add_argument("--two-sided-light", action="store_true",
                    help="render as the footage before 2026-12 was: |cos| Lambert, lit from both sides")
    args = ap.parse_args()
    if args.reuse and args.two_sided_light:
        ap.error("--two-sided-light sets how footage is rendered; --reuse classifies footage already rendered")
    out = Path(args.out)
    neutral = load_mesh(KIT / "neutral.obj")
    mesh_path = KIT / "identities" / f"{args.identity}.obj" if args.identity else KIT / "neutral.obj"
    mesh = load_mesh(mesh_path)
    render_s = None
    if not (args.reuse and (out / "appearance.toml").is_file()):
        if args.take == "sweep":
            needed = {d for ds in DRIVERS.values() for d in ds} | set(EYE_OPENINGS.values())
            expressions = {d: load_vertices(KIT / "expressions" / f"{d}.obj") for d in needed}
            # on the kit's neutral: identity_geometry moves them onto another face as any take
            world, weights, names = sweep_take(neutral.vertices, expressions)
        else:
            truth = np.load(TAKES[args.take])
            names = [str(n) for n in truth["expressions"]]
            expressions = {n: load_vertices(KIT / "expressions" / f"{n}.obj") for n in names}
            world, weights = truth["positions"], truth["weights"]
        if args.identity:
            expressions, world = identity_geometry(mesh.vertices, neutral.vertices, expressions, world,
                                                   {} if args.take == "sweep" else truth)
        t0 = time.perf_counter()
        write_appearance_kit(out, mesh, mesh.vertices, expressions, DRIVERS, world, weights,
                             names, mesh_path=str(mesh_path), markers_path=str(KIT / "markers.csv"),
                             size=args.size, texture_size=1024,
                             eyes=eye_rims(mesh.vertices, mesh.faces, expressions), gaze=GAZE,
                             two_sided_light=args.two_sided_light)
        render_s = time.perf_counter() - t0
    config = load_config(out / "appearance.toml")
    model, info = build_appearance(config, mesh, read_camera(config.appearance.camera))
    q_bits = int(stream_bits(model.layer_counts, 10.0 ** -STREAM_DECIMALS).sum())
    bits = q_bits + (light_bits(10.0 ** -STREAM_DECIMALS, model.stream_terms + 3) if model.light_face is not None else 0)
    result = {"take": args.take, "identity": args.identity or "neutral", "render_seconds": render_s, "regions": model.names, "shading": model.shading,
              "albedo_layers": model.albedo,
              "rest_floor": None if model.rest_floor is None else dict(zip(model.names, model.rest_floor.tolist())),
              "shading_surface": dict(zip(model.names, [SHADING_ORDERS.get(int(o), str(o)) for o in model.shading_orders]))
              if model.shading_orders is not None else None,
              "shading_reference": model.shading_reference,
              "stream_bits_per_frame": bits, "q_bits_per_frame": q_bits, "light_bits_per_frame": bits - q_bits,
              "stream_kbit_s_at_30hz": bits * 30 / 1000.0,
              # the neutral templates under a ±15 % shading ramp (0 is ideal: the build's own figure)
              "shading_tilt_q": info.get("shading_tilt_q")}
    if result["shading_tilt_q"]:
        print(f"a ±{SHADING_TILT:.0%} shading tilt over a neutral template reads Q",
              " ".join(f"{n} {v:.2f}" for n, v in result["shading_tilt_q"].items()))
    for take in ("take", "take_turned"):
        positions, numbers = _read_geometry(out / f"{take}.npz", mesh.n_vertices)
        t0 = time.perf_counter()
        c = classify_frames(model, out / take / "frame_%04d.png", positions, numbers, numbers / 30.0)
        seconds = time.perf_counter() - t0
        act = np.loadtxt(out / f"{take}_truth.csv", delimiter=",", skiprows=1, ndmin=2)[:, 1:]
        q = np.round(c.q, STREAM_DECIMALS)  # the stream as written
        result[take] = {**correlations(q, act, model.names), **q_errors(q, act, model.names, model.layer_counts),
                        **open_lid_correlations(q, act, model.names),
                        "frames_per_second_with_reading": len(numbers) / seconds,
                        "visible_fraction": float(c.visible.mean()), "footage_check": footage_check(c, model)}
        if take == "take":
            result[take].update(throughput(model, out, take, positions, numbers))
        q_truth = act * (np.asarray(model.layer_counts) - 1)  # the examples: activation 0 … 1 over the layers
        result[take].update(texture_ratio(model, mesh, out, take, positions, numbers, q, q_truth, c.light))
        r = result[take]
        print(take, "spearman", " ".join(f"{n} {v:.3f}" for n, v in r["spearman"].items()))
        print(take, "pearson ", " ".join(f"{n} {v:.3f}" for n, v in r["pearson"].items()))
        print(take, "active  ", " ".join(f"{n} {v:.3f}" for n, v in r["spearman_active_frames"].items()))
        print(take, "ceiling ", " ".join(f"{n} {v:.3f}" for n, v in r["spearman_of_truth_with_1pct_noise"].items()))
        print(take, "Q error ", " ".join(f"{n} {v:.3f}" for n, v in r["q_rms_error_layers"].items()),
              f"(mean {r['q_rms_error_layers_mean']:.3f} layers)")
        if r["eyeballs_lid_open"]:
            print(take, "lid open", " ".join(f"{n} {v['spearman']:.3f} ({v['frames']} frames)"
                                             for n, v in r["eyeballs_lid_open"].items()))
        print(take, "texture RMS", " ".join(f"{n} {v:.3f}" for n, v in r["texture_rms_per_region"].items()),
              f"(ratio to the neutral texture's {r['texture_rms_ratio']:.3f})")
        print(take, f"{r['frames_per_second_with_reading']:.1f} frames/s with reading",
              f"visible {r['visible_fraction']:.3f}", _check_words(r["footage_check"]))
    # the head-turned footage with the frontal take's geometry: what the footage check says of a wrong take
    positions, numbers = _read_geometry(out / "take.npz", mesh.n_vertices)
    wrong = classify_frames(model, out / "take_turned" / "frame_%04d.png", positions, numbers, numbers / 30.0)
    result["footage_check_wrong_geometry"] = footage_check(wrong, model)
    print("turned footage, frontal geometry:", _check_words(result["footage_check_wrong_geometry"]))
    eight = result["take"].get("classification_frames_per_second_eight_regions")
    if eight is not None:
        print(f"classification of the first eight regions alone {eight:.0f} frames/s")
    print(f"classification alone {result['take']['classification_frames_per_second']:.0f} frames/s, "
          f"{result['take']['classification_frames_per_cpu_second']:.0f} frames per CPU second ({len(model.names)} regions; "
          f"{result['take']['classification_frames_per_cpu_second_without_edge_on_test']:.0f} without the edge-on "
          f"test, {result['take']['classification_frames_per_cpu_second_without_visibility_tests']:.0f} without "
          f"either visibility test); "
          f"texture RMS ratio {result['take']['texture_rms_ratio']:.3f} (at the truth Q "
          f"{result['take']['texture_rms_ratio_at_truth_q']:.3f}), over the active frames "
          f"{result['take']['texture_rms_ratio_active_frames']:.3f} (at the truth Q "
          f"{result['take']['texture_rms_ratio_active_frames_at_truth_q']:.3f}); stream {result['stream_kbit_s_at_30hz']:.2f} "
          f"kbit/s at 30 Hz")
    Path(args.json).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
