// The frame stream, read in a worker: the WebSocket is drained as fast as frames come, whatever the page is
// doing, and only the latest frame is kept (latest wins); the page asks for one ("next") when it has taken the
// last, so frames never queue behind a busy page. JSON events pass through at once. Classic worker, no imports.
let ws = null, latest = null, wanted = false;
function flush() {
  if (!wanted || !latest) return;
  const frame = latest;
  latest = null; wanted = false;
  postMessage({ type: "frame", data: frame }, [frame]);
}
onmessage = (ev) => {
  const m = ev.data;
  if (m.type === "open") {
    ws = new WebSocket(m.url);
    ws.binaryType = "arraybuffer";
    ws.onopen = () => postMessage({ type: "open" });
    ws.onmessage = (e) => {
      if (typeof e.data === "string") postMessage({ type: "event", data: e.data });
      else { latest = e.data; flush(); }
    };
    ws.onclose = (e) => postMessage({ type: "close", code: e.code, reason: e.reason });
  } else if (m.type === "send") {
    if (ws && ws.readyState === 1) ws.send(m.data);
  } else if (m.type === "next") {
    wanted = true; flush();
  } else if (m.type === "close") {
    if (ws) { ws.onclose = null; ws.close(); }
    close();
  }
};
