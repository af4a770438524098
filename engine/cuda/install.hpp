// Installing the CUDA backends into make_backend() (engine/backend/backend.hpp). The engine holds no
// CUDA code; each CUDA backend library defines its installer, and a program calls the ones it
// links: the command line and the library call both.
#pragma once

namespace pillarseg {

// make_backend("cuda") builds the CUDA backend on a GPU. Defined by pillarseg_cuda_backend (the
// nvcc build).
void install_cuda_backend();

// make_backend("emu") builds the CUDA backend on the CPU emulation. Defined by
// pillarseg_cuda_backend_emu.
void install_emulated_cuda_backend();

}  // namespace pillarseg
