"""A monocular video take (2D landmark tracks) to head-space handles and head motion.

:func:`lift_take` is what ``replay`` runs for a 2D take, between reading it and evaluating the
model (in place of :mod:`facepipe.mocap.prepare`):

1. the landmarks are undistorted through the camera (:mod:`facepipe.core.camera`);
2. **pose and expression** per frame: started from a PnP of the rest landmarks (each frame from
   the previous one's pose), then head pose (6 DoF) and the weights of the rig's examples fitted
   together, robustly, to all frames' landmarks (:func:`facepipe.core.lift.fit_pose_expression_2d`);
   landmarks weighted by how little they move across the examples (rigid points weigh most) and
   by the tracking noise, which is measured on the take itself after a first pass;
3. **what the examples miss**: each landmark's remaining 2D residual is put back onto the fitted
   surface (the ray through the observed pixel met with the fitted face around the landmark's
   vertex), shrunk by how much of it is noise, and moved onto the handles through the rig's
   shell (:func:`facepipe.core.lift.landmarks_to_handles`);
4. **missing data**: frames the tracker lost get their pose interpolated (slerp) and their
   expression interpolated and faded toward neutral with the time to the nearest tracked frame;
   a missing or slipping landmark's residual fades likewise.

The examples' displacements at the landmarks come from the model itself: its output (large
scale and details) evaluated at each example's handles (``example_handles``), at the landmark
vertices and the triangles around them. The model file does not hold the examples' full
positions, and this is rig-general: it is the face the replay will produce for those handles.

``lift="heuristic"`` runs Fidaleo et al.'s scheme instead (:mod:`facepipe.pipeline.video_heuristic`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from facepipe.core.camera import Camera, pixel_rays, project, project_distorted, undistort_points
from facepipe.core.lift import (fade_fill, fit_pose_expression_2d, intersect_ray_plane, intersect_rays_triangles,
                                landmark_motion, landmark_weights, landmarks_to_handles, robust_sigma,
                                soft_keep)
from facepipe.core.rigid import interpolate_poses
from facepipe.core.runs import column_runs
from facepipe.errors import InputError
from facepipe.mocap.landmarks2d import MIN_LANDMARKS, LandmarkTake

__all__ = ["LiftOptions", "LiftResult", "LiftRig", "lift_rig", "lift_take", "summary_lines"]


@dataclass
class LiftOptions:
    """Options of :func:`lift_take`.

    Attributes
    ----------
    method : "model" (pose and expression through the rig's examples) or "heuristic" (Fidaleo
        et al. 2000: pose from the rigid points, residuals onto the neutral face).
    upper : largest expression weight (an example at full strength is 1).
    prior : weight of the prior toward neutral (per unit weight², against the landmarks'
        inverse-variance-weighted squared pixels).
    share : fraction of a landmark's example motion the examples may fail to explain (its
        variance beside the noise; rigid points weigh most).
    residual : put what the examples miss back (Fidaleo's non-rigid step on the fitted face).
    decay : seconds over which an expression or residual fades toward neutral into a gap.
    iterations : Levenberg–Marquardt steps per pass.
    """

    method: str = "model"
    upper: float = 1.0
    prior: float = 1.0
    share: float = 0.1
    residual: bool = True
    decay: float = 0.2
    iterations: int = 15


@dataclass
class LiftRig:
    """What the lift needs of a model at the landmarks (see :func:`lift_rig`).

    rest : (L, 3) rest positions; basis : (K, L, 3) example displacements at the landmarks.
    patch_rest : (P, 3), patch_basis : (K, P, 3) the same at the vertices of the triangles
    around the landmarks; patch_triangles : (L, N, 3) indices into them, patch_valid : (L, N).
    handle_rest : (H, 3); handle_basis : (K, H, 3) the examples' handle displacements.
    to_handles : (H, L) landmark displacement → handle displacement (through B).
    motion : (L,) RMS example motion of each landmark (rig units).
    mirror : (L,) index of each landmark's mirror image across the rig's x = centre plane, or -1.
    """

    vertices: np.ndarray
    rest: np.ndarray
    basis: np.ndarray
    patch_rest: np.ndarray
    patch_basis: np.ndarray
    patch_triangles: np.ndarray
    patch_valid: np.ndarray
    neutral_patch: np.ndarray
    handle_rest: np.ndarray
    handle_basis: np.ndarray
    to_handles: np.ndarray
    motion: np.ndarray
    mirror: np.ndarray


@dataclass
class LiftResult:
    """What :func:`lift_take` returns: ``head`` (T, H, 3) handle positions in rig space; ``R``, ``t``
    (T, 3, 3), (T, 3) the head pose in the camera's coordinates (camera = R @ head + t, rig units,
    OpenCV axes); ``weights`` (T, K); ``landmarks`` (T, L, 3) the tracked points in head space;
    ``fitted`` (T, L, 3) the fitted face's landmarks in camera coordinates; ``report``; ``used`` (T, L)
    the samples the lift used (tracked, not slipping)."""

    head: np.ndarray
    R: np.ndarray
    t: np.ndarray
    weights: np.ndarray
    landmarks: np.ndarray
    fitted: np.ndarray
    report: dict
    used: np.ndarray | None = None


def _rings(triangles: np.ndarray, vertices: np.ndarray, n_vertices: int, rings: int = 1):
    """Per landmark vertex: the triangles within ``rings`` rings of it (lists of triangle indices)."""
    import scipy.sparse as sp

    T = len(triangles)
    inc = sp.csr_matrix((np.ones(3 * T), (triangles.ravel(), np.repeat(np.arange(T), 3))), shape=(n_vertices, T))
    out = []
    for v in vertices:
        verts = np.array([v])
        tris = np.zeros(0, dtype=np.int64)
        for _ in range(rings):
            tris = np.unique(inc[verts].indices)
            verts = np.unique(triangles[tris])
        out.append(tris)
    return out


def lift_rig(model, vertices: np.ndarray, with_details: bool = True) -> LiftRig:
    """The model at the landmark vertices: rest positions, the examples' displacements there (the
    model's own output at each example's handles), the surface patches around them and the map
    from landmark to handle displacements.

    Parameters
    ----------
    model : a baked :class:`facepipe.io.model_file.Model`.
    vertices : (L,) landmark vertices.
    with_details : include the model's details in the examples' displacements (else the large
        scale B alone).
    """
    rest_all = model.rest.astype(np.float64)
    V = len(rest_all)
    faces = model.triangles.astype(np.int64)
    vertices = np.asarray(vertices, dtype=np.int64)
    rings = _rings(faces, vertices, V)
    width = max(len(r) for r in rings)
    patch_vertices = np.unique(np.concatenate([faces[r].ravel() for r in rings] + [vertices]))
    where = {int(v): i for i, v in enumerate(patch_vertices)}
    lookup = np.vectorize(where.__getitem__, otypes=[np.int64])
    patch_triangles = np.zeros((len(vertices), width, 3), dtype=np.int64)
    patch_valid = np.zeros((len(vertices), width), dtype=bool)
    for i, r in enumerate(rings):
        patch_triangles[i, :len(r)] = lookup(faces[r])
        patch_valid[i, :len(r)] = True
    eh = np.asarray(model.example_handles, dtype=np.float64)
    handle_rest = eh[0]
    handle_basis = eh[1:] - eh[0]
    disp = _example_displacements(model, handle_rest, eh[1:], patch_vertices, with_details)
    land = lookup(vertices)
    B = np.asarray(model.B, dtype=np.float64)
    rest_patch = rest_all[patch_vertices]
    lo, hi = rest_all[vertices].min(axis=0), rest_all[vertices].max(axis=0)
    return LiftRig(vertices=vertices, rest=rest_patch[land], basis=disp[:, land], patch_rest=rest_patch,
                   patch_basis=disp, patch_triangles=patch_triangles, patch_valid=patch_valid,
                   neutral_patch=rest_patch, handle_rest=handle_rest, handle_basis=handle_basis,
                   to_handles=landmarks_to_handles(B[vertices], model.edges), motion=landmark_motion(disp[:, land]),
                   mirror=_mirror_pairs(rest_all[vertices], 0.5 * (lo[0] + hi[0]), 0.05 * float(np.max(hi - lo))))


def _example_displacements(model, handle_rest, example_handles, rows, with_details: bool) -> np.ndarray:
    """(K, len(rows), 3): the model's output at each example's handles, minus rest, at ``rows``."""
    B = np.asarray(model.B, dtype=np.float64)
    large = np.einsum("vh,khc->kvc", B[rows], example_handles - handle_rest)
    if not with_details or model.method == "none" or len(example_handles) == 0:
        return large
    from facepipe.pipeline.replay import NumpyEvaluator  # (the reference evaluator: float64, whole mesh)

    evaluator = NumpyEvaluator(model)
    out = np.empty_like(large)
    rest = evaluator.rest[rows]
    for a in range(0, len(example_handles), 8):  # a few full-mesh frames at a time
        out[a:a + 8] = evaluator.evaluate(example_handles[a:a + 8])[:, rows] - rest
    return out


def _mirror_pairs(points: np.ndarray, centre_x: float, tolerance: float) -> np.ndarray:
    """Each point's mirror image across the plane x = centre_x (the rig's left-right axis), or -1."""
    mirrored = points * np.array([-1.0, 1.0, 1.0]) + np.array([2.0 * centre_x, 0.0, 0.0])
    d = np.linalg.norm(mirrored[:, None] - points[None], axis=-1)
    j = d.argmin(axis=1)
    ok = (d[np.arange(len(points)), j] < tolerance) & (j != np.arange(len(points)))
    return np.where(ok, j, -1)


# ----------------------------------------------------------------------------- pose start


def initial_poses(rest: np.ndarray, points: np.ndarray, usable: np.ndarray, matrix: np.ndarray):
    """Per usable frame a PnP pose of the rest landmarks (camera = R @ head + t), each frame
    started from the previous one's; NaN for the others."""
    T = points.shape[0]
    R = np.full((T, 3, 3), np.nan)
    t = np.full((T, 3), np.nan)
    rvec = tvec = None
    for f in np.flatnonzero(usable):
        vis = np.isfinite(points[f]).all(axis=1)
        obj = rest[vis].reshape(-1, 1, 3)
        img = points[f, vis].reshape(-1, 1, 2)
        ok = False
        if rvec is not None:
            ok, r_, t_ = cv2.solvePnP(obj, img, matrix, None, rvec.copy(), tvec.copy(), True, cv2.SOLVEPNP_ITERATIVE)
            ok = ok and t_[2, 0] > 0
        if not ok:
            ok, r_, t_ = cv2.solvePnP(obj, img, matrix, None, flags=cv2.SOLVEPNP_SQPNP)
            ok = ok and t_[2, 0] > 0
        if ok:
            rvec, tvec = r_, t_
            R[f] = cv2.Rodrigues(r_)[0]
            t[f] = t_[:, 0]
    return R, t


# ----------------------------------------------------------------------------- the lift


def _fit_frames(rig: LiftRig, pts, base, matrix, R, t, C, opt: LiftOptions, robust: float, target=None,
                chunk: int = 256):
    T, L = base.shape
    K = rig.basis.shape[0]
    out = [np.empty((T, 3, 3)), np.empty((T, 3)), np.empty((T, K)), np.empty((T, L, 2)), np.empty((T, L))]
    for a in range(0, T, chunk):
        b = min(T, a + chunk)
        res = fit_pose_expression_2d(pts[a:b], base[a:b], matrix, rig.rest, rig.basis, R[a:b], t[a:b], C[a:b],
                                     upper=opt.upper, prior=opt.prior, robust=robust, iterations=opt.iterations,
                                     target=None if target is None else target[a:b])
        for o, r in zip(out, res):
            o[a:b] = r
    return out


def _surface_points(rig: LiftRig, rays, R, t, C, patch_basis=True):
    """Where the rays through the observed (undistorted) pixels meet the fitted surface around each
    landmark, in camera coordinates (T, L, 3); NaN for missing samples. The tangent plane at the
    fitted landmark stands in where the ray leaves the patch."""
    K, Pn = rig.patch_basis.shape[:2]
    patch = rig.patch_rest + ((C @ rig.patch_basis.reshape(K, Pn * 3)).reshape(-1, Pn, 3) if patch_basis else 0.0)
    if np.ndim(patch) == 2:
        patch = np.broadcast_to(patch, (len(R),) + patch.shape)
    cam = patch @ R.transpose(0, 2, 1) + t[:, None, :]
    tri = cam[:, rig.patch_triangles]  # (T, L, N, 3, 3)
    _, hit, points = intersect_rays_triangles(np.zeros(rays.shape), rays, tri, rig.patch_valid[None])
    # fallback: the plane through the fitted landmark, normal to its patch
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    normal = (np.cross(b - a, c - a) * rig.patch_valid[None, :, :, None]).sum(axis=2)
    return hit, points, normal, cam


def backproject(rig: LiftRig, camera: Camera, pts: np.ndarray, use: np.ndarray, R, t, C, cam_fit,
                on_fitted: bool = True):
    """Head-space points (T, L, 3) where the rays through the observed (undistorted) landmarks meet
    the face around each landmark's vertex — the fitted face (weights ``C``), or the neutral one —
    and (T, L) where that worked (``use`` and a finite point).

    ``cam_fit`` (T, L, 3): the face's landmarks in camera coordinates. Where the ray leaves the
    patch of triangles the tangent plane stands in; at a grazing view (the silhouette) a pixel's
    error runs far along the surface, so beyond twice the ray's own distance from the landmark
    the point of the ray nearest the landmark is taken."""
    rays = pixel_rays(camera.matrix, np.where(use[..., None], pts, 0.0))
    hit, on_surface, normal, _ = _surface_points(rig, rays, R, t, C, patch_basis=on_fitted)
    _, on_plane = intersect_ray_plane(np.zeros_like(rays), rays, cam_fit, normal)
    X = np.where(hit[..., None], on_surface, on_plane)
    unit = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    foot = unit * (unit * cam_fit).sum(-1, keepdims=True)
    near = np.linalg.norm(foot - cam_fit, axis=-1)
    far = ~np.isfinite(X).all(axis=-1) | (np.linalg.norm(X - cam_fit, axis=-1) > 2.0 * near + 1e-12)
    X = np.where(far[..., None], foot, X)
    good = use & np.isfinite(X).all(axis=-1)
    return np.einsum("tji,tlj->tli", R, X - t[:, None, :]), good


def posed_frames(take: LandmarkTake, camera: Camera, rig: LiftRig):
    """The undistorted points, their visibility, and the frames whose head pose the landmarks
    give a start for: ``(points, visible, rows, R0, t0)``; InputError where no frame has one."""
    L = take.points.shape[1]
    pts = undistort_points(camera, take.points)
    visible = np.isfinite(pts).all(axis=-1)
    usable = visible.sum(axis=1) >= min(MIN_LANDMARKS, L)
    R0, t0 = initial_poses(rig.rest, pts, usable, camera.matrix)
    posed = np.isfinite(t0).all(axis=1)
    if not posed.any():
        raise InputError("no frame's head pose could be found from the landmarks", path=take.path,
                         hint="check that the landmark map matches the tracker's points and the camera the footage")
    return pts, visible, np.flatnonzero(posed), R0, t0


def every_frames_pose(R_rows: np.ndarray, t_rows: np.ndarray, rows: np.ndarray, times: np.ndarray):
    """The head pose of every frame from those fitted at ``rows``, the others interpolated:
    ``(R, t, filled, fitted)``."""
    T = len(times)
    R = np.full((T, 3, 3), np.nan)
    t = np.full((T, 3), np.nan)
    R[rows], t[rows] = R_rows, t_rows
    R, t, filled = interpolate_poses(R, t, times)
    fitted = np.zeros(T, dtype=bool)
    fitted[rows] = True
    return R, t, filled, fitted


def lift_take(take: LandmarkTake, camera: Camera, rig: LiftRig, options: LiftOptions | None = None) -> LiftResult:
    """Head-space handles and camera-space head pose of a 2D take, with a report.

    Parameters
    ----------
    take : read with the landmark map's names (:func:`facepipe.mocap.landmarks2d.read_landmark_take`).
    camera : the calibration; rig : :func:`lift_rig` of the model at the map's vertices.

    Raises
    ------
    InputError
        No frame whose head pose can be found.
    """
    opt = options or LiftOptions()
    if opt.method == "heuristic":
        # lazily: the baseline's module builds on this one's helpers
        from facepipe.pipeline.video_heuristic import heuristic_lift

        return heuristic_lift(take, camera, rig, opt)
    T, L = take.points.shape[:2]
    K = rig.basis.shape[0]
    pts, visible, rows, R0, t0 = posed_frames(take, camera, rig)
    P, Rf, tf = pts[rows], R0[rows], t0[rows]
    vis = visible[rows]
    focal = camera.focal
    C0 = np.zeros((len(rows), K))
    # pass 1: a nominal noise of 1 px; pass 2: the noise measured on the take's own residuals
    sigma = 1.0
    for _ in range(2):
        base = vis * landmark_weights(rig.motion, sigma, focal / tf[:, 2], opt.share)
        Rf, tf, C0, resid, w = _fit_frames(rig, P, base, camera.matrix, Rf, tf, C0, opt, robust=2.5 * sigma)
        inlier = vis & (np.linalg.norm(resid, axis=-1) < 4.0 * sigma)
        sigma = max(robust_sigma(resid, inlier), 1e-3 * float(np.linalg.norm([camera.width, camera.height])) / 1e3)
    outlier = vis & (np.linalg.norm(resid, axis=-1) > 4.0 * sigma)

    # every frame: fitted ones, the others interpolated (pose) and faded toward neutral (expression)
    R, t, filled, fitted = every_frames_pose(Rf, tf, rows, take.times)
    C = np.zeros((T, K))
    C[rows] = C0
    C = fade_fill(C[:, None, :], fitted[:, None], take.times, opt.decay)[:, 0]
    y = rig.rest + np.einsum("tk,klc->tlc", C, rig.basis)  # fitted landmarks, head space
    cam_fit = np.einsum("tij,tlj->tli", R, y) + t[:, None, :]

    # Fidaleo's step on the fitted face: each observed landmark put back on the surface
    use = np.zeros((T, L), dtype=bool)
    use[rows] = vis & ~outlier
    landmarks = y.copy()
    shrink = np.zeros(L)
    correction = np.zeros((T, L, 3))
    if opt.residual and use.any():
        head_pts, good = backproject(rig, camera, pts, use, R, t, C, cam_fit)
        r3 = np.where(good[..., None], head_pts - y, 0.0)
        # what of it stands out of the noise (σ px at the landmark's depth, two image axes) and of
        # what the model misses anyway (the share of the landmark's example motion it may miss)
        floor = 2.0 * (sigma * cam_fit[..., 2] / focal) ** 2 + (opt.share * rig.motion) ** 2
        fps = 1.0 / float(np.median(np.diff(take.times))) if T > 1 else 30.0
        keep = soft_keep((r3 ** 2).sum(-1), good, floor, opt.decay * fps)
        shrink = keep.sum(axis=0) / np.maximum(good.sum(axis=0), 1)
        correction = fade_fill(r3 * keep[..., None], good, take.times, opt.decay)
        landmarks = y + np.where(good[..., None], r3, np.nan)
    head = rig.handle_rest + np.einsum("tk,khc->thc", C, rig.handle_basis) + \
        np.einsum("hl,tlc->thc", rig.to_handles, correction)

    fit_px = np.linalg.norm(project(camera.matrix, cam_fit) - pts, axis=-1)
    report = _report(take, camera, R, t, C, fit_px, visible, use, outlier_rows=(rows, outlier), filled=filled,
                     fitted=fitted, sigma=sigma, shrink=shrink, method="model", names=take.names,
                     decay=opt.decay)
    return LiftResult(head, R, t, C, landmarks, cam_fit, report, use)


def _pose_summary(R: np.ndarray, t: np.ndarray) -> dict:
    """Head pose per frame: rotation (degrees) from the take's median pose, and translation."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_matrix(R)
    mean = rot.mean()
    rel = (mean.inv() * rot).magnitude()
    return {"rotation_deg": np.degrees(rel).round(4).tolist(),
            "rotation_vector": rot.as_rotvec().round(6).tolist(),
            "translation": t.round(5).tolist(),
            "rotation_deg_max": float(np.degrees(rel).max()),
            "translation_range": (t.max(axis=0) - t.min(axis=0)).round(5).tolist()}


def _report(take, camera, R, t, C, fit_px, visible, used, outlier_rows, filled, fitted, sigma, shrink, method,
            names, decay: float = LiftOptions.decay) -> dict:
    T, L = visible.shape
    rows, outlier = outlier_rows
    out_count = np.zeros(L, dtype=np.int64)
    out_count_frame = np.zeros(T, dtype=np.int64)
    if len(rows):
        out_count += outlier.sum(axis=0)
        out_count_frame[rows] = outlier.sum(axis=1)
    per_frame = np.full(T, np.nan)
    seen = used.any(axis=1)
    per_frame[seen] = np.sqrt((np.where(used, fit_px, 0.0) ** 2).sum(axis=1)[seen] / used.sum(axis=1)[seen])
    missing = ~fitted
    _, lost_start, lost_stop = column_runs(missing)
    longest_gap = int((lost_stop - lost_start).max(initial=0))
    return {
        "method": method,
        "format": take.format,
        "camera": {"path": camera.path, "width": camera.width, "height": camera.height,
                   "focal_px": camera.focal, "distortion": camera.distortion.reshape(-1).tolist()},
        "landmarks": len(names),
        "frames_missing": int(missing.sum()),
        "frames_failed_by_tracker": int(take.failed.sum()),
        "frames_filled": int(filled.sum()),
        "longest_gap_frames": longest_gap,
        "samples_missing": int((~visible).sum()),
        "samples_outliers": int(out_count.sum()),
        "noise_px": float(sigma),
        "fit_reprojection_px": {
            "per_frame": [None if not np.isfinite(v) else round(float(v), 4) for v in per_frame],
            "mean": float(np.nanmean(per_frame)) if np.isfinite(per_frame).any() else None,
            "max": float(np.nanmax(per_frame)) if np.isfinite(per_frame).any() else None,
        },
        "residual_kept": {n: round(float(s), 4) for n, s in zip(names, shrink)},
        "per_landmark": {n: {"missing": int((~visible[:, i]).sum()), "outliers": int(out_count[i])}
                         for i, n in enumerate(names)},
        "head_pose": _pose_summary(R, t),
        "expression_weights_max": C.max(axis=0).round(4).tolist() if C.size else [],
        "notes": ([f"{int(missing.sum())} frame(s) without a tracked face ({len(lost_start)} gap(s), longest "
                   f"{longest_gap}): head pose interpolated, expression faded toward "
                   f"neutral over {decay:g} s"] if missing.any() else []),
    }


def reprojection_of_output(camera: Camera, take: LandmarkTake, landmark_positions: np.ndarray, R: np.ndarray,
                           t: np.ndarray, head_motion: str, used: np.ndarray | None = None) -> dict:
    """Per-frame RMS distance (pixels of the footage) between the tracked landmarks and the replayed
    face's landmark vertices projected through the camera (distortion included).

    landmark_positions : (T, L, 3) rows of the written positions (camera space with ``keep``,
    rig space with ``remove``: then R, t put them in front of the camera); ``used`` (T, L): the
    samples to count (default all tracked ones; the lift's report sets slipping samples aside)."""
    X = np.asarray(landmark_positions, dtype=np.float64)
    if head_motion != "keep":
        X = np.einsum("tij,tlj->tli", R, X) + t[:, None, :]
    px = project_distorted(camera, X)
    err = np.linalg.norm(px - take.points, axis=-1)
    vis = np.isfinite(err) & (True if used is None else used)
    per = np.full(len(X), np.nan)
    seen = vis.any(axis=1)
    per[seen] = np.sqrt((np.where(vis, err, 0.0) ** 2).sum(axis=1)[seen] / vis.sum(axis=1)[seen])
    ok = np.isfinite(per)
    return {"per_frame": [None if not np.isfinite(v) else round(float(v), 4) for v in per],
            "mean": float(per[ok].mean()) if ok.any() else None,
            "median": float(np.median(per[ok])) if ok.any() else None,
            "max": float(per[ok].max()) if ok.any() else None}


def summary_lines(report: dict) -> list[str]:
    """A few lines for the terminal: what the lift did."""
    v = report
    rep = v.get("reprojection_px") or {}
    fit = v.get("fit_reprojection_px") or {}
    pose = v.get("head_pose", {})
    lines = [f"2D take ({v['format']}, {v['landmarks']} landmarks) lifted by the "
             f"{'rig' + chr(39) + 's examples' if v['method'] == 'model' else 'heuristic (Fidaleo et al.)'}: "
             f"tracking noise ≈ {v['noise_px']:.2f} px, {v['samples_outliers']} slipping sample(s) set aside"]
    if rep.get("mean") is not None:
        lines.append(f"reprojection error of the replayed face: mean {rep['mean']:.3f} px, max frame {rep['max']:.3f} px"
                     + (f" (fit {fit['mean']:.3f} px)" if fit.get("mean") is not None else ""))
    lines.append(f"frames: {v['frames_missing']} without a tracked face ({v['frames_failed_by_tracker']} failed by the "
                 f"tracker), {v['frames_filled']} filled; {v['samples_missing']} landmark samples missing")
    lines.append(f"head pose: up to {pose.get('rotation_deg_max', 0):.1f}° from the median pose, translation range "
                 + " × ".join(f"{x:.2f}" for x in pose.get("translation_range", [])))
    lines += [f"note: {n}" for n in v.get("notes", [])]
    return lines
