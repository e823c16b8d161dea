// A WebGL2 renderer of disentangled Gaussians that computes what the server's relight computes
// (core.relight: native.rasterize's projection and blending, then deferred shading), so a frame
// of the stream relit in the page matches the server's relit render of the same view.
//
// Pass 1 splats every Gaussian (sorted far to near, one instanced quad each) into four float
// targets at once, each blended "over" with its own branch's alpha (premultiplied: the blend
// factor of a target is that target's source alpha): degree-0 colour and full-SH colour with the
// appearance alpha, normal and (visibility, depth) with the geometry alpha; beta mixing, the
// Mip-Splatting screen blur and opacity compensation, the 0.99 clamp and the 1/255 cut as in
// docs/design.md 3.4. Pass 2 reads that G-buffer per pixel: appearance, normals, AO, or relit =
// albedo * (visibility * E_env(n) + lights) + the view-dependent residual (core.relight.shade).

import { ROW, SHADE_FRAG, SHADE_VERT, SPLAT_FRAG, SPLAT_VERT } from './shaders.js';

/** A compiled shader, or the compiler's log as an Error. */
export function compile(gl, type, source) {
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

