// hybridmpm page: live particles over a binary WebSocket (frames.js) drawn with WebGL2 (render.js; canvas2d.js where
// WebGL2 is missing), sketches with mouse or pen, downloads. No build step, no CDN. Test hook: window.__hmpm.

import { BodyLayer } from "./bodies.js";
import { Canvas2DRenderer } from "./canvas2d.js";
import { FrameStream, readFrame } from "./frames.js";
import { encodeGif } from "./gif.js";
import { ObstacleGrab } from "./grab.js";
import { Palette } from "./palette.js";
import { pixelRay, project, rayPlane } from "./picking.js";
import { LEVELS, QualityController, SOFTWARE_START, levelForScale } from "./quality.js";
import { GLRenderer } from "./render.js";
import { simplify, sketchBody } from "./sketch.js";
import { WALL } from "/codes.js"; // the particle-type codes, served from hybridmpm.conventions

const MAX_POINTS = 512;
const HISTORY = 120;                 // frames kept for the GIF
const GIF_SIZE = 320;                // pixels
const INK = "#d1245a", PLAN = "#0b7a4b";
const DEFAULT_3D = "paddle3d";         // the page's scene where WebGL2 draws 3D (the dam break's 23,520 particles, a paddle to drag)

const params = new URLSearchParams(location.search);
const bench = params.get("bench") === "1";    // draw every animation frame (and turn a 3D camera): frames/s
const syncDraw = params.get("sync") === "1";  // wait for the GPU inside the timed draw
const syncPixel = new Uint8Array(4);

const hook = (window.__hmpm = {
  framesReceived: 0, framesRendered: 0, lastDrawMs: 0, drawMs: [], fps: 0, controls: [], errors: [],
  session: null, status: "", lastFrame: -1, lastSketch: null, renderer: "", look: "",
  applied: null, strokeCss: [], planCss: [], lastControlFrame: 0, controlRunning: false, gif: null, camera: null,
  obstacleMoves: [], obstacleEvents: [], grabbed: null, // the drag tool: the PUTs it sent (answers), the stream's events
  realtimeFactor: null, realtimeLabel: null, // a real-time session's: the latest frame's factor (null: not measured), its configuration
  showParticles: (on) => { renderer.showParticles = !!on; dirty = true; },
  centroidCss: () => centroidCss(),
  toCss: (p) => toCss(p),             // world point -> CSS pixels of the sketch canvas
  view: null,                         // the renderer (tests and benchmarks)
  // rigid bodies: the palette's POSTs (bodyDrops), what the last draw drew (bodiesDrawn), a body list drawn in place of the session's
  showBodies: (list) => { if (session) { session.bodies = list; dirty = true; } },
});
window.addEventListener("error", (e) => hook.errors.push(String(e.message || e)));
window.addEventListener("unhandledrejection", (e) => hook.errors.push(String(e.reason)));

const $ = (id) => document.getElementById(id);
const simCanvas = $("sim"), inkCanvas = $("ink"), ink2d = inkCanvas.getContext("2d");

let renderer;
try {
  if (params.get("gl") === "0") throw new Error("WebGL switched off (?gl=0)");
  renderer = new GLRenderer(simCanvas);
} catch (e) {
  renderer = new Canvas2DRenderer(simCanvas);
  console.info(`Canvas2D view: ${e.message}`);
}
hook.renderer = renderer.kind; hook.view = renderer;
const bodyLayer = (renderer.bodies = new BodyLayer());
Object.defineProperty(hook, "bodiesDrawn", { enumerable: true, get: () => bodyLayer.drawn });

let session = null, ws = null, playing = params.get("autoplay") !== "0";
let latest = null;           // {frame, n, dim, solver, controlled, cframe, time, pos}
let fresh = false;           // latest not yet handed to the renderer
let dirty = false;
let stroke = [];             // world points [x, y, z] of the sketch being drawn (2D: z = 0)
let plane = null;            // 3D: {point, normal} of the sketch plane
let drawing = false, orbiting = null;
let applied = null;          // the applied sketch: {kind, stroke, plan, id, frames, running}
const history = [];          // the last HISTORY frames received (the GIF's)
const recentSolvers = [];    // 1 = network, last 200 frames
const renderTimes = [];
let lastArrival = 0, interval = 0, lastReadout = 0;

function setStatus(text) { hook.status = text; $("status").textContent = text; }
const is3D = () => !!session && session.dim === 3 && renderer.kind === "webgl2";

// ---------------------------------------------------------------- coordinates (the one place)
// CSS pixels of the sketch canvas <-> the domain. 2D (and the Canvas2D view): the domain's x–y fills the
// canvas, the y axis flipped exactly here (the canvas grows downwards, the domain upwards). 3D: the
// camera's rays (picking.js pixelRay) meet the sketch plane.
function bounds() { return session ? session.bounds : [[0, 0], [1, 1]]; }
function toDomain(clientX, clientY) {
  const r = inkCanvas.getBoundingClientRect(), [lo, hi] = bounds();
  const u = (clientX - r.left) / r.width, v = (clientY - r.top) / r.height;
  return [lo[0] + u * (hi[0] - lo[0]), lo[1] + (1 - v) * (hi[1] - lo[1])];
}
function toWorld(clientX, clientY) {
  if (!is3D()) { const [x, y] = toDomain(clientX, clientY); return [x, y, plane ? plane.point[2] : 0]; }
  const r = inkCanvas.getBoundingClientRect();
  return rayPlane(pixelRay(matrices(), clientX - r.left, clientY - r.top, r.width, r.height), plane.point, plane.normal);
}
function matrices() { return renderer.last ? renderer.last.M : renderer.camera.matrices(1); }
function toCss(p) {
  const r = inkCanvas.getBoundingClientRect();
  return project(matrices(), p, r.width, r.height);
}
function fluidCentroid() {
  if (!latest || !session) return [0.5, 0.5, 0.5];
  const { n, dim, pos } = latest, types = session.particle_type, c = [0, 0, 0];
  let k = 0;
  for (let i = 0; i < n; i++) {
    if (types[i] === WALL) continue;
    for (let d = 0; d < dim; d++) c[d] += pos[i * dim + d];
    k++;
  }
  return c.map((v) => v / Math.max(1, k));
}
function centroidCss() { return toCss(fluidCentroid()); }

// ---------------------------------------------------------------- API
async function api(method, path, body) {
  const res = await fetch(path, {
    method, headers: body ? { "Content-Type": "application/json" } : {}, body: body ? JSON.stringify(body) : undefined,
  });
  let data = null;
  try { data = await res.json(); } catch { data = null; }
  if (!res.ok) {
    const d = data && data.detail;
    const msg = Array.isArray(d) ? d.map((e) => `${(e.loc || []).slice(1).join(".")}: ${e.msg}`).join("; ") : (d || res.statusText);
    throw new Error(`${res.status} ${msg}`);
  }
  return data;
}

// the solvers and control methods each scene offers, and its defaults (GET /v1/scenes: no probing by error)
const sceneSolvers = {}, sceneMethods = {};
async function loadScenes() {
  const scenes = await api("GET", "/v1/scenes");
  const sel = $("scene");
  for (const s of scenes) {
    const o = document.createElement("option");
    o.value = s.name; o.textContent = `${s.name} (${s.dim}D)${s.model ? "" : ", MPM only"}`;
    sel.appendChild(o);
    sceneSolvers[s.name] = s.solvers;
    sceneMethods[s.name] = { methods: s.methods, def: s.default_method };
  }
  // the default scene: the 3D dam break with its paddle where WebGL2 draws 3D, the 2D water blocks on the Canvas2D fallback (an x–y view)
  const fallback = renderer.kind === "webgl2" && sceneSolvers[DEFAULT_3D] ? DEFAULT_3D : "water2d";
  sel.value = params.get("scene") || fallback;
  $("seed").value = params.get("seed") || "0";
  // a real-time session where the scene offers one (?solver= chooses another: ?solver=default the chart's choice)
  $("solver").value = params.get("solver") || ((sceneSolvers[sel.value] || []).includes("realtime") ? "realtime" : "default");
  syncSolvers();
  if (params.get("method")) $("method").value = params.get("method");
  if (params.get("frames")) $("frames").value = params.get("frames");
  if (params.get("look")) setLook(params.get("look"));
}

// offer only the scene's control methods, its default selected
function syncMethods() {
  const offered = sceneMethods[$("scene").value];
  if (!offered) return;
  const sel = $("method");
  for (const o of sel.options) o.disabled = !offered.methods.includes(o.value);
  sel.value = offered.def;
}

// offer only the scene's solvers; a solver it lacks falls back to its first (MPM)
function syncSolvers() {
  syncMethods();
  const allowed = sceneSolvers[$("scene").value] || [];
  const sel = $("solver");
  for (const o of sel.options) o.disabled = allowed.length > 0 && !allowed.includes(o.value);
  if (allowed.length > 0 && !allowed.includes(sel.value)) sel.value = allowed[0];
}

function leaveSession() {
  closeStream();
  if (session && session.owned) { api("DELETE", `/v1/sessions/${session.id}`).catch(() => {}); } // a joined one is another page's
  session = null; latest = null; hook.session = null; $("apply").disabled = true;
  showRealtime(null); hook.realtimeFactor = null;
  dragTool.leave();
  history.length = 0; stroke = []; setApplied(null);
}
async function newSession() {
  leaveSession();
  setStatus("creating session…");
  try {
    const solver = $("solver").value; // realtime: what the page asks, not the server's default (serve --realtime)
    session = await api("POST", "/v1/sessions", {
      scene: $("scene").value, seed: Number($("seed").value) || 0, solver, realtime: solver === "realtime",
      when_full: "coarser", // a full server starts a real-time session coarser rather than refusing it
    });
  } catch (e) { setStatus(`could not create a session: ${e.message}`); return; }
  session.owned = true;
  useSession();
}
// ?session=ID: watch (and draw on) a session another page or client made; leaving it does not delete it
async function joinSession(id) {
  leaveSession();
  setStatus("joining session…");
  try { session = await api("GET", `/v1/sessions/${encodeURIComponent(id)}`); } catch (e) { setStatus(`could not join the session: ${e.message}`); return; }
  session.owned = false;
  if (sceneSolvers[session.scene]) { $("scene").value = session.scene; syncSolvers(); }
  useSession();
}
function useSession() {
  hook.session = session;
  renderer.setSession(session);
  hook.camera = renderer.camera;
  for (const el of document.querySelectorAll(".only3d")) el.hidden = !is3D();
  for (const el of document.querySelectorAll(".only2d")) el.hidden = is3D();
  if (!is3D() && tool() === "turn") document.querySelector("input[name=tool][value=arrow]").checked = true;
  $("r-n").textContent = `${session.num_fluid} fluid + ${session.num_particles - session.num_fluid} boundary`;
  $("apply").disabled = false;
  $("dl-npz").href = `/v1/sessions/${session.id}/trajectory`;
  $("dl-ply").href = `/v1/sessions/${session.id}/trajectory?format=ply`;
  $("dl-control").hidden = true;
  showRealtime(session.realtime);
  openStream();
}
// A real-time session's configuration (its description's `realtime`, then the stream's "realtime" events): the label
// beside the frames/s readout, with the real-time factor of the latest frame (onFrame); both hidden otherwise
function showRealtime(rt) {
  if (session) session.realtime = rt || null;
  hook.realtimeLabel = rt ? rt.label : null;
  for (const el of document.querySelectorAll(".only-rt")) el.hidden = !rt;
  $("r-rung").textContent = rt ? rt.label : "–";
  $("r-rung").title = rt ? `${rt.rung}, ${rt.changes} changes so far; the ladder, most accurate first: ${(rt.ladder || []).join(", ")}` : "";
  showFactor();
}
function showFactor() {
  const f = hook.realtimeFactor;
  $("r-rtf").textContent = f === null ? "measuring…" : `sim ${f.toFixed(2)}× real time`;
}

// ---------------------------------------------------------------- stream
// The WebSocket lives in a worker (frames.js FrameStream): frames and events come to onFrame and onEvent.
function closeStream() { if (ws) { ws.onclose = null; ws.close(); ws = null; } }
function openStream() {
  const proto = location.protocol === "https:" ? "wss" : "ws";
  ws = new FrameStream(`${proto}://${location.host}${session.stream}`, { frame: onFrame, event: onEvent, error: (text) => hook.errors.push(text) });
  ws.onopen = () => { setStatus("streaming"); if (playing) ws.send(JSON.stringify({ type: "play" })); };
  ws.onclose = (ev) => setStatus(ev.code === 4000 ? "session expired: start a new one" : `stream closed (${ev.code} ${ev.reason})`);
}
// A control this page did not apply (another viewer's, or one running when this page joined): shown as the
// page that applied it shows it, its sketch in domain coordinates (3D: on the mid-depth plane) and its plan.
function showOthersControl(c) {
  const mine = applied && applied.running && (applied.id === null || applied.id === c.id);
  if (mine) { applied.id = c.id; if (c.plan && !applied.plan) { applied.plan = c.plan; setApplied(applied); } return; }
  if (!c.sketch || !Array.isArray(c.sketch.points)) return;
  const stroke = c.sketch.points.map((p) => (is3D() ? [p[0], p[1], 0.5] : [p[0], p[1]]));
  setApplied({ kind: c.sketch.kind === "oval" ? "oval" : "arrow", stroke, plan: c.plan || null, id: c.id, frames: c.frames, running: true });
}
function onEvent(msg) {
  if (msg.type === "meta") {
    hook.streamFrame = msg.frame; // the session's frame when this page's stream opened
    if (msg.control && msg.control.status === "running") { // joined while a control runs: told so by the first message
      hook.controlRunning = true;
      showOthersControl(msg.control);
      setStatus(`control ${msg.control.method} running…`);
    }
  } else if (msg.type === "control") {
    hook.controlRunning = msg.status === "running";
    if (msg.status === "running") showOthersControl(msg);
    else if (applied && applied.running && applied.id === msg.id && !hook.controls.some((c) => c.id === msg.id)) { applied.running = false; setApplied(applied); }
    setStatus(msg.status === "running" ? `control ${msg.method} running…`
      : msg.status === "done" ? `control done; ${playing ? "the simulation continues" : "paused (press play to go on)"}` : `control ${msg.status}`);
  } else if (msg.type === "plan") {
    if (applied && applied.running && !applied.plan && (applied.id === null || applied.id === msg.id)) { applied.plan = msg; hook.applied.plan = msg; drawInk(true); }
  } else if (msg.type === "reset") {
    setApplied(null);
    refreshObstacles(); // the obstacles are back where the scene put them
  } else if (msg.type === "particles") {
    // a block was poured (or a reset took it away): the frames' n changes, the particle types with it
    if (session) {
      Object.assign(session, { particle_type: msg.particle_type, num_particles: msg.num_particles, num_fluid: msg.num_fluid });
      renderer.setSession(session); dirty = true;
    }
  } else if (msg.type === "obstacle") {
    hook.obstacleEvents.push(msg); if (hook.obstacleEvents.length > 200) hook.obstacleEvents.shift();
    const ob = session && session.obstacles && session.obstacles[msg.index];
    // drawn where the server moved it (every viewer), except the one this page is dragging: there the pointer leads
    if (ob && !dragTool.holds(msg.index)) { ob.center = msg.center; dirty = true; }
  } else if (msg.type === "bodies") { // added or removed: the shapes as given now, their poses at this frame once read
    if (session) { session.bodies = msg.bodies; dirty = true; refreshBodies(); }
  } else if (msg.type === "realtime") {
    const rt = { ...msg };
    delete rt.type;
    if (session) showRealtime(rt);
  } else if (msg.type === "error") setStatus(msg.message);
}
async function refreshBodies() {
  const id = session && session.id;
  try {
    const s = await api("GET", `/v1/sessions/${id}`);
    if (session && session.id === id && Array.isArray(s.bodies)) { session.bodies = s.bodies; dirty = true; }
  } catch { /* the session is gone: nothing to redraw */ }
}
function onFrame(buf) {
  const f = readFrame(buf);
  if (!f) return;
  latest = f;
  const { frame, solver, controlled, cframe } = f;
  history.push(latest); if (history.length > HISTORY) history.shift();
  hook.framesReceived += 1; hook.lastFrame = frame; hook.realtimeFactor = f.realtimeFactor;
  if (controlled) hook.lastControlFrame = cframe;
  const now = performance.now();
  if (lastArrival) interval = 0.9 * interval + 0.1 * (now - lastArrival);
  lastArrival = now;
  recentSolvers.push(solver); if (recentSolvers.length > 200) recentSolvers.shift();
  fresh = dirty = true;
  dragTool.frame(frame); // a drag on a paused session played it: paused again once the last move is stepped
}

// ---------------------------------------------------------------- drawing
// every animation frame: draw what changed, and tell the quality controller whether it drew
function render(now) {
  requestAnimationFrame(render);
  const drew = drawFrame(now);
  if (quality) quality.frame(now, drew);
}
function drawFrame(now) {
  if (bench && latest) {
    dirty = true;
    if (is3D()) renderer.camera.yaw += 0.01;
  }
  if (!dirty || !latest || !session) return false;
  dirty = false;
  const t0 = performance.now();
  if (fresh && renderer.setFrame(latest)) fresh = false; // else held until the 'particles' event names its count
  renderer.draw();
  if (syncDraw && renderer.gl) renderer.gl.readPixels(0, 0, 1, 1, renderer.gl.RGBA, renderer.gl.UNSIGNED_BYTE, syncPixel); // waits for the GPU
  const ms = performance.now() - t0;
  hook.lastDrawMs = ms; hook.drawMs.push(ms); if (hook.drawMs.length > 100) hook.drawMs.shift();
  hook.framesRendered += 1;
  renderTimes.push(now); while (renderTimes.length > 2 && now - renderTimes[0] > 2000) renderTimes.shift();
  hook.fps = renderTimes.length > 1 ? (1000 * (renderTimes.length - 1)) / (renderTimes.at(-1) - renderTimes[0]) : 0;
  if (renderer.gl && hook.framesRendered % 120 === 1) {
    const err = renderer.glError();
    if (err) { hook.errors.push(`WebGL error ${err}`); console.error(`WebGL error ${err}`); }
  }
  drawInk();
  $("badge").textContent = `${latest.solver ? "network" : "MPM"}${latest.controlled ? " · controlled" : ""}`;
  $("badge").className = latest.solver ? "nn" : "mpm";
  if (now - lastReadout > 250) {
    lastReadout = now;
    $("r-frame").textContent = `${latest.frame}${latest.controlled ? ` (controlled ${latest.cframe})` : ""}`;
    $("r-latency").textContent = `${interval.toFixed(1)} ms`;
    const med = [...hook.drawMs].sort((a, b) => a - b)[hook.drawMs.length >> 1];
    $("r-draw").textContent = `${ms.toFixed(1)} ms (median ${med.toFixed(1)})${syncDraw ? ", GPU included" : ", CPU"}`;
    $("r-fps").textContent = `${hook.fps.toFixed(0)} frames/s`;
    if (session.realtime) showFactor();
    const share = recentSolvers.reduce((a, b) => a + b, 0) / Math.max(1, recentSolvers.length);
    $("r-share").textContent = `${(100 * share).toFixed(0)} %`;
    showQuality();
  }
  return true;
}

function tool() { return document.querySelector("input[name=tool]:checked").value; }

function polyline(pts, close) {
  ink2d.beginPath();
  let started = false;
  for (const p of pts) {
    if (!p) { started = false; continue; }
    if (started) ink2d.lineTo(p[0], p[1]); else { ink2d.moveTo(p[0], p[1]); started = true; }
  }
  if (close) ink2d.closePath();
  ink2d.stroke();
}
function arrowHead(a, b, color) {
  if (!a || !b) return;
  const ang = Math.atan2(b[1] - a[1], b[0] - a[0]);
  ink2d.beginPath(); ink2d.moveTo(b[0], b[1]);
  ink2d.lineTo(b[0] - 14 * Math.cos(ang - 0.4), b[1] - 14 * Math.sin(ang - 0.4));
  ink2d.lineTo(b[0] - 14 * Math.cos(ang + 0.4), b[1] - 14 * Math.sin(ang + 0.4));
  ink2d.closePath(); ink2d.fillStyle = color; ink2d.fill();
}

// The overlay: the sketch plane while drawing (3D), the stroke (being drawn, or applied: it stays for the
// whole controlled horizon and after, until cleared), and the plan's centroid path with where the plan is now.
// Redrawn only when what it shows changes (an unchanged overlay costs nothing to composite again).
let inkKey = "", inkBlank = false;
function drawInk(force = false) {
  const r = inkCanvas.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(r.width * dpr)), h = Math.max(1, Math.round(r.height * dpr));
  const cam = renderer.camera, plan = applied && !drawing ? applied.plan : null;
  const step = plan && latest && latest.controlled ? Math.round(latest.cframe / plan.stride) : -1;
  const key = [w, h, cam.yaw, cam.pitch, cam.dist, drawing, stroke.length, applied ? applied.stroke.length : -1, plan ? plan.centroid_path.length : -1, step, tool()].join();
  if (!force && key === inkKey) return;
  inkKey = key;
  const empty = !drawing && !applied && stroke.length === 0;
  if (empty && inkBlank && inkCanvas.width === w && inkCanvas.height === h) return; // nothing shown, nothing to redo
  inkBlank = empty;
  if (inkCanvas.width !== w || inkCanvas.height !== h) { inkCanvas.width = w; inkCanvas.height = h; }
  ink2d.setTransform(dpr, 0, 0, dpr, 0, 0);
  ink2d.clearRect(0, 0, r.width, r.height);
  ink2d.lineJoin = ink2d.lineCap = "round";
  if (drawing && plane && is3D()) { // the sketch plane: a square of 0.6 m facing the camera
    const M = matrices(), v = M.view, right = [v[0], v[4], v[8]], up = [v[1], v[5], v[9]], c = plane.point;
    const corner = (a, b) => toCss([c[0] + 0.3 * (a * right[0] + b * up[0]), c[1] + 0.3 * (a * right[1] + b * up[1]), c[2] + 0.3 * (a * right[2] + b * up[2])]);
    ink2d.strokeStyle = "rgba(209, 36, 90, 0.35)"; ink2d.lineWidth = 1; ink2d.setLineDash([4, 4]);
    polyline([corner(-1, -1), corner(1, -1), corner(1, 1), corner(-1, 1)], true);
    ink2d.setLineDash([]);
  }
  const shown = drawing || !applied ? { kind: tool(), stroke } : applied;
  const css = shown.stroke.map(toCss);
  hook.strokeCss = css.filter(Boolean).map((p) => [p[0], p[1]]);
  if (css.length >= 2) {
    ink2d.strokeStyle = INK; ink2d.lineWidth = 3;
    polyline(css, shown.kind === "oval");
    if (shown.kind === "arrow") arrowHead(css.at(-2), css.at(-1), INK);
  }
  hook.planCss = [];
  if (plan && plan.centroid_path.length > 1) {
    const pts = plan.centroid_path.map((p) => toCss([p[0], p[1], p[2] || 0]));
    hook.planCss = pts.filter(Boolean).map((p) => [p[0], p[1]]);
    ink2d.strokeStyle = PLAN; ink2d.lineWidth = 2.5; ink2d.setLineDash([7, 5]);
    polyline(pts, false);
    ink2d.setLineDash([]);
    const end = pts.at(-1);
    if (end) { ink2d.beginPath(); ink2d.arc(end[0], end[1], 7, 0, 2 * Math.PI); ink2d.lineWidth = 2; ink2d.stroke(); }
    if (latest && latest.controlled) { // where the plan is now
      const k = Math.min(pts.length - 1, Math.round(latest.cframe / plan.stride)), p = pts[k];
      if (p) { ink2d.beginPath(); ink2d.arc(p[0], p[1], 5, 0, 2 * Math.PI); ink2d.fillStyle = PLAN; ink2d.fill(); }
    }
  }
}

function setApplied(a) {
  applied = a;
  hook.applied = a ? { kind: a.kind, stroke: a.stroke, plan: a.plan, running: a.running } : null;
  dirty = true;
  if (latest) drawInk(true);
}

function addSamples(ev) {
  const evs = typeof ev.getCoalescedEvents === "function" ? ev.getCoalescedEvents() : []; // secure contexts only
  for (const e of evs.length ? evs : [ev]) { const p = toWorld(e.clientX, e.clientY); if (p) stroke.push(p); }
}
// ---------------------------------------------------------------- the drag tool: move an obstacle through the fluid (grab.js)
const dragTool = new ObstacleGrab({
  api, session: () => session, latest: () => latest, playing: () => playing, ws: () => ws, is3D, setStatus, hook,
  canvas: inkCanvas, domain: toDomain, bounds, matrices, redraw: () => { dirty = true; },
});

async function refreshObstacles() {
  if (!session) return;
  try {
    const s = await api("GET", `/v1/sessions/${session.id}`);
    if (!session || s.id !== session.id || !s.obstacles) return;
    s.obstacles.forEach((ob, i) => { if (s.obstacle_centers && s.obstacle_centers[i]) ob.center = s.obstacle_centers[i]; });
    session.obstacles = s.obstacles; dirty = true;
  } catch { /* the session is gone: nothing to redraw */ }
}

const palette = new Palette($("palette"), {
  api, session: () => session, is3D, setStatus, hook, domain: toDomain,
  ray: (x, y, h) => { const r = inkCanvas.getBoundingClientRect(); return rayPlane(pixelRay(matrices(), x - r.left, y - r.top, r.width, r.height), [0, h, 0], [0, 1, 0]); },
});
inkCanvas.addEventListener("contextmenu", (ev) => ev.preventDefault());
inkCanvas.addEventListener("pointerdown", (ev) => {
  if (palette.armed && ev.button === 0 && session) { // the palette's drop (a body's: on release, a drag throws it)
    if (palette.press(ev) && palette.gesture) inkCanvas.setPointerCapture(ev.pointerId);
    return;
  }
  if (tool() === "drag" && session && (ev.button === 0 || !is3D())) { // 3D: the other buttons turn the camera (below)
    dragTool.press(ev);
    return;
  }
  if (is3D() && (ev.button === 1 || ev.button === 2 || (ev.button === 0 && tool() === "turn"))) {
    inkCanvas.setPointerCapture(ev.pointerId);
    orbiting = [ev.clientX, ev.clientY];
    return;
  }
  if (ev.button !== 0 || !latest) return;
  inkCanvas.setPointerCapture(ev.pointerId);
  const c = fluidCentroid();
  if (is3D()) { // the plane facing the camera through the fluid's centroid, moved along the view by the slider
    const n = renderer.camera.forward(), off = Number($("depth").value) || 0;
    plane = { normal: n, point: [c[0] + off * n[0], c[1] + off * n[1], c[2] + off * n[2]] };
  } else plane = { normal: [0, 0, 1], point: [0, 0, session && session.dim === 3 ? c[2] : 0] };
  drawing = true; stroke = [];
  const p = toWorld(ev.clientX, ev.clientY);
  if (p) stroke.push(p);
  drawInk(true);
});
inkCanvas.addEventListener("pointermove", (ev) => {
  if (dragTool.active) { dragTool.move(ev); return; }
  if (palette.gesture) { palette.move(ev); return; }
  if (orbiting) {
    renderer.camera.orbit(ev.clientX - orbiting[0], ev.clientY - orbiting[1]);
    orbiting = [ev.clientX, ev.clientY]; dirty = true;
  } else if (drawing) { addSamples(ev); drawInk(true); }
});
const endStroke = (ev) => {
  if (palette.gesture) { if (ev.type === "pointerup") palette.release(ev); else palette.gesture = null; return; }
  if (dragTool.active) { dragTool.release(ev); return; }
  if (orbiting) { orbiting = null; return; }
  if (!drawing) return;
  drawing = false; addSamples(ev); stroke = simplify(stroke, MAX_POINTS);
  setApplied(null);
};
inkCanvas.addEventListener("pointerup", endStroke);
inkCanvas.addEventListener("pointercancel", endStroke);
inkCanvas.addEventListener("wheel", (ev) => {
  if (!is3D()) return;
  ev.preventDefault();
  renderer.camera.zoom(ev.deltaY); dirty = true;
}, { passive: false });

async function applySketch() {
  if (!session || stroke.length < 2) { setStatus("draw an arrow or an oval first"); return; }
  const frames = Number($("frames").value);
  if (!Number.isInteger(frames) || frames < 1 || frames > 1000) { setStatus("frames: the control horizon must be an integer in [1, 1000]"); return; }
  const kind = tool() === "oval" ? "oval" : "arrow";
  const body = { sketch: sketchBody(kind, stroke, session.dim), method: $("method").value, frames };
  hook.lastSketch = body.sketch;
  const xy = body.sketch.points, span = Math.hypot(xy.at(-1)[0] - xy[0][0], xy.at(-1)[1] - xy[0][1]);
  const len3 = Math.hypot(...[0, 1, 2].map((d) => stroke.at(-1)[d] - stroke[0][d]));
  setApplied({ kind, stroke, plan: null, id: null, frames, running: true });
  stroke = [];
  $("apply").disabled = true;
  setStatus(`applying ${body.method}…${is3D() && kind === "arrow" && span < 0.5 * len3 ? " (the controller follows the x–y part of a 3D sketch: turn the camera toward the front for more)" : ""}`);
  try {
    const res = await api("POST", `/v1/sessions/${session.id}/controls`, body);
    hook.controls.push(res);
    if (applied) {
      applied.id = res.id; applied.running = false;
      if (!applied.plan && res.plan) applied.plan = res.plan;
      setApplied(applied);
    }
    if (res.sketch_png) { $("sketchpng").src = `data:image/png;base64,${res.sketch_png}`; $("sketchpng").hidden = false; }
    $("dl-control").href = res.trajectory; $("dl-control").hidden = false;
    const d = res.metrics.centroid_displacement || [];
    setStatus(`done: ${res.frames} controlled frames, centroid moved (${d.map((x) => x.toFixed(3)).join(", ")}) m; first frame after ${res.first_frame_ms.toFixed(0)} ms${playing ? "" : "; paused (press play to go on)"}`);
  } catch (e) {
    setStatus(`control refused: ${e.message}`);
    hook.controls.push({ error: e.message });
    setApplied(null);
  } finally { $("apply").disabled = false; }
}

// ---------------------------------------------------------------- take-away: a GIF of the last frames
async function makeGif() {
  const n = Number($("gif-n").value);
  if (!Number.isInteger(n) || n < 2 || n > HISTORY) { setStatus(`gif frames: must be an integer in [2, ${HISTORY}]`); return; }
  const frames = history.slice(-n);
  if (frames.length < 2) { setStatus("gif frames: fewer than 2 frames received yet; play the simulation first"); return; }
  $("gif").disabled = true;
  if (quality) quality.hold(true); // its long draws say nothing of the page's frame rate
  try {
    const tmp = document.createElement("canvas");
    tmp.width = tmp.height = GIF_SIZE;
    const ctx = tmp.getContext("2d");
    const images = [];
    drawInk(true);
    for (let i = 0; i < frames.length; i++) {
      renderer.setFrame(frames[i]);
      ctx.putImageData(new ImageData(renderer.snapshot(GIF_SIZE, GIF_SIZE), GIF_SIZE, GIF_SIZE), 0, 0);
      ctx.drawImage(inkCanvas, 0, 0, GIF_SIZE, GIF_SIZE);
      images.push(ctx.getImageData(0, 0, GIF_SIZE, GIF_SIZE).data);
      if (i % 8 === 0) { setStatus(`GIF: drawing frame ${i + 1} of ${frames.length}…`); await new Promise((r) => setTimeout(r, 0)); }
    }
    fresh = dirty = true;
    const dt = (frames.at(-1).time - frames[0].time) / (frames.length - 1);
    const delay = Math.max(2, Math.min(50, Math.round(dt * 100) || 4)); // real time, within what viewers show
    const bytes = await encodeGif(images, GIF_SIZE, GIF_SIZE, delay, async (i) => {
      if (i % 8 === 0) { setStatus(`GIF: encoding frame ${i + 1} of ${frames.length}…`); await new Promise((r) => setTimeout(r, 0)); }
    });
    const url = URL.createObjectURL(new Blob([bytes], { type: "image/gif" }));
    const a = document.createElement("a");
    a.href = url; a.download = `${session.scene}-seed${session.seed}-frames${frames[0].frame}-${frames.at(-1).frame}.gif`;
    document.body.appendChild(a); a.click(); a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
    hook.gif = { frames: frames.length, bytes: bytes.length, delay };
    setStatus(`GIF of ${frames.length} frames (${(bytes.length / 1024).toFixed(0)} KiB) saved`);
  } catch (e) {
    setStatus(`GIF failed: ${e.message}`);
    hook.errors.push(String(e));
  } finally { $("gif").disabled = false; if (quality) quality.hold(false); }
}

// ---------------------------------------------------------------- controls
function setLook(look) {
  const want = look === "fluid" && renderer.fluidAvailable ? "fluid" : "particles";
  renderer.look = want; hook.look = want;
  const input = document.querySelector(`input[name=look][value=${want}]`);
  if (input) input.checked = true;
  dirty = true;
}
for (const input of document.querySelectorAll("input[name=look]")) input.addEventListener("change", () => setLook(input.value));
if (!renderer.fluidAvailable) document.querySelector("input[name=look][value=fluid]").disabled = true;
setLook(renderer.fluidAvailable ? "fluid" : "particles");
$("r-view").textContent = renderer.kind === "webgl2"
  ? `WebGL2${renderer.software ? ", software GL" : ""}${renderer.fluidAvailable ? "" : " (no float targets: particles)"}` : "Canvas2D (no WebGL2)";
$("r-view").title = renderer.gpu || "";
// The quality (quality.js): auto, or a level the user fixes. `?quality=auto|1…` presets it; `?scale=1|0.75|0.5` fixes
// the highest level drawn at that resolution.
let quality = null;
function showQuality() {
  if (!quality) return;
  const l = LEVELS[quality.level];
  $("r-quality").textContent = `${quality.describe()} · ${l.label}`;
  $("r-quality").title = `${quality.fps.toFixed(1)} frames/s drawable (last measurement); ${quality.changes.length} changes`;
}
if (renderer.kind === "webgl2") {
  const sel = $("quality");
  for (let i = LEVELS.length - 1; i >= 0; i--) {
    const o = document.createElement("option");
    o.value = String(i + 1); o.textContent = `${i + 1}: ${LEVELS[i].label}`;
    sel.appendChild(o);
  }
  const q = params.get("quality"), scale = Number(params.get("scale"));
  const asked = q && /^[0-9]+$/.test(q) && Number(q) >= 1 && Number(q) <= LEVELS.length ? Number(q) - 1 : null;
  const fixed = asked !== null ? asked : [0.5, 0.75, 1].includes(scale) ? levelForScale(scale) : null;
  const start = fixed !== null ? fixed : renderer.software ? SOFTWARE_START : LEVELS.length - 1;
  quality = new QualityController((l) => {
    renderer.scale = l.scale; renderer.lod = l.lod; renderer.fluidFactor = l.fluid; renderer.blurTaps = l.taps;
    dirty = true; showQuality();
  }, start, fixed === null);
  sel.value = fixed === null ? "auto" : String(fixed + 1);
  sel.addEventListener("change", () => {
    if (sel.value === "auto") quality.setAuto(true); else quality.fix(Number(sel.value) - 1);
    showQuality();
  });
  document.addEventListener("visibilitychange", () => quality.hold(document.hidden)); // no frames while hidden
} else $("quality-label").hidden = true;
Object.defineProperty(hook, "quality", { enumerable: true, get: () => (quality ? quality.state() : null) });

$("apply").addEventListener("click", applySketch);
$("clear").addEventListener("click", () => { stroke = []; setApplied(null); });
$("gif").addEventListener("click", makeGif);
$("view-reset").addEventListener("click", () => { renderer.camera.reset(); dirty = true; });
$("new").addEventListener("click", newSession);
$("scene").addEventListener("change", () => { syncSolvers(); newSession(); });
$("play").addEventListener("click", () => {
  playing = !playing;
  $("play").textContent = playing ? "pause" : "play";
  if (ws && ws.readyState === 1) ws.send(JSON.stringify({ type: playing ? "play" : "pause" }));
});
$("reset").addEventListener("click", () => { setApplied(null); if (ws && ws.readyState === 1) ws.send(JSON.stringify({ type: "reset" })); });
window.addEventListener("resize", () => { dirty = true; });
$("play").textContent = playing ? "pause" : "play";

requestAnimationFrame(render);
loadScenes().then(() => (params.get("session") ? joinSession(params.get("session")) : newSession())).catch((e) => setStatus(`could not load scenes: ${e.message}`));
