#include "engine/model/backend.hpp"

#include <atomic>
#include <chrono>

#include "core/error.hpp"

namespace pillarseg {

namespace {
constexpr size_t kAlignment = 64;
size_t align_up(size_t n) { return (n + kAlignment - 1) / kAlignment * kAlignment; }
std::atomic<BackendFactory> cuda_backend_factory{nullptr};
}  // namespace

double Backend::clock_ms() {
  synchronize();
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

std::unique_ptr<CapturedGraph> Backend::capture(const std::function<void()>&) {
  PS_FAIL("backend {} cannot capture graphs (check supports_capture() first)", name());
}

void Arena::reserve(size_t bytes) {
  measuring_ = false;
  if (bytes <= capacity_ && base_) return;
  release();
  capacity_ = std::max<size_t>(align_up(bytes), kAlignment);
  base_ = backend_->allocate(capacity_);
  used_ = 0;
}

void Arena::release() noexcept {
  if (base_) backend_->deallocate(base_);
  base_ = nullptr;
  capacity_ = 0;
  used_ = 0;
}

void* Arena::take_bytes(size_t bytes) {
  const size_t offset = used_;
  used_ += align_up(bytes);
  if (measuring_) return nullptr;
  PS_CHECK(used_ <= capacity_, "arena overflow: {} bytes requested, capacity {} (plan the arena before use)", used_,
           capacity_);
  return static_cast<char*>(base_) + offset;
}

void set_cuda_backend_factory(BackendFactory factory) { cuda_backend_factory.store(factory); }

std::unique_ptr<Backend> make_cuda_backend(const std::string& convolution) {
  const BackendFactory factory = cuda_backend_factory.load();
  PS_CHECK(factory != nullptr,
           "--device cuda: this build has no CUDA backend (configure with the CUDA toolkit installed, so that "
           "CMake finds nvcc); use --device cpu");
  return factory(convolution);
}

std::unique_ptr<Backend> make_backend(const std::string& device, const std::string& convolution) {
  if (device == "cpu") {
    PS_CHECK(convolution == "own", "--conv {} needs --device cuda (the CPU backend has one convolution)",
             convolution);
    return make_cpu_backend();
  }
  if (device == "cuda") return make_cuda_backend(convolution);
  PS_FAIL("--device must be cpu or cuda, got '{}'", device);
}

}  // namespace pillarseg
