"""Footage of a known performance, for checking the appearance classification against the truth.

A face (rest mesh with UVs, expression shapes, a take's expression weights and head motion) is
rendered through a known pinhole camera with OpenCV lens distortion, Lambert-lit, with a known
texture: a procedural skin plus, per region, a wrinkle pattern (dark stripes under a smooth
bump) whose strength is the region's **truth activation** (the mean weight of the expressions
that drive it). The classification must recover that activation from the images alone.

Independence from the classifier: this renderer rasterises the truth mesh (the preview's
z-buffer), looks the texture up per pixel through the triangles' UVs with OpenCV's remap, and
distorts the ideal image by remapping it through ``cv2.undistortPoints``; the classifier
projects its template points with ``cv2.projectPoints`` and samples with its own bilinear
lookup, and sees only the written PNG files (with 0.5 % noise, 8-bit).

Used by ``facepipe sample --appearance`` (the synthetic rig) and ``bench/appearance_ict.py``.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np

from facepipe.core.render import rasterize
from facepipe.core.rigid import rigid_fit
from facepipe.core.tangent_frames import vertex_normals
from facepipe.io.atomic import atomic_path

__all__ = ["Scene", "Eye", "eyes_behind", "eye_poses", "head_motion", "iris_colour", "make_scene", "neck_pivot",
           "other_light", "uv_scales", "region_layout",
           "skin_texture", "wrinkle_fields", "render_frame",
           "write_appearance_footage"]


@dataclass
class Scene:
    """Camera (intrinsics, distortion, world → camera pose) and light of a rendering."""

    matrix: np.ndarray
    distortion: np.ndarray
    width: int
    height: int
    rotation: np.ndarray
    translation: np.ndarray
    light: np.ndarray = None      # direction towards the light, camera coordinates
    light_rgb: tuple = (1.0, 1.0, 1.0)
    ambient: float = 0.25
    #: light a surface facing away from the light as if it faced it (``abs`` of the cosine): a
    #: second light as strong exactly opposite, which no set has; the footage before 2026-12 was
    #: lit so, kept to reproduce its figures
    two_sided: bool = False
    #: a second, fill light: the direction towards it times its strength relative to the key
    #: light's (None: the key light alone)
    fill_light: np.ndarray = None

    def to_camera(self, world: np.ndarray) -> np.ndarray:
        return np.asarray(world, dtype=np.float64) @ self.rotation.T + self.translation

    def shading(self, normals: np.ndarray) -> np.ndarray:
        """The light's intensity (...) on unit normals (..., 3) in camera coordinates, before the
        light's colour: ambient plus Lambert's cosine law for a distant point light, nothing from
        it where a surface faces away (a real light's attached shadow: the far side of a fold, the
        inside of the lips, the side of the head turned from it)."""
        cosine = normals @ self.light
        lit = np.abs(cosine) if self.two_sided else np.maximum(cosine, 0.0)
        if self.fill_light is not None:
            lit = lit + np.maximum(normals @ self.fill_light, 0.0)
        return self.ambient + (1.0 - self.ambient) * lit


def make_scene(rest: np.ndarray, size: int = 512, fill: float = 0.75, distortion=(-0.05, 0.02, 0.0, 0.0, 0.0),
               light=(-0.4, -0.5, -1.0), two_sided: bool = False) -> Scene:
    """A camera in front of the face (+z world, +y up) framing ``rest`` to ``fill`` of the image,
    lit from ``light`` (camera coordinates; ``two_sided``: :attr:`Scene.two_sided`)."""
    centre = 0.5 * (rest.min(axis=0) + rest.max(axis=0))
    extent = float(np.max(rest.max(axis=0)[:2] - rest.min(axis=0)[:2]))
    focal = 2.0 * size
    distance = focal * extent / (fill * size) + float(rest[:, 2].max() - centre[2])
    R = np.diag([1.0, -1.0, -1.0])  # OpenCV axes: x right, y down, z forward (into the face)
    t = -R @ centre + np.array([0.0, 0.0, distance])
    K = np.array([[focal, 0.0, 0.5 * (size - 1)], [0.0, focal, 0.5 * (size - 1)], [0.0, 0.0, 1.0]])
    light = np.asarray(light, dtype=np.float64)
    return Scene(K, np.asarray(distortion, dtype=np.float64), size, size, R, t, light / np.linalg.norm(light),
                 two_sided=two_sided)


def uv_scales(rest: np.ndarray, faces: np.ndarray, corner_uv: np.ndarray) -> np.ndarray:
    """(F, 2) surface length per unit of u and of v on every triangle (the columns' norms of the
    Jacobian of the UV → surface map); NaN on triangles degenerate in UV."""
    e3 = np.stack([rest[faces[:, 1]] - rest[faces[:, 0]], rest[faces[:, 2]] - rest[faces[:, 0]]], axis=-1)  # (F,3,2)
    e2 = np.stack([corner_uv[:, 1] - corner_uv[:, 0], corner_uv[:, 2] - corner_uv[:, 0]], axis=-1)  # (F,2,2)
    det = e2[:, 0, 0] * e2[:, 1, 1] - e2[:, 0, 1] * e2[:, 1, 0]
    ok = np.abs(det) > 1e-14
    inv = np.full_like(e2, np.nan)
    inv[ok] = np.linalg.inv(e2[ok])
    return np.linalg.norm(e3 @ inv, axis=1)


def _template_inside(box, mask: np.ndarray) -> bool:
    """Whether a template rectangle and its half-step offsets lie on texels of ``mask`` (the region)."""
    from facepipe.pipeline.appearance_points import template_points  # the points the config's template becomes

    n = mask.shape[0]
    pts = template_points(box, 16).reshape(-1, 2)
    col = np.floor(pts[:, 0] * n).astype(np.int64)
    row = np.floor((1.0 - pts[:, 1]) * n).astype(np.int64)
    inside = (col >= 0) & (col < n) & (row >= 0) & (row < n)
    return bool(inside.all() and mask[row, col].all())


def _box(centre, halves, scale) -> list:
    """UV rectangle [u0, v0, u1, v1] of half-sizes ``halves`` (surface units) about ``centre``."""
    hu, hv = halves[0] / scale[0], halves[1] / scale[1]
    return [float(centre[0] - hu), float(centre[1] - hv), float(centre[0] + hu), float(centre[1] + hv)]


def _elongate(centre, half: float, scale, mask: np.ndarray, most: float = 4.0) -> tuple:
    """The largest-area of the square and the rectangles stretched along u or v (up to ``most``
    times) about ``centre`` that fit in the region (half-sizes in surface units)."""
    best = (half, half)
    for axis in (0, 1):
        for k in np.linspace(1.25, most, 12):
            halves = (half * k, half) if axis == 0 else (half, half * k)
            if not _template_inside(_box(centre, halves, scale), mask):
                break
            if halves[0] * halves[1] > best[0] * best[1]:
                best = halves
    return best


def region_layout(rest: np.ndarray, faces: np.ndarray, corner_uv: np.ndarray, displacements: np.ndarray,
                  share: float = 0.25, resolution: int = 512) -> list:
    """Where each region is, from the displacement (R, V, 3) of its driving expressions.

    A region's surface is the triangles whose vertices all move most for it, by at least
    ``share`` of its largest displacement. Its template is a square on the surface (a rectangle
    in UV, its sides scaled by the UV layout's local stretch) at the place that moves most for
    how deep it lies inside that surface (away from holes such as the eyes and mouth, from the
    UV layout's seams and from the neighbouring regions), as large as fits there. The wrinkle
    pattern is centred on the template and sized to it, in surface units.

    Returns per region: ``vertices`` (its group: the pattern's footprint), ``centre`` (UV),
    ``scale`` (surface length per unit u, v), ``half`` (template half-sizes along u and v, surface
    units; a thin region's template is stretched along it),
    ``template`` [u0, v0, u1, v1] and the stripes' ``angle`` and ``wavelength`` (surface units).
    """
    from scipy import ndimage

    from facepipe.pipeline.appearance_points import texel_map

    mag = np.linalg.norm(displacements, axis=-1)  # (R, V)
    owner = np.argmax(mag, axis=0)
    scales = uv_scales(rest, faces, corner_uv)
    texel_face, texel_bary = texel_map(corner_uv, resolution)
    covered = texel_face >= 0
    tf = np.maximum(texel_face, 0)
    vertex_uv = np.zeros((rest.shape[0], 2))
    vertex_uv[faces.ravel()] = corner_uv.reshape(-1, 2)
    rows, cols = np.mgrid[0:resolution, 0:resolution]
    texel_uv = np.stack([(cols + 0.5) / resolution, 1.0 - (rows + 0.5) / resolution], axis=-1)
    out = []
    for r in range(mag.shape[0]):
        moving = (owner == r) & (mag[r] >= share * mag[r].max())
        tri = moving[faces].all(axis=1) & np.isfinite(scales).all(axis=1)
        mask = covered & tri[tf]
        if not mask.any():
            raise ValueError(f"region {r}: no triangle moves mostly for it")
        ju, jv = np.median(scales[tri], axis=0)
        # depth in surface units: distance to the region's border in UV, each axis by its stretch
        depth = ndimage.distance_transform_edt(mask, sampling=(jv / resolution, ju / resolution))
        moved = np.einsum("hwk,hwk->hw", texel_bary, mag[r][faces[tf]]) * mask
        i, j = np.unravel_index(np.argmax(depth * moved), mask.shape)
        centre = texel_uv[i, j]
        near = mask & (np.hypot((texel_uv[..., 0] - centre[0]) * ju, (texel_uv[..., 1] - centre[1]) * jv)
                       <= depth[i, j])
        ju, jv = np.median(scales[texel_face[near]], axis=0)  # the stretch where the template lies
        half = 0.7 * float(depth[i, j])  # its corners (and half-step offsets) about at the depth
        for _ in range(20):
            if _template_inside(_box(centre, (half, half), (ju, jv)), mask):
                break
            half *= 0.85
        halves = _elongate(centre, half, (ju, jv), mask)  # along a thin region (an eyelid) as far as it fits
        d = np.hypot((vertex_uv[:, 0] - centre[0]) * ju / halves[0], (vertex_uv[:, 1] - centre[1]) * jv / halves[1])
        angle = float(np.pi * ((r * 0.37) % 1.0))
        out.append({"centre": centre, "scale": np.array([ju, jv]), "half": np.array(halves),
                    "template": _box(centre, halves, (ju, jv)), "wavelength": _wavelength(halves, angle),
                    "angle": angle, "vertices": np.flatnonzero(d < 3.0)})
    return out


def _wavelength(halves, angle: float, template_size: int = 16) -> float:
    """The stripes' wavelength (surface units): two thirds of the template's shorter half-size,
    and at least three times the Nyquist wavelength of the template's grid along the stripes'
    direction of change (a stretched template's grid is coarse along its length: stripes finer
    than its points alias, and no template of that grid could tell their strength)."""
    step_u, step_v = 2.0 * halves[0] / template_size, 2.0 * halves[1] / template_size
    nyquist = 2.0 * max(step_u * abs(np.cos(angle)), step_v * abs(np.sin(angle)))
    return float(max(2.0 * min(halves) / 3.0, 3.0 * nyquist))


def skin_texture(size: int, seed: int = 0) -> np.ndarray:
    """(size, size, 3) float32 skin: a tone, low-frequency blotches and fine pores."""
    rng = np.random.default_rng(seed)
    coarse = cv2.GaussianBlur(rng.normal(size=(size, size)).astype(np.float32), (0, 0), size / 40)
    fine = cv2.GaussianBlur(rng.normal(size=(size, size)).astype(np.float32), (0, 0), 0.8)
    lum = 1.0 + 0.6 * coarse / max(coarse.std(), 1e-6) * 0.08 + 0.04 * fine / max(fine.std(), 1e-6)
    tone = np.array([0.78, 0.58, 0.48], dtype=np.float32)
    return np.clip(lum[..., None] * tone, 0.0, 1.0).astype(np.float32)


def wrinkle_fields(size: int, layout: list) -> np.ndarray:
    """(R, size, size) darkening of each region at full activation: stripes under a smooth bump
    covering its template, in surface units (the UV stretch undone)."""
    v, u = np.meshgrid(1.0 - (np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size, indexing="ij")
    fields = []
    for o in layout:
        x = (u - o["centre"][0]) * o["scale"][0]
        y = (v - o["centre"][1]) * o["scale"][1]
        bump = np.exp(-0.5 * ((x / (1.2 * o["half"][0])) ** 2 + (y / (1.2 * o["half"][1])) ** 2))
        s = x * np.cos(o["angle"]) + y * np.sin(o["angle"])
        stripes = 0.5 * (1.0 + np.cos(2 * np.pi * s / o["wavelength"]))
        fields.append((0.55 * bump * stripes ** 2).astype(np.float32))
    return np.stack(fields)


def _distortion_maps(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of the distorted image, where it lies in the ideal pinhole image."""
    ys, xs = np.mgrid[0:scene.height, 0:scene.width].astype(np.float64)
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(pts, scene.matrix, scene.distortion, P=scene.matrix).reshape(scene.height,
                                                                                              scene.width, 2)
    return ideal[..., 0].astype(np.float32), ideal[..., 1].astype(np.float32)


@dataclass
class Eye:
    """An eyeball behind an eye opening, in head space: centre, radius and its axes at rest
    (columns: right, up, forward — the gaze at rest)."""

    centre: np.ndarray
    radius: float
    axes: np.ndarray


def eyes_behind(rest: np.ndarray, rims: list) -> list:
    """An eyeball behind each eye opening (its rim's vertex loop): radius 0.55 × the opening's
    width, its front 10 % of the radius behind the rim's centre, looking along the rim's normal
    (the side the face looks to: +z, the camera's side in the scene)."""
    eyes = []
    for rim in rims:
        P = rest[np.asarray(rim)]
        c = P.mean(axis=0)
        _, _, vt = np.linalg.svd(P - c, full_matrices=False)
        forward = vt[2] if vt[2][2] >= 0 else -vt[2]
        width = float(np.ptp((P - c) @ vt[0]))
        radius = 0.55 * width
        right = np.cross([0.0, 1.0, 0.0], forward)
        right /= np.linalg.norm(right)
        eyes.append(Eye(c - 1.1 * radius * forward, radius, np.stack([right, np.cross(forward, right), forward], 1)))
    return eyes


def _sphere(n_lon: int = 48, n_lat: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A unit UV sphere's vertices (N, 3) and outward-wound triangles (T, 3), poles on ±z."""
    lat = np.linspace(0.0, np.pi, n_lat + 1)
    lon = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    th, ph = np.meshgrid(lat, lon, indexing="ij")
    verts = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    idx = np.arange((n_lat + 1) * n_lon).reshape(n_lat + 1, n_lon)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    tri = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return verts, tri


def iris_colour(local: np.ndarray) -> np.ndarray:
    """(N, 3) albedo of an eyeball at unit directions (N, 3) in its own axes (the gaze along +z):
    pupil, an iris with radial fibres and a darker limbus, sclera."""
    theta = np.arccos(np.clip(local[:, 2], -1.0, 1.0))
    phi = np.arctan2(local[:, 1], local[:, 0])
    fibres = 0.8 + 0.2 * np.cos(14 * phi) * np.cos(40 * theta)
    iris = np.array([0.28, 0.40, 0.52]) * fibres[:, None] * (1.0 - 0.5 * np.clip((theta - 0.36) / 0.1, 0, 1))[:, None]
    out = np.where((theta < 0.46)[:, None], iris, np.array([0.86, 0.84, 0.80]))
    return np.where((theta < 0.17)[:, None], np.array([0.04, 0.04, 0.05]), out).astype(np.float32)


def render_frame(world: np.ndarray, faces: np.ndarray, corner_uv: np.ndarray, texture: np.ndarray, scene: Scene,
                 maps=None, background: float = 0.12, eyes=(), with_coverage: bool = False):
    """(H, W, 3) float image of the textured, lit mesh through the scene's camera (before noise);
    with ``with_coverage`` also the share (H, W) of each pixel the mesh covers (its silhouette
    through the lens distortion's resampling).

    world : (V, 3); faces : (F, 3); corner_uv : (F, 3, 2) UVs of the triangles' corners.
    eyes : eyeballs (world centre (3,), world axes (3, 3) with the gaze as the third column,
    radius) drawn with the mesh (its lids cover them), their colour from :func:`iris_colour`.
    """
    n_skin, n_faces = len(world), len(faces)
    if len(eyes):
        unit, tri = _sphere()
        world = np.concatenate([world] + [centre + radius * unit @ axes.T for centre, axes, radius in eyes])
        faces = np.concatenate([faces] + [tri + n_skin + k * len(unit) for k in range(len(eyes))])
    cam = scene.to_camera(world)
    K = scene.matrix
    pixels = np.stack([K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]], 1)
    face, bary = rasterize(pixels, -cam[:, 2], faces, scene.width, scene.height)
    drawn = (face >= 0).astype(np.float32)
    img = np.full((scene.height, scene.width, 3), background, dtype=np.float32)
    if len(eyes):
        on_eye = face >= n_faces
        k_eye = (face[on_eye] - n_faces) // len(tri)
        point = np.einsum("nk,nkc->nc", bary[on_eye], world[faces[face[on_eye]]])
        colour = np.zeros((len(point), 3), dtype=np.float32)
        shade = np.zeros(len(point))
        for k, (centre, axes, radius) in enumerate(eyes):
            sel = k_eye == k
            d = (point[sel] - centre) / radius
            d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
            colour[sel] = iris_colour(d @ axes)
            shade[sel] = scene.shading(d @ scene.rotation.T)
        img[on_eye] = colour * (shade[:, None] * np.asarray(scene.light_rgb, dtype=np.float32))
        face = np.where(on_eye, -1, face)
    hit = face >= 0
    f, b = face[hit], bary[hit]
    uv = np.einsum("nk,nkc->nc", b, corner_uv[f])
    height, width = texture.shape[:2]
    # OpenCV's remap wants maps under 32767 rows: the lookups as rows of 1024
    n_hit = uv.shape[0]
    pad = (-n_hit) % 1024
    tx = np.r_[uv[:, 0] * width - 0.5, np.zeros(pad)].astype(np.float32).reshape(-1, 1024)
    ty = np.r_[(1.0 - uv[:, 1]) * height - 0.5, np.zeros(pad)].astype(np.float32).reshape(-1, 1024)
    albedo = cv2.remap(texture, tx, ty, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)[:n_hit]
    normals = vertex_normals(cam[:n_skin], faces[:n_faces])
    n = np.einsum("nk,nkc->nc", b, normals[faces[f]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    img[hit] = albedo * (scene.shading(n)[:, None] * np.asarray(scene.light_rgb))
    mx, my = maps if maps is not None else _distortion_maps(scene)
    image = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if not with_coverage:
        return image
    return image, cv2.remap(drawn, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _write_png(path: Path, image: np.ndarray, rng: np.random.Generator, noise: float) -> None:
    noisy = image + noise * rng.normal(size=image.shape)
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, np.clip(np.round(noisy * 255), 0, 255).astype(np.uint8), extension=".png")


def write_appearance_footage(folder, world_frames: np.ndarray, activations: np.ndarray, faces, corner_uv,
                             skin: np.ndarray, fields: np.ndarray, scene: Scene, *, noise: float = 0.005,
                             seed: int = 0, numbers=None, progress=None, eyes=None) -> list[Path]:
    """Render and write ``folder/frame_NNNN.png`` for every frame: geometry (T, V, 3) world, the
    regions' activations (T, R) scaling their wrinkle fields (R, S, S) on the skin (S, S, 3);
    ``eyes``: per frame the eyeballs to draw (see :func:`render_frame`)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    maps = _distortion_maps(scene)
    numbers = np.arange(len(world_frames)) if numbers is None else numbers
    paths = []
    for k, (positions, a) in enumerate(zip(world_frames, activations)):
        dark = np.tensordot(np.asarray(a, dtype=np.float32), fields, axes=1)
        texture = np.ascontiguousarray(skin * np.clip(1.0 - dark, 0.0, 1.0)[..., None], dtype=np.float32)
        path = folder / f"frame_{int(numbers[k]):04d}.png"
        _write_png(path, render_frame(positions, faces, corner_uv, texture, scene, maps,
                                      eyes=() if eyes is None else eyes[k]), rng, noise)
        paths.append(path)
        if progress is not None:
            progress(1)
    return paths


def scene_json(scene: Scene) -> str:
    """The scene's camera as the calibration JSON :func:`facepipe.io.camera_file.read_camera` reads."""
    return json.dumps({"image_width": scene.width, "image_height": scene.height,
                       "camera_matrix": scene.matrix.tolist(), "dist_coeffs": scene.distortion.tolist()}, indent=1)


def _activations(weights: np.ndarray, names: list, drivers: dict) -> np.ndarray:
    """(T, R) the mean weight of each region's driving expressions."""
    index = {n: i for i, n in enumerate(names)}
    return np.stack([weights[:, [index[d] for d in ds]].mean(axis=1) for ds in drivers.values()], axis=1)


def _yaw_pitch(yaw: float, pitch: float) -> np.ndarray:
    """Rotation by ``pitch`` about x, then ``yaw`` about y (radians)."""
    Ry = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(pitch), -np.sin(pitch)], [0, np.sin(pitch), np.cos(pitch)]])
    return Ry @ Rx


def _head_turns(frames: int, degrees: float) -> np.ndarray:
    """(T, 3, 3) head rotations: yaw sweeping ±degrees and pitch ±degrees/3 over the take."""
    T = max(frames, 1)
    return np.stack([_yaw_pitch(np.deg2rad(degrees) * np.sin(2 * np.pi * f / T),
                                np.deg2rad(degrees / 3) * np.sin(4 * np.pi * f / T)) for f in range(frames)])


def neck_pivot(rest: np.ndarray) -> np.ndarray:
    """The point the test footage turns the head about: bottom, back and middle of the rest mesh."""
    return np.array([0.5 * (rest[:, 0].min() + rest[:, 0].max()), rest[:, 1].min(), rest[:, 2].min()])


def other_light(scene: Scene) -> Scene:
    """The scene lit as the turned take is: a warm light from the other side, more ambient."""
    return dataclasses.replace(scene, light=np.array([0.6, -0.2, -0.8]) / np.linalg.norm([0.6, -0.2, -0.8]),
                               light_rgb=(1.0, 0.9, 0.75), ambient=0.3)


def key_and_fill(scene: Scene, fill: float = 0.4) -> Scene:
    """The scene lit as a set is: its light as the key, and a fill light of ``fill`` times its
    strength from the other side (mirrored across the face's vertical plane, from lower down),
    with less ambient: a shading no single light gives."""
    key = np.asarray(scene.light, dtype=np.float64)
    other = np.array([-key[0], -0.5 * key[1], key[2]])
    return dataclasses.replace(scene, fill_light=fill * other / np.linalg.norm(other), ambient=0.15)


def _head_turn(world: np.ndarray, degrees: float, pivot: np.ndarray) -> np.ndarray:
    """World frames turned about ``pivot`` by :func:`_head_turns`."""
    return np.einsum("fij,fvj->fvi", _head_turns(len(world), degrees), world - pivot) + pivot


def head_motion(rest: np.ndarray, expressions: dict, world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The head's rigid motion (T, 3, 3), (T, 3) in frames (T, V, 3): world = R @ head + t, fitted
    to the vertices no expression moves (the back of the head; the tenth that move least where
    every vertex moves)."""
    moved = np.max([np.linalg.norm(e - rest, axis=1) for e in expressions.values()], axis=0)
    still = np.flatnonzero(moved <= 1e-9 * np.ptp(rest))
    if len(still) < 3:
        still = np.argsort(moved)[:max(3, len(rest) // 10)]
    return rigid_fit(rest[still], np.asarray(world, dtype=np.float64)[:, still])


def eye_poses(eyes: list, weights: np.ndarray, gaze: np.ndarray, rotations: np.ndarray | None = None,
              translations: np.ndarray | None = None) -> list:
    """Per frame the eyeballs to draw (world centre, axes, radius): each eye turned by the frame's
    gaze — yaw and pitch (degrees) ``weights`` (T, K) @ ``gaze`` (K, E, 2), expression k turning
    eye e by gaze[k, e] at full weight — and carried by the head's motion (T, 3, 3), (T, 3)
    (world = R @ head + t; none: the head at rest)."""
    angles = np.deg2rad(np.einsum("tk,kec->tec", weights, gaze))
    out = []
    for f in range(len(weights)):
        R = np.eye(3) if rotations is None else rotations[f]
        t = np.zeros(3) if translations is None else translations[f]
        out.append([(R @ eye.centre + t, R @ eye.axes @ _yaw_pitch(*angles[f, e]), eye.radius)
                    for e, eye in enumerate(eyes)])
    return out


def write_appearance_kit(out_dir, mesh, rest: np.ndarray, expressions: dict, drivers: dict, take_world: np.ndarray,
                         take_weights: np.ndarray, take_names: list, *, mesh_path: str, markers_path: str,
                         layers: int = 5, size: int = 512, texture_size: int = 512, turn_degrees: float = 15.0,
                         noise: float = 0.005, seed: int = 0, progress=None, eyes: dict | None = None,
                         gaze: dict | None = None, two_sided_light: bool = False, rom_degrees: float = 10.0) -> dict:
    """Write footage of a known performance and an appearance config for it into ``out_dir``.

    expressions : name → (V, 3) positions at weight 1; drivers : region → expression names.
    take_world (T, V, 3), take_weights (T, K) with take_names: the performance.
    eyes : region → the rim (vertex loop) of the eye opening it looks into: an eyeball is drawn
    behind each (:func:`eyes_behind`) and the region is a card across the opening; gaze :
    expression → (region, yaw, pitch), the degrees it turns that region's eyeball at full weight.
    two_sided_light: light as the footage before 2026-12 was (:attr:`Scene.two_sided`).
    Writes ``camera.json``, ``examples/`` (per region, its drivers at ``layers`` strengths from 0 to
    1, frame 0 neutral; then every expression that drives no region at full strength and the
    neutral face with the head turned ``rom_degrees`` left, right, up and down, the config's
    ``rest_frames``: the range of motion an actor would show) with ``examples.npz``,
    ``take/`` and ``take_turned/`` (the head turned up to ``turn_degrees`` and another light) each
    with its geometry ``.npz`` (positions in world space, frame numbers) and truth ``_truth.csv``
    (activation per region), ``regions/NAME.txt`` and ``appearance.toml``. Returns the paths and
    the layout.
    """
    out = Path(out_dir)
    (out / "regions").mkdir(parents=True, exist_ok=True)
    faces = mesh.faces
    corner_uv = mesh.uvs[mesh.face_uvs]
    names = list(drivers)
    eyes, gaze = eyes or {}, gaze or {}
    disp = np.stack([np.mean([expressions[d] - rest for d in drivers[r]], axis=0) for r in names])
    surface = [r for r, name in enumerate(names) if name not in eyes]
    on_skin = iter(region_layout(rest, faces, corner_uv, disp[surface]))
    # a card's template: the middle of its own square (the card fills it with the opening)
    layout = [{"vertices": np.asarray(eyes[name]), "template": [0.2, 0.2, 0.8, 0.8], "card": True} if name in eyes
              else next(on_skin) for name in names]
    skin = skin_texture(texture_size, seed)
    fields = np.zeros((len(names), texture_size, texture_size), dtype=np.float32)
    fields[surface] = wrinkle_fields(texture_size, [layout[r] for r in surface])
    eye_names = list(eyes)
    eyeballs = eyes_behind(rest, [eyes[n] for n in eye_names])
    scene = make_scene(rest, size, two_sided=two_sided_light)
    (out / "camera.json").write_text(scene_json(scene))

    # examples: neutral, then each region's drivers at increasing strength, alone
    strengths = np.linspace(0.0, 1.0, layers)[1:]
    expression_names = sorted(expressions)
    column = {n: k for k, n in enumerate(expression_names)}
    no_weights = np.zeros(len(expression_names))
    ex_world, ex_act, ex_weights, frames = [rest], [np.zeros(len(names))], [no_weights], {}
    for r, name in enumerate(names):
        frames[name] = [0]
        for s in strengths:
            ex_world.append(rest + s * disp[r])  # each driver at s / (its region's drivers)
            a = np.zeros(len(names))
            a[r] = s
            ex_act.append(a)
            w = no_weights.copy()
            w[[column[d] for d in drivers[name]]] = s / len(drivers[name])
            ex_weights.append(w)
            frames[name].append(len(ex_world) - 1)
    driving = {d for ds in drivers.values() for d in ds}
    rest_frames = []
    for name in sorted(set(expressions) - driving):  # other expressions: every region at rest
        ex_world.append(expressions[name])
        ex_act.append(np.zeros(len(names)))
        w = no_weights.copy()
        w[column[name]] = 1.0
        ex_weights.append(w)
        rest_frames.append(len(ex_world) - 1)
    # the head turned with the face at rest: what a take's head motion does to every region
    pivot = neck_pivot(rest)
    for yaw, pitch in ((rom_degrees, 0.0), (-rom_degrees, 0.0), (0.0, rom_degrees), (0.0, -rom_degrees)) if rom_degrees else ():
        ex_world.append((rest - pivot) @ _yaw_pitch(np.deg2rad(yaw), np.deg2rad(pitch)).T + pivot)
        ex_act.append(np.zeros(len(names)))
        ex_weights.append(no_weights)
        rest_frames.append(len(ex_world) - 1)
    ex_world = np.asarray(ex_world)

    def gaze_table(expression_list):  # (K, E, 2): the degrees each expression turns each eyeball
        table = np.zeros((len(expression_list), len(eye_names), 2))
        for k, n in enumerate(expression_list):
            if n in gaze:
                region, yaw, pitch = gaze[n]
                table[k, eye_names.index(region)] = (yaw, pitch)
        return table

    ex_eyes = eye_poses(eyeballs, np.asarray(ex_weights), gaze_table(expression_names),
                        *head_motion(rest, expressions, ex_world)) if eyes else None
    write_appearance_footage(out / "examples", ex_world, np.asarray(ex_act), faces, corner_uv, skin, fields, scene,
                             noise=noise, seed=seed + 1, progress=progress, eyes=ex_eyes)
    _save_geometry(out / "examples.npz", ex_world, np.arange(len(ex_world)))

    truth = _activations(take_weights, take_names, drivers)
    variants = {"take": (take_world, scene),
                "take_turned": (_head_turn(take_world, turn_degrees, neck_pivot(rest)), other_light(scene))}
    for k, (world, sc) in enumerate(variants.values()):
        key = list(variants)[k]
        # the eyeballs move with the head: the take's own head motion, and the turn
        take_eyes = eye_poses(eyeballs, take_weights, gaze_table(take_names),
                              *head_motion(rest, expressions, world)) if eyes else None
        write_appearance_footage(out / key, world, truth, faces, corner_uv, skin, fields, sc, noise=noise,
                                 seed=seed + 2 + k, progress=progress, eyes=take_eyes)
        _save_geometry(out / f"{key}.npz", world, np.arange(len(world)))
        _write_truth(out / f"{key}_truth.csv", names, truth)
    for name, o in zip(names, layout):
        (out / "regions" / f"{name}.txt").write_text("".join(f"{v}\n" for v in o["vertices"].tolist()))
    config = out / "appearance.toml"
    config.write_text(_config_text(mesh_path, markers_path, names, layout, frames, scene, texture_size, rest_frames))
    return {"config": str(config), "regions": names, "layout": layout, "examples": len(ex_world),
            "frames": len(take_world)}


def _save_geometry(path: Path, world: np.ndarray, numbers: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        np.savez(tmp, positions=np.asarray(world, dtype=np.float32), frame=np.asarray(numbers, dtype=np.int32))


def _write_truth(path: Path, names: list, truth: np.ndarray) -> None:
    rows = "".join(f"{f}," + ",".join(f"{x:.6f}" for x in row) + "\n" for f, row in enumerate(truth))
    path.write_text("frame," + ",".join(names) + "\n" + rows)


def _config_text(mesh_path, markers_path, names, layout, frames, scene: Scene, texture_size: int,
                 rest_frames=()) -> str:
    lines = ["[rig]", f'mesh = "{mesh_path}"', f'markers = "{markers_path}"', "", "[appearance]",
             'camera = "camera.json"', f"camera_rotation = {scene.rotation.tolist()}",
             f"camera_translation = {scene.translation.tolist()}", 'footage = "examples/frame_%04d.png"',
             'geometry = "examples.npz"', "neutral_frame = 0", f"texture_size = {texture_size}",
             f"rest_frames = {list(rest_frames)}", ""]
    for name, o in zip(names, layout):
        lines += [f"[appearance.regions.{name}]", f'vertices = "regions/{name}.txt"',
                  f"template = [{', '.join(f'{x:.5f}' for x in o['template'])}]",
                  f"frames = {frames[name]}"] + (["card = true"] if o.get("card") else []) + [""]
    return "\n".join(lines)
