"""The export formats' registry: a registered format is exported by name, the command line's
--format choices and help are the registry's, every built-in exporter resolves."""

from __future__ import annotations

import click
import numpy as np
import pytest

from facepipe.cli.commands import export as export_command
from facepipe.errors import InputError
from facepipe.export import registry
from facepipe.export.dispatch import export_replay
from tests.conftest import run_cli


@pytest.fixture
def xyz_format():
    """A format registered for the test (removed afterwards): one text file of the layer's first
    frame, named by the options it was given."""
    seen = {}

    def export_xyz(replay, dest, options):
        positions = replay.layer(options.layer)
        path = dest / f"first_{options.start}.xyz"
        dest.mkdir(parents=True, exist_ok=True)
        np.savetxt(path, positions[0])
        seen.update(replay=replay, options=options)
        return [path], {"layer": options.layer, "frames": int(positions.shape[0])}

    registry.register(registry.Format("xyz", "text points", (".xyz",), export_xyz))
    try:
        yield seen
    finally:
        del registry.FORMATS["xyz"]


def test_a_registered_format_is_exported_by_name(rig, tmp_path, xyz_format):
    dest = tmp_path / "xyz"
    info = export_replay(rig.replays["psd"], "xyz", dest, layer="large", start=7)
    path = dest / "first_7.xyz"
    large = np.load(rig.replays["psd"] / "large_scale.npy")
    np.testing.assert_allclose(np.loadtxt(path), large[0], rtol=1e-15)
    assert xyz_format["options"].layer == "large" and xyz_format["replay"].path == rig.replays["psd"]
    # the dispatcher's report: the format's name, its details, then the files it wrote
    assert list(info)[:3] == ["format", "layer", "frames"]
    assert info["format"] == "xyz" and info["files"] == 1 and info["bytes"] == path.stat().st_size
    assert info["dest"] == str(dest)


def test_unknown_format_names_the_registered_ones(rig, tmp_path, xyz_format):
    with pytest.raises(InputError, match="choose one of obj, exr, wrinkle, usd, mdd, pc2, textures, xyz"):
        export_replay(rig.replays["psd"], "abc", tmp_path / "abc")


def test_cli_format_choices_and_help_come_from_the_registry():
    option = next(p for p in export_command.params if p.name == "fmt")
    assert isinstance(option.type, click.Choice)
    assert list(option.type.choices) == list(registry.FORMATS) == ["obj", "exr", "wrinkle", "usd", "mdd", "pc2",
                                                                         "textures"]
    assert option.help == ("obj: OBJ sequence; exr: displacement maps per frame; wrinkle: wrinkle-map set (PSD); "
                           "usd: .usdc with time-sampled points; mdd, pc2: point caches; textures: layered textures "
                           "per frame from a classified take (appearance.csv).")
    dest = next(p for p in export_command.params if p.name == "dest")
    assert dest.help == ("Folder (obj, exr, wrinkle, textures) or file (usd: .usdc/.usd/.usda, mdd: .mdd, "
                         "pc2: .pc2).")


def test_every_built_in_exporter_resolves():
    for fmt in registry.FORMATS.values():
        module, function = fmt.exporter.split(":")
        assert callable(getattr(__import__(module, fromlist=[function]), function)), fmt.name


def test_cli_exports_every_geometry_format(rig, tmp_path):
    """The registry's file formats through the command line: one file each, named by the suffix."""
    for name in ("usd", "mdd", "pc2"):
        out = tmp_path / f"take{registry.FORMATS[name].suffixes[0]}"
        assert run_cli("export", rig.replays["psd"], "--format", name, "-o", out, "-q") == 0
        assert out.is_file() and out.stat().st_size > 0
    assert run_cli("export", rig.replays["psd"], "--format", "pc2", "-o", tmp_path / "take.mdd", "-q") == 2
