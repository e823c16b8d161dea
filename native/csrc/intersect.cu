// Tile binning on the GPU: count the tiles of every Gaussian's box, prefix-sum the counts (CUB),
// emit one 64-bit key per (Gaussian, tile) pair = tile id << 32 | depth bits, radix-sort the pairs
// (CUB, only the bits in use), and find each tile's range by binary search in the sorted keys.
#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>
#include <cuda_runtime.h>

#include "intersect_cuda.h"

namespace dgs {
namespace cuda {
namespace {

constexpr int kThreads = 256;
constexpr size_t kAlign = 256;

inline size_t align_up(size_t b) { return (b + kAlign - 1) / kAlign * kAlign; }

inline unsigned blocks_for(int64_t n) { return unsigned((n + kThreads - 1) / kThreads); }

struct Grid {
  int64_t tiles_x, tiles_y;
  int64_t count() const { return tiles_x * tiles_y; }
};

inline Grid make_grid(int width, int height, int tile_size) {
  return {(int64_t(width) + tile_size - 1) / tile_size,
          (int64_t(height) + tile_size - 1) / tile_size};
}

// Number of sort-key bits above 32 that tile ids use.
inline int tile_bits(int64_t n_tiles) {
  int b = 0;
  while (b < 32 && (int64_t(1) << b) < n_tiles) ++b;
  return b;
}

// Tile range [tx0, tx1] x [ty0, ty1] of a box, clipped to the grid; false when empty.
__device__ __forceinline__ bool tile_range(const int32_t* r, int tile_size, int64_t tiles_x,
                                           int64_t tiles_y, int64_t& tx0, int64_t& tx1,
                                           int64_t& ty0, int64_t& ty1) {
  if (r[0] > r[2] || r[1] > r[3] || r[2] < 0 || r[3] < 0) return false;
  tx0 = r[0] < 0 ? 0 : r[0] / tile_size;
  ty0 = r[1] < 0 ? 0 : r[1] / tile_size;
  tx1 = r[2] / tile_size;
  ty1 = r[3] / tile_size;
  if (tx1 >= tiles_x) tx1 = tiles_x - 1;
  if (ty1 >= tiles_y) ty1 = tiles_y - 1;
  return tx0 <= tx1 && ty0 <= ty1;
}

__global__ void count_tiles_kernel(const int32_t* __restrict__ rects, int64_t n, int tile_size,
                                   int64_t tiles_x, int64_t tiles_y,
                                   int64_t* __restrict__ counts) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  int64_t tx0, tx1, ty0, ty1;
  counts[i] = tile_range(rects + 4 * i, tile_size, tiles_x, tiles_y, tx0, tx1, ty0, ty1)
                  ? (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
                  : 0;
}

// Float bit pattern as an unsigned integer with the same order (negative values flipped).
__device__ __forceinline__ uint32_t ordered_bits(float d) {
  const uint32_t u = __float_as_uint(d);
  return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}

template <typename T>
__global__ void emit_pairs_kernel(const int32_t* __restrict__ rects, const T* __restrict__ depths,
                                  const int64_t* __restrict__ cum_counts, int64_t n,
                                  int tile_size, int64_t tiles_x, int64_t tiles_y,
                                  uint64_t* __restrict__ keys, int32_t* __restrict__ values) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  int64_t tx0, tx1, ty0, ty1;
  if (!tile_range(rects + 4 * i, tile_size, tiles_x, tiles_y, tx0, tx1, ty0, ty1)) return;
  int64_t k = cum_counts[i] - (tx1 - tx0 + 1) * (ty1 - ty0 + 1);
  const uint64_t zbits = ordered_bits(float(depths[i]));
  for (int64_t ty = ty0; ty <= ty1; ++ty)
    for (int64_t tx = tx0; tx <= tx1; ++tx) {
      keys[k] = (uint64_t(ty * tiles_x + tx) << 32) | zbits;
      values[k] = int32_t(i);
      ++k;
    }
}

// offsets[t] = first position whose tile is >= t (t = 0 .. n_tiles; the last is m).
__global__ void tile_offsets_kernel(const uint64_t* __restrict__ keys, int64_t m, int64_t n_tiles,
                                    int64_t* __restrict__ offsets) {
  const int64_t t = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t > n_tiles) return;
  const uint64_t target = uint64_t(t) << 32;
  int64_t lo = 0, hi = m;
  while (lo < hi) {
    const int64_t mid = lo + (hi - lo) / 2;
    if (keys[mid] < target) lo = mid + 1;
    else hi = mid;
  }
  offsets[t] = lo;
}

// Scratch layout of the sort phase, in order, each part 256-byte aligned.
struct SortScratch {
  size_t keys_in, keys_out, values_in, cub;
  size_t total() const { return keys_in + keys_out + values_in + cub; }
};

inline SortScratch sort_scratch(int64_t m, int end_bit) {
  SortScratch s;
  s.keys_in = align_up(size_t(m) * sizeof(uint64_t));
  s.keys_out = s.keys_in;
  s.values_in = align_up(size_t(m) * sizeof(int32_t));
  size_t cub_bytes = 0;
  cub::DeviceRadixSort::SortPairs(nullptr, cub_bytes, static_cast<const uint64_t*>(nullptr),
                                  static_cast<uint64_t*>(nullptr),
                                  static_cast<const int32_t*>(nullptr),
                                  static_cast<int32_t*>(nullptr), m, 0, end_bit);
  s.cub = align_up(cub_bytes);
  return s;
}

inline size_t scan_cub_bytes(int64_t n) {
  size_t bytes = 0;
  cub::DeviceScan::InclusiveSum(nullptr, bytes, static_cast<const int64_t*>(nullptr),
                                static_cast<int64_t*>(nullptr), n);
  return align_up(bytes);
}

}  // namespace

size_t intersect_count_temp_bytes(int64_t n) {
  if (n <= 0) return 0;
  return align_up(size_t(n) * sizeof(int64_t)) + scan_cub_bytes(n);
}

cudaError_t launch_intersect_count(const int32_t* rects, int64_t n, int width, int height,
                                   int tile_size, int64_t* cum_counts, void* temp,
                                   size_t temp_bytes, cudaStream_t stream) {
  if (n < 0 || width < 0 || height < 0 || tile_size <= 0) return cudaErrorInvalidValue;
  if (n == 0) return cudaSuccess;
  if (temp == nullptr || temp_bytes < intersect_count_temp_bytes(n)) return cudaErrorInvalidValue;
  const Grid g = make_grid(width, height, tile_size);
  auto* counts = static_cast<int64_t*>(temp);
  char* cub_temp = static_cast<char*>(temp) + align_up(size_t(n) * sizeof(int64_t));
  size_t cub_bytes = scan_cub_bytes(n);
  count_tiles_kernel<<<blocks_for(n), kThreads, 0, stream>>>(rects, n, tile_size, g.tiles_x,
                                                             g.tiles_y, counts);
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  return cub::DeviceScan::InclusiveSum(cub_temp, cub_bytes, counts, cum_counts, n, stream);
}

size_t intersect_sort_temp_bytes(int64_t m, int width, int height, int tile_size) {
  if (m <= 0 || tile_size <= 0) return 0;
  const Grid g = make_grid(width, height, tile_size);
  return sort_scratch(m, 32 + tile_bits(g.count())).total();
}

template <typename T>
cudaError_t launch_intersect_sort(const int32_t* rects, const T* depths,
                                  const int64_t* cum_counts, int64_t n, int64_t m, int width,
                                  int height, int tile_size, int64_t* tile_offsets,
                                  int32_t* flat_ids, void* temp, size_t temp_bytes,
                                  cudaStream_t stream) {
  if (n < 0 || m < 0 || width < 0 || height < 0 || tile_size <= 0) return cudaErrorInvalidValue;
  const Grid g = make_grid(width, height, tile_size);
  const int64_t n_tiles = g.count();
  if (m == 0 || n == 0)
    return cudaMemsetAsync(tile_offsets, 0, size_t(n_tiles + 1) * sizeof(int64_t), stream);
  const int end_bit = 32 + tile_bits(n_tiles);
  SortScratch s = sort_scratch(m, end_bit);
  if (temp == nullptr || temp_bytes < s.total()) return cudaErrorInvalidValue;
  char* base = static_cast<char*>(temp);
  auto* keys_in = reinterpret_cast<uint64_t*>(base);
  auto* keys_out = reinterpret_cast<uint64_t*>(base + s.keys_in);
  auto* values_in = reinterpret_cast<int32_t*>(base + s.keys_in + s.keys_out);
  char* cub_temp = base + s.keys_in + s.keys_out + s.values_in;
  emit_pairs_kernel<T><<<blocks_for(n), kThreads, 0, stream>>>(
      rects, depths, cum_counts, n, tile_size, g.tiles_x, g.tiles_y, keys_in, values_in);
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  size_t cub_bytes = s.cub;
  err = cub::DeviceRadixSort::SortPairs(cub_temp, cub_bytes, keys_in, keys_out, values_in,
                                        flat_ids, m, 0, end_bit, stream);
  if (err != cudaSuccess) return err;
  tile_offsets_kernel<<<blocks_for(n_tiles + 1), kThreads, 0, stream>>>(keys_out, m, n_tiles,
                                                                        tile_offsets);
  return cudaGetLastError();
}

template cudaError_t launch_intersect_sort<float>(const int32_t*, const float*, const int64_t*,
                                                  int64_t, int64_t, int, int, int, int64_t*,
                                                  int32_t*, void*, size_t, cudaStream_t);
template cudaError_t launch_intersect_sort<double>(const int32_t*, const double*, const int64_t*,
                                                   int64_t, int64_t, int, int, int, int64_t*,
                                                   int32_t*, void*, size_t, cudaStream_t);

}  // namespace cuda
}  // namespace dgs
