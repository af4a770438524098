// pillarseg for C++: RAII over the C API of pillarseg.h (same engine, same ABI, same thread
// rules): one Segmenter per model and device, move-only, closed by its destructor; failures are
// pillarseg::Error exceptions carrying the C API's message.
//
//   pillarseg::Options options;
//   options.device = "cuda";
//   pillarseg::Segmenter segmenter("model.safetensors", options);
//   std::vector<uint8_t> labels = segmenter.segment(points);  // points: x y z r per point
//   // labels[iy * segmenter.width() + ix]: class id of cell (ix, iy)
#pragma once

#include <algorithm>
#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "pillarseg/pillarseg.h"

namespace pillarseg {

class Error : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct Options {
  std::string device = "cpu";  // "cpu", "cuda" or "emu" (the CUDA backend on the CPU emulation)
  int threads = 0;             // CPU threads, 0 = all
  int cuda_device = 0;
  bool mask_unobserved = false;  // cells no ray observed: class 0, probabilities 0
  std::string convolution = "own";  // with "cuda": "own", "cudnn" or "cublas"
  std::string precision = "fp32";   // "fp32", "bf16" or "fp16" (see pillarseg_options)
  // The sensor's points into the model's frame and scale (see pillarseg_options).
  bool reflectance_none = false;
  float reflectance_scale = 1, reflectance_offset = 0;
  bool reflectance_clip = true;
  std::array<double, 16> transform = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};  // row-major 4 x 4
  int flips = 1;  // test-time mirrors: 1, 2 or 4 copies of the scan averaged (see pillarseg_options)
};

class Segmenter {
 public:
  // weights: a safetensors checkpoint (a weights-only one too); config: a run config YAML
  // whose grid and model settings win, or empty.
  explicit Segmenter(const std::string& weights, const Options& options = {},
                     const std::string& config = {}) {
    pillarseg_options o;
    pillarseg_default_options(&o);
    o.device = options.device.c_str();
    o.threads = options.threads;
    o.cuda_device = options.cuda_device;
    o.mask_unobserved = options.mask_unobserved ? 1 : 0;
    o.convolution = options.convolution.c_str();
    o.precision = options.precision.c_str();
    o.reflectance_none = options.reflectance_none ? 1 : 0;
    o.reflectance_scale = options.reflectance_scale;
    o.reflectance_offset = options.reflectance_offset;
    o.reflectance_clip = options.reflectance_clip ? 1 : 0;
    std::copy(options.transform.begin(), options.transform.end(), o.transform);
    o.flips = options.flips;
    char error[1024];
    handle_ = pillarseg_open(weights.c_str(), config.empty() ? nullptr : config.c_str(), &o, error,
                             sizeof error);
    if (handle_ == nullptr) throw Error(error);
    pillarseg_grid(handle_, &width_, &height_);
  }
  ~Segmenter() { pillarseg_close(handle_); }
  Segmenter(Segmenter&& other) noexcept
      : handle_(std::exchange(other.handle_, nullptr)), width_(other.width_), height_(other.height_) {}
  Segmenter& operator=(Segmenter&& other) noexcept {
    if (this != &other) {
      pillarseg_close(handle_);
      handle_ = std::exchange(other.handle_, nullptr);
      width_ = other.width_;
      height_ = other.height_;
    }
    return *this;
  }
  Segmenter(const Segmenter&) = delete;
  Segmenter& operator=(const Segmenter&) = delete;

  int width() const { return width_; }    // cells along x (columns)
  int height() const { return height_; }  // cells along y (rows)
  std::size_t cells() const { return static_cast<std::size_t>(width_) * static_cast<std::size_t>(height_); }
  std::string device() const { return pillarseg_device_name(handle_); }
  std::string precision() const { return pillarseg_precision(handle_); }
  pillarseg_segmenter* handle() const { return handle_; }

  // xyzr: 4 floats per point. labels: cells() bytes; probabilities: 12 * cells() floats or null.
  void segment(const float* xyzr, std::size_t num_points, std::uint8_t* labels,
               float* probabilities = nullptr) {
    char error[1024];
    if (pillarseg_segment(handle_, xyzr, num_points, labels, probabilities, error, sizeof error) != 0)
      throw Error(error);
  }
  // xyzr.size() must be a multiple of 4; returns the label map (height rows of width ids).
  std::vector<std::uint8_t> segment(const std::vector<float>& xyzr) {
    if (xyzr.size() % 4 != 0)
      throw Error("pillarseg::Segmenter::segment: " + std::to_string(xyzr.size()) +
                  " floats are not whole points (4 floats each: x, y, z, reflectance)");
    std::vector<std::uint8_t> labels(cells());
    segment(xyzr.data(), xyzr.size() / 4, labels.data());
    return labels;
  }

 private:
  pillarseg_segmenter* handle_ = nullptr;
  int width_ = 0, height_ = 0;
};

// "vehicle" .. "terrain" for 1..12, "unlabeled" for 0; empty for any other id.
inline std::string class_name(int class_id) {
  const char* name = pillarseg_class_name(class_id);
  return name ? name : "";
}

inline std::string version() { return pillarseg_version(); }

// A point file's points, 4 floats each (x, y, z, reflectance as stored); format empty: by the
// extension, else "kitti", "pcd", "ply", "npy" or "nuscenes".
inline std::vector<float> read_points(const std::string& path, const std::string& format = {}) {
  float* points = nullptr;
  std::size_t n = 0;
  char error[1024];
  if (pillarseg_read_points(path.c_str(), format.empty() ? nullptr : format.c_str(), &points, &n, error,
                            sizeof error) != 0)
    throw Error(error);
  const std::unique_ptr<float, void (*)(void*)> owned(points, pillarseg_free);
  return std::vector<float>(owned.get(), owned.get() + 4 * n);
}

}  // namespace pillarseg
