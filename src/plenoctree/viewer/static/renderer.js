// WebGL2 ray marcher for a packed PlenOctree (see tree.js for the texture layout).
// Each step finds the leaf of the point just past the current boundary by descending from the
// deepest node it shares with the previous point (a per-ray stack of the path), so most steps
// cost one or two child fetches instead of a full descent from the root.
// Same semantics as the CPU renderer (plenoctree/render/_torch_impl.py): exact voxel-boundary
// stepping with a step_eps push, T (1 - exp(-sigma delta)) weights, early stop when
// T < stop_thresh, background composited with the remaining T, colour sigmoid(sum_b k_b Y_b(d))
// over the basis range [sh_min, sh_max]. Uniform names follow RenderOptions.

const VERTEX = `#version 300 es
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}`;

const FRAGMENT = `#version 300 es
precision highp float;
precision highp int;
precision highp isampler2DArray;
precision highp sampler2DArray;

#define MAX_BASIS 36
#define QBITS 23
const float QSCALE = 8388608.0;   // 2^QBITS

uniform isampler2DArray u_child;
uniform sampler2DArray u_data;
uniform ivec3 u_child_layout;     // log2(items per row), log2(layer height), texels per item
uniform ivec3 u_data_layout;
uniform int u_basis_dim;
uniform int u_groups;             // groups of 4 bases after basis 0 (3 texels each)
uniform int u_kind;               // 0 SH, 1 SG, 2 RGBA
uniform int u_sh_degree;
uniform int u_sh_min;
uniform int u_sh_max;             // inclusive, already clamped
uniform vec4 u_sg[32];            // sharpness, mu_x, mu_y, mu_z
uniform mat4 u_c2w;
uniform vec4 u_intrinsics;        // fx, fy, cx, cy (pixels of the render target)
uniform float u_height;           // render target height in pixels
uniform vec3 u_offset;
uniform vec3 u_invradius;
uniform vec3 u_box_min;           // slicing box, tree units
uniform vec3 u_box_max;
uniform float u_stop_thresh;
uniform float u_step_eps;
uniform vec3 u_background;
uniform int u_mode;               // 0 rgb, 1 depth, 2 alpha
uniform vec2 u_depth_range;       // world distances mapped to white .. black
uniform int u_max_steps;
uniform int u_mesh;               // 1: inserted meshes (mesh.js) occlude the volume
uniform sampler2D u_mesh_color;   // their unlit colour and world distance along each ray
uniform sampler2D u_mesh_dist;
uniform int u_ndc;                // 1: the tree lives in NDC space (forward-facing scene)
uniform vec4 u_ndc_cam;           // NDC reference camera: 2 fx / W, 2 fy / H, near, unused
out vec4 frag_color;

// Index of the highest set bit of v > 0 (findMSB is not in GLSL ES 3.00).
int msb(int v) {
  int m = clamp(int(log2(float(v))), 0, 30);
  if ((v >> m) == 0) m -= 1;
  else if ((v >> (m + 1)) != 0) m += 1;
  return m;
}

// Texel t of item i (see planTexture in tree.js): shifts and masks only.
ivec3 texel(int i, int t, ivec3 lay) {
  int row = i >> lay.x;
  int x = (i - (row << lay.x)) * lay.z + t;
  return ivec3(x, row & ((1 << lay.y) - 1), row >> lay.y);
}

void basis_values(vec3 d, out float bv[MAX_BASIS]) {
  for (int i = 0; i < MAX_BASIS; ++i) bv[i] = 0.0;
  if (u_kind == 2) { bv[0] = 1.0; }
  else if (u_kind == 1) {
    for (int i = 0; i < 32; ++i) {
      if (i >= u_basis_dim) break;
      bv[i] = exp(u_sg[i].x * (dot(u_sg[i].yzw, d) - 1.0)) / float(u_basis_dim);
    }
  } else {
    float x = d.x, y = d.y, z = d.z;
    bv[0] = 0.28209479177387814;
    if (u_sh_degree >= 1) {
      bv[1] = -0.4886025119029199 * y; bv[2] = 0.4886025119029199 * z; bv[3] = -0.4886025119029199 * x;
    }
    float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    if (u_sh_degree >= 2) {
      bv[4] = 1.0925484305920792 * xy;
      bv[5] = -1.0925484305920792 * yz;
      bv[6] = 0.31539156525252005 * (2.0 * zz - xx - yy);
      bv[7] = -1.0925484305920792 * xz;
      bv[8] = 0.5462742152960396 * (xx - yy);
    }
    if (u_sh_degree >= 3) {
      bv[9] = -0.5900435899266435 * y * (3.0 * xx - yy);
      bv[10] = 2.890611442640554 * xy * z;
      bv[11] = -0.4570457994644658 * y * (4.0 * zz - xx - yy);
      bv[12] = 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
      bv[13] = -0.4570457994644658 * x * (4.0 * zz - xx - yy);
      bv[14] = 1.445305721320277 * z * (xx - yy);
      bv[15] = -0.5900435899266435 * x * (xx - 3.0 * yy);
    }
    if (u_sh_degree >= 4) {
      bv[16] = 2.5033429417967046 * xy * (xx - yy);
      bv[17] = -1.7701307697799304 * yz * (3.0 * xx - yy);
      bv[18] = 0.9461746957575601 * xy * (7.0 * zz - 1.0);
      bv[19] = -0.6690465435572892 * yz * (7.0 * zz - 3.0);
      bv[20] = 0.10578554691520431 * (zz * (35.0 * zz - 30.0) + 3.0);
      bv[21] = -0.6690465435572892 * xz * (7.0 * zz - 3.0);
      bv[22] = 0.47308734787878004 * (xx - yy) * (7.0 * zz - 1.0);
      bv[23] = -1.7701307697799304 * xz * (xx - 3.0 * yy);
      bv[24] = 0.6258357354491761 * (xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy));
    }
  }
  for (int i = 0; i < MAX_BASIS; ++i) {
    if (i < u_sh_min || i > u_sh_max) bv[i] = 0.0;
  }
}

void main() {
  // Pixel (u, v) from the top-left: gl_FragCoord.x = u + 0.5, v + 0.5 = height - gl_FragCoord.y.
  float px = gl_FragCoord.x;
  float py = u_height - gl_FragCoord.y;
  vec3 dcam = vec3((px - u_intrinsics.z) / u_intrinsics.x, -(py - u_intrinsics.w) / u_intrinsics.y, -1.0);
  vec3 dir = normalize(mat3(u_c2w) * dcam);
  vec3 origin = u_c2w[3].xyz;
  vec3 world_o = origin, world_d = dir;
  bool behind = false;
  if (u_ndc == 1) {
    // world ray -> NDC ray, any camera (plenoctree.datasets.ndc.to_ndc_rays(clip=True)):
    // NeRF's ray from the near plane; a camera past the near plane starts where it stands;
    // a ray that never reaches the NDC volume draws the background
    float near = u_ndc_cam.z;
    vec2 a = -u_ndc_cam.xy;
    vec3 o2, d2;
    if (origin.z <= -near) {
      o2 = vec3(a * origin.xy / origin.z, 1.0 + 2.0 * near / origin.z);
      d2 = vec3(a * (dir.xy * origin.z - origin.xy * dir.z), -2.0 * near * dir.z);
    } else if (dir.z < -1e-12) {
      vec3 on = origin + (-(near + origin.z) / dir.z) * dir;
      vec2 r = on.xy / on.z;
      o2 = vec3(a * r, 1.0 + 2.0 * near / on.z);
      d2 = vec3(a * (dir.xy / dir.z - r), -2.0 * near / on.z);
    } else {
      behind = true;
    }
    if (!behind && (any(greaterThan(abs(o2.xy), vec2(1e4))) || dot(d2, d2) <= 0.0)) behind = true;
    if (!behind) {
      origin = o2;
      dir = normalize(d2);
    }
  }

  float bv[MAX_BASIS];
  basis_values(dir, bv);

  vec3 o = u_offset + u_invradius * origin;
  vec3 d = u_invradius * dir;
  float eps_t = u_step_eps / length(d);
  vec3 dsafe = mix(d, vec3(1e-30), equal(d, vec3(0.0)));
  vec3 invd = 1.0 / dsafe;
  vec3 ta = (u_box_min - o) * invd;
  vec3 tb = (u_box_max - o) * invd;
  vec3 lo3 = min(ta, tb), hi3 = max(ta, tb);
  float t0 = max(max(max(lo3.x, lo3.y), lo3.z), 0.0);
  float t1 = min(min(hi3.x, hi3.y), hi3.z);
  vec3 positive = step(0.0, d);

  vec3 background = u_background;
  if (u_mesh == 1) {
    // a mesh surface ends the ray there and replaces the background behind the volume
    ivec2 pix = ivec2(gl_FragCoord.xy);
    float tm = texelFetch(u_mesh_dist, pix, 0).r;
    if (tm < 1e29 && u_ndc == 1) {
      // world hit point -> NDC point -> distance along the unit NDC ray (before the near
      // plane: negative, the mesh hides the whole volume)
      vec3 p = world_o + tm * world_d;
      if (p.z < 0.0) {
        vec3 q = vec3(-u_ndc_cam.x * p.x / p.z, -u_ndc_cam.y * p.y / p.z, 1.0 + 2.0 * u_ndc_cam.z / p.z);
        tm = max(dot(q - origin, dir), 0.0);
      } else {
        tm = 0.0;
      }
    }
    if (tm < 1e29) {
      t1 = min(t1, tm);
      background = texelFetch(u_mesh_color, pix, 0).rgb;
    }
  }
  vec3 rgb = vec3(0.0);
  float T = 1.0, wsum = 0.0, wtsum = 0.0;
  float t = t0;
  if (t0 < t1 && !behind) {
    // stack[l] = node holding the level-l cell of the current point; a step restarts the
    // descent at the deepest node it shares with the previous point (same high bits).
    int stack[QBITS];
    stack[0] = 0;
    ivec3 prev = ivec3(0);
    int prev_level = 0;
    for (int s = 0; s < u_max_steps; ++s) {
      vec3 q = o + (t + eps_t) * d;
      ivec3 qi = ivec3(clamp(floor(q * QSCALE), 0.0, QSCALE - 1.0));
      ivec3 x = qi ^ prev;
      int diff = x.x | x.y | x.z;
      int level = diff == 0 ? prev_level : min(prev_level, QBITS - 1 - msb(diff));
      int node = stack[level], val = 0;
      for (; level < QBITS; ++level) {
        ivec3 bit = (qi >> (QBITS - 1 - level)) & 1;
        int cell = node * 8 + bit.x * 4 + bit.y * 2 + bit.z;
        val = texelFetch(u_child, texel(cell, 0, u_child_layout), 0).r;
        if (val <= 0) break;
        node += val;
        stack[level + 1] = node;
      }
      prev = qi;
      prev_level = level;
      int shift = QBITS - 1 - level;
      vec3 lo = vec3((qi >> shift) << shift) / QSCALE;
      float size = exp2(-float(level + 1));
      vec3 bound = lo + size * positive;
      vec3 te = (bound - o) * invd;
      float t_exit = min(min(te.x, te.y), te.z);
      float t_end = min(max(t_exit, t + eps_t), t1);
      if (val < 0) {
        int leaf = -val - 1;
        vec4 tx = texelFetch(u_data, texel(leaf, 0, u_data_layout), 0);
        float sigma = max(tx.x, 0.0);
        float att = exp(-sigma * (t_end - t));
        float w = T * (1.0 - att);
        vec3 acc = tx.yzw * bv[0];
        for (int g = 0; g < u_groups; ++g) {
          int b = 4 * g + 1;
          if (b > u_sh_max) break;
          if (b + 3 < u_sh_min) continue;
          vec4 p0 = texelFetch(u_data, texel(leaf, 3 * g + 1, u_data_layout), 0);
          vec4 p1 = texelFetch(u_data, texel(leaf, 3 * g + 2, u_data_layout), 0);
          vec4 p2 = texelFetch(u_data, texel(leaf, 3 * g + 3, u_data_layout), 0);
          acc += p0.xyz * bv[b] + vec3(p0.w, p1.xy) * bv[b + 1]
               + vec3(p1.zw, p2.x) * bv[b + 2] + p2.yzw * bv[b + 3];
        }
        rgb += w / (1.0 + exp(-acc));
        wsum += w;
        wtsum += w * 0.5 * (t + t_end);
        T *= att;
        if (T < u_stop_thresh) break;
      }
      if (t_end >= t1) break;
      t = t_end;
    }
  }
  float alpha = 1.0 - T;
  if (u_mode == 0) {
    frag_color = vec4(rgb + T * background, 1.0);
  } else if (u_mode == 1) {
    float depth = wtsum / max(wsum, 1e-10);
    float g = 1.0 - clamp((depth - u_depth_range.x) / max(u_depth_range.y - u_depth_range.x, 1e-6), 0.0, 1.0);
    frag_color = vec4(vec3(g) * alpha + T * u_background, 1.0);
  } else {
    // opacity drawn in the colour that contrasts with the background (white on dark, black
    // on light), so it shows on the default white background too
    float lum = dot(u_background, vec3(0.299, 0.587, 0.114));
    vec3 ink = lum > 0.5 ? vec3(0.0) : vec3(1.0);
    frag_color = vec4(mix(u_background, ink, alpha), 1.0);
  }
}`;

export class GLError extends Error {
  constructor(message) {
    super(message);
    this.name = "GLError";
  }
}

function compile(gl, type, src) {
  const sh = gl.createShader(type);
  gl.shaderSource(sh, src);
  gl.compileShader(sh);
  if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) {
    throw new GLError(`shader compilation failed: ${gl.getShaderInfoLog(sh)}`);
  }
  return sh;
}

export class Renderer {
  // overrides: {maxTextureSize, maxLayers} to simulate a smaller device (tests, ?max_texture=).
  constructor(canvas, overrides = {}) {
    this.canvas = canvas;
    const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, depth: false, preserveDrawingBuffer: true });
    if (!gl) throw new GLError("WebGL2 is not available in this browser (or it is disabled); the viewer needs it");
    this.gl = gl;
    const devMax = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    const devLayers = gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS);
    this.limits = {
      maxTextureSize: Math.min(devMax, overrides.maxTextureSize || devMax),
      maxLayers: Math.min(devLayers, overrides.maxLayers || devLayers),
      deviceMaxTextureSize: devMax,
      deviceMaxLayers: devLayers,
    };
    const prog = gl.createProgram();
    gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, VERTEX));
    gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, FRAGMENT));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) {
      throw new GLError(`shader link failed: ${gl.getProgramInfoLog(prog)}`);
    }
    this.prog = prog;
    this.vao = gl.createVertexArray();
    this.loc = {};
    const n = gl.getProgramParameter(prog, gl.ACTIVE_UNIFORMS);
    for (let i = 0; i < n; i++) {
      const info = gl.getActiveUniform(prog, i);
      const name = info.name.replace(/\[0\]$/, "");
      this.loc[name] = gl.getUniformLocation(prog, info.name);
    }
    this.tree = null;
  }

  _texture(unit, internal, format, type, plan, data) {
    const gl = this.gl;
    const tex = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, tex);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage3D(gl.TEXTURE_2D_ARRAY, 0, internal, plan.width, plan.height, plan.layers, 0, format, type, data);
    const err = gl.getError();
    if (err === gl.OUT_OF_MEMORY) throw new GLError("the GPU ran out of memory uploading the tree");
    if (err !== gl.NO_ERROR) throw new GLError(`texture upload failed (GL error 0x${err.toString(16)})`);
    return tex;
  }

  // packed: the result of packTree().
  upload(packed) {
    const gl = this.gl;
    this.release();
    this.childTex = this._texture(0, gl.R32I, gl.RED_INTEGER, gl.INT, packed.child, packed.child.data);
    this.dataTex = this._texture(1, gl.RGBA16F, gl.RGBA, gl.HALF_FLOAT, packed.data, packed.data.data);
    this.tree = packed;
  }

  release() {
    const gl = this.gl;
    if (this.childTex) gl.deleteTexture(this.childTex);
    if (this.dataTex) gl.deleteTexture(this.dataTex);
    this.childTex = this.dataTex = null;
    this.tree = null;
  }

  // camera: {c2w: 16 numbers row-major (OpenGL camera: x right, y up, looks down -z),
  //          fx, fy, cx, cy, width, height}
  // opts: {stop_thresh, step_eps, background[3], sh_min, sh_max, box_min[3], box_max[3],
  //        mode: "rgb"|"depth"|"alpha", depth_range[2]}
  // meshTex: [colour, distance] textures of MeshPass.draw for this camera, or null.
  draw(camera, opts, meshTex = null) {
    if (!this.tree) throw new GLError("no tree loaded");
    if (this.canvas.width !== camera.width || this.canvas.height !== camera.height) {
      this.canvas.width = camera.width;
      this.canvas.height = camera.height;
    }
    this._setup(camera, opts, meshTex);
    this.gl.drawArrays(this.gl.TRIANGLES, 0, 3);
  }

  // Progressive full frames (a frame too slow to draw at once, e.g. on software GL, would stall
  // the page for its whole length): beginBands(camera) allocates an offscreen RGBA8 target of
  // the camera's size; drawBand(camera, opts, meshTex, y0, y1) draws its rows [y0, y1) (from
  // the top) there, one band per animation frame; presentBands() copies the finished frame to
  // the canvas. The pixels equal draw()'s (same fragment coordinates).
  beginBands(camera) {
    const gl = this.gl, w = camera.width, h = camera.height;
    if (!this.band || this.band.w !== w || this.band.h !== h) {
      this.endBands();
      const tex = gl.createTexture();
      gl.activeTexture(gl.TEXTURE7);        // a unit no sampler reads (no feedback loop)
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA8, w, h);
      gl.bindTexture(gl.TEXTURE_2D, null);
      const fb = gl.createFramebuffer();
      gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      this.band = { tex, fb, w, h };
    }
  }

  drawBand(camera, opts, meshTex, y0, y1) {
    const gl = this.gl, h = camera.height;
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.band.fb);
    this._setup(camera, opts, meshTex);
    gl.enable(gl.SCISSOR_TEST);
    gl.scissor(0, h - y1, camera.width, y1 - y0);      // GL rows count from the bottom
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.disable(gl.SCISSOR_TEST);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  }

  presentBands() {
    const gl = this.gl, { fb, w, h } = this.band;
    if (this.canvas.width !== w || this.canvas.height !== h) {
      this.canvas.width = w;
      this.canvas.height = h;
    }
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, fb);
    gl.bindFramebuffer(gl.DRAW_FRAMEBUFFER, null);
    gl.blitFramebuffer(0, 0, w, h, 0, 0, w, h, gl.COLOR_BUFFER_BIT, gl.NEAREST);
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, null);
  }

  endBands() {
    if (!this.band) return;
    this.gl.deleteFramebuffer(this.band.fb);
    this.gl.deleteTexture(this.band.tex);
    this.band = null;
  }

  // Program, textures and uniforms of a frame for `camera` (viewport: its full size).
  _setup(camera, opts, meshTex) {
    const gl = this.gl, L = this.loc, t = this.tree;
    gl.viewport(0, 0, camera.width, camera.height);
    gl.useProgram(this.prog);
    gl.bindVertexArray(this.vao);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.childTex);
    gl.activeTexture(gl.TEXTURE1);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.dataTex);
    gl.uniform1i(L.u_child, 0);
    gl.uniform1i(L.u_data, 1);
    if (meshTex) {
      gl.activeTexture(gl.TEXTURE2);
      gl.bindTexture(gl.TEXTURE_2D, meshTex[0]);
      gl.activeTexture(gl.TEXTURE3);
      gl.bindTexture(gl.TEXTURE_2D, meshTex[1]);
    }
    if (L.u_mesh_color) gl.uniform1i(L.u_mesh_color, 2);
    if (L.u_mesh_dist) gl.uniform1i(L.u_mesh_dist, 3);
    if (L.u_mesh) gl.uniform1i(L.u_mesh, meshTex ? 1 : 0);
    gl.uniform3i(L.u_child_layout, t.child.log2PerRow, t.child.log2h, t.child.perItem);
    gl.uniform3i(L.u_data_layout, t.data.log2PerRow, t.data.log2h, t.data.perItem);
    const B = t.format.basisDim;
    gl.uniform1i(L.u_basis_dim, B);
    gl.uniform1i(L.u_groups, Math.ceil((B - 1) / 4));
    gl.uniform1i(L.u_kind, t.format.kind);
    gl.uniform1i(L.u_sh_degree, Math.max(t.format.shDegree, 0));
    const shMax = opts.sh_max < 0 ? B - 1 : Math.min(opts.sh_max, B - 1);
    gl.uniform1i(L.u_sh_min, opts.sh_min);
    gl.uniform1i(L.u_sh_max, shMax);
    if (t.sg && L.u_sg) {
      const sg = new Float32Array(32 * 4);
      sg.set(t.sg);
      gl.uniform4fv(L.u_sg, sg);
    }
    const m = camera.c2w;   // row-major -> column-major
    gl.uniformMatrix4fv(L.u_c2w, false, [m[0], m[4], m[8], m[12], m[1], m[5], m[9], m[13],
      m[2], m[6], m[10], m[14], m[3], m[7], m[11], m[15]]);
    gl.uniform4f(L.u_intrinsics, camera.fx, camera.fy, camera.cx, camera.cy);
    gl.uniform1f(L.u_height, camera.height);
    gl.uniform3fv(L.u_offset, t.offset);
    gl.uniform3fv(L.u_invradius, t.invradius);
    gl.uniform3fv(L.u_box_min, opts.box_min || [0, 0, 0]);
    gl.uniform3fv(L.u_box_max, opts.box_max || [1, 1, 1]);
    gl.uniform1f(L.u_stop_thresh, opts.stop_thresh);
    gl.uniform1f(L.u_step_eps, opts.step_eps);
    gl.uniform3fv(L.u_background, opts.background);
    gl.uniform1i(L.u_mode, { rgb: 0, depth: 1, alpha: 2 }[opts.mode || "rgb"]);
    gl.uniform2fv(L.u_depth_range, opts.depth_range || [0, 1]);
    // a ray crosses at most ~3 * 2^(depth+1) finest cells; the cap keeps bad input from hanging
    gl.uniform1i(L.u_max_steps, Math.min(3 * 2 ** (t.maxDepth + 1) + 64, 1 << 20));
    const ndc = opts.ndc;          // {fx, fy, width, height, near} of the NDC reference camera
    gl.uniform1i(L.u_ndc, ndc ? 1 : 0);
    gl.uniform4f(L.u_ndc_cam, ndc ? 2 * ndc.fx / ndc.width : 0, ndc ? 2 * ndc.fy / ndc.height : 0,
      ndc ? ndc.near : 1, 0);
  }

  // Wait for the GPU (reads one pixel); returns nothing.
  finish() {
    const px = new Uint8Array(4);
    this.gl.readPixels(0, 0, 1, 1, this.gl.RGBA, this.gl.UNSIGNED_BYTE, px);
  }

  // RGBA8 pixels of the last frame, rows top to bottom.
  readPixels() {
    const gl = this.gl, w = this.canvas.width, h = this.canvas.height;
    const buf = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, buf);
    const out = new Uint8Array(w * h * 4);
    for (let y = 0; y < h; y++) out.set(buf.subarray((h - 1 - y) * w * 4, (h - y) * w * 4), y * w * 4);
    return out;
  }
}
