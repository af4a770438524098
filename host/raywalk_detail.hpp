// The exact crossing arithmetic shared by the host ray walks (raywalk.cpp: single rays and 3D
// volumes; raywalk_sweep.cpp: 2D observability by slab sweeps). Internal to host/raywalk*.cpp:
// raywalk.hpp defines the walk these decide. A ray is two or three RayAxis in cell coordinates;
// CrossingCell gives, exactly, the cell along one axis where the ray crosses a cell boundary of
// another.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <span>
#include <vector>

#include "core/grid.hpp"
#include "core/point.hpp"

namespace pillarseg::host::raywalk_detail {

// floor(value) clamped to [-1, n]: -1 and n stand for every cell beyond the grid on that side
// (a float point may lie 1e38 m away, where no int64 index reaches).
inline int64_t clamped_floor(double value, int64_t n) {
  if (!(value >= -1.0)) return -1;
  if (value >= static_cast<double>(n)) return n;
  return static_cast<int64_t>(std::floor(value));
}

// One axis of a ray in cell coordinates, from `origin` (t = 0) to `end` (t = 1), on an axis of
// n cells.
struct RayAxis {
  double origin = 0.0, end = 0.0;
  double delta = 0.0;  // end - origin, rounded
  int step = 0;        // sign of end - origin (exact)
  int64_t first = 0;   // the cell the ray enters from the origin, clamped to [-1, n]
  int64_t last = 0;    // the end point's cell floor(end), clamped to [-1, n]

  int64_t lo() const { return std::min(first, last); }
  int64_t hi() const { return std::max(first, last); }
};

inline RayAxis make_axis(double origin, double end, int64_t n) {
  RayAxis axis;
  axis.origin = origin;
  axis.end = end;
  axis.delta = end - origin;
  axis.step = (end > origin) - (end < origin);
  axis.first = axis.step < 0 ? clamped_floor(std::ceil(origin) - 1.0, n) : clamped_floor(origin, n);
  axis.last = clamped_floor(end, n);
  return axis;
}

// sum + err == a + b exactly (Knuth's two-sum, any order of magnitudes).
inline void two_sum(double a, double b, double& sum, double& err) {
  sum = a + b;
  const double b_virtual = sum - a;
  const double a_virtual = sum - b_virtual;
  err = (a - a_virtual) + (b - b_virtual);
}

// The exact sign of sum_i x[i] * y[i]. Each product is split into its rounded value and its
// exact rounding error (fma); the terms are accumulated into a nonoverlapping expansion
// (Shewchuk's Grow-Expansion with zero elimination), whose sign is that of its largest
// component.
template <size_t N>
int exact_sign_of_dot(const std::array<double, N>& x, const std::array<double, N>& y) {
  std::array<double, 2 * N> expansion{};
  size_t size = 0;
  const auto grow = [&](double term) {
    size_t kept = 0;
    double running = term;
    for (size_t i = 0; i < size; ++i) {
      double sum = 0.0, err = 0.0;
      two_sum(running, expansion[i], sum, err);
      if (err != 0.0) expansion[kept++] = err;
      running = sum;
    }
    if (running != 0.0) expansion[kept++] = running;
    size = kept;
  };
  for (size_t i = 0; i < N; ++i) {
    const double product = x[i] * y[i];
    grow(std::fma(x[i], y[i], -product));
    grow(product);
  }
  if (size == 0) return 0;
  return expansion[size - 1] > 0.0 ? 1 : -1;
}

// The cell along axis m that the ray occupies where it crosses a cell boundary of axis a: the
// m-cell of the last cell before that a-step and of the first cell after it, clamped to
// [m.lo(), m.hi()]. Where the ray crosses an m-boundary at the same t, m_steps_first says which
// axis steps first (the walk steps x, then y, then z).
class CrossingCell {
 public:
  CrossingCell(const RayAxis& m, const RayAxis& a, bool m_steps_first, int64_t m_cells)
      : m_(m), a_(a), m_steps_first_(m_steps_first), lo_(m.lo()), hi_(m.hi()) {
    slope_ = slope(m, a);
    window_ = tie_window(m_cells, m.origin);
  }

  // The change along m per unit along a (0 for a ray that does not move along a).
  static double slope(const RayAxis& m, const RayAxis& a) {
    return a.delta != 0.0 ? m.delta / a.delta : 0.0;
  }

  // The double evaluation errs by less than 2^-48 (|value| + |m.origin|) (rounded deltas,
  // slope, differences and fma); it decides alone outside a window far wider than that.
  static double tie_window(int64_t m_cells, double m_origin) {
    return 0x1p-30 * (static_cast<double>(m_cells) + 2.0 + std::abs(m_origin));
  }

  // boundary: the a-coordinate of the crossed boundary (an integer).
  int64_t at(double boundary) const {
    if (m_.step == 0) return m_.first;
    const double value = std::fma(boundary - a_.origin, slope_, m_.origin);
    // Beyond the range the exact cell lies beyond it too, whatever the rounding.
    if (!(value > static_cast<double>(lo_))) return lo_;
    if (!(value < static_cast<double>(hi_ + 1))) return hi_;
    const double nearest = std::nearbyint(value);
    const int64_t cell = std::abs(value - nearest) > window_
                             ? static_cast<int64_t>(std::floor(value))
                             : exact_cell(boundary, nearest);
    return std::clamp(cell, lo_, hi_);
  }

  // out[i] = at(first_boundary + i * boundary_step) for i < count, as doubles: one pass in
  // double that the compiler vectorises (floor by adding and subtracting 1.5 * 2^52, which
  // rounds to the nearest integer, as GCC does not vectorise std::floor), and the exact pass only
  // where some value lies near a tie.
  void fill(double first_boundary, double boundary_step, int64_t count, double* out) const {
    const double lo = static_cast<double>(lo_), hi = static_cast<double>(hi_);
    if (m_.step == 0) {
      std::fill(out, out + count, static_cast<double>(m_.first));
      return;
    }
    constexpr double kRoundToInteger = 0x1.8p52;
    const double offset = first_boundary - a_.origin;
    int64_t near_ties = 0;
    for (int64_t i = 0; i < count; ++i) {
      const double along = offset + static_cast<double>(i) * boundary_step;
      // Clamped into [lo - 1/2, hi + 3/2], a value floors to the same cell, once clamped, as in
      // at(), and stays far below 2^51, where the rounding trick holds.
      const double value =
          std::min(std::max(std::fma(along, slope_, m_.origin), lo - 0.5), hi + 1.5);
      const double nearest = (value + kRoundToInteger) - kRoundToInteger;
      const double distance = value - nearest;
      near_ties += std::abs(distance) <= window_;
      out[i] = std::min(std::max(distance < 0.0 ? nearest - 1.0 : nearest, lo), hi);
    }
    if (near_ties == 0) return;
    for (int64_t i = 0; i < count; ++i)
      out[i] = static_cast<double>(at(first_boundary + static_cast<double>(i) * boundary_step));
  }

 private:
  // The cell beside the integer k, from the exact sign of (m(t) - k) * (a.end - a.origin) =
  // (m.origin - k) (a.end - a.origin) + (boundary - a.origin) (m.end - m.origin), expanded into
  // products of the inputs.
  int64_t exact_cell(double boundary, double k) const {
    const int side =
        a_.step * exact_sign_of_dot<6>({m_.origin, -k, k, boundary, -boundary, -a_.origin},
                                       {a_.end, a_.end, a_.origin, m_.end, m_.origin, m_.end});
    const auto cell = static_cast<int64_t>(k);
    if (side > 0) return cell;
    if (side < 0) return cell - 1;
    // Tie: m crosses k at the same t; the cell after m's step if m steps first, else before.
    return m_steps_first_ == (m_.step > 0) ? cell : cell - 1;
  }

  RayAxis m_, a_;
  bool m_steps_first_;
  int64_t lo_, hi_;
  double slope_ = 0.0, window_ = 0.0;
};

// The 2D observability counts of raywalk.hpp (raywalk_sweep.cpp). origin_u, origin_v: the sensor
// origin in cell coordinates; transmissions, detections: (H, W) of the grid, zero on entry; the
// grid and origin are checked by the caller; non-finite points are skipped. `buffers`: the
// sweeps and per-thread scratch (ObservabilityWorkspace), grown as needed.
struct SweepBuffers;
void count_observability_2d(std::span<const Point> points, double origin_u, double origin_v,
                            const GridSpec& grid, SweepBuffers& buffers, uint32_t* transmissions,
                            uint32_t* detections);

}  // namespace pillarseg::host::raywalk_detail
