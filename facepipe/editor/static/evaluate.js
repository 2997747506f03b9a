// The per-vertex evaluation of a facepipe model in the browser, in double precision over the
// model's float32 arrays: the same arithmetic as facepipe.pipeline.replay.NumpyEvaluator
// (large = rest + B·u, local frames of the large scale, WPSD/PSD details, the gate's
// per-site confidence spread to the vertices by α, final = large + [t b n]·d).
// The pose terms (handles with the edits applied, strain features, the gate's site confidence)
// come from the server, computed by the replay's own code.

export function unpackBundle(buffer) {
  const headerLength = new DataView(buffer).getUint32(0, true);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, headerLength)));
  const base = 4 + headerLength;
  const kinds = { '<f4': Float32Array, '<f8': Float64Array, '<u4': Uint32Array, '<i4': Int32Array };
  const arrays = {};
  for (const [name, entry] of Object.entries(header.arrays)) {
    const Kind = kinds[entry.dtype];
    if (!Kind) throw new Error(`unsupported dtype ${entry.dtype} of ${name}`);
    const count = entry.shape.reduce((a, b) => a * b, 1);
    arrays[name] = new Kind(buffer, base + entry.offset, count);
  }
  return { meta: header.meta, arrays, shapes: Object.fromEntries(Object.entries(header.arrays).map(([k, e]) => [k, e.shape])) };
}

// A drag step re-evaluates only what its change reaches, when few handles moved (a drag moves
// one): the large scale by B's columns of the moved handles (u = u₀ + B[:, h]·Δu_h, exact up to
// rounding), the WPSD details of the vertices whose edge weights reach a changed strain feature,
// and the confidence only when the gate's changed; frames and the final surface are redone
// everywhere (the large scale moves everywhere). A frame evaluated whole is the replay's arithmetic.
const INCREMENTAL_SHARE = 0.25;  // more changed handles or features than this share: evaluate whole

export class BrowserEvaluator {
  constructor(bundle) {
    const a = bundle.arrays;
    this.meta = bundle.meta;
    this.rest = a.rest;
    this.tri = a.triangles;
    this.hv = a.handle_vertices;
    this.B = a.B;
    this.nb = a.frame_neighbors;
    this.basis = a.basis_features;
    this.W = a.rbf_weights;
    this.c = a.rbf_const;
    this.ei = a.edge_index;
    this.ew = a.edge_weight;
    this.V = this.rest.length / 3;
    this.H = this.hv.length;
    this.F = bundle.meta.features;
    this.P = bundle.shapes.basis_features[0];
    this.K = bundle.shapes.edge_index[1];
    this.method = bundle.meta.method;
    this.u = new Float64Array(this.H * 3);
    this.large = new Float64Array(this.V * 3);
    this.normal = new Float64Array(this.V * 3);
    this.sq = new Float64Array(this.F * this.P);
    this.phi = new Float64Array(this.P);
    this.details = new Float64Array(this.V * 3);  // [t b n] coefficients before the gate's confidence
    this.conf = new Float64Array(this.V).fill(1);
    this.features = new Float64Array(this.F);
    this.gate = null;
    this.valid = false;  // the caches above hold the last evaluation
    this.edgeVertices = null;  // per feature edge, the vertices its weights reach (built on first use)
  }

  // handles: (H·3) head-space positions; features: (F); gate: (F) site confidence or null.
  // Writes final and large (V·3 float32) and, if given, detailN (V): the details along the normal.
  // incremental: a drag step may update the last evaluation (see above) rather than start afresh.
  evaluate(handles, features, gate, final, largeOut, detailN, incremental = false) {
    const { V, H, rest, B, u, large } = this;
    const changed = [];
    for (let h = 0; h < H; h++) {
      const v = this.hv[h];
      for (let x = 0; x < 3; x++) {
        if (handles[3 * h + x] - rest[3 * v + x] !== u[3 * h + x]) { changed.push(h); break; }
      }
    }
    const whole = !incremental || !this.valid || changed.length > INCREMENTAL_SHARE * H;
    for (const h of (whole ? [] : changed)) {  // the moved handles' columns of B, added to the last large scale
      const v = this.hv[h];
      for (let x = 0; x < 3; x++) {
        const du = handles[3 * h + x] - rest[3 * v + x] - u[3 * h + x];
        if (du !== 0) for (let w = 0; w < V; w++) large[3 * w + x] += B[w * H + h] * du;
      }
    }
    for (let h = 0; h < H; h++) {
      const v = this.hv[h];
      for (let x = 0; x < 3; x++) u[3 * h + x] = handles[3 * h + x] - rest[3 * v + x];
    }
    if (whole) this.largeScale();
    if (this.method === 'none') {
      for (let i = 0; i < 3 * V; i++) { final[i] = large[i]; largeOut[i] = large[i]; }
      if (detailN) detailN.fill(0);
      this.valid = true;
      return;
    }
    this.vertexNormals();
    this.updateDetails(features, whole);
    this.updateConfidence(gate, whole);
    this.valid = true;
    this.finalSurface(final, largeOut, detailN);
  }

  // u = B·u_H over every vertex
  largeScale() {
    const { V, H, rest, B, u, large } = this;
    for (let v = 0; v < V; v++) {
      let sx = 0, sy = 0, sz = 0;
      const row = v * H;
      for (let h = 0; h < H; h++) {
        const b = B[row + h];
        sx += b * u[3 * h]; sy += b * u[3 * h + 1]; sz += b * u[3 * h + 2];
      }
      large[3 * v] = sx + rest[3 * v]; large[3 * v + 1] = sy + rest[3 * v + 1]; large[3 * v + 2] = sz + rest[3 * v + 2];
    }
  }

  // the WPSD/PSD detail coefficients: of every vertex, or of those reached by a changed feature
  updateDetails(features, whole) {
    const { V, P, F, sq, basis } = this;
    const changed = [];
    for (let f = 0; f < F; f++) if (features[f] !== this.features[f]) changed.push(f);
    const wpsd = this.method === 'wpsd';
    if (!whole && (!wpsd || changed.length > INCREMENTAL_SHARE * F)) whole = true;
    for (const f of (whole ? Array.from({ length: F }, (_, i) => i) : changed)) {
      for (let p = 0; p < P; p++) { const d = features[f] - basis[p * F + f]; sq[f * P + p] = d * d; }
      this.features[f] = features[f];
    }
    if (!wpsd) {  // PSD: one global distance per basis pose
      const { phi } = this;
      for (let p = 0; p < P; p++) { let s = 0; for (let f = 0; f < F; f++) s += sq[f * P + p]; phi[p] = Math.sqrt(s); }
    }
    if (whole) {
      for (let v = 0; v < V; v++) this.vertexDetails(v, wpsd);
      return;
    }
    if (!changed.length) return;
    const reached = this.reachedBy(changed);
    for (const v of reached) this.vertexDetails(v, wpsd);
  }

  // vertex v's detail coefficients before the gate
  vertexDetails(v, wpsd) {
    const { P, K, sq, phi, W, c, ei, ew, details } = this;
    if (wpsd) {
      for (let p = 0; p < P; p++) phi[p] = 0;
      for (let k = 0; k < K; k++) {
        const w = ew[v * K + k], e = ei[v * K + k] * P;
        if (w === 0) continue;
        for (let p = 0; p < P; p++) phi[p] += w * sq[e + p];
      }
      for (let p = 0; p < P; p++) phi[p] = Math.sqrt(Math.max(phi[p], 0));
    }
    let d0 = c[3 * v], d1 = c[3 * v + 1], d2 = c[3 * v + 2];
    const wrow = v * P * 3;
    for (let p = 0; p < P; p++) {
      d0 += phi[p] * W[wrow + 3 * p]; d1 += phi[p] * W[wrow + 3 * p + 1]; d2 += phi[p] * W[wrow + 3 * p + 2];
    }
    details[3 * v] = d0; details[3 * v + 1] = d1; details[3 * v + 2] = d2;
  }

  // the vertices whose edge weights reach any of these feature edges
  reachedBy(edges) {
    const { V, K, F, ei, ew } = this;
    if (!this.edgeVertices) {
      this.edgeVertices = Array.from({ length: F }, () => []);
      for (let v = 0; v < V; v++) {
        for (let k = 0; k < K; k++) if (ew[v * K + k] !== 0) this.edgeVertices[ei[v * K + k]].push(v);
      }
    }
    const reached = new Set();
    for (const f of edges) for (const v of this.edgeVertices[f]) reached.add(v);
    return reached;
  }

  // the gate's per-site confidence spread to the vertices by α (1 without a gate), when it changed
  updateConfidence(gate, whole) {
    const { V, K, F, ei, ew, conf } = this;
    let same = !whole && (gate === null) === (this.gate === null);
    if (same && gate) for (let f = 0; f < F && same; f++) same = gate[f] === this.gate[f];
    if (same) return;
    this.gate = gate ? Float64Array.from(gate) : null;
    for (let v = 0; v < V; v++) {
      if (!gate) { conf[v] = 1; continue; }
      let s = 0;
      for (let k = 0; k < K; k++) s += ew[v * K + k] * gate[ei[v * K + k]];
      conf[v] = s;
    }
  }

  // final = large + [t b n]·(details × confidence), the local frames of the large scale
  // (tangent_frames.local_frames)
  finalSurface(final, largeOut, detailN) {
    const { V, large, normal, nb, details, conf } = this;
    const gated = this.gate !== null;
    for (let v = 0; v < V; v++) {
      let d0 = details[3 * v], d1 = details[3 * v + 1], d2 = details[3 * v + 2];
      if (gated) { const s = conf[v]; d0 *= s; d1 *= s; d2 *= s; }
      const nx = normal[3 * v], ny = normal[3 * v + 1], nz = normal[3 * v + 2];
      const j = nb[v];
      const ex = large[3 * j] - large[3 * v], ey = large[3 * j + 1] - large[3 * v + 1], ez = large[3 * j + 2] - large[3 * v + 2];
      const en = ex * nx + ey * ny + ez * nz;
      let tx = ex - en * nx, ty = ey - en * ny, tz = ez - en * nz;
      // lengths as numpy's norm forms them (√ of the summed squares; Math.hypot is far slower)
      const tl = Math.sqrt(tx * tx + ty * ty + tz * tz), el = Math.sqrt(ex * ex + ey * ey + ez * ez);
      if (!(tl > 1e-6 * Math.max(el, 1e-30))) {
        // n × (1, 0, 0), or n × (0, 1, 0) where the normal is along x
        tx = 0; ty = nz; tz = -ny;
        if (Math.sqrt(nz * nz + ny * ny) < 1e-6) { tx = -nz; ty = 0; tz = nx; }
      }
      const tn = Math.sqrt(tx * tx + ty * ty + tz * tz);
      if (tn > 1e-30) { tx /= tn; ty /= tn; tz /= tn; } else { tx = 1; ty = 0; tz = 0; }
      const bx = ny * tz - nz * ty, by = nz * tx - nx * tz, bz = nx * ty - ny * tx;
      const lx = large[3 * v], ly = large[3 * v + 1], lz = large[3 * v + 2];
      final[3 * v] = lx + tx * d0 + bx * d1 + nx * d2;
      final[3 * v + 1] = ly + ty * d0 + by * d1 + ny * d2;
      final[3 * v + 2] = lz + tz * d0 + bz * d1 + nz * d2;
      largeOut[3 * v] = lx; largeOut[3 * v + 1] = ly; largeOut[3 * v + 2] = lz;
      if (detailN) detailN[v] = d2;
    }
  }

  // area-weighted vertex normals of the large scale, unit length ((0, 0, 1) where undefined)
  vertexNormals() { vertexNormals(this.tri, this.large, this.normal, this.V); }
}

// Strain features (|p_a − p_b| − l) / l of handles (H·3) over feature edges (F·2) with rest
// lengths l (F) into out (F): facepipe.core.strain.strain_features, in the same order of operations.
export function strainFeatures(handles, edges, restLengths, out) {
  for (let f = 0; f < restLengths.length; f++) {
    const a = 3 * edges[2 * f], b = 3 * edges[2 * f + 1];
    const dx = handles[a] - handles[b], dy = handles[a + 1] - handles[b + 1], dz = handles[a + 2] - handles[b + 2];
    out[f] = (Math.sqrt(dx * dx + dy * dy + dz * dz) - restLengths[f]) / restLengths[f];
  }
  return out;
}

// Area-weighted unit vertex normals of positions (V·3) over triangles into normal (V·3; (0, 0, 1)
// where undefined): what three.js's computeVertexNormals draws with, and the replay's frames use.
export function vertexNormals(tri, positions, normal, V) {
  normal.fill(0);
  for (let f = 0; f < tri.length; f += 3) {
    const a = 3 * tri[f], b = 3 * tri[f + 1], c = 3 * tri[f + 2];
    const ux = positions[b] - positions[a], uy = positions[b + 1] - positions[a + 1], uz = positions[b + 2] - positions[a + 2];
    const vx = positions[c] - positions[a], vy = positions[c + 1] - positions[a + 1], vz = positions[c + 2] - positions[a + 2];
    const cx = uy * vz - uz * vy, cy = uz * vx - ux * vz, cz = ux * vy - uy * vx;
    normal[a] += cx; normal[a + 1] += cy; normal[a + 2] += cz;
    normal[b] += cx; normal[b + 1] += cy; normal[b + 2] += cz;
    normal[c] += cx; normal[c + 1] += cy; normal[c + 2] += cz;
  }
  for (let v = 0; v < V; v++) {
    const x = normal[3 * v], y = normal[3 * v + 1], z = normal[3 * v + 2];
    const l = Math.sqrt(x * x + y * y + z * z);
    if (l > 1e-30) { normal[3 * v] = x / l; normal[3 * v + 1] = y / l; normal[3 * v + 2] = z / l; }
    else { normal[3 * v] = 0; normal[3 * v + 1] = 0; normal[3 * v + 2] = 1; }
  }
}
