// Gaussian ray tracer on the CPU: BVH built by median splits of the box centres along the
// longest axis, traversal with an explicit stack, parallel over origins.
#include "raytrace.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <numeric>
#include <vector>

#include "checks.h"
#include "raytrace_math.h"

namespace dgs {
namespace {

constexpr int kLeafSize = 4;
constexpr int kStackSize = 64;

template <typename T> struct Node {
  T lo[3], hi[3];
  int32_t right;  // internal: index of the right child (the left one follows the node)
  int32_t first;  // leaf: first entry in the ordered index list
  int32_t count;  // leaf: number of entries; 0 for internal nodes
};

template <typename T> struct Prepared {
  std::vector<Vec3<T>> mean;
  std::vector<Mat3<T>> inv_cov;
  std::vector<T> lo, hi, opacity;  // boxes as (N,3) arrays
};

template <typename T> struct Bvh {
  std::vector<Node<T>> nodes;
  std::vector<int32_t> order;
};

template <typename T>
int32_t build_node(Bvh<T>& bvh, const Prepared<T>& g, int32_t first, int32_t count, int depth) {
  const int32_t index = int32_t(bvh.nodes.size());
  bvh.nodes.push_back({});
  Node<T> node;
  for (int a = 0; a < 3; ++a) { node.lo[a] = T(1e30); node.hi[a] = T(-1e30); }
  T clo[3] = {T(1e30), T(1e30), T(1e30)}, chi[3] = {T(-1e30), T(-1e30), T(-1e30)};
  for (int32_t i = first; i < first + count; ++i) {
    const int32_t k = bvh.order[i];
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
    auto begin = bvh.order.begin() + first;
    std::nth_element(begin, begin + half, begin + count, [&](int32_t x, int32_t y) {
      return g.lo[3 * x + axis] + g.hi[3 * x + axis] < g.lo[3 * y + axis] + g.hi[3 * y + axis];
    });
    node.count = 0;
    build_node(bvh, g, first, half, depth + 1);
    node.right = build_node(bvh, g, first + half, count - half, depth + 1);
  }
  bvh.nodes[index] = node;
  return index;
}

// Transmittance along one ray from o in direction d.
template <typename T>
T trace_ray(const Bvh<T>& bvh, const Prepared<T>& g, const Vec3<T>& o, const Vec3<T>& d,
            int64_t exclude) {
  const Vec3<T> inv_d = {T(1) / d.x, T(1) / d.y, T(1) / d.z};
  int32_t stack[kStackSize];
  int top = 0;
  stack[top++] = 0;
  T trans = T(1);
  while (top > 0) {
    const Node<T>& node = bvh.nodes[stack[--top]];
    if (!ray_hits_box(o, inv_d, node.lo, node.hi)) continue;
    if (node.count == 0) {
      stack[top++] = node.right;
      stack[top++] = int32_t(&node - bvh.nodes.data()) + 1;
      continue;
    }
    for (int32_t i = node.first; i < node.first + node.count; ++i) {
      const int32_t k = bvh.order[i];
      if (k == exclude || !ray_hits_box(o, inv_d, &g.lo[3 * k], &g.hi[3 * k])) continue;
      const T al = alpha_along_ray(o, d, g.mean[k], g.inv_cov[k], g.opacity[k]);
      trans *= T(1) - al;
      // Order does not matter for a product, so the walk may stop as soon as T is negligible.
      if (trans < transmittance_min<T>()) return trans;
    }
  }
  return trans;
}

template <typename T>
Prepared<T> prepare(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                    const at::Tensor& opacity) {
  const int64_t n = means.size(0);
  Prepared<T> g;
  g.mean.resize(n); g.inv_cov.resize(n); g.lo.resize(3 * n); g.hi.resize(3 * n);
  g.opacity.resize(n);
  const T* mp = means.data_ptr<T>();
  const T* qp = quats.data_ptr<T>();
  const T* sp = scales.data_ptr<T>();
  const T* op = opacity.data_ptr<T>();
  at::parallel_for(0, n, 4096, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      const Mat3<T> r = quat_to_rotmat(qp[4 * i], qp[4 * i + 1], qp[4 * i + 2], qp[4 * i + 3]);
      const Vec3<T> s = {sp[3 * i], sp[3 * i + 1], sp[3 * i + 2]};
      g.mean[i] = {mp[3 * i], mp[3 * i + 1], mp[3 * i + 2]};
      g.inv_cov[i] = inverse_covariance_3d(r, s);
      const Vec3<T> e = three_sigma_extent(r, s);
      const T ext[3] = {e.x, e.y, e.z}, c[3] = {g.mean[i].x, g.mean[i].y, g.mean[i].z};
      for (int a = 0; a < 3; ++a) {
        g.lo[3 * i + a] = c[a] - ext[a];
        g.hi[3 * i + a] = c[a] + ext[a];
      }
      g.opacity[i] = op[i];
    }
  });
  return g;
}

}  // namespace

at::Tensor trace_visibility(const at::Tensor& origins, const at::Tensor& normals,
                            const at::Tensor& means, const at::Tensor& quats,
                            const at::Tensor& scales, const at::Tensor& opacity,
                            const at::Tensor& exclude, int64_t n_dirs) {
  const int64_t m = origins.size(0), n = means.size(0);
  check_cpu_input(origins, "origins", {m, 3});
  check_cpu_input(normals, "normals", {m, 3});
  check_cpu_input(means, "means", {n, 3});
  check_cpu_input(quats, "quats", {n, 4});
  check_cpu_input(scales, "scales", {n, 3});
  check_cpu_input(opacity, "opacity", {n});
  check_cpu_input(exclude, "exclude", {m});
  check_same_dtype({origins, normals, means, quats, scales, opacity});
  TORCH_CHECK(exclude.scalar_type() == at::kLong, "exclude must be int64");
  TORCH_CHECK(n_dirs > 0, "n_dirs must be positive, got ", n_dirs);
  TORCH_CHECK(n < (int64_t(1) << 31), "too many Gaussians for the CPU tracer: ", n);
  at::Tensor vis = at::ones({m}, origins.options());
  if (n == 0 || m == 0) return vis;
  AT_DISPATCH_FLOATING_TYPES(origins.scalar_type(), "trace_visibility", [&] {
    using T = scalar_t;
    const Prepared<T> g = prepare<T>(means, quats, scales, opacity);
    Bvh<T> bvh;
    bvh.order.resize(n);
    std::iota(bvh.order.begin(), bvh.order.end(), 0);
    bvh.nodes.reserve(size_t(2 * n / kLeafSize + 2));
    build_node(bvh, g, 0, int32_t(n), 0);
    const T* op = origins.data_ptr<T>();
    const T* np = normals.data_ptr<T>();
    const int64_t* ex = exclude.data_ptr<int64_t>();
    T* out = vis.data_ptr<T>();
    at::parallel_for(0, m, 64, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) {
        const Vec3<T> o = {op[3 * i], op[3 * i + 1], op[3 * i + 2]};
        const Vec3<T> nn = {np[3 * i], np[3 * i + 1], np[3 * i + 2]};
        Vec3<T> t, b;
        normal_frame(nn, t, b);
        T num = T(0), den = T(0);
        for (int k = 0; k < n_dirs; ++k) {
          const Vec3<T> l = fibonacci_hemisphere<T>(k, int(n_dirs));
          const Vec3<T> d = {t.x * l.x + b.x * l.y + nn.x * l.z, t.y * l.x + b.y * l.y + nn.y * l.z,
                             t.z * l.x + b.z * l.y + nn.z * l.z};
          num += l.z * trace_ray(bvh, g, o, d, ex[i]);
          den += l.z;
        }
        out[i] = num / den;
      }
    });
  });
  return vis;
}

}  // namespace dgs
