// Reading .npz / .plnz files (zip archives of .npy arrays) in the browser, with no library:
// the zip directory (incl. zip64) is parsed here, DEFLATE members are inflated with the
// built-in DecompressionStream('deflate-raw'), and every size and CRC is checked, so a
// truncated or foreign file raises a FormatError with a clear message.

export class FormatError extends Error {
  constructor(message) {
    super(message);
    this.name = "FormatError";
  }
}

const CRC_TABLE = (() => {
  const t = new Uint32Array(256);
  for (let n = 0; n < 256; n++) {
    let c = n;
    for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
    t[n] = c >>> 0;
  }
  return t;
})();

export function crc32(bytes) {
  let c = 0xffffffff;
  for (let i = 0; i < bytes.length; i++) c = CRC_TABLE[(c ^ bytes[i]) & 0xff] ^ (c >>> 8);
  return (c ^ 0xffffffff) >>> 0;
}

function u64(view, off) {
  const lo = view.getUint32(off, true);
  const hi = view.getUint32(off + 4, true);
  if (hi >= 0x200000) throw new FormatError("zip64 field too large");
  return hi * 0x100000000 + lo;
}

// Parse the central directory. Returns Map(name -> entry).
export function zipDirectory(buffer, fileName = "file") {
  const bytes = new Uint8Array(buffer);
  const view = new DataView(buffer);
  const n = bytes.length;
  const fail = (msg) => { throw new FormatError(`${fileName}: ${msg}`); };
  if (n < 22) fail(`not a PlenOctree tree file (only ${n} bytes)`);
  if (view.getUint32(0, true) !== 0x04034b50) {
    fail("not a PlenOctree tree file (not a zip/.npz archive: bad signature)");
  }
  let eocd = -1;
  for (let i = n - 22; i >= Math.max(0, n - 22 - 65535); i--) {
    if (view.getUint32(i, true) === 0x06054b50) { eocd = i; break; }
  }
  if (eocd < 0) fail("truncated or damaged archive (zip end-of-directory record not found)");
  let count = view.getUint16(eocd + 10, true);
  let cdSize = view.getUint32(eocd + 12, true);
  let cdOff = view.getUint32(eocd + 16, true);
  if (count === 0xffff || cdSize === 0xffffffff || cdOff === 0xffffffff) {
    const loc = eocd - 20;
    if (loc < 0 || view.getUint32(loc, true) !== 0x07064b50) fail("damaged zip64 locator");
    const rec = u64(view, loc + 8);
    if (rec + 56 > n || view.getUint32(rec, true) !== 0x06064b50) fail("damaged zip64 directory");
    count = u64(view, rec + 32);
    cdSize = u64(view, rec + 40);
    cdOff = u64(view, rec + 48);
  }
  if (cdOff + cdSize > n) fail("truncated archive (central directory past the end of the file)");
  const entries = new Map();
  let p = cdOff;
  const dec = new TextDecoder();
  for (let e = 0; e < count; e++) {
    if (p + 46 > n || view.getUint32(p, true) !== 0x02014b50) fail("damaged zip directory");
    const method = view.getUint16(p + 10, true);
    const crc = view.getUint32(p + 16, true);
    let csize = view.getUint32(p + 20, true);
    let size = view.getUint32(p + 24, true);
    const nameLen = view.getUint16(p + 28, true);
    const extraLen = view.getUint16(p + 30, true);
    const commentLen = view.getUint16(p + 32, true);
    let local = view.getUint32(p + 42, true);
    if (p + 46 + nameLen + extraLen > n) fail("damaged zip directory");
    const name = dec.decode(bytes.subarray(p + 46, p + 46 + nameLen));
    let q = p + 46 + nameLen;
    const end = q + extraLen;
    while (q + 4 <= end) {
      const id = view.getUint16(q, true);
      const len = view.getUint16(q + 2, true);
      if (id === 0x0001) {
        let r = q + 4;
        if (size === 0xffffffff) { size = u64(view, r); r += 8; }
        if (csize === 0xffffffff) { csize = u64(view, r); r += 8; }
        if (local === 0xffffffff) { local = u64(view, r); r += 8; }
      }
      q += 4 + len;
    }
    if (local + 30 > n || view.getUint32(local, true) !== 0x04034b50) {
      fail(`truncated archive (member ${name} lies past the end of the file)`);
    }
    const start = local + 30 + view.getUint16(local + 26, true) + view.getUint16(local + 28, true);
    if (start + csize > n) fail(`truncated archive (member ${name} is cut short)`);
    if (method !== 0 && method !== 8) fail(`member ${name}: unsupported zip compression ${method}`);
    entries.set(name, { name, method, crc, csize, size, start });
    p += 46 + nameLen + extraLen + commentLen;
  }
  return entries;
}

async function inflateRaw(bytes) {
  const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate-raw"));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

export async function memberBytes(buffer, entry, fileName = "file") {
  const raw = new Uint8Array(buffer, entry.start, entry.csize);
  let out;
  if (entry.method === 0) {
    out = raw;
  } else {
    try {
      out = await inflateRaw(raw);
    } catch (err) {
      throw new FormatError(`${fileName}: member ${entry.name}: damaged DEFLATE data (${err.message})`);
    }
  }
  if (out.length !== entry.size) {
    throw new FormatError(`${fileName}: member ${entry.name}: expected ${entry.size} bytes, got ${out.length} (truncated or damaged)`);
  }
  if (crc32(out) !== entry.crc) {
    throw new FormatError(`${fileName}: member ${entry.name}: CRC mismatch (damaged file)`);
  }
  return out;
}

const DTYPES = {
  "<f2": [Uint16Array, 2, "f2"], "<f4": [Float32Array, 4, "f4"], "<f8": [Float64Array, 8, "f8"],
  "<i4": [Int32Array, 4, "i4"], "<i8": [BigInt64Array, 8, "i8"], "<u2": [Uint16Array, 2, "u2"],
  "<u4": [Uint32Array, 4, "u4"], "|u1": [Uint8Array, 1, "u1"], "|b1": [Uint8Array, 1, "b1"],
  "<i2": [Int16Array, 2, "i2"], "|i1": [Int8Array, 1, "i1"], "<u8": [BigUint64Array, 8, "u8"],
};

// Parse one .npy payload: {dtype, shape, data} where data is a typed array (float16 stays as
// raw Uint16 bits, dtype "f2") or, for unicode scalars, a JS string.
export function parseNpy(bytes, what = "array") {
  const fail = (msg) => { throw new FormatError(`${what}: ${msg}`); };
  if (bytes.length < 10 || bytes[0] !== 0x93 || String.fromCharCode(...bytes.subarray(1, 6)) !== "NUMPY") {
    fail("not a .npy array");
  }
  const major = bytes[6];
  const dv = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  let hlen, hstart;
  if (major === 1) { hlen = dv.getUint16(8, true); hstart = 10; }
  else if (major === 2 || major === 3) { hlen = dv.getUint32(8, true); hstart = 12; }
  else fail(`unsupported .npy version ${major}`);
  if (hstart + hlen > bytes.length) fail("truncated .npy header");
  const header = new TextDecoder().decode(bytes.subarray(hstart, hstart + hlen));
  const descr = /'descr':\s*'([^']+)'/.exec(header);
  const fortran = /'fortran_order':\s*(True|False)/.exec(header);
  const shapeM = /'shape':\s*\(([^)]*)\)/.exec(header);
  if (!descr || !fortran || !shapeM) fail("bad .npy header");
  const shape = shapeM[1].split(",").map((s) => s.trim()).filter((s) => s.length).map(Number);
  if (shape.some((s) => !Number.isInteger(s) || s < 0)) fail("bad shape in .npy header");
  const count = shape.reduce((a, b) => a * b, 1);
  const off = hstart + hlen;
  const d = descr[1];
  const uni = /^<U(\d+)$/.exec(d);
  if (uni) {
    const width = Number(uni[1]);
    if (count !== 1) fail("only scalar strings are supported");
    if (off + 4 * width > bytes.length) fail("truncated string");
    const cps = [];
    for (let i = 0; i < width; i++) {
      const cp = dv.getUint32(off + 4 * i, true);
      if (cp === 0) break;
      cps.push(cp);
    }
    return { dtype: "str", shape, data: String.fromCodePoint(...cps) };
  }
  const spec = DTYPES[d];
  if (!spec) fail(`unsupported dtype ${d}`);
  if (fortran[1] === "True" && shape.length > 1) fail("Fortran-ordered arrays are not supported");
  const [Ctor, size, name] = spec;
  if (off + count * size !== bytes.length) {
    fail(`size mismatch: header says ${count} x ${size} bytes, member holds ${bytes.length - off}`);
  }
  const copy = bytes.slice(off, off + count * size);       // aligned copy
  return { dtype: name, shape, data: new Ctor(copy.buffer) };
}

// A lazily read archive: keys() lists the arrays, read(key) inflates and parses one.
export class NpzArchive {
  constructor(buffer, fileName = "file") {
    this.buffer = buffer;
    this.fileName = fileName;
    this.entries = zipDirectory(buffer, fileName);
    this.arrays = new Map();
    for (const [name, e] of this.entries) {
      if (name.endsWith(".npy")) this.arrays.set(name.slice(0, -4), e);
    }
  }
  keys() { return [...this.arrays.keys()]; }
  has(key) { return this.arrays.has(key); }
  // Uncompressed payload size in bytes (known before inflating).
  size(key) { return this.arrays.get(key).size; }
  async read(key) {
    const e = this.arrays.get(key);
    if (!e) throw new FormatError(`${this.fileName}: missing array '${key}' (found ${this.keys().join(", ")})`);
    const bytes = await memberBytes(this.buffer, e, this.fileName);
    return parseNpy(bytes, `${this.fileName}: array '${key}'`);
  }
}

// Download url into an ArrayBuffer, reporting progress through onStatus(text); FormatError
// (naming the URL) when it cannot be fetched or arrives cut short.
export async function fetchBuffer(url, onStatus = () => {}) {
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
    onStatus(`Downloading ${(got / 1e6).toFixed(1)}${total ? " / " + (total / 1e6).toFixed(1) : ""} MB`);
  }
  if (total && got !== total) throw new FormatError(`${url}: download cut short (${got} of ${total} bytes)`);
  const out = new Uint8Array(got);
  let p = 0;
  for (const c of chunks) { out.set(c, p); p += c.length; }
  return out.buffer;
}

// Bytes as base64 (for scripts reading pixels through window.viewer).
export function toBase64(bytes) {
  let s = "";
  for (let i = 0; i < bytes.length; i += 0x8000) s += String.fromCharCode.apply(null, bytes.subarray(i, i + 0x8000));
  return btoa(s);
}
