// The viewer page's code (manifoldneus/output/viewer.py inlines it). Reads the JSON in #scene-data: the
// mesh (base64 typed arrays), per round the cameras' frusta (apex + 4 image corners, world frame),
// the GT and pycolmap reference frusta, and per round each view's error against GT. It draws on
// demand (no animation loop) and, once drawn, writes what it drew onto <html data-*> for tests.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

const data = JSON.parse(document.getElementById("scene-data").textContent);
const root = document.documentElement;
const COLOURS = {
  anchor: new THREE.Color(0xff9f1c), held: new THREE.Color(0xe056fd), gt: new THREE.Color(0xf0f0f0),
  error: new THREE.Color(0xff4d4d), reference: new THREE.Color(0x3ec1d3), other: new THREE.Color(0x8a8f99),
};
const nRounds = Math.max(1, ...data.cameras.map((c) => c.round));

function decode(b64, Type) {
  const text = atob(b64);
  const bytes = new Uint8Array(text.length);
  for (let i = 0; i < text.length; i++) bytes[i] = text.charCodeAt(i);
  return new Type(bytes.buffer);
}

function roleColour(camera) {
  if (camera.role === "held out") return COLOURS.held;
  if (camera.role === "anchor") return COLOURS.anchor;
  if (camera.role.startsWith("round")) {  // successor rounds: blue (first) to green (last)
    return new THREE.Color().setHSL(0.62 - 0.3 * (camera.round - 1) / Math.max(1, nRounds - 1), 0.75, 0.58);
  }
  return COLOURS.other;
}

// ---------------------------------------------------------------- scene

const container = document.getElementById("view");
// Without WebGL (disabled, blocked, an old GPU driver) say so on the page rather than show an empty panel.
const probe = document.createElement("canvas");
if (!(probe.getContext("webgl2") || probe.getContext("webgl"))) {
  document.getElementById("panel").hidden = true;
  document.getElementById("no-webgl").hidden = false;
  root.dataset.viewerState = "no-webgl";
  throw new Error("WebGL is not available: the viewer cannot draw");
}
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.setSize(window.innerWidth, window.innerHeight);
renderer.setClearColor(0x1e2127);
container.appendChild(renderer.domElement);
const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(40, window.innerWidth / window.innerHeight, 0.01, 100);
scene.add(camera);
scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 1.6));
const headlight = new THREE.DirectionalLight(0xffffff, 1.6);
headlight.position.set(0.3, 0.5, 1);
camera.add(headlight);  // lights the side the user looks at

function meshObject(m) {
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(decode(m.positions, Float32Array), 3));
  geometry.setIndex(new THREE.BufferAttribute(decode(m.indices, Uint32Array), 1));
  if (m.colours) geometry.setAttribute("color", new THREE.BufferAttribute(decode(m.colours, Uint8Array), 3, true));
  geometry.computeVertexNormals();
  geometry.computeBoundingSphere();
  const material = new THREE.MeshLambertMaterial({
    vertexColors: Boolean(m.colours), color: m.colours ? 0xffffff : 0xb8bcc6, side: THREE.DoubleSide });
  return new THREE.Mesh(geometry, material);
}

// Line segments of frusta: apex to each corner, and the image rectangle; one colour per frustum.
function frustaObject(frusta, colours) {
  const pos = [], col = [];
  frusta.forEach((f, k) => {
    const p = (i) => [f[3 * i], f[3 * i + 1], f[3 * i + 2]];
    const edges = [[0, 1], [0, 2], [0, 3], [0, 4], [1, 2], [2, 3], [3, 4], [4, 1]];
    for (const [a, b] of edges) {
      pos.push(...p(a), ...p(b));
      col.push(...colours[k].toArray(), ...colours[k].toArray());
    }
    // a filled tick above the top edge marks the image's up
    const top = [0, 1, 2].map((d) => (f[3 + d] + f[6 + d]) / 2);
    const mid = [0, 1, 2].map((d) => (f[3 + d] + f[6 + d] + f[9 + d] + f[12 + d]) / 4);
    const tip = [0, 1, 2].map((d) => top[d] + 0.35 * (top[d] - mid[d]));
    pos.push(...p(1), ...tip, ...tip, ...p(2));
    for (let i = 0; i < 4; i++) col.push(...colours[k].toArray());
  });
  return lineObject(pos, col);
}

function lineObject(pos, col) {
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.Float32BufferAttribute(pos, 3));
  geometry.setAttribute("color", new THREE.Float32BufferAttribute(col, 3));
  return new THREE.LineSegments(geometry, new THREE.LineBasicMaterial({ vertexColors: true }));
}

function pointsObject(ref) {
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(decode(ref.points, Float32Array), 3));
  geometry.setAttribute("color", new THREE.BufferAttribute(decode(ref.colours, Uint8Array), 3, true));
  return new THREE.Points(geometry, new THREE.PointsMaterial({ size: 2, sizeAttenuation: false, vertexColors: true }));
}

const mesh = data.mesh.n_faces > 0 ? meshObject(data.mesh) : null;
if (mesh) scene.add(mesh);
const layers = { estimated: null, gt: null, held: null, reference: null, points: null };
const held = data.cameras.filter((c) => c.role === "held out" && data.gt);
if (held.length) {
  layers.held = frustaObject(held.map((c) => data.gt.frusta[c.view]), held.map(() => COLOURS.held));
  scene.add(layers.held);
}
if (data.reference) {
  const views = data.cameras.filter((c) => data.reference.frusta[c.view]);
  layers.reference = frustaObject(views.map((c) => data.reference.frusta[c.view]), views.map(() => COLOURS.reference));
  layers.points = pointsObject(data.reference);
  scene.add(layers.reference, layers.points);
}

// The cameras of one round: its posed views' frusta, and their GT frusta with a line to each.
function showRound(r) {
  for (const key of ["estimated", "gt"]) {
    if (!layers[key]) continue;
    scene.remove(layers[key]);
    layers[key].traverse((object) => { if (object.geometry) object.geometry.dispose(); });
  }
  const round = data.rounds[r];
  const posed = data.cameras.filter((c) => round.frusta[c.view]);
  layers.estimated = frustaObject(posed.map((c) => round.frusta[c.view]), posed.map(roleColour));
  scene.add(layers.estimated);
  if (data.gt) {
    const gtObject = frustaObject(posed.map((c) => data.gt.frusta[c.view]), posed.map(() => COLOURS.gt));
    const pos = [], col = [];
    for (const c of posed) {
      pos.push(...round.frusta[c.view].slice(0, 3), ...data.gt.frusta[c.view].slice(0, 3));
      col.push(...COLOURS.error.toArray(), ...COLOURS.error.toArray());
    }
    layers.gt = new THREE.Group();
    layers.gt.add(gtObject, lineObject(pos, col));
    scene.add(layers.gt);
  }
  document.getElementById("round-label").textContent = round.label;
  document.getElementById("round-count").textContent = `(${posed.length} cameras)`;
  applyToggles();
  root.dataset.round = round.label;
  root.dataset.camerasDrawn = String(posed.length);
}

// ---------------------------------------------------------------- view and controls

// The panel covers the left of the window: the view's centre is moved to the middle of what is left.
const panel = document.getElementById("panel");
function freeArea() {
  const cover = window.innerWidth >= 640 ? panel.offsetWidth + 20 : 0;
  camera.setViewOffset(window.innerWidth, window.innerHeight, -cover / 2, 0, window.innerWidth, window.innerHeight);
  // the half-angle the free area subtends: vertically, and horizontally over the uncovered width
  const half = THREE.MathUtils.degToRad(camera.fov / 2);
  const horizontal = Math.atan(Math.tan(half) * (window.innerWidth - cover) / window.innerHeight);
  return Math.min(half, horizontal);
}

// Look at a sphere (centre, radius) from direction `look` with image-up `up`, filling `fill` of the free area.
function frame(centre, radius, look, up, fill) {
  camera.up.copy(up);
  const distance = radius / fill / Math.sin(freeArea());
  camera.position.copy(centre).add(look.clone().normalize().multiplyScalar(distance));
  camera.near = distance / 100;
  camera.far = distance * 10;
  camera.updateProjectionMatrix();
  controls.target.copy(centre);
  controls.update();
}

// Reset: every camera and the mesh in view, seen from the cameras' side, their image-up up.
function fitView() {
  const final = data.rounds[data.rounds.length - 1];
  const frusta = final.frusta.filter(Boolean);
  const centre = mesh ? mesh.geometry.boundingSphere.center.clone() : new THREE.Vector3();
  const apex = (f) => new THREE.Vector3(f[0], f[1], f[2]);
  if (!mesh && frusta.length) frusta.forEach((f) => centre.add(apex(f).divideScalar(frusta.length)));
  // up: the mean of the cameras' image-up directions (top edge minus bottom edge)
  const up = new THREE.Vector3();
  const look = new THREE.Vector3();
  for (const f of frusta) {
    up.add(new THREE.Vector3(f[3] + f[6] - f[9] - f[12], f[4] + f[7] - f[10] - f[13], f[5] + f[8] - f[11] - f[14]));
    look.add(apex(f).sub(centre));
  }
  let radius = mesh ? mesh.geometry.boundingSphere.radius : 1;
  for (const f of frusta) radius = Math.max(radius, apex(f).distanceTo(centre));
  if (look.lengthSq() === 0) look.set(0, 0, 1);
  if (up.lengthSq() === 0) up.set(0, 1, 0);
  frame(centre, radius, look, up.normalize(), 1 / 0.75);  // margin: near cameras project wider
  root.dataset.view = "all";
}

// Fit to object: the mesh fills the free area, seen from where the user looks now.
function fitObject() {
  if (!mesh) return fitView();
  const sphere = mesh.geometry.boundingSphere;
  frame(sphere.center.clone(), sphere.radius, camera.position.clone().sub(controls.target), camera.up.clone(), 0.9);
  root.dataset.view = "object";
}

const controls = new OrbitControls(camera, renderer.domElement);
controls.addEventListener("change", render);

function render() {
  renderer.render(scene, camera);
}

const toggles = { "show-mesh": () => mesh, "show-held": () => layers.held, "show-gt": () => layers.gt,
                  "show-ref": () => layers.reference, "show-points": () => layers.points };
function applyToggles() {
  for (const [id, object] of Object.entries(toggles)) {
    const box = document.getElementById(id);
    box.disabled = !object();
    if (object()) object().visible = box.checked;
  }
}
for (const id of Object.keys(toggles)) document.getElementById(id).addEventListener("change", () => { applyToggles(); render(); });

const slider = document.getElementById("round");
slider.max = String(data.rounds.length - 1);
slider.value = slider.max;
slider.addEventListener("input", () => { showRound(Number(slider.value)); render(); });

// Hover: the camera whose centre is drawn nearest the pointer (within 12 px) tells its error.
const tip = document.getElementById("tip");
function describe(c) {
  const round = data.rounds[Number(slider.value)];
  const lines = [`view ${c.name}: ${c.role === "anchor" ? "anchor" : c.role}`];
  if (c.role === "held out") lines.push("held out of training: drawn at its ground-truth pose");
  const err = round.errors && round.errors[c.view];
  if (err) {
    lines.push(`after ${round.label}: rotation ${err[0].toFixed(3)} deg, centre ${err[1].toPrecision(3)} ${data.frame.units}`);
    lines.push("against ground truth (white; red line)");
  }
  return lines.join("\n");
}
renderer.domElement.addEventListener("pointermove", (event) => {
  const round = data.rounds[Number(slider.value)];
  const rect = renderer.domElement.getBoundingClientRect();
  let best = null, bestDistance = 12;
  for (const c of data.cameras) {
    const f = round.frusta[c.view] || (c.role === "held out" && data.gt && layers.held.visible ? data.gt.frusta[c.view] : null);
    if (!f) continue;
    const p = new THREE.Vector3(f[0], f[1], f[2]).project(camera);
    const dx = (p.x + 1) / 2 * rect.width - (event.clientX - rect.left);
    const dy = (1 - p.y) / 2 * rect.height - (event.clientY - rect.top);
    const d = Math.hypot(dx, dy);
    if (p.z < 1 && d < bestDistance) { best = c; bestDistance = d; }
  }
  tip.style.display = best ? "block" : "none";
  if (best) {
    tip.textContent = describe(best);
    tip.style.left = `${event.clientX + 14}px`;
    tip.style.top = `${event.clientY + 10}px`;
  }
});

window.addEventListener("resize", () => {
  camera.aspect = window.innerWidth / window.innerHeight;
  freeArea();
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight);
  render();
});
document.getElementById("fit-object").addEventListener("click", () => { fitObject(); render(); });
document.getElementById("reset-view").addEventListener("click", () => { fitView(); render(); });
window.addEventListener("keydown", (event) => {
  if (event.target.tagName === "INPUT") return;
  if (event.key === "f") { fitObject(); render(); }
  if (event.key === "r") { fitView(); render(); }
});

// ---------------------------------------------------------------- panel

document.getElementById("title").textContent = data.title;
document.getElementById("frame").textContent = `frame: ${data.frame.frame} (${data.frame.units})`;
document.getElementById("frame").title = data.frame.how;
const counts = data.counts;
document.getElementById("counts").textContent =
  `${counts.views} views: ${counts.optimised} optimised, ${counts.held_out} held out` +
  (data.reference ? `; pycolmap registered ${data.reference.n_registered}` : "");
document.getElementById("mesh-size").textContent = data.mesh.n_faces === data.mesh.n_faces_full
  ? `(${data.mesh.n_faces} triangles)` : `(${data.mesh.n_faces} of ${data.mesh.n_faces_full} triangles)`;
const legend = [["anchors", COLOURS.anchor]];
for (let r = 1; r <= nRounds; r++) {
  if (data.cameras.some((c) => c.round === r && c.role !== "held out")) legend.push([`round ${r}`, roleColour({ role: "round", round: r })]);
}
legend.push(["held out", COLOURS.held]);
if (data.gt) legend.push(["ground truth", COLOURS.gt], ["error", COLOURS.error]);
if (data.reference) legend.push(["pycolmap", COLOURS.reference]);
document.getElementById("legend").innerHTML = legend.map(([name, colour]) =>
  `<span style="white-space: nowrap; margin-right: 8px"><span class="swatch" style="background: #${colour.getHexString()}"></span>${name}</span>`).join(" ");

showRound(data.rounds.length - 1);
fitView();
if (window.location.hash === "#view=object") fitObject();  // a link that opens fitted to the object
render();
root.dataset.heldOutDrawn = String(held.length);
root.dataset.meshTriangles = String(mesh ? data.mesh.n_faces : 0);
root.dataset.referenceCameras = String(data.reference ? data.reference.n_registered : 0);
root.dataset.viewerState = "ready";
