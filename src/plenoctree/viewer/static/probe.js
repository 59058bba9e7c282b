// Radiance probe ("lumisphere", as in the paper's viewer): the leaf a ray mostly stops in and
// the colour that leaf shows from every direction. Works on the CPU copy of the packed
// textures (see tree.js for the layout): descent, a fine ray march, the SH/SG basis in JS.

import { halfToFloat } from "./tree.js";

const SH = {
  C0: 0.28209479177387814, C1: 0.4886025119029199,
  C2: [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396],
  C3: [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435],
  C4: [2.5033429417967046, -1.7701307697799304, 0.9461746957575601, -0.6690465435572892,
    0.10578554691520431, -0.6690465435572892, 0.47308734787878004, -1.7701307697799304,
    0.6258357354491761],
};

// Basis values [B] for a unit direction d (same as the shader and plenoctree.sh).
export function basisValues(format, sg, d) {
  const B = format.basisDim, out = new Float64Array(B);
  if (format.kind === 2) { out[0] = 1; return out; }
  if (format.kind === 1) {
    for (let i = 0; i < B; i++) {
      const s = sg[4 * i], m = [sg[4 * i + 1], sg[4 * i + 2], sg[4 * i + 3]];
      out[i] = Math.exp(s * (m[0] * d[0] + m[1] * d[1] + m[2] * d[2] - 1)) / B;
    }
    return out;
  }
  const [x, y, z] = d, xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  const v = [SH.C0];
  if (format.shDegree >= 1) v.push(-SH.C1 * y, SH.C1 * z, -SH.C1 * x);
  if (format.shDegree >= 2) {
    v.push(SH.C2[0] * xy, SH.C2[1] * yz, SH.C2[2] * (2 * zz - xx - yy), SH.C2[3] * xz, SH.C2[4] * (xx - yy));
  }
  if (format.shDegree >= 3) {
    v.push(SH.C3[0] * y * (3 * xx - yy), SH.C3[1] * xy * z, SH.C3[2] * y * (4 * zz - xx - yy),
      SH.C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH.C3[4] * x * (4 * zz - xx - yy),
      SH.C3[5] * z * (xx - yy), SH.C3[6] * x * (xx - 3 * yy));
  }
  if (format.shDegree >= 4) {
    v.push(SH.C4[0] * xy * (xx - yy), SH.C4[1] * yz * (3 * xx - yy), SH.C4[2] * xy * (7 * zz - 1),
      SH.C4[3] * yz * (7 * zz - 3), SH.C4[4] * (zz * (35 * zz - 30) + 3), SH.C4[5] * xz * (7 * zz - 3),
      SH.C4[6] * (xx - yy) * (7 * zz - 1), SH.C4[7] * xz * (xx - 3 * yy),
      SH.C4[8] * (xx * (xx - 3 * yy) - yy * (3 * xx - yy)));
  }
  out.set(v.slice(0, B));
  return out;
}

// Array index of texel t of item i (planTexture's layout: shifts and masks, as the shader).
function texelIndex(i, t, plan) {
  const row = i >> plan.log2PerRow;
  const x = (i - (row << plan.log2PerRow)) * plan.perItem + t;
  const y = row & ((1 << plan.log2h) - 1), layer = row >> plan.log2h;
  return (layer * plan.height + y) * plan.width + x;
}

// Child value of the leaf cell holding tree point p in [0, 1]^3 (> 0 never; 0 empty leaf,
// < 0 leaf -(v+1)).
export function leafValue(packed, p) {
  let node = 0;
  let pos = p.slice();
  for (let level = 0; level < 32; level++) {
    const idx = pos.map((v) => Math.min(Math.max(Math.floor(v * 2), 0), 1));
    const cell = node * 8 + idx[0] * 4 + idx[1] * 2 + idx[2];
    const val = packed.child.data[texelIndex(cell, 0, packed.child)];
    if (val <= 0) return val;
    node += val;
    pos = pos.map((v, k) => v * 2 - idx[k]);
  }
  return 0;
}

// sigma and coefficients [B][3] of leaf number `leaf` (float16 values as the GPU reads them).
export function leafData(packed, leaf) {
  const B = packed.format.basisDim, D = packed.data, px = (t) => 4 * texelIndex(leaf, t, D);
  const h = (i) => halfToFloat(D.data[i]);
  const t0 = px(0);
  const coeffs = [[h(t0 + 1), h(t0 + 2), h(t0 + 3)]];
  for (let g = 0; 4 * g + 1 < B; g++) {
    const vals = [];
    for (let k = 1; k <= 3; k++) { const o = px(3 * g + k); for (let c = 0; c < 4; c++) vals.push(h(o + c)); }
    for (let j = 0; j < 4 && 4 * g + 1 + j < B; j++) coeffs.push(vals.slice(3 * j, 3 * j + 3));
  }
  return { sigma: h(t0), coeffs };
}

export function colorOf(packed, coeffs, dir) {
  const bv = basisValues(packed.format, packed.sg, dir);
  return [0, 1, 2].map((c) => {
    let s = 0;
    for (let b = 0; b < bv.length; b++) s += coeffs[b][c] * bv[b];
    return 1 / (1 + Math.exp(-s));
  });
}

// The leaf a world ray (origin, unit dir) gives the largest weight T (1 - exp(-sigma dt)),
// marching n uniform steps over its part inside the tree box. null when the ray hits nothing.
export function probeRay(packed, origin, dir, n = 2048) {
  const o = [0, 1, 2].map((k) => packed.offset[k] + packed.invradius[k] * origin[k]);
  const d = [0, 1, 2].map((k) => packed.invradius[k] * dir[k]);
  let t0 = 0, t1 = Infinity;
  for (let k = 0; k < 3; k++) {
    if (Math.abs(d[k]) < 1e-30) { if (o[k] < 0 || o[k] > 1) return null; continue; }
    const a = (0 - o[k]) / d[k], b = (1 - o[k]) / d[k];
    t0 = Math.max(t0, Math.min(a, b));
    t1 = Math.min(t1, Math.max(a, b));
  }
  if (!(t0 < t1)) return null;
  const dt = (t1 - t0) / n;
  let T = 1, best = null;
  for (let i = 0; i < n && T > 1e-3; i++) {
    const t = t0 + (i + 0.5) * dt;
    const val = leafValue(packed, o.map((v, k) => Math.min(Math.max(v + t * d[k], 0), 1)));
    if (val >= 0) continue;
    const leaf = -val - 1;
    const { sigma } = leafData(packed, leaf);
    const a = 1 - Math.exp(-Math.max(sigma, 0) * dt);
    const w = T * a;
    if (!best || w > best.weight) best = { leaf, weight: w, t };
    T *= 1 - a;
  }
  if (!best) return null;
  const point = [0, 1, 2].map((k) => origin[k] + best.t * dir[k]);
  return { ...best, point, ...leafData(packed, best.leaf) };
}

// Lumisphere image (size x size RGBA8, rows top-down) of a probed leaf as seen by a camera with
// rotation c2w (row-major 16): the sphere pixel with outward normal n shows the colour a ray
// travelling along -n sees; outside the disk: transparent.
export function lumisphere(packed, coeffs, c2w, size) {
  const img = new Uint8ClampedArray(size * size * 4);
  for (let v = 0; v < size; v++) {
    for (let u = 0; u < size; u++) {
      const x = (2 * (u + 0.5)) / size - 1, y = 1 - (2 * (v + 0.5)) / size;
      const r2 = x * x + y * y;
      if (r2 > 1) continue;
      const z = Math.sqrt(1 - r2);           // camera space: +z towards the viewer
      const n = [0, 1, 2].map((k) => c2w[4 * k] * x + c2w[4 * k + 1] * y + c2w[4 * k + 2] * z);
      const col = colorOf(packed, coeffs, n.map((w) => -w));
      const o = 4 * (v * size + u);
      img[o] = Math.round(col[0] * 255); img[o + 1] = Math.round(col[1] * 255);
      img[o + 2] = Math.round(col[2] * 255); img[o + 3] = 255;
    }
  }
  return img;
}

// The ray the tree sees for the world ray (origin, dir): unit direction; for an NDC tree
// (ndc: {fx, fy, width, height, near}) the same world -> NDC map as the shader and
// to_ndc_rays(clip=True) (a camera past the near plane starts where it stands); null when
// the ray never reaches the NDC volume. [origin, dir].
export function treeRay(origin, dir, ndc = null) {
  const l = Math.hypot(...dir) || 1;
  const d = dir.map((v) => v / l);
  if (!ndc) return [origin, d];
  const ax = -2 * ndc.fx / ndc.width, ay = -2 * ndc.fy / ndc.height, n = ndc.near;
  let o, d2;
  if (origin[2] <= -n) {
    o = [ax * origin[0] / origin[2], ay * origin[1] / origin[2], 1 + 2 * n / origin[2]];
    d2 = [ax * (d[0] * origin[2] - origin[0] * d[2]), ay * (d[1] * origin[2] - origin[1] * d[2]),
      -2 * n * d[2]];
  } else if (d[2] < -1e-12) {
    const t = -(n + origin[2]) / d[2];
    const on = origin.map((v, k) => v + t * d[k]);
    const rx = on[0] / on[2], ry = on[1] / on[2];
    o = [ax * rx, ay * ry, 1 + 2 * n / on[2]];
    d2 = [ax * (d[0] / d[2] - rx), ay * (d[1] / d[2] - ry), -2 * n / on[2]];
  } else {
    return null;
  }
  const l2 = Math.hypot(...d2);
  if (!(l2 > 0) || !(Math.abs(o[0]) <= 1e4 && Math.abs(o[1]) <= 1e4)) return null;
  return [o, d2.map((v) => v / l2)];
}
