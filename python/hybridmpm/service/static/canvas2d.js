// The Canvas2D fallback of the view where WebGL2 is missing (render.js is the WebGL2 one).

import { COLORS, JELLY_ALPHA } from "./colors.js";
import { Camera } from "./mat.js";
import { JELLY, MUD, SAND, SNOW, WALL, WATER } from "/codes.js"; // the particle-type codes, served from hybridmpm.conventions

// The Canvas2D fallback (no WebGL2): particles as dots, 3D scenes as their x–y view (the controller's front view).
export class Canvas2DRenderer {
  constructor(canvas) {
    this.canvas = canvas; this.ctx = canvas.getContext("2d"); this.kind = "canvas2d";
    this.look = "particles"; this.showParticles = true; this.session = null; this.frame = null; this.camera = new Camera(2);
    this.bodies = null; // the rigid bodies' layer (bodies.js)
  }
  get fluidAvailable() { return false; }
  setSession(s) { this.session = s; this.frame = null; this.camera = new Camera(2); }
  setFrame(f) { if (f.n !== this.session.num_particles) return false; this.frame = f; return true; }
  draw() {
    const c = this.canvas, ctx = this.ctx, r = c.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(r.width * dpr)), h = Math.max(1, Math.round(r.height * dpr));
    if (c.width !== w || c.height !== h) { c.width = w; c.height = h; }
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#ffffff"; ctx.fillRect(0, 0, r.width, r.height);
    const M = this.camera.matrices(1);
    this.last = { M, w, h };
    const s = this.session, f = this.frame;
    if (!s || !f || !this.showParticles) return M;
    const sz = Math.max(1.5, r.width / 256), types = s.particle_type, { n, dim, pos } = f;
    for (const t of [WALL, WATER, SAND, MUD, SNOW, JELLY]) {
      ctx.fillStyle = (COLORS[t] || COLORS[WATER])[f.solver ? 1 : 0];
      ctx.globalAlpha = t === JELLY ? JELLY_ALPHA : 1;
      for (let i = 0; i < n; i++) {
        if (types[i] !== t) continue;
        ctx.fillRect(pos[i * dim] * r.width - sz / 2, (1 - pos[i * dim + 1]) * r.height - sz / 2, sz, sz);
      }
    }
    ctx.globalAlpha = 1;
    if (this.bodies) this.bodies.drawCanvas(ctx, s, f, (x, y) => [x * r.width, (1 - y) * r.height]);
    return M;
  }
  snapshot(width, height) {
    const tmp = document.createElement("canvas");
    tmp.width = width; tmp.height = height;
    const ctx = tmp.getContext("2d");
    this.draw();
    ctx.drawImage(this.canvas, 0, 0, width, height);
    return ctx.getImageData(0, 0, width, height).data;
  }
  glError() { return 0; }
}
