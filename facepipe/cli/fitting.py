"""``facepipe fit`` and ``facepipe bake``: the validated choice of parameters, the fit, the report.

By default both choose the rig's parameters by validation on its examples
(:func:`facepipe.pipeline.tune.choose_parameters`) whenever the examples allow it, and say what
was chosen and why; otherwise (or with ``--no-tune``) they fit with the config's values, with a
warning when validation was wanted but impossible.
"""

from __future__ import annotations

import time
from pathlib import Path

from facepipe.errors import InputError
from facepipe.io.config import load_config
from facepipe.io.outputs import check_output_path
from facepipe.io.model_file import add_model_arrays, fit_to_model, geometry_to, model_arrays, save_fit
from facepipe.io.npz_file import NpzWriter
from facepipe.cli.progress import StageBar
from facepipe.pipeline.fit import FIT_STAGES, fit_config
from facepipe.pipeline.tune import choose_parameters


def run_fit(config, rep, tune: bool = True, on_geometry=None):
    """Load the rig, choose its parameters by validation (``tune``), fit: (rig, FitResult).

    The validation's report is ``fit.report["tune"]`` when it ran; ``fit.report["validation"]``
    says whether it did and, if not, why. ``on_geometry``: see
    :func:`~facepipe.pipeline.fit.fit_rig`."""
    t0 = time.perf_counter()
    choice = {}

    def prepare(rig, geodesics):
        rep.say(f"rig: {rig.mesh.n_vertices} vertices, {len(rig.handles)} handles, {len(rig.anchors)} anchors, "
                f"{len(rig.example_names)} example poses")
        if rig.welded:
            w = rig.welded
            rep.say(f"note: [rig] weld: {w['split']} vertices split along seams welded, so the rig, its model and "
                    f"outputs have {w['welded']} vertices (the mesh file {w['vertices']})")
        choice["report"] = choose_parameters(rig, tune, progress=_progress_bars(rep), geodesics=geodesics)
        say_choice(rep, choice["report"], rig.config.units)

    def progress(method, n, curve):
        rep.detail(f"  {method}: {n:2d} poses  mean RMS {curve['mean_rms']:.4f}  max {curve['max_rms']:.4f}")

    config = load_config(config)  # a missing or malformed config is said alone, before any bar
    # the validation's bars appear under the steps' bar, in its second step
    with StageBar(len(FIT_STAGES), "fit", quiet=rep.quiet) as steps:
        rig, fit = fit_config(config, progress=progress, prepare=prepare, stage=steps.step, early_basis=not tune,
                              on_geometry=on_geometry)
    rep.detail(solver_line(fit.report["deformer"], fit.report["shell_solver"], fit.report["shell_solver_passed_over"]))
    report = choice["report"]
    if report["validated"]:
        fit.report["tune"] = {k: v for k, v in report.items() if k != "validated"}
    fit.report["validation"] = {"validated": report["validated"]} if report["validated"] else report
    fit.report["seconds"]["total"] = time.perf_counter() - t0
    return rig, fit


def _progress_bars(rep):
    """progress(stage, done, total) of the validation as one bar per stage (totals may shrink)."""
    bars = {}

    def step(stage, done, total):
        if stage not in bars:
            bars[stage] = rep.bar(total, unit="fit" if stage == "details" else "shell", desc=f"validate {stage}")
        bar = bars[stage]
        bar.total = total
        bar.update(done - bar.n)
        if done >= total:
            bar.close()

    return step


def say_choice(rep, report: dict, units: str) -> None:
    """What validation chose and why, or why it did not run (a warning where it was wanted)."""
    if not report["validated"]:
        if report["reason"] != "disabled":
            rep.say(f"warning: parameters not validated ({report['reason']}); fitting with the config's values")
        return
    if report.get("time_blocks"):
        say_performance_choice(rep, report, units)
        return
    c, d = report["chosen"], report["default"]
    rep.say(f"validated in {report['seconds']['total']:.1f} s on {len(report['folds'])} folds of held-out "
            f"expressions: k_stretch {c['k_stretch']:g}, β ×{c['beta_scale']:g}, λ {c['smoothing']:g}, "
            f"τ {c['novelty_tau']:g}, P {c['poses']}" + _strain_choice(c))
    rep.say(f"  why: held-out RMS {c['cv_rms']:.4f} {units} against {d['cv_rms']:.4f} with the config's values "
            f"and {c['large_cv_rms']:.4f} with the large scale alone; the largest basis (then the strongest "
            f"novelty gate) among the candidates within a standard error of the best, no held-out expression "
            f"worse than with the config's values by more than {100 * report['max_regression']:g} %")
    if report.get("stopped_early"):
        rep.detail(f"  {len(report['stopped_early'])} candidates stopped early, clearly worse on the first folds")
    if report["harm"]:
        what = "details turned off ([psd] method = none)" if report["fallback"] else \
            "kept, as [tune] fallback = false"
        rep.say(f"warning: the validated error with details is above the large-scale-only error by more than "
                f"{100 * report['max_regression']:g} %: the details would do harm on unseen expressions; {what}")


def _strain_choice(chosen: dict) -> str:
    """The local-strain model's validated kernel width and ridge, where it has them."""
    if "strain_width" not in chosen:
        return ""
    return f", strain kernel σ {chosen['strain_width']:g}, ridge {chosen['strain_ridge']:g}"


def say_performance_choice(rep, report: dict, units: str) -> None:
    """What validation on held-out time blocks of the training performance (and held-out
    expressions) chose and why."""
    c, d = report["chosen"], report["default"]
    n_blocks, n_expr = len(report["time_blocks"]), report["expression_folds"]
    rep.say(f"validated in {report['seconds']['total']:.1f} s on {n_blocks} held-out time blocks of the performance"
            + (f" and {n_expr} folds of held-out expressions" if n_expr else "")
            + f": k_stretch {c['k_stretch']:g}, β ×{c['beta_scale']:g}, λ {c['smoothing']:g}, "
              f"τ {c['novelty_tau']:g}, P {c['poses']}" + _strain_choice(c))
    rep.say(f"  new mixtures (held-out time blocks): RMS {c['cv_rms']:.4f} {units} against {d['cv_rms']:.4f} with "
            f"the config's values and {c['large_cv_rms']:.4f} with the large scale alone")
    if n_expr:
        rep.say(f"  new expressions (held out whole): RMS {c['expression_cv_rms']:.4f} against "
                f"{c['expression_large_rms']:.4f} with the large scale alone; worst held-out expression "
                f"{100 * (c['worst_expression_vs_large'] - 1):+.1f} % against its large scale")
    if not c.get("no_harm", True):
        rep.say(f"warning: every candidate makes some held-out expression worse than its large scale alone by more "
                f"than {100 * report['max_regression']:g} %; chose the one that does least harm")
    rep.say("  why: the smallest error on held-out time blocks (new mixtures of the examples' expressions) among "
            "the candidates that make no held-out expression worse than the large scale alone by more than "
            f"{100 * report['max_regression']:g} %")
    if report["harm"]:
        what = "details turned off ([psd] method = none)" if report["fallback"] else \
            "kept, as [tune] fallback = false"
        rep.say(f"warning: on held-out time blocks the details are worse than the large scale alone by more than "
                f"{100 * report['max_regression']:g} %; {what}")


def solver_line(deformer: str, solver: str | None, passed_over: dict | None = None) -> str:
    """Which sparse solver factored the shell, and the ones passed over before it (--verbose)."""
    if deformer == "rbf":
        return "large scale: RBF volume morph (dense solve)"
    if solver is None:
        return "shell solver: none (every vertex prescribed, nothing to factor)"
    skipped = "; ".join(f"{name} passed over: {why}" for name, why in (passed_over or {}).items())
    return f"shell solver: {solver}" + (f" ({skipped})" if skipped else "")


def print_fit_summary(rep, fit, units: str) -> None:
    r = fit.report
    rep.say(f"feature graph: F = {r['feature_edges']} edges; marker spacing {r['marker_spacing']:.3f} {units}; "
            f"WPSD β = {r['beta']:.3f}/{units}, {r['edges_per_vertex_mean']:.1f} edges per vertex")
    if r.get("vertices_without_edges"):
        rep.say(f"note: {r['vertices_without_edges']} vertices lie in parts of the mesh that no marker reaches (e.g. "
                "eyeballs or teeth, held by their anchors): they move with the head and get no details")
    rep.say(f"large-scale only: training RMS mean {r['large_scale_rms']['mean']:.4f} {units}")
    for method, curve in r["curves"].items():
        pts = "  ".join(f"P={c['poses']}:{c['mean_rms']:.4f}" for c in curve
                        if c["poses"] in (0, 1, 2, 3, 6, 12) or c is curve[-1])
        rep.say(f"{method.upper():5s} training RMS by basis size: {pts}")
    rep.say(f"basis ({r['method']}): {', '.join(r['basis'])}")
    if "holdout" in r:
        h = r["holdout"]["summary"]
        rep.say(f"held-out examples ({h['folds']} folds): large-scale RMS {h['large_rms_mean']:.4f}, final "
                f"{h['final_rms_mean']:.4f} {units}; worst change {100 * h['worst_harm']:+.1f} %, "
                f"{h['examples_made_worse_over_2pct']} made worse by more than 2 %")


def fit_command(rep, config: str, output: str, holdout: int, tune: bool, write_json) -> None:
    """The body of ``facepipe fit``."""
    from facepipe.cli.preview import plot_fit_curves, plot_tuning

    check_output_path(output, kind="file", what="fit file")
    rig, result = run_fit(config, rep, tune=tune)
    if holdout:
        from facepipe.pipeline.cross_validation import holdout_errors

        with rep.bar(0, unit="fold", desc="holdout") as bar:
            def step(i, n):
                bar.total = n
                bar.update(1)

            result.report["holdout"] = holdout_errors(rig, holdout, progress=step)
    save_fit(output, result, rig)
    report_path = Path(output).with_suffix(".json")
    write_json(report_path, result.report)
    plot_path = plot_fit_curves(result.report, Path(output).with_suffix(".png"), units=rig.config.units)
    if "tune" in result.report:
        write_json(Path(output).with_suffix(".tune.json"), result.report["tune"])
        plot_tuning(result.report["tune"], Path(output).with_suffix(".tune.png"), units=rig.config.units)
    print_fit_summary(rep, result, rig.config.units)
    rep.say(f"wrote {output}, {report_path} and {plot_path} ({result.report['seconds']['total']:.1f} s)")


def bake_command(rep, source: str, output: str, tune: bool) -> None:
    """The body of ``facepipe bake``: from a FIT.npz (its choice carried over) or a CONFIG (fitted,
    validated by default, here)."""
    check_output_path(output, kind="file", what="model file")
    t0 = time.perf_counter()
    if source.endswith(".npz"):
        if not Path(source).is_file():
            raise InputError("fit file not found", path=source, hint="write it with 'facepipe fit CONFIG -o FIT.npz', "
                                                                     "or bake from the config itself")
        with StageBar(2, "bake", quiet=rep.quiet) as steps:
            meta = fit_to_model(source, output, stage=steps.step)
        shell = meta.get("shell", {})
        rep.detail(solver_line(shell.get("method", "shell"), shell.get("solver", "not recorded (an older fit file)")))
    else:
        with NpzWriter(output) as npz:  # the geometry is written while the details are fitted
            rig, result = run_fit(source, rep, tune=tune, on_geometry=geometry_to(npz))
            arrays, meta = model_arrays(result, rig)
            add_model_arrays(npz, arrays, meta)
        print_fit_summary(rep, result, rig.config.units)
    size = Path(output).stat().st_size / 1e6
    rep.say(f"wrote {output}: method {meta['method']}, {len(meta['basis']) - 1} basis poses, "
            f"{size:.1f} MB ({time.perf_counter() - t0:.1f} s)")
