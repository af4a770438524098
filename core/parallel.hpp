// Thread control and a static-schedule parallel loop (OpenMP). Static chunks keep the work
// each thread does, and so any per-thread partial result, the same from run to run for a
// given thread count.
#pragma once

#include <cstdint>

namespace pillarseg {

// The threads of the calling thread's parallel loops: its ScopedThreads setting if one is alive,
// else the process's (set_num_threads; by default all hardware threads).
int num_threads();
void set_num_threads(int n);  // n <= 0: all hardware threads

// While alive, num_threads() on the calling thread returns n (n <= 0: the process's setting), so
// that work done on behalf of one caller (a segmenter of the library) uses its own count without
// changing other threads'. Nests; restores the previous setting when destroyed.
class ScopedThreads {
 public:
  explicit ScopedThreads(int n);
  ~ScopedThreads();
  ScopedThreads(const ScopedThreads&) = delete;
  ScopedThreads& operator=(const ScopedThreads&) = delete;

 private:
  int previous_;
};

// Calls fn(begin, end, t) on contiguous chunks of [0, n), one chunk per thread t, in
// parallel. Chunk t is [n * t / T, n * (t + 1) / T) for T = num_threads(), so fn may fill
// per-thread buffers indexed by t and merge them afterwards in order t = 0..T-1.
template <class Fn>
void parallel_chunks(int64_t n, Fn&& fn) {
  const int threads = num_threads();
  if (threads <= 1 || n < 2) {
    fn(int64_t{0}, n, 0);
    return;
  }
#pragma omp parallel for schedule(static, 1) num_threads(threads)
  for (int t = 0; t < threads; ++t) {
    const int64_t begin = n * t / threads;
    const int64_t end = n * (t + 1) / threads;
    if (begin < end) fn(begin, end, t);
  }
}

// Calls fn(i) for i in [0, n) in parallel, static schedule.
template <class Fn>
void parallel_for(int64_t n, Fn&& fn) {
  parallel_chunks(n, [&](int64_t begin, int64_t end, int) {
    for (int64_t i = begin; i < end; ++i) fn(i);
  });
}

}  // namespace pillarseg
