// The CPU's 16-bit max-pool, bilinear upsampling and pillar scatter (engine/cpu/half_ops.hpp): the
// AVX-512 forms against the scalar loops, bit for bit, for BF16 and FP16, at shapes that leave
// every tail (widths not multiples of 16 or 32, a single row or column, planes of several scatter
// tiles), on values with NaN (several payloads, both signs), infinities, signed zeros, denormals
// and ties, with guard words after every output and the thread count varied; the NaN rule and the
// conversions by hand and over a sweep of FP32 bit patterns. Skipped with the reason where this CPU
// or build has no AVX-512 forms (the scalar loops are checked against the host reference in
// test_backend_ops).
#include <gtest/gtest.h>

#include <algorithm>
#include <initializer_list>
#include <array>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "core/error.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"
#include "engine/cpu/cpu_features.hpp"
#include "engine/cpu/half_ops.hpp"
#include "weights_io/half.hpp"

using namespace pillarseg;
using cpu::HalfOpsKernels;

namespace {

constexpr std::int64_t kGuard = 37;
constexpr std::uint16_t kGuardWord = 0xA7A7;
constexpr std::uint16_t kStale = 0x5A5A;  // a canvas's words before the scatter

std::string name(Precision p) { return precision_name(p); }

std::uint16_t bits(float v, Precision p) { return cpu::to_bits(v, p); }

// NaN bit patterns of the 16-bit type: quiet and signalling, both signs, several payloads.
std::vector<std::uint16_t> nans(Precision p) {
  if (p == Precision::BF16) return {0x7FC0, 0xFFC0, 0x7F81, 0x7FA5, 0xFFFF, 0x7FFF};
  return {0x7E00, 0xFE00, 0x7C01, 0x7D55, 0xFFFF, 0x7FFF};
}

// Finite and infinite specials: signed zeros, infinities, the largest values, denormals.
std::vector<std::uint16_t> specials(Precision p) {
  if (p == Precision::BF16)
    return {0x0000, 0x8000, 0x7F80, 0xFF80, 0x7F7F, 0xFF7F, 0x0001, 0x8001, 0x007F, 0x0080};
  return {0x0000, 0x8000, 0x7C00, 0xFC00, 0x7BFF, 0xFBFF, 0x0001, 0x8001, 0x03FF, 0x0400};
}

bool is_infinite_or_nan(std::uint16_t h, Precision p) {
  return p == Precision::BF16 ? (h & 0x7F80) == 0x7F80 : (h & 0x7C00) == 0x7C00;
}

// n random 16-bit values in [-4, 4], a few of them repeated (ties), with `special` of every 8
// replaced by a special value.
std::vector<std::uint16_t> random_words(std::int64_t n, Precision p, std::uint64_t seed,
                                        bool with_specials) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> value(-4.0f, 4.0f);
  std::vector<std::uint16_t> words(static_cast<size_t>(n));
  std::vector<std::uint16_t> pool = specials(p);
  for (std::uint16_t nan : nans(p)) pool.push_back(nan);
  for (std::int64_t i = 0; i < n; ++i) {
    const auto at = static_cast<size_t>(i);
    words[at] = bits(value(rng), p);
    if (i > 0 && rng() % 5 == 0) words[at] = words[at - 1];
    if (with_specials && rng() % 8 == 0) words[at] = pool[rng() % pool.size()];
  }
  return words;
}

// An output of n words followed by kGuard guard words.
struct Guarded {
  std::vector<std::uint16_t> words;
  explicit Guarded(std::int64_t n, std::uint16_t fill = kGuardWord)
      : words(static_cast<size_t>(n + kGuard), fill) {
    std::fill(words.end() - kGuard, words.end(), kGuardWord);
  }
  HRef ref(const Shape& shape) { return HRef{words.data(), shape}; }
  bool guards_intact() const {
    return std::all_of(words.end() - kGuard, words.end(), [](std::uint16_t w) { return w == kGuardWord; });
  }
};

// The first index where a and b differ (their lengths equal), or -1.
std::int64_t first_difference(const std::vector<std::uint16_t>& a, const std::vector<std::uint16_t>& b) {
  for (size_t i = 0; i < a.size(); ++i)
    if (a[i] != b[i]) return static_cast<std::int64_t>(i);
  return -1;
}

// run(y, kernels) into a guarded output of `shape` (its words `fill` before): once with the scalar
// loop, then with the AVX-512 form at each thread count, expecting the same words and intact
// guards (`label` names the case); returns the scalar loop's output.
template <class Run>
Guarded expect_avx512_equals_scalar(const Shape& shape, std::uint16_t fill, std::initializer_list<int> thread_counts,
                                    const std::string& label, const Run& run) {
  Guarded scalar(shape_numel(shape), fill);
  HRef sr = scalar.ref(shape);
  run(sr, HalfOpsKernels::Scalar);
  for (int threads : thread_counts) {
    ScopedThreads scoped(threads);
    Guarded fast(shape_numel(shape), fill);
    HRef fr = fast.ref(shape);
    run(fr, HalfOpsKernels::Avx512);
    const std::int64_t at = first_difference(scalar.words, fast.words);
    EXPECT_EQ(at, -1) << label << ", " << threads << " threads: word " << at << " is "
                      << fast.words[static_cast<size_t>(at < 0 ? 0 : at)] << ", the scalar loop's "
                      << scalar.words[static_cast<size_t>(at < 0 ? 0 : at)];
    EXPECT_TRUE(fast.guards_intact()) << label;
  }
  return scalar;
}

class HalfOpsAvx512 : public ::testing::TestWithParam<Precision> {
 protected:
  void SetUp() override {
    std::string why;
    if (!cpu::avx512_half_ops_available(&why)) GTEST_SKIP() << "no AVX-512 16-bit data movement: " << why;
  }
};

// ---- max-pool ----

TEST_P(HalfOpsAvx512, MaxPoolMatchesTheScalarLoopBitForBit) {
  const Precision p = GetParam();
  const std::vector<Shape> shapes = {{1, 1, 2, 2},  {1, 1, 1, 9},   {1, 1, 5, 1},  {1, 1, 3, 3},
                                     {2, 3, 7, 9},  {1, 2, 2, 33},  {1, 1, 4, 64}, {1, 1, 6, 65},
                                     {3, 2, 5, 95}, {1, 4, 9, 130}, {1, 1, 2, 1000}};
  std::uint64_t seed = 1;
  for (const Shape& xs : shapes) {
    const Shape ys = op::maxpool2d(xs);
    std::vector<std::uint16_t> x = random_words(shape_numel(xs), p, seed++, /*with_specials=*/true);
    const HRef xr{x.data(), xs};
    expect_avx512_equals_scalar(ys, kGuardWord, {1, 3}, name(p) + " x " + shape_str(xs),
                                [&](HRef& y, HalfOpsKernels k) { cpu::maxpool2d_half(xr, p, y, k); });
  }
}

// The rule by hand: a greater value or a NaN replaces the best so far (so the last NaN of the
// window wins), equal values keep the first (-0 before +0 stays -0).
TEST_P(HalfOpsAvx512, MaxPoolKeepsTheNanRuleAndTheFirstOfEqualValues) {
  const Precision p = GetParam();
  const std::uint16_t one = bits(1.0f, p), three = bits(3.0f, p), nan_a = nans(p)[0], nan_b = nans(p)[3],
                      minus_zero = 0x8000, zero = 0x0000, minus_inf = specials(p)[3];
  // Windows (0, 0), (0, 1), (1, 0), (1, 1), side by side in a (1, 1, 2, 2 n) input; 17 windows
  // so that the 16-lane step and its tail both see each.
  const std::vector<std::array<std::uint16_t, 4>> windows = {
      {one, nan_a, three, nan_b},   {minus_zero, zero, zero, zero},
      {zero, minus_zero, minus_zero, minus_zero}, {nan_b, one, three, one},
      {minus_inf, minus_inf, minus_inf, minus_inf}, {one, three, nan_a, one}};
  const std::vector<std::uint16_t> expected = {nan_b, minus_zero, zero, nan_b, minus_inf, nan_a};
  for (HalfOpsKernels kernels : {HalfOpsKernels::Scalar, HalfOpsKernels::Avx512}) {
    const std::int64_t n = 17;
    std::vector<std::uint16_t> x(static_cast<size_t>(4 * n));
    for (std::int64_t i = 0; i < n; ++i) {
      const auto& w = windows[static_cast<size_t>(i) % windows.size()];
      x[static_cast<size_t>(2 * i)] = w[0], x[static_cast<size_t>(2 * i + 1)] = w[1];
      x[static_cast<size_t>(2 * n + 2 * i)] = w[2], x[static_cast<size_t>(2 * n + 2 * i + 1)] = w[3];
    }
    Guarded y(n);
    HRef yr = y.ref({1, 1, 1, n});
    cpu::maxpool2d_half(HRef{x.data(), {1, 1, 2, 2 * n}}, p, yr, kernels);
    for (std::int64_t i = 0; i < n; ++i)
      EXPECT_EQ(y.words[static_cast<size_t>(i)], expected[static_cast<size_t>(i) % expected.size()])
          << name(p) << (kernels == HalfOpsKernels::Scalar ? " scalar" : " avx512") << ", window " << i;
  }
}

// ---- bilinear upsampling ----

// NaN and infinities only where both coordinates are even: no 2x2 window of the input holds two,
// so every NaN a result holds comes from one operand (which NaN an addition of two NaNs returns
// depends on the operand order, which the scalar loop leaves to the compiler).
std::vector<std::uint16_t> upsample_input(const Shape& xs, Precision p, std::uint64_t seed) {
  std::vector<std::uint16_t> x = random_words(shape_numel(xs), p, seed, /*with_specials=*/true);
  std::mt19937_64 rng(seed + 1000);
  const std::vector<std::uint16_t> finite = {specials(p)[0], specials(p)[1], specials(p)[4], specials(p)[5],
                                             specials(p)[6], specials(p)[7], specials(p)[8], specials(p)[9]};
  const std::int64_t h = xs[2], w = xs[3];
  for (std::int64_t i = 0; i < shape_numel(xs); ++i) {
    std::uint16_t& v = x[static_cast<size_t>(i)];
    const std::int64_t iy = i / w % h, ix = i % w;
    if (!is_infinite_or_nan(v, p)) continue;
    if (iy % 2 != 0 || ix % 2 != 0) v = finite[rng() % finite.size()];
  }
  return x;
}

TEST_P(HalfOpsAvx512, UpsampleMatchesTheScalarLoopBitForBit) {
  const Precision p = GetParam();
  const std::vector<Shape> shapes = {{1, 1, 1, 1}, {1, 1, 1, 7},  {1, 1, 6, 1},  {2, 3, 5, 4},  {1, 2, 3, 8},
                                     {1, 1, 4, 9}, {1, 1, 2, 16}, {1, 2, 3, 17}, {1, 1, 5, 31}, {2, 1, 3, 33},
                                     {1, 3, 4, 62}, {1, 2, 7, 125}, {1, 1, 2, 250}};
  std::uint64_t seed = 100;
  for (const Shape& xs : shapes) {
    const Shape ys = op::upsample_bilinear(xs);
    std::vector<std::uint16_t> x = upsample_input(xs, p, seed++);
    const HRef xr{x.data(), xs};
    expect_avx512_equals_scalar(ys, kGuardWord, {1, 3}, name(p) + " x " + shape_str(xs),
                                [&](HRef& y, HalfOpsKernels k) { cpu::upsample_bilinear_half(xr, p, y, k); });
  }
}

// By hand: (1, 1, 1, 2) -> (1, 1, 2, 4): columns at 0, 1/3, 2/3, 1 of the way from a to b, each
// w0 a + w1 b with both products rounded to FP32 before the sum (no FMA), then rounded once.
TEST_P(HalfOpsAvx512, UpsampleWeighsByTheTapsAndRoundsOnce) {
  const Precision p = GetParam();
  const float a = 1.0f, b = p == Precision::BF16 ? 1.0f + 0x1p-7f : 1.0f + 0x1p-10f;
  std::vector<std::uint16_t> x = {bits(a, p), bits(b, p)};
  for (HalfOpsKernels kernels : {HalfOpsKernels::Scalar, HalfOpsKernels::Avx512}) {
    Guarded y(8);
    HRef yr = y.ref({1, 1, 2, 4});
    cpu::upsample_bilinear_half(HRef{x.data(), {1, 1, 1, 2}}, p, yr, kernels);
    // The taps' weights (core/bilinear_taps.hpp); volatile keeps each product rounded on its own.
    const float third = 1.0f / 3.0f, two_thirds = 2.0f / 3.0f;
    const volatile float products[4] = {two_thirds * a, third * b, third * a, two_thirds * b};
    const std::uint16_t expected[4] = {bits(a, p), bits(products[0] + products[1], p),
                                       bits(products[2] + products[3], p), bits(b, p)};
    for (int row = 0; row < 2; ++row)
      for (int i = 0; i < 4; ++i)
        EXPECT_EQ(y.words[static_cast<size_t>(4 * row + i)], expected[i])
            << name(p) << (kernels == HalfOpsKernels::Scalar ? " scalar" : " avx512") << ", column " << i;
    EXPECT_TRUE(y.guards_intact());
  }
}

// Pairs (a, b) of 16-bit values whose (2/3) a + (1/3) b (the FP32 weights of output 1 of 2 -> 4)
// rounds to other bits with the two products rounded before the sum than in either fused form
// fma(2/3, a, (1/3) b) or fma(1/3, b, (2/3) a): a every 97th pattern from 0.5 on, every b, the
// first n found (about 1 in 4,000 pairs for BF16, 1 in 600 for FP16).
std::vector<std::array<std::uint16_t, 2>> pairs_an_fma_would_change(Precision p, size_t n) {
  const float w0 = 2.0f / 3.0f, w1 = 1.0f / 3.0f;
  std::vector<std::array<std::uint16_t, 2>> found;
  for (std::uint32_t step = 0; step < 0x10000 / 97 && found.size() < n; ++step) {
    const auto a_bits = static_cast<std::uint16_t>(bits(0.5f, p) + 97 * step);
    if (is_infinite_or_nan(a_bits, p)) continue;
    const float av = p == Precision::BF16 ? weights::bf16_bits_to_float(a_bits) : weights::f16_bits_to_float(a_bits);
    for (std::uint32_t b_bits = 0; b_bits < 0x10000 && found.size() < n; ++b_bits) {
      const auto b16 = static_cast<std::uint16_t>(b_bits);
      if (is_infinite_or_nan(b16, p)) continue;
      const float bv = p == Precision::BF16 ? weights::bf16_bits_to_float(b16) : weights::f16_bits_to_float(b16);
      const volatile float products[2] = {w0 * av, w1 * bv};
      const std::uint16_t unfused = bits(products[0] + products[1], p);
      if (unfused != bits(std::fma(w0, av, products[1]), p) && unfused != bits(std::fma(w1, bv, products[0]), p))
        found.push_back({a_bits, b16});
    }
  }
  return found;
}

// Along x (planes (1, 2)) and along y (planes (2, 1)): output 1 of each plane is the unfused sum
// of a pair an FMA would round otherwise.
TEST_P(HalfOpsAvx512, UpsampleMultipliesAndAddsWithoutFusing) {
  const Precision p = GetParam();
  const std::vector<std::array<std::uint16_t, 2>> pairs = pairs_an_fma_would_change(p, 40);
  ASSERT_EQ(pairs.size(), 40u) << name(p);
  const auto planes = static_cast<std::int64_t>(pairs.size());
  std::vector<std::uint16_t> x;
  for (const auto& pair : pairs) x.insert(x.end(), pair.begin(), pair.end());
  const float w0 = 2.0f / 3.0f, w1 = 1.0f / 3.0f;
  for (const Shape& xs : {Shape{planes, 1, 1, 2}, Shape{planes, 1, 2, 1}}) {
    for (HalfOpsKernels kernels : {HalfOpsKernels::Scalar, HalfOpsKernels::Avx512}) {
      Guarded y(8 * planes);
      HRef yr = y.ref(op::upsample_bilinear(xs));
      cpu::upsample_bilinear_half(HRef{x.data(), xs}, p, yr, kernels);
      for (std::int64_t i = 0; i < planes; ++i) {
        const auto& [a, b] = pairs[static_cast<size_t>(i)];
        const auto value = [&](std::uint16_t h) {
          return p == Precision::BF16 ? weights::bf16_bits_to_float(h) : weights::f16_bits_to_float(h);
        };
        const volatile float products[2] = {w0 * value(a), w1 * value(b)};
        // Output 1 along x: word 1 of the plane's (2, 4); along y: row 1's first word of its (4, 2).
        const std::int64_t word = 8 * i + (xs[3] == 2 ? 1 : 2);
        EXPECT_EQ(y.words[static_cast<size_t>(word)], bits(products[0] + products[1], p))
            << name(p) << (kernels == HalfOpsKernels::Scalar ? " scalar" : " avx512") << " x " << shape_str(xs)
            << ", a " << a << ", b " << b;
      }
      EXPECT_TRUE(y.guards_intact());
    }
  }
}

// ---- pillar scatter ----

struct ScatterCase {
  std::int64_t pillars, channels, batch, canvas_channels, height, width, channel0;
};

// Features in [-3, 3] with specials; cells on the canvas, some repeated (the later row wins), some
// inert (-1, -1, -1) and some outside the canvas (skipped).
void scatter_inputs(const ScatterCase& c, std::uint64_t seed, std::vector<float>& features,
                    std::vector<std::int32_t>& cells) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> value(-3.0f, 3.0f);
  const float special[] = {std::numeric_limits<float>::quiet_NaN(), -std::numeric_limits<float>::quiet_NaN(),
                           std::numeric_limits<float>::infinity(), -std::numeric_limits<float>::infinity(),
                           0.0f, -0.0f, 1e-40f, -1e-42f, 3.0e38f, 65520.0f, 1.0f + 0x1p-8f, 6.0e-8f};
  features.resize(static_cast<size_t>(c.pillars * c.channels));
  for (float& f : features) f = rng() % 6 == 0 ? special[rng() % std::size(special)] : value(rng);
  cells.resize(static_cast<size_t>(3 * c.pillars));
  for (std::int64_t r = 0; r < c.pillars; ++r) {
    std::int32_t* cell = cells.data() + 3 * r;
    const std::uint64_t kind = rng() % 10;
    if (kind == 0) {
      cell[0] = cell[1] = cell[2] = -1;
    } else if (kind == 1 && r > 0) {
      std::copy_n(cell - 3, 3, cell);  // the cell of the row before
    } else if (kind == 2) {
      cell[0] = static_cast<std::int32_t>(rng() % static_cast<std::uint64_t>(c.batch));
      cell[1] = static_cast<std::int32_t>(rng() % 2 == 0 ? c.height : -2);
      cell[2] = static_cast<std::int32_t>(rng() % static_cast<std::uint64_t>(c.width + 3)) - 1;
    } else {
      cell[0] = static_cast<std::int32_t>(rng() % static_cast<std::uint64_t>(c.batch));
      cell[1] = static_cast<std::int32_t>(rng() % static_cast<std::uint64_t>(c.height));
      cell[2] = static_cast<std::int32_t>(rng() % static_cast<std::uint64_t>(c.width));
    }
  }
}

TEST_P(HalfOpsAvx512, ScatterMatchesTheScalarLoopBitForBit) {
  const Precision p = GetParam();
  // Planes of one tile and of several (2257 and 4096 cells: 1024-cell tiles with tails), channel
  // counts below, at and past 16, more pillars than a 128-pillar chunk on a tile.
  const std::vector<ScatterCase> cases = {{0, 4, 2, 7, 6, 7, 2},     {1, 4, 2, 7, 6, 7, 2},
                                          {37, 16, 2, 19, 6, 7, 3},  {300, 17, 2, 20, 37, 61, 0},
                                          {500, 1, 1, 3, 1, 1000, 2}, {2000, 64, 1, 64, 64, 64, 0},
                                          {900, 33, 3, 40, 9, 113, 7}};
  std::uint64_t seed = 7;
  for (const ScatterCase& c : cases) {
    std::vector<float> features;
    std::vector<std::int32_t> cells;
    scatter_inputs(c, seed++, features, cells);
    const Ref fr{features.data(), {c.pillars, c.channels}};
    const IRef cr{cells.data(), {c.pillars, 3}};
    const Shape canvas{c.batch, c.canvas_channels, c.height, c.width};
    const auto label = name(p) + " " + std::to_string(c.pillars) + " pillars x " + std::to_string(c.channels) +
                       " into " + shape_str(canvas) + " at " + std::to_string(c.channel0);
    const Guarded scalar =
        expect_avx512_equals_scalar(canvas, kStale, {1, 2, 3}, label, [&](HRef& y, HalfOpsKernels k) {
          cpu::scatter_half(fr, cr, static_cast<int>(c.channel0), p, y, k);
        });
    // Every word of the band written (zero or a feature), the channels outside it untouched.
    const std::int64_t plane = c.height * c.width;
    for (std::int64_t i = 0; i < shape_numel(canvas); ++i) {
      const std::int64_t ch = i / plane % c.canvas_channels;
      const bool in_band = ch >= c.channel0 && ch < c.channel0 + c.channels;
      ASSERT_EQ(scalar.words[static_cast<size_t>(i)] == kStale, !in_band) << label << ", word " << i;
    }
  }
}

// Every FP32 bit pattern of a sweep (a stride of 4093 through all 2^32, with the specials of both
// formats' roundings) scattered one pillar a cell: each word is to_bits of its feature (the
// rounding of weights_io/half.hpp, denormals kept, NaN made quiet with its top bits).
TEST_P(HalfOpsAvx512, ScatterRoundsEveryValueAsToBits) {
  const Precision p = GetParam();
  const std::int64_t channels = 16, side = 256, pillars = side * side;
  std::vector<float> features(static_cast<size_t>(pillars * channels));
  std::uint64_t pattern = 0;
  for (float& f : features) {
    f = std::bit_cast<float>(static_cast<std::uint32_t>(pattern));
    pattern += 4093;
  }
  const float edges[] = {65504.0f, 65519.0f, 65520.0f, 6.0e-8f, 2.98e-8f, 0x1p-24f, 0x1p-25f, 0x1.8p-25f,
                         1.0f + 0x1p-8f, 1.0f + 3 * 0x1p-8f, 1.0f + 0x1p-11f, 1.0f + 3 * 0x1p-11f,
                         std::bit_cast<float>(0x7F7FFFFFu), std::bit_cast<float>(0x7F7F8000u),
                         std::bit_cast<float>(0x7F800001u), std::bit_cast<float>(0xFFBFFFFFu),
                         std::bit_cast<float>(0x00000001u), std::bit_cast<float>(0x807FFFFFu)};
  std::copy(std::begin(edges), std::end(edges), features.begin());
  std::vector<std::int32_t> cells(static_cast<size_t>(3 * pillars));
  for (std::int64_t r = 0; r < pillars; ++r) {
    cells[static_cast<size_t>(3 * r + 1)] = static_cast<std::int32_t>(r / side);
    cells[static_cast<size_t>(3 * r + 2)] = static_cast<std::int32_t>(r % side);
  }
  Guarded canvas(channels * pillars, kStale);
  HRef cr = canvas.ref({1, channels, side, side});
  cpu::scatter_half(Ref{features.data(), {pillars, channels}}, IRef{cells.data(), {pillars, 3}}, 0, p, cr,
                    HalfOpsKernels::Avx512);
  std::int64_t wrong = 0;
  for (std::int64_t r = 0; r < pillars; ++r)
    for (std::int64_t c = 0; c < channels; ++c) {
      const float f = features[static_cast<size_t>(r * channels + c)];
      const std::uint16_t got = canvas.words[static_cast<size_t>(c * pillars + r)];
      if (got != bits(f, p) && wrong++ < 5)
        ADD_FAILURE() << name(p) << ": " << std::hex << std::bit_cast<std::uint32_t>(f) << " gave " << got
                      << ", to_bits " << bits(f, p);
    }
  EXPECT_EQ(wrong, 0);
  EXPECT_TRUE(canvas.guards_intact());
}

INSTANTIATE_TEST_SUITE_P(Precisions, HalfOpsAvx512, ::testing::Values(Precision::BF16, Precision::F16),
                         [](const ::testing::TestParamInfo<Precision>& param) { return name(param.param); });

}  // namespace
