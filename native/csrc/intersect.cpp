// Tile binning on the CPU: a counting sort by tile, then a sort by depth inside each tile
// (parallel over tiles). The CUDA twin sorts 64-bit tile|depth keys with a radix sort instead.
#include "intersect.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <vector>

#include "checks.h"

namespace dgs {
namespace {

template <typename T>
void sort_tiles(const T* depth, const int64_t* offsets, int32_t* ids, int64_t n_tiles) {
  at::parallel_for(0, n_tiles, 16, [&](int64_t begin, int64_t end) {
    for (int64_t t = begin; t < end; ++t) {
      std::sort(ids + offsets[t], ids + offsets[t + 1], [depth](int32_t a, int32_t b) {
        return depth[a] < depth[b] || (depth[a] == depth[b] && a < b);
      });
    }
  });
}

}  // namespace

std::tuple<at::Tensor, at::Tensor> intersect_tiles(const at::Tensor& rects,
                                                   const at::Tensor& depths, int64_t width,
                                                   int64_t height, int64_t tile_size) {
#ifdef DGS_WITH_CUDA
  if (rects.is_cuda()) return intersect_tiles_cuda(rects, depths, width, height, tile_size);
#endif
  const int64_t n = rects.size(0);
  check_cpu_input(rects, "rects", {n, 4});
  check_cpu_input(depths, "depths", {n});
  TORCH_CHECK(rects.scalar_type() == at::kInt, "rects must be int32");
  TORCH_CHECK(tile_size > 0, "tile_size must be positive");
  const int64_t tiles_x = (width + tile_size - 1) / tile_size;
  const int64_t tiles_y = (height + tile_size - 1) / tile_size;
  const int64_t n_tiles = tiles_x * tiles_y;
  const int32_t* rc = rects.data_ptr<int32_t>();
  at::Tensor offsets = at::zeros({n_tiles + 1}, rects.options().dtype(at::kLong));
  int64_t* off = offsets.data_ptr<int64_t>();
  // Count per tile (serial: O(M) integer work, a few ms even for millions of pairs).
  for (int64_t i = 0; i < n; ++i) {
    const int32_t* r = rc + 4 * i;
    if (r[0] > r[2] || r[1] > r[3]) continue;
    for (int64_t ty = r[1] / tile_size; ty <= r[3] / tile_size; ++ty)
      for (int64_t tx = r[0] / tile_size; tx <= r[2] / tile_size; ++tx)
        ++off[ty * tiles_x + tx + 1];
  }
  for (int64_t t = 0; t < n_tiles; ++t) off[t + 1] += off[t];
  const int64_t m = off[n_tiles];
  at::Tensor ids = at::empty({m}, rects.options().dtype(at::kInt));
  int32_t* idp = ids.data_ptr<int32_t>();
  std::vector<int64_t> cursor(off, off + n_tiles);
  for (int64_t i = 0; i < n; ++i) {
    const int32_t* r = rc + 4 * i;
    if (r[0] > r[2] || r[1] > r[3]) continue;
    for (int64_t ty = r[1] / tile_size; ty <= r[3] / tile_size; ++ty)
      for (int64_t tx = r[0] / tile_size; tx <= r[2] / tile_size; ++tx)
        idp[cursor[ty * tiles_x + tx]++] = int32_t(i);
  }
  AT_DISPATCH_FLOATING_TYPES(depths.scalar_type(), "intersect_tiles", [&] {
    sort_tiles<scalar_t>(depths.data_ptr<scalar_t>(), off, idp, n_tiles);
  });
  return {offsets, ids};
}

}  // namespace dgs
