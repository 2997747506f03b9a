"""Appearance models (``facepipe appearance build``) as .npz files, the Q stream (appearance.csv)
and each frame's light (light.csv)."""

from __future__ import annotations

import dataclasses
import functools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facepipe.core.camera import Camera
from facepipe.core.hole_cards import card_triangles, with_card_vertices
from facepipe.errors import InputError
from facepipe.io.atomic import atomic_path
from facepipe.io.npz_file import NPZ_READ_ERRORS, open_npz

__all__ = ["AppearanceModel", "save_appearance", "load_appearance", "write_stream", "read_stream", "format_stream",
           "format_light", "read_light", "LIGHT_COLUMNS", "POINT_LIGHT_COLUMNS", "STREAM_LIGHTS", "light_columns",
           "STREAM_DECIMALS"]

#: Q is written to this many decimals: the stream's quantisation step, and its bit rate's.
STREAM_DECIMALS = 4


@dataclass
class AppearanceModel:
    """What classification and the layered texture need (saved by :func:`save_appearance`).

    names : region names; camera : intrinsics; rotation (3, 3), translation (3,) : world → camera;
    faces : (F, 3) rest-mesh triangles; normal_sign : ±1, the side of the triangles that faces out;
    template_face (R, 5, N), template_bary (R, 5, N, 3) : the template points and their offsets;
    templates : per region (n, C) coefficients; indices : per region kept coefficients;
    weights : (C,) per-coefficient weights; template_size, min_facing, decay, min_event : settings;
    min_point_facing : template points any of the region's examples sees more edge-on than this
    cosine are left out of the match (``template_facing`` (R, 5, N), their least cosine there;
    0: no edge-on test, in the examples or the frames); frame_facing_share : a frame leaves out
    the points it sees at under this share of ``template_facing``
    (:func:`facepipe.pipeline.appearance_points.frame_facing_limits`; 0, models before it: those
    it sees more edge-on than ``min_point_facing``); template_mask (R, N) : each region's stable
    template points, those every example shows well (in view, not hidden, not edge-on): its
    templates are normalised over them, its kept coefficients chosen on them, and it is matched
    on them (None in models before it: all points); min_seen : the share of a template's
    (stable) points that must be seen for the region to be classified; occlusion : template points hidden by the face itself are found (ray cast) and
    left out of the match (False in models before it);
    shading : patches divided by their shading plane (else by their mean; models before it);
    light_face (K,), light_bary (K, 3), light_albedo (K,) : points on the surface (fixed
    barycentric coordinates) and their albedo, over which each frame's light is fitted and
    divided out of the patches (None: no light fit); corner_uv (F, 3, 2) : the triangles' UVs
    (to render the layered texture; None in models before it);
    rest_floor : (R,) the highest Q each region read at rest in the examples, which
    classification measures Q from (None: 0, models before it or built without it);
    rest_nuisance : per region None or (k, N) texel directions explained away in its match
    (:class:`facepipe.core.appearance.RegionBank`'s ``nuisance``: what other expressions in the
    examples do to its patch; None: none, models before it);
    rest_readings, rest_off_path : (K, R) the example frames' Q and off-path ratio where each
    region is at rest (NaN elsewhere), and rest_tolerance, rest_noise : with them a reading's
    own floor (:func:`facepipe.core.appearance.conditional_floor`) replaces ``rest_floor`` (None,
    or tolerance 0: ``rest_floor`` for every reading, as in models before them);
    template_patches : per region (n, size²) its layers' template samples before normalising
    (light divided out where fitted): a partly seen sample's templates are normalised from them
    over the same texels (None, models before them: from the normalised templates, approximately);
    card_rest (N, 3), card_stable (K,), card_stable_rest (K, 3) : cards across holes
    (:mod:`facepipe.core.hole_cards`): vertex V + i of ``faces`` is ``card_rest[i]`` moved by the
    rigid motion of the rest mesh's vertices ``card_stable`` from ``card_stable_rest`` (None: no cards);
    card_motion : per region None or its motion check (:class:`facepipe.core.card_motion.CardMotion`:
    a card region's reading counts only where its patch moved along its layers' path; None for
    every region in models before it);
    cards_shaded : whether the cards' texels, with ``neutral_albedo``, hold albedo too (divided by
    the shading of the card's plane) and a frame's light shades them as the skin (False in models
    before it: they keep the footage's values);
    neutral : (S, S, 3) texture, as the neutral frame shows it; volumes : per region (n, h, w, 3);
    alphas : per region (h, w); boxes : (R, 2) top-left texel of each volume;
    neutral_albedo : (S, S, 3) the neutral texture with its frame's shading divided out, and then
    the volumes hold albedo too (each layer divided by its own frame's shading): a frame's texture
    is the layered albedo times the shading of the frame's own geometry under its light
    (:func:`facepipe.pipeline.appearance_texture.frame_texture`); None (models before it, or built
    without a light fit): the volumes hold the footage's values, shading included;
    light_colour : (K, 3) the light points' RGB albedo (their colour under the grey light the
    stream carries), over which a frame's light colour is measured (None: a white light);
    stream_light : the grey light the stream (light.csv) and the textures carry, ``"sh9"`` (nine
    spherical-harmonic terms) or ``"point"`` (an ambient term and two distant lights: the light
    classification fits with ``light_model = "point"``, whose terminators the nine terms round
    off into bands);
    tiles : (T,) the UDIM tiles other than ``tile`` that the rest mesh's UV layout uses (no region
    lies on them), with tile_neutral (T, S, S, 3) the neutral frame's texture there and
    tile_albedo (T, S, S, 3) its albedo (None with ``neutral_albedo`` None); None: one tile;
    tile : the UDIM tile the regions lie on, whose texture ``neutral``, the boxes and the layers
    are (1001 in models before it);
    shading_orders : (R,) with ``shading``, the surface each region's patches are divided by (1 the
    plane, 2 the quadratic: :func:`facepipe.core.appearance.shading_order`); None: the plane
    (models before it);
    shading_reference : what each region's shading surface is fitted against
    (:data:`facepipe.core.appearance.SHADING_REFERENCES`): ``neutral``, its neutral template
    (``template_patches``' first row, over its mean); ``patch`` (models before it), the patch alone;
    peak_interpolation : how Q is read from a patch's match distances
    (:data:`facepipe.core.appearance.PEAK_INTERPOLATIONS`; models before it: ``parabola``);
    light_model : the light the templates' and each frame's shading are modelled by
    (:data:`facepipe.core.lighting.LIGHT_MODELS`; models before it: ``sh9``), and with
    ``point`` light_point_albedo (K,) : the light points' albedo under it. ``light_albedo`` is
    theirs under the nine-term light, which the stream carries where ``stream_light`` says so;
    light_residual : the median over the example frames of what each one's light leaves
    unexplained of its light points' brightness
    (:func:`facepipe.pipeline.appearance_light.frame_light_residuals`): what a frame whose
    geometry lies on the face reads, against which classification checks its footage (None:
    no light points, or models before it).
    """

    names: list
    camera: Camera
    rotation: np.ndarray
    translation: np.ndarray
    faces: np.ndarray
    normal_sign: float
    template_face: np.ndarray
    template_bary: np.ndarray
    templates: list
    indices: list
    weights: np.ndarray
    template_size: int
    min_facing: float
    decay: float
    neutral: np.ndarray
    volumes: list
    alphas: list
    boxes: np.ndarray
    shading: bool = False
    light_face: np.ndarray | None = None
    light_bary: np.ndarray | None = None
    light_albedo: np.ndarray | None = None
    corner_uv: np.ndarray | None = None
    min_seen: float = 0.5
    occlusion: bool = True
    min_point_facing: float = 0.0
    template_facing: np.ndarray | None = None
    template_mask: np.ndarray | None = None
    rest_floor: np.ndarray | None = None
    card_rest: np.ndarray | None = None
    card_stable: np.ndarray | None = None
    card_stable_rest: np.ndarray | None = None
    neutral_albedo: np.ndarray | None = None
    light_colour: np.ndarray | None = None
    tiles: np.ndarray | None = None
    tile_neutral: np.ndarray | None = None
    tile_albedo: np.ndarray | None = None
    tile: int = 1001
    shading_orders: np.ndarray | None = None
    peak_interpolation: str = "parabola"
    min_event: float = 0.0  # seconds (models written before it: 0, every reading kept)
    light_model: str = "sh9"  # (models written before it: the nine-term light)
    light_point_albedo: np.ndarray | None = None
    light_residual: float | None = None  # (models written before it: None, footage not checked against it)
    rest_nuisance: list | None = None
    rest_readings: np.ndarray | None = None
    rest_off_path: np.ndarray | None = None
    rest_tolerance: float = 0.0
    rest_noise: float = 0.0
    template_patches: list | None = None  # (models written before them: None)
    cards_shaded: bool = False  # (models written before it: the cards' texels as the footage showed them)
    frame_facing_share: float = 0.0  # (models written before it: 0, min_point_facing in the frames too)
    stream_light: str = "sh9"  # the light the stream and textures carry (models written before it: the nine terms)
    shading_reference: str = "patch"  # what the shading surface is fitted against (models written before it: the patch)
    card_motion: list | None = None  # (models written before it: no card's motion checked)

    @property
    def extra_tiles(self) -> list:
        """The UDIM tiles beside ``tile`` that the textures cover (``tiles``; none in older models)."""
        return [] if self.tiles is None else [int(t) for t in self.tiles]

    @property
    def all_tiles(self) -> list:
        """Every UDIM tile the textures cover, in increasing order (the regions' ``tile`` among them)."""
        return sorted([int(self.tile)] + self.extra_tiles)

    @property
    def albedo(self) -> bool:
        """Whether the layers hold albedo (a frame's texture is shaded by its own geometry and light)."""
        return self.neutral_albedo is not None

    @property
    def base_texture(self) -> np.ndarray:
        """The texture the regions' volumes blend into: the neutral albedo, or the neutral texture."""
        return self.neutral if self.neutral_albedo is None else self.neutral_albedo

    @property
    def n_vertices(self) -> int:
        """The rest mesh's vertex count (``faces`` also index the cards' vertices after them)."""
        return int(self.faces.max()) + 1 - (0 if self.card_rest is None else len(self.card_rest))

    @functools.cached_property
    def occluders(self) -> np.ndarray:
        """The rest mesh's own triangles (T, 3): what can hide a template point. A card stands in
        for an eyeball, which lies behind the skin, so it hides nothing (a closing lid that dips
        behind a card's plane still covers the eye)."""
        return self.faces[~card_triangles(self.faces, self.n_vertices)]

    def with_cards(self, world: np.ndarray) -> np.ndarray:
        """Positions (..., V, 3) of the rest mesh's vertices with the cards' after them."""
        world = np.asarray(world, dtype=np.float64)
        if self.card_rest is None:
            return world
        return with_card_vertices(world, self.card_stable, self.card_stable_rest, self.card_rest)

    def to_camera(self, world: np.ndarray) -> np.ndarray:
        """Camera-space positions of the rest mesh's vertices (..., V, 3) and the cards'."""
        return self.with_cards(world) @ self.rotation.T + self.translation

    @property
    def stream_terms(self) -> int:
        """The grey light's values in the stream: 9 (the nine terms) or 7 (a point light)."""
        return 7 if self.stream_light == "point" else 9

    @property
    def layer_counts(self) -> list:
        return [len(t) for t in self.templates]

    def without_rest_floors(self) -> "AppearanceModel":
        """The same model reading raw Q: no rest floor of any kind (what is explained away in the
        match stays)."""
        return dataclasses.replace(self, rest_floor=None, rest_readings=None, rest_off_path=None)


def save_appearance(path, model) -> None:
    """Write an :class:`AppearanceModel` (atomically)."""
    arrays = {"names": np.array(model.names), "camera_matrix": model.camera.matrix,
              "camera_distortion": model.camera.distortion, "camera_size": np.array([model.camera.width,
                                                                                    model.camera.height]),
              "rotation": model.rotation, "translation": model.translation, "faces": model.faces,
              "normal_sign": np.array(model.normal_sign), "template_face": model.template_face,
              "template_bary": model.template_bary, "weights": model.weights,
              "settings": np.array([model.template_size, model.min_facing, model.decay, float(model.shading),
                                   model.min_seen, float(model.occlusion), model.min_point_facing,
                                    model.min_event]), "neutral": model.neutral,
              "boxes": model.boxes, "tile": np.array(int(model.tile)),
              "peak_interpolation": np.array(model.peak_interpolation), "light_model": np.array(model.light_model)}
    if model.corner_uv is not None:
        arrays["corner_uv"] = model.corner_uv
    if model.template_facing is not None:
        arrays["template_facing"] = model.template_facing
    if model.template_mask is not None:
        arrays["template_mask"] = model.template_mask
    if model.rest_floor is not None:
        arrays["rest_floor"] = model.rest_floor
    if model.rest_readings is not None:
        arrays.update(rest_readings=model.rest_readings, rest_off_path=model.rest_off_path,
                      rest_tolerance=np.array(float(model.rest_tolerance)), rest_noise=np.array(float(model.rest_noise)))
    for r, patches in enumerate(model.template_patches or []):
        arrays[f"template_patches_{r}"] = np.asarray(patches, dtype=np.float64)
    for r, directions in enumerate(model.rest_nuisance or []):
        if directions is not None and len(directions):
            arrays[f"rest_nuisance_{r}"] = np.asarray(directions)
    for r, motion in enumerate(model.card_motion or []):
        if motion is not None:
            arrays.update({f"card_motion_reference_{r}": np.asarray(motion.reference, dtype=np.float64),
                           f"card_motion_reference_seen_{r}": np.asarray(motion.reference_seen, dtype=bool),
                           f"card_motion_least_{r}": np.array(float(motion.least)),
                           f"card_motion_layers_{r}": np.asarray(motion.layers, dtype=np.float64).reshape(-1, 2),
                           f"card_motion_rest_{r}": np.asarray(motion.rest, dtype=np.float64).reshape(-1, 2)})
    if model.shading_orders is not None:
        arrays["shading_orders"] = np.asarray(model.shading_orders, dtype=np.int64)
    if model.card_rest is not None:
        arrays.update(card_rest=model.card_rest, card_stable=model.card_stable, card_stable_rest=model.card_stable_rest,
                      cards_shaded=np.array(bool(model.cards_shaded)))
    if model.frame_facing_share > 0:
        arrays["frame_facing_share"] = np.array(float(model.frame_facing_share))
    if model.stream_light != "sh9":
        arrays["stream_light"] = np.array(model.stream_light)
    if model.shading_reference != "patch":
        arrays["shading_reference"] = np.array(model.shading_reference)
    if model.light_face is not None:
        arrays.update(light_face=model.light_face, light_bary=model.light_bary, light_albedo=model.light_albedo)
    if model.neutral_albedo is not None:
        arrays["neutral_albedo"] = model.neutral_albedo
    if model.light_colour is not None:
        arrays["light_colour"] = model.light_colour
    if model.light_point_albedo is not None:
        arrays["light_point_albedo"] = model.light_point_albedo
    if model.light_residual is not None:
        arrays["light_residual"] = np.array(float(model.light_residual))
    if model.extra_tiles:
        arrays.update(tiles=np.asarray(model.tiles, dtype=np.int64), tile_neutral=model.tile_neutral)
        if model.tile_albedo is not None:
            arrays["tile_albedo"] = model.tile_albedo
    for r in range(len(model.names)):
        arrays[f"templates_{r}"] = model.templates[r]
        arrays[f"indices_{r}"] = model.indices[r]
        arrays[f"volume_{r}"] = model.volumes[r]
        arrays[f"alpha_{r}"] = model.alphas[r]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)


def _flag(d: dict, name: str) -> bool:
    """A stored true/false (False where absent: models written before it)."""
    if name not in d:
        return False
    value = np.asarray(d[name])
    if value.shape != () or value.item() not in (0, 1):
        raise ValueError(f"{name} {value.tolist()!r} is not true or false")
    return bool(value.item())


def _card_motion(d: dict, r: int, name: str):
    """Region r's stored motion check (:class:`~facepipe.core.card_motion.CardMotion`), or None."""
    if f"card_motion_least_{r}" not in d:
        return None
    from facepipe.core.card_motion import CardMotion

    least = np.asarray(d[f"card_motion_least_{r}"], dtype=np.float64)
    layers = np.asarray(d.get(f"card_motion_layers_{r}", np.zeros((0,))), dtype=np.float64)
    rest = np.asarray(d.get(f"card_motion_rest_{r}", np.zeros((0,))), dtype=np.float64)
    if not (least.shape == () and np.isfinite(least) and least > 0):
        raise ValueError(f"card_motion_least_{r} (region {name}): {least.tolist()!r} is not a shift > 0")
    for key, rows in (("layers", layers), ("rest", rest)):
        if rows.ndim != 2 or rows.shape[1] != 2 or not np.allclose(np.linalg.norm(rows, axis=1), 1.0, atol=1e-6):
            raise ValueError(f"card_motion_{key}_{r} (region {name}): not rows of unit directions (x, y)")
    if not len(layers):
        raise ValueError(f"card_motion_layers_{r} (region {name}): no direction of its layers")
    reference = np.asarray(d.get(f"card_motion_reference_{r}", np.zeros(0)), dtype=np.float64)
    seen = np.asarray(d.get(f"card_motion_reference_seen_{r}", np.zeros(0)))
    size = int(d["settings"][0])
    if reference.shape != (size, size) or seen.shape != (size, size) or not np.isfinite(reference).all():
        raise ValueError(f"card_motion_reference_{r} (region {name}): not a finite {size} × {size} patch with the "
                         "texels it sees")
    return CardMotion(reference, seen.astype(bool), float(least), layers, rest)


def load_appearance(path):
    """Read a model written by :func:`save_appearance`."""
    path = Path(path)
    if not path.is_file():
        raise InputError("appearance model not found", path=path, hint="build one: facepipe appearance build CONFIG")
    hint = "build one with: facepipe appearance build CONFIG -o APPEARANCE.npz"
    try:
        with open_npz(path, "an appearance model written by 'facepipe appearance build'", hint) as archive:
            d = {key: archive[key] for key in archive.files}
        n = len(d["names"])
        size = d["camera_size"]
        camera = Camera(d["camera_matrix"], d["camera_distortion"], int(size[0]), int(size[1]), str(path))
        s = d["settings"]
        model = AppearanceModel([str(x) for x in d["names"]], camera, d["rotation"], d["translation"], d["faces"],
                               float(d["normal_sign"]), d["template_face"], d["template_bary"],
                               [d[f"templates_{r}"] for r in range(n)], [d[f"indices_{r}"] for r in range(n)],
                               d["weights"], int(s[0]), float(s[1]), float(s[2]), d["neutral"],
                               [d[f"volume_{r}"] for r in range(n)], [d[f"alpha_{r}"] for r in range(n)], d["boxes"],
                               bool(s[3]) if len(s) > 3 else False, d.get("light_face"), d.get("light_bary"),
                               d.get("light_albedo"), d.get("corner_uv"),
                               float(s[4]) if len(s) > 4 else 0.5, bool(s[5]) if len(s) > 5 else False,
                               float(s[6]) if len(s) > 6 else 0.0, d.get("template_facing"),
                               None if d.get("template_mask") is None else d["template_mask"].astype(bool),
                               d.get("rest_floor"), d.get("card_rest"), d.get("card_stable"),
                               d.get("card_stable_rest"), d.get("neutral_albedo"), d.get("light_colour"),
                               d.get("tiles"), d.get("tile_neutral"), d.get("tile_albedo"),
                               int(d["tile"]) if "tile" in d else 1001, d.get("shading_orders"),
                               str(d["peak_interpolation"]) if "peak_interpolation" in d else "parabola",
                               float(s[7]) if len(s) > 7 else 0.0,
                               str(d["light_model"]) if "light_model" in d else "sh9", d.get("light_point_albedo"),
                               float(d["light_residual"]) if "light_residual" in d else None,
                               [d.get(f"rest_nuisance_{r}") for r in range(n)], d.get("rest_readings"),
                               d.get("rest_off_path"), float(d["rest_tolerance"]) if "rest_tolerance" in d else 0.0,
                               float(d["rest_noise"]) if "rest_noise" in d else 0.0,
                               [d[f"template_patches_{r}"] for r in range(n)] if "template_patches_0" in d else None,
                               _flag(d, "cards_shaded"),
                               float(d["frame_facing_share"]) if "frame_facing_share" in d else 0.0,
                               str(d["stream_light"]) if "stream_light" in d else "sh9",
                               str(d["shading_reference"]) if "shading_reference" in d else "patch",
                               [_card_motion(d, r, str(d["names"][r])) for r in range(n)])
        from facepipe.core.appearance import PEAK_INTERPOLATIONS, SHADING_REFERENCES  # lazy: PyWavelets only where read
        from facepipe.core.lighting import LIGHT_MODELS

        if model.light_residual is not None and not (np.isfinite(model.light_residual) and model.light_residual >= 0):
            raise ValueError(f"light_residual {model.light_residual} is not a share ≥ 0")
        if not (np.isfinite(model.min_event) and model.min_event >= 0):
            raise ValueError(f"min_event {model.min_event} is not a duration ≥ 0")
        if model.peak_interpolation not in PEAK_INTERPOLATIONS:
            raise ValueError(f"peak_interpolation {model.peak_interpolation!r} is not one of "
                             f"{', '.join(PEAK_INTERPOLATIONS)}")
        if model.shading_reference not in SHADING_REFERENCES:
            raise ValueError(f"shading_reference {model.shading_reference!r} is not one of {', '.join(SHADING_REFERENCES)}")
        if model.light_model not in LIGHT_MODELS:
            raise ValueError(f"light_model {model.light_model!r} is not one of {', '.join(LIGHT_MODELS)}")
        if model.light_model == "point" and (model.light_albedo is None or model.light_point_albedo is None
                                             or model.light_point_albedo.shape != model.light_albedo.shape):
            raise ValueError("light_model 'point' needs light_point_albedo, one value per light point")
        if model.shading_orders is not None and (model.shading_orders.shape != (n,)
                                                 or not np.isin(model.shading_orders, (1, 2)).all()):
            raise ValueError(f"shading_orders {model.shading_orders.tolist()} is not 1 or 2 for each of its {n} regions")
        if model.rest_readings is not None and (model.rest_off_path is None or model.rest_readings.ndim != 2
                                                or model.rest_readings.shape[1] != n
                                                or model.rest_off_path.shape != model.rest_readings.shape):
            raise ValueError(f"rest_readings and rest_off_path are not the same (frames, {n}) array")
        if not (model.rest_tolerance >= 0 and model.rest_noise >= 0):
            raise ValueError(f"rest_tolerance {model.rest_tolerance} or rest_noise {model.rest_noise} is not ≥ 0")
        points = model.template_size ** 2
        for r, (name, directions) in enumerate(zip(model.names, model.rest_nuisance)):
            if directions is not None and (directions.ndim != 2 or directions.shape[1] != points
                                           or not np.isfinite(directions).all()):
                raise ValueError(f"rest_nuisance_{r} (region {name}): its explained-away directions are not finite "
                                 f"rows of {points} texels")
        for r, (name, patches) in enumerate(zip(model.names, model.template_patches or [])):
            if patches.shape != (len(model.templates[r]), points) or not np.isfinite(patches).all():
                raise ValueError(f"template_patches_{r} (region {name}): not finite rows of {points} texels, one "
                                 f"per template ({len(model.templates[r])})")
        if model.stream_light not in STREAM_LIGHTS or (model.stream_light == "point" and model.light_model != "point"):
            raise ValueError(f"stream_light {model.stream_light!r} is not one of {', '.join(STREAM_LIGHTS)} "
                             "(\"point\" with light_model \"point\" only)")
        if not 0.0 <= model.frame_facing_share <= 1.0:
            raise ValueError(f"frame_facing_share {model.frame_facing_share} is not a share in [0, 1]")
        if model.cards_shaded and (model.card_rest is None or model.neutral_albedo is None):
            raise ValueError("cards_shaded is set, but the model has no cards or holds no albedo")
        tiles = len(model.extra_tiles)
        if tiles and not (model.tile_neutral is not None and len(model.tile_neutral) == tiles
                          and (model.tile_albedo is None) == (model.neutral_albedo is None)
                          and (model.tile_albedo is None or len(model.tile_albedo) == tiles)):
            raise ValueError(f"its {tiles} other UV tiles' textures are missing or incomplete")
        return model
    except NPZ_READ_ERRORS as exc:
        raise InputError(f"not an appearance model ({exc})", path=path, hint=hint) from None


def write_stream(folder, model_path, classification, layer_counts, footage=None, geometry=None,
                 figures: dict | None = None) -> Path:
    """``appearance.csv`` (frame, time, Q per region), ``light.csv`` (frame, time, the light the
    model's stream carries and its colour; where the model fits one) and ``appearance.json`` (the model, the footage
    and geometry classified, missing frames, and ``figures``: the run's speed and the stream's bit
    rate)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    c = classification
    names = [str(n) for n in c.names]
    csv = folder / "appearance.csv"
    with atomic_path(csv) as tmp:
        Path(tmp).write_text(format_stream(names, c.numbers, c.times, c.q))
    light = folder / "light.csv"
    if c.light is not None:
        with atomic_path(light) as tmp:
            Path(tmp).write_text(format_light(c.numbers, c.times, c.light))
    elif light.exists():  # a classification before this one's, with another model
        light.unlink()
    info = {"model": str(Path(model_path).resolve()), "regions": names,
            "footage": str(footage) if footage is not None else None,
            "geometry": str(Path(geometry).resolve()) if geometry is not None else None, "layers": list(map(int, layer_counts)),
            "frames": len(c.numbers), "hidden_fraction": float(1 - c.visible.mean()),
            "skipped_frames": [{"frame": int(n), "problem": p} for n, p in c.problems], **(figures or {})}
    with atomic_path(folder / "appearance.json") as tmp:
        Path(tmp).write_text(json.dumps(info, indent=1))
    return csv


def format_stream(names, numbers, times, q) -> str:
    """appearance.csv's text: ``frame,time,NAME…``, Q to :data:`STREAM_DECIMALS` decimals."""
    lines = ["frame,time," + ",".join(str(n) for n in names)]
    lines += [f"{int(n)},{t:.6f}," + ",".join(f"{x:.{STREAM_DECIMALS}f}" for x in row)
              for n, t, row in zip(numbers, times, q)]
    return "\n".join(lines) + "\n"


#: light.csv's columns after frame and time: the grey light's nine spherical-harmonic coefficients
#: and the light's colour (a gain per channel).
LIGHT_COLUMNS = [f"sh{k}" for k in range(9)] + ["red", "green", "blue"]
#: light.csv's columns for a point light (``stream_light = "point"``): the ambient term, the key
#: and the fill light (each its direction times its strength), and the colour.
POINT_LIGHT_COLUMNS = ["ambient", "key_x", "key_y", "key_z", "fill_x", "fill_y", "fill_z", "red", "green", "blue"]
#: The lights a stream may carry → its light.csv columns.
STREAM_LIGHTS = {"sh9": LIGHT_COLUMNS, "point": POINT_LIGHT_COLUMNS}


def light_columns(light) -> list:
    """light.csv's columns for lights (T, 12) (nine terms and a colour) or (T, 10) (a point light
    and a colour)."""
    width = np.shape(light)[-1]
    for columns in STREAM_LIGHTS.values():
        if len(columns) == width:
            return columns
    raise ValueError(f"a light of {width} values is neither the nine terms' nor the point light's, with a colour")


def format_light(numbers, times, light) -> str:
    """light.csv's text: ``frame,time,`` then :data:`LIGHT_COLUMNS` or :data:`POINT_LIGHT_COLUMNS`
    (by the lights' width), to :data:`STREAM_DECIMALS` decimals."""
    lines = ["frame,time," + ",".join(light_columns(light))]
    lines += [f"{int(n)},{t:.6f}," + ",".join(f"{x:.{STREAM_DECIMALS}f}" for x in row)
              for n, t, row in zip(numbers, times, light)]
    return "\n".join(lines) + "\n"


def read_light(folder, numbers: np.ndarray) -> np.ndarray | None:
    """(T, 12) or (T, 10) the light of each of the stream's frames ``numbers`` from a classified
    folder's light.csv (:data:`LIGHT_COLUMNS`, or :data:`POINT_LIGHT_COLUMNS` by its header); None
    where the folder has none (a model without a light fit, or classified before facepipe wrote it)."""
    csv = Path(folder) / "light.csv"
    if not csv.is_file():
        return None
    lines = csv.read_text(encoding="utf-8", errors="replace").splitlines()
    header = lines[0].strip().split(",") if lines else []
    columns = next((c for c in STREAM_LIGHTS.values() if header == ["frame", "time"] + c), None)
    if columns is None:
        raise InputError(f"line 1 ({', '.join(header) or 'empty'}) is not a light's header: frame, time, then "
                         + " or ".join(f"{', '.join(c)} ({kind})" for kind, c in STREAM_LIGHTS.items()),
                         path=csv, hint="classify the footage again: facepipe appearance classify ... -o FOLDER")
    data = _numbers_table(csv, ["frame", "time"] + columns, lines)
    if not np.array_equal(data[:, 0].astype(np.int64), np.asarray(numbers)) or not np.isfinite(data[:, 2:]).all():
        raise InputError(f"light.csv does not hold {len(columns)} finite values ({', '.join(columns)}) "
                         "for each of appearance.csv's frames",
                         path=csv, hint="classify the footage again: facepipe appearance classify ... -o FOLDER")
    return data[:, 2:]


def read_stream(folder) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
    """appearance.json, frame numbers (T,), times (T,), Q (T, R) of a classified folder."""
    folder = Path(folder)
    csv, meta = folder / "appearance.csv", folder / "appearance.json"
    if not csv.is_file() or not meta.is_file():
        raise InputError("no appearance.csv / appearance.json here", path=folder,
                         hint="classify the footage first: facepipe appearance classify ... -o FOLDER")
    try:
        info = json.loads(meta.read_text())
        info["regions"], info["model"]
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise InputError(f"appearance.json is not a classification's summary ({exc})", path=meta,
                         hint="classify the footage again: facepipe appearance classify ... -o FOLDER") from None
    lines = csv.read_text(encoding="utf-8", errors="replace").splitlines()
    columns = ["frame", "time"] + [str(n) for n in info["regions"]]
    order = _columns_by_name(csv, lines[0] if lines else "", columns)
    data = _numbers_table(csv, columns, lines)[:, order]
    return info, data[:, 0].astype(np.int64), data[:, 1], data[:, 2:]


def _columns_by_name(csv: Path, header: str, columns: list) -> np.ndarray:
    """Where each of ``columns`` is in a stream file's header line (a file edited in another tool
    may have them in another order); exit 2 naming those missing, unknown or repeated."""
    names = [cell.strip() for cell in header.split(",")]
    if names == columns:
        return np.arange(len(columns))
    missing = [c for c in columns if c not in names]
    unknown = [n for n in names if n not in columns]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if missing or unknown or repeated:
        said = "; ".join(f"{what}: {', '.join(which)}" for what, which in
                         (("missing", missing), ("not in the classification", unknown), ("repeated", repeated)) if which)
        raise InputError(f"line 1: its columns are not frame, time and the classification's regions "
                         f"(appearance.json: {', '.join(columns[2:])}) — {said}", path=csv,
                         hint="keep the header appearance classify wrote (columns may be in any order), or "
                              "classify the footage again")
    return np.array([names.index(c) for c in columns])


def _numbers_table(csv: Path, columns: list, lines: list | None = None) -> np.ndarray:
    """(rows, len(columns)) the numbers of a stream file written by this module (a header line,
    then one row of numbers a frame; ``lines``: its lines where already read); the first line that
    is not a row of them is named."""
    rows = []
    lines = csv.read_text(encoding="utf-8", errors="replace").splitlines() if lines is None else lines
    for line_no, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        try:
            values = [float(cell) for cell in line.split(",")]
        except ValueError:
            values = []
        if len(values) != len(columns):
            raise InputError(f"line {line_no} is not a row of {len(columns)} numbers ({', '.join(columns)})",
                             path=csv, hint="classify the footage again: facepipe appearance classify ... -o FOLDER")
        rows.append(values)
    return np.asarray(rows, dtype=np.float64).reshape(-1, len(columns))
