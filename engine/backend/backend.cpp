#include "engine/backend/backend.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <vector>

#include <fmt/format.h>

#include "core/error.hpp"

namespace pillarseg {

namespace {
constexpr size_t kAlignment = 64;
size_t align_up(size_t n) { return (n + kAlignment - 1) / kAlignment * kAlignment; }
// The factories of "cuda" and "emu", in this order.
constexpr std::array<const char*, 2> kFactoryDevices = {"cuda", "emu"};
std::array<std::atomic<BackendFactory>, 2> backend_factories{};

std::atomic<BackendFactory>& factory_slot(const std::string& device) {
  for (size_t i = 0; i < kFactoryDevices.size(); ++i)
    if (device == kFactoryDevices[i]) return backend_factories[i];
  PS_FAIL("set_backend_factory: device must be cuda or emu, got '{}'", device);
}
}  // namespace

double Backend::clock_ms() {
  synchronize();
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

std::unique_ptr<CapturedGraph> Backend::capture(const std::function<void()>&) {
  PS_FAIL("backend {} cannot capture graphs (check supports_capture() first)", name());
}

const char* precision_name(Precision p) {
  switch (p) {
    case Precision::F32: return "fp32";
    case Precision::BF16: return "bf16";
    case Precision::F16: return "fp16";
    case Precision::I8: return "int8";
  }
  return "?";
}

Precision precision_of(DType dtype) {
  switch (dtype) {
    case DType::F32:
      return Precision::F32;
    case DType::BF16:
      return Precision::BF16;
    case DType::F16:
      return Precision::F16;
    case DType::I8:
      return Precision::I8;
    default:
      break;
  }
  PS_FAIL("{} is not the dtype of a precision", dtype_name(dtype));
}

DType dtype_of(Precision p) {
  switch (p) {
    case Precision::BF16:
      return DType::BF16;
    case Precision::F16:
      return DType::F16;
    case Precision::I8:
      return DType::I8;
    case Precision::F32:
      break;
  }
  return DType::F32;
}

Precision parse_precision(const std::string& text, const std::string& what) {
  if (text == "fp32") return Precision::F32;
  if (text == "bf16") return Precision::BF16;
  if (text == "fp16") return Precision::F16;
  if (text == "int8") return Precision::I8;
  PS_FAIL("{}: expected fp32, bf16, fp16 or int8, got '{}'", what, text);
}

bool Backend::supports_precision(Precision p, std::string* why_not) const {
  if (p == Precision::F32) return true;
  if (why_not != nullptr)
    *why_not = fmt::format("the {} backend computes in FP32 only ({} convolutions run on the CUDA backend)", name(),
                           precision_name(p));
  return false;
}

int64_t Backend::prepared_conv_transform_elements(const Shape&, int, DType) const { return 0; }
DType Backend::prepared_conv_dtype(const Shape&, int, bool, DType half) const { return half; }
void Backend::require_precision(Precision p) const {
  std::string why;
  PS_CHECK(supports_precision(p, &why), "backend {}: --precision {}: {}", name(), precision_name(p), why);
}
void Backend::prepare_conv_weights(const Ref&, const Ref*, const BatchNormRefs*, const TensorRef& prepared, Ref&,
                                   const TensorRef&, const Ref*) {
  PS_FAIL("backend {}: no {} convolutions (supports_precision)", name(), dtype_name(prepared.dtype));
}
void Backend::prepare_conv_transpose_weights(const Ref&, const Ref*, const TensorRef& prepared, Ref&, const Ref*) {
  PS_FAIL("backend {}: no {} convolutions (supports_precision)", name(), dtype_name(prepared.dtype));
}
void Backend::conv2d_prepared_forward(const TensorRef&, const TensorRef& prepared, const TensorRef&, const Ref&,
                                      const Shape&, int, bool, const TensorRef&, const Ref*, Int8Input) {
  PS_FAIL("backend {}: no {} convolutions (supports_precision)", name(), dtype_name(prepared.dtype));
}
void Backend::conv_transpose2d_prepared_forward(const TensorRef&, const TensorRef& prepared, const Ref&, const Shape&,
                                                const TensorRef&, const Ref*, Int8Input) {
  PS_FAIL("backend {}: no {} convolutions (supports_precision)", name(), dtype_name(prepared.dtype));
}
void Backend::convert(const Ref&, const TensorRef& y) {
  PS_FAIL("backend {}: no {} activations (supports_precision)", name(), dtype_name(y.dtype));
}
bool Backend::supports_training_precision(Precision p, std::string* why_not) const {
  if (p == Precision::F32) return true;
  if (why_not != nullptr) {
    *why_not = fmt::format("backend {} trains in fp32 only ({} training runs on --device cuda)", name(),
                           precision_name(p));
  }
  return false;
}
void Backend::begin_sum_over_replicas(Ref& values, Replicas& replicas) {
  if (device() == Device::Cpu) {
    replicas.begin_sum(values.data, values.numel());
    return;
  }
  std::vector<float> host(static_cast<size_t>(values.numel()));
  download(host.data(), values.data, values.bytes());
  replicas.begin_sum(host.data(), values.numel());
  replicas.end_sums();
  upload(values.data, host.data(), values.bytes());
}
void Backend::end_sums_over_replicas(Replicas& replicas) {
  if (device() == Device::Cpu) replicas.end_sums();
}
bool Backend::supports_synchronized_batchnorm(std::string* why_not) const {
  if (why_not != nullptr) {
    *why_not = fmt::format("backend {} computes BatchNorm statistics over its own batch only (no synchronised "
                           "BatchNorm), which data-parallel training needs",
                           name());
  }
  return false;
}
MemoryBudget Backend::memory_budget() const { return host_memory_budget(); }

void Arena::reserve(size_t bytes) {
  measuring_ = false;
  if (bytes <= capacity_ && base_) return;
  release();
  capacity_ = std::max<size_t>(align_up(bytes), kAlignment);
  base_ = backend_->allocate(capacity_);
  used_ = 0;
}

void Arena::release() noexcept {
  if (base_) backend_->deallocate(base_);
  base_ = nullptr;
  capacity_ = 0;
  used_ = 0;
}

void* Arena::take_bytes(size_t bytes) {
  const size_t offset = used_;
  used_ += align_up(bytes);
  if (measuring_) return nullptr;
  PS_CHECK(used_ <= capacity_, "arena overflow: {} bytes requested, capacity {} (plan the arena before use)", used_,
           capacity_);
  return static_cast<char*>(base_) + offset;
}

void set_backend_factory(const std::string& device, BackendFactory factory) {
  factory_slot(device).store(factory);
}

std::string available_devices() {
  std::string devices = "cpu";
  for (size_t i = 0; i < kFactoryDevices.size(); ++i)
    if (backend_factories[i].load() != nullptr) devices += std::string(", ") + kFactoryDevices[i];
  return devices;
}

std::unique_ptr<Backend> make_backend(const std::string& device, const BackendOptions& options) {
  if (device == "cpu") {
    PS_CHECK(options.convolution == "own",
             "--conv {} needs --device cuda (the CPU backend has one convolution)", options.convolution);
    return make_cpu_backend();
  }
  PS_CHECK(device == "cuda" || device == "emu", "--device must be cpu, cuda or emu, got '{}'", device);
  const BackendFactory factory = factory_slot(device).load();
  PS_CHECK(factory != nullptr, "--device {}: {}", device,
           device == "cuda" ? "this build has no CUDA backend (configure with the CUDA toolkit installed, so that "
                              "CMake finds nvcc); use --device cpu, or --device emu for the CUDA backend on the "
                              "CPU emulation"
                            : "this program has no emulated CUDA backend (link pillarseg_cuda_backend_emu); use "
                              "--device cpu");
  return factory(options);
}

int64_t pillar_rows(int64_t num_points, const GridSpec& grid, int max_pillars) {
  PS_CHECK(num_points >= 0 && max_pillars >= 0,
           "pillar_rows: expected M >= 0 points and P >= 0 pillars, given M = {}, P = {}", num_points,
           max_pillars);
  return max_pillars > 0 ? int64_t{max_pillars} : std::min(num_points, grid.cells());
}

}  // namespace pillarseg
