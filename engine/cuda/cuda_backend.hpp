// CudaBackend: the Backend interface (engine/backend/backend.hpp) on the CUDA kernels of kernels/,
// every op of the network one or more kernel launches on the backend's own stream, nothing on the
// host. The same source builds two libraries, as the kernels do: pillarseg_cuda_backend (nvcc
// kernels, a GPU) and pillarseg_cuda_backend_emu (the kernels on the CUDA emulation, what the
// tests run); a program links one of them.
//
// Memory: activations, parameters and gradients come from allocate() (cudaMalloc; the model's
// arenas plan them once). The kernels' scratch (the pillar gather's and ray walks' working arrays,
// convolution weight-gradient partials, BatchNorm and PFN statistics, loss and reduction partials)
// lives in the backend's Workspace, grown only when an op needs more than any before, so a
// training or inference loop allocates nothing after its first steps. Uploads go through a pinned
// staging buffer and downloads through a pinned readback buffer (cudaMallocHost) with
// cudaMemcpyAsync; only download(), synchronize(), loss() and sum_of_squares() wait for the
// device. The stats count the allocations and the bytes that cross the bus each way.
//
// Graphs: capture() records the work queued by a callback as a CUDA graph (stream capture) and
// returns it for replay; the scan pipeline (engine/pipeline/) records everything after the
// upload this way, PillarSegNet its evaluation forward. A graph is valid() until a workspace it
// names grows.
//
// Devices: options.device selects the GPU; make_current() makes it the calling thread's current
// device (the runtime keeps one per thread), and the constructor calls it.
//
// Convolutions: Conv2d runs our kernels (kernels/conv2d.cuh) or, for comparison, cuDNN or
// im2col + cuBLAS (engine/cuda/vendor_conv.hpp), chosen by CudaBackendOptions::convolution; the
// vendor libraries exist only in the GPU build (the emulated one throws if asked for them).
// ConvTranspose2d is always ours.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include "engine/backend/backend.hpp"
#include "engine/cuda/install.hpp"
#include "engine/cuda/vendor_conv.hpp"
#include "kernels/cuda_handles.hpp"
#include "kernels/device_buffer.hpp"
#include "kernels/losses.cuh"

namespace pillarseg {
// engine/cuda/nccl_sum.hpp (the GPU build only)
class NcclCommunicator;
class NcclGradientSum;
class NcclStatisticsSum;
}  // namespace pillarseg

namespace pillarseg::inline PILLARSEG_CUDA_NAMESPACE {

struct CudaBackendOptions {
  int device = 0;      // the CUDA device ordinal
  bool graphs = true;  // supports_capture(): the pipeline and the model replay graphs
  // Largest pinned staging (and readback) buffer; a larger upload (download) is copied in pieces
  // of this size.
  size_t max_staging_bytes = size_t{64} << 20;
  // Who computes Conv2d forward and backward: Own (our kernels), Cudnn (cuDNN, deterministic
  // algorithms chosen once per shape, its workspace grown when an algorithm needs more), or
  // Cublas (im2col / col2im kernels + cuBLAS SGEMM for all three passes, through a cols buffer of
  // vendor.workspace_limit_bytes). Cudnn and Cublas do FP32 math without TF32 unless
  // vendor.allow_tensor_cores; shapes with a zero dimension always run our kernels. Only in the
  // GPU build: the emulated backend throws pillarseg::Error for anything but Own.
  ConvolutionImpl convolution = ConvolutionImpl::Own;
  cuda::VendorConvOptions vendor;
};

// What the backend has allocated and recorded so far (the steady state adds nothing).
struct CudaBackendStats {
  int64_t device_allocations = 0;  // cudaMalloc calls: allocate() and workspace growth
  int64_t pinned_allocations = 0;  // cudaMallocHost calls: staging and readback growth
  size_t workspace_bytes = 0;      // device scratch held now
  size_t staging_bytes = 0;        // pinned staging held now (uploads)
  size_t readback_bytes = 0;       // pinned readback held now (downloads)
  int64_t bytes_uploaded = 0;      // host -> device, by upload()
  int64_t bytes_downloaded = 0;    // device -> host, by download()
  int64_t graphs_captured = 0;
  int64_t graph_replays = 0;
  cuda::VendorConvStats vendor_conv;  // the cuDNN or cuBLAS engine's (zeros with Own)
};

class CudaBackend final : public Backend {
 public:
  // Selects device 0, creates the stream and, with a vendor convolution, its library handle;
  // throws pillarseg::Error "no CUDA device found: ..." when the runtime reports none, and
  // for options.convolution other than Own in the emulated build.
  explicit CudaBackend(const CudaBackendOptions& options = {});
  ~CudaBackend() override;
  CudaBackend(const CudaBackend&) = delete;
  CudaBackend& operator=(const CudaBackend&) = delete;

  Device device() const override { return Device::Cuda; }
  std::string name() const override { return name_; }
  ConvolutionImpl convolution() const { return options_.convolution; }
  const CudaBackendStats& stats() const { return stats_; }
  cudaStream_t stream() const { return stream_.get(); }

  void* allocate(size_t bytes) override;
  void deallocate(void* p) noexcept override;
  // The device's free memory (cudaMemGetInfo); in the emulation the host's, which it allocates.
  MemoryBudget memory_budget() const override;
  void upload(void* dst, const void* host_src, size_t bytes) override;
  void download(void* host_dst, const void* src, size_t bytes) override;
  void fill_zero(void* dst, size_t bytes) override;
  void synchronize() override;
  double clock_ms() override;
  bool supports_capture() const override { return options_.graphs; }
  std::unique_ptr<CapturedGraph> capture(const std::function<void()>& work) override;
  void make_current() override;
  Counters counters() const override;

  void pad_points(const IRef& num_points, Ref& points) override;
  int64_t pillar_gather(const Ref& points, const GridSpec& grid, int max_pillars, IRef& cell,
                        IRef& point_index, IRef& count, IRef& num_pillars) override;
  void decorate_points(const Ref& points, const GridSpec& grid, const IRef& cell,
                       const IRef& point_index, const IRef& count, const IRef& live_rows,
                       Ref& out) override;
  void batch_cells(const IRef& cell, int sample, IRef& cells) override;
  void observability_2d(const Ref& points, const Eigen::Vector3d& origin, const GridSpec& grid,
                        URef& transmissions, URef& detections) override;
  void observability_input(const URef& transmissions, const URef& detections, Ref& out) override;
  void occupancy_3d(const Ref& points, const Eigen::Vector3d& origin, const GridSpec& grid,
                    Ref& probability) override;
  void grid_map_features(const Ref& points, const GridSpec& grid, const URef& detections,
                         const URef& transmissions, Ref& out) override;
  void mask_unobserved(const URef& transmissions, const URef& detections, LRef& labels,
                       Ref* probabilities) override;

  void pfn_forward(const Ref& points, const Ref& weight, BatchNormRefs& bn, bool training,
                   const IRef& live_rows, IRef& argmax, Ref& out) override;
  void pfn_backward(const Ref& points, const Ref& weight, const BatchNormRefs& bn,
                    const IRef& argmax, const Ref& dout, Ref& dweight, Ref& dgamma,
                    Ref& dbeta) override;
  void scatter_forward(const Ref& features, const IRef& cells, int channel0, const TensorRef& canvas) override;
  void scatter_backward(const Ref& dcanvas, const IRef& cells, int channel0,
                        Ref& dfeatures) override;
  void copy_channels(const TensorRef& x, int channel0, const TensorRef& y) override;
  void extract_channels(const Ref& y, int channel0, Ref& x) override;
  void conv2d_forward(const Ref& x, const Ref& w, const Ref* bias, int pad, Ref& y) override;
  void conv2d_backward(const Ref& x, const Ref& w, const Ref& dy, int pad, Ref* dx, Ref& dw, Ref* dbias,
                       DType compute = DType::F32) override;
  void conv_transpose2d_forward(const Ref& x, const Ref& w, const Ref* bias, Ref& y) override;
  void conv_transpose2d_backward(const Ref& x, const Ref& w, const Ref& dy, Ref& dx, Ref& dw, Ref* dbias,
                                 DType compute = DType::F32) override;
  void batchnorm_relu_forward(const Ref& x, BatchNormRefs& bn, bool training, Ref& y) override;
  void batchnorm_relu_backward(const Ref& x, const Ref& y, const Ref& dy, const BatchNormRefs& bn,
                               Ref& dx, Ref& dgamma, Ref& dbeta) override;
  void maxpool2d_forward(const TensorRef& x, const TensorRef& y, IRef* argmax) override;
  void maxpool2d_backward(const Ref& dy, const IRef& argmax, Ref& dx) override;
  void upsample_bilinear_forward(const TensorRef& x, const TensorRef& y) override;
  void upsample_bilinear_backward(const Ref& dy, Ref& dx) override;
  void pad_concat_forward(const TensorRef& skip, const TensorRef& up, const TensorRef& y) override;
  void pad_concat_backward(const Ref& dy, Ref& dskip, Ref& dup) override;
  void add_inplace(Ref& a, const Ref& b) override;
  void softmax(const Ref& logits, Ref& probs) override;
  void argmax(const Ref& logits, LRef& labels) override;
  void mirror_add(const Ref& x, bool mirror_y, bool mirror_x, Ref& sum) override;
  void argmax_positive(const Ref& values, LRef& labels) override;
  double loss(const LossSpec& spec, const Ref& logits, const LRef& labels, const Ref& coefficients,
              Ref& dlogits) override;
  double sum_of_squares(const Ref& x) override;
  void scale(Ref& x, float factor) override;
  void adam_step(Ref& param, const Ref& grad, Ref& m, Ref& v, int64_t step, const AdamOptions& options) override;

  // BF16 / FP16 evaluation convolutions on the tensor cores (kernels/conv2d_mma.cuh): compute
  // capability 8.0 or later, or the emulation.
  bool supports_precision(Precision p, std::string* why_not = nullptr) const override;
  // (No transformed form of the weights: prepared_conv_transform_elements is 0.)
  // INT8 (kernels/conv2d_mma_s8.cuh): mma.sync m16n8k32 on compute capability 8.0 or later, or the
  // emulation; the weights prepared on the device.
  void prepare_conv_weights(const Ref& w, const Ref* bias, const BatchNormRefs* bn, const TensorRef& prepared,
                            Ref& bias_out, const TensorRef& transformed, const Ref* weight_scale = nullptr) override;
  void prepare_conv_transpose_weights(const Ref& w, const Ref* bias, const TensorRef& prepared, Ref& bias_out,
                                      const Ref* weight_scale = nullptr) override;
  void conv2d_prepared_forward(const TensorRef& x, const TensorRef& prepared, const TensorRef& transformed,
                               const Ref& bias_out, const Shape& weight, int pad, bool relu, const TensorRef& y,
                               const Ref* weight_scale = nullptr, Int8Input input = {}) override;
  void conv_transpose2d_prepared_forward(const TensorRef& x, const TensorRef& prepared, const Ref& bias_out,
                                         const Shape& weight, const TensorRef& y, const Ref* weight_scale = nullptr,
                                         Int8Input input = {}) override;
  bool supports_training_precision(Precision p, std::string* why_not) const override;
  // Synchronised BatchNorm: the kernels' statistics summed over the replicas. On a GPU, when
  // BatchNormRefs::replicas is the run's Replicas, in device memory over NCCL on the compute
  // stream (engine/cuda/nccl_sum.hpp's NcclStatisticsSum, a DeviceReplicaSum): no BatchNorm
  // waits for the device. In the emulation, or with a ReplicaSum that is not a Replicas, on the
  // host.
  bool supports_synchronized_batchnorm(std::string*) const override { return true; }
#if !defined(PILLARSEG_CUDA_EMULATION)
  // On a GPU the gradients are summed in device memory over NCCL (engine/cuda/nccl_sum.hpp) on a
  // stream of their own that waits for the backward to reach each piece, and the compute stream
  // waits for it at the end; the emulation sums through the host. The gradients and the
  // BatchNorm statistics share one communicator, made when either first needs it.
  void begin_sum_over_replicas(Ref& values, Replicas& replicas) override;
  void end_sums_over_replicas(Replicas& replicas) override;
#endif
  void convert(const Ref& x, const TensorRef& y) override;

 private:
  // The ops above for each dtype of their tensors (FP32, or 16-bit as bits in precision p).
  void scatter_forward_f32(const Ref& features, const IRef& cells, int channel0, Ref& canvas);
  void scatter_forward_16(const Ref& features, const IRef& cells, int channel0, Precision p, HRef& canvas);
  void copy_channels_f32(const Ref& x, int channel0, Ref& y);
  void copy_channels_16(const HRef& x, int channel0, HRef& y);
  void conv2d_backward_f32(const Ref& x, const Ref& w, const Ref& dy, int pad, Ref* dx, Ref& dw, Ref* dbias);
  void conv2d_backward_16(const Ref& x, const Ref& w, const Ref& dy, int pad, Precision p, Ref* dx, Ref& dw,
                          Ref* dbias);
  void conv_transpose2d_backward_f32(const Ref& x, const Ref& w, const Ref& dy, Ref& dx, Ref& dw, Ref* dbias);
  void conv_transpose2d_backward_16(const Ref& x, const Ref& w, const Ref& dy, Precision p, Ref& dx, Ref& dw,
                                    Ref* dbias);
  void maxpool2d_f32(const Ref& x, Ref& y, IRef& argmax);
  void maxpool2d_16(const HRef& x, Precision p, HRef& y);
  void upsample_bilinear_f32(const Ref& x, Ref& y);
  void upsample_bilinear_16(const HRef& x, Precision p, HRef& y);
  void pad_concat_f32(const Ref& skip, const Ref& up, Ref& y);
  void pad_concat_16(const HRef& skip, const HRef& up, HRef& y);
  void convert_16(const Ref& x, Precision p, HRef& y);
  void prepare_conv_weights_16(const Ref& w, const Ref* bias, const BatchNormRefs* bn, Precision p, HRef& w16,
                               Ref& bias_out, const HRef& transformed);
  void prepare_conv_transpose_weights_16(const Ref& w, const Ref* bias, Precision p, HRef& w16, Ref& bias_out);
  void conv2d_prepared_16(const TensorRef& x, const HRef& w16, const HRef& transformed, const Ref& bias_out,
                          const Shape& weight, int pad, bool relu, Precision p, const TensorRef& y);
  void conv_transpose2d_prepared_16(const TensorRef& x, const HRef& w16, const Ref& bias_out, const Shape& weight,
                                    Precision p, const TensorRef& y);

  // The kernels' scratch, in one place. `floats`, `doubles`, `gather` and `rays` grow to the
  // largest request so far; the loss and reduction buffers have fixed sizes.
  struct Workspace {
    cuda::DeviceBuffer<float> floats;           // convolution weight-gradient partials
    cuda::DeviceBuffer<std::uint16_t> halves;   // 16-bit training: the input gradient's weights
    cuda::DeviceBuffer<double> doubles;         // BatchNorm and PFN statistics
    cuda::DeviceBuffer<std::int32_t> gather;    // the pillar gather's (and grid map's) arrays
    cuda::DeviceBuffer<std::uint32_t> rays;     // the ray walks' counts
    cuda::DeviceBuffer<double> sum_of_squares;  // kSumOfSquaresPartials partials, then the result
    cuda::DeviceBuffer<cuda::LossPartial> loss_partials;
    cuda::DeviceBuffer<cuda::LossResult> loss_result;
    // The Lovász term's bin counts and steps (cuda::lovasz_softmax_loss), made on its first use.
    cuda::DeviceBuffer<int> lovasz_counts;
    cuda::DeviceBuffer<double> lovasz_steps;
  };
  float* float_workspace(size_t count);
  std::uint16_t* half_workspace(size_t count);
  double* double_workspace(int64_t count);
  std::int32_t* gather_workspace(int64_t count);
  std::uint32_t* ray_workspace(int64_t count);
  template <class T>
  T* grow(cuda::DeviceBuffer<T>& buffer, size_t count);

  // Pinned memory for `bytes` of upload: the next free part of the staging buffer. When the
  // buffer is full it waits for the stream (earlier copies out of it are then done) and, the
  // first times, grows to hold everything uploaded between two waits.
  void* staging_slot(size_t bytes);
  // Pinned memory for a download of `bytes` (grown, never shrunk).
  void* readback_buffer(size_t bytes);
  void wait_for_stream();  // cudaStreamSynchronize; the staging buffer is free again
  void require_not_capturing(const char* op) const;
  // The vendor engine for `shape`, or nullptr where our kernels run it (Own, or an empty shape).
  cuda::Conv2dEngine* vendor_engine(const cuda::Conv2dShape& shape);
  // What the BatchNorm kernels sum their statistics with: `replicas`, or on a GPU, where it is
  // the run's Replicas, the NCCL statistics sum (made on the first call).
  ReplicaSum* batchnorm_sum(ReplicaSum* replicas);
#if !defined(PILLARSEG_CUDA_EMULATION)
  NcclCommunicator& nccl_communicator(Replicas& replicas);  // made on the first call
#endif

  CudaBackendOptions options_;
  std::string name_;
  cuda::Stream stream_;
  cuda::Event clock_events_[2];  // clock_ms(): the last two marks
  int clock_next_ = 0;
  bool clock_started_ = false;
  double clock_total_ms_ = 0;
  Workspace workspace_;
  // Incremented whenever a workspace moves: graphs recorded before name the old memory.
  int64_t workspace_generation_ = 0;
  cuda::PinnedBuffer staging_, readback_;
  size_t staging_used_ = 0;
  bool capturing_ = false;
  std::unique_ptr<cuda::Conv2dEngine> vendor_conv_;  // null with ConvolutionImpl::Own
#if !defined(PILLARSEG_CUDA_EMULATION)
  // Data-parallel training: the communicator, then the sums over it (destroyed before it).
  std::unique_ptr<NcclCommunicator> nccl_;
  std::unique_ptr<NcclGradientSum> nccl_gradients_;
  std::unique_ptr<NcclStatisticsSum> nccl_statistics_;
#endif
  CudaBackendStats stats_;
};

// "no CUDA device found: <reason>; use --device cpu", for the result of cudaGetDeviceCount.
std::string no_cuda_device_message(cudaError_t error, int device_count);

// A CudaBackend with default options but the Conv2d implementation and device of `options` (what
// make_backend() calls).
std::unique_ptr<Backend> make_cuda_device_backend(const BackendOptions& options);

// This build's device name for make_backend() ("cuda" on the GPU build, "emu" on the emulation)
// and its installer (install_cuda_backend or install_emulated_cuda_backend, engine/cuda/install.hpp).
#if defined(PILLARSEG_CUDA_EMULATION)
inline constexpr const char* kCudaBackendDevice = "emu";
inline void install_this_cuda_backend() { install_emulated_cuda_backend(); }
#else
inline constexpr const char* kCudaBackendDevice = "cuda";
inline void install_this_cuda_backend() { install_cuda_backend(); }
#endif

}  // namespace pillarseg::inline PILLARSEG_CUDA_NAMESPACE
