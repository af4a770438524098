// ParameterSet: every tensor of the model with its PyTorch state_dict name. Trainable
// parameters live in one flat array (values, gradients and the two Adam moments each one flat
// array), so the optimiser, the gradient norm and checkpointing work on whole arrays. BatchNorm
// running statistics are buffers in a second flat array; num_batches_tracked counters are host
// integers. Values and buffers are allocated by finalize(); the gradients and the Adam moments
// only on first use (zero-filled), so a model that only runs inference holds neither.
#pragma once

#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "engine/backend/backend.hpp"

namespace pillarseg {

struct ParamEntry {
  std::string name;
  Shape shape;
  int64_t offset = 0;  // in elements within its flat array
  bool trainable = true;
  int64_t fan_in = 0;  // for PyTorch's default initialisation; 0: constant init
  float init_value = 0.0f;  // used when fan_in == 0
};

class ParameterSet {
 public:
  explicit ParameterSet(Backend& backend);
  ~ParameterSet();
  ParameterSet(const ParameterSet&) = delete;
  ParameterSet& operator=(const ParameterSet&) = delete;

  // Declaration phase (before finalize()). Returns the index of the entry.
  int add_trainable(const std::string& name, Shape shape, int64_t fan_in, float init_value = 0.0f);
  int add_buffer(const std::string& name, Shape shape, float init_value);
  int64_t* add_counter(const std::string& name);  // num_batches_tracked
  // Allocates the flat arrays and initialises: weights and biases uniform(-1/sqrt(fan_in),
  // 1/sqrt(fan_in)) (PyTorch's default for Linear/Conv), constants elsewhere.
  void finalize(uint64_t seed);

  // The memory of a value, of all trainable values (flat) and of all buffers, to read or to write:
  // each call counts as a change (see generation()).
  Ref value(int index);
  Ref values() const {
    mark_changed();
    return values_;
  }
  Ref buffers() const {
    mark_changed();
    return buffers_;
  }
  // Which values and buffers the set holds: it changes whenever they may have changed (finalize(),
  // every upload, every call of value(), values() or buffers(), which hand out memory a caller
  // may write), so that what a model derives from them (the evaluation's prepared 16-bit weights)
  // is made again. Code that keeps such a Ref and writes through it later calls mark_changed().
  uint64_t generation() const { return generation_; }
  void mark_changed() const { ++generation_; }
  // value(index) for the model's op graph, without counting as a change: the model marks the
  // changes its own nodes make (a training forward's running statistics).
  Ref graph_value(int index) const;
  // Gradients and Adam moments (flat, num_trainable()), allocated and zero-filled on the first
  // call that asks for them.
  Ref grad(int index);
  Ref grads();
  Ref adam_m();
  Ref adam_v();
  bool has_gradients() const { return grad_block_ != nullptr; }
  bool has_optimizer_state() const { return moment_block_ != nullptr; }
  // Bytes of backend memory held: values and buffers, plus gradients and moments once used.
  size_t allocated_bytes() const;
  int64_t num_trainable() const { return trainable_count_; }
  int64_t num_buffer_values() const { return buffer_count_; }

  const std::vector<ParamEntry>& entries() const { return entries_; }
  const std::map<std::string, int64_t>& counters() const { return counters_; }
  std::map<std::string, int64_t>& counters() { return counters_; }

  // Host copies by name (state_dict order), and loading them back (shapes must match).
  Tensor<float> download(int index) const;
  void upload(int index, const Tensor<float>& t);
  int find(const std::string& name) const;  // -1 if absent
  // Every value and buffer (running statistics) of `other`, a set with the same entries (the
  // same model, possibly on another backend), through the host.
  void copy_values_from(const ParameterSet& other);

  // Whole-array host copies for checkpoints (values, m, v, buffers).
  std::vector<float> download_flat(const Ref& r) const;
  // Host copies of the Adam moments without allocating them: zeros (what Adam starts from)
  // while the model has not stepped.
  std::vector<float> download_adam_m() const;
  std::vector<float> download_adam_v() const;
  void upload_flat(const Ref& r, const std::vector<float>& data);
  void zero_grads();

 private:
  // Elements of one trainable section, rounded up to 16 floats (64-byte aligned sections).
  int64_t padded_trainable() const { return (trainable_count_ + 15) / 16 * 16; }
  // A zero-filled block of `sections` trainable sections (at least 64 bytes).
  void* allocate_sections(int sections, size_t& bytes);
  void ensure_gradients();
  void ensure_optimizer_state();

  Backend& backend_;
  std::vector<ParamEntry> entries_;
  std::map<std::string, int64_t> counters_;
  int64_t trainable_count_ = 0, buffer_count_ = 0;
  // values + buffers; gradients; m + v.
  void *value_block_ = nullptr, *grad_block_ = nullptr, *moment_block_ = nullptr;
  size_t value_bytes_ = 0, grad_bytes_ = 0, moment_bytes_ = 0;
  Ref values_, grads_, m_, v_, buffers_;
  mutable uint64_t generation_ = 0;
  bool finalized_ = false;
};

}  // namespace pillarseg
