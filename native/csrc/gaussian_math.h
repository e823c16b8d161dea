// Per-Gaussian and per-pixel math of the disentangled rasterizer, shared by the CPU kernels and
// the CUDA kernels. Everything here is an inline host/device function on plain structs, templated
// on the scalar type (float in production, double for gradcheck), with no torch headers, so a
// .cu file can include it without a CUDA build of torch. DESIGN.md section 3.4 states the math.
#pragma once

#include <cmath>
#include <cstdint>

#if defined(__CUDACC__)
#define DGS_HD __host__ __device__ __forceinline__
#else
#define DGS_HD inline
#endif

namespace dgs {

// Constants of the blending rule. 1/255 and 0.99 follow the official 3DGS rasterizer
// (Kerbl et al. 2023, forward.cu); 1e-4 is its transmittance floor.
template <typename T> DGS_HD T alpha_max() { return T(0.99); }
template <typename T> DGS_HD T alpha_min() { return T(1.0) / T(255.0); }
template <typename T> DGS_HD T transmittance_min() { return T(1e-4); }
// Guard band of the projection Jacobian, as a fraction of the image size (DESIGN 3.4).
template <typename T> DGS_HD T fov_guard() { return T(0.15); }

// Scalar math with one overload per type, so float code never goes through double on the host.
DGS_HD float m_exp(float x) { return expf(x); }
DGS_HD double m_exp(double x) { return exp(x); }
DGS_HD float m_log(float x) { return logf(x); }
DGS_HD double m_log(double x) { return log(x); }
DGS_HD float m_sqrt(float x) { return sqrtf(x); }
DGS_HD double m_sqrt(double x) { return sqrt(x); }
DGS_HD float m_ceil(float x) { return ceilf(x); }
DGS_HD double m_ceil(double x) { return ceil(x); }
DGS_HD float m_floor(float x) { return floorf(x); }
DGS_HD double m_floor(double x) { return floor(x); }

template <typename T> struct Vec2 { T x, y; };
template <typename T> struct Vec3 { T x, y, z; };
// Symmetric 2x2 matrix [[a, b], [b, c]].
template <typename T> struct Sym2 { T a, b, c; };
// Row-major 3x3 matrix.
template <typename T> struct Mat3 { T m[3][3]; };
// 2x3 matrix (projection Jacobian).
template <typename T> struct Mat23 { T m[2][3]; };

template <typename T> DGS_HD Mat3<T> mat3_zero() {
  Mat3<T> r;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) r.m[i][j] = T(0);
  return r;
}

template <typename T> DGS_HD Mat3<T> matmul(const Mat3<T>& a, const Mat3<T>& b) {
  Mat3<T> r;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      r.m[i][j] = a.m[i][0] * b.m[0][j] + a.m[i][1] * b.m[1][j] + a.m[i][2] * b.m[2][j];
  return r;
}

template <typename T> DGS_HD Mat3<T> transpose(const Mat3<T>& a) {
  Mat3<T> r;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) r.m[i][j] = a.m[j][i];
  return r;
}

template <typename T> DGS_HD Mat3<T> add(const Mat3<T>& a, const Mat3<T>& b) {
  Mat3<T> r;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) r.m[i][j] = a.m[i][j] + b.m[i][j];
  return r;
}

template <typename T> DGS_HD Vec3<T> matvec(const Mat3<T>& a, const Vec3<T>& v) {
  return {a.m[0][0] * v.x + a.m[0][1] * v.y + a.m[0][2] * v.z,
          a.m[1][0] * v.x + a.m[1][1] * v.y + a.m[1][2] * v.z,
          a.m[2][0] * v.x + a.m[2][1] * v.y + a.m[2][2] * v.z};
}

template <typename T> DGS_HD Vec3<T> matTvec(const Mat3<T>& a, const Vec3<T>& v) {
  return {a.m[0][0] * v.x + a.m[1][0] * v.y + a.m[2][0] * v.z,
          a.m[0][1] * v.x + a.m[1][1] * v.y + a.m[2][1] * v.z,
          a.m[0][2] * v.x + a.m[1][2] * v.y + a.m[2][2] * v.z};
}

// ---------------------------------------------------------------------------------------------
// Rotation from a quaternion (w, x, y, z), not necessarily normalized.

template <typename T> DGS_HD Mat3<T> quat_to_rotmat(T w, T x, T y, T z) {
  const T inv = T(1) / m_sqrt(w * w + x * x + y * y + z * z);
  w *= inv; x *= inv; y *= inv; z *= inv;
  Mat3<T> r;
  r.m[0][0] = T(1) - T(2) * (y * y + z * z);
  r.m[0][1] = T(2) * (x * y - w * z);
  r.m[0][2] = T(2) * (x * z + w * y);
  r.m[1][0] = T(2) * (x * y + w * z);
  r.m[1][1] = T(1) - T(2) * (x * x + z * z);
  r.m[1][2] = T(2) * (y * z - w * x);
  r.m[2][0] = T(2) * (x * z - w * y);
  r.m[2][1] = T(2) * (y * z + w * x);
  r.m[2][2] = T(1) - T(2) * (x * x + y * y);
  return r;
}

// Vector-Jacobian product of quat_to_rotmat: dL/dR -> dL/dq (through the normalization).
template <typename T>
DGS_HD void quat_to_rotmat_vjp(T w, T x, T y, T z, const Mat3<T>& g, T out[4]) {
  const T inv = T(1) / m_sqrt(w * w + x * x + y * y + z * z);
  const T qw = w * inv, qx = x * inv, qy = y * inv, qz = z * inv;
  // Gradient with respect to the normalized quaternion.
  const T gw = T(2) * (qx * (g.m[2][1] - g.m[1][2]) + qy * (g.m[0][2] - g.m[2][0]) +
                       qz * (g.m[1][0] - g.m[0][1]));
  const T gx = T(2) * (-T(2) * qx * (g.m[1][1] + g.m[2][2]) + qy * (g.m[1][0] + g.m[0][1]) +
                       qz * (g.m[2][0] + g.m[0][2]) + qw * (g.m[2][1] - g.m[1][2]));
  const T gy = T(2) * (qx * (g.m[1][0] + g.m[0][1]) - T(2) * qy * (g.m[0][0] + g.m[2][2]) +
                       qz * (g.m[2][1] + g.m[1][2]) + qw * (g.m[0][2] - g.m[2][0]));
  const T gz = T(2) * (qx * (g.m[2][0] + g.m[0][2]) + qy * (g.m[2][1] + g.m[1][2]) -
                       T(2) * qz * (g.m[0][0] + g.m[1][1]) + qw * (g.m[1][0] - g.m[0][1]));
  // Through q / |q|: (I - q q^T) g / |q|.
  const T dot = qw * gw + qx * gx + qy * gy + qz * gz;
  out[0] = (gw - qw * dot) * inv;
  out[1] = (gx - qx * dot) * inv;
  out[2] = (gy - qy * dot) * inv;
  out[3] = (gz - qz * dot) * inv;
}

// ---------------------------------------------------------------------------------------------
// 3D covariance Sigma = R S S^T R^T with S = diag(scale).

template <typename T> DGS_HD Mat3<T> covariance_3d(const Mat3<T>& r, const Vec3<T>& s) {
  Mat3<T> m;  // M = R S
  for (int i = 0; i < 3; ++i) {
    m.m[i][0] = r.m[i][0] * s.x;
    m.m[i][1] = r.m[i][1] * s.y;
    m.m[i][2] = r.m[i][2] * s.z;
  }
  return matmul(m, transpose(m));
}

// VJP of covariance_3d for a symmetric upstream gradient g_sigma: -> dL/dR, dL/ds.
template <typename T>
DGS_HD void covariance_3d_vjp(const Mat3<T>& r, const Vec3<T>& s, const Mat3<T>& g_sigma,
                              Mat3<T>& g_r, Vec3<T>& g_s) {
  const T sv[3] = {s.x, s.y, s.z};
  Mat3<T> m;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) m.m[i][j] = r.m[i][j] * sv[j];
  // dL/dM = (G + G^T) M = 2 G M for symmetric G.
  Mat3<T> gm = matmul(g_sigma, m);
  T gs[3] = {T(0), T(0), T(0)};
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      gm.m[i][j] *= T(2);
      g_r.m[i][j] = gm.m[i][j] * sv[j];
      gs[j] += gm.m[i][j] * r.m[i][j];
    }
  g_s = {gs[0], gs[1], gs[2]};
}

// ---------------------------------------------------------------------------------------------
// Camera intrinsics and the local affine approximation (EWA splatting, Zwicker et al. 2002).

template <typename T> struct Intrinsics {
  T fx, fy, cx, cy;
  int width, height;
};

template <typename T> struct IntrinsicsGrad { T fx, fy, cx, cy; };

// Clamp bounds of x/z for the Jacobian: the view frustum widened by fov_guard of the image.
template <typename T> DGS_HD void jacobian_limits(const Intrinsics<T>& k, T& lox, T& hix, T& loy,
                                                  T& hiy) {
  const T gx = fov_guard<T>() * T(k.width), gy = fov_guard<T>() * T(k.height);
  lox = -(k.cx + gx) / k.fx;
  hix = (T(k.width) - k.cx + gx) / k.fx;
  loy = -(k.cy + gy) / k.fy;
  hiy = (T(k.height) - k.cy + gy) / k.fy;
}

template <typename T> DGS_HD T clamp_val(T v, T lo, T hi) { return v < lo ? lo : (v > hi ? hi : v); }

template <typename T> DGS_HD Mat23<T> projection_jacobian(const Vec3<T>& p, const Intrinsics<T>& k) {
  T lox, hix, loy, hiy;
  jacobian_limits(k, lox, hix, loy, hiy);
  const T tx = p.z * clamp_val(p.x / p.z, lox, hix);
  const T ty = p.z * clamp_val(p.y / p.z, loy, hiy);
  const T iz = T(1) / p.z, iz2 = iz * iz;
  Mat23<T> j;
  j.m[0][0] = k.fx * iz; j.m[0][1] = T(0); j.m[0][2] = -k.fx * tx * iz2;
  j.m[1][0] = T(0); j.m[1][1] = k.fy * iz; j.m[1][2] = -k.fy * ty * iz2;
  return j;
}

// VJP of projection_jacobian: dL/dJ -> dL/dp (added), dL/dK (added).
template <typename T>
DGS_HD void projection_jacobian_vjp(const Vec3<T>& p, const Intrinsics<T>& k, const Mat23<T>& gj,
                                    Vec3<T>& gp, IntrinsicsGrad<T>& gk) {
  T lox, hix, loy, hiy;
  jacobian_limits(k, lox, hix, loy, hiy);
  const T rx = p.x / p.z, ry = p.y / p.z;
  const T tx = p.z * clamp_val(rx, lox, hix);
  const T ty = p.z * clamp_val(ry, loy, hiy);
  const T iz = T(1) / p.z, iz2 = iz * iz, iz3 = iz2 * iz;
  // Direct dependence on z, fx, fy.
  gp.z += -k.fx * iz2 * gj.m[0][0] - k.fy * iz2 * gj.m[1][1] +
          T(2) * k.fx * tx * iz3 * gj.m[0][2] + T(2) * k.fy * ty * iz3 * gj.m[1][2];
  gk.fx += iz * gj.m[0][0] - tx * iz2 * gj.m[0][2];
  gk.fy += iz * gj.m[1][1] - ty * iz2 * gj.m[1][2];
  // Through tx, ty: identity inside the clamp; z * limit outside, where limit depends on K.
  const T g_tx = -k.fx * iz2 * gj.m[0][2];
  const T g_ty = -k.fy * iz2 * gj.m[1][2];
  if (rx < lox || rx > hix) {
    const T lim = rx < lox ? lox : hix;
    gp.z += lim * g_tx;
    // lim = (+-(W or 0) - cx -+ guard) / fx: d lim/d cx = -1/fx, d lim/d fx = -lim/fx.
    gk.cx += -p.z / k.fx * g_tx;
    gk.fx += -p.z * lim / k.fx * g_tx;
  } else {
    gp.x += g_tx;
  }
  if (ry < loy || ry > hiy) {
    const T lim = ry < loy ? loy : hiy;
    gp.z += lim * g_ty;
    gk.cy += -p.z / k.fy * g_ty;
    gk.fy += -p.z * lim / k.fy * g_ty;
  } else {
    gp.y += g_ty;
  }
}

// Sigma2D = J C J^T for a symmetric 3x3 C (camera-space covariance).
template <typename T> DGS_HD Sym2<T> project_covariance(const Mat23<T>& j, const Mat3<T>& c) {
  T jc[2][3];
  for (int i = 0; i < 2; ++i)
    for (int l = 0; l < 3; ++l)
      jc[i][l] = j.m[i][0] * c.m[0][l] + j.m[i][1] * c.m[1][l] + j.m[i][2] * c.m[2][l];
  Sym2<T> s;
  s.a = jc[0][0] * j.m[0][0] + jc[0][1] * j.m[0][1] + jc[0][2] * j.m[0][2];
  s.b = jc[0][0] * j.m[1][0] + jc[0][1] * j.m[1][1] + jc[0][2] * j.m[1][2];
  s.c = jc[1][0] * j.m[1][0] + jc[1][1] * j.m[1][1] + jc[1][2] * j.m[1][2];
  return s;
}

// VJP of project_covariance. g is the gradient as a symmetric matrix [[ga, gb], [gb, gc]]
// (gb is the gradient of ONE off-diagonal element). -> dL/dJ, dL/dC (symmetric).
template <typename T>
DGS_HD void project_covariance_vjp(const Mat23<T>& j, const Mat3<T>& c, const Sym2<T>& g,
                                   Mat23<T>& gj, Mat3<T>& gc) {
  const T gm[2][2] = {{g.a, g.b}, {g.b, g.c}};
  // dL/dJ = 2 G J C.
  T jc[2][3];
  for (int i = 0; i < 2; ++i)
    for (int l = 0; l < 3; ++l)
      jc[i][l] = j.m[i][0] * c.m[0][l] + j.m[i][1] * c.m[1][l] + j.m[i][2] * c.m[2][l];
  for (int i = 0; i < 2; ++i)
    for (int l = 0; l < 3; ++l) gj.m[i][l] = T(2) * (gm[i][0] * jc[0][l] + gm[i][1] * jc[1][l]);
  // dL/dC = J^T G J.
  for (int a = 0; a < 3; ++a)
    for (int b = 0; b < 3; ++b) {
      T acc = T(0);
      for (int i = 0; i < 2; ++i)
        for (int l = 0; l < 2; ++l) acc += j.m[i][a] * gm[i][l] * j.m[l][b];
      gc.m[a][b] = acc;
    }
}

template <typename T> DGS_HD T det2(const Sym2<T>& s) { return s.a * s.c - s.b * s.b; }

template <typename T> DGS_HD Sym2<T> inverse2(const Sym2<T>& s) {
  const T inv = T(1) / det2(s);
  return {s.c * inv, -s.b * inv, s.a * inv};
}

// VJP of the inverse, both as symmetric matrices (off-diagonal gradients per element):
// dL/dS = -S^-1 G S^-1.
template <typename T> DGS_HD Sym2<T> inverse2_vjp(const Sym2<T>& conic, const Sym2<T>& g) {
  const T a = conic.a, b = conic.b, c = conic.c;
  // P = conic * G
  const T p00 = a * g.a + b * g.b, p01 = a * g.b + b * g.c;
  const T p10 = b * g.a + c * g.b, p11 = b * g.b + c * g.c;
  return {-(p00 * a + p01 * b), -(p00 * b + p01 * c), -(p10 * b + p11 * c)};
}

// Mip-Splatting 2D filter compensation (Yu et al. 2024): sqrt(det(S - eps I) / det(S)).
template <typename T> DGS_HD T compensation(const Sym2<T>& s_blur, T eps) {
  const T det = det2(s_blur);
  const T det_o = (s_blur.a - eps) * (s_blur.c - eps) - s_blur.b * s_blur.b;
  const T r = det_o / det;
  return r > T(0) ? m_sqrt(r) : T(0);
}

// VJP of compensation with respect to s_blur, as a symmetric matrix gradient.
template <typename T> DGS_HD Sym2<T> compensation_vjp(const Sym2<T>& s, T eps, T g_comp) {
  const T det = det2(s);
  const T det_o = (s.a - eps) * (s.c - eps) - s.b * s.b;
  const T r = det_o / det;
  if (!(r > T(0))) return {T(0), T(0), T(0)};
  const T comp = m_sqrt(r);
  const T k = g_comp / (T(2) * comp * det * det);
  // d det / dS = [[c, -b], [-b, a]]; d det_o / dS = [[c - eps, -b], [-b, a - eps]].
  return {k * ((s.c - eps) * det - det_o * s.c), k * (-s.b * det + det_o * s.b),
          k * ((s.a - eps) * det - det_o * s.a)};
}

// Beta mixing of the two opacities (paper eq. 5), scaled by the compensation factor.
template <typename T>
DGS_HD void mix_opacities(T op_c, T op_g, T beta, T comp, T& o_c, T& o_g) {
  o_c = T(0.5) * comp * ((T(1) + beta) * op_c + (T(1) - beta) * op_g);
  o_g = T(0.5) * comp * ((T(1) - beta) * op_c + (T(1) + beta) * op_g);
}

// ---------------------------------------------------------------------------------------------
// One Gaussian through one camera: everything the projection forward computes, kept together so
// the backward pass (and the CUDA kernels) recompute it with the very same code.

template <typename T> struct ProjCamera {
  Mat3<T> r;  // world-to-camera rotation
  Vec3<T> t;  // world-to-camera translation
  Intrinsics<T> k;
};

// From a row-major 4x4 world-to-camera matrix and a row-major 3x3 K.
template <typename T>
DGS_HD ProjCamera<T> camera_from(const T* viewmat, const T* K, int width, int height) {
  ProjCamera<T> cam;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) cam.r.m[i][j] = viewmat[4 * i + j];
  cam.t = {viewmat[3], viewmat[7], viewmat[11]};
  cam.k = {K[0], K[4], K[2], K[5], width, height};
  return cam;
}

template <typename T> struct Projected {
  Vec3<T> p;        // camera-space mean
  Mat3<T> rq;       // rotation of the Gaussian
  Mat3<T> cov3d;    // world-space covariance
  Mat3<T> cov_cam;  // camera-space covariance
  Mat23<T> jac;
  Sym2<T> cov2d;    // with the eps2d filter
  T comp;           // Mip-Splatting compensation (1 without antialiasing)
  bool valid;       // inside (near, far) with a positive-definite 2D covariance
};

template <typename T>
DGS_HD Projected<T> project_one(const T* mean, const T* quat, const T* scale,
                                const ProjCamera<T>& cam, T eps2d, bool antialiased, T near_plane,
                                T far_plane) {
  Projected<T> g;
  g.valid = false;
  g.comp = T(1);
  g.p = matvec(cam.r, Vec3<T>{mean[0], mean[1], mean[2]});
  g.p.x += cam.t.x; g.p.y += cam.t.y; g.p.z += cam.t.z;
  if (!(g.p.z > near_plane) || !(g.p.z < far_plane)) return g;
  g.rq = quat_to_rotmat(quat[0], quat[1], quat[2], quat[3]);
  g.cov3d = covariance_3d(g.rq, Vec3<T>{scale[0], scale[1], scale[2]});
  g.cov_cam = matmul(matmul(cam.r, g.cov3d), transpose(cam.r));
  g.jac = projection_jacobian(g.p, cam.k);
  g.cov2d = project_covariance(g.jac, g.cov_cam);
  g.cov2d.a += eps2d;
  g.cov2d.c += eps2d;
  if (!(det2(g.cov2d) > T(0))) return g;
  g.comp = antialiased ? compensation(g.cov2d, eps2d) : T(1);
  g.valid = true;
  return g;
}

// Gradients of one Gaussian's projection; `camera` holds the world-to-camera rotation (9,
// row-major), translation (3) and fx, fy, cx, cy (4), to be summed over Gaussians.
template <typename T> struct ProjectionGrads {
  T mean[3], quat[4], scale[3], op_c, op_g;
  T camera[16];
};

// VJP of project_one followed by mean2d = (fx x/z + cx, fy y/z + cy), depth = z, the conic
// (inverse 2D covariance) and the beta mixing of the opacities, for a valid `g`.
// v_conic is (a, b, c) with b the one off-diagonal scalar; v_opac is (appearance, geometry).
template <typename T>
DGS_HD ProjectionGrads<T> project_one_vjp(const Projected<T>& g, const T* mean, const T* quat,
                                          const T* scale, T op_c, T op_g,
                                          const ProjCamera<T>& cam, T beta, T eps2d,
                                          bool antialiased, const T* v_mean2d, const T* v_conic,
                                          T v_depth, const T* v_opac) {
  ProjectionGrads<T> out;
  // Opacity mixing.
  const T voc = v_opac[0], vog = v_opac[1];
  const T half_c = T(0.5) * g.comp;
  out.op_c = half_c * ((T(1) + beta) * voc + (T(1) - beta) * vog);
  out.op_g = half_c * ((T(1) - beta) * voc + (T(1) + beta) * vog);
  const T v_comp = T(0.5) * (((T(1) + beta) * op_c + (T(1) - beta) * op_g) * voc +
                             ((T(1) - beta) * op_c + (T(1) + beta) * op_g) * vog);
  // Conic -> 2D covariance (conic b is one scalar used twice: per-element gradient is half).
  const Sym2<T> conic = inverse2(g.cov2d);
  Sym2<T> g_cov2d = inverse2_vjp(conic, Sym2<T>{v_conic[0], T(0.5) * v_conic[1], v_conic[2]});
  if (antialiased) {
    const Sym2<T> gc = compensation_vjp(g.cov2d, eps2d, v_comp);
    g_cov2d.a += gc.a; g_cov2d.b += gc.b; g_cov2d.c += gc.c;
  }
  Mat23<T> g_jac;
  Mat3<T> g_cov_cam;
  project_covariance_vjp(g.jac, g.cov_cam, g_cov2d, g_jac, g_cov_cam);
  // Camera point: mean2d, depth and the Jacobian.
  const T iz = T(1) / g.p.z;
  const T vmx = v_mean2d[0], vmy = v_mean2d[1];
  Vec3<T> g_p = {cam.k.fx * iz * vmx, cam.k.fy * iz * vmy,
                 -(cam.k.fx * g.p.x * vmx + cam.k.fy * g.p.y * vmy) * iz * iz + v_depth};
  IntrinsicsGrad<T> g_k = {g.p.x * iz * vmx, g.p.y * iz * vmy, vmx, vmy};
  projection_jacobian_vjp(g.p, cam.k, g_jac, g_p, g_k);
  // Camera-space covariance R C R^T -> world covariance and the camera rotation.
  const Mat3<T> g_cov3d = matmul(matmul(transpose(cam.r), g_cov_cam), cam.r);
  const Mat3<T> g_r_cov = matmul(matmul(g_cov_cam, cam.r), g.cov3d);  // x2 below
  Mat3<T> g_rq;
  Vec3<T> g_s;
  covariance_3d_vjp(g.rq, Vec3<T>{scale[0], scale[1], scale[2]}, g_cov3d, g_rq, g_s);
  quat_to_rotmat_vjp(quat[0], quat[1], quat[2], quat[3], g_rq, out.quat);
  const Vec3<T> g_mean = matTvec(cam.r, g_p);
  out.mean[0] = g_mean.x; out.mean[1] = g_mean.y; out.mean[2] = g_mean.z;
  out.scale[0] = g_s.x; out.scale[1] = g_s.y; out.scale[2] = g_s.z;
  // Camera: p = R mu + t.
  const T gpv[3] = {g_p.x, g_p.y, g_p.z};
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) out.camera[3 * a + b] = gpv[a] * mean[b] + T(2) * g_r_cov.m[a][b];
    out.camera[9 + a] = gpv[a];
  }
  out.camera[12] = g_k.fx; out.camera[13] = g_k.fy; out.camera[14] = g_k.cx;
  out.camera[15] = g_k.cy;
  return out;
}

// ---------------------------------------------------------------------------------------------
// Screen extent: the axis-aligned box of the ellipse where max(o_c, o_g) exp(-q/2) >= 1/255,
// widened by a small margin so that float rounding never drops a pixel that dense evaluation
// would blend. Returns false when the Gaussian can never reach 1/255.
template <typename T>
DGS_HD bool screen_extent(const Sym2<T>& cov2d, T o_max, T& ex, T& ey) {
  if (!(o_max >= alpha_min<T>())) return false;
  const T k = T(2) * m_log(o_max / alpha_min<T>());
  const T kk = k * T(1.001) + T(1e-3);
  ex = m_sqrt(kk * cov2d.a) * T(1.001) + T(1e-2);
  ey = m_sqrt(kk * cov2d.c) * T(1.001) + T(1e-2);
  return true;
}

// Threshold k of the quadratic form d^T conic d <= k inside which max(o_c, o_g) can reach 1/255,
// widened like screen_extent. Negative when the Gaussian never reaches 1/255.
template <typename T> DGS_HD T level_k(T o_max) {
  if (!(o_max >= alpha_min<T>())) return T(-1);
  return T(2) * m_log(o_max / alpha_min<T>()) * T(1.001) + T(1e-3);
}

// Pixels [u_lo, u_hi] of row centre y = v + 0.5 inside the ellipse d^T conic d <= k (solving the
// quadratic in dx), widened by a small margin; false when the row misses the ellipse. Pixels
// outside the span cannot reach 1/255, so skipping them keeps dense-evaluation results.
template <typename T>
DGS_HD bool row_span(const Sym2<T>& conic, T k, T mx, T dy, int64_t& u_lo, int64_t& u_hi) {
  const T det = conic.a * conic.c - conic.b * conic.b;
  const T disc = conic.a * k - dy * dy * det;
  if (!(disc >= T(0))) return false;
  const T root = m_sqrt(disc) / conic.a;
  const T centre = mx - T(0.5) - conic.b * dy / conic.a;
  const T margin = root * T(1e-3) + T(1e-2);
  u_lo = int64_t(m_ceil(centre - root - margin));
  u_hi = int64_t(m_floor(centre + root + margin));
  return u_lo <= u_hi;
}

// Pixel rectangle [u0, u1] x [v0, v1] (inclusive) of pixel centres u + 0.5 within the extent,
// clipped to the image. Returns false when empty.
template <typename T>
DGS_HD bool pixel_rect(T mx, T my, T ex, T ey, int width, int height, int32_t rect[4]) {
  const T fu0 = m_ceil(mx - ex - T(0.5)), fu1 = m_floor(mx + ex - T(0.5));
  const T fv0 = m_ceil(my - ey - T(0.5)), fv1 = m_floor(my + ey - T(0.5));
  if (!(fu1 >= T(0)) || !(fv1 >= T(0)) || !(fu0 <= T(width - 1)) || !(fv0 <= T(height - 1)))
    return false;
  rect[0] = fu0 < T(0) ? 0 : int32_t(fu0);
  rect[1] = fv0 < T(0) ? 0 : int32_t(fv0);
  rect[2] = fu1 > T(width - 1) ? width - 1 : int32_t(fu1);
  rect[3] = fv1 > T(height - 1) ? height - 1 : int32_t(fv1);
  return rect[0] <= rect[2] && rect[1] <= rect[3];
}

// ---------------------------------------------------------------------------------------------
// Per pixel: the Gaussian's exponent at offset d = pixel centre - mean2d.
template <typename T> DGS_HD T gaussian_exponent(const Sym2<T>& conic, T dx, T dy) {
  return T(-0.5) * (conic.a * dx * dx + conic.c * dy * dy) - conic.b * dx * dy;
}

// Alpha of one branch; `clamped` tells the backward pass that the gradient is zero.
template <typename T> DGS_HD T branch_alpha(T o, T vis, bool& clamped) {
  const T a = o * vis;
  clamped = a > alpha_max<T>();
  return clamped ? alpha_max<T>() : a;
}

// d exponent / d mean2d at offset d = pixel centre - mean2d (the offset's sign flips twice).
template <typename T> DGS_HD Vec2<T> exponent_dmean(const Sym2<T>& conic, T dx, T dy) {
  return {conic.a * dx + conic.b * dy, conic.b * dx + conic.c * dy};
}

// d exponent / d conic, with b the one off-diagonal scalar.
template <typename T> DGS_HD Sym2<T> exponent_dconic(T dx, T dy) {
  return {T(-0.5) * dx * dx, -dx * dy, T(-0.5) * dy * dy};
}

}  // namespace dgs
