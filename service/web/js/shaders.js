// The player's GLSL (deferred.js): the splatting pass into the four-target G-buffer and the
// per-pixel pass that shows or relights it. Written to compute what native.rasterize and
// core.relight.shade compute (docs/design.md 3.4, section 5).

export const ROW = 256; // Gaussians per texture row (the SH texture is 16 x ROW texels wide)

const COMMON = `#version 300 es
precision highp float;
precision highp int;
`;

export const SPLAT_VERT = `${COMMON}
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

export const SPLAT_FRAG = `${COMMON}
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

export const SHADE_VERT = `${COMMON}
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2)) * 2.0 - 1.0;
  gl_Position = vec4(p, 0.0, 1.0);
}`;

export const SHADE_FRAG = `${COMMON}
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
