// Orbit camera (OpenGL convention: x right, y up, looks down -z) with mouse, touch and keyboard
// controls: drag = orbit, right/middle drag or shift-drag = pan, wheel = zoom; one finger =
// orbit, two fingers = pinch zoom + pan; W/S forward/back, A/D left/right, Q/E down/up (fly:
// target and eye move together), arrow keys turn the view around the eye.
// An exact pose (a training camera jumped to) is kept in `pose` until the next move.

export const UP = { "+z": [0, 0, 1], "-z": [0, 0, -1], "+y": [0, 1, 0], "-y": [0, -1, 0],
  "+x": [1, 0, 0], "-x": [-1, 0, 0] };

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return scale(a, 1 / l); };
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];

// Camera-to-world (row-major 16 numbers) looking from eye at target with the given world up.
export function lookAt(eye, target, up) {
  const back = norm(sub(eye, target));
  let right = cross(up, back);
  if (Math.hypot(...right) < 1e-8) right = cross([1, 0, 0], back);
  right = norm(right);
  const trueUp = cross(back, right);
  return [right[0], trueUp[0], back[0], eye[0],
    right[1], trueUp[1], back[1], eye[1],
    right[2], trueUp[2], back[2], eye[2],
    0, 0, 0, 1];
}

const FLY = { KeyW: [0, 0, 1], KeyS: [0, 0, -1], KeyA: [-1, 0, 0], KeyD: [1, 0, 0],
  KeyQ: [0, -1, 0], KeyE: [0, 1, 0] };
const TURN = { ArrowLeft: [1, 0], ArrowRight: [-1, 0], ArrowUp: [0, -1], ArrowDown: [0, 1] };

export const isMoveKey = (code) => Boolean(FLY[code] || TURN[code]);

// Move `camera` for the key codes in `held` over dt seconds: fly at 0.5 `radius` per second
// (W/S forward/back, A/D left/right, Q/E down/up), turn 60°/s around the eye (arrows).
export function applyHeldKeys(camera, held, dt, radius) {
  let f = [0, 0, 0], tr = [0, 0];
  for (const k of held) {
    if (FLY[k]) f = f.map((v, i) => v + FLY[k][i]);
    if (TURN[k]) tr = tr.map((v, i) => v + TURN[k][i]);
  }
  if (f.some((v) => v)) camera.fly(f[0], f[1], f[2], 0.5 * radius * dt);
  if (tr.some((v) => v)) camera.turn(tr[0] * dt * Math.PI / 3, tr[1] * dt * Math.PI / 3);
}

export class OrbitCamera {
  constructor({ target = [0, 0, 0], distance = 4, azimuth = 0.6, elevation = 0.5, fovY = 40, up = "+z" } = {}) {
    this.target = target.slice();
    this.distance = distance;
    this.azimuth = azimuth;
    this.elevation = elevation;
    this.fovY = fovY;
    this.up = up;
    this.pose = null;          // exact row-major c2w (a jumped-to camera) until the next move
    this.onChange = () => {};
  }

  // Plain state (for reset): target, distance, azimuth, elevation, fovY, up, pose.
  state() {
    return { target: this.target.slice(), distance: this.distance, azimuth: this.azimuth,
      elevation: this.elevation, fovY: this.fovY, up: this.up, pose: this.pose && this.pose.slice() };
  }

  setState(s) {
    Object.assign(this, { ...s, target: s.target.slice(), pose: s.pose ? s.pose.slice() : null });
    this.onChange();
  }

  // Orbit parameters that put the eye at `eye` looking at `target`.
  lookFrom(eye, target) {
    const [a, b, u] = this._frame();
    const v = sub(eye, target);
    this.distance = Math.max(Math.hypot(...v), 1e-6);
    const dir = scale(v, 1 / this.distance);
    this.elevation = Math.asin(Math.max(-1, Math.min(1, dot(dir, u))));
    this.azimuth = Math.atan2(dot(dir, b), dot(dir, a));
    this.target = target.slice();
    this.pose = null;
  }

  // Jump to an exact camera (row-major c2w, vertical fov in degrees): orbit about the point
  // of its view axis nearest to `pivot` (the scene centre) afterwards.
  setPose(c2w, fovY, pivot) {
    const eye = [c2w[3], c2w[7], c2w[11]];
    const fwd = [-c2w[2], -c2w[6], -c2w[10]];
    const along = Math.max(dot(sub(pivot, eye), fwd), 1e-3 * Math.hypot(...sub(pivot, eye)) + 1e-6);
    this.lookFrom(eye, add(eye, scale(fwd, along)));
    this.fovY = fovY;
    this.pose = c2w.slice();
    this.onChange();
  }

  _moved() { this.pose = null; }

  // Basis of the orbit frame for the chosen up axis: (a, b, up) right-handed.
  _frame() {
    const u = UP[this.up] || UP["+z"];
    const a = Math.abs(u[0]) < 0.9 ? norm(cross(u, [1, 0, 0])) : norm(cross(u, [0, 1, 0]));
    const b = cross(u, a);
    return [a, b, u];
  }

  eye() {
    const [a, b, u] = this._frame();
    const ce = Math.cos(this.elevation), se = Math.sin(this.elevation);
    const dir = add(add(scale(a, ce * Math.cos(this.azimuth)), scale(b, ce * Math.sin(this.azimuth))), scale(u, se));
    return add(this.target, scale(dir, this.distance));
  }

  // {c2w, fx, fy, cx, cy, width, height} for a render target of width x height pixels.
  view(width, height) {
    const fy = 0.5 * height / Math.tan(0.5 * this.fovY * Math.PI / 180);
    const c2w = this.pose ? this.pose.slice() : lookAt(this.eye(), this.target, UP[this.up] || UP["+z"]);
    return { c2w, fx: fy, fy, cx: width / 2, cy: height / 2, width, height };
  }

  // Fly: move eye and target by (right, up, forward) * step in the camera frame.
  fly(right, up, forward, step) {
    const m = lookAt(this.eye(), this.target, UP[this.up] || UP["+z"]);
    const r = [m[0], m[4], m[8]], u = [m[1], m[5], m[9]], f = [-m[2], -m[6], -m[10]];
    const d = add(add(scale(r, right * step), scale(u, up * step)), scale(f, forward * step));
    this.target = add(this.target, d);
    this._moved();
    this.onChange();
  }

  // Turn the view around the eye by yaw / pitch radians (the eye stays put).
  turn(yaw, pitch) {
    const eye = this.eye();
    this.azimuth += yaw;
    this.elevation = Math.max(-1.55, Math.min(1.55, this.elevation - pitch));
    const e2 = this.eye();
    this.target = add(this.target, sub(eye, e2));
    this._moved();
    this.onChange();
  }

  orbit(dx, dy) {
    this._moved();
    this.azimuth -= dx * 0.008;
    this.elevation = Math.max(-1.55, Math.min(1.55, this.elevation + dy * 0.008));
    this.onChange();
  }

  pan(dx, dy, viewHeight) {
    this._moved();
    const m = lookAt(this.eye(), this.target, UP[this.up] || UP["+z"]);
    const right = [m[0], m[4], m[8]], up = [m[1], m[5], m[9]];
    const perPixel = 2 * this.distance * Math.tan(0.5 * this.fovY * Math.PI / 180) / Math.max(viewHeight, 1);
    this.target = add(this.target, add(scale(right, -dx * perPixel), scale(up, dy * perPixel)));
    this.onChange();
  }

  zoom(factor) {
    this._moved();
    this.distance = Math.max(1e-3, this.distance * factor);
    this.onChange();
  }

  // Mouse, wheel and touch handlers on `el`.
  attach(el) {
    let last = null, mode = null;
    el.addEventListener("contextmenu", (e) => e.preventDefault());
    el.addEventListener("pointerdown", (e) => {
      if (e.pointerType === "touch") return;
      el.setPointerCapture(e.pointerId);
      last = [e.clientX, e.clientY];
      mode = e.button === 0 && !e.shiftKey ? "orbit" : "pan";
    });
    el.addEventListener("pointermove", (e) => {
      if (!last || e.pointerType === "touch") return;
      const dx = e.clientX - last[0], dy = e.clientY - last[1];
      last = [e.clientX, e.clientY];
      if (mode === "orbit") this.orbit(dx, dy); else this.pan(dx, dy, el.clientHeight);
    });
    const end = () => { last = null; mode = null; };
    el.addEventListener("pointerup", end);
    el.addEventListener("pointercancel", end);
    el.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.zoom(Math.exp(e.deltaY * 0.001));
    }, { passive: false });
    let touches = null;
    const snapshot = (ev) => [...ev.touches].map((t) => [t.clientX, t.clientY]);
    el.addEventListener("touchstart", (e) => { e.preventDefault(); touches = snapshot(e); }, { passive: false });
    el.addEventListener("touchmove", (e) => {
      e.preventDefault();
      const now = snapshot(e);
      if (!touches || now.length !== touches.length) { touches = now; return; }
      if (now.length === 1) {
        this.orbit(now[0][0] - touches[0][0], now[0][1] - touches[0][1]);
      } else if (now.length >= 2) {
        const dist = (p) => Math.hypot(p[0][0] - p[1][0], p[0][1] - p[1][1]);
        const mid = (p) => [(p[0][0] + p[1][0]) / 2, (p[0][1] + p[1][1]) / 2];
        const d0 = dist(touches), d1 = dist(now);
        if (d0 > 0 && d1 > 0) this.zoom(d0 / d1);
        const m0 = mid(touches), m1 = mid(now);
        this.pan(m1[0] - m0[0], m1[1] - m0[1], el.clientHeight);
      }
      touches = now;
    }, { passive: false });
    el.addEventListener("touchend", (e) => { touches = snapshot(e); });
  }
}
