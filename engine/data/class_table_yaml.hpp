// The class-table override file (configs/classes.yaml): DESIGN.md's table with the classes it
// lists changed.
//   classes: [{id, name, raw: [...], color: [r, g, b], gt_weight}, ...]
//   moving: [raw ids]
// Classes not listed keep their defaults; the raw ids of a listed class replace its own and are
// taken away from every other class.
#pragma once

#include <string>

#include "core/classes.hpp"

namespace pillarseg {

// Throws pillarseg::Error naming `path` and what is wrong (unreadable YAML, a class id outside
// 0..12, a raw id above 65535, a color that is not 3 values in 0..255, a negative gt_weight).
ClassTable load_class_table(const std::string& path);

}  // namespace pillarseg
