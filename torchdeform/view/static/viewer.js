// torchdeform viewer: renders the body's surface with three.js, updated over a WebSocket.
//
// The socket lives in a worker (socket-worker.js): big frames arrive while this thread renders; each
// animation frame asks it for the newest one.
// Server -> page (see torchdeform/view/server.py and session.py):
//   a "mesh" JSON message: surface ("embedded" smooth label surfaces, the "lattice" surface, or
//     "bodies": the lattice surfaces of several bodies), vertices V, faces, colors (3 per vertex, sRGB
//     0-255: the solid texture at the rest positions, or each body's colour), bounds, tissue terms, tool
//     radius, tools: [{name, vertices (own frame, m), faces, smooth, color}], and optionally parts:
//     [{name, vertices, triangles}] (several bodies: one mesh drawn per part, its vertices and triangles
//     consecutive in that order) and commands (the accepted ones; the others' controls are hidden);
//   binary frames, float32 little endian: V * 3 vertex positions in metres (axis order D, H, W), then
//     12 values per tool: its position c (m) and rotation R (row-major), a tool vertex p at c + R p;
//   "stats" JSON;
//   with a camera in the mesh message ({kind, tool, size: [h, w], fov}): endoscope images, binary, a 16-byte
//     header (uint32 magic 0x7FC44E45, uint16 h, uint16 w, float32 t, uint32 sequence) then h * w RGB
//     bytes, rows from the top; the socket worker tells them from frames by the magic. They are drawn in
//     the round pane at the bottom right, hidden when the scene has no camera.
// Page -> server: {"cmd": play|pause|reset|drag|release|tool|cut|term|fps, ...} JSON messages.
// Library axes (D, H, W) are shown as three.js (y, z, x): D (gravity's axis) is up; the mapping is a
// cyclic permutation (a rotation), so the triangles keep their winding.
// The lattice surface (of each piece, after cuts) is closed with outward (counter-clockwise) faces, so
// only its front faces are drawn; embedded surfaces are drawn two-sided (a cut opens them). Vertex
// normals are recomputed each frame (smooth shading), the tissue is Phong-shaded with a specular
// highlight (wet), the tools steel-grey. Where drawing is slow (software WebGL, a busy laptop) the page
// lowers its drawing resolution, down to half, to keep 30 frames a second, and raises it again when it can.
import * as THREE from "./three.module.min.js";

const token = new URLSearchParams(location.search).get("token") || "";
const $ = (id) => document.getElementById(id);
const canvas = $("view");

// ------------------------------------------------------------------ exposed for tests
const stats = { fps: 0, resolution: 1, framesReceived: 0, framesShown: 0, framesSkipped: 0, lastStats: null, meshVersion: null, vertices: 0,
                surface: null, colored: false, tools: [], parts: [], connected: false, sent: 0, mode: "drag",
                endoscope: { tool: null, size: null, received: 0, shown: 0, t: null },
                ms: { normals: 0, render: 0, frame: 0, message: 0 } };
window.viewerStats = stats;

// ------------------------------------------------------------------ scene
const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
const nativeRatio = Math.min(window.devicePixelRatio || 1, 2);
renderer.setPixelRatio(nativeRatio);
renderer.setClearColor(0x1e2227, 1);
const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(40, 1, 1e-4, 100);
scene.add(new THREE.HemisphereLight(0xffffff, 0x404048, 1.4));
const sun = new THREE.DirectionalLight(0xffffff, 2.2);
scene.add(sun);
scene.add(sun.target);

// library (d, h, w) -> three (x, y, z) = (w, d, h)
const LIB_TO_WORLD = new THREE.Matrix4().set(0, 0, 1, 0,
                                             1, 0, 0, 0,
                                             0, 1, 0, 0,
                                             0, 0, 0, 1);
const toWorld = (p) => new THREE.Vector3(p[2], p[0], p[1]);
const toLib = (v) => [v.y, v.z, v.x];

const body = new THREE.Group();          // holds the surface in library coordinates
body.matrixAutoUpdate = false;
body.matrix.copy(LIB_TO_WORLD);
scene.add(body);
// tissue: the texture's colours per vertex (one colour where a server sends none) and a wet highlight,
// white of weight 0.3 as in the animation (Color(r, g, b) takes linear values); tools: steel, 0.5
const WET = new THREE.Color(0.3, 0.3, 0.3), STEEL_SHINE = new THREE.Color(0.5, 0.5, 0.5);
const material = new THREE.MeshPhongMaterial({ color: 0xffffff, specular: WET, shininess: 40,
                                               side: THREE.FrontSide, vertexColors: true });
const plainMaterial = new THREE.MeshPhongMaterial({ color: 0xc4736b, specular: WET, shininess: 40,
                                                    side: THREE.FrontSide });
let surface = null;                      // THREE.Mesh, geometry in library coordinates
let partMeshes = [];                     // several bodies: one THREE.Mesh per body, sharing surface's attributes
let positionsDirty = false;
let toolMeshes = [];                     // THREE.Mesh per scene tool, in library coordinates, posed per frame

// sRGB byte -> linear (three.js renders in linear space and encodes sRGB on output)
const SRGB_TO_LINEAR = new Float32Array(256).map((_, i) => new THREE.Color().setRGB(i / 255, 0, 0,
                                                                                 THREE.SRGBColorSpace).r);

const toolMaterial = new THREE.MeshLambertMaterial({ color: 0x8fc1ff, transparent: true, opacity: 0.45,
                                                     depthWrite: false });
const toolSphere = new THREE.Mesh(new THREE.SphereGeometry(1, 24, 16), toolMaterial);
toolSphere.visible = false;
scene.add(toolSphere);
const strokeGeometry = new THREE.BufferGeometry().setAttribute("position",
  new THREE.BufferAttribute(new Float32Array(6), 3));
const stroke = new THREE.Line(strokeGeometry, new THREE.LineBasicMaterial({ color: 0xffe066, depthTest: false }));
stroke.visible = false;
stroke.renderOrder = 10;
scene.add(stroke);

// orbit camera around `orbit.target`
const orbit = { target: new THREE.Vector3(), radius: 0.1, theta: 0.7, phi: 1.1, size: 0.05 };
let framed = false;

function placeCamera() {
  const { target, radius, theta, phi } = orbit;
  camera.position.set(target.x + radius * Math.sin(phi) * Math.sin(theta), target.y + radius * Math.cos(phi),
                      target.z + radius * Math.sin(phi) * Math.cos(theta));
  camera.near = Math.max(radius / 1000, 1e-5);
  camera.far = radius * 100;
  camera.updateProjectionMatrix();
  camera.lookAt(target);
  sun.position.copy(camera.position).add(new THREE.Vector3(0, orbit.size * 2, 0));
  sun.target.position.copy(target);
}

function resize() {
  const w = window.innerWidth, h = window.innerHeight;
  renderer.setSize(w, h, false);
  camera.aspect = w / Math.max(h, 1);
  camera.updateProjectionMatrix();
}
window.addEventListener("resize", resize);
resize();
placeCamera();

// Area-weighted vertex normals in one pass over typed arrays (three's computeVertexNormals makes
// vector objects per face: about 5 ms for a 32^3 body's 48,000 faces, this about 1 ms).
function vertexNormals(geometry) {
  const p = geometry.getAttribute("position").array, f = geometry.getIndex().array;
  let attr = geometry.getAttribute("normal");
  if (!attr || attr.count * 3 !== p.length) {
    attr = new THREE.BufferAttribute(new Float32Array(p.length), 3).setUsage(THREE.DynamicDrawUsage);
    geometry.setAttribute("normal", attr);
  }
  const n = attr.array;
  n.fill(0);
  for (let k = 0; k < f.length; k += 3) {
    const a = 3 * f[k], b = 3 * f[k + 1], c = 3 * f[k + 2];
    const ux = p[b] - p[a], uy = p[b + 1] - p[a + 1], uz = p[b + 2] - p[a + 2];
    const vx = p[c] - p[a], vy = p[c + 1] - p[a + 1], vz = p[c + 2] - p[a + 2];
    const nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;   // twice the area
    n[a] += nx; n[a + 1] += ny; n[a + 2] += nz;
    n[b] += nx; n[b + 1] += ny; n[b + 2] += nz;
    n[c] += nx; n[c + 1] += ny; n[c + 2] += nz;
  }
  for (let i = 0; i < n.length; i += 3) {
    const len = Math.hypot(n[i], n[i + 1], n[i + 2]) || 1;
    n[i] /= len; n[i + 1] /= len; n[i + 2] /= len;
  }
  attr.needsUpdate = true;
}

// ------------------------------------------------------------------ messages from the server
let toolRadius = 0.002;

function onMesh(msg) {
  const V = msg.vertices | 0;
  const geometry = new THREE.BufferGeometry();
  const old = surface ? surface.geometry.getAttribute("position") : null;
  const pos = new Float32Array(V * 3);
  if (old && old.count === V) pos.set(old.array);
  geometry.setAttribute("position", new THREE.BufferAttribute(pos, 3).setUsage(THREE.DynamicDrawUsage));
  geometry.setIndex(new THREE.BufferAttribute(Uint32Array.from(msg.faces), 1));
  const colored = Array.isArray(msg.colors) && msg.colors.length === 3 * V;
  if (colored) {
    const rgb = new Float32Array(3 * V);
    for (let i = 0; i < rgb.length; i++) rgb[i] = SRGB_TO_LINEAR[msg.colors[i] & 255];
    geometry.setAttribute("color", new THREE.BufferAttribute(rgb, 3));
  }
  if (surface) {
    body.remove(surface);
    surface.geometry.dispose();
  }
  for (const m of partMeshes) {
    body.remove(m);
    m.geometry.dispose();
  }
  const side = msg.surface === "embedded" ? THREE.DoubleSide : THREE.FrontSide;
  for (const m of [material, plainMaterial]) if (m.side !== side) { m.side = side; m.needsUpdate = true; }
  surface = new THREE.Mesh(geometry, colored ? material : plainMaterial);
  partMeshes = buildParts(msg, geometry, colored ? material : plainMaterial);
  if (!partMeshes.length) body.add(surface);   // else the parts draw it, body by body
  positionsDirty = !!(old && old.count === V);
  stats.meshVersion = msg.version;
  stats.vertices = V;
  stats.surface = msg.surface || "lattice";
  stats.colored = colored;
  stats.parts = partMeshes.map((m) => m.name);
  showCommands(msg.commands || null);
  buildTools(msg.tools || []);
  toolRadius = msg.tool_radius || toolRadius;
  toolSphere.scale.setScalar(toolRadius);
  const lo = toWorld(msg.bounds[0]), hi = toWorld(msg.bounds[1]);
  const size = Math.max(hi.clone().sub(lo).length(), 1e-4);
  if (!framed) {
    orbit.target.copy(lo).add(hi).multiplyScalar(0.5);
    orbit.size = size;
    orbit.radius = 1.6 * size / Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)) / 2;
    framed = true;
    placeCamera();
  }
  buildTerms(msg.terms || {});
  showEndoscope(msg.camera || null);
}

// ------------------------------------------------------------------ the endoscope pane
const scopeCanvas = $("scope-view");
const scopeContext = scopeCanvas.getContext("2d");
let scopePixels = null;                  // ImageData of the pane's size, reused

function showEndoscope(camera) {
  const size = camera && Array.isArray(camera.size) ? camera.size.map((v) => v | 0) : null;
  $("scope").hidden = !size;
  stats.endoscope.tool = size ? String(camera.tool) : null;
  stats.endoscope.size = size;
  if (!size) return;
  $("scope-name").textContent = `endoscope: ${camera.tool}`;
  if (scopeCanvas.height !== size[0] || scopeCanvas.width !== size[1]) {
    scopeCanvas.height = size[0];
    scopeCanvas.width = size[1];
  }
  if (!scopePixels || scopePixels.height !== size[0] || scopePixels.width !== size[1]) {
    scopePixels = scopeContext.createImageData(size[1], size[0]);
  }
}

function onEndoscope(buffer) {
  stats.endoscope.received++;
  const header = new DataView(buffer);
  const h = header.getUint16(4, true), w = header.getUint16(6, true);
  if (!scopePixels || h !== scopePixels.height || w !== scopePixels.width || buffer.byteLength !== 16 + 3 * h * w) {
    return;                              // not this scene's camera (an older message): skip it
  }
  const rgb = new Uint8Array(buffer, 16), rgba = scopePixels.data;
  for (let i = 0, j = 0; i < rgb.length; i += 3, j += 4) {
    rgba[j] = rgb[i];
    rgba[j + 1] = rgb[i + 1];
    rgba[j + 2] = rgb[i + 2];
    rgba[j + 3] = 255;
  }
  scopeContext.putImageData(scopePixels, 0, 0);
  stats.endoscope.shown++;
  stats.endoscope.t = header.getFloat32(8, true);
}

// several bodies: one mesh per part (body), each with its own triangles; the positions, normals and
// colours are the whole surface's attributes, shared, so a frame updates them once for all
function buildParts(msg, geometry, mat) {
  const parts = Array.isArray(msg.parts) ? msg.parts : [];
  if (!parts.length || !parts.every((p) => Number.isInteger(p.triangles))) return [];
  vertexNormals(geometry);               // the shared normal attribute
  const faces = geometry.getIndex().array;
  let first = 0;
  return parts.map((p) => {
    const g = new THREE.BufferGeometry();
    for (const name of ["position", "normal", "color"]) {
      const a = geometry.getAttribute(name);
      if (a) g.setAttribute(name, a);
    }
    g.setIndex(new THREE.BufferAttribute(faces.slice(3 * first, 3 * (first + p.triangles)), 1));
    first += p.triangles;
    const mesh = new THREE.Mesh(g, mat);
    mesh.name = String(p.name);
    mesh.frustumCulled = false;          // its bounds move with the frames
    body.add(mesh);
    return mesh;
  });
}

// the controls of the commands the server accepts (null: all); several bodies: play, pause, reset
function showCommands(commands) {
  const modes = ["drag", "tool", "cut"];
  const allowed = commands === null ? modes : modes.filter((m) => commands.includes(m));
  $("mode-drag").parentElement.style.display = allowed.length ? "" : "none";
  for (const m of modes) $(`mode-${m}`).style.display = allowed.includes(m) ? "" : "none";
  if (!allowed.includes(stats.mode)) stats.mode = allowed.length ? allowed[0] : "none";
  $("help").textContent = allowed.length ? HELP
    : "Several bodies: play, pause and reset; the scene's tools follow their paths. Right- or left-drag: orbit. Wheel: zoom.";
}
const HELP = $("help").textContent;

// the scene's tools: steel, shiny; smooth (a sphere, a capsule) or flat (a box, a mesh's edges)
function buildTools(tools) {
  for (const m of toolMeshes) {
    body.remove(m);
    m.geometry.dispose();
    m.material.dispose();
  }
  toolMeshes = tools.map((t) => {
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(Float32Array.from(t.vertices), 3));
    geometry.setIndex(new THREE.BufferAttribute(Uint32Array.from(t.faces), 1));
    geometry.computeVertexNormals();
    const c = t.color || [0.6, 0.6, 0.6];          // the server sends the animation's steel
    const mesh = new THREE.Mesh(geometry, new THREE.MeshPhongMaterial({
      color: new THREE.Color().setRGB(c[0], c[1], c[2], THREE.SRGBColorSpace), specular: STEEL_SHINE,
      shininess: 60, flatShading: !t.smooth }));
    mesh.name = t.name;
    mesh.matrixAutoUpdate = false;
    mesh.visible = false;                // until a frame gives its pose
    body.add(mesh);
    return mesh;
  });
  stats.tools = tools.map((t) => t.name);
}

function onFrame(buffer) {
  const V = stats.vertices, T = toolMeshes.length;
  if (!surface || buffer.byteLength !== 4 * (3 * V + 12 * T)) {     // a frame of an older mesh
    stats.framesSkipped++;
    return;
  }
  stats.framesShown++;
  const t0 = performance.now();
  const data = new Float32Array(buffer);
  surface.geometry.getAttribute("position").array.set(data.subarray(0, 3 * V));
  for (let k = 0; k < T; k++) {
    const p = data.subarray(3 * V + 12 * k, 3 * V + 12 * (k + 1));   // c (3), R (9, row-major)
    const m = toolMeshes[k];
    m.matrix.set(p[3], p[4], p[5], p[0],
                 p[6], p[7], p[8], p[1],
                 p[9], p[10], p[11], p[2],
                 0, 0, 0, 1);
    m.matrixWorldNeedsUpdate = true;
    m.visible = true;
  }
  stats.ms.message = 0.9 * stats.ms.message + 0.1 * (performance.now() - t0);
  positionsDirty = true;
}

const fmt = (v, digits) => (typeof v === "number" && isFinite(v) ? v.toFixed(digits) : "-");

function onStats(msg) {
  stats.lastStats = msg;
  $("time").textContent = fmt(msg.t, 3);
  $("simhz").textContent = fmt(msg.sim_hz, 0);
  $("force").textContent = fmt(msg.force, 4);
  $("springs").textContent = msg.springs ?? "-";
  $("play").classList.toggle("active", !!msg.playing);
  $("pause").classList.toggle("active", !msg.playing);
}

// ------------------------------------------------------------------ the socket (in a worker)
const socket = new Worker("/static/socket-worker.js");
let asked = false;       // a frame was asked of the worker and has not come yet

function send(msg) {
  if (stats.connected) {
    socket.postMessage({ type: "send", text: JSON.stringify(msg) });
    stats.sent++;
  }
}

socket.onmessage = (ev) => {
  const m = ev.data;
  if (m.type === "frame") {
    asked = false;
    stats.framesReceived = m.received;
    onFrame(m.buffer);
  } else if (m.type === "endoscope") {
    onEndoscope(m.buffer);
  } else if (m.type === "text") {
    let msg;
    try { msg = JSON.parse(m.text); } catch (e) { return; }
    if (msg.type === "mesh") onMesh(msg);
    else if (msg.type === "stats") onStats(msg);
  } else if (m.type === "open") {
    stats.connected = true;
    $("status").textContent = "";
  } else if (m.type === "close") {
    stats.connected = false;
    $("status").textContent = "disconnected: retrying...";
  }
};
const scheme = location.protocol === "https:" ? "wss" : "ws";
socket.postMessage({ type: "connect", url: `${scheme}://${location.host}/ws?token=${encodeURIComponent(token)}` });

// ------------------------------------------------------------------ controls
$("play").onclick = () => send({ cmd: "play" });
$("pause").onclick = () => send({ cmd: "pause" });
$("reset").onclick = () => send({ cmd: "reset" });
for (const mode of ["drag", "tool", "cut"]) {
  $(`mode-${mode}`).onclick = () => {
    stats.mode = mode;
    for (const m of ["drag", "tool", "cut"]) $(`mode-${m}`).classList.toggle("active", m === mode);
    toolSphere.visible = false;
  };
}

let termsKey = "";
function buildTerms(terms) {
  const key = JSON.stringify(Object.keys(terms).map((k) => [k, terms[k].min, terms[k].max]));
  if (key === termsKey) return;
  termsKey = key;
  const box = $("terms");
  box.textContent = "";
  for (const [name, t] of Object.entries(terms)) {
    const label = document.createElement("label");
    const value = document.createElement("span");
    value.textContent = fmt(t.value, 2);
    label.append(`${name} `, value);
    const input = document.createElement("input");
    Object.assign(input, { type: "range", id: `term-${name}`, min: t.min, max: t.max,
                           step: (t.max - t.min) / 200, value: t.value });
    input.oninput = () => {
      value.textContent = fmt(Number(input.value), 2);
      send({ cmd: "term", name, value: Number(input.value) });
    };
    label.append(input);
    box.append(label);
  }
}

// ------------------------------------------------------------------ the mouse
const raycaster = new THREE.Raycaster();
const ndc = new THREE.Vector2();

function ray(ev) {
  const r = canvas.getBoundingClientRect();
  ndc.set(((ev.clientX - r.left) / r.width) * 2 - 1, -((ev.clientY - r.top) / r.height) * 2 + 1);
  raycaster.setFromCamera(ndc, camera);
  return raycaster.ray;
}

function pick(ev) {
  if (!surface) return null;
  ray(ev);
  surface.geometry.computeBoundingSphere();
  const hits = raycaster.intersectObject(surface, false);
  return hits.length ? hits[0] : null;
}

function viewDirection() {
  return camera.getWorldDirection(new THREE.Vector3());
}

function facingPlane(point) {
  return new THREE.Plane().setFromNormalAndCoplanarPoint(viewDirection(), point);
}

function onPlane(ev, plane) {
  return ray(ev).intersectPlane(plane, new THREE.Vector3());
}

function vertexWorld(i) {
  const a = surface.geometry.getAttribute("position");
  return new THREE.Vector3(a.getX(i), a.getY(i), a.getZ(i)).applyMatrix4(LIB_TO_WORLD);
}

let gesture = null;      // what the pressed mouse is doing
let pending = null;      // the latest drag/tool command, sent once per animation frame

canvas.addEventListener("contextmenu", (ev) => ev.preventDefault());
canvas.addEventListener("pointerdown", (ev) => {
  canvas.setPointerCapture(ev.pointerId);
  if (ev.button === 2 || ev.shiftKey || stats.mode === "none") {
    gesture = { kind: "orbit", x: ev.clientX, y: ev.clientY };
    return;
  }
  if (ev.button !== 0 || !surface) return;
  if (stats.mode === "drag") {
    const hit = pick(ev);
    if (!hit) return;
    const face = hit.face;
    let best = face.a, bestD = Infinity;
    for (const i of [face.a, face.b, face.c]) {
      const d = vertexWorld(i).distanceToSquared(hit.point);
      if (d < bestD) { bestD = d; best = i; }
    }
    gesture = { kind: "drag", vertex: best, start: hit.point.clone(), origin: vertexWorld(best),
                plane: facingPlane(hit.point) };
  } else if (stats.mode === "tool") {
    const hit = pick(ev);
    const point = hit ? hit.point.clone() : onPlane(ev, facingPlane(orbit.target));
    if (!point) return;
    gesture = { kind: "tool", plane: facingPlane(point), since: performance.now(), point };
    toolAt(ev);
  } else if (stats.mode === "cut") {
    const hit = pick(ev);
    const start = hit ? hit.point.clone() : onPlane(ev, facingPlane(orbit.target));
    if (!start) return;
    gesture = { kind: "cut", start, end: start.clone(), plane: facingPlane(start) };
    strokeLine(start, start);
    stroke.visible = true;
  }
});

canvas.addEventListener("pointermove", (ev) => {
  if (!gesture) {
    if (stats.mode === "tool") hover(ev);
    return;
  }
  if (gesture.kind === "orbit") {
    orbit.theta -= (ev.clientX - gesture.x) * 0.01;
    orbit.phi = Math.min(Math.max(orbit.phi - (ev.clientY - gesture.y) * 0.01, 0.05), Math.PI - 0.05);
    gesture.x = ev.clientX;
    gesture.y = ev.clientY;
    placeCamera();
  } else if (gesture.kind === "drag") {
    const p = onPlane(ev, gesture.plane);
    if (!p) return;
    const target = gesture.origin.clone().add(p.sub(gesture.start));
    pending = { cmd: "drag", vertex: gesture.vertex, target: toLib(target) };
  } else if (gesture.kind === "tool") {
    const p = onPlane(ev, gesture.plane);
    if (p) gesture.point = p;
    toolAt(ev);
  } else if (gesture.kind === "cut") {
    const p = onPlane(ev, gesture.plane);
    if (p) gesture.end = p;
    strokeLine(gesture.start, gesture.end);
  }
});

function endGesture(ev) {
  if (!gesture) return;
  const g = gesture;
  gesture = null;
  if (g.kind === "drag") {
    pending = null;
    send({ cmd: "release" });
  } else if (g.kind === "tool") {
    pending = null;
    toolSphere.visible = false;
    send({ cmd: "tool", position: null });
  } else if (g.kind === "cut") {
    stroke.visible = false;
    const u = g.end.clone().sub(g.start);
    if (u.length() > 1e-6) {
      const dir = viewDirection();
      const depth = orbit.size;
      const origin = g.start.clone().addScaledVector(dir, -depth);
      send({ cmd: "cut", origin: toLib(origin), u: toLib(u), v: toLib(dir.multiplyScalar(2 * depth)) });
    }
  }
}
canvas.addEventListener("pointerup", endGesture);
canvas.addEventListener("pointercancel", endGesture);

canvas.addEventListener("wheel", (ev) => {
  ev.preventDefault();
  orbit.radius *= Math.exp(Math.sign(ev.deltaY) * 0.1);
  placeCamera();
}, { passive: false });

// tool: hovering shows the sphere touching the surface; pressing pushes it in along the view,
// one radius deeper over 0.4 s, while the mouse moves it on the plane through the pressed point
function hover(ev) {
  const hit = pick(ev);
  toolSphere.visible = !!hit;
  if (hit) toolSphere.position.copy(hit.point).addScaledVector(viewDirection(), -toolRadius);
}

function toolAt(ev) {
  if (!gesture || gesture.kind !== "tool") return;
  const push = Math.min((performance.now() - gesture.since) / 400, 1);
  const centre = gesture.point.clone().addScaledVector(viewDirection(), toolRadius * (2 * push - 1));
  toolSphere.position.copy(centre);
  toolSphere.visible = true;
  pending = { cmd: "tool", position: toLib(centre) };
}

function strokeLine(a, b) {
  const arr = strokeGeometry.getAttribute("position");
  arr.setXYZ(0, a.x, a.y, a.z);
  arr.setXYZ(1, b.x, b.y, b.z);
  arr.needsUpdate = true;
  strokeGeometry.computeBoundingSphere();
}

// ------------------------------------------------------------------ the frame loop
const RESOLUTION = { low: 33, high: 50, min: 0.5, step: 0.8 };   // fps band, smallest scale, factor

function adaptResolution(fps) {
  let scale = stats.resolution;
  if (fps < RESOLUTION.low && scale > RESOLUTION.min) scale = Math.max(RESOLUTION.min, scale * RESOLUTION.step);
  else if (fps > RESOLUTION.high && scale < 1) scale = Math.min(1, scale / RESOLUTION.step);
  if (scale === stats.resolution) return;
  stats.resolution = scale;
  renderer.setPixelRatio(nativeRatio * scale);
  resize();
  $("resolution").textContent = (scale * 100).toFixed(0);
}

let counted = 0, since = performance.now(), lastNow = since;

function frame(now) {
  requestAnimationFrame(frame);
  if (!asked) {
    asked = true;
    socket.postMessage({ type: "want" });
  }
  if (gesture && gesture.kind === "tool") toolAt(null);
  if (pending) {
    send(pending);
    pending = null;
  }
  const t0 = performance.now();
  if (surface && positionsDirty) {
    surface.geometry.getAttribute("position").needsUpdate = true;
    vertexNormals(surface.geometry);
    positionsDirty = false;
  }
  const t1 = performance.now();
  renderer.render(scene, camera);
  const t2 = performance.now();
  stats.ms.normals = 0.9 * stats.ms.normals + 0.1 * (t1 - t0);
  stats.ms.render = 0.9 * stats.ms.render + 0.1 * (t2 - t1);
  stats.ms.frame = 0.9 * stats.ms.frame + 0.1 * (now - lastNow);
  lastNow = now;
  counted++;
  if (now - since >= 1000) {
    stats.fps = (counted * 1000) / (now - since);
    counted = 0;
    since = now;
    $("fps").textContent = stats.fps.toFixed(0);
    adaptResolution(stats.fps);
    send({ cmd: "fps", value: Math.round(stats.fps * 10) / 10 });
  }
}
requestAnimationFrame(frame);
