"""The ``pc2`` export: a replay's layer as a PC2 point cache (the file format:
:mod:`facepipe.io.point_caches`). PC2 has no per-sample times, so a take with dropped frames
(non-uniform times) is refused."""

from __future__ import annotations

from pathlib import Path

from facepipe.export.caches import export_cache, prepare_cache
from facepipe.export.registry import ExportOptions
from facepipe.io.point_caches import check_pc2_times, check_positions, write_pc2


def export_pc2(replay, dest: Path, options: ExportOptions) -> tuple[list[Path], dict]:
    """The replay's layer as a PC2 cache (the ``pc2`` format's exporter)."""

    def write(path, positions, fps, progress):
        # checked before the existing file is weighed: --force would not make this take exportable
        check_positions(positions, None, path)
        check_pc2_times(replay.times, path)
        if not prepare_cache(path, options.force, options.resume):
            return None
        return write_pc2(path, positions, replay.times, fps, progress=progress)

    return export_cache(replay, dest, options, "pc2", write, file_order=True)
