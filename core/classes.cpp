#include "core/classes.hpp"

#include <algorithm>

#include "core/hash.hpp"

namespace pillarseg {

ClassTable ClassTable::defaults() {
  struct Row {
    const char* name;
    std::vector<uint32_t> raw;
    Rgb color;
    int weight;
  };
  const Row rows[kNumClassIds] = {
      {"unlabeled", {0, 1, 52, 99}, {0, 0, 0}, 0},
      {"vehicle", {10, 13, 16, 18, 20, 252, 256, 257, 258, 259}, {0, 0, 255}, 5},
      {"person", {30, 254}, {255, 30, 30}, 5},
      {"two-wheel", {11, 15}, {30, 60, 150}, 5},
      {"rider", {31, 32, 253, 255}, {150, 30, 90}, 5},
      {"road", {40, 60}, {255, 0, 255}, 1},
      {"sidewalk", {48}, {75, 0, 75}, 1},
      {"other-ground", {44, 49}, {255, 150, 255}, 1},
      {"building", {50}, {255, 200, 0}, 1},
      {"object", {51, 80, 81}, {255, 120, 50}, 1},
      {"vegetation", {70}, {0, 175, 0}, 1},
      {"trunk", {71}, {135, 60, 0}, 1},
      {"terrain", {72}, {150, 240, 80}, 1},
  };
  ClassTable t;
  for (int id = 0; id < kNumClassIds; ++id) {
    t.names_[id] = rows[id].name;
    t.raw_ids_[id] = rows[id].raw;
    t.colors_[id] = rows[id].color;
    t.gt_weights_[id] = rows[id].weight;
  }
  t.moving_ids_ = {252, 253, 254, 255, 256, 257, 258, 259};
  t.rebuild_lut();
  return t;
}

void ClassTable::rebuild_lut() {
  lut_.fill(kUnlabeled);
  moving_.fill(0);
  for (int id = 1; id < kNumClassIds; ++id)
    for (uint32_t raw : raw_ids_[id]) lut_[raw & 0xFFFFu] = static_cast<uint8_t>(id);
  for (uint32_t raw : moving_ids_) moving_[raw & 0xFFFFu] = 1;
}

void ClassTable::set_raw_ids(int id, std::vector<uint32_t> raw) {
  for (int other = 0; other < kNumClassIds; ++other) {
    if (other == id) continue;
    auto& v = raw_ids_[other];
    std::erase_if(v, [&](uint32_t x) { return std::find(raw.begin(), raw.end(), x) != raw.end(); });
  }
  raw_ids_.at(static_cast<size_t>(id)) = std::move(raw);
  rebuild_lut();
}

void ClassTable::set_moving_ids(std::vector<uint32_t> raw) {
  moving_ids_ = std::move(raw);
  rebuild_lut();
}

uint64_t ClassTable::fingerprint() const {
  Hasher h;
  for (int id = 0; id < kNumClassIds; ++id) {
    h.add(names_[id]);
    h.add(gt_weights_[id]);
    h.add(colors_[id].r), h.add(colors_[id].g), h.add(colors_[id].b);
  }
  h.add_bytes(lut_.data(), lut_.size());
  h.add_bytes(moving_.data(), moving_.size());
  return h.digest();
}

}  // namespace pillarseg
