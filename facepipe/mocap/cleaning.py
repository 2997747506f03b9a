"""Cleaning a take with the rig's own prior: head pose, noise, outliers and gaps together.

The rig's example poses span the expressions the model knows (``model.example_handles``,
head-space handle positions of the rest pose and every example). A frame's markers are
explained as a rigid head motion of an expression in that span plus what the span misses:

    x_fm = R_f (r_m + Σ_k c_fk D_km + e_fm) + t_f + n_fm

with r the neutral handles (rest pose plus the actor's marker offsets), D_k the examples'
handle displacements, c ≥ 0 sparse expression weights, e the off-span part of the
expression (smooth in time, marker-dependent size τ_m) and n the capture noise (white,
size σ). Per frame, pose and weights are fitted together (Gauss–Newton with a non-negative
L1 prior on c, markers weighted by 1 / (σ² + τ_m²): skin that the examples explain well,
like the stable markers, counts most — Fidaleo et al.'s "rigid points weighted for pose",
measured rather than hand-picked). Then:

- **noise**: σ is measured from the second temporal differences of the residuals, τ_m
  from their size; a sample's off-span residual is kept with the factor τ_m² / (τ_m² + σ²)
  (a Wiener shrink: all of it when the examples cannot explain the marker, little of it when
  the residual is noise);
- **outliers**: a marker whose residual jumps away in one frame and back later (far beyond
  its own typical frame-to-frame step) is dropped for those frames and filled like a gap;
- **gaps**: a missing sample is the prior's prediction from that frame's visible markers plus
  the marker's residual interpolated across the gap (PCHIP) and faded out with the distance
  to the nearest visible sample: a short gap is a smooth interpolation, a long one follows
  the prior and, where nothing is known, decays to neutral;
- **frames without markers**: pose and weights are interpolated from the nearest fitted
  frames;
- **over time** (a noisy take): each frame's pose is refitted from the expression smoothed over
  the take (its own weights trade against its pose under noise, worst at the take's ends), the
  poses smoothed and the expression refitted under them; each marker's residual is smoothed and
  shrunk against the noise that passes the smoother at each frame;
- optional temporal smoothing of the result (Gaussian, in frames).

Everything is arrays in, arrays and a JSON-serialisable report out.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from facepipe.mocap.gaps import fill_gaps
from facepipe.core.rigid import interpolate_poses, rigid_fit, stable_marker_pose
from facepipe.core.runs import column_runs
from facepipe.core.temporal import noise_variance_share, smooth_series
from facepipe.mocap.outliers import find_jumps, nanmean_or_zero, nanmedian_or_zero, noise_sigma
from facepipe.mocap.pose_expression import fit_pose_expression

#: Orders of the differences the pose and weight smoothers penalise, chosen per signal with λ (see
#: :func:`facepipe.core.temporal.smooth_series`): 2 alone continues a take's ends as straight lines, and
#: a head that accelerates at the first frame is then placed worse there than no smoothing would.
ORDERS = (2, 3, 4)

__all__ = ["ORDERS", "CleanOptions", "CleanResult", "clean_take", "sample_counts"]


@dataclass
class CleanOptions:
    """Options of :func:`clean_take`.

    Attributes
    ----------
    prior : bool
        Use the rig's examples (False: only the rest pose, i.e. pose fitting, outliers and
        gap filling toward neutral).
    sparsity : float
        κ, in standard deviations of each expression weight: the L1 prior (threshold κ)
        chooses the active expressions, which are refitted without it and shrunk by the
        non-negative garrote max(0, 1 − κ² var / c²) (0: plain non-negative least squares).
    outlier : float
        A jump is a single-frame step of a marker's residual larger than this many times the
        marker's typical step (and than ``jump``) that is undone within ``max_jump`` seconds:
        the samples in between are outliers (see :func:`find_jumps`).
    jump : float or None
        Absolute floor of a jump (rig units); default 5 % of the marker spacing.
    max_jump : float
        Seconds a marker may stay jumped away and still be recognised.
    decay : float
        Seconds over which a marker's residual fades into a gap (the fill then follows
        the prior alone).
    short_gap : int
        Gaps up to this many frames are reported as interpolated, longer ones as filled
        from the prior.
    smooth : float
        σ (frames) of a Gaussian temporal smoothing of the cleaned handles; 0 is off.
    iterations : int
        Gauss–Newton iterations per pass.
    """

    prior: bool = True
    sparsity: float = 2.0
    outlier: float = 5.0
    jump: float | None = None
    max_jump: float = 1.0
    decay: float = 0.2
    short_gap: int = 5
    smooth: float = 0.0
    iterations: int = 12
    temporal: bool = True


@dataclass
class CleanResult:
    """What :func:`clean_take` returns.

    Attributes
    ----------
    head : (T, H, 3) float64
        Clean handle positions in head (rig) space, neutral at the reference, no NaN.
    R, t : (T, 3, 3), (T, 3)
        Head motion, world = R @ head + t.
    weights : (T, K) float64
        Expression weights of the examples.
    report : dict
        JSON-serialisable: ``markers`` (per marker counts), ``total``, ``noise``.
    outliers : (T, H) bool
        Samples dropped as outliers (and filled like gaps).
    """

    head: np.ndarray
    R: np.ndarray
    t: np.ndarray
    weights: np.ndarray
    report: dict
    outliers: np.ndarray | None = None


def _distance_to_visible(known: np.ndarray) -> np.ndarray:
    """(T, M) frames from each sample to the nearest known sample of its marker (0 where known)."""
    T, M = known.shape
    idx = np.arange(T)[:, None]
    last = np.where(known, idx, -10 ** 9)
    last = np.maximum.accumulate(last, axis=0)
    nxt = np.where(known, idx, 10 ** 9)
    nxt = np.minimum.accumulate(nxt[::-1], axis=0)[::-1]
    return np.minimum(idx - last, nxt - idx).astype(np.float64)


#: The steps of :func:`clean_take`, in order (what its ``progress`` is called with).
CLEAN_STEPS = ("pose and expression fit", "robust refit", "smoothing over time", "filling gaps")


def clean_take(world: np.ndarray, reference: np.ndarray, basis: np.ndarray, stable: np.ndarray,
               times: np.ndarray, options: CleanOptions | None = None, *, fix_pose: bool = False,
               spacing: float = 1.0, names=None, progress=None) -> CleanResult:
    """Head pose, expression weights and clean head-space handles of a take.

    Parameters
    ----------
    world : (T, H, 3) float
        Markers in the rig's units and (aligned) space, NaN where missing.
    reference : (H, 3)
        Neutral handles in head space (rest pose + the actor's marker offsets).
    basis : (K, H, 3)
        Example handle displacements from the rest pose (K may be 0).
    stable : (H,) bool
        Markers for the starting pose (all markers are used when fewer than 3 are visible).
    times : (T,) seconds, strictly increasing.
    options : CleanOptions
    fix_pose : bool
        The take is already in head space (no stabilisation): R = I, t = 0.
    spacing : float
        Typical marker spacing (rig units), the scale of the default jump threshold.
    names : list[str], optional
        Marker names for the report.
    progress : callable(step name) or None
        Called as each of the :data:`CLEAN_STEPS` steps starts (a long take's cleaning takes a
        while: this is what a progress bar shows).

    Returns
    -------
    CleanResult
        ``head`` (T, H, 3): clean handles in head space, the neutral face at ``reference``
        (subtract the marker offsets ``reference - rest`` to drive the rig).
    """
    opt = options or CleanOptions()
    step = progress or (lambda name: None)
    world = np.asarray(world, dtype=np.float64)
    T, H, _ = world.shape
    basis = np.asarray(basis, dtype=np.float64) if opt.prior else np.zeros((0, H, 3))
    K = basis.shape[0]
    names = [f"marker{m}" for m in range(H)] if names is None else list(names)
    times = np.asarray(times, dtype=np.float64)
    visible = np.isfinite(world).all(axis=-1)
    n_vis = visible.sum(axis=1)
    fps = 1.0 / np.median(np.diff(times)) if T > 1 else 30.0
    notes: list[str] = []

    # frames the fit can use: 3 markers fix a pose (1 is enough without one)
    usable = n_vis >= (1 if fix_pose else 3)
    if not usable.any():
        raise ValueError("no frame has enough visible markers")
    R0, t0 = _starting_pose(world, reference, stable, times, usable, fix_pose, notes)
    rows = np.flatnonzero(usable)
    frames = _UsableFrames(world[rows], visible[rows], reference, basis, opt.iterations, fix_pose)

    step("pose and expression fit")
    # pass 1: unweighted, no sparsity: residuals for the noise and per-marker scales
    sigma_floor = 1e-7 * spacing  # noise-free input: keep the weights finite, the L1 bias negligible
    R1, t1, C1, _ = frames.fit(frames.visible.astype(np.float64), R0[rows], t0[rows], robust_scale=sigma_floor)
    # share of the noise the fit absorbs (parameters / equations), the rest stays in the residual
    absorbed = min(0.9, (6 * (not fix_pose) + K) / max(1.0, 3 * float(np.mean(n_vis[rows]))))
    jump = 0.05 * spacing if opt.jump is None else float(opt.jump)
    noise = _NoiseModel.measure(frames.residual(R1, t1, C1), frames.visible, sigma_floor, absorbed, opt.outlier,
                                jump)

    step("robust refit")
    # pass 2: weighted by trust, sparse expression, robust to jumping markers; then without the
    # outliers that leaves, and the chosen expressions refitted without the L1 prior's shrinkage
    W = frames.visible.astype(np.float64) * (noise.trust / noise.sigma**2)[None, :]
    robust = noise.scale * np.sqrt(3.0)
    R2, t2, C2 = _sparse_fit(frames, W, R1, t1, C1, robust, opt.sparsity)
    outlier_rows = _jumps_in_rows(frames.residual(R2, t2, C2), frames.visible, rows, T, jump, opt.outlier,
                                  max_run=int(round(opt.max_jump * fps)))
    W_kept = np.where(outlier_rows, 0.0, W)
    if outlier_rows.any():  # they were only down-weighted
        R2, t2, C2 = _sparse_fit(frames, W_kept, R2, t2, C2, robust, opt.sparsity)
    if K and opt.sparsity > 0:
        R2, t2, C2 = _relaxed_refit(frames, W_kept, R2, t2, C2, robust, opt.sparsity)

    step("smoothing over time")
    R, t, C = _every_frame(R2, t2, C2, usable, times)
    # noise-free input (σ at its floor) is left exactly as the fit gives it
    temporal = opt.temporal and T >= 4 and noise.sigma > sigma_floor
    if temporal and not fix_pose:
        R, t, C = _refit_over_time(frames, W_kept, R, t, C, usable, times, robust, opt.sparsity)
        R2, t2, C2 = R[rows], t[rows], C[rows]
    outlier = np.zeros((T, H), dtype=bool)
    outlier[rows] = outlier_rows
    known = visible & ~outlier
    residual = np.full((T, H, 3), np.nan)
    residual[rows] = np.where(outlier_rows[..., None], np.nan, frames.residual(R2, t2, C2))
    step("filling gaps")
    clean = _clean_handles(reference + np.einsum("tk,khc->thc", C, basis), residual, known, noise, times,
                           fps, names, opt, temporal)
    report = _clean_report(visible, outlier, int((~usable).sum()), noise, jump, C, opt, names, notes)
    return CleanResult(clean, R, t, C, report, outlier)


def _starting_pose(world: np.ndarray, reference: np.ndarray, stable: np.ndarray, times: np.ndarray,
                   usable: np.ndarray, fix_pose: bool, notes: list[str]):
    """(T, 3, 3), (T, 3) the pose the fit starts from: a robust rigid fit of the stable markers,
    else of all markers, interpolated over the frames the fit cannot use (identity with a fixed pose)."""
    T = len(world)
    if fix_pose:
        return np.tile(np.eye(3), (T, 1, 1)), np.zeros((T, 3))
    R0, t0 = stable_marker_pose(reference, world, stable, notes, usable,
                                fallback="their starting pose comes from all visible markers")
    R0, t0, _ = interpolate_poses(np.where(usable[:, None, None], R0, np.nan),
                                  np.where(usable[:, None], t0, np.nan), times)
    return R0, t0


@dataclass(frozen=True)
class _UsableFrames:
    """The frames the fit can use (enough visible markers), and what every fit of them shares."""

    world: np.ndarray  # (n, H, 3), NaN where missing
    visible: np.ndarray  # (n, H) bool
    reference: np.ndarray  # (H, 3)
    basis: np.ndarray  # (K, H, 3)
    iterations: int
    fix_pose: bool

    def fit(self, W, R, t, C=None, **options):
        """:func:`fit_pose_expression` of these frames with sample weights W (n, H)."""
        return fit_pose_expression(self.world, W, self.reference, self.basis, R, t, C,
                                   iterations=self.iterations, fix_pose=self.fix_pose, **options)

    def residual(self, R, t, C) -> np.ndarray:
        """(n, H, 3) the markers in head space minus the model of pose R, t and weights C; NaN where missing."""
        head = np.einsum("nji,nhj->nhi", R, np.where(self.visible[..., None], self.world, 0.0) - t[:, None, :])
        return np.where(self.visible[..., None], head - (self.reference + np.einsum("nk,khc->nhc", C, self.basis)),
                        np.nan)


@dataclass(frozen=True)
class _NoiseModel:
    """Capture noise σ and each marker's off-span variance τ² (both per coordinate)."""

    sigma: float
    ms: np.ndarray  # (H,) mean square residual per coordinate of the samples that are not outliers
    tau2: np.ndarray  # (H,)

    @classmethod
    def measure(cls, residual: np.ndarray, visible: np.ndarray, sigma_floor: float, absorbed: float,
                outlier: float, jump: float) -> "_NoiseModel":
        """From a first fit's residual (n, H, 3; NaN where missing); ``absorbed``: the share of the
        noise the fit absorbs (parameters / equations); ``outlier``, ``jump``: as in CleanOptions."""
        # the residual keeps the share 1 - absorbed of the capture noise (the fit took the rest)
        sigma = max(noise_sigma(np.nan_to_num(residual), visible) / np.sqrt(1.0 - absorbed), sigma_floor)
        r2 = np.sum(residual**2, axis=-1)  # (n, H), NaN where missing
        # per marker, per coordinate: first robustly (median |r|² / median of χ²(3)), so that a
        # marker that jumps or slides for a while cannot hide its bad samples by inflating its
        # own scale; then the mean over the samples that pass, which also counts the markers
        # that move off the examples' span only now and then
        ms = nanmedian_or_zero(r2, axis=0) / 2.366
        rough = np.sqrt(sigma**2 + np.maximum(0.0, ms - sigma**2 * (1 - absorbed)))
        bad = (np.sqrt(np.nan_to_num(r2)) > outlier * rough * np.sqrt(3.0)) & (np.sqrt(np.nan_to_num(r2)) > jump)
        ms = nanmean_or_zero(np.where(bad, np.nan, r2), axis=0) / 3.0
        return cls(sigma, ms, np.maximum(0.0, ms - sigma**2 * (1 - absorbed)))

    @property
    def scale(self) -> np.ndarray:
        """(H,) per-coordinate residual scale of each marker."""
        return np.sqrt(self.sigma**2 + self.tau2)

    @property
    def trust(self) -> np.ndarray:
        """(H,) relative weight of each marker in the fit."""
        return self.sigma**2 / (self.sigma**2 + self.tau2)

    @property
    def keep(self) -> np.ndarray:
        """(H,) share of the off-span residual kept (a Wiener shrink)."""
        return self.tau2 / (self.tau2 + self.sigma**2)


def _l1_weights(W: np.ndarray, basis: np.ndarray, sparsity: float):
    """(n, K) the L1 prior's weights: ``sparsity`` standard deviations of each expression weight
    (None without examples or sparsity)."""
    if not (basis.shape[0] and sparsity > 0):
        return None
    return sparsity * np.sqrt(np.einsum("nh,khc->nk", W, basis**2))  # diag of Dᵀ W D per frame


def _sparse_fit(frames: _UsableFrames, W, R, t, C, robust_scale, sparsity: float):
    """Pose and weights with the L1 prior, from R, t, C: robust, markers weighted by W."""
    R, t, C, _ = frames.fit(W, R, t, C, l1=_l1_weights(W, frames.basis, sparsity), robust_scale=robust_scale)
    return R, t, C


def _relaxed_refit(frames: _UsableFrames, W, R, t, C, robust_scale, sparsity: float):
    """The L1 prior chose which expressions are active; refit them without its shrinkage, then
    shrink each by the non-negative garrote max(0, 1 - κ² var / c²): a weight of a few standard
    deviations (a near-neutral frame) is pulled toward zero, a clear one is left alone (the L1
    prior would bias every active weight by κ standard deviations)."""
    R, t, C, _ = frames.fit(W, R, t, C, robust_scale=robust_scale, active=C > 0)
    var = 1.0 / np.maximum(np.einsum("nh,khc->nk", W, frames.basis**2), 1e-300)
    with np.errstate(over="ignore"):  # a weight the markers say nothing about: var / c² is inf, the weight 0
        return R, t, C * np.maximum(0.0, 1.0 - sparsity**2 * var / np.maximum(C**2, 1e-300))


def _jumps_in_rows(residual: np.ndarray, visible: np.ndarray, rows: np.ndarray, T: int, floor: float,
                   factor: float, max_run: int) -> np.ndarray:
    """(n, H) :func:`find_jumps` of the residual (n, H, 3) of the take's ``rows`` among its T frames
    (the frames between them unknown)."""
    H = visible.shape[1]
    res_seq = np.full((T, H, 3), np.nan)
    res_seq[rows] = residual
    known_seq = np.zeros((T, H), dtype=bool)
    known_seq[rows] = visible
    return find_jumps(res_seq, known_seq, floor, factor, max_run=max_run)[rows]


def _every_frame(R_rows: np.ndarray, t_rows: np.ndarray, C_rows: np.ndarray, usable: np.ndarray,
                 times: np.ndarray):
    """Pose and weights of all T frames from those of the usable ones: the others interpolated."""
    T, K = len(usable), C_rows.shape[1]
    rows = np.flatnonzero(usable)
    R = np.full((T, 3, 3), np.nan)
    t = np.full((T, 3), np.nan)
    C = np.zeros((T, K))
    R[rows], t[rows], C[rows] = R_rows, t_rows, C_rows
    empty = ~usable
    if empty.any():
        R, t, _ = interpolate_poses(R, t, times)
        for k in range(K):
            C[empty, k] = np.interp(times[empty], times[rows], C_rows[:, k])
    return R, t, C


def _smooth_poses(R: np.ndarray, t: np.ndarray, centre: np.ndarray, noise_var: np.ndarray | None = None):
    """Head poses smoothed over the take (:func:`facepipe.core.temporal.smooth_series`).

    Rotations as rotation vectors from their mean (a head turns far less than π); translations
    as the motion of ``centre`` (the markers' centroid in head space): about the face itself a
    rotation's noise does not leak into the translation through the lever arm to the origin, so
    the two are smoothed apart. With ``noise_var`` ((2,): the rotation's and the centre's noise
    variance per component, :func:`_pose_variance`) the strength is chosen by the unbiased risk,
    so poses whose noise is negligible next to their frame-to-frame deviations are left as fitted.
    """
    mean = Rotation.from_matrix(R).mean()
    v = (mean.inv() * Rotation.from_matrix(R)).as_rotvec()
    moved = np.einsum("tij,j->ti", R, centre) + t
    noise = None if noise_var is None else np.repeat(noise_var, 3)
    z = smooth_series(np.concatenate([v, moved], axis=1), groups=np.array([0, 0, 0, 1, 1, 1]), noise_var=noise,
                      orders=ORDERS)[0]
    Rs = (mean * Rotation.from_rotvec(z[:, :3])).as_matrix()
    return Rs, z[:, 3:] - np.einsum("tij,j->ti", Rs, centre)


def _pose_variance(W: np.ndarray, handles: np.ndarray) -> np.ndarray:
    """(2,) the noise variance per component of a weighted rigid fit's rotation vector and of its
    translation at the weighted centroid, averaged over the frames: the mean diagonal of the inverse
    rotational inertia Σ_m w_m (|q_m|² I − q_m q_mᵀ) (q about the centroid) and 1 / Σ_m w_m.
    W (n, H) the markers' inverse noise variances, handles (n, H, 3) the head-space points fitted."""
    sw = np.maximum(W.sum(axis=1), 1e-300)
    q = handles - (np.einsum("nh,nhc->nc", W, handles) / sw[:, None])[:, None, :]
    inertia = (np.einsum("nh,nhc,nhc->n", W, q, q)[:, None, None] * np.eye(3)
               - np.einsum("nh,nhi,nhj->nij", W, q, q))
    inertia += np.eye(3) * 1e-12 * np.einsum("nii->n", inertia).max(initial=1e-300)
    rotation = np.einsum("nii->n", np.linalg.inv(inertia)).mean() / 3.0
    return np.array([rotation, float(np.mean(1.0 / sw))])


def _refit_over_time(frames: _UsableFrames, W, R, t, C, usable: np.ndarray, times: np.ndarray, robust_scale,
                     sparsity: float):
    """Pose and expression weights of all frames (R, t, C over the take) refitted with the take's
    smoothness, from the per-frame fit's R, t, C.

    1. Pose from the expression over time: each frame's head is placed by a weighted rigid fit of
       the handles of the weights smoothed over the take (Whittaker, strength by the unbiased risk
       of each weight's known noise), not of the frame's own weights, which trade against its pose
       under noise — most at a take's first and last frames, which have no neighbours on one side
       to average that out. The poses are then smoothed over the take (:func:`_smooth_poses`).
    2. The expression refitted under the smoothed pose (whatever the pose's noise moved into the
       expression goes back out): L1 prior, then the relaxed refit of :func:`_relaxed_refit`; then
       smoothed over the take as in 1. The smoothers may follow a weight's curvature to the take's
       ends (:data:`ORDERS`), so a weight that rises from the first frame is not flattened there.
    """
    rows = np.flatnonzero(usable)
    reference, basis = frames.reference, frames.basis
    K = basis.shape[0]
    if K:
        variance = _weight_variance(W, basis)
        smoothed = np.maximum(smooth_series(C, noise_var=variance, orders=ORDERS)[0][rows], 0.0)
        handles = reference + np.einsum("nk,khc->nhc", smoothed, basis)
        R_rows, t_rows = rigid_fit(handles, np.where(frames.visible[..., None], frames.world, 0.0), W)
        R, t, _ = _every_frame(R_rows, t_rows, C[rows], usable, times)
    else:
        handles = np.broadcast_to(reference, frames.world.shape)
    R, t = _smooth_poses(R, t, reference.mean(axis=0), _pose_variance(W, handles))
    posed = replace(frames, fix_pose=True)
    C_rows = _sparse_fit(posed, W, R[rows], t[rows], C[rows], robust_scale, sparsity)[2]
    if K and sparsity > 0:
        C_rows = _relaxed_refit(posed, W, R[rows], t[rows], C_rows, robust_scale, sparsity)[2]
    C = _every_frame(R[rows], t[rows], C_rows, usable, times)[2]
    if K:
        C = np.maximum(smooth_series(C, noise_var=variance, orders=ORDERS)[0], 0.0)
    return R, t, C


def _weight_variance(W: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """(K,) each expression weight's noise variance, averaged over the frames: the diagonal of
    (Dᵀ W_f D)⁻¹ (W (n, H) the markers' inverse noise variances, D the basis (K, H, 3)), so examples
    that move the markers alike share the noise between them."""
    K = basis.shape[0]
    G = np.einsum("nh,khc,lhc->nkl", W, basis, basis)
    G += np.eye(K) * (1e-9 * np.einsum("nkk->nk", G).max(axis=1, initial=0.0) + 1e-300)[:, None, None]
    return np.einsum("nkk->nk", np.linalg.inv(G)).mean(axis=0)


def _clean_handles(model: np.ndarray, residual: np.ndarray, known: np.ndarray, noise: "_NoiseModel",
                   times: np.ndarray, fps: float, names, opt: CleanOptions, temporal: bool = False) -> np.ndarray:
    """(T, H, 3) the prior's handles ``model`` plus the kept share of each marker's off-span
    residual (NaN where not known): across gaps by PCHIP, faded with the distance to the nearest
    known sample; smoothed in time if asked.

    With ``temporal``, each marker's residual is first smoothed over the take
    (:func:`facepipe.core.temporal.smooth_series`: the off-span expression is smooth, the noise
    white), and the Wiener shrink then weighs, per frame, the smoothed residual's signal variance
    against the noise left in it there (σ² times the diagonal of H², about twice as large at the
    take's ends as in its middle). The signal variance is measured on the smoothed residual itself,
    over the whole take (its mean square less the noise's): τ², measured on the unsmoothed
    per-frame residual, also holds what the per-frame fit left behind and overstates it.
    """
    never = ~known.any(axis=0)
    res_known = np.where(never[None, :, None], 0.0, residual)
    res_filled, _ = fill_gaps(res_known, times=times, marker_names=names)
    keep = noise.keep
    if temporal:
        T, H, _ = res_filled.shape
        # second differences alone (not ORDERS): higher ones changed nothing measurable here, at 3× the cost
        smoothed, lam, _, order = smooth_series(res_filled.reshape(T, 3 * H), groups=np.repeat(np.arange(H), 3))
        res_filled = smoothed.reshape(T, H, 3)
        # per frame: the first and last frames keep more of the noise than the middle
        passed = {key: noise_variance_share(T, key[0], order=key[1]) for key in set(zip(lam, order))}
        noise_var = noise.sigma**2 * np.stack([passed[key] for key in zip(lam, order)], axis=1)  # (T, H)
        signal = np.maximum(np.mean(res_filled**2, axis=(0, 2)) - noise_var.mean(axis=0), 0.0)  # (H,)
        keep = signal / np.maximum(signal + noise_var, 1e-300)
    else:
        keep = np.broadcast_to(keep, known.shape)
    fade = np.exp(-_distance_to_visible(known) / max(opt.decay * fps, 1e-9))
    clean = model + (keep * fade)[..., None] * res_filled
    if opt.smooth and opt.smooth > 0 and len(clean) > 1:
        from scipy.ndimage import gaussian_filter1d  # lazy: the CLI starts without scipy

        clean = gaussian_filter1d(clean, float(opt.smooth), axis=0, mode="nearest")
    return clean


def _clean_report(visible: np.ndarray, outlier: np.ndarray, frames_interpolated: int, noise: _NoiseModel,
                  jump: float, C: np.ndarray, opt: CleanOptions, names, notes: list[str]) -> dict:
    """The report of :func:`clean_take` (see :class:`CleanResult`)."""
    T, K = C.shape
    H = visible.shape[1]
    per, total = sample_counts(~visible, outlier.sum(axis=0), frames_interpolated, opt.short_gap, names,
                               noise.trust, np.sqrt(3 * noise.ms))
    return {
        "markers": per,
        "total": total,
        "noise": {
            "sigma": float(noise.sigma),
            "off_span_rms_median": float(np.median(np.sqrt(3 * noise.tau2))) if H else 0.0,
            "residual_kept_median": float(np.median(noise.keep)) if H else 0.0,
            "jump_threshold": float(jump),
            "examples": int(K),
            "active_expressions_mean": float((C > 0).sum(axis=1).mean()) if K and T else 0.0,
        },
        "smooth_frames": float(opt.smooth or 0.0),
        "notes": notes,
    }


def sample_counts(missing: np.ndarray, outliers: np.ndarray, frames_interpolated: int, short_gap: int, names,
                  weight: np.ndarray, residual_rms: np.ndarray) -> tuple[dict, dict]:
    """The cleaning report's per-marker and total counts.

    missing : (T, H) mask of missing samples; outliers : (H,) samples dropped per marker;
    frames_interpolated : frames whose pose was interpolated; short_gap : gaps up to this many
    frames count as interpolated, longer ones as filled from the prior; weight, residual_rms :
    (H,) each marker's weight in the fit and residual scale.
    """
    T, H = missing.shape
    col, start, stop = column_runs(missing)
    run_len = stop - start
    gaps = np.bincount(col, minlength=H)
    longest = np.zeros(H, dtype=np.int64)
    np.maximum.at(longest, col, run_len)
    short_fill = np.zeros(H, dtype=np.int64)
    np.add.at(short_fill, col, np.where(run_len <= short_gap, run_len, 0))
    n_missing = missing.sum(axis=0)
    per = {names[m]: {"missing": int(n_missing[m]), "gaps": int(gaps[m]), "longest_gap": int(longest[m]),
                      "interpolated": int(short_fill[m]), "from_prior": int(n_missing[m] - short_fill[m]),
                      "outliers": int(outliers[m]), "weight": float(weight[m]),
                      "residual_rms": float(residual_rms[m])}
           for m in range(H)}
    total = {
        "frames": int(T),
        "markers": int(H),
        "missing": int(n_missing.sum()),
        "missing_fraction": float(missing.mean()) if T else 0.0,
        "gaps": int(gaps.sum()),
        "longest_gap": int(longest.max()) if H else 0,
        "longest_gap_marker": names[int(np.argmax(longest))] if H and longest.max() > 0 else None,
        "filled": int(n_missing.sum() + outliers.sum()),
        "interpolated": int(short_fill.sum()),
        "from_prior": int(n_missing.sum() - short_fill.sum()),
        "outliers": int(outliers.sum()),
        "frames_interpolated": int(frames_interpolated),
    }
    return per, total
