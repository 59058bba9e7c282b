// The PlenOctree viewer page: loads the tree named by ?tree= or config.json, packs it into
// textures, renders on demand, wires the controls, and exposes `window.viewer` for scripts.
// Every failure ends in a visible message (never a blank canvas).

import { NpzArchive, FormatError } from "./npz.js";
import { packTree, LimitError } from "./tree.js";
import { Renderer, GLError } from "./renderer.js";
import { OrbitCamera } from "./camera.js";

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
// Resolution scale: a number, or "auto": while the view changes, frames render at autoScale
// (tuned so a frame takes ~TARGET_MS), and 300 ms after the last change once at full size.
let scaleMode = params.get("scale") || "auto";
let autoScale = 1;
const TARGET_MS = 60;
let dirty = true;
let lastChange = 0;
let needFull = false;
let lastFrameMs = null;

function invalidate() {
  dirty = true;
  lastChange = performance.now();
}
let treeName = "";

let resolveReady, rejectReady;
const ready = new Promise((res, rej) => { resolveReady = res; rejectReady = rej; });
ready.catch(() => {});

const api = {
  state: "loading", message: "", ready,
  info: () => (renderer && renderer.tree ? describe(renderer.tree) : null),
  limits: () => (renderer ? renderer.limits : null),
  setView(view) { fixedView = view; invalidate(); },
  clearView() { fixedView = null; invalidate(); },
  setOptions(o) { Object.assign(opts, o); syncControls(); invalidate(); },
  options: () => JSON.parse(JSON.stringify(opts)),
  render() { return renderOnce(); },
  pixels() {
    const px = renderer.readPixels();
    let s = "";
    for (let i = 0; i < px.length; i += 0x8000) s += String.fromCharCode.apply(null, px.subarray(i, i + 0x8000));
    return btoa(s);
  },
  // Median milliseconds per frame (draw + wait for the GPU) over n frames.
  benchmark(n = 10) {
    const times = [];
    renderOnce();
    for (let i = 0; i < n; i++) times.push(renderOnce());
    times.sort((a, b) => a - b);
    return times[Math.floor(times.length / 2)];
  },
  camera: () => camera,
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
  const text = err && err.message ? err.message : String(err);
  $("message-title").textContent = title;
  $("message-text").textContent = text;
  $("message-hint").textContent = hint;
  $("message").hidden = false;
  setStatus("");
  api.state = "error";
  api.message = `${title}: ${text}${hint ? "\n" + hint : ""}`;
  rejectReady(new Error(api.message));
  console.error(api.message);
}

function describe(t) {
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

function renderOnce(scale = scaleMode === "auto" ? 1 : Number(scaleMode)) {
  if (!renderer || !renderer.tree) throw new Error("no tree loaded");
  const [w, h] = targetSize(scale);
  const view = fixedView || camera.view(w, h);
  if (!fixedView) {
    const c = camera.target, e = camera.eye();
    const dist = Math.hypot(e[0] - c[0], e[1] - c[1], e[2] - c[2]);
    const r = treeRadius() * Math.sqrt(3);
    opts.depth_range = [Math.max(0, dist - r), dist + r];
  }
  const t0 = performance.now();
  renderer.draw(view, opts);
  renderer.finish();
  const ms = performance.now() - t0;
  lastFrameMs = ms;
  if (scaleMode === "auto" && !fixedView) {
    const fullMs = ms / (scale * scale);
    autoScale = Math.max(0.2, Math.min(1, Math.sqrt(TARGET_MS / Math.max(fullMs, 1e-3))));
  }
  $("fps").textContent = `${ms.toFixed(1)} ms/frame (${(1000 / ms).toFixed(1)} FPS) @ ${w}x${h}`;
  return ms;
}

function treeRadius() {
  const t = renderer.tree;
  return Math.max(...t.invradius.map((v) => 0.5 / v));
}

function loop() {
  const now = performance.now();
  const continuous = $("continuous").checked;
  try {
    if (api.state === "ready" && (dirty || continuous)) {
      dirty = false;
      if (scaleMode === "auto") {
        const moving = continuous || now - lastChange < 300;
        renderOnce(moving ? autoScale : 1);
        needFull = moving && autoScale < 1;
      } else {
        renderOnce();
      }
    } else if (api.state === "ready" && needFull && now - lastChange >= 300) {
      needFull = false;
      renderOnce(1);
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
  const B = renderer && renderer.tree ? renderer.tree.format.basisDim : 1;
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
    const B = renderer.tree.format.basisDim;
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
    renderOnce();
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
    try { await loadBuffer(await f.arrayBuffer(), f.name); } catch (err) { showError(err); }
  });
  canvas.addEventListener("webglcontextlost", (e) => {
    e.preventDefault();
    const err = new Error("the WebGL context was lost (a frame took too long or GPU memory ran out)");
    err.name = "ContextLost";
    showError(err);
  });
  window.addEventListener("resize", () => { invalidate(); });
  camera.onChange = () => { invalidate(); };
  camera.attach(canvas);
}

// ---------------------------------------------------------------- loading
async function fetchTree(url) {
  let resp;
  try {
    resp = await fetch(url);
  } catch (err) {
    throw new FormatError(`${url}: cannot download (${err.message})`);
  }
  if (!resp.ok) throw new FormatError(`${url}: the server answered ${resp.status} ${resp.statusText}`);
  const total = Number(resp.headers.get("Content-Length")) || 0;
  if (!resp.body) return resp.arrayBuffer();
  const reader = resp.body.getReader();
  const chunks = [];
  let got = 0;
  for (;;) {
    const { done, value } = await reader.read();
    if (done) break;
    chunks.push(value);
    got += value.length;
    setStatus(`Downloading ${(got / 1e6).toFixed(1)}${total ? " / " + (total / 1e6).toFixed(1) : ""} MB`);
  }
  if (total && got !== total) throw new FormatError(`${url}: download cut short (${got} of ${total} bytes)`);
  const out = new Uint8Array(got);
  let p = 0;
  for (const c of chunks) { out.set(c, p); p += c.length; }
  return out.buffer;
}

async function loadBuffer(buffer, name) {
  treeName = name;
  setStatus("Reading the archive...");
  const archive = new NpzArchive(buffer, name);
  const limits = { ...renderer.limits, maxBytes: Number(params.get("max_mb") || config.max_mb || 2048) * 1e6 };
  const packed = await packTree(archive, limits, setStatus);
  setStatus("Uploading textures...");
  renderer.upload(packed);
  const r = treeRadius();
  const center = [0, 1, 2].map((i) => (0.5 - packed.offset[i]) / packed.invradius[i]);
  camera.target = center;
  camera.distance = (config.camera_distance || 2.6) * r;
  if (config.up) camera.up = config.up;
  $("up").value = camera.up;
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

async function main() {
  buildControls();
  try {
    const cfg = await fetch("config.json");
    if (cfg.ok) config = await cfg.json();
  } catch (err) { /* no config: ?tree= or the file picker */ }
  if (config.title) document.title = config.title;
  const treeUrl = params.get("tree") || config.tree;
  renderer = new Renderer(canvas, {
    maxTextureSize: Number(params.get("max_texture")) || undefined,
    maxLayers: Number(params.get("max_layers")) || undefined,
  });
  requestAnimationFrame(loop);
  if (!treeUrl) {
    throw new FormatError("no tree given: open this page with ?tree=URL, or use 'Open another tree'");
  }
  const name = decodeURIComponent(treeUrl.split("/").pop());
  treeName = name;
  setStatus(`Downloading ${name}...`);
  const buffer = await fetchTree(treeUrl);
  await loadBuffer(buffer, name);
}

main().catch(showError);
