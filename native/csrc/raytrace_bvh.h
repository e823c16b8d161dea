// The ray tracer's BVH and per-ray walk, shared by the CPU tracer (raytrace.cpp) and the CUDA one
// (raytrace.cu) so both trace the same tree with the same code. The tree is built on the host
// into flat arrays (BvhArrays); the walk reads them through raw pointers (BvhView), host or
// device memory alike. No torch here: raytrace.cu includes this header.
#pragma once

#include <algorithm>
#include <cstdint>
#include <numeric>
#include <vector>

#include "raytrace_math.h"

namespace dgs {

constexpr int kLeafSize = 4;
// Traversal stack entries per ray; the build bounds the depth so that it cannot overflow.
constexpr int kStackSize = 64;

template <typename T> struct Node {
  T lo[3], hi[3];
  int32_t right;  // internal: index of the right child (the left one follows the node)
  int32_t first;  // leaf: first entry in the ordered index list
  int32_t count;  // leaf: number of entries; 0 for internal nodes
};

// The prepared scene as seen by the walk. Per-Gaussian arrays are indexed by Gaussian id:
// mean (n,3), inv_cov (n,9) row-major, lo/hi (n,3) the 3-sigma box, opacity (n).
template <typename T> struct BvhView {
  const Node<T>* nodes;
  const int32_t* order;  // leaf entries -> Gaussian ids
  const T* mean;
  const T* inv_cov;
  const T* lo;
  const T* hi;
  const T* opacity;
  int64_t n;  // number of Gaussians; 0 means no tree (every ray sees the sky)
};

// Transmittance along one ray from o in direction d, Gaussian `exclude` ignored (-1: none).
template <typename T>
DGS_HD T trace_ray(const BvhView<T>& bvh, const Vec3<T>& o, const Vec3<T>& d, int64_t exclude) {
  const Vec3<T> inv_d = {T(1) / d.x, T(1) / d.y, T(1) / d.z};
  int32_t stack[kStackSize];
  int top = 0;
  stack[top++] = 0;
  T trans = T(1);
  while (top > 0) {
    const int32_t index = stack[--top];
    const Node<T>& node = bvh.nodes[index];
    if (!ray_hits_box(o, inv_d, node.lo, node.hi)) continue;
    if (node.count == 0) {
      stack[top++] = node.right;
      stack[top++] = index + 1;
      continue;
    }
    for (int32_t i = node.first; i < node.first + node.count; ++i) {
      const int32_t k = bvh.order[i];
      if (k == exclude || !ray_hits_box(o, inv_d, bvh.lo + 3 * k, bvh.hi + 3 * k)) continue;
      const T* mp = bvh.mean + 3 * k;
      const T* cp = bvh.inv_cov + 9 * k;
      const Vec3<T> mean = {mp[0], mp[1], mp[2]};
      const Mat3<T> inv_cov = {
          {{cp[0], cp[1], cp[2]}, {cp[3], cp[4], cp[5]}, {cp[6], cp[7], cp[8]}}};
      const T al = alpha_along_ray(o, d, mean, inv_cov, bvh.opacity[k]);
      trans *= T(1) - al;
      // Order does not matter for a product, so the walk may stop as soon as T is negligible.
      if (trans < transmittance_min<T>()) return trans;
    }
  }
  return trans;
}

// Visibility of one origin o3 (3) with unit normal n3 (3): the cosine-weighted mean of the
// transmittance of n_dirs rays over the Fibonacci hemisphere about the normal.
template <typename T>
DGS_HD T origin_visibility(const BvhView<T>& bvh, const T* o3, const T* n3, int64_t exclude,
                           int n_dirs) {
  if (bvh.n == 0) return T(1);
  const Vec3<T> o = {o3[0], o3[1], o3[2]};
  const Vec3<T> nn = {n3[0], n3[1], n3[2]};
  Vec3<T> t, b;
  normal_frame(nn, t, b);
  T num = T(0), den = T(0);
  for (int k = 0; k < n_dirs; ++k) {
    const Vec3<T> l = fibonacci_hemisphere<T>(k, n_dirs);
    const Vec3<T> d = {t.x * l.x + b.x * l.y + nn.x * l.z, t.y * l.x + b.y * l.y + nn.y * l.z,
                       t.z * l.x + b.z * l.y + nn.z * l.z};
    num += l.z * trace_ray(bvh, o, d, exclude);
    den += l.z;
  }
  return num / den;
}

// ---- Host-only: the prepared Gaussians and the tree, as flat arrays. ----

template <typename T> struct BvhArrays {
  std::vector<Node<T>> nodes;
  std::vector<int32_t> order;
  std::vector<T> mean, inv_cov, lo, hi, opacity;  // (n,3), (n,9), (n,3), (n,3), (n)

  int64_t size() const { return int64_t(opacity.size()); }
  BvhView<T> view() const {
    return {nodes.data(), order.data(), mean.data(), inv_cov.data(), lo.data(), hi.data(),
            opacity.data(), size()};
  }
};

// Inverse covariance and 3-sigma box of Gaussian i, from means (n,3), quats (n,4) w,x,y,z,
// scales (n,3), opacity (n) on the host.
template <typename T>
inline void prepare_gaussian(int64_t i, const T* means, const T* quats, const T* scales,
                             const T* opacity, BvhArrays<T>& g) {
  const T* q = quats + 4 * i;
  const Mat3<T> r = quat_to_rotmat(q[0], q[1], q[2], q[3]);
  const Vec3<T> s = {scales[3 * i], scales[3 * i + 1], scales[3 * i + 2]};
  const Mat3<T> ic = inverse_covariance_3d(r, s);
  for (int a = 0; a < 3; ++a)
    for (int b = 0; b < 3; ++b) g.inv_cov[9 * i + 3 * a + b] = ic.m[a][b];
  const Vec3<T> e = three_sigma_extent(r, s);
  const T ext[3] = {e.x, e.y, e.z};
  for (int a = 0; a < 3; ++a) {
    const T c = means[3 * i + a];
    g.mean[3 * i + a] = c;
    g.lo[3 * i + a] = c - ext[a];
    g.hi[3 * i + a] = c + ext[a];
  }
  g.opacity[i] = opacity[i];
}

// Node over order[first, first + count), then its children: median split of the box centres
// along the longest axis of their spread, down to kLeafSize entries.
template <typename T>
int32_t build_node(BvhArrays<T>& g, int32_t first, int32_t count, int depth) {
  const int32_t index = int32_t(g.nodes.size());
  g.nodes.push_back({});
  Node<T> node;
  for (int a = 0; a < 3; ++a) { node.lo[a] = T(1e30); node.hi[a] = T(-1e30); }
  T clo[3] = {T(1e30), T(1e30), T(1e30)}, chi[3] = {T(-1e30), T(-1e30), T(-1e30)};
  for (int32_t i = first; i < first + count; ++i) {
    const int32_t k = g.order[i];
    for (int a = 0; a < 3; ++a) {
      node.lo[a] = std::min(node.lo[a], g.lo[3 * k + a]);
      node.hi[a] = std::max(node.hi[a], g.hi[3 * k + a]);
      const T c = T(0.5) * (g.lo[3 * k + a] + g.hi[3 * k + a]);
      clo[a] = std::min(clo[a], c);
      chi[a] = std::max(chi[a], c);
    }
  }
  node.right = -1; node.first = first; node.count = count;
  // Depth is bounded so the traversal stack (kStackSize) cannot overflow.
  if (count > kLeafSize && depth < kStackSize - 2) {
    int axis = 0;
    for (int a = 1; a < 3; ++a)
      if (chi[a] - clo[a] > chi[axis] - clo[axis]) axis = a;
    const int32_t half = count / 2;
    auto begin = g.order.begin() + first;
    std::nth_element(begin, begin + half, begin + count, [&](int32_t x, int32_t y) {
      return g.lo[3 * x + axis] + g.hi[3 * x + axis] < g.lo[3 * y + axis] + g.hi[3 * y + axis];
    });
    node.count = 0;
    build_node(g, first, half, depth + 1);
    node.right = build_node(g, first + half, count - half, depth + 1);
  }
  g.nodes[index] = node;
  return index;
}

// Prepares n < 2^31 Gaussians (host pointers) and builds their tree. `parallel_for(n, grain,
// body)` runs body(begin, end) over chunks of [0, n) (the torch side passes at::parallel_for, so
// this header stays torch-free); the tree itself is built serially.
template <typename T, typename ParallelFor>
BvhArrays<T> build_bvh(const T* means, const T* quats, const T* scales, const T* opacity,
                       int64_t n, const ParallelFor& parallel_for) {
  BvhArrays<T> g;
  g.mean.resize(3 * n); g.inv_cov.resize(9 * n); g.lo.resize(3 * n); g.hi.resize(3 * n);
  g.opacity.resize(n);
  parallel_for(n, int64_t(4096), [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) prepare_gaussian(i, means, quats, scales, opacity, g);
  });
  if (n == 0) return g;
  g.order.resize(n);
  std::iota(g.order.begin(), g.order.end(), 0);
  g.nodes.reserve(size_t(2 * n / kLeafSize + 2));
  build_node(g, 0, int32_t(n), 0);
  return g;
}

}  // namespace dgs
