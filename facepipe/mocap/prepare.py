"""From a read take to clean head-space handles: align, stabilise, clean, and say what was done.

:func:`prepare_take` is the pipeline ``replay`` runs between reading a take and evaluating the
model:

1. **alignment** to the rig: a similarity (scale, rotation, translation; Umeyama, robustly
   reweighted) from a neutral reference — a frame of the take (``neutral_frame``), a
   separate neutral take, or by default the rig's rest pose itself — to the rest-pose
   handles. With a neutral reference, each marker's offset from its rest position (where the
   actor's markers sit relative to the rig's) is removed, so only motion drives the face.
   A scale far from 1 is a unit mismatch (mm read as cm) and an error naming the likely
   unit, never a silent rescale;
2. **head stabilisation**: the per-frame rigid head motion, fitted robustly (see
   :mod:`facepipe.mocap.cleaning`: jointly with the expression when cleaning, else a reweighted
   Kabsch of the stable markers);
3. **cleaning** (:func:`facepipe.mocap.cleaning.clean_take`): noise, outliers and gaps through the
   rig's prior — or, with cleaning off, gaps filled by PCHIP only.

The head motion returned maps the rig's head space to the take's space (rigid, at the
rig's scale), so ``world = R @ head + t`` puts the output where the take's face is.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from facepipe.mocap.cleaning import CleanOptions, clean_take, sample_counts
from facepipe.errors import InputError
from facepipe.mocap.gaps import fill_gaps
from facepipe.mocap.markers import known_unit_ratios
from facepipe.mocap.take import Take
from facepipe.core.rigid import interpolate_poses, robust_rigid_fit, similarity_fit, stable_marker_pose

__all__ = ["CLEAN_WINDOW", "PrepareOptions", "PreparedTake", "clean_margin", "prepare_take", "prepare_take_windows",
           "summary_lines"]

#: Takes longer than this many frames (and the context) are cleaned window by window.
CLEAN_WINDOW = 4096

#: Faces differ in size, units by factors of 2.54 or more: a scale outside this range is a
#: unit mismatch (or not a face), never silently applied.
SCALE_RANGE = (0.75, 1.33)


@dataclass
class PrepareOptions:
    """Options of :func:`prepare_take`.

    Attributes
    ----------
    neutral_frame : int or None
        Frame number (as in the take's frame column) where the actor holds a neutral face.
    neutral_take : Take or None
        A separate take of the neutral face (same markers, read in the rig's units).
    stabilise : bool
        Remove the head's rigid motion (False: the take is taken to be in head space).
    clean : bool
        Clean through the rig's prior (False: gaps filled by PCHIP only, nothing else).
    frames : slice or None
        Rows of the take to prepare (the neutral frame may lie outside them).
    clean_options : CleanOptions
    """

    neutral_frame: int | None = None
    neutral_take: Take | None = None
    stabilise: bool = True
    clean: bool = True
    frames: slice | None = None
    clean_options: CleanOptions = field(default_factory=CleanOptions)


def _robust_similarity(source: np.ndarray, target: np.ndarray, iterations: int = 8):
    """Similarity target ≈ s Q source + b over the finite points, Cauchy-reweighted."""
    ok = np.isfinite(source).all(axis=1) & np.isfinite(target).all(axis=1)
    src, tgt = np.where(ok[:, None], source, 0.0), np.where(ok[:, None], target, 0.0)
    w = ok.astype(np.float64)
    floor = 1e-6 * (1.0 + float(np.abs(tgt).max(initial=0.0)))
    for _ in range(iterations):
        s, Q, b = similarity_fit(src, tgt, w)
        r = np.linalg.norm(s * src @ Q.T + b - tgt, axis=1)
        c = 2.5 * max(1.4826 * float(np.median(r[ok])), floor)
        w = ok / (1.0 + (r / c) ** 2)
    s, Q, b = similarity_fit(src, tgt, w)
    return float(s), Q, b


def _neutral_from_take(neutral: Take) -> np.ndarray:
    """(H, 3) median neutral markers of a neutral take, in the space of its first usable frame."""
    pos = neutral.positions
    vis = np.isfinite(pos).all(axis=-1)
    rows = np.flatnonzero(vis.sum(axis=1) >= 3)
    if rows.size == 0:
        raise InputError("the neutral take has no frame with 3 visible markers", path=neutral.path,
                         hint="record a neutral take with the markers visible")
    ref = pos[rows[0]]
    R, t, _ = robust_rigid_fit(np.where(np.isfinite(ref), ref, np.nan), pos[rows])
    good = np.isfinite(t).all(axis=1)
    R, t = R[good], t[good]
    back = np.einsum("nji,nhj->nhi", R, pos[rows[good]] - t[:, None, :])  # into the first frame's space
    never = np.isnan(back).all(axis=0)  # a marker never visible stays NaN (0 spares numpy an empty median)
    return np.where(never, np.nan, np.nanmedian(np.where(never, 0.0, back), axis=0))


def _unit_error(scale: float, take: Take, rig_units: str, what: str) -> InputError:
    source = take.source_units or rig_units
    ratios = known_unit_ratios(source)
    unit = min(ratios, key=lambda u: abs(np.log(scale) - np.log(ratios[u])))
    told = "as the file declares" if take.units and take.source_units and take.format != "facepipe-csv" else \
        "as assumed (the file does not say)"
    if abs(np.log(scale) - np.log(ratios[unit])) < np.log(1.25) and unit != source:
        return InputError(
            f"unit mismatch: the take's face is {1 / scale:.3g}× the size of the rig's ({what}): the take seems to "
            f"be in {unit}, not in {source} {told}",
            path=take.path,
            hint=f"pass --take-units {unit} (the rig is in {rig_units})",
        )
    return InputError(
        f"the take's face is {1 / scale:.3g}× the size of the rig's ({what}); no unit explains it",
        path=take.path,
        hint="check that the take is of this rig's markers and in the units it declares (--take-units), "
        "or give a neutral reference (--neutral-frame / --neutral-take)",
    )


def prepare_take(take: Take, model, options: PrepareOptions | None = None, window: int | None = None):
    """Clean head-space handles and head motion of a take, and a report of what was done.

    The whole selection at once; :func:`prepare_take_windows` gives it window by window (what
    replay streams). Parameters, returns and errors as there.
    """
    prepared = prepare_take_windows(take, model, options, window)
    parts = list(prepared.windows())
    head, R, t = (np.concatenate([p[i] for p in parts]) for i in range(3))
    return head, R, t, prepared.report()


def prepare_take_windows(take: Take, model, options: PrepareOptions | None = None,
                         window: int | None = None) -> "PreparedTake":
    """Clean head-space handles and head motion of a take, and a report of what was done, as a
    :class:`PreparedTake`: its windows are cleaned as they are asked for.

    Alignment, the checks of the take and the choice of windows happen here (their errors are
    raised here); cleaning waits for :meth:`PreparedTake.windows`.

    A take of more than ``window`` frames (default :data:`CLEAN_WINDOW`; plus the context) is
    cleaned window by window: each window with :func:`clean_margin` frames of context on both
    sides and its own noise statistics, so cleaning needs memory for one window, not the take,
    and replay evaluates one window while the next is cleaned. A shorter take (and one replayed
    with cleaning off) is prepared whole.

    Parameters
    ----------
    take : Take
        Read with the model's marker names in the rig's units (:func:`facepipe.mocap.read_take`
        with ``units=model.meta["units"]``); absent markers may be all-NaN columns.
    model : facepipe.io.model_file.Model
        Uses ``rest``, ``handle_vertices``, ``stable``, ``example_handles``,
        ``meta["marker_spacing"]`` and ``meta["units"]``.
    options : PrepareOptions

    Returns (:func:`prepare_take`; the windows of :class:`PreparedTake` hold the same in parts)
    -------
    head : (T, H, 3) float64
        Handle positions in head (rig) space relative to the rest pose, no NaN.
    R, t : (T, 3, 3), (T, 3)
        world = R @ head + t in the take's space (rigid; rig scale).
    report : dict
        JSON-serialisable: ``alignment``, ``head_motion``, ``cleaning`` and per-marker
        ``markers`` counts, ``total``, ``notes`` (fallbacks taken).

    Raises
    ------
    InputError
        Unit mismatch, a neutral frame not in the take, a marker never visible without
        cleaning, no usable frame, no pose anywhere.

    Example
    -------
    >>> take = read_take("take.c3d", model.marker_names, units=model.meta["units"])  # doctest: +SKIP
    >>> head, R, t, report = prepare_take(take, model, PrepareOptions(neutral_frame=0))  # doctest: +SKIP
    """
    opt = options or PrepareOptions()
    window = CLEAN_WINDOW if window is None else int(window)
    rig = _Rig.of(model, take)
    if take.positions.shape[1] != len(rig.rest):
        raise ValueError(f"take has {take.positions.shape[1]} markers, the model {len(rig.rest)}")
    notes: list[str] = []
    alignment = _align(take, rig, opt, notes)
    rows = np.arange(take.n_frames)[opt.frames] if opt.frames is not None else np.arange(take.n_frames)
    if rows.size == 0:
        raise InputError(f"the frame range selects none of the take's {take.n_frames} frames", path=take.path,
                         hint=f"choose rows within 0:{take.n_frames} with --frames A:B")
    if not np.isfinite(take.positions).all(axis=-1).any():
        raise InputError("no marker is visible in the selected frames", path=take.path,
                         hint="choose other frames with --frames")
    return PreparedTake(take, rig, opt, alignment, _choose_windows(take, rows, opt, window, notes), rows, notes)


@dataclass(frozen=True)
class _Rig:
    """What preparing a take needs of the model."""

    rest: np.ndarray  # (H, 3) rest-pose handles
    stable: np.ndarray  # (H,) bool
    basis: np.ndarray  # (K, H, 3) the examples' handle displacements
    spacing: float  # typical marker spacing
    units: str

    @classmethod
    def of(cls, model, take: Take) -> "_Rig":
        prior = np.asarray(model.example_handles, dtype=np.float64)
        return cls(rest=model.rest[model.handle_vertices].astype(np.float64),
                   stable=np.asarray(model.stable, dtype=bool), basis=prior[1:] - prior[0],
                   spacing=float(model.meta.get("marker_spacing") or 1.0),
                   units=model.meta.get("units") or take.units or "")


@dataclass(frozen=True)
class _Alignment:
    """The take's markers to the rig: x_rig = s Q x_take + b from a neutral reference (identity
    without one), and each marker's offset from its rest position."""

    s: float
    Q: np.ndarray
    b: np.ndarray
    offsets: np.ndarray  # (H, 3)
    from_neutral: bool
    report: dict

    def to_rig(self, world: np.ndarray) -> np.ndarray:
        """(n, H, 3) markers of the take in the rig's space."""
        return self.s * np.einsum("ij,thj->thi", self.Q, world) + self.b if self.from_neutral else world

    def to_take_space(self, R: np.ndarray, t: np.ndarray, rest: np.ndarray):
        """Head motion in the take's space: undo the alignment (rigid part, rig scale)."""
        if not self.from_neutral:
            return R, t
        Q, b, s = self.Q, self.b, self.s
        c = rest.mean(axis=0)
        Rw = np.einsum("ji,tjk->tik", Q, R)
        return Rw, np.einsum("ji,tj->ti", Q, np.einsum("tij,j->ti", R, c) + t - b) / s - np.einsum("tij,j->ti", Rw, c)


def _align(take: Take, rig: _Rig, opt: PrepareOptions, notes: list[str]) -> _Alignment:
    """The alignment to the rig from the neutral reference of ``opt`` (the rest pose by default,
    where only the sizes are checked); refuses a scale that is a unit mismatch."""
    neutral, source = _neutral_reference(take, opt)
    if neutral is None:
        report = {"reference": source}
        scale = _size_check(take, rig)
        if scale is not None:
            report["scale_check"] = scale
        report["units"] = {"take": take.source_units, "rig": rig.units}
        H = len(rig.rest)
        return _Alignment(1.0, np.eye(3), np.zeros(3), np.zeros((H, 3)), False, report)
    return _align_to_neutral(take, rig, neutral, source, notes)


def _neutral_reference(take: Take, opt: PrepareOptions):
    """(H, 3) the neutral markers of ``opt`` (None: the rest pose is the reference) and what they are."""
    if opt.neutral_frame is not None and opt.neutral_take is not None:
        raise InputError("give either a neutral frame or a neutral take, not both")
    if opt.neutral_frame is not None:
        hit = np.flatnonzero(take.frames == int(opt.neutral_frame))
        if hit.size == 0:
            raise InputError(f"neutral frame {opt.neutral_frame} is not in the take (frames "
                             f"{int(take.frames[0])}..{int(take.frames[-1])})", path=take.path,
                             hint="--neutral-frame takes a frame number of the take's frame column")
        return take.positions[int(hit[0])], f"frame {int(opt.neutral_frame)}"
    if opt.neutral_take is not None:
        return _neutral_from_take(opt.neutral_take), f"take {opt.neutral_take.path}"
    return None, "rest pose"


def _align_to_neutral(take: Take, rig: _Rig, neutral: np.ndarray, source: str, notes: list[str]) -> _Alignment:
    """The similarity from the neutral markers to the rest pose, and the markers' offsets from it."""
    rest, names = rig.rest, take.marker_names
    seen = np.isfinite(neutral).all(axis=1)
    if seen.sum() < 3:
        raise InputError(f"the neutral reference ({source}) has fewer than 3 visible markers", path=take.path,
                         hint="choose a neutral frame where the markers are visible")
    s, Q, b = _robust_similarity(neutral, rest)
    if not SCALE_RANGE[0] < s < SCALE_RANGE[1]:
        raise _unit_error(s, take, rig.units, f"similarity from the neutral {source}")
    offsets = np.zeros((len(rest), 3))
    offsets[seen] = (s * neutral @ Q.T + b)[seen] - rest[seen]
    lost = [names[m] for m in np.flatnonzero(~seen)]
    if lost:
        notes.append(f"{len(lost)} marker(s) not visible in the neutral reference keep the rig's rest position: "
                     + ", ".join(lost[:8]) + (" ..." if len(lost) > 8 else ""))
    off = np.linalg.norm(offsets, axis=1)
    report = {"reference": source, "scale": s,
              "rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(Q) - 1) / 2, -1, 1)))),
              "translation": b.tolist(), "offsets_rms": float(np.sqrt(np.mean(off[seen] ** 2))),
              "offsets_max": float(off.max()), "offsets_max_marker": names[int(np.argmax(off))],
              "units": {"take": take.source_units, "rig": rig.units}}
    return _Alignment(s, Q, b, offsets, True, report)


def _size_check(take: Take, rig: _Rig) -> float | None:
    """The median scale of similarities from frames of the take to the rest pose (None without a
    frame of 4 markers); refuses one that is a unit mismatch."""
    vis = np.isfinite(take.positions).all(axis=-1)
    rows = np.flatnonzero(vis.sum(axis=1) >= 4)
    if not rows.size:
        return None
    pick = rows[np.linspace(0, rows.size - 1, min(rows.size, 32)).astype(int)]
    scale = float(np.median([_robust_similarity(take.positions[r], rig.rest)[0] for r in pick]))
    if not SCALE_RANGE[0] < scale < SCALE_RANGE[1]:
        raise _unit_error(scale, take, rig.units, "similarity of the markers to the rest pose")
    return scale


class _Window(NamedTuple):
    """A window of a take: it yields the take's rows [start, stop) (its core), cleaned with the
    rows [lo, hi) (the core and its context)."""

    start: int
    stop: int
    lo: int
    hi: int


def _choose_windows(take: Take, rows: np.ndarray, opt: PrepareOptions, window: int, notes: list[str]) -> list[_Window]:
    """The windows that cover ``rows``.

    The take is cleaned whole (noise and marker scales are measured over all of it, gaps are
    bridged from both sides), or a long take window by window with context on both sides; the
    windows are fixed by the take's rows, so a --frames part replays exactly as in the whole take.
    """
    T = take.n_frames
    fps = 1.0 / float(np.median(np.diff(take.times))) if T > 1 else 30.0
    margin = clean_margin(opt.clean_options, fps)
    whole = [_Window(0, T, 0, T)]
    if not (opt.clean and T > window + 2 * margin):
        return whole
    cores = [(a, min(T, a + window)) for a in range(0, T, window)]
    windows = [_Window(a, b, max(0, a - margin), min(T, b + margin)) for a, b in cores
               if ((rows >= a) & (rows < b)).any()]
    # a window needs frames with enough markers to fit the head (else its poses come from
    # neighbouring frames, which only the whole take has): such a take is cleaned whole
    enough = np.isfinite(take.positions).all(axis=-1).sum(axis=1) >= (3 if opt.stabilise else 1)
    if not all(enough[w.lo:w.hi].any() for w in windows):
        notes.append(f"a stretch of {window} or more frames without enough markers to fit the head: "
                     "the take was cleaned whole")
        return whole
    return windows


@dataclass(frozen=True)
class _WindowSummary:
    """What the take's report needs of a prepared window."""

    report: dict  # clean_take's report, or (cleaning off) fill_gaps' counts; with the window's notes
    outliers: np.ndarray | None  # (core frames, H) samples dropped as outliers (cleaning only)
    rotation_deg_max: float  # the largest head rotation over the rows it yields


class PreparedTake:
    """A take prepared window by window (:func:`prepare_take_windows`).

    ``rows``: the take's rows it yields (the ``--frames`` selection); :meth:`windows` yields
    (head, R, t) for consecutive runs of them, cleaned as they are asked for; :meth:`report`
    is the report of the whole selection at any time (it cleans the windows not yet cleaned,
    for their counts, so ask for it after the windows to clean each once).
    """

    def __init__(self, take: Take, rig: _Rig, options: PrepareOptions, alignment: _Alignment,
                 windows: list[_Window], rows: np.ndarray, notes: list[str]):
        self.rows = rows
        self.n_frames = int(len(rows))
        self.n_windows = len(windows)
        self._take, self._rig, self._options, self._alignment = take, rig, options, alignment
        self._window_spans = windows
        self._notes = list(notes)  # of the alignment and the choice of windows
        self._summaries: list[_WindowSummary | None] = [None] * len(windows)

    def windows(self, progress=None):
        """Yield (head (n, H, 3), R (n, 3, 3), t (n, 3)) of each window's rows, cleaned now;
        ``progress(step name)`` is called as each cleaning step of each window starts."""
        for i, window in enumerate(self._window_spans):
            head, R, t, self._summaries[i] = self._prepare(window, progress)
            yield head, R, t

    def report(self) -> dict:
        """The JSON-serialisable report of the selection (see :func:`prepare_take_windows`)."""
        for i, window in enumerate(self._window_spans):
            if self._summaries[i] is None:
                self._summaries[i] = self._prepare(window)[3]
        return _take_report(self._take, self._options, self._alignment, self._cleaning_report(),
                            max([0.0] + [s.rotation_deg_max for s in self._summaries]), self._notes)

    def _prepare(self, window: _Window, progress=None):
        """Head, R and t of the window's rows, and its summary."""
        take, rig, opt = self._take, self._rig, self._options
        world = self._alignment.to_rig(take.positions[window.lo:window.hi])
        reference = rig.rest + self._alignment.offsets
        times = take.times[window.lo:window.hi]
        if opt.clean:
            result = clean_take(world, reference, rig.basis, rig.stable, times, opt.clean_options,
                                fix_pose=not opt.stabilise, spacing=rig.spacing, names=take.marker_names,
                                progress=progress)
            head, R, t, report = result.head, result.R, result.t, result.report
            outliers = result.outliers[window.start - window.lo:window.stop - window.lo]
        else:
            head, R, t, report = _fill_window(world, reference, rig.stable, times, opt.stabilise, take)
            outliers = None
        R, t = self._alignment.to_take_space(R, t, rig.rest)
        local = self.rows[(self.rows >= window.start) & (self.rows < window.stop)] - window.lo
        angles = np.degrees(np.arccos(np.clip((np.trace(R[local], axis1=1, axis2=2) - 1) / 2, -1, 1)))
        summary = _WindowSummary(report, outliers, float(angles.max()) if angles.size else 0.0)
        return (head - self._alignment.offsets)[local], R[local], t[local], summary

    def _cleaning_report(self) -> dict:
        """The cleaning part of the report: the one window's, or the windows' merged."""
        if len(self._window_spans) == 1:
            return self._summaries[0].report
        covered = np.concatenate([self._take.positions[w.start:w.stop] for w in self._window_spans])
        return merged_clean_report([(s.report, s.outliers) for s in self._summaries], covered,
                                   self._take.marker_names, self._options.clean_options,
                                   fix_pose=not self._options.stabilise)


def _fill_window(world: np.ndarray, reference: np.ndarray, stable: np.ndarray, times: np.ndarray,
                 stabilise: bool, take: Take):
    """Cleaning off: head motion from the stable markers (interpolated where too few are seen),
    gaps filled by PCHIP. Returns head (in rig space, the neutral at ``reference``), R, t and
    a report of the gaps and notes."""
    notes: list[str] = []
    n = len(world)
    if stabilise:
        R, t = stable_marker_pose(reference, world, stable, notes)
        try:
            R, t, filled = interpolate_poses(R, t, times)
        except ValueError:
            raise InputError("no frame has 3 visible markers: the head's motion cannot be found",
                             path=take.path, hint="check the take's markers, or use --no-stabilise") from None
        if filled.any():
            notes.append(f"{int(filled.sum())} frame(s) without 3 visible markers: head pose interpolated")
        head = np.einsum("tji,thj->thi", R, world - t[:, None, :])
    else:
        R, t = np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))
        head = world.copy()
    head, gap = fill_gaps(head, times=times, marker_names=take.marker_names, path=take.path)
    return head, R, t, {"markers": gap["markers"], "total": gap["total"], "notes": notes}


def _take_report(take: Take, opt: PrepareOptions, alignment: _Alignment, clean_report: dict,
                 rotation_deg_max: float, notes: list[str]) -> dict:
    """The report of :func:`prepare_take_windows` from its cleaning report (see there)."""
    absent = list(take.markers.get("absent", [])) if take.markers else []
    notes = notes + clean_report.get("notes", [])
    markers = {name: dict(counts) for name, counts in clean_report["markers"].items()}
    for name in absent:
        markers.setdefault(name, {})["absent"] = True
    if absent:
        notes.append(f"{len(absent)} rig marker(s) absent from the take, filled from the others through the "
                     "rig's prior: " + ", ".join(absent[:8]) + (" ..." if len(absent) > 8 else ""))
    return {
        "format": take.format,
        "alignment": alignment.report,
        "head_motion": {"stabilised": bool(opt.stabilise), "rotation_deg_max": rotation_deg_max},
        "cleaning": {"prior": bool(opt.clean and opt.clean_options.prior), "enabled": bool(opt.clean),
                     **{k: v for k, v in clean_report.items() if k not in ("markers", "total", "notes")}},
        "markers": markers,
        "total": clean_report["total"],
        "absent_markers": absent,
        "extra_markers": list(take.extra_markers),
        "duplicate_markers": dict(take.markers.get("duplicates", {})) if take.markers else {},
        "renamed_markers": len(take.markers.get("renamed", {})) if take.markers else 0,
        "subject": take.markers.get("subject") if take.markers else None,
        "notes": notes,
    }


def clean_margin(options: CleanOptions, fps: float) -> int:
    """Frames of context cleaned on each side of a window: twice the reach of the jump test
    (``max_jump``) and of the fade into gaps (3 × ``decay``), plus the smoothing's 4σ."""
    reach = max(options.max_jump, 3.0 * options.decay) * fps
    return int(np.ceil(2.0 * reach + 4.0 * (options.smooth or 0.0))) + 16


def merged_clean_report(windows, world, names, options: CleanOptions, fix_pose: bool) -> dict:
    """One cleaning report for windows cleaned apart: ``windows`` holds (clean_take's report, the
    outliers (n, H) of the rows its core yields) per window; ``world`` the markers of the rows the
    cores cover, in order (visibility only). Counts cover the cores once; per-marker weights and
    scales are means over the frames; the noise is each window's (median, range)."""
    visible = np.isfinite(world).all(axis=-1)
    outliers = np.zeros(len(names), dtype=np.int64)
    frames = np.array([len(core_outliers) for _, core_outliers in windows], dtype=np.float64)
    share = frames / frames.sum()
    per_window = [report for report, _ in windows]
    for _, core_outliers in windows:
        outliers += core_outliers.sum(axis=0)

    def frame_mean(key):  # a per-marker figure, averaged over the windows' frames
        return np.array([sum(w * rep["markers"][name][key] for w, rep in zip(share, per_window)) for name in names])

    empty = visible.sum(axis=1) < (1 if fix_pose else 3)
    per, total = sample_counts(~visible, outliers, int(empty.sum()), options.short_gap, names,
                               frame_mean("weight"), frame_mean("residual_rms"))
    sigmas = [rep["noise"]["sigma"] for rep in per_window]
    noise = dict(per_window[0]["noise"])
    noise.update(
        sigma=float(np.median(sigmas)), sigma_range=[float(min(sigmas)), float(max(sigmas))], windows=len(windows),
        off_span_rms_median=float(np.median([rep["noise"]["off_span_rms_median"] for rep in per_window])),
        residual_kept_median=float(np.median([rep["noise"]["residual_kept_median"] for rep in per_window])),
        active_expressions_mean=float(sum(w * rep["noise"]["active_expressions_mean"]
                                          for w, rep in zip(share, per_window))))
    notes = []
    for rep in per_window:
        notes += [n for n in rep.get("notes", []) if n not in notes]
    return {
        "markers": per,
        "total": total,
        "noise": noise,
        "smooth_frames": float(options.smooth or 0.0),
        "notes": notes,
    }


def summary_lines(report: dict) -> list[str]:
    """A few lines for the terminal: what alignment, stabilisation and cleaning did."""
    total = report.get("total", {})
    a = report.get("alignment", {})
    units = a.get("units", {})
    lines = []
    align = f"alignment: {a.get('reference')}"
    if "scale" in a:
        align += f", scale {a['scale']:.4f}, marker offsets rms {a['offsets_rms']:.3g}"
    elif "scale_check" in a:
        align += f" (size check {a['scale_check']:.3f})"
    if units.get("take") and units.get("take") != units.get("rig"):
        align += f"; {units['take']} -> {units['rig']}"
    lines.append(align)
    c = report.get("cleaning", {})
    if c.get("enabled"):
        noise = c.get("noise", {})
        lines.append(
            f"markers: {total.get('missing', 0)} missing samples ({100 * total.get('missing_fraction', 0):.1f} %) "
            f"in {total.get('gaps', 0)} gaps (longest {total.get('longest_gap', 0)}, "
            f"{total.get('longest_gap_marker') or '-'}): {total.get('interpolated', 0)} interpolated, "
            f"{total.get('from_prior', 0)} from the rig's prior; {total.get('outliers', 0)} outliers removed; "
            f"noise σ ≈ {noise.get('sigma', 0):.3g} {units.get('rig') or 'rig units'}"
            + (f"; smoothed σ = {c['smooth_frames']:g} frames" if c.get("smooth_frames") else ""))
    else:
        lines.append(f"markers: {total.get('filled', 0)} missing samples filled in {total.get('gaps', 0)} gaps "
                     "by interpolation (cleaning off)")
    extra = report.get("extra_markers") or []
    dup = report.get("duplicate_markers") or {}
    if extra or dup:
        lines.append(f"take markers: {len(extra)} extra (ignored)" + (f", {len(dup)} duplicated (first used)"
                                                                       if dup else ""))
    for note in report.get("notes", []):
        lines.append(f"note: {note}")
    return lines
