// The memory a request may still take, checked before a big allocation (DESIGN.md section 9:
// "sizes are checked before allocating; an impossible request says what it would need"), so
// that a grid, batch or point count too large for the machine is a pillarseg::Error saying what
// it would need instead of an out-of-memory kill; and the 32-bit index limits, checked likewise.
//
// The host's budget is the least of:
//   - MemAvailable of /proc/meminfo (what can be allocated without swapping; the physical RAM,
//     sysconf(_SC_PHYS_PAGES) x page size, where /proc/meminfo cannot be read);
//   - the cgroup's limit less its usage (cgroup v2 memory.max - memory.current, v1
//     memory.limit_in_bytes - memory.usage_in_bytes, for this process's cgroup and each one above
//     it), its inactive page cache counted as free;
//   - RLIMIT_AS less the process's address space (VmSize), RLIMIT_DATA less its data (VmData),
//     when set.
// PILLARSEG_MEMORY_LIMIT=BYTES in the environment replaces it (a byte count, or with a K, M, G or
// T suffix, powers of 1024: "512M", "8G"): for tests, or to keep a run below what the machine
// has. It is then every backend's budget (Backend::memory_budget()).
#pragma once

#include <cstdint>
#include <initializer_list>
#include <optional>
#include <string>
#include <string_view>

namespace pillarseg {

struct MemoryBudget {
  uint64_t bytes = 0;       // what may still be allocated
  std::string description;  // what bounds it: "MemAvailable 21.9 GiB of 23.5 GiB RAM"
};

// The host's budget (see the file comment), read anew at every call.
MemoryBudget host_memory_budget();
// PILLARSEG_MEMORY_LIMIT when set; throws pillarseg::Error for a value that is not a byte count.
std::optional<MemoryBudget> memory_limit_override();

// Throws pillarseg::Error "<what> would need 37.5 GiB, more than the 23.4 GiB of memory
// available (MemAvailable ...)" when `bytes` exceed the budget.
void require_memory(uint64_t bytes, std::string_view what, const MemoryBudget& budget);
void require_memory(uint64_t bytes, std::string_view what);  // against host_memory_budget()

// "512 B", "1.5 KiB", "37.5 GiB".
std::string format_bytes(uint64_t bytes);

// The product / sum, or pillarseg::Error "<what>: 40000 x 40000 x ... overflows 64-bit
// arithmetic" (a negative factor is an error too).
uint64_t checked_product(std::initializer_list<int64_t> factors, std::string_view what);
uint64_t checked_sum(std::initializer_list<uint64_t> terms, std::string_view what);

// The largest count that int32 indices hold.
inline constexpr int64_t kMaxInt32Index = 2147483647;
// Throws pillarseg::Error "<what> = <product> overflows the 32-bit <indices> (at most
// 2147483647)" when the product of the factors exceeds kMaxInt32Index.
void require_int32_count(std::initializer_list<int64_t> factors, std::string_view what,
                         std::string_view indices);

}  // namespace pillarseg
