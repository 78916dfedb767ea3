// The meshes the WebGL2 renderer draws its solids with (the domain's walls, the obstacles, the bodies' boxes and
// balls), and the model matrix that places one.

// ------------------------------------------------------------------ meshes
// a unit cube [-1, 1]³ as triangles with normals; `inward`: wound and lit from inside (a room)
export function cube(inward) {
  const out = [];
  const faces = [[0, 1], [0, -1], [1, 1], [1, -1], [2, 1], [2, -1]];
  for (const [ax, s] of faces) {
    const u = (ax + 1) % 3, v = (ax + 2) % 3;
    const corner = (a, b) => { const p = [0, 0, 0]; p[ax] = s; p[u] = a; p[v] = b; return p; };
    let quad = [corner(-1, -1), corner(1, -1), corner(1, 1), corner(-1, -1), corner(1, 1), corner(-1, 1)];
    if ((s < 0) !== inward) quad = [quad[0], quad[2], quad[1], quad[3], quad[5], quad[4]];
    const n = [0, 0, 0]; n[ax] = inward ? -s : s;
    for (const p of quad) out.push(...p, ...n);
  }
  return new Float32Array(out);
}
export function sphere(lat = 14, lon = 24) {
  const out = [];
  const pt = (i, j) => {
    const th = (Math.PI * i) / lat, ph = (2 * Math.PI * j) / lon;
    return [Math.sin(th) * Math.cos(ph), Math.cos(th), -Math.sin(th) * Math.sin(ph)];
  };
  for (let i = 0; i < lat; i++) for (let j = 0; j < lon; j++) {
    const a = pt(i, j), b = pt(i + 1, j), c = pt(i + 1, j + 1), d = pt(i, j + 1);
    for (const p of [a, b, c, a, c, d]) out.push(...p, ...p);
  }
  return new Float32Array(out);
}
export function disc(seg = 40) {
  const out = [];
  for (let j = 0; j < seg; j++) {
    const a = (2 * Math.PI * j) / seg, b = (2 * Math.PI * (j + 1)) / seg;
    out.push(0, 0, 0, 0, 0, 1, Math.cos(a), Math.sin(a), 0, 0, 0, 1, Math.cos(b), Math.sin(b), 0, 0, 0, 1);
  }
  return new Float32Array(out);
}
export const SQUARE = new Float32Array([-1, -1, 0, 0, 0, 1, 1, -1, 0, 0, 0, 1, 1, 1, 0, 0, 0, 1, -1, -1, 0, 0, 0, 1, 1, 1, 0, 0, 0, 1, -1, 1, 0, 0, 0, 1]);
export const BOX_EDGES = (() => {
  const c = [];
  for (let a = 0; a < 3; a++) for (const s of [-1, 1]) for (const t of [-1, 1]) {
    const p = [0, 0, 0], q = [0, 0, 0], u = (a + 1) % 3, v = (a + 2) % 3;
    p[a] = -1; q[a] = 1; p[u] = q[u] = s; p[v] = q[v] = t;
    c.push(...p, 0, 1, 0, ...q, 0, 1, 0);
  }
  return new Float32Array(c);
})();

// column-major model matrix: world = center + R · (scale ⊙ local); R row-major 3×3
export function model(center, scaleXYZ, R) {
  const r = R || [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
  const m = new Float32Array(16);
  for (let c = 0; c < 3; c++) for (let row = 0; row < 3; row++) m[c * 4 + row] = r[row][c] * scaleXYZ[c];
  m[12] = center[0]; m[13] = center[1]; m[14] = center[2] || 0; m[15] = 1;
  return m;
}
export function rotation(ob, dim) {
  if (ob.rotation) return ob.rotation.map((row) => [...row, 0].slice(0, 3)).concat(dim === 2 ? [[0, 0, 1]] : []).slice(0, 3);
  const a = ((ob.angle_deg || 0) * Math.PI) / 180;
  return [[Math.cos(a), -Math.sin(a), 0], [Math.sin(a), Math.cos(a), 0], [0, 0, 1]];
}
