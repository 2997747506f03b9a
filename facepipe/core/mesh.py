"""Mesh reading, writing and topology checks, with the original polygons and UVs kept.

The solver works on triangles, but exports must reproduce the artist's polygons
and per-corner texture coordinates in the rest mesh's vertex order. trimesh
re-indexes vertices at UV seams and triangulates on load, so OBJ files are read
here (the format is a few line types); PLY and other formats go through trimesh
with ``process=False`` so that vertex order is kept.

The ``check_*`` functions turn the ways a rig's input can be wrong into an
:class:`~facepipe.errors.InputError` that names the file and the element (vertex,
edge, polygon, marker, line) *before* a solver fails with a singular matrix or
silently produces garbage. They are vectorised: a million triangles take
about half a second.
"""

from __future__ import annotations

import gc
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from facepipe.errors import InputError


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
            self._edges = unique_edges(self.faces)
        return self._edges

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
    e = triangle_edges(faces)
    if e.shape[0] == 0:
        return e
    # one int64 key per edge, sorted: several times faster than unique(axis=0), and than
    # numpy 2's hash-based np.unique on millions of keys
    n = int(e.max()) + 1
    key = _sorted_unique(e[:, 0] * n + e[:, 1])
    return np.stack([key // n, key % n], axis=1)


def _sorted_unique(key: np.ndarray) -> np.ndarray:
    key = np.sort(key)
    keep = np.empty(key.shape, dtype=bool)
    keep[:1] = True
    np.not_equal(key[1:], key[:-1], out=keep[1:])
    return key[keep]


# ----------------------------------------------------------------------------------------------
# reading

def load_mesh(path: str | os.PathLike) -> Mesh:
    """Read a mesh: OBJ with the own reader (polygons, UVs, groups kept), other formats
    (PLY, ...) through trimesh with the file's vertex order kept.

    Parameters
    ----------
    path : file name; the suffix picks the reader.

    Returns
    -------
    Mesh

    Raises
    ------
    InputError
        Missing, empty, binary-where-text-expected, truncated or malformed files, naming the
        line and what is wrong with it.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("mesh file not found", path=path, hint="check the path in the config")
    if path.suffix.lower() == ".obj":
        mesh = _load_obj(path)
    else:
        mesh = _load_with_trimesh(path)
    if mesh.n_vertices == 0:
        raise InputError("the mesh has no vertices", path=path)
    if mesh.n_polygons == 0:
        raise InputError(
            f"the mesh has {mesh.n_vertices} vertices but no faces",
            path=path,
            hint="a point cloud cannot be a rig mesh: export the faces too",
        )
    return mesh


# OBJ statements that carry nothing facepipe uses; anything else that is not v/vt/f/g/o is
# reported, because an unknown statement usually means the file is not an OBJ at all
_OBJ_IGNORED = frozenset(
    "vn vp l p s mg usemtl mtllib maplib usemap lod bevel c_interp d_interp shadow_obj "
    "trace_obj ctech stech cstype deg bmat step curv curv2 surf parm trim hole scrv sp end "
    "con call csh".split()
)


def _load_obj(path: Path) -> Mesh:
    # the parser builds hundreds of thousands of small lists: the cyclic garbage collector
    # would walk them again and again (30 % of the time) though they hold no cycles
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
        return _parse_obj(path)
    finally:
        if gc_was_enabled:
            gc.enable()


def _read_obj_bytes(path: Path) -> bytes:
    data = path.read_bytes()
    if not data.strip():
        raise InputError("the file is empty", path=path, hint="re-export the mesh")
    nul = data.find(b"\0")
    if nul >= 0:
        raise InputError(
            f"binary data at byte {nul}: this is not a text OBJ file",
            path=path,
            hint="export the mesh as a text OBJ, or give the file its real extension (e.g. .ply)",
        )
    return data


def _parse_obj(path: Path) -> Mesh:
    data = _read_obj_bytes(path)
    mesh = _fast_obj(data, path)  # numpy over the bytes: ~20x faster on large meshes
    if mesh is not None:
        return mesh
    return _parse_obj_lists(path, data)


def _parse_obj_lists(path: Path, data: bytes) -> Mesh:
    """The reference reader: a list of tokens per statement. It reads every file the fast path
    declines (odd line breaks, continuations, mixed corner layouts) and names bad lines."""
    text = data.decode("utf-8", errors="replace")
    if "\\\n" in text or "\\\r\n" in text:
        # a trailing backslash continues a statement on the next line
        text = re.sub(r"\\\r?\n", " ", text)
    lines = text.splitlines()
    unterminated = not text.endswith(("\n", "\r"))

    def fail(line_no: int, message: str, hint: str | None = None):
        if unterminated and line_no == len(lines) and hint is None:
            hint = "the last line has no line end: the file may be truncated"
        raise InputError(f"line {line_no}: {message}", path=path, hint=hint)

    v_rows: list[list[str]] = []
    vt_rows: list[list[str]] = []
    f_rows: list[list[str]] = []
    f_line: list[int] = []
    f_nv: list[int] = []  # vertices read before each face: negative indices count back from it
    f_nt: list[int] = []
    f_group: list[int] = []
    group_names = ["default"]
    group_index = {"default": 0}
    current_group = 0
    for line_no, line in enumerate(lines, start=1):
        if "#" in line:  # comment lines, and comments after a statement (some exporters)
            line = line[:line.index("#")]
        parts = line.split()
        if not parts:
            continue
        tag = parts[0]
        if tag == "v":
            v_rows.append(parts)
        elif tag == "f" or tag == "fo":
            if len(parts) < 4:
                fail(line_no, f"a face needs at least three corners: {line.strip()!r}")
            f_rows.append(parts)
            f_line.append(line_no)
            f_nv.append(len(v_rows))
            f_nt.append(len(vt_rows))
            f_group.append(current_group)
        elif tag == "vt":
            vt_rows.append(parts)
        elif tag in ("g", "o"):
            name = " ".join(parts[1:]) or "default"
            if name not in group_index:
                group_index[name] = len(group_names)
                group_names.append(name)
            current_group = group_index[name]
        elif tag not in _OBJ_IGNORED:
            fail(
                line_no,
                f"unknown OBJ statement {line.strip()[:60]!r}",
                hint="facepipe reads v, vt, f, g and o lines; is this a text OBJ file?",
            )

    vertices = _parse_floats(v_rows, 3, "v", "a vertex needs three numbers", lines, fail)
    uv_array = None
    if vt_rows:
        # "vt u" alone is allowed (v defaults to 0); a third (w) coordinate is dropped
        padded = [r[1:3] if len(r) >= 3 else r[1:2] + ["0"] for r in vt_rows]
        uv_array = _parse_floats(padded, 2, "vt", "bad texture coordinate", lines, fail, pre_sliced=True)

    sizes = np.fromiter((len(r) - 1 for r in f_rows), dtype=np.int64, count=len(f_rows))
    offsets = np.zeros(len(f_rows) + 1, dtype=np.int64)
    np.cumsum(sizes, out=offsets[1:])
    v_tok, t_tok = _split_corners([t for r in f_rows for t in r[1:]])
    corner_face = np.repeat(np.arange(len(f_rows)), sizes)
    corner_v = _resolve_indices(v_tok, np.asarray(f_nv, dtype=np.int64)[corner_face], len(v_rows),
                                "vertex", corner_face, f_line, fail)
    polygon_uvs = None
    if t_tok is not None:
        has_t = np.fromiter((bool(t) for t in t_tok), dtype=bool, count=len(t_tok)) if "" in t_tok else None
        if has_t is None or has_t.any():
            if has_t is not None:
                bad = int(corner_face[np.argmin(has_t)])
                fail(
                    f_line[bad],
                    "this face has corners without texture coordinates, but other faces have them",
                    hint="give every face corner a vt index (f v/vt ...), or none",
                )
            polygon_uvs = _resolve_indices(t_tok, np.asarray(f_nt, dtype=np.int64)[corner_face],
                                           len(vt_rows), "texture", corner_face, f_line, fail)
    if polygon_uvs is None:
        uv_array = None
    return Mesh(
        vertices=vertices,
        polygon_offsets=offsets,
        polygon_vertices=corner_v,
        uvs=uv_array,
        polygon_uvs=polygon_uvs,
        polygon_groups=np.asarray(f_group, dtype=np.int32),
        group_names=group_names,
        path=str(path),
    )


_INT = r"[-+]?\d+"
# (whole-file pattern, fields per corner, whether the second field is a texture index)
_CORNER_FORMATS = [
    (re.compile(rf"{_INT}/{_INT}(?: {_INT}/{_INT})*"), 2, True),              # v/vt
    (re.compile(rf"{_INT}/{_INT}/{_INT}(?: {_INT}/{_INT}/{_INT})*"), 3, True),  # v/vt/vn
    (re.compile(rf"{_INT}//{_INT}(?: {_INT}//{_INT})*"), 2, False),            # v//vn
    (re.compile(rf"{_INT}(?: {_INT})*"), 1, False),                            # v
]


def _split_corners(tokens: list[str]) -> tuple[list[str], list[str] | None]:
    """Vertex and texture index strings of face corners (``""`` where a corner has no vt).

    When every corner has the same layout (the usual case) one regular expression checks
    the whole file and one ``split`` cuts it, instead of a ``split("/")`` per corner.
    """
    if not tokens:
        return [], None
    joined = " ".join(tokens)
    for pattern, stride, has_t in _CORNER_FORMATS:
        if pattern.fullmatch(joined):
            fields = joined.replace("//", "/").replace("/", " ").split()
            return fields[0::stride], (fields[1::stride] if has_t else None)
    split = [t.split("/") for t in tokens]
    return [s[0] for s in split], [s[1] if len(s) > 1 else "" for s in split]


def _parse_floats(rows, width, tag, what, lines, fail, pre_sliced=False) -> np.ndarray:
    """(len(rows), width) float64 from OBJ statements; on a bad row name its line."""
    if not rows:
        return np.zeros((0, width), dtype=np.float64)
    try:
        # numpy parses the strings in C; ragged rows or non-numbers raise ValueError
        out = np.array(rows if pre_sliced else [r[1:width + 1] for r in rows], dtype=np.float64)
        if out.shape == (len(rows), width):
            return out
    except ValueError:
        pass
    # the slow path only runs to find and name the bad line
    k = -1
    for line_no, line in enumerate(lines, start=1):
        parts = line.split()
        if parts and parts[0] == tag:
            k += 1
            try:
                if len(parts) < (2 if tag == "vt" else width + 1):
                    raise ValueError
                [float(x) for x in parts[1:width + 1]]
            except ValueError:
                fail(line_no, f"{what}: {line.strip()[:80]!r}")
    raise AssertionError("unreachable: a bad row was not found again")  # pragma: no cover


def _resolve_indices(tokens, count_before, count_total, what, corner_face, f_line, fail) -> np.ndarray:
    """0-based indices from OBJ corner tokens (1-based, negative = relative to the end so far)."""
    try:
        raw = np.array(tokens, dtype=np.int64) if tokens else np.zeros(0, dtype=np.int64)
    except ValueError:
        for k, t in enumerate(tokens):
            try:
                int(t)
            except ValueError:
                fail(f_line[int(corner_face[k])], f"bad {what} index {t!r}")
        raise
    # positive indices may refer to vertices defined later in the file, negative ones only back
    idx = np.where(raw > 0, raw - 1, count_before + raw)
    bad = (raw == 0) | (idx < 0) | (idx >= count_total)
    if bad.any():
        k = int(np.argmax(bad))
        fail(
            f_line[int(corner_face[k])],
            f"{what} index {int(raw[k])} is out of range: the file has {count_total} "
            f"{'vertices' if what == 'vertex' else 'texture coordinates'} (OBJ indices start at 1)",
        )
    return idx


# ---------------------------------------------------------------------------------------------- fast OBJ path
#
# The reader above builds Python lists of every statement's tokens: ~15 s for a 1M-triangle
# mesh. The fast path below does the same work on numpy arrays over the file's bytes: token
# boundaries, a tag per line, the numbers parsed by numpy's C parser in one call per kind. It
# only takes files it is sure to read exactly as the reader above would (plain ASCII
# statements, ``\n`` or ``\r\n`` line ends, one corner layout for all faces), and returns None
# for anything else — unusual files and every kind of bad input — so that the reader above
# reads them, with its messages naming the line.

# bytes allowed in the numbers the fast path reads (the comma separates them)
_OBJ_LUT_FLOAT = np.zeros(256, dtype=bool)
_OBJ_LUT_FLOAT[np.frombuffer(b"0123456789+-.eE,", dtype=np.uint8)] = True
_OBJ_LUT_INT = np.zeros(256, dtype=bool)
_OBJ_LUT_INT[np.frombuffer(b"0123456789+-,", dtype=np.uint8)] = True


def _tag_key(text: bytes) -> int:
    return sum(b << (8 * k) for k, b in enumerate(text)) | (len(text) << 56)


_TAG_V, _TAG_VT, _TAG_F, _TAG_FO, _TAG_G, _TAG_O = (_tag_key(t) for t in (b"v", b"vt", b"f", b"fo", b"g", b"o"))


class _Tokens:
    """Whitespace-separated tokens of an OBJ file's bytes, comments cut, grouped by line.

    Only for files that pass :func:`_obj_prefilter`: their only bytes below 32 are tab, line
    feed and carriage return, so ``byte <= 32`` is exactly str.split()'s whitespace.
    """

    def __init__(self, data: bytes):
        buf = np.frombuffer(data, dtype=np.uint8)
        self.buf = buf
        n = buf.shape[0]
        space = buf <= 32
        edge = np.flatnonzero(space[1:] != space[:-1]) + 1  # where a run of spaces starts or ends
        if n and not space[0]:
            edge = np.concatenate([[0], edge])
        del space
        if edge.shape[0] % 2:
            edge = np.concatenate([edge, [n]])
        start, end = edge[0::2], edge[1::2]
        del edge
        # the line of each token: line feeds counted in the gaps before it
        newline = np.flatnonzero(buf == 10)
        gap = np.searchsorted(start, newline)
        line = np.cumsum(np.bincount(gap, minlength=start.shape[0] + 1)[:start.shape[0]])  # 0-based
        del gap
        if b"#" in data:
            # a comment runs from the first '#' to the line end: cut tokens there
            hashes = np.flatnonzero(buf == 35)
            hash_line = np.searchsorted(newline, hashes)
            keep_first = np.ones(hashes.shape[0], dtype=bool)
            keep_first[1:] = hash_line[1:] != hash_line[:-1]
            cut = np.full(newline.shape[0] + 1, n, dtype=np.int64)
            cut[hash_line[keep_first]] = hashes[keep_first]
            end = np.minimum(end, cut[line])
            keep = start < end
            start, end, line = start[keep], end[keep], line[keep]
        self.start, self.end = start, end
        # the first token of each line is its tag
        head = np.ones(line.shape[0], dtype=bool)
        np.not_equal(line[1:], line[:-1], out=head[1:])
        self.head = np.flatnonzero(head)  # token index of each statement's tag
        self.count = np.diff(np.append(self.head, line.shape[0]))  # tokens per statement
        self.stmt_line = line[self.head]  # 0-based line of each statement
        tag_start, tag_len = start[self.head], end[self.head] - start[self.head]
        key = tag_len.astype(np.uint64) << np.uint64(56)
        short = tag_len <= 7
        for k in range(7):
            byte = buf[np.minimum(tag_start + k, n - 1)].astype(np.uint64)
            key |= np.where(short & (k < tag_len), byte << np.uint64(8 * k), np.uint64(0))
        key[~short] = np.uint64(0)  # no statement facepipe reads has a tag this long
        self.tag = key

    def text(self, tok: int) -> bytes:
        return self.buf[self.start[tok]:self.end[tok]].tobytes()

    def gather(self, tokens: np.ndarray, lengths: np.ndarray | None = None,
               skip: np.ndarray | None = None) -> np.ndarray:
        """The bytes of ``tokens`` (from ``skip`` bytes in, ``lengths`` long when given), each
        followed by a comma."""
        start = self.start[tokens]
        lens = (self.end[tokens] - start) if lengths is None else lengths
        if skip is not None:
            start = start + skip
        return _gather_spans(self.buf, start, lens)


def _gather_spans(buf: np.ndarray, start: np.ndarray, lens: np.ndarray) -> np.ndarray:
    """Bytes ``buf[start:start + lens]`` of disjoint, increasing spans, each followed by a comma.

    Each span and the byte after it (a space or slash, replaced by the comma) are marked by +1/-1
    steps summed over the buffer, then compressed out: two passes at memory speed, where an index
    per output byte would cost several.
    """
    if start.shape[0] == 0:
        return np.zeros(0, dtype=np.uint8)
    # only the stretch of the file the spans lie in (statements of a kind usually come together)
    lo = int(start[0])
    buf = buf[lo:int(start[-1] + lens[-1]) + 1]
    start = start - lo
    n = buf.shape[0]
    step = np.zeros(n + 2, dtype=np.int8)
    step[start] = 1
    step[start + lens + 1] -= 1  # disjoint spans: no index twice, but it may be another's start
    keep = np.cumsum(step[:n + 1], dtype=np.int8).view(bool)
    out = buf[keep[:n]]
    if keep[n]:  # the last span ends with the file
        out = np.append(out, np.uint8(44))
    out[np.cumsum(lens + 1) - 1] = 44  # ','
    return out


def _only_bytes(chars: np.ndarray, allowed: np.ndarray) -> bool:
    """Whether every byte is an allowed one: a few comparisons over the bytes (a table lookup
    or a histogram would first widen every byte to an index)."""
    bad = (chars < 43) | (chars > 57)  # digits and + , - . /
    for b in np.flatnonzero(allowed):
        if b < 43 or b > 57:
            bad &= chars != b
    for b in range(43, 58):
        if not allowed[b]:
            bad |= chars == b
    return not bad.any()


def _parse_numbers(chars: np.ndarray, count: int, dtype, allowed: np.ndarray) -> np.ndarray | None:
    """``count`` numbers from comma-separated ASCII, or None unless every field is one plain number."""
    if count == 0:
        return np.zeros(0, dtype=dtype)
    if not _only_bytes(chars, allowed):
        return None
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            values = np.fromstring(chars.tobytes(), dtype=dtype, sep=",")  # noqa: NPY201 - text mode
        except (ValueError, DeprecationWarning):
            return None
    return values if values.shape[0] == count else None


def _obj_prefilter(data: bytes) -> bool:
    """Whether the fast path may read this file: no continuations, and its only line breaks
    are ``\\n`` and ``\\r\\n`` and its only control characters tab, CR and LF (one-byte
    searches, isascii and translate run at memory speed; the two-byte searches, several times
    slower, only where their first byte occurs)."""
    if b"\\" in data and (b"\\\n" in data or b"\\\r\n" in data):
        return False
    if not data.isascii():
        for seq in (b"\xc2\x85", b"\xe2\x80\xa8", b"\xe2\x80\xa9"):  # Unicode line breaks
            if seq in data:
                return False
    if data.translate(None, _NOT_CONTROL):  # what is left: control characters other than tab, LF, CR
        return False
    if b"\r" not in data:
        return True
    return data.count(b"\r\n") == data.count(b"\r")


_NOT_CONTROL = bytes(range(32, 256)) + b"\t\n\r"


def _fast_floats(tok: _Tokens, stmts: np.ndarray, width: int, pad_second: bool = False) -> np.ndarray | None:
    """(len(stmts), width) floats from the tokens after each statement's tag."""
    if stmts.shape[0] == 0:
        return np.zeros((0, width))
    count = tok.count[stmts]
    if pad_second:  # "vt u" means v = 0
        if (count < 2).any():
            return None
        two = count >= 3
    else:
        if (count < width + 1).any():
            return None
        two = np.ones(stmts.shape[0], dtype=bool)
    if two.all():
        tokens = (tok.head[stmts][:, None] + np.arange(1, width + 1)).ravel()
        values = _parse_numbers(tok.gather(tokens), tokens.shape[0], np.float64, _OBJ_LUT_FLOAT)
        return None if values is None else values.reshape(-1, width)
    out = np.zeros((stmts.shape[0], width))
    for sel, w in ((two, width), (~two, 1)):
        tokens = (tok.head[stmts[sel]][:, None] + np.arange(1, w + 1)).ravel()
        values = _parse_numbers(tok.gather(tokens), tokens.shape[0], np.float64, _OBJ_LUT_FLOAT)
        if values is None:
            return None
        out[sel, :w] = values.reshape(-1, w)
    return out


def _fast_obj_vertices(data: bytes) -> np.ndarray | None:
    """(V, 3) positions of an OBJ file's ``v`` statements, or None (see :func:`_fast_obj`)."""
    if not _obj_prefilter(data):
        return None
    simple = _simple_obj_vertices(data)
    if simple is not None:
        return simple
    tok = _Tokens(data)
    return _fast_floats(tok, np.flatnonzero(tok.tag == np.uint64(_TAG_V)), 3)


def _simple_obj_vertices(data: bytes) -> np.ndarray | None:
    """Positions of a file whose vertices are all written ``v x y z`` (one space apart, at the
    line start, no comments), found from the line starts alone without cutting the rest of the
    file (faces are most of it) into tokens; None for any other layout."""
    if b"#" in data:
        return None
    buf = np.frombuffer(data, dtype=np.uint8)
    # the lines after the last one starting with "v" (the faces, most of the file) are left
    # alone where none of them is indented (so none can be a vertex)
    last = data.rfind(b"\nv")
    stop = data.find(b"\n", last + 1) if last >= 0 else -1
    if stop >= 0 and data.find(b"\n ", stop) < 0 and data.find(b"\n\t", stop) < 0:
        buf = buf[:stop + 1]
    n = buf.shape[0]
    line_end = np.flatnonzero(buf == 10)
    if n == 0 or line_end.shape[0] == 0:
        return None
    starts = np.concatenate([[0], line_end + 1])
    ends = np.concatenate([line_end, [n]])
    keep = starts < n
    starts, ends = starts[keep], ends[keep]
    first = buf[starts]
    if ((first == 32) | (first == 9)).any() or (first[-1] == 118 and starts[-1] + 1 == n):
        return None  # indented statements, or a bare "v" ending the file
    second = buf[np.minimum(starts + 1, n - 1)]
    is_v = (first == 118) & (starts + 1 < n) & ((second == 32) | (second == 9) | (second == 10) | (second == 13))
    v_start, v_end = starts[is_v] + 2, ends[is_v]
    if v_start.shape[0] == 0 or (second[is_v] != 32).any():
        return None
    v_end = v_end - (buf[v_end - 1] == 13)  # CRLF
    chars = _gather_spans(buf, v_start, v_end - v_start)
    chars[chars == 32] = 44  # "x y z" -> "x,y,z,"; doubled spaces or more numbers fail the count
    values = _parse_numbers(chars, 3 * v_start.shape[0], np.float64, _OBJ_LUT_FLOAT)
    return None if values is None else values.reshape(-1, 3)


def _fast_obj(data: bytes, path: Path) -> Mesh | None:
    """The mesh of an OBJ file as :func:`_parse_obj_lists` reads it, or None where it might not."""
    if not _obj_prefilter(data):
        return None
    tok = _Tokens(data)
    tag = tok.tag
    is_v = tag == np.uint64(_TAG_V)
    is_vt = tag == np.uint64(_TAG_VT)
    is_f = (tag == np.uint64(_TAG_F)) | (tag == np.uint64(_TAG_FO))
    is_g = (tag == np.uint64(_TAG_G)) | (tag == np.uint64(_TAG_O))
    other = ~(is_v | is_vt | is_f | is_g)
    if other.any():
        for key in np.unique(tag[other]):
            if key == 0:  # a tag of 8 or more characters
                return None
            length = int(key >> np.uint64(56))
            name = bytes((int(key) >> (8 * k)) & 255 for k in range(length))
            if name.decode("ascii", errors="replace") not in _OBJ_IGNORED:
                return None
    v_stmt, vt_stmt, f_stmt = np.flatnonzero(is_v), np.flatnonzero(is_vt), np.flatnonzero(is_f)
    vertices = _fast_floats(tok, v_stmt, 3)
    uvs = _fast_floats(tok, vt_stmt, 2, pad_second=True)
    if vertices is None or uvs is None:
        return None

    # faces: every corner token after the tags
    sizes = tok.count[f_stmt] - 1
    if (sizes < 3).any():
        return None
    n_faces = f_stmt.shape[0]
    offsets = np.zeros(n_faces + 1, dtype=np.int64)
    np.cumsum(sizes, out=offsets[1:])
    corner_face = np.repeat(np.arange(n_faces), sizes)
    corners = tok.head[f_stmt][corner_face] + (np.arange(offsets[-1]) - offsets[corner_face]) + 1
    # corner layout: every corner token must have the same number of slashes (0, 1 or 2)
    lens = tok.end[corners] - tok.start[corners]
    chars = tok.gather(corners)  # "v/t/n," per corner
    at = np.cumsum(lens + 1) - (lens + 1)  # where each corner starts in chars
    slash = np.flatnonzero(chars == 47)
    n_corners = corners.shape[0]
    if n_corners == 0 or slash.shape[0] % n_corners:
        return None  # no faces: the reader above says so
    n = slash.shape[0] // n_corners
    if n > 2:
        return None  # more fields: the reader above sorts them out
    for j in range(n):  # slash k·n + j must lie in corner k: no corner has more or fewer
        if not ((slash[j::n] > at) & (slash[j::n] < at + lens)).all():
            return None
    double = n == 2 and bool((slash[1::2] - slash[0::2] == 1).any())
    if double:  # v//vn: only the vertex field is wanted (the reader above reads no normals either)
        if not (slash[1::2] - slash[0::2] == 1).all():
            return None  # some v/vt/vn and some v//vn corners
        chars = _gather_spans(chars, at, slash[0::2] - at)
        fields = 1
    else:
        chars[slash] = 44  # v/vt and v/vt/vn: every field is a number, one parse for all
        fields = n + 1
    raw = _parse_numbers(chars, n_corners * fields, np.int64, _OBJ_LUT_INT)
    if raw is None:
        return None
    raw = raw.reshape(n_corners, fields)
    face_line = tok.stmt_line[f_stmt]
    v_before = np.searchsorted(tok.stmt_line[v_stmt], face_line)[corner_face]
    corner_v = _fast_indices(raw[:, 0], v_before, v_stmt.shape[0])
    if corner_v is None:
        return None
    polygon_uvs = None
    if fields >= 2:
        t_before = np.searchsorted(tok.stmt_line[vt_stmt], face_line)[corner_face]
        polygon_uvs = _fast_indices(raw[:, 1], t_before, vt_stmt.shape[0])
        if polygon_uvs is None:
            return None

    # groups: g/o statements are few; their names as the reader above makes them
    group_names = ["default"]
    polygon_groups = np.zeros(n_faces, dtype=np.int32)
    g_stmt = np.flatnonzero(is_g)
    if g_stmt.shape[0]:
        group_index = {"default": 0}
        ids = np.empty(g_stmt.shape[0], dtype=np.int32)
        for k, s in enumerate(g_stmt):
            head = tok.head[s]
            parts = [tok.text(t).decode("utf-8", errors="replace") for t in range(head + 1, head + tok.count[s])]
            name = " ".join(" ".join(parts).split()) or "default"
            if name not in group_index:
                group_index[name] = len(group_names)
                group_names.append(name)
            ids[k] = group_index[name]
        which = np.searchsorted(tok.stmt_line[g_stmt], face_line) - 1
        polygon_groups = np.where(which >= 0, ids[np.maximum(which, 0)], 0).astype(np.int32)
    return Mesh(
        vertices=vertices,
        polygon_offsets=offsets,
        polygon_vertices=corner_v,
        uvs=uvs if polygon_uvs is not None else None,
        polygon_uvs=polygon_uvs,
        polygon_groups=polygon_groups,
        group_names=group_names,
        path=str(path),
    )


def _fast_indices(raw: np.ndarray, count_before: np.ndarray, count_total: int) -> np.ndarray | None:
    idx = np.where(raw > 0, raw - 1, count_before + raw)
    if ((raw == 0) | (idx < 0) | (idx >= count_total)).any():
        return None
    return idx


def _load_with_trimesh(path: Path) -> Mesh:
    import trimesh

    if path.stat().st_size == 0:
        raise InputError("the file is empty", path=path, hint="re-export the mesh")
    try:
        loaded = trimesh.load(path, process=False, maintain_order=True)
        if isinstance(loaded, trimesh.Scene):
            # glTF and friends: the scene's meshes in one, placed by their transforms
            loaded = loaded.to_mesh() if hasattr(loaded, "to_mesh") else loaded.dump(concatenate=True)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(f"cannot read mesh: {type(exc).__name__}: {exc}", path=path,
                         hint="is the file complete and in the format its extension says?") from None
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    uvs = None
    polygon_uvs = None
    visual_uv = getattr(getattr(loaded, "visual", None), "uv", None)
    if visual_uv is not None and len(visual_uv) == len(vertices):
        uvs = np.asarray(visual_uv, dtype=np.float64)
        polygon_uvs = faces.reshape(-1).copy()
    return Mesh(
        vertices=vertices,
        polygon_offsets=np.arange(0, 3 * len(faces) + 1, 3, dtype=np.int64),
        polygon_vertices=faces.reshape(-1),
        uvs=uvs,
        polygon_uvs=polygon_uvs,
        polygon_groups=np.zeros(len(faces), dtype=np.int32),
        group_names=["default"],
        path=str(path),
    )


def load_vertices(path: str | os.PathLike) -> np.ndarray:
    """Vertex positions (V, 3) float64 of a mesh file (for example poses).

    An OBJ file's ``v`` statements are read alone (its faces are not parsed nor checked: a
    pose only needs positions in the rest mesh's order); files the fast path declines, and
    other formats, go through :func:`load_mesh`.
    """
    path = Path(path)
    if path.suffix.lower() == ".obj" and path.is_file():
        vertices = _fast_obj_vertices(_read_obj_bytes(path))
        if vertices is not None and len(vertices):
            return vertices
    return load_mesh(path).vertices


# ----------------------------------------------------------------------------------------------
# writing
#
# Writing an OBJ sequence is dominated by turning floats into text. printf-style formatting
# costs a Python-level conversion per number; here the digits are computed with integer array
# arithmetic into a byte matrix, and the unused cells (leading zeros, trailing zeros, missing
# signs) are masked out before one ``tobytes``: no per-number Python work at all.

_POW10 = 10 ** np.arange(19, dtype=np.int64)
_POW10F = 10.0 ** np.arange(19)
# every 4-digit group as 4 ASCII bytes, one row per byte (a column per group value), and the
# group's count of trailing zeros
_DIGITS4 = np.ascontiguousarray(
    np.frombuffer(b"".join(b"%04d" % i for i in range(10000)), dtype=np.uint8).reshape(10000, 4).T
)
_TRAILING4 = np.array([4 if i == 0 else len(str(i)) - len(str(i).rstrip("0")) for i in range(10000)],
                      dtype=np.int64)
_MINUS, _DOT, _SPACE, _NEWLINE = (ord(c) for c in "-. \n")

# significant digits written per coordinate: 9 round-trips every float32 exactly
OBJ_SIGNIFICANT_DIGITS = 9
# digits (integer and decimal places) per number: the absolute precision floor for tiny values
# next to large ones is 1e-15 x the block's largest magnitude, far below a float32 ulp, and the
# digit arithmetic stays within int64
_MAX_DIGITS = 17


def _digit_rows(q: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Zero-padded decimal digits of non-negative integers, one row per digit position.

    Parameters
    ----------
    q : (m,) int64, 0 <= q < 10**width
    width : int

    Returns
    -------
    digits : (width, m) uint8 ASCII, most significant row first
    trailing : (m,) int64 trailing zeros of each number (``4 * ceil(width / 4)`` for 0)
    """
    m = q.shape[0]
    n4 = -(-width // 4)
    out = np.empty((4 * n4, m), dtype=np.uint8)
    trailing = np.zeros(m, dtype=np.int64)
    zero_so_far = np.ones(m, dtype=bool)
    rest = q.copy()
    # four digits per table look-up: a quarter of the integer divisions of digit-by-digit
    for c in range(n4 - 1, -1, -1):
        group = rest % 10000
        np.take(_DIGITS4, group, axis=1, out=out[4 * c:4 * c + 4])
        trailing += np.where(zero_so_far, _TRAILING4[group], 0)
        zero_so_far &= group == 0
        if c:
            rest //= 10000
    return out[4 * n4 - width:], trailing


def _int_digits(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Decimal digits of non-negative integers, right-aligned, one row per number.

    Parameters
    ----------
    q : (n,) int64, >= 0

    Returns
    -------
    chars : (n, W) uint8 ASCII digits, W = digits of ``q.max()``
    mask : (n, W) bool, False on leading zeros (the units digit is always kept)
    """
    n_cols = max(1, int(np.searchsorted(_POW10, int(q.max(initial=0)), side="right")))
    chars = np.ascontiguousarray(_digit_rows(q, n_cols)[0].T)
    # column j holds 10**(n_cols-1-j): shown when q reaches that power; the units always
    mask = q[:, None] >= _POW10[n_cols - 1::-1][None, :]
    mask[:, -1] = True
    return chars, mask


def _number_rows(x: np.ndarray, significant: int) -> np.ndarray | None:
    """Shortest fixed-point text of floats, one row per character position.

    Like ``%.{significant}g`` without exponent notation, trailing zeros dropped. The digits
    are computed in int64 with at most ``_MAX_DIGITS`` per number, so values below about
    ``10**(significant - 16)`` times the block's largest magnitude are written to an absolute
    precision of ``1e-15`` times the largest instead of to ``significant`` digits.

    Parameters
    ----------
    x : (m,) float64
    significant : int, 1..15

    Returns
    -------
    (W, m) uint8: column i spells ``x[i]`` (sign, integer digits, point, decimals) with NUL
    bytes in the unused cells; or None when a value is non-finite, or the largest is >= 1e15
    or below 1e-5 (the caller falls back to printf formatting).
    """
    m = x.shape[0]
    a = np.abs(x)
    a_max = float(a.max()) if m else 0.0
    if m == 0 or not np.isfinite(a_max) or a_max >= 1e15 or 0 < a_max < 1e-5:
        return None
    # integer digits of the largest value, one more in case rounding carries (9.99.. -> 10)
    n_int = max(1, int(np.floor(np.log10(a_max))) + 2) if a_max > 0 else 1
    with np.errstate(divide="ignore"):
        exponent = np.floor(np.log10(a))
    exponent[a == 0] = 0
    decimals = np.clip(significant - 1 - exponent.astype(np.int64), 0, max(_MAX_DIGITS - n_int, 0))
    q = (a * _POW10F[decimals] + 0.5).astype(np.int64)
    n_dec = int(decimals.max())
    # align every value on n_dec decimals: one digit layout for the whole block
    q *= _POW10[n_dec - decimals]
    n_int = max(1, int(np.searchsorted(_POW10, int(q.max()) // _POW10[n_dec], side="right")))
    digits, trailing = _digit_rows(q, n_int + n_dec)
    shown_dec = n_dec - trailing  # negative for zero: no decimals shown

    rows = np.empty((n_int + n_dec + 2, m), dtype=np.uint8)
    np.multiply((x < 0) & (q > 0), _MINUS, out=rows[0], casting="unsafe")
    rows[1:n_int + 1] = digits[:n_int]
    for i in range(n_int - 1):  # leading zeros of the integer part (the units digit stays)
        rows[1 + i] *= q >= _POW10[n_dec + n_int - 1 - i]
    np.multiply(shown_dec > 0, _DOT, out=rows[n_int + 1], casting="unsafe")
    rows[n_int + 2:] = digits[n_int:]
    for i in range(n_dec):  # trailing zeros of the decimals
        rows[n_int + 2 + i] *= shown_dec > i
    return rows


def _format_rows(tag: bytes, values: np.ndarray) -> bytes:
    """OBJ rows ``tag x y z`` for a (n, k) float block, one per line, ``\\n`` terminated.

    Numbers carry :data:`OBJ_SIGNIFICANT_DIGITS` significant digits (every float32 survives
    the round trip) and no exponent. The text is built column-wise in a byte matrix with NUL
    in unused cells, transposed once and the NULs dropped by ``bytes.translate``: no
    per-number Python work, 2-3x faster than one printf over the block.

    Parameters
    ----------
    tag : bytes, e.g. ``b"v"`` or ``b"vt"``
    values : (n, k) float

    Returns
    -------
    bytes

    Example
    -------
    >>> _format_rows(b"v", np.array([[1.5, -2.0, 0.0]]))
    b'v 1.5 -2 0\\n'
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2:
        values = values.reshape(values.shape[0], -1)
    n, k = values.shape
    if n == 0:
        return b""
    # coordinate-major, so that every coordinate's numbers are one contiguous slice
    x = values.T.reshape(-1)
    rows = _number_rows(x, OBJ_SIGNIFICANT_DIGITS)
    if rows is None:
        # NaN/inf or huge values: printf, one % over the whole block
        fmt = tag.decode() + f" %.{OBJ_SIGNIFICANT_DIGITS}g" * k
        return ("\n".join([fmt] * n) % tuple(values.ravel().tolist()) + "\n").encode()
    w = rows.shape[0]
    head = len(tag)
    text = np.empty((head + k * (w + 1) + 1, n), dtype=np.uint8)
    text[:head] = np.frombuffer(tag, dtype=np.uint8)[:, None]
    for j in range(k):
        o = head + j * (w + 1)
        text[o] = _SPACE
        text[o + 1:o + 1 + w] = rows[:, j * n:(j + 1) * n]
    text[-1] = _NEWLINE
    return np.ascontiguousarray(text.T).tobytes().translate(None, b"\0")


def _assemble_rows(prefix: bytes, cells: list[tuple[np.ndarray, np.ndarray]],
                   separators: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Byte matrix and mask of text rows ``prefix sep0 cell0 sep1 cell1 ... \\n``.

    Parameters
    ----------
    prefix : bytes written at the start of every row
    cells : list of (chars (n, W_k) uint8, mask (n, W_k) bool), one per column
    separators : one byte per column, written before it

    Returns
    -------
    chars (n, W) uint8 and mask (n, W) bool; ``chars[mask].tobytes()`` is the text.
    """
    n = cells[0][0].shape[0]
    parts_c = [np.broadcast_to(np.frombuffer(prefix, np.uint8), (n, len(prefix)))]
    parts_m = [np.ones((n, len(prefix)), dtype=bool)]
    for sep, (c, m) in zip(separators, cells, strict=True):
        parts_c += [np.full((n, 1), sep, np.uint8), c]
        parts_m += [np.ones((n, 1), dtype=bool), m]
    parts_c.append(np.full((n, 1), _NEWLINE, np.uint8))
    parts_m.append(np.ones((n, 1), dtype=bool))
    return np.concatenate(parts_c, axis=1), np.concatenate(parts_m, axis=1)


def format_obj_faces(mesh: Mesh) -> bytes:
    """The ``f`` lines of an OBJ (1-based, ``v/vt`` when the mesh has UVs), formatted once.

    ``g`` lines are written where the polygon group changes when the mesh has named groups.
    Vectorised per polygon size, so a sequence of frames formats the topology only once.

    Parameters
    ----------
    mesh : Mesh

    Returns
    -------
    bytes, ``\\n``-terminated lines in polygon order.
    """
    sizes = mesh.polygon_sizes
    n_poly = mesh.n_polygons
    if n_poly == 0:
        return b""
    v = np.asarray(mesh.polygon_vertices, dtype=np.int64) + 1
    t = None if mesh.polygon_uvs is None else np.asarray(mesh.polygon_uvs, dtype=np.int64) + 1
    v_chars = _int_digits(v)
    t_chars = None if t is None else _int_digits(t)

    # one byte matrix per polygon size, then every row is scattered to its place in the file
    blocks = []
    line_len = np.zeros(n_poly, dtype=np.int64)
    for size in np.unique(sizes):
        idx = np.flatnonzero(sizes == size)
        cols = mesh.polygon_offsets[idx][:, None] + np.arange(size)[None, :]
        cells, seps = [], b""
        for j in range(size):
            cells.append((v_chars[0][cols[:, j]], v_chars[1][cols[:, j]]))
            seps += b" "
            if t_chars is not None:
                cells.append((t_chars[0][cols[:, j]], t_chars[1][cols[:, j]]))
                seps += b"/"
        chars, mask = _assemble_rows(b"f", cells, seps)
        line_len[idx] = mask.sum(axis=1)
        blocks.append((idx, chars, mask))

    group_lines = _group_lines(mesh)
    head_len = np.zeros(n_poly, dtype=np.int64)
    for k, text in group_lines.items():
        head_len[k] = len(text)
    total = head_len + line_len
    end = np.cumsum(total)
    start = end - line_len
    out = np.empty(int(end[-1]), dtype=np.uint8)
    for idx, chars, mask in blocks:
        pos = start[idx][:, None] + np.cumsum(mask, axis=1, dtype=np.int64) - 1
        out[pos[mask]] = chars[mask]
    for k, text in group_lines.items():
        s = int(start[k] - head_len[k])
        out[s:s + len(text)] = np.frombuffer(text, np.uint8)
    return out.tobytes()


def _group_lines(mesh: Mesh) -> dict[int, bytes]:
    """``g NAME`` lines keyed by the first polygon of each run of one group."""
    groups = mesh.polygon_groups
    names = mesh.group_names
    if groups is None or len(groups) == 0 or not names:
        return {}
    groups = np.asarray(groups)
    used = np.unique(groups)
    if used.min() < 0 or used.max() >= len(names) or all(names[int(g)] == "default" for g in used):
        return {}  # unnamed (or inconsistent) groups: write none rather than invent names
    starts = np.flatnonzero(np.r_[True, groups[1:] != groups[:-1]])
    return {int(k): f"g {names[int(groups[k])]}\n".encode() for k in starts}


def format_obj_header(mesh: Mesh) -> bytes:
    """The ``vt`` lines of an OBJ (empty without UVs)."""
    if mesh.uvs is None or mesh.polygon_uvs is None:
        return b""
    return _format_rows(b"vt", mesh.uvs)


def obj_bytes(mesh: Mesh, vertices: np.ndarray | None = None, faces_block: bytes | None = None,
              uv_block: bytes | None = None) -> bytes:
    """A whole OBJ file as bytes; pass pre-formatted blocks to reuse them across frames.

    Parameters
    ----------
    mesh : Mesh, the topology, UVs and groups
    vertices : (V, 3) float, positions to write instead of ``mesh.vertices``
    faces_block, uv_block : bytes from :func:`format_obj_faces` / :func:`format_obj_header`

    Returns
    -------
    bytes
    """
    vertices = mesh.vertices if vertices is None else vertices
    faces_block = format_obj_faces(mesh) if faces_block is None else faces_block
    uv_block = format_obj_header(mesh) if uv_block is None else uv_block
    return b"".join([_format_rows(b"v", vertices), uv_block, faces_block])


def save_obj(path: str | os.PathLike, mesh: Mesh, vertices: np.ndarray | None = None) -> None:
    """Write ``mesh`` (or its topology with other ``vertices`` (V, 3)) as OBJ, atomically."""
    from facepipe.io.atomic import atomic_open

    with atomic_open(path, "wb") as fh:
        fh.write(obj_bytes(mesh, vertices))


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
    problems: list[str] = []
    V = np.asarray(mesh.vertices)
    n_v = V.shape[0]
    if V.ndim != 2 or V.shape[1] != 3:
        raise InputError(f"vertices have shape {V.shape}, expected (V, 3)", path=where)
    offsets = np.asarray(mesh.polygon_offsets, dtype=np.int64)
    pv = np.asarray(mesh.polygon_vertices, dtype=np.int64)
    sizes = np.diff(offsets)
    n_poly = sizes.shape[0]

    finite = np.isfinite(V).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        problems.append(
            f"{len(bad)} vertices have NaN or infinite coordinates: vertex {_first(bad)} "
            f"(vertex {int(bad[0])} is {V[bad[0]].tolist()})"
        )
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
    if small.size or out.any():
        # the remaining checks index vertices through the polygons: they would fail or mislead
        _raise_problems(problems, where)

    repeated_poly = _polygons_with_repeats(offsets, pv, sizes)
    if repeated_poly.any():
        bad = np.flatnonzero(repeated_poly)
        k = int(bad[0])
        problems.append(
            f"{len(bad)} polygons use a vertex twice: polygon {_first(bad)} (polygon {k} has vertices "
            f"{pv[offsets[k]:offsets[k + 1]].tolist()}); remove the repeated corner"
        )

    if n_poly:
        faces, face_poly = triangulate(offsets, pv)
    else:
        faces, face_poly = np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64)
    if faces.shape[0] and finite.all():
        a, b, c = V[faces[:, 0]], V[faces[:, 1]], V[faces[:, 2]]
        double_area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
        mean_e2 = float(np.mean(np.concatenate([((b - a) ** 2).sum(1), ((c - b) ** 2).sum(1),
                                                 ((a - c) ** 2).sum(1)])))
        tiny = (0.5 * double_area <= area_tolerance * mean_e2) & ~repeated_poly[face_poly]
        if tiny.any():
            bad_t = np.flatnonzero(tiny)
            bad_p = np.unique(face_poly[bad_t])
            t = int(bad_t[0])
            k = int(face_poly[t])
            problems.append(
                f"{len(bad_p)} polygons have a zero-area (degenerate) triangle: polygon {_first(bad_p)} "
                f"(polygon {k}, vertices {pv[offsets[k]:offsets[k + 1]].tolist()}, triangle "
                f"{faces[t].tolist()} has area {0.5 * double_area[t]:.3g}, below "
                f"{area_tolerance:g} x mean squared edge length {mean_e2:.3g}); "
                "collapse or re-triangulate it"
            )

    if faces.shape[0]:
        e = triangle_edges(faces)
        key = e[:, 0] * n_v + e[:, 1]
        skey = np.sort(key)
        # runs of equal keys in the sorted list: their lengths are the edges' face counts
        starts = np.flatnonzero(np.r_[True, skey[1:] != skey[:-1]])
        counts = np.diff(np.r_[starts, skey.shape[0]])
        over = np.flatnonzero(counts > 2)
        if over.size:
            k = int(over[0])
            i, j = divmod(int(skey[starts[k]]), n_v)
            using = np.unique(face_poly[np.flatnonzero(key == skey[starts[k]]) % len(faces)])
            problems.append(
                f"{len(over)} non-manifold edges: edge ({i}, {j}) is used by {int(counts[k])} triangles "
                f"(polygons {_first(using)}); an edge may be shared by at most two faces"
            )
        # the same triangle twice (possibly with another winding) passes the edge test at a border
        tri = np.sort(faces, axis=1)
        if n_v < 2_000_000:  # one int64 key per triangle: a 1-D sort instead of a 3-key lexsort
            tkey = (tri[:, 0] * n_v + tri[:, 1]) * n_v + tri[:, 2]
            order = np.argsort(tkey)
            same = tkey[order][1:] == tkey[order][:-1]
        else:
            order = np.lexsort((tri[:, 2], tri[:, 1], tri[:, 0]))
            same = (tri[order][1:] == tri[order][:-1]).all(axis=1)
        if same.any():
            d = int(np.argmax(same))
            p, q = sorted((int(face_poly[order[d]]), int(face_poly[order[d + 1]])))
            problems.append(
                f"{int(same.sum())} duplicated triangles: polygons {p} and {q} both cover triangle "
                f"{tri[order[d]].tolist()}; delete the duplicate face"
            )

    used = np.bincount(pv, minlength=n_v) > 0
    if not used.all():
        bad = np.flatnonzero(~used)
        problems.append(
            f"{len(bad)} vertices are used by no face: vertex {_first(bad, 10)}; remove them (from the "
            "rest mesh and every example pose alike) or reference them from faces"
        )
    _raise_problems(problems, where)


def _polygons_with_repeats(offsets: np.ndarray, pv: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """(N,) bool: polygons that list a vertex more than once."""
    n_poly = sizes.shape[0]
    if n_poly == 0:
        return np.zeros(0, dtype=bool)
    corner_poly = np.repeat(np.arange(n_poly, dtype=np.int64), sizes)
    max_size = int(sizes.max())
    repeated = np.zeros(n_poly, dtype=bool)
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
                     *, path: str | os.PathLike | None = None) -> tuple[int, np.ndarray]:
    """Check that every connected part of the mesh holds at least one constrained vertex.

    The shell energy is invariant to moving a part rigidly (k_bend only: affinely), so a part
    without a handle or anchor makes the linear system singular.

    Parameters
    ----------
    mesh : Mesh
    constrained_vertices : (K,) int, vertex indices of handles and anchors
    what : str, how the message names a constrained vertex
    path : file named in the message; defaults to ``mesh.path``.

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
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    where = _where(mesh, path)
    n_v = mesh.n_vertices
    cv = np.asarray(constrained_vertices, dtype=np.int64).ravel()
    out = (cv < 0) | (cv >= n_v)
    if out.any():
        raise InputError(f"{what} vertex {int(cv[np.argmax(out)])} is out of range: the mesh has "
                         f"{n_v} vertices (0..{n_v - 1})", path=where)
    # two edges per triangle connect its corners; duplicates do not matter for connectivity,
    # so the (slow) de-duplication of the edge list is skipped
    f = mesh.faces
    rows = np.concatenate([f[:, 0], f[:, 1]])
    cols = np.concatenate([f[:, 1], f[:, 2]])
    graph = coo_matrix((np.ones(rows.shape[0], dtype=np.int32), (rows, cols)), shape=(n_v, n_v)).tocsr()
    n_comp, labels = connected_components(graph, directed=True, connection="weak")
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
            hint=f"put a {what} on every separate part, or remove the part from the rest mesh "
                 "and every example pose",
        )
    return int(n_comp), labels.astype(np.int32)


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
