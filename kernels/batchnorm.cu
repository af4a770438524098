// BatchNorm (+ ReLU) over the channels of x (B, C, S), see batchnorm.cuh. Every pass walks x as
// B * C planes of S values cut into chunks of kChunk values, one block per (plane, chunk), so
// the grid grows with the data and each block knows its channel without a division per element.
// Planes are read with float4 loads when S is a multiple of 4 and every array is 16-byte aligned.
//   training forward: [statistics partials] per block: sums of (x - shift) and (x - shift)^2 in
//                     double, shift = the channel's first value (one read of x, yet no
//                     cancellation for a large mean against a small spread);
//                     [finalize] one warp per channel adds its blocks' partials in a fixed order;
//                     [apply] y = (x - mean) * scale + beta (then ReLU).
//   backward:         [partials] per block: sums of g and g * xhat; [finalize] dgamma, dbeta;
//                     [input gradient] dx.
//   synchronised:     between [partials] and [finalize], each channel's parts added in order,
//                     summed over the replicas (twice in the forward: the values' sums and count,
//                     then the squares about their common mean) and finalized as one part; on the
//                     host for a ReplicaSum, in one thread per channel for a DeviceReplicaSum.
#include "kernels/batchnorm.cuh"

#include <cmath>
#include <cstdint>
#include <initializer_list>
#include <limits>
#include <vector>

#include "kernels/block_reduce.cuh"
#include "kernels/common.cuh"
#include "kernels/replica_sum.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kBlockSize = 256;
// Values of a plane per block: 16 per thread, enough to hide memory latency.
constexpr std::int64_t kChunk = 4096;
constexpr int kChannelsPerFinalizeBlock = kBlockSize / kWarpSize;

// How the passes cut x (B, C, S) into blocks.
struct PlaneChunks {
  std::int64_t channels = 0;
  std::int64_t inner = 0;
  std::int64_t chunks_per_plane = 0;
  bool vectorized = false;  // float4 loads and stores
};

PlaneChunks plane_chunks(const PlanarShape& shape, std::initializer_list<const float*> arrays) {
  bool aligned = shape.inner % 4 == 0;
  for (const float* p : arrays) {
    if (p != nullptr && reinterpret_cast<std::uintptr_t>(p) % 16 != 0) aligned = false;
  }
  return PlaneChunks{shape.channels, shape.inner, ceil_div(shape.inner, kChunk), aligned};
}

// Blocks per channel whose partial sums the finalize adds: one per (batch item, chunk).
std::int64_t parts_per_channel(const PlanarShape& shape) {
  return shape.batch * ceil_div(shape.inner, kChunk);
}

dim3 chunk_grid(const PlanarShape& shape, const char* op) {
  const std::int64_t blocks = shape.batch * shape.channels * ceil_div(shape.inner, kChunk);
  PS_CHECK(blocks <= std::numeric_limits<int>::max(),
           "{}: x of (B, C, S) = ({}, {}, {}) needs {} blocks, more than a grid holds; split the "
           "batch",
           op, shape.batch, shape.channels, shape.inner, blocks);
  return dim3(static_cast<unsigned>(blocks));
}

void check_shape(const PlanarShape& shape, const char* op) {
  PS_CHECK(shape.batch >= 0 && shape.channels >= 1 && shape.inner >= 0,
           "{}: expected x of (B, C, S = H * W) with B, S >= 0 and C >= 1, given ({}, {}, {})", op,
           shape.batch, shape.channels, shape.inner);
}

void check_eps_momentum(float eps, float momentum, const char* op) {
  PS_CHECK(eps > 0.0f, "{}: expected eps > 0, given {}", op, eps);
  PS_CHECK(momentum >= 0.0f && momentum <= 1.0f, "{}: expected momentum in [0, 1], given {}", op,
           momentum);
}

// A block's place: its plane (batch item, channel) and the values [begin, end) of the plane.
struct ChunkPlace {
  std::int64_t plane;
  std::int64_t batch;
  std::int64_t channel;
  std::int64_t part;  // the block's index among the parts of its channel
  std::int64_t begin;
  std::int64_t end;
};

}  // namespace

static __device__ __forceinline__ ChunkPlace chunk_place(const PlaneChunks& layout) {
  const std::int64_t block = blockIdx.x;
  const std::int64_t plane = block / layout.chunks_per_plane;
  const std::int64_t chunk = block - plane * layout.chunks_per_plane;
  const std::int64_t batch = plane / layout.channels;
  const std::int64_t begin = chunk * kChunk;
  const std::int64_t end = begin + kChunk < layout.inner ? begin + kChunk : layout.inner;
  return ChunkPlace{
      plane, batch, plane - batch * layout.channels, batch * layout.chunks_per_plane + chunk,
      begin, end};
}

// Calls visit(s) for the values s of [begin, end) this thread owns, or visit4(s) for the groups
// of four s..s+3 when the layout is vectorized (begin and end are then multiples of 4).
template <class Visit, class Visit4>
static __device__ __forceinline__ void for_each_in_chunk(const PlaneChunks& layout,
                                                         const ChunkPlace& place, Visit visit,
                                                         Visit4 visit4) {
  if (layout.vectorized) {
    for (std::int64_t s = place.begin + 4 * threadIdx.x; s < place.end; s += 4 * kBlockSize) {
      visit4(s);
    }
  } else {
    for (std::int64_t s = place.begin + threadIdx.x; s < place.end; s += kBlockSize) visit(s);
  }
}

static __device__ __forceinline__ float normalize(float x, float center, float scale, float shift,
                                                  bool relu) {
  const float y = (x - center) * scale + shift;
  return relu && y < 0.0f ? 0.0f : y;  // NaN passes the ReLU
}

// The gradient reaching the BatchNorm output: dy, blocked where the fused ReLU output y is not
// > 0. Without a ReLU the kernels pass y = 1.
static __device__ __forceinline__ float relu_gate(float y, float dy) {
  return y > 0.0f ? dy : 0.0f;
}

// The ReLU output at s, s..s+3: y's, or 1 (passing everything) without a ReLU.
static __device__ __forceinline__ float output_at(const float* y, std::int64_t s) {
  return y == nullptr ? 1.0f : y[s];
}
static __device__ __forceinline__ float4 output4_at(const float* y, std::int64_t s) {
  return y == nullptr ? make_float4(1.0f, 1.0f, 1.0f, 1.0f)
                      : *reinterpret_cast<const float4*>(y + s);
}

// x (B, C, S) -> shifts (C), partials (C, parts, 2): the shifted sums of this block's values.
static __global__ void __launch_bounds__(kBlockSize)
    statistics_partials_kernel(const float* x, PlaneChunks layout, std::int64_t parts,
                               double* shifts, double* partials) {
  const ChunkPlace place = chunk_place(layout);
  const double shift = sum_shift(x[place.channel * layout.inner]);
  const float* plane = x + place.plane * layout.inner;
  double sum = 0.0;
  double sum_squares = 0.0;
  const auto add = [&](float v) {
    const double d = static_cast<double>(v) - shift;
    sum += d;
    sum_squares += d * d;
  };
  for_each_in_chunk(
      layout, place, [&](std::int64_t s) { add(plane[s]); },
      [&](std::int64_t s) {
        const float4 v = *reinterpret_cast<const float4*>(plane + s);
        add(v.x);
        add(v.y);
        add(v.z);
        add(v.w);
      });
  sum = block_sum<kBlockSize>(sum);
  sum_squares = block_sum<kBlockSize>(sum_squares);
  if (threadIdx.x == 0) {
    double* pair = partials + 2 * (place.channel * parts + place.part);
    pair[0] = sum;
    pair[1] = sum_squares;
    if (place.part == 0) shifts[place.channel] = shift;
  }
}

// One warp per channel: partials -> mean, biased variance -> saved and running statistics. The
// values' count is `count`, or *total_count where that is given (a synchronised BatchNorm's count
// of all replicas' values, summed on the device).
static __global__ void __launch_bounds__(kBlockSize)
    finalize_statistics_kernel(const double* shifts, const double* partials, std::int64_t channels,
                               std::int64_t parts, std::int64_t count, const double* total_count,
                               float eps, float momentum, float* running_mean, float* running_var,
                               float* save_mean, float* save_inv_std) {
  const std::int64_t channel =
      std::int64_t{blockIdx.x} * kChannelsPerFinalizeBlock + threadIdx.x / kWarpSize;
  const int lane = static_cast<int>(threadIdx.x % kWarpSize);
  if (channel >= channels) return;  // whole warps leave together
  const double* pairs = partials + 2 * channel * parts;
  const double sum = warp_sum_strided(pairs, parts, 2, lane);
  const double sum_squares = warp_sum_strided(pairs + 1, parts, 2, lane);
  if (lane != 0) return;
  double mean = 0.0;
  double variance = 0.0;
  const double n = total_count != nullptr ? *total_count : static_cast<double>(count);
  if (n > 0) {
    mean = shifts[channel] + sum / n;
    // sum (v - mean)^2 = sum (v - shift)^2 - (sum (v - shift))^2 / n, which rounding can push
    // a little below 0 for a constant channel; NaN stays NaN.
    variance = (sum_squares - sum * sum / n) / n;
    variance = variance < 0.0 ? 0.0 : variance;
    const double m = momentum;
    const double unbiased_variance = variance * (n / (n - 1.0));
    running_mean[channel] =
        static_cast<float>((1.0 - m) * static_cast<double>(running_mean[channel]) + m * mean);
    running_var[channel] = static_cast<float>(
        (1.0 - m) * static_cast<double>(running_var[channel]) + m * unbiased_variance);
  }
  save_mean[channel] = static_cast<float>(mean);
  save_inv_std[channel] = static_cast<float>(1.0 / sqrt(variance + static_cast<double>(eps)));
}

// x (B, C, S) -> y (B, C, S) = normalize(x). The channel's scale is gamma * inv_std, where
// inv_std is given (training: the batch statistics) or computed from the variance (evaluation:
// the running statistics).
static __global__ void __launch_bounds__(kBlockSize)
    apply_kernel(const float* x, PlaneChunks layout, const float* mean,
                 const float* inv_std_or_variance, bool from_variance, float eps,
                 const float* gamma, const float* beta, bool relu, float* y) {
  const ChunkPlace place = chunk_place(layout);
  const std::int64_t c = place.channel;
  const double inv_std = from_variance
                             ? 1.0 / sqrt(static_cast<double>(inv_std_or_variance[c]) + eps)
                             : static_cast<double>(inv_std_or_variance[c]);
  const float center = mean[c];
  const auto scale = static_cast<float>(static_cast<double>(gamma[c]) * inv_std);
  const float shift = beta[c];
  const float* in = x + place.plane * layout.inner;
  float* out = y + place.plane * layout.inner;
  for_each_in_chunk(
      layout, place, [&](std::int64_t s) { out[s] = normalize(in[s], center, scale, shift, relu); },
      [&](std::int64_t s) {
        const float4 v = *reinterpret_cast<const float4*>(in + s);
        *reinterpret_cast<float4*>(out + s) = make_float4(
            normalize(v.x, center, scale, shift, relu), normalize(v.y, center, scale, shift, relu),
            normalize(v.z, center, scale, shift, relu), normalize(v.w, center, scale, shift, relu));
      });
}

// dy, x, y (B, C, S) -> partials (C, parts, 2): sums of g and g * xhat over this block's values.
static __global__ void __launch_bounds__(kBlockSize)
    backward_partials_kernel(const float* dy, const float* x, const float* y, PlaneChunks layout,
                             std::int64_t parts, const float* mean, const float* inv_std,
                             double* partials) {
  const ChunkPlace place = chunk_place(layout);
  const float center = mean[place.channel];
  const float channel_inv_std = inv_std[place.channel];
  const std::int64_t offset = place.plane * layout.inner;
  const float* gradient = dy + offset;
  const float* input = x + offset;
  const float* output = y == nullptr ? nullptr : y + offset;
  double sum_g = 0.0;
  double sum_g_xhat = 0.0;
  const auto add = [&](float v, float o, float d) {
    const float g = relu_gate(o, d);
    sum_g += g;
    sum_g_xhat += g * ((v - center) * channel_inv_std);
  };
  for_each_in_chunk(
      layout, place, [&](std::int64_t s) { add(input[s], output_at(output, s), gradient[s]); },
      [&](std::int64_t s) {
        const float4 v = *reinterpret_cast<const float4*>(input + s);
        const float4 o = output4_at(output, s);
        const float4 d = *reinterpret_cast<const float4*>(gradient + s);
        add(v.x, o.x, d.x);
        add(v.y, o.y, d.y);
        add(v.z, o.z, d.z);
        add(v.w, o.w, d.w);
      });
  sum_g = block_sum<kBlockSize>(sum_g);
  sum_g_xhat = block_sum<kBlockSize>(sum_g_xhat);
  if (threadIdx.x == 0) {
    double* pair = partials + 2 * (place.channel * parts + place.part);
    pair[0] = sum_g;
    pair[1] = sum_g_xhat;
  }
}

// One warp per channel: partials -> dgamma, dbeta, coefficients (mean g, mean g * xhat).
static __global__ void __launch_bounds__(kBlockSize)
    finalize_backward_kernel(const double* partials, std::int64_t channels, std::int64_t parts,
                             std::int64_t count, float* dgamma, float* dbeta,
                             double* coefficients) {
  const std::int64_t channel =
      std::int64_t{blockIdx.x} * kChannelsPerFinalizeBlock + threadIdx.x / kWarpSize;
  const int lane = static_cast<int>(threadIdx.x % kWarpSize);
  if (channel >= channels) return;  // whole warps leave together
  const double* pairs = partials + 2 * channel * parts;
  const double sum_g = warp_sum_strided(pairs, parts, 2, lane);
  const double sum_g_xhat = warp_sum_strided(pairs + 1, parts, 2, lane);
  if (lane != 0) return;
  dbeta[channel] = static_cast<float>(sum_g);
  dgamma[channel] = static_cast<float>(sum_g_xhat);
  const double n = count > 0 ? static_cast<double>(count) : 1.0;
  coefficients[2 * channel] = sum_g / n;
  coefficients[2 * channel + 1] = sum_g_xhat / n;
}

// dy, x, y (B, C, S) -> dx (B, C, S) = gamma * inv_std * (g - mean g - xhat * mean g xhat).
static __global__ void __launch_bounds__(kBlockSize)
    input_gradient_kernel(const float* dy, const float* x, const float* y, PlaneChunks layout,
                          const float* gamma, const float* mean, const float* inv_std,
                          const double* coefficients, float* dx) {
  const ChunkPlace place = chunk_place(layout);
  const std::int64_t c = place.channel;
  const float center = mean[c];
  const float channel_inv_std = inv_std[c];
  const auto mean_g = static_cast<float>(coefficients[2 * c]);
  const auto mean_g_xhat = static_cast<float>(coefficients[2 * c + 1]);
  const auto scale = static_cast<float>(static_cast<double>(gamma[c]) * channel_inv_std);
  const std::int64_t offset = place.plane * layout.inner;
  const float* gradient = dy + offset;
  const float* input = x + offset;
  const float* output = y == nullptr ? nullptr : y + offset;
  float* result = dx + offset;
  const auto dx_of = [&](float v, float o, float d) {
    const float g = relu_gate(o, d);
    const float xhat = (v - center) * channel_inv_std;
    return ((g - mean_g) - xhat * mean_g_xhat) * scale;
  };
  for_each_in_chunk(
      layout, place,
      [&](std::int64_t s) { result[s] = dx_of(input[s], output_at(output, s), gradient[s]); },
      [&](std::int64_t s) {
        const float4 v = *reinterpret_cast<const float4*>(input + s);
        const float4 o = output4_at(output, s);
        const float4 d = *reinterpret_cast<const float4*>(gradient + s);
        *reinterpret_cast<float4*>(result + s) = make_float4(
            dx_of(v.x, o.x, d.x), dx_of(v.y, o.y, d.y), dx_of(v.z, o.z, d.z), dx_of(v.w, o.w, d.w));
      });
}

// ---- synchronised BatchNorm: this replica's sums combined with the other replicas' ----
// The per-channel steps below run on the host after the sums are brought there, for a
// ReplicaSum, or in one thread per channel on the device, for a DeviceReplicaSum (nothing leaves
// the device): the same code, so the same bits. On a GPU the products and sums are rounded one
// at a time (nvcc would fuse them into fmas, which the host code of the GPU build, compiled for
// baseline x86-64, has none of); in the emulation both paths are the same host code.

static __host__ __device__ __forceinline__ double rounded_product(double a, double b) {
#if defined(__CUDA_ARCH__)
  return __dmul_rn(a, b);
#else
  return a * b;
#endif
}

static __host__ __device__ __forceinline__ double rounded_sum(double a, double b) {
#if defined(__CUDA_ARCH__)
  return __dadd_rn(a, b);
#else
  return a + b;
#endif
}

static __host__ __device__ __forceinline__ double rounded_difference(double a, double b) {
#if defined(__CUDA_ARCH__)
  return __dsub_rn(a, b);
#else
  return a - b;
#endif
}

namespace {

// The pairs of a channel's parts added in part order j = 0, 1, ... (none for parts = 0).
struct PairSum {
  double first = 0.0;
  double second = 0.0;
};

}  // namespace

static __host__ __device__ __forceinline__ PairSum add_parts_in_order(const double* partials,
                                                                      std::int64_t channel,
                                                                      std::int64_t parts) {
  const double* pairs = partials + 2 * channel * parts;
  PairSum total;
  for (std::int64_t j = 0; j < parts; ++j) {
    total.first = rounded_sum(total.first, pairs[2 * j]);
    total.second = rounded_sum(total.second, pairs[2 * j + 1]);
  }
  return total;
}

// Statistics, step 1: this replica's sum of the channel's `count` values, count * shift +
// sum (v - shift) (0 without values: parts = 0). Summed over the replicas with the count.
static __host__ __device__ __forceinline__ double local_sum(const double* shifts,
                                                            const double* partials,
                                                            std::int64_t channel,
                                                            std::int64_t parts, double count) {
  if (parts == 0) return 0.0;
  return rounded_sum(rounded_product(count, shifts[channel]),
                     add_parts_in_order(partials, channel, parts).first);
}

// Statistics, step 2, from totals (C + 1: step 1's sums over the replicas, then their count):
// the mean of all replicas' values, written to shifts[channel], and this replica's
// sum (v - mean)^2 = S2 - 2 d S1 + count d^2 with d = mean - shift (exact algebra that keeps the
// shift's precision), written as one part about the mean: pair = (0, that). Summed over the
// replicas, the pairs are the statistics of all values.
static __host__ __device__ __forceinline__ void squares_about_mean(
    double* shifts, const double* partials, std::int64_t channel, std::int64_t channels,
    std::int64_t parts, double count, const double* totals, double* pair) {
  const double n = totals[channels];
  const double mean = n > 0 ? totals[channel] / n : 0.0;
  double squares = 0.0;
  if (parts > 0) {
    const PairSum s = add_parts_in_order(partials, channel, parts);
    const double d = rounded_difference(mean, shifts[channel]);
    squares =
        rounded_sum(rounded_difference(s.second, rounded_product(rounded_product(2.0, d), s.first)),
                    rounded_product(rounded_product(count, d), d));
  }
  shifts[channel] = mean;
  pair[0] = 0.0;
  pair[1] = squares;
}

// Backward, step 1: this replica's sums of g and of g * xhat over the channel, written to
// totals[channel] and totals[channels + channel]; totals[2 C] holds the count.
static __host__ __device__ __forceinline__ void local_backward_sums(const double* partials,
                                                                    std::int64_t channel,
                                                                    std::int64_t channels,
                                                                    std::int64_t parts,
                                                                    double* totals) {
  const PairSum s = add_parts_in_order(partials, channel, parts);
  totals[channel] = s.first;
  totals[channels + channel] = s.second;
}

// Backward, step 2, from the totals summed over the replicas: the coefficients of all replicas'
// values (a count of 0 divides by 1, as the single-process finalize does).
static __host__ __device__ __forceinline__ void combined_coefficients(const double* totals,
                                                                      std::int64_t channel,
                                                                      std::int64_t channels,
                                                                      double* coefficients) {
  const double n = totals[2 * channels] > 0 ? totals[2 * channels] : 1.0;
  coefficients[2 * channel] = totals[channel] / n;
  coefficients[2 * channel + 1] = totals[channels + channel] / n;
}

// The steps on the device, one thread per channel.
static __device__ __forceinline__ std::int64_t channel_of_thread() {
  return std::int64_t{blockIdx.x} * kBlockSize + threadIdx.x;
}

static __global__ void __launch_bounds__(kBlockSize)
    local_sums_kernel(const double* shifts, const double* partials, std::int64_t channels,
                      std::int64_t parts, double count, double* totals) {
  const std::int64_t channel = channel_of_thread();
  if (channel == 0) totals[channels] = count;
  if (channel < channels) totals[channel] = local_sum(shifts, partials, channel, parts, count);
}

static __global__ void __launch_bounds__(kBlockSize)
    squares_about_mean_kernel(double* shifts, const double* partials, std::int64_t channels,
                              std::int64_t parts, double count, const double* totals,
                              double* pairs) {
  const std::int64_t channel = channel_of_thread();
  if (channel >= channels) return;
  squares_about_mean(shifts, partials, channel, channels, parts, count, totals,
                     pairs + 2 * channel);
}

static __global__ void __launch_bounds__(kBlockSize)
    local_backward_sums_kernel(const double* partials, std::int64_t channels, std::int64_t parts,
                               double count, double* totals) {
  const std::int64_t channel = channel_of_thread();
  if (channel == 0) totals[2 * channels] = count;
  if (channel < channels) local_backward_sums(partials, channel, channels, parts, totals);
}

static __global__ void __launch_bounds__(kBlockSize)
    combined_coefficients_kernel(const double* totals, std::int64_t channels,
                                 double* coefficients) {
  const std::int64_t channel = channel_of_thread();
  if (channel < channels) combined_coefficients(totals, channel, channels, coefficients);
}

std::int64_t batchnorm_workspace_doubles(const PlanarShape& shape) {
  check_shape(shape, "batchnorm_workspace_doubles");
  // At least one part: synchronised statistics are written back as one (see finalize).
  const std::int64_t parts = parts_per_channel(shape);
  return 2 * shape.channels * (parts > 0 ? parts : 1) + 2 * shape.channels;
}

namespace {

dim3 channel_grid(std::int64_t channels) {
  return dim3(static_cast<unsigned>(ceil_div(channels, std::int64_t{kBlockSize})));
}

// A ReplicaSum's path: the sums brought to the host, combined there and written back.
template <class T>
std::vector<T> to_host(const T* device, std::int64_t n, cudaStream_t stream) {
  std::vector<T> host(static_cast<std::size_t>(n));
  if (n > 0) {
    PS_CUDA_CHECK(cudaMemcpyAsync(host.data(), device, host.size() * sizeof(T),
                                  cudaMemcpyDeviceToHost, stream));
    PS_CUDA_CHECK(cudaStreamSynchronize(stream));
  }
  return host;
}

template <class T>
void to_device(const std::vector<T>& host, T* device, cudaStream_t stream) {
  PS_CUDA_CHECK(cudaMemcpyAsync(device, host.data(), host.size() * sizeof(T),
                                cudaMemcpyHostToDevice, stream));
  PS_CUDA_CHECK(cudaStreamSynchronize(stream));
}

// This replica's shifted sums -> the statistics of all replicas' values, written back as one
// part about the common mean (shifts = mean, pair 0 = (0, sum (v - mean)^2)); count becomes the
// count of all replicas' values. `parts` is 0 when this replica has no values.
void combine_statistics(double* shifts, double* partials, std::int64_t channels,
                        std::int64_t parts, std::int64_t& count, ReplicaSum& replicas,
                        cudaStream_t stream) {
  const auto c_count = static_cast<std::size_t>(channels);
  std::vector<double> shift =
      parts > 0 ? to_host(shifts, channels, stream) : std::vector<double>(c_count, 0.0);
  const std::vector<double> pairs = to_host(partials, 2 * channels * parts, stream);
  const auto n_local = static_cast<double>(count);
  std::vector<double> totals(c_count + 1);
  for (std::int64_t c = 0; c < channels; ++c) {
    totals[static_cast<std::size_t>(c)] = local_sum(shift.data(), pairs.data(), c, parts, n_local);
  }
  totals[c_count] = n_local;
  replicas.sum(totals.data(), channels + 1);
  std::vector<double> one_part(2 * c_count);
  for (std::int64_t c = 0; c < channels; ++c) {
    squares_about_mean(shift.data(), pairs.data(), c, channels, parts, n_local, totals.data(),
                       one_part.data() + 2 * c);
  }
  replicas.sum(one_part.data(), 2 * channels);
  to_device(shift, shifts, stream);
  to_device(one_part, partials, stream);
  count = static_cast<std::int64_t>(totals[c_count]);
}

// A DeviceReplicaSum's path: the same steps as kernels, the sums on the device, all queued on
// `stream`. The totals and the one part live in the sum's scratch; the returned pointers are the
// part's pairs and the count of all replicas' values.
struct CombinedOnDevice {
  double* pairs;
  const double* count;
};

CombinedOnDevice combine_statistics_on_device(double* shifts, const double* partials,
                                              std::int64_t channels, std::int64_t parts,
                                              std::int64_t count, DeviceReplicaSum& replicas,
                                              cudaStream_t stream) {
  double* totals = replicas.scratch(3 * channels + 1);
  double* pairs = totals + channels + 1;
  const auto n_local = static_cast<double>(count);
  launch_kernel(local_sums_kernel, channel_grid(channels), dim3(kBlockSize), 0, stream, shifts,
                partials, channels, parts, n_local, totals);
  replicas.sum(totals, channels + 1, stream);
  launch_kernel(squares_about_mean_kernel, channel_grid(channels), dim3(kBlockSize), 0, stream,
                shifts, partials, channels, parts, n_local, totals, pairs);
  replicas.sum(pairs, 2 * channels, stream);
  return {pairs, totals + channels};
}

// The backward's coefficients of all replicas' values, from this replica's partials (parts = 0
// without values), on the host for a ReplicaSum and on the device for a DeviceReplicaSum.
void combine_backward_sums(const double* partials, std::int64_t channels, std::int64_t parts,
                           std::int64_t count, double* coefficients, ReplicaSum& replicas,
                           cudaStream_t stream) {
  if (auto* on_device = dynamic_cast<DeviceReplicaSum*>(&replicas)) {
    double* totals = on_device->scratch(2 * channels + 1);
    launch_kernel(local_backward_sums_kernel, channel_grid(channels), dim3(kBlockSize), 0, stream,
                  partials, channels, parts, static_cast<double>(count), totals);
    on_device->sum(totals, 2 * channels + 1, stream);
    launch_kernel(combined_coefficients_kernel, channel_grid(channels), dim3(kBlockSize), 0, stream,
                  totals, channels, coefficients);
    return;
  }
  const std::vector<double> pairs = to_host(partials, 2 * channels * parts, stream);
  std::vector<double> totals(static_cast<std::size_t>(2 * channels) + 1);
  for (std::int64_t c = 0; c < channels; ++c) {
    local_backward_sums(pairs.data(), c, channels, parts, totals.data());
  }
  totals[static_cast<std::size_t>(2 * channels)] = static_cast<double>(count);
  replicas.sum(totals.data(), 2 * channels + 1);
  std::vector<double> all(static_cast<std::size_t>(2 * channels));
  for (std::int64_t c = 0; c < channels; ++c) {
    combined_coefficients(totals.data(), c, channels, all.data());
  }
  to_device(all, coefficients, stream);
}

}  // namespace

void batchnorm_finalize_statistics(double* shifts, double* partials, std::int64_t channels,
                                   std::int64_t parts, std::int64_t count, float eps,
                                   float momentum, float* running_mean, float* running_var,
                                   float* save_mean, float* save_inv_std, cudaStream_t stream,
                                   ReplicaSum* replicas) {
  const char* op = "batchnorm_finalize_statistics";
  PS_CHECK(channels >= 1 && parts >= 0 && count >= 0,
           "{}: expected channels >= 1, parts >= 0, count >= 0, given {}, {}, {}", op, channels,
           parts, count);
  // With replicas: the statistics of all replicas' values, as one part.
  const double* total_count = nullptr;  // on the device, with a DeviceReplicaSum
  if (replicas != nullptr) {
    PS_CHECK(shifts != nullptr && partials != nullptr,
             "{}: synchronised BatchNorm needs the shifts ({} doubles) and room for one part of "
             "partials ({} doubles) in device memory",
             op, channels, 2 * channels);
    const std::int64_t own_parts = count > 0 ? parts : 0;
    if (auto* on_device = dynamic_cast<DeviceReplicaSum*>(replicas)) {
      const CombinedOnDevice combined = combine_statistics_on_device(
          shifts, partials, channels, own_parts, count, *on_device, stream);
      partials = combined.pairs;
      total_count = combined.count;
    } else {
      combine_statistics(shifts, partials, channels, own_parts, count, *replicas, stream);
    }
    parts = 1;
  }
  // The device's total count cannot be checked without waiting for it: there a total of 1 value
  // gives a NaN running variance (n / (n - 1) = Inf times a variance of 0).
  PS_CHECK(total_count != nullptr || count != 1,
           "{}: a channel needs more than 1 value when training (its unbiased variance is "
           "undefined otherwise), given 1",
           op);
  check_eps_momentum(eps, momentum, op);
  PS_CHECK(save_mean != nullptr && save_inv_std != nullptr && running_mean != nullptr &&
               running_var != nullptr && (parts == 0 || (shifts != nullptr && partials != nullptr)),
           "{}: the statistics ({} floats each) and the partials must be device memory", op,
           channels);
  launch_kernel(finalize_statistics_kernel,
                dim3(static_cast<unsigned>(ceil_div(channels, kChannelsPerFinalizeBlock))),
                dim3(kBlockSize), 0, stream, shifts, partials, channels, parts, count, total_count,
                eps, momentum, running_mean, running_var, save_mean, save_inv_std);
}

void batchnorm_finalize_backward(const double* partials, std::int64_t channels, std::int64_t parts,
                                 std::int64_t count, float* dgamma, float* dbeta,
                                 double* coefficients, cudaStream_t stream,
                                 ReplicaSum* replicas) {
  const char* op = "batchnorm_finalize_backward";
  PS_CHECK(channels >= 1 && parts >= 0 && count >= 0,
           "{}: expected channels >= 1, parts >= 0, count >= 0, given {}, {}, {}", op, channels,
           parts, count);
  PS_CHECK(dgamma != nullptr && dbeta != nullptr && coefficients != nullptr &&
               (parts == 0 || partials != nullptr),
           "{}: dgamma, dbeta ({} floats), coefficients ({} doubles) and the partials must be "
           "device memory",
           op, channels, 2 * channels);
  launch_kernel(finalize_backward_kernel,
                dim3(static_cast<unsigned>(ceil_div(channels, kChannelsPerFinalizeBlock))),
                dim3(kBlockSize), 0, stream, partials, channels, parts, count, dgamma, dbeta,
                coefficients);
  if (replicas != nullptr) {
    combine_backward_sums(partials, channels, count > 0 ? parts : 0, count, coefficients, *replicas,
                          stream);
  }
}

void batchnorm_forward_train(const float* x, const PlanarShape& shape, const float* gamma,
                             const float* beta, float eps, float momentum, float* running_mean,
                             float* running_var, bool relu, float* y, float* save_mean,
                             float* save_inv_std, double* workspace, cudaStream_t stream,
                             ReplicaSum* replicas) {
  const char* op = "batchnorm_forward_train";
  check_shape(shape, op);
  const std::int64_t count = shape.values_per_channel();
  PS_CHECK(count != 1 || replicas != nullptr,
           "{}: expected more than 1 value per channel when training, given x of (B, C, S) = "
           "({}, {}, {})",
           op, shape.batch, shape.channels, shape.inner);
  PS_CHECK(gamma != nullptr && beta != nullptr && running_mean != nullptr &&
               running_var != nullptr && save_mean != nullptr && save_inv_std != nullptr &&
               workspace != nullptr,
           "{}: gamma, beta, the running and saved statistics ({} floats each) and the workspace "
           "({} doubles) must be device memory",
           op, shape.channels, batchnorm_workspace_doubles(shape));
  PS_CHECK(count == 0 || (x != nullptr && y != nullptr),
           "{}: x and y must point to {} floats of device memory", op, shape.channels * count);
  const std::int64_t parts = parts_per_channel(shape);
  double* shifts = workspace;
  double* partials = workspace + shape.channels;
  const PlaneChunks layout = plane_chunks(shape, {x, y});
  if (count > 0) {
    launch_kernel(statistics_partials_kernel, chunk_grid(shape, op), dim3(kBlockSize), 0, stream, x,
                  layout, parts, shifts, partials);
  }
  batchnorm_finalize_statistics(shifts, partials, shape.channels, parts, count, eps, momentum,
                                running_mean, running_var, save_mean, save_inv_std, stream,
                                replicas);
  if (count > 0) {
    launch_kernel(apply_kernel, chunk_grid(shape, op), dim3(kBlockSize), 0, stream, x, layout,
                  save_mean, save_inv_std, false, eps, gamma, beta, relu, y);
  }
}

void batchnorm_forward_eval(const float* x, const PlanarShape& shape, const float* gamma,
                            const float* beta, const float* running_mean, const float* running_var,
                            float eps, bool relu, float* y, cudaStream_t stream) {
  const char* op = "batchnorm_forward_eval";
  check_shape(shape, op);
  check_eps_momentum(eps, 0.0f, op);
  const std::int64_t count = shape.values_per_channel();
  if (count == 0) return;
  PS_CHECK(x != nullptr && y != nullptr && gamma != nullptr && beta != nullptr &&
               running_mean != nullptr && running_var != nullptr,
           "{}: x, y ({} floats) and gamma, beta, running_mean, running_var ({} floats each) must "
           "be device memory",
           op, shape.channels * count, shape.channels);
  launch_kernel(apply_kernel, chunk_grid(shape, op), dim3(kBlockSize), 0, stream, x,
                plane_chunks(shape, {x, y}), running_mean, running_var, true, eps, gamma, beta,
                relu, y);
}

void batchnorm_backward(const float* dy, const float* x, const float* y, const PlanarShape& shape,
                        const float* gamma, const float* save_mean, const float* save_inv_std,
                        float* dx, float* dgamma, float* dbeta, double* workspace,
                        cudaStream_t stream, ReplicaSum* replicas) {
  const char* op = "batchnorm_backward";
  check_shape(shape, op);
  const std::int64_t count = shape.values_per_channel();
  PS_CHECK(gamma != nullptr && save_mean != nullptr && save_inv_std != nullptr &&
               dgamma != nullptr && dbeta != nullptr && workspace != nullptr,
           "{}: gamma, save_mean, save_inv_std, dgamma, dbeta ({} floats each) and the workspace "
           "({} doubles) must be device memory",
           op, shape.channels, batchnorm_workspace_doubles(shape));
  PS_CHECK(count == 0 || (dy != nullptr && x != nullptr && dx != nullptr),
           "{}: dy, x and dx must point to {} floats of device memory", op, shape.channels * count);
  const std::int64_t parts = parts_per_channel(shape);
  double* partials = workspace;
  double* coefficients = workspace + 2 * shape.channels * parts;
  const PlaneChunks layout = plane_chunks(shape, {dy, x, y, dx});
  if (count > 0) {
    launch_kernel(backward_partials_kernel, chunk_grid(shape, op), dim3(kBlockSize), 0, stream, dy,
                  x, y, layout, parts, save_mean, save_inv_std, partials);
  }
  batchnorm_finalize_backward(partials, shape.channels, parts, count, dgamma, dbeta, coefficients,
                              stream, replicas);
  if (count > 0) {
    launch_kernel(input_gradient_kernel, chunk_grid(shape, op), dim3(kBlockSize), 0, stream, dy, x,
                  y, layout, gamma, save_mean, save_inv_std, coefficients, dx);
  }
}

}  // namespace pillarseg::cuda
