#include "engine/util/tensorboard.hpp"

#include <array>
#include <bit>
#include <cerrno>
#include <chrono>
#include <cstring>

#include "core/error.hpp"
#include "core/io.hpp"

namespace pillarseg {

namespace fs = std::filesystem;

namespace {

// The reflected Castagnoli polynomial's table.
constexpr std::array<std::uint32_t, 256> kCrcTable = [] {
  std::array<std::uint32_t, 256> t{};
  for (std::uint32_t i = 0; i < 256; ++i) {
    std::uint32_t c = i;
    for (int k = 0; k < 8; ++k) c = (c & 1u) ? 0x82F63B78u ^ (c >> 1) : c >> 1;
    t[i] = c;
  }
  return t;
}();

void put_varint(std::string& out, std::uint64_t v) {
  while (v >= 0x80) {
    out.push_back(static_cast<char>((v & 0x7F) | 0x80));
    v >>= 7;
  }
  out.push_back(static_cast<char>(v));
}

template <class T>
void put_le(std::string& out, T v) {
  char bytes[sizeof(T)];
  std::memcpy(bytes, &v, sizeof(T));  // x86-64 and aarch64 are little-endian
  static_assert(std::endian::native == std::endian::little,
                "event files are written little-endian");
  out.append(bytes, sizeof(T));
}

void put_bytes_field(std::string& out, int field, std::string_view bytes) {
  put_varint(out, static_cast<std::uint64_t>(field) << 3 | 2);
  put_varint(out, bytes.size());
  out.append(bytes);
}

std::string event_header(double wall_time, std::int64_t step) {
  std::string e;
  put_varint(e, 1 << 3 | 1);
  put_le(e, wall_time);
  put_varint(e, 2 << 3 | 0);
  put_varint(e, static_cast<std::uint64_t>(step));
  return e;
}

double now_seconds() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

// A minimal protocol-buffer reader over one message.
struct Reader {
  std::string_view in;
  size_t at = 0;
  bool ok = true;
  bool done() const { return at >= in.size() || !ok; }
  std::uint64_t varint() {
    std::uint64_t v = 0;
    for (int shift = 0; shift < 64; shift += 7) {
      if (at >= in.size()) break;
      const auto b = static_cast<unsigned char>(in[at++]);
      v |= static_cast<std::uint64_t>(b & 0x7F) << shift;
      if ((b & 0x80) == 0) return v;
    }
    ok = false;
    return 0;
  }
  std::string_view bytes(size_t n) {
    if (at + n > in.size()) {
      ok = false;
      return {};
    }
    const std::string_view v = in.substr(at, n);
    at += n;
    return v;
  }
  // Skips a field of wire type `wire`.
  void skip(unsigned wire) {
    if (wire == 0)
      varint();
    else if (wire == 1)
      bytes(8);
    else if (wire == 2)
      bytes(varint());
    else if (wire == 5)
      bytes(4);
    else
      ok = false;
  }
};

// The event's step and scalars (tag, value); false where it does not parse.
bool parse_event(std::string_view data, std::int64_t& step, double& wall_time,
                 std::vector<std::pair<std::string, float>>& values) {
  Reader r{data};
  step = 0, wall_time = 0;
  while (!r.done()) {
    const std::uint64_t key = r.varint();
    const unsigned field = static_cast<unsigned>(key >> 3), wire = static_cast<unsigned>(key & 7);
    if (field == 1 && wire == 1) {
      std::memcpy(&wall_time, r.bytes(8).data(), 8);
    } else if (field == 2 && wire == 0) {
      step = static_cast<std::int64_t>(r.varint());
    } else if (field == 5 && wire == 2) {
      Reader summary{r.bytes(r.varint())};
      while (!summary.done()) {
        const std::uint64_t k = summary.varint();
        if (k >> 3 != 1 || (k & 7) != 2) {
          summary.skip(static_cast<unsigned>(k & 7));
          continue;
        }
        Reader value{summary.bytes(summary.varint())};
        std::string tag;
        float v = 0;
        while (!value.done()) {
          const std::uint64_t vk = value.varint();
          if (vk == (1 << 3 | 2)) {
            tag = std::string(value.bytes(value.varint()));
          } else if (vk == (2 << 3 | 5)) {
            std::memcpy(&v, value.bytes(4).data(), 4);
          } else {
            value.skip(static_cast<unsigned>(vk & 7));
          }
        }
        if (!value.ok) return false;
        values.emplace_back(tag, v);
      }
      if (!summary.ok) return false;
    } else {
      r.skip(wire);
    }
  }
  return r.ok;
}

// The file's records, up to the first one cut short or corrupt.
std::vector<std::string> read_records(const fs::path& path, bool* truncated) {
  const std::string all = read_file_text(path);
  std::vector<std::string> records;
  size_t at = 0;
  bool cut = false;
  while (at < all.size()) {
    if (at + 12 > all.size()) {
      cut = true;
      break;
    }
    std::uint64_t length = 0;
    std::uint32_t length_crc = 0, data_crc = 0;
    std::memcpy(&length, all.data() + at, 8);
    std::memcpy(&length_crc, all.data() + at + 8, 4);
    if (length_crc != masked_crc32c(std::string_view(all).substr(at, 8)) ||
        length > all.size() - at - 12 || all.size() - at - 12 - length < 4) {
      cut = true;
      break;
    }
    const std::string_view data = std::string_view(all).substr(at + 12, length);
    std::memcpy(&data_crc, all.data() + at + 12 + length, 4);
    if (data_crc != masked_crc32c(data)) {
      cut = true;
      break;
    }
    records.emplace_back(data);
    at += 12 + length + 4;
  }
  if (truncated != nullptr) *truncated = cut;
  return records;
}

std::string framed(const std::string& event) {
  std::string out;
  put_le(out, static_cast<std::uint64_t>(event.size()));
  const std::string length = out;
  put_le(out, masked_crc32c(length));
  out += event;
  put_le(out, masked_crc32c(event));
  return out;
}

}  // namespace

std::uint32_t crc32c(std::string_view bytes) {
  std::uint32_t c = 0xFFFFFFFFu;
  for (const char ch : bytes)
    c = kCrcTable[(c ^ static_cast<unsigned char>(ch)) & 0xFFu] ^ (c >> 8);
  return c ^ 0xFFFFFFFFu;
}

std::uint32_t masked_crc32c(std::string_view bytes) {
  const std::uint32_t c = crc32c(bytes);
  return ((c >> 15) | (c << 17)) + 0xA282EAD8u;
}

std::vector<EventScalar> read_event_scalars(const fs::path& path, bool* truncated) {
  std::vector<EventScalar> out;
  for (const std::string& record : read_records(path, truncated)) {
    std::int64_t step = 0;
    double wall_time = 0;
    std::vector<std::pair<std::string, float>> values;
    PS_CHECK(parse_event(record, step, wall_time, values), "{}: an event record does not parse",
             path.string());
    for (auto& [tag, v] : values) out.push_back({tag, step, v, wall_time});
  }
  return out;
}

fs::path EventWriter::path_in(const fs::path& run_dir) {
  return run_dir / "events.out.tfevents.0.pillarseg";
}

EventWriter::EventWriter(const fs::path& run_dir, bool resume, std::int64_t keep_through_step)
    : path_(path_in(run_dir)) {
  if (resume && fs::exists(path_)) {
    std::string kept;
    for (const std::string& record : read_records(path_, nullptr)) {
      std::int64_t step = 0;
      double wall_time = 0;
      std::vector<std::pair<std::string, float>> values;
      if (!parse_event(record, step, wall_time, values) || step > keep_through_step) continue;
      kept += framed(record);
    }
    write_file_atomic(path_, kept.data(), kept.size());
    out_.open(path_, std::ios::binary | std::ios::app);
  } else {
    out_.open(path_, std::ios::binary | std::ios::trunc);
    std::string e = event_header(now_seconds(), 0);
    put_bytes_field(e, 3, "brain.Event:2");
    PS_CHECK(out_, "{}: cannot open the event file for writing", path_.string());
    record(e);
  }
  PS_CHECK(out_, "{}: cannot open the event file for writing", path_.string());
}

void EventWriter::record(const std::string& event) {
  out_ << framed(event);
}

void EventWriter::scalar(const std::string& tag, std::int64_t step, double value) {
  std::string v;
  put_bytes_field(v, 1, tag);
  put_varint(v, 2 << 3 | 5);
  put_le(v, static_cast<float>(value));
  std::string summary;
  put_bytes_field(summary, 1, v);
  std::string e = event_header(now_seconds(), step);
  put_bytes_field(e, 5, summary);
  record(e);
}

void EventWriter::flush() {
  out_.flush();
  PS_CHECK(out_, "{}: cannot write the event file: {}", path_.string(),
           write_error_cause(errno));
}

}  // namespace pillarseg
