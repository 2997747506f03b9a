"""Fidaleo et al. (2000, §III)'s heuristic for 2D landmark takes: the baseline of ``--lift heuristic``.

Per frame:

1. the head pose from the rigid points alone: a robust pose fit of the *neutral* landmarks,
   the points weighted by how little they move across the examples (Fidaleo et al. weight
   hand-picked rigid points higher; here the examples pick them);
2. every landmark's remaining 2D disparity is non-rigid motion: its ray is met with the
   *neutral* surface around its vertex, giving a 3D displacement from rest;
3. a missing landmark takes its mirror partner's displacement (expressions assumed symmetric),
   else decays toward neutral; a displacement that jumps far beyond the landmark's usual
   frame-to-frame step is held at its previous value;
4. the handles follow the landmark displacements through the rig's shell (the same map the
   model-based lift uses for its residuals).

Nothing here uses the rig's examples beyond choosing the rigid points: that is the point of
the comparison.
"""

from __future__ import annotations

import numpy as np

from facepipe.core.camera import Camera, project
from facepipe.core.lift import fit_pose_expression_2d, landmark_weights, robust_sigma
from facepipe.mocap.landmarks2d import LandmarkTake
from facepipe.pipeline.video_lift import LiftResult, LiftRig, _report, backproject, every_frames_pose, posed_frames

__all__ = ["heuristic_lift", "JUMP_FACTOR"]

#: A landmark's displacement that changes by more than this many times its median frame-to-frame
#: change is an abrupt jump and is held.
JUMP_FACTOR = 5.0


def heuristic_lift(take: LandmarkTake, camera: Camera, rig: LiftRig, opt) -> LiftResult:
    """Fidaleo et al.'s lift of a 2D take (see the module); returns what :func:`lift_take` does."""
    T, L = take.points.shape[:2]
    K = rig.basis.shape[0]
    pts, visible, rows, R0, t0 = posed_frames(take, camera, rig)
    vis = visible[rows]
    # 1. pose from the rigid points: the neutral face, rigid landmarks weighted highest
    sigma = 1.0
    Rf, tf = R0[rows], t0[rows]
    for _ in range(2):
        base = vis * landmark_weights(rig.motion, sigma, camera.focal / tf[:, 2], opt.share)
        Rf, tf, _, resid, _ = fit_pose_expression_2d(pts[rows], base, camera.matrix, rig.rest, np.zeros((0, L, 3)),
                                                     Rf, tf, robust=2.5 * sigma, iterations=opt.iterations)
        sigma = max(robust_sigma(resid, vis), 1e-3)
    R, t, filled, fitted = every_frames_pose(Rf, tf, rows, take.times)

    # 2. the disparities onto the neutral surface
    use = np.zeros((T, L), dtype=bool)
    use[rows] = vis
    neutral_cam = np.einsum("tij,lj->tli", R, rig.rest) + t[:, None, :]
    head_pts, good = backproject(rig, camera, pts, use, R, t, np.zeros((T, K)), neutral_cam, on_fitted=False)
    raw = np.where(good[..., None], head_pts - rig.rest, np.nan)

    # 3. symmetry fill, decay toward neutral, held jumps: frame by frame, as a tracker would run
    step = np.linalg.norm(np.diff(raw, axis=0), axis=-1)
    typical = np.nanmedian(np.where(np.isfinite(step), step, np.nan), axis=0) if np.isfinite(step).any() else \
        np.zeros(L)
    limit = JUMP_FACTOR * np.nan_to_num(typical, nan=np.inf)
    mirror = rig.mirror
    flip = np.array([-1.0, 1.0, 1.0])  # the rig's left-right axis is x
    disp = np.zeros((T, L, 3))
    prev = np.zeros((L, 3))
    held = 0
    times = take.times
    for f in range(T):
        d = raw[f].copy()
        miss = ~np.isfinite(d).all(axis=1)
        partner = np.where(miss & (mirror >= 0), mirror, -1)
        ok = partner >= 0
        ok[ok] &= ~miss[partner[ok]]
        d[ok] = raw[f, partner[ok]] * flip
        miss &= ~ok
        dt = times[f] - times[f - 1] if f else 0.0
        d[miss] = prev[miss] * np.exp(-dt / opt.decay)
        if f:
            jump = ~miss & (np.linalg.norm(d - prev, axis=1) > limit)
            d[jump] = prev[jump]
            held += int(jump.sum())
        disp[f] = d
        prev = d
    head = rig.handle_rest + np.einsum("hl,tlc->thc", rig.to_handles, disp)

    cam_fit = np.einsum("tij,tlj->tli", R, rig.rest + disp) + t[:, None, :]
    fit_px = np.linalg.norm(project(camera.matrix, neutral_cam) - pts, axis=-1)
    report = _report(take, camera, R, t, np.zeros((T, K)), fit_px, visible, use,
                     outlier_rows=(rows, np.zeros_like(vis)), filled=filled, fitted=fitted, sigma=sigma,
                     shrink=np.ones(L), method="heuristic", names=take.names, decay=opt.decay)
    report["held_jumps"] = held
    return LiftResult(head, R, t, np.zeros((T, K)), rig.rest + disp, cam_fit, report, use)
