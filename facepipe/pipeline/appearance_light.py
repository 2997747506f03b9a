"""Each frame's light, fitted at the appearance model's light points (:mod:`facepipe.core.lighting`).

The nine-term grey light that the stream carries (:func:`frame_lights`), its colour
(:func:`frame_colours`), and the shading that a frame's template patches are divided by under
the model's light model (:func:`frame_shading`).
"""

from __future__ import annotations

import numpy as np

from facepipe.core import appearance as ap, lighting
from facepipe.core.camera import project_distorted_fast
from facepipe.io.appearance_file import AppearanceModel
from facepipe.io.footage import to_gray
from facepipe.pipeline.appearance_points import stencil_normals, point_normals

__all__ = ["frame_lights", "frame_colours", "frame_light", "frame_light_residuals", "frame_shading"]


def _light_points(camera_positions: np.ndarray, model: AppearanceModel, stencil=None):
    """The model's light points in frames (F, V, 3, camera space): their unit normals (F, K, 3),
    pixels (F, K, 2) and whether each faces the camera (F, K). ``stencil``: :func:`stencil_normals`
    of these frames where already computed."""
    vn, local = stencil_normals(camera_positions, model) if stencil is None else stencil
    X = np.einsum("kj,fkjc->fkc", model.light_bary, camera_positions[:, model.faces[model.light_face]])  # (F, K, 3)
    normals = point_normals(camera_positions, local[model.faces], model.light_face, model.light_bary, 1.0, vn)
    facing = (normals * -X).sum(axis=-1) > model.min_facing * np.linalg.norm(X, axis=-1)
    return normals, project_distorted_fast(model.camera, X), facing


def _light_point_values(images: np.ndarray, points) -> np.ndarray:
    """(F, K[, C]) the light points' values (:func:`_light_points`) sampled from the images
    (F, H, W[, C]), NaN where outside the image or not facing the camera."""
    _, pixels, facing = points
    values = np.empty(pixels.shape[:2] + images.shape[3:])
    for f in range(len(images)):
        sampled, inside = ap.bilinear_sample(images[f], pixels[f])
        values[f] = sampled
        values[f][~(facing[f] & inside)] = np.nan
    return values


def frame_lights(grays: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, points=None,
                 values=None) -> np.ndarray:
    """(F, 9) each frame's grey light, fitted (:func:`facepipe.core.lighting.fit_light`) over the
    model's light points: their albedo known, their normals from the frame's geometry (F, V, 3,
    camera space), their values sampled from its luminance (F, H, W) where in the image and facing
    the camera. ``points``: :func:`_light_points` of these frames, and ``values`` their values
    (:func:`_light_point_values`), where already computed."""
    points = _light_points(camera_positions, model) if points is None else points
    values = _light_point_values(grays, points) if values is None else values
    return lighting.fit_light(values, model.light_albedo, points[0])


def frame_colours(images: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, lights: np.ndarray,
                  points=None) -> np.ndarray:
    """(F, 3) each frame's light colour: per channel the median, over the light points the frame
    shows, of their value in the RGB frame (F, H, W, 3) over their colour albedo times their
    shading under the frame's grey light (F, 9) or (F, 7), the stream's (``stream_light``). About 1 for the light the examples were shot
    under; a warmer light reads red over blue. White (1, 1, 1) where the model keeps no colour
    albedo or too few points are seen. ``points``: as for :func:`frame_lights`."""
    out = np.ones((len(images), 3))
    if model.light_colour is None:
        return out
    points = _light_points(camera_positions, model) if points is None else points
    values, normals = _light_point_values(images, points), points[0]  # (F, K, 3) both
    for f in range(len(images)):
        seen = np.isfinite(values[f]).all(axis=-1)
        if seen.sum() >= 27:  # as many as a light fit needs
            predicted = model.light_colour[seen] * lighting.light_shading(normals[f][seen], lights[f])[:, None]
            out[f] = np.median(values[f][seen] / np.maximum(predicted, 1e-6), axis=0)
    return out


def frame_light(image: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel) -> np.ndarray:
    """(12,) or (10,) one RGB frame's (H, W, 3) light with its geometry (V, 3, camera space): the
    grey light the stream carries (the nine terms, :func:`frame_lights`, or the point light, by the
    model's ``stream_light``) and its colour (:func:`frame_colours`)."""
    points = _light_points(camera_positions[None], model)
    gray = to_gray(image)[None]
    grey = _fitted_lights(gray, camera_positions[None], model, points, _light_point_values(gray, points))[0]
    return np.concatenate([grey, frame_colours(image[None, ..., :3], camera_positions[None], model, grey, points)],
                          axis=1)[0]


def _fitted_lights(grays: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, points, values):
    """The frames' lights as the stream carries them (F, 9) or (F, 7) (the model's
    ``stream_light``), their lights under the model's own light model (the templates' shading: a
    point light's terminator is a kink nine terms round off) and what those leave unexplained of
    the light points' brightness (F,) (:func:`facepipe.core.lighting.light_residual`)."""
    light = frame_lights(grays, camera_positions, model, points, values)
    if model.light_model == "point":
        own = lighting.fit_point_light(values, model.light_point_albedo, points[0], start=light)
        residual = lighting.light_residual(values, model.light_point_albedo, points[0], own)
    else:
        own = light
        residual = lighting.light_residual(values, model.light_albedo, points[0], own)
    return (own if model.stream_light == "point" else light), own, residual


def frame_light_residuals(grays: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel) -> np.ndarray:
    """(F,) what each frame's light leaves unexplained of its light points' brightness
    (:func:`facepipe.core.lighting.light_residual`): a few percent where the geometry (F, V, 3,
    camera space) lies on the face in the frames (F, H, W), several times more where it misses it."""
    points = _light_points(camera_positions, model)
    return _fitted_lights(grays, camera_positions, model, points, _light_point_values(grays, points))[2]


def frame_shading(grays: np.ndarray, camera_positions: np.ndarray, model: AppearanceModel, images=None):
    """The shading (F, R, 5, size, size) at the template points of frames under each frame's light
    (fitted as the model's ``light_model`` says), the template points' unit normals (F, R, 5, N, 3),
    the lights the stream carries (the model's ``stream_light``): (F, 9) or (F, 7), or with the
    frames' RGB ``images`` (F, H, W, 3) (F, 12) or (F, 10), their colour after them
    (:func:`frame_colours`, from the same light points), and what the lights leave unexplained
    (F,) (:func:`frame_light_residuals`)."""
    stencil = stencil_normals(camera_positions, model)
    vn, local = stencil
    points = _light_points(camera_positions, model, stencil)
    values = _light_point_values(grays, points)
    light, shading_light, residual = _fitted_lights(grays, camera_positions, model, points, values)
    if images is not None:
        light = np.concatenate([light, frame_colours(images, camera_positions, model, light, points)], axis=1)
    t_normals = point_normals(camera_positions, local[model.faces], model.template_face, model.template_bary, 1.0,
                              vn)  # (F, R, 5, N, 3)
    out = np.stack([lighting.light_shading(t_normals[f], shading_light[f]) for f in range(len(grays))])
    s = model.template_size
    return out.reshape(out.shape[:3] + (s, s)), t_normals, light, residual
