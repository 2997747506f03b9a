"""``facepipe batch``: replay (and export) many takes against one model on a Dask cluster.

The command parses, hands the takes to :func:`facepipe.batch.jobs.run_batch` and reports;
its exit status is 0 when every take is done (replayed now or already), 2 when some failed (they
are listed), 1 when the cluster failed.
"""

from __future__ import annotations

from pathlib import Path

import click

from facepipe.cli.commands import _common, _reporter
from facepipe.cli.take_options import landmark_take_options, mesh_cache_options
from facepipe.errors import InputError
from facepipe.export import registry as export_formats


@click.command()
@click.argument("takes", nargs=-1, required=True)
@click.option("-m", "--model", "model_path", required=True, type=click.Path(dir_okay=False),
              help="The baked model, on storage every worker reads at the same path.")
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False),
              help="Folder for OUT/<take stem>/ (positions.npy, replay.json, exports; takes sharing a stem: "
                   "OUT/<stem>_<format>/) and OUT/batch.json; on storage every worker writes at the same path.")
@click.option("--export", "exports", multiple=True, type=click.Choice(list(export_formats.FORMATS)),
              help="Also export every take in this format (repeatable): a folder OUT/<stem>/<format>/ or a file "
                   "OUT/<stem>/<stem>.<suffix>.")
@click.option("--workers", type=int, default=None,
              help="Worker processes of the local cluster [default: the CPUs this process may use].")
@click.option("--scheduler", default=None,
              help="Run on an existing cluster: its scheduler's address, tcp://HOST:8786 [default: "
                   "DASK_SCHEDULER_ADDRESS, else a local cluster].")
@click.option("--scheduler-file", default=None, type=click.Path(dir_okay=False),
              help="Run on an existing cluster through the file 'dask scheduler --scheduler-file F' wrote.")
@click.option("--force", is_flag=True, help="Replay and export takes whose outputs are already complete.")
@click.option("--retries", default=2, show_default=True,
              help="Runs again of a take whose storage errs (a take whose worker dies runs again elsewhere anyway).")
@click.option("--connect-timeout", default=30.0, show_default=True, help="Seconds to wait for the scheduler.")
@click.option("--backend", type=click.Choice(["auto", "opencl", "numpy"]), default="auto", show_default=True,
              help="As for replay, on every worker.")
@click.option("--device", default=None, help="As for replay: the OpenCL device on every worker.")
@click.option("--frames", "frames_text", default=None, help="Replay only rows A:B of every take.")
@click.option("--chunk", default=32, show_default=True, help="Frames evaluated together.")
@click.option("--head-motion", type=click.Choice(["keep", "remove"]), default="keep", show_default=True)
@click.option("--save-large-scale", is_flag=True, help="Also write large_scale.npy for every take.")
@click.option("--neutral-frame", type=int, default=None, help="As for replay, the same frame number in every take.")
@click.option("--neutral-take", type=click.Path(dir_okay=False), default=None, help="As for replay, for every take.")
@click.option("--take-units", default=None, help="Units of the takes (mm, cm, m, in), overriding what the files say.")
@click.option("--subject", default=None, help="Use this subject's markers when a take holds several.")
@click.option("--no-stabilise", is_flag=True, help="The takes are already in head space.")
@click.option("--no-clean", is_flag=True, help="No prior-based cleaning: gaps only interpolated (PCHIP).")
@click.option("--smooth", type=float, default=0.0, show_default=True,
              help="Temporal smoothing of the cleaned markers: Gaussian sigma in frames (0 = off).")
@mesh_cache_options
@landmark_take_options
@_common
@click.pass_context
def batch(ctx, takes, model_path, output, exports, workers, scheduler, scheduler_file, force, retries, connect_timeout,
          backend, device, frames_text, chunk, head_motion, save_large_scale, neutral_frame, neutral_take, take_units,
          subject, no_stabilise, no_clean, smooth, large_scale, rest_frame, cache_fps, camera_path, landmarks_path, lift,
          min_confidence, quiet, verbose):
    """Replay every TAKE (files, folders of takes, glob patterns) onto MODEL on a Dask cluster, as
    'facepipe replay' would one by one: OUTPUT/<take stem>/positions.npy and replay.json.

    Takes are marker takes, mesh caches (USD, MDD, PC2; an OBJ sequence is a folder of OBJ files
    or a frame_%04d.obj pattern, named after its folder) and 2D landmark takes (with --camera);
    each option applies to the takes it concerns.

    Takes whose outputs exist from the same model, take and options are skipped (--force redoes
    them); a take whose worker dies runs again elsewhere; a bad take is reported and the rest go on.
    Exit status: 0 every take done, 2 some failed (listed), 1 the cluster failed.
    """
    from facepipe.batch.jobs import ReplayOptions, run_batch
    from facepipe.batch.cluster import ClusterSpec

    rep = _reporter(ctx, quiet, verbose)
    checks = [(workers is None or workers >= 1, "--workers must be at least 1"), (chunk >= 1, "--chunk must be at least 1"),
              (smooth >= 0, "--smooth must be 0 (off) or a positive number of frames"),
              (retries >= 0, "--retries must be 0 or more"), (connect_timeout > 0, "--connect-timeout must be positive"),
              (cache_fps is None or cache_fps > 0, "--cache-fps must be positive"),
              (min_confidence is None or 0.0 <= min_confidence <= 1.0, "--min-confidence must be within 0..1")]
    for ok, message in checks:
        if not ok:
            raise InputError(message)
    options = ReplayOptions(backend=backend, device=device, frames=frames_text, chunk=chunk, head_motion=head_motion,
                            save_large=save_large_scale, neutral_frame=neutral_frame,
                            neutral_take=_absolute(neutral_take),
                            take_units=take_units, subject=subject, stabilise=not no_stabilise, clean=not no_clean,
                            smooth=smooth, large_scale=large_scale, rest_frame=rest_frame, cache_fps=cache_fps,
                            camera=_absolute(camera_path), landmarks=_absolute(landmarks_path), lift=lift,
                            min_confidence=min_confidence)
    cluster = ClusterSpec(workers=workers, scheduler=scheduler, scheduler_file=scheduler_file,
                          connect_timeout=connect_timeout)
    bars = []  # opened once the takes and the model are found good, so bad input is said alone

    def start(total):
        rep.say(f"batch of {total} takes on the {cluster.describe()}")
        bars.append(rep.bar(total, unit="take", desc="batch"))

    def progress(record):
        if record.status == "failed" and not rep.quiet:
            bars[0].write(f"failed: {record.name}: {record.error}")
        bars[0].update(1)

    try:
        result = run_batch(takes, model_path, output, options, exports=exports, force=force, cluster=cluster,
                           retries=retries, progress=progress, on_start=start)
    finally:
        for bar in bars:
            bar.close()
    _summary(rep, result, Path(output))
    return result.exit_status


def _absolute(path: str | None) -> str | None:
    """A path as every worker finds it, whatever its working directory."""
    return str(Path(path).resolve()) if path else None


def _summary(rep, result, out: Path) -> None:
    t = result.report["totals"]
    rate = f" ({t['takes_per_second'] * 60:.1f} takes/min)" if t["replayed"] and t["takes_per_second"] else ""
    rep.say(f"{t['takes']} takes: {t['ok']} done ({t['replayed']} replayed), {t['skipped']} skipped "
            f"(outputs complete), {t['failed']} failed in {t['seconds']:.1f} s{rate}"
            + (f"; {t['retried']} needed more than one attempt (a worker lost or a storage error: batch.json "
               "lists each attempt's)" if t["retried"] else ""))
    for record in result.failed:  # always listed, even with --quiet
        click.echo(f"failed: {record.take}: {record.error}", err=True)
    if result.cluster_error:
        click.echo(f"error: the cluster failed: {result.cluster_error}", err=True)
    rep.say(f"wrote {out / 'batch.json'}")
