// Host memory for large buffers (a CPU backend's activations, prepared weights and workspaces).
#pragma once

#include <cstddef>

namespace pillarseg {

// 64-byte aligned memory of at least `bytes` (free with std::free), or null when the host has none.
// A buffer of 2 MiB or more is aligned to 2 MiB and, on Linux, asked for transparent huge pages
// (madvise MADV_HUGEPAGE; a no-op where the kernel's THP mode is "never"): the U-Net's kernels read
// rows of many channel planes at once (a 3x3 convolution's input transform: 4 rows of 4 planes a
// step, each plane 0.25-1 MB apart), which on 4 KiB pages misses the TLB on almost every row.
void* allocate_host(std::size_t bytes);

}  // namespace pillarseg
