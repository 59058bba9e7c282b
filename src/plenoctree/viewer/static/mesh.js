// Meshes inserted into the scene (as in the paper's viewer): OBJ / GLB parsing and a WebGL2
// pass that rasterises them (vertex colours under a headlight, depth test) into an offscreen
// target holding colour and the world distance along each pixel's ray. The volume pass then stops each ray at
// that distance and composites the mesh colour behind the volume in front of it, so the mesh
// is occluded by the volume exactly as far as the volume is opaque.

import { UP } from "./camera.js";

export class MeshError extends Error {
  constructor(message) { super(message); this.name = "MeshError"; }
}

// OBJ: "v x y z [r g b]" and "f a b c ..." (polygons fanned, negative indices, a/b/c forms).
export function parseObj(text, name = "mesh.obj") {
  const pos = [], col = [], idx = [];
  let hasColor = false;
  for (const raw of text.split("\n")) {
    const line = raw.trim();
    if (line.startsWith("v ")) {
      const p = line.split(/\s+/).slice(1).map(Number);
      if (p.length < 3 || p.slice(0, 3).some((v) => !Number.isFinite(v))) throw new MeshError(`${name}: bad vertex line '${line}'`);
      pos.push(p[0], p[1], p[2]);
      if (p.length >= 6) { hasColor = true; col.push(p[3], p[4], p[5]); } else col.push(0.8, 0.8, 0.8);
    } else if (line.startsWith("f ")) {
      const n = pos.length / 3;
      const f = line.split(/\s+/).slice(1).map((t) => { const i = parseInt(t.split("/")[0], 10); return i < 0 ? n + i : i - 1; });
      if (f.length < 3 || f.some((i) => !(i >= 0 && i < n))) throw new MeshError(`${name}: bad face line '${line}'`);
      for (let k = 1; k + 1 < f.length; k++) idx.push(f[0], f[k], f[k + 1]);
    }
  }
  if (!idx.length) throw new MeshError(`${name}: no faces`);
  return { positions: new Float32Array(pos), colors: new Float32Array(col), indices: new Uint32Array(idx), hasColor, yUp: false };
}

const COMPONENTS = { SCALAR: 1, VEC2: 2, VEC3: 3, VEC4: 4 };
const TYPES = { 5121: [Uint8Array, 255], 5123: [Uint16Array, 65535], 5125: [Uint32Array, 1], 5126: [Float32Array, 1] };

// GLB (binary glTF 2.0): every triangle primitive of every mesh; POSITION, optional COLOR_0.
export function parseGlb(buffer, name = "mesh.glb") {
  const dv = new DataView(buffer);
  if (buffer.byteLength < 20 || dv.getUint32(0, true) !== 0x46546c67) throw new MeshError(`${name}: not a GLB file`);
  let off = 12, json = null, bin = null;
  while (off + 8 <= buffer.byteLength) {
    const len = dv.getUint32(off, true), type = dv.getUint32(off + 4, true);
    const chunk = buffer.slice(off + 8, off + 8 + len);
    if (type === 0x4e4f534a) json = JSON.parse(new TextDecoder().decode(chunk));
    else if (type === 0x004e4942) bin = chunk;
    off += 8 + len;
  }
  if (!json || !bin) throw new MeshError(`${name}: GLB without JSON or binary chunk`);
  const read = (ai) => {
    const acc = json.accessors[ai], view = json.bufferViews[acc.bufferView];
    const [T, norm] = TYPES[acc.componentType] || [];
    if (!T) throw new MeshError(`${name}: accessor component type ${acc.componentType} not supported`);
    const n = acc.count * COMPONENTS[acc.type];
    const start = (view.byteOffset || 0) + (acc.byteOffset || 0);
    const arr = new T(bin.slice(start, start + n * T.BYTES_PER_ELEMENT));
    return { arr, norm, comps: COMPONENTS[acc.type] };
  };
  const pos = [], col = [], idx = [];
  for (const mesh of json.meshes || []) {
    for (const prim of mesh.primitives) {
      if ((prim.mode ?? 4) !== 4) continue;
      const base = pos.length / 3;
      const p = read(prim.attributes.POSITION).arr;
      for (let i = 0; i < p.length; i++) pos.push(p[i]);   // (no spread: large meshes)
      const nv = p.length / 3;
      if (prim.attributes.COLOR_0 !== undefined) {
        const c = read(prim.attributes.COLOR_0);
        for (let i = 0; i < nv; i++) for (let k = 0; k < 3; k++) col.push(c.arr[i * c.comps + k] / c.norm);
      } else for (let i = 0; i < nv; i++) col.push(0.8, 0.8, 0.8);
      const ind = prim.indices !== undefined ? read(prim.indices).arr : Uint32Array.from({ length: nv }, (_, i) => i);
      for (const i of ind) idx.push(base + i);
    }
  }
  if (!idx.length) throw new MeshError(`${name}: no triangles`);
  return { positions: new Float32Array(pos), colors: new Float32Array(col), indices: new Uint32Array(idx), hasColor: true, yUp: true };
}

// glTF is +Y up: turn it onto the scene's up axis (inverse of plenoctree export's rotation).
export function toSceneUp(mesh, up) {
  if (!mesh.yUp) return mesh;
  const u = UP[up] || UP["+z"];
  const p = mesh.positions, out = new Float32Array(p.length);
  // rows of R (scene -> glTF) for each up axis; world = R^T g
  const R = { "+z": [[1, 0, 0], [0, 0, 1], [0, -1, 0]], "-z": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
    "+y": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "-y": [[1, 0, 0], [0, -1, 0], [0, 0, -1]],
    "+x": [[0, 1, 0], [1, 0, 0], [0, 0, -1]], "-x": [[0, 1, 0], [-1, 0, 0], [0, 0, 1]] }[up] || null;
  if (!R || !u) return mesh;
  for (let i = 0; i < p.length; i += 3) {
    for (let k = 0; k < 3; k++) out[i + k] = R[0][k] * p[i] + R[1][k] * p[i + 1] + R[2][k] * p[i + 2];
  }
  return { ...mesh, positions: out, yUp: false };
}

// Headlight Lambert shading of the mesh colour (two-sided, a light at the eye):
// shade = MESH_AMBIENT + (1 - MESH_AMBIENT) |n . v|, v the unit ray direction, n the
// interpolated area-weighted vertex normal (vertexNormals).
export const MESH_AMBIENT = 0.3;

// Area-weighted vertex normals, Float32Array [3 n] (unit; 0 for vertices of no face).
export function vertexNormals(positions, indices) {
  const nrm = new Float32Array(positions.length);
  for (let f = 0; f + 2 < indices.length; f += 3) {
    const a = indices[f] * 3, b = indices[f + 1] * 3, c = indices[f + 2] * 3;
    const u = [0, 1, 2].map((k) => positions[b + k] - positions[a + k]);
    const w = [0, 1, 2].map((k) => positions[c + k] - positions[a + k]);
    const n = [u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]];
    for (const v of [a, b, c]) for (let k = 0; k < 3; k++) nrm[v + k] += n[k];
  }
  for (let v = 0; v < nrm.length; v += 3) {
    const l = Math.hypot(nrm[v], nrm[v + 1], nrm[v + 2]);
    if (l > 0) for (let k = 0; k < 3; k++) nrm[v + k] /= l;
  }
  return nrm;
}

const VS = `#version 300 es
uniform mat4 u_w2c;            // world -> camera (OpenGL camera: looks down -z)
uniform vec4 u_intr;           // fx, fy, cx, cy (pixels)
uniform vec2 u_size;           // width, height
uniform vec2 u_clip;           // near, far (world units)
uniform vec3 u_eye;            // camera centre (world)
in vec3 a_pos;
in vec3 a_col;
in vec3 a_nrm;
in vec4 a_plane;               // the triangle's plane n . x = w (world, n unit)
out vec3 v_col;
out vec3 v_cam;
out vec3 v_nrm;
flat out vec4 v_plane;         // the same plane in camera coordinates
void main() {
  vec4 pc = u_w2c * vec4(a_pos, 1.0);
  float z = -pc.z;
  // pixel u = cx + fx x / z (from the left), v = cy - fy y / z (from the top); NDC x = 2u/W - 1,
  // y = 1 - 2v/H, both times w = z
  // clip coordinates linear in the camera-space position (so clipping behind the eye works)
  float n = u_clip.x, f = u_clip.y;
  float zc = ((f + n) * z - 2.0 * f * n) / (f - n);
  gl_Position = vec4((2.0 * u_intr.z / u_size.x - 1.0) * z + 2.0 * u_intr.x * pc.x / u_size.x,
                     (1.0 - 2.0 * u_intr.w / u_size.y) * z + 2.0 * u_intr.y * pc.y / u_size.y,
                     zc, z);
  v_col = a_col;
  v_cam = pc.xyz;
  v_nrm = mat3(u_w2c) * a_nrm;   // rotation only (camera space)
  v_plane = vec4(mat3(u_w2c) * a_plane.xyz, a_plane.w - dot(a_plane.xyz, u_eye));
}`;

const FS = `#version 300 es
precision highp float;
uniform float u_ambient;       // MESH_AMBIENT; 1 = unlit
uniform vec4 u_intr;
uniform vec2 u_size;
in vec3 v_col;
in vec3 v_cam;
in vec3 v_nrm;
flat in vec4 v_plane;
layout(location = 0) out vec4 o_col;
layout(location = 1) out vec4 o_dist;
void main() {
  float ln = length(v_nrm);
  // no normal (degenerate faces): flat normal of the facet from screen-space derivatives
  vec3 n = ln > 1e-6 ? v_nrm / ln : normalize(cross(dFdx(v_cam), dFdy(v_cam)));
  float lambert = abs(dot(n, normalize(v_cam)));          // headlight, two-sided
  o_col = vec4(v_col * (u_ambient + (1.0 - u_ambient) * lambert), 1.0);
  // world distance from the eye along this pixel's ray (the volume pass's ray: pixel centre),
  // intersected exactly with the triangle's plane (interpolating the distance is not precise
  // enough in front of dense volume cells)
  vec3 rc = normalize(vec3((gl_FragCoord.x - u_intr.z) / u_intr.x,
                           -((u_size.y - gl_FragCoord.y) - u_intr.w) / u_intr.y, -1.0));
  float den = dot(v_plane.xyz, rc);
  float dist = abs(den) > 1e-4 ? v_plane.w / den : length(v_cam);
  o_dist = vec4(dist, 0.0, 0.0, 1.0);
}`;

function compile(gl, type, src) {
  const sh = gl.createShader(type);
  gl.shaderSource(sh, src);
  gl.compileShader(sh);
  if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) throw new MeshError(`mesh shader: ${gl.getShaderInfoLog(sh)}`);
  return sh;
}

export class MeshPass {
  constructor(gl) {
    this.gl = gl;
    if (!gl.getExtension("EXT_color_buffer_float")) throw new MeshError("this browser cannot render float targets (EXT_color_buffer_float), needed for mesh occlusion");
    const prog = gl.createProgram();
    gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, VS));
    gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, FS));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new MeshError(`mesh program: ${gl.getProgramInfoLog(prog)}`);
    this.prog = prog;
    this.meshes = [];
    this.size = [0, 0];
    this.shading = true;       // false: unlit vertex colours
  }

  add(mesh) {
    const gl = this.gl;
    // one vertex per triangle corner, so each corner can carry its triangle's plane
    const nTri = mesh.indices.length / 3, vn = vertexNormals(mesh.positions, mesh.indices);
    const pos = new Float32Array(nTri * 9), col = new Float32Array(nTri * 9);
    const nrm = new Float32Array(nTri * 9), plane = new Float32Array(nTri * 12);
    const P = mesh.positions;
    for (let f = 0; f < nTri; f++) {
      const v = [0, 1, 2].map((c) => mesh.indices[3 * f + c] * 3);
      const e1 = [0, 1, 2].map((k) => P[v[1] + k] - P[v[0] + k]);
      const e2 = [0, 1, 2].map((k) => P[v[2] + k] - P[v[0] + k]);
      let n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]];
      const l = Math.hypot(...n) || 1;
      n = n.map((x) => x / l);
      const w = n[0] * P[v[0]] + n[1] * P[v[0] + 1] + n[2] * P[v[0] + 2];
      for (let c = 0; c < 3; c++) {
        for (let k = 0; k < 3; k++) {
          pos[9 * f + 3 * c + k] = P[v[c] + k];
          col[9 * f + 3 * c + k] = mesh.colors[v[c] + k];
          nrm[9 * f + 3 * c + k] = vn[v[c] + k];
        }
        plane.set([n[0], n[1], n[2], w], 12 * f + 4 * c);
      }
    }
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const buf = (data, name, size = 3) => {
      const loc = gl.getAttribLocation(this.prog, name);
      const b = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, b);
      gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, size, gl.FLOAT, false, 0, 0);
    };
    buf(pos, "a_pos");
    buf(col, "a_col");
    buf(nrm, "a_nrm");
    buf(plane, "a_plane", 4);
    gl.bindVertexArray(null);
    let far = 0;
    for (let i = 0; i < P.length; i++) far = Math.max(far, Math.abs(P[i]));
    this.meshes.push({ vao, count: nTri * 3, extent: far });
  }

  clear() { this.meshes = []; }

  _targets(w, h) {
    const gl = this.gl;
    if (this.fbo && this.size[0] === w && this.size[1] === h) return;
    const tex = (internal, format, type) => {
      const t = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, t);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.texImage2D(gl.TEXTURE_2D, 0, internal, w, h, 0, format, type, null);
      return t;
    };
    this.colorTex = tex(gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE);
    this.distTex = tex(gl.R32F, gl.RED, gl.FLOAT);
    const depth = gl.createRenderbuffer();
    gl.bindRenderbuffer(gl.RENDERBUFFER, depth);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, w, h);
    this.fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, this.colorTex, 0);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT1, gl.TEXTURE_2D, this.distTex, 0);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    this.size = [w, h];
  }

  // Rasterise every mesh for `camera` ({c2w row-major, fx, fy, cx, cy, width, height}); the
  // distance target is 1e30 where no mesh is hit. Returns [colorTex, distTex].
  draw(camera) {
    const gl = this.gl, w = camera.width, h = camera.height;
    this._targets(w, h);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
    gl.drawBuffers([gl.COLOR_ATTACHMENT0, gl.COLOR_ATTACHMENT1]);
    gl.viewport(0, 0, w, h);
    gl.clearBufferfv(gl.COLOR, 0, [0, 0, 0, 0]);
    gl.clearBufferfv(gl.COLOR, 1, [1e30, 0, 0, 0]);
    gl.clearBufferfi(gl.DEPTH_STENCIL, 0, 1.0, 0);
    gl.enable(gl.DEPTH_TEST);
    gl.useProgram(this.prog);
    const m = camera.c2w;
    // w2c = [R^T | -R^T t] (column-major for GL)
    const R = [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]], t = [m[3], m[7], m[11]];
    const w2c = new Float32Array(16);
    for (let i = 0; i < 3; i++) {
      for (let j = 0; j < 3; j++) w2c[j * 4 + i] = R[j][i];
      w2c[12 + i] = -(R[0][i] * t[0] + R[1][i] * t[1] + R[2][i] * t[2]);
    }
    w2c[15] = 1;
    const P = (n) => gl.getUniformLocation(this.prog, n);
    gl.uniformMatrix4fv(P("u_w2c"), false, w2c);
    gl.uniform4f(P("u_intr"), camera.fx, camera.fy, camera.cx, camera.cy);
    gl.uniform2f(P("u_size"), w, h);
    gl.uniform1f(P("u_ambient"), this.shading ? MESH_AMBIENT : 1.0);
    gl.uniform3f(P("u_eye"), t[0], t[1], t[2]);
    const extent = Math.max(1, ...this.meshes.map((x) => x.extent)) + Math.hypot(...t);
    gl.uniform2f(P("u_clip"), 1e-3 * extent, 4 * extent);
    for (const x of this.meshes) {
      gl.bindVertexArray(x.vao);
      gl.drawArrays(gl.TRIANGLES, 0, x.count);
    }
    gl.bindVertexArray(null);
    gl.disable(gl.DEPTH_TEST);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    return [this.colorTex, this.distTex];
  }
}
