// Lambert lighting of the face per vertex, in JavaScript: what three.js's MeshLambertMaterial
// draws with a key light and a hemisphere light (colour/π × (key × max(n·l, 0) + the hemisphere's
// mix of ground and sky by n·up), in linear light, then sRGB), evaluated where the normals are
// made (the evaluation worker) rather than in a shader. A software rasteriser (a machine without
// a GPU) pays for every varying and every shader instruction per vertex and per pixel; the
// lighting is independent of the view, so the drawing only has to interpolate two ready colours
// (the front's and the back's: the inside of lips and eyelids shows).
//
// The colours are written as normalised bytes, RGBA, in the output's colour space (sRGB), one
// set for the front faces and one for the back.

// light: { key: [dx, dy, dz] unit towards the key light, keyColour: [r, g, b], up: [x, y, z] unit,
//          sky: [r, g, b], ground: [r, g, b] } in linear light (three.js's working colour space)
// normal: (V·3) unit normals; albedo: (V·3) linear colours, or a constant [r, g, b]
// front, back: Uint8Array (V·4) written
export function lightVertices(normal, albedo, light, front, back, V) {
  const [kx, ky, kz] = light.key, [ux, uy, uz] = light.up;
  const [kr, kg, kb] = light.keyColour, [sr, sg, sb] = light.sky, [gr, gg, gb] = light.ground;
  const stride = albedo.length >= 3 * V ? 3 : 0;  // per vertex, or one colour for all
  for (let v = 0; v < V; v++) {
    const nx = normal[3 * v], ny = normal[3 * v + 1], nz = normal[3 * v + 2];
    const a = stride * v;
    // 1/π: Lambert's BRDF
    const ar = albedo[a] * 0.3183098861837907, ag = albedo[a + 1] * 0.3183098861837907, ab = albedo[a + 2] * 0.3183098861837907;
    const nl = nx * kx + ny * ky + nz * kz, nu = nx * ux + ny * uy + nz * uz;
    // the front (n) and the back (−n): the key light on the side it faces, the hemisphere's
    // ground at t = 0 and sky at 1
    const keyF = nl > 0 ? nl : 0, keyB = nl < 0 ? -nl : 0, tF = 0.5 * nu + 0.5, tB = 0.5 - 0.5 * nu;
    const i = 4 * v;
    front[i] = toByte(ar * (kr * keyF + gr + (sr - gr) * tF));
    front[i + 1] = toByte(ag * (kg * keyF + gg + (sg - gg) * tF));
    front[i + 2] = toByte(ab * (kb * keyF + gb + (sb - gb) * tF));
    front[i + 3] = 255;
    back[i] = toByte(ar * (kr * keyB + gr + (sr - gr) * tB));
    back[i + 1] = toByte(ag * (kg * keyB + gg + (sg - gg) * tB));
    back[i + 2] = toByte(ab * (kb * keyB + gb + (sb - gb) * tB));
    back[i + 3] = 255;
  }
}

// linear light → an sRGB byte (three.js's sRGBTransferOETF, clamped as the framebuffer clamps),
// by a table of 4096 steps of linear light (within a byte of the exact transfer: its slope
// is below 13 where the table is used, the linear toe is computed)
const STEPS = 4096;
const TABLE = new Uint8Array(STEPS + 1);
for (let i = 0; i <= STEPS; i++) {
  const c = i / STEPS;
  const s = c <= 0.0031308 ? 12.92 * c : 1.055 * Math.pow(c, 0.41666) - 0.055;
  TABLE[i] = Math.round(255 * Math.min(Math.max(s, 0), 1));
}
function toByte(c) {
  if (!(c > 0)) return 0;
  if (c >= 1) return 255;
  return c < 0.0031308 ? (3294.6 * c + 0.5) | 0 : TABLE[(c * STEPS + 0.5) | 0];  // 3294.6 = 255 × 12.92
}
