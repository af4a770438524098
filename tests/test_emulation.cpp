// The CUDA emulation (kernels/emu/): barrier and warp semantics, block reductions for block sizes
// that are and are not multiples of the warp, atomics from many blocks, dynamic shared memory,
// grid-stride loops and index variables, streams, events and graph capture, DeviceBuffer, the
// checking macro's messages, and the detection of misuse a GPU would hang on or leave undefined.
#include <gtest/gtest.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <functional>
#include <numeric>
#include <string>
#include <type_traits>
#include <vector>

#include "core/error.hpp"
#include "kernels/common.cuh"
#include "kernels/device_buffer.hpp"

using namespace pillarseg;
using cuda::DeviceBuffer;
using cuda::launch_kernel;

namespace {

constexpr unsigned kFullMask = 0xffffffffu;

// The message of the pillarseg::Error `fn` throws, or "" if it throws nothing.
std::string error_message(const std::function<void()>& fn) {
  try {
    fn();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

bool contains(const std::string& text, const std::string& part) {
  return text.find(part) != std::string::npos;
}

// Distinct values per block and thread, so that a read of another block's data shows.
std::vector<int> distinct_values(int n) {
  std::vector<int> values(static_cast<size_t>(n));
  for (int i = 0; i < n; ++i) values[static_cast<size_t>(i)] = 1000 + 7 * i;
  return values;
}

}  // namespace

// ---- kernels used by the tests ----

// in, out (gridDim.x * blockDim.x): out[t] = in[(t + 1) % blockDim.x] within each block. Correct
// only if every thread has written the tile before any reads it.
static __global__ void rotate_in_block_kernel(const int* in, int* out) {
  __shared__ int tile[1024];
  const int n = static_cast<int>(blockDim.x);
  const int t = static_cast<int>(threadIdx.x);
  const int base = static_cast<int>(blockIdx.x) * n;
  tile[t] = in[base + t];
  __syncthreads();
  out[base + t] = tile[(t + 1) % n];
}

// in, out (gridDim.x * blockDim.x): inclusive prefix sums within each block (Hillis-Steele, one
// barrier per step of a loop).
static __global__ void inclusive_scan_kernel(const int* in, int* out) {
  __shared__ int buffers[2][1024];
  const int n = static_cast<int>(blockDim.x);
  const int t = static_cast<int>(threadIdx.x);
  const int base = static_cast<int>(blockIdx.x) * n;
  int current = 0;
  buffers[current][t] = in[base + t];
  __syncthreads();
  for (int offset = 1; offset < n; offset *= 2) {
    const int value = buffers[current][t] + (t >= offset ? buffers[current][t - offset] : 0);
    buffers[1 - current][t] = value;
    current = 1 - current;
    __syncthreads();
  }
  out[base + t] = buffers[current][t];
}

// values (gridDim.x * blockDim.x) -> sums (gridDim.x): the sum of each block's values, for any
// block size. The last warp may be partial: its mask names only its lanes, and values that
// __shfl_down_sync brings from past the last lane are not added.
static __global__ void block_sum_kernel(const long long* values, long long* sums) {
  __shared__ long long warp_totals[32];
  const int n = static_cast<int>(blockDim.x);
  const int t = static_cast<int>(threadIdx.x);
  const int lane = t % 32;
  const int warp = t / 32;
  const int lanes = min(32, n - warp * 32);
  const unsigned mask = lanes == 32 ? kFullMask : (1u << lanes) - 1u;
  long long v = values[static_cast<int>(blockIdx.x) * n + t];
  for (int offset = 16; offset > 0; offset /= 2) {
    const long long other = __shfl_down_sync(mask, v, static_cast<unsigned>(offset));
    if (lane + offset < lanes) v += other;
  }
  if (lane == 0) warp_totals[warp] = v;
  __syncthreads();
  if (t == 0) {
    long long total = 0;
    for (int w = 0; w < (n + 31) / 32; ++w) total += warp_totals[w];
    sums[blockIdx.x] = total;
  }
}

struct WarpResults {
  int index[32], index_width8[32], up1[32], down4_width16[32], xor1[32], xor16[32];
  unsigned ballot_every_third[32], ballot_low_half[32];
  int any_none[32], any_one[32], all_but_one[32], all_true[32];
  double xor3_double[32];
  int broadcast_per_warp[64];
};

// One block of 64 threads (two warps); lane values v = lane * 10 + 1.
static __global__ void warp_semantics_kernel(WarpResults* r) {
  const int t = static_cast<int>(threadIdx.x);
  const int lane = t % 32;
  const int v = lane * 10 + 1;
  r->broadcast_per_warp[t] = __shfl_sync(kFullMask, t, 0);
  if (t >= 32) return;
  r->index[lane] = __shfl_sync(kFullMask, v, (lane + 3) % 32);
  r->index_width8[lane] = __shfl_sync(kFullMask, v, 2, 8);
  r->up1[lane] = __shfl_up_sync(kFullMask, v, 1);
  r->down4_width16[lane] = __shfl_down_sync(kFullMask, v, 4, 16);
  r->xor1[lane] = __shfl_xor_sync(kFullMask, v, 1);
  r->xor16[lane] = __shfl_xor_sync(kFullMask, v, 16);
  r->ballot_every_third[lane] = __ballot_sync(kFullMask, lane % 3 == 0);
  r->ballot_low_half[lane] = lane < 16 ? __ballot_sync(0x0000ffffu, lane % 2 == 1) : 0u;
  r->any_none[lane] = __any_sync(kFullMask, 0);
  r->any_one[lane] = __any_sync(kFullMask, lane == 17);
  r->all_but_one[lane] = __all_sync(kFullMask, lane != 5);
  r->all_true[lane] = __all_sync(kFullMask, 1);
  r->xor3_double[lane] = __shfl_xor_sync(kFullMask, lane + 0.5, 3);
  __syncwarp();
}

struct AtomicCounters {
  int count = 0;
  int cas_count = 0;
  int max = -1;
  int min = 1 << 30;
  unsigned int ring = 0;
  unsigned int bits = 0;
  unsigned long long sum = 0;
  float float_count = 0.0f;
  unsigned int histogram[16] = {};
};

// values (n) -> counters, from every thread of every block at once.
static __global__ void atomics_kernel(const int* values, int n, AtomicCounters* c) {
  const int stride = static_cast<int>(gridDim.x * blockDim.x);
  for (int i = static_cast<int>(blockIdx.x * blockDim.x + threadIdx.x); i < n; i += stride) {
    const int value = values[i];
    atomicAdd(&c->count, 1);
    atomicAdd(&c->sum, static_cast<unsigned long long>(value));
    atomicMax(&c->max, value);
    atomicMin(&c->min, value);
    atomicAdd(&c->histogram[value % 16], 1u);
    atomicAdd(&c->float_count, 1.0f);
    atomicInc(&c->ring, 9u);
    atomicOr(&c->bits, 1u << (value % 32));
    int assumed = 0;
    int seen = 0;
    while ((seen = atomicCAS(&c->cas_count, assumed, assumed + 1)) != assumed) assumed = seen;
  }
}

// in, out (gridDim.x * blockDim.x): reverses each block's values through dynamic shared memory,
// which holds two arrays of blockDim.x floats (the launch gives 2 * blockDim.x floats).
static __global__ void reverse_in_block_kernel(const float* in, float* out) {
  float* staged = cuda::dynamic_shared<float>();
  float* doubled = staged + blockDim.x;
  const int n = static_cast<int>(blockDim.x);
  const int t = static_cast<int>(threadIdx.x);
  const int base = static_cast<int>(blockIdx.x) * n;
  staged[t] = in[base + t];
  doubled[t] = 2.0f * in[base + t];
  __syncthreads();
  out[base + t] = staged[n - 1 - t] + doubled[n - 1 - t];
}

// visits (n): each element incremented once by a grid-stride loop (a template, launched as
// grid_stride_kernel<int>).
template <class T>
static __global__ void grid_stride_kernel(T* visits, int n) {
  const int stride = static_cast<int>(gridDim.x * blockDim.x);
  for (int i = static_cast<int>(blockIdx.x * blockDim.x + threadIdx.x); i < n; i += stride)
    visits[i] += 1;
}

struct IndexRecord {
  int block[3], thread[3], block_dim[3], grid_dim[3];
};

// records (all threads of a 3D grid of 3D blocks): each thread writes its indices at its
// global linear index.
static __global__ void index_kernel(IndexRecord* records) {
  const unsigned block = blockIdx.x + gridDim.x * (blockIdx.y + gridDim.y * blockIdx.z);
  const unsigned thread = threadIdx.x + blockDim.x * (threadIdx.y + blockDim.y * threadIdx.z);
  IndexRecord& r = records[block * blockDim.x * blockDim.y * blockDim.z + thread];
  r = IndexRecord{
      {static_cast<int>(blockIdx.x), static_cast<int>(blockIdx.y), static_cast<int>(blockIdx.z)},
      {static_cast<int>(threadIdx.x), static_cast<int>(threadIdx.y), static_cast<int>(threadIdx.z)},
      {static_cast<int>(blockDim.x), static_cast<int>(blockDim.y), static_cast<int>(blockDim.z)},
      {static_cast<int>(gridDim.x), static_cast<int>(gridDim.y), static_cast<int>(gridDim.z)}};
}

// x, y (n): y = a * x + b.
static __global__ void scale_add_kernel(const float* x, float a, float b, float* y, int n) {
  const int stride = static_cast<int>(gridDim.x * blockDim.x);
  for (int i = static_cast<int>(blockIdx.x * blockDim.x + threadIdx.x); i < n; i += stride)
    y[i] = a * x[i] + b;
}

// Threads from 48 on return before the barrier the others wait at.
static __global__ void early_return_before_barrier_kernel(int* out) {
  if (threadIdx.x >= 48) return;
  __syncthreads();
  out[threadIdx.x] = 1;
}

// Only odd threads reach the barrier.
static __global__ void odd_threads_barrier_kernel(int* out) {
  if (threadIdx.x % 2 == 1) __syncthreads();
  out[threadIdx.x] = 1;
}

// Lanes from 16 on return, the others shuffle with a mask naming all 32 lanes.
static __global__ void shuffle_with_returned_lanes_kernel(int* out) {
  if (threadIdx.x >= 16) return;
  out[threadIdx.x] = __shfl_down_sync(kFullMask, static_cast<int>(threadIdx.x), 1);
}

// Each lane shuffles with a mask naming lane 0 only.
static __global__ void mask_without_own_lane_kernel(int* out) {
  out[threadIdx.x] = __shfl_sync(0x1u, static_cast<int>(threadIdx.x), 0);
}

// Even lanes shuffle, odd lanes vote, with the same mask.
static __global__ void mixed_warp_operations_kernel(int* out) {
  if (threadIdx.x % 2 == 0) {
    out[threadIdx.x] = __shfl_sync(kFullMask, 1, 0);
  } else {
    out[threadIdx.x] = static_cast<int>(__ballot_sync(kFullMask, 1));
  }
}

// A full-warp mask in a block of 33 threads, whose second warp has one lane.
static __global__ void full_mask_in_partial_warp_kernel(int* out) {
  out[threadIdx.x] = __shfl_sync(kFullMask, static_cast<int>(threadIdx.x), 0);
}

// A shuffle width that is not a power of two.
static __global__ void bad_width_kernel(int* out) {
  out[threadIdx.x] = __shfl_sync(kFullMask, static_cast<int>(threadIdx.x), 0, 3);
}

// in, out (gridDim.x * blockDim.x): out[t] = tile[(t + 1) % n] with NO barrier between the
// writes and the reads: a race, whose result depends on the order the threads run in.
static __global__ void racy_rotate_kernel(const int* in, int* out) {
  __shared__ int tile[1024];
  const int n = static_cast<int>(blockDim.x);
  const int t = static_cast<int>(threadIdx.x);
  const int base = static_cast<int>(blockIdx.x) * n;
  tile[t] = in[base + t];
  out[base + t] = tile[(t + 1) % n];
}

// A warp-synchronous exchange through shared memory: each lane writes its slot and reads its
// neighbour's; with `sync` a __syncwarp() separates the two (correct), without it they race.
static __global__ void warp_exchange_kernel(const int* in, int* out, bool sync) {
  __shared__ int slots[32];
  const int lane = static_cast<int>(threadIdx.x);
  slots[lane] = in[lane];
  if (sync) __syncwarp();
  out[lane] = slots[lane ^ 1];
}

// out[0] = the index of the block that ran last (every block writes it): the blocks' order.
static __global__ void last_block_kernel(int* out) {
  if (threadIdx.x == 0) out[0] = static_cast<int>(blockIdx.x);
}

// out (gridDim.x * blockDim.x * 2): what each thread reads from a static and a dynamic shared
// slot before anything writes them; then every thread writes both (so that a block that
// inherited them from the block before would read those values instead of the poison).
static __global__ void read_before_write_kernel(std::uint32_t* out) {
  __shared__ std::uint32_t slots[256];
  std::uint32_t* dynamic_slots = cuda::dynamic_shared<std::uint32_t>();
  const unsigned t = threadIdx.x;
  const unsigned i = (blockIdx.x * blockDim.x + t) * 2;
  out[i] = slots[t];
  out[i + 1] = dynamic_slots[t];
  __syncthreads();
  slots[t] = 7;
  dynamic_slots[t] = 9;
}

// Runs `launch` under `schedule` and returns what it left in `out`, restoring the schedule.
template <class T>
std::vector<T> run_under(const emu::Schedule& schedule, DeviceBuffer<T>& out,
                         const std::function<void()>& launch) {
  const emu::Schedule previous = emu::current_schedule();
  emu::set_schedule(schedule);
  PS_CUDA_CHECK(cudaMemset(out.data(), 0, out.size() * sizeof(T)));
  try {
    launch();
  } catch (...) {
    emu::set_schedule(previous);
    throw;
  }
  emu::set_schedule(previous);
  return out.to_host();
}

const emu::Schedule kForward{};
const emu::Schedule kReverse{emu::Schedule::Order::Reverse, 0};
emu::Schedule random_schedule(std::uint64_t seed) {
  return emu::Schedule{emu::Schedule::Order::Random, seed};
}

// ---- tests ----

TEST(EmulationBarrier, EveryThreadWritesBeforeAnyReads) {
  for (const int block : {1, 7, 256, 1024}) {
    const int blocks = 24;
    const std::vector<int> in = distinct_values(block * blocks);
    auto device_in = DeviceBuffer<int>::from_host(in);
    DeviceBuffer<int> device_out(in.size());
    launch_kernel(rotate_in_block_kernel, dim3(blocks), dim3(block), 0, nullptr, device_in.data(),
                  device_out.data());
    const std::vector<int> out = device_out.to_host();
    for (int b = 0; b < blocks; ++b) {
      for (int t = 0; t < block; ++t) {
        ASSERT_EQ(out[static_cast<size_t>(b * block + t)],
                  in[static_cast<size_t>(b * block + (t + 1) % block)])
            << "block size " << block << ", block " << b << ", thread " << t;
      }
    }
  }
}

TEST(EmulationBarrier, BarriersInALoopGivePrefixSums) {
  for (const int block : {1, 100, 1024}) {
    const int blocks = 3;
    const std::vector<int> in = distinct_values(block * blocks);
    auto device_in = DeviceBuffer<int>::from_host(in);
    DeviceBuffer<int> device_out(in.size());
    launch_kernel(inclusive_scan_kernel, dim3(blocks), dim3(block), 0, nullptr, device_in.data(),
                  device_out.data());
    const std::vector<int> out = device_out.to_host();
    for (int b = 0; b < blocks; ++b) {
      std::vector<int> expected(static_cast<size_t>(block));
      std::partial_sum(in.begin() + b * block, in.begin() + (b + 1) * block, expected.begin());
      for (int t = 0; t < block; ++t) {
        ASSERT_EQ(out[static_cast<size_t>(b * block + t)], expected[static_cast<size_t>(t)])
            << "block size " << block << ", block " << b << ", thread " << t;
      }
    }
  }
}

TEST(EmulationWarp, BlockSumWithShufflesIsExactForEveryBlockSize) {
  for (const int block : {32, 64, 256, 1024, 96, 33, 50, 1}) {
    const int blocks = 5;
    std::vector<long long> values(static_cast<size_t>(block * blocks));
    for (size_t i = 0; i < values.size(); ++i)
      values[i] = static_cast<long long>((i * 2654435761u) % 100003) - 50000;
    auto device_values = DeviceBuffer<long long>::from_host(values);
    DeviceBuffer<long long> device_sums(static_cast<size_t>(blocks));
    launch_kernel(block_sum_kernel, dim3(blocks), dim3(block), 0, nullptr, device_values.data(),
                  device_sums.data());
    const std::vector<long long> sums = device_sums.to_host();
    for (int b = 0; b < blocks; ++b) {
      const long long expected =
          std::accumulate(values.begin() + b * block, values.begin() + (b + 1) * block, 0ll);
      EXPECT_EQ(sums[static_cast<size_t>(b)], expected)
          << "block size " << block << ", block " << b;
    }
  }
}

TEST(EmulationWarp, ShufflesAndVotesFollowCudaSemantics) {
  DeviceBuffer<WarpResults> device_results(1);
  launch_kernel(warp_semantics_kernel, dim3(1), dim3(64), 0, nullptr, device_results.data());
  const WarpResults r = device_results.to_host()[0];
  unsigned every_third = 0;
  for (int lane = 0; lane < 32; lane += 3) every_third |= 1u << lane;
  for (int lane = 0; lane < 32; ++lane) {
    SCOPED_TRACE(lane);
    const auto value_of = [](int source) { return source * 10 + 1; };
    EXPECT_EQ(r.index[lane], value_of((lane + 3) % 32));
    EXPECT_EQ(r.index_width8[lane], value_of((lane / 8) * 8 + 2));
    EXPECT_EQ(r.up1[lane], lane == 0 ? value_of(0) : value_of(lane - 1));
    EXPECT_EQ(r.down4_width16[lane], lane % 16 >= 12 ? value_of(lane) : value_of(lane + 4));
    EXPECT_EQ(r.xor1[lane], value_of(lane ^ 1));
    EXPECT_EQ(r.xor16[lane], value_of(lane ^ 16));
    EXPECT_EQ(r.ballot_every_third[lane], every_third);
    EXPECT_EQ(r.ballot_low_half[lane], lane < 16 ? 0xAAAAu : 0u);
    EXPECT_EQ(r.any_none[lane], 0);
    EXPECT_EQ(r.any_one[lane], 1);
    EXPECT_EQ(r.all_but_one[lane], 0);
    EXPECT_EQ(r.all_true[lane], 1);
    EXPECT_EQ(r.xor3_double[lane], (lane ^ 3) + 0.5);
  }
  for (int t = 0; t < 64; ++t)
    EXPECT_EQ(r.broadcast_per_warp[t], t < 32 ? 0 : 32) << "thread " << t;
}

TEST(EmulationAtomics, CountsFromManyBlocksAreExact) {
  const int n = 100000;
  std::vector<int> values(n);
  for (int i = 0; i < n; ++i) values[static_cast<size_t>(i)] = (i * 7919) % 100000;
  auto device_values = DeviceBuffer<int>::from_host(values);
  auto device_counters = DeviceBuffer<AtomicCounters>::from_host(std::vector<AtomicCounters>(1));
  launch_kernel(atomics_kernel, dim3(64), dim3(128), 0, nullptr, device_values.data(), n,
                device_counters.data());
  const AtomicCounters c = device_counters.to_host()[0];

  AtomicCounters expected;
  for (const int value : values) {
    expected.sum += static_cast<unsigned long long>(value);
    expected.max = std::max(expected.max, value);
    expected.min = std::min(expected.min, value);
    expected.histogram[value % 16] += 1;
    expected.bits |= 1u << (value % 32);
  }
  EXPECT_EQ(c.count, n);
  EXPECT_EQ(c.cas_count, n);
  EXPECT_EQ(c.sum, expected.sum);
  EXPECT_EQ(c.max, expected.max);
  EXPECT_EQ(c.min, expected.min);
  EXPECT_EQ(c.float_count, static_cast<float>(n));   // exact below 2^24
  EXPECT_EQ(c.ring, static_cast<unsigned>(n % 10));  // atomicInc wraps after 9
  EXPECT_EQ(c.bits, expected.bits);
  for (int bin = 0; bin < 16; ++bin)
    EXPECT_EQ(c.histogram[bin], expected.histogram[bin]) << "bin " << bin;
}

TEST(EmulationSharedMemory, DynamicSharedMemoryHasTheLaunchSize) {
  const int block = 200;
  const int blocks = 6;
  std::vector<float> in(static_cast<size_t>(block * blocks));
  for (size_t i = 0; i < in.size(); ++i) in[i] = static_cast<float>(i) * 0.5f;
  auto device_in = DeviceBuffer<float>::from_host(in);
  DeviceBuffer<float> device_out(in.size());
  launch_kernel(reverse_in_block_kernel, dim3(blocks), dim3(block), 2 * block * sizeof(float),
                nullptr, device_in.data(), device_out.data());
  const std::vector<float> out = device_out.to_host();
  for (int b = 0; b < blocks; ++b) {
    for (int t = 0; t < block; ++t) {
      ASSERT_EQ(out[static_cast<size_t>(b * block + t)],
                3.0f * in[static_cast<size_t>(b * block + block - 1 - t)]);
    }
  }
}

TEST(EmulationSharedMemory, MoreThan48KiBNeedsTheOptInAttribute) {
  const int block = 32;
  DeviceBuffer<float> in(block), out(block);
  in.fill_zero();
  const std::size_t large = 64 * 1024;
  const std::string refused = error_message([&] {
    launch_kernel(reverse_in_block_kernel, dim3(1), dim3(block), large, nullptr, in.data(),
                  out.data());
  });
  EXPECT_TRUE(contains(refused, "cudaErrorInvalidValue")) << refused;
  EXPECT_TRUE(contains(refused, "cudaFuncAttributeMaxDynamicSharedMemorySize")) << refused;

  PS_CUDA_CHECK(cudaFuncSetAttribute(reverse_in_block_kernel,
                                     cudaFuncAttributeMaxDynamicSharedMemorySize,
                                     static_cast<int>(large)));
  launch_kernel(reverse_in_block_kernel, dim3(1), dim3(block), large, nullptr, in.data(),
                out.data());
  EXPECT_EQ(out.to_host(), std::vector<float>(block, 0.0f));

  EXPECT_EQ(cudaFuncSetAttribute(reverse_in_block_kernel,
                                 cudaFuncAttributeMaxDynamicSharedMemorySize, 300000),
            cudaErrorInvalidValue);
  EXPECT_EQ(cudaGetLastError(), cudaErrorInvalidValue);
  EXPECT_EQ(cudaGetLastError(), cudaSuccess);
  // Back to the default, so that the test also holds when repeated in one process.
  PS_CUDA_CHECK(cudaFuncSetAttribute(reverse_in_block_kernel,
                                     cudaFuncAttributeMaxDynamicSharedMemorySize, 48 * 1024));
}

TEST(EmulationIndices, GridStrideLoopVisitsEveryElementOnce) {
  const int n = 10007;
  DeviceBuffer<int> visits(n);
  visits.fill_zero();
  launch_kernel(grid_stride_kernel<int>, dim3(3), dim3(64), 0, nullptr, visits.data(), n);
  EXPECT_EQ(visits.to_host(), std::vector<int>(n, 1));
}

TEST(EmulationIndices, ThreeDimensionalGridsAndBlocks) {
  const dim3 grid(2, 3, 4);
  const dim3 block(4, 2, 3);
  const int threads = 2 * 3 * 4 * 4 * 2 * 3;
  DeviceBuffer<IndexRecord> records(threads);
  records.fill_zero();
  launch_kernel(index_kernel, grid, block, 0, nullptr, records.data());
  const std::vector<IndexRecord> r = records.to_host();
  int i = 0;
  for (int bz = 0; bz < 4; ++bz)
    for (int by = 0; by < 3; ++by)
      for (int bx = 0; bx < 2; ++bx)
        for (int tz = 0; tz < 3; ++tz)
          for (int ty = 0; ty < 2; ++ty)
            for (int tx = 0; tx < 4; ++tx, ++i) {
              const IndexRecord& record = r[static_cast<size_t>(i)];
              ASSERT_EQ(std::vector<int>(record.block, record.block + 3),
                        (std::vector<int>{bx, by, bz}))
                  << i;
              ASSERT_EQ(std::vector<int>(record.thread, record.thread + 3),
                        (std::vector<int>{tx, ty, tz}))
                  << i;
              ASSERT_EQ(std::vector<int>(record.block_dim, record.block_dim + 3),
                        (std::vector<int>{4, 2, 3}));
              ASSERT_EQ(std::vector<int>(record.grid_dim, record.grid_dim + 3),
                        (std::vector<int>{2, 3, 4}));
            }
}

TEST(EmulationRuntime, ArgumentsAreConvertedAndCopiedAtLaunch) {
  const int n = 1000;
  std::vector<float> x(n);
  std::iota(x.begin(), x.end(), -500.0f);
  auto device_x = DeviceBuffer<float>::from_host(x);
  DeviceBuffer<float> device_y(n);
  const std::int64_t count = n;  // the kernel takes an int
  double scale = 0.5;            // the kernel takes a float
  launch_kernel(scale_add_kernel, dim3(2), dim3(128), 0, nullptr, device_x.data(), scale, 3.0f,
                device_y.data(), count);
  const std::vector<float> y = device_y.to_host();
  for (int i = 0; i < n; ++i)
    ASSERT_EQ(y[static_cast<size_t>(i)], 0.5f * x[static_cast<size_t>(i)] + 3.0f) << i;
}

TEST(EmulationRuntime, OneEmulatedDevice) {
  int count = 0;
  PS_CUDA_CHECK(cudaGetDeviceCount(&count));
  EXPECT_EQ(count, 1);
  cudaDeviceProp properties;
  PS_CUDA_CHECK(cudaGetDeviceProperties(&properties, 0));
  EXPECT_TRUE(contains(properties.name, "emulation")) << properties.name;
  EXPECT_EQ(properties.warpSize, 32);
  EXPECT_EQ(properties.maxThreadsPerBlock, 1024);
  EXPECT_EQ(properties.sharedMemPerBlock, 48u * 1024u);
  EXPECT_EQ(cudaSetDevice(1), cudaErrorInvalidDevice);
  EXPECT_EQ(cudaGetLastError(), cudaErrorInvalidDevice);
}

TEST(EmulationStreams, EventsMeasureTheWorkBetweenThem) {
  cudaStream_t stream = nullptr;
  PS_CUDA_CHECK(cudaStreamCreate(&stream));
  cudaEvent_t start = nullptr, stop = nullptr, untimed = nullptr;
  PS_CUDA_CHECK(cudaEventCreate(&start));
  PS_CUDA_CHECK(cudaEventCreate(&stop));
  PS_CUDA_CHECK(cudaEventCreateWithFlags(&untimed, cudaEventDisableTiming));
  float milliseconds = -1.0f;
  EXPECT_EQ(cudaEventElapsedTime(&milliseconds, start, stop),
            cudaErrorInvalidResourceHandle);  // not recorded
  const int n = 1 << 16;
  DeviceBuffer<float> x(n), y(n);
  x.fill_zero(stream);
  PS_CUDA_CHECK(cudaEventRecord(start, stream));
  launch_kernel(scale_add_kernel, dim3(64), dim3(256), 0, stream, x.data(), 1.0f, 2.0f, y.data(),
                n);
  PS_CUDA_CHECK(cudaEventRecord(stop, stream));
  PS_CUDA_CHECK(cudaEventRecord(untimed, stream));
  PS_CUDA_CHECK(cudaEventSynchronize(stop));
  PS_CUDA_CHECK(cudaEventElapsedTime(&milliseconds, start, stop));
  EXPECT_GE(milliseconds, 0.0f);
  EXPECT_EQ(cudaEventElapsedTime(&milliseconds, start, untimed), cudaErrorInvalidResourceHandle);
  EXPECT_EQ(y.to_host(stream), std::vector<float>(n, 2.0f));
  PS_CUDA_CHECK(cudaEventDestroy(start));
  PS_CUDA_CHECK(cudaEventDestroy(stop));
  PS_CUDA_CHECK(cudaEventDestroy(untimed));
  PS_CUDA_CHECK(cudaStreamDestroy(stream));
  EXPECT_EQ(cudaStreamDestroy(stream), cudaErrorInvalidResourceHandle);
  static_cast<void>(cudaGetLastError());
}

TEST(EmulationStreams, GraphCaptureRecordsAndReplays) {
  const int n = 3000;
  cudaStream_t stream = nullptr;
  PS_CUDA_CHECK(cudaStreamCreate(&stream));
  DeviceBuffer<float> x(n), y(n);
  std::vector<float> host_x(n), host_y(n, -1.0f);
  std::iota(host_x.begin(), host_x.end(), 0.0f);

  PS_CUDA_CHECK(cudaStreamBeginCapture(stream, cudaStreamCaptureModeGlobal));
  PS_CUDA_CHECK(
      cudaMemcpyAsync(x.data(), host_x.data(), n * sizeof(float), cudaMemcpyHostToDevice, stream));
  launch_kernel(scale_add_kernel, dim3(4), dim3(128), 0, stream, x.data(), 2.0f, 1.0f, y.data(), n);
  PS_CUDA_CHECK(
      cudaMemcpyAsync(host_y.data(), y.data(), n * sizeof(float), cudaMemcpyDeviceToHost, stream));
  cudaStreamCaptureStatus status = cudaStreamCaptureStatusNone;
  PS_CUDA_CHECK(cudaStreamIsCapturing(stream, &status));
  EXPECT_EQ(status, cudaStreamCaptureStatusActive);
  cudaGraph_t graph = nullptr;
  PS_CUDA_CHECK(cudaStreamEndCapture(stream, &graph));
  EXPECT_EQ(host_y, std::vector<float>(n, -1.0f)) << "capture must record, not run";

  cudaGraphExec_t executable = nullptr;
  PS_CUDA_CHECK(cudaGraphInstantiate(&executable, graph, 0));
  for (const float shift : {0.0f, 0.25f}) {
    for (int i = 0; i < n; ++i) host_x[static_cast<size_t>(i)] = static_cast<float>(i) + shift;
    PS_CUDA_CHECK(cudaGraphLaunch(executable, stream));
    PS_CUDA_CHECK(cudaStreamSynchronize(stream));
    for (int i = 0; i < n; ++i) {
      ASSERT_EQ(host_y[static_cast<size_t>(i)], 2.0f * host_x[static_cast<size_t>(i)] + 1.0f)
          << "shift " << shift;
    }
  }
  // The graph gives what direct launches give.
  DeviceBuffer<float> direct(n);
  launch_kernel(scale_add_kernel, dim3(4), dim3(128), 0, stream, x.data(), 2.0f, 1.0f,
                direct.data(), n);
  EXPECT_EQ(direct.to_host(stream), host_y);

  PS_CUDA_CHECK(cudaGraphExecDestroy(executable));
  PS_CUDA_CHECK(cudaGraphDestroy(graph));
  PS_CUDA_CHECK(cudaStreamDestroy(stream));
}

TEST(EmulationStreams, AllocatingOrSynchronisingDuringCaptureInvalidatesIt) {
  cudaStream_t stream = nullptr;
  PS_CUDA_CHECK(cudaStreamCreate(&stream));
  PS_CUDA_CHECK(cudaStreamBeginCapture(stream, cudaStreamCaptureModeGlobal));
  void* memory = nullptr;
  EXPECT_EQ(cudaMalloc(&memory, 64), cudaErrorStreamCaptureUnsupported);
  EXPECT_TRUE(contains(emu::last_error_detail(), "while a stream captures"))
      << emu::last_error_detail();
  EXPECT_EQ(cudaStreamSynchronize(stream), cudaErrorStreamCaptureUnsupported);
  cudaStreamCaptureStatus status = cudaStreamCaptureStatusNone;
  PS_CUDA_CHECK(cudaStreamIsCapturing(stream, &status));
  EXPECT_EQ(status, cudaStreamCaptureStatusInvalidated);
  cudaGraph_t graph = nullptr;
  EXPECT_EQ(cudaStreamEndCapture(stream, &graph), cudaErrorStreamCaptureInvalidated);
  EXPECT_EQ(graph, nullptr);
  EXPECT_EQ(cudaStreamEndCapture(stream, &graph), cudaErrorIllegalState);  // no capture left to end
  static_cast<void>(cudaGetLastError());
  PS_CUDA_CHECK(cudaStreamDestroy(stream));
}

TEST(EmulationDeviceBuffer, OwnsMovesAndCopies) {
  static_assert(!std::is_copy_constructible_v<DeviceBuffer<float>>);
  static_assert(!std::is_copy_assignable_v<DeviceBuffer<float>>);
  static_assert(std::is_nothrow_move_constructible_v<DeviceBuffer<float>>);
  static_assert(std::is_nothrow_move_assignable_v<DeviceBuffer<float>>);

  DeviceBuffer<float> empty;
  EXPECT_TRUE(empty.empty());
  EXPECT_EQ(empty.data(), nullptr);
  EXPECT_EQ(DeviceBuffer<float>(0).data(), nullptr);

  const std::vector<float> values{1.0f, -2.0f, 3.5f};
  auto a = DeviceBuffer<float>::from_host(values);
  EXPECT_EQ(a.size(), 3u);
  EXPECT_EQ(a.bytes(), 12u);
  float* const memory = a.data();
  DeviceBuffer<float> b = std::move(a);
  EXPECT_EQ(b.data(), memory);
  EXPECT_EQ(a.data(), nullptr);  // a moved-from buffer is empty
  EXPECT_EQ(a.size(), 0u);
  EXPECT_EQ(b.to_host(), values);
  b.fill_zero();
  EXPECT_EQ(b.to_host(), std::vector<float>(3, 0.0f));

  const std::string mismatch = error_message([&] { b.copy_from_host(std::vector<float>(4)); });
  EXPECT_TRUE(contains(mismatch, "the host data has 4 elements, the buffer 3")) << mismatch;

  b = DeviceBuffer<float>(5);  // frees the old memory
  EXPECT_EQ(cudaFree(memory), cudaErrorInvalidValue)
      << "the moved-into buffer must have freed its old memory";
  static_cast<void>(cudaGetLastError());
}

TEST(EmulationErrors, CheckMacroNamesCallFileAndLine) {
  const float source = 1.0f;
  const int line = __LINE__ + 2;
  const std::string message = error_message(
      [&] { PS_CUDA_CHECK(cudaMemcpy(nullptr, &source, sizeof(float), cudaMemcpyHostToDevice)); });
  EXPECT_TRUE(
      contains(message, "cudaMemcpy(nullptr, &source, sizeof(float), cudaMemcpyHostToDevice)"))
      << message;
  EXPECT_TRUE(contains(message, "test_emulation.cpp:" + std::to_string(line))) << message;
  EXPECT_TRUE(contains(message, "cudaErrorInvalidValue (invalid argument)")) << message;
  EXPECT_TRUE(contains(message, "the destination pointer is null with 4 bytes to copy")) << message;
  EXPECT_EQ(cudaGetLastError(), cudaSuccess) << "the macro clears the last error";
}

TEST(EmulationErrors, CopiesCheckTheirPointersAgainstTheKind) {
  DeviceBuffer<float> device(4);
  std::vector<float> host(8);
  const std::string into_host = error_message(
      [&] { PS_CUDA_CHECK(cudaMemcpy(host.data(), host.data() + 4, 16, cudaMemcpyHostToDevice)); });
  EXPECT_TRUE(contains(into_host, "is not device memory")) << into_host;
  const std::string past_end = error_message(
      [&] { PS_CUDA_CHECK(cudaMemcpy(host.data(), device.data(), 32, cudaMemcpyDeviceToHost)); });
  EXPECT_TRUE(contains(past_end, "runs 16 bytes past the end of its 16-byte device allocation"))
      << past_end;
  const std::string device_as_host = error_message(
      [&] { PS_CUDA_CHECK(cudaMemcpy(device.data(), host.data(), 16, cudaMemcpyDeviceToHost)); });
  EXPECT_TRUE(contains(device_as_host, "is device memory, but the copy kind says host memory"))
      << device_as_host;
  const std::string bad_kind = error_message([&] {
    PS_CUDA_CHECK(cudaMemcpy(device.data(), host.data(), 16, static_cast<cudaMemcpyKind>(7)));
  });
  EXPECT_TRUE(contains(bad_kind, "cudaErrorInvalidMemcpyDirection")) << bad_kind;
  const std::string interior_free =
      error_message([&] { PS_CUDA_CHECK(cudaFree(device.data() + 1)); });
  EXPECT_TRUE(contains(interior_free, "is not the start of a live cudaMalloc allocation"))
      << interior_free;
  const std::string bad_stream = error_message([&] {
    PS_CUDA_CHECK(
        cudaMemsetAsync(device.data(), 0, 16, reinterpret_cast<cudaStream_t>(host.data())));
  });
  EXPECT_TRUE(contains(bad_stream, "cudaErrorInvalidResourceHandle")) << bad_stream;
}

TEST(EmulationErrors, InvalidLaunchConfigurationsNameTheLaunch) {
  DeviceBuffer<int> out(64);
  const int line = __LINE__ + 2;
  const std::string too_large = error_message([&] {
    launch_kernel(grid_stride_kernel<int>, dim3(1), dim3(2048), 0, nullptr, out.data(), 64);
  });
  EXPECT_TRUE(contains(too_large, "kernel launch <<<(1, 1, 1), (2048, 1, 1), 0>>>")) << too_large;
  EXPECT_TRUE(contains(too_large, "test_emulation.cpp:" + std::to_string(line))) << too_large;
  EXPECT_TRUE(contains(too_large, "cudaErrorInvalidConfiguration")) << too_large;
  EXPECT_TRUE(contains(too_large, "has 2048 threads")) << too_large;
  const std::string empty_grid = error_message([&] {
    launch_kernel(grid_stride_kernel<int>, dim3(0), dim3(32), 0, nullptr, out.data(), 64);
  });
  EXPECT_TRUE(contains(empty_grid, "cudaErrorInvalidConfiguration")) << empty_grid;
  const std::string deep_block = error_message([&] {
    launch_kernel(grid_stride_kernel<int>, dim3(1), dim3(1, 1, 65), 0, nullptr, out.data(), 64);
  });
  EXPECT_TRUE(contains(deep_block, "z <= 64")) << deep_block;
  EXPECT_EQ(cudaGetLastError(), cudaSuccess);
}

TEST(EmulationMisuse, DivergentBarriersAreReported) {
  DeviceBuffer<int> out(64);
  const std::string early_return = error_message([&] {
    launch_kernel(early_return_before_barrier_kernel, dim3(8), dim3(64), 0, nullptr, out.data());
  });
  EXPECT_TRUE(contains(early_return, "cudaErrorLaunchFailure")) << early_return;
  EXPECT_TRUE(contains(early_return, "__syncthreads() was reached by 48 of 64 threads"))
      << early_return;
  EXPECT_TRUE(contains(early_return,
                       "16 threads had returned without reaching it (first: thread (48, 0, 0))"))
      << early_return;
  EXPECT_TRUE(contains(early_return, "block (0, 0, 0)")) << early_return;

  const std::string odd_only = error_message([&] {
    launch_kernel(odd_threads_barrier_kernel, dim3(1), dim3(64), 0, nullptr, out.data());
  });
  EXPECT_TRUE(contains(odd_only,
                       "__syncthreads() was reached by 32 of 64 threads (first: thread (1, 0, 0))"))
      << odd_only;

  // The scheduler recovers: the same threads run a correct kernel next.
  const std::vector<int> in = distinct_values(64);
  auto device_in = DeviceBuffer<int>::from_host(in);
  launch_kernel(rotate_in_block_kernel, dim3(1), dim3(64), 0, nullptr, device_in.data(),
                out.data());
  const std::vector<int> rotated = out.to_host();
  for (int t = 0; t < 64; ++t)
    ASSERT_EQ(rotated[static_cast<size_t>(t)], in[static_cast<size_t>((t + 1) % 64)]);
}

TEST(EmulationMisuse, BadWarpMasksAreReported) {
  DeviceBuffer<int> out(64);
  const auto launch_message = [&](void (*kernel)(int*), int threads) {
    return error_message(
        [&] { launch_kernel(kernel, dim3(1), dim3(threads), 0, nullptr, out.data()); });
  };
  const std::string returned = launch_message(shuffle_with_returned_lanes_kernel, 32);
  EXPECT_TRUE(contains(
      returned, "lanes 0, 1, 2, 3, 4, 5, 6, 7, ... wait in __shfl_down_sync with mask 0xffffffff"))
      << returned;
  EXPECT_TRUE(contains(returned, "lanes 16, 17, 18, 19, 20, 21, 22, 23, ... had returned"))
      << returned;

  const std::string own_lane = launch_message(mask_without_own_lane_kernel, 32);
  EXPECT_TRUE(contains(own_lane, "thread (1, 0, 0)")) << own_lane;
  EXPECT_TRUE(contains(
      own_lane, "__shfl_sync with mask 0x00000001, which does not contain the calling lane 1"))
      << own_lane;

  const std::string mixed = launch_message(mixed_warp_operations_kernel, 32);
  EXPECT_TRUE(contains(
      mixed, "__ballot_sync with mask 0xffffffff while lanes 0 of warp 0 wait in __shfl_sync"))
      << mixed;

  const std::string missing = launch_message(full_mask_in_partial_warp_kernel, 33);
  EXPECT_TRUE(
      contains(missing, "names lanes 1, 2, 3, 4, 5, 6, 7, 8, ... of warp 1, which do not exist"))
      << missing;
  EXPECT_TRUE(contains(missing, "a block of 33 threads has 1 lanes in that warp")) << missing;

  const std::string width = launch_message(bad_width_kernel, 32);
  EXPECT_TRUE(contains(width, "width 3; the width must be a power of two from 1 to 32")) << width;
}

TEST(EmulationMisuse, DeviceFunctionsOutsideAKernelThrow) {
  const std::string message = error_message([] { __syncthreads(); });
  EXPECT_TRUE(contains(message, "__syncthreads() was called outside a kernel launch")) << message;
}

TEST(EmulationSchedule, ParsesTheThreeOrdersAndRefusesAnythingElse) {
  EXPECT_EQ(emu::parse_schedule("forward", "V"), kForward);
  EXPECT_EQ(emu::parse_schedule("reverse", "V"), kReverse);
  EXPECT_EQ(emu::parse_schedule("random:0", "V"), random_schedule(0));
  EXPECT_EQ(emu::parse_schedule("random:18446744073709551615", "V"),
            random_schedule(18446744073709551615ull));
  EXPECT_EQ(emu::to_string(random_schedule(42)), "random:42");
  EXPECT_EQ(emu::parse_schedule(emu::to_string(kReverse), "V"), kReverse);
  for (const char* bad : {"", "Forward", "backward", "random", "random:", "random:-1", "random:1x",
                          "random:18446744073709551616", " reverse"}) {
    const std::string message =
        error_message([&] { emu::parse_schedule(bad, "PILLARSEG_EMU_SCHEDULE"); });
    EXPECT_TRUE(contains(message, "PILLARSEG_EMU_SCHEDULE='" + std::string(bad) + "'")) << message;
    EXPECT_TRUE(contains(message, "expected forward, reverse or random:SEED")) << message;
  }
}

TEST(EmulationSchedule, APlantedRaceGivesDifferentResultsUnderTheOrders) {
  const int block = 256;
  const int blocks = 3;
  const std::vector<int> in = distinct_values(block * blocks);
  auto device_in = DeviceBuffer<int>::from_host(in);
  DeviceBuffer<int> device_out(in.size());
  auto launch = [&] {
    launch_kernel(racy_rotate_kernel, dim3(blocks), dim3(block), 0, nullptr, device_in.data(),
                  device_out.data());
  };
  const std::vector<int> forward = run_under(kForward, device_out, launch);
  const std::vector<int> reverse = run_under(kReverse, device_out, launch);
  const std::vector<int> random = run_under(random_schedule(7), device_out, launch);
  // Forward: thread t reads slot t + 1 before thread t + 1 has written it, so it reads the poison
  // (all bits set: -1), except the last thread, which reads slot 0. Reverse: every slot t + 1 is
  // written before thread t reads it, except slot 0 for the last thread.
  for (int b = 0; b < blocks; ++b) {
    for (int t = 0; t < block; ++t) {
      const auto i = static_cast<size_t>(b * block + t);
      const int correct = in[static_cast<size_t>(b * block + (t + 1) % block)];
      EXPECT_EQ(forward[i], t == block - 1 ? correct : -1) << "block " << b << " thread " << t;
      EXPECT_EQ(reverse[i], t == block - 1 ? -1 : correct) << "block " << b << " thread " << t;
    }
  }
  EXPECT_NE(random, forward);
  EXPECT_NE(random, reverse);
  // The same seed gives the same order; another seed another.
  EXPECT_EQ(run_under(random_schedule(7), device_out, launch), random);
  EXPECT_NE(run_under(random_schedule(8), device_out, launch), random);
}

TEST(EmulationSchedule, AWarpExchangeNeedsSyncwarp) {
  std::vector<int> in(32);
  std::iota(in.begin(), in.end(), 100);
  auto device_in = DeviceBuffer<int>::from_host(in);
  DeviceBuffer<int> device_out(32);
  for (const bool sync : {true, false}) {
    auto launch = [&] {
      launch_kernel(warp_exchange_kernel, dim3(1), dim3(32), 0, nullptr, device_in.data(),
                    device_out.data(), sync);
    };
    const std::vector<int> forward = run_under(kForward, device_out, launch);
    const std::vector<int> reverse = run_under(kReverse, device_out, launch);
    const std::vector<int> random = run_under(random_schedule(3), device_out, launch);
    if (sync) {
      for (int lane = 0; lane < 32; ++lane)
        EXPECT_EQ(forward[static_cast<size_t>(lane)], 100 + (lane ^ 1));
      EXPECT_EQ(reverse, forward);
      EXPECT_EQ(random, forward);
    } else {
      EXPECT_NE(reverse, forward) << "without __syncwarp, even lanes read their neighbour's slot "
                                     "before it is written under forward and after under reverse";
    }
  }
}

TEST(EmulationSchedule, CorrectKernelsGiveTheSameBitsUnderEveryOrder) {
  for (const int block : {1, 33, 256}) {
    const int blocks = 5;
    const std::vector<int> in = distinct_values(block * blocks);
    auto device_in = DeviceBuffer<int>::from_host(in);
    DeviceBuffer<int> device_out(in.size());
    for (const auto kernel : {rotate_in_block_kernel, inclusive_scan_kernel}) {
      auto launch = [&] {
        launch_kernel(kernel, dim3(blocks), dim3(block), 0, nullptr, device_in.data(),
                      device_out.data());
      };
      const std::vector<int> forward = run_under(kForward, device_out, launch);
      EXPECT_EQ(run_under(kReverse, device_out, launch), forward) << "block size " << block;
      EXPECT_EQ(run_under(random_schedule(11), device_out, launch), forward)
          << "block size " << block;
    }
  }
}

TEST(EmulationSchedule, BlocksRunInTheScheduleOrder) {
  const int previous_threads = omp_get_max_threads();
  omp_set_num_threads(1);  // one OS thread: the blocks run one after the other in the order
  DeviceBuffer<int> device_out(1);
  const int blocks = 97;
  auto launch = [&] {
    launch_kernel(last_block_kernel, dim3(blocks), dim3(32), 0, nullptr, device_out.data());
  };
  const std::vector<int> forward = run_under(kForward, device_out, launch);
  const std::vector<int> reverse = run_under(kReverse, device_out, launch);
  std::vector<int> random_last;
  for (std::uint64_t seed = 1; seed <= 4; ++seed)
    random_last.push_back(run_under(random_schedule(seed), device_out, launch)[0]);
  omp_set_num_threads(previous_threads);
  EXPECT_EQ(forward[0], blocks - 1);
  EXPECT_EQ(reverse[0], 0);
  EXPECT_TRUE(std::any_of(random_last.begin(), random_last.end(), [&](int last) {
    return last != blocks - 1 && last != 0;
  })) << "four seeds all ended with the first or the last block";
}

TEST(EmulationSharedMemory, EveryBlockStartsWithPoisonedSharedMemory) {
  const int block = 256;
  const int blocks = 9;
  DeviceBuffer<std::uint32_t> device_out(static_cast<size_t>(block * blocks * 2));
  for (const auto& schedule : {kForward, kReverse, random_schedule(5)}) {
    const std::vector<std::uint32_t> out = run_under(schedule, device_out, [&] {
      launch_kernel(read_before_write_kernel, dim3(blocks), dim3(block),
                    block * sizeof(std::uint32_t), nullptr, device_out.data());
    });
    for (size_t i = 0; i < out.size(); ++i) {
      ASSERT_EQ(out[i], 0xFFFFFFFFu)
          << (i % 2 == 0 ? "static" : "dynamic") << " shared slot of thread " << i / 2 % block
          << " of block " << i / 2 / block << " under " << emu::to_string(schedule);
    }
  }
}
