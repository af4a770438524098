#include "engine/util/image.hpp"

#include <png.h>

#include <cstdio>
#include <ostream>

#include "core/error.hpp"
#include "core/io.hpp"

namespace pillarseg {

namespace {

void write_png(const std::filesystem::path& path, int width, int height, int color_type, int channels,
               const uint8_t* pixels) {
  PS_CHECK(width > 0 && height > 0, "{}: cannot write an empty {}x{} image", path.string(), width, height);
  write_file_atomic(path, [&](std::ostream& out) {
    png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
    PS_CHECK(png, "{}: png_create_write_struct failed", path.string());
    png_infop info = png_create_info_struct(png);
    if (!info || setjmp(png_jmpbuf(png))) {
      png_destroy_write_struct(&png, &info);
      PS_FAIL("{}: libpng failed while encoding", path.string());
    }
    png_set_write_fn(
        png, &out,
        [](png_structp p, png_bytep data, png_size_t n) {
          static_cast<std::ostream*>(png_get_io_ptr(p))->write(reinterpret_cast<const char*>(data),
                                                               static_cast<std::streamsize>(n));
        },
        [](png_structp p) { static_cast<std::ostream*>(png_get_io_ptr(p))->flush(); });
    png_set_IHDR(png, info, static_cast<png_uint_32>(width), static_cast<png_uint_32>(height), 8, color_type,
                 PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
    png_set_compression_level(png, 3);
    png_write_info(png, info);
    const size_t stride = static_cast<size_t>(width) * channels;
    for (int y = 0; y < height; ++y) png_write_row(png, const_cast<png_bytep>(pixels + y * stride));
    png_write_end(png, nullptr);
    png_destroy_write_struct(&png, &info);
  });
}

}  // namespace

void write_png_rgb(const std::filesystem::path& path, const ImageRgb& image) {
  PS_CHECK(image.pixels.size() == static_cast<size_t>(image.width) * image.height * 3,
           "{}: image buffer has {} bytes, expected {}x{}x3", path.string(), image.pixels.size(), image.width,
           image.height);
  write_png(path, image.width, image.height, PNG_COLOR_TYPE_RGB, 3, image.pixels.data());
}

void write_png_gray(const std::filesystem::path& path, int width, int height, const std::vector<uint8_t>& pixels) {
  PS_CHECK(pixels.size() == static_cast<size_t>(width) * height, "{}: image buffer has {} bytes, expected {}x{}",
           path.string(), pixels.size(), width, height);
  write_png(path, width, height, PNG_COLOR_TYPE_GRAY, 1, pixels.data());
}

ImageRgb read_png_rgb(const std::filesystem::path& path) {
  png_image img{};
  img.version = PNG_IMAGE_VERSION;
  PS_CHECK(png_image_begin_read_from_file(&img, path.c_str()), "{}: not a readable PNG: {}", path.string(),
           img.message);
  img.format = PNG_FORMAT_RGB;
  ImageRgb out(static_cast<int>(img.width), static_cast<int>(img.height));
  if (!png_image_finish_read(&img, nullptr, out.pixels.data(), 0, nullptr)) {
    png_image_free(&img);
    PS_FAIL("{}: PNG decoding failed: {}", path.string(), img.message);
  }
  return out;
}

}  // namespace pillarseg
