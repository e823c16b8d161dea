// The ray tracer's BVH and per-ray walk, shared by the CPU tracer (raytrace.cpp) and the CUDA one
// (raytrace.cu) so both trace the same tree with the same code. The tree is built on the host
// into flat arrays (BvhArrays); the walk reads them through raw pointers (BvhView), host or
// device memory alike. No torch here: raytrace.cu includes this header.
#pragma once

#include <algorithm>
#include <cstdint>
#include <utility>
#include <vector>

#include "raytrace_math.h"

namespace dgs {

// Leaves hold up to kLeafSize entries, or up to kMaxLeaf where the SAH finds no cheaper split.
constexpr int kLeafSize = 8;
constexpr int kMaxLeaf = 12;
// Bins per axis of the binned SAH build (Wald 2007, "On fast construction of SAH-based BVHs").
constexpr int kBins = 16;
// Traversal stack entries per ray; the build bounds the depth so that it cannot overflow.
constexpr int kStackSize = 64;

template <typename T> struct Node {
  T lo[3], hi[3];
  int32_t right;  // internal: index of the right child (the left one follows the node)
  int32_t first;  // leaf: first entry in the ordered index list; internal: the split axis
  int32_t count;  // leaf: number of entries; 0 for internal nodes
};

// One Gaussian as the walk reads it, in one piece (64 bytes in float: a cache line): its box,
// mean, the upper triangle of its inverse covariance (xx, xy, xz, yy, yz, zz) and opacity. The
// box is the 3-sigma box of DESIGN.md, shrunk to the ellipsoid outside which alpha < 1/255
// where that is smaller (low opacity): a ray that misses it has alpha 0 there anyway.
template <typename T> struct Prim {
  T lo[3], hi[3], mean[3], ic[6], opacity;
};

// The prepared scene as seen by the walk: prims in the tree's leaf order (a leaf's Gaussians
// are contiguous in memory), order[i] the Gaussian id of prims[i]. Gaussians below 1/255
// opacity are left out of the tree (they never occlude).
template <typename T> struct BvhView {
  const Node<T>* nodes;
  const int32_t* order;
  const Prim<T>* prims;
  int64_t n;  // number of Gaussians; 0 means no tree (every ray sees the sky)
  // (also when every Gaussian is below 1/255 opacity: then the tree has no nodes)
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
      // Nearer child first (the left one holds the lower coordinates along the split axis):
      // occluders met sooner end the walk sooner (T < transmittance_min).
      const T da = node.first == 0 ? d.x : (node.first == 1 ? d.y : d.z);
      stack[top++] = da >= T(0) ? node.right : index + 1;
      stack[top++] = da >= T(0) ? index + 1 : node.right;
      continue;
    }
    for (int32_t i = node.first; i < node.first + node.count; ++i) {
      const Prim<T>& g = bvh.prims[i];
      if (!ray_hits_box(o, inv_d, g.lo, g.hi) || bvh.order[i] == exclude) continue;
      const Vec3<T> mean = {g.mean[0], g.mean[1], g.mean[2]};
      const T* c = g.ic;
      const Mat3<T> inv_cov = {{{c[0], c[1], c[2]}, {c[1], c[3], c[4]}, {c[2], c[4], c[5]}}};
      const T al = alpha_along_ray(o, d, mean, inv_cov, g.opacity);
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
  std::vector<Prim<T>> prims;  // by Gaussian id while building, then in leaf order (`order`)
  int64_t count = 0;           // Gaussians given (traced or not)

  // What BvhView::n must be: the Gaussians, or 0 when the tree is empty.
  int64_t traced() const { return nodes.empty() ? 0 : count; }
  BvhView<T> view() const { return {nodes.data(), order.data(), prims.data(), traced()}; }
};

// Gaussian i from means (n,3), quats (n,4) w,x,y,z, scales (n,3), opacity (n) on the host.
template <typename T>
inline Prim<T> prepare_gaussian(int64_t i, const T* means, const T* quats, const T* scales,
                                const T* opacity) {
  const T* q = quats + 4 * i;
  const Mat3<T> r = quat_to_rotmat(q[0], q[1], q[2], q[3]);
  const Vec3<T> s = {scales[3 * i], scales[3 * i + 1], scales[3 * i + 2]};
  const Mat3<T> ic = inverse_covariance_3d(r, s);
  const Vec3<T> e = three_sigma_extent(r, s);
  // Extent of the level set alpha = 1/255 in sigmas (level_k widens it a little, so rounding
  // never culls a ray that reaches 1/255), capped at the 3-sigma box.
  const T k = level_k(opacity[i]);
  const T f = k >= T(9) ? T(1) : (k > T(0) ? m_sqrt(k) / T(3) : T(0));
  const T ext[3] = {e.x * f, e.y * f, e.z * f};
  Prim<T> g;
  for (int a = 0; a < 3; ++a) {
    g.mean[a] = means[3 * i + a];
    g.lo[a] = g.mean[a] - ext[a];
    g.hi[a] = g.mean[a] + ext[a];
  }
  const T upper[6] = {ic.m[0][0], ic.m[0][1], ic.m[0][2], ic.m[1][1], ic.m[1][2], ic.m[2][2]};
  for (int a = 0; a < 6; ++a) g.ic[a] = upper[a];
  g.opacity = opacity[i];
  return g;
}

// Bounds of a set of boxes, and the surface area the SAH weighs them by.
template <typename T> struct Bounds {
  T lo[3] = {T(1e30), T(1e30), T(1e30)}, hi[3] = {T(-1e30), T(-1e30), T(-1e30)};
  void grow(const T* l, const T* h) {
    for (int a = 0; a < 3; ++a) { lo[a] = std::min(lo[a], l[a]); hi[a] = std::max(hi[a], h[a]); }
  }
  void grow(const Bounds& b) { grow(b.lo, b.hi); }
  T area() const {
    const T x = hi[0] - lo[0], y = hi[1] - lo[1], z = hi[2] - lo[2];
    return x < T(0) ? T(0) : T(2) * (x * y + y * z + z * x);
  }
};

// Best binned-SAH split of order[first, first + count): (axis, bin boundary) and its cost
// relative to the parent's area (traversal step 1, one Gaussian test 1); axis -1 when every box
// centre coincides.
template <typename T>
std::pair<int, int> sah_split(const BvhArrays<T>& g, int32_t first, int32_t count,
                              const T clo[3], const T chi[3], T parent_area, T& best_cost) {
  std::pair<int, int> best = {-1, 0};
  best_cost = T(1e30);
  for (int axis = 0; axis < 3; ++axis) {
    const T extent = chi[axis] - clo[axis];
    if (!(extent > T(0))) continue;
    Bounds<T> bins[kBins];
    int32_t counts[kBins] = {};
    for (int32_t i = first; i < first + count; ++i) {
      const int32_t k = g.order[i];
      const T c = T(0.5) * (g.prims[k].lo[axis] + g.prims[k].hi[axis]);
      const int b = std::min(kBins - 1, int(T(kBins) * (c - clo[axis]) / extent));
      bins[b].grow(g.prims[k].lo, g.prims[k].hi);
      ++counts[b];
    }
    T right_area[kBins];
    int32_t right_count[kBins];
    Bounds<T> acc;
    int32_t n = 0;
    for (int b = kBins - 1; b > 0; --b) {  // right side of the boundary before bin b
      acc.grow(bins[b]);
      n += counts[b];
      right_area[b] = acc.area();
      right_count[b] = n;
    }
    Bounds<T> left;
    int32_t nl = 0;
    for (int b = 1; b < kBins; ++b) {
      left.grow(bins[b - 1]);
      nl += counts[b - 1];
      if (nl == 0 || right_count[b] == 0) continue;
      const T cost = T(1) + (left.area() * T(nl) + right_area[b] * T(right_count[b])) /
                                std::max(parent_area, T(1e-30));
      if (cost < best_cost) { best_cost = cost; best = {axis, b}; }
    }
  }
  return best;
}

// Node over order[first, first + count), then its children: binned SAH splits of the box
// centres, a median split along the longest axis where the SAH finds none, down to kLeafSize
// entries (kMaxLeaf where splitting costs more than testing them all).
template <typename T>
int32_t build_node(BvhArrays<T>& g, int32_t first, int32_t count, int depth) {
  const int32_t index = int32_t(g.nodes.size());
  g.nodes.push_back({});
  Bounds<T> box, centres;
  for (int32_t i = first; i < first + count; ++i) {
    const int32_t k = g.order[i];
    box.grow(g.prims[k].lo, g.prims[k].hi);
    T c[3];
    for (int a = 0; a < 3; ++a) c[a] = T(0.5) * (g.prims[k].lo[a] + g.prims[k].hi[a]);
    centres.grow(c, c);
  }
  Node<T> node;
  for (int a = 0; a < 3; ++a) { node.lo[a] = box.lo[a]; node.hi[a] = box.hi[a]; }
  node.right = -1; node.first = first; node.count = count;
  // Depth is bounded so the traversal stack (kStackSize) cannot overflow.
  if (count > kLeafSize && depth < kStackSize - 2) {
    T cost;
    const std::pair<int, int> split = sah_split(g, first, count, centres.lo, centres.hi,
                                                box.area(), cost);
    int axis = split.first;
    int32_t half = 0;
    auto begin = g.order.begin() + first;
    if (axis >= 0 && !(count <= kMaxLeaf && cost >= T(count))) {
      const T lo = centres.lo[axis], extent = centres.hi[axis] - centres.lo[axis];
      const auto mid = std::partition(begin, begin + count, [&](int32_t k) {
        const T c = T(0.5) * (g.prims[k].lo[axis] + g.prims[k].hi[axis]);
        return std::min(kBins - 1, int(T(kBins) * (c - lo) / extent)) < split.second;
      });
      half = int32_t(mid - begin);
    } else if (axis < 0 || count > kMaxLeaf) {  // coinciding centres: halve by index
      axis = 0;
      for (int a = 1; a < 3; ++a)
        if (centres.hi[a] - centres.lo[a] > centres.hi[axis] - centres.lo[axis]) axis = a;
      half = count / 2;
      std::nth_element(begin, begin + half, begin + count, [&](int32_t x, int32_t y) {
        return g.prims[x].lo[axis] + g.prims[x].hi[axis] < g.prims[y].lo[axis] + g.prims[y].hi[axis];
      });
    }
    if (half > 0 && half < count) {
      node.count = 0;
      node.first = axis;
      build_node(g, first, half, depth + 1);
      node.right = build_node(g, first + half, count - half, depth + 1);
    }
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
  g.count = n;
  g.prims.resize(size_t(n));
  parallel_for(n, int64_t(4096), [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i)
      g.prims[size_t(i)] = prepare_gaussian(i, means, quats, scales, opacity);
  });
  // Only Gaussians that can reach alpha 1/255 (and have finite boxes) enter the tree.
  for (int64_t i = 0; i < n; ++i)
    if (g.prims[size_t(i)].hi[0] >= g.prims[size_t(i)].lo[0] && level_k(opacity[i]) > T(0))
      g.order.push_back(int32_t(i));
  if (!g.order.empty()) {
    g.nodes.reserve(size_t(2 * g.order.size() / kLeafSize + 2));
    build_node(g, 0, int32_t(g.order.size()), 0);
  }
  std::vector<Prim<T>> leaf_order(g.order.size());
  for (size_t i = 0; i < g.order.size(); ++i) leaf_order[i] = g.prims[size_t(g.order[i])];
  g.prims.swap(leaf_order);
  return g;
}

}  // namespace dgs
