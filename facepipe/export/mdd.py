"""The ``mdd`` export: a replay's layer as an MDD point cache (the file format:
:mod:`facepipe.io.point_caches`)."""

from __future__ import annotations

from pathlib import Path

from facepipe.export.caches import export_cache, prepare_cache
from facepipe.export.registry import ExportOptions
from facepipe.io.point_caches import check_positions, write_mdd


def export_mdd(replay, dest: Path, options: ExportOptions) -> tuple[list[Path], dict]:
    """The replay's layer as an MDD cache (the ``mdd`` format's exporter)."""

    def write(path, positions, fps, progress):
        check_positions(positions, None, path)
        if not prepare_cache(path, options.force, options.resume):
            return None
        return write_mdd(path, positions, replay.times, progress=progress)

    return export_cache(replay, dest, options, "mdd", write, file_order=True)
