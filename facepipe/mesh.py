"""Mesh reading and writing with the original polygons and UVs kept.

The solver works on triangles, but exports must reproduce the artist's polygons
and per-corner texture coordinates in the rest mesh's vertex order. trimesh
re-indexes vertices at UV seams and triangulates on load, so OBJ files are read
here (the format is a few line types); PLY and other formats go through trimesh
with ``process=False`` so that vertex order is kept.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError


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
    first = np.repeat(np.cumsum(n_tri) - n_tri, n_tri)
    k = np.arange(polygon.shape[0], dtype=np.int64) - first
    start = offsets[polygon]
    tris = np.stack([corners[start], corners[start + k + 1], corners[start + k + 2]], axis=1)
    return tris, polygon


def load_mesh(path: str | os.PathLike) -> Mesh:
    """Read an OBJ (own reader, polygons and UVs kept) or any format trimesh reads (PLY, ...)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("mesh file not found", path=path, hint="check the path in the config")
    if path.suffix.lower() == ".obj":
        mesh = _load_obj(path)
    else:
        mesh = _load_with_trimesh(path)
    if mesh.n_vertices == 0 or mesh.n_polygons == 0:
        raise InputError("the mesh has no vertices or no faces", path=path)
    return mesh


def _parse_index(token: str, count: int, path: Path, line_no: int, what: str) -> int:
    try:
        i = int(token)
    except ValueError:
        raise InputError(f"line {line_no}: bad {what} index {token!r}", path=path) from None
    # OBJ indices are 1-based; negative ones count back from the last element read
    i = i - 1 if i > 0 else count + i
    if i < 0 or i >= count:
        raise InputError(f"line {line_no}: {what} index {token} is out of range (have {count})", path=path)
    return i


def _load_obj(path: Path) -> Mesh:
    vertices: list[list[float]] = []
    uvs: list[list[float]] = []
    offsets = [0]
    corner_v: list[int] = []
    corner_t: list[int] = []
    groups: list[int] = []
    group_names = ["default"]
    current_group = 0
    any_uv = False
    missing_uv = False
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for line_no, line in enumerate(fh, start=1):
            if not line or line[0] == "#":
                continue
            parts = line.split()
            if not parts:
                continue
            tag = parts[0]
            if tag == "v":
                try:
                    vertices.append([float(parts[1]), float(parts[2]), float(parts[3])])
                except (ValueError, IndexError):
                    raise InputError(f"line {line_no}: a vertex needs three numbers: {line.strip()!r}", path=path) from None
            elif tag == "vt":
                try:
                    uvs.append([float(parts[1]), float(parts[2]) if len(parts) > 2 else 0.0])
                except (ValueError, IndexError):
                    raise InputError(f"line {line_no}: bad texture coordinate {line.strip()!r}", path=path) from None
            elif tag == "f":
                if len(parts) < 4:
                    raise InputError(f"line {line_no}: a face needs at least three corners", path=path)
                for token in parts[1:]:
                    fields = token.split("/")
                    corner_v.append(_parse_index(fields[0], len(vertices), path, line_no, "vertex"))
                    if len(fields) > 1 and fields[1]:
                        corner_t.append(_parse_index(fields[1], len(uvs), path, line_no, "texture"))
                        any_uv = True
                    else:
                        corner_t.append(-1)
                        missing_uv = True
                offsets.append(len(corner_v))
                groups.append(current_group)
            elif tag in ("g", "o"):
                name = " ".join(parts[1:]) or "default"
                if name not in group_names:
                    group_names.append(name)
                current_group = group_names.index(name)
    polygon_uvs = None
    uv_array = None
    if any_uv:
        if missing_uv:
            raise InputError(
                "some faces have texture coordinates and others do not",
                path=path,
                hint="give every face corner a vt index, or none",
            )
        polygon_uvs = np.asarray(corner_t, dtype=np.int64)
        uv_array = np.asarray(uvs, dtype=np.float64).reshape(-1, 2)
    return Mesh(
        vertices=np.asarray(vertices, dtype=np.float64).reshape(-1, 3),
        polygon_offsets=np.asarray(offsets, dtype=np.int64),
        polygon_vertices=np.asarray(corner_v, dtype=np.int64),
        uvs=uv_array,
        polygon_uvs=polygon_uvs,
        polygon_groups=np.asarray(groups, dtype=np.int32),
        group_names=group_names,
        path=str(path),
    )


def _load_with_trimesh(path: Path) -> Mesh:
    import trimesh

    try:
        loaded = trimesh.load(path, process=False, maintain_order=True, force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(f"cannot read mesh: {exc}", path=path) from None
    faces = np.asarray(loaded.faces, dtype=np.int64)
    uvs = None
    polygon_uvs = None
    visual_uv = getattr(getattr(loaded, "visual", None), "uv", None)
    if visual_uv is not None and len(visual_uv) == len(loaded.vertices):
        uvs = np.asarray(visual_uv, dtype=np.float64)
        polygon_uvs = faces.reshape(-1).copy()
    return Mesh(
        vertices=np.asarray(loaded.vertices, dtype=np.float64),
        polygon_offsets=np.arange(0, 3 * len(faces) + 1, 3, dtype=np.int64),
        polygon_vertices=faces.reshape(-1),
        uvs=uvs,
        polygon_uvs=polygon_uvs,
        path=str(path),
    )


def load_vertices(path: str | os.PathLike) -> np.ndarray:
    """Vertex positions (V, 3) float64 of a mesh file (for example poses)."""
    return load_mesh(path).vertices


def format_obj_faces(mesh: Mesh) -> bytes:
    """The ``f`` lines of an OBJ (1-based, ``v/vt`` when the mesh has UVs), formatted once.

    Vectorised per polygon size, so a sequence of frames formats the topology only once.
    """
    sizes = mesh.polygon_sizes
    v = mesh.polygon_vertices + 1
    t = None if mesh.polygon_uvs is None else mesh.polygon_uvs + 1
    lines = np.empty(mesh.n_polygons, dtype=object)
    for size in np.unique(sizes):
        idx = np.flatnonzero(sizes == size)
        starts = mesh.polygon_offsets[idx]
        cols = starts[:, None] + np.arange(size)[None, :]
        if t is None:
            fmt = "f" + " %d" * size
            block = v[cols]
        else:
            fmt = "f" + " %d/%d" * size
            block = np.empty((len(idx), 2 * size), dtype=np.int64)
            block[:, 0::2] = v[cols]
            block[:, 1::2] = t[cols]
        text = "\n".join(fmt % tuple(row) for row in block.tolist())
        lines[idx] = text.split("\n")
    return ("\n".join(lines.tolist()) + "\n").encode()


def format_obj_header(mesh: Mesh) -> bytes:
    """The ``vt`` lines of an OBJ (empty without UVs)."""
    if mesh.uvs is None:
        return b""
    return _format_rows(b"vt", mesh.uvs)


def _format_rows(tag: bytes, values: np.ndarray) -> bytes:
    # np.savetxt-like but into memory and ~5x faster: one % over a whole block
    values = np.asarray(values, dtype=np.float64)
    fmt = tag.decode() + " %.8g" * values.shape[1]
    return ("\n".join([fmt] * values.shape[0]) % tuple(values.ravel().tolist()) + "\n").encode()


def obj_bytes(mesh: Mesh, vertices: np.ndarray | None = None, faces_block: bytes | None = None,
              uv_block: bytes | None = None) -> bytes:
    """A whole OBJ file as bytes; pass pre-formatted blocks to reuse them across frames."""
    vertices = mesh.vertices if vertices is None else vertices
    faces_block = format_obj_faces(mesh) if faces_block is None else faces_block
    uv_block = format_obj_header(mesh) if uv_block is None else uv_block
    return b"".join([_format_rows(b"v", vertices), uv_block, faces_block])


def save_obj(path: str | os.PathLike, mesh: Mesh, vertices: np.ndarray | None = None) -> None:
    """Write ``mesh`` (or its topology with other ``vertices``) as OBJ, atomically."""
    from .atomic import atomic_open

    with atomic_open(path, "wb") as fh:
        fh.write(obj_bytes(mesh, vertices))
