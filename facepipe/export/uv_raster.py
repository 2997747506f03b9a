"""Rasterising per-vertex values into a mesh's UV layout: the texture side of map exports.

A map is a linear function of the values it shows: every filled texel is a fixed
barycentric combination of the values at the corners of one triangle. That combination
depends only on the UV layout and the resolution, so it is computed once as a sparse
matrix (:class:`UVRaster`) and each frame's map is one sparse product. Linearity is also
what makes layered wrinkle maps exact: the map of ``c + Σ_i φ_i w_i`` is
``map(c) + Σ_i φ_i map(w_i)``.

Conventions
-----------
* Texel ``(row i, column j)`` of a ``H × W`` image samples ``u = (j + ½) / W`` and
  ``v = 1 − (i + ½) / H``: row 0 is the top of the texture (``v = 1``), as every painting
  and rendering tool displays it and as OpenEXR stores scanlines (increasing y).
* UVs outside ``[0, 1]²`` are UDIM tiles: tile ``1001 + ⌊u⌋ + 10 ⌊v⌋`` (``0 ≤ ⌊u⌋ < 10``,
  ``⌊v⌋ ≥ 0``). A triangle belongs to the tile of its UV centroid.
* Seams and islands come free: values are gathered per triangle corner, so a vertex on a
  seam gives its value to each island it appears in.
* Edge padding: texels outside every triangle but within ``padding`` texels of a covered one
  take their values from the triangle that covers their nearest covered texel: the first ring
  (within 1.5 texels, what bilinear filtering at an island's border reaches) continues that
  triangle's linear interpolation, so a sample on the border is as exact as one inside; the
  rings beyond take the value at the triangle's closest point (bounded by its corner values),
  so mip-maps do not blend in the empty background. A sliver whose continuation would reach
  beyond one triangle's width (a barycentric coordinate below −1) uses the closest point too.
* Vertex samples: a bilinear lookup at a vertex's UV (what a renderer does, and what the maps
  are checked by) blends the 2 × 2 texels around it. Where UV triangles span a few texels
  (eyelid and lip rims) those texels lie in different triangles of the vertex's fan, or across
  an island border, and the piecewise-linear field bends at the texel scale, so plain
  rasterisation misses the vertex value by a sizeable fraction of the field's range. The
  raster therefore also fits its texels to the vertices (:class:`LookupFit`): the texels of
  the 2 × 2 footprints of every vertex lookup (a distinct (slot, UV) pair: each UV corner of a
  seam vertex is its own sample) take the smallest change from their rasterised values that
  makes the bilinear lookups return the vertex values — a damped least-squares problem whose
  matrix depends only on the layout and the resolution, factorised once; each map is then one
  sparse product plus one sparse solve. Samples whose footprints overlap are fitted together;
  contradictory ones (islands closer than a texel with different values) get the
  least-squares compromise, which :meth:`UVRaster.lookup_errors` measures. The fit is linear
  in the values, so layered wrinkle maps stay exact blends.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from facepipe.core.raster import edge_padding, triangle_pixels, udim_corner, udim_tile_numbers
from facepipe.errors import InputError
import scipy.sparse.linalg as spla

# a texel centre on a shared edge belongs to both triangles; the tolerance (in barycentric
# units) closes hairline cracks from rounding without growing triangles visibly
_INSIDE_TOLERANCE = 1e-9

# damping μ of the vertex-sample fit (dimensionless: both terms are squared value differences).
# An isolated sample keeps the fraction μ / (|b|² + μ) ≤ 4 μ of its misfit (|b|² ≥ ¼ for
# bilinear weights), here ≤ 0.4 %; the texels of a cluster of coupled samples move by at most
# |r| / (2 √μ) ≈ 16 |r| (r: the cluster's misfits), which bounds the overshoot where samples
# closer than a texel contradict each other
_FIT_DAMPING = 1e-3


@dataclass
class LookupFit:
    """Texel corrections that make bilinear lookups at the vertex lookups return their values.

    With A the rasterisation (texels from slot values), B the bilinear weights of the lookups
    on the texels of their footprints and E the selection of each sample's slot, the misfit of
    plain rasterisation is r = R v with R = E − B A. The correction δ of the footprint texels is

        δ = argmin |B δ − r|² + μ |δ|² = (BᵀB + μ I)⁻¹ Bᵀ r,

    the smallest change that fits the lookups (a texel outside every footprint keeps its
    rasterised value). BᵀB + μ I couples only texels within one texel of each other (≤ 9 per
    row) and depends only on the layout: it is factorised once (sparse LU).

    Attributes
    ----------
    rows : (F,) int64, the rows of :attr:`UVRaster.matrix` (filled texels) that the fit moves.
    weights : (n, F) csr_matrix, B: bilinear weights of the fitted samples on those texels.
    residual : (n, S) csr_matrix, R: sample value minus plain bilinear lookup, per slot value.
    samples : (n,) int64, the fitted lookups' indices into :attr:`UVRaster.lookup_slots`.
    damping : μ.
    """

    rows: np.ndarray
    weights: sp.csr_matrix
    residual: sp.csr_matrix
    samples: np.ndarray
    damping: float
    factor: object = None  # scipy.sparse.linalg.SuperLU of BᵀB + μ I
    _weights_t: sp.csr_matrix | None = field(default=None, repr=False)

    def correction(self, flat: np.ndarray) -> np.ndarray:
        """δ (F, C) for slot values ``flat`` (S, C) float64, one channel at a time (so a channel's
        correction does not depend on which channels go with it)."""
        if self._weights_t is None:
            self._weights_t = self.weights.T.tocsr()
        out = np.empty((self.rows.shape[0], flat.shape[1]))
        for c in range(flat.shape[1]):
            out[:, c] = self.factor.solve(self._weights_t @ (self.residual @ flat[:, c]))
        return out


@dataclass
class UVRaster:
    """A UV layout rasterised at one resolution: values at triangle corners → texels.

    Attributes
    ----------
    width, height : int, image size in texels.
    matrix : (N, S) scipy.sparse.csr_matrix, float64
        Row k gives texel ``texels[k]`` as a combination of the S value slots (vertices or
        UV indices: whatever ``corner_slots`` indexed when it was built).
    texels : (N,) int64 flat indices (``row * width + column``) of the filled texels.
    covered : (height, width) bool, texels whose centre lies in a triangle.
    filled : (height, width) bool, covered texels plus the edge padding.
    triangle : (height, width) int64, the triangle whose values a filled texel shows
        (−1 where empty): for diagnostics and overlap checks.
    lookup_slots, lookup_uv : (n,) int64 and (n, 2) float64, the vertex lookups: every
        distinct (slot, UV) pair of the triangles' corners within the tile.
    fit : :class:`LookupFit` that corrects the texels around the lookups (None: plain
        rasterisation, ``matrix`` alone).
    """

    width: int
    height: int
    matrix: sp.csr_matrix
    texels: np.ndarray
    covered: np.ndarray
    filled: np.ndarray
    triangle: np.ndarray
    lookup_slots: np.ndarray | None = None
    lookup_uv: np.ndarray | None = None
    fit: LookupFit | None = None

    @property
    def n_slots(self) -> int:
        return int(self.matrix.shape[1])

    def __call__(self, values: np.ndarray, fill: float = 0.0, dtype=np.float32) -> np.ndarray:
        """The map of slot values.

        Parameters
        ----------
        values : (S,) or (S, C) values per slot (e.g. per vertex), any units.
        fill : value of empty texels.
        dtype : of the result.

        Returns
        -------
        (height, width) or (height, width, C) array of ``dtype``.

        Example
        -------
        >>> raster = uv_raster(uv, faces, n_vertices, 256, 256)   # doctest: +SKIP
        >>> image = raster(details[:, 2])                         # (256, 256) normal component
        """
        values = np.asarray(values)
        if values.shape[0] != self.n_slots:
            raise ValueError(f"{values.shape[0]} values for a raster of {self.n_slots} slots")
        flat = values.reshape(values.shape[0], -1).astype(np.float64, copy=False)
        out = np.full((self.height * self.width, flat.shape[1]), fill, dtype=dtype)
        mapped = self.matrix @ flat
        if self.fit is not None and self.fit.rows.shape[0]:
            mapped[self.fit.rows] += self.fit.correction(flat)
        out[self.texels] = mapped
        return out.reshape((self.height, self.width) + values.shape[1:])

    def lookup_errors(self, values: np.ndarray, image: np.ndarray, pixel_type=None) -> np.ndarray:
        """|bilinear lookup of ``image`` at the vertex lookups − their values|: (n,) or (n, C).

        ``values`` (S[, C]) are what ``image`` (this raster's map of them) shows; a sample outside
        the tile's filled texels compares with the fill value. ``pixel_type`` (e.g. np.float16)
        rounds the texels looked up as a file of that type stores them.
        """
        want = np.asarray(values, dtype=np.float64)[self.lookup_slots]
        got = bilinear_lookup(image, self.lookup_uv, pixel_type).reshape(want.shape)
        return np.abs(got - want)


def uv_to_texel(uv: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous texel coordinates of UVs (within one tile): texel centres are integers.

    Parameters
    ----------
    uv : (..., 2) texture coordinates in [0, 1]².

    Returns
    -------
    x, y : (...) column and row coordinates; texel (i, j) has its centre at x = j, y = i.
    """
    uv = np.asarray(uv, dtype=np.float64)
    return uv[..., 0] * width - 0.5, (1.0 - uv[..., 1]) * height - 0.5


def udim_tiles(corner_uv: np.ndarray, path=None) -> np.ndarray:
    """UDIM tile of every triangle, from its UV centroid.

    Parameters
    ----------
    corner_uv : (T, 3, 2) UVs of the triangles' corners.
    path : the mesh file, for the error message.

    Returns
    -------
    (T,) int64 tile numbers (1001 for [0, 1]²).

    Raises
    ------
    InputError
        A triangle with a non-finite UV or outside the UDIM range (u in [0, 10), v ≥ 0).
    """
    tiles, valid = udim_tile_numbers(corner_uv)
    if not valid.all():
        t = int(np.flatnonzero(~valid)[0])
        raise InputError(
            f"{int((~valid).sum())} triangles have UVs outside the UDIM range (u in [0, 10), v >= 0), "
            f"first triangle {t} with UV centroid {corner_uv[t].mean(axis=0).tolist()}",
            path=path, hint="lay the UVs out in [0, 1]² or in UDIM tiles")
    return tiles


def uv_raster(corner_uv: np.ndarray, corner_slots: np.ndarray, n_slots: int, width: int, height: int,
              padding: int = 8, chunk_texels: int = 1 << 22, fit: bool = True) -> UVRaster:
    """Rasterise triangles given in UV space: the sparse map from slot values to texels.

    Vectorised over triangles: each triangle's bounding box of texel centres is enumerated
    in one flat array (chunks of about ``chunk_texels`` candidates), barycentric
    coordinates are computed for all of them at once and the texels inside are kept. A
    texel covered by several triangles (a shared edge, or overlapping islands) shows the last.

    Parameters
    ----------
    corner_uv : (T, 3, 2) float, UVs of the triangles' corners within this tile ([0, 1]²;
        parts outside are clipped).
    corner_slots : (T, 3) int, the value slot of every corner (``mesh.faces`` for per-vertex
        values, ``mesh.face_uvs`` for per-UV values).
    n_slots : number of value slots (columns of the matrix).
    width, height : image size in texels.
    padding : texels of edge padding around every island (0 for none).
    fit : fit the texels around the vertex lookups so that bilinear lookups there return the
        vertex values (:class:`LookupFit`); False for plain rasterisation. A sample whose
        footprint reaches an empty texel (an island border without padding), or that lies
        beyond the outermost texel centres (within half a texel of the tile's edge, where a
        lookup depends on the wrap mode), is not fitted.

    Returns
    -------
    UVRaster

    Example
    -------
    >>> mesh = load_mesh("neutral.obj")                                   # doctest: +SKIP
    >>> raster = uv_raster(mesh.uvs[mesh.face_uvs], mesh.faces, mesh.n_vertices, 2048, 2048)
    """
    corner_uv = np.asarray(corner_uv, dtype=np.float64)
    corner_slots = np.asarray(corner_slots, dtype=np.int64)
    x, y = uv_to_texel(corner_uv, width, height)  # (T, 3) each
    p = np.stack([x, y], axis=-1)  # (T, 3, 2)
    e1 = p[:, 1] - p[:, 0]
    e2 = p[:, 2] - p[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = np.abs(det) > 1e-12 * np.maximum(1.0, np.abs(p).max(axis=(1, 2))) ** 2  # zero-area UV triangles show nothing
    x0 = np.clip(np.ceil(x.min(axis=1) - 1e-7), 0, width).astype(np.int64)
    x1 = np.clip(np.floor(x.max(axis=1) + 1e-7), -1, width - 1).astype(np.int64)
    y0 = np.clip(np.ceil(y.min(axis=1) - 1e-7), 0, height).astype(np.int64)
    y1 = np.clip(np.floor(y.max(axis=1) + 1e-7), -1, height - 1).astype(np.int64)

    hit_texel, hit_tri, hit_bary = [], [], []
    for t, row, col, b0, b1, b2 in triangle_pixels(p, ok, x0, x1, y0, y1, chunk_texels, _INSIDE_TOLERANCE):
        hit_texel.append(row * width + col)
        hit_tri.append(t)
        hit_bary.append(np.stack([b0, b1, b2], axis=1))
    texel = np.concatenate(hit_texel) if hit_texel else np.zeros(0, np.int64)
    tri = np.concatenate(hit_tri) if hit_tri else np.zeros(0, np.int64)
    bary = np.concatenate(hit_bary) if hit_bary else np.zeros((0, 3))
    # one triangle per texel (a shared edge or overlapping islands give several): whichever
    # scattered last; selecting by the winner keeps the choice consistent without a sort
    winner = np.full(height * width, -1, dtype=np.int64)
    winner[texel] = np.arange(texel.shape[0])
    keep = winner[texel] == np.arange(texel.shape[0])
    texel, tri, bary = texel[keep], tri[keep], bary[keep]

    covered = np.zeros(height * width, dtype=bool)
    covered[texel] = True
    covered = covered.reshape(height, width)
    owner = np.full(height * width, -1, dtype=np.int64)
    owner[texel] = tri

    if padding > 0 and texel.shape[0]:
        padded, nearest, dist = edge_padding(covered, padding)
        pi, pj = np.divmod(padded, width)
        src_tri = owner[nearest]
        q = np.stack([pj, pi], axis=-1).astype(np.float64)
        pad_bary = _closest_point_barycentric(p[src_tri], q)
        src = p[src_tri]
        e1s, e2s = src[:, 1] - src[:, 0], src[:, 2] - src[:, 0]
        linear = _barycentric(src, q, e1s, e2s, e1s[:, 0] * e2s[:, 1] - e1s[:, 1] * e2s[:, 0])
        near = (dist <= 1.5) & (linear >= -1.0).all(axis=1)
        pad_bary[near] = linear[near]
        texel = np.concatenate([texel, pi * width + pj])
        tri = np.concatenate([tri, src_tri])
        bary = np.concatenate([bary, pad_bary])
        owner[pi * width + pj] = src_tri

    n = texel.shape[0]
    # exactly three entries per row: build the CSR arrays directly (no COO sort)
    matrix = sp.csr_matrix((bary.ravel(), corner_slots[tri].ravel(), np.arange(0, 3 * n + 1, 3)), shape=(n, n_slots))
    filled = np.zeros(height * width, dtype=bool)
    filled[texel] = True
    lookup_slots, lookup_uv = _vertex_lookups(corner_uv, corner_slots)
    raster = UVRaster(width, height, matrix, texel, covered, filled.reshape(height, width),
                      owner.reshape(height, width), lookup_slots, lookup_uv)
    if fit:
        raster.fit = _fit_lookups(raster)
    return raster


def _vertex_lookups(corner_uv: np.ndarray, corner_slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct (slot, UV) pairs of the corners with a finite UV in the tile ([0, 1]²)."""
    uv = corner_uv.reshape(-1, 2)
    slot = corner_slots.reshape(-1)
    inside = np.isfinite(uv).all(axis=1) & (uv >= 0.0).all(axis=1) & (uv <= 1.0).all(axis=1)
    if not inside.any():
        return np.zeros(0, np.int64), np.zeros((0, 2))
    keys = np.unique(np.c_[slot[inside].astype(np.float64), uv[inside]], axis=0)
    return keys[:, 0].astype(np.int64), keys[:, 1:]


def _fit_lookups(raster: UVRaster, damping: float = _FIT_DAMPING) -> LookupFit:
    """The :class:`LookupFit` of a plain raster (see there for the least-squares problem)."""

    W, H = raster.width, raster.height
    index, weight = bilinear_footprint(raster.lookup_uv, W, H)  # (n, 4) each
    row_of = np.full(H * W, -1, dtype=np.int64)
    row_of[raster.texels] = np.arange(raster.texels.shape[0])
    rows = row_of[index]
    used = weight > 0.0
    ok = (~used | (rows >= 0)).all(axis=1)  # footprints within the filled texels
    # beyond the outermost texel centres a lookup depends on the renderer's wrap mode (clamp,
    # periodic, the next UDIM tile): such samples are not fitted
    x, y = uv_to_texel(raster.lookup_uv, W, H)
    ok &= (x >= 0.0) & (x <= W - 1.0) & (y >= 0.0) & (y <= H - 1.0)
    samples = np.flatnonzero(ok)
    rows, weight, used = rows[ok], weight[ok], used[ok]
    n = samples.shape[0]
    S = raster.n_slots
    unknown, col = np.unique(rows[used], return_inverse=True)
    B = sp.csr_matrix((weight[used], col, np.r_[0, np.cumsum(used.sum(axis=1))]), shape=(n, unknown.shape[0]))
    B.sum_duplicates()  # clamped footprints at the image border repeat a texel
    E = sp.csr_matrix((np.ones(n), raster.lookup_slots[samples], np.arange(n + 1)), shape=(n, S))
    R = (E - B @ raster.matrix[unknown]).tocsr()
    # plain rasterisation reproduces a sample exactly where its footprint lies in one
    # triangle's plane: rounding there leaves entries at the 1e-16 level
    R.data[np.abs(R.data) < 1e-12] = 0.0
    R.eliminate_zeros()
    normal = (B.T @ B + damping * sp.identity(unknown.shape[0], format="csr")).tocsc()
    factor = spla.splu(normal, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True}) if unknown.shape[0] else None
    return LookupFit(unknown, B, R, samples, damping, factor)


def _barycentric(p: np.ndarray, q: np.ndarray, e1: np.ndarray, e2: np.ndarray, det: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (n, 3) of points q (n, 2) in triangles p (n, 3, 2)."""
    d = q - p[:, 0]
    b1 = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / det
    b2 = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / det
    return np.stack([1.0 - b1 - b2, b1, b2], axis=-1)


def _closest_point_barycentric(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (n, 3) of the point of triangle p (n, 3, 2) closest to q (n, 2).

    Inside: the point itself. Outside: the closest point over the three edges (segments).
    """
    e1 = p[:, 1] - p[:, 0]
    e2 = p[:, 2] - p[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    bary = _barycentric(p, q, e1, e2, det)
    inside = (bary >= 0).all(axis=1)
    best = np.full(q.shape[0], np.inf)
    out = bary.copy()
    for i, j in ((0, 1), (1, 2), (2, 0)):
        a, b = p[:, i], p[:, j]
        ab = b - a
        s = np.clip(np.einsum("nk,nk->n", q - a, ab) / np.maximum(np.einsum("nk,nk->n", ab, ab), 1e-300), 0.0, 1.0)
        c = a + s[:, None] * ab
        d2 = np.einsum("nk,nk->n", q - c, q - c)
        better = (d2 < best) & ~inside
        best = np.where(better, d2, best)
        cand = np.zeros_like(bary)
        cand[:, i] = 1.0 - s
        cand[:, j] = s
        out = np.where(better[:, None], cand, out)
    return out


def bilinear_lookup(image: np.ndarray, uv: np.ndarray, pixel_type=None) -> np.ndarray:
    """Bilinear lookup of a map at UVs (one tile), clamped at the image border.

    Parameters
    ----------
    image : (H, W) or (H, W, C) map.
    uv : (n, 2) texture coordinates in [0, 1]².
    pixel_type : round the texels read to this type first (e.g. np.float16, as a half file holds them).

    Returns
    -------
    (n,) or (n, C) float64 values.
    """
    image = np.asarray(image)
    H, W = image.shape[:2]
    index, weight = bilinear_footprint(uv, W, H)
    texels = image.reshape((H * W,) + image.shape[2:])[index]  # (n, 4[, C]): only what the lookups read
    if pixel_type is not None:
        texels = texels.astype(pixel_type)
    if texels.ndim == 3:
        weight = weight[..., None]
    return (texels.astype(np.float64) * weight).sum(axis=1)


def bilinear_footprint(uv: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The texels and weights of bilinear lookups at UVs (one tile), clamped at the image border.

    Texel centres sit at ``((j + ½) / W, 1 − (i + ½) / H)`` (:func:`uv_to_texel`), as OpenEXR
    stores scanlines top down and renderers filter (GL_LINEAR, OIIO's bilinear with clamp).

    Returns
    -------
    index : (n, 4) int64 flat texel indices (``row * width + column``) of the 2 × 2 texels.
    weight : (n, 4) float64 bilinear weights (summing to 1).
    """
    x, y = uv_to_texel(uv, width, height)
    x = np.clip(x, 0.0, width - 1.0)
    y = np.clip(y, 0.0, height - 1.0)
    j0 = np.minimum(np.floor(x).astype(np.int64), max(width - 2, 0))
    i0 = np.minimum(np.floor(y).astype(np.int64), max(height - 2, 0))
    fx, fy = x - j0, y - i0
    j1 = np.minimum(j0 + 1, width - 1)
    i1 = np.minimum(i0 + 1, height - 1)
    index = np.stack([i0 * width + j0, i0 * width + j1, i1 * width + j0, i1 * width + j1], axis=-1)
    weight = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=-1)
    return index, weight


@dataclass
class TiledRaster:
    """A UV layout over one or more UDIM tiles: one :class:`UVRaster` per tile.

    Attributes
    ----------
    tiles : dict tile number → UVRaster (ascending tile numbers).
    """

    tiles: dict

    @property
    def udim(self) -> bool:
        """True when the layout uses any tile but 1001 (file names then carry the tile)."""
        return list(self.tiles) != [1001]

    def __call__(self, values: np.ndarray, dtype=np.float32) -> dict:
        """Maps of slot values per tile: {tile: (H, W[, C]) array}."""
        return {tile: raster(values, dtype=dtype) for tile, raster in self.tiles.items()}


def mesh_raster(mesh, width: int, height: int, padding: int = 8, slots: str = "vertex",
                fit: bool = True) -> TiledRaster:
    """Rasterisation of a mesh's per-vertex (or per-UV) values into its UV layout, tile by tile.

    Parameters
    ----------
    mesh : facepipe.core.mesh.Mesh with UVs; the per-corner UV triangulation (``mesh.face_uvs``)
        places the values, which the vertex triangles (``mesh.faces``) carry.
    width, height : texels per tile.
    padding : texels of edge padding.
    slots : "vertex" (values per vertex, V) or "uv" (values per UV index, U: e.g. tangent
        frames, which differ on the two sides of a seam).
    fit : fit the texels around the vertices' UVs so that bilinear lookups there return the
        vertex values (see :func:`uv_raster`).

    Returns
    -------
    TiledRaster whose slots are the mesh's vertices or UV indices.

    Raises
    ------
    InputError
        The mesh has no UVs, or UVs outside the UDIM range.
    """
    require_uvs(mesh)
    if width < 1 or height < 1:
        raise InputError(f"map resolution {width}x{height} is not positive")
    corner_uv = mesh.uvs[mesh.face_uvs]
    tiles = udim_tiles(corner_uv, mesh.path or None)
    out = {}
    for tile in np.unique(tiles):
        sel = tiles == tile
        offset = np.array(udim_corner(int(tile)), dtype=np.float64)
        corner_slots, n_slots = (mesh.faces, mesh.n_vertices) if slots == "vertex" else (mesh.face_uvs, len(mesh.uvs))
        out[int(tile)] = uv_raster(corner_uv[sel] - offset, corner_slots[sel], n_slots, width, height, padding,
                                   fit=fit)
    return TiledRaster(out)


def corner_uv_lookups(mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every distinct (vertex, UV) pair of a mesh: where a vertex's value sits in the maps.

    Returns
    -------
    vertex : (n,) int64; uv : (n, 2) float64 within its tile; tile : (n,) int64 UDIM tile;
    uv_index : (n,) int64 the pair's UV index.
    """
    pairs = np.unique(np.stack([mesh.faces.ravel(), mesh.face_uvs.ravel()], axis=1), axis=0)
    uv = mesh.uvs[pairs[:, 1]]
    corner_uv = mesh.uvs[mesh.face_uvs]
    tri_tile = udim_tiles(corner_uv, mesh.path or None)
    # a UV on a tile border (u = 1.0) belongs to the tile of the triangles that use it
    uv_tile = np.zeros(len(mesh.uvs), dtype=np.int64)
    uv_tile[mesh.face_uvs.ravel()] = np.repeat(tri_tile, 3)
    tile = uv_tile[pairs[:, 1]]
    offset = np.stack([(tile - 1001) % 10, (tile - 1001) // 10], axis=1)
    return pairs[:, 0], uv - offset, tile, pairs[:, 1]


def require_uvs(mesh) -> None:
    """InputError unless the mesh has texture coordinates (the maps' layout)."""
    if mesh.uvs is None or mesh.polygon_uvs is None:
        raise InputError("the rest mesh has no texture coordinates (UVs), so it has no map layout",
                         path=mesh.path or None,
                         hint="give the rig (or, for a transferred model, the transfer target) an OBJ with 'vt' "
                              "lines and per-corner 'f v/vt' indices, then bake or transfer again; or export "
                              "geometry (--format obj|usd|mdd|pc2)")
