"""The facepipe command line: parse, call the library, report.

Exit status: 0 success, 2 bad input (the message names the file and the fix), 1 internal error.
"""

from __future__ import annotations

import json
import sys
import time
import traceback
from pathlib import Path

import click
import numpy as np

from .errors import InputError


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
        from tqdm import tqdm

        return tqdm(total=total, unit=unit, desc=desc, disable=self.quiet, dynamic_ncols=True, file=sys.stderr)


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
    from .atomic import atomic_path

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


def _run_fit(config, rep: Reporter):
    from .fit import fit_rig
    from .rig import load_rig

    t0 = time.perf_counter()
    rig = load_rig(config)
    rep.say(f"rig: {rig.mesh.n_vertices} vertices, {len(rig.handles)} handles, {len(rig.anchors)} anchors, "
            f"{len(rig.example_names)} example poses")

    def progress(method, n, curve):
        rep.detail(f"  {method}: {n:2d} poses  mean RMS {curve['mean_rms']:.4f}  max {curve['max_rms']:.4f}")

    t_load = time.perf_counter() - t0
    fit = fit_rig(rig, progress=progress)
    fit.report["seconds"]["load"] = t_load
    fit.report["seconds"]["total"] = time.perf_counter() - t0
    return rig, fit


def _print_fit_summary(rep: Reporter, fit, units: str) -> None:
    r = fit.report
    rep.say(f"feature graph: F = {r['feature_edges']} edges; marker spacing {r['marker_spacing']:.3f} {units}; "
            f"WPSD β = {r['beta']:.3f}/{units}, {r['edges_per_vertex_mean']:.1f} edges per vertex")
    rep.say(f"large-scale only: training RMS mean {r['large_scale_rms']['mean']:.4f} {units}")
    for method, curve in r["curves"].items():
        pts = "  ".join(f"P={c['poses']}:{c['mean_rms']:.4f}" for c in curve
                        if c["poses"] in (0, 1, 2, 3, 6, 12) or c is curve[-1])
        rep.say(f"{method.upper():5s} training RMS by basis size: {pts}")
    rep.say(f"basis ({r['method']}): {', '.join(r['basis'])}")


@cli.command()
@click.argument("config", type=click.Path(dir_okay=False))
@click.option("-o", "--output", default="fit.npz", show_default=True, type=click.Path(dir_okay=False),
              help="Fit file to write; a .json report is written beside it.")
@_common
@click.pass_context
def fit(ctx, config, output, quiet, verbose):
    """Extract the examples' details and select the pose basis greedily."""
    from .model import save_fit

    rep = _reporter(ctx, quiet, verbose)
    rig, result = _run_fit(config, rep)
    save_fit(output, result, rig)
    report_path = Path(output).with_suffix(".json")
    _write_json(report_path, result.report)
    _print_fit_summary(rep, result, rig.config.units)
    rep.say(f"wrote {output} and {report_path} ({result.report['seconds']['total']:.1f} s)")


@cli.command()
@click.argument("source", type=click.Path(dir_okay=False))
@click.option("-o", "--output", default="model.npz", show_default=True, type=click.Path(dir_okay=False))
@_common
@click.pass_context
def bake(ctx, source, output, quiet, verbose):
    """Write the model replay needs (float32, one file) from a CONFIG.toml or a FIT.npz."""
    from .model import fit_to_model, model_arrays, save_model

    rep = _reporter(ctx, quiet, verbose)
    t0 = time.perf_counter()
    if source.endswith(".npz"):
        meta = fit_to_model(source, output)
    else:
        rig, result = _run_fit(source, rep)
        arrays, meta = model_arrays(result, rig)
        save_model(output, arrays, meta)
        _print_fit_summary(rep, result, rig.config.units)
    size = Path(output).stat().st_size / 1e6
    rep.say(f"wrote {output}: method {meta['method']}, {len(meta['basis']) - 1} basis poses, "
            f"{size:.1f} MB ({time.perf_counter() - t0:.1f} s)")


# ----------------------------------------------------------------------------- replay


def _parse_frames(text: str | None) -> slice | None:
    if not text:
        return None
    try:
        a, b = (text.split(":") + [""])[:2]
        return slice(int(a) if a else None, int(b) if b else None)
    except ValueError:
        raise InputError(f"--frames {text!r} is not of the form A:B (row indices, end exclusive)") from None


@cli.command()
@click.argument("take", type=click.Path(dir_okay=False))
@click.option("-m", "--model", "model_path", required=True, type=click.Path(dir_okay=False))
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False), help="Output folder.")
@click.option("--backend", type=click.Choice(["numpy"]), default="numpy", show_default=True)
@click.option("--frames", "frames_text", default=None, help="Replay only rows A:B of the take.")
@click.option("--chunk", default=32, show_default=True, help="Frames evaluated together.")
@click.option("--head-motion", type=click.Choice(["keep", "remove"]), default="keep", show_default=True,
              help="Re-apply the head's rigid motion to the output, or leave the face in rig space.")
@click.option("--save-large-scale", is_flag=True, help="Also write large_scale.npy (the shell alone).")
@_common
@click.pass_context
def replay(ctx, take, model_path, output, backend, frames_text, chunk, head_motion, save_large_scale, quiet,
           verbose):
    """Replay a mocap TAKE onto the full-resolution face: OUTPUT/positions.npy and replay.json."""
    from .model import load_model
    from .mocap import fill_gaps, read_take
    from .replay import replay as run_replay
    from .stabilise import stabilise

    rep = _reporter(ctx, quiet, verbose)
    if chunk < 1:
        raise InputError("--chunk must be at least 1")
    model = load_model(model_path)
    take_data = read_take(take, model.marker_names, frames=_parse_frames(frames_text))
    rest_handles = model.rest[model.handle_vertices].astype(np.float64)
    # gaps are filled in head space, where a marker moves with the face only, not the head
    head, R, t = stabilise(take_data.positions, rest_handles, model.stable.astype(bool), take_data.frames,
                           model.marker_names, prior=model.example_handles.astype(np.float64))
    head, gap_report = fill_gaps(head, marker_names=model.marker_names, times=take_data.times, path=take)
    T = head.shape[0]
    with rep.bar(T, desc="replay") as bar:
        result = run_replay(model, head, R, t, take_data.frames, take_data.times, Path(output), chunk=chunk,
                            head_motion=head_motion, progress=bar.update,
                            extra_report={"take": str(take), "markers": gap_report,
                                          "extra_markers": take_data.extra_markers},
                            save_large=save_large_scale)
    r = result.report
    totals = gap_report.get("total", {})
    rep.say(f"replayed {r['frames']} frames × {r['vertices']} vertices ({r['method']}, {r['backend']}) "
            f"at {r['frames_per_second']:.1f} frames/s")
    rep.say(f"markers: {totals.get('filled', 0)} missing samples filled in {totals.get('gaps', 0)} gaps; "
            f"head motion up to {r['head_rotation_deg_max']:.1f}° / {r['head_translation_max']:.2f}")
    rep.say(f"wrote {result.positions_path} and {Path(output) / 'replay.json'}")


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
@click.option("--format", "fmt", type=click.Choice(["obj"]), default="obj", show_default=True)
@click.option("-o", "--dest", required=True, type=click.Path(file_okay=False))
@click.option("-m", "--model", "model_path", default=None, help="Model (default: the one replay.json names).")
@click.option("--force", is_flag=True, help="Overwrite existing files.")
@click.option("--resume", is_flag=True, help="Skip frames whose file already exists.")
@_common
@click.pass_context
def export(ctx, outdir, fmt, dest, model_path, force, resume, quiet, verbose):
    """Export a replay (OUTDIR) as an OBJ sequence DEST/frame_0001.obj, ... with the rest mesh's polygons/UVs."""
    from .export import write_obj_sequence
    from .model import load_model

    rep = _reporter(ctx, quiet, verbose)
    outdir = Path(outdir)
    info = _replay_info(outdir)
    model = load_model(model_path or info["model"])
    positions = _load_positions(outdir)
    if positions.shape[1] != model.n_vertices:
        raise InputError(f"positions have {positions.shape[1]} vertices, the model {model.n_vertices}",
                         path=outdir / "positions.npy", hint="pass the model used for this replay with -m")
    t0 = time.perf_counter()
    with rep.bar(positions.shape[0], desc="export") as bar:
        written = write_obj_sequence(model.mesh(), positions, Path(dest), force=force, resume=resume,
                                     progress=bar.update)
    seconds = time.perf_counter() - t0
    rep.say(f"wrote {len(written)} OBJ files to {dest} ({len(written) / max(seconds, 1e-9):.1f} files/s)")


@cli.command(name="eval")
@click.argument("outdir", type=click.Path(file_okay=False))
@click.option("--truth", required=True, type=click.Path(dir_okay=False), help="Truth .npz with 'positions'.")
@click.option("--vertices", "vertex_range", default=None, help="Vertex range A:B (default: all).")
@click.option("--large-scale", is_flag=True, help="Also evaluate large_scale.npy if the replay wrote it.")
@_common
@click.pass_context
def eval_(ctx, outdir, truth, vertex_range, large_scale, quiet, verbose):
    """Per-frame RMS and max vertex error of a replay against ground truth."""
    from .evaluate import frame_errors, match_frames, parse_vertex_range, summarize

    rep = _reporter(ctx, quiet, verbose)
    outdir = Path(outdir)
    info = _replay_info(outdir)
    positions = _load_positions(outdir)
    try:
        data = np.load(truth, mmap_mode="r")
        truth_pos = data["positions"]
        truth_frames = data["frame"] if "frame" in data else np.arange(truth_pos.shape[0])
    except FileNotFoundError:
        raise InputError("truth file not found", path=truth) from None
    except Exception as exc:
        raise InputError(f"cannot read the truth: {exc}", path=truth) from None
    if truth_pos.shape[1:] != positions.shape[1:]:
        raise InputError(f"truth has shape {truth_pos.shape}, the replay {positions.shape}", path=truth)
    index = match_frames(np.asarray(info["frame_numbers"]), np.asarray(truth_frames), truth)
    truth_sel = np.asarray(truth_pos)[index] if len(index) < 4096 else truth_pos[index]
    vertices = parse_vertex_range(vertex_range, positions.shape[1])
    result = {"vertices": [vertices.start, vertices.stop], "truth": str(truth)}
    sources = [("final", "positions.npy")]
    if large_scale:
        sources.append(("large_scale", "large_scale.npy"))
    for label, name in sources:
        pos = _load_positions(outdir, name)
        rms, mx = frame_errors(pos, truth_sel, vertices)
        result[label] = dict(summarize(rms, mx), per_frame_rms=rms.tolist(), per_frame_max=mx.tolist())
        if verbose:
            for f, a, b in zip(info["frame_numbers"], rms, mx):
                rep.detail(f"  frame {f:6d}  rms {a:.5f}  max {b:.5f}")
    _write_json(outdir / "eval.json", result)
    for label, _ in sources:
        s = result[label]
        rep.say(f"{label}: {s['frames']} frames, vertices {vertices.start}:{vertices.stop}: RMS mean "
                f"{s['rms_mean']:.5f}, p95 {s['rms_p95']:.5f}, max frame {s['rms_max']:.5f}; "
                f"largest vertex error {s['max_error']:.5f}")
    rep.say(f"wrote {outdir / 'eval.json'}")


# ----------------------------------------------------------------------------- sample


@cli.command()
@click.argument("directory", type=click.Path(file_okay=False))
@click.option("--vertices", default=20000, show_default=True, help="Approximate vertex count (up to 600k).")
@click.option("--examples", default=8, show_default=True, help="Example poses (6-12).")
@click.option("--frames", default=120, show_default=True, help="Frames of the take.")
@click.option("--seed", default=0, show_default=True)
@_common
@click.pass_context
def sample(ctx, directory, vertices, examples, frames, seed, quiet, verbose):
    """Write a self-contained synthetic rig: mesh, markers, anchors, examples, a take with truth, a config."""
    from .sample import write_sample_rig

    rep = _reporter(ctx, quiet, verbose)
    if not 100 <= vertices <= 2_000_000:
        raise InputError(f"--vertices {vertices} is outside 100..2000000")
    info = write_sample_rig(directory, n_vertices=vertices, n_examples=examples, n_frames=frames, seed=seed)
    rep.say(f"wrote sample rig to {directory}: " + ", ".join(f"{k} {v}" for k, v in info.items()
                                                             if isinstance(v, (int, float))))


@cli.command()
@click.option("-o", "--output", default="bench/results.json", show_default=True, type=click.Path(dir_okay=False))
@click.option("--vertices", default=20000, show_default=True, help="Vertices of the generated rig.")
@click.option("--frames", default=64, show_default=True)
@click.option("--repeats", default=3, show_default=True, help="Timings are medians over this many runs.")
@click.option("--work", default="bench/work", show_default=True, type=click.Path(file_okay=False))
@_common
@click.pass_context
def bench(ctx, output, vertices, frames, repeats, work, quiet, verbose):
    """Measure bake and replay speed on a generated rig; write the figures as JSON."""
    from .bench import run_bench

    rep = _reporter(ctx, quiet, verbose)
    results = run_bench(Path(work), n_vertices=vertices, n_frames=frames, repeats=repeats, log=rep.say)
    _write_json(Path(output), results)
    rep.say(f"wrote {output}")


def main(argv=None) -> None:
    """Console entry point: maps InputError to exit status 2, anything unexpected to 1."""
    try:
        status = cli.main(args=argv, standalone_mode=False)
    except InputError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as exc:
        exc.show()
        sys.exit(2)
    except KeyboardInterrupt:
        click.echo("interrupted: complete output files are kept, partial ones removed", err=True)
        sys.exit(130)
    except Exception:
        click.echo("internal error (please report it with the text below):", err=True)
        traceback.print_exc()
        sys.exit(1)
    sys.exit(status if isinstance(status, int) else 0)


if __name__ == "__main__":
    main()
