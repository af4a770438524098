// Point padding: a scan of M points in a buffer sized for more. Rows [M, capacity) of points
// (capacity, 4) become NaN, so they belong to no pillar (GridSpec::contains is false for them) and
// cast no ray (the walks skip non-finite points): every op then gives what it gives for the M
// points alone. This is how one CUDA graph, recorded for a point capacity, serves every scan up to
// it.
#pragma once

#include <cstdint>

#include "core/tensor.hpp"

namespace pillarseg::host {

// points (capacity, 4): rows [num_points, capacity) = quiet NaN; 0 <= num_points <= capacity.
void pad_points(int64_t num_points, Tensor<float>& points);

}  // namespace pillarseg::host
