#include "engine/render/label_map.hpp"

#include "core/error.hpp"
#include "core/io.hpp"

namespace pillarseg {

namespace fs = std::filesystem;

ImageRgb render_label_map(const Tensor<uint8_t>& map, const ClassTable& table) {
  PS_CHECK(map.rank() == 2, "render_label_map: expected an (H, W) map, got shape {}",
           shape_str(map.shape()));
  const int height = static_cast<int>(map.dim(0)), width = static_cast<int>(map.dim(1));
  ImageRgb image(width, height);
  for (int iy = 0; iy < height; ++iy) {
    for (int ix = 0; ix < width; ++ix) {
      const uint8_t k = map(iy, ix);
      PS_CHECK(k < kNumClassIds,
               "render_label_map: cell (iy {}, ix {}) has class id {}, expected 0..{}", iy, ix, k,
               kNumClassIds - 1);
      const Rgb color = table.color(k);
      uint8_t* pixel = image.at(ix, height - 1 - iy);
      pixel[0] = color.r;
      pixel[1] = color.g;
      pixel[2] = color.b;
    }
  }
  return image;
}

void write_label_map(const fs::path& path, const Tensor<uint8_t>& map, const ClassTable& table) {
  const std::string extension = lower_extension(path);
  if (extension == ".png") {
    write_png_rgb(path, render_label_map(map, table));
  } else if (extension == ".u8") {
    PS_CHECK(map.rank() == 2, "{}: expected an (H, W) map, got shape {}", path.string(),
             shape_str(map.shape()));
    write_file_atomic(path, map.data(), static_cast<size_t>(map.numel()));
  } else {
    PS_FAIL("{}: unknown extension '{}', expected .png (color map) or .u8 (raw class ids)",
            path.string(), extension);
  }
}

}  // namespace pillarseg
