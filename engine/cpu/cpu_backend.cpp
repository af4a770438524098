// CpuBackend: the Backend interface on the host/ reference ops (Eigen, OpenMP). Refs are
// host pointers; each op wraps them as Tensor views (no copies) and calls host/. The 3x3 / pad 1
// convolutions (forward, input and weight gradients, and eval-mode Conv -> BatchNorm -> ReLU in
// one pass) run on the Winograd fast path host/conv2d_winograd, which is tested against
// host/conv2d; the PFN runs per block of pillars (engine/cpu/pfn_blocked, tested against
// host/pfn); --precision bf16 runs the U-Net on engine/cpu/bf16_conv (AVX512_BF16).
// make_cpu_reference_backend() has none of these.
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <map>
#include <span>
#include <vector>

#include "core/eigen.hpp"
#include "core/error.hpp"
#include "core/host_memory.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"
#include "engine/cpu/bf16_conv.hpp"
#include "engine/cpu/half_ops.hpp"
#include "engine/cpu/int8_conv.hpp"
#include "engine/cpu/pfn_blocked.hpp"
#include "engine/cpu/pointwise_conv.hpp"
#include "engine/backend/backend.hpp"
#include "host/adam.hpp"
#include "host/batchnorm.hpp"
#include "host/conv2d.hpp"
#include "host/conv2d_winograd.hpp"
#include "host/conv_transpose2d.hpp"
#include "host/grid_map_features.hpp"
#include "host/mask_unobserved.hpp"
#include "host/losses.hpp"
#include "host/maxpool2d.hpp"
#include "host/mirror_add.hpp"
#include "host/observability_input.hpp"
#include "host/pad_concat.hpp"
#include "host/pfn.hpp"
#include "host/pillar_gather.hpp"
#include "host/point_decoration.hpp"
#include "host/pad_points.hpp"
#include "host/raywalk.hpp"
#include "host/scatter.hpp"
#include "host/softmax.hpp"
#include "host/upsample_bilinear.hpp"

namespace pillarseg {

namespace {

template <class T>
Tensor<T> view(const RefT<T>& r) {
  return Tensor<T>::view(r.data, r.shape);
}

// points (M, 4) in host memory as the M points they hold.
std::span<const Point> as_points(const Ref& points) {
  PS_CHECK(points.shape.size() == 2 && points.dim(1) == 4,
           "points must be (M, 4) rows x y z r, got {}", shape_str(points.shape));
  return {reinterpret_cast<const Point*>(points.data), static_cast<size_t>(points.dim(0))};
}

// The live rows of `rows` that a live-rows argument (host memory here) leaves: its value,
// clamped to [0, rows].
int64_t live_row_count(const char* op, const IRef& live_rows, int64_t rows) {
  const int64_t live = *live_rows_data(op, live_rows);
  return std::clamp<int64_t>(live, 0, rows);
}

host::BatchNormOptions bn_options(const BatchNormRefs& bn) { return {bn.eps, bn.momentum, bn.replicas}; }

host::BatchNormSaved<float> bn_saved(const BatchNormRefs& bn) {
  return {view(bn.save_mean), view(bn.save_invstd)};
}

class CpuBackend final : public Backend {
 public:
  CpuBackend(bool fast_paths, cpu::Bf16Kernels bf16_kernels, cpu::Int8Kernels int8_kernels,
             bool bf16_dot_outpaces_fma = false)
      : fast_paths_(fast_paths), bf16_kernels_(bf16_kernels), int8_kernels_(int8_kernels),
        bf16_dot_outpaces_fma_(bf16_dot_outpaces_fma) {}
  Device device() const override { return Device::Cpu; }
  std::string name() const override { return fast_paths_ ? "cpu" : "cpu-reference"; }

  // BF16 (engine/cpu/bf16_conv.hpp): the AVX512_BF16 micro-kernel where this CPU has it (asked
  // at run time), with the Winograd products on AMX-BF16 tiles where it has those too, or their
  // exact scalar models for the tests; not in the reference backend, and no FP16 (the CPU's
  // 16-bit type is BF16).
  // INT8 (engine/cpu/int8_conv.hpp): the AVX512-VNNI micro-kernel, or AMX-INT8 tiles where the
  // CPU has them, or their models for the tests; its 16-bit activations move by the BF16 data
  // movement ops, which need no BF16 instructions.
  bool supports_precision(Precision p, std::string* why_not) const override {
    if (p == Precision::F32) return true;
    std::string why;
    const bool emulated =
        bf16_kernels_ == cpu::Bf16Kernels::Emulated || bf16_kernels_ == cpu::Bf16Kernels::AmxEmulated;
    const bool int8_emulated =
        int8_kernels_ == cpu::Int8Kernels::Emulated || int8_kernels_ == cpu::Int8Kernels::AmxEmulated;
    if (!fast_paths_) {
      why = "the reference CPU backend computes in FP32 only";
    } else if (p == Precision::I8) {
      if (int8_emulated || cpu::avx512_vnni_available(&why)) return true;
      why = "the CPU's INT8 convolutions need AVX512-VNNI: " + why + " (AMX-INT8 tiles are used where present too)";
    } else if (p == Precision::F16) {
      why = "the CPU backend has no FP16 convolutions (its 16-bit type is BF16, on AVX512_BF16; fp16 runs on "
            "--device cuda)";
    } else if (emulated || cpu::avx512_bf16_available(&why)) {
      return true;
    } else {
      why = "the CPU's BF16 convolutions need AVX512_BF16: " + why + " (AMX-BF16 tiles are used where present too)";
    }
    if (why_not != nullptr) *why_not = why;
    return false;
  }
  // The 3 x 3 pad-1 convolutions run by Winograd; their transformed weights U are made with the
  // prepared weights.
  int64_t prepared_conv_transform_elements(const Shape& weight, int pad, DType dtype) const override {
    if (dtype != DType::BF16 || !supports_precision(Precision::BF16, nullptr) || !op::winograd_3x3(weight, pad))
      return 0;
    return cpu::winograd_weight_elements(bf16_kernels_, weight);
  }
  DType prepared_conv_dtype(const Shape& weight, int pad, bool transposed, DType half) const override {
    if (half != DType::BF16 || transposed || !fast_paths_ || !op::winograd_3x3(weight, pad)) return half;
    return cpu::bf16_winograd_pays(bf16_kernels_, bf16_dot_outpaces_fma_, weight) ? half : DType::F32;
  }
  void prepare_conv_weights(const Ref& w, const Ref* bias, const BatchNormRefs* bn, const TensorRef& prepared,
                            Ref& bias_out, const TensorRef& transformed, const Ref* weight_scale) override {
    const char* op = "CpuBackend::prepare_conv_weights";
    if (prepared.dtype == DType::I8) {
      require_precision(Precision::I8);
      PS_CHECK(transformed.data == nullptr, "{}: no transformed form of INT8 weights", op);
      prepare_int8(op, w, bias, bn, /*transposed=*/false, prepared, bias_out, weight_scale);
      return;
    }
    if (prepared.dtype == DType::F32) {  // FP32 arithmetic on 16-bit activations (prepared_conv_dtype)
      PS_CHECK(transformed.data == nullptr, "{}: no transformed form of FP32 weights", op);
      Ref folded = prepared.f32(op);
      fold_batchnorm(op, w, bias, bn, folded, bias_out);
      return;
    }
    require_precision(precision_of(prepared.dtype));
    HRef w16 = prepared.bits16(op);
    cpu::prepare_conv_weights(w, bias, bn, precision_of(prepared.dtype), w16, bias_out);
    if (transformed.data == nullptr) return;
    require_shape(op, "transformed", transformed.bits16(op), {cpu::winograd_weight_elements(bf16_kernels_, w.shape)});
    cpu::winograd_transform_weights(bf16_kernels_, w16, w.shape, static_cast<uint16_t*>(transformed.data));
  }
  void prepare_conv_transpose_weights(const Ref& w, const Ref* bias, const TensorRef& prepared, Ref& bias_out,
                                      const Ref* weight_scale) override {
    if (prepared.dtype == DType::I8) {
      require_precision(Precision::I8);
      prepare_int8("CpuBackend::prepare_conv_transpose_weights", w, bias, nullptr, /*transposed=*/true, prepared,
                   bias_out, weight_scale);
      return;
    }
    require_precision(precision_of(prepared.dtype));
    HRef w16 = prepared.bits16("CpuBackend::prepare_conv_transpose_weights");
    cpu::prepare_conv_transpose_weights(w, bias, precision_of(prepared.dtype), w16, bias_out);
  }
  void conv2d_prepared_forward(const TensorRef& x, const TensorRef& prepared, const TensorRef& transformed,
                               const Ref& bias_out, const Shape& weight, int pad, bool relu, const TensorRef& y,
                               const Ref* weight_scale, Int8Input input) override {
    const char* op = "CpuBackend::conv2d_prepared_forward";
    if (prepared.dtype == DType::I8) {
      require_precision(Precision::I8);
      const cpu::Int8ConvWeights& direct = int8_weights(op, prepared, bias_out, weight_scale, weight);
      // The Winograd domain where the preparation made that form (cpu::int8_winograd_runs) and the
      // calibration gave its input scales: cpu::int8_forward_in_winograd, read from what was prepared.
      const auto winograd = int8_winograd_prepared_.find(prepared.data);
      if (winograd != int8_winograd_prepared_.end() && op::winograd_3x3(weight, pad) && input.has_winograd()) {
        cpu::int8_winograd_forward(int8_kernels_, int8_activation(x), input.winograd.data(), winograd->second, relu,
                                   int8_activation(y), int8_winograd_workspace_);
        return;
      }
      cpu::int8_conv2d_forward(int8_kernels_, int8_activation(x), input.scale, input.non_negative, direct, pad, relu,
                               int8_activation(y), int8_workspace_);
      return;
    }
    if (prepared.dtype == DType::F32) {
      if (weight.size() == 4 && weight[2] == 1 && pad == 0) {  // the head of the INT8 forward
        PS_CHECK(prepared.shape == weight, "{}: prepared must be {}, got {}", op, shape_str(weight),
                 shape_str(prepared.shape));
        cpu::pointwise_conv_forward(op, x, prepared.f32(op), bias_out, relu, y);
        return;
      }
      fp32_conv3x3_on_activations(op, x, prepared.f32(op), bias_out, weight, pad, relu, y);
      return;
    }
    const Precision p = precision_of(prepared.dtype);
    require_precision(p);
    const HRef w16 = prepared.bits16(op);
    if (op::winograd_3x3(weight, pad)) {  // the U-Net's: Winograd F(2x2, 3x3)
      if (transformed.data != nullptr)
        require_shape(op, "transformed", transformed.bits16(op), {cpu::winograd_weight_elements(bf16_kernels_, weight)});
      cpu::conv3x3_winograd_forward(bf16_kernels_, half_input(x, p), w16, static_cast<uint16_t*>(transformed.data),
                                    bias_out, weight, relu, y, bf16_winograd_);
    } else {
      cpu::conv2d_forward(bf16_kernels_, half_input(x, p), w16, bias_out, weight, pad, relu, y);
    }
  }
  void conv_transpose2d_prepared_forward(const TensorRef& x, const TensorRef& prepared, const Ref& bias_out,
                                         const Shape& weight, const TensorRef& y, const Ref* weight_scale,
                                         Int8Input input) override {
    if (prepared.dtype == DType::I8) {
      require_precision(Precision::I8);
      const char* op = "CpuBackend::conv_transpose2d_prepared_forward";
      cpu::int8_conv_transpose2d_forward(int8_kernels_, int8_activation(x), input.scale, input.non_negative,
                                         int8_weights(op, prepared, bias_out, weight_scale, weight),
                                         int8_activation(y), int8_workspace_);
      return;
    }
    const Precision p = precision_of(prepared.dtype);
    require_precision(p);
    cpu::conv_transpose2d_forward(bf16_kernels_, half_input(x, p), prepared.bits16("CpuBackend::conv_transpose2d_prepared_forward"),
                                  bias_out, weight, y);
  }
  void convert(const Ref& x, const TensorRef& y) override {
    const Precision p = precision_of(y.dtype);
    require_precision(p);
    HRef h = y.bits16("CpuBackend::convert");
    cpu::to_half(x, p, h);
  }

  void* allocate(size_t bytes) override {
    void* p = allocate_host(bytes);
    PS_CHECK(p, "out of host memory allocating {} bytes", bytes);
    return p;
  }
  void deallocate(void* p) noexcept override { std::free(p); }
  void upload(void* dst, const void* src, size_t bytes) override { std::memcpy(dst, src, bytes); }
  void download(void* dst, const void* src, size_t bytes) override { std::memcpy(dst, src, bytes); }
  void fill_zero(void* dst, size_t bytes) override { std::memset(dst, 0, bytes); }

  void pfn_forward(const Ref& points, const Ref& weight, BatchNormRefs& bn, bool training,
                   const IRef& live_rows, IRef& argmax, Ref& out_rows) override {
    const char* op = "pfn_forward";
    const bool cut = live_rows_data(op, live_rows) != nullptr;
    PS_CHECK(!training || !cut, "{}: live_rows in training (the batch statistics take every row)", op);
    // Evaluation with live rows: the leading live pillars only.
    const int64_t live = cut ? live_row_count(op, live_rows, out_rows.dim(0)) : 0;
    const Ref in = cut ? row_slice(op, points, 0, live) : points;
    Ref out = cut ? row_slice(op, out_rows, 0, live) : out_rows;
    if (fast_paths_) {
      if (training) {
        cpu::pfn_forward_train(points, weight, bn, argmax, out);
      } else {
        cpu::pfn_forward_eval(in, weight, bn, out);
      }
      return;
    }
    Tensor<float> y = view(out), mean = view(bn.running_mean), var = view(bn.running_var);
    if (training) {
      host::PfnSaved<float> saved{bn_saved(bn), view(argmax)};
      int64_t counted = 0;  // the model keeps num_batches_tracked
      host::pfn_forward_train(view(points), view(weight), view(bn.gamma), view(bn.beta),
                              bn_options(bn), mean, var, counted, y, saved);
    } else {
      host::pfn_forward_eval(view(in), view(weight), view(bn.gamma), view(bn.beta), mean, var,
                             bn_options(bn), y);
    }
  }
  void pfn_backward(const Ref& points, const Ref& weight, const BatchNormRefs& bn,
                    const IRef& argmax, const Ref& dout, Ref& dweight, Ref& dgamma, Ref& dbeta) override {
    if (fast_paths_) {
      cpu::pfn_backward(points, weight, bn, argmax, dout, dweight, dgamma, dbeta);
      return;
    }
    const host::PfnSaved<float> saved{bn_saved(bn), view(argmax)};
    Tensor<float> d_points, dw = view(dweight), dg = view(dgamma), db = view(dbeta);
    host::pfn_backward(view(dout), view(points), view(weight), view(bn.gamma), saved, d_points, dw, dg,
                       db, static_cast<float*>(nullptr), bn.replicas);
  }

  void scatter_forward(const Ref& features, const IRef& cells, int channel0, const TensorRef& canvas_ref) override {
    if (is_float16(canvas_ref.dtype)) {
      const Precision p = precision_of(canvas_ref.dtype);
      require_precision(p);
      HRef canvas = canvas_ref.bits16("CpuBackend::scatter_forward");
      cpu::scatter_half(features, cells, channel0, p, canvas);
      return;
    }
    Ref canvas = canvas_ref.f32("CpuBackend::scatter_forward");
    const int64_t B = canvas.dim(0), Cc = canvas.dim(1), H = canvas.dim(2), W = canvas.dim(3), C = features.dim(1);
    PS_CHECK(channel0 >= 0 && channel0 + C <= Cc, "scatter: channels [{}, {}) outside the canvas's {}", channel0,
             channel0 + C, Cc);
    if (C == Cc) {  // the canvas is the pillar stream alone
      Tensor<float> out = view(canvas);
      host::scatter_forward(view(features), view(cells), B, H, W, out);
      return;
    }
    Tensor<float> part;
    host::scatter_forward(view(features), view(cells), B, H, W, part);
    move_channels(Ref{part.data(), part.shape()}, channel0, canvas, /*into_y=*/true);
  }
  void scatter_backward(const Ref& dcanvas, const IRef& cells, int channel0, Ref& dfeatures) override {
    const int64_t B = dcanvas.dim(0), H = dcanvas.dim(2), W = dcanvas.dim(3), C = dfeatures.dim(1);
    Tensor<float> df = view(dfeatures);
    if (C == dcanvas.dim(1)) {
      host::scatter_backward(view(dcanvas), view(cells), df);
      return;
    }
    Tensor<float> part({B, C, H, W});
    Ref part_ref{part.data(), part.shape()};
    extract_channels(dcanvas, channel0, part_ref);
    host::scatter_backward(part, view(cells), df);
  }
  void copy_channels(const TensorRef& x, int channel0, const TensorRef& y) override {
    const char* op = "CpuBackend::copy_channels";
    PS_CHECK(x.dtype == y.dtype, "{}: x is {} but y is {}", op, dtype_name(x.dtype), dtype_name(y.dtype));
    if (is_float16(y.dtype)) {
      HRef out = y.bits16(op);
      cpu::copy_channels_half(x.bits16(op), channel0, out);
      return;
    }
    Ref out = y.f32(op);
    move_channels(x.f32(op), channel0, out, /*into_y=*/true);
  }
  void extract_channels(const Ref& y, int channel0, Ref& x) override {
    move_channels(x, channel0, y, /*into_y=*/false);
  }

  void conv2d_forward(const Ref& x, const Ref& w, const Ref* bias, int pad, Ref& y) override {
    Tensor<float> out = view(y);
    if (winograd_applies(w, pad)) {
      host::conv3x3_winograd_forward(view(x), view(w), {nullptr, bias ? bias->data : nullptr, false}, out,
                                     winograd_);
      return;
    }
    Tensor<float> b;
    if (bias) b = view(*bias);
    host::conv2d_forward(view(x), view(w), bias ? &b : nullptr, pad, out);
  }
  void conv2d_backward(const Ref& x, const Ref& w, const Ref& dy, int pad, Ref* dx, Ref& dw, Ref* dbias,
                       DType compute = DType::F32) override {
    require_fp32_training(compute);
    Tensor<float> gx, gw = view(dw), gb;
    if (dbias) gb = view(*dbias);
    if (dx) gx = view(*dx);
    if (!winograd_applies(w, pad)) {
      host::conv2d_backward(view(x), view(w), view(dy), pad, dx ? &gx : nullptr, &gw, dbias ? &gb : nullptr);
      return;
    }
    if (dbias) host::conv2d_backward(view(x), view(w), view(dy), pad, nullptr, nullptr, &gb);
    host::conv3x3_winograd_weight_gradient(view(x), view(dy), gw, winograd_);
    if (dx) host::conv3x3_winograd_input_gradient(view(dy), view(w), gx, winograd_);
  }
  // BatchNorm with running statistics folded into the epilogue of the convolution:
  //   y = relu(conv(x, w) * s + (bias - mean) * s + beta),  s = gamma / sqrt(var + eps),
  // computed in double as host::batchnorm_relu_forward_eval does.
  void conv2d_bn_relu_eval(const Ref& x, const Ref& w, const Ref* bias, const BatchNormRefs& bn, int pad,
                           Ref& y) override {
    if (!winograd_applies(w, pad)) {
      Backend::conv2d_bn_relu_eval(x, w, bias, bn, pad, y);
      return;
    }
    const int64_t O = w.dim(0);
    PS_CHECK(bn.gamma.numel() == O && bn.beta.numel() == O && bn.running_mean.numel() == O &&
                 bn.running_var.numel() == O,
             "conv2d_bn_relu_eval: BatchNorm parameters must have the conv's {} output channels", O);
    epilogue_scale_.resize(static_cast<size_t>(O));
    epilogue_shift_.resize(static_cast<size_t>(O));
    for (int64_t o = 0; o < O; ++o) {
      const double s = bn.gamma.data[o] / std::sqrt(static_cast<double>(bn.running_var.data[o]) + bn.eps);
      const double b = bias ? bias->data[o] : 0.0;
      epilogue_scale_[static_cast<size_t>(o)] = static_cast<float>(s);
      epilogue_shift_[static_cast<size_t>(o)] = static_cast<float>((b - bn.running_mean.data[o]) * s + bn.beta.data[o]);
    }
    Tensor<float> out = view(y);
    host::conv3x3_winograd_forward(view(x), view(w), {epilogue_scale_.data(), epilogue_shift_.data(), true}, out,
                                   winograd_);
  }
  void conv_transpose2d_forward(const Ref& x, const Ref& w, const Ref* bias, Ref& y) override {
    Tensor<float> out = view(y), b;
    if (bias) b = view(*bias);
    host::conv_transpose2d_forward(view(x), view(w), bias ? &b : nullptr, out);
  }
  void conv_transpose2d_backward(const Ref& x, const Ref& w, const Ref& dy, Ref& dx, Ref& dw, Ref* dbias,
                                 DType compute = DType::F32) override {
    require_fp32_training(compute);
    // host/ rearranges dy in place; this backend's own copy keeps the caller's dy intact.
    transpose_dy_.assign(dy.data, dy.data + dy.numel());
    Tensor<float> gx = view(dx), gw = view(dw), gb, scratch_dy = Tensor<float>::view(transpose_dy_.data(), dy.shape);
    if (dbias) gb = view(*dbias);
    host::conv_transpose2d_backward_overwriting_dy(view(x), view(w), scratch_dy, &gx, &gw,
                                                   dbias ? &gb : nullptr);
  }
  bool supports_synchronized_batchnorm(std::string*) const override { return true; }
  void batchnorm_relu_forward(const Ref& x, BatchNormRefs& bn, bool training, Ref& y) override {
    Tensor<float> out = view(y), mean = view(bn.running_mean), var = view(bn.running_var);
    if (training) {
      host::BatchNormSaved<float> saved = bn_saved(bn);
      int64_t counted = 0;  // the model keeps num_batches_tracked
      host::batchnorm_relu_forward_train(view(x), view(bn.gamma), view(bn.beta), bn_options(bn), mean, var, counted,
                                         out, saved);
    } else {
      host::batchnorm_relu_forward_eval(view(x), view(bn.gamma), view(bn.beta), mean, var, bn_options(bn), out);
    }
  }
  void batchnorm_relu_backward(const Ref& x, const Ref& y, const Ref& dy, const BatchNormRefs& bn, Ref& dx,
                               Ref& dgamma, Ref& dbeta) override {
    // dx may be dy (in place): host/ tells that case by the tensor object, so both are one view.
    Tensor<float> gy = view(dy), separate_gx = view(dx), gg = view(dgamma), gb = view(dbeta);
    Tensor<float>& gx = dx.data == dy.data ? gy : separate_gx;
    host::batchnorm_relu_backward(gy, view(x), view(y), view(bn.gamma), bn_saved(bn), gx, gg, gb, bn.replicas);
  }
  void maxpool2d_forward(const TensorRef& x, const TensorRef& y, IRef* argmax) override {
    const char* op = "CpuBackend::maxpool2d_forward";
    if (is_float16(x.dtype)) {
      const Precision p = precision_of(x.dtype);
      require_precision(p);
      HRef out = y.bits16(op);
      cpu::maxpool2d_half(x.bits16(op), p, out);
      return;
    }
    PS_CHECK(argmax != nullptr, "{}: an f32 max-pool writes its arg-max (none given)", op);
    Tensor<float> out = view(y.f32(op));
    Tensor<int32_t> idx = view(*argmax);
    host::maxpool2d_forward(view(x.f32(op)), out, &idx);
  }
  void maxpool2d_backward(const Ref& dy, const IRef& argmax, Ref& dx) override {
    Tensor<float> gx = view(dx);
    host::maxpool2d_backward(view(dy), view(argmax), dx.shape, gx);
  }
  void upsample_bilinear_forward(const TensorRef& x, const TensorRef& y) override {
    const char* op = "CpuBackend::upsample_bilinear_forward";
    if (is_float16(x.dtype)) {
      const Precision p = precision_of(x.dtype);
      require_precision(p);
      HRef out = y.bits16(op);
      cpu::upsample_bilinear_half(x.bits16(op), p, out);
      return;
    }
    Tensor<float> out = view(y.f32(op));
    host::upsample_bilinear_forward(view(x.f32(op)), out);
  }
  void upsample_bilinear_backward(const Ref& dy, Ref& dx) override {
    Tensor<float> gx = view(dx);
    host::upsample_bilinear_backward(view(dy), gx);
  }
  void pad_concat_forward(const TensorRef& skip, const TensorRef& up, const TensorRef& y) override {
    const char* op = "CpuBackend::pad_concat_forward";
    if (is_float16(y.dtype)) {
      HRef out = y.bits16(op);
      cpu::pad_concat_half(skip.bits16(op), up.bits16(op), out);
      return;
    }
    Tensor<float> out = view(y.f32(op));
    host::pad_concat_forward(view(skip.f32(op)), view(up.f32(op)), out);
  }
  void pad_concat_backward(const Ref& dy, Ref& dskip, Ref& dup) override {
    Tensor<float> gs = view(dskip), gu = view(dup);
    host::pad_concat_backward(view(dy), dskip.shape, dup.shape, &gs, &gu);
  }
  void add_inplace(Ref& a, const Ref& b) override {
    PS_CHECK(a.shape == b.shape, "add_inplace: shapes {} and {} differ", shape_str(a.shape), shape_str(b.shape));
    float* pa = a.data;
    const float* pb = b.data;
    parallel_for(a.numel(), [&](int64_t i) { pa[i] += pb[i]; });
  }

  void softmax(const Ref& logits, Ref& probs) override {
    Tensor<float> p = view(probs);
    host::softmax_channels(view(logits), p);
  }
  void argmax(const Ref& logits, LRef& labels) override {
    Tensor<uint8_t> l = view(labels);
    host::argmax_class_ids(view(logits), l);
  }
  void mirror_add(const Ref& x, bool mirror_y, bool mirror_x, Ref& sum) override {
    Tensor<float> s = view(sum);
    host::mirror_add(view(x), mirror_y, mirror_x, s);
  }
  void argmax_positive(const Ref& values, LRef& labels) override {
    Tensor<uint8_t> l = view(labels);
    host::argmax_positive_class_ids(view(values), l);
  }
  double loss(const LossSpec& spec, const Ref& logits, const LRef& labels, const Ref& coefficients,
              Ref& dlogits) override {
    PS_CHECK(coefficients.numel() == 13, "loss: 13 class coefficients expected, got {}", coefficients.numel());
    double c[13];
    for (int i = 0; i < 13; ++i) c[i] = coefficients.data[i];
    Tensor<float> d = view(dlogits);
    const std::span<const double> weights(c, 13);
    if (spec.kind == LossKind::Bce) return host::bce_loss(view(logits), view(labels), weights, &d);
    const double ce = host::cross_entropy_loss(view(logits), view(labels), weights, &d);
    if (spec.kind == LossKind::CrossEntropy) return ce;
    Tensor<float> d_lovasz;
    const double lovasz = host::lovasz_softmax_loss(view(logits), view(labels), &d_lovasz);
    const float w = spec.lovasz_weight;
    for (int64_t i = 0; i < d.numel(); ++i) d[i] += w * d_lovasz[i];
    return ce + static_cast<double>(w) * lovasz;
  }

  double sum_of_squares(const Ref& x) override {
    const std::span<float> s(x.data, static_cast<size_t>(x.numel()));
    const std::span<float> all[] = {s};
    const double norm = host::grad_norm<float>(std::span<const std::span<float>>(all));
    return norm * norm;
  }
  void scale(Ref& x, float factor) override {
    float* p = x.data;
    parallel_for(x.numel(), [&](int64_t i) { p[i] *= factor; });
  }
  void adam_step(Ref& param, const Ref& grad, Ref& m, Ref& v, int64_t step, const AdamOptions& options) override {
    const size_t n = static_cast<size_t>(param.numel());
    host::adam_step<float>(std::span<float>(param.data, n), std::span<const float>(grad.data, n),
                           std::span<float>(m.data, n), std::span<float>(v.data, n), step, options);
  }

  // ---- input preparation ----

  void pad_points(const IRef& num_points, Ref& points) override {
    PS_CHECK(num_points.numel() == 1, "pad_points: num_points must be (1), got {}", shape_str(num_points.shape));
    Tensor<float> rows = view(points);
    host::pad_points(num_points.data[0], rows);
  }
  int64_t pillar_gather(const Ref& points, const GridSpec& grid, int max_pillars, IRef& cell, IRef& point_index,
                        IRef& count, IRef& num_pillars) override {
    const int64_t rows = cell.shape.size() == 2 ? cell.dim(0) : -1;
    PS_CHECK(rows >= 0 && cell.shape == (Shape{rows, 2}) && point_index.shape.size() == 2 &&
                 point_index.dim(0) == rows && count.shape == (Shape{rows}) && num_pillars.numel() == 1,
             "pillar_gather: expected cell (R, 2), point_index (R, N), count (R) and num_pillars (1), got {}, {}, "
             "{} and {}",
             shape_str(cell.shape), shape_str(point_index.shape), shape_str(count.shape),
             shape_str(num_pillars.shape));
    const host::PillarConfig config{static_cast<int>(point_index.dim(1)), max_pillars};
    const int64_t kept = host::pillar_gather(as_points(points), grid, config, host::SampleMode::Inference, nullptr,
                                             pillar_workspace_,
                                             host::PillarRows{cell.data, point_index.data, count.data, rows});
    num_pillars.data[0] = static_cast<int32_t>(kept);
    return kept;
  }
  void decorate_points(const Ref& points, const GridSpec& grid, const IRef& cell,
                       const IRef& point_index, const IRef& count, const IRef& live_rows,
                       Ref& out) override {
    const char* op = "decorate_points";
    if (live_rows_data(op, live_rows) != nullptr) {
      const int64_t live = live_row_count(op, live_rows, count.dim(0));
      Ref live_out = row_slice(op, out, 0, live);
      decorate_points(points, grid, row_slice(op, cell, 0, live),
                      row_slice(op, point_index, 0, live), row_slice(op, count, 0, live), IRef{},
                      live_out);
      return;
    }
    host::Pillars pillars{view(cell), view(point_index), view(count)};
    Tensor<float> decorated = view(out);
    host::decorate_points(as_points(points), pillars, grid, decorated);
  }
  void batch_cells(const IRef& cell, int sample, IRef& cells) override {
    Tensor<int32_t> out = view(cells);
    host::batch_cells(view(cell), sample, out);
  }
  void observability_2d(const Ref& points, const Eigen::Vector3d& origin, const GridSpec& grid, URef& transmissions,
                        URef& detections) override {
    host::ObservabilityCounts counts{view(transmissions), view(detections)};
    host::observability_2d(as_points(points), origin, grid, observability_workspace_, counts);
  }
  void observability_input(const URef& transmissions, const URef& detections, Ref& out) override {
    Tensor<float> input = view(out);
    host::observability_input(view(transmissions), view(detections), input);
  }
  void occupancy_3d(const Ref& points, const Eigen::Vector3d& origin, const GridSpec& grid,
                    Ref& probability) override {
    const Shape expected{grid.layers(), grid.height(), grid.width()};
    PS_CHECK(probability.shape == expected, "occupancy_3d: probability must be {}, got {}", shape_str(expected),
             shape_str(probability.shape));
    Tensor<float> out = view(probability);
    out = host::occupancy_probability(host::occupancy_counts_3d(as_points(points), origin, grid));
  }
  void grid_map_features(const Ref& points, const GridSpec& grid, const URef& detections, const URef& transmissions,
                         Ref& out) override {
    const Shape expected{host::kGridMapLayers, grid.height(), grid.width()};
    PS_CHECK(out.shape == expected, "grid_map_features: out must be {}, got {}", shape_str(expected),
             shape_str(out.shape));
    Tensor<float> layers = view(out);
    layers = host::grid_map_features(as_points(points), view(detections), view(transmissions), grid);
  }
  void mask_unobserved(const URef& transmissions, const URef& detections, LRef& labels, Ref* probabilities) override {
    Tensor<uint8_t> masked = view(labels);
    if (probabilities == nullptr) {
      host::mask_unobserved(view(transmissions), view(detections), masked, nullptr);
      return;
    }
    Tensor<float> probs = view(*probabilities);
    host::mask_unobserved(view(transmissions), view(detections), masked, &probs);
  }

 private:
  // The Winograd fast path covers the U-Net's 3x3 / pad 1 convolutions (op::winograd_3x3).
  bool winograd_applies(const Ref& w, int pad) const { return fast_paths_ && op::winograd_3x3(w.shape, pad); }

  // FP32 prepared weights (prepared_conv_dtype): w (O, I, k, k) with the eval BatchNorm folded in
  // (scale gamma / sqrt(var + eps) and shift in double, as conv2d_bn_relu_eval computes them) ->
  // folded (O, I, k, k), bias_out (O).
  static void fold_batchnorm(const char* op, const Ref& w, const Ref* bias, const BatchNormRefs* bn, Ref& folded,
                             Ref& bias_out) {
    require_rank(op, "w", w, 4);
    require_shape(op, "prepared", folded, w.shape);
    const int64_t out = w.dim(0), k = w.numel() / out;
    require_shape(op, "bias_out", bias_out, {out});
    for (int64_t o = 0; o < out; ++o) {
      double scale = 1.0, shift = bias != nullptr ? bias->data[o] : 0.0;
      if (bn != nullptr) {
        scale = bn->gamma.data[o] / std::sqrt(static_cast<double>(bn->running_var.data[o]) + bn->eps);
        shift = (shift - bn->running_mean.data[o]) * scale + bn->beta.data[o];
      }
      for (int64_t j = 0; j < k; ++j) folded.data[o * k + j] = static_cast<float>(w.data[o * k + j] * scale);
      bias_out.data[o] = static_cast<float>(shift);
    }
  }
  // A 3 x 3 pad-1 convolution in FP32 (Winograd F(4x4, 3x3)) on x and y both FP32 or both BF16
  // (widened as read, rounded as written, in the transforms: no converted copy).
  void fp32_conv3x3_on_activations(const char* op, const TensorRef& x, const Ref& w, const Ref& bias_out,
                                   const Shape& weight, int pad, bool relu, const TensorRef& y) {
    PS_CHECK(op::winograd_3x3(weight, pad) && w.shape == weight,
             "{}: FP32 prepared weights run the 3 x 3 pad-1 and the 1 x 1 convolutions only, got weight {} pad {}", op,
             shape_str(weight), pad);
    PS_CHECK(x.dtype == y.dtype && (x.dtype == DType::F32 || x.dtype == DType::BF16),
             "{}: FP32 arithmetic takes x and y both f32 or both bf16, got {} and {}", op, dtype_name(x.dtype),
             dtype_name(y.dtype));
    const host::ConvEpilogue epilogue{nullptr, bias_out.data, relu};
    if (x.dtype == DType::F32) {
      Tensor<float> out = view(y.f32(op));
      host::conv3x3_winograd_forward(view(x.f32(op)), view(w), epilogue, out, winograd_);
      return;
    }
    Tensor<uint16_t> out = view(y.bits16(op));
    host::conv3x3_winograd_forward(view(x.bits16(op)), view(w), epilogue, out, winograd_);
  }

  void require_fp32_training(DType compute) const {
    PS_CHECK(compute == DType::F32, "backend {} trains in fp32 only ({} training runs on --device cuda)", name(),
             dtype_name(compute));
  }
  // x as BF16: itself, or rounded from FP32 into staging_.
  HRef half_input(const TensorRef& x, Precision p) {
    if (is_float16(x.dtype)) return {static_cast<uint16_t*>(x.data), x.shape};
    staging_.resize(static_cast<size_t>(x.numel()));
    HRef h{staging_.data(), x.shape};
    cpu::to_half(Ref{static_cast<float*>(x.data), x.shape}, p, h);
    return h;
  }

  // INT8: the weights w (with the eval BatchNorm folded in, as the CUDA backend folds them: scale
  // gamma / sqrt(var + eps) in FP32, w' = w scale, b' = scale bias + beta - scale mean) quantized
  // and packed for this backend's kernels, kept here by the address of the graph's prepared
  // tensor (the graph prepares every layer again when its memory or the parameters change; a
  // preparation after a forward begins a new set); the prepared tensor gets the int8 values in
  // the CUDA backend's tap-major layout, weight_scale and bias_out the scales and folded bias.
  void prepare_int8(const char* op, const Ref& w, const Ref* bias, const BatchNormRefs* bn, bool transposed,
                    const TensorRef& prepared, Ref& bias_out, const Ref* weight_scale) {
    PS_CHECK(weight_scale != nullptr, "{}: INT8 weights need their weight_scale tensor", op);
    require_rank(op, "w", w, 4);
    const int64_t out = transposed ? w.dim(1) : w.dim(0), columns = transposed ? 4 * out : out;
    require_shape(op, "prepared", prepared.i8(op), pillarseg::op::half16_conv_weights(w.shape, transposed));
    require_shape(op, "bias_out", bias_out, {columns});
    require_shape(op, "weight_scale", *weight_scale, {columns});
    if (int8_forward_ran_) int8_prepared_.clear(), int8_winograd_prepared_.clear(), int8_forward_ran_ = false;
    int8_folded_.assign(w.data, w.data + w.numel());
    int8_bias_.assign(static_cast<size_t>(out), 0.0f);
    const int64_t k = transposed ? 0 : w.numel() / out;
    for (int64_t o = 0; o < out; ++o) {
      float scale = 1.0f, shift = 0.0f;
      if (bn != nullptr) {
        scale = bn->gamma.data[o] / std::sqrt(bn->running_var.data[o] + bn->eps);
        shift = bn->beta.data[o] - scale * bn->running_mean.data[o];
        for (int64_t j = 0; j < k; ++j) int8_folded_[static_cast<size_t>(o * k + j)] *= scale;
      }
      int8_bias_[static_cast<size_t>(o)] = scale * (bias != nullptr ? bias->data[o] : 0.0f) + shift;
    }
    const Ref folded{int8_folded_.data(), w.shape}, folded_bias{int8_bias_.data(), {out}};
    cpu::Int8ConvWeights& prepared_weights = int8_prepared_[prepared.data];
    if (transposed) {
      cpu::prepare_int8_conv_transpose(int8_kernels_, folded, folded_bias, prepared_weights);
    } else {
      cpu::prepare_int8_conv(int8_kernels_, folded, folded_bias, prepared_weights);
    }
    // And the Winograd-domain form where this CPU runs it (used when the input has its scales).
    if (!transposed && cpu::int8_winograd_runs(int8_kernels_, w.shape, cpu::int8_winograd_rule())) {
      cpu::prepare_int8_winograd(folded, folded_bias, int8_winograd_prepared_[prepared.data]);
    } else {
      int8_winograd_prepared_.erase(prepared.data);
    }
    // The tap-major int8 values (the CUDA layout: column n, K index t Ip + c), scales and bias.
    auto* q = static_cast<int8_t*>(prepared.data);
    const int64_t kp = prepared.dim(1), in = transposed ? w.dim(0) : w.dim(1);
    const int64_t taps = transposed ? 1 : w.dim(2) * w.dim(3), padded = kp / taps;
    std::fill(q, q + prepared.numel(), int8_t{0});
    for (int64_t n = 0; n < columns; ++n) {
      for (int64_t t = 0; t < taps; ++t)
        for (int64_t c = 0; c < in; ++c)
          q[n * kp + t * padded + c] =
              transposed ? prepared_weights.q[static_cast<size_t>((c * out + n / 4) * 4 + n % 4)]
                         : prepared_weights.q[static_cast<size_t>((n * in + c) * taps + t)];
      weight_scale->data[n] = prepared_weights.scale[static_cast<size_t>(transposed ? n / 4 : n)];
      bias_out.data[n] = prepared_weights.bias[static_cast<size_t>(n)];
    }
  }
  const cpu::Int8ConvWeights& int8_weights(const char* op, const TensorRef& prepared, const Ref& bias_out,
                                           const Ref* weight_scale, const Shape& weight) {
    PS_CHECK(weight_scale != nullptr && bias_out.data != nullptr, "{}: INT8 needs its weight scales and bias", op);
    const auto it = int8_prepared_.find(prepared.data);
    PS_CHECK(it != int8_prepared_.end() && it->second.weight == weight,
             "{}: these INT8 weights {} were not prepared on this backend (prepare_conv_weights first)", op,
             shape_str(weight));
    int8_forward_ran_ = true;
    return it->second;
  }
  static ActRef int8_activation(const TensorRef& t) {
    PS_CHECK(t.dtype == DType::F32 || t.dtype == DType::BF16, "CpuBackend: INT8 convolutions take f32 or bf16 "
             "activations, got {}", dtype_name(t.dtype));
    return ActRef{t.data, t.shape, t.dtype == DType::BF16};
  }

  bool fast_paths_;
  cpu::Bf16Kernels bf16_kernels_;
  cpu::Int8Kernels int8_kernels_;
  // Whether the BF16 3 x 3 convolutions pay at every shape without AMX (cpu::bf16_winograd_pays):
  // this CPU's answer natively, the Intel rule on the instruction models.
  bool bf16_dot_outpaces_fma_;
  std::map<const void*, cpu::Int8ConvWeights> int8_prepared_;
  std::map<const void*, cpu::Int8WinogradWeights> int8_winograd_prepared_;  // by the same address
  bool int8_forward_ran_ = false;
  std::vector<float> int8_folded_, int8_bias_;
  cpu::Int8ConvWorkspace int8_workspace_;
  cpu::Int8WinogradWorkspace int8_winograd_workspace_;
  cpu::Bf16WinogradWorkspace bf16_winograd_;  // the BF16 3 x 3 convolutions' scratch
  std::vector<uint16_t> staging_;
  std::vector<float> transpose_dy_;  // conv_transpose2d_backward's copy of dy
  host::WinogradWorkspace winograd_;
  std::vector<float> epilogue_scale_, epilogue_shift_;
  host::PillarWorkspace pillar_workspace_;
  host::ObservabilityWorkspace observability_workspace_;

  // Copies x (B, Cx, H, W) to or from channels [channel0, channel0 + Cx) of y (B, Cy, H, W).
  static void move_channels(const Ref& x, int channel0, const Ref& y, bool into_y) {
    PS_CHECK(x.shape.size() == 4 && y.shape.size() == 4 && x.dim(0) == y.dim(0) && x.dim(2) == y.dim(2) &&
                 x.dim(3) == y.dim(3) && channel0 >= 0 && channel0 + x.dim(1) <= y.dim(1),
             "channel copy: {} does not fit at channel {} of {}", shape_str(x.shape), channel0, shape_str(y.shape));
    const int64_t B = x.dim(0), Cx = x.dim(1), Cy = y.dim(1), plane = x.dim(2) * x.dim(3);
    for (int64_t b = 0; b < B; ++b) {
      float* ys = y.data + (b * Cy + channel0) * plane;
      float* xs = x.data + b * Cx * plane;
      const size_t bytes = static_cast<size_t>(Cx * plane) * sizeof(float);
      if (into_y) std::memcpy(ys, xs, bytes);
      else std::memcpy(xs, ys, bytes);
    }
  }
};

}  // namespace

std::unique_ptr<Backend> make_cpu_backend() {
  return std::make_unique<CpuBackend>(/*fast_paths=*/true, cpu::native_bf16_kernels(), cpu::native_int8_kernels(),
                                      cpu::bf16_dot_outpaces_fma());
}
std::unique_ptr<Backend> make_cpu_reference_backend() {
  return std::make_unique<CpuBackend>(/*fast_paths=*/false, cpu::Bf16Kernels::Avx512, cpu::Int8Kernels::Vnni);
}
std::unique_ptr<Backend> make_cpu_backend_emulated_bf16(bool amx) {
  return std::make_unique<CpuBackend>(/*fast_paths=*/true,
                                      amx ? cpu::Bf16Kernels::AmxEmulated : cpu::Bf16Kernels::Emulated,
                                      amx ? cpu::Int8Kernels::AmxEmulated : cpu::Int8Kernels::Emulated);
}

}  // namespace pillarseg
