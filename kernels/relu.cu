// ReLU forward and backward kernels on flat float arrays (n), see relu.cuh. Memory bound, so the
// kernels move four floats per load and store (float4) wherever all pointers share one 16-byte
// alignment: a scalar head of up to 3 elements reaches the boundary, a float4 body follows, and a
// scalar tail of up to 3 elements ends. Pointers with different alignments take the scalar path.
#include "kernels/relu.cuh"

#include <algorithm>
#include <cstdint>
#include <initializer_list>

#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {
namespace {

constexpr int kBlockSize = 256;
// A grid-stride loop covers the rest; 4096 blocks of 256 threads fill any current GPU.
constexpr std::int64_t kMaxBlocks = 4096;

// [0, n) as a scalar head [0, head), a float4 body [head, head + 4 * vectors) and a scalar tail
// of `tail` elements. The kernels see it as vectors + head + tail work items: items below
// `vectors` are float4s, the others single elements.
struct Float4Split {
  std::int64_t head = 0;
  std::int64_t vectors = 0;
  std::int64_t tail = 0;
};

Float4Split split_for_float4(std::int64_t n, std::initializer_list<const float*> pointers) {
  const auto misalignment = [](const float* p) { return reinterpret_cast<std::uintptr_t>(p) % 16; };
  const std::uintptr_t shared_misalignment = misalignment(*pointers.begin());
  for (const float* p : pointers) {
    if (misalignment(p) != shared_misalignment) return Float4Split{n, 0, 0};
  }
  const std::int64_t head =
      std::min<std::int64_t>(n, static_cast<std::int64_t>((16 - shared_misalignment) % 16 / 4));
  const std::int64_t vectors = (n - head) / 4;
  return Float4Split{head, vectors, n - head - 4 * vectors};
}

std::int64_t work_items(const Float4Split& split) {
  return split.vectors + split.head + split.tail;
}

dim3 grid_for(const Float4Split& split) {
  return dim3(static_cast<unsigned>(std::min(ceil_div(work_items(split), kBlockSize), kMaxBlocks)));
}

}  // namespace

static __device__ __forceinline__ float relu(float x) {
  return x <= 0.0f ? 0.0f : x;
}
static __device__ __forceinline__ float relu_grad(float x, float dy) {
  return x <= 0.0f ? 0.0f : dy;
}

// The element of scalar work item s (0 <= s < head + tail).
static __device__ __forceinline__ std::int64_t scalar_element(const Float4Split& split,
                                                              std::int64_t s) {
  return s < split.head ? s : split.head + 4 * split.vectors + (s - split.head);
}

// x (n) -> y (n), n = head + 4 * vectors + tail.
static __global__ void __launch_bounds__(kBlockSize)
    relu_forward_kernel(const float* x, float* y, Float4Split split) {
  const std::int64_t items = split.vectors + split.head + split.tail;
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  for (std::int64_t item = std::int64_t{blockIdx.x} * blockDim.x + threadIdx.x; item < items;
       item += stride) {
    if (item < split.vectors) {
      const std::int64_t i = split.head + 4 * item;
      const float4 v = *reinterpret_cast<const float4*>(x + i);
      *reinterpret_cast<float4*>(y + i) = make_float4(relu(v.x), relu(v.y), relu(v.z), relu(v.w));
    } else {
      const std::int64_t i = scalar_element(split, item - split.vectors);
      y[i] = relu(x[i]);
    }
  }
}

// x (n), dy (n) -> dx (n).
static __global__ void __launch_bounds__(kBlockSize)
    relu_backward_kernel(const float* x, const float* dy, float* dx, Float4Split split) {
  const std::int64_t items = split.vectors + split.head + split.tail;
  const std::int64_t stride = std::int64_t{gridDim.x} * blockDim.x;
  for (std::int64_t item = std::int64_t{blockIdx.x} * blockDim.x + threadIdx.x; item < items;
       item += stride) {
    if (item < split.vectors) {
      const std::int64_t i = split.head + 4 * item;
      const float4 v = *reinterpret_cast<const float4*>(x + i);
      const float4 g = *reinterpret_cast<const float4*>(dy + i);
      *reinterpret_cast<float4*>(dx + i) = make_float4(relu_grad(v.x, g.x), relu_grad(v.y, g.y),
                                                       relu_grad(v.z, g.z), relu_grad(v.w, g.w));
    } else {
      const std::int64_t i = scalar_element(split, item - split.vectors);
      dx[i] = relu_grad(x[i], dy[i]);
    }
  }
}

void relu_forward(const float* x, float* y, std::int64_t n, cudaStream_t stream) {
  PS_CHECK(n >= 0, "relu_forward: n = {}; expected a number of elements >= 0", n);
  if (n == 0) return;
  PS_CHECK(x != nullptr && y != nullptr,
           "relu_forward: x and y must point to {} floats of device memory, got x = {}, y = {}", n,
           fmt::ptr(x), fmt::ptr(y));
  const Float4Split split = split_for_float4(n, {x, y});
  launch_kernel(relu_forward_kernel, grid_for(split), dim3(kBlockSize), 0, stream, x, y, split);
}

void relu_backward(const float* x, const float* dy, float* dx, std::int64_t n,
                   cudaStream_t stream) {
  PS_CHECK(n >= 0, "relu_backward: n = {}; expected a number of elements >= 0", n);
  if (n == 0) return;
  PS_CHECK(x != nullptr && dy != nullptr && dx != nullptr,
           "relu_backward: x, dy and dx must point to {} floats of device memory, got x = {}, dy = "
           "{}, dx = {}",
           n, fmt::ptr(x), fmt::ptr(dy), fmt::ptr(dx));
  const Float4Split split = split_for_float4(n, {x, dy, dx});
  launch_kernel(relu_backward_kernel, grid_for(split), dim3(kBlockSize), 0, stream, x, dy, dx,
                split);
}

}  // namespace pillarseg::cuda
