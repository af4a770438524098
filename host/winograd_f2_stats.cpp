#include "host/winograd_f2_stats.hpp"

#include <algorithm>
#include <cmath>
#include <vector>

#include "core/error.hpp"
#include "core/parallel.hpp"

namespace pillarseg::host {

namespace {

constexpr int kBins = 4096;

// Calls visit(p, v) for every tile of the planes [begin, end) of x and each of its 16 positions.
template <class Visit>
void for_each_v(const float* x, const Shape& shape, int64_t begin, int64_t end, Visit&& visit) {
  const int64_t h = shape[2], w = shape[3];
  const int64_t th = (h + 1) / 2, tw = (w + 1) / 2;
  for (int64_t plane = begin; plane < end; ++plane) {
    const float* xp = x + plane * h * w;
    const auto at = [&](int64_t iy, int64_t ix) -> float {
      return iy < 0 || iy >= h || ix < 0 || ix >= w ? 0.0f : xp[iy * w + ix];
    };
    for (int64_t ty = 0; ty < th; ++ty) {
      for (int64_t tx = 0; tx < tw; ++tx) {
        float hr[4][4];
        for (int r = 0; r < 4; ++r) {
          float d[4];
          for (int j = 0; j < 4; ++j) d[j] = at(2 * ty - 1 + r, 2 * tx - 1 + j);
          hr[r][0] = d[0] - d[2], hr[r][1] = d[1] + d[2], hr[r][2] = d[2] - d[1], hr[r][3] = d[1] - d[3];
        }
        for (int j = 0; j < 4; ++j) {
          const float v[4] = {hr[0][j] - hr[2][j], hr[1][j] + hr[2][j], hr[2][j] - hr[1][j], hr[1][j] - hr[3][j]};
          for (int i = 0; i < 4; ++i) visit(4 * i + j, v[i]);
        }
      }
    }
  }
}

void check_shape(const char* op, const float* x, const Shape& shape) {
  PS_CHECK(shape.size() == 4, "{}: x must be (B, C, H, W), got {}", op, shape_str(shape));
  PS_CHECK(x != nullptr || shape_numel(shape) == 0, "{}: x has no memory", op);
}

}  // namespace

std::array<float, 16> winograd_f2_input_absmax(const float* x, const Shape& shape) {
  check_shape("winograd_f2_input_absmax", x, shape);
  const int threads = std::max(num_threads(), 1);
  std::vector<std::array<float, 16>> partial(static_cast<size_t>(threads), std::array<float, 16>{});
  parallel_chunks(shape[0] * shape[1], [&](int64_t begin, int64_t end, int thread) {
    std::array<float, 16>& mx = partial[static_cast<size_t>(thread)];
    for_each_v(x, shape, begin, end, [&](int p, float v) {
      const float a = std::abs(v);
      if (a > mx[static_cast<size_t>(p)]) mx[static_cast<size_t>(p)] = a;  // NaN is never larger
    });
  });
  std::array<float, 16> out{};
  for (const auto& mx : partial)
    for (size_t p = 0; p < 16; ++p) out[p] = std::max(out[p], mx[p]);
  return out;
}

std::array<float, 16> winograd_f2_input_percentiles(const float* x, const Shape& shape, double percentile) {
  const char* op = "winograd_f2_input_percentiles";
  PS_CHECK(percentile > 0 && percentile <= 100, "{}: the percentile must be in (0, 100], got {}", op, percentile);
  const std::array<float, 16> max_abs = winograd_f2_input_absmax(x, shape);
  const int threads = std::max(num_threads(), 1);
  // Counts per thread, position and bin; bin k holds |v| in [k, k + 1) max / kBins (the last
  // bin also max itself).
  std::vector<int64_t> counts(static_cast<size_t>(threads) * 16 * kBins, 0);
  std::array<float, 16> to_bin{};
  for (size_t p = 0; p < 16; ++p) to_bin[p] = max_abs[p] > 0.0f ? kBins / max_abs[p] : 0.0f;
  parallel_chunks(shape[0] * shape[1], [&](int64_t begin, int64_t end, int thread) {
    int64_t* c = counts.data() + static_cast<size_t>(thread) * 16 * kBins;
    for_each_v(x, shape, begin, end, [&](int p, float v) {
      if (std::isnan(v)) return;
      const int bin = std::min(static_cast<int>(std::abs(v) * to_bin[static_cast<size_t>(p)]), kBins - 1);
      ++c[p * kBins + bin];
    });
  });
  std::array<float, 16> out{};
  for (int p = 0; p < 16; ++p) {
    std::vector<int64_t> bins(kBins, 0);
    int64_t n = 0;
    for (int t = 0; t < threads; ++t) {
      for (int k = 0; k < kBins; ++k) {
        const int64_t count = counts[(static_cast<size_t>(t) * 16 + static_cast<size_t>(p)) * kBins + k];
        bins[static_cast<size_t>(k)] += count;
        n += count;
      }
    }
    if (n == 0 || max_abs[static_cast<size_t>(p)] == 0.0f) continue;
    // Nearest rank: the smallest value with at least percentile% of the values at or below it.
    const auto rank = static_cast<int64_t>(std::max(1.0, std::ceil(percentile / 100.0 * static_cast<double>(n))));
    if (rank >= n) {
      out[static_cast<size_t>(p)] = max_abs[static_cast<size_t>(p)];
      continue;
    }
    int64_t seen = 0;
    for (int k = 0; k < kBins; ++k) {
      seen += bins[static_cast<size_t>(k)];
      if (seen >= rank) {
        const float max_p = max_abs[static_cast<size_t>(p)];
        out[static_cast<size_t>(p)] = std::min(max_p, max_p * static_cast<float>(k + 1) / kBins);
        break;
      }
    }
  }
  return out;
}

}  // namespace pillarseg::host
