// The session's frames on the page: the stream's worker (stream.js) seen from the page, and a binary frame read
// (service/frames.py: a 32-byte header, float32 positions [n, dim], then the rigid bodies' poses, bodies.js).

import { readBodies } from "./bodies.js";

const HEADER_BYTES = 32;
const FLAG_REALTIME = 16; // flags bit4: a real-time session's frame; the u16 at byte 26 is its real-time factor × 1000

// The WebSocket lives in a worker (stream.js) that keeps only the latest frame and hands it over when the page
// asks. Read here, frames the page was too busy to take queued in the browser: a page drawing 2 frames/s
// showed frames hundreds behind the server's (a paused session seemed to jump when it moved again).
// on: {frame(buf) a binary frame, event(msg) a JSON event, error(text) the worker failed}
export class FrameStream {
  constructor(url, on) {
    this.readyState = 0; this.onopen = null; this.onclose = null;
    this.worker = new Worker("/static/stream.js");
    this.worker.onmessage = (ev) => {
      const m = ev.data;
      if (m.type === "frame") { this.worker.postMessage({ type: "next" }); on.frame(m.data); }
      else if (m.type === "event") on.event(JSON.parse(m.data));
      else if (m.type === "open") { this.readyState = 1; this.worker.postMessage({ type: "next" }); if (this.onopen) this.onopen(); }
      else if (m.type === "close") { this.readyState = 3; if (this.onclose) this.onclose(m); }
    };
    this.worker.onerror = (e) => on.error(`stream worker: ${e.message}`);
    this.worker.postMessage({ type: "open", url });
  }
  send(text) { this.worker.postMessage({ type: "send", data: text }); }
  close() { this.readyState = 3; this.worker.onmessage = null; this.worker.postMessage({ type: "close" }); } // nothing more from it
}

// A binary frame: {frame, n, dim, solver, controlled, cframe, time, realtimeFactor, pos, bodies}, or null when it is
// shorter than its header says. realtimeFactor: simulated over wall time of a real-time session's frames (flag bit4),
// null when the frame is not a real-time session's or its session has not measured it yet (0 in the header)
export function readFrame(buf) {
  const dv = new DataView(buf);
  const dim = dv.getUint8(6), flags = dv.getUint8(7), frame = dv.getUint32(8, true), n = dv.getUint32(12, true);
  const time = dv.getFloat64(16, true), solver = dv.getUint8(24), controlled = dv.getUint8(25), cframe = dv.getUint32(28, true);
  const rt = flags & FLAG_REALTIME ? dv.getUint16(26, true) : 0;
  if (buf.byteLength < HEADER_BYTES + n * dim * 4) return null;
  return {
    frame, n, dim, solver, controlled, cframe, time, realtimeFactor: rt > 0 ? rt / 1000 : null,
    pos: new Float32Array(buf, HEADER_BYTES, n * dim), bodies: readBodies(buf, n, dim),
  };
}
