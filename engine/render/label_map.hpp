// Label maps (H, W) of class ids 0..12, row iy, column ix: the top-view picture and the files
// `pillarseg gt` and `pillarseg infer` write (.png colors, .u8 raw class ids).
#pragma once

#include <cstdint>
#include <filesystem>

#include "core/classes.hpp"
#include "core/tensor.hpp"
#include "engine/util/image.hpp"

namespace pillarseg {

// Top-view picture of a map (H, W): image width W, height H, pixel (column ix, row H-1-iy),
// so +x (forward) points right and +y (left of the car) up; colors from ClassTable::color.
ImageRgb render_label_map(const Tensor<uint8_t>& map, const ClassTable& table);
// By extension: ".png" the rendered picture, ".u8" the raw class ids, H rows of W bytes
// (row iy, column ix, not flipped). Written atomically.
void write_label_map(const std::filesystem::path& path, const Tensor<uint8_t>& map,
                     const ClassTable& table);

}  // namespace pillarseg
