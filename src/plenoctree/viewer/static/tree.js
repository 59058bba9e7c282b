// Decode a PlenOctree file (native .npz, svox .npz, compressed .plnz / svox compressed) into
// the two textures the shader reads, checking the device's texture limits first.
//
// Child texture (R32I, one texel per cell, cell = node*8 + i*4 + j*2 + k):
//   > 0  relative offset to the child node;  0  empty leaf (sigma = 0);  < 0  leaf -(v+1).
// Data texture (RGBA16F): per non-empty leaf the values (sigma, R_0, G_0, B_0, R_1, G_1, B_1, ...)
// packed 4 to a texel, zero-padded to 1 + 3 ceil((B - 1) / 4) texels (SH16: 13, SH9: 7).
// Both are 2-D texture arrays (several layers only for very large trees); see planTexture.

import { FormatError } from "./npz.js";

export class LimitError extends Error {
  constructor(message) {
    super(message);
    this.name = "LimitError";
  }
}

export const MAX_VIEWER_DEPTH = 22;   // levels the shader can descend (float32 positions)
export const MAX_SG_LOBES = 32;
const SH_BASES = { 1: 0, 4: 1, 9: 2, 16: 3, 25: 4 };

// float32 -> float16 bits (round to nearest even), for trees stored as float32.
const f32 = new Float32Array(1);
const u32 = new Uint32Array(f32.buffer);
export function toHalfBits(x) {
  f32[0] = x;
  const b = u32[0];
  const sign = (b >>> 16) & 0x8000;
  const exp = (b >>> 23) & 0xff;
  let mant = b & 0x7fffff;
  if (exp === 0xff) return sign | 0x7c00 | (mant ? 0x200 : 0);
  let e = exp - 127 + 15;
  if (e >= 0x1f) return sign | 0x7c00;
  if (e <= 0) {
    if (e < -10) return sign;
    mant |= 0x800000;
    const shift = 14 - e;
    let h = mant >>> shift;
    const rem = mant & ((1 << shift) - 1);
    const half = 1 << (shift - 1);
    if (rem > half || (rem === half && (h & 1))) h += 1;
    return sign | h;
  }
  let h = (e << 10) | (mant >>> 13);
  const rem = mant & 0x1fff;
  if (rem > 0x1000 || (rem === 0x1000 && (h & 1))) h += 1;
  return sign | h;
}

export function halfToFloat(h) {
  const s = h & 0x8000 ? -1 : 1;
  const e = (h >>> 10) & 0x1f;
  const m = h & 0x3ff;
  if (e === 0) return s * m * 2 ** -24;
  if (e === 0x1f) return m ? NaN : s * Infinity;
  return s * (1 + m / 1024) * 2 ** (e - 15);
}

export function parseFormat(name, fileName) {
  const fmt = String(name).trim().toUpperCase();
  if (fmt === "RGBA") return { name: fmt, kind: 2, basisDim: 1, shDegree: -1 };
  const m = /^(SH|SG)(\d+)$/.exec(fmt);
  if (!m) throw new FormatError(`${fileName}: data format '${name}' is not supported by the viewer (SH1..SH25, SG<B>, RGBA)`);
  const b = Number(m[2]);
  if (m[1] === "SH") {
    if (!(b in SH_BASES)) throw new FormatError(`${fileName}: SH basis count ${b} is not 1, 4, 9, 16 or 25`);
    return { name: fmt, kind: 0, basisDim: b, shDegree: SH_BASES[b] };
  }
  if (b < 1 || b > MAX_SG_LOBES) throw new FormatError(`${fileName}: SG with ${b} lobes (the viewer supports 1..${MAX_SG_LOBES})`);
  return { name: fmt, kind: 1, basisDim: b, shDegree: -1 };
}

const pow2floor = (x) => 2 ** Math.floor(Math.log2(x));

// Texture layout for `items` items of `perItem` texels each, within the device limits.
// Items per row and (with several layers) the layer height are powers of two, so the shader
// finds texel t of item i with shifts and masks: x = (i & (perRow-1)) * perItem + t,
// row = i >> log2(perRow), y = row & (H-1), layer = row >> log2(H).
export function planTexture(items, perItem, limits, what) {
  const max = limits.maxTextureSize;
  if (perItem > max) {
    throw new LimitError(`${what}: ${perItem} texels per item do not fit in one row of ${max}`);
  }
  const perRow = Math.min(pow2floor(max / perItem), 2 ** Math.ceil(Math.log2(Math.max(items, 1))));
  const rows = Math.max(1, Math.ceil(items / perRow));
  let height = rows, layers = 1, log2h = 30;
  if (rows > max) {
    height = pow2floor(max);
    layers = Math.ceil(rows / height);
    log2h = Math.log2(height);
  }
  const plan = { width: perRow * perItem, height, layers, perRow, perItem, rows,
    log2PerRow: Math.log2(perRow), log2h };
  if (layers > limits.maxLayers) {
    const need = `${plan.width} x ${rows} texels`;
    const have = `${max} x ${max} x ${limits.maxLayers} layers`;
    throw new LimitError(`${what} needs ${need} (${items.toLocaleString()} items), more than this device allows (${have}; MAX_TEXTURE_SIZE = ${max}, MAX_ARRAY_TEXTURE_LAYERS = ${limits.maxLayers})`);
  }
  return plan;
}

// Texels per leaf: texel 0 = (sigma, R_0, G_0, B_0); then groups of 3 texels hold the RGB
// triplets of 4 further bases (12 values): bases 4g+1 .. 4g+4 in texels 3g+1 .. 3g+3.
export const basisGroups = (B) => Math.ceil((B - 1) / 4);
export const texelsPerLeaf = (B) => 1 + 3 * basisGroups(B);

function scalar(arr) {
  if (arr.dtype === "str") return arr.data;
  const v = arr.data[0];
  return typeof v === "bigint" ? Number(v) : v;
}

function toInt32(arr, what) {
  if (arr.dtype === "i4") return arr.data;
  const out = new Int32Array(arr.data.length);
  for (let i = 0; i < out.length; i++) {
    const v = Number(arr.data[i]);
    if (!Number.isInteger(v) || Math.abs(v) > 0x7fffffff) throw new FormatError(`${what}: value out of range`);
    out[i] = v;
  }
  return out;
}

function vec3(arr, what) {
  const d = arr.data;
  if (arr.dtype === "str" || (d.length !== 3 && d.length !== 1)) throw new FormatError(`${what} must be 3 numbers`);
  const v = [0, 1, 2].map((i) => Number(d[d.length === 1 ? 0 : i]));
  if (!v.every(Number.isFinite)) throw new FormatError(`${what} has non-finite values`);
  return v;
}

// Breadth-first depth of every node; throws on offsets that leave the array or revisit nodes.
function nodeDepths(child, nNodes, fileName) {
  const depth = new Int32Array(nNodes).fill(-1);
  depth[0] = 0;
  let maxDepth = 0;
  const queue = new Int32Array(nNodes);
  let head = 0, tail = 1;
  queue[0] = 0;
  while (head < tail) {
    const node = queue[head++];
    for (let c = 0; c < 8; c++) {
      const off = child[node * 8 + c];
      if (off === 0) continue;
      const kid = node + off;
      if (off < 0) {
        throw new FormatError(`${fileName}: child offset ${off} at cell ${node * 8 + c} points backwards (an svox tree with reused node slots); re-save it with plenoctree first (load_tree + save_tree, or plenoctree lod)`);
      }
      if (kid >= nNodes || depth[kid] >= 0) {
        throw new FormatError(`${fileName}: child offsets do not form a tree (cell ${node * 8 + c} -> node ${kid})`);
      }
      depth[kid] = depth[node] + 1;
      if (depth[kid] > maxDepth) maxDepth = depth[kid];
      queue[tail++] = kid;
    }
  }
  return maxDepth;
}

const halfPositive = (h) => (h & 0x8000) === 0 && (h & 0x7fff) !== 0;
const halfFinite = (h) => (h & 0x7c00) !== 0x7c00;

// The NDC space a forward-facing tree lives in (plenoctree.octree.ndc): the header's "ndc"
// (native format_version 2, .plnz version 2) or the svox layout's ndc_config [width, height,
// fx, fy, near]; null for world-space trees.
async function readNdc(archive, header, fail) {
  let n = header.ndc || null;
  if (!n && archive.has("ndc_config")) {
    const a = await archive.read("ndc_config");
    if (a.dtype === "str" || a.data.length !== 5) fail("'ndc_config' must be 5 numbers (width, height, fx, fy, near)");
    const v = Array.from(a.data, Number);
    n = { width: v[0], height: v[1], fx: v[2], fy: v[3], near: v[4] };
  }
  if (!n) return null;
  for (const k of ["width", "height", "fx", "fy", "near"]) {
    if (!(Number.isFinite(n[k]) && n[k] > 0)) fail(`NDC setting '${k}' must be a positive number, got ${n[k]}`);
  }
  return { width: n.width, height: n.height, fx: n.fx, fy: n.fy, near: n.near };
}

// archive: NpzArchive. limits: {maxTextureSize, maxLayers, maxBytes}. onStatus(text) optional.
export async function packTree(archive, limits, onStatus = () => {}) {
  const fileName = archive.fileName;
  const fail = (msg) => { throw new FormatError(`${fileName}: ${msg}`); };
  const compressed = archive.has("quant_colors") || archive.has("quant_map");
  if (!archive.has("child") || !(compressed || archive.has("data"))) {
    fail(`not a PlenOctree tree (needs 'child' and 'data' or 'quant_colors'; found ${archive.keys().join(", ") || "no arrays"})`);
  }
  let header = {};
  if (archive.has("header")) {
    try { header = JSON.parse(scalar(await archive.read("header"))); } catch (e) { fail(`bad header (${e.message})`); }
  }
  if (archive.has("plnz_version")) {
    const v = scalar(await archive.read("plnz_version"));
    if (v !== 1 && v !== 2) fail(`unknown plnz_version ${v} (this viewer reads versions 1, 2)`);
  }
  const childArr = await archive.read("child");
  if (childArr.shape.length !== 4 || childArr.shape.slice(1).join() !== "2,2,2" || childArr.shape[0] < 1) {
    fail(`'child' must have shape [n, 2, 2, 2], got [${childArr.shape}]`);
  }
  const capacity = childArr.shape[0];
  let nNodes = capacity;
  if (archive.has("n_internal")) nNodes = scalar(await archive.read("n_internal"));
  if (!(nNodes >= 1 && nNodes <= capacity)) fail(`n_internal ${nNodes} outside 1..${capacity}`);
  const child = toInt32(childArr, `${fileName}: 'child'`);
  const offset = vec3(await archive.read("offset"), `${fileName}: 'offset'`);
  const invKey = archive.has("invradius3") ? "invradius3" : "invradius";
  const invradius = vec3(await archive.read(invKey), `${fileName}: '${invKey}'`);
  if (!invradius.every((v) => v > 0)) fail("invradius must be > 0");
  const maxDepth = nodeDepths(child, nNodes, fileName);
  if (maxDepth + 1 > MAX_VIEWER_DEPTH) fail(`tree is ${maxDepth + 1} levels deep; the viewer supports ${MAX_VIEWER_DEPTH}`);

  // Data format and the per-cell sources of sigma and colour.
  let fmtName = header.data_format;
  if (fmtName === undefined && archive.has("data_format")) fmtName = scalar(await archive.read("data_format"));
  const nCells = nNodes * 8;
  let sigmaBits = null, data = null, D = 0, qc = null, qm = null, retained = null, nQuant = 0, nRet = 0, K = 0;
  if (compressed) {
    for (const k of ["sigma", "quant_colors", "quant_map"]) if (!archive.has(k)) fail(`missing array '${k}'`);
    const qcArr = await archive.read("quant_colors");
    if (qcArr.dtype !== "f2" || qcArr.shape.length !== 3 || qcArr.shape[2] !== 3) fail(`'quant_colors' must be float16 [bases, K, 3], got ${qcArr.dtype} [${qcArr.shape}]`);
    [nQuant, K] = qcArr.shape;
    qc = qcArr.data;
    if (archive.has("data_retained")) {
      const ra = await archive.read("data_retained");
      if (ra.dtype !== "f2" || ra.shape.length !== 6 || ra.shape[1] !== capacity) fail(`'data_retained' must be float16 [r, ${capacity}, 2, 2, 2, 3], got ${ra.dtype} [${ra.shape}]`);
      nRet = ra.shape[0];
      retained = ra.data;
    }
    if (fmtName === undefined) fmtName = `SH${nQuant + nRet}`;
  } else if (fmtName === undefined) {
    // legacy svox: infer SH from data_dim without reading the data yet
    const dd = archive.has("data_dim") ? scalar(await archive.read("data_dim")) : null;
    if (dd === null) fail("no data_format and no data_dim");
    fmtName = `SH${(dd - 1) / 3}`;
  }
  const format = parseFormat(fmtName, fileName);
  const B = format.basisDim;
  if (compressed && nQuant + nRet !== B) fail(`${format.name} has ${B} bases but the file holds ${nQuant} quantised + ${nRet} retained`);

  // Limits for the child texture can be checked now; the data texture needs the leaf count.
  const childPlan = planTexture(nCells, 1, limits, "The octree structure (child texture)");
  if (compressed) {
    const sa = await archive.read("sigma");
    if (sa.dtype !== "f2" || sa.data.length !== capacity * 8) fail(`'sigma' must be float16 [${capacity}, 2, 2, 2]`);
    sigmaBits = sa.data;
  } else {
    const bytes = archive.size("data");
    if (bytes > limits.maxBytes) {
      throw new LimitError(`The tree's data is ${(bytes / 1e6).toFixed(0)} MB uncompressed, more than this page will load (${(limits.maxBytes / 1e6).toFixed(0)} MB)`);
    }
    onStatus("Inflating data...");
    const da = await archive.read("data");
    if (!["f2", "f4", "f8"].includes(da.dtype) || da.shape.length !== 5 || da.shape[0] !== capacity) fail(`'data' must be float [${capacity}, 2, 2, 2, D], got ${da.dtype} [${da.shape}]`);
    D = da.shape[4];
    const wantD = format.kind === 2 ? 4 : 3 * B + 1;
    if (D !== wantD) fail(`data_dim ${D} does not match ${format.name} (expects ${wantD})`);
    data = da;
  }
  const sigmaOf = compressed
    ? (c) => sigmaBits[c]
    : data.dtype === "f2" ? (c) => data.data[c * D + D - 1] : (c) => toHalfBits(data.data[c * D + D - 1]);

  // Leaf numbering; the child texel array.
  onStatus("Packing the tree...");
  const childTex = new Int32Array(childPlan.width * childPlan.height * childPlan.layers);
  let nLeaves = 0;
  for (let c = 0; c < nCells; c++) {
    const v = child[c];
    if (v !== 0) { childTex[c] = v; continue; }
    const s = sigmaOf(c);
    if (!halfFinite(s)) fail(`sigma of cell ${c} is not finite`);
    if (halfPositive(s)) childTex[c] = -(++nLeaves);
  }
  const P = texelsPerLeaf(B);
  const dataPlan = planTexture(Math.max(nLeaves, 1), P, limits, "The tree's colour data (data texture)");
  const bytes = dataPlan.width * dataPlan.height * dataPlan.layers * 8 + childTex.byteLength;
  if (bytes > limits.maxBytes) {
    throw new LimitError(`The tree needs ${(bytes / 1e6).toFixed(0)} MB of textures (${nLeaves.toLocaleString()} leaves x ${B} bases), more than this page allows (${(limits.maxBytes / 1e6).toFixed(0)} MB)`);
  }
  let dataTex;
  try {
    dataTex = new Uint16Array(dataPlan.width * dataPlan.height * dataPlan.layers * 4);
  } catch (e) {
    throw new LimitError(`Out of memory allocating ${(bytes / 1e6).toFixed(0)} MB for the tree's textures`);
  }
  const qmArr = compressed ? await archive.read("quant_map") : null;
  if (compressed) {
    if (qmArr.dtype !== "u2" || qmArr.data.length !== nQuant * capacity * 8) fail(`'quant_map' must be uint16 [${nQuant}, ${capacity}, 2, 2, 2]`);
    qm = qmArr.data;
  }
  const rgba = format.kind === 2;
  const src = compressed ? null : data.data;
  const conv = compressed || data.dtype === "f2" ? (x) => x : toHalfBits;
  const capCells = capacity * 8;
  let leaf = 0;
  const perRowMask = dataPlan.perRow - 1;
  for (let c = 0; c < nCells; c++) {
    if (childTex[c] >= 0) continue;
    // leaf -> first texel (x, row) of the row-major layout
    const base = (((leaf >>> dataPlan.log2PerRow) * dataPlan.width) + (leaf & perRowMask) * P) * 4;
    dataTex[base] = sigmaOf(c);
    for (let b = 0; b < B; b++) {
      const o = base + 1 + 3 * b;
      if (compressed) {
        if (b < nRet) {
          const r = (b * capCells + c) * 3;
          dataTex[o] = retained[r]; dataTex[o + 1] = retained[r + 1]; dataTex[o + 2] = retained[r + 2];
        } else {
          const q = b - nRet;
          const idx = qm[q * capCells + c];
          if (idx >= K) fail(`codebook index ${idx} out of range for basis ${b} (codebook has ${K} entries) at cell ${c}`);
          const r = (q * K + idx) * 3;
          dataTex[o] = qc[r]; dataTex[o + 1] = qc[r + 1]; dataTex[o + 2] = qc[r + 2];
        }
      } else if (rgba) {
        const r = c * D;
        dataTex[o] = conv(src[r]); dataTex[o + 1] = conv(src[r + 1]); dataTex[o + 2] = conv(src[r + 2]);
      } else {
        const r = c * D + b;
        dataTex[o] = conv(src[r]); dataTex[o + 1] = conv(src[r + B]); dataTex[o + 2] = conv(src[r + 2 * B]);
      }
      if (!halfFinite(dataTex[o]) || !halfFinite(dataTex[o + 1]) || !halfFinite(dataTex[o + 2])) {
        fail(`colour coefficient of cell ${c}, basis ${b} is not finite`);
      }
    }
    leaf++;
  }
  let sg = null;
  if (format.kind === 1) {
    if (!archive.has("extra_data")) fail(`${format.name} needs 'extra_data' (SG lobes)`);
    const ed = await archive.read("extra_data");
    if (ed.shape.join() !== `${B},4`) fail(`'extra_data' must be [${B}, 4]`);
    sg = Float32Array.from(ed.data, Number);
  }
  const ndc = await readNdc(archive, header, fail);
  return {
    fileName, compressed, format, sg, offset, invradius, nNodes, nLeaves, maxDepth, ndc,
    bits: compressed ? Math.round(Math.log2(K)) : null, retain: nRet,
    child: { data: childTex, ...childPlan },
    data: { data: dataTex, ...dataPlan },
    textureBytes: bytes,
  };
}
