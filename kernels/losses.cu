// Weighted softmax cross-entropy and one-hot sigmoid BCE with their gradients (see losses.cuh);
// the Lovász-softmax term's four kernels are in the section of their own below.
//   [partials] a grid of at most kLossPartials blocks walks the B * S cells (grid-stride), one
//              thread per cell over its K channels: loss sums in double, label counts;
//   [finalize] one block adds the partials in a fixed order -> LossResult;
//   [gradient] one thread per cell writes its K gradients, scaled by the result's 1 / M.
// The losses differ only in the per-cell functions below; the kernels are templates on the kind.
#include "kernels/losses.cuh"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

#include "kernels/block_reduce.cuh"
#include "kernels/block_scan.cuh"
#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kBlockSize = 256;
// Cells per thread of the partials pass before it adds another block.
constexpr std::int64_t kCellsPerThread = 4;

enum class Loss { CrossEntropy, Bce };

void check_arguments(const char* op, const float* logits, const std::uint8_t* labels,
                     std::int64_t batch, std::int64_t classes, std::int64_t inner,
                     const float* d_logits, const LossPartial* workspace,
                     const LossResult* result) {
  PS_CHECK(batch >= 0 && inner >= 0 && classes >= 1 && classes <= 255,
           "{}: expected logits (B, K, H * W) with B, H * W >= 0 and 1 <= K <= 255, given ({}, "
           "{}, {})",
           op, batch, classes, inner);
  PS_CHECK(batch <= 65535 && ceil_div(inner, kBlockSize) <= std::numeric_limits<int>::max(),
           "{}: a batch of {} items of {} cells exceeds the grid", op, batch, inner);
  PS_CHECK(workspace != nullptr && result != nullptr,
           "{}: the workspace ({} LossPartial) and the result must be device memory", op,
           kLossPartials);
  PS_CHECK(batch * inner == 0 || (logits != nullptr && labels != nullptr),
           "{}: logits ({} floats) and labels ({} bytes) must be device memory", op,
           batch * classes * inner, batch * inner);
  PS_CHECK(d_logits != logits || logits == nullptr,
           "{}: d_logits must not be the logits (not in place)", op);
}

}  // namespace

// Where cell i of the B * S cells starts in logits (B, K, S): its channel 0.
static __device__ __forceinline__ std::int64_t cell_offset(std::int64_t i, std::int64_t classes,
                                                           std::int64_t inner) {
  const std::int64_t b = i / inner;
  return b * classes * inner + (i - b * inner);
}

// log(sum_k exp(z_k)) of a cell as the host computes it: max + log(sum exp(z - max)), in float.
static __device__ __forceinline__ float log_sum_exp(const float* z, std::int64_t classes,
                                                    std::int64_t inner) {
  float max_logit = z[0];
  for (std::int64_t k = 1; k < classes; ++k) {
    const float v = z[k * inner];
    max_logit = v > max_logit ? v : max_logit;
  }
  float sum = 0.0f;
  for (std::int64_t k = 0; k < classes; ++k) sum += expf(z[k * inner] - max_logit);
  return max_logit + logf(sum);
}

// softplus(x) = log(1 + exp(x)) = max(x, 0) + log(1 + exp(-|x|)), stable for any x.
static __device__ __forceinline__ float softplus(float x) {
  return (x > 0.0f ? x : 0.0f) + log1pf(expf(-fabsf(x)));
}

// The loss of a labelled cell (label in 1..K), before the 1 / M or 1 / (M K).
template <Loss kind>
static __device__ __forceinline__ double cell_loss(const float* z, int label, std::int64_t classes,
                                                   std::int64_t inner, const float* class_weights) {
  if constexpr (kind == Loss::CrossEntropy) {
    const float lse = log_sum_exp(z, classes, inner);
    return static_cast<double>(class_weights[label]) *
           (static_cast<double>(lse) - static_cast<double>(z[(label - 1) * inner]));
  } else {
    double loss = 0.0;
    for (std::int64_t k = 0; k < classes; ++k) {
      const float v = z[k * inner];
      const float term = softplus(label == k + 1 ? -v : v);
      loss += static_cast<double>(class_weights[k + 1]) * static_cast<double>(term);
    }
    return loss;
  }
}

// logits, labels -> partials[blockIdx.x]: the sums over the cells this block visits.
template <Loss kind>
static __global__ void __launch_bounds__(kBlockSize)
    loss_partials_kernel(const float* logits, const std::uint8_t* labels, std::int64_t classes,
                         std::int64_t inner, std::int64_t cells, const float* class_weights,
                         LossPartial* partials) {
  double loss = 0.0;
  std::int64_t labelled = 0;
  std::int64_t invalid = 0;
  const std::int64_t stride = std::int64_t{gridDim.x} * kBlockSize;
  for (std::int64_t i = std::int64_t{blockIdx.x} * kBlockSize + threadIdx.x; i < cells;
       i += stride) {
    const int label = labels[i];
    if (label == 0) continue;
    if (label > classes) {
      ++invalid;
      continue;
    }
    ++labelled;
    const float* z = logits + cell_offset(i, classes, inner);
    loss += cell_loss<kind>(z, label, classes, inner, class_weights);
  }
  loss = block_sum<kBlockSize>(loss);
  labelled = block_sum<kBlockSize>(labelled);
  invalid = block_sum<kBlockSize>(invalid);
  if (threadIdx.x == 0) partials[blockIdx.x] = LossPartial{loss, labelled, invalid};
}

// One block: partials (count) -> *result.
static __global__ void __launch_bounds__(kBlockSize)
    loss_finalize_kernel(const LossPartial* partials, int count, std::int64_t classes,
                         bool per_channel, LossResult* result) {
  double loss = 0.0;
  std::int64_t labelled = 0;
  std::int64_t invalid = 0;
  for (int i = static_cast<int>(threadIdx.x); i < count; i += kBlockSize) {
    loss += partials[i].loss;
    labelled += partials[i].labelled;
    invalid += partials[i].invalid_labels;
  }
  loss = block_sum<kBlockSize>(loss);
  labelled = block_sum<kBlockSize>(labelled);
  invalid = block_sum<kBlockSize>(invalid);
  if (threadIdx.x != 0) return;
  const double terms = static_cast<double>(per_channel ? labelled * classes : labelled);
  const double scale = labelled > 0 ? 1.0 / terms : 0.0;
  *result = LossResult{loss * scale, scale, labelled, invalid, classes};
}

// One thread per cell: d_logits of its K channels.
template <Loss kind>
static __global__ void __launch_bounds__(kBlockSize)
    loss_gradient_kernel(const float* logits, const std::uint8_t* labels, std::int64_t classes,
                         std::int64_t inner, const float* class_weights, const LossResult* result,
                         float* d_logits) {
  const std::int64_t cell = std::int64_t{blockIdx.x} * kBlockSize + threadIdx.x;
  if (cell >= inner) return;
  const std::int64_t b = blockIdx.y;
  const float* z = logits + b * classes * inner + cell;
  float* d = d_logits + b * classes * inner + cell;
  const int label = labels[b * inner + cell];
  if (label == 0 || label > classes) {  // no loss, so no gradient, even for NaN logits
    for (std::int64_t k = 0; k < classes; ++k) d[k * inner] = 0.0f;
    return;
  }
  const double scale = result->gradient_scale;
  if constexpr (kind == Loss::CrossEntropy) {
    // c[y] / M * (softmax_k - [k == y - 1]).
    const float lse = log_sum_exp(z, classes, inner);
    const auto cell_weight = static_cast<float>(static_cast<double>(class_weights[label]) * scale);
    for (std::int64_t k = 0; k < classes; ++k) {
      const float target = k == label - 1 ? 1.0f : 0.0f;
      d[k * inner] = cell_weight * (expf(z[k * inner] - lse) - target);
    }
  } else {
    // c[k + 1] / (M K) * (sigmoid(z_k) - t_k), sigmoid from exp(-|z|) so that nothing overflows.
    for (std::int64_t k = 0; k < classes; ++k) {
      const float v = z[k * inner];
      const float e = expf(-fabsf(v));
      const float sigmoid = (v >= 0.0f ? 1.0f : e) / (1.0f + e);
      const float target = label == k + 1 ? 1.0f : 0.0f;
      const auto weight = static_cast<float>(static_cast<double>(class_weights[k + 1]) * scale);
      d[k * inner] = weight * (sigmoid - target);
    }
  }
}

namespace {

template <Loss kind>
void run_loss(const char* op, const float* logits, const std::uint8_t* labels, std::int64_t batch,
              std::int64_t classes, std::int64_t inner, const float* class_weights, float* d_logits,
              LossPartial* workspace, LossResult* result, cudaStream_t stream) {
  check_arguments(op, logits, labels, batch, classes, inner, d_logits, workspace, result);
  PS_CHECK(class_weights != nullptr, "{}: class_weights ({} floats) must be device memory", op,
           classes + 1);
  const std::int64_t cells = batch * inner;
  const std::int64_t blocks =
      std::clamp<std::int64_t>(ceil_div(cells, kBlockSize * kCellsPerThread), 1, kLossPartials);
  launch_kernel(loss_partials_kernel<kind>, dim3(static_cast<unsigned>(blocks)), dim3(kBlockSize),
                0, stream, logits, labels, classes, std::max<std::int64_t>(inner, 1), cells,
                class_weights, workspace);
  launch_kernel(loss_finalize_kernel, dim3(1), dim3(kBlockSize), 0, stream, workspace,
                static_cast<int>(blocks), classes, kind == Loss::Bce, result);
  if (d_logits == nullptr || cells == 0) return;
  launch_kernel(
      loss_gradient_kernel<kind>,
      dim3(static_cast<unsigned>(ceil_div(inner, kBlockSize)), static_cast<unsigned>(batch)),
      dim3(kBlockSize), 0, stream, logits, labels, classes, inner, class_weights, result, d_logits);
}

}  // namespace

void cross_entropy_loss(const float* logits, const std::uint8_t* labels, std::int64_t batch,
                        std::int64_t classes, std::int64_t inner, const float* class_weights,
                        float* d_logits, LossPartial* workspace, LossResult* result,
                        cudaStream_t stream) {
  run_loss<Loss::CrossEntropy>("cross_entropy_loss", logits, labels, batch, classes, inner,
                               class_weights, d_logits, workspace, result, stream);
}

void bce_loss(const float* logits, const std::uint8_t* labels, std::int64_t batch,
              std::int64_t classes, std::int64_t inner, const float* class_weights, float* d_logits,
              LossPartial* workspace, LossResult* result, cudaStream_t stream) {
  run_loss<Loss::Bce>("bce_loss", logits, labels, batch, classes, inner, class_weights, d_logits,
                      workspace, result, stream);
}

// ---------------------------------------------------------------- Lovász-softmax

// The softmax of a cell as the host computes it: exp(z - max) / sum, the sum in class order.
struct CellSoftmax {
  float max_logit;
  float sum;
  __device__ float operator()(const float* z, std::int64_t k, std::int64_t inner) const {
    return expf(z[k * inner] - max_logit) / sum;
  }
};

static __device__ __forceinline__ CellSoftmax cell_softmax(const float* z, std::int64_t classes,
                                                           std::int64_t inner) {
  float max_logit = z[0];
  for (std::int64_t k = 1; k < classes; ++k) max_logit = fmaxf(max_logit, z[k * inner]);
  float sum = 0.0f;
  for (std::int64_t k = 0; k < classes; ++k) sum += expf(z[k * inner] - max_logit);
  return CellSoftmax{max_logit, sum};
}

// Class k's part of a labelled cell: its probability and its error, 1 - p for the cell's own class
// (fg) and p for the others.
struct LovaszTerm {
  float p;
  float error;
  bool fg;
};

static __device__ __forceinline__ LovaszTerm lovasz_term(const float* z, std::int64_t k,
                                                         std::int64_t inner, int label,
                                                         const CellSoftmax& softmax) {
  const bool fg = label == k + 1;
  const float p = softmax(z, k, inner);
  return LovaszTerm{p, fg ? 1.0f - p : p, fg};
}

static __global__ void __launch_bounds__(kBlockSize)
    lovasz_histogram_kernel(const float* logits, const std::uint8_t* labels, std::int64_t classes,
                            std::int64_t inner, std::int64_t cells, int* counts) {
  const std::int64_t stride = std::int64_t{gridDim.x} * kBlockSize;
  for (std::int64_t i = std::int64_t{blockIdx.x} * kBlockSize + threadIdx.x; i < cells;
       i += stride) {
    const int label = labels[i];
    if (label == 0 || label > classes) continue;
    const float* z = logits + cell_offset(i, classes, inner);
    const CellSoftmax softmax = cell_softmax(z, classes, inner);
    for (std::int64_t k = 0; k < classes; ++k) {
      const LovaszTerm term = lovasz_term(z, k, inner, label, softmax);
      atomicAdd(&counts[(k * kLovaszBins + lovasz_bin(term.error)) * 2 + term.fg], 1);
    }
  }
}

// One block per class: the bins from the largest error down, kBinsPerThread of them a thread.
static __global__ void __launch_bounds__(kBlockSize)
    lovasz_steps_kernel(std::int64_t classes, int* counts, double* steps) {
  constexpr int kBinsPerThread = kLovaszBins / kBlockSize;
  static_assert(kLovaszBins % kBlockSize == 0, "the bins must split evenly over the threads");
  const std::int64_t k = blockIdx.x;
  const int* class_counts = counts + k * kLovaszBins * 2;
  const int first = static_cast<int>(threadIdx.x) * kBinsPerThread;  // rank of its first bin
  int fg = 0, bg = 0;
  for (int j = 0; j < kBinsPerThread; ++j) {
    const int bin = kLovaszBins - 1 - (first + j);
    bg += class_counts[bin * 2];
    fg += class_counts[bin * 2 + 1];
  }
  int total_fg = 0, total_bg = 0;
  fg = block_exclusive_scan<kBlockSize>(fg, &total_fg);
  bg = block_exclusive_scan<kBlockSize>(bg, &total_bg);
  if (threadIdx.x == 0) counts[classes * kLovaszBins * 2 + k] = total_fg;
  if (total_fg == 0) return;  // an absent class: no steps are read
  double* class_steps = steps + k * kLovaszBins;
  for (int j = 0; j < kBinsPerThread; ++j) {
    const int bin = kLovaszBins - 1 - (first + j);
    const int n = class_counts[bin * 2] + class_counts[bin * 2 + 1];
    if (n == 0) continue;
    const double before = lovasz_jaccard(total_fg, fg, bg);
    bg += class_counts[bin * 2];
    fg += class_counts[bin * 2 + 1];
    class_steps[bin] = (lovasz_jaccard(total_fg, fg, bg) - before) / n;
  }
}

// The weight of class k's error in a cell's loss: the Jaccard step of the error's bin over the C
// present classes (times the loss's weight); 0 for an absent class.
static __device__ __forceinline__ double lovasz_error_weight(const int* totals,
                                                             const double* steps, std::int64_t k,
                                                             const LovaszTerm& term, double scale) {
  return totals[k] == 0 ? 0.0 : scale * steps[k * kLovaszBins + lovasz_bin(term.error)];
}

static __global__ void __launch_bounds__(kBlockSize)
    lovasz_cells_kernel(const float* logits, const std::uint8_t* labels, std::int64_t classes,
                        std::int64_t inner, std::int64_t cells, float weight, const int* counts,
                        const double* steps, float* d_logits, LossPartial* partials) {
  const int* totals = counts + classes * kLovaszBins * 2;
  int present = 0;
  for (std::int64_t k = 0; k < classes; ++k) present += totals[k] > 0;
  const double scale = present > 0 ? static_cast<double>(weight) / present : 0.0;
  double loss = 0.0;
  const std::int64_t stride = std::int64_t{gridDim.x} * kBlockSize;
  for (std::int64_t i = std::int64_t{blockIdx.x} * kBlockSize + threadIdx.x; i < cells;
       i += stride) {
    const int label = labels[i];
    if (label == 0 || label > classes) continue;
    const std::int64_t offset = cell_offset(i, classes, inner);
    const float* z = logits + offset;
    const CellSoftmax softmax = cell_softmax(z, classes, inner);
    // d loss / d p_k = slope_k = -+ weight_k (d error / d p = -1 for fg, +1 else);
    // d loss / d z_k = p_k (slope_k - sum_c slope_c p_c). The second pass recomputes each term
    // rather than keeping K of them per thread.
    // The class loops count in int (classes <= 255, check_arguments): with a 64-bit k ptxas spilled
    // 24 bytes on sm_80-89.
    double slope_dot_p = 0.0;
    for (int k = 0; k < static_cast<int>(classes); ++k) {
      const LovaszTerm term = lovasz_term(z, k, inner, label, softmax);
      const double error_weight = lovasz_error_weight(totals, steps, k, term, scale);
      loss += error_weight * term.error;
      slope_dot_p += (term.fg ? -error_weight : error_weight) * term.p;
    }
    if (d_logits == nullptr) continue;
    float* d = d_logits + offset;
    for (int k = 0; k < static_cast<int>(classes); ++k) {
      const LovaszTerm term = lovasz_term(z, k, inner, label, softmax);
      const double error_weight = lovasz_error_weight(totals, steps, k, term, scale);
      const double slope = term.fg ? -error_weight : error_weight;
      d[k * inner] += static_cast<float>(term.p * (slope - slope_dot_p));
    }
  }
  loss = block_sum<kBlockSize>(loss);
  if (threadIdx.x == 0) partials[blockIdx.x] = LossPartial{loss, 0, 0};
}

static __global__ void __launch_bounds__(kBlockSize)
    lovasz_finalize_kernel(const LossPartial* partials, int count, LossResult* result) {
  double loss = 0.0;
  for (int i = static_cast<int>(threadIdx.x); i < count; i += kBlockSize) loss += partials[i].loss;
  loss = block_sum<kBlockSize>(loss);
  if (threadIdx.x == 0) result->loss += loss;
}

void lovasz_softmax_loss(const float* logits, const std::uint8_t* labels, std::int64_t batch,
                         std::int64_t classes, std::int64_t inner, float weight, float* d_logits,
                         int* counts, double* steps, LossPartial* workspace, LossResult* result,
                         cudaStream_t stream) {
  const char* op = "lovasz_softmax_loss";
  check_arguments(op, logits, labels, batch, classes, inner, d_logits, workspace, result);
  PS_CHECK(counts != nullptr && steps != nullptr,
           "{}: counts ({} ints) and steps ({} doubles) must be device memory", op,
           lovasz_count_ints(classes), lovasz_step_doubles(classes));
  PS_CHECK(std::isfinite(weight) && weight >= 0, "{}: expected a finite weight >= 0, given {}", op,
           weight);
  const std::int64_t cells = batch * inner;
  PS_CHECK(cells <= std::numeric_limits<int>::max(),
           "{}: {} cells exceed the bins' int counts", op, cells);
  PS_CUDA_CHECK(cudaMemsetAsync(counts, 0, sizeof(int) * lovasz_count_ints(classes), stream));
  const std::int64_t blocks =
      std::clamp<std::int64_t>(ceil_div(cells, kBlockSize * kCellsPerThread), 1, kLossPartials);
  const std::int64_t cell_stride = std::max<std::int64_t>(inner, 1);
  launch_kernel(lovasz_histogram_kernel, dim3(static_cast<unsigned>(blocks)), dim3(kBlockSize), 0,
                stream, logits, labels, classes, cell_stride, cells, counts);
  launch_kernel(lovasz_steps_kernel, dim3(static_cast<unsigned>(classes)), dim3(kBlockSize), 0,
                stream, classes, counts, steps);
  launch_kernel(lovasz_cells_kernel, dim3(static_cast<unsigned>(blocks)), dim3(kBlockSize), 0,
                stream, logits, labels, classes, cell_stride, cells, weight, counts, steps,
                d_logits, workspace);
  launch_kernel(lovasz_finalize_kernel, dim3(1), dim3(kBlockSize), 0, stream, workspace,
                static_cast<int>(blocks), result);
}

double loss_value(const LossResult* result, cudaStream_t stream) {
  PS_CHECK(result != nullptr, "loss_value: result must be device memory, got null");
  LossResult host;
  PS_CUDA_CHECK(cudaMemcpyAsync(&host, result, sizeof(LossResult), cudaMemcpyDeviceToHost, stream));
  PS_CUDA_CHECK(cudaStreamSynchronize(stream));
  PS_CHECK(host.invalid_labels == 0,
           "loss: {} labels are not class ids 0..{}; pass labels of the {} classes (0 = unlabeled)",
           host.invalid_labels, host.classes, host.classes);
  return host.loss;
}

}  // namespace pillarseg::cuda
