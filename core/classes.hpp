// ClassTable: raw SemanticKITTI label -> one of the 12 classes (0 = unlabeled), the moving
// flag (raw ids 252-259), the ground-truth weights w_k and the render colors. The table is
// data: defaults() is DESIGN.md's table; an override file (configs/classes.yaml) is read by
// load_class_table() (engine/data/class_table_yaml.hpp) through the edits below.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

namespace pillarseg {

inline constexpr int kNumClasses = 12;          // vehicle .. terrain; id 0 is unlabeled
inline constexpr int kNumClassIds = kNumClasses + 1;
inline constexpr uint8_t kUnlabeled = 0;

struct Rgb {
  uint8_t r = 0, g = 0, b = 0;
  bool operator==(const Rgb&) const = default;
};

class ClassTable {
 public:
  static ClassTable defaults();

  // Edits; each keeps the table consistent. id in 0..12 (checked by the caller).
  void set_name(int id, std::string name) { names_.at(static_cast<size_t>(id)) = std::move(name); }
  // The raw ids (each <= 65535) of class id, replacing its own; they are taken away from every
  // other class, as a raw id belongs to one class.
  void set_raw_ids(int id, std::vector<uint32_t> raw);
  void set_color(int id, Rgb color) { colors_.at(static_cast<size_t>(id)) = color; }
  void set_gt_weight(int id, int weight) { gt_weights_.at(static_cast<size_t>(id)) = weight; }
  void set_moving_ids(std::vector<uint32_t> raw);

  // Class id 0..12 of a raw .label word (semantic id = v & 0xFFFF).
  uint8_t class_of(uint32_t label) const { return lut_[label & 0xFFFFu]; }
  bool is_moving(uint32_t label) const { return moving_[label & 0xFFFFu] != 0; }

  const std::string& name(int id) const { return names_.at(static_cast<size_t>(id)); }
  Rgb color(int id) const { return colors_.at(static_cast<size_t>(id)); }
  // w_k of the sparse ground-truth rule: 5 for traffic participants, 1 others, 0 unlabeled.
  int gt_weight(int id) const { return gt_weights_.at(static_cast<size_t>(id)); }
  const std::vector<uint32_t>& raw_ids(int id) const { return raw_ids_.at(static_cast<size_t>(id)); }

  // A stable hash of the whole table, part of the ground-truth cache key.
  uint64_t fingerprint() const;

 private:
  void rebuild_lut();

  std::array<uint8_t, 65536> lut_{};
  std::array<uint8_t, 65536> moving_{};
  std::array<std::string, kNumClassIds> names_;
  std::array<Rgb, kNumClassIds> colors_;
  std::array<int, kNumClassIds> gt_weights_{};
  std::array<std::vector<uint32_t>, kNumClassIds> raw_ids_;
  std::vector<uint32_t> moving_ids_;
};

}  // namespace pillarseg
