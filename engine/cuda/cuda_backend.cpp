// CudaBackend (see cuda_backend.hpp): each Backend op checks its Refs' shapes (the API edge),
// works out the kernel's shape struct and calls its launcher on the backend's stream. Refs hold
// device pointers; shapes follow the Backend interface: activations (B, C, H, W), pillar tensors
// (P, N, 10) and (P, C), cells (P, 3), labels (B, H, W).
#include "engine/cuda/cuda_backend.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cstring>

#include "core/error.hpp"
#include "core/ops.hpp"
#include "kernels/adam.cuh"
#include "kernels/batchnorm.cuh"
#include "kernels/common.cuh"
#include "kernels/conv2d.cuh"
#include "kernels/conv2d_mma.cuh"
#include "kernels/conv2d_mma_s8.cuh"
#include "kernels/half_ops.cuh"
#include "kernels/conv_transpose2d.cuh"
#include "kernels/elementwise.cuh"
#include "kernels/grid_map_features.cuh"
#include "kernels/mask_unobserved.cuh"
#include "kernels/maxpool2d.cuh"
#include "kernels/mirror_add.cuh"
#include "kernels/observability_input.cuh"
#include "kernels/pad_concat.cuh"
#include "kernels/pfn.cuh"
#include "kernels/pillar_gather.cuh"
#include "kernels/point_decoration.cuh"
#include "kernels/pad_points.cuh"
#include "kernels/raywalk.cuh"
#include "kernels/reduce.cuh"
#include "kernels/scatter.cuh"
#include "kernels/softmax.cuh"
#include "kernels/upsample_bilinear.cuh"
#if !defined(PILLARSEG_CUDA_EMULATION)
#include "engine/cuda/nccl_sum.hpp"
#endif

namespace pillarseg::inline PILLARSEG_CUDA_NAMESPACE {

namespace {

constexpr size_t kStagingAlignment = 256;

size_t align_staging(size_t bytes) {
  return (bytes + kStagingAlignment - 1) / kStagingAlignment * kStagingAlignment;
}

// (B, C, H, W) seen as B items of C planes of H * W values.
cuda::PlanarShape planar(const Ref& x) {
  return {x.dim(0), x.dim(1), x.dim(2) * x.dim(3)};
}

// A CUDA graph instance, replayed on its backend's stream; valid while the backend's workspaces
// stay where they were at the capture.
class CudaGraph final : public CapturedGraph {
 public:
  CudaGraph(cuda::GraphExec executable, cudaStream_t stream, int64_t& replays,
            const int64_t& generation)
      : executable_(std::move(executable)),
        stream_(stream),
        replays_(replays),
        generation_(generation),
        captured_generation_(generation) {}

  void replay() override {
    PS_CHECK(valid(),
             "CudaBackend: a graph was replayed after a workspace it names moved; record it again");
    executable_.launch(stream_);
    ++replays_;
  }
  bool valid() const override { return generation_ == captured_generation_; }

 private:
  cuda::GraphExec executable_;
  cudaStream_t stream_;
  int64_t& replays_;
  const int64_t& generation_;
  int64_t captured_generation_;
};

// points (M, 4) as the kernels see them.
int64_t point_count(const char* op, const Ref& points) {
  require_rank(op, "points", points, 2);
  PS_CHECK(points.dim(1) == 4, "{}: points must be (M, 4) rows x y z r, got {}", op,
           shape_str(points.shape));
  return points.dim(0);
}

cuda::SensorOrigin sensor_origin(const Eigen::Vector3d& origin) {
  return {origin.x(), origin.y(), origin.z()};
}

}  // namespace

ConvolutionImpl parse_convolution_impl(const std::string& name) {
  if (name == "own") return ConvolutionImpl::Own;
  if (name == "cudnn") return ConvolutionImpl::Cudnn;
  if (name == "cublas") return ConvolutionImpl::Cublas;
  PS_FAIL("--conv must be own, cudnn or cublas, got '{}'", name);
}

const char* convolution_impl_name(ConvolutionImpl impl) {
  switch (impl) {
    case ConvolutionImpl::Own:
      return "own";
    case ConvolutionImpl::Cudnn:
      return "cudnn";
    case ConvolutionImpl::Cublas:
      return "cublas";
  }
  return "unknown";
}

std::string no_cuda_device_message(cudaError_t error, int device_count) {
  const std::string reason = error != cudaSuccess
                                 ? fmt::format("cudaGetDeviceCount failed with {} ({})",
                                               cudaGetErrorName(error), cudaGetErrorString(error))
                                 : fmt::format("the CUDA runtime reports {} devices", device_count);
  return fmt::format("no CUDA device found: {}; use --device cpu", reason);
}

namespace {

// Checks the options and selects the device (before any other runtime object is made on it).
const CudaBackendOptions& selected(const CudaBackendOptions& options) {
  PS_CHECK(options.max_staging_bytes >= kStagingAlignment,
           "CudaBackend: max_staging_bytes must be at least {}, got {}", kStagingAlignment,
           options.max_staging_bytes);
#if defined(PILLARSEG_CUDA_EMULATION)
  PS_CHECK(options.convolution == ConvolutionImpl::Own,
           "CudaBackend: --conv {} needs the GPU build; the emulated CUDA backend has only our own "
           "convolutions (cuDNN and cuBLAS run on a GPU only), use --conv own",
           convolution_impl_name(options.convolution));
#endif
  int devices = 0;
  const cudaError_t counted = cudaGetDeviceCount(&devices);
  if (counted != cudaSuccess || devices < 1) {
    static_cast<void>(cudaGetLastError());  // later checks start clean
    PS_FAIL("{}", no_cuda_device_message(counted, devices));
  }
  PS_CHECK(options.device >= 0 && options.device < devices,
           "CudaBackend: CUDA device {} does not exist; the runtime reports {} device(s), 0..{}",
           options.device, devices, devices - 1);
  PS_CUDA_CHECK(cudaSetDevice(options.device));
  return options;
}

}  // namespace

CudaBackend::CudaBackend(const CudaBackendOptions& options) : options_(selected(options)) {
  cudaDeviceProp properties;
  PS_CUDA_CHECK(cudaGetDeviceProperties(&properties, options_.device));
  name_ = fmt::format("{}:{} ({}{})", kCudaBackendDevice, options_.device, properties.name,
                      options_.convolution == ConvolutionImpl::Own
                          ? std::string()
                          : fmt::format(", {} convolutions",
                                        convolution_impl_name(options_.convolution)));
  workspace_.sum_of_squares = cuda::DeviceBuffer<double>(cuda::kSumOfSquaresPartials + 1);
  workspace_.loss_partials = cuda::DeviceBuffer<cuda::LossPartial>(cuda::kLossPartials);
  workspace_.loss_result = cuda::DeviceBuffer<cuda::LossResult>(1);
#if !defined(PILLARSEG_CUDA_EMULATION)
  if (options_.convolution != ConvolutionImpl::Own) {
    vendor_conv_ = cuda::make_vendor_conv2d(options_.convolution, options_.vendor);
    stats_.vendor_conv = vendor_conv_->stats();
  }
#endif
  stats_.device_allocations += 3;
  stats_.workspace_bytes = workspace_.sum_of_squares.bytes() + workspace_.loss_partials.bytes() +
                           workspace_.loss_result.bytes();
}

CudaBackend::~CudaBackend() {
  // Nothing may be in flight when the memory goes; a failure here leaves nothing to report to.
  static_cast<void>(cudaStreamSynchronize(stream_.get()));
}

void CudaBackend::make_current() { PS_CUDA_CHECK(cudaSetDevice(options_.device)); }

Backend::Counters CudaBackend::counters() const {
  Counters c;
  c.allocations = stats_.device_allocations + stats_.pinned_allocations;
  c.bytes_uploaded = stats_.bytes_uploaded;
  c.bytes_downloaded = stats_.bytes_downloaded;
  c.graphs_captured = stats_.graphs_captured;
  c.graph_replays = stats_.graph_replays;
#if defined(PILLARSEG_CUDA_EMULATION)
  const emu::InstructionCounts issued = emu::instruction_counts();
  c.tensor_core_flops = static_cast<int64_t>(issued.tensor_core_flops());
  c.async_copy_bytes = static_cast<int64_t>(issued.cp_async_bytes);
#endif
  return c;
}

// ---- memory ----

void* CudaBackend::allocate(size_t bytes) {
  require_not_capturing("allocate");
  void* p = nullptr;
  PS_CUDA_CHECK(cudaMalloc(&p, std::max<size_t>(bytes, 1)));
  ++stats_.device_allocations;
  return p;
}

MemoryBudget CudaBackend::memory_budget() const {
#if defined(PILLARSEG_CUDA_EMULATION)
  return Backend::memory_budget();
#else
  if (std::optional<MemoryBudget> forced = memory_limit_override()) return *forced;
  PS_CUDA_CHECK(cudaSetDevice(options_.device));
  size_t free_bytes = 0, total_bytes = 0;
  PS_CUDA_CHECK(cudaMemGetInfo(&free_bytes, &total_bytes));
  return MemoryBudget{free_bytes, fmt::format("{} free of {} on {}", format_bytes(free_bytes),
                                              format_bytes(total_bytes), name_)};
#endif
}

void CudaBackend::deallocate(void* p) noexcept {
  // cudaFree waits for the device; it fails only for a context that is already broken.
  static_cast<void>(cudaFree(p));
}

void CudaBackend::upload(void* dst, const void* host_src, size_t bytes) {
  require_not_capturing("upload");
  stats_.bytes_uploaded += static_cast<int64_t>(bytes);
  const auto* src = static_cast<const char*>(host_src);
  auto* out = static_cast<char*>(dst);
  while (bytes > 0) {
    const size_t piece = std::min(bytes, options_.max_staging_bytes);
    void* slot = staging_slot(piece);
    std::memcpy(slot, src, piece);
    PS_CUDA_CHECK(cudaMemcpyAsync(out, slot, piece, cudaMemcpyHostToDevice, stream_.get()));
    src += piece, out += piece, bytes -= piece;
  }
}

void CudaBackend::download(void* host_dst, const void* src, size_t bytes) {
  require_not_capturing("download");
  if (bytes == 0) return;
  stats_.bytes_downloaded += static_cast<int64_t>(bytes);
  const auto* from = static_cast<const char*>(src);
  auto* out = static_cast<char*>(host_dst);
  while (bytes > 0) {
    const size_t piece = std::min(bytes, options_.max_staging_bytes);
    void* pinned = readback_buffer(piece);
    PS_CUDA_CHECK(cudaMemcpyAsync(pinned, from, piece, cudaMemcpyDeviceToHost, stream_.get()));
    wait_for_stream();
    std::memcpy(out, pinned, piece);
    from += piece, out += piece, bytes -= piece;
  }
}

void CudaBackend::fill_zero(void* dst, size_t bytes) {
  if (bytes == 0) return;
  PS_CUDA_CHECK(cudaMemsetAsync(dst, 0, bytes, stream_.get()));
}

void CudaBackend::synchronize() {
  require_not_capturing("synchronize");
  wait_for_stream();
}

void CudaBackend::wait_for_stream() {
  PS_CUDA_CHECK(cudaStreamSynchronize(stream_.get()));
  staging_used_ = 0;
}

void CudaBackend::require_not_capturing(const char* op) const {
  PS_CHECK(!capturing_,
           "CudaBackend::{} while a graph is being captured: a graph may hold device work only "
           "(upload inputs before the capture, download after the replay)",
           op);
}

void* CudaBackend::staging_slot(size_t bytes) {
  const size_t needed = align_staging(bytes);
  if (staging_used_ + needed > staging_.bytes()) {
    const size_t interval_bytes = staging_used_ + needed;
    wait_for_stream();  // the copies out of the staging buffer are done: all of it is free
    const size_t limit = align_staging(options_.max_staging_bytes);
    if (staging_.bytes() < limit) {
      // Doubling at least: a run of growing uploads reallocates only a few times.
      const size_t capacity = std::min(std::max(interval_bytes, 2 * staging_.bytes()), limit);
      stats_.staging_bytes -= staging_.bytes();
      staging_ = cuda::PinnedBuffer();
      staging_ = cuda::PinnedBuffer(capacity);
      stats_.staging_bytes += capacity;
      ++stats_.pinned_allocations;
    }
  }
  void* slot = static_cast<char*>(staging_.data()) + staging_used_;
  staging_used_ += needed;
  return slot;
}

void* CudaBackend::readback_buffer(size_t bytes) {
  if (bytes > readback_.bytes()) {
    readback_ = cuda::PinnedBuffer();
    readback_ = cuda::PinnedBuffer(bytes);
    stats_.readback_bytes = bytes;
    ++stats_.pinned_allocations;
  }
  return readback_.data();
}

template <class T>
T* CudaBackend::grow(cuda::DeviceBuffer<T>& buffer, size_t count) {
  if (count <= buffer.size()) return buffer.data();
  PS_CHECK(!capturing_,
           "CudaBackend: an op needs {} more bytes of workspace while a graph is being captured; "
           "run the work once before capturing it",
           (count - buffer.size()) * sizeof(T));
  wait_for_stream();  // queued kernels may still use the old buffer
  stats_.workspace_bytes -= buffer.bytes();
  buffer = cuda::DeviceBuffer<T>();  // freed first: its content is scratch, and peak memory drops
  buffer = cuda::DeviceBuffer<T>(count);
  stats_.workspace_bytes += buffer.bytes();
  ++stats_.device_allocations;
  ++workspace_generation_;
  return buffer.data();
}

float* CudaBackend::float_workspace(size_t count) {
  return grow(workspace_.floats, count);
}

std::uint16_t* CudaBackend::half_workspace(size_t count) {
  return grow(workspace_.halves, std::max<size_t>(count, 1));
}

double* CudaBackend::double_workspace(int64_t count) {
  return grow(workspace_.doubles, static_cast<size_t>(std::max<int64_t>(count, 1)));
}

std::int32_t* CudaBackend::gather_workspace(int64_t count) {
  return grow(workspace_.gather, static_cast<size_t>(std::max<int64_t>(count, 1)));
}

std::uint32_t* CudaBackend::ray_workspace(int64_t count) {
  return grow(workspace_.rays, static_cast<size_t>(std::max<int64_t>(count, 1)));
}

// ---- clock and graphs ----

double CudaBackend::clock_ms() {
  require_not_capturing("clock_ms");
  cudaEvent_t now = clock_events_[clock_next_].get();
  PS_CUDA_CHECK(cudaEventRecord(now, stream_.get()));
  PS_CUDA_CHECK(cudaEventSynchronize(now));
  staging_used_ = 0;  // the stream has drained
  if (clock_started_) {
    float elapsed = 0;
    PS_CUDA_CHECK(cudaEventElapsedTime(&elapsed, clock_events_[1 - clock_next_].get(), now));
    clock_total_ms_ += elapsed;  // summed per interval: float event times stay precise
  }
  clock_started_ = true;
  clock_next_ = 1 - clock_next_;
  return clock_total_ms_;
}

std::unique_ptr<CapturedGraph> CudaBackend::capture(const std::function<void()>& work) {
  PS_CHECK(options_.graphs, "CudaBackend::capture: this backend was made with graphs off");
  require_not_capturing("capture");
  PS_CUDA_CHECK(cudaStreamBeginCapture(stream_.get(), cudaStreamCaptureModeGlobal));
  capturing_ = true;
  try {
    work();
  } catch (...) {
    capturing_ = false;
    cudaGraph_t partial = nullptr;
    if (cudaStreamEndCapture(stream_.get(), &partial) == cudaSuccess && partial != nullptr) {
      static_cast<void>(cudaGraphDestroy(partial));
    }
    static_cast<void>(cudaGetLastError());
    throw;
  }
  capturing_ = false;
  cudaGraph_t graph = nullptr;
  PS_CUDA_CHECK(cudaStreamEndCapture(stream_.get(), &graph));
  cuda::GraphExec executable(graph);
  ++stats_.graphs_captured;
  return std::make_unique<CudaGraph>(std::move(executable), stream_.get(), stats_.graph_replays,
                                     workspace_generation_);
}

// ---- input preparation ----

void CudaBackend::pad_points(const IRef& num_points, Ref& points) {
  const int64_t capacity = point_count("pad_points", points);
  require_shape("pad_points", "num_points", num_points, {1});
  cuda::pad_points(num_points.data, capacity, points.data, stream_.get());
}

int64_t CudaBackend::pillar_gather(const Ref& points, const GridSpec& grid, int max_pillars,
                                   IRef& cell, IRef& point_index, IRef& count,
                                   IRef& num_pillars) {
  const char* op = "pillar_gather";
  const int64_t M = point_count(op, points);
  require_rank(op, "point_index", point_index, 2);
  const int64_t rows = cuda::pillar_gather_capacity(M, grid, max_pillars);
  const int64_t N = point_index.dim(1);
  require_shape(op, "cell", cell, {rows, 2});
  require_shape(op, "point_index", point_index, {rows, N});
  require_shape(op, "count", count, {rows});
  require_shape(op, "num_pillars", num_pillars, {1});
  const int64_t size = cuda::pillar_gather_workspace_size(M, grid);
  std::int32_t* workspace = gather_workspace(size);
  cuda::pillar_gather(points.data, M, grid, static_cast<int>(N), max_pillars, cell.data,
                      point_index.data, count.data, num_pillars.data, workspace, size,
                      stream_.get());
  return rows;
}

void CudaBackend::decorate_points(const Ref& points, const GridSpec& grid, const IRef& cell,
                                  const IRef& point_index, const IRef& count, const IRef& live_rows,
                                  Ref& out) {
  const char* op = "decorate_points";
  const int64_t M = point_count(op, points);
  require_rank(op, "point_index", point_index, 2);
  const int64_t rows = point_index.dim(0), N = point_index.dim(1);
  require_shape(op, "cell", cell, {rows, 2});
  require_shape(op, "count", count, {rows});
  require_shape(op, "out", out, {rows, N, cuda::kDecoratedFeatures});
  cuda::decorate_points(points.data, M, cell.data, point_index.data, count.data, rows, N, grid,
                        out.data, stream_.get(), live_rows_data(op, live_rows));
}

void CudaBackend::batch_cells(const IRef& cell, int sample, IRef& cells) {
  require_rank("batch_cells", "cell", cell, 2);
  require_shape("batch_cells", "cell", cell, {cell.dim(0), 2});
  require_shape("batch_cells", "cells", cells, {cell.dim(0), 3});
  cuda::batch_cells(cell.data, cell.dim(0), sample, cells.data, stream_.get());
}

void CudaBackend::observability_2d(const Ref& points, const Eigen::Vector3d& origin,
                                   const GridSpec& grid, URef& transmissions, URef& detections) {
  const char* op = "observability_2d";
  const int64_t M = point_count(op, points);
  require_shape(op, "transmissions", transmissions, {grid.height(), grid.width()});
  require_shape(op, "detections", detections, {grid.height(), grid.width()});
  const int64_t size = cuda::observability_2d_workspace_size(grid);
  std::uint32_t* workspace = ray_workspace(size);
  cuda::observability_2d(points.data, M, sensor_origin(origin), grid, transmissions.data,
                         detections.data, workspace, size, stream_.get());
}

void CudaBackend::observability_input(const URef& transmissions, const URef& detections,
                                      Ref& out) {
  const char* op = "observability_input";
  require_rank(op, "transmissions", transmissions, 2);
  require_shape(op, "detections", detections, transmissions.shape);
  PS_CHECK(out.numel() == transmissions.numel(), "{}: out must hold H * W = {} values, got {}", op,
           transmissions.numel(), shape_str(out.shape));
  cuda::observability_input(transmissions.data, detections.data, transmissions.numel(), out.data,
                            stream_.get());
}

void CudaBackend::occupancy_3d(const Ref& points, const Eigen::Vector3d& origin,
                               const GridSpec& grid, Ref& probability) {
  const char* op = "occupancy_3d";
  const int64_t M = point_count(op, points);
  const Shape voxels{grid.layers(), grid.height(), grid.width()};
  require_shape(op, "probability", probability, voxels);
  const int64_t n = shape_numel(voxels);
  std::uint32_t* counts = ray_workspace(2 * n);
  cuda::occupancy_counts_3d(points.data, M, sensor_origin(origin), grid, counts, counts + n,
                            stream_.get());
  cuda::occupancy_probability(counts, counts + n, n, probability.data, stream_.get());
}

void CudaBackend::grid_map_features(const Ref& points, const GridSpec& grid,
                                    const URef& detections, const URef& transmissions, Ref& out) {
  const char* op = "grid_map_features";
  const int64_t M = point_count(op, points);
  require_shape(op, "detections", detections, {grid.height(), grid.width()});
  require_shape(op, "transmissions", transmissions, {grid.height(), grid.width()});
  require_shape(op, "out", out, {cuda::kGridMapLayers, grid.height(), grid.width()});
  const int64_t size = cuda::pillar_gather_workspace_size(M, grid);
  std::int32_t* workspace = gather_workspace(size);
  cuda::grid_map_features(points.data, M, grid, detections.data, transmissions.data, out.data,
                          workspace, size, stream_.get());
}

void CudaBackend::mask_unobserved(const URef& transmissions, const URef& detections,
                                  LRef& labels, Ref* probabilities) {
  const char* op = "mask_unobserved";
  require_rank(op, "transmissions", transmissions, 2);
  require_shape(op, "detections", detections, transmissions.shape);
  const int64_t n = transmissions.numel();
  PS_CHECK(labels.numel() == n, "{}: labels must hold H * W = {} values, got {}", op, n,
           shape_str(labels.shape));
  int64_t planes = 0;
  if (probabilities != nullptr) {
    PS_CHECK(n > 0 && probabilities->numel() % n == 0,
             "{}: probabilities {} are not whole planes of H * W = {} cells", op,
             shape_str(probabilities->shape), n);
    planes = probabilities->numel() / n;
  }
  cuda::mask_unobserved(transmissions.data, detections.data, n, labels.data,
                        probabilities ? probabilities->data : nullptr, planes, stream_.get());
}

// ---- pillar feature net and scatter ----

// The PFN kernels keep no (P N, C) tensor whole: they recompute the linear output per block of
// pillars.
void CudaBackend::pfn_forward(const Ref& points, const Ref& weight, BatchNormRefs& bn,
                              bool training, const IRef& live_rows, IRef& argmax, Ref& out) {
  const char* op = "pfn_forward";
  require_shape(op, "out", out, op::pfn(points.shape, weight.shape, op));
  const cuda::PfnShape shape{points.dim(0), points.dim(1), weight.dim(0)};
  const int32_t* live = live_rows_data(op, live_rows);
  if (!training) {
    // Evaluation needs no arg-max slots (nothing flows back).
    cuda::pfn_forward_eval(points.data, weight.data, shape, bn.gamma.data, bn.beta.data,
                           bn.running_mean.data, bn.running_var.data, bn.eps, out.data, nullptr,
                           stream_.get(), live);
    return;
  }
  PS_CHECK(live == nullptr, "{}: live_rows in training (the batch statistics take every row)", op);
  require_shape(op, "argmax", argmax, {shape.pillars, shape.channels});
  double* workspace = double_workspace(cuda::pfn_workspace_doubles(shape));
  cuda::pfn_forward_train(points.data, weight.data, shape, bn.gamma.data, bn.beta.data, bn.eps,
                          bn.momentum, bn.running_mean.data, bn.running_var.data, out.data,
                          argmax.data, bn.save_mean.data, bn.save_invstd.data, workspace, stream_.get(),
                          batchnorm_sum(bn.replicas));
}

void CudaBackend::pfn_backward(const Ref& points, const Ref& weight, const BatchNormRefs& bn,
                               const IRef& argmax, const Ref& dout, Ref& dweight, Ref& dgamma,
                               Ref& dbeta) {
  const char* op = "pfn_backward";
  require_shape(op, "dout", dout, op::pfn(points.shape, weight.shape, op));
  const cuda::PfnShape shape{points.dim(0), points.dim(1), weight.dim(0)};
  require_shape(op, "argmax", argmax, {shape.pillars, shape.channels});
  require_shape(op, "dweight", dweight, weight.shape);
  double* workspace = double_workspace(cuda::pfn_workspace_doubles(shape));
  // The points are the network's input: their gradient is not computed.
  cuda::pfn_backward(dout.data, points.data, weight.data, shape, bn.gamma.data, bn.save_mean.data,
                     bn.save_invstd.data, argmax.data, nullptr, dweight.data, dgamma.data,
                     dbeta.data, workspace, stream_.get(), batchnorm_sum(bn.replicas));
}

void CudaBackend::scatter_forward_f32(const Ref& features, const IRef& cells, int channel0,
                                  Ref& canvas) {
  op::scatter(features.shape, cells.shape, canvas.shape, channel0, "scatter_forward");
  const cuda::ScatterCanvas shape{canvas.dim(0), canvas.dim(1), canvas.dim(2), canvas.dim(3),
                                  channel0};
  cuda::scatter_forward(features.data, cells.data, features.dim(0), features.dim(1), shape,
                        canvas.data, stream_.get());
}

void CudaBackend::scatter_backward(const Ref& dcanvas, const IRef& cells, int channel0,
                                   Ref& dfeatures) {
  op::scatter(dfeatures.shape, cells.shape, dcanvas.shape, channel0, "scatter_backward");
  const cuda::ScatterCanvas shape{dcanvas.dim(0), dcanvas.dim(1), dcanvas.dim(2), dcanvas.dim(3),
                                  channel0};
  cuda::scatter_backward(dcanvas.data, shape, cells.data, dfeatures.dim(0), dfeatures.dim(1),
                         dfeatures.data, stream_.get());
}

namespace {

// x (B, Cx, H, W) as the band [channel0, channel0 + Cx) of y (B, Cy, H, W).
cuda::ChannelBand channel_band(const char* caller, const Ref& x, int channel0, const Ref& y) {
  op::channel_band(x.shape, y.shape, channel0, caller);
  return {x.dim(0), x.dim(1), x.dim(2) * x.dim(3), y.dim(1), channel0};
}

}  // namespace

void CudaBackend::copy_channels_f32(const Ref& x, int channel0, Ref& y) {
  cuda::copy_channels(x.data, channel_band("copy_channels", x, channel0, y), y.data, stream_.get());
}

void CudaBackend::extract_channels(const Ref& y, int channel0, Ref& x) {
  cuda::extract_channels(y.data, channel_band("extract_channels", x, channel0, y), x.data, stream_.get());
}

// ---- convolutions ----

namespace {

cuda::Conv2dShape conv_shape(const char* caller, const Ref& x, const Ref& w, int pad) {
  op::conv2d(x.shape, w.shape, pad, nullptr, caller);
  return {x.dim(0), x.dim(1), x.dim(2), x.dim(3), w.dim(0), w.dim(2), pad};
}

Shape conv_output(const cuda::Conv2dShape& s) {
  return {s.batch, s.out_channels, s.out_height(), s.out_width()};
}

cuda::ConvTranspose2dShape conv_transpose_shape(const char* caller, const Ref& x, const Ref& w) {
  op::conv_transpose2d(x.shape, w.shape, nullptr, caller);
  return {x.dim(0), x.dim(1), x.dim(2), x.dim(3), w.dim(1)};
}

Shape conv_transpose_output(const cuda::ConvTranspose2dShape& s) {
  return {s.batch, s.out_channels, s.out_height(), s.out_width()};
}

// The shape of a convolution's backward (FP32 or 16-bit) after checking all its tensors.
cuda::Conv2dShape conv_backward_shape(const char* op, const Ref& x, const Ref& w, const Ref& dy, int pad,
                                      const Ref* dx, const Ref& dw, const Ref* dbias) {
  const cuda::Conv2dShape shape = conv_shape(op, x, w, pad);
  require_shape(op, "dy", dy, conv_output(shape));
  require_shape(op, "dw", dw, w.shape);
  if (dbias) require_shape(op, "dbias", *dbias, {shape.out_channels});
  if (dx) require_shape(op, "dx", *dx, x.shape);
  return shape;
}

cuda::ConvTranspose2dShape conv_transpose_backward_shape(const char* op, const Ref& x, const Ref& w, const Ref& dy,
                                                         const Ref& dx, const Ref& dw, const Ref* dbias) {
  const cuda::ConvTranspose2dShape shape = conv_transpose_shape(op, x, w);
  require_shape(op, "dy", dy, conv_transpose_output(shape));
  require_shape(op, "dx", dx, x.shape);
  require_shape(op, "dw", dw, w.shape);
  if (dbias) require_shape(op, "dbias", *dbias, {shape.out_channels});
  return shape;
}

}  // namespace

cuda::Conv2dEngine* CudaBackend::vendor_engine(const cuda::Conv2dShape& s) {
  const bool empty = s.batch == 0 || s.in_channels == 0 || s.out_channels == 0 ||
                     s.out_height() <= 0 || s.out_width() <= 0;
  return empty ? nullptr : vendor_conv_.get();
}

void CudaBackend::conv2d_forward(const Ref& x, const Ref& w, const Ref* bias, int pad, Ref& y) {
  const char* op = "conv2d_forward";
  const cuda::Conv2dShape shape = conv_shape(op, x, w, pad);
  require_shape(op, "y", y, conv_output(shape));
  if (bias) require_shape(op, "bias", *bias, {shape.out_channels});
  if (cuda::Conv2dEngine* vendor = vendor_engine(shape)) {
    vendor->forward(x.data, w.data, bias ? bias->data : nullptr, y.data, shape, stream_.get(),
                    capturing_);
    stats_.vendor_conv = vendor->stats();
    return;
  }
  cuda::conv2d_forward(x.data, w.data, bias ? bias->data : nullptr, y.data, shape, stream_.get());
}

void CudaBackend::conv2d_backward_f32(const Ref& x, const Ref& w, const Ref& dy, int pad, Ref* dx,
                                  Ref& dw, Ref* dbias) {
  const char* op = "conv2d_backward";
  const cuda::Conv2dShape shape = conv_backward_shape(op, x, w, dy, pad, dx, dw, dbias);
  if (cuda::Conv2dEngine* vendor = vendor_engine(shape)) {
    if (dx) vendor->backward_data(dy.data, w.data, dx->data, shape, stream_.get(), capturing_);
    vendor->backward_weights(x.data, dy.data, dw.data, dbias ? dbias->data : nullptr, shape,
                             stream_.get(), capturing_);
    stats_.vendor_conv = vendor->stats();
    return;
  }
  if (dx) cuda::conv2d_backward_data(dy.data, w.data, dx->data, shape, stream_.get());
  const size_t floats = cuda::conv2d_backward_weights_workspace(shape);
  float* workspace = float_workspace(floats);
  cuda::conv2d_backward_weights(x.data, dy.data, dw.data, dbias ? dbias->data : nullptr, shape,
                                workspace, workspace_.floats.size(), stream_.get());
}

void CudaBackend::conv_transpose2d_forward(const Ref& x, const Ref& w, const Ref* bias, Ref& y) {
  const char* op = "conv_transpose2d_forward";
  const cuda::ConvTranspose2dShape shape = conv_transpose_shape(op, x, w);
  require_shape(op, "y", y, conv_transpose_output(shape));
  if (bias) require_shape(op, "bias", *bias, {shape.out_channels});
  cuda::conv_transpose2d_forward(x.data, w.data, bias ? bias->data : nullptr, y.data, shape,
                                 stream_.get());
}

void CudaBackend::conv_transpose2d_backward_f32(const Ref& x, const Ref& w, const Ref& dy, Ref& dx,
                                            Ref& dw, Ref* dbias) {
  const char* op = "conv_transpose2d_backward";
  const cuda::ConvTranspose2dShape shape = conv_transpose_backward_shape(op, x, w, dy, dx, dw, dbias);
  cuda::conv_transpose2d_backward_data(dy.data, w.data, dx.data, shape, stream_.get());
  const size_t floats = cuda::conv_transpose2d_backward_weights_workspace(shape);
  float* workspace = float_workspace(floats);
  cuda::conv_transpose2d_backward_weights(x.data, dy.data, dw.data, dbias ? dbias->data : nullptr,
                                          shape, workspace, workspace_.floats.size(), stream_.get());
}

// ---- BatchNorm + ReLU, pooling, upsampling, joins ----

void CudaBackend::batchnorm_relu_forward(const Ref& x, BatchNormRefs& bn, bool training, Ref& y) {
  const char* op = "batchnorm_relu_forward";
  require_rank(op, "x", x, 4);
  require_shape(op, "y", y, x.shape);
  require_shape(op, "gamma", bn.gamma, {x.dim(1)});
  const cuda::PlanarShape shape = planar(x);
  if (!training) {
    cuda::batchnorm_forward_eval(x.data, shape, bn.gamma.data, bn.beta.data, bn.running_mean.data,
                                 bn.running_var.data, bn.eps, /*relu=*/true, y.data, stream_.get());
    return;
  }
  double* workspace = double_workspace(cuda::batchnorm_workspace_doubles(shape));
  cuda::batchnorm_forward_train(x.data, shape, bn.gamma.data, bn.beta.data, bn.eps, bn.momentum,
                                bn.running_mean.data, bn.running_var.data, /*relu=*/true, y.data,
                                bn.save_mean.data, bn.save_invstd.data, workspace, stream_.get(),
                                batchnorm_sum(bn.replicas));
}

void CudaBackend::batchnorm_relu_backward(const Ref& x, const Ref& y, const Ref& dy,
                                          const BatchNormRefs& bn, Ref& dx, Ref& dgamma,
                                          Ref& dbeta) {
  const char* op = "batchnorm_relu_backward";
  require_rank(op, "x", x, 4);
  require_shape(op, "y", y, x.shape);
  require_shape(op, "dy", dy, x.shape);
  require_shape(op, "dx", dx, x.shape);
  require_shape(op, "dgamma", dgamma, {x.dim(1)});
  require_shape(op, "dbeta", dbeta, {x.dim(1)});
  const cuda::PlanarShape shape = planar(x);
  double* workspace = double_workspace(cuda::batchnorm_workspace_doubles(shape));
  cuda::batchnorm_backward(dy.data, x.data, y.data, shape, bn.gamma.data, bn.save_mean.data,
                           bn.save_invstd.data, dx.data, dgamma.data, dbeta.data, workspace,
                           stream_.get(), batchnorm_sum(bn.replicas));
}

void CudaBackend::maxpool2d_f32(const Ref& x, Ref& y, IRef& argmax) {
  const char* op = "maxpool2d_forward";
  const Shape pooled = op::maxpool2d(x.shape, op);
  require_shape(op, "y", y, pooled);
  require_shape(op, "argmax", argmax, pooled);
  cuda::maxpool2d_forward(x.data, x.dim(0) * x.dim(1), x.dim(2), x.dim(3), y.data, argmax.data,
                          stream_.get());
}

void CudaBackend::maxpool2d_backward(const Ref& dy, const IRef& argmax, Ref& dx) {
  const char* op = "maxpool2d_backward";
  require_rank(op, "dx", dx, 4);
  const Shape pooled{dx.dim(0), dx.dim(1), dx.dim(2) / 2, dx.dim(3) / 2};
  require_shape(op, "dy", dy, pooled);
  require_shape(op, "argmax", argmax, pooled);
  cuda::maxpool2d_backward(dy.data, argmax.data, dx.dim(0) * dx.dim(1), dx.dim(2), dx.dim(3),
                           dx.data, stream_.get());
}

void CudaBackend::upsample_bilinear_f32(const Ref& x, Ref& y) {
  require_shape("upsample_bilinear_forward", "y", y, op::upsample_bilinear(x.shape, "upsample_bilinear_forward"));
  cuda::upsample_bilinear_forward(x.data, x.dim(0) * x.dim(1), x.dim(2), x.dim(3), y.data, stream_.get());
}

void CudaBackend::upsample_bilinear_backward(const Ref& dy, Ref& dx) {
  require_rank("upsample_bilinear_backward", "dx", dx, 4);
  require_shape("upsample_bilinear_backward", "dy", dy,
                {dx.dim(0), dx.dim(1), 2 * dx.dim(2), 2 * dx.dim(3)});
  cuda::upsample_bilinear_backward(dy.data, dx.dim(0) * dx.dim(1), dx.dim(2), dx.dim(3), dx.data,
                                   stream_.get());
}

namespace {

cuda::PadConcatShape pad_concat_shape(const char* caller, const Ref& skip, const Ref& up,
                                      const Ref& joined) {
  require_shape(caller, "the joined tensor", joined, op::pad_concat(skip.shape, up.shape, caller));
  return {skip.dim(0), skip.dim(1), up.dim(1), skip.dim(2), skip.dim(3), up.dim(2), up.dim(3)};
}

}  // namespace

void CudaBackend::pad_concat_f32(const Ref& skip, const Ref& up, Ref& y) {
  cuda::pad_concat_forward(skip.data, up.data, pad_concat_shape("pad_concat_forward", skip, up, y),
                           y.data, stream_.get());
}

void CudaBackend::pad_concat_backward(const Ref& dy, Ref& dskip, Ref& dup) {
  cuda::pad_concat_backward(dy.data, pad_concat_shape("pad_concat_backward", dskip, dup, dy),
                            dskip.data, dup.data, stream_.get());
}

void CudaBackend::add_inplace(Ref& a, const Ref& b) {
  require_shape("add_inplace", "b", b, a.shape);
  cuda::add_inplace(a.data, b.data, a.numel(), stream_.get());
}

// ---- head, loss, optimiser ----

void CudaBackend::softmax(const Ref& logits, Ref& probs) {
  require_rank("softmax", "logits", logits, 4);
  require_shape("softmax", "probs", probs, logits.shape);
  cuda::softmax_channels(logits.data, logits.dim(0), logits.dim(1), logits.dim(2) * logits.dim(3),
                         probs.data, stream_.get());
}

void CudaBackend::argmax(const Ref& logits, LRef& labels) {
  require_rank("argmax", "logits", logits, 4);
  require_shape("argmax", "labels", labels, {logits.dim(0), logits.dim(2), logits.dim(3)});
  cuda::argmax_class_ids(logits.data, logits.dim(0), logits.dim(1), logits.dim(2) * logits.dim(3),
                         labels.data, stream_.get());
}

void CudaBackend::mirror_add(const Ref& x, bool mirror_y, bool mirror_x, Ref& sum) {
  require_rank("mirror_add", "x", x, 4);
  require_shape("mirror_add", "sum", sum, x.shape);
  cuda::mirror_add(x.data, x.dim(0) * x.dim(1), x.dim(2), x.dim(3), mirror_y, mirror_x, sum.data,
                   stream_.get());
}

void CudaBackend::argmax_positive(const Ref& values, LRef& labels) {
  require_rank("argmax_positive", "values", values, 4);
  require_shape("argmax_positive", "labels", labels, {values.dim(0), values.dim(2), values.dim(3)});
  cuda::argmax_positive_class_ids(values.data, values.dim(0), values.dim(1),
                                  values.dim(2) * values.dim(3), labels.data, stream_.get());
}

double CudaBackend::loss(const LossSpec& spec, const Ref& logits, const LRef& labels,
                         const Ref& coefficients, Ref& dlogits) {
  const char* op = "loss";
  require_not_capturing(op);
  require_rank(op, "logits", logits, 4);
  const int64_t B = logits.dim(0), K = logits.dim(1), S = logits.dim(2) * logits.dim(3);
  require_shape(op, "labels", labels, {B, logits.dim(2), logits.dim(3)});
  require_shape(op, "coefficients (one per class id, 0 unused)", coefficients, {K + 1});
  require_shape(op, "dlogits", dlogits, logits.shape);
  const auto run = spec.kind == LossKind::Bce ? &cuda::bce_loss : &cuda::cross_entropy_loss;
  run(logits.data, labels.data, B, K, S, coefficients.data, dlogits.data,
      workspace_.loss_partials.data(), workspace_.loss_result.data(), stream_.get());
  if (spec.kind == LossKind::CrossEntropyLovasz) {
    int* counts = grow(workspace_.lovasz_counts, static_cast<size_t>(cuda::lovasz_count_ints(K)));
    double* steps = grow(workspace_.lovasz_steps, static_cast<size_t>(cuda::lovasz_step_doubles(K)));
    cuda::lovasz_softmax_loss(logits.data, labels.data, B, K, S, spec.lovasz_weight, dlogits.data,
                              counts, steps, workspace_.loss_partials.data(),
                              workspace_.loss_result.data(), stream_.get());
  }
  const double value = cuda::loss_value(workspace_.loss_result.data(), stream_.get());
  staging_used_ = 0;  // loss_value waited for the stream
  return value;
}

double CudaBackend::sum_of_squares(const Ref& x) {
  require_not_capturing("sum_of_squares");
  double* partials = workspace_.sum_of_squares.data();
  double* result = partials + cuda::kSumOfSquaresPartials;
  cuda::sum_of_squares(x.data, x.numel(), partials, result, stream_.get());
  double host = 0;
  download(&host, result, sizeof(double));
  return host;
}

#if !defined(PILLARSEG_CUDA_EMULATION)
NcclCommunicator& CudaBackend::nccl_communicator(Replicas& replicas) {
  if (!nccl_) nccl_ = std::make_unique<NcclCommunicator>(replicas);
  return *nccl_;
}

void CudaBackend::begin_sum_over_replicas(Ref& values, Replicas& replicas) {
  if (!nccl_gradients_) {
    nccl_gradients_ = std::make_unique<NcclGradientSum>(nccl_communicator(replicas), stream_.get());
  }
  nccl_gradients_->begin(values.data, values.numel());
}

void CudaBackend::end_sums_over_replicas(Replicas&) {
  if (nccl_gradients_) nccl_gradients_->end();
}
#endif

ReplicaSum* CudaBackend::batchnorm_sum(ReplicaSum* replicas) {
#if defined(PILLARSEG_CUDA_EMULATION)
  return replicas;
#else
  // A ReplicaSum that is not the run's Replicas (none, or one that cannot make a communicator)
  // keeps the host path.
  auto* run = dynamic_cast<Replicas*>(replicas);
  if (run == nullptr) return replicas;
  if (!nccl_statistics_) {
    nccl_statistics_ = std::make_unique<NcclStatisticsSum>(nccl_communicator(*run), *run);
  }
  return nccl_statistics_.get();
#endif
}

void CudaBackend::scale(Ref& x, float factor) {
  cuda::scale(x.data, factor, x.numel(), stream_.get());
}

void CudaBackend::adam_step(Ref& param, const Ref& grad, Ref& m, Ref& v, int64_t step,
                            const AdamOptions& options) {
  const char* op = "adam_step";
  require_shape(op, "grad", grad, param.shape);
  require_shape(op, "m", m, param.shape);
  require_shape(op, "v", v, param.shape);
  cuda::adam_step(param.data, grad.data, m.data, v.data, param.numel(), step, options, stream_.get());
}

// ---- mixed-precision evaluation convolutions ----

namespace {

cuda::Half16 half_type(const char* op, Precision p) {
  PS_CHECK(p != Precision::F32, "{}: precision fp32 has no 16-bit weights", op);
  return p == Precision::BF16 ? cuda::Half16::BF16 : cuda::Half16::F16;
}

}  // namespace

bool CudaBackend::supports_precision(Precision p, std::string* why_not) const {
  if (p == Precision::F32) return true;
  return cuda::mma_supported(why_not);
}

void CudaBackend::prepare_conv_weights_16(const Ref& w, const Ref* bias, const BatchNormRefs* bn, Precision p,
                                       HRef& w16, Ref& bias_out, const HRef& transformed) {
  const char* op = "prepare_conv_weights";
  PS_CHECK(transformed.data == nullptr, "{}: the CUDA backend has no transformed weights", op);
  require_rank(op, "w", w, 4);
  const cuda::Conv2dShape shape{1, w.dim(1), w.dim(2), w.dim(3), w.dim(0), w.dim(2), 0};
  if (bias) require_shape(op, "bias", *bias, {w.dim(0)});
  require_shape(op, "w16", w16, op::half16_conv_weights(w.shape, false));
  require_shape(op, "bias_out", bias_out, {w.dim(0)});
  cuda::FoldedBatchNorm folded;
  if (bn != nullptr) {
    require_shape(op, "gamma", bn->gamma, {w.dim(0)});
    folded = {bn->gamma.data, bn->beta.data, bn->running_mean.data, bn->running_var.data, bn->eps};
  }
  cuda::prepare_conv_weights(w.data, bias ? bias->data : nullptr, folded, shape, half_type(op, p), w16.data,
                             bias_out.data, stream_.get());
}

void CudaBackend::prepare_conv_transpose_weights_16(const Ref& w, const Ref* bias, Precision p, HRef& w16,
                                                 Ref& bias_out) {
  const char* op = "prepare_conv_transpose_weights";
  require_rank(op, "w", w, 4);
  if (bias) require_shape(op, "bias", *bias, {w.dim(1)});
  require_shape(op, "w16", w16, op::half16_conv_weights(w.shape, true));
  require_shape(op, "bias_out", bias_out, {4 * w.dim(1)});
  cuda::prepare_conv_transpose_weights(w.data, bias ? bias->data : nullptr, w.dim(0), w.dim(1), half_type(op, p),
                                       w16.data, bias_out.data, stream_.get());
}

void CudaBackend::conv2d_prepared_16(const TensorRef& x, const HRef& w16, const HRef& transformed, const Ref& bias_out,
                                      const Shape& weight, int pad, bool relu, Precision p, const TensorRef& y) {
  const char* op = "conv2d_prepared_forward";
  PS_CHECK(transformed.data == nullptr, "{}: the CUDA backend has no transformed weights", op);
  const Shape y_shape = op::conv2d(x.shape, weight, pad, nullptr, op);
  PS_CHECK(y.shape == y_shape, "{}: y must be {}, got {}", op, shape_str(y_shape), shape_str(y.shape));
  require_shape(op, "w16", w16, op::half16_conv_weights(weight, false));
  require_shape(op, "bias_out", bias_out, {weight[0]});
  const cuda::Conv2dShape shape{x.dim(0), x.dim(1), x.dim(2), x.dim(3), weight[0], weight[2], pad};
  float* workspace =
      float_workspace(static_cast<size_t>(cuda::conv2d_mma_forward_workspace(shape)));
  cuda::conv2d_mma_forward(x.data, is_float16(x.dtype), w16.data, bias_out.data, shape, half_type(op, p), relu,
                           y.data, is_float16(y.dtype), stream_.get(), workspace);
}

void CudaBackend::conv_transpose2d_prepared_16(const TensorRef& x, const HRef& w16, const Ref& bias_out,
                                                 const Shape& weight, Precision p, const TensorRef& y) {
  const char* op = "conv_transpose2d_prepared_forward";
  const Shape y_shape = op::conv_transpose2d(x.shape, weight, nullptr, op);
  PS_CHECK(y.shape == y_shape, "{}: y must be {}, got {}", op, shape_str(y_shape), shape_str(y.shape));
  require_shape(op, "w16", w16, op::half16_conv_weights(weight, true));
  require_shape(op, "bias_out", bias_out, {4 * weight[1]});
  float* workspace =
      float_workspace(static_cast<size_t>(cuda::conv_transpose2d_mma_forward_workspace(
          x.dim(0), x.dim(1), x.dim(2), x.dim(3), weight[1])));
  cuda::conv_transpose2d_mma_forward(x.data, is_float16(x.dtype), w16.data, bias_out.data, x.dim(0), x.dim(1),
                                      x.dim(2), x.dim(3), weight[1], half_type(op, p), y.data,
                                      is_float16(y.dtype), stream_.get(), workspace);
}

bool CudaBackend::supports_training_precision(Precision p, std::string* why_not) const {
  if (p == Precision::I8) {
    if (why_not != nullptr) *why_not = "int8 is an inference precision (training runs fp32, bf16 or fp16)";
    return false;
  }
  return supports_precision(p, why_not);
}

void CudaBackend::conv2d_backward_16(const Ref& x, const Ref& w, const Ref& dy, int pad, Precision p, Ref* dx,
                                       Ref& dw, Ref* dbias) {
  const char* op = "conv2d_backward";
  const cuda::Conv2dShape shape = conv_backward_shape(op, x, w, dy, pad, dx, dw, dbias);
  const cuda::Half16 type = half_type(op, p);
  if (dx) {
    const size_t halves = static_cast<size_t>(
        shape.in_channels * op::half16_weight_k(shape.out_channels, shape.kernel * shape.kernel));
    std::uint16_t* w16t = half_workspace(halves);
    cuda::prepare_conv_data_weights(w.data, shape, type, w16t, stream_.get());
    float* split =
        float_workspace(static_cast<size_t>(cuda::conv2d_mma_backward_data_workspace(shape)));
    cuda::conv2d_mma_backward_data(dy.data, w16t, shape, type, dx->data, stream_.get(), split);
  }
  float* workspace = float_workspace(static_cast<size_t>(cuda::conv2d_mma_backward_weights_workspace(shape)));
  cuda::conv2d_mma_backward_weights(x.data, dy.data, shape, type, dw.data, dbias ? dbias->data : nullptr, workspace,
                                    stream_.get());
}

void CudaBackend::conv_transpose2d_backward_16(const Ref& x, const Ref& w, const Ref& dy, Precision p, Ref& dx,
                                                  Ref& dw, Ref* dbias) {
  const char* op = "conv_transpose2d_backward";
  const cuda::ConvTranspose2dShape shape = conv_transpose_backward_shape(op, x, w, dy, dx, dw, dbias);
  const cuda::Half16 type = half_type(op, p);
  std::uint16_t* w16t = half_workspace(
      static_cast<size_t>(shape.in_channels * op::half16_weight_k(shape.out_channels, 4)));
  cuda::prepare_conv_transpose_data_weights(w.data, shape, type, w16t, stream_.get());
  float* split = float_workspace(
      static_cast<size_t>(cuda::conv_transpose2d_mma_backward_data_workspace(shape)));
  cuda::conv_transpose2d_mma_backward_data(dy.data, w16t, shape, type, dx.data, stream_.get(),
                                            split);
  float* workspace =
      float_workspace(static_cast<size_t>(cuda::conv_transpose2d_mma_backward_weights_workspace(shape)));
  cuda::conv_transpose2d_mma_backward_weights(x.data, dy.data, shape, type, dw.data, dbias ? dbias->data : nullptr,
                                               workspace, stream_.get());
}

void CudaBackend::convert_16(const Ref& x, Precision p, HRef& y) {
  require_shape("to_half", "y", y, x.shape);
  cuda::to_half16(x.data, x.numel(), half_type("to_half", p), y.data, stream_.get());
}

void CudaBackend::maxpool2d_16(const HRef& x, Precision p, HRef& y) {
  const char* op = "maxpool2d_half";
  require_shape(op, "y", y, op::maxpool2d(x.shape, op));
  cuda::maxpool2d_half16(x.data, x.dim(0) * x.dim(1), x.dim(2), x.dim(3), half_type(op, p), y.data, stream_.get());
}

void CudaBackend::upsample_bilinear_16(const HRef& x, Precision p, HRef& y) {
  const char* op = "upsample_bilinear_half";
  require_shape(op, "y", y, op::upsample_bilinear(x.shape, op));
  cuda::upsample_bilinear_half16(x.data, x.dim(0) * x.dim(1), x.dim(2), x.dim(3), half_type(op, p), y.data, stream_.get());
}

void CudaBackend::pad_concat_16(const HRef& skip, const HRef& up, HRef& y) {
  const char* op = "pad_concat_half";
  require_shape(op, "y", y, op::pad_concat(skip.shape, up.shape, op));
  const cuda::PadConcatShape shape{skip.dim(0), skip.dim(1), up.dim(1), skip.dim(2), skip.dim(3), up.dim(2), up.dim(3)};
  cuda::pad_concat_half16(skip.data, up.data, shape, y.data, stream_.get());
}

void CudaBackend::scatter_forward_16(const Ref& features, const IRef& cells, int channel0,
                                       Precision p, HRef& canvas) {
  const char* op = "scatter_forward_half";
  op::scatter(features.shape, cells.shape, canvas.shape, channel0, op);
  const cuda::ScatterCanvas shape{canvas.dim(0), canvas.dim(1), canvas.dim(2), canvas.dim(3),
                                  channel0};
  cuda::scatter_forward_half(features.data, cells.data, features.dim(0), features.dim(1), shape,
                             half_type(op, p), canvas.data, stream_.get());
}

void CudaBackend::copy_channels_16(const HRef& x, int channel0, HRef& y) {
  const char* op = "copy_channels_half";
  op::channel_band(x.shape, y.shape, channel0, op);
  cuda::copy_channels_half16(x.data, {x.dim(0), x.dim(1), x.dim(2) * x.dim(3), y.dim(1), channel0}, y.data,
                             stream_.get());
}

// ---- factory ----

std::unique_ptr<Backend> make_cuda_device_backend(const BackendOptions& options) {
  CudaBackendOptions cuda_options;
  cuda_options.convolution = parse_convolution_impl(options.convolution);
  cuda_options.device = options.cuda_device;
  return std::make_unique<CudaBackend>(cuda_options);
}

// ---- the Backend's ops, by the dtype of their tensors ----

void CudaBackend::scatter_forward(const Ref& features, const IRef& cells, int channel0, const TensorRef& canvas) {
  const char* op = "scatter_forward";
  if (is_float16(canvas.dtype)) {
    HRef c = canvas.bits16(op);
    scatter_forward_16(features, cells, channel0, precision_of(canvas.dtype), c);
    return;
  }
  Ref c = canvas.f32(op);
  scatter_forward_f32(features, cells, channel0, c);
}

void CudaBackend::copy_channels(const TensorRef& x, int channel0, const TensorRef& y) {
  const char* op = "copy_channels";
  PS_CHECK(x.dtype == y.dtype, "{}: x is {} but y is {}", op, dtype_name(x.dtype), dtype_name(y.dtype));
  if (is_float16(y.dtype)) {
    HRef out = y.bits16(op);
    copy_channels_16(x.bits16(op), channel0, out);
    return;
  }
  Ref out = y.f32(op);
  copy_channels_f32(x.f32(op), channel0, out);
}

void CudaBackend::conv2d_backward(const Ref& x, const Ref& w, const Ref& dy, int pad, Ref* dx, Ref& dw, Ref* dbias,
                                  DType compute) {
  if (compute == DType::F32) {
    conv2d_backward_f32(x, w, dy, pad, dx, dw, dbias);
  } else {
    conv2d_backward_16(x, w, dy, pad, precision_of(compute), dx, dw, dbias);
  }
}

void CudaBackend::conv_transpose2d_backward(const Ref& x, const Ref& w, const Ref& dy, Ref& dx, Ref& dw, Ref* dbias,
                                            DType compute) {
  if (compute == DType::F32) {
    conv_transpose2d_backward_f32(x, w, dy, dx, dw, dbias);
  } else {
    conv_transpose2d_backward_16(x, w, dy, precision_of(compute), dx, dw, dbias);
  }
}

void CudaBackend::maxpool2d_forward(const TensorRef& x, const TensorRef& y, IRef* argmax) {
  const char* op = "maxpool2d_forward";
  if (is_float16(x.dtype)) {
    HRef out = y.bits16(op);
    maxpool2d_16(x.bits16(op), precision_of(x.dtype), out);
    return;
  }
  PS_CHECK(argmax != nullptr, "{}: an f32 max-pool writes its arg-max (none given)", op);
  Ref out = y.f32(op);
  maxpool2d_f32(x.f32(op), out, *argmax);
}

void CudaBackend::upsample_bilinear_forward(const TensorRef& x, const TensorRef& y) {
  const char* op = "upsample_bilinear_forward";
  if (is_float16(x.dtype)) {
    HRef out = y.bits16(op);
    upsample_bilinear_16(x.bits16(op), precision_of(x.dtype), out);
    return;
  }
  Ref out = y.f32(op);
  upsample_bilinear_f32(x.f32(op), out);
}

void CudaBackend::pad_concat_forward(const TensorRef& skip, const TensorRef& up, const TensorRef& y) {
  const char* op = "pad_concat_forward";
  if (is_float16(y.dtype)) {
    HRef out = y.bits16(op);
    pad_concat_16(skip.bits16(op), up.bits16(op), out);
    return;
  }
  Ref out = y.f32(op);
  pad_concat_f32(skip.f32(op), up.f32(op), out);
}

void CudaBackend::convert(const Ref& x, const TensorRef& y) {
  HRef out = y.bits16("convert");
  convert_16(x, precision_of(y.dtype), out);
}

void CudaBackend::prepare_conv_weights(const Ref& w, const Ref* bias, const BatchNormRefs* bn,
                                       const TensorRef& prepared, Ref& bias_out, const TensorRef& transformed,
                                       const Ref* weight_scale) {
  const char* op = "prepare_conv_weights";
  if (prepared.dtype == DType::I8) {
    PS_CHECK(transformed.data == nullptr, "{}: the CUDA backend has no transformed weights", op);
    PS_CHECK(weight_scale != nullptr, "{}: INT8 weights need their weight_scale tensor", op);
    require_rank(op, "w", w, 4);
    const cuda::Conv2dShape shape{1, w.dim(1), w.dim(2), w.dim(3), w.dim(0), w.dim(2), 0};
    if (bias) require_shape(op, "bias", *bias, {w.dim(0)});
    require_shape(op, "prepared", prepared.i8(op), op::half16_conv_weights(w.shape, false));
    require_shape(op, "bias_out", bias_out, {w.dim(0)});
    require_shape(op, "weight_scale", *weight_scale, {w.dim(0)});
    cuda::FoldedBatchNorm folded;
    if (bn != nullptr) {
      require_shape(op, "gamma", bn->gamma, {w.dim(0)});
      folded = {bn->gamma.data, bn->beta.data, bn->running_mean.data, bn->running_var.data, bn->eps};
    }
    cuda::prepare_conv_weights_s8(w.data, bias ? bias->data : nullptr, folded, shape, prepared.i8(op).data,
                                  weight_scale->data, bias_out.data, stream_.get());
    return;
  }
  if (prepared.dtype == DType::F32) {  // the FP32 kernel on 16-bit activations: the INT8 forward's head
    PS_CHECK(transformed.data == nullptr, "{}: the CUDA backend has no transformed weights", op);
    require_rank(op, "w", w, 4);
    if (bias) require_shape(op, "bias", *bias, {w.dim(0)});
    require_shape(op, "prepared", prepared.f32(op), w.shape);
    require_shape(op, "bias_out", bias_out, {w.dim(0)});
    cuda::FoldedBatchNorm folded;
    if (bn != nullptr) {
      require_shape(op, "gamma", bn->gamma, {w.dim(0)});
      folded = {bn->gamma.data, bn->beta.data, bn->running_mean.data, bn->running_var.data, bn->eps};
    }
    const cuda::Conv2dShape shape{1, w.dim(1), w.dim(2), w.dim(3), w.dim(0), w.dim(2), 0};
    cuda::fold_conv_weights(w.data, bias ? bias->data : nullptr, folded, shape, prepared.f32(op).data, bias_out.data,
                            stream_.get());
    return;
  }
  HRef w16 = prepared.bits16(op);
  prepare_conv_weights_16(w, bias, bn, precision_of(prepared.dtype), w16, bias_out,
                          HRef{static_cast<uint16_t*>(transformed.data), transformed.shape});
}

void CudaBackend::prepare_conv_transpose_weights(const Ref& w, const Ref* bias, const TensorRef& prepared,
                                                 Ref& bias_out, const Ref* weight_scale) {
  if (prepared.dtype == DType::I8) {
    const char* op = "prepare_conv_transpose_weights";
    PS_CHECK(weight_scale != nullptr, "{}: INT8 weights need their weight_scale tensor", op);
    require_rank(op, "w", w, 4);
    if (bias) require_shape(op, "bias", *bias, {w.dim(1)});
    require_shape(op, "prepared", prepared.i8(op), op::half16_conv_weights(w.shape, true));
    require_shape(op, "bias_out", bias_out, {4 * w.dim(1)});
    require_shape(op, "weight_scale", *weight_scale, {4 * w.dim(1)});
    cuda::prepare_conv_transpose_weights_s8(w.data, bias ? bias->data : nullptr, w.dim(0), w.dim(1),
                                            prepared.i8(op).data, weight_scale->data, bias_out.data, stream_.get());
    return;
  }
  HRef w16 = prepared.bits16("prepare_conv_transpose_weights");
  prepare_conv_transpose_weights_16(w, bias, precision_of(prepared.dtype), w16, bias_out);
}

namespace {

// An activation of the INT8 convolutions: FP32 or BF16 planes.
cuda::ActivationLayout s8_layout(const char* op, const TensorRef& t) {
  PS_CHECK(t.dtype == DType::F32 || t.dtype == DType::BF16, "{}: INT8 convolutions take f32 or bf16 activations, got {}",
           op, dtype_name(t.dtype));
  return t.dtype == DType::BF16 ? cuda::ActivationLayout::BF16 : cuda::ActivationLayout::F32;
}

}  // namespace

void CudaBackend::conv2d_prepared_forward(const TensorRef& x, const TensorRef& prepared, const TensorRef& transformed,
                                          const Ref& bias_out, const Shape& weight, int pad, bool relu,
                                          const TensorRef& y, const Ref* weight_scale, Int8Input input) {
  const char* op = "conv2d_prepared_forward";
  if (prepared.dtype == DType::I8) {
    PS_CHECK(transformed.data == nullptr, "{}: the CUDA backend has no transformed weights", op);
    PS_CHECK(weight_scale != nullptr, "{}: INT8 needs its weight scales", op);
    const Shape y_shape = op::conv2d(x.shape, weight, pad, nullptr, op);
    PS_CHECK(y.shape == y_shape, "{}: y must be {}, got {}", op, shape_str(y_shape), shape_str(y.shape));
    require_shape(op, "prepared", prepared.i8(op), op::half16_conv_weights(weight, false));
    require_shape(op, "bias_out", bias_out, {weight[0]});
    require_shape(op, "weight_scale", *weight_scale, {weight[0]});
    const cuda::Conv2dShape shape{x.dim(0), x.dim(1), x.dim(2), x.dim(3), weight[0], weight[2], pad};
    auto* workspace = reinterpret_cast<std::int32_t*>(
        float_workspace(static_cast<size_t>(cuda::conv2d_mma_s8_forward_workspace(shape))));
    cuda::conv2d_mma_s8_forward(cuda::ActivationsS8{x.data, s8_layout(op, x), input.scale, input.non_negative},
                                prepared.i8(op).data,
                                weight_scale->data, bias_out.data, shape, relu,
                                cuda::OutputS8{y.data, s8_layout(op, y), 1.0f}, stream_.get(), workspace);
    return;
  }
  if (prepared.dtype == DType::F32) {
    // FP32 arithmetic on x as stored: conv2d.cuh's kernel on FP32 x, a 1 x 1 convolution's own
    // kernel on 16-bit x (half_ops.cuh; no workspace, so that a graph can record it). The INT8
    // forward's head: no ReLU, an FP32 y.
    PS_CHECK(transformed.data == nullptr, "{}: the CUDA backend has no transformed weights", op);
    PS_CHECK(!relu && y.dtype == DType::F32,
             "{}: FP32 prepared weights run without ReLU into an f32 y on the CUDA backend, got relu {} and y {}", op,
             relu, dtype_name(y.dtype));
    const Shape y_shape = op::conv2d(x.shape, weight, pad, nullptr, op);
    PS_CHECK(y.shape == y_shape, "{}: y must be {}, got {}", op, shape_str(y_shape), shape_str(y.shape));
    require_shape(op, "prepared", prepared.f32(op), weight);
    require_shape(op, "bias_out", bias_out, {weight[0]});
    if (x.dtype == DType::F32) {
      const cuda::Conv2dShape shape{x.dim(0), x.dim(1), x.dim(2), x.dim(3), weight[0], weight[2], pad};
      cuda::conv2d_forward(x.f32(op).data, prepared.f32(op).data, bias_out.data, y.f32(op).data, shape,
                           stream_.get());
      return;
    }
    PS_CHECK(weight[2] == 1 && pad == 0, "{}: FP32 prepared weights on {} x run 1 x 1 convolutions only, got {} pad {}",
             op, dtype_name(x.dtype), shape_str(weight), pad);
    cuda::pointwise_conv_half16(x.bits16(op).data, half_type(op, precision_of(x.dtype)), prepared.f32(op).data,
                                bias_out.data, x.dim(0), x.dim(1), weight[0], x.dim(2) * x.dim(3), y.f32(op).data,
                                stream_.get());
    return;
  }
  conv2d_prepared_16(x, prepared.bits16(op), HRef{static_cast<uint16_t*>(transformed.data), transformed.shape},
                     bias_out, weight, pad, relu, precision_of(prepared.dtype), y);
}

void CudaBackend::conv_transpose2d_prepared_forward(const TensorRef& x, const TensorRef& prepared, const Ref& bias_out,
                                                    const Shape& weight, const TensorRef& y, const Ref* weight_scale,
                                                    Int8Input input) {
  if (prepared.dtype == DType::I8) {
    const char* op = "conv_transpose2d_prepared_forward";
    PS_CHECK(weight_scale != nullptr, "{}: INT8 needs its weight scales", op);
    const Shape y_shape = op::conv_transpose2d(x.shape, weight, nullptr, op);
    PS_CHECK(y.shape == y_shape, "{}: y must be {}, got {}", op, shape_str(y_shape), shape_str(y.shape));
    require_shape(op, "prepared", prepared.i8(op), op::half16_conv_weights(weight, true));
    require_shape(op, "bias_out", bias_out, {4 * weight[1]});
    require_shape(op, "weight_scale", *weight_scale, {4 * weight[1]});
    auto* workspace = reinterpret_cast<std::int32_t*>(float_workspace(static_cast<size_t>(
        cuda::conv_transpose2d_mma_s8_forward_workspace(x.dim(0), x.dim(1), x.dim(2), x.dim(3), weight[1]))));
    cuda::conv_transpose2d_mma_s8_forward(cuda::ActivationsS8{x.data, s8_layout(op, x), input.scale,
                                                              input.non_negative},
                                          prepared.i8(op).data, weight_scale->data, bias_out.data, x.dim(0),
                                          x.dim(1), x.dim(2), x.dim(3), weight[1], /*relu=*/false,
                                          cuda::OutputS8{y.data, s8_layout(op, y), 1.0f}, stream_.get(), workspace);
    return;
  }
  conv_transpose2d_prepared_16(x, prepared.bits16("conv_transpose2d_prepared_forward"), bias_out, weight,
                               precision_of(prepared.dtype), y);
}

}  // namespace pillarseg::inline PILLARSEG_CUDA_NAMESPACE

namespace pillarseg {

#if defined(PILLARSEG_CUDA_EMULATION)
void install_emulated_cuda_backend() { set_backend_factory("emu", &make_cuda_device_backend); }
#else
void install_cuda_backend() { set_backend_factory("cuda", &make_cuda_device_backend); }
#endif

}  // namespace pillarseg
