// The settings of one AdamW step (Adam with decoupled weight decay), the one struct that the
// host reference (host/adam.hpp), the CUDA kernel (kernels/adam.cuh), the backends and the
// trainer share. Defaults are torch.optim.AdamW's.
#pragma once

namespace pillarseg {

struct AdamOptions {
  double lr = 1e-3;
  double beta1 = 0.9;
  double beta2 = 0.999;
  double eps = 1e-8;
  double weight_decay = 0.01;  // decoupled: params *= 1 - lr * weight_decay before the Adam update
};

}  // namespace pillarseg
