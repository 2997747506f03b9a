"""Cards across holes: the rim loops, the card's winding, positions and UVs; and an appearance
region on a card, end to end on rendered footage of an eyeball turning behind a hole."""

import numpy as np
import pytest
from scipy.stats import spearmanr

from facepipe.core.hole_cards import boundary_loops, hole_cards, stable_vertices


def _grid_with_hole(n: int = 12, hole: float = 0.25):
    """A unit square grid (z = a gentle bulge) in triangles, with the triangles inside a centred
    ellipse removed; planar UVs in [0.05, 0.95]."""
    xs = np.linspace(0.0, 1.0, n + 1)
    X, Y = np.meshgrid(xs, xs)
    P = np.stack([X.ravel(), Y.ravel(), 0.1 * np.exp(-8 * ((X - 0.5) ** 2 + (Y - 0.5) ** 2)).ravel()], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    centre = P[faces].mean(axis=1)
    keep = ((centre[:, 0] - 0.5) / 1.4) ** 2 + (centre[:, 1] - 0.5) ** 2 > hole ** 2
    uv = 0.05 + 0.9 * P[:, :2]
    return P, faces[keep], uv


def _half_edges(faces):
    return set(map(tuple, np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).tolist()))


def test_boundary_loops_and_a_card_across_the_hole():
    P, faces, _ = _grid_with_hole()
    loops = boundary_loops(faces)
    assert len(loops) == 2 and len(loops[0]) == 48  # the border, then the hole
    hole = loops[1]
    edges = _half_edges(faces)
    assert all((int(hole[i]), int(hole[(i + 1) % len(hole)])) in edges for i in range(len(hole)))
    stable = stable_vertices(P, P[None])
    cards = hole_cards(P, [hole], np.array([[0.4, 0.4, 0.6, 0.6]]), stable, rings=3, depth=0.1)
    X = cards.extend(P)
    L = len(hole)
    assert X.shape == (len(P) + 1 + 3 * L, 3)
    assert cards.rim_sizes.tolist() == [L]
    assert np.allclose(X[:len(P)], P)
    # its outer ring is the rim set back along the card's normal; its centre the rim's mean, set back
    width = np.ptp(P[hole][:, 0])  # the hole is widest along x: 0.1 × its width along its widest axis
    span = np.linalg.norm(P[hole][:, None] - P[hole][None], axis=-1).max()
    back = X[len(P) + 1 + 2 * L:] - P[hole]
    assert np.allclose(back, back[0]) and 0.1 * width <= np.linalg.norm(back[0]) <= 0.1 * span
    assert abs(back[0][2]) > 0.99 * np.linalg.norm(back[0])  # along the card's normal, into the hole
    assert np.allclose(X[len(P)], P[hole].mean(axis=0) + back[0])
    # the card winds as the mesh around the rim: its outer edges run against the rim's boundary edges
    copy = {len(P) + 1 + 2 * L + i: int(v) for i, v in enumerate(hole)}
    outer = [(copy[a], copy[b]) for a, b in np.concatenate([cards.faces[:, [0, 1]], cards.faces[:, [1, 2]],
                                                             cards.faces[:, [2, 0]]]).tolist()
             if a in copy and b in copy]
    assert len(outer) == L and all((b, a) in edges for a, b in outer)
    assert [len(loop) for loop in boundary_loops(cards.faces)] == [L]
    # the normals of the card face the mesh's side; its UVs fill its square, wound the same way
    tri = X[cards.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    mesh_n = np.cross(P[faces][:, 1] - P[faces][:, 0], P[faces][:, 2] - P[faces][:, 0]).sum(axis=0)
    assert (n @ mesh_n > 0).all()
    uv = cards.corner_uv
    area = (uv[:, 1, 0] - uv[:, 0, 0]) * (uv[:, 2, 1] - uv[:, 0, 1]) - (uv[:, 1, 1] - uv[:, 0, 1]) * (uv[:, 2, 0]
                                                                                                       - uv[:, 0, 0])
    assert (area >= 0).all() and area.sum() > 0.9 * 0.2 * 0.2 * 0.96 ** 2  # most of the square
    assert uv.min() >= 0.4 and uv.max() <= 0.6


def test_cards_move_with_the_head_not_with_the_lids():
    P, faces, _ = _grid_with_hole()
    hole = boundary_loops(faces)[1]
    rng = np.random.default_rng(0)
    # "expressions": the vertices near the hole move, the rest do not
    near = np.linalg.norm(P[:, :2] - 0.5, axis=1) < 0.4
    frames = np.stack([P + near[:, None] * rng.normal(scale=0.03, size=P.shape) for _ in range(4)])
    stable = stable_vertices(P, frames, share=0.3)
    assert not near[stable].any()
    cards = hole_cards(P, [hole], np.array([[0.0, 0.0, 0.2, 0.2]]), stable)
    rest_card = cards.extend(P)[len(P):]
    assert np.allclose(cards.extend(frames)[:, len(P):], rest_card)  # lids moving: the card stays
    angle = 0.3
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    turned = frames[0] @ R.T + [1.0, 2.0, 3.0]
    assert np.allclose(cards.extend(turned)[len(P):], rest_card @ R.T + [1.0, 2.0, 3.0])  # the head turning
    with pytest.raises(ValueError):
        cards.extend(P[:-1])


def test_cards_set_back_to_other_depths():
    P, faces, _ = _grid_with_hole()
    hole = boundary_loops(faces)[1]
    stable = stable_vertices(P, P[None])
    squares = np.array([[0.4, 0.4, 0.6, 0.6]])
    cards = hole_cards(P, [hole], squares, stable, rings=3, depth=0.1)
    deep = hole_cards(P, [hole], squares, stable, rings=3, depth=np.array([0.3]))
    moved = cards.at_depths(0.3)
    assert np.allclose(moved.rest, deep.rest) and moved.depths.tolist() == [0.3]
    # every vertex moved by the same 0.2 × the rim's width, along the card's normal into the hole
    shift = moved.rest - cards.rest
    assert np.allclose(shift, shift[0]) and np.isclose(np.linalg.norm(shift[0]), 0.2 * cards.widths[0])
    assert np.allclose(shift[0] / np.linalg.norm(shift[0]), -cards.normals[0])
    assert np.allclose(moved.at_depths(0.1).rest, cards.rest)
    assert cards.vertex_card.tolist() == [0] * len(cards.rest)


def _long_head():
    """A long strip of vertices: the still part (x < 7, the skull) and the face at one end (x ≥ 7)."""
    x, y = np.meshgrid(np.linspace(0.0, 10.0, 41), np.linspace(0.0, 1.0, 5))
    P = np.stack([x.ravel(), y.ravel(), 0.1 * np.sin(x.ravel())], axis=1)
    return P, P[:, 0] >= 7.0


def test_stable_vertices_are_the_still_ones_however_far_from_the_moving_face():
    P, face = _long_head()
    rng = np.random.default_rng(3)
    # expressions move the face end a lot and coherently (a least-squares fit over the whole strip
    # turns to follow it, so far still vertices seem to move); some face vertices barely move
    amount = np.where(face, rng.uniform(0.002, 1.0, len(P)), 0.0)
    frames = np.stack([P + np.outer(amount * w, [0.0, 1.0, 0.3]) for w in (0.5, 1.0, -0.7)])
    stable = stable_vertices(P, frames, share=(~face).mean())
    assert not face[stable].any()
    assert P[stable, 0].min() == 0.0  # the far end is among them


def test_stable_vertices_are_the_still_ones_when_the_expressions_move_most_of_the_mesh():
    # a blendshape rig whose expressions each move most vertices a little, the same way (a block
    # moving together): concentration steps from a whole-mesh fit settle on that block; the
    # still vertices (none of the expressions moves them) have the least residual and are kept
    P, _ = _long_head()
    rng = np.random.default_rng(5)
    still = P[:, 0] < 2.5
    frames = []
    for k in range(6):
        offset = rng.normal(scale=0.02, size=3) + rng.normal(scale=0.002, size=P.shape)  # together, not rigidly
        local = np.where(P[:, 0] > 8.0, rng.uniform(0.0, 0.3), 0.0)[:, None] * rng.normal(size=3)
        frames.append(P + np.where(still[:, None], 0.0, offset + local))
    stable = stable_vertices(P, np.stack(frames), share=still.mean())
    assert still[stable].all()


def test_card_follows_the_head_when_some_stable_vertices_move_in_a_take():
    P, faces, _ = _grid_with_hole()
    hole = boundary_loops(faces)[1]
    stable = np.arange(0, len(P), 3)
    cards = hole_cards(P, [hole], np.array([[0.0, 0.0, 0.2, 0.2]]), stable)
    rest_card = cards.extend(P)[len(P):]
    angle = 0.2
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    moved = P.copy()
    jaw = stable[: len(stable) // 5]                    # a fifth of them move (a jaw the examples never opened)
    moved[jaw] += [0.0, -0.3, 0.1]
    turned = moved @ R.T + [0.5, -1.0, 2.0]
    np.testing.assert_allclose(cards.extend(turned)[len(P):], rest_card @ R.T + [0.5, -1.0, 2.0], atol=1e-6)
    frames = np.stack([turned, P])                    # frames at once: each its own fit
    np.testing.assert_allclose(cards.extend(frames)[1, len(P):], rest_card, atol=1e-9)


# --------------------------------------------------------------------------- end to end


def _head_turn(yaw: float, pitch: float, about: np.ndarray):
    """The rigid motion (R, t) turning a head by yaw and pitch (degrees) about a point."""
    y, p = np.radians(yaw), np.radians(pitch)
    R = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]]) @ \
        np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    return R, about - R @ about


def _eye_kit(tmp_path, yaws_examples, yaws_take, size=160, rest_turns=(), eye_front=None, extra_config=(),
             take_light=False, rest_looks=(), pitches_take=None):
    """Footage of a grid with a hole, an eyeball behind it turning by the given yaws (degrees):
    the examples (neutral first) and a take, with their geometry and an appearance config with
    one card region. ``rest_turns``: more example frames, the eye at rest and the head turned by
    each (yaw, pitch) in degrees (the config's rest_frames; the others' head is still);
    ``eye_front``: the eyeball's front this far behind the rim's centre, × the opening's width
    (else :func:`eyes_behind`'s); ``take_light``: the take lit as the sample's turned take is (a
    warm light from the other side, more ambient); ``rest_looks``: more rest frames, the head
    still and the eye pitched by each (degrees: a look up or down, across the layers' gaze);
    ``pitches_take``: the take's eye pitch per frame (none: 0)."""
    from facepipe.appearance_sample import (_save_geometry, eye_poses, eyes_behind, make_scene, other_light,
                                            scene_json, skin_texture, write_appearance_footage)
    from facepipe.io.mesh_write import save_obj
    from facepipe.core.mesh import Mesh

    P, faces, uv = _grid_with_hole(24)
    P = P * 6.0  # a 6-unit patch, the hole about 2 × 3 units
    hole = boundary_loops(faces)[1]
    mesh = Mesh(P, np.arange(len(faces) + 1) * 3, faces.ravel(), uv, faces.ravel())
    save_obj(tmp_path / "patch.obj", mesh)
    (tmp_path / "rim.txt").write_text("".join(f"{v}\n" for v in hole))
    (tmp_path / "markers.csv").write_text("name,vertex\nA,0\nB,1\nC,2\n")
    scene = make_scene(P, size)
    (tmp_path / "camera.json").write_text(scene_json(scene))
    corner_uv = uv[faces]
    skin = skin_texture(256)
    eyes = eyes_behind(P, [hole])
    if eye_front is not None:
        (eye,) = eyes
        width = eye.radius / 0.55
        eye.centre = P[hole].mean(axis=0) - (eye_front * width + eye.radius) * eye.axes[:, 2]
    no_fields = np.zeros((1, 256, 256), dtype=np.float32)
    rest = len(rest_turns) + len(rest_looks)
    pitches_take = np.zeros(len(yaws_take)) if pitches_take is None else pitches_take
    for name, yaws, pitches, turns in (
            ("examples", list(yaws_examples) + [0.0] * rest, [0.0] * (len(yaws_examples) + len(rest_turns))
             + list(rest_looks), [(0.0, 0.0)] * len(yaws_examples) + list(rest_turns) + [(0.0, 0.0)] * len(rest_looks)),
            ("take", yaws_take, pitches_take, [(0.0, 0.0)] * len(yaws_take))):
        yaws = np.asarray(yaws, dtype=np.float64)
        head = [_head_turn(*turn, P.mean(axis=0)) for turn in turns]
        Rs, ts = np.array([R for R, _ in head]), np.array([t for _, t in head])
        world = P @ Rs.transpose(0, 2, 1) + ts[:, None]
        gaze = np.array([[[1.0, 0.0]], [[0.0, 1.0]]])  # weights (yaw, pitch) in degrees
        poses = eye_poses(eyes, np.stack([yaws, np.asarray(pitches, dtype=np.float64)], axis=1), gaze, Rs, ts)
        lit = other_light(scene) if take_light and name == "take" else scene
        write_appearance_footage(tmp_path / name, world, np.zeros((len(yaws), 1)), faces, corner_uv, skin, no_fields,
                                 lit, eyes=poses, seed=3 if name == "take" else 1)
        _save_geometry(tmp_path / f"{name}.npz", world, np.arange(len(yaws)))
    frames = list(range(len(yaws_examples)))
    (tmp_path / "appearance.toml").write_text("\n".join([
        "[rig]", 'mesh = "patch.obj"', 'markers = "markers.csv"', "", "[appearance]", 'camera = "camera.json"',
        f"camera_rotation = {scene.rotation.tolist()}", f"camera_translation = {scene.translation.tolist()}",
        'footage = "examples/frame_%04d.png"', 'geometry = "examples.npz"', "neutral_frame = 0",
        f"rest_frames = {list(range(len(frames), len(frames) + rest))}", "texture_size = 256", "",
        "[appearance.regions.eyeball]", 'vertices = "rim.txt"',
        "template = [0.2, 0.2, 0.8, 0.8]", f"frames = {frames}", "card = true", ""]))
    if extra_config:  # more [appearance] keys, before the region's table
        text = (tmp_path / "appearance.toml").read_text()
        (tmp_path / "appearance.toml").write_text(text.replace("\n\n[appearance.regions", "\n" + "\n".join(extra_config)
                                                               + "\n\n[appearance.regions"))
    return tmp_path


@pytest.mark.slow
def test_an_eyeball_region_on_a_card_follows_the_gaze(tmp_path, capsys):
    from facepipe.cli.commands import main
    from facepipe.io.appearance_file import load_appearance
    from facepipe.io.mesh_read import load_mesh

    def run(*args):
        with pytest.raises(SystemExit) as exc:
            main([str(a) for a in args])
        return exc.value.code

    rng = np.random.default_rng(5)
    take = np.concatenate([[0.0, 24.0], rng.uniform(0.0, 24.0, 22)])
    kit = _eye_kit(tmp_path, [0.0, 6.0, 12.0, 18.0, 24.0], take)
    assert run("appearance", "build", kit / "appearance.toml", "-o", kit / "app.npz", "-q") == 0
    model = load_appearance(kit / "app.npz")
    assert model.card_rest is not None and model.n_vertices == 25 * 25
    assert run("appearance", "classify", kit / "app.npz", kit / "take" / "frame_%04d.png", "--geometry",
               kit / "take.npz", "-o", kit / "cls", "-q") == 0
    q = np.loadtxt(kit / "cls" / "appearance.csv", delimiter=",", skiprows=1)[:, 2]
    assert spearmanr(q, take).statistic > 0.95
    assert np.abs(q - take / 6.0).max() < 0.75  # the layer index, continuous between the examples' yaws
    # the layered texture's card square carries the eye; the preview renders the card
    cards = load_mesh(kit / "app_cards.obj")  # the card at rest with its UVs, for the user's scene
    assert np.allclose(cards.vertices, model.card_rest, atol=1e-6)
    assert cards.n_polygons == (model.faces >= 25 * 25).all(axis=1).sum()
    assert cards.uvs.min() >= 0 and cards.uvs.max() <= 1
    assert run("export", kit / "cls", "--format", "textures", "-o", kit / "tex", "-q") == 0
    assert run("preview", kit / "cls", "-o", kit / "preview.png", "-q") == 0
    capsys.readouterr()


def _built(kit):
    from facepipe.io.camera_file import read_camera
    from facepipe.io.config import load_config
    from facepipe.io.mesh_read import load_mesh
    from facepipe.pipeline.appearance_build import build_appearance

    config = load_config(kit / "appearance.toml")
    return build_appearance(config, load_mesh(config.mesh), read_camera(config.appearance.camera))


def test_a_frames_light_shades_the_card_as_it_shades_the_skin(tmp_path):
    """The take lit otherwise than the examples (another direction, colour and ambient): the
    reconstructed eye's texels are as bright as the take's own, the renderer's eyeball under its
    light, not as the examples showed them (measured: 2–8 % off per channel, against 0–36 %)."""
    from facepipe.io.footage import open_footage, read_frames
    from facepipe.pipeline.appearance import _read_geometry, classify_frames
    from facepipe.pipeline.appearance_points import texel_map, unwrap
    from facepipe.pipeline.appearance_texture import card_texels, frame_texture

    kit = _eye_kit(tmp_path, [0.0, 6.0, 12.0, 18.0, 24.0], [0.0, 12.0, 24.0], take_light=True)
    model, _ = _built(kit)
    assert model.cards_shaded
    positions, numbers = _read_geometry(kit / "take.npz", model.n_vertices)
    c = classify_frames(model, kit / "take" / "frame_%04d.png", positions, numbers, numbers / 30.0)
    texels = texel_map(model.corner_uv, model.neutral.shape[0])
    card = card_texels(model, texels[0])
    for (_, image, _), t in zip(read_frames(open_footage(kit / "take" / "frame_%04d.png"), numbers), range(3)):
        cam = model.to_camera(positions[t])
        truth, seen = unwrap(image, cam, model.faces, *texels, model.camera, min_facing=model.min_facing,
                             normal_sign=model.normal_sign)
        use = seen & card
        assert use.sum() > 500
        level = truth[use].mean(axis=0)
        rebuilt = frame_texture(model, c.q[t], cam, c.light[t], texels)[use].mean(axis=0)
        as_examples = model.neutral[use].mean(axis=0)  # the eye as the examples' light showed it
        unshaded, shaded = np.abs(as_examples / level - 1).max(), np.abs(rebuilt / level - 1).max()
        assert unshaded > 0.25  # the take's light changes the eye's level (its colour most) …
        # … and the frame's light carries it (within what a plane's shading leaves of a sphere's)
        assert shaded < 0.1 and shaded < unshaded / 3
    # the model file keeps it; one written before it keeps the cards as the footage showed them
    from facepipe.io.appearance_file import load_appearance, save_appearance

    save_appearance(kit / "app.npz", model)
    assert load_appearance(kit / "app.npz").cards_shaded
    arrays = dict(np.load(kit / "app.npz"))
    del arrays["cards_shaded"]
    np.savez(kit / "old.npz", **arrays)
    old = load_appearance(kit / "old.npz")
    assert not old.cards_shaded
    # a broken flag is refused, naming it (the CLI exits 2 with the message)
    from facepipe.errors import InputError

    for broken in (np.array([1, 0]), np.array(5)):
        np.savez(kit / "broken.npz", **arrays, cards_shaded=broken)
        with pytest.raises(InputError, match="cards_shaded"):
            load_appearance(kit / "broken.npz")
    no_albedo = {k: v for k, v in arrays.items() if k != "neutral_albedo"}
    np.savez(kit / "broken.npz", **no_albedo, cards_shaded=np.array(True))
    with pytest.raises(InputError, match="cards_shaded"):
        load_appearance(kit / "broken.npz")
    cam = old.to_camera(positions[0])
    np.testing.assert_array_equal(frame_texture(old, c.q[0], cam, c.light[0], texels)[card],
                                  frame_texture(old, c.q[0], None, None, texels)[card])


#: Rest frames of a capture session's range of motion: the head turned (yaw, pitch), the eye ahead.
HEAD_TURNS = [(8.0, 0.0), (-8.0, 0.0), (0.0, 8.0), (0.0, -8.0)]


@pytest.mark.slow
def test_a_look_across_the_layers_gaze_reads_rest(tmp_path):
    """The eye's layers turn it sideways; the take also looks up and down (the head still), as two
    at-rest example frames do. The motion check reads those looks as rest (the Haar match alone
    reads some of them as gaze), and the sideways gazes as before."""
    import dataclasses

    from facepipe.io.appearance_file import load_appearance, save_appearance
    from facepipe.pipeline.appearance import _read_geometry, classify_frames

    rng = np.random.default_rng(7)
    yaw = np.concatenate([[0.0, 24.0], rng.uniform(0.0, 24.0, 14), np.zeros(10)])
    pitch = np.concatenate([np.zeros(16), np.linspace(-20.0, -4.0, 5), np.linspace(4.0, 20.0, 5)])
    kit = _eye_kit(tmp_path, [0.0, 6.0, 12.0, 18.0, 24.0], yaw, rest_looks=[-20.0, 20.0], pitches_take=pitch)
    model, info = _built(kit)
    check = info["cards"]["eyeball"]["motion_check"]
    assert check["across_frames"] == [5, 6]
    assert check["least_texels"] == pytest.approx(0.5 * check["layer_shifts_texels"][0], abs=0.01)
    save_appearance(kit / "app.npz", model)
    loaded = load_appearance(kit / "app.npz").card_motion[0]
    for field in ("reference", "reference_seen", "layers", "rest"):
        np.testing.assert_array_equal(getattr(loaded, field), getattr(model.card_motion[0], field))
    positions, numbers = _read_geometry(kit / "take.npz", model.n_vertices)
    looks = pitch != 0

    def read(m):
        return classify_frames(m, kit / "take" / "frame_%04d.png", positions, numbers, numbers / 30.0).q[:, 0]

    q = read(model)
    assert (q[looks] == 0).all()
    assert spearmanr(q, yaw).statistic > 0.95
    assert np.abs(q[~looks] - yaw[~looks] / 6.0).max() < 0.75
    assert read(dataclasses.replace(model, card_motion=None))[looks].max() > 0.05  # what the check takes away
    # the config turns it off: the Haar match alone
    text = (kit / "appearance.toml").read_text()
    (kit / "appearance.toml").write_text(text.replace('texture_size = 256', 'texture_size = 256\ncard_motion_check = false'))
    unchecked, info = _built(kit)
    assert unchecked.card_motion is None and "motion_check" not in info["cards"]["eyeball"]


@pytest.mark.parametrize("front", [0.0, 0.25])
def test_card_depth_is_fitted_where_the_rendered_iris_lies(tmp_path, front):
    """The eyeball's front drawn ``front`` × the opening's width behind the rim's centre; its
    pupil's edge lies 0.008 behind the front, its iris' edge (the limbus) 0.057: the fitted card
    lies between them (the default, 0.1, lies outside both bands)."""
    kit = _eye_kit(tmp_path, [0.0, 6.0, 12.0, 18.0, 24.0], [3.0], size=160, rest_turns=HEAD_TURNS, eye_front=front)
    model, info = _built(kit)
    card = info["cards"]["eyeball"]
    assert card["depth_fitted"] and card["depth_frames"] == 4 and card["depth_parallax_px"] > 1.0
    assert front <= card["depth"] <= front + 0.06
    assert any("set back" in note for note in info["notes"])
    # the model's card is the fitted one: its centre that far behind the rim's centre
    P = load_mesh_vertices(kit)
    hole = boundary_loops(model.faces[model.faces.max(axis=1) < model.n_vertices])[1]
    rim = P[hole]
    width = np.ptp((rim - rim.mean(axis=0))[:, 0])  # the hole is widest along x, the patch faces +z
    assert np.isclose(rim.mean(axis=0)[2] - model.card_rest[0][2], card["depth"] * width, rtol=0.02)
    # the cards hide nothing, and the light is fitted on the skin alone
    assert (model.occluders < model.n_vertices).all() and len(model.occluders) < len(model.faces)
    assert (model.light_face < len(model.occluders)).all()


def load_mesh_vertices(kit):
    from facepipe.io.mesh_read import load_mesh

    return load_mesh(kit / "patch.obj").vertices


def test_card_depth_kept_where_the_head_never_turns_or_set(tmp_path):
    kit = _eye_kit(tmp_path / "still", [0.0, 10.0, 20.0], [5.0], size=96)
    _, info = _built(kit)
    card = info["cards"]["eyeball"]
    assert not card["depth_fitted"] and card["depth"] == 0.1
    assert any("turn the head too little" in note for note in info["notes"])
    # turned so far that the card faces away: the frame moves its samples but shows none of them
    kit = _eye_kit(tmp_path / "away", [0.0, 10.0, 20.0], [5.0], size=96, rest_turns=[(75.0, 0.0)])
    _, info = _built(kit)
    card = info["cards"]["eyeball"]
    assert not card["depth_fitted"] and card["depth"] == 0.1 and card["depth_parallax_px"] > 0.5
    assert any("show too little of its card" in note for note in info["notes"])
    kit = _eye_kit(tmp_path / "set", [0.0, 10.0, 20.0], [5.0], size=96, rest_turns=HEAD_TURNS,
                   extra_config=["card_depth = 0.3"])
    _, info = _built(kit)
    assert info["cards"]["eyeball"]["depth"] == 0.3 and not info["cards"]["eyeball"]["depth_fitted"]


@pytest.mark.parametrize("key, value, said", [("card_depth", '"deep"', '"auto" or a number'),
                                              ("card_depth", "1.5", "not in [0, 1]"),
                                              ("card_depth", "-0.1", "not in [0, 1]"),
                                              ("card_motion_check", '"yes"', "true or false")])
def test_card_settings_are_checked(tmp_path, capsys, key, value, said):
    from facepipe.cli.commands import main

    kit = _eye_kit(tmp_path, [0.0, 10.0, 20.0], [5.0], size=64, extra_config=[f"{key} = {value}"])
    with pytest.raises(SystemExit) as exc:
        main(["appearance", "build", str(kit / "appearance.toml"), "-o", str(kit / "app.npz"), "-q"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert key in err and said in err and "appearance.toml" in err
    assert not (kit / "app.npz").exists()


def test_a_card_region_must_rim_a_hole(tmp_path, capsys):
    from facepipe.cli.commands import main

    kit = _eye_kit(tmp_path, [0.0, 10.0, 20.0], [5.0], size=96)
    (kit / "rim.txt").write_text("0\n1\n2\n")  # corner vertices of the border: no hole's rim
    with pytest.raises(SystemExit) as exc:
        main(["appearance", "build", str(kit / "appearance.toml"), "-o", str(kit / "app.npz"), "-q"])
    assert exc.value.code == 2
    assert "rim" in capsys.readouterr().err


def test_rendered_eyeballs_move_with_the_head_and_turn_with_the_gaze():
    from facepipe.appearance_sample import eye_poses, eyes_behind, head_motion

    P, faces, _ = _grid_with_hole()
    hole = boundary_loops(faces)[1]
    near = np.linalg.norm(P[:, :2] - 0.5, axis=1) < 0.4
    expression = P + near[:, None] * 0.05  # moves only the vertices near the hole
    angle = 0.4
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    world = np.stack([P, expression @ R.T + [0.5, -1.0, 2.0]])
    Rs, ts = head_motion(P, {"e": expression}, world)
    assert np.allclose(Rs[0], np.eye(3)) and np.allclose(Rs[1], R) and np.allclose(ts[1], [0.5, -1.0, 2.0])
    (eye,) = eyes_behind(P, [hole])
    assert eye.centre[2] < P[hole][:, 2].mean()  # behind the opening
    gaze = np.array([[[30.0, 0.0]]])  # expression 0 turns eye 0 by 30° of yaw
    poses = eye_poses([eye], np.array([[0.0], [1.0]]), gaze, Rs, ts)
    (c0, a0, r0), (c1, a1, r1) = poses[0][0], poses[1][0]
    assert np.allclose(c0, eye.centre) and np.allclose(c1, R @ eye.centre + [0.5, -1.0, 2.0]) and r0 == r1
    assert np.isclose(np.degrees(np.arccos((R @ a0[:, 2]) @ a1[:, 2])), 30.0)  # the gaze turned 30° in the head


def test_free_uv_squares_on_another_udim_tile():
    """A card's square is found where the layout leaves room on the regions' tile: the layout moved
    one tile right (1002) gives the same squares moved with it."""
    from facepipe.pipeline.appearance_cards import free_uv_squares

    _, faces, uv = _grid_with_hole()
    corner_uv = 0.5 * uv[faces]  # the layout in the tile's lower-left quarter: room for squares elsewhere
    on_1001 = free_uv_squares(corner_uv, 64, 2)
    on_1002 = free_uv_squares(corner_uv + [1.0, 0.0], 64, 2, tile=1002)
    assert [side for _, side in on_1001] == [side for _, side in on_1002] and on_1001[0][1] > 8
    for (a, _), (b, _) in zip(on_1001, on_1002):
        np.testing.assert_allclose(np.asarray(b) - [1.0, 0.0, 1.0, 0.0], a, atol=1e-12)
        assert 1.0 <= b[0] < b[2] <= 2.0 and 0.0 <= b[1] < b[3] <= 1.0


def test_uv_points_in_a_cards_fan_of_slivers_are_located():
    """A card over a hole with a long rim: its first ring is a fan of slivers around the centre,
    whose centroids lie far from points near the centre (a nearest-centroid search misses them)."""
    from facepipe.pipeline.appearance_points import locate_uv

    angle = np.linspace(0.0, 2 * np.pi, 240, endpoint=False)
    rim = np.stack([1.4 * np.cos(angle), np.sin(angle), 0.05 * np.cos(3 * angle)], axis=1)
    P = np.concatenate([rim, rim * 2.0])
    L = len(rim)
    i, j = np.arange(L), (np.arange(L) + 1) % L
    faces = np.concatenate([np.stack([i, L + i, L + j], 1), np.stack([i, L + j, j], 1)])  # a ring around the hole
    hole = boundary_loops(faces)[1]
    cards = hole_cards(P, [hole], np.array([[0.2, 0.2, 0.8, 0.8]]), np.arange(L), rings=4)
    rng = np.random.default_rng(3)
    points = 0.5 + rng.uniform(-0.05, 0.05, size=(200, 2))  # near the card's centre (0.5, 0.5)
    face, bary = locate_uv(points, cards.corner_uv)
    assert (face >= 0).all()
    assert np.allclose(np.einsum("nk,nkc->nc", bary, cards.corner_uv[face]), points, atol=1e-9)
    assert (bary >= -1e-9).all()
    outside = locate_uv(np.array([[0.05, 0.05]]), cards.corner_uv)[0]
    assert outside.tolist() == [-1]
