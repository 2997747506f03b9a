"""The appearance model's texture of a frame, and the albedo it is built from.

A frame's texture is the skin's albedo at the frame's Q (the layered texture,
:mod:`facepipe.core.layered_texture`) times the shading of the frame's own geometry under its own
light (:func:`frame_texture`); at build time the example frames' textures are divided by their
own shading into that albedo (:func:`to_albedo`).
"""

from __future__ import annotations

import numpy as np

from facepipe.core import layered_texture, lighting
from facepipe.core.hole_cards import card_triangles
from facepipe.core.raster import edge_padding
from facepipe.core.tangent_frames import vertex_normals
from facepipe.io.appearance_file import AppearanceModel
from facepipe.pipeline.appearance_light import frame_light
from facepipe.pipeline.appearance_points import point_facing, point_normals, surface_points, texel_map, unwrap

__all__ = ["frame_texture", "texel_shading", "skin_texels", "card_texels", "shaded_texels", "to_albedo",
           "texture_differences"]


def _neutral_albedo(model: AppearanceModel, texture: np.ndarray, seen: np.ndarray, texels, neutral_cam: np.ndarray,
                    light: np.ndarray, cfg) -> np.ndarray:
    """A tile's neutral texture (S, S, 3) with the neutral frame's shading divided out where the
    frame shows the skin (``seen``); the rest filled from the texels it shows well (better than
    ``min_point_facing``): one seen near edge-on is a smear of a few pixels under the light fit's
    least certain normals, and a fill spreads its error over everything beyond it (as a template
    point seen so is left out). Off the skin (a card, no triangle) the texture is kept."""
    texel_face, texel_bary = texels
    everywhere = (slice(None), slice(None))
    skin = skin_texels(model, texel_face)
    shading = texel_shading(model, neutral_cam, light, texel_face, texel_bary, *everywhere)
    seen = seen & skin
    albedo = np.where(seen[..., None], texture / shading, texture)
    well_seen = seen & (_texel_facing(model, neutral_cam, texel_face, texel_bary, *everywhere)
                        > max(cfg.min_facing, cfg.min_point_facing))
    if well_seen.any():
        albedo = np.where((skin & ~seen)[..., None], layered_texture.fill_unseen(albedo, well_seen), albedo)
    return albedo


def to_albedo(model: AppearanceModel, cfg, frames: dict, cam_pos: dict, neutral_seen: np.ndarray,
              layer_seen: list, texels, tiles: dict | None = None) -> None:
    """Divide the shading of their own frame out of the neutral texture and every layer: the model
    then holds the skin's albedo (``neutral_albedo``, its volumes; ``neutral`` stays the neutral
    frame's texture as the footage showed it), and a frame's texture is that albedo at its Q
    times the shading of its own geometry under its own light (:func:`frame_texture`) — what no
    layer index can carry: how the face's large-scale motion (a jaw opening, a cheek raised) and
    the head's turning under the light change the shading over every region.

    Each example frame's light is fitted as a classified frame's is (:func:`frame_light`). A
    layer's texels that its own frame does not show hold the neutral albedo; texels the neutral
    frame does not show are filled (:func:`facepipe.core.layered_texture.fill_unseen`) from those it
    sees better than ``min_point_facing``. A card's texels (an eye behind its opening) are divided
    by the shading of the card's plane, seen or not (the model is made with ``cards_shaded``
    where it has cards and a light, so :func:`texel_shading` shades them): its plane is not the eyeball's surface, but
    it faces where the eyeball's visible front does, so a frame's light brightens or darkens the
    eye as it does the skin around it (the classification divides a card's samples by the same
    shading); unseen texels keep their fill, scaled alike. ``tiles``: the
    layout's other UDIM tiles (:func:`_tile_neutral` of each), whose neutral texture becomes
    ``tile_albedo`` the same way."""
    texel_face, texel_bary = texels
    used = sorted({cfg.neutral_frame} | {f for region in cfg.regions for f in region.frames})
    # a frame at a time: the frames' positions together would be the examples' count times the mesh
    lights = {f: frame_light(frames[f][0], cam_pos[f], model) for f in used}
    skin, card = skin_texels(model, texel_face), card_texels(model, texel_face)
    neutral_cam, neutral_light = cam_pos[cfg.neutral_frame], lights[cfg.neutral_frame]
    albedo = _neutral_albedo(model, model.neutral, neutral_seen, texels, neutral_cam, neutral_light, cfg)
    if tiles:
        model.tile_albedo = np.stack([_neutral_albedo(model, t["texture"], t["seen"], t["texels"], neutral_cam,
                                                      neutral_light, cfg) for t in tiles.values()]).astype(np.float32)
    volumes = []
    for r, region in enumerate(cfg.regions):
        (h, w), (r0, c0) = model.alphas[r].shape, model.boxes[r]
        rows, cols = slice(r0, r0 + h), slice(c0, c0 + w)
        layers = []
        for k, f in enumerate(region.frames):
            own = texel_shading(model, cam_pos[f], lights[f], texel_face, texel_bary, rows, cols)
            # divided by its own shading: the skin its frame shows, and the card, seen or not
            divided = card[rows, cols] | (layer_seen[r][k] & skin[rows, cols])
            layers.append(np.where(divided[..., None], model.volumes[r][k] / own,
                                   np.where(skin[rows, cols][..., None], albedo[rows, cols], model.volumes[r][k])))
        volumes.append(np.stack(layers).astype(np.float32))
    model.neutral_albedo, model.volumes = albedo.astype(np.float32), volumes


def _texel_facing(model: AppearanceModel, camera_positions: np.ndarray, texel_face: np.ndarray,
                  texel_bary: np.ndarray, rows, cols) -> np.ndarray:
    """(h, w) the cosine between the smooth surface's normal at the texels [rows, cols] of one frame
    (V, 3, camera space) and their direction to the camera; −1 off the UV layout."""
    tf, tb = texel_face[rows, cols], texel_bary[rows, cols]
    out = np.full(tf.shape, -1.0)
    covered = tf >= 0
    if covered.any():
        out[covered] = point_facing(camera_positions, model.faces, tf[covered], tb[covered], model.normal_sign)
    return out


def skin_texels(model: AppearanceModel, texel_face: np.ndarray) -> np.ndarray:
    """(S, S) the texels on the rest mesh's triangles (not on a card, not outside the UV layout)."""
    return (texel_face >= 0) & ~card_texels(model, texel_face)


def card_texels(model: AppearanceModel, texel_face: np.ndarray) -> np.ndarray:
    """(S, S) the texels on the cards' triangles (an eye behind its opening)."""
    on_card = card_triangles(model.faces, model.n_vertices)
    return (texel_face >= 0) & on_card[np.maximum(texel_face, 0)]


def shaded_texels(model: AppearanceModel, texel_face: np.ndarray) -> np.ndarray:
    """(S, S) the texels a frame's light shades: the skin's, and the cards' where the model's layers
    hold their albedo (``cards_shaded``; models built before it keep the cards as the footage
    showed them)."""
    return texel_face >= 0 if model.cards_shaded else skin_texels(model, texel_face)


def texel_shading(model: AppearanceModel, camera_positions: np.ndarray, light: np.ndarray, texel_face: np.ndarray,
                  texel_bary: np.ndarray, rows=slice(None), cols=slice(None)) -> np.ndarray:
    """(h, w, 3) the shading of the texels [rows, cols] on one frame's surface (V, 3), camera
    space, under its light as the stream carries it (12,) or (10,): the grey light's
    (:func:`facepipe.core.lighting.light_shading` of the nine terms or the point light) times its
    colour (the last three; white for a grey light alone, (9,) or (7,)); 1 where the light shades
    nothing (:func:`shaded_texels`).

    Kept within the shading of the light points the frame's light was fitted on (those facing the
    camera): a normal the fit never saw (the face's rim, turned away) would get the nine terms'
    extrapolation, a bright or dark band the footage does not have."""
    whole = all(isinstance(i, slice) and i == slice(None) for i in (rows, cols))
    on, interpolation = _texel_interpolation(model, texel_face[rows, cols], texel_bary[rows, cols],
                                             texel_face if whole else None)
    out = np.ones(on.shape + (3,))
    if on.any():
        grey, colour = _grey_and_colour(light)
        vn = model.normal_sign * vertex_normals(camera_positions[None], model.faces)
        normals = interpolation @ vn[0]
        normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-30)
        shading = np.clip(lighting.light_shading(normals, grey), *_fitted_shading_range(model, camera_positions, grey, vn))
        out[on] = shading[:, None] * colour
    return out


def _grey_and_colour(light: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A frame's light as the stream carries it, (12,) the nine terms and a colour or (10,) a point
    light and a colour, or its grey part alone, (9,) or (7,) (white): the grey light and the colour."""
    light = np.asarray(light, dtype=np.float64)
    if len(light) in (10, 12):
        return light[:-3], light[-3:]
    return light, np.ones(3)


def _texel_interpolation(model: AppearanceModel, texel_face: np.ndarray, texel_bary: np.ndarray, key=None):
    """The shaded texels (h, w) of a texel map (:func:`shaded_texels`) and the sparse matrix (N, V)
    that interpolates vertex values at them (their barycentric weights): a frame's texel normals are
    one sparse product. With ``key`` (the whole texel map: one per UDIM tile) the pair is kept on
    the model for the next frame."""
    kept = getattr(model, "_texel_interpolations", None)
    if kept is None:
        kept = model._texel_interpolations = {}
    cached = kept.get(id(key)) if key is not None else None
    if cached is not None and cached[0] is key:
        return cached[1], cached[2]
    import scipy.sparse as sp

    on = shaded_texels(model, texel_face)
    face, bary = texel_face[on], texel_bary[on]
    n = len(face)
    matrix = sp.csr_matrix((np.asarray(bary, dtype=np.float64).ravel(), (np.repeat(np.arange(n), 3),
                            model.faces[face].ravel())), shape=(n, int(model.faces.max()) + 1))
    if key is not None:
        if len(kept) >= 16:  # a texel map per UDIM tile: a head has a few
            kept.clear()
        kept[id(key)] = (key, on, matrix)
    return on, matrix


def _fitted_shading_range(model: AppearanceModel, camera_positions: np.ndarray, light: np.ndarray, vn: np.ndarray):
    """(low, high) the shading of the model's light points that face the camera in this frame
    (V, 3; ``vn`` (1, V, 3) its vertex normals) under its grey light (9,) or (7,): the normals
    :func:`frame_lights` fitted it on ((0, inf) where none)."""
    X = surface_points(camera_positions, model.faces, model.light_face, model.light_bary)
    normals = point_normals(camera_positions[None], model.faces, model.light_face, model.light_bary, 1.0, vn)[0]
    facing = (normals * -X).sum(axis=-1) > model.min_facing * np.linalg.norm(X, axis=-1)
    if not facing.any():
        return 0.0, np.inf
    shading = lighting.light_shading(normals[facing], light)
    return float(shading.min()), float(shading.max())


def frame_texture(model: AppearanceModel, q: np.ndarray, camera_positions: np.ndarray | None = None,
                  light: np.ndarray | None = None, texels=None, tile: int | None = None) -> np.ndarray:
    """A frame's texture (S, S, 3) on UDIM ``tile``: on the regions' tile (``model.tile``, the
    default) the layered texture at Q (R,), on the model's other tiles (``model.tiles``, where no
    region lies) their neutral texture. For a model that holds albedo, that albedo times the
    shading of the frame's surface (V, 3, camera space) under its light (12,) or (10,) on the skin (as the
    camera saw it); the albedo alone where either is not given. ``texels``: the tile's
    :func:`texel_map` where already made. The texels beyond the UV islands are edge-padded
    (:func:`_padded`)."""
    tile = model.tile if tile is None else tile
    if tile == model.tile:
        texture = layered_texture.compose_texture(model.base_texture, model.volumes, model.alphas, model.boxes, q)
    else:
        k = model.extra_tiles.index(tile)
        texture = model.tile_albedo[k] if model.albedo else model.tile_neutral[k]
    if model.corner_uv is None:  # (models before UVs were kept: no layout to pad)
        return texture
    if texels is None:  # the layout's texel map, made once per tile
        maps = model.__dict__.setdefault("_texel_maps", {})
        if tile not in maps:
            maps[tile] = texel_map(model.corner_uv, model.neutral.shape[0], tile)
        texels = maps[tile]
    texel_face, texel_bary = texels
    if model.albedo and camera_positions is not None and light is not None:
        texture = texture * texel_shading(model, camera_positions, light, texel_face, texel_bary)
    return _padded(model, texture, texel_face, tile)


#: Texels of edge padding around the UV islands of a frame's texture.
EDGE_PADDING = 8


def _padded(model: AppearanceModel, texture: np.ndarray, texel_face: np.ndarray, tile: int) -> np.ndarray:
    """``texture`` with the texels outside the UV layout, up to :data:`EDGE_PADDING` from it, given
    their nearest covered texel's value: a renderer's bilinear lookup (and its mip-maps) at an
    island's border blends texels beyond it, which would otherwise hold a fill unshaded by the
    frame (a seam along every island's border wherever the frame's shading is far from 1)."""
    kept = model.__dict__.setdefault("_edge_padding", {})
    if tile not in kept:
        kept[tile] = edge_padding(texel_face >= 0, EDGE_PADDING)[:2]
    targets, sources = kept[tile]
    if not len(targets):
        return texture
    out = np.array(texture, copy=True)
    flat = out.reshape(-1, out.shape[-1])
    flat[targets] = flat[sources]
    return out


def texture_differences(model: AppearanceModel, texel_face: np.ndarray, texel_bary: np.ndarray, image: np.ndarray,
                        camera_positions: np.ndarray, q: np.ndarray, light: np.ndarray | None = None) -> np.ndarray:
    """How far the frame's texture at Q (:func:`frame_texture`, shaded under ``light`` (12,) or (10,) where
    the model holds albedo) and the neutral texture are from a frame's own texels.

    The frame (RGB image, its geometry in camera space) is unwrapped into the texture through the
    rest mesh's texel map (:func:`texel_map` at the model's texture size) as the layers were.
    Returns (R, 3) per region over its texels (alpha > 0) the frame shows: the sum of squared
    differences of the reconstruction at ``q`` (R,), that of the neutral texture (as the neutral
    frame showed it: what a face without the stream would wear), and the count of texel channels —
    an RMS ratio below 1 says the stream brings the texture closer to the frame.
    """
    out = np.zeros((len(model.names), 3))
    texture = frame_texture(model, q, camera_positions, light, (texel_face, texel_bary))
    for r, (alpha, (r0, c0)) in enumerate(zip(model.alphas, model.boxes)):
        rows, cols = slice(r0, r0 + alpha.shape[0]), slice(c0, c0 + alpha.shape[1])
        truth, seen = unwrap(image, camera_positions, model.faces, texel_face, texel_bary, model.camera, rows, cols,
                             model.min_facing, model.normal_sign)
        use = seen & (alpha > 0)
        out[r] = (((texture[rows, cols] - truth)[use] ** 2).sum(), ((model.neutral[rows, cols] - truth)[use] ** 2).sum(),
                  3 * use.sum())
    return out
