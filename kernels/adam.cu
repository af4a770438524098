// AdamW step on flat arrays (see adam.cuh). Memory bound (4 arrays read, 3 written): float4 loads
// and stores wherever the four arrays share one 16-byte alignment (kernels/float4_split.cuh), a
// grid-stride loop over the work items.
#include "kernels/adam.cuh"

#include <cmath>
#include <cstdint>

#include "kernels/common.cuh"
#include "kernels/float4_split.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kBlockSize = 256;
constexpr std::int64_t kMaxBlocks = 4096;

// The step's scalars, rounded to float once on the host as PyTorch's float tensors see them.
struct AdamCoefficients {
  float decay;  // 1 - lr * weight_decay
  float beta1;
  float one_minus_beta1;
  float beta2;
  float one_minus_beta2;
  float step_size;                  // lr / (1 - beta1^t)
  float inv_sqrt_bias_correction2;  // 1 / sqrt(1 - beta2^t)
  float eps;
};

}  // namespace

// One element: p, m, v updated from g.
static __device__ __forceinline__ void adam_update(float& p, float g, float& m, float& v,
                                                   const AdamCoefficients& k) {
  p *= k.decay;
  m = k.beta1 * m + k.one_minus_beta1 * g;
  v = k.beta2 * v + k.one_minus_beta2 * (g * g);
  p -= k.step_size * m / (sqrtf(v) * k.inv_sqrt_bias_correction2 + k.eps);
}

static __global__ void __launch_bounds__(kBlockSize)
    adam_kernel(float* params, const float* grads, float* exp_avg, float* exp_avg_sq,
                Float4Split split, AdamCoefficients k) {
  const std::int64_t items = split.items();
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  for (std::int64_t item = std::int64_t{blockIdx.x} * blockDim.x + threadIdx.x; item < items;
       item += stride) {
    if (item < split.vectors) {
      const std::int64_t i = split.head + 4 * item;
      float4 p = *reinterpret_cast<const float4*>(params + i);
      const float4 g = *reinterpret_cast<const float4*>(grads + i);
      float4 m = *reinterpret_cast<const float4*>(exp_avg + i);
      float4 v = *reinterpret_cast<const float4*>(exp_avg_sq + i);
      adam_update(p.x, g.x, m.x, v.x, k);
      adam_update(p.y, g.y, m.y, v.y, k);
      adam_update(p.z, g.z, m.z, v.z, k);
      adam_update(p.w, g.w, m.w, v.w, k);
      *reinterpret_cast<float4*>(params + i) = p;
      *reinterpret_cast<float4*>(exp_avg + i) = m;
      *reinterpret_cast<float4*>(exp_avg_sq + i) = v;
    } else {
      const std::int64_t i = scalar_element(split, item - split.vectors);
      adam_update(params[i], grads[i], exp_avg[i], exp_avg_sq[i], k);
    }
  }
}

void adam_step(float* params, const float* grads, float* exp_avg, float* exp_avg_sq, std::int64_t n,
               std::int64_t step, const AdamOptions& options, cudaStream_t stream) {
  const char* op = "adam_step";
  PS_CHECK(n >= 0, "{}: n = {}; expected a number of parameters >= 0", op, n);
  PS_CHECK(step >= 1, "{}: expected step >= 1 (1-based, counting this step), given {}", op, step);
  PS_CHECK(options.lr >= 0 && options.eps >= 0 && options.weight_decay >= 0,
           "{}: expected lr, eps, weight_decay >= 0, given {}, {}, {}", op, options.lr, options.eps,
           options.weight_decay);
  PS_CHECK(options.beta1 >= 0 && options.beta1 < 1 && options.beta2 >= 0 && options.beta2 < 1,
           "{}: expected beta1, beta2 in [0, 1), given {}, {}", op, options.beta1, options.beta2);
  if (n == 0) return;
  PS_CHECK(params != nullptr && grads != nullptr && exp_avg != nullptr && exp_avg_sq != nullptr,
           "{}: params, grads, exp_avg and exp_avg_sq must point to {} floats of device memory", op,
           n);
  const double bias_correction1 = 1 - std::pow(options.beta1, static_cast<double>(step));
  const double bias_correction2 = 1 - std::pow(options.beta2, static_cast<double>(step));
  const AdamCoefficients coefficients{static_cast<float>(1 - options.lr * options.weight_decay),
                                      static_cast<float>(options.beta1),
                                      static_cast<float>(1 - options.beta1),
                                      static_cast<float>(options.beta2),
                                      static_cast<float>(1 - options.beta2),
                                      static_cast<float>(options.lr / bias_correction1),
                                      static_cast<float>(1 / std::sqrt(bias_correction2)),
                                      static_cast<float>(options.eps)};
  const Float4Split split = split_for_float4(n, {params, grads, exp_avg, exp_avg_sq});
  launch_kernel(adam_kernel, grid_stride_blocks(split.items(), kBlockSize, kMaxBlocks),
                dim3(kBlockSize), 0, stream, params, grads, exp_avg, exp_avg_sq, split,
                coefficients);
}

}  // namespace pillarseg::cuda
