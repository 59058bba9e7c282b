// Who draws the frames, and how fast they reach the screen.
// - detectGL(): the browser's WebGL2 renderer name, and whether it is a software one
//   (SwiftShader, llvmpipe, ...): `plenoctree view --render auto` then lets the server draw.
// - CpuFrames: the CPU mode. The server's numba renderer draws each frame (GET frame?...: the
//   camera and the options, see plenoctree/viewer/frames.py) as a JPEG; the page decodes it off
//   the main thread (createImageBitmap) and draws it on its canvas with a 2D context. At most
//   one request is in flight: when a frame arrives the next request carries the latest camera
//   (nothing queues). While the camera moves, frames come at the resolution scale that holds
//   TARGET_MS per frame (measured on every frame); once it has not moved for QUIET_MS, one
//   full-resolution frame follows. A frame the server cannot draw (or a lost connection) is
//   reported through onError and not asked for again until the camera or an option changes:
//   the page never stops drawing.
// - FrameStats: frames actually delivered to the screen in the last second (both modes).

const SOFTWARE_GL = /swiftshader|llvmpipe|softpipe|software|basic render|mesa offscreen|lavapipe/i;

// {webgl2: bool, renderer: "ANGLE (..., SwiftShader ...)" or "", software: bool}; the probe
// context is released at once (the page's canvas stays free for either mode).
export function detectGL() {
  const c = document.createElement("canvas");
  let gl = null;
  try { gl = c.getContext("webgl2"); } catch (err) { gl = null; }
  if (!gl) return { webgl2: false, renderer: "", software: true };
  const name = glRendererName(gl);
  const lose = gl.getExtension("WEBGL_lose_context");
  if (lose) lose.loseContext();
  return { webgl2: true, renderer: name, software: SOFTWARE_GL.test(name) };
}

export function glRendererName(gl) {
  const dbg = gl.getExtension("WEBGL_debug_renderer_info");
  return String(gl.getParameter(dbg ? dbg.UNMASKED_RENDERER_WEBGL : gl.RENDERER) || "");
}

export class FrameStats {
  constructor() { this.times = []; this.log = []; }

  // A frame reached the screen: {width, height, full, ms, renderMs?} (ms: request to screen).
  add(frame) {
    const t = performance.now();
    this.times.push(t);
    while (this.times.length && this.times[0] < t - 1000) this.times.shift();
    this.log.push({ t, ...frame });
    if (this.log.length > 2000) this.log.splice(0, 1000);
    this.last = { t, ...frame };
  }

  // Frames delivered in the last second (0 when the view has been idle for a second).
  fps() {
    const t = performance.now();
    while (this.times.length && this.times[0] < t - 1000) this.times.shift();
    return this.times.length;
  }
}

const TARGET_MS = 45;        // request -> screen while moving (20+ FPS with a margin)
const QUIET_MS = 40;         // no camera change this long: the full-resolution frame
const MIN_SCALE = 0.25;
const SHARP_QUALITY = 90;    // JPEG quality of the full-resolution frame (no chroma subsampling)
const MOVING_QUALITY = 80;
// Moving frames stop a ray at transmittance 0.1 with svox's renormalised colour (the
// renderer's `renormalize`: a render 1.13-1.25x faster on flower and lounge for ~0.25 dB,
// docs/results.md); the sharp frame is exact.
const MOVING_STOP = 0.1;

export class FrameError extends Error {
  constructor(message) { super(message); this.name = "FrameError"; }
}

// The query string of GET /frame for a view ({c2w, fx, fy, cx, cy, width, height}) and the
// page's options (background, stop_thresh, renormalize, sh_min, sh_max, mode, depth_range).
export function frameQuery(view, opts, quality = 90) {
  const f = (v) => (Number.isInteger(v) ? String(v) : v.toPrecision(9));
  const p = new URLSearchParams({
    w: String(view.width), h: String(view.height), c2w: view.c2w.map(f).join(","),
    fx: f(view.fx), fy: f(view.fy), cx: f(view.cx), cy: f(view.cy),
    bg: opts.background.map(f).join(","), stop: f(opts.stop_thresh),
    renorm: opts.renormalize ? "1" : "0",
    sh_min: String(opts.sh_min), sh_max: String(opts.sh_max), mode: opts.mode || "rgb",
    dr: (opts.depth_range || [0, 1]).map(f).join(","), q: String(quality),
  });
  return p.toString();
}

// The render options of a frame drawn at resolution `scale`: the page's own at full
// resolution, the fast rule (MOVING_STOP, renormalised) for a moving frame.
export function frameOptions(opts, scale) {
  if (scale === 1) return opts;
  return { ...opts, stop_thresh: Math.max(opts.stop_thresh, MOVING_STOP), renormalize: true };
}

export class CpuFrames {
  constructor(canvas, stats) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d", { alpha: false });
    this.stats = stats;
    this.busy = false;
    this.scale = 0.5;            // resolution scale while moving (adapted per frame)
    this.otherMs = 10;           // request -> screen time besides the server's render (EMA)
    this.renderFullMs = null;    // server render time of a full-resolution frame (EMA)
    this.sentKey = null;         // camera + options of the last request
    this.sharpKey = null;        // ... of the frame on screen when it is full resolution
    this.failedKey = null;       // ... of a frame the server could not draw (not asked again)
    this.onError = () => {};
    this.next = () => {};        // called when a frame is on screen (pump the next one)
  }

  // Call on every animation frame; it calls itself again (through `this.next()`) as each
  // frame lands. v: {key (camera + options, a string), viewAt(scale) (that view at a
  // resolution scale), opts, target ([W, H] of the canvas), fixed (a script's exact view: no
  // scaling), continuous (keep drawing), changedAt (performance.now() of the last change)}.
  pump(v) {
    if (this.busy) return;
    if (v.key === this.failedKey && !v.continuous) return;     // wait for the next change
    const moving = v.continuous || performance.now() - v.changedAt < QUIET_MS;
    if (v.key === this.sentKey && !v.continuous && (v.key === this.sharpKey || moving)) return;
    const scale = v.fixed || !moving ? 1 : this.scale;
    this.sentKey = v.key;
    this._draw(v.key, v.viewAt(scale), v.opts, v.fixed ? null : v.target, scale);
  }

  // Draw `view` at full resolution after the frame in flight (scripts: api.render); resolves
  // with the request -> screen milliseconds, rejects with the server's error.
  async drawNow(key, view, opts, target) {
    while (this.busy) await new Promise((r) => setTimeout(r, 5));
    this.sentKey = key;
    const err = await this._draw(key, view, opts, target, 1, false);
    if (err) throw err;
    return this.stats.last.ms;
  }

  // One request -> screen round trip; returns the error (null when the frame is on screen).
  async _draw(key, view, opts, target, scale, chain = true) {
    this.busy = true;
    const t0 = performance.now();
    try {
      const q = scale === 1 ? SHARP_QUALITY : MOVING_QUALITY;
      const query = frameQuery(view, frameOptions(opts, scale), q);
      const resp = await fetch(`frame?${query}`, { cache: "no-store" });
      if (!resp.ok) throw new FrameError(`the server could not draw this view: ${(await resp.text()).trim()}`);
      const renderMs = Number(resp.headers.get("X-Render-Ms")) || 0;
      const encodeMs = Number(resp.headers.get("X-Encode-Ms")) || 0;
      const bmp = await createImageBitmap(await resp.blob());
      const [W, H] = target || [view.width, view.height];
      if (this.canvas.width !== W || this.canvas.height !== H) {
        this.canvas.width = W;
        this.canvas.height = H;
      }
      this.ctx.imageSmoothingEnabled = true;
      this.ctx.drawImage(bmp, 0, 0, W, H);
      bmp.close();
      const ms = performance.now() - t0;
      const full = scale === 1;
      this.sharpKey = full ? key : null;   // what is on screen now (a moving frame too)
      this.failedKey = null;
      this._adapt(ms, renderMs, view.width * view.height, W * H);
      this.stats.add({ width: view.width, height: view.height, full, ms, renderMs, encodeMs, key });
    } catch (err) {
      this.sentKey = null;
      this.failedKey = key;
      if (chain) this.onError(err);
      return err;
    } finally {
      this.busy = false;
    }
    if (chain) this.next();
    return null;
  }

  // Scale for the next moving frame: other + renderFull * s^2 = TARGET_MS.
  _adapt(ms, renderMs, pixels, fullPixels) {
    const k = 0.5;
    const renderFull = renderMs * fullPixels / Math.max(pixels, 1);
    this.renderFullMs = this.renderFullMs === null ? renderFull : (1 - k) * this.renderFullMs + k * renderFull;
    this.otherMs = (1 - k) * this.otherMs + k * Math.max(ms - renderMs, 0);
    const budget = Math.max(TARGET_MS - this.otherMs, 0.3 * TARGET_MS);
    const s = Math.sqrt(budget / Math.max(this.renderFullMs, 1e-3));
    this.scale = Math.max(MIN_SCALE, Math.min(1, s));
  }
}

// CPU mode: disable the tools that need the tree in the page (probe, slicing box, meshes,
// opening another tree), with a tooltip saying why.
export function markWebglOnly() {
  const $ = (id) => document.getElementById(id);
  const why = "WebGL only: the page is drawn by the CPU renderer on the server (open the page "
    + "with ?render=webgl, or start plenoctree view --render webgl, to use it)";
  const inputs = ["probe_mode", "mesh_file", "mesh_clear", "mesh_shading", "slice_reset", "file"]
    .map($).concat([...$("slices").querySelectorAll("input")]);
  for (const el of inputs) { el.disabled = true; el.title = why; }
  for (const id of ["probe_box", "slices_box", "mesh_box", "file_box"]) {
    const sum = $(id).querySelector("summary");
    sum.title = why;
    sum.insertAdjacentHTML("beforeend", ' <span class="small">(WebGL only)</span>');
  }
}
