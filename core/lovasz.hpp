// The ranking of the Lovász-softmax loss (host/losses.hpp, kernels/losses.cu): the errors in
// [0, 1] fall into kLovaszBins equal bins, ranked from the largest bin down, and the Jaccard loss
// after the cells of the bins ranked so far (fg of the class's cells, bg of the others') is the
// one formula both weigh by, so that the host and the device bin and weigh alike.
#pragma once

#include <cstdint>

#include "core/host_device.hpp"

namespace pillarseg {

inline constexpr int kLovaszBins = 4096;

template <class T>
PILLARSEG_HOST_DEVICE inline int lovasz_bin(T error) {
  const int bin = static_cast<int>(error * static_cast<T>(kLovaszBins));
  return bin < kLovaszBins - 1 ? bin : kLovaszBins - 1;
}

// 1 - |class \ ranked| / |class u ranked| for a class of total_fg cells (> 0): 0 before any.
PILLARSEG_HOST_DEVICE inline double lovasz_jaccard(std::int64_t total_fg, std::int64_t fg,
                                                   std::int64_t bg) {
  return 1.0 - static_cast<double>(total_fg - fg) / static_cast<double>(total_fg + bg);
}

}  // namespace pillarseg
