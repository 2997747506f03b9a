"""Where a region's reading at rest comes from when the head turns or the light changes: the
neutral face rendered at yaws of -15 to 15 degrees under the test footage's two lights and a key
light with a fill light from the other side (a shading no single light gives), each
region's Q (no rest floor) classified with the shading facepipe fits to the frame, and with the
renderer's exact shading at the template points (known for rendered footage only).

Readings that agree across the conditions with the exact shading but not with the fitted one
come from the light fit, not from the sampling or the pose. Needs the rendered ICT kit of
bench/appearance_ict.py (its --out folder: examples and config). Writes bench/appearance_light.json
(or --json). Run from the repository root:

    python bench/appearance_light.py [--out /tmp/ict_appearance]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's facepipe, however it is run

from facepipe.appearance_sample import key_and_fill, make_scene, neck_pivot, other_light, render_frame, skin_texture
from facepipe.core import appearance as ap, lighting
from facepipe.io.camera_file import read_camera
from facepipe.io.config import load_config
from facepipe.io.footage import to_gray
from facepipe.io.mesh_read import load_mesh
from facepipe.pipeline.appearance import region_bank
from facepipe.pipeline.appearance_build import build_appearance
from facepipe.pipeline.appearance_light import frame_shading
from facepipe.pipeline.appearance_points import sample_template_frames, template_positions

KIT = Path(__file__).resolve().parents[2] / "shared" / "data" / "ict"
YAWS = (-15.0, -7.5, 0.0, 7.5, 15.0)


def _yaw(world: np.ndarray, degrees: float, pivot: np.ndarray) -> np.ndarray:
    a = np.deg2rad(degrees)
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    return (world - pivot) @ R.T + pivot


def rest_readings(model, gray: np.ndarray, camera_positions: np.ndarray, scene, bank) -> dict:
    """Raw Q (R,) of one frame with the fitted shading and with the scene's exact shading."""
    points = template_positions(camera_positions, model)
    patches, _, seen = sample_template_frames(gray, camera_positions, model, points)
    fitted, normals, _, _ = frame_shading(gray, camera_positions, model)
    exact = scene.shading(normals).reshape(fitted.shape)  # the renderer's, at the template points' normals
    out = {}
    for name, shading in (("fitted", fitted), ("exact", exact)):
        q, _ = ap.classify_regions(patches / shading, bank, model.shading, seen, model.min_seen, model.peak_interpolation)
        out[name] = q[0]
    return out


def main() -> None:
    ap_ = argparse.ArgumentParser()
    ap_.add_argument("--out", default="/tmp/ict_appearance", help="bench/appearance_ict.py's folder")
    ap_.add_argument("--json", default="bench/appearance_light.json")
    ap_.add_argument("--light-model", choices=lighting.LIGHT_MODELS, default=None,
                     help="the light the model divides out (default: the config's, else facepipe's default)")
    args = ap_.parse_args()
    out = Path(args.out)
    if not (out / "appearance.toml").is_file():
        sys.exit(f"no rendered kit in {out}: run python bench/appearance_ict.py --out {out} first")
    mesh = load_mesh(KIT / "neutral.obj")
    config = load_config(out / "appearance.toml")
    if args.light_model is not None:
        config.appearance.light_model = args.light_model
    model, _ = build_appearance(config, mesh, read_camera(config.appearance.camera))
    model = model.without_rest_floors()  # the raw reading
    surface = [r for r, region in enumerate(config.appearance.regions) if not region.card]  # no eyeballs drawn here
    texture_size = int(config.appearance.texture_size)
    skin = skin_texture(texture_size, 0)  # the kit's skin (seed 0): the neutral texture
    scene = make_scene(mesh.vertices, model.camera.width)
    bank = region_bank(model)
    corner_uv = mesh.uvs[mesh.face_uvs]
    pivot = neck_pivot(mesh.vertices)
    rows = []
    for light_name, lit in (("kit light", scene), ("other light", other_light(scene)),
                            ("key and fill", key_and_fill(scene))):
        for yaw in YAWS:
            world = _yaw(mesh.vertices, yaw, pivot)
            image = np.clip(render_frame(world, mesh.faces, corner_uv, skin, lit), 0.0, 1.0)
            cams = model.to_camera(world[None])
            readings = rest_readings(model, to_gray(image)[None], cams, lit, bank)
            rows.append({"light": light_name, "yaw": yaw,
                         **{k: {model.names[r]: float(v[r]) for r in surface} for k, v in readings.items()}})
    spread = {k: {model.names[r]: float(np.ptp([row[k][model.names[r]] for row in rows])) for r in surface}
              for k in ("fitted", "exact")}
    for k in ("fitted", "exact"):
        print(f"{k:7s} shading, rest Q over {len(rows)} poses and lights (min-max):")
        for r in surface:
            values = [row[k][model.names[r]] for row in rows]
            print(f"  {model.names[r]:14s} {min(values):.2f} - {max(values):.2f}")
    difference = float(np.mean([abs(row["fitted"][m] - row["exact"][m]) for row in rows for m in row["fitted"]]))
    print(f"mean |fitted - exact| rest reading: {difference:.4f} layer ({model.light_model} light)")
    Path(args.json).write_text(json.dumps({"light_model": model.light_model, "conditions": rows, "spread": spread,
                                           "mean_fitted_minus_exact": difference}, indent=1))


if __name__ == "__main__":
    main()
