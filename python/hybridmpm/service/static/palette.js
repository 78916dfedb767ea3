// The palette: drop a block of water, sand, jelly, snow or mud where the pointer clicks
// (POST /v1/sessions/{id}/blocks; docs/page.md "The palette"). A material's button arms it; the next
// click on the stage drops a cube of the chosen side there: 2D centred on the pointer, 3D centred where
// the pointer's ray meets the horizontal plane at the chosen height. The cube is moved inside the walls;
// the server refuses one over the particles already there (more than 10 % overlap) or beyond the pour
// bounds, and the status line says why. Every viewer learns the new particles from the stream's
// 'particles' event (app.js). Test hook: window.__hmpm.drops (each answer, or {error}).

export const MATERIALS = [ // [label, the block's material (a model or a preset: hybridmpm.materials)]
  ["water", "water"], ["sand", "sand"], ["jelly", "jello"], ["snow", "snow"], ["mud", "mud"],
];

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
    this.side = root.querySelector("#drop-side"); this.height = root.querySelector("#drop-height");
  }

  arm(material) {
    this.armed = material;
    for (const b of this.buttons) b.setAttribute("aria-pressed", String(b.dataset.material === material));
    if (material) this.deps.setStatus(`click the stage to drop a block of ${material}`);
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
    const s = Math.max(0.02, Math.min(0.3, Number(this.side.value) || 0.1));
    const c = this.deps.is3D() ? this.deps.ray(clientX, clientY, Number(this.height.value) || 0.5) : this.deps.domain(clientX, clientY);
    if (!c) { this.deps.setStatus("the pointer's ray misses the drop height's plane: click lower"); return true; }
    const material = this.armed, body = { material, ...this.block(sess.dim === 3 && c.length < 3 ? [...c, 0.5] : c.slice(0, sess.dim), s) };
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
