// DeviceBuffer<T>: `size()` elements of T in device memory, allocated with cudaMalloc through
// PS_CUDA_CHECK and freed by the destructor; move-only. With the arena, the only owner of device
// memory: nothing else calls cudaMalloc.
#pragma once

#include <cstddef>
#include <limits>
#include <span>
#include <type_traits>
#include <utility>
#include <vector>

#include "core/error.hpp"
#include "kernels/common.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

template <class T>
class DeviceBuffer {
  static_assert(std::is_trivially_copyable_v<T>, "device memory holds trivially copyable values");

 public:
  DeviceBuffer() = default;

  // `count` uninitialised elements (none: no allocation, data() is nullptr).
  explicit DeviceBuffer(std::size_t count) {
    PS_CHECK(count <= std::numeric_limits<std::size_t>::max() / sizeof(T),
             "DeviceBuffer: {} elements of {} bytes overflow the address space", count, sizeof(T));
    if (count == 0) return;
    PS_CUDA_CHECK(cudaMalloc(&data_, count * sizeof(T)));
    count_ = count;
  }

  // A buffer holding a copy of `host`.
  static DeviceBuffer from_host(std::span<const T> host, cudaStream_t stream = nullptr) {
    DeviceBuffer buffer(host.size());
    buffer.copy_from_host(host, stream);
    return buffer;
  }

  ~DeviceBuffer() { release(); }
  DeviceBuffer(DeviceBuffer&& other) noexcept
      : data_(std::exchange(other.data_, nullptr)), count_(std::exchange(other.count_, 0)) {}
  DeviceBuffer& operator=(DeviceBuffer&& other) noexcept {
    if (this != &other) {
      release();
      data_ = std::exchange(other.data_, nullptr);
      count_ = std::exchange(other.count_, 0);
    }
    return *this;
  }
  DeviceBuffer(const DeviceBuffer&) = delete;
  DeviceBuffer& operator=(const DeviceBuffer&) = delete;

  T* data() noexcept { return data_; }
  const T* data() const noexcept { return data_; }
  std::size_t size() const noexcept { return count_; }
  std::size_t bytes() const noexcept { return count_ * sizeof(T); }
  bool empty() const noexcept { return count_ == 0; }

  // Copies `host` (size() elements) into the buffer, in order on `stream`.
  void copy_from_host(std::span<const T> host, cudaStream_t stream = nullptr) {
    PS_CHECK(host.size() == count_,
             "DeviceBuffer::copy_from_host: the host data has {} elements, the buffer {}",
             host.size(), count_);
    PS_CUDA_CHECK(cudaMemcpyAsync(data_, host.data(), bytes(), cudaMemcpyHostToDevice, stream));
  }

  // Copies the buffer into `host` (size() elements) after the work queued on `stream`, and waits.
  void copy_to_host(std::span<T> host, cudaStream_t stream = nullptr) const {
    PS_CHECK(host.size() == count_,
             "DeviceBuffer::copy_to_host: the host data has {} elements, the buffer {}",
             host.size(), count_);
    PS_CUDA_CHECK(cudaMemcpyAsync(host.data(), data_, bytes(), cudaMemcpyDeviceToHost, stream));
    PS_CUDA_CHECK(cudaStreamSynchronize(stream));
  }

  std::vector<T> to_host(cudaStream_t stream = nullptr) const {
    std::vector<T> host(count_);
    copy_to_host(host, stream);
    return host;
  }

  // Sets every byte to zero, in order on `stream`.
  void fill_zero(cudaStream_t stream = nullptr) {
    PS_CUDA_CHECK(cudaMemsetAsync(data_, 0, bytes(), stream));
  }

 private:
  void release() noexcept {
    // A destructor cannot throw; cudaFree only fails for a context that is already broken, which
    // the next checked call reports.
    if (data_ != nullptr) static_cast<void>(cudaFree(data_));
    data_ = nullptr;
    count_ = 0;
  }

  T* data_ = nullptr;
  std::size_t count_ = 0;
};

}  // namespace pillarseg::cuda
