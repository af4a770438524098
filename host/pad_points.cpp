#include "host/pad_points.hpp"

#include <algorithm>
#include <limits>

#include "core/error.hpp"

namespace pillarseg::host {

void pad_points(int64_t num_points, Tensor<float>& points) {
  PS_CHECK(points.rank() == 2 && points.dim(1) == 4,
           "pad_points: expected points (capacity, 4) rows x y z r, given {}",
           shape_str(points.shape()));
  PS_CHECK(num_points >= 0 && num_points <= points.dim(0),
           "pad_points: the scan's {} points do not fit the buffer of {} rows", num_points,
           points.dim(0));
  std::fill(points.data() + 4 * num_points, points.data() + points.numel(),
            std::numeric_limits<float>::quiet_NaN());
}

}  // namespace pillarseg::host
