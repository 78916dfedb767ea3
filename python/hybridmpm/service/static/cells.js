// The water of a 3D frame binned on the grid's cells (render.js and fluid.js draw what these return; no WebGL here).
// A cell of the grid (dx = 1 / n_grid) holds 2³ particles at rest: the particle spacing is dx / 2.
//  * surfaceIndices: the particles that can be seen: every particle but the water inside the body.
//  * cellSplats: one splat per cell of c × c × c grid cells at the mean of its water particles (the
//    quality's coarser levels: c³ · 8 times fewer splats to set up, the cost software GL pays most for).
// A cell is full with at least half its particles at rest; one whose six face neighbours are full too lies
// inside, hidden behind the surface. (Cells of the particle spacing hold about one particle each: once the
// particles leave their lattice nearly every such cell has an empty neighbour, and nearly every particle was
// drawn: 24,600 of 25,304 while the default scene plays.)

import { WATER } from "/codes.js"; // the particle-type codes, served from hybridmpm.conventions

export const PER_CELL = 8; // particles in a grid cell at rest

// Scratch space for a lattice of cells of `c` grid cells over [0, 1]³ with a ring of empty ones around.
export class Lattice {
  constructor(nGrid, c, capacity, sums = false) {
    this.c = c; this.inv = nGrid / c;
    this.L = Math.ceil(this.inv); this.G = this.L + 2;
    const cells = this.G * this.G * this.G;
    this.count = new Uint16Array(cells);
    this.sum = sums ? new Float32Array(3 * cells) : null;
    this.touched = new Int32Array(Math.min(cells, capacity));
    this.cellOf = new Int32Array(capacity);
    this.full = Math.max(1, (PER_CELL * c * c * c) / 2);
  }
  cell(pos, i) {
    const G = this.G, hi = G - 2, inv = this.inv;
    const x = Math.min(hi, Math.max(1, Math.floor(pos[3 * i] * inv) + 1));
    const y = Math.min(hi, Math.max(1, Math.floor(pos[3 * i + 1] * inv) + 1));
    const z = Math.min(hi, Math.max(1, Math.floor(pos[3 * i + 2] * inv) + 1));
    return (x * G + y) * G + z;
  }
  inside(k) {
    const n = this.count, f = this.full, G = this.G, G2 = G * G;
    return n[k] >= f && n[k - 1] >= f && n[k + 1] >= f && n[k - G] >= f && n[k + G] >= f && n[k - G2] >= f && n[k + G2] >= f;
  }
}

// Every particle but the water inside the body (on a lattice of grid cells, c = 1): their indices into `out`;
// returns how many.
export function surfaceIndices(pos, n, types, lat, out) {
  const count = lat.count, cellOf = lat.cellOf, touched = lat.touched;
  let t = 0;
  for (let i = 0; i < n; i++) {
    if (types[i] !== WATER) continue;
    const k = (cellOf[i] = lat.cell(pos, i));
    if (count[k] === 0) touched[t++] = k;
    if (count[k] < 65535) count[k]++;
  }
  let m = 0;
  for (let i = 0; i < n; i++) if (types[i] !== WATER || !lat.inside(cellOf[i])) out[m++] = i;
  for (let j = 0; j < t; j++) count[touched[j]] = 0;
  return m;
}

// One splat per cell that holds water and is not inside: its position (the mean of the cell's water particles,
// into outPos as x, y, z) and info (type 5, the cell's particle count, into outInfo); returns how many.
export function cellSplats(pos, n, types, lat, outPos, outInfo) {
  const count = lat.count, sum = lat.sum, touched = lat.touched;
  let t = 0;
  for (let i = 0; i < n; i++) {
    if (types[i] !== WATER) continue;
    const k = lat.cell(pos, i);
    if (count[k] === 0) touched[t++] = k;
    if (count[k] < 65535) count[k]++;
    sum[3 * k] += pos[3 * i]; sum[3 * k + 1] += pos[3 * i + 1]; sum[3 * k + 2] += pos[3 * i + 2];
  }
  let m = 0;
  for (let j = 0; j < t; j++) {
    const k = touched[j], c = count[k];
    if (lat.inside(k)) continue;
    outPos[3 * m] = sum[3 * k] / c; outPos[3 * m + 1] = sum[3 * k + 1] / c; outPos[3 * m + 2] = sum[3 * k + 2] / c;
    outInfo[2 * m] = WATER; outInfo[2 * m + 1] = c;
    m++;
  }
  for (let j = 0; j < t; j++) { const k = touched[j]; count[k] = 0; sum[3 * k] = sum[3 * k + 1] = sum[3 * k + 2] = 0; }
  return m;
}
