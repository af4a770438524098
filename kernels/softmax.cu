// Channel softmax and the arg-max class ids (see softmax.cuh). A grid of (cells of a batch item,
// batch items); each thread walks its cell's K channels three times for the softmax (max, sum
// of exponentials, normalised outputs), reading them back from L1 rather than holding K values in
// registers, so any K compiles to the same kernel.
#include "kernels/softmax.cuh"

#include <cstdint>
#include <limits>

#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kBlockSize = 256;

dim3 cell_grid(std::int64_t batch, std::int64_t inner) {
  return dim3(static_cast<unsigned>(ceil_div(inner, kBlockSize)), static_cast<unsigned>(batch));
}

void check_shape(const char* op, std::int64_t batch, std::int64_t classes, std::int64_t inner,
                 std::int64_t max_classes) {
  PS_CHECK(batch >= 0 && inner >= 0 && classes >= 1 && classes <= max_classes,
           "{}: expected logits (B, K, H * W) with B, H * W >= 0 and 1 <= K <= {}, given ({}, {}, "
           "{})",
           op, max_classes, batch, classes, inner);
  PS_CHECK(batch <= 65535 && ceil_div(inner, kBlockSize) <= std::numeric_limits<int>::max(),
           "{}: a batch of {} items of {} cells exceeds the grid", op, batch, inner);
}

}  // namespace

static __global__ void __launch_bounds__(kBlockSize)
    softmax_kernel(const float* logits, std::int64_t classes, std::int64_t inner,
                   float* probabilities) {
  const std::int64_t cell = std::int64_t{blockIdx.x} * kBlockSize + threadIdx.x;
  if (cell >= inner) return;
  const std::int64_t offset = std::int64_t{blockIdx.y} * classes * inner + cell;
  const float* z = logits + offset;
  float* p = probabilities + offset;
  float max_logit = z[0];
  for (std::int64_t k = 1; k < classes; ++k) {
    const float v = z[k * inner];
    max_logit = v > max_logit ? v : max_logit;
  }
  float sum = 0.0f;
  for (std::int64_t k = 0; k < classes; ++k) sum += expf(z[k * inner] - max_logit);
  const float inv_sum = 1.0f / sum;
  for (std::int64_t k = 0; k < classes; ++k)
    p[k * inner] = expf(z[k * inner] - max_logit) * inv_sum;
}

// kPositive: the largest positive value wins, from 0 with class 0 (NaN never wins); else the
// largest of all, from channel 0's value, a NaN counting as the largest.
template <bool kPositive>
static __global__ void __launch_bounds__(kBlockSize)
    argmax_kernel(const float* values, std::int64_t classes, std::int64_t inner,
                  std::uint8_t* class_ids) {
  const std::int64_t cell = std::int64_t{blockIdx.x} * kBlockSize + threadIdx.x;
  if (cell >= inner) return;
  const float* z = values + std::int64_t{blockIdx.y} * classes * inner + cell;
  float best = kPositive ? 0.0f : z[0];
  std::int64_t best_channel = kPositive ? -1 : 0;
  for (std::int64_t k = kPositive ? 0 : 1; k < classes; ++k) {
    const float v = z[k * inner];
    const bool v_is_nan = v != v;
    const bool best_is_nan = best != best;
    if (v > best || (!kPositive && v_is_nan && !best_is_nan)) {
      best = v;
      best_channel = k;
    }
  }
  class_ids[std::int64_t{blockIdx.y} * inner + cell] = static_cast<std::uint8_t>(best_channel + 1);
}

void softmax_channels(const float* logits, std::int64_t batch, std::int64_t classes,
                      std::int64_t inner, float* probabilities, cudaStream_t stream) {
  const char* op = "softmax_channels";
  check_shape(op, batch, classes, inner, std::numeric_limits<std::int64_t>::max());
  if (batch * inner == 0) return;
  PS_CHECK(logits != nullptr && probabilities != nullptr,
           "{}: logits and probabilities must point to {} floats of device memory", op,
           batch * classes * inner);
  PS_CHECK(logits != probabilities, "{}: probabilities must not be the logits (not in place)", op);
  launch_kernel(softmax_kernel, cell_grid(batch, inner), dim3(kBlockSize), 0, stream, logits,
                classes, inner, probabilities);
}

namespace {

template <bool kPositive>
void launch_argmax(const char* op, const char* what, const float* values, std::int64_t batch,
                   std::int64_t classes, std::int64_t inner, std::uint8_t* class_ids,
                   cudaStream_t stream) {
  check_shape(op, batch, classes, inner, 255);
  if (batch * inner == 0) return;
  PS_CHECK(values != nullptr && class_ids != nullptr,
           "{}: {} ({} floats) and class_ids ({} bytes) must be device memory", op, what,
           batch * classes * inner, batch * inner);
  launch_kernel(argmax_kernel<kPositive>, cell_grid(batch, inner), dim3(kBlockSize), 0, stream,
                values, classes, inner, class_ids);
}

}  // namespace

void argmax_class_ids(const float* logits, std::int64_t batch, std::int64_t classes,
                      std::int64_t inner, std::uint8_t* class_ids, cudaStream_t stream) {
  launch_argmax<false>("argmax_class_ids", "logits", logits, batch, classes, inner, class_ids,
                       stream);
}

void argmax_positive_class_ids(const float* values, std::int64_t batch, std::int64_t classes,
                               std::int64_t inner, std::uint8_t* class_ids, cudaStream_t stream) {
  launch_argmax<true>("argmax_positive_class_ids", "values", values, batch, classes, inner,
                      class_ids, stream);
}

}  // namespace pillarseg::cuda
