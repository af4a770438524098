// PointPillars PFN layer, fused (host/pfn.hpp is the spec):
//   points (P, N, D = 10) decorated points, padding slots all-zero rows; weight (C, D), no bias;
//   z = points . weight^T (P * N, C), never stored: every pass recomputes it (10 multiply-adds);
//   a = ReLU(BatchNorm(z)), statistics over all P * N rows, padding included;
//   out (P, C) = max of a over the N slots of each pillar; max_slot (P, C) int32 = the first slot
//   reaching it (NaN wins, as torch.max), or -1 where out is not > 0 (no gradient passes).
// Training is a statistics pass over z (per-block shifted sums in double, combined per channel
// in a fixed order by kernels/batchnorm.cu's finalize), then an apply + max pass. The backward
// routes d_out through the saved slots, through BatchNorm (dgamma, dbeta), and to d_weight and
// d_points; every sum is per block, then per output in a fixed order: deterministic.
// Pointers are device memory; the work is queued on `stream`; nothing waits for the device.
#pragma once

#include <cstdint>

#include "core/replicas.hpp"
#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// The decorated point's features (x, y, z, r, 3 offsets from the pillar mean, 3 from its centre).
inline constexpr std::int64_t kPfnFeatures = 10;

struct PfnShape {
  std::int64_t pillars = 0;   // P
  std::int64_t slots = 0;     // N, points per pillar
  std::int64_t channels = 0;  // C
  __host__ __device__ std::int64_t rows() const { return pillars * slots; }
};

// The scratch, in doubles, that pfn_forward_train and pfn_backward need for `shape`: the larger
// of C (1 + 2 R) and C (2 ceil(P / 256) + 2 + 10 R), R = ceil(P * N / 1024) (4 MiB for 40000
// pillars of 20 slots and C = 64).
std::int64_t pfn_workspace_doubles(const PfnShape& shape);

// Training forward. points (P, N, 10), weight (C, 10), gamma, beta (C); running_mean and
// running_var (C) updated in place (BatchNorm, `eps`, `momentum`). Writes out (P, C), max_slot
// (P, C), save_mean and save_inv_std (C, the batch statistics of z for the backward). P = 0
// leaves the running statistics as they are; P * N = 1 is refused (no variance).
void pfn_forward_train(const float* points, const float* weight, const PfnShape& shape,
                       const float* gamma, const float* beta, float eps, float momentum,
                       float* running_mean, float* running_var, float* out, std::int32_t* max_slot,
                       float* save_mean, float* save_inv_std, double* workspace,
                       cudaStream_t stream, ReplicaSum* replicas = nullptr);

// Evaluation forward with the running statistics. Shapes as pfn_forward_train; max_slot may be
// nullptr (not needed). live_pillars: nullptr, or one int32 of device memory (the gather's P',
// read when the kernel runs): pillars at or past it are inert and their rows of out (and
// max_slot) are left as they are.
void pfn_forward_eval(const float* points, const float* weight, const PfnShape& shape,
                      const float* gamma, const float* beta, const float* running_mean,
                      const float* running_var, float eps, float* out, std::int32_t* max_slot,
                      cudaStream_t stream, const std::int32_t* live_pillars = nullptr);

// Backward of the training forward. d_out (P, C); points, weight, gamma, save_mean,
// save_inv_std and max_slot as given to and written by the forward (a slot outside -1..N-1
// routes nothing). Writes d_weight (C, 10), d_gamma, d_beta (C) and, unless it is nullptr,
// d_points (P, N, 10).
void pfn_backward(const float* d_out, const float* points, const float* weight,
                  const PfnShape& shape, const float* gamma, const float* save_mean,
                  const float* save_inv_std, const std::int32_t* max_slot, float* d_points,
                  float* d_weight, float* d_gamma, float* d_beta, double* workspace,
                  cudaStream_t stream, ReplicaSum* replicas = nullptr);

}  // namespace pillarseg::cuda
