#include "engine/data/point_formats.hpp"

#include <fmt/format.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstring>

#include "core/error.hpp"
#include "core/io.hpp"
#include "core/memory_budget.hpp"
#include "engine/data/semantickitti.hpp"

namespace pillarseg {

namespace fs = std::filesystem;

static_assert(std::endian::native == std::endian::little, "the point readers assume a little-endian host");

namespace {

constexpr std::array<std::string_view, 5> kSuffixes = {".pcd.bin", ".bin", ".pcd", ".ply", ".npy"};
constexpr std::array<PointFormat, 5> kSuffixFormats = {PointFormat::Nuscenes, PointFormat::Kitti, PointFormat::Pcd,
                                                       PointFormat::Ply, PointFormat::Npy};

// ---------------------------------------------------------------------------------------------
// Scalars of the binary formats: the PCD, PLY and NumPy element types, read as double.

enum class Scalar { I8, U8, I16, U16, I32, U32, I64, U64, F32, F64 };

size_t scalar_size(Scalar t) {
  switch (t) {
    case Scalar::I8: case Scalar::U8: return 1;
    case Scalar::I16: case Scalar::U16: return 2;
    case Scalar::I32: case Scalar::U32: case Scalar::F32: return 4;
    case Scalar::I64: case Scalar::U64: case Scalar::F64: return 8;
  }
  return 0;
}

bool integral(Scalar t) { return t != Scalar::F32 && t != Scalar::F64; }

template <class T>
T load_as(const char* p, bool big_endian) {
  std::array<char, sizeof(T)> raw;
  std::memcpy(raw.data(), p, sizeof(T));
  if (big_endian) std::reverse(raw.begin(), raw.end());
  return std::bit_cast<T>(raw);
}

double load_scalar(const char* p, Scalar t, bool big_endian) {
  switch (t) {
    case Scalar::I8: return load_as<int8_t>(p, big_endian);
    case Scalar::U8: return load_as<uint8_t>(p, big_endian);
    case Scalar::I16: return load_as<int16_t>(p, big_endian);
    case Scalar::U16: return load_as<uint16_t>(p, big_endian);
    case Scalar::I32: return load_as<int32_t>(p, big_endian);
    case Scalar::U32: return load_as<uint32_t>(p, big_endian);
    case Scalar::I64: return static_cast<double>(load_as<int64_t>(p, big_endian));
    case Scalar::U64: return static_cast<double>(load_as<uint64_t>(p, big_endian));
    case Scalar::F32: return load_as<float>(p, big_endian);
    case Scalar::F64: return load_as<double>(p, big_endian);
  }
  return 0;
}

// ---------------------------------------------------------------------------------------------
// Text helpers of the header formats.

bool is_space(char c) { return std::isspace(static_cast<unsigned char>(c)) != 0; }

std::vector<std::string_view> split_words(std::string_view line) {
  std::vector<std::string_view> words;
  size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && is_space(line[i])) ++i;
    size_t j = i;
    while (j < line.size() && !is_space(line[j])) ++j;
    if (j > i) words.push_back(line.substr(i, j - i));
    i = j;
  }
  return words;
}

// A number of an ASCII point file: decimal, "nan", "inf" (either sign; a leading '+' too).
bool parse_double(std::string_view word, double& value) {
  if (word.size() > 1 && word[0] == '+' && word[1] != '-') word.remove_prefix(1);
  const auto [ptr, ec] = std::from_chars(word.data(), word.data() + word.size(), value);
  return ec == std::errc() && ptr == word.data() + word.size();
}

template <class T>
bool parse_integer(std::string_view word, T& value) {
  const auto [ptr, ec] = std::from_chars(word.data(), word.data() + word.size(), value);
  return ec == std::errc() && ptr == word.data() + word.size();
}

// Reads lines of a header from the start of a file's bytes; pos() is the first byte after the
// last line returned.
class HeaderLines {
 public:
  explicit HeaderLines(std::span<const char> bytes) : bytes_(bytes) {}
  bool next(std::string_view& line) {
    if (pos_ >= bytes_.size()) return false;
    const char* begin = bytes_.data() + pos_;
    const void* newline = std::memchr(begin, '\n', bytes_.size() - pos_);
    const size_t end = newline ? static_cast<size_t>(static_cast<const char*>(newline) - bytes_.data()) : bytes_.size();
    line = std::string_view(begin, end - pos_);
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    pos_ = newline ? end + 1 : end;
    ++number_;
    return true;
  }
  size_t pos() const { return pos_; }
  int number() const { return number_; }

 private:
  std::span<const char> bytes_;
  size_t pos_ = 0;
  int number_ = 0;
};

bool starts_with(std::span<const char> bytes, std::string_view prefix) {
  return bytes.size() >= prefix.size() && std::memcmp(bytes.data(), prefix.data(), prefix.size()) == 0;
}

// A headerless format (KITTI, nuScenes) refuses a file that opens like one of the others: its
// first floats would be nonsense coordinates, and the user named the wrong format.
void refuse_other_format(std::span<const char> bytes, const std::string& name, const char* expected) {
  const char* other = starts_with(bytes, "\x93NUMPY")                                ? "a NumPy .npy file"
                      : starts_with(bytes, "ply\n") || starts_with(bytes, "ply\r\n") ? "a PLY file"
                      : starts_with(bytes, "# .PCD") || starts_with(bytes, "VERSION ") ||
                              starts_with(bytes, "FIELDS ")
                          ? "a PCD file"
                          : nullptr;
  PS_CHECK(other == nullptr, "{}: starts like {}, not {}: give the file its format's extension or pass --format",
           name, other, expected);
}

// The records vector for `count` points, after the count is checked against the 32-bit point
// indices and the memory.
std::vector<Point> allocate_records(uint64_t count, const std::string& name) {
  PS_CHECK(count < static_cast<uint64_t>(kMaxInt32Index),
           "{}: {} points overflow the 32-bit point indices (at most {} a scan)", name, count, kMaxInt32Index - 1);
  require_memory(checked_product({static_cast<int64_t>(count), static_cast<int64_t>(sizeof(Point))}, name),
                 fmt::format("{}: its {} points", name, count));
  std::vector<Point> records;
  records.reserve(static_cast<size_t>(count));
  return records;
}

// ---------------------------------------------------------------------------------------------
// KITTI .bin: float32 records x y z reflectance.

std::vector<Point> decode_kitti(std::span<const char> bytes, const std::string& name) {
  refuse_other_format(bytes, name, "a KITTI .bin (x y z reflectance float32 records)");
  PS_CHECK(bytes.size() % sizeof(Point) == 0,
           "{}: size {} bytes is not a multiple of 16 (x y z reflectance float32 records); truncated file?", name,
           bytes.size());
  std::vector<Point> records(bytes.size() / sizeof(Point));
  if (!records.empty()) std::memcpy(records.data(), bytes.data(), bytes.size());
  return records;
}

// ---------------------------------------------------------------------------------------------
// nuScenes .pcd.bin: float32 records x y z intensity ring (the laser's index, a whole number).

constexpr int kMaxRingIndex = 1023;

std::vector<Point> decode_nuscenes(std::span<const char> bytes, const std::string& name) {
  refuse_other_format(bytes, name, "a nuScenes .pcd.bin (x y z intensity ring float32 records)");
  constexpr size_t kRecord = 5 * sizeof(float);
  PS_CHECK(bytes.size() % kRecord == 0,
           "{}: size {} bytes is not a multiple of 20 (nuScenes .pcd.bin: x y z intensity ring float32 records)",
           name, bytes.size());
  const size_t n = bytes.size() / kRecord;
  std::vector<Point> records(n);
  for (size_t i = 0; i < n; ++i) {
    std::array<float, 5> v;
    std::memcpy(v.data(), bytes.data() + i * kRecord, kRecord);
    PS_CHECK(v[4] >= 0 && v[4] <= static_cast<float>(kMaxRingIndex) && v[4] == std::floor(v[4]),
             "{}: point {} has {} as its ring (the 5th float), not a whole number in [0, {}]: not a nuScenes "
             ".pcd.bin (x y z intensity ring float32 records)?",
             name, i, v[4], kMaxRingIndex);
    records[i] = Point{v[0], v[1], v[2], v[3]};
  }
  return records;
}

// ---------------------------------------------------------------------------------------------
// NumPy .npy, version 1.0, 2.0 or 3.0: the magic, a header length, a Python dict literal
// {'descr': '<f4', 'fortran_order': False, 'shape': (N, C)}, then the array.

class NpyHeaderParser {
 public:
  NpyHeaderParser(std::string_view text, const std::string& name) : text_(text), name_(name) {}

  void parse(std::string& descr, bool& fortran_order, std::vector<int64_t>& shape) {
    bool have_descr = false, have_order = false, have_shape = false;
    expect('{');
    while (true) {
      skip_space();
      if (peek() == '}') break;
      const std::string key = string_literal();
      expect(':');
      skip_space();
      if (key == "descr") {
        PS_CHECK(peek() == '\'' || peek() == '"',
                 "{}: .npy dtype is not a simple type (a structured array?): expected '<f4' or '<f8'", name_);
        descr = string_literal();
        have_descr = true;
      } else if (key == "fortran_order") {
        fortran_order = boolean();
        have_order = true;
      } else if (key == "shape") {
        shape = integer_tuple();
        have_shape = true;
      } else {
        fail(fmt::format("unexpected key '{}' (expected descr, fortran_order, shape)", key));
      }
      skip_space();
      if (peek() == ',') {
        ++pos_;
        continue;
      }
      skip_space();
      if (peek() != '}') fail("expected ',' or '}' after a value");
    }
    ++pos_;
    PS_CHECK(have_descr && have_order && have_shape,
             "{}: .npy header lacks {}: not a NumPy file written by numpy.save?", name_,
             !have_descr ? "'descr'" : !have_order ? "'fortran_order'" : "'shape'");
    skip_space();
    PS_CHECK(pos_ == text_.size(), "{}: .npy header has text after its dictionary", name_);
  }

 private:
  [[noreturn]] void fail(const std::string& what) const {
    PS_FAIL("{}: .npy header at byte {}: {}", name_, pos_, what);
  }
  char peek() const { return pos_ < text_.size() ? text_[pos_] : '\0'; }
  void skip_space() {
    while (pos_ < text_.size() && is_space(text_[pos_])) ++pos_;
  }
  void expect(char c) {
    skip_space();
    if (peek() != c) fail(fmt::format("expected '{}'", c));
    ++pos_;
  }
  std::string string_literal() {
    const char quote = peek();
    if (quote != '\'' && quote != '"') fail("expected a quoted string");
    const size_t end = text_.find(quote, pos_ + 1);
    if (end == std::string_view::npos) fail("unterminated string");
    std::string s(text_.substr(pos_ + 1, end - pos_ - 1));
    pos_ = end + 1;
    return s;
  }
  bool boolean() {
    constexpr std::array<std::pair<std::string_view, bool>, 2> kWords = {{{"True", true}, {"False", false}}};
    for (const auto& [word, value] : kWords) {
      if (text_.substr(pos_, word.size()) == word) {
        pos_ += word.size();
        return value;
      }
    }
    fail("expected True or False");
  }
  std::vector<int64_t> integer_tuple() {
    expect('(');
    std::vector<int64_t> values;
    while (true) {
      skip_space();
      if (peek() == ')') break;
      size_t end = pos_;
      while (end < text_.size() && std::isdigit(static_cast<unsigned char>(text_[end]))) ++end;
      int64_t v = 0;
      if (end == pos_ || !parse_integer(text_.substr(pos_, end - pos_), v)) fail("expected a dimension (an integer)");
      values.push_back(v);
      pos_ = end;
      if (peek() == 'L') ++pos_;
      skip_space();
      if (peek() == ',') ++pos_;
      else if (peek() != ')') fail("expected ',' or ')' in the shape");
    }
    ++pos_;
    return values;
  }

  std::string_view text_;
  const std::string& name_;
  size_t pos_ = 0;
};

std::vector<Point> decode_npy(std::span<const char> bytes, const std::string& name) {
  PS_CHECK(starts_with(bytes, "\x93NUMPY"), "{}: not a NumPy .npy file (no \\x93NUMPY magic at its start)", name);
  PS_CHECK(bytes.size() >= 10, "{}: .npy file of {} bytes ends inside its preamble", name, bytes.size());
  const int major = static_cast<unsigned char>(bytes[6]);
  PS_CHECK(major >= 1 && major <= 3, "{}: .npy format version {}.{} (expected 1.0, 2.0 or 3.0)", name, major,
           static_cast<int>(static_cast<unsigned char>(bytes[7])));
  const size_t length_bytes = major == 1 ? 2 : 4;
  PS_CHECK(bytes.size() >= 8 + length_bytes, "{}: .npy file of {} bytes ends inside its preamble", name,
           bytes.size());
  const size_t header_size = major == 1 ? load_as<uint16_t>(bytes.data() + 8, false)
                                        : static_cast<size_t>(load_as<uint32_t>(bytes.data() + 8, false));
  const size_t header_start = 8 + length_bytes;
  PS_CHECK(header_size <= bytes.size() - header_start, "{}: .npy header of {} bytes runs past the end of the file",
           name, header_size);
  std::string descr;
  bool fortran_order = false;
  std::vector<int64_t> shape;
  NpyHeaderParser(std::string_view(bytes.data() + header_start, header_size), name)
      .parse(descr, fortran_order, shape);

  PS_CHECK(descr == "<f4" || descr == "<f8" || descr == ">f4" || descr == ">f8",
           "{}: .npy dtype '{}': expected float32 or float64 ('<f4', '<f8', '>f4', '>f8')", name, descr);
  const Scalar type = descr[2] == '4' ? Scalar::F32 : Scalar::F64;
  const bool big_endian = descr[0] == '>';
  PS_CHECK(!fortran_order, "{}: .npy array is in Fortran order: save a C-order array (numpy.ascontiguousarray)",
           name);
  PS_CHECK(shape.size() == 2 && shape[1] >= 3 && shape[1] <= 5,
           "{}: .npy shape ({}): expected (N, 3), (N, 4) or (N, 5) (x y z [reflectance [other]])", name,
           fmt::join(shape, ", "));
  const size_t columns = static_cast<size_t>(shape[1]);
  const uint64_t expected =
      checked_product({shape[0], shape[1], static_cast<int64_t>(scalar_size(type))}, name + ": .npy shape");
  const size_t data_start = header_start + header_size;
  const size_t data_bytes = bytes.size() - data_start;
  PS_CHECK(data_bytes == expected, "{}: .npy array of shape ({}, {}) {} needs {} bytes, the file holds {}{}", name,
           shape[0], shape[1], descr, expected, data_bytes, data_bytes < expected ? " (truncated?)" : "");
  std::vector<Point> records = allocate_records(static_cast<uint64_t>(shape[0]), name);
  const size_t item = scalar_size(type);
  for (int64_t i = 0; i < shape[0]; ++i) {
    const char* row = bytes.data() + data_start + static_cast<size_t>(i) * columns * item;
    const auto column = [&](size_t c) { return static_cast<float>(load_scalar(row + c * item, type, big_endian)); };
    records.push_back(Point{column(0), column(1), column(2), columns >= 4 ? column(3) : 0.0f});
  }
  return records;
}

// ---------------------------------------------------------------------------------------------
// The fields a point reader takes: x, y, z and an optional intensity, from the first present of
// these names.

constexpr std::array<std::string_view, 3> kIntensityNames = {"intensity", "reflectance", "i"};

// Index of each of x, y, z and the intensity among `names` (-1: absent); errors for a missing
// coordinate or a name given twice.
std::array<int, 4> find_point_fields(const std::vector<std::string>& names, const std::string& where) {
  std::vector<std::string> sorted = names;
  std::sort(sorted.begin(), sorted.end());
  for (size_t f = 1; f < sorted.size(); ++f)
    PS_CHECK(sorted[f] != sorted[f - 1] || sorted[f] == "_", "{}: field '{}' appears twice", where, sorted[f]);
  std::array<int, 4> index = {-1, -1, -1, -1};
  for (size_t f = 0; f < names.size(); ++f)
    if (names[f] == "x" || names[f] == "y" || names[f] == "z")
      index[static_cast<size_t>(names[f][0] - 'x')] = static_cast<int>(f);
  for (size_t c = 0; c < 3; ++c)
    PS_CHECK(index[c] >= 0, "{}: no field '{}' (x, y and z are required; fields: {})", where,
             static_cast<char>('x' + c), fmt::join(names, " "));
  for (std::string_view candidate : kIntensityNames) {
    const auto it = std::find(names.begin(), names.end(), candidate);
    if (it != names.end()) {
      index[3] = static_cast<int>(it - names.begin());
      break;
    }
  }
  return index;
}

// ---------------------------------------------------------------------------------------------
// PCD (PCL's point cloud data): a text header (FIELDS, SIZE, TYPE, COUNT, WIDTH, HEIGHT,
// VIEWPOINT, POINTS, DATA), then the points: ascii (a line a point), binary (point-major
// records) or binary_compressed (uint32 compressed and expanded sizes, then LZF data that expands
// to the fields one after another, each for all points).

struct PcdField {
  std::string name;
  Scalar type = Scalar::F32;
  size_t size = 4, count = 1;
  size_t offset = 0;  // within a binary record (values before it in an ascii line)
};

Scalar pcd_scalar(char type, uint64_t size, const std::string& where) {
  const bool size_ok = type == 'F' ? size == 4 || size == 8 : size == 1 || size == 2 || size == 4 || size == 8;
  PS_CHECK((type == 'F' || type == 'I' || type == 'U') && size_ok,
           "{}: TYPE {} with SIZE {} (expected F 4/8, I or U 1/2/4/8)", where, type, size);
  if (type == 'F') return size == 4 ? Scalar::F32 : Scalar::F64;
  const int log = size == 1 ? 0 : size == 2 ? 1 : size == 4 ? 2 : 3;
  constexpr std::array<Scalar, 4> kSigned = {Scalar::I8, Scalar::I16, Scalar::I32, Scalar::I64};
  constexpr std::array<Scalar, 4> kUnsigned = {Scalar::U8, Scalar::U16, Scalar::U32, Scalar::U64};
  return type == 'I' ? kSigned[static_cast<size_t>(log)] : kUnsigned[static_cast<size_t>(log)];
}

std::vector<Point> decode_pcd(std::span<const char> bytes, const std::string& name) {
  HeaderLines lines(bytes);
  std::vector<std::string> names;
  std::vector<uint64_t> sizes, counts;
  std::string types, data;
  std::optional<uint64_t> width, height, points;
  std::vector<std::string> seen;
  std::string_view line;
  while (data.empty()) {
    PS_CHECK(lines.next(line), "{}: PCD header ends without a DATA line (not a PCD file?)", name);
    const std::vector<std::string_view> words = split_words(line);
    if (words.empty() || words[0].front() == '#') continue;
    const std::string where = fmt::format("{}: PCD header line {}", name, lines.number());
    const std::string key(words[0]);
    PS_CHECK(std::find(seen.begin(), seen.end(), key) == seen.end(), "{}: {} given twice", where, key);
    seen.push_back(key);
    const auto integers = [&] {
      std::vector<uint64_t> values;
      for (size_t i = 1; i < words.size(); ++i) {
        uint64_t v = 0;
        PS_CHECK(parse_integer(words[i], v), "{}: {} value '{}' is not a non-negative integer", where, key, words[i]);
        values.push_back(v);
      }
      return values;
    };
    const auto one_integer = [&] {
      const std::vector<uint64_t> v = integers();
      PS_CHECK(v.size() == 1, "{}: {} takes one number, got {}", where, key, v.size());
      return v[0];
    };
    if (key == "VERSION" || key == "VIEWPOINT") {
      continue;  // the version changes nothing read here; the viewpoint is not applied to the points
    } else if (key == "FIELDS") {
      for (size_t i = 1; i < words.size(); ++i) names.emplace_back(words[i]);
    } else if (key == "SIZE") {
      sizes = integers();
    } else if (key == "TYPE") {
      for (size_t i = 1; i < words.size(); ++i) {
        PS_CHECK(words[i].size() == 1, "{}: TYPE '{}' (expected F, I or U)", where, words[i]);
        types += words[i][0];
      }
    } else if (key == "COUNT") {
      counts = integers();
    } else if (key == "WIDTH") {
      width = one_integer();
    } else if (key == "HEIGHT") {
      height = one_integer();
    } else if (key == "POINTS") {
      points = one_integer();
    } else if (key == "DATA") {
      PS_CHECK(words.size() == 2 && (words[1] == "ascii" || words[1] == "binary" || words[1] == "binary_compressed"),
               "{}: DATA '{}' (expected ascii, binary or binary_compressed)", where,
               line.substr(std::min(line.size(), size_t{5})));
      data = std::string(words[1]);
    } else {
      PS_FAIL("{}: unknown header entry '{}' (not a PCD file?)", where, key);
    }
  }
  const std::string where = name + ": PCD header";
  PS_CHECK(!names.empty(), "{}: no FIELDS", where);
  PS_CHECK(sizes.size() == names.size() && types.size() == names.size(),
           "{}: {} FIELDS, {} SIZE and {} TYPE values: expected one of each a field", where, names.size(), sizes.size(),
           types.size());
  if (counts.empty()) counts.assign(names.size(), 1);
  PS_CHECK(counts.size() == names.size(), "{}: {} FIELDS but {} COUNT values", where, names.size(), counts.size());
  PS_CHECK(points || width, "{}: neither POINTS nor WIDTH says how many points there are", where);
  const uint64_t grid_points =
      width ? checked_product({static_cast<int64_t>(std::min<uint64_t>(*width, uint64_t{1} << 40)),
                               static_cast<int64_t>(std::min<uint64_t>(height.value_or(1), uint64_t{1} << 40))},
                              where + ": WIDTH x HEIGHT")
            : 0;
  const uint64_t n = points ? *points : grid_points;
  PS_CHECK(!width || grid_points == n, "{}: WIDTH x HEIGHT = {} x {} is not POINTS {}", where, *width,
           height.value_or(1), n);

  std::vector<PcdField> fields(names.size());
  size_t record = 0, values_per_point = 0;
  for (size_t f = 0; f < names.size(); ++f) {
    PcdField& field = fields[f];
    field.name = names[f];
    field.type = pcd_scalar(types[f], sizes[f], fmt::format("{}: field '{}'", where, field.name));
    field.size = scalar_size(field.type);
    PS_CHECK(counts[f] >= 1 && counts[f] <= 65536, "{}: field '{}' has COUNT {} (expected 1..65536)", where,
             field.name, counts[f]);
    field.count = static_cast<size_t>(counts[f]);
    field.offset = data == "ascii" ? values_per_point : record;
    record += field.size * field.count;
    values_per_point += field.count;
  }
  const std::array<int, 4> used = find_point_fields(names, where);
  for (int f : used)
    if (f >= 0)
      PS_CHECK(fields[static_cast<size_t>(f)].count == 1, "{}: field '{}' has COUNT {} (expected 1)", where,
               fields[static_cast<size_t>(f)].name, fields[static_cast<size_t>(f)].count);

  const std::span<const char> body = bytes.subspan(lines.pos());
  std::vector<Point> records;
  const auto point_of = [&](auto&& value_of) {
    Point p;
    p.x = static_cast<float>(value_of(fields[static_cast<size_t>(used[0])]));
    p.y = static_cast<float>(value_of(fields[static_cast<size_t>(used[1])]));
    p.z = static_cast<float>(value_of(fields[static_cast<size_t>(used[2])]));
    p.r = used[3] >= 0 ? static_cast<float>(value_of(fields[static_cast<size_t>(used[3])])) : 0.0f;
    return p;
  };
  if (data == "ascii") {
    // Each point a line of at least one byte: a count beyond the bytes is an error before allocating.
    PS_CHECK(n <= body.size(), "{}: POINTS {} but only {} bytes of ascii data", where, n, body.size());
    records = allocate_records(n, name);
    HeaderLines text(body);
    std::vector<std::string_view> words;
    while (text.next(line)) {
      words = split_words(line);
      if (words.empty()) continue;
      const int number = lines.number() + text.number();
      PS_CHECK(records.size() < n, "{}: line {}: more point lines than POINTS {}", name, number, n);
      PS_CHECK(words.size() == values_per_point, "{}: line {}: {} values, expected {} (the FIELDS' COUNTs)", name,
               number, words.size(), values_per_point);
      records.push_back(point_of([&](const PcdField& field) {
        double v = 0;
        PS_CHECK(parse_double(words[field.offset], v), "{}: line {}: {} value '{}' is not a number", name, number,
                 field.name, words[field.offset]);
        return v;
      }));
    }
    PS_CHECK(records.size() == n, "{}: {} point lines, but POINTS says {} (truncated file?)", name, records.size(), n);
    return records;
  }
  const uint64_t expanded = checked_product({static_cast<int64_t>(n), static_cast<int64_t>(record)}, where);
  if (data == "binary") {
    PS_CHECK(body.size() == expanded, "{}: binary data of {} bytes, but {} points of {} bytes need {}{}", name,
             body.size(), n, record, expanded, body.size() < expanded ? " (truncated file?)" : "");
    records = allocate_records(n, name);
    for (uint64_t i = 0; i < n; ++i) {
      const char* point = body.data() + i * record;
      records.push_back(
          point_of([&](const PcdField& field) { return load_scalar(point + field.offset, field.type, false); }));
    }
    return records;
  }
  PS_CHECK(body.size() >= 8, "{}: binary_compressed data of {} bytes ends inside its two sizes", name, body.size());
  const uint32_t compressed_size = load_as<uint32_t>(body.data(), false);
  const uint32_t expanded_size = load_as<uint32_t>(body.data() + 4, false);
  PS_CHECK(body.size() - 8 == compressed_size, "{}: binary_compressed data holds {} bytes after its sizes, not {}{}",
           name, body.size() - 8, compressed_size, body.size() - 8 < compressed_size ? " (truncated file?)" : "");
  PS_CHECK(expanded_size == expanded, "{}: binary_compressed data expands to {} bytes, but {} points of {} bytes are {}",
           name, expanded_size, n, record, expanded);
  require_memory(expanded, fmt::format("{}: expanding its binary_compressed data", name));
  const std::vector<char> fields_data = lzf_decompress(body.subspan(8), expanded, name);
  records = allocate_records(n, name);
  // Field f's values for all points start at the sum of the earlier fields' sizes x n.
  std::vector<size_t> field_start(fields.size());
  for (size_t f = 1; f < fields.size(); ++f)
    field_start[f] = field_start[f - 1] + fields[f - 1].size * fields[f - 1].count * static_cast<size_t>(n);
  for (size_t f = 0; f < fields.size(); ++f) fields[f].offset = field_start[f];
  for (uint64_t i = 0; i < n; ++i)
    records.push_back(point_of([&](const PcdField& field) {
      return load_scalar(fields_data.data() + field.offset + i * field.size, field.type, false);
    }));
  return records;
}

// ---------------------------------------------------------------------------------------------
// PLY: "ply", "format ascii|binary_little_endian|binary_big_endian 1.0", elements with their
// properties (scalars or lists), "end_header"; then each element's instances in order. The
// vertex element's x, y, z and intensity are read; earlier elements are walked past.

struct PlyProperty {
  std::string name;
  Scalar type = Scalar::F32;
  bool list = false;
  Scalar count_type = Scalar::U8;
};

struct PlyElement {
  std::string name;
  uint64_t count = 0;
  std::vector<PlyProperty> properties;
};

Scalar ply_scalar(std::string_view word, const std::string& where) {
  static constexpr std::array<std::pair<std::string_view, Scalar>, 16> kTypes = {{
      {"char", Scalar::I8},     {"int8", Scalar::I8},     {"uchar", Scalar::U8},     {"uint8", Scalar::U8},
      {"short", Scalar::I16},   {"int16", Scalar::I16},   {"ushort", Scalar::U16},   {"uint16", Scalar::U16},
      {"int", Scalar::I32},     {"int32", Scalar::I32},   {"uint", Scalar::U32},     {"uint32", Scalar::U32},
      {"float", Scalar::F32},   {"float32", Scalar::F32}, {"double", Scalar::F64},   {"float64", Scalar::F64},
  }};
  for (const auto& [n, t] : kTypes)
    if (n == word) return t;
  PS_FAIL("{}: unknown property type '{}' (expected char, uchar, short, ushort, int, uint, float, double or "
          "int8 .. float64)",
          where, word);
}

// Where a PLY value is: formatted only for an error message (not for every value read).
struct PlyPlace {
  const std::string& element;
  uint64_t index;
  const std::string& property;
  std::string text() const { return fmt::format("{} {} property '{}'", element, index, property); }
};

// The bytes (binary) or words (ascii) of a PLY body, front to back, every read bounds-checked.
class PlyBody {
 public:
  PlyBody(std::span<const char> bytes, bool ascii, bool big_endian, const std::string& name)
      : bytes_(bytes), ascii_(ascii), big_endian_(big_endian), name_(name) {}

  double value(Scalar type, const PlyPlace& at) {
    if (ascii_) {
      const std::string_view w = word(at);
      double v = 0;
      PS_CHECK(parse_double(w, v), "{}: {}: '{}' is not a number", name_, at.text(), w);
      return v;
    }
    const size_t size = scalar_size(type);
    PS_CHECK(size <= bytes_.size() - pos_, "{}: the data ends inside {} (truncated file?)", name_, at.text());
    const double v = load_scalar(bytes_.data() + pos_, type, big_endian_);
    pos_ += size;
    return v;
  }
  // A list's length: a non-negative whole number.
  uint64_t list_length(Scalar type, const PlyPlace& at) {
    const double v = value(type, at);
    PS_CHECK(v >= 0 && v == std::floor(v) && v < 4294967296.0, "{}: {}: list length {} is not a whole number >= 0",
             name_, at.text(), v);
    return static_cast<uint64_t>(v);
  }
  void skip(Scalar type, uint64_t count, const PlyPlace& at) {
    if (ascii_) {
      for (uint64_t k = 0; k < count; ++k) value(type, at);
      return;
    }
    const uint64_t bytes = count * scalar_size(type);
    PS_CHECK(bytes <= bytes_.size() - pos_, "{}: the data ends inside {} (truncated file?)", name_, at.text());
    pos_ += static_cast<size_t>(bytes);
  }
  size_t remaining() const { return bytes_.size() - pos_; }
  bool only_space_left() const {
    return std::all_of(bytes_.begin() + static_cast<std::ptrdiff_t>(pos_), bytes_.end(), is_space);
  }

 private:
  std::string_view word(const PlyPlace& at) {
    while (pos_ < bytes_.size() && is_space(bytes_[pos_])) ++pos_;
    PS_CHECK(pos_ < bytes_.size(), "{}: the data ends before {} (truncated file?)", name_, at.text());
    const size_t start = pos_;
    while (pos_ < bytes_.size() && !is_space(bytes_[pos_])) ++pos_;
    return std::string_view(bytes_.data() + start, pos_ - start);
  }

  std::span<const char> bytes_;
  bool ascii_, big_endian_;
  const std::string& name_;
  size_t pos_ = 0;
};

std::vector<Point> decode_ply(std::span<const char> bytes, const std::string& name) {
  HeaderLines lines(bytes);
  std::string_view line;
  PS_CHECK(lines.next(line) && line == "ply", "{}: not a PLY file (its first line is not 'ply')", name);
  std::string format;
  std::vector<PlyElement> elements;
  while (true) {
    PS_CHECK(lines.next(line), "{}: PLY header ends without 'end_header'", name);
    const std::vector<std::string_view> words = split_words(line);
    const std::string where = fmt::format("{}: PLY header line {}", name, lines.number());
    if (words.empty()) continue;
    if (words[0] == "comment" || words[0] == "obj_info") continue;
    if (words[0] == "end_header") break;
    if (words[0] == "format") {
      PS_CHECK(format.empty(), "{}: a second 'format' line", where);
      PS_CHECK(words.size() == 3 && (words[1] == "ascii" || words[1] == "binary_little_endian" ||
                                     words[1] == "binary_big_endian") && words[2] == "1.0",
               "{}: '{}' (expected 'format ascii|binary_little_endian|binary_big_endian 1.0')", where, line);
      format = std::string(words[1]);
    } else if (words[0] == "element") {
      PlyElement e;
      PS_CHECK(words.size() == 3 && parse_integer(words[2], e.count), "{}: '{}' (expected 'element NAME COUNT')",
               where, line);
      e.name = std::string(words[1]);
      elements.push_back(std::move(e));
    } else if (words[0] == "property") {
      PS_CHECK(!elements.empty(), "{}: a property before any element", where);
      PlyProperty p;
      if (words.size() == 5 && words[1] == "list") {
        p.list = true;
        p.count_type = ply_scalar(words[2], where);
        PS_CHECK(integral(p.count_type), "{}: a list's length type must be an integer type, got '{}'", where,
                 words[2]);
        p.type = ply_scalar(words[3], where);
        p.name = std::string(words[4]);
      } else {
        PS_CHECK(words.size() == 3, "{}: '{}' (expected 'property TYPE NAME' or 'property list TYPE TYPE NAME')",
                 where, line);
        p.type = ply_scalar(words[1], where);
        p.name = std::string(words[2]);
      }
      elements.back().properties.push_back(std::move(p));
    } else {
      PS_FAIL("{}: unknown header entry '{}'", where, words[0]);
    }
  }
  PS_CHECK(!format.empty(), "{}: PLY header has no 'format' line", name);
  const auto vertex = std::find_if(elements.begin(), elements.end(), [](const PlyElement& e) { return e.name == "vertex"; });
  PS_CHECK(vertex != elements.end(), "{}: PLY file has no 'vertex' element", name);
  std::vector<std::string> names;
  for (const PlyProperty& p : vertex->properties) names.push_back(p.name);
  const std::array<int, 4> used = find_point_fields(names, name + ": PLY vertex");
  for (int f : used)
    if (f >= 0)
      PS_CHECK(!vertex->properties[static_cast<size_t>(f)].list, "{}: PLY vertex property '{}' is a list", name,
               vertex->properties[static_cast<size_t>(f)].name);

  const bool ascii = format == "ascii";
  PlyBody body(bytes.subspan(lines.pos()), ascii, format == "binary_big_endian", name);
  const auto walk = [&](const PlyElement& e, uint64_t i, std::array<double, 4>* out) {
    for (size_t k = 0; k < e.properties.size(); ++k) {
      const PlyProperty& p = e.properties[k];
      const PlyPlace at{e.name, i, p.name};
      if (p.list) {
        body.skip(p.type, body.list_length(p.count_type, at), at);
        continue;
      }
      const auto slot = std::find(used.begin(), used.end(), static_cast<int>(k));
      if (out && slot != used.end()) (*out)[static_cast<size_t>(slot - used.begin())] = body.value(p.type, at);
      else body.skip(p.type, 1, at);
    }
  };
  for (auto e = elements.begin(); e != vertex; ++e)
    if (!e->properties.empty())
      for (uint64_t i = 0; i < e->count; ++i) walk(*e, i, nullptr);
  // Each vertex takes at least one byte (a value, or an ascii word and its separator), so a count
  // beyond the remaining bytes is an error before allocating.
  PS_CHECK(vertex->count <= body.remaining(), "{}: {} vertices, but only {} bytes of data are left (truncated file?)",
           name, vertex->count, body.remaining());
  std::vector<Point> records = allocate_records(vertex->count, name);
  for (uint64_t i = 0; i < vertex->count; ++i) {
    std::array<double, 4> v = {0, 0, 0, 0};
    walk(*vertex, i, &v);
    records.push_back(Point{static_cast<float>(v[0]), static_cast<float>(v[1]), static_cast<float>(v[2]),
                            static_cast<float>(v[3])});
  }
  if (vertex + 1 == elements.end())
    PS_CHECK(ascii ? body.only_space_left() : body.remaining() == 0,
             "{}: {} bytes after the last vertex, where the file should end", name, body.remaining());
  return records;
}

// Drops the non-finite records (and their labels), in place.
Scan scan_from_records(std::vector<Point> records, const fs::path& path, const std::optional<fs::path>& label_path) {
  const size_t n = records.size();
  std::vector<uint32_t> raw_labels;
  if (label_path) {
    raw_labels = read_labels(*label_path);
    PS_CHECK(raw_labels.size() == n, "{}: {} labels, but {} has {} points", label_path->string(), raw_labels.size(),
             path.string(), n);
  }
  Scan scan;
  size_t kept = 0;
  for (size_t i = 0; i < n; ++i) {
    const Point& p = records[i];
    if (!(std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z) && std::isfinite(p.r))) continue;
    records[kept] = p;
    if (label_path) raw_labels[kept] = raw_labels[i];
    ++kept;
  }
  scan.dropped_nonfinite = n - kept;
  records.resize(kept);
  scan.points = std::move(records);
  if (label_path) {
    raw_labels.resize(kept);
    scan.labels = std::move(raw_labels);
  }
  if (scan.dropped_nonfinite)
    spdlog::warn("{}: dropped {} of {} points with non-finite values", path.string(), scan.dropped_nonfinite, n);
  return scan;
}

}  // namespace

void require_records(const fs::path& path, size_t record_bytes, uint64_t bytes_in_memory, const char* records) {
  std::error_code error;
  const uintmax_t size = fs::file_size(path, error);
  if (error) return;
  const uint64_t count = size / record_bytes;
  PS_CHECK(count < static_cast<uint64_t>(kMaxInt32Index),
           "{}: {} bytes are {} {}, which overflows the 32-bit point indices (at most {} a scan)", path.string(), size,
           count, records, kMaxInt32Index - 1);
  require_memory(checked_product({static_cast<int64_t>(count), static_cast<int64_t>(bytes_in_memory)}, path.string()),
                 fmt::format("{}: reading its {} {} ({} bytes)", path.string(), count, records, size));
}

PointFormat parse_point_format(std::string_view name, std::string_view option) {
  for (const PointFormat f : {PointFormat::FromExtension, PointFormat::Kitti, PointFormat::Pcd, PointFormat::Ply,
                              PointFormat::Npy, PointFormat::Nuscenes})
    if (name == point_format_name(f)) return f;
  PS_FAIL("{} '{}': unknown point format (expected auto, kitti, pcd, ply, npy or nuscenes)", option, name);
}

const char* point_format_name(PointFormat format) {
  switch (format) {
    case PointFormat::FromExtension: return "auto";
    case PointFormat::Kitti: return "kitti";
    case PointFormat::Pcd: return "pcd";
    case PointFormat::Ply: return "ply";
    case PointFormat::Npy: return "npy";
    case PointFormat::Nuscenes: return "nuscenes";
  }
  return "?";
}

std::span<const std::string_view> point_file_suffixes() { return kSuffixes; }

std::string_view point_file_suffix(const fs::path& path) {
  std::string file = path.filename().string();
  std::transform(file.begin(), file.end(), file.begin(), [](unsigned char c) { return std::tolower(c); });
  for (std::string_view suffix : kSuffixes)
    if (file.size() > suffix.size() && file.ends_with(suffix)) return suffix;
  return {};
}

PointFormat point_format_of(const fs::path& path) {
  const std::string_view suffix = point_file_suffix(path);
  for (size_t i = 0; i < kSuffixes.size(); ++i)
    if (suffix == kSuffixes[i]) return kSuffixFormats[i];
  PS_FAIL("{}: no point-file extension (.bin KITTI, .pcd, .ply, .npy, .pcd.bin nuScenes): name its format with "
          "--format",
          path.string());
}

std::vector<Point> decode_points(std::span<const char> bytes, PointFormat format, const std::string& name) {
  switch (format) {
    case PointFormat::Kitti: return decode_kitti(bytes, name);
    case PointFormat::Pcd: return decode_pcd(bytes, name);
    case PointFormat::Ply: return decode_ply(bytes, name);
    case PointFormat::Npy: return decode_npy(bytes, name);
    case PointFormat::Nuscenes: return decode_nuscenes(bytes, name);
    case PointFormat::FromExtension: break;
  }
  PS_FAIL("{}: decode_points needs a named format", name);
}

std::vector<char> lzf_decompress(std::span<const char> compressed, size_t expanded_size, const std::string& name) {
  // Each 3 compressed bytes give at most 264: a larger claim is corrupt, not a reason to allocate.
  PS_CHECK(expanded_size / 88 <= compressed.size(), "{}: LZF data of {} bytes cannot expand to {} bytes", name,
           compressed.size(), expanded_size);
  std::vector<char> out(expanded_size);
  size_t in = 0, op = 0;
  const auto byte = [&] { return static_cast<size_t>(static_cast<unsigned char>(compressed[in++])); };
  while (in < compressed.size()) {
    const size_t control = byte();
    if (control < 32) {  // a literal run of control + 1 bytes
      const size_t length = control + 1;
      PS_CHECK(length <= compressed.size() - in, "{}: LZF literal run at byte {} runs past the end of the data", name,
               in - 1);
      PS_CHECK(length <= expanded_size - op, "{}: LZF data expands past the declared {} bytes", name, expanded_size);
      std::memcpy(out.data() + op, compressed.data() + in, length);
      in += length;
      op += length;
      continue;
    }
    // A back-reference: length (3 bits, 7: plus the next byte) + 2 bytes, from 1 + offset
    // (13 bits: 5 here, 8 in the next byte) bytes back.
    size_t length = control >> 5;
    PS_CHECK(in < compressed.size(), "{}: LZF back-reference at byte {} runs past the end of the data", name, in - 1);
    if (length == 7) {
      length += byte();
      PS_CHECK(in < compressed.size(), "{}: LZF back-reference at byte {} runs past the end of the data", name, in - 2);
    }
    const size_t distance = ((control & 0x1f) << 8) + byte() + 1;
    length += 2;
    PS_CHECK(distance <= op, "{}: LZF back-reference {} bytes back at output byte {}, before the start", name,
             distance, op);
    PS_CHECK(length <= expanded_size - op, "{}: LZF data expands past the declared {} bytes", name, expanded_size);
    for (size_t k = 0; k < length; ++k, ++op) out[op] = out[op - distance];  // may overlap its own output
  }
  PS_CHECK(op == expanded_size, "{}: LZF data expands to {} bytes, not the declared {}", name, op, expanded_size);
  return out;
}

Scan read_points(const fs::path& path, PointFormat format, const std::optional<fs::path>& label_path) {
  if (format == PointFormat::FromExtension) format = point_format_of(path);
  if (format == PointFormat::Kitti) {
    // The file's bytes and the scan's points (the labels' own check follows in read_labels).
    require_records(path, sizeof(Point), 2 * sizeof(Point) + (label_path ? 2 * sizeof(uint32_t) : 0), "points");
  } else {
    std::error_code error;
    const uintmax_t size = fs::file_size(path, error);
    if (!error) require_memory(size, fmt::format("{}: reading its {} bytes", path.string(), size));
  }
  std::vector<Point> records;
  {
    const std::vector<char> bytes = read_file_bytes(path);
    records = decode_points(bytes, format, path.string());
  }
  return scan_from_records(std::move(records), path, label_path);
}

}  // namespace pillarseg
