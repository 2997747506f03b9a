"""The ``usd`` export: a replay's layer as a USD layer on the rest mesh, ``.usdc``, ``.usd`` or
``.usda`` (the layer's contents: :mod:`facepipe.io.usd_file`)."""

from __future__ import annotations

from pathlib import Path

from facepipe.export.caches import export_cache, prepare_cache
from facepipe.export.registry import ExportOptions
from facepipe.io.point_caches import check_positions
from facepipe.io.usd_file import write_usd


def export_usd(replay, dest: Path, options: ExportOptions) -> tuple[list[Path], dict]:
    """The replay's layer as a USD layer on the rest mesh (the ``usd`` format's exporter)."""

    def write(path, positions, fps, progress):
        model = replay.load_model(options.model_path)
        mesh = model.mesh()
        check_positions(positions, mesh.n_vertices, path)
        if not prepare_cache(path, options.force, options.resume):
            return None
        return write_usd(path, mesh, positions, replay.times, fps, units=model.meta.get("units", ""),
                         up_axis=options.up_axis, frame_numbers=replay.frame_numbers,
                         metadata={"layer": options.layer, "replay": str(replay.path)}, progress=progress)

    return export_cache(replay, dest, options, "usd", write)
