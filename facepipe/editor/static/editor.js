// facepipe edit: the page. Shows the face, its handles and the timeline; a drag of a handle
// sends the uncommitted edit with every move and draws the answer (pose terms evaluated here in
// browser mode, positions from the server in server mode); releasing commits the edit.
import * as THREE from 'three';
import { OrbitControls } from '/static/vendor/three/OrbitControls.js';
import { unpackBundle, BrowserEvaluator } from '/static/evaluate.js';

const $ = (id) => document.getElementById(id);
const SKIN = [0.86, 0.72, 0.64];

const state = {
  ready: false, frame: 0, layer: 'final', preview: null, inFlight: 0, pending: false, requestId: 0,
  playing: false, inFlightMax: 2, evaluations: 0, frameTimes: [], truth: null, truthRow: -1, edits: [],
};

const bundle = unpackBundle(await (await fetch('/api/model.bin')).arrayBuffer());
const meta = bundle.meta;
const V = meta.vertices, H = meta.handles, F = meta.features;
const evaluator = meta.mode === 'browser' ? new BrowserEvaluator(bundle) : null;
const final = new Float32Array(bundle.arrays.rest);
const large = new Float32Array(bundle.arrays.rest);
const detailN = new Float32Array(V);
let handles = new Float64Array(H * 3);
for (let h = 0; h < H; h++) for (let x = 0; x < 3; x++) handles[3 * h + x] = bundle.arrays.rest[3 * bundle.arrays.handle_vertices[h] + x];

// ---------------------------------------------------------------- scene
const renderer = new THREE.WebGLRenderer({ antialias: false });
// while a handle is dragged or the take plays the canvas renders at half resolution: a software
// rasteriser (a machine without a GPU) is bound by the pixels it shades; full resolution once settled
const fullRatio = window.devicePixelRatio;
let interactive = false;
function setInteractive(on) {
  if (on === interactive) return;
  interactive = on;
  renderer.setPixelRatio(on ? fullRatio / 2 : fullRatio);
  renderer.setSize(window.innerWidth, window.innerHeight);
}
renderer.setPixelRatio(fullRatio);
renderer.setSize(window.innerWidth, window.innerHeight);
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x303338);
const geometry = new THREE.BufferGeometry();
const positionAttr = new THREE.BufferAttribute(new Float32Array(V * 3), 3);
positionAttr.setUsage(THREE.DynamicDrawUsage);
geometry.setAttribute('position', positionAttr);
const colorAttr = new THREE.BufferAttribute(new Float32Array(V * 3), 3);
geometry.setAttribute('color', colorAttr);
geometry.setIndex(new THREE.BufferAttribute(bundle.arrays.triangles, 1));
const material = new THREE.MeshLambertMaterial({ vertexColors: true, side: THREE.DoubleSide });
const face = new THREE.Mesh(geometry, material);
scene.add(face);
scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 0.6));

// frame the rest face: look along its mean normal at the markers, y up unless that is the view
const rest = bundle.arrays.rest;
const box = new THREE.Box3().setFromBufferAttribute(new THREE.BufferAttribute(rest, 3));
const centre = box.getCenter(new THREE.Vector3());
const radius = box.getSize(new THREE.Vector3()).length() / 2;
const view = new THREE.Vector3(...meta.view).normalize();
const camera = new THREE.PerspectiveCamera(30, window.innerWidth / window.innerHeight, radius / 100, radius * 100);
camera.up.set(0, 1, 0);
if (Math.abs(view.y) > 0.9) camera.up.set(0, 0, 1);
camera.position.copy(centre).addScaledVector(view, radius * 3.2);
camera.lookAt(centre);
// a key light from above and the side at a grazing angle: wrinkles show as shading
const key = new THREE.DirectionalLight(0xffffff, 2.2);
const side = new THREE.Vector3().crossVectors(camera.up, view).normalize();
key.position.copy(centre).addScaledVector(view, radius * 0.8).addScaledVector(camera.up, radius * 2.5).addScaledVector(side, radius * 0.5);
key.target.position.copy(centre);
scene.add(key, key.target);

const markerGeometry = new THREE.SphereGeometry(meta.marker_size, 12, 8);
const markerMaterial = new THREE.MeshBasicMaterial({ color: 0x2f8cff });
const activeMaterial = new THREE.MeshBasicMaterial({ color: 0xffd23f });
const markers = [];
for (let h = 0; h < H; h++) {
  const m = new THREE.Mesh(markerGeometry, markerMaterial);
  m.userData.handle = h;
  markers.push(m);
  scene.add(m);
}

// ---------------------------------------------------------------- drawing
function heat(t) {  // 0..1 → dark blue, cyan, yellow, red
  t = Math.min(Math.max(t, 0), 1);
  return [Math.min(1, Math.max(0, 1.5 * t * 2 - 1)), Math.min(1, Math.max(0, 2 - Math.abs(4 * t - 2))), Math.min(1, Math.max(0, 1.5 - 3 * t))];
}

function colour() {
  const c = colorAttr.array;
  if (state.layer === 'details') {
    // scaled by the 95th percentile over the vertices: a few large details (a sparse neck) would
    // otherwise wash out the face's wrinkles
    const sorted = Float32Array.from(detailN, Math.abs).sort();
    const top = Math.max(sorted[Math.floor(0.95 * (V - 1))], 1e-12);
    for (let v = 0; v < V; v++) {  // blue in, white none, red out
      const s = Math.max(-1, Math.min(1, detailN[v] / top));
      c[3 * v] = s > 0 ? 1 : 1 + s; c[3 * v + 1] = 1 - Math.abs(s); c[3 * v + 2] = s < 0 ? 1 : 1 - s;
    }
  } else if (state.layer === 'error' && state.truth) {
    const e = new Float32Array(V);
    let top = 1e-12;
    for (let v = 0; v < V; v++) {
      const dx = final[3 * v] - state.truth[3 * v], dy = final[3 * v + 1] - state.truth[3 * v + 1], dz = final[3 * v + 2] - state.truth[3 * v + 2];
      e[v] = Math.sqrt(dx * dx + dy * dy + dz * dz);
      top = Math.max(top, e[v]);
    }
    for (let v = 0; v < V; v++) { const [r, g, b] = heat(e[v] / top); c[3 * v] = r; c[3 * v + 1] = g; c[3 * v + 2] = b; }
    $('message').textContent = `error up to ${top.toFixed(3)} ${meta.units || ''}`;
  } else {
    for (let v = 0; v < V; v++) { c[3 * v] = SKIN[0]; c[3 * v + 1] = SKIN[1]; c[3 * v + 2] = SKIN[2]; }
  }
  colorAttr.needsUpdate = true;
}

function draw() {
  positionAttr.array.set(state.layer === 'large' ? large : final);
  positionAttr.needsUpdate = true;
  geometry.computeVertexNormals();
  geometry.computeBoundingSphere();
  colour();
  for (let h = 0; h < H; h++) markers[h].position.set(handles[3 * h], handles[3 * h + 1], handles[3 * h + 2]);
  if (!state.noRender) renderer.render(scene, camera);
}

// ---------------------------------------------------------------- the server
const socket = new WebSocket(`ws://${location.host}/ws`);
socket.binaryType = 'arraybuffer';

function requestEvaluation() {
  if (socket.readyState !== WebSocket.OPEN) return;
  // two requests in flight: the server forms the next pose terms while this page draws the last
  if (state.inFlight >= state.inFlightMax) { state.pending = true; return; }
  state.inFlight += 1;
  state.pending = false;
  state.sentAt = performance.now();
  socket.send(JSON.stringify({ op: 'eval', id: ++state.requestId, frame: state.frame, preview: state.preview, layer: state.layer }));
}

function easing() {
  return { ease_in: Math.max(0, Number($('easeIn').value) || 0), ease_out: Math.max(0, Number($('easeOut').value) || 0) };
}

function receive(buffer) {
  const t0 = performance.now();
  const head = new Float64Array(buffer, 0, 6);
  const row = head[1];
  if (head[2] === 0) {  // pose terms: evaluate here
    const terms = new Float64Array(buffer, 48);
    handles = terms.slice(0, 3 * H);
    const features = terms.subarray(3 * H, 3 * H + F);
    const gate = meta.gate ? terms.subarray(3 * H + F, 3 * H + 2 * F) : null;
    evaluator.evaluate(handles, features, gate, final, large, detailN);
  } else {  // positions from the server
    handles = new Float64Array(buffer, 48, 3 * H).slice();
    const offset = 48 + 24 * H;
    final.set(new Float32Array(buffer, offset, 3 * V));
    if (head[3] === 2) {
      large.set(new Float32Array(buffer, offset + 12 * V, 3 * V));
      // the details along the large scale's normal, for the details view
      const n = geometryNormals(large);
      for (let v = 0; v < V; v++) {
        detailN[v] = (final[3 * v] - large[3 * v]) * n[3 * v] + (final[3 * v + 1] - large[3 * v + 1]) * n[3 * v + 1] + (final[3 * v + 2] - large[3 * v + 2]) * n[3 * v + 2];
      }
    }
  }
  state.shownRow = row;
  state.shownId = head[0];
  state.exact = head[4] === 1;
  if (!drag && !state.playing && state.exact) setInteractive(false);
  const t1 = performance.now();
  draw();
  // where the time goes (the server's share is the rest of the round trip)
  state.timings = { evaluate: t1 - t0, draw: performance.now() - t1, roundTrip: t0 - state.sentAt };
  state.evaluations += 1;
  const now = performance.now();
  state.frameTimes.push(now);
  while (state.frameTimes.length && state.frameTimes[0] < now - 1000) state.frameTimes.shift();
  showStatus();
}

function geometryNormals(positions) {
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.BufferAttribute(positions, 3));
  g.setIndex(geometry.index);
  g.computeVertexNormals();
  return g.getAttribute('normal').array;
}

function fps() {
  const t = state.frameTimes;
  return t.length < 2 ? 0 : (t.length - 1) * 1000 / (t[t.length - 1] - t[0]);
}

function showStatus() {
  const where = meta.mode === 'browser' ? 'evaluated in the browser (JavaScript)' : `evaluated on the server (${meta.engine}), streamed`;
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
  const refine = new Float64Array(event.data, 0, 6);
  if (refine[5] === 1) {  // the exact evaluation of an earlier request, sent when the gate's fits were made
    if (refine[0] === state.requestId && state.inFlight === 0) receive(event.data);
    return;
  }
  state.inFlight -= 1;
  receive(event.data);
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
let drag = null;
function ray(event) {
  const r = renderer.domElement.getBoundingClientRect();
  pointer.set(((event.clientX - r.left) / r.width) * 2 - 1, -((event.clientY - r.top) / r.height) * 2 + 1);
  raycaster.setFromCamera(pointer, camera);
  return raycaster.ray;
}
function handleNormal(h) {
  const n = geometry.getAttribute('normal');
  const v = bundle.arrays.handle_vertices[h];
  return new THREE.Vector3(n.getX(v), n.getY(v), n.getZ(v)).normalize();
}
renderer.domElement.addEventListener('pointerdown', (event) => {
  const hit = (ray(event), raycaster.intersectObjects(markers, false))[0];
  if (!hit) return;
  event.stopImmediatePropagation();  // not an orbit
  const h = hit.object.userData.handle;
  const start = hit.object.position.clone();
  const normal = camera.getWorldDirection(new THREE.Vector3());
  const perPixel = 2 * start.distanceTo(camera.position) * Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)) / renderer.domElement.clientHeight;
  drag = { h, start, plane: new THREE.Plane().setFromNormalAndCoplanarPoint(normal, start), y0: event.clientY,
           surfaceNormal: handleNormal(h), perPixel, pointerId: event.pointerId };
  hit.object.material = activeMaterial;
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
  markers[drag.h].material = markerMaterial;
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
controls.addEventListener('change', () => renderer.render(scene, camera));
window.addEventListener('resize', () => {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
  renderer.render(scene, camera);
});

// ---------------------------------------------------------------- for tests and scripts
window.facepipeEditor = {
  meta, state,
  get ready() { return state.ready; },
  get idle() { return state.inFlight === 0 && !state.pending; },
  // the shown frame is the exact evaluation of the latest request (the gate's fits included)
  get settled() { return state.inFlight === 0 && !state.pending && state.exact && state.shownId === state.requestId; },
  fps,
  setFrame,
  // the positions shown for the current frame (final layer), as a plain array
  positions: () => Array.from(final),
  // where handle h is drawn, in CSS pixels of the page
  handleScreen(h) {
    const p = markers[h].position.clone().project(camera);
    const r = renderer.domElement.getBoundingClientRect();
    return { x: r.left + (p.x + 1) / 2 * r.width, y: r.top + (1 - p.y) / 2 * r.height };
  },
  // what a drag of handle h by offset (rig units) shows, without committing it (scripts, benches)
  preview(h, offset) { state.preview = offset ? { handle: h, offset, ...easing() } : null; setInteractive(!!offset); requestEvaluation(); },
  handlePosition: (h) => Array.from(handles.slice(3 * h, 3 * h + 3)),
};
setFrame(0);
showStatus();
