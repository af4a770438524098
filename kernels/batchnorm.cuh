// BatchNorm over the channel axis of x (B, C, H, W), optionally fused with the ReLU that follows
// it, with PyTorch semantics (host/batchnorm.hpp is the spec). x is seen as (B, C, S), S = H * W;
// gamma, beta, the running statistics and the saved statistics are (C).
//   training:   y = gamma * (x - mean) / sqrt(var + eps) + beta with the batch mean and biased
//               batch variance of each channel over its B * S values; the running statistics move
//               towards the mean and the *unbiased* variance by `momentum`.
//   evaluation: the same with the running statistics.
//   backward:   dx, dgamma, dbeta of the training forward; with `y` given, dy is first masked by
//               y > 0 (the ReLU).
// Statistics are sums in double, per block and then per channel in a fixed order (no atomics):
// the same inputs give the same bits on every run. The PFN (kernels/pfn.cu), whose BatchNorm
// runs over its linear outputs computed on the fly, reuses the second passes below.
// Pointers are device memory; the work is queued on `stream`; nothing waits for the device,
// except for synchronised BatchNorm (`replicas`, a data-parallel run) with a ReplicaSum that sums
// on the host: its statistics are brought there. With a DeviceReplicaSum
// (kernels/replica_sum.cuh; NCCL's on a GPU) they are summed on the device, queued on `stream`
// too, with the same formulas and the same bits as the host path.
#pragma once

#include <cstdint>

#include "core/replicas.hpp"
#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// x viewed as (B, C, S): `batch` items of `channels` planes of `inner` = H * W values each.
struct PlanarShape {
  std::int64_t batch = 0;
  std::int64_t channels = 0;
  std::int64_t inner = 0;
  std::int64_t values_per_channel() const { return batch * inner; }
};

// The scratch, in doubles, that batchnorm_forward_train and batchnorm_backward need for `shape`:
// 2 * C * B * ceil(S / 4096) + 2 * C (about 4 KiB per channel for a 2 x 500 x 1000 batch).
std::int64_t batchnorm_workspace_doubles(const PlanarShape& shape);

// Training forward. x, y (B, C, S); gamma, beta (C); running_mean, running_var (C) updated in
// place; save_mean, save_inv_std (C) written (the batch mean and 1 / sqrt(biased variance + eps),
// what the backward needs). y may be x (in place). A channel needs more than one value (B * S !=
// 1); B * S = 0 gives save_mean = 0, save_inv_std = 1 / sqrt(eps) and leaves the running
// statistics.
void batchnorm_forward_train(const float* x, const PlanarShape& shape, const float* gamma,
                             const float* beta, float eps, float momentum, float* running_mean,
                             float* running_var, bool relu, float* y, float* save_mean,
                             float* save_inv_std, double* workspace, cudaStream_t stream,
                             ReplicaSum* replicas = nullptr);

// Evaluation forward with the running statistics. x, y (B, C, S); the others (C). y may be x.
void batchnorm_forward_eval(const float* x, const PlanarShape& shape, const float* gamma,
                            const float* beta, const float* running_mean, const float* running_var,
                            float eps, bool relu, float* y, cudaStream_t stream);

// Backward of the training forward. dy, x (B, C, S); y (B, C, S), the fused forward's output, or
// nullptr for a plain BatchNorm; gamma, save_mean, save_inv_std (C) as given to and written by the
// forward. Writes dx (B, C, S; may be dy, in place), dgamma and dbeta (C).
void batchnorm_backward(const float* dy, const float* x, const float* y, const PlanarShape& shape,
                        const float* gamma, const float* save_mean, const float* save_inv_std,
                        float* dx, float* dgamma, float* dbeta, double* workspace,
                        cudaStream_t stream, ReplicaSum* replicas = nullptr);

// ---- the second passes, shared with kernels/pfn.cu ----
// Both read per-block partial sums laid out as partials[2 * (c * parts + j)] and
// partials[2 * (c * parts + j) + 1] for channel c and part j < parts, and add the parts of a
// channel in the order j = 0, 1, ... (by the lanes of one warp, then a shuffle tree).

// Statistics from partial sums of the `count` values v of each channel taken relative to a
// shift (any value near the data, for precision): pair j = (sum (v - shift[c]), sum
// (v - shift[c])^2). Writes save_mean, save_inv_std and, when count > 0, updates the running
// statistics as batchnorm_forward_train does. shifts (C) and partials are doubles.
// With replicas (synchronised BatchNorm of a data-parallel run, core/replicas.hpp) the statistics
// are those of the values of all replicas: this replica's parts are added in part order and
// combined with the others' (their sums and counts first, then the squares about the common
// mean), and the finalize reads them as one part. With a plain ReplicaSum that happens on the
// host: the sums are brought there and written back into shifts and the first part of partials
// (so partials must have room for one part even when parts = 0), and the stream is
// synchronised. With a DeviceReplicaSum it happens on the device, in kernels and the sum's own
// scratch, queued on `stream` (shifts is overwritten with the common mean): nothing waits, and
// a total count of 1, which the host then cannot see, gives a NaN running variance instead of
// the error the host path raises.
void batchnorm_finalize_statistics(double* shifts, double* partials, std::int64_t channels,
                                   std::int64_t parts, std::int64_t count, float eps,
                                   float momentum, float* running_mean, float* running_var,
                                   float* save_mean, float* save_inv_std, cudaStream_t stream,
                                   ReplicaSum* replicas = nullptr);

// Backward sums from partials: pair j = (sum g, sum g * xhat) over parts of the `count` values of
// each channel (g the gradient reaching the BatchNorm output, xhat the normalised input).
// Writes dbeta = sum g and dgamma = sum g * xhat (C), and coefficients (2 C doubles):
// coefficients[2 c] = sum g / count, coefficients[2 c + 1] = sum g * xhat / count, with which
// dx = gamma * inv_std * (g - coefficients[2 c] - xhat * coefficients[2 c + 1]).
// With replicas, dbeta and dgamma stay this replica's own sums (its share of the parameters'
// gradient) while the coefficients are those of all replicas' values: the sums (parts added in
// part order) and counts summed over the replicas, on the host for a plain ReplicaSum (the
// stream is synchronised) and on the device for a DeviceReplicaSum (nothing waits).
void batchnorm_finalize_backward(const double* partials, std::int64_t channels, std::int64_t parts,
                                 std::int64_t count, float* dgamma, float* dbeta,
                                 double* coefficients, cudaStream_t stream,
                                 ReplicaSum* replicas = nullptr);

}  // namespace pillarseg::cuda
