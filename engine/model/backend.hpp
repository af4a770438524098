// Backend: the ops of PillarSegNet on one device. The model (engine/model/pillarsegnet.*) is
// written once against this interface; CpuBackend runs the host/ reference ops, CudaBackend
// the kernels/ (on a GPU, or on the CPU through the CUDA emulation layer). Tensors are Refs:
// a pointer into the backend's memory (host or device) and a shape; a backend never
// allocates inside an op.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include "core/tensor.hpp"

namespace pillarseg {

enum class Device { Cpu, Cuda };

// A tensor in a backend's memory; T is float, int32_t or uint8_t.
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

// BatchNorm parameters, running statistics and the per-channel statistics a training forward
// saves for the backward. All (C).
struct BatchNormRefs {
  Ref gamma, beta, running_mean, running_var;
  Ref save_mean, save_invstd;
  float eps = 1e-5f, momentum = 0.1f;
};

enum class LossKind { CrossEntropy, Bce };

// Device work recorded once by Backend::capture() (a CUDA graph) and run again by replay(), on
// the memory the recorded ops named, with whatever it holds at replay time. Must not outlive its
// backend.
class CapturedGraph {
 public:
  virtual ~CapturedGraph() = default;
  virtual void replay() = 0;
};

struct AdamHyper {
  float lr = 1e-3f, beta1 = 0.9f, beta2 = 0.99f, eps = 1e-8f, weight_decay = 0.01f;
  int64_t step = 1;  // 1-based, for the bias correction
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
  // Waits for the work queued so far, then reads the backend's clock, in ms from an arbitrary
  // origin (stage timing): the host's steady clock here, CUDA events on the CUDA backend.
  virtual double clock_ms();

  // Graph capture: a backend that supports it records the ops that `work` queues, without
  // running them, and returns them for replay. Recorded ops must not allocate, upload, download
  // or wait (the model records only the evaluation forward's device work).
  virtual bool supports_capture() const { return false; }
  virtual std::unique_ptr<CapturedGraph> capture(const std::function<void()>& work);

  // Pillar feature net: decorated points (P, N, 10), W (C, 10) -> BN -> ReLU -> max over N
  // -> (P, C). Training uses batch statistics over all P*N rows and saves what backward needs
  // (the batch statistics in bn.save_*, the arg-max slot (P, C) in `argmax`, -1 where the
  // output is 0). Backward recomputes the linear output; d_points (P, N, 10) is scratch.
  // `scratch` is memory the caller plans for what a backend keeps whole during the op: room for
  // P N C floats in the training forward (the activations before the max) and 2 P N C in the
  // backward (the linear output and its gradient); a null scratch makes such a backend allocate
  // them itself, and a backend that works in smaller blocks ignores it.
  virtual void pfn_forward(const Ref& points, const Ref& weight, BatchNormRefs& bn, bool training,
                           IRef& argmax, Ref& out, const Ref& scratch) = 0;
  virtual void pfn_backward(const Ref& points, const Ref& weight, const BatchNormRefs& bn,
                            const IRef& argmax, const Ref& dout, Ref& d_points, Ref& dweight,
                            Ref& dgamma, Ref& dbeta, const Ref& scratch) = 0;
  // Pillar features (P, C) + cells (P, 3: batch, iy, ix) -> canvas (B, C, H, W) at channel
  // offset `channel0` of a canvas with more channels (the other channels are untouched).
  virtual void scatter_forward(const Ref& features, const IRef& cells, int channel0, Ref& canvas) = 0;
  virtual void scatter_backward(const Ref& dcanvas, const IRef& cells, int channel0, Ref& dfeatures) = 0;
  // Copies x (B, Cx, H, W) into channels [channel0, channel0 + Cx) of y (B, Cy, H, W), and back.
  virtual void copy_channels(const Ref& x, int channel0, Ref& y) = 0;
  virtual void extract_channels(const Ref& y, int channel0, Ref& x) = 0;

  // Stride-1 convolution, weight (O, I, k, k), zero padding `pad`.
  virtual void conv2d_forward(const Ref& x, const Ref& w, const Ref* bias, int pad, Ref& y) = 0;
  virtual void conv2d_backward(const Ref& x, const Ref& w, const Ref& dy, int pad, Ref* dx, Ref& dw, Ref* dbias) = 0;
  // ConvTranspose2d kernel 2 stride 2, weight (I, O, 2, 2). The backward may overwrite dy (the
  // CPU backend rearranges it in place instead of keeping a second tensor of its size).
  virtual void conv_transpose2d_forward(const Ref& x, const Ref& w, const Ref* bias, Ref& y) = 0;
  virtual void conv_transpose2d_backward(const Ref& x, const Ref& w, const Ref& dy, Ref& dx, Ref& dw, Ref* dbias) = 0;
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
  virtual void maxpool2x2_forward(const Ref& x, Ref& y, IRef& argmax) = 0;
  virtual void maxpool2x2_backward(const Ref& dy, const IRef& argmax, Ref& dx) = 0;
  virtual void upsample2x_forward(const Ref& x, Ref& y) = 0;
  virtual void upsample2x_backward(const Ref& dy, Ref& dx) = 0;
  // y = [skip, zero-padded up] along channels.
  virtual void pad_concat_forward(const Ref& skip, const Ref& up, Ref& y) = 0;
  virtual void pad_concat_backward(const Ref& dy, Ref& dskip, Ref& dup) = 0;
  // a += b (gradient of a tensor used twice).
  virtual void add_inplace(Ref& a, const Ref& b) = 0;

  // Head outputs: logits (B, 12, H, W).
  virtual void softmax(const Ref& logits, Ref& probs) = 0;
  virtual void argmax(const Ref& logits, LRef& labels) = 0;  // (B, H, W), class ids 1..12
  // Mean loss over labelled cells; writes dlogits. coefficients: (13) per class id.
  virtual double loss(LossKind kind, const Ref& logits, const LRef& labels, const Ref& coefficients,
                      Ref& dlogits) = 0;

  // Optimiser over one flat parameter array.
  virtual double sum_of_squares(const Ref& x) = 0;
  virtual void scale(Ref& x, float factor) = 0;
  virtual void adam_step(Ref& param, const Ref& grad, Ref& m, Ref& v, const AdamHyper& hyper) = 0;
};

std::unique_ptr<Backend> make_cpu_backend();
// The CPU backend on the host/ reference ops alone (no Winograd, Conv -> BN -> ReLU composed):
// what the fast paths are tested and benchmarked against.
std::unique_ptr<Backend> make_cpu_reference_backend();
// The CUDA backend, its Conv2d by `convolution`: "own" (our kernels), "cudnn" or "cublas" (for
// comparison; GPU build only); throws pillarseg::Error with the reason when it is not available
// (a build without it, or no device, or the convolution).
std::unique_ptr<Backend> make_cuda_backend(const std::string& convolution = "own");
// `convolution` other than "own" needs device "cuda".
std::unique_ptr<Backend> make_backend(const std::string& device, const std::string& convolution = "own");
// What make_cuda_backend() calls. pillarseg_lib holds no CUDA code: a program linked with a CUDA
// backend library installs its factory (engine/cuda/cuda_backend.hpp, install_cuda_backend()).
using BackendFactory = std::unique_ptr<Backend> (*)(const std::string& convolution);
void set_cuda_backend_factory(BackendFactory factory);

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
