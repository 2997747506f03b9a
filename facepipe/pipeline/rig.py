"""The rig: the files a config names (rest mesh, markers, anchors, examples), loaded and validated.

The config itself is read by :mod:`facepipe.io.config`. Every problem is an InputError naming
the file, the line or key, and the fix.
"""

from __future__ import annotations

import csv
import glob
import hashlib
import json
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from facepipe.pipeline.background import BackgroundCall
from facepipe.errors import InputError
from facepipe.core.mesh import (Mesh, check_components, check_marker_vertices, check_mesh, check_pose,
                                coincident_vertices, weld_vertices)
from facepipe.io.config import Config, load_config
from facepipe.io.landmark_map import LandmarkMap, read_landmark_map
from facepipe.io.mesh_read import load_mesh, load_vertices

ROLES = ("handle", "stable", "ignore")
# example files of this many bytes in all are read by a second process (below, the start costs more)
EXAMPLES_IN_A_PROCESS = 64 * 2**20


@dataclass
class Markers:
    """Markers of the rig, in the file's order.

    names / vertices / roles for every row; ``handles`` selects those that drive the shell
    (every role but ``ignore``); ``stable`` flags, among the handles, those for head motion.
    """

    names: list[str]
    vertices: np.ndarray
    roles: list[str]

    @property
    def handle_mask(self) -> np.ndarray:
        return np.array([r != "ignore" for r in self.roles], dtype=bool)

    @property
    def handle_names(self) -> list[str]:
        return [n for n, r in zip(self.names, self.roles) if r != "ignore"]

    @property
    def handle_vertices(self) -> np.ndarray:
        return self.vertices[self.handle_mask]

    @property
    def stable(self) -> np.ndarray:
        return np.array([r == "stable" for r, keep in zip(self.roles, self.handle_mask) if keep], dtype=bool)


def name_vertex_rows(path, kind: str = "marker"):
    """Rows of a ``name,vertex[,…]`` CSV (header and ``#`` comments allowed), checked.

    Yields (line number, name, vertex, the remaining cells); names must be unique and vertices
    integers (their range is the caller's to check, against its mesh).
    """
    if not Path(path).is_file():
        raise InputError(f"{kind} file not found", path=path)
    seen = set()
    with open(path, newline="", encoding="utf-8") as fh:
        for line_no, row in enumerate(csv.reader(fh), start=1):
            row = [c.strip() for c in row]
            if not row or not any(row) or row[0].startswith("#"):
                continue
            if line_no == 1 and row[0].lower() == "name":
                continue
            if len(row) < 2:
                raise InputError(f"line {line_no}: expected name,vertex, got {','.join(row)!r}", path=path)
            try:
                vertex = int(row[1])
            except ValueError:
                raise InputError(f"line {line_no}: {kind} {row[0]!r} has vertex {row[1]!r}, not an integer",
                                 path=path) from None
            if abs(vertex) >= 2**63:  # (the caller checks the range against its mesh, in 64-bit integers)
                raise InputError(f"line {line_no}: {kind} {row[0]!r} has vertex {row[1]}, past any mesh's vertex count",
                                 path=path, hint="vertices are 0-based indices of the rest mesh")
            if row[0] in seen:
                raise InputError(f"line {line_no}: {kind} name {row[0]!r} appears twice", path=path)
            seen.add(row[0])
            yield line_no, row[0], vertex, row[2:]


def load_markers(path: Path, n_vertices: int) -> Markers:
    """Read ``name,vertex[,role]`` (header optional); validate names, indices and roles."""
    names, vertices, roles, lines = [], [], [], []
    for line_no, name, vertex, rest in name_vertex_rows(path, "marker"):
        role = rest[0].lower() if rest and rest[0] else "handle"
        if role not in ROLES:
            raise InputError(f"line {line_no}: marker {name!r} has role {role!r}", path=path,
                             hint="use handle, stable or ignore")
        names.append(name)
        vertices.append(vertex)
        roles.append(role)
        lines.append(line_no)
    if not names:
        raise InputError("no markers", path=path)
    vertices = np.asarray(vertices, dtype=np.int64)
    check_marker_vertices(vertices, n_vertices, names, path, lines=lines)
    markers = Markers(names, vertices, roles)
    if markers.handle_mask.sum() < 3:
        raise InputError("fewer than 3 markers drive the shell (role handle or stable)", path=path)
    return markers


def load_anchors(path: Path | None, n_vertices: int) -> np.ndarray:
    """Vertex indices held fixed to the skull (one per line), or an empty array."""
    if path is None:
        return np.zeros(0, dtype=np.int64)
    if not Path(path).is_file():
        raise InputError("anchor file not found", path=path)
    quick = _plain_indices(Path(path).read_bytes(), n_vertices)
    if quick is not None:
        return np.unique(quick)
    values = []
    with open(path, encoding="utf-8") as fh:
        for line_no, line in enumerate(fh, start=1):
            text = line.split("#")[0].strip()
            if not text:
                continue
            try:
                v = int(text)
            except ValueError:
                raise InputError(f"line {line_no}: {text!r} is not a vertex index", path=path) from None
            if not 0 <= v < n_vertices:
                raise InputError(f"line {line_no}: anchor vertex {v} is out of range (mesh has {n_vertices})",
                                 path=path)
            values.append(v)
    return np.unique(np.asarray(values, dtype=np.int64))


def _plain_indices(data: bytes, n_vertices: int) -> np.ndarray | None:
    """The indices of a file of one plain index per line and nothing else (no comment, sign or
    blank line), all in range — what a large anchors file is (a face's neck and scalp: 100k lines
    are a fifth of a second line by line) — or None, for the line-by-line reader to read or name
    the line at fault."""
    if not data.strip() or data.translate(None, b"0123456789\r\n"):
        return None
    lines = data.split()
    if len(lines) != data.count(b"\n") + (not data.endswith(b"\n")):  # a blank line somewhere
        return None
    if max(map(len, lines)) > 18:  # (past 64 bits, or far past any mesh)
        return None
    values = np.array(lines, dtype=np.int64)
    return values if values.max() < n_vertices else None


def example_paths(config: Config) -> list[Path]:
    """The example meshes named by the config's globs, sorted, without repeats."""
    out: list[Path] = []
    for pattern in config.example_meshes:
        found = sorted(glob.glob(pattern))
        if not found:
            raise InputError(f"[examples] meshes: {pattern!r} matches no file", path=config.path)
        out += [Path(p) for p in found if Path(p) not in out]
    return out


@dataclass
class Rig:
    """Everything the fit needs, validated."""

    config: Config
    mesh: Mesh
    markers: Markers
    anchors: np.ndarray
    example_names: list[str]
    example_positions: np.ndarray  # (E, V, 3) float64 (meshes, then sequence frames)
    digest: str
    landmarks: LandmarkMap | None = None  # [video] landmarks: a 2D tracker's points on the mesh
    # [rig] weld: {"vertices": the file's count, "welded": the rig's, "split": vertices merged}, or None
    welded: dict | None = None
    weld_index: np.ndarray | None = None  # (V_file,) the rig vertex of each vertex of the mesh file

    @property
    def handles(self) -> np.ndarray:
        return self.markers.handle_vertices


def load_rig(config: Config | str | Path, load_examples: bool = True, on_mesh=None) -> Rig:
    """Load and check the rest mesh, markers, anchors and example poses of a config.

    ``on_mesh(mesh, markers, anchors)``, if given, is called as soon as the rest mesh, the markers
    and the anchors are read and checked, while the examples are still being read: work that
    needs only those starts early (:func:`facepipe.pipeline.fit.fit_config`). An error raised
    later is still raised.
    """
    if not isinstance(config, Config):
        config = load_config(config)
    # the example files are read (positions only: an OBJ pose's faces are not parsed) while this
    # process reads the rest mesh: by a second process where they are large (text parsing holds
    # the GIL for much of its time, so a thread would mostly wait)
    try:
        paths, paths_error = (example_paths(config) if load_examples else []), None
    except InputError as exc:  # told after the rest mesh's own errors, as a user fixes them in that order
        paths, paths_error = [], exc
    size = sum(p.stat().st_size for p in paths if p.is_file())
    reads = BackgroundCall(_read_examples, paths,
                           background=size >= EXAMPLES_IN_A_PROCESS and (os.cpu_count() or 1) >= 2)
    try:
        mesh = load_mesh(config.mesh)
        check_mesh(mesh)
        markers = load_markers(config.markers, mesh.n_vertices)
        anchors = load_anchors(config.anchors, mesh.n_vertices)
        landmarks = None if config.landmarks is None else read_landmark_map(config.landmarks, mesh.n_vertices,
                                                                                 given_by=f"[video] landmarks in {config.path}")
        if config.shell.method == "shell" and not config.weld:  # (a welded mesh is checked once welded)
            # the RBF morph needs no connectivity; the shell is singular on a part without constraints
            _check_parts(mesh, markers, anchors, config)
        if on_mesh is not None and not config.weld:  # after the checks: what it starts may factor the shell
            on_mesh(mesh, markers, anchors)
        if paths_error is not None:
            raise paths_error
        on_top = coincident_vertices(mesh.vertices)  # (while the examples are read: a seam's split vertices)
        read = reads.result()
    except BaseException:
        reads.cancel()
        raise
    digest = hashlib.sha256(json.dumps(config.to_dict(), sort_keys=True).encode())
    for p in [config.mesh, config.markers, config.anchors, config.landmarks]:
        if p is not None:
            digest.update(Path(p).read_bytes())
    names: list[str] = []
    poses: list[np.ndarray] = []
    # checked in order, so the first bad file is the one named; a file the reader gave up on is
    # read again here, which raises its error
    for p, got in zip(paths, read):
        verts, file_digest = got if got is not None else _read_example(p)
        check_pose(mesh, verts, p)
        names.append(p.stem)
        poses.append(verts)
        digest.update(file_digest)
    if load_examples:
        if config.sequence is not None:
            seq, rows = load_sequence(config.sequence, mesh, config.sequence_stride, config.sequence_frames)
            names += [f"{config.sequence.stem}:{i}" for i in rows]
            poses += list(seq)
            digest.update(Path(config.sequence).read_bytes())
        if not poses and config.psd.method != "none":
            raise InputError("no example poses", path=config.path,
                             hint="set [examples] meshes and/or sequence, or [psd] method = 'none'")
    positions = np.stack(poses) if poses else np.zeros((0, mesh.n_vertices, 3))
    welded = None
    representative = split_vertices(mesh.vertices, positions, on_top)
    if representative is not None:
        if not config.weld:
            raise split_mesh_error(mesh, representative, f"set weld = true in [rig] of {config.path.name}")
        n_file = mesh.n_vertices
        mesh, keep, index = weld_vertices(mesh, representative)
        check_mesh(mesh)  # (a polygon with two corners on one seam vertex)
        markers, anchors, landmarks = _welded_vertices(markers, anchors, landmarks, index, config)
        positions = positions[:, keep]
        welded = {"vertices": n_file, "welded": mesh.n_vertices, "split": int(n_file - mesh.n_vertices)}
    if config.weld:  # the checks and the early start put off until the mesh was welded
        if config.shell.method == "shell":
            check_components(mesh, np.concatenate([markers.handle_vertices, anchors]))
        if on_mesh is not None:
            on_mesh(mesh, markers, anchors)
    return Rig(config, mesh, markers, anchors, names, positions, digest.hexdigest()[:16], landmarks, welded,
               index if welded else None)


def _check_parts(mesh: Mesh, markers: Markers, anchors: np.ndarray, config: Config) -> None:
    """Every part of the mesh holds a handle or anchor (:func:`facepipe.core.mesh.check_components`);
    where one does not and the mesh has vertices on top of others, the hint says it may be split
    along seams (an island a seam cuts off entirely is a part of its own). The seams are looked for
    only then: a rig that passes pays nothing before its shell starts."""
    constrained = np.concatenate([markers.handle_vertices, anchors])
    try:
        check_components(mesh, constrained)
    except InputError:
        split = int((coincident_vertices(mesh.vertices) != np.arange(mesh.n_vertices)).sum())
        if not split:
            raise
        check_components(mesh, constrained, hint=(
            f"{split} vertices sit exactly on others: if the mesh is split along UV seams or hard edges, set weld = "
            f"true in [rig] of {config.path.name}; else put a handle or anchor on every separate part (an eyeball "
            "or teeth: one of its vertices in the anchors file), or remove the part"))


def split_vertices(rest: np.ndarray, poses: np.ndarray, at_rest: np.ndarray | None = None) -> np.ndarray | None:
    """Each vertex's representative (:func:`facepipe.core.mesh.coincident_vertices`) where some
    vertices sit exactly on another in the rest pose and in every pose of ``poses`` (E, V, 3) —
    a mesh split along UV seams or hard edges —, else None. Vertices that coincide at rest but part
    in some pose (lips that touch) are not split: they stay apart. ``at_rest``: the rest pose's
    representatives, if at hand."""
    representative = coincident_vertices(rest) if at_rest is None else at_rest
    if (representative == np.arange(len(rest))).all():
        return None
    if len(poses):  # the same position in every pose: the rows of all poses side by side coincide
        representative = coincident_vertices(np.concatenate([rest] + list(poses), axis=1))
        if (representative == np.arange(len(rest))).all():
            return None
    return representative


def split_mesh_error(mesh: Mesh, representative: np.ndarray, how: str, where: str = "in the rest pose and in every "
                     "example") -> InputError:
    """The refusal of a mesh split along seams; ``how``: the option that welds them."""
    split = np.flatnonzero(representative != np.arange(len(representative)))
    show = ", ".join(f"{int(v)} on {int(representative[v])}" for v in split[:3])
    return InputError(
        f"{len(split)} vertices sit exactly on another vertex{' ' + where if where else ''}, and no face joins them "
        "(the mesh is split "
        f"along UV seams or hard edges: {show}{' …' if len(split) > 3 else ''}): the thin shell would tear the face "
        "open along those seams", path=mesh.path,
        hint=f"{how} (the model and its outputs then have the welded mesh's "
             f"{int((representative == np.arange(len(representative))).sum())} vertices, each polygon's UVs kept), or "
             "export the mesh with shared vertices (OBJ: one 'v' per point, 'vt' per corner)")


def _welded_vertices(markers: Markers, anchors: np.ndarray, landmarks, index: np.ndarray, config: Config):
    """Markers, anchors and landmarks on the welded mesh (``index``: each file vertex's welded one);
    InputError for two markers on the two sides of one seam."""
    moved = index[markers.vertices]
    _, first, counts = np.unique(moved, return_index=True, return_counts=True)
    if (counts > 1).any():
        v = moved[first[counts > 1][0]]
        both = [markers.names[i] for i in np.flatnonzero(moved == v)]
        raise InputError(f"markers {' and '.join(both)} sit on copies of one vertex split at a seam (welded into "
                         f"vertex {int(v)})", path=config.markers, hint="keep one of them")
    markers = replace(markers, vertices=moved)
    anchors = np.unique(index[anchors])
    if landmarks is not None:
        landmarks = replace(landmarks, vertices=index[landmarks.vertices])
    return markers, anchors, landmarks


def _read_example(path: Path) -> tuple[np.ndarray, bytes]:
    """An example pose's positions and the SHA-256 of its file."""
    return load_vertices(path), hashlib.sha256(Path(path).read_bytes()).digest()


def _read_examples(paths: list[Path]) -> list:
    """:func:`_read_example` of each path, None for a file that fails (its error is raised by the caller)."""
    out = []
    for p in paths:
        try:
            out.append(_read_example(p))
        except Exception:  # noqa: BLE001 - re-read by the caller, which raises the file's own error
            out.append(None)
    return out


def load_sequence(path: Path, mesh: Mesh, stride: int = 1, frames: list | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Frames of a captured take with truth (.npz with ``positions`` (T, V, 3)), in head space,
    and their rows in the file.

    ``frames`` = [first, stop) keeps rows first … stop − 1 (then every ``stride``-th of them);
    where the file has ``rotation``/``translation`` of the head, they are removed.
    """
    if not Path(path).is_file():
        raise InputError("[examples] sequence file not found", path=path)
    try:
        data = np.load(path)
        n_rows = data["positions"].shape[0]
        first, stop = frames if frames is not None else (0, n_rows)
        if stop > n_rows:
            raise InputError(f"[examples] sequence_frames = [{first}, {stop}] reaches past the sequence's "
                             f"{n_rows} frames", path=path, hint=f"use a stop of at most {n_rows}")
        rows = np.arange(first, stop, stride)
        positions = np.asarray(data["positions"][first:stop:stride], dtype=np.float64)
    except KeyError:
        raise InputError("the sequence .npz has no 'positions' array", path=path) from None
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"cannot read the sequence: {exc}", path=path) from None
    if positions.ndim != 3 or positions.shape[1:] != (mesh.n_vertices, 3):
        raise InputError(f"positions have shape {positions.shape}, expected (frames, {mesh.n_vertices}, 3)",
                         path=path)
    if "rotation" in data and "translation" in data:
        rot = np.asarray(data["rotation"], dtype=np.float64)[rows]
        trans = np.asarray(data["translation"], dtype=np.float64)[rows]
        positions = np.einsum("tvi,tij->tvj", positions - trans[:, None, :], rot)
    for i, frame in zip(rows, positions):
        check_pose(mesh, frame, f"{path} (frame {i})")
    return positions, rows
