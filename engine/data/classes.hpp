// ClassTable: raw SemanticKITTI label -> one of the 12 classes (0 = unlabeled), the moving
// flag (raw ids 252-259), the ground-truth weights w_k and the render colors. The table is
// data: defaults() is DESIGN.md's table, from_yaml() reads an override (configs/classes.yaml).
#pragma once

#include <array>
#include <cstdint>
#include <string>
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
  // YAML: {classes: [{id, name, raw: [...], color: [r,g,b], gt_weight}], moving: [...]}.
  // Classes not listed keep their defaults; raw ids of a listed class replace its defaults.
  static ClassTable from_yaml(const std::string& path);

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
