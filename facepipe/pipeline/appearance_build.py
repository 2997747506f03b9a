"""Building an appearance model (``facepipe appearance build CONFIG``; Fidaleo et al. 2000, §V).

The rest mesh's UV layout is rasterised once (every texel's triangle and barycentric
coordinates); each example frame is unwrapped into it through its geometry and the camera
(texels facing away are taken from the neutral texture); a region's layers are its example
frames' texels inside its vertex group's UV triangles, with an alpha ramp into the neutral
texture at its border. Its template is a template_size² grid of UV points in the template
rectangle, located in the UV triangles once (fixed barycentric coordinates), also shifted
diagonally by half a grid step for the offset samples; the templates are those points' samples
in the example frames. Each region's rest floor is the highest Q it reads in the example frames
where it is at rest (:func:`calibrate_rest`). A ``card`` region (an eye) lies on a card across
the hole its vertex group rims (:mod:`facepipe.pipeline.appearance_cards`): the
cards' triangles follow the mesh's, their vertices its vertices, in a free square of the UV
layout, and every frame's positions are extended with them
(:meth:`facepipe.io.appearance_file.AppearanceModel.with_cards`). With a light fit the neutral
texture and every layer are divided by the shading of their own frame
(:func:`facepipe.pipeline.appearance_texture.to_albedo`): the model holds the skin's albedo.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from facepipe.core import appearance as ap, layered_texture, lighting
from facepipe.core.camera import Camera, project_distorted
from facepipe.core.card_motion import LEAST_FIRST_SHIFT, card_motion, card_shifts
from facepipe.core.raster import udim_tile_numbers
from facepipe.errors import InputError
from facepipe.io.appearance_file import AppearanceModel
from facepipe.io.footage import frames_at, open_footage, read_frames_of, to_gray
from facepipe.parallel import serial_blas
from facepipe.pipeline.appearance import (OFF_FACE_RATIO, TakeGeometry, check_frame_size, classify_decoded,
                                          examples_at_rest, read_patches, read_take_geometry, region_bank,
                                          sample_patches)
from facepipe.pipeline.appearance_cards import card_depths, region_cards, template_rect
from facepipe.pipeline.appearance_light import frame_light_residuals
from facepipe.pipeline.appearance_points import (point_facing, point_normals, points_seen_well, region_template,
                                                 surface_points, texel_map, triangle_normals, unwrap,
                                                 with_unseen_margin)
from facepipe.pipeline.appearance_texture import to_albedo

__all__ = ["build_appearance", "calibrate_rest", "explain_rest"]


def _example_frames(cfg, footage_numbers_needed, geometry: TakeGeometry, camera: Camera) -> dict:
    """The example frames the regions name: frame number → (RGB image, camera-space positions).
    Each is the footage's frame of that number, or the one at the geometry's own time for it
    (:func:`facepipe.io.footage.frames_at`)."""
    index = {int(n): i for i, n in enumerate(geometry.numbers)}
    needed = np.array(sorted(footage_numbers_needed), dtype=np.int64)
    for n in needed:
        if int(n) not in index:
            raise InputError(f"example frame {int(n)} has no geometry", path=cfg.geometry,
                             hint="the geometry's frame numbers must include the example frames")
    rows = np.array([index[int(n)] for n in needed], dtype=np.int64)
    footage = open_footage(cfg.footage)
    at, _ = frames_at(footage, needed, None if geometry.times is None else geometry.times[rows])
    frames = {}
    for shown, image, problem in read_frames_of(footage, at):
        for k in shown:
            n = int(needed[k])
            if image is None:
                raise InputError(f"example frame {n}: {problem}", path=cfg.footage,
                                 hint="every frame an [appearance.regions] table names must be readable")
            check_frame_size(image, camera, n, cfg.footage)
            frames[n] = (image, geometry.positions[rows[k]])
    return frames


def group_masks(cfg, n_vertices: int, config_path) -> dict:
    """Region name → (V,) mask of its vertex group, each group file read and checked once."""
    masks = {}
    for region in cfg.regions:
        masks[region.name] = np.zeros(n_vertices, dtype=bool)
        masks[region.name][_read_group(region, n_vertices, config_path)] = True
    return masks


def regions_tile(cfg, mesh, groups: dict, tile_of: np.ndarray, in_udim: np.ndarray, config_path) -> int:
    """The UDIM tile every region lies on (1001 where none has a triangle in the UDIM range): the
    tile of a region's triangles (those its vertex group holds whole; a card region's, those that
    touch its rim). A region over two tiles, or regions on different tiles, are refused: a region's
    layers are one box of one tile's texture, and the layered texture is one tile's."""
    where = {}
    for region in cfg.regions:
        inside = groups[region.name][mesh.faces]
        triangles = (inside.any(axis=1) if region.card else inside.all(axis=1)) & in_udim
        found = np.unique(tile_of[triangles])
        if len(found) > 1:
            raise InputError(f"region {region.name}: its vertex group's triangles lie on UDIM tiles "
                             f"{', '.join(map(str, found))}", path=region.vertices,
                             hint="a region's layers are one box of one tile's texture: lay the region out on one "
                                  "tile, or split it into a region per tile")
        if len(found):
            where[region.name] = int(found[0])
    if len(set(where.values())) > 1:
        raise InputError("the regions lie on different UDIM tiles: " + ", ".join(f"{n} on {t}" for n, t in where.items()),
                         path=config_path, hint="lay every region out on one tile (the layered texture's); the "
                                                "other tiles keep the neutral texture")
    return next(iter(where.values()), 1001)


def build_appearance(config, mesh, camera: Camera, progress=None) -> tuple[AppearanceModel, dict]:
    """Build the appearance model from a config's ``[appearance]`` table (see the module docstring)."""
    cfg = config.appearance
    faces = mesh.faces
    if mesh.face_uvs is None:
        raise InputError("the rest mesh has no UVs: the layered texture needs its UV layout", path=config.mesh)
    corner_uv = mesh.uvs[mesh.face_uvs]
    R = np.asarray(cfg.camera_rotation, dtype=np.float64)
    t = np.asarray(cfg.camera_translation, dtype=np.float64)
    geometry = read_take_geometry(cfg.geometry, mesh.n_vertices)
    positions = geometry.positions
    if geometry.in_camera and not (np.allclose(R, np.eye(3)) and np.allclose(t, 0.0)):
        raise InputError("the example geometry is a 2D take's replay, already in its camera's coordinates, and the "
                         "config moves it again by camera_rotation/camera_translation", path=config.path,
                         hint="leave camera_rotation and camera_translation out of [appearance] for this geometry")
    # the regions' UDIM tile: their layered texture's (the others keep the neutral texture)
    tile_of, in_udim = udim_tile_numbers(corner_uv)
    groups = group_masks(cfg, mesh.n_vertices, config.path)
    home = regions_tile(cfg, mesh, groups, tile_of, in_udim, config.path)
    cards, card_of = region_cards(cfg, mesh, groups, corner_uv, positions, config.path, home)
    if cards is not None:  # the cards' triangles after the mesh's, their vertices after its vertices
        faces = np.concatenate([faces, cards.faces])
        corner_uv = np.concatenate([corner_uv, cards.corner_uv])
        positions = cards.extend(positions)
    needed = {cfg.neutral_frame} | {f for r in cfg.regions for f in r.frames} | set(cfg.rest_frames)
    frames = _example_frames(cfg, needed, replace(geometry, positions=positions), camera)  # (the cards' too)
    cam_pos = {n: positions_world @ R.T + t for n, (_, positions_world) in frames.items()}
    S = cfg.texture_size
    texel_face, texel_bary = texel_map(corner_uv, S, home)
    neutral_cam = cam_pos[cfg.neutral_frame]
    covered = texel_face >= 0
    cos = ap.facing(triangle_normals(neutral_cam, faces, texel_face[covered]),
                    surface_points(neutral_cam, faces, texel_face[covered], texel_bary[covered]))
    normal_sign = 1.0 if np.median(cos) >= 0 else -1.0
    depth_fits, notes = {}, []
    if cards is not None:  # each card's depth, and the frames' card vertices there
        cards, depth_fits = card_depths(cfg, cards, card_of, frames, faces, corner_uv, camera, normal_sign,
                                        config.path, notes)
        frames = {n: (image, cards.extend(p[:mesh.n_vertices])) for n, (image, p) in frames.items()}
        cam_pos = {n: positions_world @ R.T + t for n, (_, positions_world) in frames.items()}
        neutral_cam = cam_pos[cfg.neutral_frame]
    neutral, seen = unwrap(frames[cfg.neutral_frame][0], neutral_cam, faces, texel_face, texel_bary, camera,
                           min_facing=cfg.min_facing, normal_sign=normal_sign)
    # texels the neutral frame does not show (edge-on, behind the head) continue the skin around them
    neutral = layered_texture.fill_unseen(neutral, seen) if seen.any() else np.full_like(neutral, 0.5)
    # the layout's other UDIM tiles (a head's scalp, neck, ears) hold no region: their neutral texture
    tiles = {t: _tile_neutral(frames[cfg.neutral_frame][0], neutral_cam, faces, texel_map(corner_uv, S, t), camera,
                              cfg, normal_sign, np.median(neutral[seen], axis=0) if seen.any() else 0.5)
             for t in np.unique(tile_of[in_udim]).tolist() if t != home}
    # the light is fitted on the skin alone: a card's texels show an eyeball, whose moving iris
    # and wet sheen follow no shading of the card's plane
    light = _example_light(neutral, seen & (texel_face < len(mesh.faces)), neutral_cam, faces, texel_face, texel_bary,
                           normal_sign, cfg.light_model) if cfg.light_fit else None
    weights = ap.coefficient_weights(cfg.template_size, cfg.scale_weights)
    names, volumes, alphas, boxes, tfaces, tbarys, templates, indices = [], [], [], [], [], [], [], []
    relative = cfg.shading and cfg.shading_reference == "neutral"  # the layers' shading fitted against the neutral's
    template_patches = []  # the layers' samples before normalising: a partly seen sample's templates are normalised from them
    facing_examples, masks, layer_seen, orders, surfaces = [], [], [], [], {}
    if not in_udim.all():
        notes.append(f"{int((~in_udim).sum())} triangles of the rest mesh (the first: {int(np.argmin(in_udim))}) have "
                     "UVs outside the UDIM range (u in 0–10, v ≥ 0): the textures leave them out")
    for region in cfg.regions:
        triangles = np.zeros(len(faces), dtype=bool)
        if region.name in card_of:
            triangles[len(mesh.faces):] = cards.card == card_of[region.name]
        else:
            triangles[:len(mesh.faces)] = groups[region.name][mesh.faces].all(axis=1)
        rect = template_rect(region, cards, card_of)
        vol, alpha, box, seen_in = _region_volume(region, config, faces, triangles, frames, cam_pos, texel_face,
                                                  texel_bary, camera, neutral, cfg, normal_sign)
        layer_seen.append(seen_in)
        face, bary = region_template(region, rect, corner_uv, cfg.template_size, config.path)
        gray = [to_gray(frames[f][0]) for f in region.frames]
        patches = []
        facing_examples.append(np.min([point_facing(cam_pos[f], faces, face, bary, normal_sign)
                                       for f in region.frames], axis=0))
        seen_well, pixels = points_seen_well(np.stack([cam_pos[f] for f in region.frames]), faces, face[0], bary[0],
                                             camera, cfg.template_size, normal_sign, cfg.min_point_facing,
                                             cfg.occlusion, cfg.min_relative_facing, mesh.faces)
        stable = with_unseen_margin(seen_well, pixels, cfg.unseen_margin)
        # a small template in few pixels (a lid at low resolution): where the margin would take too
        # much of it, a narrower one (halved twice, then none), since matching on too little of
        # it is worse than reading part of a fold's edge
        margin, full = cfg.unseen_margin, stable.mean()
        while stable.mean() < cfg.min_seen and margin > 0:
            margin = margin / 2.0 if margin > cfg.unseen_margin / 4.0 else 0.0
            stable = with_unseen_margin(seen_well, pixels, margin)
        if margin != cfg.unseen_margin and stable.mean() >= cfg.min_seen:
            notes.append(f"region {region.name}: the unseen margin ({cfg.unseen_margin:g} px) would leave {full:.0%} "
                         f"of its template, under min_seen = {cfg.min_seen:g}: "
                         + (f"kept with {margin:g} px" if margin > 0 else "its points kept without it")
                         + f" ({stable.mean():.0%})")
        if stable.mean() < cfg.min_seen:
            raise InputError(f"region {region.name}: only {stable.mean():.0%} of its template is seen well (in the "
                             f"image, not hidden, not edge-on) in every example frame, under min_seen = "
                             f"{cfg.min_seen}", path=config.path,
                             hint="move the template to where every example shows the region, or lower "
                                  "min_point_facing / min_seen")
        masks.append(stable)
        for g, f in zip(gray, region.frames):
            X = surface_points(cam_pos[f], faces, face[0], bary[0])
            values, inside = ap.bilinear_sample(g, project_distorted(camera, X))
            if not inside.all():
                raise InputError(f"region {region.name}: its template leaves the image in example frame {f}",
                                 path=config.path, hint="choose example frames where the region is in view")
            if light is not None:  # the example's own shading out: the templates hold the albedo's structure
                normals = point_normals(cam_pos[f][None], faces, face[0], bary[0], normal_sign)[0]
                values = values / lighting.light_shading(normals, light["light"])
            patches.append(values.reshape(cfg.template_size, cfg.template_size))
        # the templates, and the coefficients kept, of the stable points alone: what rolls out of
        # view in some example (an eyelid into its socket) neither dominates the selection nor
        # takes up the normalisation's plane
        size = cfg.template_size
        stack, mask = np.stack(patches), stable.reshape(size, size)
        order, kept = _shading_surface(cfg, region, stack, mask, weights)
        if cfg.shading:  # (else the patches are divided by their mean alone)
            surfaces[region.name] = {"surface": ap.SHADING_ORDERS[order], "contrast_kept": kept}
        reference = ap.neutral_reference(stack, mask) if relative else None
        coeffs = ap.haar_coefficients(ap.normalise_patches(stack, order if cfg.shading else 0, mask, reference))
        orders.append(order)
        names.append(region.name)
        volumes.append(vol.astype(np.float32))
        alphas.append(alpha.astype(np.float32))
        boxes.append(box)
        tfaces.append(face)
        tbarys.append(bary)
        templates.append(coeffs)
        template_patches.append(stack.reshape(len(stack), -1))
        indices.append(ap.select_coefficients(coeffs, cfg.keep))
        if progress is not None:
            progress(1)
    model = AppearanceModel(names, camera, R, t, faces, normal_sign, np.stack(tfaces), np.stack(tbarys), templates,
                            indices, weights, cfg.template_size, cfg.min_facing, cfg.decay,
                            neutral.astype(np.float32), volumes, alphas, np.asarray(boxes, dtype=np.int64),
                            cfg.shading, *((light["face"], light["bary"], light["albedo"]) if light else (None,) * 3),
                            corner_uv.astype(np.float32), cfg.min_seen, cfg.occlusion, cfg.min_point_facing,
                            np.stack(facing_examples).astype(np.float32), np.stack(masks),
                            card_rest=None if cards is None else cards.rest,
                            card_stable=None if cards is None else cards.stable,
                            card_stable_rest=None if cards is None else cards.stable_rest,
                            light_colour=None if light is None else light["colour"].astype(np.float32),
                            tiles=np.array(list(tiles), dtype=np.int64) if tiles else None,
                            tile_neutral=np.stack([t["texture"] for t in tiles.values()]) if tiles else None,
                            tile=home, shading_orders=np.asarray(orders, dtype=np.int64), template_patches=template_patches,
                            peak_interpolation=cfg.peak_interpolation, min_event=cfg.min_event,
                            light_model=cfg.light_model if light is not None else "sh9",
                            light_point_albedo=None if light is None else light["point_albedo"],
                            # the cards' texels become albedo with the skin's (to_albedo), shaded alike
                            cards_shaded=light is not None and cards is not None,
                            frame_facing_share=cfg.frame_facing_share,
                            # the stream and the textures carry the light the classification fits
                            stream_light="point" if light is not None and cfg.light_model == "point" else "sh9",
                            shading_reference=cfg.shading_reference)
    if light is not None:
        to_albedo(model, cfg, frames, cam_pos, seen, layer_seen, (texel_face, texel_bary), tiles)
    numbers = sorted(frames)
    grays, cams = np.stack([to_gray(frames[n][0]) for n in numbers]), np.stack([cam_pos[n] for n in numbers])
    motions = {}
    if cards is not None and cfg.card_motion_check:
        # before the examples are read: the check holds in their readings, and so in the floors
        motions = card_motions(model, cfg, numbers, grays, cams, notes)
    # the example frames classified once: their readings set the rest floors, their lights the residual
    readings = classify_decoded(grays, cams, model, region_bank(model)) if cfg.rest_calibration else None
    explained = {}
    if cfg.rest_calibration and cfg.rest_explain > 0:
        readings, explained = explain_rest(model, cfg, numbers, grays, cams, readings, notes)
    rest = calibrate_rest(model, cfg, numbers, readings, notes, explained) if cfg.rest_calibration else {}
    if light is not None:
        model.light_residual = _example_light_residual(
            frame_light_residuals(grays, cams, model) if readings is None else readings.light_residual, numbers, notes)
    tilt = _shading_tilt(model, notes) if cfg.shading else None
    info = {"regions": names, "layers": model.layer_counts, "texture_size": S, "tiles": model.all_tiles,
            "albedo": model.albedo, "rest": rest, "shading_tilt_q": tilt,
            "rest_path_tolerance": model.rest_tolerance if model.rest_readings is not None else 0.0,
            "shading": surfaces, "shading_reference": model.shading_reference if cfg.shading else None,
            "peak_interpolation": model.peak_interpolation, "notes": notes}
    if light is not None:
        info["light"] = {"model": model.light_model, "examples": light["light"].tolist(),
                         "residual": model.light_residual}
    if cards is not None:
        info["cards"] = {name: {"uv_square": cards.squares[c].tolist(),
                                "rim_vertices": int(cards.rim_sizes[c]),
                                "carried_by_vertices": int(len(cards.stable)),
                                "depth": float(cards.depths[c]),
                                "depth_fitted": bool(depth_fits.get(name, {}).get("fitted", False)),
                                **({"motion_check": motions[name]} if name in motions else {}),
                                **({"depth_parallax_px": round(depth_fits[name]["parallax"], 2),
                                    "depth_frames": depth_fits[name]["frames"]} if name in depth_fits else {})}
                         for name, c in card_of.items()}
    return model, info


def card_motions(model: AppearanceModel, cfg, numbers: list, grays: np.ndarray, cams: np.ndarray, notes: list) -> dict:
    """Set each card region's motion check (``model.card_motion``,
    :func:`facepipe.core.card_motion.card_motion`) from the example frames (their ``numbers``,
    luminance and geometry in camera space): its layers' shifts against its neutral template, and
    those of the frames where it is at rest and seen. Returns per card region what the build
    reports: the layers' shifts, the least shift read as motion, the at-rest frames that move
    the card across its path (or why it has no check)."""
    model.card_motion = [None] * len(model.names)
    cards = [r for r, region in enumerate(cfg.regions) if region.card]
    patches, visible, seen, *_ = sample_patches(grays, cams, model)
    at_rest = examples_at_rest(cfg, numbers) & visible
    row = {n: i for i, n in enumerate(numbers)}
    report = {}
    for r in cards:
        name, frames = model.names[r], cfg.regions[r].frames
        neutral = row[frames[0]]  # against what the neutral frame shows of the card, where it shows it
        reference, reference_seen = patches[neutral, r, 0], seen[neutral, r, 0]
        shifts = card_shifts(reference, reference_seen, patches[:, r, 0], seen[:, r, 0])
        layers = shifts[[row[f] for f in frames]]
        motion = card_motion(reference, reference_seen, layers, shifts[at_rest[:, r]])
        lengths = np.linalg.norm(layers[1:], axis=1)
        entry = {"layer_shifts_texels": [None if not np.isfinite(x) else round(float(x), 2) for x in lengths]}
        if motion is None:
            moved = (f"moves its card's content {lengths[0]:.2f} texels (under {LEAST_FIRST_SHIFT:g})"
                     if np.isfinite(lengths[0]) else "shows too little of its card to measure how far it moves")
            notes.append(f"region {name}: its first layer {moved}: read by its match alone, without the motion check")
        else:
            across = [int(n) for n, s in zip(np.asarray(numbers)[at_rest[:, r]], shifts[at_rest[:, r]])
                      if np.linalg.norm(s) > motion.least]
            entry.update(least_texels=round(motion.least, 2), across_frames=across)
            notes.append(f"region {name}: read only where its card's content moves along its layers' path (more "
                         f"than {motion.least:.2f} texels, half its first layer's shift)"
                         + (f"; at-rest example frame{'s' if len(across) > 1 else ''} {', '.join(map(str, across))} "
                            f"move{'' if len(across) > 1 else 's'} it otherwise" if across else ""))
        model.card_motion[r] = motion
        report[name] = entry
    return report


#: A rest floor is kept to at most this many layers; above half a layer the build says so.
MOST_REST_FLOOR = ap.MOST_REST_FLOOR
#: At most this many example frames are explained away in one region's match.
MOST_EXPLAINED = 3
#: An example frame is explained away only where each of the region's layer steps keeps at least
#: this share of its (squared) length: else the region's own motion would go with it.
LEAST_STEP_KEPT = 0.25


def _example_light_residual(residual: np.ndarray, numbers: list, notes: list) -> float:
    """The example frames' (``numbers``) median light residual (:func:`frame_light_residuals`:
    ``residual``), which classification checks footage against; an example frame leaving more
    than :data:`~facepipe.pipeline.appearance.OFF_FACE_RATIO` times it unexplained is noted: its
    geometry misses the face in its image (another frame's geometry, a shifted frame number), and
    the layers taken from it are not that face."""
    median = float(np.nanmedian(residual))
    for number, r in zip(numbers, residual):
        if median > 0 and r > OFF_FACE_RATIO * median:
            notes.append(f"example frame {number}: its light leaves {r / median:.0f}× the other example frames' share "
                         "of the face's brightness unexplained: its geometry seems to miss the face in the image "
                         "(check the frame's number and its geometry)")
    return median


def explain_rest(model: AppearanceModel, cfg, numbers: list, grays: np.ndarray, cams: np.ndarray, readings,
                 notes: list) -> tuple:
    """Explain away, in each region's match, the example frames where it is at rest but reads
    above ``cfg.rest_explain`` layers: another expression moves its patch along its layers (an
    eye looking up raises the lid the eyelid's templates close). Greedily, the highest such
    reading first, each frame's patch difference from the neutral template becomes one of the
    region's ``rest_nuisance`` directions (:class:`facepipe.core.appearance.RegionBank`) and the
    example frames are read again; at most :data:`MOST_EXPLAINED` per region.

    Only a frame that shows the region wholly (its centre sample sees every stable point) is
    explained away, and only while it is the region's highest reading at rest: a partly covered
    patch (a lid over the eyeball) changes with how far it is covered, which one direction does
    not describe. A frame whose direction would leave less than :data:`LEAST_STEP_KEPT` of any
    layer step is kept (and noted): it looks like the region's own motion.

    Returns the example frames' readings (:class:`~facepipe.pipeline.appearance.FrameReadings`)
    with the explained-away directions in the match, and per region the frame numbers explained.
    """
    at_rest = examples_at_rest(cfg, numbers)
    patches, visible, seen, *_ = sample_patches(grays, cams, model)  # sampled once, read again as directions add
    bank = region_bank(model)
    R, size = len(model.names), model.template_size
    wholly = (seen[:, :, 0] & bank.masks.reshape(R, size, size)).sum(axis=(-2, -1)) >= bank.mask_count  # (F, R)
    directions, frames, done = [[] for _ in range(R)], [[] for _ in range(R)], np.zeros(R, dtype=bool)
    for _ in range(MOST_EXPLAINED):
        q = np.where(at_rest & np.isfinite(readings.q), readings.q, -np.inf)
        added = False
        for r in np.flatnonzero(~done):
            f = int(np.argmax(q[:, r]))
            if not (q[f, r] > cfg.rest_explain and wholly[f, r]) or numbers[f] in frames[r]:
                done[r] = True
                continue
            direction = ap.rest_direction(bank, patches[f, r, 0], r, model.shading)
            kept = ap.kept_step_shares(bank, r, np.array(directions[r] + [direction]))
            if kept.min() < LEAST_STEP_KEPT:
                notes.append(f"region {model.names[r]}: example frame {numbers[f]} reads Q {q[f, r]:.2f} at rest but "
                             f"changes its patch much as its own layers do (a layer step would keep "
                             f"{kept.min():.0%}): not explained away")
                done[r] = True
                continue
            directions[r].append(direction)
            frames[r].append(int(numbers[f]))
            added = True
        done |= np.array([len(d) >= MOST_EXPLAINED for d in directions])
        if not added:
            break
        model.rest_nuisance = [np.array(d) if d else None for d in directions]
        with serial_blas():  # small products (classify_chunk's reason)
            q_read, seen_read, off_path = read_patches(patches, visible, seen, model, region_bank(model))
        readings = replace(readings, q=q_read, visible=seen_read, off_path=off_path)
    explained = {model.names[r]: frames[r] for r in range(R) if frames[r]}
    for name, explained_frames in explained.items():
        notes.append(f"region {name}: example frame{'s' if len(explained_frames) > 1 else ''} "
                     f"{', '.join(map(str, explained_frames))} (at rest, reading above {cfg.rest_explain:g} layers) "
                     "explained away in its match")
    return readings, explained


def calibrate_rest(model: AppearanceModel, cfg, numbers: list, readings, notes: list,
                   explained: dict | None = None) -> dict:
    """Set the model's rest floors from the example frames (their ``numbers``, in order, and their
    readings: :class:`~facepipe.pipeline.appearance.FrameReadings` of
    :func:`~facepipe.pipeline.appearance.classify_decoded`), and return them per region
    (with the frames ``explained`` away in each region's match: :func:`explain_rest`).

    A region is at rest in every example frame but its own layers above the neutral one (the
    neutral frame, the other regions' examples and the ``rest_frames``, other expressions where
    no region is active: frames where the rest of the face moves): the highest Q it reads there
    is its floor (:func:`facepipe.core.appearance.rest_floor`), which classification measures Q
    from. A floor above half a layer is noted: the region's template
    sees another region's motion (a brow lowered over the lid), and the floor hides that much of
    its own first layer.
    """
    at_rest = examples_at_rest(cfg, numbers)
    q = readings.q
    floor, row = ap.rest_floor(q, at_rest, MOST_REST_FLOOR)
    model.rest_floor = floor
    model.rest_tolerance = float(cfg.rest_path_tolerance)
    model.rest_noise = float(cfg.rest_explain)  # at-rest readings up to it are noise: they hide every reading
    if cfg.rest_path_tolerance > 0 and readings.off_path is not None:
        # each at-rest reading hides only readings as far off the path as it (conditional_floor)
        kept = at_rest & np.isfinite(q)
        model.rest_readings = np.where(kept, q, np.nan)
        model.rest_off_path = np.where(kept, readings.off_path, np.nan)
    explained = explained or {}
    out = {}
    for r, name in enumerate(model.names):
        frame = int(numbers[row[r]]) if row[r] >= 0 else None
        out[name] = {"floor": float(floor[r]), "frame": frame, "explained": explained.get(name, [])}
        if frame is None:
            notes.append(f"region {name}: no example frame shows it at rest (seen): its rest floor is 0")
        elif q[row[r], r] > 0.5 * MOST_REST_FLOOR:
            notes.append(f"region {name} reads Q {q[row[r], r]:.2f} at rest in example frame {frame}: its "
                         f"template sees that frame's motion; Q is measured from {floor[r]:.2f}")
    return out


def _tile_neutral(image: np.ndarray, neutral_cam: np.ndarray, faces: np.ndarray, texels, camera: Camera, cfg,
                  normal_sign: float, fill) -> dict:
    """The neutral frame's texture on another UDIM tile (its texel map ``texels``), what the
    frame does not show filled from what it does (``fill``, a colour, where it shows nothing of
    the tile): {"texture", "seen", "texels"}."""
    texture, seen = unwrap(image, neutral_cam, faces, *texels, camera, min_facing=cfg.min_facing,
                           normal_sign=normal_sign)
    texture = layered_texture.fill_unseen(texture, seen) if seen.any() else np.broadcast_to(np.asarray(fill, dtype=np.float64),
                                                                                 texture.shape).copy()
    return {"texture": texture.astype(np.float32), "seen": seen, "texels": texels}


def _example_light(neutral, seen, neutral_cam, faces, texel_face, texel_bary, normal_sign, light_model: str,
                   samples: int = 2000):
    """The example footage's light fitted over the neutral texture's texels (their albedo taken
    as uniform: the fit is robust to what differs; its scale such that the median texel's shading
    is 1), and ``samples`` texels spread over the surface, where each frame's light will be fitted,
    with their albedo under it (grey, and colour: RGB over the grey shading).

    ``light`` is the light the templates are divided by, under ``light_model``
    (:data:`facepipe.core.lighting.LIGHT_MODELS`). ``albedo`` is derived under the nine-term
    light; with the point light also ``point_albedo``, under it: each light is fitted over the
    albedo its own model gives. ``colour``, under the light the stream and the textures carry:
    the point light where it is the model's, else the nine terms."""
    rows, cols = np.nonzero(seen & (texel_face >= 0))
    if len(rows) < 50:
        return None
    pick = np.random.default_rng(0).choice(len(rows), size=min(samples * 4, len(rows)), replace=False)
    rows, cols = rows[pick], cols[pick]
    face, bary = texel_face[rows, cols], texel_bary[rows, cols]
    normals = point_normals(neutral_cam[None], faces, face, bary, normal_sign)[0]
    lum = to_gray(neutral[rows, cols])

    def scaled(light):
        # the neutral frame's shading 1 on the median texel: the albedo it gives (and the layers')
        # is about as bright as the footage, in the range images hold
        return light / float(np.median(lighting.light_shading(normals, light)))

    light = scaled(lighting.fit_light(lum, np.ones(len(lum)), normals))
    shading = lighting.light_shading(normals, light)
    keep = slice(0, min(samples, len(rows)))
    out = {"light": light, "face": face[keep].astype(np.int64), "bary": bary[keep], "albedo": (lum / shading)[keep],
           "colour": (neutral[rows, cols] / shading[:, None])[keep], "point_albedo": None}
    if light_model == "point":
        out["light"] = scaled(lighting.fit_point_light(lum, np.ones(len(lum)), normals, start=light))
        point_shading = lighting.light_shading(normals, out["light"])
        out["point_albedo"] = (lum / point_shading)[keep]
        # the stream carries the point light: the colour is measured under it
        out["colour"] = (neutral[rows, cols] / point_shading[:, None])[keep]
    return out


def _region_volume(region, config, faces, triangles, frames, cam_pos, texel_face, texel_bary, camera, neutral, cfg,
                   normal_sign):
    """A region's texture volume (n, h, w, 3) over its UV box, its alpha (h, w), the box's corner
    and where each layer's own example frame shows its texels (n, h, w) (elsewhere the neutral
    texture's): the texels of its ``triangles`` (F,) (a mask over ``faces``)."""
    mask = (texel_face >= 0) & triangles[np.maximum(texel_face, 0)]
    if not mask.any():
        raise InputError(f"region {region.name}: its vertex group covers no texel of the UV layout", path=config.path,
                         hint="the group needs whole triangles with UVs (or a larger texture_size)")
    r_idx, c_idx = np.nonzero(mask)
    rows, cols = slice(r_idx.min(), r_idx.max() + 1), slice(c_idx.min(), c_idx.max() + 1)
    layers, seen_in = [], []
    for f in region.frames:
        colours, seen = unwrap(frames[f][0], cam_pos[f], faces, texel_face, texel_bary, camera, rows, cols,
                               cfg.min_facing, normal_sign)
        layers.append(np.where(seen[..., None], colours, neutral[rows, cols]))
        seen_in.append(seen)
    alpha = layered_texture.region_alpha(mask[rows, cols], cfg.ramp)
    return np.stack(layers), alpha, (rows.start, cols.start), np.stack(seen_in)


#: A region whose neutral template reads at least this Q under the ramp of
#: :func:`facepipe.core.appearance.shading_tilt_readings` is named in the build's notes: a side light's gradient over it reads as its own motion.
TILT_NOTED = 0.1


def _shading_tilt(model, notes: list) -> dict:
    """Per region the Q its neutral template reads under a shading ramp
    (:func:`facepipe.core.appearance.shading_tilt_readings`); regions reading :data:`TILT_NOTED`
    or more are noted, with the setting that takes such a ramp out."""
    s = model.template_size
    neutral = np.stack([np.asarray(p[0], dtype=np.float64).reshape(s, s) for p in model.template_patches])
    tilt = ap.shading_tilt_readings(region_bank(model), neutral, model.shading, interpolation=model.peak_interpolation)
    for name, q in zip(model.names, tilt):
        if q >= TILT_NOTED:
            notes.append(f"region {name}: its neutral template under a ±{ap.SHADING_TILT:.0%} shading ramp reads Q "
                         f"{q:.2f} (its texture is uneven, so a side light's gradient over it looks like its own "
                         f"motion); shading_reference = \"neutral\" takes such a ramp out exactly (try both on your "
                         f"footage: what else it reads at rest may change too)")
    return dict(zip(model.names, np.round(tilt, 4).tolist()))


def _shading_surface(cfg, region, patches: np.ndarray, mask: np.ndarray, weights: np.ndarray
                     ) -> tuple[int, float | None]:
    """The order of the shading surface a region's patches (its layers, n × size × size, over the
    stable texels ``mask``) are divided by: the region's ``shading_surface``, else the table's;
    "auto" chooses by :func:`facepipe.core.appearance.shading_order`. With it the share of the
    layers' contrast the quadratic keeps (None where not measured)."""
    surface = region.shading_surface or cfg.shading_surface
    if surface != "auto" or not cfg.shading:
        return (2 if surface == "quadratic" else 1), None
    return ap.shading_order(patches, mask, weights, cfg.keep)


def _read_group(region, n_vertices: int, config_path) -> np.ndarray:
    path = region.vertices
    if not path.is_file():
        raise InputError(f"region {region.name}: vertex group file not found", path=path,
                         hint="one 0-based vertex index per line")
    values = []
    for line_no, line in enumerate(path.read_text().splitlines(), start=1):
        text = line.split("#")[0].strip()
        if not text:
            continue
        if not text.isdigit() or int(text) >= n_vertices:
            raise InputError(f"line {line_no}: {text!r} is not a vertex index below {n_vertices}", path=path)
        values.append(int(text))
    if not values:
        raise InputError(f"region {region.name}: the vertex group is empty", path=path)
    return np.asarray(values, dtype=np.int64)
