// weights_io: F16/BF16 conversions (hand-computed bit patterns and every rounding boundary),
// the strict JSON reader/writer, and safetensors files: round trips of each dtype, a
// byte-exact file, a hand-built file with padding and metadata, every error case (the message
// names the file), the checkpoint name/shape check, and a fuzz loop over mutated files.
#include <fmt/format.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <limits>
#include <string>
#include <typeinfo>
#include <vector>

#include "core/error.hpp"
#include "core/io.hpp"
#include "core/rng.hpp"
#include "tests/support/test_support.hpp"
#include "weights_io/half.hpp"
#include "weights_io/json.hpp"
#include "weights_io/safetensors.hpp"

using namespace pillarseg;
using namespace pillarseg::weights;
namespace fs = std::filesystem;

namespace {

float from_bits(uint32_t bits) {
  return std::bit_cast<float>(bits);
}
uint32_t to_bits(float value) {
  return std::bit_cast<uint32_t>(value);
}

// Runs fn, expects a pillarseg::Error whose message contains every fragment.
template <class Fn>
void expect_error(Fn&& fn, const std::vector<std::string>& fragments) {
  try {
    fn();
    ADD_FAILURE() << "expected a pillarseg::Error containing \"" << fragments.front() << "\"";
  } catch (const Error& e) {
    const std::string message = e.what();
    for (const std::string& fragment : fragments) {
      EXPECT_NE(message.find(fragment), std::string::npos)
          << "message lacks \"" << fragment << "\":\n"
          << message;
    }
  }
}

std::vector<uint8_t> u64_le(uint64_t v) {
  std::vector<uint8_t> out(8);
  for (int i = 0; i < 8; ++i) out[static_cast<size_t>(i)] = static_cast<uint8_t>(v >> (8 * i));
  return out;
}

// A file image: length prefix, header text, data.
std::vector<uint8_t> file_image(const std::string& header, const std::vector<uint8_t>& data) {
  std::vector<uint8_t> out(8 + header.size() + data.size());
  const std::vector<uint8_t> length = u64_le(header.size());
  std::copy(length.begin(), length.end(), out.begin());
  std::copy(header.begin(), header.end(), out.begin() + 8);
  std::copy(data.begin(), data.end(), out.begin() + 8 + static_cast<std::ptrdiff_t>(header.size()));
  return out;
}

fs::path write_bytes(const fs::path& path, const std::vector<uint8_t>& bytes) {
  write_file_atomic(path, bytes.data(), bytes.size());
  return path;
}

Tensor<float> random_tensor(Shape shape, uint64_t seed) {
  Tensor<float> t(std::move(shape));
  Rng rng(seed);
  for (int64_t i = 0; i < t.numel(); ++i) t[i] = static_cast<float>(rng.normal());
  return t;
}

// A small valid file with every dtype, metadata, a scalar and an empty tensor.
SafeTensors sample_file() {
  SafeTensors st;
  st.metadata["format"] = "pt";
  st.metadata["note"] = "pillarseg test";
  st.add_f32("vfe.pfn_layers.0.linear.weight", random_tensor({4, 10}, 1));
  st.add_f32("segmentation_head.outc.conv.weight", random_tensor({3, 2, 1, 1}, 2), DType::F16);
  st.add_f32("segmentation_head.outc.conv.bias", random_tensor({3}, 3), DType::BF16);
  st.add_i64("vfe.pfn_layers.0.norm.num_batches_tracked", {}, {123456789012345});
  st.add_f32("empty", Tensor<float>({0, 3}));
  return st;
}

}  // namespace

// ---------------------------------------------------------------- F16 / BF16 conversions

TEST(Half, F16SpecialValuesHandComputed) {
  EXPECT_EQ(float_to_f16_bits(0.0f), 0x0000);
  EXPECT_EQ(float_to_f16_bits(-0.0f), 0x8000);
  EXPECT_EQ(float_to_f16_bits(1.0f), 0x3C00);
  EXPECT_EQ(float_to_f16_bits(-2.0f), 0xC000);
  EXPECT_EQ(float_to_f16_bits(0.5f), 0x3800);
  EXPECT_EQ(float_to_f16_bits(0.1f), 0x2E66);  // 0.0999755859375
  EXPECT_EQ(float_to_f16_bits(1.0f / 3.0f), 0x3555);
  EXPECT_EQ(float_to_f16_bits(65504.0f), 0x7BFF);  // largest finite
  EXPECT_EQ(float_to_f16_bits(65519.0f), 0x7BFF);  // below the midpoint to 2^16
  EXPECT_EQ(float_to_f16_bits(65520.0f), 0x7C00);  // midpoint, 0x7BFF is odd: ties to Inf
  EXPECT_EQ(float_to_f16_bits(1e6f), 0x7C00);
  EXPECT_EQ(float_to_f16_bits(-1e6f), 0xFC00);
  EXPECT_EQ(float_to_f16_bits(std::numeric_limits<float>::infinity()), 0x7C00);
  EXPECT_EQ(float_to_f16_bits(-std::numeric_limits<float>::infinity()), 0xFC00);
  EXPECT_EQ(float_to_f16_bits(std::ldexp(1.0f, -14)), 0x0400);     // smallest normal
  EXPECT_EQ(float_to_f16_bits(std::ldexp(1023.0f, -24)), 0x03FF);  // largest subnormal
  EXPECT_EQ(float_to_f16_bits(std::ldexp(1.0f, -24)), 0x0001);     // smallest subnormal
  EXPECT_EQ(float_to_f16_bits(-std::ldexp(1.0f, -24)), 0x8001);
  EXPECT_EQ(float_to_f16_bits(std::ldexp(1.0f, -25)), 0x0000);     // tie between 0 and 2^-24: even
  EXPECT_EQ(float_to_f16_bits(std::ldexp(3.0f, -26)), 0x0001);     // 0.75 * 2^-24 rounds up
  EXPECT_EQ(float_to_f16_bits(std::ldexp(3.0f, -25)), 0x0002);     // 1.5 * 2^-24: tie to even 2
  EXPECT_EQ(float_to_f16_bits(std::ldexp(5.0f, -25)), 0x0002);     // 2.5 * 2^-24: tie to even 2
  EXPECT_EQ(float_to_f16_bits(std::ldexp(2047.0f, -25)), 0x0400);  // rounds up into the normals
  EXPECT_EQ(float_to_f16_bits(from_bits(0x00000001)), 0x0000);     // float subnormal underflows
  EXPECT_EQ(float_to_f16_bits(-from_bits(0x00000001)), 0x8000);
  // Ties between normals: 1 + 2^-11 lies halfway between 0x3C00 and 0x3C01.
  EXPECT_EQ(float_to_f16_bits(1.0f + std::ldexp(1.0f, -11)), 0x3C00);
  EXPECT_EQ(float_to_f16_bits(1.0f + std::ldexp(3.0f, -11)), 0x3C02);
  EXPECT_EQ(float_to_f16_bits(1.0f + std::ldexp(1.0f, -11) + std::ldexp(1.0f, -20)), 0x3C01);
  // 2 - 2^-12 lies above the midpoint between 0x3FFF (2 - 2^-10) and 2: the mantissa carries
  // into the exponent.
  EXPECT_EQ(float_to_f16_bits(2.0f - std::ldexp(1.0f, -12)), 0x4000);

  const uint16_t nan = float_to_f16_bits(std::numeric_limits<float>::quiet_NaN());
  EXPECT_EQ(nan & 0x7C00, 0x7C00);
  EXPECT_NE(nan & 0x03FF, 0);
  // A signalling NaN whose payload sits only in the low 13 bits must not become Inf.
  const uint16_t low_payload_nan = float_to_f16_bits(from_bits(0xFF800001u));
  EXPECT_EQ(low_payload_nan & 0xFC00, 0xFC00);
  EXPECT_NE(low_payload_nan & 0x03FF, 0);

  EXPECT_EQ(f16_bits_to_float(0x0001), std::ldexp(1.0f, -24));
  EXPECT_EQ(f16_bits_to_float(0x03FF), std::ldexp(1023.0f, -24));
  EXPECT_EQ(f16_bits_to_float(0x0200), std::ldexp(1.0f, -15));
  EXPECT_EQ(f16_bits_to_float(0x0400), std::ldexp(1.0f, -14));
  EXPECT_EQ(f16_bits_to_float(0x7BFF), 65504.0f);
  EXPECT_EQ(f16_bits_to_float(0x3555), 0.333251953125f);
  EXPECT_EQ(f16_bits_to_float(0xC000), -2.0f);
  EXPECT_EQ(to_bits(f16_bits_to_float(0x8000)), 0x80000000u);
  EXPECT_EQ(f16_bits_to_float(0xFC00), -std::numeric_limits<float>::infinity());
  EXPECT_TRUE(std::isnan(f16_bits_to_float(0x7E00)));
  EXPECT_TRUE(std::isnan(f16_bits_to_float(0x7C01)));
}

// Every F16 value widens exactly and narrows back to itself; around every midpoint between two
// neighbouring F16 values, floats just below/above round down/up and the midpoint to even.
TEST(Half, F16EveryValueAndEveryRoundingBoundary) {
  for (uint32_t h = 0; h <= 0xFFFF; ++h) {
    const auto half = static_cast<uint16_t>(h);
    const float f = f16_bits_to_float(half);
    if ((half & 0x7C00) == 0x7C00 && (half & 0x03FF) != 0) {
      ASSERT_TRUE(std::isnan(f)) << std::hex << h;
      ASSERT_EQ(float_to_f16_bits(f) & 0x8000, half & 0x8000) << "NaN keeps its sign";
      continue;
    }
    ASSERT_EQ(float_to_f16_bits(f), half) << std::hex << h;
    // Exact value by a formula independent of the bit manipulation.
    const int exponent = (half >> 10) & 0x1F;
    const int mantissa = half & 0x3FF;
    const double magnitude = exponent == 0x1F ? INFINITY
                             : exponent == 0  ? std::ldexp(mantissa, -24)
                                              : std::ldexp(1024 + mantissa, exponent - 25);
    ASSERT_EQ(static_cast<double>(f), (half & 0x8000) ? -magnitude : magnitude) << std::hex << h;
  }
  for (uint32_t h = 0; h < 0x7C00; ++h) {  // positive finite values and their upper neighbour
    const double lo = f16_bits_to_float(static_cast<uint16_t>(h));
    const double hi = h + 1 == 0x7C00 ? 65536.0 : f16_bits_to_float(static_cast<uint16_t>(h + 1));
    const auto midpoint = static_cast<float>((lo + hi) / 2);  // 12 significant bits: exact
    ASSERT_EQ(static_cast<double>(midpoint), (lo + hi) / 2);
    const auto even = static_cast<uint16_t>((h & 1) ? h + 1 : h);
    ASSERT_EQ(float_to_f16_bits(midpoint), even) << std::hex << h;
    ASSERT_EQ(float_to_f16_bits(std::nextafter(midpoint, 0.0f)), h) << std::hex << h;
    ASSERT_EQ(float_to_f16_bits(std::nextafter(midpoint, INFINITY)), h + 1) << std::hex << h;
    ASSERT_EQ(float_to_f16_bits(-midpoint), even | 0x8000) << std::hex << h;
  }
}

TEST(Half, BF16SpecialValuesHandComputed) {
  EXPECT_EQ(float_to_bf16_bits(0.0f), 0x0000);
  EXPECT_EQ(float_to_bf16_bits(-0.0f), 0x8000);
  EXPECT_EQ(float_to_bf16_bits(1.0f), 0x3F80);
  EXPECT_EQ(float_to_bf16_bits(-2.0f), 0xC000);
  EXPECT_EQ(float_to_bf16_bits(0.1f), 0x3DCD);                               // 0x3DCCCCCD rounds up
  EXPECT_EQ(float_to_bf16_bits(from_bits(0x3F808000u)), 0x3F80);             // tie, 0x3F80 even
  EXPECT_EQ(float_to_bf16_bits(from_bits(0x3F818000u)), 0x3F82);             // tie, 0x3F81 odd
  EXPECT_EQ(float_to_bf16_bits(from_bits(0x3F808001u)), 0x3F81);             // above the midpoint
  EXPECT_EQ(float_to_bf16_bits(from_bits(0x3F807FFFu)), 0x3F80);             // below the midpoint
  EXPECT_EQ(float_to_bf16_bits(from_bits(0x7F7F0000u)), 0x7F7F);             // largest finite BF16
  EXPECT_EQ(float_to_bf16_bits(std::numeric_limits<float>::max()), 0x7F80);  // rounds to Inf
  EXPECT_EQ(float_to_bf16_bits(std::numeric_limits<float>::infinity()), 0x7F80);
  EXPECT_EQ(float_to_bf16_bits(-std::numeric_limits<float>::infinity()), 0xFF80);
  EXPECT_EQ(float_to_bf16_bits(from_bits(0x00010000u)), 0x0001);    // subnormal, exact
  EXPECT_EQ(float_to_bf16_bits(from_bits(0x00018000u)), 0x0002);    // subnormal tie to even
  EXPECT_EQ(float_to_bf16_bits(from_bits(0x00008000u)), 0x0000);    // tie between 0 and 0x0001
  EXPECT_EQ(float_to_bf16_bits(from_bits(0x007FFFFFu)), 0x0080);    // into the smallest normal
  const uint16_t nan = float_to_bf16_bits(from_bits(0x7F800001u));  // payload in the low bits
  EXPECT_EQ(nan & 0x7F80, 0x7F80);
  EXPECT_NE(nan & 0x007F, 0);
  EXPECT_TRUE(std::isnan(bf16_bits_to_float(nan)));
  EXPECT_EQ(float_to_bf16_bits(from_bits(0xFFC00000u)), 0xFFC0);  // negative quiet NaN

  EXPECT_EQ(bf16_bits_to_float(0x3F80), 1.0f);
  EXPECT_EQ(bf16_bits_to_float(0x0001), from_bits(0x00010000u));
  EXPECT_EQ(to_bits(bf16_bits_to_float(0x8000)), 0x80000000u);
  EXPECT_EQ(bf16_bits_to_float(0xFF80), -std::numeric_limits<float>::infinity());
}

TEST(Half, BF16EveryValueAndEveryRoundingBoundary) {
  for (uint32_t b = 0; b <= 0xFFFF; ++b) {
    const auto bf16 = static_cast<uint16_t>(b);
    const float f = bf16_bits_to_float(bf16);
    ASSERT_EQ(to_bits(f), b << 16);
    if (std::isnan(f)) continue;
    ASSERT_EQ(float_to_bf16_bits(f), bf16) << std::hex << b;
  }
  for (uint32_t b = 0; b < 0x7F80; ++b) {
    // The float halfway between b and b + 1 has low half 0x8000; its neighbours 0x7FFF/0x8001.
    const uint32_t midpoint = (b << 16) | 0x8000u;
    const auto even = static_cast<uint16_t>((b & 1) ? b + 1 : b);
    ASSERT_EQ(float_to_bf16_bits(from_bits(midpoint)), even) << std::hex << b;
    ASSERT_EQ(float_to_bf16_bits(from_bits(midpoint - 1)), b) << std::hex << b;
    ASSERT_EQ(float_to_bf16_bits(from_bits(midpoint + 1)), b + 1) << std::hex << b;
    ASSERT_EQ(float_to_bf16_bits(from_bits(midpoint | 0x80000000u)), even | 0x8000)
        << std::hex << b;
  }
}

// ---------------------------------------------------------------- JSON

TEST(Json, ParsesAllValueKindsAndEscapes) {
  const std::string text =
      " {\"a\": [1, -2, 0, 9223372036854775807, -9223372036854775808],\n"
      "  \"s\": \"q\\\"b\\\\s\\/\\b\\f\\n\\r\\t\\u00e9\\u20AC\\ud83d\\ude00 raw\xC3\xA9\",\n"
      "  \"t\": true, \"f\": false, \"n\": null, \"o\": {}, \"e\": [] } ";
  const json::Value v = json::parse(text, "test");
  ASSERT_TRUE(v.is_object());
  ASSERT_EQ(v.members().size(), 7u);
  EXPECT_EQ(v.members()[0].first, "a");  // document order kept
  const json::ValueList& a = v.find("a")->items();
  ASSERT_EQ(a.size(), 5u);
  EXPECT_EQ(a[0].as_integer(), 1);
  EXPECT_EQ(a[1].as_integer(), -2);
  EXPECT_EQ(a[2].as_integer(), 0);
  EXPECT_EQ(a[3].as_integer(), std::numeric_limits<int64_t>::max());
  EXPECT_EQ(a[4].as_integer(), std::numeric_limits<int64_t>::min());
  EXPECT_EQ(v.find("s")->as_string(),
            "q\"b\\s/\b\f\n\r\t\xC3\xA9\xE2\x82\xAC\xF0\x9F\x98\x80 raw\xC3\xA9");
  EXPECT_TRUE(v.find("t")->as_bool());
  EXPECT_FALSE(v.find("f")->as_bool());
  EXPECT_TRUE(v.find("n")->is_null());
  EXPECT_TRUE(v.find("o")->members().empty());
  EXPECT_TRUE(v.find("e")->items().empty());
  EXPECT_EQ(v.find("missing"), nullptr);
  expect_error([&] { v.find("a")->as_string(); }, {"expected a string, found array"});
}

TEST(Json, DumpIsCompactEscapedAndRoundTrips) {
  json::Value v = json::Value::object();
  v.add("name", json::Value("tab\there \"q\" back\\slash \x01 \xC3\xA9"));
  v.add("list",
        json::Value(json::ValueList{json::Value(int64_t{-5}), json::Value(true), json::Value()}));
  v.add("empty", json::Value::object());
  const std::string text = json::dump(v);
  EXPECT_EQ(text,
            "{\"name\":\"tab\\there \\\"q\\\" back\\\\slash \\u0001 \xC3\xA9\","
            "\"list\":[-5,true,null],\"empty\":{}}");
  EXPECT_EQ(json::dump(json::parse(text, "round trip")), text);
  expect_error([&] { v.add("name", json::Value()); }, {"already has a member \"name\""});
  expect_error([] { json::dump(json::Value(std::string("bad \xC0\xAF"))); }, {"not valid UTF-8"});
}

TEST(Json, RejectsMalformedInputWithPosition) {
  struct Case {
    std::string text;
    std::string fragment;
  };
  const std::vector<Case> cases = {
      {"", "expected a value, found end of input"},
      {"{\"a\":1,}", "expected a member name"},
      {"[1,]", "expected a value, found ']'"},
      {"[1 2]", "expected ',' or ']'"},
      {"{\"a\" 1}", "expected ':'"},
      {"{\"a\":1", "expected ',' or '}'"},
      {"{\"a\":1}{}", "after the end of the JSON value"},
      {"{\"a\":1,\"a\":2}", "duplicate key \"a\""},
      {"01", "leading zeros"},
      {"-", "expected a digit"},
      {"1.5", "only integers"},
      {"1e3", "only integers"},
      {"9223372036854775808", "out of the 64-bit range"},
      {"-9223372036854775809", "out of the 64-bit range"},
      {"tru", "expected 'true'"},
      {"nul", "expected 'null'"},
      {"'a'", "expected a value"},
      {"\"abc", "unterminated string"},
      {"\"a\x01\"", "control character"},
      {"\"a\nb\"", "control character"},
      {"\"\\q\"", "invalid escape"},
      {"\"\\u12G4\"", "hex digit"},
      {"\"\\u12\"", "hex digit"},
      {"\"\\ud800\"", "not followed by a \\u low surrogate"},
      {"\"\\ud800\\u0041\"", "not a low surrogate"},
      {"\"\\udc00\"", "lone low surrogate"},
      {"\"\xC0\xAF\"", "invalid UTF-8"},          // overlong '/'
      {"\"\xED\xA0\x80\"", "invalid UTF-8"},      // UTF-8 encoded surrogate
      {"\"\xF4\x90\x80\x80\"", "invalid UTF-8"},  // above U+10FFFF
      {"\"\xE2\x82\"", "invalid UTF-8"},          // truncated sequence
      {"\"\x80\"", "invalid UTF-8"},              // lone continuation byte
      {std::string(100000, '['), "nesting deeper than"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.text.substr(0, 40));
    expect_error([&] { json::parse(c.text, "source.json"); },
                 {"source.json", "invalid JSON", c.fragment});
  }
  expect_error([] { json::parse("{\n  \"a\": x}", "src"); }, {"line 2, column 8"});
}

// ---------------------------------------------------------------- safetensors

TEST(SafeTensors, RoundTripOfEveryDtype) {
  const fs::path path = test::temp_dir() / "round_trip.safetensors";
  const Tensor<float> f32 = random_tensor({2, 3, 5}, 7);
  Tensor<float> wide = random_tensor({17}, 8);  // arbitrary floats: F16/BF16 round them
  wide[0] = 0.0f;
  wide[1] = -0.0f;
  wide[2] = std::ldexp(1.0f, -24);
  wide[3] = std::numeric_limits<float>::infinity();
  wide[4] = std::numeric_limits<float>::quiet_NaN();
  wide[5] = 1e-30f;
  const std::vector<int64_t> i64 = {
      0, -1, std::numeric_limits<int64_t>::max(), std::numeric_limits<int64_t>::min(), 42, 7};

  SafeTensors st;
  st.metadata["format"] = "pt";
  st.add_f32("f32", f32);
  st.add_f32("f16", wide, DType::F16);
  st.add_f32("bf16", wide, DType::BF16);
  st.add_i64("i64", {2, 3}, i64);
  st.add_i64("scalar", {}, {5});
  st.add_f32("empty", Tensor<float>({3, 0, 2}), DType::F16);
  st.write(path);

  const SafeTensors back = SafeTensors::read(path);
  EXPECT_EQ(back.source(), path.string());
  EXPECT_EQ(back.names(),
            (std::vector<std::string>{"bf16", "empty", "f16", "f32", "i64", "scalar"}));
  EXPECT_EQ(back.metadata, st.metadata);
  for (const std::string& name : st.names()) {
    EXPECT_EQ(back.at(name).dtype, st.at(name).dtype) << name;
    EXPECT_EQ(back.at(name).shape, st.at(name).shape) << name;
    EXPECT_EQ(back.at(name).bytes, st.at(name).bytes) << name;
  }
  EXPECT_TRUE(test::all_close(back.get_f32("f32"), f32, 0, 0));
  const Tensor<float> f16 = back.get_f32("f16", {17});
  const Tensor<float> bf16 = back.get_f32("bf16", {17});
  for (int64_t i = 0; i < wide.numel(); ++i) {
    EXPECT_EQ(float_to_f16_bits(f16[i]), float_to_f16_bits(wide[i])) << i;
    EXPECT_EQ(to_bits(bf16[i]), static_cast<uint32_t>(float_to_bf16_bits(wide[i])) << 16) << i;
    if (std::isfinite(wide[i])) {
      EXPECT_NEAR(f16[i], wide[i], std::abs(wide[i]) * std::ldexp(1.0, -11) + std::ldexp(1.0, -25));
      EXPECT_NEAR(bf16[i], wide[i], std::abs(wide[i]) * std::ldexp(1.0, -8));
    }
  }
  EXPECT_EQ(to_bits(f16[1]), 0x80000000u);
  EXPECT_EQ(f16[2], std::ldexp(1.0f, -24));
  EXPECT_TRUE(std::isnan(f16[4]) && std::isnan(bf16[4]));
  EXPECT_EQ(f16[5], 0.0f);
  EXPECT_EQ(back.get_i64("i64"), i64);
  EXPECT_EQ(back.get_i64("scalar"), std::vector<int64_t>{5});
  EXPECT_EQ(back.get_f32("empty").shape(), (Shape{3, 0, 2}));
  EXPECT_EQ(back.get_f32("empty").numel(), 0);
  EXPECT_EQ(back.serialize(), st.serialize());
}

TEST(SafeTensors, ByteExactOutput) {
  // Added out of order. The header lists names in order; the data holds the widest dtype first.
  SafeTensors st;
  Tensor<float> b({2});
  b[0] = 1.0f, b[1] = -2.0f;
  st.add_f32("b", b);
  Tensor<float> a({1, 3});
  a[0] = 1.0f, a[1] = -0.5f, a[2] = 65504.0f;
  st.add_f32("a", a, DType::F16);
  st.add_i64("c", {}, {7});
  st.metadata["format"] = "pt";

  const std::string header =
      "{\"__metadata__\":{\"format\":\"pt\"},"
      "\"a\":{\"dtype\":\"F16\",\"shape\":[1,3],\"data_offsets\":[16,22]},"
      "\"b\":{\"dtype\":\"F32\",\"shape\":[2],\"data_offsets\":[8,16]},"
      "\"c\":{\"dtype\":\"I64\",\"shape\":[],\"data_offsets\":[0,8]}}";
  ASSERT_EQ(header.size(), 195u);  // + 5 spaces = 200: the data starts at 208 = 8 * 26
  const std::vector<uint8_t> data = {
      7,    0,    0,    0,    0,    0,    0,    0,     // c: int64 7
      0x00, 0x00, 0x80, 0x3F, 0x00, 0x00, 0x00, 0xC0,  // b: 1.0f, -2.0f
      0x00, 0x3C, 0x00, 0xB8, 0xFF, 0x7B};             // a: F16 1.0, -0.5, 65504
  const std::vector<uint8_t> expected = file_image(header + "     ", data);
  ASSERT_EQ(expected.size(), 8u + 200u + 22u);
  ASSERT_EQ(std::vector<uint8_t>(expected.begin(), expected.begin() + 8),
            (std::vector<uint8_t>{200, 0, 0, 0, 0, 0, 0, 0}));
  EXPECT_EQ(st.serialize(), expected);

  const fs::path path = test::temp_dir() / "exact.safetensors";
  st.write(path);
  const std::vector<char> on_disk = read_file_bytes(path);
  EXPECT_EQ(std::vector<uint8_t>(on_disk.begin(), on_disk.end()), expected);
  for (const auto& entry : fs::directory_iterator(path.parent_path())) {
    EXPECT_EQ(entry.path().filename(), "exact.safetensors") << "temporary file left behind";
  }
}

TEST(SafeTensors, SameContentSameBytesAndAtomicOverwrite) {
  SafeTensors one, two;
  one.add_f32("x", random_tensor({3}, 1));
  one.add_f32("y", random_tensor({2, 2}, 2), DType::BF16);
  two.add_f32("y", random_tensor({2, 2}, 2), DType::BF16);
  two.add_f32("x", random_tensor({3}, 1));
  EXPECT_EQ(one.serialize(), two.serialize());
  const std::vector<uint8_t> bytes = one.serialize();
  uint64_t header_length = 0;
  for (int i = 7; i >= 0; --i) header_length = (header_length << 8) | bytes[static_cast<size_t>(i)];
  EXPECT_EQ((8 + header_length) % 8, 0u) << "the data must start 8-byte aligned";
  EXPECT_EQ(bytes[8 + header_length - 1], ' ') << "padded with spaces";

  const fs::path path = test::temp_dir() / "overwrite.safetensors";
  one.write(path);
  SafeTensors three;
  three.add_i64("z", {1}, {3});
  three.write(path);
  EXPECT_EQ(SafeTensors::read(path).names(), std::vector<std::string>{"z"});
}

// Odd element counts of mixed widths, names interleaved: every tensor must still start at a
// file offset that is a multiple of its element size.
TEST(SafeTensors, EveryTensorAlignedToItsElementSize) {
  SafeTensors st;
  const DType dtypes[] = {DType::F16, DType::F32, DType::BF16, DType::I64};
  for (int i = 0; i < 12; ++i) {
    const std::string name = fmt::format("t{}", i);
    const DType dtype = dtypes[i % 4];
    if (dtype == DType::I64) {
      st.add_i64(name, {i % 3}, std::vector<int64_t>(static_cast<size_t>(i % 3), i));
    } else {
      st.add_f32(name, random_tensor({2 * i + 1}, static_cast<uint64_t>(i)), dtype);
    }
  }
  const std::vector<uint8_t> bytes = st.serialize();
  uint64_t header_length = 0;
  for (int i = 7; i >= 0; --i) header_length = (header_length << 8) | bytes[static_cast<size_t>(i)];
  const json::Value header = json::parse(
      std::string_view(reinterpret_cast<const char*>(bytes.data()) + 8, header_length), "aligned");
  for (const std::string& name : st.names()) {
    const json::Value* entry = header.find(name);
    ASSERT_NE(entry, nullptr) << name;
    const int64_t begin = entry->find("data_offsets")->items()[0].as_integer();
    EXPECT_EQ((8 + static_cast<int64_t>(header_length) + begin) % dtype_size(st.at(name).dtype), 0)
        << name << " " << dtype_name(st.at(name).dtype) << " at data offset " << begin;
  }
  EXPECT_EQ(SafeTensors::parse(bytes, "aligned").serialize(), bytes);
}

// A file written by hand the way other writers lay it out: whitespace and newlines in the
// header, members not in name order, metadata between tensors and with escapes, padding.
TEST(SafeTensors, ReadsHandBuiltFileWithPaddingAndMetadata) {
  std::string header =
      "{\n  \"weight\": {\"dtype\": \"BF16\", \"shape\": [2, 2], \"data_offsets\": [8, 16]},\n"
      "  \"__metadata__\": {\"format\": \"pt\", \"author\": \"Jos\\u00e9 \\ud83d\\ude00\"},\n"
      "  \"count\": {\"shape\": [], \"data_offsets\": [0, 8], \"dtype\": \"I64\"}\n}";
  header.append(13, ' ');
  const std::vector<uint8_t> data = {
      0xFE, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF,  // count = -2
      0x80, 0x3F, 0x00, 0xC0, 0x00, 0x00, 0x80, 0x7F,  // 1, -2, 0, +Inf
  };
  const fs::path path =
      write_bytes(test::temp_dir() / "hand.safetensors", file_image(header, data));
  const SafeTensors st = SafeTensors::read(path);
  EXPECT_EQ(st.names(), (std::vector<std::string>{"count", "weight"}));
  EXPECT_EQ(st.metadata.at("format"), "pt");
  EXPECT_EQ(st.metadata.at("author"), "Jos\xC3\xA9 \xF0\x9F\x98\x80");
  EXPECT_EQ(st.get_i64("count"), std::vector<int64_t>{-2});
  EXPECT_EQ(st.at("count").shape, Shape{});
  const Tensor<float> w = st.get_f32("weight", {2, 2});
  EXPECT_EQ(w(0, 0), 1.0f);
  EXPECT_EQ(w(0, 1), -2.0f);
  EXPECT_EQ(w(1, 0), 0.0f);
  EXPECT_EQ(w(1, 1), std::numeric_limits<float>::infinity());
}

TEST(SafeTensors, MalformedFilesNameTheFileAndTheProblem) {
  const fs::path dir = test::temp_dir();
  const std::vector<uint8_t> eight(8, 0);
  const std::string f32x2 = "\"dtype\":\"F32\",\"shape\":[2]";
  struct Case {
    std::string label;
    std::vector<uint8_t> bytes;
    std::string fragment;
  };
  const std::vector<uint8_t> valid = sample_file().serialize();
  std::vector<uint8_t> truncated(valid.begin(), valid.end() - 1);
  std::vector<uint8_t> trailing = valid;
  trailing.insert(trailing.end(), {1, 2, 3});
  std::vector<uint8_t> huge_length = valid;
  std::fill(huge_length.begin(), huge_length.begin() + 8, 0xFF);
  std::vector<uint8_t> length_past_end = file_image("{}", {});
  length_past_end[0] = 200;
  const std::vector<Case> cases = {
      {"empty", {}, "shorter than the 8-byte header length"},
      {"short", {1, 0, 0, 0, 0}, "shorter than the 8-byte header length"},
      {"length_past_end", length_past_end,
       "header length 200 is larger than the 2 bytes that follow it"},
      {"huge_length", huge_length, "header length 18446744073709551615 is larger"},
      {"not_json", file_image("{\"a\":", {}), "invalid JSON"},
      {"not_object", file_image("[1, 2]", {}), "not a JSON object (it does not start with '{')"},
      {"empty_header", file_image("", {}), "not a JSON object (it does not start with '{')"},
      {"padding_nul", file_image(std::string("{}\0\0", 4), {}), "after the end of the JSON value"},
      {"entry_not_object", file_image("{\"a\":[1]}", {}), "expected an object with dtype"},
      {"no_dtype", file_image("{\"a\":{\"shape\":[2],\"data_offsets\":[0,8]}}", eight),
       "tensor \"a\" has no \"dtype\""},
      {"no_shape", file_image("{\"a\":{\"dtype\":\"F32\",\"data_offsets\":[0,8]}}", eight),
       "tensor \"a\" has no \"shape\""},
      {"no_offsets", file_image("{\"a\":{" + f32x2 + "}}", eight),
       "tensor \"a\" has no \"data_offsets\""},
      {"unknown_field", file_image("{\"a\":{" + f32x2 + ",\"data_offsets\":[0,8],\"x\":1}}", eight),
       "unknown field \"x\""},
      {"unknown_dtype",
       file_image("{\"a\":{\"dtype\":\"F17\",\"shape\":[2],\"data_offsets\":[0,8]}}", eight),
       "unknown dtype \"F17\""},
      {"unsupported_dtype",
       file_image("{\"a\":{\"dtype\":\"F64\",\"shape\":[1],\"data_offsets\":[0,8]}}", eight),
       "dtype F64, which pillarseg does not load"},
      {"dtype_not_string",
       file_image("{\"a\":{\"dtype\":4,\"shape\":[2],\"data_offsets\":[0,8]}}", eight),
       "dtype must be a string"},
      {"negative_dim",
       file_image("{\"a\":{\"dtype\":\"F32\",\"shape\":[-2],\"data_offsets\":[0,8]}}", eight),
       "non-negative integers, found -2"},
      {"size_mismatch",
       file_image("{\"a\":{\"dtype\":\"F32\",\"shape\":[3],\"data_offsets\":[0,8]}}", eight),
       "shape (3) of F32 needs 12 bytes, but data_offsets [0, 8] span 8"},
      {"absurd_shape",
       file_image("{\"a\":{\"dtype\":\"F32\",\"shape\":[1000000000000,1000000000000],"
                  "\"data_offsets\":[0,8]}}",
                  eight),
       "needs more than 2^63 bytes"},
      {"offsets_one_number", file_image("{\"a\":{" + f32x2 + ",\"data_offsets\":[0]}}", eight),
       "data_offsets must be an array [begin, end]"},
      {"offsets_reversed", file_image("{\"a\":{" + f32x2 + ",\"data_offsets\":[8,0]}}", eight),
       "data_offsets [8, 0] are not an interval"},
      {"offsets_out_of_range", file_image("{\"a\":{" + f32x2 + ",\"data_offsets\":[4,12]}}", eight),
       "extend past the end of the data (8 bytes)"},
      {"truncated", truncated, "the file is truncated"},
      {"overlap",
       file_image("{\"a\":{" + f32x2 + ",\"data_offsets\":[0,8]},\"b\":{" + f32x2 +
                      ",\"data_offsets\":[4,12]}}",
                  std::vector<uint8_t>(12, 0)),
       "tensors \"a\" [0, 8) and \"b\" [4, 12) overlap"},
      {"hole",
       file_image("{\"a\":{\"dtype\":\"F32\",\"shape\":[],\"data_offsets\":[0,4]},"
                  "\"b\":{\"dtype\":\"F32\",\"shape\":[],\"data_offsets\":[8,12]}}",
                  std::vector<uint8_t>(12, 0)),
       "data bytes [4, 8) belong to no tensor"},
      {"trailing_garbage", trailing, "3 trailing bytes after the last tensor"},
      {"not_covering", file_image("{}", eight), "8 trailing bytes"},
      {"duplicate_names",
       file_image("{\"a\":{" + f32x2 + ",\"data_offsets\":[0,8]},\"a\":{" + f32x2 +
                      ",\"data_offsets\":[8,16]}}",
                  std::vector<uint8_t>(16, 0)),
       "duplicate key \"a\""},
      {"metadata_not_object", file_image("{\"__metadata__\":[]}", {}),
       "must be an object of strings"},
      {"metadata_value_not_string", file_image("{\"__metadata__\":{\"epoch\":3}}", {}),
       "entry \"epoch\" must be a string, found integer"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.label);
    const fs::path path = write_bytes(dir / (c.label + ".safetensors"), c.bytes);
    expect_error([&] { SafeTensors::read(path); }, {path.string(), c.fragment});
  }
  expect_error([&] { SafeTensors::read(dir / "absent.safetensors"); }, {"absent.safetensors"});
}

TEST(SafeTensors, AccessErrorsNameTheFileAndTheTensor) {
  const fs::path path = test::temp_dir() / "access.safetensors";
  sample_file().write(path);
  const SafeTensors st = SafeTensors::read(path);
  expect_error([&] { st.at("vfe.pfn_layers.0.linear.bias"); },
               {path.string(), "no tensor named \"vfe.pfn_layers.0.linear.bias\"",
                "holds 5 tensors", "vfe.pfn_layers.0.linear.weight"});
  expect_error([&] { st.get_f32("vfe.pfn_layers.0.norm.num_batches_tracked"); },
               {path.string(), "is I64, not a floating-point tensor"});
  expect_error([&] { st.get_i64("vfe.pfn_layers.0.linear.weight"); },
               {path.string(), "is F32, not I64"});
  expect_error(
      [&] {
        st.get_f32("vfe.pfn_layers.0.linear.weight", {10, 4});
      },
      {path.string(), "has shape (4, 10), expected (10, 4)"});
  EXPECT_EQ(st.get_f32("vfe.pfn_layers.0.linear.weight", {4, 10}).numel(), 40);
  EXPECT_TRUE(st.contains("empty"));
  EXPECT_FALSE(st.contains("Empty"));
}

TEST(SafeTensors, AddChecksItsArguments) {
  SafeTensors st;
  st.add_f32("w", Tensor<float>({2}));
  expect_error([&] { st.add_f32("w", Tensor<float>({2})); },
               {"already holds a tensor named \"w\""});
  expect_error([&] { st.add_i64("w", {}, {1}); }, {"already holds a tensor named \"w\""});
  expect_error([&] { st.add_f32("", Tensor<float>({2})); }, {"must not be empty"});
  expect_error([&] { st.add_f32("__metadata__", Tensor<float>({2})); }, {"reserved"});
  expect_error([&] { st.add_f32("bad\xFF", Tensor<float>({2})); }, {"not valid UTF-8"});
  expect_error([&] { st.add_f32("x", Tensor<float>({2}), DType::I64); },
               {"cannot be stored as I64"});
  expect_error(
      [&] {
        st.add_i64("x", {2, 2}, {1, 2, 3});
      },
      {"shape (2, 2) holds 4 values, given 3"});
  expect_error([&] { st.add_i64("x", {-1}, {}); }, {"negative dimension"});
  Tensor<float> big({3});
  big[2] = 70000.0f;
  expect_error([&] { st.add_f32("x", big, DType::F16); },
               {"element 2 = 70000 overflows F16", "store it as F32 or BF16"});
  st.add_f32("x", big, DType::BF16);  // BF16 has the float32 range
  big[2] = std::numeric_limits<float>::infinity();
  st.add_f32("inf", big, DType::F16);  // an Inf is kept, not an overflow
  expect_error(
      [&] {
        st.add(TensorRecord{"r", DType::F16, {3}, std::vector<uint8_t>(4)});
      },
      {"needs 6 bytes, given 4"});
  st.add(TensorRecord{"r", DType::F16, {3}, {0x00, 0x3C, 0x00, 0x40, 0x00, 0x00}});
  EXPECT_EQ(st.get_f32("r")[1], 2.0f);
  st.metadata["bad"] = "\xC3";
  expect_error([&] { st.serialize(); }, {"metadata entry \"bad\" is not valid UTF-8"});
}

TEST(SafeTensors, CheckNamesAndShapesReportsEveryProblemAtOnce) {
  SafeTensors st;
  st.add_f32("conv.weight", Tensor<float>({8, 4, 3, 3}));
  st.add_f32("conv.bias", Tensor<float>({7}));
  st.add_f32("norm.num_batches_tracked", Tensor<float>(Shape{}));
  st.add_f32("stray", Tensor<float>({1}));
  const std::vector<ExpectedTensor> expected = {
      {"conv.weight", {8, 4, 3, 3}},
      {"conv.bias", {8}},
      {"norm.num_batches_tracked", {}, ValueKind::Integer},
      {"norm.weight", {8}},
  };
  expect_error([&] { check_names_and_shapes(st, expected, "UNet checkpoint"); },
               {"UNet checkpoint (<in-memory safetensors>): 4 problems",
                "missing norm.weight (expected shape (8))",
                "wrong shape conv.bias: (7) in the file, expected (8)",
                "wrong dtype norm.num_batches_tracked: F32 in the file, expected I64",
                "unexpected stray (F32 (1))"});

  SafeTensors good;
  good.add_f32("conv.weight", Tensor<float>({8, 4, 3, 3}), DType::F16);
  good.add_i64("norm.num_batches_tracked", {}, {0});
  EXPECT_NO_THROW(check_names_and_shapes(
      good, {{"conv.weight", {8, 4, 3, 3}}, {"norm.num_batches_tracked", {}, ValueKind::Integer}},
      "net"));
  expect_error(
      [&] {
        check_names_and_shapes(good, {{"a", {1}}, {"a", {1}}}, "net");
      },
      {"names \"a\" twice"});
  expect_error(
      [&] {
        check_names_and_shapes(good, {{"conv.weight", {8, 4, 3, 3}}}, "net");
      },
      {"1 problem with", "unexpected norm.num_batches_tracked (I64 ())"});
}

// Random byte flips, truncations, insertions and length-field rewrites of a valid file: each
// mutant parses into consistent tensors or throws pillarseg::Error; nothing else may escape
// (std::bad_alloc from an absurd allocation, a crash under the sanitizers).
TEST(SafeTensors, FuzzedFilesParseOrThrowError) {
  const std::vector<uint8_t> valid = sample_file().serialize();
  const size_t header_end = 8 + static_cast<size_t>(valid[0] | (valid[1] << 8));
  Rng rng(2024);
  int parsed = 0, rejected = 0;
  constexpr int kMutants = 4000;
  for (int iteration = 0; iteration < kMutants; ++iteration) {
    std::vector<uint8_t> mutant = valid;
    const uint64_t kind = rng.uniform_int(5);
    if (kind == 0) {  // flip a few bytes anywhere
      for (uint64_t n = 1 + rng.uniform_int(4); n > 0; --n) {
        mutant[rng.uniform_int(mutant.size())] ^= static_cast<uint8_t>(1 + rng.uniform_int(255));
      }
    } else if (kind == 1) {  // flip one byte inside the header text (reaches the validation)
      mutant[8 + rng.uniform_int(header_end - 8)] = static_cast<uint8_t>(rng.uniform_int(256));
    } else if (kind == 2) {  // truncate
      mutant.resize(rng.uniform_int(mutant.size()));
    } else if (kind == 3) {  // insert or delete a byte
      const size_t at = rng.uniform_int(mutant.size());
      if (rng.bernoulli(0.5)) {
        mutant.insert(mutant.begin() + static_cast<std::ptrdiff_t>(at),
                      static_cast<uint8_t>(rng.next_u64()));
      } else {
        mutant.erase(mutant.begin() + static_cast<std::ptrdiff_t>(at));
      }
    } else {  // rewrite the length field: random, or off by a little
      const uint64_t length =
          rng.bernoulli(0.5) ? rng.next_u64() : header_end - 8 + rng.uniform_int(9) - 4;
      const std::vector<uint8_t> le = u64_le(length);
      std::copy(le.begin(), le.end(), mutant.begin());
    }
    try {
      const SafeTensors st = SafeTensors::parse(mutant, "mutant");
      ++parsed;
      size_t total = 0;
      for (const std::string& name : st.names()) {
        const TensorRecord& r = st.at(name);
        ASSERT_EQ(static_cast<int64_t>(r.bytes.size()), shape_numel(r.shape) * dtype_size(r.dtype));
        total += r.bytes.size();
        if (is_floating(r.dtype)) {
          ASSERT_EQ(st.get_f32(name).numel(), shape_numel(r.shape));
        } else {
          ASSERT_EQ(static_cast<int64_t>(st.get_i64(name).size()), shape_numel(r.shape));
        }
      }
      ASSERT_LE(total, mutant.size());
      const SafeTensors again = SafeTensors::parse(st.serialize(), "re-serialized mutant");
      ASSERT_EQ(again.serialize(), st.serialize());
    } catch (const Error& e) {
      ++rejected;
      ASSERT_NE(std::string(e.what()).find("mutant"), std::string::npos) << e.what();
    } catch (const std::exception& e) {
      FAIL() << "iteration " << iteration << ": " << typeid(e).name() << ": " << e.what();
    }
  }
  EXPECT_GT(parsed, 0);  // flips in the data region keep the file valid
  EXPECT_GT(rejected, kMutants / 4);
  EXPECT_EQ(parsed + rejected, kMutants);
}
