// The sketch as it goes to the controller (POST /v1/sessions/{id}/controls' `sketch`): the stroke thinned, and in
// 3D an arrow's depth carried as its width.

// a 3D arrow's depth travels as its width (control/sketch.py: wider = nearer the viewer, +z)
const WIDTH_MIN = 0.006, WIDTH_MAX = 0.024, WIDTH_FLAT = 0.015, DEPTH_FLAT = 0.005;

// Ramer–Douglas–Peucker (3D distances), then uniform thinning, to at most `max` points.
export function simplify(pts, max) {
  if (pts.length <= 2) return pts;
  const keep = new Uint8Array(pts.length); keep[0] = keep[pts.length - 1] = 1;
  const eps = 1e-3, stack = [[0, pts.length - 1]];
  while (stack.length) {
    const [a, b] = stack.pop();
    const A = pts[a], B = pts[b], d = [B[0] - A[0], B[1] - A[1], B[2] - A[2]], l2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2] || 1e-24;
    let best = -1, bi = -1;
    for (let i = a + 1; i < b; i++) {
      const q = [pts[i][0] - A[0], pts[i][1] - A[1], pts[i][2] - A[2]];
      const t = (q[0] * d[0] + q[1] * d[1] + q[2] * d[2]) / l2;
      const e = Math.hypot(q[0] - t * d[0], q[1] - t * d[1], q[2] - t * d[2]);
      if (e > best) { best = e; bi = i; }
    }
    if (best > eps) { keep[bi] = 1; stack.push([a, bi], [bi, b]); }
  }
  let out = pts.filter((_, i) => keep[i]);
  if (out.length > max) { const step = (out.length - 1) / (max - 1); out = Array.from({ length: max }, (_, i) => out[Math.round(i * step)]); }
  return out;
}

// The sketch as the controller reads it: x–y points (the front view); in 3D (dim 3) an arrow's depth z as its
// width, the stroke's depth range spanning WIDTH_MIN … WIDTH_MAX, wider = nearer (+z), constant when flat.
export function sketchBody(kind, pts, dim) {
  const clamp = (v) => Math.max(-0.99, Math.min(1.99, v));
  const sketch = { kind, points: pts.map((p) => [clamp(p[0]), clamp(p[1])]) };
  if (dim === 3 && kind === "arrow") {
    const zs = pts.map((p) => p[2]), lo = Math.min(...zs), hi = Math.max(...zs);
    sketch.width = zs.map((z) => (hi - lo < DEPTH_FLAT ? WIDTH_FLAT : WIDTH_MIN + ((z - lo) / (hi - lo)) * (WIDTH_MAX - WIDTH_MIN)));
  }
  return sketch;
}
