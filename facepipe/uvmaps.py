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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.ndimage
import scipy.sparse as sp

from .errors import InputError
from .render import triangle_pixels

# a texel centre on a shared edge belongs to both triangles; the tolerance (in barycentric
# units) closes hairline cracks from rounding without growing triangles visibly
_INSIDE_TOLERANCE = 1e-9


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
    """

    width: int
    height: int
    matrix: sp.csr_matrix
    texels: np.ndarray
    covered: np.ndarray
    filled: np.ndarray
    triangle: np.ndarray

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
        out[self.texels] = self.matrix @ flat
        return out.reshape((self.height, self.width) + values.shape[1:])


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
    centroid = corner_uv.mean(axis=1)
    bad = ~np.isfinite(centroid).all(axis=1)
    cell = np.floor(np.where(bad[:, None], 0.0, centroid)).astype(np.int64)
    bad |= (cell[:, 0] < 0) | (cell[:, 0] > 9) | (cell[:, 1] < 0)
    if bad.any():
        t = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"{int(bad.sum())} triangles have UVs outside the UDIM range (u in [0, 10), v >= 0), "
            f"first triangle {t} with UV centroid {centroid[t].tolist()}",
            path=path, hint="lay the UVs out in [0, 1]² or in UDIM tiles")
    return 1001 + cell[:, 0] + 10 * cell[:, 1]


def uv_raster(corner_uv: np.ndarray, corner_slots: np.ndarray, n_slots: int, width: int, height: int,
              padding: int = 8, chunk_texels: int = 1 << 22) -> UVRaster:
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
        dist, (ni, nj) = scipy.ndimage.distance_transform_edt(~covered, return_indices=True)
        pad = (~covered) & (dist <= padding)
        pi, pj = np.nonzero(pad)
        src_tri = owner[ni[pi, pj] * width + nj[pi, pj]]
        q = np.stack([pj, pi], axis=-1).astype(np.float64)
        pad_bary = _closest_point_barycentric(p[src_tri], q)
        src = p[src_tri]
        e1s, e2s = src[:, 1] - src[:, 0], src[:, 2] - src[:, 0]
        linear = _barycentric(src, q, e1s, e2s, e1s[:, 0] * e2s[:, 1] - e1s[:, 1] * e2s[:, 0])
        near = (dist[pi, pj] <= 1.5) & (linear >= -1.0).all(axis=1)
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
    return UVRaster(width, height, matrix, texel, covered, filled.reshape(height, width),
                    owner.reshape(height, width))


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


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a map at UVs (one tile), clamped at the image border.

    Parameters
    ----------
    image : (H, W) or (H, W, C) map.
    uv : (n, 2) texture coordinates in [0, 1]².

    Returns
    -------
    (n,) or (n, C) float64 values.
    """
    H, W = image.shape[:2]
    x, y = uv_to_texel(uv, W, H)
    x = np.clip(x, 0.0, W - 1.0)
    y = np.clip(y, 0.0, H - 1.0)
    j0 = np.minimum(np.floor(x).astype(np.int64), W - 2) if W > 1 else np.zeros(x.shape, np.int64)
    i0 = np.minimum(np.floor(y).astype(np.int64), H - 2) if H > 1 else np.zeros(y.shape, np.int64)
    fx = (x - j0) if W > 1 else np.zeros_like(x)
    fy = (y - i0) if H > 1 else np.zeros_like(y)
    j1 = np.minimum(j0 + 1, W - 1)
    i1 = np.minimum(i0 + 1, H - 1)
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    top = img[i0, j0] * (1 - fx) + img[i0, j1] * fx
    bottom = img[i1, j0] * (1 - fx) + img[i1, j1] * fx
    return top * (1 - fy) + bottom * fy


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


def mesh_raster(mesh, width: int, height: int, padding: int = 8, slots: str = "vertex") -> TiledRaster:
    """Rasterisation of a mesh's per-vertex (or per-UV) values into its UV layout, tile by tile.

    Parameters
    ----------
    mesh : facepipe.mesh.Mesh with UVs; the per-corner UV triangulation (``mesh.face_uvs``)
        places the values, which the vertex triangles (``mesh.faces``) carry.
    width, height : texels per tile.
    padding : texels of edge padding.
    slots : "vertex" (values per vertex, V) or "uv" (values per UV index, U: e.g. tangent
        frames, which differ on the two sides of a seam).

    Returns
    -------
    TiledRaster whose slots are the mesh's vertices or UV indices.

    Raises
    ------
    InputError
        The mesh has no UVs, or UVs outside the UDIM range.
    """
    if mesh.uvs is None or mesh.polygon_uvs is None:
        raise InputError("the rest mesh has no texture coordinates (UVs), so it has no map layout",
                         path=mesh.path or None,
                         hint="give the rig an OBJ with 'vt' lines and per-corner 'f v/vt' indices, then bake "
                              "again; or export geometry (--format obj|usd|mdd|pc2)")
    if width < 1 or height < 1:
        raise InputError(f"map resolution {width}x{height} is not positive")
    corner_uv = mesh.uvs[mesh.face_uvs]
    tiles = udim_tiles(corner_uv, mesh.path or None)
    out = {}
    for tile in np.unique(tiles):
        sel = tiles == tile
        offset = np.array([(tile - 1001) % 10, (tile - 1001) // 10], dtype=np.float64)
        corner_slots, n_slots = (mesh.faces, mesh.n_vertices) if slots == "vertex" else (mesh.face_uvs, len(mesh.uvs))
        out[int(tile)] = uv_raster(corner_uv[sel] - offset, corner_slots[sel], n_slots, width, height, padding)
    return TiledRaster(out)


def corner_uv_samples(mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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
