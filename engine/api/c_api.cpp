// The C API of include/pillarseg/pillarseg.h over ScanSegmenter (engine/pipeline/segmenter.hpp).
// Every entry point catches every exception and turns it into the caller's error message: nothing
// unwinds across the C boundary. Only the pillarseg_* functions are exported from the shared
// library (engine/api/exports.map).
#include "pillarseg/pillarseg.h"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <memory>
#include <new>
#include <optional>
#include <span>
#include <string>

#include "core/classes.hpp"
#include "core/error.hpp"
#include "core/memory_budget.hpp"
#include "core/point.hpp"
#include "engine/cuda/install.hpp"
#include "engine/data/input_mapping.hpp"
#include "engine/data/point_formats.hpp"
#include "engine/pipeline/segmenter.hpp"

struct pillarseg_segmenter {
  std::unique_ptr<pillarseg::ScanSegmenter> engine;
  std::string device_name;
};

namespace {

// Copies `message` into error[0 .. error_size), truncated and terminated.
void write_error(char* error, size_t error_size, const std::string& message) {
  if (error == nullptr || error_size == 0) return;
  const size_t n = std::min(message.size(), error_size - 1);
  std::memcpy(error, message.data(), n);
  error[n] = '\0';
}

void clear_error(char* error, size_t error_size) { write_error(error, error_size, ""); }

// Runs fn; returns true, or false with the reason in `error` for any exception.
template <class Fn>
bool guarded(const char* function, char* error, size_t error_size, Fn&& fn) {
  try {
    fn();
    clear_error(error, error_size);
    return true;
  } catch (const pillarseg::Error& e) {
    write_error(error, error_size, std::string(function) + ": " + e.what());
  } catch (const std::bad_alloc&) {
    write_error(error, error_size, std::string(function) + ": out of memory");
  } catch (const std::exception& e) {
    write_error(error, error_size, std::string(function) + ": unexpected error: " + e.what());
  } catch (...) {
    write_error(error, error_size, std::string(function) + ": unexpected error of an unknown type");
  }
  return false;
}

// The CUDA backends this library holds, installed once.
void install_backends() {
  static const bool installed = [] {
#if defined(PILLARSEG_WITH_CUDA_BACKEND)
    pillarseg::install_cuda_backend();
#endif
    pillarseg::install_emulated_cuda_backend();
    return true;
  }();
  static_cast<void>(installed);
}

// Whether the caller's options struct (of options->struct_size bytes) holds `member`.
#define PS_OPTION_PRESENT(options, member) \
  ((options)->struct_size >= offsetof(pillarseg_options, member) + sizeof((options)->member))

// The parts of the input mapping the options set: the reflectance when it is none, scaled or
// offset; the transform when it is not the identity (an older, shorter struct sets neither).
struct InputOverrides {
  std::optional<pillarseg::ReflectanceMapping> reflectance;
  std::optional<pillarseg::Pose> transform;
};

InputOverrides input_overrides(const pillarseg_options& o) {
  InputOverrides out;
  if (PS_OPTION_PRESENT(&o, reflectance_clip)) {
    PS_CHECK(std::isfinite(o.reflectance_scale) && std::isfinite(o.reflectance_offset),
             "options->reflectance_scale and reflectance_offset must be finite, got {} and {}", o.reflectance_scale,
             o.reflectance_offset);
    pillarseg::ReflectanceMapping r;
    if (o.reflectance_none != 0) {
      r.kind = pillarseg::ReflectanceMapping::Kind::None;
      out.reflectance = r;
    } else if (o.reflectance_scale != 1.0f || o.reflectance_offset != 0.0f) {
      r.kind = pillarseg::ReflectanceMapping::Kind::Scale;
      r.scale = o.reflectance_scale;
      r.offset = o.reflectance_offset;
      r.clip = o.reflectance_clip != 0;
      out.reflectance = r;
    }
  }
  if (PS_OPTION_PRESENT(&o, transform)) {
    const pillarseg::Pose t = pillarseg::transform_from_numbers(o.transform, "options->transform");
    if (t != pillarseg::Pose::Identity()) out.transform = t;
  }
  return out;
}

}  // namespace

extern "C" {

const char* pillarseg_version(void) { return PILLARSEG_VERSION_STRING; }

void pillarseg_init_options(pillarseg_options* options, size_t struct_size) {
  if (options == nullptr || struct_size < sizeof(options->struct_size)) return;
  pillarseg_options defaults{};
  defaults.struct_size = std::min(struct_size, sizeof(pillarseg_options));
  defaults.device = "cpu";
  defaults.threads = 0;
  defaults.cuda_device = 0;
  defaults.mask_unobserved = 0;
  defaults.convolution = "own";
  defaults.precision = "fp32";
  defaults.reflectance_none = 0;
  defaults.reflectance_scale = 1.0f;
  defaults.reflectance_offset = 0.0f;
  defaults.reflectance_clip = 1;
  for (int i = 0; i < 16; ++i) defaults.transform[i] = i % 5 == 0 ? 1.0 : 0.0;
  defaults.flips = 1;
  std::memcpy(options, &defaults, defaults.struct_size);
}

// The exported function of version 0.3 (the header maps the name to pillarseg_init_options):
// its callers' struct ends after `precision`.
#undef pillarseg_default_options
void pillarseg_default_options(pillarseg_options* options) {
  pillarseg_init_options(options, offsetof(pillarseg_options, reflectance_none));
}

pillarseg_segmenter* pillarseg_open(const char* weights_path, const char* config_path,
                                    const pillarseg_options* options, char* error,
                                    size_t error_size) {
  pillarseg_segmenter* opened = nullptr;
  guarded("pillarseg_open", error, error_size, [&] {
    PS_CHECK(weights_path != nullptr && weights_path[0] != '\0', "weights_path is NULL or empty");
    pillarseg_options defaults;
    pillarseg_init_options(&defaults, sizeof defaults);
    const pillarseg_options* o = options ? options : &defaults;
    PS_CHECK(o->struct_size >= offsetof(pillarseg_options, device) + sizeof(o->device),
             "options->struct_size is {}: set it with pillarseg_default_options()", o->struct_size);
    pillarseg::SegmenterOptions so;
    so.device = o->device ? o->device : "cpu";
    if (PS_OPTION_PRESENT(o, threads)) {
      PS_CHECK(o->threads >= 0, "options->threads must be >= 0 (0: all), got {}", o->threads);
      so.threads = o->threads;
    }
    if (PS_OPTION_PRESENT(o, cuda_device)) {
      PS_CHECK(o->cuda_device >= 0, "options->cuda_device must be >= 0, got {}", o->cuda_device);
      so.backend.cuda_device = o->cuda_device;
    }
    if (PS_OPTION_PRESENT(o, mask_unobserved)) so.mask_unobserved = o->mask_unobserved != 0;
    if (PS_OPTION_PRESENT(o, convolution) && o->convolution != nullptr) so.backend.convolution = o->convolution;
    if (PS_OPTION_PRESENT(o, precision) && o->precision != nullptr)
      so.precision = pillarseg::parse_precision(o->precision, "options->precision");
    if (PS_OPTION_PRESENT(o, flips)) {
      PS_CHECK(o->flips == 1 || o->flips == 2 || o->flips == 4,
               "options->flips must be 1 (the scan alone), 2 (and y -> -y) or 4 (and x -> -x, and both), got {}",
               o->flips);
      so.flips = o->flips;
    }
    PS_CHECK(so.device == "cpu" || so.device == "cuda" || so.device == "emu",
             "options->device must be \"cpu\", \"cuda\" or \"emu\", got \"{}\"", so.device);
    const InputOverrides input = input_overrides(*o);
    install_backends();
    auto s = std::make_unique<pillarseg_segmenter>();
    s->engine = pillarseg::open_segmenter(weights_path, config_path ? config_path : "", so);
    pillarseg::InputMapping mapping = s->engine->input_mapping();
    if (input.reflectance) mapping.reflectance = *input.reflectance;
    if (input.transform) mapping.transform = *input.transform;
    s->engine->set_input_mapping(mapping);
    s->device_name = s->engine->backend().name();
    opened = s.release();
  });
  return opened;
}

void pillarseg_grid(const pillarseg_segmenter* s, int* width, int* height) {
  if (width) *width = s ? s->engine->model().grid.width() : 0;
  if (height) *height = s ? s->engine->model().grid.height() : 0;
}

void pillarseg_grid_geometry(const pillarseg_segmenter* s, double* x_min, double* y_min,
                             double* cell) {
  const pillarseg::GridSpec grid = s ? s->engine->model().grid : pillarseg::GridSpec{};
  if (x_min) *x_min = s ? grid.x_min : 0.0;
  if (y_min) *y_min = s ? grid.y_min : 0.0;
  if (cell) *cell = s ? grid.cell : 0.0;
}

const char* pillarseg_device_name(const pillarseg_segmenter* s) {
  return s ? s->device_name.c_str() : "";
}

const char* pillarseg_precision(const pillarseg_segmenter* s) {
  return s ? pillarseg::precision_name(s->engine->net().precision()) : "";
}

const char* pillarseg_class_name(int class_id) {
  static const pillarseg::ClassTable table = pillarseg::ClassTable::defaults();
  if (class_id < 0 || class_id > pillarseg::kNumClasses) return nullptr;
  return table.name(class_id).c_str();
}

int pillarseg_segment(pillarseg_segmenter* s, const float* points_xyzr, size_t num_points,
                      uint8_t* labels, float* probabilities, char* error, size_t error_size) {
  const bool ok = guarded("pillarseg_segment", error, error_size, [&] {
    PS_CHECK(s != nullptr, "the segmenter is NULL (pillarseg_open failed?)");
    PS_CHECK(points_xyzr != nullptr || num_points == 0, "points_xyzr is NULL for {} points", num_points);
    PS_CHECK(labels != nullptr, "labels is NULL: it must hold width x height = {} bytes",
             s->engine->model().grid.cells());
    // Checked before the points are touched: a count beyond the 32-bit point indices, or (in
    // the pipeline's reserve) beyond the memory, is an error, never a read past the caller's buffer.
    constexpr size_t kMaxPoints = pillarseg::kMaxInt32Index - 1;
    PS_CHECK(num_points <= kMaxPoints, "{} points overflow the 32-bit point indices (at most {} a scan)", num_points,
             kMaxPoints);
    const std::span<const pillarseg::Point> points(reinterpret_cast<const pillarseg::Point*>(points_xyzr),
                                                   num_points);
    s->engine->segment(points, labels, probabilities);
  });
  return ok ? 0 : 1;
}

void pillarseg_close(pillarseg_segmenter* s) {
  // A destructor of the engine cannot throw (buffers and handles free themselves).
  delete s;
}

int pillarseg_read_points(const char* path, const char* format, float** points_xyzr, size_t* num_points,
                          char* error, size_t error_size) {
  if (points_xyzr) *points_xyzr = nullptr;
  if (num_points) *num_points = 0;
  const bool ok = guarded("pillarseg_read_points", error, error_size, [&] {
    PS_CHECK(path != nullptr && path[0] != '\0', "path is NULL or empty");
    PS_CHECK(points_xyzr != nullptr && num_points != nullptr, "points_xyzr and num_points must not be NULL");
    const pillarseg::PointFormat f =
        format ? pillarseg::parse_point_format(format, "format") : pillarseg::PointFormat::FromExtension;
    const pillarseg::Scan scan = pillarseg::read_points(path, f);
    const size_t bytes = scan.points.size() * sizeof(pillarseg::Point);
    // At least one byte: a successful read always hands back memory to free.
    void* memory = std::malloc(std::max<size_t>(bytes, 1));
    if (memory == nullptr) throw std::bad_alloc();
    if (bytes > 0) std::memcpy(memory, scan.points.data(), bytes);
    *points_xyzr = static_cast<float*>(memory);
    *num_points = scan.points.size();
  });
  return ok ? 0 : 1;
}

void pillarseg_free(void* memory) { std::free(memory); }

}  // extern "C"
