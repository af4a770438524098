#include "engine/model/backend.hpp"

#include "engine/core/error.hpp"

namespace pillarseg {

namespace {
constexpr size_t kAlignment = 64;
size_t align_up(size_t n) { return (n + kAlignment - 1) / kAlignment * kAlignment; }
}  // namespace

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

std::unique_ptr<Backend> make_backend(const std::string& device) {
  if (device == "cpu") return make_cpu_backend();
  if (device == "cuda") return make_cuda_backend();
  PS_FAIL("--device must be cpu or cuda, got '{}'", device);
}

}  // namespace pillarseg

#ifndef PILLARSEG_WITH_CUDA_BACKEND
namespace pillarseg {
std::unique_ptr<Backend> make_cuda_backend() {
  PS_FAIL("--device cuda: this build has no CUDA backend (the CUDA kernels are not wired into the engine yet; "
          "see README, 'Status'); use --device cpu");
}
}  // namespace pillarseg
#endif
