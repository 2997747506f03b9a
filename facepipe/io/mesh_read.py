"""Reading meshes: OBJ with facepipe's own reader, other formats through trimesh.

trimesh re-indexes vertices at UV seams and triangulates on load, so OBJ files are read here
(the format is a few line types), keeping the artist's polygons, per-corner UVs and groups in
the file's vertex order; PLY and other formats go through trimesh with ``process=False`` so
that vertex order is kept. Every kind of malformed file is an
:class:`~facepipe.errors.InputError` naming the line.
"""

from __future__ import annotations

import io
import os
import re
from pathlib import Path

import numpy as np

from facepipe.core.mesh import Mesh
from facepipe.errors import InputError


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
    data = _read_obj_bytes(path)
    mesh = _fast_obj(data, path)  # numpy over the bytes: far faster on large meshes
    if mesh is not None:
        return mesh
    return _parse_obj_lists(path, data)


def _read_obj_bytes(path: Path) -> bytes:
    data = path.read_bytes()
    if not data or data.isspace():  # (not strip(): a copy of the whole file to test for blanks)
        raise InputError("the file is empty", path=path, hint="re-export the mesh")
    nul = data.find(b"\0")
    if nul >= 0:
        raise InputError(
            f"binary data at byte {nul}: this is not a text OBJ file",
            path=path,
            hint="export the mesh as a text OBJ, or give the file its real extension (e.g. .ply)",
        )
    return data


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
    except (ValueError, OverflowError):
        for k, t in enumerate(tokens):
            try:
                value = int(t)
            except ValueError:
                fail(f_line[int(corner_face[k])], f"bad {what} index {t!r}")
            if abs(value) > np.iinfo(np.int64).max:  # a number, but no file has that many
                fail(f_line[int(corner_face[k])], f"{what} index {t} is out of range: the file has {count_total} "
                     f"{'vertices' if what == 'vertex' else 'texture coordinates'}")
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
# The reader above builds Python lists of every statement's tokens, slow on large meshes.
# The fast path below does the same work on numpy arrays over the file's bytes: token
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
    text = chars.tobytes().rstrip(b",")  # every field is followed by a comma
    try:
        # NumPy stops at the first field it cannot parse (raising, or on older versions warning
        # and returning the numbers before it): a short count declines the file
        values = np.fromstring(text, dtype=dtype, sep=",")  # noqa: NPY201 - text mode
    except ValueError:
        return None
    if values.shape[0] != count or not _plain_number(text[text.rfind(b",") + 1:], dtype):
        return None  # the last field can end in garbage that the count does not show
    return values


def _plain_number(field: bytes, dtype) -> bool:
    try:
        (int if np.issubdtype(dtype, np.integer) else float)(field)
    except ValueError:
        return False
    return True


_FLOAT_BYTES = b"0123456789+-.eE \n"
_INT_BYTES = b"0123456789+- \n"
_SLASH_TO_SPACE = bytes.maketrans(b"/", b" ")


def _block_numbers(data: bytes, begin: int, end: int, tag: bytes, lines: int, width: int, dtype,
                   slashes: bool = False) -> np.ndarray | None:
    """(lines · width,) numbers of the whole lines ``data[begin:end]``, each ``tag`` and then
    ``width`` numbers one space apart (``a/b`` corners read as two with ``slashes``), or None
    unless every field is one plain number (as :func:`_parse_numbers` reads them).

    A contiguous block is handed to NumPy's text reader whole, without gathering its fields
    first: on a large mesh about twice as fast. The caller has checked the number of fields
    per line; here every byte but the tags must belong to a number (no ``nan``, ``inf`` or
    hexadecimal, which the reference reader treats its own way).
    """
    block = data[begin:end]
    if slashes:
        block = block.translate(_SLASH_TO_SPACE)
    allowed = _INT_BYTES if np.issubdtype(dtype, np.integer) else _FLOAT_BYTES
    if block.translate(None, allowed) != tag * lines:
        return None
    try:
        values = np.loadtxt(io.BytesIO(block), dtype=dtype, usecols=range(1, width + 1), ndmin=2, comments=None)
    except ValueError:
        return None
    return values.ravel() if values.shape == (lines, width) else None


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
    block = _block_lines(is_v)
    if block is not None:  # one run of lines: read whole where each has three fields
        begin, end = int(starts[block[0]]), int(ends[block[1] - 1]) + 1
        lines = block[1] - block[0]
        if data.count(b" ", begin, end) == 3 * lines and data.find(b"\r", begin, end) < 0:
            values = _block_numbers(data, begin, end, b"v", lines, 3, np.float64)
            return None if values is None else values.reshape(-1, 3)
    v_end = v_end - (buf[v_end - 1] == 13)  # CRLF
    # two spaces in each line after the tag's: a line of two numbers beside one of four would
    # otherwise pass the total count with its numbers shifted into the next vertex
    spaces = np.flatnonzero(buf == 32)
    if not (np.searchsorted(spaces, v_end) - np.searchsorted(spaces, v_start) == 2).all():
        return None
    chars = _gather_spans(buf, v_start, v_end - v_start)
    chars[chars == 32] = 44  # "x y z" -> "x,y,z,"
    values = _parse_numbers(chars, 3 * v_start.shape[0], np.float64, _OBJ_LUT_FLOAT)
    return None if values is None else values.reshape(-1, 3)


def _block_lines(is_line: np.ndarray) -> tuple[int, int] | None:
    """The first and past-the-last line of the one contiguous run of lines ``is_line`` marks
    ((0, 0) where it marks none), or None where they are not contiguous."""
    lines = np.flatnonzero(is_line)
    if lines.shape[0] == 0:
        return 0, 0
    if lines[-1] - lines[0] + 1 != lines.shape[0]:
        return None
    return int(lines[0]), int(lines[-1]) + 1


def _per_line(positions: np.ndarray, starts: np.ndarray, ends: np.ndarray, block: tuple[int, int], k: int) -> bool:
    """Whether each line of ``block`` holds exactly ``k`` of the byte at ``positions`` (sorted byte
    offsets of every occurrence in the file): the block's occurrences, taken k at a time, must
    each lie in the next line (one comparison per occurrence, no count per line)."""
    a, b = block
    if a == b:
        return True
    lo, hi = np.searchsorted(positions, [starts[a], ends[b - 1]])
    inside = positions[lo:hi]
    if inside.shape[0] != k * (b - a):
        return False
    if k == 0:
        return True
    line = a + np.arange(inside.shape[0]) // k
    return bool(((inside > starts[line]) & (inside < ends[line])).all())


def _plain_obj(data: bytes, path: Path) -> Mesh | None:
    """The mesh of an OBJ file in the plain layout most exporters write, found from its line
    starts alone (the token reader below cuts every file into tokens first: most of its time on a
    large mesh); None for any other layout, which that reader then reads.

    The plain layout: ``\\n`` line ends, no comments or tabs, every line a statement at its start
    with single spaces; a block of ``v x y z`` lines, one of ``vt u v`` lines and one of ``vn``
    lines (ignored), then only ``f`` lines, all with the same number of corners and the same
    corner layout (``v``, ``v/vt`` or ``v/vt/vn``).
    """
    if b"#" in data or b"\r" in data or b"\t" in data or not data.endswith(b"\n"):
        return None
    buf = np.frombuffer(data, dtype=np.uint8)
    n = buf.shape[0]
    ends = np.flatnonzero(buf == 10)
    starts = np.concatenate([[0], ends[:-1] + 1])
    first = buf[starts]
    second = buf[np.minimum(starts + 1, n - 1)]
    third = buf[np.minimum(starts + 2, n - 1)]
    is_f = (first == 102) & (second == 32)
    is_v = (first == 118) & (second == 32)
    is_vt = (first == 118) & (second == 116) & (third == 32)
    is_vn = (first == 118) & (second == 110) & (third == 32)
    if not (is_f | is_v | is_vt | is_vn).all():
        return None  # groups, materials, smoothing, blank lines: the token reader keeps or skips them
    blocks = [_block_lines(m) for m in (is_v, is_vt, is_vn, is_f)]
    if any(b is None for b in blocks):
        return None
    v_block, vt_block, vn_block, f_block = blocks
    n_faces = f_block[1] - f_block[0]
    if n_faces == 0 or f_block[1] != starts.shape[0] or max(v_block[1], vt_block[1], vn_block[1]) > f_block[0]:
        return None  # no faces, or faces before a vertex (relative indices count back from each face)
    spaces = np.flatnonzero(buf == 32)
    slashes = np.flatnonzero(buf[int(starts[f_block[0]]):] == 47) + int(starts[f_block[0]])
    face = f_block[0]
    corners = int(np.searchsorted(spaces, ends[face]) - np.searchsorted(spaces, starts[face]))
    per_corner = int(np.searchsorted(slashes, ends[face]) - np.searchsorted(slashes, starts[face]))
    if corners < 3 or per_corner % corners or per_corner // corners > 2:
        return None
    fields = per_corner // corners + 1
    if not (_per_line(spaces, starts, ends, v_block, 3) and _per_line(spaces, starts, ends, vt_block, 2)
            and _per_line(spaces, starts, ends, f_block, corners)
            and _per_line(slashes, starts, ends, f_block, per_corner)):
        return None  # more or fewer numbers than the token reader keeps, doubled spaces, v//vn corners

    def numbers(block, tag, width, dtype):
        lines = block[1] - block[0]
        if lines == 0:
            return np.zeros(0, dtype=dtype)
        # the block's lines were checked above: each its tag, one space, and width fields
        return _block_numbers(data, int(starts[block[0]]), int(ends[block[1] - 1]) + 1, tag, lines, width, dtype,
                              slashes=fields > 1 and tag == b"f")

    vertices = numbers(v_block, b"v", 3, np.float64)
    uvs = numbers(vt_block, b"vt", 2, np.float64)
    raw = numbers(f_block, b"f", corners * fields, np.int64)
    if vertices is None or uvs is None or raw is None:
        return None
    raw = raw.reshape(n_faces * corners, fields)
    n_v, n_vt = v_block[1] - v_block[0], vt_block[1] - vt_block[0]
    corner_v = _fast_indices(raw[:, 0], n_v, n_v)
    polygon_uvs = _fast_indices(raw[:, 1], n_vt, n_vt) if fields >= 2 else None
    if corner_v is None or (fields >= 2 and polygon_uvs is None):
        return None
    return Mesh(vertices=vertices.reshape(-1, 3), polygon_offsets=np.arange(n_faces + 1, dtype=np.int64) * corners,
                polygon_vertices=corner_v, uvs=uvs.reshape(-1, 2) if polygon_uvs is not None else None,
                polygon_uvs=polygon_uvs, polygon_groups=np.zeros(n_faces, dtype=np.int32),
                group_names=["default"], path=str(path))


def _fast_obj(data: bytes, path: Path) -> Mesh | None:
    """The mesh of an OBJ file as :func:`_parse_obj_lists` reads it, or None where it might not."""
    if not _obj_prefilter(data):
        return None
    plain = _plain_obj(data, path)
    if plain is not None:
        return plain
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
    import trimesh  # lazily: only formats other than OBJ need it (start-up)

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
