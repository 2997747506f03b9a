"""A synthetic, face-like rig with strain-driven wrinkles: the project's built-in test face.

The generator mirrors the files of the ICT kit (see ``shared/data/ict/README.md``) so that
every stage of the pipeline can run, and be checked against ground truth, without outside
data:

* the **surface** is the front of an ellipsoid (semi-axes 8.5 × 13 × 9.5 cm, longitude
  ±70°, latitude -58°..50°: 16 cm wide, 21 cm tall, 9 cm deep) with a nose, eye sockets, lips
  and chin added as smooth relief along the normal, and a mouth slit (a hole, 5 cm wide). It
  is sampled on a regular (u, v) grid of about square cells, each split into two triangles
  (diagonals alternating); the UVs are the grid parameters;
* **face coordinates** (X, Y) in cm are arc lengths along the grid's rows and columns from the
  middle of the face. Markers, expressions and wrinkles are all laid out in (X, Y), which
  does not depend on the resolution, so the rig is the same face at any vertex count;
* 90 **handle markers** (a centroidal Voronoi tessellation of the face at least 2 cm off the
  border, mean nearest-neighbour distance 1.6 cm, eight of them fixed on the lips) and 6
  **stable markers** (forehead top, temples, nose bridge; they move by 0.08 cm at most) snap
  to the nearest vertex;
* the **anchors** are the 1 cm band along the border, which no expression moves (every field
  fades in from 1.5 to 4 cm off the border);
* each **expression** is a smooth displacement field (Gaussian muscle pulls, 0.5–1.3 cm at
  most; the jaw tears the mouth open along the slit) plus **wrinkles**: where the smooth field
  compresses the skin along u or v, a normal offset ``a_max tanh((c - c_crit) / c0) cos(2π s / λ)``
  appears (``c`` the compression, ``s`` the face coordinate along it, λ = 0.7 cm,
  a_max = 0.12 cm, c_crit = 0.02, c0 = 0.15);
* the **take** mixes the expressions with smooth random weights; the truth of every frame
  applies the same wrinkle rule to the mixed smooth field, so the wrinkles of a mixture are
  not the mixture of the examples' wrinkles (as in real skin, and unlike a blendshape rig).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

from facepipe.io.atomic import atomic_open, atomic_path
from facepipe.errors import InputError
from facepipe.core.mesh import Mesh
from facepipe.io.point_caches import write_mdd
from facepipe.io.mesh_write import format_obj_faces, obj_bytes, save_obj

# --- the surface: the front of an ellipsoid, in cm (+x subject's left, +y up, +z out) -------
_A, _B, _C = 8.5, 13.0, 9.5           # semi-axes along x, y, z
_PHI0 = np.deg2rad(70.0)               # half the longitude range (u)
_THETA_LO, _THETA_HI = np.deg2rad(-58.0), np.deg2rad(50.0)   # latitude range (v): room under the chin
_GL_X, _GL_W = np.polynomial.legendre.leggauss(16)
_GL_X, _GL_W = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W     # Gauss-Legendre on [0, 1]

# --- layout in face coordinates (X, Y), cm -------------------------------------------------
_MOUTH_Y = -4.0                        # mouth slit centre line
_MOUTH_HALF_WIDTH = 2.5
_MOUTH_HALF_HEIGHT = 0.2               # at least 0.75 of a grid row, so the slit is always open
_ANCHOR_BAND = 1.0                     # anchors: closer than this to the border
_GATE_START, _GATE_WIDTH = 1.5, 2.5    # expressions fade in from 1.5 to 4 cm off the border
_MARKER_MARGIN = 2.0                   # handle markers at least this far from the border
_N_HANDLES = 90

# --- the wrinkle rule ----------------------------------------------------------------------
WAVELENGTH = 0.7                       # cm, about 0.4 x the marker spacing: too fine for markers
WRINKLE_MAX = 0.12                     # cm, saturation amplitude
WRINKLE_CRITICAL = 0.02                # compression below which skin does not buckle
WRINKLE_SCALE = 0.15                   # compression beyond critical that gives 76 % of max

FPS = 30.0
MIN_VERTICES = 2000                    # below this the grid cannot hold the markers apart


@dataclass
class SampleRig:
    """The synthetic rig as arrays (see :func:`make_sample_arrays`).

    Attributes
    ----------
    mesh : Mesh
        Rest pose, triangles, per-corner UVs (the grid parameters in [0, 1]²), cm.
    marker_names : list of str, (M,)
        ``M001``..``M090`` (handles) then ``S01``..``S06`` (stable).
    marker_vertices : (M,) int64
        0-based vertex of every marker.
    marker_roles : list of str, (M,)
        ``"handle"`` or ``"stable"``.
    anchors : (A,) int64
        Sorted vertices of the border band that no expression moves.
    example_names : list of str, (E,)
        Sorted expression names (the order ``expressions/*.obj`` globs in).
    example_positions : (E, V, 3) float64
        Example poses, cm: neutral + smooth field + wrinkles.
    example_wrinkles : (E, V) float64
        The wrinkle part of every example: offset along the deformed normal, cm.
    example_compression : (E, V, 2) float64
        Compression of the smooth field along u and v (``max(0, -strain)``), unitless.
    take_positions : (T, V, 3) float32
        Ground truth of every frame of the take, cm.
    take_weights : (T, E) float32
        Expression weights of the take, in [0, 1].
    fps : float
        Frames per second of the take.
    face_coords : (V, 2) float64
        Face coordinates (X, Y) of every vertex, cm.
    wavelength : float
        Wrinkle wavelength, cm.
    """

    mesh: Mesh
    marker_names: list
    marker_vertices: np.ndarray
    marker_roles: list
    anchors: np.ndarray
    example_names: list
    example_positions: np.ndarray
    example_wrinkles: np.ndarray
    example_compression: np.ndarray
    take_positions: np.ndarray
    take_weights: np.ndarray
    fps: float
    face_coords: np.ndarray
    wavelength: float = WAVELENGTH
    #: (T, V, 3) float32: the take's truth without the wrinkles (the smooth motion a rig would
    #: export as a point cache), cm
    take_smooth: np.ndarray | None = None

    @property
    def take_times(self) -> np.ndarray:
        """(T,) float64 seconds of every frame."""
        return np.arange(self.take_positions.shape[0], dtype=np.float64) / self.fps


# =========================================================================== the surface


def _smootherstep(t: np.ndarray) -> np.ndarray:
    # C2, so that strains (first derivatives of the fields) stay C1 where a field fades in
    t = np.clip(t, 0.0, 1.0)
    return t * t * t * (t * (6.0 * t - 15.0) + 10.0)


def _gauss(X, Y, cx, cy, sx, sy):
    return np.exp(-0.5 * (((X - cx) / sx) ** 2 + ((Y - cy) / sy) ** 2))


def _row_arc(phi: np.ndarray) -> np.ndarray:
    """Arc length along the equator from φ = 0 to φ (signed), cm; a row at θ is cos θ times this."""
    t = phi[..., None] * _GL_X
    return phi * (np.sqrt((_A * np.cos(t)) ** 2 + (_C * np.sin(t)) ** 2) @ _GL_W)


def _column_arc(phi: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Arc length along the meridian at φ from θ = 0 to θ (signed), cm."""
    k2 = (_A * np.sin(phi)) ** 2 + (_C * np.cos(phi)) ** 2
    t = theta[..., None] * _GL_X
    return theta * (np.sqrt((_B * np.cos(t)) ** 2 + k2[..., None] * np.sin(t) ** 2) @ _GL_W)


def _face_coords(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Face coordinates X, Y (cm) and the distance to the border along the grid lines (cm)."""
    phi = (2.0 * u - 1.0) * _PHI0
    theta = _THETA_LO + v * (_THETA_HI - _THETA_LO)
    g = _row_arc(phi)
    X = np.cos(theta) * g
    Y = _column_arc(phi, theta)
    to_side = np.cos(theta) * (_row_arc(np.array(_PHI0)) - np.abs(g))
    # the ends of the meridians depend on φ only: evaluate them once per distinct φ
    phis, which = np.unique(phi, return_inverse=True)
    top = _column_arc(phis, np.full_like(phis, _THETA_HI))[which].reshape(phi.shape)
    bottom = _column_arc(phis, np.full_like(phis, _THETA_LO))[which].reshape(phi.shape)
    to_top, to_bottom = top - Y, Y - bottom
    return X, Y, np.minimum(to_side, np.minimum(to_top, to_bottom))


def _relief(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Height of nose, eye sockets, lips and chin above the ellipsoid, cm (slopes below 1)."""
    h = 1.2 * _gauss(X, Y, 0.0, -0.8, 0.9, 0.8)                      # nose tip
    h += 0.6 * _gauss(X, Y, 0.0, 1.2, 0.7, 1.8)                      # nose ridge
    h -= 0.7 * (_gauss(X, Y, -3.2, 2.4, 1.3, 1.0) + _gauss(X, Y, 3.2, 2.4, 1.3, 1.0))
    h += 0.3 * _gauss(X, Y, 0.0, _MOUTH_Y, 2.0, 0.8)                  # lips
    h += 0.3 * _gauss(X, Y, 0.0, -7.0, 1.8, 1.0)                     # chin
    return h


def _surface(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points of the face surface at grid parameters (u, v) ∈ [0, 1]².

    Returns
    -------
    points : (..., 3) float64, cm.
    X, Y : (...) float64 face coordinates, cm.
    border : (...) float64 distance to the border along the grid lines, cm.
    """
    phi = (2.0 * u - 1.0) * _PHI0
    theta = _THETA_LO + v * (_THETA_HI - _THETA_LO)
    e = np.stack([_A * np.cos(theta) * np.sin(phi), _B * np.sin(theta), _C * np.cos(theta) * np.cos(phi)], -1)
    normal = e / np.array([_A * _A, _B * _B, _C * _C])
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    X, Y, border = _face_coords(u, v)
    return e + _relief(X, Y)[..., None] * normal, X, Y, border


def _grid_shape(n_vertices: int) -> tuple[int, int]:
    # cells about square on average: columns/rows = mean row length / column length
    row = 2.0 * float(_row_arc(np.array(_PHI0))) * (np.sin(_THETA_HI) - np.sin(_THETA_LO)) / (_THETA_HI - _THETA_LO)
    column = float(_column_arc(np.array(0.0), np.array(_THETA_HI)) - _column_arc(np.array(0.0), np.array(_THETA_LO)))
    nu = round(float(np.sqrt(n_vertices * row / column)))
    nu += 1 - nu % 2                   # odd: a grid column on the face's mid line
    nv = round(n_vertices / nu)
    return nu, nv


def _face_mesh(n_vertices: int):
    """The triangulated grid with the mouth slit cut out.

    Returns vertices (V, 3), faces (F, 3) int64, uvs (V, 2), face coordinates (V, 2), border
    distance (V,), unit tangents along u and v (V, 3) each, and the grid edges along u and
    along v, (Eu, 2) and (Ev, 2) int64.
    """
    nu, nv = _grid_shape(n_vertices)
    uu, vv = np.meshgrid(np.linspace(0.0, 1.0, nu), np.linspace(0.0, 1.0, nv))
    points, X, Y, border = _surface(uu, vv)
    # tangent frame of the rest surface: differences on the grid are O(h²), far below anything
    # that matters here, and cheaper than differentiating the quadratures
    t_u = np.gradient(points, axis=1)
    t_v = np.gradient(points, axis=0)

    # mouth slit: cells whose centre falls in a flat-ended lens; at least one full row is cut
    # (half height >= 0.75 row), so the hole is open at every resolution
    mid_y = Y[:, nu // 2]
    half_height = max(_MOUTH_HALF_HEIGHT, 0.75 * float(np.max(np.diff(mid_y))))
    rows = np.flatnonzero(np.abs(0.5 * (mid_y[1:] + mid_y[:-1]) - _MOUTH_Y) < half_height + 0.5)
    cu, cv = np.meshgrid((np.arange(nu - 1) + 0.5) / (nu - 1), (rows + 0.5) / (nv - 1))
    cX, cY, _ = _face_coords(cu, cv)
    keep = np.ones((nv - 1, nu - 1), dtype=bool)
    keep[rows] = (np.abs(cX) / _MOUTH_HALF_WIDTH) ** 4 + (np.abs(cY - _MOUTH_Y) / half_height) ** 4 >= 1.0

    idx = np.arange(nu * nv).reshape(nv, nu)
    a, b, c, d = (corner[keep] for corner in (idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]))
    # alternate the diagonal in a checkerboard so the triangulation has no preferred direction
    flip = ((np.arange(nv - 1)[:, None] + np.arange(nu - 1)[None, :]) % 2).astype(bool)[keep][:, None]
    t1 = np.where(flip, np.stack([a, b, d], -1), np.stack([a, b, c], -1))
    t2 = np.where(flip, np.stack([b, c, d], -1), np.stack([a, c, d], -1))
    faces = np.concatenate([t1, t2])
    # a grid edge exists when a kept cell lies on either side of it
    pad = np.zeros((nv + 1, nu + 1), dtype=bool)
    pad[1:-1, 1:-1] = keep
    u_on = (pad[1:, 1:-1] | pad[:-1, 1:-1]).ravel()
    v_on = (pad[1:-1, 1:] | pad[1:-1, :-1]).ravel()
    u_edges = np.stack([idx[:, :-1].ravel()[u_on], idx[:, 1:].ravel()[u_on]], -1)
    v_edges = np.stack([idx[:-1, :].ravel()[v_on], idx[1:, :].ravel()[v_on]], -1)

    used = np.zeros(nu * nv, dtype=bool)
    used[faces] = True
    remap = np.cumsum(used) - 1
    uv = np.stack([uu, vv], -1).reshape(-1, 2)[used]
    t_u = t_u.reshape(-1, 3)[used]
    t_v = t_v.reshape(-1, 3)[used]
    return (points.reshape(-1, 3)[used], remap[faces], uv, np.stack([X, Y], -1).reshape(-1, 2)[used],
            border.ravel()[used], t_u / np.linalg.norm(t_u, axis=1, keepdims=True),
            t_v / np.linalg.norm(t_v, axis=1, keepdims=True), remap[u_edges], remap[v_edges])


# =========================================================================== markers


_LIP_MARKERS = [(x, _MOUTH_Y + dy) for dy in (0.45, -0.45) for x in (-1.2, 0.0, 1.2)] + \
               [(-2.75, _MOUTH_Y), (2.75, _MOUTH_Y)]
_STABLE_MARKERS = [(0.0, 8.3), (-3.2, 8.2), (3.2, 8.2), (-7.4, 4.6), (7.4, 4.6), (0.0, 1.4)]


@functools.lru_cache(maxsize=4)
def _marker_uvs(n_handles: int = _N_HANDLES) -> np.ndarray:
    """(n_handles + 6, 2) grid parameters of the handle (90 by default) then 6 stable markers.

    A centroidal Voronoi tessellation (Lloyd's iterations) of the face region on a fixed
    reference grid spreads the free handles evenly in 3D around the fixed lip and stable
    markers; being computed on its own grid, it does not depend on the mesh's resolution.
    """
    uu, vv = np.meshgrid(np.linspace(0.0, 1.0, 201), np.linspace(0.0, 1.0, 221))
    points, X, Y, border = _surface(uu, vv)
    near_mouth = (np.abs(X) < _MOUTH_HALF_WIDTH + 0.1) & (np.abs(Y - _MOUTH_Y) < 0.35)
    ok = ((border >= _MARKER_MARGIN) & ~near_mouth).ravel()
    cand = points.reshape(-1, 3)[ok]
    cand_xy = np.stack([X, Y], -1).reshape(-1, 2)[ok]
    cand_uv = np.stack([uu, vv], -1).reshape(-1, 2)[ok]
    xy_tree = cKDTree(cand_xy)
    fixed = cand[xy_tree.query(np.array(_LIP_MARKERS + _STABLE_MARKERS))[1]]

    # farthest-point start: deterministic and already well spread
    n_free = n_handles - len(_LIP_MARKERS)
    dist = np.min(np.linalg.norm(cand[:, None, :] - fixed[None], axis=2), axis=1)
    free = np.empty((n_free, 3))
    for k in range(n_free):
        i = int(np.argmax(dist))
        free[k] = cand[i]
        dist = np.minimum(dist, np.linalg.norm(cand - cand[i], axis=1))
    for _ in range(40):
        owner = cKDTree(np.concatenate([free, fixed])).query(cand)[1]
        counts = np.bincount(owner, minlength=n_free + len(fixed))[:n_free]
        sums = np.stack([np.bincount(owner, cand[:, j], minlength=n_free + len(fixed))[:n_free]
                         for j in range(3)], -1)
        free = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], free)
    tree = cKDTree(cand)
    free_uv = cand_uv[tree.query(free)[1]]
    fixed_uv = cand_uv[tree.query(fixed)[1]]
    handles = np.concatenate([free_uv, fixed_uv[: len(_LIP_MARKERS)]])
    # name handles top to bottom in 1 cm bands, then left to right (subject's right first)
    hX, hY, _ = _face_coords(handles[:, 0], handles[:, 1])
    handles = handles[np.lexsort((hX, -np.round(hY)))]
    uvs = np.concatenate([handles, fixed_uv[len(_LIP_MARKERS):]])
    uvs.flags.writeable = False        # cached and shared between calls
    return uvs


# =========================================================================== expressions

# name: list of (centre X, Y; sigma X, Y; displacement along u, v, normal), cm
_PULLS: dict[str, list] = {
    "browRaise": [((-2.8, 4.8), (1.6, 1.5), (0.0, 0.9, 0.1)), ((2.8, 4.8), (1.6, 1.5), (0.0, 0.9, 0.1)),
                  ((0.0, 5.2), (1.4, 1.4), (0.0, 0.3, 0.0))],
    "frown": [((-1.5, 4.0), (1.3, 1.2), (0.6, -0.4, -0.1)), ((1.5, 4.0), (1.3, 1.2), (-0.6, -0.4, -0.1))],
    "smile_L": [((2.9, -3.8), (1.6, 1.5), (0.7, 0.8, 0.2)), ((3.6, -1.6), (1.8, 1.6), (0.1, 0.5, 0.35))],
    "pucker": [((-1.8, -4.0), (1.4, 1.3), (0.5, 0.0, 0.3)), ((1.8, -4.0), (1.4, 1.3), (-0.5, 0.0, 0.3)),
               ((0.0, -4.0), (1.5, 1.3), (0.0, 0.0, 0.4))],
    "squint_L": [((3.3, 1.0), (1.4, 1.2), (0.0, 0.45, 0.1)), ((5.6, 2.4), (1.3, 1.4), (-0.5, 0.1, 0.0))],
    "sneer": [((-1.1, 0.6), (1.1, 1.3), (0.1, 0.5, 0.1)), ((1.1, 0.6), (1.1, 1.3), (-0.1, 0.5, 0.1))],
    "mouthFrown_L": [((2.8, -4.4), (1.5, 1.4), (0.1, -0.6, 0.0))],
    "cheekPuff": [((-3.4, -3.2), (1.8, 1.6), (-0.2, 0.0, 0.8)), ((3.4, -3.2), (1.8, 1.6), (0.2, 0.0, 0.8))],
}
for _left in ("smile_L", "squint_L", "mouthFrown_L"):  # the right side mirrors the left
    _PULLS[_left[:-1] + "R"] = [((-cx, cy), s, (-dx, dy, dn)) for (cx, cy), s, (dx, dy, dn) in _PULLS[_left]]

# the first n_examples of this list make the example set
_PRIORITY = ["browRaise", "jawOpen", "smile_L", "smile_R", "frown", "pucker", "squint_L", "squint_R",
             "sneer", "mouthFrown_L", "mouthFrown_R", "cheekPuff"]
EXPRESSIONS = tuple(_PRIORITY)


def _jaw_weight(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    # The jaw tears the mouth open: below the slit everything follows the jaw; above it the
    # upper lip stays (1 - p), while beside the slit (|X| > 2.2, p = 0) both sides agree, so the
    # field is continuous (C1) everywhere except across the hole.
    side = np.exp(-0.5 * (X / 3.0) ** 2)
    below = np.where(Y >= -6.5, 1.0, np.exp(-0.5 * ((Y + 6.5) / 2.0) ** 2))
    p = np.where(np.abs(X) < 2.2, np.cos(0.5 * np.pi * X / 2.2) ** 2, 0.0)
    above = np.exp(-0.5 * ((Y - _MOUTH_Y) / 1.5) ** 2) * (1.0 - p)
    return side * np.where(Y < _MOUTH_Y, below, above)


def _expression_field(name: str, xy: np.ndarray, gate: np.ndarray, frame: tuple) -> np.ndarray:
    """Smooth displacement (V, 3) cm of one expression at weight 1."""
    X, Y = xy[:, 0], xy[:, 1]
    local = np.zeros((xy.shape[0], 3))
    if name == "jawOpen":
        local += _jaw_weight(X, Y)[:, None] * np.array([0.0, -1.1, -0.3])
    else:
        for (cx, cy), (sx, sy), d in _PULLS[name]:
            local += _gauss(X, Y, cx, cy, sx, sy)[:, None] * np.asarray(d)
    t_u, t_v, n = frame
    return gate[:, None] * (local[:, :1] * t_u + local[:, 1:2] * t_v + local[:, 2:] * n)


# =========================================================================== wrinkles


def _norm(x: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("ij,ij->i", x, x))


class _WrinkleRule:
    """The fine-scale detail of a pose as a function of its smooth displacement field.

    The skin's strain along u (v) at a vertex is the stretch of the grid line through it: the
    mean of its u (v) edges, deformed against rest (a central difference inside the grid).
    Where the skin is compressed by more than ``WRINKLE_CRITICAL`` it buckles into waves
    across the compression direction, along the deformed normal ``t_u × t_v``.

    Parameters
    ----------
    rest : (V, 3) float64 rest positions, cm.
    u_edges, v_edges : (Eu, 2), (Ev, 2) int64 grid edges along u and along v.
    xy : (V, 2) float64 face coordinates, cm (the waves' phase).
    gate : (V,) float64 in [0, 1], zero where nothing may move.
    """

    def __init__(self, rest: np.ndarray, u_edges: np.ndarray, v_edges: np.ndarray, xy: np.ndarray,
                 gate: np.ndarray, wavelength: float = WAVELENGTH):
        self.rest = rest
        self.edges = (u_edges, v_edges)
        n_v = rest.shape[0]
        self.mean = []
        for e in self.edges:
            # (V, E) sparse: every vertex averages the edges it lies on
            m = scipy.sparse.csr_matrix((np.ones(2 * len(e)), (e.T.ravel(), np.tile(np.arange(len(e)), 2))),
                                        shape=(n_v, len(e)))
            self.mean.append(scipy.sparse.diags(1.0 / np.asarray(m.sum(axis=1)).ravel()) @ m)
        self.rest_len = np.stack([_norm(t) for t in self._tangents(rest)], -1)
        k = 2.0 * np.pi / wavelength
        self.waves = gate[:, None] * np.cos(k * xy)        # (V, 2): waves across u, across v

    def _tangents(self, x: np.ndarray) -> list[np.ndarray]:
        return [m @ (x[e[:, 1]] - x[e[:, 0]]) for m, e in zip(self.mean, self.edges)]

    def compression(self, smooth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Compression along u and v (V, 2) (``max(0, -strain)``) and unit normals (V, 3)."""
        t_u, t_v = self._tangents(self.rest + smooth)
        strain = np.stack([_norm(t_u), _norm(t_v)], -1) / self.rest_len - 1.0
        normal = np.cross(t_u, t_v)
        normal /= _norm(normal)[:, None]
        return np.maximum(0.0, -strain), normal

    def __call__(self, smooth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Wrinkled positions (V, 3), normal offsets (V,) and compression (V, 2) of a smooth field."""
        compression, normal = self.compression(smooth)
        amplitude = WRINKLE_MAX * np.tanh(np.maximum(0.0, compression - WRINKLE_CRITICAL) / WRINKLE_SCALE)
        offset = np.sum(amplitude * self.waves, axis=1)
        return self.rest + smooth + offset[:, None] * normal, offset, compression


# =========================================================================== the take


def _take_weights(n_frames: int, n_examples: int, rng: np.random.Generator) -> np.ndarray:
    """(T, E) smooth weights in [0, 1]: every expression rises and falls 1-2 times (per 120 frames)
    in raised-cosine bumps of 16-40 frames that never overlap, so about 3 are active at once."""
    t = np.arange(n_frames, dtype=np.float64)
    weights = np.zeros((n_frames, n_examples))
    for k in range(n_examples):
        n_events = 1 + rng.poisson(n_frames / 240.0)
        slot = n_frames / n_events
        for e in range(n_events):
            width = min(rng.uniform(16.0, 40.0), slot)
            start = e * slot + rng.uniform(0.0, slot - width)
            height = rng.uniform(0.5, 1.0)
            phase = np.clip((t - start) / width, 0.0, 1.0)
            weights[:, k] += height * 0.5 * (1.0 - np.cos(2.0 * np.pi * phase))
    return weights


# =========================================================================== public API


def make_sample_arrays(n_vertices: int = 20000, n_examples: int = 8, n_frames: int = 120,
                       seed: int = 0, n_markers: int | None = None) -> SampleRig:
    """Build the synthetic face rig and a take with ground truth, in memory.

    The face, its markers, anchors and example poses depend only on ``n_vertices`` (the
    resolution) and ``n_examples``; ``seed`` draws the take's expression weights.

    Parameters
    ----------
    n_vertices : int
        Approximate vertex count (the grid's is within a few % of it), >= 2000.
    n_examples : int
        Number of example poses, 1..12 (6-12 make sense; the first of ``EXPRESSIONS`` are used).
    n_frames : int
        Frames of the take (30 fps), >= 1.
    seed : int
        Seed of the take's weights.
    n_markers : int, optional
        Markers that drive the shell, handles plus the 6 stable ones (default 96); e.g. 89 for
        the paper's configuration. The handles are spread by the same Voronoi relaxation.

    Returns
    -------
    SampleRig
        Arrays in cm; see its attributes.

    Raises
    ------
    InputError
        For counts out of range.

    Example
    -------
    >>> rig = make_sample_arrays(3000, n_examples=6, n_frames=10)
    >>> rig.example_positions.shape[0], len(rig.marker_names)
    (6, 96)
    """
    if n_vertices < MIN_VERTICES:
        raise InputError(f"n_vertices {n_vertices} is too small for the sample rig",
                         hint=f"use at least {MIN_VERTICES} (20000 is the default)")
    if not 1 <= n_examples <= len(_PRIORITY):
        raise InputError(f"n_examples {n_examples} is out of range", hint=f"use 1..{len(_PRIORITY)}")
    if n_frames < 1:
        raise InputError(f"n_frames {n_frames} must be at least 1")

    rest, faces, uv, xy, border, t_u, t_v, u_edges, v_edges = _face_mesh(int(n_vertices))
    normal = np.cross(t_u, t_v)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    t_v = np.cross(normal, t_u)           # orthonormal frame: the grid lines are not quite orthogonal
    gate = _smootherstep((border - _GATE_START) / _GATE_WIDTH)
    corners = faces.reshape(-1)
    mesh = Mesh(vertices=rest, polygon_offsets=np.arange(0, corners.size + 1, 3, dtype=np.int64),
                polygon_vertices=corners, uvs=uv, polygon_uvs=corners.copy())

    n_stable = len(_STABLE_MARKERS)
    # n_markers counts every marker that drives the shell: the handles plus the 6 stable ones
    n_handles = _N_HANDLES if n_markers is None else int(n_markers) - n_stable
    if n_handles < len(_LIP_MARKERS) + 4:
        raise InputError(f"n_markers {n_markers} is too small for the sample rig",
                         hint=f"use at least {len(_LIP_MARKERS) + 4 + n_stable}")
    marker_uv = _marker_uvs(n_handles)
    marker_points = _surface(marker_uv[:, 0], marker_uv[:, 1])[0]
    marker_vertices = cKDTree(rest).query(marker_points)[1].astype(np.int64)
    marker_names = [f"M{i + 1:03d}" for i in range(n_handles)] + [f"S{i + 1:02d}" for i in range(n_stable)]
    marker_roles = ["handle"] * n_handles + ["stable"] * n_stable
    anchors = np.flatnonzero(border < _ANCHOR_BAND).astype(np.int64)

    names = sorted(_PRIORITY[:n_examples])
    fields = np.stack([_expression_field(name, xy, gate, (t_u, t_v, normal)) for name in names])
    rule = _WrinkleRule(rest, u_edges, v_edges, xy, gate)
    n_v = rest.shape[0]
    example_positions = np.empty((n_examples, n_v, 3))
    example_wrinkles = np.empty((n_examples, n_v))
    example_compression = np.empty((n_examples, n_v, 2))
    for k in range(n_examples):
        example_positions[k], example_wrinkles[k], example_compression[k] = rule(fields[k])

    # the truth uses the weights as stored (float32), so it can be recomputed from the npz
    weights = _take_weights(n_frames, n_examples, np.random.default_rng(seed)).astype(np.float32)
    take = np.empty((n_frames, n_v, 3), dtype=np.float32)
    smooth = np.empty((n_frames, n_v, 3), dtype=np.float32)
    flat_fields = fields.reshape(n_examples, -1)
    for f in range(n_frames):
        field_f = (weights[f].astype(np.float64) @ flat_fields).reshape(n_v, 3)
        take[f] = rule(field_f)[0]
        smooth[f] = rest + field_f

    return SampleRig(mesh=mesh, marker_names=marker_names, marker_vertices=marker_vertices,
                     marker_roles=marker_roles, anchors=anchors, example_names=names,
                     example_positions=example_positions, example_wrinkles=example_wrinkles,
                     example_compression=example_compression, take_positions=take,
                     take_weights=weights, fps=FPS, face_coords=xy, take_smooth=smooth)


_CONFIG = """\
# facepipe sample rig: a synthetic face written by `facepipe sample` (facepipe.sample_rig).
# The take to replay is take.csv; its ground truth is take_truth.npz:
#   facepipe fit sample.toml && facepipe bake sample.toml
#   facepipe replay take.csv -m model.npz -o out && facepipe eval out --truth take_truth.npz
# Its wrinkles are a nonlinear function of the smooth motion, so unlike the ICT kit the truth is
# not a linear mix of the examples.

[rig]
mesh = "neutral.obj"
markers = "markers.csv"
anchors = "anchors.txt"
units = "cm"

[examples]
meshes = ["expressions/*.obj"]
sequence = ""

[shell]
k_stretch = 0.0
k_bend = 1.0

[features]
graph = "auto"

[psd]
method = "wpsd"
fit = "interpolate"
max_poses = {max_poses}
tolerance = 0.0
max_edges_per_vertex = 16
min_edge_weight = 0.025
"""


def _write_text(path: Path, text: str) -> None:
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(text)


def _take_csv(rig: SampleRig) -> str:
    """The take's marker columns as in the ICT kit: 6-decimal time, 5-decimal cm coordinates."""
    header = ["frame", "time"] + [f"{n}_{c}" for n in rig.marker_names for c in "xyz"]
    values = rig.take_positions[:, rig.marker_vertices].astype(np.float64).reshape(len(rig.take_positions), -1)
    fmt = "%d,%.6f" + ",%.5f" * values.shape[1]
    rows = [fmt % (f, t, *row) for f, (t, row) in enumerate(zip(rig.take_times, values.tolist()))]
    return ",".join(header) + "\n" + "".join(r + "\n" for r in rows)


def write_sample_rig(out_dir, n_vertices: int = 20000, n_examples: int = 8, n_frames: int = 120,
                     seed: int = 0, n_markers: int | None = None) -> dict:
    """Write the synthetic rig, a take and its ground truth, and a config, into ``out_dir``.

    Files (every one written atomically; ``sample.toml`` last): ``neutral.obj`` (with
    per-corner ``vt``), ``markers.csv`` (``name,vertex,role``, 0-based), ``anchors.txt``,
    ``expressions/NAME.obj``, ``take.csv`` (mocap CSV), ``take_truth.npz`` (the keys of the ICT
    kit's truth files), ``take_smooth.mdd`` (the truth without its wrinkles: the smooth motion as a
    rig's point cache) and ``sample.toml`` (paths relative to it).

    Parameters
    ----------
    out_dir : str or path
        Folder to write into (created if missing). Expression OBJs of an earlier sample run that
        this one does not write are removed, because the config globs ``expressions/*.obj``.
    n_vertices, n_examples, n_frames, seed, n_markers
        As for :func:`make_sample_arrays`.

    Returns
    -------
    dict
        Paths (``config``, ``mesh``, ``markers``, ``anchors``, ``expressions`` (list), ``take``,
        ``truth``) and counts (``vertices``, ``triangles``, ``markers``, ``handles``, ``stable``,
        ``anchors``, ``examples``, ``frames``).

    Raises
    ------
    InputError
        For counts out of range, or an ``expressions`` folder holding other OBJ files.

    Example
    -------
    >>> info = write_sample_rig("sample", n_vertices=3000)   # doctest: +SKIP
    >>> info["config"]                                        # doctest: +SKIP
    'sample/sample.toml'
    """
    out = Path(out_dir)
    expr_dir = out / "expressions"
    if expr_dir.is_dir():
        strangers = [p.name for p in sorted(expr_dir.glob("*.obj")) if p.stem not in _PRIORITY]
        if strangers:
            raise InputError(f"{expr_dir} holds OBJ files that the sample config's glob would load as "
                             f"examples: {', '.join(strangers[:5])}", path=out,
                             hint="write the sample rig into an empty folder")
    rig = make_sample_arrays(n_vertices, n_examples, n_frames, seed, n_markers)
    mesh = rig.mesh

    paths = {"config": out / "sample.toml", "mesh": out / "neutral.obj", "markers": out / "markers.csv",
             "anchors": out / "anchors.txt", "take": out / "take.csv", "truth": out / "take_truth.npz",
             "smooth_cache": out / "take_smooth.mdd"}
    save_obj(paths["mesh"], mesh)
    _write_text(paths["markers"], "name,vertex,role\n" + "".join(
        f"{n},{v},{r}\n" for n, v, r in zip(rig.marker_names, rig.marker_vertices.tolist(), rig.marker_roles)))
    _write_text(paths["anchors"], "".join(f"{a}\n" for a in rig.anchors.tolist()))

    bare = Mesh(mesh.vertices, mesh.polygon_offsets, mesh.polygon_vertices)
    faces_block = format_obj_faces(bare)        # formatted once for every expression
    expressions = []
    for name, positions in zip(rig.example_names, rig.example_positions):
        path = expr_dir / f"{name}.obj"
        with atomic_open(path, "wb") as fh:
            fh.write(obj_bytes(bare, positions, faces_block=faces_block, uv_block=b""))
        expressions.append(path)
    for stale in expr_dir.glob("*.obj"):
        if stale.stem not in rig.example_names:
            stale.unlink()

    _write_text(paths["take"], _take_csv(rig))
    n_frames = rig.take_positions.shape[0]
    with atomic_path(paths["truth"]) as tmp:
        np.savez(tmp, positions=rig.take_positions,
                 frame=np.arange(n_frames, dtype=np.int32),
                 time=rig.take_times,
                 rotation=np.broadcast_to(np.eye(3, dtype=np.float32), (n_frames, 3, 3)),
                 translation=np.zeros((n_frames, 3), dtype=np.float32),
                 weights=rig.take_weights,
                 expressions=np.array(rig.example_names))
    # the take's motion without the wrinkles, as a rig would export it (replay it with the model to
    # add the details: facepipe replay take_smooth.mdd -m model.npz -o out)
    write_mdd(paths["smooth_cache"], rig.take_smooth, rig.take_times)
    _write_text(paths["config"], _CONFIG.format(max_poses=len(rig.example_names)))

    info: dict = {k: str(v) for k, v in paths.items()}
    info["expressions"] = [str(p) for p in expressions]
    n_stable = rig.marker_roles.count("stable")
    info.update(vertices=mesh.n_vertices, triangles=mesh.n_polygons, markers=len(rig.marker_names),
                handles=len(rig.marker_names) - n_stable, stable=n_stable, anchors=int(rig.anchors.size),
                examples=len(rig.example_names), frames=n_frames)
    return info
