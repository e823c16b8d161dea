// Ray tracing through Gaussians for ambient occlusion: per-ray math shared by the CPU tracer and
// the CUDA one (DESIGN.md section 5, "Ambient occlusion"); the tree and its walk are in
// raytrace_bvh.h. Plain structs, no torch.
#pragma once

#include "gaussian_math.h"

namespace dgs {

// Direction i of n on the hemisphere z >= 0, Fibonacci lattice: uniform in z = cos(theta), so
// the points cover equal areas; azimuth advances by the golden angle.
template <typename T> DGS_HD Vec3<T> fibonacci_hemisphere(int i, int n) {
  const T z = T(1) - (T(i) + T(0.5)) / T(n);
  const T r = m_sqrt(T(1) - z * z > T(0) ? T(1) - z * z : T(0));
  const T phi = T(2.39996322972865332) * T(i);  // pi (3 - sqrt 5)
  return {r * T(cos(phi)), r * T(sin(phi)), z};
}

// An orthonormal frame (t, b, n) around a unit normal n.
template <typename T> DGS_HD void normal_frame(const Vec3<T>& n, Vec3<T>& t, Vec3<T>& b) {
  // Cross with the world axis least aligned with n.
  const T ax = n.x < T(0) ? -n.x : n.x;
  const Vec3<T> a = ax < T(0.9) ? Vec3<T>{T(1), T(0), T(0)} : Vec3<T>{T(0), T(1), T(0)};
  t = {n.y * a.z - n.z * a.y, n.z * a.x - n.x * a.z, n.x * a.y - n.y * a.x};
  const T inv = T(1) / m_sqrt(t.x * t.x + t.y * t.y + t.z * t.z);
  t = {t.x * inv, t.y * inv, t.z * inv};
  b = {n.y * t.z - n.z * t.y, n.z * t.x - n.x * t.z, n.x * t.y - n.y * t.x};
}

// Inverse covariance R diag(1/s^2) R^T as a row-major 3x3 matrix.
template <typename T> DGS_HD Mat3<T> inverse_covariance_3d(const Mat3<T>& r, const Vec3<T>& s) {
  const T inv[3] = {T(1) / (s.x * s.x), T(1) / (s.y * s.y), T(1) / (s.z * s.z)};
  Mat3<T> m;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      m.m[i][j] = r.m[i][0] * inv[0] * r.m[j][0] + r.m[i][1] * inv[1] * r.m[j][1] +
                  r.m[i][2] * inv[2] * r.m[j][2];
  return m;
}

// Half extents of the axis-aligned box around the 3-sigma ellipsoid: 3 sqrt(Sigma_ii).
template <typename T> DGS_HD Vec3<T> three_sigma_extent(const Mat3<T>& r, const Vec3<T>& s) {
  const Mat3<T> c = covariance_3d(r, s);
  return {T(3) * m_sqrt(c.m[0][0]), T(3) * m_sqrt(c.m[1][1]), T(3) * m_sqrt(c.m[2][2])};
}

// Whether the ray o + t d, t >= 0, meets the box [lo, hi] (slab test; inv_d = 1 / d).
template <typename T>
DGS_HD bool ray_hits_box(const Vec3<T>& o, const Vec3<T>& inv_d, const T lo[3], const T hi[3]) {
  const T oo[3] = {o.x, o.y, o.z}, id[3] = {inv_d.x, inv_d.y, inv_d.z};
  T t0 = T(0), t1 = T(1e30);
  for (int a = 0; a < 3; ++a) {
    T ta = (lo[a] - oo[a]) * id[a], tb = (hi[a] - oo[a]) * id[a];
    if (ta > tb) { const T tmp = ta; ta = tb; tb = tmp; }
    t0 = ta > t0 ? ta : t0;
    t1 = tb < t1 ? tb : t1;
    if (t0 > t1) return false;
  }
  return true;
}

// Alpha of a Gaussian at the ray's closest approach (in its own Mahalanobis metric), t >= 0,
// with the rasterizer's clamp at 0.99; 0 below 1/255.
template <typename T>
DGS_HD T alpha_along_ray(const Vec3<T>& o, const Vec3<T>& d, const Vec3<T>& mean,
                         const Mat3<T>& inv_cov, T opacity) {
  const Vec3<T> m = {mean.x - o.x, mean.y - o.y, mean.z - o.z};
  const Vec3<T> ad = matvec(inv_cov, d), am = matvec(inv_cov, m);
  const T a = d.x * ad.x + d.y * ad.y + d.z * ad.z;
  const T b = d.x * am.x + d.y * am.y + d.z * am.z;
  const T c = m.x * am.x + m.y * am.y + m.z * am.z;
  const T t = b > T(0) ? b / a : T(0);
  const T q = c - T(2) * t * b + t * t * a;
  const T al = opacity * m_exp(T(-0.5) * (q > T(0) ? q : T(0)));
  if (al < alpha_min<T>()) return T(0);
  return al > alpha_max<T>() ? alpha_max<T>() : al;
}

}  // namespace dgs
