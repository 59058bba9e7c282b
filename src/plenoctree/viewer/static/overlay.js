// Training-camera frustums drawn on a 2-D canvas laid over the WebGL canvas, projected with the
// current view (row-major c2w, pinhole intrinsics of the render target).

// cams: config.json's cameras (or null: just clear); current: the highlighted index;
// r: frustum depth in world units.
export function drawFrustums(ov, view, cams, current, r) {
  const dpr = window.devicePixelRatio || 1;
  const W = Math.round(ov.clientWidth * dpr), H = Math.round(ov.clientHeight * dpr);
  if (ov.width !== W || ov.height !== H) { ov.width = W; ov.height = H; }
  const ctx = ov.getContext("2d");
  ctx.clearRect(0, 0, W, H);
  if (!cams) return;
  const m = view.c2w;
  const sx = W / view.width, sy = H / view.height;
  // world -> camera (inverse of a rigid c2w): R^T (p - t)
  const project = (p) => {
    const d = [p[0] - m[3], p[1] - m[7], p[2] - m[11]];
    const x = m[0] * d[0] + m[4] * d[1] + m[8] * d[2];
    const y = m[1] * d[0] + m[5] * d[1] + m[9] * d[2];
    const z = m[2] * d[0] + m[6] * d[1] + m[10] * d[2];
    if (z > -1e-6) return null;
    return [(view.cx + view.fx * x / -z) * sx, (view.cy - view.fy * y / -z) * sy];
  };
  cams.c2w.forEach((c, i) => {
    const eye = [c[3], c[7], c[11]];
    const fy = Array.isArray(cams.fy) ? cams.fy[i] : cams.fy;
    const fx = Array.isArray(cams.fx) ? cams.fx[i] : cams.fx;
    const hw = 0.5 * cams.width / fx, hh = 0.5 * cams.height / fy;
    const corner = (a, b) => [0, 1, 2].map((k) => eye[k] + r * (a * hw * c[4 * k] + b * hh * c[4 * k + 1] - c[4 * k + 2]));
    const pts = [eye, corner(-1, -1), corner(1, -1), corner(1, 1), corner(-1, 1)].map(project);
    if (pts.some((q) => q === null)) return;
    ctx.strokeStyle = i === current ? "#ff4081" : "#1a73e8";
    ctx.lineWidth = (i === current ? 2 : 1) * dpr;
    ctx.beginPath();
    for (let k = 1; k <= 4; k++) { ctx.moveTo(...pts[0]); ctx.lineTo(...pts[k]); }
    ctx.moveTo(...pts[1]);
    for (const k of [2, 3, 4, 1]) ctx.lineTo(...pts[k]);
    ctx.stroke();
  });
}
