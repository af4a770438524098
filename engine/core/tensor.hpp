// Tensor<T>: an owning, 64-byte aligned, row-major host array with a shape, e.g. (C, H, W).
// Views on it are Eigen::Map or raw pointers; the host reference ops take Tensor<T>&.
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <initializer_list>
#include <memory>
#include <new>
#include <numeric>
#include <string>
#include <vector>

#include "engine/core/error.hpp"

namespace pillarseg {

using Shape = std::vector<int64_t>;

inline int64_t shape_numel(const Shape& shape) {
  return std::accumulate(shape.begin(), shape.end(), int64_t{1}, std::multiplies<>());
}

inline std::string shape_str(const Shape& shape) {
  std::string s = "(";
  for (size_t i = 0; i < shape.size(); ++i) s += (i ? ", " : "") + std::to_string(shape[i]);
  return s + ")";
}

// Allocator for 64-byte aligned storage (cache lines, AVX-512 loads).
template <class T>
struct AlignedAllocator {
  using value_type = T;
  static constexpr std::size_t kAlignment = 64;
  AlignedAllocator() = default;
  template <class U>
  AlignedAllocator(const AlignedAllocator<U>&) {}
  T* allocate(std::size_t n) {
    if (n == 0) return nullptr;
    std::size_t bytes = (n * sizeof(T) + kAlignment - 1) / kAlignment * kAlignment;
    void* p = std::aligned_alloc(kAlignment, bytes);
    if (!p) throw std::bad_alloc();
    return static_cast<T*>(p);
  }
  void deallocate(T* p, std::size_t) noexcept { std::free(p); }
  template <class U>
  bool operator==(const AlignedAllocator<U>&) const { return true; }
};

template <class T>
using AlignedVector = std::vector<T, AlignedAllocator<T>>;

template <class T>
class Tensor {
 public:
  Tensor() = default;
  explicit Tensor(Shape shape, T value = T{}) : shape_(std::move(shape)) {
    for (int64_t d : shape_) PS_CHECK(d >= 0, "tensor shape {} has a negative dimension", shape_str(shape_));
    data_.assign(static_cast<size_t>(shape_numel(shape_)), value);
  }
  static Tensor zeros(Shape shape) { return Tensor(std::move(shape), T{}); }

  const Shape& shape() const { return shape_; }
  int64_t dim(int i) const { return shape_.at(i < 0 ? shape_.size() + i : i); }
  int rank() const { return static_cast<int>(shape_.size()); }
  int64_t numel() const { return static_cast<int64_t>(data_.size()); }
  bool empty() const { return data_.empty(); }

  T* data() { return data_.data(); }
  const T* data() const { return data_.data(); }
  T& operator[](int64_t i) { return data_[static_cast<size_t>(i)]; }
  const T& operator[](int64_t i) const { return data_[static_cast<size_t>(i)]; }

  // Multi-index access, row-major: t(c, y, x).
  template <class... I>
  T& operator()(I... idx) { return data_[static_cast<size_t>(offset(idx...))]; }
  template <class... I>
  const T& operator()(I... idx) const { return data_[static_cast<size_t>(offset(idx...))]; }

  void fill(T value) { std::fill(data_.begin(), data_.end(), value); }
  void set_zero() { fill(T{}); }
  // Same data, new shape with the same element count.
  void reshape(Shape shape) {
    PS_CHECK(shape_numel(shape) == numel(), "cannot reshape {} to {}", shape_str(shape_), shape_str(shape));
    shape_ = std::move(shape);
  }
  // New shape; contents are zero.
  void resize(Shape shape) {
    shape_ = std::move(shape);
    data_.assign(static_cast<size_t>(shape_numel(shape_)), T{});
  }

  AlignedVector<T>& storage() { return data_; }
  const AlignedVector<T>& storage() const { return data_; }

 private:
  template <class... I>
  int64_t offset(I... idx) const {
    const int64_t index[] = {static_cast<int64_t>(idx)...};
    int64_t off = 0;
    for (size_t i = 0; i < sizeof...(I); ++i) off = off * shape_[i] + index[i];
    return off;
  }

  Shape shape_;
  AlignedVector<T> data_;
};

using TensorF = Tensor<float>;
using TensorD = Tensor<double>;

// Converts element type (e.g. float -> double for finite-difference checks).
template <class To, class From>
Tensor<To> tensor_cast(const Tensor<From>& t) {
  Tensor<To> out(t.shape());
  for (int64_t i = 0; i < t.numel(); ++i) out[i] = static_cast<To>(t[i]);
  return out;
}

}  // namespace pillarseg
