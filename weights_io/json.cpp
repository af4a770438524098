// Strict JSON parsing (recursive descent with a depth limit) and compact serialisation.
#include "weights_io/json.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <limits>
#include <set>

#include "core/error.hpp"

namespace pillarseg::json {

namespace {

// Deep enough for any real document; shallow enough that the recursion stays far from the
// stack limit on hostile input such as a megabyte of '['.
constexpr int kMaxDepth = 128;

// Length of the UTF-8 sequence starting at text[pos] if it is well-formed, 0 otherwise.
size_t utf8_sequence_length(std::string_view text, size_t pos) {
  const auto byte = [&](size_t i) { return static_cast<unsigned char>(text[i]); };
  const unsigned char lead = byte(pos);
  if (lead < 0x80) return 1;
  size_t length = 0;
  uint32_t min_code_point = 0;
  uint32_t code_point = 0;
  if (lead >= 0xC2 && lead <= 0xDF) {
    length = 2, min_code_point = 0x80, code_point = lead & 0x1Fu;
  } else if (lead >= 0xE0 && lead <= 0xEF) {
    length = 3, min_code_point = 0x800, code_point = lead & 0x0Fu;
  } else if (lead >= 0xF0 && lead <= 0xF4) {
    length = 4, min_code_point = 0x10000, code_point = lead & 0x07u;
  } else {
    return 0;  // continuation byte, overlong 2-byte lead (C0, C1), or beyond U+10FFFF
  }
  if (pos + length > text.size()) return 0;
  for (size_t i = 1; i < length; ++i) {
    if ((byte(pos + i) & 0xC0u) != 0x80u) return 0;
    code_point = (code_point << 6) | (byte(pos + i) & 0x3Fu);
  }
  if (code_point < min_code_point || code_point > 0x10FFFF) return 0;
  if (code_point >= 0xD800 && code_point <= 0xDFFF) return 0;  // surrogates are not characters
  return length;
}

void append_utf8(std::string& out, uint32_t code_point) {
  if (code_point < 0x80) {
    out += static_cast<char>(code_point);
  } else if (code_point < 0x800) {
    out += static_cast<char>(0xC0u | (code_point >> 6));
    out += static_cast<char>(0x80u | (code_point & 0x3Fu));
  } else if (code_point < 0x10000) {
    out += static_cast<char>(0xE0u | (code_point >> 12));
    out += static_cast<char>(0x80u | ((code_point >> 6) & 0x3Fu));
    out += static_cast<char>(0x80u | (code_point & 0x3Fu));
  } else {
    out += static_cast<char>(0xF0u | (code_point >> 18));
    out += static_cast<char>(0x80u | ((code_point >> 12) & 0x3Fu));
    out += static_cast<char>(0x80u | ((code_point >> 6) & 0x3Fu));
    out += static_cast<char>(0x80u | (code_point & 0x3Fu));
  }
}

// A printable rendering of the byte at the error position for messages.
std::string describe_byte(std::string_view text, size_t pos) {
  if (pos >= text.size()) return "end of input";
  const auto c = static_cast<unsigned char>(text[pos]);
  if (c >= 0x20 && c < 0x7F) return fmt::format("'{}'", static_cast<char>(c));
  return fmt::format("byte 0x{:02X}", c);
}

class Parser {
 public:
  Parser(std::string_view text, std::string_view source) : text_(text), source_(source) {}

  Value parse_document() {
    skip_whitespace();
    Value value = parse_value(0);
    skip_whitespace();
    if (pos_ != text_.size())
      fail(fmt::format("unexpected {} after the end of the JSON value", here()));
    return value;
  }

 private:
  [[noreturn]] void fail(const std::string& what) const {
    size_t line = 1, column = 1;
    for (size_t i = 0; i < pos_ && i < text_.size(); ++i) {
      if (text_[i] == '\n') {
        ++line;
        column = 1;
      } else {
        ++column;
      }
    }
    PS_FAIL("{}: invalid JSON at line {}, column {} (byte {}): {}", source_, line, column, pos_,
            what);
  }

  std::string here() const { return describe_byte(text_, pos_); }
  bool at_end() const { return pos_ >= text_.size(); }
  char peek() const { return at_end() ? '\0' : text_[pos_]; }

  void skip_whitespace() {
    while (!at_end() && (peek() == ' ' || peek() == '\t' || peek() == '\n' || peek() == '\r'))
      ++pos_;
  }

  void expect(char c) {
    if (at_end() || peek() != c) fail(fmt::format("expected '{}', found {}", c, here()));
    ++pos_;
  }

  Value parse_value(int depth) {
    if (depth > kMaxDepth) fail(fmt::format("nesting deeper than {} levels", kMaxDepth));
    if (at_end()) fail("expected a value, found end of input");
    switch (peek()) {
      case '{':
        return parse_object(depth);
      case '[':
        return parse_array(depth);
      case '"':
        return Value(parse_string());
      case 't':
        parse_literal("true");
        return Value(true);
      case 'f':
        parse_literal("false");
        return Value(false);
      case 'n':
        parse_literal("null");
        return Value();
      default:
        if (peek() == '-' || (peek() >= '0' && peek() <= '9')) return Value(parse_integer());
        fail(fmt::format("expected a value, found {}", here()));
    }
  }

  void parse_literal(std::string_view literal) {
    if (text_.substr(pos_, literal.size()) != literal) {
      fail(fmt::format("expected '{}', found {}", literal, here()));
    }
    pos_ += literal.size();
  }

  Value parse_object(int depth) {
    expect('{');
    MemberList members;
    std::set<std::string, std::less<>> keys;
    skip_whitespace();
    if (peek() == '}') {
      ++pos_;
      return Value(std::move(members));
    }
    while (true) {
      skip_whitespace();
      if (peek() != '"') fail(fmt::format("expected a member name (a string), found {}", here()));
      const size_t key_pos = pos_;
      std::string key = parse_string();
      if (!keys.insert(key).second) {
        pos_ = key_pos;
        fail(fmt::format("duplicate key \"{}\"", key));
      }
      skip_whitespace();
      expect(':');
      skip_whitespace();
      Value value = parse_value(depth + 1);
      members.emplace_back(std::move(key), std::move(value));
      skip_whitespace();
      if (peek() == ',') {
        ++pos_;
        continue;
      }
      if (peek() == '}') {
        ++pos_;
        return Value(std::move(members));
      }
      fail(fmt::format("expected ',' or '}}' in an object, found {}", here()));
    }
  }

  Value parse_array(int depth) {
    expect('[');
    ValueList items;
    skip_whitespace();
    if (peek() == ']') {
      ++pos_;
      return Value(std::move(items));
    }
    while (true) {
      skip_whitespace();
      items.push_back(parse_value(depth + 1));
      skip_whitespace();
      if (peek() == ',') {
        ++pos_;
        continue;
      }
      if (peek() == ']') {
        ++pos_;
        return Value(std::move(items));
      }
      fail(fmt::format("expected ',' or ']' in an array, found {}", here()));
    }
  }

  // -?(0|[1-9][0-9]*), within int64.
  int64_t parse_integer() {
    const size_t start = pos_;
    const bool negative = peek() == '-';
    if (negative) ++pos_;
    if (at_end() || peek() < '0' || peek() > '9')
      fail(fmt::format("expected a digit, found {}", here()));
    if (peek() == '0' && pos_ + 1 < text_.size() && text_[pos_ + 1] >= '0' &&
        text_[pos_ + 1] <= '9') {
      fail("numbers must not have leading zeros");
    }
    // Accumulate the magnitude as a negative number: -2^63 fits, 2^63 does not.
    int64_t value = 0;
    constexpr int64_t kMin = std::numeric_limits<int64_t>::min();
    while (!at_end() && peek() >= '0' && peek() <= '9') {
      const int digit = peek() - '0';
      if (value < (kMin + digit) / 10) {
        pos_ = start;
        fail("integer out of the 64-bit range");
      }
      value = value * 10 - digit;
      ++pos_;
    }
    if (peek() == '.' || peek() == 'e' || peek() == 'E') {
      fail("only integers are supported (no fractions or exponents)");
    }
    if (negative) return value;
    if (value == kMin) {
      pos_ = start;
      fail("integer out of the 64-bit range");
    }
    return -value;
  }

  uint32_t parse_hex4() {
    uint32_t code = 0;
    for (int i = 0; i < 4; ++i) {
      const char c = peek();
      uint32_t digit = 0;
      if (c >= '0' && c <= '9') {
        digit = static_cast<uint32_t>(c - '0');
      } else if (c >= 'a' && c <= 'f') {
        digit = static_cast<uint32_t>(c - 'a' + 10);
      } else if (c >= 'A' && c <= 'F') {
        digit = static_cast<uint32_t>(c - 'A' + 10);
      } else {
        fail(fmt::format("expected a hex digit in a \\u escape, found {}", here()));
      }
      code = code * 16 + digit;
      ++pos_;
    }
    return code;
  }

  std::string parse_string() {
    expect('"');
    std::string out;
    while (true) {
      if (at_end()) fail("unterminated string");
      const auto c = static_cast<unsigned char>(peek());
      if (c == '"') {
        ++pos_;
        return out;
      }
      if (c < 0x20) fail(fmt::format("control character {} in a string must be escaped", here()));
      if (c == '\\') {
        ++pos_;
        parse_escape(out);
        continue;
      }
      const size_t length = utf8_sequence_length(text_, pos_);
      if (length == 0) fail(fmt::format("invalid UTF-8 ({}) in a string", here()));
      out.append(text_.substr(pos_, length));
      pos_ += length;
    }
  }

  // After a backslash: one of \" \\ \/ \b \f \n \r \t \u and four hex digits (with surrogate pairs).
  void parse_escape(std::string& out) {
    if (at_end()) fail("unterminated escape");
    const char c = peek();
    ++pos_;
    switch (c) {
      case '"':
        out += '"';
        return;
      case '\\':
        out += '\\';
        return;
      case '/':
        out += '/';
        return;
      case 'b':
        out += '\b';
        return;
      case 'f':
        out += '\f';
        return;
      case 'n':
        out += '\n';
        return;
      case 'r':
        out += '\r';
        return;
      case 't':
        out += '\t';
        return;
      case 'u':
        break;
      default:
        --pos_;
        fail(fmt::format("invalid escape '\\{}'", describe_byte(text_, pos_)));
    }
    const uint32_t unit = parse_hex4();
    if (unit >= 0xDC00 && unit <= 0xDFFF) fail(fmt::format("lone low surrogate \\u{:04X}", unit));
    if (unit < 0xD800 || unit > 0xDBFF) {
      append_utf8(out, unit);
      return;
    }
    if (text_.substr(pos_, 2) != "\\u") {
      fail(fmt::format("high surrogate \\u{:04X} not followed by a \\u low surrogate", unit));
    }
    pos_ += 2;
    const uint32_t low = parse_hex4();
    if (low < 0xDC00 || low > 0xDFFF) {
      fail(fmt::format("high surrogate \\u{:04X} followed by \\u{:04X}, not a low surrogate", unit,
                       low));
    }
    append_utf8(out, 0x10000u + ((unit - 0xD800u) << 10) + (low - 0xDC00u));
  }

  std::string_view text_;
  std::string_view source_;
  size_t pos_ = 0;
};

void dump_string(const std::string& s, std::string& out) {
  PS_CHECK(is_valid_utf8(s), "JSON writer: string \"{}\" is not valid UTF-8", s);
  out += '"';
  for (const char ch : s) {
    const auto c = static_cast<unsigned char>(ch);
    switch (ch) {
      case '"':
        out += "\\\"";
        break;
      case '\\':
        out += "\\\\";
        break;
      case '\b':
        out += "\\b";
        break;
      case '\f':
        out += "\\f";
        break;
      case '\n':
        out += "\\n";
        break;
      case '\r':
        out += "\\r";
        break;
      case '\t':
        out += "\\t";
        break;
      default:
        if (c < 0x20) {
          out += fmt::format("\\u{:04x}", c);
        } else {
          out += ch;
        }
    }
  }
  out += '"';
}

void dump_value(const Value& value, std::string& out) {
  switch (value.kind()) {
    case Value::Kind::Null:
      out += "null";
      break;
    case Value::Kind::Bool:
      out += value.as_bool() ? "true" : "false";
      break;
    case Value::Kind::Integer:
      out += std::to_string(value.as_integer());
      break;
    case Value::Kind::String:
      dump_string(value.as_string(), out);
      break;
    case Value::Kind::Array: {
      out += '[';
      bool first = true;
      for (const Value& item : value.items()) {
        if (!first) out += ',';
        first = false;
        dump_value(item, out);
      }
      out += ']';
      break;
    }
    case Value::Kind::Object: {
      out += '{';
      bool first = true;
      for (const auto& [key, member] : value.members()) {
        if (!first) out += ',';
        first = false;
        dump_string(key, out);
        out += ':';
        dump_value(member, out);
      }
      out += '}';
      break;
    }
  }
}

}  // namespace

const char* kind_name(Value::Kind kind) {
  switch (kind) {
    case Value::Kind::Null:
      return "null";
    case Value::Kind::Bool:
      return "boolean";
    case Value::Kind::Integer:
      return "integer";
    case Value::Kind::String:
      return "string";
    case Value::Kind::Array:
      return "array";
    case Value::Kind::Object:
      return "object";
  }
  return "unknown";
}

bool Value::as_bool() const {
  PS_CHECK(is_bool(), "JSON: expected a boolean, found {}", kind_name(kind()));
  return std::get<bool>(data_);
}

int64_t Value::as_integer() const {
  PS_CHECK(is_integer(), "JSON: expected an integer, found {}", kind_name(kind()));
  return std::get<int64_t>(data_);
}

const std::string& Value::as_string() const {
  PS_CHECK(is_string(), "JSON: expected a string, found {}", kind_name(kind()));
  return std::get<std::string>(data_);
}

const ValueList& Value::items() const {
  PS_CHECK(is_array(), "JSON: expected an array, found {}", kind_name(kind()));
  return std::get<ValueList>(data_);
}

const MemberList& Value::members() const {
  PS_CHECK(is_object(), "JSON: expected an object, found {}", kind_name(kind()));
  return std::get<MemberList>(data_);
}

const Value* Value::find(std::string_view key) const {
  for (const auto& [name, value] : members()) {
    if (name == key) return &value;
  }
  return nullptr;
}

void Value::push_back(Value item) {
  PS_CHECK(is_array(), "JSON: push_back on a {}, not an array", kind_name(kind()));
  std::get<ValueList>(data_).push_back(std::move(item));
}

void Value::add(std::string key, Value value) {
  PS_CHECK(is_object(), "JSON: add(\"{}\") on a {}, not an object", key, kind_name(kind()));
  PS_CHECK(find(key) == nullptr, "JSON: object already has a member \"{}\"", key);
  std::get<MemberList>(data_).emplace_back(std::move(key), std::move(value));
}

Value parse(std::string_view text, std::string_view source) {
  return Parser(text, source).parse_document();
}

std::string dump(const Value& value) {
  std::string out;
  dump_value(value, out);
  return out;
}

bool is_valid_utf8(std::string_view text) {
  size_t pos = 0;
  while (pos < text.size()) {
    const size_t length = utf8_sequence_length(text, pos);
    if (length == 0) return false;
    pos += length;
  }
  return true;
}

}  // namespace pillarseg::json
