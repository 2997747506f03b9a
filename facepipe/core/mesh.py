"""The mesh type, triangulation and edges, and the checks that a rig's mesh can carry a solve.

The solver works on triangles, but exports must reproduce the artist's polygons and per-corner
texture coordinates in the rest mesh's vertex order, so a :class:`Mesh` keeps the polygons,
their UVs and groups, and triangulates on demand.

The ``check_*`` functions turn the ways a rig's input can be wrong into an
:class:`~facepipe.errors.InputError` that names the file and the element (vertex,
edge, polygon, marker, line) *before* a solver fails with a singular matrix or
silently produces garbage. They are vectorised: a million triangles take
about half a second.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from facepipe.core.runs import offsets_within
from facepipe.core.vectors import cross, lengths
from facepipe.errors import InputError
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


@dataclass
class Mesh:
    """A polygon mesh in the rest mesh's vertex order.

    Attributes
    ----------
    vertices : (V, 3) float64
    polygon_offsets : (N + 1,) int64
        Polygon ``k`` has corners ``polygon_vertices[polygon_offsets[k]:polygon_offsets[k+1]]``.
    polygon_vertices : (C,) int64
        Vertex index of every polygon corner.
    uvs : (U, 2) float64 or None
        Texture coordinates.
    polygon_uvs : (C,) int64 or None
        UV index of every polygon corner (same layout as ``polygon_vertices``).
    polygon_groups : (N,) int32 or None, with ``group_names``
        The OBJ group (``g``/``o``) each polygon belongs to.
    path : str
        Where the mesh was read from (for error messages).
    """

    vertices: np.ndarray
    polygon_offsets: np.ndarray
    polygon_vertices: np.ndarray
    uvs: np.ndarray | None = None
    polygon_uvs: np.ndarray | None = None
    polygon_groups: np.ndarray | None = None
    group_names: list[str] = field(default_factory=list)
    path: str = ""

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_polygons(self) -> int:
        return int(self.polygon_offsets.shape[0] - 1)

    @property
    def polygon_sizes(self) -> np.ndarray:
        return np.diff(self.polygon_offsets)

    @property
    def faces(self) -> np.ndarray:
        """(T, 3) int64 triangles: every polygon fan-triangulated from its first corner."""
        if getattr(self, "_faces", None) is None:
            self._faces, self._face_polygon = triangulate(self.polygon_offsets, self.polygon_vertices)
        return self._faces

    @property
    def face_polygon(self) -> np.ndarray:
        """(T,) int64: the polygon each triangle of :attr:`faces` came from."""
        self.faces  # noqa: B018 - fills the cache
        return self._face_polygon

    @property
    def face_uvs(self) -> np.ndarray | None:
        """(T, 3) int64 UV indices of the triangles' corners, or None without UVs."""
        if self.polygon_uvs is None:
            return None
        return triangulate(self.polygon_offsets, self.polygon_uvs)[0]

    @property
    def edges(self) -> np.ndarray:
        """(E, 2) int64 unique undirected edges of :attr:`faces`, ``edges[:, 0] < edges[:, 1]``."""
        if getattr(self, "_edges", None) is None:
            self._edges = _edges_from_keys(self.sorted_edge_keys(), self.n_vertices)
            self._edge_keys = None  # (only the edges and the mesh check read them)
        return self._edges

    def sorted_edge_keys(self) -> np.ndarray:
        """:func:`sorted_edge_keys` of :attr:`faces` (kept: :func:`check_mesh` sorts them to count
        each edge's triangles, and :attr:`edges` are their runs)."""
        if getattr(self, "_edge_keys", None) is None:
            self._edge_keys = sorted_edge_keys(self.faces, self.n_vertices)
        return self._edge_keys

    def with_vertices(self, vertices: np.ndarray) -> "Mesh":
        """The same topology and UVs with other vertex positions (V, 3)."""
        return Mesh(
            np.asarray(vertices, dtype=np.float64),
            self.polygon_offsets,
            self.polygon_vertices,
            self.uvs,
            self.polygon_uvs,
            self.polygon_groups,
            self.group_names,
            self.path,
        )


def triangulate(offsets: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate polygons.

    Parameters
    ----------
    offsets : (N + 1,) int64 polygon offsets into ``corners``.
    corners : (C,) int64 per-corner indices (vertices or UVs).

    Returns
    -------
    triangles : (T, 3) int64, T = sum(size - 2)
    polygon : (T,) int64, the polygon each triangle came from.

    Example
    -------
    >>> triangulate(np.array([0, 4]), np.array([0, 1, 2, 3]))[0].tolist()
    [[0, 1, 2], [0, 2, 3]]
    """
    offsets = np.asarray(offsets, dtype=np.int64)
    corners = np.asarray(corners, dtype=np.int64)
    sizes = np.diff(offsets)
    n_tri = np.maximum(sizes - 2, 0)
    polygon = np.repeat(np.arange(sizes.shape[0], dtype=np.int64), n_tri)
    # k-th triangle of a polygon uses corners 0, k+1, k+2
    k = offsets_within(n_tri)
    start = offsets[polygon]
    tris = np.stack([corners[start], corners[start + k + 1], corners[start + k + 2]], axis=1)
    return tris, polygon


def triangle_edges(faces: np.ndarray) -> np.ndarray:
    """(3T, 2) int64 directed edges of triangles, sorted per edge (smaller index first).

    Row ``j * T + t`` is the edge of triangle ``t`` opposite its corner ``(j + 2) % 3``.
    """
    faces = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=0)
    e.sort(axis=1)
    return e


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges of a triangle mesh.

    Parameters
    ----------
    faces : (T, 3) int64

    Returns
    -------
    (E, 2) int64 with ``edges[:, 0] < edges[:, 1]``, sorted lexicographically.

    Example
    -------
    >>> unique_edges(np.array([[0, 1, 2], [0, 2, 3]])).tolist()
    [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]]
    """
    faces = np.asarray(faces, dtype=np.int64)
    if faces.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.int64)
    n = int(faces.max()) + 1
    return _edges_from_keys(sorted_edge_keys(faces, n), n)


def sorted_edge_keys(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(3T,) int64: every triangle's edges as keys i · n_vertices + j (i < j), sorted.

    An edge appears once per triangle that uses it: the runs of equal keys are the mesh's
    edges, and their lengths the number of triangles sharing each. (One int64 key per edge,
    sorted: several times faster than unique(axis=0), and than numpy 2's hash-based np.unique
    on millions of keys.)"""
    e = triangle_edges(faces)
    return np.sort(e[:, 0] * n_vertices + e[:, 1])


def _edges_from_keys(skey: np.ndarray, n_vertices: int) -> np.ndarray:
    """The unique edges (E, 2) of :func:`sorted_edge_keys`' keys."""
    keep = np.empty(skey.shape, dtype=bool)
    keep[:1] = True
    np.not_equal(skey[1:], skey[:-1], out=keep[1:])
    key = skey[keep]
    return np.stack([key // n_vertices, key % n_vertices], axis=1)


# ----------------------------------------------------------------------------------------------
# checks: each raises InputError naming the file and the element, and says how to fix it

def _where(mesh: Mesh, path) -> str | None:
    if path is not None:
        return str(path)
    return mesh.path or None


def _first(indices: np.ndarray, limit: int = 5) -> str:
    shown = ", ".join(str(int(i)) for i in indices[:limit])
    return shown + (", ..." if len(indices) > limit else "")


def check_mesh(mesh: Mesh, *, area_tolerance: float = 1e-10, path: str | os.PathLike | None = None) -> None:
    """Check that a mesh can carry a thin-shell solve: finite, manifold, no degenerate pieces.

    Checks: NaN/inf coordinates; polygons with fewer than three corners or with corner
    indices out of range; a vertex repeated within a polygon; triangles (of the fan
    triangulation) with an area below ``area_tolerance`` times the mean squared edge length
    (their cotangent weights are infinite); edges used by more than two triangles; the same
    triangle twice; vertices used by no polygon (their rows of the shell system are empty).
    Every problem found is listed in one error.

    Parameters
    ----------
    mesh : Mesh
    area_tolerance : float
        Relative area below which a triangle counts as degenerate (dimensionless).
    path : file named in the message; defaults to ``mesh.path``.

    Raises
    ------
    InputError
        Naming the first offending vertex, edge or polygon of each kind and how many there are.

    Example
    -------
    >>> m = Mesh(np.eye(3), np.array([0, 3]), np.array([0, 1, 2]))
    >>> check_mesh(m)   # a single triangle is fine
    """
    where = _where(mesh, path)
    V = np.asarray(mesh.vertices)
    if V.ndim != 2 or V.shape[1] != 3:
        raise InputError(f"vertices have shape {V.shape}, expected (V, 3)", path=where)
    offsets = np.asarray(mesh.polygon_offsets, dtype=np.int64)
    pv = np.asarray(mesh.polygon_vertices, dtype=np.int64)
    sizes = np.diff(offsets)
    finite = np.isfinite(V).all(axis=1)
    problems = _coordinate_problems(V, finite) + _corner_problems(mesh, offsets, pv, sizes, V.shape[0])
    if (sizes < 3).any() or ((pv < 0) | (pv >= V.shape[0])).any():
        # the remaining checks index vertices through the polygons: they would fail or mislead
        _raise_problems(problems, where)

    repeated_poly = _polygons_with_repeats(offsets, pv, sizes)
    problems += _repeated_corner_problems(repeated_poly, offsets, pv)
    if sizes.shape[0]:
        faces, face_poly = mesh.faces, mesh.face_polygon  # (kept by the mesh for what follows)
    else:
        faces, face_poly = np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
    if faces.shape[0] and finite.all():
        problems += _degenerate_triangle_problems(V, faces, face_poly, repeated_poly, offsets, pv, area_tolerance)
    if faces.shape[0]:
        problems += _non_manifold_problems(faces, face_poly, V.shape[0], mesh.sorted_edge_keys())
        problems += _duplicate_triangle_problems(faces, face_poly, V.shape[0])
    problems += _unused_vertex_problems(pv, V.shape[0])
    _raise_problems(problems, where)


def _coordinate_problems(V: np.ndarray, finite: np.ndarray) -> list[str]:
    if finite.all():
        return []
    bad = np.flatnonzero(~finite)
    return [f"{len(bad)} vertices have NaN or infinite coordinates: vertex {_first(bad)} "
            f"(vertex {int(bad[0])} is {V[bad[0]].tolist()})"]


def _corner_problems(mesh: Mesh, offsets: np.ndarray, pv: np.ndarray, sizes: np.ndarray, n_v: int) -> list[str]:
    """Polygons too small, and corners (vertex or UV) that index nothing."""
    problems = []
    small = np.flatnonzero(sizes < 3)
    if small.size:
        k = int(small[0])
        problems.append(f"{len(small)} polygons have fewer than three corners: polygon {_first(small)} "
                        f"(polygon {k} has {int(sizes[k])})")
    out = (pv < 0) | (pv >= n_v)
    if out.any():
        c = int(np.argmax(out))
        k = int(np.searchsorted(offsets, c, side="right") - 1)
        problems.append(f"{int(out.sum())} polygon corners refer to missing vertices: polygon {k} uses "
                        f"vertex {int(pv[c])}, the mesh has {n_v} vertices (0..{n_v - 1})")
    if mesh.polygon_uvs is not None:
        n_uv = 0 if mesh.uvs is None else len(mesh.uvs)
        puv = np.asarray(mesh.polygon_uvs, dtype=np.int64)
        out_uv = (puv < 0) | (puv >= n_uv)
        if puv.shape != pv.shape:
            problems.append(f"{puv.shape[0]} UV corners for {pv.shape[0]} vertex corners")
        elif out_uv.any():
            c = int(np.argmax(out_uv))
            k = int(np.searchsorted(offsets, c, side="right") - 1)
            problems.append(f"polygon {k} uses texture coordinate {int(puv[c])}, the mesh has {n_uv}")
    return problems


def _repeated_corner_problems(repeated_poly: np.ndarray, offsets: np.ndarray, pv: np.ndarray) -> list[str]:
    if not repeated_poly.any():
        return []
    bad = np.flatnonzero(repeated_poly)
    k = int(bad[0])
    return [f"{len(bad)} polygons use a vertex twice: polygon {_first(bad)} (polygon {k} has vertices "
            f"{pv[offsets[k]:offsets[k + 1]].tolist()}); remove the repeated corner"]


def _degenerate_triangle_problems(V, faces, face_poly, repeated_poly, offsets, pv, area_tolerance) -> list[str]:
    """Triangles whose area is below ``area_tolerance`` × the mean squared edge length: their
    cotangent weights are unbounded."""
    a, b, c = V[faces[:, 0]], V[faces[:, 1]], V[faces[:, 2]]
    ab, ac = b - a, c - a
    double_area = lengths(cross(ab, ac))
    bc = c - b
    mean_e2 = (np.einsum("ij,ij->", ab, ab) + np.einsum("ij,ij->", bc, bc) + np.einsum("ij,ij->", ac, ac)) \
        / (3 * faces.shape[0])
    tiny = (0.5 * double_area <= area_tolerance * mean_e2) & ~repeated_poly[face_poly]
    if not tiny.any():
        return []
    bad_t = np.flatnonzero(tiny)
    bad_p = np.unique(face_poly[bad_t])
    t = int(bad_t[0])
    k = int(face_poly[t])
    return [f"{len(bad_p)} polygons have a zero-area (degenerate) triangle: polygon {_first(bad_p)} "
            f"(polygon {k}, vertices {pv[offsets[k]:offsets[k + 1]].tolist()}, triangle "
            f"{faces[t].tolist()} has area {0.5 * double_area[t]:.3g}, below "
            f"{area_tolerance:g} x mean squared edge length {mean_e2:.3g}); "
            "collapse or re-triangulate it"]


def _non_manifold_problems(faces: np.ndarray, face_poly: np.ndarray, n_v: int, skey: np.ndarray) -> list[str]:
    """Edges used by more than two triangles (``skey``: :func:`sorted_edge_keys` of ``faces``)."""
    # runs of equal keys in the sorted list: their lengths are the edges' face counts
    starts = np.flatnonzero(np.r_[True, skey[1:] != skey[:-1]])
    counts = np.diff(np.r_[starts, skey.shape[0]])
    over = np.flatnonzero(counts > 2)
    if not over.size:
        return []
    k = int(over[0])
    i, j = divmod(int(skey[starts[k]]), n_v)
    e = triangle_edges(faces)
    using = np.unique(face_poly[np.flatnonzero((e[:, 0] == i) & (e[:, 1] == j)) % len(faces)])
    return [f"{len(over)} non-manifold edges: edge ({i}, {j}) is used by {int(counts[k])} triangles "
            f"(polygons {_first(using)}); an edge may be shared by at most two faces"]


def _duplicate_triangle_problems(faces: np.ndarray, face_poly: np.ndarray, n_v: int) -> list[str]:
    """The same triangle twice (possibly with another winding): it passes the edge test at a border."""
    tri = np.sort(faces, axis=1)
    if n_v < 2_000_000:  # one int64 key per triangle: a 1-D sort instead of a 3-key lexsort
        tkey = (tri[:, 0] * n_v + tri[:, 1]) * n_v + tri[:, 2]
        order = np.argsort(tkey)
        same = tkey[order][1:] == tkey[order][:-1]
    else:
        order = np.lexsort((tri[:, 2], tri[:, 1], tri[:, 0]))
        same = (tri[order][1:] == tri[order][:-1]).all(axis=1)
    if not same.any():
        return []
    d = int(np.argmax(same))
    p, q = sorted((int(face_poly[order[d]]), int(face_poly[order[d + 1]])))
    return [f"{int(same.sum())} duplicated triangles: polygons {p} and {q} both cover triangle "
            f"{tri[order[d]].tolist()}; delete the duplicate face"]


def _unused_vertex_problems(pv: np.ndarray, n_v: int) -> list[str]:
    used = np.bincount(pv, minlength=n_v) > 0
    if used.all():
        return []
    bad = np.flatnonzero(~used)
    return [f"{len(bad)} vertices are used by no face: vertex {_first(bad, 10)}; remove them (from the "
            "rest mesh and every example pose alike) or reference them from faces"]


def _polygons_with_repeats(offsets: np.ndarray, pv: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """(N,) bool: polygons that list a vertex more than once."""
    n_poly = sizes.shape[0]
    if n_poly == 0:
        return np.zeros(0, dtype=bool)
    max_size = int(sizes.max())
    repeated = np.zeros(n_poly, dtype=bool)
    if max_size <= 8 and int(sizes.min()) == max_size:  # polygons of one size (all triangles): a table
        corners = pv.reshape(n_poly, max_size)
        for i in range(max_size):
            for j in range(i + 1, max_size):
                repeated |= corners[:, i] == corners[:, j]
        return repeated
    corner_poly = np.repeat(np.arange(n_poly, dtype=np.int64), sizes)
    if max_size <= 8:
        # compare every corner with the ones after it in its polygon: O(C * size), no sort
        end = offsets[1:][corner_poly]
        c = np.arange(pv.shape[0], dtype=np.int64)
        for j in range(1, max_size):
            inside = c + j < end
            same = np.zeros(pv.shape[0], dtype=bool)
            same[inside] = pv[c[inside]] == pv[c[inside] + j]
            repeated[corner_poly[same]] = True
    else:
        order = np.lexsort((pv, corner_poly))
        sp, sv = corner_poly[order], pv[order]
        dup = (sp[1:] == sp[:-1]) & (sv[1:] == sv[:-1])
        repeated[sp[1:][dup]] = True
    return repeated


def _raise_problems(problems: list[str], where) -> None:
    if not problems:
        return
    if len(problems) == 1:
        message = f"mesh problem: {problems[0]}"
    else:
        message = "mesh problems:\n  - " + "\n  - ".join(problems)
    raise InputError(
        message,
        path=where,
        hint="repair the mesh in a modelling tool and export it again, keeping the vertex order "
             "of the example poses",
    )


def check_components(mesh: Mesh, constrained_vertices, what: str = "handle or anchor",
                     *, path: str | os.PathLike | None = None, hint: str | None = None) -> tuple[int, np.ndarray]:
    """Check that every connected part of the mesh holds at least one constrained vertex.

    The shell energy is invariant to moving a part rigidly (k_bend only: affinely), so a part
    without a handle or anchor makes the linear system singular.

    Parameters
    ----------
    mesh : Mesh
    constrained_vertices : (K,) int, vertex indices of handles and anchors
    what : str, how the message names a constrained vertex
    path : file named in the message; defaults to ``mesh.path``.
    hint : the fix, where the caller knows a better one than the rig's (the anchors file).

    Returns
    -------
    n_components : int
    labels : (V,) int32, the component of every vertex (a vertex in no face is its own part)

    Raises
    ------
    InputError
        Naming the size of each unconstrained part and one vertex in it.

    Example
    -------
    >>> m = Mesh(np.eye(3), np.array([0, 3]), np.array([0, 1, 2]))
    >>> check_components(m, [0])[0]
    1
    """

    where = _where(mesh, path)
    n_v = mesh.n_vertices
    cv = np.asarray(constrained_vertices, dtype=np.int64).ravel()
    out = (cv < 0) | (cv >= n_v)
    if out.any():
        raise InputError(f"{what} vertex {int(cv[np.argmax(out)])} is out of range: the mesh has "
                         f"{n_v} vertices (0..{n_v - 1})", path=where)
    n_comp, labels = component_labels(mesh)
    has = np.zeros(n_comp, dtype=bool)
    has[labels[cv]] = True
    missing = np.flatnonzero(~has)
    if missing.size:
        sizes = np.bincount(labels, minlength=n_comp)
        first_vertex = np.full(n_comp, n_v, dtype=np.int64)
        np.minimum.at(first_vertex, labels, np.arange(n_v))
        used = np.bincount(np.asarray(mesh.polygon_vertices, dtype=np.int64), minlength=n_v) > 0
        # biggest parts first: those are the ones a user means to animate
        missing = missing[np.argsort(-sizes[missing], kind="stable")]
        parts = []
        for c in missing[:5]:
            v = int(first_vertex[c])
            if sizes[c] == 1 and not used[v]:
                parts.append(f"vertex {v} (used by no face)")
            else:
                parts.append(f"a part of {int(sizes[c])} vertices containing vertex {v}")
        more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
        raise InputError(
            f"{len(missing)} of the mesh's {n_comp} connected parts have no {what} vertex, so the "
            f"shell system is singular: " + "; ".join(parts) + more,
            path=where,
            hint=hint or f"put a {what} on every separate part — a part that only moves with the head (an "
                         "eyeball, teeth) needs one of its vertices in the anchors file — or remove the part from "
                         "the rest mesh and every example pose",
        )
    return int(n_comp), labels.astype(np.int32)


def component_labels(mesh: Mesh) -> tuple[int, np.ndarray]:
    """The mesh's connected parts: their count and each vertex's part (V,) (a vertex in no face is
    its own part)."""
    n_v = mesh.n_vertices
    # two edges per triangle connect its corners; duplicates do not matter for connectivity,
    # so the (slow) de-duplication of the edge list is skipped
    f = mesh.faces
    rows = np.concatenate([f[:, 0], f[:, 1]])
    cols = np.concatenate([f[:, 1], f[:, 2]])
    graph = coo_matrix((np.ones(rows.shape[0], dtype=np.int32), (rows, cols)), shape=(n_v, n_v)).tocsr()
    return connected_components(graph, directed=True, connection="weak")


def coincident_vertices(vertices: np.ndarray) -> np.ndarray:
    """(V,) int64 each vertex's representative: the lowest index at exactly its position (itself
    where no other vertex is there). A mesh split along UV seams or hard edges (as engines and some
    exporters write it: one vertex per UV or normal) has such vertices, which no face joins.

    Example
    -------
    >>> coincident_vertices(np.array([[0., 0, 0], [1, 0, 0], [0, 0, 0]])).tolist()
    [0, 1, 0]
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64) + 0.0  # (−0.0 is 0.0)
    rows = v.view(np.dtype((np.void, v.dtype.itemsize * v.shape[1]))).ravel()
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    return first[inverse.ravel()].astype(np.int64)


def weld_vertices(mesh: Mesh, representative: np.ndarray) -> tuple[Mesh, np.ndarray, np.ndarray]:
    """The mesh with every vertex replaced by its representative (:func:`coincident_vertices`):
    (welded mesh, ``keep`` (W,) the original index of each welded vertex, ``index`` (V,) each
    original vertex's welded index). Polygons, their per-corner UVs and groups are kept."""
    V = mesh.n_vertices
    keep = np.flatnonzero(representative == np.arange(V))
    new = np.full(V, -1, dtype=np.int64)
    new[keep] = np.arange(len(keep))
    index = new[representative]
    welded = replace(mesh, vertices=mesh.vertices[keep],
                     polygon_vertices=index[np.asarray(mesh.polygon_vertices, dtype=np.int64)])
    return welded, keep, index


def file_vertices(weld_index: np.ndarray) -> np.ndarray:
    """(W,) one vertex of the mesh file for each vertex of the welded mesh (the ``keep`` of
    :func:`weld_vertices`), from ``weld_index`` (V,) each file vertex's welded one: what reads
    frames in the file's order onto the welded mesh."""
    return np.unique(np.asarray(weld_index), return_index=True)[1]


def welded_frames(frames, weld_index: np.ndarray) -> "VertexSelection":
    """Frames (T, V_file, 3) in the mesh file's vertex order (a truth, a mesh cache) read on the
    welded mesh, one vertex of each welded group (:func:`file_vertices`), lazily."""
    return VertexSelection(frames, file_vertices(weld_index))


class VertexSelection:
    """Frames (T, V, 3) — an array or a memmap — seen through a vertex index array (W,): read
    lazily, frame by frame or a block of frames at a time, as (T, W, 3). Used between a welded rig
    and the mesh file's vertex order (:func:`weld_vertices`) without copying a whole take."""

    def __init__(self, frames, vertices: np.ndarray):
        self.frames = frames
        self.vertices = np.asarray(vertices, dtype=np.int64)
        self.dtype = getattr(frames, "dtype", np.dtype(np.float64))

    @property
    def shape(self) -> tuple:
        return (int(self.frames.shape[0]), len(self.vertices), int(self.frames.shape[2]))

    @property
    def ndim(self) -> int:
        return 3

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    def __getitem__(self, rows):
        block = np.asarray(self.frames[rows])
        return block[self.vertices] if block.ndim == 2 else block[:, self.vertices]

    def rows(self, start: int, stop: int) -> "VertexSelection":
        """Frames ``start:stop``, still read lazily."""
        return VertexSelection(self.frames[start:stop], self.vertices)

    def __array__(self, dtype=None, copy=None):
        out = self[:]
        return out if dtype is None else out.astype(dtype)


_CHECK_EDGES = 200_000  # edges sampled to pass a large pose quickly (check_pose)


def check_pose(rest_mesh: Mesh, pose_vertices: np.ndarray, path: str | os.PathLike | None,
               *, stretch: float = 3.0, max_fraction: float = 0.05, max_scale: float = 1.5) -> None:
    """Check that an example pose is the rest mesh deformed: same vertices in the same order.

    A different vertex order cannot be seen from the positions alone, but it shows in the
    rest mesh's edges: a re-ordered pose connects far-apart points, so most edges change
    length by large factors, while even a wide-open jaw stretches only a few edges (on the
    ICT kit, under 1.6 % of the edges change by more than 2x in any expression).

    Parameters
    ----------
    rest_mesh : Mesh
    pose_vertices : (V, 3) float, the example pose
    path : the pose's file, named in messages
    stretch : float
        An edge is "broken" when its length changes by more than this factor either way.
    max_fraction : float
        The vertex order is reported as different when more than this fraction of edges break.
    max_scale : float
        A median edge-length ratio beyond this factor (or below its inverse) is reported as a
        units mismatch.

    Raises
    ------
    InputError
        Different vertex count (both counts named), non-finite coordinates (first vertex
        named), a different vertex order (fraction of broken edges and the first offending
        vertex named) or a different scale.
    """
    P = np.asarray(pose_vertices)
    rest_name = rest_mesh.path or "the rest mesh"
    if P.ndim != 2 or P.shape[1] != 3:
        raise InputError(f"the pose's vertices have shape {P.shape}, expected (V, 3)", path=path)
    if P.shape[0] != rest_mesh.n_vertices:
        raise InputError(
            f"the pose has {P.shape[0]} vertices but the rest mesh ({rest_name}) has {rest_mesh.n_vertices}",
            path=path,
            hint="an example pose must be the rest mesh deformed: the same vertices in the same order",
        )
    finite = np.isfinite(P).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise InputError(f"{len(bad)} vertices have NaN or infinite coordinates: vertex {_first(bad)}",
                         path=path)
    X = np.asarray(rest_mesh.vertices, dtype=np.float64)
    e_all = rest_mesh.edges
    if e_all.shape[0] == 0:
        return

    def edge_ratios(e, cache_key):
        cached = getattr(rest_mesh, cache_key, None)  # the same for every pose of a rig
        if cached is not None and cached[0] is rest_mesh.vertices and cached[1].shape[0] == e.shape[0]:
            rest_len = cached[1]
        else:
            rest_len = np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)
            setattr(rest_mesh, cache_key, (rest_mesh.vertices, rest_len))
        pose_len = np.linalg.norm(P[e[:, 0]].astype(np.float64) - P[e[:, 1]], axis=1)
        keep = rest_len > 0
        e, ratio = e[keep], pose_len[keep] / rest_len[keep]
        broken = (ratio > stretch) | (ratio < 1.0 / stretch)
        return e, ratio, broken, float(np.median(ratio)), float(broken.mean())

    if e_all.shape[0] > 2 * _CHECK_EDGES:
        # a large mesh: an evenly spread sample of edges tells a clearly good pose (a few percent
        # broken, a median ratio near 1) from a bad one; anything near a limit gets every edge
        e = e_all[np.linspace(0, e_all.shape[0] - 1, _CHECK_EDGES).astype(np.int64)]
        _, _, _, median, fraction = edge_ratios(e, "_sample_edge_lengths")
        if fraction <= 0.5 * max_fraction and 1.1 / max_scale < median < max_scale / 1.1:
            return
    e, ratio, broken, median, fraction = edge_ratios(e_all, "_edge_lengths")
    if fraction > max_fraction:
        # a pose in other units breaks every edge by the same factor: tell that apart from
        # a re-ordering, which breaks them by factors spread over orders of magnitude
        rel = ratio / median if median > 0 else ratio
        rel_broken = float(((rel > stretch) | (rel < 1.0 / stretch)).mean())
        if median > 0 and rel_broken <= max_fraction:
            _raise_scale(median, path, rest_name)
        bad = e[broken]
        v = int(bad.min())
        k = int(np.flatnonzero((bad == v).any(axis=1))[0])
        other = int(bad[k, 1] if bad[k, 0] == v else bad[k, 0])
        r = float(ratio[np.flatnonzero(broken)[k]])
        raise InputError(
            f"the vertex order differs from the rest mesh ({rest_name}): {100 * fraction:.1f} % of the "
            f"edges change length by more than {stretch:g}x; first offending vertex: {v} (its edge to "
            f"vertex {other} is {r:.3g} x its rest length)",
            path=path,
            hint="export the example pose from the same mesh as the rest pose without re-ordering "
                 "vertices (e.g. keep 'vertex order' in the exporter, do not triangulate or weld)",
        )
    if median > max_scale or median < 1.0 / max_scale:
        _raise_scale(median, path, rest_name)


def _raise_scale(median: float, path, rest_name: str):
    raise InputError(
        f"the pose is about {median:.3g} times the size of the rest mesh ({rest_name}): "
        "edges change length by that factor almost everywhere",
        path=path,
        hint="export the example poses in the rest mesh's units (different units, e.g. mm vs cm?)",
    )


def check_marker_vertices(vertices, n_vertices: int, names: Sequence[str], path: str | os.PathLike | None,
                          lines: Sequence[int] | None = None) -> None:
    """Check marker vertex indices: in range, integral, one marker per vertex, unique names.

    Parameters
    ----------
    vertices : (M,) int, the vertex of every marker (0-based)
    n_vertices : int, vertices of the rest mesh
    names : (M,) str, marker names
    path : the markers file, named in messages
    lines : (M,) int or None, the file line of every marker; without it messages say "entry k"

    Raises
    ------
    InputError
        Naming the marker, its line and the offending vertex.

    Example
    -------
    >>> check_marker_vertices([3, 7], 10, ["chin", "nose"], "markers.csv", lines=[2, 3])
    """
    raw = np.asarray(vertices)
    names = [str(n) for n in names]
    if raw.ndim != 1 or raw.shape[0] != len(names):
        raise InputError(f"{raw.shape} marker vertices for {len(names)} marker names", path=path)

    def at(i: int) -> str:
        return f"marker {names[i]!r} (line {lines[i]})" if lines is not None else f"marker {names[i]!r} (entry {i + 1})"

    if raw.dtype.kind == "f":
        frac = ~np.isfinite(raw) | (raw != np.round(raw))
        if frac.any():
            i = int(np.argmax(frac))
            raise InputError(f"{at(i)}: vertex {raw[i]!r} is not a whole number", path=path)
    elif raw.dtype.kind not in "iu" and raw.size:
        raise InputError(f"marker vertices must be integers, got {raw.dtype}", path=path)
    v = raw.astype(np.int64)
    out = (v < 0) | (v >= n_vertices)
    if out.any():
        i = int(np.argmax(out))
        raise InputError(
            f"{at(i)}: vertex {int(v[i])} is out of range: the mesh has {n_vertices} vertices "
            f"(0..{n_vertices - 1})" + (f"; {int(out.sum())} markers in all" if out.sum() > 1 else ""),
            path=path,
            hint="marker vertex indices are 0-based and refer to the rig mesh",
        )
    order = np.argsort(v, kind="stable")
    same = np.flatnonzero(v[order][1:] == v[order][:-1])
    if same.size:
        i, j = sorted((int(order[same[0]]), int(order[same[0] + 1])))
        raise InputError(
            f"{at(i)} and {at(j)} both use vertex {int(v[i])}",
            path=path,
            hint="every marker needs a vertex of its own: two handles on one vertex conflict",
        )
    seen: dict[str, int] = {}
    for i, name in enumerate(names):
        if name in seen:
            raise InputError(f"{at(i)}: the name is used before by {at(seen[name])}", path=path,
                             hint="marker names must be unique: they match the mocap columns")
        seen[name] = i
