// Backend: the ops of PillarSegNet on one device, from a scan's raw points to the label map. The
// input pipeline (engine/pipeline/) and the model (engine/model/pillarsegnet.*) are written once
// against this interface; CpuBackend runs the host/ reference ops, CudaBackend the kernels/ (on a
// GPU, or on the CPU through the CUDA emulation layer). Tensors are Refs: a pointer into the
// backend's memory (host or device) and a shape; a backend never allocates inside an op except
// its own scratch, which grows to the largest request and then stays.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include "core/adam_options.hpp"
#include "core/error.hpp"
#include "core/eigen.hpp"
#include "core/grid.hpp"
#include "core/memory_budget.hpp"
#include "core/replicas.hpp"
#include "core/dtype.hpp"
#include "core/tensor.hpp"

namespace pillarseg {

enum class Device { Cpu, Cuda };

// The arithmetic of the evaluation forward's U-Net: FP32, or BF16 / FP16 (convolutions with FP32
// accumulation, activations stored in 16 bits between them: on the tensor cores of the CUDA
// backend, BF16 also on the CPU's AVX512_BF16). The PFN, scatter, head output, softmax, arg-max
// and training run in FP32.
//
// INT8 (DESIGN.md section 10): the U-Net's convolutions on INT8 weights (per output channel) and
// inputs (per tensor, the calibrated scales of engine/model/calibration.hpp) with INT32
// accumulation, BatchNorm folded, the epilogue in FP32; the activations between them in BF16; the
// head in FP32 arithmetic (FP32 prepared weights) on the U-Net's BF16 last output; the occupancy
// stream's convolutions, the PFN, softmax and arg-max in FP32.
enum class Precision { F32, BF16, F16, I8 };
const char* precision_name(Precision p);  // "fp32", "bf16", "fp16", "int8"
// "fp32", "bf16", "fp16" or "int8"; throws pillarseg::Error naming `what` (the option) otherwise.
Precision parse_precision(const std::string& text, const std::string& what = "--precision");

// A tensor in a backend's memory; T is float, int32_t, uint32_t or uint8_t.
template <class T>
struct RefT {
  T* data = nullptr;
  Shape shape;
  int64_t numel() const { return shape_numel(shape); }
  int64_t dim(int i) const { return shape.at(static_cast<size_t>(i < 0 ? static_cast<int>(shape.size()) + i : i)); }
  size_t bytes() const { return static_cast<size_t>(numel()) * sizeof(T); }
};
using Ref = RefT<float>;
using IRef = RefT<int32_t>;
using LRef = RefT<uint8_t>;
using URef = RefT<uint32_t>;  // ray counts
using HRef = RefT<uint16_t>;  // 16-bit floats (BF16 or FP16) as bits

// Argument checks of the backends' ops: "op: what must be (shape), got (shape)".
template <class T>
void require_shape(const char* op, const char* what, const RefT<T>& r, const Shape& expected) {
  PS_CHECK(r.shape == expected, "{}: {} must be {}, got {}", op, what, shape_str(expected), shape_str(r.shape));
}
template <class T>
void require_rank(const char* op, const char* what, const RefT<T>& r, size_t rank) {
  PS_CHECK(r.shape.size() == rank, "{}: {} must have {} dimensions, got {}", op, what, rank, shape_str(r.shape));
}

// Rows [offset, offset + rows) of a tensor whose first dimension counts rows (a view of the same
// memory); `op` names the caller in the error when they lie outside it.
template <class T>
RefT<T> row_slice(const char* op, const RefT<T>& whole, int64_t offset, int64_t rows) {
  PS_CHECK(!whole.shape.empty() && offset >= 0 && rows >= 0 && offset + rows <= whole.dim(0),
           "{}: rows [{}, {}) outside the {} planned", op, offset, offset + rows,
           whole.shape.empty() ? 0 : whole.dim(0));
  Shape shape = whole.shape;
  shape[0] = rows;
  const int64_t row_size = whole.dim(0) > 0 ? whole.numel() / whole.dim(0) : 0;
  return RefT<T>{whole.data + offset * row_size, std::move(shape)};
}

// The live-rows argument of decorate_points and pfn_forward: nullptr when empty (every row is
// live), else its one int32 (in the backend's memory).
inline const int32_t* live_rows_data(const char* op, const IRef& live_rows) {
  if (live_rows.data == nullptr) return nullptr;
  require_shape(op, "live_rows", live_rows, {1});
  return live_rows.data;
}

// A tensor of any dtype in a backend's memory (DESIGN.md section 7: the dtype belongs to the
// tensor, not to op or method names). The ops whose tensors come in several dtypes (the
// activations: FP32, or BF16 / FP16 as bits; prepared weights) take it; an FP32 Ref converts to
// it.
struct TensorRef {
  void* data = nullptr;
  Shape shape;
  DType dtype = DType::F32;
  TensorRef() = default;
  TensorRef(void* data_, Shape shape_, DType dtype_) : data(data_), shape(std::move(shape_)), dtype(dtype_) {}
  TensorRef(const Ref& r) : data(r.data), shape(r.shape), dtype(DType::F32) {}  // NOLINT: implicit on purpose
  int64_t numel() const { return shape_numel(shape); }
  int64_t dim(int i) const { return shape.at(static_cast<size_t>(i < 0 ? static_cast<int>(shape.size()) + i : i)); }
  size_t bytes() const { return static_cast<size_t>(numel()) * dtype_bytes(dtype); }
  // The typed views; `op` (the caller) names the error when the dtype is another.
  Ref f32(const char* op) const {
    PS_CHECK(dtype == DType::F32, "{}: expected an f32 tensor {}, got {}", op, shape_str(shape), dtype_name(dtype));
    return Ref{static_cast<float*>(data), shape};
  }
  RefT<int8_t> i8(const char* op) const {
    PS_CHECK(dtype == DType::I8, "{}: expected an i8 tensor {}, got {}", op, shape_str(shape), dtype_name(dtype));
    return RefT<int8_t>{static_cast<int8_t*>(data), shape};
  }
  HRef bits16(const char* op) const {
    PS_CHECK(is_float16(dtype), "{}: expected a bf16 or f16 tensor {}, got {}", op, shape_str(shape),
             dtype_name(dtype));
    return HRef{static_cast<uint16_t*>(data), shape};
  }
};
// The precision of a dtype (F32, BF16, F16, I8), and back.
Precision precision_of(DType dtype);
DType dtype_of(Precision p);

// The INT8 kernels' activation argument (engine/cpu/int8_conv.hpp): FP32, or BF16 (`half`).
struct ActRef {
  void* data = nullptr;
  Shape shape;
  bool half = false;
  int64_t numel() const { return shape_numel(shape); }
  int64_t dim(int i) const { return shape.at(static_cast<size_t>(i)); }
};

// BatchNorm parameters, running statistics and the per-channel statistics a training forward
// saves for the backward. All (C).
struct BatchNormRefs {
  Ref gamma, beta, running_mean, running_var;
  Ref save_mean, save_invstd;
  float eps = 1e-5f, momentum = 0.1f;
  // Synchronised BatchNorm of a data-parallel run (core/replicas.hpp), on a backend that
  // supports_synchronized_batchnorm(); nullptr: this process's batch.
  ReplicaSum* replicas = nullptr;
};

// CrossEntropyLovasz: the weighted cross-entropy plus the Lovász-softmax loss (host/losses.hpp).
enum class LossKind { CrossEntropy, Bce, CrossEntropyLovasz };

// What Backend::loss computes: the kind, and the weight of its Lovász term. A data-parallel
// replica gives its Lovász term 1 / R: the loss of a class's IoU over the whole batch is not a sum
// over cells, so each replica ranks its own share's cells (as PyTorch's DDP runs it) and the
// replicas' sum is the mean of their terms.
struct LossSpec {
  LossSpec(LossKind k = LossKind::CrossEntropy, float lovasz = 1.0f)  // NOLINT: from a LossKind
      : kind(k), lovasz_weight(lovasz) {}
  LossKind kind;
  float lovasz_weight;
};

// Device work recorded once by Backend::capture() (a CUDA graph) and run again by replay(), on
// the memory the recorded ops named, with whatever it holds at replay time. Must not outlive its
// backend.
class CapturedGraph {
 public:
  virtual ~CapturedGraph() = default;
  virtual void replay() = 0;
  // False once the backend has moved memory the recorded ops name (its scratch grew since the
  // capture): the graph must be recorded again before the next replay.
  virtual bool valid() const { return true; }
};

class Backend {
 public:
  virtual ~Backend() = default;
  virtual Device device() const = 0;
  virtual std::string name() const = 0;

  // Memory.
  virtual void* allocate(size_t bytes) = 0;
  virtual void deallocate(void* p) noexcept = 0;
  virtual void upload(void* dst, const void* host_src, size_t bytes) = 0;
  virtual void download(void* host_dst, const void* src, size_t bytes) = 0;
  virtual void fill_zero(void* dst, size_t bytes) = 0;
  virtual void synchronize() {}
  // What allocate() may still take, for the size checks made before planning (the model's and
  // the input pipeline's): the host's memory (core/memory_budget.hpp) unless the backend has
  // memory of its own; PILLARSEG_MEMORY_LIMIT replaces it on every backend.
  virtual MemoryBudget memory_budget() const;
  // Waits for the work queued so far, then reads the backend's clock, in ms from an arbitrary
  // origin (stage timing): the host's steady clock here, CUDA events on the CUDA backend.
  virtual double clock_ms();

  // Graph capture: a backend that supports it records the ops that `work` queues, without
  // running them, and returns them for replay. Recorded ops must not allocate, upload, download
  // or wait (the model records only the evaluation forward's device work).
  virtual bool supports_capture() const { return false; }
  virtual std::unique_ptr<CapturedGraph> capture(const std::function<void()>& work);
  // What the backend has done so far: the allocations a steady state must not add to, the bytes
  // it moved between the host and the device, the graphs it recorded and replayed. The CPU
  // backend counts nothing (its memory is the host's).
  struct Counters {
    int64_t allocations = 0;  // device and pinned allocations, scratch growth included
    int64_t bytes_uploaded = 0, bytes_downloaded = 0;
    int64_t graphs_captured = 0, graph_replays = 0;
    // Counted by the CUDA emulation only (-1 elsewhere): the flops the tensor-core instructions
    // issued (mma.sync m16n8k16: 4,096 each, the padding of tiles and of K included) and the
    // bytes cp.async copied into shared memory.
    int64_t tensor_core_flops = -1, async_copy_bytes = -1;
  };
  virtual Counters counters() const { return {}; }
  // Makes this backend's device the calling thread's current one (the CUDA runtime keeps it per
  // thread); a program that runs a backend from another thread than the one that made it calls
  // this first.
  virtual void make_current() {}

  // ---- input preparation: a scan's points -> the network's inputs (DESIGN.md section 6) ----
  // points (M, 4) rows x, y, z, reflectance in the backend's memory. A row with a non-finite
  // coordinate belongs to no pillar and casts no ray.

  // Rows [num_points[0], M) of points (M, 4) = NaN; num_points (1) in the backend's memory. A scan
  // of any size up to M then runs in the buffers (and the graph) planned for M.
  virtual void pad_points(const IRef& num_points, Ref& points) = 0;
  // Pillar gather, inference sampling (host/pillar_gather.hpp): points (M, 4) -> cell (R, 2) rows
  // (iy, ix), point_index (R, N), count (R) and num_pillars (1) = P', for R >= pillar_rows(M,
  // grid, max_pillars). Returns the leading rows the next ops must read: P' where the backend
  // knows it without waiting for the device (the CPU backend), else R (rows past P' are inert:
  // cell (-1, -1), count 0, point_index -1).
  virtual int64_t pillar_gather(const Ref& points, const GridSpec& grid, int max_pillars, IRef& cell,
                                IRef& point_index, IRef& count, IRef& num_pillars) = 0;
  // The decorated points (rows, N, 10) of the pillars (host/point_decoration.hpp): cell (rows, 2),
  // point_index (rows, N), count (rows) from pillar_gather. live_rows: empty, or pillar_gather's
  // num_pillars (1): the rows at or past its value are inert and may be left unwritten (a device
  // reads it when the work runs, so a recorded graph stops at each scan's own P').
  virtual void decorate_points(const Ref& points, const GridSpec& grid, const IRef& cell,
                               const IRef& point_index, const IRef& count, const IRef& live_rows,
                               Ref& out) = 0;
  // cell (rows, 2) -> cells (rows, 3) = (sample, iy, ix), (-1, -1, -1) for an inert row.
  virtual void batch_cells(const IRef& cell, int sample, IRef& cells) = 0;
  // 2D ray counts (host/raywalk.hpp): points (M, 4), the sensor origin in their frame ->
  // transmissions, detections (H, W).
  virtual void observability_2d(const Ref& points, const Eigen::Vector3d& origin,
                                const GridSpec& grid, URef& transmissions, URef& detections) = 0;
  // The 2D occupancy input (host/observability_input.hpp): (H W values) = log(1 + t + d).
  virtual void observability_input(const URef& transmissions, const URef& detections,
                                   Ref& out) = 0;
  // 3D occupancy probability (Z, H, W) (host/raywalk.hpp).
  virtual void occupancy_3d(const Ref& points, const Eigen::Vector3d& origin, const GridSpec& grid,
                            Ref& probability) = 0;
  // The six grid-map layers (6, H, W) (host/grid_map_features.hpp).
  virtual void grid_map_features(const Ref& points, const GridSpec& grid, const URef& detections,
                                 const URef& transmissions, Ref& out) = 0;
  // labels (H W values) = 0, and probabilities (K planes of H W) = 0 when given, where no ray
  // touched the cell (host/mask_unobserved.hpp).
  virtual void mask_unobserved(const URef& transmissions, const URef& detections, LRef& labels,
                               Ref* probabilities) = 0;

  // Pillar feature net: decorated points (P, N, 10), W (C, 10) -> BN -> ReLU -> max over N
  // -> (P, C). Training uses batch statistics over all P*N rows and saves what backward needs
  // (the batch statistics in bn.save_*, the arg-max slot (P, C) in `argmax`, -1 where the
  // output is 0). The backward recomputes the linear output and gives the parameters'
  // gradients (the points are the network's input: none for them). live_rows (evaluation only;
  // empty in training, whose statistics take every row): as decorate_points', the rows of out at
  // or past its value may be left unwritten.
  virtual void pfn_forward(const Ref& points, const Ref& weight, BatchNormRefs& bn, bool training,
                           const IRef& live_rows, IRef& argmax, Ref& out) = 0;
  virtual void pfn_backward(const Ref& points, const Ref& weight, const BatchNormRefs& bn,
                            const IRef& argmax, const Ref& dout, Ref& dweight, Ref& dgamma,
                            Ref& dbeta) = 0;
  // Pillar features (P, C) + cells (P, 3: batch, iy, ix) -> canvas (B, C, H, W) at channel
  // offset `channel0` of a canvas with more channels (the other channels are untouched); an FP32
  // canvas, or a 16-bit one (the values rounded to its dtype; a cell outside the canvas, an inert
  // row's, is skipped), so that a mixed-precision U-Net's input needs no FP32 canvas.
  virtual void scatter_forward(const Ref& features, const IRef& cells, int channel0, const TensorRef& canvas) = 0;
  virtual void scatter_backward(const Ref& dcanvas, const IRef& cells, int channel0, Ref& dfeatures) = 0;
  // Copies x (B, Cx, H, W) into channels [channel0, channel0 + Cx) of y (B, Cy, H, W) (both of
  // one dtype), and back (FP32).
  virtual void copy_channels(const TensorRef& x, int channel0, const TensorRef& y) = 0;
  virtual void extract_channels(const Ref& y, int channel0, Ref& x) = 0;

  // Stride-1 convolution, weight (O, I, k, k), zero padding `pad`. The backward's arithmetic:
  // `compute` F32, or BF16 / FP16 with x, dy and w rounded to it and FP32 accumulation on the
  // tensor cores (kernels/conv2d_mma.cuh; supports_training_precision() says where); its
  // tensors are FP32 either way, and the backend keeps the flipped 16-bit weights and the weight
  // gradient's partial sums in its own scratch.
  virtual void conv2d_forward(const Ref& x, const Ref& w, const Ref* bias, int pad, Ref& y) = 0;
  virtual void conv2d_backward(const Ref& x, const Ref& w, const Ref& dy, int pad, Ref* dx, Ref& dw, Ref* dbias,
                               DType compute = DType::F32) = 0;
  // ConvTranspose2d kernel 2 stride 2, weight (I, O, 2, 2).
  virtual void conv_transpose2d_forward(const Ref& x, const Ref& w, const Ref* bias, Ref& y) = 0;
  virtual void conv_transpose2d_backward(const Ref& x, const Ref& w, const Ref& dy, Ref& dx, Ref& dw, Ref* dbias,
                                         DType compute = DType::F32) = 0;
  // Eval-mode Conv2d -> BatchNorm (running statistics) -> ReLU, y = relu(bn(conv(x, w) + bias)),
  // which a backend may run as one pass (BatchNorm folded into the convolution's output). The
  // default composes conv2d_forward and batchnorm_relu_forward, the latter in place on y.
  virtual void conv2d_bn_relu_eval(const Ref& x, const Ref& w, const Ref* bias, const BatchNormRefs& bn, int pad,
                                   Ref& y) {
    conv2d_forward(x, w, bias, pad, y);
    BatchNormRefs running = bn;
    batchnorm_relu_forward(y, running, /*training=*/false, y);
  }
  // BatchNorm over channels (axis 1) followed by ReLU; y = relu(bn(x)). The backward's dx may
  // be dy (in place).
  virtual void batchnorm_relu_forward(const Ref& x, BatchNormRefs& bn, bool training, Ref& y) = 0;
  virtual void batchnorm_relu_backward(const Ref& x, const Ref& y, const Ref& dy, const BatchNormRefs& bn, Ref& dx,
                                       Ref& dgamma, Ref& dbeta) = 0;
  // Max-pool 2x2 of FP32 (with the arg-max the backward reads) or 16-bit activations (argmax
  // null: the evaluation keeps none).
  virtual void maxpool2d_forward(const TensorRef& x, const TensorRef& y, IRef* argmax) = 0;
  virtual void maxpool2d_backward(const Ref& dy, const IRef& argmax, Ref& dx) = 0;
  // Bilinear x2 (align_corners), x and y of one dtype.
  virtual void upsample_bilinear_forward(const TensorRef& x, const TensorRef& y) = 0;
  virtual void upsample_bilinear_backward(const Ref& dy, Ref& dx) = 0;
  // y = [skip, zero-padded up] along channels, all of one dtype.
  virtual void pad_concat_forward(const TensorRef& skip, const TensorRef& up, const TensorRef& y) = 0;
  virtual void pad_concat_backward(const Ref& dy, Ref& dskip, Ref& dup) = 0;
  // a += b (gradient of a tensor used twice).
  virtual void add_inplace(Ref& a, const Ref& b) = 0;

  // Head outputs: logits (B, 12, H, W).
  virtual void softmax(const Ref& logits, Ref& probs) = 0;
  virtual void argmax(const Ref& logits, LRef& labels) = 0;  // (B, H, W), class ids 1..12
  // Test-time flips (ScanSegmenter, SegmenterOptions::flips), on the device: sum (B, K, H, W) +=
  // x mirrored back (rows where mirror_y, columns where mirror_x; host/mirror_add.hpp), one float
  // addition per element; and the class ids of the largest positive value of the sum, 0 where
  // none is (a cell masked as unobserved in every copy).
  virtual void mirror_add(const Ref& x, bool mirror_y, bool mirror_x, Ref& sum) = 0;
  virtual void argmax_positive(const Ref& values, LRef& labels) = 0;  // (B, H, W), class ids 0..12
  // The loss of spec (mean over labelled cells; the Lovász term over the present classes); writes
  // dlogits. coefficients: (13) per class id, the cross-entropy's and BCE's.
  virtual double loss(const LossSpec& spec, const Ref& logits, const LRef& labels, const Ref& coefficients,
                      Ref& dlogits) = 0;

  // Optimiser over one flat parameter array.
  virtual double sum_of_squares(const Ref& x) = 0;
  virtual void scale(Ref& x, float factor) = 0;
  virtual void adam_step(Ref& param, const Ref& grad, Ref& m, Ref& v, int64_t step, const AdamOptions& options) = 0;
  // Data-parallel training: values (a piece of the parameter gradients) summed over the replicas
  // in replica order, the same bits on every replica, begun once the work queued so far has
  // written them, so that the sum may run while the backward goes on; end_sums_over_replicas()
  // completes (on a device: queues the wait for) every piece begun. The default goes through the
  // host: on the CPU Replicas::begin_sum at once; on a device the piece is downloaded, summed and
  // uploaded before begin returns. The CUDA backend on a GPU sums in device memory over NCCL
  // where it is installed, on a stream of its own.
  virtual void begin_sum_over_replicas(Ref& values, Replicas& replicas);
  virtual void end_sums_over_replicas(Replicas& replicas);

  // ---- mixed-precision evaluation convolutions (kernels/conv2d_mma.cuh is the spec; the CPU's
  // are engine/cpu/bf16_conv.hpp) ----
  // Whether this backend runs them in `p` (F32 always); else false with the reason in why_not.
  virtual bool supports_precision(Precision p, std::string* why_not = nullptr) const;
  // weight (O, I, k, k) [, bias (O)] [, eval BatchNorm] -> prepared (O, Kp)
  // (op::half16_conv_weights) rounded to its dtype with the BatchNorm scale multiplied in,
  // bias_out (O) with its shift added; and where the backend has one, `transformed`: a form of the
  // same weights of its own (the CPU's Winograd-transformed U), made here once rather than in
  // every convolution, of prepared_conv_transform_elements() elements of `dtype` (the caller
  // plans it beside the prepared weights; data null when there is none).
  virtual int64_t prepared_conv_transform_elements(const Shape& weight, int pad, DType dtype) const;
  // The arithmetic of an evaluation convolution of `weight` (pad `pad`; transposed: (I, O, 2, 2))
  // on activations of the 16-bit `half`: `half`, or F32 where this backend's FP32 kernel for it
  // is the faster on this machine, on the same 16-bit activations (FP32 prepared weights:
  // op::prepared_conv_weights). A fixed rule of the backend's kernels and the shape, never a
  // timing, so that a model computes the same bits on a machine from run to run.
  virtual DType prepared_conv_dtype(const Shape& weight, int pad, bool transposed, DType half) const;
  // INT8 prepared weights (DESIGN.md section 10) also write `weight_scale` (O): the per-output-
  // channel symmetric scales max |w'| / 127 of the weights w' with the BatchNorm folded in, the
  // prepared int8 values q = clamp(round_half_even(w' / scale), -127, 127); null for 16-bit.
  virtual void prepare_conv_weights(const Ref& w, const Ref* bias, const BatchNormRefs* bn, const TensorRef& prepared,
                                    Ref& bias_out, const TensorRef& transformed, const Ref* weight_scale = nullptr);
  // weight (I, O, 2, 2) [, bias (O)] -> prepared (4 O, Kp), bias_out (4 O) [, weight_scale (4 O)].
  virtual void prepare_conv_transpose_weights(const Ref& w, const Ref* bias, const TensorRef& prepared, Ref& bias_out,
                                              const Ref* weight_scale = nullptr);
  // y = act(conv(x, prepared) + bias_out) for the weight shape `weight` (O, I, k, k) and `pad`,
  // in the prepared weights' arithmetic (FP32 prepared weights: FP32 sums of x as stored, the INT8
  // forward's 1 x 1 head on every backend); x and y FP32 or 16-bit; `transformed` as
  // prepare_conv_weights made it (or data null). INT8: x quantized as `input` says (Int8Input),
  // INT32 sums, y = act(acc input.scale weight_scale[o] + bias_out[o]).
  virtual void conv2d_prepared_forward(const TensorRef& x, const TensorRef& prepared, const TensorRef& transformed,
                                       const Ref& bias_out, const Shape& weight, int pad, bool relu,
                                       const TensorRef& y, const Ref* weight_scale = nullptr,
                                       Int8Input input = {});
  // y (B, O, 2H, 2W) = the transposed convolution of x (B, I, H, W) for weight (I, O, 2, 2).
  virtual void conv_transpose2d_prepared_forward(const TensorRef& x, const TensorRef& prepared, const Ref& bias_out,
                                                 const Shape& weight, const TensorRef& y,
                                                 const Ref* weight_scale = nullptr, Int8Input input = {});
  // Training in `p` (FP32 tensors and master weights; the convolutions' forward is
  // conv2d_prepared_forward / conv_transpose2d_prepared_forward on weights prepared without
  // BatchNorm, the backward conv2d_backward / conv_transpose2d_backward with `compute` p):
  // whether this backend has them, else false with the reason.
  virtual bool supports_training_precision(Precision p, std::string* why_not = nullptr) const;
  // Whether the training BatchNorm ops (batchnorm_relu_*, pfn_*) honour BatchNormRefs::replicas,
  // as data-parallel training needs; else false with the reason in why_not.
  virtual bool supports_synchronized_batchnorm(std::string* why_not = nullptr) const;
  // x FP32 -> y rounded to y's dtype (BF16 or FP16, to nearest even).
  virtual void convert(const Ref& x, const TensorRef& y);

 protected:
  // Throws unless this backend supports_precision(p), naming the backend and why.
  void require_precision(Precision p) const;
};

std::unique_ptr<Backend> make_cpu_backend();
// The CPU backend on the host/ reference ops alone (no Winograd, Conv -> BN -> ReLU composed):
// what the fast paths are tested and benchmarked against.
std::unique_ptr<Backend> make_cpu_reference_backend();
// The CPU backend with its BF16 convolutions' micro-kernel on the exact scalar model of the
// AVX512_BF16 instructions (engine/cpu/bf16_isa_emulated.hpp), and with `amx` the Winograd
// products on the model of the AMX tiles, and its INT8 convolutions on the models of VPDPBUSD
// or (`amx`) the AMX-INT8 tiles (engine/cpu/int8_isa_emulated.hpp), on any CPU: how the tests
// check --precision bf16 and int8 on the CPU where it lacks them. Slow; otherwise
// make_cpu_backend().
std::unique_ptr<Backend> make_cpu_backend_emulated_bf16(bool amx = false);

// How make_backend() makes a backend.
struct BackendOptions {
  std::string convolution = "own";  // Conv2d: own (our kernels), cudnn or cublas (--device cuda)
  int cuda_device = 0;              // the CUDA device ordinal (--device cuda)
};
// device: "cpu", "cuda" (the CUDA backend on a GPU) or "emu" (the CUDA backend on the CPU
// emulation, for verification). Throws pillarseg::Error with the reason when it is not available
// (a build without it, no device, a convolution other than "own" off the GPU).
std::unique_ptr<Backend> make_backend(const std::string& device, const BackendOptions& options = {});
// The devices make_backend() takes in this program, for messages: "cpu", "cpu, emu", ...
std::string available_devices();

// What make_backend("cuda") and make_backend("emu") call. The engine holds no CUDA code: a
// program linked with a CUDA backend library installs its factory (engine/cuda/install.hpp).
using BackendFactory = std::unique_ptr<Backend> (*)(const BackendOptions& options);
// device "cuda" or "emu"; a null factory uninstalls.
void set_backend_factory(const std::string& device, BackendFactory factory);

// R, the rows of pillar_gather's outputs for M points: P when max_pillars P > 0, else min(M,
// W H), room for every non-empty pillar.
int64_t pillar_rows(int64_t num_points, const GridSpec& grid, int max_pillars);

// Owns one allocation of a backend and hands out Refs from it in order (a bump allocator);
// `reset()` forgets them, `reserve()` grows the block (invalidating earlier Refs). Planning
// runs twice: after begin_measure(), take() only counts bytes (and returns null pointers);
// then reserve(used()), reset(), and the same takes get real memory.
class Arena {
 public:
  explicit Arena(Backend& backend) : backend_(&backend) {}
  ~Arena() { release(); }
  Arena(const Arena&) = delete;
  Arena& operator=(const Arena&) = delete;

  void begin_measure() {
    measuring_ = true;
    used_ = 0;
  }
  void reserve(size_t bytes);
  void reset() { used_ = 0; }
  void release() noexcept;
  template <class T>
  RefT<T> take(Shape shape) {
    RefT<T> r;
    r.shape = std::move(shape);
    r.data = static_cast<T*>(take_bytes(r.bytes()));
    return r;
  }
  size_t used() const { return used_; }
  size_t capacity() const { return capacity_; }

 private:
  void* take_bytes(size_t bytes);
  Backend* backend_;
  void* base_ = nullptr;
  size_t capacity_ = 0, used_ = 0;
  bool measuring_ = false;
};

}  // namespace pillarseg
