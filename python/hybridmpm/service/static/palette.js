// The palette: drop a block of water, sand, jelly, snow or mud where the pointer clicks
// (POST /v1/sessions/{id}/blocks; docs/page.md "The palette"). A material's button arms it; the next
// click on the stage drops a cube of the chosen side there: 2D centred on the pointer, 3D centred where
// the pointer's ray meets the horizontal plane at the chosen height. The cube is moved inside the walls;
// the server refuses one over the particles already there (more than 10 % overlap) or beyond the pour
// bounds, and the status line says why. Every viewer learns the new particles from the stream's
// 'particles' event (app.js). Test hook: window.__hmpm.drops (each answer, or {error}).
// A rigid body's button (crate, ball) arms it the same way (POST /v1/sessions/{id}/bodies; docs/bodies.md
// "The page"): a click drops one there at rest, a drag throws it from where the press was with the drag's
// velocity (the pointer's displacement on the same plane over the drag's duration, at most THROW_MAX). Test
// hook: window.__hmpm.bodyDrops (each request with its answer, or {error}).

export const MATERIALS = [ // [label, the block's material (a model or a preset: hybridmpm.materials)]
  ["water", "water"], ["sand", "sand"], ["jelly", "jello"], ["snow", "snow"], ["mud", "mud"],
];
// [label (the button's data-body), shape, density kg/m³, what it is]: their size is the drop side (a crate's edge, a ball's diameter)
export const BODIES = [
  ["crate", "box", 500, "a wooden crate: a cube, 500 kg/m³ (it floats half out of the water)"],
  ["ball", "sphere", 700, "a ball, 700 kg/m³ (it floats 70 % under)"],
];
export const THROW_MAX = 4; // m/s: a throw's speed at most (the domain is 1 m across)
const CLICK_PX = 5;          // a press that moves less than this many CSS pixels is a click: a drop at rest

export class Palette {
  // deps: {api(method, path, body), session() -> the session or null, ray(clientX, clientY, y) -> the 3D point at
  // height y or null, domain(clientX, clientY) -> [x, y], is3D() -> bool, setStatus(text), hook}
  constructor(root, deps) {
    this.deps = deps; this.armed = null; this.busy = false;
    deps.hook.drops = [];
    this.buttons = MATERIALS.map(([label, material]) => {
      const b = document.createElement("button");
      b.type = "button"; b.textContent = label; b.dataset.material = material; b.setAttribute("aria-pressed", "false");
      b.title = `drop a block of ${label} where you click next`;
      b.addEventListener("click", () => this.arm(this.armed === material ? null : material));
      root.querySelector(".materials").append(b);
      return b;
    });
    deps.hook.bodyDrops = [];
    this.gesture = null; // a body's press: {start: [x, y(, z)] m, t0 ms, x, y CSS px, last}
    for (const [label, shape, density, what] of BODIES) {
      const b = document.createElement("button");
      b.type = "button"; b.textContent = label; b.dataset.body = label; b.setAttribute("aria-pressed", "false");
      b.title = `${what}, as wide as the side below: click the stage to drop one, drag to throw it (at most ${THROW_MAX} m/s)`;
      b.addEventListener("click", () => this.arm(this.armed === label ? null : label));
      root.querySelector(".bodies").append(b);
      this.buttons.push(b);
    }
    this.side = root.querySelector("#drop-side"); this.height = root.querySelector("#drop-height");
  }

  isBody(name) { return BODIES.some((b) => b[0] === name); }

  arm(material) {
    this.armed = material;
    for (const b of this.buttons) b.setAttribute("aria-pressed", String((b.dataset.material || b.dataset.body) === material));
    if (material) this.deps.setStatus(this.isBody(material) ? `click the stage to drop a ${material}, drag to throw it` : `click the stage to drop a block of ${material}`);
  }

  // where the pointer is: 3D on the drop height's plane, 2D the domain (null: the ray misses the plane)
  target(clientX, clientY) {
    const sess = this.deps.session(), c = this.deps.is3D() ? this.deps.ray(clientX, clientY, this.dropHeight()) : this.deps.domain(clientX, clientY);
    if (!c) return null;
    return sess.dim === 3 && c.length < 3 ? [...c.slice(0, 2), 0.5] : c.slice(0, sess.dim);
  }
  dropHeight() { return Number(this.height.value) || 0.5; }
  dropSide() { return Math.max(0.02, Math.min(0.3, Number(this.side.value) || 0.1)); }

  // the pointer pressed on the stage while armed (true: the palette's): a block drops now, a body on release
  press(ev) {
    if (!this.armed || !this.deps.session()) return false;
    if (!this.isBody(this.armed)) { this.drop(ev.clientX, ev.clientY); return true; }
    const start = this.target(ev.clientX, ev.clientY);
    if (!start) { this.deps.setStatus("the pointer's ray misses the drop height's plane: click lower"); return true; }
    this.gesture = { start, last: start, t0: performance.now(), x: ev.clientX, y: ev.clientY };
    return true;
  }
  move(ev) { const p = this.target(ev.clientX, ev.clientY); if (p && this.gesture) this.gesture.last = p; }
  // released: a drop at rest (a click) or a throw along the drag
  release(ev) {
    const g = this.gesture;
    this.gesture = null;
    if (!g) return;
    this.move(ev);
    const end = this.target(ev.clientX, ev.clientY) || g.last, dt = Math.max(0.02, (performance.now() - g.t0) / 1000);
    let v = g.start.map(() => 0);
    if (Math.hypot(ev.clientX - g.x, ev.clientY - g.y) >= CLICK_PX) {
      v = end.map((x, d) => (x - g.start[d]) / dt);
      const speed = Math.hypot(...v);
      if (speed > THROW_MAX) v = v.map((x) => (x * THROW_MAX) / speed);
    }
    this.dropBody(this.armed, g.start, v);
  }

  // POST body `name` (BODIES) centred at c (moved inside the walls) with velocity v [m/s]
  async dropBody(name, c, v) {
    const sess = this.deps.session(), [, shape, density] = BODIES.find((b) => b[0] === name);
    if (!sess || this.busy) return;
    const half = this.dropSide() / 2, [lo, hi] = sess.bounds, t = (sess.wall_thickness || 0) + 1e-3;
    const center = c.map((x, d) => Math.max(lo[d] + t + half, Math.min(hi[d] - t - half, x)));
    const body = { shape: shape === "sphere" && sess.dim === 2 ? "circle" : shape, center, density, velocity: v.map((x) => Math.round(x * 1e4) / 1e4) };
    if (shape === "box") body.half_extents = center.map(() => half); else body.radius = half;
    this.busy = true;
    try {
      const res = await this.deps.api("POST", `/v1/sessions/${sess.id}/bodies`, body);
      this.deps.hook.bodyDrops.push({ ...res, name, body });
      const speed = Math.hypot(...body.velocity);
      this.deps.setStatus(`${speed > 0 ? `threw a ${name} at ${speed.toFixed(2)} m/s` : `dropped a ${name}`} (body ${res.index}; ${res.num_bodies} in all)`);
    } catch (e) {
      this.deps.hook.bodyDrops.push({ name, body, error: e.message });
      this.deps.setStatus(`the ${name} was refused: ${e.message}`);
    } finally { this.busy = false; }
  }

  // the block centred at c (D numbers), of side s, moved inside the walls' faces: {lo, hi}
  block(c, s) {
    const sess = this.deps.session(), [lo, hi] = sess.bounds, t = sess.wall_thickness || 0, eps = 1e-4;
    const a = c.map((x, d) => Math.max(lo[d] + t + eps, Math.min(hi[d] - t - eps - s, x - s / 2)));
    return { lo: a, hi: a.map((x) => x + s) };
  }

  // the pointer at (clientX, clientY): a drop when armed (true: the click was the palette's)
  async drop(clientX, clientY) {
    const sess = this.deps.session();
    if (!this.armed || !sess) return false;
    if (this.busy) return true;
    const s = this.dropSide(), c = this.target(clientX, clientY);
    if (!c) { this.deps.setStatus("the pointer's ray misses the drop height's plane: click lower"); return true; }
    const material = this.armed, body = { material, ...this.block(c, s) };
    this.busy = true;
    try {
      const res = await this.deps.api("POST", `/v1/sessions/${sess.id}/blocks`, body);
      this.deps.hook.drops.push({ ...res, material, lo: body.lo, hi: body.hi });
      this.deps.setStatus(`dropped ${res.added} particles of ${material} (${res.num_particles} in all)`);
    } catch (e) {
      this.deps.hook.drops.push({ material, lo: body.lo, hi: body.hi, error: e.message });
      this.deps.setStatus(`the block was refused: ${e.message}`);
    } finally { this.busy = false; }
    return true;
  }
}
