// TensorBoard event files beside metrics.jsonl (OpenPCDet's habit): RUN_DIR/events.out.tfevents.
// 0.pillarseg, in the TFRecord format TensorBoard reads - records of (uint64 length, masked
// CRC-32C of the length, a tf.Event protocol buffer, masked CRC-32C of it) - with the Event and
// Summary messages encoded here by hand (wall_time = 1, step = 2, file_version = 3, summary = 5;
// Summary.value = 1; Value.tag = 1, Value.simple_value = 2).
#pragma once

#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>
#include <string_view>
#include <vector>

namespace pillarseg {

// CRC-32C (Castagnoli), and TFRecord's mask of it.
std::uint32_t crc32c(std::string_view bytes);
std::uint32_t masked_crc32c(std::string_view bytes);

// One scalar of an event file as read back.
struct EventScalar {
  std::string tag;
  std::int64_t step = 0;
  float value = 0;
  double wall_time = 0;
};
// The scalars of an event file, checking every record's CRCs; stops at the first record that is
// cut short or corrupt (what a killed writer leaves) and says so in `truncated`.
std::vector<EventScalar> read_event_scalars(const std::filesystem::path& path,
                                            bool* truncated = nullptr);

class EventWriter {
 public:
  // RUN_DIR/events.out.tfevents.0.pillarseg. A fresh run starts the file (its file_version
  // record); on resume the records of steps after `keep_through_step` (and a cut-short tail) are
  // dropped first and the file rewritten atomically, so that no step appears twice.
  EventWriter(const std::filesystem::path& run_dir, bool resume, std::int64_t keep_through_step);
  static std::filesystem::path path_in(const std::filesystem::path& run_dir);

  void scalar(const std::string& tag, std::int64_t step, double value);
  void flush();

 private:
  void record(const std::string& event);
  std::filesystem::path path_;
  std::ofstream out_;
};

}  // namespace pillarseg
