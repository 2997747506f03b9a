"""How far an eye card is set back into its opening, fitted from the example frames.

A card (:mod:`facepipe.core.hole_cards`) stands in for the eyeball behind an opening: a flat
surface carried by the head's rigid motion. What the camera sees through the opening (the
iris) lies at some depth behind the rim; a card at another depth puts each iris point on the
wrong card point as soon as the head turns (parallax), and a turned head then reads as a gaze.
The depth is observable: in the example frames where the eye is at rest (looking ahead) but the
head is turned (a capture session's range of motion), the card's texture must stay what the
neutral frame shows. So each card's depth is the candidate at which those frames' samples of
its template area match the neutral frame's best (normalised cross-correlation over the points
both see: a turned head's other shading changes the samples' level and contrast, not their
pattern), refined by a parabola through the best candidate and its neighbours. Where the
frames turn the head too little for the candidates to move a sample by :data:`MIN_PARALLAX`
pixels, the depth is not observable and the card keeps its default.
"""

from __future__ import annotations

import numpy as np

from facepipe.core import appearance as ap
from facepipe.core.hole_cards import HoleCards, card_positions, card_triangles
from facepipe.core.camera import project_distorted_fast
from facepipe.io.footage import to_gray
from facepipe.pipeline.appearance_points import points_seen_well

__all__ = ["DEPTH_CANDIDATES", "MIN_PARALLAX", "MIN_COMMON", "fit_card_depth"]

#: The depths tried, × the opening's width: from the rim's plane to 0.4 behind it (an eyeball's
#: radius is about half the opening's width; its front lies within a tenth of it).
DEPTH_CANDIDATES = np.linspace(0.0, 0.4, 33)
#: Pixels: the least shift between the nearest and farthest candidate's samples, in some frame
#: against the neutral one, for the depth to be fitted (below it the frames barely turn the head).
MIN_PARALLAX = 0.5
#: A frame counts only where it and the neutral frame both see this share of the points at
#: every candidate depth (a closing lid's frame would compare a sliver).
MIN_COMMON = 0.25
#: The grid of points sampled over the card's template area: this many to a side.
GRID = 32


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    scale = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / scale) if scale > 0 else 0.0


def fit_card_depth(cards: HoleCards, card: int, face: np.ndarray, bary: np.ndarray, images: list,
                   worlds: np.ndarray, camera, rotation: np.ndarray, translation: np.ndarray, faces: np.ndarray,
                   normal_sign: float, settings, candidates: np.ndarray = DEPTH_CANDIDATES) -> dict:
    """Fit card ``card``'s depth from frames (``images``, F RGB images, with the mesh's
    world positions (F, V, 3); the neutral frame first, the others where its eye is at rest; only
    the frames that turn the head are read), sampled at points
    (face (GRID²,), bary (GRID², 3): fixed barycentric coordinates on ``faces``, the mesh's and
    the cards' triangles) over its template area, seen through ``camera`` at the world → camera
    pose ``rotation``, ``translation``; ``settings`` the [appearance] table (its visibility tests).

    Returns {"depth": fitted (or the card's own where not observable), "fitted": bool,
    "parallax": the largest shift (pixels) between the candidates' samples in a frame against the
    neutral one, "frames": how many frames were compared, "cost": (D,) 1 − mean correlation per
    candidate (NaN where not fitted), "candidates": (D,); fitted, also "counted": the frames
    compared (indices into ``images``) and "frame_cost": (D, counted) each one's}.
    """
    if not card_triangles(faces[face], cards.n_vertices).all():
        raise ValueError("the sample points must lie on the cards' triangles")
    candidates = np.asarray(candidates, dtype=np.float64)
    worlds = np.asarray(worlds, dtype=np.float64)

    def card_camera(depth, frames):  # the cards' vertices in camera space, this card at ``depth``
        moved = cards.at_depths(np.where(np.arange(len(cards.depths)) == card, depth, cards.depths))
        return card_positions(worlds[frames], moved.stable, moved.stable_rest, moved.rest) @ rotation.T + translation

    corners = faces[face] - cards.n_vertices  # the sample points' triangles lie on the cards

    def points(card_cam):  # the sample points (F, N, 3)
        return np.einsum("nk,fnkc->fnc", bary, card_cam[:, corners])

    # how far the candidates move each frame's samples against the neutral frame's: only frames
    # that turn the head against it tell the depths apart (a still frame's samples change with
    # none, and its noise would only blur the others')
    every = np.arange(len(worlds))
    ends = [project_distorted_fast(camera, points(card_camera(d, every))) for d in candidates[[0, -1]]]
    shift = (ends[1] - ends[0]) - (ends[1][:1] - ends[0][:1])  # (F, N, 2)
    moved = np.median(np.linalg.norm(shift, axis=-1), axis=1)  # (F,)
    parallax = float(moved[1:].max(initial=0.0))
    turned = np.concatenate([[0], np.flatnonzero(moved[1:] >= MIN_PARALLAX) + 1])
    out = {"depth": float(cards.depths[card]), "fitted": False, "parallax": parallax, "frames": 0,
           "cost": np.full(len(candidates), np.nan), "candidates": candidates, "frame_cost": None}
    if len(turned) < 2:
        return out
    mesh_cam = worlds[turned] @ rotation.T + translation
    size = int(round(np.sqrt(len(face))))
    occluders = faces[~card_triangles(faces, cards.n_vertices)]  # the mesh's own: a card hides nothing
    grays = [to_gray(images[f]) for f in turned]
    values, seen = [], []
    for depth in candidates:
        cam = np.concatenate([mesh_cam, card_camera(depth, turned)], axis=1)
        good, px = points_seen_well(cam, faces, face, bary, camera, size, normal_sign, settings.min_point_facing,
                                    settings.occlusion, settings.min_relative_facing, occluders)
        sampled = np.empty(good.shape)
        for k, gray in enumerate(grays):
            sampled[k], inside = ap.bilinear_sample(gray, px[k])
            good[k] &= inside
        values.append(sampled)
        seen.append(good)
    values, seen = np.stack(values), np.stack(seen)  # (D, 1 + turned frames, N)
    common = seen & seen[:, :1]
    counted = np.flatnonzero((common.mean(axis=2) >= MIN_COMMON).all(axis=0)[1:]) + 1
    out["frames"] = int(len(counted))
    if not len(counted):
        return out
    frame_cost = np.array([[1.0 - _ncc(values[d, 0, common[d, f]], values[d, f, common[d, f]]) for f in counted]
                           for d in range(len(candidates))])
    cost = frame_cost.mean(axis=1)
    best = int(np.argmin(cost))
    depth = candidates[best]
    if 0 < best < len(candidates) - 1:  # the parabola's vertex through the best and its neighbours
        left, mid, right = cost[best - 1:best + 2]
        curve = left - 2 * mid + right
        if curve > 0:
            depth += 0.5 * (left - right) / curve * (candidates[best + 1] - candidates[best])
    out.update(depth=float(depth), fitted=True, cost=cost, frame_cost=frame_cost, counted=turned[counted])
    return out
