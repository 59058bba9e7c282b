// The PlenOctree viewer page: loads the tree named by ?tree= or config.json, packs it into
// textures, renders on demand, wires the controls, and exposes `window.viewer` for scripts.
// Every failure ends in a visible message (never a blank canvas).
// Two ways to draw (frames.js): WebGL2 in the page, or, where the server offers it (config.json
// "cpu": `plenoctree view --render cpu|auto`) and the browser has only software WebGL, frames
// drawn by the server's CPU renderer. The frame loop never waits for the GPU: a fence tells
// when a WebGL frame is done (no synchronous read-back).

import { NpzArchive, FormatError, fetchBuffer, toBase64 } from "./npz.js";
import { packTree, LimitError } from "./tree.js";
import { Renderer, GLError } from "./renderer.js";
import { OrbitCamera, UP, applyHeldKeys, isMoveKey } from "./camera.js";
import { drawFrustums } from "./overlay.js";
import { probeRay, lumisphere, treeRay } from "./probe.js";
import { MeshPass, parseObj, parseGlb, toSceneUp } from "./mesh.js";
import { detectGL, glRendererName, FrameStats, CpuFrames, FrameError, markWebglOnly } from "./frames.js";
import { GlFrames } from "./glframes.js";
import { startLive, restoreLiveCamera } from "./live.js";

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const canvas = $("canvas");

const opts = {
  stop_thresh: 0.01, step_eps: 1e-6, background: [1, 1, 1], sh_min: 0, sh_max: -1,
  box_min: [0, 0, 0], box_max: [1, 1, 1], mode: "rgb", depth_range: [0, 1],
};
let config = {};
let renderer = null;
let camera = new OrbitCamera();
let fixedView = null;     // a camera set by a script (setView) replaces the orbit camera
// Resolution scale: a number, or "auto": while the view changes, frames render at a scale
// that keeps them fast (glframes.js, frames.js), then once at full size.
let scaleMode = params.get("scale") || "auto";
let dirty = true;
let lastChange = 0;
// "webgl" or "cpu"; scene: what the camera and controls need of the tree (the packed tree in
// WebGL mode, config.json's "cpu" description in CPU mode)
let drawMode = "webgl";
let scene = null;
let cpu = null;
let glf = null;              // WebGL mode: GlFrames
let rendererLabel = "";
let glInfo = null;           // detectGL(): {webgl2, renderer, software}
const stats = new FrameStats();

function invalidate() {
  dirty = true;
  lastChange = performance.now();
}
let treeName = "";

let resolveReady, rejectReady;
const ready = new Promise((res, rej) => { resolveReady = res; rejectReady = rej; });
ready.catch(() => {});

const api = {
  state: "loading", message: "", notice: "", ready,
  info: () => (scene ? describe(scene) : null),
  limits: () => (renderer ? renderer.limits : null),
  setView(view) { fixedView = view; invalidate(); },
  clearView() { fixedView = null; invalidate(); },
  setOptions(o) { Object.assign(opts, o); syncControls(); invalidate(); },
  options: () => JSON.parse(JSON.stringify(opts)),
  // WebGL: draw now and wait for the GPU (ms). CPU mode: a Promise of the full-resolution
  // frame of the current view on screen (ms from request to screen).
  render() { return drawMode === "cpu" ? cpuDrawNow() : renderOnce(); },
  pixels() {
    return toBase64(drawMode === "cpu" ? canvasPixels() : renderer.readPixels());
  },
  // Median milliseconds per frame over n frames: WebGL, draw + wait for the GPU (a number);
  // CPU mode, full-resolution frames from request to screen (a Promise of the number).
  benchmark(n = 10) {
    if (drawMode === "cpu") return cpuBenchmark(n);
    const times = [];
    renderOnce();
    for (let i = 0; i < n; i++) times.push(renderOnce());
    times.sort((a, b) => a - b);
    return times[Math.floor(times.length / 2)];
  },
  camera: () => camera,
  // Who draws: {mode: "webgl"|"cpu", label, software (WebGL is a software renderer)}.
  renderer: () => ({ mode: drawMode, label: rendererLabel, software: Boolean(glInfo && glInfo.software) }),
  // Frames delivered in the last second, the last frame and a log of recent ones
  // ({t: performance.now() on screen, width, height, full, ms: request to screen, ...}).
  stats: () => ({ fps: stats.fps(), last: stats.last || null, log: stats.log }),
  // The interactive camera's view for a width x height target ({c2w row-major, fx, ...}).
  currentView: (w, h) => camera.view(w, h),
  resetView() { resetView(); },
  cameras: () => (config.cameras ? config.cameras.c2w.length : 0),
  jumpToCamera(i) { jumpToCamera(i); },
  setFov(deg) { setFov(deg); },
  dismissMessage() { dismissMessage(); },
  // Radiance probe along a world ray: {leaf, point, sigma, coeffs, weight, image (base64 RGBA
  // size x size lumisphere seen with the current view's rotation)} or null.
  probeRay(origin, dir, size = 128) { return runProbe(origin, dir, size); },
  // Probe the pixel (x, y) of the canvas (CSS pixels from the top-left).
  probe(x, y) { return probePixel(x, y); },
  // Insert a mesh: OBJ text, or GLB bytes as base64 (name ending in .glb).
  addMesh(data, name = "mesh.obj") {
    if (/\.glb$/i.test(name) && typeof data === "string") {
      const bin = atob(data), buf = new Uint8Array(bin.length);
      for (let i = 0; i < bin.length; i++) buf[i] = bin.charCodeAt(i);
      data = buf.buffer;
    }
    return addMesh(data, name);
  },
  clearMeshes() { if (meshPass) meshPass.clear(); invalidate(); },
  // Headlight shading of inserted meshes (mesh.js MESH_AMBIENT); false = unlit colours.
  setMeshShading(on) { meshShading = Boolean(on); $("mesh_shading").checked = meshShading; if (meshPass) meshPass.shading = meshShading; invalidate(); },
};
window.viewer = api;

function setStatus(text) { $("status").textContent = text; }

function showError(err) {
  let title = "Cannot show this tree";
  let hint = "";
  const served = config.tree && treeName === decodeURIComponent(config.tree.split("/").pop());
  const lodHint = (served && config.lod_hint) || `plenoctree lod ${treeName || "TREE"} --target-mb 30 --out ${(treeName || "tree").replace(/\.(npz|plnz)$/, "")}_web.plnz`;
  if (err instanceof LimitError) {
    title = "This tree is too large for this device";
    hint = `Make a smaller tree for the web (lower SH degree, merged or pruned leaves):\n  ${lodHint}`;
  } else if (err instanceof FormatError) {
    title = "This file is not a tree the viewer can read";
  } else if (err instanceof GLError) {
    title = "WebGL problem";
  } else if (err && err.name === "ContextLost") {
    title = "The GPU stopped the viewer";
    hint = `Lower the resolution scale, or use a smaller tree:\n  ${lodHint}`;
  } else {
    title = "Unexpected error";
  }
  if (err && err.title) title = err.title;
  const text = err && err.message ? err.message : String(err);
  $("message-title").textContent = title;
  $("message-text").textContent = text;
  $("message-hint").textContent = hint;
  $("message").hidden = false;
  $("message-close").hidden = !scene;
  setStatus("");
  api.state = "error";
  api.message = `${title}: ${text}${hint ? "\n" + hint : ""}`;
  rejectReady(new Error(api.message));
  console.error(api.message);
}

// Close the message card; the page keeps working with the tree it had (if any).
function dismissMessage() {
  $("message").hidden = true;
  if (scene) {
    api.state = "ready";
    api.message = "";
    invalidate();
  }
}

// ---------------------------------------------------------------- views
let initialView = null;
let meshPass = null;
let meshShading = true;

// Insert a mesh (OBJ text or GLB bytes; world coordinates, GLB +Y up turned onto the scene's
// up axis). Returns {vertices, triangles}.
function addMesh(data, name) {
  if (!renderer) throw new Error("the viewer is not ready");
  const mesh = /\.glb$/i.test(name) || data instanceof ArrayBuffer && new Uint32Array(data.slice(0, 4))[0] === 0x46546c67
    ? toSceneUp(parseGlb(data instanceof ArrayBuffer ? data : new TextEncoder().encode(data).buffer, name), camera.up)
    : parseObj(typeof data === "string" ? data : new TextDecoder().decode(data), name);
  if (!meshPass) { meshPass = new MeshPass(renderer.gl); meshPass.shading = meshShading; }
  meshPass.add(mesh);
  invalidate();
  return { vertices: mesh.positions.length / 3, triangles: mesh.indices.length / 3 };
}

function sceneCenter(t) { return [0, 1, 2].map((i) => (0.5 - t.offset[i]) / t.invradius[i]); }

// Vertical fov (degrees) of training camera i.
function cameraFovY(i) {
  const c = config.cameras;
  const fy = Array.isArray(c.fy) ? c.fy[i] : c.fy;
  return 2 * Math.atan(0.5 * c.height / fy) * 180 / Math.PI;
}

// First view: like the dataset cameras when the bundle has them (camera 0's direction and fov,
// their median distance to the scene centre, their up axis), else the scene's bounding sphere
// (half the box diagonal) fitted into the view with a 5 % margin.
function frameInitialView(t) {
  const center = sceneCenter(t);
  const cams = config.cameras;
  if (config.up && UP[config.up]) camera.up = config.up;
  if (opts.ndc) {
    // forward-facing: the NDC reference camera (identity pose at the origin, looking down -z)
    const n = opts.ndc;
    camera.up = "+y";
    camera.fovY = 2 * Math.atan(0.5 * n.height / n.fy) * 180 / Math.PI;
    camera.lookFrom([0, 0, 0], [0, 0, -1]);
    camera.pose = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];
  } else if (cams && cams.c2w.length) {
    const dists = cams.c2w.map((m) => Math.hypot(m[3] - center[0], m[7] - center[1], m[11] - center[2]));
    dists.sort((a, b) => a - b);
    const median = dists[Math.floor(dists.length / 2)];
    const m = cams.c2w[0];
    const eye = [m[3], m[7], m[11]];
    const v = [eye[0] - center[0], eye[1] - center[1], eye[2] - center[2]];
    const l = Math.hypot(...v) || 1;
    camera.fovY = cameraFovY(0);
    camera.lookFrom(center.map((c, k) => c + v[k] / l * median), center);
  } else {
    const r = Math.hypot(...t.invradius.map((v) => 0.5 / v));
    const aspect = Math.max(canvas.clientWidth, 1) / Math.max(canvas.clientHeight, 1);
    const halfY = 0.5 * camera.fovY * Math.PI / 180;
    const half = Math.min(halfY, Math.atan(Math.tan(halfY) * aspect));
    camera.target = center;
    camera.distance = (config.camera_distance ? config.camera_distance * r : 1.05 * r / Math.sin(half));
    camera.pose = null;
  }
  initialView = camera.state();
  $("fov").value = String(Math.round(camera.fovY));
  $("fov_out").textContent = $("fov").value;
  $("up").value = camera.up;
}

function resetView() {
  if (initialView) camera.setState(initialView);
  fixedView = null;
  $("fov").value = String(Math.round(camera.fovY));
  $("fov_out").textContent = $("fov").value;
  $("up").value = camera.up;
  invalidate();
}

function setFov(deg) {
  const v = Math.max(10, Math.min(120, Number(deg)));
  camera.fovY = v;
  $("fov").value = String(Math.round(v));
  $("fov_out").textContent = $("fov").value;
  invalidate();
}

function jumpToCamera(i) {
  const cams = config.cameras;
  if (!cams || !cams.c2w.length || !scene) return;
  const n = cams.c2w.length;
  i = ((Math.round(i) % n) + n) % n;
  // (NDC trees: orbit about a point 2 near-plane distances in front of the camera)
  const pivot = opts.ndc ? [cams.c2w[i][3] - 2 * cams.c2w[i][2], cams.c2w[i][7] - 2 * cams.c2w[i][6],
    cams.c2w[i][11] - 2 * cams.c2w[i][10]] : sceneCenter(scene);
  camera.setPose(cams.c2w[i], cameraFovY(i), pivot);
  fixedView = null;
  $("camera_select").value = String(i);
  $("fov").value = String(Math.round(camera.fovY));
  $("fov_out").textContent = $("fov").value;
  invalidate();
}

// Frustums of the training cameras on the overlay canvas (see overlay.js).
function drawCameras(view) {
  const show = config.cameras && $("show_cameras").checked && !fixedView;
  drawFrustums($("overlay"), view, show ? config.cameras : null,
    Number($("camera_select").value), treeRadius() * 0.12);
}

// ---------------------------------------------------------------- radiance probe
function runProbe(origin, dir, size = 128) {
  if (!renderer || !renderer.tree) return null;
  const ray = treeRay(origin, dir, opts.ndc);
  if (!ray) return null;
  const hit = probeRay(renderer.tree, ray[0], ray[1]);
  const info = $("probe_info");
  const cv = $("probe_canvas");
  const ctx = cv.getContext("2d");
  ctx.clearRect(0, 0, cv.width, cv.height);
  if (!hit) { info.textContent = "nothing along this ray"; return null; }
  const view = fixedView || camera.view(size, size);
  const img = lumisphere(renderer.tree, hit.coeffs, view.c2w, size);
  const shown = size === cv.width ? img : lumisphere(renderer.tree, hit.coeffs, view.c2w, cv.width);
  ctx.putImageData(new ImageData(shown, cv.width, cv.width), 0, 0);
  info.textContent = `leaf ${hit.leaf} at (${hit.point.map((v) => v.toFixed(3)).join(", ")}), `
    + `sigma ${hit.sigma.toFixed(2)}, weight ${hit.weight.toFixed(2)}; the sphere shows the colour `
    + "seen from each direction (as oriented in the current view)";
  return { leaf: hit.leaf, point: hit.point, sigma: hit.sigma, weight: hit.weight,
    coeffs: hit.coeffs, image: toBase64(img) };
}

function probePixel(x, y) {
  const w = Math.max(1, canvas.clientWidth), h = Math.max(1, canvas.clientHeight);
  const view = fixedView ? { ...fixedView } : camera.view(w, h);
  const sx = view.width / w, sy = view.height / h;
  const m = view.c2w;
  const dc = [(x * sx - view.cx) / view.fx, -(y * sy - view.cy) / view.fy, -1];
  const dir = [0, 1, 2].map((k) => m[4 * k] * dc[0] + m[4 * k + 1] * dc[1] + m[4 * k + 2] * dc[2]);
  $("probe_box").open = true;
  return runProbe([m[3], m[7], m[11]], dir);
}

// ---------------------------------------------------------------- keyboard fly
const held = new Set();
let lastKeyTime = null;
// Advance the held keys by dt seconds (camera.js: fly 0.5 scene radii per second, turn 60°/s).
function applyKeys(dt) {
  if (held.size && scene) applyHeldKeys(camera, held, dt, treeRadius());
}

function onKey(e, down) {
  const tag = (e.target && e.target.tagName) || "";
  if (["INPUT", "SELECT", "TEXTAREA"].includes(tag) && e.target.type !== "checkbox" && e.target.type !== "range") return;
  if (isMoveKey(e.code)) {
    e.preventDefault();
    if (down) held.add(e.code); else held.delete(e.code);
    return;
  }
  if (!down) return;
  if (e.code === "KeyR") resetView();
  else if (e.code === "BracketRight") jumpToCamera(Number($("camera_select").value) + 1);
  else if (e.code === "BracketLeft") jumpToCamera(Number($("camera_select").value) - 1);
  else if (e.key === "?" || e.code === "KeyH") $("hints").hidden = !$("hints").hidden;
  else if (e.code === "Escape") dismissMessage();
}

function describe(t) {
  if (t.cpu) {
    return { file: treeName, format: t.format.name, basis_dim: t.format.basisDim, n_leaves: t.nLeaves,
      max_depth: t.maxDepth, renderer: "cpu" };
  }
  return {
    file: t.fileName, format: t.format.name, basis_dim: t.format.basisDim, compressed: t.compressed,
    bits: t.bits, retain: t.retain, n_nodes: t.nNodes, n_leaves: t.nLeaves, max_depth: t.maxDepth,
    child_texture: [t.child.width, t.child.height, t.child.layers],
    data_texture: [t.data.width, t.data.height, t.data.layers],
    texture_mb: t.textureBytes / 1e6,
  };
}

function targetSize(scale) {
  if (fixedView) return [fixedView.width, fixedView.height];
  const dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(canvas.clientWidth * dpr * scale));
  const h = Math.max(1, Math.round(canvas.clientHeight * dpr * scale));
  return [w, h];
}

// Depth view: world distances around the scene (NDC lengths for NDC trees).
function updateDepthRange() {
  if (opts.ndc) {
    opts.depth_range = [0, 2.5];          // NDC lengths (the cube is 2 deep)
  } else if (!fixedView) {
    const c = camera.target, e = camera.eye();
    const dist = Math.hypot(e[0] - c[0], e[1] - c[1], e[2] - c[2]);
    const r = treeRadius() * Math.sqrt(3);
    opts.depth_range = [Math.max(0, dist - r), dist + r];
  }
}

// Draw and wait for the GPU (scripts: api.render / benchmark, Save PNG): ms.
function renderOnce(scale = scaleMode === "auto" ? 1 : Number(scaleMode)) {
  if (!renderer || !renderer.tree) throw new Error("no tree loaded");
  const ms = glf.renderNow(scale, scaleMode);
  showRate();
  return ms;
}

function treeRadius() {
  const t = scene;
  return Math.max(...t.invradius.map((v) => 0.5 / v));
}

// The corner label: who draws, delivered FPS and the resolution of the last frame.
function showRate() {
  const last = stats.last;
  const text = last ? `${rendererLabel} · ${stats.fps()} FPS @ ${last.width}x${last.height}`
    + ` · ${last.ms.toFixed(0)} ms/frame` : rendererLabel;
  if ($("fps").textContent !== text) $("fps").textContent = text;
}

// ---------------------------------------------------------------- CPU mode
// The current view for CpuFrames.pump (see frames.js).
let overlayKey = "";
function cpuView() {
  const [W, H] = targetSize(1);
  updateDepthRange();
  const full = fixedView || camera.view(W, H);
  const key = JSON.stringify([full, opts.background, opts.stop_thresh, opts.sh_min, opts.sh_max,
    opts.mode, opts.depth_range]);
  if (key !== overlayKey) { overlayKey = key; drawCameras(full); }
  const fixedScale = scaleMode === "auto" ? null : Number(scaleMode);
  const viewAt = (s) => {
    if (fixedView) return fixedView;
    const k = fixedScale || s;
    return camera.view(Math.max(1, Math.round(W * k)), Math.max(1, Math.round(H * k)));
  };
  return { key, viewAt, opts, target: [W, H], fixed: Boolean(fixedView),
    continuous: $("continuous").checked, changedAt: lastChange };
}

function cpuDrawNow() {
  const v = cpuView();
  return cpu.drawNow(v.key, v.viewAt(1), v.opts, v.fixed ? null : v.target);
}

async function cpuBenchmark(n) {
  const times = [];
  await cpuDrawNow();
  for (let i = 0; i < n; i++) times.push(await cpuDrawNow());
  times.sort((a, b) => a - b);
  return times[Math.floor(times.length / 2)];
}

// A frame the server could not draw: a notice that goes away by itself; the page keeps its state and draws again at the next camera change.
let noticeTimer = null;
function showNotice(text) {
  const el = $("notice");
  el.textContent = text;
  el.hidden = false;
  api.notice = text;
  console.warn(text);
  clearTimeout(noticeTimer);
  noticeTimer = setTimeout(() => { el.hidden = true; }, 6000);
}

// RGBA8 pixels of the 2D canvas (CPU mode), rows top to bottom.
function canvasPixels() {
  const ctx = canvas.getContext("2d");
  return new Uint8Array(ctx.getImageData(0, 0, canvas.width, canvas.height).data.buffer);
}

function loop() {
  const now = performance.now();
  if (lastKeyTime !== null && api.state === "ready") applyKeys(Math.min((now - lastKeyTime) / 1000, 0.1));
  lastKeyTime = now;
  try {
    if (api.state === "ready") {
      if (drawMode === "cpu") cpu.pump(cpuView());
      else dirty = glf.tick(now, dirty, lastChange, scaleMode, $("continuous").checked);
      showRate();
    }
  } catch (err) { showError(err); }
  requestAnimationFrame(loop);
}

// ---------------------------------------------------------------- controls
function hexToRgb(hex) {
  const v = parseInt(hex.slice(1), 16);
  return [(v >> 16) / 255, ((v >> 8) & 255) / 255, (v & 255) / 255];
}
function rgbToHex(c) {
  return "#" + c.map((x) => Math.round(Math.max(0, Math.min(1, x)) * 255).toString(16).padStart(2, "0")).join("");
}

function syncControls() {
  $("background").value = rgbToHex(opts.background);
  $("stop_thresh").value = opts.stop_thresh;
  $("mode").value = opts.mode;
  const B = scene ? scene.format.basisDim : 1;
  $("sh_min").max = $("sh_max").max = String(B - 1);
  $("sh_min").value = opts.sh_min;
  $("sh_max").value = opts.sh_max < 0 ? B - 1 : opts.sh_max;
  $("sh_min_out").textContent = $("sh_min").value;
  $("sh_max_out").textContent = $("sh_max").value;
  $("view_dep").checked = opts.sh_min === 0 && (opts.sh_max < 0 || opts.sh_max >= B - 1);
  for (let a = 0; a < 3; a++) {
    $(`box_min_${a}`).value = opts.box_min[a];
    $(`box_max_${a}`).value = opts.box_max[a];
  }
}

function buildControls() {
  const slices = $("slices");
  "xyz".split("").forEach((axis, a) => {
    for (const end of ["min", "max"]) {
      const label = document.createElement("label");
      label.textContent = `${axis} ${end} `;
      const input = document.createElement("input");
      Object.assign(input, { type: "range", id: `box_${end}_${a}`, min: 0, max: 1, step: 0.01, value: end === "min" ? 0 : 1 });
      input.addEventListener("input", () => { opts[`box_${end}`][a] = Number(input.value); invalidate(); });
      label.appendChild(input);
      slices.appendChild(label);
    }
  });
  $("slice_reset").addEventListener("click", () => { opts.box_min = [0, 0, 0]; opts.box_max = [1, 1, 1]; syncControls(); invalidate(); });
  $("scale").value = scaleMode;
  $("scale").addEventListener("change", () => { scaleMode = $("scale").value; invalidate(); });
  $("mode").addEventListener("change", () => { opts.mode = $("mode").value; invalidate(); });
  $("background").addEventListener("input", () => { opts.background = hexToRgb($("background").value); invalidate(); });
  $("stop_thresh").addEventListener("change", () => {
    const v = Number($("stop_thresh").value);
    if (v >= 0 && v < 1) { opts.stop_thresh = v; invalidate(); }
  });
  $("up").addEventListener("change", () => { camera.up = $("up").value; invalidate(); });
  $("continuous").addEventListener("change", () => { invalidate(); });
  const shChanged = () => {
    opts.sh_min = Number($("sh_min").value);
    const B = scene.format.basisDim;
    const mx = Number($("sh_max").value);
    opts.sh_max = mx >= B - 1 ? -1 : mx;
    syncControls();
    invalidate();
  };
  $("sh_min").addEventListener("input", shChanged);
  $("sh_max").addEventListener("input", shChanged);
  $("view_dep").addEventListener("change", () => {
    opts.sh_min = 0;
    opts.sh_max = $("view_dep").checked ? -1 : 0;
    syncControls();
    invalidate();
  });
  $("screenshot").addEventListener("click", () => {
    if (drawMode === "webgl") renderOnce();
    canvas.toBlob((blob) => {
      const a = document.createElement("a");
      a.href = URL.createObjectURL(blob);
      a.download = "plenoctree.png";
      a.click();
    });
  });
  $("file").addEventListener("change", async () => {
    const f = $("file").files[0];
    if (!f) return;
    $("message").hidden = true;
    api.state = "loading";
    try { await loadBuffer(await f.arrayBuffer(), f.name, false); } catch (err) { showError(err); }
    $("file").value = "";
  });
  canvas.addEventListener("webglcontextlost", (e) => {
    e.preventDefault();
    const err = new Error("the WebGL context was lost (a frame took too long or GPU memory ran out)");
    err.name = "ContextLost";
    showError(err);
  });
  window.addEventListener("resize", () => { invalidate(); });
  window.addEventListener("keydown", (e) => onKey(e, true));
  window.addEventListener("keyup", (e) => onKey(e, false));
  window.addEventListener("blur", () => held.clear());
  $("message-close").addEventListener("click", dismissMessage);
  $("hints-close").addEventListener("click", () => { $("hints").hidden = true; });
  $("reset_view").addEventListener("click", resetView);
  $("fov").addEventListener("input", () => setFov($("fov").value));
  $("camera_select").addEventListener("change", () => jumpToCamera(Number($("camera_select").value)));
  $("camera_prev").addEventListener("click", () => jumpToCamera(Number($("camera_select").value) - 1));
  $("camera_next").addEventListener("click", () => jumpToCamera(Number($("camera_select").value) + 1));
  $("show_cameras").addEventListener("change", () => invalidate());
  $("mesh_file").addEventListener("change", async () => {
    const f = $("mesh_file").files[0];
    if (!f) return;
    try {
      const r = addMesh(/\.glb$/i.test(f.name) ? await f.arrayBuffer() : await f.text(), f.name);
      $("mesh_info").textContent = `${f.name}: ${r.vertices.toLocaleString()} vertices, ${r.triangles.toLocaleString()} triangles`;
    } catch (err) { showError(err); }
    $("mesh_file").value = "";
  });
  $("mesh_clear").addEventListener("click", () => { api.clearMeshes(); $("mesh_info").textContent = ""; });
  $("mesh_shading").addEventListener("change", () => api.setMeshShading($("mesh_shading").checked));
  canvas.addEventListener("click", (e) => {
    if (!(e.altKey || $("probe_mode").checked) || api.state !== "ready" || drawMode !== "webgl") return;
    const r = canvas.getBoundingClientRect();
    probePixel(e.clientX - r.left, e.clientY - r.top);
  });
  camera.onChange = () => { invalidate(); };
  camera.attach(canvas);
}

// ---------------------------------------------------------------- loading
// bundled: the tree named by config.json (its "ndc" applies), not one opened from the disk.
async function loadBuffer(buffer, name, bundled = true) {
  treeName = name;
  setStatus("Reading the archive...");
  const archive = new NpzArchive(buffer, name);
  const limits = { ...renderer.limits, maxBytes: Number(params.get("max_mb") || config.max_mb || 2048) * 1e6 };
  const packed = await packTree(archive, limits, setStatus);
  setStatus("Uploading textures...");
  renderer.upload(packed);
  scene = packed;
  opts.ndc = packed.ndc || (bundled && config.ndc) || null;   // the file's own, else the bundle's
  frameInitialView(packed);
  if (bundled) restoreLiveCamera(config, camera);
  opts.sh_min = 0;
  opts.sh_max = -1;
  syncControls();
  const d = describe(packed);
  $("info").textContent = `${name}: ${d.format}${d.compressed ? `, compressed (${d.bits} bits)` : ""}, `
    + `${d.n_leaves.toLocaleString()} leaves, depth ${d.max_depth + 1}, ${d.texture_mb.toFixed(1)} MB of textures`;
  setStatus("");
  api.state = "ready";
  invalidate();
  resolveReady(d);
}

function fillCameraList() {
  const cams = config.cameras;
  const sel = $("camera_select");
  sel.textContent = "";
  const n = cams ? cams.c2w.length : 0;
  $("cameras_box").hidden = n === 0;
  for (let i = 0; i < n; i++) {
    const o = document.createElement("option");
    o.value = String(i);
    o.textContent = cams.names && cams.names[i] ? `${i}: ${cams.names[i]}` : `camera ${i}`;
    sel.appendChild(o);
  }
}

// CPU mode: the server draws (config.json "cpu": box, basis count, NDC space, threads); the
// page never downloads the tree. Tools that need the tree in the page are WebGL-only.
function startCpuMode() {
  const c = config.cpu;
  drawMode = "cpu";
  treeName = decodeURIComponent(config.tree.split("/").pop());
  scene = { cpu: true, offset: c.offset, invradius: c.invradius, nLeaves: c.n_leaves,
    maxDepth: c.max_depth, format: { name: c.format, basisDim: c.basis_dim } };
  opts.ndc = c.ndc || null;
  cpu = new CpuFrames(canvas, stats);
  cpu.onError = (err) => showNotice(err instanceof FrameError ? err.message
    : `the server could not be reached (${err && err.message ? err.message : err}); `
      + "the next camera change tries again");
  cpu.next = () => { if (api.state === "ready") cpu.pump(cpuView()); };
  rendererLabel = `CPU (numba, ${c.threads} thread${c.threads === 1 ? "" : "s"})`;
  $("fps").title = glInfo.webgl2 ? `this browser's WebGL: ${glInfo.renderer || "unknown"}` : "no WebGL2 in this browser";
  markWebglOnly();
  frameInitialView(scene);
  restoreLiveCamera(config, camera);
  opts.sh_min = 0;
  opts.sh_max = -1;
  syncControls();
  $("info").textContent = `${treeName}: ${c.format}, ${c.n_leaves.toLocaleString()} leaves, `
    + `depth ${c.max_depth + 1}, drawn by the server's CPU renderer`;
  setStatus("");
  api.state = "ready";
  invalidate();
  requestAnimationFrame(loop);
  resolveReady(describe(scene));
}

async function main() {
  buildControls();
  if (location.protocol === "file:" && !params.get("tree")) {
    const err = new FormatError("this page was opened from the disk (file://), where browsers do not "
      + "let it read the tree. Serve the folder over HTTP and open the address it prints:\n"
      + "  python -m http.server --bind 127.0.0.1 8000 --directory <this folder>\n"
      + "or run: plenoctree view TREE");
    err.title = "Open this viewer through a web server";
    throw err;
  }
  try {
    const cfg = await fetch("config.json");
    if (cfg.ok) config = await cfg.json();
  } catch (err) { /* no config: ?tree= or the file picker */ }
  if (config.title) document.title = config.title;
  // the dataset's background (black for real photos), until the user picks another
  if (Array.isArray(config.background) && config.background.length === 3
      && config.background.every((v) => Number.isFinite(v) && v >= 0 && v <= 1)) {
    opts.background = config.background.slice();
    syncControls();
  }
  fillCameraList();
  if (config.live) {
    startLive(config, () => (api.state === "ready" ? camera.state() : null));
    if (!config.tree) {                  // the run has made no tree yet: poll until it has
      setStatus("Waiting for the run's first tree (the trainer writes a preview within minutes)...");
      return;
    }
  }
  const treeUrl = params.get("tree") || config.tree;
  const wanted = params.get("tree") ? "webgl" : params.get("render") || config.render || "webgl";
  glInfo = detectGL();
  if (wanted === "cpu" && !config.cpu) {
    const err = new FormatError("this page's server does not draw frames; start it with\n"
      + "  plenoctree view TREE --render cpu");
    err.title = "CPU mode is not available here";
    throw err;
  }
  if (config.cpu && (wanted === "cpu" || (wanted === "auto" && glInfo.software))) {
    startCpuMode();
    return;
  }
  renderer = new Renderer(canvas, {
    maxTextureSize: Number(params.get("max_texture")) || undefined,
    maxLayers: Number(params.get("max_layers")) || undefined,
  });
  const gpu = glRendererName(renderer.gl);
  rendererLabel = `WebGL (${gpu.length > 60 ? gpu.slice(0, 57) + "..." : gpu})`
    + (glInfo.software ? " - software GL: slow; plenoctree view --render cpu draws with the CPU" : "");
  $("fps").title = gpu;
  glf = new GlFrames(renderer, stats, {
    view: (scale) => { const [w, h] = targetSize(scale); return fixedView || camera.view(w, h); },
    fixed: () => Boolean(fixedView),
    opts: () => { updateDepthRange(); return opts; },
    meshes: (view) => (meshPass && meshPass.meshes.length ? meshPass.draw(view) : null),
    overlay: drawCameras,
  }, Number(params.get("band_ms")) || 40);
  requestAnimationFrame(loop);
  if (!treeUrl) {
    throw new FormatError("no tree given: open this page with ?tree=URL, or use 'Open another tree'");
  }
  const name = decodeURIComponent(treeUrl.split("/").pop());
  treeName = name;
  setStatus(`Downloading ${name}...`);
  const buffer = await fetchBuffer(treeUrl, setStatus);
  await loadBuffer(buffer, name);
}

main().catch(showError);
