// The one header through which kernels and the CUDA backend see CUDA: the real <cuda_runtime.h>
// under nvcc or a CUDA host build, or, with PILLARSEG_CUDA_EMULATION defined (the
// pillarseg_kernels_emu library), the host emulation of kernels/emu/: the runtime API, the device
// vocabulary (qualifiers, threadIdx..., __syncthreads, shuffles, votes, atomics) and the types.
#pragma once

// Everything built on CUDA lives in an inline namespace named for the build: pillarseg::cuda::gpu
// (nvcc, a GPU) or pillarseg::cuda::emulated (the host compiler on the emulation), and likewise
// the CUDA backend in pillarseg::gpu or pillarseg::emulated. Code names them as pillarseg::cuda::X
// and pillarseg::CudaBackend; a program can link both builds (the command line and the library
// run --device cuda and --device emu) and each keeps its own launchers, buffers and backend.
#if defined(PILLARSEG_CUDA_EMULATION)
#define PILLARSEG_CUDA_NAMESPACE emulated
#else
#define PILLARSEG_CUDA_NAMESPACE gpu
#endif

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
