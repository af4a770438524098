// The one header through which kernels and the CUDA backend see CUDA: the real <cuda_runtime.h>
// under nvcc or a CUDA host build, or, with PILLARSEG_CUDA_EMULATION defined (the
// pillarseg_kernels_emu library), the host emulation of kernels/emu/: the runtime API, the device
// vocabulary (qualifiers, threadIdx..., __syncthreads, shuffles, votes, atomics) and the types.
#pragma once

#if defined(PILLARSEG_CUDA_EMULATION)
#if defined(__CUDACC__)
#error "PILLARSEG_CUDA_EMULATION is for the host compiler; nvcc builds use the real CUDA runtime"
#endif
#include "kernels/emu/emu_device.hpp"
#include "kernels/emu/emu_runtime.hpp"
#include "kernels/emu/emu_types.hpp"
#else
#include <cuda_runtime.h>
#endif
