// An interactive viewer of a frame's Gaussian PLY (the standard 3DGS layout, docs/design.md 3.3):
// every Gaussian drawn as a screen-space ellipse from its projected 3D covariance, blended back
// to front (WebGL2, one instanced quad per Gaussian, attributes read from a float texture).
// Colour modes: appearance (SH degree 0), geometry-branch normals, visibility (AO).

import { compile } from './deferred.js';

const SH_C0 = 0.28209479177387814;
const ROW = 512; // Gaussians per texture row (4 texels each)

const TYPES = { char: ['getInt8', 1], int8: ['getInt8', 1], uchar: ['getUint8', 1],
  uint8: ['getUint8', 1], short: ['getInt16', 2], int16: ['getInt16', 2],
  ushort: ['getUint16', 2], uint16: ['getUint16', 2], int: ['getInt32', 4],
  int32: ['getInt32', 4], uint: ['getUint32', 4], uint32: ['getUint32', 4],
  float: ['getFloat32', 4], float32: ['getFloat32', 4], double: ['getFloat64', 8],
  float64: ['getFloat64', 8] };

/** Columns of a binary little-endian PLY's vertex element: {count, columns: {name: Float32Array}}. */
export function parsePly(buffer) {
  const bytes = new Uint8Array(buffer);
  const head = new TextDecoder('ascii').decode(bytes.subarray(0, Math.min(bytes.length, 65536)));
  const end = head.indexOf('end_header\n');
  if (!head.startsWith('ply\n') || end < 0) throw new Error('not a PLY file (no end_header)');
  const lines = head.slice(0, end).split('\n');
  if (!lines.includes('format binary_little_endian 1.0')) {
    throw new Error('only binary little-endian PLY files can be viewed');
  }
  let count = -1, inVertex = false, stride = 0;
  const props = [];
  for (const line of lines) {
    const p = line.trim().split(/\s+/);
    if (p[0] === 'element') {
      inVertex = p[1] === 'vertex';
      if (inVertex) count = Number(p[2]);
      else if (count < 0) throw new Error(`element ${p[1]} comes before the vertices`);
    } else if (p[0] === 'property' && inVertex) {
      if (p[1] === 'list' || !(p[1] in TYPES)) throw new Error(`unsupported property ${line}`);
      props.push({ name: p[2], reader: TYPES[p[1]][0], offset: stride });
      stride += TYPES[p[1]][1];
    }
  }
  if (count < 0) throw new Error('the PLY has no vertex element');
  const body = end + 'end_header\n'.length;
  if (bytes.length < body + count * stride) throw new Error('the PLY file is truncated');
  const view = new DataView(buffer, body);
  const columns = {};
  for (const prop of props) {
    const col = new Float32Array(count);
    for (let i = 0, o = prop.offset; i < count; i++, o += stride) col[i] = view[prop.reader](o, true);
    columns[prop.name] = col;
  }
  return { count, columns };
}

const sigmoid = (x) => 1 / (1 + Math.exp(-x));

/** Per-Gaussian texels: centre+alpha, covariance (6), colour, for the colour `mode`. */
function packGaussians(ply, mode) {
  const c = ply.columns, n = ply.count;
  for (const name of ['x', 'y', 'z', 'scale_0', 'scale_1', 'scale_2', 'rot_0', 'rot_1', 'rot_2',
                      'rot_3', 'opacity']) {
    if (!c[name]) throw new Error(`the PLY has no '${name}' property; not a 3DGS file`);
  }
  const rows = Math.ceil(n / ROW);
  const data = new Float32Array(rows * ROW * 16);
  for (let i = 0; i < n; i++) {
    const o = i * 16;
    let w = c.rot_0[i], x = c.rot_1[i], y = c.rot_2[i], z = c.rot_3[i];
    const qn = Math.hypot(w, x, y, z) || 1;
    w /= qn; x /= qn; y /= qn; z /= qn;
    const R = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
               2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
               2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)];
    const s = [Math.exp(c.scale_0[i]), Math.exp(c.scale_1[i]), Math.exp(c.scale_2[i])];
    const M = R.map((v, k) => v * s[k % 3]); // R S
    const cov = (a, b) => M[3 * a] * M[3 * b] + M[3 * a + 1] * M[3 * b + 1] + M[3 * a + 2] * M[3 * b + 2];
    let r, g, b, alpha = sigmoid(c.opacity[i]);
    if (mode === 'normal' && c.normal_x) {
      const nx = c.normal_x[i], ny = c.normal_y[i], nz = c.normal_z[i];
      const nn = Math.hypot(nx, ny, nz) || 1;
      r = 0.5 + 0.5 * nx / nn; g = 0.5 + 0.5 * ny / nn; b = 0.5 + 0.5 * nz / nn;
      if (c.opacity_geo) alpha = sigmoid(c.opacity_geo[i]);
    } else if (mode === 'visibility' && c.visibility) {
      r = g = b = sigmoid(c.visibility[i]);  // stored as a logit, like the opacities
      if (c.opacity_geo) alpha = sigmoid(c.opacity_geo[i]);
    } else {
      r = 0.5 + SH_C0 * (c.f_dc_0 ? c.f_dc_0[i] : 0);
      g = 0.5 + SH_C0 * (c.f_dc_1 ? c.f_dc_1[i] : 0);
      b = 0.5 + SH_C0 * (c.f_dc_2 ? c.f_dc_2[i] : 0);
    }
    data.set([c.x[i], c.y[i], c.z[i], alpha, cov(0, 0), cov(0, 1), cov(0, 2), cov(1, 1),
              cov(1, 2), cov(2, 2), 0, 0, Math.min(1, Math.max(0, r)),
              Math.min(1, Math.max(0, g)), Math.min(1, Math.max(0, b)), 1], o);
  }
  return { data, rows };
}

const VERT = `#version 300 es
precision highp float;
precision highp int;
uniform highp sampler2D u_data;
uniform mat4 u_view;
uniform mat4 u_proj;
uniform vec2 u_focal;
uniform vec2 u_viewport;
in uint a_index;
out vec4 v_color;
out vec2 v_pos;
void main() {
  int i = int(a_index);
  ivec2 base = ivec2((i % ${ROW}) * 4, i / ${ROW});
  vec4 t0 = texelFetch(u_data, base, 0);
  vec4 t1 = texelFetch(u_data, base + ivec2(1, 0), 0);
  vec4 t2 = texelFetch(u_data, base + ivec2(2, 0), 0);
  vec4 t3 = texelFetch(u_data, base + ivec2(3, 0), 0);
  vec4 cam = u_view * vec4(t0.xyz, 1.0);
  vec4 clip = u_proj * cam;
  float z = cam.z;
  if (z > -1e-3 || abs(clip.x) > 1.3 * clip.w || abs(clip.y) > 1.3 * clip.w) {
    gl_Position = vec4(0.0, 0.0, 2.0, 1.0);
    return;
  }
  mat3 sigma = mat3(t1.x, t1.y, t1.z, t1.y, t1.w, t2.x, t1.z, t2.x, t2.y);
  mat3 J = mat3(-u_focal.x / z, 0.0, 0.0,
                0.0, -u_focal.y / z, 0.0,
                u_focal.x * cam.x / (z * z), u_focal.y * cam.y / (z * z), 0.0);
  mat3 T = J * mat3(u_view);
  mat3 c = T * sigma * transpose(T);
  float a = c[0][0] + 0.3, b = c[0][1], d = c[1][1] + 0.3;
  float mid = 0.5 * (a + d);
  float radius = length(vec2(0.5 * (a - d), b));
  float l1 = mid + radius, l2 = mid - radius;
  if (l2 <= 0.0) {
    gl_Position = vec4(0.0, 0.0, 2.0, 1.0);
    return;
  }
  vec2 dir = abs(b) > 1e-12 ? normalize(vec2(b, l1 - a)) : (a >= d ? vec2(1, 0) : vec2(0, 1));
  vec2 major = min(sqrt(2.0 * l1), 1024.0) * dir;
  vec2 minor = min(sqrt(2.0 * l2), 1024.0) * vec2(dir.y, -dir.x);
  vec2 corner = vec2(float(gl_VertexID & 1), float((gl_VertexID >> 1) & 1)) * 4.0 - 2.0;
  v_pos = corner;
  v_color = vec4(t3.rgb, t0.w);
  vec2 ndc = clip.xy / clip.w;
  vec2 offset = (corner.x * major + corner.y * minor) * 2.0 / u_viewport;
  gl_Position = vec4(ndc + offset, 0.0, 1.0);
}`;

const FRAG = `#version 300 es
precision highp float;
in vec4 v_color;
in vec2 v_pos;
out vec4 fragColor;
void main() {
  float A = -dot(v_pos, v_pos);
  if (A < -4.0) discard;
  float alpha = min(0.99, exp(A) * v_color.a);
  if (alpha < 1.0 / 255.0) discard;
  fragColor = vec4(v_color.rgb * alpha, alpha);
}`;


function lookAt(eye, target, up) {
  const f = norm(sub(target, eye)), s = norm(cross(f, up)), u = cross(s, f);
  return new Float32Array([s[0], u[0], -f[0], 0, s[1], u[1], -f[1], 0, s[2], u[2], -f[2], 0,
    -dot(s, eye), -dot(u, eye), dot(f, eye), 1]);
}
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => { const l = Math.hypot(...a) || 1; return [a[0] / l, a[1] / l, a[2] / l]; };

export const UPS = { '+z': [0, 0, 1], '-y': [0, -1, 0], '+y': [0, 1, 0] };

export class SplatViewer {
  /** A viewer drawing into `canvas`; throws when WebGL2 is unavailable. */
  constructor(canvas) {
    const gl = canvas.getContext('webgl2', { antialias: false, premultipliedAlpha: true,
                                             preserveDrawingBuffer: true });
    if (!gl) throw new Error('this browser has no WebGL2; the splat viewer needs it');
    this.gl = gl;
    this.canvas = canvas;
    const prog = gl.createProgram();
    gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, VERT));
    gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, FRAG));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
    this.prog = prog;
    this.loc = Object.fromEntries(['u_data', 'u_view', 'u_proj', 'u_focal', 'u_viewport']
      .map((n) => [n, gl.getUniformLocation(prog, n)]));
    this.texture = gl.createTexture();
    this.indexBuffer = gl.createBuffer();
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.indexBuffer);
    const a = gl.getAttribLocation(prog, 'a_index');
    gl.enableVertexAttribArray(a);
    gl.vertexAttribIPointer(a, 1, gl.UNSIGNED_INT, 0, 0);
    gl.vertexAttribDivisor(a, 1);
    this.count = 0;
    this.up = UPS['+z'];
    this.orbit = { yaw: 0.6, pitch: 0.3, distance: 3, target: [0, 0, 0] };
    this.mode = 'color';
    this.attachControls();
  }

  /** Show a parsed PLY (see parsePly); the camera frames its central 98% of Gaussians. */
  setGaussians(ply) {
    this.ply = ply;
    this.count = ply.count;
    const { x, y, z } = ply.columns;
    const pct = (col, q) => { const s = Float32Array.from(col).sort(); return s[Math.floor(q * (s.length - 1))]; };
    const lo = [pct(x, 0.01), pct(y, 0.01), pct(z, 0.01)], hi = [pct(x, 0.99), pct(y, 0.99), pct(z, 0.99)];
    this.orbit.target = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2];
    this.orbit.distance = 1.6 * Math.max(1e-3, Math.hypot(...sub(hi, lo)));
    this.upload();
  }

  setMode(mode) { this.mode = mode; if (this.ply) this.upload(); }

  setUp(name) { this.up = UPS[name] || UPS['+z']; this.draw(); }

  upload() {
    const gl = this.gl;
    const { data, rows } = packGaussians(this.ply, this.mode);
    if (rows > gl.getParameter(gl.MAX_TEXTURE_SIZE)) throw new Error(`too many Gaussians to view (${this.count})`);
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, ROW * 4, rows, 0, gl.RGBA, gl.FLOAT, data);
    this.depths = new Float32Array(this.count);
    this.order = new Uint32Array(this.count);
    this.draw();
  }

  view() {
    const { yaw, pitch, distance, target } = this.orbit;
    const up = this.up;
    // An orthonormal frame about `up`: azimuth in the plane, elevation towards up.
    const ref = Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
    const e1 = norm(cross(up, ref)), e2 = cross(up, e1);
    const dir = [0, 1, 2].map((k) => Math.cos(pitch) * (Math.cos(yaw) * e1[k] + Math.sin(yaw) * e2[k])
                                     + Math.sin(pitch) * up[k]);
    const eye = [0, 1, 2].map((k) => target[k] + distance * dir[k]);
    return lookAt(eye, target, up);
  }

  /** Indices far to near along the view direction (16-bit counting sort). */
  sort(view) {
    const n = this.count, cx = this.ply.columns.x, cy = this.ply.columns.y, cz = this.ply.columns.z;
    const d = this.depths;
    let min = Infinity, max = -Infinity;
    for (let i = 0; i < n; i++) {
      d[i] = view[2] * cx[i] + view[6] * cy[i] + view[10] * cz[i] + view[14];
      if (d[i] < min) min = d[i];
      if (d[i] > max) max = d[i];
    }
    const bins = 65536, scale = (bins - 1) / Math.max(max - min, 1e-9);
    const counts = new Uint32Array(bins), keys = new Uint16Array(n);
    for (let i = 0; i < n; i++) { keys[i] = (d[i] - min) * scale; counts[keys[i]]++; }
    for (let b = 1; b < bins; b++) counts[b] += counts[b - 1];
    // Camera looks down -z: the most negative z is farthest, so it draws first.
    for (let i = n - 1; i >= 0; i--) this.order[--counts[keys[i]]] = i;
  }

  draw() {
    if (!this.ply) return;
    const gl = this.gl, canvas = this.canvas;
    const w = canvas.clientWidth || canvas.width, h = canvas.clientHeight || canvas.height;
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    const view = this.view();
    this.sort(view);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.indexBuffer);
    gl.bufferData(gl.ARRAY_BUFFER, this.order, gl.DYNAMIC_DRAW);
    const fovy = 40 * Math.PI / 180, f = h / (2 * Math.tan(fovy / 2));
    const near = this.orbit.distance * 0.01, far = this.orbit.distance * 100;
    const t = 1 / Math.tan(fovy / 2);
    const proj = new Float32Array([t * h / w, 0, 0, 0, 0, t, 0, 0, 0, 0, (far + near) / (near - far), -1,
      0, 0, 2 * far * near / (near - far), 0]);
    gl.viewport(0, 0, w, h);
    gl.clearColor(0.08, 0.09, 0.11, 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.useProgram(this.prog);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    gl.disable(gl.DEPTH_TEST);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.uniform1i(this.loc.u_data, 0);
    gl.uniformMatrix4fv(this.loc.u_view, false, view);
    gl.uniformMatrix4fv(this.loc.u_proj, false, proj);
    gl.uniform2f(this.loc.u_focal, f, f);
    gl.uniform2f(this.loc.u_viewport, w, h);
    gl.bindVertexArray(this.vao);
    gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, this.count);
  }

  requestDraw() {
    if (this.pending) return;
    this.pending = requestAnimationFrame(() => { this.pending = 0; this.draw(); });
  }

  attachControls() {
    const c = this.canvas, o = this.orbit;
    let drag = null;
    c.addEventListener('pointerdown', (e) => { drag = [e.clientX, e.clientY]; c.setPointerCapture(e.pointerId); });
    c.addEventListener('pointerup', () => { drag = null; });
    c.addEventListener('pointermove', (e) => {
      if (!drag) return;
      o.yaw -= (e.clientX - drag[0]) * 0.01;
      o.pitch = Math.max(-1.5, Math.min(1.5, o.pitch + (e.clientY - drag[1]) * 0.01));
      drag = [e.clientX, e.clientY];
      this.requestDraw();
    });
    c.addEventListener('wheel', (e) => {
      e.preventDefault();
      o.distance *= Math.exp(e.deltaY * 0.001);
      this.requestDraw();
    }, { passive: false });
  }

  /** Fraction of pixels that differ from the background (tests check that something drew). */
  coverage() {
    const gl = this.gl, w = this.canvas.width, h = this.canvas.height;
    const px = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    let drawn = 0;
    for (let i = 0; i < px.length; i += 4) {
      if (Math.abs(px[i] - 20) + Math.abs(px[i + 1] - 23) + Math.abs(px[i + 2] - 28) > 12) drawn++;
    }
    return drawn / (w * h);
  }
}
