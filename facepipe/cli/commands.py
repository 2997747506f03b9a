"""The facepipe command line: parse, call the library, report.

Exit status: 0 success, 2 bad input (the message names the file and the fix), 1 internal error.

Each command imports the library modules it needs when it runs, so that ``facepipe --help`` and
a mistyped option answer at once, without loading SciPy, PyOpenCL or matplotlib.
"""

from __future__ import annotations

import json
import sys
import time
import traceback
from concurrent.futures import ThreadPoolExecutor, wait
from pathlib import Path

import click
import numpy as np
from tqdm import tqdm

from facepipe.cli.interrupts import terminate_as_interrupt
from facepipe.cli.progress import refresh_seconds
from facepipe.cli.take_options import landmark_take_options, mesh_cache_options
from facepipe.errors import InputError, describe_system_error
from facepipe.export import registry as export_formats  # names the formats without importing them
from facepipe.io.atomic import atomic_path
from facepipe.io.outputs import check_output_path, prepare_replay_folder


class Reporter:
    """Printing and progress bars that honour --quiet / --verbose."""

    def __init__(self, quiet: bool = False, verbose: bool = False):
        self.quiet = quiet
        self.verbose = verbose

    def say(self, text: str = "") -> None:
        if not self.quiet:
            click.echo(text)

    def detail(self, text: str) -> None:
        if self.verbose and not self.quiet:
            click.echo(text)

    def bar(self, total: int, unit: str = "frame", desc: str = ""):

        return tqdm(total=total, unit=unit, desc=desc, disable=self.quiet, dynamic_ncols=True, file=sys.stderr,
                    mininterval=refresh_seconds())


def _common(f):
    f = click.option("--quiet", "-q", is_flag=True, help="Print nothing but errors; no progress bars.")(f)
    f = click.option("--verbose", "-v", is_flag=True, help="Print more detail.")(f)
    return f


def _reporter(ctx: click.Context, quiet: bool, verbose: bool) -> Reporter:
    parent = ctx.find_object(Reporter)
    rep = Reporter(quiet or (parent.quiet if parent else False), verbose or (parent.verbose if parent else False))
    ctx.obj = rep
    return rep


def _write_json(path: Path, data: dict) -> None:

    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, default=_json_default))


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@_common
@click.version_option(package_name="facepipe")
@click.pass_context
def cli(ctx, quiet, verbose):
    """Facial motion capture to high-resolution, wrinkled face animation.

    Typical use: facepipe fit rig.toml; facepipe bake rig.toml -o model.npz;
    facepipe replay take.csv -m model.npz -o out; facepipe export out --format obj -o frames.
    """
    ctx.obj = Reporter(quiet, verbose)


# ----------------------------------------------------------------------------- fit / bake


def _run_fit(config, rep: Reporter, tune: bool = True):
    from facepipe.cli.fitting import run_fit

    return run_fit(config, rep, tune=tune)


_TUNE_HELP = ("Choose k_stretch, the WPSD β, the RBF regularisation, the novelty gate's τ and the basis size by "
              "validation on the examples (whole expressions held out, and time blocks of a training performance "
              "([examples] sequence) where there is one; candidates in the config's [tune] table) — "
              "the default whenever the examples allow it; --no-tune fits with the config's values.")


@cli.command()
@click.argument("config", type=click.Path(dir_okay=False))
@click.option("-o", "--output", default="fit.npz", show_default=True, type=click.Path(dir_okay=False),
              help="Fit file to write; a .json report is written beside it.")
@click.option("--holdout", default=0, show_default=True,
              help="Also cross-validate: refit leaving about K examples out at a time (left/right halves of an "
                   "expression together) and report the error on them, large-scale vs final.")
@click.option("--tune/--no-tune", default=True, show_default=True, help=_TUNE_HELP + " Writes FIT.tune.json and "
              "FIT.tune.png.")
@_common
@click.pass_context
def fit(ctx, config, output, holdout, tune, quiet, verbose):
    """Extract the examples' details and select the pose basis greedily (parameters validated by default)."""
    from facepipe.cli.fitting import fit_command

    fit_command(_reporter(ctx, quiet, verbose), config, output, holdout, tune, _write_json)


@cli.command()
@click.argument("source", type=click.Path(dir_okay=False))
@click.option("-o", "--output", default="model.npz", show_default=True, type=click.Path(dir_okay=False))
@click.option("--tune/--no-tune", default=True, show_default=True,
              help=_TUNE_HELP + " Only for a CONFIG: a FIT.npz carries its own choice.")
@_common
@click.pass_context
def bake(ctx, source, output, tune, quiet, verbose):
    """Write the model replay needs (float32, one file) from a CONFIG.toml or a FIT.npz."""
    from facepipe.cli.fitting import bake_command

    bake_command(_reporter(ctx, quiet, verbose), source, output, tune)


# ----------------------------------------------------------------------------- replay


def say_replayed(rep: Reporter, result, lines=(), large_scale_from: str | None = None, head_motion: bool = True,
                 space: str = "") -> None:
    """The summary of a replay: frames, vertices, method, backend and speed (and where the large
    scale came from, for a mesh cache), then ``lines`` (the take's own report), the head's motion,
    and what was written (``space``: in which coordinates, where that needs saying)."""
    r = result.report
    source = f", large scale from the {large_scale_from}" if large_scale_from else ""
    rep.say(f"replayed {r['frames']} frames × {r['vertices']} vertices ({r['method']}{source}, {r['backend']}) "
            f"at {r['frames_per_second']:.1f} frames/s")
    for line in lines:
        rep.say(line)
    if head_motion:
        rep.say(f"head motion up to {r['head_rotation_deg_max']:.1f}° rotation, {r['head_translation_max']:.2f} "
                f"{r.get('units') or 'rig units'} translation")
    rep.say(f"wrote {result.positions_path} and {result.positions_path.parent / 'replay.json'}{space}")


def _make_evaluator(model, backend: str, device: str | None, chunk: int, rep: Reporter):
    """The replay evaluator: OpenCL when asked for, or (auto) when a device works; else NumPy."""
    from facepipe.pipeline.backend import marker_evaluator

    return _said_device(rep, marker_evaluator(model, backend, device, chunk, note=lambda text: rep.say(f"note: {text}")))


def _said_device(rep: Reporter, evaluator):
    """``evaluator``, its OpenCL device told to the user."""
    if evaluator.backend == "opencl":
        rep.say(f"OpenCL device: {evaluator.device}")
    return evaluator


def _refuse_options_not_for(kind, take, given):
    """Options that do nothing for this kind of take are refused rather than silently ignored."""
    ignored = [name for name, is_given in given.items() if is_given]
    if ignored:
        raise InputError(f"{', '.join(ignored)} {'does' if len(ignored) == 1 else 'do'} not apply to a {kind}; "
                         "leave {} out".format("it" if len(ignored) == 1 else "them"), path=take)


@cli.command()
@click.argument("take", type=click.Path())
@click.option("-m", "--model", "model_path", required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False), help="Output folder.")
@click.option("--backend", type=click.Choice(["auto", "opencl", "numpy"]), default="auto", show_default=True,
              help="opencl: the OpenCL kernels (GPU, else PoCL's CPU driver, installed with facepipe); numpy: the "
                   "float64 reference; auto: opencl when a device works, else numpy.")
@click.option("--device", default=None, help="OpenCL device: P:D, gpu, cpu or part of its name [default: "
              "PYOPENCL_CTX, else the first GPU, else the CPU].")
@click.option("--frames", "frames_text", default=None, help="Replay only rows A:B of the take.")
@click.option("--chunk", default=32, show_default=True, help="Frames evaluated together.")
@click.option("--head-motion", type=click.Choice(["keep", "remove"]), default="keep", show_default=True,
              help="Re-apply the head's rigid motion to the output, or leave the face in rig space.")
@click.option("--save-large-scale", is_flag=True, help="Also write large_scale.npy (the shell alone; for a mesh cache replayed with "
              "--large-scale take, the cache's surface, else read back from the cache by exports).")
@click.option("--edits", "edits_path", default=None, type=click.Path(dir_okay=False),
              help="EDITS.json (from `facepipe edit`): handle offsets keyed at frames, added to the cleaned take.")
@click.option("--neutral-frame", type=int, default=None,
              help="Frame number of the take where the face is neutral: aligns the take to the rig by a similarity "
                   "and removes each marker's offset from the rig's rest pose.")
@click.option("--neutral-take", type=click.Path(dir_okay=False), default=None,
              help="A separate take of the neutral face (any supported format), used like --neutral-frame.")
@click.option("--take-units", default=None, help="Units of the take (mm, cm, m, in), overriding what the file says.")
@click.option("--subject", default=None, help="Use this subject's markers when the take holds several.")
@click.option("--no-stabilise", is_flag=True, help="Do not remove head motion: the take is already in head space.")
@click.option("--no-clean", is_flag=True,
              help="No prior-based cleaning (noise, outliers, long gaps): gaps are only interpolated (PCHIP).")
@click.option("--smooth", type=float, default=0.0, show_default=True,
              help="Temporal smoothing of the cleaned markers: Gaussian sigma in frames (0 = off).")
@landmark_take_options
@click.option("--force", is_flag=True, help="Replace an earlier replay in OUTPUT (its results, eval.json included, "
              "are removed).")
@mesh_cache_options
@_common
@click.pass_context
def replay(ctx, take, model_path, output, backend, device, frames_text, chunk, head_motion, save_large_scale, edits_path,
           neutral_frame,
           neutral_take, take_units, subject, no_stabilise, no_clean, smooth, camera_path, landmarks_path, lift,
           min_confidence, force, large_scale, rest_frame, cache_fps, quiet, verbose):
    """Replay a mocap TAKE onto the full-resolution face: OUTPUT/positions.npy and replay.json.

    TAKE is a facepipe CSV, C3D, TRC, Vicon Nexus CSV or OptiTrack Motive CSV, or a mesh cache of the
    rig's face (USD, MDD, PC2, a folder or frame_%04d.obj pattern of OBJs; see --large-scale); it is converted to the
    rig's units, aligned to the rig, stabilised and cleaned (see the README's Mocap section). A 2D
    landmark take (OpenFace CSV, or frame,time,NAME_u,NAME_v,…) needs --camera and --landmarks and is
    lifted to 3D through the rig's examples (see the README's Video takes section).
    """

    from facepipe.cli.progress import LazyBar, StageBar
    from facepipe.mocap.cleaning import CLEAN_STEPS
    from facepipe.io.model_file import load_model
    from facepipe.mocap.marker_take import MarkerTakeOptions, read_marker_take
    from facepipe.mocap.prepare import summary_lines
    from facepipe.io.edits_file import read_edits
    from facepipe.pipeline.replay import edited_windows, replay_windows

    rep = _reporter(ctx, quiet, verbose)
    if chunk < 1:
        raise InputError("--chunk must be at least 1")
    prepare_replay_folder(output, force)
    from facepipe.mocap.landmarks2d import is_landmark_take
    from facepipe.mocap.registry import mesh_cache_format

    if edits_path and (mesh_cache_format(take) is not None or camera_path or landmarks_path
                       or is_landmark_take(take)):
        raise InputError("--edits offsets the handles of a marker take; mesh caches and 2D takes are not edited",
                         path=edits_path)
    kind = ("mesh cache" if mesh_cache_format(take) is not None
            else "2D landmark take" if camera_path or landmarks_path or is_landmark_take(take) else "marker take")
    _refuse_options_not_for(kind, take, {
        "--neutral-frame": neutral_frame is not None and kind != "marker take",
        "--neutral-take": neutral_take is not None and kind != "marker take",
        "--subject": subject is not None and kind != "marker take",
        "--no-stabilise": no_stabilise and kind != "marker take",
        "--no-clean": no_clean and kind != "marker take",
        "--smooth": smooth != 0 and kind != "marker take",
        "--lift": lift is not None and kind != "2D landmark take",
        "--min-confidence": min_confidence is not None and kind != "2D landmark take",
    })
    if kind == "mesh cache":
        from facepipe.cli.cache_replay import replay_cache

        replay_cache(rep, take, model_path, output, large_scale=large_scale, rest_frame=rest_frame,
                     take_units=take_units, cache_fps=cache_fps, frames_text=frames_text, head_motion=head_motion,
                     chunk=chunk, save_large=save_large_scale, backend=backend, device=device,
                     make_evaluator=lambda model: _make_evaluator(model, backend, device, chunk, rep))
        return
    if large_scale == "take" or rest_frame is not None or cache_fps is not None:
        raise InputError("--large-scale take, --rest-frame and --cache-fps are for mesh caches (USD, MDD, PC2, OBJ "
                         "sequences); a marker take always drives the shell", path=take)
    if kind == "2D landmark take":
        from facepipe.cli.video import replay_video

        return replay_video(rep, take, model_path, output, camera_path=camera_path, landmarks_path=landmarks_path,
                            lift=lift, frames_text=frames_text, head_motion=head_motion, chunk=chunk,
                            save_large=save_large_scale, min_confidence=min_confidence,
                            make_evaluator=lambda model: _make_evaluator(model, backend, device, chunk, rep))
    if smooth < 0:
        raise InputError("--smooth must be 0 (off) or a positive number of frames")
    model = load_model(model_path)
    units = model.meta.get("units")
    edits = read_edits(edits_path, model.marker_names, units) if edits_path else []
    # the device is set up (B and the tables uploaded, kernels built: seconds at 530k vertices)
    # while the take is read and cleaned
    setup = ThreadPoolExecutor(1)
    evaluator_future = setup.submit(_make_evaluator, model, backend, device, chunk, rep)
    setup.shutdown(wait=False)
    try:
        # a long take is cleaned window by window, each while the previous one is on the device
        marker_take = read_marker_take(take, model, MarkerTakeOptions(
            take_units=take_units, subject=subject, clean=not no_clean, stabilise=not no_stabilise,
            neutral_frame=neutral_frame, neutral_take=neutral_take, frames=frames_text, smooth=smooth))
    except BaseException:
        wait([evaluator_future])  # the take's error is the one to report; the setup's outcome no longer matters
        raise
    evaluator = evaluator_future.result()
    take_data, prepared = marker_take.take, marker_take.prepared

    # cleaning steps on a bar of their own; the frame bar opens with its first frames, so its rate
    # and ETA are the evaluation's. Frames of the last cleaned window mean cleaning is over: its bar
    # closes then, so the frame bar takes its line rather than opening below a bar still drawn
    steps = len(CLEAN_STEPS) * prepared.n_windows if not no_clean else 0
    with StageBar(steps, "clean", quiet=rep.quiet or not steps) as clean_bar, \
            LazyBar(lambda: rep.bar(prepared.n_frames, desc="replay")) as bar:
        windows = prepared.windows(progress=clean_bar.step)
        if edits:
            windows = edited_windows(windows, take_data.frames, edits)

        def frames_done(n: int) -> None:
            clean_bar.close_after_last_step()
            bar.update(n)

        result = replay_windows(model, windows, take_data.frames, take_data.times,
                                Path(output), chunk=chunk, evaluator=evaluator, head_motion=head_motion,
                                progress=frames_done, extra_report=marker_take.report, save_large=save_large_scale)
    say_replayed(rep, result, summary_lines(prepared.report()))


# ----------------------------------------------------------------------------- export / eval


def _replay_info(outdir: Path) -> dict:
    path = outdir / "replay.json"
    if not path.is_file():
        raise InputError("no replay.json here", path=outdir, hint="give the folder written by 'facepipe replay'")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"replay.json is not valid JSON: {exc}", path=path) from None


def _load_positions(outdir: Path, name: str = "positions.npy") -> np.ndarray:
    path = outdir / name
    if not path.is_file():
        raise InputError(f"no {name} here", path=outdir, hint="run 'facepipe replay' first")
    try:
        return np.load(path, mmap_mode="r")
    except Exception as exc:
        raise InputError(f"cannot read {name}: {exc}", path=path) from None


@cli.command()
@click.argument("outdir", type=click.Path(file_okay=False))
@click.option("--format", "fmt", type=click.Choice(list(export_formats.FORMATS)), default="obj", show_default=True,
              help=export_formats.format_help())
@click.option("-o", "--dest", required=True, type=click.Path(), help=export_formats.destination_help())
@click.option("-m", "--model", "model_path", default=None, help="Model (default: the one replay.json names).")
@click.option("--layer", type=click.Choice(["final", "large", "details", "albedo"]), default="final", show_default=True,
              help="Geometry formats: the final surface, the large-scale one, or the details alone (final − large, "
                   "as vectors; both need replay --save-large-scale, or a mesh cache replayed as a take). Textures: "
                   "final (as the camera saw the face) or albedo (the layers without the frame's shading).")
@click.option("--resolution", default="2048", show_default=True, help="Maps: N or WxH texels per UDIM tile.")
@click.option("--padding", default=8, show_default=True, help="Maps: texels of edge padding around UV islands.")
@click.option("--half/--float", "half", default=None, help="Maps: pixel type [default: exr half, wrinkle float]; textures: EXR half/float instead "
              "of 16-bit PNG.")
@click.option("--vector/--scalar", "vector", default=True, help="Maps: R,G,B vector, or Y along the normal. "
              "[default: vector]")
@click.option("--space", type=click.Choice(["local", "tangent", "object"]), default="local", show_default=True,
              help="exr vector maps: the model's local frames (t, b, n), UV-aligned tangent frames (what renderers' "
              "tangent-space vector displacement expects), or object-space vectors.")
@click.option("--start", default=1, show_default=True, help="Sequences: number of the first file.")
@click.option("--up-axis", type=click.Choice(["Y", "Z"]), default="Y", show_default=True, help="USD stage up axis.")
@click.option("--force", is_flag=True, help="Overwrite existing files.")
@click.option("--resume", is_flag=True, help="Keep files already written and write only the missing ones.")
@_common
@click.pass_context
def export(ctx, outdir, fmt, dest, model_path, layer, resolution, padding, half, vector, space, start, up_axis, force,
           resume, quiet, verbose):
    """Export a replay (OUTDIR) for other tools: OBJ sequence, EXR displacement or wrinkle maps, USD, MDD, PC2;
    or a classified take's textures (OUTDIR with appearance.csv and light.csv; -m: the appearance model)."""
    from facepipe.export.dispatch import export_replay, parse_resolution

    rep = _reporter(ctx, quiet, verbose)
    if padding < 0:
        raise InputError("--padding must be 0 or more texels")
    r = export_replay(outdir, fmt, dest, model_path=model_path, layer=layer, resolution=parse_resolution(resolution),
                      padding=padding, half=half, mode="vector" if vector else "scalar", space=space, start=start,
                      up_axis=up_axis, force=force, resume=resume,
                      make_bar=lambda n, d, u="frame": rep.bar(n, unit=u, desc=d))
    kept = f"; kept {r['kept']} already there (--resume)" if r["kept"] else ""
    rep.say(f"wrote {r['written']} {fmt.upper()} file{'s' if r['written'] != 1 else ''} to {r['dest']}: "
            f"{r['bytes'] / 1e6:.1f} MB in {r['seconds']:.1f} s ({r['megabytes_per_second'] or 0:.1f} MB/s){kept}")
    for note in r.get("notes", []):
        rep.say(f"note: {note}")
    rep.detail(json.dumps(r, default=_json_default))


@cli.command()
@click.argument("outdir", type=click.Path(file_okay=False))
@click.option("-o", "--output", default="preview.png", show_default=True, type=click.Path(dir_okay=False),
              help="Image to write (.png, .jpg, .pdf, .svg).")
@click.option("-m", "--model", "model_path", default=None, help="Model (default: the one replay.json names).")
@click.option("--truth", default=None, type=click.Path(dir_okay=False),
              help="Truth .npz: adds the truth and heat maps of the vertex error of both layers.")
@click.option("--frame", "frames", multiple=True, type=int,
              help="Take frame number to show (repeatable) [default: the most expressive frame].")
@click.option("--strip", default=0, show_default=True, help="Show this many evenly spaced frames, one row each.")
@click.option("--size", default=420, show_default=True, help="Width of one panel in pixels.")
@click.option("--view", type=click.Choice(["auto", "camera", "head", "appearance"]), default="auto", show_default=True,
              help="camera: a 2D take's replayed face through the footage's camera with the tracked and reprojected "
                   "landmarks; head: large scale vs final (and --truth) in head space; appearance: a classified "
                   "take's input frames, the layered texture at Q drawn over them through the camera, the Q curves; auto: "
                   "appearance for a folder of appearance classify, camera for a 2D take (head with --truth).")
@click.option("--force", is_flag=True, help="Overwrite an existing image.")
@click.option("--movie", default=None, type=click.Path(dir_okay=False),
              help="Render every frame into a movie instead (.mp4 or .gif) at the take's rate, take frame numbers "
                   "burnt in: the final surface (and --truth, --with-large-scale beside it; a 2D take through its "
                   "camera).")
@click.option("--with-large-scale", is_flag=True, help="--movie: show the large-scale surface beside the final one.")
@_common
@click.pass_context
def preview(ctx, outdir, output, model_path, truth, frames, strip, size, view, force, movie, with_large_scale, quiet,
            verbose):
    """Render shaded frames of a replay (large scale vs final, error heat maps against --truth; a 2D take's
    face through its camera) to an image."""
    from facepipe.cli.preview import preview_replay

    rep = _reporter(ctx, quiet, verbose)
    if not 32 <= size <= 4096:
        raise InputError(f"--size {size} is outside 32..4096 pixels")
    if strip < 0 or strip > 64:
        raise InputError(f"--strip {strip} is outside 0..64 frames")
    if movie:
        from facepipe.cli.movie import movie_command

        if frames or strip:
            raise InputError("--frame and --strip choose the frames of a still; a movie shows every replayed frame",
                             hint="replay a part of the take (replay --frames A:B) for a shorter movie")

        return movie_command(rep, outdir, model_path, movie, view=view, truth_path=truth,
                             with_large=with_large_scale, size=size, force=force)
    t0 = time.perf_counter()
    s = preview_replay(outdir, model_path, output, view=view, truth_path=truth, frame_numbers=list(frames),
                       strip=strip, size=size, force=force)
    for k, f in enumerate(s["frames"]):
        errs = (f"; RMS vs truth: final {s['rms']['final'][k]:.4g}, large scale {s['rms']['large'][k]:.4g}"
                if "rms" in s else "")
        if s.get("view") == "appearance":
            errs = "; Q " + " ".join(f"{x:.2f}" for x in s["q"][k])
            if f in s.get("unread", {}):
                errs += f"; no input image: {s['unread'][f]}"
        if s.get("view") == "camera":
            px = s["reprojection_px"][k]
            errs = "; tracker lost the face" if px is None else f"; landmark reprojection RMS {px:.3f} px"
        rep.say(f"frame {f}{errs}")
    rep.say(f"wrote {output} ({time.perf_counter() - t0:.1f} s)")


@cli.command(name="eval")
@click.argument("outdir", type=click.Path(file_okay=False))
@click.option("--truth", required=True, type=click.Path(dir_okay=False), help="Truth .npz with 'positions'.")
@click.option("--vertices", "vertex_range", default=None,
              help="Vertex range A:B in the mesh file's numbering (also for a rig welded along seams; default: all).")
@click.option("--large-scale", is_flag=True, help="Also evaluate the large-scale layer (large_scale.npy where the replay wrote "
              "it; a mesh cache's own surface, read back from the cache).")
@click.option("--space", type=click.Choice(["auto", "take", "head"]), default="auto", show_default=True,
              help="Compare in the take's space (positions as written and the truth as given) or in head space (the "
                   "head's motion out of both: the replay's from handles.npz, the truth's from its 'rotation' and "
                   "'translation'); auto: head for a 2D take's replay (written in camera coordinates), else take.")
@click.option("--compare", "compare_config", default=None, type=click.Path(dir_okay=False),
              help="CONFIG.toml: also fit it and compare baselines (shell, RBF morph, global and local blend "
                   "shapes, PSD and WPSD by basis size) on this replay's handles; writes compare.json/.png.")
@click.option("--tune/--no-tune", default=True, show_default=True,
              help="With --compare: fit the config with its parameters validated, as 'fit' does (default).")
@_common
@click.pass_context
def eval_(ctx, outdir, truth, vertex_range, large_scale, space, compare_config, tune, quiet, verbose):
    """Per-frame RMS and max vertex error of a replay against ground truth.

    The truth's frames are the replay's by frame number, or by time where the numbers differ and
    both have times (a tracker's frames counted from 1, the truth's from 0)."""
    from facepipe.io.replay_folder import ReplayDir
    from facepipe.pipeline.evaluate import frame_errors, parse_vertex_range, summarize, truth_rows

    rep = _reporter(ctx, quiet, verbose)
    outdir = Path(outdir)
    info = _replay_info(outdir)
    positions = _load_positions(outdir)
    matched: dict = {}
    replay = ReplayDir(outdir)
    truth_pos, index, extras = truth_rows(truth, info["frame_numbers"], positions.shape[1], info.get("times"), matched,
                                          replay.weld_index)
    if matched["frames_matched_by"] == "time":
        rep.say("note: the take's frame numbers are not the truth's: frames matched by time")
    truth_sel = np.asarray(truth_pos)[index] if len(index) < 4096 else truth_pos[index]
    # a rig welded along seams: A:B numbers the mesh file's vertices, as the user's tools do
    weld_index = replay.weld_index() if vertex_range else None
    vertices = parse_vertex_range(vertex_range, positions.shape[1] if weld_index is None else len(weld_index))
    selected = vertices if weld_index is None else np.asarray(weld_index)[vertices]  # (each file vertex's welded one)
    units = info.get("units") or "rig units"  # (replays before units were recorded: the rig's)
    space = space if space != "auto" else "head" if str(info.get("coordinates", "")).startswith("camera") else "take"
    pose, truth_pose = _eval_poses(outdir, info, truth, extras, index) if space == "head" else (None, None)
    result = {"vertices": [vertices.start, vertices.stop], "truth": str(truth), "units": units, "space": space,
              **({"vertices_numbered_by": "mesh file"} if weld_index is not None else {}), **matched}
    sources = [("final", "positions.npy")]
    if large_scale:
        sources.append(("large_scale", "large_scale.npy"))
    for label, name in sources:
        # (a mesh cache's large scale is the cache: read back from it where the replay kept no copy)
        pos = _load_positions(outdir, name) if label == "final" else replay.layer("large")
        rms, mx = frame_errors(pos, truth_sel, selected, pose=pose, truth_pose=truth_pose)
        result[label] = dict(summarize(rms, mx), per_frame_rms=rms.tolist(), per_frame_max=mx.tolist())
        if verbose:
            for f, a, b in zip(info["frame_numbers"], rms, mx):
                rep.detail(f"  frame {f:6d}  rms {a:.5f}  max {b:.5f} {units}")
    _write_json(outdir / "eval.json", result)
    if compare_config:
        _compare(rep, outdir, compare_config, np.asarray(truth_sel), selected, tune)
    numbering = " of the mesh file" if weld_index is not None else ""
    for label, _ in sources:
        s = result[label]
        rep.say(f"{label}: {s['frames']} frames, vertices {vertices.start}:{vertices.stop}{numbering}: RMS mean "
                f"{s['rms_mean']:.5f} {units}, p95 {s['rms_p95']:.5f} {units}, max frame {s['rms_max']:.5f} {units}; "
                f"largest vertex error {s['max_error']:.5f} {units}")
    rep.say(f"wrote {outdir / 'eval.json'}")


def _eval_poses(outdir: Path, info: dict, truth, extras: dict, index: np.ndarray):
    """The head's pose in the replay (None where it wrote head space) and in the truth, per replayed
    frame, for comparing both in head space."""
    if "rotation" not in extras or "translation" not in extras:
        raise InputError("the truth has no head pose ('rotation' and 'translation' per frame) to compare in head space",
                         path=truth, hint="compare in the take's space: --space take")
    truth_pose = (extras["rotation"][index], extras["translation"][index])
    if info.get("head_motion", "keep") == "remove":
        return None, truth_pose
    path = outdir / "handles.npz"
    if not path.is_file():
        raise InputError("no handles.npz here (the head's pose of every frame)", path=outdir,
                         hint="re-run 'facepipe replay' with this version")
    with np.load(path) as handles:
        return (handles["rotation"].astype(np.float64), handles["translation"].astype(np.float64)), truth_pose


def _compare(rep: Reporter, outdir: Path, config: str, truth: np.ndarray, vertices: slice | np.ndarray,
             tune: bool = False) -> None:
    from facepipe.pipeline.baselines import compare_methods, plot_comparison

    path = outdir / "handles.npz"
    if not path.is_file():
        raise InputError("no handles.npz here", path=outdir, hint="re-run 'facepipe replay' with this version")
    handles = np.load(path)
    rig, fit = _run_fit(config, rep, tune=tune)
    if handles["head"].shape[1] != len(rig.handles):
        raise InputError(f"the replay has {handles['head'].shape[1]} handles, the config's rig {len(rig.handles)}",
                         path=config, hint="compare with the config the replayed model was baked from")
    rep.say("comparing methods on the replay's handles:")
    result = compare_methods(fit, rig, handles["head"].astype(np.float64), handles["rotation"].astype(np.float64),
                             handles["translation"].astype(np.float64), truth, vertices, log=rep.say)
    _write_json(outdir / "compare.json", result)
    plot_comparison(result, outdir / "compare.png", title=f"{Path(config).stem}: error against basis size")
    rep.say(f"{'method':26s} {'P':>3s} {'mean RMS':>9s} {'p95':>9s} {'frames/s':>9s}")
    for r in result["rows"]:
        p = "" if r["poses"] is None else str(r["poses"])
        rep.say(f"{r['method']:26s} {p:>3s} {r['rms_mean']:9.5f} {r['rms_p95']:9.5f} {r['frames_per_second']:9.1f}")
    rep.say(f"wrote {outdir / 'compare.json'} and {outdir / 'compare.png'}")


# ----------------------------------------------------------------------------- transfer


@cli.command()
@click.argument("model_path", metavar="MODEL", type=click.Path(dir_okay=False))
@click.option("--target", required=True, type=click.Path(dir_okay=False), help="The other face's rest mesh (OBJ, PLY).")
@click.option("--source-points", required=True, type=click.Path(dir_okay=False),
              help="CSV name,vertex: marked points on the model's mesh (about 40, spread over the face).")
@click.option("--target-points", required=True, type=click.Path(dir_okay=False),
              help="CSV name,vertex: the same named points on the target.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Model to write; a .json summary is written beside it.")
@click.option("--target-markers", default=None, type=click.Path(dir_okay=False),
              help="markers.csv of the target (name,vertex[,role]) [default: each marker mapped to the nearest "
                   "target vertex through the correspondence].")
@click.option("--deform", type=click.Choice(["auto", "shell", "rbf"]), default="auto", show_default=True,
              help="How the source is fitted to the target's points: thin shell, RBF volume morph, or auto (the "
                   "shell when every part of the source holds a point).")
@click.option("--max-distance", type=float, default=None,
              help="Target vertices farther than this from the fitted source are an error [default: half the "
                   "points' spacing].")
@click.option("--allow-far", is_flag=True, help="Map vertices beyond --max-distance anyway (to the nearest source).")
@click.option("--refine/--no-refine", default=True, show_default=True,
              help="After the fit to the points, move the whole source onto the target's surface (closest "
                   "points with agreeing normals, regularised by the thin shell), so parts without points "
                   "correspond too.")
@click.option("--scale-details/--no-scale-details", default=True, show_default=True,
              help="Scale the details by the size ratio of the faces (from the points' similarity).")
@click.option("--target-anchors", default=None, type=click.Path(dir_okay=False),
              help="Target vertices (one per line) held with the head besides those mapped from the model's "
                   "anchors: one vertex of each part the source lacks (an eyeball, teeth).")
@click.option("--target-weld", is_flag=True,
              help="Weld a target mesh split along UV seams or hard edges (vertices on one another that no face "
                   "joins; refused without): target files then number the mesh file's vertices.")
@click.option("--target-units", default=None, metavar="UNIT",
              help="Length unit of the target mesh (mm, cm, m, in, ...) [default: the model's]: the new model is in "
                   "it (takes, exports and lengths such as --max-distance in it).")
@_common
@click.pass_context
def transfer(ctx, model_path, target, source_points, target_points, output, target_markers, deform, max_distance,
             allow_far, refine, scale_details, target_anchors, target_weld, target_units, quiet, verbose):
    """Transfer a MODEL's learned details onto another face: an ordinary model of the target."""
    from facepipe.cli.progress import StageBar
    from facepipe.pipeline.transfer import TRANSFER_STAGES, transfer_files

    rep = _reporter(ctx, quiet, verbose)
    if max_distance is not None and max_distance <= 0:
        raise InputError("--max-distance must be a positive length")
    with StageBar(len(TRANSFER_STAGES), "transfer", quiet=rep.quiet) as steps:
        s = transfer_files(model_path, target, source_points, target_points, output, target_markers, deform=deform,
                           max_distance=max_distance, allow_far=allow_far, scale_details=scale_details,
                           refine=refine, target_units=target_units, target_anchors_path=target_anchors,
                           target_weld=target_weld, stage=steps.step)
    d = s["projection_distance"]
    rep.say(f"{s['points']} points; similarity scale {s['similarity']['scale']:.4f}, rotation "
            f"{s['similarity']['rotation_deg']:.1f}°; fitted by the {s['deformation']}")
    rep.say(f"mapped {s['vertices_mapped']} target vertices onto {s['source_vertices']} source vertices: distance "
            f"median {d['median']:.3g}, p99 {d['p99']:.3g}, max {d['max']:.3g}; {s['far_vertices']} beyond "
            f"{s['far_limit']:.3g}; {s['normal_mismatches']} without a source triangle facing their way")
    if s.get("refined"):
        r, far = s["refined"], s["refined"]["target_to_source"]
        rep.say(f"refined onto the target's surface in {len(r['stiffness_lengths'])} stiffness steps: target to "
                f"refined source mean {far['mean']:.3g}, p95 {far['p95']:.3g}, max {far['max']:.3g}; "
                f"{100 * r['paired_fraction']:.0f} % of the source paired")
    m = s["markers"]
    rep.say(f"markers: {m.get('given', m.get('mapped'))} {'given' if 'given' in m else 'mapped'}; anchors "
            f"{s['anchors']['target']}; method {s['method']}, details scaled by {s['detail_scale']:.4f}")
    if s["units"]["target"] != s["units"]["source"]:
        rep.say(f"units: the target and the new model in {s['units']['target']} (the source model in "
                f"{s['units']['source']})")
    for note in s["notes"]:
        rep.say(f"note: {note}")
    rep.say(f"wrote {output} and {Path(output).with_suffix('.json')} ({s['seconds_total']:.1f} s)")


# ----------------------------------------------------------------------------- sample


@cli.command()
@click.argument("directory", type=click.Path(file_okay=False))
@click.option("--vertices", default=20000, show_default=True, help="Approximate vertex count (up to 600k).")
@click.option("--examples", default=8, show_default=True, help="Example poses (6-12).")
@click.option("--frames", default=120, show_default=True, help="Frames of the take.")
@click.option("--seed", default=0, show_default=True)
@click.option("--markers", default=None, type=int, help="Markers driving the shell, 6 stable ones included "
              "[default: 96]; 89 is the paper's configuration.")
@click.option("--appearance", "with_appearance", is_flag=True,
              help="Also render footage of the take with known texture and light (DIRECTORY/appearance: example "
                   "frames, the take frontal and with the head turned, truth activations, appearance.toml).")
@click.option("--image-size", default=384, show_default=True, help="--appearance: image width and height in pixels.")
@_common
@click.pass_context
def sample(ctx, directory, vertices, examples, frames, seed, markers, with_appearance, image_size, quiet, verbose):
    """Write a self-contained synthetic rig: mesh, markers, anchors, examples, a take with truth, a config."""
    from facepipe.sample_rig import write_sample_rig

    rep = _reporter(ctx, quiet, verbose)
    if not 100 <= vertices <= 2_000_000:
        raise InputError(f"--vertices {vertices} is outside 100..2000000")
    check_output_path(directory, kind="folder", what="sample rig folder")
    if with_appearance:
        from facepipe.cli.appearance import check_sample_appearance

        check_sample_appearance(examples)
    info = write_sample_rig(directory, n_vertices=vertices, n_examples=examples, n_frames=frames, seed=seed,
                            n_markers=markers)
    rep.say(f"wrote sample rig to {directory}: " + ", ".join(f"{k} {v}" for k, v in info.items()
                                                             if isinstance(v, (int, float))))
    if with_appearance:
        from facepipe.cli.appearance import sample_appearance

        kit = sample_appearance(directory, frames, image_size, rep)
        rep.say(f"wrote footage of {kit['frames']} frames (frontal and head turned) and {kit['examples']} example "
                f"frames; config {kit['config']}")


# ----------------------------------------------------------------------------- appearance


@cli.group()
def appearance():
    """Appearance from footage: layered textures driven by wavelet classification (Fidaleo et al. 2000)."""


@appearance.command("build")
@click.argument("config", type=click.Path(dir_okay=False))
@click.option("-o", "--output", default="appearance.npz", show_default=True, type=click.Path(dir_okay=False))
@_common
@click.pass_context
def appearance_build(ctx, config, output, quiet, verbose):
    """Build an appearance model from the config's [appearance] table (example frames with geometry)."""
    from facepipe.cli.appearance import build_command

    build_command(config, output, _reporter(ctx, quiet, verbose), _write_json)


@appearance.command("classify")
@click.argument("model", type=click.Path(dir_okay=False))
@click.argument("footage")
@click.option("--geometry", required=True, type=click.Path(),
              help="The take's geometry: a replay folder or an .npz with positions (T, V, 3) and frame (T,).")
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False),
              help="Folder for appearance.csv (frame, time, Q per region), light.csv (each frame's light) and "
                   "appearance.json.")
@click.option("--fps", default=30.0, show_default=True,
              help="Frame rate of a geometry that records no frame times (times = number / fps; a replay folder "
                   "has its own).")
@_common
@click.pass_context
def appearance_classify(ctx, model, footage, geometry, output, fps, quiet, verbose):
    """Classify every frame of FOOTAGE (folder, frame_%04d.png pattern or video) against MODEL's templates."""
    from facepipe.cli.appearance import classify_command

    if fps <= 0:
        raise InputError(f"--fps {fps} must be positive")
    classify_command(model, footage, geometry, output, fps, _reporter(ctx, quiet, verbose))


@cli.command()
@click.argument("model_path", metavar="MODEL", type=click.Path(dir_okay=False))
@click.argument("take", required=False, type=click.Path(dir_okay=False))
@click.option("--edits", "edits_path", default=None, type=click.Path(dir_okay=False),
              help="EDITS.json to load (if it exists) and save to [default: TAKE.edits.json, or edits.json].")
@click.option("--port", default=8765, show_default=True, help="TCP port (0 picks a free one).")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to listen on; anything but loopback lets other machines edit.")
@click.option("--truth", "truth_path", default=None, type=click.Path(dir_okay=False),
              help="Truth .npz of the take: the page shows the error as a heat map.")
@click.option("--evaluate", "mode", type=click.Choice(["auto", "browser", "server"]), default="auto",
              show_default=True, help="Where the per-vertex evaluation runs: in the page (JavaScript) or on "
                                      "the server's engine (streamed positions); auto by the size of B (the "
                                      "server for a local-strain model, which the page does not evaluate).")
@click.option("--backend", type=click.Choice(["auto", "opencl", "numpy"]), default="auto", show_default=True,
              help="The server's engine in server mode.")
@click.option("--take-units", default=None, help="Units of the take, overriding what the file says.")
@_common
@click.pass_context
def edit(ctx, model_path, take, edits_path, port, host, truth_path, mode, backend, take_units, quiet, verbose):
    """Fine-tune TAKE in the browser: drag handles, see the face with its wrinkles at once.

    Serves a page on http://127.0.0.1:PORT/ (printed); edits (handle offsets keyed at frames,
    eased in and out) save to EDITS.json, which `facepipe replay TAKE --edits EDITS.json` applies.
    """
    from facepipe.cli.editor import edit_command

    edit_command(_reporter(ctx, quiet, verbose), model_path, take, edits_path, host, port, truth_path, mode, backend,
                 take_units)


# ----------------------------------------------------------------------------- batch

# (its module imports this one's option helpers, so it is registered once they exist)
from facepipe.cli.batch import batch as _batch  # noqa: E402

cli.add_command(_batch)


def main(argv=None) -> None:
    """Console entry point: maps InputError to exit status 2, anything unexpected to 1."""
    try:
        with terminate_as_interrupt():  # SIGTERM unwinds as Ctrl-C does: partial outputs removed
            status = cli.main(args=argv, standalone_mode=False)
    except InputError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except click.exceptions.Abort as exc:
        if isinstance(exc.__cause__, KeyboardInterrupt):  # click re-raises Ctrl-C (and SIGTERM) as Abort
            click.echo("interrupted: complete output files are kept, partial ones removed", err=True)
            sys.exit(getattr(exc.__cause__, "exit_status", 130))
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as exc:
        exc.show()
        sys.exit(2)
    except KeyboardInterrupt as exc:
        click.echo("interrupted: complete output files are kept, partial ones removed", err=True)
        sys.exit(getattr(exc, "exit_status", 130))
    except (OSError, MemoryError) as exc:  # the machine's, not a bug: a full disk, a folder it may not write
        click.echo(f"error: {describe_system_error(exc)}", err=True)
        sys.exit(1)
    except Exception:
        click.echo("internal error (please report it with the text below):", err=True)
        traceback.print_exc()
        sys.exit(1)
    sys.exit(status if isinstance(status, int) else 0)


if __name__ == "__main__":
    main()
