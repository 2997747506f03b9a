// The editor's second thread: it turns what the server sends into a frame ready to draw — the
// per-vertex evaluation (browser mode), or the streamed positions and a drag's patch (server
// mode) — plus the normals and, lit by them (shading.js), the colours the renderer draws, so the
// page's own thread only uploads and draws, and a frame is evaluated here while the last one is drawn.
//
// A frame travels as one set of typed arrays (final, large, normal, detailN, color, front, back)
// transferred, not copied, both ways: the page sends a set back once a newer one is on screen.
import { unpackBundle, BrowserEvaluator, vertexNormals } from '/static/evaluate.js';
import { lightVertices } from '/static/shading.js';

let evaluator = null, triangles = null, V = 0, H = 0, light = null, skin = null;
let patch = null;  // server mode: the current drag's base, B's column and patch vertices
const pool = [];

function takeSet() {
  const s = pool.pop();
  if (s) return s;
  return { final: new Float32Array(3 * V), large: new Float32Array(3 * V), normal: new Float32Array(3 * V),
           detailN: new Float32Array(V), color: new Float32Array(3 * V), front: new Uint8Array(4 * V),
           back: new Uint8Array(4 * V) };
}

// the details along the large scale's normal, blue in, white none, red out; scaled by the 95th
// percentile over the vertices (a few large details, a sparse neck, would wash out the wrinkles)
function detailColours(set) {
  const sorted = Float32Array.from(set.detailN, Math.abs).sort();
  const top = Math.max(sorted[Math.floor(0.95 * (V - 1))], 1e-12);
  const c = set.color;
  for (let v = 0; v < V; v++) {
    const s = Math.max(-1, Math.min(1, set.detailN[v] / top));
    c[3 * v] = s > 0 ? 1 : 1 + s; c[3 * v + 1] = 1 - Math.abs(s); c[3 * v + 2] = s < 0 ? 1 : 1 - s;
  }
}

// the details along the normal from streamed final and large positions (server mode)
function detailsFromPositions(set) {
  vertexNormals(triangles, set.large, set.normal, V);
  const { final, large, normal, detailN } = set;
  for (let v = 0; v < V; v++) {
    detailN[v] = (final[3 * v] - large[3 * v]) * normal[3 * v] + (final[3 * v + 1] - large[3 * v + 1]) * normal[3 * v + 1] +
      (final[3 * v + 2] - large[3 * v + 2]) * normal[3 * v + 2];
  }
}

// base + column × offset in float32 (numpy's order: the product rounded, then the sum)
function shifted(out, base, column, offset) {
  const o0 = Math.fround(offset[0]), o1 = Math.fround(offset[1]), o2 = Math.fround(offset[2]);
  for (let v = 0; v < V; v++) {
    const b = column[v];
    out[3 * v] = base[3 * v] + Math.fround(b * o0);
    out[3 * v + 1] = base[3 * v + 1] + Math.fround(b * o1);
    out[3 * v + 2] = base[3 * v + 2] + Math.fround(b * o2);
  }
}

// fill a set from a message; false when the message cannot be drawn (a step of a gone patch)
function fill(m, set) {
  if (m.op === 'pose') {
    evaluator.evaluate(m.handles, m.features, m.gate, set.final, set.large, set.detailN, m.drag);
    return true;
  }
  if (m.op === 'positions') {
    set.final.set(m.final);
    if (m.large) set.large.set(m.large);
    return true;
  }
  if (m.op === 'step') {
    if (!patch || patch.serial !== m.serial) return false;
    shifted(set.final, patch.final, patch.column, m.offset);
    const idx = patch.vertices, values = m.values;
    for (let i = 0; i < idx.length; i++) {
      const v = 3 * idx[i];
      set.final[v] = values[3 * i]; set.final[v + 1] = values[3 * i + 1]; set.final[v + 2] = values[3 * i + 2];
    }
    if (m.layer !== 'final') shifted(set.large, patch.large, patch.column, m.offset);
    return true;
  }
  throw new Error(`unknown op ${m.op}`);
}

onmessage = (event) => {
  const m = event.data;
  if (m.op === 'init') {
    const bundle = unpackBundle(m.buffer);
    triangles = bundle.arrays.triangles;
    V = bundle.meta.vertices;
    H = bundle.meta.handles;
    light = m.light;
    skin = m.skin;
    if (bundle.meta.mode === 'browser') evaluator = new BrowserEvaluator(bundle);
    postMessage({ op: 'ready' });
    return;
  }
  if (m.op === 'recycle') { pool.push(m.set); return; }
  if (m.op === 'patch') { patch = m; return; }
  const t0 = performance.now();
  const set = takeSet();
  if (!fill(m, set)) { pool.push(set); postMessage({ op: 'skipped', id: m.id }); return; }
  const t1 = performance.now();
  const layered = m.layer !== 'final' && !(m.op === 'positions' && !m.large);
  if (m.layer === 'details' && m.op !== 'pose' && layered) detailsFromPositions(set);
  if (m.layer === 'details') detailColours(set);
  vertexNormals(triangles, m.layer === 'large' && layered ? set.large : set.final, set.normal, V);
  const t2 = performance.now();
  // the error layer's colours need the truth, which the page holds: it lights them itself
  if (m.layer !== 'error') lightVertices(set.normal, m.layer === 'details' ? set.color : skin, light, set.front, set.back, V);
  const t3 = performance.now();
  const { final, large, normal, detailN, color, front, back } = set;
  postMessage({ op: 'frame', id: m.id, row: m.row, exact: m.exact, layer: m.layer, handles: m.handles, layered,
                set, timings: { evaluate: t1 - t0, normals: t2 - t1, light: t3 - t2 } },
              [final.buffer, large.buffer, normal.buffer, detailN.buffer, color.buffer, front.buffer, back.buffer]);
};
