// The block scheduler of the CUDA emulation: runs a grid of blocks of threads on the host.
//
// Blocks are spread over OpenMP threads. The threads of one block run as fibers on one OS thread,
// one after the other: a thread runs until it returns or until it must wait for other threads of
// its block (__syncthreads, or a warp shuffle/vote/__syncwarp that needs every lane of its mask);
// only then does the scheduler start or resume another thread. A kernel that never waits so costs
// one fiber switch per block, not per thread. Misuse that would hang or be undefined on a GPU (a
// barrier some threads never reach, a warp mask naming lanes that returned or do not exist,
// different warp operations with one mask) stops the launch with a pillarseg::Error saying which
// block, thread and operation.
//
// The order is a choice, as on a GPU, where nothing orders the threads between synchronisation
// points: the schedule (PILLARSEG_EMU_SCHEDULE=forward|reverse|random:SEED) says in which order
// the threads of a block run in each interval between two synchronisation points (a barrier or a
// warp operation) and in which order the blocks run. A kernel whose result depends on it has a
// race. Every block starts with its shared memory, static and dynamic, filled with 0xFF bytes
// (NaN as float, -1 as integer), as device memory is at allocation.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <string>
#include <string_view>
#include <vector>

#include "kernels/emu/emu_types.hpp"

namespace pillarseg::emu {

// One launch as the scheduler sees it: the shapes, the dynamic shared memory per block, and a
// function running the kernel for the current thread with the launch's bound arguments.
struct GridLaunch {
  dim3 grid;
  dim3 block;
  std::size_t dynamic_shared_bytes = 0;
  const void* bound_arguments = nullptr;
  void (*run_thread)(const void* bound_arguments) = nullptr;
};

// The order of a block's threads in each interval, and of a grid's blocks.
//   forward:      ascending (thread 0 first, block 0 first)
//   reverse:      descending
//   random:SEED   a permutation per interval and per block, from SEED and the block's index (the
//                 same for the same SEED); the blocks in a permuted order
struct Schedule {
  enum class Order : std::uint8_t { Forward, Reverse, Random };
  Order order = Order::Forward;
  std::uint64_t seed = 0;
  bool operator==(const Schedule&) const = default;
};

// "forward", "reverse" or "random:SEED" (SEED a decimal unsigned 64-bit number); anything else
// throws pillarseg::Error naming `source` (the variable or argument it came from).
Schedule parse_schedule(std::string_view text, std::string_view source);
std::string to_string(const Schedule& schedule);

// The schedule of the launches that start from now on: PILLARSEG_EMU_SCHEDULE when set (read at
// the first launch; a bad value fails that launch and every one after it with the parse error),
// else forward, until set_schedule replaces it (tests compare orders in one process).
Schedule current_schedule();
void set_schedule(const Schedule& schedule);

// Runs every thread of every block of `launch`; returns when all have returned. Throws
// pillarseg::Error (naming the block and the thread) on misuse, and rethrows anything a kernel
// throws. Preconditions (shapes within CUDA's limits) are checked by the runtime's launch.
void run_grid(const GridLaunch& launch);

// ---- the device side: called by the functions of emu_device.hpp from inside a kernel ----

// The warp-synchronous operations; all lanes of a mask must call the same one.
enum class WarpOp : std::uint8_t {
  Sync,
  ShuffleIndex,
  ShuffleUp,
  ShuffleDown,
  ShuffleXor,
  Ballot,
  Any,
  All,
  Matrix  // mma.sync and ldmatrix (emu_mma.hpp): a function of every lane's registers
};

// __syncthreads(): waits until every thread of the block has arrived; returns how many arrived
// with a non-zero predicate (for __syncthreads_count/_and/_or).
int block_barrier(int predicate);

// Shuffles: each lane of `mask` gives `value` and receives the value of the lane that `op` and
// `lane_argument` (source lane, delta or lane mask) select within its segment of `width` lanes.
std::uint64_t warp_shuffle(WarpOp op, unsigned mask, std::uint64_t value, int lane_argument,
                           int width);

// Votes and __syncwarp: returns the ballot of `predicate` over the lanes of `mask`.
unsigned warp_vote(WarpOp op, unsigned mask, int predicate);

// A warp-collective matrix instruction: each lane of `mask` gives its own block of registers
// (`lane_block`, alive until this returns); once all have arrived, `compute` runs once with the
// blocks of all 32 lanes (nullptr for lanes outside the mask), reading each lane's inputs and
// writing each lane's outputs, and then every lane returns. All lanes must give the same
// `compute`; `name` is the instruction, for messages.
void warp_matrix(const char* name, unsigned mask, void* lane_block, void (*compute)(void* const* lanes));

// The current block's dynamic shared memory (the launch's dynamic_shared_bytes, 256-byte
// aligned; nullptr when the launch asked for none).
std::byte* dynamic_shared_memory();

// The asynchronous copies (cp.async, emu_mma.hpp) of the current thread: each holds the 16 bytes
// it read from global memory when it was issued and writes them to its shared-memory
// destination only when its group completes (cp.async.wait_group), so that a kernel reading a
// stage before waiting for it reads what was there before, as it may on a GPU. `open`: issued
// since the last commit; `committed`: the committed groups, oldest first. Empty when a thread
// starts; what a thread leaves pending is dropped when it returns.
struct AsyncCopy {
  std::byte* destination = nullptr;
  std::array<std::byte, 16> bytes{};
};
struct AsyncCopies {
  std::vector<AsyncCopy> open;
  std::deque<std::vector<AsyncCopy>> committed;
};
AsyncCopies& thread_async_copies();

// What the emulated kernels have issued since the process started, summed over every launch and
// thread (atomic): warp-level mma.sync m16n8k16 instructions (4,096 flops each: 16 x 8 x 16
// multiply-adds), m16n8k32 INT8 instructions (u8 or s8 by s8; 8,192 each: 16 x 8 x 32) and the
// bytes cp.async copied from global to shared memory (zero-filled copies included: a GPU issues
// them too). The benchmarks read differences (Backend::counters()).
struct InstructionCounts {
  std::uint64_t mma_m16n8k16 = 0;
  std::uint64_t cp_async_bytes = 0;
  std::uint64_t mma_m16n8k32 = 0;
  // The tensor cores' operations: 2 x 16 x 8 x 16 per m16n8k16, 2 x 16 x 8 x 32 per m16n8k32.
  std::uint64_t tensor_core_flops() const { return 4096 * mma_m16n8k16 + 8192 * mma_m16n8k32; }
};
InstructionCounts instruction_counts();
void count_mma_m16n8k16();
void count_mma_m16n8k32();
void count_cp_async_bytes(std::uint64_t bytes);

}  // namespace pillarseg::emu
