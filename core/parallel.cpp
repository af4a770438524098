#include "core/parallel.hpp"

#include <omp.h>

#include <thread>

namespace pillarseg {

namespace {
int g_threads = 0;  // 0: not set yet, use the hardware count
}

int num_threads() {
  if (g_threads <= 0) {
    const unsigned hw = std::thread::hardware_concurrency();
    return hw == 0 ? 1 : static_cast<int>(hw);
  }
  return g_threads;
}

void set_num_threads(int n) {
  g_threads = n;
  omp_set_num_threads(num_threads());
}

}  // namespace pillarseg
