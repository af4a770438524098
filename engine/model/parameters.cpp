#include "engine/model/parameters.hpp"

#include <algorithm>
#include <cmath>

#include "core/error.hpp"
#include "core/rng.hpp"

namespace pillarseg {

ParameterSet::ParameterSet(Backend& backend) : backend_(backend) {}

ParameterSet::~ParameterSet() {
  for (void* block : {value_block_, grad_block_, moment_block_})
    if (block) backend_.deallocate(block);
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
  // 64-byte aligned sections: values, buffers. Both are uploaded whole below.
  const int64_t t = padded_trainable(), b = (buffer_count_ + 15) / 16 * 16;
  value_bytes_ = std::max<size_t>(static_cast<size_t>(t + b) * sizeof(float), 64);
  value_block_ = backend_.allocate(value_bytes_);
  auto* base = static_cast<float*>(value_block_);
  values_ = {base, {trainable_count_}};
  buffers_ = {base + t, {buffer_count_}};

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
  mark_changed();
  return graph_value(index);
}

Ref ParameterSet::graph_value(int index) const {
  const ParamEntry& e = entries_.at(static_cast<size_t>(index));
  return {(e.trainable ? values_.data : buffers_.data) + e.offset, e.shape};
}

void* ParameterSet::allocate_sections(int sections, size_t& bytes) {
  PS_CHECK(finalized_, "ParameterSet: gradients or optimizer state asked for before finalize()");
  bytes = std::max<size_t>(static_cast<size_t>(sections * padded_trainable()) * sizeof(float), 64);
  void* block = backend_.allocate(bytes);
  backend_.fill_zero(block, bytes);
  return block;
}

void ParameterSet::ensure_gradients() {
  if (grad_block_) return;
  grad_block_ = allocate_sections(1, grad_bytes_);
  grads_ = {static_cast<float*>(grad_block_), {trainable_count_}};
}

void ParameterSet::ensure_optimizer_state() {
  if (moment_block_) return;
  moment_block_ = allocate_sections(2, moment_bytes_);
  auto* base = static_cast<float*>(moment_block_);
  m_ = {base, {trainable_count_}};
  v_ = {base + padded_trainable(), {trainable_count_}};
}

Ref ParameterSet::grad(int index) {
  const ParamEntry& e = entries_.at(static_cast<size_t>(index));
  PS_CHECK(e.trainable, "{} is a buffer and has no gradient", e.name);
  ensure_gradients();
  return {grads_.data + e.offset, e.shape};
}

Ref ParameterSet::grads() {
  ensure_gradients();
  return grads_;
}

Ref ParameterSet::adam_m() {
  ensure_optimizer_state();
  return m_;
}

Ref ParameterSet::adam_v() {
  ensure_optimizer_state();
  return v_;
}

size_t ParameterSet::allocated_bytes() const { return value_bytes_ + grad_bytes_ + moment_bytes_; }

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
  mark_changed();
}

void ParameterSet::copy_values_from(const ParameterSet& other) {
  PS_CHECK(other.entries_.size() == entries_.size(), "copying parameters: {} entries into a model of {}",
           other.entries_.size(), entries_.size());
  for (size_t i = 0; i < entries_.size(); ++i) {
    PS_CHECK(other.entries_[i].name == entries_[i].name, "copying parameters: entry {} is {}, not {}", i,
             other.entries_[i].name, entries_[i].name);
    upload(static_cast<int>(i), other.download(static_cast<int>(i)));
  }
}

std::vector<float> ParameterSet::download_flat(const Ref& r) const {
  std::vector<float> out(static_cast<size_t>(r.numel()));
  if (!out.empty()) backend_.download(out.data(), r.data, r.bytes());
  return out;
}

std::vector<float> ParameterSet::download_adam_m() const {
  return moment_block_ ? download_flat(m_) : std::vector<float>(static_cast<size_t>(trainable_count_), 0.0f);
}

std::vector<float> ParameterSet::download_adam_v() const {
  return moment_block_ ? download_flat(v_) : std::vector<float>(static_cast<size_t>(trainable_count_), 0.0f);
}

void ParameterSet::upload_flat(const Ref& r, const std::vector<float>& data) {
  PS_CHECK(static_cast<int64_t>(data.size()) == r.numel(), "flat parameter array has {} values, expected {}",
           data.size(), r.numel());
  if (!data.empty()) backend_.upload(r.data, data.data(), r.bytes());
  mark_changed();
}

void ParameterSet::zero_grads() {
  if (!grad_block_) {
    ensure_gradients();  // zero-filled
    return;
  }
  backend_.fill_zero(grad_block_, grad_bytes_);
}

}  // namespace pillarseg
