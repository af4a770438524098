// Sizes checked before allocating (DESIGN.md section 9): the machine's memory budget and its
// PILLARSEG_MEMORY_LIMIT override, checked arithmetic, the model's memory estimate (by hand for a
// small config, and against the lifetime planner's placement for several variants), and the
// errors that a grid, batch or point count too large for the memory or for 32-bit indices gives
// at parse time, model construction, planning, a scan's buffers and a .bin file read - each
// before anything is allocated.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "core/host_memory.hpp"
#include "core/memory_budget.hpp"
#include "core/point.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/model/graph.hpp"  // memory_report() in failure messages
#include "engine/model/memory_estimate.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "engine/model/run_config.hpp"
#include "engine/pipeline/segmenter.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using pillarseg::test::error_of;
using ::testing::HasSubstr;

namespace {

// Sets an environment variable for the scope, restoring what was there.
class ScopedEnv {
 public:
  ScopedEnv(const char* name, const char* value) : name_(name) {
    if (const char* old = std::getenv(name)) old_ = old;
    if (value)
      setenv(name, value, 1);
    else
      unsetenv(name);
  }
  ~ScopedEnv() {
    if (old_)
      setenv(name_, old_->c_str(), 1);
    else
      unsetenv(name_);
  }
  ScopedEnv(const ScopedEnv&) = delete;
  ScopedEnv& operator=(const ScopedEnv&) = delete;

 private:
  const char* name_;
  std::optional<std::string> old_;
};

// A grid of w x h cells of `cell` metres from the origin.
GridSpec grid_of(int w, int h, double cell = 1.0) {
  GridSpec g;
  g.x_min = 0, g.x_max = w * cell, g.y_min = 0, g.y_max = h * cell;
  g.z_min = -1, g.z_max = 1, g.voxel_z = 0.5;  // 4 layers
  g.cell = cell;
  return g;
}

// 0.01 m cells over x, y in [-200, 200): 40000 x 40000 cells.
const char* kHugeGridConfig = "grid: {x: [-200, 200], y: [-200, 200], cell: 0.01}\n";

}  // namespace

TEST(MemoryBudget, FormatsBytes) {
  EXPECT_EQ(format_bytes(0), "0 B");
  EXPECT_EQ(format_bytes(1023), "1023 B");
  EXPECT_EQ(format_bytes(1024), "1.0 KiB");
  EXPECT_EQ(format_bytes(1536), "1.5 KiB");
  EXPECT_EQ(format_bytes(uint64_t{75} << 29), "37.5 GiB");
  EXPECT_EQ(format_bytes(uint64_t{3} << 40), "3.0 TiB");
  EXPECT_EQ(format_bytes(~uint64_t{0}), "16.0 EiB");
}

TEST(MemoryBudget, OverrideParsesByteCounts) {
  {
    const ScopedEnv env("PILLARSEG_MEMORY_LIMIT", "512M");
    EXPECT_EQ(host_memory_budget().bytes, uint64_t{512} << 20);
    EXPECT_EQ(host_memory_budget().description, "PILLARSEG_MEMORY_LIMIT=512M");
  }
  for (const auto& [text, bytes] :
       std::vector<std::pair<const char*, uint64_t>>{{"1000", 1000},
                                                     {"8G", uint64_t{8} << 30},
                                                     {"2GiB", uint64_t{2} << 30},
                                                     {"3k", 3072},
                                                     {"1TB", uint64_t{1} << 40}}) {
    const ScopedEnv env("PILLARSEG_MEMORY_LIMIT", text);
    EXPECT_EQ(host_memory_budget().bytes, bytes) << text;
  }
  for (const char* bad : {"abc", "8X", "-1", "1.5G", "99999999999T", "8 G"}) {
    const ScopedEnv env("PILLARSEG_MEMORY_LIMIT", bad);
    EXPECT_THAT(error_of([] { host_memory_budget(); }), HasSubstr("PILLARSEG_MEMORY_LIMIT="))
        << bad;
  }
}

TEST(MemoryBudget, MachineBudgetIsAtMostThePhysicalMemory) {
  const ScopedEnv env("PILLARSEG_MEMORY_LIMIT", nullptr);
  const MemoryBudget budget = host_memory_budget();
  const uint64_t physical = static_cast<uint64_t>(sysconf(_SC_PHYS_PAGES)) *
                            static_cast<uint64_t>(sysconf(_SC_PAGE_SIZE));
  EXPECT_GT(budget.bytes, 0u);
  EXPECT_LE(budget.bytes, physical);
  EXPECT_THAT(budget.description, HasSubstr("MemAvailable"));
}

TEST(MemoryBudget, RequireMemorySaysWhatWouldBeNeeded) {
  const MemoryBudget budget{uint64_t{1} << 30, "a test's"};
  EXPECT_NO_THROW(require_memory(uint64_t{1} << 30, "exactly the budget", budget));
  EXPECT_EQ(error_of([&] { require_memory(uint64_t{75} << 29, "the thing", budget); }),
            "the thing would need 37.5 GiB, more than the 1.0 GiB of memory available (a test's)");
  const ScopedEnv env("PILLARSEG_MEMORY_LIMIT", "1M");
  EXPECT_THAT(error_of([] { require_memory(uint64_t{2} << 20, "two MiB"); }),
              HasSubstr("two MiB would need 2.0 MiB, more than the 1.0 MiB of memory available "
                        "(PILLARSEG_MEMORY_LIMIT=1M)"));
}

TEST(MemoryBudget, CheckedArithmetic) {
  EXPECT_EQ(checked_product({70000, 70000, 2}, "cells"), 9800000000u);
  EXPECT_EQ(checked_product({}, "nothing"), 1u);
  EXPECT_EQ(error_of([] {
              checked_product({int64_t{1} << 32, int64_t{1} << 32}, "the canvas");
            }),
            "the canvas: 4294967296 x 4294967296 overflows 64-bit arithmetic");
  EXPECT_THAT(error_of([] { checked_product({3, -2}, "rows"); }), HasSubstr("negative"));
  EXPECT_EQ(checked_sum({1, 2, 3}, "sum"), 6u);
  EXPECT_THAT(error_of([] {
                checked_sum({~uint64_t{0}, 1}, "the total");
              }),
              HasSubstr("overflows 64-bit"));

  EXPECT_NO_THROW(require_int32_count({46340, 46340}, "a square grid", "cell indices"));
  EXPECT_NO_THROW(require_int32_count({kMaxInt32Index}, "the largest", "indices"));
  EXPECT_NO_THROW(require_int32_count({int64_t{1} << 62, 0}, "nothing", "indices"));
  EXPECT_EQ(error_of([] {
              require_int32_count({70000, 70000, 2}, "grid of 70000 x 70000 cells x batch 2",
                                  "cell indices");
            }),
            "grid of 70000 x 70000 cells x batch 2 = 9800000000 overflows the 32-bit cell indices "
            "(at most 2147483647)");
  EXPECT_THAT(error_of([] {
                require_int32_count({int64_t{1} << 62, int64_t{1} << 62}, "huge", "indices");
              }),
              HasSubstr("huge = 2.13e+37 overflows the 32-bit indices"));
}

// A 16 x 8 grid, depth 2, b = 4, C = 4, N = 3, P = 8, bilinear: the parameters and the pillar
// buffers by hand; the activations are the block the model's planner places for the same graph.
TEST(ModelMemoryEstimate, HandComputedForASmallConfig) {
  ModelConfig c;
  c.grid = grid_of(16, 8);
  c.max_points_per_pillar = 3, c.max_pillars = 8, c.pillar_channels = 4, c.base_width = 4,
  c.depth = 2;
  c.validate();
  // Trainable values: PFN 40 + BN 8; down1 296 + 16 + 584 + 16; down2 584 + 16 + 584 + 16;
  // up1 1160 + 16 + 292 + 8; up2 292 + 8 + 148 + 8; head 60: 4152. Buffers (running mean and
  // variance): 2 (4 + 8 + 8 + 8 + 8 + 8 + 4 + 4 + 4) = 112. The model agrees:
  auto backend = make_cpu_backend();
  PillarSegNet net(c, *backend);
  EXPECT_EQ(net.parameters().num_trainable(), 4152);
  EXPECT_EQ(net.parameters().num_buffer_values(), 112);
  const ModelMemoryEstimate eval = estimate_model_memory(c, 1, false);
  EXPECT_EQ(eval.parameters, 4u * (4152 + 112));
  // Pillar rows: 8 a sample + a quarter, at least 1024; a row (3 x 10 + 3 + 4) floats.
  EXPECT_EQ(eval.pillars, 4u * 37 * 1024);
  net.prepare(1, 8, false);
  EXPECT_EQ(eval.activations, net.activation_bytes()) << net.graph(false).memory_report();
  // The canvas (4 x 128 floats) and the pillar buffers are alive together: the block holds them.
  EXPECT_GE(eval.activations, 4u * 4 * 128 + eval.pillars);
  EXPECT_EQ(eval.total(), eval.parameters + eval.activations);

  const ModelMemoryEstimate train = estimate_model_memory(c, 2, true);
  EXPECT_EQ(train.parameters, 4u * (4 * 4152 + 112));
  // A row adds the arg-max and the output's gradient (the backends keep no (N, C) working memory
  // a pillar): 37 + 4 + 4.
  EXPECT_EQ(train.pillars, 4u * 45 * 1024);
  net.prepare(2, 16, true);
  EXPECT_EQ(train.activations, net.activation_bytes()) << net.graph(true).memory_report();
  EXPECT_THAT(train.breakdown(), HasSubstr("parameters 65.3 KiB, activations "));
  EXPECT_THAT(train.breakdown(), HasSubstr(" (pillar buffers 180.0 KiB of them)"));
}

// The estimate is what the lifetime planner places (the pillar buffers at the rows the estimate
// assumes), and the parameters what the model allocates, for every variant of the model.
TEST(ModelMemoryEstimate, IsWhatThePlannerPlaces) {
  struct Case {
    const char* name;
    ModelConfig config;
    int batch;
  };
  std::vector<Case> cases;
  const auto add = [&](const char* name, const std::function<void(ModelConfig&)>& change,
                       int batch = 1) {
    ModelConfig c;
    c.grid = grid_of(256, 128);
    c.max_points_per_pillar = 4, c.max_pillars = 2000, c.pillar_channels = 8, c.base_width = 8;
    change(c);
    cases.push_back({name, c, batch});
  };
  add("bilinear depth 4", [](ModelConfig&) {});
  add(
      "bilinear depth 4 batch 2", [](ModelConfig&) {}, 2);
  add("transposed depth 3", [](ModelConfig& c) { c.transposed = true, c.depth = 3; });
  add("2d occupancy, depth 2",
      [](ModelConfig& c) { c.occupancy = OccupancyInput::Observability2D, c.depth = 2; });
  add("3d occupancy, grid map",
      [](ModelConfig& c) { c.occupancy = OccupancyInput::Occupancy3D, c.grid_map_input = true; });
  add(
      "grid map only, odd grid",
      [](ModelConfig& c) {
        c.pillar_input = false, c.grid_map_input = true, c.grid = grid_of(253, 131);
      },
      3);
  add(
      "all pillars (P = 0), depth 5", [](ModelConfig& c) { c.max_pillars = 0, c.depth = 5; }, 2);
  add("wide: b = 32, C = 64", [](ModelConfig& c) { c.base_width = 32, c.pillar_channels = 64; });
  for (const Case& k : cases) {
    for (const bool training : {false, true}) {
      SCOPED_TRACE(fmt::format("{}, {}", k.name, training ? "training" : "eval"));
      auto backend = make_cpu_backend();
      PillarSegNet net(k.config, *backend);
      const ModelConfig& c = k.config;
      const int64_t rows = c.max_pillars > 0
                               ? int64_t{c.max_pillars} * k.batch
                               : std::min(c.grid.cells(), kTypicalScanPoints) * k.batch;
      net.prepare(k.batch, c.pillar_input ? rows : 0, training);
      const ModelMemoryEstimate e = estimate_model_memory(c, k.batch, training);
      EXPECT_EQ(e.activations, net.activation_bytes()) << e.breakdown();
      // The parameters as the model holds them: values and buffers (no gradients yet).
      if (!training) {
        EXPECT_NEAR(static_cast<double>(e.parameters),
                    static_cast<double>(net.parameters().allocated_bytes()),
                    0.01 * static_cast<double>(e.parameters) + 4096);
      }
    }
  }
}

TEST(ModelMemoryEstimate, HugeGridFailsBeforeAllocating) {
  // 0.01 m cells over 400 m: 40000 x 40000 = 1.6e9 cells (within the 32-bit cell indices for one
  // sample, not for the default training batch of 2, which the parse rejects on any machine).
  EXPECT_THAT(
      error_of([] { parse_run_config(kHugeGridConfig, "huge.yaml"); }),
      HasSubstr(
          "huge.yaml: train.batch_size 2: grid of 40000 x 40000 cells x batch 2 (up to a pillar a "
          "cell "
          "with model.max_pillars 0) = 3200000000 overflows the 32-bit pillar indices (at most "
          "2147483647)"));
  const RunConfig config =
      parse_run_config(std::string(kHugeGridConfig) + "train: {batch_size: 1}\n", "huge.yaml");
  // Building the model checks the evaluation's memory first: terabytes, more than any machine
  // here has (an allocation would have failed with another message, or been killed).
  auto backend = make_cpu_backend();
  const std::string error = error_of([&] { PillarSegNet net(config.model, *backend); });
  EXPECT_THAT(error, HasSubstr("evaluation of PillarSegNet on a 40000 x 40000 grid of 0.01 m cells "
                               "(batch 1) would need "));
  EXPECT_THAT(error, HasSubstr(" TiB, more than the "));
  EXPECT_THAT(error, HasSubstr("; the estimate: parameters 65.8 MiB, activations "));
  EXPECT_THAT(
      error_of([&] { check_model_memory(config.model, 1, true, backend->memory_budget()); }),
      HasSubstr("training of PillarSegNet on a 40000 x 40000 grid"));
  // The same under a low limit: the paper's grid needs more than 64 MiB.
  const ScopedEnv env("PILLARSEG_MEMORY_LIMIT", "64M");
  EXPECT_THAT(
      error_of([&] { PillarSegNet net(ModelConfig{}, *backend); }),
      HasSubstr(
          "evaluation of PillarSegNet on a 1000 x 500 grid of 0.1 m cells (batch 1) would need "));
  EXPECT_THAT(error_of([&] { PillarSegNet net(ModelConfig{}, *backend); }),
              HasSubstr("more than the 64.0 MiB of memory available (PILLARSEG_MEMORY_LIMIT=64M; "
                        "the estimate: "));
}

TEST(ModelMemoryEstimate, ThirtyTwoBitIndexOverflows) {
  // 0.01 m cells over 700 m: 70000 x 70000 cells, beyond the 32-bit flat cell indices.
  EXPECT_THAT(error_of([] {
                parse_run_config("grid: {x: [-350, 350], y: [-350, 350], cell: 0.01}\n", "g.yaml");
              }),
              HasSubstr("g.yaml: grid of 70000 x 70000 cells = 4900000000 overflows the 32-bit "
                        "cell indices (at most "
                        "2147483647)"));
  // An axis whose cell count does not even fit an int.
  EXPECT_THAT(error_of([] { parse_run_config("grid: {cell: 0.000000001}\n", "a.yaml"); }),
              HasSubstr("a.yaml: grid: the x range / 1e-09 m = 1e+11 cells along x overflows the "
                        "32-bit cell indices"));
  EXPECT_THAT(
      error_of([] { parse_run_config("grid: {voxel_z: 0.000000001}\n", "z.yaml"); }),
      HasSubstr(
          "z.yaml: grid: the z range / 1e-09 m = 4e+09 layers overflows the 32-bit cell indices"));
  // Channel counts: b 2^depth.
  EXPECT_THAT(
      error_of([] { parse_run_config("model: {base_width: 1073741824, depth: 2}\n", "b.yaml"); }),
      HasSubstr("model.base_width 1073741824 x 2^depth 2 = 4294967296 overflows the 32-bit channel "
                "counts"));
  // Pillar rows of a batch and the PFN's point rows.
  ModelConfig c;
  c.max_pillars = 30000;
  EXPECT_NO_THROW(check_index_limits(c, 2));
  EXPECT_EQ(error_of([&] { check_index_limits(c, 4000); }),
            "model.max_pillars 30000 x batch 4000 x 20 points a pillar = 2400000000 overflows the "
            "32-bit point rows "
            "of the PFN (at most 2147483647)");
  EXPECT_THAT(error_of([&] { check_index_limits(c, 80000); }),
              HasSubstr("model.max_pillars 30000 x batch 80000 = 2400000000 overflows the 32-bit "
                        "pillar indices"));
  c.max_pillars = 0;
  EXPECT_THAT(error_of([&] { check_index_limits(c, 5000); }),
              HasSubstr("grid of 1000 x 500 cells x batch 5000 (up to a pillar a cell with "
                        "model.max_pillars 0) = "
                        "2500000000 overflows the 32-bit pillar indices"));
  EXPECT_THAT(error_of([] { parse_run_config("train: {batch_size: 5000}\n", "t.yaml"); }),
              HasSubstr("t.yaml: train.batch_size 5000: grid of 1000 x 500 cells x batch 5000"));
}

TEST(ModelMemoryEstimate, PlanIsCheckedExactlyAndFailsCleanly) {
  ModelConfig c;
  c.grid = grid_of(64, 32);
  c.max_points_per_pillar = 4, c.max_pillars = 100, c.pillar_channels = 8, c.base_width = 8,
  c.depth = 3;
  auto backend = make_cpu_backend();
  PillarSegNet net(c, *backend);
  net.prepare(1, 100, false);
  const size_t eval_bytes = net.activation_bytes();
  {
    const ScopedEnv env("PILLARSEG_MEMORY_LIMIT", "100k");
    EXPECT_THAT(error_of([&] { net.prepare(2, 200, true); }),
                HasSubstr("the training step of PillarSegNet on a 64 x 32 grid (batch 2, 1024 "
                          "pillar rows) would need "));
    // Within the limit the same plan stays usable.
    EXPECT_NO_THROW(net.prepare(1, 100, false));
    EXPECT_EQ(net.activation_bytes(), eval_bytes);
  }
  // After a refused plan, the next one is placed and allocated afresh.
  EXPECT_NO_THROW(net.prepare(2, 200, true));
  EXPECT_GT(net.activation_bytes(), eval_bytes);
  // The PFN's point rows of a batch are int32.
  EXPECT_THAT(error_of([&] { net.prepare(1, int64_t{1} << 30, false); }),
              HasSubstr("1073741824 pillars x 4 points a pillar = 4294967296 overflows the 32-bit "
                        "point rows of the PFN"));
}

TEST(ModelMemoryEstimate, ScanPointCountsAreCheckedBeforeThePointsAreRead) {
  ModelConfig c;
  c.grid = grid_of(32, 16, 0.5);
  c.max_points_per_pillar = 4, c.pillar_channels = 4, c.base_width = 4, c.depth = 2;
  ScanSegmenter segmenter(c, make_cpu_backend());
  std::vector<uint8_t> labels(static_cast<size_t>(c.grid.cells()));
  const std::vector<Point> few(10, Point{1.0f, 1.0f, 0.0f, 0.5f});
  // The span claims far more points than the buffer holds: the checks must come before any read.
  const std::span<const Point> too_many(few.data(), size_t{3} << 30);
  EXPECT_THAT(error_of([&] { segmenter.segment(too_many, labels.data()); }),
              HasSubstr("a scan of 3221225472 points overflows the 32-bit point indices (at most "
                        "2147483646 points)"));
  {
    const ScopedEnv env("PILLARSEG_MEMORY_LIMIT", "256M");
    const std::span<const Point> many(few.data(), size_t{1} << 30);
    EXPECT_THAT(error_of([&] { segmenter.segment(many, labels.data()); }),
                HasSubstr("a scan of 1073741824 points (buffers for 1342177280 points, 512 pillar "
                          "rows) would need "));
  }
  // The segmenter still works after the refused scans.
  EXPECT_NO_THROW(segmenter.segment(few, labels.data()));
}

TEST(ModelMemoryEstimate, BinFileLargerThanTheMemoryIsRefusedBeforeReading) {
  const std::filesystem::path dir = pillarseg::test::temp_dir();
  const std::filesystem::path bin = dir / "000000.bin";
  const std::filesystem::path big = dir / "big.bin";
  { std::ofstream(bin, std::ios::binary).flush(); }
  // 256 MiB of zeros, sparse: 16M points, a valid size.
  std::filesystem::resize_file(bin, uint64_t{256} << 20);
  const auto remove_files = [&] {
    for (const auto& entry : std::filesystem::directory_iterator(dir))
      std::filesystem::remove(entry.path());
  };
  {
    const ScopedEnv env("PILLARSEG_MEMORY_LIMIT", "64M");
    const std::string error = error_of([&] { read_scan(bin); });
    EXPECT_THAT(error,
                HasSubstr(bin.string() +
                          ": reading its 16777216 points (268435456 bytes) would need 512.0 MiB, "
                          "more than the 64.0 MiB of memory available"));
    { std::ofstream(dir / "000000.label", std::ios::binary).flush(); }
    std::filesystem::resize_file(dir / "000000.label", uint64_t{256} << 20);
    EXPECT_THAT(
        error_of([&] { read_labels(dir / "000000.label"); }),
        HasSubstr(
            "000000.label: reading its 67108864 labels (268435456 bytes) would need 512.0 MiB"));
  }
  // A size implying 2^31 points or more exceeds the 32-bit point indices whatever the memory.
  { std::ofstream(big, std::ios::binary).flush(); }
  std::error_code sparse;
  std::filesystem::resize_file(big, uint64_t{1} << 35, sparse);
  if (sparse) {
    remove_files();
    GTEST_SKIP() << "no 32 GiB sparse file here: " << sparse.message();
  }
  EXPECT_THAT(error_of([&] { read_scan(big); }),
              HasSubstr("big.bin: 34359738368 bytes are 2147483648 points, which overflows the "
                        "32-bit point indices "
                        "(at most 2147483646 a scan)"));
  remove_files();
}

// Host buffers: a small one on a cache line, a large one (the CPU backend's activation block) on
// a 2 MiB boundary, where the kernel can back it with transparent huge pages; both usable to
// their last byte.
TEST(HostMemory, LargeBuffersOnHugePageBoundariesSmallOnesOnCacheLines) {
  const auto address = [](const void* p) { return reinterpret_cast<std::uintptr_t>(p); };
  void* small = pillarseg::allocate_host(100);
  ASSERT_NE(small, nullptr);
  EXPECT_EQ(address(small) % 64, 0u);
  std::memset(small, 0xA5, 100);
  std::free(small);
  const std::size_t large_bytes = (std::size_t{3} << 20) + 5;
  auto* large = static_cast<unsigned char*>(pillarseg::allocate_host(large_bytes));
  ASSERT_NE(large, nullptr);
  EXPECT_EQ(address(large) % (std::size_t{2} << 20), 0u);
  large[0] = 1, large[large_bytes - 1] = 2;
  EXPECT_EQ(large[0] + large[large_bytes - 1], 3);
  std::free(large);
  // The CPU backend's allocations are these.
  auto backend = pillarseg::make_cpu_backend();
  void* block = backend->allocate(std::size_t{4} << 20);
  EXPECT_EQ(address(block) % (std::size_t{2} << 20), 0u);
  backend->deallocate(block);
}
