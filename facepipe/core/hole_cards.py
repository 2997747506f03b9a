"""Cards across the holes of a mesh: a surface where the mesh has none, for appearance regions.

A face scan's eye openings (and mouth) are holes: the skin ends at the lids, and what the camera
sees through them (the eyeball, the iris moving with the gaze) lies on no triangle, so no
texture region can hold it. A **card** spans such a hole: rings of triangles from the rim's
centre out to a copy of the rim, set back a little into the hole. It moves with the head, not
with the lids: the eyeball sits in the skull, so the card is carried by the rigid motion of the
mesh's least moving vertices (a lid that moves over the opening covers the card, as it covers
the eye, instead of shifting what the card sees). Its texture is a square of the UV layout the
mesh leaves unused, the rim on its best-fit plane pushed out from its centre onto the square's
border (a rim must be star-shaped about its centre, as eye openings are); the card's triangles
wind as the mesh's around the rim, so their normals face the same side.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from facepipe.core.rigid import rigid_fit, robust_rigid_fit

__all__ = ["boundary_loops", "HoleCards", "hole_cards", "card_positions", "card_triangles", "with_card_vertices",
           "stable_vertices"]


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """The mesh's holes and open borders: closed loops of vertex indices (each in the direction
    of its triangles' boundary edges), longest first. A vertex where two loops touch starts the
    next loop where the walk left it (each boundary edge is used once)."""
    faces = np.asarray(faces, dtype=np.int64)
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    n = int(faces.max()) + 1 if faces.size else 0
    key = half[:, 0] * n + half[:, 1]
    twin = half[:, 1] * n + half[:, 0]
    boundary = half[~np.isin(key, twin)]
    if boundary.shape[0] == 0:
        return []
    order = np.argsort(boundary[:, 0], kind="stable")
    starts = np.searchsorted(boundary[order, 0], np.arange(n + 1))
    used = np.zeros(boundary.shape[0], dtype=bool)
    loops = []
    for first in range(boundary.shape[0]):
        if used[first]:
            continue
        loop, edge = [], first
        while not used[edge]:
            used[edge] = True
            a, b = boundary[edge]
            loop.append(int(a))
            out = order[starts[b]:starts[b + 1]]
            free = out[~used[out]]
            if free.shape[0] == 0:
                break
            edge = int(free[0])
        loops.append(np.asarray(loop, dtype=np.int64))
    return sorted(loops, key=len, reverse=True)


@dataclass
class HoleCards:
    """Cards across holes, appended to a mesh of V vertices.

    rest : (N, 3) the cards' vertices at rest (vertex V + i of ``faces``); stable (K,),
    stable_rest (K, 3) : the mesh's vertices that carry the cards — the head's least moving
    ones, their rest positions — whose rigid motion each frame moves the cards; faces : (T, 3)
    the cards' triangles (indices V … V + N − 1); corner_uv : (T, 3, 2); card : (T,) which card
    each triangle belongs to; squares : (C, 4) each card's UV square [u0, v0, u1, v1];
    rim_sizes : (C,) the vertices of each card's rim; depths (C,), widths (C,), normals (C, 3):
    each card set back by depth × its rim's width along −normal (its rim's outward normal);
    vertex_card (N,) : which card each vertex belongs to.
    """

    n_vertices: int
    rest: np.ndarray
    stable: np.ndarray
    stable_rest: np.ndarray
    faces: np.ndarray
    corner_uv: np.ndarray
    card: np.ndarray
    squares: np.ndarray
    rim_sizes: np.ndarray
    depths: np.ndarray
    widths: np.ndarray
    normals: np.ndarray
    vertex_card: np.ndarray

    def at_depths(self, depths) -> "HoleCards":
        """The same cards set back by ``depths`` (a number, or one per card) × their rims' widths."""
        depths = np.broadcast_to(np.asarray(depths, dtype=np.float64), self.depths.shape).copy()
        shift = ((self.depths - depths) * self.widths)[self.vertex_card, None] * self.normals[self.vertex_card]
        return replace(self, rest=self.rest + shift, depths=depths)

    def extend(self, positions: np.ndarray) -> np.ndarray:
        """Positions (..., V, 3) with the cards' vertices after the mesh's: (..., V + N, 3)."""
        positions = np.asarray(positions, dtype=np.float64)
        if positions.shape[-2] != self.n_vertices:
            raise ValueError(f"positions of {positions.shape[-2]} vertices for a mesh of {self.n_vertices}")
        return with_card_vertices(positions, self.stable, self.stable_rest, self.rest)


def card_triangles(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(T,) which triangles of a mesh of ``n_vertices`` with cards appended (their vertices after
    its, their triangles after its) lie on a card: a card's triangles use only its vertices."""
    return np.asarray(faces).min(axis=1) >= n_vertices


def with_card_vertices(positions: np.ndarray, stable: np.ndarray, stable_rest: np.ndarray,
                       rest: np.ndarray) -> np.ndarray:
    """Positions (..., V, 3) with the cards' vertices (:func:`card_positions`) after them: (..., V + N, 3)."""
    positions = np.asarray(positions, dtype=np.float64)
    return np.concatenate([positions, card_positions(positions, stable, stable_rest, rest)], axis=-2)


#: A frame whose stable vertices all lie within this share of their extent of a rigid motion of
#: their rest positions moved rigidly; beyond it some moved on their own and the fit is robust.
STILL_RESIDUAL = 1e-4


def card_positions(positions: np.ndarray, stable: np.ndarray, stable_rest: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """The cards' vertices (..., N, 3) in frames (..., V, 3): their rest positions (N, 3) moved by
    the rigid motion of the ``stable`` vertices (K,) from ``stable_rest`` (K, 3).

    The motion is fitted robustly (:func:`~facepipe.core.rigid.robust_rigid_fit`): a vertex that
    stayed still in every example may move in a take (a jaw opening the examples never show), and
    a card pulled along with it would shift over the eyeball as a gaze does."""
    target = np.asarray(positions, dtype=np.float64)[..., stable, :]
    flat = target.reshape((-1,) + target.shape[-2:])
    R, t = rigid_fit(stable_rest, flat)
    # the robust fit only for frames whose stable vertices did not all follow (it costs ten fits)
    residual = np.linalg.norm(np.einsum("fij,kj->fki", R, stable_rest) + t[:, None] - flat, axis=-1).max(axis=-1)
    moved = residual > STILL_RESIDUAL * float(np.ptp(stable_rest, axis=0).max(initial=0.0))
    if moved.any():
        R[moved], t[moved], _ = robust_rigid_fit(stable_rest, flat[moved])
    R, t = R.reshape(target.shape[:-2] + (3, 3)), t.reshape(target.shape[:-2] + (3,))
    return np.einsum("...ij,nj->...ni", R, rest) + t[..., None, :]


#: Rounds of :func:`stable_vertices`' trimmed fit at most (it stops once its set repeats).
STABLE_ROUNDS = 20


def stable_vertices(rest: np.ndarray, frames: np.ndarray, share: float = 0.1, most: int = 2000) -> np.ndarray:
    """The vertices (at least 3, at most ``most``, evenly taken) that move least over ``frames``
    (F, V, 3) after each frame's rigid fit of those vertices themselves: a ``share`` of them;
    every vertex where no frame moves one (then the head's rigid motion is carried by the whole
    mesh).

    The fit is trimmed (least trimmed squares' concentration steps): fitted to the set, the set
    is the ``share`` of vertices it leaves the least squared residual over the frames, until the
    set repeats; each step lowers the set's residual, to a local least. A least-squares fit of
    the whole mesh is pulled by the expression's moving part, and the rotation it gets wrong
    moves still vertices by their distance from the centroid (far ones, the back of the head,
    look moved; ones near the middle, a jaw's side, look still); and where the expressions move
    most of the mesh a little (a blendshape rig's deltas rarely end where the skull does), its
    steps can settle on a block that moves together. So the steps start three ways, from the
    whole mesh's fit, from a robust fit's (:func:`~facepipe.core.rigid.robust_rigid_fit`) and
    from the vertices that move least without any fit (the examples' head still), and the set
    with the least residual is kept."""
    rest = np.asarray(rest, dtype=np.float64)
    frames = np.asarray(frames, dtype=np.float64).reshape(-1, *rest.shape)
    count = max(3, int(share * len(rest)))
    least = np.arange(count)
    if len(frames):
        def residuals(R, t):  # (V,) squared, summed over the frames, a frame at a time (a large mesh's would not fit)
            out = np.zeros(len(rest))
            for f in range(len(frames)):
                out += ((rest @ R[f].T + t[f] - frames[f]) ** 2).sum(axis=1)
            return out

        def concentrate(moved):
            chosen = None
            for _ in range(STABLE_ROUNDS):
                picked = np.sort(np.argsort(moved, kind="stable")[:count])
                if chosen is not None and np.array_equal(picked, chosen):
                    break
                chosen = picked
                moved = residuals(*rigid_fit(rest[chosen], frames[:, chosen]))
            return moved[chosen].sum(), chosen

        still = (np.broadcast_to(np.eye(3), (len(frames), 3, 3)), np.zeros((len(frames), 3)))  # no fit at all
        starts = [residuals(*rigid_fit(rest, frames)), residuals(*robust_rigid_fit(rest, frames)[:2]), residuals(*still)]
        least = min((concentrate(moved) for moved in starts), key=lambda found: found[0])[1]
    return least[np.linspace(0, len(least) - 1, min(most, len(least))).round().astype(np.int64)]


def _plane_axes(points: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane axes (e1, e2) of points around their mean: e1 along their widest spread, and
    (e1, e2, normal) right-handed, so a triangle winding around ``normal`` winds the same in UV."""
    centred = points - points.mean(axis=0)
    flat = centred - np.outer(centred @ normal, normal)
    _, _, vt = np.linalg.svd(flat, full_matrices=False)
    e1 = vt[0] - (vt[0] @ normal) * normal
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(normal, e1)


def hole_cards(rest: np.ndarray, loops: list[np.ndarray], squares: np.ndarray, stable: np.ndarray,
               rings: int = 4, depth=0.1) -> HoleCards:
    """Cards across the holes ``loops`` (from :func:`boundary_loops`) of a mesh with rest
    positions (V, 3), each textured over its UV square (C, 4) [u0, v0, u1, v1]; ``rings`` rings of
    triangles from the centre to the rim, the card set back into the hole by ``depth`` × the
    rim's width (so lids that close over the opening lie in front of it); carried by the rigid
    motion of the ``stable`` vertices (:func:`stable_vertices`); ``depth`` a number, or one per card."""
    rest = np.asarray(rest, dtype=np.float64)
    V = rest.shape[0]
    stable = np.asarray(stable, dtype=np.int64)
    positions, faces, uvs, card, normals, widths = [], [], [], [], [], []
    depths = np.broadcast_to(np.asarray(depth, dtype=np.float64), (len(loops),)).copy()
    for c, (loop, square) in enumerate(zip(loops, np.asarray(squares, dtype=np.float64))):
        loop = np.asarray(loop, dtype=np.int64)
        L = loop.shape[0]
        if L < 3:
            raise ValueError(f"a hole's rim needs three vertices or more, not {L}")
        P = rest[loop]
        centre = P.mean(axis=0)
        nxt = np.roll(P, -1, axis=0)  # the card's fan triangles (rim j, rim i, centre): their summed normal
        normal = np.cross(P - nxt, centre - nxt).sum(axis=0)
        normal /= max(np.linalg.norm(normal), 1e-300)
        e1, e2 = _plane_axes(P, normal)
        flat = np.stack([(P - centre) @ e1, (P - centre) @ e2], axis=1)
        width = float(np.ptp(flat[:, 0]))
        # the card's vertices: its centre, then rings 1 … K from the centre to a copy of the rim
        # (ring K), the whole card set back along its normal
        s = np.arange(1, rings + 1) / rings
        ring_pos = (1 - s)[:, None, None] * centre + s[:, None, None] * P[None]  # (K, L, 3)
        first = V + sum(len(p) for p in positions)
        positions.append(np.concatenate([centre[None], ring_pos.reshape(-1, 3)]) - depths[c] * width * normal)
        normals.append(normal)
        widths.append(width)
        ids = first + 1 + np.arange(rings * L).reshape(rings, L)
        # the rim walked as the mesh's boundary edges run (a → b): the card runs each edge b → a,
        # winding as the mesh's triangles that end at the rim
        i = np.arange(L)
        j = (i + 1) % L
        tri = [np.stack([ids[0, j], ids[0, i], np.full(L, first)], axis=1)]
        for k in range(rings - 1):
            inner, outer = ids[k], ids[k + 1]
            tri += [np.stack([outer[j], outer[i], inner[i]], axis=1), np.stack([outer[j], inner[i], inner[j]], axis=1)]
        tri = np.concatenate(tri)
        # UV: the rim on its best-fit plane pushed out from its centre onto the square's border
        # (2 % in), so the card fills its square and any template inside it lies on the card;
        # the rings are the same mixes of the rim's UVs as of its positions
        flat /= np.maximum(np.abs(flat).max(axis=0), 1e-300)  # the rim's extent: ±1 along both axes
        unit = 0.5 + 0.48 * flat / np.maximum(np.abs(flat).max(axis=1, keepdims=True), 1e-300)
        rim_uv = square[:2] + unit * (square[2:] - square[:2])
        centre_uv = rim_uv.mean(axis=0)
        vertex_uv = np.concatenate([centre_uv[None], ((1 - s)[:, None, None] * centre_uv
                                                      + s[:, None, None] * rim_uv[None]).reshape(-1, 2)])
        faces.append(tri)
        uvs.append(vertex_uv[tri - first])
        card.append(np.full(len(tri), c, dtype=np.int64))
    return HoleCards(V, np.concatenate(positions) if positions else np.zeros((0, 3)), stable, rest[stable],
                     np.concatenate(faces) if faces else np.zeros((0, 3), dtype=np.int64),
                     np.concatenate(uvs) if uvs else np.zeros((0, 3, 2)),
                     np.concatenate(card) if card else np.zeros(0, dtype=np.int64),
                     np.asarray(squares, dtype=np.float64).reshape(-1, 4),
                     np.array([len(loop) for loop in loops], dtype=np.int64), depths,
                     np.array(widths, dtype=np.float64), np.array(normals, dtype=np.float64).reshape(-1, 3),
                     np.repeat(np.arange(len(positions)), [len(p) for p in positions]).astype(np.int64))
