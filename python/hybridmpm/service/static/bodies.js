// Rigid bodies on the page (docs/bodies.md "The page"): crates, balls, capsules and convex meshes that float in
// the fluid, drawn at each frame's pose. Their shapes and sizes come from the session's description (`bodies`:
// {shape, half_extents | radius | radius + half_height | vertices + faces, center, rotation, ...}, refreshed on the
// stream's `bodies` event); their poses from the binary frame (flag bit3: a u32 count after the positions, then
// float32 [B, dim + dim²] per body: centre, rotation row-major, columns the body's axes). A frame whose body count
// is not the description's (a body added or removed since it was stepped, a paused session) draws the description's
// poses. Drawn in wood brown (render.gif's BODY_FILL): shaded solids in 3D, flat shapes in 2D.

export const FLAG_BODIES = 8;
export const BODY_FILL = "#b07a3c";
const HEADER_BYTES = 32;
const rgb = (hex) => [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16) / 255);

// The bodies' block of binary frame `buf` ({count, poses: Float32Array [count·(dim + dim²)]}), or null when the frame
// carries none or its length is not what its count says (never throws: a damaged frame draws no poses)
export function readBodies(buf, n, dim) {
  const dv = new DataView(buf);
  if (!(dv.getUint8(7) & FLAG_BODIES)) return null;
  const at = HEADER_BYTES + 4 * n * dim, per = dim + dim * dim;
  if (buf.byteLength < at + 4) return null;
  const count = dv.getUint32(at, true);
  if (buf.byteLength !== at + 4 + 4 * count * per) return null;
  return { count, poses: new Float32Array(buf, at + 4, count * per) };
}

// A body's rotation as 3 rows of 3 (2D: about z) from a D×D matrix (row-major list, or nested rows), or from
// the body as given (2D `angle_deg`; a missing rotation: none)
function rows3(R, dim) {
  const out = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
  if (!R) return out;
  for (let i = 0; i < dim; i++) for (let j = 0; j < dim; j++) out[i][j] = Array.isArray(R[0]) ? R[i][j] : R[i * dim + j];
  return out;
}
function givenRotation(b, dim) {
  if (b.rotation) return rows3(b.rotation, dim);
  const a = ((b.angle_deg || 0) * Math.PI) / 180;
  return dim === 2 ? [[Math.cos(a), -Math.sin(a), 0], [Math.sin(a), Math.cos(a), 0], [0, 0, 1]] : rows3(null, 3);
}
// column-major model matrix: world = centre + R · (scale ⊙ local)
function model(c, s, R) {
  const m = new Float32Array(16);
  for (let col = 0; col < 3; col++) for (let row = 0; row < 3; row++) m[col * 4 + row] = R[row][col] * s[col];
  m[12] = c[0]; m[13] = c[1]; m[14] = c[2] || 0; m[15] = 1;
  return m;
}

// ------------------------------------------------------------------ meshes (position, normal; triangles)
function capsule3(r, hh, lat = 8, lon = 24) { // about the local y axis: a cylinder of half-length hh, hemispherical ends
  const out = [], rows = [];
  for (let i = 0; i <= lat; i++) rows.push([(Math.PI / 2) * (i / lat), hh]);
  for (let i = 0; i <= lat; i++) rows.push([Math.PI / 2 + (Math.PI / 2) * (i / lat), -hh]);
  const pt = (row, j) => {
    const [th, off] = rows[row], ph = (2 * Math.PI * j) / lon;
    const n = [Math.sin(th) * Math.cos(ph), Math.cos(th), -Math.sin(th) * Math.sin(ph)];
    return [[r * n[0], r * n[1] + off, r * n[2]], n];
  };
  for (let i = 0; i + 1 < rows.length; i++) for (let j = 0; j < lon; j++) {
    const a = pt(i, j), b = pt(i + 1, j), c = pt(i + 1, j + 1), d = pt(i, j + 1);
    for (const [p, n] of [a, b, c, a, c, d]) out.push(...p, ...n);
  }
  return new Float32Array(out);
}
function outline2(pts) { // a convex outline [[x, y], ...] as a fan of triangles facing +z
  const out = [];
  for (let i = 0; i < pts.length; i++) {
    const a = pts[i], b = pts[(i + 1) % pts.length];
    out.push(0, 0, 0, 0, 0, 1, a[0], a[1], 0, 0, 0, 1, b[0], b[1], 0, 0, 0, 1);
  }
  return new Float32Array(out);
}
function stadium(r, hh, seg = 16) { // a 2D capsule's outline about the local y axis
  const pts = [];
  for (let k = 0; k <= seg; k++) { const a = (Math.PI * k) / seg; pts.push([r * Math.cos(a), hh + r * Math.sin(a)]); }
  for (let k = 0; k <= seg; k++) { const a = Math.PI + (Math.PI * k) / seg; pts.push([r * Math.cos(a), -hh + r * Math.sin(a)]); }
  return pts;
}
function triangles(vertices, faces) { // a mesh's faces, flat-shaded, each normal turned away from the vertices' mean
  const ok = Array.isArray(vertices) && Array.isArray(faces);
  const V = ok ? vertices.filter((v) => Array.isArray(v) && v.length === 3 && v.every(Number.isFinite)) : [];
  if (!ok || V.length !== vertices.length) return new Float32Array(0);
  const mid = [0, 1, 2].map((d) => V.reduce((s, v) => s + v[d], 0) / Math.max(1, V.length)), out = [];
  for (const f of faces) {
    if (!Array.isArray(f) || f.length !== 3 || !f.every((i) => Number.isInteger(i) && i >= 0 && i < V.length)) continue;
    const [a, b, c] = f.map((i) => V[i]);
    const u = [0, 1, 2].map((d) => b[d] - a[d]), v = [0, 1, 2].map((d) => c[d] - a[d]);
    let n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
    const l = Math.hypot(...n) || 1, away = [0, 1, 2].reduce((s, d) => s + n[d] * (a[d] - mid[d]), 0) < 0 ? -1 : 1;
    n = n.map((x) => (away * x) / l);
    for (const p of [a, b, c]) out.push(...p, ...n);
  }
  return new Float32Array(out);
}

// The mesh, scale and silhouette points of body `b` in a session of `dim` dimensions: {mesh: name | [name, make()],
// scale, points (local [x, y, z] whose x–y hull is its outline in the Canvas2D view), radius (a ball: drawn round)};
// null for a shape this page does not know
function geometry(b, dim) {
  const r = Number(b.radius), e = b.half_extents;
  if (b.shape === "box" && Array.isArray(e)) {
    const s = [e[0], e[1], dim === 3 ? e[2] : 0], points = [];
    for (let k = 0; k < 8; k++) points.push([0, 1, 2].map((d) => ((k >> d) & 1 ? s[d] : -s[d])));
    return { mesh: dim === 3 ? "cube" : "square", scale: [s[0], s[1], dim === 3 ? s[2] : 1], points };
  }
  if ((b.shape === "sphere" || b.shape === "circle") && r > 0) return { mesh: dim === 3 ? "sphere" : "disc", scale: [r, r, r], radius: r };
  if (b.shape === "capsule" && r > 0 && Number(b.half_height) >= 0) {
    const hh = Number(b.half_height), key = `body:capsule${dim}:${r}:${hh}`, ring = stadium(r, hh);
    const points = dim === 2 ? ring.map(([x, y]) => [x, y, 0]) : [];
    if (dim === 3) for (let k = 0; k < 48; k++) for (const y of [-hh, hh]) { // the end spheres' great circles
      const a = (2 * Math.PI * (k % 16)) / 16, [u, v] = [r * Math.cos(a), r * Math.sin(a)];
      points.push(k < 16 ? [u, y + v, 0] : k < 32 ? [0, y + v, u] : [u, y, v]);
    }
    return { mesh: [key, () => (dim === 3 ? capsule3(r, hh) : outline2(ring))], scale: [1, 1, 1], points };
  }
  if (b.shape === "mesh" && dim === 3 && Array.isArray(b.vertices) && Array.isArray(b.faces)) {
    if (!b.__key) Object.defineProperty(b, "__key", { value: `body:mesh:${JSON.stringify([b.vertices, b.faces])}` });
    const points = b.vertices.filter((v) => Array.isArray(v) && v.length === 3 && v.every(Number.isFinite));
    return { mesh: [b.__key, () => triangles(b.vertices, b.faces)], scale: [1, 1, 1], points };
  }
  return null;
}

// the convex hull of 2D points (Andrew's monotone chain), counter-clockwise
function hull(pts) {
  const p = pts.slice().sort((a, b) => a[0] - b[0] || a[1] - b[1]);
  if (p.length < 3) return p;
  const cross = (o, a, b) => (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]);
  const half = (list) => {
    const h = [];
    for (const q of list) { while (h.length >= 2 && cross(h[h.length - 2], h[h.length - 1], q) <= 0) h.pop(); h.push(q); }
    h.pop();
    return h;
  };
  return half(p).concat(half(p.reverse()));
}

// The bodies of the session shown, drawn by either renderer (render.js calls draw / drawCanvas). `drawn`: what the
// last draw drew ([{index, shape, center, rotation (rows), from: "frame" | "description", frame}]; the page's hook).
export class BodyLayer {
  constructor() { this.drawn = []; this.meshes = new Map(); }

  // [{index, shape, geometry, center [3], R (3 rows)}] of session `s` at frame `f` (its poses when its count matches)
  poses(s, f) {
    const list = (s && Array.isArray(s.bodies)) ? s.bodies : [], dim = s ? s.dim : 2, per = dim + dim * dim;
    const fromFrame = !!(f && f.bodies && f.bodies.count === list.length);
    const out = [];
    list.forEach((b, i) => {
      const g = b && geometry(b, dim);
      if (!g) return;
      let c, R;
      if (fromFrame) {
        const p = f.bodies.poses.subarray(i * per, (i + 1) * per);
        c = [p[0], p[1], dim === 3 ? p[2] : 0]; R = rows3(p.subarray(dim), dim);
      } else {
        if (!Array.isArray(b.center)) return;
        c = [b.center[0], b.center[1], dim === 3 ? b.center[2] : 0]; R = givenRotation(b, dim);
      }
      out.push({ index: i, shape: b.shape, g, c, R, from: fromFrame ? "frame" : "description" });
    });
    this.drawn = out.map((o) => ({ index: o.index, shape: o.shape, center: o.c.slice(0, dim), rotation: o.R.slice(0, dim).map((r) => r.slice(0, dim)),
      from: o.from, frame: f ? f.frame : -1 }));
    return out;
  }

  // WebGL2: shaded solids (3D; 2D flat, in front of the particles); `view` is the GLRenderer (its solid() and meshes)
  draw(view, M, dim) {
    const gl = view.gl, col = rgb(BODY_FILL);
    gl.disable(gl.CULL_FACE); // a mesh's winding is the sender's: the depth test alone hides the far side
    for (const o of this.poses(view.session, view.frame)) {
      let name = o.g.mesh;
      if (Array.isArray(name)) {
        const [key, make] = name;
        if (!view.meshes[key]) view.addMesh(key, make());
        name = key;
      }
      if (!view.meshes[name].count) continue;
      const c = dim === 3 ? o.c : [o.c[0], o.c[1], 0.5];
      view.solid(name, M, model(c, o.g.scale, o.R), col);
    }
  }

  // Canvas2D (the x–y view): filled silhouettes over the particles; `px(x, y)` maps the domain to CSS pixels
  drawCanvas(ctx, session, frame, px) {
    ctx.fillStyle = BODY_FILL; ctx.strokeStyle = "#6d4a22"; ctx.lineWidth = 1.5;
    for (const o of this.poses(session, frame)) {
      ctx.beginPath();
      if (o.g.radius) {
        const [x, y] = px(o.c[0], o.c[1]), [x1] = px(o.c[0] + o.g.radius, o.c[1]);
        ctx.arc(x, y, Math.abs(x1 - x), 0, 2 * Math.PI);
      } else {
        const R = o.R, world = o.g.points.map((q) => [0, 1].map((d) => o.c[d] + R[d][0] * q[0] + R[d][1] * q[1] + R[d][2] * q[2]));
        hull(world).forEach(([x, y], k) => { const q = px(x, y); if (k) ctx.lineTo(q[0], q[1]); else ctx.moveTo(q[0], q[1]); });
        ctx.closePath();
      }
      ctx.fill(); ctx.stroke();
    }
  }
}
