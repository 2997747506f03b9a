// Drawing only what a drag changes. A software rasteriser (a machine without a GPU) pays about a
// microsecond per triangle per rasteriser thread however few pixels the triangle covers, and a
// drag moves a region of the face: the rest moves too (the large scale is exact everywhere) but by
// far less than a pixel there. So while a handle is dragged the canvas keeps its last whole
// drawing (preserveDrawingBuffer) and each frame redraws, clipped to a rectangle, only the
// triangles that reach it. The rectangle holds the triangles of every vertex that moved by more
// than REDRAW_PIXELS on screen, or whose lit colour changed by more than a byte, since the last
// whole drawing (where they are drawn now and where they were then), and it grows, never
// shrinks, until the next whole drawing: no stale pixel is left where a vertex once moved, and
// outside it the picture is that whole drawing, within REDRAW_PIXELS and a byte of drawing
// everything. A camera move, a resize, another frame or layer, or the end of the drag draws
// everything again.

export const REDRAW_PIXELS = 0.1;

// screen positions (V·2, drawing-buffer pixels, y down) of positions (V·3) through the
// column-major 4×4 view-projection matrix m, onto a width × height drawing buffer
export function projectVertices(positions, m, width, height, out, V) {
  for (let v = 0; v < V; v++) {
    const x = positions[3 * v], y = positions[3 * v + 1], z = positions[3 * v + 2];
    const w = m[3] * x + m[7] * y + m[11] * z + m[15];
    out[2 * v] = (0.5 + 0.5 * (m[0] * x + m[4] * y + m[8] * z + m[12]) / w) * width;
    out[2 * v + 1] = (0.5 - 0.5 * (m[1] * x + m[5] * y + m[9] * z + m[13]) / w) * height;
  }
  return out;
}

// The vertices whose screen position moved by more than `pixels` or whose colours (RGBA bytes,
// front and back) changed by more than a byte between `then` and `now` ({screen, front, back});
// flags (V) set to 1 for them; returns their number.
export function changedVertices(now, then, pixels, flags, V) {
  let changed = 0;
  const limit = pixels * pixels;
  for (let v = 0; v < V; v++) {
    const dx = now.screen[2 * v] - then.screen[2 * v], dy = now.screen[2 * v + 1] - then.screen[2 * v + 1];
    let moved = dx * dx + dy * dy > limit;
    for (let c = 4 * v; !moved && c < 4 * v + 3; c++) {
      moved = Math.abs(now.front[c] - then.front[c]) > 1 || Math.abs(now.back[c] - then.back[c]) > 1;
    }
    flags[v] = moved ? 1 : 0;
    changed += flags[v];
  }
  return changed;
}

// rect ({x0, y0, x1, y1}, pixels) grown over the triangles (tri: T·3) with a flagged corner, at
// each set of screen positions given (where they are drawn now, and were drawn then)
export function growOverTriangles(tri, flags, screens, rect) {
  for (let f = 0; f < tri.length; f += 3) {
    if (!(flags[tri[f]] | flags[tri[f + 1]] | flags[tri[f + 2]])) continue;
    for (const s of screens) {
      for (let k = 0; k < 3; k++) {
        const x = s[2 * tri[f + k]], y = s[2 * tri[f + k] + 1];
        if (x < rect.x0) rect.x0 = x;
        if (x > rect.x1) rect.x1 = x;
        if (y < rect.y0) rect.y0 = y;
        if (y > rect.y1) rect.y1 = y;
      }
    }
  }
  return rect;
}

// The triangles (tri: T·3) of which any part may fall in rect, at screen positions `screen`
// (a triangle lies within the bounding box of its corners), written to out; returns their count.
export function trianglesIn(tri, screen, rect, out) {
  let n = 0;
  for (let f = 0; f < tri.length; f += 3) {
    const a = 2 * tri[f], b = 2 * tri[f + 1], c = 2 * tri[f + 2];
    const xa = screen[a], xb = screen[b], xc = screen[c], ya = screen[a + 1], yb = screen[b + 1], yc = screen[c + 1];
    if (Math.max(xa, xb, xc) < rect.x0 || Math.min(xa, xb, xc) > rect.x1 ||
        Math.max(ya, yb, yc) < rect.y0 || Math.min(ya, yb, yc) > rect.y1) continue;
    out[n++] = tri[f]; out[n++] = tri[f + 1]; out[n++] = tri[f + 2];
  }
  return n / 3;
}
