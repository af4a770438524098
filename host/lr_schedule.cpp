// Constant and one-cycle (OpenPCDet adam_onecycle) lr / beta1 schedules.
#include "host/lr_schedule.hpp"

#include <cmath>
#include <numbers>

#include "core/error.hpp"

namespace pillarseg::host {

double cos_anneal(double start, double end, double fraction) {
  return end + (start - end) / 2 * (std::cos(std::numbers::pi * fraction) + 1);
}

LrAndMomentum lr_schedule_at(const LrScheduleOptions& options, int64_t step) {
  const char* op = "lr_schedule_at";
  PS_CHECK(options.lr_max >= 0, "{}: expected lr_max >= 0, given {}", op, options.lr_max);
  PS_CHECK(step >= 0, "{}: expected step >= 0, given {}", op, step);
  if (options.kind == LrScheduleKind::kConstant) return {options.lr_max, options.constant_beta1};

  PS_CHECK(options.total_steps >= 1, "{}: expected total_steps >= 1, given {}", op,
           options.total_steps);
  PS_CHECK(step <= options.total_steps, "{}: step {} is past the end of the {}-step cycle", op,
           step, options.total_steps);
  PS_CHECK(options.pct_start > 0 && options.pct_start < 1,
           "{}: expected pct_start in (0, 1), given {}", op, options.pct_start);
  PS_CHECK(options.div_factor > 0, "{}: expected div_factor > 0, given {}", op, options.div_factor);

  const double lr_low = options.lr_max / options.div_factor;
  const auto peak_step = static_cast<int64_t>(
      std::floor(static_cast<double>(options.total_steps) * options.pct_start));
  if (step < peak_step) {
    const double f = static_cast<double>(step) / static_cast<double>(peak_step);
    return {cos_anneal(lr_low, options.lr_max, f),
            cos_anneal(options.momentum_max, options.momentum_min, f)};
  }
  const double f =
      static_cast<double>(step - peak_step) / static_cast<double>(options.total_steps - peak_step);
  return {cos_anneal(options.lr_max, lr_low / 1e4, f),
          cos_anneal(options.momentum_min, options.momentum_max, f)};
}

}  // namespace pillarseg::host
