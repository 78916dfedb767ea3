// hybridmpm page: live particles over a binary WebSocket, sketches with mouse or pen.
// No build step, no CDN. Test hook: window.__hmpm.

const HEADER_BYTES = 32;
const COLORS = {
  5: ["#1f5fd1", "#19b5c9"], // water: [MPM, network]
  6: ["#b8862e", "#e3c44a"], // sand
  3: ["#6b7280", "#6b7280"], // static boundary
};
const MAX_POINTS = 512;

const hook = (window.__hmpm = {
  framesReceived: 0, framesRendered: 0, lastDrawMs: 0, drawMs: [], controls: [], errors: [],
  session: null, status: "", lastFrame: -1, lastSketch: null,
});
window.addEventListener("error", (e) => hook.errors.push(String(e.message || e)));
window.addEventListener("unhandledrejection", (e) => hook.errors.push(String(e.reason)));

const $ = (id) => document.getElementById(id);
const simCanvas = $("sim"), inkCanvas = $("ink");
const sim2d = simCanvas.getContext("2d"), ink2d = inkCanvas.getContext("2d");
const params = new URLSearchParams(location.search);

let session = null, ws = null, playing = params.get("autoplay") !== "0";
let latest = null;           // {frame, n, dim, solver, controlled, pos}
let dirty = false;
let stroke = [];             // domain points of the current sketch
let drawing = false;
const recentSolvers = [];    // 1 = network, last 200 frames
let lastArrival = 0, interval = 0;

function setStatus(text) { hook.status = text; $("status").textContent = text; }

// ---------------------------------------------------------------- coordinates (the one place)
// CSS pixels of an element -> backing pixels (devicePixelRatio) and domain <-> CSS pixels,
// with the y axis flipped exactly here: the canvas grows downwards, the domain upwards.
function bounds() { return session ? session.bounds : [[0, 0], [1, 1]]; }
function fitCanvas(c, ctx) {
  const r = c.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(r.width * dpr)), h = Math.max(1, Math.round(r.height * dpr));
  if (c.width !== w || c.height !== h) { c.width = w; c.height = h; }
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0); // draw in CSS pixels
  return r;
}
function toDomain(clientX, clientY) {
  const r = inkCanvas.getBoundingClientRect(), [lo, hi] = bounds();
  const u = (clientX - r.left) / r.width, v = (clientY - r.top) / r.height;
  return [lo[0] + u * (hi[0] - lo[0]), lo[1] + (1 - v) * (hi[1] - lo[1])];
}
function toCss(x, y, r) {
  const [lo, hi] = bounds();
  return [((x - lo[0]) / (hi[0] - lo[0])) * r.width, (1 - (y - lo[1]) / (hi[1] - lo[1])) * r.height];
}

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

// the solvers each scene offers (a scene without a shipped model: MPM only)
const sceneSolvers = {};
async function loadScenes() {
  const scenes = await api("GET", "/v1/scenes");
  const sel = $("scene");
  for (const s of scenes) {
    const o = document.createElement("option");
    o.value = s.name; o.textContent = `${s.name} (${s.dim}D)${s.model ? "" : ", MPM only"}`;
    sel.appendChild(o);
    sceneSolvers[s.name] = s.solvers;
  }
  sel.value = params.get("scene") || "water2d";
  $("seed").value = params.get("seed") || "0";
  $("solver").value = params.get("solver") || "hybrid";
  if (params.get("method")) $("method").value = params.get("method");
  syncSolvers();
}

// offer only the scene's solvers; a solver it lacks falls back to its first (MPM)
function syncSolvers() {
  const allowed = sceneSolvers[$("scene").value] || [];
  const sel = $("solver");
  for (const o of sel.options) o.disabled = allowed.length > 0 && !allowed.includes(o.value);
  if (allowed.length > 0 && !allowed.includes(sel.value)) sel.value = allowed[0];
}

async function newSession() {
  closeStream();
  if (session) { api("DELETE", `/v1/sessions/${session.id}`).catch(() => {}); }
  session = null; latest = null; hook.session = null; $("apply").disabled = true;
  setStatus("creating session…");
  try {
    session = await api("POST", "/v1/sessions", {
      scene: $("scene").value, seed: Number($("seed").value) || 0, solver: $("solver").value,
    });
  } catch (e) { setStatus(`could not create a session: ${e.message}`); return; }
  hook.session = session;
  $("r-n").textContent = `${session.num_fluid} fluid + ${session.num_particles - session.num_fluid} boundary`;
  $("apply").disabled = false;
  openStream();
}

// ---------------------------------------------------------------- stream
function closeStream() { if (ws) { ws.onclose = null; ws.close(); ws = null; } }
function openStream() {
  const proto = location.protocol === "https:" ? "wss" : "ws";
  ws = new WebSocket(`${proto}://${location.host}${session.stream}`);
  ws.binaryType = "arraybuffer";
  ws.onopen = () => { setStatus("streaming"); if (playing) ws.send(JSON.stringify({ type: "play" })); };
  ws.onmessage = (ev) => (typeof ev.data === "string" ? onEvent(JSON.parse(ev.data)) : onFrame(ev.data));
  ws.onclose = (ev) => setStatus(ev.code === 4000 ? "session expired: start a new one" : `stream closed (${ev.code} ${ev.reason})`);
}
function onEvent(msg) {
  if (msg.type === "control") setStatus(msg.status === "running" ? `control ${msg.method} running…` : "control done; the simulation continues");
  else if (msg.type === "error") setStatus(msg.message);
}
function onFrame(buf) {
  const dv = new DataView(buf);
  const dim = dv.getUint8(6), frame = dv.getUint32(8, true), n = dv.getUint32(12, true);
  const solver = dv.getUint8(24), controlled = dv.getUint8(25);
  if (buf.byteLength < HEADER_BYTES + n * dim * 4) return;
  latest = { frame, n, dim, solver, controlled, pos: new Float32Array(buf, HEADER_BYTES, n * dim) };
  hook.framesReceived += 1; hook.lastFrame = frame;
  const now = performance.now();
  if (lastArrival) interval = 0.9 * interval + 0.1 * (now - lastArrival);
  lastArrival = now;
  recentSolvers.push(solver); if (recentSolvers.length > 200) recentSolvers.shift();
  dirty = true;
}

// ---------------------------------------------------------------- drawing
function render() {
  requestAnimationFrame(render);
  if (!dirty || !latest || !session) return;
  dirty = false;
  const t0 = performance.now();
  const r = fitCanvas(simCanvas, sim2d);
  sim2d.fillStyle = "#ffffff"; sim2d.fillRect(0, 0, r.width, r.height);
  const { n, dim, pos, solver } = latest, types = session.particle_type;
  const s = Math.max(1.5, r.width / 256);
  for (const t of [3, 5, 6]) {
    sim2d.fillStyle = (COLORS[t] || COLORS[5])[solver ? 1 : 0];
    for (let i = 0; i < n; i++) {
      if (types[i] !== t) continue;
      const [cx, cy] = toCss(pos[i * dim], pos[i * dim + 1], r); // 3D: x–y view
      sim2d.fillRect(cx - s / 2, cy - s / 2, s, s);
    }
  }
  hook.lastDrawMs = performance.now() - t0; hook.drawMs.push(hook.lastDrawMs); if (hook.drawMs.length > 100) hook.drawMs.shift();
  hook.framesRendered += 1;
  $("r-frame").textContent = `${latest.frame}${latest.controlled ? " (controlled)" : ""}`;
  $("r-latency").textContent = `${interval.toFixed(1)} ms`;
  $("r-draw").textContent = `${hook.lastDrawMs.toFixed(1)} ms`;
  const share = recentSolvers.reduce((a, b) => a + b, 0) / Math.max(1, recentSolvers.length);
  $("r-share").textContent = `${(100 * share).toFixed(0)} %`;
}

function tool() { return document.querySelector("input[name=tool]:checked").value; }
function redrawInk() {
  const r = fitCanvas(inkCanvas, ink2d);
  ink2d.clearRect(0, 0, r.width, r.height);
  if (stroke.length < 2) return;
  ink2d.strokeStyle = "#d1245a"; ink2d.lineWidth = 3; ink2d.lineJoin = ink2d.lineCap = "round";
  ink2d.beginPath();
  stroke.forEach(([x, y], i) => { const [px, py] = toCss(x, y, r); if (i) ink2d.lineTo(px, py); else ink2d.moveTo(px, py); });
  if (tool() === "oval") ink2d.closePath();
  ink2d.stroke();
  if (tool() === "arrow") {
    const [ax, ay] = toCss(...stroke[stroke.length - 2], r), [bx, by] = toCss(...stroke[stroke.length - 1], r);
    const ang = Math.atan2(by - ay, bx - ax);
    ink2d.beginPath(); ink2d.moveTo(bx, by);
    ink2d.lineTo(bx - 14 * Math.cos(ang - 0.4), by - 14 * Math.sin(ang - 0.4));
    ink2d.lineTo(bx - 14 * Math.cos(ang + 0.4), by - 14 * Math.sin(ang + 0.4));
    ink2d.closePath(); ink2d.fillStyle = "#d1245a"; ink2d.fill();
  }
}
function addSamples(ev) {
  const evs = typeof ev.getCoalescedEvents === "function" ? ev.getCoalescedEvents() : []; // secure contexts only
  for (const e of evs.length ? evs : [ev]) stroke.push(toDomain(e.clientX, e.clientY));
}
inkCanvas.addEventListener("pointerdown", (ev) => {
  if (ev.button !== 0) return;
  inkCanvas.setPointerCapture(ev.pointerId);
  drawing = true; stroke = [toDomain(ev.clientX, ev.clientY)]; redrawInk();
});
inkCanvas.addEventListener("pointermove", (ev) => { if (drawing) { addSamples(ev); redrawInk(); } });
const endStroke = (ev) => { if (!drawing) return; drawing = false; addSamples(ev); stroke = simplify(stroke, MAX_POINTS); redrawInk(); };
inkCanvas.addEventListener("pointerup", endStroke);
inkCanvas.addEventListener("pointercancel", endStroke);

// Ramer–Douglas–Peucker, then uniform thinning, to at most `max` points.
function simplify(pts, max) {
  if (pts.length <= 2) return pts;
  const keep = new Uint8Array(pts.length); keep[0] = keep[pts.length - 1] = 1;
  const eps = 1e-3, stack = [[0, pts.length - 1]];
  while (stack.length) {
    const [a, b] = stack.pop();
    const [ax, ay] = pts[a], [bx, by] = pts[b], dx = bx - ax, dy = by - ay, len = Math.hypot(dx, dy) || 1e-12;
    let best = -1, bi = -1;
    for (let i = a + 1; i < b; i++) {
      const d = Math.abs(dy * (pts[i][0] - ax) - dx * (pts[i][1] - ay)) / len;
      if (d > best) { best = d; bi = i; }
    }
    if (best > eps) { keep[bi] = 1; stack.push([a, bi], [bi, b]); }
  }
  let out = pts.filter((_, i) => keep[i]);
  if (out.length > max) { const step = (out.length - 1) / (max - 1); out = Array.from({ length: max }, (_, i) => out[Math.round(i * step)]); }
  return out;
}

async function applySketch() {
  if (!session || stroke.length < 2) { setStatus("draw an arrow or an oval first"); return; }
  const body = { sketch: { kind: tool(), points: stroke.map(([x, y]) => [x, y]) }, method: $("method").value };
  hook.lastSketch = body.sketch;
  $("apply").disabled = true;
  setStatus(`applying ${body.method}…`);
  try {
    const res = await api("POST", `/v1/sessions/${session.id}/controls`, body);
    hook.controls.push(res);
    if (res.sketch_png) { $("sketchpng").src = `data:image/png;base64,${res.sketch_png}`; $("sketchpng").hidden = false; }
    const d = res.metrics.centroid_displacement || [];
    setStatus(`done: ${res.frames} controlled frames, centroid moved (${d.map((x) => x.toFixed(3)).join(", ")}) m; first frame after ${res.first_frame_ms.toFixed(0)} ms`);
    stroke = []; redrawInk();
  } catch (e) {
    setStatus(`control refused: ${e.message}`);
    hook.controls.push({ error: e.message });
  } finally { $("apply").disabled = false; }
}

// ---------------------------------------------------------------- controls
$("apply").addEventListener("click", applySketch);
$("clear").addEventListener("click", () => { stroke = []; redrawInk(); });
$("new").addEventListener("click", newSession);
$("scene").addEventListener("change", () => { syncSolvers(); newSession(); });
$("play").addEventListener("click", () => {
  playing = !playing;
  $("play").textContent = playing ? "pause" : "play";
  if (ws && ws.readyState === 1) ws.send(JSON.stringify({ type: playing ? "play" : "pause" }));
});
$("reset").addEventListener("click", () => { if (ws && ws.readyState === 1) ws.send(JSON.stringify({ type: "reset" })); });
window.addEventListener("resize", () => { dirty = true; redrawInk(); });
$("play").textContent = playing ? "pause" : "play";

requestAnimationFrame(render);
loadScenes().then(newSession).catch((e) => setStatus(`could not load scenes: ${e.message}`));
