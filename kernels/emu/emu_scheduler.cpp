// The block scheduler of the CUDA emulation (see emu_scheduler.hpp): fibers, barriers, warp
// rendezvous, deadlock diagnosis, the schedule's orders, shared-memory poisoning, and the OpenMP
// loop over the blocks of a grid.
//
// The order: a block's threads start in the schedule's order; when a barrier or a warp operation
// completes, every thread it held, the one that completed it included, is queued again in the
// schedule's order, so that no thread runs on past a synchronisation point ahead of the others
// because it happened to arrive last.
//
// Fibers switch stacks with a few instructions on x86-64 (saving the callee-saved registers);
// elsewhere, or with PILLARSEG_EMU_UCONTEXT defined, with ucontext's swapcontext, which also saves
// the signal mask with a system call and is about a hundred times slower. Under AddressSanitizer
// every switch is announced with __sanitizer_start/finish_switch_fiber so that ASan knows which
// stack is live.
#include "kernels/emu/emu_scheduler.hpp"

#include <omp.h>
#include <pthread.h>
#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <limits>
#include <memory>
#include <mutex>
#include <new>
#include <numeric>
#include <optional>
#include <string>
#include <vector>

#include "core/error.hpp"
#include "kernels/emu/emu_device.hpp"

#if defined(__SANITIZE_ADDRESS__)
#define PS_EMU_ASAN 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define PS_EMU_ASAN 1
#endif
#endif
#if defined(PS_EMU_ASAN)
#include <sanitizer/asan_interface.h>
#include <sanitizer/common_interface_defs.h>
#endif

#if defined(__x86_64__) && defined(__ELF__) && !defined(PILLARSEG_EMU_UCONTEXT)
#define PS_EMU_ASM_SWITCH 1
#else
#include <ucontext.h>
#endif

#if defined(PS_EMU_ASM_SWITCH)
// pillarseg_emu_switch_stack(save, load): pushes the callee-saved registers of the System V
// x86-64 ABI on the current stack, stores the stack pointer in *save, loads `load` and pops the
// registers saved there; `ret` then continues the other fiber where it switched away.
// pillarseg_emu_fiber_start: where a new fiber's first switch returns to; calls the entry
// function left in r12 (fiber_main, which never returns).
extern "C" {
void pillarseg_emu_switch_stack(void** save_stack_pointer, void* load_stack_pointer);
void pillarseg_emu_fiber_start();
}
asm(R"(
  .pushsection .text
  .globl pillarseg_emu_switch_stack
  .hidden pillarseg_emu_switch_stack
  .type pillarseg_emu_switch_stack, @function
  .p2align 4
pillarseg_emu_switch_stack:
  pushq %rbp
  pushq %rbx
  pushq %r12
  pushq %r13
  pushq %r14
  pushq %r15
  movq %rsp, (%rdi)
  movq %rsi, %rsp
  popq %r15
  popq %r14
  popq %r13
  popq %r12
  popq %rbx
  popq %rbp
  ret
  .size pillarseg_emu_switch_stack, .-pillarseg_emu_switch_stack

  .globl pillarseg_emu_fiber_start
  .hidden pillarseg_emu_fiber_start
  .type pillarseg_emu_fiber_start, @function
  .p2align 4
pillarseg_emu_fiber_start:
  callq *%r12
  ud2
  .size pillarseg_emu_fiber_start, .-pillarseg_emu_fiber_start
  .popsection
)");
#endif

// The bounds of this thread's copy of the section holding every `__shared__` variable
// (emu_device.hpp), defined by the linker; the anchor makes sure the section exists.
extern "C" {
extern __thread unsigned char __start_pillarseg_emu_shared[] __attribute__((visibility("hidden")));
extern __thread unsigned char __stop_pillarseg_emu_shared[] __attribute__((visibility("hidden")));
}
namespace {
static thread_local
    __attribute__((section("pillarseg_emu_shared"), used)) unsigned char shared_section_anchor[1];
}  // namespace

namespace pillarseg::emu {
namespace {

constexpr int kWarpSize = 32;
// Shared memory at the start of a block: every byte 0xFF (a NaN as float, -1 as an integer).
constexpr unsigned char kSharedPoison = 0xFF;

std::uint64_t splitmix64(std::uint64_t& state) {
  std::uint64_t z = (state += 0x9E3779B97F4A7C15ull);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}

// The seed's permutation of the threads of one synchronisation event of one block.
std::uint64_t event_state(const Schedule& schedule, std::uint64_t block, std::uint64_t event) {
  std::uint64_t state = schedule.seed;
  std::uint64_t mixed = splitmix64(state) ^ block;
  state = mixed;
  mixed = splitmix64(state) ^ event;
  state = mixed;
  return splitmix64(state);
}

// Puts `items` in the schedule's order: ascending, descending, or shuffled by `state`.
void order_items(std::vector<int>& items, const Schedule& schedule, std::uint64_t state) {
  switch (schedule.order) {
    case Schedule::Order::Forward:
      std::sort(items.begin(), items.end());
      return;
    case Schedule::Order::Reverse:
      std::sort(items.begin(), items.end(), std::greater<>());
      return;
    case Schedule::Order::Random:
      std::sort(items.begin(), items.end());
      for (std::size_t i = items.size(); i > 1; --i) {
        const std::size_t j = splitmix64(state) % i;
        std::swap(items[i - 1], items[j]);
      }
      return;
  }
}
#if defined(PS_EMU_ASAN)
// ASan's redzones make frames several times larger.
constexpr std::size_t kFiberStackBytes = 512 * 1024;
#else
constexpr std::size_t kFiberStackBytes = 128 * 1024;
#endif
// What a lane reads from a lane outside the shuffle's mask (undefined in CUDA): all bits set, a
// NaN as float or double and -1 as an integer, so that a kernel using it shows wrong results.
constexpr std::uint64_t kUndefinedLaneValue = ~std::uint64_t{0};

const char* op_name(WarpOp op) {
  switch (op) {
    case WarpOp::Sync:
      return "__syncwarp";
    case WarpOp::ShuffleIndex:
      return "__shfl_sync";
    case WarpOp::ShuffleUp:
      return "__shfl_up_sync";
    case WarpOp::ShuffleDown:
      return "__shfl_down_sync";
    case WarpOp::ShuffleXor:
      return "__shfl_xor_sync";
    case WarpOp::Ballot:
      return "__ballot_sync";
    case WarpOp::Any:
      return "__any_sync";
    case WarpOp::All:
      return "__all_sync";
    case WarpOp::Matrix:
      return "a warp matrix instruction (mma.sync, ldmatrix)";
  }
  return "?";
}

bool is_shuffle(WarpOp op) {
  return op == WarpOp::ShuffleIndex || op == WarpOp::ShuffleUp || op == WarpOp::ShuffleDown ||
         op == WarpOp::ShuffleXor;
}

// The lane whose value `lane` receives, or -1 for its own value (CUDA's rules for a source outside
// the lane's segment of `width` lanes: up/down/xor keep their own value; idx wraps).
int shuffle_source_lane(WarpOp op, int lane, int argument, int width) {
  const int segment = lane & ~(width - 1);
  int source = lane;
  switch (op) {
    case WarpOp::ShuffleIndex:
      source = segment + (argument & (width - 1));
      break;
    case WarpOp::ShuffleUp:
      source = lane - argument;
      break;
    case WarpOp::ShuffleDown:
      source = lane + argument;
      break;
    case WarpOp::ShuffleXor:
      source = lane ^ argument;
      break;
    default:
      return -1;
  }
  if (op == WarpOp::ShuffleUp && source < segment) return -1;
  if (source < 0 || source >= segment + width) return -1;
  return source;
}

std::string format_dim(uint3 v) {
  return fmt::format("({}, {}, {})", v.x, v.y, v.z);
}

// Lanes set in `bits`, as "0, 5, 31" (at most `limit` of them, then "...").
std::string format_lanes(unsigned bits, int limit = 8) {
  std::string out;
  int shown = 0;
  for (int lane = 0; lane < kWarpSize; ++lane) {
    if (((bits >> lane) & 1u) == 0) continue;
    if (shown == limit) return out + ", ...";
    out += shown == 0 ? fmt::format("{}", lane) : fmt::format(", {}", lane);
    ++shown;
  }
  return out;
}

uint3 block_index_of(std::uint64_t linear, dim3 grid) {
  return uint3{static_cast<unsigned>(linear % grid.x),
               static_cast<unsigned>(linear / grid.x % grid.y),
               static_cast<unsigned>(linear / (std::uint64_t{grid.x} * grid.y))};
}

// The schedule's order of the blocks of a grid of `blocks`: the b-th block run is block
// BlockOrder(b); random: b -> (a b + c) mod blocks with a coprime to blocks, from the seed.
class BlockOrder {
  __extension__ using Wide = unsigned __int128;  // a x b before the modulus: 128 bits

 public:
  BlockOrder(const Schedule& schedule, std::uint64_t blocks)
      : order_(schedule.order), blocks_(blocks) {
    if (order_ != Schedule::Order::Random || blocks < 2) return;
    std::uint64_t state = schedule.seed ^ (blocks * 0xD6E8FEB86659FD93ull);
    multiplier_ = splitmix64(state) % blocks;
    while (std::gcd(multiplier_, blocks) != 1) multiplier_ = (multiplier_ + 1) % blocks;
    offset_ = splitmix64(state) % blocks;
  }
  std::uint64_t operator()(std::uint64_t b) const {
    switch (order_) {
      case Schedule::Order::Forward:
        return b;
      case Schedule::Order::Reverse:
        return blocks_ - 1 - b;
      case Schedule::Order::Random:
        if (blocks_ < 2) return b;
        return static_cast<std::uint64_t>((static_cast<Wide>(multiplier_) * b + offset_) % blocks_);
    }
    return b;
  }

 private:
  Schedule::Order order_;
  std::uint64_t blocks_;
  std::uint64_t multiplier_ = 1, offset_ = 0;
};

enum class ThreadStatus : std::uint8_t { NotStarted, Running, AtBarrier, InWarpOp, Returned };

struct Fiber {
  std::byte* mapping = nullptr;  // guard page + stack
  std::size_t mapping_bytes = 0;
  std::byte* stack_bottom = nullptr;
  std::size_t stack_bytes = 0;
#if defined(PS_EMU_ASM_SWITCH)
  void* stack_pointer = nullptr;
#else
  ucontext_t context{};
#endif
  void* asan_fake_stack = nullptr;
  int thread = -1;  // linear index of the thread running on this fiber; -1 when idle
};

struct ThreadState {
  uint3 index{};
  ThreadStatus status = ThreadStatus::NotStarted;
  Fiber* fiber = nullptr;
  std::uint64_t warp_result = 0;
  AsyncCopies async_copies;
};

// Lanes of one warp meeting in one warp-synchronous operation with one mask.
struct WarpGroup {
  WarpOp op = WarpOp::Sync;
  unsigned mask = 0;
  unsigned arrived = 0;
  std::array<std::uint64_t, kWarpSize> values{};
  std::array<std::int8_t, kWarpSize> sources{};
  void (*compute)(void* const* lanes) = nullptr;  // WarpOp::Matrix
};

[[noreturn]] void fiber_main();

// Runs the blocks given to one OS thread, one at a time; owns that thread's fibers.
class BlockRunner {
 public:
  static BlockRunner& for_this_thread() {
    thread_local std::unique_ptr<BlockRunner> runner;
    if (!runner) {
      runner = std::make_unique<BlockRunner>();
      t_current_runner = runner.get();
    }
    return *runner;
  }
  // The runner of this OS thread if it is running a kernel thread now, else nullptr.
  static BlockRunner* in_kernel() {
    BlockRunner* runner = t_current_runner;
    return runner != nullptr && runner->current_ != &runner->main_ ? runner : nullptr;
  }

  BlockRunner();
  ~BlockRunner();
  BlockRunner(const BlockRunner&) = delete;
  BlockRunner& operator=(const BlockRunner&) = delete;

  void run_block(const GridLaunch& launch, const Schedule& schedule, std::uint64_t block_linear,
                 std::byte* dynamic_shared);

  int barrier(int predicate);
  std::uint64_t warp_exchange(WarpOp op, unsigned mask, std::uint64_t value, int lane_argument,
                              int width, void (*compute)(void* const* lanes) = nullptr);
  std::byte* dynamic_shared() const { return dynamic_shared_; }
  AsyncCopies& async_copies() {
    return threads_[static_cast<std::size_t>(current_->thread)].async_copies;
  }

  // Body of every fiber: start threads while some are left, then wait idle for the next block.
  [[noreturn]] void fiber_loop();

 private:
  Fiber* acquire_fiber();
  void initialise_context(Fiber& fiber);
  void switch_to(Fiber* to);
  Fiber* next_fiber();
  void wait();
  void run_threads_on_current_fiber();
  void wake(Fiber* fiber);
  void release_in_order(std::vector<int>& threads);
  void abandon_waiting_fibers();
  [[noreturn]] void fail_here(const std::string& what) const;
  std::string describe_deadlock() const;

  static thread_local BlockRunner* t_current_runner;

  Fiber main_;  // the OS thread's own stack
  Fiber* current_ = &main_;
  std::vector<std::unique_ptr<Fiber>> fibers_;
  std::vector<Fiber*> idle_;
  std::size_t page_bytes_ = 4096;

  // The block being run.
  const GridLaunch* launch_ = nullptr;
  Schedule schedule_;
  std::uint64_t block_linear_ = 0;
  std::uint64_t events_ = 0;      // synchronisation events completed in this block
  std::vector<int> start_order_;  // the threads in the order they start
  std::vector<int> released_;     // scratch: the threads an event releases
  uint3 block_index_{};
  std::byte* dynamic_shared_ = nullptr;
  int num_threads_ = 0;
  int next_thread_ = 0;
  int returned_ = 0;
  std::vector<ThreadState> threads_;
  std::vector<Fiber*> runnable_;
  std::size_t runnable_head_ = 0;
  int barrier_arrived_ = 0;
  int barrier_predicates_ = 0;
  int barrier_result_ = 0;
  std::vector<std::vector<WarpGroup>> warp_groups_;  // per warp, the operations under way
  std::vector<unsigned> returned_lanes_;             // per warp, the lanes that have returned
  std::exception_ptr failure_;
};

thread_local BlockRunner* BlockRunner::t_current_runner = nullptr;

BlockRunner::BlockRunner() {
  const long page = sysconf(_SC_PAGESIZE);
  if (page > 0) page_bytes_ = static_cast<std::size_t>(page);
#if defined(PS_EMU_ASAN)
  // ASan needs the bounds of the stack a fiber switches back to.
  pthread_attr_t attributes;
  if (pthread_getattr_np(pthread_self(), &attributes) == 0) {
    void* low = nullptr;
    std::size_t size = 0;
    pthread_attr_getstack(&attributes, &low, &size);
    pthread_attr_destroy(&attributes);
    main_.stack_bottom = static_cast<std::byte*>(low);
    main_.stack_bytes = size;
  }
#endif
}

BlockRunner::~BlockRunner() {
  t_current_runner = nullptr;
  for (const auto& fiber : fibers_) munmap(fiber->mapping, fiber->mapping_bytes);
}

Fiber* BlockRunner::acquire_fiber() {
  if (!idle_.empty()) {
    Fiber* fiber = idle_.back();
    idle_.pop_back();
    return fiber;
  }
  auto fiber = std::make_unique<Fiber>();
  fiber->mapping_bytes = kFiberStackBytes + page_bytes_;
  void* mapping = mmap(nullptr, fiber->mapping_bytes, PROT_READ | PROT_WRITE,
                       MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE, -1, 0);
  PS_CHECK(mapping != MAP_FAILED, "CUDA emulation: cannot map a {} KiB fiber stack (fiber {}): {}",
           kFiberStackBytes / 1024, fibers_.size(), std::strerror(errno));
  fiber->mapping = static_cast<std::byte*>(mapping);
  // The lowest page stays unmapped so that a stack overflow faults instead of corrupting memory.
  mprotect(fiber->mapping, page_bytes_, PROT_NONE);
  fiber->stack_bottom = fiber->mapping + page_bytes_;
  // Stacks are page aligned, so without an offset the hot top of every stack would fall into the
  // same few L1 cache sets and evict each other at every switch; offsets spread them out.
  const std::size_t cache_offset = fibers_.size() * 704 % page_bytes_ / 64 * 64;
  fiber->stack_bytes = kFiberStackBytes - cache_offset;
  initialise_context(*fiber);
  fibers_.push_back(std::move(fiber));
  return fibers_.back().get();
}

void BlockRunner::initialise_context(Fiber& fiber) {
  fiber.thread = -1;
  fiber.asan_fake_stack = nullptr;
#if defined(PS_EMU_ASAN)
  // Frames abandoned on this stack (after a failed block) leave their redzones poisoned.
  __asan_unpoison_memory_region(fiber.stack_bottom, fiber.stack_bytes);
#endif
#if defined(PS_EMU_ASM_SWITCH)
  // The frame pillarseg_emu_switch_stack pops: r15, r14, r13, r12 (= fiber_main), rbx, rbp, then
  // the return address pillarseg_emu_fiber_start, whose `call` then sees a 16-byte aligned stack.
  const auto top = reinterpret_cast<std::uintptr_t>(fiber.stack_bottom + fiber.stack_bytes);
  auto** frame = reinterpret_cast<void**>(top - 9 * sizeof(void*));
  std::fill(frame, frame + 9, nullptr);
  frame[3] = reinterpret_cast<void*>(&fiber_main);
  frame[6] = reinterpret_cast<void*>(&pillarseg_emu_fiber_start);
  fiber.stack_pointer = frame;
#else
  getcontext(&fiber.context);
  fiber.context.uc_stack.ss_sp = fiber.stack_bottom;
  fiber.context.uc_stack.ss_size = fiber.stack_bytes;
  fiber.context.uc_link = nullptr;
  makecontext(&fiber.context, &fiber_main, 0);
#endif
}

void BlockRunner::switch_to(Fiber* to) {
  Fiber* from = current_;
  current_ = to;
#if defined(PS_EMU_ASAN)
  __sanitizer_start_switch_fiber(&from->asan_fake_stack, to->stack_bottom, to->stack_bytes);
#endif
#if defined(PS_EMU_ASM_SWITCH)
  pillarseg_emu_switch_stack(&from->stack_pointer, to->stack_pointer);
#else
  swapcontext(&from->context, &to->context);
#endif
#if defined(PS_EMU_ASAN)
  __sanitizer_finish_switch_fiber(from->asan_fake_stack, nullptr, nullptr);
#endif
}

// The fiber to continue with: a thread that can go on, else a fresh fiber if threads are left to
// start, else the OS thread's own stack (the block has finished, failed or cannot go on).
Fiber* BlockRunner::next_fiber() {
  if (failure_) return &main_;
  if (runnable_head_ < runnable_.size()) {
    Fiber* fiber = runnable_[runnable_head_++];
    if (runnable_head_ == runnable_.size()) {
      runnable_.clear();
      runnable_head_ = 0;
    }
    return fiber;
  }
  if (next_thread_ < num_threads_) return acquire_fiber();
  return &main_;
}

// The current thread waits: switch to another; resumes when someone wakes this fiber.
void BlockRunner::wait() {
  Fiber* self = current_;
  Fiber* next = next_fiber();
  if (next != self) switch_to(next);
  threadIdx = threads_[static_cast<std::size_t>(self->thread)].index;
}

void BlockRunner::wake(Fiber* fiber) {
  threads_[static_cast<std::size_t>(fiber->thread)].status = ThreadStatus::Running;
  runnable_.push_back(fiber);
}

// Queues the threads a completed barrier or warp operation held, in the schedule's order.
void BlockRunner::release_in_order(std::vector<int>& threads) {
  order_items(threads, schedule_, event_state(schedule_, block_linear_, ++events_));
  for (const int thread : threads) wake(threads_[static_cast<std::size_t>(thread)].fiber);
}

void BlockRunner::run_threads_on_current_fiber() {
  Fiber* self = current_;
  while (next_thread_ < num_threads_) {
    const int thread = start_order_[static_cast<std::size_t>(next_thread_++)];
    ThreadState& state = threads_[static_cast<std::size_t>(thread)];
    self->thread = thread;
    state.fiber = self;
    state.status = ThreadStatus::Running;
    threadIdx = state.index;
    try {
      launch_->run_thread(launch_->bound_arguments);
    } catch (...) {
      failure_ = std::current_exception();
    }
    state.status = ThreadStatus::Returned;
    returned_lanes_[static_cast<std::size_t>(thread / kWarpSize)] |= 1u << (thread % kWarpSize);
    ++returned_;
    if (failure_) break;
  }
  self->thread = -1;
}

void BlockRunner::fiber_loop() {
#if defined(PS_EMU_ASAN)
  __sanitizer_finish_switch_fiber(nullptr, nullptr, nullptr);
#endif
  for (;;) {
    run_threads_on_current_fiber();
    idle_.push_back(current_);
    switch_to(next_fiber());
  }
}

void fiber_main() {
  BlockRunner::for_this_thread().fiber_loop();
}

void BlockRunner::run_block(const GridLaunch& launch, const Schedule& schedule,
                            std::uint64_t block_linear, std::byte* dynamic_shared) {
  launch_ = &launch;
  schedule_ = schedule;
  block_linear_ = block_linear;
  events_ = 0;
  block_index_ = block_index_of(block_linear, launch.grid);
  dynamic_shared_ = dynamic_shared;
  std::memset(__start_pillarseg_emu_shared, kSharedPoison,
              static_cast<std::size_t>(__stop_pillarseg_emu_shared - __start_pillarseg_emu_shared));
  if (dynamic_shared != nullptr)
    std::memset(dynamic_shared, kSharedPoison, launch.dynamic_shared_bytes);
  num_threads_ = static_cast<int>(launch.block.x * launch.block.y * launch.block.z);
  start_order_.resize(static_cast<std::size_t>(num_threads_));
  for (int t = 0; t < num_threads_; ++t) start_order_[static_cast<std::size_t>(t)] = t;
  order_items(start_order_, schedule_, event_state(schedule_, block_linear_, 0));
  next_thread_ = 0;
  returned_ = 0;
  threads_.resize(static_cast<std::size_t>(num_threads_));
  for (int t = 0; t < num_threads_; ++t) {
    const auto linear = static_cast<unsigned>(t);
    ThreadState& state = threads_[static_cast<std::size_t>(t)];
    state.index = uint3{linear % launch.block.x, linear / launch.block.x % launch.block.y,
                        linear / (launch.block.x * launch.block.y)};
    state.status = ThreadStatus::NotStarted;
    state.fiber = nullptr;
    state.async_copies.open.clear();
    state.async_copies.committed.clear();
  }
  warp_groups_.resize(static_cast<std::size_t>((num_threads_ + kWarpSize - 1) / kWarpSize));
  for (auto& groups : warp_groups_) groups.clear();
  returned_lanes_.assign(warp_groups_.size(), 0u);
  runnable_.clear();
  runnable_head_ = 0;
  barrier_arrived_ = 0;
  barrier_predicates_ = 0;
  failure_ = nullptr;
  blockIdx = block_index_;
  blockDim = launch.block;
  gridDim = launch.grid;

  switch_to(next_fiber());

  if (returned_ == num_threads_ && !failure_) return;
  std::exception_ptr failure = failure_;
  const std::string deadlock = failure ? std::string() : describe_deadlock();
  abandon_waiting_fibers();
  if (failure) std::rethrow_exception(failure);
  throw Error(deadlock);
}

// After a failed block: the fibers still holding a waiting thread start afresh next time.
void BlockRunner::abandon_waiting_fibers() {
  for (const auto& fiber : fibers_) {
    if (fiber->thread < 0) continue;
    initialise_context(*fiber);
    idle_.push_back(fiber.get());
  }
  runnable_.clear();
  runnable_head_ = 0;
  barrier_arrived_ = 0;
  failure_ = nullptr;
}

void BlockRunner::fail_here(const std::string& what) const {
  const ThreadState& state = threads_[static_cast<std::size_t>(current_->thread)];
  throw Error(fmt::format("CUDA emulation: block {} thread {} (grid {}, block shape {}): {}",
                          format_dim(block_index_), format_dim(state.index),
                          format_dim(launch_->grid), format_dim(launch_->block), what));
}

int BlockRunner::barrier(int predicate) {
  barrier_predicates_ += predicate != 0 ? 1 : 0;
  threads_[static_cast<std::size_t>(current_->thread)].status = ThreadStatus::AtBarrier;
  if (++barrier_arrived_ == num_threads_) {
    barrier_result_ = barrier_predicates_;
    barrier_predicates_ = 0;
    barrier_arrived_ = 0;
    released_.resize(static_cast<std::size_t>(num_threads_));
    for (int t = 0; t < num_threads_; ++t) released_[static_cast<std::size_t>(t)] = t;
    release_in_order(released_);
  }
  wait();
  // The next barrier cannot complete (and overwrite the result) before this thread arrives there.
  return barrier_result_;
}

std::uint64_t BlockRunner::warp_exchange(WarpOp op, unsigned mask, std::uint64_t value,
                                         int lane_argument, int width,
                                         void (*compute)(void* const* lanes)) {
  const int thread = current_->thread;
  const int warp = thread / kWarpSize;
  const int lane = thread % kWarpSize;
  const int lanes_in_warp = std::min(kWarpSize, num_threads_ - warp * kWarpSize);
  const unsigned existing = lanes_in_warp == kWarpSize ? ~0u : (1u << lanes_in_warp) - 1u;
  const unsigned lane_bit = 1u << lane;
  if ((mask & lane_bit) == 0) {
    fail_here(fmt::format("{} with mask {:#010x}, which does not contain the calling lane {}",
                          op_name(op), mask, lane));
  }
  if ((mask & ~existing) != 0) {
    fail_here(fmt::format(
        "{} with mask {:#010x} names lanes {} of warp {}, which do not exist: a block of {} "
        "threads "
        "has {} lanes in that warp",
        op_name(op), mask, format_lanes(mask & ~existing), warp, num_threads_, lanes_in_warp));
  }
  const unsigned returned_lanes = mask & returned_lanes_[static_cast<std::size_t>(warp)];
  if (returned_lanes != 0) {
    fail_here(
        fmt::format("{} with mask {:#010x} names lanes {} of warp {}, which have already returned",
                    op_name(op), mask, format_lanes(returned_lanes), warp));
  }
  if (is_shuffle(op) && (width < 1 || width > kWarpSize || (width & (width - 1)) != 0)) {
    fail_here(fmt::format("{} with width {}; the width must be a power of two from 1 to 32",
                          op_name(op), width));
  }

  auto& groups = warp_groups_[static_cast<std::size_t>(warp)];
  auto group = std::find_if(groups.begin(), groups.end(), [&](const WarpGroup& g) {
    return g.mask == mask && (g.arrived & lane_bit) == 0;
  });
  if (group == groups.end()) {
    groups.push_back(WarpGroup{op, mask, 0, {}, {}, compute});
    group = groups.end() - 1;
  } else if (group->op != op) {
    fail_here(
        fmt::format("{} with mask {:#010x} while lanes {} of warp {} wait in {} with the same mask",
                    op_name(op), mask, format_lanes(group->arrived), warp, op_name(group->op)));
  } else if (group->compute != compute) {
    fail_here(fmt::format("{} with mask {:#010x} while lanes {} of warp {} wait in a different one",
                          op_name(op), mask, format_lanes(group->arrived), warp));
  }
  group->values[static_cast<std::size_t>(lane)] = value;
  group->sources[static_cast<std::size_t>(lane)] = static_cast<std::int8_t>(
      is_shuffle(op) ? shuffle_source_lane(op, lane, lane_argument, width) : -1);
  group->arrived |= lane_bit;

  ThreadState& self = threads_[static_cast<std::size_t>(thread)];
  if (group->arrived != mask) {
    self.status = ThreadStatus::InWarpOp;
    wait();
    return self.warp_result;
  }

  // The last lane has arrived: hand every lane its result and wake the others.
  if (op == WarpOp::Matrix) {
    std::array<void*, kWarpSize> lanes{};
    for (unsigned bits = mask; bits != 0; bits &= bits - 1) {
      const int other = std::countr_zero(bits);
      lanes[static_cast<std::size_t>(other)] = reinterpret_cast<void*>(
          static_cast<std::uintptr_t>(group->values[static_cast<std::size_t>(other)]));
    }
    group->compute(lanes.data());
  }
  unsigned ballot = 0;
  if (!is_shuffle(op)) {
    for (unsigned bits = mask; bits != 0; bits &= bits - 1) {
      const int other = std::countr_zero(bits);
      if (group->values[static_cast<std::size_t>(other)] != 0) ballot |= 1u << other;
    }
  }
  released_.clear();
  for (unsigned bits = mask; bits != 0; bits &= bits - 1) {
    const int other = std::countr_zero(bits);
    std::uint64_t result = ballot;
    if (is_shuffle(op)) {
      const int source = group->sources[static_cast<std::size_t>(other)];
      if (source < 0) {
        result = group->values[static_cast<std::size_t>(other)];
      } else if (((mask >> source) & 1u) != 0) {
        result = group->values[static_cast<std::size_t>(source)];
      } else {
        result = kUndefinedLaneValue;
      }
    }
    threads_[static_cast<std::size_t>(warp * kWarpSize + other)].warp_result = result;
    released_.push_back(warp * kWarpSize + other);
  }
  *group = groups.back();
  groups.pop_back();
  self.status = ThreadStatus::InWarpOp;
  release_in_order(released_);
  wait();
  return self.warp_result;
}

std::string BlockRunner::describe_deadlock() const {
  int first_returned = -1;
  int first_at_barrier = -1;
  for (int t = 0; t < num_threads_; ++t) {
    const ThreadStatus status = threads_[static_cast<std::size_t>(t)].status;
    if (status == ThreadStatus::Returned && first_returned < 0) first_returned = t;
    if (status == ThreadStatus::AtBarrier && first_at_barrier < 0) first_at_barrier = t;
  }
  auto thread_name = [&](int t) { return format_dim(threads_[static_cast<std::size_t>(t)].index); };
  std::string message = fmt::format(
      "CUDA emulation: block {} (grid {}, block shape {}) cannot go on, a GPU would hang here:",
      format_dim(block_index_), format_dim(launch_->grid), format_dim(launch_->block));
  if (barrier_arrived_ > 0) {
    message += fmt::format(" __syncthreads() was reached by {} of {} threads (first: thread {})",
                           barrier_arrived_, num_threads_, thread_name(first_at_barrier));
    if (first_returned >= 0) {
      message +=
          fmt::format(", while {} threads had returned without reaching it (first: thread {})",
                      returned_, thread_name(first_returned));
    }
    message += ";";
  }
  for (std::size_t warp = 0; warp < warp_groups_.size(); ++warp) {
    for (const WarpGroup& group : warp_groups_[warp]) {
      unsigned returned_lanes = 0;
      unsigned barrier_lanes = 0;
      for (unsigned bits = group.mask & ~group.arrived; bits != 0; bits &= bits - 1) {
        const int lane = std::countr_zero(bits);
        const ThreadStatus status =
            threads_[warp * kWarpSize + static_cast<std::size_t>(lane)].status;
        if (status == ThreadStatus::Returned) returned_lanes |= 1u << lane;
        if (status == ThreadStatus::AtBarrier) barrier_lanes |= 1u << lane;
      }
      message += fmt::format(" in warp {}, lanes {} wait in {} with mask {:#010x} for lanes {}",
                             warp, format_lanes(group.arrived), op_name(group.op), group.mask,
                             format_lanes(group.mask & ~group.arrived));
      if (returned_lanes != 0)
        message += fmt::format(" (lanes {} had returned)", format_lanes(returned_lanes));
      if (barrier_lanes != 0) {
        message += fmt::format(" (lanes {} wait at __syncthreads())", format_lanes(barrier_lanes));
      }
      message += ";";
    }
  }
  message +=
      " every thread of a block must reach each __syncthreads(), and every lane named in a warp "
      "mask must call the same *_sync function";
  return message;
}

BlockRunner& runner_in_kernel(const char* function) {
  BlockRunner* runner = BlockRunner::in_kernel();
  PS_CHECK(runner != nullptr, "CUDA emulation: {} was called outside a kernel launch", function);
  return *runner;
}

// The dynamic shared memory of the blocks one OS thread runs: exactly the launch's size (so that
// AddressSanitizer sees accesses past it); run_block fills it with 0xFF bytes (NaN as float) at
// the start of every block because CUDA leaves shared memory uninitialised.
struct DynamicSharedMemory {
  explicit DynamicSharedMemory(std::size_t bytes) : size(bytes) {
    if (bytes == 0) return;
    data = static_cast<std::byte*>(::operator new (bytes, std::align_val_t{256}));
  }
  ~DynamicSharedMemory() {
    if (data != nullptr) ::operator delete (data, std::align_val_t{256});
  }
  DynamicSharedMemory(const DynamicSharedMemory&) = delete;
  DynamicSharedMemory& operator=(const DynamicSharedMemory&) = delete;
  std::size_t size = 0;
  std::byte* data = nullptr;
};

std::mutex schedule_mutex;
std::optional<Schedule> chosen_schedule;
std::string schedule_error;  // PILLARSEG_EMU_SCHEDULE's parse error, when it has one

}  // namespace

Schedule parse_schedule(std::string_view text, std::string_view source) {
  if (text == "forward") return Schedule{};
  if (text == "reverse") return Schedule{Schedule::Order::Reverse, 0};
  constexpr std::string_view kRandom = "random:";
  if (text.starts_with(kRandom)) {
    const std::string_view digits = text.substr(kRandom.size());
    std::uint64_t seed = 0;
    bool valid = !digits.empty() && digits.size() <= 20;
    for (const char c : digits) {
      if (c < '0' || c > '9') {
        valid = false;
        break;
      }
      const auto digit = static_cast<std::uint64_t>(c - '0');
      if (seed > (std::numeric_limits<std::uint64_t>::max() - digit) / 10) {
        valid = false;
        break;
      }
      seed = seed * 10 + digit;
    }
    if (valid) return Schedule{Schedule::Order::Random, seed};
  }
  throw Error(fmt::format(
      "{}='{}': expected forward, reverse or random:SEED (SEED a decimal number below 2^64), "
      "the order in which the CUDA emulation runs a block's threads between synchronisation points",
      source, text));
}

std::string to_string(const Schedule& schedule) {
  switch (schedule.order) {
    case Schedule::Order::Forward:
      return "forward";
    case Schedule::Order::Reverse:
      return "reverse";
    case Schedule::Order::Random:
      return fmt::format("random:{}", schedule.seed);
  }
  return "?";
}

Schedule current_schedule() {
  const std::lock_guard lock(schedule_mutex);
  if (!chosen_schedule && schedule_error.empty()) {
    const char* variable = std::getenv("PILLARSEG_EMU_SCHEDULE");
    if (variable == nullptr || *variable == '\0') {
      chosen_schedule = Schedule{};
    } else {
      try {
        chosen_schedule = parse_schedule(variable, "PILLARSEG_EMU_SCHEDULE");
      } catch (const Error& e) {
        schedule_error = e.what();
      }
    }
  }
  if (!chosen_schedule) throw Error(schedule_error);
  return *chosen_schedule;
}

void set_schedule(const Schedule& schedule) {
  const std::lock_guard lock(schedule_mutex);
  chosen_schedule = schedule;
  schedule_error.clear();
}

void run_grid(const GridLaunch& launch) {
  PS_CHECK(BlockRunner::in_kernel() == nullptr,
           "CUDA emulation: a kernel launched a kernel (dynamic parallelism is not emulated)");
  const Schedule schedule = current_schedule();
  const std::uint64_t blocks = std::uint64_t{launch.grid.x} * launch.grid.y * launch.grid.z;
  const BlockOrder block_order(schedule, blocks);
  const int threads = static_cast<int>(
      std::min<std::uint64_t>(static_cast<std::uint64_t>(omp_get_max_threads()), blocks));
  if (threads <= 1) {
    BlockRunner& runner = BlockRunner::for_this_thread();
    DynamicSharedMemory shared(launch.dynamic_shared_bytes);
    for (std::uint64_t b = 0; b < blocks; ++b)
      runner.run_block(launch, schedule, block_order(b), shared.data);
    return;
  }

  // Blocks are independent, so their order must not change results (the schedule permutes it to
  // show where it does); a failure stops the others early and the failure of the block that comes
  // first in the schedule's order is reported.
  std::atomic<bool> failed{false};
  std::mutex failure_mutex;
  std::exception_ptr failure;
  std::uint64_t failed_block = std::numeric_limits<std::uint64_t>::max();
  const auto chunk = static_cast<int>(
      std::max<std::uint64_t>(1, blocks / (static_cast<std::uint64_t>(threads) * 8)));
  const auto block_count = static_cast<std::int64_t>(blocks);
#pragma omp parallel num_threads(threads)
  {
    std::unique_ptr<DynamicSharedMemory> shared;
#pragma omp for schedule(dynamic, chunk)
    for (std::int64_t b = 0; b < block_count; ++b) {
      if (failed.load(std::memory_order_relaxed)) continue;
      try {
        if (!shared) shared = std::make_unique<DynamicSharedMemory>(launch.dynamic_shared_bytes);
        BlockRunner::for_this_thread().run_block(
            launch, schedule, block_order(static_cast<std::uint64_t>(b)), shared->data);
      } catch (...) {
        const std::lock_guard lock(failure_mutex);
        if (static_cast<std::uint64_t>(b) < failed_block) {
          failed_block = static_cast<std::uint64_t>(b);
          failure = std::current_exception();
        }
        failed.store(true, std::memory_order_relaxed);
      }
    }
  }
  if (failure) std::rethrow_exception(failure);
}

int block_barrier(int predicate) {
  return runner_in_kernel("__syncthreads()").barrier(predicate);
}

std::uint64_t warp_shuffle(WarpOp op, unsigned mask, std::uint64_t value, int lane_argument,
                           int width) {
  return runner_in_kernel(op_name(op)).warp_exchange(op, mask, value, lane_argument, width);
}

unsigned warp_vote(WarpOp op, unsigned mask, int predicate) {
  return static_cast<unsigned>(
      runner_in_kernel(op_name(op))
          .warp_exchange(op, mask, predicate != 0 ? 1u : 0u, 0, kWarpSize));
}

void warp_matrix(const char* name, unsigned mask, void* lane_block,
                 void (*compute)(void* const* lanes)) {
  runner_in_kernel(name).warp_exchange(
      WarpOp::Matrix, mask,
      static_cast<std::uint64_t>(reinterpret_cast<std::uintptr_t>(lane_block)), 0, kWarpSize,
      compute);
}

std::byte* dynamic_shared_memory() {
  return runner_in_kernel("dynamic_shared()").dynamic_shared();
}

AsyncCopies& thread_async_copies() {
  return runner_in_kernel("cp.async").async_copies();
}

namespace {
std::atomic<std::uint64_t> mma_count{0}, cp_async_byte_count{0}, mma_k32_count{0};
}  // namespace

InstructionCounts instruction_counts() {
  return InstructionCounts{mma_count.load(std::memory_order_relaxed),
                           cp_async_byte_count.load(std::memory_order_relaxed),
                           mma_k32_count.load(std::memory_order_relaxed)};
}

void count_mma_m16n8k16() {
  mma_count.fetch_add(1, std::memory_order_relaxed);
}

void count_mma_m16n8k32() {
  mma_k32_count.fetch_add(1, std::memory_order_relaxed);
}

void count_cp_async_bytes(std::uint64_t bytes) {
  cp_async_byte_count.fetch_add(bytes, std::memory_order_relaxed);
}

}  // namespace pillarseg::emu
