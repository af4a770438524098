#include "engine/model/parameters.hpp"

#include <cmath>

#include "engine/core/error.hpp"
#include "engine/core/rng.hpp"

namespace pillarseg {

ParameterSet::ParameterSet(Backend& backend) : backend_(backend) {}

ParameterSet::~ParameterSet() {
  if (block_) backend_.deallocate(block_);
}

int ParameterSet::add_trainable(const std::string& name, Shape shape, int64_t fan_in, float init_value) {
  PS_CHECK(!finalized_, "parameter {} declared after finalize()", name);
  PS_CHECK(find(name) < 0, "duplicate parameter name {}", name);
  ParamEntry e{name, shape, trainable_count_, true, fan_in, init_value};
  trainable_count_ += shape_numel(shape);
  entries_.push_back(std::move(e));
  return static_cast<int>(entries_.size()) - 1;
}

int ParameterSet::add_buffer(const std::string& name, Shape shape, float init_value) {
  PS_CHECK(!finalized_, "buffer {} declared after finalize()", name);
  PS_CHECK(find(name) < 0, "duplicate parameter name {}", name);
  ParamEntry e{name, shape, buffer_count_, false, 0, init_value};
  buffer_count_ += shape_numel(shape);
  entries_.push_back(std::move(e));
  return static_cast<int>(entries_.size()) - 1;
}

int64_t* ParameterSet::add_counter(const std::string& name) {
  PS_CHECK(!finalized_, "counter {} declared after finalize()", name);
  return &counters_[name];
}

void ParameterSet::finalize(uint64_t seed) {
  PS_CHECK(!finalized_, "ParameterSet::finalize() called twice");
  finalized_ = true;
  // 64-byte aligned sections: values, grads, m, v (trainable count each), buffers.
  const auto padded = [](int64_t n) { return (n + 15) / 16 * 16; };
  const int64_t t = padded(trainable_count_), b = padded(buffer_count_);
  const size_t bytes = static_cast<size_t>(4 * t + b) * sizeof(float);
  block_ = backend_.allocate(bytes == 0 ? 64 : bytes);
  auto* base = static_cast<float*>(block_);
  values_ = {base, {trainable_count_}};
  grads_ = {base + t, {trainable_count_}};
  m_ = {base + 2 * t, {trainable_count_}};
  v_ = {base + 3 * t, {trainable_count_}};
  buffers_ = {base + 4 * t, {buffer_count_}};
  backend_.fill_zero(block_, bytes);

  std::vector<float> host_values(static_cast<size_t>(trainable_count_));
  std::vector<float> host_buffers(static_cast<size_t>(buffer_count_));
  Rng rng(seed);
  for (const ParamEntry& e : entries_) {
    std::vector<float>& dst = e.trainable ? host_values : host_buffers;
    const int64_t n = shape_numel(e.shape);
    if (e.fan_in > 0) {
      const double bound = 1.0 / std::sqrt(static_cast<double>(e.fan_in));
      for (int64_t i = 0; i < n; ++i) dst[static_cast<size_t>(e.offset + i)] = static_cast<float>(rng.uniform(-bound, bound));
    } else {
      for (int64_t i = 0; i < n; ++i) dst[static_cast<size_t>(e.offset + i)] = e.init_value;
    }
  }
  upload_flat(values_, host_values);
  upload_flat(buffers_, host_buffers);
}

int ParameterSet::find(const std::string& name) const {
  for (size_t i = 0; i < entries_.size(); ++i)
    if (entries_[i].name == name) return static_cast<int>(i);
  return -1;
}

Ref ParameterSet::value(int index) {
  const ParamEntry& e = entries_.at(static_cast<size_t>(index));
  return {(e.trainable ? values_.data : buffers_.data) + e.offset, e.shape};
}

Ref ParameterSet::grad(int index) {
  const ParamEntry& e = entries_.at(static_cast<size_t>(index));
  PS_CHECK(e.trainable, "{} is a buffer and has no gradient", e.name);
  return {grads_.data + e.offset, e.shape};
}

Tensor<float> ParameterSet::download(int index) const {
  const ParamEntry& e = entries_.at(static_cast<size_t>(index));
  Tensor<float> t(e.shape);
  const float* src = (e.trainable ? values_.data : buffers_.data) + e.offset;
  backend_.download(t.data(), src, static_cast<size_t>(t.numel()) * sizeof(float));
  return t;
}

void ParameterSet::upload(int index, const Tensor<float>& t) {
  const ParamEntry& e = entries_.at(static_cast<size_t>(index));
  PS_CHECK(t.shape() == e.shape, "{}: shape {} does not match the model's {}", e.name, shape_str(t.shape()),
           shape_str(e.shape));
  float* dst = (e.trainable ? values_.data : buffers_.data) + e.offset;
  backend_.upload(dst, t.data(), static_cast<size_t>(t.numel()) * sizeof(float));
}

std::vector<float> ParameterSet::download_flat(const Ref& r) const {
  std::vector<float> out(static_cast<size_t>(r.numel()));
  if (!out.empty()) backend_.download(out.data(), r.data, r.bytes());
  return out;
}

void ParameterSet::upload_flat(const Ref& r, const std::vector<float>& data) {
  PS_CHECK(static_cast<int64_t>(data.size()) == r.numel(), "flat parameter array has {} values, expected {}",
           data.size(), r.numel());
  if (!data.empty()) backend_.upload(r.data, data.data(), r.bytes());
}

void ParameterSet::zero_grads() {
  if (grads_.numel()) backend_.fill_zero(grads_.data, grads_.bytes());
}

}  // namespace pillarseg
