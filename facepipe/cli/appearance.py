"""The bodies of ``facepipe appearance build`` / ``classify`` and of ``facepipe sample --appearance``."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from facepipe.core.runs import column_runs
from facepipe.errors import InputError

__all__ = ["build_command", "check_sample_appearance", "classify_command", "sample_appearance", "SAMPLE_DRIVERS"]

#: Regions of the sample rig and the expressions whose mean weight is each one's truth activation.
SAMPLE_DRIVERS = {"forehead": ["browRaise"], "brows": ["frown"], "mouth": ["pucker"], "nasolabial_L": ["smile_L"],
                  "nasolabial_R": ["smile_R"], "eyelid_L": ["squint_L"], "eyelid_R": ["squint_R"], "chin": ["jawOpen"]}


def build_command(config_path, output, rep, write_json) -> dict:
    from facepipe.io.appearance_file import save_appearance
    from facepipe.io.camera_file import read_camera
    from facepipe.io.config import load_config
    from facepipe.io.mesh_read import load_mesh
    from facepipe.pipeline.appearance_build import build_appearance

    config = load_config(config_path)
    if config.appearance is None:
        raise InputError("the config has no [appearance] table", path=config_path,
                         hint="add [appearance] with camera, footage, geometry and [appearance.regions.NAME] tables")
    mesh = load_mesh(config.mesh)
    camera = read_camera(config.appearance.camera)
    with rep.bar(len(config.appearance.regions), unit="region", desc="regions") as bar:
        model, info = build_appearance(config, mesh, camera, progress=bar.update)
    save_appearance(output, model)
    if model.card_rest is not None:  # the cards at rest with their UVs, for the user's scene (parented to the head)
        info["cards_obj"] = str(write_cards_obj(Path(output).with_name(Path(output).stem + "_cards.obj"), model))
    report = Path(output).with_suffix(".json")
    write_json(report, info)
    rep.say(f"{len(info['regions'])} regions ({', '.join(f'{n} {k}' for n, k in zip(info['regions'], info['layers']))}"
            f" layers), texture {info['texture_size']}²"
            + (f" on UDIM tile{'s' if len(info['tiles']) > 1 else ''} {', '.join(map(str, info['tiles']))}"
               if info["tiles"] != [1001] else "")
            + f"; wrote {output} and {report}")
    if info.get("albedo"):
        rep.say("layers hold albedo (each example frame's shading divided out): a frame's texture is shaded by its "
                "own geometry under the light classification fits to it")
    for name, card in info.get("cards", {}).items():
        u0, v0, u1, v1 = card["uv_square"]
        rep.say(f"card {name}: across a hole of {card['rim_vertices']} rim vertices, textured in UV "
                f"[{u0:.4f}, {v0:.4f}, {u1:.4f}, {v1:.4f}], carried by {card['carried_by_vertices']} vertices, "
                f"set back {card['depth']:.3f} × its width ({'fitted' if card['depth_fitted'] else 'not fitted'})")
    if "cards_obj" in info:
        rep.say(f"the cards at rest, with their UVs: {info['cards_obj']}")
    if info.get("rest"):
        rep.say("rest floors (the highest Q read at rest in the examples): " + ", ".join(
            f"{n} {v['floor']:.2f}" + (f" (frames {', '.join(map(str, v['explained']))} explained away)"
                                       if v.get("explained") else "") for n, v in info["rest"].items()))
        if info.get("rest_path_tolerance"):
            rep.say("each reading is measured from the at-rest readings that lie as far off the region's layers "
                    f"for their Q (within × {info['rest_path_tolerance']:g}), not from the highest")
    if info.get("shading"):
        fitted = {"neutral": "fitted against each region's neutral layer, ", "patch": "fitted through each patch, "}
        rep.say(f"shading surfaces ({fitted.get(info.get('shading_reference'), '')}"
                "share of the layers' contrast a quadratic keeps): " + ", ".join(
            f"{n} {v['surface']}" + ("" if v["contrast_kept"] is None else f" ({v['contrast_kept']:.2f})")
            for n, v in info["shading"].items()))
    if info.get("light"):
        rep.say(f"each frame's light fitted as {_light_words(info['light'])}")
    if info.get("peak_interpolation"):
        rep.say(f"Q read from the match distances by {info['peak_interpolation']} interpolation")
    for note in info["notes"]:
        rep.say(f"note: {note}")
    return info


def _light_words(light: dict) -> str:
    """The build's light model, and the example footage's light under it, in words."""
    if light["model"] != "point":
        return "nine spherical-harmonic terms"
    ambient, *lights = light["examples"]
    said = []
    for name, direction in zip(("key", "fill"), np.reshape(lights, (-1, 3))):
        strength = float(np.linalg.norm(direction))
        if strength > 0.0:
            x, y, z = direction / strength
            said.append(f"{name} {strength:.2f} from ({x:+.2f}, {y:+.2f}, {z:+.2f})")
    return (f"an ambient term and a key and a fill light (the examples': ambient {ambient:.2f}, "
            + ", ".join(said) + "; directions towards the lights, camera axes)")


def write_cards_obj(path: Path, model) -> Path:
    """The model's cards at rest (their own vertices, triangles and UVs) as an OBJ, atomically:
    the layered textures' card squares map onto it; it moves rigidly with the head."""
    from facepipe.core.hole_cards import card_triangles
    from facepipe.core.mesh import Mesh
    from facepipe.io.mesh_write import save_obj

    V = model.n_vertices
    on_card = card_triangles(model.faces, V)
    faces = model.faces[on_card] - V
    corner_uv = np.asarray(model.corner_uv[on_card], dtype=np.float64).reshape(-1, 2)
    mesh = Mesh(np.asarray(model.card_rest, dtype=np.float64), np.arange(len(faces) + 1, dtype=np.int64) * 3,
                faces.ravel().astype(np.int64), corner_uv, np.arange(len(corner_uv), dtype=np.int64))
    save_obj(path, mesh)
    return path


def classify_command(model_path, footage, geometry_path, output, fps, rep):
    from facepipe.core.layered_texture import light_bits, stream_bits
    from facepipe.io.appearance_file import STREAM_DECIMALS, load_appearance, write_stream
    from facepipe.io.footage import frames_at, open_footage
    from facepipe.pipeline.appearance import classify_frames, off_face_frames, take_geometry

    model = load_appearance(model_path)
    geometry, model, note = take_geometry(geometry_path, model)
    if note:
        rep.say(f"note: {note}")
    numbers, times = geometry.numbers, geometry.times
    if times is None:
        times = numbers / fps
    elif len(times) > 1 and np.median(np.diff(times)) > 0:
        fps = float(1.0 / np.median(np.diff(times)))  # the take's own rate (for the stream's bit rate)
    start = time.perf_counter()
    opened = open_footage(footage)  # its errors before the progress bar opens
    at, matched = frames_at(opened, numbers, geometry.times)
    if matched:
        rep.say(f"note: {matched}")
    with rep.bar(len(numbers), desc="classify") as bar:
        result = classify_frames(model, opened, geometry.positions, numbers, times, progress=bar.update,
                                 footage_numbers=at)
    seconds = time.perf_counter() - start
    q_bits = int(stream_bits(model.layer_counts, 10.0 ** -STREAM_DECIMALS).sum())
    bits = q_bits + (light_bits(10.0 ** -STREAM_DECIMALS, result.light.shape[1]) if result.light is not None else 0)
    figures = {"seconds": seconds, "frames_per_second": len(numbers) / max(seconds, 1e-9), "fps": fps,
               "stream_bits_per_frame": bits, "q_bits_per_frame": q_bits, "light_bits_per_frame": bits - q_bits,
               "stream_kbit_s": bits * fps / 1000.0,
               # the light divided out of the patches, and the one light.csv carries
               "light_model": model.light_model if model.light_face is not None else None,
               "stream_light": model.stream_light if model.light_face is not None else None}
    for n, problem in result.problems:
        rep.say(f"frame {n}: {problem}; skipped (held, decaying to neutral)")
    never = [name for r, name in enumerate(model.names) if not result.visible[:, r].any()]
    if never:
        rep.say(f"note: never visible, kept neutral: {', '.join(never)}")
    hidden = hidden_spans(model.names, result.visible, numbers, [n for n, _ in result.problems])
    figures["hidden_frames"] = {name: count for name, (count, _) in hidden.items()}
    some = [f"{name} {count} (frames {text})" for name, (count, text) in hidden.items() if name not in never and count]
    if some:
        rep.say("note: hidden in some frames (facing away, edge-on, behind the face or out of view; Q holds its "
                "last value there, decaying to neutral): " + "; ".join(some))
    if result.brief is not None:
        figures["brief_readings_at_rest"] = {name: int(n) for name, n in zip(model.names, result.brief.sum(axis=0))}
        some = [f"{name} {n}" for name, n in figures["brief_readings_at_rest"].items() if n]
        if some:
            rep.say(f"note: readings that left rest for under {model.min_event:g} s, under a layer, set back to rest "
                    f"(image noise; [appearance] min_event = 0 keeps them): " + ", ".join(some))
    check = off_face_frames(result, model)
    if check is not None:
        off = check["off_face"]
        figures["footage_check"] = {
            "light_residual_examples": check["examples"], "light_residual_median": _json_number(check["median"]),
            "ratio_median": _json_number(check["ratio"]), "ratio_limit": check["limit"],
            "frames_off_face": int(off.sum()),
            "light_residual": [_json_number(round(float(x), 5)) for x in result.light_residual]}
        if off.any():
            spans = hidden_spans(["off"], ~off[:, None], numbers)["off"][1]
            rep.say(f"warning: {int(off.sum())} of {len(numbers)} frames (frames {spans}) do not match the geometry: "
                    f"their light leaves over {check['limit']:g}× as much of the face's brightness unexplained as "
                    f"the example footage's (take median {100 * check['median']:.1f} %, examples "
                    f"{100 * check['examples']:.1f} %). The geometry misses the face in the image there and Q read "
                    "there is not to be trusted: check that --geometry is this footage's take (its head pose and "
                    "frame numbers) and that the footage is from the camera the model was built with")
        elif np.isfinite(check["ratio"]):  # (a take with no frame read has nothing to check)
            rep.say(f"footage check: the geometry lies on the face in every frame read (the light leaves "
                    f"{check['ratio']:.1f}× the example footage's share of the face's brightness unexplained; "
                    f"over {check['limit']:g}× would name the frame)")
    elif model.light_face is not None:
        rep.detail("note: the model predates the footage check (rebuild it to check the geometry against the footage)")
    path = write_stream(output, model_path, result, model.layer_counts, footage=_absolute_footage(footage),
                        geometry=geometry_path, figures=figures)
    light = f" + light {bits - q_bits}" if bits > q_bits else ""
    rep.say(f"{len(numbers)} frames, {len(model.names)} regions in {seconds:.1f} s "
            f"({figures['frames_per_second']:.0f} frames/s, reading included); stream (Q {q_bits}{light}) {bits} bits "
            f"a frame = {figures['stream_kbit_s']:.2f} kbit/s at {fps:.4g} Hz; wrote {path}")
    return result


def _json_number(x: float) -> float | None:
    """x, or None where it is not finite (JSON has no NaN: a frame not read has no residual)."""
    return float(x) if np.isfinite(x) else None


def hidden_spans(names, visible: np.ndarray, numbers: np.ndarray, skipped=(), most: int = 3) -> dict:
    """Per region the count of frames (T,) it was hidden in, frames skipped as unreadable left out
    (they are reported as such), and those frames as text: its first ``most`` spans of frame
    numbers ("72–105, 110")."""
    hidden = ~np.asarray(visible, dtype=bool) & ~np.isin(numbers, list(skipped))[:, None]
    column, start, stop = column_runs(hidden)
    out = {}
    for r, name in enumerate(names):
        spans = [(int(numbers[a]), int(numbers[b - 1])) for a, b in zip(start[column == r], stop[column == r])]
        text = ", ".join(str(a) if a == b else f"{a}–{b}" for a, b in spans[:most]) + (" …" if len(spans) > most else "")
        out[name] = (int(hidden[:, r].sum()), text)
    return out


def _absolute_footage(footage) -> str:
    """The footage's path (a folder, a video, or a ``frame_%04d.png`` pattern) made absolute."""
    return str(Path(footage).parent.resolve() / Path(footage).name)


def check_sample_appearance(examples: int) -> None:
    """Refuse, before anything is written, a sample whose examples lack a region's drivers."""
    from facepipe.sample_rig import EXPRESSIONS

    missing = sorted({d for ds in SAMPLE_DRIVERS.values() for d in ds} - set(EXPRESSIONS[:examples]))
    if missing:
        needed = max(EXPRESSIONS.index(d) for d in missing) + 1
        raise InputError(f"--appearance needs the expressions {missing}, which --examples {examples} leaves out",
                         hint=f"write the sample with --examples {needed} or more")


def sample_appearance(directory, frames: int, size: int, rep) -> dict:
    """Footage of the sample rig's take (``DIR/appearance``) with its truth and an appearance config."""
    from facepipe.appearance_sample import write_appearance_kit
    from facepipe.io.mesh_read import load_mesh
    from facepipe.sample_rig import EXPRESSIONS

    directory = Path(directory)
    mesh = load_mesh(directory / "neutral.obj")
    with np.load(directory / "take_truth.npz") as truth:
        world, weights, names = truth["positions"][:frames], truth["weights"][:frames], list(truth["expressions"])
    missing = sorted({d for ds in SAMPLE_DRIVERS.values() for d in ds} - set(names))
    if missing:
        raise InputError(f"the sample's take lacks the expressions {missing}", path=directory,
                         hint=f"write the sample with --examples {len(EXPRESSIONS[:8])} or more")
    from facepipe.io.mesh_read import load_vertices

    expressions = {n: load_vertices(directory / "expressions" / f"{n}.obj") for n in names}
    driving = {d for ds in SAMPLE_DRIVERS.values() for d in ds}
    total = 1 + 4 * len(SAMPLE_DRIVERS) + len(set(names) - driving) + 2 * len(world)
    with rep.bar(total, desc="render") as bar:
        return write_appearance_kit(directory / "appearance", mesh, mesh.vertices, expressions, SAMPLE_DRIVERS, world,
                                    weights, names, mesh_path="../neutral.obj", markers_path="../markers.csv",
                                    size=size, texture_size=512, progress=bar.update)
