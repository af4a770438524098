// A small strict JSON reader and writer, enough for safetensors headers: objects (member order
// kept, duplicate keys rejected), arrays, strings (all escapes, \u plus four hex digits, with surrogate pairs,
// UTF-8 validated), 64-bit integers, true/false/null. Fractional and exponent numbers are
// rejected, as is anything RFC 8259 does not allow (trailing commas, leading zeros, control
// characters in strings, lone surrogates, overlong UTF-8, trailing text).
// Malformed input throws pillarseg::Error naming the source, line, column and what was
// expected; nesting is limited so that hostile input cannot exhaust the stack.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <utility>
#include <variant>
#include <vector>

namespace pillarseg::json {

class Value;
using ValueList = std::vector<Value>;
using Member = std::pair<std::string, Value>;
using MemberList = std::vector<Member>;  // in document (or insertion) order

class Value {
 public:
  enum class Kind { Null, Bool, Integer, String, Array, Object };

  Value() = default;  // null
  explicit Value(bool b) : data_(b) {}
  explicit Value(int64_t i) : data_(i) {}
  explicit Value(std::string s) : data_(std::move(s)) {}
  explicit Value(const char* s) : data_(std::string(s)) {}
  explicit Value(ValueList items) : data_(std::move(items)) {}
  explicit Value(MemberList members) : data_(std::move(members)) {}
  static Value array() { return Value(ValueList{}); }
  static Value object() { return Value(MemberList{}); }

  Kind kind() const { return static_cast<Kind>(data_.index()); }
  bool is_null() const { return kind() == Kind::Null; }
  bool is_bool() const { return kind() == Kind::Bool; }
  bool is_integer() const { return kind() == Kind::Integer; }
  bool is_string() const { return kind() == Kind::String; }
  bool is_array() const { return kind() == Kind::Array; }
  bool is_object() const { return kind() == Kind::Object; }

  // Accessors throw pillarseg::Error naming the expected and the actual kind.
  bool as_bool() const;
  int64_t as_integer() const;
  const std::string& as_string() const;
  const ValueList& items() const;
  const MemberList& members() const;

  // Object member by key, nullptr if absent (linear: headers hold a handful of keys per object).
  const Value* find(std::string_view key) const;
  // Appends to an array / adds a member to an object; adding an existing key throws.
  void push_back(Value item);
  void add(std::string key, Value value);

 private:
  std::variant<std::nullptr_t, bool, int64_t, std::string, ValueList, MemberList> data_ = nullptr;
};

// "null", "boolean", "integer", "string", "array", "object".
const char* kind_name(Value::Kind kind);

// Parses one JSON document (surrounding whitespace allowed). `source` names the input in error
// messages, e.g. "model.safetensors: header". Peak memory is a small multiple of text.size().
Value parse(std::string_view text, std::string_view source);

// Compact serialisation, no whitespace, members in stored order; deterministic. Non-ASCII text
// is written as UTF-8; '"', '\\' and control characters are escaped. Throws if a string is not
// valid UTF-8.
std::string dump(const Value& value);

// True if `text` is well-formed UTF-8 (no overlong forms, surrogates or code points > U+10FFFF).
bool is_valid_utf8(std::string_view text);

}  // namespace pillarseg::json
