// Linked into the *_gpu test executables (tests/CMakeLists.txt): the kernel and CUDA-backend
// tests built against the nvcc kernels instead of the emulation. On a machine without a usable
// CUDA device every test is skipped, with the runtime's reason.
#include <cuda_runtime.h>
#include <gtest/gtest.h>

namespace {

class CudaDeviceEnvironment : public ::testing::Environment {
 public:
  void SetUp() override {
    int devices = 0;
    const cudaError_t status = cudaGetDeviceCount(&devices);
    if (status != cudaSuccess) {
      GTEST_SKIP() << "no CUDA device: cudaGetDeviceCount failed with " << cudaGetErrorName(status) << " ("
                   << cudaGetErrorString(status) << ")";
    }
    if (devices == 0) GTEST_SKIP() << "no CUDA device: cudaGetDeviceCount found none";
  }
};

const ::testing::Environment* const kEnvironment =
    ::testing::AddGlobalTestEnvironment(new CudaDeviceEnvironment);

}  // namespace
