// The WebGL mode's frame scheduling: the page never waits for the GPU in its frame loop.
// A fence (gl.fenceSync), polled on later animation frames, tells when a frame is done (no
// synchronous read-back). While the camera moves, frames are drawn at the resolution scale that
// keeps a frame near TARGET_MS ("auto"); FULL_AFTER_MS after the last change comes the full
// resolution frame: at once when it is fast, else refined in bands of about `bandMs` each into
// an offscreen target and shown when complete (a slow GPU, e.g. software GL, never stalls the
// page for a whole frame); a camera move drops the refinement.

const TARGET_MS = 60;
const FULL_AFTER_MS = 100;
const MIN_SCALE = 0.2;

export class GlFrames {
  // renderer: the Renderer; stats: a FrameStats; page: {view(scale): the view to draw at a
  // resolution scale (a script's fixed view ignores the scale), fixed(): a script's view is
  // set, opts(): the render options of this frame (depth range updated), meshes(view): mesh textures or
  // null, overlay(view): draw the 2-D overlay}; bandMs: band length of a refined frame.
  constructor(renderer, stats, page, bandMs = 40) {
    Object.assign(this, { renderer, stats, page, bandMs });
    this.autoScale = 1;
    this.lastMs = 0;           // ms of the last frame drawn at once
    this.fullMs = 0;           // measured ms of a full-resolution frame
    this.needFull = false;
    this.pending = null;       // the frame in flight: {sync, t0, width, height, scale | rows}
    this.refine = null;        // the full frame being refined: {view, meshTex, y, rows, t0}
  }

  // One animation frame: `changed` (the view changed since the last call), `changedAt`
  // (performance.now() of that change), scaleMode ("auto" or a number), continuous.
  tick(now, changed, changedAt, scaleMode, continuous) {
    if (this.pending) {
      const gl = this.renderer.gl, p = this.pending;
      if (gl.getSyncParameter(p.sync, gl.SYNC_STATUS) !== gl.SIGNALED) return changed;
      gl.deleteSync(p.sync);
      this.pending = null;
      if (p.rows) this._bandDone(now, p); else this._done(p, now - p.t0, scaleMode);
    }
    // stopped: no change for FULL_AFTER_MS, or for two frames when frames are slower (a slow
    // frame delays the animation frames that move the camera)
    const stopped = now - changedAt >= Math.max(FULL_AFTER_MS, 2 * this.lastMs);
    if (changed || continuous) {
      this.refine = null;
      if (scaleMode !== "auto") {
        this.pending = this._draw(Number(scaleMode));
      } else if (continuous || !stopped) {
        this.pending = this._draw(this.autoScale);
        this.needFull = this.autoScale < 1;
      } else {
        this._full(now);
      }
    } else if (this.refine) {
      this._nextBand();
    } else if (this.needFull && stopped) {
      this._full(now);
    }
    return false;
  }

  // The full-resolution frame: at once when fast, else refined in bands.
  _full(now) {
    this.needFull = false;
    if (this.page.fixed() || this.fullMs <= 1.5 * this.bandMs) this.pending = this._draw(1);
    else this._startRefine(now);
  }

  // Draw at `scale` and wait for the GPU (scripts: viewer.render / benchmark, Save PNG): ms.
  renderNow(scale, scaleMode) {
    const f = this._draw(scale);
    this.renderer.finish();
    const ms = performance.now() - f.t0;
    this.renderer.gl.deleteSync(f.sync);
    this._done(f, ms, scaleMode);
    return ms;
  }

  _fence() {
    const gl = this.renderer.gl;
    const sync = gl.fenceSync(gl.SYNC_GPU_COMMANDS_COMPLETE, 0);
    gl.flush();
    return sync;
  }

  _draw(scale) {
    const view = this.page.view(scale);
    const opts = this.page.opts();
    const t0 = performance.now();
    this.renderer.draw(view, opts, this.page.meshes(view));
    this.page.overlay(view);
    return { sync: this._fence(), t0, width: view.width, height: view.height, scale };
  }

  _done(f, ms, scaleMode) {
    this.lastMs = ms;
    if (scaleMode === "auto" && !this.page.fixed() && f.scale > 0) {
      this.fullMs = ms / (f.scale * f.scale);
      this.autoScale = Math.max(MIN_SCALE, Math.min(1, Math.sqrt(TARGET_MS / Math.max(this.fullMs, 1e-3))));
    }
    this.stats.add({ width: f.width, height: f.height, full: f.scale === 1, ms });
  }

  _startRefine(now) {
    const view = this.page.view(1);
    this.renderer.beginBands(view);
    const h = view.height;
    const rows = Math.max(4, Math.min(h, Math.round(h * this.bandMs / this.fullMs)));
    this.refine = { view, meshTex: this.page.meshes(view), y: 0, rows, t0: now };
    this._nextBand();
  }

  _nextBand() {
    const r = this.refine, y1 = Math.min(r.view.height, r.y + r.rows);
    this.renderer.drawBand(r.view, this.page.opts(), r.meshTex, r.y, y1);
    this.pending = { sync: this._fence(), t0: performance.now(), rows: y1 - r.y };
    r.y = y1;
  }

  // A band is done: size the next one to bandMs; show the frame when its last band is done.
  _bandDone(now, f) {
    const r = this.refine;
    if (!r) return;                          // dropped by a camera move
    const ms = Math.max(now - f.t0, 1), h = r.view.height;
    this.fullMs = ms * h / f.rows;
    r.rows = Math.max(4, Math.min(h, Math.round(f.rows * this.bandMs / ms)));
    if (r.y < h) return;
    this.renderer.presentBands();
    this.page.overlay(r.view);
    this.stats.add({ width: r.view.width, height: h, full: true, ms: now - r.t0, bands: true });
    this.refine = null;
  }
}
