// The tensor-core convolutions of conv2d_mma.cuh. One kernel serves the forward of both kinds and
// the input gradients (the convolution's: a convolution of dy with flipped weights; the
// transposed one's: a gather of dy's sub-pixels): a block of 128 threads (4 warps in a 2 x 2
// arrangement) computes a 64 x 64 tile of D (64 output pixels by 64 GEMM columns) in steps of 32
// along K:
//   - staging: each thread owns one pixel m of the tile (tid % 64) and gathers its 16 values of
//     the step's A (rows k = tid / 64 + 2 j), zero outside the image, rounded to the 16-bit type,
//     into As[k][m] (pixels contiguous, as NCHW reads them); the weights' 64 x 32 block goes to
//     Bs[n][k] in 16-byte vectors. Rows are padded by 8 elements against bank conflicts, and stay
//     16-byte aligned for ldmatrix;
//   - compute: per 16 of K, each warp loads its two 16 x 16 A fragments with ldmatrix.x4.trans
//     (As holds A transposed) and its four 16 x 8 B fragments with two ldmatrix.x4, and issues
//     8 mma.sync m16n8k16;
//   - epilogue: bias, ReLU, and the FP32 store of each accumulator to its (pixel, column), for
//     the transposed kind at its sub-pixel (2 h + dy, 2 w + dx).
// The weight gradients have their own kernel on the same compute step (mma_weight_grad_kernel):
// D (weights x columns) over the pixels, split over blocks, the parts summed in order.
#include "kernels/conv2d_mma.cuh"

#include <array>
#include <atomic>
#include <cstring>
#include <string>
#include <type_traits>

#include "core/ops.hpp"
#include "kernels/block_reduce.cuh"
#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kTileM = 64, kTileN = 64, kTileK = 32, kThreads = 128;
constexpr int kPadA = kTileM + 8, kPadB = kTileK + 8;  // shared row lengths, in 16-bit elements

// How row m (a pixel) and column k of A come from x, and where D's (pixel, n) goes.
enum class Gather {
  Conv,        // x (B, I, H, W): k = (channel, tap) at the pixel + tap - pad; y (B, N, Ho, Wo)
  Transposed,  // x (B, I, H, W): k = channel at the pixel; y's sub-pixel (2 h + dy, 2 w + dx) of n
  SubPixels,   // x (B, I / 4.., 2 H, 2 W): k = (channel, dy, dx) at (2 h + dy, 2 w + dx); as Conv
};

struct MmaGemm {
  std::int64_t batch, in_channels, height, width;  // x (SubPixels: height, width of the pixels)
  std::int64_t columns;                            // N: O, or 4 O for the transposed kind
  std::int64_t out_height, out_width;              // of the pixels D's rows are (conv: y's)
  std::int64_t k, k_padded;                        // I k k (I, 4 I), and rounded up to 32
  int kernel, pad;
  Gather gather;
  bool relu;
};

// 16 bytes, both ends 16-byte aligned.
__device__ __forceinline__ void copy16(void* dst, const void* src) {
#if defined(__CUDA_ARCH__)
  *static_cast<uint4*>(dst) = *static_cast<const uint4*>(src);
#else
  std::memcpy(dst, src, 16);
#endif
}

// A warp's 2 x 4 accumulator fragments of mma_tile_step = 0.
__device__ __forceinline__ void zero_accumulators(float (&acc)[2][4][4]) {
#pragma unroll
  for (int a = 0; a < 2; ++a)
#pragma unroll
    for (int b = 0; b < 4; ++b)
#pragma unroll
      for (int c = 0; c < 4; ++c) acc[a][b][c] = 0.0f;
}

// One step of 32 along K for a warp of the 2 x 2 arrangement: per 16 of K, its two 16 x 16 A
// fragments with ldmatrix.x4.trans (as holds A transposed: as[k][m]) and its four 16 x 8 B
// fragments with two ldmatrix.x4 (bs[n][k]), and 8 mma.sync m16n8k16 into acc.
template <Half16 H>
__device__ __forceinline__ void mma_tile_step(const std::uint16_t (&as)[kTileK][kPadA],
                                              const std::uint16_t (&bs)[kTileN][kPadB],
                                              float (&acc)[2][4][4], int warp_m, int warp_n,
                                              int lane) {
#pragma unroll
  for (int kk = 0; kk < kTileK; kk += 16) {
    std::uint32_t a[2][4], b[4][2];
    const int j = lane / 8, r = lane % 8;
#pragma unroll
    for (int mt = 0; mt < 2; ++mt) {
      // Matrix j of the fragment: k rows kk + (j / 2) 8 .. + 8, pixels + (j % 2) 8.
      const int pm = warp_m * 32 + mt * 16 + (j % 2) * 8;
      ldmatrix_x4<true>(a[mt], &as[kk + (j / 2) * 8 + r][pm]);
    }
#pragma unroll
    for (int np = 0; np < 2; ++np) {
      // Matrices: (n 0-7, k 0-7), (n 0-7, k 8-15), (n 8-15, k 0-7), (n 8-15, k 8-15).
      const int pn = warp_n * 32 + np * 16 + (j / 2) * 8 + r;
      std::uint32_t regs[4];
      ldmatrix_x4<false>(regs, &bs[pn][kk + (j % 2) * 8]);
      b[2 * np][0] = regs[0], b[2 * np][1] = regs[1], b[2 * np + 1][0] = regs[2],
            b[2 * np + 1][1] = regs[3];
    }
#pragma unroll
    for (int mt = 0; mt < 2; ++mt)
#pragma unroll
      for (int nt = 0; nt < 4; ++nt) mma_m16n8k16<H>(acc[mt][nt], a[mt], b[nt], acc[mt][nt]);
  }
}

// TIn, TOut: float (FP32 activations) or std::uint16_t (16-bit activations of type H).
template <Half16 H, class TIn, class TOut>
__global__ void __launch_bounds__(kThreads)
    mma_gemm_kernel(const TIn* __restrict__ x, const std::uint16_t* __restrict__ w16,
                    const float* __restrict__ bias, MmaGemm g, TOut* __restrict__ y) {
  __shared__ __align__(16) std::uint16_t as[kTileK][kPadA];
  __shared__ __align__(16) std::uint16_t bs[kTileN][kPadB];
  const int tid = static_cast<int>(threadIdx.x), lane = tid % 32, warp = tid / 32;
  const int warp_m = warp % 2, warp_n = warp / 2;
  const std::int64_t pixels_per_image = g.out_height * g.out_width;
  const std::int64_t rows = g.batch * pixels_per_image;
  const std::int64_t m0 = static_cast<std::int64_t>(blockIdx.x) * kTileM;
  const std::int64_t n0 = static_cast<std::int64_t>(blockIdx.y) * kTileN;

  // This thread's staging pixel.
  const int sm = tid % kTileM;
  const std::int64_t m = m0 + sm;
  const bool m_valid = m < rows;
  const std::int64_t image = m_valid ? m / pixels_per_image : 0;
  const std::int64_t pixel = m_valid ? m % pixels_per_image : 0;
  const std::int64_t oy = pixel / g.out_width, ox = pixel % g.out_width;
  const std::int64_t plane = g.height * g.width;
  const TIn* x_image = x + image * g.in_channels * (g.gather == Gather::SubPixels ? 4 * plane : plane);
  const int taps = g.kernel * g.kernel;

  float acc[2][4][4];
  zero_accumulators(acc);

  for (std::int64_t k0 = 0; k0 < g.k_padded; k0 += kTileK) {
// A: rows k0 + tid / 64 + 2 j of this thread's pixel.
#pragma unroll
    for (int j = 0; j < kTileK * kTileM / kThreads; ++j) {
      const int sk = tid / kTileM + 2 * j;
      const std::int64_t k = k0 + sk;
      std::int64_t index = -1;
      if (m_valid && k < g.k) {
        if (g.gather == Gather::Transposed) {
          index = k * plane + oy * g.width + ox;
        } else if (g.gather == Gather::SubPixels) {
          const std::int64_t channel = k / 4, dy = (k % 4) / 2, dx = k % 2;
          index = (channel * 2 * g.height + 2 * oy + dy) * 2 * g.width + 2 * ox + dx;
        } else {
          const std::int64_t channel = k / taps;
          const int tap = static_cast<int>(k % taps);
          const std::int64_t iy = oy + tap / g.kernel - g.pad, ix = ox + tap % g.kernel - g.pad;
          if (iy >= 0 && iy < g.height && ix >= 0 && ix < g.width)
            index = channel * plane + iy * g.width + ix;
        }
      }
      std::uint16_t bits = 0;  // +0 in both types
      if (index >= 0) {
        if constexpr (std::is_same_v<TIn, float>)
          bits = to_half16<H>(x_image[index]);
        else
          bits = x_image[index];
      }
      as[sk][sm] = bits;
    }
    // B: 64 rows n of 32 k, as 256 vectors of 8 elements.
    for (int v = tid; v < kTileN * kTileK / 8; v += kThreads) {
      const int sn = v / (kTileK / 8), sk = v % (kTileK / 8) * 8;
      const std::int64_t n = n0 + sn;
      if (n < g.columns) {
        copy16(&bs[sn][sk], w16 + n * g.k_padded + k0 + sk);
      } else {
        for (int e = 0; e < 8; ++e) bs[sn][sk + e] = 0;
      }
    }
    __syncthreads();
    mma_tile_step<H>(as, bs, acc, warp_m, warp_n, lane);
    __syncthreads();
  }

  // Epilogue: accumulator i of (mt, nt) is D[row g + 8 (i >= 2)][column 2 t + (i & 1)].
  const int group = lane / 4, t = lane % 4;
#pragma unroll
  for (int mt = 0; mt < 2; ++mt) {
#pragma unroll
    for (int half = 0; half < 2; ++half) {
      const std::int64_t row = m0 + warp_m * 32 + mt * 16 + group + 8 * half;
      if (row >= rows) continue;
      const std::int64_t img = row / pixels_per_image, px = row % pixels_per_image;
      const std::int64_t py = px / g.out_width, pxx = px % g.out_width;
#pragma unroll
      for (int nt = 0; nt < 4; ++nt) {
#pragma unroll
        for (int e = 0; e < 2; ++e) {
          const std::int64_t n = n0 + warp_n * 32 + nt * 8 + 2 * t + e;
          if (n >= g.columns) continue;
          float value = acc[mt][nt][2 * half + e] + (bias != nullptr ? bias[n] : 0.0f);
          if (g.relu) value = value > 0.0f ? value : 0.0f;
          std::int64_t index = 0;
          if (g.gather == Gather::Transposed) {
            const std::int64_t o = n / 4, dy = (n % 4) / 2, dx = n % 2;
            const std::int64_t yh = 2 * g.out_height, yw = 2 * g.out_width;
            index = ((img * (g.columns / 4) + o) * yh + 2 * py + dy) * yw + 2 * pxx + dx;
          } else {
            index = (img * g.columns + n) * pixels_per_image + px;
          }
          if constexpr (std::is_same_v<TOut, float>)
            y[index] = value;
          else
            y[index] = to_half16<H>(value);
        }
      }
    }
  }
}

// The training weight gradient as D (M x N) = A (M x Q) B (Q x N) over the Q = B x pixels of its
// pixel grid, each block (blockIdx.z) summing `chunk` of them into partial[z] (M x N):
//   convolution, w (O, I, k, k): m = (i, tap), n = o, q a pixel of dy (B, O, Ho, Wo); A[m][q] = x
//     at q + tap - pad (zero outside), B[q][n] = dy[o] at q; dw[o][m] = D[m][o];
//   transposed, w (I, O, 2, 2): m = i, n = (o, dy, dx), q a pixel of x (B, I, H, W); A[m][q] = x[i]
//     at q, B[q][n] = dy[o] at (2 h + dy, 2 w + dx); dw[m][n] = D[m][n].
// The staging rounds x and dy to the 16-bit type; the compute is mma_tile_step's.
struct MmaWeightGrad {
  std::int64_t batch, in_channels, height, width;  // x
  std::int64_t out_channels;                       // O
  std::int64_t rows, columns;                      // M, N
  std::int64_t out_height, out_width;              // the pixel grid of q (conv: dy's; transposed: x's)
  std::int64_t chunk;                              // pixels per split, a multiple of kTileK
  int kernel, pad;
  bool transposed;
};

template <Half16 H>
__global__ void __launch_bounds__(kThreads)
    mma_weight_grad_kernel(const float* __restrict__ x, const float* __restrict__ dy, MmaWeightGrad g,
                           float* __restrict__ partial) {
  __shared__ __align__(16) std::uint16_t as[kTileK][kPadA];
  __shared__ __align__(16) std::uint16_t bs[kTileN][kPadB];
  const int tid = static_cast<int>(threadIdx.x), lane = tid % 32, warp = tid / 32;
  const int warp_m = warp % 2, warp_n = warp / 2;
  const std::int64_t m0 = static_cast<std::int64_t>(blockIdx.x) * kTileM;
  const std::int64_t n0 = static_cast<std::int64_t>(blockIdx.y) * kTileN;
  const std::int64_t pixels = g.out_height * g.out_width, total = g.batch * pixels;
  const std::int64_t q_begin = static_cast<std::int64_t>(blockIdx.z) * g.chunk;
  const std::int64_t q_end = q_begin + g.chunk < total ? q_begin + g.chunk : total;
  const std::int64_t plane = g.height * g.width;
  const int taps = g.kernel * g.kernel;

  float acc[2][4][4];
  zero_accumulators(acc);

  for (std::int64_t q0 = q_begin; q0 < q_end; q0 += kTileK) {
    // A: as[sk][sm] = A[m0 + sm][q0 + sk]; a warp reads 32 consecutive pixels of one row m.
#pragma unroll 4
    for (int j = 0; j < kTileK * kTileM / kThreads; ++j) {
      const int sk = tid % kTileK, sm = tid / kTileK + (kThreads / kTileK) * j;
      const std::int64_t m = m0 + sm, q = q0 + sk;
      std::uint16_t bits = 0;
      if (m < g.rows && q < q_end) {
        const std::int64_t image = q / pixels, p = q % pixels;
        const std::int64_t channel = g.transposed ? m : m / taps;
        std::int64_t index = -1;
        if (g.transposed) {
          index = (image * g.in_channels + channel) * plane + p;
        } else {
          const int tap = static_cast<int>(m % taps);
          const std::int64_t iy = p / g.out_width + tap / g.kernel - g.pad;
          const std::int64_t ix = p % g.out_width + tap % g.kernel - g.pad;
          if (iy >= 0 && iy < g.height && ix >= 0 && ix < g.width)
            index = (image * g.in_channels + channel) * plane + iy * g.width + ix;
        }
        if (index >= 0) bits = to_half16<H>(x[index]);
      }
      as[sk][sm] = bits;
    }
    // B: bs[sn][sk] = B[q0 + sk][n0 + sn].
    for (int v = tid; v < kTileN * kTileK; v += kThreads) {
      const int sn = v / kTileK, sk = v % kTileK;
      const std::int64_t n = n0 + sn, q = q0 + sk;
      std::uint16_t bits = 0;
      if (n < g.columns && q < q_end) {
        const std::int64_t image = q / pixels, p = q % pixels;
        std::int64_t index;
        if (g.transposed) {
          const std::int64_t o = n / 4, sy = (n % 4) / 2, sx = n % 2;
          index = ((image * g.out_channels + o) * 2 * g.out_height + 2 * (p / g.out_width) + sy) * 2 * g.out_width +
                  2 * (p % g.out_width) + sx;
        } else {
          index = (image * g.out_channels + n) * pixels + p;
        }
        bits = to_half16<H>(dy[index]);
      }
      bs[sn][sk] = bits;
    }
    __syncthreads();
    mma_tile_step<H>(as, bs, acc, warp_m, warp_n, lane);
    __syncthreads();
  }

  const int group = lane / 4, t = lane % 4;
  float* out = partial + static_cast<std::int64_t>(blockIdx.z) * g.rows * g.columns;
#pragma unroll
  for (int mt = 0; mt < 2; ++mt) {
#pragma unroll
    for (int half = 0; half < 2; ++half) {
      const std::int64_t row = m0 + warp_m * 32 + mt * 16 + group + 8 * half;
      if (row >= g.rows) continue;
#pragma unroll
      for (int nt = 0; nt < 4; ++nt) {
#pragma unroll
        for (int e = 0; e < 2; ++e) {
          const std::int64_t n = n0 + warp_n * 32 + nt * 8 + 2 * t + e;
          if (n < g.columns) out[row * g.columns + n] = acc[mt][nt][2 * half + e];
        }
      }
    }
  }
}

// dw = the sum of the splits' partials in split order (the same bits on every run), laid out as
// w: convolution dw[n][m], transposed dw[m][n].
__global__ void weight_grad_reduce_kernel(const float* __restrict__ partial, std::int64_t splits,
                                          std::int64_t rows, std::int64_t columns, bool transposed,
                                          float* __restrict__ dw) {
  const std::int64_t n_total = rows * columns;
  for (std::int64_t i = static_cast<std::int64_t>(blockIdx.x) * blockDim.x + threadIdx.x; i < n_total;
       i += static_cast<std::int64_t>(gridDim.x) * blockDim.x) {
    float sum = 0.0f;
    for (std::int64_t z = 0; z < splits; ++z) sum += partial[z * n_total + i];
    const std::int64_t m = i / columns, n = i % columns;
    dw[transposed ? i : n * rows + m] = sum;
  }
}

// dbias[o] = the sum of dy[b, o] over its planes (B, O, plane), one block a channel, in double.
constexpr int kBiasThreads = 256;
__global__ void __launch_bounds__(kBiasThreads)
    bias_grad_kernel(const float* __restrict__ dy, std::int64_t batch, std::int64_t channels,
                     std::int64_t plane, float* __restrict__ dbias) {
  const std::int64_t o = blockIdx.x;
  double sum = 0.0;
  for (std::int64_t i = threadIdx.x; i < batch * plane; i += kBiasThreads)
    sum += dy[((i / plane) * channels + o) * plane + i % plane];
  sum = block_sum<kBiasThreads>(sum);
  if (threadIdx.x == 0) dbias[o] = static_cast<float>(sum);
}

// The weights of the input gradients, w16t (I, Kp) rounded: convolution w (O, I, k, k) flipped,
// row i column (o, tap) = w[o][i][taps - 1 - tap]; transposed w (I, O, 2, 2): row i = its 4 O
// values.
template <Half16 H>
__global__ void prepare_data_weights_kernel(const float* __restrict__ w, std::int64_t rows,
                                            std::int64_t k, std::int64_t k_padded, int taps,
                                            bool transposed, std::uint16_t* __restrict__ w16t) {
  const std::int64_t i = static_cast<std::int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= rows * k_padded) return;
  const std::int64_t r = i / k_padded, c = i % k_padded;
  float value = 0.0f;
  if (c < k) {
    value = transposed ? w[r * k + c] : w[((c / taps) * rows + r) * taps + (taps - 1 - c % taps)];
  }
  w16t[i] = to_half16<H>(value);
}

template <Half16 H>
__global__ void prepare_weights_kernel(const float* __restrict__ w, const float* __restrict__ bias,
                                       FoldedBatchNorm bn, std::int64_t rows, std::int64_t k,
                                       std::int64_t k_padded, bool transposed,
                                       std::int64_t out_channels, std::uint16_t* __restrict__ w16,
                                       float* __restrict__ bias_out) {
  const std::int64_t i = static_cast<std::int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= rows * k_padded) return;
  const std::int64_t n = i / k_padded, kk = i % k_padded;
  float scale = 1.0f, shift = 0.0f;
  // Transposed: row n = o 4 + s of column kk = i reads w[i, o, s]; no BatchNorm.
  const std::int64_t o = transposed ? n / 4 : n;
  if (!transposed && bn.gamma != nullptr) {
    scale = bn.gamma[o] / sqrtf(bn.running_var[o] + bn.eps);
    shift = bn.beta[o] - scale * bn.running_mean[o];
  }
  float value = 0.0f;
  if (kk < k) value = transposed ? w[(kk * out_channels + o) * 4 + n % 4] : w[n * k + kk] * scale;
  w16[i] = to_half16<H>(value);
  if (kk == 0) bias_out[n] = scale * (bias != nullptr ? bias[o] : 0.0f) + shift;
}

// One warp: each lane builds its A and B registers from row-major A (16 x 16) and B (16 x 8) by
// the ISA's formulas, runs the mma, and writes its four results to D (16 x 8) by the formula.
template <Half16 H>
__global__ void mma_probe_kernel(const float* a, const float* b, const float* c, float* d) {
  const int lane = static_cast<int>(threadIdx.x), g = lane / 4, t = lane % 4;
  std::uint32_t ra[4], rb[2];
  for (int r = 0; r < 4; ++r) {
    std::uint32_t reg = 0;
    for (int half = 0; half < 2; ++half) {
      const int i = 2 * r + half;
      const int row = g + ((i == 2 || i == 3 || i == 6 || i == 7) ? 8 : 0);
      const int col = 2 * t + (i & 1) + (i >= 4 ? 8 : 0);
      reg |= std::uint32_t{to_half16<H>(a[row * 16 + col])} << (16 * half);
    }
    ra[r] = reg;
  }
  for (int r = 0; r < 2; ++r) {
    std::uint32_t reg = 0;
    for (int half = 0; half < 2; ++half) {
      const int i = 2 * r + half;
      const int row = 2 * t + (i & 1) + (i >= 2 ? 8 : 0);
      reg |= std::uint32_t{to_half16<H>(b[row * 8 + g])} << (16 * half);
    }
    rb[r] = reg;
  }
  float rc[4], rd[4];
  for (int i = 0; i < 4; ++i) rc[i] = c[(g + (i >= 2 ? 8 : 0)) * 8 + 2 * t + (i & 1)];
  mma_m16n8k16<H>(rd, ra, rb, rc);
  for (int i = 0; i < 4; ++i) d[(g + (i >= 2 ? 8 : 0)) * 8 + 2 * t + (i & 1)] = rd[i];
}

// One warp loads a 16 x 16 matrix of 16-bit values v[r][c] = 256 r + c (as bits) into shared
// memory and reads it with ldmatrix.x4 (matrices: rows 0-7 / 8-15 by columns 0-7 / 8-15, in the
// order (0, 0), (8, 0), (0, 8), (8, 8)) and x2 (the first two), plain and transposed.
__global__ void ldmatrix_probe_kernel(std::uint32_t* out) {
  __shared__ __align__(16) std::uint16_t m[16][16];
  const int lane = static_cast<int>(threadIdx.x);
  for (int i = lane; i < 256; i += 32)
    m[i / 16][i % 16] = static_cast<std::uint16_t>(256 * (i / 16) + i % 16);
  __syncwarp();
  const int j = lane / 8, r = lane % 8;
  const int row = (j % 2) * 8 + r, col = (j / 2) * 8;
  std::uint32_t x4[4], x4t[4], x2[2], x2t[2];
  ldmatrix_x4<false>(x4, &m[row][col]);
  ldmatrix_x4<true>(x4t, &m[row][col]);
  ldmatrix_x2<false>(x2, &m[row][col]);
  ldmatrix_x2<true>(x2t, &m[row][col]);
  for (int q = 0; q < 4; ++q) {
    out[lane * 12 + q] = x4[q];
    out[lane * 12 + 4 + q] = x4t[q];
  }
  for (int q = 0; q < 2; ++q) {
    out[lane * 12 + 8 + q] = x2[q];
    out[lane * 12 + 10 + q] = x2t[q];
  }
}

template <Half16 H>
void launch_gemm(dim3 grid, const void* x, bool x_half, const std::uint16_t* w16, const float* bias,
                 const MmaGemm& g, void* y, bool y_half, cudaStream_t stream) {
  using U = std::uint16_t;
  if (x_half && y_half)
    launch_kernel(mma_gemm_kernel<H, U, U>, grid, dim3(kThreads), 0, stream,
                  static_cast<const U*>(x), w16, bias, g, static_cast<U*>(y));
  else if (x_half)
    launch_kernel(mma_gemm_kernel<H, U, float>, grid, dim3(kThreads), 0, stream,
                  static_cast<const U*>(x), w16, bias, g, static_cast<float*>(y));
  else if (y_half)
    launch_kernel(mma_gemm_kernel<H, float, U>, grid, dim3(kThreads), 0, stream,
                  static_cast<const float*>(x), w16, bias, g, static_cast<U*>(y));
  else
    launch_kernel(mma_gemm_kernel<H, float, float>, grid, dim3(kThreads), 0, stream,
                  static_cast<const float*>(x), w16, bias, g, static_cast<float*>(y));
}

void run_gemm(const void* x, bool x_half, const std::uint16_t* w16, const float* bias,
              const MmaGemm& g, Half16 type, void* y, bool y_half, cudaStream_t stream) {
  const std::int64_t rows = g.batch * g.out_height * g.out_width;
  if (rows == 0 || g.columns == 0) return;
  std::string why;
  PS_CHECK(mma_supported(&why), "conv2d_mma: {}", why);
  const dim3 grid(static_cast<unsigned>(ceil_div(rows, kTileM)),
                  static_cast<unsigned>(ceil_div(g.columns, kTileN)));
  with_half16(type, [&](auto h) {
    launch_gemm<decltype(h)::value>(grid, x, x_half, w16, bias, g, y, y_half, stream);
  });
}

void run_prepare(const float* w, const float* bias, const FoldedBatchNorm& bn, std::int64_t rows,
                 std::int64_t k, bool transposed, std::int64_t out_channels, Half16 type,
                 std::uint16_t* w16, float* bias_out, cudaStream_t stream) {
  const std::int64_t total = rows * mma_padded_k(k);
  if (total == 0) return;
  const dim3 grid(static_cast<unsigned>(ceil_div(total, 256)));
  with_half16(type, [&](auto h) {
    launch_kernel(prepare_weights_kernel<decltype(h)::value>, grid, dim3(256), 0, stream, w, bias,
                  bn, rows, k, mma_padded_k(k), transposed, out_channels, w16, bias_out);
  });
}

}  // namespace

static_assert(kTileK == op::kHalf16WeightK, "the prepared weights' K padding is the kernel's K step");

std::int64_t mma_padded_k(std::int64_t k) { return op::half16_padded_k(k); }

bool mma_supported(std::string* why_not) {
#if defined(PILLARSEG_CUDA_EMULATION)
  static_cast<void>(why_not);
  return true;
#else
  int device = 0;
  PS_CUDA_CHECK(cudaGetDevice(&device));
  // Asked once per device: every launch checks it.
  static std::array<std::atomic<int>, 64> cached{};  // 10 major + minor, 0: not asked yet
  int capability = device >= 0 && device < 64 ? cached[static_cast<size_t>(device)].load() : 0;
  if (capability == 0) {
    int major = 0, minor = 0;
    PS_CUDA_CHECK(cudaDeviceGetAttribute(&major, cudaDevAttrComputeCapabilityMajor, device));
    PS_CUDA_CHECK(cudaDeviceGetAttribute(&minor, cudaDevAttrComputeCapabilityMinor, device));
    capability = 10 * major + minor;
    if (device >= 0 && device < 64) cached[static_cast<size_t>(device)].store(capability);
  }
  const int major = capability / 10, minor = capability % 10;
  if (major >= 8) return true;
  if (why_not != nullptr) {
    *why_not = fmt::format(
        "BF16 and FP16 tensor-core convolutions (mma.sync m16n8k16) need compute capability 8.0 or "
        "later; device {} "
        "has {}.{}",
        device, major, minor);
  }
  return false;
#endif
}

void prepare_conv_weights(const float* w, const float* bias, const FoldedBatchNorm& bn,
                          const Conv2dShape& shape, Half16 type, std::uint16_t* w16,
                          float* bias_out, cudaStream_t stream) {
  run_prepare(w, bias, bn, shape.out_channels, shape.in_channels * shape.kernel * shape.kernel,
              false, shape.out_channels, type, w16, bias_out, stream);
}

void prepare_conv_transpose_weights(const float* w, const float* bias, std::int64_t in_channels,
                                    std::int64_t out_channels, Half16 type, std::uint16_t* w16,
                                    float* bias_out, cudaStream_t stream) {
  run_prepare(w, bias, FoldedBatchNorm{}, 4 * out_channels, in_channels, true, out_channels, type,
              w16, bias_out, stream);
}

void conv2d_mma_forward(const void* x, bool x_half, const std::uint16_t* w16, const float* bias,
                        const Conv2dShape& shape, Half16 type, bool relu, void* y, bool y_half,
                        cudaStream_t stream) {
  const std::int64_t k = shape.in_channels * shape.kernel * shape.kernel;
  MmaGemm g{};
  g.batch = shape.batch, g.in_channels = shape.in_channels, g.height = shape.height;
  g.width = shape.width, g.columns = shape.out_channels;
  g.out_height = shape.out_height(), g.out_width = shape.out_width();
  g.k = k, g.k_padded = mma_padded_k(k);
  g.kernel = static_cast<int>(shape.kernel), g.pad = static_cast<int>(shape.pad);
  g.gather = Gather::Conv, g.relu = relu;
  run_gemm(x, x_half, w16, bias, g, type, y, y_half, stream);
}

void conv_transpose2x2_mma_forward(const void* x, bool x_half, const std::uint16_t* w16,
                                   const float* bias, std::int64_t batch, std::int64_t in_channels,
                                   std::int64_t height, std::int64_t width,
                                   std::int64_t out_channels, Half16 type, void* y, bool y_half,
                                   cudaStream_t stream) {
  // The pixels are x's; each of the 4 O columns writes its sub-pixel of y.
  MmaGemm g{};
  g.batch = batch, g.in_channels = in_channels, g.height = height, g.width = width;
  g.columns = 4 * out_channels, g.out_height = height, g.out_width = width;
  g.k = in_channels, g.k_padded = mma_padded_k(in_channels);
  g.kernel = 1, g.pad = 0, g.gather = Gather::Transposed, g.relu = false;
  run_gemm(x, x_half, w16, bias, g, type, y, y_half, stream);
}

// ---- training gradients ----

namespace {

// The split of the weight gradient's Q pixels: about 256 blocks in all (a fixed count, so that
// the sums, and their bits, do not depend on the GPU), chunks of whole K steps.
MmaWeightGrad weight_grad_split(MmaWeightGrad g) {
  const std::int64_t total = g.batch * g.out_height * g.out_width;
  const std::int64_t tiles = ceil_div(g.rows, kTileM) * ceil_div(g.columns, kTileN);
  const std::int64_t steps = ceil_div(total, kTileK);
  std::int64_t splits = ceil_div(std::int64_t{256}, tiles);
  if (splits > steps) splits = steps;
  if (splits < 1) splits = 1;
  g.chunk = ceil_div(steps, splits) * kTileK;
  return g;
}

std::int64_t split_count(const MmaWeightGrad& g) {
  return g.chunk == 0 ? 0 : ceil_div(g.batch * g.out_height * g.out_width, g.chunk);
}

MmaWeightGrad conv_weight_grad(const Conv2dShape& shape) {
  MmaWeightGrad g{};
  g.batch = shape.batch, g.in_channels = shape.in_channels, g.height = shape.height, g.width = shape.width;
  g.out_channels = shape.out_channels;
  g.rows = shape.in_channels * shape.kernel * shape.kernel, g.columns = shape.out_channels;
  g.out_height = shape.out_height(), g.out_width = shape.out_width();
  g.kernel = static_cast<int>(shape.kernel), g.pad = static_cast<int>(shape.pad), g.transposed = false;
  return weight_grad_split(g);
}

MmaWeightGrad conv_transpose_weight_grad(const ConvTranspose2dShape& shape) {
  MmaWeightGrad g{};
  g.batch = shape.batch, g.in_channels = shape.in_channels, g.height = shape.height, g.width = shape.width;
  g.out_channels = shape.out_channels;
  g.rows = shape.in_channels, g.columns = 4 * shape.out_channels;
  g.out_height = shape.height, g.out_width = shape.width;
  g.kernel = 1, g.pad = 0, g.transposed = true;
  return weight_grad_split(g);
}

void run_weight_grad(const float* x, const float* dy, const MmaWeightGrad& g, Half16 type, float* dw,
                     float* workspace, cudaStream_t stream) {
  const std::int64_t splits = split_count(g);
  if (g.rows == 0 || g.columns == 0) return;
  if (splits == 0) {  // no pixels: the gradient is zero
    PS_CUDA_CHECK(cudaMemsetAsync(dw, 0, static_cast<size_t>(g.rows * g.columns) * sizeof(float), stream));
    return;
  }
  std::string why;
  PS_CHECK(mma_supported(&why), "conv2d_mma backward: {}", why);
  const dim3 grid(static_cast<unsigned>(ceil_div(g.rows, kTileM)), static_cast<unsigned>(ceil_div(g.columns, kTileN)),
                  static_cast<unsigned>(splits));
  with_half16(type, [&](auto h) {
    launch_kernel(mma_weight_grad_kernel<decltype(h)::value>, grid, dim3(kThreads), 0, stream, x, dy, g, workspace);
  });
  const std::int64_t n = g.rows * g.columns;
  launch_kernel(weight_grad_reduce_kernel, dim3(static_cast<unsigned>(ceil_div(n, 256) < 4096 ? ceil_div(n, 256) : 4096)),
                dim3(256), 0, stream, workspace, splits, g.rows, g.columns, g.transposed, dw);
}

void run_bias_grad(const float* dy, std::int64_t batch, std::int64_t channels, std::int64_t plane, float* dbias,
                   cudaStream_t stream) {
  if (dbias == nullptr || channels == 0) return;
  launch_kernel(bias_grad_kernel, dim3(static_cast<unsigned>(channels)), dim3(kBiasThreads), 0, stream, dy, batch,
                channels, plane, dbias);
}

void run_prepare_data(const float* w, std::int64_t rows, std::int64_t k, int taps, bool transposed, Half16 type,
                      std::uint16_t* w16t, cudaStream_t stream) {
  const std::int64_t total = rows * mma_padded_k(k);
  if (total == 0) return;
  with_half16(type, [&](auto h) {
    launch_kernel(prepare_data_weights_kernel<decltype(h)::value>, dim3(static_cast<unsigned>(ceil_div(total, 256))),
                  dim3(256), 0, stream, w, rows, k, mma_padded_k(k), taps, transposed, w16t);
  });
}

}  // namespace

void prepare_conv_data_weights(const float* w, const Conv2dShape& shape, Half16 type, std::uint16_t* w16t,
                               cudaStream_t stream) {
  const int taps = static_cast<int>(shape.kernel * shape.kernel);
  run_prepare_data(w, shape.in_channels, shape.out_channels * taps, taps, false, type, w16t, stream);
}

void conv2d_mma_backward_data(const float* dy, const std::uint16_t* w16t, const Conv2dShape& shape, Half16 type,
                              float* dx, cudaStream_t stream) {
  // dx = the convolution of dy (B, O, Ho, Wo) with the flipped weights, padding k - 1 - pad.
  const std::int64_t k = shape.out_channels * shape.kernel * shape.kernel;
  MmaGemm g{};
  g.batch = shape.batch, g.in_channels = shape.out_channels, g.height = shape.out_height();
  g.width = shape.out_width(), g.columns = shape.in_channels;
  g.out_height = shape.height, g.out_width = shape.width;
  g.k = k, g.k_padded = mma_padded_k(k);
  g.kernel = static_cast<int>(shape.kernel), g.pad = static_cast<int>(shape.kernel - 1 - shape.pad);
  g.gather = Gather::Conv, g.relu = false;
  run_gemm(dy, false, w16t, nullptr, g, type, dx, false, stream);
}

std::int64_t conv2d_mma_backward_weights_workspace(const Conv2dShape& shape) {
  const MmaWeightGrad g = conv_weight_grad(shape);
  return split_count(g) * g.rows * g.columns;
}

void conv2d_mma_backward_weights(const float* x, const float* dy, const Conv2dShape& shape, Half16 type, float* dw,
                                 float* dbias, float* workspace, cudaStream_t stream) {
  run_weight_grad(x, dy, conv_weight_grad(shape), type, dw, workspace, stream);
  run_bias_grad(dy, shape.batch, shape.out_channels, shape.out_height() * shape.out_width(), dbias, stream);
}

void prepare_conv_transpose_data_weights(const float* w, const ConvTranspose2dShape& shape, Half16 type,
                                         std::uint16_t* w16t, cudaStream_t stream) {
  run_prepare_data(w, shape.in_channels, 4 * shape.out_channels, 1, true, type, w16t, stream);
}

void conv_transpose2x2_mma_backward_data(const float* dy, const std::uint16_t* w16t, const ConvTranspose2dShape& shape,
                                         Half16 type, float* dx, cudaStream_t stream) {
  // dx (B, I, H, W): pixels of x, K = the 4 O sub-pixel values of dy above each.
  MmaGemm g{};
  g.batch = shape.batch, g.in_channels = shape.out_channels, g.height = shape.height, g.width = shape.width;
  g.columns = shape.in_channels, g.out_height = shape.height, g.out_width = shape.width;
  g.k = 4 * shape.out_channels, g.k_padded = mma_padded_k(g.k);
  g.kernel = 1, g.pad = 0, g.gather = Gather::SubPixels, g.relu = false;
  run_gemm(dy, false, w16t, nullptr, g, type, dx, false, stream);
}

std::int64_t conv_transpose2x2_mma_backward_weights_workspace(const ConvTranspose2dShape& shape) {
  const MmaWeightGrad g = conv_transpose_weight_grad(shape);
  return split_count(g) * g.rows * g.columns;
}

void conv_transpose2x2_mma_backward_weights(const float* x, const float* dy, const ConvTranspose2dShape& shape,
                                            Half16 type, float* dw, float* dbias, float* workspace,
                                            cudaStream_t stream) {
  run_weight_grad(x, dy, conv_transpose_weight_grad(shape), type, dw, workspace, stream);
  run_bias_grad(dy, shape.batch, shape.out_channels, 4 * shape.height * shape.width, dbias, stream);
}

void mma_fragment_probe(const float* a, const float* b, const float* c, Half16 type, float* d,
                        cudaStream_t stream) {
  std::string why;
  PS_CHECK(mma_supported(&why), "mma_fragment_probe: {}", why);
  with_half16(type, [&](auto h) {
    launch_kernel(mma_probe_kernel<decltype(h)::value>, dim3(1), dim3(32), 0, stream, a, b, c, d);
  });
}

void ldmatrix_probe(std::uint32_t* out, cudaStream_t stream) {
  launch_kernel(ldmatrix_probe_kernel, dim3(1), dim3(32), 0, stream, out);
}

}  // namespace pillarseg::cuda
