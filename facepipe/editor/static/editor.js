// facepipe edit: the page. Shows the face, its handles and the timeline; a drag of a handle
// sends the uncommitted edit with every move and draws the answer; releasing commits the edit.
//
// Three stages overlap, so a frame costs the slowest of them rather than their sum: the server
// forms the pose terms (browser mode) or positions (server mode) of the latest request; a worker
// thread (evaluate_worker.js) evaluates the vertices and their normals; this thread uploads and
// draws the newest finished frame once per animation frame (requestAnimationFrame), dropping any
// it had no time to show.
import * as THREE from 'three';
import { OrbitControls } from '/static/vendor/three/OrbitControls.js';
import { unpackBundle, strainFeatures, vertexNormals } from '/static/evaluate.js';
import { faceMaterial, faceLight, markerMaterial } from '/static/materials.js';
import { lightVertices } from '/static/shading.js';
import { REDRAW_PIXELS, changedVertices, growOverTriangles, projectVertices, trianglesIn } from '/static/partial_redraw.js';

const $ = (id) => document.getElementById(id);
const SKIN = [0.86, 0.72, 0.64];

const state = {
  ready: false, frame: 0, layer: 'final', preview: null, inFlight: 0, pending: false, requestId: 0,
  playing: false, inFlightMax: 2, evaluations: 0, presented: 0, frameTimes: [], truth: null, truthRow: -1,
  edits: [], workerBusy: false, dragRequests: new Set(), timings: {}, stageSums: {}, stageCounts: {},
};
// where a frame's time goes (milliseconds): the latest, and sums and counts for averages
function note(stage, ms) {
  state.timings[stage] = ms;
  state.stageSums[stage] = (state.stageSums[stage] || 0) + ms;
  state.stageCounts[stage] = (state.stageCounts[stage] || 0) + 1;
}

// a draw at the next animation frame (see present)
let scheduled = false, redraw = false;
function schedule(again = true) {
  if (again) redraw = true;
  if (!scheduled) { scheduled = true; requestAnimationFrame(present); }
}

const modelBuffer = await (await fetch('/api/model.bin')).arrayBuffer();
const bundle = unpackBundle(modelBuffer);
const meta = bundle.meta;
const V = meta.vertices, H = meta.handles, F = meta.features;
// this thread keeps its own copies of the mesh: the bundle (with B) moves to the worker
const rest = bundle.arrays.rest.slice();
const triangles = bundle.arrays.triangles.slice();
const handleVertices = bundle.arrays.handle_vertices.slice();
// browser mode: a drag's steps are posed here (see evaluateHere)
const featureEdges = bundle.arrays.edges ? bundle.arrays.edges.slice() : null;
const restLengths = bundle.arrays.rest_lengths ? bundle.arrays.rest_lengths.slice() : null;
let handles = new Float64Array(H * 3);
for (let h = 0; h < H; h++) for (let x = 0; x < 3; x++) handles[3 * h + x] = rest[3 * handleVertices[h] + x];
let drag = null;      // the handle being dragged (pointerdown)
let shown = null;     // the frame on screen: the worker's set of arrays (final, large, normal, …)
let incoming = null;  // the newest finished frame not yet drawn

// ---------------------------------------------------------------- scene
// the drawing is kept between frames: a drag redraws only what it changes (partial_redraw.js)
const renderer = new THREE.WebGLRenderer({ antialias: false, powerPreference: 'high-performance', preserveDrawingBuffer: true });
// while a handle is dragged or the take plays the canvas renders at half resolution: a software
// rasteriser (a machine without a GPU) is bound by the pixels it shades; full resolution once settled
const fullRatio = window.devicePixelRatio;
let interactive = false;
function setInteractive(on) {
  if (on === interactive) return;
  interactive = on;
  renderer.setPixelRatio(on ? fullRatio / 2 : fullRatio);
  renderer.setSize(window.innerWidth, window.innerHeight);
  schedule();
}
renderer.setPixelRatio(fullRatio);
renderer.setSize(window.innerWidth, window.innerHeight);
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x303338);
// drawn: the positions and the lit colours of the front and back faces (bytes, see materials.js);
// the normals stay in this thread (a Shift drag's direction)
const geometry = new THREE.BufferGeometry();
const positionAttr = new THREE.BufferAttribute(rest.slice(), 3);
positionAttr.setUsage(THREE.DynamicDrawUsage);
geometry.setAttribute('position', positionAttr);
const frontAttr = new THREE.BufferAttribute(new Uint8Array(V * 4), 4, true);
frontAttr.setUsage(THREE.DynamicDrawUsage);
geometry.setAttribute('front', frontAttr);
const backAttr = new THREE.BufferAttribute(new Uint8Array(V * 4), 4, true);
backAttr.setUsage(THREE.DynamicDrawUsage);
geometry.setAttribute('back', backAttr);
let shownNormal = new Float32Array(V * 3);
vertexNormals(triangles, rest, shownNormal, V);
const wholeIndex = new THREE.BufferAttribute(triangles, 1);
const partIndex = new THREE.BufferAttribute(new Uint32Array(triangles.length), 1);
partIndex.setUsage(THREE.DynamicDrawUsage);
geometry.setIndex(wholeIndex);
// what the last whole drawing showed (see drawScene)
const drawn = { key: null, screen: new Float32Array(2 * V), front: new Uint8Array(4 * V), back: new Uint8Array(4 * V),
                rect: null };
const screenNow = new Float32Array(2 * V), changed = new Uint8Array(V), viewProjection = new THREE.Matrix4();
geometry.computeBoundingSphere();

// frame the rest face: look along its mean normal at the markers, y up unless that is the view
const box = new THREE.Box3().setFromBufferAttribute(new THREE.BufferAttribute(rest, 3));
const centre = box.getCenter(new THREE.Vector3());
const radius = box.getSize(new THREE.Vector3()).length() / 2;
// the face moves by centimetres about a head's size: the rest's bounds, grown, never cull it
geometry.boundingSphere.radius *= 2;
const view = new THREE.Vector3(...meta.view).normalize();
const camera = new THREE.PerspectiveCamera(30, window.innerWidth / window.innerHeight, radius / 100, radius * 100);
camera.up.set(0, 1, 0);
if (Math.abs(view.y) > 0.9) camera.up.set(0, 0, 1);
camera.position.copy(centre).addScaledVector(view, radius * 3.2);
camera.lookAt(centre);
// a key light from above and the side at a grazing angle: wrinkles show as shading
const side = new THREE.Vector3().crossVectors(camera.up, view).normalize();
const keyPosition = centre.clone().addScaledVector(view, radius * 0.8).addScaledVector(camera.up, radius * 2.5).addScaledVector(side, radius * 0.5);
const light = faceLight(keyPosition.clone().sub(centre).normalize(), new THREE.Vector3(0, 1, 0));
lightVertices(shownNormal, SKIN, light, frontAttr.array, backAttr.array, V);
const face = new THREE.Mesh(geometry, faceMaterial());
scene.add(face);

// the handles: round points, one draw
const markerGeometry = new THREE.BufferGeometry();
const markerPositions = new THREE.BufferAttribute(new Float32Array(3 * H), 3);
markerPositions.setUsage(THREE.DynamicDrawUsage);
markerGeometry.setAttribute('position', markerPositions);
const markerColours = new THREE.BufferAttribute(new Float32Array(3 * H), 3);
markerGeometry.setAttribute('markerColour', markerColours);
const markers = new THREE.Points(markerGeometry, markerMaterial(meta.marker_size));
markers.frustumCulled = false;
scene.add(markers);
const markerColour = new THREE.Color(0x2f8cff), activeColour = new THREE.Color(0xffd23f);
function placeMarkers() {
  markerPositions.array.set(handles);
  markerPositions.needsUpdate = true;
}
function markHandle(h, active) {
  const c = active ? activeColour : markerColour;
  markerColours.setXYZ(h, c.r, c.g, c.b);
  markerColours.needsUpdate = true;
  schedule();
}
for (let h = 0; h < H; h++) markHandle(h, false);
placeMarkers();

// ---------------------------------------------------------------- the worker
const worker = new Worker('/static/evaluate_worker.js', { type: 'module' });
await new Promise((resolve, reject) => {
  worker.onmessage = (e) => e.data.op === 'ready' && resolve();
  worker.onerror = (e) => reject(new Error(`the evaluation worker failed: ${e.message}`));
  worker.postMessage({ op: 'init', buffer: modelBuffer, light, skin: SKIN }, [modelBuffer]);
});
let workerNext = null;  // the newest job waiting for the worker (older ones are dropped)
function toWorker(job, transfer = []) {
  if (state.workerBusy) {
    workerNext = { job, transfer };
    return;
  }
  state.workerBusy = true;
  worker.postMessage(job, transfer);
}
function recycle(set) {
  worker.postMessage({ op: 'recycle', set }, [set.final.buffer, set.large.buffer, set.normal.buffer, set.detailN.buffer,
                                               set.color.buffer, set.front.buffer, set.back.buffer]);
}
worker.onmessage = (event) => {
  const m = event.data;
  state.workerBusy = false;
  if (workerNext) { const next = workerNext; workerNext = null; toWorker(next.job, next.transfer); }
  if (m.op !== 'frame') return;
  state.evaluations += 1;
  note('worker_evaluate', m.timings.evaluate);
  note('worker_normals', m.timings.normals);
  note('worker_light', m.timings.light);
  if (incoming) recycle(incoming.set);
  incoming = m;
  schedule();
};
worker.onerror = (e) => { $('message').textContent = `evaluation failed: ${e.message}`; };

// ---------------------------------------------------------------- drawing

function heat(t) {  // 0..1 → dark blue, cyan, yellow, red
  t = Math.min(Math.max(t, 0), 1);
  return [Math.min(1, Math.max(0, 1.5 * t * 2 - 1)), Math.min(1, Math.max(0, 2 - Math.abs(4 * t - 2))), Math.min(1, Math.max(0, 1.5 - 3 * t))];
}

// the lit colours of a frame: the worker's, or (error layer) the heat map lit here
function colour(frame) {
  if (frame.layer === 'error' && state.truth) {
    const final = frame.set.final, e = new Float32Array(V), albedo = new Float32Array(3 * V);
    let top = 1e-12;
    for (let v = 0; v < V; v++) {
      const dx = final[3 * v] - state.truth[3 * v], dy = final[3 * v + 1] - state.truth[3 * v + 1], dz = final[3 * v + 2] - state.truth[3 * v + 2];
      e[v] = Math.sqrt(dx * dx + dy * dy + dz * dz);
      top = Math.max(top, e[v]);
    }
    for (let v = 0; v < V; v++) { const [r, g, b] = heat(e[v] / top); albedo[3 * v] = r; albedo[3 * v + 1] = g; albedo[3 * v + 2] = b; }
    $('message').textContent = `error up to ${top.toFixed(3)} ${meta.units || ''}`;
    lightVertices(frame.set.normal, albedo, light, frontAttr.array, backAttr.array, V);
  } else {
    frontAttr.array.set(frame.set.front);
    backAttr.array.set(frame.set.back);
  }
  frontAttr.needsUpdate = true;
  backAttr.needsUpdate = true;
}

// once per animation frame: the newest finished frame (if any) is uploaded and the scene drawn
function present(now) {
  scheduled = false;
  if (incoming) {
    const t0 = performance.now();
    const frame = incoming;
    incoming = null;
    positionAttr.array.set(frame.layer === 'large' && frame.layered ? frame.set.large : frame.set.final);
    positionAttr.needsUpdate = true;
    shownNormal = frame.set.normal;
    colour(frame);
    handles = frame.handles;
    placeMarkers();
    if (shown) recycle(shown.set);
    shown = frame;
    if (state.pending) requestEvaluation();
    state.shownRow = frame.row;
    state.shownId = frame.id;
    state.exact = frame.exact;
    if (!drag && !state.playing && state.exact) setInteractive(false);
    note('upload', performance.now() - t0);
    state.presented += 1;
    state.frameTimes.push(now);
    while (state.frameTimes.length && state.frameTimes[0] < now - 1000) state.frameTimes.shift();
    redraw = true;
  }
  if (!redraw || state.noRender) return;
  redraw = false;
  const t1 = performance.now();
  markers.material.uniforms.pixelsPerUnit.value =
    renderer.domElement.height / (2 * Math.tan(THREE.MathUtils.degToRad(camera.fov) / 2));
  drawScene();
  note('render_submit', performance.now() - t1);
  // the status line four times a second: a changed text costs a repaint of its layer every frame
  if (now - (state.statusAt || 0) > 250) { state.statusAt = now; showStatus(); }
  else if (!state.statusTimer) state.statusTimer = setTimeout(() => { state.statusTimer = null; showStatus(); }, 260);
}

// the scene, whole or (while a handle is dragged) the part the drag changed since the last whole
// drawing (partial_redraw.js)
function drawScene() {
  const width = renderer.domElement.width, height = renderer.domElement.height;
  camera.updateMatrixWorld();
  viewProjection.multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse);
  projectVertices(positionAttr.array, viewProjection.elements, width, height, screenNow, V);
  const key = `${width}x${height} ${state.shownRow} ${shown ? shown.layer : ''}`;
  let triangleCount = -1;
  if (drag && drawn.key === key) {
    // the rectangle grows over the triangles of the vertices changed since the whole drawing
    changedVertices({ screen: screenNow, front: frontAttr.array, back: backAttr.array }, drawn, REDRAW_PIXELS, changed, V);
    const rect = growOverTriangles(triangles, changed, [screenNow, drawn.screen], drawn.rect);
    // a pixel's rounding either side, and the handles' discs (drawn about their vertices, see materials.js)
    const grow = 2 + 1.5 * meta.marker_size * markers.material.uniforms.pixelsPerUnit.value / camera.position.distanceTo(centre);
    const clip = { x0: Math.max(0, Math.floor(rect.x0 - grow)), y0: Math.max(0, Math.floor(rect.y0 - grow)),
                   x1: Math.min(width, Math.ceil(rect.x1 + grow)), y1: Math.min(height, Math.ceil(rect.y1 + grow)) };
    if (clip.x1 > clip.x0 && clip.y1 > clip.y0) {
      triangleCount = trianglesIn(triangles, screenNow, clip, partIndex.array);
      if (triangleCount > 0.6 * triangles.length / 3) triangleCount = -1;  // most of it: whole is as cheap
    } else {
      triangleCount = 0;
    }
    if (triangleCount >= 0) {
      const ratio = renderer.getPixelRatio();  // three.js takes the scissor in CSS pixels, y up
      partIndex.clearUpdateRanges();
      partIndex.addUpdateRange(0, 3 * triangleCount);
      partIndex.needsUpdate = true;
      geometry.setIndex(partIndex);
      geometry.setDrawRange(0, 3 * triangleCount);
      renderer.setScissor(clip.x0 / ratio, (height - clip.y1) / ratio, (clip.x1 - clip.x0) / ratio, (clip.y1 - clip.y0) / ratio);
      renderer.setScissorTest(true);
      renderer.render(scene, camera);
      renderer.setScissorTest(false);
      note('redrawn_triangles', triangleCount);
      return;
    }
  }
  geometry.setIndex(wholeIndex);
  geometry.setDrawRange(0, Infinity);
  renderer.render(scene, camera);
  note('redrawn_triangles', triangles.length / 3);
  drawn.key = key;
  drawn.screen.set(screenNow);
  drawn.front.set(frontAttr.array);
  drawn.back.set(backAttr.array);
  drawn.rect = { x0: Infinity, y0: Infinity, x1: -Infinity, y1: -Infinity };
}

// ---------------------------------------------------------------- the server
const socket = new WebSocket(`ws://${location.host}/ws`);
socket.binaryType = 'arraybuffer';

function requestEvaluation() {
  if (drag && drag.local && state.preview) evaluateHere(); else askServer();
}

function askServer() {
  if (socket.readyState !== WebSocket.OPEN) return;
  // two requests in flight: the server forms the next answer while the last one is evaluated and
  // drawn; none while a finished frame waits to be drawn (a frame made faster than the screen
  // takes them would be dropped: its work is better left to the others on a busy machine)
  if (state.inFlight >= state.inFlightMax || incoming || workerNext) { state.pending = true; return; }
  state.inFlight += 1;
  state.pending = false;
  state.sentAt = performance.now();
  if (state.preview) state.dragRequests.add(state.requestId + 1);
  socket.send(JSON.stringify({ op: 'eval', id: ++state.requestId, frame: state.frame, preview: state.preview, layer: state.layer }));
}

// Browser mode, while a handle is dragged: the step's pose terms are formed here rather than asked
// of the server (a round trip through the browser's network process and the server's event loop
// per step): the handles of the frame as last answered (its edits applied, no preview) with the
// drag's offset added (its own key frame: weight 1, core/edits.py), their strain features, and the
// gate the server would stand in with — the latest exact one, that of the last answer. When the
// pointer rests the server is asked as before (the gate's exact fits follow), and the frame shown
// once the handle is released is the server's. Answers to requests older than a step made here
// are not shown (the pose has moved on).
const REST_MS = 150;
function evaluateHere() {
  if (incoming || state.workerBusy) { state.pending = true; return; }
  state.pending = false;
  const { handle, offset } = state.preview;
  const handles = drag.local.handles.slice();
  for (let x = 0; x < 3; x++) handles[3 * handle + x] += offset[x];
  const id = ++state.requestId;
  state.localFloor = id;
  toWorker({ op: 'pose', id, row: state.frame, exact: false, layer: state.layer, drag: true, handles,
             features: strainFeatures(handles, featureEdges, restLengths, new Float64Array(F)), gate: drag.local.gate });
  clearTimeout(state.restTimer);
  const onRest = () => {
    if (!drag || !drag.local) return;
    if (state.inFlight >= state.inFlightMax || incoming || workerNext) { state.restTimer = setTimeout(onRest, REST_MS); return; }
    askServer();
  };
  state.restTimer = setTimeout(onRest, REST_MS);
}

function easing() {
  return { ease_in: Math.max(0, Number($('easeIn').value) || 0), ease_out: Math.max(0, Number($('easeOut').value) || 0) };
}

// an answer of the server (see facepipe/editor/server.py) to the worker
function receive(buffer) {
  const head = new Float64Array(buffer, 0, 6);
  const [id, row, kind, layers, exact] = head;
  // a drag's step may be evaluated from the last frame (evaluate.js); any other frame whole
  const job = { id, row, exact: exact === 1, layer: state.layer, drag: state.dragRequests.has(id) };
  for (const old of state.dragRequests) if (old <= id) state.dragRequests.delete(old);
  if (kind === 0) {  // pose terms: evaluated in the worker
    if (id < (state.localFloor || 0)) return;  // older than a drag step posed here
    const terms = new Float64Array(buffer, 48);
    Object.assign(job, { op: 'pose', handles: terms.slice(0, 3 * H), features: terms.slice(3 * H, 3 * H + F),
                         gate: meta.gate ? terms.slice(3 * H + F, 3 * H + 2 * F) : null });
    state.lastPose = { row, handles: job.handles, gate: job.gate, preview: job.drag };
    // an answer while the pointer rested: the gate the server now stands in with for this drag
    if (drag && drag.local && job.drag) drag.local.gate = job.gate;
    toWorker(job);
  } else if (kind === 1) {  // whole positions
    const offset = 48 + 24 * H;
    Object.assign(job, { op: 'positions', handles: new Float64Array(buffer, 48, 3 * H).slice(),
                         final: new Float32Array(buffer, offset, 3 * V),
                         large: layers === 2 ? new Float32Array(buffer, offset + 12 * V, 3 * V) : null });
    toWorker(job, [buffer]);
  } else {  // a drag's patch (2: its base, 3: a step)
    const h8 = new Float64Array(buffer, 0, 8), serial = h8[6], n = h8[7], base = 64 + 24 * H;
    if (kind === 2) {  // never dropped: posted ahead of any waiting step
      worker.postMessage({ op: 'patch', serial, final: new Float32Array(buffer, base, 3 * V),
                           large: new Float32Array(buffer, base + 12 * V, 3 * V),
                           column: new Float32Array(buffer, base + 24 * V, V),
                           vertices: new Uint32Array(buffer, base + 28 * V, n) }, [buffer]);
      return;
    }
    Object.assign(job, { op: 'step', serial, handles: new Float64Array(buffer, 64, 3 * H).slice(),
                         offset: Array.from(new Float64Array(buffer, base, 3)), values: new Float32Array(buffer, base + 24, 3 * n) });
    toWorker(job, [buffer]);
  }
}

function fps() {
  const t = state.frameTimes;
  return t.length < 2 ? 0 : (t.length - 1) * 1000 / (t[t.length - 1] - t[0]);
}

function showStatus() {
  const where = meta.mode === 'browser' ? 'evaluated in the browser (JavaScript, worker)' : `evaluated on the server (${meta.engine}), streamed`;
  const gate = meta.gate ? (state.exact ? ' · gate exact' : ' · gate updating') : '';
  $('status').textContent = `${V} vertices · ${where} · ${fps().toFixed(1)} frames/s${gate}`;
}

function showEdits(message) {
  state.edits = message.edits;
  $('undo').disabled = !message.can_undo;
  $('redo').disabled = !message.can_redo;
  $('edits').textContent = message.edits.length
    ? message.edits.map((e) => `frame ${e.frame} (in ${e.ease_in}, out ${e.ease_out}): ` +
        Object.entries(e.offsets).map(([n, o]) => `${n} [${o.map((x) => x.toFixed(3)).join(', ')}]`).join('; ')).join('\n')
    : 'no edits';
  if (message.saved) $('message').textContent = `saved ${message.saved}`;
}

socket.addEventListener('message', (event) => {
  if (typeof event.data === 'string') {
    const message = JSON.parse(event.data);
    if (message.type === 'state') { showEdits(message); state.lastState = message; }
    else if (message.type === 'error') { $('message').textContent = message.message; state.inFlight = Math.max(0, state.inFlight - 1); }
    return;
  }
  const head = new Float64Array(event.data, 0, 6);
  if (head[5] === 1) {  // the exact evaluation of an earlier request, sent when the gate's fits were made
    if (head[0] === state.requestId && state.inFlight === 0) receive(event.data);
    return;
  }
  const answers = head[2] !== 2;  // a patch's base comes ahead of the answer
  if (answers) {
    state.inFlight -= 1;
    note('round_trip', performance.now() - state.sentAt);
  }
  receive(event.data);
  if (!answers) return;
  if (state.pending) requestEvaluation();
  else if (state.playing) requestAnimationFrame(advance);
  state.ready = true;
});
socket.addEventListener('open', () => requestEvaluation());
socket.addEventListener('close', () => { $('message').textContent = 'disconnected from the server'; });

// ---------------------------------------------------------------- timeline
const scrub = $('scrub');
scrub.max = String(meta.frames.length - 1);
function setFrame(row) {
  state.frame = Math.max(0, Math.min(meta.frames.length - 1, row));
  scrub.value = String(state.frame);
  $('frameLabel').textContent = `frame ${meta.frames[state.frame]} (${meta.times[state.frame].toFixed(2)} s) of ${meta.take}`;
  if (state.layer === 'error') loadTruth().then(requestEvaluation); else requestEvaluation();
}
scrub.addEventListener('input', () => setFrame(Number(scrub.value)));
let playStart = 0, playFrom = 0;
function advance() {
  if (!state.playing) return;
  const elapsed = (performance.now() - playStart) / 1000;
  const t0 = meta.times[playFrom];
  let row = playFrom;
  while (row + 1 < meta.times.length && meta.times[row + 1] - t0 <= elapsed) row++;
  if (row >= meta.times.length - 1) { state.playing = false; $('play').textContent = 'Play'; }
  setFrame(row);
}
$('play').addEventListener('click', () => {
  state.playing = !state.playing;
  $('play').textContent = state.playing ? 'Pause' : 'Play';
  if (state.playing) {
    playFrom = state.frame >= meta.frames.length - 1 ? 0 : state.frame;
    playStart = performance.now();
    setInteractive(true);
    advance();
  }
});

async function loadTruth() {
  if (!meta.truth || state.truthRow === state.frame) return;
  state.truth = new Float32Array(await (await fetch(`/api/truth/${state.frame}`)).arrayBuffer());
  state.truthRow = state.frame;
}
if (meta.truth) $('layer').querySelector('option[value=error]').disabled = false;
$('layer').addEventListener('change', async () => {
  state.layer = $('layer').value;
  if (state.layer === 'error') await loadTruth();
  requestEvaluation();
});

// ---------------------------------------------------------------- edits
const send = (message) => socket.send(JSON.stringify(message));
$('undo').addEventListener('click', () => { send({ op: 'undo' }); requestEvaluation(); });
$('redo').addEventListener('click', () => { send({ op: 'redo' }); requestEvaluation(); });
$('save').addEventListener('click', () => send({ op: 'save' }));
window.addEventListener('keydown', (e) => {
  if ((e.ctrlKey || e.metaKey) && e.key.toLowerCase() === 'z') { e.preventDefault(); $(e.shiftKey ? 'redo' : 'undo').click(); }
  if ((e.ctrlKey || e.metaKey) && e.key.toLowerCase() === 's') { e.preventDefault(); $('save').click(); }
});

// dragging: the handle follows the pointer in the plane through it facing the camera, or with
// Shift along the surface normal at the handle (vertical pointer motion)
const raycaster = new THREE.Raycaster();
const pointer = new THREE.Vector2();
function ray(event) {
  const r = renderer.domElement.getBoundingClientRect();
  pointer.set(((event.clientX - r.left) / r.width) * 2 - 1, -((event.clientY - r.top) / r.height) * 2 + 1);
  raycaster.setFromCamera(pointer, camera);
  return raycaster.ray;
}
function handleNormal(h) {
  const v = handleVertices[h];
  return new THREE.Vector3(shownNormal[3 * v], shownNormal[3 * v + 1], shownNormal[3 * v + 2]).normalize();
}
// the handle drawn under the pointer (its disc, grown by a few pixels to be easy to hit; the
// nearest to the camera where discs overlap), or -1
function pick(event) {
  const r = renderer.domElement.getBoundingClientRect();
  const pixelsPerUnit = r.height / (2 * Math.tan(THREE.MathUtils.degToRad(camera.fov) / 2));
  const p = new THREE.Vector3();
  let best = -1, bestDepth = Infinity;
  for (let h = 0; h < H; h++) {
    p.set(handles[3 * h], handles[3 * h + 1], handles[3 * h + 2]);
    const depth = p.distanceTo(camera.position);
    p.project(camera);
    const x = r.left + (p.x + 1) / 2 * r.width, y = r.top + (1 - p.y) / 2 * r.height;
    const reach = meta.marker_size * pixelsPerUnit / depth + 3;
    if (p.z < 1 && Math.hypot(event.clientX - x, event.clientY - y) <= reach && depth < bestDepth) { best = h; bestDepth = depth; }
  }
  return best;
}
renderer.domElement.addEventListener('pointerdown', (event) => {
  const h = pick(event);
  if (h < 0) return;
  event.stopImmediatePropagation();  // not an orbit
  const start = new THREE.Vector3(handles[3 * h], handles[3 * h + 1], handles[3 * h + 2]);
  const normal = camera.getWorldDirection(new THREE.Vector3());
  const perPixel = 2 * start.distanceTo(camera.position) * Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)) / renderer.domElement.clientHeight;
  drag = { h, start, plane: new THREE.Plane().setFromNormalAndCoplanarPoint(normal, start), y0: event.clientY,
           surfaceNormal: handleNormal(h), perPixel, pointerId: event.pointerId, local: null };
  // the steps are posed here from the frame as the server last answered it, if that is this frame
  // without a preview and nothing newer is on its way (evaluateHere)
  const last = state.lastPose;
  if (featureEdges && last && last.row === state.frame && !last.preview && state.inFlight === 0 && !state.pending) {
    drag.local = { handles: last.handles, gate: last.gate };
  }
  markHandle(h, true);
  setInteractive(true);
  renderer.domElement.setPointerCapture(event.pointerId);
}, { capture: true });
renderer.domElement.addEventListener('pointermove', (event) => {
  if (!drag) return;
  let offset;
  if (event.shiftKey) {
    offset = drag.surfaceNormal.clone().multiplyScalar((drag.y0 - event.clientY) * drag.perPixel);
  } else {
    const hit = ray(event).intersectPlane(drag.plane, new THREE.Vector3());
    if (!hit) return;
    offset = hit.sub(drag.start);
  }
  state.preview = { handle: drag.h, offset: offset.toArray(), ...easing() };
  requestEvaluation();
});
function endDrag() {
  if (!drag) return;
  clearTimeout(state.restTimer);
  markHandle(drag.h, false);
  if (state.preview) send({ op: 'commit', frame: state.frame, preview: state.preview });
  state.preview = null;
  drag = null;
  requestEvaluation();
}
renderer.domElement.addEventListener('pointerup', endDrag);
renderer.domElement.addEventListener('pointercancel', endDrag);

const controls = new OrbitControls(camera, renderer.domElement);
controls.target.copy(centre);
controls.update();
controls.addEventListener('change', () => { drawn.key = null; schedule(); });
window.addEventListener('resize', () => {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
  drawn.key = null;
  schedule();
});

// ---------------------------------------------------------------- for tests and scripts
window.facepipeEditor = {
  meta, state,
  get ready() { return state.ready; },
  get idle() { return state.inFlight === 0 && !state.pending && !state.workerBusy && !incoming; },
  // the shown frame is the exact evaluation of the latest request (the gate's fits included)
  get settled() { return this.idle && state.exact && state.shownId === state.requestId; },
  fps,
  setFrame,
  // the positions shown for the current frame (final layer), as a plain array
  positions: () => Array.from(shown.set.final),
  // where handle h is drawn, in CSS pixels of the page
  handleScreen(h) {
    const p = new THREE.Vector3(handles[3 * h], handles[3 * h + 1], handles[3 * h + 2]).project(camera);
    const r = renderer.domElement.getBoundingClientRect();
    return { x: r.left + (p.x + 1) / 2 * r.width, y: r.top + (1 - p.y) / 2 * r.height };
  },
  // what a drag of handle h by offset (rig units) shows, without committing it (scripts, benches)
  preview(h, offset) { state.preview = offset ? { handle: h, offset, ...easing() } : null; setInteractive(!!offset); requestEvaluation(); },
  handlePosition: (h) => Array.from(handles.slice(3 * h, 3 * h + 3)),
  three: { THREE, renderer, scene, camera, face, markers, geometry },  // for experiments on the drawing
  // draw the scene whole at the next animation frame (a drag draws only what it changed)
  redrawWhole() { drawn.key = null; schedule(); },
  // milliseconds a draw of the scene takes to finish in the GPU process, at
  // the drag's resolution: alone, and with the positions and colours uploaded first
  renderCost(n = 10) {
    const gl = renderer.getContext();
    const wasInteractive = interactive;
    setInteractive(true);
    geometry.setIndex(wholeIndex);  // the whole scene (a drag may have left a part of it set)
    geometry.setDrawRange(0, Infinity);
    drawn.key = null;
    const timed = (upload) => {
      const pixel = new Uint8Array(4);
      // a read of a pixel waits for the draw (Chromium's gl.finish is only a flush)
      const finish = () => gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, pixel);
      renderer.render(scene, camera);
      finish();
      const t0 = performance.now();
      for (let i = 0; i < n; i++) {
        if (upload) { positionAttr.needsUpdate = true; frontAttr.needsUpdate = true; backAttr.needsUpdate = true; }
        renderer.render(scene, camera);
        finish();
      }
      return (performance.now() - t0) / n;
    };
    const result = { render: timed(false), upload_and_render: timed(true),
                     pixels: renderer.domElement.width * renderer.domElement.height };
    setInteractive(wasInteractive);
    return result;
  },
};
setFrame(0);
showStatus();
