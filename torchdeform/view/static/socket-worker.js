// torchdeform viewer: the WebSocket, in a worker so that big binary frames arrive while the page's
// main thread renders. Text messages (mesh, stats) are passed on in order; of the binary frames
// only the latest is kept, handed over (transferred, not copied) when the page asks for one.
// Frames are pulled: the worker asks the server for one ({"cmd": "next"}) on opening and each time
// it hands one to the page, so the server sends about as many frames as the page draws.
//
// Endoscope images (binary too, their first four bytes the uint32 0x7FC44E45, little endian: as float32
// a NaN, which no frame starts with) are handed over as they come: the server sends at most ~10 a second.
//
// page -> worker: {type: "connect", url}, {type: "send", text}, {type: "want"}
// worker -> page: {type: "open"}, {type: "close"}, {type: "text", text}, {type: "frame", buffer, received},
//                 {type: "endoscope", buffer}
let ws = null;
let url = null;
let latest = null;       // the newest frame not yet handed over (older ones are dropped: never stale)
let wanted = false;      // the page asked for a frame and none was there
let received = 0;

const NEXT = JSON.stringify({ cmd: "next" });
const ENDOSCOPE_MAGIC = 0x7FC44E45;
const ENDOSCOPE_HEADER = 16;

function isEndoscope(buffer) {
  return buffer.byteLength >= ENDOSCOPE_HEADER && new DataView(buffer).getUint32(0, true) === ENDOSCOPE_MAGIC;
}

function handOver() {
  postMessage({ type: "frame", buffer: latest, received }, [latest]);
  latest = null;
  wanted = false;
  if (ws && ws.readyState === WebSocket.OPEN) ws.send(NEXT);
}

function connect() {
  ws = new WebSocket(url);
  ws.binaryType = "arraybuffer";
  ws.onopen = () => {
    postMessage({ type: "open" });
    ws.send(NEXT);
  };
  ws.onmessage = (ev) => {
    if (typeof ev.data === "string") {
      postMessage({ type: "text", text: ev.data });
      return;
    }
    if (isEndoscope(ev.data)) {
      postMessage({ type: "endoscope", buffer: ev.data }, [ev.data]);
      return;
    }
    received++;
    latest = ev.data;
    if (wanted) handOver();
  };
  ws.onclose = () => {
    postMessage({ type: "close" });
    setTimeout(connect, 1000);
  };
}

onmessage = (ev) => {
  const m = ev.data;
  if (m.type === "connect" && url === null) {
    url = m.url;
    connect();
  } else if (m.type === "send") {
    if (ws && ws.readyState === WebSocket.OPEN) ws.send(m.text);
  } else if (m.type === "want") {
    if (latest) handOver();
    else wanted = true;
  }
};
