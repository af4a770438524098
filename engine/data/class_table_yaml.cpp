#include "engine/data/class_table_yaml.hpp"

#include <yaml-cpp/yaml.h>

#include <vector>

#include "core/error.hpp"

namespace pillarseg {

ClassTable load_class_table(const std::string& path) {
  ClassTable t = ClassTable::defaults();
  YAML::Node root;
  try {
    root = YAML::LoadFile(path);
  } catch (const YAML::Exception& e) {
    PS_FAIL("class table {}: cannot read YAML: {}", path, e.what());
  }
  try {
    if (root["classes"]) {
      PS_CHECK(root["classes"].IsSequence(), "class table {}: 'classes' must be a list", path);
      for (const auto& node : root["classes"]) {
        const int id = node["id"].as<int>();
        PS_CHECK(id >= 0 && id < kNumClassIds, "class table {}: class id {} is outside 0..{}", path,
                 id, kNumClassIds - 1);
        if (node["name"]) t.set_name(id, node["name"].as<std::string>());
        if (node["raw"]) {
          std::vector<uint32_t> raw = node["raw"].as<std::vector<uint32_t>>();
          for (uint32_t r : raw)
            PS_CHECK(r <= 0xFFFFu, "class table {}: raw id {} of class {} exceeds 65535", path, r, id);
          t.set_raw_ids(id, std::move(raw));
        }
        if (node["color"]) {
          auto c = node["color"].as<std::vector<int>>();
          PS_CHECK(c.size() == 3, "class table {}: color of class {} needs 3 values, got {}", path, id,
                   c.size());
          for (int v : c)
            PS_CHECK(v >= 0 && v <= 255, "class table {}: color value {} of class {} is outside 0..255",
                     path, v, id);
          t.set_color(id, {static_cast<uint8_t>(c[0]), static_cast<uint8_t>(c[1]), static_cast<uint8_t>(c[2])});
        }
        if (node["gt_weight"]) {
          const int weight = node["gt_weight"].as<int>();
          PS_CHECK(weight >= 0, "class table {}: gt_weight of class {} is negative", path, id);
          t.set_gt_weight(id, weight);
        }
      }
    }
    if (root["moving"]) t.set_moving_ids(root["moving"].as<std::vector<uint32_t>>());
  } catch (const YAML::Exception& e) {
    PS_FAIL("class table {}: {}", path, e.what());
  }
  return t;
}

}  // namespace pillarseg
