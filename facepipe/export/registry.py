"""The export formats behind one registry (as the mocap readers'): a record per format, by name.

A format is one module with an exporter, ``exporter(replay, dest, options) -> (paths, info)``
(a :class:`facepipe.io.replay_folder.ReplayDir`, the destination and the :class:`ExportOptions`;
it returns every file written or kept and the format's details for the export's report), plus
one :func:`register` call. ``facepipe export --format NAME`` looks the format up here, and the
command line's ``--format`` choices and help are the registered formats.

The built-in formats are registered below by their exporters' import paths, imported when a
format is used: the command line lists the formats without importing them (the map formats
pull in SciPy, which ``facepipe --help`` need not pay for).
"""

from __future__ import annotations

import contextlib
import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from facepipe.errors import InputError

#: ``exporter(replay, dest, options) -> (paths, info)``.
Exporter = Callable[..., tuple[list[Path], dict]]


def null_bar(total, desc="", unit="frame"):
    """A progress bar that shows nothing (the default of :class:`ExportOptions`)."""

    class _Bar:
        def update(self, n=1):
            pass

    return contextlib.nullcontext(_Bar())


@dataclass(frozen=True)
class ExportOptions:
    """The options of an export; each format reads those that apply to it.

    model_path : model to use instead of the one replay.json names.
    layer : geometry formats: "final" (positions.npy) or "large" (large_scale.npy: the
        surface that displacement maps are applied to).
    resolution : (width, height) texels per UDIM tile of a map.
    padding : texels of edge padding around UV islands.
    half : half-float maps; None = the format's default (exr half, wrinkle float).
    mode : maps: "vector" (R, G, B) or "scalar" (Y, along the normal).
    space : exr vector maps: "local" (the model's frames t, b, n), "tangent" (UV-aligned
        frames, the renderers' tangent space) or "object" (see :mod:`facepipe.pipeline.detail_layers`).
    start : number of the first file of a sequence.
    up_axis : USD stage up axis.
    force, resume : overwrite existing files / keep them and write only what is missing.
    make_bar : ``make_bar(total, desc, unit)`` → context manager with ``update(n)`` (a progress bar).
    """

    model_path: str | Path | None = None
    layer: str = "final"
    resolution: tuple[int, int] = (2048, 2048)
    padding: int = 8
    half: bool | None = None
    mode: str = "vector"
    space: str = "local"
    start: int = 1
    up_axis: str = "Y"
    force: bool = False
    resume: bool = False
    make_bar: Callable = null_bar


@dataclass(frozen=True)
class Format:
    """A registered export format.

    Attributes
    ----------
    name : str
        The ``--format`` value.
    summary : str
        What it writes, for the command line's help (formats with the same summary share it).
    suffixes : tuple[str, ...]
        A file format's suffixes (lower case, with the dot; the first is the default); empty
        for a format that writes a folder.
    exporter : Exporter, or ``"module:function"`` naming one (imported on first use).
    model_check : optional ``check(model)`` (or ``"module:function"``) raising InputError for a
        model the format cannot export from whatever the take (e.g. maps of a model without UVs),
        so that ``facepipe batch`` refuses it before replaying any take.
    not_in_batch : why ``facepipe batch`` cannot write this format (it needs more than a replay
        gives), or None.
    """

    name: str
    summary: str
    suffixes: tuple[str, ...]
    exporter: Exporter | str
    model_check: Callable | str | None = None
    not_in_batch: str | None = None

    def export(self, replay, dest: Path, options: ExportOptions) -> tuple[list[Path], dict]:
        return _resolve(self.exporter)(replay, dest, options)

    def check_model(self, model) -> None:
        """InputError where this format cannot export from any replay of ``model``."""
        if self.model_check is not None:
            _resolve(self.model_check)(model)


def _resolve(function):
    """A function, or the one ``"module:function"`` names (imported on first use)."""
    if isinstance(function, str):
        module, name = function.split(":")
        function = getattr(importlib.import_module(module), name)
    return function


#: Registered formats by name, in the order the command line lists them.
FORMATS: dict[str, Format] = {}


def register(fmt: Format) -> None:
    """Add a format to the registry (a later one with the same name replaces it)."""
    FORMATS[fmt.name] = fmt


def get_format(name: str) -> Format:
    """The registered format ``name``.

    Raises
    ------
    InputError
        An unknown name, with the registered ones.
    """
    if name not in FORMATS:
        raise InputError(f"unknown export format {name!r}; choose one of {', '.join(FORMATS)}")
    return FORMATS[name]


def format_help() -> str:
    """The formats and what they write, for ``--format``'s help (a summary shared by formats next
    to each other is said once: ``mdd, pc2: point caches``)."""
    groups: list[tuple[list[str], str]] = []
    for fmt in FORMATS.values():
        if groups and groups[-1][1] == fmt.summary:
            groups[-1][0].append(fmt.name)
        else:
            groups.append(([fmt.name], fmt.summary))
    return "; ".join(f"{', '.join(names)}: {summary}" for names, summary in groups) + "."


def destination_help() -> str:
    """What ``-o`` names per format: a folder, or a file and its suffixes."""
    folders = [f.name for f in FORMATS.values() if not f.suffixes]
    files = [f"{f.name}: {'/'.join(f.suffixes)}" for f in FORMATS.values() if f.suffixes]
    return f"Folder ({', '.join(folders)}) or file ({', '.join(files)})."


register(Format("obj", "OBJ sequence", (), "facepipe.export.common:export_obj"))
register(Format("exr", "displacement maps per frame", (), "facepipe.export.exr_maps:export_exr",
                "facepipe.export.exr_maps:check_map_model"))
register(Format("wrinkle", "wrinkle-map set (PSD)", (), "facepipe.export.exr_maps:export_wrinkle",
                "facepipe.export.exr_maps:check_wrinkle_set_model"))
register(Format("usd", ".usdc with time-sampled points", (".usdc", ".usd", ".usda"), "facepipe.export.usd:export_usd"))
register(Format("mdd", "point caches", (".mdd",), "facepipe.export.mdd:export_mdd"))
register(Format("pc2", "point caches", (".pc2",), "facepipe.export.pc2:export_pc2"))
register(Format("textures", "layered textures per frame from a classified take (appearance.csv)", (),
                "facepipe.export.textures:export_textures",
                not_in_batch="layered textures come from a take's footage classified on its replay (facepipe "
                             "appearance classify), which a batch does not do: replay the takes, classify each "
                             "one's footage into its folder, then facepipe export OUT/<take> --format textures"))
