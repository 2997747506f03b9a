"""The rig's config file (TOML): its tables and keys, read and checked strictly.

Paths in the config are relative to the config file. Every value must have its key's type as
written: a value of another type is refused (InputError, exit status 2) rather than converted,
since a conversion hides the mistake (``12.7`` read as ``12``, ``"no"`` read as true). An integer
is accepted where a number is expected, nothing else: a boolean is neither an integer nor a
number, a float is never an integer, a string never a number or a list. The message names the
file, the ``[table] key``, the value, the expected type and what to write instead. The keys are
described in the README ("Config").
"""

from __future__ import annotations

import datetime
import json
import math
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path

from facepipe.core.psd import DEFAULT_RCOND
from facepipe.errors import InputError


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
    rcond: float = DEFAULT_RCOND  # RBF pseudo-inverse cut-off, relative to the largest singular value
    smoothing: float = 0.0
    novelty_tau: float = 0.15  # details fade where this fraction of local strain is unlike the examples' (0 = off)
    novelty_radius: float = 1.5  # neighbourhood of the novelty test, × median feature-edge length
    # method "local_strain": per-vertex Gaussian kernel regression over the large-scale surface's
    # local strain (core.strain_details); width σ in strain units (no unit), ridge λ
    strain_width: float = 0.08
    strain_ridge: float = 0.3


@dataclass
class TuneConfig:
    """Candidate ranges of ``fit --tune`` (the ``[tune]`` table of the config)."""

    k_stretch: list = field(default_factory=lambda: [0.0, 0.03, 0.1, 0.2, 0.3, 1.0, 3.0, 10.0])
    beta_scale: list = field(default_factory=lambda: [0.5, 1.0, 2.0])
    smoothing: list = field(default_factory=lambda: [0.0, 0.01, 0.1])
    novelty_tau: list = field(default_factory=lambda: [0.1, 0.15, 0.2, 0.3])  # the novelty gate (0 = off)
    # method local_strain: the kernel width σ and ridge λ (strain has no unit: any face, any scale)
    strain_width: list = field(default_factory=lambda: [0.02, 0.04, 0.08, 0.16])
    strain_ridge: list = field(default_factory=lambda: [0.03, 0.3, 3.0])
    max_poses: int = 16  # largest basis tried (at least [psd] max_poses, at most the training examples)
    folds: int = 5  # cross-validation folds (whole expressions per fold)
    vertices: str = ""  # vertex range the errors are measured on, e.g. "0:9409" (default: all)
    sample_vertices: int = 1500  # the details are cross-validated on this many of them, evenly spread
    fallback: bool = True  # details validated worse than the large scale alone → method "none"
    # a candidate may not make any held-out example worse than the defaults (model or large scale
    # alone) by more than this fraction: better on average is not enough
    max_regression: float = 0.01


@dataclass
class AppearanceRegion:
    """One ``[appearance.regions.NAME]`` table: the region's vertex group, its template's UV
    rectangle [u0, v0, u1, v1] (in the layout's own coordinates: on UDIM tile 1002, u in 1 … 2;
    every region on one tile) and its example frames from neutral to extreme; with ``card``, the
    region is a card across the hole whose rim the group holds, its template in the card's own
    square (0 … 1)."""

    name: str
    vertices: Path
    template: list
    frames: list
    card: bool = False  # the region is a card across the hole its vertex group rims (an eye opening)
    shading_surface: str | None = None  # this region's, instead of [appearance] shading_surface


@dataclass
class AppearanceConfig:
    """The ``[appearance]`` table: example footage with its geometry, the camera, the regions."""

    camera: Path
    footage: str
    geometry: Path
    camera_rotation: list = field(default_factory=lambda: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    camera_translation: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    neutral_frame: int = 0
    texture_size: int = 1024
    template_size: int = 16
    keep: int = 50
    scale_weights: list = field(default_factory=lambda: [2.0, 4.0, 2.0, 1.0, 0.0])
    ramp: float = 10.0
    min_facing: float = 0.2  # a region is hidden when its normal is more than ~78° from the camera
    decay: float = 0.5  # seconds: a hidden region's value fades to neutral
    min_event: float = 0.07  # seconds: briefer departures from rest, under a layer, are image noise (0: keep all)
    shading: bool = True  # patches divided by their shading surface (else by their mean) before the match
    # that surface: "plane", "quadratic" (takes out more of a side light's or turned head's shading
    # over a curved patch), or "auto": per region the quadratic where it keeps 3/4 of its layers' contrast
    shading_surface: str = "auto"
    # what that surface is fitted against: "patch", the surface through the patch's own
    # intensities; "neutral", the shading that maps the region's neutral layer onto the patch (a
    # smooth light over the neutral texture is taken out exactly, however dark or uneven the texture)
    shading_reference: str = "patch"
    # how Q is read from the match distances: "segment", the nearest point of the path through the
    # layers (a layer reads its own index, a blend of two its weight), or "parabola" (the paper's
    # vertex through three distances, exact only for layers evenly spaced in appearance)
    peak_interpolation: str = "segment"
    light_fit: bool = True  # each frame's light fitted over the face's known normals and divided out of the patches
    # that light: "point" (ambient + a key and a fill distant light, their cosines clamped at zero:
    # a light's terminator across a fold is modelled) or "sh9" (nine spherical-harmonic terms, smooth)
    light_model: str = "point"
    occlusion: bool = True  # template points the face hides (ray cast) left out of the match
    min_seen: float = 0.5  # a region with less of its template seen is hidden (holds, decaying)
    min_point_facing: float = 0.35  # template points an example sees more edge-on (cosine) left out (0: no edge-on test)
    # a frame leaves out the template points it sees at under this share of the least cosine the
    # region's examples saw them at (their grid cells get under that share of the templates'
    # pixels); 0: those it sees more edge-on than min_point_facing, as the examples
    frame_facing_share: float = 0.5
    min_relative_facing: float = 0.8  # template points an example sees under this share of the template's median facing (a fold turning away) left out
    unseen_margin: float = 1.0  # pixels: template points this near (along x and y) one an example does not show well left out too (their samples read it)
    rest_calibration: bool = True  # Q measured from the highest value each region reads at rest in the other regions' examples
    rest_frames: list = field(default_factory=list)  # more example frames where no region is active (other expressions), for the rest floors
    # layers: an example frame where a region is at rest but reads above this is another
    # expression moving its patch (a raised lid in the eyelid's), not noise: it is explained
    # away, its change left out of that region's match (at most 3 per region; 0: none)
    rest_explain: float = 0.2
    # how far off a region's layer path (for its Q) a reading may lie and still be hidden by an
    # at-rest example above rest_explain as far off, × that example's: each reading gets its
    # own rest floor (0: one floor per region, the highest at-rest reading)
    rest_path_tolerance: float = 2.0
    # how far a card is set back into its opening, × the opening's width: "auto" fits it from the
    # example frames where its eye is at rest and the head turned (else 0.1), or a number
    card_depth: object = "auto"
    # an eye card's reading counts only where its content moved along its layers' path (a look
    # across it, a lid narrowing the opening read as rest); false: the Haar match alone
    card_motion_check: bool = True
    regions: list = field(default_factory=list)


@dataclass
class Config:
    path: Path
    mesh: Path
    markers: Path
    anchors: Path | None = None
    units: str = "cm"
    # weld vertices split along UV seams or hard edges (coincident in the rest pose and every
    # example, joined by no face); without it such a mesh is refused: the shell would tear there
    weld: bool = False
    example_meshes: list[str] = field(default_factory=list)
    sequence: Path | None = None
    sequence_stride: int = 1
    # [first, stop): the rows of the sequence file used for training (None: all); the rest of the
    # take can then serve as a test part
    sequence_frames: list | None = None
    graph: str = "auto"
    shell: ShellConfig = field(default_factory=ShellConfig)
    psd: PsdConfig = field(default_factory=PsdConfig)
    tune: TuneConfig = field(default_factory=TuneConfig)
    appearance: AppearanceConfig | None = None
    landmarks: Path | None = None  # [video] landmarks: a 2D tracker's points on the mesh (name,vertex CSV)

    def to_dict(self) -> dict:
        d = asdict(self)
        return json.loads(json.dumps(d, default=str))


# The type of every key (``_PATHS``: a string or a list of strings); the tables read into a
# dataclass take the types of its defaults.
_PATHS = "paths"
_AUTO_OR_NUMBER = "auto or a number"
_TYPES: dict[str, dict[str, object]] = {
    "rig": {"mesh": str, "markers": str, "anchors": str, "units": str, "weld": bool},
    "examples": {"meshes": _PATHS, "sequence": str, "sequence_stride": int, "sequence_frames": list},
    "shell": {k: type(v) for k, v in asdict(ShellConfig()).items()},
    "features": {"graph": str},
    "psd": {k: type(v) for k, v in asdict(PsdConfig()).items()},
    "tune": {k: type(v) for k, v in asdict(TuneConfig()).items()},
    "appearance": {"camera": str, "footage": str, "geometry": str, "camera_rotation": list,
                   "camera_translation": list, "neutral_frame": int, "texture_size": int, "template_size": int,
                   "keep": int, "scale_weights": list, "ramp": float, "min_facing": float, "decay": float, "min_event": float,
                   "shading": bool, "shading_surface": str, "shading_reference": str, "peak_interpolation": str, "light_fit": bool, "light_model": str, "occlusion": bool, "min_seen": float, "min_point_facing": float, "frame_facing_share": float,
                   "min_relative_facing": float, "unseen_margin": float, "rest_calibration": bool, "rest_frames": list,
                   "rest_explain": float, "rest_path_tolerance": float, "card_depth": "auto or a number",
                   "card_motion_check": bool, "regions": dict},
    "video": {"landmarks": str},
}
_REGION_TYPES = {"vertices": str, "template": list, "frames": list, "card": bool, "shading_surface": str}
_REGION_OPTIONAL = {"card", "shading_surface"}
#: The values of ``shading_surface``.
SHADING_SURFACES = ("auto", "plane", "quadratic")
#: The values of ``peak_interpolation`` (facepipe.core.appearance.PEAK_INTERPOLATIONS).
PEAK_INTERPOLATIONS = ("segment", "parabola")
#: The values of ``shading_reference`` (facepipe.core.appearance.SHADING_REFERENCES).
SHADING_REFERENCES = ("neutral", "patch")
#: The values of ``light_model`` (facepipe.core.lighting.LIGHT_MODELS).
LIGHT_MODELS = ("point", "sh9")
_KNOWN = {section: set(keys) for section, keys in _TYPES.items()}
# a default value to show in a hint, for the keys of the tables without a dataclass
_EXAMPLES = {"mesh": "neutral.obj", "markers": "markers.csv", "anchors": "anchors.txt", "units": "cm", "weld": True,
             "meshes": ["expressions/*.obj"], "sequence": "take.npz", "sequence_stride": 1,
             "sequence_frames": [0, 80], "graph": "auto",
             "landmarks": "landmarks68.csv"}


def load_config(path: str | Path) -> Config:
    """Read and validate a config TOML (the README's "Config" section lists the keys).

    Raises
    ------
    InputError
        A missing or unreadable file, an unknown table or key, a value of the wrong type (never
        converted: see the module docstring) or out of its range, naming the file and the key.
    """
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
        if not isinstance(values, dict):
            raise InputError(f"{section} = {_toml(values)} is {_kind(values)}, expected the table [{section}]",
                             path=path, hint=f"write its keys under a line [{section}]")
        unknown = set(values) - _KNOWN[section]
        if unknown:
            raise InputError(f"unknown key(s) {sorted(unknown)} in [{section}]", path=path,
                             hint=f"known keys: {sorted(_KNOWN[section])}")
    base = path.parent
    rig = _typed_table(raw, "rig", path)
    for key in ("mesh", "markers"):
        if not rig.get(key):
            raise InputError(f"[rig] {key} is required", path=path)

    def rel(p):
        return None if not p else (base / p)

    examples = _typed_table(raw, "examples", path)
    meshes = examples.get("meshes", [])
    if isinstance(meshes, str):
        meshes = [meshes]
    if examples.get("sequence_stride", 1) < 1:
        raise InputError(f"[examples] sequence_stride = {examples['sequence_stride']} must be ≥ 1", path=path)
    frames = _frame_range(examples.get("sequence_frames"), path)
    if frames is not None and not examples.get("sequence"):
        raise InputError(f"[examples] sequence_frames = {_toml(frames)} without a sequence", path=path,
                         hint="set [examples] sequence = \"take.npz\" or remove sequence_frames")
    features = _typed_table(raw, "features", path)
    video = _typed_table(raw, "video", path)
    shell = _section(ShellConfig, raw.get("shell", {}), path, "shell")
    psd = _section(PsdConfig, raw.get("psd", {}), path, "psd")
    tune = _section(TuneConfig, raw.get("tune", {}), path, "tune")
    for key in ("k_stretch", "beta_scale", "smoothing", "novelty_tau"):
        values = getattr(tune, key)
        if not values or any(v < 0 for v in values):
            raise InputError(f"[tune] {key} must be a non-empty list of numbers ≥ 0", path=path)
    for key in ("strain_width", "strain_ridge"):
        values = getattr(tune, key)
        if not values or any(not v > 0 for v in values):
            raise InputError(f"[tune] {key} must be a non-empty list of numbers > 0", path=path)
    if tune.folds < 2 or tune.max_poses < 1 or tune.sample_vertices < 1 or tune.max_regression < 0:
        raise InputError("[tune] folds must be ≥ 2, max_poses and sample_vertices ≥ 1, max_regression ≥ 0",
                         path=path)
    if psd.method not in ("wpsd", "psd", "local_strain", "none"):
        raise InputError(f"[psd] method = {psd.method!r}", path=path, hint="use wpsd, psd, local_strain or none")
    if psd.strain_width <= 0 or psd.strain_ridge <= 0:
        raise InputError(f"[psd] strain_width = {psd.strain_width!r}, strain_ridge = {psd.strain_ridge!r}", path=path,
                         hint="both must be > 0 (e.g. strain_width = 0.08, strain_ridge = 0.3)")
    if psd.fit not in ("interpolate", "least-squares"):
        raise InputError(f"[psd] fit = {psd.fit!r}", path=path, hint="use interpolate or least-squares")
    if psd.max_poses < 0 or psd.max_edges_per_vertex < 1 or psd.greedy_vertices < 0:
        raise InputError("[psd] max_poses and greedy_vertices must be ≥ 0, max_edges_per_vertex ≥ 1", path=path)
    if not 0.0 <= psd.rcond < 1.0:
        raise InputError(f"[psd] rcond = {psd.rcond!r}", path=path, hint="a cut-off relative to the largest "
                         f"singular value: 0 ≤ rcond < 1 (default {DEFAULT_RCOND:g})")
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
        units=rig.get("units", "cm"),
        weld=rig.get("weld", False),
        example_meshes=[str(base / m) for m in meshes],
        sequence=rel(examples.get("sequence")),
        sequence_stride=examples.get("sequence_stride", 1),
        sequence_frames=frames,
        graph=features.get("graph", "auto"),
        shell=shell,
        psd=psd,
        tune=tune,
        appearance=_appearance(raw, path) if "appearance" in raw else None,
        landmarks=rel(video.get("landmarks")),
    )


def _frame_range(value, path: Path) -> list | None:
    """``[examples] sequence_frames``: [first, stop), two integers with 0 ≤ first < stop, or None."""
    if value is None:
        return None
    if len(value) != 2 or not all(isinstance(v, int) for v in value) or not 0 <= value[0] < value[1]:
        fixed = [int(v) for v in value] if len(value) == 2 and all(float(v).is_integer() for v in value) else None
        raise InputError(f"[examples] sequence_frames = {_toml(value)}, expected [first, stop): two integers with "
                         "0 ≤ first < stop (the sequence's rows first … stop − 1)", path=path,
                         hint=f"write sequence_frames = {_toml(fixed)}" if fixed and 0 <= fixed[0] < fixed[1]
                         else "e.g. sequence_frames = [0, 80] trains on rows 0–79")
    return list(value)


def _appearance(raw: dict, path: Path) -> AppearanceConfig:
    """The ``[appearance]`` table and its ``[appearance.regions.NAME]`` tables, checked strictly."""
    # the regions (tables) and the rotation (rows of numbers) are checked below, the rest by type
    given = dict(raw["appearance"])
    region_tables = given.pop("regions", {})
    rotation = given.pop("camera_rotation", None)
    table = _typed_table({"appearance": given}, "appearance", path)
    if not isinstance(region_tables, dict):
        raise InputError(f"[appearance] regions = {_toml(region_tables)} is {_kind(region_tables)}", path=path,
                         hint="write each region as a table [appearance.regions.NAME]")
    for key in ("camera", "footage", "geometry"):
        if not table.get(key):
            raise InputError(f"[appearance] {key} is required", path=path,
                             hint="camera = calibration file, footage = example frames, geometry = their positions")
    base = path.parent
    regions = []
    for name, values in region_tables.items():
        where = f"appearance.regions.{name}"
        if not isinstance(values, dict):
            raise InputError(f"[{where}] is not a table", path=path, hint=f"write its keys under [{where}]")
        unknown = set(values) - set(_REGION_TYPES)
        missing = set(_REGION_TYPES) - _REGION_OPTIONAL - set(values)
        if unknown or missing:
            raise InputError(f"[{where}] unknown {sorted(unknown)} / missing {sorted(missing)} keys", path=path,
                             hint="each region takes vertices, template = [u0, v0, u1, v1], frames = [...] "
                                  "(optional: card = true for a hole, shading_surface = \"auto\")")
        v = {k: checked_value(values[k], t, path, where, k) for k, t in _REGION_TYPES.items() if k in values}
        template = [checked_value(x, float, path, where, "template") for x in v["template"]]
        frames = [checked_value(x, int, path, where, "frames") for x in v["frames"]]
        if len(template) != 4 or not (template[0] < template[2] and template[1] < template[3]):
            raise InputError(f"[{where}] template = {template} is not [u0, v0, u1, v1] with u0 < u1, v0 < v1",
                             path=path)
        card = v.get("card", False)
        if card and not all(0.0 <= x <= 1.0 for x in template):
            raise InputError(f"[{where}] template = {template}: a card's template is in the card's own square, "
                             "0 … 1", path=path, hint="e.g. template = [0.2, 0.2, 0.8, 0.8], the card's middle")
        if len(frames) < 3:
            raise InputError(f"[{where}] frames = {frames}: a region needs at least three layers", path=path,
                             hint="give 3 or more example frames, neutral first (5 or 6 for smooth motion)")
        twice = sorted({f for f in frames if frames.count(f) > 1})
        if twice:
            raise InputError(f"[{where}] frames = {frames} lists frame {twice[0]} more than once: each layer is an "
                             "example frame of its own", path=path,
                             hint="give distinct example frames, neutral first, ordered to the extreme")
        surface = v.get("shading_surface")
        if surface is not None:
            _check_surface(surface, path, where)
        regions.append(AppearanceRegion(name, base / v["vertices"], template, frames, card, surface))
    if not regions:
        raise InputError("[appearance] has no regions", path=path,
                         hint="add tables [appearance.regions.NAME] with vertices, template and frames")
    out = AppearanceConfig(camera=base / table.pop("camera"), footage=str(base / table.pop("footage")),
                           geometry=base / table.pop("geometry"), regions=regions)
    for key, value in table.items():
        setattr(out, key, value)
    if rotation is not None:
        out.camera_rotation = rotation
    rot = out.camera_rotation
    if (not isinstance(rot, list) or len(rot) != 3 or any(not isinstance(r, list) or len(r) != 3 for r in rot)
            or not isinstance(out.camera_translation, list) or len(out.camera_translation) != 3
            or not all(_is(x, float) for r in rot for x in r) or not all(_is(x, float) for x in out.camera_translation)):
        raise InputError("[appearance] camera_rotation must be 3 × 3 numbers and camera_translation 3 numbers",
                         path=path, hint="the world → camera pose (OpenCV axes); leave them out for camera space")
    if out.texture_size < 16 or out.template_size < 4 or out.template_size & (out.template_size - 1) or out.keep < 1:
        raise InputError("[appearance] texture_size must be ≥ 16, template_size a power of two ≥ 4, keep ≥ 1",
                         path=path)
    if out.ramp < 0 or out.decay < 0 or out.min_event < 0 or not all(_is(x, float) and x >= 0 for x in out.scale_weights):
        raise InputError("[appearance] ramp, decay, min_event and scale_weights must be ≥ 0", path=path)
    if not 0.0 <= out.min_point_facing < 1.0:
        raise InputError(f"[appearance] min_point_facing = {out.min_point_facing} is not in [0, 1)", path=path,
                         hint="a cosine: 0 keeps every point the camera sees, 0.35 drops those seen within ~70° of edge-on")
    if not 0.0 <= out.frame_facing_share <= 1.0:
        raise InputError(f"[appearance] frame_facing_share = {out.frame_facing_share} is not in [0, 1]", path=path,
                         hint="a share of the cosine the examples saw each template point at: 0.5 drops the points a "
                              "frame sees at under half of it; 0 uses min_point_facing in the frames too")
    if not 0.0 <= out.min_relative_facing < 1.0:
        raise InputError(f"[appearance] min_relative_facing = {out.min_relative_facing} is not in [0, 1)", path=path,
                         hint="a share of the template's median facing: 0 keeps every point, 0.8 drops folds turning away")
    if not 0.0 <= out.unseen_margin < 8.0:
        raise InputError(f"[appearance] unseen_margin = {out.unseen_margin} is not in [0, 8) pixels", path=path,
                         hint="0 keeps every point seen well; 1 drops those whose bilinear samples reach one that is not")
    out.rest_frames = [checked_value(x, int, path, "appearance", "rest_frames") for x in out.rest_frames]
    for region in regions:
        layers = set(region.frames[1:]) & set(out.rest_frames)
        if layers:
            raise InputError(f"[appearance] rest_frames lists frame {min(layers)}, a layer of region {region.name} "
                             f"(frames = {region.frames}): a rest frame shows every region at rest", path=path,
                             hint=f"take frame {min(layers)} out of rest_frames, or out of that region's layers")
    gram = [[sum(a * b for a, b in zip(r1, r2)) for r2 in rot] for r1 in rot]  # R Rᵀ
    det = (rot[0][0] * (rot[1][1] * rot[2][2] - rot[1][2] * rot[2][1])
           - rot[0][1] * (rot[1][0] * rot[2][2] - rot[1][2] * rot[2][0])
           + rot[0][2] * (rot[1][0] * rot[2][1] - rot[1][1] * rot[2][0]))
    if not (all(abs(gram[i][j] - (i == j)) <= 1e-3 for i in range(3) for j in range(3)) and det > 0):
        raise InputError(f"[appearance] camera_rotation = {_toml(rot)} is not a rotation (its rows are not "
                         f"orthonormal, or it mirrors: determinant {det:.4g})", path=path,
                         hint="the world → camera rotation, e.g. from cv2.Rodrigues of solvePnP's rvec; "
                              "[[1, 0, 0], [0, -1, 0], [0, 0, -1]] looks at a face whose +y is up from +z")
    if not 0.0 <= out.rest_explain <= 1.0:
        raise InputError(f"[appearance] rest_explain = {out.rest_explain} is not in [0, 1] layers", path=path,
                         hint="0 explains no at-rest example away; 0.2 those that read above a fifth of a layer")
    if not (out.rest_path_tolerance >= 0 and math.isfinite(out.rest_path_tolerance)):
        raise InputError(f"[appearance] rest_path_tolerance = {out.rest_path_tolerance} is not a finite number ≥ 0",
                         path=path, hint="0 keeps one rest floor per region; 2 (the default) gives each reading its own")
    if out.card_depth != "auto" and not (0.0 <= out.card_depth <= 1.0):
        raise InputError(f"[appearance] card_depth = {out.card_depth} is not in [0, 1] (× the opening's width)",
                         path=path, hint='"auto" (the default) fits it; 0.1 sets the cards a tenth of the width back')
    _check_surface(out.shading_surface, path, "appearance")
    if out.shading_reference not in SHADING_REFERENCES:
        raise InputError(f"[appearance] shading_reference = {_toml(out.shading_reference)} is not one of "
                         f"{', '.join(SHADING_REFERENCES)}", path=path,
                         hint='"neutral" fits each patch\'s shading against its region\'s neutral layer, '
                              '"patch" through the patch alone')
    if out.peak_interpolation not in PEAK_INTERPOLATIONS:
        raise InputError(f"[appearance] peak_interpolation = {_toml(out.peak_interpolation)} is not one of "
                         f"{', '.join(PEAK_INTERPOLATIONS)}", path=path,
                         hint='"segment" (the default) or "parabola" (the paper\'s)')
    if out.light_model not in LIGHT_MODELS:
        raise InputError(f"[appearance] light_model = {_toml(out.light_model)} is not one of "
                         f"{', '.join(LIGHT_MODELS)}", path=path,
                         hint='"point" (the default: an ambient term, a key and a fill light) or "sh9" (nine '
                              'spherical-harmonic terms)')
    if not 0.0 < out.min_seen <= 1.0:
        raise InputError(f"[appearance] min_seen = {out.min_seen} is not in (0, 1]", path=path,
                         hint="the share of a template that must be seen, e.g. 0.5")
    return out


def _check_surface(value: str, path: Path, where: str) -> None:
    if value not in SHADING_SURFACES:
        raise InputError(f"[{where}] shading_surface = {_toml(value)} is not one of {', '.join(SHADING_SURFACES)}",
                         path=path, hint='"auto" chooses per region; "plane" or "quadratic" fixes it')


def _typed_table(raw: dict, name: str, path: Path) -> dict:
    """The keys of table ``[name]``, each checked against its type (ints for floats made floats)."""
    return {key: checked_value(value, _TYPES[name][key], path, name, key, _EXAMPLES.get(key))
            for key, value in raw.get(name, {}).items()}


def _section(cls, values: dict, path: Path, name: str):
    """The dataclass ``cls`` with the table's values, each checked against its default's type."""
    out = cls()
    for key, value in values.items():
        setattr(out, key, checked_value(value, _TYPES[name][key], path, name, key, getattr(out, key)))
    return out


def checked_value(value, expected, path, section: str, key: str, example=None):
    """``value`` if its TOML type is ``expected``: an int given for a float is returned as a float.

    Parameters
    ----------
    value : as tomllib read it.
    expected : int, float, bool, str, list (a list of numbers) or "paths" (a string or a list of
        strings).
    path, section, key : the config file and where the value is in it, for the message.
    example : a valid value of the key for the hint (e.g. its default), or None.

    Raises
    ------
    InputError
        naming the file, ``[section] key = value``, the expected type and what to write instead.

    Example
    -------
    >>> checked_value(2, float, "rig.toml", "shell", "k_bend")
    2.0
    """
    if _is(value, expected):
        return float(value) if expected is float or (expected == _AUTO_OR_NUMBER and value != "auto") else value
    if expected is list and isinstance(value, list):
        bad = next(v for v in value if not _is(v, float))
        got = f"{_toml(value)} holds {_toml(bad)} ({_kind(bad)})"
    elif expected == _PATHS and isinstance(value, list):
        bad = next(v for v in value if not isinstance(v, str))
        got = f"{_toml(value)} holds {_toml(bad)} ({_kind(bad)})"
    else:
        got = f"{_toml(value)} is {_kind(value)}"
    raise InputError(f"[{section}] {key} = {got}, expected {_EXPECTED[expected]}", path=path,
                     hint=_instead(value, expected, key, example))


_EXPECTED = {int: "an integer", float: "a number", bool: "true or false", str: "a string in quotes",
             list: "a list of numbers", _PATHS: "a string or a list of strings",
             _AUTO_OR_NUMBER: '"auto" or a number'}


def _is(value, expected) -> bool:
    """Whether ``value`` has the type ``expected`` (bool is neither int nor float; an int is a float)."""
    if isinstance(value, bool):
        return expected is bool
    if expected is float:
        return isinstance(value, (int, float))
    if expected is list:
        return isinstance(value, list) and all(_is(v, float) for v in value)
    if expected == _AUTO_OR_NUMBER:
        return value == "auto" or isinstance(value, (int, float))
    if expected == _PATHS:
        return isinstance(value, str) or (isinstance(value, list) and all(isinstance(v, str) for v in value))
    return isinstance(value, expected)


def _instead(value, expected, key: str, example) -> str:
    """What to write instead of ``value``: the same value in the right type where there is one."""
    fixed = _as(value, expected)
    if fixed is not None:
        return f"write {key} = {_toml(fixed)}"
    if example is not None:
        return f"write {_EXPECTED[expected]}, e.g. {key} = {_toml(example)}"
    return f"write {_EXPECTED[expected]}"


def _as(value, expected):
    """``value`` as the type ``expected`` where it plainly is one (``"0.5"`` → 0.5, ``12.0`` → 12,
    ``"no"`` → false, ``0.5`` → [0.5]); None where a guess would be needed (``12.7`` for an integer)."""
    if expected is list:
        items = value if isinstance(value, list) else (value.split(",") if isinstance(value, str) else [value])
        items = [_as(v, float) if not _is(v, float) else v for v in items]
        return items if items and all(v is not None for v in items) else None
    if expected == _PATHS:
        return None if isinstance(value, (dict, list)) else [_as(value, str)]
    if expected == _AUTO_OR_NUMBER:
        return "auto" if isinstance(value, str) and value.strip().lower() == "auto" else _as(value, float)
    if expected is str:
        if isinstance(value, (dict, list)):
            return None
        return _toml(value) if not isinstance(value, str) else value
    if isinstance(value, str):
        text = value.strip().lower()
        if expected is bool:
            return {"true": True, "yes": True, "on": True, "false": False, "no": False, "off": False}.get(text)
        try:
            number = float(text)
        except ValueError:
            return None
        value = number
    if isinstance(value, bool):
        return None  # true is no number: which one was meant is a guess
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if expected is int:
        return int(value) if isinstance(value, (int, float)) and float(value).is_integer() else None
    if expected is float:
        return value if isinstance(value, (int, float)) else None
    if expected is bool:
        return {0: False, 1: True}.get(value) if isinstance(value, (int, float)) else None
    return None


def _toml(value) -> str:
    """``value`` written as in a TOML file."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value == math.inf else "-inf" if value == -math.inf
                                                else repr(value))
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + " }"
    if isinstance(value, (datetime.date, datetime.time)):
        return value.isoformat()
    return str(value)


def _kind(value) -> str:
    """The TOML type of ``value``, with its article."""
    for kind, name in ((bool, "a boolean"), (int, "an integer"), (float, "a float"), (str, "a string"),
                       (list, "a list"), (dict, "a table")):
        if isinstance(value, kind):
            return name
    return "a date/time"
