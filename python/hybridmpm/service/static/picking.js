// From the pointer to the world and back, under the matrices a renderer drew with (M: view, proj, viewProj, inv,
// eye): a world point's CSS pixels, the ray through a pixel, where a ray meets a plane or an obstacle.

import { dot, transform4 } from "./mat.js";
import { rotation } from "./meshes.js";

// World point → CSS pixels of an element of size (cssW, cssH) under the matrices M (from draw()); null behind the eye.
export function project(M, p, cssW, cssH) {
  const c = transform4(M.viewProj, [p[0], p[1], p[2] || 0]);
  if (c[3] <= 1e-6) return null;
  return [((c[0] / c[3]) * 0.5 + 0.5) * cssW, (0.5 - (c[1] / c[3]) * 0.5) * cssH, c[3]];
}

// The ray through CSS pixel (x, y): {origin, dir} in world coordinates
export function pixelRay(M, x, y, cssW, cssH) {
  const nx = (x / cssW) * 2 - 1, ny = 1 - (y / cssH) * 2;
  const a = transform4(M.inv, [nx, ny, -1]), b = transform4(M.inv, [nx, ny, 1]);
  const p0 = [a[0] / a[3], a[1] / a[3], a[2] / a[3]], p1 = [b[0] / b[3], b[1] / b[3], b[2] / b[3]];
  const d = [p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]], l = Math.hypot(...d) || 1;
  return { origin: p0, dir: [d[0] / l, d[1] / l, d[2] / l] };
}

// Where the ray meets the plane through `point` with normal `n` (null if parallel or behind)
export function rayPlane(ray, point, n) {
  const den = dot(ray.dir, n);
  if (Math.abs(den) < 1e-9) return null;
  const t = dot([point[0] - ray.origin[0], point[1] - ray.origin[1], point[2] - ray.origin[2]], n) / den;
  if (t < 0) return null;
  return [ray.origin[0] + t * ray.dir[0], ray.origin[1] + t * ray.dir[1], ray.origin[2] + t * ray.dir[2]];
}

// Where the ray first meets an obstacle grown by `slack` metres (a box with its rotation, a sphere): the distance
// along the ray [m], or null (a miss, only behind the origin, or a mesh: never hit). 3D; the ray's dir is a unit vector.
export function rayObstacle(ray, ob, slack = 0) {
  const o = [0, 1, 2].map((d) => ray.origin[d] - (ob.center[d] || 0)), dir = ray.dir;
  if (ob.shape === "sphere") {
    const r = ob.radius + slack, b = dot(o, dir), disc = b * b - (dot(o, o) - r * r);
    if (disc < 0) return null;
    const s = Math.sqrt(disc), t = -b - s >= 0 ? -b - s : -b + s; // from inside: where the ray leaves it
    return t >= 0 ? t : null;
  }
  if (ob.shape !== "box") return null;
  const R = rotation(ob, 3); // columns: the box's axes; the slab test in the box's frame, Rᵀ (p − centre)
  let t0 = 0, t1 = Infinity;
  for (let k = 0; k < 3; k++) {
    const ok = R[0][k] * o[0] + R[1][k] * o[1] + R[2][k] * o[2], dk = R[0][k] * dir[0] + R[1][k] * dir[1] + R[2][k] * dir[2];
    const e = (ob.half_extents[k] || 0) + slack;
    if (Math.abs(dk) < 1e-12) { if (Math.abs(ok) > e) return null; continue; }
    const a = (-e - ok) / dk, b = (e - ok) / dk;
    t0 = Math.max(t0, Math.min(a, b)); t1 = Math.min(t1, Math.max(a, b));
    if (t0 > t1) return null;
  }
  return t0;
}
