// safetensors files (the checkpoint format, exchanged unchanged with PyTorch): an 8-byte
// little-endian header length N, N bytes of JSON header
//   {"__metadata__": {str: str}, "name": {"dtype": "F32", "shape": [d0, ...],
//    "data_offsets": [begin, end]}, ...}
// padded with spaces, then the data buffer; offsets are relative to the buffer, tensors are
// little-endian, row-major, and must tile the buffer exactly.
// SafeTensors holds a whole file in memory as named tensors of dtype F32, F16, BF16 or I64.
// Reading validates everything and treats the file as hostile: every error names the file and
// what is wrong, and no allocation exceeds the file size. Writing is deterministic (names
// sorted, metadata first, every tensor aligned to its element size) and atomic.
#pragma once

#include <cstdint>
#include <filesystem>
#include <map>
#include <span>
#include <string>
#include <vector>

#include "core/tensor.hpp"

namespace pillarseg::weights {

enum class DType { F32, F16, BF16, I64 };

// "F32", "F16", "BF16", "I64": the names in the header.
const char* dtype_name(DType dtype);
int64_t dtype_size(DType dtype);  // bytes per element
bool is_floating(DType dtype);    // F32, F16, BF16

struct TensorRecord {
  std::string name;
  DType dtype = DType::F32;
  std::vector<int64_t> shape;  // () is a scalar with one element
  std::vector<uint8_t> bytes;  // numel(shape) * dtype_size(dtype) bytes, little-endian, row-major
};

class SafeTensors {
 public:
  SafeTensors() = default;

  // Reads and validates a file; errors name the file.
  static SafeTensors read(const std::filesystem::path& path);
  // Parses and validates a file image; `source` names it in errors (a path, or a description).
  static SafeTensors parse(std::span<const uint8_t> file, const std::string& source);

  // The file image: header with "__metadata__" first (omitted when empty), then the tensors
  // sorted by name, padded with spaces so that the data starts at a multiple of 8 bytes. The
  // data holds the widest dtypes first (I64, F32, F16/BF16; by name within a width) so that
  // every tensor is aligned to its element size, as the reference writer does. Same contents
  // give the same bytes.
  std::vector<uint8_t> serialize() const;
  // serialize() written with write_file_atomic (temporary file, then rename), synced to disk
  // (checkpoints survive a crash of the machine, not only of the process).
  void write(const std::filesystem::path& path) const;

  // Adds a float tensor stored as F32, F16 or BF16 (rounded to nearest even). A finite value
  // that overflows F16 is an error rather than a silent Inf. Names must be new, non-empty,
  // valid UTF-8 and not "__metadata__".
  void add_f32(const std::string& name, const Tensor<float>& tensor, DType stored = DType::F32);
  // Adds an I64 tensor (e.g. BatchNorm num_batches_tracked, shape ()); values.size() must be
  // the element count of shape.
  void add_i64(const std::string& name, std::vector<int64_t> shape, std::vector<int64_t> values);
  // Adds a record as is (its bytes must match its shape and dtype).
  void add(TensorRecord record);

  bool contains(const std::string& name) const;
  std::vector<std::string> names() const;  // sorted
  size_t size() const { return tensors_.size(); }
  // The file this was read from, or "<in-memory safetensors>".
  const std::string& source() const { return source_; }

  // The record; a missing name is an error naming the file and the tensor.
  const TensorRecord& at(const std::string& name) const;
  // F32, F16 or BF16 converted to float (exactly); I64 is an error.
  Tensor<float> get_f32(const std::string& name) const;
  // As get_f32, and the shape must equal expected_shape.
  Tensor<float> get_f32(const std::string& name, const Shape& expected_shape) const;
  // An I64 tensor's values, row-major; other dtypes are an error.
  std::vector<int64_t> get_i64(const std::string& name) const;

  std::map<std::string, std::string> metadata;  // the "__metadata__" object

 private:
  void check_new_name(const std::string& name) const;

  std::map<std::string, TensorRecord> tensors_;
  std::string source_ = "<in-memory safetensors>";
};

// What a tensor's values are: Float accepts F32/F16/BF16, Integer accepts I64.
enum class ValueKind { Float, Integer };

struct ExpectedTensor {
  std::string name;
  Shape shape;
  ValueKind kind = ValueKind::Float;
};

// Checks that `file` holds exactly the expected tensors: throws one Error listing every
// missing, unexpected, wrong-shape and wrong-dtype tensor. `what` says what the file is meant
// to be (e.g. "PillarSegNet checkpoint") and leads the message.
void check_names_and_shapes(const SafeTensors& file, const std::vector<ExpectedTensor>& expected,
                            const std::string& what);

}  // namespace pillarseg::weights
