"""Preview images without a display: shaded replay frames, error heat maps, the fit curve.

``facepipe preview OUTDIR -o preview.png`` renders, per chosen frame, the large-scale layer
and the final result side by side, and with ``--truth`` the truth and heat maps of the
per-vertex error of both layers on the truth's surface, on one colour scale. The face is
shown in head space (the take's head motion taken out) from the direction the face looks,
so frames line up. Rendering is :mod:`facepipe.core.render` (a NumPy z-buffer); the figure is
matplotlib with the Agg backend.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.colors import PowerNorm
from matplotlib.figure import Figure

from facepipe.io.atomic import atomic_path
from facepipe.errors import InputError
from facepipe.core.render import frame_camera, render, view_direction
from facepipe.export.common import check_targets
from facepipe.io.outputs import check_output_path
from facepipe.pipeline.evaluate import replay_truth, to_head_space
from facepipe.pipeline.replay import NumpyEvaluator

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pdf", ".svg")


def _figure(width_in: float, height_in: float, dpi: int = 100):
    # the object-oriented API with an Agg canvas: no pyplot state, no display needed
    fig = Figure(figsize=(width_in, height_in), dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def check_image_path(path: Path, force: bool) -> None:
    """InputError for an image name matplotlib cannot write, or an existing file without ``force``."""
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise InputError(f"cannot write a {path.suffix or 'suffix-less'} image", path=path,
                         hint=f"name it *{' or *'.join(IMAGE_SUFFIXES)} (video is not supported: use --strip for "
                              "several frames in one image)")
    check_targets([path], force, False)


def _save(fig, path: Path, force: bool) -> Path:
    path = Path(path)
    check_image_path(path, force)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lower().lstrip(".").replace("jpg", "jpeg"))
    return path


# ----------------------------------------------------------------------------- fit curve


def plot_tuning(report: dict, path: str | os.PathLike, units: str = "", force: bool = True) -> Path:
    """The validation errors of ``fit --tune`` as an image (see :func:`facepipe.pipeline.tune.tune_rig`).

    Left: the examples' large-scale error against k_stretch. Right: the cross-validated error of
    every (β, λ) candidate against the basis size, the large-scale-only level and the choice.
    """
    fig = _figure(10.5, 4.2, dpi=120)
    left, right = fig.subplots(1, 2)
    unit = f" ({units})" if units else ""
    shell = report["shell"]
    ks = [r["k_stretch"] for r in shell]
    floor = min([k for k in ks if k > 0], default=1.0) / 3
    left.plot([max(k, floor) for k in ks], [r["large_rms"] for r in shell], "-o", ms=4, color="tab:green")
    rejected = [r for r in shell if not r.get("accepted", True)]
    if rejected:
        left.plot([max(r["k_stretch"], floor) for r in rejected], [r["large_rms"] for r in rejected], "x",
                  ms=9, color="tab:red", label="rejected: an example worse than the default's")
    left.set_xscale("log")
    left.axvline(max(report["chosen"]["k_stretch"], floor), color="0.3", ls=":", label="chosen")
    left.set_xlabel("k_stretch (relative to the marker spacing; 0 drawn at the left edge)")
    left.set_ylabel(f"examples' large-scale RMS{unit}")
    left.set_title("Shell stiffness")
    left.grid(True, alpha=0.3)
    left.legend(fontsize=8)
    # one curve per (k, β, λ): the gate threshold τ that does best for it
    curves: dict = {}
    for r in report["details"]:
        key = (r["k_stretch"], r["beta_scale"], r["smoothing"])
        curves.setdefault(key, {}).setdefault(r.get("novelty_tau", 0.0), []).append((r["poses"], r["cv_rms"]))
    for (k, b, s), by_tau in sorted(curves.items()):
        t, pts = min(by_tau.items(), key=lambda item: min(e for _, e in item[1]))
        pts.sort()
        right.plot([p for p, _ in pts], [e for _, e in pts], "-", lw=1.2, label=f"k={k:g} β×{b:g} λ={s:g} τ={t:g}")
    chosen = report["chosen"]
    right.plot([chosen["poses"]], [chosen["cv_rms"]], "k*", ms=12, label="chosen")
    right.axhline(chosen["large_cv_rms"], color="0.4", ls=":", label="large scale only")
    right.set_xlabel("basis poses")
    if report.get("time_blocks"):  # chosen on the held-out time blocks of a performance
        right.set_ylabel(f"held-out time blocks' RMS{unit}")
        right.set_title(f"{report['method'].upper()} validation ({len(report['time_blocks'])} time blocks, "
                        f"{report['expression_folds']} expression folds)")
    else:
        right.set_ylabel(f"held-out RMS{unit}")
        right.set_title(f"{report['method'].upper()} cross-validation ({len(report['folds'])} folds)")
    right.grid(True, alpha=0.3)
    right.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    return _save(fig, Path(path), force)


def plot_fit_curves(report: dict, path: str | os.PathLike, units: str = "", force: bool = True) -> Path:
    """Training error against basis size (the fit report's ``curves``) as an image.

    Parameters
    ----------
    report : the fit report: ``curves`` {method: [{"poses", "mean_rms", "max_rms"}, …]} and
        ``large_scale_rms`` {"mean", "max"} (the error with no details at all).
    path : image file (.png, …), written atomically.
    units : length units for the axis label.

    Returns
    -------
    Path written.
    """
    fig = _figure(6.4, 4.2, dpi=120)
    ax = fig.subplots()
    colors = {"psd": "tab:blue", "wpsd": "tab:orange"}
    positive = []
    for method, curve in report.get("curves", {}).items():
        if not curve:
            continue
        x = [c["poses"] for c in curve]
        mean = [c["mean_rms"] for c in curve]
        mx = [c["max_rms"] for c in curve]
        color = colors.get(method)
        ax.plot(x, mean, "-o", ms=3.5, color=color, label=f"{method.upper()} mean over examples")
        ax.plot(x, mx, "--", color=color, alpha=0.7, label=f"{method.upper()} worst example")
        positive += [v for v in mean + mx if v > 0]
    large = report.get("large_scale_rms", {})
    if large.get("mean"):
        ax.axhline(large["mean"], color="0.4", ls=":", label="large scale only (mean)")
        positive.append(large["mean"])
    log, bottom, below = error_axis(positive)
    if log:
        ax.set_yscale("log")
        ax.set_ylim(bottom=bottom)
        if below:
            ax.text(0.99, 0.01, f"{below} value(s) below {bottom:.2g} (numerically zero) drawn at the axis' foot",
                    transform=ax.transAxes, ha="right", va="bottom", fontsize=7, color="0.3")
            for line in ax.get_lines():  # clipped to the foot rather than dropped off the plot
                y = np.asarray(line.get_ydata(), dtype=np.float64)
                line.set_ydata(np.maximum(y, bottom))
    ax.set_xlabel("basis poses added to the rest pose")
    ax.set_ylabel(f"training RMS of the details{f' ({units})' if units else ''}")
    ax.set_title("Fit error versus basis size")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, Path(path), force)


def error_axis(values, span: float = 1e4) -> tuple[bool, float | None, int]:
    """The scale of an error axis: (log scale?, its bottom, how many values lie below it).

    Errors spanning more than a factor of 20 go on a log axis. Its bottom is the smallest value
    within ``span`` of the largest: a fit that reproduces an example exactly has an error of
    rounding size (1e-17), and an axis down to it would squash every value that matters into its
    top few decades; such values are drawn at the foot and counted.
    """
    positive = [float(v) for v in values if v > 0]
    if not positive or max(positive) / min(positive) <= 20:
        return False, None, 0
    top = max(positive)
    significant = [v for v in positive if v >= top / span]
    bottom = min(significant) / 1.5
    return True, bottom, sum(v < bottom for v in values if v is not None)


# ----------------------------------------------------------------------------- replay preview


def pick_frames(head: np.ndarray, rest_handles: np.ndarray, count: int = 1) -> np.ndarray:
    """Frame indices to show: the most expressive (largest mean handle motion from rest)
    for one, or ``count`` evenly spaced ones over the take.

    Returns
    -------
    (count,) int64 frame indices, increasing.
    """
    T = head.shape[0]
    if count <= 1:
        motion = np.linalg.norm(head - rest_handles[None], axis=2).mean(axis=1)
        return np.array([int(np.argmax(motion))])
    return np.unique(np.round(np.linspace(0, T - 1, min(count, T))).astype(np.int64))



def preview_replay(outdir, model_path, path, *, view: str = "auto", truth_path=None, frame_numbers=None,
                   strip: int = 0, size: int = 420, force: bool = False) -> dict:
    """``facepipe preview``: the camera view of a 2D take's replay
    (:func:`facepipe.cli.video_preview.render_camera_preview`), the head-space view
    (:func:`render_preview`) or a classified take's appearance
    (:func:`facepipe.cli.appearance_preview.render_appearance_preview`); ``view`` "auto" takes the
    appearance view for a folder with appearance.csv and no replay, the camera view where the
    replay has one."""
    from facepipe.cli.appearance_preview import is_classified, render_appearance_preview
    from facepipe.cli.video_preview import render_camera_preview
    from facepipe.io.replay_folder import ReplayDir

    check_output_path(path, kind="file", what="preview image")
    if view == "appearance" or (view == "auto" and is_classified(outdir) and not (Path(outdir) / "replay.json").is_file()):
        return render_appearance_preview(outdir, path, model_path=model_path, frame_numbers=frame_numbers, strip=strip,
                                         size=size, force=force)
    replay = ReplayDir(outdir)
    model = replay.load_model(model_path)
    if view == "auto":
        view = "camera" if replay.video is not None and truth_path is None else "head"
    if view == "camera":
        if truth_path is not None:
            raise InputError("--truth is drawn in head space, not through the camera", path=truth_path,
                             hint="add --view head for the truth and the error heat maps")
        return render_camera_preview(replay, model, path, frame_numbers=frame_numbers, strip=strip, size=size,
                                     force=force)
    return dict(render_preview(replay, model, path, truth_path=truth_path, frame_numbers=frame_numbers, strip=strip,
                               size=size, force=force), view="head")


def render_preview(replay, model, path: str | os.PathLike, *, truth_path=None, frame_numbers=None, strip: int = 0,
                   size: int = 420, force: bool = False, log=None) -> dict:
    """Render a replay's preview image.

    Parameters
    ----------
    replay : facepipe.io.replay_folder.ReplayDir.
    model : its Model (rest mesh, triangles, handles; the large scale is evaluated again from
        the handles when the replay has no large_scale.npy).
    path : image to write (.png, …), atomically; not overwritten without ``force``.
    truth_path : optional truth .npz (``positions`` in the take's space, ``frame``).
    frame_numbers : take frame numbers to show (one row each); default: ``strip`` evenly
        spaced frames, or the most expressive frame.
    size : pixel width of one panel.

    Returns
    -------
    dict with the frames shown and, with a truth, their RMS/max errors per layer.
    """
    path = Path(path)
    check_image_path(path, force)  # before any rendering: a refused preview costs nothing
    all_frames = replay.frame_numbers
    index = _shown_frames(replay, replay.handles["head"], model, frame_numbers, strip)
    final, large, truth = _head_space_surfaces(replay, model, index, truth_path)
    faces = model.triangles.astype(np.int64)
    camera = frame_camera(model.rest.astype(np.float64), view_direction(model), width=size)
    units = model.meta.get("units", "")
    columns = ["large scale", "final"] + (["truth", "|final − truth|", "|large − truth|"] if truth else [])
    summary = {"frames": [int(all_frames[i]) for i in index], "panels": columns}
    errors = None
    if truth:
        errors = ([np.linalg.norm(f - t, axis=1) for f, t in zip(final, truth)],
                  [np.linalg.norm(g - t, axis=1) for g, t in zip(large, truth)])
        summary.update(error_summary(*errors))
        cmap = colormaps["YlOrRd"]
        # one scale for both layers (comparable colours), square-root so the final layer's
        # small errors still show next to the large-scale layer's big ones
        norm = PowerNorm(0.5, 0.0, summary["color_max"])

    bar_w = 0.95 if truth else 0.0  # room on the right for the colour bar and its label
    fig, axes = _panel_grid(camera, len(index), len(columns), bar_w)
    for r, i in enumerate(index):
        images = [render(large[r], faces, camera), render(final[r], faces, camera)]
        titles = ["large scale", "final"]
        if truth:
            images.append(render(truth[r], faces, camera))
            titles.append("truth")
            for label, err in (("final", errors[0][r]), ("large", errors[1][r])):
                images.append(render(truth[r], faces, camera, colors=cmap(norm(err))[:, :3]))
                rms = np.sqrt((err ** 2).mean())
                titles.append(f"|{label} − truth|: RMS {rms:.3g}, max {err.max():.3g} {units}")
        for c, (img, title) in enumerate(zip(images, titles)):
            ax = axes[r, c]
            ax.imshow(img, interpolation="antialiased")
            ax.set_axis_off()
            ax.set_title((f"frame {int(all_frames[i])}: " if c == 0 else "") + title, fontsize=8)
    if truth:
        fig_w = fig.get_figwidth()
        cax = fig.add_axes((1 - bar_w / fig_w + 0.12 / fig_w, 0.08, 0.16 / fig_w, 0.8))
        label = f"vertex error ({units})" if units else "vertex error"
        largest = max(max(summary["max"]["final"]), max(summary["max"]["large"]))
        clipped = largest > summary["color_max"]
        if clipped:  # the scale stops at the 99.5th percentile: say so, and what lies beyond
            label += f"; clipped at {summary['color_max']:.3g} (largest {largest:.3g})"
        fig.colorbar(ScalarMappable(norm, cmap), cax=cax, label=label, extend="max" if clipped else "neither")
        summary["color_clipped"] = bool(clipped)
    _save(fig, path, force)
    summary["path"] = str(path)
    return summary


def _shown_frames(replay, head: np.ndarray, model, frame_numbers, strip: int) -> np.ndarray:
    """Indices of the replay's frames to show: the given take frame numbers (InputError for one
    the replay lacks), else ``strip`` evenly spaced ones or the most expressive one (``head``:
    the replay's head-space handles)."""
    all_frames = replay.frame_numbers
    if frame_numbers:
        lookup = {int(f): i for i, f in enumerate(all_frames)}
        missing = [f for f in frame_numbers if int(f) not in lookup]
        if missing:
            raise InputError(f"the replay has no frame {missing[0]} (it has {all_frames[0]}..{all_frames[-1]})",
                             path=replay.path / "replay.json", hint="give a frame number of the take")
        return np.array([lookup[int(f)] for f in frame_numbers])
    rest_handles = model.rest[model.handle_vertices].astype(np.float64)
    return pick_frames(head.astype(np.float64), rest_handles, max(1, strip))



def _head_space_surfaces(replay, model, index: np.ndarray, truth_path) -> tuple[list, list, list | None]:
    """The final and large-scale surfaces, and the truth if given, of the frames ``index`` in head
    space (the take's head motion taken out where the replay kept it). The large scale is
    evaluated from the handles when the replay has no large_scale.npy."""
    handles = replay.handles
    keep = handles["head_motion"] == "keep"
    R = handles["rotation"].astype(np.float64)
    tr = handles["translation"].astype(np.float64)

    def to_head(x, i):
        return to_head_space(x, R[i], tr[i]) if keep else np.asarray(x, dtype=np.float64)

    final = [to_head(replay.positions[i], i) for i in index]
    if replay.large_scale is not None:
        large = [to_head(replay.large_scale[i], i) for i in index]
    else:
        _, lg = NumpyEvaluator(model).evaluate(handles["head"][index].astype(np.float64), with_large=True)
        large = list(lg)
    truth = None
    if truth_path is not None:
        known = replay_truth(truth_path, replay, model.n_vertices)
        truth = [known.head(i, to_head) for i in index]
    return final, large, truth


def error_summary(e_final: list[np.ndarray], e_large: list[np.ndarray]) -> dict:
    """RMS and max of the per-vertex errors of both layers per frame, and the colour scale's top
    (the 99.5th percentile over both)."""
    return {"rms": {"final": [float(np.sqrt((e ** 2).mean())) for e in e_final],
                    "large": [float(np.sqrt((e ** 2).mean())) for e in e_large]},
            "max": {"final": [float(e.max()) for e in e_final], "large": [float(e.max()) for e in e_large]},
            "color_max": float(np.percentile(np.concatenate(e_large + e_final), 99.5)) or 1e-12}


def _panel_grid(camera, rows: int, columns: int, bar_w: float, dpi: int = 100):
    """A figure of rows × columns panels of the camera's size, a title above each, and ``bar_w``
    inches on the right for a colour bar: (figure, (rows, columns) axes)."""
    panel_w, panel_h = camera.width / dpi, camera.height / dpi
    title_h = 0.32
    fig_w = panel_w * columns + bar_w
    fig_h = (panel_h + title_h) * rows
    fig = _figure(fig_w, fig_h, dpi)
    fig.subplots_adjust(left=0.0, right=1 - bar_w / fig_w, top=1 - title_h / fig_h, bottom=0.0, wspace=0.0,
                        hspace=title_h / panel_h)
    return fig, np.atleast_2d(fig.subplots(rows, columns, squeeze=False))
