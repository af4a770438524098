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
#include <algorithm>
#include <numeric>
#include <string>
#include <vector>

#include "core/error.hpp"

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

// A Tensor either owns its storage or is a view of memory owned elsewhere (an arena):
// Tensor<T>::view(ptr, shape). A view never reallocates: resize() to a shape with the same
// element count zero-fills it in place, assignment copies elements into it, and copying a
// view gives an owning tensor. Ops write outputs through resize(), so the same op code
// serves owning tensors and arena views.
template <class T>
class Tensor {
 public:
  Tensor() = default;
  explicit Tensor(Shape shape, T value = T{}) : shape_(std::move(shape)) {
    for (int64_t d : shape_) PS_CHECK(d >= 0, "tensor shape {} has a negative dimension", shape_str(shape_));
    data_.assign(static_cast<size_t>(shape_numel(shape_)), value);
    numel_ = static_cast<int64_t>(data_.size());
  }
  static Tensor zeros(Shape shape) { return Tensor(std::move(shape), T{}); }
  static Tensor view(T* data, Shape shape) {
    Tensor t;
    t.shape_ = std::move(shape);
    t.numel_ = shape_numel(t.shape_);
    t.view_ = data;
    return t;
  }

  Tensor(const Tensor& other) : shape_(other.shape_), numel_(other.numel_) {
    data_.assign(other.data(), other.data() + other.numel_);
  }
  Tensor(Tensor&& other) noexcept
      : shape_(std::move(other.shape_)), data_(std::move(other.data_)), view_(other.view_), numel_(other.numel_) {
    other.view_ = nullptr;
    other.numel_ = 0;
    other.shape_.clear();
  }
  Tensor& operator=(const Tensor& other) {
    if (this == &other) return *this;
    if (view_) {
      copy_into_view(other);
    } else {
      shape_ = other.shape_;
      numel_ = other.numel_;
      data_.assign(other.data(), other.data() + other.numel_);
    }
    return *this;
  }
  Tensor& operator=(Tensor&& other) {
    if (this == &other) return *this;
    if (view_) {
      copy_into_view(other);
    } else {
      shape_ = std::move(other.shape_);
      data_ = std::move(other.data_);
      view_ = other.view_;
      numel_ = other.numel_;
      other.view_ = nullptr;
      other.numel_ = 0;
      other.shape_.clear();
    }
    return *this;
  }
  ~Tensor() = default;

  const Shape& shape() const { return shape_; }
  int64_t dim(int i) const { return shape_.at(static_cast<size_t>(i < 0 ? static_cast<int>(shape_.size()) + i : i)); }
  int rank() const { return static_cast<int>(shape_.size()); }
  int64_t numel() const { return numel_; }
  bool empty() const { return numel_ == 0; }
  bool is_view() const { return view_ != nullptr; }

  T* data() { return view_ ? view_ : data_.data(); }
  const T* data() const { return view_ ? view_ : data_.data(); }
  T& operator[](int64_t i) { return data()[i]; }
  const T& operator[](int64_t i) const { return data()[i]; }
  T* begin() { return data(); }
  T* end() { return data() + numel_; }
  const T* begin() const { return data(); }
  const T* end() const { return data() + numel_; }

  // Multi-index access, row-major: t(c, y, x).
  template <class... I>
  T& operator()(I... idx) { return data()[offset(idx...)]; }
  template <class... I>
  const T& operator()(I... idx) const { return data()[offset(idx...)]; }

  // The elements as a plain vector (a copy), e.g. to compare in tests.
  std::vector<T> values() const { return std::vector<T>(begin(), end()); }
  // Same shape and the same elements (bitwise equal for floats, so NaN != NaN).
  bool operator==(const Tensor& other) const {
    return shape_ == other.shape_ && std::equal(begin(), end(), other.begin());
  }

  void fill(T value) { std::fill(begin(), end(), value); }
  void set_zero() { fill(T{}); }
  // Same data, new shape with the same element count.
  void reshape(Shape shape) {
    PS_CHECK(shape_numel(shape) == numel_, "cannot reshape {} to {}", shape_str(shape_), shape_str(shape));
    shape_ = std::move(shape);
  }
  // New shape filled with value, reusing the allocation when it is large enough.
  void assign(Shape shape, T value) {
    resize_for_overwrite(std::move(shape));
    fill(value);
  }
  // New shape whose every element the caller will write: keeps the allocation and leaves the
  // contents unspecified (no zero-fill pass). A view must keep its element count.
  void resize_for_overwrite(Shape shape) {
    const int64_t n = shape_numel(shape);
    if (view_) {
      PS_CHECK(n == numel_, "a view of shape {} cannot be resized to {}", shape_str(shape_), shape_str(shape));
    } else {
      data_.resize(static_cast<size_t>(n));
      numel_ = n;
    }
    shape_ = std::move(shape);
  }
  // New shape; contents are zero. A view keeps its memory and must keep its element count.
  void resize(Shape shape) {
    if (view_) {
      PS_CHECK(shape_numel(shape) == numel_, "a view of shape {} cannot be resized to {}", shape_str(shape_),
               shape_str(shape));
      shape_ = std::move(shape);
      set_zero();
      return;
    }
    shape_ = std::move(shape);
    data_.assign(static_cast<size_t>(shape_numel(shape_)), T{});
    numel_ = static_cast<int64_t>(data_.size());
  }

 private:
  void copy_into_view(const Tensor& other) {
    PS_CHECK(other.numel_ == numel_, "cannot assign a tensor of shape {} to a view of shape {}",
             shape_str(other.shape_), shape_str(shape_));
    shape_ = other.shape_;
    std::copy(other.data(), other.data() + numel_, view_);
  }
  template <class... I>
  int64_t offset(I... idx) const {
    const int64_t index[] = {static_cast<int64_t>(idx)...};
    int64_t off = 0;
    for (size_t i = 0; i < sizeof...(I); ++i) off = off * shape_[i] + index[i];
    return off;
  }

  Shape shape_;
  AlignedVector<T> data_;
  T* view_ = nullptr;  // non-null: a view of memory owned elsewhere
  int64_t numel_ = 0;
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
