"""A small software renderer for previews: z-buffer, per-pixel Lambert shading; orthographic
cameras framing a mesh, or a calibrated pinhole camera with OpenCV's lens distortion (a 2D take's
face drawn where the footage shows it).

No display and no OpenGL: triangles are rasterised with NumPy in one vectorised pass
(every triangle's bounding box of pixel centres is enumerated, the nearest surface wins
per pixel), so a 600k-vertex mesh renders in seconds at preview sizes. Normals are
interpolated per pixel from the vertex normals, which shows wrinkles at the mesh's
resolution rather than the triangles' facets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facepipe.core.raster import triangle_pixels
from facepipe.core.tangent_frames import vertex_normals


@dataclass
class Camera:
    """An orthographic camera.

    Attributes
    ----------
    rotation : (3, 3) rows are the camera's right, up and backward axes in world space
        (camera coordinates = rotation @ world; +z points to the viewer).
    center : (2,) camera-plane point at the image centre.
    scale : pixels per length unit.
    width, height : image size in pixels.
    """

    rotation: np.ndarray
    center: np.ndarray
    scale: float
    width: int
    height: int

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (…, 2) (x right, y down; pixel centres at integers) and depth (…)
        (larger = nearer the viewer) of world points (…, 3)."""
        c = np.asarray(points, dtype=np.float64) @ self.rotation.T
        x = (c[..., 0] - self.center[0]) * self.scale + 0.5 * self.width - 0.5
        y = -(c[..., 1] - self.center[1]) * self.scale + 0.5 * self.height - 0.5
        return np.stack([x, y], axis=-1), c[..., 2]


@dataclass
class PinholeCamera:
    """A calibrated camera looking at points given in its own coordinates (OpenCV axes: x right,
    y down, z forward), drawing them where the (distorted) footage shows them.

    Attributes
    ----------
    matrix : (3, 3) [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in pixels of this image.
    distortion : (N,) OpenCV's coefficients, N in {0, 4, 5, 8, 12, 14}.
    width, height : image size in pixels.
    """

    matrix: np.ndarray
    distortion: np.ndarray
    width: int
    height: int

    @property
    def rotation(self) -> np.ndarray:
        """Camera axes → the renderer's view axes (x right, y up, +z toward the viewer)."""
        return np.diag([1.0, -1.0, -1.0])

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (…, 2) and depth 1/z (…) (larger = nearer; affine across a triangle's image, so
        the z-buffer compares true depths) of camera-space points (…, 3); NaN behind the camera."""
        X = np.asarray(points, dtype=np.float64)
        pix = pinhole_project(self.matrix, self.distortion, X)
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.where(X[..., 2] > 0, 1.0 / X[..., 2], np.nan)
        return np.where(np.isfinite(depth)[..., None], pix, np.nan), depth


def pinhole_project(matrix: np.ndarray, distortion: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixels (…, 2) of camera-space points (…, 3) through OpenCV's camera model.

    The model of ``cv2.projectPoints``: x = X/Z, y = Y/Z; radial (k1 k2 k3 over k4 k5 k6),
    tangential (p1 p2) and thin-prism (s1 … s4) distortion, then the sensor tilt (τx τy), then
    u = fx x'' + s y'' + cx, v = fy y'' + cy (OpenCV ignores the skew s; it is 0 in its
    calibrations). Points at Z = 0 give inf/NaN.

    Parameters
    ----------
    matrix : (3, 3) camera matrix; distortion : (N,), N in {0, 4, 5, 8, 12, 14}.
    """
    K = np.asarray(matrix, dtype=np.float64)
    d = np.zeros(14)
    dist = np.asarray(distortion, dtype=np.float64).reshape(-1)
    if dist.size not in (0, 4, 5, 8, 12, 14):
        raise ValueError(f"{dist.size} distortion coefficients: OpenCV's model has 0, 4, 5, 8, 12 or 14")
    d[:dist.size] = dist
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tau_x, tau_y = d
    X = np.asarray(points, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = X[..., 0] / X[..., 2], X[..., 1] / X[..., 2]
        r2 = x * x + y * y
        r4 = r2 * r2
        radial = (1 + k1 * r2 + k2 * r4 + k3 * r4 * r2) / (1 + k4 * r2 + k5 * r4 + k6 * r4 * r2)
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
        if tau_x or tau_y:
            tilted = np.stack([xd, yd, np.ones_like(xd)], axis=-1) @ _tilt(tau_x, tau_y).T
            xd, yd = tilted[..., 0] / tilted[..., 2], tilted[..., 1] / tilted[..., 2]
    return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=-1)


def _tilt(tau_x: float, tau_y: float) -> np.ndarray:
    """OpenCV's tilted-sensor projection (``computeTiltProjectionMatrix``): a Scheimpflug sensor
    rotated by τx about x and τy about y, projected back along the optical axis."""
    cx, sx, cy, sy = np.cos(tau_x), np.sin(tau_x), np.cos(tau_y), np.sin(tau_y)
    rot_x = np.array([[1, 0, 0], [0, cx, sx], [0, -sx, cx]])
    rot_y = np.array([[cy, 0, -sy], [0, 1, 0], [sy, 0, cy]])
    rot = rot_y @ rot_x
    proj = np.array([[rot[2, 2], 0, -rot[0, 2]], [0, rot[2, 2], -rot[1, 2]], [0, 0, 1]])
    return proj @ rot


def image_window(matrix: np.ndarray, x0: float, y0: float, scale: float) -> np.ndarray:
    """The camera matrix of a window of an image: the part from pixel (x0, y0) on, resampled by
    ``scale`` (pixel centres at integers in both images: u' = (u − x0 + ½)·scale − ½)."""
    K = np.asarray(matrix, dtype=np.float64).copy()
    K[:2, :] *= scale
    K[0, 2] = (matrix[0, 2] - x0 + 0.5) * scale - 0.5
    K[1, 2] = (matrix[1, 2] - y0 + 0.5) * scale - 0.5
    K[2] = [0.0, 0.0, 1.0]
    return K


def frame_camera(points: np.ndarray, forward: np.ndarray, width: int = 512, up=(0.0, 1.0, 0.0),
                 margin: float = 0.04) -> Camera:
    """A camera looking at ``points`` against ``forward`` (the direction the face looks),
    framing their extent with a margin; the height follows from the extent's aspect.

    Parameters
    ----------
    points : (V, 3) the geometry to frame (e.g. the rest mesh).
    forward : (3,) direction from the subject towards the camera.
    width : image width in pixels.
    up : (3,) world direction that should point up in the image (projected).
    """
    back = np.asarray(forward, dtype=np.float64)
    back = back / np.linalg.norm(back)
    up = np.asarray(up, dtype=np.float64)
    up = up - (up @ back) * back
    if np.linalg.norm(up) < 1e-6:  # looking along the up axis: any perpendicular will do
        up = np.cross(back, [1.0, 0.0, 0.0]) if abs(back[0]) < 0.9 else np.cross(back, [0.0, 1.0, 0.0])
    up = up / np.linalg.norm(up)
    right = np.cross(up, back)
    R = np.stack([right, up, back])
    c = np.asarray(points, dtype=np.float64) @ R.T
    lo, hi = c[:, :2].min(axis=0), c[:, :2].max(axis=0)
    extent = np.maximum(hi - lo, 1e-12) * (1 + 2 * margin)
    scale = width / extent[0]
    height = max(1, int(round(extent[1] * scale)))
    return Camera(R, 0.5 * (lo + hi), float(scale), int(width), height)


def rasterize(pixels: np.ndarray, depth: np.ndarray, faces: np.ndarray, width: int, height: int,
              chunk: int = 1 << 22) -> tuple[np.ndarray, np.ndarray]:
    """Visible triangle and barycentric coordinates per pixel (a z-buffer).

    Parameters
    ----------
    pixels : (V, 2) pixel coordinates (x, y; centres at integers); depth : (V,) larger = nearer.
    faces : (T, 3) triangles.

    Returns
    -------
    face : (height, width) int64, the visible triangle (−1 for background).
    bary : (height, width, 3) float64 barycentric coordinates in it.
    """
    faces = np.asarray(faces, dtype=np.int64)
    p = pixels[faces]  # (T, 3, 2)
    z = depth[faces]  # (T, 3)
    e1 = p[:, 1] - p[:, 0]
    e2 = p[:, 2] - p[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = np.abs(det) > 1e-12
    x0 = np.clip(np.ceil(p[..., 0].min(axis=1)), 0, width).astype(np.int64)
    x1 = np.clip(np.floor(p[..., 0].max(axis=1)), -1, width - 1).astype(np.int64)
    y0 = np.clip(np.ceil(p[..., 1].min(axis=1)), 0, height).astype(np.int64)
    y1 = np.clip(np.floor(p[..., 1].max(axis=1)), -1, height - 1).astype(np.int64)

    n_pix = width * height
    zbuf = np.full(n_pix, -np.inf)
    face = np.full(n_pix, -1, dtype=np.int64)
    bary = np.zeros((n_pix, 3))
    for t, row, col, b0, b1, b2 in triangle_pixels(p, ok, x0, x1, y0, y1, chunk):
        pix = row * width + col
        zc = b0 * z[t, 0] + b1 * z[t, 1] + b2 * z[t, 2]
        # nearest candidate per pixel: sort by (pixel, depth), keep each pixel's last
        order = np.lexsort((zc, pix))
        pix, zc = pix[order], zc[order]
        last = np.r_[pix[1:] != pix[:-1], True]
        sel = order[last]
        pix, zc = pix[last], zc[last]
        nearer = zc > zbuf[pix]
        pix, sel = pix[nearer], sel[nearer]
        zbuf[pix] = zc[nearer]
        face[pix] = t[sel]
        bary[pix] = np.stack([b0[sel], b1[sel], b2[sel]], axis=1)
    return face.reshape(height, width), bary.reshape(height, width, 3)


def render(vertices: np.ndarray, faces: np.ndarray, camera: Camera, colors: np.ndarray | None = None,
           background=(1.0, 1.0, 1.0), light=(-0.35, 0.45, 1.0), ambient: float = 0.18) -> np.ndarray:
    """Shade a mesh: two-sided Lambert with per-pixel normals, optional per-vertex colours.

    Parameters
    ----------
    vertices : (V, 3); faces : (T, 3).
    camera : from :func:`frame_camera`, or a :class:`PinholeCamera` (vertices in its coordinates).
    colors : (V, 3) RGB in [0, 1] per vertex (interpolated), or None for light grey.
    light : (3,) light direction in camera coordinates (towards the light; +z = the viewer).
    ambient : the unlit fraction.

    Returns
    -------
    (height, width, 3) float RGB image in [0, 1].
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    pix, depth = camera.project(vertices)
    seen = np.isfinite(pix).all(axis=1) & np.isfinite(depth)
    if not seen.all():  # (a pinhole camera: triangles reaching behind it are not drawn)
        faces = faces[seen[faces].all(axis=1)]
        pix, depth = np.where(seen[:, None], pix, 0.0), np.where(seen, depth, 0.0)
    face, bary = rasterize(pix, depth, faces, camera.width, camera.height)
    img = np.empty((camera.height, camera.width, 3))
    img[:] = background
    hit = face >= 0
    if not hit.any():
        return img
    f = face[hit]
    b = bary[hit]
    corners = faces[f]  # (n, 3)
    normals = vertex_normals(vertices, faces) @ camera.rotation.T
    n = np.einsum("nk,nkc->nc", b, normals[corners])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    light = np.asarray(light, dtype=np.float64)
    light = light / np.linalg.norm(light)
    lambert = np.abs(n @ light)  # two-sided: the inside of lips and eyelids is lit too
    shade = ambient + (1 - ambient) * lambert
    if colors is None:
        base = np.full((f.shape[0], 3), 0.82)
    else:
        base = np.einsum("nk,nkc->nc", b, np.asarray(colors, dtype=np.float64)[corners])
    img[hit] = np.clip(base * shade[:, None], 0.0, 1.0)
    return img


def view_direction(model) -> np.ndarray:
    """The direction the face looks in the rest pose: the mean normal at the markers."""
    n = vertex_normals(model.rest.astype(np.float64), model.triangles.astype(np.int64))
    d = n[model.handle_vertices].sum(axis=0)
    if np.linalg.norm(d) < 1e-9:
        d = np.array([0.0, 0.0, 1.0])
    return d / np.linalg.norm(d)
