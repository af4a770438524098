#include "core/parallel.hpp"

#include <omp.h>

#include <atomic>
#include <thread>

namespace pillarseg {

namespace {
std::atomic<int> g_threads{0};     // 0: not set yet, use the hardware count
thread_local int t_threads = 0;    // a ScopedThreads' count on this thread, 0: none

int process_threads() {
  const int n = g_threads.load(std::memory_order_relaxed);
  if (n <= 0) {
    const unsigned hw = std::thread::hardware_concurrency();
    return hw == 0 ? 1 : static_cast<int>(hw);
  }
  return n;
}
}  // namespace

int num_threads() { return t_threads > 0 ? t_threads : process_threads(); }

void set_num_threads(int n) {
  g_threads.store(n, std::memory_order_relaxed);
  omp_set_num_threads(process_threads());
}

ScopedThreads::ScopedThreads(int n) : previous_(t_threads) {
  if (n > 0) t_threads = n;
}

ScopedThreads::~ScopedThreads() { t_threads = previous_; }

}  // namespace pillarseg
