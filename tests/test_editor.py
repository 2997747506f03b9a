"""`facepipe edit`: the server's evaluation against the replay's, the drag patch, the web server's
surface, and the page in headless Chromium against `replay --edits`."""

import asyncio
import json
import struct
from pathlib import Path

import numpy as np
import pytest

from facepipe.core.novelty import CONFIDENCE_TOLERANCE
from facepipe.core.edits import HandleEdit, apply_edits
from facepipe.editor.drag_patch import DragPatch
from facepipe.editor.server import drag_messages, evaluation_message, make_app
from facepipe.editor.session import EditorSession, pack_arrays
from facepipe.io.model_file import load_model
from facepipe.pipeline.replay import NumpyEvaluator
from tests.conftest import run_cli
from bench.editor_browser import (browser_page, chromium_or_reason, drag, editor_server, save_edits, screenshot,
                                  wait_settled)


@pytest.fixture(scope="module")
def editor_rig(tmp_path_factory):
    """A small sample rig, its model (the config's values) and the take prepared as replay does."""
    root = tmp_path_factory.mktemp("editor")
    assert run_cli("sample", root / "rig", "--vertices", 3000, "--frames", 24, "-q") == 0
    model_path = root / "model.npz"
    assert run_cli("bake", root / "rig" / "sample.toml", "--no-tune", "-o", model_path, "-q") == 0
    from facepipe.cli.editor import prepared_take

    model = load_model(model_path)
    return root, model_path, model, prepared_take(root / "rig" / "take.csv", model)


def brow_handle(model) -> int:
    """The handle over the sample face's left brow (the browRaise region's centre, x = −2.8, y = 4.8)."""
    rest = model.rest[model.handle_vertices]
    return int(np.argmin(np.hypot(rest[:, 0] + 2.8, rest[:, 1] - 4.8)))


def test_pack_arrays_round_trip():
    arrays = {"a": np.arange(5, dtype=np.float32), "b": np.arange(6, dtype=np.uint32).reshape(2, 3)}
    blob = pack_arrays(arrays, {"x": 1})
    n = struct.unpack("<I", blob[:4])[0]
    header = json.loads(blob[4:4 + n])
    assert (4 + n) % 8 == 0 and header["meta"] == {"x": 1}
    for name, array in arrays.items():
        e = header["arrays"][name]
        assert e["offset"] % 8 == 0
        got = np.frombuffer(blob, dtype=e["dtype"], count=array.size, offset=4 + n + e["offset"]).reshape(e["shape"])
        np.testing.assert_array_equal(got, array)


def test_server_mode_frame_equals_replay(editor_rig, tmp_path):
    _, _, model, take = editor_rig
    h = brow_handle(model)
    edits = [HandleEdit(float(take.frames[10]), {h: (0.0, 0.4, 0.1)}, 3.0, 3.0)]
    session = EditorSession(model, take, tmp_path / "e.json", edits, mode="server")
    reference = NumpyEvaluator(model)
    for row in (8, 10, 12, 20):
        message, exact = evaluation_message(session, {"op": "eval", "id": 1, "frame": row, "layer": "details"},
                                            exact=True)
        assert exact
        head = np.frombuffer(message, "<f8", 6)
        V, H = model.n_vertices, len(model.handle_vertices)
        final = np.frombuffer(message, "<f4", 3 * V, 48 + 24 * H).reshape(V, 3)
        large = np.frombuffer(message, "<f4", 3 * V, 48 + 24 * H + 12 * V).reshape(V, 3)
        handles = apply_edits(take.head[row:row + 1], take.frames[row:row + 1], edits)
        want_final, want_large = reference.evaluate(handles.astype(np.float64), with_large=True)
        assert head[1] == row and head[4] == 1
        np.testing.assert_allclose(final, want_final[0], atol=2e-5)
        np.testing.assert_allclose(large, want_large[0], atol=2e-5)
    session.close()


def test_drag_patch_matches_the_full_frame(editor_rig, tmp_path):
    _, _, model, take = editor_rig
    session = EditorSession(model, take, tmp_path / "e.json", mode="server")
    h, row = brow_handle(model), 6
    base = session.handles(row)
    site = session.pose_terms(base)[1]
    base_final, base_large = session.evaluate(base, site)
    patch = DragPatch(model, h, base, base_final, base_large, site)
    offset = np.array([0.1, 0.5, -0.2])
    moved = base.copy()
    moved[h] += offset
    final, large = patch.evaluate(offset)
    want_final, want_large = session.evaluate(moved, site)
    np.testing.assert_allclose(large, want_large, atol=1e-5)  # linear: exact everywhere
    inside = np.zeros(model.n_vertices, bool)
    inside[patch.patch] = True
    np.testing.assert_allclose(final[inside], want_final[inside], atol=1e-5)
    # outside, only the frames' turn is left out: bounded by the support × the offset × the details' reach
    outside = np.abs(final[~inside] - want_final[~inside]).max() if (~inside).any() else 0.0
    assert outside < 1e-3 * np.linalg.norm(offset) + 1e-5
    assert inside.sum() < model.n_vertices  # a patch, not the whole mesh
    session.close()


def test_drag_patch_frames_are_local_frames_of_the_moved_patch(editor_rig, tmp_path):
    """A drag step's frames, made from terms linear in the offset, against local_frames of the
    moved sub-mesh (vertex normals by the sparse incidence sum); degenerate rows take
    local_frames' fallbacks."""
    from facepipe.core.tangent_frames import frames_from_normals, local_frames

    _, _, model, take = editor_rig
    session = EditorSession(model, take, tmp_path / "e.json", mode="server")
    try:
        h, row = brow_handle(model), 6
        base = session.handles(row)
        base_final, base_large = session.evaluate(base, None)
        patch = DragPatch(model, h, base, base_final, base_large, None)
        offset = np.array([0.2, 0.6, -0.3])
        sub = base_large[patch.used].astype(np.float64) + patch.column[patch.used, None].astype(np.float64) * offset
        want = local_frames(sub, patch.sub_faces, patch.sub_neighbours)[patch.patch_local]  # (n, 3, 3)
        got = np.stack(patch.frames(offset), axis=-1).transpose(1, 0, 2)  # (n, coordinate, column)
        np.testing.assert_allclose(got, want, atol=2e-5)
        # a zero normal, and a frame neighbour along the normal: the fallbacks of local_frames
        patch.normal0[:, 0] = patch.normal1[:, 0] = 0.0
        patch.edge0[:, 1], patch.edge1[1] = want[1, :, 2] * 0.3, 0.0
        got = np.stack(patch.frames(offset), axis=-1).transpose(1, 0, 2)
        normal = np.array([[0.0, 0.0, 1.0], want[1, :, 2]])
        edges = np.stack([patch.edge0[:, k] + patch.edge1[k] * offset for k in (0, 1)])
        np.testing.assert_allclose(got[:2], frames_from_normals(normal, edges), atol=1e-6)
    finally:
        session.close()


def test_server_drag_messages_rebuild_the_patch_evaluation(editor_rig, tmp_path):
    """The drag's patch protocol: the page's rebuild (base + column × float32(offset), the patch's
    positions over it; as evaluate_worker.js does it) is DragPatch.evaluate bit for bit, and a page
    without the patch's base (a second connection) is sent it."""
    _, _, model, take = editor_rig
    session = EditorSession(model, take, tmp_path / "e.json", mode="server")
    try:
        h, row = brow_handle(model), 5
        evaluation_message(session, {"op": "eval", "frame": row}, exact=True)  # the frame's gate, as the page's first
        V, H = model.n_vertices, len(model.handle_vertices)
        request = {"op": "eval", "id": 3, "frame": row, "preview": {"handle": h, "offset": [0.0, 0.2, 0.05]}}
        base_message, step = drag_messages(session, request)
        head = np.frombuffer(base_message, "<f8", 8)
        assert head[2] == 2 and head[6] == session.patch_serial
        n = int(head[7])
        at = 64 + 24 * H
        base = np.frombuffer(base_message, "<f4", 3 * V, at).reshape(V, 3)
        column = np.frombuffer(base_message, "<f4", V, at + 24 * V)
        vertices = np.frombuffer(base_message, "<u4", n, at + 28 * V)
        for offset in ([0.0, 0.2, 0.05], [0.1, -0.3, 0.0]):
            request["preview"]["offset"] = offset
            messages = drag_messages(session, request, known_serial=session.patch_serial)
            assert len(messages) == 1  # this page has the base: the step alone
            step = messages[0]
            assert np.frombuffer(step, "<f8", 8)[2] == 3
            sent = np.frombuffer(step, "<f8", 3, at)
            rebuilt = base + column[:, None] * sent.astype(np.float32)[None]
            rebuilt[vertices] = np.frombuffer(step, "<f4", 3 * n, at + 24).reshape(n, 3)
            want, _ = session._patch[1].evaluate(offset)
            np.testing.assert_array_equal(rebuilt, want)
        assert len(drag_messages(session, request, known_serial=-1)) == 2  # a new page: base and step
    finally:
        session.close()


def test_provisional_gate_then_exact(editor_rig, tmp_path):
    _, _, model, take = editor_rig
    session = EditorSession(model, take, tmp_path / "e.json", mode="browser")
    try:
        first = session.handles(3)
        f0, s0, exact0 = session.pose_terms(first, exact=False)
        assert exact0  # nothing to stand in yet: made at once
        moved = first.copy()
        moved[brow_handle(model)] += [0, 0.3, 0]
        _, s1, exact1 = session.pose_terms(moved, exact=False)
        assert not exact1 and s1 is s0  # the latest exact gate stands in
        session.exact_gate(moved)
        _, s2, exact2 = session.pose_terms(moved, exact=False)
        want = session.reference.details.gate
        u = moved[None] - session.rest_handles[None]
        features = session.pose_terms(moved)[0][None]
        np.testing.assert_array_equal(s2, want.site_confidences(features, u)[0])
        # the fits settled early: within CONFIDENCE_TOLERANCE of the fully converged ones
        np.testing.assert_allclose(s2, want.site_confidence(want.novelty(features, u))[0], rtol=0,
                                   atol=CONFIDENCE_TOLERANCE)
        assert exact2
    finally:
        session.close()


def test_web_server_serves_only_its_own(editor_rig, tmp_path):
    from aiohttp.test_utils import TestClient, TestServer

    _, _, model, take = editor_rig
    session = EditorSession(model, take, tmp_path / "e.json", mode="browser")

    async def run():
        async with TestClient(TestServer(make_app(session))) as client:
            assert (await client.get("/")).status == 200
            assert (await client.get("/static/vendor/three/three.module.js")).status == 200
            assert (await client.get("/static/vendor/three/LICENSE")).status == 200
            for path in ("/static/../session.py", "/static/%2e%2e/session.py", "/api/truth/0", "/model.npz",
                         f"/static/{Path(__file__).name}"):
                assert (await client.get(path)).status in (403, 404), path
            blob = await (await client.get("/api/model.bin")).read()
            n = struct.unpack("<I", blob[:4])[0]
            assert json.loads(blob[4:4 + n])["meta"]["vertices"] == model.n_vertices
            with pytest.raises(Exception):  # another site's page may not drive the session
                await client.ws_connect("/ws", headers={"Origin": "http://evil.example"})
            ws = await client.ws_connect("/ws")
            assert json.loads((await ws.receive()).data)["type"] == "state"
            await ws.send_str(json.dumps({"op": "eval", "id": 7, "frame": 2}))
            answer = np.frombuffer((await ws.receive()).data, "<f8")
            assert answer[0] == 7 and answer[1] == 2
            await ws.send_str(json.dumps({"op": "commit", "frame": 2,
                                          "preview": {"handle": 0, "offset": [0, 0.1, 0], "ease_in": 2}}))
            assert len(json.loads((await ws.receive()).data)["edits"]) == 1
            await ws.send_str(json.dumps({"op": "save"}))
            assert json.loads((await ws.receive()).data)["saved"] == str(tmp_path / "e.json")
            await ws.send_str(json.dumps({"op": "eval", "frame": 999}))
            assert json.loads((await ws.receive()).data)["type"] == "error"
            await ws.close()

    try:
        asyncio.run(run())
    finally:
        session.close()
    assert json.loads((tmp_path / "e.json").read_text())["edits"][0]["ease_in"] == 2


def test_edit_refuses_malformed_edits_file(editor_rig, tmp_path):
    _, model_path, _, _ = editor_rig
    bad = tmp_path / "e.json"
    bad.write_text("[1, 2")
    assert run_cli("edit", model_path, "--edits", bad, "-q") == 2


# ----------------------------------------------------------------------------- in a browser


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["browser", "server"])
def test_page_drag_replays_identically(editor_rig, tmp_path, mode):
    chromium, reason = chromium_or_reason()
    if chromium is None:
        pytest.skip(reason)
    root, model_path, model, take = editor_rig
    edits_path = tmp_path / "edits.json"
    shots = Path(__import__("os").environ.get("FACEPIPE_EDITOR_SHOTS", tmp_path))
    h, row = brow_handle(model), 12
    with editor_server(model_path, root / "rig" / "take.csv", "--edits", edits_path, "--evaluate", mode,
                       "--backend", "numpy") as url, browser_page(chromium, url) as page:
        assert page.evaluate("window.facepipeEditor.meta.mode") == mode
        page.evaluate(f"window.facepipeEditor.setFrame({row})")
        wait_settled(page)
        before = screenshot(page, shots / f"editor_{mode}_before.png")
        start = page.evaluate(f"window.facepipeEditor.handleScreen({h})")
        drag(page, start, 0, -40)
        wait_settled(page)
        after = screenshot(page, shots / f"editor_{mode}_after.png")
        end = page.evaluate(f"window.facepipeEditor.handleScreen({h})")
        assert end["y"] < start["y"] - 20  # the handle followed the pointer up
        # the canvas changed around the brow handle, not at the far (chin) side of the face
        diff = np.abs(after - before).sum(axis=2)
        yy, xx = np.mgrid[:diff.shape[0], :diff.shape[1]]
        near = np.hypot(xx - start["x"], yy - start["y"]) < 60
        chin = page.evaluate("window.facepipeEditor.handleScreen(%d)" % int(np.argmin(model.rest[model.handle_vertices][:, 1])))
        far = np.hypot(xx - chin["x"], yy - chin["y"]) < 60
        assert diff[near].mean() > 10 * max(diff[far].mean(), 0.1)
        shown = np.array(page.evaluate("window.facepipeEditor.positions()"), dtype=np.float64).reshape(-1, 3)
        save_edits(page)
        assert not page.errors
    saved = json.loads(edits_path.read_text())
    assert len(saved["edits"]) == 1 and saved["edits"][0]["frame"] == float(take.frames[row])
    out = tmp_path / "replay"
    assert run_cli("replay", root / "rig" / "take.csv", "-m", model_path, "-o", out, "--edits", edits_path,
                   "--backend", "numpy", "--head-motion", "remove", "-q") == 0
    replayed = np.load(out / "positions.npy")[row]
    difference = float(np.abs(shown - replayed).max())
    (shots / f"editor_{mode}_difference.json").write_text(json.dumps({"max_abs_cm": difference}))
    assert difference < 1e-4
    # the edit moved the face there, so the agreement is not that of two unedited frames
    plain = tmp_path / "plain"
    assert run_cli("replay", root / "rig" / "take.csv", "-m", model_path, "-o", plain, "--backend", "numpy",
                   "--head-motion", "remove", "--frames", f"{row}:{row + 1}", "-q") == 0
    assert np.abs(np.load(plain / "positions.npy")[0] - replayed).max() > 0.1


INCREMENTAL_JS = """async () => {
  const { unpackBundle, BrowserEvaluator } = await import('/static/evaluate.js');
  const bundle = unpackBundle(await (await fetch('/api/model.bin')).arrayBuffer());
  const { vertices: V, handles: H, features: F } = bundle.meta;
  let seed = 7;
  const random = () => ((seed = (seed * 16807) % 2147483647) / 2147483647);
  const rest = bundle.arrays.rest, hv = bundle.arrays.handle_vertices, basis = bundle.arrays.basis_features;
  // a pose, features and gate made up: the evaluator takes the pose terms as given
  const handles = Float64Array.from({ length: 3 * H }, (_, i) => rest[3 * hv[Math.floor(i / 3)] + i % 3] + 0.2 * (random() - 0.5));
  const features = Float64Array.from({ length: F }, (_, f) => basis[f] + 0.1 * (random() - 0.5));
  const gate = Float64Array.from({ length: F }, () => 0.5 + 0.5 * random());
  const out = () => [new Float32Array(3 * V), new Float32Array(3 * V), new Float32Array(V)];
  const stepped = new BrowserEvaluator(bundle), whole = new BrowserEvaluator(bundle);
  const [f0, l0, n0] = out();
  stepped.evaluate(handles, features, gate, f0, l0, n0, true);  // nothing to update: whole
  const results = [];
  // a drag: one handle moves and the features of a few edges change; then the gate changes too
  for (const [moveGate, h] of [[false, 3], [false, 3], [true, 5]]) {
    for (let x = 0; x < 3; x++) handles[3 * h + x] += 0.3 * (random() - 0.5);
    for (const f of [h % F, (7 * h + 1) % F]) features[f] += 0.05;
    if (moveGate) gate[h % F] *= 0.5;
    const [f1, l1, n1] = out(), [f2, l2, n2] = out();
    stepped.evaluate(handles, features, gate, f1, l1, n1, true);
    whole.evaluate(handles, features, gate, f2, l2, n2, false);
    let final = 0, large = 0, moved = 0;
    for (let i = 0; i < 3 * V; i++) {
      final = Math.max(final, Math.abs(f1[i] - f2[i])); large = Math.max(large, Math.abs(l1[i] - l2[i]));
      moved = Math.max(moved, Math.abs(f1[i] - f0[i]));
    }
    results.push({ final, large, moved });
  }
  return results;
}"""


@pytest.mark.slow
def test_page_drag_step_evaluation_equals_whole(editor_rig, tmp_path):
    """The page's incremental drag evaluation (evaluate.js) against its whole evaluation of the
    same pose terms: the same surface up to float32 rounding, after a handle, features and the gate move."""
    chromium, reason = chromium_or_reason()
    if chromium is None:
        pytest.skip(reason)
    root, model_path, model, _ = editor_rig
    with editor_server(model_path, "--edits", tmp_path / "e.json", "--evaluate", "browser") as url, \
            browser_page(chromium, url) as page:
        results = page.evaluate(INCREMENTAL_JS)
        assert not page.errors
    scale = float(np.ptp(model.rest))
    for step in results:
        assert step["moved"] > 1e-3 * scale  # the pose moved the face: the comparison is not of two rest faces
        assert step["final"] < 1e-6 * scale and step["large"] < 1e-6 * scale, step


PAGE_NUMERICS_JS = """async ({ normals, albedo, light, handles, edges, rest, points }) => {
  const { lightVertices } = await import('/static/shading.js');
  const { strainFeatures } = await import('/static/evaluate.js');
  const { projectVertices } = await import('/static/partial_redraw.js');
  const V = normals.length / 3;
  const front = new Uint8Array(4 * V), back = new Uint8Array(4 * V);
  lightVertices(Float32Array.from(normals), Float32Array.from(albedo), light, front, back, V);
  const features = strainFeatures(Float64Array.from(handles), Uint32Array.from(edges), Float64Array.from(rest),
                                  new Float64Array(rest.length));
  const { THREE, camera, renderer } = window.facepipeEditor.three;
  const width = renderer.domElement.width, height = renderer.domElement.height;
  const m = new THREE.Matrix4().multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse);
  const screen = projectVertices(Float32Array.from(points), m.elements, width, height, new Float32Array(points.length / 3 * 2), points.length / 3);
  const want = [];  // three.js's own projection, to drawing-buffer pixels
  for (let i = 0; i < points.length; i += 3) {
    const p = new THREE.Vector3(points[i], points[i + 1], points[i + 2]).project(camera);
    want.push((p.x + 1) / 2 * width, (1 - p.y) / 2 * height);
  }
  return { front: Array.from(front), back: Array.from(back), features: Array.from(features),
           screen: Array.from(screen), want };
}"""


@pytest.mark.slow
def test_page_lighting_strain_and_projection(editor_rig, tmp_path):
    """The page's per-vertex Lambert lighting in sRGB bytes (shading.js), its strain features
    (evaluate.js) and its screen projection (partial_redraw.js) against independent references:
    the lighting formula and sRGB transfer in NumPy, core.strain.strain_features, three.js's project."""
    from facepipe.core.strain import strain_features

    chromium, reason = chromium_or_reason()
    if chromium is None:
        pytest.skip(reason)
    root, model_path, model, _ = editor_rig
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(300, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    albedo = rng.uniform(0, 1, size=(300, 3))
    key, up = np.array([0.3, 0.8, 0.52]), np.array([0.0, 1.0, 0.0])
    key /= np.linalg.norm(key)
    light = {"key": key.tolist(), "up": up.tolist(), "keyColour": [2.2, 2.2, 2.2], "sky": [0.6, 0.6, 0.6],
             "ground": [0.03, 0.03, 0.03]}
    handles = model.rest[model.handle_vertices].astype(np.float64) + rng.normal(scale=0.2, size=(len(model.handle_vertices), 3))
    points = model.rest[rng.choice(model.n_vertices, 50, replace=False)].astype(np.float64)
    with editor_server(model_path, "--edits", tmp_path / "e.json", "--evaluate", "browser") as url, \
            browser_page(chromium, url) as page:
        got = page.evaluate(PAGE_NUMERICS_JS, {
            "normals": normals.ravel().tolist(), "albedo": albedo.ravel().tolist(), "light": light,
            "handles": handles.ravel().tolist(), "edges": model.edges.ravel().tolist(),
            "rest": model.rest_lengths.tolist(), "points": points.ravel().tolist()})
        assert not page.errors
    for side, sign in (("front", 1.0), ("back", -1.0)):
        n = sign * normals
        linear = albedo / np.pi * (2.2 * np.maximum(n @ key, 0.0)[:, None] + 0.03 + 0.57 * (0.5 * (n @ up) + 0.5)[:, None])
        srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.maximum(linear, 0) ** (1 / 2.4) - 0.055)
        want = np.round(255 * np.clip(srgb, 0, 1))
        bytes_ = np.array(got[side]).reshape(-1, 4)
        assert np.abs(bytes_[:, :3] - want).max() <= 1 and (bytes_[:, 3] == 255).all(), side
    want_features = strain_features(handles[None], model.edges, model.rest_lengths)[0]
    np.testing.assert_allclose(got["features"], want_features, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got["screen"], got["want"], atol=1e-2)


@pytest.mark.slow
def test_page_partial_redraw_matches_a_whole_drawing(editor_rig, tmp_path):
    """While a handle is dragged the page redraws only the rectangle its change reaches
    (partial_redraw.js): the canvas then equals a whole drawing of the same frame but for
    sub-pixel differences at a few pixels."""
    chromium, reason = chromium_or_reason()
    if chromium is None:
        pytest.skip(reason)
    root, model_path, model, _ = editor_rig
    h = brow_handle(model)
    with editor_server(model_path, root / "rig" / "take.csv", "--edits", tmp_path / "e.json", "--evaluate",
                       "browser") as url, browser_page(chromium, url) as page:
        page.evaluate("window.facepipeEditor.setFrame(12)")
        wait_settled(page)
        start = page.evaluate(f"window.facepipeEditor.handleScreen({h})")
        page.mouse.move(start["x"], start["y"])
        page.mouse.down()
        for k in range(1, 16):  # held: the drag's frames are drawn in part
            page.mouse.move(start["x"], start["y"] - 2 * k)
            page.wait_for_function("window.facepipeEditor.idle")
        wait_settled(page)  # the pointer rests: the exact gate's frame, drawn in part as well
        redrawn = page.evaluate("window.facepipeEditor.state.timings.redrawn_triangles")
        part = canvas_pixels(page)
        page.evaluate("window.facepipeEditor.redrawWhole()")
        page.evaluate("() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
        whole = canvas_pixels(page)
        page.mouse.up()
        assert not page.errors
    assert 0 < redrawn < len(model.triangles)  # drawn in part
    differs = np.abs(part - whole).max(axis=2) > 8
    face = np.abs(whole - whole[0, 0]).max(axis=2) > 8  # not the background
    assert face.sum() > 1000 and differs.sum() <= 0.002 * face.sum(), (differs.sum(), face.sum())


def canvas_pixels(page) -> np.ndarray:
    """The editor's canvas as drawn (RGB, float): its drawing buffer, kept between frames."""
    import base64
    import io

    import imageio.v3 as iio

    url = page.evaluate("window.facepipeEditor.three.renderer.domElement.toDataURL('image/png')")
    return iio.imread(io.BytesIO(base64.b64decode(url.split(",", 1)[1])))[..., :3].astype(float)
