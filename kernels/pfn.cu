// Fused PFN layer (see pfn.cuh): points (P, N, 10), weight (C, 10) -> out, max_slot (P, C), and
// its backward. Most kernels run blocks of 32 channels (threadIdx.x, so that a warp reads one
// point row as a broadcast and writes (P, C) outputs coalesced) by 8 row groups (threadIdx.y);
// each thread keeps its channel's 10 weights in registers and recomputes z = point . w.
//   forward:  [statistics] per block of 1024 rows: shifted sums of z in double -> partials;
//             [finalize]   kernels/batchnorm.cu, per channel in a fixed order;
//             [apply_max]  one thread per (pillar, channel): BatchNorm + ReLU + max over slots.
//   backward: [sums]       per block of 256 pillars: sum g, sum g * xhat over the routed rows
//                          (g = d_out(p, c) at row (p, max_slot(p, c)), 0 elsewhere);
//             [finalize]   kernels/batchnorm.cu: d_gamma, d_beta, the dz coefficients;
//             [d_weight]   per block of 1024 rows: sum dz * point -> partials, then one warp per
//                          weight adds them in a fixed order;
//             [d_points]   one thread per row: sum over channels of dz * w.
#include "kernels/pfn.cuh"

#include <cstdint>
#include <limits>

#include "kernels/batchnorm.cuh"
#include "kernels/block_reduce.cuh"
#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kChannelTile = 32;  // threadIdx.x
constexpr int kRowGroups = 8;     // threadIdx.y
constexpr int kBlockSize = kChannelTile * kRowGroups;
// Rows (P * N) per block of the statistics and d_weight passes: 128 per thread.
constexpr std::int64_t kRowsPerBlock = 1024;
// Pillars per block of the backward sums: 32 per thread (a pillar has one routed row per
// channel, so this pass reads N times less than the others).
constexpr std::int64_t kPillarsPerSumsBlock = 256;
constexpr int kFeatures = static_cast<int>(kPfnFeatures);

std::int64_t row_parts(const PfnShape& shape) {
  return ceil_div(shape.rows(), kRowsPerBlock);
}
std::int64_t pillar_parts(const PfnShape& shape) {
  return ceil_div(shape.pillars, kPillarsPerSumsBlock);
}

unsigned channel_tiles(const PfnShape& shape) {
  return static_cast<unsigned>(ceil_div(shape.channels, kChannelTile));
}

void check_shape(const PfnShape& shape, const char* op) {
  PS_CHECK(shape.pillars >= 0 && shape.slots >= 1 && shape.channels >= 1,
           "{}: expected points (P, N, 10) with P >= 0, N >= 1 and weight (C, 10) with C >= 1, "
           "given P = {}, N = {}, C = {}",
           op, shape.pillars, shape.slots, shape.channels);
  PS_CHECK(shape.rows() <= std::numeric_limits<std::int32_t>::max() &&
               shape.channels <= std::int64_t{65535} * kChannelTile,
           "{}: P * N = {} rows and C = {} channels exceed what the grid covers (2^31 rows, "
           "2097120 channels)",
           op, shape.rows(), shape.channels);
}

// The 10 weights of channel c, in registers.
struct ChannelWeights {
  float w[kFeatures];
};

// The per-channel constants of BatchNorm as the forward applies it and the backward inverts it.
struct ChannelNorm {
  float center;   // mean
  float inv_std;  // 1 / sqrt(variance + eps)
  float scale;    // gamma * inv_std
};

// What dL/dz of a channel needs besides z and the routed gradient g.
struct ChannelBackward {
  ChannelNorm norm;
  float mean_g;
  float mean_g_xhat;
};

}  // namespace

static __device__ __forceinline__ ChannelWeights load_weights(const float* weight, std::int64_t c) {
  ChannelWeights weights;
#pragma unroll
  for (int d = 0; d < kFeatures; ++d) weights.w[d] = weight[c * kFeatures + d];
  return weights;
}

// z = point . w, the linear layer's output for one row and channel.
static __device__ __forceinline__ float linear(const float* point, const ChannelWeights& weights) {
  float z = 0.0f;
#pragma unroll
  for (int d = 0; d < kFeatures; ++d) z += point[d] * weights.w[d];
  return z;
}

// Sum of v over the kRowGroups threads of a column (same threadIdx.x), in the order
// threadIdx.y = 0, 1, ...; threads with threadIdx.y == 0 hold the total. Every thread must call
// it; ends with a barrier so that it may be called again at once.
static __device__ __forceinline__ double column_sum(double v) {
  __shared__ double column[kRowGroups][kChannelTile];
  column[threadIdx.y][threadIdx.x] = v;
  __syncthreads();
  double total = 0.0;
  if (threadIdx.y == 0) {
    for (int group = 0; group < kRowGroups; ++group) total += column[group][threadIdx.x];
  }
  __syncthreads();
  return total;
}

static __device__ __forceinline__ ChannelNorm channel_norm(const float* mean,
                                                           const float* inv_std_or_variance,
                                                           bool from_variance, float eps,
                                                           const float* gamma, std::int64_t c) {
  const double inv_std = from_variance
                             ? 1.0 / sqrt(static_cast<double>(inv_std_or_variance[c]) + eps)
                             : static_cast<double>(inv_std_or_variance[c]);
  return ChannelNorm{mean[c], static_cast<float>(inv_std),
                     static_cast<float>(static_cast<double>(gamma[c]) * inv_std)};
}

// points (P, N, 10), weight (C, 10) -> shifts (C), partials (C, parts, 2): the sums of z - shift
// and (z - shift)^2 over the rows of block blockIdx.x, shift = z of row 0.
static __global__ void __launch_bounds__(kBlockSize)
    statistics_kernel(const float* points, const float* weight, PfnShape shape, std::int64_t parts,
                      double* shifts, double* partials) {
  const std::int64_t c = std::int64_t{blockIdx.y} * kChannelTile + threadIdx.x;
  const bool active = c < shape.channels;
  double sum = 0.0;
  double sum_squares = 0.0;
  double shift = 0.0;
  if (active) {
    const ChannelWeights weights = load_weights(weight, c);
    shift = sum_shift(linear(points, weights));
    const std::int64_t begin = std::int64_t{blockIdx.x} * kRowsPerBlock;
    const std::int64_t end =
        begin + kRowsPerBlock < shape.rows() ? begin + kRowsPerBlock : shape.rows();
    for (std::int64_t row = begin + threadIdx.y; row < end; row += kRowGroups) {
      const double d = static_cast<double>(linear(points + row * kFeatures, weights)) - shift;
      sum += d;
      sum_squares += d * d;
    }
  }
  sum = column_sum(sum);
  sum_squares = column_sum(sum_squares);
  if (active && threadIdx.y == 0) {
    double* pair = partials + 2 * (c * parts + blockIdx.x);
    pair[0] = sum;
    pair[1] = sum_squares;
    if (blockIdx.x == 0) shifts[c] = shift;
  }
}

// One thread per (pillar, channel): out = max over slots of ReLU(BatchNorm(z)), max_slot.
static __global__ void __launch_bounds__(kBlockSize)
    apply_max_kernel(const float* points, const float* weight, PfnShape shape, const float* mean,
                     const float* inv_std_or_variance, bool from_variance, float eps,
                     const float* gamma, const float* beta, float* out, std::int32_t* max_slot,
                     const std::int32_t* live_pillars) {
  const std::int64_t c = std::int64_t{blockIdx.y} * kChannelTile + threadIdx.x;
  const std::int64_t p = std::int64_t{blockIdx.x} * kRowGroups + threadIdx.y;
  if (c >= shape.channels || p >= shape.pillars) return;
  if (live_pillars != nullptr && p >= *live_pillars) return;  // inert: left as it is
  const ChannelWeights weights = load_weights(weight, c);
  const ChannelNorm norm = channel_norm(mean, inv_std_or_variance, from_variance, eps, gamma, c);
  const float shift = beta[c];
  const auto activation = [&](std::int64_t slot) {
    const float z = linear(points + (p * shape.slots + slot) * kFeatures, weights);
    const float a = (z - norm.center) * norm.scale + shift;
    return a < 0.0f ? 0.0f : a;  // NaN passes the ReLU
  };
  float best = activation(0);
  std::int32_t best_slot = 0;
  for (std::int64_t n = 1; n < shape.slots; ++n) {
    const float a = activation(n);
    const bool a_is_nan = a != a;
    const bool best_is_nan = best != best;
    if (a > best || (a_is_nan && !best_is_nan)) {  // torch.max: the first maximum, NaN wins
      best = a;
      best_slot = static_cast<std::int32_t>(n);
    }
  }
  out[p * shape.channels + c] = best;
  if (max_slot != nullptr) max_slot[p * shape.channels + c] = best > 0.0f ? best_slot : -1;
}

// d_out, max_slot (P, C) -> partials (C, parts, 2): sum g and sum g * xhat over the rows routed
// from the pillars of block blockIdx.x.
static __global__ void __launch_bounds__(kBlockSize)
    backward_sums_kernel(const float* d_out, const float* points, const float* weight,
                         PfnShape shape, const float* mean, const float* inv_std,
                         const std::int32_t* max_slot, std::int64_t parts, double* partials) {
  const std::int64_t c = std::int64_t{blockIdx.y} * kChannelTile + threadIdx.x;
  const bool active = c < shape.channels;
  double sum_g = 0.0;
  double sum_g_xhat = 0.0;
  if (active) {
    const ChannelWeights weights = load_weights(weight, c);
    const float center = mean[c];
    const float channel_inv_std = inv_std[c];
    const std::int64_t begin = std::int64_t{blockIdx.x} * kPillarsPerSumsBlock;
    const std::int64_t end =
        begin + kPillarsPerSumsBlock < shape.pillars ? begin + kPillarsPerSumsBlock : shape.pillars;
    for (std::int64_t p = begin + threadIdx.y; p < end; p += kRowGroups) {
      const std::int32_t slot = max_slot[p * shape.channels + c];
      if (slot < 0 || slot >= shape.slots) continue;
      const float g = d_out[p * shape.channels + c];
      const float z = linear(points + (p * shape.slots + slot) * kFeatures, weights);
      sum_g += g;
      sum_g_xhat += g * ((z - center) * channel_inv_std);
    }
  }
  sum_g = column_sum(sum_g);
  sum_g_xhat = column_sum(sum_g_xhat);
  if (active && threadIdx.y == 0) {
    double* pair = partials + 2 * (c * parts + blockIdx.x);
    pair[0] = sum_g;
    pair[1] = sum_g_xhat;
  }
}

static __device__ __forceinline__ ChannelBackward channel_backward(const float* gamma,
                                                                   const float* mean,
                                                                   const float* inv_std,
                                                                   const double* coefficients,
                                                                   std::int64_t c) {
  return ChannelBackward{channel_norm(mean, inv_std, false, 0.0f, gamma, c),
                         static_cast<float>(coefficients[2 * c]),
                         static_cast<float>(coefficients[2 * c + 1])};
}

// dL/dz of a row and channel: BatchNorm's backward of the routed gradient g.
static __device__ __forceinline__ float dz_of(float z, float g, const ChannelBackward& k) {
  const float xhat = (z - k.norm.center) * k.norm.inv_std;
  return ((g - k.mean_g) - xhat * k.mean_g_xhat) * k.norm.scale;
}

// The gradient reaching row (p, n), channel c, from the max: d_out(p, c) if n is its slot.
static __device__ __forceinline__ float routed_gradient(const float* d_out,
                                                        const std::int32_t* max_slot,
                                                        const PfnShape& shape, std::int64_t p,
                                                        std::int64_t n, std::int64_t c) {
  return max_slot[p * shape.channels + c] == n ? d_out[p * shape.channels + c] : 0.0f;
}

// -> weight_partials (C * 10, parts): sum over the rows of block blockIdx.x of dz * point.
static __global__ void __launch_bounds__(kBlockSize)
    weight_partials_kernel(const float* d_out, const float* points, const float* weight,
                           PfnShape shape, const float* gamma, const float* mean,
                           const float* inv_std, const double* coefficients,
                           const std::int32_t* max_slot, std::int64_t parts,
                           double* weight_partials) {
  const std::int64_t c = std::int64_t{blockIdx.y} * kChannelTile + threadIdx.x;
  const bool active = c < shape.channels;
  // Sums over this thread's 128 rows in float, wider sums in double.
  float sums[kFeatures] = {};
  if (active) {
    const ChannelWeights weights = load_weights(weight, c);
    const ChannelBackward k = channel_backward(gamma, mean, inv_std, coefficients, c);
    const std::int64_t begin = std::int64_t{blockIdx.x} * kRowsPerBlock;
    const std::int64_t end =
        begin + kRowsPerBlock < shape.rows() ? begin + kRowsPerBlock : shape.rows();
    std::int64_t row = begin + threadIdx.y;
    std::int64_t p = row / shape.slots;
    std::int64_t n = row - p * shape.slots;
    for (; row < end; row += kRowGroups) {
      const float* point = points + row * kFeatures;
      const float dz =
          dz_of(linear(point, weights), routed_gradient(d_out, max_slot, shape, p, n, c), k);
#pragma unroll
      for (int d = 0; d < kFeatures; ++d) sums[d] += dz * point[d];
      for (n += kRowGroups; n >= shape.slots; n -= shape.slots) ++p;
    }
  }
  for (int d = 0; d < kFeatures; ++d) {
    const double total = column_sum(static_cast<double>(sums[d]));
    if (active && threadIdx.y == 0)
      weight_partials[(c * kFeatures + d) * parts + blockIdx.x] = total;
  }
}

// One warp per weight (c, d): d_weight = the sum of its parts, in order.
static __global__ void __launch_bounds__(kBlockSize)
    weight_gradient_kernel(const double* weight_partials, std::int64_t weights, std::int64_t parts,
                           float* d_weight) {
  const std::int64_t i =
      std::int64_t{blockIdx.x} * (kBlockSize / kWarpSize) + threadIdx.x / kWarpSize;
  const int lane = static_cast<int>(threadIdx.x % kWarpSize);
  if (i >= weights) return;  // whole warps leave together
  const double total = warp_sum_strided(weight_partials + i * parts, parts, 1, lane);
  if (lane == 0) d_weight[i] = static_cast<float>(total);
}

// One thread per row (p, n): d_points(p, n, :) = sum over channels c of dz(p, n, c) * w_c. The
// channels' weights and constants pass through shared memory 32 at a time.
static __global__ void __launch_bounds__(kBlockSize)
    points_gradient_kernel(const float* d_out, const float* points, const float* weight,
                           PfnShape shape, const float* gamma, const float* mean,
                           const float* inv_std, const double* coefficients,
                           const std::int32_t* max_slot, float* d_points) {
  __shared__ ChannelWeights tile_weights[kChannelTile];
  __shared__ ChannelBackward tile_backward[kChannelTile];
  const std::int64_t row = std::int64_t{blockIdx.x} * kBlockSize + threadIdx.x;
  const bool active = row < shape.rows();
  const std::int64_t p = active ? row / shape.slots : 0;
  const std::int64_t n = row - p * shape.slots;
  float point[kFeatures] = {};
  float sums[kFeatures] = {};
  if (active) {
#pragma unroll
    for (int d = 0; d < kFeatures; ++d) point[d] = points[row * kFeatures + d];
  }
  for (std::int64_t c0 = 0; c0 < shape.channels; c0 += kChannelTile) {
    const std::int64_t tile =
        shape.channels - c0 < kChannelTile ? shape.channels - c0 : kChannelTile;
    __syncthreads();  // the previous tile is no longer read
    if (threadIdx.x < tile) {
      tile_weights[threadIdx.x] = load_weights(weight, c0 + threadIdx.x);
      tile_backward[threadIdx.x] =
          channel_backward(gamma, mean, inv_std, coefficients, c0 + threadIdx.x);
    }
    __syncthreads();
    if (!active) continue;
    for (std::int64_t j = 0; j < tile; ++j) {
      const ChannelWeights& weights = tile_weights[j];
      const float dz =
          dz_of(linear(point, weights), routed_gradient(d_out, max_slot, shape, p, n, c0 + j),
                tile_backward[j]);
#pragma unroll
      for (int d = 0; d < kFeatures; ++d) sums[d] += dz * weights.w[d];
    }
  }
  if (active) {
#pragma unroll
    for (int d = 0; d < kFeatures; ++d) d_points[row * kFeatures + d] = sums[d];
  }
}

std::int64_t pfn_workspace_doubles(const PfnShape& shape) {
  check_shape(shape, "pfn_workspace_doubles");
  // At least one part: synchronised statistics are written back as one (batchnorm.cuh).
  const std::int64_t parts = row_parts(shape);
  const std::int64_t forward = shape.channels + 2 * shape.channels * (parts > 0 ? parts : 1);
  const std::int64_t backward = 2 * shape.channels * pillar_parts(shape) + 2 * shape.channels +
                                kFeatures * shape.channels * row_parts(shape);
  return forward > backward ? forward : backward;
}

void pfn_forward_train(const float* points, const float* weight, const PfnShape& shape,
                       const float* gamma, const float* beta, float eps, float momentum,
                       float* running_mean, float* running_var, float* out, std::int32_t* max_slot,
                       float* save_mean, float* save_inv_std, double* workspace,
                       cudaStream_t stream, ReplicaSum* replicas) {
  const char* op = "pfn_forward_train";
  check_shape(shape, op);
  PS_CHECK(shape.rows() != 1 || replicas != nullptr,
           "{}: BatchNorm needs more than 1 row (P * N) when training, given P = {}, N = {}", op,
           shape.pillars, shape.slots);
  PS_CHECK(weight != nullptr && gamma != nullptr && beta != nullptr && workspace != nullptr,
           "{}: weight ({} floats), gamma, beta ({} floats) and the workspace ({} doubles) must "
           "be device memory",
           op, shape.channels * kFeatures, shape.channels, pfn_workspace_doubles(shape));
  PS_CHECK(shape.pillars == 0 || (points != nullptr && out != nullptr && max_slot != nullptr),
           "{}: points ({} floats), out and max_slot ({} values each) must be device memory", op,
           shape.rows() * kFeatures, shape.pillars * shape.channels);
  const std::int64_t parts = row_parts(shape);
  double* shifts = workspace;
  double* partials = workspace + shape.channels;
  if (shape.pillars > 0) {
    launch_kernel(statistics_kernel, dim3(static_cast<unsigned>(parts), channel_tiles(shape)),
                  dim3(kChannelTile, kRowGroups), 0, stream, points, weight, shape, parts, shifts,
                  partials);
  }
  batchnorm_finalize_statistics(shifts, partials, shape.channels, parts, shape.rows(), eps,
                                momentum, running_mean, running_var, save_mean, save_inv_std,
                                stream, replicas);
  if (shape.pillars > 0) {
    launch_kernel(
        apply_max_kernel,
        dim3(static_cast<unsigned>(ceil_div(shape.pillars, kRowGroups)), channel_tiles(shape)),
        dim3(kChannelTile, kRowGroups), 0, stream, points, weight, shape, save_mean, save_inv_std,
        false, eps, gamma, beta, out, max_slot, nullptr);
  }
}

void pfn_forward_eval(const float* points, const float* weight, const PfnShape& shape,
                      const float* gamma, const float* beta, const float* running_mean,
                      const float* running_var, float eps, float* out, std::int32_t* max_slot,
                      cudaStream_t stream, const std::int32_t* live_pillars) {
  const char* op = "pfn_forward_eval";
  check_shape(shape, op);
  PS_CHECK(eps > 0.0f, "{}: expected eps > 0, given {}", op, eps);
  if (shape.pillars == 0) return;
  PS_CHECK(points != nullptr && weight != nullptr && gamma != nullptr && beta != nullptr &&
               running_mean != nullptr && running_var != nullptr && out != nullptr,
           "{}: points ({} floats), weight ({} floats), gamma, beta, running_mean, running_var "
           "({} floats each) and out ({} floats) must be device memory",
           op, shape.rows() * kFeatures, shape.channels * kFeatures, shape.channels,
           shape.pillars * shape.channels);
  launch_kernel(
      apply_max_kernel,
      dim3(static_cast<unsigned>(ceil_div(shape.pillars, kRowGroups)), channel_tiles(shape)),
      dim3(kChannelTile, kRowGroups), 0, stream, points, weight, shape, running_mean, running_var,
      true, eps, gamma, beta, out, max_slot, live_pillars);
}

void pfn_backward(const float* d_out, const float* points, const float* weight,
                  const PfnShape& shape, const float* gamma, const float* save_mean,
                  const float* save_inv_std, const std::int32_t* max_slot, float* d_points,
                  float* d_weight, float* d_gamma, float* d_beta, double* workspace,
                  cudaStream_t stream, ReplicaSum* replicas) {
  const char* op = "pfn_backward";
  check_shape(shape, op);
  PS_CHECK(weight != nullptr && gamma != nullptr && save_mean != nullptr &&
               save_inv_std != nullptr && d_weight != nullptr && d_gamma != nullptr &&
               d_beta != nullptr && workspace != nullptr,
           "{}: weight, d_weight ({} floats), gamma, save_mean, save_inv_std, d_gamma, d_beta ({} "
           "floats each) and the workspace ({} doubles) must be device memory",
           op, shape.channels * kFeatures, shape.channels, pfn_workspace_doubles(shape));
  PS_CHECK(shape.pillars == 0 || (d_out != nullptr && points != nullptr && max_slot != nullptr),
           "{}: d_out and max_slot ({} values each) and points ({} floats) must be device memory",
           op, shape.pillars * shape.channels, shape.rows() * kFeatures);
  const std::int64_t sums_parts = pillar_parts(shape);
  const std::int64_t weight_parts = row_parts(shape);
  double* partials = workspace;
  double* coefficients = partials + 2 * shape.channels * sums_parts;
  double* weight_partials = coefficients + 2 * shape.channels;
  const dim3 tile_block(kChannelTile, kRowGroups);
  if (shape.pillars > 0) {
    launch_kernel(backward_sums_kernel,
                  dim3(static_cast<unsigned>(sums_parts), channel_tiles(shape)), tile_block, 0,
                  stream, d_out, points, weight, shape, save_mean, save_inv_std, max_slot,
                  sums_parts, partials);
  }
  batchnorm_finalize_backward(partials, shape.channels, sums_parts, shape.rows(), d_gamma, d_beta,
                              coefficients, stream, replicas);
  if (shape.pillars > 0) {
    launch_kernel(weight_partials_kernel,
                  dim3(static_cast<unsigned>(weight_parts), channel_tiles(shape)), tile_block, 0,
                  stream, d_out, points, weight, shape, gamma, save_mean, save_inv_std,
                  coefficients, max_slot, weight_parts, weight_partials);
  }
  const std::int64_t weights = shape.channels * kFeatures;
  launch_kernel(weight_gradient_kernel,
                dim3(static_cast<unsigned>(ceil_div(weights, kBlockSize / kWarpSize))),
                dim3(kBlockSize), 0, stream, weight_partials, weights, weight_parts, d_weight);
  if (d_points != nullptr && shape.pillars > 0) {
    launch_kernel(points_gradient_kernel,
                  dim3(static_cast<unsigned>(ceil_div(shape.rows(), kBlockSize))), dim3(kBlockSize),
                  0, stream, d_out, points, weight, shape, gamma, save_mean, save_inv_std,
                  coefficients, max_slot, d_points);
  }
}

}  // namespace pillarseg::cuda
