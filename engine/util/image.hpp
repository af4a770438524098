// PNG output (libpng): 8-bit RGB or grey images, rows top to bottom, written atomically.
#pragma once

#include <cstdint>
#include <filesystem>
#include <vector>

namespace pillarseg {

struct ImageRgb {
  int width = 0, height = 0;
  std::vector<uint8_t> pixels;  // height rows of width * 3 bytes
  ImageRgb() = default;
  ImageRgb(int w, int h) : width(w), height(h), pixels(static_cast<size_t>(w) * h * 3, 0) {}
  uint8_t* at(int x, int y) { return &pixels[(static_cast<size_t>(y) * width + x) * 3]; }
  const uint8_t* at(int x, int y) const { return &pixels[(static_cast<size_t>(y) * width + x) * 3]; }
};

void write_png_rgb(const std::filesystem::path& path, const ImageRgb& image);
void write_png_gray(const std::filesystem::path& path, int width, int height, const std::vector<uint8_t>& pixels);
// Reads an 8-bit RGB or RGBA PNG (alpha dropped); for tests and tools.
ImageRgb read_png_rgb(const std::filesystem::path& path);

}  // namespace pillarseg
