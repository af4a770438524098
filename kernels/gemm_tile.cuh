// Device-side machinery of the convolution kernels (kernels/conv2d.cu and
// kernels/conv_transpose2d.cu): a tiled single-precision GEMM
//   C (M x N) = A (M x K) * B (K x N)
// whose operands are never materialised. A block computes one kBlockM x kBlockN tile of C; a
// "loader" per operand gathers kBlockK-deep slices of A and B straight from the tensors (weights,
// NCHW images, im2col taps with zero padding) into registers, then into shared memory, where each
// thread multiplies a kThreadM x kThreadN register tile. The loads of slice s + 1 are in flight
// while slice s is multiplied (register prefetch, two shared-memory stages, one barrier per slice).
// Epilogues write a thread's register tile to NCHW images or to row-major matrices, with float4
// stores where four outputs are contiguous and aligned.
//
// Also here: exact division by a runtime constant (FastDivmod), the flattened (batch, pixel) axis
// of NCHW tensors, and the fixed-order reductions that make the weight gradients deterministic:
// the K axis of a weight-gradient GEMM (every pixel of the batch) is split into chunks whose
// partial tiles go to a workspace, and a second kernel sums the chunks in chunk order.
//
// Indices are int: launchers check that every tensor has fewer than 2^31 elements.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>

#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE::gemm {

// ---- tile shapes ----

// A block of kThreads = (kBlockM / kThreadM) * (kBlockN / kThreadN) threads computes a
// kBlockM x kBlockN tile of C, kBlockK steps of K per shared-memory slice. Thread t owns rows
// (t / kThreadsN) * kThreadM + [0, kThreadM) and columns (t % kThreadsN) * kThreadN + [0, 4).
template <int BlockM, int BlockN, int ThreadM>
struct TileShape {
  static constexpr int kBlockM = BlockM;
  static constexpr int kBlockN = BlockN;
  static constexpr int kBlockK = 16;
  static constexpr int kThreadM = ThreadM;
  static constexpr int kThreadN = 4;  // one float4 of B per k step; a float4 store per row
  static constexpr int kThreadsN = kBlockN / kThreadN;
  static constexpr int kThreads = (kBlockM / kThreadM) * kThreadsN;
  static_assert(kBlockM % kThreadM == 0 && kBlockN % kThreadN == 0, "threads must tile the block");
  static_assert(kThreadM % 4 == 0, "a thread reads its rows of A as float4s");
};

// 64 x 64 tile, 8 x 4 outputs per thread, 128 threads: 32 multiply-adds per three 16-byte
// shared-memory reads, 17 KiB of shared memory, 80-110 registers (ptxas, sm_80 and sm_90), so 4-5
// blocks share an SM. For the U-Net's layers, whose channel counts are multiples of 64.
using WideTile = TileShape<64, 64, 8>;
// 16 x 128 tile, 4 x 4 outputs per thread, 128 threads, 19 KiB of shared memory: for M <= 16
// (the 1x1 head's 12 classes, the occupancy convolution's 16 channels), where a 64-row tile
// would compute 4x as many zeros.
using NarrowTile = TileShape<16, 128, 4>;

// The shape a launcher uses for a GEMM with M rows.
inline constexpr int kNarrowTileMaxRows = NarrowTile::kBlockM;

// Shared-memory rows are padded by 4 floats (one bank group): loaders that write a slice
// transposed (consecutive threads on consecutive k, as the coalesced global loads want) then hit
// at most 2 threads per bank instead of 16, and rows stay 16-byte aligned for float4 reads.
inline constexpr int kRowPadding = 4;

// The two shared-memory stages of a block: slices of A and B stored k-major (a[k][m], b[k][n]),
// so that a thread's rows and columns for one k are contiguous float4s.
template <class Tile>
struct alignas(16) SharedSlices {
  float a[2][Tile::kBlockK][Tile::kBlockM + kRowPadding];
  float b[2][Tile::kBlockK][Tile::kBlockN + kRowPadding];
};
template <class Tile>
using SliceA = float[Tile::kBlockK][Tile::kBlockM + kRowPadding];
template <class Tile>
using SliceB = float[Tile::kBlockK][Tile::kBlockN + kRowPadding];

// How the threads of a block cover a slice of `Lines` lines of `LineLength` contiguous elements
// (contiguous in the source tensor): each thread loads kPerThread consecutive elements of one
// line, kThreadsPerLine threads per line.
template <int Lines, int LineLength, int Threads>
struct RunLayout {
  static constexpr int kPerThread = Lines * LineLength / Threads;
  static constexpr int kThreadsPerLine = LineLength / kPerThread;
  static_assert(kPerThread * Threads == Lines * LineLength && kPerThread >= 1,
                "the slice must split evenly over the threads");
  static_assert(kPerThread * kThreadsPerLine == LineLength, "runs must tile a line");
  static __device__ __forceinline__ int line(int thread) { return thread / kThreadsPerLine; }
  static __device__ __forceinline__ int offset(int thread) {
    return thread % kThreadsPerLine * kPerThread;
  }
};

// ---- integer helpers ----

// Exact n / d and n % d for 0 <= n < 2^31 and a divisor 1 <= d < 2^31 fixed at launch, with one
// 64-bit multiply and a shift instead of a division (round-up method, as CUTLASS's FastDivmod):
// with l = ceil(log2 d), s = 31 + l and m = ceil(2^s / d) (which fits 32 bits),
// n m / 2^s = n / d + n (m d - 2^s) / (d 2^s), and the second term is below 2^31 d / (d 2^s)
// = 2^-l <= 1 / d, too small to reach the next integer.
struct FastDivmod {
  int divisor = 1;
  std::uint32_t multiplier = 1u << 31;
  int shift = 31;

  FastDivmod() = default;
  __host__ __device__ explicit FastDivmod(int d) : divisor(d) {
    int log2_ceil = 0;
    while ((std::int64_t{1} << log2_ceil) < d) ++log2_ceil;
    shift = 31 + log2_ceil;
    multiplier = static_cast<std::uint32_t>(((std::uint64_t{1} << shift) + d - 1) /
                                            static_cast<std::uint64_t>(d));
  }
  __host__ __device__ __forceinline__ int div(int n) const {
    return static_cast<int>((static_cast<std::uint64_t>(n) * multiplier) >> shift);
  }
  __host__ __device__ __forceinline__ void divmod(int n, int& quotient, int& remainder) const {
    quotient = div(n);
    remainder = n - quotient * divisor;
  }
};

// The flattened (batch, pixel) axis of an NCHW tensor with `pixels` = H W per channel:
// index p = b pixels + pixel, element (b, c, pixel) at b image_stride + c pixels + pixel.
struct PixelAxis {
  int total = 0;         // batch * pixels
  FastDivmod pixels;     // H * W
  int image_stride = 0;  // channels * pixels

  __host__ __device__ __forceinline__ int offset(int channel, int p) const {
    int b, pixel;
    pixels.divmod(p, b, pixel);
    return b * image_stride + channel * pixels.divisor + pixel;
  }
};

inline PixelAxis make_pixel_axis(std::int64_t batch, std::int64_t channels, std::int64_t pixels) {
  PixelAxis axis;
  axis.total = static_cast<int>(batch * pixels);
  axis.pixels = FastDivmod(static_cast<int>(pixels));
  axis.image_stride = static_cast<int>(channels * pixels);
  return axis;
}

// ---- loads ----

template <int N>
__device__ __forceinline__ bool is_vector_aligned(const float* p) {
  constexpr std::uintptr_t kBytes = N % 4 == 0 ? 16 : (N % 2 == 0 ? 8 : 4);
  return reinterpret_cast<std::uintptr_t>(p) % kBytes == 0;
}

// out[i] = src[i] for i < valid and 0 for i >= valid (src[i] is not read there); float4 (or
// float2) loads when all N are valid and src is aligned for them.
template <int N>
__device__ __forceinline__ void fetch_run(const float* src, int valid, float (&out)[N]) {
  if (valid >= N && is_vector_aligned<N>(src)) {
    if constexpr (N % 4 == 0) {
#pragma unroll
      for (int v = 0; v < N / 4; ++v) {
        const float4 q = reinterpret_cast<const float4*>(src)[v];
        out[4 * v] = q.x;
        out[4 * v + 1] = q.y;
        out[4 * v + 2] = q.z;
        out[4 * v + 3] = q.w;
      }
      return;
    } else if constexpr (N % 2 == 0) {
#pragma unroll
      for (int v = 0; v < N / 2; ++v) {
        const float2 q = reinterpret_cast<const float2*>(src)[v];
        out[2 * v] = q.x;
        out[2 * v + 1] = q.y;
      }
      return;
    }
  }
#pragma unroll
  for (int i = 0; i < N; ++i) out[i] = i < valid ? src[i] : 0.0f;
}

// out[i] = tensor[channel, flattened pixel p + i] for p + i < axis.total, else 0. One contiguous
// (vectorised where aligned) run when the N pixels lie in one image; pixel by pixel across an
// image boundary.
template <int N>
__device__ __forceinline__ void fetch_pixel_run(const float* tensor, int channel, int p,
                                                const PixelAxis& axis, float (&out)[N]) {
  if (p >= axis.total) {
#pragma unroll
    for (int i = 0; i < N; ++i) out[i] = 0.0f;
    return;
  }
  int b, pixel;
  axis.pixels.divmod(p, b, pixel);
  if (pixel + N <= axis.pixels.divisor) {
    fetch_run<N>(tensor + b * axis.image_stride + channel * axis.pixels.divisor + pixel, N, out);
    return;
  }
#pragma unroll
  for (int i = 0; i < N; ++i) {
    out[i] = p + i < axis.total ? tensor[axis.offset(channel, p + i)] : 0.0f;
  }
}

// How the threads of a block cover a kBlockK x kBlockN slice of B that is gathered element by
// element (im2col taps, pixel shuffles):
//   ColumnLayoutB: each thread loads one column n (consecutive threads, consecutive pixels) at
//   rows first_row + kRowStep j;
//   RowLayoutB: each thread loads one row k (consecutive threads, consecutive pixels of K) at
//   columns first_column + kColumnStep j.
template <class Tile>
struct ColumnLayoutB {
  static constexpr int kRowStep = Tile::kThreads / Tile::kBlockN;
  static constexpr int kPerThread = Tile::kBlockK / kRowStep;
  static_assert(kRowStep * Tile::kBlockN == Tile::kThreads &&
                    kPerThread * kRowStep == Tile::kBlockK,
                "the slice must split evenly over the threads");
  static __device__ __forceinline__ int column(int thread) { return thread % Tile::kBlockN; }
  static __device__ __forceinline__ int first_row(int thread) { return thread / Tile::kBlockN; }
};
template <class Tile>
struct RowLayoutB {
  static constexpr int kColumnStep = Tile::kThreads / Tile::kBlockK;
  static constexpr int kPerThread = Tile::kBlockN / kColumnStep;
  static_assert(kColumnStep * Tile::kBlockK == Tile::kThreads &&
                    kPerThread * kColumnStep == Tile::kBlockN,
                "the slice must split evenly over the threads");
  static __device__ __forceinline__ int row(int thread) { return thread % Tile::kBlockK; }
  static __device__ __forceinline__ int first_column(int thread) { return thread / Tile::kBlockK; }
};

// dst[i] = values[i] in shared memory; float4 stores when N is a multiple of 4 (dst is then
// 16-byte aligned: runs start at multiples of N in rows of a multiple of 4 floats).
template <int N>
__device__ __forceinline__ void store_run_to_shared(const float (&values)[N], float* dst) {
  if constexpr (N % 4 == 0) {
#pragma unroll
    for (int v = 0; v < N / 4; ++v) {
      reinterpret_cast<float4*>(dst)[v] =
          make_float4(values[4 * v], values[4 * v + 1], values[4 * v + 2], values[4 * v + 3]);
    }
  } else {
#pragma unroll
    for (int i = 0; i < N; ++i) dst[i] = values[i];
  }
}

// ---- operand loaders shared by the convolutions ----
// A loader's fetch(k0) reads its thread's share of the slice [k0, k0 + kBlockK) into registers
// (zero outside the operand) and store(slice) writes them into a shared-memory stage.

// A (M x K) stored row-major with leading dimension ld: A[m][k] = a[m * ld + k] (a weight tensor
// (O, I, k, k) seen as O x I k k, or (I, 4 O) for the transposed convolution's input gradient).
template <class Tile>
struct RowMajorLoaderA {
  using Layout = RunLayout<Tile::kBlockM, Tile::kBlockK, Tile::kThreads>;
  const float* a;
  int rows, depth, ld;  // M, K, leading dimension
  int line, row;        // this thread's row in the tile and in A
  float values[Layout::kPerThread];

  __device__ RowMajorLoaderA(const float* a_, int rows_, int depth_, int ld_, int m0)
      : a(a_),
        rows(rows_),
        depth(depth_),
        ld(ld_),
        line(Layout::line(static_cast<int>(threadIdx.x))),
        row(m0 + line) {}
  __device__ __forceinline__ void fetch(int k0) {
    const int k = k0 + Layout::offset(static_cast<int>(threadIdx.x));
    const int valid = row < rows ? depth - k : 0;
    fetch_run<Layout::kPerThread>(a + static_cast<std::ptrdiff_t>(row) * ld + k, valid, values);
  }
  __device__ __forceinline__ void store(SliceA<Tile>& slice) const {
    const int offset = Layout::offset(static_cast<int>(threadIdx.x));
#pragma unroll
    for (int i = 0; i < Layout::kPerThread; ++i) slice[offset + i][line] = values[i];
  }
};

// A (M x K) stored column-major (K x M row-major) with leading dimension ld:
// A[m][k] = a[k * ld + m] (the transposed convolution's weight (I, 4 O) as a 4 O x I matrix).
template <class Tile>
struct ColumnMajorLoaderA {
  using Layout = RunLayout<Tile::kBlockK, Tile::kBlockM, Tile::kThreads>;
  const float* a;
  int rows, depth, ld;
  int m0;
  float values[Layout::kPerThread];

  __device__ ColumnMajorLoaderA(const float* a_, int rows_, int depth_, int ld_, int m0_)
      : a(a_), rows(rows_), depth(depth_), ld(ld_), m0(m0_) {}
  __device__ __forceinline__ void fetch(int k0) {
    const int k = k0 + Layout::line(static_cast<int>(threadIdx.x));
    const int m = m0 + Layout::offset(static_cast<int>(threadIdx.x));
    const int valid = k < depth ? rows - m : 0;
    fetch_run<Layout::kPerThread>(a + static_cast<std::ptrdiff_t>(k) * ld + m, valid, values);
  }
  __device__ __forceinline__ void store(SliceA<Tile>& slice) const {
    store_run_to_shared(values, &slice[Layout::line(static_cast<int>(threadIdx.x))]
                                      [Layout::offset(static_cast<int>(threadIdx.x))]);
  }
};

// A (M x K) = channels x flattened pixels of an NCHW tensor: A[c][p] = tensor[b, c, pixel]
// (dy or x in the weight gradients, whose K axis runs over every pixel of the batch).
template <class Tile>
struct PixelRowsLoaderA {
  using Layout = RunLayout<Tile::kBlockM, Tile::kBlockK, Tile::kThreads>;
  const float* tensor;
  PixelAxis axis;
  int channels;
  int channel;  // this thread's row
  float values[Layout::kPerThread];

  __device__ PixelRowsLoaderA(const float* tensor_, const PixelAxis& axis_, int channels_, int m0)
      : tensor(tensor_),
        axis(axis_),
        channels(channels_),
        channel(m0 + Layout::line(static_cast<int>(threadIdx.x))) {}
  __device__ __forceinline__ void fetch(int k0) {
    const int p = k0 + Layout::offset(static_cast<int>(threadIdx.x));
    fetch_pixel_run<Layout::kPerThread>(tensor, channel, channel < channels ? p : axis.total, axis,
                                        values);
  }
  __device__ __forceinline__ void store(SliceA<Tile>& slice) const {
    const int m = Layout::line(static_cast<int>(threadIdx.x));
    const int offset = Layout::offset(static_cast<int>(threadIdx.x));
#pragma unroll
    for (int i = 0; i < Layout::kPerThread; ++i) slice[offset + i][m] = values[i];
  }
};

// B (K x N) = channels x flattened pixels of an NCHW tensor: B[c][p] = tensor[b, c, pixel]
// (the input of a 1x1 convolution and of the transposed convolution).
template <class Tile>
struct PixelColumnsLoaderB {
  using Layout = RunLayout<Tile::kBlockK, Tile::kBlockN, Tile::kThreads>;
  const float* tensor;
  PixelAxis axis;
  int channels;
  int p;  // this thread's first pixel
  float values[Layout::kPerThread];

  __device__ PixelColumnsLoaderB(const float* tensor_, const PixelAxis& axis_, int channels_,
                                 int n0)
      : tensor(tensor_),
        axis(axis_),
        channels(channels_),
        p(n0 + Layout::offset(static_cast<int>(threadIdx.x))) {}
  __device__ __forceinline__ void fetch(int k0) {
    const int channel = k0 + Layout::line(static_cast<int>(threadIdx.x));
    fetch_pixel_run<Layout::kPerThread>(tensor, channel, channel < channels ? p : axis.total, axis,
                                        values);
  }
  __device__ __forceinline__ void store(SliceB<Tile>& slice) const {
    store_run_to_shared(values, &slice[Layout::line(static_cast<int>(threadIdx.x))]
                                      [Layout::offset(static_cast<int>(threadIdx.x))]);
  }
};

// ---- the main loop ----

// This thread's kThreadM x kThreadN tile of C.
template <class Tile>
using Accumulators = float[Tile::kThreadM][Tile::kThreadN];

// acc += A[rows, k_begin:k_end] * B[k_begin:k_end, columns] over this thread's rows and columns,
// k in increasing order with one fused multiply-add per product (so each output's rounding
// depends on the shapes only). k_end - k_begin is a multiple of kBlockK or reaches past K, where
// the loaders give zeros. Every thread of the block must call it (it synchronises the block).
template <class Tile, class LoaderA, class LoaderB>
__device__ __forceinline__ void accumulate_products(LoaderA& loader_a, LoaderB& loader_b,
                                                    int k_begin, int k_end,
                                                    Accumulators<Tile>& acc) {
  __shared__ SharedSlices<Tile> slices;
  if (k_begin >= k_end) return;
  const int thread = static_cast<int>(threadIdx.x);
  const int row0 = thread / Tile::kThreadsN * Tile::kThreadM;
  const int column0 = thread % Tile::kThreadsN * Tile::kThreadN;

  loader_a.fetch(k_begin);
  loader_b.fetch(k_begin);
  loader_a.store(slices.a[0]);
  loader_b.store(slices.b[0]);
  __syncthreads();
  int stage = 0;
  for (int k0 = k_begin; k0 < k_end; k0 += Tile::kBlockK) {
    const bool has_next = k0 + Tile::kBlockK < k_end;
    if (has_next) {
      loader_a.fetch(k0 + Tile::kBlockK);
      loader_b.fetch(k0 + Tile::kBlockK);
    }
#pragma unroll
    for (int kk = 0; kk < Tile::kBlockK; ++kk) {
      float a[Tile::kThreadM];
      float b[Tile::kThreadN];
#pragma unroll
      for (int v = 0; v < Tile::kThreadM / 4; ++v) {
        const float4 q = *reinterpret_cast<const float4*>(&slices.a[stage][kk][row0 + 4 * v]);
        a[4 * v] = q.x;
        a[4 * v + 1] = q.y;
        a[4 * v + 2] = q.z;
        a[4 * v + 3] = q.w;
      }
      const float4 q = *reinterpret_cast<const float4*>(&slices.b[stage][kk][column0]);
      b[0] = q.x;
      b[1] = q.y;
      b[2] = q.z;
      b[3] = q.w;
#pragma unroll
      for (int i = 0; i < Tile::kThreadM; ++i) {
#pragma unroll
        for (int j = 0; j < Tile::kThreadN; ++j) acc[i][j] = __fmaf_rn(a[i], b[j], acc[i][j]);
      }
    }
    // The other stage was last read before the previous barrier, so it can be overwritten now.
    if (has_next) {
      loader_a.store(slices.a[stage ^ 1]);
      loader_b.store(slices.b[stage ^ 1]);
    }
    __syncthreads();
    stage ^= 1;
  }
}

// The first row and column of C that this thread owns, for a block at (m0, n0).
template <class Tile>
__device__ __forceinline__ int thread_row0(int m0) {
  return m0 + static_cast<int>(threadIdx.x) / Tile::kThreadsN * Tile::kThreadM;
}
template <class Tile>
__device__ __forceinline__ int thread_column0(int n0) {
  return n0 + static_cast<int>(threadIdx.x) % Tile::kThreadsN * Tile::kThreadN;
}

// ---- epilogues ----

// Stores v0..v3 to out[0..3] as one float4 and returns true when out is 16-byte aligned; stores
// nothing and returns false otherwise. On the GPU the store is __stwb (st.global.wb.v4, the
// default write-back policy): nvcc 13 splits a plain float4 assignment into four scalar stores
// when the address comes from FastDivmod arithmetic, which __stwb keeps it from doing.
__device__ __forceinline__ bool store_float4_if_aligned(float* out, float v0, float v1, float v2,
                                                        float v3) {
  if (!is_vector_aligned<4>(out)) return false;
#if defined(__CUDA_ARCH__)
  __stwb(reinterpret_cast<float4*>(out), make_float4(v0, v1, v2, v3));
#else
  *reinterpret_cast<float4*>(out) = make_float4(v0, v1, v2, v3);
#endif
  return true;
}

// C (channels x flattened pixels) -> out (B, channels, H, W): out[b, m, pixel] = C[m][p] + bias[m]
// (bias may be nullptr) for this thread's rows m < rows and columns p < axis.total. A row's 4
// pixels go out as one float4 when they lie in one image at an aligned address, else one by one.
template <class Tile>
__device__ __forceinline__ void store_to_images(const Accumulators<Tile>& acc, int m0, int n0,
                                                int rows, const PixelAxis& axis, const float* bias,
                                                float* out) {
  const int row0 = thread_row0<Tile>(m0);
  const int p = thread_column0<Tile>(n0);
  if (p >= axis.total) return;
  int b, pixel;
  axis.pixels.divmod(p, b, pixel);
  const bool one_image = pixel + 4 <= axis.pixels.divisor;
#pragma unroll
  for (int i = 0; i < Tile::kThreadM; ++i) {
    const int m = row0 + i;
    if (m >= rows) break;
    float v[Tile::kThreadN];
#pragma unroll
    for (int j = 0; j < Tile::kThreadN; ++j)
      v[j] = bias != nullptr ? acc[i][j] + bias[m] : acc[i][j];
    if (one_image &&
        store_float4_if_aligned(out + b * axis.image_stride + m * axis.pixels.divisor + pixel, v[0],
                                v[1], v[2], v[3])) {
      continue;
    }
#pragma unroll
    for (int j = 0; j < Tile::kThreadN; ++j) {
      if (p + j < axis.total) out[axis.offset(m, p + j)] = v[j];
    }
  }
}

// C -> out (rows x columns, row-major with leading dimension ld), this thread's part of it.
template <class Tile>
__device__ __forceinline__ void store_row_major(const Accumulators<Tile>& acc, int m0, int n0,
                                                int rows, int columns, std::int64_t ld,
                                                float* out) {
  const int row0 = thread_row0<Tile>(m0);
  const int n = thread_column0<Tile>(n0);
#pragma unroll
  for (int i = 0; i < Tile::kThreadM; ++i) {
    const int m = row0 + i;
    if (m >= rows) break;
    float* row = out + m * ld + n;
    if (n + 4 <= columns &&
        store_float4_if_aligned(row, acc[i][0], acc[i][1], acc[i][2], acc[i][3])) {
      continue;
    }
#pragma unroll
    for (int j = 0; j < 4; ++j) {
      if (n + j < columns) row[j] = acc[i][j];
    }
  }
}

// ---- deterministic split-K for the weight gradients ----

// A weight gradient sums over K = every pixel of the batch (10^5 and more), while its M x N
// output has few tiles, so K is split into `splits` chunks of `chunk` pixels (a multiple of
// kBlockK, the last chunk shorter); chunk z's partial M x N tile goes to workspace slice z and
// the slices are summed in order z = 0, 1, ... The plan depends on the shapes only, never on the
// GPU, so every run and every device gives the same bits.
struct SplitPlan {
  int splits = 1;
  int chunk = 0;
};

// Enough blocks to fill any current GPU several times over (132 SMs on an H100). Since
// splits <= ceil(kSplitTargetBlocks / tiles), the workspace holds about kSplitTargetBlocks + tiles
// tiles of partials: at most ~16 MiB beyond one copy of the gradient.
inline constexpr std::int64_t kSplitTargetBlocks = 1024;
// A chunk is at least this many pixels (16 slices), so a block's loop outweighs its epilogue.
inline constexpr std::int64_t kSplitMinChunk = 256;
// Bounds the second pass: each gradient element sums at most this many partials.
inline constexpr std::int64_t kSplitMaxSplits = 256;

inline SplitPlan plan_splits(std::int64_t depth, std::int64_t tiles, int block_k) {
  SplitPlan plan;
  if (depth <= 0) return plan;
  const std::int64_t wanted = ceil_div(kSplitTargetBlocks, std::max<std::int64_t>(tiles, 1));
  const std::int64_t most = std::min(kSplitMaxSplits, ceil_div(depth, kSplitMinChunk));
  const std::int64_t splits = std::clamp<std::int64_t>(wanted, 1, std::max<std::int64_t>(most, 1));
  const std::int64_t chunk = ceil_div(ceil_div(depth, splits), std::int64_t{block_k}) * block_k;
  plan.chunk = static_cast<int>(chunk);
  plan.splits = static_cast<int>(ceil_div(depth, chunk));
  return plan;
}

// The threads of the reduction kernels below.
inline constexpr int kReduceThreads = 256;

// The grid of a grid-stride loop over `count` elements in blocks of kReduceThreads: one element
// per thread up to 4096 blocks, which fill any current GPU.
inline dim3 reduce_grid(std::int64_t count) {
  constexpr std::int64_t kMaxBlocks = 4096;
  return dim3(static_cast<unsigned>(
      std::clamp<std::int64_t>(ceil_div(count, std::int64_t{kReduceThreads}), 1, kMaxBlocks)));
}

// Sum over the kReduceThreads threads of a block, in a fixed order; thread 0 gets the total.
__device__ __forceinline__ float block_sum(float v) {
  __shared__ float warp_totals[kReduceThreads / 32];
  const int lane = static_cast<int>(threadIdx.x % 32);
  const int warp = static_cast<int>(threadIdx.x / 32);
#pragma unroll
  for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_down_sync(0xffffffffu, v, offset);
  if (lane == 0) warp_totals[warp] = v;
  __syncthreads();
  if (warp == 0) {
    v = lane < kReduceThreads / 32 ? warp_totals[lane] : 0.0f;
#pragma unroll
    for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_down_sync(0xffffffffu, v, offset);
  }
  return v;
}

// Block (c, z) of a (channels, splits) grid of kReduceThreads threads:
//   partials[z * channels + c] = sum of dy[b, c, j] over the flattened indices q = b plane + j
//   in [z chunk, (z + 1) chunk) of [0, total = batch * plane),
// dy (batch, channels, plane): split z's share of the bias gradient. Each thread sums every
// kReduceThreads-th element in order, then block_sum adds the threads in a fixed order.
__device__ __forceinline__ void channel_sum_chunk(const float* dy, int channels,
                                                  const FastDivmod& plane, int total, int chunk,
                                                  float* partials) {
  const int c = static_cast<int>(blockIdx.x);
  const int z = static_cast<int>(blockIdx.y);
  const int begin = z * chunk;
  const int end = min(total, begin + chunk);
  float sum = 0.0f;
  for (int q = begin + static_cast<int>(threadIdx.x); q < end; q += kReduceThreads) {
    int b, j;
    plane.divmod(q, b, j);
    sum += dy[(b * channels + c) * plane.divisor + j];
  }
  sum = block_sum(sum);
  if (threadIdx.x == 0) partials[z * channels + c] = sum;
}

// out[e] = sum over z = 0, 1, ..., splits - 1 of partials[z * count + e], for the element e of
// this thread in a grid-stride loop over [0, count).
__device__ __forceinline__ void sum_splits(const float* partials, int splits, int count,
                                           float* out) {
  const int stride = static_cast<int>(gridDim.x * blockDim.x);
  for (int e = static_cast<int>(blockIdx.x * blockDim.x + threadIdx.x); e < count; e += stride) {
    float sum = partials[e];
    for (int z = 1; z < splits; ++z) sum += partials[static_cast<std::int64_t>(z) * count + e];
    out[e] = sum;
  }
}

// ---- launcher-side checks ----

// Indices in the kernels are int.
inline constexpr std::int64_t kMaxElements = (std::int64_t{1} << 31) - 1;

// Throws unless `count` elements fit the kernels' int indices; `what` names the tensor and shape.
inline void check_elements(const char* op, const char* what, std::int64_t count) {
  PS_CHECK(count <= kMaxElements,
           "{}: {} has {} elements; the kernels index with int and take at most {} per tensor", op,
           what, count, kMaxElements);
}

// Throws unless `pointer` is non-null where the tensor it points to has elements.
inline void check_pointer(const char* op, const char* name, const float* pointer,
                          std::int64_t count) {
  PS_CHECK(count == 0 || pointer != nullptr,
           "{}: {} is null but must point to {} floats of device memory", op, name, count);
}

// Throws if the float ranges [a, a + a_count) and [b, b + b_count) overlap: an output may not
// alias an input or another output.
inline void check_disjoint(const char* op, const char* a_name, const float* a, std::int64_t a_count,
                           const char* b_name, const float* b, std::int64_t b_count) {
  if (a == nullptr || b == nullptr || a_count == 0 || b_count == 0) return;
  const auto a_begin = reinterpret_cast<std::uintptr_t>(a);
  const auto b_begin = reinterpret_cast<std::uintptr_t>(b);
  const auto a_end = a_begin + static_cast<std::uintptr_t>(a_count) * sizeof(float);
  const auto b_end = b_begin + static_cast<std::uintptr_t>(b_count) * sizeof(float);
  PS_CHECK(a_end <= b_begin || b_end <= a_begin,
           "{}: {} ({} floats at {}) and {} ({} floats at {}) overlap; outputs must not alias "
           "inputs or each other",
           op, a_name, a_count, static_cast<const void*>(a), b_name, b_count,
           static_cast<const void*>(b));
}

// The element counts of a convolution's input x, weight w and output y.
struct OperandCounts {
  std::int64_t x, w, y;
};

// The operand checks of the convolution launchers (conv2d.cu, conv_transpose2d.cu): every tensor
// with elements has a pointer, and no output aliases an input or another output.
// Forward: x, w, bias (nullptr, or `bias_count` floats) -> y.
inline void check_forward_operands(const char* op, const OperandCounts& n, const float* x,
                                   const float* w, const float* bias, std::int64_t bias_count,
                                   const float* y) {
  check_pointer(op, "x", x, n.x);
  check_pointer(op, "w", w, n.w);
  check_pointer(op, "y", y, n.y);
  check_disjoint(op, "y", y, n.y, "x", x, n.x);
  check_disjoint(op, "y", y, n.y, "w", w, n.w);
  check_disjoint(op, "y", y, n.y, "bias", bias, bias_count);
}

// Input gradient: dy, w -> dx.
inline void check_backward_data_operands(const char* op, const OperandCounts& n, const float* dy,
                                         const float* w, const float* dx) {
  check_pointer(op, "dy", dy, n.y);
  check_pointer(op, "w", w, n.w);
  check_pointer(op, "dx", dx, n.x);
  check_disjoint(op, "dx", dx, n.x, "dy", dy, n.y);
  check_disjoint(op, "dx", dx, n.x, "w", w, n.w);
}

// Parameter gradients: x, dy -> dw, db (nullptr, or `db_count` floats), through `workspace` of
// `workspace_floats`, of which `needed` (what `workspace_function`(shape) returns) are required.
inline void check_backward_weights_operands(const char* op, const char* workspace_function,
                                            const OperandCounts& n, const float* x, const float* dy,
                                            const float* dw, const float* db, std::int64_t db_count,
                                            const float* workspace, std::size_t workspace_floats,
                                            std::size_t needed) {
  check_pointer(op, "x", x, n.x);
  check_pointer(op, "dy", dy, n.y);
  check_pointer(op, "dw", dw, n.w);
  PS_CHECK(workspace_floats >= needed && (needed == 0 || workspace != nullptr),
           "{}: the workspace must hold {}(shape) = {} floats, got {} floats at {}", op,
           workspace_function, needed, workspace_floats, static_cast<const void*>(workspace));
  const auto ws = static_cast<std::int64_t>(needed);
  check_disjoint(op, "dw", dw, n.w, "x", x, n.x);
  check_disjoint(op, "dw", dw, n.w, "dy", dy, n.y);
  check_disjoint(op, "dw", dw, n.w, "db", db, db_count);
  check_disjoint(op, "dw", dw, n.w, "workspace", workspace, ws);
  check_disjoint(op, "db", db, db_count, "x", x, n.x);
  check_disjoint(op, "db", db, db_count, "dy", dy, n.y);
  check_disjoint(op, "db", db, db_count, "workspace", workspace, ws);
  check_disjoint(op, "workspace", workspace, ws, "x", x, n.x);
  check_disjoint(op, "workspace", workspace, ws, "dy", dy, n.y);
}

// The grid of a GEMM of rows x columns in Tile's blocks, `splits` deep; throws if CUDA cannot
// launch it (at most 65535 blocks along y and z).
template <class Tile>
dim3 tile_grid(const char* op, std::int64_t rows, std::int64_t columns, std::int64_t splits = 1) {
  const std::int64_t row_tiles = ceil_div(rows, std::int64_t{Tile::kBlockM});
  PS_CHECK(row_tiles <= 65535 && splits <= 65535,
           "{}: {} rows need {} tiles of {}, more than a grid's 65535 along y", op, rows, row_tiles,
           Tile::kBlockM);
  return dim3(static_cast<unsigned>(ceil_div(columns, std::int64_t{Tile::kBlockN})),
              static_cast<unsigned>(row_tiles), static_cast<unsigned>(splits));
}

}  // namespace pillarseg::cuda::gemm
