// The emulated tests under more than one schedule (DESIGN.md section 6, "GPU truth"): with
// PILLARSEG_EMU_SCHEDULE set (CTest sets it: forward, reverse, random:SEED), every test writes the
// hashes of all it copied back from the emulated device, in order, to
// PILLARSEG_EMU_DIGESTS_DIR/<order>/<Suite.Test> (order: the schedule's name without its seed);
// tests/compare_emu_digests.py then checks that reverse and random read back forward's bits.
// Its object (pillarseg_test_emu_digests, compiled once) is in each emulated test executable,
// so its listener registers itself before main runs.
#include <gtest/gtest.h>

#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <vector>

#include <fmt/format.h>

#include "core/io.hpp"
#include "kernels/emu/emu_runtime.hpp"

namespace {

class CopyDigestListener : public ::testing::EmptyTestEventListener {
 public:
  explicit CopyDigestListener(std::filesystem::path dir) : dir_(std::move(dir)) {}

  void OnTestStart(const ::testing::TestInfo&) override {
    pillarseg::emu::take_copy_digests();
    pillarseg::emu::record_copy_digests(true);
  }

  void OnTestEnd(const ::testing::TestInfo& info) override {
    pillarseg::emu::record_copy_digests(false);
    const std::vector<std::uint64_t> digests = pillarseg::emu::take_copy_digests();
    std::string name = fmt::format("{}.{}", info.test_suite_name(), info.name());
    for (char& c : name) {
      if (c == '/') c = '_';
    }
    std::string text;
    for (const std::uint64_t digest : digests) text += fmt::format("{:016x}\n", digest);
    std::filesystem::create_directories(dir_);
    pillarseg::write_file_atomic(dir_ / name, text.data(), text.size());
  }

 private:
  std::filesystem::path dir_;
};

[[maybe_unused]] const bool registered = [] {
  const char* schedule = std::getenv("PILLARSEG_EMU_SCHEDULE");
  if (schedule != nullptr && *schedule != '\0') {
    const std::string order = std::string(schedule).substr(0, std::string(schedule).find(':'));
    ::testing::UnitTest::GetInstance()->listeners().Append(
        new CopyDigestListener(std::filesystem::path(PILLARSEG_EMU_DIGESTS_DIR) / order));
  }
  return true;
}();

}  // namespace
