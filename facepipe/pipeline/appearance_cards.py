"""Eye cards of an appearance model: where a ``card`` region's card lies and how far it is set back.

A ``card`` region (an eye) lies on a card across the hole its vertex group rims
(:mod:`facepipe.core.hole_cards`): the cards' triangles follow the mesh's, their vertices its
vertices, in a free square of the UV layout (:func:`free_uv_squares`), carried by the vertices
that move least over the example frames (:func:`region_cards`). A card region's template
rectangle is given in its card's own square (:func:`template_rect`), and each card's depth is
fitted from the example frames where its eye is at rest (:func:`card_depths`,
:mod:`facepipe.pipeline.appearance_card_depth`).
"""

from __future__ import annotations

import numpy as np

from facepipe.core.camera import Camera
from facepipe.core.hole_cards import boundary_loops, hole_cards, stable_vertices
from facepipe.core.raster import udim_corner
from facepipe.errors import InputError
from facepipe.pipeline.appearance import examples_at_rest
from facepipe.pipeline.appearance_card_depth import GRID as CARD_DEPTH_GRID, MIN_COMMON, MIN_PARALLAX, fit_card_depth
from facepipe.pipeline.appearance_points import region_template, texel_map

__all__ = ["CARD_RINGS", "MIN_CARD_TEXELS", "free_uv_squares", "region_cards", "template_rect", "card_depths"]


#: Rings of triangles from a card's centre to its rim; and the smallest UV square a card may get (texels)
CARD_RINGS = 4


MIN_CARD_TEXELS = 16


def free_uv_squares(corner_uv: np.ndarray, size: int, count: int, gap: int = 2, tile: int = 1001) -> list:
    """``count`` UV squares [u0, v0, u1, v1] where the layout (at ``size`` texels) has no triangle
    on UDIM ``tile``, largest first, each ``gap`` texels from any triangle and the others; their
    sides in texels."""
    import cv2  # OpenCV's distance transform: only where a model with cards is built

    covered = texel_map(corner_uv, size, tile)[0] >= 0
    u0, v0 = udim_corner(tile)
    free = np.pad(~covered, 1).astype(np.uint8)  # the texture's border counts as used
    squares = []
    for _ in range(count):
        # the chessboard distance to the nearest used texel: the half-side of the largest square there
        half = cv2.distanceTransform(free, cv2.DIST_C, 3)[1:-1, 1:-1]
        i, j = np.unravel_index(int(np.argmax(half)), half.shape)
        h = int(half[i, j]) - gap
        side = 2 * h - 1
        squares.append(([u0 + (j - h + 1) / size, v0 + 1.0 - (i + h) / size, u0 + (j + h) / size,
                         v0 + 1.0 - (i - h + 1) / size], side))
        free[1 + max(i - h - gap, 0):1 + i + h + gap, 1 + max(j - h - gap, 0):1 + j + h + gap] = 0
    return squares


def region_cards(cfg, mesh, groups: dict, corner_uv: np.ndarray, positions: np.ndarray, config_path,
                 tile: int = 1001):
    """Cards (:func:`facepipe.core.hole_cards.hole_cards`) across the holes that the ``card``
    regions' vertex groups (``groups``: region name → vertex mask, :func:`group_masks`) rim, each
    in a free square of the UV layout on ``tile``, carried by the vertices
    that move least over the geometry's frames ``positions`` (T, V, 3); and region name → card.
    (None, {}) where no region is a card."""
    wanted = [r for r in cfg.regions if r.card]
    if not wanted:
        return None, {}
    loops = boundary_loops(mesh.faces)
    chosen, card_of = [], {}
    for region in wanted:
        share = [float(groups[region.name][loop].mean()) for loop in loops]
        best = int(np.argmax(share)) if share else -1
        if best < 0 or share[best] < 0.5:
            raise InputError(f"region {region.name}: card = true, but its vertex group holds at most "
                             f"{max(share, default=0):.0%} of any hole's rim (the mesh has {len(loops)} holes or "
                             f"open borders)", path=region.vertices,
                             hint="list the vertices around the hole the card spans (an eye's lid rims), or "
                                  "leave card out for a region on the surface")
        for other, c in card_of.items():
            if chosen[c] == best:
                raise InputError(f"regions {other} and {region.name} are cards across the same hole",
                                 path=config_path, hint="one card region per hole")
        card_of[region.name] = len(chosen)
        chosen.append(best)
    squares = free_uv_squares(corner_uv, cfg.texture_size, len(chosen), tile=tile)
    for (square, side), region in zip(squares, wanted):
        if side < MIN_CARD_TEXELS:
            raise InputError(f"region {region.name}: the UV layout has room for a card of {max(side, 0)} texels at "
                             f"texture_size = {cfg.texture_size}, under {MIN_CARD_TEXELS}", path=config_path,
                             hint="raise texture_size, or leave free space in the UV layout for the cards")
    cards = hole_cards(mesh.vertices, [loops[b] for b in chosen], np.array([sq for sq, _ in squares]),
                       stable_vertices(mesh.vertices, positions), CARD_RINGS)
    return cards, card_of


def template_rect(region, cards, card_of: dict) -> list:
    """A region's template rectangle in the UV layout: a card region's ``template`` is in its
    card's own square."""
    if region.name not in card_of:
        return region.template
    square = cards.squares[card_of[region.name]]
    u0, v0, u1, v1 = region.template
    return [square[0] + u0 * (square[2] - square[0]), square[1] + v0 * (square[3] - square[1]),
            square[0] + u1 * (square[2] - square[0]), square[1] + v1 * (square[3] - square[1])]


def card_depths(cfg, cards, card_of: dict, frames: dict, faces: np.ndarray, corner_uv: np.ndarray, camera: Camera,
                normal_sign: float, config_path, notes: list) -> tuple:
    """The cards at ``cfg.card_depth``, or (``"auto"``) each at the depth fitted from the example
    ``frames`` (number → (image, positions with the cards')) where its region is at rest
    (:func:`facepipe.pipeline.appearance_card_depth.fit_card_depth`; where they turn the head too
    little, the default depth, noted); and region name → the fit's report."""
    if cfg.card_depth != "auto":
        return cards.at_depths(cfg.card_depth), {}
    numbers = [cfg.neutral_frame] + sorted(n for n in frames if n != cfg.neutral_frame)
    at_rest = examples_at_rest(cfg, numbers)
    R = np.asarray(cfg.camera_rotation, dtype=np.float64)
    t = np.asarray(cfg.camera_translation, dtype=np.float64)
    V = cards.n_vertices
    depths, fits = cards.depths.copy(), {}
    for r, region in enumerate(cfg.regions):
        if region.name not in card_of:
            continue
        use = [n for n, rest in zip(numbers, at_rest[:, r]) if rest]  # the neutral frame first
        face, bary = region_template(region, template_rect(region, cards, card_of), corner_uv, CARD_DEPTH_GRID,
                                      config_path)
        c = card_of[region.name]
        fit = fit_card_depth(cards, c, face[0], bary[0], [frames[n][0] for n in use],
                             np.stack([frames[n][1][:V] for n in use]), camera, R, t, faces, normal_sign, cfg)
        fits[region.name] = fit
        if fit["fitted"]:
            depths[c] = fit["depth"]
            notes.append(f"region {region.name}: its card set back {fit['depth']:.3f} × the opening's width, fitted "
                         f"over {fit['frames']} example frame{'s' if fit['frames'] != 1 else ''} at rest (the head's turn moves its samples up to "
                         f"{fit['parallax']:.1f} px)")
        elif fit["parallax"] < MIN_PARALLAX:
            notes.append(f"region {region.name}: the example frames at rest turn the head too little to fit its card's "
                         f"depth (its samples move {fit['parallax']:.2f} px, under {MIN_PARALLAX:g}): set back "
                         f"{depths[c]:g} × the opening's width; add frames of the neutral face with the head turned")
        else:
            notes.append(f"region {region.name}: the example frames at rest that turn the head show too little of its "
                         f"card (under {MIN_COMMON:.0%} of its template, seen in them and the neutral frame) to fit its "
                         f"depth: set back {depths[c]:g} × the opening's width; add head-turned frames with the eye open")
    return cards.at_depths(depths), fits
