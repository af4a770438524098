// PILLARSEG_HOST_DEVICE: a core/ function that the host reference and the CUDA kernels both call
// (nvcc compiles it for both sides; every other compiler, the emulation's included, sees a plain
// function).
#pragma once

#if defined(__CUDACC__)
#define PILLARSEG_HOST_DEVICE __host__ __device__
#else
#define PILLARSEG_HOST_DEVICE
#endif
