// A WebGL2 renderer of disentangled Gaussians that computes what the server's relight computes
// (core.relight: native.rasterize's projection and blending, then deferred shading), so a frame
// of the stream relit in the page matches the server's relit render of the same view.
//
// Pass 1 splats every Gaussian (sorted far to near, one instanced quad each) into four float
// targets at once, each blended "over" with its own branch's alpha (premultiplied: the blend
// factor of a target is that target's source alpha): degree-0 colour and full-SH colour with the
// appearance alpha, normal and (visibility, depth) with the geometry alpha; beta mixing, the
// Mip-Splatting screen blur and opacity compensation, the 0.99 clamp and the 1/255 cut as in
// DESIGN.md 3.4. Pass 2 reads that G-buffer per pixel: appearance, normals, AO, or relit =
// albedo * (visibility * E_env(n) + lights) + the view-dependent residual (core.relight.shade).

const ROW = 256; // Gaussians per texture row (the SH texture is 16 x ROW texels wide)

const COMMON = `#version 300 es
precision highp float;
precision highp int;
`;

const SPLAT_VERT = `${COMMON}
uniform highp sampler2D u_g;      // 4 texels a Gaussian: mean+oc, cov(4), cov(2)+og+vis, normal
uniform highp sampler2D u_sh;     // 16 texels a Gaussian: sh0 then the higher coefficients
uniform mat4 u_view;              // world to camera, OpenCV axes
uniform vec4 u_K;                 // fx fy cx cy
uniform vec2 u_size;              // width height
uniform vec3 u_center;            // camera centre
uniform float u_beta, u_eps2d;
uniform int u_aa, u_deg;
in uint a_index;
flat out vec3 v_c0, v_cf, v_n;
flat out vec4 v_conic;            // a b c (of the inverse 2D covariance), camera z
flat out vec2 v_mean, v_o;        // mean2d (pixels, y down), (o_c, o_g)
flat out float v_vis;
const float C1 = 0.4886025119029199;
const float C2[5] = float[5](1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396);
const float C3[7] = float[7](-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658, 1.445305721320277, -0.5900435899266435);
vec3 shc(ivec2 base, int k) { return texelFetch(u_sh, base + ivec2(k, 0), 0).rgb; }
void main() {
  int i = int(a_index);
  ivec2 gb = ivec2((i % ${ROW}) * 4, i / ${ROW});
  ivec2 sb = ivec2((i % ${ROW}) * 16, i / ${ROW});
  vec4 t0 = texelFetch(u_g, gb, 0), t1 = texelFetch(u_g, gb + ivec2(1, 0), 0);
  vec4 t2 = texelFetch(u_g, gb + ivec2(2, 0), 0), t3 = texelFetch(u_g, gb + ivec2(3, 0), 0);
  vec3 p = (u_view * vec4(t0.xyz, 1.0)).xyz;
  gl_Position = vec4(0.0, 0.0, 2.0, 1.0);
  if (p.z <= 0.01) return;
  float fx = u_K.x, fy = u_K.y, cx = u_K.z, cy = u_K.w, W = u_size.x, H = u_size.y;
  float tx = p.z * clamp(p.x / p.z, -(cx + 0.15 * W) / fx, (W - cx + 0.15 * W) / fx);
  float ty = p.z * clamp(p.y / p.z, -(cy + 0.15 * H) / fy, (H - cy + 0.15 * H) / fy);
  mat3 J = mat3(fx / p.z, 0.0, 0.0, 0.0, fy / p.z, 0.0, -fx * tx / (p.z * p.z), -fy * ty / (p.z * p.z), 0.0);
  mat3 S = mat3(t1.x, t1.y, t1.z, t1.y, t1.w, t2.x, t1.z, t2.x, t2.y);
  mat3 T = J * mat3(u_view);
  mat3 c = T * S * transpose(T);
  float a = c[0][0], b = c[0][1], d = c[1][1];
  float det0 = a * d - b * b;
  a += u_eps2d; d += u_eps2d;
  float det = a * d - b * b;
  if (det <= 0.0) return;
  float comp = 1.0;
  if (u_aa == 1) comp = det0 / det > 0.0 ? sqrt(det0 / det) : 0.0;
  float oc = 0.5 * comp * ((1.0 + u_beta) * t0.w + (1.0 - u_beta) * t2.z);
  float og = 0.5 * comp * ((1.0 - u_beta) * t0.w + (1.0 + u_beta) * t2.z);
  float omax = max(oc, og);
  if (omax < 1.0 / 255.0) return;
  float k = 2.0 * log(omax * 255.0) * 1.001 + 1e-3;
  vec2 ext = sqrt(k * vec2(a, d)) * 1.001 + 0.01;
  vec2 mean = vec2(fx * p.x / p.z + cx, fy * p.y / p.z + cy);
  vec2 corner = vec2(float(gl_VertexID & 1), float((gl_VertexID >> 1) & 1)) * 2.0 - 1.0;
  vec2 px = mean + corner * ext;
  gl_Position = vec4(px.x / W * 2.0 - 1.0, 1.0 - px.y / H * 2.0, 0.0, 1.0);
  v_conic = vec4(d / det, -b / det, a / det, p.z);
  v_mean = mean;
  v_o = vec2(oc, og);
  v_n = t3.xyz;
  v_vis = t2.w;
  vec3 s0 = shc(sb, 0);
  v_c0 = max(0.28209479177387814 * s0 + 0.5, 0.0);
  vec3 dir = normalize(t0.xyz - u_center);
  float x = dir.x, y = dir.y, z = dir.z;
  vec3 col = 0.28209479177387814 * s0;
  if (u_deg > 0) col += -C1 * y * shc(sb, 1) + C1 * z * shc(sb, 2) - C1 * x * shc(sb, 3);
  if (u_deg > 1) {
    float xx = x * x, yy = y * y, zz = z * z;
    col += C2[0] * x * y * shc(sb, 4) + C2[1] * y * z * shc(sb, 5) + C2[2] * (2.0 * zz - xx - yy) * shc(sb, 6)
         + C2[3] * x * z * shc(sb, 7) + C2[4] * (xx - yy) * shc(sb, 8);
    if (u_deg > 2) {
      col += C3[0] * y * (3.0 * xx - yy) * shc(sb, 9) + C3[1] * x * y * z * shc(sb, 10)
           + C3[2] * y * (4.0 * zz - xx - yy) * shc(sb, 11) + C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * shc(sb, 12)
           + C3[4] * x * (4.0 * zz - xx - yy) * shc(sb, 13) + C3[5] * z * (xx - yy) * shc(sb, 14)
           + C3[6] * x * (xx - 3.0 * yy) * shc(sb, 15);
    }
  }
  v_cf = max(col + 0.5, 0.0);
}`;

const SPLAT_FRAG = `${COMMON}
uniform vec2 u_size;
flat in vec3 v_c0, v_cf, v_n;
flat in vec4 v_conic;
flat in vec2 v_mean, v_o;
flat in float v_vis;
layout(location = 0) out vec4 o_c0;
layout(location = 1) out vec4 o_cf;
layout(location = 2) out vec4 o_n;
layout(location = 3) out vec4 o_vd;
void main() {
  vec2 q = vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);  // pixel centre, OpenCV (y down)
  vec2 d = q - v_mean;
  float e = -0.5 * (v_conic.x * d.x * d.x + v_conic.z * d.y * d.y) - v_conic.y * d.x * d.y;
  float ac = min(0.99, v_o.x * exp(e)), ag = min(0.99, v_o.y * exp(e));
  if (ac < 1.0 / 255.0) ac = 0.0;
  if (ag < 1.0 / 255.0) ag = 0.0;
  if (ac == 0.0 && ag == 0.0) discard;
  o_c0 = vec4(v_c0 * ac, ac);
  o_cf = vec4(v_cf * ac, ac);
  o_n = vec4(v_n * ag, ag);
  o_vd = vec4(v_vis * ag, v_conic.w * ag, 0.0, ag);
}`;

const SHADE_VERT = `${COMMON}
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2)) * 2.0 - 1.0;
  gl_Position = vec4(p, 0.0, 1.0);
}`;

const SHADE_FRAG = `${COMMON}
uniform sampler2D u_c0, u_cf, u_n, u_vd;
uniform int u_mode;                 // 0 appearance, 1 relit, 2 normals, 3 AO
uniform int u_linear;               // the capture stores linear colour (EXR)
uniform vec3 u_bg;                  // background as stored
uniform vec3 u_env[9];              // environment SH9 radiance in the map's own frame
uniform mat3 u_frame;               // world -> map frame (rows e1, e2, up), rotation applied
uniform float u_capture;            // uniform capture irradiance
uniform int u_lights;
uniform vec4 u_light[8];            // xyz vector, w 0 directional (towards) / 1 point (position)
uniform vec3 u_lightc[8];           // colour x intensity
uniform mat3 u_camR;                // camera to world rotation (R^T)
uniform vec3 u_camC;                // camera centre
uniform vec4 u_Kinv;                // 1/fx 1/fy cx cy
uniform vec2 u_size;
out vec4 color;
const float A[9] = float[9](3.141592653589793, 2.0943951023931953, 2.0943951023931953, 2.0943951023931953,
  0.7853981633974483, 0.7853981633974483, 0.7853981633974483, 0.7853981633974483, 0.7853981633974483);
vec3 toLinear(vec3 x) {
  x = clamp(x, 0.0, 1.0);
  return mix(pow((x + 0.055) / 1.055, vec3(2.4)), x / 12.92, vec3(lessThanEqual(x, vec3(0.04045))));
}
vec3 toSrgb(vec3 x) {
  x = clamp(x, 0.0, 1.0);
  return mix(1.055 * pow(max(x, vec3(1e-12)), vec3(1.0 / 2.4)) - 0.055, 12.92 * x, vec3(lessThanEqual(x, vec3(0.0031308))));
}
vec3 irradiance(vec3 n) {
  vec3 d = u_frame * n;
  float x = d.x, y = d.y, z = d.z;
  float Y[9] = float[9](0.28209479177387814, 0.4886025119029199 * y, 0.4886025119029199 * z,
    0.4886025119029199 * x, 1.0925484305920792 * x * y, 1.0925484305920792 * y * z,
    0.31539156525252005 * (3.0 * z * z - 1.0), 1.0925484305920792 * x * z, 0.5462742152960396 * (x * x - y * y));
  vec3 e = vec3(0.0);
  for (int k = 0; k < 9; k++) e += A[k] * Y[k] * u_env[k];
  return max(e, 0.0);
}
vec3 decode(vec3 x) { return u_linear == 1 ? max(x, 0.0) : toLinear(x); }
void main() {
  ivec2 px = ivec2(gl_FragCoord.xy);
  vec4 c0 = texelFetch(u_c0, px, 0), cf = texelFetch(u_cf, px, 0);
  vec4 gn = texelFetch(u_n, px, 0), vd = texelFetch(u_vd, px, 0);
  float ac = c0.a, ag = gn.a;
  vec3 bg = u_bg;
  if (u_mode == 0) { color = vec4(cf.rgb + (1.0 - ac) * bg, 1.0); return; }
  bool cov = ag > 1e-3;
  vec3 n = cov ? normalize(gn.rgb) : vec3(0.0);
  float vis = cov ? clamp(vd.r / ag, 0.0, 1.0) : 0.0;
  if (u_mode == 2) { color = vec4(cov ? n * 0.5 + 0.5 : vec3(0.0), 1.0); return; }
  if (u_mode == 3) { color = vec4(vec3(vis), 1.0); return; }
  vec3 base = ac > 1e-3 ? decode(c0.rgb / ac) : vec3(0.0);
  vec3 full = ac > 1e-3 ? decode(cf.rgb / ac) : vec3(0.0);
  float depth = ag > 1e-6 ? vd.g / ag : 0.0;
  vec2 uv = vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);
  vec3 ray = vec3((uv.x - u_Kinv.z) * u_Kinv.x, (uv.y - u_Kinv.w) * u_Kinv.y, 1.0);
  vec3 P = u_camR * (ray * depth) + u_camC;
  vec3 lit = vec3(0.0);
  bool covered = abs(n.x) + abs(n.y) + abs(n.z) > 0.0 && ac > 0.0;
  if (covered) {
    vec3 albedo = base / max(vis, 0.05) / u_capture;
    vec3 light = vis * irradiance(n);
    for (int i = 0; i < 8; i++) {
      if (i >= u_lights) break;
      vec4 L = u_light[i];
      if (L.w < 0.5) light += u_lightc[i] * max(0.0, dot(n, normalize(L.xyz)));
      else {
        vec3 to = L.xyz - P;
        float d2 = max(dot(to, to), 1e-8);
        light += u_lightc[i] * max(0.0, dot(n, to) / sqrt(d2)) / d2;
      }
    }
    lit = max(albedo * light + (full - base), 0.0);
  }
  vec3 bgs = u_linear == 1 ? toSrgb(bg) : bg;
  color = vec4(toSrgb(lit) * ac + bgs * (1.0 - ac), 1.0);
}`;

function compile(gl, type, source) {
  const s = gl.createShader(type);
  gl.shaderSource(s, source);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
  return s;
}

function program(gl, vs, fs) {
  const p = gl.createProgram();
  gl.attachShader(p, compile(gl, gl.VERTEX_SHADER, vs));
  gl.attachShader(p, compile(gl, gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(p));
  const loc = {};
  const n = gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < n; i++) {
    const name = gl.getActiveUniform(p, i).name;  // arrays are named "u_x[0]"
    loc[name.replace(/\[0\]$/, '')] = gl.getUniformLocation(p, name);
  }
  return { p, loc };
}

/** (world-to-camera 4x4 column-major for GL, camera centre) of an OpenCV world_to_camera. */
export function viewOf(w2c) {
  const m = new Float32Array(16);
  for (let r = 0; r < 4; r++) for (let c = 0; c < 4; c++) m[c * 4 + r] = w2c[r][c];
  const R = [0, 1, 2].map((r) => [0, 1, 2].map((c) => w2c[r][c])), t = [0, 1, 2].map((r) => w2c[r][3]);
  const center = [0, 1, 2].map((c) => -(R[0][c] * t[0] + R[1][c] * t[1] + R[2][c] * t[2]));
  return { view: m, R, center };
}

/** The right-handed frame (rows e1, e2, up) of core.relight.envmap.up_frame. */
export function upFrame(up) {
  const l = Math.hypot(...up);
  const u = up.map((v) => v / l);
  const score = u.map((v, i) => Math.abs(v) + i * 1e-9);
  const axis = [0, 0, 0];
  axis[score.indexOf(Math.min(...score))] = 1;
  const dot = axis[0] * u[0] + axis[1] * u[1] + axis[2] * u[2];
  let e1 = axis.map((v, i) => v - dot * u[i]);
  const n1 = Math.hypot(...e1);
  e1 = e1.map((v) => v / n1);
  const e2 = [u[1] * e1[2] - u[2] * e1[1], u[2] * e1[0] - u[0] * e1[2], u[0] * e1[1] - u[1] * e1[0]];
  return [e1, e2, u];
}

export class DeferredSplats {
  /** A renderer into `canvas`; throws when WebGL2 or float render targets are missing. */
  constructor(canvas) {
    const gl = canvas.getContext('webgl2', { antialias: false, preserveDrawingBuffer: true, premultipliedAlpha: false });
    if (!gl) throw new Error('this browser has no WebGL2; the player needs it');
    if (!gl.getExtension('EXT_color_buffer_float')) throw new Error('this browser cannot render to float textures (EXT_color_buffer_float); the player needs it');
    this.float32 = !!gl.getExtension('EXT_float_blend');
    this.gl = gl;
    this.canvas = canvas;
    this.splat = program(gl, SPLAT_VERT, SPLAT_FRAG);
    this.shade = program(gl, SHADE_VERT, SHADE_FRAG);
    this.gtex = gl.createTexture();
    this.shtex = gl.createTexture();
    this.indexBuffer = gl.createBuffer();
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.indexBuffer);
    const a = gl.getAttribLocation(this.splat.p, 'a_index');
    gl.enableVertexAttribArray(a);
    gl.vertexAttribIPointer(a, 1, gl.UNSIGNED_INT, 0, 0);
    gl.vertexAttribDivisor(a, 1);
    this.emptyVao = gl.createVertexArray();
    this.count = 0;
    this.targets = null;
  }

  /** Upload a decoded frame (core.export stream frame, see stream.js). */
  setFrame(f) {
    const gl = this.gl, n = f.count, rows = Math.max(1, Math.ceil(n / ROW));
    if (rows > gl.getParameter(gl.MAX_TEXTURE_SIZE)) throw new Error(`too many Gaussians to draw (${n})`);
    const g = new Float32Array(rows * ROW * 16), sh = new Float32Array(rows * ROW * 64);
    const dim = f.shDim;
    for (let i = 0; i < n; i++) {
      const w = f.quats[4 * i], x = f.quats[4 * i + 1], y = f.quats[4 * i + 2], z = f.quats[4 * i + 3];
      const s0 = Math.exp(f.scales[3 * i]), s1 = Math.exp(f.scales[3 * i + 1]), s2 = Math.exp(f.scales[3 * i + 2]);
      // M = R S, covariance M M^T (rows of M: a, b, c).
      const a0 = (1 - 2 * (y * y + z * z)) * s0, a1 = 2 * (x * y - w * z) * s1, a2 = 2 * (x * z + w * y) * s2;
      const b0 = 2 * (x * y + w * z) * s0, b1 = (1 - 2 * (x * x + z * z)) * s1, b2 = 2 * (y * z - w * x) * s2;
      const c0 = 2 * (x * z - w * y) * s0, c1 = 2 * (y * z + w * x) * s1, c2 = (1 - 2 * (x * x + y * y)) * s2;
      const o = 16 * i;
      g[o] = f.means[3 * i]; g[o + 1] = f.means[3 * i + 1]; g[o + 2] = f.means[3 * i + 2]; g[o + 3] = f.opacityC[i];
      g[o + 4] = a0 * a0 + a1 * a1 + a2 * a2; g[o + 5] = a0 * b0 + a1 * b1 + a2 * b2;
      g[o + 6] = a0 * c0 + a1 * c1 + a2 * c2; g[o + 7] = b0 * b0 + b1 * b1 + b2 * b2;
      g[o + 8] = b0 * c0 + b1 * c1 + b2 * c2; g[o + 9] = c0 * c0 + c1 * c1 + c2 * c2;
      g[o + 10] = f.opacityG[i]; g[o + 11] = f.visibility[i];
      g[o + 12] = f.normals[3 * i]; g[o + 13] = f.normals[3 * i + 1]; g[o + 14] = f.normals[3 * i + 2];
      const h = 64 * i;
      sh[h] = f.sh0[3 * i]; sh[h + 1] = f.sh0[3 * i + 1]; sh[h + 2] = f.sh0[3 * i + 2];
      for (let k = 0; k < dim; k++) {
        const src = 3 * (dim * i + k), dst = h + 4 * (k + 1);
        sh[dst] = f.shN[src]; sh[dst + 1] = f.shN[src + 1]; sh[dst + 2] = f.shN[src + 2];
      }
    }
    const upload = (tex, data, width) => {
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, width, rows, 0, gl.RGBA, gl.FLOAT, data);
    };
    upload(this.gtex, g, ROW * 4);
    upload(this.shtex, sh, ROW * 16);
    this.frame = f;
    this.count = n;
    this.depths = new Float32Array(n);
    this.order = new Uint32Array(n);
  }

  ensureTargets(w, h) {
    const gl = this.gl;
    if (this.targets && this.targets.w === w && this.targets.h === h) return;
    const fmt = this.float32 ? gl.RGBA32F : gl.RGBA16F;
    const fb = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
    const tex = [0, 1, 2, 3].map((k) => {
      const t = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, t);
      gl.texStorage2D(gl.TEXTURE_2D, 1, fmt, w, h);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0 + k, gl.TEXTURE_2D, t, 0);
      return t;
    });
    gl.drawBuffers([0, 1, 2, 3].map((k) => gl.COLOR_ATTACHMENT0 + k));
    if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) throw new Error('the G-buffer cannot be created here');
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    this.targets = { fb, tex, w, h };
  }

  /** Indices far to near by camera z (a 16-bit counting sort; ties keep index order). */
  sort(view) {
    const n = this.count, m = this.frame.means, d = this.depths;
    let min = Infinity, max = -Infinity;
    for (let i = 0; i < n; i++) {
      d[i] = view[2] * m[3 * i] + view[6] * m[3 * i + 1] + view[10] * m[3 * i + 2] + view[14];
      if (d[i] < min) min = d[i];
      if (d[i] > max) max = d[i];
    }
    const bins = 65536, scale = (bins - 1) / Math.max(max - min, 1e-9);
    const counts = new Uint32Array(bins), keys = new Uint16Array(n);
    for (let i = 0; i < n; i++) { keys[i] = (max - d[i]) * scale; counts[keys[i]]++; }
    for (let b = 1; b < bins; b++) counts[b] += counts[b - 1];
    for (let i = n - 1; i >= 0; i--) this.order[--counts[keys[i]]] = i;
  }

  /**
   * Draw the frame from `camera` ({world_to_camera 4x4 rows, K 3x3 rows, width, height}) with
   * `look` ({mode: appearance|relit|normals|ao, render: the stream's render settings,
   * env: 9x3, frame: 3x3 rows, capture: irradiance, lights: [{kind, vector, color, intensity}]}).
   */
  draw(camera, look) {
    if (!this.frame) return;
    const gl = this.gl, W = camera.width, H = camera.height, r = look.render;
    if (this.canvas.width !== W || this.canvas.height !== H) { this.canvas.width = W; this.canvas.height = H; }
    this.ensureTargets(W, H);
    const { view, R, center } = viewOf(camera.world_to_camera);
    this.sort(view);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.indexBuffer);
    gl.bufferData(gl.ARRAY_BUFFER, this.order, gl.DYNAMIC_DRAW);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.targets.fb);
    gl.viewport(0, 0, W, H);
    for (let k = 0; k < 4; k++) gl.clearBufferfv(gl.COLOR, k, [0, 0, 0, 0]);
    const s = this.splat;
    gl.useProgram(s.p);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    gl.disable(gl.DEPTH_TEST);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.gtex);
    gl.uniform1i(s.loc.u_g, 0);
    gl.activeTexture(gl.TEXTURE1);
    gl.bindTexture(gl.TEXTURE_2D, this.shtex);
    gl.uniform1i(s.loc.u_sh, 1);
    gl.uniformMatrix4fv(s.loc.u_view, false, view);
    const K = camera.K;
    gl.uniform4f(s.loc.u_K, K[0][0], K[1][1], K[0][2], K[1][2]);
    gl.uniform2f(s.loc.u_size, W, H);
    gl.uniform3fv(s.loc.u_center, center);
    gl.uniform1f(s.loc.u_beta, r.beta);
    gl.uniform1f(s.loc.u_eps2d, r.eps2d);
    gl.uniform1i(s.loc.u_aa, r.antialiased ? 1 : 0);
    gl.uniform1i(s.loc.u_deg, Math.min(r.sh_degree, Math.round(Math.sqrt(this.frame.shDim + 1)) - 1));
    gl.bindVertexArray(this.vao);
    gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, this.count);
    gl.disable(gl.BLEND);
    this.shadePass(camera, look, R, center);
  }

  shadePass(camera, look, R, center) {
    const gl = this.gl, sh = this.shade, L = sh.loc, r = look.render;
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.useProgram(sh.p);
    ['u_c0', 'u_cf', 'u_n', 'u_vd'].forEach((name, k) => {
      gl.activeTexture(gl.TEXTURE2 + k);
      gl.bindTexture(gl.TEXTURE_2D, this.targets.tex[k]);
      gl.uniform1i(L[name], 2 + k);
    });
    gl.uniform1i(L.u_mode, { appearance: 0, relit: 1, normals: 2, ao: 3 }[look.mode] ?? 0);
    gl.uniform1i(L.u_linear, r.linear ? 1 : 0);
    gl.uniform3fv(L.u_bg, r.background);
    gl.uniform3fv(L.u_env, look.env.flat());
    gl.uniformMatrix3fv(L.u_frame, true, look.frame.flat());
    gl.uniform1f(L.u_capture, look.capture);
    const lights = look.lights.slice(0, 8);
    gl.uniform1i(L.u_lights, lights.length);
    if (lights.length) {
      gl.uniform4fv(L.u_light, lights.flatMap((l) => [...l.vector, l.kind === 'point' ? 1 : 0]));
      gl.uniform3fv(L.u_lightc, lights.flatMap((l) => l.color.map((c) => c * l.intensity)));
    }
    gl.uniformMatrix3fv(L.u_camR, true, [0, 1, 2].flatMap((i) => [0, 1, 2].map((j) => R[j][i])));
    gl.uniform3fv(L.u_camC, center);
    const K = camera.K;
    gl.uniform4f(L.u_Kinv, 1 / K[0][0], 1 / K[1][1], K[0][2], K[1][2]);
    gl.uniform2f(L.u_size, camera.width, camera.height);
    gl.bindVertexArray(this.emptyVao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }

  /** RGBA bytes of the canvas, top row first (as an image file stores them). */
  pixels() {
    const gl = this.gl, w = this.canvas.width, h = this.canvas.height;
    const px = new Uint8Array(w * h * 4), out = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    for (let y = 0; y < h; y++) out.set(px.subarray((h - 1 - y) * w * 4, (h - y) * w * 4), y * w * 4);
    return out;
  }
}

