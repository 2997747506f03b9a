"""A calibrated pinhole camera with OpenCV's lens distortion: projection and undistortion.

Conventions are OpenCV's: camera coordinates x right, y down, z forward (the viewing
direction); pixel (u, v) = (fx x/z + cx, fy y/z + cy) before distortion, pixel centres at
integers. Landmarks are undistorted once (:func:`undistort_points`) and every fit works on the
ideal pinhole image (the camera matrix, no distortion): residuals stay in pixels.

Pure functions over arrays; OpenCV's own undistortion and projection are used so that
facepipe's camera model is exactly the one the calibration was made with.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Camera", "project", "project_distorted", "project_distorted_fast", "undistort_points", "pixel_rays"]


@dataclass(frozen=True)
class Camera:
    """Intrinsics of one camera.

    Attributes
    ----------
    matrix : (3, 3) float64
        [[fx, s, cx], [0, fy, cy], [0, 0, 1]].
    distortion : (N,) float64
        OpenCV's coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [τx τy]]]]), N in
        {0, 4, 5, 8, 12, 14}.
    width, height : int
        The image size the calibration is for, in pixels.
    path : str
        Where it was read from (for messages).
    """

    matrix: np.ndarray
    distortion: np.ndarray
    width: int
    height: int
    path: str = ""

    @property
    def focal(self) -> float:
        """Mean focal length in pixels (converts lengths at a depth into pixels)."""
        return float(0.5 * (self.matrix[0, 0] + self.matrix[1, 1]))


def undistort_points(camera: Camera, points: np.ndarray) -> np.ndarray:
    """Pixels of the distorted image → pixels of the ideal pinhole image (same camera matrix).

    Parameters
    ----------
    points : (..., 2) pixels; NaN rows stay NaN.

    Returns
    -------
    (..., 2) float64.
    """
    pts = np.asarray(points, dtype=np.float64)
    out = np.full(pts.shape, np.nan)
    flat = pts.reshape(-1, 2)
    ok = np.isfinite(flat).all(axis=1)
    if ok.any():
        und = cv2.undistortPoints(flat[ok].reshape(-1, 1, 2), camera.matrix, camera.distortion,
                                  P=camera.matrix)
        out.reshape(-1, 2)[ok] = und.reshape(-1, 2)
    return out


def project(matrix: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Ideal pinhole pixels (..., 2) of camera-space points (..., 3)."""
    X = np.asarray(X, dtype=np.float64)
    z = X[..., 2]
    x, y = X[..., 0] / z, X[..., 1] / z
    return np.stack([matrix[0, 0] * x + matrix[0, 1] * y + matrix[0, 2], matrix[1, 1] * y + matrix[1, 2]], axis=-1)


def project_distorted(camera: Camera, X: np.ndarray) -> np.ndarray:
    """Pixels of the real (distorted) image (..., 2) of camera-space points (..., 3); NaN stays NaN."""
    X = np.asarray(X, dtype=np.float64)
    out = np.full(X.shape[:-1] + (2,), np.nan)
    flat = X.reshape(-1, 3)
    ok = np.isfinite(flat).all(axis=1)
    if ok.any():
        px, _ = cv2.projectPoints(flat[ok].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.matrix,
                                  camera.distortion)
        out.reshape(-1, 2)[ok] = px.reshape(-1, 2)
    return out


def project_distorted_fast(camera: Camera, X: np.ndarray) -> np.ndarray:
    """:func:`project_distorted` in NumPy: OpenCV's model (radial k1–k6 as a rational function,
    tangential p1, p2, thin prism s1–s4; fx, fy, cx, cy as ``cv2.projectPoints`` uses them),
    without the Jacobians ``cv2.projectPoints`` always computes — several times faster for many
    points. A tilted-sensor model (τx, τy) goes to OpenCV."""
    d = np.zeros(14)
    given = np.asarray(camera.distortion, dtype=np.float64).ravel()
    d[:len(given)] = given
    if d[12] or d[13]:
        return project_distorted(camera, X)
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d[:12]
    X = np.asarray(X, dtype=np.float64)
    x, y = X[..., 0] / X[..., 2], X[..., 1] / X[..., 2]
    r2 = x * x + y * y
    r4 = r2 * r2
    radial = (1 + (k1 + (k2 + k3 * r2) * r2) * r2) / (1 + (k4 + (k5 + k6 * r2) * r2) * r2)
    xy2 = 2 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + p2 * xy2 + s3 * r2 + s4 * r4
    K = camera.matrix
    return np.stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=-1)


def pixel_rays(matrix: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Directions (..., 3) (z = 1) of the rays from the camera centre through ideal pixels (..., 2)."""
    p = np.asarray(pixels, dtype=np.float64)
    fx, s, cx = matrix[0]
    fy, cy = matrix[1, 1], matrix[1, 2]
    y = (p[..., 1] - cy) / fy
    x = (p[..., 0] - cx - s * y) / fx
    return np.stack([x, y, np.ones_like(x)], axis=-1)
