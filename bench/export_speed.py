"""Export benchmark: file sizes and write speed per format, and the OBJ writer against trimesh.

Runs on the ICT kit's neutral mesh when ``../shared`` is beside the checkout (a real scan
layout: quads, seams, two UDIM tiles), else on a given mesh (the benchmark's sample rig).
The animation is synthetic (smooth random motion of the rest mesh), since write speed does
not depend on what moves. Figures are medians of repeated runs; tests never assert them.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np

from bench.timing import median_time

ICT_MESH = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ict" / "neutral.obj"


def _size(path: Path) -> int:
    path = Path(path)
    return path.stat().st_size if path.is_file() else sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def synthetic_motion(rest: np.ndarray, n_frames: int, seed: int = 0) -> np.ndarray:
    """(T, V, 3) float32: the rest mesh moved by a few smooth waves, ~1 % of its size."""
    rng = np.random.default_rng(seed)
    size = float(np.ptp(rest, axis=0).max())
    k = rng.normal(size=(4, 3)) * 2 * np.pi / size
    amp = rng.normal(size=(4, 3)) * 0.01 * size
    t = np.linspace(0, 2 * np.pi, n_frames, endpoint=False)
    phase = rest @ k.T  # (V, 4)
    out = rest[None] + np.einsum("tvw,wc->tvc", np.sin(phase[None] + t[:, None, None]), amp)
    return out.astype(np.float32)


def _trimesh_writer(mesh):
    """The trimesh way to write the same frames: a triangle mesh with per-vertex UVs (split at
    the seams, as trimesh requires), exported with ``trimesh.exchange.obj.export_obj``."""
    import trimesh

    pairs, inverse = np.unique(np.stack([mesh.faces.ravel(), mesh.face_uvs.ravel()], axis=1), axis=0,
                               return_inverse=True)
    faces = inverse.reshape(-1, 3)
    visual = trimesh.visual.TextureVisuals(uv=mesh.uvs[pairs[:, 1]])

    def write(frame: np.ndarray, path: Path) -> None:
        tm = trimesh.Trimesh(vertices=frame[pairs[:, 0]], faces=faces, visual=visual, process=False)
        text = trimesh.exchange.obj.export_obj(tm, include_normals=False, include_texture=True)
        path.write_text(text if isinstance(text, str) else text[0])

    return write


def run_export_bench(work_dir: Path, mesh_path: Path | None = None, n_frames: int = 16, repeats: int = 3,
                     resolution: int = 2048, prefer_ict: bool = True, log=print) -> dict:
    """Time every export format on one mesh.

    Parameters
    ----------
    work_dir : scratch folder (emptied).
    mesh_path : mesh to use when the ICT kit is absent (or ``prefer_ict`` is False).
    n_frames : frames per sequence; repeats : timings are medians over this many runs.
    resolution : EXR map size per UDIM tile.

    Returns
    -------
    dict: mesh (name, vertices, polygons, tiles), per format {bytes, seconds, megabytes_per_second,
    ms_per_frame}, the raster set-up time, and ``obj_vs_trimesh`` (trimesh's time / ours).
    """
    from facepipe.export.common import write_obj_sequence
    from facepipe.export.exr_maps import write_displacement_maps
    from facepipe.io.mesh_read import load_mesh
    from facepipe.io.point_caches import write_mdd, write_pc2
    from facepipe.io.usd_file import write_usd
    from facepipe.export.uv_raster import mesh_raster

    work_dir = Path(work_dir)
    shutil.rmtree(work_dir, ignore_errors=True)
    work_dir.mkdir(parents=True)
    path = ICT_MESH if (prefer_ict and ICT_MESH.is_file()) or mesh_path is None else Path(mesh_path)
    mesh = load_mesh(path)
    pos = synthetic_motion(mesh.vertices, n_frames)
    times = np.arange(n_frames) / 30.0
    out: dict = {"mesh": {"path": str(path), "ict": path == ICT_MESH, "vertices": mesh.n_vertices,
                          "polygons": mesh.n_polygons}, "frames": n_frames, "repeats": repeats}

    def record(name, fn, target, frames=n_frames):
        seconds = median_time(fn, repeats)
        size = _size(target)
        out[name] = {"bytes": size, "seconds": seconds, "megabytes_per_second": size / 1e6 / seconds,
                     "ms_per_frame": seconds / frames * 1e3}
        log(f"export {name:8s}: {size / 1e6:8.1f} MB in {seconds:6.2f} s = {size / 1e6 / seconds:7.1f} MB/s "
            f"({seconds / frames * 1e3:.1f} ms/frame)")

    record("obj", lambda: write_obj_sequence(mesh, pos, work_dir / "obj", force=True), work_dir / "obj")
    trimesh_write = _trimesh_writer(mesh)
    (work_dir / "trimesh").mkdir()

    def trimesh_all():
        for t in range(n_frames):
            trimesh_write(pos[t].astype(np.float64), work_dir / "trimesh" / f"frame_{t + 1:04d}.obj")

    record("obj_trimesh", trimesh_all, work_dir / "trimesh")
    out["obj_vs_trimesh"] = out["obj_trimesh"]["seconds"] / out["obj"]["seconds"]
    log(f"OBJ sequence: {out['obj_vs_trimesh']:.1f}x faster than trimesh")
    record("mdd", lambda: write_mdd(work_dir / "a.mdd", pos, times), work_dir / "a.mdd")
    record("pc2", lambda: write_pc2(work_dir / "a.pc2", pos, times, 30.0), work_dir / "a.pc2")
    record("usd", lambda: write_usd(work_dir / "a.usdc", mesh, pos, times, 30.0), work_dir / "a.usdc")

    if mesh.uvs is not None:
        t0 = time.perf_counter()
        raster = mesh_raster(mesh, resolution, resolution)
        out["exr_raster_setup_seconds"] = time.perf_counter() - t0
        out["exr_tiles"] = list(raster.tiles)
        disp = pos - mesh.vertices[None].astype(np.float32)  # stands in for the detail layer
        frames = min(n_frames, 4)  # maps are slow: a few frames make the median
        for half in (True, False):
            name = f"exr_{'half' if half else 'float'}_{resolution}"
            dest = work_dir / name
            record(name, lambda: write_displacement_maps(raster, lambda s, e: disp[s:e], frames, dest, half=half,
                                                         force=True), dest, frames=frames)
        log(f"EXR raster set-up ({resolution}², {len(raster.tiles)} tiles): {out['exr_raster_setup_seconds']:.1f} s")
    shutil.rmtree(work_dir, ignore_errors=True)
    return out
