// safetensors reading (validation of every header field against the file before any use) and
// writing (deterministic header and layout), plus the checkpoint name/shape check.
#include "weights_io/safetensors.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <cstring>
#include <limits>
#include <optional>
#include <set>
#include <string_view>
#include <tuple>

#include "core/error.hpp"
#include "core/io.hpp"
#include "weights_io/half.hpp"
#include "weights_io/json.hpp"

namespace pillarseg::weights {

// Tensor bytes are copied to and from host arrays with memcpy, which is only the file's
// little-endian layout on a little-endian host (every platform the engine targets).
static_assert(std::endian::native == std::endian::little,
              "safetensors I/O assumes a little-endian host");

namespace {

// The reference implementation refuses headers above 100 MB; so do we, before parsing.
constexpr uint64_t kMaxHeaderBytes = 100'000'000;
constexpr std::string_view kMetadataKey = "__metadata__";

// Valid safetensors dtypes this engine does not load, so that a foreign file gets a precise
// message rather than "unknown dtype".
constexpr std::array<std::string_view, 16> kUnsupportedDtypes = {
    "BOOL", "U8",  "I8",      "I16",     "U16",     "I32",     "U32",     "U64",
    "F64",  "C64", "F8_E5M2", "F8_E4M3", "F8_E8M0", "F6_E2M3", "F6_E3M2", "F4"};

std::optional<DType> dtype_from_name(std::string_view name) {
  if (name == "F32") return DType::F32;
  if (name == "F16") return DType::F16;
  if (name == "BF16") return DType::BF16;
  if (name == "I64") return DType::I64;
  return std::nullopt;
}

// numel(shape) * dtype_size, or nullopt if a dimension is negative or the size exceeds
// max_bytes (checked before each multiplication, so nothing overflows).
std::optional<int64_t> checked_byte_size(const std::vector<int64_t>& shape, DType dtype,
                                         int64_t max_bytes) {
  for (const int64_t d : shape) {
    if (d < 0) return std::nullopt;
    if (d == 0) return 0;
  }
  int64_t bytes = dtype_size(dtype);
  for (const int64_t d : shape) {
    if (bytes > max_bytes / d) return std::nullopt;
    bytes *= d;
  }
  if (bytes > max_bytes) return std::nullopt;
  return bytes;
}

uint64_t load_u64_le(const uint8_t* p) {
  uint64_t v = 0;
  for (int i = 7; i >= 0; --i) v = (v << 8) | p[i];
  return v;
}

void store_u64_le(uint64_t v, uint8_t* p) {
  for (int i = 0; i < 8; ++i) p[i] = static_cast<uint8_t>(v >> (8 * i));
}

// One header entry after field validation, before the layout check.
struct HeaderEntry {
  std::string name;
  DType dtype;
  std::vector<int64_t> shape;
  int64_t begin;
  int64_t end;
};

HeaderEntry parse_entry(const std::string& file, const std::string& name, const json::Value& entry,
                        int64_t buffer_size) {
  PS_CHECK(entry.is_object(),
           "{}: tensor \"{}\": expected an object with dtype, shape and data_offsets, found {}",
           file, name, json::kind_name(entry.kind()));
  for (const auto& [key, value] : entry.members()) {
    PS_CHECK(key == "dtype" || key == "shape" || key == "data_offsets",
             "{}: tensor \"{}\": unknown field \"{}\" (expected dtype, shape, data_offsets)", file,
             name, key);
  }
  const json::Value* dtype_value = entry.find("dtype");
  const json::Value* shape_value = entry.find("shape");
  const json::Value* offsets_value = entry.find("data_offsets");
  PS_CHECK(dtype_value, "{}: tensor \"{}\" has no \"dtype\"", file, name);
  PS_CHECK(shape_value, "{}: tensor \"{}\" has no \"shape\"", file, name);
  PS_CHECK(offsets_value, "{}: tensor \"{}\" has no \"data_offsets\"", file, name);

  PS_CHECK(dtype_value->is_string(), "{}: tensor \"{}\": dtype must be a string, found {}", file,
           name, json::kind_name(dtype_value->kind()));
  const std::string& dtype_text = dtype_value->as_string();
  const std::optional<DType> dtype = dtype_from_name(dtype_text);
  if (!dtype) {
    const bool known = std::find(kUnsupportedDtypes.begin(), kUnsupportedDtypes.end(),
                                 dtype_text) != kUnsupportedDtypes.end();
    PS_CHECK(!known,
             "{}: tensor \"{}\" has dtype {}, which pillarseg does not load (supported: F32, F16, "
             "BF16, I64); convert the tensor before exporting",
             file, name, dtype_text);
    PS_FAIL("{}: tensor \"{}\" has unknown dtype \"{}\" (expected F32, F16, BF16 or I64)", file,
            name, dtype_text);
  }

  PS_CHECK(shape_value->is_array(), "{}: tensor \"{}\": shape must be an array, found {}", file,
           name, json::kind_name(shape_value->kind()));
  std::vector<int64_t> shape;
  for (const json::Value& d : shape_value->items()) {
    PS_CHECK(d.is_integer() && d.as_integer() >= 0,
             "{}: tensor \"{}\": shape entries must be non-negative integers, found {}", file, name,
             d.is_integer() ? std::to_string(d.as_integer()) : json::kind_name(d.kind()));
    shape.push_back(d.as_integer());
  }

  PS_CHECK(offsets_value->is_array() && offsets_value->items().size() == 2,
           "{}: tensor \"{}\": data_offsets must be an array [begin, end]", file, name);
  const json::Value& begin_value = offsets_value->items()[0];
  const json::Value& end_value = offsets_value->items()[1];
  PS_CHECK(begin_value.is_integer() && end_value.is_integer(),
           "{}: tensor \"{}\": data_offsets must be two integers", file, name);
  const int64_t begin = begin_value.as_integer();
  const int64_t end = end_value.as_integer();
  PS_CHECK(begin >= 0 && begin <= end,
           "{}: tensor \"{}\": data_offsets [{}, {}] are not an interval", file, name, begin, end);
  PS_CHECK(
      end <= buffer_size,
      "{}: tensor \"{}\": data_offsets [{}, {}] extend past the end of the data ({} bytes): the "
      "file is truncated or its header is wrong",
      file, name, begin, end, buffer_size);
  const std::optional<int64_t> bytes =
      checked_byte_size(shape, *dtype, std::numeric_limits<int64_t>::max());
  PS_CHECK(bytes && *bytes == end - begin,
           "{}: tensor \"{}\": shape {} of {} needs {} bytes, but data_offsets [{}, {}] span {}",
           file, name, shape_str(shape), dtype_text,
           bytes ? std::to_string(*bytes) : std::string("more than 2^63"), begin, end, end - begin);
  return HeaderEntry{name, *dtype, std::move(shape), begin, end};
}

// The tensors must tile the data buffer: sorted by offset, each starts where the previous one
// ends, the first at 0 and the last at the end (no overlap, no hole, no trailing bytes).
void check_layout(const std::string& file, std::vector<const HeaderEntry*> entries,
                  int64_t buffer_size) {
  std::sort(entries.begin(), entries.end(), [](const HeaderEntry* a, const HeaderEntry* b) {
    return std::tie(a->begin, a->end, a->name) < std::tie(b->begin, b->end, b->name);
  });
  int64_t covered = 0;
  const HeaderEntry* previous = nullptr;
  for (const HeaderEntry* e : entries) {
    if (e->begin < covered) {
      PS_FAIL("{}: tensors \"{}\" [{}, {}) and \"{}\" [{}, {}) overlap in the data buffer", file,
              previous->name, previous->begin, previous->end, e->name, e->begin, e->end);
    }
    PS_CHECK(e->begin == covered,
             "{}: data bytes [{}, {}) belong to no tensor (a hole before tensor \"{}\")", file,
             covered, e->begin, e->name);
    covered = e->end;
    previous = e;
  }
  PS_CHECK(
      covered == buffer_size,
      "{}: {} trailing bytes after the last tensor (data offset {} of {}) belong to no tensor: "
      "trailing garbage, or not a file written by a safetensors writer",
      file, buffer_size - covered, covered, buffer_size);
}

}  // namespace

const char* dtype_name(DType dtype) {
  switch (dtype) {
    case DType::F32:
      return "F32";
    case DType::F16:
      return "F16";
    case DType::BF16:
      return "BF16";
    case DType::I64:
      return "I64";
  }
  return "?";
}

int64_t dtype_size(DType dtype) {
  switch (dtype) {
    case DType::F32:
      return 4;
    case DType::F16:
      return 2;
    case DType::BF16:
      return 2;
    case DType::I64:
      return 8;
  }
  return 0;
}

bool is_floating(DType dtype) {
  return dtype != DType::I64;
}

SafeTensors SafeTensors::read(const std::filesystem::path& path) {
  const std::vector<char> bytes = read_file_bytes(path);
  return parse(
      std::span<const uint8_t>(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size()),
      path.string());
}

SafeTensors SafeTensors::parse(std::span<const uint8_t> file, const std::string& source) {
  PS_CHECK(file.size() >= 8,
           "{}: not a safetensors file: {} bytes, shorter than the 8-byte header length", source,
           file.size());
  const uint64_t header_length = load_u64_le(file.data());
  const uint64_t after_length = file.size() - 8;
  PS_CHECK(header_length <= after_length,
           "{}: header length {} is larger than the {} bytes that follow it: the file is truncated "
           "or not a safetensors file",
           source, header_length, after_length);
  PS_CHECK(header_length <= kMaxHeaderBytes,
           "{}: header length {} exceeds the format's limit of {} bytes", source, header_length,
           kMaxHeaderBytes);
  const std::string_view header(reinterpret_cast<const char*>(file.data() + 8), header_length);
  // The format requires the header to start with '{'; with that, a header that parses is an
  // object.
  PS_CHECK(!header.empty() && header.front() == '{',
           "{}: the header is not a JSON object (it does not start with '{{'): not a safetensors "
           "file",
           source);
  const json::Value root = json::parse(header, source + ": header");

  const std::span<const uint8_t> buffer = file.subspan(8 + header_length);
  const auto buffer_size = static_cast<int64_t>(buffer.size());
  SafeTensors out;
  out.source_ = source;
  std::vector<HeaderEntry> entries;
  for (const auto& [name, value] : root.members()) {
    if (name == kMetadataKey) {
      PS_CHECK(value.is_object(), "{}: \"__metadata__\" must be an object of strings, found {}",
               source, json::kind_name(value.kind()));
      for (const auto& [key, text] : value.members()) {
        PS_CHECK(text.is_string(), "{}: \"__metadata__\" entry \"{}\" must be a string, found {}",
                 source, key, json::kind_name(text.kind()));
        out.metadata.emplace(key, text.as_string());
      }
      continue;
    }
    entries.push_back(parse_entry(source, name, value, buffer_size));
  }
  std::vector<const HeaderEntry*> pointers;
  for (const HeaderEntry& e : entries) pointers.push_back(&e);
  check_layout(source, std::move(pointers), buffer_size);

  for (HeaderEntry& e : entries) {
    TensorRecord record{e.name, e.dtype, std::move(e.shape), {}};
    record.bytes.assign(buffer.begin() + e.begin, buffer.begin() + e.end);
    out.tensors_.emplace(e.name, std::move(record));
  }
  return out;
}

std::vector<uint8_t> SafeTensors::serialize() const {
  json::Value header = json::Value::object();
  if (!metadata.empty()) {
    json::Value meta = json::Value::object();
    for (const auto& [key, value] : metadata) {
      PS_CHECK(json::is_valid_utf8(key) && json::is_valid_utf8(value),
               "safetensors metadata entry \"{}\" is not valid UTF-8", key);
      meta.add(key, json::Value(value));
    }
    header.add(std::string(kMetadataKey), std::move(meta));
  }
  // Data layout: widest elements first (I64, F32, then F16/BF16), by name within a width. The
  // buffer starts 8-byte aligned and each group's size is a multiple of its element size, so
  // every tensor starts at a multiple of its element size in the file, which mmap-based loaders
  // (PyTorch's included) need in order to view the bytes in place.
  std::vector<const TensorRecord*> layout;
  for (const auto& [name, record] : tensors_) layout.push_back(&record);
  std::stable_sort(layout.begin(), layout.end(), [](const TensorRecord* a, const TensorRecord* b) {
    return dtype_size(a->dtype) > dtype_size(b->dtype);
  });
  std::map<std::string, int64_t> begin_of;
  int64_t buffer_size = 0;
  for (const TensorRecord* record : layout) {
    begin_of[record->name] = buffer_size;
    buffer_size += static_cast<int64_t>(record->bytes.size());
  }
  // Header: members in name order.
  for (const auto& [name, record] : tensors_) {
    json::Value shape = json::Value::array();
    for (const int64_t d : record.shape) shape.push_back(json::Value(d));
    const int64_t begin = begin_of.at(name);
    const int64_t end = begin + static_cast<int64_t>(record.bytes.size());
    json::Value entry = json::Value::object();
    entry.add("dtype", json::Value(dtype_name(record.dtype)));
    entry.add("shape", std::move(shape));
    entry.add("data_offsets", json::Value(json::ValueList{json::Value(begin), json::Value(end)}));
    header.add(name, std::move(entry));
  }
  std::string text = json::dump(header);
  text.append((8 - (8 + text.size()) % 8) % 8, ' ');

  std::vector<uint8_t> out(8 + text.size() + static_cast<size_t>(buffer_size));
  store_u64_le(text.size(), out.data());
  std::memcpy(out.data() + 8, text.data(), text.size());
  uint8_t* data = out.data() + 8 + text.size();
  for (const TensorRecord* record : layout) {
    if (!record->bytes.empty()) std::memcpy(data, record->bytes.data(), record->bytes.size());
    data += record->bytes.size();
  }
  return out;
}

void SafeTensors::write(const std::filesystem::path& path) const {
  const std::vector<uint8_t> bytes = serialize();
  write_file_atomic(path, bytes.data(), bytes.size(), Durability::kPowerLoss);
}

void SafeTensors::check_new_name(const std::string& name) const {
  PS_CHECK(!name.empty(), "safetensors: a tensor name must not be empty");
  PS_CHECK(name != kMetadataKey,
           "safetensors: \"__metadata__\" is reserved and cannot name a tensor");
  PS_CHECK(json::is_valid_utf8(name), "safetensors: tensor name \"{}\" is not valid UTF-8", name);
  PS_CHECK(!contains(name), "{}: already holds a tensor named \"{}\"", source_, name);
}

void SafeTensors::add(TensorRecord record) {
  check_new_name(record.name);
  const std::optional<int64_t> bytes =
      checked_byte_size(record.shape, record.dtype, std::numeric_limits<int64_t>::max());
  PS_CHECK(bytes, "safetensors: tensor \"{}\" has an invalid shape {}", record.name,
           shape_str(record.shape));
  PS_CHECK(*bytes == static_cast<int64_t>(record.bytes.size()),
           "safetensors: tensor \"{}\" of shape {} and dtype {} needs {} bytes, given {}",
           record.name, shape_str(record.shape), dtype_name(record.dtype), *bytes,
           record.bytes.size());
  std::string name = record.name;
  tensors_.emplace(std::move(name), std::move(record));
}

void SafeTensors::add_f32(const std::string& name, const Tensor<float>& tensor, DType stored) {
  PS_CHECK(is_floating(stored), "safetensors: tensor \"{}\": a float tensor cannot be stored as {}",
           name, dtype_name(stored));
  check_new_name(name);
  const int64_t n = tensor.numel();
  TensorRecord record{name, stored, tensor.shape(), {}};
  record.bytes.resize(static_cast<size_t>(n * dtype_size(stored)));
  if (stored == DType::F32) {
    if (n > 0) std::memcpy(record.bytes.data(), tensor.data(), record.bytes.size());
  } else {
    for (int64_t i = 0; i < n; ++i) {
      const float v = tensor[i];
      uint16_t bits = 0;
      if (stored == DType::F16) {
        bits = float_to_f16_bits(v);
        PS_CHECK(!std::isfinite(v) || (bits & 0x7C00u) != 0x7C00u,
                 "safetensors: tensor \"{}\": element {} = {} overflows F16 (largest 65504); store "
                 "it as F32 or BF16",
                 name, i, v);
      } else {
        bits = float_to_bf16_bits(v);
      }
      record.bytes[static_cast<size_t>(2 * i)] = static_cast<uint8_t>(bits & 0xFFu);
      record.bytes[static_cast<size_t>(2 * i + 1)] = static_cast<uint8_t>(bits >> 8);
    }
  }
  tensors_.emplace(name, std::move(record));
}

void SafeTensors::add_i64(const std::string& name, std::vector<int64_t> shape,
                          std::vector<int64_t> values) {
  check_new_name(name);
  for (const int64_t d : shape) {
    PS_CHECK(d >= 0, "safetensors: tensor \"{}\": shape {} has a negative dimension", name,
             shape_str(shape));
  }
  const std::optional<int64_t> bytes =
      checked_byte_size(shape, DType::I64, std::numeric_limits<int64_t>::max());
  PS_CHECK(bytes && *bytes / 8 == static_cast<int64_t>(values.size()),
           "safetensors: tensor \"{}\": shape {} holds {} values, given {}", name, shape_str(shape),
           bytes ? std::to_string(*bytes / 8) : std::string("too many"), values.size());
  TensorRecord record{name, DType::I64, std::move(shape), {}};
  record.bytes.resize(values.size() * 8);
  if (!values.empty()) std::memcpy(record.bytes.data(), values.data(), record.bytes.size());
  tensors_.emplace(name, std::move(record));
}

bool SafeTensors::contains(const std::string& name) const {
  return tensors_.count(name) != 0;
}

std::vector<std::string> SafeTensors::names() const {
  std::vector<std::string> out;
  out.reserve(tensors_.size());
  for (const auto& [name, record] : tensors_) out.push_back(name);
  return out;
}

const TensorRecord& SafeTensors::at(const std::string& name) const {
  const auto it = tensors_.find(name);
  if (it != tensors_.end()) return it->second;
  constexpr size_t kListed = 10;
  std::string listing;
  size_t listed = 0;
  for (const auto& [existing, record] : tensors_) {
    if (listed == kListed) {
      listing += ", ...";
      break;
    }
    listing += (listed++ ? ", " : "") + existing;
  }
  PS_FAIL("{}: no tensor named \"{}\" (the file holds {} tensors{}{})", source_, name,
          tensors_.size(), tensors_.empty() ? "" : ": ", listing);
}

Tensor<float> SafeTensors::get_f32(const std::string& name) const {
  const TensorRecord& record = at(name);
  PS_CHECK(is_floating(record.dtype),
           "{}: tensor \"{}\" is {}, not a floating-point tensor (use get_i64)", source_, name,
           dtype_name(record.dtype));
  Tensor<float> out(record.shape);
  const int64_t n = out.numel();
  if (record.dtype == DType::F32) {
    if (n > 0) std::memcpy(out.data(), record.bytes.data(), record.bytes.size());
    return out;
  }
  for (int64_t i = 0; i < n; ++i) {
    const auto bits = static_cast<uint16_t>(record.bytes[static_cast<size_t>(2 * i)] |
                                            (record.bytes[static_cast<size_t>(2 * i + 1)] << 8));
    out[i] = record.dtype == DType::F16 ? f16_bits_to_float(bits) : bf16_bits_to_float(bits);
  }
  return out;
}

Tensor<float> SafeTensors::get_f32(const std::string& name, const Shape& expected_shape) const {
  const TensorRecord& record = at(name);
  PS_CHECK(record.shape == expected_shape, "{}: tensor \"{}\" has shape {}, expected {}", source_,
           name, shape_str(record.shape), shape_str(expected_shape));
  return get_f32(name);
}

std::vector<int64_t> SafeTensors::get_i64(const std::string& name) const {
  const TensorRecord& record = at(name);
  PS_CHECK(record.dtype == DType::I64, "{}: tensor \"{}\" is {}, not I64 (use get_f32)", source_,
           name, dtype_name(record.dtype));
  std::vector<int64_t> out(record.bytes.size() / 8);
  if (!out.empty()) std::memcpy(out.data(), record.bytes.data(), record.bytes.size());
  return out;
}

void check_names_and_shapes(const SafeTensors& file, const std::vector<ExpectedTensor>& expected,
                            const std::string& what) {
  std::set<std::string> expected_names;
  for (const ExpectedTensor& e : expected) {
    PS_CHECK(expected_names.insert(e.name).second,
             "check_names_and_shapes({}): the expected list names \"{}\" twice", what, e.name);
  }
  std::vector<std::string> missing, wrong_shape, wrong_dtype, unexpected;
  for (const ExpectedTensor& e : expected) {
    if (!file.contains(e.name)) {
      missing.push_back(fmt::format("missing {} (expected shape {})", e.name, shape_str(e.shape)));
      continue;
    }
    const TensorRecord& record = file.at(e.name);
    if (record.shape != e.shape) {
      wrong_shape.push_back(fmt::format("wrong shape {}: {} in the file, expected {}", e.name,
                                        shape_str(record.shape), shape_str(e.shape)));
    }
    const bool kind_ok = (e.kind == ValueKind::Float) == is_floating(record.dtype);
    if (!kind_ok) {
      wrong_dtype.push_back(fmt::format("wrong dtype {}: {} in the file, expected {}", e.name,
                                        dtype_name(record.dtype),
                                        e.kind == ValueKind::Float ? "F32, F16 or BF16" : "I64"));
    }
  }
  for (const std::string& name : file.names()) {
    if (expected_names.count(name) == 0) {
      const TensorRecord& record = file.at(name);
      unexpected.push_back(fmt::format("unexpected {} ({} {})", name, dtype_name(record.dtype),
                                       shape_str(record.shape)));
    }
  }
  const size_t problems =
      missing.size() + wrong_shape.size() + wrong_dtype.size() + unexpected.size();
  if (problems == 0) return;
  std::string message = fmt::format("{} ({}): {} problem{} with the tensors:", what, file.source(),
                                    problems, problems == 1 ? "" : "s");
  for (const auto* list : {&missing, &wrong_shape, &wrong_dtype, &unexpected}) {
    for (const std::string& line : *list) message += "\n  " + line;
  }
  PS_FAIL("{}", message);
}

}  // namespace pillarseg::weights
