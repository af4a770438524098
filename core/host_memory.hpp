// Host memory for large buffers (the CPU backend's allocations: activations, prepared weights).
#pragma once

#include <cstddef>

namespace pillarseg {

// 64-byte aligned memory of at least `bytes` (free with std::free), or null when the host has none.
// A buffer of 2 MiB or more is aligned to 2 MiB and, on Linux, asked for transparent huge pages
// (madvise MADV_HUGEPAGE; advice only: a no-op where the kernel's THP mode is "never"). The
// U-Net's kernels read rows of many channel planes at once (a 3x3 convolution's input transform:
// 4 rows of 4 planes a step, 0.25-1 MB apart), and on 2 MiB pages they miss the TLB less: 1-4%
// faster per layer (docs/benchmarks.md, "INT8 against OpenVINO after the AVX-512 data movement,
// and huge pages").
void* allocate_host(std::size_t bytes);

}  // namespace pillarseg
