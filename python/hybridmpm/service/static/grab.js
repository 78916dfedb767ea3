// The drag tool: move an obstacle through the fluid.
// Pointer down on an obstacle (boxes and spheres, a few pixels of slack; 2D: inside its outline, 3D: the first one
// the pointer's ray from the camera meets) grabs it. The pointer's moves move it in a plane: 2D the domain's x–y,
// 3D the horizontal plane through the point grabbed (its y stays). They go to the server as
// PUT /v1/sessions/{id}/obstacles/{i} with the new centre, at most one every MOVE_EVERY_MS and one at a time (the
// latest position wins: each reaches the centre over the next coarse step); pointer up sends the last one and lets
// go. The session plays while dragging (a paused one pauses again after). Test hooks: window.__hmpm.obstacleMoves
// (each PUT's answer, or {index, center, error}) and window.__hmpm.grabbed (the obstacle held, or null).

import { pixelRay, rayObstacle, rayPlane } from "./picking.js";

const MOVE_EVERY_MS = 50, GRAB_SLACK_PX = 6, OBSTACLE_SPEED_MAX = 50; // m/s, the solver's limit (mpm/motion.py)

export class ObstacleGrab {
  // deps: {api(method, path, body), session() -> the session or null, latest() -> the latest frame or null,
  // playing() -> bool, ws() -> the frame stream or null, is3D() -> bool, setStatus(text), hook, canvas (the sketch
  // canvas), domain(clientX, clientY) -> [x, y], bounds() -> [lo, hi], matrices() -> the view's M, redraw()}
  constructor(deps) {
    this.deps = deps;
    this.grab = null;            // {index, axes, y, offset: centre − pointer, target, sent, timer}
    this.moveInFlight = false;
    this.resumeAfter = null;     // frame after which a session paused before the drag is paused again
  }

  get active() { return this.grab !== null; }
  holds(index) { return !!this.grab && this.grab.index === index; }

  // the drag tool's press on the stage: grabs the obstacle under the pointer, or says why there is none
  press(ev) {
    const { session, is3D, domain, setStatus } = this.deps, sess = session();
    if (ev.button !== 0 || this.grab) return;
    const hit = is3D() ? this.obstacleHit(ev.clientX, ev.clientY) : { index: this.obstacleAt(domain(ev.clientX, ev.clientY)), point: domain(ev.clientX, ev.clientY) };
    if (hit && hit.index >= 0) this.start(ev, hit.index, hit.point);
    else setStatus((sess.obstacles || []).length ? "no obstacle here: press on a box or a ball to drag it" : "this scene has no obstacle to drag");
  }

  // the pointer let go (or the gesture was cancelled): the last move goes, then the obstacle is let go
  release(ev) { if (!this.grab.released) { this.move(ev); this.end(); } }

  // the page leaves its session: nothing more is sent, and no pause is owed
  leave() { this.resumeAfter = null; if (this.grab) this.finish(); }

  // a frame arrived: a drag on a paused session played it so the fluid answers the moves; paused again once the
  // last move is stepped
  frame(frame) {
    const { playing, ws } = this.deps, stream = ws();
    if (this.resumeAfter !== null && !this.grab && !this.moveInFlight && frame > this.resumeAfter) {
      this.resumeAfter = null;
      if (!playing() && stream && stream.readyState === 1) stream.send(JSON.stringify({ type: "pause" }));
    }
  }

  obstacleAt(p) {
    const { session, canvas, bounds } = this.deps, sess = session();
    const obs = (sess && sess.obstacles) || [], r = canvas.getBoundingClientRect(), [lo, hi] = bounds();
    const slack = (GRAB_SLACK_PX * (hi[0] - lo[0])) / Math.max(1, r.width);
    for (let i = obs.length - 1; i >= 0; i--) { // the one drawn last (on top) first
      const ob = obs[i], dx = p[0] - ob.center[0], dy = p[1] - ob.center[1];
      if (ob.shape === "sphere") { if (Math.hypot(dx, dy) <= ob.radius + slack) return i; continue; }
      if (ob.shape !== "box") continue; // meshes are not draggable
      let c = 1, s = 0;
      if (ob.rotation) { c = ob.rotation[0][0]; s = ob.rotation[1][0]; } // columns: the box's axes
      else { const a = ((ob.angle_deg || 0) * Math.PI) / 180; c = Math.cos(a); s = Math.sin(a); }
      const u = c * dx + s * dy, v = -s * dx + c * dy, e = ob.half_extents; // Rᵀ (p − centre)
      if (Math.abs(u) <= e[0] + slack && Math.abs(v) <= e[1] + slack) return i;
    }
    return -1;
  }
  // 3D: the obstacle the pointer's ray meets first, and where ({index, point}), or null
  obstacleHit(clientX, clientY) {
    const { session, canvas, matrices } = this.deps, sess = session();
    const obs = (sess && sess.obstacles) || [], r = canvas.getBoundingClientRect(), M = matrices();
    const ray = pixelRay(M, clientX - r.left, clientY - r.top, r.width, r.height);
    let best = null;
    obs.forEach((ob, i) => {
      if (ob.shape !== "box" && ob.shape !== "sphere") return; // meshes are not draggable
      const far = Math.hypot(...[0, 1, 2].map((d) => ob.center[d] - M.eye[d]));
      const slack = (2 * GRAB_SLACK_PX * far) / (M.proj[5] * Math.max(1, r.height)); // the pixels' size at its distance
      const t = rayObstacle(ray, ob, slack);
      if (t !== null && (!best || t < best.t)) best = { index: i, t, point: ray.origin.map((o, d) => o + t * ray.dir[d]) };
    });
    return best;
  }
  // Where the pointer is in the grab's plane: 2D the domain's x–y; 3D on the horizontal plane at height y (null where
  // its ray misses the plane: above the horizon)
  pointer(ev, y) {
    const { is3D, domain, canvas, matrices } = this.deps;
    if (!is3D()) return domain(ev.clientX, ev.clientY);
    const r = canvas.getBoundingClientRect();
    return rayPlane(pixelRay(matrices(), ev.clientX - r.left, ev.clientY - r.top, r.width, r.height), [0, y, 0], [0, 1, 0]);
  }
  clampCenter(c, axes) { // the moved axes inside the walls: the server refuses a centre out of the domain
    const sess = this.deps.session(), [lo, hi] = this.deps.bounds(), t = (sess && sess.wall_thickness) || 0;
    return c.map((x, d) => (axes.includes(d) ? Math.max(lo[d] + t, Math.min(hi[d] - t, x)) : x));
  }
  async sendMove() {
    const { api, session, latest, hook, setStatus } = this.deps, sess = session(), last = latest();
    if (!this.grab || this.moveInFlight || !sess) return;
    const grab = this.grab;
    if (!grab.target || grab.target === grab.sent) { if (grab.released) this.finish(); return; }
    if (last && last.frame <= grab.waitFrame) return; // at most one move per coarse step (the last one not stepped yet)
    // one request moves it over one coarse step: a far pointer is followed in steps under the server's speed limit
    const g = grab, index = g.index, sid = sess.id, from = g.at, to = g.target;
    const maxStep = 0.5 * OBSTACLE_SPEED_MAX * (sess.r_t || 1) * (sess.dt_frame || 0.0025);
    const dist = Math.hypot(...to.map((x, d) => x - from[d])), f = dist > maxStep ? maxStep / dist : 1;
    const center = f < 1 ? to.map((x, d) => from[d] + f * (x - from[d])) : to;
    g.sent = f < 1 ? null : to; this.moveInFlight = true;
    try {
      const res = await api("PUT", `/v1/sessions/${sid}/obstacles/${index}`, { center, velocity: null });
      hook.obstacleMoves.push(res);
      g.at = center; g.waitFrame = res.frame;
      if (this.resumeAfter !== null) this.resumeAfter = Math.max(this.resumeAfter, res.frame);
    } catch (e) {
      hook.obstacleMoves.push({ index, center, error: e.message });
      setStatus(`obstacle move refused: ${e.message}`);
      g.sent = g.target; // not again; the next pointer move tries from where the server has it
      if (/^409/.test(e.message)) { g.released = true; g.target = null; } // a control runs, or the network alone steps
    } finally { this.moveInFlight = false; }
  }
  finish() { clearInterval(this.grab.timer); this.grab = null; this.deps.hook.grabbed = null; }
  start(ev, index, point) { // point: where it was grabbed (the pointer, in 2D; the ray's hit, in 3D)
    const { session, is3D, canvas, hook, playing, ws, latest, setStatus } = this.deps, stream = ws(), last = latest();
    const ob = session().obstacles[index], axes = is3D() ? [0, 2] : [0, 1];
    canvas.setPointerCapture(ev.pointerId);
    this.grab = { index, axes, y: point[1], offset: axes.map((d) => ob.center[d] - point[d]), at: ob.center.slice(), target: null,
      sent: null, waitFrame: -1, released: false, timer: setInterval(() => this.sendMove(), MOVE_EVERY_MS / 5) };
    hook.grabbed = index;
    if (!playing() && stream && stream.readyState === 1) { stream.send(JSON.stringify({ type: "play" })); this.resumeAfter = last ? last.frame : 0; }
    setStatus(`dragging obstacle ${index}${playing() ? "" : " (playing while you drag)"}`);
  }
  move(ev) {
    const grab = this.grab;
    if (grab.released) return;
    const now = performance.now(), p = this.pointer(ev, grab.y), ob = this.deps.session().obstacles[grab.index];
    if (!p) return; // the ray misses the drag plane: the obstacle stays where it was last drawn
    const c = ob.center.slice();
    grab.axes.forEach((d, k) => { c[d] = p[d] + grab.offset[k]; });
    ob.center = this.clampCenter(c, grab.axes); this.deps.redraw(); // drawn under the pointer at once; the server follows
    grab.pending = ob.center;
    if (!grab.lastTake || now - grab.lastTake >= MOVE_EVERY_MS) { grab.target = ob.center; grab.lastTake = now; } // throttled, latest wins
    else {
      clearTimeout(grab.take);
      grab.take = setTimeout(() => { if (this.grab && !this.grab.released) { this.grab.target = this.grab.pending; this.grab.lastTake = performance.now(); } }, MOVE_EVERY_MS);
    }
  }
  end() {
    const grab = this.grab;
    clearTimeout(grab.take);
    if (grab.pending) grab.target = grab.pending; // the drop point goes last
    grab.released = true; // the timer sends what is left, then lets go
    this.deps.setStatus(`obstacle ${grab.index} let go${this.deps.playing() ? "" : "; paused after its last move"}`);
  }
}
