// Learning-rate and momentum (Adam beta1) schedules, per optimiser step s (0-based):
//   constant: lr = lr_max, beta1 = constant_beta1;
//   one-cycle: OpenPCDet's adam_onecycle (fastai OneCycle). With s1 = floor(total_steps *
//     pct_start), the step where the peak is reached:
//       s < s1:  f = s / s1,                     lr = cos_anneal(lr_max / div, lr_max, f),
//                                                beta1 = cos_anneal(mom_max, mom_min, f)
//       s >= s1: f = (s - s1) / (total - s1),    lr = cos_anneal(lr_max, lr_max / div / 1e4, f),
//                                                beta1 = cos_anneal(mom_min, mom_max, f)
//     with cos_anneal(start, end, f) = end + (start - end) / 2 * (cos(pi f) + 1). The floor
//     is OpenPCDet's int(total_step * pct_start); when total * pct_start is an integer,
//     s < s1 is the same as s / total < pct_start. OpenPCDet pairs the schedule with Adam
//     betas (0.9, 0.99), beta1 being replaced by the schedule's momentum.
#pragma once

#include <cstdint>

namespace pillarseg::host {

enum class LrScheduleKind { kConstant, kOneCycle };

struct LrScheduleOptions {
  LrScheduleKind kind = LrScheduleKind::kOneCycle;
  double lr_max = 1e-3;         // the peak lr (one-cycle) or the lr (constant)
  int64_t total_steps = 1;      // one-cycle: optimiser steps of the whole run
  double div_factor = 10;       // one-cycle: starting lr = lr_max / div_factor
  double pct_start = 0.4;       // one-cycle: fraction of the steps spent warming up
  double momentum_max = 0.95;   // one-cycle: beta1 at the start and the end
  double momentum_min = 0.85;   // one-cycle: beta1 at the peak lr
  double constant_beta1 = 0.9;  // constant: beta1
};

struct LrAndMomentum {
  double lr = 0;
  double beta1 = 0;
};

// Cosine interpolation from start (fraction 0) to end (fraction 1).
double cos_anneal(double start, double end, double fraction);

// The lr and beta1 to use for optimiser step `step` (0-based; 0..total_steps for one-cycle).
LrAndMomentum lr_schedule_at(const LrScheduleOptions& options, int64_t step);

}  // namespace pillarseg::host
