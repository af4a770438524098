// Confusion-matrix accumulation over the 12 classes (host/confusion.hpp is the spec):
//   truth, predicted (n) uint8 class ids, mask (n) uint8 or nullptr -> confusion (12, 12) int64,
//   rows the true class, columns the predicted class (id c at index c - 1), added to what it
//   holds. A cell counts when truth != 0 (0 is unlabeled) and, with a mask, mask != 0.
// Where the host throws (a counted cell with a true id above 12 or a predicted id outside
// 1..12), a kernel cannot: such a cell is left out of the matrix and added to *invalid_cells
// (one uint64, accumulated like the matrix), which the caller reads after the stream and refuses
// when it is not 0. Integer counts: the result does not depend on the order of the atomics.
// Pointers are device memory; the work is queued on `stream`.
#pragma once

#include <cstdint>

#include "kernels/emu/cuda_compat.cuh"

namespace pillarseg::cuda::inline PILLARSEG_CUDA_NAMESPACE {

// truth, predicted, mask (n; mask may be nullptr) -> confusion (12, 12) += counts,
// *invalid_cells += the counted cells with ids outside the classes.
void confusion_accumulate(const std::uint8_t* truth, const std::uint8_t* predicted,
                          const std::uint8_t* mask, std::int64_t n, std::int64_t* confusion,
                          std::uint64_t* invalid_cells, cudaStream_t stream);

}  // namespace pillarseg::cuda
