"""The rig: config file (TOML) and the files it names, loaded and validated.

Paths in the config are relative to the config file. Every problem is an InputError
naming the file, the line or key, and the fix.
"""

from __future__ import annotations

import csv
import glob
import hashlib
import json
import os
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from facepipe.pipeline.background import BackgroundCall
from facepipe.errors import InputError
from facepipe.core.mesh import (Mesh, check_components, check_marker_vertices, check_mesh, check_pose, load_mesh, load_vertices)

ROLES = ("handle", "stable", "ignore")
# example files of this many bytes in all are read by a second process (below, the start costs more)
EXAMPLES_IN_A_PROCESS = 64 * 2**20


@dataclass
class ShellConfig:
    method: str = "shell"  # shell (thin shell on the mesh) | rbf (volume morph, no connectivity needed)
    k_stretch: float = 0.0  # relative to the marker spacing h: effective k_s = k_stretch / h²
    k_bend: float = 1.0
    rbf_lambda: float = 0.01  # rbf: Tikhonov λ relative to the marker spacing
    phantoms: int = 0  # rbf: phantom points held still (from the anchors, else the border); 0 = 2 × handles


@dataclass
class PsdConfig:
    method: str = "wpsd"
    fit: str = "interpolate"
    max_poses: int = 12
    tolerance: float = 0.0
    # the greedy choice scores the training poses on this many vertices, evenly spread (0 = all); the
    # chosen basis is then fitted on every vertex
    greedy_vertices: int = 32768
    max_edges_per_vertex: int = 16
    min_edge_weight: float = 0.025
    beta: float = 0.0  # WPSD falloff (1/length); 0 = beta_scale / median feature-edge length
    beta_scale: float = 1.0
    rcond: float = 3e-4  # RBF pseudo-inverse cut-off, relative (psd.DEFAULT_RCOND)
    smoothing: float = 0.0
    novelty_tau: float = 0.15  # details fade where this fraction of local strain is unlike the examples' (0 = off)
    novelty_radius: float = 1.5  # neighbourhood of the novelty test, × median feature-edge length


@dataclass
class TuneConfig:
    """Candidate ranges of ``fit --tune`` (the ``[tune]`` table of the config)."""

    k_stretch: list = field(default_factory=lambda: [0.0, 0.03, 0.1, 0.2, 0.3, 1.0, 3.0, 10.0])
    beta_scale: list = field(default_factory=lambda: [0.5, 1.0, 2.0])
    smoothing: list = field(default_factory=lambda: [0.0, 0.01, 0.1])
    novelty_tau: list = field(default_factory=lambda: [0.1, 0.15, 0.2, 0.3])  # the novelty gate (0 = off)
    max_poses: int = 16  # largest basis tried (at least [psd] max_poses, at most the training examples)
    folds: int = 5  # cross-validation folds (whole expressions per fold)
    vertices: str = ""  # vertex range the errors are measured on, e.g. "0:9409" (default: all)
    sample_vertices: int = 3000  # the details are cross-validated on this many of them, evenly spread
    fallback: bool = True  # details validated worse than the large scale alone → method "none"
    # a candidate may not make any held-out example worse than the defaults (model or large scale
    # alone) by more than this fraction: better on average is not enough
    max_regression: float = 0.01


@dataclass
class Config:
    path: Path
    mesh: Path
    markers: Path
    anchors: Path | None = None
    units: str = "cm"
    example_meshes: list[str] = field(default_factory=list)
    sequence: Path | None = None
    sequence_stride: int = 1
    graph: str = "auto"
    shell: ShellConfig = field(default_factory=ShellConfig)
    psd: PsdConfig = field(default_factory=PsdConfig)
    tune: TuneConfig = field(default_factory=TuneConfig)

    def to_dict(self) -> dict:
        d = asdict(self)
        return json.loads(json.dumps(d, default=str))


_KNOWN = {
    "rig": {"mesh", "markers", "anchors", "units"},
    "examples": {"meshes", "sequence", "sequence_stride"},
    "shell": set(ShellConfig.__dataclass_fields__),
    "features": {"graph"},
    "psd": set(PsdConfig.__dataclass_fields__),
    "tune": set(TuneConfig.__dataclass_fields__),
}


def load_config(path: str | Path) -> Config:
    """Read and validate a config TOML (see DESIGN.md for the keys)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("config file not found", path=path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid TOML: {exc}", path=path) from None
    for section, values in raw.items():
        if section not in _KNOWN:
            raise InputError(f"unknown section [{section}]", path=path, hint=f"known: {sorted(_KNOWN)}")
        if isinstance(values, dict) and section in _KNOWN:
            unknown = set(values) - _KNOWN[section]
            if unknown:
                raise InputError(f"unknown key(s) {sorted(unknown)} in [{section}]", path=path,
                                 hint=f"known keys: {sorted(_KNOWN[section])}")
    base = path.parent
    rig = raw.get("rig", {})
    for key in ("mesh", "markers"):
        if not rig.get(key):
            raise InputError(f"[rig] {key} is required", path=path)

    def rel(p):
        return None if not p else (base / p)

    examples = raw.get("examples", {})
    meshes = examples.get("meshes", [])
    if isinstance(meshes, str):
        meshes = [meshes]
    shell = _section(ShellConfig, raw.get("shell", {}), path, "shell")
    psd = _section(PsdConfig, raw.get("psd", {}), path, "psd")
    tune = _section(TuneConfig, raw.get("tune", {}), path, "tune")
    for key in ("k_stretch", "beta_scale", "smoothing", "novelty_tau"):
        values = getattr(tune, key)
        if not values or any(not isinstance(v, (int, float)) or v < 0 for v in values):
            raise InputError(f"[tune] {key} must be a non-empty list of numbers ≥ 0", path=path)
    if tune.folds < 2 or tune.max_poses < 1 or tune.sample_vertices < 1 or tune.max_regression < 0:
        raise InputError("[tune] folds must be ≥ 2, max_poses and sample_vertices ≥ 1, max_regression ≥ 0",
                         path=path)
    if psd.method not in ("wpsd", "psd", "none"):
        raise InputError(f"[psd] method = {psd.method!r}", path=path, hint="use wpsd, psd or none")
    if psd.fit not in ("interpolate", "least-squares"):
        raise InputError(f"[psd] fit = {psd.fit!r}", path=path, hint="use interpolate or least-squares")
    if psd.max_poses < 0 or psd.max_edges_per_vertex < 1 or psd.greedy_vertices < 0:
        raise InputError("[psd] max_poses and greedy_vertices must be ≥ 0, max_edges_per_vertex ≥ 1", path=path)
    if shell.method not in ("shell", "rbf"):
        raise InputError(f"[shell] method = {shell.method!r}", path=path, hint="use shell or rbf")
    if shell.rbf_lambda < 0 or shell.phantoms < 0:
        raise InputError("[shell] rbf_lambda and phantoms must be ≥ 0", path=path)
    if shell.k_bend < 0 or shell.k_stretch < 0 or (shell.k_bend == 0 and shell.k_stretch == 0):
        raise InputError("[shell] k_stretch and k_bend must be ≥ 0 and not both 0", path=path)
    return Config(
        path=path,
        mesh=rel(rig["mesh"]),
        markers=rel(rig["markers"]),
        anchors=rel(rig.get("anchors")),
        units=str(rig.get("units", "cm")),
        example_meshes=[str(base / m) for m in meshes],
        sequence=rel(examples.get("sequence")),
        sequence_stride=int(examples.get("sequence_stride", 1)),
        graph=str(raw.get("features", {}).get("graph", "auto")),
        shell=shell,
        psd=psd,
        tune=tune,
    )


def _section(cls, values: dict, path: Path, name: str):
    out = cls()
    for key, value in values.items():
        default = getattr(out, key)
        try:
            if isinstance(default, (bool, list)) and not isinstance(value, type(default)):
                raise TypeError  # bool("no") is True, list("ab") splits a string
            value = type(default)(value)
        except (TypeError, ValueError):
            raise InputError(f"[{name}] {key} = {value!r} should be a {type(default).__name__}", path=path) from None
        setattr(out, key, value)
    return out


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

    @property
    def handles(self) -> np.ndarray:
        return self.markers.handle_vertices


def load_rig(config: Config | str | Path, load_examples: bool = True, on_mesh=None) -> Rig:
    """Load and check the rest mesh, markers, anchors and example poses of a config.

    ``on_mesh(mesh, markers)``, if given, is called as soon as the rest mesh and the markers are
    read and checked, while the examples are still being read: work that needs only those two
    starts early (:func:`facepipe.pipeline.fit.fit_config`). An error raised later is still raised.
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
        if on_mesh is not None:
            on_mesh(mesh, markers)
        if config.shell.method == "shell":
            # the RBF morph needs no connectivity; the shell is singular on a part without constraints
            check_components(mesh, np.concatenate([markers.handle_vertices, anchors]))
        if paths_error is not None:
            raise paths_error
        read = reads.result()
    except BaseException:
        reads.cancel()
        raise
    digest = hashlib.sha256(json.dumps(config.to_dict(), sort_keys=True).encode())
    for p in [config.mesh, config.markers, config.anchors]:
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
            seq = load_sequence(config.sequence, mesh, config.sequence_stride)
            names += [f"{config.sequence.stem}:{i}" for i in range(0, seq.shape[0] * config.sequence_stride,
                                                                     config.sequence_stride)]
            poses += list(seq)
            digest.update(Path(config.sequence).read_bytes())
        if not poses and config.psd.method != "none":
            raise InputError("no example poses", path=config.path,
                             hint="set [examples] meshes and/or sequence, or [psd] method = 'none'")
    positions = np.stack(poses) if poses else np.zeros((0, mesh.n_vertices, 3))
    return Rig(config, mesh, markers, anchors, names, positions, digest.hexdigest()[:16])


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


def load_sequence(path: Path, mesh: Mesh, stride: int = 1) -> np.ndarray:
    """Frames of a captured take with truth (.npz with ``positions`` (T, V, 3)), in head space.

    Where the file has ``rotation``/``translation`` of the head, they are removed.
    """
    if not Path(path).is_file():
        raise InputError("[examples] sequence file not found", path=path)
    try:
        data = np.load(path)
        positions = np.asarray(data["positions"], dtype=np.float64)[::stride]
    except KeyError:
        raise InputError("the sequence .npz has no 'positions' array", path=path) from None
    except Exception as exc:
        raise InputError(f"cannot read the sequence: {exc}", path=path) from None
    if positions.ndim != 3 or positions.shape[1:] != (mesh.n_vertices, 3):
        raise InputError(f"positions have shape {positions.shape}, expected (frames, {mesh.n_vertices}, 3)",
                         path=path)
    if "rotation" in data and "translation" in data:
        rot = np.asarray(data["rotation"], dtype=np.float64)[::stride]
        trans = np.asarray(data["translation"], dtype=np.float64)[::stride]
        positions = np.einsum("tvi,tij->tvj", positions - trans[:, None, :], rot)
    for i, frame in enumerate(positions):
        check_pose(mesh, frame, f"{path} (frame {i * stride})")
    return positions
